//! Detector column striping: the relative gain of each detector column of a pushbroom swath,
//! estimated from the swath itself.
//!
//! M3 images each line with the same row of detector columns, so a column whose calibration is
//! off by a fraction ε brightens or darkens the whole length of the strip by ε: a stripe along
//! the track. Shape from shading reads such a stripe as a slope across it, and with several
//! observations as a disagreement between them (docs/science.md, "Detector column striping").
//!
//! The estimate, for one observation, in ln r (r the reflectance, so that a gain adds):
//! 1. The swath is cut into blocks of [`BLOCK_LINES`] lines. In each block b, each column's
//!    median m_b(c) over its usable pixels (a median, so that a crater or a shadow in a few
//!    lines does not count), high-passed across the columns:
//!    h_b(c) = m_b(c) − median_j{(m_b(c − j) + m_b(c + j))/2}, j = 1 … R, R =
//!    [`HALF_WINDOW`] (fewer pairs near the swath's edges; the first and last columns, with
//!    no neighbour on one side, are not measured). The running median of the pairs' means
//!    removes the illumination's and the albedo's trends across the swath (a linear one
//!    cancels in every pair), and keeps what changes from one column to the next. (Leaving column c out keeps
//!    h_b(c) from being exactly 0 whenever c is its window's median, which would pull the
//!    medians of step 2 to 0.)
//! 2. A stripe is the same in every block; the terrain in h_b changes from block to block.
//!    Over the blocks, each column's median μ(c) estimates its stripe, and the spread of its
//!    h_b (σ(c) = 1.4826·MAD) the terrain left in that estimate: n²(c) = (π/2)·σ²(c)/B(c),
//!    the variance of a median of B(c) values.
//! 3. The stripes' own variance s² = mean μ² − mean n², taken as none unless mean μ² exceeds
//!    mean n² by three times its spread without stripes ((1 + 3·√(2/C))·mean n², C columns);
//!    and each column's ln g(c) = k(c)·μ(c) with k(c) = s²/(s² + n²(c)): the estimate
//!    shrunk by how much of it is stripe rather than terrain (a Wiener factor).
//!
//! Only what changes within R columns is seen: the part of the stripes that is smooth over
//! them (about a fifth of their variance for independent column gains) stays. Wider windows
//! would see it, but on the synthetic scenes they take the scene's own structure, which at
//! that width runs over several blocks, for stripes (docs/science.md, "Detector column
//! striping").
//!
//! Images without striping get s² = 0 and gains of exactly 1; a long strip
//! (thousands of lines) measures its stripes closely, a short one shrinks them towards 1.
//! Dividing each column's reflectance by g(c) removes its stripe. A gain trend across the
//! whole swath looks like the illumination's and is left to the observation's gain.

use crate::fusion::ops::median;
use serde::{Deserialize, Serialize};

/// Lines per block (the last, shorter, block of a swath counts from half this).
pub const BLOCK_LINES: usize = 32;

/// R: each column is compared with the median of its neighbours' means in pairs (c − j,
/// c + j), j = 1 … R.
pub const HALF_WINDOW: usize = 4;

/// Fewest blocks a column needs for its gain to be estimated (1 otherwise).
pub const MIN_BLOCKS: usize = 4;

/// One observation's column medians m_b(c), block by block ([`ColumnProfiles::add_block`]).
#[derive(Debug, Clone, Default)]
pub struct ColumnProfiles {
    /// m_b(c) of every block so far, NaN where block b could not measure column c.
    blocks: Vec<Vec<f64>>,
}

/// The relative gain of each detector column, and what the estimate saw
/// ([`ColumnProfiles::gains`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ColumnGains {
    /// g(c) per detector column (sample), 1 where not estimated: the observed radiance is
    /// g(c) times what the column would see calibrated like its neighbours.
    pub gain: Vec<f64>,
    pub summary: Striping,
}

/// What a column gain estimate saw (the run record's `column_striping`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Striping {
    /// Blocks measured (the most any column had).
    pub blocks: usize,
    /// Columns with a gain other than 1 (an offset other than 0).
    pub columns: usize,
    /// √s²: the stripes' RMS in ln r, or in metres for a DEM's tracks (0 when none stand out
    /// of the terrain).
    pub stripe_rms: f64,
    /// √(mean n²): the RMS of the terrain left in each column's estimate, in ln r (metres).
    pub noise_rms: f64,
    /// RMS of ln g(c) (of the offsets) over the columns: the correction applied.
    pub correction_rms: f64,
}

