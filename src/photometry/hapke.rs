//! Hapke IMSA with opposition effect and macroscopic roughness (docs/photometry.md):
//!
//! r(i,e,g) = (w/4π) · μ0e/(μ0e+μe) · [(1+B(g))·P(g) + H(μ0e)·H(μe) − 1] · S(i,e,ψ)   [sr⁻¹]
//!
//! r is the bidirectional reflectance (radiance over irradiance at normal incidence), i.e. what
//! M3 radiance divided by the solar irradiance gives; I/F = π·r.

use super::{Albedo, AlbedoCurve, Cosines, Dual, ReflectanceCos, ReflectanceModel};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Single-particle phase function P(g).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase", deny_unknown_fields)]
pub enum PhaseFunction {
    /// Hapke 2012 two-term Henyey–Greenstein: P = (1+c)/2·HG(b) + (1−c)/2·HG(−b),
    /// HG(b) = (1−b²)/(1 − 2b·cos g + b²)^1.5. b > 0 with c > 0 is back-scattering.
    Hg2012 { b: f64, c: f64 },
    /// The ISIS/ASP convention: P = (1−c)·HG(−b) + c·HG(b), so c_ISIS = (1 + c_2012)/2.
    HgIsis { b: f64, c: f64 },
    /// Two-term Legendre polynomial in the scattering angle θ = π − g:
    /// P = 1 + b·cos θ + c·(3cos²θ − 1)/2 (Hapke 1981).
    Legendre { b: f64, c: f64 },
}

impl PhaseFunction {
    /// P(g) from cos g.
    pub fn eval(&self, cos_g: f64) -> f64 {
        // t^1.5 as t·√t: the same value to rounding, several times cheaper than powf.
        let hg = |b: f64| {
            let t = 1.0 - 2.0 * b * cos_g + b * b;
            (1.0 - b * b) / (t * t.sqrt())
        };
        match *self {
            PhaseFunction::Hg2012 { b, c } => 0.5 * (1.0 + c) * hg(b) + 0.5 * (1.0 - c) * hg(-b),
            PhaseFunction::HgIsis { b, c } => (1.0 - c) * hg(-b) + c * hg(b),
            PhaseFunction::Legendre { b, c } => {
                let ct = -cos_g;
                1.0 + b * ct + c * (1.5 * ct * ct - 0.5)
            }
        }
    }
}

/// Chandrasekhar H-function approximation used for multiple scattering.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "UPPERCASE")]
pub enum HFunction {
    /// Hapke 1981: H(x) = (1+2x)/(1+2γx), γ = √(1−w).
    H81,
    /// Hapke 2002: H(x) = 1/{1 − w·x·[r0 + (1−2r0·x)/2 · ln((1+x)/x)]}, r0 = (1−γ)/(1+γ).
    H02,
}

impl HFunction {
    /// H(x; w), differentiable in both arguments.
    pub fn eval<const N: usize>(&self, x: Dual<N>, w: Dual<N>) -> Dual<N> {
        self.eval_with_gamma(x, w, (1.0 - w).sqrt())
    }

    /// H(x; w) given γ = √(1 − w) (formed once where H is evaluated at two arguments).
    #[inline]
    fn eval_with_gamma<const N: usize>(&self, x: Dual<N>, w: Dual<N>, gamma: Dual<N>) -> Dual<N> {
        match self {
            HFunction::H81 => (1.0 + x * 2.0) / (1.0 + gamma * x * 2.0),
            HFunction::H02 => {
                if x.v <= 0.0 {
                    return Dual::constant(1.0);
                }
                let r0 = (1.0 - gamma) / (1.0 + gamma);
                let l = ((1.0 + x) / x).ln();
                1.0 / (1.0 - w * x * (r0 + (1.0 - r0 * x * 2.0) * 0.5 * l))
            }
        }
    }
}

