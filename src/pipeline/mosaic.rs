//! Step 3, the mosaic: blend the tiles band by band into COGs, the quick look and the run
//! record (`run.json`), with the products' metadata.

use super::*;

/// Rows the mosaic blends at a time.
pub(super) const MOSAIC_BAND: usize = 256;

/// What a GIS user sees of each layer.
/// Longest side of a run's quick-look panels, pixels.
pub(super) const QUICKLOOK_SIDE: usize = 480;

/// The run's quick look (`quicklook.png`): the image, hillshades of the input and the fused
/// DEM, the albedo, dem − input_dem and the residual, each titled, with colour bars and a
/// scale bar, from block means of the products (`thumbs` in [`TILE_LAYERS`] order).
pub(super) fn write_quicklook(
    path: &Path,
    thumbs: &[Thumbnail],
    spacing: f64,
    nm: f64,
) -> Result<()> {
    use crate::quicklook::{
        diverging, diverging_ramp, grey, grey_ramp, hillshade, quantiles, rgb, scale_bar,
        write_sheet, ColourBar, Panel,
    };
    let [dem, albedo, residual, _, input, image] = [0, 1, 2, 3, 4, 5].map(|k| thumbs[k].means());
    let pixel = spacing * thumbs[0].factor as f64;
    let stretched = |a: &Array2<f64>, title: String, digits: usize| {
        let r = quantiles(a, 0.01, 0.99).unwrap_or((0.0, 1.0));
        Panel {
            title,
            picture: grey(a, r),
            bar: Some(ColourBar {
                ramp: grey_ramp,
                low: format!("{:.*}", digits, r.0),
                high: format!("{:.*}", digits, r.1),
            }),
        }
    };
    // Hillshades cannot take no-data: fill it with the input DEM (the fused DEM has none).
    let filled = |a: &Array2<f64>| {
        Zip::from(a)
            .and(&input)
            .map_collect(|&v, &i| if v.is_finite() { v } else { i })
    };
    let mut input_shade = rgb(&hillshade(&filled(&input), pixel));
    scale_bar(&mut input_shade, pixel);
    let change = Zip::from(&dem).and(&input).map_collect(|&a, &b| a - b);
    let limit = quantiles(&change.mapv(f64::abs), 0.0, 0.99)
        .map_or(1.0, |q| q.1)
        .max(0.01);
    let panels = [
        stretched(&image, format!("image I at {nm} nm, sr-1"), 4),
        Panel {
            title: "input DEM, light az 315 el 45".into(),
            picture: input_shade,
            bar: None,
        },
        Panel {
            title: "fused DEM, same light".into(),
            picture: rgb(&hillshade(&filled(&dem), pixel)),
            bar: None,
        },
        stretched(&albedo, "albedo".into(), 3),
        Panel {
            title: "dem - input_dem, m".into(),
            picture: diverging(&change, limit),
            bar: Some(ColourBar {
                ramp: diverging_ramp,
                low: format!("-{limit:.1}"),
                high: format!("+{limit:.1}"),
            }),
        },
        stretched(&residual, "residual |I-R|, sr-1".into(), 4),
    ];
    write_sheet(path, &panels, 3)
}

/// The dataset metadata of a run's products: software, inputs by product ID, wavelength,
/// photometric model, solver parameters and the DEM widths the tiles used.
pub(super) fn product_metadata(
    o: &Orbital,
    inputs: &Inputs,
    plan: &Plan,
    key: &str,
) -> Vec<(&'static str, String)> {
    let id = inputs::product_id;
    let m3: Vec<String> = inputs
        .obs
        .iter()
        .map(|ob| id(&ob.label, &ob.label_path))
        .collect();
    let dems: Vec<String> = inputs
        .lola
        .iter()
        .map(|d| match d {
            Dem::Pds(d) => id(&d.label, &d.label_path),
            Dem::GeoTiff(g) => g
                .path
                .file_name()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default(),
        })
        .collect();
    let solver = plan.solver(&o.solver);
    let join = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join(",")
    };
    vec![
        ("SFSFUSE_VERSION", crate::BUILD.to_string()),
        ("RUN_KEY", key.to_string()),
        ("M3_PRODUCT_IDS", m3.join(",")),
        ("DEM_PRODUCT_IDS", dems.join(",")),
        ("WAVELENGTH_NM", format!("{}", o.inputs.wavelength_nm)),
        (
            "PHOTOMETRIC_MODEL",
            serde_json::to_string(&o.photometry).expect("models serialise"),
        ),
        (
            "SOLVER_PARAMETERS",
            serde_json::to_string(&solver).expect("parameters serialise"),
        ),
        ("DEM_PSF_SIGMA_PX", format!("{}", plan.dem_psf_sigma)),
        ("M3_GAINS", join(&plan.gains)),
        ("M3_NOISE_WEIGHTS", join(&plan.noise_weights)),
        (
            "DEM_EFFECTIVE_RESOLUTION_M",
            format!("{}", plan.dem_resolution_m),
        ),
    ]
}

