//! Reflectance models for shape from shading (docs/photometry.md).
//!
//! Frame: x east, y north, z up. A surface with gradients p = ∂z/∂x, q = ∂z/∂y has the unit
//! normal n = (−p, −q, 1)/N, N = √(1+p²+q²). With s the unit vector to the Sun and v the unit
//! vector to the camera, μ0 = s·n, μ = v·n, cos g = s·v.
//!
//! A model implements [`ReflectanceModel`]: the reflectance as a function of (μ0, μ, cos g) and
//! the albedo, with its partials in μ0 and μ. [`ReflectanceModel::shade`] chains those with
//! ∂μ0/∂p = −s_x/N − p·μ0/N² (and likewise) to give R, ∂R/∂p, ∂R/∂q.

mod dual;
mod hapke;

pub use dual::Dual;
pub use hapke::{HFunction, Hapke, PhaseFunction, WCurve};

use serde::{Deserialize, Serialize};

/// A 3-vector in the local east-north-up frame.
pub type Vec3 = [f64; 3];

/// A unit vector stored in f32 (per-pixel Sun and view directions: 12 bytes a pixel instead of
/// 24; 6·10⁻⁸ rad is far below any geometry's accuracy). Widened exactly where it is used.
pub type Vec3f = [f32; 3];

/// `v` in f64, exactly.
#[inline]
pub fn widen(v: &Vec3f) -> Vec3 {
    v.map(f64::from)
}

/// `v` rounded to f32.
#[inline]
pub fn narrow(v: Vec3) -> Vec3f {
    v.map(|x| x as f32)
}

/// Cosines that fix the photometric geometry of one pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cosines {
    /// μ0 = cos i, incidence.
    pub mu0: f64,
    /// μ = cos e, emission.
    pub mu: f64,
    /// cos g, phase (independent of the surface slope).
    pub cos_g: f64,
}

/// A reflectance value with its partial derivatives in μ0 and μ (phase angle held fixed).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReflectanceCos {
    pub r: f64,
    pub dr_dmu0: f64,
    pub dr_dmu: f64,
}

/// R(p, q) and its gradient; `lit` is false where μ0 ≤ 0 or μ ≤ 0 (no photometric information:
/// the value and derivatives are then 0 and the pixel must be masked from E_I).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shade {
    pub r: f64,
    pub dr_dp: f64,
    pub dr_dq: f64,
    pub lit: bool,
}

impl Shade {
    const DARK: Shade = Shade {
        r: 0.0,
        dr_dp: 0.0,
        dr_dq: 0.0,
        lit: false,
    };
}

/// Outcome of the pixel-wise albedo inversion R(ρ; μ0, μ, g) = I.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Albedo {
    /// The unique albedo reproducing the observation (0 when the observation is ≤ 0).
    Value(f64),
    /// μ0 ≤ 0 or μ ≤ 0: the pixel carries no information about the albedo.
    Shadowed,
    /// The observation exceeds what the model can produce at the largest admissible albedo
    /// (saturation or wrong geometry): flagged rather than invented.
    OutOfRange,
}

/// R(ρ) at one pixel's fixed cosines ([`ReflectanceModel::albedo_curve`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum AlbedoCurve {
    /// R = u·ρ: the models linear in the albedo (Lambert, the metallic lobes); u = R(ρ = 1).
    Linear(f64),
    /// Hapke's dependence on w, its w-free factors computed once.
    Hapke(WCurve),
}

impl AlbedoCurve {
    /// (R, ∂R/∂ρ) at albedo `rho`.
    pub fn eval(&self, rho: f64) -> (f64, f64) {
        match self {
            AlbedoCurve::Linear(u) => (u * rho, *u),
            AlbedoCurve::Hapke(c) => c.eval(rho),
        }
    }

    /// Solve R(ρ) = `observed` for ρ on this curve: the model's
    /// [`ReflectanceModel::invert_cosines`] at the curve's cosines, bit for bit.
    pub fn invert(&self, observed: f64) -> Albedo {
        match self {
            AlbedoCurve::Linear(u) => invert_linear(observed, *u),
            AlbedoCurve::Hapke(c) => c.invert(observed),
        }
    }
}

/// Geometry of one pixel for a surface of gradient (p, q): the cosines and their p, q partials.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Incidence {
    pub cos: Cosines,
    pub dmu0_dp: f64,
    pub dmu0_dq: f64,
    pub dmu_dp: f64,
    pub dmu_dq: f64,
}

