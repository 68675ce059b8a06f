//! Step 1, the plan (`plan.json`): grid, tiles, swath index, the run-wide intensity scale,
//! the observations' gains and noise weights, and the DEM's widths.

use super::*;
use ndarray::ArrayView2;

/// The plan of an orbital run (see the module documentation).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Plan {
    pub version: String,
    pub key: String,
    pub grid: Grid,
    pub halo: usize,
    /// Blend half-width, pixels ([`tiling::weight`]).
    pub blend: usize,
    pub tiles: Vec<Tile>,
    /// Ī: mean valid reflectance on the grid (each observation's divided by its gain), sr⁻¹.
    pub intensity_scale: f64,
    /// Swath pixels behind Ī.
    pub intensity_pixels: usize,
    /// σ of the input DEM's point spread on the grid, pixels.
    pub dem_psf_sigma: f64,
    /// Where the grid spacing came from (`[grid] resolution_m` or the observation's ground
    /// sample distance).
    pub resolution_source: String,
    /// The first DEM's effective resolution, metres, and where it came from.
    pub dem_resolution_m: f64,
    pub dem_resolution_source: String,
    /// σ_DEM the tiles solve with, pixels (`[solver] sigma_dem`, or from the DEM's effective
    /// resolution).
    pub sigma_dem: f64,
    /// E_DEM's track weighting a the tiles solve with, and why (`pipeline::plan::track_weight`).
    #[serde(default = "one")]
    pub dem_track_weight: f64,
    #[serde(default)]
    pub dem_track_source: String,
    /// `multi_delta_factor_high_sun_east_west` the tiles solve with, and why
    /// (`pipeline::plan::high_sun_east_west`).
    #[serde(default = "one")]
    pub high_sun_east_west: f64,
    #[serde(default)]
    pub high_sun_east_west_source: String,
    /// The membrane where one observation carries a pixel, as the tiles apply it
    /// ([`fusion::coarse_dem_membrane`] from σ_B, or the workflow's own).
    #[serde(default)]
    pub membrane: String,
    /// One per M3 observation, in input order.
    pub swaths: Vec<SwathIndex>,
    /// Radiometric gain g_k of each observation, relative to the first of its overlapping
    /// group (1 where it overlaps no other).
    #[serde(default)]
    pub gains: Vec<f64>,
    /// What each gain is relative to, by input index
    /// ([`fusion::gains::GainEstimate::relative_to`]; `None`: nothing tied it down, or
    /// the observation does not reach the grid).
    #[serde(default)]
    pub gain_reference: Vec<Option<usize>>,
    /// Each observation's gain trend along its track (`[inputs] gain_trend`; `None`: none, the
    /// default), in input order.
    #[serde(default)]
    pub gain_trends: Vec<Option<GainTrend>>,
    /// Noise weight ν_k of each observation (docs/science.md, "Several observations").
    #[serde(default)]
    pub noise_weights: Vec<f64>,
    /// The coarse reference the tiles start from and anchor to (`reference.bin`); `None`: the
    /// tiles solve every stage themselves (`pipeline::reference`).
    #[serde(default)]
    pub reference: Option<ReferenceInfo>,
    /// Each observation's registration, in input order (`pipeline::register`).
    #[serde(default)]
    pub registration: Vec<Registration>,
    /// Each observation's pixel size, metres ([`ingest::ground_sample_distance`]; `None` where
    /// LOC gives none), in input order.
    #[serde(default)]
    pub pixel_size_m: Vec<Option<f64>>,
    /// Each observation's mean Sun over its usable pixels on the grid, [azimuth clockwise from
    /// north, elevation], degrees ([`ingest::Survey::mean_sun`]; `None` without any), in
    /// input order.
    #[serde(default)]
    pub sun_deg: Vec<Option<[f64; 2]>>,
    /// Each observation's lowest and highest Sun over its usable pixels on the grid,
    /// [elevation, elevation] in degrees ([`ingest::Survey::sun_elevation_range`]; `None`
    /// without any), in input order.
    #[serde(default)]
    pub sun_elevation_range_deg: Vec<Option<[f64; 2]>>,
    /// Each observation's swath pixels on the grid, usable or not (dark, refused), in input
    /// order: an observation with some reaches the region, whether or not any is used.
    #[serde(default)]
    pub on_grid_pixels: Vec<usize>,
    /// Each observation's OBS Sun against the ephemeris at its label's times
    /// ([`ingest::SunCheck`]; `None`: the label gives no START_TIME), in input order.
    #[serde(default)]
    pub sun_ephemeris: Vec<Option<ingest::SunCheck>>,
    /// Each observation's LOC heights against the DEM ([`ingest::DemVsLoc`]; `None`: no
    /// sampled pixel where both are defined), in input order.
    #[serde(default)]
    pub dem_vs_loc: Vec<Option<ingest::DemVsLoc>>,
    /// Each observation's detector column gain estimate ([`crate::striping::Striping`];
    /// `None`: the swath is too short to measure), in input order. The gains themselves are in
    /// `swaths` when `[inputs] destripe` applies them.
    #[serde(default)]
    pub striping: Vec<Option<crate::striping::Striping>>,
    /// Each DEM product's offsets between its tracks over the region, in `[inputs] lola` order
    /// ([`ingest::lola_track_offsets`]; `None`: not estimated). Taken out of the heights
    /// wherever the run reads the DEM when `[inputs] dem_destripe` is on.
    #[serde(default)]
    pub dem_tracks: Vec<Option<ingest::TrackOffsets>>,
}

/// σ_k, grid pixels, of each observation's blur on a grid of `spacing` metres, from its pixel
/// size (`fusion::blur::sigma_px`; 0 where its pixels are no coarser than the grid's or LOC
/// gives no size): E_I compares such an observation with the reflectance averaged over its
/// pixel (docs/science.md, "Images coarser than the grid").
pub fn blur_px(pixel_size_m: &[Option<f64>], spacing: f64) -> Vec<f64> {
    pixel_size_m
        .iter()
        .map(|p| p.map_or(0.0, |p| fusion::blur::sigma_px(p, spacing)))
        .collect()
}

impl Plan {
    /// `blur_px` of the plan's observations on its grid.
    pub fn blur_px(&self) -> Vec<f64> {
        blur_px(&self.pixel_size_m, self.grid.spacing)
    }
}

impl Plan {
    /// The workflow's solver parameters with what the plan decided from the DEM and the
    /// images: σ_DEM, the track weighting and the high-Sun factor where the images measure
    /// east–west slopes (the tiles solve with these, and the products' metadata lists them).
    pub(super) fn solver(&self, workflow: &FusionParams) -> FusionParams {
        FusionParams {
            sigma_dem: self.sigma_dem,
            dem_track_weight: self.dem_track_weight,
            multi_delta_factor_high_sun_east_west: self.high_sun_east_west,
            ..workflow.clone()
        }
    }
}