/// What the estimate at one half-window found: ln g(c) (0 where nothing), s², mean n², the
/// most blocks.
struct Scale {
    ln_gain: Vec<f64>,
    s2: f64,
    n2: f64,
    blocks: usize,
}

impl ColumnProfiles {
    /// Add one block: `ln_r` holds its lines (rows) of every column, ln of the reflectance,
    /// NaN where a pixel is not usable (refused, dark, outside the swath). A block of fewer
    /// than [`BLOCK_LINES`]/2 lines is skipped; a column needs half the block's lines usable to
    /// be measured.
    pub fn add_block(&mut self, ln_r: ndarray::ArrayView2<f64>) {
        let lines = ln_r.nrows();
        if lines < BLOCK_LINES / 2 {
            return;
        }
        let m: Vec<f64> = ln_r
            .columns()
            .into_iter()
            .map(|col| {
                let mut v: Vec<f64> = col.iter().copied().filter(|x| x.is_finite()).collect();
                if 2 * v.len() < lines {
                    f64::NAN
                } else {
                    median(&mut v).unwrap_or(f64::NAN)
                }
            })
            .collect();
        self.blocks.push(m);
    }

    /// Add every block of [`BLOCK_LINES`] lines of `ln_r` (lines × columns, as
    /// [`ColumnProfiles::add_block`]).
    pub fn add_lines(&mut self, ln_r: ndarray::ArrayView2<f64>) {
        let lines = ln_r.nrows();
        for start in (0..lines).step_by(BLOCK_LINES) {
            let end = (start + BLOCK_LINES).min(lines);
            self.add_block(ln_r.slice(ndarray::s![start..end, ..]));
        }
    }

    /// The column gains (module documentation); `None` before any block.
    pub fn gains(&self) -> Option<ColumnGains> {
        let (offset, summary) = self.offsets()?;
        Some(ColumnGains {
            gain: offset.iter().map(|l| l.exp()).collect(),
            summary,
        })
    }

    /// The estimate of the module documentation in the units the blocks were given in: each
    /// column's additive stripe (0 where none is estimated), and what the estimate saw. Of
    /// ln r, these are ln g(c) ([`ColumnProfiles::gains`]); of heights, an altimeter's offset
    /// between its tracks where they run along the columns (`ingest::lola_track_offsets`).
    /// `None` before any block.
    pub fn offsets(&self) -> Option<(Vec<f64>, Striping)> {
        self.offsets_within(HALF_WINDOW)
    }

    /// [`ColumnProfiles::offsets`] with each column compared with its neighbours up to `r`
    /// columns either side (R of the module documentation).
    pub fn offsets_within(&self, r: usize) -> Option<(Vec<f64>, Striping)> {
        let cols = self.blocks.first()?.len();
        let scale = self.scale(r, &vec![0.0; cols]);
        let columns = scale.ln_gain.iter().filter(|&&l| l != 0.0).count();
        let correction_rms =
            (scale.ln_gain.iter().map(|l| l * l).sum::<f64>() / cols.max(1) as f64).sqrt();
        let summary = Striping {
            blocks: scale.blocks,
            columns,
            stripe_rms: scale.s2.sqrt(),
            noise_rms: scale.n2.sqrt(),
            correction_rms,
        };
        Some((scale.ln_gain, summary))
    }