/// How a layer is stored: the mask and the observation counts are whole numbers (Byte), the
/// rest float32.
pub(super) fn sample_format(l: Layer) -> SampleFormat {
    match l {
        Layer::Mask | Layer::Observations => SampleFormat::Byte,
        _ => SampleFormat::Float32,
    }
}

pub(super) fn layer_info(l: Layer, lunar: bool) -> (&'static str, &'static str) {
    match l {
        Layer::Dem if lunar => ("fused height above the 1737.4 km sphere", "m"),
        Layer::Dem => ("fused height", "m"),
        Layer::Albedo => (
            "albedo (Hapke single-scattering albedo w for the Hapke model)",
            "",
        ),
        Layer::Residual => (
            "|I/g - R| at the solution (w-weighted RMS over the observations used); no data without photometric information",
            "sr-1",
        ),
        Layer::Mask => (
            "0 = fused from shading, 1 = seen but not photometric (shadow, refused pixel), 2 = no image (input DEM)",
            "",
        ),
        Layer::InputDem if lunar => (
            "input DEM resampled to the grid, height above the 1737.4 km sphere",
            "m",
        ),
        Layer::InputDem => ("input depth map as height", "m"),
        Layer::Image if lunar => (
            "observed reflectance I on the grid (first observation covering each pixel)",
            "sr-1",
        ),
        Layer::Image => ("intensity image", ""),
        Layer::Observations => (
            "number of observations that carried photometric information at the pixel",
            "",
        ),
    }
}

#[derive(Debug, Clone, Serialize)]
pub(super) struct InputFile {
    pub(super) path: PathBuf,
    pub(super) bytes: u64,
    pub(super) sha256: String,
}

#[derive(Debug, Clone, Serialize)]
pub(super) struct Metrics {
    pub(super) pixels: usize,
    pub(super) photometric_fraction: f64,
    pub(super) residual_mean: f64,
    /// RMS of (fused − input DEM), metres.
    pub(super) height_change_rms_m: f64,
    pub(super) height_min_m: f64,
    pub(super) height_max_m: f64,
    pub(super) albedo_mean: f64,
}

#[derive(Debug, Clone, Serialize)]
pub(super) struct RunRecord<'a> {
    pub(super) tool: &'static str,
    pub(super) version: &'static str,
    /// The workflow with every default filled in.
    pub(super) workflow: &'a Workflow,
    /// [`run_key`]: the products' `RUN_KEY`, which ties them to this record.
    pub(super) run_key: String,
    pub(super) inputs: Vec<InputFile>,
    pub(super) grid: Option<Grid>,
    pub(super) crs_wkt: Option<String>,
    pub(super) halo: Option<usize>,
    pub(super) intensity_scale: Option<f64>,
    pub(super) dem_psf_sigma: Option<f64>,
    /// Where the grid spacing came from; the DEM's effective resolution, its source, and the
    /// σ_DEM the tiles used (orbital runs).
    pub(super) resolution_source: Option<String>,
    pub(super) dem_resolution_m: Option<f64>,
    pub(super) dem_resolution_source: Option<String>,
    pub(super) sigma_dem: Option<f64>,
    /// E_DEM's track weighting the tiles used and why (orbital runs).
    pub(super) dem_track_weight: Option<f64>,
    pub(super) dem_track_source: Option<String>,
    /// `multi_delta_factor_high_sun_east_west` the tiles used and why (orbital runs).
    pub(super) high_sun_east_west: Option<f64>,
    pub(super) high_sun_east_west_source: Option<String>,
    /// Each DEM product's offsets between its tracks (orbital runs; `Plan::dem_tracks`), in
    /// `[inputs] lola` order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub(super) dem_tracks: Vec<Option<DemTracks>>,
    /// The membrane where one observation carries a pixel (orbital runs; `Plan::membrane`).
    pub(super) membrane: Option<String>,
    /// The plan's coarse reference (orbital runs with one).
    pub(super) reference: Option<ReferenceInfo>,
    pub(super) threads: usize,
    pub(super) tiles: Vec<TileRecord>,
    pub(super) metrics: Metrics,
    /// Sanity figures for real data (orbital runs).
    pub(super) sanity: Option<Sanity>,
    /// Per M3 observation: gain, weight and how much of its footprint was photometric
    /// (orbital runs).
    pub(super) observations: Vec<ObservationRecord>,
    pub(super) outputs: Vec<PathBuf>,
}

