//! The fusion energy as a function of the surface z (slopes dimensionless, z in metres):
//!
//! E(z) = E_I + δ·E_DEM + η·E_reg, with
//! * E_I   = Σ_k Σ_x w_k(x)·(I_k/g_k − R(p, q, ρ; s_k, v_k))²/Ī² over the observations k,
//!   (p, q) the central-difference gradient of z, summed over the pixels each observation saw
//!   lit: valid, not image-shadowed (I_k/g_k/Ī_k ≥ threshold, Ī_k its own mean), seen by the
//!   camera (μ > 0), and within the selection; w_k and the gains g_k are those of
//!   [`super::observations`]. R is continued through μ0 = 0
//!   ([`crate::photometry::ReflectanceModel::shade_observed`]),
//!   so a surface turned away from the Sun at an observed-lit pixel is penalised, not dropped;
//!   an observation coarser than the grid compares its image with B_k R instead, B_k its blur
//!   ([`super::blur`], [`Objective::blurred_terms`]);
//! * E_DEM = Σ ‖f_σ(∇ B z) − f_σ(∇ z_DEM)‖², f_σ the Gaussian low-pass of width σ_DEM, B the
//!   input DEM's own point-spread (identity for the seed's plain term);
//! * E_reg = Σ ω(x)·‖∇(z − z_DEM)‖², the membrane regulariser, ω = 1 unless the opt-in
//!   edge-aware weights of [`Objective::set_membrane_weights`] are set for a stage;
//! * E_tie = Σ κ(x)·((z − z_DEM)/ε)², κ = κ₀·max(1 − s, 1 − 2c, 0), which holds the surface to
//!   the input DEM where no image constrains it: s the photometric support of
//!   [`super::support`] (1 within σ_s of the image's footprint, 0 beyond 3σ_s), c below (a
//!   swath's edge has c ≈ ½ and is left free; a strip narrower than ≈ 1.25 σ_B is held);
//!   κ₀ = (δ + η)/σ_s², so the tie takes over from the DEM-gradient term within about σ_s.
//!
//! Where the image covers B's whole neighbourhood, E_DEM compares the solution *blurred by the
//! DEM's own point spread* with the DEM, so the image may supply the detail the DEM lost. Away
//! from the image there is no such detail, and matching B z to z_DEM would deconvolve the
//! DEM; there the target is B z_DEM instead, whose minimiser is z = z_DEM itself. Between, the
//! target is T = c·z_DEM + (1 − c)·B z_DEM with c = G_σB ∗ [image covers the pixel], the
//! share of B's neighbourhood the image sees: a fixed field, so E_DEM stays DCT-diagonal.
//!
//! ∇ in the last two is the forward difference with Neumann boundaries and the Gaussians act on
//! gradient fields through their antisymmetric extension, so f_σ∇ = ∇f_σ and both terms are
//! diagonal in the DCT-II basis: E_DEM = Σ_kl (λ_kl/ε²)(ĝ_s ẑ − ĝ_σ T̂)², ĝ_s = ĝ_σ·ĝ_B,
//! E_reg = Σ_kl (λ_kl/ε²)(ẑ − ẑ_DEM)².
//!
//! The seed's integrability term γ·E_int couples auxiliary gradients (p, q) to z. Its Eq. 2
//! evaluates R at z_x, z_y, which makes γ a step size (docs/science.md): both solvers minimise the
//! E(z) above, where E_int = 0.

use super::blur;
use super::observations::{self, Weights};
use super::ops;
use super::shadows::{self, ShadowState, ShadowTerm};
use super::support;
use super::Problem;
use crate::photometry::ReflectanceModel;
use crate::spectral::{self, to, Dct2d, Real};
use ndarray::{Array2, ArrayView2, Axis, Zip};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The terms of the energy at one iterate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
pub struct Energy {
    /// E_I.
    pub intensity: f64,
    /// E_int = Σ‖∇z − (p, q)‖² of the `paper` solver's auxiliary gradients (0 for `fast`).
    pub integrability: f64,
    /// E_DEM (unweighted).
    pub dem: f64,
    /// E_reg (unweighted).
    pub membrane: f64,
    /// E_tie (its weight κ(x) is inside).
    #[serde(default)]
    pub tie: f64,
    /// E_S, the cast shadows' term (its weight λ inside; [`super::shadows`]).
    #[serde(default)]
    pub shadow: f64,
    /// E_I + δ·E_DEM + η·E_reg + E_tie + E_S.
    pub total: f64,
}

/// Photometric quantities of one observation at the current surface: residual
/// r = (I/g − R)/Ī and a = ∂R/∂p/Ī, b = ∂R/∂q/Ī, all zero where the pixel is not used.
/// Computed in f64 and stored in f32: they feed the gradient and the Newton systems (solved
/// in f32), where a relative rounding of 6·10⁻⁸ is far below the conjugate gradients'
/// tolerance; E_I itself is summed from the f64 residuals ([`Photo::intensity`]), and the
/// residual curvature re-evaluates R's slope in f64 ([`Objective::curvature`]).
pub struct ObsPhoto {
    pub res: Array2<f32>,
    pub a: Array2<f32>,
    pub b: Array2<f32>,
    pub used: Array2<bool>,
}

/// Photometric quantities of all observations at the current surface, and E_I (w_k the
/// per-pixel weights of [`Weights`]). The weighted sums over the observations that the
/// gradient and the Newton systems need are formed where they are used
/// ([`Objective::add_photo_gradient`], [`Objective::add_gauss_newton_hessian`]), not stored: a line
/// search's trial would store them for nothing.
pub struct Photo {
    pub obs: Vec<ObsPhoto>,
    /// E_I = Σ_k Σ w_k r_k².
    pub intensity: f64,
    /// True where at least one observation is used.
    pub used: Array2<bool>,
    /// E_S and the rays it holds at the surface: those engaged for the stage, or before any
    /// stage the violated ones (empty without the term).
    pub shadow: ShadowState,
}

/// The state at one iterate z.
pub struct Iterate {
    pub photo: Photo,
    /// ẑ, the DCT coefficients of z.
    pub zh: Array2<f64>,
    pub energy: Energy,
}

/// How a stage weighs the membrane ([`Objective::set_membrane_weights`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MembraneRule {
    /// k of the edge-aware membrane (a slope; 0: off).
    pub slope: f64,
    /// f: the membrane's factor where several observations carry a pixel.
    pub multi_factor: f64,
    /// k_m: the edge-aware membrane's slope where several observations carry a pixel (0:
    /// plain there).
    pub multi_slope: f64,
    /// S₀: where several observations carry a pixel the membrane is scaled by
    /// min(1, √(S/S₀)) of their photometric stiffness S (0: off).
    pub stiffness: f64,
}

/// e(k) = 1/√(1 + g²/k²) for a correction slope of squared size g² (1 when k = 0): the
/// edge-aware membrane's factor ([`Objective::set_membrane_weights`]).
fn edge_factor(g2: f64, k: f64) -> f64 {
    if k > 0.0 {
        1.0 / (1.0 + g2 / (k * k)).sqrt()
    } else {
        1.0
    }
}

impl MembraneRule {
    /// The rule of `params`.
    pub fn of(params: &super::FusionParams) -> Self {
        Self {
            slope: params.edge_membrane_slope,
            multi_factor: params.multi_eta_factor,
            multi_slope: params.multi_edge_membrane_slope,
            stiffness: params.multi_eta_stiffness,
        }
    }
}

/// The DEM term's factors where several observations carry a pixel
/// ([`Objective::with_multi_delta`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MultiDelta {
    /// f: δ × f where several observations carry a pixel (1: δ everywhere).
    pub factor: f64,
    /// f_all: towards δ × f_all where they measure slope free of albedo in every direction.
    pub all: f64,
    /// f_high: towards δ × f_high where their Suns stand high.
    pub high_sun: f64,
    /// f_high,ew ≤ f_high: what f_high becomes where those high Suns also measure east–west
    /// slopes free of albedo ([`observations::east_west_unmeasured`] small).
    pub high_sun_east_west: f64,
    /// f_ew: towards δ × f_ew where they measure east–west slopes free of albedo.
    pub east_west: f64,
}

impl MultiDelta {
    /// The factors of `params`.
    pub fn of(params: &super::FusionParams) -> Self {
        Self {
            factor: params.multi_delta_factor,
            all: params.multi_delta_factor_all,
            high_sun: params.multi_delta_factor_high_sun,
            high_sun_east_west: params.multi_delta_factor_high_sun_east_west,
            east_west: params.multi_delta_factor_east_west,
        }
    }

    /// f everywhere several observations carry a pixel, whatever their Suns.
    pub fn uniform(factor: f64) -> Self {
        Self {
            factor,
            all: factor,
            high_sun: factor,
            high_sun_east_west: factor,
            east_west: factor,
        }
    }
}

/// Precomputed operators for one problem.
pub struct Objective<'a, 'p> {
    pub problem: &'a Problem<'p>,
    pub dct: Dct2d,
    /// The transform of f32 arrays, for the conjugate-gradient iterations of `fast`'s Newton
    /// steps.
    pub dct_cg: Dct2d<f32>,
    /// λ_kl/ε².
    pub lam: spectral::LaplacianSymbol,
    /// 1/ℓ² (m⁻²; 0: none): E_DEM measures the heights of the blurred difference u as well as
    /// its gradients, Σ|∇u|² + Σu²/ℓ², so that at wavelengths beyond 2πℓ the DEM's heights,
    /// not only its slopes, hold the surface ([`Objective::with_dem_height_length`]).
    pub dem_height: f64,
    /// ĝ_s = ĝ_σDEM·ĝ_B (solution side). Stored in f32 and widened exactly wherever it is
    /// used, so that the energy, its gradient, its Hessian and the preconditioner all see the
    /// same operator (the f32-rounded filter, within 6·10⁻⁸ of the f64 one).
    pub gs: Array2<f32>,
    /// ĝ_σDEM·T̂, T = c·z_DEM + (1 − c)·B z_DEM (DEM side, constant; see the module
    /// documentation). In f32: its rounding moves the target by ≈ 10⁻⁷ of the heights (under
    /// a millimetre on the Moon), far below any DEM's error.
    pub dem_target: Array2<f32>,
    /// ẑ_DEM, the membrane's anchor, in f32 for the same reason.
    pub dem_hat: Array2<f32>,
    pub delta: f64,
    pub eta: f64,
    /// Ī: intensities are divided by it.
    pub scale: f64,
    /// Each observation's usable pixels, weights w_k(x) and gain g_k.
    pub weights: Weights,
    /// The support band (r₀, r₁) of [`support::band`]: s = 1 within r₀ of the image's
    /// footprint, 0 beyond r₁ ([`Objective::support`]).
    pub band: (f64, f64),
    /// κ(x)/ε², the tie's per-pixel weight; `None` when the image covers every pixel.
    pub tie: Option<Array2<f64>>,
    /// r(x) = (1 − f)·c(x): where several observations carry a pixel (multi-coverage c of
    /// [`Weights::multiplicity`]) the DEM term's weight there is δ·(1 − r), down to δ·f
    /// ([`Objective::with_multi_delta`]); `None`: δ everywhere.
    pub dem_relief: Option<Array2<f64>>,
    /// r_η(x) = 1 − ω(x): the membrane's weight at x is η·ω(x)
    /// ([`Objective::set_membrane_weights`]); `None`: η everywhere.
    pub membrane_relief: Option<Array2<f64>>,
    /// c_R(x), the multi-coverage of the regularisers where it differs from c(x)
    /// ([`Objective::with_shadow_cover`]); `None`: c(x) of [`Weights::multiplicity`].
    pub coverage: Option<Array2<f64>>,
    /// B_k of each observation coarser than the grid ([`super::blur`]); `None`: sharp.
    pub kernels: Vec<Option<blur::Kernel>>,
    /// E_S, the cast shadows' rays ([`Objective::with_shadows`]).
    pub shadows: Option<ShadowTerm>,
    /// ν(x), how much of each pixel's albedo follows its slopes in the Gauss–Newton steps
    /// ([`Objective::set_albedo_coupling`]); `None`: the albedo is held (ν = 0).
    pub albedo_coupling: Option<Array2<f64>>,
}

