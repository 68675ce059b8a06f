//! Orthonormal 2-D DCT-II with reflective (Neumann) boundaries, and the operators that are
//! diagonal in its basis: the 5-point Laplacian and Gaussian low-pass filters (ALGORITHM.md,
//! "Making it fast").
//!
//! Basis: φ_k(i) = c_k·cos(πk(i+½)/N), c_0 = √(1/N), c_k = √(2/N). It diagonalises
//! * the Neumann forward-difference Laplacian DᵀD with eigenvalues λ_k = 2 − 2cos(πk/N);
//! * convolution with any symmetric kernel on the half-sample-symmetric (mirror) extension of
//!   the signal, with transfer ĝ_k = Σₘ g(m)·cos(πkm/N).
//!
//! Transforms run row by row in parallel; each row is independent, so the result does not
//! depend on the number of threads.

use ndarray::{Array2, ArrayView2, Axis, Zip};
use rayon::prelude::*;
use rustdct::{DctPlanner, TransformType2And3};
use std::sync::Arc;

/// A planned orthonormal 2-D DCT for arrays of `ny` rows × `nx` columns.
#[derive(Clone)]
pub struct Dct2d {
    ny: usize,
    nx: usize,
    rows: Arc<dyn TransformType2And3<f64>>,
    cols: Arc<dyn TransformType2And3<f64>>,
}

impl std::fmt::Debug for Dct2d {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Dct2d({}×{})", self.ny, self.nx)
    }
}

impl Dct2d {
    pub fn new(ny: usize, nx: usize) -> Self {
        let mut planner = DctPlanner::new();
        Self {
            ny,
            nx,
            rows: planner.plan_dct2(nx),
            cols: planner.plan_dct2(ny),
        }
    }

    pub fn shape(&self) -> (usize, usize) {
        (self.ny, self.nx)
    }

    /// Forward transform: spatial values → orthonormal coefficients.
    pub fn forward(&self, a: &Array2<f64>) -> Array2<f64> {
        let mut out = a.as_standard_layout().into_owned();
        rows_apply(&mut out, &self.rows, true);
        let mut t = transpose(out.view());
        rows_apply(&mut t, &self.cols, true);
        transpose(t.view())
    }

    /// Inverse transform: orthonormal coefficients → spatial values.
    pub fn inverse(&self, a: &Array2<f64>) -> Array2<f64> {
        let mut t = transpose(a.view());
        rows_apply(&mut t, &self.cols, false);
        let mut out = transpose(t.view());
        rows_apply(&mut out, &self.rows, false);
        out
    }

    /// `inverse(forward(a) ⊙ m)`: apply an operator that is diagonal in the DCT basis.
    pub fn apply_diagonal(&self, a: &Array2<f64>, m: &Array2<f64>) -> Array2<f64> {
        let mut c = self.forward(a);
        c *= m;
        self.inverse(&c)
    }
}

fn rows_apply(a: &mut Array2<f64>, plan: &Arc<dyn TransformType2And3<f64>>, forward: bool) {
    let n = a.ncols();
    let c0 = (1.0 / n as f64).sqrt();
    let ck = (2.0 / n as f64).sqrt();
    a.axis_iter_mut(Axis(0)).into_par_iter().for_each_init(
        || vec![0.0; plan.get_scratch_len()],
        |scratch, mut row| {
            let buf = row.as_slice_mut().expect("standard layout rows");
            if forward {
                plan.process_dct2_with_scratch(buf, scratch);
                buf[0] *= c0;
                buf[1..].iter_mut().for_each(|x| *x *= ck);
            } else {
                buf[0] *= 2.0 * c0;
                buf[1..].iter_mut().for_each(|x| *x *= ck);
                plan.process_dct3_with_scratch(buf, scratch);
            }
        },
    );
}

/// Cache-blocked parallel transpose into a new standard-layout array.
pub fn transpose(a: ArrayView2<f64>) -> Array2<f64> {
    const B: usize = 32;
    let (ny, nx) = a.dim();
    let mut out = Array2::<f64>::zeros((nx, ny));
    out.axis_chunks_iter_mut(Axis(0), B)
        .into_par_iter()
        .enumerate()
        .for_each(|(bi, mut block)| {
            let x0 = bi * B;
            for y0 in (0..ny).step_by(B) {
                for y in y0..(y0 + B).min(ny) {
                    for (dx, mut orow) in block.axis_iter_mut(Axis(0)).enumerate() {
                        orow[y] = a[(y, x0 + dx)];
                    }
                }
            }
        });
    out
}

