//! Cast shadows as height constraints (E_S, docs/science.md "Cast shadows").
//!
//! A pixel an observation sees in shadow lies below the Sun's horizon: walking from it
//! towards the Sun, some point of the surface rises above the ray that climbs at the Sun's
//! elevation e. A pixel seen lit just past a shadow's far end lies above it: no point on the
//! way back to the rim that cast the shadow rises above its ray. With s the step along the
//! Sun's azimuth in pixels, Δ the pixel size and z(s) the surface there (bilinear between
//! pixel centres), the slack of step s is
//!
//! σ(s) = z(s) − z(0) − s·Δ·tan e,
//!
//! and the violation, in pixels of shadow length, is u = max(0, −max_s σ(s))/(Δ tan e) for a
//! shadowed pixel and u = max(0, max_s σ(s))/(Δ tan e) for a lit one. E_S = λ·Σ u² over the
//! rays. The photometric term sees neither: it drops shadowed pixels, and a crater floor in
//! shadow is then held only by the DEM and the membrane, which leave it too shallow.
//!
//! The step that casts (or clears) the shadow is chosen softly: the slack of a ray is the mean
//! of its steps' slacks weighted by π_s ∝ exp((σ(s) − max σ)/(T·Δ tan e)), T =
//! [`STEP_SOFTNESS_PX`], so that where two steps' slacks cross the ray's constraint moves from
//! one blocker to the other continuously rather than at once.
//!
//! Within a stage E_S is a fixed quadratic ([`ShadowTerm::fix_steps`]): each ray's step weights
//! π_s are fixed where the stage starts, and a ray violated there by u₀ weighs
//! min(1, u₀/[`ENGAGE_PX`]) for the stage, u free to turn negative. The stage's energy is then a
//! continuous function of the surface it starts from, so that a tile ends where the whole
//! region does.
//!
//! The walk of a ray is bounded by the image itself: the blocker of a shadowed pixel must lie
//! near the sunward end of the dark run it belongs to, so a ray reaches to the first pixel seen
//! lit sunward of it plus [`MARGIN_PX`] (at most `reach_px`). A shadowed pixel whose reach
//! leaves the grid is not constrained: the blocker may lie outside the window.

use super::Problem;
use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;

/// Pixels a ray reaches past the first lit pixel sunward of its start.
pub const MARGIN_PX: usize = 2;

/// The violation, in pixels of shadow length, at which a ray violated where a stage starts
/// weighs in full for that stage; less violated, it weighs in proportion
/// ([`ShadowTerm::fix_steps`]).
pub const ENGAGE_PX: f64 = 4.0;

/// T, the softness of a ray's choice of step, in pixels of shadow length: a step whose slack
/// lies d·Δ tan e below the largest weighs e^(−d/T) as much. With the step chosen outright (the
/// largest slack alone), a step whose slack overtook another's between a tile's start and the
/// whole region's moved the ray's constraint to another blocker, and weakly held shadowed
/// pixels ended metres apart (docs/science.md, "Cast shadows").
pub const STEP_SOFTNESS_PX: f64 = 0.25;

/// Steps weighing less than this fraction of the heaviest are left out of a ray (e^(−9.2)).
const STEP_CUT: f64 = 9.2;

/// W, the pixels of shadow length over which [`lit_fraction`] spreads a shadow's edge. The
/// bilinear surface places an edge to about 0.3 px even on the truth, and a share that follows
/// the surface's edge to the pixel (W = 1, or the slope of the pixel's own floor taken in)
/// moved with every pixel-scale change of the surface: 128-px tiles then ended up to 0.23× the
/// RMSE from the whole region, against at most 0.1× with W = 2, which is also the more accurate
/// (315/20 + 45/20, seeds 4 and 6: 4.42 / 5.06 → 4.38 / 5.02 m; W = 3: 4.42 m; docs/science.md,
/// "Partial shadow").
pub const LIT_EDGE_WIDTH_PX: f64 = 2.0;

/// The least lit share [`lit_fraction`] gives a pixel. A pixel the image sees lit is at least
/// half lit: the shadow mask takes the pixels mostly dark. A share let down to 0 left a pixel
/// the surface put in shadow without its photometric hold, or asked a sliver of it for all
/// its brightness, and 128-px tiles ended up to 33 m (6× the RMSE) from the whole region at
/// single craters (315/20 + 45/20, seed 5; docs/science.md, "Partial shadow").
pub const MIN_LIT_FRACTION: f64 = 0.5;

/// The longest walk `shadow_reach_px` may ask for.
pub const MAX_REACH_PX: usize = 4096;

/// A Sun higher than this (tan e) casts no shadow a grid pixel can hold.
const MAX_TAN_ELEVATION: f64 = 20.0;

/// One constrained pixel under one observation's Sun.
#[derive(Debug, Clone)]
pub struct Ray {
    /// Row and column of the pixel.
    pub i: u32,
    pub j: u32,
    /// Step towards the Sun, in rows and columns per unit step (a unit horizontal vector).
    pub dr: f32,
    pub dc: f32,
    /// Δ·tan e: the ray's rise per unit step, metres.
    pub rise: f32,
    /// Steps walked.
    pub steps: u16,
    /// Seen lit (the surface must stay under the ray) rather than in shadow.
    pub lit: bool,
    /// The ray's share of λ.
    pub weight: f32,
    /// The steps that cast or clear the shadow and their weights π_s (summing to 1), fixed for
    /// a stage ([`ShadowTerm::fix_steps`]); empty until then (they follow the surface).
    pub picks: Vec<(u16, f32)>,
    /// The ray's share of λ for the stage, from its violation u₀ where its steps were fixed:
    /// min(1, u₀/[`ENGAGE_PX`]), 0 if it was not violated. For that stage the ray is a plain
    /// quadratic, u² times this (u may turn negative).
    pub engaged: f32,
}