/// Hapke IMSA parameters. The albedo ρ of the fusion is the single-scattering albedo w.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Hapke {
    pub phase: PhaseFunction,
    /// Shadow-hiding opposition amplitude B0.
    pub b0: f64,
    /// Opposition width h; B = 0 when h = 0.
    pub h: f64,
    /// Mean macroscopic slope angle θ̄ in degrees (Hapke 1984); 0 = smooth.
    pub theta_bar_deg: f64,
    pub h_function: HFunction,
}

impl Default for Hapke {
    /// The lunar set used with this method (Warell 2004 as adopted by the seed authors' group):
    /// b = 0.21, c = 0.70 (2012 convention), B0 = 3.1, h = 0.11, θ̄ = 11°, H81.
    fn default() -> Self {
        Hapke::moon()
    }
}

/// w is searched in [0, W_MAX]: r(w) is strictly increasing there.
const W_MAX: f64 = 1.0 - 1e-12;

impl Hapke {
    /// See [`Default`].
    pub fn moon() -> Self {
        Hapke {
            phase: PhaseFunction::Hg2012 { b: 0.21, c: 0.70 },
            b0: 3.1,
            h: 0.11,
            theta_bar_deg: 11.0,
            h_function: HFunction::H81,
        }
    }

    /// M(g) = (1 + B(g))·P(g). Within one scene g is often the same for every pixel, so the
    /// last value is memoised per thread (keyed on g and every parameter it depends on).
    fn phase_term(&self, cos_g: f64) -> f64 {
        use std::cell::Cell;
        type Key = (u64, u64, u64, PhaseFunction);
        thread_local! {
            static LAST: Cell<Option<(Key, f64)>> = const { Cell::new(None) };
        }
        let key: Key = (
            cos_g.to_bits(),
            self.b0.to_bits(),
            self.h.to_bits(),
            self.phase,
        );
        LAST.with(|c| match c.get() {
            Some((k, m)) if k == key => m,
            _ => {
                let m = (1.0 + self.opposition(cos_g)) * self.phase.eval(cos_g);
                c.set(Some((key, m)));
                m
            }
        })
    }

    /// B(g) = B0/(1 + tan(g/2)/h), with tan(g/2) = √((1 − cos g)/(1 + cos g)) (no inverse
    /// trigonometry: this runs once per pixel and evaluation where the geometry varies per
    /// pixel).
    pub fn opposition(&self, cos_g: f64) -> f64 {
        if self.h == 0.0 {
            return 0.0;
        }
        let c = cos_g.clamp(-1.0, 1.0);
        if c <= -1.0 {
            return 0.0; // g = π: tan(g/2) is infinite
        }
        let tan_half = ((1.0 - c) / (1.0 + c)).sqrt();
        self.b0 / (1.0 + tan_half / self.h)
    }

    /// The w-independent factors at one geometry: (μ0e, μe, S) as functions of (μ0, μ) — the
    /// Hapke 1984 roughness correction, both branches — and M = (1+B)·P.
    fn w_free<const N: usize>(
        &self,
        mu0: Dual<N>,
        mu: Dual<N>,
        cos_g: f64,
    ) -> (Dual<N>, Dual<N>, Dual<N>, f64) {
        let m = self.phase_term(cos_g);
        if self.theta_bar_deg == 0.0 {
            return (mu0, mu, Dual::constant(1.0), m);
        }
        let (mu0e, mue, s) = roughness(mu0, mu, cos_g, self.theta_bar_deg.to_radians());
        (mu0e, mue, s, m)
    }
}

/// r = w/(4π)·μ0e/(μ0e + μe)·(H(μ0e)H(μe) + M − 1)·S.
fn r_from_parts<const N: usize>(
    h: HFunction,
    w: Dual<N>,
    mu0e: Dual<N>,
    mue: Dual<N>,
    s: Dual<N>,
    m: f64,
) -> Dual<N> {
    let gamma = (1.0 - w).sqrt();
    let hh = h.eval_with_gamma(mu0e, w, gamma) * h.eval_with_gamma(mue, w, gamma);
    w * (1.0 / (4.0 * PI)) * mu0e / (mu0e + mue) * (hh + (m - 1.0)) * s
}

