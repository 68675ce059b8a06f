//! The first albedo stage on a coarser grid (docs/science.md, "Coarse first stage").
//!
//! The first stage's albedo is smooth (σ_ρ ≈ 100 px) and what its surface solve adds to the
//! input DEM is mostly relief wider than a few pixels: the fine stages that follow re-estimate
//! everything finer. So it is solved on the grid block-averaged by an integer factor f — f²
//! times fewer pixels, and as many fewer Gauss–Newton unknowns — and only its *correction*
//! z − z_DEM is carried back to the full grid, by bilinear interpolation between the coarse
//! pixel centres. The input DEM's own detail is kept as it is.
//!
//! Block averaging (not point sampling) keeps the shading's mean over each block, so the
//! coarse image does not alias relief finer than the block into the coarse solve.

use super::{Directions, FusionError, FusionParams, Observation, Problem, StageReport};
use crate::photometry::{narrow, Vec3f};
use ndarray::{Array2, ArrayView2, Zip};

/// A problem's arrays block-averaged by `factor` (owned; [`Coarse::problem`] borrows them).
pub struct Coarse {
    pub factor: usize,
    pub images: Vec<Array2<f64>>,
    pub suns: Vec<Directions<'static>>,
    pub views: Vec<Directions<'static>>,
    pub dem: Array2<f64>,
}

/// The block (f × f, clipped at the far edges) of coarse pixel (i, j).
fn block(dim: (usize, usize), f: usize, i: usize, j: usize) -> (usize, usize, usize, usize) {
    (
        i * f,
        ((i + 1) * f).min(dim.0),
        j * f,
        ((j + 1) * f).min(dim.1),
    )
}

/// The coarse grid's shape: ⌈ny/f⌉ × ⌈nx/f⌉.
pub fn coarse_dim((ny, nx): (usize, usize), f: usize) -> (usize, usize) {
    (ny.div_ceil(f), nx.div_ceil(f))
}

/// Block means of `a`; a block with fewer than half of its pixels finite is NaN (an image's
/// edge or no-data), otherwise the mean of its finite pixels.
pub fn block_mean(a: ArrayView2<f64>, f: usize) -> Array2<f64> {
    let dim = a.dim();
    Array2::from_shape_fn(coarse_dim(dim, f), |(i, j)| {
        let (r0, r1, c0, c1) = block(dim, f, i, j);
        let (mut s, mut n) = (0.0, 0usize);
        for r in r0..r1 {
            for c in c0..c1 {
                let v = a[(r, c)];
                if v.is_finite() {
                    s += v;
                    n += 1;
                }
            }
        }
        if 2 * n >= (r1 - r0) * (c1 - c0) && n > 0 {
            s / n as f64
        } else {
            f64::NAN
        }
    })
}

/// Block means of unit vectors over their finite members (summed in f64), renormalised and
/// stored in f32; NaN where a block has none (no geometry there, as where an observation's
/// swath ends).
pub fn block_mean_vectors(a: ArrayView2<Vec3f>, f: usize) -> Array2<Vec3f> {
    let dim = a.dim();
    Array2::from_shape_fn(coarse_dim(dim, f), |(i, j)| {
        let (r0, r1, c0, c1) = block(dim, f, i, j);
        let mut s = [0.0; 3];
        for r in r0..r1 {
            for c in c0..c1 {
                let v = &a[(r, c)];
                if v.iter().all(|x| x.is_finite()) {
                    for k in 0..3 {
                        s[k] += f64::from(v[k]);
                    }
                }
            }
        }
        let n = (s[0] * s[0] + s[1] * s[1] + s[2] * s[2]).sqrt();
        if n > 0.0 {
            narrow([s[0] / n, s[1] / n, s[2] / n])
        } else {
            [f32::NAN; 3]
        }
    })
}

fn block_directions(d: &Directions, f: usize) -> Directions<'static> {
    match d {
        Directions::Uniform(v) => Directions::Uniform(*v),
        Directions::PerPixel(a) => Directions::PerPixel(block_mean_vectors(a.view(), f).into()),
    }
}

/// `pr` block-averaged by `f`.
pub fn coarsen(pr: &Problem, f: usize) -> Coarse {
    Coarse {
        factor: f,
        images: pr
            .observations
            .iter()
            .map(|o| block_mean(o.image, f))
            .collect(),
        suns: pr
            .observations
            .iter()
            .map(|o| block_directions(&o.sun, f))
            .collect(),
        views: pr
            .observations
            .iter()
            .map(|o| block_directions(&o.view, f))
            .collect(),
        dem: block_mean(pr.dem, f),
    }
}

