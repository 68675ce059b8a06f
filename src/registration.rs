//! Registration of an observation to the input DEM: the translation that best aligns the image
//! with the DEM's own shading under the observation's geometry.
//!
//! M3's selenolocation (the LOC backplane of an L1B product) is uncertain by about 200 m
//! between observations and 450 m absolute (RMS), and some observations are off by
//! kilometres: one to several grid pixels at 140 m. LOLA's geolocation is good to tens of
//! metres. An image fused where it is displaced puts its craters' shading beside the DEM's
//! craters, and two observations displaced differently disagree about every slope; so each
//! observation is aligned to the DEM before it is fused (docs/science.md, "Registration").
//!
//! The estimate compares, over a window, the image blurred to the DEM's resolution (σ_B) with
//! the DEM rendered under the image's own Sun and view (constant albedo), both band-passed (the
//! difference of Gaussians σ_B − 4σ_B, masked), by their normalised cross-correlation
//! c(d) = Σ a(x)·b(x − d) / √(Σ a(x)² · Σ b(x − d)²) over the pixels valid in both, for every
//! whole-pixel displacement d within the search radius; the peak is refined by a parabola in
//! each axis.

use crate::fusion::ops;
use crate::fusion::Directions;
use crate::grid::{interpolate, Interpolation};
use crate::photometry::ReflectanceModel;
use crate::spectral::{self, Dct2d};
use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The fewest pixels valid in both band-passed fields at the peak for a displacement to count.
pub const MIN_PIXELS: usize = 16384;

/// The lowest normalised correlation at the peak for a displacement to count: below it the
/// image and the DEM's shading share too little structure (a flat region, an image mostly in
/// shadow, a DEM much coarser than the features) to say where the image lies. An image of
/// other relief reaches 0.04 over a 256² window (test below).
pub const MIN_CORRELATION: f64 = 0.2;

/// How many times the best correlation beyond the peak's own width the peak must reach.
pub const PEAK_RATIO: f64 = 1.5;

/// The lowest correlation at the peak for a run to move an observation by its estimate. Under
/// a high Sun the shading is faint and the estimate strays (Sun 75° high: 1.4–2.6 px from the
/// truth at correlations 0.21–0.31 on the synthetic scenes; docs/science.md "Registration").
pub const APPLY_CORRELATION: f64 = 0.5;

/// The longest estimate against the DEM's shading on undisplaced synthetic scenes, by the
/// Sun's elevation above the horizon: (elevation in degrees, length in grid pixels). Measured
/// with the DEM 4× coarser than the grid on 256² and 512² scenes (seeds 10, 1 and 3; Sun
/// azimuths 0–315° in steps of 45°, 24 estimates per elevation and size; at 45° and above also
/// on 512² scenes through `run`, 24 pairs of Suns drawn at random, 20–60° high), the DEM's
/// shadows cast under a Sun lowered by [`shadow_lowering`] up to 25° (since 2026-12-07;
/// with them cast under the Sun itself the bias was 1.2–1.3 px from 10° to 20°, 0.76 px at
/// 25°). The estimate is
/// biased by what the DEM cannot render: relief sharper than its point spread, and under a low
/// Sun shadows larger than its own; under a high Sun the shading is faint against the albedo
/// (docs/science.md, "Registration"; `cargo run --release --example registration_bias`
/// measures it).
pub const DEM_BIAS: [(f64, f64); 8] = [
    (10.0, 0.71),
    (15.0, 0.52),
    (20.0, 0.52),
    (25.0, 0.27),
    (30.0, 0.54),
    (45.0, 0.64),
    (60.0, 1.32),
    (75.0, 2.63),
];

/// The DEM's point spread σ_B, grid pixels, of the scenes [`DEM_BIAS`] was measured on: a DEM
/// 4× coarser than the grid ([`crate::fusion::dem_psf_sigma`]; LDEM_64 under a 140 m grid is
/// at 2.95 px).
pub const DEM_BIAS_PSF: f64 = crate::fusion::dem_psf_sigma(4.0);

/// How the bias against the DEM grows with its point spread: × (σ_B/[`DEM_BIAS_PSF`]) to this
/// power above it. The same 256² scenes and Suns with the DEM 6× and 8× coarser (σ_B 4.2 and
/// 5.7 px) gave 0.71 / 0.88 px at most under a 30° Sun and 0.99 / 1.42 px at 45°, against
/// 0.54 / 0.64 px at 4× (× 1.31–1.55 and × 1.63–2.2 for σ_B × 1.5 and × 2; the power 1.3 gives
/// × 1.69 and × 2.46).
pub const DEM_BIAS_PSF_POWER: f64 = 1.3;

/// The same for an estimate relative to an earlier observation fused alone, by the higher of
/// the two Suns: 0.34 px at most while both stand 55° high or lower (14 pairs of Suns on three
/// 256² scenes, and the 512² pairs through `run`), 0.68 px where the earlier image has a Sun
/// 60° high (its single-image fusion is the least sharp), 1.54 px for two Suns 70° high.
pub const RELATIVE_BIAS: [(f64, f64); 3] = [(55.0, 0.35), (60.0, 0.70), (70.0, 1.60)];

