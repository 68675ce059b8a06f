//! Radiometric gains between observations (docs/science.md, "Several observations"): I_k =
//! g_k·R, with g_k a constant per observation ([`estimate_gains`]) and optionally a trend along
//! its track ([`estimate_gain_trends`], [`GainTrend`]), both estimated where observations overlap
//! on a given surface, relative to the first observation of each overlapping group.

use super::ops::median;
use super::Problem;
use crate::photometry::{Albedo, ReflectanceModel};
use ndarray::{Array2, ArrayView2, Zip};
use rayon::prelude::*;

/// The most pixels a pair of observations is sampled at for its gain ratio.
pub const GAIN_SAMPLES: usize = 1 << 16;

/// Fewest overlapping pixels from which a pair of observations informs the gains.
pub const MIN_OVERLAP: usize = 50;

/// The gains of [`estimate_gains`] and what each is relative to.
#[derive(Debug, Clone, PartialEq)]
pub struct GainEstimate {
    /// g_k.
    pub gains: Vec<f64>,
    /// The observation g_k is relative to: the first (lowest index) of its overlapping group,
    /// itself for that one; `None` where it overlaps no other observation by
    /// [`MIN_OVERLAP`] pixels, so that nothing tied its gain down and g = 1 is assumed.
    pub relative_to: Vec<Option<usize>>,
}

/// The gains g_k, from where observations overlap on surface `z`: for each pair (j, k) the
/// median over their common usable pixels (every `stride`-th row and column, at most about
/// [`GAIN_SAMPLES`]) of ln(I_k/g_k) − ln R_k(ρ_j), ρ_j inverted from
/// I_j/g_j, is the error of ln g_k − ln g_j; the logs are corrected by least squares over the
/// pairs (weighted by overlap size) with the first observation of each connected group fixed,
/// three times over (R is not linear in ρ for Hapke). Observations overlapping no other keep
/// g = 1. The groups are those of the first pass's pairs.
pub fn estimate_gains(pr: &Problem, usable: &[Array2<bool>], z: ArrayView2<f64>) -> GainEstimate {
    let k_obs = pr.observations.len();
    let mut log_g = vec![0.0; k_obs];
    let mut relative_to: Vec<Option<usize>> = (0..k_obs).map(|_| None).collect();
    if k_obs < 2 {
        return GainEstimate {
            gains: vec![1.0; k_obs],
            relative_to: (0..k_obs).map(Some).collect(),
        };
    }
    let (p, q) = super::ops::gradient(z, pr.spacing);
    // Every `stride`-th row and column: at most ≈ GAIN_SAMPLES pixels per pair (a median needs
    // no more, and each sample costs an albedo inversion).
    let stride = ((z.len() as f64 / GAIN_SAMPLES as f64).sqrt().ceil() as usize).max(1);
    for pass in 0..3 {
        let g: Vec<f64> = log_g.iter().map(|l: &f64| l.exp()).collect();
        let mut pairs = Vec::new();
        for j in 0..k_obs {
            for k in j + 1..k_obs {
                let samples = pair_ratios(pr, usable, (p.view(), q.view()), &g, (j, k), stride);
                let mut all: Vec<f64> = samples.into_iter().map(|s| s.2).collect();
                if all.len() >= MIN_OVERLAP {
                    let n = all.len() as f64;
                    if let Some(m) = median(&mut all) {
                        pairs.push((j, k, m, n));
                    }
                }
            }
        }
        if pairs.is_empty() {
            break;
        }
        if pass == 0 {
            let root = group_roots(k_obs, &pairs);
            for &(j, k, _, _) in &pairs {
                relative_to[j] = Some(root[j]);
                relative_to[k] = Some(root[k]);
            }
        }
        let delta = solve_pairs(k_obs, &pairs);
        for (l, d) in log_g.iter_mut().zip(&delta) {
            *l += d;
        }
    }
    GainEstimate {
        gains: log_g.iter().map(|l| l.exp()).collect(),
        relative_to,
    }
}

