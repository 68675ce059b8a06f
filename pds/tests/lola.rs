//! LDEM_4 (the full global 4 px/deg LOLA GDR) read through its label.

use pds::lola::LolaDem;

mod common;
use common::shared_data;

#[test]
fn ldem4_extremes_fall_where_the_manifest_says() {
    let Some(data) = shared_data() else { return };
    let dem = LolaDem::open(&data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    assert_eq!((dem.lines(), dem.samples()), (720, 1440));
    assert!((dem.map_scale_m - 7580.84).abs() < 1e-9);
    assert_eq!(dem.radius_m, 1_737_400.0);
    let dn = dem.read_dn(0, dem.lines()).unwrap();
    let (imin, min) = dn
        .iter()
        .enumerate()
        .fold((0, f64::MAX), |a, (i, &v)| if v < a.1 { (i, v) } else { a });
    let (imax, max) = dn
        .iter()
        .enumerate()
        .fold((0, f64::MIN), |a, (i, &v)| if v > a.1 { (i, v) } else { a });
    assert_eq!((min, max), (-17757.0, 21008.0));
    let at = |i: usize| dem.lonlat((i / 1440) as f64, (i % 1440) as f64);
    let (lon, lat) = at(imin);
    assert!(
        (lon - 187.625).abs() < 1e-9 && (lat + 70.375).abs() < 1e-9,
        "min at {lon} {lat}"
    );
    let (lon, lat) = at(imax);
    assert!(
        (lon - 201.375).abs() < 1e-9 && (lat - 5.375).abs() < 1e-9,
        "max at {lon} {lat}"
    );
    // pixel() inverts lonlat(), with longitudes given in either convention.
    let (l, s) = dem.pixel(187.625, -70.375);
    assert!((l - (imin / 1440) as f64).abs() < 1e-9 && (s - (imin % 1440) as f64).abs() < 1e-9);
    let (_, s) = dem.pixel(-172.375, -70.375);
    assert!((s - (imin % 1440) as f64).abs() < 1e-9);
    // Heights are DN × 0.5 m; a window read matches the full read.
    let h = dem.read_heights(100, 2).unwrap();
    assert_eq!(h.len(), 2880);
    assert_eq!(h[5], dn[100 * 1440 + 5] * 0.5);
}

#[test]
fn truncated_and_mislabelled_products_are_reported() {
    let Some(data) = shared_data() else { return };
    let dir = std::env::temp_dir().join(format!("pds-lola-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let label = std::fs::read_to_string(data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    std::fs::write(dir.join("LDEM_4.LBL"), &label).unwrap();
    // Truncated image (lower-case name on disk: found case-insensitively).
    let img = std::fs::read(data.join("lola_ldem4/LDEM_4.IMG")).unwrap();
    std::fs::write(dir.join("ldem_4.img"), &img[..1000]).unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("ldem_4.img") && e.contains("1000 bytes") && e.contains("2073600"),
        "{e}"
    );
    // Unknown sample type.
    std::fs::write(dir.join("ldem_4.img"), &img).unwrap();
    std::fs::write(
        dir.join("LDEM_4.LBL"),
        label.replace("LSB_INTEGER", "VAX_REAL"),
    )
    .unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("SAMPLE_TYPE") && e.contains("VAX_REAL"), "{e}");
    // A kilometre product (the `*_FLOAT` convention) reads in metres all the same.
    std::fs::write(dir.join("ldem_4.img"), &img).unwrap();
    std::fs::write(
        dir.join("LDEM_4.LBL"),
        label.replace(
            "UNIT                  = METER",
            "UNIT                  = KILOMETER",
        ),
    )
    .unwrap();
    let km = LolaDem::open(&dir.join("LDEM_4.LBL")).unwrap();
    assert_eq!(km.scaling_factor, 500.0);
    assert_eq!(km.offset, 1_737_400_000.0);
    std::fs::write(
        dir.join("LDEM_4.LBL"),
        label.replace(
            "UNIT                  = METER",
            "UNIT                  = FURLONG",
        ),
    )
    .unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("UNIT") && e.contains("FURLONG"), "{e}");
    // Absurd dimensions: refused against the file length, nothing allocated.
    std::fs::write(
        dir.join("LDEM_4.LBL"),
        label.replace(
            "LINES                 = 720",
            "LINES                 = 9000000000000",
        ),
    )
    .unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("overflow") || e.contains("truncated"), "{e}");
    // Missing pointer target.
    std::fs::remove_file(dir.join("ldem_4.img")).unwrap();
    std::fs::write(dir.join("LDEM_4.LBL"), &label).unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("LDEM_4.IMG") && e.contains("not in"), "{e}");
    // A pointer that tries to leave the directory.
    std::fs::write(
        dir.join("LDEM_4.LBL"),
        label.replace(
            "^IMAGE                    = \"LDEM_4.IMG\"",
            "^IMAGE = \"../../etc/passwd\"",
        ),
    )
    .unwrap();
    let e = LolaDem::open(&dir.join("LDEM_4.LBL"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not a plain file name"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}
