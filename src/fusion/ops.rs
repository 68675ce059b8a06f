//! Discrete operators of the fusion energy on a grid of `ny` rows (row 0 north) × `nx` columns
//! (column 0 west) with spacing ε metres.
//!
//! The photometric term reads the surface gradient at pixel centres by the fourth-order central
//! difference of [`STENCIL`] (the plain central difference one pixel from an edge, one-sided at
//! the edge): p = ∂z/∂x (east), q = ∂z/∂y (north, i.e. towards row − 1). The
//! quadratic terms use forward differences, which the DCT diagonalises (see `spectral`).

use crate::spectral::{to, Real};
use ndarray::{Array2, ArrayView1, ArrayView2, Axis, Zip};
use rayon::prelude::*;

/// Interior coefficients (c₁, c₂) of the photometric gradient,
/// p·ε = c₁·(v[j+1] − v[j−1]) + c₂·(v[j+2] − v[j−2]): the fourth-order central difference
/// (−v[j+2] + 8v[j+1] − 8v[j−1] + v[j−2])/12, exact up to quartics. Its response to a wave of
/// angular frequency ω (radians per pixel) is (8 sin ω − sin 2ω)/6, against ω for the true
/// derivative and sin ω for the plain central difference: at 4 px wavelength the central
/// difference sees 64 % of the slope, this stencil 85 % (a detector averaging over its pixel
/// sees 90 %), so the rendered image keeps the contrast of small craters that the plain
/// difference smooths away (docs/science.md, "The photometric gradient").
pub const STENCIL: (f64, f64) = (8.0 / 12.0, -1.0 / 12.0);

/// The response Σₘ 2cₘ·sin(mω) of the interior stencil at angular frequency ω.
pub fn stencil_response(omega: f64) -> f64 {
    let (c1, c2) = STENCIL;
    2.0 * c1 * omega.sin() + 2.0 * c2 * (2.0 * omega).sin()
}

/// Coefficient D[j][k]·ε of the 1-D gradient on `n` points: the interior stencil where
/// j ∈ [2, n − 3], central at j = 1 and n − 2, one-sided at both ends.
fn coef(n: usize, j: usize, k: usize) -> f64 {
    if n < 2 {
        return 0.0;
    }
    if j == 0 {
        return match k {
            0 => -1.0,
            1 => 1.0,
            _ => 0.0,
        };
    }
    if j == n - 1 {
        return if k == n - 1 {
            1.0
        } else if k == n - 2 {
            -1.0
        } else {
            0.0
        };
    }
    let (c1, c2) = if j >= 2 && j + 3 <= n {
        STENCIL
    } else {
        (0.5, 0.0)
    };
    if k + 1 == j {
        -c1
    } else if k == j + 1 {
        c1
    } else if k + 2 == j {
        -c2
    } else if k == j + 2 {
        c2
    } else {
        0.0
    }
}

/// (Dᵀu)[k]·ε for one line, gathered from u[k−2..=k+2] via `get`.
#[inline]
fn adjoint_at<T: Real>(n: usize, k: usize, get: impl Fn(usize) -> T) -> T {
    let lo = k.saturating_sub(2);
    let hi = (k + 2).min(n.saturating_sub(1));
    (lo..=hi).map(|j| to::<T>(coef(n, j, k)) * get(j)).sum()
}

/// (D v)[j]·ε of a line of `n` values read through `v`: one-sided at the ends, the plain
/// central difference one point from them, [`STENCIL`] inside.
#[inline]
fn diff_at<T: Real>(n: usize, j: usize, v: impl Fn(usize) -> T) -> T {
    if n < 2 {
        T::zero()
    } else if j == 0 {
        v(1) - v(0)
    } else if j == n - 1 {
        v(n - 1) - v(n - 2)
    } else if j == 1 || j == n - 2 {
        to::<T>(0.5) * (v(j + 1) - v(j - 1))
    } else {
        to::<T>(STENCIL.0) * (v(j + 1) - v(j - 1)) + to::<T>(STENCIL.1) * (v(j + 2) - v(j - 2))
    }
}