/// An estimate is applied from this many times the longest bias of its kind at its Sun's
/// elevation ([`DEM_BIAS`], [`RELATIVE_BIAS`]): so moving an observation by its estimate
/// leaves at most half the displacement it corrects, and the margin covers scenes whose bias
/// runs longer than the synthetic ones'.
pub const BIAS_MARGIN: f64 = 2.0;

/// The shortest estimate against the DEM ever applied, grid pixels, whatever the elevation.
pub const DEM_MIN_APPLY_PX: f64 = 1.25;

/// The shortest estimate relative to another observation ever applied, grid pixels.
pub const RELATIVE_MIN_APPLY_PX: f64 = 0.75;

/// `table` (ascending in its first column, two points or more) at `x`: linear between its
/// points, its first value below them, and continued along its last segment above them.
fn piecewise_linear(table: &[(f64, f64)], x: f64) -> f64 {
    let n = table.len();
    if x <= table[0].0 {
        return table[0].1;
    }
    // The segment that holds x; the last one beyond the table.
    let i = table.iter().position(|&(t, _)| x <= t).unwrap_or(n - 1);
    let ((x0, y0), (x1, y1)) = (table[i - 1], table[i]);
    y0 + (y1 - y0) * (x - x0) / (x1 - x0)
}

/// The displacement, grid pixels, from which an estimate against the DEM's shading under a
/// Sun `elevation_deg` above the horizon, the DEM's point spread σ_B = `psf_px`, is applied:
/// [`BIAS_MARGIN`] times the longest bias of [`DEM_BIAS`] there, grown for a DEM coarser than
/// the table's by (σ_B/[`DEM_BIAS_PSF`])^[`DEM_BIAS_PSF_POWER`], at least [`DEM_MIN_APPLY_PX`]
/// (with LDEM_64 under a 140 m grid, σ_B = 2.95 px: 1.25 px under Suns 13–40° high, 1.35 px
/// at 45°, 1.5 px at 10°, 2.8 px at 60°); without an elevation, never (infinity).
pub fn dem_apply_px(elevation_deg: f64, psf_px: f64) -> f64 {
    if !elevation_deg.is_finite() {
        return f64::INFINITY;
    }
    let coarser = (psf_px / DEM_BIAS_PSF).max(1.0).powf(DEM_BIAS_PSF_POWER);
    (BIAS_MARGIN * piecewise_linear(&DEM_BIAS, elevation_deg) * coarser).max(DEM_MIN_APPLY_PX)
}

/// The displacement, grid pixels, from which an estimate relative to an earlier observation is
/// applied, the higher of the two Suns `higher_elevation_deg` above the horizon:
/// [`BIAS_MARGIN`] times the longest bias of [`RELATIVE_BIAS`] there, at least
/// [`RELATIVE_MIN_APPLY_PX`] (0.75 px while both Suns stand 55° high or lower, 1.4 px at 60°);
/// without an elevation, never (infinity).
pub fn relative_apply_px(higher_elevation_deg: f64) -> f64 {
    if !higher_elevation_deg.is_finite() {
        return f64::INFINITY;
    }
    (BIAS_MARGIN * piecewise_linear(&RELATIVE_BIAS, higher_elevation_deg))
        .max(RELATIVE_MIN_APPLY_PX)
}

/// The mean elevation, degrees, of the Sun over the pixels of a window where `image` is finite
/// (its usable pixels, cast shadows included): 90° less the mean of the to-Sun zenith angles
/// arccos s_z, `sun` the unit vectors to the Sun in the grid frame (z up) — the mean
/// [`crate::ingest::Survey::mean_sun`] takes over a whole footprint. NaN without such a pixel.
/// Over a long polar strip the Sun's elevation changes along the track, so each window's
/// estimate is judged by the Sun it was made under ([`dem_apply_px`], [`relative_apply_px`]).
pub fn mean_sun_elevation_deg(
    image: ArrayView2<f64>,
    sun: ArrayView2<crate::photometry::Vec3f>,
) -> f64 {
    let (sum, n) = image
        .iter()
        .zip(sun.iter())
        .filter(|(r, s)| r.is_finite() && s[2].is_finite())
        .fold((0.0, 0usize), |(sum, n), (_, s)| {
            (
                sum + f64::from(s[2]).clamp(-1.0, 1.0).acos().to_degrees(),
                n + 1,
            )
        });
    if n == 0 {
        f64::NAN
    } else {
        90.0 - sum / n as f64
    }
}

/// Albedo the DEM is rendered with: the correlation does not depend on the image's scale, and
/// this is a typical lunar single-scattering albedo at 1.2 µm for the Hapke model.
const RENDER_ALBEDO: f64 = 0.4;

