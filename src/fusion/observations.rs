//! Several observations of one surface (docs/science.md, "Several observations"): which pixels
//! each observation contributes, with what weight, at what radiometric gain, and the albedo
//! they agree on.
//!
//! E_I = Σ_k Σ_x w_k(x)·(I_k(x)/g_k − R(p, q, ρ; s_k, v_k))²/Ī², with
//! * g_k, the gain of observation k (its detector and calibration relative to the reference:
//!   I_k = g_k·R), estimated from where observations overlap ([`super::gains`]);
//! * w_k(x) = ν_k·e_k(x)·τ_k(x)·s_k(x) on the pixels k sees lit (0 elsewhere):
//!   - ν_k = Ī/Ī_k ([`noise_weight`]), Ī_k the mean of I_k/g_k over its valid pixels: the
//!     variance of each image's error is taken as proportional to its brightness, as a
//!     photon-limited detector's shot noise is, so a dim low-Sun image weighs more per unit
//!     of absolute error than a bright one, but less than a fixed relative error would make it
//!     (that image's photometric model error grows faster than its brightness falls). One
//!     observation: ν = 1;
//!   - e_k(x) = ramp_k(x)/max_j ramp_j(x), ramp_k a C¹ smoothstep of the distance to the edge
//!     of k's footprint over `edge_ramp_px`: an observation fades in over a band inside its
//!     edge wherever another one carries on, so no strip edge is a step in the data; where it
//!     is alone e_k = 1;
//!   - τ_k(x), 1 up to 10° before the maximum incidence and a smoothstep to 0 at it: near the
//!     terminator shadows and roughness make the model least reliable;
//!   - β (`shadow_edge_weight`; 0.4β under k's Sun up to 20° high, β from 25°) on a pixel next
//!     to one k sees shadowed, wherever another observation carries the pixel away from its own
//!     shadows, β_all
//!     (`shadow_edge_weight_all`) where two or more others do ([`shadow_edge_factors`]); 1
//!     elsewhere.
//! * Selection: pixels outside [min, max] incidence drop out; with `max_per_pixel` = M > 0 only
//!   the M observations of largest w_k·μ_k/s_k² (μ the cosine of the emission angle, s_k² the
//!   area of an observation's pixel in grid pixels, 1 unless it is coarser than the grid) are
//!   kept at a pixel.

use super::support::{self, smoothstep};
use super::Problem;
use crate::photometry::{incidence, Albedo, AlbedoCurve, ReflectanceModel, Vec3};
use ndarray::{Array2, ArrayView2, Axis, Zip};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Which observations a pixel uses (`[inputs]` in a workflow).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Selection {
    /// At most this many observations per pixel, the best by w·μ (0: all).
    pub max_per_pixel: usize,
    /// Pixels whose Sun is closer to the zenith than this are not used (degrees).
    pub min_incidence_deg: f64,
    /// Pixels whose Sun is lower than this are not used; weights fade over the 10° before it.
    pub max_incidence_deg: f64,
}

impl Default for Selection {
    fn default() -> Self {
        Self {
            max_per_pixel: 0,
            min_incidence_deg: 0.0,
            max_incidence_deg: 90.0,
        }
    }
}

impl Selection {
    /// Whether a pixel whose Sun stands at incidence `inc` (degrees) is within the selection:
    /// `min_incidence_deg` ≤ inc < `max_incidence_deg`.
    pub fn admits(&self, inc: f64) -> bool {
        inc >= self.min_incidence_deg && inc < self.max_incidence_deg
    }

    /// Whether some incidence in `[lo, hi]` (degrees) is within the selection, the window
    /// widened by [`RANGE_TOLERANCE_DEG`] either side: a range of a whole observation's Suns
    /// (`pipeline::plan`'s check that a window leaves some observation in) is measured from
    /// the swath's own angles, which the grid's Sun vectors carry to within rounding.
    pub fn admits_some_of(&self, [lo, hi]: [f64; 2]) -> bool {
        hi >= self.min_incidence_deg - RANGE_TOLERANCE_DEG
            && lo < self.max_incidence_deg + RANGE_TOLERANCE_DEG
    }
}

/// Slack of [`Selection::admits_some_of`], degrees.
pub const RANGE_TOLERANCE_DEG: f64 = 1e-3;

/// Width, in degrees, over which τ fades to 0 at the maximum incidence.
pub const INCIDENCE_FADE_DEG: f64 = 10.0;

/// Per-observation masks and weights for one problem.
#[derive(Debug, Clone)]
pub struct Weights {
    /// Pixels observation k contributes: valid, lit in the image, within the selection.
    pub usable: Vec<Array2<bool>>,
    /// w_k(x), 0 where not usable. Formed in f64 and stored in f32 (a weight needs no more
    /// than f32's 7 digits; every use widens it exactly, so all of them see the same w_k).
    pub weight: Vec<Array2<f32>>,
    /// g_k.
    pub gains: Vec<f64>,
    /// ν_k.
    pub noise: Vec<f64>,
    /// f_k(x), the lit share of each pixel just past observation k's own cast shadows on the
    /// surface the stage started from ([`super::shadows::lit_fractions`]); `None`: 1
    /// everywhere.
    pub lit: Vec<Option<Array2<f32>>>,
}

impl Weights {
    /// f_k at pixel `ix` ([`Weights::lit`]).
    #[inline]
    pub fn lit_at(&self, k: usize, ix: (usize, usize)) -> f64 {
        self.lit[k].as_ref().map_or(1.0, |f| f64::from(f[ix]))
    }

    /// c(x) = min(1, Σ_k u_k/max_k u_k − 1), u_k = w_k/ν_k (the edge ramp, incidence taper
    /// and shadow-edge factor): 0 where one observation carries the pixel (or none), 1 where a
    /// second one carries it in full, continuous across the edge ramps.
    pub fn multiplicity(&self) -> Array2<f64> {
        let dim = self.weight[0].dim();
        let mut sum = Array2::<f64>::zeros(dim);
        let mut top = Array2::<f64>::zeros(dim);
        for (w, &nu) in self.weight.iter().zip(&self.noise) {
            Zip::from(&mut sum)
                .and(&mut top)
                .and(w)
                .for_each(|s, t, &w| {
                    let w = f64::from(w);
                    *s += w / nu;
                    *t = t.max(w / nu);
                });
        }
        Zip::from(&sum)
            .and(&top)
            .map_collect(|&s, &t| if t > 0.0 { (s / t - 1.0).min(1.0) } else { 0.0 })
    }
}

/// Suns all within this many degrees of one another (every pair, angle between the vectors)
/// count as alike ([`suns_alike`]): the images then differ under a slope by no more than
/// their noise and measure no slope free of albedo (two images under one Sun give 0.94× one
/// image's error on the 256² scene, by averaging their noise; docs/science.md, "Where two Suns
/// fall short of 0.65×").
pub const ALIKE_SUNS_DEG: f64 = 5.0;

/// Whether every pair of the Sun vectors `suns` (unit, grid frame) lies within
/// [`ALIKE_SUNS_DEG`] of each other: cos θ = s_j·s_k ≥ cos 5°. True for one Sun or none.
pub fn suns_alike(suns: &[Vec3]) -> bool {
    let min_cos = ALIKE_SUNS_DEG.to_radians().cos();
    suns.iter().enumerate().all(|(j, a)| {
        suns[j + 1..]
            .iter()
            .all(|b| a[0] * b[0] + a[1] * b[1] + a[2] * b[2] >= min_cos)
    })
}

/// Sun directions within this many degrees of a mirror image about the east–west line count
/// as measuring east–west slopes only together with the albedo ([`east_west_share`]).
pub const EAST_WEST_BLIND_DEG: f64 = 20.0;

/// The share of the images' albedo-free slope information that bears on east–west slopes, for
/// observations with Sun vectors `suns` (grid frame: x east along the rows, z up) seeing one
/// pixel: M_xx/(M_xx + M_yy) of M = Σ_k g_k g_kᵀ − (Σ_k g_k)(Σ_k g_k)ᵀ/n, g_k = −(s_x, s_y)/s_z
/// the gradient of ln R in the slopes on a level surface for a Lambert surface (a change of
/// albedo moves every ln R_k alike, so only the g_k's spread about their mean measures slope
/// free of it). Two Suns mirrored about the east–west line brighten and darken alike under an
/// east–west slope: share 0. `None` with fewer than two Suns above the horizon or Suns all in
/// one direction.
pub fn east_west_share(suns: &[Vec3]) -> Option<f64> {
    let g: Vec<(f64, f64)> = suns
        .iter()
        .filter(|s| s[2] > 1e-6)
        .map(|s| (-s[0] / s[2], -s[1] / s[2]))
        .collect();
    if g.len() < 2 {
        return None;
    }
    let n = g.len() as f64;
    let (mx, my) = g
        .iter()
        .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x / n, b + y / n));
    let (xx, yy) = g.iter().fold((0.0, 0.0), |(a, b), &(x, y)| {
        (a + (x - mx) * (x - mx), b + (y - my) * (y - my))
    });
    (xx + yy > 1e-12).then(|| xx / (xx + yy))
}

/// m₀ of [`every_direction`]: its factor λ_min/(λ_min + m₀). Three Suns 120° apart in azimuth
/// at one elevation e give λ_min = 1.5·cot² e (u_k = 1): 4.5 at 30°, 0.74 at 55°, where the
/// factor is 0.99 and 0.94.
pub const EVERY_DIRECTION_M0: f64 = 0.05;

/// [r₀, r₁] of [`every_direction`]: its factor rises from 0 to 1 as λ_min/λ_max goes from r₀ to
/// r₁. Three Suns spread evenly in azimuth give 0.6–0.8 (60/60 + 180/50 + 300/55: 0.65;
/// 105/30 + 225/35 + 345/25: 0.62); two Suns mirrored about a line and a third along it that
/// measures the other direction weakly, or three within 120° of azimuth, 0.1 (45/30 + 135/30 +
/// 90/60, 20/25 + 80/30 + 140/35): there lowering δ lets the DEM's errors in the weak
/// direction through (docs/science.md, "Several observations").
pub const EVERY_DIRECTION_RATIO: [f64; 2] = [0.2, 0.6];