/// A ray E_S holds at one surface: u = c·z over the heights it reads (the pixel's, then the
/// four around each of its steps), and its value.
#[derive(Debug, Clone)]
pub struct Row {
    pub idx: Vec<u32>,
    pub coef: Vec<f32>,
    pub u: f64,
}

/// E_S's rays and weight.
#[derive(Debug, Clone)]
pub struct ShadowTerm {
    pub rays: Vec<Ray>,
    pub weight: f64,
    /// τ, pixels of shadow length a ray may be violated by at no cost.
    pub tolerance: f64,
}

/// E_S at one surface: its value λ·Σ ω·u² and the rays that hold it (engaged for the stage, or
/// before any stage the violated ones).
#[derive(Debug, Clone, Default)]
pub struct ShadowState {
    pub energy: f64,
    pub rows: Vec<Row>,
}

/// How an image sees a pixel for the rays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Seen {
    Shadow,
    Dim,
    Lit,
    Unseen,
}

/// The step towards the Sun `sun` (unit, grid frame) along its azimuth, in rows and columns per
/// unit step (east is +column, north is −row), and Δ·tan e, the ray's rise per step of
/// `spacing` metres, e the Sun's elevation; `None` where the Sun is at or below the horizon,
/// or so near the zenith (tan e over [`MAX_TAN_ELEVATION`]) that it casts no shadow a grid
/// pixel can hold.
fn towards_sun(sun: &crate::photometry::Vec3, spacing: f64) -> Option<(f64, f64, f64)> {
    let h = (sun[0] * sun[0] + sun[1] * sun[1]).sqrt();
    if sun[2] <= 0.0 || h <= 0.0 || sun[2] / h > MAX_TAN_ELEVATION {
        return None;
    }
    Some((-sun[1] / h, sun[0] / h, spacing * sun[2] / h))
}

/// The rays of every observation: `shadowed(k, v)` and `lit(k, v)` say whether observation
/// k's value v is shadow or clearly lit; `reach_px` bounds every walk.
pub fn rays(
    pr: &Problem,
    shadowed: &(dyn Fn(usize, f64) -> bool + Sync),
    lit: &(dyn Fn(usize, f64) -> bool + Sync),
    weight: &(dyn Fn(usize, usize, usize) -> f64 + Sync),
    reach_px: usize,
) -> Vec<Ray> {
    let (ny, nx) = pr.dem.dim();
    let mut out = Vec::new();
    for (k, o) in pr.observations.iter().enumerate() {
        let seen = o.image.mapv(|v| {
            if !v.is_finite() {
                Seen::Unseen
            } else if shadowed(k, v) {
                Seen::Shadow
            } else if lit(k, v) {
                Seen::Lit
            } else {
                Seen::Dim
            }
        });
        let rows: Vec<Vec<Ray>> = (0..ny)
            .into_par_iter()
            .map(|i| {
                let mut row = Vec::new();
                for j in 0..nx {
                    let start = seen[(i, j)];
                    if start == Seen::Dim || start == Seen::Unseen {
                        continue;
                    }
                    let w = weight(k, i, j);
                    if w <= 0.0 {
                        continue;
                    }
                    let Some((dr, dc, rise)) = towards_sun(&o.sun.at(i, j), pr.spacing) else {
                        continue;
                    };
                    if let Some(ray) = walk(&seen, (i, j), (dr, dc), start, reach_px) {
                        row.push(Ray {
                            i: i as u32,
                            j: j as u32,
                            dr: dr as f32,
                            dc: dc as f32,
                            rise: rise as f32,
                            steps: ray as u16,
                            lit: start == Seen::Lit,
                            weight: w as f32,
                            picks: Vec::new(),
                            engaged: 0.0,
                        });
                    }
                }
                row
            })
            .collect();
        out.extend(rows.into_iter().flatten());
    }
    out
}

/// The steps a ray from `ij` takes, from the image alone (nearest pixels): a shadowed pixel
/// reaches the first lit pixel sunward of it plus [`MARGIN_PX`], and is not constrained if
/// that leaves the grid or `reach_px`; a lit pixel is constrained only if a shadow lies within
/// [`MARGIN_PX`] + 1 steps sunward of it (it ends that shadow), and reaches the first lit pixel
/// past the shadow plus the margin, cut at the grid's edge.
fn walk(
    seen: &Array2<Seen>,
    (i, j): (usize, usize),
    (dr, dc): (f64, f64),
    start: Seen,
    reach_px: usize,
) -> Option<usize> {
    let (ny, nx) = seen.dim();
    let at = |s: usize| -> Option<Seen> {
        let (r, c) = nearest_along((i, j), s as f64, (dr, dc));
        if r < 0.0 || c < 0.0 || r > (ny - 1) as f64 || c > (nx - 1) as f64 {
            None
        } else {
            Some(seen[(r as usize, c as usize)])
        }
    };
    if start == Seen::Shadow {
        for s in 1..=reach_px {
            match at(s)? {
                Seen::Lit => {
                    let end = s + MARGIN_PX;
                    return (end <= reach_px && at(end).is_some()).then_some(end);
                }
                Seen::Unseen => return None,
                _ => {}
            }
        }
        return None;
    }
    // Lit: a shadow within the first MARGIN_PX + 1 steps, then its far end.
    let mut s = 1;
    let mut dark = false;
    while s <= MARGIN_PX + 1 {
        match at(s)? {
            Seen::Shadow => {
                dark = true;
                break;
            }
            Seen::Lit => return None,
            Seen::Unseen => return None,
            Seen::Dim => {}
        }
        s += 1;
    }
    if !dark {
        return None;
    }
    let mut last = s;
    while s < reach_px {
        s += 1;
        match at(s) {
            None | Some(Seen::Unseen) => return Some(last),
            Some(Seen::Lit) => return Some((s + MARGIN_PX).min(reach_px)),
            Some(_) => last = s,
        }
    }
    Some(last)
}

