//! M3 Level 1B crops (real mission data) read through their labels.

use pds::lola::LolaDem;
use pds::m3::{band_centres, Mode, Observation};

mod common;
use common::test_data;

const SETS: [(&str, &str); 3] = [
    ("forwardAscending", "M3T20090630T083407_V03_L1B_cropped.LBL"),
    (
        "forwardDescending",
        "M3G20081129T171431_V03_L1B_cropped.LBL",
    ),
    (
        "reverseDescending",
        "M3G20090106T113423_V03_L1B_cropped.LBL",
    ),
];

fn enu(zenith: f64, azimuth: f64) -> [f64; 3] {
    let (z, a) = (zenith.to_radians(), azimuth.to_radians());
    [z.sin() * a.sin(), z.sin() * a.cos(), z.cos()]
}

#[test]
fn obs_phase_equals_the_angle_between_sun_and_view() {
    let Some(data) = test_data() else { return };
    for (dir, lbl) in SETS {
        let o = Observation::open(&data.join("m3_l1b_crops").join(dir).join(lbl)).unwrap();
        let obs = o.part("OBS").unwrap();
        assert_eq!(obs.bands, 10);
        let b = |k| obs.read_band(k, 0, obs.lines).unwrap();
        let (saz, sze, vaz, vze, ph) = (b(0), b(1), b(2), b(3), b(4));
        let mut worst = 0.0f64;
        for i in 0..saz.len() {
            let (s, v) = (enu(sze[i], saz[i]), enu(vze[i], vaz[i]));
            let g = (s[0] * v[0] + s[1] * v[1] + s[2] * v[2])
                .clamp(-1.0, 1.0)
                .acos()
                .to_degrees();
            worst = worst.max((g - ph[i]).abs());
        }
        assert!(worst <= 1e-3, "{dir}: phase differs by {worst}°");
    }
}