/// One observation's part in a run.
#[derive(Debug, Clone, Serialize)]
pub(super) struct ObservationRecord {
    pub(super) label: PathBuf,
    /// Radiometric gain g relative to the first observation of its overlapping group.
    pub(super) gain: f64,
    /// How that gain was fixed ([`gain_source`]).
    pub(super) gain_source: String,
    /// Its gain's trend along the track (`[inputs] gain_trend`; absent: none).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) gain_trend: Option<GainTrend>,
    /// Noise weight ν (docs/science.md, "Several observations").
    pub(super) noise_weight: f64,
    /// Its pixels on the grid (its footprint).
    pub(super) footprint_pixels: usize,
    /// The share of its footprint where it carried photometric information.
    pub(super) photometric_fraction: f64,
    /// Its registration to the DEM ([`super::register::register`]).
    pub(super) registration: Option<super::register::Registration>,
    /// Its pixel size, metres ([`crate::ingest::ground_sample_distance`]).
    pub(super) pixel_size_m: Option<f64>,
    /// σ, grid pixels, of the blur E_I models it with (0: none; [`super::plan::blur_px`]).
    pub(super) blur_px: f64,
    /// Its mean Sun over its usable pixels on the grid, degrees ([`super::plan::Plan::sun_deg`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) sun: Option<MeanSun>,
    /// Its OBS Sun against the ephemeris at its label's times ([`crate::ingest::SunCheck`]);
    /// a note instead where the label gives no START_TIME.
    pub(super) sun_ephemeris: SunEphemeris,
    /// Its LOC heights against the DEM at sampled pixels ([`crate::ingest::DemVsLoc`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) dem_vs_loc: Option<crate::ingest::DemVsLoc>,
    /// Its detector column gains ([`crate::striping::Striping`]) and whether they were
    /// divided out (`[inputs] destripe`, and some column off 1).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) column_striping: Option<ColumnStriping>,
}

/// What the run record says of a DEM product's offsets between its tracks.
#[derive(Debug, Clone, Copy, Serialize)]
pub(super) struct DemTracks {
    /// What the estimate saw, in metres ([`crate::striping::Striping`]).
    #[serde(flatten)]
    pub(super) estimate: crate::striping::Striping,
    /// Whether the run took them out of the heights (`[inputs] dem_destripe`).
    pub(super) applied: bool,
}

/// What the run record says of an observation's detector column gains.
#[derive(Debug, Clone, Copy, Serialize)]
pub(super) struct ColumnStriping {
    #[serde(flatten)]
    pub(super) estimate: crate::striping::Striping,
    pub(super) applied: bool,
}

/// What the run record says of an observation's Sun check.
#[derive(Debug, Clone, Serialize)]
#[serde(untagged)]
pub(super) enum SunEphemeris {
    Checked(crate::ingest::SunCheck),
    NotChecked(String),
}

/// An observation's mean Sun over the region, degrees.
#[derive(Debug, Clone, Copy, Serialize)]
pub(super) struct MeanSun {
    /// Clockwise from north (circular mean).
    pub(super) azimuth_deg: f64,
    /// Above the local horizontal of the reference sphere (90° − the mean OBS to-Sun zenith).
    pub(super) elevation_deg: f64,
    /// The lowest and highest elevation over the same pixels (over a long strip the Sun
    /// changes along the track).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub(super) elevation_range_deg: Option<[f64; 2]>,
}

/// Below this mean Sun elevation, degrees, an observation used with others is named in a
/// warning ([`low_sun_warning`]).
pub const LOW_SUN_DEG: f64 = 10.0;

/// The observations used alongside others whose Sun stands below [`LOW_SUN_DEG`] on average
/// over the region (`sun_deg`, [azimuth, mean elevation]) or over part of it (`range_deg`, the
/// lowest and highest elevation; over a long strip the Sun changes along the track): such an
/// image is mostly cast shadow and grazing light, which the photometric model describes least
/// well; measured on the synthetic scenes, a Sun 5° high added to one 30° high gains 7 %, one
/// 2° high nothing (docs/science.md, "Several observations").
pub(super) fn low_sun_warning(
    labels: &[String],
    used: &[bool],
    sun_deg: &[Option<[f64; 2]>],
    range_deg: &[Option<[f64; 2]>],
) -> Option<String> {
    if used.iter().filter(|&&u| u).count() < 2 {
        return None;
    }
    let low: Vec<String> = labels
        .iter()
        .zip(used)
        .zip(sun_deg)
        .enumerate()
        .filter_map(|(k, ((label, &used), sun))| {
            let [_, el] = sun.filter(|_| used)?;
            if el < LOW_SUN_DEG {
                return Some(format!("{label} ({el:.1}°)"));
            }
            let [lo, hi] = range_deg.get(k).copied().flatten()?;
            (lo < LOW_SUN_DEG)
                .then(|| format!("{label} ({lo:.1}–{hi:.1}° over the region, {el:.1}° on average)"))
        })
        .collect();
    (!low.is_empty()).then(|| {
        format!(
            "Sun less than {LOW_SUN_DEG:.0}° above the horizon on average over the region, or over part of it: {}. Such an image, or that part of it, is mostly cast shadow and grazing light, where the photometric model is least reliable; it is weighted by its brightness and tapered near the horizon, but it adds little (docs/science.md, \"Several observations\"). Leave it out, or lower [inputs] max_incidence_deg to drop its most grazing pixels",
            low.join(", ")
        )
    })
}