/// 1-D eigenvalues 2 − 2cos(πk/N) of the Neumann second difference.
pub fn laplacian_eigenvalues(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos())
        .collect()
}

/// 1-D DCT-domain symbol sin²(πk/N) of the central difference's normal operator (exact in the
/// interior; used only for preconditioning).
pub fn central_symbol(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| (std::f64::consts::PI * k as f64 / n as f64).sin().powi(2))
        .collect()
}

/// Transfer function ĝ_k = Σₘ g(m)·cos(πkm/N) of the sampled, unit-sum Gaussian of width `sigma`
/// pixels on the mirror extension of an `n`-point signal. σ = 0 is the identity.
pub fn gaussian_transfer(n: usize, sigma: f64) -> Vec<f64> {
    if sigma <= 0.0 {
        return vec![1.0; n];
    }
    let radius = (6.0 * sigma).ceil() as i64 + 1;
    let w: Vec<f64> = (0..=radius)
        .map(|m| (-(m * m) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let norm = w[0] + 2.0 * w[1..].iter().sum::<f64>();
    (0..n)
        .map(|k| {
            let om = std::f64::consts::PI * k as f64 / n as f64;
            (w[0]
                + 2.0
                    * w.iter()
                        .enumerate()
                        .skip(1)
                        .map(|(m, g)| g * (om * m as f64).cos())
                        .sum::<f64>())
                / norm
        })
        .collect()
}

/// Outer product table t[l][k] = f(ay[l], ax[k]).
pub fn separable(ay: &[f64], ax: &[f64], f: impl Fn(f64, f64) -> f64 + Sync) -> Array2<f64> {
    let mut t = Array2::zeros((ay.len(), ax.len()));
    t.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(ay.par_iter())
        .for_each(|(mut row, &y)| {
            for (v, &x) in row.iter_mut().zip(ax) {
                *v = f(y, x);
            }
        });
    t
}

/// 2-D Gaussian transfer table for a `ny × nx` grid.
pub fn gaussian_table(ny: usize, nx: usize, sigma: f64) -> Array2<f64> {
    separable(
        &gaussian_transfer(ny, sigma),
        &gaussian_transfer(nx, sigma),
        |a, b| a * b,
    )
}

/// Gaussian low-pass of width `sigma` pixels with mirror boundaries.
pub fn gaussian_filter(dct: &Dct2d, a: &Array2<f64>, sigma: f64) -> Array2<f64> {
    if sigma <= 0.0 {
        return a.clone();
    }
    let (ny, nx) = dct.shape();
    dct.apply_diagonal(a, &gaussian_table(ny, nx, sigma))
}

/// Normalised (masked) Gaussian: G(m·a)/G(m) where `mask` is true, filling masked-out pixels
/// from their valid neighbourhood. Where no valid pixel lies within reach, the mean of all
/// valid pixels is used. `None` when no pixel is valid.
pub fn masked_gaussian(
    dct: &Dct2d,
    a: &Array2<f64>,
    mask: &Array2<bool>,
    sigma: f64,
) -> Option<Array2<f64>> {
    weighted_gaussian(dct, a, &mask.mapv(|b| if b { 1.0 } else { 0.0 }), sigma)
}

/// Normalised weighted Gaussian G(w·a)/G(w) (w ≥ 0; w = 0 excludes a pixel). Where the
/// weights vanish within reach, the weighted mean of all pixels is used. `None` when all
/// weights are 0.
pub fn weighted_gaussian(
    dct: &Dct2d,
    a: &Array2<f64>,
    w: &Array2<f64>,
    sigma: f64,
) -> Option<Array2<f64>> {
    let total = w.sum();
    if total <= 0.0 {
        return None;
    }
    let wa = Zip::from(a).and(w).map_collect(|&x, &w| x * w);
    let mean = wa.sum() / total;
    if sigma <= 0.0 {
        return Some(
            Zip::from(a)
                .and(w)
                .map_collect(|&x, &w| if w > 0.0 { x } else { mean }),
        );
    }
    let num = gaussian_filter(dct, &wa, sigma);
    let den = gaussian_filter(dct, w, sigma);
    let floor = 1e-6 * total / w.len() as f64;
    Some(
        Zip::from(&num)
            .and(&den)
            .map_collect(|&n, &d| if d > floor { n / d } else { mean }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn test_array(ny: usize, nx: usize) -> Array2<f64> {
        Array2::from_shape_fn((ny, nx), |(i, j)| {
            ((i * 7 + j * 13) % 17) as f64 + (0.3 * i as f64).sin() * j as f64
        })
    }

    /// Direct convolution on the mirror extension x[−1] = x[0], x[N] = x[N−1], …
    fn mirror_convolve(a: &Array2<f64>, sigma: f64) -> Array2<f64> {
        let radius = (6.0 * sigma).ceil() as i64 + 1;
        let w: Vec<f64> = (-radius..=radius)
            .map(|m| (-(m * m) as f64 / (2.0 * sigma * sigma)).exp())
            .collect();
        let norm: f64 = w.iter().sum();
        let reflect = |i: i64, n: i64| {
            let p = i.rem_euclid(2 * n);
            (if p < n { p } else { 2 * n - 1 - p }) as usize
        };
        let pass = |a: &Array2<f64>, axis: usize| {
            let (ny, nx) = a.dim();
            Array2::from_shape_fn((ny, nx), |(i, j)| {
                let mut s = 0.0;
                for (k, m) in (-radius..=radius).enumerate() {
                    s += w[k]
                        * if axis == 0 {
                            a[(reflect(i as i64 + m, ny as i64), j)]
                        } else {
                            a[(i, reflect(j as i64 + m, nx as i64))]
                        };
                }
                s / norm
            })
        };
        pass(&pass(a, 0), 1)
    }

    #[test]
    fn round_trip_is_identity_and_orthonormal() {
        let a = test_array(37, 50);
        let d = Dct2d::new(37, 50);
        let c = d.forward(&a);
        let b = d.inverse(&c);
        assert!((&a - &b).iter().all(|x| x.abs() < 1e-11));
        let e_space: f64 = a.iter().map(|x| x * x).sum();
        let e_freq: f64 = c.iter().map(|x| x * x).sum();
        assert!(((e_space - e_freq) / e_space).abs() < 1e-13);
    }

    #[test]
    fn gaussian_in_dct_domain_equals_mirror_convolution() {
        let a = test_array(31, 44);
        let d = Dct2d::new(31, 44);
        // Includes a kernel wider than the array (multiple reflections).
        for sigma in [0.7, 2.9, 10.0, 40.0] {
            let f = gaussian_filter(&d, &a, sigma);
            let g = mirror_convolve(&a, sigma);
            let err = (&f - &g).iter().fold(0.0f64, |m, x| m.max(x.abs()));
            assert!(err < 1e-10, "σ={sigma}: {err}");
        }
    }

    #[test]
    fn laplacian_is_diagonal() {
        let (ny, nx) = (23, 30);
        let a = test_array(ny, nx);
        // Neumann 5-point Laplacian applied directly: Σ over existing neighbours (a_n − a).
        let direct = Array2::from_shape_fn((ny, nx), |(i, j)| {
            let mut s = 0.0;
            if i > 0 {
                s += a[(i - 1, j)] - a[(i, j)];
            }
            if i + 1 < ny {
                s += a[(i + 1, j)] - a[(i, j)];
            }
            if j > 0 {
                s += a[(i, j - 1)] - a[(i, j)];
            }
            if j + 1 < nx {
                s += a[(i, j + 1)] - a[(i, j)];
            }
            -s
        });
        let d = Dct2d::new(ny, nx);
        let lam = separable(
            &laplacian_eigenvalues(ny),
            &laplacian_eigenvalues(nx),
            |a, b| a + b,
        );
        let spectral = d.apply_diagonal(&a, &lam);
        assert!((&direct - &spectral).iter().all(|x| x.abs() < 1e-10));
    }

    #[test]
    fn masked_gaussian_fills_holes_and_keeps_constants() {
        let (ny, nx) = (20, 25);
        let d = Dct2d::new(ny, nx);
        let a = Array2::from_elem((ny, nx), 0.37);
        let mask = Array2::from_shape_fn((ny, nx), |(i, j)| (i + j) % 3 != 0);
        let f = masked_gaussian(&d, &a, &mask, 4.0).unwrap();
        assert!(f.iter().all(|x| (x - 0.37).abs() < 1e-12));
        assert!(masked_gaussian(&d, &a, &Array2::from_elem((ny, nx), false), 4.0).is_none());
    }
}
