//! Every real label in tests/data parses, and the values the readers rely on are read right.

use pds::{parse_label, Pointer};
use std::path::PathBuf;

mod common;
use common::test_data;

fn labels(dir: &std::path::Path, out: &mut Vec<PathBuf>) {
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            labels(&p, out);
        } else if p.extension().is_some_and(|x| x.eq_ignore_ascii_case("lbl")) {
            out.push(p);
        }
    }
}

#[test]
fn every_vendored_label_parses() {
    let Some(data) = test_data() else { return };
    let mut all = Vec::new();
    labels(&data, &mut all);
    assert!(all.len() >= 7, "found only {all:?}");
    for p in &all {
        let bytes = std::fs::read(p).unwrap();
        let l = parse_label(&bytes).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
        assert!(l.get("PDS_VERSION_ID").is_some(), "{}", p.display());
    }
}

#[test]
fn lola_label_values() {
    let Some(data) = test_data() else { return };
    let l = parse_label(&std::fs::read(data.join("lola_ldem4/LDEM_4.LBL")).unwrap()).unwrap();
    let file = l.child("UNCOMPRESSED_FILE").unwrap();
    assert_eq!(
        file.pointer("IMAGE").unwrap().unwrap(),
        Pointer::File("LDEM_4.IMG".into())
    );
    let img = file.child("IMAGE").unwrap();
    assert_eq!(img.get("LINES").unwrap().as_i64(), Some(720));
    assert_eq!(img.get("SCALING_FACTOR").unwrap().as_f64(), Some(0.5));
    assert_eq!(img.get("OFFSET").unwrap().as_f64(), Some(1737400.0));
    let map = l.child("IMAGE_MAP_PROJECTION").unwrap();
    assert_eq!(map.get("MAP_SCALE").unwrap().unit(), Some("m/pix"));
    assert_eq!(
        map.get("SAMPLE_PROJECTION_OFFSET").unwrap().as_f64(),
        Some(719.5)
    );
    assert_eq!(
        map.get("MAP_PROJECTION_TYPE").unwrap().as_str(),
        Some("SIMPLE CYLINDRICAL")
    );
    assert_eq!(
        map.get("FIRST_STANDARD_PARALLEL").unwrap().as_str(),
        Some("N/A")
    );
}

#[test]
fn m3_label_values() {
    let Some(data) = test_data() else { return };
    let l = parse_label(
        &std::fs::read(
            data.join("m3_l1b_crops/reverseDescending/M3G20090106T113423_V03_L1B_cropped.LBL"),
        )
        .unwrap(),
    )
    .unwrap();
    assert_eq!(
        l.get("SOLAR_DISTANCE").unwrap().as_f64(),
        Some(0.984326066205)
    );
    assert_eq!(l.get("SOLAR_DISTANCE").unwrap().unit(), Some("AU"));
    assert_eq!(
        l.get("INSTRUMENT_MODE_ID").unwrap().as_str(),
        Some("GLOBAL")
    );
    assert_eq!(l.get("CH1:SWATH_WIDTH").unwrap().as_i64(), Some(304));
    let obs = l.child("OBS_FILE").unwrap();
    assert_eq!(
        obs.pointer("OBS_IMAGE").unwrap().unwrap(),
        Pointer::File("M3G20090106T113423_V03_OBS_cropped.IMG".into())
    );
    assert_eq!(
        obs.child("OBS_IMAGE")
            .unwrap()
            .get("BANDS")
            .unwrap()
            .as_i64(),
        Some(10)
    );
    let names = obs.child("obs_image").unwrap().get("BAND_NAME").unwrap();
    match names {
        pds::Value::Sequence(v) => assert_eq!(v.len(), 10),
        other => panic!("{other:?}"),
    }
}

#[test]
fn torture_label_from_isis() {
    let Some(data) = test_data() else { return };
    let l = parse_label(&std::fs::read(data.join("pds3_syntax/BILtestData_cropped.LBL")).unwrap())
        .unwrap();
    // Multi-line strings are folded and objects nest.
    assert!(!l.root.children.is_empty());
    let n: usize = l.root.children.iter().map(|c| c.attributes.len()).sum();
    assert!(n > 10, "{n}");
    // The original PDS formatting (padded to 80 columns, CRLF) keeps its times readable.
    let path = std::path::Path::new("BILtestData_cropped.LBL");
    let start = pds::m3::time_of(path, &l, "START_TIME").unwrap().unwrap();
    let stop = pds::m3::time_of(path, &l, "STOP_TIME").unwrap().unwrap();
    assert_eq!(start.to_string(), "2008-11-18T22:26:04.000");
    assert_eq!(
        ((stop.julian_date() - start.julian_date()) * 86_400.0).round(),
        120.0
    );
}