/// What the Newton operator needs of an observation coarser than the grid: its part of E_I's
/// Gauss–Newton Hessian is Dᵀ Aᵀ B (2W) B A D, A = (a, b) per pixel, not a per-pixel matrix
/// ([`Objective::blurred_terms`]).
pub struct BlurTerm {
    pub kernel: blur::Kernel,
    pub a: Array2<f32>,
    pub b: Array2<f32>,
    /// 2w_k on the pixels used, 0 elsewhere.
    pub w2: Array2<f32>,
}

impl<'a, 'p> Objective<'a, 'p> {
    pub fn new(
        problem: &'a Problem<'p>,
        delta: f64,
        eta: f64,
        sigma_dem: f64,
        psf: f64,
        scale: f64,
        weights: Weights,
    ) -> Self {
        let (ny, nx) = problem.dem.dim();
        let dct = Dct2d::new(ny, nx);
        let e2 = problem.spacing * problem.spacing;
        let lam = spectral::LaplacianSymbol::new(ny, nx, problem.spacing);
        let gd = spectral::gaussian_table(ny, nx, sigma_dem);
        let gb = spectral::gaussian_table(ny, nx, psf);
        let gs = Zip::from(&gd).and(&gb).map_collect(|&d, &b| (d * b) as f32);
        let dem_hat = dct.forward(&problem.dem.to_owned());
        let (r0, r1) = support::band(sigma_dem);
        let covered = problem.footprint();
        let (dem_target, tie) = if covered.iter().all(|&c| c) {
            (&gd * &dem_hat, None)
        } else {
            // How much of B's neighbourhood the image covers: the share of the DEM's blur that
            // the image can undo.
            let cover = spectral::gaussian_filter(
                &dct,
                &covered.mapv(|c| if c { 1.0 } else { 0.0 }),
                psf.max(1.0),
            )
            .mapv(|c| c.clamp(0.0, 1.0));
            let blurred = dct.inverse(&(&gb * &dem_hat));
            let target = Zip::from(&cover)
                .and(problem.dem)
                .and(&blurred)
                .map_collect(|&c, &d, &b| c * d + (1.0 - c) * b);
            // Held to the DEM off the footprint (1 − s) and where the image sees less than half
            // of B's neighbourhood (1 − 2c): a five-line swath under LDEM_4 (σ_B = 35 px)
            // otherwise drifts by kilometres along the strip, while the edge of a wide swath
            // (c ≈ ½) keeps its correction.
            let kappa0 = (delta + eta) / (r0 * r0);
            let tie = Zip::from(&support::support(&covered, r0, r1))
                .and(&cover)
                .map_collect(|&s, &c| kappa0 * (1.0 - s).max(1.0 - 2.0 * c) / e2);
            (&gd * &dct.forward(&target), Some(tie))
        };
        let f32_of = |a: &Array2<f64>| a.mapv(|x| x as f32);
        let (dem_target, dem_hat) = (f32_of(&dem_target), f32_of(&dem_hat));
        Self {
            problem,
            dct_cg: Dct2d::new_f32(ny, nx),
            dct,
            lam,
            gs,
            dem_target,
            dem_hat,
            delta,
            eta,
            scale,
            weights,
            band: (r0, r1),
            tie,
            kernels: (0..problem.observations.len())
                .map(|k| problem.blur_kernel(k))
                .collect(),
            dem_relief: None,
            membrane_relief: None,
            coverage: None,
            dem_height: 0.0,
            shadows: None,
            albedo_coupling: None,
        }
    }

    /// What stays fixed through the stage that starts from surface `z` with albedo `rho`: the
    /// membrane's weights ([`Objective::set_membrane_weights`]) and E_S's steps and engaged rays
    /// ([`ShadowTerm::fix_steps`]).
    pub fn begin_stage(&mut self, z: ArrayView2<f64>, rho: ArrayView2<f64>, m: MembraneRule) {
        self.set_membrane_weights(z, rho, m);
        if let Some(t) = &mut self.shadows {
            t.fix_steps(z);
        }
    }

    /// Sets f_k, the lit share of each pixel just past an observation's own shadows
    /// ([`super::shadows::lit_fractions`]), on surface `z`, for the stage that starts there,
    /// where `params.partial_shadow` asks for it: E_I then compares I/g with f·R. Shadows are
    /// I/g/Ī_k below `shadow_threshold`, as [`Weights::usable`] finds them; rays walk at most
    /// `shadow_reach_px`.
    pub fn set_lit_fractions(&mut self, z: ArrayView2<f64>, params: &super::FusionParams) {
        if !params.partial_shadow {
            return;
        }
        let blurred: Vec<bool> = self.kernels.iter().map(Option::is_some).collect();
        self.weights.lit = super::shadows::lit_fractions(
            self.problem,
            (&self.weights, self.scale),
            &blurred,
            z,
            (params.shadow_threshold, params.shadow_reach_px),
        );
    }

    /// Adds E_S ([`super::shadows`]) of weight λ = `weight`: the rays of every pixel an
    /// observation sees shadowed (I/g/Ī_k below `threshold`, as the photometric term drops it)
    /// or lit just past a shadow's end (I/g/Ī_k at least `lit_threshold`), each walked at most
    /// `reach_px` steps, forgiven `tolerance` pixels of shadow length, and weighing
    /// `weight_all` instead of 1 where two or more other observations carry the pixel (raised
    /// towards 1 under Suns lower than 30°, [`shadows::ray_weight_all`]) and `weight_alone`
    /// where no other observation sees it. λ = 0 leaves the energy as it was.
    pub fn with_shadows(
        mut self,
        weight: f64,
        tolerance: f64,
        (weight_all, weight_alone): (f64, f64),
        threshold: f64,
        lit_threshold: f64,
        reach_px: usize,
    ) -> Self {
        if weight <= 0.0 || reach_px == 0 {
            return self;
        }
        let w = &self.weights;
        let own: Vec<f64> = w
            .noise
            .iter()
            .map(|&nu| observations::own_mean(self.scale, nu))
            .collect();
        let gains = w.gains.clone();
        let usable = &w.usable;
        // Where two or more other observations carry the pixel, its slopes in every direction
        // are measured and the ray adds mostly its own sub-pixel error, unless its Sun is low
        // and its shadows long ([`shadows::ray_weight_all`]). Where no other
        // observation sees it (lit or not), its ray is the only one: under a low Sun the
        // surface there then ended metres apart on a tile and on the whole region.
        let factor = |k: usize, i: usize, j: usize| {
            let seen = self.problem.seen_by_another(k, (i, j));
            let others = (0..usable.len())
                .filter(|&m| m != k && usable[m][(i, j)])
                .count();
            if !seen {
                weight_alone
            } else if others >= 2 {
                let sun = self.problem.observations[k].sun.at(i, j);
                shadows::ray_weight_all(weight_all, observations::elevation_deg(&sun))
            } else {
                1.0
            }
        };
        let rays = shadows::rays(
            self.problem,
            &|k, v| observations::image_shadowed(v, gains[k], own[k], threshold),
            &|k, v| !observations::image_shadowed(v, gains[k], own[k], lit_threshold),
            &factor,
            reach_px,
        );
        if !rays.is_empty() {
            self.shadows = Some(ShadowTerm {
                rays,
                weight,
                tolerance,
            });
        }
        self
    }

    /// s: the photometric support, 1 on and near the images' footprint (finite I, shadow
    /// included), 0 beyond the band ([`support::support`]). Formed when asked for (the
    /// tie is formed from it once, the end of the fusion tapers the correction with it): it
    /// is not held through the stages.
    pub fn support(&self) -> Array2<f64> {
        support::support(&self.problem.footprint(), self.band.0, self.band.1)
    }

    /// Let E_DEM hold heights as well as gradients beyond the length `length_m` (metres; 0 or
    /// less: gradients only): E_DEM = Σ_x |∇u|² + Σ_x u²/ℓ², u = B_s z − T the blurred
    /// difference. In the DCT basis the weight of a coefficient goes from λ_k/ε² to
    /// λ_k/ε² + 1/ℓ²: unchanged where λ_k/ε² ≫ 1/ℓ² (wavelengths well below 2πℓ), a height tie
    /// above. Gradients alone leave the longest wavelengths to whatever slope bias the
    /// photometric model has: integrated over a region such a bias is a tilt that grows with
    /// its width (docs/science.md, "Long wavelengths").
    pub fn with_dem_height_length(mut self, length_m: f64) -> Self {
        self.dem_height = if length_m > 0.0 && length_m.is_finite() {
            1.0 / (length_m * length_m)
        } else {
            0.0
        };
        self
    }

    /// Weigh E_DEM's across-track slopes of along-track-smooth structure by `weight` (a)
    /// against the rest. Tracks run along the grid's columns (north–south on a north-up grid:
    /// LOLA's orbits are near-polar), and S_t is a Gaussian of `sigma_px` pixels along them:
    ///
    /// E_DEM = Σ_x |∂_y u|² + ⟨∂_x u, (1 − (1 − a)·S_t) ∂_x u⟩ + Σ_x u²/ℓ²,
    ///
    /// u = B_s z − T the blurred difference. A gridded altimetry DEM's largest errors are the
    /// offsets between neighbouring tracks: constant along a track, their east–west slopes are
    /// smooth along the columns, which is the part S_t keeps. Where the image measures those
    /// slopes it should decide them, not the DEM (docs/science.md, "The DEM's tracks"). S_t is
    /// diagonal in the DCT basis (ĝ_t(k_y)), so the term stays diagonal there: each
    /// coefficient's weight goes from λ_k/ε² + h to λ_y/ε² + (1 − (1 − a)ĝ_t)λ_x/ε² + h, which
    /// is folded as the square root of its ratio into ĝ_s and the target T̂. So u itself carries
    /// the weighting, and the relief fields, which lower E_DEM pixel by pixel, lower this form
    /// of it and never more than all of it. S_t reaches 3σ_t along a column: a tile's halo
    /// covers 4σ_t (workflow::auto_halo). Call after [`Self::with_dem_height_length`];
    /// a = 1 changes nothing.
    pub fn with_dem_tracks(mut self, weight: f64, sigma_px: f64) -> Self {
        if weight >= 1.0 {
            return self;
        }
        let (ny, nx) = self.gs.dim();
        let e2 = self.problem.spacing * self.problem.spacing;
        let ly = spectral::laplacian_eigenvalues(ny);
        let lx = spectral::laplacian_eigenvalues(nx);
        let gt = spectral::gaussian_transfer(ny, sigma_px);
        let h = self.dem_height;
        let factor = Array2::from_shape_fn((ny, nx), |(ky, kx)| {
            let (y, x) = (ly[ky] / e2, lx[kx] / e2);
            let all = y + x + h;
            if all > 0.0 {
                ((y + x * (1.0 - (1.0 - weight) * gt[ky]) + h) / all).sqrt()
            } else {
                1.0
            }
        });
        let scale = |a: &mut Array2<f32>| {
            Zip::from(a)
                .and(&factor)
                .for_each(|a, &f| *a = (f64::from(*a) * f) as f32)
        };
        scale(&mut self.gs);
        scale(&mut self.dem_target);
        self
    }

