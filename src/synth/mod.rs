//! A deterministic synthetic lunar scene with known truth, for the demo, the tests and the
//! benchmark (issue: "science core", item 4).
//!
//! * Truth DEM: smooth relief (random long-wavelength waves) plus fresh bowl craters with a
//!   power-law size distribution N(>D) ∝ D⁻², depth/diameter ≈ 0.2, raised rims (0.04·D) and
//!   ejecta decaying as (R/r)³ out to 3R; beyond D = 15 km depth and rim grow as D^0.301
//!   ([`complex_crater_scale`]). Slopes are analytic.
//! * Truth albedo (Hapke w, mean 0.44): dark soft-edged patches, bright ejecta rings around the
//!   larger craters, and a weak fine-scale texture.
//! * Image: Hapke IMSA (lunar parameters) rendered from the analytic slopes under the given
//!   Sun and view, averaged over 3 × 3 subsamples per pixel (a detector integrates over its
//!   footprint), cast shadows by ray marching, plus Gaussian noise of `noise` × the mean lit
//!   reflectance.
//! * Input DEM, LOLA-like: the truth low-passed (Gaussian σ = factor/2), averaged over
//!   factor × factor blocks, plus white noise and along-track (north–south) striping per coarse
//!   column, then resampled bilinearly to the grid.

use crate::fusion::Directions;
use crate::photometry::{Hapke, ReflectanceModel, Vec3};
use crate::rng::Rng;
use crate::spectral::{gaussian_filter, Dct2d};
use ndarray::{s, Array2, Axis, Zip};
use rayon::prelude::*;
use serde::Serialize;

pub mod products;

/// What to generate.
#[derive(Debug, Clone, Serialize)]
pub struct SceneSpec {
    pub size: usize,
    /// Metres per pixel.
    pub spacing: f64,
    pub seed: u64,
    /// Sun incidence (zenith) angle and azimuth (clockwise from north), degrees, at the first
    /// row.
    pub sun_incidence_deg: f64,
    pub sun_azimuth_deg: f64,
    /// How the Sun's azimuth and elevation change, degrees, from the first row to the last
    /// ([`SunPath`]; `[0, 0]`: the same Sun everywhere).
    pub sun_drift_deg: [f64; 2],
    /// Camera zenith and azimuth, degrees.
    pub view_zenith_deg: f64,
    pub view_azimuth_deg: f64,
    /// Image noise σ as a fraction of the mean lit reflectance.
    pub noise: f64,
    /// How many times coarser the input DEM is sampled.
    pub dem_factor: usize,
    /// White noise of the coarse input DEM, metres.
    pub dem_noise_m: f64,
    /// σ of the per-track (coarse column) offsets, metres.
    pub dem_stripe_m: f64,
    /// Smallest crater diameter, pixels.
    pub crater_min_px: f64,
    /// Craters per megapixel.
    pub crater_density: f64,
    /// Columns `[first, end)` the first observation covers (`None`: all); NaN elsewhere.
    pub columns: Option<[usize; 2]>,
    /// Further observations of the same surface, each with its own Sun, gain, coverage and
    /// independent noise (same view and noise level).
    pub more: Vec<ShotSpec>,
}

/// One further observation of a scene.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShotSpec {
    pub sun_incidence_deg: f64,
    pub sun_azimuth_deg: f64,
    /// How its Sun's azimuth and elevation change from the first row to the last, degrees.
    pub sun_drift_deg: [f64; 2],
    /// Radiometric gain: the image is g × the rendered reflectance (detector and calibration
    /// differences between observations).
    pub gain: f64,
    /// Columns `[first, end)` it covers (`None`: all).
    pub columns: Option<[usize; 2]>,
}

/// One further observation of a scene, rendered.
#[derive(Debug, Clone)]
pub struct Shot {
    pub spec: ShotSpec,
    /// g × reflectance (sr⁻¹) with noise; NaN outside its columns.
    pub image: Array2<f64>,
    pub shadow: Array2<bool>,
    pub sun: SunPath,
}

impl Default for SceneSpec {
    /// The demo scene: 512² at 140 m/px (the seed's M3 resolution), Sun 60° from zenith in the
    /// east-south-east, near-nadir view, 1 % noise, input DEM 4× coarser.
    fn default() -> Self {
        Self {
            size: 512,
            spacing: 140.0,
            seed: 1,
            sun_incidence_deg: 60.0,
            sun_azimuth_deg: 105.0,
            sun_drift_deg: [0.0, 0.0],
            view_zenith_deg: 3.0,
            view_azimuth_deg: 250.0,
            noise: 0.01,
            dem_factor: 4,
            dem_noise_m: 3.0,
            dem_stripe_m: 4.0,
            crater_min_px: 4.0,
            crater_density: 1500.0,
            columns: None,
            more: Vec::new(),
        }
    }
}

/// Sun directions (azimuth clockwise from north, elevation above the horizon; degrees) of
/// the demo's observations, in order: the first is the single-image demo's, the second ≥ 90°
/// away in azimuth, the third ≥ 90° from both.
pub const DEMO_SUNS: [(f64, f64); 6] = [
    (105.0, 30.0),
    (225.0, 35.0),
    (345.0, 25.0),
    (45.0, 28.0),
    (165.0, 32.0),
    (285.0, 27.0),
];

/// Parse a Sun direction `AZ/EL` (degrees: azimuth clockwise from north, elevation above the
/// horizon), as `sfsfuse synth --sun` takes it.
pub fn parse_sun(text: &str) -> Result<(f64, f64), String> {
    let (a, e) = parse_pair(text).ok_or_else(|| {
        format!("--sun {text}: expected AZIMUTH/ELEVATION in degrees, e.g. 110/55")
    })?;
    if !(a.is_finite() && (0.0..=360.0).contains(&a)) {
        return Err(format!("--sun {text}: azimuth {a} must be in [0, 360]"));
    }
    if !(e > 0.0 && e <= 90.0) {
        return Err(format!(
            "--sun {text}: elevation {e} must be above the horizon (0 < elevation ≤ 90)"
        ));
    }
    Ok((a, e))
}

