//! The synthetic scene written out as mission-format products (docs/formats.md), so the whole
//! pipeline — PDS3 labels, M3 L1B and LOLA GDR readers, swath and DEM resampling, tiling,
//! export — runs on data whose truth is known:
//!
//! * an M3-like **L1B observation** in GLOBAL mode: one detached label with `RDN_FILE`,
//!   `LOC_FILE`, `OBS_FILE` (and `RDN_HDR_FILE` with the 85 band centres), an 85-band
//!   PC_REAL 32 radiance cube, LINE_INTERLEAVED; LOC (PC_REAL 64: east longitude, latitude,
//!   radius), OBS (PC_REAL 32, 10 bands: Sun and M3 azimuth/zenith in local east-north-up,
//!   phase, Sun-distance offset, path length, facet slope/aspect/cos i). Swath pixel (line,
//!   sample) lies at grid pixel (row, col); radiance L = r·E₁AU(λ)/d² with the scene's
//!   reflectance at 1209.57 nm (band 31) and a smooth lunar-like spectral slope elsewhere;
//! * a **solar spectrum table** with the 85 global band centres: a 5778 K black body seen from
//!   1 AU (the real global-mode table is not redistributable here; the pipeline only needs a
//!   table consistent with the radiances, as a user supplies the real one);
//! * a LOLA-like **GDR DEM** (`LDEM_64`-style: 64 px/deg simple cylindrical, CENTER_LONGITUDE =
//!   180, LSB_INTEGER 16, SCALING_FACTOR 0.5 m, OFFSET 1 737 400 m) sampling the scene's
//!   coarse, noisy input DEM;
//! * the truth height and albedo as GeoTIFFs on the scene's grid, for scoring.
//!
//! Every product is marked synthetic in its label.

use super::{Scene, SceneSpec};
use crate::error::{Error, Result};
use crate::export::{write_geotiff, BandInfo};
use crate::grid::{Grid, Interpolation, MOON_RADIUS_M};
use crate::raster::{write_atomic, write_atomic_with};
use ndarray::Array2;
use std::path::{Path, PathBuf};

/// Where the written products are.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Products {
    /// The first observation's label (`m3_labels[0]`).
    pub m3_label: PathBuf,
    /// Every observation's label, the scene's first observation first.
    pub m3_labels: Vec<PathBuf>,
    pub lola_label: PathBuf,
    pub solar_table: PathBuf,
    pub truth_dem: PathBuf,
    pub truth_albedo: PathBuf,
    pub grid: Grid,
    pub spec: SceneSpec,
}

/// The observation ID of the synthetic product (an impossible date: clearly not a real one).
pub const M3_ID: &str = "M3G20991231T000000";
/// LOLA-like resolution, pixels per degree.
pub const LOLA_RES: f64 = 64.0;
/// SOLAR_DISTANCE written into the label, AU.
const SOLAR_DISTANCE: f64 = 0.984326066205;

pub use crate::ingest::blackbody_irradiance;

fn f32_bytes(out: &mut Vec<u8>, v: f64) {
    out.extend_from_slice(&(v as f32).to_le_bytes());
}

/// Write the scene's products into `dir`.
pub fn write(scene: &Scene, grid: &Grid, dir: &Path) -> Result<Products> {
    write_observed(scene, grid, dir, &[], &[])
}

/// How an observation's products depart from the scene along its strip:
/// - its selenolocation as its LOC backplane carries it: every pixel of swath line l put
///   `offset_m + drift_m·l/(L − 1)` ([east, north] metres on the 1737.4 km sphere; L lines)
///   from where it lies — a constant error, and one that drifts along the strip as an
///   attitude error growing with time would;
/// - its radiance multiplied by exp(τ·(l − (L − 1)/2)/1000), τ = `gain_trend`: a gain
///   drifting along the track (`fusion::gains::GainTrend`);
/// - each detector column's radiance multiplied by its own gain exp(σ·N(0, 1)), σ =
///   `column_striping` ([`column_gains`]): residual striping, which `run` estimates and
///   divides out (`crate::striping`).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ProductErrors {
    pub offset_m: [f64; 2],
    pub drift_m: [f64; 2],
    pub gain_trend: f64,
    pub column_striping: f64,
}

