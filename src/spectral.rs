//! Orthonormal 2-D DCT-II with reflective (Neumann) boundaries, and the operators that are
//! diagonal in its basis: the 5-point Laplacian and Gaussian low-pass filters (docs/science.md,
//! "Solvers").
//!
//! Basis: φ_k(i) = c_k·cos(πk(i+½)/N), c_0 = √(1/N), c_k = √(2/N). It diagonalises
//! * the Neumann forward-difference Laplacian DᵀD with eigenvalues λ_k = 2 − 2cos(πk/N);
//! * convolution with any symmetric kernel on the half-sample-symmetric (mirror) extension of
//!   the signal, with transfer ĝ_k = Σₘ g(m)·cos(πkm/N).
//!
//! Transforms run row by row in parallel; each row is independent, so the result does not
//! depend on the number of threads.

use ndarray::{Array2, Axis, Zip};
use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::num_traits::Float;
use rustfft::{Fft, FftNum, FftPlanner};
use std::sync::Arc;

/// The element type a [`Dct2d`] transforms: `f64`, or `f32` where a few parts in 10⁷ are enough
/// (the conjugate-gradient iterations of `fusion::fast`: half the memory traffic of f64, and
/// the transforms are bound by memory, not arithmetic).
pub trait Real: FftNum + Float + std::iter::Sum + Default {}
impl Real for f32 {}
impl Real for f64 {}

/// `x` as `T` (rounded to f32 when `T` is f32).
#[inline]
pub(crate) fn to<T: Real>(x: f64) -> T {
    T::from(x).expect("finite f64 converts")
}

/// Orthonormal DCT-II / DCT-III of one length by Makhoul's algorithm: reorder
/// v = (x₀, x₂, x₄, …, x₅, x₃, x₁), take an N-point FFT, and X_k = Re(e^{−iπk/2N}·V_k). Two real
/// lines are transformed with one complex FFT (the second as the imaginary part). The
/// normalisation c_k (c_0 = √(1/N), c_k = √(2/N)), the ½ of the two-line split and the inverse
/// FFT's 1/N are folded into the twiddle factors.
#[derive(Clone)]
struct LineDct<T: Real> {
    n: usize,
    fwd: Arc<dyn Fft<T>>,
    inv: Arc<dyn Fft<T>>,
    /// Forward: T_k = e^{−iπk/2N}·c_k/2 (k ≥ 1).
    fwd_tw: Vec<Complex<T>>,
    /// Inverse: U_k = e^{iπk/2N}/(c_k·N) (k ≥ 1).
    inv_tw: Vec<Complex<T>>,
    /// c_0 and 1/(c_0·N).
    c0: T,
    s0: T,
    scratch_len: usize,
}

impl<T: Real> LineDct<T> {
    fn new(planner: &mut FftPlanner<T>, n: usize) -> Self {
        let fwd = planner.plan_fft_forward(n);
        let inv = planner.plan_fft_inverse(n);
        let (c0, ck) = Self::scales(n);
        // Twiddles in f64, rounded once to T.
        let tw =
            |k: usize| Complex::from_polar(1.0, -std::f64::consts::PI * k as f64 / (2 * n) as f64);
        let cast = |c: Complex<f64>| Complex::new(to::<T>(c.re), to::<T>(c.im));
        let fwd_tw = (0..n).map(|k| cast(tw(k) * (0.5 * ck))).collect();
        let inv_tw = (0..n)
            .map(|k| cast(tw(k).conj() / (ck * n as f64)))
            .collect();
        let scratch_len = fwd
            .get_inplace_scratch_len()
            .max(inv.get_inplace_scratch_len());
        Self {
            n,
            fwd,
            inv,
            fwd_tw,
            inv_tw,
            c0: to(c0),
            s0: to(1.0 / (c0 * n as f64)),
            scratch_len,
        }
    }