/// D v·ε along one contiguous line ([`diff_at`]; the interior without branches).
fn diff_line<T: Real>(v: &[T], out: &mut [T]) {
    let n = v.len();
    let (c1, c2) = (to::<T>(STENCIL.0), to::<T>(STENCIL.1));
    for j in [0, 1, n.saturating_sub(2), n.saturating_sub(1)] {
        if j < n {
            out[j] = diff_at(n, j, |k| v[k]);
        }
    }
    // The interior j ∈ [2, n − 3]: out[j] from v[j − 2 ..= j + 2].
    if n >= 5 {
        for (o, w) in out[2..n - 2].iter_mut().zip(v.windows(5)) {
            *o = c1 * (w[3] - w[1]) + c2 * (w[4] - w[0]);
        }
    }
}

/// Dᵀu·ε along one contiguous line.
fn adjoint_line<T: Real>(u: &[T], out: &mut [T]) {
    let n = u.len();
    let (c1, c2) = (to::<T>(STENCIL.0), to::<T>(STENCIL.1));
    // Where every row j ∈ [k − 2, k + 2] that reaches k is interior (k ∈ [4, n − 5]), branch-free.
    let (lo, hi) = if n >= 9 { (4, n - 4) } else { (n, n) };
    for k in (0..lo).chain(hi..n) {
        out[k] = adjoint_at(n, k, |j| u[j]);
    }
    if lo < hi {
        for (o, w) in out[lo..hi].iter_mut().zip(u[lo - 2..].windows(5)) {
            *o = c1 * (w[1] - w[3]) + c2 * (w[0] - w[4]);
        }
    }
}

/// Surface gradients (p, q) at pixel centres.
pub fn gradient(z: ArrayView2<f64>, eps: f64) -> (Array2<f64>, Array2<f64>) {
    let mut p = Array2::zeros(z.dim());
    let mut q = Array2::zeros(z.dim());
    gradient_into(z, eps, &mut p, &mut q);
    (p, q)
}

/// [`gradient`] into `p` and `q` (standard layout, the shape of `z`).
pub fn gradient_into<T: Real>(z: ArrayView2<T>, eps: f64, p: &mut Array2<T>, q: &mut Array2<T>) {
    let z = z.as_standard_layout();
    p.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(q.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(i, (mut prow, mut qrow))| {
            gradient_row(
                z.view(),
                eps,
                i,
                prow.as_slice_mut().expect("standard layout"),
                qrow.as_slice_mut().expect("standard layout"),
            );
        });
}

/// [`gradient`] along row `i` of `z` (standard layout) into `p` and `q` (one row each): the
/// values `gradient_into` gives there, for callers that go row by row and need no slope
/// arrays of the grid's size.
pub fn gradient_row<T: Real>(z: ArrayView2<T>, eps: f64, i: usize, p: &mut [T], q: &mut [T]) {
    let ny = z.nrows();
    let inv = to::<T>(1.0 / eps);
    diff_line(z.row(i).as_slice().expect("standard layout"), p);
    p.iter_mut().for_each(|x| *x = *x * inv);
    // y points north = towards smaller row index: q = −(D along rows).
    // (coef is 0 everywhere on a single row.)
    q.iter_mut().for_each(|x| *x = T::zero());
    let lo = i.saturating_sub(2);
    let hi = (i + 2).min(ny - 1);
    for k in lo..=hi {
        let c = coef(ny, i, k);
        if c != 0.0 {
            let c = to::<T>(c);
            let r = z.row(k);
            for (o, &x) in q.iter_mut().zip(r.as_slice().expect("standard layout")) {
                *o = *o - c * x * inv;
            }
        }
    }
}