/// `--sun-drift` ΔAZ/ΔEL: how far a Sun moves along a strip, degrees, each finite (the
/// range is checked against the Sun it moves, [`SceneSpec::with_sun_drifts`]).
pub fn parse_sun_drift(text: &str) -> Result<[f64; 2], String> {
    match parse_pair(text) {
        Some((a, e)) if a.is_finite() && e.is_finite() => Ok([a, e]),
        _ => Err(format!(
            "--sun-drift {text}: expected ΔAZIMUTH/ΔELEVATION in degrees, e.g. 0/15"
        )),
    }
}

/// `--loc-offset` and `--loc-drift` EAST/NORTH: a selenolocation error in metres, each finite and within
/// 100 km.
pub fn parse_offset(text: &str) -> Result<[f64; 2], String> {
    let (e, n) = parse_pair(text)
        .ok_or_else(|| format!("{text}: expected EAST/NORTH in metres, e.g. 150/-150"))?;
    if !(e.is_finite() && n.is_finite() && e.abs() <= 1e5 && n.abs() <= 1e5) {
        return Err(format!(
            "{text}: each of east and north must be a number of metres within 100 km"
        ));
    }
    Ok([e, n])
}

/// `A/B`: two numbers separated by a slash (spaces around them allowed); `None` otherwise.
pub fn parse_pair(text: &str) -> Option<(f64, f64)> {
    let (a, b) = text.split_once('/')?;
    Some((a.trim().parse().ok()?, b.trim().parse().ok()?))
}

impl SceneSpec {
    /// This scene seen under several Suns (azimuth, elevation; the first replaces the spec's
    /// own), with gains (missing ones are 1). With `strips`, observation k covers only the
    /// k-th of a row of equal column strips that overlap their neighbours by half a strip
    /// (two strips: [0, ⅔n) and [⅓n, n)).
    pub fn with_observations(mut self, suns: &[(f64, f64)], gains: &[f64], strips: bool) -> Self {
        let n = self.size;
        let k = suns.len().max(1);
        let strip = |i: usize| -> Option<[usize; 2]> {
            if !strips || k == 1 {
                return None;
            }
            // Width w with (k + 1)·w/2 = n; strip i starts at i·w/2.
            let w = 2.0 * n as f64 / (k as f64 + 1.0);
            let a = (i as f64 * w / 2.0).round() as usize;
            let b = ((i as f64 * w / 2.0 + w).round() as usize).min(n);
            Some([a, b])
        };
        if let Some(&(az, el)) = suns.first() {
            self.sun_azimuth_deg = az;
            self.sun_incidence_deg = 90.0 - el;
        }
        self.columns = strip(0);
        self.more = suns
            .iter()
            .enumerate()
            .skip(1)
            .map(|(i, &(az, el))| ShotSpec {
                sun_incidence_deg: 90.0 - el,
                sun_azimuth_deg: az,
                sun_drift_deg: [0.0, 0.0],
                gain: gains.get(i).copied().unwrap_or(1.0),
                columns: strip(i),
            })
            .collect();
        self
    }

    /// The first observation's Sun over the scene.
    pub fn sun_path(&self) -> SunPath {
        SunPath {
            azimuth_deg: self.sun_azimuth_deg,
            zenith_deg: self.sun_incidence_deg,
            drift_deg: self.sun_drift_deg,
        }
    }

    /// The Suns of its observations moving along the rows (in observation order; missing ones
    /// do not move): Δazimuth and Δelevation, degrees, from the first row to the last
    /// ([`SunPath`]). Refused, naming the observation, where a Sun would end at or below the
    /// horizon or past the zenith, or turn by more than 180° in azimuth.
    pub fn with_sun_drifts(mut self, drifts: &[[f64; 2]]) -> Result<Self, String> {
        for (k, &d) in drifts.iter().enumerate() {
            let path = match k {
                0 => self.sun_path(),
                _ => match self.more.get(k - 1) {
                    Some(m) => m.sun_path(),
                    None => {
                        return Err(format!(
                            "--sun-drift {}/{}: observation {} has no --sun",
                            d[0],
                            d[1],
                            k + 1
                        ))
                    }
                },
            };
            let end = 90.0 - path.zenith_deg + d[1];
            if !(d[0].is_finite() && d[0].abs() <= 180.0 && end > 0.0 && end <= 90.0) {
                return Err(format!(
                    "--sun-drift {}/{}: observation {}'s Sun at {}/{} would end at {}/{}: the azimuth may turn by at most 180° and the elevation must stay above the horizon (0 < elevation ≤ 90)",
                    d[0],
                    d[1],
                    k + 1,
                    path.azimuth_deg,
                    90.0 - path.zenith_deg,
                    (path.azimuth_deg + d[0]).rem_euclid(360.0),
                    end
                ));
            }
            match k {
                0 => self.sun_drift_deg = d,
                _ => self.more[k - 1].sun_drift_deg = d,
            }
        }
        Ok(self)
    }
}

/// A generated scene.
#[derive(Debug, Clone)]
pub struct Scene {
    pub spec: SceneSpec,
    pub truth_height: Array2<f64>,
    pub truth_albedo: Array2<f64>,
    /// Bidirectional reflectance r (sr⁻¹) with noise; 0 + noise in cast shadow.
    pub image: Array2<f64>,
    /// True where the truth surface is in cast or self shadow.
    pub shadow: Array2<bool>,
    pub input_dem: Array2<f64>,
    pub sun: SunPath,
    pub view: Vec3,
    pub model: Hapke,
    /// The further observations of `spec.more`.
    pub more: Vec<Shot>,
}

