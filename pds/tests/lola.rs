//! LDEM_4 (the full global 4 px/deg LOLA GDR) read through its label.

use pds::lola::LolaDem;

mod common;
use common::test_data;

#[test]
fn ldem4_extremes_fall_where_the_manifest_says() {
    let Some(data) = test_data() else { return };
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
    let Some(data) = test_data() else { return };
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
    assert_eq!(km.offset, Some(1_737_400_000.0));
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

/// A polar stereographic LDEM label of N × N int16 pixels (docs/formats.md, DSMAP_POLAR.CAT).
fn polar_product(dir: &std::path::Path, north: bool, n: usize, scale_m: f64) -> std::path::PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    let lat = if north { 90 } else { -90 };
    let label = format!(
        "PDS_VERSION_ID = PDS3\r\n^IMAGE = \"POLAR.IMG\"\r\nOBJECT = IMAGE\r\n  LINES = {n}\r\n  LINE_SAMPLES = {n}\r\n  SAMPLE_TYPE = LSB_INTEGER\r\n  SAMPLE_BITS = 16\r\n  UNIT = METER\r\n  SCALING_FACTOR = 0.5\r\n  OFFSET = 1737400.\r\nEND_OBJECT = IMAGE\r\nOBJECT = IMAGE_MAP_PROJECTION\r\n  MAP_PROJECTION_TYPE = \"POLAR STEREOGRAPHIC\"\r\n  A_AXIS_RADIUS = 1737.4 <KM>\r\n  CENTER_LATITUDE = {lat} <DEG>\r\n  CENTER_LONGITUDE = 0 <DEG>\r\n  MAP_SCALE = {scale_m} <METERS/PIXEL>\r\n  LINE_PROJECTION_OFFSET = {o}\r\n  SAMPLE_PROJECTION_OFFSET = {o}\r\nEND_OBJECT = IMAGE_MAP_PROJECTION\r\nEND\r\n",
        o = n as f64 / 2.0 - 0.5
    );
    let path = dir.join("POLAR.LBL");
    std::fs::write(&path, label).unwrap();
    let mut img = Vec::new();
    for i in 0..n * n {
        img.extend_from_slice(&((i % 30000) as i16).to_le_bytes());
    }
    std::fs::write(dir.join("POLAR.IMG"), img).unwrap();
    path
}

