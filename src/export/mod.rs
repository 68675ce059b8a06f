//! GeoTIFF export laid out as a Cloud Optimized GeoTIFF (COG), in pure Rust.
//!
//! One float32 band, 256 × 256 tiles, DEFLATE with the floating-point predictor (TIFF Technical
//! Note 3, Predictor = 3), NaN as no-data (`GDAL_NODATA = "nan"`), internal overviews (2 × 2
//! means of the valid pixels) down to one tile, and GeoKeys for the lunar CRS (docs/gis.md);
//! or one Byte band of whole numbers ([`SampleFormat::Byte`]: horizontal predictor, 255 as
//! no-data, nearest overviews) for counts and masks.
//!
//! Layout (GDAL's COG definition, checked by GDAL's `validate_cloud_optimized_geotiff.py`):
//! header; GDAL's structural-metadata "ghost" block right after it (`LAYOUT=IFDS_BEFORE_DATA`,
//! `BLOCK_ORDER=ROW_MAJOR`, `BLOCK_LEADER=SIZE_AS_UINT4`, `BLOCK_TRAILER=LAST_4_BYTES_REPEATED`);
//! then every IFD (full resolution first, then the overviews, largest to smallest), each followed
//! by its out-of-line tag values; then the tile data, smallest overview first and full
//! resolution last, each level row-major, each tile preceded by its size as a u32 and followed
//! by a repeat of its last 4 bytes. Classic TIFF is written when every offset fits in 32 bits,
//! BigTIFF otherwise.
//!
//! The tiff crate's encoder writes each IFD after its own data, which a COG forbids, so the
//! container is written here; the tiff crate's decoder reads the files back in the tests, and
//! GDAL itself checks them in CI (tests/gis.rs).

#[cfg(feature = "gdal")]
pub mod gdal;

use crate::error::{Error, Result};
use crate::grid::{Crs, Grid, MOON_RADIUS_M};
use flate2::{write::ZlibEncoder, Compression};
use ndarray::{Array2, ArrayView2};
use rayon::prelude::*;
use std::io::Read;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Tile edge in pixels.
pub const TILE: usize = 256;

/// What a band holds, written into the file's GDAL metadata (band description and unit).
#[derive(Debug, Clone)]
pub struct BandInfo<'a> {
    /// Band description, e.g. "height above the 1737.4 km sphere".
    pub description: &'a str,
    /// Unit, e.g. "m"; empty for dimensionless values.
    pub unit: &'a str,
    /// Extra dataset-level metadata items (name, value), e.g. the tool version.
    pub metadata: &'a [(&'a str, String)],
}

/// How a band's samples are stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SampleFormat {
    /// IEEE float32, NaN as no-data (`GDAL_NODATA = nan`), the floating-point predictor
    /// (TIFF Technical Note 3, Predictor = 3), overviews the mean of each 2 × 2 block's valid
    /// pixels.
    #[default]
    Float32,
    /// Unsigned 8-bit whole numbers 0–254 (counts, classes), [`BYTE_NODATA`] as no-data,
    /// horizontal differencing (Predictor = 2), overviews the first valid pixel of each 2 × 2
    /// block (nearest: a count or a class is never averaged).
    Byte,
}

/// The no-data value of [`SampleFormat::Byte`] bands.
pub const BYTE_NODATA: u8 = 255;

/// Which TIFF container to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Container {
    /// Classic TIFF when every offset fits in 32 bits, BigTIFF otherwise.
    #[default]
    Auto,
    /// BigTIFF whatever the size.
    BigTiff,
}

/// Write `data` on `grid` to `path` as a COG, atomically (temporary sibling, fsync, rename).
pub fn write_geotiff(
    path: &Path,
    grid: &Grid,
    data: ArrayView2<f64>,
    info: &BandInfo,
) -> Result<()> {
    write_geotiff_as(path, grid, data, info, Container::Auto)
}

/// [`write_geotiff`] with a choice of container.
pub fn write_geotiff_as(
    path: &Path,
    grid: &Grid,
    data: ArrayView2<f64>,
    info: &BandInfo,
    container: Container,
) -> Result<()> {
    check_shape(path, grid, data)?;
    let mut w = CogWriter::create(
        path,
        Some(grid),
        data.ncols(),
        data.nrows(),
        info,
        container,
    )?;
    w.push(data)?;
    w.finish()
}

/// The data must cover the grid exactly.
pub(crate) fn check_shape(path: &Path, grid: &Grid, data: ArrayView2<f64>) -> Result<()> {
    if data.dim() != (grid.rows, grid.cols) {
        return Err(Error::Usage(format!(
            "{}: data is {:?} pixels but the grid is {} × {}",
            path.display(),
            data.dim(),
            grid.rows,
            grid.cols
        )));
    }
    Ok(())
}

/// Write `data` as a tiled, compressed float32 TIFF with overviews and band metadata but no
/// georeferencing (laboratory products, which are not on the Moon), atomically.
pub fn write_tiff(path: &Path, data: ArrayView2<f64>, info: &BandInfo) -> Result<()> {
    let mut w = CogWriter::create(
        path,
        None,
        data.ncols(),
        data.nrows(),
        info,
        Container::Auto,
    )?;
    w.push(data)?;
    w.finish()
}

/// Streams one float32 band into a COG in bounded memory: rows go in top to bottom
/// ([`CogWriter::push`]); as soon as a row of 256-px tiles of any level is complete it is
/// compressed (in parallel) into that level's temporary file, and its 2 × 2 means feed the
/// next level. [`CogWriter::finish`] then writes the header, every IFD and the tile data —
/// smallest overview first — into a temporary sibling and renames it into place. Memory is a
/// few tile rows per level, whatever the image size.
pub struct CogWriter {
    path: PathBuf,
    grid: Option<Grid>,
    info: OwnedInfo,
    container: Container,
    format: SampleFormat,
    levels: Vec<Level>,
    stats: Stats,
    done: bool,
}