/// Unit vector in east-north-up from zenith and azimuth (clockwise from north), degrees: docs/formats.md's
/// (sin z·sin az, sin z·cos az, cos z).
pub fn direction(zenith_deg: f64, azimuth_deg: f64) -> Vec3 {
    let (z, a) = (zenith_deg.to_radians(), azimuth_deg.to_radians());
    [z.sin() * a.sin(), z.sin() * a.cos(), z.cos()]
}

/// The Sun of one observation over a scene: azimuth (clockwise from north) and zenith angle,
/// degrees, at the first grid row, the azimuth and the elevation changing in proportion to the
/// row by `drift_deg` = [Δazimuth, Δelevation] at the last. Over a strip whose track runs north–south, as M3's polar orbit's did, the Sun
/// moves so as the local time and latitude change along it (`sfsfuse synth --sun-drift`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SunPath {
    pub azimuth_deg: f64,
    pub zenith_deg: f64,
    pub drift_deg: [f64; 2],
}

impl SunPath {
    /// The Sun over row `row` (fractional) of `rows`: azimuth + t·Δazimuth and
    /// zenith − t·Δelevation, t = row/(rows − 1), as a unit east-north-up vector
    /// ([`direction`]; a Sun that does not move is exactly `direction(zenith, azimuth)` on
    /// every row).
    pub fn at_row(&self, row: f64, rows: usize) -> Vec3 {
        let t = if rows > 1 {
            row / (rows - 1) as f64
        } else {
            0.0
        };
        let [da, de] = self.drift_deg;
        direction(self.zenith_deg - t * de, self.azimuth_deg + t * da)
    }

    /// Whether the Sun is the same over every row.
    pub fn is_uniform(&self) -> bool {
        self.drift_deg == [0.0, 0.0]
    }

    /// The Sun at each pixel of a `rows` × `cols` grid, as the fusion takes it: one vector
    /// when it does not change, one per pixel (f32) when it does.
    pub fn directions<'a>(&self, rows: usize, cols: usize) -> Directions<'a> {
        if self.is_uniform() {
            return Directions::Uniform(self.at_row(0.0, rows));
        }
        let per_row: Vec<crate::photometry::Vec3f> = (0..rows)
            .map(|i| self.at_row(i as f64, rows).map(|x| x as f32))
            .collect();
        Directions::PerPixel(Array2::from_shape_fn((rows, cols), |(i, _)| per_row[i]).into())
    }
}

impl ShotSpec {
    /// This observation's Sun over the scene.
    pub fn sun_path(&self) -> SunPath {
        SunPath {
            azimuth_deg: self.sun_azimuth_deg,
            zenith_deg: self.sun_incidence_deg,
            drift_deg: self.sun_drift_deg,
        }
    }
}

struct Crater {
    x: f64,
    y: f64,
    r: f64,
    depth: f64,
    rim: f64,
}

impl Crater {
    /// Height and (∂/∂x, ∂/∂y) at offset (dx, dy) from the centre, metres.
    fn eval(&self, dx: f64, dy: f64) -> (f64, f64, f64) {
        let r = (dx * dx + dy * dy).sqrt();
        let (h, dh) = if r <= self.r {
            let u = r / self.r;
            (
                self.rim + self.depth * (u * u - 1.0),
                2.0 * self.depth * r / (self.r * self.r),
            )
        } else if r < 3.0 * self.r {
            let k = 1.0 / (1.0 - 1.0 / 27.0);
            let c = self.r / r;
            (
                self.rim * k * (c * c * c - 1.0 / 27.0),
                -3.0 * self.rim * k * c * c * c / r,
            )
        } else {
            return (0.0, 0.0, 0.0);
        };
        if r == 0.0 {
            return (h, 0.0, 0.0);
        }
        (h, dh * dx / r, dh * dy / r)
    }
}

struct Wave {
    kx: f64,
    ky: f64,
    phase: f64,
    amp: f64,
}

/// Subsamples per pixel and axis used to render the image.
const SUB: usize = 3;

/// Diameter, metres, of the Moon's simple-to-complex crater transition (Pike 1977: ≈ 15 km).
pub const COMPLEX_CRATER_M: f64 = 15e3;

/// Factor on the depth and rim height of a crater of diameter `d` metres: 1 up to
/// [`COMPLEX_CRATER_M`]; beyond, depth grows as D^0.301 rather than in proportion (Pike 1977,
/// complex lunar craters), continuous at the transition. A 229 km crater (the largest in an
/// 8192² scene) is then 6.9 km deep, not 46 km. Scenes under 536 px at 140 m hold no crater
/// that wide, so they are unchanged.
pub fn complex_crater_scale(d: f64) -> f64 {
    if d <= COMPLEX_CRATER_M {
        1.0
    } else {
        (d / COMPLEX_CRATER_M).powf(0.301 - 1.0)
    }
}