    /// (c_0, c_k) of the orthonormal basis of length `n`.
    fn scales(n: usize) -> (f64, f64) {
        let n = n as f64;
        ((1.0 / n).sqrt(), (2.0 / n).sqrt())
    }

    /// Orthonormal DCT-II of `a` and `b` in place.
    fn forward_pair(
        &self,
        a: &mut [T],
        b: &mut [T],
        buf: &mut [Complex<T>],
        scratch: &mut [Complex<T>],
    ) {
        let n = self.n;
        let (a, b, buf) = (&mut a[..n], &mut b[..n], &mut buf[..n]);
        let half = n.div_ceil(2);
        for m in 0..half {
            buf[m] = Complex::new(a[2 * m], b[2 * m]);
        }
        for m in 0..n / 2 {
            buf[n - 1 - m] = Complex::new(a[2 * m + 1], b[2 * m + 1]);
        }
        self.fwd.process_with_scratch(buf, scratch);
        // With W = FFT(v_a + i·v_b): V_a,k = (W_k + W̄_{N−k})/2, V_b,k = (W_k − W̄_{N−k})/(2i).
        a[0] = buf[0].re * self.c0;
        b[0] = buf[0].im * self.c0;
        for k in 1..n {
            let (w, v, t) = (buf[k], buf[n - k], self.fwd_tw[k]);
            a[k] = (w.re + v.re) * t.re - (w.im - v.im) * t.im;
            b[k] = (w.im + v.im) * t.re - (v.re - w.re) * t.im;
        }
    }

    /// Orthonormal DCT-III (the inverse of [`Self::forward_pair`]) of `a` and `b` in place.
    fn inverse_pair(
        &self,
        a: &mut [T],
        b: &mut [T],
        buf: &mut [Complex<T>],
        scratch: &mut [Complex<T>],
    ) {
        let n = self.n;
        let (a, b, buf) = (&mut a[..n], &mut b[..n], &mut buf[..n]);
        // Unnormalised X_k = Y_k/c_k, V_k = e^{iπk/2N}(X_k − i·X_{N−k}) (X_N = 0) for each line;
        // both lines at once: V_a + i·V_b = e^{iπk/2N}(X_a,k + X_b,N−k + i(X_b,k − X_a,N−k)).
        buf[0] = Complex::new(a[0] * self.s0, b[0] * self.s0);
        for k in 1..n {
            let x = Complex::new(a[k] + b[n - k], b[k] - a[n - k]);
            buf[k] = x * self.inv_tw[k];
        }
        self.inv.process_with_scratch(buf, scratch);
        let half = n.div_ceil(2);
        for m in 0..half {
            a[2 * m] = buf[m].re;
            b[2 * m] = buf[m].im;
        }
        for m in 0..n / 2 {
            a[2 * m + 1] = buf[n - 1 - m].re;
            b[2 * m + 1] = buf[n - 1 - m].im;
        }
    }
}

/// A planned orthonormal 2-D DCT for arrays of `ny` rows × `nx` columns of `T` ([`Real`]:
/// `f64` unless made by [`Dct2d::new_f32`]).
#[derive(Clone)]
pub struct Dct2d<T: Real = f64> {
    ny: usize,
    nx: usize,
    rows: LineDct<T>,
    cols: LineDct<T>,
}

impl<T: Real> std::fmt::Debug for Dct2d<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Dct2d({}×{})", self.ny, self.nx)
    }
}

impl Dct2d<f64> {
    pub fn new(ny: usize, nx: usize) -> Self {
        Self::plan(ny, nx)
    }

    /// `inverse(forward(a) ⊙ m)`: apply an operator that is diagonal in the DCT basis.
    pub fn apply_diagonal(&self, a: &Array2<f64>, m: &Array2<f64>) -> Array2<f64> {
        let mut c = self.forward(a);
        c *= m;
        self.inverse(&c)
    }
}

