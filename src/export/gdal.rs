//! GeoTIFF/COG export through GDAL's own COG driver (cargo feature `gdal`, system libgdal).
//!
//! The band is built in GDAL's MEM driver (geotransform, CRS, no-data, description, unit,
//! metadata, statistics) and copied with the COG driver: DEFLATE, 256-px blocks, BigTIFF when
//! needed, and per [`SampleFormat`] the same choices as the pure-Rust writer in [`super`]:
//! float32 with NaN no-data, the floating-point predictor and averaged overviews, or Byte with
//! [`BYTE_NODATA`], horizontal differencing and nearest-neighbour overviews (a count or a class
//! is never averaged). The CRS is given to GDAL by its IAU_2015 code where it has one, else as
//! [`crate::grid::Crs::wkt`] (WKT2 on the IAU_2015:30100 Moon sphere). Written under a temporary name and renamed.

use super::{BandInfo, SampleFormat, BYTE_NODATA};
use crate::error::{Error, Result};
use crate::grid::Grid;
use gdal::raster::{Buffer, RasterCreationOptions};
use gdal::spatial_ref::SpatialRef;
use gdal::{DriverManager, Metadata};
use ndarray::ArrayView2;
use std::path::Path;

/// Write `data` on `grid` to `path` as a float32 COG with GDAL.
pub fn write_geotiff(
    path: &Path,
    grid: &Grid,
    data: ArrayView2<f64>,
    info: &BandInfo,
) -> Result<()> {
    write_geotiff_as(path, grid, data, info, SampleFormat::Float32)
}

/// [`write_geotiff`] with a choice of sample format. A Byte band takes whole numbers 0–254 and
/// NaN (written as [`BYTE_NODATA`]); anything else is refused naming the pixel.
pub fn write_geotiff_as(
    path: &Path,
    grid: &Grid,
    data: ArrayView2<f64>,
    info: &BandInfo,
    format: SampleFormat,
) -> Result<()> {
    let fail = |what: &str, e: gdal::errors::GdalError| {
        Error::Usage(format!("{}: GDAL {what}: {e}", path.display()))
    };
    super::check_shape(path, grid, data)?;
    if format == SampleFormat::Byte {
        super::check_byte_values(path, data, 0)?;
    }
    let mem = DriverManager::get_driver_by_name("MEM").map_err(|e| fail("MEM driver", e))?;
    let mut ds = match format {
        SampleFormat::Float32 => mem.create_with_band_type::<f32, _>("", grid.cols, grid.rows, 1),
        SampleFormat::Byte => mem.create_with_band_type::<u8, _>("", grid.cols, grid.rows, 1),
    }
    .map_err(|e| fail("create", e))?;
    ds.set_geo_transform(&grid.geotransform())
        .map_err(|e| fail("geotransform", e))?;
    let srs = match grid.crs.iau_2015() {
        Some(code) => SpatialRef::from_definition(code),
        None => SpatialRef::from_wkt(&grid.crs.wkt()),
    }
    .map_err(|e| fail("CRS", e))?;
    ds.set_spatial_ref(&srs).map_err(|e| fail("CRS", e))?;
    for (k, v) in info.metadata {
        ds.set_metadata_item(k, v, "")
            .map_err(|e| fail("metadata", e))?;
    }
    {
        let mut band = ds.rasterband(1).map_err(|e| fail("band", e))?;
        let nodata = match format {
            SampleFormat::Float32 => f64::NAN,
            SampleFormat::Byte => f64::from(BYTE_NODATA),
        };
        band.set_no_data_value(Some(nodata))
            .map_err(|e| fail("no-data", e))?;
        band.set_description(info.description)
            .map_err(|e| fail("description", e))?;
        let unit = std::ffi::CString::new(info.unit)
            .map_err(|_| Error::Usage(format!("unit {:?} contains NUL", info.unit)))?;
        // SAFETY: the band handle is valid while `band` lives; GDAL copies the string.
        let rv = unsafe { gdal_sys::GDALSetRasterUnitType(band.c_rasterband(), unit.as_ptr()) };
        if rv != gdal_sys::CPLErr::CE_None {
            return Err(Error::Usage(format!(
                "{}: GDAL could not set the unit",
                path.display()
            )));
        }
        let values: Vec<f32> = data.iter().map(|&v| v as f32).collect();
        let mut stats = super::Stats::default();
        stats.add(&values);
        for (k, v) in stats.items() {
            band.set_metadata_item(k, &v, "")
                .map_err(|e| fail("statistics", e))?;
        }
        let size = (grid.cols, grid.rows);
        match format {
            SampleFormat::Float32 => band.write((0, 0), size, &mut Buffer::new(size, values)),
            SampleFormat::Byte => {
                let bytes = values.iter().map(|&v| super::byte_sample(v)).collect();
                band.write((0, 0), size, &mut Buffer::new(size, bytes))
            }
        }
        .map_err(|e| fail("write", e))?;
    }
    let resampling = match format {
        SampleFormat::Float32 => "RESAMPLING=AVERAGE",
        SampleFormat::Byte => "RESAMPLING=NEAREST",
    };
    let cog = DriverManager::get_driver_by_name("COG").map_err(|e| fail("COG driver", e))?;
    let options = RasterCreationOptions::from_iter([
        "COMPRESS=DEFLATE",
        "PREDICTOR=YES",
        "BLOCKSIZE=256",
        "OVERVIEWS=AUTO",
        resampling,
        "BIGTIFF=IF_SAFER",
    ]);
    let tmp = crate::raster::tmp_name(path);
    let copied = ds.create_copy(&cog, &tmp, &options);
    match copied {
        Ok(out) => drop(out),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(fail("COG copy", e));
        }
    }
    // GDAL closed the file; make it durable before it takes the final name.
    std::fs::File::open(&tmp)
        .and_then(|f| f.sync_all())
        .and_then(|()| std::fs::rename(&tmp, path))
        .map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            Error::io(path, e)
        })
}
