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
//!
//! One file per stage: `inputs` (opening the products), `plan`, `tile`, `mosaic` (with the run
//! record and the products' metadata), `lab` (laboratory workflows); this file holds the
//! entry points (`run`, `list_tiles`), the plan key, the run key and the tile-list syntax.

use crate::error::{Error, Result};
use crate::export::{BandInfo, CogWriter, Container, SampleFormat};
use crate::fusion::gains::GainTrend;
use crate::fusion::{self, Directions, FusionParams, Problem, StageReport};
use crate::grid::{Crs, Grid, Projector};
use crate::ingest::{self, SwathIndex};
use crate::output::OutputDir;
use crate::photometry::{ModelSpec, ReflectanceModel};
use crate::progress::Progress;
use crate::quicklook::Thumbnail;
use crate::raster::write_atomic;
use crate::registration::Displacement;
use crate::sanity::{Sanity, TileSums, Usage};
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

mod inputs;
mod lab;
mod mosaic;
mod plan;
mod reference;
mod register;
mod tile;

pub use inputs::LOLA_TRACK_GAP_M;
use inputs::*;
use lab::*;
use mosaic::*;
pub use plan::Plan;
use plan::*;
pub use reference::ReferenceInfo;
use reference::*;
use register::*;
use tile::*;
pub use tile::{TileRecord, MASK_FUSED, MASK_NOT_PHOTOMETRIC, MASK_NO_IMAGE};

/// What `run` is asked to do.
#[derive(Debug, Clone, Default)]
pub struct Request {
    /// Only these tiles (and no mosaic); `None` = every pending tile, then the mosaic.
    pub tiles: Option<Vec<usize>>,
    /// Only the mosaic (every tile must be done).
    pub mosaic_only: bool,
}

/// Most tiles a run plans (a 2³¹-pixel region in 1024-px tiles is 2048; tiny tiles over a
/// large region would make a plan of millions of windows).
pub const MAX_TILES: usize = 20_000;
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

/// What both keys hash first: the build ([`crate::BUILD`]: the version and a hash of the
/// sources it was built from, so that another build's plan and tiles are not reused) and the
/// resolved workflow (with whether
/// `[solver] sigma_dem`, `dem_track_weight` and `multi_delta_factor_high_sun_east_west` were
/// given, which serialisation does not show).
fn key_text(wf: &Workflow) -> String {
    let mut text = format!("sfsfuse {}\n", crate::BUILD);
    text.push_str(&serde_json::to_string(wf).expect("workflows serialise"));
    if let Workflow::Orbital(o) = wf {
        text.push_str(&format!("\nsigma_dem_given={}", o.sigma_dem_given));
        text.push_str(&format!(
            "\ndem_track_weight_given={}",
            o.dem_track_weight_given
        ));
        text.push_str(&format!(
            "\nhigh_sun_east_west_given={}",
            o.high_sun_east_west_given
        ));
    }
    text
}

