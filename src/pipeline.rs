//! `sfsfuse run`: a workflow from mission products to fused GeoTIFFs (docs/workflows.md).
//!
//! Orbital runs go in three steps, each restartable:
//!
//! 1. **Plan** (`<out>/plan.json`): the grid, the tiles, and what needs the whole region — the
//!    intensity scale Ī (the mean reflectance of every valid swath pixel on the grid) and a
//!    line index of each swath. Keyed by a hash of the tool version, the resolved workflow
//!    and each input file's size and modification time; a plan with another key is replaced.
//! 2. **Tiles** (`<out>/tiles/tile_NNNNN.sfstile`): each tile reads only its window of the
//!    products, fuses it with the run-wide Ī, and writes its layers over core + halo in one
//!    atomic file. A tile whose file exists with the plan's key is skipped, so reruns and
//!    resumed runs (after kill -9) redo only missing tiles. Tiles are independent: `--tile N`
//!    runs one anywhere (cluster tasks).
//! 3. **Mosaic**: the tiles blended with [`tiling::weight`] (a partition of unity over the
//!    inner half of the halos) into `dem.tif`, `albedo.tif`, `residual.tif`, `mask.tif`
//!    (and `input_dem.tif` on request), then the run record `run.json`.
//!
//! Results are bit-identical for any thread count: tiles are independent, each fusion is
//! deterministic, and the mosaic sums tiles in id order.

use crate::error::{Error, Result};
use crate::export::{BandInfo, CogWriter, Container, SampleFormat};
use crate::fusion::{self, Directions, FusionParams, Problem, StageReport};
use crate::grid::{Crs, Grid, Projector};
use crate::ingest::{self, SwathIndex};
use crate::output::OutputDir;
use crate::photometry::{ModelSpec, ReflectanceModel};
use crate::progress::Progress;
use crate::quicklook::Thumbnail;
use crate::raster::write_atomic;
use crate::sanity::{Sanity, TileSums};
use crate::tiling::{self, Tile, Window};
use crate::workflow::{Lab, Layer, Orbital, RegionKind, Workflow};
use ndarray::{s, Array2, Zip};
use pds::lola::LolaDem;
use pds::m3::Observation;
use pds::solar::SolarSpectrum;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What `run` is asked to do.
#[derive(Debug, Clone, Default)]
pub struct Request {
    /// Only these tiles (and no mosaic); `None` = every pending tile, then the mosaic.
    pub tiles: Option<Vec<usize>>,
    /// Only the mosaic (every tile must be done).
    pub mosaic_only: bool,
}

/// The opened inputs of an orbital run.
struct Inputs {
    obs: Vec<Observation>,
    lola: Vec<Dem>,
    solar: SolarSpectrum,
    model: Box<dyn ReflectanceModel>,
}

impl Inputs {
    /// Fetch what `[fetch]` lists (cached files are not downloaded again), then open.
    fn open(o: &Orbital, progress: &Progress) -> Result<Self> {
        if let Some(f) = &o.fetch {
            progress.stage("fetching inputs");
            crate::fetch::fetch(&f.products, &f.directory, &f.sources, progress)?;
            progress.finish();
        }
        let obs: Vec<Observation> = o
            .inputs
            .m3
            .iter()
            .map(|p| Observation::open(p))
            .collect::<std::result::Result<_, _>>()?;
        let solar = SolarSpectrum::read(&o.inputs.solar_spectrum)?;
        check_solar_mode(&solar, &obs)?;
        Ok(Inputs {
            obs,
            lola: o
                .inputs
                .lola
                .iter()
                .map(|p| Dem::open(p))
                .collect::<Result<_>>()?,
            solar,
            model: o.photometry.build(),
        })
    }

    /// Every file the run reads.
    fn files(&self) -> Result<Vec<PathBuf>> {
        let mut v = Vec::new();
        for o in &self.obs {
            v.push(o.label_path.clone());
            v.push(o.rdn.path.clone());
            for part in ["LOC", "OBS"] {
                v.push(o.part(part)?.path);
            }
        }
        for d in &self.lola {
            match d {
                Dem::Pds(d) => v.extend([d.label_path.clone(), d.raster.path.clone()]),
                Dem::GeoTiff(d) => v.push(d.path.clone()),
            }
        }
        v.push(self.solar.path.clone());
        v.dedup();
        Ok(v)
    }
}

/// The solar table must follow the observations' band sampling: M3's GLOBAL and TARGET modes
/// have different bands, and a table of the other mode gives the wrong irradiance for the
/// band (its band passes differ) without any other sign.
fn check_solar_mode(solar: &SolarSpectrum, obs: &[Observation]) -> Result<()> {
    let Some(table) = solar.mode() else {
        return Ok(());
    };
    let name = |m: pds::m3::Mode| match m {
        pds::m3::Mode::Global => "GLOBAL",
        pds::m3::Mode::Target => "TARGET",
    };
    for o in obs {
        if o.mode != table {
            return Err(Error::Usage(format!(
                "{} is a {}-mode solar spectrum table ({} rows) but {} has INSTRUMENT_MODE_ID = {}: give [inputs] solar_spectrum the {} table (M3{}20110224_RFL_SOLAR_SPEC.TAB)",
                solar.path.display(),
                name(table),
                solar.rows.len(),
                o.label_path.display(),
                name(o.mode),
                name(o.mode),
                if o.mode == pds::m3::Mode::Global { "G" } else { "T" }
            )));
        }
    }
    Ok(())
}

/// An input DEM: a LOLA GDR (PDS3 label) or a GeoTIFF on the Moon sphere.
enum Dem {
    Pds(LolaDem),
    GeoTiff(ingest::GeoTiffDem),
}

impl Dem {
    /// `.tif`/`.tiff` is a GeoTIFF; anything else a PDS3 label.
    fn open(p: &Path) -> Result<Dem> {
        let ext = p
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        Ok(if ext == "tif" || ext == "tiff" {
            Dem::GeoTiff(ingest::GeoTiffDem::open(p)?)
        } else {
            Dem::Pds(LolaDem::open(p)?)
        })
    }

    fn on_grid(
        &self,
        geo: &crate::grid::Geographic,
        method: crate::grid::Interpolation,
    ) -> Result<Array2<f64>> {
        match self {
            Dem::Pds(d) => ingest::lola_on_grid(d, geo, method),
            Dem::GeoTiff(d) => ingest::geotiff_on_grid(d, geo, method),
        }
    }

    /// Pixel size, metres.
    fn pixel_m(&self) -> f64 {
        match self {
            Dem::Pds(d) => d.map_scale_m,
            Dem::GeoTiff(d) => d.pixel_m(),
        }
    }