/// (ψ/π)·e with ψ = acos(cos ψ), skipping the arc cosine where e is exactly 0 (a near-nadir
/// view's E1, [`neg_exp`]: M3's every pixel in the i ≥ e branch), where the product is 0.
fn psi_over_pi_times<const N: usize>(cos_psi: Dual<N>, e: Dual<N>) -> Dual<N> {
    if e == Dual::constant(0.0) {
        e
    } else {
        cos_psi.acos() / PI * e
    }
}

/// sin x from cos x, with value and derivative 0 at x = 0.
fn sin_from_cos<const N: usize>(c: Dual<N>) -> Dual<N> {
    let s2 = 1.0 - c * c;
    if s2.v <= 1e-24 {
        Dual::constant(0.0)
    } else {
        s2.sqrt()
    }
}

/// Hapke 1984 E1(x), E2(x) (0 at x = 0) from cos x and sin x.
fn e1_e2<const N: usize>(cos_x: Dual<N>, sin_x: Dual<N>, cot_tb: f64) -> (Dual<N>, Dual<N>) {
    if sin_x.v == 0.0 {
        return (Dual::constant(0.0), Dual::constant(0.0));
    }
    let cot_x = cos_x / sin_x;
    (
        neg_exp(cot_x * (2.0 / PI * cot_tb)),
        neg_exp(cot_x * cot_x * (cot_tb * cot_tb / PI)),
    )
}

/// exp(−a) for a ≥ 0, returning an exact 0 (with zero derivatives) from a = 40 on
/// (e⁻⁴⁰ = 4·10⁻¹⁸). E1 and E2 only ever add to cosines, through a factor tan θ̄·sin x/(2 − E1)
/// < 1, so there they are below the rounding of the cosines they change; near-nadir views
/// (e ≲ 5° at θ̄ = 11°, every M3 pixel) then cost no exponential at all.
fn neg_exp<const N: usize>(a: Dual<N>) -> Dual<N> {
    if a.v > 40.0 {
        Dual::constant(0.0)
    } else {
        (-a).exp()
    }
}

/// tan θ̄, cot θ̄ and χ(θ̄) = 1/√(1 + π tan²θ̄), memoised per thread for the last θ̄ (one
/// model per run: the tangent and root are then computed once, not per pixel).
fn roughness_constants(tb: f64) -> (f64, f64, f64) {
    use std::cell::Cell;
    type Constants = (f64, f64, f64);
    thread_local! {
        static LAST: Cell<Option<(u64, Constants)>> = const { Cell::new(None) };
    }
    LAST.with(|c| match c.get() {
        Some((k, v)) if k == tb.to_bits() => v,
        _ => {
            let tan_tb = tb.tan();
            let v = (
                tan_tb,
                1.0 / tan_tb,
                1.0 / (1.0 + PI * tan_tb * tan_tb).sqrt(),
            );
            c.set(Some((tb.to_bits(), v)));
            v
        }
    })
}

