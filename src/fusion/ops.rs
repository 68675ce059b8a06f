//! Discrete operators of the fusion energy on a grid of `ny` rows (row 0 north) × `nx` columns
//! (column 0 west) with spacing ε metres.
//!
//! The photometric term reads the surface gradient at pixel centres by central differences,
//! one-sided at the edges: p = ∂z/∂x (east), q = ∂z/∂y (north, i.e. towards row − 1). The
//! quadratic terms use forward differences, which the DCT diagonalises (see `spectral`).

use ndarray::{Array2, ArrayView2, Axis, Zip};
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

/// (D v)[j] along a line accessed through `get`.
fn apply_1d(n: usize, j: usize, get: impl Fn(usize) -> f64) -> f64 {
    let lo = j.saturating_sub(1);
    let hi = (j + 1).min(n.saturating_sub(1));
    (lo..=hi).map(|k| coef(n, j, k) * get(k)).sum()
}

/// (Dᵀ u)[k] along a line accessed through `get`.
fn adjoint_1d(n: usize, k: usize, get: impl Fn(usize) -> f64) -> f64 {
    let lo = k.saturating_sub(1);
    let hi = (k + 1).min(n.saturating_sub(1));
    (lo..=hi).map(|j| coef(n, j, k) * get(j)).sum()
}

/// Surface gradients (p, q) at pixel centres.
pub fn gradient(z: ArrayView2<f64>, eps: f64) -> (Array2<f64>, Array2<f64>) {
    let (ny, nx) = z.dim();
    let mut p = Array2::zeros((ny, nx));
    let mut q = Array2::zeros((ny, nx));
    Zip::indexed(&mut p)
        .and(&mut q)
        .par_for_each(|(i, j), p, q| {
            *p = apply_1d(nx, j, |k| z[(i, k)]) / eps;
            // y points north = towards smaller row index.
            *q = -apply_1d(ny, i, |k| z[(k, j)]) / eps;
        });
    (p, q)
}

/// Adjoint of [`gradient`]: D_xᵀu + D_yᵀv (a negative divergence).
pub fn gradient_adjoint(u: ArrayView2<f64>, v: ArrayView2<f64>, eps: f64) -> Array2<f64> {
    let (ny, nx) = u.dim();
    let mut out = Array2::zeros((ny, nx));
    Zip::indexed(&mut out).par_for_each(|(i, j), o| {
        *o = (adjoint_1d(nx, j, |k| u[(i, k)]) - adjoint_1d(ny, i, |k| v[(k, j)])) / eps;
    });
    out
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