/// φ(x) ∈ [0, 1): how fully the images at a pixel measure slope free of albedo in every
/// direction. M = Σ_k u_k g_k g_kᵀ − (Σ_k u_k g_k)(Σ_k u_k g_k)ᵀ/Σ_k u_k over the observations
/// k that carry the pixel (u_k = w_k/ν_k > 0: edge ramp, incidence taper, shadow-edge factor),
/// g_k = −(s_x, s_y)/s_z the gradient of ln R in the slopes on a level surface for a Lambert
/// surface ([`east_west_share`]); φ = clamp((λ_min/λ_max − r₀)/(r₁ − r₀), 0, 1)·λ_min/(λ_min +
/// m₀), λ_min ≤ λ_max M's eigenvalues, [r₀, r₁] = [`EVERY_DIRECTION_RATIO`], m₀ =
/// [`EVERY_DIRECTION_M0`]: the least-measured direction must be measured both comparably to
/// the best one and in absolute terms. A change of albedo moves every ln R_k alike, so only the
/// g_k's spread measures slope free of it: two observations spread along one direction only
/// (M has rank one, φ = 0, taken as exactly 0), three or more Suns apart in azimuth along
/// every one. Times smoothstep((ē − e₀)/(e₁ − e₀)), ē the Suns' mean elevation
/// ([`EVERY_DIRECTION_SUN_DEG`]): under Suns 20° high or lower on average φ = 0. 0 where
/// c(x) = 0.
pub fn every_direction(pr: &Problem, w: &Weights, c: &Array2<f64>) -> Array2<f64> {
    where_overlapping(pr, w, c, every_direction_at)
}

/// `at` of each pixel's observations as (u_k = w_k/ν_k, Sun vector) where c(x) > 0, 0
/// elsewhere.
fn where_overlapping<F>(pr: &Problem, w: &Weights, c: &Array2<f64>, at: F) -> Array2<f64>
where
    F: Fn(&mut dyn Iterator<Item = (f64, Vec3)>) -> f64 + Sync,
{
    Zip::indexed(c).par_map_collect(|(i, j), &c| {
        if c <= 0.0 {
            return 0.0;
        }
        at(&mut pr
            .observations
            .iter()
            .zip(&w.weight)
            .zip(&w.noise)
            .map(|((o, wk), &nu)| (f64::from(wk[(i, j)]) / nu, o.sun.at(i, j))))
    })
}

