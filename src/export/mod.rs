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

mod cog;
#[cfg(feature = "gdal")]
pub mod gdal;
mod geokeys;
mod read;

pub use cog::CogWriter;

use geokeys::*;
pub use geokeys::{crs_from_geokeys, GeoTiffCrs};
pub use read::{geotransform_from, read_tiff, TiffRaster};

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

/// A [`SampleFormat::Byte`] band takes whole numbers 0–254 and NaN (no data): the first other
/// value of `rows` (whose first row is row `first_row` of the image) is refused naming `path`,
/// the value and its pixel.
pub(crate) fn check_byte_values(
    path: &Path,
    rows: ArrayView2<f64>,
    first_row: usize,
) -> Result<()> {
    match rows
        .indexed_iter()
        .find(|(_, x)| !(x.is_nan() || (x.fract() == 0.0 && (0.0..255.0).contains(*x))))
    {
        Some(((r, c), x)) => Err(Error::Usage(format!(
            "{}: {x} at row {}, column {c} is not a whole number 0–254 for a Byte band",
            path.display(),
            first_row + r
        ))),
        None => Ok(()),
    }
}

/// The stored byte of a [`SampleFormat::Byte`] value ([`check_byte_values`] passed): NaN is
/// [`BYTE_NODATA`].
pub(crate) fn byte_sample(v: f32) -> u8 {
    if v.is_nan() {
        BYTE_NODATA
    } else {
        v as u8
    }
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
