//! Ingest: mission products onto one grid. The I/O edge between `pds` (formats) and the pure
//! `grid` geometry.
//!
//! * [`m3_on_grid`]: an M3 L1B observation → bidirectional reflectance r = L·d²/E₁AU(λ) at one
//!   wavelength (docs/formats.md; d = SOLAR_DISTANCE + OBS band 6), and per-pixel unit vectors to
//!   the Sun and to M3 (OBS bands 1–4, east-north-up, rotated into the grid frame), resampled
//!   from the swath by [`grid::swath_positions`] and bilinear interpolation.
//! * [`lola_on_grid`]: a LOLA GDR → heights (m above the 1737.4 km sphere) at every grid
//!   centre, bilinear or bicubic in the product's own projection.
//!
//! Both read only the lines of the product that the grid needs.

use crate::error::{Error, Result};
use crate::grid::{self, enu_to_grid, Geographic, Grid, Interpolation, Projector};
use crate::photometry::{narrow, Vec3, Vec3f};
use crate::registration::Displacement;
use crate::synth::direction;
use ndarray::{s, Array2, ArrayView2, Axis, Zip};
use pds::lola::{LolaDem, Projection};
use pds::m3::Observation;
use pds::solar::{reflectance, SolarSpectrum};

/// Lines of LOC read to measure a swath's ground sample distance (from its middle).
const GSD_LINES: usize = 256;

/// The ground sample distance of an observation, metres: the geometric mean of the median
/// distances between neighbouring samples of a line and between neighbouring lines, over up
/// to `GSD_LINES` lines from the middle of LOC (great circles at the LOC radius) — the side
/// of a square pixel with the area of the swath's. M3 global mode gives ≈ 140–150 m from the
/// 100 km orbit (the real crops: 143 m across, 157 m along track → 150 m) and about twice that
/// from 200 km.
pub fn ground_sample_distance(obs: &Observation) -> Result<f64> {
    let loc = obs.part("LOC")?;
    let n = GSD_LINES.min(loc.lines);
    let first = (loc.lines - n) / 2;
    let [lon, lat, rad] = [0, 1, 2].map(|b| read2(&loc, b, first, n));
    let (lon, lat, rad) = (lon?, lat?, rad?);
    let dist = |a: (usize, usize), b: (usize, usize)| {
        let (la1, la2) = (lat[a].to_radians(), lat[b].to_radians());
        let dl = (lon[b] - lon[a]).to_radians();
        let h =
            ((la2 - la1) / 2.0).sin().powi(2) + la1.cos() * la2.cos() * (dl / 2.0).sin().powi(2);
        let d = 2.0 * 0.5 * (rad[a] + rad[b]) * h.sqrt().min(1.0).asin();
        d.is_finite().then_some(d)
    };
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        (!v.is_empty()).then(|| v[v.len() / 2])
    };
    let (lines, samples) = lon.dim();
    let across = (0..lines)
        .flat_map(|l| (1..samples).filter_map(move |m| dist((l, m - 1), (l, m))))
        .filter(|d| *d > 0.0)
        .collect();
    let along = (1..lines)
        .flat_map(|l| (0..samples).filter_map(move |m| dist((l - 1, m), (l, m))))
        .filter(|d| *d > 0.0)
        .collect();
    match (median(across), median(along)) {
        (Some(a), Some(b)) => Ok((a * b).sqrt()),
        (Some(d), None) | (None, Some(d)) => Ok(d),
        (None, None) => Err(Error::Usage(format!(
            "{}: LOC has no two neighbouring valid positions to measure the ground sample distance from: give [grid] resolution_m",
            obs.label_path.display()
        ))),
    }
}

/// Lines of LOC scanned at a time when looking for the part of a swath over the grid.
const SCAN_LINES: usize = 1024;

/// An image with its illumination geometry on a grid.
#[derive(Debug, Clone)]
pub struct ImageOnGrid {
    /// Bidirectional reflectance, sr⁻¹; 0 where dark (radiance ≤ 0 within noise); NaN
    /// outside the swath or where [`check_pixel`] refuses the pixel.
    pub reflectance: Array2<f64>,
    /// Unit vectors to the Sun and to the camera in the grid frame, in f32 (12 bytes a pixel
    /// each; widened exactly where they are used); NaN outside the swath.
    pub sun: Array2<Vec3f>,
    pub view: Array2<Vec3f>,
    /// The swath lines used, `first..end`.
    pub lines: (usize, usize),
    /// The wavelength used and the two bands blended to reach it (same band twice when exact).
    pub wavelength_nm: f64,
    pub bands: (usize, usize),
    /// Solar irradiance at 1 AU used, W/(m² µm).
    pub irradiance: f64,
}

fn read2(r: &pds::raw::Raster, band: usize, first: usize, count: usize) -> Result<Array2<f64>> {
    let v = r.read_band(band, first, count)?;
    Array2::from_shape_vec((count, r.samples), v).map_err(|e| Error::Usage(e.to_string()))
}

/// Lines of a swath per block of a [`SwathIndex`].
pub const INDEX_BLOCK: usize = 64;

/// Where each block of [`INDEX_BLOCK`] swath lines falls in one map projection: the bounding
/// box (x_min, x_max, y_min, y_max) in metres of its pixel centres, `None` where no pixel
/// projects. Lets each tile read only the lines it needs. It also carries what every read of
/// the swath applies: its detector columns' relative gains.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SwathIndex {
    pub lines: usize,
    pub boxes: Vec<Option<[f64; 4]>>,
    /// The relative gain of each detector column (sample), which every read of the swath
    /// divides its radiance by ([`crate::striping`]; `None`: none applied).
    #[serde(default)]
    pub column_gains: Option<Vec<f64>>,
}

impl SwathIndex {
    /// The lines `first..end` whose blocks can reach `grid` (with a 2-pixel margin).
    pub fn lines_for(&self, grid: &Grid) -> Option<(usize, usize)> {
        let m = 2.0 * grid.spacing;
        let (gx0, gx1) = (grid.x0 - m, grid.x0 + grid.cols as f64 * grid.spacing + m);
        let (gy0, gy1) = (grid.y0 - grid.rows as f64 * grid.spacing - m, grid.y0 + m);
        let hit: Vec<usize> = self
            .boxes
            .iter()
            .enumerate()
            .filter(|(_, b)| {
                b.is_some_and(|b| b[0] <= gx1 && b[1] >= gx0 && b[2] <= gy1 && b[3] >= gy0)
            })
            .map(|(k, _)| k)
            .collect();
        let (&a, &b) = (hit.first()?, hit.last()?);
        // One line of margin across block edges.
        Some((
            (a * INDEX_BLOCK).saturating_sub(1),
            ((b + 1) * INDEX_BLOCK + 1).min(self.lines),
        ))
    }
}

/// One pass over an observation for a run: its [`SwathIndex`] in the grid's projection, and
/// the sum and count of valid reflectances of the pixels that fall on the grid (for the
/// run-wide intensity scale Ī).
#[derive(Debug, Clone)]
pub struct Survey {
    pub index: SwathIndex,
    pub sum: f64,
    pub count: usize,
    /// Swath pixels that fall on the grid, usable or not.
    pub on_grid: usize,
    /// Of those, how many [`check_pixel`] refused, by cause.
    pub refused: Refusals,
    /// Over the `count` usable pixels: Σ of the OBS to-Sun zenith (degrees) and of the sine
    /// and cosine of the to-Sun azimuth (clockwise from north) — the observation's mean
    /// illumination over the region ([`Survey::mean_sun`]).
    pub sun_sums: [f64; 3],
    /// Over the same pixels: the smallest and largest OBS to-Sun zenith, degrees
    /// ([`Survey::sun_elevation_range`]; [∞, −∞] without any). Over a long polar strip the Sun
    /// changes along the track.
    pub sun_zenith_range: [f64; 2],
    /// OBS's Sun against the ephemeris at the label's times over every pixel of the swath
    /// ([`SunCheck`]; `None` where the label gives no START_TIME, as synthetic products).
    pub sun_ephemeris: Option<SunCheck>,
    /// Its detector columns' relative gains, estimated over every line of the swath
    /// ([`crate::striping`]; `None` for a swath too short to measure a block). Not yet in
    /// `index`: the plan puts them there when `[inputs] destripe` is on.
    pub striping: Option<crate::striping::ColumnGains>,
    /// LOC's surface heights at a sample of the usable pixels on the grid (every
    /// [`LOC_HEIGHT_STEP`]-th line and sample): longitude, latitude (degrees) and radius less
    /// the 1737.4 km sphere (metres), to hold the DEM against ([`LocHeights`]).
    pub loc_heights: LocHeights,
}

/// Every how many lines and samples the survey samples LOC's heights.
pub const LOC_HEIGHT_STEP: usize = 8;

/// LOC's heights at sampled swath pixels ([`Survey::loc_heights`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LocHeights {
    pub lon: Vec<f64>,
    pub lat: Vec<f64>,
    pub height_m: Vec<f64>,
}

/// How an observation's LOC heights compare with the DEM at the same points ([`dem_vs_loc`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DemVsLoc {
    /// The sampled pixels compared (usable, on the grid, the DEM defined there).
    pub pixels: usize,
    /// Median of LOC's height less the DEM's, metres.
    pub median_m: f64,
    /// Median absolute deviation about it, metres.
    pub mad_m: f64,
}

/// |median| of LOC's heights less the DEM's above which a run warns, metres. On the vendored
/// crops over LDEM_4 the median is 1–23 m (LOC's radii come from a LOLA-based surface; RMS
/// 150–220 m at LDEM_4's 7.6 km posting). A DEM on a sphere 600 m off (1738 km), in feet, or
/// in kilometres over terrain more than 300 m from the datum lies beyond it.
pub const MAX_DEM_LOC_OFFSET_M: f64 = 300.0;