/// [`BandInfo`] with owned strings (a writer outlives its caller's borrows).
struct OwnedInfo {
    description: String,
    unit: String,
    metadata: Vec<(String, String)>,
}

/// Band statistics over the finite values, as GDAL stores them (`STATISTICS_*` band metadata),
/// so that a GIS styles the layer without scanning it. Sums run in pixel order: the same
/// values give the same figures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    pub total: u64,
    pub valid: u64,
    pub min: f64,
    pub max: f64,
    pub sum: f64,
    pub sum_sq: f64,
}

impl Default for Stats {
    fn default() -> Self {
        Stats {
            total: 0,
            valid: 0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            sum: 0.0,
            sum_sq: 0.0,
        }
    }
}

impl Stats {
    /// Add values as they are stored (float32).
    pub fn add(&mut self, values: &[f32]) {
        for &v in values {
            self.total += 1;
            if v.is_finite() {
                let v = v as f64;
                self.valid += 1;
                self.min = self.min.min(v);
                self.max = self.max.max(v);
                self.sum += v;
                self.sum_sq += v * v;
            }
        }
    }

    /// The `STATISTICS_*` items: minimum, maximum, mean, population standard deviation and the
    /// valid percentage; none without a finite value.
    pub fn items(&self) -> Vec<(&'static str, String)> {
        if self.valid == 0 {
            return Vec::new();
        }
        let n = self.valid as f64;
        let mean = self.sum / n;
        let sd = (self.sum_sq / n - mean * mean).max(0.0).sqrt();
        vec![
            ("STATISTICS_MINIMUM", format!("{}", self.min)),
            ("STATISTICS_MAXIMUM", format!("{}", self.max)),
            ("STATISTICS_MEAN", format!("{mean}")),
            ("STATISTICS_STDDEV", format!("{sd}")),
            (
                "STATISTICS_VALID_PERCENT",
                format!("{}", 100.0 * n / self.total as f64),
            ),
        ]
    }
}

struct Level {
    w: usize,
    h: usize,
    /// Rows received and not yet compressed (row-major, `w` wide).
    buf: Vec<f32>,
    rows_in: usize,
    tmp: PathBuf,
    file: std::io::BufWriter<std::fs::File>,
    /// Compressed size of each tile so far, row-major.
    sizes: Vec<u64>,
}

impl CogWriter {
    /// A writer for a `width × height` float32 band to `path` (`grid` = None: no GeoTIFF
    /// tags).
    pub fn create(
        path: &Path,
        grid: Option<&Grid>,
        width: usize,
        height: usize,
        info: &BandInfo,
        container: Container,
    ) -> Result<Self> {
        Self::create_as(
            path,
            grid,
            width,
            height,
            info,
            container,
            SampleFormat::Float32,
        )
    }

    /// [`CogWriter::create`] with a choice of sample format.
    pub fn create_as(
        path: &Path,
        grid: Option<&Grid>,
        width: usize,
        height: usize,
        info: &BandInfo,
        container: Container,
        format: SampleFormat,
    ) -> Result<Self> {
        if width == 0 || height == 0 || width > u32::MAX as usize || height > u32::MAX as usize {
            return Err(Error::Usage(format!(
                "{}: cannot write a {height} × {width} image",
                path.display()
            )));
        }
        let mut dims = vec![(height, width)];
        while let Some(&(h, w)) = dims.last().filter(|(h, w)| *h.max(w) > TILE) {
            dims.push((h.div_ceil(2), w.div_ceil(2)));
        }
        let mut levels: Vec<Level> = Vec::with_capacity(dims.len());
        for (k, &(h, w)) in dims.iter().enumerate() {
            let tmp = crate::raster::tmp_name(&path.with_extension(format!("L{k}")));
            // Errors name the file the caller asked for, not the temporary.
            let f = match std::fs::File::create(&tmp) {
                Ok(f) => f,
                Err(e) => {
                    for l in &levels {
                        let _ = std::fs::remove_file(&l.tmp);
                    }
                    return Err(Error::io(path, e));
                }
            };
            levels.push(Level {
                w,
                h,
                buf: Vec::new(),
                rows_in: 0,
                tmp,
                file: std::io::BufWriter::new(f),
                sizes: Vec::new(),
            });
        }
        Ok(CogWriter {
            path: path.to_path_buf(),
            grid: grid.copied(),
            info: OwnedInfo {
                description: info.description.to_string(),
                unit: info.unit.to_string(),
                metadata: info
                    .metadata
                    .iter()
                    .map(|(k, v)| (k.to_string(), v.clone()))
                    .collect(),
            },
            container,
            format,
            levels,
            stats: Stats::default(),
            done: false,
        })
    }

    /// Append rows (each `width` wide) below those already pushed.
    pub fn push(&mut self, rows: ArrayView2<f64>) -> Result<()> {
        let l = &self.levels[0];
        if rows.ncols() != l.w || l.rows_in + rows.nrows() > l.h {
            return Err(Error::Usage(format!(
                "{}: pushing {} × {} rows at row {} of a {} × {} image",
                self.path.display(),
                rows.nrows(),
                rows.ncols(),
                l.rows_in,
                l.h,
                l.w
            )));
        }
        if self.format == SampleFormat::Byte {
            if let Some(((r, c), x)) = rows
                .indexed_iter()
                .find(|(_, x)| !(x.is_nan() || (x.fract() == 0.0 && (0.0..255.0).contains(*x))))
            {
                return Err(Error::Usage(format!(
                    "{}: {x} at row {}, column {c} is not a whole number 0–254 for a Byte band",
                    self.path.display(),
                    l.rows_in + r
                )));
            }
        }
        let v: Vec<f32> = rows.iter().map(|&x| x as f32).collect();
        self.stats.add(&v);
        self.push_level(0, v, rows.nrows())
    }

