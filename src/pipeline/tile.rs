//! Step 2, tiles: ingest a window of every input, fuse it, write its layers and record in one
//! atomic, checksummed `.sfstile` file; find and verify finished tiles.

use super::*;
use ndarray::ArrayView2;

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

/// Layers stored per tile, in file order: every layer a workflow can ask for.
pub(super) const TILE_LAYERS: [Layer; 7] = Layer::ALL;
pub(super) const TILE_MAGIC: &[u8; 8] = b"SFSTILE1";

/// Where `layer` is in [`TILE_LAYERS`] (every layer is stored).
pub(super) fn stored_index(layer: Layer) -> usize {
    TILE_LAYERS
        .iter()
        .position(|&x| x == layer)
        .expect("every layer is stored per tile")
}

/// `mask` codes: fused from shading.
pub const MASK_FUSED: f64 = 0.0;
/// `mask` codes: an observation sees the pixel but gave no photometric information there
/// (cast shadow, a refused or too-dark pixel, outside the incidence window).
pub const MASK_NOT_PHOTOMETRIC: f64 = 1.0;
/// `mask` codes: no observation sees the pixel; the height is the input DEM's (within the
/// support band, its faded correction).
pub const MASK_NO_IMAGE: f64 = 2.0;

/// The `mask` layer from where the fusion was photometric and the image (NaN where no
/// observation sees the pixel).
fn mask_codes(photometric: &Array2<bool>, image: &Array2<f64>) -> Array2<f64> {
    Zip::from(photometric).and(image).map_collect(|&p, &i| {
        if p {
            MASK_FUSED
        } else if i.is_finite() {
            MASK_NOT_PHOTOMETRIC
        } else {
            MASK_NO_IMAGE
        }
    })
}

pub(super) fn tile_path(out: &Path, id: usize) -> PathBuf {
    out.join("tiles").join(format!("tile_{id:05}.sfstile"))
}