/// LOC's heights against `dem` (the DEM's heights at the same points, NaN where it has none):
/// `None` where no point has both.
pub fn dem_vs_loc(loc: &LocHeights, dem: &[f64]) -> Option<DemVsLoc> {
    use crate::fusion::ops::median;
    let mut d: Vec<f64> = loc
        .height_m
        .iter()
        .zip(dem)
        .map(|(l, h)| l - h)
        .filter(|d| d.is_finite())
        .collect();
    let median_m = median(&mut d)?;
    let mut dev: Vec<f64> = d.iter().map(|x| (x - median_m).abs()).collect();
    Some(DemVsLoc {
        pixels: d.len(),
        median_m,
        mad_m: median(&mut dev)?,
    })
}

/// Largest accepted angle, degrees, between the Sun of OBS (to-Sun azimuth and zenith at LOC's
/// longitude and latitude, turned into the Moon's body-fixed frame) and the Sun of
/// [`crate::ephemeris::sun_in_moon_frame`] at the label's time. They agree within 0.01° on
/// the vendored M3 crops; another observation's OBS, azimuths counted another way (16–36° off
/// on those crops) or a wrong time do not.
pub const MAX_SUN_EPHEMERIS_DEG: f64 = 1.0;

/// How far OBS's Sun lies from the ephemeris's over an observation's swath ([`survey`]).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SunCheck {
    /// The largest angle over the pixels compared, degrees.
    pub worst_deg: f64,
    /// Where it is: line and sample, counted from 1 as in the label.
    pub line: usize,
    pub sample: usize,
    /// The pixels compared (finite LOC and OBS, within 0.1° of neither pole).
    pub pixels: usize,
    /// The angle allowed: [`MAX_SUN_EPHEMERIS_DEG`] plus half the Sun's motion over the
    /// Moon's sky between START_TIME and STOP_TIME (each pixel is compared with the Sun at
    /// their midpoint; ≈ 0.5° an hour).
    pub allowed_deg: f64,
    /// The Moon's distance from the Sun at that midpoint, AU, which the label's
    /// SOLAR_DISTANCE must match within `distance_allowed_au` ([`MAX_SOLAR_DISTANCE_OFF_AU`]
    /// plus half its change between START_TIME and STOP_TIME).
    pub distance_au: f64,
    pub distance_allowed_au: f64,
}

/// Largest accepted difference, AU, between the label's SOLAR_DISTANCE and the Moon's distance
/// from the Sun at its START_TIME–STOP_TIME ([`crate::ephemeris::sun_distance_au`]): they
/// agree within 1.3·10⁻⁴ AU on the vendored M3 labels; 10⁻³ AU scales the reflectance by
/// 0.2 % (d²), while the range [`pds::m3::Observation::open`] accepts (0.98–1.02 AU) spans
/// 8 %.
pub const MAX_SOLAR_DISTANCE_OFF_AU: f64 = 1e-3;

/// What the ephemeris says at the midpoint of `obs`'s START_TIME and STOP_TIME: the Sun in the
/// Moon's body-fixed frame, the angle allowed from it ([`SunCheck::allowed_deg`]) and the
/// Sun's distance; `None` without START_TIME.
fn sun_at_label_times(obs: &Observation) -> Option<(Vec3, SunCheck)> {
    use crate::ephemeris::{angle_deg, days_since_j2000, sun_distance_au, sun_in_moon_frame};
    let a = days_since_j2000(obs.start_time.as_ref()?);
    let b = obs.stop_time.as_ref().map_or(a, days_since_j2000);
    let arc = angle_deg(sun_in_moon_frame(a), sun_in_moon_frame(b));
    let (ra, rb) = (sun_distance_au(a), sun_distance_au(b));
    let check = SunCheck {
        worst_deg: 0.0,
        line: 0,
        sample: 0,
        pixels: 0,
        allowed_deg: MAX_SUN_EPHEMERIS_DEG + 0.5 * arc,
        distance_au: 0.5 * (ra + rb),
        distance_allowed_au: MAX_SOLAR_DISTANCE_OFF_AU + 0.5 * (ra - rb).abs(),
    };
    Some((sun_in_moon_frame(0.5 * (a + b)), check))
}

/// [`SunCheck`] of `obs` from its label alone: the Sun's distance at its times, no pixel
/// compared (`pixels` 0); `None` where the label gives no START_TIME. What can be checked of
/// an observation whose LOC or OBS is not at hand.
pub fn label_sun_check(obs: &Observation) -> Option<SunCheck> {
    sun_at_label_times(obs).map(|(_, check)| check)
}

/// [`SunCheck`] of `obs` over its whole swath, read from its LOC and OBS files (what
/// [`survey`] measures on the way; `None` where the label gives no START_TIME).
pub fn sun_check(obs: &Observation) -> Result<Option<SunCheck>> {
    let Some((sun, mut check)) = sun_at_label_times(obs) else {
        return Ok(None);
    };
    let (loc, obsr) = parts(obs)?;
    for start in (0..loc.lines).step_by(INDEX_BLOCK) {
        let n = INDEX_BLOCK.min(loc.lines - start);
        let lon = loc.read_band(0, start, n)?;
        let lat = loc.read_band(1, start, n)?;
        let az = obsr.read_band(0, start, n)?;
        let zen = obsr.read_band(1, start, n)?;
        sun_ephemeris_lines(
            &mut check,
            sun,
            [&lon, &lat, &az, &zen],
            (start, loc.samples),
        );
    }
    Ok(Some(check))
}

/// Refuse `obs` when its label's SOLAR_DISTANCE is not the Moon's distance from the Sun at its
/// times, or when its [`SunCheck`] exceeds the angle allowed, naming the label or the OBS
/// file, the pixel and the label's times.
pub fn check_sun_ephemeris(obs: &Observation, check: &SunCheck) -> Result<()> {
    let off_au = obs.solar_distance_au - check.distance_au;
    if off_au.abs() > check.distance_allowed_au {
        return Err(Error::Usage(format!(
            "{}: SOLAR_DISTANCE = {} AU, but the Moon was {:.5} AU from the Sun between START_TIME {} and STOP_TIME {} UTC ({:+.5} AU off, at most {:.4} allowed; real M3 labels agree within 0.00013 AU). Every reflectance scales with its square ({:+.2} %): the label's SOLAR_DISTANCE or its times are not this observation's. For simulated products whose label keeps a real observation's times, set [inputs] check_sun_ephemeris = false",
            obs.label_path.display(),
            obs.solar_distance_au,
            check.distance_au,
            fmt_time(&obs.start_time),
            fmt_time(&obs.stop_time),
            off_au,
            check.distance_allowed_au,
            100.0 * ((obs.solar_distance_au / check.distance_au).powi(2) - 1.0)
        )));
    }
    if check.worst_deg <= check.allowed_deg {
        return Ok(());
    }
    let obs_path = obs
        .part("OBS")
        .map_or_else(|_| obs.label_path.clone(), |r| r.path);
    Err(Error::Usage(format!(
        "{}: OBS (to-Sun azimuth and zenith, bands 1–2) at line {}, sample {} puts the Sun {:.2}° from where it stood over that pixel's LOC longitude and latitude between START_TIME {} and STOP_TIME {} UTC of {} (at most {:.2}° allowed; on real M3 products the two agree within 0.01°). The OBS file does not describe this observation: check that the label, LOC and OBS files are of one product (an OBS from another observation, or azimuths counted other than clockwise from north, do this). For simulated products whose label keeps a real observation's times, set [inputs] check_sun_ephemeris = false",
        obs_path.display(),
        check.line,
        check.sample,
        check.worst_deg,
        fmt_time(&obs.start_time),
        fmt_time(&obs.stop_time),
        obs.label_path.display(),
        check.allowed_deg
    )))
}

fn fmt_time(t: &Option<pds::time::UtcTime>) -> String {
    t.map_or("?".to_string(), |t| t.to_string())
}

impl Survey {
    /// The observation's mean Sun over its usable pixels on the grid, as (azimuth clockwise
    /// from north, elevation above the local horizontal of the reference sphere), degrees; the
    /// azimuth is the circular mean. `None` without a usable pixel.
    pub fn mean_sun(&self) -> Option<(f64, f64)> {
        (self.count > 0).then(|| {
            let [zen, sin, cos] = self.sun_sums;
            let az = sin.atan2(cos).to_degrees().rem_euclid(360.0);
            (az, 90.0 - zen / self.count as f64)
        })
    }

    /// The lowest and highest Sun over the observation's usable pixels on the grid, as
    /// [elevation, elevation] in degrees above the local horizontal (90° less the largest and
    /// smallest OBS to-Sun zenith). `None` without a usable pixel.
    pub fn sun_elevation_range(&self) -> Option<[f64; 2]> {
        let [lo, hi] = self.sun_zenith_range;
        (self.count > 0).then_some([90.0 - hi, 90.0 - lo])
    }
}

/// Why swath pixels were refused as photometric ([`check_pixel`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Refusals {
    /// Dark: radiance ≤ 0 but within noise of it (reflectance ≥ [`DARK_FLOOR`]); kept as 0,
    /// part of the image's footprint (cast shadow) but not photometric.
    pub dark: usize,
    /// Radiance NaN, below [`DARK_FLOOR`] or above [`MAX_REFLECTANCE`] as reflectance.
    pub radiance: usize,
    /// OBS puts the Sun at or below the local horizon (to-Sun zenith ≥ 90°).
    pub sun_below_horizon: usize,
    /// OBS puts M3 at or below the local horizon (to-M3 zenith ≥ 90°).
    pub view_below_horizon: usize,
    /// OBS phase disagrees with the angle between the Sun and M3 vectors by more than
    /// [`MAX_PHASE_MISMATCH_DEG`], or the geometry is not finite.
    pub geometry: usize,
    /// OBS's to-Sun distance (band 6, an offset from SOLAR_DISTANCE) is not finite or more
    /// than [`MAX_SUN_DISTANCE_OFFSET_AU`] from it.
    #[serde(default)]
    pub sun_distance: usize,
}

