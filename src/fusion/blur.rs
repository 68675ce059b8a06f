//! An observation coarser than the grid: its detector pixel spans several grid pixels, so what
//! it measures at a grid pixel is the reflectance *averaged* over a neighbourhood, B_k R, not R
//! at the pixel's own slope (docs/science.md, "Images coarser than the grid"). B_k is modelled
//! as a Gaussian of σ_k grid pixels, truncated at ⌈3σ_k⌉ and normalised; the observation's term
//! of E_I becomes Σ_x w_k(x)·(I_k/g_k − (B_k R_k)(x))²/Ī².
//!
//! Where B_k is used, the pixels it averages over must all be modelled: an observation with a
//! kernel uses a pixel only where every pixel within the kernel's radius is usable and inside
//! the grid ([`erode`]). The convolutions then never reach past the grid on a used pixel, and
//! the transpose Bᵀ of a field that is 0 within the radius of the border is the same symmetric
//! convolution: the gradient and the Newton operator use [`convolve`] for both.

use crate::spectral::{to, Real};
use ndarray::{Array2, Axis, Zip};
use rayon::prelude::*;

/// A normalised, symmetric, truncated Gaussian: `taps[0]` at the centre, `taps[d]` at ±d.
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    pub taps: Vec<f64>,
}

/// The weight factor of an observation coarser than the grid in the final albedo map's joint
/// inversion, where a sharp observation is used too: it sees the albedo blurred. (Its image
/// enters that inversion sharpened, `fusion::sharpened_images`, which does most of the work:
/// 0.3 or 1 differ by 0.0001 in albedo RMSE. In the stages' inversions it keeps its full
/// weight and its own image: the surface comes out better so.)
pub const FINAL_ALBEDO_WEIGHT: f64 = 0.3;

/// Below this σ (grid pixels) an observation is taken as sharp: B_k is the identity.
pub const MIN_SIGMA_PX: f64 = 0.25;

impl Kernel {
    /// The Gaussian of σ pixels (`None` below [`MIN_SIGMA_PX`] or not finite).
    pub fn gaussian(sigma: f64) -> Option<Self> {
        if !(sigma.is_finite() && sigma >= MIN_SIGMA_PX) {
            return None;
        }
        let radius = (3.0 * sigma).ceil() as usize;
        let raw: Vec<f64> = (0..=radius)
            .map(|d| (-0.5 * (d as f64 / sigma).powi(2)).exp())
            .collect();
        let total = raw[0] + 2.0 * raw[1..].iter().sum::<f64>();
        Some(Self {
            taps: raw.into_iter().map(|t| t / total).collect(),
        })
    }

    /// ⌈3σ⌉: how far the kernel reaches.
    pub fn radius(&self) -> usize {
        self.taps.len() - 1
    }
}

/// σ in grid pixels of the blur an observation of `pixel_m` metres adds on a grid of
/// `spacing_m` (0 when its pixels are no coarser than the grid's). The detector's box of s grid
/// pixels (s = pixel/spacing; variance s²/12) and the bilinear tent that carries the swath onto
/// the grid (s²/6), less what an observation at the grid's own pixel size has of both, which
/// the solver's model stands for (1/12 + 1/6): σ² = (s² − 1)/4. Twice the grid's pixel:
/// σ = 0.87 px. Below [`MIN_SIGMA_PX`] (s < 1.12) 0: the observation counts as sharp.
pub fn sigma_px(pixel_m: f64, spacing_m: f64) -> f64 {
    let s = pixel_m / spacing_m;
    if !s.is_finite() || s <= 1.0 {
        return 0.0;
    }
    let sigma = ((s * s - 1.0) / 4.0).sqrt();
    if sigma < MIN_SIGMA_PX {
        0.0
    } else {
        sigma
    }
}

/// `a` convolved with `k` along both axes, indices clamped at the border.
pub fn convolve<T: Real>(k: &Kernel, a: &Array2<T>) -> Array2<T> {
    let (ny, nx) = a.dim();
    let taps: Vec<T> = k.taps.iter().map(|&t| to::<T>(t)).collect();
    let r = k.radius() as isize;
    let a = a.as_standard_layout();
    let mut rows = Array2::<T>::zeros((ny, nx));
    rows.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut out)| {
            let src = a.row(i);
            for j in 0..nx as isize {
                let mut s = taps[0] * src[j as usize];
                for d in 1..=r {
                    let (l, h) = ((j - d).max(0), (j + d).min(nx as isize - 1));
                    s = s + taps[d as usize] * (src[l as usize] + src[h as usize]);
                }
                out[j as usize] = s;
            }
        });
    let mut out = Array2::<T>::zeros((ny, nx));
    out.axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut o)| {
            let i = i as isize;
            o.assign(&rows.row(i as usize));
            o.mapv_inplace(|v| taps[0] * v);
            for d in 1..=r {
                let (l, h) = (
                    (i - d).max(0) as usize,
                    (i + d).min(ny as isize - 1) as usize,
                );
                let t = taps[d as usize];
                Zip::from(&mut o)
                    .and(rows.row(l))
                    .and(rows.row(h))
                    .for_each(|o, &a, &b| *o = *o + t * (a + b));
            }
        });
    out
}