/// ln(I_k/g_k) − ln R_k(ρ_j) at the common usable pixels (row, column) of observations j and
/// k, every `stride`-th row and column, ρ_j inverted from I_j/g_j on the slopes `p`, `q`
/// ([`estimate_gains`]); row order.
fn pair_ratios(
    pr: &Problem,
    usable: &[Array2<bool>],
    (p, q): (ArrayView2<f64>, ArrayView2<f64>),
    g: &[f64],
    (j, k): (usize, usize),
    stride: usize,
) -> Vec<(usize, usize, f64)> {
    let model: &dyn ReflectanceModel = pr.model;
    let (oj, ok) = (&pr.observations[j], &pr.observations[k]);
    let rows: Vec<Vec<(usize, usize, f64)>> = (0..p.nrows())
        .into_par_iter()
        .step_by(stride)
        .map(|i| {
            let mut out = Vec::new();
            for c in (0..p.ncols()).step_by(stride) {
                if !(usable[j][(i, c)] && usable[k][(i, c)]) {
                    continue;
                }
                let (pp, qq) = (p[(i, c)], q[(i, c)]);
                let ij = oj.image[(i, c)] / g[j];
                let ik = ok.image[(i, c)] / g[k];
                let Albedo::Value(rho) =
                    model.invert(ij, pp, qq, &oj.sun.at(i, c), &oj.view.at(i, c))
                else {
                    continue;
                };
                let r = model.shade(pp, qq, rho, &ok.sun.at(i, c), &ok.view.at(i, c));
                if r.lit && r.r > 0.0 {
                    out.push((i, c, ik.ln() - r.r.ln()));
                }
            }
            out
        })
        .collect();
    rows.into_iter().flatten().collect()
}

/// A gain that drifts along an observation's track, as a detector's response or the
/// photometric model's error drifting over an orbit would: the observation's gain at swath line
/// l is g·exp(τ·(l' − l̄)/1000), l' = l clamped to the lines the trend was measured over, g its
/// gain ([`estimate_gains`], which then holds at l̄). Beyond those lines it is not carried on:
/// a trend measured where two strips overlap over part of their length says nothing of the
/// rest.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct GainTrend {
    /// τ: the change of ln g per 1000 swath lines.
    pub per_1000_lines: f64,
    /// l̄: the line at which the trend is 1 (the mean line of the observation's pixels on the
    /// grid the trend was estimated on).
    pub line: f64,
    /// The first and last lines it was measured over (where it overlaps the others).
    pub lines: [f64; 2],
}

impl GainTrend {
    /// exp(τ·(l' − l̄)/1000): what the observation's image is divided by at swath line `line`.
    pub fn factor(&self, line: f64) -> f64 {
        let l = line.clamp(self.lines[0], self.lines[1]);
        (self.per_1000_lines * (l - self.line) / 1000.0).exp()
    }
}

/// The fewest swath lines the pixels two observations share must span for them to inform a
/// gain trend ([`estimate_gain_trends`]).
pub const MIN_TREND_LINES: f64 = 128.0;

/// Bins of a pair's samples along the track ([`estimate_gain_trends`]).
pub const TREND_BINS: usize = 16;

