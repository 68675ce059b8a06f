//! Sanity figures for runs on real data, where no truth is known: does the fused DEM explain
//! the image better than the input DEM did, and did the DEM change only where the image
//! constrains it? Sums are gathered per tile over its core ([`TileSums::of_tile`]), added over
//! the tiles, and turned into [`Sanity`] once per run. Pure: no I/O.
//!
//! * Correlation: Pearson's r between the observed image I and the image R rendered with the
//!   final albedo from the input DEM and from the fused DEM, over photometric pixels.
//! * Change: RMS and max of dem − input_dem on the image's footprint (I has a value), in the
//!   transition band around it (off the footprint, support s > 0) and beyond it (s = 0, where
//!   the product must be the input DEM).

use crate::fusion::{self, Fusion, Problem};
use ndarray::{s, Array2};
use serde::{Deserialize, Serialize};

/// Additive sums over a set of pixels.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Sums {
    pub pixels: usize,
    /// Pixels that carried photometric information (per observation: its own).
    pub photometric: usize,
    /// (count, Σ(dem − input)², max |dem − input|) on the footprint, in the band, beyond.
    pub change: [(usize, f64, f64); 3],
    /// Over photometric pixels: n, ΣI, ΣI², then ΣR, ΣR², ΣIR for the rendering from the input
    /// DEM and from the fused DEM.
    pub corr: [f64; 9],
}

impl Sums {
    /// One pixel's change: `class` 0 footprint, 1 band, 2 beyond; `dz` = dem − input.
    fn pixel(&mut self, class: usize, dz: f64) {
        self.pixels += 1;
        let c = &mut self.change[class];
        *c = (c.0 + 1, c.1 + dz * dz, c.2.max(dz.abs()));
    }

    /// One photometric pair: the observed value and both rendered values.
    fn photo(&mut self, (i, a, b): (f64, f64, f64)) {
        for (acc, v) in self
            .corr
            .iter_mut()
            .zip([1.0, i, i * i, a, a * a, i * a, b, b * b, i * b])
        {
            *acc += v;
        }
    }

    pub fn add(&mut self, o: &Sums) {
        self.pixels += o.pixels;
        self.photometric += o.photometric;
        for (a, b) in self.change.iter_mut().zip(&o.change) {
            *a = (a.0 + b.0, a.1 + b.1, a.2.max(b.2));
        }
        for (a, b) in self.corr.iter_mut().zip(&o.corr) {
            *a += b;
        }
    }

    /// Pearson's r of I with the rendering from the input DEM (`k` = 0) or the fused DEM (1).
    fn correlation(&self, k: usize) -> f64 {
        let c = &self.corr;
        let (n, sx, sxx) = (c[0], c[1], c[2]);
        let (sy, syy, sxy) = (c[3 + 3 * k], c[4 + 3 * k], c[5 + 3 * k]);
        let vx = sxx - sx * sx / n;
        let vy = syy - sy * sy / n;
        if n < 2.0 || vx <= 0.0 || vy <= 0.0 {
            f64::NAN
        } else {
            (sxy - sx * sy / n) / (vx * vy).sqrt()
        }
    }

    /// (RMS, max) of the change in `class`; NaN RMS without pixels.
    fn change(&self, class: usize) -> (f64, f64) {
        let (n, ss, max) = self.change[class];
        let rms = if n == 0 {
            f64::NAN
        } else {
            (ss / n as f64).sqrt()
        };
        (rms, max)
    }
}

/// Rows of a tile's core rendered at a time for its sums (two bands of this many rows are in
/// memory, not two renderings of the whole core).
const RENDER_ROWS: usize = 64;

/// A tile's sums: over every core pixel, and per observation over the pixels whose image it
/// supplied.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TileSums {
    pub all: Sums,
    pub observations: Vec<Sums>,
    /// Core pixels where two or more observations were used; of those the ones where their
    /// Suns are alike, within 5° of one another ([`fusion::observations::suns_alike`]), and
    /// of the others the ones where they measure east–west slopes hardly at all free of
    /// albedo ([`fusion::observations::east_west_share`] below sin²(20°)).
    #[serde(default)]
    pub overlap: usize,
    #[serde(default)]
    pub overlap_alike_suns: usize,
    #[serde(default)]
    pub overlap_east_west_blind: usize,
}