/// The displacement of an image relative to the DEM's shading, grid pixels: its content lies
/// at `rows` (southward) and `cols` (eastward) from where the DEM puts the same relief.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Shift {
    pub rows: f64,
    pub cols: f64,
    /// Normalised cross-correlation at the peak, and where the image lies (d = 0).
    pub correlation: f64,
    pub correlation_in_place: f64,
    /// Pixels valid in both fields at the peak.
    pub pixels: usize,
}

impl Shift {
    /// Its length, grid pixels.
    pub fn length(&self) -> f64 {
        self.rows.hypot(self.cols)
    }
}

/// Where an observation's swath pixels are placed back from where its LOC puts them: metres
/// along the grid's x and y, possibly drifting along the swath (an attitude drift moves the
/// selenolocation error with time, so with the line). Knots at swath lines, in increasing
/// order: piecewise linear in the line between them, constant beyond the first and the last
/// (the plan puts those at the first and last lines it registered on). No knot: no
/// displacement; one: a translation.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Displacement {
    pub knots: Vec<Knot>,
}

/// One knot of a [`Displacement`]: the displacement at swath line `line`, metres along the
/// grid's x and y.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Knot {
    pub line: f64,
    pub m: [f64; 2],
}

impl Displacement {
    /// The same displacement at every line.
    pub fn constant(m: [f64; 2]) -> Displacement {
        Displacement {
            knots: vec![Knot { line: 0.0, m }],
        }
    }

    /// Through `knots`, (line, [x, y] metres), ordered by line.
    pub fn through(knots: &[(f64, [f64; 2])]) -> Displacement {
        Displacement {
            knots: knots.iter().map(|&(line, m)| Knot { line, m }).collect(),
        }
    }

    /// Whether it moves no pixel.
    pub fn is_none(&self) -> bool {
        self.knots.iter().all(|k| k.m == [0.0; 2])
    }

    /// The displacement at swath line `line`, metres along x and y.
    pub fn at(&self, line: f64) -> [f64; 2] {
        let k = &self.knots;
        match k.iter().position(|k| k.line > line) {
            _ if k.is_empty() => [0.0; 2],
            Some(0) => k[0].m,
            None => k[k.len() - 1].m,
            Some(i) => {
                let (a, b) = (k[i - 1], k[i]);
                let t = (line - a.line) / (b.line - a.line);
                [0, 1].map(|c| a.m[c] + t * (b.m[c] - a.m[c]))
            }
        }
    }

    /// The largest component, metres, it reaches at any line: how far beyond a grid LOC may
    /// put the pixels that land on it.
    pub fn reach_m(&self) -> f64 {
        self.knots
            .iter()
            .map(|k| k.m[0].abs().max(k.m[1].abs()))
            .fold(0.0, f64::max)
    }
}

/// The DEM `dem` (grid `spacing` metres) rendered under `sun` and `view` by `model` at a
/// constant albedo: R at the central-difference slopes, 0 in the DEM's cast shadows
/// (`cast_shadows`); NaN where the DEM is not finite or the surface is unlit or unseen.
pub fn render(
    dem: ArrayView2<f64>,
    spacing: f64,
    model: &dyn ReflectanceModel,
    sun: &Directions,
    view: &Directions,
) -> Array2<f64> {
    render_lowered(dem, spacing, model, (sun, view), 0.0)
}

/// Set `r` to 0 where `dem` casts a shadow under `sun`, lowered by [`shadow_lowering`] of its
/// elevation for a DEM of point spread `psf_px` (its azimuth kept): where, marching from the
/// pixel towards the Sun in half-pixel steps, the DEM (bilinear) rises above the ray at that
/// elevation. The march stops at the grid's edge, at [`SHADOW_REACH`] pixels, or where the ray
/// clears the DEM's highest point. The images' shadows are dark too; without them the
/// estimate's bias under a Sun 10° high was 1.6–2.0 px, with them 1.0–1.2 px.
fn cast_shadows(
    dem: ArrayView2<f64>,
    spacing: f64,
    (sun, psf_px): (&Directions, f64),
    r: &mut Array2<f64>,
) {
    let (ny, nx) = dem.dim();
    let top = dem
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .fold(f64::NEG_INFINITY, f64::max);
    Zip::indexed(r).par_for_each(|(i, j), r| {
        let (s, z0) = (sun.at(i, j), dem[(i, j)]);
        let h = s[0].hypot(s[1]);
        if !(r.is_finite() && h > 0.0 && s[2] > 0.0) {
            return;
        }
        // The ray's rise per pixel: tan e, or tan of the lowered elevation.
        let e = s[2].clamp(-1.0, 1.0).asin();
        let cut = shadow_lowering(e.to_degrees(), psf_px);
        let tan = if cut > 0.0 {
            ((1.0 - cut) * e).tan()
        } else {
            s[2] / h
        };
        // Grid rows run south: towards the Sun, the row falls by its northward component.
        let (east, north, rise) = (s[0] / h, s[1] / h, tan * spacing);
        let reach = ((top - z0) / rise).min(SHADOW_REACH);
        let mut t = 0.5;
        while t <= reach {
            let (row, col) = (i as f64 - t * north, j as f64 + t * east);
            if row < 0.0 || col < 0.0 || row > (ny - 1) as f64 || col > (nx - 1) as f64 {
                return;
            }
            if interpolate(dem, row, col, Interpolation::Bilinear, false) > z0 + t * rise {
                *r = 0.0;
                return;
            }
            t += 0.5;
        }
    });
}