    fn push_level(&mut self, k: usize, rows: Vec<f32>, n: usize) -> Result<()> {
        let lv = &mut self.levels[k];
        lv.buf.extend_from_slice(&rows);
        lv.rows_in += n;
        loop {
            let lv = &mut self.levels[k];
            let buffered = lv.buf.len() / lv.w;
            let last = lv.rows_in == lv.h;
            if !(buffered >= TILE || (last && buffered > 0)) {
                return Ok(());
            }
            let take = buffered.min(TILE);
            let band: Vec<f32> = lv.buf.drain(..take * lv.w).collect();
            let band = Array2::from_shape_vec((take, lv.w), band).expect("band shape");
            let format = self.format;
            let lv = &mut self.levels[k];
            for t in compress_level(band.view(), format) {
                lv.file.write_all(&t).map_err(|e| Error::io(&lv.tmp, e))?;
                lv.sizes.push(t.len() as u64);
            }
            if k + 1 < self.levels.len() {
                let half = halve(band.view(), format);
                let n = half.nrows();
                self.push_level(k + 1, half.into_raw_vec_and_offset().0, n)?;
            }
        }
    }

    /// Write the file (see the type's documentation).
    pub fn finish(mut self) -> Result<()> {
        let res = self.assemble();
        self.cleanup();
        res
    }

    fn assemble(&mut self) -> Result<()> {
        if let Some(l) = self.levels.iter().find(|l| l.rows_in != l.h) {
            return Err(Error::Usage(format!(
                "{}: {} of {} rows were written",
                self.path.display(),
                l.rows_in,
                l.h
            )));
        }
        for l in &mut self.levels {
            l.file.flush().map_err(|e| Error::io(&l.tmp, e))?;
        }
        let info = BandInfo {
            description: &self.info.description,
            unit: &self.info.unit,
            metadata: &self
                .info
                .metadata
                .iter()
                .map(|(k, v)| (k.as_str(), v.clone()))
                .collect::<Vec<_>>(),
        };
        let data_bytes: u64 = self
            .levels
            .iter()
            .flat_map(|l| &l.sizes)
            .map(|s| s + 8)
            .sum();
        let ntiles: u64 = self.levels.iter().map(|l| l.sizes.len() as u64).sum();
        let big = self.container == Container::BigTiff
            || data_bytes + 1_000_000 + 64 * ntiles > u32::MAX as u64;
        let w = Width { big };
        let ghost = ghost_block();
        let header_len = if big { 16 } else { 8 };
        let mut pos = (header_len + ghost.len()) as u64;
        pos += pos % 2;
        let grid = self.grid;
        let xml = gdal_metadata(&info, &self.stats);
        let main = |k: usize| (k == 0).then_some((grid.as_ref(), xml.as_str()));
        let format = self.format;
        let mut ifd_pos = Vec::new();
        for (k, l) in self.levels.iter().enumerate() {
            ifd_pos.push(pos);
            pos += ifd_size(
                &level_tags(k, (l.h, l.w), &l.sizes, main(k), &w, &[], format),
                &w,
            );
            pos += pos % 2;
        }
        // Data: smallest overview first, full resolution last.
        let mut offsets: Vec<Vec<u64>> = vec![Vec::new(); self.levels.len()];
        let data_start = pos;
        for k in (0..self.levels.len()).rev() {
            for s in &self.levels[k].sizes {
                offsets[k].push(pos + 4);
                pos += s + 8;
            }
        }
        let tmp = crate::raster::tmp_name(&self.path);
        let res = (|| -> Result<()> {
            let f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
            let mut out = std::io::BufWriter::new(f);
            let mut head = Vec::with_capacity(data_start as usize);
            if big {
                head.extend_from_slice(b"II\x2b\x00\x08\x00\x00\x00");
                head.extend_from_slice(&ifd_pos[0].to_le_bytes());
            } else {
                head.extend_from_slice(b"II\x2a\x00");
                head.extend_from_slice(&(ifd_pos[0] as u32).to_le_bytes());
            }
            head.extend_from_slice(&ghost);
            for (k, l) in self.levels.iter().enumerate() {
                pad_to(&mut head, ifd_pos[k]);
                let tags = level_tags(k, (l.h, l.w), &l.sizes, main(k), &w, &offsets[k], format);
                let next = ifd_pos.get(k + 1).copied().unwrap_or(0);
                write_ifd(&mut head, &tags, ifd_pos[k], next, &w);
            }
            pad_to(&mut head, data_start);
            out.write_all(&head).map_err(|e| Error::io(&tmp, e))?;
            for l in self.levels.iter().rev() {
                let mut r = std::io::BufReader::new(
                    std::fs::File::open(&l.tmp).map_err(|e| Error::io(&l.tmp, e))?,
                );
                let mut t = Vec::new();
                for &s in &l.sizes {
                    t.resize(s as usize, 0);
                    r.read_exact(&mut t).map_err(|e| Error::io(&l.tmp, e))?;
                    out.write_all(&(s as u32).to_le_bytes())
                        .map_err(|e| Error::io(&tmp, e))?;
                    out.write_all(&t).map_err(|e| Error::io(&tmp, e))?;
                    out.write_all(&t[t.len() - 4..])
                        .map_err(|e| Error::io(&tmp, e))?;
                }
            }
            let f = out
                .into_inner()
                .map_err(|e| Error::io(&tmp, e.into_error()))?;
            f.sync_all().map_err(|e| Error::io(&tmp, e))?;
            debug_assert_eq!(f.metadata().map(|m| m.len()).unwrap_or(pos), pos);
            std::fs::rename(&tmp, &self.path).map_err(|e| Error::io(&self.path, e))
        })();
        if res.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        res
    }