/// The roughness correction (μ0e, μe, S) of Hapke 1984 as docs/photometry.md states it.
fn roughness<const N: usize>(
    mu0: Dual<N>,
    mu: Dual<N>,
    cos_g: f64,
    tb: f64,
) -> (Dual<N>, Dual<N>, Dual<N>) {
    let (tan_tb, cot_tb, chi) = roughness_constants(tb);
    let (sin_i, sin_e) = (sin_from_cos(mu0), sin_from_cos(mu));
    let (e1i, e2i) = e1_e2(mu0, sin_i, cot_tb);
    let (e1e, e2e) = e1_e2(mu, sin_e, cot_tb);
    let cos_psi = if sin_i.v * sin_e.v <= 0.0 {
        Dual::constant(1.0)
    } else {
        ((cos_g - mu0 * mu) / (sin_i * sin_e)).clamp(-1.0 + 1e-12, 1.0 - 1e-12)
    };
    // sin²(ψ/2).
    let half_sin2 = (1.0 - cos_psi) * 0.5;
    // f(ψ) = exp(−2 tan(ψ/2)), with tan(ψ/2) = √((1 − cos ψ)/(1 + cos ψ)) (cheaper than tan);
    // f = 0 at ψ = π.
    let f = if cos_psi.v <= -1.0 {
        Dual::constant(0.0)
    } else if cos_psi.v >= 1.0 {
        Dual::constant(1.0)
    } else {
        (((1.0 - cos_psi) / (1.0 + cos_psi)).sqrt() * -2.0).exp()
    };
    let eta =
        |c: Dual<N>, s: Dual<N>, e1: Dual<N>, e2: Dual<N>| (c + s * tan_tb * e2 / (2.0 - e1)) * chi;
    let eta_i = eta(mu0, sin_i, e1i, e2i);
    let eta_e = eta(mu, sin_e, e1e, e2e);
    if mu0.v >= mu.v {
        // i ≤ e
        let d = 2.0 - e1e - psi_over_pi_times(cos_psi, e1i);
        let mu0e = (mu0 + sin_i * tan_tb * (cos_psi * e2e + half_sin2 * e2i) / d) * chi;
        let mue = (mu + sin_e * tan_tb * (e2e - half_sin2 * e2i) / d) * chi;
        let s = (mue / eta_e) * (mu0 / eta_i) * chi / (1.0 - f + f * chi * (mu0 / eta_i));
        (mu0e, mue, s)
    } else {
        // i ≥ e
        let d = 2.0 - e1i - psi_over_pi_times(cos_psi, e1e);
        let mu0e = (mu0 + sin_i * tan_tb * (e2i - half_sin2 * e2e) / d) * chi;
        let mue = (mu + sin_e * tan_tb * (cos_psi * e2i + half_sin2 * e2e) / d) * chi;
        let s = (mue / eta_e) * (mu0 / eta_i) * chi / (1.0 - f + f * chi * (mu / eta_e));
        (mu0e, mue, s)
    }
}

/// Hapke's r(w) at fixed cosines: the w-free factors (μ0e, μe, S, M) computed once
/// ([`Hapke::w_curve`]). With H81 an evaluation is one square root and four divisions:
/// r = w·k·(H(a)H(b) + M − 1), k = a/(a + b)·S/4π,
/// H(a)H(b) = (1 + 2a)(1 + 2b)/((1 + 2γa)(1 + 2γb)), γ = √(1 − w), and
/// ∂(H(a)H(b))/∂w = H(a)H(b)·(a/(1 + 2γa) + b/(1 + 2γb))/γ.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WCurve {
    h_function: HFunction,
    /// μ0e, μe, S, M.
    a: f64,
    b: f64,
    s: f64,
    m: f64,
    /// a/(a + b)·S/4π and (1 + 2a)(1 + 2b).
    k: f64,
    n: f64,
}

impl WCurve {
    /// (r, ∂r/∂w) at w.
    pub fn eval(&self, w: f64) -> (f64, f64) {
        let (a, b, k, n, m) = (self.a, self.b, self.k, self.n, self.m);
        match self.h_function {
            HFunction::H81 => {
                let gamma = (1.0 - w).sqrt();
                let (da, db) = (1.0 + 2.0 * gamma * a, 1.0 + 2.0 * gamma * b);
                let hh = n / (da * db);
                let bracket = hh + m - 1.0;
                let dhh = hh * (a / da + b / db) / gamma;
                (w * k * bracket, k * (bracket + w * dhh))
            }
            HFunction::H02 => {
                let f = r_from_parts(
                    self.h_function,
                    Dual::<1>::var(w, 0),
                    Dual::constant(a),
                    Dual::constant(b),
                    Dual::constant(self.s),
                    m,
                );
                (f.v, f.d[0])
            }
        }
    }

