//! Photometric support: how far each pixel is from the nearest pixel the image constrains, and
//! the smooth weight s ∈ [0, 1] that the energy and the result use to fade the correction
//! z − z_DEM out where no image constrains the surface (docs/science.md, "Where the image
//! ends").
//!
//! s = 1 within `r0` pixels of a photometric pixel, 0 beyond `r1`, and the C¹ smoothstep
//! 3t² − 2t³ of t = (r1 − d)/(r1 − r0) between. Distances are exact Euclidean distances in
//! pixels (Felzenszwalb & Huttenlocher's lower envelope of parabolas, one pass per axis).
//! A pixel's s depends only on the mask within `r1` of it, so a tile with a halo ≥ `r1` gets
//! the same s as the whole region.

use ndarray::{Array2, Axis, Zip};
use rayon::prelude::*;

/// Squared distance transform of one line: f[i] = 0 at sources, `inf` elsewhere, in place.
fn edt_line(f: &mut [f64], v: &mut Vec<usize>, z: &mut Vec<f64>, out: &mut [f64]) {
    let n = f.len();
    v.clear();
    z.clear();
    // Lower envelope of the parabolas (x − q)² + f[q] over the finite f[q].
    for q in 0..n {
        if !f[q].is_finite() {
            continue;
        }
        loop {
            let Some(&p) = v.last() else {
                v.push(q);
                z.push(f64::NEG_INFINITY);
                break;
            };
            let s = ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q - p) as f64);
            if s <= *z.last().expect("z has one entry per parabola") {
                v.pop();
                z.pop();
            } else {
                v.push(q);
                z.push(s);
                break;
            }
        }
    }
    if v.is_empty() {
        out.iter_mut().for_each(|o| *o = f64::INFINITY);
        return;
    }
    let mut k = 0;
    for (x, o) in out.iter_mut().enumerate() {
        while k + 1 < v.len() && z[k + 1] < x as f64 {
            k += 1;
        }
        let d = x as f64 - v[k] as f64;
        *o = d * d + f[v[k]];
    }
    f.copy_from_slice(out);
}

/// Exact Euclidean distance, in pixels, from each pixel to the nearest `true` pixel of `mask`
/// (0 on the mask; +∞ everywhere when the mask is empty).
pub fn distance(mask: &Array2<bool>) -> Array2<f64> {
    let mut d = mask.mapv(|b| if b { 0.0 } else { f64::INFINITY });
    let pass = |a: &mut Array2<f64>, axis: Axis| {
        a.axis_iter_mut(axis).into_par_iter().for_each(|mut lane| {
            let mut f: Vec<f64> = lane.iter().copied().collect();
            let mut out = vec![0.0; f.len()];
            edt_line(&mut f, &mut Vec::new(), &mut Vec::new(), &mut out);
            lane.iter_mut().zip(&f).for_each(|(l, &x)| *l = x);
        });
    };
    // Columns first (lanes along axis 0 are iterated over axis 1), then rows.
    pass(&mut d, Axis(1));
    pass(&mut d, Axis(0));
    d.mapv_inplace(f64::sqrt);
    d
}

/// C¹ step: 0 at t ≤ 0, 1 at t ≥ 1, 3t² − 2t³ between (NaN stays NaN).
pub(crate) fn smoothstep(t: f64) -> f64 {
    let t = t.clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// The support weight s(d): 1 for d ≤ r0, 0 for d ≥ r1, C¹ smoothstep between.
pub fn weight(d: f64, r0: f64, r1: f64) -> f64 {
    if d <= r0 {
        1.0
    } else if d >= r1 {
        0.0
    } else {
        smoothstep((r1 - d) / (r1 - r0))
    }
}

/// The band of the support weight for a DEM term of width `sigma_dem` pixels: (r0, r1) =
/// (σ, 3σ) with σ = max(σ_DEM, 1 px). Beyond r1 (at most 3 σ_DEM for σ_DEM ≥ 1) the result is
/// the input DEM.
pub fn band(sigma_dem: f64) -> (f64, f64) {
    let s = sigma_dem.max(1.0);
    (s, 3.0 * s)
}

/// s for every pixel, given the photometric mask.
pub fn support(mask: &Array2<bool>, r0: f64, r1: f64) -> Array2<f64> {
    Zip::from(&distance(mask)).par_map_collect(|&d| weight(d, r0, r1))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The transform against brute force on an irregular mask.
    #[test]
    fn distances_are_exact() {
        let (ny, nx) = (23, 31);
        let mask = Array2::from_shape_fn((ny, nx), |(i, j)| {
            (i * 7 + j * 13) % 29 == 0 || (i == 11 && j > 20)
        });
        let d = distance(&mask);
        let src: Vec<(usize, usize)> = mask
            .indexed_iter()
            .filter(|(_, &b)| b)
            .map(|(ij, _)| ij)
            .collect();
        for ((i, j), &got) in d.indexed_iter() {
            let want = src
                .iter()
                .map(|&(a, b)| {
                    let (di, dj) = (a as f64 - i as f64, b as f64 - j as f64);
                    (di * di + dj * dj).sqrt()
                })
                .fold(f64::INFINITY, f64::min);
            assert!((got - want).abs() < 1e-12, "({i},{j}): {got} vs {want}");
        }
        assert!(distance(&Array2::from_elem((4, 5), false))
            .iter()
            .all(|d| d.is_infinite()));
    }

    #[test]
    fn weight_is_smooth_and_bounded() {
        assert_eq!(weight(0.0, 3.0, 9.0), 1.0);
        assert_eq!(weight(3.0, 3.0, 9.0), 1.0);
        assert_eq!(weight(9.0, 3.0, 9.0), 0.0);
        assert_eq!(weight(f64::INFINITY, 3.0, 9.0), 0.0);
        assert!((weight(6.0, 3.0, 9.0) - 0.5).abs() < 1e-15);
        // C¹: one-sided slopes vanish at both ends.
        let h = 1e-6;
        assert!((weight(3.0 + h, 3.0, 9.0) - 1.0).abs() < 1e-10);
        assert!(weight(9.0 - h, 3.0, 9.0) < 1e-10);
    }
}
