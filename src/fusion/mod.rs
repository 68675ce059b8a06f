//! Fusion of shape from shading with an absolute DEM (Herbort, Grumpe & Wöhler; docs/science.md).
//!
//! [`fuse`] runs the albedo outer loop: at each stage m it inverts R(ρ; μ0, μ, g) = I pixel by
//! pixel on the current surface, low-passes ρ with a masked Gaussian of width σ_ρ⁽ᵐ⁾, and then
//! minimises the energy of [`objective`] over z with that albedo, using the selected
//! [`SolverKind`]. The final albedo is the per-pixel inversion on the final surface, lightly
//! smoothed.

mod fast;
pub mod objective;
pub mod ops;
mod paper;
pub mod support;

pub use objective::Energy;

use crate::photometry::{Albedo, ReflectanceModel, Vec3};
use crate::spectral::{self, Dct2d};
use ndarray::{Array2, ArrayView2, Zip};
use objective::Objective;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Unit vectors (east, north, up) to the Sun or to the camera: one for the whole grid, or one
/// per pixel (as M3's OBS backplanes give them).
#[derive(Debug, Clone)]
pub enum Directions {
    Uniform(Vec3),
    PerPixel(Array2<Vec3>),
}

impl Directions {
    #[inline]
    pub fn at(&self, i: usize, j: usize) -> &Vec3 {
        match self {
            Directions::Uniform(v) => v,
            Directions::PerPixel(a) => &a[(i, j)],
        }
    }
}

/// One fusion problem on a locally metric grid (row 0 north, column 0 west).
pub struct Problem<'a> {
    /// Observed reflectance I in the model's units (sr⁻¹ for Hapke); NaN = no data.
    pub image: ArrayView2<'a, f64>,
    /// Input DEM resampled to the grid, metres; must be finite everywhere.
    pub dem: ArrayView2<'a, f64>,
    /// Grid spacing ε in metres (equal in x and y).
    pub spacing: f64,
    /// Standard deviation, in grid pixels, of the input DEM's own point-spread relative to the
    /// grid (0 = the seed's plain DEM term). See [`dem_psf_sigma`].
    pub dem_psf_sigma: f64,
    pub sun: Directions,
    pub view: Directions,
    pub model: &'a dyn ReflectanceModel,
    /// Ī, the intensity scale E_I is normalised by. `None`: the mean of the usable pixels of
    /// this image. A tiled run passes the mean over the whole region, so every tile weighs
    /// E_I against the DEM terms alike (no tile-to-tile offsets).
    pub intensity_scale: Option<f64>,
}

/// Effective Gaussian point-spread, in grid pixels, of a DEM sampled `factor` times coarser than
/// the grid and resampled to it bilinearly: an anti-alias low-pass of σ = factor/2 plus the box
/// of one coarse pixel (variance factor²/12) plus the bilinear tent (variance factor²/6) give
/// σ² = factor²/4 + factor²/4, σ = factor/√2 (≈ 2.8 px at 4× coarser).
pub fn dem_psf_sigma(factor: f64) -> f64 {
    if factor <= 1.0 {
        0.0
    } else {
        factor / std::f64::consts::SQRT_2
    }
}

/// Default σ_DEM, in grid pixels, for a DEM whose independent heights are `factor` grid pixels
/// apart: 0.75 × factor (at least 1 px) up to 4× coarser, where it reaches the 3 px tuned on
/// the demo scene, then max(3, 0.35 × factor). What matters most for a coarse DEM is its point
/// spread B ([`dem_psf_sigma`], from the *effective* resolution); σ_DEM low-passes the
/// comparison: wide enough to keep the DEM's noise and interpolation ramps out of E_DEM,
/// narrow enough to keep the slopes a fine DEM does resolve (docs/science.md, "The DEM's
/// resolution").
pub fn dem_sigma(factor: f64) -> f64 {
    if factor <= 4.0 {
        (0.75 * factor).max(1.0)
    } else {
        (0.35 * factor).max(3.0)
    }
}

/// Which z-solver minimises each stage's energy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum SolverKind {
    /// Gauss–Newton on z with conjugate gradients preconditioned in the DCT basis.
    Fast,
    /// The seed's Eq. 2: p ← z_x + (1/γ)(I−R)R_p + …, z ← z̄ − (ε²/κ)(p_x + q_y), κ = 4.
    Paper,
}