    /// The module documentation's steps at half-window `r`, on the medians less `prior` (ln
    /// gains already taken out; none for [`ColumnProfiles::gains`]).
    fn scale(&self, r: usize, prior: &[f64]) -> Scale {
        let cols = prior.len();
        // h_b(c) of every block: its corrected median less the median of its neighbours'
        // means in pairs (c − j, c + j), j = 1 … w, w = r or fewer near the swath's edges,
        // down to r/4; NaN where the column or fewer than half the pairs are measured. A trend
        // across the swath cancels in every pair.
        let h: Vec<Vec<f64>> = self
            .blocks
            .iter()
            .map(|m| {
                let m: Vec<f64> = m.iter().zip(prior).map(|(m, p)| m - p).collect();
                (0..cols)
                    .map(|c| {
                        let w = r.min(c).min(cols - 1 - c);
                        if 4 * w < r {
                            return f64::NAN;
                        }
                        let mut pairs: Vec<f64> = (1..=w)
                            .map(|j| 0.5 * (m[c - j] + m[c + j]))
                            .filter(|x| x.is_finite())
                            .collect();
                        if m[c].is_nan() || 2 * pairs.len() < w {
                            f64::NAN
                        } else {
                            median(&mut pairs).map_or(f64::NAN, |r| m[c] - r)
                        }
                    })
                    .collect()
            })
            .collect();
        // Per column: μ(c), n²(c) and B(c), where B(c) ≥ MIN_BLOCKS.
        let per_column: Vec<Option<(f64, f64, usize)>> = (0..cols)
            .map(|c| {
                let mut v: Vec<f64> = h.iter().map(|h| h[c]).filter(|x| x.is_finite()).collect();
                let b = v.len();
                if b < MIN_BLOCKS {
                    return None;
                }
                let mu = median(&mut v)?;
                let mut dev: Vec<f64> = v.iter().map(|x| (x - mu).abs()).collect();
                let sigma = 1.4826 * median(&mut dev)?;
                Some((
                    mu,
                    std::f64::consts::FRAC_PI_2 * sigma * sigma / b as f64,
                    b,
                ))
            })
            .collect();
        let measured: Vec<(f64, f64, usize)> = per_column.iter().flatten().copied().collect();
        let blocks = measured.iter().map(|m| m.2).max().unwrap_or(0);
        let n = measured.len() as f64;
        let (mean_mu2, mean_n2) = if measured.is_empty() {
            (0.0, 0.0)
        } else {
            (
                measured.iter().map(|m| m.0 * m.0).sum::<f64>() / n,
                measured.iter().map(|m| m.1).sum::<f64>() / n,
            )
        };
        // Without stripes, mean μ² / mean n² is 1 within ≈ √(2/C) over C columns: stripes
        // count only beyond three times that.
        let detected = mean_mu2 > (1.0 + 3.0 * (2.0 / n.max(1.0)).sqrt()) * mean_n2;
        let s2 = if detected { mean_mu2 - mean_n2 } else { 0.0 };
        let ln_gain = per_column
            .iter()
            .map(|m| match m {
                Some((mu, n2, _)) if s2 > 0.0 => s2 / (s2 + n2) * mu,
                _ => 0.0,
            })
            .collect();
        Scale {
            ln_gain,
            s2,
            n2: mean_n2,
            blocks,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;
    use ndarray::Array2;

    /// ln r of a swath: a smooth trend across it, terrain-like noise of `terrain` (ln r) per
    /// pixel, and stripes `stripe[c]`.
    fn swath(lines: usize, stripe: &[f64], terrain: f64, seed: u64) -> Array2<f64> {
        let mut rng = Rng::new(seed);
        Array2::from_shape_fn((lines, stripe.len()), |(_, c)| {
            -2.0 + 0.002 * c as f64 + stripe[c] + terrain * rng.normal()
        })
    }

    fn stripes(cols: usize, rms: f64, seed: u64) -> Vec<f64> {
        let mut rng = Rng::new(seed);
        (0..cols).map(|_| rms * rng.normal()).collect()
    }

    fn rms(v: impl Iterator<Item = f64>, n: usize) -> f64 {
        (v.map(|x| x * x).sum::<f64>() / n as f64).sqrt()
    }

    #[test]
    fn a_long_strip_gives_back_its_stripes() {
        // 1 % stripes under 5 % terrain over 2048 lines (64 blocks): each column's estimate
        // carries ≈ 1.25·5 %/√32/√64 ≈ 0.14 % of terrain; what is smooth over 4 columns each
        // side is not seen (≈ 0.2 of the stripes' variance).
        let cols = 304;
        let truth = stripes(cols, 0.01, 7);
        let mut p = ColumnProfiles::default();
        p.add_lines(swath(2048, &truth, 0.05, 8).view());
        let g = p.gains().unwrap();
        assert_eq!(g.summary.blocks, 64);
        // Every column but the first and the last, which have no neighbours on one side.
        assert_eq!(g.summary.columns, cols - 2);
        assert_eq!((g.gain[0], g.gain[cols - 1]), (1.0, 1.0));
        // Against the truth less its mean (a gain common to every column is not a stripe).
        let mean = truth.iter().sum::<f64>() / cols as f64;
        let centred: Vec<f64> = truth.iter().map(|t| t - mean).collect();
        let est_mean = g.gain.iter().map(|g| g.ln()).sum::<f64>() / cols as f64;
        let err = rms(
            g.gain
                .iter()
                .zip(&centred)
                .map(|(g, t)| g.ln() - est_mean - t),
            cols,
        );
        let raw = rms(centred.iter().copied(), cols);
        assert!(err < 0.5 * raw, "left {err:.5} of {raw:.5}");
        let sum = g.summary;
        assert!(
            (sum.stripe_rms - raw).abs() < 0.15 * raw,
            "{} vs {raw}",
            sum.stripe_rms
        );
        assert!(sum.noise_rms < 0.003, "{}", sum.noise_rms);
    }

    /// Heights: a DEM gridded from altimeter tracks along its columns, 4 m offsets between
    /// them under 10 m of terrain per pixel over a tilted plane, in 16-line blocks (as
    /// `ingest::lola_track_offsets` reads a DEM) over 256 lines. The offsets come back in
    /// metres, the same numbers `gains` gives as logarithms.
    #[test]
    fn heights_give_back_their_track_offsets_in_metres() {
        let cols = 160;
        let truth = stripes(cols, 4.0, 11);
        let mut rng = Rng::new(12);
        let heights = Array2::from_shape_fn((256, cols), |(l, c)| {
            -1500.0 + 3.0 * c as f64 - 0.5 * l as f64 + truth[c] + 10.0 * rng.normal()
        });
        let mut p = ColumnProfiles::default();
        for start in (0..256).step_by(16) {
            p.add_block(heights.slice(ndarray::s![start..start + 16, ..]));
        }
        let (off, sum) = p.offsets().unwrap();
        assert_eq!(sum.blocks, 16);
        let mean = truth.iter().sum::<f64>() / cols as f64;
        let est_mean = off.iter().sum::<f64>() / cols as f64;
        let err = rms(
            off.iter()
                .zip(&truth)
                .map(|(o, t)| o - est_mean - (t - mean)),
            cols,
        );
        let raw = rms(truth.iter().map(|t| t - mean), cols);
        assert!(err < 0.6 * raw, "left {err:.2} m of {raw:.2} m");
        assert!(
            (sum.stripe_rms - raw).abs() < 0.25 * raw,
            "{} vs {raw}",
            sum.stripe_rms
        );
        let g = p.gains().unwrap();
        assert_eq!(g.summary, sum);
        for (g, o) in g.gain.iter().zip(&off) {
            assert_eq!(*g, o.exp());
        }
    }

    #[test]
    fn a_strip_without_stripes_keeps_gains_of_one() {
        let cols = 304;
        let mut p = ColumnProfiles::default();
        p.add_lines(swath(1024, &vec![0.0; cols], 0.05, 9).view());
        let g = p.gains().unwrap();
        let off = g.gain.iter().map(|g| g.ln().abs()).fold(0.0, f64::max);
        assert!(off < 5e-4, "largest correction {off}");
        assert!(
            g.summary.correction_rms < 1e-4,
            "{}",
            g.summary.correction_rms
        );
    }

    #[test]
    fn too_few_lines_or_usable_pixels_estimate_nothing() {
        let cols = 64;
        let truth = stripes(cols, 0.01, 3);
        // Three blocks: under MIN_BLOCKS.
        let mut p = ColumnProfiles::default();
        p.add_lines(swath(3 * BLOCK_LINES, &truth, 0.01, 4).view());
        let g = p.gains().unwrap();
        assert!(g.gain.iter().all(|&g| g == 1.0));
        assert_eq!(g.summary.columns, 0);
        // A block of fewer than half BLOCK_LINES lines is not measured.
        let mut p = ColumnProfiles::default();
        p.add_lines(swath(BLOCK_LINES / 2 - 1, &truth, 0.01, 4).view());
        assert!(p.gains().is_none());
        // Columns with fewer than half their pixels usable are not measured; the others are.
        let mut img = swath(8 * BLOCK_LINES, &truth, 0.01, 5);
        for mut line in img.rows_mut().into_iter().step_by(2) {
            line[10] = f64::NAN;
            line[11] = f64::NAN;
        }
        line_nan_in_three_of_four(&mut img, 20);
        let mut p = ColumnProfiles::default();
        p.add_lines(img.view());
        let g = p.gains().unwrap();
        assert_eq!(g.gain[20], 1.0);
        assert_ne!(g.gain[10], 1.0, "half of the lines usable is enough");
        assert_ne!(g.gain[30], 1.0);
    }

    fn line_nan_in_three_of_four(img: &mut Array2<f64>, c: usize) {
        for (i, mut line) in img.rows_mut().into_iter().enumerate() {
            if i % 4 != 0 {
                line[c] = f64::NAN;
            }
        }
    }
}