/// [`gradient`] at one pixel (i, j): the same stencils in the same arithmetic, so the same
/// values, for callers that need (p, q) at a few pixels only.
pub fn gradient_at(z: ArrayView2<f64>, eps: f64, i: usize, j: usize) -> (f64, f64) {
    let (ny, nx) = z.dim();
    let inv = 1.0 / eps;
    let d = diff_at(nx, j, |k| z[(i, k)]);
    // `gradient_into`'s column sum, in its order.
    let mut q = 0.0;
    for k in i.saturating_sub(2)..=(i + 2).min(ny - 1) {
        let c = coef(ny, i, k);
        if c != 0.0 {
            q -= c * z[(k, j)] * inv;
        }
    }
    (d * inv, q)
}

/// Adjoint of [`gradient`]: D_xᵀu + D_yᵀv (a negative divergence).
pub fn gradient_adjoint(u: ArrayView2<f64>, v: ArrayView2<f64>, eps: f64) -> Array2<f64> {
    let mut out = Array2::zeros(u.dim());
    gradient_adjoint_into(u, v, eps, &mut out);
    out
}

/// [`gradient_adjoint`] into `out` (standard layout, the shape of `u`).
pub fn gradient_adjoint_into<T: Real>(
    u: ArrayView2<T>,
    v: ArrayView2<T>,
    eps: f64,
    out: &mut Array2<T>,
) {
    let u = u.as_standard_layout();
    let v = v.as_standard_layout();
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(k, mut orow)| {
            let o = orow.as_slice_mut().expect("standard layout");
            adjoint_row(
                u.row(k).as_slice().expect("standard layout"),
                v.view(),
                eps,
                k,
                o,
            );
        });
}

/// Row `k` of [`gradient_adjoint`] into `o`, given that row of `u` (`u_row`) and the whole of
/// `v` (standard layout): for callers that form `u` row by row and hold no array of it.
pub fn adjoint_row<T: Real>(u_row: &[T], v: ArrayView2<T>, eps: f64, k: usize, o: &mut [T]) {
    adjoint_row_with(
        u_row,
        |j| v.row(j).to_slice().expect("standard layout"),
        v.nrows(),
        eps,
        k,
        o,
    );
}

/// [`adjoint_row`] with the rows of `v` (of `ny` rows) from `v_row`: only rows k − 2 ..= k + 2
/// are asked for.
fn adjoint_row_with<'v, T: Real>(
    u_row: &[T],
    v_row: impl Fn(usize) -> &'v [T],
    ny: usize,
    eps: f64,
    k: usize,
    o: &mut [T],
) {
    let inv = to::<T>(1.0 / eps);
    adjoint_line(u_row, o);
    // Rows j ∈ [k−2, k+2] of v with coefficient coef(ny, j, k); q = −D_rows, so subtract.
    let lo = k.saturating_sub(2);
    let hi = (k + 2).min(ny.saturating_sub(1));
    for j in lo..=hi {
        let c = coef(ny, j, k);
        if c != 0.0 {
            let c = to::<T>(c);
            for (x, &y) in o.iter_mut().zip(v_row(j)) {
                *x = *x - c * y;
            }
        }
    }
    o.iter_mut().for_each(|x| *x = *x * inv);
}

/// Rows per block of [`weighted_normal_into`].
const NORMAL_BLOCK_ROWS: usize = 32;