impl Refusals {
    fn add(&mut self, c: Cause) {
        match c {
            Cause::Ok => {}
            Cause::Dark => self.dark += 1,
            Cause::Radiance => self.radiance += 1,
            Cause::SunBelow => self.sun_below_horizon += 1,
            Cause::ViewBelow => self.view_below_horizon += 1,
            Cause::Geometry => self.geometry += 1,
            Cause::SunDistance => self.sun_distance += 1,
        }
    }

    pub fn total(&self) -> usize {
        self.dark
            + self.radiance
            + self.sun_below_horizon
            + self.view_below_horizon
            + self.geometry
            + self.sun_distance
    }

    /// The causes with their counts, largest first, for messages.
    pub fn describe(&self) -> String {
        let mut v = [
            (self.dark, "radiance ≤ 0 (dark, shadow)"),
            (
                self.radiance,
                "radiance NaN, negative beyond noise, or above the physical bound",
            ),
            (
                self.sun_below_horizon,
                "Sun at or below the local horizon in OBS",
            ),
            (
                self.view_below_horizon,
                "M3 at or below the local horizon in OBS",
            ),
            (
                self.geometry,
                "OBS phase inconsistent with its Sun and M3 directions",
            ),
            (
                self.sun_distance,
                "OBS to-Sun distance (band 6) more than 0.001 AU off the label's SOLAR_DISTANCE",
            ),
        ];
        v.sort_by_key(|x| std::cmp::Reverse(x.0));
        v.iter()
            .filter(|(n, _)| *n > 0)
            .map(|(n, why)| format!("{n} px: {why}"))
            .collect::<Vec<_>>()
            .join("; ")
    }
}

/// Reflectance above which a radiance is not physical: r = 1.5/π sr⁻¹ (I/F = 1.5; the
/// brightest lunar surfaces stay below I/F ≈ 0.6 at 1.2 µm, a perfect Lambertian reflector
/// lit from the zenith has I/F = 1).
pub const MAX_REFLECTANCE: f64 = 1.5 / std::f64::consts::PI;
/// Reflectance (sr⁻¹) down to which a radiance ≤ 0 is read as dark (cast shadow plus noise and
/// dark-level error: I/F ≥ −0.06, ten times M3's noise at 1.2 µm); below it the radiance is
/// not a measurement (the `linerateNotConstant` crop has −368 W/(m² µm sr), I/F ≈ −2.4).
pub const DARK_FLOOR: f64 = -0.02;
/// Largest accepted |OBS band 6|, AU: the pixel's to-Sun distance less the label's
/// SOLAR_DISTANCE. The vendored crops stay within 3·10⁻⁷ AU; a point of the near side is at
/// most a lunar radius (1.2·10⁻⁵ AU) off the centre, and the Moon's distance from the Sun
/// changes by less than 5·10⁻⁴ AU a day. A larger offset scales the reflectance by d²
/// (3 AU: ×16) and is not a geometry.
pub const MAX_SUN_DISTANCE_OFFSET_AU: f64 = 1e-3;
/// Largest accepted difference between OBS phase (band 5) and the angle between OBS's Sun and
/// M3 directions (bands 1–4), degrees. They agree to 1e-5° on real products.
pub const MAX_PHASE_MISMATCH_DEG: f64 = 1.0;

/// Why one swath pixel cannot be photometric.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Cause {
    Ok,
    Dark,
    Radiance,
    SunBelow,
    ViewBelow,
    Geometry,
    SunDistance,
}

/// The guard rails of one swath pixel: reflectance `r` (sr⁻¹, from the radiance), OBS to-Sun
/// azimuth/zenith, to-M3 azimuth/zenith and phase, degrees. A pixel is photometric only
/// where the radiance is finite, positive and below [`MAX_REFLECTANCE`], the Sun and M3 are
/// above the local horizon, and the phase matches the two directions within
/// [`MAX_PHASE_MISMATCH_DEG`]. With a sound geometry, a reflectance in
/// [`DARK_FLOOR`], 0] is [`Cause::Dark`]: seen, but in shadow.
pub fn check_pixel(
    r: f64,
    sun_az: f64,
    sun_zen: f64,
    view_az: f64,
    view_zen: f64,
    phase: f64,
) -> Cause {
    if !(r.is_finite() && (DARK_FLOOR..=MAX_REFLECTANCE).contains(&r)) {
        return Cause::Radiance;
    }
    if ![sun_az, sun_zen, view_az, view_zen, phase]
        .iter()
        .all(|v| v.is_finite())
    {
        return Cause::Geometry;
    }
    if sun_zen >= 90.0 {
        return Cause::SunBelow;
    }
    if view_zen >= 90.0 {
        return Cause::ViewBelow;
    }
    let (s, v) = (direction(sun_zen, sun_az), direction(view_zen, view_az));
    let cos = (s[0] * v[0] + s[1] * v[1] + s[2] * v[2]).clamp(-1.0, 1.0);
    if (cos.acos().to_degrees() - phase).abs() > MAX_PHASE_MISMATCH_DEG {
        return Cause::Geometry;
    }
    if r <= 0.0 {
        return Cause::Dark;
    }
    Cause::Ok
}

/// Solar spectral irradiance at 1 AU of a 5778 K black body, W/(m² µm), at `nm`:
/// E = π·B_λ(T)·(R☉/AU)², B_λ = 2hc²/λ⁵ / (exp(hc/λkT) − 1) (Planck's law; R☉ = 6.957·10⁸ m,
/// 1 AU = 1.495 978 707·10¹¹ m). The measured M3 table lies within 5 % of it in the near
/// infrared and within 0.95–1.22× of it over all its 256 bands.
pub fn blackbody_irradiance(nm: f64) -> f64 {
    let (h, c, k) = (6.626_070_15e-34, 2.997_924_58e8, 1.380_649e-23);
    let (t, r_sun, au): (f64, f64, f64) = (5778.0, 6.957e8, 1.495_978_707e11);
    let l = nm * 1e-9;
    let b = 2.0 * h * c * c / l.powi(5) / ((h * c / (l * k * t)).exp() - 1.0);
    // W/(m² m) → W/(m² µm).
    std::f64::consts::PI * b * (r_sun / au).powi(2) * 1e-6
}

/// How far a solar table's irradiance may lie from [`blackbody_irradiance`] (a factor either
/// way): the measured M3 table stays within 0.95–1.22× of it, while a table in another unit
/// (W/(m² nm): 1000× smaller; W/(m² sr µm) or at another distance) falls far outside.
pub const SOLAR_BLACKBODY_FACTOR: f64 = 2.0;

/// The solar table's irradiance at 1 AU at `nm`, W/(m² µm): refused when the table does not
/// cover `nm`, or when the value is not within [`SOLAR_BLACKBODY_FACTOR`] of the Sun's (a
/// table in another unit would scale every reflectance, and the albedo with it, silently).
pub fn irradiance_at(solar: &SolarSpectrum, nm: f64) -> Result<f64> {
    let path = solar.path.display();
    let e = solar.at(nm).ok_or_else(|| {
        Error::Usage(format!("{path}: the solar spectrum does not cover {nm} nm"))
    })?;
    let sun = blackbody_irradiance(nm);
    let ratio = e / sun;
    if !(1.0 / SOLAR_BLACKBODY_FACTOR..=SOLAR_BLACKBODY_FACTOR).contains(&ratio) {
        return Err(Error::Usage(format!(
            "{path}: the irradiance at {nm} nm is {e:.4} W/(m² µm), {ratio:.3}× the Sun's ≈ {sun:.0} W/(m² µm) at 1 AU (a 5778 K black body): the table must give W/(m² µm) at 1 AU, as M3's M3*_RFL_SOLAR_SPEC.TAB does (a table in W/(m² nm) reads 1000× smaller)"
        )));
    }
    Ok(e)
}

/// What [`reflectance_lines`] returns: reflectance, the two bands blended, the irradiance
/// used, each pixel's [`Cause`], and the OBS to-Sun azimuth and zenith it checked them with
/// (degrees; [`survey`] averages them, so the bands are read once).
type Lines = (
    Array2<f64>,
    (usize, usize),
    f64,
    Array2<Cause>,
    [Array2<f64>; 2],
);