/// Generate the scene for `spec`. One random stream draws, in this order, the relief's
/// waves, the craters, the albedo's patches and texture, the first observation's noise and
/// the input DEM's errors; each further observation's noise has a stream of its own.
pub fn generate(spec: &SceneSpec) -> Scene {
    let n = spec.size;
    let mut rng = Rng::new(spec.seed);
    let waves = relief_waves(&mut rng);
    let craters = craters(spec, &mut rng);
    let dct = Dct2d::new(n, n);
    let albedo = albedo(spec, &craters, &dct, &mut rng);
    let (height, px, py) = subsampled_relief(spec, &waves, &craters);
    let h_sub = spec.spacing / SUB as f64;

    // Rendering: each pixel averages the radiance of its SUB × SUB subsamples, as a detector
    // integrates over its footprint; the albedo is constant over a pixel.
    let model = Hapke::moon();
    let sun = spec.sun_path();
    let view = direction(spec.view_zenith_deg, spec.view_azimuth_deg);
    let surface = Subsampled {
        height: &height,
        px: &px,
        py: &py,
        albedo: &albedo,
        h_sub,
    };
    let (mut image, shadow) = surface.render(&model, &sun, &view, spec.noise, &mut rng);
    mask_columns(&mut image, spec.columns);
    let more = spec
        .more
        .iter()
        .enumerate()
        .map(|(k, m)| {
            // Each further observation's noise comes from its own stream, so the first
            // observation and the input DEM do not depend on how many there are.
            let mut rng =
                Rng::new(spec.seed ^ (0x9E37_79B9_7F4A_7C15u64.wrapping_mul(k as u64 + 1)));
            let sun = m.sun_path();
            let (mut image, shadow) = surface.render(&model, &sun, &view, spec.noise, &mut rng);
            image.mapv_inplace(|r| r * m.gain);
            mask_columns(&mut image, m.columns);
            Shot {
                spec: m.clone(),
                image,
                shadow,
                sun,
            }
        })
        .collect();
    let truth = Array2::from_shape_fn((n, n), |(i, j)| {
        height[(i * SUB + SUB / 2, j * SUB + SUB / 2)]
    });
    // The subsampled surface (SUB² × 24 bytes per pixel) is not needed beyond this point.
    drop((height, px, py));
    let height = truth;

    let input_dem = lola_like(&height, spec, &dct, &mut rng);
    Scene {
        spec: spec.clone(),
        truth_height: height,
        truth_albedo: albedo,
        image,
        shadow,
        input_dem,
        sun,
        view,
        model,
        more,
    }
}

/// The smooth relief: eight plane waves with wavelengths of 25–120 km and random directions
/// and phases, a few hundred metres in all (amplitude 40–120 m per 60 km of wavelength).
fn relief_waves(rng: &mut Rng) -> Vec<Wave> {
    (0..8)
        .map(|_| {
            let lambda = rng.range(25e3, 120e3);
            let th = rng.range(0.0, std::f64::consts::TAU);
            let k = std::f64::consts::TAU / lambda;
            Wave {
                kx: k * th.cos(),
                ky: k * th.sin(),
                phase: rng.range(0.0, std::f64::consts::TAU),
                amp: rng.range(40.0, 120.0) * lambda / 60e3,
            }
        })
        .collect()
}

/// The craters, largest first (so that small ones superpose on them): diameters with
/// N(>D) ∝ D⁻² between `crater_min_px` and n/5 pixels, `crater_density` per 10⁶ px²,
/// depth/diameter 0.17–0.21 and rim height 0.04·D, both scaled beyond the simple-to-complex
/// transition by [`complex_crater_scale`].
fn craters(spec: &SceneSpec, rng: &mut Rng) -> Vec<Crater> {
    let (n, eps) = (spec.size, spec.spacing);
    let extent = n as f64 * eps;
    let (dmin, dmax) = (spec.crater_min_px * eps, (n as f64 / 5.0) * eps);
    let count = (spec.crater_density * (n * n) as f64 / 1e6).round() as usize;
    let mut craters: Vec<Crater> = (0..count)
        .map(|_| {
            let u = rng.uniform();
            // Inverse CDF of the truncated Pareto with exponent 2.
            let d = dmin / (1.0 - u * (1.0 - (dmin / dmax).powi(2))).sqrt();
            let ratio = 0.2 * rng.range(0.85, 1.05);
            let complex = complex_crater_scale(d);
            Crater {
                x: rng.range(0.0, extent),
                y: -rng.range(0.0, extent),
                r: d / 2.0,
                depth: ratio * d * complex,
                rim: 0.04 * d * complex,
            }
        })
        .collect();
    craters.sort_by(|a, b| b.r.total_cmp(&a.r));
    craters
}

/// The albedo: 0.44 on average, darker patches (mare-like, 15–55 px radius, 0.06–0.14 darker,
/// soft edges about 4 px wide), a bright ring (+0.05) around each crater of 6 px or more, and
/// a fine texture (white noise smoothed over 1.5 px, σ = 0.01); clamped to [0.05, 0.95].
fn albedo(spec: &SceneSpec, craters: &[Crater], dct: &Dct2d, rng: &mut Rng) -> Array2<f64> {
    let (n, eps) = (spec.size, spec.spacing);
    let mut albedo = Array2::from_elem((n, n), 0.0);
    let patches: Vec<(f64, f64, f64, f64)> = (0..(n * n / 40000).max(3))
        .map(|_| {
            (
                rng.range(0.0, n as f64),
                rng.range(0.0, n as f64),
                rng.range(15.0, 55.0),
                rng.range(0.06, 0.14),
            )
        })
        .collect();
    let bright: Vec<&Crater> = craters.iter().filter(|c| c.r * 2.0 >= 6.0 * eps).collect();
    // The ring is negligible (< 0.05·e⁻¹⁶) beyond t = 4, i.e. (1 + 4·0.6)·r from the centre.
    let reach = |c: &Crater| c.r * (1.0 + 4.0 * 0.6);
    albedo
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .enumerate()
        .for_each(|(i, mut row)| {
            let fi = i as f64;
            let y = -fi * eps;
            // The bright craters whose rings reach this row, in list order (the sum's order).
            let near: Vec<&Crater> = bright
                .iter()
                .copied()
                .filter(|c| (y - c.y).abs() <= reach(c))
                .collect();
            for (j, w) in row.iter_mut().enumerate() {
                let fj = j as f64;
                for &(ci, cj, rad, amp) in &patches {
                    let d2 = (fi - ci).powi(2) + (fj - cj).powi(2);
                    // Beyond rad + 1424 px, e^((d − rad)/2) overflows to infinity and the term
                    // is exactly 0: skipping it changes no bit.
                    if d2 > (rad + PATCH_ZERO_PX).powi(2) {
                        continue;
                    }
                    let d = d2.sqrt();
                    // Soft edge about 4 px wide.
                    *w -= amp / (1.0 + ((d - rad) / 2.0).exp());
                }
                let x = fj * eps;
                for c in &near {
                    if (x - c.x).abs() > reach(c) {
                        continue;
                    }
                    let d = ((x - c.x).powi(2) + (y - c.y).powi(2)).sqrt();
                    let t = (d - c.r) / (0.6 * c.r);
                    if t.abs() < 4.0 {
                        *w += 0.05 * (-t * t).exp();
                    }
                }
            }
        });
    // Fine texture: white noise smoothed over ~1.5 px, σ ≈ 0.01.
    let white = Array2::from_shape_simple_fn((n, n), || rng.normal());
    let texture = gaussian_filter(dct, &white, 1.5);
    let tstd = (texture.iter().map(|x| x * x).sum::<f64>() / (n * n) as f64).sqrt();
    albedo.zip_mut_with(&texture, |w, t| *w += 0.01 * t / tstd);
    let mean = albedo.mean().unwrap_or(0.0);
    albedo.mapv_inplace(|w| (w - mean + 0.44).clamp(0.05, 0.95));
    albedo
}