impl Coarse {
    /// The coarse problem: `fine`'s model, selection and per-observation gains, noise weights
    /// and Ī (given explicitly: the coarse images must be weighed as the fine ones are), the
    /// DEM's point spread in coarse pixels.
    pub fn problem<'a, 'p: 'a>(
        &'a self,
        fine: &Problem<'p>,
        scale: f64,
        gains: &[f64],
        noise: &[f64],
    ) -> Problem<'a> {
        let f = self.factor as f64;
        Problem {
            observations: self
                .images
                .iter()
                .zip(&self.suns)
                .zip(&self.views)
                .map(|((image, sun), view)| Observation {
                    image: image.view(),
                    sun: sun.borrowed(),
                    view: view.borrowed(),
                })
                .collect(),
            dem: self.dem.view(),
            spacing: fine.spacing * f,
            dem_psf_sigma: fine.dem_psf_sigma / f,
            model: fine.model,
            intensity_scale: Some(scale),
            gains: Some(gains.to_vec()),
            noise_weights: Some(noise.to_vec()),
            blur: fine
                .blur
                .as_ref()
                .map(|b| b.iter().map(|s| s / f).collect()),
            selection: fine.selection,
        }
    }
}

/// The parameters of the coarse reference: every width in pixels divided by f (σ_DEM at least
/// ½ px), no further coarsening, and no pixel-scale shrink (the fine stages start from the
/// reference and settle its pixel-scale waves themselves).
pub fn coarse_params(params: &FusionParams, f: usize) -> FusionParams {
    let f = f as f64;
    let div = |s: f64| s / f;
    FusionParams {
        sigma_dem: div(params.sigma_dem).max(0.5),
        dem_height_length_px: div(params.dem_height_length_px),
        dem_track_sigma_px: div(params.dem_track_sigma_px),
        albedo_sigmas: params.albedo_sigmas.iter().copied().map(div).collect(),
        final_albedo_sigma: div(params.final_albedo_sigma),
        multi_albedo_sigma: div(params.multi_albedo_sigma),
        multi_albedo_sigma_single: div(params.multi_albedo_sigma_single),
        multi_final_albedo_sigma: div(params.multi_final_albedo_sigma),
        edge_ramp_px: div(params.edge_ramp_px),
        coarse_factor: 1,
        coarse_dem_membrane: false,
        nyquist_shrink: 0.0,
        ..params.clone()
    }
}

/// The reference: the whole fusion solved on `coarse`, a problem block-averaged by `f` with
/// the fine problem's gains, noise weights and Ī ([`Coarse::problem`]), every width divided by
/// f ([`coarse_params`]). Returns its correction z − z_DEM on the coarse grid and one record
/// for all its stages (σ_ρ of the first fine stage it stands for).
pub fn reference(
    coarse: &Problem,
    params: &FusionParams,
    f: usize,
) -> Result<(Array2<f64>, StageReport), FusionError> {
    let t0 = std::time::Instant::now();
    // The rule for a coarse DEM from the fine grid's point spread (the coarse problem's is
    // σ_B/f), as the tiles apply it.
    let params = super::coarse_dem_membrane(params, coarse.dem_psf_sigma * f as f64);
    let fused = super::fuse(coarse, &coarse_params(&params, f))?;
    let correction = &fused.height - &coarse.dem;
    Ok((
        correction,
        StageReport {
            sigma_rho: params.albedo_sigmas.first().copied().unwrap_or(f64::NAN),
            iterations: fused
                .stages
                .into_iter()
                .flat_map(|s| s.iterations)
                .collect(),
            seconds: t0.elapsed().as_secs_f64(),
        },
    ))
}

/// Position of fine pixel `k` on the coarse axis of `m` pixels (centres at f·i + (f − 1)/2),
/// clamped to the outermost centres: the two coarse pixels around it and the weight of the
/// second.
fn coarse_position(k: usize, f: usize, m: usize) -> (usize, usize, f64) {
    let t = ((k as f64 - (f as f64 - 1.0) / 2.0) / f as f64).clamp(0.0, (m - 1) as f64);
    let a = (t.floor() as usize).min(m - 1);
    (a, (a + 1).min(m - 1), t - a as f64)
}

/// The coarse pixels `lo..hi` along an axis of `m` that bilinear interpolation reads for the
/// fine pixels `start..start + n`.
pub fn coarse_span(f: usize, m: usize, start: usize, n: usize) -> (usize, usize) {
    let (lo, _, _) = coarse_position(start, f, m);
    let (_, hi, _) = coarse_position(start + n.max(1) - 1, f, m);
    (lo, hi + 1)
}