    /// The spacing of the independent heights behind the DEM at latitude `lat` (degrees), and
    /// why. A LOLA-only GDR (`LDEM_*`) is gridded from altimeter tracks and interpolated
    /// between them: where its pixels are finer than the gaps between tracks, MAP_SCALE
    /// overstates its resolution. The gaps are about [`LOLA_TRACK_GAP_M`] at the equator and
    /// shrink with cos(latitude) as the polar orbits converge. Other DEMs (SLDEM2015, merged
    /// with stereo and not interpolated; GeoTIFFs) are taken at their pixel size.
    fn effective_resolution(&self, lat: f64) -> (f64, String) {
        let pixel = self.pixel_m();
        let Dem::Pds(d) = self else {
            return (pixel, "GeoTIFF pixel size".into());
        };
        let id = d
            .label
            .get("PRODUCT_ID")
            .and_then(|v| v.as_str())
            .map(str::to_string)
            .or_else(|| {
                d.label_path
                    .file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
            })
            .unwrap_or_default()
            .to_ascii_uppercase();
        if !id.starts_with("LDEM") {
            return (pixel, format!("{id}: MAP_SCALE"));
        }
        let gap = LOLA_TRACK_GAP_M * lat.to_radians().cos().abs();
        if gap > pixel {
            (
                gap,
                format!("{id}: LOLA track gap {LOLA_TRACK_GAP_M} m × cos(latitude {lat:.2}°), coarser than MAP_SCALE {pixel:.1} m"),
            )
        } else {
            (
                pixel,
                format!("{id}: MAP_SCALE (coarser than the LOLA track gap {gap:.0} m)"),
            )
        }
    }
}

/// Typical gap between LOLA ground tracks at the equator, metres: after years of polar orbits
/// the tracks still leave kilometre-scale gaps at low latitudes that gridded products fill by
/// interpolation (docs/science.md, "The DEM's effective resolution").
pub const LOLA_TRACK_GAP_M: f64 = 1000.0;

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
    /// Ī: mean valid reflectance on the grid, sr⁻¹.
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
    /// One per M3 observation, in input order.
    pub swaths: Vec<SwathIndex>,
    /// Radiometric gain g_k of each observation, relative to the first of its overlapping
    /// group (1 where it overlaps no other).
    #[serde(default)]
    pub gains: Vec<f64>,
    /// Noise weight ν_k of each observation (docs/science.md, "Several observations").
    #[serde(default)]
    pub noise_weights: Vec<f64>,
}

/// The most pixels the gain estimate looks at: the run's grid is decimated to at most this.
const GAIN_PIXELS: usize = 1 << 20;

/// The gains of the observations, estimated once for the whole run (tiles must agree on them)
/// by [`fusion::observations::estimate_gains`] on the grid decimated to at most
/// [`GAIN_PIXELS`], over the input DEM.
fn run_gains(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    swaths: &[SwathIndex],
    scale: f64,
) -> Result<Vec<f64>> {
    let f = ((grid.rows * grid.cols) as f64 / GAIN_PIXELS as f64)
        .sqrt()
        .ceil()
        .max(1.0) as usize;
    let coarse = Grid {
        rows: grid.rows.div_ceil(f),
        cols: grid.cols.div_ceil(f),
        spacing: grid.spacing * f as f64,
        ..*grid
    };
    let pr = projector(&coarse.crs)?;
    let geo = coarse.geographic(&pr);
    let mut shots = Vec::new();
    for (k, (obs, index)) in inputs.obs.iter().zip(swaths).enumerate() {
        if index.lines_for(&coarse).is_none() {
            continue;
        }
        let img = ingest::m3_on_grid(
            obs,
            &inputs.solar,
            o.inputs.wavelength_nm,
            &coarse,
            &pr,
            &geo,
            Some(index),
        )?;
        shots.push((k, img));
    }
    let mut dem = Array2::from_elem((coarse.rows, coarse.cols), f64::NAN);
    for d in &inputs.lola {
        let Ok(h) = d.on_grid(&geo, o.grid.dem_interpolation) else {
            continue;
        };
        Zip::from(&mut dem).and(&h).for_each(|a, &b| {
            if a.is_nan() {
                *a = b;
            }
        });
    }
    fill_holes(&mut dem);
    if !dem.iter().all(|v| v.is_finite()) {
        // No DEM on the grid at all: the tiles will say so; gains cannot be estimated.
        return Ok(vec![1.0; inputs.obs.len()]);
    }
    let problem = Problem {
        observations: shots
            .iter()
            .map(|(_, img)| fusion::Observation {
                image: img.reflectance.view(),
                sun: Directions::PerPixel(img.sun.clone()),
                view: Directions::PerPixel(img.view.clone()),
            })
            .collect(),
        dem: dem.view(),
        spacing: coarse.spacing,
        dem_psf_sigma: 0.0,
        model: inputs.model.as_ref(),
        intensity_scale: Some(scale),
        gains: None,
        noise_weights: None,
        selection: o.inputs.selection(),
    };
    let mut gains = vec![1.0; inputs.obs.len()];
    if problem.observations.len() > 1 {
        let w = fusion::observations::weights(
            &problem,
            vec![1.0; problem.observations.len()],
            scale,
            None,
            o.solver.shadow_threshold,
            0.0,
        );
        let g = fusion::observations::estimate_gains(&problem, &w.usable, dem.view());
        for ((k, _), g) in shots.iter().zip(g) {
            gains[*k] = g;
        }
    }
    Ok(gains)
}

/// A finished tile's record (the header of its file, and a row of the run record).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TileRecord {
    pub id: usize,
    pub key: String,
    pub core: Window,
    pub ext: Window,
    /// "fused", or "no_image" where no pixel of the tile carries an observation (the tile
    /// then keeps the input DEM).
    pub status: String,
    pub photometric_pixels: usize,
    /// Sums behind the run's sanity figures, over the core's pixels.
    #[serde(default)]
    pub sanity: TileSums,
    /// SHA-256 of the layer bytes that follow the header: a tile whose layers do not match
    /// is damaged and is recomputed, never mosaicked.
    #[serde(default)]
    pub layers_sha256: String,
    pub iterations: usize,
    pub seconds: f64,
    pub stages: Vec<StageReport>,
}

/// Layers stored per tile, in file order.
const TILE_LAYERS: [Layer; 7] = [
    Layer::Dem,
    Layer::Albedo,
    Layer::Residual,
    Layer::Mask,
    Layer::InputDem,
    Layer::Image,
    Layer::Observations,
];
const TILE_MAGIC: &[u8; 8] = b"SFSTILE1";
/// Most tiles a run plans (a 2³¹-pixel region in 1024-px tiles is 2048; tiny tiles over a
/// large region would make a plan of millions of windows).
pub const MAX_TILES: usize = 20_000;
/// Rows the mosaic blends at a time.
const MOSAIC_BAND: usize = 256;

/// The summary `run` returns (and prints).
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    pub output_directory: PathBuf,
    pub tiles_total: usize,
    pub tiles_run: usize,
    pub tiles_skipped: usize,
    pub mosaic: bool,
    pub outputs: Vec<PathBuf>,
    pub record: Option<PathBuf>,
    /// The sanity figures of the whole run (when the mosaic was written).
    pub sanity: Option<Sanity>,
    /// Wall time of this invocation, seconds.
    #[serde(default)]
    pub seconds: f64,
}