/// Height and its analytic slopes (∂z/∂x east, ∂z/∂y north) on a grid SUB times finer than
/// the pixels: subsample (SUB/2, SUB/2) of each pixel is its centre (x = j·ε east,
/// y = −i·ε north). The waves, then the craters row by row in parallel, added within a row in
/// the (size-sorted) list order, so that the sums do not depend on the thread count.
fn subsampled_relief(
    spec: &SceneSpec,
    waves: &[Wave],
    craters: &[Crater],
) -> (Array2<f64>, Array2<f64>, Array2<f64>) {
    let m = spec.size * SUB;
    let h_sub = spec.spacing / SUB as f64;
    let origin = -((SUB / 2) as f64) * h_sub;
    let mut height = Array2::zeros((m, m));
    let mut px = Array2::zeros((m, m));
    let mut py = Array2::zeros((m, m));
    Zip::indexed(&mut height)
        .and(&mut px)
        .and(&mut py)
        .par_for_each(|(i, j), h, gx, gy| {
            let (x, y) = (origin + j as f64 * h_sub, -(origin + i as f64 * h_sub));
            for w in waves {
                let a = w.kx * x + w.ky * y + w.phase;
                *h += w.amp * a.sin();
                *gx += w.amp * w.kx * a.cos();
                *gy += w.amp * w.ky * a.cos();
            }
        });
    height
        .axis_iter_mut(Axis(0))
        .into_par_iter()
        .zip(px.axis_iter_mut(Axis(0)))
        .zip(py.axis_iter_mut(Axis(0)))
        .enumerate()
        .for_each(|(i, ((mut hrow, mut xrow), mut yrow))| {
            let y = -(origin + i as f64 * h_sub);
            for c in craters {
                let reach = 3.0 * c.r;
                if (y - c.y).abs() > reach {
                    continue;
                }
                let j0 = (((c.x - reach - origin) / h_sub).floor().max(0.0) as usize).min(m);
                let j1 = (((c.x + reach - origin) / h_sub).ceil().max(0.0) as usize + 1).min(m);
                for j in j0..j1 {
                    let (h, gx, gy) = c.eval(origin + j as f64 * h_sub - c.x, y - c.y);
                    hrow[j] += h;
                    xrow[j] += gx;
                    yrow[j] += gy;
                }
            }
        });
    (height, px, py)
}

/// NaN outside columns `[first, end)`.
fn mask_columns(image: &mut Array2<f64>, columns: Option<[usize; 2]>) {
    if let Some([a, b]) = columns {
        for ((_, j), v) in image.indexed_iter_mut() {
            if j < a || j >= b {
                *v = f64::NAN;
            }
        }
    }
}

/// The truth surface on the SUB-times finer grid, and the per-pixel albedo.
struct Subsampled<'a> {
    height: &'a Array2<f64>,
    px: &'a Array2<f64>,
    py: &'a Array2<f64>,
    albedo: &'a Array2<f64>,
    h_sub: f64,
}

impl Subsampled<'_> {
    /// The image under `sun` seen from `view` (each pixel the mean of its subsamples, cast
    /// shadows by ray marching; the Sun of the pixel's row over all of them), plus Gaussian
    /// noise of `noise` × the mean lit reflectance; and where more than half a pixel is in
    /// shadow.
    fn render(
        &self,
        model: &Hapke,
        sun: &SunPath,
        view: &Vec3,
        noise: f64,
        rng: &mut Rng,
    ) -> (Array2<f64>, Array2<bool>) {
        let n = self.albedo.nrows();
        let rows: Vec<Vec3> = (0..n).map(|i| sun.at_row(i as f64, n)).collect();
        let cast = cast_shadow(self.height, self.h_sub, &|si| rows[si / SUB]);
        let mut image = Array2::zeros((n, n));
        let mut shadow = Array2::from_elem((n, n), false);
        Zip::indexed(&mut image)
            .and(&mut shadow)
            .par_for_each(|(i, j), r, s| {
                let sun = &rows[i];
                let (mut sum, mut dark) = (0.0, 0);
                for si in i * SUB..(i + 1) * SUB {
                    for sj in j * SUB..(j + 1) * SUB {
                        let sh = model.shade(
                            self.px[(si, sj)],
                            self.py[(si, sj)],
                            self.albedo[(i, j)],
                            sun,
                            view,
                        );
                        if sh.lit && !cast[(si, sj)] {
                            sum += sh.r;
                        } else {
                            dark += 1;
                        }
                    }
                }
                *r = sum / (SUB * SUB) as f64;
                *s = 2 * dark > SUB * SUB;
            });
        let lit: Vec<f64> = image
            .iter()
            .zip(&shadow)
            .filter(|(_, s)| !**s)
            .map(|(r, _)| *r)
            .collect();
        let sigma = noise * lit.iter().sum::<f64>() / lit.len().max(1) as f64;
        image.mapv_inplace(|r| r + sigma * rng.normal());
        (image, shadow)
    }
}