impl TileSums {
    /// A tile without any image: every core pixel is beyond the band and unchanged.
    pub fn no_image(pixels: usize, observations: usize) -> TileSums {
        let mut all = Sums {
            pixels,
            ..Sums::default()
        };
        all.change[2].0 = pixels;
        TileSums {
            all,
            observations: vec![Sums::default(); observations],
            ..TileSums::default()
        }
    }

    /// Sums over the window `core` = (r0, r1, c0, c1) of a tile solved on its whole extent:
    /// `fused` the heights written, `ids[k]` the run's index of the problem's observation k.
    /// The run's sums count each pixel's change once and pool the (I_k/g_k, R_k) pairs of
    /// every observation used there; an observation's sums cover its own footprint.
    pub fn of_tile(
        problem: &Problem,
        f: &Fusion,
        fused: &Array2<f64>,
        ids: &[usize],
        observations: usize,
        core: (usize, usize, usize, usize),
    ) -> TileSums {
        let (r0, r1, c0, c1) = core;
        let cut = s![r0..r1, c0..c1];
        let (support, dem, z) = (
            f.support.slice(cut),
            problem.dem.slice(cut),
            fused.slice(cut),
        );
        let mut out = TileSums {
            all: Sums::default(),
            observations: vec![Sums::default(); observations],
            ..TileSums::default()
        };
        let blind = fusion::observations::EAST_WEST_BLIND_DEG
            .to_radians()
            .sin()
            .powi(2);
        let mut suns = Vec::with_capacity(problem.observations.len());
        for i in r0..r1 {
            for j in c0..c1 {
                // The fusion's count of the observations it used here.
                if f.observations[(i, j)] < 2 {
                    continue;
                }
                suns.clear();
                for (o, used) in problem.observations.iter().zip(&f.used_by) {
                    if used[(i, j)] {
                        suns.push(o.sun.at(i, j));
                    }
                }
                out.overlap += 1;
                if fusion::observations::suns_alike(&suns) {
                    out.overlap_alike_suns += 1;
                    continue;
                }
                let share = fusion::observations::east_west_share(&suns);
                out.overlap_east_west_blind += share.is_none_or(|s| s < blind) as usize;
            }
        }
        let seen = problem.footprint().slice_move(cut);
        for ((i, j), &d) in dem.indexed_iter() {
            let class = if seen[(i, j)] {
                0
            } else if support[(i, j)] > 0.0 {
                1
            } else {
                2
            };
            out.all.pixel(class, z[(i, j)] - d);
            out.all.photometric += f.photometric[(r0 + i, c0 + j)] as usize;
        }
        drop(seen);
        for (k, o) in problem.observations.iter().enumerate() {
            let g = f.gains[k];
            let image = o.image.slice(cut);
            let used = f.used_by[k].slice(cut);
            let mut own = ids
                .get(k)
                .filter(|&&id| id < observations)
                .map(|&id| &mut out.observations[id]);
            // The renderings from the input and the fused DEM, a band of rows at a time (the
            // sums still taken pixel by pixel in row order).
            for b0 in (0..r1 - r0).step_by(RENDER_ROWS) {
                let b1 = (b0 + RENDER_ROWS).min(r1 - r0);
                let band = (r0 + b0, r0 + b1, c0, c1);
                let rendered_in = fusion::render(problem, k, problem.dem, f.albedo.view(), band);
                let rendered_out = fusion::render(problem, k, fused.view(), f.albedo.view(), band);
                for i in b0..b1 {
                    for j in 0..c1 - c0 {
                        let v = image[(i, j)];
                        if !v.is_finite() {
                            continue;
                        }
                        let ph = used[(i, j)]
                            .then(|| (v / g, rendered_in[(i - b0, j)], rendered_out[(i - b0, j)]));
                        if let Some(own) = own.as_deref_mut() {
                            own.pixel(0, z[(i, j)] - dem[(i, j)]);
                            if let Some(ph) = ph {
                                own.photometric += 1;
                                own.photo(ph);
                            }
                        }
                        if let Some(ph) = ph {
                            out.all.photo(ph);
                        }
                    }
                }
            }
        }
        out
    }

    pub fn add(&mut self, o: &TileSums) {
        self.all.add(&o.all);
        self.overlap += o.overlap;
        self.overlap_alike_suns += o.overlap_alike_suns;
        self.overlap_east_west_blind += o.overlap_east_west_blind;
        if self.observations.len() < o.observations.len() {
            self.observations
                .resize(o.observations.len(), Sums::default());
        }
        for (a, b) in self.observations.iter_mut().zip(&o.observations) {
            a.add(b);
        }
    }
}