/// Reflectance at `nm` of lines `first..first + n`, samples `samples` (the arrays' column 0 is
/// sample `samples.start`): r = L·d²/E, L blended linearly between the two bands around `nm`,
/// d = SOLAR_DISTANCE + OBS band 6; NaN where [`check_pixel`] refuses the pixel, whose cause
/// is returned per pixel too. Each pixel's values depend on that pixel alone, so a range of
/// samples gives the same values there as whole lines. With `column_gains` (one per sample of
/// the swath, [`crate::striping`]) each sample's radiance is divided by its gain first.
fn reflectance_lines(
    obs: &Observation,
    obsr: &pds::raw::Raster,
    solar: &SolarSpectrum,
    nm: f64,
    (first, n): (usize, usize),
    samples: std::ops::Range<usize>,
    column_gains: Option<&[f64]>,
) -> Result<Lines> {
    let bracket = obs.bracket(nm)?;
    let (lo, up, w) = if bracket.weight_upper >= 1.0 {
        (bracket.upper, bracket.upper, 0.0)
    } else {
        (bracket.lower, bracket.upper, bracket.weight_upper)
    };
    let gains = column_gains.map(|g| &g[samples.clone()]);
    let cols = s![.., samples.clone()];
    let read = |r: &pds::raw::Raster, band: usize| -> Result<Array2<f64>> {
        Ok(read2(r, band, first, n)?.slice(cols).to_owned())
    };
    let l_lo = read(&obs.rdn, lo)?;
    let l_up = if up == lo {
        l_lo.clone()
    } else {
        read(&obs.rdn, up)?
    };
    let e = irradiance_at(solar, nm)?;
    let d_off = read(obsr, 5)?;
    let d0 = obs.solar_distance_au;
    let geo: Vec<Array2<f64>> = (0..5).map(|b| read(obsr, b)).collect::<Result<_>>()?;
    let mut refl = Array2::from_elem((n, samples.len()), f64::NAN);
    let mut cause = Array2::from_elem((n, samples.len()), Cause::Ok);
    Zip::indexed(&mut refl)
        .and(&mut cause)
        .par_for_each(|ij, r, c| {
            let l = (1.0 - w) * l_lo[ij] + w * l_up[ij];
            let l = gains.map_or(l, |g| l / g[ij.1]);
            let dd = d_off[ij];
            let v = if l.is_finite() && dd.is_finite() {
                reflectance(l, d0 + dd, e)
            } else {
                f64::NAN
            };
            *c = if dd.abs() <= MAX_SUN_DISTANCE_OFFSET_AU {
                check_pixel(
                    v, geo[0][ij], geo[1][ij], geo[2][ij], geo[3][ij], geo[4][ij],
                )
            } else {
                Cause::SunDistance
            };
            match *c {
                Cause::Ok => *r = v,
                Cause::Dark => *r = 0.0,
                _ => {}
            }
        });
    // OBS bands 1 and 2: to-Sun azimuth and zenith.
    let mut geo = geo.into_iter();
    let (az, zen) = (geo.next(), geo.next());
    let sun = [az, zen].map(|b| b.expect("five OBS bands read"));
    Ok((refl, (lo, up), e, cause, sun))
}

/// The parts of an observation, checked to match the radiance cube.
fn parts(obs: &Observation) -> Result<(pds::raw::Raster, pds::raw::Raster)> {
    let loc = obs.part("LOC")?;
    let obsr = obs.part("OBS")?;
    for (name, r, bands) in [("LOC", &loc, 3), ("OBS", &obsr, 10)] {
        if (r.lines, r.samples) != (obs.rdn.lines, obs.rdn.samples) || r.bands < bands {
            return Err(Error::Usage(format!(
                "{}: {name} is {} lines × {} samples × {} bands, RDN {} × {}: the parts must match ({bands} bands needed)",
                obs.label_path.display(), r.lines, r.samples, r.bands, obs.rdn.lines, obs.rdn.samples
            )));
        }
    }
    Ok((loc, obsr))
}

/// Survey `obs` for a run on `grid` (see [`Survey`]).
pub fn survey(
    obs: &Observation,
    solar: &SolarSpectrum,
    nm: f64,
    grid: &Grid,
    pr: &Projector,
) -> Result<Survey> {
    let (loc, obsr) = parts(obs)?;
    let mut boxes = Vec::with_capacity(loc.lines.div_ceil(INDEX_BLOCK));
    let (mut sum, mut count) = (0.0, 0usize);
    let (mut on_grid_count, mut refused) = (0usize, Refusals::default());
    let mut sun_sums = [0.0; 3];
    let mut sun_zenith_range = [f64::INFINITY, f64::NEG_INFINITY];
    let sun_time = sun_at_label_times(obs);
    let mut sun_check = sun_time.map(|(_, check)| check);
    let mut loc_heights = LocHeights::default();
    let mut columns = crate::striping::ColumnProfiles::default();
    for start in (0..loc.lines).step_by(INDEX_BLOCK) {
        let n = INDEX_BLOCK.min(loc.lines - start);
        let lon = loc.read_band(0, start, n)?;
        let lat = loc.read_band(1, start, n)?;
        let (refl, _, _, cause, [sun_az, sun_zen]) =
            reflectance_lines(obs, &obsr, solar, nm, (start, n), 0..loc.samples, None)?;
        // Dark pixels (0) and refused ones (NaN) are not measured.
        columns.add_lines(
            refl.mapv(|r| if r > 0.0 { r.ln() } else { f64::NAN })
                .view(),
        );
        if let (Some((sun, _)), Some(check)) = (sun_time.as_ref(), sun_check.as_mut()) {
            let zen = sun_zen.as_slice().expect("standard layout");
            let az = sun_az.as_slice().expect("standard layout");
            sun_ephemeris_lines(check, *sun, [&lon, &lat, az, zen], (start, loc.samples));
        }
        // LOC's radius on the sampled lines of this block.
        let radius: Vec<Vec<f64>> = (start..start + n)
            .step_by(LOC_HEIGHT_STEP)
            .map(|l| loc.read_band(2, l, 1))
            .collect::<std::result::Result<_, _>>()?;
        let mut b = [f64::MAX, f64::MIN, f64::MAX, f64::MIN];
        let mut any = false;
        // The projections in parallel; the sums below in the samples' order, as before.
        let xy = Zip::from(&lon)
            .and(&lat)
            .par_map_collect(|&lo, &la| pr.forward(lo, la));
        for (k, ((((xy, &r), &c), &az), &zen)) in xy
            .iter()
            .zip(refl.iter())
            .zip(cause.iter())
            .zip(sun_az.iter())
            .zip(sun_zen.iter())
            .enumerate()
        {
            let Some((x, y)) = *xy else {
                continue;
            };
            any = true;
            b = [b[0].min(x), b[1].max(x), b[2].min(y), b[3].max(y)];
            let (gr, gc) = grid.pixel(x, y);
            let on_grid = gr >= -0.5
                && gc >= -0.5
                && gr < grid.rows as f64 - 0.5
                && gc < grid.cols as f64 - 0.5;
            if on_grid {
                on_grid_count += 1;
                refused.add(c);
                if c == Cause::Ok {
                    sum += r;
                    count += 1;
                    let a = az.to_radians();
                    sun_sums[0] += zen;
                    sun_sums[1] += a.sin();
                    sun_sums[2] += a.cos();
                    sun_zenith_range = [sun_zenith_range[0].min(zen), sun_zenith_range[1].max(zen)];
                    let (i, j) = (k / loc.samples, k % loc.samples);
                    if i % LOC_HEIGHT_STEP == 0 && j % LOC_HEIGHT_STEP == 0 {
                        let h = radius[i / LOC_HEIGHT_STEP][j] - grid::MOON_RADIUS_M;
                        if h.is_finite() {
                            loc_heights.lon.push(lon[k]);
                            loc_heights.lat.push(lat[k]);
                            loc_heights.height_m.push(h);
                        }
                    }
                }
            }
        }
        boxes.push(any.then_some(b));
    }
    Ok(Survey {
        index: SwathIndex {
            lines: loc.lines,
            boxes,
            column_gains: None,
        },
        sum,
        count,
        on_grid: on_grid_count,
        refused,
        sun_sums,
        sun_zenith_range,
        sun_ephemeris: sun_check,
        striping: columns.gains(),
        loc_heights,
    })
}

/// Fold lines `first..` of `samples` samples (LOC longitude and latitude and OBS to-Sun
/// azimuth and zenith, degrees, line by line) into `check`: the angle between each pixel's Sun in the Moon's frame
/// ([`crate::ephemeris::local_to_moon`]) and `sun`. The worst is the first of equal worst
/// ones in line order, so the check does not depend on the thread count.
fn sun_ephemeris_lines(
    check: &mut SunCheck,
    sun: Vec3,
    [lon, lat, az, zen]: [&[f64]; 4],
    (first, samples): (usize, usize),
) {
    use crate::ephemeris::{angle_deg, local_to_moon};
    use rayon::prelude::*;
    // The angles in parallel (NaN where a pixel is not compared), the fold in line order.
    let off: Vec<f64> = (0..lon.len())
        .into_par_iter()
        .map(|k| {
            let (lo, la, a, z) = (lon[k], lat[k], az[k], zen[k]);
            if [lo, la, a, z].iter().all(|v| v.is_finite()) && la.abs() <= 89.9 {
                angle_deg(local_to_moon(lo, la, a, z), sun)
            } else {
                f64::NAN
            }
        })
        .collect();
    for (k, &o) in off.iter().enumerate().filter(|(_, o)| !o.is_nan()) {
        check.pixels += 1;
        if o > check.worst_deg {
            (check.worst_deg, check.line, check.sample) =
                (o, first + k / samples + 1, k % samples + 1);
        }
    }
}

/// Where LOC may put the pixels of an observation displaced by `shift` ([`m3_on_grid`]) that
/// land on `grid`: the grid grown on every side by the largest component the displacement
/// reaches, rounded up to whole pixels (`grid` itself for none).
pub fn reach(grid: &Grid, shift: &Displacement) -> Grid {
    let grow = (shift.reach_m() / grid.spacing).ceil() as usize;
    grid.window(
        -(grow as isize),
        -(grow as isize),
        grid.rows + 2 * grow,
        grid.cols + 2 * grow,
    )
}

/// Resample observation `obs` at `nm` onto `grid` (`bearing` the grid bearing of north at
/// each pixel, [`Geographic::bearing`] of `grid.geographic(pr)`), reading only the lines
/// `index` says can reach the grid (or scanning LOC for them without one). `shift` is the
/// observation's displacement on the grid, metres along the projection's x and y at each swath
/// line ([`Displacement`]): each swath pixel is placed that far back from where LOC puts it.
#[allow(clippy::too_many_arguments)]
pub fn m3_on_grid(
    obs: &Observation,
    solar: &SolarSpectrum,
    nm: f64,
    grid: &Grid,
    pr: &Projector,
    bearing: ArrayView2<f64>,
    index: Option<&SwathIndex>,
    shift: &Displacement,
) -> Result<ImageOnGrid> {
    m3_on_grid_with_lines(obs, solar, nm, grid, pr, bearing, index, shift, false)
        .map(|(img, _)| img)
}

