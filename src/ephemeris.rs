//! Where the Sun stands in the Moon's body-fixed frame at a given UTC time, to check an M3
//! observation's OBS geometry against its label's START_TIME/STOP_TIME
//! ([`crate::ingest::survey`], docs/formats.md "The Sun at the observation's time").
//!
//! Three published low-precision models, each far more accurate than the check needs (it
//! refuses at [`crate::ingest::MAX_SUN_EPHEMERIS_DEG`] = 1°):
//! - the Sun's geocentric position: the Astronomical Almanac's formula (mean longitude,
//!   mean anomaly, equation of centre; ≈ 0.01° over 1950–2050);
//! - the Moon's geocentric position: its mean longitude with the largest periodic term in
//!   longitude, latitude and parallax (≈ 1°, 5000 km; the Moon–Sun direction differs from the
//!   Earth–Sun one by at most 0.15°, so this leaves < 0.005°);
//! - the Moon's orientation: the IAU WGCCRE rotation model (pole right ascension α₀,
//!   declination δ₀ and prime meridian W with their 13 periodic terms E1–E13), which realises
//!   the mean-Earth/polar-axis frame of LOLA and M3's LOC within ≈ 0.005°.
//!
//! On the three vendored M3 crops the Sun from OBS and LOC agrees with this one within
//! 0.01° (`tests/ingest.rs`).

use crate::photometry::Vec3;
use pds::time::UtcTime;

/// Julian date of J2000.0 (2000-01-01T12:00 TT).
pub const J2000_JD: f64 = 2_451_545.0;

/// TAI − UTC, seconds, from each Julian date (UTC) on: the leap seconds since 1999 (IERS
/// Bulletin C). Earlier dates take the first value (≤ 22 s off back to 1972, 0.003° of the
/// Moon's rotation).
const TAI_MINUS_UTC: [(f64, f64); 6] = [
    (2_451_179.5, 32.0), // 1999-01-01
    (2_453_736.5, 33.0), // 2006-01-01
    (2_454_832.5, 34.0), // 2009-01-01
    (2_456_109.5, 35.0), // 2012-07-01
    (2_457_204.5, 36.0), // 2015-07-01
    (2_457_754.5, 37.0), // 2017-01-01
];

/// TT − TAI, seconds.
const TT_MINUS_TAI: f64 = 32.184;

/// Days from J2000.0 to `utc` in TDB: UTC + (TAI − UTC) + 32.184 s (TDB − TT stays under
/// 2 ms and is dropped).
pub fn days_since_j2000(utc: &UtcTime) -> f64 {
    let jd = utc.julian_date();
    let leap = TAI_MINUS_UTC
        .iter()
        .rev()
        .find(|(from, _)| jd >= *from)
        .map_or(TAI_MINUS_UTC[0].1, |(_, s)| *s);
    jd - J2000_JD + (leap + TT_MINUS_TAI) / 86_400.0
}

/// One astronomical unit, km.
const AU_KM: f64 = 149_597_870.7;
/// The Earth's equatorial radius, km (the Moon's parallax is measured against it).
const EARTH_RADIUS_KM: f64 = 6378.14;
/// Obliquity of the ecliptic at J2000.0, degrees (84 381.448″).
const OBLIQUITY_J2000_DEG: f64 = 23.439_291;
/// General precession in longitude, degrees per Julian century (5029.0966″): the shift of
/// the mean equinox of date from J2000's.
const PRECESSION_DEG_PER_CENTURY: f64 = 1.396_971;

fn sin_d(x: f64) -> f64 {
    x.to_radians().sin()
}
fn cos_d(x: f64) -> f64 {
    x.to_radians().cos()
}

/// A point at ecliptic longitude `lon`, latitude `lat` (degrees) and `distance`, in J2000
/// ecliptic Cartesian coordinates.
fn ecliptic(lon: f64, lat: f64, distance: f64) -> Vec3 {
    [
        distance * cos_d(lat) * cos_d(lon),
        distance * cos_d(lat) * sin_d(lon),
        distance * sin_d(lat),
    ]
}

