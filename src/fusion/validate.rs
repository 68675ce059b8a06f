//! The checks a fusion makes before it starts: the problem's shapes and per-observation
//! values against its DEM, and every parameter's range ([`validate_params`]), so that a bad
//! value is refused with its name rather than solved into a silently wrong surface.

use super::{shadows, Directions, FusionError, FusionParams, Problem};

/// A problem and its parameters, checked together before a fusion: at least one image, each
/// of the DEM's shape; gains and noise weights, where given, one per observation and positive;
/// a grid of at least 3 × 3 with a positive spacing; a finite DEM; per-pixel Sun and view
/// vectors of the grid's shape; the parameters' own ranges ([`validate_params`]); the DEM's
/// point spread and the incidence limits of the selection.
pub(super) fn validate(pr: &Problem, params: &FusionParams) -> Result<(), FusionError> {
    let dim = pr.dem.dim();
    if pr.observations.is_empty() {
        return Err(FusionError::NoImage);
    }
    if let Some(o) = pr.observations.iter().find(|o| o.image.dim() != dim) {
        return Err(FusionError::Shape {
            image: o.image.dim(),
            dem: dim,
        });
    }
    let k = pr.observations.len();
    for (what, v) in [("gains", &pr.gains), ("noise_weights", &pr.noise_weights)] {
        if let Some(v) = v {
            if v.len() != k {
                return Err(FusionError::PerObservation {
                    what,
                    got: v.len(),
                    want: k,
                });
            }
            if let Some(&x) = v.iter().find(|x| !(x.is_finite() && **x > 0.0)) {
                return Err(FusionError::Parameter {
                    name: what,
                    value: x,
                    why: "must be positive",
                });
            }
        }
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
    for d in pr.observations.iter().flat_map(|o| [&o.sun, &o.view]) {
        if let Directions::PerPixel(a) = d {
            if a.dim() != dim {
                return Err(FusionError::DirectionShape {
                    got: a.dim(),
                    want: dim,
                });
            }
        }
    }
    validate_params(params)?;
    let sel = &pr.selection;
    let checks: [Check; 3] = [
        (
            "dem_psf_sigma",
            pr.dem_psf_sigma,
            pr.dem_psf_sigma >= 0.0,
            "must be ≥ 0",
        ),
        (
            "min_incidence_deg",
            sel.min_incidence_deg,
            (0.0..90.0).contains(&sel.min_incidence_deg),
            "must be in [0, 90)",
        ),
        (
            "max_incidence_deg",
            sel.max_incidence_deg,
            sel.max_incidence_deg > sel.min_incidence_deg && sel.max_incidence_deg <= 90.0,
            "must be above min_incidence_deg and at most 90",
        ),
    ];
    check_all(checks)
}

/// One range check: the key, its value, whether it is in range, and what the range is.
type Check = (&'static str, f64, bool, &'static str);

/// Every check's value must be finite and pass.
fn check_all<const N: usize>(checks: [Check; N]) -> Result<(), FusionError> {
    for (name, value, ok, why) in checks {
        if !ok || !value.is_finite() {
            return Err(FusionError::Parameter { name, value, why });
        }
    }
    Ok(())
}

/// The ranges of [`FusionParams`] on their own (without a problem): a workflow's `[solver]`
/// is checked with this when it is loaded, so that a bad value is refused before any input is
/// read; [`super::fuse`] checks it again with the problem.
pub fn validate_params(params: &FusionParams) -> Result<(), FusionError> {
    check_counts(params)?;
    check_all(solver_controls(params))?;
    check_all(dem_and_membrane(params))?;
    check_all(several_observations(params))?;
    check_all(cast_shadows(params))?;
    check_stages(params)
}

/// E_S, the cast shadows' term ([`super::shadows`]).
fn cast_shadows(params: &FusionParams) -> [Check; 6] {
    [
        (
            "shadow_weight",
            params.shadow_weight,
            params.shadow_weight >= 0.0,
            "must be ≥ 0 (0: off)",
        ),
        (
            "shadow_tolerance_px",
            params.shadow_tolerance_px,
            params.shadow_tolerance_px >= 0.0,
            "must be ≥ 0 pixels of shadow length",
        ),
        (
            "shadow_weight_all",
            params.shadow_weight_all,
            (0.0..=1.0).contains(&params.shadow_weight_all),
            "must be in [0, 1]",
        ),
        (
            "shadow_weight_alone",
            params.shadow_weight_alone,
            (0.0..=1.0).contains(&params.shadow_weight_alone),
            "must be in [0, 1]",
        ),
        (
            "shadow_lit_threshold",
            params.shadow_lit_threshold,
            params.shadow_lit_threshold > params.shadow_threshold,
            "must be above shadow_threshold: a pixel cannot be both shadowed and lit",
        ),
        (
            "shadow_reach_px",
            params.shadow_reach_px as f64,
            (1..=shadows::MAX_REACH_PX).contains(&params.shadow_reach_px),
            "must be in [1, 4096] pixels",
        ),
    ]
}

/// The iteration counts: each must be at least 1.
fn check_counts(params: &FusionParams) -> Result<(), FusionError> {
    let never = "must be at least 1: with 0 the surface is never solved for";
    let counts = [
        ("max_iterations", params.max_iterations, never),
        ("cg_iterations", params.cg_iterations, never),
        (
            "multi_albedo_passes",
            params.multi_albedo_passes,
            "must be at least 1: with 0 the surface is never solved at the last albedo width where observations overlap",
        ),
    ];
    for (name, n, why) in counts {
        if n == 0 {
            return Err(FusionError::Parameter {
                name,
                value: 0.0,
                why,
            });
        }
    }
    Ok(())
}

/// δ and η not both 0, and at least one albedo stage, every σ_ρ ≥ 0.
fn check_stages(params: &FusionParams) -> Result<(), FusionError> {
    if params.delta == 0.0 && params.eta == 0.0 {
        return Err(FusionError::Parameter {
            name: "delta",
            value: 0.0,
            why: "delta and eta cannot both be 0: nothing would fix relief across the Sun",
        });
    }
    if params.albedo_sigmas.is_empty() {
        return Err(FusionError::NoAlbedoStages);
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

/// The solver's controls: step sizes, tolerances and the curvature rule.
fn solver_controls(params: &FusionParams) -> [Check; 5] {
    [
        ("gamma", params.gamma, params.gamma > 0.0, "must be > 0"),
        (
            "tolerance",
            params.tolerance,
            params.tolerance >= 0.0,
            "must be ≥ 0 (a relative energy decrease)",
        ),
        (
            "cg_tolerance",
            params.cg_tolerance,
            params.cg_tolerance > 0.0 && params.cg_tolerance < 1.0,
            "must be in (0, 1) (a relative residual)",
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
    ]
}

/// E_DEM, the membrane, the albedo's last width and the shadow test.
fn dem_and_membrane(params: &FusionParams) -> [Check; 9] {
    [
        ("delta", params.delta, params.delta >= 0.0, "must be ≥ 0"),
        ("eta", params.eta, params.eta >= 0.0, "must be ≥ 0"),
        (
            "sigma_dem",
            params.sigma_dem,
            params.sigma_dem >= 0.0,
            "must be ≥ 0",
        ),
        (
            "dem_height_length_px",
            params.dem_height_length_px,
            params.dem_height_length_px >= 0.0,
            "must be ≥ 0 (pixels; 0: the DEM term measures gradients only)",
        ),
        (
            "dem_track_weight",
            params.dem_track_weight,
            (0.0..=1.0).contains(&params.dem_track_weight),
            "must be in [0, 1] (1: the DEM term without track weighting)",
        ),
        (
            "dem_track_sigma_px",
            params.dem_track_sigma_px,
            params.dem_track_sigma_px >= 0.0,
            "must be ≥ 0 (pixels along the columns)",
        ),
        (
            "edge_membrane_slope",
            params.edge_membrane_slope,
            params.edge_membrane_slope >= 0.0,
            "must be ≥ 0 (a slope; 0 keeps the plain membrane)",
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
    ]
}

/// What acts only where several observations overlap.
fn several_observations(params: &FusionParams) -> [Check; 17] {
    [
        (
            "multi_delta_factor",
            params.multi_delta_factor,
            params.multi_delta_factor > 0.0 && params.multi_delta_factor <= 1.0,
            "must be in (0, 1]",
        ),
        (
            "multi_delta_factor_all",
            params.multi_delta_factor_all,
            params.multi_delta_factor_all > 0.0
                && params.multi_delta_factor_all <= params.multi_delta_factor,
            "must be in (0, multi_delta_factor]",
        ),
        (
            "multi_delta_factor_high_sun",
            params.multi_delta_factor_high_sun,
            params.multi_delta_factor_high_sun > 0.0
                && params.multi_delta_factor_high_sun <= params.multi_delta_factor,
            "must be in (0, multi_delta_factor]",
        ),
        (
            "multi_delta_factor_high_sun_east_west",
            params.multi_delta_factor_high_sun_east_west,
            params.multi_delta_factor_high_sun_east_west > 0.0
                && params.multi_delta_factor_high_sun_east_west <= 1.0,
            "must be in (0, 1] (at or above multi_delta_factor_high_sun the rule is off)",
        ),
        (
            "multi_delta_factor_east_west",
            params.multi_delta_factor_east_west,
            params.multi_delta_factor_east_west > 0.0 && params.multi_delta_factor_east_west <= 1.0,
            "must be in (0, 1] (at or above multi_delta_factor the rule is off)",
        ),
        (
            "multi_albedo_sigma",
            params.multi_albedo_sigma,
            params.multi_albedo_sigma >= 0.0,
            "must be ≥ 0 pixels",
        ),
        (
            "multi_albedo_sigma_single",
            params.multi_albedo_sigma_single,
            params.multi_albedo_sigma_single >= 0.0,
            "must be ≥ 0 pixels",
        ),
        (
            "multi_albedo_coupling",
            params.multi_albedo_coupling,
            (0.0..=1.0).contains(&params.multi_albedo_coupling),
            "must be in [0, 1] (0: the plain alternation; above 1 the Newton systems would lose their positive definiteness)",
        ),
        (
            "multi_final_albedo_sigma",
            params.multi_final_albedo_sigma,
            params.multi_final_albedo_sigma >= 0.0,
            "must be ≥ 0 pixels",
        ),
        (
            "multi_eta_factor",
            params.multi_eta_factor,
            params.multi_eta_factor >= 0.0,
            "must be ≥ 0",
        ),
        (
            "multi_edge_membrane_slope",
            params.multi_edge_membrane_slope,
            params.multi_edge_membrane_slope >= 0.0,
            "must be ≥ 0 (a slope; 0 keeps the plain membrane where observations overlap)",
        ),
        (
            "multi_eta_stiffness",
            params.multi_eta_stiffness,
            params.multi_eta_stiffness >= 0.0,
            "must be ≥ 0 (0: off)",
        ),
        (
            "multi_shadow_coverage",
            params.multi_shadow_coverage,
            (0.0..=1.0).contains(&params.multi_shadow_coverage),
            "must be in [0, 1] (0: off)",
        ),
        (
            "edge_ramp_px",
            params.edge_ramp_px,
            params.edge_ramp_px >= 0.0,
            "must be ≥ 0 pixels",
        ),
        (
            "shadow_edge_weight",
            params.shadow_edge_weight,
            params.shadow_edge_weight > 0.0 && params.shadow_edge_weight <= 1.0,
            "must be in (0, 1]",
        ),
        (
            "shadow_edge_weight_all",
            params.shadow_edge_weight_all,
            params.shadow_edge_weight_all > 0.0 && params.shadow_edge_weight_all <= 1.0,
            "must be in (0, 1]",
        ),
        (
            "nyquist_shrink",
            params.nyquist_shrink,
            (0.0..=1.0).contains(&params.nyquist_shrink),
            "must be in [0, 1] (0: off; 1 removes the Nyquist wave)",
        ),
    ]
}