/// Solver parameters. Intensities are divided by their mean over usable pixels, heights are in
/// metres and slopes dimensionless, so the weights below are per-pixel and transfer between
/// scenes and pixel sizes (docs/science.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FusionParams {
    pub solver: SolverKind,
    /// γ: weight of E_int in the seed's iteration; there it only sets the step ε²/(2κγ).
    pub gamma: f64,
    /// δ: weight of the low-passed DEM gradient term.
    pub delta: f64,
    /// η: weight of the membrane regulariser ‖∇(z − z_DEM)‖².
    pub eta: f64,
    /// σ_DEM in pixels.
    pub sigma_dem: f64,
    /// σ_ρ of each albedo stage, in pixels (the seed: ~100 down to ~10).
    pub albedo_sigmas: Vec<f64>,
    /// σ of the final albedo map (per-pixel inversion on the final surface), in pixels.
    pub final_albedo_sigma: f64,
    /// Pixels with I/Ī below this are treated as cast shadow and drop out of E_I.
    pub shadow_threshold: f64,
    /// Iteration limit per stage (Gauss–Newton steps for `fast`, sweeps for `paper`).
    pub max_iterations: usize,
    /// A stage stops when an iteration lowers E by less than this fraction (for `fast` a
    /// guard against stagnation: it stops on `step_tolerance`).
    pub tolerance: f64,
    /// A `fast` stage stops when no height changes by more than this many grid spacings ε in
    /// one Gauss–Newton step (0.01: 1.4 m at 140 m/px). The largest change is local, where
    /// the energy decrease is a sum over the domain, so a tile and the whole region stop
    /// equally converged at every pixel (docs/science.md, "Tiles").
    pub step_tolerance: f64,
    /// `fast`: pixels whose |I − R|/Ī exceeds this add the residual curvature −2r∇²R (its
    /// positive semi-definite part) to the Gauss–Newton Hessian; a value above any residual
    /// (say 1e9) gives plain Gauss–Newton.
    pub curvature_residual: f64,
    /// Conjugate-gradient limit per Gauss–Newton step.
    pub cg_iterations: usize,
    /// Relative residual at which conjugate gradients stop.
    pub cg_tolerance: f64,
}

impl Default for FusionParams {
    fn default() -> Self {
        Self {
            solver: SolverKind::Fast,
            gamma: 2.5,
            delta: 50.0,
            eta: 0.1,
            sigma_dem: 3.0,
            albedo_sigmas: vec![100.0, 10.0, 4.0],
            final_albedo_sigma: 1.5,
            shadow_threshold: 0.1,
            max_iterations: 30,
            tolerance: 1e-9,
            step_tolerance: 0.01,
            curvature_residual: 0.05,
            cg_iterations: 60,
            cg_tolerance: 0.1,
        }
    }
}

impl FusionParams {
    /// Defaults for the `paper` solver: thousands of sweeps are needed.
    pub fn paper() -> Self {
        Self {
            solver: SolverKind::Paper,
            max_iterations: 20000,
            tolerance: 1e-9,
            ..Self::default()
        }
    }
}

/// What went wrong before any solving.
#[derive(Debug, thiserror::Error)]
pub enum FusionError {
    #[error("image is {image:?} pixels but the DEM is {dem:?}: they must be on one grid")]
    Shape {
        image: (usize, usize),
        dem: (usize, usize),
    },
    #[error("the grid is {0:?} pixels: fusion needs at least 3 × 3")]
    TooSmall((usize, usize)),
    #[error("grid spacing must be a positive number of metres, got {0}")]
    Spacing(f64),
    #[error("the input DEM has a non-finite height at row {row}, column {col}: fill or crop no-data before fusion")]
    DemNotFinite { row: usize, col: usize },
    #[error("no pixel has a usable observation (valid, lit and above the shadow threshold)")]
    NoObservations,
    #[error("invalid parameter {name} = {value}: {why}")]
    Parameter {
        name: &'static str,
        value: f64,
        why: &'static str,
    },
    #[error("per-pixel direction array is {got:?} pixels, the grid {want:?}")]
    DirectionShape {
        got: (usize, usize),
        want: (usize, usize),
    },
}

/// One iteration's record.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IterationRecord {
    pub iteration: usize,
    pub energy: Energy,
    /// Conjugate-gradient iterations (fast) or 0 (paper).
    pub inner: usize,
    /// The largest height change of this iteration, metres (0 at the start).
    #[serde(default)]
    pub max_step: f64,
}

/// One albedo stage's record.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StageReport {
    pub sigma_rho: f64,
    pub iterations: Vec<IterationRecord>,
    pub seconds: f64,
}

