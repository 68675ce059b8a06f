//! Step 1b, the coarse reference (`reference.bin`): the whole fusion on the region
//! block-averaged by f ([`fusion::pyramid`]), computed once in the plan. Tiles start their fine
//! stages from it and anchor their large scales to it, so a tile's halo only has to cover the
//! fine stages' widths (docs/science.md, "Coarse reference").
//!
//! The file: `SFSREF01`, rows and columns (u64 LE), then the correction z − z_DEM of every
//! coarse pixel (f64 LE, row-major). Its SHA-256 is in the plan; a file that does not match is
//! refused.

use super::*;
use crate::fusion::pyramid;

/// The most coarse pixels the reference is solved on: beyond ≈ 1 MP of coarse pixels the block
/// factor grows with the region, so the plan's memory does not.
pub const REFERENCE_PIXELS: usize = 1 << 20;
/// The fewest fine pixels a band of the reference's ingest holds (bands are whole rows of
/// blocks; [`band_pixels`]).
const MIN_BAND_PIXELS: usize = 1 << 16;
const MAGIC: &[u8; 8] = b"SFSREF01";
/// The reference's file in the output directory.
pub(super) const REFERENCE_FILE: &str = "reference.bin";

/// What the plan records of its reference.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ReferenceInfo {
    /// Block factor f: the reference's pixel is f × f grid pixels.
    pub factor: usize,
    pub rows: usize,
    pub cols: usize,
    /// SHA-256 of `reference.bin`.
    pub sha256: String,
    /// Gauss–Newton steps over its stages, and the seconds it took (ingest included).
    pub iterations: usize,
    pub seconds: f64,
}

/// The block factor of a region's reference: `[solver] coarse_factor`, raised so that the
/// coarse grid holds at most [`REFERENCE_PIXELS`]; `None` when the factor is 1 (tiles then
/// solve every stage themselves), there is no albedo stage, or the coarse grid would be under
/// 8 × 8 (a region of a few dozen pixels).
pub(super) fn factor(grid: &Grid, params: &FusionParams) -> Option<usize> {
    let need = ((grid.rows * grid.cols) as f64 / REFERENCE_PIXELS as f64)
        .sqrt()
        .ceil() as usize;
    fusion::coarse_factor_at_least((grid.rows, grid.cols), params, need)
}

/// The run-wide quantities a reference is solved with.
pub(super) struct RunWide<'a> {
    pub swaths: &'a [SwathIndex],
    /// Each observation's registration shift ([`super::register::shifts`]).
    pub shifts: &'a [crate::registration::Displacement],
    /// Each observation's gain trend ([`super::Plan::gain_trends`]).
    pub trends: &'a [Option<GainTrend>],
    pub scale: f64,
    pub gains: &'a [f64],
    pub noise_weights: &'a [f64],
    /// Each observation's blur σ_k on the fine grid ([`super::plan::blur_px`]).
    pub blur_px: &'a [f64],
    pub dem_psf_sigma: f64,
    pub params: &'a FusionParams,
}

/// A reference just built: its record, its values, and the full-resolution inputs when
/// [`build`] kept them.
pub(super) struct Built {
    pub(super) info: ReferenceInfo,
    pub(super) values: Array2<f64>,
    pub(super) ingested: Option<Ingested>,
}

/// Fine pixels the reference ingests at once: no more than one tile ingests, so that the plan
/// is never the run's memory peak (a tile's window is the most any stage of the run holds at
/// full resolution). A single tile over the whole grid ingests it in one band, which the tile
/// then takes over ([`build`]); otherwise the largest tile window, and at least
/// [`MIN_BAND_PIXELS`] (the per-band cost of reading the swaths then stays small). The block
/// means do not depend on the bands.
fn band_pixels(grid: &Grid, tiles: &[Tile]) -> usize {
    let largest = tiles
        .iter()
        .map(|t| t.ext.rows * t.ext.cols)
        .max()
        .unwrap_or(0);
    if tiles.len() == 1 {
        largest.max(grid.rows * grid.cols)
    } else {
        largest.max(MIN_BAND_PIXELS)
    }
}