/// Dᵀ(H·D v) into `out` (standard layout, the shape of `v`), H a symmetric 2 × 2 matrix per
/// pixel (`h` = [xx, xy, yy]) acting on the gradient (p, q) = D v of [`gradient`]: the
/// photometric part of the Newton operator. The same values, to the bit, as
/// [`gradient_into`], the product with H per pixel and [`gradient_adjoint_into`] in turn, but
/// block by block of rows, each forming the weighted gradients of its rows (and of the two
/// rows either side that D_yᵀ reaches) in scratch of its own: no arrays of the grid's size
/// for them, and no round trip through memory.
pub fn weighted_normal_into<T: Real>(
    v: ArrayView2<T>,
    h: &Array2<[T; 3]>,
    eps: f64,
    out: &mut Array2<T>,
) {
    let (ny, nx) = v.dim();
    let v = v.as_standard_layout();
    out.axis_chunks_iter_mut(Axis(0), NORMAL_BLOCK_ROWS)
        .into_par_iter()
        .enumerate()
        .for_each(|(b, mut block)| {
            let a = b * NORMAL_BLOCK_ROWS;
            let rows = block.nrows();
            // Weighted gradients (u_x, u_y) = H·(p, q) of rows lo..hi: the block's and two
            // either side.
            let (lo, hi) = (a.saturating_sub(2), (a + rows + 2).min(ny));
            let mut ux = vec![T::zero(); (hi - lo) * nx];
            let mut uy = vec![T::zero(); (hi - lo) * nx];
            for j in lo..hi {
                let r = (j - lo) * nx..(j - lo + 1) * nx;
                let (px, qy) = (&mut ux[r.clone()], &mut uy[r]);
                gradient_row(v.view(), eps, j, px, qy);
                let hr = h.row(j);
                for ((x, y), h) in px.iter_mut().zip(qy.iter_mut()).zip(hr) {
                    let (p, q) = (*x, *y);
                    *x = h[0] * p + h[1] * q;
                    *y = h[1] * p + h[2] * q;
                }
            }
            for (r, mut orow) in block.rows_mut().into_iter().enumerate() {
                let k = a + r;
                let o = orow.as_slice_mut().expect("standard layout");
                let off = (k - lo) * nx;
                adjoint_row_with(
                    &ux[off..off + nx],
                    |j| &uy[(j - lo) * nx..(j - lo + 1) * nx],
                    ny,
                    eps,
                    k,
                    o,
                );
            }
        });
}

/// Coefficients of the eighth difference over 2⁸, (−1)ᵗ·C(8, t)/256 for t = 0 … 8 (offsets
/// −4 … 4): its response to a wave of angular frequency ω (radians per pixel) is sin⁸(ω/2),
/// 1 at the Nyquist frequency, 1/16 at half of it, under 5·10⁻⁴ at a quarter of it.
const EIGHTH_DIFFERENCE: [f64; 9] = [
    1.0 / 256.0,
    -8.0 / 256.0,
    28.0 / 256.0,
    -56.0 / 256.0,
    70.0 / 256.0,
    -56.0 / 256.0,
    28.0 / 256.0,
    -8.0 / 256.0,
    1.0 / 256.0,
];

/// The pixel-scale shrink F = F_y F_x, F(ω) = 1 − s·sin⁸(ω/2) along each axis: a wave at
/// the Nyquist frequency (ω = π) scaled by 1 − s, one at half of it by 1 − s/16, longer ones
/// kept (a polynomial of degree < 8 exactly). Each axis is the identity minus s times
/// the eighth difference (−1)ᵗ·C(8, t)/256, t = 0 … 8, continued past the grid's edges by the
/// half-sample mirror (v₋₁ = v₀, as the DCT-II's even extension: every DCT-II basis
/// function cos(ω(j + ½)) is scaled by exactly F(ω), edges included). Local (4 px each way),
/// so a tile with any halo wider than that gives what the whole region gives.
///
/// The photometric gradient's response falls to 0 at the Nyquist frequency
/// ([`stencil_response`]), so the images hold waves there only weakly, and what the solution
/// holds there is mostly error (docs/science.md, "The pixel-scale shrink").
pub fn shrink_near_nyquist(a: ArrayView2<f64>, s: f64) -> Array2<f64> {
    if s == 0.0 {
        return a.to_owned();
    }
    let along_rows = shrink_axis(a, s, Axis(1));
    shrink_axis(along_rows.view(), s, Axis(0))
}