/// The pixel nearest the point `t` pixels from (i, j) along the unit step (dr, dc), as
/// (row, column), possibly off the grid. The offset is rounded, not the position, so the pixel
/// chosen is the same wherever (i, j) lies in the window: at an exact half-pixel tie (a Sun
/// due south, 1.5 px) rounding i + t·dr went up or down with the size of i, because the sum
/// keeps the step's shortfall from 1.5 (10⁻¹⁴) where i is small and rounds it away where the
/// spacing of doubles near i is coarser than that; a tile and the whole region then took
/// different pixels for part in shadow and ended tens of metres apart on steep pits
/// (docs/science.md, "Partial shadow"). Ties round away from the pixel, the same for every
/// Sun azimuth.
#[inline]
fn nearest_along((i, j): (usize, usize), t: f64, (dr, dc): (f64, f64)) -> (f64, f64) {
    (i as f64 + (t * dr).round(), j as f64 + (t * dc).round())
}

/// Bilinear weights of (r, c) inside an ny × nx grid: the flat indices of its four pixels and
/// their weights.
#[inline]
fn bilinear(r: f64, c: f64, ny: usize, nx: usize) -> ([u32; 4], [f64; 4]) {
    let r = r.clamp(0.0, (ny - 1) as f64);
    let c = c.clamp(0.0, (nx - 1) as f64);
    let r0 = (r.floor() as usize).min(ny.saturating_sub(2));
    let c0 = (c.floor() as usize).min(nx.saturating_sub(2));
    let (fr, fc) = (r - r0 as f64, c - c0 as f64);
    let r1 = (r0 + 1).min(ny - 1);
    let c1 = (c0 + 1).min(nx - 1);
    let idx = [
        (r0 * nx + c0) as u32,
        (r0 * nx + c1) as u32,
        (r1 * nx + c0) as u32,
        (r1 * nx + c1) as u32,
    ];
    let w = [
        (1.0 - fr) * (1.0 - fc),
        (1.0 - fr) * fc,
        fr * (1.0 - fc),
        fr * fc,
    ];
    (idx, w)
}

/// The slack σ(s) = z(s) − z(0) − s·Δ·tan e of step `s` along `ray` on `zs` (flat, `nx`
/// columns), with the bilinear indices and weights of z(s).
fn slack_at(
    ray: &Ray,
    zs: &[f64],
    (ny, nx): (usize, usize),
    s: usize,
) -> (f64, [u32; 4], [f64; 4]) {
    let (i, j) = (ray.i as usize, ray.j as usize);
    let r = i as f64 + s as f64 * f64::from(ray.dr);
    let c = j as f64 + s as f64 * f64::from(ray.dc);
    let (idx, w) = bilinear(r, c, ny, nx);
    let zb: f64 = idx.iter().zip(&w).map(|(&k, &w)| w * zs[k as usize]).sum();
    (zb - zs[i * nx + j] - s as f64 * f64::from(ray.rise), idx, w)
}

/// The step weights π_s of `ray` on `zs`: e^((σ(s) − max σ)/(T·Δ tan e)) over its steps
/// (T = [`STEP_SOFTNESS_PX`]), normalised to sum 1, the steps below e^(−[`STEP_CUT`]) of the
/// heaviest left out.
fn step_weights(ray: &Ray, zs: &[f64], dim: (usize, usize)) -> Vec<(u16, f32)> {
    let slacks: Vec<f64> = (1..=ray.steps as usize)
        .map(|s| slack_at(ray, zs, dim, s).0)
        .collect();
    let top = slacks.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let scale = STEP_SOFTNESS_PX * f64::from(ray.rise);
    let kept: Vec<(u16, f64)> = slacks
        .iter()
        .enumerate()
        .map(|(k, &sl)| ((k + 1) as u16, (sl - top) / scale))
        .filter(|&(_, x)| x > -STEP_CUT)
        .map(|(s, x)| (s, x.exp()))
        .collect();
    let total: f64 = kept.iter().map(|p| p.1).sum();
    kept.into_iter()
        .map(|(s, p)| (s, (p / total) as f32))
        .collect()
}

/// The weighted slack Σ π_s σ(s) of `ray` over `picks` on `zs`, and its derivatives: the
/// heights it reads (the pixel's, then the four around each step) with their coefficients.
fn weighted_slack(
    ray: &Ray,
    picks: &[(u16, f32)],
    zs: &[f64],
    dim: (usize, usize),
) -> (f64, Vec<u32>, Vec<f64>) {
    let mut idx = Vec::with_capacity(1 + 4 * picks.len());
    let mut coef = Vec::with_capacity(1 + 4 * picks.len());
    idx.push((ray.i as usize * dim.1 + ray.j as usize) as u32);
    coef.push(0.0);
    let (mut slack, mut total) = (0.0, 0.0);
    for &(s, p) in picks {
        let p = f64::from(p);
        let (sl, ix, w) = slack_at(ray, zs, dim, s as usize);
        slack += p * sl;
        total += p;
        idx.extend(ix);
        coef.extend(w.iter().map(|w| p * w));
    }
    coef[0] = -total;
    (slack, idx, coef)
}

/// u of a ray whose (weighted) slack is `slack`: the violation in pixels of shadow length
/// less the tolerance (positive: violated).
fn violation(ray: &Ray, slack: f64, tolerance: f64) -> f64 {
    let v = if ray.lit { slack } else { -slack };
    v / f64::from(ray.rise) - tolerance
}