/// The detector column gains exp(σ·N(0, 1)) of observation `k` of a scene of seed `seed`,
/// `columns` of them: the same for the same arguments on every platform.
pub fn column_gains(sigma: f64, seed: u64, k: usize, columns: usize) -> Vec<f64> {
    let mut rng = crate::rng::Rng::new(seed ^ 0x0C01_D572_19E5_u64.wrapping_add(k as u64));
    (0..columns).map(|_| (sigma * rng.normal()).exp()).collect()
}

/// [`write()`] with observation k's LOC and gain errors `loc_errors[k]` (missing entries:
/// none; `sfsfuse run`'s registration and gain trends should find and undo them), and its
/// detector pixels `pixel_factors[k]` grid pixels wide (missing entries: 1): its swath holds ⌊rows/F⌋ lines of ⌊columns/F⌋ samples, each the
/// mean of the scene's image over its F × F grid pixels (the scene's pixels are themselves the
/// mean over their footprint, so the swath is what a detector F times coarser sees), LOC at
/// the block's centre (the mean of its pixels' positions and radii) and OBS the block's central
/// pixel's. M3's second optical period (200 km, ≈ 280 m) over a grid at the first's 140 m is
/// F = 2 (docs/science.md, "Images coarser than the grid").
pub fn write_observed(
    scene: &Scene,
    grid: &Grid,
    dir: &Path,
    loc_errors: &[ProductErrors],
    pixel_factors: &[usize],
) -> Result<Products> {
    check_observed(scene, grid, loc_errors, pixel_factors)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let pr = grid
        .crs
        .projector()
        .map_err(|e| Error::Usage(e.to_string()))?;
    let geo = grid.geographic(&pr);
    // The first observation is the scene's own; observation k ≥ 1 is named for hour k.
    let first = (scene.image.view(), scene.sun, scene.spec.columns);
    let more = scene
        .more
        .iter()
        .map(|m| (m.image.view(), m.sun, m.spec.columns));
    let mut m3_labels = Vec::new();
    for (k, (image, sun, columns)) in std::iter::once(first).chain(more).enumerate() {
        let id = if k == 0 {
            M3_ID.to_string()
        } else {
            format!("M3G20991231T{k:02}0000")
        };
        let shot = Shot {
            image,
            sun,
            columns,
            loc_error: loc_errors.get(k).copied().unwrap_or_default(),
            factor: pixel_factors.get(k).copied().unwrap_or(1),
            index: k,
            seed: scene.spec.seed,
        };
        m3_labels.push(write_m3(dir, &id, shot, scene, grid, &geo)?);
    }
    let solar_table = write_solar_table(dir)?;
    let lola_label = write_lola(scene, grid, &geo, dir)?;
    let (truth_dem, truth_albedo) = write_truth(scene, grid, dir)?;
    Ok(Products {
        m3_label: m3_labels[0].clone(),
        m3_labels,
        lola_label,
        solar_table,
        truth_dem,
        truth_albedo,
        grid: *grid,
        spec: scene.spec.clone(),
    })
}

/// Refuse what [`write_observed`] cannot write: a pixel factor of 0 or wider than the grid, a
/// LOC error or gain trend that is not a finite number, a scene not the grid's size.
fn check_observed(
    scene: &Scene,
    grid: &Grid,
    loc_errors: &[ProductErrors],
    pixel_factors: &[usize],
) -> Result<()> {
    if let Some(f) = pixel_factors
        .iter()
        .find(|&&f| f == 0 || f > grid.rows.min(grid.cols))
    {
        return Err(Error::Usage(format!(
            "a pixel factor of {f}: it must be at least 1 and at most the grid's {} × {} pixels",
            grid.rows, grid.cols
        )));
    }
    if let Some(o) = loc_errors
        .iter()
        .flat_map(|e| {
            e.offset_m
                .iter()
                .chain(&e.drift_m)
                .chain([&e.gain_trend, &e.column_striping])
        })
        .find(|v| !v.is_finite())
    {
        return Err(Error::Usage(format!(
            "a LOC error, gain trend or column striping of {o} is not a finite number"
        )));
    }
    let (rows, cols) = scene.image.dim();
    if (rows, cols) != (grid.rows, grid.cols) {
        return Err(Error::Usage(format!(
            "the scene is {rows} × {cols} but the grid {} × {}",
            grid.rows, grid.cols
        )));
    }
    Ok(())
}