/// The serde default of [`Plan::dem_track_weight`] (the plain term) and of
/// [`Plan::high_sun_east_west`] (the rule off) in a plan written before them.
fn one() -> f64 {
    1.0
}

/// [`FusionParams::multi_delta_factor_high_sun_east_west`] for a run, and why: the workflow's
/// when given; otherwise `default` only where every observation's detector columns were
/// estimated over at least [`crate::striping::MIN_BLOCKS`] blocks and none shows striping
/// (`stripe_rms` = 0: the estimate's test finds nothing that stands out of the terrain);
/// else `off` (`multi_delta_factor_high_sun`: the rule off). The lower δ takes the DEM's track
/// offsets out where the images measure east–west slopes, and lets through whatever of an
/// image's column striping its correction leaves, east–west slopes too (1 % striping, 512²,
/// 110/55 + 250/60: 5.66 → 5.99 m at 0.02; docs/science.md, "Several observations").
pub fn high_sun_east_west(
    given: Option<f64>,
    default: f64,
    off: f64,
    striping: &[Option<crate::striping::Striping>],
) -> (f64, String) {
    if let Some(f) = given {
        return (f, "[solver] multi_delta_factor_high_sun_east_west".into());
    }
    let unclear = striping.iter().enumerate().find_map(|(k, s)| match s {
        None => Some(format!("observation {} has no column estimate", k + 1)),
        Some(s) if s.blocks < crate::striping::MIN_BLOCKS => Some(format!(
            "observation {} was estimated over {} blocks only",
            k + 1,
            s.blocks
        )),
        Some(s) if s.stripe_rms > 0.0 => Some(format!(
            "observation {} shows detector column striping ({:.2} % RMS)",
            k + 1,
            100.0 * s.stripe_rms
        )),
        Some(_) => None,
    });
    match unclear {
        Some(why) => (off, format!("{why}: the rule is off")),
        None => (
            default,
            "no observation shows detector column striping".into(),
        ),
    }
}

/// How far grid north may turn from the columns over the region for E_DEM's track weighting to
/// apply by default, degrees: over the weighting's 10 px along a column a track then drifts by
/// under 0.9 px.
pub const MAX_TRACK_TURN_DEG: f64 = 5.0;

/// The largest angle between true north and the grid's columns over the region, degrees,
/// from [`crate::grid::Projector::north_bearing`] at its corners, edge midpoints and centre
/// (points the projection cannot invert are skipped).
pub(super) fn north_turn_deg(grid: &Grid, pr: &crate::grid::Projector) -> f64 {
    let (w, h) = (
        grid.cols as f64 * grid.spacing,
        grid.rows as f64 * grid.spacing,
    );
    let mut turn: f64 = 0.0;
    for fy in [0.0, 0.5, 1.0] {
        for fx in [0.0, 0.5, 1.0] {
            let (x, y) = (grid.x0 + fx * w, grid.y0 - fy * h);
            if let Some(b) = pr
                .inverse(x, y)
                .and_then(|(lon, lat)| pr.north_bearing(lon, lat))
            {
                turn = turn.max(b.to_degrees().abs());
            }
        }
    }
    turn
}

/// What the membrane is, for the plan's note and the run record: where one observation
/// carries a pixel, the edge-aware membrane of [`fusion::coarse_dem_membrane`] when the DEM's
/// point spread `dem_psf_sigma` calls for it, else the workflow's η and k; with several
/// observations, also their own (docs/science.md, "Several observations").
fn membrane_note(params: &FusionParams, dem_psf_sigma: f64, observations: usize) -> String {
    let eff = fusion::coarse_dem_membrane(params, dem_psf_sigma);
    let single = membrane_single(params, &eff, dem_psf_sigma);
    if observations < 2 {
        return single;
    }
    format!(
        "{single}; where several observations carry a pixel: η·{:.3} × min(1, √(S/{})), edge-aware with k_m {}",
        eff.eta * eff.multi_eta_factor,
        eff.multi_eta_stiffness,
        eff.multi_edge_membrane_slope
    )
}

/// [`membrane_note`]'s part for the pixels one observation carries.
fn membrane_single(params: &FusionParams, eff: &FusionParams, dem_psf_sigma: f64) -> String {
    if eff.eta != params.eta {
        format!(
            "edge-aware for a DEM {:.1}× coarser than the grid (fusion::coarse_dem_membrane): η {:.3}, k {:.4}",
            dem_psf_sigma * std::f64::consts::SQRT_2,
            eff.eta,
            eff.edge_membrane_slope
        )
    } else if params.edge_membrane_slope > 0.0 {
        format!(
            "edge-aware as the workflow sets it: η {}, k {}",
            params.eta, params.edge_membrane_slope
        )
    } else {
        format!("plain, η {}", params.eta)
    }
}

/// E_DEM's track weighting for a run ([`FusionParams::dem_track_weight`]) and why: the
/// workflow's when given; otherwise `default` only where the DEM is a gridded LOLA product
/// whose pixels resolve its near-polar tracks (`tracks`: each track a strip of pixels, its
/// offset a stripe, which the weighting is for) and grid north stays within
/// [`MAX_TRACK_TURN_DEG`] of the columns over the region
/// (`turn_deg`, [`north_turn_deg`]; near a pole, or on a grid centred far away in longitude,
/// the tracks cross the columns); else 1, the plain term.
pub fn track_weight(
    given: Option<f64>,
    default: f64,
    tracks: bool,
    turn_deg: f64,
) -> (f64, String) {
    if let Some(w) = given {
        return (w, "[solver] dem_track_weight".into());
    }
    if !tracks {
        return (
            1.0,
            "the DEM is not a gridded LOLA product (LDEM) with pixels narrower east–west than the gap between its tracks: no track offsets weighed".into(),
        );
    }
    if turn_deg > MAX_TRACK_TURN_DEG {
        return (
            1.0,
            format!(
                "grid north turns up to {turn_deg:.1}° from the columns over the region (more than {MAX_TRACK_TURN_DEG}°): LOLA's tracks do not run along them"
            ),
        );
    }
    (
        default,
        format!("LOLA grid resolving its tracks, north within {turn_deg:.2}° of the columns"),
    )
}

/// [`track_weight`]'s choice as the fusion applies it ([`fusion::track_weight`]): the plain term
/// (1) where the DEM's point spread σ_B is as wide as the along-track length σ_t, whatever was
/// chosen, with the reason.
pub fn dem_blur_track_weight(
    (weight, why): (f64, String),
    dem_psf_sigma: f64,
    track_sigma: f64,
) -> (f64, String) {
    let effective = fusion::track_weight(weight, dem_psf_sigma, track_sigma);
    if effective == weight {
        return (weight, why);
    }
    (
        effective,
        format!(
            "the DEM's point spread ({dem_psf_sigma:.1} px) is as wide as dem_track_sigma_px ({track_sigma:.1} px): it holds no structure finer along the tracks than across them (chosen: {weight} from {why})"
        ),
    )
}