/// Pixels of an observation this many times the grid's or more count as coarser than it
/// ([`coarse_pixels_warning`]).
pub const COARSE_PIXELS_FROM: f64 = 1.25;

/// The warning for observations used on the region whose pixels (`pixel_size`, metres) are
/// [`COARSE_PIXELS_FROM`] × the grid's `spacing` or more: the fusion models each as its blur
/// ([`crate::fusion::blur`]), so it resolves relief at its own scale only (docs/science.md,
/// "Images coarser than the grid").
pub(super) fn coarse_pixels_warning(
    labels: &[String],
    used: &[bool],
    pixel_size: &[Option<f64>],
    spacing: f64,
) -> Option<String> {
    let coarse: Vec<String> = labels
        .iter()
        .zip(used)
        .zip(pixel_size)
        .filter_map(|((label, &used), &size)| {
            let size = size.filter(|s| used && *s >= COARSE_PIXELS_FROM * spacing)?;
            Some(format!("{label} ({size:.0} m, {:.1}×)", size / spacing))
        })
        .collect();
    (!coarse.is_empty()).then(|| {
        format!(
            "pixels coarser than the grid's {spacing:.0} m: {}. Each is modelled as the reflectance averaged over its pixel (run.json blur_px), so it constrains relief at its own scale only; the finer detail comes from the observations at the grid's pixel size, and where none covers a part of the region, the grid there is finer than anything its images resolve (docs/science.md, \"Images coarser than the grid\"). Add observations at the grid's pixel size, or use a grid as coarse as the coarsest ([grid] resolution_m)",
            coarse.join(", ")
        )
    })
}

/// How observation `k`'s gain was fixed, in words: estimated relative to the first observation
/// of its overlapping group (`reference`, [`fusion::gains::GainEstimate`]), 1 by
/// definition for that one, assumed 1 where it overlaps no other, or none where the
/// observation was not used (`usage`).
pub(super) fn gain_source(
    k: usize,
    reference: Option<usize>,
    usage: Usage,
    labels: &[String],
) -> String {
    match (usage, reference) {
        (Usage::OffRegion, _) => {
            "none: the observation does not reach the region and was not used".into()
        }
        (Usage::Unused, _) => "none: the observation covers the region but was used nowhere".into(),
        _ if k == 0 => "1 by definition: the first observation listed is the reference".into(),
        (Usage::Used, None) => "assumed 1: the observation overlaps no other on the region".into(),
        (Usage::Used, Some(r)) if r == k => "1 by definition: the first of a group of observations that overlaps none listed before it (its gain is not tied to the first observation's)".into(),
        (Usage::Used, Some(r)) => format!(
            "estimated where the observations overlap, relative to observation {} ({})",
            r + 1,
            labels.get(r).map_or("?", String::as_str)
        ),
    }
}

/// A warning where the observations used on the region fall into more than one group that
/// overlap none of the others: gains are estimated within a group and assumed equal between
/// groups, so the albedo may step where two groups meet. `reference` as in [`gain_source`].
pub(super) fn gain_groups_warning(
    labels: &[String],
    used: &[bool],
    reference: &[Option<usize>],
) -> Option<String> {
    let mut groups: Vec<(usize, Vec<&str>)> = Vec::new();
    for (k, label) in labels.iter().enumerate() {
        if !used.get(k).copied().unwrap_or(false) {
            continue;
        }
        let root = reference.get(k).copied().flatten().unwrap_or(k);
        match groups.iter_mut().find(|(r, _)| *r == root) {
            Some((_, members)) => members.push(label),
            None => groups.push((root, vec![label])),
        }
    }
    (groups.len() > 1).then(|| {
        let list: Vec<String> = groups
            .iter()
            .map(|(_, m)| format!("[{}]", m.join(", ")))
            .collect();
        format!(
            "the observations form {} groups that do not overlap one another on the region ({}): their gains are estimated within a group and assumed equal between groups, so the albedo may step where two groups meet; an observation overlapping both would tie them",
            groups.len(),
            list.join("; ")
        )
    })
}

/// [`Metrics`] gathered band by band.
#[derive(Default)]
pub(super) struct MetricsAcc {
    pub(super) n: usize,
    pub(super) phot: usize,
    pub(super) res: (f64, usize),
    pub(super) alb: (f64, usize),
    pub(super) dh2: f64,
    pub(super) hmin: f64,
    pub(super) hmax: f64,
}