/// The solar spectrum table the synthetic radiance was made with: at each M3 global-mode band
/// centre (nm) the blackbody irradiance at 1 AU ([`blackbody_irradiance`], W/(m² µm)), two
/// columns per CRLF-ended row as M3's own tables have them.
fn write_solar_table(dir: &Path) -> Result<PathBuf> {
    let wl = pds::m3::band_centres(pds::m3::Mode::Global);
    let table: String = wl
        .iter()
        .map(|&w| format!("{w:12.6} {:12.6}\r\n", blackbody_irradiance(w)))
        .collect();
    let solar_table = dir.join("M3G_SYNTHETIC_SOLAR_SPEC.TAB");
    write_atomic(&solar_table, table.as_bytes())?;
    Ok(solar_table)
}

/// The truth height and albedo as COGs on the grid (`truth_dem.tif`, `truth_albedo.tif`).
fn write_truth(scene: &Scene, grid: &Grid, dir: &Path) -> Result<(PathBuf, PathBuf)> {
    let truth_dem = dir.join("truth_dem.tif");
    let truth_albedo = dir.join("truth_albedo.tif");
    let meta = [(
        "SFSFUSE_SCENE",
        format!("synthetic truth, seed {}", scene.spec.seed),
    )];
    write_geotiff(
        &truth_dem,
        grid,
        scene.truth_height.view(),
        &BandInfo {
            description: "synthetic truth height above the 1737.4 km sphere",
            unit: "m",
            metadata: &meta,
        },
    )?;
    write_geotiff(
        &truth_albedo,
        grid,
        scene.truth_albedo.view(),
        &BandInfo {
            description: "synthetic truth Hapke single-scattering albedo w",
            unit: "",
            metadata: &meta,
        },
    )?;
    Ok((truth_dem, truth_albedo))
}

/// One observation to write: its image on the grid, its Sun, the columns its swath covers.
struct Shot<'a> {
    image: ndarray::ArrayView2<'a, f64>,
    sun: super::SunPath,
    columns: Option<[usize; 2]>,
    /// How LOC misplaces the pixels.
    loc_error: ProductErrors,
    /// F: the detector's pixels are F × F grid pixels ([`write_observed`]).
    factor: usize,
    /// Its place among the scene's observations and the scene's seed (which seed its column
    /// gains).
    index: usize,
    seed: u64,
}