/// The most pixels the gain estimate looks at: the run's grid is decimated to at most this.
pub(super) const GAIN_PIXELS: usize = 1 << 20;

/// The gains of [`run_gains`], per observation in input order.
pub(super) struct RunGains {
    pub(super) gains: Vec<f64>,
    /// What each gain is relative to, by input index (`None`: nothing tied it down).
    pub(super) reference: Vec<Option<usize>>,
    pub(super) trends: Vec<Option<GainTrend>>,
}

impl RunGains {
    /// A single observation's: gain 1, its own reference, no trend.
    fn one() -> Self {
        RunGains {
            gains: vec![1.0],
            reference: vec![Some(0)],
            trends: vec![None],
        }
    }
}

/// The gains of the observations, estimated once for the whole run (tiles must agree on them)
/// by [`fusion::gains::estimate_gains`] on the grid decimated to at most
/// [`GAIN_PIXELS`], over the input DEM, what each is relative to (input indices), and with
/// `[inputs] gain_trend` their trends along the track
/// ([`fusion::gains::estimate_gain_trends`]; the gains are then estimated again on the
/// images divided by the trends).
pub(super) fn run_gains(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    swaths: (&[SwathIndex], &[Displacement]),
    scale: f64,
) -> Result<RunGains> {
    let n_obs = inputs.obs.len();
    let coarse = gain_grid(grid);
    let pr = projector(&coarse.crs)?;
    let geo = coarse.geographic(&pr);
    let placing = Placing {
        swaths: swaths.0,
        shifts: swaths.1,
        trends: &[],
    };
    let with_lines = o.inputs.gain_trend;
    let mut shots = observations_with_lines(
        o,
        inputs,
        placing,
        &coarse,
        (&pr, geo.bearing.view()),
        with_lines,
    )?;
    let mut dem = dem_on(o, inputs, &geo)?;
    fill_holes(&mut dem);
    let mut gains = vec![1.0; n_obs];
    let mut trends = vec![None; n_obs];
    if !dem.iter().all(|v| v.is_finite()) {
        // No DEM on the grid at all: the tiles will say so; gains cannot be estimated.
        return Ok(RunGains {
            gains,
            reference: vec![None; n_obs],
            trends,
        });
    }
    // Input indices: `shots` holds the observations that reach the grid, in input order.
    let mut reference = vec![None; n_obs];
    if let [(k, _, _)] = shots[..] {
        reference[k] = Some(k);
    }
    if shots.len() < 2 {
        return Ok(RunGains {
            gains,
            reference,
            trends,
        });
    }
    // The gains (and, asked for, the trends) on `shots` as they are.
    let estimate = |shots: &[Shot], trend: bool| {
        gains_on(o, inputs, shots, dem.view(), coarse.spacing, scale, trend)
    };
    let (mut g, t) = estimate(&shots, with_lines);
    if t.iter().any(Option::is_some) {
        // The images divided by their trends, and the gains estimated again on them.
        for ((_, img, lines), t) in shots.iter_mut().zip(&t) {
            if let (Some(t), Some(lines)) = (t, lines) {
                Zip::from(&mut img.reflectance)
                    .and(&*lines)
                    .for_each(|r, &l| *r /= t.factor(f64::from(l)));
            }
        }
        g = estimate(&shots, false).0;
    }
    for ((((k, _, _), g), r), t) in shots.iter().zip(g.gains).zip(g.relative_to).zip(t) {
        gains[*k] = g;
        reference[*k] = r.map(|r| shots[r].0);
        trends[*k] = t;
    }
    Ok(RunGains {
        gains,
        reference,
        trends,
    })
}