    /// Set the membrane's per-pixel weight η·ω(x) for the albedo stage that starts from
    /// surface `z` with albedo `rho`: ω = (1 − c)·e(k) + c·f·a·e(k_m), c the multi-coverage of
    /// [`Weights::multiplicity`], e(k) = 1/√(1 + |∇(z − z_DEM)|²/k²) (∇ the central
    /// difference; k a slope, e = 1 when k = 0) with k = `m.slope` and k_m = `m.multi_slope`,
    /// f = `m.multi_factor` and a = min(1, √(S/S₀)), S the photometric stiffness of
    /// [`Objective::level_stiffness`] and S₀ = `m.stiffness` (a = 1 when S₀ = 0). Stored as
    /// r_η = 1 − ω.
    ///
    /// The membrane pulls the correction's gradients towards 0, which flattens small craters'
    /// walls and rims (docs/science.md, "Edge-aware membrane"); where the surface already
    /// departs steeply from the DEM it pulls less, like a total-variation penalty
    /// re-linearised once per stage. Where two or more Suns carry a pixel the image fixes
    /// every slope: there the membrane is edge-aware by default (stronger where the correction
    /// is flat, weaker on walls and rims) and scaled by a to the images' own stiffness, since
    /// under a high Sun the shading changes little with slope and a fixed η would hold the
    /// surface to the DEM's gradients (docs/science.md, "Several observations"). ω is fixed
    /// within a stage, so each stage's energy keeps its form.
    pub fn set_membrane_weights(
        &mut self,
        z: ArrayView2<f64>,
        rho: ArrayView2<f64>,
        m: MembraneRule,
    ) {
        self.membrane_relief = None;
        if self.eta == 0.0 {
            return;
        }
        let multi = self.weights.weight.len() > 1
            && (m.multi_factor != 1.0 || m.stiffness > 0.0 || m.multi_slope > 0.0);
        if m.slope <= 0.0 && !multi {
            return;
        }
        let c = self.regulariser_coverage();
        // a(x), only where the stiffness rule is on and observations overlap (1 elsewhere).
        let a = (m.stiffness > 0.0 && c.iter().any(|&c| c > 0.0)).then(|| {
            let s = self.level_stiffness(rho, &c);
            s.mapv(|s| (s / m.stiffness).sqrt().min(1.0))
        });
        let (p, q) = ops::gradient(self.correction(z).view(), self.problem.spacing);
        let r = Zip::indexed(&p)
            .and(&q)
            .and(&c)
            .par_map_collect(|ij, &p, &q, &c| {
                let a = a.as_ref().map_or(1.0, |a| a[ij]);
                let g2 = p * p + q * q;
                let e = edge_factor(g2, m.slope);
                let em = edge_factor(g2, m.multi_slope);
                (1.0 - c) * (1.0 - e) + c * (1.0 - m.multi_factor * a * em)
            });
        if r.iter().any(|&r| r != 0.0) {
            self.membrane_relief = Some(r);
        }
    }

    /// Σ_k u_k·|∇ ln R_k|² at pixel `ij` on a level surface of albedo `rho` over the
    /// observations `k` for which `include(k)` holds ([`Objective::level_stiffness`]).
    fn stiffness_at(&self, ij: (usize, usize), rho: f64, include: impl Fn(usize) -> bool) -> f64 {
        let pr = self.problem;
        let w = &self.weights;
        let mut s = 0.0;
        for (k, ((o, wk), &nu)) in pr
            .observations
            .iter()
            .zip(&w.weight)
            .zip(&w.noise)
            .enumerate()
        {
            let u = f64::from(wk[ij]) / nu;
            if u <= 0.0 || !include(k) {
                continue;
            }
            let sh = pr
                .model
                .shade(0.0, 0.0, rho, &o.sun.at(ij.0, ij.1), &o.view.at(ij.0, ij.1));
            if sh.r > 0.0 {
                s += u * ((sh.dr_dp / sh.r).powi(2) + (sh.dr_dq / sh.r).powi(2));
            }
        }
        s
    }

    /// The photometric stiffness of a level surface, S(x) = Σ_k u_k(x)·|∇ ln R_k|², where
    /// c(x) > 0 (0 elsewhere): ∇ the derivative in the slopes (p, q) at p = q = 0 under the
    /// pixel's own Sun and view and albedo ρ(x), u_k = w_k/ν_k the edge ramp, incidence taper
    /// and shadow-edge factor of [`Weights`] (ν-free, so S is a property of the geometry, not
    /// of the images' brightness). It is the trace of E_I's Gauss–Newton curvature in (p, q),
    /// in units of relative brightness: ≈ 2.6 for two Suns 30–35° above the horizon, ≈ 0.3
    /// for two at 55–60°. An observation that would see the level surface unlit adds nothing.
    pub fn level_stiffness(&self, rho: ArrayView2<f64>, c: &Array2<f64>) -> Array2<f64> {
        Zip::indexed(c)
            .and(rho)
            .par_map_collect(|(i, j), &c, &rho| {
                if c <= 0.0 {
                    return 0.0;
                }
                self.stiffness_at((i, j), rho, |_| true)
            })
    }

    /// The mean of r_η(x) (0 without it): the preconditioner uses η·(1 − mean r_η).
    pub fn mean_membrane_relief(&self) -> f64 {
        self.membrane_relief
            .as_ref()
            .map_or(0.0, |r| ops::sum(r.view()) / r.len() as f64)
    }

    /// z − z_DEM.
    fn correction(&self, z: ArrayView2<f64>) -> Array2<f64> {
        Zip::from(z)
            .and(self.problem.dem)
            .map_collect(|&z, &d| z - d)
    }

    /// Let an observation that sees a pixel shadowed, or next to its own shadow, count towards
    /// the multi-coverage of the regularisers (the membrane's rule, δ·f and the pixel-scale
    /// shrink of the correction, `fusion::fine_stages`): c_R = c + (1 −
    /// min(1, S_c/S₀))·x, c of [`Weights::multiplicity`], x the extra coverage of
    /// [`observations::shadow_cover`] (κ = `kappa`), S_c the photometric stiffness of a level
    /// surface ([`Objective::level_stiffness`]) over only the observations that carry the
    /// pixel away from their own shadows, at the albedo inverted on the input DEM, S₀ =
    /// `stiffness`. Where those observations measure slope firmly (a Sun 20° high: S_c ≥ S₀)
    /// c_R = c exactly; where they barely do (one Sun 60° high, S_c ≈ 0.15) the pixel takes
    /// nearly all of x. (√(S_c/S₀), the membrane's own scale, did 1 % worse on the low + high
    /// pairs, docs/science.md.) Nothing changes with S₀ = 0 or κ = 0. Call it before
    /// [`Objective::with_multi_delta`].
    pub fn with_shadow_cover(
        mut self,
        kappa: f64,
        (threshold, edge_ramp_px): (f64, f64),
        stiffness: f64,
    ) -> Self {
        if stiffness <= 0.0 || kappa <= 0.0 || self.weights.weight.len() < 2 {
            return self;
        }
        let mut c = self.weights.multiplicity();
        let Some(cover) = observations::shadow_cover(
            self.problem,
            (&self.weights, &c),
            self.scale,
            (threshold, edge_ramp_px),
            kappa,
        ) else {
            return self;
        };
        // The albedo of each pixel on the input DEM (where none inverts, the mean of those
        // that do): S_c's albedo, as the stages' stiffness takes each stage's.
        let (rho, ok, _) =
            observations::invert_albedo(self.problem, &self.weights, self.problem.dem, 1.0);
        let (sum, count) =
            Zip::from(&rho).and(&ok).fold(
                (0.0, 0usize),
                |(s, n), &r, &k| if k { (s + r, n + 1) } else { (s, n) },
            );
        let mean = if count > 0 { sum / count as f64 } else { 0.0 };
        Zip::indexed(&mut c)
            .and(&cover.extra)
            .and(&rho)
            .and(&ok)
            .par_for_each(|(i, j), c, &x, &r, &k| {
                if x <= 0.0 {
                    return;
                }
                let r = if k { r } else { mean };
                let s = self.stiffness_at((i, j), r, |k| cover.clean[k][(i, j)]);
                if s > 0.0 {
                    *c += (1.0 - (s / stiffness).min(1.0)) * x;
                }
            });
        self.coverage = Some(c);
        self
    }

    /// The multi-coverage of the regularisers: c_R where [`Objective::with_shadow_cover`] set
    /// it, c(x) of [`Weights::multiplicity`] otherwise.
    pub fn regulariser_coverage(&self) -> Array2<f64> {
        match &self.coverage {
            Some(c) => c.clone(),
            None => self.weights.multiplicity(),
        }
    }

    /// Lower the DEM term's weight to δ·f(x) where several observations carry a pixel,
    /// blended by their multi-coverage c(x): δ(x) = δ·(1 − (1 − f(x))·c(x)), f(x) = the
    /// smallest of `factor` − (`factor` − `factor_all`)·φ(x), `factor` − (`factor` −
    /// f_h(x))·η(x) and `factor` − (`factor` − `factor_east_west`)·ψ(x): φ the share
    /// of the images' albedo-free slope information in its least-measured direction
    /// ([`observations::every_direction`]; 0 for two observations), η how high their Suns stand
    /// ([`observations::high_sun`]), ψ whether they measure east–west slopes free of albedo
    /// ([`observations::east_west_open`]), and f_h = f_high,ew + (f_high − f_high,ew)·
    /// smoothstep((χ − χ₀)/(χ₁ − χ₀)) with χ how much of the east–west direction they leave
    /// unmeasured ([`observations::east_west_unmeasured`], [χ₀, χ₁] =
    /// [`observations::EAST_WEST_UNMEASURED`]): under high Suns that measure the east–west
    /// slopes, in which the DEM's track offsets lie, the DEM may yield more, and there η is
    /// blended towards [`observations::high_sun_east_west`] (from lower Suns on) by
    /// 1 − smoothstep(…) too. With two or more Suns the images
    /// fix most slopes, with three spread in azimuth every one, and the DEM's own errors inside
    /// the σ_DEM passband (track offsets, noise) are then the largest left; under high Suns,
    /// which cast few shadows, more so (docs/science.md, "Several observations"). No effect
    /// where one observation carries a pixel.
    pub fn with_multi_delta(mut self, factors: MultiDelta) -> Self {
        let MultiDelta {
            factor,
            all: factor_all,
            high_sun: factor_high_sun,
            high_sun_east_west: factor_high_sun_ew,
            east_west: factor_east_west,
        } = factors;
        let c = self.regulariser_coverage();
        if factor < 1.0 && c.iter().any(|&c| c > 0.0) {
            let phi = (factor_all < factor && self.weights.weight.len() > 2)
                .then(|| observations::every_direction(self.problem, &self.weights, &c));
            let mut eta = (factor_high_sun < factor)
                .then(|| observations::high_sun(self.problem, &self.weights, &c));
            // Where the images leave little of the east–west direction, in which the DEM's
            // track offsets lie, to the DEM, f_high goes on down to f_high,ew and η follows
            // the wider ramp: t = 0 there, 1 where they leave it all (None: the rule is off).
            let mut t = None;
            if let Some(eta) = eta
                .as_mut()
                .filter(|_| factor_high_sun_ew < factor_high_sun)
            {
                let [x0, x1] = observations::EAST_WEST_UNMEASURED;
                let tt = observations::east_west_unmeasured(self.problem, &self.weights, &c)
                    .mapv(|x| support::smoothstep((x - x0) / (x1 - x0)));
                let wide = observations::high_sun_east_west(self.problem, &self.weights, &c);
                Zip::from(&mut *eta)
                    .and(&wide)
                    .and(&tt)
                    .for_each(|e, &w, &t| *e += (w - *e) * (1.0 - t));
                t = Some(tt);
            }
            let psi = (factor_east_west < factor)
                .then(|| observations::east_west_open(self.problem, &self.weights, &c));
            self.dem_relief = Some(Zip::indexed(&c).map_collect(|ij, &c| {
                let mut f = factor;
                if let Some(phi) = &phi {
                    f = f.min(factor - (factor - factor_all) * phi[ij]);
                }
                if let Some(eta) = &eta {
                    let fh = t.as_ref().map_or(factor_high_sun, |t| {
                        factor_high_sun_ew + (factor_high_sun - factor_high_sun_ew) * t[ij]
                    });
                    f = f.min(factor - (factor - fh) * eta[ij]);
                }
                if let Some(psi) = &psi {
                    f = f.min(factor - (factor - factor_east_west) * psi[ij]);
                }
                (1.0 - f) * c
            }));
        }
        self
    }