/// One M3-like L1B product set (label, RDN + ENVI header, LOC, OBS) named `id`: swath sample
/// s lies at grid column first + s. Each file is streamed line by line (at 8192² the radiance
/// cube alone is 23 GB) and written atomically.
fn write_m3(
    dir: &Path,
    id: &str,
    shot: Shot,
    scene: &Scene,
    grid: &Grid,
    geo: &crate::grid::Geographic,
) -> Result<PathBuf> {
    let [c0, c1] = shot.columns.unwrap_or([0, grid.cols]);
    let (c0, c1) = (c0.min(grid.cols), c1.min(grid.cols));
    let f = shot.factor.max(1);
    let swath = Swath {
        rows: grid.rows / f,
        cols: (c1 - c0) / f,
        f,
        c0,
    };
    let name = |part: &str, ext: &str| format!("{id}_V03_{part}.{ext}");
    let wl = pds::m3::band_centres(pds::m3::Mode::Global);
    write_rdn(&dir.join(name("RDN", "IMG")), &swath, &shot, &wl)?;
    write_loc(
        &dir.join(name("LOC", "IMG")),
        &swath,
        &shot.loc_error,
        scene,
        geo,
    )?;
    write_obs(
        &dir.join(name("OBS", "IMG")),
        &swath,
        &shot,
        scene,
        grid,
        geo,
    )?;
    let wl_list: Vec<String> = wl.iter().map(|w| format!("{w:.6}")).collect();
    let (rows, cols) = (swath.rows, swath.cols);
    let hdr = format!(
        "ENVI\ndescription = {{SYNTHETIC M3-like radiance written by sfsfuse}}\nsamples = {cols}\nlines = {rows}\nbands = {}\nheader offset = 0\nfile type = ENVI Standard\ndata type = 4\ninterleave = bil\nbyte order = 0\nwavelength = {{\n {} }}\n",
        wl.len(),
        wl_list.join(",\n ")
    );
    write_atomic(&dir.join(name("RDN", "HDR")), hdr.as_bytes())?;
    let image_object = |part: &str, bits: u32, bands: usize, extra: &str| {
        let rb = cols * bands * bits as usize / 8;
        format!(
            "OBJECT = {part}_FILE\r\n  ^{part}_IMAGE = \"{file}\"\r\n  RECORD_TYPE = FIXED_LENGTH\r\n  RECORD_BYTES = {rb}\r\n  FILE_RECORDS = {rows}\r\n  OBJECT = {part}_IMAGE\r\n    LINES = {rows}\r\n    LINE_SAMPLES = {cols}\r\n    SAMPLE_TYPE = PC_REAL\r\n    SAMPLE_BITS = {bits}\r\n    BANDS = {bands}\r\n    BAND_STORAGE_TYPE = LINE_INTERLEAVED\r\n{extra}  END_OBJECT = {part}_IMAGE\r\nEND_OBJECT = {part}_FILE\r\n",
            file = name(part, "IMG"),
        )
    };
    let label = format!(
        "PDS_VERSION_ID = PDS3\r\n/* SYNTHETIC product written by sfsfuse {ver} (seed {seed}): not mission data */\r\nDATA_SET_ID = \"SFSFUSE-SYNTHETIC-M3-L1B-LIKE\"\r\nPRODUCT_ID = {id}_V03_RDN\r\nRECORD_TYPE = UNDEFINED\r\nINSTRUMENT_ID = M3\r\nTARGET_NAME = MOON\r\nSOLAR_DISTANCE = {SOLAR_DISTANCE} <AU>\r\nINSTRUMENT_MODE_ID = GLOBAL\r\nCH1:SWATH_WIDTH = {cols} <pixel>\r\nCH1:SWATH_LENGTH = {rows} <pixel>\r\n{rdn}OBJECT = RDN_HDR_FILE\r\n  ^RDN_ENVI_HEADER = \"{hdr}\"\r\n  RECORD_TYPE = VARIABLE_LENGTH\r\nEND_OBJECT = RDN_HDR_FILE\r\n{loc}{obs}END\r\n",
        ver = env!("CARGO_PKG_VERSION"),
        seed = scene.spec.seed,
        rdn = image_object("RDN", 32, wl.len(), "    UNIT = \"W/(m^2 um sr)\"\r\n"),
        hdr = name("RDN", "HDR"),
        loc = image_object("LOC", 64, 3, "    BAND_NAME = (Longitude, Latitude, Radius)\r\n"),
        obs = image_object("OBS", 32, 10, ""),
    );
    let m3_label = dir.join(name("L1B", "LBL"));
    write_atomic(&m3_label, label.as_bytes())?;
    Ok(m3_label)
}

/// Where a synthetic observation's swath lies on the grid: `rows` lines of `cols` samples,
/// swath pixel (line a, sample b) covering grid rows a·F.. and columns c0 + b·F.., F = `f` of
/// each (one detector pixel of F × F grid pixels, [`write_observed`]).
struct Swath {
    rows: usize,
    cols: usize,
    f: usize,
    c0: usize,
}

impl Swath {
    /// The grid pixels swath pixel (a, b) covers.
    fn block(&self, a: usize, b: usize) -> impl Iterator<Item = (usize, usize)> {
        let (f, c0) = (self.f, self.c0);
        (a * f..(a + 1) * f).flat_map(move |i| (c0 + b * f..c0 + (b + 1) * f).map(move |j| (i, j)))
    }

    /// The mean of `v` over the grid pixels swath pixel (a, b) covers.
    fn mean(&self, a: usize, b: usize, v: &dyn Fn(usize, usize) -> f64) -> f64 {
        self.block(a, b).map(|(i, j)| v(i, j)).sum::<f64>() / (self.f * self.f) as f64
    }

    /// The grid pixel at the centre of swath pixel (a, b).
    fn centre(&self, a: usize, b: usize) -> (usize, usize) {
        (a * self.f + self.f / 2, self.c0 + b * self.f + self.f / 2)
    }
}