/// Where the samples of swath lines `first..first + n` that can reach `search` (the grid's
/// reach) fall on `grid`: their fractional grid rows and columns, and the sample they start
/// at. Only a superset of the samples, found from every 8th ([`grid::swath_sample_superset`]),
/// is projected: a tile is often narrower than the swath. Each line is moved back by `shift`
/// at it, by x along the columns and by y along the rows, which run south.
fn placed_samples(
    loc: &pds::raw::Raster,
    (first, n): (usize, usize),
    search: &Grid,
    grid: &Grid,
    pr: &Projector,
    shift: &Displacement,
) -> Result<(Array2<f64>, Array2<f64>, usize)> {
    let lon = read2(loc, 0, first, n)?;
    let lat = read2(loc, 1, first, n)?;
    let (c0, c1) =
        grid::swath_sample_superset(search, pr, lon.view(), lat.view()).unwrap_or((0, lon.ncols()));
    let cols = s![.., c0..c1];
    let (mut gr, mut gc) = grid::swath_grid_positions(grid, pr, lon.slice(cols), lat.slice(cols));
    if !shift.is_none() {
        for (i, (mut r, mut c)) in gr.rows_mut().into_iter().zip(gc.rows_mut()).enumerate() {
            let [x, y] = shift.at((first + i) as f64);
            r += y / grid.spacing;
            c -= x / grid.spacing;
        }
    }
    Ok((gr, gc, c0))
}

/// [`m3_on_grid`], and where `with_lines` the swath line (fractional, counted from the
/// product's first) each grid pixel is resampled at, NaN outside the swath: registration
/// places its estimates along the track by it, and a gain trend is a function of it. (4 bytes
/// a pixel more while they are kept.)
#[allow(clippy::too_many_arguments)]
pub fn m3_on_grid_with_lines(
    obs: &Observation,
    solar: &SolarSpectrum,
    nm: f64,
    grid: &Grid,
    pr: &Projector,
    bearing: ArrayView2<f64>,
    index: Option<&SwathIndex>,
    shift: &Displacement,
    with_lines: bool,
) -> Result<(ImageOnGrid, Option<Array2<f32>>)> {
    let label = &obs.label_path;
    let (loc, obsr) = parts(obs)?;
    // The lines and samples are looked for on the grid's reach, since LOC puts the pixels
    // that land on it that far away.
    let search = reach(grid, shift);
    let range = match index {
        Some(ix) => ix.lines_for(&search),
        None => scan_lines(&loc, &search, pr)?,
    };
    let Some((first, end)) = range else {
        return Err(Error::Usage(format!(
            "{}: no pixel of this observation falls on the grid (its LOC longitudes/latitudes are outside the region)",
            label.display()
        )));
    };
    let n = end - first;
    let gains = index.and_then(|ix| ix.column_gains.as_deref());
    if let Some(g) = gains.filter(|g| g.len() != obs.rdn.samples) {
        return Err(Error::Usage(format!(
            "{}: {} column gains for {} samples: the plan belongs to another product; delete plan.json",
            label.display(),
            g.len(),
            obs.rdn.samples
        )));
    }
    // Only the samples that can reach the grid are projected (those of a superset found from
    // every 8th sample: a tile is often narrower than the swath) and resampled; sample
    // positions still count from the line's first sample.
    let (gr, gc, c0) = placed_samples(&loc, (first, n), &search, grid, pr, shift)?;
    let (s0, s1) = grid::swath_samples(grid, gr.view(), gc.view())
        .map_or((c0, c0 + gr.ncols()), |(a, b)| (c0 + a, c0 + b));
    let within = s![.., s0 - c0..s1 - c0];
    let (line, sample) = grid::swath_positions_from(grid, gr.slice(within), gc.slice(within), s0);
    let per_pixel = swath_pixels_per_grid_pixel(gr.slice(within), gc.slice(within));
    drop((gr, gc));
    let cols = s![.., s0..s1];
    let (mut refl, (lo, up), e, _, _) =
        reflectance_lines(obs, &obsr, solar, nm, (first, n), s0..s1, gains)?;
    // A swath finer than the grid is averaged over each grid pixel's extent first: sampled
    // at a point, it would alias relief finer than a grid pixel into the image the fusion
    // explains (and keep all of its noise).
    for (axis, &f) in per_pixel.iter().enumerate() {
        if f >= AREA_MEAN_FROM {
            refl = box_mean(&refl, f, axis);
        }
    }
    // East, north and up components, each filled in the one pass that computes the vector.
    let enu = |az: &Array2<f64>, zen: &Array2<f64>| -> [Array2<f64>; 3] {
        let dim = (az.nrows(), s1 - s0);
        let [mut e, mut n, mut u] = [0; 3].map(|_| Array2::zeros(dim));
        Zip::from(&mut e)
            .and(&mut n)
            .and(&mut u)
            .and(az.slice(cols))
            .and(zen.slice(cols))
            .par_for_each(|e, n, u, &a, &z| [*e, *n, *u] = direction(z, a));
        [e, n, u]
    };
    // Exact: m ≥ s0 and s0 is a whole number.
    let s0f = s0 as f64;
    let dim = (grid.rows, grid.cols);
    // One quantity at a time (the reflectance, then the Sun's and the view's unit vectors),
    // each swath array freed before the next is read.
    let mut out_r = Array2::from_elem(dim, f64::NAN);
    Zip::indexed(&mut out_r).par_for_each(|(i, j), r| {
        let (l, m) = (line[(i, j)], sample[(i, j)]);
        if !l.is_nan() {
            *r = grid::interpolate(refl.view(), l, m - s0f, Interpolation::Bilinear, false);
        }
    });
    drop(refl);
    // The unit vectors of OBS bands `az` and `zen` (degrees) on the grid, in its frame.
    let directions = |az: usize, zen: usize| -> Result<Array2<Vec3f>> {
        let nan3 = [f32::NAN; 3];
        let swath = enu(&read2(&obsr, az, first, n)?, &read2(&obsr, zen, first, n)?);
        let mut out = Array2::from_elem(dim, nan3);
        Zip::indexed(&mut out).par_for_each(|(i, j), d| {
            let (l, m) = (line[(i, j)], sample[(i, j)]);
            if !l.is_nan() {
                let b = bearing[(i, j)];
                *d = unit_at(&swath, l, m - s0f).map_or(nan3, |u| narrow(enu_to_grid(u, b)));
            }
        });
        Ok(out)
    };
    let out_s = directions(0, 1)?;
    let out_v = directions(2, 3)?;
    let first_f = first as f64;
    let lines = with_lines.then(|| line.mapv(|l| (first_f + l) as f32));
    let img = ImageOnGrid {
        reflectance: out_r,
        sun: out_s,
        view: out_v,
        lines: (first, end),
        wavelength_nm: nm,
        bands: (lo, up),
        irradiance: e,
    };
    Ok((img, lines))
}

/// The lines of a swath whose pixels fall on `grid` (with a margin of 2 grid pixels and one
/// swath line), by scanning LOC in chunks.
fn scan_lines(
    loc: &pds::raw::Raster,
    grid: &Grid,
    pr: &Projector,
) -> Result<Option<(usize, usize)>> {
    let (mut first, mut last) = (usize::MAX, 0usize);
    let inside = |lo: f64, la: f64| {
        pr.forward(lo, la).is_some_and(|(x, y)| {
            let (r, c) = grid.pixel(x, y);
            r > -2.5 && c > -2.5 && r < grid.rows as f64 + 1.5 && c < grid.cols as f64 + 1.5
        })
    };
    for start in (0..loc.lines).step_by(SCAN_LINES) {
        let n = SCAN_LINES.min(loc.lines - start);
        let lon = loc.read_band(0, start, n)?;
        let lat = loc.read_band(1, start, n)?;
        for l in 0..n {
            let row = l * loc.samples..(l + 1) * loc.samples;
            if lon[row.clone()]
                .iter()
                .zip(&lat[row])
                .any(|(&a, &b)| inside(a, b))
            {
                first = first.min(start + l);
                last = last.max(start + l);
            }
        }
    }
    Ok((first != usize::MAX).then(|| (first.saturating_sub(1), (last + 2).min(loc.lines))))
}

/// Swath pixels per grid pixel from which [`m3_on_grid`] averages the swath over each grid
/// pixel's extent before sampling it, along the lines or the samples (the default grid takes
/// the first observation's own pixel size, ≈ 1 swath pixel per grid pixel; M3's global mode
/// samples 140 m from the 100 km orbit, ≈ 280 m from 200 km, target mode 70 m).
pub const AREA_MEAN_FROM: f64 = 1.25;

/// Swath pixels per grid pixel [along a sample's column of lines, along a line's samples]:
/// the inverse of the median distance, in grid pixels, between neighbouring swath pixels'
/// grid positions `gr`, `gc` (every 4th line and sample; 1 where none is finite).
fn swath_pixels_per_grid_pixel(gr: ArrayView2<f64>, gc: ArrayView2<f64>) -> [f64; 2] {
    let (nl, ns) = gr.dim();
    let step = |dl: usize, ds: usize| -> f64 {
        let mut d: Vec<f64> = (0..nl.saturating_sub(dl))
            .step_by(4)
            .flat_map(|l| (0..ns.saturating_sub(ds)).step_by(4).map(move |m| (l, m)))
            .map(|(l, m)| {
                let (a, b) = (
                    gr[(l + dl, m + ds)] - gr[(l, m)],
                    gc[(l + dl, m + ds)] - gc[(l, m)],
                );
                (a * a + b * b).sqrt()
            })
            .filter(|d| d.is_finite() && *d > 0.0)
            .collect();
        if d.is_empty() {
            return 1.0;
        }
        let mid = d.len() / 2;
        let (_, m, _) = d.select_nth_unstable_by(mid, f64::total_cmp);
        1.0 / *m
    };
    [step(1, 0), step(0, 1)]
}