/// `usable` kept only where every pixel within `radius` (a square) is usable and inside the
/// grid.
pub fn erode(usable: &Array2<bool>, radius: usize) -> Array2<bool> {
    let (ny, nx) = usable.dim();
    let r = radius;
    let mut rows = Array2::from_elem((ny, nx), false);
    Zip::indexed(&mut rows).par_for_each(|(i, j), o| {
        *o = j >= r && j + r < nx && (j - r..=j + r).all(|c| usable[(i, c)]);
    });
    Zip::indexed(&rows.clone())
        .map_collect(|(i, j), _| i >= r && i + r < ny && (i - r..=i + r).all(|l| rows[(l, j)]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kernel_is_a_normalised_gaussian() {
        let k = Kernel::gaussian(1.0).unwrap();
        assert_eq!(k.radius(), 3);
        let total = k.taps[0] + 2.0 * k.taps[1..].iter().sum::<f64>();
        assert!((total - 1.0).abs() < 1e-15);
        // Ratio of neighbouring taps: exp(−(d² − (d − 1)²)/2σ²).
        assert!((k.taps[1] / k.taps[0] - (-0.5f64).exp()).abs() < 1e-15);
        assert!((k.taps[2] / k.taps[1] - (-1.5f64).exp()).abs() < 1e-15);
        assert!(Kernel::gaussian(0.2).is_none());
        assert!(Kernel::gaussian(f64::NAN).is_none());
    }

    #[test]
    fn the_blur_of_a_coarser_detector_adds_to_the_grid_pixel_in_variance() {
        // Twice the grid's pixel: (4 − 1)/4.
        assert!((sigma_px(280.0, 140.0) - 0.75f64.sqrt()).abs() < 1e-15);
        assert!((sigma_px(420.0, 140.0) - 2f64.sqrt()).abs() < 1e-15);
        assert_eq!(sigma_px(140.0, 140.0), 0.0);
        assert_eq!(sigma_px(100.0, 140.0), 0.0);
        // M3's pixels a little wider than a grid set from them: sharp (σ would be 0.23 px).
        assert_eq!(sigma_px(1.1 * 140.0, 140.0), 0.0);
        assert!((sigma_px(1.2 * 140.0, 140.0) - 0.11f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn convolution_keeps_a_plane_and_is_its_own_transpose_away_from_the_border() {
        let k = Kernel::gaussian(0.9).unwrap();
        let plane = Array2::from_shape_fn((12, 15), |(i, j)| 2.0 * i as f64 - 3.0 * j as f64);
        let c = convolve(&k, &plane);
        let r = k.radius();
        for ((i, j), &v) in c.indexed_iter() {
            if i >= r && i + r < 12 && j >= r && j + r < 15 {
                assert!((v - plane[(i, j)]).abs() < 1e-12);
            }
        }
        // ⟨Bx, y⟩ = ⟨x, By⟩ for y zero within the radius of the border.
        let x = Array2::from_shape_fn((12, 15), |(i, j)| ((i * 7 + j * 3) % 5) as f64 - 2.0);
        let y = Array2::from_shape_fn((12, 15), |(i, j)| {
            if i >= r && i + r < 12 && j >= r && j + r < 15 {
                ((i * 5 + j * 11) % 7) as f64 - 3.0
            } else {
                0.0
            }
        });
        let lhs = (&convolve(&k, &x) * &y).sum();
        let rhs = (&x * &convolve(&k, &y)).sum();
        assert!((lhs - rhs).abs() < 1e-12, "{lhs} {rhs}");
    }

    #[test]
    fn erosion_keeps_pixels_whose_whole_neighbourhood_is_usable() {
        let mut u = Array2::from_elem((7, 7), true);
        u[(3, 3)] = false;
        let e = erode(&u, 1);
        // The border ring is gone (the kernel would leave the grid), and so is the 3 × 3
        // around the unusable pixel.
        let kept: Vec<_> = e
            .indexed_iter()
            .filter(|(_, &v)| v)
            .map(|(ij, _)| ij)
            .collect();
        assert_eq!(kept.len(), 25 - 9);
        assert!(!e[(2, 2)] && !e[(4, 4)] && e[(1, 1)] && e[(5, 1)]);
    }
}