impl RunSummary {
    pub fn table(&self) -> String {
        let mut s = format!(
            "finished in {:.1} s; tiles: {} total, {} run now, {} already done\n",
            self.seconds, self.tiles_total, self.tiles_run, self.tiles_skipped
        );
        for o in &self.outputs {
            s.push_str(&format!("wrote {}\n", o.display()));
        }
        if let Some(r) = &self.record {
            s.push_str(&format!("run record {}\n", r.display()));
        }
        if let Some(x) = &self.sanity {
            s.push_str(&x.table());
        }
        if !self.mosaic {
            s.push_str("mosaic not written (run without --tile, or with --mosaic, when every tile is done)\n");
        }
        s
    }
}

fn json_err(path: &Path, e: serde_json::Error) -> Error {
    Error::Usage(format!("{}: {e}", path.display()))
}

/// Hex SHA-256 of `bytes`.
fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// Hex SHA-256 of a file's contents, streamed.
pub fn file_sha256(path: &Path) -> Result<String> {
    crate::raster::file_digest::<Sha256>(path)
}

/// The key that ties plan and tiles to one workflow and one set of input files.
fn run_key(wf: &Workflow, files: &[PathBuf]) -> Result<String> {
    let mut text = format!("sfsfuse {}\n", env!("CARGO_PKG_VERSION"));
    text.push_str(&serde_json::to_string(wf).expect("workflows serialise"));
    if let Workflow::Orbital(o) = wf {
        text.push_str(&format!("\nsigma_dem_given={}", o.sigma_dem_given));
    }
    for f in files {
        let m = std::fs::metadata(f).map_err(|e| Error::io(f, e))?;
        let mtime = m
            .modified()
            .ok()
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
            .map_or(0, |d| d.as_nanos());
        text.push_str(&format!("\n{}:{}:{mtime}", f.display(), m.len()));
    }
    Ok(sha256_hex(text.as_bytes()))
}