/// The fused products.
#[derive(Debug, Clone)]
pub struct Fusion {
    /// Heights, metres, same datum as the input DEM.
    pub height: Array2<f64>,
    /// Albedo (Hapke w for the Hapke model); NaN off the image's footprint.
    pub albedo: Array2<f64>,
    /// |I − R| at the solution where the pixel carried photometric information, NaN elsewhere.
    pub residual: Array2<f64>,
    /// True where the pixel carried photometric information at the solution.
    pub photometric: Array2<bool>,
    /// s ∈ [0, 1], the photometric support ([`support`]): the result is
    /// z_DEM + s·(z − z_DEM), so it is the input DEM wherever s = 0.
    pub support: Array2<f64>,
    pub stages: Vec<StageReport>,
}

impl Fusion {
    pub fn iterations(&self) -> usize {
        self.stages
            .iter()
            .map(|s| s.iterations.len().saturating_sub(1))
            .sum()
    }
}

fn validate(pr: &Problem, params: &FusionParams) -> Result<(), FusionError> {
    let dim = pr.dem.dim();
    if pr.image.dim() != dim {
        return Err(FusionError::Shape {
            image: pr.image.dim(),
            dem: dim,
        });
    }
    if dim.0 < 3 || dim.1 < 3 {
        return Err(FusionError::TooSmall(dim));
    }
    if !(pr.spacing.is_finite() && pr.spacing > 0.0) {
        return Err(FusionError::Spacing(pr.spacing));
    }
    if let Some(((row, col), _)) = pr.dem.indexed_iter().find(|(_, h)| !h.is_finite()) {
        return Err(FusionError::DemNotFinite { row, col });
    }
    for d in [&pr.sun, &pr.view] {
        if let Directions::PerPixel(a) = d {
            if a.dim() != dim {
                return Err(FusionError::DirectionShape {
                    got: a.dim(),
                    want: dim,
                });
            }
        }
    }
    let checks: [(&'static str, f64, bool, &'static str); 9] = [
        ("gamma", params.gamma, params.gamma > 0.0, "must be > 0"),
        ("delta", params.delta, params.delta >= 0.0, "must be ≥ 0"),
        ("eta", params.eta, params.eta >= 0.0, "must be ≥ 0"),
        (
            "sigma_dem",
            params.sigma_dem,
            params.sigma_dem >= 0.0,
            "must be ≥ 0",
        ),
        (
            "dem_psf_sigma",
            pr.dem_psf_sigma,
            pr.dem_psf_sigma >= 0.0,
            "must be ≥ 0",
        ),
        (
            "final_albedo_sigma",
            params.final_albedo_sigma,
            params.final_albedo_sigma >= 0.0,
            "must be ≥ 0",
        ),
        (
            "shadow_threshold",
            params.shadow_threshold,
            params.shadow_threshold >= 0.0,
            "must be ≥ 0",
        ),
        (
            "step_tolerance",
            params.step_tolerance,
            params.step_tolerance >= 0.0,
            "must be ≥ 0 (grid spacings)",
        ),
        (
            "curvature_residual",
            params.curvature_residual,
            params.curvature_residual >= 0.0,
            "must be ≥ 0 (a large value such as 1e9 turns the curvature term off)",
        ),
    ];
    for (name, value, ok, why) in checks {
        if !ok || !value.is_finite() {
            return Err(FusionError::Parameter { name, value, why });
        }
    }
    if params.delta == 0.0 && params.eta == 0.0 {
        return Err(FusionError::Parameter {
            name: "delta",
            value: 0.0,
            why: "delta and eta cannot both be 0: nothing would fix relief across the Sun",
        });
    }
    if let Some(&s) = params
        .albedo_sigmas
        .iter()
        .find(|s| !(s.is_finite() && **s >= 0.0))
    {
        return Err(FusionError::Parameter {
            name: "albedo_sigmas",
            value: s,
            why: "every σ_ρ must be ≥ 0",
        });
    }
    Ok(())
}

/// Pixel-wise albedo inversion on surface `z`: the raw values and where they are defined.
pub fn invert_albedo(
    pr: &Problem,
    z: ArrayView2<f64>,
    usable: &Array2<bool>,
) -> (Array2<f64>, Array2<bool>) {
    let (p, q) = ops::gradient(z, pr.spacing);
    let dim = z.dim();
    let mut rho = Array2::zeros(dim);
    let mut ok = Array2::from_elem(dim, false);
    Zip::indexed(&mut rho)
        .and(&mut ok)
        .par_for_each(|(i, j), rho, ok| {
            if !usable[(i, j)] {
                return;
            }
            if let Albedo::Value(w) = pr.model.invert(
                pr.image[(i, j)],
                p[(i, j)],
                q[(i, j)],
                pr.sun.at(i, j),
                pr.view.at(i, j),
            ) {
                *rho = w;
                *ok = true;
            }
        });
    (rho, ok)
}