/// One observation's figures, over the pixels whose image it supplied.
#[derive(Debug, Clone, Serialize)]
pub struct ObservationSanity {
    pub label: String,
    pub footprint_pixels: usize,
    /// Photometric pixels over the observation's footprint.
    pub photometric_fraction: f64,
    pub correlation_input_dem: f64,
    pub correlation_fused_dem: f64,
    pub change_footprint_rms_m: f64,
    pub change_footprint_max_m: f64,
    /// Whether the plan's survey found pixels of its swath on the grid, usable or not (dark,
    /// refused). Its footprint counts only the tiles where some observation was used: where
    /// the incidence window or the shadows leave none, a tile is not fused and counts nothing.
    pub reaches_region: bool,
}

/// What part an observation had in a run, from its figures: the one distinction the
/// warnings, the run record's `gain_source` and the gain groups all draw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Usage {
    /// Its footprint misses the region (the survey found no pixel of its swath on the grid).
    OffRegion,
    /// It covers the region, but no pixel of it was used (shadow, refused radiance, incidence
    /// limits, the per-pixel maximum).
    Unused,
    /// It carried photometric information somewhere.
    Used,
}

impl ObservationSanity {
    /// [`Usage`] from the survey's reach, the footprint and the photometric fraction.
    pub fn usage(&self) -> Usage {
        if self.footprint_pixels == 0 && !self.reaches_region {
            Usage::OffRegion
        } else if self.photometric_fraction == 0.0 {
            Usage::Unused
        } else {
            Usage::Used
        }
    }
}

/// The run's figures (see the module documentation).
#[derive(Debug, Clone, Serialize)]
pub struct Sanity {
    /// Photometric pixels over all pixels of the region.
    pub photometric_fraction: f64,
    pub correlation_input_dem: f64,
    pub correlation_fused_dem: f64,
    pub change_footprint_rms_m: f64,
    pub change_footprint_max_m: f64,
    pub change_band_rms_m: f64,
    pub change_band_max_m: f64,
    pub change_beyond_rms_m: f64,
    pub change_beyond_max_m: f64,
    pub observations: Vec<ObservationSanity>,
    /// Pixels where two or more observations were used, and the shares of them where their
    /// Suns are alike and where, not alike, they measure east–west slopes hardly at all free
    /// of albedo ([`TileSums::overlap`]).
    pub overlap_pixels: usize,
    pub overlap_alike_suns_fraction: f64,
    pub overlap_east_west_blind_fraction: f64,
    pub warnings: Vec<String>,
}

/// How much lower the fused rendering's correlation may be before it is called worse (a
/// rounding-level difference is not a finding).
pub const CORRELATION_TOLERANCE: f64 = 1e-3;

/// A rendering that correlates worse with the image after fusion than before.
fn worse(label: &str, before: f64, after: f64) -> Option<String> {
    (after < before - CORRELATION_TOLERANCE).then(|| format!(
        "{label}: the fused DEM explains the image worse than the input DEM (rendered-image correlation {after:.3} < {before:.3}): check the photometric model, the wavelength and the observation's geometry"
    ))
}