/// The grid spacing of an orbital workflow and where it came from.
fn resolution(o: &Orbital, inputs: &Inputs) -> Result<(f64, String)> {
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

/// The grid of an orbital workflow with spacing `res`.
fn make_grid(o: &Orbital, inputs: &Inputs, res: f64) -> Result<Grid> {
    let usage = |e: crate::grid::GridError| Error::Usage(format!("[grid]/[region]: {e}"));
    match o.region.map(|r| r.kind()).transpose()? {
        Some(RegionKind::LonLat(b)) => {
            let (lon, lat) = b.centre();
            Grid::covering(o.grid.crs((lat, lon)), &b, res).map_err(usage)
        }
        Some(RegionKind::Map([x0, x1, y0, y1])) => {
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
            .map_err(usage)
        }
        None => {
            // The whole swath of the first observation.
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
            // Longitudes in the half-turn that keeps the swath together.
            let spread = |shift: f64| {
                let v = fin.iter().map(|p| (p.0 + shift).rem_euclid(360.0));
                let (a, b) = v.fold((f64::MAX, f64::MIN), |m, x| (m.0.min(x), m.1.max(x)));
                (a - shift, b - shift)
            };
            let (a0, b0) = spread(0.0);
            let (a1, b1) = spread(180.0);
            let (lo0, lo1) = if b0 - a0 <= b1 - a1 {
                (a0, b0)
            } else {
                (a1, b1)
            };
            let (la0, la1) = fin
                .iter()
                .fold((f64::MAX, f64::MIN), |m, p| (m.0.min(p.1), m.1.max(p.1)));
            let centre = (0.5 * (la0 + la1), 0.5 * (lo0 + lo1));
            let crs = o.grid.crs(centre);
            let pr = crs.projector().map_err(usage)?;
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
            .map_err(usage)
        }
    }
}

/// Make the plan, or load it when one with the same key exists.
fn plan(o: &Orbital, wf: &Workflow, inputs: &Inputs, progress: &Progress) -> Result<Plan> {
    let out = &o.output.directory;
    let key = run_key(wf, &inputs.files()?)?;
    let path = out.join("plan.json");
    if let Ok(text) = std::fs::read_to_string(&path) {
        if let Ok(p) = serde_json::from_str::<Plan>(&text) {
            if p.key == key {
                progress.note(&format!("plan: reusing {}", path.display()));
                return Ok(p);
            }
        }
        progress.note(&format!(
            "plan: {} belongs to other inputs or parameters; planning anew",
            path.display()
        ));
    }
    progress.stage("planning: grid, swath index, intensity scale");
    let (res, resolution_source) = resolution(o, inputs)?;
    let grid = make_grid(o, inputs, res)?;
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
    let pr = projector(&grid.crs)?;
    let mut swaths = Vec::new();
    let (mut sum, mut count) = (0.0, 0usize);
    let mut means = Vec::new();
    let mut why = Vec::new();
    for obs in &inputs.obs {
        let s = ingest::survey(obs, &inputs.solar, o.inputs.wavelength_nm, &grid, &pr)?;
        sum += s.sum;
        count += s.count;
        means.push((s.count > 0).then(|| s.sum / s.count as f64));
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
    let centre_lat = pr
        .inverse(
            grid.x0 + 0.5 * grid.cols as f64 * grid.spacing,
            grid.y0 - 0.5 * grid.rows as f64 * grid.spacing,
        )
        .map_or(0.0, |(_, lat)| lat);
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
    let params = FusionParams {
        sigma_dem,
        ..o.solver.clone()
    };
    let halo = o
        .tiling
        .halo
        .unwrap_or_else(|| crate::workflow::auto_halo(&params, dem_psf_sigma));
    let n_tiles = grid.rows.div_ceil(o.tiling.tile_size) * grid.cols.div_ceil(o.tiling.tile_size);
    if n_tiles > MAX_TILES {
        return Err(Error::Usage(format!(
            "[tiling]: {} × {} px in tiles of {} px makes {n_tiles} tiles, more than {MAX_TILES}: raise tile_size or shrink [region]",
            grid.rows, grid.cols, o.tiling.tile_size
        )));
    }
    let tiles = tiling::layout(grid.rows, grid.cols, o.tiling.tile_size, halo);
    let blend = o.tiling.blend.unwrap_or(halo / 2).min(halo);
    let intensity_scale = sum / count as f64;
    let gains = if inputs.obs.len() > 1 {
        progress.stage("planning: radiometric gains where observations overlap");
        run_gains(o, inputs, &grid, &swaths, intensity_scale)?
    } else {
        vec![1.0]
    };
    // ν_k = (Ī/Ī_k)², Ī_k the observation's mean reflectance over its pixels on the grid,
    // corrected by its gain (fusion::observations); 1 for a single observation.
    let noise_weights = if inputs.obs.len() > 1 {
        means
            .iter()
            .zip(&gains)
            .map(|(m, g)| m.map_or(1.0, |m| (intensity_scale * g / m).powi(2)))
            .collect()
    } else {
        vec![1.0]
    };
    let p = Plan {
        version: env!("CARGO_PKG_VERSION").into(),
        key,
        grid,
        halo,
        blend,
        tiles,
        intensity_scale,
        intensity_pixels: count,
        gains,
        noise_weights,
        dem_psf_sigma,
        resolution_source,
        dem_resolution_m,
        dem_resolution_source,
        sigma_dem,
        swaths,
    };
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    write_atomic(
        &path,
        serde_json::to_string_pretty(&p)
            .expect("plans serialise")
            .as_bytes(),
    )?;
    progress.finish();
    progress.note(&format!(
        "plan: {} × {} px at {} m ({}; {}), {} tiles of {} px + {} px halo, Ī = {:.5} sr⁻¹ over {} px; DEM resolution {:.0} m ({}), σ_B {:.2} px, σ_DEM {:.2} px",
        p.grid.rows,
        p.grid.cols,
        p.grid.spacing,
        p.resolution_source,
        p.grid.crs.name(),
        p.tiles.len(),
        o.tiling.tile_size,
        p.halo,
        p.intensity_scale,
        p.intensity_pixels,
        p.dem_resolution_m,
        p.dem_resolution_source,
        p.dem_psf_sigma,
        p.sigma_dem
    ));
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
    Ok(p)
}

fn projector(crs: &Crs) -> Result<Projector> {
    crs.projector().map_err(|e| Error::Usage(e.to_string()))
}

fn tile_path(out: &Path, id: usize) -> PathBuf {
    out.join("tiles").join(format!("tile_{id:05}.sfstile"))
}

/// Read a tile file's header and where its layers start; `None` when absent, unreadable, of
/// the wrong size or not of this plan.
fn tile_header(path: &Path, key: &str) -> Option<(TileRecord, u64)> {
    let mut f = std::fs::File::open(path).ok()?;
    let mut head = [0u8; 16];
    f.read_exact(&mut head).ok()?;
    if &head[..8] != TILE_MAGIC {
        return None;
    }
    let n = u64::from_le_bytes(head[8..16].try_into().ok()?) as usize;
    if n > 64 << 20 {
        return None;
    }
    let mut json = vec![0u8; n];
    f.read_exact(&mut json).ok()?;
    let r: TileRecord = serde_json::from_slice(&json).ok()?;
    let want = 16 + n as u64 + (TILE_LAYERS.len() * r.ext.len() * 4) as u64;
    let len = f.metadata().ok()?.len();
    (r.key == key && len == want).then_some((r, 16 + n as u64))
}

/// A finished tile of this plan whose layers match their checksum: its header and where its
/// layers start. `None` when absent, of another plan, or damaged — a damaged tile is reported
/// through `progress` when one is given, so that its recomputation does not go unexplained.
fn done_tile(path: &Path, key: &str, progress: Option<&Progress>) -> Option<(TileRecord, u64)> {
    let (r, data) = tile_header(path, key)?;
    let digest = (|| -> std::io::Result<String> {
        use std::io::{Seek, SeekFrom};
        let mut f = std::fs::File::open(path)?;
        f.seek(SeekFrom::Start(data))?;
        let mut h = Sha256::new();
        std::io::copy(&mut f, &mut h)?;
        Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
    })();
    match digest {
        Ok(d) if d == r.layers_sha256 => Some((r, data)),
        _ => {
            if let Some(p) = progress {
                p.note(&format!(
                    "{}: its layers do not match the checksum in its header (a damaged file): recomputing it",
                    path.display()
                ));
            }
            None
        }
    }
}

/// Rows `r0..r1` (of the tile's ext window) of layer `k` of a tile file whose layers start at
/// byte `data`.
fn read_tile_rows(
    path: &Path,
    data: u64,
    ext: &Window,
    k: usize,
    r0: usize,
    r1: usize,
) -> Result<Vec<f32>> {
    use std::os::unix::fs::FileExt;
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut buf = vec![0u8; (r1 - r0) * ext.cols * 4];
    let at = data + ((k * ext.len() + r0 * ext.cols) * 4) as u64;
    f.read_exact_at(&mut buf, at)
        .map_err(|e| Error::io(path, e))?;
    Ok(buf
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Run one tile and write its file atomically.
fn run_tile(o: &Orbital, inputs: &Inputs, plan: &Plan, tile: &Tile) -> Result<TileRecord> {
    let t0 = Instant::now();
    let e = tile.ext;
    let grid = plan
        .grid
        .window(e.r0 as isize, e.c0 as isize, e.rows, e.cols);
    let pr = projector(&grid.crs)?;
    let geo = grid.geographic(&pr);
    let dim = (e.rows, e.cols);
    // Every observation that reaches the tile; the `image` layer shows the first one that
    // covers a pixel.
    let mut image = Array2::from_elem(dim, f64::NAN);
    let mut shots = Vec::new();
    for (k, (obs, index)) in inputs.obs.iter().zip(&plan.swaths).enumerate() {
        if index.lines_for(&grid).is_none() {
            continue;
        }
        let mut img = ingest::m3_on_grid(
            obs,
            &inputs.solar,
            o.inputs.wavelength_nm,
            &grid,
            &pr,
            &geo,
            Some(index),
        )?;
        Zip::from(&mut img.reflectance)
            .and(&img.sun)
            .and(&img.view)
            .for_each(|r, s, v| {
                if !(s[2].is_finite() && v[2].is_finite()) {
                    *r = f64::NAN;
                }
            });
        if !img.reflectance.iter().any(|r| r.is_finite()) {
            continue;
        }
        Zip::from(&mut image)
            .and(&img.reflectance)
            .for_each(|i, &r| {
                if i.is_nan() {
                    *i = r;
                }
            });
        shots.push((k, img));
    }
    // The DEM: the first product that covers a pixel.
    let mut dem = Array2::from_elem(dim, f64::NAN);
    for d in &inputs.lola {
        let Ok(h) = d.on_grid(&geo, o.grid.dem_interpolation) else {
            continue;
        };
        Zip::from(&mut dem).and(&h).for_each(|a, &b| {
            if a.is_nan() {
                *a = b;
            }
        });
    }
    if let Some(((r, c), _)) = dem.indexed_iter().find(|(_, v)| !v.is_finite()) {
        let (lon, lat) = (geo.lon[(r, c)], geo.lat[(r, c)]);
        return Err(Error::Usage(format!(
            "tile {}: no LOLA DEM of [inputs] lola covers grid pixel ({}, {}) at lon {lon:.4}, lat {lat:.4} (with the interpolation's support): add a DEM that covers the region or shrink [region]",
            tile.id,
            e.r0 + r,
            e.c0 + c
        )));
    }
    let ids: Vec<usize> = shots.iter().map(|(k, _)| *k).collect();
    let per_obs = |v: &[f64]| {
        ids.iter()
            .map(|&k| v.get(k).copied().unwrap_or(1.0))
            .collect()
    };
    let problem = Problem {
        observations: shots
            .iter()
            .map(|(_, img)| fusion::Observation {
                image: img.reflectance.view(),
                sun: Directions::PerPixel(img.sun.clone()),
                view: Directions::PerPixel(img.view.clone()),
            })
            .collect(),
        dem: dem.view(),
        spacing: grid.spacing,
        dem_psf_sigma: plan.dem_psf_sigma,
        model: inputs.model.as_ref(),
        intensity_scale: Some(plan.intensity_scale),
        gains: Some(per_obs(&plan.gains)),
        noise_weights: Some(per_obs(&plan.noise_weights)),
        selection: o.inputs.selection(),
    };
    let params = FusionParams {
        sigma_dem: plan.sigma_dem,
        ..o.solver.clone()
    };
    let core = (
        tile.core.r0 - e.r0,
        tile.core.r0 - e.r0 + tile.core.rows,
        tile.core.c0 - e.c0,
        tile.core.c0 - e.c0 + tile.core.cols,
    );
    let n_obs = inputs.obs.len();
    let fused = if problem.observations.is_empty() {
        Err(fusion::FusionError::NoObservations)
    } else {
        fusion::fuse(&problem, &params)
    };
    let (status, layers, stages, photometric, sanity) = match fused {
        Ok(mut f) => {
            f.height = fusion::anchor(
                &f.height,
                dem.view(),
                f.support.view(),
                plan.halo as f64 / 3.0,
            );
            let sanity = TileSums::of_tile(&problem, &f, &f.height, &ids, n_obs, core);
            let n = f.photometric.iter().filter(|&&b| b).count();
            let mask = f.photometric.mapv(|b| if b { 0.0 } else { 1.0 });
            (
                "fused",
                [
                    f.height,
                    f.albedo,
                    f.residual,
                    mask,
                    dem.clone(),
                    image.clone(),
                    f.observations.mapv(f64::from),
                ],
                f.stages,
                n,
                sanity,
            )
        }
        Err(fusion::FusionError::NoObservations) => {
            let nan = Array2::from_elem(dim, f64::NAN);
            (
                "no_image",
                [
                    dem.clone(),
                    nan.clone(),
                    nan,
                    Array2::ones(dim),
                    dem.clone(),
                    image.clone(),
                    Array2::zeros(dim),
                ],
                Vec::new(),
                0,
                TileSums::no_image(tile.core.rows * tile.core.cols, n_obs),
            )
        }
        Err(err) => return Err(Error::Usage(format!("tile {}: {err}", tile.id))),
    };
    let mut data = Vec::with_capacity(layers.len() * e.len() * 4);
    for l in &layers {
        for &v in l.iter() {
            data.extend_from_slice(&(v as f32).to_le_bytes());
        }
    }
    let record = TileRecord {
        layers_sha256: sha256_hex(&data),
        id: tile.id,
        key: plan.key.clone(),
        core: tile.core,
        ext: e,
        status: status.into(),
        photometric_pixels: photometric,
        sanity,
        iterations: stages
            .iter()
            .map(|s| s.iterations.len().saturating_sub(1))
            .sum(),
        seconds: t0.elapsed().as_secs_f64(),
        stages,
    };
    let json = serde_json::to_vec(&record).expect("records serialise");
    let mut bytes = Vec::with_capacity(16 + json.len() + data.len());
    bytes.extend_from_slice(TILE_MAGIC);
    bytes.extend_from_slice(&(json.len() as u64).to_le_bytes());
    bytes.extend_from_slice(&json);
    bytes.extend_from_slice(&data);
    let path = tile_path(&o.output.directory, tile.id);
    write_atomic(&path, &bytes)?;
    Ok(record)
}

/// Parse a tile list like `3`, `0,4,7` or `2-5` (ids are 0-based).
pub fn parse_tiles(spec: &str) -> Result<Vec<usize>> {
    let bad = |p: &str| {
        Error::Usage(format!(
            "--tile {spec}: `{p}` is not a tile number or range like 2-5"
        ))
    };
    let mut v = Vec::new();
    for part in spec.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b): (usize, usize) = (
                    a.trim().parse().map_err(|_| bad(part))?,
                    b.trim().parse().map_err(|_| bad(part))?,
                );
                if a > b {
                    return Err(bad(part));
                }
                v.extend(a..=b);
            }
            None => v.push(part.parse().map_err(|_| bad(part))?),
        }
    }
    if v.is_empty() {
        return Err(Error::Usage(format!("--tile {spec}: no tile given")));
    }
    v.sort_unstable();
    v.dedup();
    Ok(v)
}

