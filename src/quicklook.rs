//! Quick-look PNGs: sheets of titled panels (pictures, hillshades, colour-mapped differences)
//! with colour bars and a scale bar ([`write_sheet`]), and block-mean thumbnails that let a
//! run of any size draw one ([`Thumbnail`]). Text uses the public-domain 8 × 8 VGA glyphs of
//! the `font8x8` crate.
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

/// An 8-bit RGB picture.
pub type Rgb = Array2<[u8; 3]>;

/// Colour of no-data pixels on a sheet.
const NODATA: [u8; 3] = [40, 44, 60];

/// The `lo`/`hi` quantiles (0–1) of the finite values; `None` without any.
pub fn quantiles(a: &Array2<f64>, lo: f64, hi: f64) -> Option<(f64, f64)> {
    let mut v: Vec<f64> = a.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    Some((at(lo), at(hi)))
}

/// Grey from `range` (black at its low end), no-data in a dark blue-grey.
pub fn grey(a: &Array2<f64>, (lo, hi): (f64, f64)) -> Rgb {
    let span = if hi > lo { hi - lo } else { 1.0 };
    a.mapv(|x| {
        if x.is_finite() {
            let g = (255.0 * ((x - lo) / span).clamp(0.0, 1.0)).round() as u8;
            [g, g, g]
        } else {
            NODATA
        }
    })
}

/// A grey picture as RGB.
pub fn rgb(a: &Array2<u8>) -> Rgb {
    a.mapv(|g| [g, g, g])
}

/// The diverging colour of t ∈ [−1, 1]: blue below 0, white at 0, red above.
fn diverging_colour(t: f64) -> [u8; 3] {
    let t = t.clamp(-1.0, 1.0);
    let fade = |x: f64| (255.0 * (1.0 - x.abs())).round() as u8;
    if t < 0.0 {
        [fade(t), fade(t), 255]
    } else {
        [255, fade(t), fade(t)]
    }
}

/// Signed values in ±`limit` as blue–white–red; no-data dark.
pub fn diverging(a: &Array2<f64>, limit: f64) -> Rgb {
    let l = if limit > 0.0 { limit } else { 1.0 };
    a.mapv(|x| {
        if x.is_finite() {
            diverging_colour(x / l)
        } else {
            NODATA
        }
    })
}

/// Draw `text` with its top-left corner at (`row`, `col`), the 8 × 8 public-domain VGA glyphs
/// of `font8x8` scaled by `scale`; characters it lacks are drawn as '?'.
pub fn draw_text(img: &mut Rgb, row: usize, col: usize, text: &str, scale: usize, colour: [u8; 3]) {
    use font8x8::UnicodeFonts;
    let (h, w) = img.dim();
    for (k, ch) in text.chars().enumerate() {
        let glyph = font8x8::BASIC_FONTS
            .get(ch)
            .or_else(|| font8x8::BASIC_FONTS.get('?'))
            .unwrap_or([0; 8]);
        for (gy, bits) in glyph.iter().enumerate() {
            for gx in 0..8 {
                if bits >> gx & 1 == 0 {
                    continue;
                }
                for dy in 0..scale {
                    for dx in 0..scale {
                        let (r, c) = (row + gy * scale + dy, col + (k * 8 + gx) * scale + dx);
                        if r < h && c < w {
                            img[(r, c)] = colour;
                        }
                    }
                }
            }
        }
    }
}

/// A colour bar: the ramp over 0…1 ([`grey_ramp`], [`diverging_ramp`]) and its end labels.
pub struct ColourBar {
    pub ramp: fn(f64) -> [u8; 3],
    pub low: String,
    pub high: String,
}

/// One labelled panel of a quick-look sheet: a title above the picture and, optionally, a
/// colour bar below it.
pub struct Panel {
    pub title: String,
    pub picture: Rgb,
    pub bar: Option<ColourBar>,
}

/// The grey ramp of a colour bar over 0…1.
pub fn grey_ramp(t: f64) -> [u8; 3] {
    let g = (255.0 * t.clamp(0.0, 1.0)).round() as u8;
    [g, g, g]
}

/// The diverging ramp of a colour bar over 0…1 (−1…1 mapped).
pub fn diverging_ramp(t: f64) -> [u8; 3] {
    diverging_colour(2.0 * t - 1.0)
}