/// The plan key: ties plan and tiles to one workflow and one set of input files, by their
/// paths, sizes and modification times (cheap to check on every rerun; a touched input makes a
/// new plan).
fn plan_key(wf: &Workflow, files: &[PathBuf]) -> Result<String> {
    let mut text = key_text(wf);
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

/// The run key written into every product (`RUN_KEY`) and into run.json: the hex SHA-256 of
/// the build ([`crate::BUILD`]), the workflow with every default filled in and every path reduced to its
/// file name, and each input file's name and SHA-256 in order. It names what the products
/// were made from, not where: the same input files and parameters give the same key (and the
/// same bytes) wherever they lie and wherever the run writes, and any change of an input's
/// contents or of a parameter gives another key.
fn run_key(wf: &Workflow, inputs: &[InputFile]) -> String {
    let name = |p: &Path| PathBuf::from(p.file_name().unwrap_or(p.as_os_str()));
    let names = |v: &mut Vec<PathBuf>| v.iter_mut().for_each(|p| *p = name(p));
    let mut wf = wf.clone();
    match &mut wf {
        Workflow::Orbital(o) => {
            names(&mut o.inputs.m3);
            names(&mut o.inputs.lola);
            names(&mut o.inputs.solar_spectrum);
            o.output.directory = PathBuf::new();
            // What `[fetch]` brings is in the inputs' checksums; where from is not the
            // products' business.
            o.fetch = None;
        }
        Workflow::Lab(l) => {
            l.inputs.image = name(&l.inputs.image);
            l.inputs.depth = name(&l.inputs.depth);
            l.output.directory = PathBuf::new();
        }
    }
    let mut text = key_text(&wf);
    for f in inputs {
        text.push_str(&format!("\n{}:{}", name(&f.path).display(), f.sha256));
    }
    sha256_hex(text.as_bytes())
}

fn projector(crs: &Crs) -> Result<Projector> {
    crs.projector().map_err(|e| Error::Usage(e.to_string()))
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
    let (plan, _, _) = plan(o, wf, &inputs, progress)?;
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
    let (plan, reference, ingested) = plan(o, wf, &inputs, progress)?;
    // The single tile over the whole grid takes the reference's ingest (plan).
    let ingested = std::sync::Mutex::new(ingested);
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
    // The mosaic names the inputs by their SHA-256: hash them while the tiles run, whose
    // solver leaves part of the cores idle. On an error the thread is left to finish alone: it
    // only reads.
    let sums = if req.tiles.is_none() && !pending.is_empty() {
        let files = inputs.files()?;
        Some(std::thread::spawn(move || {
            checksums(&files, &Progress::new(crate::progress::Mode::Quiet))
        }))
    } else {
        None
    };
    if !pending.is_empty() {
        let tiles = out.join("tiles");
        std::fs::create_dir_all(&tiles).map_err(|e| Error::io(&tiles, e))?;
        progress.steps("tiles", pending.len() as u64);
        let results: Vec<Result<TileRecord>> = pending
            .par_iter()
            .map(|t| {
                let cached = ingested.lock().map_or(None, |mut c| c.take());
                let r = run_tile(o, &inputs, &plan, reference.as_ref(), t, cached);
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
        let files = sums
            .map(|h| h.join().unwrap_or_else(|p| std::panic::resume_unwind(p)))
            .transpose()?;
        let (outputs, record, sanity) = mosaic(o, wf, &inputs, &plan, files, progress)?;
        summary.mosaic = true;
        summary.outputs = outputs;
        summary.record = Some(record);
        summary.sanity = Some(sanity);
    }
    Ok(summary)
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

    /// The run key follows the inputs' contents and the parameters, not the paths.
    #[test]
    fn the_run_key_follows_contents_and_parameters_not_places() {
        let text = |dir: &str, delta: f64| {
            format!(
                "kind = \"orbital\"\n[inputs]\nm3 = [\"{dir}/a_L1B.LBL\"]\nlola = [\"{dir}/LDEM.LBL\"]\n\
                 solar_spectrum = \"{dir}/solar.TAB\"\n[solver]\ndelta = {delta}\n\
                 [output]\ndirectory = \"{dir}/out\"\n"
            )
        };
        let wf = |dir: &str, delta: f64| {
            Workflow::parse(&text(dir, delta), Path::new("w.toml"), Path::new("/")).unwrap()
        };
        let files = |dir: &str, sums: [&str; 3]| -> Vec<InputFile> {
            ["a_L1B.LBL", "LDEM.LBL", "solar.TAB"]
                .iter()
                .zip(sums)
                .map(|(n, s)| InputFile {
                    path: PathBuf::from(format!("{dir}/{n}")),
                    bytes: 1,
                    sha256: s.to_string(),
                })
                .collect()
        };
        let sums = ["01", "02", "03"];
        let key = run_key(&wf("/data", 50.0), &files("/data", sums));
        assert_eq!(key.len(), 64);
        assert_eq!(
            key,
            run_key(&wf("/elsewhere/x", 50.0), &files("/elsewhere/x", sums))
        );
        assert_ne!(key, run_key(&wf("/data", 60.0), &files("/data", sums)));
        assert_ne!(
            key,
            run_key(&wf("/data", 50.0), &files("/data", ["01", "02", "04"]))
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