impl Sanity {
    /// The figures from the run's sums; `labels` names the observations in input order and
    /// `reached` says which the plan's survey found pixels of on the grid.
    pub fn from_sums(s: &TileSums, labels: &[String], reached: &[bool]) -> Sanity {
        let a = &s.all;
        let ((f_rms, f_max), (b_rms, b_max), (o_rms, o_max)) =
            (a.change(0), a.change(1), a.change(2));
        let observations: Vec<ObservationSanity> = labels
            .iter()
            .zip(
                s.observations
                    .iter()
                    .chain(std::iter::repeat(&Sums::default())),
            )
            .zip(reached.iter().chain(std::iter::repeat(&false)))
            .map(|((label, o), &reaches_region)| {
                let (rms, max) = o.change(0);
                ObservationSanity {
                    label: label.clone(),
                    footprint_pixels: o.change[0].0,
                    photometric_fraction: o.photometric as f64 / o.change[0].0.max(1) as f64,
                    correlation_input_dem: o.correlation(0),
                    correlation_fused_dem: o.correlation(1),
                    change_footprint_rms_m: rms,
                    change_footprint_max_m: max,
                    reaches_region,
                }
            })
            .collect();
        let mut warnings: Vec<String> = std::iter::once(worse(
            "all observations",
            a.correlation(0),
            a.correlation(1),
        ))
        .chain(
            observations
                .iter()
                .map(|o| worse(&o.label, o.correlation_input_dem, o.correlation_fused_dem)),
        )
        .flatten()
        .collect();
        for o in &observations {
            match o.usage() {
                Usage::OffRegion => warnings.push(format!(
                    "{}: the observation does not reach the region and was not used: check [inputs] m3 and [region]",
                    o.label
                )),
                Usage::Unused => warnings.push(format!(
                    "{}: the observation {} but none was used (all in shadow or refused as radiance, outside [inputs] min_incidence_deg … max_incidence_deg, or beyond max_observations_per_pixel)",
                    o.label,
                    if o.footprint_pixels > 0 {
                        format!("covers {} px of the region", o.footprint_pixels)
                    } else {
                        "reaches the region".to_string()
                    }
                )),
                Usage::Used => {}
            }
        }
        let share = |n: usize| n as f64 / s.overlap.max(1) as f64;
        let (alike, blind) = (
            share(s.overlap_alike_suns),
            share(s.overlap_east_west_blind),
        );
        let overlap_warnings = [
            (
                alike,
                format!(
                    "their Suns lie within {}° of one another: there the images brighten and darken alike under any slope, as under an albedo change, so they measure no slope free of albedo and the overlap gains only by averaging their noise (docs/science.md, \"Where two Suns fall short of 0.65×\"); an observation under a Sun from another direction would measure the slopes",
                    fusion::observations::ALIKE_SUNS_DEG
                ),
            ),
            (
                blind,
                format!(
                    "the images measure slope free of albedo only within {}° of north–south (as two Suns do whose azimuths' bisector lies that close to east or west): an east–west slope brightens or darkens them alike, as an albedo change does, so there east–west slopes come from the DEM rather than the images and the overlap gains less than under other Suns (docs/science.md, \"Where two Suns fall short of 0.65×\"); a further observation under a Sun from another quarter would measure them",
                    fusion::observations::EAST_WEST_BLIND_DEG
                ),
            ),
        ];
        for (fraction, what) in overlap_warnings {
            if s.overlap > 0 && fraction > 0.5 {
                warnings.push(format!(
                    "on {:.0} % of the {} px where observations overlap, {what}",
                    100.0 * fraction,
                    s.overlap
                ));
            }
        }
        if a.change[2].0 > 0 && o_max > 1e-3 {
            warnings.push(format!(
                "the DEM changed beyond the transition band around the image (max {o_max:.3} m): it should be the input DEM there"
            ));
        }
        Sanity {
            photometric_fraction: a.photometric as f64 / a.pixels.max(1) as f64,
            correlation_input_dem: a.correlation(0),
            correlation_fused_dem: a.correlation(1),
            change_footprint_rms_m: f_rms,
            change_footprint_max_m: f_max,
            change_band_rms_m: b_rms,
            change_band_max_m: b_max,
            change_beyond_rms_m: o_rms,
            change_beyond_max_m: o_max,
            observations,
            overlap_pixels: s.overlap,
            overlap_alike_suns_fraction: alike,
            overlap_east_west_blind_fraction: blind,
            warnings,
        }
    }