impl Dct2d<f32> {
    /// The transform of f32 arrays: ≈ 10⁻⁷ relative error instead of ≈ 10⁻¹⁶, in about half
    /// the time.
    pub fn new_f32(ny: usize, nx: usize) -> Self {
        Self::plan(ny, nx)
    }
}

impl<T: Real> Dct2d<T> {
    fn plan(ny: usize, nx: usize) -> Self {
        let mut planner = FftPlanner::new();
        Self {
            ny,
            nx,
            rows: LineDct::new(&mut planner, nx),
            cols: LineDct::new(&mut planner, ny),
        }
    }

    pub fn shape(&self) -> (usize, usize) {
        (self.ny, self.nx)
    }

    /// Forward transform: spatial values → orthonormal coefficients.
    pub fn forward(&self, a: &Array2<T>) -> Array2<T> {
        let mut out = a.as_standard_layout().into_owned();
        self.forward_in_place(&mut out);
        out
    }

    /// Inverse transform: orthonormal coefficients → spatial values.
    pub fn inverse(&self, a: &Array2<T>) -> Array2<T> {
        let mut out = a.as_standard_layout().into_owned();
        self.inverse_in_place(&mut out);
        out
    }

    /// [`Self::forward`] in place (no copy when `a` is in standard layout).
    pub fn forward_in_place(&self, a: &mut Array2<T>) {
        standardise(a);
        rows_apply(a, &self.rows, true);
        cols_apply(a, &self.cols, true);
    }

    /// [`Self::inverse`] in place (no copy when `a` is in standard layout).
    pub fn inverse_in_place(&self, a: &mut Array2<T>) {
        standardise(a);
        cols_apply(a, &self.cols, false);
        rows_apply(a, &self.rows, false);
    }
}

/// Make `a` row-major and contiguous, which the line transforms need (a no-op when it is).
fn standardise<T: Real>(a: &mut Array2<T>) {
    if !a.is_standard_layout() {
        *a = a.as_standard_layout().into_owned();
    }
}

/// Transform every row, two at a time; an odd last row is paired with a zero line.
fn rows_apply<T: Real>(a: &mut Array2<T>, plan: &LineDct<T>, forward: bool) {
    let n = a.ncols();
    a.axis_chunks_iter_mut(Axis(0), 2)
        .into_par_iter()
        .for_each_init(
            || {
                (
                    vec![Complex::new(T::zero(), T::zero()); n],
                    vec![Complex::new(T::zero(), T::zero()); plan.scratch_len],
                    vec![T::zero(); n],
                )
            },
            |(buf, scratch, spare), mut rows| {
                let mut it = rows.axis_iter_mut(Axis(0));
                let mut r0 = it.next().expect("chunk has a row");
                let a0 = r0.as_slice_mut().expect("standard layout rows");
                match it.next() {
                    Some(mut r1) => {
                        let a1 = r1.as_slice_mut().expect("standard layout rows");
                        if forward {
                            plan.forward_pair(a0, a1, buf, scratch);
                        } else {
                            plan.inverse_pair(a0, a1, buf, scratch);
                        }
                    }
                    None => {
                        spare.iter_mut().for_each(|x| *x = T::zero());
                        if forward {
                            plan.forward_pair(a0, spare, buf, scratch);
                        } else {
                            plan.inverse_pair(a0, spare, buf, scratch);
                        }
                    }
                }
            },
        );
}

/// Columns per block of [`cols_apply`]: 512 bytes of each row.
const COLUMN_BLOCK: usize = 64;