impl Incidence {
    /// R and its μ0, μ partials at this geometry, chained to R, ∂R/∂p, ∂R/∂q.
    fn shade(&self, r: ReflectanceCos) -> Shade {
        Shade {
            r: r.r,
            dr_dp: r.dr_dmu0 * self.dmu0_dp + r.dr_dmu * self.dmu_dp,
            dr_dq: r.dr_dmu0 * self.dmu0_dq + r.dr_dmu * self.dmu_dq,
            lit: true,
        }
    }
}

/// μ0, μ, cos g and their derivatives for gradients (p, q); `None` when μ0 ≤ 0 or μ ≤ 0.
pub fn incidence(p: f64, q: f64, sun: &Vec3, view: &Vec3) -> Option<Incidence> {
    let g = geometry(p, q, sun, view);
    (g.cos.mu0 > 0.0 && g.cos.mu > 0.0).then_some(g)
}

/// μ0, μ, cos g and their derivatives for gradients (p, q), whatever their signs.
fn geometry(p: f64, q: f64, sun: &Vec3, view: &Vec3) -> Incidence {
    let n2 = 1.0 + p * p + q * q;
    let n = n2.sqrt();
    let mu0 = (-p * sun[0] - q * sun[1] + sun[2]) / n;
    let mu = (-p * view[0] - q * view[1] + view[2]) / n;
    let cos_g = sun[0] * view[0] + sun[1] * view[1] + sun[2] * view[2];
    Incidence {
        cos: Cosines { mu0, mu, cos_g },
        dmu0_dp: -sun[0] / n - p * mu0 / n2,
        dmu0_dq: -sun[1] / n - q * mu0 / n2,
        dmu_dp: -view[0] / n - p * mu / n2,
        dmu_dq: -view[1] / n - q * mu / n2,
    }
}

/// The incidence cosine below which [`ReflectanceModel::shade_observed`] continues R linearly
/// (incidence 89.4°).
pub const MU0_FLOOR: f64 = 0.01;

/// A photometric model: reflectance as a function of albedo and the cosines of i, e, g.
pub trait ReflectanceModel: Send + Sync + std::fmt::Debug {
    /// R(ρ; μ0, μ, g) with ∂R/∂μ0 and ∂R/∂μ; called only with μ0 > 0, μ > 0.
    fn reflectance(&self, albedo: f64, c: &Cosines) -> ReflectanceCos;

    /// Solve R(ρ; μ0, μ, g) = `observed` for ρ (called only with μ0 > 0, μ > 0).
    fn invert_cosines(&self, observed: f64, c: &Cosines) -> Albedo;

    /// R as a function of the albedo alone at these cosines, with what does not depend on
    /// the albedo computed once (called only with μ0 > 0, μ > 0): the joint albedo of several
    /// observations evaluates it many times per pixel.
    fn albedo_curve(&self, c: &Cosines) -> AlbedoCurve;

    /// R alone for a surface of gradient (p, q): [`ReflectanceModel::shade`]'s value to
    /// rounding (0 where μ0 ≤ 0 or μ ≤ 0), from [`ReflectanceModel::albedo_curve`], without
    /// the derivatives in μ0 and μ (for Hapke the roughness correction in plain f64 rather
    /// than in dual numbers: a rendering, not a solve, needs only the value).
    fn shade_value(&self, p: f64, q: f64, albedo: f64, sun: &Vec3, view: &Vec3) -> f64 {
        match incidence(p, q, sun, view) {
            None => 0.0,
            Some(g) => self.albedo_curve(&g.cos).eval(albedo).0,
        }
    }

    /// R, ∂R/∂p, ∂R/∂q for a surface of gradient (p, q) under the given Sun and view vectors.
    fn shade(&self, p: f64, q: f64, albedo: f64, sun: &Vec3, view: &Vec3) -> Shade {
        match incidence(p, q, sun, view) {
            None => Shade::DARK,
            Some(g) => g.shade(self.reflectance(albedo, &g.cos)),
        }
    }