/// Read a tile file's header and where its layers start; `None` when absent, unreadable, of
/// the wrong size or not of this plan.
pub(super) fn tile_header(path: &Path, key: &str) -> Option<(TileRecord, u64)> {
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
pub(super) fn done_tile(
    path: &Path,
    key: &str,
    progress: Option<&Progress>,
) -> Option<(TileRecord, u64)> {
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
pub(super) fn read_tile_rows(
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

/// Refuse a window whose DEM has a pixel no LOLA product of `[inputs] lola` covers: the error
/// names the first such pixel of the grid (the window's origin `at` added) and its longitude
/// and latitude.
pub(super) fn dem_covers(window: &Grid, at: (usize, usize), dem: &Array2<f64>) -> Result<()> {
    let Some(((r, c), _)) = dem.indexed_iter().find(|(_, v)| !v.is_finite()) else {
        return Ok(());
    };
    let (x, y) = window.xy(r as f64, c as f64);
    let (lon, lat) = projector(&window.crs)?
        .inverse(x, y)
        .unwrap_or((f64::NAN, f64::NAN));
    Err(Error::Usage(format!(
        "no LOLA DEM of [inputs] lola covers grid pixel ({}, {}) at lon {lon:.4}, lat {lat:.4} (with the interpolation's support): add a DEM that covers the region or shrink [region]",
        at.0 + r,
        at.1 + c
    )))
}

/// Run one tile and write its file atomically. `ingested`: the tile's inputs when the plan
/// has them already (one tile over the whole grid, [`super::reference::build`]).
pub(super) fn run_tile(
    o: &Orbital,
    inputs: &Inputs,
    plan: &Plan,
    reference: Option<&Array2<f64>>,
    tile: &Tile,
    ingested: Option<Ingested>,
) -> Result<TileRecord> {
    let t0 = Instant::now();
    let e = tile.ext;
    let grid = plan
        .grid
        .window(e.r0 as isize, e.c0 as isize, e.rows, e.cols);
    // Every observation that reaches the tile, and the DEM.
    let Ingested { shots, dem } = match ingested {
        Some(i) => i,
        None => ingest_window(
            o,
            inputs,
            Placing {
                swaths: &plan.swaths,
                shifts: &super::register::shifts(&plan.registration),
                trends: &plan.gain_trends,
            },
            &grid,
        )?,
    };
    dem_covers(&grid, (e.r0, e.c0), &dem).map_err(|e| match e {
        Error::Usage(m) => Error::Usage(format!("tile {}: {m}", tile.id)),
        e => e,
    })?;
    let ids: Vec<usize> = shots.iter().map(|(k, _)| *k).collect();
    let problem = tile_problem(o, inputs, plan, &grid, &shots, &ids, dem.view());
    let outcome = fuse_tile(
        o,
        plan,
        reference,
        tile,
        &problem,
        &dem,
        &ids,
        inputs.obs.len(),
    );
    // The observations' per-pixel radiances and Sun and view vectors have served (the `image`
    // layer is formed from them now): they go before the layers are assembled.
    drop(problem);
    let image = first_image(&shots, (e.rows, e.cols));
    drop(shots);
    let layers = match outcome {
        Ok((f, sanity)) => TileLayers::fused(f, sanity, dem, image),
        Err(None) => TileLayers::no_image(tile, dem, image, inputs.obs.len()),
        Err(Some(err)) => return Err(Error::Usage(format!("tile {}: {err}", tile.id))),
    };
    write_tile(o, plan, tile, t0, layers)
}

/// The fusion problem of a tile: its observations (`shots`, whose indices in the workflow are
/// `ids`) with the plan's intensity scale, gains, noise weights and blurs, and its DEM.
fn tile_problem<'a>(
    o: &Orbital,
    inputs: &'a Inputs,
    plan: &Plan,
    grid: &Grid,
    shots: &'a [(usize, ingest::ImageOnGrid)],
    ids: &[usize],
    dem: ArrayView2<'a, f64>,
) -> Problem<'a> {
    // The plan's per-observation values, in the order of the tile's observations; an
    // observation the plan has no value for keeps `missing`.
    let per_obs = |v: &[f64], missing: f64| -> Vec<f64> {
        ids.iter()
            .map(|&k| v.get(k).copied().unwrap_or(missing))
            .collect()
    };
    Problem {
        observations: fusion_observations(shots),
        dem,
        spacing: grid.spacing,
        dem_psf_sigma: plan.dem_psf_sigma,
        model: inputs.model.as_ref(),
        intensity_scale: Some(plan.intensity_scale),
        gains: Some(per_obs(&plan.gains, 1.0)),
        noise_weights: Some(per_obs(&plan.noise_weights, 1.0)),
        blur: Some(per_obs(&plan.blur_px(), 0.0)),
        selection: o.inputs.selection(),
    }
}

/// A tile's fusion and the sums of its core for the run's sanity figures; `Err(None)` where
/// no observation reaches the tile.
type TileOutcome = std::result::Result<(fusion::Fusion, TileSums), Option<fusion::FusionError>>;

/// Fuse a tile's problem: from the plan's reference on the window where there is one (else
/// every stage on the window alone; the halo then covers the first stage's σ_ρ), then anchor
/// the result's large scales to the reference or, without one, to the input DEM
/// ([`fusion::anchor`]).
#[allow(clippy::too_many_arguments)]
fn fuse_tile(
    o: &Orbital,
    plan: &Plan,
    reference: Option<&Array2<f64>>,
    tile: &Tile,
    problem: &Problem,
    dem: &Array2<f64>,
    ids: &[usize],
    n_obs: usize,
) -> TileOutcome {
    if problem.observations.is_empty() {
        return Err(None);
    }
    let e = tile.ext;
    let params = FusionParams {
        coarse_factor: 1,
        ..plan.solver(&o.solver)
    };
    // The reference on the window (formed twice, for the fusion to take over and for the
    // anchor after it, rather than held through the fusion).
    let start = || {
        plan.reference
            .as_ref()
            .zip(reference)
            .map(|(info, r)| start_on(r, info, &e, dem))
    };
    let mut f = match start() {
        Some(z0) => fusion::fuse_from(problem, &params, z0),
        None => fusion::fuse(problem, &params),
    }
    .map_err(|err| match err {
        fusion::FusionError::NoObservations => None,
        err => Some(err),
    })?;
    let start = start();
    let level = start.as_ref().unwrap_or(dem);
    f.height = fusion::anchor(
        &f.height,
        level.view(),
        f.support.view(),
        plan.halo as f64 / 4.0,
    );
    drop(start);
    let core = (
        tile.core.r0 - e.r0,
        tile.core.r0 - e.r0 + tile.core.rows,
        tile.core.c0 - e.c0,
        tile.core.c0 - e.c0 + tile.core.cols,
    );
    let sanity = TileSums::of_tile(problem, &f, &f.height, ids, n_obs, core);
    Ok((f, sanity))
}

/// The `image` layer: at each pixel the reflectance of the first observation that covers it
/// (NaN where none does).
fn first_image(shots: &[(usize, ingest::ImageOnGrid)], dim: (usize, usize)) -> Array2<f64> {
    let mut image = Array2::from_elem(dim, f64::NAN);
    for (_, img) in shots {
        Zip::from(&mut image)
            .and(&img.reflectance)
            .for_each(|i, &r| {
                if i.is_nan() {
                    *i = r;
                }
            });
    }
    image
}

/// What a tile file holds besides its window and timing: the layers in [`TILE_LAYERS`] order
/// and what the record says of them.
pub(super) struct TileLayers {
    pub(super) status: &'static str,
    pub(super) layers: [Array2<f64>; 7],
    pub(super) stages: Vec<StageReport>,
    pub(super) photometric: usize,
    pub(super) sanity: TileSums,
}

impl TileLayers {
    /// A fused tile's layers (a lab run's too, with default sums).
    pub(super) fn fused(
        f: fusion::Fusion,
        sanity: TileSums,
        dem: Array2<f64>,
        image: Array2<f64>,
    ) -> Self {
        let photometric = f.photometric.iter().filter(|&&b| b).count();
        let mask = mask_codes(&f.photometric, &image);
        TileLayers {
            status: "fused",
            layers: [
                f.height,
                f.albedo,
                f.residual,
                mask,
                dem,
                image,
                f.observations.mapv(f64::from),
            ],
            stages: f.stages,
            photometric,
            sanity,
        }
    }

    /// A tile no observation reaches: the input DEM, no albedo or residual, every pixel
    /// [`MASK_NO_IMAGE`].
    fn no_image(tile: &Tile, dem: Array2<f64>, image: Array2<f64>, n_obs: usize) -> Self {
        let dim = dem.dim();
        let nan = Array2::from_elem(dim, f64::NAN);
        TileLayers {
            status: "no_image",
            layers: [
                dem.clone(),
                nan.clone(),
                nan,
                Array2::from_elem(dim, MASK_NO_IMAGE),
                dem,
                image,
                Array2::zeros(dim),
            ],
            stages: Vec::new(),
            photometric: 0,
            sanity: TileSums::no_image(tile.core.rows * tile.core.cols, n_obs),
        }
    }
}

/// Write a tile's file atomically: [`TILE_MAGIC`], the record's length and JSON, then the
/// layers as little-endian f32, layer after layer (hashed in one pass for the record's
/// checksum, then streamed into the file: no copy of them is assembled in memory).
fn write_tile(
    o: &Orbital,
    plan: &Plan,
    tile: &Tile,
    t0: Instant,
    t: TileLayers,
) -> Result<TileRecord> {
    let e = tile.ext;
    let le_bytes = |l: &Array2<f64>, buf: &mut Vec<u8>| {
        buf.clear();
        buf.extend(l.iter().flat_map(|&v| (v as f32).to_le_bytes()));
    };
    let mut hasher = Sha256::new();
    let mut buf = Vec::with_capacity(e.len() * 4);
    for l in &t.layers {
        le_bytes(l, &mut buf);
        hasher.update(&buf);
    }
    let record = TileRecord {
        layers_sha256: hasher
            .finalize()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect(),
        id: tile.id,
        key: plan.key.clone(),
        core: tile.core,
        ext: e,
        status: t.status.into(),
        photometric_pixels: t.photometric,
        sanity: t.sanity,
        iterations: fusion::total_iterations(&t.stages),
        seconds: t0.elapsed().as_secs_f64(),
        stages: t.stages,
    };
    let json = serde_json::to_vec(&record).expect("records serialise");
    let path = tile_path(&o.output.directory, tile.id);
    crate::raster::write_atomic_with(&path, |w| {
        w.write_all(TILE_MAGIC)?;
        w.write_all(&(json.len() as u64).to_le_bytes())?;
        w.write_all(&json)?;
        for l in &t.layers {
            le_bytes(l, &mut buf);
            w.write_all(&buf)?;
        }
        Ok(())
    })?;
    Ok(record)
}