/// Every input block-averaged by `f` over the grid: each observation's image and Sun and view
/// vectors (NaN where it does not reach) and the DEM.
struct Coarse {
    images: Vec<Array2<f64>>,
    suns: Vec<Array2<[f32; 3]>>,
    views: Vec<Array2<[f32; 3]>>,
    dem: Array2<f64>,
    /// The full-resolution ingest of the one band, where it covers the whole grid and so does
    /// the plan's one tile: the tile's own ingest would be the same.
    kept: Option<Ingested>,
}

/// [`Coarse`] over `grid`, ingested in bands of whole blocks (so that each band's block means
/// are the grid's) no larger than a tile's window ([`band_pixels`]). A region the DEM does not
/// cover fails here, before the reference is solved, as every tile over the gap would.
fn coarse_inputs(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    run: &RunWide,
    f: usize,
    tiles: &[Tile],
) -> Result<Coarse> {
    let whole = Window {
        r0: 0,
        c0: 0,
        rows: grid.rows,
        cols: grid.cols,
    };
    let keep = tiles.len() == 1 && tiles[0].ext == whole;
    let (cr, cc) = pyramid::coarse_dim((grid.rows, grid.cols), f);
    let n = inputs.obs.len();
    let mut images = vec![Array2::from_elem((cr, cc), f64::NAN); n];
    let mut suns = vec![Array2::from_elem((cr, cc), [f32::NAN; 3]); n];
    let mut views = suns.clone();
    let mut dem = Array2::from_elem((cr, cc), f64::NAN);
    let mut kept = None;
    let band = (band_pixels(grid, tiles) / (grid.cols * f)).max(1);
    for i0 in (0..cr).step_by(band) {
        let i1 = (i0 + band).min(cr);
        let (r0, r1) = (i0 * f, (i1 * f).min(grid.rows));
        let win = grid.window(r0 as isize, 0, r1 - r0, grid.cols);
        let placing = Placing {
            swaths: run.swaths,
            shifts: run.shifts,
            trends: run.trends,
        };
        let ingested = ingest_window(o, inputs, placing, &win)?;
        super::tile::dem_covers(&win, (r0, 0), &ingested.dem).map_err(|e| match e {
            Error::Usage(m) => Error::Usage(format!("the plan's coarse reference: {m}")),
            e => e,
        })?;
        for (k, img) in &ingested.shots {
            let (k, rows) = (*k, s![i0..i1, ..]);
            images[k]
                .slice_mut(rows)
                .assign(&pyramid::block_mean(img.reflectance.view(), f));
            suns[k]
                .slice_mut(rows)
                .assign(&pyramid::block_mean_vectors(img.sun.view(), f));
            views[k]
                .slice_mut(rows)
                .assign(&pyramid::block_mean_vectors(img.view.view(), f));
        }
        dem.slice_mut(s![i0..i1, ..])
            .assign(&pyramid::block_mean(ingested.dem.view(), f));
        // One band over the whole grid is exactly what a single tile over the whole grid
        // ingests: hand it on rather than ingest it again.
        if keep && r0 == 0 && r1 == grid.rows {
            kept = Some(ingested);
        }
    }
    Ok(Coarse {
        images,
        suns,
        views,
        dem,
        kept,
    })
}