/// One line per tile: id, windows, and whether it is done.
#[derive(Debug, Clone, Serialize)]
pub struct TileStatus {
    pub id: usize,
    pub core: Window,
    pub ext: Window,
    pub done: bool,
}

/// The tiles of a workflow and their state (plans the run if needed).
pub fn list_tiles(wf: &Workflow, progress: &Progress) -> Result<Vec<TileStatus>> {
    let Workflow::Orbital(o) = wf else {
        return Err(Error::Usage(
            "a lab workflow is one piece of work: it has no tiles".into(),
        ));
    };
    let inputs = Inputs::open(o, progress)?;
    let plan = plan(o, wf, &inputs, progress)?;
    Ok(plan
        .tiles
        .iter()
        .map(|t| TileStatus {
            id: t.id,
            core: t.core,
            ext: t.ext,
            done: done_tile(&tile_path(&o.output.directory, t.id), &plan.key, None).is_some(),
        })
        .collect())
}

/// Run a workflow.
pub fn run(wf: &Workflow, req: &Request, progress: &Progress) -> Result<RunSummary> {
    let out = match wf {
        Workflow::Orbital(o) => &o.output.directory,
        Workflow::Lab(l) => {
            if req.tiles.is_some() || req.mosaic_only {
                return Err(Error::Usage(
                    "--tile and --mosaic apply to orbital workflows; a lab workflow runs whole"
                        .into(),
                ));
            }
            &l.output.directory
        }
    };
    // Tile tasks share the directory (a cluster runs them side by side); anything else
    // holds it alone.
    let (dir, swept) = OutputDir::open(out, req.tiles.is_none())?;
    if swept > 0 {
        progress.note(&format!(
            "removed {swept} temporary file(s) left by an interrupted run in {}",
            out.display()
        ));
    }
    let t0 = Instant::now();
    let result = match wf {
        Workflow::Orbital(o) => run_orbital(o, wf, req, progress),
        Workflow::Lab(l) => run_lab(l, wf, progress),
    };
    match result {
        Ok(mut s) => {
            s.seconds = t0.elapsed().as_secs_f64();
            Ok(s)
        }
        Err(e) => {
            dir.abandon();
            Err(e)
        }
    }
}