/// The mean of `image` over a box `width` pixels wide along `axis` (0: down the rows, 1: along
/// them) centred on each pixel: pixel k away weighs its overlap with [−width/2, width/2],
/// clamp(width/2 + ½ − |k|, 0, 1), so the weights sum to `width`; over the finite values only,
/// NaN where there are none.
pub fn box_mean(image: &Array2<f64>, width: f64, axis: usize) -> Array2<f64> {
    let half = 0.5 * width;
    let reach = (half - 0.5).ceil().max(0.0) as isize;
    let weights: Vec<f64> = (-reach..=reach)
        .map(|k| (half + 0.5 - (k as f64).abs()).clamp(0.0, 1.0))
        .collect();
    let n = image.len_of(Axis(axis)) as isize;
    let mut out = Array2::from_elem(image.dim(), f64::NAN);
    Zip::from(out.lanes_mut(Axis(axis)))
        .and(image.lanes(Axis(axis)))
        .par_for_each(|mut o, lane| {
            for i in 0..n {
                let (mut s, mut w) = (0.0, 0.0);
                for (k, &wk) in (-reach..=reach).zip(&weights) {
                    let j = i + k;
                    if (0..n).contains(&j) {
                        let v = lane[j as usize];
                        if v.is_finite() {
                            s += wk * v;
                            w += wk;
                        }
                    }
                }
                if w > 0.0 {
                    o[i as usize] = s / w;
                }
            }
        });
    out
}

/// Bilinear blend of unit vectors at (line, sample), renormalised.
fn unit_at(a: &[Array2<f64>; 3], l: f64, m: f64) -> Option<Vec3> {
    let u = [0, 1, 2].map(|k| grid::interpolate(a[k].view(), l, m, Interpolation::Bilinear, false));
    let n = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
    (n.is_finite() && n > 0.0).then(|| [u[0] / n, u[1] / n, u[2] / n])
}

/// Heights the Moon's surface can have, metres above the 1737.4 km sphere: LOLA puts it between
/// −9.1 km (the floor of Antoniadi) and +10.8 km (south-east of Engel'gardt); the bounds leave
/// more than a kilometre either side. A DEM value outside is no height: a wrong
/// SCALING_FACTOR, OFFSET or UNIT, a radius, or a fill value (docs/formats.md).
pub const LUNAR_HEIGHT_RANGE_M: [f64; 2] = [-12_000.0, 12_000.0];

/// Lines `first..first + count` of `dem` as heights above the 1737.4 km sphere of the grid's
/// CRS, metres: DN × SCALING_FACTOR + OFFSET − 1737.4 km where the label gives OFFSET (the
/// product's reference sphere; 1737.4 km in every LOLA GDR), DN × SCALING_FACTOR where not.
pub fn lola_heights(dem: &LolaDem, first: usize, count: usize) -> Result<Vec<f64>> {
    let shift = dem.offset.map_or(0.0, |o| o - grid::MOON_RADIUS_M);
    Ok(dem
        .read_heights(first, count)?
        .into_iter()
        .map(|h| h + shift)
        .collect())
}

/// Refuses `heights` (the part of a DEM read for a grid, starting at 0-based `origin` =
/// (line, sample) of `file`: whole lines of a PDS product, the needed strips or tiles of a
/// GeoTIFF) where a finite one lies outside [`LUNAR_HEIGHT_RANGE_M`], naming the first such
/// pixel (counted from 1), its value and how many there are. NaN (no data) passes.
pub fn check_lunar_heights(
    file: &std::path::Path,
    heights: ArrayView2<f64>,
    origin: (usize, usize),
) -> Result<()> {
    let [lo, hi] = LUNAR_HEIGHT_RANGE_M;
    let outside = |h: f64| h.is_finite() && !(lo..=hi).contains(&h);
    let count = heights.iter().filter(|&&h| outside(h)).count();
    let Some(((i, j), &h)) = heights.indexed_iter().find(|(_, &h)| outside(h)) else {
        return Ok(());
    };
    Err(Error::Usage(format!(
        "{}: line {}, sample {}: height {h} m is not on the Moon (its surface lies within \
         −9.1 … +10.8 km of the 1737.4 km sphere; accepted {lo} … {hi} m), and {} more pixel(s) \
         of the part read for the grid are outside too: check the label's SCALING_FACTOR, OFFSET and UNIT, \
         whether the file holds radii rather than heights, and whether a fill value marks \
         missing data (declare it as no data)",
        file.display(),
        origin.0 + i + 1,
        origin.1 + j + 1,
        count - 1
    )))
}

/// Whether `dem` goes all round the Moon: a simple cylindrical product of 360° × MAP_RESOLUTION
/// samples, whose last column is the first one's western neighbour.
fn wraps_round(dem: &LolaDem) -> bool {
    match dem.projection {
        Projection::SimpleCylindrical { resolution, .. } => {
            (dem.samples() as f64 - 360.0 * resolution).abs() < 1e-6
        }
        Projection::PolarStereographic { .. } => false,
    }
}

/// A gridded altimetry product's offsets between its tracks, one per product column (sample)
/// over the columns a region reads ([`lola_track_offsets`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackOffsets {
    /// 0-based sample of `offsets[0]`.
    pub first_sample: usize,
    /// Metres, one per sample from `first_sample` (0 where none is estimated).
    pub offsets: Vec<f64>,
    /// What the estimate saw, in metres ([`crate::striping::Striping`]).
    pub summary: crate::striping::Striping,
}

impl TrackOffsets {
    /// Subtract each sample's offset from every line of `heights` (whole lines of the product).
    pub fn subtract_from(&self, heights: &mut Array2<f64>) {
        for mut line in heights.rows_mut() {
            for (k, &o) in self.offsets.iter().enumerate() {
                if let Some(h) = line.get_mut(self.first_sample + k) {
                    *h -= o;
                }
            }
        }
    }
}

/// Lines per block of the track offsets' estimate: half an image's
/// ([`crate::striping::BLOCK_LINES`]), as a region spans few lines of a DEM.
pub const TRACK_BLOCK_LINES: usize = 16;

/// Lines read beyond the region on either side for the track offsets' estimate: more blocks
/// along the same tracks.
pub const TRACK_MARGIN_LINES: usize = 64;

/// R of the track offsets' estimate: each product column is compared with its neighbours up
/// to 3 columns either side, one fewer than an image's columns
/// ([`crate::striping::HALF_WINDOW`]). A gridded DEM is smooth across a few of its columns, so
/// the narrower window leaves less terrain in each estimate while an offset, different from
/// one track to the next, stands out as much (docs/science.md, "Taking the offsets out of the
/// DEM").
pub const TRACK_HALF_WINDOW: usize = 3;

/// The offsets between the tracks of `dem`, a simple cylindrical product gridded from
/// altimeter tracks (LOLA's run north–south along its columns), over the samples the grid of
/// geography `geo` reads: the estimate of [`crate::striping`] on the heights themselves (an
/// offset adds, as ln g does to ln r), in blocks of [`TRACK_BLOCK_LINES`] lines over the
/// region's lines and [`TRACK_MARGIN_LINES`] either side. What changes from one column to
/// the next within ±[`TRACK_HALF_WINDOW`] columns and persists from block to block
/// is taken for an offset; terrain, which changes from block to block, shrinks the estimate
/// towards 0, and a product without offsets gets none. `None` where the grid does not reach
/// the product, for a polar stereographic product (its tracks run along no column) and where
/// the region's columns wrap round the product's edge.
pub fn lola_track_offsets(dem: &LolaDem, geo: &Geographic) -> Result<Option<TrackOffsets>> {
    if !matches!(dem.projection, Projection::SimpleCylindrical { .. }) {
        return Ok(None);
    }
    // A product all round the Moon: a region across its first and last columns reaches both
    // ends.
    let global = wraps_round(dem);
    let pixels = geo.lon.iter().zip(&geo.lat).map(|(&lon, &lat)| {
        if lon.is_finite() && lat.is_finite() {
            dem.pixel(lon, lat)
        } else {
            (f64::NAN, f64::NAN)
        }
    });
    let (lines, samples) = (dem.lines(), dem.samples());
    let Some(span) = PixelSpan::of(pixels).filter(|span| span.meets_lines(lines)) else {
        return Ok(None);
    };
    let ([l_lo, l_hi], [s_lo, s_hi]) = (span.lines, span.samples);
    if s_hi < -0.5 {
        return Ok(None);
    }
    // Every column of the region with its whole window of neighbours.
    let reach = (TRACK_HALF_WINDOW + 2) as f64;
    let s0 = (s_lo.floor() - reach).max(0.0) as usize;
    let s1 = ((s_hi.ceil() + reach + 1.0).max(0.0) as usize).min(samples);
    if s0 >= s1 || (global && 2 * (s1 - s0) > samples) {
        return Ok(None);
    }
    let margin = TRACK_MARGIN_LINES as f64;
    let l0 = (l_lo.floor() - margin).max(0.0) as usize;
    let l1 = ((l_hi.ceil() + margin + 1.0).max(0.0) as usize).min(lines);
    let [lo, hi] = LUNAR_HEIGHT_RANGE_M;
    let mut profiles = crate::striping::ColumnProfiles::default();
    for start in (l0..l1).step_by(TRACK_BLOCK_LINES) {
        let count = TRACK_BLOCK_LINES.min(l1 - start);
        let block = Array2::from_shape_vec((count, samples), lola_heights(dem, start, count)?)
            .map_err(|e| Error::Usage(e.to_string()))?;
        // A height off the Moon is no measurement here (the grid's read refuses it).
        let block =
            block
                .slice(s![.., s0..s1])
                .mapv(|h| if (lo..=hi).contains(&h) { h } else { f64::NAN });
        profiles.add_block(block.view());
    }
    Ok(profiles
        .offsets_within(TRACK_HALF_WINDOW)
        .map(|(offsets, summary)| TrackOffsets {
            first_sample: s0,
            offsets,
            summary,
        }))
}