/// The longest shadow [`render`] looks for, pixels.
pub const SHADOW_REACH: f64 = 400.0;

/// The share of its elevation by which [`render_lowered`] lowers a Sun `elevation_deg` above
/// the horizon to cast the shadows of a DEM of point spread σ_B = `psf_px` grid pixels:
/// [`SHADOW_LOWERING`] × min(1, σ_B/[`DEM_BIAS_PSF`]) up to [`SHADOW_LOWERING_FULL_DEG`],
/// fading linearly to none at [`SHADOW_LOWERING_END_DEG`]. So with LDEM_64 under a 140 m grid
/// the shadows are cast under 0.7 of the Sun's elevation up to 25°, under the Sun itself from
/// 30°; a DEM as sharp as the image (an earlier observation fused alone) casts them under the
/// Sun itself.
///
/// Why: a DEM blurred by σ_B has lower rims and gentler walls than the relief the image sees,
/// so under a low Sun it casts smaller shadows than the image shows, and what it lacks lies on
/// the side away from the Sun: the correlation places the image that far from the Sun. On the
/// scenes of [`DEM_BIAS`] (256², 3 seeds × 8 azimuths, the DEM 4× coarser than the grid) the
/// mean bias is 1.07 / 1.08 / 0.88 / 0.59 px under Suns 10 / 15 / 20 / 25° high with the DEM's
/// shadows cast under the Sun itself, and 0.20 / 0.25 / 0.26 / 0.16 px under 0.7 of it (the
/// longest 1.29 / 1.23 / 1.15 / 0.76 px against 0.62 / 0.52 / 0.52 / 0.27 px). The best
/// factor lies near 0.65–0.7 there (lower for coarser DEMs). From 30° up the DEM's shadows are
/// few and lowering them gains little (at 30° the longest bias 0.54 → 0.52 px, under half the
/// 1.25 px floor either way) while it costs the peak's correlation (0.88 → 0.84 on average at
/// 30°, which left a segment over which the displacement drifts without a clear peak), so
/// there it is not done (docs/science.md, "Registration").
pub fn shadow_lowering(elevation_deg: f64, psf_px: f64) -> f64 {
    let fade = ((SHADOW_LOWERING_END_DEG - elevation_deg)
        / (SHADOW_LOWERING_END_DEG - SHADOW_LOWERING_FULL_DEG))
        .clamp(0.0, 1.0);
    SHADOW_LOWERING * (psf_px / DEM_BIAS_PSF).clamp(0.0, 1.0) * fade
}

/// The largest share of a Sun's elevation [`shadow_lowering`] takes off.
pub const SHADOW_LOWERING: f64 = 0.3;

/// The elevation, degrees, up to which [`shadow_lowering`] takes off its full share.
pub const SHADOW_LOWERING_FULL_DEG: f64 = 25.0;

/// The elevation, degrees, from which [`shadow_lowering`] takes off nothing.
pub const SHADOW_LOWERING_END_DEG: f64 = 30.0;

/// The DEM `dem` rendered as [`render`] does, but with its cast shadows cast under each
/// pixel's Sun lowered by [`shadow_lowering`] of its elevation for a DEM of point spread
/// `psf_px` grid pixels, its azimuth kept; the shading is the Sun's own. Where nothing is
/// lowered (σ_B = 0, or a Sun 30° high or more everywhere), the same as [`render`].
pub fn render_lowered(
    dem: ArrayView2<f64>,
    spacing: f64,
    model: &dyn ReflectanceModel,
    (sun, view): (&Directions, &Directions),
    psf_px: f64,
) -> Array2<f64> {
    let (p, q) = ops::gradient(dem, spacing);
    let mut out = Array2::from_elem(dem.dim(), f64::NAN);
    Zip::indexed(&mut out)
        .and(&p)
        .and(&q)
        .par_for_each(|(i, j), r, &p, &q| {
            let (s, v) = (sun.at(i, j), view.at(i, j));
            if !(p.is_finite() && q.is_finite() && s.iter().chain(&v).all(|c| c.is_finite())) {
                return;
            }
            let sh = model.shade_observed(p, q, RENDER_ALBEDO, &s, &v);
            if sh.lit && sh.r > 0.0 {
                *r = sh.r;
            }
        });
    cast_shadows(dem, spacing, (sun, psf_px), &mut out);
    out
}