    /// Newton on w with a bisection fallback; r(w) is strictly increasing (docs/photometry.md).
    /// With H81 a step is one square root and four divisions. r(w_max) is evaluated only
    /// when the iteration reaches w_max (the observation may be out of range), and the
    /// iteration stops at 10⁻¹² relative, far below any use of the albedo.
    pub fn invert(&self, observed: f64) -> Albedo {
        if observed <= 0.0 {
            return Albedo::Value(0.0);
        }
        let r = |w: f64| self.eval(w);
        let (mut lo, mut hi) = (0.0, W_MAX);
        let mut in_range = false;
        // Start from the secant through the origin and w = 0.5 (r(w)/w varies slowly in w).
        let (r_half, _) = r(0.5);
        let mut w = if r_half >= observed {
            hi = 0.5;
            in_range = true;
            observed / (2.0 * r_half)
        } else {
            lo = 0.5;
            (observed / (2.0 * r_half)).min(W_MAX)
        };
        for _ in 0..100 {
            let (f, df) = r(w);
            let err = f - observed;
            if err > 0.0 {
                hi = w;
                in_range = true;
            } else if w == W_MAX && err < 0.0 {
                // r(w_max) < I: no albedo gives the observation.
                return Albedo::OutOfRange;
            } else {
                lo = w;
            }
            if err.abs() <= 1e-12 * observed || hi - lo <= 1e-15 {
                break;
            }
            let newton = w - err / df;
            w = if df > 0.0 && newton > lo && newton < hi {
                newton
            } else if !in_range && df > 0.0 && newton >= hi {
                W_MAX
            } else {
                0.5 * (lo + hi)
            };
        }
        if !in_range && r(W_MAX).0 < observed {
            return Albedo::OutOfRange;
        }
        Albedo::Value(w)
    }
}

impl Hapke {
    /// r(w) at cosines `c` ([`WCurve`]).
    pub fn w_curve(&self, c: &Cosines) -> WCurve {
        let (mu0e, mue, s, m) =
            self.w_free(Dual::<0>::constant(c.mu0), Dual::constant(c.mu), c.cos_g);
        let (a, b, s) = (mu0e.v, mue.v, s.v);
        WCurve {
            h_function: self.h_function,
            a,
            b,
            s,
            m,
            k: a / (a + b) * s / (4.0 * PI),
            n: (1.0 + 2.0 * a) * (1.0 + 2.0 * b),
        }
    }
}

impl ReflectanceModel for Hapke {
    fn reflectance(&self, albedo: f64, c: &Cosines) -> ReflectanceCos {
        let (mu0e, mue, s, m) = self.w_free(Dual::<2>::var(c.mu0, 0), Dual::var(c.mu, 1), c.cos_g);
        let r = r_from_parts(self.h_function, Dual::constant(albedo), mu0e, mue, s, m);
        ReflectanceCos {
            r: r.v,
            dr_dmu0: r.d[0],
            dr_dmu: r.d[1],
        }
    }

    /// Newton on w with a bisection fallback on the curve of these cosines
    /// ([`WCurve::invert`]: the w-free factors computed once, in plain f64).
    fn invert_cosines(&self, observed: f64, c: &Cosines) -> Albedo {
        self.w_curve(c).invert(observed)
    }