/// Distance beyond a dark patch's radius, in pixels, from which its soft edge
/// amp/(1 + e^((d − rad)/2)) is exactly 0 in f64: e^x overflows to infinity from x ≈ 709.8,
/// and 2·712 leaves a margin for the rounding of d.
const PATCH_ZERO_PX: f64 = 1424.0;

/// Sides, in grid cells and coarsest first, of the blocks whose maxima let a shadow ray skip
/// terrain it clears.
const SHADOW_BLOCKS: [usize; 3] = [64, 16, 4];

/// Cast shadows: march from each pixel towards the Sun of its row (`sun_of_row`) over the
/// bilinearly interpolated DEM, in steps of half a cell, until the terrain rises above the ray
/// (shadow), the ray leaves the grid or rises above the highest point (lit).
///
/// A bilinear sample in cell (i0, j0) mixes the heights at rows i0, i0 + 1 and columns
/// j0, j0 + 1, so it cannot exceed the maximum over the cell's block (of any size in
/// [`SHADOW_BLOCKS`]) and a margin of one row and column beyond it. Where the ray (which only
/// rises, with the Sun above the horizon) is already above the largest such block's maximum,
/// every step inside that block is lit and the march jumps to the last step before the ray
/// leaves the block (one step short of the continuous exit, so that rounding never skips a
/// step outside it): the same steps decide, so the result is the plain march's exactly,
/// without sampling the terrain the ray clears — with kilometre-deep craters the plain march
/// takes thousands of steps per pixel.
fn cast_shadow(
    h: &Array2<f64>,
    eps: f64,
    sun_of_row: &(dyn Fn(usize) -> Vec3 + Sync),
) -> Array2<bool> {
    let (ny, nx) = h.dim();
    let mut out = Array2::from_elem((ny, nx), false);
    let hmax = h.iter().cloned().fold(f64::MIN, f64::max);
    let maxima: Vec<(usize, Array2<f64>)> = SHADOW_BLOCKS
        .iter()
        .map(|&b| {
            let m = Array2::from_shape_fn((ny.div_ceil(b), nx.div_ceil(b)), |(bi, bj)| {
                h.slice(s![
                    bi * b..((bi + 1) * b + 1).min(ny),
                    bj * b..((bj + 1) * b + 1).min(nx)
                ])
                .iter()
                .cloned()
                .fold(f64::MIN, f64::max)
            });
            (b, m)
        })
        .collect();
    let sample = |fi: f64, fj: f64| {
        let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
        let (i1, j1) = ((i0 + 1).min(ny - 1), (j0 + 1).min(nx - 1));
        let (ti, tj) = (fi - i0 as f64, fj - j0 as f64);
        (1.0 - ti) * ((1.0 - tj) * h[(i0, j0)] + tj * h[(i0, j1)])
            + ti * ((1.0 - tj) * h[(i1, j0)] + tj * h[(i1, j1)])
    };
    // The ray parameter at which it leaves the block range [lo, lo + b) along an axis, from
    // `start` moving by `d` per unit (infinite when it does not move along that axis).
    let exit = |start: f64, d: f64, lo: usize, b: usize| {
        if d > 0.0 {
            ((lo + b) as f64 - start) / d
        } else if d < 0.0 {
            (lo as f64 - start) / d
        } else {
            f64::INFINITY
        }
    };
    let step = 0.5;
    Zip::indexed(&mut out).par_for_each(|(i, j), s| {
        let sun = sun_of_row(i);
        let horiz = (sun[0] * sun[0] + sun[1] * sun[1]).sqrt();
        if horiz < 1e-12 {
            return;
        }
        // Metres of ray rise per metre travelled; per pixel step, columns east, rows south.
        let rise = sun[2] / horiz;
        let (dj, di) = (sun[0] / horiz, -sun[1] / horiz);
        // A ray that sinks (the Sun below the horizon) may not skip anything: no blocks.
        let blocks = if rise >= 0.0 { &maxima[..] } else { &[] };
        let h0 = h[(i, j)];
        // t = k·step exactly (multiples of 0.5).
        let mut k: u64 = 1;
        loop {
            let t = k as f64 * step;
            let (fi, fj) = (i as f64 + di * t, j as f64 + dj * t);
            if fi < 0.0 || fj < 0.0 || fi > (ny - 1) as f64 || fj > (nx - 1) as f64 {
                break;
            }
            let ray = h0 + rise * t * eps;
            if ray > hmax {
                break;
            }
            let (ci, cj) = (fi.floor() as usize, fj.floor() as usize);
            let clear = blocks.iter().find(|(b, m)| ray > m[(ci / b, cj / b)]);
            if let Some(&(b, _)) = clear {
                let (lo_i, lo_j) = (ci / b * b, cj / b * b);
                let t_exit = exit(i as f64, di, lo_i, b).min(exit(j as f64, dj, lo_j, b));
                let last_inside = (t_exit / step).floor() - 1.0;
                k = if last_inside > (k + 1) as f64 {
                    last_inside as u64
                } else {
                    k + 1
                };
                continue;
            }
            if sample(fi, fj) > ray {
                *s = true;
                break;
            }
            k += 1;
        }
    });
    out
}