fn run_orbital(
    o: &Orbital,
    wf: &Workflow,
    req: &Request,
    progress: &Progress,
) -> Result<RunSummary> {
    let out = &o.output.directory;
    let inputs = Inputs::open(o, progress)?;
    let plan = plan(o, wf, &inputs, progress)?;
    let wanted: Vec<usize> = match &req.tiles {
        Some(ids) => {
            if let Some(&bad) = ids.iter().find(|&&i| i >= plan.tiles.len()) {
                return Err(Error::Usage(format!(
                    "--tile {bad}: this run has tiles 0 to {}",
                    plan.tiles.len() - 1
                )));
            }
            ids.clone()
        }
        None if req.mosaic_only => Vec::new(),
        None => (0..plan.tiles.len()).collect(),
    };
    let pending: Vec<&Tile> = wanted
        .iter()
        .map(|&i| &plan.tiles[i])
        .filter(|t| done_tile(&tile_path(out, t.id), &plan.key, Some(progress)).is_none())
        .collect();
    let skipped = wanted.len() - pending.len();
    if skipped > 0 {
        progress.note(&format!("{skipped} tile(s) already done: skipped"));
    }
    if !pending.is_empty() {
        let tiles = out.join("tiles");
        std::fs::create_dir_all(&tiles).map_err(|e| Error::io(&tiles, e))?;
        progress.steps("tiles", pending.len() as u64);
        let results: Vec<Result<TileRecord>> = pending
            .par_iter()
            .map(|t| {
                let r = run_tile(o, &inputs, &plan, t);
                if let Ok(rec) = &r {
                    progress.step(&format!(
                        "tile {} {} in {:.1} s ({} iterations)",
                        rec.id, rec.status, rec.seconds, rec.iterations
                    ));
                }
                r
            })
            .collect();
        progress.finish();
        // Report the first failure in tile order; the finished tiles are kept.
        let failed: Vec<String> = results
            .iter()
            .filter_map(|r| r.as_ref().err().map(|e| e.to_string()))
            .collect();
        if let Some(first) = failed.first() {
            return Err(Error::Usage(format!(
                "{} of {} tile(s) failed; finished tiles are kept and a rerun redoes only the rest. First failure: {first}",
                failed.len(),
                pending.len()
            )));
        }
    }
    let mut summary = RunSummary {
        output_directory: out.clone(),
        tiles_total: plan.tiles.len(),
        tiles_run: pending.len(),
        tiles_skipped: skipped,
        mosaic: false,
        outputs: Vec::new(),
        record: None,
        sanity: None,
        seconds: 0.0,
    };
    if req.tiles.is_none() {
        let (outputs, record, sanity) = mosaic(o, wf, &inputs, &plan, progress)?;
        summary.mosaic = true;
        summary.outputs = outputs;
        summary.record = Some(record);
        summary.sanity = Some(sanity);
    }
    Ok(summary)
}

/// What a GIS user sees of each layer.
/// Longest side of a run's quick-look panels, pixels.
const QUICKLOOK_SIDE: usize = 480;