/// M = Σ_k u_k g_k g_kᵀ − (Σ_k u_k g_k)(Σ_k u_k g_k)ᵀ/Σ_k u_k as (M_xx, M_xy, M_yy), g_k =
/// −(s_x, s_y)/s_z, over the observations' (u_k, Sun vector) with u_k > 0 and the Sun above the
/// horizon, how many of them counted, and the u_k-weighted mean of |g_k|² = cot² e_k (M = 0
/// and NaN without any): the spread of ln R's slope gradients that measures slope free of
/// albedo ([`every_direction`]), and how steeply the Suns fall.
fn slope_spread(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> (usize, [f64; 3], f64) {
    let (mut n, mut su, mut sx, mut sy) = (0, 0.0, 0.0, 0.0);
    let (mut mxx, mut mxy, mut myy) = (0.0, 0.0, 0.0);
    for (u, s) in observations {
        if u <= 0.0 || s[2] <= 1e-6 {
            continue;
        }
        let (gx, gy) = (-s[0] / s[2], -s[1] / s[2]);
        n += 1;
        su += u;
        sx += u * gx;
        sy += u * gy;
        mxx += u * gx * gx;
        mxy += u * gx * gy;
        myy += u * gy * gy;
    }
    if n == 0 {
        return (0, [0.0; 3], f64::NAN);
    }
    (
        n,
        [mxx - sx * sx / su, mxy - sx * sy / su, myy - sy * sy / su],
        (mxx + myy) / su,
    )
}

/// φ of [`every_direction`] at one pixel, from each observation's (u_k, Sun vector); those with
/// u_k ≤ 0 or the Sun at or below the horizon do not count.
pub fn every_direction_at(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> f64 {
    let (n, m, cot2) = slope_spread(observations);
    if n < 3 {
        return 0.0;
    }
    let (lo, hi) = eigenvalues(m);
    if hi <= 0.0 {
        return 0.0;
    }
    let [e0, e1] = EVERY_DIRECTION_SUN_DEG;
    let elevation = cot2.sqrt().recip().atan().to_degrees();
    let high_enough = smoothstep((elevation - e0) / (e1 - e0));
    direction_spread(lo, hi) * lo / (lo + EVERY_DIRECTION_M0) * high_enough
}

/// [e₀, e₁] of [`every_direction`], degrees: φ is taken in full where the Suns at a pixel stand
/// e₁ high or more on average (ē = atan(1/√(mean cot² e_k)), u_k-weighted), not at all at e₀
/// or lower, a smoothstep between. Under low Suns the images' slopes carry the forward
/// model's errors at grazing light (partial shadows, sub-pixel rims) into relief tens of
/// pixels wide, and the DEM keeps the share it has with two Suns: with the rule three Suns
/// 15° high come out 2–3.4 % lower (12°: 5.6 %, 20°: 1.4 %), and φ taken at 25° keeps three
/// 25° Suns 1.3 % lower than without it (docs/science.md, "Three low Suns").
pub const EVERY_DIRECTION_SUN_DEG: [f64; 2] = [20.0, 25.0];

/// The eigenvalues λ_min ≤ λ_max of the symmetric M = [[a, b], [b, d]] of [`slope_spread`],
/// λ_min no lower than 0.
fn eigenvalues([a, b, d]: [f64; 3]) -> (f64, f64) {
    let root = (0.25 * (a - d) * (a - d) + b * b).sqrt();
    ((0.5 * (a + d) - root).max(0.0), 0.5 * (a + d) + root)
}

/// s = clamp((λ_min/λ_max − r₀)/(r₁ − r₀), 0, 1), [r₀, r₁] = [`EVERY_DIRECTION_RATIO`]: how
/// evenly M's two directions are measured ([`every_direction`], [`east_west_unmeasured`]).
fn direction_spread(lo: f64, hi: f64) -> f64 {
    let [r0, r1] = EVERY_DIRECTION_RATIO;
    ((lo / hi - r0) / (r1 - r0)).clamp(0.0, 1.0)
}

/// [s₀, s₁] of [`east_west_open`]: ψ rises from 0 to 1 as the east–west share of the images'
/// albedo-free slope information goes from s₀ to s₁ (the direction they measure 8° and 18°
/// from north–south). Two Suns mirrored about the east–west line, or within 8° of it, measure
/// east–west slopes only together with the albedo (share ≤ 0.02: 45/30 + 135/30 0,
/// 60/30 + 135/30 0.017); 45/30 + 150/35 gives 0.04, 50/35 + 165/35 0.09, 0/45 + 120/40 0.30.
pub const EAST_WEST_OPEN_SHARE: [f64; 2] = [0.02, 0.1];

/// ψ(x) ∈ [0, 1]: whether the images at a pixel measure east–west slopes free of albedo:
/// smoothstep((s − s₀)/(s₁ − s₀)), s = M_xx/(M_xx + M_yy) of the u_k-weighted M of
/// [`every_direction`] (the share [`east_west_share`] gives for equal weights), [s₀, s₁] =
/// [`EAST_WEST_OPEN_SHARE`]. Where they do, δ may be lowered further: the DEM's largest errors
/// inside its passband are the offsets between its tracks, east–west slopes the images then
/// correct; where they do not, the DEM and the membrane alone hold those slopes (docs/science.md,
/// "The DEM term where the images see east–west slopes"). 0 where c(x) = 0.
pub fn east_west_open(pr: &Problem, w: &Weights, c: &Array2<f64>) -> Array2<f64> {
    where_overlapping(pr, w, c, east_west_open_at)
}

/// ψ of [`east_west_open`] at one pixel, from each observation's (u_k, Sun vector); those with
/// u_k ≤ 0 or the Sun at or below the horizon do not count (ψ = 0 with fewer than two, or with
/// Suns all in one direction).
pub fn east_west_open_at(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> f64 {
    let (n, [a, _, d], cot2) = slope_spread(observations);
    if n < 2 || a + d <= 1e-12 {
        return 0.0;
    }
    let [s0, s1] = EAST_WEST_OPEN_SHARE;
    let [m0, m1] = EAST_WEST_LOW_SUN_COT2;
    let low = smoothstep((m1 - cot2) / (m1 - m0));
    smoothstep((a / (a + d) - s0) / (s1 - s0)) * low
}

/// [χ₀, χ₁] of [`east_west_unmeasured`]'s use in [`super::objective::Objective::with_multi_delta`]:
/// under high Suns the DEM term goes from δ·f_high (χ ≥ χ₁) down to δ·f_high,ew (χ ≤ χ₀).
/// Two Suns mirrored about the north–south line (110/55 + 250/60) give χ ≈ 0, 115/40 + 240/60
/// 0.018, 35/60 + 275/50 0.105 (its blind direction 25° from north already lets enough of the
/// DEM's offsets through to lose 1–2 % at f_high,ew); Suns 90° apart with the bisector
/// south-east (90/55 + 180/55) 0.5, mirrored about the east–west line (45/55 + 135/55) 1;
/// three Suns spread in azimuth (λ_min/λ_max ≥ 0.6) 0.
pub const EAST_WEST_UNMEASURED: [f64; 2] = [0.02, 0.1];

/// χ(x) ∈ [0, 1]: how much of the east–west direction the images at a pixel leave unmeasured
/// free of albedo, from M of [`every_direction`]: χ = v_x²·(1 − s), v the unit eigenvector of
/// M's smaller eigenvalue λ_min (the direction the images measure least; for two Suns the
/// bisector of their azimuths, along which a slope changes both images as an albedo change
/// does), s = clamp((λ_min/λ_max − r₀)/(r₁ − r₀), 0, 1) with [r₀, r₁] =
/// [`EVERY_DIRECTION_RATIO`] (three Suns spread in azimuth measure every direction: χ = 0).
/// The DEM's track offsets are east–west slopes: where χ is large the images cannot take them
/// out, and the DEM term must hold them. 0 where c(x) = 0.
pub fn east_west_unmeasured(pr: &Problem, w: &Weights, c: &Array2<f64>) -> Array2<f64> {
    where_overlapping(pr, w, c, east_west_unmeasured_at)
}

/// χ of [`east_west_unmeasured`] at one pixel, from each observation's (u_k, Sun vector); those
/// with u_k ≤ 0 or the Sun at or below the horizon do not count. 1 with fewer than two, or
/// with Suns all in one direction (nothing measured free of albedo).
pub fn east_west_unmeasured_at(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> f64 {
    let (n, m, _) = slope_spread(observations);
    if n < 2 {
        return 1.0;
    }
    let (lo, hi) = eigenvalues(m);
    if hi <= 1e-12 {
        return 1.0;
    }
    let [a, b, d] = m;
    // (M − λ_min)v = 0: v ∥ (b, λ_min − a) or (λ_min − d, b), whichever is the longer.
    let (v1, v2) = ((b, lo - a), (lo - d, b));
    let (vx, vy) = if v1.0 * v1.0 + v1.1 * v1.1 >= v2.0 * v2.0 + v2.1 * v2.1 {
        v1
    } else {
        v2
    };
    let norm = vx * vx + vy * vy;
    let vx2 = if norm > 0.0 { vx * vx / norm } else { 0.0 };
    vx2 * (1.0 - direction_spread(lo, hi))
}

/// [m₀, m₁] of [`east_west_open`]: ψ fades from its full value to 0 as the u_k-weighted mean
/// cot² of the Suns' elevations goes from m₀ to m₁ (cot² e = 3 at 30°, 6 at 22.2°). Under such
/// low Suns the shadows hide much of each crater, whose floors the DEM alone holds, and the
/// images measure the slopes they see firmly already: two 20° Suns (cot² = 7.5) lost 1 % with δ
/// lowered and their tiles drifted apart (docs/science.md, "The DEM term where the images see
/// east–west slopes").
pub const EAST_WEST_LOW_SUN_COT2: [f64; 2] = [3.0, 6.0];

/// [m₀, m₁] of [`high_sun`]: η rises from 0 to 1 as the mean cot² of the Suns' elevations
/// falls from m₁ to m₀ (cot² e = 1.2 at 42.4°, 0.6 at 52.2°): two Suns 55–60° high get η = 1,
/// 45° (cot² = 1) η = 1/3, 30–40° none.
pub const HIGH_SUN_COT2: [f64; 2] = [0.6, 1.2];

/// η(x) ∈ [0, 1]: how high the Suns of the observations that carry a pixel stand, from the
/// u_k-weighted mean of cot² e_k = (s_x² + s_y²)/s_z² (u_k as in [`every_direction`]):
/// clamp((m₁ − mean)/(m₁ − m₀), 0, 1), [m₀, m₁] = [`HIGH_SUN_COT2`]. cot² e is |g_k|², the
/// squared slope sensitivity of ln R for a Lambert surface: under high Suns the shading says
/// little per unit slope and casts few shadows, and the DEM's own errors inside its passband
/// weigh most. 0 where c(x) = 0.
pub fn high_sun(pr: &Problem, w: &Weights, c: &Array2<f64>) -> Array2<f64> {
    where_overlapping(pr, w, c, high_sun_at)
}

/// m₁ of [`high_sun_east_west`]: where the images measure the east–west direction free of
/// albedo the high-Sun rule starts at lower Suns, cot² e = 1.6 (38.3°; 45° Suns, cot² = 1,
/// get η = 0.6 instead of 1/3).
pub const HIGH_SUN_EAST_WEST_COT2: f64 = 1.6;

/// η of [`high_sun`] on the wider ramp [m₀, [`HIGH_SUN_EAST_WEST_COT2`]], for pixels whose
/// images measure the east–west direction ([`east_west_unmeasured`] small;
/// [`super::objective::Objective::with_multi_delta`] blends the two by it).
pub fn high_sun_east_west(pr: &Problem, w: &Weights, c: &Array2<f64>) -> Array2<f64> {
    where_overlapping(pr, w, c, |o| {
        high_sun_ramp(mean_cot2(o), HIGH_SUN_EAST_WEST_COT2)
    })
}

/// η of [`high_sun`] at one pixel, from each observation's (u_k, Sun vector); those with
/// u_k ≤ 0 or the Sun at or below the horizon do not count (η = 0 without any).
pub fn high_sun_at(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> f64 {
    high_sun_ramp(mean_cot2(observations), HIGH_SUN_COT2[1])
}

/// clamp((m₁ − m)/(m₁ − m₀), 0, 1), m₀ = [`HIGH_SUN_COT2`]'s; 0 where the mean cot² m is NaN
/// (no observation).
fn high_sun_ramp(m: f64, m1: f64) -> f64 {
    if m.is_nan() {
        return 0.0;
    }
    let m0 = HIGH_SUN_COT2[0];
    ((m1 - m) / (m1 - m0)).clamp(0.0, 1.0)
}

/// The u_k-weighted mean of cot² e_k = (s_x² + s_y²)/s_z² over the observations' (u_k, Sun
/// vector) with u_k > 0 and the Sun above the horizon; NaN without any.
fn mean_cot2(observations: &mut dyn Iterator<Item = (f64, Vec3)>) -> f64 {
    let (mut su, mut s2) = (0.0, 0.0);
    for (u, s) in observations {
        if u <= 0.0 || s[2] <= 1e-6 {
            continue;
        }
        su += u;
        s2 += u * (s[0] * s[0] + s[1] * s[1]) / (s[2] * s[2]);
    }
    if su <= 0.0 {
        return f64::NAN;
    }
    s2 / su
}

/// Incidence angle, degrees, of a Sun vector in the grid frame (z up).
pub fn incidence_deg(sun: &[f64; 3]) -> f64 {
    sun[2].clamp(-1.0, 1.0).acos().to_degrees()
}

/// The Sun's elevation above the horizon of a level surface, degrees: 90° − its incidence
/// ([`incidence_deg`]).
pub fn elevation_deg(sun: &[f64; 3]) -> f64 {
    90.0 - incidence_deg(sun)
}

/// τ(i) for incidence `i` and maximum incidence `max` (degrees).
pub fn incidence_taper(i: f64, max: f64) -> f64 {
    smoothstep((max - i) / INCIDENCE_FADE_DEG)
}

/// e_k for every observation: ramp_k/max_j ramp_j over the footprints (finite images).
pub fn edge_weights(footprints: &[Array2<bool>], width: f64) -> Vec<Array2<f64>> {
    let dim = footprints[0].dim();
    if footprints.len() == 1 || width <= 0.0 {
        return vec![Array2::from_elem(dim, 1.0); footprints.len()];
    }
    let ramps: Vec<Array2<f64>> = footprints
        .iter()
        .map(|f| {
            let d = support::distance(&f.mapv(|b| !b));
            d.mapv(|d| {
                if d.is_infinite() {
                    1.0
                } else {
                    smoothstep(d / width)
                }
            })
        })
        .collect();
    let mut top = Array2::<f64>::zeros(dim);
    for r in &ramps {
        Zip::from(&mut top).and(r).for_each(|t, &r| *t = t.max(r));
    }
    ramps
        .into_iter()
        .map(|r| {
            Zip::from(&r)
                .and(&top)
                .map_collect(|&r, &t| if t > 0.0 { r / t } else { 0.0 })
        })
        .collect()
}

/// Whether a valid image value `v` is image-shadowed: I/g/Ī_k below `threshold` (g the
/// observation's gain, Ī_k its own mean reflectance, [`own_mean`]). A shadow is dark against
/// its own image's illumination: measured against the mean of all observations, a low Sun's
/// image, several times darker than a high Sun's, would have its lit slopes facing away from
/// the Sun taken for shadow. [`weights`] leaves such pixels out of E_I;
/// [`shadow_edge_factors`] looks at their neighbours.
pub(crate) fn image_shadowed(v: f64, gain: f64, own_mean: f64, threshold: f64) -> bool {
    v / gain / own_mean < threshold
}

/// The pixels next to a shadow (within one pixel, the eight neighbours) that observation `o`
/// sees valid: image-shadowed pixels as in [`image_shadowed`].
fn near_shadow(o: &super::Observation, gain: f64, own_mean: f64, threshold: f64) -> Array2<bool> {
    let (ny, nx) = o.image.dim();
    // Each row's dark pixels widened by one column to either side, then each output row the
    // union of its three neighbouring widened rows (a 3 × 3 dilation in two passes).
    let mut wide = Array2::from_elem((ny, nx), false);
    wide.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(o.image.axis_iter(Axis(0)).into_par_iter())
        .for_each(|(mut out, row)| {
            for (j, v) in row.iter().enumerate() {
                if v.is_finite() && image_shadowed(*v, gain, own_mean, threshold) {
                    for k in j.saturating_sub(1)..(j + 2).min(nx) {
                        out[k] = true;
                    }
                }
            }
        });
    let mut near = Array2::from_elem((ny, nx), false);
    near.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut out)| {
            for a in i.saturating_sub(1)..(i + 2).min(ny) {
                Zip::from(&mut out)
                    .and(wide.row(a))
                    .for_each(|n, &w| *n |= w);
            }
        });
    near
}

/// [`near_shadow`] of every observation, with its gain and own mean Ī_k.
fn near_shadows(
    pr: &Problem,
    gains: &[f64],
    own_means: &[f64],
    threshold: f64,
) -> Vec<Array2<bool>> {
    pr.observations
        .iter()
        .zip(gains)
        .zip(own_means)
        .map(|((o, &g), &m)| near_shadow(o, g, m, threshold))
        .collect()
}

/// e_k of [`edge_weights`] over the observations' footprints (their finite pixels), with a ramp
/// `width` pixels wide.
fn footprint_edges(pr: &Problem, width: f64) -> Vec<Array2<f64>> {
    let footprints: Vec<Array2<bool>> = pr
        .observations
        .iter()
        .map(|o| o.image.mapv(f64::is_finite))
        .collect();
    edge_weights(&footprints, width)
}

/// s_k(x), the shadow-edge factors, applied to the weights in place: where observation k
/// carries x (w_k > 0) within one pixel of a pixel it sees shadowed, β = `beta.0` times
/// [`low_sun_edge_factor`] of k's Sun at x if one other observation carries x with no shadow
/// of its own that near, β_all = `beta.1` if two or more do; 1 elsewhere, and 1 everywhere
/// when both are 1 (the factors off, under every Sun). Two clean observations under Suns apart in azimuth measure the slope free of
/// albedo along one direction, and k's pixel holds the other; three measure it along every
/// direction, and k's pixel then adds mostly its partial shadow. A detector pixel
/// next to a cast shadow is likely part in shadow (the shadow mask marks only the pixels
/// mostly dark), and the solver's reflectance models partial shadow only coarsely (the pixels
/// just past a shadow, its edge placed to two pixels: [`super::shadows::lit_fraction`]); before
/// it did at all, there the forward model
/// is 10–15 % of the mean brightness off, against 2–3 % elsewhere (docs/science.md, "What
/// limits several Suns"), so where another observation sees the pixel cleanly it carries the
/// pixel. A pixel no other observation sees cleanly keeps its weights: one observation's
/// results never change. `own_means` holds each observation's own mean Ī_k ([`own_mean`]).
pub fn shadow_edge_factors(
    pr: &Problem,
    gains: &[f64],
    own_means: &[f64],
    threshold: f64,
    (beta, beta_all): (f64, f64),
    weight: &mut [Array2<f64>],
) {
    if weight.len() < 2 || (beta >= 1.0 && beta_all >= 1.0) {
        return;
    }
    let near = near_shadows(pr, gains, own_means, threshold);
    // How many observations carry each pixel away from their own shadows.
    let mut clean = Array2::<u8>::zeros(weight[0].dim());
    for (w, n) in weight.iter().zip(&near) {
        Zip::from(&mut clean)
            .and(w)
            .and(n)
            .for_each(|c, &w, &n| *c = c.saturating_add(u8::from(w > 0.0 && !n)));
    }
    for ((w, n), o) in weight.iter_mut().zip(&near).zip(&pr.observations) {
        Zip::indexed(w)
            .and(n)
            .and(&clean)
            .par_for_each(|(i, j), w, &n, &c| {
                // Only where k carries the pixel: beyond its footprint its Sun is not a number.
                if n && c > 0 && *w > 0.0 {
                    let elevation = elevation_deg(&o.sun.at(i, j));
                    *w *= if c >= 2 {
                        beta_all * low_sun_edge_factor_all(elevation)
                    } else {
                        beta * low_sun_edge_factor(elevation)
                    };
                }
            });
    }
}

/// The shadow-edge factor β is taken down to this share of itself under a Sun
/// [`LOW_SUN_EDGE_DEG`]`[0]` high or lower ([`low_sun_edge_factor`]).
pub const LOW_SUN_EDGE_SHARE: f64 = 0.4;

/// The Sun elevations, degrees, between which β goes from [`LOW_SUN_EDGE_SHARE`]·β to β.
pub const LOW_SUN_EDGE_DEG: [f64; 2] = [20.0, 25.0];

/// The factor on β next to a shadow of an observation whose Sun stands `elevation_deg` above
/// the horizon at the pixel: [`LOW_SUN_EDGE_SHARE`] up to 20°, 1 from 25°, a smoothstep
/// between. A low Sun's shadows are long and their edges many, and the part-shadowed pixels
/// along them read as slopes rising towards the Sun, a crease along the shadow's edge; under
/// Suns 25° high or more the pixels on the rim's side still carry slope (docs/science.md,
/// "Several observations": β scanned again on 2026-12-07).
pub fn low_sun_edge_factor(elevation_deg: f64) -> f64 {
    low_sun_share(LOW_SUN_EDGE_SHARE, elevation_deg)
}

/// The factor on β_all next to a Sun's shadow edges, as [`low_sun_edge_factor`] with
/// [`LOW_SUN_EDGE_SHARE_ALL`] for its share.
pub fn low_sun_edge_factor_all(elevation_deg: f64) -> f64 {
    low_sun_share(LOW_SUN_EDGE_SHARE_ALL, elevation_deg)
}

/// The share of β_all kept next to the shadows of a Sun [`LOW_SUN_EDGE_DEG`]`[0]` high or
/// lower, where two or more other observations carry the pixel cleanly. Three Suns measure
/// slope free of albedo in every direction without the pixel; under a low Sun the pixels along
/// its many shadow edges, part in shadow, add a bias that the other images do not correct and
/// that sums over the craters into relief tens of pixels wide (three Suns 20° high: β_all 0.1
/// → 0.01 takes the error 6 % lower, 15° high 12 %; 25° high it gains nothing;
/// docs/science.md, "Three low Suns").
pub const LOW_SUN_EDGE_SHARE_ALL: f64 = 0.1;

/// `share` up to [`LOW_SUN_EDGE_DEG`]`[0]`, 1 from [`LOW_SUN_EDGE_DEG`]`[1]`, a smoothstep
/// between.
fn low_sun_share(share: f64, elevation_deg: f64) -> f64 {
    let [lo, hi] = LOW_SUN_EDGE_DEG;
    let t = smoothstep((elevation_deg - lo) / (hi - lo));
    share + (1.0 - share) * t
}

/// Where an observation sees a pixel in shadow, or next to its own shadow, the pixel is still
/// one it sees: a shadow bounds the heights ([`super::shadows`]), and the pixel next to one is
/// left to the other observations only because the model's partial shadow is coarse. The
/// regularisers (the several-observation membrane, δ·f and the pixel-scale shrink) count such
/// an observation towards
/// their multi-coverage, so that a crater floor a low Sun shadows and a high Sun alone carries
/// is not flattened as under one observation
/// ([`super::objective::Objective::with_shadow_cover`]; docs/science.md, "A low and a high
/// Sun").
#[derive(Debug, Clone)]
pub struct ShadowCover {
    /// max(0, c_full − c) at the pixels some observation sees shadowed or carries within one
    /// pixel of its own shadow, 0 elsewhere: c_full = min(1, Σ_k u'_k/max_{k carrying} u'_k
    /// − 1), u'_k = e_k·τ_k (edge ramp and incidence taper, without the shadow-edge factor)
    /// where k carries the pixel (w_k > 0), κ·e_k·τ_k where k sees it shadowed (within the
    /// incidence selection), c the multi-coverage of [`Weights::multiplicity`].
    pub extra: Array2<f64>,
    /// Where observation k carries the pixel away from its own shadows (w_k > 0, not within
    /// one pixel of one): the observations whose photometric stiffness decides how much of
    /// `extra` the regularisers take.
    pub clean: Vec<Array2<bool>>,
}

/// The [`ShadowCover`] of a problem with weights `w` and their multi-coverage `c`
/// ([`Weights::multiplicity`]), Ī = `scale`, the shadow threshold and edge ramp width
/// `(threshold, edge_ramp_px)` of [`weights`] and κ = `kappa`. `None` with one observation,
/// κ = 0, or where no pixel gains coverage.
pub fn shadow_cover(
    pr: &Problem,
    (w, c): (&Weights, &Array2<f64>),
    scale: f64,
    (threshold, edge_ramp_px): (f64, f64),
    kappa: f64,
) -> Option<ShadowCover> {
    let n = pr.observations.len();
    if n < 2 || kappa <= 0.0 {
        return None;
    }
    let own_means: Vec<f64> = w.noise.iter().map(|&nu| own_mean(scale, nu)).collect();
    let near = near_shadows(pr, &w.gains, &own_means, threshold);
    let edges = footprint_edges(pr, edge_ramp_px);
    let sel = pr.selection;
    let extra = Zip::indexed(c).par_map_collect(|(i, j), &c| {
        let (mut sum, mut top, mut dark) = (0.0_f64, 0.0_f64, false);
        for (k, o) in pr.observations.iter().enumerate() {
            let inc = incidence_deg(&o.sun.at(i, j));
            let u = edges[k][(i, j)] * incidence_taper(inc, sel.max_incidence_deg);
            if w.weight[k][(i, j)] > 0.0 {
                sum += u;
                top = top.max(u);
                dark |= near[k][(i, j)];
            } else {
                let v = o.image[(i, j)];
                if v.is_finite()
                    && image_shadowed(v, w.gains[k], own_means[k], threshold)
                    && sel.admits(inc)
                {
                    sum += kappa * u;
                    dark = true;
                }
            }
        }
        if !dark || top <= 0.0 {
            return 0.0;
        }
        ((sum / top - 1.0).min(1.0) - c).max(0.0)
    });
    if extra.iter().all(|&x| x == 0.0) {
        return None;
    }
    let clean = w
        .weight
        .iter()
        .zip(&near)
        .map(|(wk, nk)| Zip::from(wk).and(nk).map_collect(|&w, &n| w > 0.0 && !n))
        .collect();
    Some(ShadowCover { extra, clean })
}

/// ν_k = Ī/Ī_k: the noise weight of an observation whose mean reflectance (over its valid
/// pixels, divided by its gain) is `mean`, against the mean Ī = `scale` of all (the residuals
/// of E_I are in units of Ī).
///
/// The weight is the inverse variance of an image's error. With the variance proportional to
/// the signal (a photon-limited detector: shot noise) it is Ī/Ī_k; a fixed relative error
/// would give (Ī/Ī_k)², a fixed absolute one 1. Measured on the synthetic scenes (whose noise
/// is a fixed fraction of each image's mean, so that (Ī/Ī_k)² is what the noise alone asks
/// for), Ī/Ī_k does as well where the images are about equally bright and far better where
/// one Sun is low: 105°/30° with 100°/10° added went from 1.03–1.07× the 30° image alone to
/// 0.94–0.95×, because a low Sun's photometric model error (cast and partial shadows, grazing
/// incidence) grows faster than its brightness falls (docs/science.md, "Several
/// observations").
pub fn noise_weight(scale: f64, mean: f64) -> f64 {
    scale / mean
}

/// Ī_k = Ī/ν_k: the mean reflectance of an observation (divided by its gain) whose noise
/// weight is `nu`, the inverse of [`noise_weight`] (`scale` itself if ν is not positive).
/// Its shadow test compares each pixel with it: I/g/Ī_k below the shadow threshold is shadow.
pub fn own_mean(scale: f64, nu: f64) -> f64 {
    if nu > 0.0 {
        scale / nu
    } else {
        scale
    }
}

/// The usable pixels and weights of every observation, with the given gains g_k, scale Ī,
/// noise weights ν_k (`None`: [`noise_weight`] of each observation's mean; each observation's
/// shadows are found against its own mean Ī/ν_k, [`own_mean`]) and shadow-edge
/// factors (β, β_all) ([`shadow_edge_factors`]; 1: none).
pub fn weights(
    pr: &Problem,
    gains: Vec<f64>,
    scale: f64,
    noise: Option<Vec<f64>>,
    shadow_threshold: f64,
    edge_ramp_px: f64,
    shadow_edge_weight: (f64, f64),
) -> Weights {
    let noise = match noise {
        Some(n) => n,
        None if pr.observations.len() == 1 => vec![1.0],
        None => pr
            .observations
            .iter()
            .zip(&gains)
            .map(|(o, &g)| {
                let (s, n) = o.valid_sum(g);
                if n == 0 {
                    1.0
                } else {
                    noise_weight(scale, s / n as f64)
                }
            })
            .collect(),
    };
    // Ī_k, each observation's own mean brightness, which ν_k was computed from: its shadows
    // are dark against its own illumination, not against the other observations'.
    let own_means: Vec<f64> = noise.iter().map(|&nu| own_mean(scale, nu)).collect();
    let sel = pr.selection;
    let mut usable: Vec<Array2<bool>> = pr
        .observations
        .iter()
        .zip(&gains)
        .zip(&own_means)
        .map(|((o, &g), &m)| {
            Zip::indexed(&o.image).par_map_collect(|(i, j), &v| {
                let inc = incidence_deg(&o.sun.at(i, j));
                v.is_finite()
                    && v > 0.0
                    && !image_shadowed(v, g, m, shadow_threshold)
                    && sel.admits(inc)
            })
        })
        .collect();
    // An observation coarser than the grid models each pixel from its neighbours too: it uses a
    // pixel only where all of them are usable ([`super::blur`]).
    for (k, u) in usable.iter_mut().enumerate() {
        if let Some(kernel) = pr.blur_kernel(k) {
            *u = super::blur::erode(u, kernel.radius());
        }
    }
    let edges = footprint_edges(pr, edge_ramp_px);
    let mut weight: Vec<Array2<f64>> = pr
        .observations
        .iter()
        .zip(&usable)
        .zip(&edges)
        .zip(&noise)
        .map(|(((o, u), e), &nu)| {
            Zip::indexed(u).and(e).par_map_collect(|(i, j), &u, &e| {
                if u {
                    nu * e * incidence_taper(incidence_deg(&o.sun.at(i, j)), sel.max_incidence_deg)
                } else {
                    0.0
                }
            })
        })
        .collect();
    shadow_edge_factors(
        pr,
        &gains,
        &own_means,
        shadow_threshold,
        shadow_edge_weight,
        &mut weight,
    );
    if sel.max_per_pixel > 0 && pr.observations.len() > sel.max_per_pixel {
        keep_best(pr, &mut usable, &mut weight, sel.max_per_pixel);
    }
    let weight: Vec<Array2<f32>> = weight.iter().map(|w| w.mapv(|w| w as f32)).collect();
    for (u, w) in usable.iter_mut().zip(&weight) {
        Zip::from(u).and(w).for_each(|u, &w| *u &= w > 0.0);
    }
    let lit = vec![None; weight.len()];
    Weights {
        usable,
        weight,
        gains,
        noise,
        lit,
    }
}

/// Keep, at each pixel, the `m` observations of largest w_k·μ_k (ties: the first listed).
fn keep_best(pr: &Problem, usable: &mut [Array2<bool>], weight: &mut [Array2<f64>], m: usize) {
    let (ny, nx) = usable[0].dim();
    // An observation coarser than the grid measures one slope per s² grid pixels (its pixel's
    // area, s² = 1 + 4σ² from σ² = (s² − 1)/4, [`super::blur::sigma_px`]): its score is divided
    // by it, so that a sharp observation is kept before a coarse one of the same weight.
    let area: Vec<f64> = (0..pr.observations.len())
        .map(|k| 1.0 + 4.0 * pr.blur_sigma(k).powi(2))
        .collect();
    for i in 0..ny {
        for j in 0..nx {
            let mut score: Vec<(f64, usize)> = weight
                .iter()
                .enumerate()
                .filter(|(_, w)| w[(i, j)] > 0.0)
                .map(|(k, w)| (w[(i, j)] * pr.observations[k].view.at(i, j)[2] / area[k], k))
                .collect();
            if score.len() <= m {
                continue;
            }
            score.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            for &(_, k) in &score[m..] {
                usable[k][(i, j)] = false;
                weight[k][(i, j)] = 0.0;
            }
        }
    }
}

/// The joint albedo at each pixel on surface `z`: ρ minimising Σ_k w_k (I_k/g_k − R_k(ρ))² over
/// the observations usable there, by Gauss–Newton in ρ from the weighted mean of the
/// per-observation inversions (one observation: its inversion, exactly). An observation
/// coarser than the grid ([`super::blur`]) weighs w_k·`blurred_weight` where a sharp one is
/// used as well. Returns ρ, where it is defined, and the weight Σ_k w_k·(I_k/g_k)² of the
/// pixel's data.
pub fn invert_albedo(
    pr: &Problem,
    w: &Weights,
    z: ArrayView2<f64>,
    blurred_weight: f64,
) -> (Array2<f64>, Array2<bool>, Array2<f64>) {
    let z = z.as_standard_layout();
    let dim = z.dim();
    let model: &dyn ReflectanceModel = pr.model;
    let mut rho = Array2::zeros(dim);
    let mut ok = Array2::from_elem(dim, false);
    let mut strength = Array2::zeros(dim);
    // An observation coarser than the grid sees the albedo blurred: where a sharp one is used,
    // its weight is w_k·`blurred_weight` ([`super::blur`]).
    let blurred: Vec<bool> = (0..pr.observations.len())
        .map(|k| pr.blur_sigma(k) > 0.0)
        .collect();
    rho.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(ok.axis_iter_mut(Axis(0)))
        .zip(strength.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(i, ((mut rrow, mut orow), mut srow))| {
            // (w_k, I_k/g_k, R_k as a function of the albedo) of the observations usable here.
            let mut data: Vec<(f64, f64, AlbedoCurve)> = Vec::new();
            // The row's slopes (no slope arrays of the grid's size).
            let (mut p, mut q) = (vec![0.0; dim.1], vec![0.0; dim.1]);
            super::ops::gradient_row(z.view(), pr.spacing, i, &mut p, &mut q);
            for j in 0..dim.1 {
                data.clear();
                let (pp, qq) = (p[j], q[j]);
                let (mut sw, mut swr, mut s2) = (0.0, 0.0, 0.0);
                let sharp = (0..blurred.len()).any(|k| !blurred[k] && w.weight[k][(i, j)] > 0.0);
                for (k, o) in pr.observations.iter().enumerate() {
                    let mut wk = f64::from(w.weight[k][(i, j)]);
                    if sharp && blurred[k] {
                        wk *= blurred_weight;
                    }
                    if wk <= 0.0 {
                        continue;
                    }
                    // Part in shadow (f < 1): I/g = f·R, so R = I/(g f), weighed f².
                    let f = w.lit_at(k, (i, j));
                    wk *= f * f;
                    let ik = o.image[(i, j)] / w.gains[k] / f;
                    let Some(g) = incidence(pp, qq, &o.sun.at(i, j), &o.view.at(i, j)) else {
                        continue;
                    };
                    // R_k(ρ) at this pixel's slope: the albedo-free factors once per
                    // observation, for its own inversion (ReflectanceModel::invert_cosines,
                    // bit for bit) and for every joint Gauss–Newton step.
                    let curve = model.albedo_curve(&g.cos);
                    if let Albedo::Value(r) = curve.invert(ik) {
                        sw += wk;
                        swr += wk * r;
                        s2 += wk * ik * ik;
                        data.push((wk, ik, curve));
                    }
                }
                if data.is_empty() {
                    continue;
                }
                let mut r = swr / sw;
                if data.len() > 1 {
                    for _ in 0..4 {
                        let (mut num, mut den) = (0.0, 0.0);
                        for (wk, ik, curve) in &data {
                            let (f0, jac) = curve.eval(r);
                            num += wk * jac * (ik - f0);
                            den += wk * jac * jac;
                        }
                        if den <= 0.0 {
                            break;
                        }
                        let step = num / den;
                        r = (r + step).clamp(1e-6, 0.999);
                        if step.abs() < 1e-7 {
                            break;
                        }
                    }
                }
                rrow[j] = r;
                orow[j] = true;
                srow[j] = s2;
            }
        });
    (rho, ok, strength)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A range is admitted where any incidence in it is: the window [50°, 58°) takes a Sun at
    /// 55° and one ranging 40–50° (50 is in), not one at 60°, one ranging 58.1–70° (58 is
    /// out) or one ranging 20–49.9°.
    #[test]
    fn a_window_admits_a_range_where_it_admits_some_incidence_of_it() {
        let sel = Selection {
            min_incidence_deg: 50.0,
            max_incidence_deg: 58.0,
            ..Selection::default()
        };
        for (range, admitted) in [
            ([55.0, 55.0], true),
            ([40.0, 50.0], true),
            ([60.0, 60.0], false),
            ([58.1, 70.0], false),
            ([20.0, 49.9], false),
        ] {
            assert_eq!(sel.admits_some_of(range), admitted, "{range:?}");
        }
    }

    /// [`weights`] of a problem of two observations, gains and noise weights 1, Ī = 0.03,
    /// shadow threshold 0.1, no edge ramp, shadow-edge factors `beta` (β, β_all).
    fn pair_weights(pr: &Problem, beta: (f64, f64)) -> Weights {
        unit_weights(pr, beta)
    }

    /// [`weights`] as [`pair_weights`], for any number of observations.
    fn unit_weights(pr: &Problem, beta: (f64, f64)) -> Weights {
        let n = pr.observations.len();
        weights(pr, vec![1.0; n], 0.03, Some(vec![1.0; n]), 0.1, 0.0, beta)
    }

    /// A problem of `images` (each with its Sun's zenith and azimuth, degrees) seen from
    /// nadir, over `dem` at 100 m pixels.
    fn uniform_problem<'a>(
        images: &[(&'a Array2<f64>, f64, f64)],
        dem: &'a Array2<f64>,
        model: &'a dyn ReflectanceModel,
    ) -> Problem<'a> {
        use crate::fusion::{Directions, Observation};
        let towards =
            |zenith, azimuth| Directions::Uniform(crate::synth::direction(zenith, azimuth));
        let mut pr = Problem::single(
            images[0].0.view(),
            towards(images[0].1, images[0].2),
            towards(0.0, 0.0),
            dem.view(),
            100.0,
            0.0,
            model,
        );
        for &(image, zenith, azimuth) in &images[1..] {
            pr.observations.push(Observation {
                image: image.view(),
                sun: towards(zenith, azimuth),
                view: towards(0.0, 0.0),
            });
        }
        pr
    }

    /// A Sun at azimuth `az` (clockwise from north) and elevation `el`, degrees, in the grid
    /// frame (x east, y north, z up).
    fn sun(az: f64, el: f64) -> Vec3 {
        crate::synth::direction(90.0 - el, az)
    }

    /// Suns mirrored about the east–west line measure no east–west slope free of albedo,
    /// Suns mirrored about the north–south line nothing else; three Suns 120° apart at one
    /// elevation measure both alike; and the share does not depend on the elevation of two
    /// Suns in mirror image (analytic cases of `east_west_share`).
    #[test]
    fn the_east_west_share_of_mirrored_and_spread_suns() {
        let share = |s: &[(f64, f64)]| {
            east_west_share(&s.iter().map(|&(a, e)| sun(a, e)).collect::<Vec<_>>()).unwrap()
        };
        assert!(share(&[(45.0, 30.0), (135.0, 30.0)]) < 1e-12);
        assert!(share(&[(315.0, 55.0), (225.0, 55.0)]) < 1e-12);
        assert!((share(&[(90.0, 30.0), (270.0, 30.0)]) - 1.0).abs() < 1e-12);
        assert!((share(&[(0.0, 40.0), (120.0, 40.0), (240.0, 40.0)]) - 0.5).abs() < 1e-12);
        // 105/30 + 225/35: g₁ − g₂ mostly east–west.
        assert!(share(&[(105.0, 30.0), (225.0, 35.0)]) > 0.9);
        assert!(east_west_share(&[sun(90.0, 30.0)]).is_none());
        assert!(east_west_share(&[sun(90.0, 30.0), sun(90.0, 30.0)]).is_none());
    }

    /// ψ: 0 for Suns mirrored about the east–west line and for one Sun, 1 for a pair whose
    /// difference runs east–west, and at a share halfway between s₀ and s₁ the smoothstep's
    /// middle, 1/2 (Sun vectors built from chosen g_k = −(s_x, s_y)/s_z), whatever the two
    /// weights; an observation of u_k = 0 does not count; three Suns spread in azimuth: 1; under
    /// low Suns it fades with the mean cot² of their elevations.
    #[test]
    fn the_east_west_opening_follows_the_share_of_albedo_free_slope() {
        let psi = |s: &[(f64, f64, f64)]| {
            east_west_open_at(&mut s.iter().map(|&(u, a, e)| (u, sun(a, e))))
        };
        assert_eq!(psi(&[(1.0, 45.0, 30.0), (1.0, 135.0, 30.0)]), 0.0);
        assert_eq!(psi(&[(1.0, 45.0, 20.0), (0.3, 135.0, 20.0)]), 0.0);
        assert_eq!(psi(&[(1.0, 105.0, 30.0)]), 0.0);
        assert_eq!(psi(&[(1.0, 105.0, 30.0), (0.0, 225.0, 35.0)]), 0.0);
        assert_eq!(psi(&[(1.0, 105.0, 30.0), (1.0, 225.0, 35.0)]), 1.0);
        assert_eq!(psi(&[(1.0, 90.0, 30.0), (1.0, 270.0, 50.0)]), 1.0);
        let from_g = |gx: f64, gy: f64| {
            let n = (gx * gx + gy * gy + 1.0).sqrt();
            [-gx / n, -gy / n, 1.0 / n]
        };
        let [s0, s1] = EAST_WEST_OPEN_SHARE;
        let share: f64 = 0.5 * (s0 + s1);
        let (dx, dy) = (share.sqrt(), (1.0 - share).sqrt());
        let pair = [(0.7, from_g(0.0, 0.5)), (0.7, from_g(-dx, 0.5 - dy))];
        assert!((east_west_open_at(&mut pair.into_iter()) - 0.5).abs() < 1e-12);
        // Two observations: M = u₁u₂/(u₁ + u₂)·d dᵀ whatever the weights, so the share, and ψ,
        // stay.
        let unequal = [(0.2, from_g(0.0, 0.5)), (0.9, from_g(-dx, 0.5 - dy))];
        assert!((east_west_open_at(&mut unequal.into_iter()) - 0.5).abs() < 1e-12);
        assert!(psi(&[(1.0, 0.0, 30.0), (1.0, 120.0, 40.0), (1.0, 240.0, 40.0)]) == 1.0);
        // Low Suns: 315/20 + 45/20 (cot² 20° = 7.55) measure east–west slopes but get 0; Suns
        // east and west whose mean cot² lies halfway between m₀ and m₁ get 1/2.
        assert_eq!(psi(&[(1.0, 315.0, 20.0), (1.0, 45.0, 20.0)]), 0.0);
        let [m0, m1] = EAST_WEST_LOW_SUN_COT2;
        let g = (0.5 * (m0 + m1)).sqrt();
        let halfway = [(1.0, from_g(g, 0.0)), (1.0, from_g(-g, 0.0))];
        assert!((east_west_open_at(&mut halfway.into_iter()) - 0.5).abs() < 1e-12);
    }

    /// χ, analytic cases: two Suns mirrored about the north–south line leave no east–west
    /// slope unmeasured (their bisector, the blind direction, runs north–south: 0), mirrored
    /// about the east–west line all of it (1); Suns 90° apart with the bisector to the
    /// south-east half (the blind direction 45° from east: cos² 45°); one Sun, or two alike,
    /// measure nothing free of albedo (1); three Suns 120° apart at one elevation measure every
    /// direction (0). Two Suns 0/40 + 90/40 at unequal weights: M = u₁u₂/(u₁ + u₂)·d dᵀ keeps
    /// its eigenvectors, so χ = 1/2 whatever the weights.
    #[test]
    fn the_unmeasured_east_west_part_is_the_blind_directions() {
        let chi = |s: &[(f64, f64, f64)]| {
            east_west_unmeasured_at(&mut s.iter().map(|&(u, a, e)| (u, sun(a, e))))
        };
        assert!(chi(&[(1.0, 110.0, 55.0), (1.0, 250.0, 55.0)]) < 1e-12);
        assert!((chi(&[(1.0, 45.0, 55.0), (1.0, 135.0, 55.0)]) - 1.0).abs() < 1e-12);
        assert!((chi(&[(1.0, 90.0, 55.0), (1.0, 180.0, 55.0)]) - 0.5).abs() < 1e-9);
        assert!((chi(&[(0.2, 0.0, 40.0), (0.9, 90.0, 40.0)]) - 0.5).abs() < 1e-9);
        assert_eq!(chi(&[(1.0, 105.0, 30.0)]), 1.0);
        assert_eq!(chi(&[(1.0, 105.0, 30.0), (0.0, 225.0, 35.0)]), 1.0);
        assert_eq!(chi(&[(1.0, 105.0, 30.0), (1.0, 105.0, 30.0)]), 1.0);
        assert!(chi(&[(1.0, 0.0, 50.0), (1.0, 120.0, 50.0), (1.0, 240.0, 50.0)]) < 1e-12);
        // The example's high Suns at their own elevations: the blind direction nearly north–south.
        assert!(chi(&[(1.0, 110.0, 55.0), (1.0, 250.0, 60.0)]) < EAST_WEST_UNMEASURED[0]);
    }

    /// φ against hand-computed eigenvalues of M: three Suns 120° apart at 30° (λ = 1.5·cot² 30°
    /// = 4.5 twice: φ = 4.5/4.55); two Suns, or three with one shadowed (u = 0) or below the
    /// horizon: 0; 45/30 + 135/30 + 90/60 (λ_min/λ_max = 0.093): 0; 0/40 + 90/40 + 180/40
    /// (M = cot² 40°·diag(2/3, 2), ratio 1/3: (1/3 − 0.2)/0.4 = 1/3 of λ_min/(λ_min + m₀)).
    /// Three Suns 20° high or lower: 0, 25° or higher: all of it ([`EVERY_DIRECTION_SUN_DEG`]).
    #[test]
    fn every_direction_needs_suns_spread_in_azimuth() {
        let phi = |s: &[(f64, f64, f64)]| {
            every_direction_at(&mut s.iter().map(|&(u, a, e)| (u, sun(a, e))))
        };
        let even = phi(&[(1.0, 0.0, 30.0), (1.0, 120.0, 30.0), (1.0, 240.0, 30.0)]);
        assert!((even - 4.5 / 4.55).abs() < 1e-12, "{even}");
        // u scales M: halving every u halves λ.
        let half = phi(&[(0.5, 0.0, 30.0), (0.5, 120.0, 30.0), (0.5, 240.0, 30.0)]);
        assert!((half - 2.25 / 2.3).abs() < 1e-12, "{half}");
        assert_eq!(phi(&[(1.0, 0.0, 30.0), (1.0, 120.0, 30.0)]), 0.0);
        assert_eq!(
            phi(&[(1.0, 0.0, 30.0), (1.0, 120.0, 30.0), (0.0, 240.0, 30.0)]),
            0.0
        );
        assert_eq!(
            phi(&[(1.0, 0.0, 30.0), (1.0, 120.0, 30.0), (1.0, 240.0, -5.0)]),
            0.0
        );
        assert_eq!(
            phi(&[(1.0, 45.0, 30.0), (1.0, 135.0, 30.0), (1.0, 90.0, 60.0)]),
            0.0
        );
        let k = (40f64.to_radians().tan()).powi(-2);
        let lo = 2.0 / 3.0 * k;
        let quarter = phi(&[(1.0, 0.0, 40.0), (1.0, 90.0, 40.0), (1.0, 180.0, 40.0)]);
        assert!((quarter - (1.0 / 3.0) * lo / (lo + EVERY_DIRECTION_M0)).abs() < 1e-12);
        // Under low Suns the images do not take over: three 20° Suns give 0, three 25° Suns
        // φ in full (λ = 1.5·cot² 25°), three at 22.5° half of it (the smoothstep's middle).
        let at = |e: f64| phi(&[(1.0, 0.0, e), (1.0, 120.0, e), (1.0, 240.0, e)]);
        let full = |e: f64| {
            let l = 1.5 * (e.to_radians().tan()).powi(-2);
            l / (l + EVERY_DIRECTION_M0)
        };
        assert_eq!(at(15.0), 0.0);
        assert!(at(20.0) < 1e-12, "{}", at(20.0));
        assert!((at(25.0) - full(25.0)).abs() < 1e-12);
        assert!((at(22.5) - 0.5 * full(22.5)).abs() < 1e-12);
    }

    /// η by hand: two Suns at 60° and 55° (cot² = 1/3, 0.49): 1; at 45° (cot² = 1): (1.2 −
    /// 1)/0.6 = 1/3; at 30° and 35°: 0; a Sun at 30° with u = 1 and one at 60° with u = 3:
    /// mean cot² (3 + 1)/4 = 1: 1/3; a shadowed (u = 0) or set Sun does not count.
    #[test]
    fn high_sun_follows_the_mean_cot2_of_the_elevations() {
        let eta =
            |s: &[(f64, f64, f64)]| high_sun_at(&mut s.iter().map(|&(u, a, e)| (u, sun(a, e))));
        assert_eq!(eta(&[(1.0, 110.0, 55.0), (1.0, 250.0, 60.0)]), 1.0);
        assert!((eta(&[(1.0, 0.0, 45.0), (1.0, 120.0, 45.0)]) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(eta(&[(1.0, 105.0, 30.0), (1.0, 225.0, 35.0)]), 0.0);
        assert!((eta(&[(1.0, 105.0, 30.0), (3.0, 225.0, 60.0)]) - 1.0 / 3.0).abs() < 1e-12);
        assert_eq!(eta(&[(1.0, 0.0, 60.0), (0.0, 120.0, 10.0)]), 1.0);
        assert_eq!(eta(&[(1.0, 0.0, 60.0), (1.0, 120.0, -5.0)]), 1.0);
        assert_eq!(eta(&[(0.0, 0.0, 60.0)]), 0.0);
        // The wider ramp where the images see east–west slopes: 45° Suns (cot² = 1) at
        // (1.6 − 1)/(1.6 − 0.6) = 0.6; 40° (cot² 40° = 1.42) at 0.18; 38° and lower none.
        let wide = |e: f64| {
            let c = e.to_radians().tan().powi(-2);
            high_sun_ramp(c, HIGH_SUN_EAST_WEST_COT2)
        };
        assert!((wide(45.0) - 0.6).abs() < 1e-12);
        assert!((wide(40.0) - 0.18).abs() < 0.005);
        assert_eq!(wide(38.0), 0.0);
        assert_eq!(high_sun_ramp(f64::NAN, HIGH_SUN_EAST_WEST_COT2), 0.0);
    }

    /// Suns alike: within 5° of one another, every pair (analytic angles: 4° and 6° apart in
    /// azimuth on the horizon's 0° elevation are 4° and 6° apart).
    #[test]
    fn suns_within_five_degrees_are_alike() {
        let v = |s: &[(f64, f64)]| s.iter().map(|&(a, e)| sun(a, e)).collect::<Vec<_>>();
        assert!(suns_alike(&v(&[(90.0, 30.0)])));
        assert!(suns_alike(&v(&[(90.0, 30.0), (90.0, 30.0)])));
        assert!(suns_alike(&v(&[(90.0, 0.0), (94.0, 0.0)])));
        assert!(!suns_alike(&v(&[(90.0, 0.0), (96.0, 0.0)])));
        // Each neighbour within 5°, the outer two 8° apart: not alike.
        assert!(!suns_alike(&v(&[(90.0, 0.0), (94.0, 0.0), (98.0, 0.0)])));
        // 105/30 and 110/32: 4.7° apart.
        assert!(suns_alike(&v(&[(105.0, 30.0), (110.0, 32.0)])));
        assert!(!suns_alike(&v(&[(105.0, 30.0), (120.0, 30.0)])));
    }

    #[test]
    fn edge_weights_fade_an_observation_in_only_where_another_carries_on() {
        // Observation 0 covers columns 0..40, observation 1 columns 20..60 of a 60-column grid.
        let f0 = Array2::from_shape_fn((10, 60), |(_, j)| j < 40);
        let f1 = Array2::from_shape_fn((10, 60), |(_, j)| j >= 20);
        let e = edge_weights(&[f0, f1], 8.0);
        // Alone: full weight, up to its edge.
        assert_eq!(e[0][(5, 0)], 1.0);
        assert_eq!(e[0][(5, 19)], 1.0);
        assert_eq!(e[1][(5, 59)], 1.0);
        // Inside the overlap, next to 0's edge (column 39), 0 fades while 1 is full.
        assert!(e[0][(5, 39)] < 0.05 && e[1][(5, 39)] == 1.0);
        assert!(e[0][(5, 35)] > e[0][(5, 38)]);
        assert_eq!(e[0][(5, 30)], 1.0);
        // Off its footprint an observation has no weight.
        assert_eq!(e[0][(5, 45)], 0.0);
    }

    /// Observation 0 sees a 3 × 3 shadow at rows/columns 5..8 and another at 14..17, where
    /// observation 1 has no data (rows 13 on); observation 1 sees a shadow at rows 5..8,
    /// columns 9..11. With β = 0.25, 0's weight drops to β exactly on the eight-neighbour ring
    /// of its first shadow where 1 sees the pixel cleanly, and nowhere else.
    /// Where one observation sees a block shadowed and another carries it, the block gains κ
    /// of an observation and the ring beside it (where the shadow-edge factor β = 0.25 left
    /// c = 0.25) the rest up to 1; nothing elsewhere, nothing with κ = 0 or one observation
    /// (analytic values of `shadow_cover`).
    #[test]
    fn a_shadow_and_its_edge_count_towards_the_coverage_where_another_observation_carries_them() {
        use crate::photometry::Hapke;
        let n = 16;
        let a = Array2::from_shape_fn((n, n), |(i, j)| {
            if (6..9).contains(&i) && (6..9).contains(&j) {
                1e-4
            } else {
                0.03
            }
        });
        let b = Array2::from_elem((n, n), 0.03);
        let dem = Array2::zeros((n, n));
        let model = Hapke::moon();
        let mut pr = uniform_problem(&[(&a, 40.0, 100.0), (&b, 45.0, 250.0)], &dem, &model);
        let w = pair_weights(&pr, (0.25, 0.1));
        let cover = shadow_cover(&pr, (&w, &w.multiplicity()), 0.03, (0.1, 0.0), 0.7).unwrap();
        for i in 0..n {
            for j in 0..n {
                let block = (6..9).contains(&i) && (6..9).contains(&j);
                let ring = !block && (5..10).contains(&i) && (5..10).contains(&j);
                let expected = if block {
                    0.7
                } else if ring {
                    0.75
                } else {
                    0.0
                };
                assert!(
                    (cover.extra[(i, j)] - expected).abs() < 1e-6,
                    "({i}, {j}): {} against {expected}",
                    cover.extra[(i, j)]
                );
                // The clean carriers: 1 everywhere, 0 away from its shadow's ring.
                assert!(cover.clean[1][(i, j)]);
                assert_eq!(cover.clean[0][(i, j)], !block && !ring, "({i}, {j})");
            }
        }
        assert!(shadow_cover(&pr, (&w, &w.multiplicity()), 0.03, (0.1, 0.0), 0.0).is_none());
        pr.observations.truncate(1);
        let one = weights(&pr, vec![1.0], 0.03, None, 0.1, 0.0, (0.25, 0.1));
        assert!(shadow_cover(&pr, (&one, &one.multiplicity()), 0.03, (0.1, 0.0), 0.7).is_none());
    }

    /// Under a low Sun the shadow-edge factor is lower: 0.4 of β up to 20°, all of it from
    /// 25°, the smoothstep between (0.7 of it at 22.5°). On a pixel next to observation 0's
    /// shadow that observation 1 sees cleanly, 0's weight is β·0.4 with its Sun 20° high,
    /// β·0.7 at 22.5°, β at 50°; 1's own ring, under a 45° Sun, keeps β throughout. Where a
    /// third observation sees the pixel cleanly too, β_all takes its own share, 0.1 up to 20°.
    #[test]
    fn a_low_suns_shadow_edges_weigh_less() {
        use crate::photometry::Hapke;
        assert_eq!(low_sun_edge_factor(5.0), 0.4);
        assert_eq!(low_sun_edge_factor(20.0), 0.4);
        assert!((low_sun_edge_factor(22.5) - 0.7).abs() < 1e-12);
        assert_eq!(low_sun_edge_factor(25.0), 1.0);
        assert_eq!(low_sun_edge_factor(60.0), 1.0);
        // β_all's share is 0.1: 0.1 up to 20°, 0.55 at 22.5° (the smoothstep's half), 1 from 25°.
        assert_eq!(low_sun_edge_factor_all(15.0), 0.1);
        assert_eq!(low_sun_edge_factor_all(20.0), 0.1);
        assert!((low_sun_edge_factor_all(22.5) - 0.55).abs() < 1e-12);
        assert_eq!(low_sun_edge_factor_all(25.0), 1.0);
        assert_eq!(low_sun_edge_factor_all(40.0), 1.0);
        let n = 16;
        let dark =
            |i: usize, j: usize, lo: usize| (lo..lo + 3).contains(&i) && (lo..lo + 3).contains(&j);
        let a = Array2::from_shape_fn((n, n), |(i, j)| if dark(i, j, 4) { 1e-4 } else { 0.03 });
        let b = Array2::from_shape_fn((n, n), |(i, j)| if dark(i, j, 10) { 1e-4 } else { 0.03 });
        let dem = Array2::zeros((n, n));
        let model = Hapke::moon();
        for (elevation, share) in [(20.0, 0.4), (22.5, 0.7), (50.0, 1.0)] {
            let pr = uniform_problem(
                &[(&a, 90.0 - elevation, 100.0), (&b, 45.0, 250.0)],
                &dem,
                &model,
            );
            let w = pair_weights(&pr, (0.25, 0.1));
            // (3, 3) is on 0's ring, (9, 9) on 1's.
            let got = f64::from(w.weight[0][(3, 3)]);
            assert!((got - 0.25 * share).abs() < 1e-6, "{elevation}°: {got}");
            assert_eq!(w.weight[1][(9, 9)], 0.25, "{elevation}°");
            // A third observation that sees every pixel cleanly: 0's ring is now carried by two
            // others, and 0 keeps β_all times its own share there.
            let c = Array2::from_elem((n, n), 0.03);
            let pr = uniform_problem(
                &[
                    (&a, 90.0 - elevation, 100.0),
                    (&b, 45.0, 250.0),
                    (&c, 45.0, 10.0),
                ],
                &dem,
                &model,
            );
            let w = unit_weights(&pr, (0.25, 0.1));
            let got = f64::from(w.weight[0][(3, 3)]);
            let share_all = low_sun_edge_factor_all(elevation);
            assert!(
                (got - 0.1 * share_all).abs() < 1e-6,
                "{elevation}°, three: {got}"
            );
            assert_eq!(w.weight[1][(9, 9)], 0.1, "{elevation}°, three");
        }
        // Observation 0 ends at column 7, its Sun per pixel and not a number beyond (as an
        // ingested swath's): the ring of its shadow at columns 4..7 reaches column 7, where
        // it does not carry the pixel, and every weight stays a number.
        let edge =
            Array2::from_shape_fn((n, n), |(i, j)| if j >= 7 { f64::NAN } else { a[(i, j)] });
        let sun = Array2::from_shape_fn((n, n), |(_, j)| {
            let s = crate::synth::direction(70.0, 100.0).map(|x| x as f32);
            if j >= 7 {
                [f32::NAN; 3]
            } else {
                s
            }
        });
        let mut pr = uniform_problem(&[(&edge, 70.0, 100.0), (&b, 45.0, 250.0)], &dem, &model);
        pr.observations[0].sun = crate::fusion::Directions::PerPixel(sun.view().into());
        let w = pair_weights(&pr, (0.25, 0.1));
        assert!(w.weight.iter().all(|w| w.iter().all(|x| x.is_finite())));
        assert_eq!(w.weight[0][(5, 7)], 0.0);
        assert!((f64::from(w.weight[0][(5, 3)]) - 0.1).abs() < 1e-6);
    }

    #[test]
    fn a_pixel_next_to_a_shadow_weighs_less_only_where_another_observation_sees_it_cleanly() {
        use crate::photometry::Hapke;
        let n = 20;
        let lit = |i: usize, j: usize| 0.03 + 0.001 * ((i + 2 * j) % 3) as f64;
        let a = Array2::from_shape_fn((n, n), |(i, j)| {
            let block = |lo: usize| (lo..lo + 3).contains(&i) && (lo..lo + 3).contains(&j);
            if block(5) || block(14) {
                1e-4
            } else {
                lit(i, j)
            }
        });
        let b = Array2::from_shape_fn((n, n), |(i, j)| {
            if i >= 13 {
                f64::NAN
            } else if (5..8).contains(&i) && (9..11).contains(&j) {
                1e-4
            } else {
                lit(j, i)
            }
        });
        let dem = Array2::zeros((n, n));
        let model = Hapke::moon();
        let mut pr = uniform_problem(&[(&a, 40.0, 100.0), (&b, 45.0, 250.0)], &dem, &model);
        let w = |beta: f64| pair_weights(&pr, (beta, beta));
        let (full, edged) = (w(1.0), w(0.25));
        assert_eq!(full.usable, edged.usable);
        let ring = |i: usize, j: usize, lo: usize| {
            (lo - 1..lo + 4).contains(&i) && (lo - 1..lo + 4).contains(&j)
        };
        for i in 0..n {
            for j in 0..n {
                let (f0, e0) = (full.weight[0][(i, j)], edged.weight[0][(i, j)]);
                let (f1, e1) = (full.weight[1][(i, j)], edged.weight[1][(i, j)]);
                // Next to 1's shadow (rows 4..9, columns 8..12): 1 is not clean there.
                let near_b = (4..9).contains(&i) && (8..12).contains(&j);
                if f0 > 0.0 && ring(i, j, 5) && f1 > 0.0 && !near_b {
                    assert_eq!(e0, 0.25, "({i}, {j})");
                } else {
                    // Beside the second shadow 1 sees nothing; beside both shadows neither
                    // is clean; elsewhere nothing is near a shadow.
                    assert_eq!(e0, f0, "({i}, {j})");
                }
                // Next to its own shadow, 1 weighs less where 0 sees the pixel cleanly.
                if f1 > 0.0 && near_b && f0 > 0.0 && !ring(i, j, 5) {
                    assert_eq!(e1, 0.25, "({i}, {j})");
                } else {
                    assert_eq!(e1, f1, "({i}, {j})");
                }
            }
        }
        // The cases the rule leaves alone occur: beside 0's second shadow, 1 has no data; at
        // (4, 8) both observations are next to a shadow of their own; (4, 4) is the rule's.
        assert_eq!(edged.weight[0][(13, 13)], 1.0);
        assert_eq!(full.weight[1][(13, 13)], 0.0);
        assert_eq!(edged.weight[0][(4, 8)], 1.0);
        assert_eq!(edged.weight[1][(4, 8)], 1.0);
        assert_eq!(edged.weight[0][(4, 4)], 0.25);
        assert_eq!(edged.weight[1][(6, 11)], 0.25);
        // One observation: no factor anywhere.
        pr.observations.truncate(1);
        let one = weights(&pr, vec![1.0], 0.03, None, 0.1, 0.0, (0.25, 0.25));
        assert!(one.weight[0].iter().all(|&w| w == 0.0 || w == 1.0));
        assert!(one.weight[0][(4, 4)] == 1.0);
    }

    #[test]
    fn next_to_a_shadow_two_clean_observations_take_the_pixel_further() {
        use crate::photometry::Hapke;
        // Observation 0 has a 3 × 3 shadow at rows and columns 5..8; 1 sees everything lit; 2
        // sees the left half (columns < 6) lit and nothing of the right half. Around 0's
        // shadow, 0 weighs β_all where 1 and 2 both carry the pixel, β where 1 alone does.
        let n = 14;
        let lit = |i: usize, j: usize| 0.03 + 0.001 * ((i + 2 * j) % 3) as f64;
        let a = Array2::from_shape_fn((n, n), |(i, j)| {
            if (5..8).contains(&i) && (5..8).contains(&j) {
                1e-4
            } else {
                lit(i, j)
            }
        });
        let b = Array2::from_shape_fn((n, n), |(i, j)| lit(j, i));
        let c = Array2::from_shape_fn((n, n), |(i, j)| if j < 6 { lit(i, i) } else { f64::NAN });
        let dem = Array2::zeros((n, n));
        let model = Hapke::moon();
        let pr = uniform_problem(
            &[(&a, 40.0, 100.0), (&b, 40.0, 220.0), (&c, 40.0, 340.0)],
            &dem,
            &model,
        );
        let w = unit_weights(&pr, (0.25, 0.1));
        assert_eq!(w.weight[0][(4, 4)], 0.1, "1 and 2 carry (4, 4)");
        assert_eq!(w.weight[0][(4, 8)], 0.25, "only 1 carries (4, 8)");
        assert_eq!(w.weight[0][(6, 6)], 0.0, "the shadow itself is not used");
        assert_eq!(w.weight[0][(10, 10)], 1.0, "away from the shadow");
        assert_eq!(w.weight[1][(4, 4)], 1.0);
        assert_eq!(w.weight[2][(4, 4)], 1.0);
    }

    #[test]
    fn each_observation_finds_its_shadows_against_its_own_brightness() {
        use crate::photometry::Hapke;
        // A high Sun's image at 0.08 and a low Sun's 8× darker, at 0.01; in each, one pixel at
        // 30 % of its image's mean (a lit slope turned away from the Sun) and one at 5 % (a
        // shadow). Against the mean of both (≈ 0.045) the low Sun's 30 % pixel, 0.003, would be
        // under the threshold 0.1 × 0.045 and taken for shadow.
        let n = 12;
        let image = |mean: f64| {
            Array2::from_shape_fn((n, n), |(i, j)| match (i, j) {
                (3, 3) => 0.3 * mean,
                (8, 8) => 0.05 * mean,
                _ => mean,
            })
        };
        let (bright, dark) = (image(0.08), image(0.01));
        let dem = Array2::zeros((n, n));
        let model = Hapke::moon();
        let pr = uniform_problem(
            &[(&bright, 30.0, 100.0), (&dark, 65.0, 250.0)],
            &dem,
            &model,
        );
        let scale = (bright.sum() + dark.sum()) / (2 * n * n) as f64;
        let w = weights(&pr, vec![1.0, 1.0], scale, None, 0.1, 0.0, (1.0, 1.0));
        for k in 0..2 {
            assert!(
                w.usable[k][(3, 3)],
                "observation {k}: 30 % of its mean is lit"
            );
            assert!(
                !w.usable[k][(8, 8)],
                "observation {k}: 5 % of its mean is shadow"
            );
            assert!(w.usable[k][(0, 0)]);
        }
        assert!(
            0.3 * 0.01 < 0.1 * scale,
            "the dark image's lit pixel is under 0.1 Ī"
        );
        // The noise weights the plan hands the tiles give the same masks.
        let noise = w.noise.clone();
        let given = weights(
            &pr,
            vec![1.0, 1.0],
            scale,
            Some(noise),
            0.1,
            0.0,
            (1.0, 1.0),
        );
        assert_eq!(given.usable, w.usable);
    }

    /// A pixel part in shadow, lit share f, shows I = f·R(ρ): with f known the joint inversion
    /// gives ρ back (to the Gauss–Newton steps' tolerance); taken as wholly lit it would give
    /// a darker albedo.
    #[test]
    fn the_albedo_of_a_part_shadowed_pixel_is_inverted_from_its_lit_share() {
        let model = crate::photometry::Hapke::moon();
        let dem = Array2::zeros((4, 4));
        let (za, zb) = (40.0, 60.0);
        let flat = |zenith: f64| {
            let sh = model.shade_observed(0.0, 0.0, 0.3, &sun(0.0, 90.0 - zenith), &sun(0.0, 90.0));
            sh.r
        };
        // Observation 0 sees the pixel (1, 2) 70 % lit, observation 1 wholly.
        let mut a = Array2::from_elem((4, 4), flat(za));
        a[(1, 2)] *= 0.7;
        let b = Array2::from_elem((4, 4), flat(zb));
        let pr = uniform_problem(&[(&a, za, 0.0), (&b, zb, 0.0)], &dem, &model);
        let mut w = pair_weights(&pr, (1.0, 1.0));
        let (plain, _, _) = invert_albedo(&pr, &w, dem.view(), 1.0);
        assert!(plain[(1, 2)] < 0.29, "{}", plain[(1, 2)]);
        w.lit[0] = Some(Array2::from_shape_fn((4, 4), |ij| {
            if ij == (1, 2) {
                0.7
            } else {
                1.0
            }
        }));
        let (rho, ok, _) = invert_albedo(&pr, &w, dem.view(), 1.0);
        for ((ij, &r), &ok) in rho.indexed_iter().zip(&ok) {
            assert!(ok && (r - 0.3).abs() < 1e-6, "{ij:?}: {r}");
        }
    }

    #[test]
    fn incidence_taper_fades_over_the_last_ten_degrees() {
        assert_eq!(incidence_taper(70.0, 90.0), 1.0);
        assert_eq!(incidence_taper(80.0, 90.0), 1.0);
        assert!((incidence_taper(85.0, 90.0) - 0.5).abs() < 1e-12);
        assert_eq!(incidence_taper(90.0, 90.0), 0.0);
    }
}