/// The LOLA-like input DEM (see the module documentation).
fn lola_like(truth: &Array2<f64>, spec: &SceneSpec, dct: &Dct2d, rng: &mut Rng) -> Array2<f64> {
    let n = spec.size;
    let f = spec.dem_factor.max(1);
    let smooth = gaussian_filter(dct, truth, f as f64 / 2.0);
    let nc = n.div_ceil(f);
    let stripes: Vec<f64> = (0..nc).map(|_| spec.dem_stripe_m * rng.normal()).collect();
    let mut coarse = Array2::zeros((nc, nc));
    for ((ci, cj), v) in coarse.indexed_iter_mut() {
        let (mut s, mut k) = (0.0, 0);
        for i in ci * f..((ci + 1) * f).min(n) {
            for j in cj * f..((cj + 1) * f).min(n) {
                s += smooth[(i, j)];
                k += 1;
            }
        }
        *v = s / k as f64 + spec.dem_noise_m * rng.normal() + stripes[cj];
    }
    bilinear_from_blocks(&coarse, f, n)
}

/// An n × n grid interpolated bilinearly from `coarse`, whose pixel k stands for the block of
/// fine pixels k·f … k·f + f − 1 and is centred on fine coordinate k·f + (f − 1)/2 (clamped at
/// the edges): how a product f times coarser than the grid is carried onto it.
pub fn bilinear_from_blocks(coarse: &Array2<f64>, f: usize, n: usize) -> Array2<f64> {
    let nc = coarse.nrows();
    let c = |x: f64| ((x - (f as f64 - 1.0) / 2.0) / f as f64).clamp(0.0, (nc - 1) as f64);
    Array2::from_shape_fn((n, n), |(i, j)| {
        let (u, v) = (c(i as f64), c(j as f64));
        let (i0, j0) = (u.floor() as usize, v.floor() as usize);
        let (i1, j1) = ((i0 + 1).min(nc - 1), (j0 + 1).min(nc - 1));
        let (ti, tj) = (u - i0 as f64, v - j0 as f64);
        (1.0 - ti) * ((1.0 - tj) * coarse[(i0, j0)] + tj * coarse[(i0, j1)])
            + ti * ((1.0 - tj) * coarse[(i1, j0)] + tj * coarse[(i1, j1)])
    })
}

impl Scene {
    /// The fusion problem this scene poses.
    /// The scene without what only a check against the truth needs (the truth surface and
    /// albedo, the shadow masks): what a fusion of it reads, and nothing more, stays in
    /// memory (`sfsfuse bench` measures the fusion's memory, not the scene's).
    pub fn without_truth(self) -> Self {
        let empty = || Array2::zeros((0, 0));
        Self {
            truth_height: empty(),
            truth_albedo: empty(),
            shadow: Array2::from_elem((0, 0), false),
            more: self
                .more
                .into_iter()
                .map(|m| Shot {
                    shadow: Array2::from_elem((0, 0), false),
                    ..m
                })
                .collect(),
            ..self
        }
    }

    pub fn problem(&self) -> crate::fusion::Problem<'_> {
        let mut pr = crate::fusion::Problem::single(
            self.image.view(),
            self.sun.directions(self.image.nrows(), self.image.ncols()),
            Directions::Uniform(self.view),
            self.input_dem.view(),
            self.spec.spacing,
            crate::fusion::dem_psf_sigma(self.spec.dem_factor as f64),
            &self.model,
        );
        pr.observations
            .extend(self.more.iter().map(|m| crate::fusion::Observation {
                image: m.image.view(),
                sun: m.sun.directions(m.image.nrows(), m.image.ncols()),
                view: Directions::Uniform(self.view),
            }));
        pr
    }
}