#[test]
fn loc_radius_agrees_with_lola() {
    let Some(data) = test_data() else { return };
    let dem = LolaDem::open(&data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    let heights = dem.read_heights(0, dem.lines()).unwrap();
    let (n, m) = (dem.lines(), dem.samples());
    let bilinear = |lon: f64, lat: f64| {
        let (l, s) = dem.pixel(lon, lat);
        let (l0, s0) = (
            l.floor().clamp(0.0, (n - 2) as f64) as usize,
            s.floor() as i64,
        );
        let (tl, ts) = (l - l0 as f64, s - s0 as f64);
        let at = |i: usize, j: i64| heights[i * m + j.rem_euclid(m as i64) as usize];
        (1.0 - tl) * ((1.0 - ts) * at(l0, s0) + ts * at(l0, s0 + 1))
            + tl * ((1.0 - ts) * at(l0 + 1, s0) + ts * at(l0 + 1, s0 + 1))
    };
    for (dir, lbl) in SETS {
        let o = Observation::open(&data.join("m3_l1b_crops").join(dir).join(lbl)).unwrap();
        let loc = o.part("LOC").unwrap();
        let (lon, lat, rad) = (
            loc.read_band(0, 0, loc.lines).unwrap(),
            loc.read_band(1, 0, loc.lines).unwrap(),
            loc.read_band(2, 0, loc.lines).unwrap(),
        );
        let diffs: Vec<f64> = (0..lon.len())
            .map(|i| rad[i] - 1_737_400.0 - bilinear(lon[i], lat[i]))
            .collect();
        let mean = diffs.iter().sum::<f64>() / diffs.len() as f64;
        let rms = (diffs.iter().map(|d| d * d).sum::<f64>() / diffs.len() as f64).sqrt();
        eprintln!("{dir}: LOC − LDEM_4 mean {mean:.0} m, rms {rms:.0} m");
        assert!(
            rms < 500.0,
            "{dir}: LOC radius and LDEM_4 disagree by {rms:.0} m RMS"
        );
    }
}

#[test]
fn band_selection_by_wavelength() {
    let Some(data) = test_data() else { return };
    let t = Observation::open(&data.join("m3_l1b_crops/forwardAscending").join(SETS[0].1)).unwrap();
    assert_eq!(t.mode, Mode::Target);
    assert_eq!(t.wavelengths, vec![446.02, 456.0, 465.98]);
    // Nearest to 1209.6 nm in target mode: bands 76 (1204.58) and 77 (1214.56), which this
    // three-band crop does not hold.
    let table = band_centres(Mode::Target);
    assert_eq!((table[76], table[77]), (1204.58, 1214.56));
    let e = t.bracket(1209.6).unwrap_err().to_string();
    assert!(
        e.contains("bands 76 and 77") && e.contains("first 3 bands"),
        "{e}"
    );
    let g =
        Observation::open(&data.join("m3_l1b_crops/reverseDescending").join(SETS[2].1)).unwrap();
    assert_eq!(g.mode, Mode::Global);
    assert_eq!(band_centres(Mode::Global)[31], 1209.57);
    let e = g.nearest_band(1209.6).unwrap_err().to_string();
    assert!(e.contains("band 31 (1209.57 nm)"), "{e}");
    assert_eq!(g.nearest_band(500.0).unwrap(), 1);
    assert!((g.solar_distance_au - 0.984326066205).abs() < 1e-15);
    // The radiance band reads as finite positive radiance.
    let r = g.rdn.read_band(1, 0, g.rdn.lines).unwrap();
    assert_eq!(r.len(), 304 * 5);
    assert!(r.iter().all(|v| v.is_finite()));
}

#[test]
fn a_missing_or_truncated_part_is_named() {
    let Some(data) = test_data() else { return };
    // linerateNotConstant ships RDN and TIM only: RDN opens, LOC is reported missing.
    let o = Observation::open(
        &data.join("m3_l1b_crops/linerateNotConstant/M3G20081118T223204_V03_L1B_cropped.LBL"),
    )
    .unwrap();
    let e = o.part("LOC").unwrap_err().to_string();
    assert!(
        e.contains("M3G20081118T223204_V03_LOC_cropped.IMG") && e.contains("not in"),
        "{e}"
    );
    // A truncated OBS file.
    let src = data.join("m3_l1b_crops/reverseDescending");
    let dir = std::env::temp_dir().join(format!("pds-m3-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for e in std::fs::read_dir(&src).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
    }
    let obs = dir.join("M3G20090106T113423_V03_OBS_cropped.IMG");
    let bytes = std::fs::read(&obs).unwrap();
    std::fs::write(&obs, &bytes[..bytes.len() - 4]).unwrap();
    let o = Observation::open(&dir.join(SETS[2].1)).unwrap();
    let e = o.part("OBS").unwrap_err().to_string();
    assert!(e.contains("OBS_cropped.IMG") && e.contains("60796"), "{e}");
    // A label whose RECORD_BYTES disagrees with its dimensions.
    let lbl = dir.join(SETS[2].1);
    let text = std::fs::read_to_string(&lbl)
        .unwrap()
        .replace("RECORD_BYTES = 3648", "RECORD_BYTES = 3600");
    std::fs::write(&lbl, text).unwrap();
    let e = Observation::open(&lbl).unwrap_err().to_string();
    assert!(
        e.contains("RECORD_BYTES in RDN_FILE") && e.contains("3600"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Every label value the reader uses is checked where it is read: a value that is not a
/// number, or out of its range, is refused naming the keyword and its line.
#[test]
fn bad_label_values_are_refused_with_keyword_and_line() {
    let Some(data) = test_data() else { return };
    let src = data.join("m3_l1b_crops/reverseDescending");
    let dir = std::env::temp_dir().join(format!("pds-m3-values-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for e in std::fs::read_dir(&src).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
    }
    let lbl = dir.join(SETS[2].1);
    let original = std::fs::read_to_string(&lbl).unwrap();
    let cases = [
        (
            "RECORD_BYTES = 3648",
            "RECORD_BYTES = abc",
            "RECORD_BYTES (line 49) in RDN_FILE",
        ),
        (
            "RECORD_BYTES = 3648",
            "RECORD_BYTES = -98",
            "RECORD_BYTES (line 49) in RDN_FILE",
        ),
        (
            "  FILE_RECORDS = 5",
            "  FILE_RECORDS = 0",
            "FILE_RECORDS (line 50) in RDN_FILE",
        ),
        ("    LINES = 5", "    LINES = 0", "LINES (line 52)"),
        (
            "    SAMPLE_BITS = 32",
            "    SAMPLE_BITS = x32",
            "SAMPLE_BITS (line 55)",
        ),
        (
            "SOLAR_DISTANCE = 0.984326066205 <AU>",
            "SOLAR_DISTANCE = 7 <AU>",
            "SOLAR_DISTANCE (line 29)",
        ),
        (
            "SOLAR_DISTANCE = 0.984326066205 <AU>",
            "SOLAR_DISTANCE = 1.2 <AU>",
            "SOLAR_DISTANCE (line 29)",
        ),
        (
            "SOLAR_DISTANCE = 0.984326066205 <AU>",
            "SOLAR_DISTANCE = far",
            "SOLAR_DISTANCE (line 29)",
        ),
        (
            "INSTRUMENT_MODE_ID = GLOBAL",
            "INSTRUMENT_MODE_ID = ZOOM",
            "INSTRUMENT_MODE_ID (line 30)",
        ),
    ];
    for (from, to, want) in cases {
        assert!(original.contains(from), "{from:?} not in the label");
        std::fs::write(&lbl, original.replacen(from, to, 1)).unwrap();
        let e = Observation::open(&lbl).unwrap_err().to_string();
        assert!(e.contains(want) && e.contains(SETS[2].1), "{to}: {e}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn solar_spectrum_table() {
    let Some(data) = test_data() else { return };
    let s = pds::solar::SolarSpectrum::read(
        &data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab"),
    )
    .unwrap();
    assert_eq!(s.rows.len(), 256);
    assert_eq!(s.rows[0], (446.019989, 1915.545166));
    // docs/formats.md: the target table interpolated at 1209.57 nm gives ≈ 478.3 W/(m² µm).
    let e = s.at(1209.57).unwrap();
    assert!((e - 478.3).abs() < 0.5, "{e}");
    assert!(s.at(100.0).is_none());
    let bad = std::env::temp_dir().join(format!("pds-solar-bad-{}", std::process::id()));
    std::fs::write(&bad, "446.0 1915.5\n456.0 x\n").unwrap();
    let err = pds::solar::SolarSpectrum::read(&bad)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("line 2") && err.contains("irradiance"),
        "{err}"
    );
    std::fs::remove_file(&bad).unwrap();
}

/// The target-mode crop turned into reflectance: r = L·d²/E with d = SOLAR_DISTANCE + OBS band 6
/// gives lunar I/F values (π·r) in the range real highland/mare surfaces have at 446 nm.
#[test]
fn radiance_to_reflectance_on_the_target_crop() {
    let Some(data) = test_data() else { return };
    let o = Observation::open(&data.join("m3_l1b_crops/forwardAscending").join(SETS[0].1)).unwrap();
    let s = pds::solar::SolarSpectrum::read(
        &data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab"),
    )
    .unwrap();
    let obs = o.part("OBS").unwrap();
    let dpath = obs.read_band(5, 0, obs.lines).unwrap();
    let l = o.rdn.read_band(0, 0, o.rdn.lines).unwrap();
    let e = s.at(o.wavelengths[0]).unwrap();
    let iof: Vec<f64> = l
        .iter()
        .zip(&dpath)
        .map(|(l, dd)| {
            std::f64::consts::PI * pds::solar::reflectance(*l, o.solar_distance_au + dd, e)
        })
        .collect();
    let mean = iof.iter().sum::<f64>() / iof.len() as f64;
    assert!(
        dpath.iter().all(|d| d.abs() < 0.01),
        "band 6 is a small offset from the scene mean"
    );
    assert!(mean > 0.01 && mean < 0.3, "mean I/F {mean}");
}

#[test]
fn start_and_stop_times_are_read_from_the_labels() {
    let Some(data) = test_data() else { return };
    for ((dir, lbl), (start, stop)) in SETS.into_iter().zip([
        ("2009-06-30T08:34:07", "2009-06-30T08:34:36"),
        ("2008-11-29T17:14:31", "2008-11-29T17:14:57"),
        ("2009-01-06T11:34:23", "2009-01-06T11:34:47"),
    ]) {
        let path = data.join("m3_l1b_crops").join(dir).join(lbl);
        let o = Observation::open(&path).unwrap();
        let (a, b) = (o.start_time.unwrap(), o.stop_time.unwrap());
        assert_eq!(a.to_string()[..19], *start, "{dir}");
        assert_eq!(b.to_string()[..19], *stop, "{dir}");
        // Each line of the crop's TIM table: UTC, year, and the day of the year counted from
        // 0 at January 1st, 00:00 (the table's own independent form of the same instant).
        let tim = path.with_file_name(lbl.replace("L1B", "TIM").replace(".LBL", ".TAB"));
        for row in std::fs::read_to_string(&tim).unwrap().lines() {
            let f: Vec<&str> = row.split_whitespace().collect();
            let t = pds::time::UtcTime::parse(f[1]).unwrap();
            let jan1 = pds::time::UtcTime::parse(&format!("{}-01-01", f[2])).unwrap();
            let doy: f64 = f[3].parse().unwrap();
            let days = t.julian_date() - jan1.julian_date();
            assert!((days - doy).abs() * 86_400.0 < 1e-3, "{dir}: {row}: {days}");
            // Every line lies between START_TIME and STOP_TIME (which M3 writes to ±2 s).
            let (da, db) = (
                t.julian_date() - a.julian_date(),
                b.julian_date() - t.julian_date(),
            );
            assert!(da * 86_400.0 > -2.0 && db * 86_400.0 > -2.0, "{dir}: {row}");
        }
    }
}

#[test]
fn missing_value_constants_are_absent_times_and_bad_times_name_their_keyword() {
    let label = pds::parse_label(
        b"START_TIME = N/A\r\nSTOP_TIME = 2009-13-01T00:00:00\r\nOTHER_TIME = \"UNK\"\r\nEND\r\n",
    )
    .unwrap();
    let path = std::path::Path::new("X.LBL");
    assert_eq!(pds::m3::time_of(path, &label, "START_TIME").unwrap(), None);
    assert_eq!(pds::m3::time_of(path, &label, "OTHER_TIME").unwrap(), None);
    assert_eq!(pds::m3::time_of(path, &label, "ABSENT_TIME").unwrap(), None);
    let e = pds::m3::time_of(path, &label, "STOP_TIME")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("X.LBL") && e.contains("STOP_TIME (line 2)") && e.contains("month 13"),
        "{e}"
    );
}