/// The Sun's geocentric position at `d` days from J2000.0, km, J2000 ecliptic (Astronomical
/// Almanac, "Low precision formulas for the Sun"): L = 280.460° + 0.985 647 4° d,
/// g = 357.528° + 0.985 600 3° d, λ = L + 1.915° sin g + 0.020° sin 2g (mean equinox of
/// date), β = 0, R = 1.000 14 − 0.016 71 cos g − 0.000 14 cos 2g AU.
pub fn sun_geocentric(d: f64) -> Vec3 {
    let l = 280.460 + 0.985_647_4 * d;
    let g = 357.528 + 0.985_600_3 * d;
    let lambda = l + 1.915 * sin_d(g) + 0.020 * sin_d(2.0 * g);
    let r = 1.000_14 - 0.016_71 * cos_d(g) - 0.000_14 * cos_d(2.0 * g);
    let to_j2000 = PRECESSION_DEG_PER_CENTURY * d / 36_525.0;
    ecliptic(lambda - to_j2000, 0.0, r * AU_KM)
}

/// The Moon's geocentric position at `d` days from J2000.0, km, J2000 ecliptic: mean
/// longitude 218.32° + 481 267.881° T with the evection-free main term 6.29° sin M
/// (M = 135.0° + 477 198.87° T, the Moon's mean anomaly), latitude 5.13° sin F
/// (F = 93.3° + 483 202.02° T), parallax π = 0.9508° + 0.0518° cos M, distance R⊕/sin π
/// (Astronomical Almanac's low-precision Moon, first terms; T in Julian centuries).
pub fn moon_geocentric(d: f64) -> Vec3 {
    let t = d / 36_525.0;
    let m = 135.0 + 477_198.87 * t;
    let lon = 218.32 + 481_267.881 * t + 6.29 * sin_d(m);
    let lat = 5.13 * sin_d(93.3 + 483_202.02 * t);
    let parallax = 0.9508 + 0.0518 * cos_d(m);
    let to_j2000 = PRECESSION_DEG_PER_CENTURY * t;
    ecliptic(lon - to_j2000, lat, EARTH_RADIUS_KM / sin_d(parallax))
}

/// The Moon's orientation at `d` days from J2000.0 (TDB) by the IAU WGCCRE model: right
/// ascension and declination of its north pole in ICRF and the prime meridian angle W,
/// degrees.
pub fn moon_orientation(d: f64) -> [f64; 3] {
    let t = d / 36_525.0;
    // E1…E13, degrees: constant and rate per day.
    const E: [(f64, f64); 13] = [
        (125.045, -0.052_992_1),
        (250.089, -0.105_984_2),
        (260.008, 13.012_000_9),
        (176.625, 13.340_715_4),
        (357.529, 0.985_600_3),
        (311.589, 26.405_708_4),
        (134.963, 13.064_993_0),
        (276.617, 0.328_714_6),
        (34.226, 1.748_487_7),
        (15.134, -0.158_976_3),
        (119.743, 0.003_609_6),
        (239.961, 0.164_357_3),
        (25.053, 12.959_008_8),
    ];
    const RA: [f64; 13] = [
        -3.8787, -0.1204, 0.0700, -0.0172, 0.0, 0.0072, 0.0, 0.0, 0.0, -0.0052, 0.0, 0.0, 0.0043,
    ];
    const DEC: [f64; 13] = [
        1.5419, 0.0239, -0.0278, 0.0068, 0.0, -0.0029, 0.0009, 0.0, 0.0, 0.0008, 0.0, 0.0, -0.0009,
    ];
    const W: [f64; 13] = [
        3.5610, 0.1208, -0.0642, 0.0158, 0.0252, -0.0066, -0.0047, -0.0046, 0.0028, 0.0052, 0.0040,
        0.0019, -0.0044,
    ];
    let (mut ra, mut dec, mut w) = (
        269.9949 + 0.0031 * t,
        66.5392 + 0.0130 * t,
        38.3213 + 13.176_358_15 * d - 1.4e-12 * d * d,
    );
    for (k, (e0, rate)) in E.iter().enumerate() {
        let e = e0 + rate * d;
        ra += RA[k] * sin_d(e);
        dec += DEC[k] * cos_d(e);
        w += W[k] * sin_d(e);
    }
    [ra, dec, w.rem_euclid(360.0)]
}