/// RDN: radiance, LINE_INTERLEAVED (for each line, every band's samples in turn), f32. Each
/// swath pixel is its block's mean reflectance (times the gain trend exp(T·(l − l_mid)/1000)
/// at line l and its column's gain, [`column_gains`]), shaped by a smooth, red-sloped lunar spectrum normalised at 1209.57 nm, times
/// the blackbody solar irradiance at [`SOLAR_DISTANCE`].
fn write_rdn(path: &Path, swath: &Swath, shot: &Shot, wl: &[f64]) -> Result<()> {
    let band_1209 = wl
        .iter()
        .position(|&w| (w - 1209.57).abs() < 0.01)
        .expect("the global table holds 1209.57 nm");
    let irr: Vec<f64> = wl.iter().map(|&w| blackbody_irradiance(w)).collect();
    let (rows, cols) = (swath.rows, swath.cols);
    write_atomic_with(path, |w| {
        let mut line = Vec::with_capacity(cols * wl.len() * 4);
        let tau = shot.loc_error.gain_trend;
        let striping = shot.loc_error.column_striping;
        let column_gain =
            (striping != 0.0).then(|| column_gains(striping, shot.seed, shot.index, cols));
        for i in 0..rows {
            line.clear();
            let mut values: Vec<f64> = (0..cols)
                .map(|s| swath.mean(i, s, &|i, j| shot.image[(i, j)]))
                .collect();
            if tau != 0.0 {
                let g = (tau * (i as f64 - 0.5 * (rows - 1) as f64) / 1000.0).exp();
                values.iter_mut().for_each(|v| *v *= g);
            }
            if let Some(gains) = &column_gain {
                values.iter_mut().zip(gains).for_each(|(v, g)| *v *= g);
            }
            for (b, &wv) in wl.iter().enumerate() {
                let shape = (wv / wl[band_1209]).powf(0.6);
                for v in &values {
                    let r = v * shape;
                    f32_bytes(&mut line, r * irr[b] / (SOLAR_DISTANCE * SOLAR_DISTANCE));
                }
            }
            w.write_all(&line)?;
        }
        Ok(())
    })
}

/// LOC: longitude (east, 0–360), latitude and radius of each swath pixel (its block's means;
/// longitudes averaged about the block's first, so that none wraps at 0/360), f64, with the
/// selenolocation error `e` added: its offset plus its drift's share at the line.
fn write_loc(
    path: &Path,
    swath: &Swath,
    e: &ProductErrors,
    scene: &Scene,
    geo: &crate::grid::Geographic,
) -> Result<()> {
    let (rows, cols) = (swath.rows, swath.cols);
    write_atomic_with(path, |w| {
        let mut line = Vec::with_capacity(cols * 3 * 8);
        for i in 0..rows {
            line.clear();
            for band in 0..3 {
                // Line i of `rows`: the drift's share at it.
                let t = if rows > 1 {
                    i as f64 / (rows - 1) as f64
                } else {
                    0.0
                };
                let [east, north] = [0, 1].map(|c| e.offset_m[c] + t * e.drift_m[c]);
                for b in 0..cols {
                    let lat = swath.mean(i, b, &|i, j| geo.lat[(i, j)]);
                    let l0 = geo.lon[swath.block(i, b).next().expect("F ≥ 1")];
                    let lon = l0
                        + swath.mean(i, b, &|i, j| {
                            (geo.lon[(i, j)] - l0 + 180.0).rem_euclid(360.0) - 180.0
                        });
                    let v = match band {
                        0 => (lon + (east / (MOON_RADIUS_M * lat.to_radians().cos())).to_degrees())
                            .rem_euclid(360.0),
                        1 => lat + (north / MOON_RADIUS_M).to_degrees(),
                        _ => MOON_RADIUS_M + swath.mean(i, b, &|i, j| scene.truth_height[(i, j)]),
                    };
                    line.extend_from_slice(&v.to_le_bytes());
                }
            }
            w.write_all(&line)?;
        }
        Ok(())
    })
}