/// Root-mean-square difference of two arrays.
pub fn rmse(a: &Array2<f64>, b: &Array2<f64>) -> f64 {
    let s: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    (s / a.len() as f64).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The plain march, every half cell from the pixel: the reference the block skipping of
    /// [`cast_shadow`] must reproduce exactly.
    fn cast_shadow_plain(
        h: &Array2<f64>,
        eps: f64,
        sun_of_row: &dyn Fn(usize) -> Vec3,
    ) -> Array2<bool> {
        let (ny, nx) = h.dim();
        let hmax = h.iter().cloned().fold(f64::MIN, f64::max);
        Array2::from_shape_fn((ny, nx), |(i, j)| {
            let sun = sun_of_row(i);
            let horiz = (sun[0] * sun[0] + sun[1] * sun[1]).sqrt();
            let rise = sun[2] / horiz;
            let (dj, di) = (sun[0] / horiz, -sun[1] / horiz);
            let mut t = 0.5;
            loop {
                let (fi, fj) = (i as f64 + di * t, j as f64 + dj * t);
                if fi < 0.0 || fj < 0.0 || fi > (ny - 1) as f64 || fj > (nx - 1) as f64 {
                    return false;
                }
                let ray = h[(i, j)] + rise * t * eps;
                if ray > hmax {
                    return false;
                }
                let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
                let (i1, j1) = ((i0 + 1).min(ny - 1), (j0 + 1).min(nx - 1));
                let (ti, tj) = (fi - i0 as f64, fj - j0 as f64);
                let v = (1.0 - ti) * ((1.0 - tj) * h[(i0, j0)] + tj * h[(i0, j1)])
                    + ti * ((1.0 - tj) * h[(i1, j0)] + tj * h[(i1, j1)]);
                if v > ray {
                    return true;
                }
                t += 0.5;
            }
        })
    }

    /// A Sun moving along the rows: at the first and last rows the given directions, between
    /// them in proportion to the row (worked out by hand at the middle row of 5); a Sun that
    /// does not move is one vector for the whole grid; a drift that ends at or below the
    /// horizon is refused, naming the observation.
    #[test]
    fn a_suns_path_moves_in_proportion_to_the_row() {
        let path = SunPath {
            azimuth_deg: 350.0,
            zenith_deg: 70.0,
            drift_deg: [20.0, 10.0],
        };
        let close = |a: Vec3, b: Vec3| a.iter().zip(&b).all(|(x, y)| (x - y).abs() < 1e-12);
        assert!(close(path.at_row(0.0, 5), direction(70.0, 350.0)));
        assert!(close(path.at_row(4.0, 5), direction(60.0, 10.0)));
        // Row 2 of 5: halfway, azimuth 0° (due north) and elevation 25°.
        let mid = path.at_row(2.0, 5);
        let e = 25f64.to_radians();
        assert!(close(mid, [0.0, e.cos(), e.sin()]), "{mid:?}");
        match path.directions(5, 3) {
            Directions::PerPixel(a) => {
                assert_eq!(a.dim(), (5, 3));
                assert_eq!(a[(2, 0)], a[(2, 2)]);
                assert!((f64::from(a[(2, 1)][2]) - e.sin()).abs() < 1e-6);
            }
            Directions::Uniform(_) => panic!("a moving Sun must be given per pixel"),
        }
        let still = SunPath {
            drift_deg: [0.0, 0.0],
            ..path
        };
        assert!(
            matches!(still.directions(5, 3), Directions::Uniform(v) if close(v, direction(70.0, 350.0)))
        );
        let spec =
            SceneSpec::default().with_observations(&[(105.0, 30.0), (225.0, 35.0)], &[], false);
        let moved = spec
            .clone()
            .with_sun_drifts(&[[0.0, 0.0], [20.0, -10.0]])
            .unwrap();
        assert_eq!(moved.more[0].sun_drift_deg, [20.0, -10.0]);
        assert_eq!(moved.sun_drift_deg, [0.0, 0.0]);
        let err = spec
            .with_sun_drifts(&[[0.0, 0.0], [0.0, -35.0]])
            .unwrap_err();
        assert!(
            err.contains("observation 2") && err.contains("above the horizon"),
            "{err}"
        );
    }

    /// Complex craters: continuous at 15 km, depth ∝ D^0.301 beyond (Pike 1977), so that the
    /// widest crater of an 8192² scene at 140 m (229 km) is a few kilometres deep, as the
    /// Moon's are, and its DEM fits a LOLA-like 16-bit product.
    #[test]
    fn complex_craters_deepen_as_the_0_301_power_of_diameter() {
        assert_eq!(complex_crater_scale(3e3), 1.0);
        assert_eq!(complex_crater_scale(COMPLEX_CRATER_M), 1.0);
        let depth = |d: f64| 0.2 * d * complex_crater_scale(d);
        assert!((depth(15.001e3) / depth(15e3) - 1.0).abs() < 1e-4);
        for d in [20e3, 60e3, 150e3] {
            let ratio = depth(2.0 * d) / depth(d);
            assert!((ratio - 2f64.powf(0.301)).abs() < 1e-12, "{ratio}");
        }
        let widest = 8192.0 / 5.0 * 140.0;
        assert!((6.0e3..8.0e3).contains(&depth(widest)), "{}", depth(widest));
    }

    /// Rough terrain (a deep pit, a ridge, noise, single-cell spikes) under low Suns from every
    /// quadrant and along the axes: the same shadows, pixel for pixel, as the plain march.
    #[test]
    fn block_skipping_gives_the_plain_marchs_shadows() {
        let mut rng = Rng::new(7);
        let (ny, nx) = (77, 90);
        let h = Array2::from_shape_fn((ny, nx), |(i, j)| {
            let (x, y) = (j as f64, i as f64);
            let pit = -400.0 * (-((x - 30.0).powi(2) + (y - 40.0).powi(2)) / 60.0).exp();
            let ridge = 250.0 * (-((x - 0.6 * y - 50.0).powi(2)) / 20.0).exp();
            // Single-cell spikes: a skip that overshoots a block's exit misses their shadows.
            let spike = if rng.uniform() < 0.03 { 150.0 } else { 0.0 };
            pit + ridge + 30.0 * (0.3 * x).sin() * (0.2 * y).cos() + 5.0 * rng.uniform() + spike
        });
        let mut shadowed = 0;
        for (zenith, azimuth) in [
            (80.0, 105.0),
            (75.0, 225.0),
            (85.0, 345.0),
            (70.0, 45.0),
            (80.0, 0.0),
            (80.0, 90.0),
            (82.0, 180.0),
            (60.0, 270.0),
        ] {
            let sun = direction(zenith, azimuth);
            let fast = cast_shadow(&h, 50.0, &|_| sun);
            assert_eq!(
                fast,
                cast_shadow_plain(&h, 50.0, &|_| sun),
                "Sun {zenith}/{azimuth}"
            );
            shadowed += fast.iter().filter(|&&s| s).count();
        }
        assert!(shadowed > 500, "the scene must cast shadows: {shadowed}");
        // A Sun that moves along the rows, as over a long strip: each ray its own row's.
        let path = SunPath {
            azimuth_deg: 200.0,
            zenith_deg: 82.0,
            drift_deg: [-60.0, 20.0],
        };
        let sun = |i: usize| path.at_row(i as f64, ny);
        let fast = cast_shadow(&h, 50.0, &sun);
        assert_eq!(fast, cast_shadow_plain(&h, 50.0, &sun));
        assert!(fast.iter().filter(|&&s| s).count() > 100);
    }
}