    /// u = IDCT(ĝ_s·ẑ − ĝ_σ·T̂): the field whose forward-difference gradient E_DEM measures.
    fn dem_residual(&self, zh: &Array2<f64>) -> Array2<f64> {
        self.dct.inverse(
            &Zip::from(&self.gs)
                .and(zh)
                .and(&self.dem_target)
                .map_collect(|&g, &z, &t| f64::from(g) * z - f64::from(t)),
        )
    }

    /// Σ r·|D u|²/ε² + h·Σ r·u² (the part of E_DEM or E_reg the relief field takes away; r on
    /// an edge is the mean of its two pixels; h the height weight, [`Objective::dem_height`]
    /// for E_DEM, 0 for E_reg) and, when `grad`, its gradient with respect to u,
    /// 2Dᵀ(r∘Du)/ε² + 2h·r∘u.
    fn relief_term(
        &self,
        r: &Array2<f64>,
        u: &Array2<f64>,
        height: f64,
        grad: bool,
    ) -> (f64, Option<Array2<f64>>) {
        let (ny, nx) = u.dim();
        let e2 = self.problem.spacing * self.problem.spacing;
        // Weighted differences on the edges to the east and to the south of each pixel, none
        // past the last column or row (Neumann).
        let mut sum = Array2::<f64>::zeros((ny, nx));
        Zip::indexed(&mut sum).par_for_each(|(i, j), sum| {
            if j + 1 < nx {
                let d = u[(i, j + 1)] - u[(i, j)];
                *sum += 0.5 * (r[(i, j)] + r[(i, j + 1)]) * d * d;
            }
            if i + 1 < ny {
                let d = u[(i + 1, j)] - u[(i, j)];
                *sum += 0.5 * (r[(i, j)] + r[(i + 1, j)]) * d * d;
            }
            *sum /= e2;
            *sum += height * r[(i, j)] * u[(i, j)] * u[(i, j)];
        });
        let g = grad.then(|| {
            let mut g = Array2::zeros((ny, nx));
            relief_gradient_into(r, u, e2, height, &mut g);
            g
        });
        (ops::sum(sum.view()), g)
    }

    /// The mean of r(x) (0 without relief): the preconditioner uses δ·(1 − mean r).
    pub fn mean_relief(&self) -> f64 {
        self.dem_relief
            .as_ref()
            .map_or(0.0, |r| ops::sum(r.view()) / r.len() as f64)
    }

    /// E_tie at `z`.
    pub fn tie_energy(&self, z: ArrayView2<f64>) -> f64 {
        let Some(k) = &self.tie else { return 0.0 };
        let parts = Zip::from(k.rows())
            .and(z.rows())
            .and(self.problem.dem.rows())
            .par_map_collect(|k, z, d| {
                [k.iter()
                    .zip(z)
                    .zip(d)
                    .map(|((&k, &z), &d)| k * (z - d) * (z - d))
                    .sum::<f64>()]
            });
        ops::sum_row_parts(parts.view())[0]
    }

    /// Photometric residuals and derivatives of every observation at surface `z` with albedo
    /// `rho`, and their weighted sums.
    pub fn photo(&self, z: ArrayView2<f64>, rho: ArrayView2<f64>) -> Photo {
        let pr = self.problem;
        let model: &dyn ReflectanceModel = pr.model;
        let z = z.as_standard_layout();
        let dim = z.dim();
        let s = self.scale;
        let mut used = Array2::from_elem(dim, false);
        let mut intensity = 0.0;
        let mut obs = Vec::with_capacity(pr.observations.len());
        for (k, o) in pr.observations.iter().enumerate() {
            let usable = &self.weights.usable[k];
            let (g, w) = (self.weights.gains[k], &self.weights.weight[k]);
            let mut ph = ObsPhoto {
                res: Array2::zeros(dim),
                a: Array2::zeros(dim),
                b: Array2::zeros(dim),
                used: Array2::from_elem(dim, false),
            };
            if let Some(kernel) = &self.kernels[k] {
                intensity += self.blurred_photo(k, o, kernel, z.view(), rho, &mut ph);
                Zip::from(&mut used)
                    .and(&ph.used)
                    .par_for_each(|all, &u| *all |= u);
                obs.push(ph);
                continue;
            }
            // Row by row, the slopes of each row formed there (no slope arrays), with Σ w·r²
            // of the row (from the f64 residuals), added in row order (as `ops::dot`) and
            // then in the observations' order.
            let parts = Zip::indexed(ph.res.rows_mut())
                .and(ph.a.rows_mut())
                .and(ph.b.rows_mut())
                .and(ph.used.rows_mut())
                .par_map_collect(|i, mut res, mut a, mut b, mut used| {
                    let (mut p, mut q) = (vec![0.0; dim.1], vec![0.0; dim.1]);
                    ops::gradient_row(z.view(), pr.spacing, i, &mut p, &mut q);
                    let mut part = 0.0;
                    for j in 0..dim.1 {
                        if !usable[(i, j)] {
                            continue;
                        }
                        let sh = shade_at(model, o, (p[j], q[j]), rho, (i, j));
                        if sh.lit {
                            // Part in shadow: I/g against f·R ([`Weights::lit`]).
                            let f = self.weights.lit_at(k, (i, j));
                            let r = (o.image[(i, j)] / g - f * sh.r) / s;
                            part += f64::from(w[(i, j)]) * r * r;
                            res[j] = r as f32;
                            a[j] = (f * sh.dr_dp / s) as f32;
                            b[j] = (f * sh.dr_dq / s) as f32;
                            used[j] = true;
                        }
                    }
                    [part]
                });
            intensity += ops::sum_row_parts(parts.view())[0];
            Zip::from(&mut used)
                .and(&ph.used)
                .par_for_each(|all, &u| *all |= u);
            obs.push(ph);
        }
        let shadow = match &self.shadows {
            Some(t) => t.evaluate(z.view()),
            None => ShadowState::default(),
        };
        Photo {
            obs,
            intensity,
            used,
            shadow,
        }
    }

    /// [`Objective::photo`] of observation `k` coarser than the grid: R and its slope
    /// derivatives (a, b) at every pixel the image covers, residuals r = (I/g − B R)/Ī on the
    /// pixels used; returns Σ w r² (row by row, then in row order).
    fn blurred_photo(
        &self,
        k: usize,
        o: &super::Observation,
        kernel: &blur::Kernel,
        z: ArrayView2<f64>,
        rho: ArrayView2<f64>,
        ph: &mut ObsPhoto,
    ) -> f64 {
        let pr = self.problem;
        let model: &dyn ReflectanceModel = pr.model;
        let (dim, s) = (z.dim(), self.scale);
        let mut r = Array2::<f64>::zeros(dim);
        Zip::indexed(r.rows_mut())
            .and(ph.a.rows_mut())
            .and(ph.b.rows_mut())
            .par_for_each(|i, mut r, mut a, mut b| {
                let (mut p, mut q) = (vec![0.0; dim.1], vec![0.0; dim.1]);
                ops::gradient_row(z, pr.spacing, i, &mut p, &mut q);
                for j in 0..dim.1 {
                    if !o.image[(i, j)].is_finite() {
                        continue;
                    }
                    let sh = shade_at(model, o, (p[j], q[j]), rho, (i, j));
                    if sh.lit {
                        r[j] = sh.r;
                        a[j] = (sh.dr_dp / s) as f32;
                        b[j] = (sh.dr_dq / s) as f32;
                    }
                }
            });
        let modelled = blur::convolve(kernel, &r);
        let (usable, g, w) = (
            &self.weights.usable[k],
            self.weights.gains[k],
            &self.weights.weight[k],
        );
        let parts = Zip::indexed(ph.res.rows_mut())
            .and(ph.used.rows_mut())
            .par_map_collect(|i, mut res, mut used| {
                let mut part = 0.0;
                for j in 0..dim.1 {
                    if usable[(i, j)] {
                        let r = (o.image[(i, j)] / g - modelled[(i, j)]) / s;
                        part += f64::from(w[(i, j)]) * r * r;
                        res[j] = r as f32;
                        used[j] = true;
                    }
                }
                [part]
            });
        ops::sum_row_parts(parts.view())[0]
    }

    /// The Newton operator's part of each observation coarser than the grid (empty when there
    /// is none), taking their slope derivatives out of `photo`, which the step no longer needs.
    pub fn blurred_terms(&self, photo: Photo) -> Vec<BlurTerm> {
        self.kernels
            .iter()
            .zip(photo.obs)
            .zip(&self.weights.weight)
            .filter_map(|((k, ph), w)| {
                k.as_ref().map(|kernel| BlurTerm {
                    kernel: kernel.clone(),
                    w2: Zip::from(w)
                        .and(&ph.used)
                        .map_collect(|&w, &u| if u { 2.0 * w } else { 0.0 }),
                    a: ph.a,
                    b: ph.b,
                })
            })
            .collect()
    }

    /// The factor each observation's residual enters ∂E_I/∂z with at each pixel, w_k r_k,
    /// and for one coarser than the grid Bᵀ(w_k r_k) (its residual at x depends on the slopes
    /// around x): `None` for a sharp observation (formed where it is used).
    fn blurred_fluxes(&self, photo: &Photo) -> Vec<Option<Array2<f64>>> {
        self.kernels
            .iter()
            .zip(&photo.obs)
            .zip(&self.weights.weight)
            .map(|((k, ph), w)| {
                k.as_ref().map(|kernel| {
                    let wr = Zip::from(w)
                        .and(&ph.res)
                        .map_collect(|&w, &r| f64::from(w) * f64::from(r));
                    blur::convolve(kernel, &wr)
                })
            })
            .collect()
    }

    /// `out` ← ∂E_I/∂z + `out`, ∂E_I/∂z = −2 Dᵀ(fx, fy) of `photo`, (fx, fy) = Σ_k w_k r_k
    /// (a_k, b_k) (summed over the observations in their order). fy is formed as an array
    /// (D_yᵀ reaches two rows either side), fx and ∂E_I/∂z row by row where they are used:
    /// one array of the grid's size, not three.
    pub fn add_photo_gradient(&self, photo: &Photo, out: &mut Array2<f64>) {
        let dim = photo.used.dim();
        let weights = &self.weights.weight;
        let blurred = self.blurred_fluxes(photo);
        let mut fy = Array2::zeros(dim);
        for ((ph, w), t) in photo.obs.iter().zip(weights).zip(&blurred) {
            if let Some(t) = t {
                Zip::from(&mut fy)
                    .and(t)
                    .and(&ph.b)
                    .par_for_each(|fy, &t, &b| *fy += t * f64::from(b));
                continue;
            }
            Zip::from(&mut fy)
                .and(&ph.res)
                .and(&ph.b)
                .and(w)
                .par_for_each(|fy, &r, &b, &w| *fy += f64::from(w) * f64::from(r) * f64::from(b));
        }
        out.axis_iter_mut(Axis(0))
            .into_par_iter()
            .enumerate()
            .for_each(|(i, mut orow)| {
                let mut fx = vec![0.0; dim.1];
                for ((ph, w), t) in photo.obs.iter().zip(weights).zip(&blurred) {
                    if let Some(t) = t {
                        let (t, a) = (t.row(i), ph.a.row(i));
                        for (j, fx) in fx.iter_mut().enumerate() {
                            *fx += t[j] * f64::from(a[j]);
                        }
                        continue;
                    }
                    let (r, a, w) = (ph.res.row(i), ph.a.row(i), w.row(i));
                    for (j, fx) in fx.iter_mut().enumerate() {
                        *fx += f64::from(w[j]) * f64::from(r[j]) * f64::from(a[j]);
                    }
                }
                let mut data = vec![0.0; dim.1];
                ops::adjoint_row(&fx, fy.view(), self.problem.spacing, i, &mut data);
                for (o, d) in orow.iter_mut().zip(data) {
                    *o += d * -2.0;
                }
            });
    }