/// The gain trends τ_k ([`GainTrend`]) from where observations overlap, with the gains `g` of
/// [`estimate_gains`] (and its `relative_to`) on surface `z`; `lines[k]` the swath line each
/// pixel of observation k comes from. For each pair (j, k) sharing pixels over at least
/// [`MIN_TREND_LINES`] of k's lines, the samples of [`estimate_gains`] (ln(I_k/g_k) −
/// ln R_k(ρ_j), which the trends make u_k·τ_k − u_j·τ_j plus a constant, u = (l − l̄)/1000) are
/// cut into [`TREND_BINS`] bins of equal count along k's lines; each bin's median, against its
/// mean u_j and u_k, is one equation, all centred on the pair's means (the constant is the
/// gains'). τ is 0 at the first observation of each group (its gain's reference) and found by
/// least squares over the pairs' equations, weighted by the bins' counts. An observation no
/// such pair informs has none. Returns, per observation, its trend (`None`: none estimated, or
/// the group's first).
pub fn estimate_gain_trends(
    pr: &Problem,
    usable: &[Array2<bool>],
    z: ArrayView2<f64>,
    (g, relative_to): (&[f64], &[Option<usize>]),
    lines: &[ArrayView2<f32>],
) -> Vec<Option<GainTrend>> {
    let k_obs = pr.observations.len();
    let mean_line: Vec<Option<f64>> = (0..k_obs)
        .map(|k| {
            let (mut s, mut n) = (0.0, 0usize);
            Zip::from(&usable[k]).and(lines[k]).for_each(|&u, &l| {
                if u && l.is_finite() {
                    s += f64::from(l);
                    n += 1;
                }
            });
            (n > 0).then(|| s / n as f64)
        })
        .collect();
    let (p, q) = super::ops::gradient(z, pr.spacing);
    let stride = ((z.len() as f64 / GAIN_SAMPLES as f64).sqrt().ceil() as usize).max(1);
    // Normal equations of Σ n_b (τ_k ũ_k − τ_j ũ_j − m̃)².
    let mut a = vec![vec![0.0; k_obs]; k_obs];
    let mut b = vec![0.0; k_obs];
    let mut informed = vec![false; k_obs];
    // The lines each observation's trend is measured over: [first, last].
    let mut measured = vec![[f64::INFINITY, f64::NEG_INFINITY]; k_obs];
    for j in 0..k_obs {
        for k in j + 1..k_obs {
            let (Some(lj), Some(lk)) = (mean_line[j], mean_line[k]) else {
                continue;
            };
            let mut samples: Vec<(f64, f64, f64)> =
                pair_ratios(pr, usable, (p.view(), q.view()), g, (j, k), stride)
                    .into_iter()
                    .filter_map(|(i, c, r)| {
                        let (uj, uk) = (f64::from(lines[j][(i, c)]), f64::from(lines[k][(i, c)]));
                        (uj.is_finite() && uk.is_finite())
                            .then(|| ((uj - lj) / 1000.0, (uk - lk) / 1000.0, r))
                    })
                    .collect();
            if samples.len() < MIN_OVERLAP * TREND_BINS {
                continue;
            }
            samples.sort_by(|x, y| x.1.total_cmp(&y.1));
            let span = 1000.0 * (samples[samples.len() - 1].1 - samples[0].1);
            if span < MIN_TREND_LINES {
                continue;
            }
            let per = samples.len().div_ceil(TREND_BINS);
            let bins: Vec<(f64, f64, f64, f64)> = samples
                .chunks(per)
                .filter_map(|c| {
                    let n = c.len() as f64;
                    let mut r: Vec<f64> = c.iter().map(|s| s.2).collect();
                    let m = median(&mut r)?;
                    let uj = c.iter().map(|s| s.0).sum::<f64>() / n;
                    let uk = c.iter().map(|s| s.1).sum::<f64>() / n;
                    Some((uj, uk, m, n))
                })
                .collect();
            let w: f64 = bins.iter().map(|x| x.3).sum();
            let mean = |f: fn(&(f64, f64, f64, f64)) -> f64| {
                bins.iter().map(|x| x.3 * f(x)).sum::<f64>() / w
            };
            let (mj, mk, mm) = (mean(|x| x.0), mean(|x| x.1), mean(|x| x.2));
            for &(uj, uk, m, n) in &bins {
                // Row of the equation: +ũ_k at k, −ũ_j at j.
                let (cj, ck, rhs) = (-(uj - mj), uk - mk, m - mm);
                a[k][k] += n * ck * ck;
                a[j][j] += n * cj * cj;
                a[j][k] += n * cj * ck;
                a[k][j] += n * cj * ck;
                b[k] += n * ck * rhs;
                b[j] += n * cj * rhs;
            }
            informed[j] = true;
            informed[k] = true;
            for s in &samples {
                for (o, line) in [(j, lj + 1000.0 * s.0), (k, lk + 1000.0 * s.1)] {
                    measured[o] = [measured[o][0].min(line), measured[o][1].max(line)];
                }
            }
        }
    }
    // Each group's first observation is the reference (τ = 0), as is any not informed.
    let fixed: Vec<bool> = (0..k_obs)
        .map(|k| !informed[k] || relative_to[k].is_none_or(|r| r == k))
        .collect();
    let tau = solve_fixed(a, b, &fixed);
    (0..k_obs)
        .map(|k| {
            (!fixed[k]).then(|| GainTrend {
                per_1000_lines: tau[k],
                line: mean_line[k].expect("informed"),
                lines: measured[k],
            })
        })
        .collect()
}