    /// R, ∂R/∂p, ∂R/∂q at a pixel the camera saw lit. Where the surface would face away from
    /// the Sun, R is not 0 but continues through μ0 = 0 as
    /// R(μ0, μ) = R(μ0_f, μ)·μ0/μ0_f for μ0 < μ0_f = [`MU0_FLOOR`]
    /// (exact for Lambert, to first order in μ0 for Hapke and the metallic lobes), so such a
    /// surface contradicts the observation with a residual that grows as it turns further away
    /// and a gradient that turns it back; dropping the pixel instead would let a solver park it
    /// in self-shadow at no cost. `lit` is false only where μ ≤ 0 (unseen by the camera).
    fn shade_observed(&self, p: f64, q: f64, albedo: f64, sun: &Vec3, view: &Vec3) -> Shade {
        let g = geometry(p, q, sun, view);
        if g.cos.mu <= 0.0 {
            return Shade::DARK;
        }
        if g.cos.mu0 >= MU0_FLOOR {
            return g.shade(self.reflectance(albedo, &g.cos));
        }
        let floor = Cosines {
            mu0: MU0_FLOOR,
            ..g.cos
        };
        let r = self.reflectance(albedo, &floor);
        let t = g.cos.mu0 / MU0_FLOOR;
        g.shade(ReflectanceCos {
            r: r.r * t,
            dr_dmu0: r.r / MU0_FLOOR,
            dr_dmu: r.dr_dmu * t,
        })
    }

    /// The pixel-wise albedo inversion for a surface of gradient (p, q).
    fn invert(&self, observed: f64, p: f64, q: f64, sun: &Vec3, view: &Vec3) -> Albedo {
        match incidence(p, q, sun, view) {
            None => Albedo::Shadowed,
            Some(g) => self.invert_cosines(observed, &g.cos),
        }
    }
}

/// Lambert: R = ρ·μ0.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Lambert;

impl ReflectanceModel for Lambert {
    fn reflectance(&self, albedo: f64, c: &Cosines) -> ReflectanceCos {
        ReflectanceCos {
            r: albedo * c.mu0,
            dr_dmu0: albedo,
            dr_dmu: 0.0,
        }
    }
    fn invert_cosines(&self, observed: f64, c: &Cosines) -> Albedo {
        invert_linear(observed, self.reflectance(1.0, c).r)
    }
    fn albedo_curve(&self, c: &Cosines) -> AlbedoCurve {
        AlbedoCurve::Linear(self.reflectance(1.0, c).r)
    }
}

/// One specular lobe A·cos^B(θr) of the metallic model.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Lobe {
    pub a: f64,
    pub b: f64,
}

/// Metallic model (d'Angelo & Wöhler; seed Eq. 3):
/// R = ρ·[μ0 + Σₖ Aₖ·cos^Bₖ(θr)], cos θr = 2μ0μ − cos g, each lobe 0 where cos θr ≤ 0.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metallic {
    pub lobes: Vec<Lobe>,
}

impl Metallic {
    /// The seed's cast-iron flange: K = 1, A₁ = 1.5, B₁ = 2.
    pub fn cast_iron() -> Self {
        Self {
            lobes: vec![Lobe { a: 1.5, b: 2.0 }],
        }
    }
}

impl ReflectanceModel for Metallic {
    fn reflectance(&self, albedo: f64, c: &Cosines) -> ReflectanceCos {
        let cr = 2.0 * c.mu0 * c.mu - c.cos_g;
        let (mut lobe, mut dlobe) = (0.0, 0.0);
        if cr > 0.0 {
            for l in &self.lobes {
                lobe += l.a * cr.powf(l.b);
                dlobe += l.a * l.b * cr.powf(l.b - 1.0);
            }
        }
        ReflectanceCos {
            r: albedo * (c.mu0 + lobe),
            dr_dmu0: albedo * (1.0 + dlobe * 2.0 * c.mu),
            dr_dmu: albedo * dlobe * 2.0 * c.mu0,
        }
    }
    fn invert_cosines(&self, observed: f64, c: &Cosines) -> Albedo {
        invert_linear(observed, self.reflectance(1.0, c).r)
    }
    fn albedo_curve(&self, c: &Cosines) -> AlbedoCurve {
        AlbedoCurve::Linear(self.reflectance(1.0, c).r)
    }
}

/// ρ = I / R(ρ = 1) for models linear in the albedo.
fn invert_linear(observed: f64, unit: f64) -> Albedo {
    if unit <= 0.0 {
        Albedo::Shadowed
    } else if observed <= 0.0 {
        Albedo::Value(0.0)
    } else {
        Albedo::Value(observed / unit)
    }
}

/// The photometric model selected by a user, as written in workflow files and run records.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "model", rename_all = "lowercase", deny_unknown_fields)]
pub enum ModelSpec {
    Lambert,
    Metallic { lobes: Vec<Lobe> },
    Hapke(Hapke),
}