    /// Where the albedo follows the slopes in the Gauss–Newton steps: ν(x) ∈ [0, 1] of each
    /// pixel's albedo is taken as re-inverted from the slopes a step makes
    /// ([`Objective::add_gauss_newton_hessian`]); `None`: held as given (the plain
    /// alternation of albedo and surface).
    pub fn set_albedo_coupling(&mut self, nu: Option<Array2<f64>>) {
        self.albedo_coupling = nu;
    }

    /// H = Σ_k 2 w_k (a_k², a_k b_k, b_k²), the Gauss–Newton Hessian of E_I in (p, q) per
    /// pixel, summed in f64 and added to `m` (the residual curvature, [`Objective::curvature`]):
    /// `m` ← H + M in f32, the Newton systems' storage.
    ///
    /// Where the albedo follows the slopes (ν of [`Objective::set_albedo_coupling`]), the
    /// pixel's albedo is eliminated from E_I in share ν (variable projection): with d_k the
    /// albedo's direction ∂R_k/∂ρ·ρ/Ī (taken as R_k/Ī, exact for a model linear in ρ) and
    /// u = Σ_k w_k d_k (a_k, b_k), H − 2ν·u uᵀ/Σ_k w_k d_k². At ν = 1 that
    /// is the Hessian of min_ρ E_I, in which a slope that changes every image alike costs
    /// nothing (the albedo takes it); it stays positive semi-definite for ν ≤ 1
    /// (Cauchy–Schwarz: u uᵀ/Σ w d² ≤ H/2). Observations coarser than the grid stay out of
    /// it, as they stay out of H.
    pub fn add_gauss_newton_hessian(&self, photo: &Photo, m: &mut Array2<[f32; 3]>) {
        let obs = &photo.obs;
        let weights = &self.weights.weight;
        let coupling = self.albedo_coupling.as_ref();
        Zip::indexed(m).par_for_each(|ix, m| {
            let nu = coupling.map_or(0.0, |c| c[ix]);
            let mut h = [0.0f64; 3];
            // u = Σ_k w_k d_k (a_k, b_k) and Σ_k w_k d_k², where the albedo is coupled.
            let (mut u, mut dd) = ([0.0f64; 2], 0.0f64);
            for (k, ((ph, w), kernel)) in obs.iter().zip(weights).zip(&self.kernels).enumerate() {
                if kernel.is_some() {
                    continue; // in the Newton operator ([`Objective::blurred_terms`])
                }
                let (a, b, w) = (f64::from(ph.a[ix]), f64::from(ph.b[ix]), f64::from(w[ix]));
                h[0] += 2.0 * w * a * a;
                h[1] += 2.0 * w * a * b;
                h[2] += 2.0 * w * b * b;
                if nu > 0.0 && ph.used[ix] {
                    let d = self.albedo_direction(k, ph, ix);
                    u[0] += w * d * a;
                    u[1] += w * d * b;
                    dd += w * d * d;
                }
            }
            if dd > 0.0 {
                let f = 2.0 * nu / dd;
                h[0] -= f * u[0] * u[0];
                h[1] -= f * u[0] * u[1];
                h[2] -= f * u[1] * u[1];
            }
            *m = [
                (h[0] + f64::from(m[0])) as f32,
                (h[1] + f64::from(m[1])) as f32,
                (h[2] + f64::from(m[2])) as f32,
            ];
        });
    }

    /// d_k at pixel `ix` of observation `k` (its photometric state `ph`, used there):
    /// R_k/Ī = I_k/(g_k Ī) − r_k, which is ∂R_k/∂ρ·ρ/Ī for a model linear in the albedo. Only
    /// the direction of (d_k) over the observations matters (the projection u uᵀ/Σ w d² does
    /// not change when every d_k is scaled alike), so ρ drops out; for Hapke, whose
    /// ∂ ln R/∂ ln w varies with the geometry through the multiple-scattering term, it is the
    /// albedo's direction to a few per cent.
    fn albedo_direction(&self, k: usize, ph: &ObsPhoto, ix: (usize, usize)) -> f64 {
        let image = self.problem.observations[k].image[ix];
        image / (self.weights.gains[k] * self.scale) - f64::from(ph.res[ix])
    }

    /// The residual part of E_I's Hessian in (p, q) per pixel, Σ_k w_k·(−2r_k·∇²R_k/Ī) with
    /// each observation's term projected onto the positive semi-definite matrices, as
    /// (xx, xy, yy); an observation adds nothing where it is not used or where
    /// |r_k| ≤ `min_residual`. Gauss–Newton drops this term, which is right where residuals are
    /// small but converges only linearly (halving the error each step) where the image is
    /// brighter than any slope can make R — there R sits at its maximum over the slopes,
    /// ∂R/∂(p, q) = 0, and only this term sees the curvature. ∇²R is the forward difference of
    /// the analytic gradient over 1e-6 in p and q. Stored in f32 (each pixel's sum over the
    /// observations is formed in f64): it only enters the Newton systems, which are solved in
    /// f32 (`fast::newton_step`).
    pub fn curvature(
        &self,
        z: ArrayView2<f64>,
        rho: ArrayView2<f64>,
        photo: &Photo,
        min_residual: f64,
    ) -> Array2<[f32; 3]> {
        let pr = self.problem;
        let model: &dyn ReflectanceModel = pr.model;
        let s = self.scale;
        let mut out = Array2::from_elem(z.dim(), [0.0f32; 3]);
        Zip::indexed(&mut out).par_for_each(|(i, j), out| {
            let mut m = [0.0f64; 3];
            // (p, q) only at the pixels that need them (few: large residuals).
            let mut slopes = None;
            for (k, o) in pr.observations.iter().enumerate() {
                let ph = &photo.obs[k];
                let r = f64::from(ph.res[(i, j)]);
                if !ph.used[(i, j)] || r.abs() <= min_residual || self.kernels[k].is_some() {
                    continue;
                }
                let h = 1e-6;
                let (pp, qq) = *slopes.get_or_insert_with(|| ops::gradient_at(z, pr.spacing, i, j));
                let w = rho[(i, j)];
                let (sun, view) = (o.sun.at(i, j), o.view.at(i, j));
                let at = |dp: f64, dq: f64| model.shade_observed(pp + dp, qq + dq, w, &sun, &view);
                // Forward differences of the analytic gradient: three evaluations where
                // central ones need four (the photo's (a, b) are rounded to f32, too coarse to
                // difference over h).
                let at0 = at(0.0, 0.0);
                let (gx, gy) = (at0.dr_dp, at0.dr_dq);
                let (xp, yp) = (at(h, 0.0), at(0.0, h));
                let rxx = (xp.dr_dp - gx) / h;
                let ryy = (yp.dr_dq - gy) / h;
                let rxy = 0.5 * (xp.dr_dq - gy + yp.dr_dp - gx) / h;
                let c = -2.0 * r * self.weights.lit_at(k, (i, j)) / s;
                let t = psd_part([c * rxx, c * rxy, c * ryy]);
                let w = f64::from(self.weights.weight[k][(i, j)]);
                m[0] += w * t[0];
                m[1] += w * t[1];
                m[2] += w * t[2];
            }
            *out = m.map(|x| x as f32);
        });
        out
    }

    /// The quadratic terms (E_DEM, E_reg) at z, from z and its DCT coefficients ẑ.
    pub fn quadratic(&self, z: ArrayView2<f64>, zh: &Array2<f64>) -> (f64, f64) {
        // Both sums in one pass, per row and then in row order (as `ops::sum`).
        let parts = Zip::indexed(self.gs.rows())
            .and(zh.rows())
            .and(self.dem_target.rows())
            .and(self.dem_hat.rows())
            .par_map_collect(|i, g, z, t, h| {
                let (mut dem, mut reg) = (0.0, 0.0);
                for j in 0..g.len() {
                    let (l, z) = (self.lam.at(i, j), z[j]);
                    let d = f64::from(g[j]) * z - f64::from(t[j]);
                    let c = z - f64::from(h[j]);
                    dem += (l + self.dem_height) * d * d;
                    reg += l * c * c;
                }
                [dem, reg]
            });
        let [mut dem, mut reg] = ops::sum_row_parts(parts.view());
        if let Some(r) = &self.dem_relief {
            dem -= self
                .relief_term(r, &self.dem_residual(zh), self.dem_height, false)
                .0;
        }
        if let Some(r) = &self.membrane_relief {
            reg -= self.relief_term(r, &self.correction(z), 0.0, false).0;
        }
        (dem, reg)
    }

    /// Everything the solvers need at one iterate: photometric state, ẑ and the energy.
    pub fn evaluate(&self, z: &Array2<f64>, rho: ArrayView2<f64>) -> Iterate {
        let photo = self.photo(z.view(), rho);
        let zh = self.dct.forward(z);
        let energy = self.energy_with(z.view(), &zh, &photo);
        Iterate { photo, zh, energy }
    }

    /// Energy at `z` given its photometric state.
    pub fn energy(&self, z: ArrayView2<f64>, photo: &Photo) -> Energy {
        let zh = self.dct.forward(&z.to_owned());
        self.energy_with(z, &zh, photo)
    }

    /// Energy at `z` given ẑ and the photometric state.
    pub fn energy_with(&self, z: ArrayView2<f64>, zh: &Array2<f64>, photo: &Photo) -> Energy {
        let intensity = photo.intensity;
        let (dem, membrane) = self.quadratic(z, zh);
        let tie = self.tie_energy(z);
        let shadow = photo.shadow.energy;
        Energy {
            intensity,
            integrability: 0.0,
            dem,
            membrane,
            tie,
            shadow,
            total: intensity + self.delta * dem + self.eta * membrane + tie + shadow,
        }
    }

    /// ∂E/∂z (spatial) at `z`, given ẑ and the photometric state. ẑ is taken by value: the
    /// quadratic terms' part is formed in its place (no array of the grid's size for it).
    pub fn gradient(&self, z: ArrayView2<f64>, zh: Array2<f64>, photo: &Photo) -> Array2<f64> {
        let relief_hat = self.dem_relief.as_ref().map(|r| {
            let (_, gu) = self.relief_term(r, &self.dem_residual(&zh), self.dem_height, true);
            self.dct.forward(&gu.expect("asked for"))
        });
        let mut g = zh;
        Zip::indexed(&mut g)
            .and(&self.gs)
            .and(&self.dem_target)
            .and(&self.dem_hat)
            .par_for_each(|(i, j), q, &g, &t, &d| {
                let (g, t, d) = (f64::from(g), f64::from(t), f64::from(d));
                let (l, z) = (self.lam.at(i, j), *q);
                *q = 2.0 * (l + self.dem_height) * self.delta * g * (g * z - t)
                    + 2.0 * l * self.eta * (z - d);
            });
        if let Some(gh) = relief_hat {
            Zip::from(&mut g)
                .and(&gh)
                .and(&self.gs)
                .par_for_each(|o, &x, &g| *o -= self.delta * f64::from(g) * x);
        }
        self.dct.inverse_in_place(&mut g);
        self.add_photo_gradient(photo, &mut g);
        if let Some(r) = &self.membrane_relief {
            let (_, gu) = self.relief_term(r, &self.correction(z), 0.0, true);
            g.scaled_add(-self.eta, &gu.expect("asked for"));
        }
        if let Some(k) = &self.tie {
            Zip::from(&mut g)
                .and(k)
                .and(z)
                .and(self.problem.dem)
                .par_for_each(|g, &k, &z, &d| *g += 2.0 * k * (z - d));
        }
        if let Some(t) = &self.shadows {
            let g = g.as_slice_mut().expect("standard layout");
            shadows::add_gradient(t.weight, &photo.shadow.rows, g);
        }
        g
    }

    /// The diagonal of the quadratic terms' Hessian in the DCT basis at coefficient (i, j), for
    /// a given δ' and η': 2(λ/ε²)(δ'ĝ_s² + η') + 2δ'ĝ_s²/ℓ² (ℓ of
    /// [`Objective::with_dem_height_length`]; without the relief fields). Formed where it is
    /// used (the Newton operator and its preconditioner), not held as a table: ĝ_s and the
    /// 1-D tables of λ make it, in f64, the same value wherever it is needed.
    #[inline]
    pub fn quadratic_hessian_at(&self, i: usize, j: usize, delta: f64, eta: f64) -> f64 {
        let (g, h) = (f64::from(self.gs[(i, j)]), self.dem_height);
        2.0 * (self.lam.at(i, j) * (delta * g * g + eta) + h * delta * g * g)
    }
}