/// One axis of [`shrink_near_nyquist`]: each lane along `axis` filtered on its own.
fn shrink_axis(a: ArrayView2<f64>, s: f64, axis: Axis) -> Array2<f64> {
    let mut out = a.to_owned();
    Zip::from(out.lanes_mut(axis))
        .and(a.lanes(axis))
        .par_for_each(|mut o, v| {
            let n = v.len() as isize;
            // The half-sample mirror: …, v₁, v₀ | v₀, v₁, … at both ends.
            let at = |j: isize| {
                let j = if j < 0 { -j - 1 } else { j };
                let j = if j >= n { 2 * n - 1 - j } else { j };
                v[j.clamp(0, n - 1) as usize]
            };
            for (j, o) in o.iter_mut().enumerate() {
                let h: f64 = EIGHTH_DIFFERENCE
                    .iter()
                    .enumerate()
                    .map(|(t, c)| c * at(j as isize + t as isize - 4))
                    .sum();
                *o -= s * h;
            }
        });
    out
}

/// The median of `v` (sorted in place): its middle value, the mean of the middle two for an
/// even count; `None` when empty.
pub fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

/// max |aᵢ| in f64 (0 for an empty array); f32 values are widened exactly.
pub fn max_abs<T: Copy + Into<f64>>(a: ArrayView2<T>) -> f64 {
    a.iter().fold(0.0, |m, &x| m.max(x.into().abs()))
}

/// Σ of all elements, summed row by row in parallel and then in row order: the result does not
/// depend on the number of threads.
pub fn sum(a: ArrayView2<f64>) -> f64 {
    a.axis_iter(Axis(0))
        .into_par_iter()
        .map(|r| r.iter().sum::<f64>())
        .collect::<Vec<_>>()
        .iter()
        .sum()
}

/// Σ aᵢ·bᵢ in f64 with the same determinism as [`sum`] (f32 values are widened exactly).
pub fn dot<A, B>(a: ArrayView2<A>, b: ArrayView2<B>) -> f64
where
    A: Copy + Into<f64> + Sync,
    B: Copy + Into<f64> + Sync,
{
    a.axis_iter(Axis(0))
        .into_par_iter()
        .zip(b.axis_iter(Axis(0)))
        .map(|(x, y)| {
            x.iter()
                .zip(y)
                .map(|(&x, &y)| x.into() * y.into())
                .sum::<f64>()
        })
        .collect::<Vec<_>>()
        .iter()
        .sum()
}