/// The text scale of the colour bars' labels on panels `pw` pixels wide: 2 (16 px a character)
/// where every bar's low and high label fit side by side with a character's room between
/// them, else 1.
fn bar_label_scale<'a>(labels: impl Iterator<Item = (&'a str, &'a str)>, pw: usize) -> usize {
    let mut labels = labels;
    if labels.all(|(lo, hi)| (lo.chars().count() + hi.chars().count() + 1) * 16 <= pw) {
        2
    } else {
        1
    }
}

/// Draw a scale bar of `metres` (a round length near a fifth of the width) in the lower left of
/// a picture whose pixels are `pixel_m` metres, labelled in km or m.
pub fn scale_bar(img: &mut Rgb, pixel_m: f64) {
    let (h, w) = img.dim();
    let target = w as f64 * pixel_m / 5.0;
    let p10 = 10f64.powf(target.log10().floor());
    let len_m = [5.0, 2.0, 1.0]
        .iter()
        .map(|k| k * p10)
        .find(|&l| l <= target)
        .unwrap_or(p10);
    let len_px = (len_m / pixel_m).round() as usize;
    if len_px < 4 || h < 40 {
        return;
    }
    let (r0, c0) = (h - 16, 10);
    for r in r0 - 1..r0 + 5 {
        for c in c0 - 1..(c0 + len_px + 1).min(w) {
            img[(r, c)] = if r == r0 - 1 || r == r0 + 4 || c == c0 - 1 || c == c0 + len_px {
                [0, 0, 0]
            } else {
                [255, 255, 255]
            };
        }
    }
    let label = if len_m >= 1000.0 {
        format!("{} km", len_m / 1000.0)
    } else {
        format!("{len_m} m")
    };
    draw_text(img, r0 - 20, c0, &label, 2, [255, 255, 255]);
}

/// Lay `panels` (equal picture sizes) out `columns` to a row, each with its title and colour
/// bar, on white, and write the PNG atomically.
pub fn write_sheet(path: &Path, panels: &[Panel], columns: usize) -> Result<()> {
    let Some(first) = panels.first() else {
        return Err(Error::Usage("a quick-look sheet needs a panel".into()));
    };
    let (ph, pw) = first.picture.dim();
    if panels.iter().any(|p| p.picture.dim() != (ph, pw)) {
        return Err(Error::Usage(
            "quick-look panels must have equal sizes".into(),
        ));
    }
    let (title_h, bar_h, gap) = (24, 40, 12);
    let cell_h = title_h + ph + bar_h;
    let cols = columns.max(1).min(panels.len());
    let rows = panels.len().div_ceil(cols);
    let (height, width) = (
        rows * cell_h + (rows + 1) * gap,
        cols * pw + (cols + 1) * gap,
    );
    let mut img: Rgb = Array2::from_elem((height, width), [255, 255, 255]);
    // Titles at double size where all fit, else single; never past a panel.
    let title_scale = if panels.iter().all(|p| p.title.chars().count() * 16 <= pw) {
        2
    } else {
        1
    };
    // Colour-bar labels likewise: double size where every bar's two fit with a character's
    // room between them, else single (a narrow region's panels).
    let label_scale = bar_label_scale(
        panels
            .iter()
            .filter_map(|p| p.bar.as_ref())
            .map(|b| (b.low.as_str(), b.high.as_str())),
        pw,
    );
    for (k, p) in panels.iter().enumerate() {
        let (y0, x0) = (
            gap + (k / cols) * (cell_h + gap),
            gap + (k % cols) * (pw + gap),
        );
        let title: String = p.title.chars().take(pw / 8).collect();
        draw_text(&mut img, y0 + 4, x0, &title, title_scale, [0, 0, 0]);
        for ((i, j), v) in p.picture.indexed_iter() {
            img[(y0 + title_h + i, x0 + j)] = *v;
        }
        if let Some(ColourBar {
            ramp,
            low: lo,
            high: hi,
        }) = &p.bar
        {
            let yb = y0 + title_h + ph + 6;
            for j in 0..pw {
                let c = ramp(j as f64 / (pw.max(2) - 1) as f64);
                for i in 0..10 {
                    img[(yb + i, x0 + j)] = c;
                }
            }
            draw_text(&mut img, yb + 14, x0, lo, label_scale, [0, 0, 0]);
            let right = x0 + pw.saturating_sub(hi.chars().count() * 8 * label_scale);
            draw_text(&mut img, yb + 14, right, hi, label_scale, [0, 0, 0]);
        }
    }
    let flat: Vec<u8> = img.iter().flat_map(|p| p.iter().copied()).collect();
    let mut bytes = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut bytes, width as u32, height as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        // fdeflate's fast mode: a quick look is for looking at; it takes a quarter of the
        // default's time (0.1 s of a 512² run) for a file ≈ 1.6× as large.
        enc.set_compression(png::Compression::Fast);
        let png_err = |e| Error::Png {
            path: path.into(),
            source: e,
        };
        let mut wr = enc.write_header().map_err(png_err)?;
        wr.write_image_data(&flat).map_err(png_err)?;
    }
    crate::raster::write_atomic(path, &bytes)
}