/// The run's quick look (`quicklook.png`): the image, hillshades of the input and the fused
/// DEM, the albedo, dem − input_dem and the residual, each titled, with colour bars and a
/// scale bar, from block means of the products (`thumbs` in [`TILE_LAYERS`] order).
fn write_quicklook(path: &Path, thumbs: &[Thumbnail], spacing: f64, nm: f64) -> Result<()> {
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
fn product_metadata(o: &Orbital, inputs: &Inputs, plan: &Plan) -> Vec<(&'static str, String)> {
    let id = |label: &pds::Label, path: &Path| {
        label
            .get("PRODUCT_ID")
            .and_then(|v| v.as_str())
            .map(str::to_string)
            .unwrap_or_else(|| {
                path.file_stem()
                    .map(|s| s.to_string_lossy().into_owned())
                    .unwrap_or_default()
            })
    };
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
    let solver = FusionParams {
        sigma_dem: plan.sigma_dem,
        ..o.solver.clone()
    };
    let join = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x}"))
            .collect::<Vec<_>>()
            .join(",")
    };
    vec![
        ("SFSFUSE_VERSION", env!("CARGO_PKG_VERSION").to_string()),
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
fn sample_format(l: Layer) -> SampleFormat {
    match l {
        Layer::Mask | Layer::Observations => SampleFormat::Byte,
        _ => SampleFormat::Float32,
    }
}

fn layer_info(l: Layer, lunar: bool) -> (&'static str, &'static str) {
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
            "1 = no photometric information (shadow or no image), 0 = fused from shading",
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
struct InputFile {
    path: PathBuf,
    bytes: u64,
    sha256: String,
}

#[derive(Debug, Clone, Serialize)]
struct Metrics {
    pixels: usize,
    photometric_fraction: f64,
    residual_mean: f64,
    /// RMS of (fused − input DEM), metres.
    height_change_rms_m: f64,
    height_min_m: f64,
    height_max_m: f64,
    albedo_mean: f64,
}

#[derive(Debug, Clone, Serialize)]
struct RunRecord<'a> {
    tool: &'static str,
    version: &'static str,
    /// The workflow with every default filled in.
    workflow: &'a Workflow,
    inputs: Vec<InputFile>,
    grid: Option<Grid>,
    crs_wkt: Option<String>,
    halo: Option<usize>,
    intensity_scale: Option<f64>,
    dem_psf_sigma: Option<f64>,
    /// Where the grid spacing came from; the DEM's effective resolution, its source, and the
    /// σ_DEM the tiles used (orbital runs).
    resolution_source: Option<String>,
    dem_resolution_m: Option<f64>,
    dem_resolution_source: Option<String>,
    sigma_dem: Option<f64>,
    threads: usize,
    tiles: Vec<TileRecord>,
    metrics: Metrics,
    /// Sanity figures for real data (orbital runs).
    sanity: Option<Sanity>,
    /// Per M3 observation: gain, weight and how much of its footprint was photometric
    /// (orbital runs).
    observations: Vec<ObservationRecord>,
    outputs: Vec<PathBuf>,
}

/// One observation's part in a run.
#[derive(Debug, Clone, Serialize)]
struct ObservationRecord {
    label: PathBuf,
    /// Radiometric gain g relative to the first observation of its overlapping group.
    gain: f64,
    /// Noise weight ν (docs/science.md, "Several observations").
    noise_weight: f64,
    /// Its pixels on the grid (its footprint).
    footprint_pixels: usize,
    /// The share of its footprint where it carried photometric information.
    photometric_fraction: f64,
}

/// [`Metrics`] gathered band by band.
#[derive(Default)]
struct MetricsAcc {
    n: usize,
    phot: usize,
    res: (f64, usize),
    alb: (f64, usize),
    dh2: f64,
    hmin: f64,
    hmax: f64,
}

impl MetricsAcc {
    fn new() -> Self {
        MetricsAcc {
            hmin: f64::INFINITY,
            hmax: f64::NEG_INFINITY,
            ..Default::default()
        }
    }

    /// Add pixels: the layers in [`TILE_LAYERS`] order.
    fn add(&mut self, l: &[Array2<f64>; 7]) {
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

    fn finish(&self) -> Metrics {
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

fn checksums(files: &[PathBuf], progress: &Progress) -> Result<Vec<InputFile>> {
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
fn write_record(out: &Path, record: &RunRecord) -> Result<PathBuf> {
    let path = out.join("run.json");
    let text = serde_json::to_string_pretty(record).map_err(|e| json_err(&path, e))?;
    write_atomic(&path, text.as_bytes())?;
    Ok(path)
}

/// Blend every tile into the products and write the run record.
fn mosaic(
    o: &Orbital,
    wf: &Workflow,
    inputs: &Inputs,
    plan: &Plan,
    progress: &Progress,
) -> Result<(Vec<PathBuf>, PathBuf, Sanity)> {
    let out = &o.output.directory;
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
    let (rows, cols) = (plan.grid.rows, plan.grid.cols);
    let heads: Vec<(TileRecord, u64)> = found.into_iter().flatten().collect();
    // What the products are, from the inputs and parameters only (no path, time or run key:
    // the same inputs give the same files wherever the run writes them).
    let meta = product_metadata(o, inputs, plan);
    let mut writers = Vec::new();
    let mut outputs = Vec::new();
    for &l in &o.output.layers {
        let k = TILE_LAYERS
            .iter()
            .position(|&x| x == l)
            .expect("every layer is stored per tile");
        let (description, unit) = layer_info(l, true);
        let description = match (l, &o.photometry) {
            (Layer::Albedo, ModelSpec::Hapke(_)) => format!(
                "Hapke single-scattering albedo w at {} nm",
                o.inputs.wavelength_nm
            ),
            _ => description.to_string(),
        };
        let mut items = meta.clone();
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
        let path = out.join(format!("{}.tif", l.name()));
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
                cols,
                rows,
                &info,
                Container::Auto,
                sample_format(l),
            )?,
        ));
        outputs.push(path);
    }
    // Blend band by band: memory is one band of rows, whatever the region's size.
    let mut stats = MetricsAcc::new();
    // Block means of the layers the quick look shows, in TILE_LAYERS order.
    let mut thumbs: Vec<Thumbnail> = (0..TILE_LAYERS.len())
        .map(|_| Thumbnail::new(rows, cols, QUICKLOOK_SIDE))
        .collect();
    progress.steps("mosaic", rows.div_ceil(MOSAIC_BAND) as u64);
    for b0 in (0..rows).step_by(MOSAIC_BAND) {
        let b1 = (b0 + MOSAIC_BAND).min(rows);
        let mut acc: Vec<Array2<f64>> = (0..TILE_LAYERS.len())
            .map(|_| Array2::zeros((b1 - b0, cols)))
            .collect();
        let mut wsum = acc.clone();
        for (t, (rec, data)) in plan.tiles.iter().zip(&heads) {
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
        // Mask: without photometric information where the blend says so by majority; the
        // residual is no-data there.
        layers[3].mapv_inplace(|m| if m >= 0.5 { 1.0 } else { 0.0 });
        let mask = layers[3].clone();
        Zip::from(&mut layers[2]).and(&mask).for_each(|r, &m| {
            if m == 1.0 {
                *r = f64::NAN;
            }
        });
        // Observation counts: the nearest whole number across a blend.
        layers[6].mapv_inplace(f64::round);
        let layers: [Array2<f64>; 7] = layers.try_into().expect("seven layers");
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
    let ql = out.join("quicklook.png");
    write_quicklook(&ql, &thumbs, plan.grid.spacing, o.inputs.wavelength_nm)?;
    outputs.push(ql);
    let records: Vec<TileRecord> = heads.into_iter().map(|(r, _)| r).collect();
    let mut sums = TileSums::default();
    records.iter().for_each(|r| sums.add(&r.sanity));
    let labels: Vec<String> = inputs
        .obs
        .iter()
        .map(|o| o.label_path.display().to_string())
        .collect();
    let sanity = Sanity::from_sums(&sums, &labels);
    let record = RunRecord {
        tool: "sfsfuse",
        version: env!("CARGO_PKG_VERSION"),
        workflow: wf,
        inputs: checksums(&inputs.files()?, progress)?,
        grid: Some(plan.grid),
        crs_wkt: Some(plan.grid.crs.wkt()),
        halo: Some(plan.halo),
        intensity_scale: Some(plan.intensity_scale),
        dem_psf_sigma: Some(plan.dem_psf_sigma),
        resolution_source: Some(plan.resolution_source.clone()),
        dem_resolution_m: Some(plan.dem_resolution_m),
        dem_resolution_source: Some(plan.dem_resolution_source.clone()),
        sigma_dem: Some(plan.sigma_dem),
        threads: rayon::current_num_threads(),
        tiles: records,
        metrics: stats.finish(),
        sanity: Some(sanity.clone()),
        observations: inputs
            .obs
            .iter()
            .enumerate()
            .map(|(k, ob)| ObservationRecord {
                label: ob.label_path.clone(),
                gain: plan.gains.get(k).copied().unwrap_or(1.0),
                noise_weight: plan.noise_weights.get(k).copied().unwrap_or(1.0),
                footprint_pixels: sanity.observations.get(k).map_or(0, |o| o.footprint_pixels),
                photometric_fraction: sanity
                    .observations
                    .get(k)
                    .map_or(0.0, |o| o.photometric_fraction),
            })
            .collect(),
        outputs: outputs.clone(),
    };
    let path = write_record(out, &record)?;
    Ok((outputs, path, sanity))
}

/// `0-3, 7, 9-10`: sorted tile ids as ranges joined by `sep` (", " for people, "," for a
/// `--tile` argument).
pub fn tile_spec(ids: &[usize], sep: &str) -> String {
    let mut parts = Vec::new();
    let mut i = 0;
    while i < ids.len() {
        let mut j = i;
        while j + 1 < ids.len() && ids[j + 1] == ids[j] + 1 {
            j += 1;
        }
        parts.push(if i == j {
            ids[i].to_string()
        } else {
            format!("{}-{}", ids[i], ids[j])
        });
        i = j + 1;
    }
    parts.join(sep)
}

/// Read a single-band raster (TIFF or PNG) for lab mode.
fn read_raster(path: &Path) -> Result<Array2<f64>> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "tif" | "tiff" => Ok(crate::export::read_tiff(path)?.data),
        "png" => crate::quicklook::read_png(path),
        _ => Err(Error::Usage(format!(
            "{}: give a .tif/.tiff or .png raster",
            path.display()
        ))),
    }
}

/// Fill holes (NaN) in a depth map with the mean of their valid 8-neighbours, repeatedly,
/// inward from the hole's edge (deterministic: each sweep reads the previous sweep).
fn fill_holes(a: &mut Array2<f64>) -> usize {
    let (h, w) = a.dim();
    let holes = a.iter().filter(|v| !v.is_finite()).count();
    for _ in 0..h.max(w) {
        let prev = a.clone();
        let mut left = 0;
        for r in 0..h {
            for c in 0..w {
                if prev[(r, c)].is_finite() {
                    continue;
                }
                let (mut s, mut n) = (0.0, 0);
                for dr in -1isize..=1 {
                    for dc in -1isize..=1 {
                        let (rr, cc) = (r as isize + dr, c as isize + dc);
                        if (0..h as isize).contains(&rr) && (0..w as isize).contains(&cc) {
                            let v = prev[(rr as usize, cc as usize)];
                            if v.is_finite() {
                                s += v;
                                n += 1;
                            }
                        }
                    }
                }
                if n > 0 {
                    a[(r, c)] = s / n as f64;
                } else {
                    left += 1;
                }
            }
        }
        if left == 0 {
            break;
        }
    }
    holes
}

fn run_lab(l: &Lab, wf: &Workflow, progress: &Progress) -> Result<RunSummary> {
    let out = &l.output.directory;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    progress.stage("reading the image and the depth map");
    let image = read_raster(&l.inputs.image)?;
    let mut depth = read_raster(&l.inputs.depth)?;
    if image.dim() != depth.dim() {
        return Err(Error::Usage(format!(
            "{} is {:?} pixels but {} is {:?}: the image and the depth map must share one pixel grid",
            l.inputs.image.display(),
            image.dim(),
            l.inputs.depth.display(),
            depth.dim()
        )));
    }
    if let Some(nd) = l.inputs.depth_nodata {
        depth.mapv_inplace(|v| if v == nd { f64::NAN } else { v });
    }
    depth.mapv_inplace(|v| v * l.inputs.depth_scale);
    if depth.iter().all(|v| !v.is_finite()) {
        return Err(Error::Usage(format!(
            "{}: the depth map has no valid value",
            l.inputs.depth.display()
        )));
    }
    let filled = fill_holes(&mut depth);
    if filled > 0 {
        progress.note(&format!(
            "depth map: {filled} missing values filled from their neighbours"
        ));
    }
    let model = l.photometry.build();
    if let ModelSpec::Hapke(_) = l.photometry {
        progress.note("lab workflow with the Hapke model: intensities must be bidirectional reflectance (sr⁻¹)");
    }
    let d = |x: crate::workflow::Direction| crate::synth::direction(x.zenith_deg, x.azimuth_deg);
    let problem = Problem::single(
        image.view(),
        Directions::Uniform(d(l.illumination.light)),
        Directions::Uniform(d(l.illumination.view)),
        depth.view(),
        l.inputs.pixel_size_m,
        l.inputs.depth_psf_sigma_px,
        model.as_ref(),
    );
    progress.stage("fusing");
    let t0 = Instant::now();
    let params: &FusionParams = &l.solver;
    let f = fusion::fuse(&problem, params)?;
    let seconds = t0.elapsed().as_secs_f64();
    progress.finish();
    let mask = f.photometric.mapv(|b| if b { 0.0 } else { 1.0 });
    let layers = [
        f.height.clone(),
        f.albedo.clone(),
        f.residual.clone(),
        mask,
        depth.clone(),
        image.clone(),
        f.observations.mapv(f64::from),
    ];
    let meta = [("SFSFUSE_VERSION", env!("CARGO_PKG_VERSION").to_string())];
    let mut outputs = Vec::new();
    for &layer in &l.output.layers {
        let k = TILE_LAYERS
            .iter()
            .position(|&x| x == layer)
            .expect("every layer exists");
        let (description, unit) = layer_info(layer, false);
        let path = out.join(format!("{}.tif", layer.name()));
        let mut w = CogWriter::create_as(
            &path,
            None,
            layers[k].ncols(),
            layers[k].nrows(),
            &BandInfo {
                description,
                unit,
                metadata: &meta,
            },
            Container::Auto,
            sample_format(layer),
        )?;
        w.push(layers[k].view())?;
        w.finish()?;
        outputs.push(path);
    }
    let files = vec![l.inputs.image.clone(), l.inputs.depth.clone()];
    let (rows, cols) = image.dim();
    let record = RunRecord {
        tool: "sfsfuse",
        version: env!("CARGO_PKG_VERSION"),
        workflow: wf,
        inputs: checksums(&files, progress)?,
        grid: None,
        crs_wkt: None,
        halo: None,
        intensity_scale: None,
        dem_psf_sigma: None,
        resolution_source: None,
        dem_resolution_m: None,
        dem_resolution_source: None,
        sigma_dem: None,
        threads: rayon::current_num_threads(),
        tiles: vec![TileRecord {
            id: 0,
            key: String::new(),
            core: Window {
                r0: 0,
                c0: 0,
                rows,
                cols,
            },
            ext: Window {
                r0: 0,
                c0: 0,
                rows,
                cols,
            },
            status: "fused".into(),
            photometric_pixels: f.photometric.iter().filter(|&&b| b).count(),
            sanity: TileSums::default(),
            // A lab run writes no tile file.
            layers_sha256: String::new(),
            iterations: f.iterations(),
            seconds,
            stages: f.stages.clone(),
        }],
        sanity: None,
        observations: Vec::new(),
        metrics: {
            let mut m = MetricsAcc::new();
            m.add(&layers);
            m.finish()
        },
        outputs: outputs.clone(),
    };
    let path = write_record(out, &record)?;
    Ok(RunSummary {
        output_directory: out.clone(),
        tiles_total: 1,
        tiles_run: 1,
        tiles_skipped: 0,
        mosaic: true,
        outputs,
        record: Some(path),
        sanity: None,
        seconds: 0.0,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_lists_parse_and_compact() {
        assert_eq!(parse_tiles("3").unwrap(), [3]);
        assert_eq!(parse_tiles("5, 0-2,2").unwrap(), [0, 1, 2, 5]);
        assert!(parse_tiles("4-1").unwrap_err().to_string().contains("4-1"));
        assert!(parse_tiles("x").is_err());
        assert_eq!(tile_spec(&[0, 1, 2, 3, 7, 9, 10], ", "), "0-3, 7, 9-10");
        assert_eq!(
            parse_tiles(&tile_spec(&[0, 1, 2, 3, 7, 9, 10], ",")).unwrap(),
            [0, 1, 2, 3, 7, 9, 10]
        );
    }

    #[test]
    fn holes_fill_from_their_edges() {
        let mut a = Array2::from_shape_fn((5, 5), |(r, c)| (r + c) as f64);
        a[(2, 2)] = f64::NAN;
        a[(0, 0)] = f64::NAN;
        assert_eq!(fill_holes(&mut a), 2);
        assert!(a.iter().all(|v| v.is_finite()));
        assert!((a[(2, 2)] - 4.0).abs() < 1e-12);
    }
}