impl MetricsAcc {
    pub(super) fn new() -> Self {
        MetricsAcc {
            hmin: f64::INFINITY,
            hmax: f64::NEG_INFINITY,
            ..Default::default()
        }
    }

    /// Add pixels: the layers in [`TILE_LAYERS`] order.
    pub(super) fn add(&mut self, l: &[Array2<f64>; 7]) {
        let [h, a, r, m, d, _, _] = l;
        self.n += h.len();
        self.phot += m.iter().filter(|&&v| v == 0.0).count();
        for (x, acc) in [(r, &mut self.res), (a, &mut self.alb)] {
            for &v in x.iter().filter(|v| v.is_finite()) {
                acc.0 += v;
                acc.1 += 1;
            }
        }
        self.dh2 += h.iter().zip(d).map(|(a, b)| (a - b) * (a - b)).sum::<f64>();
        self.hmin = h.iter().copied().fold(self.hmin, f64::min);
        self.hmax = h.iter().copied().fold(self.hmax, f64::max);
    }

    pub(super) fn finish(&self) -> Metrics {
        let mean = |(s, k): (f64, usize)| if k == 0 { f64::NAN } else { s / k as f64 };
        Metrics {
            pixels: self.n,
            photometric_fraction: self.phot as f64 / self.n as f64,
            residual_mean: mean(self.res),
            height_change_rms_m: (self.dh2 / self.n as f64).sqrt(),
            height_min_m: self.hmin,
            height_max_m: self.hmax,
            albedo_mean: mean(self.alb),
        }
    }
}

/// Each input file with its size and SHA-256, in order.
pub(super) fn checksums(files: &[PathBuf], progress: &Progress) -> Result<Vec<InputFile>> {
    progress.steps("checksums", files.len() as u64);
    let v = files
        .iter()
        .map(|f| {
            let bytes = std::fs::metadata(f).map_err(|e| Error::io(f, e))?.len();
            let sha256 = file_sha256(f)?;
            progress.step(&format!("sha256 {}", f.display()));
            Ok(InputFile {
                path: f.clone(),
                bytes,
                sha256,
            })
        })
        .collect::<Result<Vec<_>>>();
    progress.finish();
    v
}

/// Write `run.json` into `out`, atomically.
pub(super) fn write_record(out: &Path, record: &RunRecord) -> Result<PathBuf> {
    let path = out.join("run.json");
    let text = serde_json::to_string_pretty(record).map_err(|e| json_err(&path, e))?;
    write_atomic(&path, text.as_bytes())?;
    Ok(path)
}

/// Rows `b0..b1` of the stored layers ([`TILE_LAYERS`]), blended from every tile that covers
/// them with the tiles' weights ([`tiling::weight`]): the weighted mean of the finite values,
/// NaN where no tile has one; the mask and the observation counts rounded to whole numbers,
/// the residual no-data wherever the mask is not [`MASK_FUSED`].
fn blend_band(
    out: &Path,
    plan: &Plan,
    heads: &[(TileRecord, u64)],
    b0: usize,
    b1: usize,
) -> Result<[Array2<f64>; 7]> {
    let (rows, cols) = (plan.grid.rows, plan.grid.cols);
    let mut acc: Vec<Array2<f64>> = (0..TILE_LAYERS.len())
        .map(|_| Array2::zeros((b1 - b0, cols)))
        .collect();
    let mut wsum = acc.clone();
    for (t, (rec, data)) in plan.tiles.iter().zip(heads) {
        let e = rec.ext;
        let (lo, hi) = (b0.max(e.r0), b1.min(e.r0 + e.rows));
        if lo >= hi {
            continue;
        }
        let w = Array2::from_shape_fn((hi - lo, e.cols), |(r, c)| {
            tiling::weight(t, rows, cols, plan.blend as f64, lo + r, e.c0 + c)
        });
        let path = tile_path(out, t.id);
        for k in 0..TILE_LAYERS.len() {
            let v = read_tile_rows(&path, *data, &e, k, lo - e.r0, hi - e.r0)?;
            let v = Array2::from_shape_vec((hi - lo, e.cols), v).expect("rows of the tile");
            let mut a = acc[k].slice_mut(s![lo - b0..hi - b0, e.c0..e.c0 + e.cols]);
            let mut ws = wsum[k].slice_mut(s![lo - b0..hi - b0, e.c0..e.c0 + e.cols]);
            Zip::from(&mut a)
                .and(&mut ws)
                .and(&v)
                .and(&w)
                .for_each(|a, ws, &v, &w| {
                    if w > 0.0 && v.is_finite() {
                        *a += w * v as f64;
                        *ws += w;
                    }
                });
        }
    }
    let mut layers: Vec<Array2<f64>> = acc
        .iter()
        .zip(&wsum)
        .map(|(a, w)| {
            Zip::from(a)
                .and(w)
                .map_collect(|&a, &w| if w > 0.0 { a / w } else { f64::NAN })
        })
        .collect();
    // Mask codes: the nearest whole number across a blend (tiles agree on whether an
    // image sees a pixel, so only 0 and 1 ever meet, and a tie counts as not
    // photometric); the residual is no-data wherever the code is not 0.
    layers[3].mapv_inplace(f64::round);
    let mask = layers[3].clone();
    Zip::from(&mut layers[2]).and(&mask).for_each(|r, &m| {
        if m != MASK_FUSED {
            *r = f64::NAN;
        }
    });
    // Observation counts: the nearest whole number across a blend.
    layers[6].mapv_inplace(f64::round);
    Ok(layers.try_into().expect("seven layers"))
}