/// Bilinear interpolation of a coarse field onto the fine window of shape `dim` whose first
/// pixel is fine pixel `at` (row, column) of the grid. The coarse field covers a grid of
/// `full` coarse pixels, block `f` (pixel centres at f·i + (f − 1)/2) and is constant beyond
/// its outermost centres; `c` holds its pixels from `origin` on (at least [`coarse_span`] of
/// the window along each axis). A window gets exactly the values of the whole grid.
pub fn upsample_window(
    c: ArrayView2<f64>,
    origin: (usize, usize),
    full: (usize, usize),
    f: usize,
    at: (usize, usize),
    dim: (usize, usize),
) -> Array2<f64> {
    let axis = |n: usize, start: usize, m: usize, o: usize| -> Vec<(usize, usize, f64)> {
        (0..n)
            .map(|k| {
                let (a, b, t) = coarse_position(start + k, f, m);
                (a - o, b - o, t)
            })
            .collect()
    };
    let ys = axis(dim.0, at.0, full.0, origin.0);
    let xs = axis(dim.1, at.1, full.1, origin.1);
    let mut out = Array2::zeros(dim);
    Zip::indexed(&mut out).par_for_each(|(i, j), o| {
        let (y0, y1, ty) = ys[i];
        let (x0, x1, tx) = xs[j];
        let top = c[(y0, x0)] * (1.0 - tx) + c[(y0, x1)] * tx;
        let bottom = c[(y1, x0)] * (1.0 - tx) + c[(y1, x1)] * tx;
        *o = top * (1.0 - ty) + bottom * ty;
    });
    out
}

/// Bilinear interpolation of a coarse field of block `f` onto the whole fine grid of shape
/// `dim` ([`upsample_window`]).
pub fn upsample(c: ArrayView2<f64>, f: usize, dim: (usize, usize)) -> Array2<f64> {
    upsample_window(c, (0, 0), c.dim(), f, (0, 0), dim)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_mean_and_upsample_keep_planes() {
        // A plane's block means are the plane at the block centres, and bilinear
        // interpolation of a plane is exact inside the outermost centres.
        let f = 4;
        let plane = Array2::from_shape_fn((40, 36), |(i, j)| 2.0 * i as f64 - 0.5 * j as f64);
        let c = block_mean(plane.view(), f);
        assert_eq!(c.dim(), (10, 9));
        for ((i, j), v) in c.indexed_iter() {
            let (y, x) = (f as f64 * i as f64 + 1.5, f as f64 * j as f64 + 1.5);
            assert!((v - (2.0 * y - 0.5 * x)).abs() < 1e-12);
        }
        let up = upsample(c.view(), f, (40, 36));
        for i in 2..38 {
            for j in 2..34 {
                assert!((up[(i, j)] - plane[(i, j)]).abs() < 1e-9, "({i}, {j})");
            }
        }
    }

    #[test]
    fn a_window_is_upsampled_as_the_whole_grid() {
        let f = 4;
        let c = Array2::from_shape_fn((9, 7), |(i, j)| ((i * 7 + j) as f64).sin());
        let dim = (35, 26);
        let whole = upsample(c.view(), f, dim);
        for (r0, c0, rows, cols) in [(0, 0, 35, 26), (5, 3, 10, 9), (30, 20, 5, 6), (1, 0, 1, 1)] {
            let (y0, y1) = coarse_span(f, 9, r0, rows);
            let (x0, x1) = coarse_span(f, 7, c0, cols);
            let part = c.slice(ndarray::s![y0..y1, x0..x1]);
            let w = upsample_window(part, (y0, x0), (9, 7), f, (r0, c0), (rows, cols));
            assert_eq!(
                w,
                whole.slice(ndarray::s![r0..r0 + rows, c0..c0 + cols]),
                "window at ({r0}, {c0})"
            );
        }
    }

    #[test]
    fn blocks_mostly_without_data_are_no_data() {
        let mut a = Array2::from_elem((4, 4), 1.0);
        a[(0, 0)] = f64::NAN;
        a[(0, 1)] = f64::NAN;
        a[(1, 0)] = f64::NAN;
        a[(2, 2)] = f64::NAN;
        let c = block_mean(a.view(), 2);
        assert!(c[(0, 0)].is_nan(), "3 of 4 missing");
        assert_eq!(c[(1, 1)], 1.0, "1 of 4 missing");
    }
}