#[test]
fn polar_stereographic_follows_the_catalogue_orientation() {
    let dir = std::env::temp_dir().join(format!("pds-polar-{}", std::process::id()));
    for north in [true, false] {
        let dem = LolaDem::open(&polar_product(&dir, north, 100, 1000.0)).unwrap();
        // DSMAP_POLAR.CAT: "In the north, Longitude 0 extends straight down from the center and
        // Longitude 90 East extends to the right. In the south, Longitude 0 extends straight up
        // from the center, and Longitude 90 East extends to the right."
        let c = 49.5;
        let lon = |l: f64, s: f64| dem.lonlat(l, s).0;
        let (down, up, right, left) = (
            lon(c + 30.0, c),
            lon(c - 30.0, c),
            lon(c, c + 30.0),
            lon(c, c - 30.0),
        );
        if north {
            assert!(
                down.abs() < 1e-9 && (up - 180.0).abs() < 1e-9,
                "{down} {up}"
            );
        } else {
            assert!(
                up.abs() < 1e-9 && (down - 180.0).abs() < 1e-9,
                "{down} {up}"
            );
        }
        assert!((right - 90.0).abs() < 1e-9 && (left - 270.0).abs() < 1e-9);
        // Latitude: r = 2R·tan(colat/2); 30 px × 1 km from the pole.
        let colat = 2.0 * (0.5 * 30_000.0 / 1_737_400.0f64).atan().to_degrees();
        let lat = dem.lonlat(c, c + 30.0).1;
        assert!(
            (lat.abs() - (90.0 - colat)).abs() < 1e-12
                && lat.signum() == if north { 1.0 } else { -1.0 }
        );
        // pixel() inverts lonlat() everywhere in the product.
        for (l, s) in [(0.0, 0.0), (12.25, 80.5), (99.0, 3.0), (49.5, 60.0)] {
            let (lo, la) = dem.lonlat(l, s);
            let (l2, s2) = dem.pixel(lo, la);
            assert!(
                (l2 - l).abs() < 1e-8 && (s2 - s).abs() < 1e-8,
                "{l} {s} → {l2} {s2}"
            );
        }
        assert_eq!(dem.read_heights(1, 1).unwrap()[3], 103.0 * 0.5);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
#[ignore = "needs PROJ's `proj` (proj-bin); .ci/run runs it"]
fn polar_stereographic_matches_proj() {
    let proj = common::external_tool("proj", "proj-bin");
    let dir = std::env::temp_dir().join(format!("pds-polar-proj-{}", std::process::id()));
    for north in [true, false] {
        let dem = LolaDem::open(&polar_product(&dir, north, 400, 240.0)).unwrap();
        let pixels = [
            (0.0, 0.0),
            (10.5, 390.25),
            (399.0, 399.0),
            (200.0, 17.0),
            (123.0, 321.0),
        ];
        let mut input = String::new();
        for &(l, s) in &pixels {
            let (lon, lat) = dem.lonlat(l, s);
            input.push_str(&format!("{lon:.12} {lat:.12}\n"));
        }
        let def = format!(
            "+proj=stere +lat_0={} +lon_0=0 +k=1 +R=1737400",
            if north { 90 } else { -90 }
        );
        let out = common::proj_forward(&proj, &def, &input);
        for (&(l, s), row) in pixels.iter().zip(out.lines()) {
            let v: Vec<f64> = row.split_whitespace().map(|t| t.parse().unwrap()).collect();
            // Map x = X, map y = −Y (lines grow downwards).
            let (x, y) = ((s - 199.5) * 240.0, -(l - 199.5) * 240.0);
            assert!(
                (v[0] - x).abs() < 1e-3 && (v[1] - y).abs() < 1e-3,
                "north={north} ({l},{s}): proj {row}, want {x} {y}"
            );
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// LDEM_4's label with one value replaced: every value the reader uses is refused by keyword
/// and line when it cannot be right (none of these used to be: `SCALING_FACTOR = abc` read as
/// 1 doubled every height).
#[test]
fn impossible_label_values_are_refused_with_keyword_and_line() {
    let Some(data) = test_data() else { return };
    let text = std::fs::read_to_string(data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    let dir = std::env::temp_dir().join(format!("pds-bad-lola-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let img = dir.join("LDEM_4.IMG");
    if !img.exists() {
        std::os::unix::fs::symlink(data.join("lola_ldem4/LDEM_4.IMG"), &img).unwrap();
    }
    let cases = [
        (
            "SCALING_FACTOR        = 0.5",
            "SCALING_FACTOR        = abc",
            "SCALING_FACTOR (line 64)",
        ),
        (
            "SCALING_FACTOR        = 0.5",
            "SCALING_FACTOR        = 0",
            "SCALING_FACTOR (line 64)",
        ),
        (
            "OFFSET                = 1737400.",
            "OFFSET                = x",
            "OFFSET (line 65)",
        ),
        (
            "MAP_SCALE                    = 7580.84 <m/pix>",
            "MAP_SCALE                    = 0 <m/pix>",
            "MAP_SCALE",
        ),
        (
            "CENTER_LONGITUDE             = 180 <deg>",
            "CENTER_LONGITUDE             = 1e308 <deg>",
            "CENTER_LONGITUDE (line 90)",
        ),
        (
            "CENTER_LATITUDE              = 0 <deg>",
            "CENTER_LATITUDE              = 90 <deg>",
            "CENTER_LATITUDE (line 89)",
        ),
        (
            "LINE_PROJECTION_OFFSET       = 359.5 <pix>",
            "LINE_PROJECTION_OFFSET       = 1e300 <pix>",
            "LINE_PROJECTION_OFFSET (line 103)",
        ),
        (
            "RECORD_BYTES              = 2880",
            "RECORD_BYTES              = -98",
            "RECORD_BYTES (line 48)",
        ),
        // Values that could each be right, but not with the rest of the label: the projection
        // then places the edges elsewhere than the label states (by 1° and by one pixel, 0.25°)
        // or the scale disagrees with the radius (Mars's).
        (
            "CENTER_LONGITUDE             = 180 <deg>",
            "CENTER_LONGITUDE             = 179 <deg>",
            "WESTERNMOST_LONGITUDE (line 101)",
        ),
        (
            "SAMPLE_PROJECTION_OFFSET     = 719.5 <pix>",
            "SAMPLE_PROJECTION_OFFSET     = 720.5 <pix>",
            "WESTERNMOST_LONGITUDE (line 101)",
        ),
        (
            "LINE_PROJECTION_OFFSET       = 359.5 <pix>",
            "LINE_PROJECTION_OFFSET       = 360.5 <pix>",
            "MAXIMUM_LATITUDE (line 99)",
        ),
        (
            "A_AXIS_RADIUS                = 1737.4 <km>",
            "A_AXIS_RADIUS                = 3396.2 <km>",
            "MAP_SCALE (line 98)",
        ),
        (
            "^IMAGE                    = \"LDEM_4.IMG\"",
            "^IMAGE                    = (\"LDEM_4.IMG\", 0)",
            "^IMAGE",
        ),
    ];
    for (from, to, want) in cases {
        assert!(text.contains(from), "{from}");
        let lbl = dir.join("LDEM_4.LBL");
        std::fs::write(&lbl, text.replace(from, to)).unwrap();
        let err = LolaDem::open(&lbl).unwrap_err().to_string();
        assert!(
            err.contains(want) && err.contains("LDEM_4.LBL"),
            "{to}: {err}"
        );
    }
    // The untouched label still opens from there.
    std::fs::write(dir.join("LDEM_4.LBL"), &text).unwrap();
    LolaDem::open(&dir.join("LDEM_4.LBL")).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
}