/// The fractional product lines and samples a set of positions ([`LolaDem::pixel`]) spans,
/// over the positions whose line and sample are both finite.
#[derive(Debug, Clone, Copy, PartialEq)]
struct PixelSpan {
    /// Smallest and largest line.
    lines: [f64; 2],
    /// Smallest and largest sample.
    samples: [f64; 2],
}

impl PixelSpan {
    /// The span of `pixels` ((line, sample) pairs); `None` where none is finite.
    fn of(pixels: impl Iterator<Item = (f64, f64)>) -> Option<Self> {
        pixels.filter(|(l, s)| l.is_finite() && s.is_finite()).fold(
            None,
            |span: Option<Self>, (l, s)| {
                Some(match span {
                    None => PixelSpan {
                        lines: [l, l],
                        samples: [s, s],
                    },
                    Some(PixelSpan {
                        lines: [l0, l1],
                        samples: [s0, s1],
                    }) => PixelSpan {
                        lines: [l0.min(l), l1.max(l)],
                        samples: [s0.min(s), s1.max(s)],
                    },
                })
            },
        )
    }

    /// Whether the span reaches a product of `lines` lines: line k covers k − 0.5 … k + 0.5.
    fn meets_lines(&self, lines: usize) -> bool {
        let [lo, hi] = self.lines;
        hi >= -0.5 && lo <= lines as f64 - 0.5
    }
}

/// Heights of `dem` at every centre of the grid whose geography is `geo`, metres above the
/// 1737.4 km sphere ([`lola_heights`]); NaN outside the product or where its support touches
/// no data; `None` when no grid pixel falls on the product. A height the grid needs outside
/// [`LUNAR_HEIGHT_RANGE_M`] is refused, as is a product that cannot be read.
pub fn lola_on_grid(
    dem: &LolaDem,
    geo: &Geographic,
    method: Interpolation,
) -> Result<Option<Array2<f64>>> {
    lola_on_grid_tracked(dem, geo, method, None)
}

/// [`lola_on_grid`] with the product's offsets between its tracks taken out of the heights
/// before they are interpolated (`tracks`, [`lola_track_offsets`]; `None`: as read).
pub fn lola_on_grid_tracked(
    dem: &LolaDem,
    geo: &Geographic,
    method: Interpolation,
    tracks: Option<&TrackOffsets>,
) -> Result<Option<Array2<f64>>> {
    let dim = geo.lon.dim();
    let mut pos_l = Array2::from_elem(dim, f64::NAN);
    let mut pos_s = pos_l.clone();
    Zip::from(&mut pos_l)
        .and(&mut pos_s)
        .and(&geo.lon)
        .and(&geo.lat)
        .par_for_each(|l, s, &lo, &la| {
            if lo.is_finite() && la.is_finite() {
                (*l, *s) = dem.pixel(lo, la);
            }
        });
    let pixels = pos_l.iter().zip(&pos_s).map(|(&l, &s)| (l, s));
    let Some(span) = PixelSpan::of(pixels).filter(|span| span.meets_lines(dem.lines())) else {
        return Ok(None);
    };
    let [lmin, lmax] = span.lines;
    let lines = dem.lines() as f64;
    let first = (lmin.floor() - 2.0).clamp(0.0, lines - 1.0) as usize;
    let end = ((lmax.ceil() + 3.0).clamp(1.0, lines)) as usize;
    let window = lola_heights(dem, first, end - first)?;
    let mut window = Array2::from_shape_vec((end - first, dem.samples()), window)
        .map_err(|e| Error::Usage(e.to_string()))?;
    check_lunar_heights(&dem.raster.path, window.view(), (first, 0))?;
    if let Some(t) = tracks {
        t.subtract_from(&mut window);
    }
    let wrap = wraps_round(dem);
    Ok(Some(Zip::from(&pos_l).and(&pos_s).par_map_collect(
        |&l, &s| grid::interpolate(window.view(), l - first as f64, s, method, wrap),
    )))
}

/// A DEM in a (Geo)TIFF file: heights in metres above the 1737.4 km sphere, on the grid its
/// ModelPixelScale/ModelTiepoint describe, in the CRS its GeoKeys describe
/// ([`crate::export::crs_from_geokeys`]); GDAL_NODATA and NaN are no data. Only the strips or
/// tiles a grid needs are read.
#[derive(Debug, Clone)]
pub struct GeoTiffDem {
    pub path: std::path::PathBuf,
    pub crs: crate::export::GeoTiffCrs,
    /// GDAL geotransform (north-up).
    pub geotransform: [f64; 6],
    pub width: usize,
    pub height: usize,
    pub nodata: Option<f64>,
}

impl GeoTiffDem {
    pub fn open(path: &std::path::Path) -> Result<Self> {
        use tiff::decoder::Decoder;
        use tiff::tags::Tag;
        let bad = |e: tiff::TiffError| {
            Error::Usage(format!("{}: not a readable GeoTIFF: {e}", path.display()))
        };
        let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut d = Decoder::new(std::io::BufReader::new(f)).map_err(bad)?;
        let (w, h) = d.dimensions().map_err(bad)?;
        let get_f64 = |d: &mut Decoder<_>, t: Tag| -> Result<Option<Vec<f64>>> {
            d.find_tag(t)
                .map_err(bad)?
                .map(|v| v.into_f64_vec().map_err(bad))
                .transpose()
        };
        let scale = get_f64(&mut d, Tag::ModelPixelScaleTag)?;
        let tie = get_f64(&mut d, Tag::ModelTiepointTag)?;
        let (Some(s), Some(t)) = (scale, tie) else {
            return Err(Error::Usage(format!(
                "{}: no ModelPixelScale/ModelTiepoint: the DEM is not georeferenced",
                path.display()
            )));
        };
        let geotransform = crate::export::geotransform_from(&s, &t).ok_or_else(|| {
            Error::Usage(format!(
                "{}: ModelPixelScale/ModelTiepoint are malformed",
                path.display()
            ))
        })?;
        let dir: Vec<u16> = d
            .find_tag(Tag::GeoKeyDirectoryTag)
            .map_err(bad)?
            .ok_or_else(|| {
                Error::Usage(format!(
                    "{}: no GeoKeys: the DEM's CRS is unknown",
                    path.display()
                ))
            })?
            .into_u16_vec()
            .map_err(bad)?;
        let doubles = get_f64(&mut d, Tag::GeoDoubleParamsTag)?.unwrap_or_default();
        let crs = crate::export::crs_from_geokeys(path, &dir, &doubles)?;
        let nodata = d
            .find_tag(Tag::GdalNodata)
            .map_err(bad)?
            .and_then(|v| v.into_string().ok())
            .and_then(|s| s.trim_matches(char::from(0)).trim().parse::<f64>().ok());
        Ok(GeoTiffDem {
            path: path.into(),
            crs,
            geotransform,
            width: w as usize,
            height: h as usize,
            nodata,
        })
    }

    /// Pixel size in metres (along the first axis; degrees converted on the sphere).
    pub fn pixel_m(&self) -> f64 {
        match self.crs {
            crate::export::GeoTiffCrs::Projected(_) => self.geotransform[1],
            crate::export::GeoTiffCrs::Geographic => {
                self.geotransform[1].to_radians() * crate::grid::MOON_RADIUS_M
            }
        }
    }

    /// Rows `r0..r1`, columns `c0..c1` (heights; no data → NaN), reading only the chunks there.
    fn window(&self, r0: usize, r1: usize, c0: usize, c1: usize) -> Result<Array2<f64>> {
        use tiff::decoder::{Decoder, DecodingResult};
        let path = &self.path;
        let bad = |e: tiff::TiffError| Error::Usage(format!("{}: {e}", path.display()));
        let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut d = Decoder::new(std::io::BufReader::new(f)).map_err(bad)?;
        let channels = match d.colortype().map_err(bad)? {
            tiff::ColorType::Gray(_) => 1,
            other => {
                return Err(Error::Usage(format!(
                    "{}: colour type {other:?}: a DEM has one band",
                    path.display()
                )))
            }
        };
        let (cw, ch) = d.chunk_dimensions();
        let (cw, ch) = (cw as usize, ch as usize);
        let across = self.width.div_ceil(cw);
        let mut out = Array2::from_elem((r1 - r0, c1 - c0), f64::NAN);
        for cy in r0 / ch..=(r1 - 1) / ch {
            for cx in c0 / cw..=(c1 - 1) / cw {
                let idx = (cy * across + cx) as u32;
                let (dw, dh) = d.chunk_data_dimensions(idx);
                let v: Vec<f64> = match d.read_chunk(idx).map_err(bad)? {
                    DecodingResult::I16(v) => v.into_iter().map(f64::from).collect(),
                    DecodingResult::U16(v) => v.into_iter().map(f64::from).collect(),
                    DecodingResult::I32(v) => v.into_iter().map(f64::from).collect(),
                    DecodingResult::F32(v) => v.into_iter().map(f64::from).collect(),
                    DecodingResult::F64(v) => v,
                    _ => return Err(Error::Usage(format!("{}: sample type not supported for a DEM (int16/uint16/int32/float32/float64)", path.display()))),
                };
                let (dw, dh) = (dw as usize, dh as usize);
                for y in 0..dh {
                    let r = cy * ch + y;
                    if r < r0 || r >= r1 {
                        continue;
                    }
                    for x in 0..dw {
                        let c = cx * cw + x;
                        if c < c0 || c >= c1 {
                            continue;
                        }
                        let h = v[(y * dw + x) * channels];
                        out[(r - r0, c - c0)] = if self.nodata.is_some_and(|n| n == h) {
                            f64::NAN
                        } else {
                            h
                        };
                    }
                }
            }
        }
        Ok(out)
    }
}