/// Block means of a large raster, accumulated band of rows by band of rows: a `factor` ×
/// `factor` block per pixel, finite values only, so a quick look of any region costs a few
/// small arrays.
pub struct Thumbnail {
    pub factor: usize,
    sum: Array2<f64>,
    count: Array2<u32>,
}

impl Thumbnail {
    /// For a `rows × cols` raster, at most `max_side` pixels on the longer side.
    pub fn new(rows: usize, cols: usize, max_side: usize) -> Thumbnail {
        let factor = rows.max(cols).div_ceil(max_side.max(1)).max(1);
        let dim = (rows.div_ceil(factor), cols.div_ceil(factor));
        Thumbnail {
            factor,
            sum: Array2::zeros(dim),
            count: Array2::zeros(dim),
        }
    }

    /// Add the rows starting at raster row `row0`.
    pub fn add(&mut self, row0: usize, rows: ndarray::ArrayView2<f64>) {
        for ((i, j), &v) in rows.indexed_iter() {
            if v.is_finite() {
                let ij = ((row0 + i) / self.factor, j / self.factor);
                self.sum[ij] += v;
                self.count[ij] += 1;
            }
        }
    }

    /// The block means (NaN where a block had no finite value).
    pub fn means(&self) -> Array2<f64> {
        ndarray::Zip::from(&self.sum)
            .and(&self.count)
            .map_collect(|&s, &n| if n > 0 { s / n as f64 } else { f64::NAN })
    }
}

#[cfg(test)]
mod sheet_tests {
    use super::*;

    #[test]
    fn thumbnails_are_block_means_of_finite_values() {
        let a = Array2::from_shape_fn((5, 7), |(i, j)| {
            if (i, j) == (0, 1) {
                f64::NAN
            } else {
                (i * 7 + j) as f64
            }
        });
        let mut t = Thumbnail::new(5, 7, 4);
        assert_eq!(t.factor, 2);
        t.add(0, a.slice(ndarray::s![0..3, ..]));
        t.add(3, a.slice(ndarray::s![3..5, ..]));
        let m = t.means();
        assert_eq!(m.dim(), (3, 4));
        // Block (0, 0): 0, NaN, 7, 8.
        assert_eq!(m[(0, 0)], 5.0);
        // Block (2, 3): row 4, column 6 alone.
        assert_eq!(m[(2, 3)], 34.0);
    }

    /// A narrow panel's colour-bar labels drop to single size rather than run into each other
    /// (a real crop on a 300 m grid: 162-px panels, "0.0109" and "0.0310" at 16 px a
    /// character need 208 px).
    #[test]
    fn colour_bar_labels_shrink_on_narrow_panels() {
        assert_eq!(bar_label_scale([("0.0109", "0.0310")].into_iter(), 208), 2);
        assert_eq!(bar_label_scale([("0.0109", "0.0310")].into_iter(), 162), 1);
        assert_eq!(
            bar_label_scale([("-2.4", "+2.4"), ("0.0109", "0.0310")].into_iter(), 162),
            1
        );
        assert_eq!(bar_label_scale(std::iter::empty(), 10), 2);
    }

    #[test]
    fn text_is_drawn_from_the_font() {
        let mut img: Rgb = Array2::from_elem((20, 40), [255, 255, 255]);
        draw_text(&mut img, 2, 2, "1", 1, [0, 0, 0]);
        let ink = img.iter().filter(|p| **p == [0, 0, 0]).count();
        // The VGA '1' is [12, 14, 12, 12, 12, 12, 63, 0], bit 0 leftmost: 2 + 3 + 4 × 2 + 6
        // set pixels, its flag (bit 1 of the second row) left of the stem.
        assert_eq!(ink, 19);
        assert_eq!(img[(3, 3)], [0, 0, 0]);
        assert_eq!(img[(2, 3)], [255, 255, 255]);
        assert!(img
            .slice(ndarray::s![.., 12..])
            .iter()
            .all(|p| *p == [255, 255, 255]));
    }
}