/// The per-row partial sums of a fused pass (one array of N sums per row), added in row order:
/// like [`sum`] and [`dot`], the result does not depend on the number of threads.
pub fn sum_row_parts<const N: usize>(parts: ArrayView1<[f64; N]>) -> [f64; N] {
    parts.iter().fold([0.0; N], |mut acc, part| {
        for (a, x) in acc.iter_mut().zip(part) {
            *a += x;
        }
        acc
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_of_odd_and_even_counts() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut [5.0]), Some(5.0));
        assert_eq!(median(&mut []), None);
    }

    /// A DCT-II basis function cos(ω_y(i + ½))·cos(ω_x(j + ½)) is scaled by exactly
    /// (1 − s·sin⁸(ω_y/2))(1 − s·sin⁸(ω_x/2)) at every pixel, edges included (the analytic
    /// response of the eighth difference under the half-sample mirror).
    #[test]
    fn the_pixel_scale_shrink_scales_each_cosine_by_its_response() {
        let (ny, nx, s) = (12, 17, 0.75);
        for (ky, kx) in [(0, 0), (1, 0), (0, 16), (11, 3), (6, 8), (11, 16)] {
            let wy = std::f64::consts::PI * ky as f64 / ny as f64;
            let wx = std::f64::consts::PI * kx as f64 / nx as f64;
            let a = Array2::from_shape_fn((ny, nx), |(i, j)| {
                (wy * (i as f64 + 0.5)).cos() * (wx * (j as f64 + 0.5)).cos()
            });
            let f = |w: f64| 1.0 - s * (w / 2.0).sin().powi(8);
            let out = shrink_near_nyquist(a.view(), s);
            for (o, v) in out.iter().zip(&a) {
                assert!(
                    (o - f(wy) * f(wx) * v).abs() < 1e-12,
                    "({ky}, {kx}): {o} vs {v}"
                );
            }
        }
    }

    /// Relief smoother than the pixel passes: a polynomial of degree 7 along each axis is kept
    /// away from the edges (the eighth difference annihilates it), and s = 0 is the identity.
    #[test]
    fn the_pixel_scale_shrink_keeps_polynomials_below_degree_eight() {
        let a = Array2::from_shape_fn((20, 24), |(i, j)| {
            let (y, x) = (i as f64 / 10.0, j as f64 / 10.0);
            3.0 + x - 2.0 * y * y + 0.5 * x.powi(7) - y.powi(5) * x.powi(2)
        });
        let out = shrink_near_nyquist(a.view(), 0.9);
        for i in 4..16 {
            for j in 4..20 {
                assert!((out[(i, j)] - a[(i, j)]).abs() < 1e-9 * a[(i, j)].abs().max(1.0));
            }
        }
        assert_eq!(shrink_near_nyquist(a.view(), 0.0), a);
    }

    #[test]
    fn gradient_at_one_pixel_is_the_gradient_there_to_the_bit() {
        for (ny, nx) in [(1, 1), (2, 2), (3, 5), (4, 4), (6, 7), (9, 11)] {
            let z = Array2::from_shape_fn((ny, nx), |(i, j)| {
                ((i * 7 + j * 13) as f64).sin() * 100.0 + (i * j) as f64 * 0.37
            });
            let (p, q) = gradient(z.view(), 140.0);
            for ((i, j), _) in z.indexed_iter() {
                let (a, b) = gradient_at(z.view(), 140.0, i, j);
                assert_eq!(
                    (a.to_bits(), b.to_bits()),
                    (p[(i, j)].to_bits(), q[(i, j)].to_bits()),
                    "{ny}×{nx} at ({i}, {j})"
                );
            }
        }
    }

    /// The block-by-block operator against its three passes (gradient, H per pixel, adjoint),
    /// in f32 as the conjugate gradients use it: the same bits, on shapes with one block, with
    /// several (a partial last one) and with fewer rows than the stencils reach.
    #[test]
    fn the_weighted_normal_is_its_three_passes_to_the_bit() {
        for (ny, nx) in [(1, 1), (2, 3), (3, 5), (5, 4), (33, 7), (70, 9), (97, 12)] {
            let v = Array2::from_shape_fn((ny, nx), |(i, j)| {
                (((i * 7 + j * 13) as f64).sin() * 100.0 + (i * j) as f64 * 0.37) as f32
            });
            let h = Array2::from_shape_fn((ny, nx), |(i, j)| {
                let t = (i * 3 + j * 5) as f32;
                [1.0 + t.sin().abs(), 0.3 * t.cos(), 2.0 + (0.7 * t).sin()]
            });
            let (mut vx, mut vy) = (Array2::zeros((ny, nx)), Array2::zeros((ny, nx)));
            gradient_into(v.view(), 140.0, &mut vx, &mut vy);
            ndarray::Zip::from(&mut vx)
                .and(&mut vy)
                .and(&h)
                .for_each(|x, y, h| {
                    let (a, b) = (*x, *y);
                    *x = h[0] * a + h[1] * b;
                    *y = h[1] * a + h[2] * b;
                });
            let mut want = Array2::zeros((ny, nx));
            gradient_adjoint_into(vx.view(), vy.view(), 140.0, &mut want);
            let mut got = Array2::zeros((ny, nx));
            weighted_normal_into(v.view(), &h, 140.0, &mut got);
            for ((ix, g), w) in got.indexed_iter().zip(&want) {
                assert_eq!(g.to_bits(), w.to_bits(), "{ny}×{nx} at {ix:?}");
            }
        }
    }

    #[test]
    fn gradient_of_a_plane_is_exact_and_north_is_up() {
        // z = 2x + 3y with x = j·ε east and y = −i·ε north.
        let eps = 10.0;
        let z = Array2::from_shape_fn((6, 7), |(i, j)| 2.0 * j as f64 * eps - 3.0 * i as f64 * eps);
        let (p, q) = gradient(z.view(), eps);
        assert!(p.iter().all(|x| (x - 2.0).abs() < 1e-12));
        assert!(q.iter().all(|x| (x - 3.0).abs() < 1e-12));
    }

    #[test]
    fn the_interior_gradient_is_exact_for_quartics() {
        // The fourth-order central difference is exact up to degree 4: z = x⁴ + x·y³ has
        // p = 4x³ + y³ and q = 3x·y², with x = j·ε and y = −i·ε. The plain central difference
        // is off by ε²·∂³z/∂x³/6 = 4x·ε² in p.
        let eps = 1.5;
        let (ny, nx) = (9, 11);
        let xy = |i: usize, j: usize| (j as f64 * eps, -(i as f64) * eps);
        let z = Array2::from_shape_fn((ny, nx), |(i, j)| {
            let (x, y) = xy(i, j);
            x.powi(4) + x * y.powi(3)
        });
        let (p, q) = gradient(z.view(), eps);
        for i in 2..ny - 2 {
            for j in 2..nx - 2 {
                let (x, y) = xy(i, j);
                let (pe, qe) = (4.0 * x.powi(3) + y.powi(3), 3.0 * x * y * y);
                assert!(
                    (p[(i, j)] - pe).abs() < 1e-9 * pe.abs().max(1.0),
                    "p at ({i}, {j})"
                );
                assert!(
                    (q[(i, j)] - qe).abs() < 1e-9 * qe.abs().max(1.0),
                    "q at ({i}, {j})"
                );
            }
        }
    }

    #[test]
    fn the_stencil_response_is_the_gradient_of_a_wave() {
        // z = sin(ωj): in the interior, p·ε = h(ω)·cos(ωj) with h = stencil_response.
        let n = 40;
        for omega in [0.3, std::f64::consts::FRAC_PI_2, 2.5] {
            let z = Array2::from_shape_fn((1, n), |(_, j)| (omega * j as f64).sin());
            let (p, _) = gradient(z.view(), 1.0);
            for j in 2..n - 2 {
                let expected = stencil_response(omega) * (omega * j as f64).cos();
                assert!((p[(0, j)] - expected).abs() < 1e-12, "ω {omega}, j {j}");
            }
        }
        // The figures of STENCIL's documentation: at 4 px wavelength the stencil sees 85 % of
        // the slope, the plain central difference 64 %.
        let w = std::f64::consts::FRAC_PI_2;
        assert!((stencil_response(w) / w - 0.849).abs() < 1e-3);
        assert!((w.sin() / w - 0.637).abs() < 1e-3);
    }

    #[test]
    fn adjoint_is_the_transpose() {
        // Entry by entry: ⟨D e_m, e_n⟩ = ⟨e_m, Dᵀ e_n⟩ for every pair of unit vectors, on
        // shapes that exercise the one-sided ends, the central rows next to them and the
        // interior stencil (or none of it).
        for (ny, nx) in [(9, 12), (1, 5), (2, 3), (6, 10), (13, 4), (5, 9)] {
            let unit =
                |m: usize| Array2::from_shape_fn((ny, nx), |(i, j)| f64::from(i * nx + j == m));
            let zero = Array2::<f64>::zeros((ny, nx));
            for m in 0..ny * nx {
                let (p, q) = gradient(unit(m).view(), 2.5);
                for n in 0..ny * nx {
                    let (i, j) = (n / nx, n % nx);
                    let dx = gradient_adjoint(unit(n).view(), zero.view(), 2.5);
                    let dy = gradient_adjoint(zero.view(), unit(n).view(), 2.5);
                    let (mi, mj) = (m / nx, m % nx);
                    assert_eq!(p[(i, j)], dx[(mi, mj)], "D_x {ny}×{nx} row {n} column {m}");
                    assert_eq!(q[(i, j)], dy[(mi, mj)], "D_y {ny}×{nx} row {n} column {m}");
                }
            }
        }
    }
}