    fn cleanup(&mut self) {
        if !self.done {
            for l in &self.levels {
                let _ = std::fs::remove_file(&l.tmp);
            }
            self.done = true;
        }
    }
}

impl Drop for CogWriter {
    /// An abandoned writer leaves no temporary behind.
    fn drop(&mut self) {
        self.cleanup();
    }
}

/// GDAL's structural metadata block (gcore/gdal_priv.h, COG driver): a fixed first line giving
/// the size of the rest.
fn ghost_block() -> Vec<u8> {
    let body = "LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\nBLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ";
    format!(
        "GDAL_STRUCTURAL_METADATA_SIZE={:06} bytes\n{body}",
        body.len()
    )
    .into_bytes()
}

fn pad_to(out: &mut Vec<u8>, pos: u64) {
    debug_assert!(out.len() as u64 <= pos);
    out.resize(pos as usize, 0);
}

/// The next overview: each pixel the mean of the valid (non-NaN) pixels of its 2 × 2 block
/// (float32), or the first valid pixel in row order (Byte).
fn halve(a: ArrayView2<f32>, format: SampleFormat) -> Array2<f32> {
    let (h, w) = a.dim();
    if format == SampleFormat::Byte {
        return Array2::from_shape_fn((h.div_ceil(2), w.div_ceil(2)), |(r, c)| {
            (2 * r..(2 * r + 2).min(h))
                .flat_map(|i| (2 * c..(2 * c + 2).min(w)).map(move |j| (i, j)))
                .map(|ij| a[ij])
                .find(|v| !v.is_nan())
                .unwrap_or(f32::NAN)
        });
    }
    Array2::from_shape_fn((h.div_ceil(2), w.div_ceil(2)), |(r, c)| {
        let (mut s, mut n) = (0.0f64, 0u32);
        for i in 2 * r..(2 * r + 2).min(h) {
            for j in 2 * c..(2 * c + 2).min(w) {
                let v = a[(i, j)];
                if v.is_finite() {
                    s += v as f64;
                    n += 1;
                }
            }
        }
        if n == 0 {
            f32::NAN
        } else {
            (s / n as f64) as f32
        }
    })
}

/// Every tile of one level, DEFLATE-compressed after the floating-point predictor; tiles at the
/// right and bottom edges are padded with no-data.
fn compress_level(a: ArrayView2<f32>, format: SampleFormat) -> Vec<Vec<u8>> {
    let (h, w) = a.dim();
    let (ty, tx) = (h.div_ceil(TILE), w.div_ceil(TILE));
    (0..ty * tx)
        .into_par_iter()
        .map(|t| {
            let (r0, c0) = ((t / tx) * TILE, (t % tx) * TILE);
            let mut raw = Vec::with_capacity(TILE * TILE * 4);
            let mut row = vec![f32::NAN; TILE];
            for r in r0..r0 + TILE {
                row.fill(f32::NAN);
                if r < h {
                    for (c, v) in row
                        .iter_mut()
                        .enumerate()
                        .take(w.saturating_sub(c0).min(TILE))
                    {
                        *v = a[(r, c0 + c)];
                    }
                }
                match format {
                    SampleFormat::Float32 => raw.extend_from_slice(&float_predictor(&row)),
                    SampleFormat::Byte => raw.extend_from_slice(&byte_predictor(&row)),
                }
            }
            let mut z = ZlibEncoder::new(Vec::new(), Compression::new(6));
            z.write_all(&raw).expect("writing to memory");
            z.finish().expect("writing to memory")
        })
        .collect()
}

/// TIFF Technical Note 3's floating-point predictor on one row: the bytes of the (big-endian)
/// values are regrouped by significance (all most significant bytes first), then each byte is
/// replaced by its difference from the previous one (libtiff `fpDiff`).
fn float_predictor(row: &[f32]) -> Vec<u8> {
    let n = row.len();
    let mut b = vec![0u8; 4 * n];
    for (i, v) in row.iter().enumerate() {
        for (k, byte) in v.to_be_bytes().into_iter().enumerate() {
            b[k * n + i] = byte;
        }
    }
    for j in (1..b.len()).rev() {
        b[j] = b[j].wrapping_sub(b[j - 1]);
    }
    b
}

/// TIFF's horizontal predictor (Predictor = 2) on one row of bytes (NaN → [`BYTE_NODATA`]):
/// each byte minus its left neighbour, modulo 256.
fn byte_predictor(row: &[f32]) -> Vec<u8> {
    let b: Vec<u8> = row
        .iter()
        .map(|&v| if v.is_nan() { BYTE_NODATA } else { v as u8 })
        .collect();
    let mut out = b.clone();
    for j in 1..b.len() {
        out[j] = b[j].wrapping_sub(b[j - 1]);
    }
    out
}

/// Offsets are 4 bytes (classic TIFF) or 8 (BigTIFF).
struct Width {
    big: bool,
}

/// One IFD entry: tag, field type, count, and the value bytes (little-endian).
struct Entry {
    tag: u16,
    kind: u16,
    count: u64,
    bytes: Vec<u8>,
}

const SHORT: u16 = 3;
const LONG: u16 = 4;
const ASCII: u16 = 2;
const DOUBLE: u16 = 12;
const LONG8: u16 = 16;