/// Build the reference of block `f` over `grid`, write it to the output directory and return
/// its record and its values; `Ok(None)` when no DEM reaches the grid at all (the tiles then
/// say where) or no observation has a usable pixel. When the plan has one tile over the whole
/// grid (`tiles`), also the full-resolution ingest of its one band: the tile's own would be
/// the same.
pub(super) fn build(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    run: &RunWide,
    f: usize,
    tiles: &[Tile],
) -> Result<Option<Built>> {
    let t0 = Instant::now();
    let (cr, cc) = pyramid::coarse_dim((grid.rows, grid.cols), f);
    let Coarse {
        images,
        suns,
        views,
        mut dem,
        kept,
    } = coarse_inputs(o, inputs, grid, run, f, tiles)?;
    let n = inputs.obs.len();
    fill_holes(&mut dem);
    if !dem.iter().all(|v| v.is_finite()) {
        return Ok(None);
    }
    let keep: Vec<usize> = (0..n)
        .filter(|&k| images[k].iter().any(|v| v.is_finite()))
        .collect();
    let per_obs = |v: &[f64]| -> Vec<f64> {
        keep.iter()
            .map(|&k| v.get(k).copied().unwrap_or(1.0))
            .collect()
    };
    let problem = Problem {
        observations: keep
            .iter()
            .map(|&k| fusion::Observation {
                image: images[k].view(),
                sun: Directions::PerPixel(suns[k].view().into()),
                view: Directions::PerPixel(views[k].view().into()),
            })
            .collect(),
        dem: dem.view(),
        spacing: grid.spacing * f as f64,
        dem_psf_sigma: run.dem_psf_sigma / f as f64,
        model: inputs.model.as_ref(),
        intensity_scale: Some(run.scale),
        gains: Some(per_obs(run.gains)),
        noise_weights: Some(per_obs(run.noise_weights)),
        blur: Some(
            keep.iter()
                .map(|&k| run.blur_px.get(k).copied().unwrap_or(0.0) / f as f64)
                .collect(),
        ),
        selection: o.inputs.selection(),
    };
    if problem.observations.is_empty() {
        return Ok(None);
    }
    let (correction, stage) = match pyramid::reference(&problem, run.params, f) {
        Ok(r) => r,
        Err(fusion::FusionError::NoObservations) => return Ok(None),
        Err(e) => {
            return Err(Error::Usage(format!(
                "the plan's coarse reference (grid block-averaged by {f}): {e}"
            )))
        }
    };
    let bytes = encode(&correction);
    let path = o.output.directory.join(REFERENCE_FILE);
    write_atomic(&path, &bytes)?;
    let info = ReferenceInfo {
        factor: f,
        rows: cr,
        cols: cc,
        sha256: sha256_hex(&bytes),
        iterations: stage.iterations.len(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    Ok(Some(Built {
        info,
        values: correction,
        ingested: kept,
    }))
}

fn encode(a: &Array2<f64>) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(24 + a.len() * 8);
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&(a.nrows() as u64).to_le_bytes());
    bytes.extend_from_slice(&(a.ncols() as u64).to_le_bytes());
    for v in a.iter() {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    bytes
}

/// Read the reference of the plan, checked against its record (a file that fails is made anew
/// by the plan).
pub(super) fn load(out: &Path, info: &ReferenceInfo) -> Result<Array2<f64>> {
    let path = out.join(REFERENCE_FILE);
    let bytes = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    let bad = |why: &str| Error::Usage(format!("{}: {why}", path.display()));
    if sha256_hex(&bytes) != info.sha256 {
        return Err(bad(
            "its SHA-256 is not the plan's (a damaged or foreign file)",
        ));
    }
    if bytes.len() != 24 + info.rows * info.cols * 8 || &bytes[..8] != MAGIC {
        return Err(bad("not a reference of this plan's size"));
    }
    let values = bytes[24..]
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().expect("8-byte chunks")))
        .collect();
    Array2::from_shape_vec((info.rows, info.cols), values)
        .map_err(|_| bad("not a reference of this plan's size"))
}

/// The reference's surface on a tile's window `e`: the window's input DEM plus the coarse
/// correction interpolated onto it ([`pyramid::upsample_window`]).
pub(super) fn start_on(
    reference: &Array2<f64>,
    info: &ReferenceInfo,
    e: &Window,
    dem: &Array2<f64>,
) -> Array2<f64> {
    let f = info.factor;
    let (y0, y1) = pyramid::coarse_span(f, info.rows, e.r0, e.rows);
    let (x0, x1) = pyramid::coarse_span(f, info.cols, e.c0, e.cols);
    let up = pyramid::upsample_window(
        reference.slice(s![y0..y1, x0..x1]),
        (y0, x0),
        (info.rows, info.cols),
        f,
        (e.r0, e.c0),
        dem.dim(),
    );
    dem + &up
}