/// The image the model renders from surface `z` with albedo `rho`: R(p, q, ρ; s, v) at every
/// pixel (0 where the surface faces away from the Sun or the camera).
pub fn render(pr: &Problem, z: ArrayView2<f64>, rho: ArrayView2<f64>) -> Array2<f64> {
    let (p, q) = ops::gradient(z, pr.spacing);
    let mut out = Array2::zeros(z.dim());
    Zip::indexed(&mut out).par_for_each(|(i, j), r| {
        *r = pr
            .model
            .shade(
                p[(i, j)],
                q[(i, j)],
                rho[(i, j)],
                pr.sun.at(i, j),
                pr.view.at(i, j),
            )
            .r;
    });
    out
}

/// Masked Gaussian of the per-pixel albedo on surface `z`.
fn albedo_map(
    pr: &Problem,
    dct: &Dct2d,
    z: ArrayView2<f64>,
    usable: &Array2<bool>,
    sigma: f64,
) -> Result<Array2<f64>, FusionError> {
    let (raw, ok) = invert_albedo(pr, z, usable);
    spectral::masked_gaussian(dct, &raw, &ok, sigma).ok_or(FusionError::NoObservations)
}

/// The final albedo: the per-pixel inversion on the final surface, smoothed by
/// `final_albedo_sigma` where it is defined; pixels without an inversion (shadow, no data) take
/// the wider last-stage estimate (σ_ρ of the last stage), which draws on more context.
fn final_albedo(
    pr: &Problem,
    dct: &Dct2d,
    z: ArrayView2<f64>,
    usable: &Array2<bool>,
    params: &FusionParams,
) -> Result<Array2<f64>, FusionError> {
    let (raw, ok) = invert_albedo(pr, z, usable);
    // Weight each inversion by its brightness²: dim pixels (near the terminator) amplify slope
    // errors into albedo errors by ∂w/∂R ∝ 1/R.
    let weights = Zip::from(&pr.image)
        .and(&ok)
        .map_collect(|&i, &k| if k { i * i } else { 0.0 });
    let fine = spectral::weighted_gaussian(dct, &raw, &weights, params.final_albedo_sigma)
        .ok_or(FusionError::NoObservations)?;
    let wide_sigma = params
        .albedo_sigmas
        .last()
        .copied()
        .unwrap_or(params.final_albedo_sigma)
        .max(params.final_albedo_sigma);
    let wide =
        spectral::masked_gaussian(dct, &raw, &ok, wide_sigma).ok_or(FusionError::NoObservations)?;
    Ok(Zip::from(&fine)
        .and(&wide)
        .and(&ok)
        .map_collect(|&f, &w, &k| if k { f } else { w }))
}

/// Validate the problem and set up its energy: Ī and the usable-pixel mask.
fn objective<'a, 'p>(
    pr: &'a Problem<'p>,
    params: &FusionParams,
) -> Result<Objective<'a, 'p>, FusionError> {
    validate(pr, params)?;
    let valid = pr.image.mapv(|v| v.is_finite() && v > 0.0);
    let count = valid.iter().filter(|&&b| b).count();
    if count == 0 {
        return Err(FusionError::NoObservations);
    }
    let scale = match pr.intensity_scale {
        Some(s) if s.is_finite() && s > 0.0 => s,
        Some(s) => {
            return Err(FusionError::Parameter {
                name: "intensity_scale",
                value: s,
                why: "must be a positive mean reflectance",
            })
        }
        None => {
            Zip::from(&pr.image)
                .and(&valid)
                .fold(0.0, |s, &v, &ok| if ok { s + v } else { s })
                / count as f64
        }
    };
    let usable = Zip::from(&pr.image)
        .and(&valid)
        .map_collect(|&v, &ok| ok && v / scale >= params.shadow_threshold);
    Ok(Objective::new(
        pr,
        params.delta,
        params.eta,
        params.sigma_dem,
        pr.dem_psf_sigma,
        scale,
        usable,
    ))
}