impl ShadowTerm {
    /// Fixes, for the stage to come, each ray's step weights π_s on `z` (standard layout;
    /// [`STEP_SOFTNESS_PX`]) and its set: the rays violated there. Within the stage E_S is then a
    /// fixed quadratic, λ·Σ ω·u² over that set with u linear in z (an active set, renewed at
    /// every stage as the membrane's weights are). The Gauss–Newton model of E_S is then exact
    /// and full steps pass the line search as they did without it; with the hinge the model
    /// missed the rays a step newly violates, the line search halved such steps or not by a
    /// hair, and a tiled run ended metres from the single window.
    pub fn fix_steps(&mut self, z: ArrayView2<f64>) {
        let (ny, nx) = z.dim();
        let z = z.as_standard_layout();
        let zs = z.as_slice().expect("standard layout");
        let tolerance = self.tolerance;
        self.rays.par_iter_mut().for_each(|ray| {
            ray.picks = step_weights(ray, zs, (ny, nx));
            let (slack, _, _) = weighted_slack(ray, &ray.picks, zs, (ny, nx));
            let u = violation(ray, slack, tolerance);
            ray.engaged = (u / ENGAGE_PX).clamp(0.0, 1.0) as f32;
        });
    }

    /// E_S and the rays that hold it at surface `z` (standard layout; [`ShadowState`]). Rays
    /// are evaluated in parallel and summed in their order: the result does not depend on the
    /// thread count. Before any stage has fixed them ([`Self::fix_steps`]), a ray's step
    /// weights are taken on `z` itself and its rows treat them as constants: the value is E_S
    /// at `z`, the rows its gradient only where the weights do not move (the solvers evaluate
    /// E_S only within stages).
    pub fn evaluate(&self, z: ArrayView2<f64>) -> ShadowState {
        let (ny, nx) = z.dim();
        let zs = z.as_slice().expect("standard layout");
        let rows: Vec<Option<Row>> = self
            .rays
            .par_iter()
            .map(|ray| {
                let fixed = !ray.picks.is_empty();
                if fixed && ray.engaged <= 0.0 {
                    return None;
                }
                let rise = f64::from(ray.rise);
                let (slack, idx, coef) = if fixed {
                    weighted_slack(ray, &ray.picks, zs, (ny, nx))
                } else {
                    weighted_slack(ray, &step_weights(ray, zs, (ny, nx)), zs, (ny, nx))
                };
                let u = violation(ray, slack, self.tolerance);
                if !fixed && u <= 0.0 {
                    return None;
                }
                let share = if fixed {
                    f64::from(ray.weight) * f64::from(ray.engaged)
                } else {
                    f64::from(ray.weight)
                };
                // u = v/rise; shadow: v = z0 − zb + c, lit: v = zb − z0 − c.
                let sign = if ray.lit { 1.0 } else { -1.0 };
                let k = sign / rise * share.sqrt();
                Some(Row {
                    idx,
                    coef: coef.iter().map(|c| (k * c) as f32).collect(),
                    u: u * share.sqrt(),
                })
            })
            .collect();
        let rows: Vec<Row> = rows.into_iter().flatten().collect();
        let energy = self.weight * rows.iter().map(|r| r.u * r.u).sum::<f64>();
        ShadowState { energy, rows }
    }
}

/// The bilinear height of `z` at (r, c), inside the grid.
fn height_at(z: ArrayView2<f64>, r: f64, c: f64) -> f64 {
    let (ny, nx) = z.dim();
    let (idx, w) = bilinear(r, c, ny, nx);
    idx.iter()
        .zip(&w)
        .map(|(&k, &w)| w * z[(k as usize / nx, k as usize % nx)])
        .sum()
}

/// f, the share of pixel (i, j) that the Sun `sun` (unit, grid frame) reaches past the terrain
/// `z` (bilinear between pixel centres, `spacing` metres apart), walking at most `reach_px`
/// pixels towards the Sun. With σ the largest slack z(s) − z(0) − s·Δ·tan e of the steps
/// s ≥ 1 (every half pixel; e the Sun's elevation), the shadow's edge lies d = −σ/(Δ tan e)
/// pixels sunward of the pixel's centre, and the pixel's lit share is
///
/// f = ½ + d/W, within [[`MIN_LIT_FRACTION`], 1],
///
/// with the edge's place taken as known to W = [`LIT_EDGE_WIDTH_PX`] pixels: the share a pixel
/// has against an edge spread evenly over W pixels, where it crosses the pixel (W = 1 would be
/// the pixel's own share of a sharp edge). 1 where the Sun is at or below the horizon or so
/// near the zenith that it casts no shadow a grid pixel can hold.
pub fn lit_fraction(
    z: ArrayView2<f64>,
    spacing: f64,
    (i, j): (usize, usize),
    sun: &crate::photometry::Vec3,
    reach_px: usize,
) -> f64 {
    let (ny, nx) = z.dim();
    let Some((dr, dc, rise)) = towards_sun(sun, spacing) else {
        return 1.0;
    };
    // Within a millionth of a pixel of the grid counts as on it: a Sun due east has a
    // north–south component of 10⁻¹⁷, not 0, and the first row's walk must not leave the grid.
    let (last_r, last_c) = ((ny - 1) as f64 + 1e-6, (nx - 1) as f64 + 1e-6);
    let z0 = z[(i, j)];
    let mut top = f64::NEG_INFINITY;
    for s in 2..=2 * reach_px {
        let t = 0.5 * s as f64;
        let (r, c) = (i as f64 + t * dr, j as f64 + t * dc);
        if r < -1e-6 || c < -1e-6 || r > last_r || c > last_c {
            break;
        }
        top = top.max(height_at(z, r, c) - z0 - t * rise);
    }
    (0.5 - top / (LIT_EDGE_WIDTH_PX * rise)).clamp(MIN_LIT_FRACTION, 1.0)
}

/// Whether the pixel 1 or 1.5 pixels from (i, j) towards the Sun `sun` (rounded to the nearest
/// pixel) is one `shadowed` says the image sees in shadow: (i, j) lies just past a cast
/// shadow, where the shadow's edge may cross it. The pixels on a shadow's other sides are the
/// rim that casts it and the shadow's flanks, where the Sun's ray grazes no blocker the pixel
/// could be part hidden by.
fn past_a_shadow(
    (i, j): (usize, usize),
    (ny, nx): (usize, usize),
    sun: &crate::photometry::Vec3,
    shadowed: impl Fn(usize, usize) -> bool,
) -> bool {
    let Some((dr, dc, _)) = towards_sun(sun, 1.0) else {
        return false;
    };
    [1.0, 1.5].iter().any(|&t| {
        let (r, c) = nearest_along((i, j), t, (dr, dc));
        r >= 0.0 && c >= 0.0 && r < ny as f64 && c < nx as f64 && shadowed(r as usize, c as usize)
    })
}