/// OBS: the ten M3 observation bands at each swath pixel's centre (to-Sun azimuth and zenith,
/// to-sensor azimuth and zenith, phase, the facet's slope and aspect, cos i; the Sun distance
/// band 0 and the range 100 km), f32: the grid-frame directions rotated to local
/// east-north-up by the grid's north bearing (the inverse of the ingest's rotation).
fn write_obs(
    path: &Path,
    swath: &Swath,
    shot: &Shot,
    scene: &Scene,
    grid: &Grid,
    geo: &crate::grid::Geographic,
) -> Result<()> {
    let to_enu = |v: [f64; 3], t: f64| {
        let (s, c) = t.sin_cos();
        [v[0] * c - v[1] * s, v[0] * s + v[1] * c, v[2]]
    };
    let az_zen = |v: [f64; 3]| {
        (
            v[0].atan2(v[1]).to_degrees().rem_euclid(360.0),
            v[2].clamp(-1.0, 1.0).acos().to_degrees(),
        )
    };
    let (p, q) = crate::fusion::ops::gradient(scene.truth_height.view(), grid.spacing);
    let (rows, cols) = (swath.rows, swath.cols);
    write_atomic_with(path, |w| {
        let mut line = Vec::with_capacity(cols * 10 * 4);
        let mut bands: Vec<Vec<f64>> = (0..10).map(|_| Vec::with_capacity(cols)).collect();
        for i in 0..rows {
            line.clear();
            bands.iter_mut().for_each(Vec::clear);
            for b in 0..cols {
                let (i, j) = swath.centre(i, b);
                let t = geo.bearing[(i, j)];
                let sun = shot.sun.at_row(i as f64, scene.spec.size);
                let (s, v) = (to_enu(sun, t), to_enu(scene.view, t));
                let (saz, sz) = az_zen(s);
                let (vaz, vz) = az_zen(v);
                let phase = (s[0] * v[0] + s[1] * v[1] + s[2] * v[2])
                    .clamp(-1.0, 1.0)
                    .acos();
                // Facet normal (−p, −q, 1)/|…| in the grid frame, then east-north-up.
                let n = (p[(i, j)] * p[(i, j)] + q[(i, j)] * q[(i, j)] + 1.0).sqrt();
                let nrm = to_enu([-p[(i, j)] / n, -q[(i, j)] / n, 1.0 / n], t);
                let (aspect, slope) = az_zen(nrm);
                let cos_i = nrm[0] * s[0] + nrm[1] * s[1] + nrm[2] * s[2];
                let vals = [
                    saz,
                    sz,
                    vaz,
                    vz,
                    phase.to_degrees(),
                    0.0,
                    100_000.0,
                    slope,
                    aspect,
                    cos_i,
                ];
                for (b, x) in vals.into_iter().enumerate() {
                    bands[b].push(x);
                }
            }
            for b in &bands {
                for &x in b {
                    f32_bytes(&mut line, x);
                }
            }
            w.write_all(&line)?;
        }
        Ok(())
    })
}