/// x solving A x = b with x_k = 0 where `fixed[k]` (Gaussian elimination with partial
/// pivoting on the free unknowns; a free unknown without a pivot is left at 0).
fn solve_fixed(mut a: Vec<Vec<f64>>, mut b: Vec<f64>, fixed: &[bool]) -> Vec<f64> {
    let n = b.len();
    for k in 0..n {
        if fixed[k] {
            a[k] = vec![0.0; n];
            a[k][k] = 1.0;
            b[k] = 0.0;
            for row in a.iter_mut().take(n) {
                row[k] = 0.0;
            }
            a[k][k] = 1.0;
        }
    }
    let scale = (0..n)
        .map(|k| a[k][k].abs())
        .fold(0.0, f64::max)
        .max(1e-300);
    let mut x = vec![0.0; n];
    let mut order: Vec<usize> = (0..n).collect();
    for col in 0..n {
        let piv = (col..n)
            .max_by(|&r, &s| a[order[r]][col].abs().total_cmp(&a[order[s]][col].abs()))
            .expect("rows left");
        order.swap(col, piv);
        let pr = order[col];
        if a[pr][col].abs() <= 1e-12 * scale {
            continue;
        }
        let pivot = a[pr].clone();
        for &r in &order[col + 1..] {
            let f = a[r][col] / pivot[col];
            if f != 0.0 {
                for (x, p) in a[r][col..].iter_mut().zip(&pivot[col..]) {
                    *x -= f * p;
                }
                b[r] -= f * b[pr];
            }
        }
    }
    for col in (0..n).rev() {
        let pr = order[col];
        if a[pr][col].abs() <= 1e-12 * scale {
            continue;
        }
        let s: f64 = (col + 1..n).map(|c| a[pr][c] * x[c]).sum();
        x[col] = (b[pr] - s) / a[pr][col];
    }
    x
}

/// The connected groups of the observations linked by `pairs`: each observation's group
/// root, the group's lowest index (itself where it is in no pair).
fn group_roots(k_obs: usize, pairs: &[(usize, usize, f64, f64)]) -> Vec<usize> {
    let mut group: Vec<usize> = (0..k_obs).collect();
    let find = |g: &Vec<usize>, mut a: usize| {
        while g[a] != a {
            a = g[a];
        }
        a
    };
    for &(j, k, _, _) in pairs {
        let (a, b) = (find(&group, j), find(&group, k));
        let (lo, hi) = (a.min(b), a.max(b));
        group[hi] = lo;
    }
    (0..k_obs).map(|k| find(&group, k)).collect()
}