/// Transform every column in place, two at a time (columns 2m and 2m + 1, an odd last column
/// with a zero line: the pairs a transpose and [`rows_apply`] would form, so the result is
/// the same to the bit). Blocks of [`COLUMN_BLOCK`] columns are copied out row by row into
/// lines of one scratch buffer, transformed, and copied back, which reads and writes the array
/// once instead of transposing it twice. The lines are `ny + 8` apart, not `ny`: with a
/// power-of-two length every line would start in the same cache set, and the row-by-row copy
/// would evict its own lines.
fn cols_apply<T: Real>(a: &mut Array2<T>, plan: &LineDct<T>, forward: bool) {
    let ny = a.nrows();
    let stride = ny + 8;
    a.axis_chunks_iter_mut(Axis(1), COLUMN_BLOCK)
        .into_par_iter()
        .for_each_init(
            || {
                (
                    vec![Complex::new(T::zero(), T::zero()); ny],
                    vec![Complex::new(T::zero(), T::zero()); plan.scratch_len],
                    vec![T::zero(); stride * (COLUMN_BLOCK + 1)],
                )
            },
            |(buf, scratch, lines), mut block| {
                let w = block.ncols();
                for (i, row) in block.rows().into_iter().enumerate() {
                    for (k, v) in row.iter().enumerate() {
                        lines[k * stride + i] = *v;
                    }
                }
                let spare = COLUMN_BLOCK * stride;
                for k in (0..w).step_by(2) {
                    let (head, tail) = lines.split_at_mut((k + 1) * stride);
                    let first = &mut head[k * stride..k * stride + ny];
                    let second = if k + 1 < w {
                        &mut tail[..ny]
                    } else {
                        let at = spare - (k + 1) * stride;
                        let spare = &mut tail[at..at + ny];
                        spare.iter_mut().for_each(|x| *x = T::zero());
                        spare
                    };
                    if forward {
                        plan.forward_pair(first, second, buf, scratch);
                    } else {
                        plan.inverse_pair(first, second, buf, scratch);
                    }
                }
                for (i, mut row) in block.rows_mut().into_iter().enumerate() {
                    for (k, v) in row.iter_mut().enumerate() {
                        *v = lines[k * stride + i];
                    }
                }
            },
        );
}

/// 1-D eigenvalues 2 − 2cos(πk/N) of the Neumann second difference.
pub fn laplacian_eigenvalues(n: usize) -> Vec<f64> {
    (0..n)
        .map(|k| 2.0 - 2.0 * (std::f64::consts::PI * k as f64 / n as f64).cos())
        .collect()
}

/// 1-D DCT-domain symbol h(πk/N)² of a difference operator's normal operator DᵀD, h the
/// stencil's response to angular frequency ω (sin ω for the central difference). Exact in the
/// interior; used only for preconditioning.
pub fn difference_symbol(n: usize, response: impl Fn(f64) -> f64) -> Vec<f64> {
    (0..n)
        .map(|k| response(std::f64::consts::PI * k as f64 / n as f64).powi(2))
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

/// λ_lk/ε², the eigenvalues of the negative Laplacian (mirror boundaries) in the DCT basis over
/// the grid spacing squared: (λ_y(l) + λ_x(k))/ε² ([`laplacian_eigenvalues`]), held as its two
/// 1-D tables and formed where it is used, in the arithmetic a table of the grid's size would
/// have been filled with (16 B less per pixel than the table, values the same to the bit).
#[derive(Debug, Clone)]
pub struct LaplacianSymbol {
    y: Vec<f64>,
    x: Vec<f64>,
    e2: f64,
}

impl LaplacianSymbol {
    /// The symbol of an `ny × nx` grid of spacing `spacing`.
    pub fn new(ny: usize, nx: usize, spacing: f64) -> Self {
        Self {
            y: laplacian_eigenvalues(ny),
            x: laplacian_eigenvalues(nx),
            e2: spacing * spacing,
        }
    }

    /// λ_lk/ε² at row `l`, column `k`.
    #[inline]
    pub fn at(&self, l: usize, k: usize) -> f64 {
        (self.y[l] + self.x[k]) / self.e2
    }
}

/// Outer product table `t[l][k] = f(ay[l], ax[k])`.
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
    let mut out = a.as_standard_layout().into_owned();
    gaussian_filter_in_place(dct, &mut out, sigma);
    out
}