    fn albedo_curve(&self, c: &Cosines) -> AlbedoCurve {
        AlbedoCurve::Hapke(self.w_curve(c))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometry::{incidence, Vec3};

    /// s = (sin i, 0, cos i) and v at emission e with s·v = cos g (docs/photometry.md's reference layout).
    fn geometry(i: f64, e: f64, g: f64) -> (Vec3, Vec3) {
        let (i, e, g) = (i.to_radians(), e.to_radians(), g.to_radians());
        let s = [i.sin(), 0.0, i.cos()];
        if e == 0.0 {
            return (s, [0.0, 0.0, 1.0]);
        }
        let cphi = if i == 0.0 {
            1.0
        } else {
            ((g.cos() - i.cos() * e.cos()) / (i.sin() * e.sin())).clamp(-1.0, 1.0)
        };
        let sphi = (1.0 - cphi * cphi).sqrt();
        (s, [e.sin() * cphi, e.sin() * sphi, e.cos()])
    }

    fn model(theta: f64, h: HFunction) -> Hapke {
        Hapke {
            theta_bar_deg: theta,
            h_function: h,
            ..Hapke::moon()
        }
    }

    /// docs/photometry.md reference table: i, e, g, then per w ∈ {0.2, 0.44, 0.8} the columns
    /// θ̄=0/H81, θ̄=11°/H81, θ̄=11°/H02.
    const TABLE: [[f64; 12]; 9] = [
        [
            0., 0., 0., 0.05765933, 0.05763308, 0.05768294, 0.13186977, 0.13167858, 0.13195137,
            0.27362859, 0.27189945, 0.27266985,
        ],
        [
            30., 0., 30., 0.02267813, 0.02265339, 0.02270350, 0.05439064, 0.05421211, 0.05448874,
            0.12868221, 0.12711166, 0.12798896,
        ],
        [
            30., 30., 2., 0.05172131, 0.05169425, 0.05175233, 0.11846323, 0.11826978, 0.11859255,
            0.24576852, 0.24411288, 0.24522290,
        ],
        [
            45., 30., 60., 0.01352710, 0.01350231, 0.01356002, 0.03374466, 0.03357048, 0.03389354,
            0.08657008, 0.08513836, 0.08634688,
        ],
        [
            20., 50., 40., 0.02430583, 0.02427102, 0.02434800, 0.05871343, 0.05847992, 0.05891114,
            0.13988753, 0.13800561, 0.13963076,
        ],
        [
            60., 10., 55., 0.01085847, 0.01080447, 0.01085207, 0.02669410, 0.02648841, 0.02675620,
            0.06587361, 0.06474697, 0.06581099,
        ],
        [
            75., 5., 78., 0.00482211, 0.00459112, 0.00462348, 0.01204064, 0.01150015, 0.01168212,
            0.03024207, 0.02910029, 0.02986079,
        ],
        [
            85., 0., 85., 0.00170117, 0.00151984, 0.00153229, 0.00417878, 0.00380603, 0.00387566,
            0.01003180, 0.00956602, 0.00985836,
        ],
        [
            70., 60., 120., 0.00654059, 0.00603720, 0.00611254, 0.01682380, 0.01547607, 0.01589761,
            0.04372276, 0.03985745, 0.04166463,
        ],
    ];

    #[test]
    fn reproduces_the_check_table() {
        let models = [
            model(0.0, HFunction::H81),
            model(11.0, HFunction::H81),
            model(11.0, HFunction::H02),
        ];
        for row in TABLE {
            let (s, v) = geometry(row[0], row[1], row[2]);
            for (wi, w) in [0.2, 0.44, 0.8].into_iter().enumerate() {
                for (mi, m) in models.iter().enumerate() {
                    let want = row[3 + 3 * wi + mi];
                    let got = m.shade(0.0, 0.0, w, &s, &v).r;
                    // The table is printed to 8 decimals: compare to its last digit (and 1e-8 relative
                    // where that is looser).
                    assert!(
                        (got - want).abs() <= 0.5e-8_f64.max(1e-8 * want),
                        "i,e,g={:?} w={w} model {mi}: {got} vs {want}",
                        &row[..3]
                    );
                }
            }
        }
    }

    #[test]
    fn reproduces_intermediate_terms() {
        // i, e, g, P, B, mu0e, mue, S, H81(mu0e), H81(mue) at w = 0.44, θ̄ = 11°.
        let rows: [[f64; 10]; 6] = [
            [
                0., 0., 0., 1.72891018, 3.10000000, 0.94545962, 0.94545962, 1.00000000, 1.19705096,
                1.19705096,
            ],
            [
                30., 0., 30., 1.53365678, 0.90223767, 0.81879205, 0.94545962, 1.00000000,
                1.18518830, 1.19705096,
            ],
            [
                45., 30., 60., 1.16870168, 0.49610805, 0.66855546, 0.81878878, 0.99997427,
                1.16820372, 1.18518797,
            ],
            [
                60., 10., 55., 1.22718407, 0.54078309, 0.47792138, 0.93165785, 0.98973410,
                1.14024213, 1.19584959,
            ],
            [
                85., 0., 85., 0.93109268, 0.33225143, 0.21981385, 0.94545962, 0.37487281,
                1.08325170, 1.19705096,
            ],
            [
                70., 60., 120., 0.76676433, 0.18511976, 0.35326328, 0.45098698, 0.85544022,
                1.11631362, 1.13552345,
            ],
        ];
        let m = model(11.0, HFunction::H81);
        for row in rows {
            let (s, v) = geometry(row[0], row[1], row[2]);
            let cos_g = s.iter().zip(v).map(|(a, b)| a * b).sum::<f64>();
            let (mu0e, mue, sh, _) =
                m.w_free(Dual::<1>::constant(s[2]), Dual::constant(v[2]), cos_g);
            let w = Dual::<1>::constant(0.44);
            let got = [
                m.phase.eval(cos_g),
                m.opposition(cos_g),
                mu0e.v,
                mue.v,
                sh.v,
                HFunction::H81.eval(mu0e, w).v,
                HFunction::H81.eval(mue, w).v,
            ];
            for (k, (g, want)) in got.iter().zip(&row[3..]).enumerate() {
                assert!(
                    (g - want).abs() <= 0.5e-8_f64.max(1e-8 * want),
                    "i,e,g={:?} term {k}: {g} vs {want}",
                    &row[..3]
                );
            }
        }
    }

    #[test]
    fn reproduces_the_derivative_table() {
        let s = [60f64.to_radians().sin(), 0.0, 60f64.to_radians().cos()];
        let v = [0.0, 5f64.to_radians().sin(), 5f64.to_radians().cos()];
        let rows = [
            (
                0.0,
                0.0,
                0.0,
                HFunction::H81,
                0.0247985912,
                -0.0306030818,
                0.0013499232,
            ),
            (
                0.0,
                0.1,
                -0.2,
                HFunction::H81,
                0.0212794645,
                -0.0338582169,
                0.0015794197,
            ),
            (
                0.0,
                0.1,
                -0.2,
                HFunction::H02,
                0.0215217860,
                -0.0340096948,
                0.0015678790,
            ),
            (
                11.0,
                0.0,
                0.0,
                HFunction::H81,
                0.024595448309,
                -0.031389438875,
                0.001335528975,
            ),
            (
                11.0,
                0.1,
                -0.2,
                HFunction::H81,
                0.020941354957,
                -0.035483721011,
                0.001754271735,
            ),
            (
                11.0,
                0.1,
                -0.2,
                HFunction::H02,
                0.021185816142,
                -0.035727402995,
                0.001750722898,
            ),
            (
                11.0,
                -0.3,
                0.15,
                HFunction::H81,
                0.032643971351,
                -0.021926338497,
                0.001096188426,
            ),
        ];
        for (tb, p, q, h, r, dp, dq) in rows {
            let got = model(tb, h).shade(p, q, 0.44, &s, &v);
            // The θ̄ = 0 rows are printed to 10 decimals, the others to 12.
            let tol = |want: f64| {
                if tb == 0.0 {
                    0.5e-10_f64.max(1e-7 * want.abs())
                } else {
                    1e-7 * want.abs()
                }
            };
            assert!(
                (got.r - r).abs() <= tol(r),
                "θ̄={tb} p={p} q={q} {h:?}: R {} vs {r}",
                got.r
            );
            assert!(
                (got.dr_dp - dp).abs() <= tol(dp),
                "θ̄={tb} p={p} q={q} {h:?}: dR/dp {} vs {dp}",
                got.dr_dp
            );
            assert!(
                (got.dr_dq - dq).abs() <= tol(dq),
                "θ̄={tb} p={p} q={q} {h:?}: dR/dq {} vs {dq}",
                got.dr_dq
            );
        }
    }

    #[test]
    fn derivatives_match_differences_on_both_roughness_branches() {
        let s = [0.3, 0.2, (1.0f64 - 0.13).sqrt()];
        let v = [-0.1, 0.05, (1.0f64 - 0.0125).sqrt()];
        let m = Hapke::moon();
        // (p, q) on the i < e and i > e sides.
        for &(p, q) in &[(0.35, 0.2), (-0.3, -0.1), (0.05, -0.4), (-0.5, 0.3)] {
            let a = m.shade(p, q, 0.3, &s, &v);
            let h = 1e-6;
            let f = |p, q| m.shade(p, q, 0.3, &s, &v).r;
            let np = (f(p + h, q) - f(p - h, q)) / (2.0 * h);
            let nq = (f(p, q + h) - f(p, q - h)) / (2.0 * h);
            assert!(
                (a.dr_dp - np).abs() < 1e-6 * np.abs().max(1e-3),
                "p: {} vs {np}",
                a.dr_dp
            );
            assert!(
                (a.dr_dq - nq).abs() < 1e-6 * nq.abs().max(1e-3),
                "q: {} vs {nq}",
                a.dr_dq
            );
        }
    }

    #[test]
    fn moon_set_is_back_scattering() {
        let p = Hapke::moon().phase;
        assert!((p.eval(1.0) - 1.729).abs() < 1e-3);
        assert!((p.eval(120f64.to_radians().cos()) - 0.767).abs() < 1e-3);
    }

    #[test]
    fn phase_conventions_agree_when_converted() {
        let a = PhaseFunction::Hg2012 { b: 0.21, c: 0.7 };
        let b = PhaseFunction::HgIsis { b: 0.21, c: 0.85 };
        for g in [0.0f64, 0.3, 1.0, 2.0] {
            assert!((a.eval(g.cos()) - b.eval(g.cos())).abs() < 1e-14);
        }
        // Legendre with b = c = 0 is isotropic.
        assert_eq!(PhaseFunction::Legendre { b: 0.0, c: 0.0 }.eval(0.3), 1.0);
    }

    #[test]
    fn albedo_inversion_round_trips_over_geometries() {
        for h in [HFunction::H81, HFunction::H02] {
            for tb in [0.0, 11.0, 25.0] {
                let m = model(tb, h);
                for (i, e, g) in [
                    (0., 0., 0.),
                    (30., 0., 30.),
                    (45., 30., 60.),
                    (20., 50., 40.),
                    (60., 10., 55.),
                    (85., 0., 85.),
                    (70., 60., 120.),
                    (30., 30., 2.),
                ] {
                    let (s, v) = geometry(i, e, g);
                    for w in [0.0, 1e-4, 0.05, 0.2, 0.44, 0.8, 0.97, 0.999] {
                        let r = m.shade(0.0, 0.0, w, &s, &v).r;
                        match m.invert(r, 0.0, 0.0, &s, &v) {
                            Albedo::Value(x) => assert!(
                                (x - w).abs() < 1e-10,
                                "{h:?} θ̄={tb} ({i},{e},{g}) w={w}: {x}"
                            ),
                            other => panic!("{other:?}"),
                        }
                    }
                    let r1 = m.shade(0.0, 0.0, W_MAX, &s, &v).r;
                    assert_eq!(m.invert(r1 * 1.01, 0.0, 0.0, &s, &v), Albedo::OutOfRange);
                    assert_eq!(m.invert(-0.5, 0.0, 0.0, &s, &v), Albedo::Value(0.0));
                }
            }
        }
    }

    #[test]
    fn shadow_and_grazing_view_carry_no_information() {
        let (s, v) = geometry(60.0, 0.0, 60.0);
        let m = Hapke::moon();
        // p = tan 30° with the Sun in the east: the slope faces west, 30° + 60° = 90° incidence.
        let r = m.shade(30f64.to_radians().tan() + 1e-9, 0.0, 0.44, &s, &v);
        assert!(!r.lit && r.r == 0.0);
        assert_eq!(m.invert(0.01, 5.0, 0.0, &s, &v), Albedo::Shadowed);
        // Camera 80° from zenith in the west, surface facing east (towards the Sun, μ0 > 0) but
        // turned more than 10° away from the camera (μ < 0).
        let v2 = [-80f64.to_radians().sin(), 0.0, 80f64.to_radians().cos()];
        assert!(incidence(-6.0, 0.0, &s, &[0.0, 0.0, 1.0]).is_some());
        assert!(!m.shade(-6.0, 0.0, 0.44, &s, &v2).lit);
        assert_eq!(m.invert(0.01, -6.0, 0.0, &s, &v2), Albedo::Shadowed);
    }
}