/// run.json's record of each observation: its gain and how it was fixed, gain trend, noise
/// weight, footprint and photometric fraction on the region (`sanity`, `usage`),
/// registration, pixel size and blur, and mean Sun.
fn observation_records(
    inputs: &Inputs,
    plan: &Plan,
    sanity: &Sanity,
    usage: &[Usage],
    labels: &[String],
) -> Vec<ObservationRecord> {
    let blur = plan.blur_px();
    inputs
        .obs
        .iter()
        .enumerate()
        .map(|(k, ob)| ObservationRecord {
            label: ob.label_path.clone(),
            gain: plan.gains.get(k).copied().unwrap_or(1.0),
            gain_source: gain_source(
                k,
                plan.gain_reference.get(k).copied().flatten(),
                usage.get(k).copied().unwrap_or(Usage::OffRegion),
                labels,
            ),
            gain_trend: plan.gain_trends.get(k).copied().flatten(),
            noise_weight: plan.noise_weights.get(k).copied().unwrap_or(1.0),
            footprint_pixels: sanity.observations.get(k).map_or(0, |o| o.footprint_pixels),
            photometric_fraction: sanity
                .observations
                .get(k)
                .map_or(0.0, |o| o.photometric_fraction),
            registration: plan.registration.get(k).cloned(),
            pixel_size_m: plan.pixel_size_m.get(k).copied().flatten(),
            blur_px: blur.get(k).copied().unwrap_or(0.0),
            sun: plan
                .sun_deg
                .get(k)
                .copied()
                .flatten()
                .map(|[az, el]| MeanSun {
                    azimuth_deg: az,
                    elevation_deg: el,
                    elevation_range_deg: plan.sun_elevation_range_deg.get(k).copied().flatten(),
                }),
            sun_ephemeris: match plan.sun_ephemeris.get(k).copied().flatten() {
                Some(c) => SunEphemeris::Checked(c),
                None => {
                    SunEphemeris::NotChecked("not checked: the label gives no START_TIME".into())
                }
            },
            dem_vs_loc: plan.dem_vs_loc.get(k).copied().flatten(),
            column_striping: plan.striping.get(k).copied().flatten().map(|estimate| {
                ColumnStriping {
                    estimate,
                    applied: plan.swaths.get(k).is_some_and(|s| s.column_gains.is_some()),
                }
            }),
        })
        .collect()
}

/// Every tile of the plan, finished: its record and where its data start
/// ([`done_tile`]); an error listing the tiles missing, failed or damaged otherwise.
fn done_tiles(out: &Path, plan: &Plan, progress: &Progress) -> Result<Vec<(TileRecord, u64)>> {
    let found: Vec<Option<(TileRecord, u64)>> = plan
        .tiles
        .iter()
        .map(|t| done_tile(&tile_path(out, t.id), &plan.key, Some(progress)))
        .collect();
    let missing: Vec<usize> = plan
        .tiles
        .iter()
        .zip(&found)
        .filter(|(_, f)| f.is_none())
        .map(|(t, _)| t.id)
        .collect();
    if !missing.is_empty() {
        return Err(Error::Usage(format!(
            "cannot mosaic: {} of {} tiles are missing, failed or damaged: {} (run them with --tile, then --mosaic)",
            missing.len(),
            plan.tiles.len(),
            tile_spec(&missing, ", ")
        )));
    }
    Ok(found.into_iter().flatten().collect())
}

/// Each product layer's COG writer, with the stored layer ([`TILE_LAYERS`] index) it takes.
type LayerWriters = Vec<(usize, CogWriter)>;