/// [`gaussian_filter`] in place: forward transform, each coefficient times ĝ_y(l)·ĝ_x(k) (the
/// value [`gaussian_table`] holds there, formed from the two 1-D transfers as it is, so the
/// result is the same to the bit), inverse transform. No table of the grid's size is made.
pub fn gaussian_filter_in_place(dct: &Dct2d, a: &mut Array2<f64>, sigma: f64) {
    if sigma <= 0.0 {
        return;
    }
    let (ny, nx) = dct.shape();
    let (gy, gx) = (gaussian_transfer(ny, sigma), gaussian_transfer(nx, sigma));
    dct.forward_in_place(a);
    a.axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(gy.par_iter())
        .for_each(|(mut row, &y)| {
            for (v, &x) in row.iter_mut().zip(&gx) {
                *v *= y * x;
            }
        });
    dct.inverse_in_place(a);
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
    normalised_gaussian(dct, a, mask.mapv(|b| if b { 1.0 } else { 0.0 }), sigma)
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
    normalised_gaussian(dct, a, w.to_owned(), sigma)
}

/// [`weighted_gaussian`] with the weights given as an array it may overwrite: G(w) is formed
/// in their place (two arrays of the grid's size in flight, not three).
fn normalised_gaussian(
    dct: &Dct2d,
    a: &Array2<f64>,
    mut w: Array2<f64>,
    sigma: f64,
) -> Option<Array2<f64>> {
    let total = w.sum();
    if total <= 0.0 {
        return None;
    }
    let wa = Zip::from(a).and(&w).map_collect(|&x, &w| x * w);
    let mean = wa.sum() / total;
    if sigma <= 0.0 {
        return Some(
            Zip::from(a)
                .and(&w)
                .map_collect(|&x, &w| if w > 0.0 { x } else { mean }),
        );
    }
    // G(w·a) in place of w·a, then the quotient in place of G(w·a).
    let mut num = wa;
    gaussian_filter_in_place(dct, &mut num, sigma);
    gaussian_filter_in_place(dct, &mut w, sigma);
    let floor = 1e-6 * total / w.len() as f64;
    Zip::from(&mut num)
        .and(&w)
        .for_each(|n, &d| *n = if d > floor { *n / d } else { mean });
    Some(num)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::ArrayView2;

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

    /// The orthonormal 2-D DCT-II of `a` straight from its definition (O(N²) per coefficient).
    fn dct_by_definition(a: &Array2<f64>) -> Array2<f64> {
        let (ny, nx) = a.dim();
        let pi = std::f64::consts::PI;
        let ck = |k: usize, n: usize| {
            if k == 0 {
                (1.0 / n as f64).sqrt()
            } else {
                (2.0 / n as f64).sqrt()
            }
        };
        Array2::from_shape_fn((ny, nx), |(l, k)| {
            let mut s = 0.0;
            for i in 0..ny {
                for j in 0..nx {
                    s += a[(i, j)]
                        * (pi * l as f64 * (i as f64 + 0.5) / ny as f64).cos()
                        * (pi * k as f64 * (j as f64 + 0.5) / nx as f64).cos();
                }
            }
            s * ck(l, ny) * ck(k, nx)
        })
    }

    #[test]
    fn the_filter_in_place_and_the_laplacian_symbol_match_their_tables_to_the_bit() {
        let (ny, nx) = (37, 52);
        let a = test_array(ny, nx);
        let d = Dct2d::new(ny, nx);
        for sigma in [0.0, 0.7, 3.0, 11.0] {
            let want = if sigma > 0.0 {
                d.apply_diagonal(&a, &gaussian_table(ny, nx, sigma))
            } else {
                a.clone()
            };
            let got = gaussian_filter(&d, &a, sigma);
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(g, w)| g.to_bits() == w.to_bits()),
                "σ {sigma}"
            );
        }
        let e2 = 140.0 * 140.0;
        let table = separable(
            &laplacian_eigenvalues(ny),
            &laplacian_eigenvalues(nx),
            |a, b| (a + b) / e2,
        );
        let lam = LaplacianSymbol::new(ny, nx, 140.0);
        for ((l, k), &t) in table.indexed_iter() {
            assert_eq!(lam.at(l, k).to_bits(), t.to_bits());
        }
    }

    #[test]
    fn matches_the_dct_ii_definition() {
        for (ny, nx) in [(5, 7), (6, 4), (1, 3), (9, 2)] {
            let a = test_array(ny, nx);
            let c = Dct2d::new(ny, nx).forward(&a);
            let want = dct_by_definition(&a);
            for ((l, k), w) in want.indexed_iter() {
                assert!(
                    (c[(l, k)] - w).abs() < 1e-10,
                    "{ny}×{nx} ({l},{k}): {} vs {w}",
                    c[(l, k)]
                );
            }
        }
    }

    /// The f32 transform (the conjugate gradients') is the same DCT to f32's precision: within
    /// 10⁻⁶ of the largest coefficient of the definition, forward and back, on shapes with odd
    /// lengths and more columns than one block of the column pass.
    #[test]
    fn the_f32_transform_matches_the_definition_to_f32_precision() {
        for (ny, nx) in [(5, 7), (9, 2), (33, 70), (16, 130)] {
            let a = test_array(ny, nx);
            let want = dct_by_definition(&a);
            let scale = want.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            let d = Dct2d::new_f32(ny, nx);
            let mut c = a.mapv(|x| x as f32);
            d.forward_in_place(&mut c);
            for ((l, k), w) in want.indexed_iter() {
                let got = f64::from(c[(l, k)]);
                assert!(
                    (got - w).abs() < 1e-6 * scale,
                    "{ny}×{nx} ({l},{k}): {got} vs {w}"
                );
            }
            d.inverse_in_place(&mut c);
            let amax = a.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for (x, y) in a.iter().zip(&c) {
                assert!(
                    (x - f64::from(*y)).abs() < 1e-6 * amax,
                    "{ny}×{nx} round trip"
                );
            }
        }
    }

    /// Cache-blocked parallel transpose into a new standard-layout array (the reference the
    /// column pass is checked against).
    fn transpose(a: ArrayView2<f64>) -> Array2<f64> {
        const B: usize = 32;
        let (ny, nx) = a.dim();
        let a = a.as_standard_layout();
        let src = a.as_slice().expect("standard layout");
        let mut out = Array2::<f64>::zeros((nx, ny));
        out.as_slice_mut()
            .expect("standard layout")
            .par_chunks_mut(B * ny)
            .enumerate()
            .for_each(|(bi, block)| {
                let x0 = bi * B;
                let w = block.len() / ny.max(1);
                for y0 in (0..ny).step_by(B) {
                    let y1 = (y0 + B).min(ny);
                    for y in y0..y1 {
                        let row = &src[y * nx + x0..y * nx + x0 + w];
                        for (dx, v) in row.iter().enumerate() {
                            block[dx * ny + y] = *v;
                        }
                    }
                }
            });
        out
    }

    #[test]
    fn the_column_pass_equals_transposed_rows_to_the_bit() {
        for (ny, nx) in [(5, 7), (8, 8), (9, 17), (33, 64), (7, 150), (1, 4), (4, 1)] {
            let a = test_array(ny, nx);
            let dct = Dct2d::new(ny, nx);
            for forward in [true, false] {
                let mut t = transpose(a.view());
                rows_apply(&mut t, &dct.cols, forward);
                let want = transpose(t.view());
                let mut got = a.clone();
                cols_apply(&mut got, &dct.cols, forward);
                assert!(
                    got.iter()
                        .zip(&want)
                        .all(|(x, y)| x.to_bits() == y.to_bits()),
                    "{ny}×{nx}, forward {forward}"
                );
            }
        }
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