/// R and its slope derivatives of observation `o` at pixel `ij` for slopes `(p, q)` and the
/// albedo there ([`ReflectanceModel::shade_observed`]).
#[inline]
fn shade_at(
    model: &dyn ReflectanceModel,
    o: &super::Observation,
    (p, q): (f64, f64),
    rho: ArrayView2<f64>,
    ij: (usize, usize),
) -> crate::photometry::Shade {
    model.shade_observed(p, q, rho[ij], &o.sun.at(ij.0, ij.1), &o.view.at(ij.0, ij.1))
}

/// The gradient with respect to u of a relief field's Σ r·|D u|²/ε² + h·Σ r·u²
/// ([`Objective::relief_term`]): 2Dᵀ(r∘Du)/ε² + 2h·r∘u, into `out`. D takes forward differences
/// to the east and to the south, 0 past the last column or row (Neumann), and r on an edge is
/// the mean of its two pixels. Each pixel computes the four edge fluxes it touches, in the same
/// arithmetic as the energy's, so f64 gives the same bits however the work is split; f32 serves
/// the conjugate gradients (`fast`).
pub(crate) fn relief_gradient_into<T: Real>(
    r: &Array2<T>,
    u: &Array2<T>,
    e2: T,
    height: T,
    out: &mut Array2<T>,
) {
    let (ny, nx) = u.dim();
    let half = to::<T>(0.5);
    let two = to::<T>(2.0);
    // Row slices (a copy only if an input is not in standard layout): each row's fluxes are
    // formed once, the eastern one carried over as the next pixel's western one.
    let (r, u) = (r.as_standard_layout(), u.as_standard_layout());
    let (rs, us) = (
        r.as_slice().expect("standard layout"),
        u.as_slice().expect("standard layout"),
    );
    fn row<T>(a: &[T], nx: usize, i: usize) -> &[T] {
        &a[i * nx..(i + 1) * nx]
    }
    Zip::indexed(out.rows_mut()).par_for_each(|i, mut g| {
        let (r0, u0) = (row(rs, nx, i), row(us, nx, i));
        let above = (i > 0).then(|| (row(rs, nx, i - 1), row(us, nx, i - 1)));
        let below = (i + 1 < ny).then(|| (row(rs, nx, i + 1), row(us, nx, i + 1)));
        let mut west = T::zero();
        for (j, g) in g.iter_mut().enumerate() {
            let east = if j + 1 < nx {
                half * (r0[j] + r0[j + 1]) * (u0[j + 1] - u0[j])
            } else {
                T::zero()
            };
            let north = match above {
                Some((ra, ua)) => half * (ra[j] + r0[j]) * (u0[j] - ua[j]),
                None => T::zero(),
            };
            let south = match below {
                Some((rb, ub)) => half * (r0[j] + rb[j]) * (ub[j] - u0[j]),
                None => T::zero(),
            };
            *g = two * (west - east + north - south) / e2 + two * height * r0[j] * u0[j];
            west = east;
        }
    });
}