/// Passive rotation about axis 3 (z) by `a` degrees.
fn r3(a: f64, v: Vec3) -> Vec3 {
    let (s, c) = a.to_radians().sin_cos();
    [c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]]
}

/// Passive rotation about axis 1 (x) by `a` degrees.
fn r1(a: f64, v: Vec3) -> Vec3 {
    let (s, c) = a.to_radians().sin_cos();
    [v[0], c * v[1] + s * v[2], -s * v[1] + c * v[2]]
}

fn unit(v: Vec3) -> Vec3 {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    [v[0] / n, v[1] / n, v[2] / n]
}

/// The Sun's position from the Moon's centre at `d` days from J2000.0, km, J2000 ecliptic:
/// [`sun_geocentric`] less [`moon_geocentric`].
pub fn sun_from_moon(d: f64) -> Vec3 {
    let (s, m) = (sun_geocentric(d), moon_geocentric(d));
    [s[0] - m[0], s[1] - m[1], s[2] - m[2]]
}

/// The distance from the Moon's centre to the Sun at `d` days from J2000.0, AU (what an M3
/// label's SOLAR_DISTANCE gives; within 1.3·10⁻⁴ AU of it on the vendored crops, where the
/// Earth's distance differs from it by up to 2.5·10⁻³ AU).
pub fn sun_distance_au(d: f64) -> f64 {
    let v = sun_from_moon(d);
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt() / AU_KM
}

/// The unit vector from the Moon's centre to the Sun at `d` days from J2000.0 (TDB), in the
/// Moon's body-fixed frame (x towards 0° E on the equator, z the north pole): the Sun's
/// geocentric position less the Moon's, turned from the J2000 ecliptic to the equator by the
/// obliquity, then into the Moon's frame by R₃(W)·R₁(90° − δ₀)·R₃(90° + α₀). (Light time and
/// aberration, ≈ 0.006°, are not applied.)
pub fn sun_in_moon_frame(d: f64) -> Vec3 {
    let equ = r1(-OBLIQUITY_J2000_DEG, sun_from_moon(d));
    let [ra, dec, w] = moon_orientation(d);
    unit(r3(w, r1(90.0 - dec, r3(90.0 + ra, equ))))
}

/// A direction given at (`lon_deg` east, `lat_deg`) on the sphere as azimuth (clockwise from
/// north) and zenith angle, degrees, in the Moon's body-fixed frame:
/// sin z (sin a ê + cos a n̂) + cos z û, with û = (cos φ cos λ, cos φ sin λ, sin φ),
/// ê = (−sin λ, cos λ, 0) and n̂ = (−sin φ cos λ, −sin φ sin λ, cos φ).
pub fn local_to_moon(lon_deg: f64, lat_deg: f64, azimuth_deg: f64, zenith_deg: f64) -> Vec3 {
    let (sl, cl) = lon_deg.to_radians().sin_cos();
    let (sp, cp) = lat_deg.to_radians().sin_cos();
    let [e, n, cz] = crate::synth::direction(zenith_deg, azimuth_deg);
    [
        -e * sl - n * sp * cl + cz * cp * cl,
        e * cl - n * sp * sl + cz * cp * sl,
        n * cp + cz * sp,
    ]
}

