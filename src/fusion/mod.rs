//! Fusion of shape from shading with an absolute DEM (Herbort, Grumpe & Wöhler; docs/science.md).
//!
//! [`fuse`] runs the albedo outer loop: at each stage m it inverts R(ρ; μ0, μ, g) = I pixel by
//! pixel on the current surface, low-passes ρ with a masked Gaussian of width σ_ρ⁽ᵐ⁾, and then
//! minimises the energy of [`objective`] over z with that albedo, using the selected
//! [`SolverKind`]. The final albedo is the per-pixel inversion on the final surface, lightly
//! smoothed.

pub mod blur;
mod fast;
pub mod gains;
pub mod objective;
pub mod observations;
pub mod ops;
mod paper;
pub mod pyramid;
pub mod shadows;
pub mod support;
mod validate;

pub use objective::Energy;
pub use observations::{Selection, Weights};
use validate::validate;
pub use validate::validate_params;

use crate::photometry::{widen, ReflectanceModel, Vec3, Vec3f};
use crate::spectral::{self, Dct2d};
use ndarray::{Array2, ArrayView2, CowArray, Ix2, Zip};
use objective::{MembraneRule, Objective, Photo};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Unit vectors (east, north, up) to the Sun or to the camera: one for the whole grid, or one
/// per pixel (as M3's OBS backplanes give them) in f32, owned or borrowed from the ingested
/// image (12 bytes per pixel each: a tile does not copy them).
#[derive(Debug, Clone)]
pub enum Directions<'a> {
    Uniform(Vec3),
    PerPixel(CowArray<'a, Vec3f, Ix2>),
}

impl Directions<'_> {
    /// The direction at pixel (i, j), in f64 (a per-pixel one widened exactly).
    #[inline]
    pub fn at(&self, i: usize, j: usize) -> Vec3 {
        match self {
            Directions::Uniform(v) => *v,
            Directions::PerPixel(a) => widen(&a[(i, j)]),
        }
    }

    /// The same directions, borrowed.
    pub fn borrowed(&self) -> Directions<'_> {
        match self {
            Directions::Uniform(v) => Directions::Uniform(*v),
            Directions::PerPixel(a) => Directions::PerPixel(a.view().into()),
        }
    }
}

/// One observation of the surface: an image on the grid with its Sun and view directions.
pub struct Observation<'a> {
    /// Observed reflectance I in the model's units (sr⁻¹ for Hapke); NaN = not seen.
    pub image: ArrayView2<'a, f64>,
    pub sun: Directions<'a>,
    pub view: Directions<'a>,
}

/// One fusion problem on a locally metric grid (row 0 north, column 0 west).
pub struct Problem<'a> {
    /// Every observation of the grid (at least one); E_I sums over them
    /// ([`observations`]).
    pub observations: Vec<Observation<'a>>,
    /// Input DEM resampled to the grid, metres; must be finite everywhere.
    pub dem: ArrayView2<'a, f64>,
    /// Grid spacing ε in metres (equal in x and y).
    pub spacing: f64,
    /// Standard deviation, in grid pixels, of the input DEM's own point-spread relative to the
    /// grid (0 = the seed's plain DEM term). See [`dem_psf_sigma`].
    pub dem_psf_sigma: f64,
    pub model: &'a dyn ReflectanceModel,
    /// Ī, the intensity scale E_I is normalised by. `None`: the mean of the usable pixels of
    /// all images. A tiled run passes the mean over the whole region, so every tile weighs
    /// E_I against the DEM terms alike (no tile-to-tile offsets).
    pub intensity_scale: Option<f64>,
    /// Radiometric gains g_k (I_k = g_k·R). `None`: estimated from where the observations
    /// overlap on the input DEM ([`gains::estimate_gains`]); a tiled run passes the
    /// run-wide values.
    pub gains: Option<Vec<f64>>,
    /// Noise weights ν_k. `None`: Ī/Ī_k from the images ([`observations::noise_weight`]).
    pub noise_weights: Option<Vec<f64>>,
    /// σ_k, grid pixels, of each observation's blur relative to the grid: its detector
    /// averages the reflectance over more than one grid pixel (an image coarser than the grid;
    /// [`blur::sigma_px`]), and E_I compares it with B_k R ([`blur`]). `None`, or σ_k below
    /// [`blur::MIN_SIGMA_PX`]: sharp.
    pub blur: Option<Vec<f64>>,
    /// Which observations each pixel uses.
    pub selection: Selection,
}

impl Observation<'_> {
    /// Σ I/g over the valid (finite, positive) pixels, and their count.
    pub fn valid_sum(&self, gain: f64) -> (f64, usize) {
        self.image.fold((0.0, 0), |(s, n), &v| {
            if v.is_finite() && v > 0.0 {
                (s + v / gain, n + 1)
            } else {
                (s, n)
            }
        })
    }
}

impl<'a> Problem<'a> {
    /// σ_k of observation `k` in grid pixels where it is modelled as blurred (at least
    /// [`blur::MIN_SIGMA_PX`]); 0: sharp.
    pub fn blur_sigma(&self, k: usize) -> f64 {
        self.blur
            .as_ref()
            .and_then(|b| b.get(k).copied())
            .filter(|s| s.is_finite() && *s >= blur::MIN_SIGMA_PX)
            .unwrap_or(0.0)
    }

    /// Whether any observation is modelled as blurred ([`Problem::blur_sigma`]).
    pub fn any_blurred(&self) -> bool {
        (0..self.observations.len()).any(|k| self.blur_sigma(k) > 0.0)
    }

    /// B_k of observation `k` ([`blur`]); `None`: sharp.
    pub fn blur_kernel(&self, k: usize) -> Option<blur::Kernel> {
        blur::Kernel::gaussian(self.blur_sigma(k))
    }

    /// Whether an observation other than `k` has a value at pixel `ij` (sees it, lit or in
    /// shadow).
    pub fn seen_by_another(&self, k: usize, ij: (usize, usize)) -> bool {
        (self.observations.iter().enumerate()).any(|(m, o)| m != k && o.image[ij].is_finite())
    }

    /// The footprint: where at least one image has a value (cast shadow included: the image
    /// sees the surface there, E_I just has no gradient to give).
    pub fn footprint(&self) -> Array2<bool> {
        let mut seen = Array2::from_elem(self.dem.dim(), false);
        for o in &self.observations {
            Zip::from(&mut seen)
                .and(&o.image)
                .for_each(|s, &v| *s |= v.is_finite());
        }
        seen
    }

    /// A problem with one image, everything else by default.
    pub fn single(
        image: ArrayView2<'a, f64>,
        sun: Directions<'a>,
        view: Directions<'a>,
        dem: ArrayView2<'a, f64>,
        spacing: f64,
        dem_psf_sigma: f64,
        model: &'a dyn ReflectanceModel,
    ) -> Self {
        Self {
            observations: vec![Observation { image, sun, view }],
            dem,
            spacing,
            dem_psf_sigma,
            model,
            intensity_scale: None,
            gains: None,
            noise_weights: None,
            blur: None,
            selection: Selection::default(),
        }
    }
}

/// Effective Gaussian point-spread, in grid pixels, of a DEM sampled `factor` times coarser than
/// the grid and resampled to it bilinearly: an anti-alias low-pass of σ = factor/2 plus the box
/// of one coarse pixel (variance factor²/12) plus the bilinear tent (variance factor²/6) give
/// σ² = factor²/4 + factor²/4, σ = factor/√2 (≈ 2.8 px at 4× coarser).
pub const fn dem_psf_sigma(factor: f64) -> f64 {
    if factor <= 1.0 {
        0.0
    } else {
        factor / std::f64::consts::SQRT_2
    }
}

/// Default σ_DEM, in grid pixels, for a DEM whose independent heights are `factor` grid pixels
/// apart: 0.5 × factor (at least 1 px) up to 4× coarser, where it reaches the 2 px tuned on
/// the demo scene, then max(2, 0.35 × factor). What matters most for a coarse DEM is its point
/// spread B ([`dem_psf_sigma`], from the *effective* resolution); σ_DEM low-passes the
/// comparison: wide enough to keep the DEM's noise and interpolation ramps out of E_DEM,
/// narrow enough to keep the slopes a fine DEM does resolve (docs/science.md, "The DEM's
/// resolution").
pub fn dem_sigma(factor: f64) -> f64 {
    if factor <= 4.0 {
        (0.5 * factor).max(1.0)
    } else {
        (0.35 * factor).max(2.0)
    }
}