/// The LOLA-like DEM: the smallest 64 px/deg window covering the grid with 4 pixels to spare,
/// each pixel the scene's input DEM at that pixel's centre (bilinear on the grid, clamped at
/// its edge), DN = round(h / 0.5).
fn write_lola(
    scene: &Scene,
    grid: &Grid,
    geo: &crate::grid::Geographic,
    dir: &Path,
) -> Result<PathBuf> {
    let lon = |v: f64| v.rem_euclid(360.0);
    let (mut lon0, mut lon1, mut lat0, mut lat1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (&a, &b) in geo.lon.iter().zip(&geo.lat) {
        lon0 = lon0.min(lon(a));
        lon1 = lon1.max(lon(a));
        lat0 = lat0.min(b);
        lat1 = lat1.max(b);
    }
    if lon1 - lon0 > 180.0 {
        return Err(Error::Usage(
            "the synthetic LOLA writer does not handle grids across longitude 0°".into(),
        ));
    }
    let res = LOLA_RES;
    let margin = 4.0;
    // Pixel centres on the LDEM lattice: lon = 180 + (s − off)/res with integer-aligned edges.
    let s_first = ((lon0 - 180.0) * res - margin).floor();
    let s_last = ((lon1 - 180.0) * res + margin).ceil();
    let l_first = ((-lat1) * res - margin).floor();
    let l_last = ((-lat0) * res + margin).ceil();
    let samples = (s_last - s_first + 1.0) as usize;
    let lines = (l_last - l_first + 1.0) as usize;
    // Line/sample 0 of this product is lattice index s_first / l_first: offsets follow.
    let sample_offset = -s_first;
    let line_offset = -l_first;
    let pr = grid
        .crs
        .projector()
        .map_err(|e| Error::Usage(e.to_string()))?;
    let mut img = Vec::with_capacity(lines * samples * 2);
    let clamp_grid = |r: f64, c: f64| {
        (
            r.clamp(0.0, grid.rows as f64 - 1.0),
            c.clamp(0.0, grid.cols as f64 - 1.0),
        )
    };
    let heights: Array2<f64> = Array2::from_shape_fn((lines, samples), |(l, s)| {
        let lo = 180.0 + (s as f64 - sample_offset) / res;
        let la = 0.0 - (l as f64 - line_offset) / res;
        let (x, y) = pr
            .forward(lo, la)
            .expect("a lunar point near the grid projects");
        let (r, c) = grid.pixel(x, y);
        let (r, c) = clamp_grid(r, c);
        crate::grid::interpolate(scene.input_dem.view(), r, c, Interpolation::Bilinear, false)
    });
    for h in heights.iter() {
        let dn = (h / 0.5).round();
        if !(i16::MIN as f64..=i16::MAX as f64).contains(&dn) {
            return Err(Error::Usage(format!(
                "the synthetic scene's input DEM reaches {h:.1} m, beyond what a LOLA-like 16-bit DN at 0.5 m holds (±16383.5 m)"
            )));
        }
        img.extend_from_slice(&(dn as i16).to_le_bytes());
    }
    let img_name = "LDEM_64_SYNTHETIC.IMG";
    write_atomic(&dir.join(img_name), &img)?;
    let scale_km = 2.0 * std::f64::consts::PI * 1737.4 / 360.0 / res;
    let label = format!(
        "PDS_VERSION_ID = PDS3\r\n/* SYNTHETIC LOLA-like GDR written by sfsfuse {ver} (seed {seed}): not mission data */\r\nDATA_SET_ID = \"SFSFUSE-SYNTHETIC-LOLA-GDR-LIKE\"\r\nPRODUCT_ID = \"LDEM_64_SYNTHETIC\"\r\nOBJECT = UNCOMPRESSED_FILE\r\n  FILE_NAME = \"{img_name}\"\r\n  RECORD_TYPE = FIXED_LENGTH\r\n  FILE_RECORDS = {lines}\r\n  RECORD_BYTES = {rb}\r\n  ^IMAGE = \"{img_name}\"\r\n  OBJECT = IMAGE\r\n    NAME = HEIGHT\r\n    DESCRIPTION = \"Synthetic height above the 1737.4 km sphere\"\r\n    LINES = {lines}\r\n    LINE_SAMPLES = {samples}\r\n    SAMPLE_TYPE = LSB_INTEGER\r\n    SAMPLE_BITS = 16\r\n    UNIT = METER\r\n    SCALING_FACTOR = 0.5\r\n    OFFSET = 1737400.\r\n  END_OBJECT = IMAGE\r\nEND_OBJECT = UNCOMPRESSED_FILE\r\nOBJECT = IMAGE_MAP_PROJECTION\r\n  ^DATA_SET_MAP_PROJECTION = \"DSMAP.CAT\"\r\n  MAP_PROJECTION_TYPE = \"SIMPLE CYLINDRICAL\"\r\n  A_AXIS_RADIUS = 1737.4 <KM>\r\n  B_AXIS_RADIUS = 1737.4 <KM>\r\n  C_AXIS_RADIUS = 1737.4 <KM>\r\n  CENTER_LATITUDE = 0. <DEG>\r\n  CENTER_LONGITUDE = 180. <DEG>\r\n  LINE_FIRST_PIXEL = 1\r\n  LINE_LAST_PIXEL = {lines}\r\n  SAMPLE_FIRST_PIXEL = 1\r\n  SAMPLE_LAST_PIXEL = {samples}\r\n  MAP_RESOLUTION = {res} <PIX/DEG>\r\n  MAP_SCALE = {scale_km:.10} <KM/PIXEL>\r\n  LINE_PROJECTION_OFFSET = {line_offset}\r\n  SAMPLE_PROJECTION_OFFSET = {sample_offset}\r\nEND_OBJECT = IMAGE_MAP_PROJECTION\r\nEND\r\n",
        ver = env!("CARGO_PKG_VERSION"),
        seed = scene.spec.seed,
        rb = samples * 2,
    );
    let path = dir.join("LDEM_64_SYNTHETIC.LBL");
    write_atomic(&path, label.as_bytes())?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn black_body_sun_is_near_the_measured_irradiance() {
        // The measured target-mode table gives ≈ 478 W/(m² µm) at 1209.6 nm (docs/formats.md); a
        // 5778 K black body is within a few per cent of it in the near infrared.
        let e = blackbody_irradiance(1209.57);
        assert!((e - 478.3).abs() / 478.3 < 0.05, "{e}");
    }
}