/// Sun elevations, degrees, up to which the partial shadow is modelled in full and from which
/// not at all ([`partial_shadow_share`]).
pub const PARTIAL_SHADOW_DEG: [f64; 2] = [22.5, 27.5];

/// a(e), how much of the lit share [`lit_fractions`] takes under a Sun `elevation_deg` high:
/// 1 up to 22.5°, 0 from 27.5°, a smoothstep between (½ at 25°). Under a 20° Sun the shadows
/// are long and their edges many, and the share takes the error 5 % lower; under Suns of
/// 30–35° the shadows are short, the edge's place (to W = [`LIT_EDGE_WIDTH_PX`]) costs more
/// than the share gains (105/30 + 225/35: +1.1 %), and a single 30° Sun's 96-px tiles ended
/// 0.105× the RMSE from the whole region; at 25° half the share does better than all of it
/// or none (docs/science.md, "Partial shadow").
pub fn partial_shadow_share(elevation_deg: f64) -> f64 {
    let [lo, hi] = PARTIAL_SHADOW_DEG;
    1.0 - super::support::smoothstep((elevation_deg - lo) / (hi - lo))
}

/// Sun elevations, degrees, up to which a ray at a pixel two or more other observations carry
/// weighs in full and from which it weighs `shadow_weight_all` ([`ray_weight_all`]).
pub const LOW_SUN_RAY_DEG: [f64; 2] = [20.0, 30.0];

/// E_S's factor on a ray at a pixel two or more other observations carry, its Sun
/// `elevation_deg` high: 1 up to 20°, `weight_all` (ω_all) from 30°, a smoothstep between.
/// Under Suns of 25–35° the shadows are short, the truth itself violates many of their rays
/// by a fraction of a pixel (sub-pixel rims), and where the other images already fix the
/// pixel a full ray pulls floors below the truth; under a 20° Sun the shadows are long and
/// their rays hold crater floors the other images see at grazing light (three Suns 20° high,
/// ω_all 0.1 → 1: the error 8 % lower; docs/science.md, "Three low Suns").
pub fn ray_weight_all(weight_all: f64, elevation_deg: f64) -> f64 {
    let [lo, hi] = LOW_SUN_RAY_DEG;
    let t = super::support::smoothstep((elevation_deg - lo) / (hi - lo));
    weight_all + (1.0 - weight_all) * (1.0 - t)
}

/// f_k for every observation ([`super::observations::Weights::lit`]): 1 − a·(1 − f), f the
/// [`lit_fraction`] on surface `z` and a the [`partial_shadow_share`] of the Sun there, at each
/// pixel observation k uses just past one of its own shadows (the pixel 1 or 1.5 pixels
/// towards its Sun is shadowed, I/g/Ī_k below `threshold`; walks of at most `reach_px`) and
/// another observation sees (its image valid there), 1 elsewhere. A pixel no other
/// observation sees is held by its one image alone, and there the share, as E_S's rays
/// (`shadow_weight_alone`), made the result depend on the window: one 20° Sun's 128-px tiles
/// ended 0.16–0.19× the RMSE from the whole region, against 0.06× without (docs/science.md,
/// "Partial shadow"). One observation alone is therefore as before. `None` where that is 1 at every pixel, and for an observation coarser than the
/// grid (`blurred`): its rendering is blurred before it meets the image, and f stays 1.
pub fn lit_fractions(
    pr: &Problem,
    (w, scale): (&super::observations::Weights, f64),
    blurred: &[bool],
    z: ArrayView2<f64>,
    (threshold, reach_px): (f64, usize),
) -> Vec<Option<Array2<f32>>> {
    use super::observations::{elevation_deg, image_shadowed, own_mean};
    pr.observations
        .iter()
        .enumerate()
        .map(|(k, o)| {
            if blurred[k] {
                return None;
            }
            let (gain, own) = (w.gains[k], own_mean(scale, w.noise[k]));
            let dim = o.image.dim();
            let shadowed = |r: usize, c: usize| {
                let v = o.image[(r, c)];
                v.is_finite() && image_shadowed(v, gain, own, threshold)
            };
            let f = Zip::indexed(&w.usable[k]).par_map_collect(|ij, &u| {
                // Where no other observation sees the pixel, the share is its only hold.
                if !u || !pr.seen_by_another(k, ij) {
                    return 1.0;
                }
                let sun = o.sun.at(ij.0, ij.1);
                let a = partial_shadow_share(elevation_deg(&sun));
                if a > 0.0 && past_a_shadow(ij, dim, &sun, shadowed) {
                    (1.0 - a * (1.0 - lit_fraction(z, pr.spacing, ij, &sun, reach_px))) as f32
                } else {
                    1.0
                }
            });
            f.iter().any(|&f| f < 1.0).then_some(f)
        })
        .collect()
}

/// ∂E_S/∂z = 2λ Σ u·c, added into `g` (flat, standard layout), rows in order.
pub fn add_gradient(weight: f64, rows: &[Row], g: &mut [f64]) {
    for r in rows {
        for (&k, &c) in r.idx.iter().zip(&r.coef) {
            g[k as usize] += 2.0 * weight * r.u * f64::from(c);
        }
    }
}