/// A COG writer for each layer of `[output] layers`, in its order, with the stored layer it
/// takes ([`stored_index`]), its description, unit and the products' metadata `meta` (a DEM's
/// with its vertical reference); and the layers' paths.
fn layer_writers(
    o: &Orbital,
    plan: &Plan,
    meta: &[(&'static str, String)],
) -> Result<(LayerWriters, Vec<PathBuf>)> {
    let mut writers = Vec::new();
    let mut outputs = Vec::new();
    for &l in &o.output.layers {
        let k = stored_index(l);
        let (description, unit) = layer_info(l, true);
        let description = match (l, &o.photometry) {
            (Layer::Albedo, ModelSpec::Hapke(_)) => format!(
                "Hapke single-scattering albedo w at {} nm",
                o.inputs.wavelength_nm
            ),
            _ => description.to_string(),
        };
        let mut items = meta.to_vec();
        if matches!(l, Layer::Dem | Layer::InputDem) {
            items.extend([
                ("VERTICAL_REFERENCE", "sphere".to_string()),
                (
                    "REFERENCE_RADIUS_M",
                    format!("{}", crate::grid::MOON_RADIUS_M),
                ),
                ("HEIGHT_KIND", "height above reference".to_string()),
            ]);
        }
        let path = o.output.directory.join(format!("{}.tif", l.name()));
        let info = BandInfo {
            description: &description,
            unit,
            metadata: &items,
        };
        writers.push((
            k,
            CogWriter::create_as(
                &path,
                Some(&plan.grid),
                plan.grid.cols,
                plan.grid.rows,
                &info,
                Container::Auto,
                sample_format(l),
            )?,
        ));
        outputs.push(path);
    }
    Ok((writers, outputs))
}

/// Blend the finished tiles (`heads`) into the layers' writers band by band (memory is one
/// band of rows, whatever the region's size) and finish the GeoTIFFs; returns the metrics
/// over the layers and the block means the quick look shows, in `TILE_LAYERS` order.
fn blend_tiles(
    out: &Path,
    plan: &Plan,
    heads: &[(TileRecord, u64)],
    mut writers: Vec<(usize, CogWriter)>,
    progress: &Progress,
) -> Result<(MetricsAcc, Vec<Thumbnail>)> {
    let (rows, cols) = (plan.grid.rows, plan.grid.cols);
    let mut stats = MetricsAcc::new();
    let mut thumbs: Vec<Thumbnail> = (0..TILE_LAYERS.len())
        .map(|_| Thumbnail::new(rows, cols, QUICKLOOK_SIDE))
        .collect();
    progress.steps("mosaic", rows.div_ceil(MOSAIC_BAND) as u64);
    for b0 in (0..rows).step_by(MOSAIC_BAND) {
        let b1 = (b0 + MOSAIC_BAND).min(rows);
        let layers = blend_band(out, plan, heads, b0, b1)?;
        stats.add(&layers);
        for (t, l) in thumbs.iter_mut().zip(&layers) {
            t.add(b0, l.view());
        }
        for (k, w) in &mut writers {
            w.push(layers[*k].view())?;
        }
        progress.step(&format!("rows {b0}..{b1}"));
    }
    progress.finish();
    progress.stage("writing GeoTIFFs");
    for (_, w) in writers {
        w.finish()?;
    }
    progress.finish();
    Ok((stats, thumbs))
}

/// The run's sanity figures from its tiles' sums, with the warnings about observations that
/// share no gain reference, pixels coarser than the grid and low Suns; and how each
/// observation (`labels`) was used.
fn run_sanity<'a>(
    plan: &Plan,
    records: impl IntoIterator<Item = &'a TileRecord>,
    labels: &[String],
) -> (Sanity, Vec<Usage>) {
    let mut sums = TileSums::default();
    records.into_iter().for_each(|r| sums.add(&r.sanity));
    let reached: Vec<bool> = (0..labels.len())
        .map(|k| plan.on_grid_pixels.get(k).is_some_and(|&n| n > 0))
        .collect();
    let mut sanity = Sanity::from_sums(&sums, labels, &reached);
    let usage: Vec<Usage> = sanity.observations.iter().map(|o| o.usage()).collect();
    let used: Vec<bool> = usage.iter().map(|&u| u == Usage::Used).collect();
    sanity
        .warnings
        .extend(gain_groups_warning(labels, &used, &plan.gain_reference));
    sanity.warnings.extend(coarse_pixels_warning(
        labels,
        &used,
        &plan.pixel_size_m,
        plan.grid.spacing,
    ));
    sanity.warnings.extend(low_sun_warning(
        labels,
        &used,
        &plan.sun_deg,
        &plan.sun_elevation_range_deg,
    ));
    sanity
        .warnings
        .extend(dem_datum_warning(labels, &plan.dem_vs_loc));
    (sanity, usage)
}

/// Refuse to write products no observation shaped: where no pixel of any observation was
/// used on the region (every one in shadow, outside the incidence window or beyond the
/// per-pixel maximum; the plan refuses a window that admits no observation's Sun at all),
/// the products would repeat the input DEM under the name of a fusion. The error lists what
/// the run's warnings say of each observation.
fn some_observation_used(sanity: &Sanity) -> Result<()> {
    if sanity.photometric_fraction > 0.0 {
        return Ok(());
    }
    Err(Error::Usage(format!(
        "no pixel of any observation was used on the region (photometric fraction 0), so the products would only repeat the input DEM and none was written: {}. Check [inputs] min_incidence_deg … max_incidence_deg and max_observations_per_pixel against the observations' Suns, and the images themselves",
        sanity.warnings.join("; ")
    )))
}

/// The warning for observations whose LOC heights lie a median of more than
/// [`crate::ingest::MAX_DEM_LOC_OFFSET_M`] from the DEM's at the same points: the DEM is then
/// likely on another reference sphere or in another unit, which the fused DEM inherits.
pub(super) fn dem_datum_warning(
    labels: &[String],
    dem_vs_loc: &[Option<crate::ingest::DemVsLoc>],
) -> Option<String> {
    let off: Vec<String> = labels
        .iter()
        .zip(dem_vs_loc)
        .filter_map(|(label, c)| {
            let c = c.filter(|c| c.median_m.abs() > crate::ingest::MAX_DEM_LOC_OFFSET_M)?;
            Some(format!(
                "{label} ({:+.0} m, spread {:.0} m, {} px)",
                c.median_m, c.mad_m, c.pixels
            ))
        })
        .collect();
    (!off.is_empty()).then(|| {
        format!(
            "the observations' own surface heights (LOC radius − 1737.4 km) lie a median of more than {:.0} m from the DEM's at the same points: {}. On real M3 products over LOLA they agree within a few tens of metres; the DEM's heights are likely above another sphere than 1737.4 km, or in another unit (kilometres, feet), and the fused DEM keeps them so (docs/formats.md, \"The DEM against LOC\"). Check the DEM's datum and unit",
            crate::ingest::MAX_DEM_LOC_OFFSET_M,
            off.join(", ")
        )
    })
}

/// Blend every tile into the products and write the run record. `files`: the inputs with
/// their checksums if they were hashed already ([`checksums`]), else they are hashed here,
/// once every tile is known to be there.
pub(super) fn mosaic(
    o: &Orbital,
    wf: &Workflow,
    inputs: &Inputs,
    plan: &Plan,
    files: Option<Vec<InputFile>>,
    progress: &Progress,
) -> Result<(Vec<PathBuf>, PathBuf, Sanity)> {
    let out = &o.output.directory;
    let heads = done_tiles(out, plan, progress)?;
    let files = match files {
        Some(f) => {
            progress.note(&format!(
                "checksums: {} input files, hashed while the tiles ran",
                f.len()
            ));
            f
        }
        None => checksums(&inputs.files()?, progress)?,
    };
    // What the products are, from the inputs' contents and the parameters only (no path or
    // time: the same inputs give the same files wherever they lie and the run writes).
    let key = run_key(wf, &files);
    let labels = inputs.labels();
    let (sanity, usage) = run_sanity(plan, heads.iter().map(|(r, _)| r), &labels);
    some_observation_used(&sanity)?;
    let meta = product_metadata(o, inputs, plan, &key);
    let (writers, mut outputs) = layer_writers(o, plan, &meta)?;
    let (stats, thumbs) = blend_tiles(out, plan, &heads, writers, progress)?;
    let ql = out.join("quicklook.png");
    write_quicklook(&ql, &thumbs, plan.grid.spacing, o.inputs.wavelength_nm)?;
    outputs.push(ql);
    let records: Vec<TileRecord> = heads.into_iter().map(|(r, _)| r).collect();
    let record = RunRecord {
        tool: "sfsfuse",
        version: crate::BUILD,
        workflow: wf,
        run_key: key,
        inputs: files,
        grid: Some(plan.grid),
        crs_wkt: Some(plan.grid.crs.wkt()),
        halo: Some(plan.halo),
        intensity_scale: Some(plan.intensity_scale),
        dem_psf_sigma: Some(plan.dem_psf_sigma),
        resolution_source: Some(plan.resolution_source.clone()),
        dem_resolution_m: Some(plan.dem_resolution_m),
        dem_resolution_source: Some(plan.dem_resolution_source.clone()),
        sigma_dem: Some(plan.sigma_dem),
        dem_track_weight: Some(plan.dem_track_weight),
        dem_track_source: Some(plan.dem_track_source.clone()),
        high_sun_east_west: Some(plan.high_sun_east_west),
        high_sun_east_west_source: Some(plan.high_sun_east_west_source.clone()),
        dem_tracks: plan
            .dem_tracks
            .iter()
            .map(|t| {
                t.as_ref().map(|t| DemTracks {
                    estimate: t.summary,
                    applied: o.inputs.dem_destripe,
                })
            })
            .collect(),
        membrane: Some(plan.membrane.clone()),
        reference: plan.reference.clone(),
        threads: rayon::current_num_threads(),
        tiles: records,
        metrics: stats.finish(),
        sanity: Some(sanity.clone()),
        observations: observation_records(inputs, plan, &sanity, &usage, &labels),
        outputs: outputs.clone(),
    };
    let path = write_record(out, &record)?;
    Ok((outputs, path, sanity))
}