/// E_DEM's track weighting a for a DEM of point spread `dem_psf_sigma` (σ_B, pixels), with the
/// along-track length `track_sigma` (σ_t, pixels): `weight` where σ_B < σ_t, else 1 (the plain
/// term). The weighting frees east–west slopes of structure that is smooth along the columns
/// over σ_t but not across them: track offsets. A DEM blurred by σ_B ≥ σ_t holds nothing
/// finer than σ_t in either direction, so the weighting would free every east–west slope it
/// holds, which costs (docs/science.md, "The DEM's tracks": 0.30× → 0.31× the input's error on
/// the 14×-coarse DEM).
pub fn track_weight(weight: f64, dem_psf_sigma: f64, track_sigma: f64) -> f64 {
    if dem_psf_sigma >= track_sigma {
        1.0
    } else {
        weight
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
    /// Pixels with I/Ī_k below this are treated as cast shadow and drop out of E_I, Ī_k the
    /// observation's own mean ([`observations::own_mean`]; one observation: Ī).
    pub shadow_threshold: f64,
    /// Iteration limit per stage (Gauss–Newton steps for `fast`, sweeps for `paper`).
    pub max_iterations: usize,
    /// A stage stops when an iteration lowers E by less than this fraction (for `fast` a
    /// guard against stagnation: it stops on `step_tolerance`).
    pub tolerance: f64,
    /// A `fast` stage stops when no height changes by more than this many grid spacings ε in
    /// one Gauss–Newton step (0.01: 1.4 m at 140 m/px), or when the contraction of the last two
    /// steps' largest changes says the steps to come would not (`fast::remaining`). The
    /// largest change is local, where
    /// the energy decrease is a sum over the domain, so a tile and the whole region stop
    /// equally converged at every pixel (docs/science.md, "Tiles").
    pub step_tolerance: f64,
    /// `fast`: pixels whose |I − R|/Ī exceeds this add the residual curvature −2r∇²R (its
    /// positive semi-definite part) to the Gauss–Newton Hessian; a value above any residual
    /// (say 1e9) gives plain Gauss–Newton.
    pub curvature_residual: f64,
    /// Conjugate-gradient limit per Gauss–Newton step.
    pub cg_iterations: usize,
    /// Relative residual at which conjugate gradients stop. The rule is global (a norm over the
    /// whole grid), so an inexact step depends on the window it is solved on, and so does the
    /// path to a nonconvex minimum: at 0.1 a tile and the whole region ended up to 0.97 m apart
    /// on a crater rim, at 0.02 0.47 m. The fine stages then take 1.4× the conjugate-gradient
    /// iterations and one Gauss–Newton step fewer: the same time at 1 MP (docs/science.md,
    /// "Tiles").
    pub cg_tolerance: f64,
    /// Width, in pixels, of the band inside an observation's edge over which its weight ramps
    /// up where another observation carries on ([`observations::edge_weights`]).
    pub edge_ramp_px: f64,
    /// β: an observation's weight on a pixel next to one it sees shadowed, where another
    /// observation sees the pixel away from its own shadows ([`observations::shadow_edge_factors`];
    /// 1: the full weight). Under the observation's Sun up to 20° high it is 0.4β, rising to β
    /// at 25° ([`observations::low_sun_edge_factor`]); β and β_all both 1 turn the factors off
    /// under every Sun. Such a pixel is likely part in shadow, which the reflectance does
    /// not model (docs/science.md, "Several observations"). No effect with one observation.
    pub shadow_edge_weight: f64,
    /// β_all: the same factor where two or more other observations see the pixel away from
    /// their own shadows ([`observations::shadow_edge_factors`]). Three Suns spread in azimuth
    /// measure slope free of albedo in every direction without the pixel, which then adds
    /// mostly its partial shadow (docs/science.md, "Several observations"). Under the
    /// observation's Sun up to 20° high it is 0.1β_all, rising to β_all at 25°
    /// ([`observations::low_sun_edge_factor_all`]; "Three low Suns"). No effect with one or two
    /// observations.
    pub shadow_edge_weight_all: f64,
    /// Where two or more observations see a pixel under different Suns, shading and albedo
    /// separate pixel by pixel: a last albedo stage of this σ_ρ (pixels) is run there,
    /// blended by the multi-coverage c(x) of [`observations::Weights::multiplicity`] into the
    /// albedo of the pixels one observation carries (`multi_albedo_sigma_single`; no effect
    /// with one observation).
    pub multi_albedo_sigma: f64,
    /// σ_ρ (pixels) of the overlap passes where one observation carries a pixel next to
    /// pixels that several carry (c(x) = 0 there; blended by c with `multi_albedo_sigma`, and
    /// away from the overlap with the last configured σ_ρ: `near_overlap`). Sharper than a
    /// single image's last stage (4 px): beside pixels that two Suns pin down, one image's
    /// shading at 2–4 px is better read as albedo than as slope (docs/science.md, "The albedo
    /// where one observation carries a pixel"). No effect with one observation.
    pub multi_albedo_sigma_single: f64,
    /// σ of the final albedo map where c(x) = 1 (blended by c with `final_albedo_sigma`).
    pub multi_final_albedo_sigma: f64,
    /// How many times the last stage where observations overlap alternates its albedo
    /// inversion (at `multi_albedo_sigma`) and its surface solve (≥ 1). At that σ_ρ the
    /// albedo is nearly per pixel and follows the surface it is inverted from, so a second
    /// inversion from the solved surface moves the joint minimum on (docs/science.md,
    /// "Several observations"). Where two Suns leave a direction of slope to the albedo each
    /// plain pass takes only about a third off the way left to the alternation's limit;
    /// five passes with [`FusionParams::multi_albedo_coupling`] come near it ("The
    /// alternation run to its limit"). Every pass but the last takes [`PASS_STEPS`] steps,
    /// the same in every window.
    pub multi_albedo_passes: usize,
    /// κ: in every pass of that last stage but the last, the Gauss–Newton step takes into
    /// account that the albedo, inverted again at the next pass, follows the slopes: the
    /// albedo's direction is projected out of E_I's Hessian in share κ·c(x)
    /// ([`objective::Objective::set_albedo_coupling`], variable projection). The passes reach
    /// the same limit in fewer steps (docs/science.md, "The alternation run to its limit").
    /// In [0, 1]; 0: the plain alternation.
    pub multi_albedo_coupling: f64,
    /// Where several observations carry a pixel, δ is lowered to δ × this (blended by the
    /// multi-coverage c(x); [`objective::Objective::with_multi_delta`]); 1 keeps δ everywhere.
    pub multi_delta_factor: f64,
    /// Where the observations at a pixel measure slope free of albedo in every direction
    /// (three or more Suns spread in azimuth), δ is lowered further, towards δ × this: the
    /// factor becomes f − (f − f_all)·φ(x), f = `multi_delta_factor`, φ the share of that
    /// information in its least-measured direction ([`observations::every_direction`]; 0 for
    /// two observations, whose images never measure a second direction, and under Suns 20°
    /// high or lower on average, whose slopes carry the forward model's errors at grazing
    /// light: [`observations::EVERY_DIRECTION_SUN_DEG`]).
    pub multi_delta_factor_all: f64,
    /// Where the Suns of the observations at a pixel stand high (mean cot² of their
    /// elevations under 1.2, fully under 0.6: ≈ 42° and 52°), δ is lowered further, towards
    /// δ × this ([`observations::high_sun`]); the smallest of this rule's factor,
    /// `multi_delta_factor_all`'s and `multi_delta_factor_east_west`'s is used.
    pub multi_delta_factor_high_sun: f64,
    /// Where those high Suns also measure east–west slopes free of albedo (χ of
    /// [`observations::east_west_unmeasured`] under 0.02, fully; over 0.1 not at all:
    /// [`observations::EAST_WEST_UNMEASURED`]), `multi_delta_factor_high_sun` goes on down
    /// towards this, and η of [`observations::high_sun`] follows the wider ramp of
    /// [`observations::high_sun_east_west`] (from cot² e = 1.6, 38°, rather than 1.2).
    /// The DEM's track offsets are east–west slopes, which such images take
    /// out; where a pair's blind direction (the bisector of its azimuths) has an east–west
    /// part, a lower δ lets the offsets through (docs/science.md, "Several observations").
    /// At or above `multi_delta_factor_high_sun` the rule is off. It lets more of each image's
    /// detector column striping through as well (east–west slopes too), so `sfsfuse run` keeps
    /// it only where the survey finds no striping in any observation
    /// (`pipeline::plan::high_sun_east_west`).
    pub multi_delta_factor_high_sun_east_west: f64,
    /// Where the observations at a pixel measure east–west slopes free of albedo (their Suns
    /// not mirrored about the east–west line) and their Suns stand above about 25°, δ is
    /// lowered further, towards δ × this ([`observations::east_west_open`]); the smallest of
    /// the three rules' factors is used. At or above `multi_delta_factor` the rule is off, so a
    /// workflow that lowers `multi_delta_factor` below it (as [`FusionParams::edge_aware`]
    /// does) keeps one factor everywhere.
    /// Where they do not, the DEM holds those slopes, in which its track offsets lie, with
    /// δ × `multi_delta_factor`.
    pub multi_delta_factor_east_west: f64,
    /// k of the edge-aware membrane (a slope, dimensionless): from the second albedo stage on,
    /// the membrane weight at a pixel where one observation carries it is η/√(1 + |∇(z −
    /// z_DEM)|²/k²) of the surface the stage starts from
    /// ([`objective::Objective::set_membrane_weights`]); 0 keeps η everywhere.
    pub edge_membrane_slope: f64,
    /// Where several observations carry a pixel, the membrane's weight is η × this (blended
    /// by the multi-coverage c(x)), before the factors of `multi_eta_stiffness` and
    /// `multi_edge_membrane_slope`.
    pub multi_eta_factor: f64,
    /// k_m: where several observations carry a pixel the membrane is edge-aware, its weight
    /// × 1/√(1 + |∇(z − z_DEM)|²/k_m²) of the surface each stage starts from (a slope; 0:
    /// plain there). Two or more Suns fix the slopes of walls and rims, which a plain
    /// membrane flattens (docs/science.md, "Several observations").
    pub multi_edge_membrane_slope: f64,
    /// S₀: where several observations carry a pixel the membrane is further scaled by
    /// min(1, √(S/S₀)), S the photometric stiffness of a level surface there
    /// ([`objective::Objective::level_stiffness`]: Σ_k |∇ ln R_k|² over the observations, in
    /// the slopes); 0 turns it off. Under high Suns the shading changes little with slope and
    /// a fixed η holds the surface to the DEM's gradients (docs/science.md, "Several
    /// observations").
    pub multi_eta_stiffness: f64,
    /// κ: an observation that sees a pixel in shadow counts as κ of an observation towards
    /// the multi-coverage of the regularisers, the several-observation membrane, δ·f and the
    /// pixel-scale shrink (one that carries a pixel next to its own shadow, where the
    /// shadow-edge factor lowers its weight, counts in full), scaled down as the observations
    /// carrying the pixel cleanly measure slope more firmly ([`observations::ShadowCover`],
    /// [`objective::Objective::with_shadow_cover`]). A low Sun's shadowed crater floors, which
    /// a high Sun alone carries, then take the regularisation of two observations instead of
    /// being flattened as under one (docs/science.md, "A low and a high Sun"). 0 turns it off;
    /// under two low Suns it changes nothing; with `multi_eta_stiffness` = 0 it is off.
    pub multi_shadow_coverage: f64,
    /// The first albedo stage is solved on the grid block-averaged by this factor and its
    /// correction z − z_DEM interpolated back ([`pyramid`]); 1 solves it on the full grid.
    pub coarse_factor: usize,
    /// ℓ, pixels: E_DEM holds the heights of the blurred difference u = B_s z − T as well as
    /// its gradients, with weight 1/ℓ² against |∇u|² ([`objective::Objective::with_dem_height_length`]),
    /// so that at wavelengths beyond 2πℓ the DEM's heights hold the surface; 0 leaves gradients
    /// only. Without it a slope bias of the photometric model integrates into a tilt that grows
    /// with the region (docs/science.md, "Long wavelengths").
    pub dem_height_length_px: f64,
    /// a: E_DEM's weight on across-track (east–west) slopes of structure that is smooth along
    /// the track (north–south, over `dem_track_sigma_px`), relative to the rest
    /// ([`objective::Objective::with_dem_tracks`]). A gridded altimetry DEM's largest
    /// errors are offsets between neighbouring near-polar tracks: constant along a track,
    /// they are east–west slopes of north–south structure, and where the image measures
    /// those slopes the DEM should not hold them as firmly as the rest. 1: the plain term.
    /// A DEM whose point spread is as wide as `dem_track_sigma_px` gets the plain term
    /// whatever this says ([`track_weight`]).
    pub dem_track_weight: f64,
    /// σ_t, pixels: the length along the track (grid columns) over which structure counts as
    /// smooth for `dem_track_weight`, a Gaussian along the columns.
    pub dem_track_sigma_px: f64,
    /// Where the input DEM is much coarser than the grid, the membrane on the pixels one
    /// observation carries becomes edge-aware ([`coarse_dem_membrane`]): `fuse` applies the
    /// rule from the problem's point spread σ_B, then clears this flag. Off: the workflow's η
    /// and k everywhere.
    pub coarse_dem_membrane: bool,
    /// s of the pixel-scale shrink applied, where several observations overlap, to the fused
    /// correction z − z_DEM ([`ops::shrink_near_nyquist`]: waves near the Nyquist frequency
    /// scaled by 1 − s along each axis, at half of it by 1 − s/16; blended in by the
    /// multi-coverage c(x), so a pixel one observation carries is left alone). The
    /// photometric gradient barely sees waves that short, so what the solution holds there is
    /// mostly error (docs/science.md, "The pixel-scale shrink"). 0: off.
    pub nyquist_shrink: f64,
    /// λ of E_S, the cast shadows' term ([`shadows`]): a pixel an observation sees shadowed
    /// must lie below the Sun's horizon, one it sees lit past a shadow's end above it; the
    /// violation is measured in pixels of shadow length (docs/science.md, "Cast shadows").
    /// 0: off.
    pub shadow_weight: f64,
    /// τ: pixels of shadow length an E_S ray may be violated by at no cost.
    pub shadow_tolerance_px: f64,
    /// ω_all, E_S's factor on rays at pixels two or more other observations carry, under a Sun
    /// 30° high or more; under a Sun up to 20° high such a ray weighs 1, a smoothstep between
    /// ([`shadows::ray_weight_all`]; docs/science.md, "Three low Suns").
    pub shadow_weight_all: f64,
    /// E_S's factor on rays at pixels no other observation sees (one observation alone, or
    /// where strips do not overlap). A single ray per pixel made tiled runs end metres from
    /// the whole region under low Suns (docs/science.md, "Cast shadows"); 0: none there.
    pub shadow_weight_alone: f64,
    /// I/g/Ī_k from which a pixel counts as lit for E_S (the pixels between this and
    /// `shadow_threshold` are part in shadow and constrain nothing). 0.15: with the partial
    /// shadow's lit shares and rays of 40 px, a dim pixel that ends a shadow holds its ray as
    /// well as a bright one (0.5 until 2026-12-07; docs/science.md, "The lit threshold at 0.15").
    pub shadow_lit_threshold: f64,
    /// The longest walk of an E_S ray towards the Sun, and of a lit share's, pixels (where
    /// they act, a `run`'s halo is at least 4/3 of it, `workflow::auto_halo`). 40: a shadow
    /// longer than the walk gives its pixels no ray, and a 1.6-km deep crater under a 20° Sun
    /// casts one of 31 px (24 until 2026-12-07; docs/science.md, "Cast shadows", "The reach at
    /// 40 px").
    pub shadow_reach_px: usize,
    /// Model the pixels just past an observation's own cast shadows (the pixel 1 or 1.5 px
    /// towards its Sun image-shadowed) that another observation sees too as part in shadow:
    /// E_I and the albedo inversion compare
    /// I/g with f·R, f the pixel's lit share on the surface each stage starts from
    /// ([`shadows::lit_fraction`]; walks of at most `shadow_reach_px`), under Suns up to
    /// 27.5° high ([`shadows::partial_shadow_share`]). Off: f = 1, as before 2026-12-07.
    pub partial_shadow: bool,
}

impl Default for FusionParams {
    fn default() -> Self {
        Self {
            solver: SolverKind::Fast,
            gamma: 2.5,
            delta: 50.0,
            eta: 0.1,
            sigma_dem: 2.0,
            albedo_sigmas: vec![100.0, 10.0, 4.0],
            final_albedo_sigma: 1.0,
            shadow_threshold: 0.1,
            max_iterations: 30,
            tolerance: 1e-9,
            step_tolerance: 0.01,
            curvature_residual: 0.05,
            cg_iterations: 60,
            cg_tolerance: 0.02,
            edge_ramp_px: 16.0,
            shadow_edge_weight: 0.25,
            shadow_edge_weight_all: 0.1,
            multi_albedo_sigma: 0.5,
            multi_albedo_sigma_single: 2.0,
            multi_final_albedo_sigma: 0.7,
            multi_albedo_passes: 5,
            multi_albedo_coupling: 0.5,
            multi_delta_factor: 0.2,
            multi_delta_factor_all: 0.1,
            multi_delta_factor_high_sun: 0.05,
            multi_delta_factor_high_sun_east_west: 0.02,
            multi_delta_factor_east_west: 0.12,
            edge_membrane_slope: 0.0,
            multi_eta_factor: 8.0,
            multi_edge_membrane_slope: 0.01,
            multi_eta_stiffness: 8.0,
            multi_shadow_coverage: 0.7,
            coarse_factor: 4,
            dem_height_length_px: 30.0,
            dem_track_weight: 0.1,
            dem_track_sigma_px: 9.0,
            coarse_dem_membrane: true,
            nyquist_shrink: 0.75,
            shadow_weight: 2.0,
            shadow_tolerance_px: 0.0,
            shadow_weight_all: 0.1,
            shadow_weight_alone: 0.0,
            shadow_lit_threshold: 0.15,
            shadow_reach_px: 40,
            partial_shadow: true,
        }
    }
}

/// η of the membrane where one observation carries a pixel over a DEM ≥ 7× coarser than the
/// grid ([`coarse_dem_membrane`]).
pub const COARSE_DEM_ETA: f64 = 0.8;
/// k of that membrane's edge-aware factor (a slope; [`FusionParams::edge_membrane_slope`]).
pub const COARSE_DEM_EDGE_SLOPE: f64 = 0.02;

/// The parameters `fuse` solves with for a DEM of point spread `dem_psf_sigma` (σ_B, grid
/// pixels), when `params.coarse_dem_membrane` is set and the membrane is not already
/// edge-aware: with f = √2·σ_B the DEM's coarsening factor ([`dem_psf_sigma`]) and
/// t = smoothstep((f − 5)/2) (0 up to 5×, 1 from 7×), η → η + t·(η_c − η),
/// k = k_c/t (the edge-aware factor 1/√(1 + |∇(z − z_DEM)|²/k²) fades out as t → 0) and
/// `multi_eta_factor` scaled by η/η' so that the pixels several observations carry keep
/// their membrane. η_c = [`COARSE_DEM_ETA`], k_c = [`COARSE_DEM_EDGE_SLOPE`]. A DEM that
/// coarse holds nothing of the craters' walls the image sees, so a membrane that pulls the
/// correction's slopes towards the DEM's flattens them: the edge-aware membrane lets steep
/// corrections stand and holds flat ones firmly (docs/science.md, "The DEM's resolution":
/// 14× coarser, 0.41 / 0.47 / 0.38× → 0.33 / 0.39 / 0.29× the input's error at 256²). The
/// flag is cleared in what it returns, so the coarse reference's own problem, of point spread
/// σ_B/f, does not apply it again.
pub fn coarse_dem_membrane(params: &FusionParams, dem_psf_sigma: f64) -> FusionParams {
    let mut p = FusionParams {
        coarse_dem_membrane: false,
        ..params.clone()
    };
    if !params.coarse_dem_membrane || params.edge_membrane_slope > 0.0 || params.eta <= 0.0 {
        return p;
    }
    let f = dem_psf_sigma * std::f64::consts::SQRT_2;
    let t = support::smoothstep((f - 5.0) / 2.0);
    // Also a point spread that is not a number (refused with its name by `validate`).
    if t.is_nan() || t <= 0.0 {
        return p;
    }
    p.eta = params.eta + t * (COARSE_DEM_ETA - params.eta);
    p.edge_membrane_slope = COARSE_DEM_EDGE_SLOPE / t;
    p.multi_eta_factor = params.multi_eta_factor * params.eta / p.eta;
    p
}

impl FusionParams {
    /// The edge-aware membrane for single-image work (docs/science.md, "Edge-aware
    /// membrane"): η = 0.5 where the correction is flat, η/√(1 + |∇(z − z_DEM)|²/0.03²) on
    /// steep corrections, δ = 100; where several observations carry a pixel the membrane and
    /// DEM term keep the defaults' weights (η·1.2 = 0.6 before the stiffness and edge factors,
    /// δ·0.1 = 10). On the synthetic
    /// scenes it lowers single-image elevation errors by 8–10 %; it is not the default because
    /// several observations gain nothing from it (their ratio to the single image would rise
    /// from 0.65× to 0.71×) and on the real M3 crop it moves the DEM half as far.
    pub fn edge_aware() -> Self {
        Self {
            delta: 100.0,
            eta: 0.5,
            edge_membrane_slope: 0.03,
            multi_eta_factor: 1.2,
            multi_delta_factor: 0.1,
            ..Self::default()
        }
    }

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
    #[error(
        "the starting surface is {start:?} pixels but the DEM is {dem:?}: they must be on one grid"
    )]
    StartShape {
        start: (usize, usize),
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
    #[error("albedo_sigmas is empty: list at least one σ_ρ (the default is [100, 10, 4]); each is a stage of surface solves, and with none the DEM would pass through unchanged")]
    NoAlbedoStages,
    #[error("per-pixel direction array is {got:?} pixels, the grid {want:?}")]
    DirectionShape {
        got: (usize, usize),
        want: (usize, usize),
    },
    #[error("the problem has no observation: fusion needs at least one image")]
    NoImage,
    #[error("{what} has {got} values for {want} observations")]
    PerObservation {
        what: &'static str,
        got: usize,
        want: usize,
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
    /// The residual |I/g − R| at the solution (with several observations, their w-weighted
    /// RMS) where the pixel carried photometric information, NaN elsewhere.
    pub residual: Array2<f64>,
    /// True where the pixel carried photometric information at the solution.
    pub photometric: Array2<bool>,
    /// How many observations carried photometric information at each pixel.
    pub observations: Array2<u8>,
    /// Per observation: where it carried photometric information.
    pub used_by: Vec<Array2<bool>>,
    /// The radiometric gains g_k used (given or estimated).
    pub gains: Vec<f64>,
    /// The noise weights ν_k used.
    pub noise_weights: Vec<f64>,
    /// s ∈ [0, 1], the photometric support ([`support`]): the result is
    /// z_DEM + s·(z − z_DEM), so it is the input DEM wherever s = 0.
    pub support: Array2<f64>,
    pub stages: Vec<StageReport>,
}

impl Fusion {
    /// The Gauss–Newton (or `paper`) iterations of every stage ([`total_iterations`]).
    pub fn iterations(&self) -> usize {
        total_iterations(&self.stages)
    }
}

/// The iterations of `stages` in all: each stage's report lists its energy before the first
/// iteration and after each, so a stage took one fewer than it lists.
pub fn total_iterations(stages: &[StageReport]) -> usize {
    stages
        .iter()
        .map(|s| s.iterations.len().saturating_sub(1))
        .sum()
}

/// The image observation `k` of the problem renders from surface `z` with albedo `rho`:
/// R(p, q, ρ; s_k, v_k) (0 where the surface faces away from the Sun or the camera), in the
/// units of I/g_k, on the rows `r0..r1` and columns `c0..c1` of the grid (the slopes come
/// from the whole surface, so a value does not depend on the window).
pub fn render(
    pr: &Problem,
    k: usize,
    z: ArrayView2<f64>,
    rho: ArrayView2<f64>,
    (r0, r1, c0, c1): (usize, usize, usize, usize),
) -> Array2<f64> {
    let o = &pr.observations[k];
    let z = z.as_standard_layout();
    let nx = z.ncols();
    let mut out = Array2::zeros((r1 - r0, c1 - c0));
    // Row by row, the slopes of each row formed there ([`ops::gradient_row`], the values of
    // [`ops::gradient`]): no slope arrays of the grid's size.
    Zip::indexed(out.rows_mut()).par_for_each(|i, mut row| {
        let i = r0 + i;
        let (mut p, mut q) = (vec![0.0; nx], vec![0.0; nx]);
        ops::gradient_row(z.view(), pr.spacing, i, &mut p, &mut q);
        for (r, j) in row.iter_mut().zip(c0..c1) {
            *r = pr
                .model
                .shade_value(p[j], q[j], rho[(i, j)], &o.sun.at(i, j), &o.view.at(i, j));
        }
    });
    out
}

/// Masked Gaussians, one per σ of `sigmas`, of the per-pixel (joint) albedo on surface `z`
/// (one inversion for all of them).
fn albedo_maps(
    pr: &Problem,
    w: &Weights,
    dct: &Dct2d,
    z: ArrayView2<f64>,
    sigmas: &[f64],
) -> Result<Vec<Array2<f64>>, FusionError> {
    let (raw, ok, _) = observations::invert_albedo(pr, w, z, 1.0);
    sigmas
        .iter()
        .map(|&s| spectral::masked_gaussian(dct, &raw, &ok, s).ok_or(FusionError::NoObservations))
        .collect()
}

/// The masked Gaussian of width `sigma` of the per-pixel (joint) albedo on surface `z`.
pub(crate) fn albedo_map(
    pr: &Problem,
    w: &Weights,
    dct: &Dct2d,
    z: ArrayView2<f64>,
    sigma: f64,
) -> Result<Array2<f64>, FusionError> {
    Ok(albedo_maps(pr, w, dct, z, &[sigma])?.remove(0))
}

/// The final albedo: the per-pixel joint inversion on the final surface (`raw`, defined where
/// `ok`, weighted by `strength` = Σ_k w_k (I_k/g_k)²: dim pixels near the terminator amplify
/// slope errors into albedo errors by ∂w/∂R ∝ 1/R), smoothed by `sigma` where it is defined;
/// pixels without an inversion (shadow, no data) take the wider last-stage estimate (σ_ρ of
/// the last stage), which draws on more context.
fn final_albedo(
    dct: &Dct2d,
    (raw, ok, strength): &(Array2<f64>, Array2<bool>, Array2<f64>),
    sigma: f64,
    params: &FusionParams,
) -> Result<Array2<f64>, FusionError> {
    let mut fine = spectral::weighted_gaussian(dct, raw, strength, sigma)
        .ok_or(FusionError::NoObservations)?;
    let wide_sigma = params
        .albedo_sigmas
        .last()
        .copied()
        .unwrap_or(sigma)
        .max(sigma);
    let wide =
        spectral::masked_gaussian(dct, raw, ok, wide_sigma).ok_or(FusionError::NoObservations)?;
    Zip::from(&mut fine)
        .and(&wide)
        .and(ok)
        .for_each(|f, &w, &k| {
            if !k {
                *f = w;
            }
        });
    Ok(fine)
}

/// c·a + (1 − c)·b.
fn blend(a: &Array2<f64>, b: &Array2<f64>, c: &Array2<f64>) -> Array2<f64> {
    Zip::from(a)
        .and(b)
        .and(c)
        .map_collect(|&a, &b, &c| c * a + (1.0 - c) * b)
}

/// Mean of I_k/g_k over the valid (finite, positive) pixels of all observations, and their count.
fn mean_intensity(pr: &Problem, gains: &[f64]) -> (f64, usize) {
    let (mut s, mut n) = (0.0, 0usize);
    for (o, &g) in pr.observations.iter().zip(gains) {
        let (so, no) = o.valid_sum(g);
        s += so;
        n += no;
    }
    (if n > 0 { s / n as f64 } else { 0.0 }, n)
}

/// Validate the problem and set up its energy: gains, Ī and the per-observation weights.
pub(crate) fn objective<'a, 'p>(
    pr: &'a Problem<'p>,
    params: &FusionParams,
) -> Result<Objective<'a, 'p>, FusionError> {
    validate(pr, params)?;
    let k = pr.observations.len();
    let mut gains = pr.gains.clone().unwrap_or_else(|| vec![1.0; k]);
    let (mean, count) = mean_intensity(pr, &gains);
    if count == 0 {
        return Err(FusionError::NoObservations);
    }
    let mut scale = match pr.intensity_scale {
        Some(s) if s.is_finite() && s > 0.0 => s,
        Some(s) => {
            return Err(FusionError::Parameter {
                name: "intensity_scale",
                value: s,
                why: "must be a positive mean reflectance",
            })
        }
        None => mean,
    };
    let weights = |gains: Vec<f64>, scale: f64| {
        observations::weights(
            pr,
            gains,
            scale,
            pr.noise_weights.clone(),
            params.shadow_threshold,
            params.edge_ramp_px,
            (params.shadow_edge_weight, params.shadow_edge_weight_all),
        )
    };
    if pr.gains.is_none() && k > 1 {
        let first = weights(gains, scale);
        gains = gains::estimate_gains(pr, &first.usable, pr.dem).gains;
        if pr.intensity_scale.is_none() {
            scale = mean_intensity(pr, &gains).0;
        }
    }
    let w = weights(gains, scale);
    Ok(Objective::new(
        pr,
        params.delta,
        params.eta,
        params.sigma_dem,
        pr.dem_psf_sigma,
        scale,
        w,
    )
    .with_shadow_cover(
        params.multi_shadow_coverage,
        (params.shadow_threshold, params.edge_ramp_px),
        params.multi_eta_stiffness,
    )
    .with_multi_delta(objective::MultiDelta::of(params))
    .with_dem_height_length(params.dem_height_length_px * pr.spacing)
    .with_dem_tracks(
        track_weight(
            params.dem_track_weight,
            pr.dem_psf_sigma,
            params.dem_track_sigma_px,
        ),
        params.dem_track_sigma_px,
    )
    .with_shadows(
        params.shadow_weight,
        params.shadow_tolerance_px,
        (params.shadow_weight_all, params.shadow_weight_alone),
        params.shadow_threshold,
        params.shadow_lit_threshold,
        params.shadow_reach_px,
    ))
}

/// Run the whole fusion: albedo stages, each followed by a surface solve. With
/// `params.coarse_factor` = f > 1 the whole fusion first runs on the grid block-averaged by f
/// ([`pyramid::reference`]) and the stages after the first start from its result.
pub fn fuse(pr: &Problem, params: &FusionParams) -> Result<Fusion, FusionError> {
    // The parameters as given are checked before the rule for a coarse DEM rewrites them;
    // the problem is checked with them by `objective`.
    validate_params(params)?;
    let params = &coarse_dem_membrane(params, pr.dem_psf_sigma);
    let obj = objective(pr, params)?;
    let mut z = pr.dem.to_owned();
    let mut stages = Vec::new();
    let mut sigmas = &params.albedo_sigmas[..];
    if let Some(f) = coarse_factor(pr.dem.dim(), params) {
        let coarse = pyramid::coarsen(pr, f);
        let w = &obj.weights;
        let cp = coarse.problem(pr, obj.scale, &w.gains, &w.noise);
        let (correction, stage) = pyramid::reference(&cp, params, f)?;
        z += &pyramid::upsample(correction.view(), f, z.dim());
        stages.push(stage);
        sigmas = &sigmas[1..];
    }
    fine_stages(pr, obj, params, z, sigmas, stages)
}

/// The fusion's stages after the first, from `start` (in a tiled run, the input DEM plus the
/// plan's coarse reference correction over the whole region, [`pyramid::reference`]).
pub fn fuse_from(
    pr: &Problem,
    params: &FusionParams,
    start: Array2<f64>,
) -> Result<Fusion, FusionError> {
    validate_params(params)?;
    let params = &coarse_dem_membrane(params, pr.dem_psf_sigma);
    let obj = objective(pr, params)?;
    if start.dim() != pr.dem.dim() {
        return Err(FusionError::StartShape {
            start: start.dim(),
            dem: pr.dem.dim(),
        });
    }
    let sigmas = params.albedo_sigmas.get(1..).unwrap_or(&[]);
    fine_stages(pr, obj, params, start, sigmas, Vec::new())
}

/// The factor of the coarse first stage for a grid of `dim`: `params.coarse_factor`, or
/// `None` when it is 1, there is no albedo stage, or the coarse grid would be under 8 × 8.
pub fn coarse_factor(dim: (usize, usize), params: &FusionParams) -> Option<usize> {
    coarse_factor_at_least(dim, params, 1)
}

/// [`coarse_factor`], raised to at least `min` (a tiled run keeps its reference's grid
/// bounded this way); still `None` when `params.coarse_factor` is 1.
pub fn coarse_factor_at_least(
    (ny, nx): (usize, usize),
    params: &FusionParams,
    min: usize,
) -> Option<usize> {
    let f = params.coarse_factor;
    if f <= 1 || params.albedo_sigmas.is_empty() {
        return None;
    }
    let f = f.max(min);
    (ny / f >= 8 && nx / f >= 8).then_some(f)
}

/// `fast`: Gauss–Newton steps of an albedo stage before the last. Such a stage only hands the
/// next one its surface, from which the next inverts its albedo (and, where the membrane is
/// edge-aware, weighs it): a fixed count, so that every window takes the same steps (fewer
/// only where the energy stops decreasing). A threshold on the window's largest change
/// stopped it after two steps in one window and three in another, and under a Sun 20° high
/// one image's tiles then ended up to 0.44× the RMSE from the whole region (docs/science.md,
/// "Solvers").
pub const STAGE_STEPS: usize = 2;

/// Gauss–Newton steps of each pass of the last stage where observations overlap but the final
/// one ([`FusionParams::multi_albedo_passes`]): a fixed count, as [`STAGE_STEPS`].
pub const PASS_STEPS: usize = 1;

/// The images of the observations coarser than the grid, each times R_k/(B_k R_k) at surface
/// `z` and albedo `rho` ([`blur`]): the rendering's shading within the kernel put back into the
/// blurred image, so that the albedo inverted from it at a pixel's own slope keeps the image's
/// brightness at the scales the image resolves, not its blurred shading. `None` for a sharp
/// observation (or none at all: every entry `None`).
fn sharpened_images(
    pr: &Problem,
    z: ArrayView2<f64>,
    rho: ArrayView2<f64>,
) -> Vec<Option<Array2<f64>>> {
    let (p, q) = ops::gradient(z, pr.spacing);
    (0..pr.observations.len())
        .map(|k| {
            let kernel = pr.blur_kernel(k)?;
            let o = &pr.observations[k];
            let r = Zip::indexed(&o.image).par_map_collect(|(i, j), &v| {
                if !v.is_finite() {
                    return 0.0;
                }
                let sh = pr.model.shade_observed(
                    p[(i, j)],
                    q[(i, j)],
                    rho[(i, j)],
                    &o.sun.at(i, j),
                    &o.view.at(i, j),
                );
                if sh.lit {
                    sh.r
                } else {
                    0.0
                }
            });
            let blurred = blur::convolve(&kernel, &r);
            Some(
                Zip::from(&o.image)
                    .and(&r)
                    .and(&blurred)
                    .par_map_collect(|&v, &r, &b| if b > 0.0 && r > 0.0 { v * r / b } else { v }),
            )
        })
        .collect()
}

/// `pr` with observation k's image replaced by `images[k]` where it is `Some`.
fn with_images<'b>(pr: &'b Problem, images: &'b [Option<Array2<f64>>]) -> Problem<'b> {
    Problem {
        observations: pr
            .observations
            .iter()
            .zip(images)
            .map(|(o, i)| Observation {
                image: i.as_ref().map_or(o.image.view(), |i| i.view()),
                sun: o.sun.borrowed(),
                view: o.view.borrowed(),
            })
            .collect(),
        dem: pr.dem.view(),
        spacing: pr.spacing,
        dem_psf_sigma: pr.dem_psf_sigma,
        model: pr.model,
        intensity_scale: pr.intensity_scale,
        gains: pr.gains.clone(),
        noise_weights: pr.noise_weights.clone(),
        blur: pr.blur.clone(),
        selection: pr.selection,
    }
}

/// The albedo stages of widths `sigmas` from surface `z`, then the support taper, the final
/// albedo and the layers.
fn fine_stages(
    pr: &Problem,
    mut obj: Objective,
    params: &FusionParams,
    mut z: Array2<f64>,
    sigmas: &[f64],
    mut stages: Vec<StageReport>,
) -> Result<Fusion, FusionError> {
    // The multi-coverage c(x), kept only where observations overlap (a single observation's
    // is 0 everywhere: no array is held through the stages for it).
    let multi = Some(obj.weights.multiplicity()).filter(|c| c.iter().any(|&c| c > 0.0));
    let last_rho = albedo_stages(
        pr,
        &mut obj,
        params,
        &mut z,
        sigmas,
        multi.as_ref(),
        &mut stages,
    )?;
    // Where observations overlap, the correction's pixel-scale waves are shrunk (blended in
    // by the regularisers' coverage c_R, which is the multi-coverage c unless a shadowing
    // observation counts, `Objective::with_shadow_cover`); beyond the support band the
    // result is the input DEM, within it the correction fades. (s is formed again for the
    // layers at the end: the final albedo's arrays need the memory in between.)
    Zip::from(&mut z).and(pr.dem).par_for_each(|z, &d| *z -= d);
    if multi.is_some() || obj.coverage.is_some() {
        let cover = obj.regulariser_coverage();
        let shrunk = ops::shrink_near_nyquist(z.view(), params.nyquist_shrink);
        z = blend(&shrunk, &z, &cover);
    }
    Zip::from(&mut z)
        .and(&obj.support())
        .and(pr.dem)
        .par_for_each(|z, &s, &d| *z = d + s * *z);
    obj.set_lit_fractions(z.view(), params);
    let mut albedo = final_albedo_layer(pr, &obj, params, z.view(), last_rho, multi.as_ref())?;
    drop(multi);
    // The residuals and coverage of each observation on the final surface (their slopes'
    // derivatives are not needed: freed at once).
    let Photo {
        obs, used: covered, ..
    } = obj.photo(z.view(), albedo.view());
    let obs: Vec<_> = obs.into_iter().map(|ph| (ph.res, ph.used)).collect();
    // Off every image's footprint the albedo would only be the smoothing's fill: no data.
    Zip::from(&mut albedo)
        .and(&pr.footprint())
        .for_each(|a, &s| {
            if !s {
                *a = f64::NAN;
            }
        });
    let w = &obj.weights;
    let (residual, count) = residual_layers(&obs, &w.weight, &covered, obj.scale);
    let photometric = covered;
    let used_by = obs.into_iter().map(|(_, used)| used).collect();
    Ok(Fusion {
        height: z,
        albedo,
        residual,
        photometric,
        observations: count,
        used_by,
        gains: w.gains.clone(),
        noise_weights: w.noise.clone(),
        support: obj.support(),
        stages,
    })
}

/// The alternation of albedo and surface: one stage per width of `sigmas` (the albedo
/// low-passed at σ_ρ from the current surface, the membrane weighed on it, then the surface
/// solved), and where observations overlap (`multi`, the multi-coverage c(x)) the last stage
/// at `multi_albedo_sigma` blended by c, `multi_albedo_passes` times. Appends each stage's
/// report to `stages`; returns the last stage's albedo where an observation is coarser than the
/// grid (the final albedo's sharpened images need it), `None` otherwise.
fn albedo_stages(
    pr: &Problem,
    obj: &mut Objective,
    params: &FusionParams,
    z: &mut Array2<f64>,
    sigmas: &[f64],
    multi: Option<&Array2<f64>>,
    stages: &mut Vec<StageReport>,
) -> Result<Option<Array2<f64>>, FusionError> {
    // Where observations overlap, a last stage at `multi_albedo_sigma` follows the configured
    // ones (blended into the last of them, and next to the overlap into
    // `multi_albedo_sigma_single`).
    let multi_stage = params
        .albedo_sigmas
        .last()
        .copied()
        .filter(|_| multi.is_some());
    // Where observations overlap, every stage solves its conjugate gradients further
    // (`MULTI_CG_FACTOR`), and the passes further still.
    let factor = if multi.is_some() {
        MULTI_CG_FACTOR
    } else {
        1.0
    };
    let params = &FusionParams {
        cg_tolerance: factor * params.cg_tolerance,
        ..params.clone()
    };
    let early = early_stage_params(params);
    // The last stage's albedo, kept for the final albedo's sharpened images only where an
    // observation is coarser than the grid (otherwise not held past its stage).
    let keep_rho = pr.any_blurred();
    let mut last_rho: Option<Array2<f64>> = None;
    for (m, &sigma) in sigmas.iter().enumerate() {
        let t0 = Instant::now();
        obj.set_lit_fractions(z.view(), params);
        let rho = albedo_map(pr, &obj.weights, &obj.dct, z.view(), sigma)?;
        obj.begin_stage(z.view(), rho.view(), MembraneRule::of(params));
        let last = m + 1 == sigmas.len() && multi_stage.is_none();
        let stage_params = if last || params.solver == SolverKind::Paper {
            params
        } else {
            &early
        };
        let iterations = minimise(obj, z, rho.view(), stage_params, &mut |_| {});
        if keep_rho {
            last_rho = Some(rho);
        }
        stages.push(StageReport {
            sigma_rho: sigma,
            iterations,
            seconds: t0.elapsed().as_secs_f64(),
        });
    }
    if let (Some(last), Some(multi)) = (multi_stage, multi) {
        // The passes' albedo replaces the configured stages' (there is at least one pass).
        drop(last_rho.take());
        last_rho = overlap_passes(pr, obj, params, z, (last, multi), keep_rho, stages)?;
    }
    Ok(last_rho)
}

/// The parameters of a stage before the last: exactly [`STAGE_STEPS`] Gauss–Newton steps, the
/// same in every window, where a threshold on the window's largest change would make a tile
/// and the whole region hand the next stage different surfaces.
fn early_stage_params(params: &FusionParams) -> FusionParams {
    FusionParams {
        step_tolerance: 0.0,
        max_iterations: STAGE_STEPS.min(params.max_iterations),
        ..params.clone()
    }
}

/// The last stage where observations overlap, `multi_albedo_passes` times: the albedo at
/// `multi_albedo_sigma` blended by the multi-coverage `multi` with the one where one
/// observation carries the pixel (at `multi_albedo_sigma_single` next to the overlap, at
/// `last`, the last configured σ_ρ, away from it: [`near_overlap`]), the membrane weighed on
/// it, the surface solved, each step's conjugate gradients to [`PASS_CG_FACTOR`] × the
/// stages' `cg_tolerance`. Every pass but the last hands the next its surface, from which the
/// next inverts its albedo and weighs its membrane: a fixed number of steps, the same in every
/// window (one: a second step moves the results by less than 1 mm). Appends each pass's
/// report to `stages`; returns the last pass's albedo where `keep_rho`.
fn overlap_passes(
    pr: &Problem,
    obj: &mut Objective,
    params: &FusionParams,
    z: &mut Array2<f64>,
    (last, multi): (f64, &Array2<f64>),
    keep_rho: bool,
    stages: &mut Vec<StageReport>,
) -> Result<Option<Array2<f64>>, FusionError> {
    let passes = params.multi_albedo_passes;
    let near = near_overlap(&obj.dct, multi, NEAR_OVERLAP_SIGMA_FACTOR * last);
    // The passes solve their steps further (`PASS_CG_FACTOR`).
    let params = &FusionParams {
        cg_tolerance: PASS_CG_FACTOR * params.cg_tolerance,
        ..params.clone()
    };
    let handing_on = FusionParams {
        step_tolerance: 0.0,
        max_iterations: PASS_STEPS.min(params.max_iterations),
        ..params.clone()
    };
    let mut last_rho = None;
    for pass in 0..passes {
        let t0 = Instant::now();
        obj.set_lit_fractions(z.view(), params);
        let maps = albedo_maps(
            pr,
            &obj.weights,
            &obj.dct,
            z.view(),
            &[
                params.multi_albedo_sigma,
                params.multi_albedo_sigma_single,
                last,
            ],
        )?;
        let one = blend(&maps[1], &maps[2], &near);
        let rho = blend(&maps[0], &one, multi);
        drop(maps);
        obj.begin_stage(z.view(), rho.view(), MembraneRule::of(params));
        let handing = pass + 1 < passes;
        let pass_params = if handing && params.solver == SolverKind::Fast {
            &handing_on
        } else {
            params
        };
        // A pass that hands its surface on steps with the albedo following the slopes; the
        // last solves with the albedo it inverted.
        let kappa = params.multi_albedo_coupling;
        obj.set_albedo_coupling((handing && kappa > 0.0).then(|| multi.mapv(|c| kappa * c)));
        let iterations = minimise(obj, z, rho.view(), pass_params, &mut |_| {});
        obj.set_albedo_coupling(None);
        if keep_rho {
            last_rho = Some(rho);
        }
        stages.push(StageReport {
            sigma_rho: params.multi_albedo_sigma,
            iterations,
            seconds: t0.elapsed().as_secs_f64(),
        });
    }
    Ok(last_rho)
}

/// How near a pixel lies to where several observations carry the surface: b = min(1,
/// [`NEAR_OVERLAP_GAIN`] · (G_σ ∗ c)(x)), c the multi-coverage (σ = `sigma`; the overlap
/// passes use [`NEAR_OVERLAP_SIGMA_FACTOR`] × the last configured σ_ρ). Where one observation
/// carries a pixel the passes take its albedo at `multi_albedo_sigma_single` in share b and at
/// the last configured σ_ρ in share 1 − b: in the other Suns' shadows and the rings beside them
/// b is 1, while deep in one strip's own part, as in a window with no overlap at all, the
/// albedo stays that of a single image (b = 0). b reaches 0 within some 3σ of the overlap, well
/// inside a tile's halo.
fn near_overlap(dct: &Dct2d, multi: &Array2<f64>, sigma: f64) -> Array2<f64> {
    spectral::gaussian_filter(dct, multi, sigma).mapv(|v| (NEAR_OVERLAP_GAIN * v).clamp(0.0, 1.0))
}

/// The width of `near_overlap`'s Gaussian in the overlap passes, in last configured σ_ρ (8 px
/// at the defaults; `workflow::auto_halo` counts it where several observations are listed).
pub const NEAR_OVERLAP_SIGMA_FACTOR: f64 = 2.0;

/// The gain of `near_overlap`, the share of the sharper albedo next to the overlap: a pixel
/// with a quarter of its σ-neighbourhood's weight in the overlap counts as next to it.
pub const NEAR_OVERLAP_GAIN: f64 = 4.0;

/// Where observations overlap in a window, its stages solve each Gauss–Newton step's conjugate
/// gradients to this share of `cg_tolerance` (0.005 at the default; the overlap passes then to
/// [`PASS_CG_FACTOR`] of that). E_S at λ = 2 holds the floors two low Suns shadow from both
/// sides 1–2 % better than at 1, but pixels that only E_S and the membrane hold end where the
/// conjugate gradients leave them, which a residual relative to the window sets: 315/20 + 45/20
/// in 128-px tiles against one 512-px tile ended 0.19× the RMSE apart at the default tolerance
/// (seed 3, pixel (90, 336)) and 0.14× at half of it (seed 7, (320, 293)); at this one 0.009×
/// and 0.067×, for ≈ 15 % of a pair's fusion (docs/science.md, "Cast shadows";
/// docs/performance.md). One observation alone has no E_S and keeps the default.
pub const MULTI_CG_FACTOR: f64 = 0.25;

/// The overlap passes solve each Gauss–Newton step's conjugate gradients to this share of the
/// stages' tolerance ([`MULTI_CG_FACTOR`] × `cg_tolerance`, 0.00125 at the default). With the
/// sharper albedo where one observation carries a pixel, a doubly shadowed pit between partly
/// shadowed pixels (315/20 + 45/20, seed 4) ended 0.77 m (0.18× the RMSE) apart in 128-px tiles
/// and one 512-px tile at the stages' tolerance, 0.23 m at this one, at the same cost within
/// the machine's noise (docs/science.md, "The albedo where one observation carries a pixel";
/// measured with the stages at 0.02 and E_S at λ = 1).
pub const PASS_CG_FACTOR: f64 = 0.25;

/// The albedo layer on the final surface `z`: inverted jointly over the observations
/// ([`observations::invert_albedo`]; an observation coarser than the grid with the rendering's
/// shading within its kernel put back, at the last stage's albedo `last_rho`:
/// [`sharpened_images`]) and low-passed at `final_albedo_sigma`, and where observations
/// overlap blended by their multi-coverage `multi` with the same at
/// `multi_final_albedo_sigma`.
fn final_albedo_layer(
    pr: &Problem,
    obj: &Objective,
    params: &FusionParams,
    z: ArrayView2<f64>,
    last_rho: Option<Array2<f64>>,
    multi: Option<&Array2<f64>>,
) -> Result<Array2<f64>, FusionError> {
    let w = &obj.weights;
    let inverted = match last_rho {
        Some(rho) => {
            let images = sharpened_images(pr, z, rho.view());
            drop(rho);
            observations::invert_albedo(&with_images(pr, &images), w, z, blur::FINAL_ALBEDO_WEIGHT)
        }
        None => observations::invert_albedo(pr, w, z, blur::FINAL_ALBEDO_WEIGHT),
    };
    let albedo = final_albedo(&obj.dct, &inverted, params.final_albedo_sigma, params)?;
    Ok(match multi {
        Some(multi) => {
            let fine = final_albedo(&obj.dct, &inverted, params.multi_final_albedo_sigma, params)?;
            blend(&fine, &albedo, multi)
        }
        None => albedo,
    })
}

/// The residual layer, Ī·√(Σ_k w_k r_k²/Σ_k w_k) over the observations used at a pixel (`obs`:
/// each observation's residual r_k = I_k/g_k/Ī − R_k/Ī and where it was used; `weight`: w_k)
/// where the pixel is `covered`, NaN elsewhere; and the count of observations used at each
/// pixel.
fn residual_layers(
    obs: &[(Array2<f32>, Array2<bool>)],
    weight: &[Array2<f32>],
    covered: &Array2<bool>,
    scale: f64,
) -> (Array2<f64>, Array2<u8>) {
    let dim = covered.dim();
    let mut sq = Array2::<f64>::zeros(dim);
    let mut sw = Array2::<f64>::zeros(dim);
    let mut count = Array2::<u8>::zeros(dim);
    for ((res, used), wk) in obs.iter().zip(weight) {
        Zip::from(&mut sq)
            .and(&mut sw)
            .and(&mut count)
            .and(res)
            .and(used)
            .and(wk)
            .for_each(|sq, sw, n, &r, &u, &w| {
                if u {
                    let (r, w) = (f64::from(r), f64::from(w));
                    *sq += w * r * r;
                    *sw += w;
                    *n = n.saturating_add(1);
                }
            });
    }
    // In place of the sums of squares.
    let mut residual = sq;
    Zip::from(&mut residual)
        .and(&sw)
        .and(covered)
        .for_each(|q, &w, &u| {
            *q = if u && w > 0.0 {
                (*q / w).sqrt() * scale
            } else {
                f64::NAN
            }
        });
    (residual, count)
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

pub(crate) fn minimise(
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
    albedo_map(pr, &obj.weights, &obj.dct, pr.dem, sigma)
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
    let mut obj = objective(pr, params)?;
    obj.begin_stage(z.view(), rho, MembraneRule::of(params));
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::photometry::Lambert;

    /// A strip's overlap (c = 1 on columns 0–29 of 80) and one shadowed pixel's hole in it:
    /// the hole, and the strip's own part for the first few pixels past the overlap, count as
    /// next to it (b = 1); from some 3σ on the strip's own part keeps a single image's albedo
    /// (b = 0), and b falls monotonically in between.
    #[test]
    fn the_sharper_albedo_is_taken_only_next_to_the_overlap() {
        let (ny, nx) = (40, 80);
        let mut c = Array2::from_shape_fn((ny, nx), |(_, j)| if j < 30 { 1.0 } else { 0.0 });
        c[[20, 10]] = 0.0;
        let b = near_overlap(&Dct2d::new(ny, nx), &c, 4.0);
        assert!(b[[20, 10]] == 1.0, "the hole: {}", b[[20, 10]]);
        for j in 0..32 {
            assert!(b[[20, j]] == 1.0, "column {j}: {}", b[[20, j]]);
        }
        for j in 44..nx {
            assert!(b[[20, j]] < 1e-3, "column {j}: {}", b[[20, j]]);
        }
        for j in 30..nx - 1 {
            assert!(b[[20, j + 1]] <= b[[20, j]] + 1e-12, "column {j}");
        }
    }

    /// An image that is exactly B R of the surface at the albedo used: sharpened, it is R
    /// itself wherever B R is positive (Lambert, R = ρ μ0 for a Sun 40° from zenith); a sharp
    /// observation is left alone.
    #[test]
    fn a_blurred_image_sharpened_at_the_true_albedo_is_the_rendering() {
        let (ny, nx) = (20, 24);
        let z = Array2::from_shape_fn((ny, nx), |(i, j)| {
            30.0 * ((i as f64 / 4.0).sin() + (j as f64 / 5.0).cos())
        });
        let rho = Array2::from_elem((ny, nx), 0.3);
        let sun = crate::synth::direction(40.0, 120.0);
        let (p, q) = ops::gradient(z.view(), 100.0);
        let r = Array2::from_shape_fn((ny, nx), |ij| {
            let n = [-p[ij], -q[ij], 1.0];
            let len = (n[0] * n[0] + n[1] * n[1] + 1.0).sqrt();
            0.3 * ((n[0] * sun[0] + n[1] * sun[1] + n[2] * sun[2]) / len).max(0.0)
        });
        assert!(r.iter().all(|&v| v > 0.0), "a lit surface");
        let kernel = blur::Kernel::gaussian(1.0).unwrap();
        let image = blur::convolve(&kernel, &r);
        let mut pr = Problem::single(
            image.view(),
            Directions::Uniform(sun),
            Directions::Uniform(crate::synth::direction(0.0, 0.0)),
            z.view(),
            100.0,
            0.0,
            &Lambert,
        );
        pr.observations.push(Observation {
            image: image.view(),
            sun: Directions::Uniform(sun),
            view: Directions::Uniform(crate::synth::direction(0.0, 0.0)),
        });
        pr.blur = Some(vec![0.0, 1.0]);
        let out = sharpened_images(&pr, z.view(), rho.view());
        assert!(out[0].is_none());
        let s = out[1].as_ref().unwrap();
        for (ij, &v) in s.indexed_iter() {
            assert!((v - r[ij]).abs() < 1e-12, "{ij:?}: {v} against {}", r[ij]);
        }
    }
}