/// The Gauss–Newton Hessian of E_S applied to `v`, 2λ Σ c·(c·v), added into `out` (flat).
pub fn add_normal(weight: f32, rows: &[Row], v: &[f32], out: &mut [f32]) {
    for r in rows {
        let s: f32 = r
            .idx
            .iter()
            .zip(&r.coef)
            .map(|(&k, &c)| c * v[k as usize])
            .sum();
        for (&k, &c) in r.idx.iter().zip(&r.coef) {
            out[k as usize] += 2.0 * weight * c * s;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::Directions;
    use crate::photometry::Hapke;
    use ndarray::s;

    const SPACING: f64 = 100.0;
    /// Sun 30° above the horizon, from the east.
    const ELEVATION: f64 = 30.0;
    const WALL: usize = 25;

    /// A plain at 0 m with a plateau `height` m high from column [`WALL`] east.
    fn plateau(ny: usize, nx: usize, height: f64) -> Array2<f64> {
        Array2::from_shape_fn((ny, nx), |(_, j)| if j >= WALL { height } else { 0.0 })
    }

    /// The image of a 200 m plateau under [`ELEVATION`]: its shadow, H/(Δ tan e) = 3.46 px
    /// long, covers columns 22–24 (the ray from column 21 clears the plateau's edge at
    /// 4 px by 200 − 4·57.7 < 0 m); 0 there, 1 elsewhere.
    fn image(ny: usize, nx: usize) -> Array2<f64> {
        Array2::from_shape_fn(
            (ny, nx),
            |(_, j)| if (22..WALL).contains(&j) { 0.0 } else { 1.0 },
        )
    }

    fn term(pr: &Problem) -> ShadowTerm {
        let rays = rays(pr, &|_, v| v < 0.1, &|_, v| v >= 0.5, &|_, _, _| 1.0, 48);
        ShadowTerm {
            rays,
            weight: 2.0,
            tolerance: 0.0,
        }
    }

    fn problem<'a>(image: &'a Array2<f64>, dem: &'a Array2<f64>, model: &'a Hapke) -> Problem<'a> {
        Problem::single(
            image.view(),
            Directions::Uniform(crate::synth::direction(90.0 - ELEVATION, 90.0)),
            Directions::Uniform([0.0, 0.0, 1.0]),
            dem.view(),
            SPACING,
            1.5,
            model,
        )
    }

    /// ω_all under a low Sun: 1 up to 20°, ω_all from 30°, the smoothstep between (halfway
    /// at 25°); ω_all = 1 leaves every ray at 1.
    #[test]
    fn rays_under_a_low_sun_weigh_in_full_where_others_carry_the_pixel() {
        assert_eq!(ray_weight_all(0.1, 10.0), 1.0);
        assert_eq!(ray_weight_all(0.1, 20.0), 1.0);
        assert!((ray_weight_all(0.1, 25.0) - 0.55).abs() < 1e-12);
        assert_eq!(ray_weight_all(0.1, 30.0), 0.1);
        assert_eq!(ray_weight_all(0.1, 60.0), 0.1);
        assert_eq!(ray_weight_all(1.0, 45.0), 1.0);
        assert_eq!(ray_weight_all(0.0, 25.0), 0.5);
    }

    /// The lit share of the pixels past a plateau's shadow, against the shadow's edge worked
    /// out as the point where the Sun's ray over the plateau's edge meets the floor. The
    /// plateau rises from column 24 (its last floor pixel) to column 25 (bilinearly between
    /// them), so the ray that grazes column 25 at height H casts the longest shadow, its edge
    /// at x_e = 25 − H/(Δ tan e), and floor pixel j, d = x_e − j pixels from it, has
    /// f = ½ + d/W within [[`MIN_LIT_FRACTION`], 1].
    #[test]
    fn the_lit_share_of_a_pixel_follows_its_distance_from_the_shadows_edge() {
        let tan_e = ELEVATION.to_radians().tan();
        let sun = crate::synth::direction(90.0 - ELEVATION, 90.0);
        let least = MIN_LIT_FRACTION;
        let width = LIT_EDGE_WIDTH_PX;
        for (length, want) in [
            // x_e = 21.3: pixel 21 is 0.3 px short of it, 20 1.3 px; 22 is past it.
            (
                3.7,
                [
                    (19, 1.0),
                    (20, 1.0),
                    (21, 0.5 + 0.3 / width),
                    (22, least),
                    (23, least),
                ],
            ),
            // x_e = 20.9.
            (
                4.1,
                [
                    (18, 1.0),
                    (19, 1.0),
                    (20, 0.5 + 0.9 / width),
                    (21, least),
                    (22, least),
                ],
            ),
        ] {
            let z = plateau(10, 40, length * SPACING * tan_e);
            for (j, want) in want {
                let f = lit_fraction(z.view(), SPACING, (5, j), &sun, 48);
                assert!(
                    (f - want).abs() < 1e-9,
                    "shadow {length} px, column {j}: {f} vs {want}"
                );
            }
        }
        // No Sun above the horizon: nothing to be part hidden from.
        let flat = plateau(10, 40, 3.7 * SPACING * tan_e);
        let set = crate::synth::direction(95.0, 90.0);
        assert_eq!(lit_fraction(flat.view(), SPACING, (5, 21), &set, 48), 1.0);
        // The first row, under a Sun due east (a north–south component of 10⁻¹⁷): as any row.
        let f = lit_fraction(flat.view(), SPACING, (0, 21), &sun, 48);
        assert!((f - (0.5 + 0.3 / width)).abs() < 1e-9, "first row: {f}");
    }

    /// Only the pixels just past a shadow the image sees, on its side away from the Sun, and
    /// seen by another observation too, take a lit share: the image shows the plateau's shadow
    /// on rows 0–2 only, and on rows 3–4 the pixel the surface would put part in shadow keeps
    /// 1, as do the plateau's edge (the rim that casts the shadow) and the plain far from it;
    /// on row 5 the image shows a shadow at column 22 again, but no other observation sees the
    /// row. The share is taken in full under a Sun 20° high, half under 25° (a = ½), not at
    /// all under 30°.
    #[test]
    fn lit_shares_are_taken_only_just_past_a_shadow_under_a_low_sun() {
        let model = Hapke::moon();
        let mut img = image(6, 40);
        img.slice_mut(s![3.., ..]).fill(1.0);
        img.row_mut(5).fill(1.0);
        img[(5, 22)] = 0.0;
        let dem = plateau(6, 40, 200.0);
        let mut other = Array2::from_elem((6, 40), 1.0);
        other.row_mut(5).fill(f64::NAN);
        for (elevation, a) in [(20.0_f64, 1.0), (25.0, 0.5), (30.0, 0.0)] {
            assert!((partial_shadow_share(elevation) - a).abs() < 1e-12);
            let sun = crate::synth::direction(90.0 - elevation, 90.0);
            let mut pr = Problem::single(
                img.view(),
                Directions::Uniform(sun),
                Directions::Uniform([0.0, 0.0, 1.0]),
                dem.view(),
                SPACING,
                1.5,
                &model,
            );
            // A second observation, a high Sun's, sees every pixel but the last row: there
            // the first is alone and takes no share.
            pr.observations.push(crate::fusion::Observation {
                image: other.view(),
                sun: Directions::Uniform(crate::synth::direction(30.0, 270.0)),
                view: Directions::Uniform([0.0, 0.0, 1.0]),
            });
            let w = crate::fusion::observations::weights(
                &pr,
                vec![1.0, 1.0],
                1.0,
                Some(vec![1.0, 1.0]),
                0.1,
                0.0,
                (1.0, 1.0),
            );
            // The shadow is 3.7 px long on this surface: x_e = 21.3, 0.3 px past pixel 21.
            let z = plateau(6, 40, 3.7 * SPACING * elevation.to_radians().tan());
            let share = 0.5 + 0.3 / LIT_EDGE_WIDTH_PX;
            assert!((lit_fraction(z.view(), SPACING, (4, 21), &sun, 48) - share).abs() < 1e-9);
            let lit = lit_fractions(&pr, (&w, 1.0), &[false, false], z.view(), (0.1, 48));
            // Where every share is 1, none is stored.
            let Some(f) = lit[0].as_ref() else {
                assert_eq!(a, 0.0, "{elevation}°: no share stored");
                continue;
            };
            for ((i, j), &f) in f.indexed_iter() {
                // Columns 20 and 21 lie 1.5 and 1 px west of the shadow's first pixel, 22; on
                // column 20 the whole pixel is west of x_e.
                let want = if i < 3 && j == 21 {
                    1.0 - a * (1.0 - share)
                } else {
                    1.0
                };
                assert!(
                    (f64::from(f) - want).abs() < 1e-6,
                    "{elevation}°, ({i}, {j}): {f}"
                );
            }
            // The second observation has no shadow; one coarser than the grid keeps f = 1.
            assert!(lit[1].is_none());
            let blurred = lit_fractions(&pr, (&w, 1.0), &[true, false], z.view(), (0.1, 48));
            assert!(blurred[0].is_none());
        }
    }

    /// The rays a plateau's shadow gives: one per shadowed pixel, reaching the plateau's
    /// first lit pixel plus the margin, and one from the lit pixel just before the shadow.
    #[test]
    fn a_shadow_gives_a_ray_per_dark_pixel_and_one_at_its_far_end() {
        let (ny, nx) = (6, 40);
        let (img, dem) = (image(ny, nx), plateau(ny, nx, 0.0));
        let model = Hapke::moon();
        let pr = problem(&img, &dem, &model);
        let t = term(&pr);
        assert_eq!(t.rays.len(), 4 * ny);
        for r in &t.rays {
            let j = r.j as usize;
            if r.lit {
                assert_eq!(j, 21);
                assert_eq!(r.steps as usize, WALL - j + MARGIN_PX);
            } else {
                assert!((22..WALL).contains(&j));
                assert_eq!(r.steps as usize, WALL - j + MARGIN_PX);
            }
            assert!(r.dr.abs() < 1e-6 && (r.dc - 1.0).abs() < 1e-6);
            let rise = SPACING * ELEVATION.to_radians().tan();
            assert!((f64::from(r.rise) - rise).abs() < 1e-3 * rise);
        }
    }

    /// The step weights' mean of n·e^(−n/T) over n = 0, 1, 2, … (the steps' slacks falling by
    /// one pixel of shadow each; those beyond [`STEP_CUT`]·T left out).
    fn soft_excess() -> f64 {
        let t = STEP_SOFTNESS_PX;
        let kept: Vec<f64> = (0..)
            .map(f64::from)
            .take_while(|n| n / t < STEP_CUT)
            .collect();
        let w: f64 = kept.iter().map(|n| (-n / t).exp()).sum();
        kept.iter().map(|n| n * (-n / t).exp()).sum::<f64>() / w
    }

    /// E_S against the plateau's geometry: 0 on the truth; a floor that casts no shadow
    /// (the plateau levelled) violates each shadowed ray by one pixel of shadow at its best
    /// step, the first, where the ray has risen Δ tan e, and the next steps, each a pixel
    /// more, weigh e^(−1/T): 1 + [`soft_excess`]; a plateau twice as high violates the lit ray
    /// past the shadow by H/(Δ tan e) − 4 pixels at the plateau's edge, 4 px away, its next
    /// steps each a pixel less: H/(Δ tan e) − 4 − [`soft_excess`].
    #[test]
    fn the_shadow_term_holds_the_truth_and_measures_violations_in_pixels() {
        let (ny, nx) = (6, 40);
        let img = image(ny, nx);
        let truth = plateau(ny, nx, 200.0);
        let model = Hapke::moon();
        let pr = problem(&img, &truth, &model);
        let t = term(&pr);
        let at_truth = t.evaluate(truth.view());
        assert_eq!(at_truth.energy, 0.0);
        assert!(at_truth.rows.is_empty());

        let flat = plateau(ny, nx, 0.0);
        let s = t.evaluate(flat.view());
        assert_eq!(s.rows.len(), 3 * ny);
        let u = 1.0 + soft_excess();
        for r in &s.rows {
            assert!((r.u - u).abs() < 1e-5, "{} against {u}", r.u);
        }
        assert!((s.energy - 2.0 * (3 * ny) as f64 * u * u).abs() < 1e-3);

        let high = 400.0;
        let s = t.evaluate(plateau(ny, nx, high).view());
        let expected = high / (SPACING * ELEVATION.to_radians().tan()) - 4.0 - soft_excess();
        assert_eq!(s.rows.len(), ny);
        for r in &s.rows {
            assert!((r.u - expected).abs() < 1e-4, "{} against {expected}", r.u);
        }
    }

    /// A surface between the plateau's: some rays violated, at generic steps.
    fn rough(ny: usize, nx: usize) -> Array2<f64> {
        Array2::from_shape_fn((ny, nx), |(i, j)| {
            let base = if j >= WALL { 120.0 } else { 0.0 };
            base + 15.0 * (0.7 * i as f64 + 0.3 * j as f64).sin() + 3.0 * j as f64
        })
    }

    /// ∂E_S/∂z against central differences of E_S with the rays fixed for a stage, and the
    /// Gauss–Newton Hessian applied to a vector against the change of the gradient along it
    /// (E_S is then quadratic in z).
    #[test]
    fn the_gradient_and_hessian_match_finite_differences() {
        let (ny, nx) = (6, 40);
        let img = image(ny, nx);
        let z = rough(ny, nx);
        let model = Hapke::moon();
        let pr = problem(&img, &z, &model);
        let free = term(&pr);
        // With each ray's step weights fixed on z, the rays violated there stay, each weighing
        // min(1, u/ENGAGE_PX): E_S at z is λ·Σ min(1, u/ENGAGE_PX)·u².
        let unfixed = free.evaluate(z.view());
        let mut t = free.clone();
        t.fix_steps(z.view());
        assert!(t.rays.iter().all(|r| {
            let total: f32 = r.picks.iter().map(|p| p.1).sum();
            !r.picks.is_empty()
                && r.picks.iter().all(|p| p.0 >= 1 && p.0 <= r.steps)
                && (total - 1.0).abs() < 1e-5
        }));
        let s = t.evaluate(z.view());
        assert_eq!(s.rows.len(), unfixed.rows.len());
        let expected: f64 = unfixed
            .rows
            .iter()
            .map(|r| t.weight * (r.u / ENGAGE_PX).min(1.0) * r.u * r.u)
            .sum();
        assert!(
            (s.energy - expected).abs() < 1e-6 * expected,
            "{} against {expected}",
            s.energy
        );
        assert!(!s.rows.is_empty());
        let mut g = vec![0.0; ny * nx];
        add_gradient(t.weight, &s.rows, &mut g);
        let h = 1e-4;
        for (k, &gk) in g.iter().enumerate() {
            let mut zp = z.clone();
            zp.as_slice_mut().unwrap()[k] += h;
            let mut zm = z.clone();
            zm.as_slice_mut().unwrap()[k] -= h;
            let num = (t.evaluate(zp.view()).energy - t.evaluate(zm.view()).energy) / (2.0 * h);
            assert!(
                (gk - num).abs() < 1e-6 + 1e-5 * num.abs(),
                "{k}: {gk} against {num}"
            );
        }
        let v: Vec<f32> = (0..ny * nx).map(|k| ((k * 7) % 11) as f32 - 5.0).collect();
        let mut hv = vec![0f32; ny * nx];
        add_normal(t.weight as f32, &s.rows, &v, &mut hv);
        let step = 1e-3;
        let shifted = |sign: f64| {
            let zs = Array2::from_shape_fn((ny, nx), |(i, j)| {
                z[(i, j)] + sign * step * f64::from(v[i * nx + j])
            });
            let mut g = vec![0.0; ny * nx];
            add_gradient(t.weight, &t.evaluate(zs.view()).rows, &mut g);
            g
        };
        let (gp, gm) = (shifted(1.0), shifted(-1.0));
        for (k, (&h, (p, m))) in hv.iter().zip(gp.iter().zip(&gm)).enumerate() {
            let num = (p - m) / (2.0 * step);
            assert!(
                (f64::from(h) - num).abs() < 1e-4 * (1.0 + num.abs()),
                "{k}: {h} against {num}"
            );
        }
    }

    /// Whether a pixel lies just past a shadow does not depend on where it lies in the window.
    /// A Sun due south whose unit step is a hair short of one row, 1 − 10⁻¹⁴ (as a per-pixel
    /// geometry gives it): 1.5 steps is a half-pixel tie, and rounding the position i + 1.5·dr
    /// took the second row sunward at some rows and the first at others (the sum keeps the
    /// shortfall from 1.5 only where the spacing of doubles near i is finer than it). With the
    /// shadow two rows sunward, every row must answer alike, for a Sun from the north too.
    #[test]
    fn a_pixel_past_a_shadow_is_found_wherever_it_lies_in_the_window() {
        let (ny, nx) = (2100, 3);
        let e = 1.4e-7;
        let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        for north in [false, true] {
            let sign = if north { -1.0 } else { 1.0 };
            let sun = [e * c, -sign * c, s];
            let (dr, _, _) = towards_sun(&sun, 1.0).unwrap();
            assert!((dr - sign).abs() < 1e-13 && dr != sign, "{dr}");
            let answers: Vec<bool> = (2..ny - 2)
                .map(|i| {
                    let shadow = (i as f64 + 2.0 * sign) as usize;
                    past_a_shadow((i, 1), (ny, nx), &sun, |r, _| r == shadow)
                })
                .collect();
            assert!(
                answers.iter().all(|&a| a == answers[0]),
                "north {north}: {} of {} rows differ from the first",
                answers.iter().filter(|&&a| a != answers[0]).count(),
                answers.len()
            );
        }
    }
}