impl ModelSpec {
    /// The model object.
    pub fn build(&self) -> Box<dyn ReflectanceModel> {
        match self {
            ModelSpec::Lambert => Box::new(Lambert),
            ModelSpec::Metallic { lobes } => Box::new(Metallic {
                lobes: lobes.clone(),
            }),
            ModelSpec::Hapke(h) => Box::new(h.clone()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn numeric(m: &dyn ReflectanceModel, p: f64, q: f64, s: &Vec3, v: &Vec3) -> (f64, f64) {
        let h = 1e-6;
        let f = |p, q| m.shade(p, q, 0.7, s, v).r;
        (
            (f(p + h, q) - f(p - h, q)) / (2.0 * h),
            (f(p, q + h) - f(p, q - h)) / (2.0 * h),
        )
    }

    #[test]
    fn lambert_and_metallic_derivatives_match_differences() {
        let s = [0.5f64.sin(), 0.1, 0.0];
        let s = [s[0], s[1], (1.0 - s[0] * s[0] - s[1] * s[1]).sqrt()];
        let v = [0.05, -0.02, (1.0f64 - 0.05 * 0.05 - 0.02 * 0.02).sqrt()];
        let models: [&dyn ReflectanceModel; 2] = [&Lambert, &Metallic::cast_iron()];
        for m in models {
            for &(p, q) in &[(0.0, 0.0), (0.2, -0.1), (-0.3, 0.25)] {
                let a = m.shade(p, q, 0.7, &s, &v);
                let (np, nq) = numeric(m, p, q, &s, &v);
                assert!((a.dr_dp - np).abs() < 1e-7, "{m:?} p {} {np}", a.dr_dp);
                assert!((a.dr_dq - nq).abs() < 1e-7, "{m:?} q {} {nq}", a.dr_dq);
            }
        }
    }

    /// `shade_value` (the albedo curve's R) is `shade`'s R to rounding for every model, on
    /// both of Hapke's roughness branches (i ≤ e and i ≥ e) and for H02, and 0 where the
    /// surface faces away from the Sun or the camera.
    #[test]
    fn the_value_alone_is_the_shades_value() {
        let h02 = Hapke {
            h_function: HFunction::H02,
            ..Hapke::moon()
        };
        let models: [&dyn ReflectanceModel; 4] =
            [&Lambert, &Metallic::cast_iron(), &Hapke::moon(), &h02];
        let dir = |i: f64, az: f64| {
            let (i, az) = (i.to_radians(), az.to_radians());
            [i.sin() * az.sin(), i.sin() * az.cos(), i.cos()]
        };
        for m in models {
            for (sun, view) in [
                (dir(60.0, 105.0), dir(2.0, 30.0)),
                (dir(5.0, 250.0), dir(40.0, 80.0)),
            ] {
                for &(p, q) in &[(0.0, 0.0), (0.2, -0.1), (-0.3, 0.25), (0.05, 0.4)] {
                    let (a, b) = (
                        m.shade(p, q, 0.3, &sun, &view).r,
                        m.shade_value(p, q, 0.3, &sun, &view),
                    );
                    assert!(
                        (a - b).abs() <= 1e-14 * a.abs(),
                        "{m:?} ({p}, {q}): {a} against {b}"
                    );
                }
                assert_eq!(m.shade_value(3.0, 0.0, 0.3, &[0.9, 0.0, 0.436], &view), 0.0);
            }
        }
    }

    /// `shade_observed` is `shade` where the Sun is above μ0_f; below it, its derivatives are
    /// those of the value it returns, it is continuous at μ0_f, it keeps falling as the surface
    /// turns away from the Sun (so I − R keeps growing), and for Lambert it is ρ·μ0 exactly.
    #[test]
    fn observed_shading_continues_through_the_terminator() {
        let s = [60f64.to_radians().sin(), 0.0, 60f64.to_radians().cos()];
        let v = [0.03, 0.01, (1.0f64 - 0.03 * 0.03 - 0.01 * 0.01).sqrt()];
        let hapke = Hapke::moon();
        let models: [&dyn ReflectanceModel; 3] = [&Lambert, &Metallic::cast_iron(), &hapke];
        // μ0 = 0 at p = tan 30° ≈ 0.577.
        let p_floor = |q: f64| {
            // Solve μ0(p, q) = μ0_f for p by bisection on the Sun-facing side.
            let (mut lo, mut hi) = (0.0, 1.0);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if incidence(mid, q, &s, &v).is_some_and(|g| g.cos.mu0 > MU0_FLOOR) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            lo
        };
        for m in models {
            let lit = m.shade(0.2, 0.1, 0.6, &s, &v);
            assert_eq!(m.shade_observed(0.2, 0.1, 0.6, &s, &v), lit, "{m:?}");
            let pf = p_floor(0.1);
            let (below, above) = (
                m.shade_observed(pf + 1e-9, 0.1, 0.6, &s, &v),
                m.shade_observed(pf - 1e-9, 0.1, 0.6, &s, &v),
            );
            // A step of 2e-9 in p moves R by |∂R/∂p|·2e-9 < 1e-8: a jump would be far more.
            assert!(
                (below.r - above.r).abs() < 1e-8,
                "{m:?}: {} vs {}",
                below.r,
                above.r
            );
            let mut last = f64::INFINITY;
            for p in [0.5, 0.58, 0.7, 1.0, 1.5] {
                let a = m.shade_observed(p, 0.1, 0.6, &s, &v);
                assert!(
                    a.lit && a.r < last,
                    "{m:?} at p = {p}: {} after {last}",
                    a.r
                );
                last = a.r;
                let h = 1e-6;
                let f = |p, q| m.shade_observed(p, q, 0.6, &s, &v).r;
                let np = (f(p + h, 0.1) - f(p - h, 0.1)) / (2.0 * h);
                let nq = (f(p, 0.1 + h) - f(p, 0.1 - h)) / (2.0 * h);
                assert!(
                    (a.dr_dp - np).abs() < 1e-6,
                    "{m:?} p = {p}: {} {np}",
                    a.dr_dp
                );
                assert!(
                    (a.dr_dq - nq).abs() < 1e-6,
                    "{m:?} p = {p}: {} {nq}",
                    a.dr_dq
                );
            }
            assert!(
                last < 0.0,
                "{m:?}: R = {last} on a slope facing away from the Sun"
            );
        }
        for p in [0.7, 1.5] {
            let n = (1.0f64 + p * p + 0.01).sqrt();
            let mu0 = (-p * s[0] - 0.1 * s[1] + s[2]) / n;
            let r = Lambert.shade_observed(p, 0.1, 0.6, &s, &v).r;
            assert!((r - 0.6 * mu0).abs() < 1e-15, "{r} vs {}", 0.6 * mu0);
        }
        // Unseen by the camera: no information, as with `shade`.
        assert!(!Lambert.shade_observed(40.0, 0.0, 0.6, &s, &v).lit);
    }

    #[test]
    fn lambert_is_albedo_times_cos_incidence() {
        // Sun 60° from zenith towards east, flat surface: R = ρ·cos 60°.
        let s = [60f64.to_radians().sin(), 0.0, 60f64.to_radians().cos()];
        let r = Lambert.shade(0.0, 0.0, 0.8, &s, &[0.0, 0.0, 1.0]);
        assert!((r.r - 0.4).abs() < 1e-15);
        // A slope tilted 60° away from the Sun (p = tan 30° is the surface rising to the east by
        // 30°, facing west): μ0 = cos 90° = 0 → no information.
        let away = Lambert.shade(3f64.sqrt(), 0.0, 0.8, &s, &[0.0, 0.0, 1.0]);
        assert!(!away.lit && away.r == 0.0 && away.dr_dp == 0.0);
    }

    #[test]
    fn metallic_lobe_vanishes_beyond_ninety_degrees() {
        // cos θr = 2μ0μ − cos g ≤ 0 → pure Lambert.
        let c = Cosines {
            mu0: 0.3,
            mu: 0.3,
            cos_g: 0.5,
        };
        let r = Metallic::cast_iron().reflectance(1.0, &c);
        assert_eq!(r.r, 0.3);
        // cos θr = 2·0.9·0.9 − 0.62 = 1.0 → lobe 1.5.
        let c = Cosines {
            mu0: 0.9,
            mu: 0.9,
            cos_g: 0.62,
        };
        let r = Metallic::cast_iron().reflectance(2.0, &c);
        assert!((r.r - 2.0 * (0.9 + 1.5)).abs() < 1e-12);
    }

    #[test]
    fn linear_inversion_round_trips_and_flags_shadow() {
        let s = [0.6, 0.0, 0.8];
        let v = [0.0, 0.0, 1.0];
        let m = Metallic::cast_iron();
        let r = m.shade(0.1, -0.2, 0.37, &s, &v).r;
        match m.invert(r, 0.1, -0.2, &s, &v) {
            Albedo::Value(a) => assert!((a - 0.37).abs() < 1e-14),
            other => panic!("{other:?}"),
        }
        assert_eq!(m.invert(0.1, 2.0, 0.0, &s, &v), Albedo::Shadowed);
        assert_eq!(Lambert.invert(-0.01, 0.0, 0.0, &s, &v), Albedo::Value(0.0));
    }
}