/// The band-pass of `a` where it is finite: G_lo·a − G_hi·a with the Gaussians normalised over
/// the finite pixels (σ_lo = `lo`, σ_hi = `hi` pixels); NaN where `a` is not finite. `None`
/// when no pixel is finite.
pub fn band_pass(a: ArrayView2<f64>, lo: f64, hi: f64) -> Option<Array2<f64>> {
    let (ny, nx) = a.dim();
    let dct = Dct2d::new(ny, nx);
    let valid = a.mapv(f64::is_finite);
    let filled = a.mapv(|v| if v.is_finite() { v } else { 0.0 });
    let low = spectral::masked_gaussian(&dct, &filled, &valid, lo)?;
    let wide = spectral::masked_gaussian(&dct, &filled, &valid, hi)?;
    let mut out = low - wide;
    Zip::from(&mut out).and(&valid).for_each(|o, &v| {
        if !v {
            *o = f64::NAN;
        }
    });
    Some(out)
}

/// The displacement of `image` relative to `rendered` (the DEM's shading on the same grid),
/// searched over whole pixels within `search` in each axis and refined to a fraction of a pixel;
/// `psf` is the DEM's point spread σ_B in pixels (the image is blurred to it). `None` when the
/// peak lies on the search's edge (the displacement may be larger), or falls short of
/// [`MIN_CORRELATION`] or [`MIN_PIXELS`].
pub fn estimate(
    image: ArrayView2<f64>,
    rendered: ArrayView2<f64>,
    psf: f64,
    search: usize,
) -> Option<Shift> {
    let (a, b) = compared(image, rendered, psf)?;
    let lo = psf.max(1.0);
    let r = search as isize;
    let shifts: Vec<(isize, isize)> = (-r..=r)
        .flat_map(|dy| (-r..=r).map(move |dx| (dy, dx)))
        .collect();
    // The search on every other row and column (a quarter of the sums: the band-passed fields
    // vary over σ_B ≥ 1 px), then every pixel at the peak and its neighbours.
    let scores: Vec<(f64, usize)> = shifts
        .par_iter()
        .map(|&(dy, dx)| correlation(a.view(), b.view(), dy, dx, 2))
        .collect();
    // The first of equal maxima in row-major order: deterministic.
    let (best, _) =
        scores
            .iter()
            .enumerate()
            .fold(
                None,
                |acc: Option<(usize, &(f64, usize))>, (k, s)| match acc {
                    Some((_, b)) if b.0 >= s.0 => acc,
                    _ => Some((k, s)),
                },
            )?;
    let (dy, dx) = shifts[best];
    let at = |y: isize, x: isize| correlation(a.view(), b.view(), y, x, 1);
    let (c, n) = at(dy, dx);
    // The best correlation away from the peak (beyond its own width): a peak must stand out
    // of what relief unrelated to the image reaches over the search.
    let apart = (2.0 * lo).ceil() as isize + 1;
    let second = shifts
        .iter()
        .zip(&scores)
        .filter(|((y, x), _)| (y - dy).abs().max((x - dx).abs()) > apart)
        .map(|(_, s)| s.0)
        .fold(0.0, f64::max);
    if dy.abs() == r
        || dx.abs() == r
        || !(c >= MIN_CORRELATION && c >= PEAK_RATIO * second)
        || n < MIN_PIXELS
    {
        return None;
    }
    let near = |y: isize, x: isize| at(y, x).0;
    let vertex = |m: f64, z: f64, p: f64| {
        let den = m - 2.0 * z + p;
        if den < 0.0 {
            (0.5 * (m - p) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    Some(Shift {
        rows: dy as f64 + vertex(near(dy - 1, dx), c, near(dy + 1, dx)),
        cols: dx as f64 + vertex(near(dy, dx - 1), c, near(dy, dx + 1)),
        correlation: c,
        correlation_in_place: near(0, 0),
        pixels: n,
    })
}

/// The band-passed image and rendering [`estimate`] correlates.
fn compared(
    image: ArrayView2<f64>,
    rendered: ArrayView2<f64>,
    psf: f64,
) -> Option<(Array2<f64>, Array2<f64>)> {
    let lo = psf.max(1.0);
    let hi = 4.0 * lo;
    let a = band_pass(image, lo, hi)?;
    // The rendering of a DEM blurred by σ_B is already that blurred: only its long
    // wavelengths (albedo-free, but the image's are not) are taken out.
    let b = band_pass(rendered, 0.0, hi)?;
    Some((a, b))
}

/// Where on the window an estimate `s` of [`estimate`] (same `image`, `rendered` and `psf`)
/// was made: the mean of `values` (say, each pixel's swath line) weighted by each pixel's
/// share of the correlation at the peak's whole-pixel displacement, max(0, a(x)·b(x − d)).
/// Where the displacement drifts over the window the estimate is that of the pixels that
/// carry the correlation (a large crater's rim, say), not of the window's middle. `None` when
/// no pixel contributes.
pub fn where_estimated(
    image: ArrayView2<f64>,
    rendered: ArrayView2<f64>,
    psf: f64,
    s: &Shift,
    values: ArrayView2<f32>,
) -> Option<f64> {
    let (a, b) = compared(image, rendered, psf)?;
    let (dy, dx) = (s.rows.round() as isize, s.cols.round() as isize);
    let (ny, nx) = a.dim();
    let (mut sum, mut weight) = (0.0, 0.0);
    for i in (dy.max(0) as usize)..((ny as isize + dy.min(0)).max(0) as usize) {
        let bi = (i as isize - dy) as usize;
        for j in (dx.max(0) as usize)..((nx as isize + dx.min(0)).max(0) as usize) {
            let w = a[(i, j)] * b[(bi, (j as isize - dx) as usize)];
            let v = f64::from(values[(i, j)]);
            if w > 0.0 && v.is_finite() {
                sum += w * v;
                weight += w;
            }
        }
    }
    (weight > 0.0).then(|| sum / weight)
}

/// c(d) of the module documentation for d = (`dy`, `dx`) over every `step`-th row and column,
/// with the pixel count; sums in row order (deterministic).
fn correlation(
    a: ArrayView2<f64>,
    b: ArrayView2<f64>,
    dy: isize,
    dx: isize,
    step: usize,
) -> (f64, usize) {
    let (ny, nx) = a.dim();
    let (mut ab, mut aa, mut bb, mut n) = (0.0, 0.0, 0.0, 0usize);
    let rows = (dy.max(0) as usize)..((ny as isize + dy.min(0)) as usize);
    let cols = (dx.max(0) as usize)..((nx as isize + dx.min(0)) as usize);
    for i in rows.step_by(step) {
        let bi = (i as isize - dy) as usize;
        for j in cols.clone().step_by(step) {
            let (u, v) = (a[(i, j)], b[(bi, (j as isize - dx) as usize)]);
            if u.is_finite() && v.is_finite() {
                ab += u * v;
                aa += u * u;
                bb += v * v;
                n += 1;
            }
        }
    }
    let den = (aa * bb).sqrt();
    (if den > 0.0 { ab / den } else { 0.0 }, n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::{interpolate, Interpolation};
    use crate::synth::{generate, SceneSpec};

    /// The lengths from which estimates are applied, by hand from the tables: twice the bias
    /// bound, linear between the measured elevations, held below the first and continued
    /// along the last segment above the last, never under the floors; never without a Sun.
    #[test]
    fn estimates_are_applied_from_twice_their_bias_at_the_suns_elevation() {
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        // Against the DEM at the table's point spread (or finer): 2 × 0.52 = 1.04 at 20° and
        // 2 × 0.54 = 1.08 at 30°, under the 1.25 floor; 2 × 0.71 at 10°, 2 × (0.71 − 0.19/5) at 11°;
        // 2 × (0.64 + 0.68 × 1/3) at 50°; 2 × 1.32 at 60°; held at 2 × 0.71 below 10°;
        // 2 × (2.63 + 1.31) at 90°.
        let table = DEM_BIAS_PSF;
        assert!(close(dem_apply_px(20.0, table), 1.25));
        assert!(close(dem_apply_px(30.0, table), 1.25));
        assert!(close(dem_apply_px(10.0, table), 1.42));
        assert!(close(dem_apply_px(11.0, table), 2.0 * (0.71 - 0.19 / 5.0)));
        assert!(close(
            dem_apply_px(50.0, 1.0),
            2.0 * (0.64 + 0.68 * 5.0 / 15.0)
        ));
        assert!(close(dem_apply_px(60.0, table), 2.64));
        assert!(close(dem_apply_px(5.0, table), 1.42));
        assert!(close(dem_apply_px(90.0, table), 2.0 * (2.63 + 1.31)));
        // A DEM twice as coarse: × 2^1.3 (30°: 2 × 0.54 × 2.4623 = 2.659).
        let twice = dem_apply_px(30.0, 2.0 * table);
        assert!(
            (twice - 2.0 * 0.54 * 2f64.powf(1.3)).abs() < 1e-12 && twice > 2.65,
            "{twice}"
        );
        // Relative: the floor while both Suns stand 55° high or lower, then 2 × 0.70 at 60°,
        // 2 × 1.15 at 65°, 2 × 2.50 at 80°.
        assert!(close(relative_apply_px(20.0), 0.75));
        assert!(close(relative_apply_px(55.0), 0.75));
        assert!(close(relative_apply_px(60.0), 1.4));
        assert!(close(relative_apply_px(65.0), 2.3));
        assert!(close(relative_apply_px(80.0), 5.0));
        assert_eq!(dem_apply_px(f64::NAN, table), f64::INFINITY);
        assert_eq!(relative_apply_px(f64::NAN), f64::INFINITY);
    }

    /// A wall 45 m high on columns 20–24, 10 m pixels, the Sun due east and 20° high: the
    /// bilinear DEM reaches the wall's top at column 20, so a pixel of column j is in its cast
    /// shadow while 20 − j < 45 m/(10 m · tan e): under the Sun itself (4.5/tan 20° = 12.36)
    /// columns 8–19, and with the shadows cast at 0.7 of its elevation (14°, 4.5/tan 14° =
    /// 18.05) columns 2–19. Column 19, whose central-difference slope faces away from the Sun,
    /// is unlit (NaN) rather than shadowed, so 11 and 17 pixels west of the wall are 0. The
    /// shading is the Sun's own either way; with nothing lowered the rendering is [`render`]'s.
    #[test]
    fn the_dems_shadows_are_cast_under_the_lowered_sun() {
        let dem = Array2::from_shape_fn(
            (16, 64),
            |(_, j)| {
                if (20..25).contains(&j) {
                    45.0
                } else {
                    0.0
                }
            },
        );
        let view = Directions::Uniform([0.0, 0.0, 1.0]);
        let model = crate::photometry::Lambert;
        let sun_at = |deg: f64| {
            let e = deg.to_radians();
            Directions::Uniform([e.cos(), 0.0, e.sin()])
        };
        let west = |r: &Array2<f64>| (0..20).filter(|&j| r[(8, j)] == 0.0).count();
        let low = sun_at(20.0);
        let at = |psf: f64| render_lowered(dem.view(), 10.0, &model, (&low, &view), psf);
        assert_eq!(west(&at(0.0)), 11);
        let lowered = at(DEM_BIAS_PSF);
        assert_eq!(west(&lowered), 17);
        assert!(lowered[(8, 19)].is_nan() && lowered[(8, 1)] > 0.0);
        // The lit pixels keep the Sun's own shading: Lambert's ρ·cos i, i = 70°.
        let cos_i = 20f64.to_radians().sin();
        assert!((lowered[(8, 0)] - RENDER_ALBEDO * cos_i).abs() < 1e-12);
        // Nothing lowered: σ_B = 0, or a Sun 30° high.
        let same = |a: &Array2<f64>, b: &Array2<f64>| {
            a.iter()
                .zip(b)
                .all(|(a, b)| a == b || (a.is_nan() && b.is_nan()))
        };
        assert!(same(
            &at(0.0),
            &render(dem.view(), 10.0, &model, &low, &view)
        ));
        let high = sun_at(30.0);
        assert!(same(
            &render_lowered(dem.view(), 10.0, &model, (&high, &view), DEM_BIAS_PSF),
            &render(dem.view(), 10.0, &model, &high, &view)
        ));
        // The share taken off: 0.3 up to 25°, half of it at 27.5°, none from 30°; in
        // proportion to σ_B below the table's.
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(shadow_lowering(10.0, DEM_BIAS_PSF), 0.3));
        assert!(close(shadow_lowering(25.0, 3.0 * DEM_BIAS_PSF), 0.3));
        assert!(close(shadow_lowering(27.5, DEM_BIAS_PSF), 0.15));
        assert!(close(shadow_lowering(20.0, 0.5 * DEM_BIAS_PSF), 0.15));
        assert_eq!(shadow_lowering(30.0, DEM_BIAS_PSF), 0.0);
        assert_eq!(shadow_lowering(20.0, 0.0), 0.0);
    }

    /// A window's Sun: the mean of the zenith angles over the pixels with an image value, by
    /// hand. Half the pixels under a Sun 20° high and half 40° high give 30°; a pixel without
    /// an image value or without a Sun vector does not count, whatever its Sun; a window
    /// without any gives none.
    #[test]
    fn a_windows_sun_is_the_mean_over_its_usable_pixels() {
        let up = |el: f64| {
            let e = el.to_radians();
            [0.0, e.cos() as f32, e.sin() as f32]
        };
        let image = Array2::from_shape_fn(
            (4, 4),
            |(i, j)| {
                if i == 3 && j == 3 {
                    f64::NAN
                } else {
                    0.1
                }
            },
        );
        let sun = Array2::from_shape_fn((4, 4), |(i, j)| match (i, j) {
            (3, 3) => up(85.0),
            (3, 2) => [f32::NAN; 3],
            (i, _) if i < 2 => up(20.0),
            _ => up(40.0),
        });
        // Rows 0–1 (8 px at 20°) and rows 2–3 less two (6 px at 40°): 90 − (8·70 + 6·50)/14.
        let el = mean_sun_elevation_deg(image.view(), sun.view());
        let want = 90.0 - (8.0 * 70.0 + 6.0 * 50.0) / 14.0;
        assert!((el - want).abs() < 1e-4, "{el} against {want}");
        let half = Array2::from_shape_fn((4, 4), |(i, _)| if i < 2 { up(20.0) } else { up(40.0) });
        let all = Array2::from_elem((4, 4), 0.1);
        assert!((mean_sun_elevation_deg(all.view(), half.view()) - 30.0).abs() < 1e-4);
        let none = Array2::from_elem((4, 4), f64::NAN);
        assert!(mean_sun_elevation_deg(none.view(), half.view()).is_nan());
    }

    /// Where an estimate was made: the correlation's weight lies on the one feature of the
    /// window, a bump at row 40 of 128, so the mean row weighted by it is 40 (by symmetry);
    /// with no finite value there is none.
    #[test]
    fn an_estimate_stands_for_where_the_correlation_lies() {
        let bump = Array2::from_shape_fn((128, 128), |(i, j)| {
            let r2 = (i as f64 - 40.0).powi(2) + (j as f64 - 64.0).powi(2);
            (-r2 / 18.0).exp()
        });
        let s = Shift {
            rows: 0.2,
            cols: -0.3,
            correlation: 1.0,
            correlation_in_place: 1.0,
            pixels: 128 * 128,
        };
        let rows = Array2::from_shape_fn((128, 128), |(i, _)| i as f32);
        let at = where_estimated(bump.view(), bump.view(), 1.0, &s, rows.view()).unwrap();
        assert!((at - 40.0).abs() < 1e-6, "{at}");
        let none = Array2::from_elem((128, 128), f32::NAN);
        assert!(where_estimated(bump.view(), bump.view(), 1.0, &s, none.view()).is_none());
    }

    /// A displacement is none without knots or with knots at zero, constant with one knot,
    /// linear in the line between two and constant beyond them; its reach is its largest
    /// component at a knot.
    #[test]
    fn a_displacement_is_piecewise_linear_in_the_line() {
        assert_eq!(Displacement::default().at(7.0), [0.0; 2]);
        assert!(Displacement::default().is_none() && Displacement::constant([0.0; 2]).is_none());
        let c = Displacement::constant([30.0, -40.0]);
        assert!(!c.is_none());
        assert_eq!(
            (c.at(-5.0), c.at(1e6), c.reach_m()),
            ([30.0, -40.0], [30.0, -40.0], 40.0)
        );
        let d = Displacement::through(&[(100.0, [0.0, 10.0]), (300.0, [200.0, -30.0])]);
        assert_eq!(d.at(0.0), [0.0, 10.0]);
        assert_eq!(d.at(100.0), [0.0, 10.0]);
        assert_eq!(d.at(150.0), [50.0, 0.0]);
        assert_eq!(d.at(300.0), [200.0, -30.0]);
        assert_eq!(d.at(1000.0), [200.0, -30.0]);
        assert_eq!(d.reach_m(), 200.0);
    }

    /// `a` displaced by (`rows`, `cols`) pixels: out(x) = a(x − d), bicubic; NaN off `a`.
    fn displaced(a: &Array2<f64>, rows: f64, cols: f64) -> Array2<f64> {
        Array2::from_shape_fn(a.dim(), |(i, j)| {
            interpolate(
                a.view(),
                i as f64 - rows,
                j as f64 - cols,
                Interpolation::Bicubic,
                false,
            )
        })
    }

    /// The DEM of `pr` rendered under its first observation's Sun and view as the plan renders
    /// it for an estimate against the DEM ([`render_lowered`] at the DEM's point spread).
    fn against_the_dem(pr: &crate::fusion::Problem) -> Array2<f64> {
        let o = &pr.observations[0];
        render_lowered(
            pr.dem,
            pr.spacing,
            pr.model,
            (&o.sun, &o.view),
            pr.dem_psf_sigma,
        )
    }

    /// The 256² synthetic scene of `seed` (one Sun, 105/30).
    fn scene(seed: u64) -> crate::synth::Scene {
        generate(&SceneSpec {
            size: 256,
            seed,
            ..SceneSpec::default()
        })
    }

    #[test]
    fn a_displaced_image_is_found_where_it_was_put() {
        let sc = scene(10);
        let pr = sc.problem();
        let rendered = against_the_dem(&pr);
        // In place: the estimate is biased by the shading of relief sharper than the DEM's
        // (up to 1.3 px over the scenes and Suns measured where the correlation reaches 0.5,
        // docs/science.md "Registration") — under the 1.25 px from which a run applies it
        // under this scene's Sun, 30° high (`dem_apply_px`).
        let s = estimate(sc.image.view(), rendered.view(), pr.dem_psf_sigma, 8).unwrap();
        assert!(
            s.length() < 0.8 && s.length() < dem_apply_px(30.0, pr.dem_psf_sigma),
            "{s:?}"
        );
        assert!(s.correlation > 0.5, "{s:?}");
        // Displaced by whole and fractional pixels, in either direction.
        for (r, c) in [(3.0, -2.0), (-1.4, 2.6), (0.0, 5.5)] {
            let moved = displaced(&sc.image, r, c);
            let e = estimate(moved.view(), rendered.view(), pr.dem_psf_sigma, 8).unwrap();
            let err = (e.rows - r - s.rows).hypot(e.cols - c - s.cols);
            assert!(
                err < 0.35,
                "put at ({r}, {c}), found {e:?} (in place {s:?})"
            );
        }
        // Beyond the search radius there is no answer, rather than a wrong one.
        let far = displaced(&sc.image, 0.0, 12.0);
        assert!(estimate(far.view(), rendered.view(), pr.dem_psf_sigma, 8).is_none());
    }

    #[test]
    fn an_image_of_other_relief_is_not_placed() {
        let (a, b) = (scene(10), scene(11));
        let pr = a.problem();
        let rendered = against_the_dem(&pr);
        assert_eq!(
            estimate(b.image.view(), rendered.view(), pr.dem_psf_sigma, 8),
            None
        );
    }
}