/// Run the whole fusion: albedo stages, each followed by a surface solve.
pub fn fuse(pr: &Problem, params: &FusionParams) -> Result<Fusion, FusionError> {
    let obj = objective(pr, params)?;
    let mut z = pr.dem.to_owned();
    let mut stages = Vec::new();
    for &sigma in &params.albedo_sigmas {
        let t0 = Instant::now();
        let rho = albedo_map(pr, &obj.dct, z.view(), &obj.observed, sigma)?;
        let iterations = minimise(&obj, &mut z, rho.view(), params, &mut |_| {});
        stages.push(StageReport {
            sigma_rho: sigma,
            iterations,
            seconds: t0.elapsed().as_secs_f64(),
        });
    }
    // Beyond the support band the result is the input DEM; within it the correction fades.
    Zip::from(&mut z)
        .and(&obj.support)
        .and(pr.dem)
        .par_for_each(|z, &s, &d| *z = d + s * (*z - d));
    let mut albedo = final_albedo(pr, &obj.dct, z.view(), &obj.observed, params)?;
    let photo = obj.photo(z.view(), albedo.view());
    // Off the image's footprint the albedo would only be the smoothing's fill: no data.
    Zip::from(&mut albedo).and(pr.image).for_each(|a, &i| {
        if !i.is_finite() {
            *a = f64::NAN;
        }
    });
    let residual = Zip::from(&photo.res)
        .and(&photo.used)
        .map_collect(|&r, &u| if u { (r * obj.scale).abs() } else { f64::NAN });
    Ok(Fusion {
        height: z,
        albedo,
        residual,
        photometric: photo.used,
        support: obj.support,
        stages,
    })
}

/// The state at the starting surface, reported to `observe` and logged as iteration 0 (shared
/// by both solvers).
fn start(
    obj: &Objective,
    z: &Array2<f64>,
    rho: ArrayView2<f64>,
    observe: &mut dyn FnMut(&Energy),
) -> (objective::Iterate, Vec<IterationRecord>) {
    let it = obj.evaluate(z, rho);
    observe(&it.energy);
    let log = vec![IterationRecord {
        iteration: 0,
        energy: it.energy,
        inner: 0,
        max_step: 0.0,
    }];
    (it, log)
}

fn minimise(
    obj: &Objective,
    z: &mut Array2<f64>,
    rho: ArrayView2<f64>,
    params: &FusionParams,
    observe: &mut dyn FnMut(&Energy),
) -> Vec<IterationRecord> {
    match params.solver {
        SolverKind::Fast => fast::minimise(obj, z, rho, params, observe),
        SolverKind::Paper => paper::minimise(obj, z, rho, params, observe),
    }
}

/// The albedo map of the first stage (σ_ρ = `params.albedo_sigmas[0]`) on the input DEM.
pub fn initial_albedo(pr: &Problem, params: &FusionParams) -> Result<Array2<f64>, FusionError> {
    let obj = objective(pr, params)?;
    let sigma = params
        .albedo_sigmas
        .first()
        .copied()
        .unwrap_or(params.final_albedo_sigma);
    albedo_map(pr, &obj.dct, pr.dem, &obj.observed, sigma)
}

/// Solve one surface problem at fixed albedo from `z`, calling `observe` after each iteration
/// with the current energy (the benchmark times convergence with it).
pub fn solve_fixed_albedo(
    pr: &Problem,
    params: &FusionParams,
    rho: ArrayView2<f64>,
    z: &mut Array2<f64>,
    observe: &mut dyn FnMut(&Energy),
) -> Result<Vec<IterationRecord>, FusionError> {
    let obj = objective(pr, params)?;
    Ok(minimise(&obj, z, rho, params, observe))
}

/// Anchor a fused surface to the input DEM at large scales: z − s·G_σ ∗ (z − z_DEM), a
/// Gaussian of `sigma` pixels with mirror boundaries, weighted by the photometric support s
/// ([`Fusion::support`]) so that where the result is the input DEM it stays so. Where the
/// image covers the domain every term of E constrains gradients only, so the level of z (the
/// mean of z − z_DEM) is otherwise fixed by the domain the solver ran on; this makes it the
/// DEM's, locally, whatever the domain — the same on a tile with a halo ≥ 3σ as on the whole
/// region.
pub fn anchor(
    z: &Array2<f64>,
    dem: ArrayView2<f64>,
    support: ArrayView2<f64>,
    sigma: f64,
) -> Array2<f64> {
    let (ny, nx) = z.dim();
    let dct = Dct2d::new(ny, nx);
    let diff = Zip::from(z).and(dem).map_collect(|&a, &b| a - b);
    let low = spectral::gaussian_filter(&dct, &diff, sigma);
    Zip::from(z)
        .and(&low)
        .and(support)
        .map_collect(|&a, &l, &s| a - s * l)
}