fn shorts(tag: u16, v: &[u16]) -> Entry {
    Entry {
        tag,
        kind: SHORT,
        count: v.len() as u64,
        bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}
fn longs(tag: u16, v: &[u32]) -> Entry {
    Entry {
        tag,
        kind: LONG,
        count: v.len() as u64,
        bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}
fn doubles(tag: u16, v: &[f64]) -> Entry {
    Entry {
        tag,
        kind: DOUBLE,
        count: v.len() as u64,
        bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect(),
    }
}
fn ascii(tag: u16, s: &str) -> Entry {
    let mut bytes = s.as_bytes().to_vec();
    bytes.push(0);
    Entry {
        tag,
        kind: ASCII,
        count: bytes.len() as u64,
        bytes,
    }
}

/// The tags of one level; `offsets` may be empty while laying out (the sizes are the same).
fn level_tags(
    level: usize,
    (h, w): (usize, usize),
    sizes: &[u64],
    main: Option<(Option<&Grid>, &str)>,
    width: &Width,
    offsets: &[u64],
    format: SampleFormat,
) -> Vec<Entry> {
    let n = sizes.len();
    let byte_nodata = BYTE_NODATA.to_string();
    let (bits, predictor, sample_format, nodata) = match format {
        SampleFormat::Float32 => (32, 3, 3, "nan"),
        SampleFormat::Byte => (8, 2, 1, byte_nodata.as_str()),
    };
    let offsets: Vec<u64> = if offsets.is_empty() {
        vec![0; n]
    } else {
        offsets.to_vec()
    };
    let mut e = vec![
        longs(254, &[u32::from(level > 0)]),
        longs(256, &[w as u32]),
        longs(257, &[h as u32]),
        shorts(258, &[bits]),
        shorts(259, &[8]),
        shorts(262, &[1]),
        shorts(277, &[1]),
        shorts(284, &[1]),
        shorts(317, &[predictor]),
        shorts(322, &[TILE as u16]),
        shorts(323, &[TILE as u16]),
        if width.big {
            Entry {
                tag: 324,
                kind: LONG8,
                count: n as u64,
                bytes: offsets.iter().flat_map(|x| x.to_le_bytes()).collect(),
            }
        } else {
            longs(324, &offsets.iter().map(|&x| x as u32).collect::<Vec<_>>())
        },
        longs(325, &sizes.iter().map(|&t| t as u32).collect::<Vec<_>>()),
        shorts(339, &[sample_format]),
        ascii(42113, nodata),
    ];
    if let Some((grid, xml)) = main {
        if let Some(grid) = grid {
            let s = grid.spacing;
            e.push(doubles(33550, &[s, s, 0.0]));
            e.push(doubles(33922, &[0.0, 0.0, 0.0, grid.x0, grid.y0, 0.0]));
            let keys = geokeys(&grid.crs);
            e.push(shorts(34735, &keys.directory));
            e.push(doubles(34736, &keys.doubles));
            e.push(ascii(34737, &keys.ascii));
        }
        e.push(ascii(42112, xml));
    }
    e.sort_by_key(|x| x.tag);
    e
}

/// GDAL's XML metadata (tag 42112): band description, unit and statistics, and dataset items.
fn gdal_metadata(info: &BandInfo, stats: &Stats) -> String {
    let esc = |s: &str| {
        s.replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
    };
    let mut s = String::from("<GDALMetadata>\n");
    for (k, v) in info.metadata {
        s.push_str(&format!("  <Item name=\"{}\">{}</Item>\n", esc(k), esc(v)));
    }
    s.push_str(&format!(
        "  <Item name=\"DESCRIPTION\" sample=\"0\" role=\"description\">{}</Item>\n",
        esc(info.description)
    ));
    if !info.unit.is_empty() {
        s.push_str(&format!(
            "  <Item name=\"UNITTYPE\" sample=\"0\" role=\"unittype\">{}</Item>\n",
            esc(info.unit)
        ));
    }
    for (k, v) in stats.items() {
        s.push_str(&format!("  <Item name=\"{k}\" sample=\"0\">{v}</Item>\n"));
    }
    s.push_str("</GDALMetadata>");
    s
}

fn ifd_size(tags: &[Entry], w: &Width) -> u64 {
    let (head, entry, next, inline) = if w.big { (8, 20, 8, 8) } else { (2, 12, 4, 4) };
    let extra: u64 = tags
        .iter()
        .filter(|t| t.bytes.len() > inline)
        .map(|t| t.bytes.len() as u64 + (t.bytes.len() as u64 % 2))
        .sum();
    head + entry * tags.len() as u64 + next + extra
}

/// Serialise one IFD at file position `at` (== `out.len()`), with out-of-line values after it.
fn write_ifd(out: &mut Vec<u8>, tags: &[Entry], at: u64, next: u64, w: &Width) {
    debug_assert_eq!(out.len() as u64, at);
    let (head, entry, nextb, inline) = if w.big {
        (8u64, 20u64, 8u64, 8usize)
    } else {
        (2, 12, 4, 4)
    };
    let mut extra_pos = at + head + entry * tags.len() as u64 + nextb;
    let mut extra = Vec::new();
    if w.big {
        out.extend_from_slice(&(tags.len() as u64).to_le_bytes());
    } else {
        out.extend_from_slice(&(tags.len() as u16).to_le_bytes());
    }
    for t in tags {
        out.extend_from_slice(&t.tag.to_le_bytes());
        out.extend_from_slice(&t.kind.to_le_bytes());
        if w.big {
            out.extend_from_slice(&t.count.to_le_bytes());
        } else {
            out.extend_from_slice(&(t.count as u32).to_le_bytes());
        }
        if t.bytes.len() <= inline {
            let mut v = t.bytes.clone();
            v.resize(inline, 0);
            out.extend_from_slice(&v);
        } else {
            if w.big {
                out.extend_from_slice(&extra_pos.to_le_bytes());
            } else {
                out.extend_from_slice(&(extra_pos as u32).to_le_bytes());
            }
            extra.extend_from_slice(&t.bytes);
            extra_pos += t.bytes.len() as u64;
            if t.bytes.len() % 2 == 1 {
                extra.push(0);
                extra_pos += 1;
            }
        }
    }
    if w.big {
        out.extend_from_slice(&next.to_le_bytes());
    } else {
        out.extend_from_slice(&(next as u32).to_le_bytes());
    }
    out.extend_from_slice(&extra);
}

/// The three GeoTIFF key tags.
struct GeoKeys {
    directory: Vec<u16>,
    doubles: Vec<f64>,
    ascii: String,
}

/// GeoKeys (OGC GeoTIFF 1.1) for a user-defined projected CRS on the Moon sphere:
/// a user-defined geographic CRS (2048 = 32767) whose citation names datum, ellipsoid and
/// prime meridian in the form GDAL reads ("GCS Name = …|Datum = …|Ellipsoid = …|Primem = …|"),
/// semi-axes 1 737 400 m, and the coordinate transformation with its parameters.
fn geokeys(crs: &Crs) -> GeoKeys {
    let mut keys: Vec<(u16, u16, u16, u16)> = Vec::new(); // (id, location, count, value)
    let mut dbl = Vec::new();
    let mut asc = String::new();
    let mut push_ascii = |keys: &mut Vec<(u16, u16, u16, u16)>, id: u16, s: &str| {
        let start = asc.len() as u16;
        asc.push_str(s);
        asc.push('|');
        keys.push((id, 34737, (s.len() + 1) as u16, start));
    };
    let mut push_dbl = |keys: &mut Vec<(u16, u16, u16, u16)>, id: u16, v: f64| {
        keys.push((id, 34736, 1, dbl.len() as u16));
        dbl.push(v);
    };
    keys.push((1024, 0, 1, 1)); // GTModelType: projected
    keys.push((1025, 0, 1, 1)); // GTRasterType: PixelIsArea
    push_ascii(&mut keys, 1026, &crs.name());
    keys.push((2048, 0, 1, 32767)); // GeodeticCRS: user-defined
    push_ascii(
        &mut keys,
        2049,
        "GCS Name = Moon (2015) - Sphere / Ocentric|Datum = Moon (2015) - Sphere|Ellipsoid = Moon (2015) - Sphere|Primem = Reference Meridian",
    );
    keys.push((2050, 0, 1, 32767)); // GeodeticDatum: user-defined
    keys.push((2054, 0, 1, 9102)); // GeogAngularUnits: degree
    keys.push((2056, 0, 1, 32767)); // Ellipsoid: user-defined
    push_dbl(&mut keys, 2057, MOON_RADIUS_M);
    push_dbl(&mut keys, 2058, MOON_RADIUS_M);
    keys.push((3072, 0, 1, 32767)); // ProjectedCRS: user-defined
    keys.push((3074, 0, 1, 32767)); // Projection: user-defined
    let (ct, params): (u16, Vec<(u16, f64)>) = match *crs {
        // CT_Equirectangular: ProjCenterLat, ProjCenterLong, ProjStdParallel1.
        Crs::Equirectangular { lon_0 } => (17, vec![(3078, 0.0), (3088, lon_0), (3089, 0.0)]),
        // CT_PolarStereographic: ProjNatOriginLat, ProjScaleAtNatOrigin, ProjStraightVertPoleLong.
        Crs::PolarStereographic { north } => (
            15,
            vec![
                (3081, if north { 90.0 } else { -90.0 }),
                (3092, 1.0),
                (3095, 0.0),
            ],
        ),
        // CT_Stereographic: ProjCenterLong, ProjCenterLat, ProjScaleAtNatOrigin.
        Crs::Stereographic { lat_0, lon_0 } => {
            (14, vec![(3088, lon_0), (3089, lat_0), (3092, 1.0)])
        }
        // CT_Orthographic: ProjCenterLong, ProjCenterLat.
        Crs::Orthographic { lat_0, lon_0 } => (21, vec![(3088, lon_0), (3089, lat_0)]),
    };
    keys.push((3075, 0, 1, ct));
    keys.push((3076, 0, 1, 9001)); // ProjLinearUnits: metre
    for (id, v) in params.into_iter().chain([(3082, 0.0), (3083, 0.0)]) {
        push_dbl(&mut keys, id, v);
    }
    keys.sort_by_key(|k| k.0);
    let mut directory = vec![1, 1, 0, keys.len() as u16];
    for (id, loc, count, value) in keys {
        directory.extend_from_slice(&[id, loc, count, value]);
    }
    GeoKeys {
        directory,
        doubles: dbl,
        ascii: asc,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statistics_are_gdals_over_finite_values() {
        let mut st = Stats::default();
        st.add(&[1.0, 2.0, f32::NAN]);
        st.add(&[3.0]);
        let items: std::collections::HashMap<_, _> = st.items().into_iter().collect();
        assert_eq!(items["STATISTICS_MINIMUM"], "1");
        assert_eq!(items["STATISTICS_MAXIMUM"], "3");
        assert_eq!(items["STATISTICS_MEAN"], "2");
        let sd: f64 = items["STATISTICS_STDDEV"].parse().unwrap();
        assert!((sd - (2.0f64 / 3.0).sqrt()).abs() < 1e-15);
        assert_eq!(items["STATISTICS_VALID_PERCENT"], "75");
        assert!(Stats::default().items().is_empty());
    }

    #[test]
    fn float_predictor_matches_its_definition() {
        // Two values: bytes regrouped by significance, then differenced.
        let b = float_predictor(&[1.0, 2.0]);
        // 1.0 = 3F 80 00 00, 2.0 = 40 00 00 00 → planes 3F 40 | 80 00 | 00 00 | 00 00.
        let planes = [0x3Fu8, 0x40, 0x80, 0x00, 0, 0, 0, 0];
        let mut want = planes;
        for j in (1..8).rev() {
            want[j] = planes[j].wrapping_sub(planes[j - 1]);
        }
        assert_eq!(b, want);
    }

    #[test]
    fn overviews_average_valid_pixels_only() {
        let a = Array2::from_shape_vec(
            (3, 3),
            vec![1.0, 3.0, 5.0, f32::NAN, 2.0, 7.0, 4.0, 4.0, f32::NAN],
        )
        .unwrap();
        let h = halve(a.view(), SampleFormat::Float32);
        assert_eq!(h.dim(), (2, 2));
        assert_eq!(h[(0, 0)], 2.0);
        assert_eq!(h[(0, 1)], 6.0);
        assert_eq!(h[(1, 0)], 4.0);
        assert!(h[(1, 1)].is_nan());
        // Byte bands (counts, classes): the first valid pixel, never a mean.
        let b = halve(a.view(), SampleFormat::Byte);
        assert_eq!(b[(0, 0)], 1.0);
        assert_eq!(b[(0, 1)], 5.0);
        assert_eq!(b[(1, 0)], 4.0);
        assert!(b[(1, 1)].is_nan());
    }

    #[test]
    fn byte_predictor_differences_bytes_and_marks_no_data() {
        assert_eq!(
            byte_predictor(&[3.0, 5.0, 2.0, f32::NAN]),
            vec![3, 2, 253, 253]
        );
    }

    /// A Byte band round-trips through the tiff crate with its no-data value, and values that
    /// do not fit are refused naming the file and the pixel.
    #[test]
    fn byte_bands_round_trip_and_refuse_what_does_not_fit() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-byte-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("count.tif");
        let a = Array2::from_shape_fn((300, 270), |(i, j)| {
            if i == 7 && j == 9 {
                f64::NAN
            } else {
                ((i + 2 * j) % 5) as f64
            }
        });
        let info = BandInfo {
            description: "a count",
            unit: "",
            metadata: &[],
        };
        let mut w = CogWriter::create_as(
            &path,
            None,
            270,
            300,
            &info,
            Container::Auto,
            SampleFormat::Byte,
        )
        .unwrap();
        w.push(a.view()).unwrap();
        w.finish().unwrap();
        let r = read_tiff(&path).unwrap();
        assert_eq!(r.nodata, Some(255.0));
        assert_eq!(r.images, 2);
        for ((i, j), &v) in r.data.indexed_iter() {
            let want = if (i, j) == (7, 9) { 255.0 } else { a[(i, j)] };
            assert_eq!(v, want, "({i}, {j})");
        }
        let mut w = CogWriter::create_as(
            &path,
            None,
            2,
            1,
            &info,
            Container::Auto,
            SampleFormat::Byte,
        )
        .unwrap();
        let e = w
            .push(Array2::from_elem((1, 2), 2.5).view())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("count.tif") && e.contains("2.5") && e.contains("row 0"),
            "{e}"
        );
        drop(w);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn ghost_block_declares_its_own_size() {
        let g = String::from_utf8(ghost_block()).unwrap();
        let (first, rest) = g.split_once('\n').unwrap();
        let n: usize = first
            .trim_start_matches("GDAL_STRUCTURAL_METADATA_SIZE=")
            .trim_end_matches(" bytes")
            .parse()
            .unwrap();
        assert_eq!(n, rest.len());
    }
}

/// GDAL's geotransform of a north-up GeoTIFF from ModelPixelScale (sx, sy, …) and one
/// ModelTiepoint (i, j, k, x, y, z): (x − i·sx, sx, 0, y + j·sy, 0, −sy); `None` if either is
/// too short or a scale is not positive.
pub fn geotransform_from(scale: &[f64], tie: &[f64]) -> Option<[f64; 6]> {
    (scale.len() >= 2 && tie.len() >= 6 && scale[0] > 0.0 && scale[1] > 0.0).then(|| {
        [
            tie[3] - tie[0] * scale[0],
            scale[0],
            0.0,
            tie[4] + tie[1] * scale[1],
            0.0,
            -scale[1],
        ]
    })
}

/// A single-band raster read from a (Geo)TIFF, with its georeferencing where it has one.
#[derive(Debug, Clone)]
pub struct TiffRaster {
    pub data: Array2<f64>,
    /// GDAL geotransform from ModelPixelScale + ModelTiepoint (north-up files), if present.
    pub geotransform: Option<[f64; 6]>,
    /// GDAL_NODATA, if present.
    pub nodata: Option<f64>,
    /// How many images (full resolution + overviews) the file holds.
    pub images: usize,
}

/// Read the first image of a TIFF (any sample type the tiff crate decodes: 8/16/32-bit integers,
/// float32/64; the first channel of multi-channel images), with the tiff crate.
pub fn read_tiff(path: &Path) -> Result<TiffRaster> {
    use tiff::decoder::{Decoder, DecodingResult};
    use tiff::tags::Tag;
    let bad =
        |e: tiff::TiffError| Error::Usage(format!("{}: not a readable TIFF: {e}", path.display()));
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut d = Decoder::new(std::io::BufReader::new(f)).map_err(bad)?;
    let (w, h) = d.dimensions().map_err(bad)?;
    let channels = match d.colortype().map_err(bad)? {
        tiff::ColorType::Gray(_) => 1,
        tiff::ColorType::GrayA(_) => 2,
        tiff::ColorType::RGB(_) => 3,
        tiff::ColorType::RGBA(_) => 4,
        other => {
            return Err(Error::Usage(format!(
                "{}: colour type {other:?} is not supported; give a single-band raster",
                path.display()
            )))
        }
    };
    let scale = d.find_tag(Tag::ModelPixelScaleTag).map_err(bad)?;
    let tie = d.find_tag(Tag::ModelTiepointTag).map_err(bad)?;
    let geotransform = match (scale, tie) {
        (Some(s), Some(t)) => {
            let s = s.into_f64_vec().map_err(bad)?;
            let t = t.into_f64_vec().map_err(bad)?;
            geotransform_from(&s, &t)
        }
        _ => None,
    };
    let nodata = d
        .find_tag(Tag::GdalNodata)
        .map_err(bad)?
        .and_then(|v| v.into_string().ok())
        .and_then(|s| s.trim_matches(char::from(0)).trim().parse::<f64>().ok());
    let img = d.read_image().map_err(bad)?;
    let v: Vec<f64> = match img {
        DecodingResult::U8(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::U16(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::U32(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::I8(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::I16(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::I32(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::F32(v) => v.into_iter().map(f64::from).collect(),
        DecodingResult::F64(v) => v,
        _ => {
            return Err(Error::Usage(format!(
                "{}: sample type not supported (use 8/16/32-bit integers or float32/64)",
                path.display()
            )))
        }
    };
    let v: Vec<f64> = v.into_iter().step_by(channels).collect();
    let data = Array2::from_shape_vec((h as usize, w as usize), v)
        .map_err(|e| Error::Usage(format!("{}: {e}", path.display())))?;
    let mut images = 1;
    while d.more_images() {
        d.next_image().map_err(bad)?;
        images += 1;
    }
    Ok(TiffRaster {
        data,
        geotransform,
        nodata,
        images,
    })
}

/// What a GeoTIFF's GeoKeys say its CRS is, when it is one of ours.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GeoTiffCrs {
    Projected(Crs),
    /// Longitude/latitude in degrees on the Moon sphere.
    Geographic,
}

/// Read the CRS from GeoKeys (tags 34735/34736): the Moon sphere (semi-major axis 1 737 400 m,
/// no flattening) with one of the coordinate transformations [`geokeys`] writes — CT 17
/// (equirectangular, standard parallel 0), 15 (polar stereographic, pole longitude 0), 14/16
/// (stereographic, scale 1), 21 (orthographic) — metres, no false easting/northing; or a
/// geographic model. Anything else is refused with the key that does not fit.
pub fn crs_from_geokeys(path: &Path, dir: &[u16], doubles: &[f64]) -> Result<GeoTiffCrs> {
    let bad = |why: String| {
        Error::Usage(format!("{}: GeoKeys: {why}; give a DEM on the IAU 2015 Moon sphere in an equirectangular, polar stereographic, stereographic or orthographic projection (or reproject it with gdalwarp)", path.display()))
    };
    if dir.len() < 4 || dir[0] != 1 {
        return Err(bad("no GeoKey directory".into()));
    }
    let n = dir[3] as usize;
    if dir.len() < 4 + 4 * n {
        return Err(bad("the key directory is shorter than it says".into()));
    }
    let key = |id: u16| -> Option<f64> {
        dir[4..4 + 4 * n]
            .chunks_exact(4)
            .find(|k| k[0] == id)
            .and_then(|k| match k[1] {
                0 => Some(k[3] as f64),
                34736 => doubles.get(k[3] as usize).copied(),
                _ => None,
            })
    };
    let a = key(2057).ok_or_else(|| {
        bad("no semi-major axis (key 2057): not a Moon CRS sphere sfsfuse can check".into())
    })?;
    let b = key(2058).unwrap_or(a);
    let inv_f = key(2059).unwrap_or(0.0);
    if (a - MOON_RADIUS_M).abs() > 1.0 || (b - a).abs() > 1.0 || inv_f != 0.0 {
        return Err(bad(format!(
            "the ellipsoid is a = {a} m, b = {b} m, 1/f = {inv_f}, not the 1 737 400 m Moon sphere"
        )));
    }
    match key(1024).map(|v| v as u16) {
        Some(2) => return Ok(GeoTiffCrs::Geographic),
        Some(1) => {}
        other => {
            return Err(bad(format!(
                "model type (key 1024) {other:?} is neither projected nor geographic"
            )))
        }
    }
    if key(3076).is_some_and(|u| u != 9001.0) {
        return Err(bad("linear units (key 3076) are not metres".into()));
    }
    if key(3082).unwrap_or(0.0) != 0.0 || key(3083).unwrap_or(0.0) != 0.0 {
        return Err(bad(
            "false easting/northing (keys 3082/3083) are not 0".into()
        ));
    }
    let lat = key(3089).or(key(3081)).unwrap_or(0.0);
    let lon = key(3088).or(key(3080)).unwrap_or(0.0);
    let crs = match key(3075).map(|v| v as u16) {
        Some(17) => {
            if key(3078).unwrap_or(0.0) != 0.0 || lat != 0.0 {
                return Err(bad(
                    "equirectangular with a standard parallel or origin latitude other than 0"
                        .into(),
                ));
            }
            Crs::Equirectangular { lon_0: lon }
        }
        Some(15) => {
            if key(3095).unwrap_or(0.0) != 0.0 {
                return Err(bad(
                    "polar stereographic with a pole longitude (key 3095) other than 0".into(),
                ));
            }
            Crs::PolarStereographic {
                north: key(3081).unwrap_or(lat) > 0.0,
            }
        }
        Some(14) | Some(16) => {
            if key(3092).or(key(3093)).unwrap_or(1.0) != 1.0 {
                return Err(bad("stereographic with a scale factor other than 1".into()));
            }
            Crs::Stereographic {
                lat_0: lat,
                lon_0: lon,
            }
        }
        Some(21) => Crs::Orthographic {
            lat_0: lat,
            lon_0: lon,
        },
        other => {
            return Err(bad(format!(
                "coordinate transformation (key 3075) {other:?} is not one sfsfuse reads"
            )))
        }
    };
    Ok(GeoTiffCrs::Projected(crs))
}