/// The grid the gains are estimated on: `grid` decimated by the smallest whole factor that
/// leaves at most [`GAIN_PIXELS`] pixels.
fn gain_grid(grid: &Grid) -> Grid {
    let f = ((grid.rows * grid.cols) as f64 / GAIN_PIXELS as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    Grid {
        rows: grid.rows.div_ceil(f),
        cols: grid.cols.div_ceil(f),
        spacing: grid.spacing * f as f64,
        ..*grid
    }
}

/// The observations' gains over `dem` ([`fusion::gains::estimate_gains`], on their usable
/// pixels at unit gains and Ī = `scale`) and, where `trend`, their trends along the track
/// ([`fusion::gains::estimate_gain_trends`]; `shots` then carry their swath lines).
fn gains_on(
    o: &Orbital,
    inputs: &Inputs,
    shots: &[Shot],
    dem: ArrayView2<f64>,
    spacing: f64,
    scale: f64,
    trend: bool,
) -> (fusion::gains::GainEstimate, Vec<Option<GainTrend>>) {
    let problem = Problem {
        observations: shots.iter().map(|(_, img, _)| fusion_view(img)).collect(),
        dem,
        spacing,
        dem_psf_sigma: 0.0,
        model: inputs.model.as_ref(),
        intensity_scale: Some(scale),
        gains: None,
        noise_weights: None,
        blur: None,
        selection: o.inputs.selection(),
    };
    let w = fusion::observations::weights(
        &problem,
        vec![1.0; problem.observations.len()],
        scale,
        None,
        o.solver.shadow_threshold,
        0.0,
        (1.0, 1.0),
    );
    let g = fusion::gains::estimate_gains(&problem, &w.usable, dem);
    let t = if trend {
        let lines: Vec<ArrayView2<f32>> = shots
            .iter()
            .map(|(_, _, l)| l.as_ref().expect("ingested with lines").view())
            .collect();
        fusion::gains::estimate_gain_trends(
            &problem,
            &w.usable,
            dem,
            (&g.gains, &g.relative_to),
            &lines,
        )
    } else {
        vec![None; shots.len()]
    };
    (g, t)
}

/// The grid spacing of an orbital workflow and where it came from.
pub(super) fn resolution(o: &Orbital, inputs: &Inputs) -> Result<(f64, String)> {
    if let Some(r) = o.grid.resolution_m {
        return Ok((r, "[grid] resolution_m".into()));
    }
    let obs = &inputs.obs[0];
    let gsd = ingest::ground_sample_distance(obs)?;
    // Whole decimetres: a tidy grid that does not move with the last digits of LOC.
    let res = (gsd * 10.0).round() / 10.0;
    Ok((
        res,
        format!(
            "ground sample distance of {} (LOC), {gsd:.2} m",
            obs.label_path.display()
        ),
    ))
}

/// The grid of an orbital workflow with spacing `res`: the `[region]` given, or without one
/// the whole swath of the first observation.
pub(super) fn make_grid(o: &Orbital, inputs: &Inputs, res: f64) -> Result<Grid> {
    match o.region.map(|r| r.kind()).transpose()? {
        Some(RegionKind::LonLat(b)) => {
            let (lon, lat) = b.centre();
            Grid::covering(o.grid.crs((lat, lon)), &b, res).map_err(grid_usage)
        }
        Some(RegionKind::Map(bounds)) => map_grid(o, bounds, res),
        None => swath_grid(o, inputs, res),
    }
}

/// A grid or projection error as a usage error of the workflow's `[grid]`/`[region]`.
fn grid_usage(e: crate::grid::GridError) -> Error {
    Error::Usage(format!("[grid]/[region]: {e}"))
}

/// The grid over map bounds `[x0, x1, y0, y1]` (metres in the `[grid]` projection), widened to
/// whole pixels of `res`; refused when it holds more than one run can.
fn map_grid(o: &Orbital, [x0, x1, y0, y1]: [f64; 4], res: f64) -> Result<Grid> {
    let crs = o.grid.crs((
        o.grid.center_lat.unwrap_or(0.0),
        o.grid.center_lon.unwrap_or(0.0),
    ));
    let (c0, c1) = ((x0 / res).floor(), (x1 / res).ceil());
    let (r0, r1) = ((y0 / res).floor(), (y1 / res).ceil());
    if (c1 - c0) * (r1 - r0) > crate::grid::MAX_PIXELS as f64 {
        return Err(Error::Usage(format!("[region]: {} × {} pixels at {res} m is more than one run can hold ({}); use a coarser resolution or a smaller region", r1 - r0, c1 - c0, crate::grid::MAX_PIXELS)));
    }
    Grid::new(
        crs,
        (r1 - r0) as usize,
        (c1 - c0) as usize,
        c0 * res,
        r1 * res,
        res,
    )
    .map_err(grid_usage)
}

/// The grid over the whole swath of the first observation (its LOC backplane's valid
/// longitudes and latitudes), centred on it.
fn swath_grid(o: &Orbital, inputs: &Inputs, res: f64) -> Result<Grid> {
    let obs = &inputs.obs[0];
    let loc = obs.part("LOC")?;
    let (lon, lat) = (
        loc.read_band(0, 0, loc.lines)?,
        loc.read_band(1, 0, loc.lines)?,
    );
    let fin: Vec<(f64, f64)> = lon
        .iter()
        .zip(&lat)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .map(|(&a, &b)| (a, b))
        .collect();
    if fin.is_empty() {
        return Err(Error::Usage(format!(
            "{}: LOC has no valid longitude/latitude",
            obs.label_path.display()
        )));
    }
    let (lo0, lo1) = longitude_span(&fin);
    let (la0, la1) = fin
        .iter()
        .fold((f64::MAX, f64::MIN), |m, p| (m.0.min(p.1), m.1.max(p.1)));
    let centre = (0.5 * (la0 + la1), 0.5 * (lo0 + lo1));
    let crs = o.grid.crs(centre);
    let pr = crs.projector().map_err(grid_usage)?;
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(a, b) in &fin {
        if let Some((x, y)) = pr.forward(a, b) {
            (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
        }
    }
    let (c0, c1) = ((x0 / res).floor(), (x1 / res).ceil());
    let (r0, r1) = ((y0 / res).floor(), (y1 / res).ceil());
    Grid::new(
        crs,
        (r1 - r0).max(1.0) as usize,
        (c1 - c0).max(1.0) as usize,
        c0 * res,
        r1 * res,
        res,
    )
    .map_err(grid_usage)
}

/// The smallest longitude range (degrees, west to east) holding every (lon, lat) point: of
/// the ranges in [0, 360) and in [−180, 180), the narrower, so that a swath across the 0°
/// or the 180° meridian stays together.
fn longitude_span(points: &[(f64, f64)]) -> (f64, f64) {
    let spread = |shift: f64| {
        let v = points.iter().map(|p| (p.0 + shift).rem_euclid(360.0));
        let (a, b) = v.fold((f64::MAX, f64::MIN), |m, x| (m.0.min(x), m.1.max(x)));
        (a - shift, b - shift)
    };
    let (a0, b0) = spread(0.0);
    let (a1, b1) = spread(180.0);
    if b0 - a0 <= b1 - a1 {
        (a0, b0)
    } else {
        (a1, b1)
    }
}

/// Make the plan, or load it when one with the same key exists (and its reference file, when
/// it has one, matches its checksum); with the plan, the reference's values, and when the
/// plan was made now and has a single tile over the whole grid, the full-resolution inputs
/// the reference ingested (the tile's, [`super::reference::build`]).
pub(super) fn plan(
    o: &Orbital,
    wf: &Workflow,
    inputs: &Inputs,
    progress: &Progress,
) -> Result<(Plan, Option<Array2<f64>>, Option<Ingested>)> {
    let out = &o.output.directory;
    let key = plan_key(wf, &inputs.files()?)?;
    let path = out.join("plan.json");
    if let Some((p, reference)) = existing(out, &key, progress) {
        if o.inputs.dem_destripe {
            inputs.set_dem_tracks(&p.dem_tracks);
        }
        return Ok((p, reference, None));
    }
    progress.stage("planning: grid, swath index, intensity scale");
    let (res, resolution_source) = resolution(o, inputs)?;
    let grid = make_grid(o, inputs, res)?;
    at_least_three_pixels(&grid)?;
    within_half_moon(&grid)?;
    let pr = projector(&grid.crs)?;
    // Before anything reads the DEM: every read takes the offsets out.
    let dem_tracks = dem_track_offsets(inputs, &grid, &pr)?;
    if o.inputs.dem_destripe {
        inputs.set_dem_tracks(&dem_tracks);
    }
    let Surveyed {
        swaths,
        sum,
        count,
        means,
        sums,
        sun_deg,
        sun_elevation_range_deg,
        on_grid_pixels,
        sun_ephemeris,
        dem_vs_loc,
        striping,
    } = survey_all(o, inputs, &grid, &pr)?;
    incidence_window_admits(
        &o.inputs.selection(),
        &inputs.labels(),
        &sun_elevation_range_deg,
    )?;
    let mut dem = dem_terms(o, inputs, &grid, &pr);
    let (high_sun_ew, high_sun_ew_source) = high_sun_east_west(
        o.high_sun_east_west_given
            .then_some(o.solver.multi_delta_factor_high_sun_east_west),
        o.solver.multi_delta_factor_high_sun_east_west,
        o.solver.multi_delta_factor_high_sun,
        &striping,
    );
    dem.params.multi_delta_factor_high_sun_east_west = high_sun_ew;
    let (params, dem_psf_sigma) = (&dem.params, dem.dem_psf_sigma);
    let membrane = membrane_note(params, dem_psf_sigma, inputs.obs.len());
    let reference_factor = super::reference::factor(&grid, params);
    let halo = o.tiling.halo.unwrap_or_else(|| {
        crate::workflow::auto_halo(
            params,
            dem_psf_sigma,
            reference_factor.is_some(),
            inputs.obs.len() > 1,
        )
    });
    let tiles = layout_tiles(o, &grid, halo)?;
    let blend = o.tiling.blend.unwrap_or(halo / 4).min(halo);
    let intensity_scale = sum / count as f64;
    progress.stage("planning: registration of the observations");
    let registration = register(
        o,
        inputs,
        &grid,
        &swaths,
        dem_psf_sigma,
        params,
        (intensity_scale, &sun_deg),
    )?;
    let shifts = shifts(&registration);
    let Radiometry {
        gains:
            RunGains {
                gains,
                reference: gain_reference,
                trends: gain_trends,
            },
        intensity_scale,
        noise_weights,
    } = radiometry(
        o,
        inputs,
        &grid,
        (&swaths, &shifts),
        (intensity_scale, &sums, &means, count),
        progress,
    )?;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    let pixel_size_m: Vec<Option<f64>> = inputs
        .obs
        .iter()
        .map(|obs| ingest::ground_sample_distance(obs).ok())
        .collect();
    let blur = blur_px(&pixel_size_m, grid.spacing);
    let built = match reference_factor {
        Some(f) => {
            progress.stage("planning: the coarse reference over the whole region");
            let run = RunWide {
                swaths: &swaths,
                shifts: &shifts,
                trends: &gain_trends,
                scale: intensity_scale,
                gains: &gains,
                noise_weights: &noise_weights,
                blur_px: &blur,
                dem_psf_sigma,
                params,
            };
            super::reference::build(o, inputs, &grid, &run, f, &tiles)?
        }
        None => None,
    };
    let p = Plan {
        version: crate::BUILD.into(),
        key,
        grid,
        halo,
        blend,
        tiles,
        intensity_scale,
        intensity_pixels: count,
        gains,
        gain_reference,
        gain_trends,
        noise_weights,
        dem_psf_sigma,
        resolution_source,
        dem_resolution_m: dem.dem_resolution_m,
        dem_resolution_source: dem.dem_resolution_source,
        sigma_dem: dem.sigma_dem,
        dem_track_weight: dem.dem_track_weight,
        dem_track_source: dem.dem_track_source,
        high_sun_east_west: high_sun_ew,
        high_sun_east_west_source: high_sun_ew_source,
        membrane,
        swaths,
        reference: built.as_ref().map(|b| b.info.clone()),
        registration,
        pixel_size_m,
        sun_deg,
        sun_elevation_range_deg,
        on_grid_pixels,
        sun_ephemeris,
        dem_vs_loc,
        striping,
        dem_tracks,
    };
    write_atomic(
        &path,
        serde_json::to_string_pretty(&p)
            .expect("plans serialise")
            .as_bytes(),
    )?;
    progress.finish();
    report(&p, o, inputs, progress);
    let (reference, ingested) = match built {
        Some(b) => (Some(b.values), b.ingested),
        None => (None, None),
    };
    Ok((p, reference, ingested))
}

/// The run-wide radiometry: the gains, the intensity scale of the tiles' E_I and the noise
/// weights.
struct Radiometry {
    gains: RunGains,
    /// Ī: the mean of I_k/g_k over every observation's usable pixels on the grid.
    intensity_scale: f64,
    noise_weights: Vec<f64>,
}

/// The gains where observations overlap ([`run_gains`]; one observation: gain 1), then Ī of
/// the tiles' E_I — the mean of I_k/g_k over every observation's pixels on the grid, as `fuse`
/// computes it for itself — and the noise weights. `raw` is what the survey measured: the
/// raw mean Ī (it served the registration and the gains), each observation's sum and mean
/// of usable reflectance, and the count of usable pixels.
fn radiometry(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    placed: (&[SwathIndex], &[Displacement]),
    (raw_scale, sums, means, count): (f64, &[f64], &[Option<f64>], usize),
    progress: &Progress,
) -> Result<Radiometry> {
    let several = inputs.obs.len() > 1;
    let gains = if several {
        progress.stage("planning: radiometric gains where observations overlap");
        run_gains(o, inputs, grid, placed, raw_scale)?
    } else {
        RunGains::one()
    };
    let intensity_scale = if several {
        sums.iter()
            .zip(&gains.gains)
            .map(|(s, g)| s / g)
            .sum::<f64>()
            / count as f64
    } else {
        raw_scale
    };
    let noise_weights = noise_weights(means, &gains.gains, intensity_scale);
    Ok(Radiometry {
        gains,
        intensity_scale,
        noise_weights,
    })
}

/// Refuse a grid of fewer than 3 pixels along a side (fusion's smallest, `FusionError::TooSmall`),
/// naming the spacing: the region is then smaller than a few pixels of it.
fn at_least_three_pixels(grid: &Grid) -> Result<()> {
    if grid.rows < 3 || grid.cols < 3 {
        return Err(Error::Usage(format!(
            "[grid]/[region]: at {} m a pixel, the region is {} × {} pixels; fusion needs at least 3 × 3: use a finer resolution_m or a larger region",
            grid.spacing, grid.rows, grid.cols
        )));
    }
    Ok(())
}

/// Refuse a grid wider or taller than half the Moon's circumference: no one locally metric
/// projection holds such a region.
fn within_half_moon(grid: &Grid) -> Result<()> {
    let half_moon = std::f64::consts::PI * crate::grid::MOON_RADIUS_M;
    let (w, h) = (
        grid.cols as f64 * grid.spacing,
        grid.rows as f64 * grid.spacing,
    );
    if w > half_moon || h > half_moon {
        return Err(Error::Usage(format!(
            "[region]: {:.0} × {:.0} km is more than half the Moon's circumference ({:.0} km) across: not a region one locally metric grid can hold; split it",
            w / 1e3,
            h / 1e3,
            half_moon / 1e3
        )));
    }
    Ok(())
}

/// The tiles of `[tiling] tile_size` with `halo` over the grid ([`tiling::layout`]); more
/// than [`MAX_TILES`] are refused, naming what to change.
fn layout_tiles(o: &Orbital, grid: &Grid, halo: usize) -> Result<Vec<Tile>> {
    let n_tiles = grid.rows.div_ceil(o.tiling.tile_size) * grid.cols.div_ceil(o.tiling.tile_size);
    if n_tiles > MAX_TILES {
        return Err(Error::Usage(format!(
            "[tiling]: {} × {} px in tiles of {} px makes {n_tiles} tiles, more than {MAX_TILES}: raise tile_size or shrink [region]",
            grid.rows, grid.cols, o.tiling.tile_size
        )));
    }
    Ok(tiling::layout(
        grid.rows,
        grid.cols,
        o.tiling.tile_size,
        halo,
    ))
}

/// The DEM's widths on the grid and the fusion parameters they set ([`dem_terms`]).
struct DemTerms {
    /// The DEM's effective resolution, metres, and where it came from.
    dem_resolution_m: f64,
    dem_resolution_source: String,
    /// σ_B, the DEM's point spread on the grid, and σ_DEM, pixels.
    dem_psf_sigma: f64,
    sigma_dem: f64,
    /// E_DEM's track weight a and why.
    dem_track_weight: f64,
    dem_track_source: String,
    /// `[solver]` with σ_DEM and a.
    params: FusionParams,
}

/// The latitude of the grid's centre, degrees (0 where the projection has none there).
fn centre_lat(grid: &Grid, pr: &crate::grid::Projector) -> f64 {
    pr.inverse(
        grid.x0 + 0.5 * grid.cols as f64 * grid.spacing,
        grid.y0 - 0.5 * grid.rows as f64 * grid.spacing,
    )
    .map_or(0.0, |(_, lat)| lat)
}

/// Each DEM product's offsets between its tracks over the region
/// ([`ingest::lola_track_offsets`], on the grid decimated as for the gains): estimated for a
/// gridded LOLA product whose pixels resolve its tracks at the region's latitude
/// ([`Dem::resolves_tracks`]), `None` for any other DEM. Estimated whether or not
/// `[inputs] dem_destripe` applies them, so that the record says what they would be.
fn dem_track_offsets(
    inputs: &Inputs,
    grid: &Grid,
    pr: &crate::grid::Projector,
) -> Result<Vec<Option<ingest::TrackOffsets>>> {
    let lat = centre_lat(grid, pr);
    let coarse = gain_grid(grid);
    let geo = coarse.geographic(&projector(&coarse.crs)?);
    inputs
        .lola
        .iter()
        .map(|d| match d {
            Dem::Pds(p) if d.resolves_tracks(lat) => ingest::lola_track_offsets(p, &geo),
            _ => Ok(None),
        })
        .collect()
}

/// The DEM's effective resolution at the region's centre (`[inputs] dem_resolution_m`, or the
/// product's own), the point spread σ_B and σ_DEM it gives on the grid unless the workflow
/// sets them ([`fusion::dem_psf_sigma`], [`fusion::dem_sigma`]), and E_DEM's track weight
/// ([`track_weight`], [`dem_blur_track_weight`]).
fn dem_terms(o: &Orbital, inputs: &Inputs, grid: &Grid, pr: &crate::grid::Projector) -> DemTerms {
    let centre_lat = centre_lat(grid, pr);
    let (dem_resolution_m, dem_resolution_source) = match o.inputs.dem_resolution_m {
        Some(r) => (r, "[inputs] dem_resolution_m".to_string()),
        None => inputs.lola[0].effective_resolution(centre_lat),
    };
    let factor = dem_resolution_m / grid.spacing;
    let dem_psf_sigma = o
        .inputs
        .dem_psf_sigma_px
        .unwrap_or(fusion::dem_psf_sigma(factor));
    let sigma_dem = if o.sigma_dem_given {
        o.solver.sigma_dem
    } else {
        fusion::dem_sigma(factor)
    };
    let (dem_track_weight, dem_track_source) = track_weight(
        o.dem_track_weight_given
            .then_some(o.solver.dem_track_weight),
        o.solver.dem_track_weight,
        inputs.lola[0].resolves_tracks(centre_lat),
        north_turn_deg(grid, pr),
    );
    let (dem_track_weight, dem_track_source) = dem_blur_track_weight(
        (dem_track_weight, dem_track_source),
        dem_psf_sigma,
        o.solver.dem_track_sigma_px,
    );
    let params = FusionParams {
        sigma_dem,
        dem_track_weight,
        ..o.solver.clone()
    };
    DemTerms {
        dem_resolution_m,
        dem_resolution_source,
        dem_psf_sigma,
        sigma_dem,
        dem_track_weight,
        dem_track_source,
        params,
    }
}

/// ν_k = Ī/Ī_k ([`fusion::observations::noise_weight`]), Ī_k each observation's mean
/// reflectance over its pixels on the grid (`means`) corrected by its gain; 1 for a single
/// observation, and for one without a pixel on the grid.
fn noise_weights(means: &[Option<f64>], gains: &[f64], scale: f64) -> Vec<f64> {
    if means.len() < 2 {
        return vec![1.0; means.len()];
    }
    means
        .iter()
        .zip(gains)
        .map(|(m, g)| m.map_or(1.0, |m| fusion::observations::noise_weight(scale, m / g)))
        .collect()
}

/// What the plan's survey of every observation found on the grid ([`survey_all`]).
struct Surveyed {
    swaths: Vec<SwathIndex>,
    /// Σ of the usable reflectances over every observation, and their count.
    sum: f64,
    count: usize,
    /// Per observation: the mean usable reflectance (`None` without a usable pixel), the sum,
    /// and the mean Sun [azimuth, elevation] in degrees.
    means: Vec<Option<f64>>,
    sums: Vec<f64>,
    sun_deg: Vec<Option<[f64; 2]>>,
    /// Per observation: its lowest and highest Sun elevation, degrees.
    sun_elevation_range_deg: Vec<Option<[f64; 2]>>,
    /// Per observation: its swath pixels on the grid, usable or not.
    on_grid_pixels: Vec<usize>,
    /// Per observation: its OBS Sun against the ephemeris ([`ingest::SunCheck`]).
    sun_ephemeris: Vec<Option<ingest::SunCheck>>,
    /// Per observation: LOC's heights against the DEM ([`ingest::DemVsLoc`]).
    dem_vs_loc: Vec<Option<ingest::DemVsLoc>>,
    /// Per observation: its detector column gain estimate ([`crate::striping`]).
    striping: Vec<Option<crate::striping::Striping>>,
}

/// Survey every observation on the grid ([`ingest::survey`]): its swath index, the sums of Ī,
/// its mean Sun, its OBS Sun and SOLAR_DISTANCE against the ephemeris (refused beyond what
/// [`ingest::check_sun_ephemeris`] allows, unless `[inputs] check_sun_ephemeris = false`) and
/// its LOC heights against the DEM, and its detector columns' gains (put in its swath index,
/// which every read of it goes through, when `[inputs] destripe` is on). An error naming each
/// observation and what became of its pixels when no usable pixel falls on the grid.
fn survey_all(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    pr: &crate::grid::Projector,
) -> Result<Surveyed> {
    let mut swaths = Vec::new();
    let (mut sum, mut count) = (0.0, 0usize);
    let mut means = Vec::new();
    let mut sums = Vec::new();
    let mut sun_deg = Vec::new();
    let mut sun_elevation_range_deg = Vec::new();
    let mut on_grid_pixels = Vec::new();
    let mut sun_ephemeris = Vec::new();
    let mut dem_vs_loc = Vec::new();
    let mut striping = Vec::new();
    let mut why = Vec::new();
    for (k, obs) in inputs.obs.iter().enumerate() {
        let mut s = ingest::survey(obs, inputs.solar(k), o.inputs.wavelength_nm, grid, pr)?;
        if o.inputs.destripe {
            // Only gains other than 1 are worth dividing by.
            s.index.column_gains = s
                .striping
                .as_ref()
                .filter(|g| g.summary.columns > 0)
                .map(|g| g.gain.clone());
        }
        striping.push(s.striping.as_ref().map(|g| g.summary));
        if let Some(check) = s
            .sun_ephemeris
            .as_ref()
            .filter(|_| o.inputs.check_sun_ephemeris)
        {
            ingest::check_sun_ephemeris(obs, check)?;
        }
        sun_ephemeris.push(s.sun_ephemeris);
        dem_vs_loc.push(loc_against_dem(o, inputs, &s.loc_heights)?);
        sum += s.sum;
        count += s.count;
        means.push((s.count > 0).then(|| s.sum / s.count as f64));
        sums.push(s.sum);
        sun_deg.push(s.mean_sun().map(|(az, el)| [az, el]));
        sun_elevation_range_deg.push(s.sun_elevation_range());
        on_grid_pixels.push(s.on_grid);
        why.push(if s.on_grid == 0 {
            format!(
                "{}: no pixel of its swath falls on the grid (region)",
                obs.label_path.display()
            )
        } else {
            format!(
                "{}: {} of its pixels fall on the grid, {} refused ({})",
                obs.label_path.display(),
                s.on_grid,
                s.refused.total(),
                s.refused.describe()
            )
        });
        swaths.push(s.index);
    }
    if count == 0 {
        return Err(Error::Usage(format!(
            "no usable M3 pixel on the grid ({} × {} px at {} m): {}. Check [region] against the observations' coverage, and the observations' radiance and OBS geometry",
            grid.rows,
            grid.cols,
            grid.spacing,
            why.join("; ")
        )));
    }
    Ok(Surveyed {
        swaths,
        sum,
        count,
        means,
        sums,
        sun_deg,
        sun_elevation_range_deg,
        on_grid_pixels,
        sun_ephemeris,
        dem_vs_loc,
        striping,
    })
}

/// Refuse an incidence window (`[inputs] min_incidence_deg` … `max_incidence_deg`) that
/// leaves out every observation: where each observation's Sun stands, over its usable pixels
/// on the grid (`elevations`, the survey's range of Sun elevations; `None` where it has none),
/// the window admits no incidence (90° − elevation), so no image would constrain the surface
/// and the run would write the input DEM back as its result. An observation the window leaves
/// out while others stay in is reported by the run's sanity figures.
fn incidence_window_admits(
    sel: &fusion::Selection,
    labels: &[String],
    elevations: &[Option<[f64; 2]>],
) -> Result<()> {
    let incidences: Vec<(&String, [f64; 2])> = labels
        .iter()
        .zip(elevations)
        .filter_map(|(label, e)| e.map(|[lo, hi]| (label, [90.0 - hi, 90.0 - lo])))
        .collect();
    if incidences.is_empty() || incidences.iter().any(|(_, r)| sel.admits_some_of(*r)) {
        return Ok(());
    }
    let seen: Vec<String> = incidences
        .iter()
        .map(|(label, [lo, hi])| format!("{label}: {lo:.1}–{hi:.1}°"))
        .collect();
    Err(Error::Usage(format!(
        "[inputs] min_incidence_deg = {} and max_incidence_deg = {} leave out every observation: over the region their Suns stand at incidences (from the zenith) of {}. Widen the window (the defaults, 0 and 90, admit every Sun above the horizon) or list observations taken under Suns within it",
        sel.min_incidence_deg,
        sel.max_incidence_deg,
        seen.join("; ")
    )))
}

/// LOC's sampled heights against the DEM at the same points ([`ingest::dem_vs_loc`]).
fn loc_against_dem(
    o: &Orbital,
    inputs: &Inputs,
    loc: &ingest::LocHeights,
) -> Result<Option<ingest::DemVsLoc>> {
    let n = loc.lon.len();
    if n == 0 {
        return Ok(None);
    }
    let row = |v: &[f64]| Array2::from_shape_vec((1, n), v.to_vec()).expect("1 × n");
    let geo = crate::grid::Geographic {
        lon: row(&loc.lon),
        lat: row(&loc.lat),
        bearing: Array2::zeros((1, n)),
    };
    let dem = super::inputs::dem_on(o, inputs, &geo)?;
    Ok(ingest::dem_vs_loc(
        loc,
        dem.as_slice().expect("standard layout"),
    ))
}

/// The plan in `out`'s plan.json when it has the run's `key` and its reference file (if it has
/// one) matches its checksum, with the reference's values; `None` (saying why) when there is
/// none, it belongs to other inputs or parameters, or its reference does not load.
fn existing(out: &Path, key: &str, progress: &Progress) -> Option<(Plan, Option<Array2<f64>>)> {
    let path = out.join("plan.json");
    let text = std::fs::read_to_string(&path).ok()?;
    let why = match serde_json::from_str::<Plan>(&text) {
        Ok(p) if p.key == key => {
            let reference = p
                .reference
                .as_ref()
                .map(|r| super::reference::load(out, r))
                .transpose();
            match reference {
                Ok(reference) => {
                    progress.note(&format!("plan: reusing {}", path.display()));
                    return Some((p, reference));
                }
                Err(e) => e.to_string(),
            }
        }
        _ => format!("{} belongs to other inputs or parameters", path.display()),
    };
    progress.note(&format!("plan: {why}; planning anew"));
    None
}

/// What the plan says of itself once made: the grid and tiling, Ī, the DEM's widths and track
/// weight, the membrane, each observation's mean Sun and registration, the coarse reference,
/// the gains, noise weights and gain trends.
fn report(p: &Plan, o: &Orbital, inputs: &Inputs, progress: &Progress) {
    progress.note(&format!(
        "plan: {} × {} px at {} m ({}; {}), {} {} of {} px + {} px halo, Ī = {:.5} sr⁻¹ over {} px; DEM resolution {:.0} m ({}), σ_B {:.2} px, σ_DEM {:.2} px",
        p.grid.rows,
        p.grid.cols,
        p.grid.spacing,
        p.resolution_source,
        p.grid.crs.name(),
        p.tiles.len(),
        if p.tiles.len() == 1 { "tile" } else { "tiles" },
        o.tiling.tile_size,
        p.halo,
        p.intensity_scale,
        p.intensity_pixels,
        p.dem_resolution_m,
        p.dem_resolution_source,
        p.dem_psf_sigma,
        p.sigma_dem
    ));
    progress.note(&format!(
        "plan: E_DEM track weight {} ({})",
        p.dem_track_weight, p.dem_track_source
    ));
    progress.note(&format!(
        "plan: δ under high Suns that measure east–west slopes: multi_delta_factor_high_sun_east_west {} ({})",
        p.high_sun_east_west, p.high_sun_east_west_source
    ));
    progress.note(&format!("plan: membrane {}", p.membrane));
    for (k, (obs, sun)) in inputs.obs.iter().zip(&p.sun_deg).enumerate() {
        if let Some([az, el]) = sun {
            let range = match p.sun_elevation_range_deg.get(k).copied().flatten() {
                Some([lo, hi]) if hi - lo >= 0.05 => format!(" ({lo:.1}–{hi:.1}°)"),
                _ => String::new(),
            };
            progress.note(&format!(
                "plan: {}: mean Sun over its pixels on the grid at azimuth {az:.1}°, elevation {el:.1}°{range}",
                obs.label_path.display()
            ));
        }
    }
    for (obs, r) in inputs.obs.iter().zip(&p.registration) {
        progress.note(&format!(
            "plan: registration of {}: {}",
            obs.label_path.display(),
            r.note
        ));
    }
    if let Some(r) = &p.reference {
        progress.note(&format!(
            "plan: coarse reference on {} × {} px of {} × {} grid pixels ({} Gauss–Newton steps, {:.1} s)",
            r.rows, r.cols, r.factor, r.factor, r.iterations, r.seconds
        ));
    }
    if p.gains.len() > 1 {
        let list = |v: &[f64]| {
            v.iter()
                .map(|x| format!("{x:.4}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        progress.note(&format!(
            "plan: {} observations, gains {} (relative to the first of each overlapping group), noise weights {}",
            p.gains.len(),
            list(&p.gains),
            list(&p.noise_weights)
        ));
    }
    if p.gain_trends.iter().any(Option::is_some) {
        let list: Vec<String> = p
            .gain_trends
            .iter()
            .map(|t| t.map_or("none".into(), |t| format!("{:+.4}", t.per_1000_lines)))
            .collect();
        progress.note(&format!(
            "plan: gain trends along the track, change of ln g per 1000 lines: {}",
            list.join(", ")
        ));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::Crs;

    /// A 512² grid of 140 m pixels centred on the projection's origin.
    fn grid(crs: Crs) -> Grid {
        let half = 256.0 * 140.0;
        Grid::new(crs, 512, 512, -half, half, 140.0).unwrap()
    }

    /// On a stereographic grid centred on the region north stays within a fraction of a
    /// degree of the columns (meridians converge by Δλ·sin φ: ±36 km at −13.4° turn by ≈ 0.3°); on a
    /// south-polar grid around the pole it points every way.
    #[test]
    fn north_turns_little_on_a_centred_grid_and_every_way_at_a_pole() {
        let centred = grid(Crs::Stereographic {
            lat_0: -13.4,
            lon_0: 357.2,
        });
        let turn = north_turn_deg(&centred, &centred.crs.projector().unwrap());
        assert!(turn > 0.1 && turn < 1.0, "{turn}°");
        let polar = grid(Crs::PolarStereographic { north: false });
        let turn = north_turn_deg(&polar, &polar.crs.projector().unwrap());
        assert!(turn > 90.0, "{turn}°");
    }

    /// The narrower of the two ranges: a swath across 0° or 180° stays together.
    #[test]
    fn a_swath_across_a_meridian_keeps_its_longitudes_together() {
        let at = |lons: &[f64]| longitude_span(&lons.iter().map(|&l| (l, 0.0)).collect::<Vec<_>>());
        assert_eq!(at(&[10.0, 20.0, 15.0]), (10.0, 20.0));
        assert_eq!(at(&[359.0, 1.0]), (-1.0, 1.0));
        assert_eq!(at(&[-1.0, 1.0]), (-1.0, 1.0));
        assert_eq!(at(&[179.0, -179.0]), (179.0, 181.0));
        assert_eq!(at(&[179.0, 181.0]), (179.0, 181.0));
    }

    /// The high-Sun east–west factor stays on only where every observation's columns were
    /// estimated over enough blocks and none shows striping; a workflow's own value wins.
    #[test]
    fn the_high_sun_east_west_factor_needs_images_without_striping() {
        let s = |blocks: usize, rms: f64| {
            Some(crate::striping::Striping {
                blocks,
                columns: 0,
                stripe_rms: rms,
                noise_rms: 0.003,
                correction_rms: 0.0,
            })
        };
        let decide =
            |obs: &[Option<crate::striping::Striping>]| high_sun_east_west(None, 0.02, 0.05, obs);
        assert_eq!(decide(&[s(16, 0.0), s(8, 0.0)]).0, 0.02);
        let (f, why) = decide(&[s(16, 0.0), s(16, 0.0108)]);
        assert_eq!(f, 0.05);
        assert!(
            why.contains("observation 2") && why.contains("1.08 %"),
            "{why}"
        );
        assert_eq!(decide(&[s(3, 0.0)]).0, 0.05);
        assert_eq!(decide(&[s(16, 0.0), None]).0, 0.05);
        let (f, why) = high_sun_east_west(Some(0.03), 0.02, 0.05, &[s(16, 0.01)]);
        assert_eq!(
            (f, why.as_str()),
            (0.03, "[solver] multi_delta_factor_high_sun_east_west")
        );
    }

    #[test]
    fn the_track_weighting_applies_to_resolved_lola_tracks_along_the_columns_only() {
        assert_eq!(track_weight(None, 0.1, true, 0.5).0, 0.1);
        assert_eq!(track_weight(None, 0.1, true, 6.0).0, 1.0);
        assert_eq!(track_weight(None, 0.1, false, 0.5).0, 1.0);
        // Given in the workflow, it is kept whatever the DEM and the grid.
        let (w, why) = track_weight(Some(0.3), 0.1, false, 40.0);
        assert_eq!((w, why.as_str()), (0.3, "[solver] dem_track_weight"));
        assert!(track_weight(None, 0.1, true, 6.0).1.contains("6.0°"));
        // A DEM blurred as widely as σ_t: the plain term, whoever chose the weighting.
        let chosen = track_weight(Some(0.3), 0.1, true, 0.5);
        let (w, why) = dem_blur_track_weight(chosen.clone(), 9.9, 9.0);
        assert_eq!(w, 1.0);
        assert!(why.contains("9.9 px") && why.contains("[solver] dem_track_weight"));
        assert_eq!(dem_blur_track_weight(chosen.clone(), 2.4, 9.0), chosen);
    }
}