/// Heights of a GeoTIFF DEM at every centre of the grid whose geography is `geo` (as
/// [`lola_on_grid`]: NaN outside the DEM or where the support touches no data, `None` when no
/// grid pixel falls on it, heights outside [`LUNAR_HEIGHT_RANGE_M`] refused).
pub fn geotiff_on_grid(
    dem: &GeoTiffDem,
    geo: &Geographic,
    method: Interpolation,
) -> Result<Option<Array2<f64>>> {
    use crate::export::GeoTiffCrs;
    let pr = match dem.crs {
        GeoTiffCrs::Projected(c) => Some(c.projector().map_err(|e| Error::Usage(e.to_string()))?),
        GeoTiffCrs::Geographic => None,
    };
    let gt = dem.geotransform;
    let dim = geo.lon.dim();
    let mut pos_r = Array2::from_elem(dim, f64::NAN);
    let mut pos_c = pos_r.clone();
    Zip::from(&mut pos_r)
        .and(&mut pos_c)
        .and(&geo.lon)
        .and(&geo.lat)
        .par_for_each(|r, c, &lo, &la| {
            let xy = match &pr {
                Some(p) => p.forward(lo, la),
                None => {
                    // Longitude into the turn that starts at the DEM's west edge.
                    let lo = gt[0] + (lo - gt[0]).rem_euclid(360.0);
                    Some((lo, la))
                }
            };
            if let Some((x, y)) = xy {
                *c = (x - gt[0]) / gt[1] - 0.5;
                *r = (gt[3] - y) / -gt[5] - 0.5;
            }
        });
    let (mut r_lo, mut r_hi, mut c_lo, mut c_hi) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for (&r, &c) in pos_r
        .iter()
        .zip(&pos_c)
        .filter(|(r, c)| r.is_finite() && c.is_finite())
    {
        (r_lo, r_hi, c_lo, c_hi) = (r_lo.min(r), r_hi.max(r), c_lo.min(c), c_hi.max(c));
    }
    let (hh, ww) = (dem.height as f64, dem.width as f64);
    if r_lo > r_hi || r_hi < -0.5 || r_lo > hh - 0.5 || c_hi < -0.5 || c_lo > ww - 0.5 {
        return Ok(None);
    }
    let r0 = (r_lo.floor() - 2.0).clamp(0.0, hh - 1.0) as usize;
    let r1 = (r_hi.ceil() + 3.0).clamp(1.0, hh) as usize;
    let c0 = (c_lo.floor() - 2.0).clamp(0.0, ww - 1.0) as usize;
    let c1 = (c_hi.ceil() + 3.0).clamp(1.0, ww) as usize;
    let window = dem.window(r0, r1, c0, c1)?;
    check_lunar_heights(&dem.path, window.view(), (r0, c0))?;
    Ok(Some(Zip::from(&pos_r).and(&pos_c).par_map_collect(
        |&r, &c| grid::interpolate(window.view(), r - r0 as f64, c - c0 as f64, method, false),
    )))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// LOC against the DEM: the median and the median absolute deviation of the differences
    /// where both are defined (NaN DEM points skipped); none without such a point.
    #[test]
    fn loc_heights_against_the_dem_are_a_median_and_its_spread() {
        let loc = LocHeights {
            lon: vec![0.0; 5],
            lat: vec![0.0; 5],
            height_m: vec![-100.0, 0.0, 50.0, 700.0, 10.0],
        };
        // Differences 500, 600, NaN, 610, 0 → sorted 0, 500, 600, 610: median 550;
        // deviations 550, 50, 50, 60 → median 55.
        let c = dem_vs_loc(&loc, &[-600.0, -600.0, f64::NAN, 90.0, 10.0]).unwrap();
        assert_eq!((c.pixels, c.median_m, c.mad_m), (4, 550.0, 55.0));
        assert_eq!(dem_vs_loc(&loc, &[f64::NAN; 5]), None);
    }

    /// A span covers the positions whose line and sample are both finite; a product's lines
    /// run from −0.5 to lines − 0.5, so a span reaches it only within those edges.
    #[test]
    fn a_pixel_span_keeps_finite_positions_and_meets_the_lines_at_their_edges() {
        let nan = f64::NAN;
        let span = PixelSpan::of(
            [
                (3.0, 7.0),
                (nan, 100.0),
                (-2.0, nan),
                (1.5, -4.0),
                (9.0, 2.0),
            ]
            .into_iter(),
        )
        .unwrap();
        assert_eq!(span.lines, [1.5, 9.0]);
        assert_eq!(span.samples, [-4.0, 7.0]);
        assert_eq!(PixelSpan::of([(nan, 1.0), (1.0, nan)].into_iter()), None);
        assert_eq!(PixelSpan::of(std::iter::empty()), None);
        let lines = |lo: f64, hi: f64| PixelSpan {
            lines: [lo, hi],
            samples: [0.0, 0.0],
        };
        // 10 lines: −0.5 … 9.5.
        assert!(lines(-3.0, -0.5).meets_lines(10));
        assert!(!lines(-3.0, -0.51).meets_lines(10));
        assert!(lines(9.5, 12.0).meets_lines(10));
        assert!(!lines(9.51, 12.0).meets_lines(10));
        assert!(lines(-5.0, 20.0).meets_lines(10));
    }

    /// The mean Sun: the azimuth's circular mean (350° and 20° average to 5°, not 185°), the
    /// elevation 90° − the mean zenith; none without a usable pixel.
    #[test]
    fn the_mean_sun_averages_azimuths_on_the_circle() {
        let survey = |pixels: &[(f64, f64)]| Survey {
            index: SwathIndex {
                lines: 0,
                boxes: Vec::new(),
                column_gains: None,
            },
            sum: 0.0,
            count: pixels.len(),
            on_grid: pixels.len(),
            refused: Refusals::default(),
            sun_sums: pixels.iter().fold([0.0; 3], |[z, s, c], &(az, zen)| {
                let a = f64::to_radians(az);
                [z + zen, s + a.sin(), c + a.cos()]
            }),
            sun_zenith_range: pixels
                .iter()
                .fold([f64::INFINITY, f64::NEG_INFINITY], |[lo, hi], &(_, zen)| {
                    [lo.min(zen), hi.max(zen)]
                }),
            sun_ephemeris: None,
            striping: None,
            loc_heights: LocHeights::default(),
        };
        let s = survey(&[(350.0, 60.0), (20.0, 70.0)]);
        let (az, el) = s.mean_sun().unwrap();
        assert!((az - 5.0).abs() < 1e-9, "{az}");
        assert!((el - 25.0).abs() < 1e-9, "{el}");
        // The lowest Sun is 90° less the largest zenith.
        assert_eq!(s.sun_elevation_range(), Some([20.0, 30.0]));
        assert_eq!(survey(&[]).mean_sun(), None);
    }

    /// The box's weights by hand: width 1 is the identity; width 2 weighs the neighbours ½
    /// (a unit spike spreads as ¼, ½, ¼); width 3 weighs three pixels alike; a constant stays
    /// itself, also at the ends (the weights renormalise) and beside a NaN, which is skipped.
    #[test]
    fn box_mean_weighs_each_pixel_by_its_overlap_with_the_box() {
        let spike = Array2::from_shape_fn((1, 7), |(_, j)| if j == 3 { 1.0 } else { 0.0 });
        assert_eq!(box_mean(&spike, 1.0, 1), spike);
        let two = box_mean(&spike, 2.0, 1);
        assert_eq!(two.row(0).to_vec(), [0.0, 0.0, 0.25, 0.5, 0.25, 0.0, 0.0]);
        let three = box_mean(&spike, 3.0, 1);
        for (j, v) in three.row(0).iter().enumerate() {
            let want = if (2..=4).contains(&j) { 1.0 / 3.0 } else { 0.0 };
            assert!((v - want).abs() < 1e-15, "{j}: {v}");
        }
        // Down the rows: the same weights along axis 0.
        assert_eq!(
            box_mean(&spike.t().to_owned(), 2.0, 0).column(0).to_vec(),
            two.row(0).to_vec()
        );
        let mut flat = Array2::from_elem((3, 5), 2.5);
        flat[(1, 2)] = f64::NAN;
        for axis in [0, 1] {
            let m = box_mean(&flat, 2.6, axis);
            assert!(m.iter().all(|&v| (v - 2.5).abs() < 1e-15), "{m:?}");
        }
        // A lone NaN with no finite neighbour within the box stays NaN.
        let lone = Array2::from_shape_vec((1, 3), vec![1.0, f64::NAN, 1.0]).unwrap();
        assert!(box_mean(&lone, 1.0, 1)[(0, 1)].is_nan());
    }

    /// Swath pixels per grid pixel from positions with known steps: lines 0.5 grid px apart,
    /// samples 0.25 apart (a swath 2× finer down the lines and 4× along them), rotated.
    #[test]
    fn swath_pixels_per_grid_pixel_inverts_the_neighbour_distance() {
        let (c, s) = (0.6f64, 0.8f64);
        let gr = Array2::from_shape_fn((40, 60), |(l, m)| 0.5 * l as f64 * c - 0.25 * m as f64 * s);
        let gc = Array2::from_shape_fn((40, 60), |(l, m)| 0.5 * l as f64 * s + 0.25 * m as f64 * c);
        let [a, b] = swath_pixels_per_grid_pixel(gr.view(), gc.view());
        assert!(
            (a - 2.0).abs() < 1e-12 && (b - 4.0).abs() < 1e-12,
            "{a} {b}"
        );
        let nan = Array2::from_elem((4, 4), f64::NAN);
        assert_eq!(
            swath_pixels_per_grid_pixel(nan.view(), nan.view()),
            [1.0, 1.0]
        );
    }
}
