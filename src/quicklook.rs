//! Quick-look PNGs: hillshades of several DEMs side by side.
//!
//! Hillshade: Lambertian shading cos∠(n, s) of the surface normal from central differences,
//! lit from the cartographic default azimuth 315° (north-west) at 45° elevation, so that
//! craters read as depressions; values below 0 are clamped to black.

use crate::error::{Error, Result};
use crate::fusion::ops;
use crate::synth::direction;
use ndarray::Array2;
use std::path::Path;

/// Hillshade of `z` (metres) on a grid of `spacing` metres, as 8-bit grey.
pub fn hillshade(z: &Array2<f64>, spacing: f64) -> Array2<u8> {
    let (p, q) = ops::gradient(z.view(), spacing);
    let s = direction(45.0, 315.0);
    Array2::from_shape_fn(z.dim(), |ij| {
        let (p, q) = (p[ij], q[ij]);
        let c = (-p * s[0] - q * s[1] + s[2]) / (1.0 + p * p + q * q).sqrt();
        (c.clamp(0.0, 1.0) * 255.0).round() as u8
    })
}

/// Place equally sized panels side by side with a `gap`-pixel white separator and write a PNG.
pub fn write_panels(path: &Path, panels: &[Array2<u8>], gap: usize) -> Result<()> {
    let (h, w) = panels.first().map(|p| p.dim()).unwrap_or((0, 0));
    if panels.iter().any(|p| p.dim() != (h, w)) {
        return Err(Error::Usage(
            "quick-look panels must have equal sizes".into(),
        ));
    }
    let width = panels.len() * w + gap * panels.len().saturating_sub(1);
    let mut img = vec![255u8; width * h];
    for (k, p) in panels.iter().enumerate() {
        let x0 = k * (w + gap);
        for ((i, j), v) in p.indexed_iter() {
            img[i * width + x0 + j] = *v;
        }
    }
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, width as u32, h as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        let mut wr = enc.write_header().map_err(|e| Error::Png {
            path: path.into(),
            source: e,
        })?;
        wr.write_image_data(&img).map_err(|e| Error::Png {
            path: path.into(),
            source: e,
        })?;
    }
    crate::raster::write_atomic(path, &bytes)
}

/// Read the first channel of a PNG (8- or 16-bit, grey or colour; palettes expanded) as
/// numbers in the file's own scale (0–255 or 0–65535).
pub fn read_png(path: &Path) -> Result<Array2<f64>> {
    let bad = |e: png::DecodingError| {
        Error::Usage(format!("{}: not a readable PNG: {e}", path.display()))
    };
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut dec = png::Decoder::new(std::io::BufReader::new(f));
    dec.set_transformations(png::Transformations::EXPAND);
    let mut reader = dec.read_info().map_err(bad)?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| Error::Usage(format!("{}: image too large", path.display())))?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(bad)?;
    let channels = info.color_type.samples();
    let wide = info.bit_depth == png::BitDepth::Sixteen;
    let step = channels * if wide { 2 } else { 1 };
    let (w, h) = (info.width as usize, info.height as usize);
    let v: Vec<f64> = (0..w * h)
        .map(|k| {
            let o = k * step;
            if wide {
                u16::from_be_bytes([buf[o], buf[o + 1]]) as f64
            } else {
                buf[o] as f64
            }
        })
        .collect();
    Array2::from_shape_vec((h, w), v).map_err(|e| Error::Usage(format!("{}: {e}", path.display())))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_ground_shades_at_cos_45() {
        let h = hillshade(&Array2::zeros((4, 4)), 10.0);
        let want = (45f64.to_radians().cos() * 255.0).round() as u8;
        assert!(h.iter().all(|&v| v == want));
        // A slope facing the light (rising to the south-east) is brighter.
        let z = Array2::from_shape_fn((5, 5), |(i, j)| (i as f64 + j as f64) * 3.0);
        assert!(hillshade(&z, 10.0)[(2, 2)] > want);
    }
}