/// The positive semi-definite part of the symmetric 2 × 2 matrix (xx, xy, yy): its negative
/// eigenvalues set to 0.
pub fn psd_part([a, b, c]: [f64; 3]) -> [f64; 3] {
    let mean = 0.5 * (a + c);
    let rad = (0.25 * (a - c) * (a - c) + b * b).sqrt();
    let (l1, l2) = (mean + rad, mean - rad);
    if l2 >= 0.0 {
        return [a, b, c];
    }
    if l1 <= 0.0 {
        return [0.0; 3];
    }
    // Only l1 > 0: l1·e·eᵀ with e its unit eigenvector.
    let (ex, ey) = if b.abs() > 1e-300 {
        (l1 - c, b)
    } else if a >= c {
        (1.0, 0.0)
    } else {
        (0.0, 1.0)
    };
    let n2 = ex * ex + ey * ey;
    [l1 * ex * ex / n2, l1 * ex * ey / n2, l1 * ey * ey / n2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::Directions;
    use crate::photometry::Hapke;

    /// `relief_gradient_into` is the gradient of Σ_edges r_e·(Δu)²/ε² + h·Σ r·u², r_e the
    /// mean of an edge's two pixels (written out here edge by edge), by central differences;
    /// and f32 agrees with f64 to f32's precision (the conjugate gradients use f32).
    #[test]
    fn the_relief_gradient_is_the_relief_energys() {
        let (ny, nx, e2, h) = (7, 9, 3.0, 0.4);
        let r = Array2::from_shape_fn((ny, nx), |(i, j)| 0.2 + 0.1 * ((i * 3 + j * 5) % 7) as f64);
        let u = Array2::from_shape_fn((ny, nx), |(i, j)| ((i * 7 + j * 3) as f64 * 0.37).sin());
        let energy = |u: &Array2<f64>| {
            let mut e = 0.0;
            for i in 0..ny {
                for j in 0..nx {
                    if j + 1 < nx {
                        let d = u[(i, j + 1)] - u[(i, j)];
                        e += 0.5 * (r[(i, j)] + r[(i, j + 1)]) * d * d / e2;
                    }
                    if i + 1 < ny {
                        let d = u[(i + 1, j)] - u[(i, j)];
                        e += 0.5 * (r[(i, j)] + r[(i + 1, j)]) * d * d / e2;
                    }
                    e += h * r[(i, j)] * u[(i, j)] * u[(i, j)];
                }
            }
            e
        };
        let mut g = Array2::zeros((ny, nx));
        relief_gradient_into(&r, &u, e2, h, &mut g);
        for ((i, j), &gij) in g.indexed_iter() {
            let step = 1e-6;
            let (mut up, mut down) = (u.clone(), u.clone());
            up[(i, j)] += step;
            down[(i, j)] -= step;
            let fd = (energy(&up) - energy(&down)) / (2.0 * step);
            assert!((gij - fd).abs() < 1e-7, "({i}, {j}): {gij} against {fd}");
        }
        let mut g32 = Array2::<f32>::zeros((ny, nx));
        relief_gradient_into(
            &r.mapv(|x| x as f32),
            &u.mapv(|x| x as f32),
            3.0,
            0.4,
            &mut g32,
        );
        let scale = g.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        for (a, b) in g.iter().zip(&g32) {
            assert!((a - f64::from(*b)).abs() < 1e-5 * scale, "{a} against {b}");
        }
    }

    /// A smooth surface z and a different smooth DEM, metres.
    fn surfaces(ny: usize, nx: usize) -> (Array2<f64>, Array2<f64>) {
        let z = Array2::from_shape_fn((ny, nx), |(i, j)| {
            30.0 * (0.4 * i as f64).sin() + 20.0 * (0.3 * j as f64).cos()
        });
        let dem = Array2::from_shape_fn((ny, nx), |(i, j)| {
            25.0 * (0.35 * i as f64).sin() + 0.5 * j as f64
        });
        (z, dem)
    }

    /// One observation of `image` over `dem` (Sun 50° from the zenith at azimuth 100°, view 5°
    /// off nadir, 100 m pixels, DEM point spread 1.5 px).
    fn single<'a>(
        image: ArrayView2<'a, f64>,
        dem: ArrayView2<'a, f64>,
        model: &'a Hapke,
    ) -> Problem<'a> {
        Problem::single(
            image,
            Directions::Uniform(crate::synth::direction(50.0, 100.0)),
            Directions::Uniform(crate::synth::direction(5.0, 200.0)),
            dem,
            100.0,
            1.5,
            model,
        )
    }

    /// Every finite pixel usable, unit gains, no edge ramps.
    fn weights_of(pr: &Problem, scale: f64) -> Weights {
        let k = pr.observations.len();
        crate::fusion::observations::weights(pr, vec![1.0; k], scale, None, 0.0, 0.0, (1.0, 1.0))
    }

    /// ∂E/∂z at `points` of `z` (albedo 0.4) against central differences of E.
    fn assert_gradient_matches(obj: &Objective, z: &Array2<f64>, points: &[(usize, usize)]) {
        let rho = Array2::from_elem(z.dim(), 0.4);
        let e = |z: &Array2<f64>| obj.energy(z.view(), &obj.photo(z.view(), rho.view())).total;
        let g = obj.gradient(
            z.view(),
            obj.dct.forward(z),
            &obj.photo(z.view(), rho.view()),
        );
        for &(i, j) in points {
            let h = 1e-3;
            let mut zp = z.clone();
            zp[(i, j)] += h;
            let mut zm = z.clone();
            zm[(i, j)] -= h;
            let num = (e(&zp) - e(&zm)) / (2.0 * h);
            assert!(
                (g[(i, j)] - num).abs() < 1e-6 * num.abs().max(1e-3),
                "({i},{j}): {} vs {num}",
                g[(i, j)]
            );
        }
    }

    /// ∂E/∂z against central differences of E on a small smooth problem.
    #[test]
    fn gradient_matches_finite_differences() {
        let (ny, nx) = (12, 10);
        let (z, dem) = surfaces(ny, nx);
        let image =
            Array2::from_shape_fn((ny, nx), |(i, j)| 0.03 + 0.002 * ((i * 3 + j) % 5) as f64);
        let model = Hapke::moon();
        let pr = single(image.view(), dem.view(), &model);
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, weights_of(&pr, 0.03));
        assert_gradient_matches(&obj, &z, &[(0, 0), (3, 4), (11, 9), (6, 0), (0, 7)]);
    }

    /// The same with a third of the image missing: the blended DEM target and the tie are in
    /// the energy, and the gradient still matches it.
    #[test]
    fn gradient_matches_finite_differences_where_the_image_ends() {
        let (ny, nx) = (12, 30);
        let (z, dem) = surfaces(ny, nx);
        let image = Array2::from_shape_fn((ny, nx), |(i, j)| {
            if j >= 20 {
                f64::NAN
            } else {
                0.03 + 0.002 * ((i * 3 + j) % 5) as f64
            }
        });
        let model = Hapke::moon();
        let pr = single(image.view(), dem.view(), &model);
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, weights_of(&pr, 0.03));
        assert!(obj.tie.is_some());
        assert!(obj.tie_energy(z.view()) > 0.0);
        assert_gradient_matches(&obj, &z, &[(3, 4), (6, 19), (5, 21), (11, 25), (0, 29)]);
    }

    /// Two observation images on a 12 × 30 grid, columns 0..20 and 8..30, the second × `gain`.
    fn two_strips(gain: f64) -> (Array2<f64>, Array2<f64>) {
        let strip = |lo: usize, hi: usize, g: f64| {
            Array2::from_shape_fn((12, 30), |(i, j)| {
                if j < lo || j >= hi {
                    f64::NAN
                } else {
                    g * (0.03 + 0.002 * ((i * 3 + j) % 5) as f64)
                }
            })
        };
        (strip(0, 20, 1.0), strip(8, 30, gain))
    }

    /// The problem of the two strips `a` and `b` under different Suns over `dem`.
    fn two_observations<'a>(
        a: &'a Array2<f64>,
        b: &'a Array2<f64>,
        dem: &'a Array2<f64>,
        model: &'a Hapke,
    ) -> Problem<'a> {
        let mut pr = single(a.view(), dem.view(), model);
        pr.observations.push(crate::fusion::Observation {
            image: b.view(),
            sun: Directions::Uniform(crate::synth::direction(65.0, 230.0)),
            view: Directions::Uniform(crate::synth::direction(2.0, 90.0)),
        });
        pr
    }

    /// The weights of [`two_observations`] over [`two_strips`]`(1.1)`: gains 1 and 1.1, noise
    /// weights 1 and 0.7, Ī = 0.03, 4-px edge ramps.
    fn two_strip_weights(pr: &Problem) -> Weights {
        crate::fusion::observations::weights(
            pr,
            vec![1.0, 1.1],
            0.03,
            Some(vec![1.0, 0.7]),
            0.0,
            4.0,
            (1.0, 1.0),
        )
    }

    /// Two overlapping observations under different Suns, with gains, noise weights and edge
    /// ramps: the summed photometric term's gradient matches E too.
    #[test]
    fn gradient_matches_finite_differences_with_two_observations() {
        let (z, dem) = surfaces(12, 30);
        let (a, b) = two_strips(1.1);
        let model = Hapke::moon();
        let pr = two_observations(&a, &b, &dem, &model);
        let w = two_strip_weights(&pr);
        assert!(w.weight[1][(3, 9)] > 0.0 && w.weight[1][(3, 9)] < 0.7);
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w)
            .with_multi_delta(MultiDelta::uniform(0.3));
        assert!(obj.dem_relief.as_ref().unwrap()[(5, 15)] > 0.5);
        assert_gradient_matches(&obj, &z, &[(3, 4), (6, 9), (5, 15), (11, 25), (0, 29)]);
    }

    /// With lit shares f < 1 (pixels part in shadow, [`Weights::lit`]) E_I compares I/g with
    /// f·R: the gradient still matches finite differences, and the energy is not the one
    /// with f = 1.
    #[test]
    fn gradient_matches_finite_differences_with_part_shadowed_pixels() {
        let (z, dem) = surfaces(12, 30);
        let (a, b) = two_strips(1.1);
        let model = Hapke::moon();
        let pr = two_observations(&a, &b, &dem, &model);
        let mut w = two_strip_weights(&pr);
        let plain = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w.clone());
        w.lit[0] = Some(Array2::from_shape_fn(z.dim(), |(i, j)| {
            if (i + j) % 3 == 0 {
                0.6 + 0.01 * i as f32
            } else {
                1.0
            }
        }));
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w);
        let rho = Array2::from_elem(z.dim(), 0.4);
        let e = |o: &Objective| o.energy(z.view(), &o.photo(z.view(), rho.view())).intensity;
        assert!((e(&obj) - e(&plain)).abs() > 1e-3 * e(&plain));
        assert_gradient_matches(&obj, &z, &[(3, 3), (6, 9), (5, 15), (11, 25), (0, 0)]);
    }

    /// The second observation coarser than the grid (a blur of σ = 0.9 px, radius 3): its
    /// residuals compare the image with B R, it uses only pixels whose whole neighbourhood it
    /// sees, and the gradient (through Bᵀ) still matches E.
    #[test]
    fn gradient_matches_finite_differences_with_a_blurred_observation() {
        let (z, dem) = surfaces(12, 30);
        let (a, b) = two_strips(1.1);
        let model = Hapke::moon();
        let mut pr = two_observations(&a, &b, &dem, &model);
        pr.blur = Some(vec![0.0, 0.9]);
        let w = two_strip_weights(&pr);
        // Eroded by 3 px: inside the grid and the strip (columns 8..30).
        assert!(w.usable[1][(3, 11)] && !w.usable[1][(3, 10)] && !w.usable[1][(2, 15)]);
        assert!(w.usable[1][(8, 26)] && !w.usable[1][(8, 27)] && !w.usable[1][(9, 15)]);
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w);
        assert!(obj.kernels[0].is_none() && obj.kernels[1].is_some());
        // The residual at a used pixel is the image against the blurred rendering.
        let rho = Array2::from_elem(z.dim(), 0.4);
        let ph = obj.photo(z.view(), rho.view());
        let (i, j) = (5, 15);
        let kernel = obj.kernels[1].as_ref().unwrap();
        let mut modelled = 0.0;
        for di in -3i32..=3 {
            for dj in -3i32..=3 {
                let (y, x) = ((i as i32 + di) as usize, (j as i32 + dj) as usize);
                let (p, q) = ops::gradient_at(z.view(), pr.spacing, y, x);
                let sh = model.shade_observed(
                    p,
                    q,
                    0.4,
                    &pr.observations[1].sun.at(y, x),
                    &pr.observations[1].view.at(y, x),
                );
                modelled += kernel.taps[di.unsigned_abs() as usize]
                    * kernel.taps[dj.unsigned_abs() as usize]
                    * sh.r;
            }
        }
        let expected = (b[(i, j)] / 1.1 - modelled) / 0.03;
        assert!(
            (f64::from(ph.obs[1].res[(i, j)]) - expected).abs() < 1e-5 * expected.abs().max(1.0)
        );
        assert_gradient_matches(
            &obj,
            &z,
            &[(3, 4), (6, 9), (5, 15), (2, 12), (11, 25), (0, 29)],
        );
    }

    /// E_DEM's height part ([`Objective::with_dem_height_length`], ℓ = 3 px so that it weighs
    /// as much as the gradients), with the relief field of two overlapping observations that
    /// lowers both parts: the gradient still matches E, and the part is in E.
    #[test]
    fn gradient_matches_finite_differences_with_the_dem_height_part() {
        let (z, dem) = surfaces(12, 30);
        let (a, b) = two_strips(1.1);
        let model = Hapke::moon();
        let pr = two_observations(&a, &b, &dem, &model);
        let w = || two_strip_weights(&pr);
        let plain = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w())
            .with_multi_delta(MultiDelta::uniform(0.3));
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, w())
            .with_multi_delta(MultiDelta::uniform(0.3))
            .with_dem_height_length(300.0);
        assert_eq!(obj.dem_height, 1.0 / (300.0 * 300.0));
        let zh = obj.dct.forward(&z);
        let (with, without) = (
            obj.quadratic(z.view(), &zh).0,
            plain.quadratic(z.view(), &zh).0,
        );
        assert!(with > 1.2 * without, "{with} vs {without}");
        assert_gradient_matches(
            &obj,
            &z,
            &[(0, 0), (3, 4), (6, 9), (5, 15), (11, 25), (0, 29)],
        );
    }

    /// E_DEM with the track weighting ([`Objective::with_dem_tracks`]), against the DCT
    /// basis: over a zero DEM, E_DEM of a surface that is one cosine across the columns (the
    /// shape of a track offset: constant along them) is a × the plain term's, while one cosine
    /// along the columns keeps its weight; with the relief field of two overlapping
    /// observations and the height part the gradient still matches E.
    #[test]
    fn the_track_weighting_lowers_e_dem_for_across_track_slopes_only() {
        let (ny, nx) = (12, 30);
        let flat = Array2::zeros((ny, nx));
        let image = Array2::from_elem((ny, nx), 0.03);
        let model = Hapke::moon();
        let pr = single(image.view(), flat.view(), &model);
        let plain = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, weights_of(&pr, 0.03));
        let tracks = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, weights_of(&pr, 0.03))
            .with_dem_tracks(0.1, 2.0);
        let pi = std::f64::consts::PI;
        let across = Array2::from_shape_fn((ny, nx), |(_, j)| {
            (pi * 3.0 * (j as f64 + 0.5) / nx as f64).cos()
        });
        let along = Array2::from_shape_fn((ny, nx), |(i, _)| {
            (pi * 3.0 * (i as f64 + 0.5) / ny as f64).cos()
        });
        let dem_energy =
            |o: &Objective, z: &Array2<f64>| o.quadratic(z.view(), &o.dct.forward(z)).0;
        // ĝ_s is held in f32: the ratios hold to its rounding (≈ 10⁻⁷).
        let ratio = dem_energy(&tracks, &across) / dem_energy(&plain, &across);
        assert!((ratio - 0.1).abs() < 1e-6, "across the columns: {ratio}");
        let ratio = dem_energy(&tracks, &along) / dem_energy(&plain, &along);
        assert!((ratio - 1.0).abs() < 1e-6, "along the columns: {ratio}");

        let (z, dem) = surfaces(ny, nx);
        let (a, b) = two_strips(1.1);
        let pr = two_observations(&a, &b, &dem, &model);
        let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.03, two_strip_weights(&pr))
            .with_multi_delta(MultiDelta::uniform(0.3))
            .with_dem_height_length(300.0)
            .with_dem_tracks(0.1, 2.0);
        assert_gradient_matches(
            &obj,
            &z,
            &[(0, 0), (3, 4), (6, 9), (5, 15), (11, 25), (0, 29)],
        );
    }

    /// Two Lambert observations seen from nadir over `dem` at 100 m pixels: `a` under a Sun 60°
    /// from the zenith at azimuth 100°, `b` under `sun_b` (zenith, azimuth in degrees), the
    /// DEM's point spread `dem_psf` pixels.
    fn two_lambert<'a>(
        (a, b): (&'a Array2<f64>, &'a Array2<f64>),
        dem: &'a Array2<f64>,
        sun_b: (f64, f64),
        dem_psf: f64,
        model: &'a crate::photometry::Lambert,
    ) -> Problem<'a> {
        let nadir = || Directions::Uniform(crate::synth::direction(0.0, 0.0));
        let mut pr = Problem::single(
            a.view(),
            Directions::Uniform(crate::synth::direction(60.0, 100.0)),
            nadir(),
            dem.view(),
            100.0,
            dem_psf,
            model,
        );
        pr.observations.push(crate::fusion::Observation {
            image: b.view(),
            sun: Directions::Uniform(crate::synth::direction(sun_b.0, sun_b.1)),
            view: nadir(),
        });
        pr
    }

    /// The level surface's photometric stiffness against its closed form for Lambert
    /// (ln R = ln μ0 + const, ∂ ln μ0/∂(p, q) = −(s_x, s_y)/s_z at p = q = 0, so
    /// S = Σ_k tan² i_k), and the several-observation membrane it scales: ω = f·√(S/S₀) where
    /// two observations carry a flat correction in full, capped at f; one observation's pixels
    /// keep η (no field where only one observation exists).
    #[test]
    fn the_several_observation_membrane_follows_the_level_stiffness() {
        let (ny, nx) = (6, 40);
        let dem = Array2::from_shape_fn((ny, nx), |(i, j)| 3.0 * i as f64 - 0.5 * j as f64);
        let (a, b) = (
            Array2::from_elem((ny, nx), 0.2),
            Array2::from_shape_fn((ny, nx), |(_, j)| if j < 20 { f64::NAN } else { 0.2 }),
        );
        let model = crate::photometry::Lambert;
        let pr = two_lambert((&a, &b), &dem, (45.0, 220.0), 1.5, &model);
        let mut obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, 0.2, weights_of(&pr, 0.2));
        let rho = Array2::from_elem((ny, nx), 0.5);
        let c = obj.weights.multiplicity();
        let s = obj.level_stiffness(rho.view(), &c);
        let tan2 = |deg: f64| deg.to_radians().tan().powi(2);
        // Where both see the pixel: tan² 60° + tan² 45° = 4; where one does, c = 0 and S is
        // not formed.
        assert!(
            (s[(3, 30)] - (tan2(60.0) + tan2(45.0))).abs() < 1e-9,
            "{}",
            s[(3, 30)]
        );
        assert_eq!(s[(3, 5)], 0.0);
        // A flat correction (z = z_DEM) leaves the edge factors at 1: ω = f·min(1, √(S/S₀)).
        for (stiffness, want) in [(16.0, 4.0 * 0.5), (4.0, 4.0), (0.0, 4.0)] {
            let rule = MembraneRule {
                slope: 0.0,
                multi_factor: 4.0,
                multi_slope: 0.03,
                stiffness,
            };
            obj.set_membrane_weights(dem.view(), rho.view(), rule);
            let r = obj.membrane_relief.as_ref().unwrap();
            assert!(
                (1.0 - r[(3, 30)] - want).abs() < 1e-6,
                "S₀ {stiffness}: {}",
                r[(3, 30)]
            );
            assert_eq!(r[(3, 5)], 0.0, "one observation keeps η");
        }
    }

    /// The albedo coupling of the Gauss–Newton Hessian against its closed form, two Lambert
    /// observations over a level surface (Suns 60° and 45° from the zenith, 120° apart in
    /// azimuth), the second only over the right half. R_k = ρ·cos i_k, so ∂R_k/∂(p, q)/Ī =
    /// d_k g_k with d_k = R_k/Ī = ρ cos i_k/Ī and g_k = ∇ln μ0, |g_k| = tan i_k, and
    /// H = 2 Σ_k W_k g_k g_kᵀ with W_k = w_k d_k². With the albedo eliminated (ν = 1) H
    /// becomes 2 times the W-weighted covariance of the g_k: for two observations
    /// 2 W₁W₂/(W₁ + W₂)·(g₁ − g₂)(g₁ − g₂)ᵀ, singular (the slope both images see alike is
    /// the albedo's) with trace 2 W₁W₂/(W₁ + W₂)·(tan² i₁ + tan² i₂ − 2 tan i₁ tan i₂ cos Δφ).
    /// Where one observation carries the pixel, H becomes (1 − ν)H: one image and a free albedo
    /// fix no slope. Without a coupling H is unchanged.
    #[test]
    fn the_albedo_coupling_takes_the_albedos_direction_out_of_the_hessian() {
        let (ny, nx) = (6, 40);
        let dem = Array2::zeros((ny, nx));
        let (a, b) = (
            Array2::from_elem((ny, nx), 0.2),
            Array2::from_shape_fn((ny, nx), |(_, j)| if j < 20 { f64::NAN } else { 0.2 }),
        );
        let model = crate::photometry::Lambert;
        let pr = two_lambert((&a, &b), &dem, (45.0, 220.0), 1.5, &model);
        let scale = 0.2;
        let mut obj = Objective::new(&pr, 3.0, 0.2, 1.2, 1.5, scale, weights_of(&pr, scale));
        let rho = Array2::from_elem((ny, nx), 0.5);
        let photo = obj.photo(dem.view(), rho.view());
        let hessian = |obj: &Objective| {
            let mut m = Array2::from_elem((ny, nx), [0.0f32; 3]);
            obj.add_gauss_newton_hessian(&photo, &mut m);
            m.mapv(|h| h.map(f64::from))
        };
        let plain = hessian(&obj);
        obj.set_albedo_coupling(Some(Array2::from_elem((ny, nx), 1.0)));
        let full = hessian(&obj);
        obj.set_albedo_coupling(Some(Array2::from_elem((ny, nx), 0.5)));
        let half = hessian(&obj);
        obj.set_albedo_coupling(None);
        assert_eq!(hessian(&obj), plain);

        let (two, one) = ((3, 30), (3, 5));
        let (i1, i2, dphi) = (60f64.to_radians(), 45f64.to_radians(), 120f64.to_radians());
        let w = |k: usize| obj.weights.weight[k][two] as f64;
        let (d1, d2) = (0.5 * i1.cos() / scale, 0.5 * i2.cos() / scale);
        let (w1, w2) = (w(0) * d1 * d1, w(1) * d2 * d2);
        let spread = i1.tan().powi(2) + i2.tan().powi(2) - 2.0 * i1.tan() * i2.tan() * dphi.cos();
        let want = 2.0 * w1 * w2 / (w1 + w2) * spread;
        let [xx, xy, yy] = full[two];
        assert!(
            ((xx + yy) - want).abs() < 1e-5 * want,
            "trace {} against {want}",
            xx + yy
        );
        assert!(
            (xx * yy - xy * xy).abs() < 1e-5 * want * want,
            "{:?}",
            full[two]
        );
        let [pxx, _, pyy] = plain[two];
        assert!(
            xx + yy < 0.9 * (pxx + pyy),
            "{:?} against {:?}",
            full[two],
            plain[two]
        );
        for ((f, h), p) in full[one].iter().zip(&half[one]).zip(&plain[one]) {
            assert!(f.abs() < 1e-6 * p.abs().max(1.0), "{:?}", full[one]);
            assert!(
                (h - 0.5 * p).abs() < 1e-6 * p.abs().max(1.0),
                "{:?}",
                half[one]
            );
        }
        for ((f, h), p) in full[two].iter().zip(&half[two]).zip(&plain[two]) {
            assert!((h - 0.5 * (f + p)).abs() < 1e-5 * p.abs().max(1.0));
        }
    }

    /// The regularisers' coverage where one observation sees a block shadowed and another
    /// carries it, against the closed form for Lambert (S_c = tan² i of the clean carrier,
    /// whatever the albedo): c_R = c + (1 − min(1, S_c/S₀))·κ on the block. Under a Sun 60°
    /// high (tan² 30° = 1/3) the block takes 0.7·(1 − 1/12) of an observation; under one 20°
    /// high (tan² 70° = 7.5 ≥ S₀ = 4) nothing changes anywhere; nor with S₀ = 0.
    #[test]
    fn a_shadow_carried_by_a_high_sun_takes_the_coverage_of_two_observations() {
        let n = 16;
        let dem = Array2::zeros((n, n));
        let a = Array2::from_shape_fn((n, n), |(i, j)| {
            if (6..9).contains(&i) && (6..9).contains(&j) {
                1e-4
            } else {
                0.2
            }
        });
        let b = Array2::from_elem((n, n), 0.2);
        let model = crate::photometry::Lambert;
        let coverage = |zenith_b: f64, stiffness: f64| {
            let pr = two_lambert((&a, &b), &dem, (zenith_b, 250.0), 0.0, &model);
            let w = crate::fusion::observations::weights(
                &pr,
                vec![1.0, 1.0],
                0.2,
                None,
                0.1,
                0.0,
                (0.25, 0.1),
            );
            let obj = Objective::new(&pr, 3.0, 0.2, 1.2, 0.0, 0.2, w).with_shadow_cover(
                0.7,
                (0.1, 0.0),
                stiffness,
            );
            (obj.regulariser_coverage(), obj.weights.multiplicity())
        };
        let (high, c) = coverage(30.0, 4.0);
        let want = 0.7 * (1.0 - 30f64.to_radians().tan().powi(2) / 4.0);
        assert_eq!(c[(7, 7)], 0.0);
        assert!((high[(7, 7)] - want).abs() < 1e-9, "{}", high[(7, 7)]);
        assert_eq!(high[(1, 1)], c[(1, 1)]);
        let (low, c) = coverage(70.0, 4.0);
        assert_eq!(low, c);
        let (off, c) = coverage(30.0, 0.0);
        assert_eq!(off, c);
    }

    /// With the edge-aware membrane's per-pixel weights (and the plain, weaker membrane where
    /// two observations overlap) the gradient still matches E.
    #[test]
    fn gradient_matches_finite_differences_with_an_edge_aware_membrane() {
        let (z, dem) = surfaces(12, 30);
        let (a, b) = two_strips(1.0);
        let model = Hapke::moon();
        let pr = two_observations(&a, &b, &dem, &model);
        let w = crate::fusion::observations::weights(
            &pr,
            vec![1.0, 1.0],
            0.03,
            None,
            0.0,
            4.0,
            (1.0, 1.0),
        );
        let mut obj = Objective::new(&pr, 3.0, 0.5, 1.2, 1.5, 0.03, w);
        // The weights come from another surface than the one the gradient is checked at.
        let start = &dem + &z.mapv(|v| 0.5 * v);
        let rho = Array2::from_elem(dem.dim(), 0.3);
        let rule = |slope, multi_factor, stiffness| MembraneRule {
            slope,
            multi_factor,
            multi_slope: 0.0,
            stiffness,
        };
        obj.set_membrane_weights(start.view(), rho.view(), rule(0.05, 0.2, 0.0));
        let r = obj.membrane_relief.as_ref().unwrap();
        // Single coverage: 1 − m, strictly between 0 and 1 on a steep correction; full double
        // coverage: 1 − 0.2 (to the rounding of the weights, held in f32).
        assert!(r[(5, 2)] > 0.1 && r[(5, 2)] < 1.0, "{}", r[(5, 2)]);
        assert!((r[(5, 14)] - 0.8).abs() < 1e-6, "{}", r[(5, 14)]);
        assert_gradient_matches(&obj, &z, &[(3, 4), (6, 9), (5, 15), (11, 25), (0, 29)]);
        // k = 0, a factor of 1 and no stiffness rule: the plain membrane, no field at all.
        obj.set_membrane_weights(start.view(), rho.view(), rule(0.0, 1.0, 0.0));
        assert!(obj.membrane_relief.is_none());
    }

    #[test]
    fn psd_part_drops_negative_eigenvalues() {
        let close = |a: [f64; 3], b: [f64; 3]| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert_eq!(psd_part([2.0, 0.5, 1.0]), [2.0, 0.5, 1.0]);
        assert_eq!(psd_part([-2.0, 0.5, -1.0]), [0.0; 3]);
        assert!(close(psd_part([2.0, 0.0, -1.0]), [2.0, 0.0, 0.0]));
        assert!(close(psd_part([-1.0, 0.0, 3.0]), [0.0, 0.0, 3.0]));
        // Eigenvalues 3 and −1, eigenvector (1, 1)/√2 for 3.
        assert!(close(psd_part([1.0, 2.0, 1.0]), [1.5, 1.5, 1.5]));
    }

    /// Where the image is brighter than R can get (r > 0 near R's maximum over the slopes),
    /// 2aaᵀ + M is the exact Hessian of the pixel's (I − R)²/Ī² in (p, q).
    #[test]
    fn curvature_completes_the_gauss_newton_hessian() {
        use crate::photometry::Lambert;
        let (ny, nx) = (5, 5);
        let sun = crate::synth::direction(40.0, 90.0);
        // A plane tilted most of the way towards the Sun: near R's maximum.
        let (p0, q0) = (-0.8 * sun[0] / sun[2], 0.3);
        let eps = 10.0;
        let z = Array2::from_shape_fn((ny, nx), |(i, j)| p0 * eps * j as f64 - q0 * eps * i as f64);
        let image = Array2::from_elem((ny, nx), 0.9);
        let model = Lambert;
        let pr = Problem::single(
            image.view(),
            Directions::Uniform(sun),
            Directions::Uniform([0.0, 0.0, 1.0]),
            z.view(),
            eps,
            0.0,
            &model,
        );
        let s = 0.7;
        let obj = Objective::new(&pr, 1.0, 0.1, 1.0, 0.0, s, weights_of(&pr, s));
        let rho = Array2::from_elem((ny, nx), 0.6);
        let photo = obj.photo(z.view(), rho.view());
        let m = obj.curvature(z.view(), rho.view(), &photo, 0.0)[(2, 2)].map(f64::from);
        let ph = &photo.obs[0];
        let (a, b) = (f64::from(ph.a[(2, 2)]), f64::from(ph.b[(2, 2)]));
        assert!(ph.res[(2, 2)] > 0.1, "the pixel must be brighter than R");
        let e = |p: f64, q: f64| {
            let r = (0.9 - model.shade_observed(p, q, 0.6, &sun, &[0.0, 0.0, 1.0]).r) / s;
            r * r
        };
        let h = 1e-4;
        let hxx = (e(p0 + h, q0) - 2.0 * e(p0, q0) + e(p0 - h, q0)) / (h * h);
        let hyy = (e(p0, q0 + h) - 2.0 * e(p0, q0) + e(p0, q0 - h)) / (h * h);
        let hxy = (e(p0 + h, q0 + h) - e(p0 + h, q0 - h) - e(p0 - h, q0 + h) + e(p0 - h, q0 - h))
            / (4.0 * h * h);
        for (got, want) in [
            (2.0 * a * a + m[0], hxx),
            (2.0 * a * b + m[1], hxy),
            (2.0 * b * b + m[2], hyy),
        ] {
            // f32 storage: a few parts in 10⁷ on top of the differences' 10⁻⁵.
            assert!(
                (got - want).abs() < 1e-5 * want.abs().max(1.0),
                "{got} vs {want}"
            );
        }
        // Below the residual threshold the term is left out.
        let none = obj.curvature(z.view(), rho.view(), &photo, 1e9);
        assert!(none.iter().all(|m| *m == [0.0; 3]));
    }
}
