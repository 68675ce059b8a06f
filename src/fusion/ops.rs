//! Discrete operators of the fusion energy on a grid of `ny` rows (row 0 north) × `nx` columns
//! (column 0 west) with spacing ε metres.
//!
//! The photometric term reads the surface gradient at pixel centres by central differences,
//! one-sided at the edges: p = ∂z/∂x (east), q = ∂z/∂y (north, i.e. towards row − 1). The
//! quadratic terms use forward differences, which the DCT diagonalises (see `spectral`).

use ndarray::{Array2, ArrayView1, ArrayView2, Axis};
use rayon::prelude::*;

/// Coefficient D[j][k]·ε of the 1-D central difference (one-sided at both ends) on `n` points.
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
    if k + 1 == j {
        -0.5
    } else if k == j + 1 {
        0.5
    } else {
        0.0
    }
}

/// (Dᵀu)[k]·ε for one line, gathered from u[k−1], u[k], u[k+1] via `get`.
#[inline]
fn adjoint_at(n: usize, k: usize, get: impl Fn(usize) -> f64) -> f64 {
    let lo = k.saturating_sub(1);
    let hi = (k + 1).min(n.saturating_sub(1));
    (lo..=hi).map(|j| coef(n, j, k) * get(j)).sum()
}

/// D v·ε along one contiguous line.
fn diff_line(v: &[f64], out: &mut [f64]) {
    let n = v.len();
    if n < 2 {
        out.iter_mut().for_each(|o| *o = 0.0);
        return;
    }
    out[0] = v[1] - v[0];
    out[n - 1] = v[n - 1] - v[n - 2];
    for j in 1..n - 1 {
        out[j] = 0.5 * (v[j + 1] - v[j - 1]);
    }
}

/// Dᵀu·ε along one contiguous line.
fn adjoint_line(u: &[f64], out: &mut [f64]) {
    let n = u.len();
    for k in 0..n {
        out[k] = if k >= 2 && k + 2 < n {
            0.5 * (u[k - 1] - u[k + 1])
        } else {
            adjoint_at(n, k, |j| u[j])
        };
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
pub fn gradient_into(z: ArrayView2<f64>, eps: f64, p: &mut Array2<f64>, q: &mut Array2<f64>) {
    let ny = z.nrows();
    let z = z.as_standard_layout();
    let inv = 1.0 / eps;
    p.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(q.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(i, (mut prow, mut qrow))| {
            let pr = prow.as_slice_mut().expect("standard layout");
            diff_line(z.row(i).as_slice().expect("standard layout"), pr);
            pr.iter_mut().for_each(|x| *x *= inv);
            // y points north = towards smaller row index: q = −(D along rows).
            let qr = qrow.as_slice_mut().expect("standard layout");
            if ny < 2 {
                qr.iter_mut().for_each(|x| *x = 0.0);
                return;
            }
            let (a, b, w) = if i == 0 {
                (1, 0, 1.0)
            } else if i == ny - 1 {
                (ny - 1, ny - 2, 1.0)
            } else {
                (i + 1, i - 1, 0.5)
            };
            let (ra, rb) = (z.row(a), z.row(b));
            let (ra, rb) = (
                ra.as_slice().expect("standard layout"),
                rb.as_slice().expect("standard layout"),
            );
            for ((o, x), y) in qr.iter_mut().zip(ra).zip(rb) {
                *o = -w * (x - y) * inv;
            }
        });
}

/// Adjoint of [`gradient`]: D_xᵀu + D_yᵀv (a negative divergence).
pub fn gradient_adjoint(u: ArrayView2<f64>, v: ArrayView2<f64>, eps: f64) -> Array2<f64> {
    let mut out = Array2::zeros(u.dim());
    gradient_adjoint_into(u, v, eps, &mut out);
    out
}

/// [`gradient_adjoint`] into `out` (standard layout, the shape of `u`).
pub fn gradient_adjoint_into(
    u: ArrayView2<f64>,
    v: ArrayView2<f64>,
    eps: f64,
    out: &mut Array2<f64>,
) {
    let ny = u.nrows();
    let u = u.as_standard_layout();
    let v = v.as_standard_layout();
    let inv = 1.0 / eps;
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(k, mut orow)| {
            let o = orow.as_slice_mut().expect("standard layout");
            adjoint_line(u.row(k).as_slice().expect("standard layout"), o);
            // Rows j ∈ {k−1, k, k+1} of v with coefficient coef(ny, j, k); q = −D_rows, so subtract.
            let lo = k.saturating_sub(1);
            let hi = (k + 1).min(ny.saturating_sub(1));
            for j in lo..=hi {
                let c = coef(ny, j, k);
                if c != 0.0 {
                    let vr = v.row(j);
                    for (x, y) in o.iter_mut().zip(vr.as_slice().expect("standard layout")) {
                        *x -= c * y;
                    }
                }
            }
            o.iter_mut().for_each(|x| *x *= inv);
        });
}

/// max |aᵢ| (0 for an empty array).
pub fn max_abs(a: ArrayView2<f64>) -> f64 {
    a.iter().fold(0.0, |m, x| m.max(x.abs()))
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

/// Σ aᵢ·bᵢ with the same determinism as [`sum`].
pub fn dot(a: ArrayView2<f64>, b: ArrayView2<f64>) -> f64 {
    a.axis_iter(Axis(0))
        .into_par_iter()
        .zip(b.axis_iter(Axis(0)))
        .map(|(x, y)| x.iter().zip(y).map(|(x, y)| x * y).sum::<f64>())
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
    fn gradient_of_a_plane_is_exact_and_north_is_up() {
        // z = 2x + 3y with x = j·ε east and y = −i·ε north.
        let eps = 10.0;
        let z = Array2::from_shape_fn((6, 7), |(i, j)| 2.0 * j as f64 * eps - 3.0 * i as f64 * eps);
        let (p, q) = gradient(z.view(), eps);
        assert!(p.iter().all(|x| (x - 2.0).abs() < 1e-12));
        assert!(q.iter().all(|x| (x - 3.0).abs() < 1e-12));
    }

    #[test]
    fn adjoint_is_the_transpose() {
        let (ny, nx) = (9, 12);
        let z = Array2::from_shape_fn((ny, nx), |(i, j)| ((i * 31 + j * 17) % 11) as f64);
        let u = Array2::from_shape_fn((ny, nx), |(i, j)| ((i * 7 + j * 5) % 13) as f64 - 6.0);
        let v = Array2::from_shape_fn((ny, nx), |(i, j)| ((i * 3 + j * 19) % 7) as f64 - 3.0);
        let (p, q) = gradient(z.view(), 2.5);
        let lhs = dot(p.view(), u.view()) + dot(q.view(), v.view());
        let rhs = dot(z.view(), gradient_adjoint(u.view(), v.view(), 2.5).view());
        assert!(
            (lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0),
            "{lhs} {rhs}"
        );
    }
}