    /// Lines for the terminal ("—" where a class has no pixel).
    pub fn table(&self) -> String {
        let m = |rms: f64, max: f64, digits: usize| {
            if rms.is_nan() {
                "— (no pixel)".to_string()
            } else {
                format!("{rms:.digits$} / {max:.digits$} m")
            }
        };
        let mut t = format!(
            "photometric fraction {:.3}\nimage vs rendered: correlation {:.3} from the input DEM, {:.3} from the fused DEM\ndem − input_dem RMS / max: footprint {}, band {}, beyond {}\n",
            self.photometric_fraction,
            self.correlation_input_dem,
            self.correlation_fused_dem,
            m(self.change_footprint_rms_m, self.change_footprint_max_m, 2),
            m(self.change_band_rms_m, self.change_band_max_m, 2),
            m(self.change_beyond_rms_m, self.change_beyond_max_m, 3)
        );
        if self.observations.len() > 1 {
            for o in &self.observations {
                if o.usage() != Usage::Used {
                    t.push_str(&format!(
                        "  {}: {} px (not used)\n",
                        o.label, o.footprint_pixels
                    ));
                    continue;
                }
                t.push_str(&format!(
                    "  {}: {} px, photometric {:.3}, correlation {:.3} → {:.3}, change {:.2} / {:.2} m\n",
                    o.label,
                    o.footprint_pixels,
                    o.photometric_fraction,
                    o.correlation_input_dem,
                    o.correlation_fused_dem,
                    o.change_footprint_rms_m,
                    o.change_footprint_max_m
                ));
            }
        }
        for w in &self.warnings {
            t.push_str(&format!("warning: {w}\n"));
        }
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pearson's r on hand-made pixels: a rendering proportional to the image correlates 1,
    /// its mirror −1; changes land in their classes.
    #[test]
    fn correlation_and_change_by_class() {
        let mut s = Sums::default();
        for (k, i) in [0.1, 0.2, 0.4, 0.3].into_iter().enumerate() {
            s.pixel(k % 2, 3.0 * k as f64);
            s.photometric += 1;
            s.photo((i, 2.0 * i + 1.0, 1.0 - i));
        }
        s.pixel(2, 0.0);
        assert!((s.correlation(0) - 1.0).abs() < 1e-12);
        assert!((s.correlation(1) + 1.0).abs() < 1e-12);
        // Class 0 got changes 0 and 6, class 1 got 3 and 9.
        assert_eq!(s.change(0), ((18.0f64).sqrt(), 6.0));
        assert_eq!(s.change(1), ((45.0f64).sqrt(), 9.0));
        assert_eq!(s.change[2], (1, 0.0, 0.0));
        // One observation with three footprint pixels, two of them photometric.
        let mut o = Sums::default();
        o.pixel(0, 1.0);
        o.photometric += 1;
        o.photo((0.1, 0.3, 0.1));
        o.pixel(0, -2.0);
        o.photometric += 1;
        o.photo((0.2, 0.5, 0.3));
        o.pixel(0, 0.5);
        let mut t = TileSums {
            all: s.clone(),
            observations: vec![o],
            ..TileSums::default()
        };
        t.add(&TileSums::no_image(10, 1));
        assert_eq!(t.all.pixels, 15);
        assert_eq!(t.all.change[2].0, 11);
        let out = Sanity::from_sums(&t, &["A".into()], &[true]);
        let a = &out.observations[0];
        assert_eq!((a.footprint_pixels, a.change_footprint_max_m), (3, 2.0));
        assert!((a.photometric_fraction - 2.0 / 3.0).abs() < 1e-15);
        // Two points correlate perfectly either way: only the run-wide −1 warns.
        assert_eq!(out.warnings.len(), 1, "{:?}", out.warnings);
        // The overlap's shares under Suns alike and east–west blind each warn above one half,
        // summed over tiles, each with its own warning only.
        type Share = (
            fn(&mut TileSums, usize),
            fn(&Sanity) -> f64,
            &'static str,
            &'static str,
        );
        let shares: [Share; 2] = [
            (
                |t, n| t.overlap_east_west_blind = n,
                |s| s.overlap_east_west_blind_fraction,
                "north–south",
                "within 5° of one another",
            ),
            (
                |t, n| t.overlap_alike_suns = n,
                |s| s.overlap_alike_suns_fraction,
                "within 5° of one another",
                "north–south",
            ),
        ];
        for (set, share, says, not) in shares {
            for (a, b, warns) in [(4, 5, false), (5, 5, false), (6, 5, true)] {
                let mut t2 = t.clone();
                for n in [a, b] {
                    let mut tile = TileSums {
                        overlap: 10,
                        ..TileSums::default()
                    };
                    set(&mut tile, n);
                    t2.add(&tile);
                }
                let out = Sanity::from_sums(&t2, &["A".into()], &[true]);
                assert_eq!(out.overlap_pixels, 20);
                assert!((share(&out) - (a + b) as f64 / 20.0).abs() < 1e-15);
                let warned = |text: &str| out.warnings.iter().any(|w| w.contains(text));
                assert_eq!(warned(says), warns, "{:?}", out.warnings);
                assert!(!warned(not), "{:?}", out.warnings);
            }
        }
    }
}