/// The angle between two unit vectors, degrees.
pub fn angle_deg(a: Vec3, b: Vec3) -> f64 {
    // atan2 of |a × b| and a·b keeps small angles exact.
    let c = [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ];
    let cross = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    let dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    cross.atan2(dot).to_degrees()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn utc(t: &str) -> f64 {
        days_since_j2000(&UtcTime::parse(t).unwrap())
    }

    /// The Sun's right ascension and declination, degrees, at `t`.
    fn sun_ra_dec(t: &str) -> (f64, f64) {
        let v = r1(-OBLIQUITY_J2000_DEG, sun_geocentric(utc(t)));
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        (
            v[1].atan2(v[0]).to_degrees().rem_euclid(360.0),
            (v[2] / n).asin().to_degrees(),
        )
    }

    #[test]
    fn the_sun_crosses_the_equinoxes_and_solstices_on_their_dates() {
        // 2009's equinoxes and solstices (UTC, to the minute, from the almanac): the Sun at
        // RA 0 / 90 / 180 / 270° and declination 0 / +ε / 0 / −ε (J2000 equator; the equinox
        // of date has moved 0.13° from J2000's by 2009).
        let eps = OBLIQUITY_J2000_DEG;
        for (t, ra, dec) in [
            ("2009-03-20T11:44", 0.0, 0.0),
            ("2009-06-21T05:45", 90.0, eps),
            ("2009-09-22T21:18", 180.0, 0.0),
            ("2009-12-21T17:47", 270.0, -eps),
        ] {
            let (a, d) = sun_ra_dec(t);
            let da = ((a - ra + 180.0).rem_euclid(360.0) - 180.0).abs();
            assert!(da < 0.2, "{t}: RA {a}");
            assert!((d - dec).abs() < 0.08, "{t}: dec {d}");
        }
    }

    #[test]
    fn the_sun_stays_within_the_moons_small_obliquity_of_its_equator() {
        // The lunar equator is inclined 1.54° to the ecliptic: the subsolar latitude never
        // exceeds it. Every 3 days over 2008–2010.
        let mut most = 0.0f64;
        for k in 0..365 {
            let s = sun_in_moon_frame(utc("2008-01-01") + 3.0 * k as f64);
            most = most.max(s[2].asin().to_degrees().abs());
        }
        assert!((1.4..1.6).contains(&most), "{most}");
    }

    #[test]
    fn full_moon_lights_the_near_side_and_new_moon_the_far_side() {
        // Full Moon 2009-01-11T03:27 UTC: the Sun stands behind the Earth, over the near side
        // near 0° E; new Moon 2009-01-26T07:55: over the far side, near 180° (within the
        // optical libration in longitude, ≤ 8°).
        for (t, lon0) in [("2009-01-11T03:27", 0.0), ("2009-01-26T07:55", 180.0)] {
            let s = sun_in_moon_frame(utc(t));
            let lon = s[1].atan2(s[0]).to_degrees();
            let off = ((lon - lon0 + 180.0).rem_euclid(360.0) - 180.0).abs();
            assert!(off < 10.0, "{t}: {lon}");
        }
    }

    #[test]
    fn the_suns_distance_follows_the_earths_orbit() {
        // Perihelion 2009-01-04 (0.983 27 AU) and aphelion 2009-07-04 (1.016 67 AU) of the
        // Earth–Moon barycentre's orbit: the Moon is within 0.0026 AU of the Earth.
        for (t, r) in [("2009-01-04T15:00", 0.98327), ("2009-07-04T02:00", 1.01667)] {
            let d = sun_distance_au(utc(t));
            assert!((d - r).abs() < 0.003, "{t}: {d}");
        }
    }

    #[test]
    fn local_directions_are_the_local_axes() {
        let close = |a: Vec3, b: Vec3| angle_deg(a, b) < 1e-9;
        // Zenith: the radial direction. At 0° N 0° E, east is +y, north +z.
        assert!(close(
            local_to_moon(30.0, 40.0, 123.0, 0.0),
            unit(ecliptic(30.0, 40.0, 1.0))
        ));
        assert!(close(local_to_moon(0.0, 0.0, 90.0, 90.0), [0.0, 1.0, 0.0]));
        assert!(close(local_to_moon(0.0, 0.0, 0.0, 90.0), [0.0, 0.0, 1.0]));
        // From 45° N, looking north at 45° from the zenith points at the pole.
        assert!(close(local_to_moon(70.0, 45.0, 0.0, 45.0), [0.0, 0.0, 1.0]));
        assert!((angle_deg([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]) - 90.0).abs() < 1e-12);
    }

    #[test]
    fn leap_seconds_step_on_their_dates() {
        let a = utc("2008-12-31T23:59:59");
        let b = utc("2009-01-01T00:00:00");
        assert!(
            ((b - a) * 86_400.0 - 2.0).abs() < 1e-4,
            "{}",
            (b - a) * 86_400.0
        );
        // J2000.0 is 11:58:55.816 UTC (TT − UTC = 64.184 s then).
        assert!(utc("2000-01-01T11:58:55.816").abs() * 86_400.0 < 1e-4);
    }
}
