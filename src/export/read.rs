//! Reading TIFFs back (the tiff crate): the first image, its georeferencing and no-data.

use super::*;

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