/// Least squares δ_k − δ_j = c_jk (weight n_jk) over the pairs, δ = 0 at the first
/// observation of each connected group (Gauss–Seidel; the groups are small graphs).
fn solve_pairs(k_obs: usize, pairs: &[(usize, usize, f64, f64)]) -> Vec<f64> {
    // Connected groups: the reference is each group's lowest index.
    let root = group_roots(k_obs, pairs);
    let reference: Vec<bool> = (0..k_obs).map(|k| root[k] == k).collect();
    let mut d = vec![0.0; k_obs];
    for _ in 0..500 {
        let mut moved = 0.0f64;
        for k in 0..k_obs {
            if reference[k] {
                continue;
            }
            let (mut s, mut w) = (0.0, 0.0);
            for &(a, b, c, n) in pairs {
                if b == k {
                    s += n * (d[a] + c);
                    w += n;
                } else if a == k {
                    s += n * (d[b] - c);
                    w += n;
                }
            }
            if w > 0.0 {
                let new = s / w;
                moved = moved.max((new - d[k]).abs());
                d[k] = new;
            }
        }
        if moved < 1e-12 {
            break;
        }
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fusion::observations::weights;

    /// A x = b with x₀ fixed at 0: the rest solve the reduced system (x₁ = 0.3, x₂ = −0.2
    /// by hand); an unknown no equation reaches stays 0.
    #[test]
    fn fixed_unknowns_stay_at_zero_and_the_rest_solve() {
        // Equations 2x₁ + x₂ = 0.4, x₁ + 3x₂ = −0.3 (and anything in row and column 0).
        let a = vec![
            vec![5.0, 1.0, 2.0, 0.0],
            vec![1.0, 2.0, 1.0, 0.0],
            vec![2.0, 1.0, 3.0, 0.0],
            vec![0.0, 0.0, 0.0, 0.0],
        ];
        let x = solve_fixed(a, vec![9.0, 0.4, -0.3, 0.0], &[true, false, false, false]);
        let want = [0.0, 0.3, -0.2, 0.0];
        for (g, w) in x.iter().zip(want) {
            assert!((g - w).abs() < 1e-12, "{x:?}");
        }
    }

    /// Two Suns over the synthetic scene (256², seed 10), the second image's gain drifting
    /// along its lines (the rows) by exp(τ·(row − 127.5)/1000), τ = 0.2 (±2.5 % over the
    /// scene): the first observation is the reference (no trend), the second's τ comes back
    /// within 0.01 from the input DEM; with no drift written, |τ| stays under 0.01.
    #[test]
    fn a_gain_drifting_along_the_track_comes_back() {
        use crate::synth::{generate, SceneSpec};
        let spec = SceneSpec {
            size: 256,
            seed: 10,
            ..SceneSpec::default()
        }
        .with_observations(&[(105.0, 30.0), (225.0, 35.0)], &[], false);
        let plain = generate(&spec);
        let lines = Array2::from_shape_fn((256, 256), |(i, _)| i as f32);
        let trend = |tau: f64| {
            let mut sc = plain.clone();
            for (i, mut row) in sc.more[0].image.rows_mut().into_iter().enumerate() {
                let f = (tau * (i as f64 - 127.5) / 1000.0).exp();
                row.mapv_inplace(|v| v * f);
            }
            let pr = sc.problem();
            let scale = sc.image.mean().unwrap();
            let w = weights(&pr, vec![1.0; 2], scale, None, 0.1, 0.0, (1.0, 1.0));
            let g = estimate_gains(&pr, &w.usable, pr.dem);
            estimate_gain_trends(
                &pr,
                &w.usable,
                pr.dem,
                (&g.gains, &g.relative_to),
                &[lines.view(), lines.view()],
            )
        };
        let t = trend(0.2);
        assert!(t[0].is_none(), "{t:?}");
        let t1 = t[1].expect("the second observation's trend");
        assert!((t1.per_1000_lines - 0.2).abs() < 0.01, "{t1:?}");
        assert!((t1.line - 127.5).abs() < 5.0 && t1.lines[0] < 5.0 && t1.lines[1] > 250.0);
        let none = trend(0.0)[1].expect("estimated");
        assert!(none.per_1000_lines.abs() < 0.01, "{none:?}");
    }

    #[test]
    fn pair_least_squares_recovers_log_gains_with_a_reference_per_group() {
        // Group {0, 1, 2}: δ1 = 0.1, δ2 = −0.05, consistent pairs. Group {3, 4}: δ4 − δ3 = 0.2.
        let pairs = [
            (0, 1, 0.1, 100.0),
            (1, 2, -0.15, 50.0),
            (0, 2, -0.05, 80.0),
            (3, 4, 0.2, 60.0),
        ];
        let d = solve_pairs(6, &pairs);
        let want = [0.0, 0.1, -0.05, 0.0, 0.2, 0.0];
        for (g, w) in d.iter().zip(want) {
            assert!((g - w).abs() < 1e-9, "{d:?}");
        }
        // The groups' roots: their lowest index; observation 5 is alone.
        assert_eq!(group_roots(6, &pairs), [0, 0, 0, 3, 3, 5]);
    }
}
