//! The command line as a user meets it.

use std::process::Command;

#[path = "../pds/tests/common/mod.rs"]
mod common;
use common::test_data;

fn sfsfuse() -> Command {
    Command::new(env!("CARGO_BIN_EXE_sfsfuse"))
}

/// The JSON a successful command printed (its stderr shown when it failed).
/// `sfsfuse inspect --json` of `path`, which must succeed.
fn inspect_json(path: &std::path::Path) -> serde_json::Value {
    json_of(
        &sfsfuse()
            .args(["inspect", "--json"])
            .arg(path)
            .output()
            .unwrap(),
    )
}

/// Copy every file of `src` into `dir`.
fn copy_files(src: &std::path::Path, dir: &std::path::Path) {
    for e in std::fs::read_dir(src).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
    }
}

fn json_of(o: &std::process::Output) -> serde_json::Value {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn scratch(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("sfsfuse-cli-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn demo_writes_products_and_a_json_report() {
    let out = scratch("demo");
    let o = sfsfuse()
        .args(["demo", "--size", "48", "--json", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    let r = json_of(&o);
    assert_eq!(r["size"], 48);
    for k in [
        "input_rmse_m",
        "result_rmse_m",
        "albedo_rmse",
        "fusion_seconds",
        "megapixels_per_second",
    ] {
        assert!(
            r[k].as_f64().is_some_and(|v| v.is_finite() && v > 0.0),
            "{k}: {}",
            r[k]
        );
    }
    assert!(r["iterations"].as_u64().unwrap() > 0);
    // Every stage reports E and its terms per iteration, and E never rises.
    let stages = r["stages"].as_array().unwrap();
    assert_eq!(
        stages.len(),
        r["params"]["albedo_sigmas"].as_array().unwrap().len()
    );
    for st in stages {
        let its = st["iterations"].as_array().unwrap();
        let totals: Vec<f64> = its
            .iter()
            .map(|i| i["energy"]["total"].as_f64().unwrap())
            .collect();
        assert!(totals.windows(2).all(|w| w[1] <= w[0]), "{totals:?}");
        for i in its {
            let e = &i["energy"];
            let sum = e["intensity"].as_f64().unwrap()
                + r["params"]["delta"].as_f64().unwrap() * e["dem"].as_f64().unwrap()
                + r["params"]["eta"].as_f64().unwrap() * e["membrane"].as_f64().unwrap()
                + e["tie"].as_f64().unwrap()
                + e["shadow"].as_f64().unwrap();
            assert!((sum - e["total"].as_f64().unwrap()).abs() <= 1e-9 * sum.abs());
        }
    }
    for f in [
        "dem.tif",
        "albedo.tif",
        "residual.tif",
        "input_dem.tif",
        "truth_dem.tif",
        "image.tif",
        "quicklook.png",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    let dem = sfsfuse::export::read_tiff(&out.join("dem.tif")).unwrap();
    assert_eq!(dem.data.dim(), (48, 48));
    assert!(dem.data.iter().all(|v| v.is_finite()));
    // The demo grid: 140 m pixels centred on the projection origin.
    assert_eq!(
        dem.geotransform,
        Some([-3360.0, 140.0, 0.0, 3360.0, 0.0, -140.0])
    );
    let png = std::fs::read(out.join("quicklook.png")).unwrap();
    // IHDR width and height: 3 × 2 titled panels of 48 px with 12-px margins (24-px title,
    // 40-px colour-bar strip).
    assert_eq!(
        u32::from_be_bytes([png[16], png[17], png[18], png[19]]),
        3 * 48 + 4 * 12
    );
    assert_eq!(
        u32::from_be_bytes([png[20], png[21], png[22], png[23]]),
        2 * (24 + 48 + 40) + 3 * 12
    );
    let leftovers: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".tmp"))
        .collect();
    assert!(leftovers.is_empty());
    // The error panel's span: by default within the errors' range (the 99th percentile of
    // |fused − true|), or as given, so that quick looks of several runs compare.
    let truth = sfsfuse::export::read_tiff(&out.join("truth_dem.tif")).unwrap();
    let largest = (&dem.data - &truth.data)
        .iter()
        .fold(0.0f64, |m, &e| m.max(e.abs()));
    let auto = r["quicklook_error_limit_m"].as_f64().unwrap();
    assert!(auto > 0.0 && auto <= largest, "{auto} vs {largest}");
    let o = sfsfuse()
        .args([
            "demo",
            "--size",
            "48",
            "--json",
            "--error-limit",
            "7.5",
            "--out",
        ])
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(json_of(&o)["quicklook_error_limit_m"].as_f64(), Some(7.5));
    assert_ne!(std::fs::read(out.join("quicklook.png")).unwrap(), png);
    for bad in ["0", "-2", "nan", "inf"] {
        let o = sfsfuse()
            .args([
                "demo",
                "--size",
                "16",
                &format!("--error-limit={bad}"),
                "--out",
            ])
            .arg(&out)
            .output()
            .unwrap();
        assert!(!o.status.success(), "--error-limit {bad}");
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(e.contains("--error-limit"), "{e}");
    }
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn bad_arguments_fail_with_a_clear_message() {
    let o = sfsfuse()
        .args(["demo", "--size", "8", "--out"])
        .arg(scratch("small"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("--size 8"), "{e}");

    // The output directory cannot be created under a regular file: the error names the path.
    let base = scratch("file");
    std::fs::create_dir_all(&base).unwrap();
    let file = base.join("not-a-dir");
    std::fs::write(&file, b"x").unwrap();
    let o = sfsfuse()
        .args(["demo", "--size", "16", "--out"])
        .arg(file.join("out"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(e.contains("not-a-dir"), "{e}");
    std::fs::remove_dir_all(&base).unwrap();
}

#[test]
fn inspect_describes_real_products() {
    let Some(data) = test_data() else { return };
    let r = inspect_json(&data.join("lola_ldem4/LDEM_4.LBL"));
    assert_eq!(r["kind"], "LOLA GDR");
    assert_eq!(r["lines"], 720);
    // MANIFEST.md: DN −17757 … 21008, heights are DN × 0.5 m.
    assert_eq!(r["height_m"]["min"], -8878.5);
    assert_eq!(r["height_m"]["max"], 10504.0);
    assert_eq!(r["height_problem"], serde_json::Value::Null);
    assert_eq!(r["longitude_deg"]["min"], 0.0);
    assert_eq!(r["latitude_deg"]["max"], 90.0);
    // The same label over data that are all the int16 fill (−16 384 m): described, with a
    // warning that `run` refuses such heights.
    let dir = scratch("inspect-fill");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data.join("lola_ldem4/LDEM_4.LBL"), dir.join("LDEM_4.LBL")).unwrap();
    std::fs::write(
        dir.join("LDEM_4.IMG"),
        i16::MIN.to_le_bytes().repeat(720 * 1440),
    )
    .unwrap();
    let o = sfsfuse()
        .arg("inspect")
        .arg(dir.join("LDEM_4.LBL"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{text}");
    assert!(
        text.contains("-16384.0000 … -16384.0000 m above the 1737.4 km sphere")
            && text.contains("warning        heights outside -12000 … 12000 m are not the Moon's"),
        "{text}"
    );
    std::fs::remove_dir_all(&dir).unwrap();

    let r = inspect_json(
        &data.join("m3_l1b_crops/forwardDescending/M3G20081129T171431_V03_L1B_cropped.LBL"),
    );
    assert_eq!(r["kind"], "M3 L1B");
    assert_eq!(r["mode"], "GLOBAL");
    assert_eq!(r["samples"], 304);
    // MANIFEST.md: ~29.1°S, 173.7–175.3°E.
    let (lat0, lat1) = (
        r["latitude_deg"]["min"].as_f64().unwrap(),
        r["latitude_deg"]["max"].as_f64().unwrap(),
    );
    let (lon0, lon1) = (
        r["longitude_deg"]["min"].as_f64().unwrap(),
        r["longitude_deg"]["max"].as_f64().unwrap(),
    );
    assert!(lat0 > -29.5 && lat1 < -28.7, "{lat0} {lat1}");
    assert!(
        (lon0 - 173.7).abs() < 0.2 && (lon1 - 175.3).abs() < 0.2,
        "{lon0} {lon1}"
    );
    // M3 global mode from the 100 km orbit images ≈ 140 m pixels; across the track here,
    // MANIFEST.md's 173.7–175.3°E at 29.1°S over 304 samples: 1.6° × cos 29.1° × 30.32 km/° /
    // 304 ≈ 139 m. LOC's (across · along)^½ must be near that.
    let px = r["pixel_size_m"].as_f64().unwrap();
    assert!((130.0..165.0).contains(&px), "{px}");

    let o = sfsfuse()
        .arg("inspect")
        .arg(data.join("pds3_syntax/BILtestData_cropped.LBL"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("BILtestData_cropped.LBL"));
    let o = sfsfuse()
        .arg("inspect")
        .arg(data.join("lola_ldem4/LDEM_4.IMG"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("LDEM_4.IMG is a data file") && e.contains("LDEM_4.LBL instead"),
        "{e}"
    );
}

/// `inspect` measures an observation's detector column striping over its lines, at the band
/// nearest the run's default 1209.6 nm: 2 % drawn per column (`synth --column-striping 0.02`,
/// 128 lines: 4 blocks) reads as about that, the same scene without stripes as none, and a
/// crop whose bands stop short of 1209.6 nm says why it is not measured.
#[test]
fn inspect_measures_detector_column_striping() {
    let base = scratch("inspect-striping");
    let write = |name: &str, extra: &[&str]| {
        let out = base.join(name);
        let o = sfsfuse()
            .args(["synth", "--size", "128", "--out"])
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        inspect_json(&out.join("M3G20991231T000000_V03_L1B.LBL"))
    };
    let striped = write("striped", &["--column-striping", "0.02"]);
    let c = &striped["column_striping"];
    let rms = c["stripe_rms"].as_f64().unwrap();
    assert!((0.014..0.026).contains(&rms), "{c}");
    assert!(
        c["columns"].as_u64().unwrap() >= 120 && c["blocks"] == 4,
        "{c}"
    );
    assert_eq!(striped["column_striping_nm"], 1209.57);
    let clean = write("clean", &[]);
    let c = &clean["column_striping"];
    assert!(c["columns"] == 0 && c["stripe_rms"] == 0.0, "{c}");
    assert!(clean["column_striping_note"].is_null(), "{clean}");
    std::fs::remove_dir_all(&base).unwrap();
    let Some(data) = test_data() else { return };
    let r = inspect_json(
        &data.join("m3_l1b_crops/forwardDescending/M3G20081129T171431_V03_L1B_cropped.LBL"),
    );
    let note = r["column_striping_note"].as_str().unwrap();
    assert!(
        note.contains("not measured") && note.contains("only the first 3 bands"),
        "{note}"
    );
}

/// A part the label names whose file is cut short is bad input: `inspect` still describes the
/// rest, then names the file and the bytes the label needs and exits non-zero. A part whose
/// file is absent is only described as absent (exit 0).
#[test]
fn inspect_refuses_a_truncated_part_and_describes_an_absent_one() {
    let Some(data) = test_data() else { return };
    let src = data.join("m3_l1b_crops/forwardDescending");
    let dir = scratch("inspect-truncated");
    std::fs::create_dir_all(&dir).unwrap();
    copy_files(&src, &dir);
    let label = dir.join("M3G20081129T171431_V03_L1B_cropped.LBL");
    let loc = dir.join("M3G20081129T171431_V03_LOC_cropped.IMG");
    // The label's LOC: 5 lines × 304 samples × 3 bands of 8-byte reals = 36 480 bytes.
    assert_eq!(std::fs::metadata(&loc).unwrap().len(), 36480);
    std::fs::write(&loc, [0u8; 7]).unwrap();
    let o = sfsfuse().arg("inspect").arg(&label).output().unwrap();
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(1), "{out}{err}");
    assert!(
        out.contains("radiance b0") && out.contains("incidence"),
        "{out}"
    );
    assert!(
        err.contains("M3G20081129T171431_V03_LOC_cropped.IMG")
            && err.contains("file is 7 bytes but the label needs 36480"),
        "{err}"
    );
    std::fs::remove_file(&loc).unwrap();
    let r = inspect_json(&label);
    assert!(
        r["loc_problem"]
            .as_str()
            .is_some_and(|p| p.contains("which is not in")),
        "{r}"
    );
    assert_eq!(r["loc_unreadable"], false);
    assert!(r["incidence_deg"]["min"].is_number(), "{r}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `inspect` shows an observation's illumination: the incidence range equals the range of
/// OBS band 2 read straight from the file's bytes (LINE_INTERLEAVED float32, 10 bands).
#[test]
fn inspect_shows_the_illumination_and_describes_geotiffs() {
    let data = test_data().unwrap();
    let dir = data.join("m3_l1b_crops/reverseDescending");
    let r = inspect_json(&dir.join("M3G20090106T113423_V03_L1B_cropped.LBL"));
    let bytes = std::fs::read(dir.join("M3G20090106T113423_V03_OBS_cropped.IMG")).unwrap();
    let samples = 304;
    let zen: Vec<f64> = bytes
        .chunks_exact(4)
        .enumerate()
        .filter(|(k, _)| (k / samples) % 10 == 1)
        .map(|(_, c)| f32::from_le_bytes([c[0], c[1], c[2], c[3]]) as f64)
        .collect();
    let (lo, hi) = zen
        .iter()
        .fold((f64::MAX, f64::MIN), |m, &v| (m.0.min(v), m.1.max(v)));
    assert_eq!(r["incidence_deg"]["min"].as_f64().unwrap(), lo);
    assert_eq!(r["incidence_deg"]["max"].as_f64().unwrap(), hi);
    for k in ["emission_deg", "phase_deg", "sun_azimuth_deg"] {
        assert!(
            r[k]["min"].as_f64().unwrap() <= r[k]["max"].as_f64().unwrap(),
            "{k}"
        );
    }
    // The label's times, and OBS's Sun against the ephemeris at them (0.003° measured).
    assert_eq!(r["start_time"], "2009-01-06T11:34:23.000");
    assert_eq!(r["stop_time"], "2009-01-06T11:34:47.000");
    assert!(
        r["sun_ephemeris"]["worst_deg"].as_f64().unwrap() < 0.02,
        "{r}"
    );

    // A GeoTIFF we write is described: size, CRS, pixel, band metadata.
    let tmp = std::env::temp_dir().join(format!("sfsfuse-inspect-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let tif = tmp.join("h.tif");
    let grid = sfsfuse::grid::Grid::new(
        sfsfuse::grid::Crs::Stereographic {
            lat_0: -13.4,
            lon_0: 357.2,
        },
        20,
        30,
        -2100.0,
        1400.0,
        140.0,
    )
    .unwrap();
    let a = ndarray::Array2::from_shape_fn((20, 30), |(i, j)| (i * 30 + j) as f64);
    sfsfuse::export::write_geotiff(
        &tif,
        &grid,
        a.view(),
        &sfsfuse::export::BandInfo {
            description: "test heights",
            unit: "m",
            metadata: &[],
        },
    )
    .unwrap();
    let r = inspect_json(&tif);
    assert_eq!(r["kind"], "GeoTIFF");
    assert_eq!(
        (r["width"].as_u64(), r["height"].as_u64()),
        (Some(30), Some(20))
    );
    assert_eq!(r["pixel_m"], 140.0);
    assert!(r["crs"]
        .as_str()
        .unwrap()
        .contains("+proj=stere +lat_0=-13.4"));
    assert!(r["metadata"].to_string().contains("test heights"), "{r}");
    std::fs::remove_dir_all(&tmp).unwrap();
}

/// `bench --pipeline` runs each configuration `--repeat` times, keeps every sample and compares
/// the fastest runs.
#[test]
fn the_pipeline_bench_compares_the_fastest_of_its_repeated_runs() {
    let o = sfsfuse()
        .args([
            "bench",
            "--pipeline",
            "--size",
            "128",
            "--tile",
            "64",
            "--repeat",
            "2",
            "--json",
        ])
        .output()
        .unwrap();
    let r = json_of(&o);
    assert_eq!(r["tiles"], 4, "{r}");
    for (k, samples) in [
        ("single_seconds", "single_samples_seconds"),
        ("tiled_seconds", "tiled_samples_seconds"),
    ] {
        let v: Vec<f64> = r[samples]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| x.as_f64().unwrap())
            .collect();
        assert_eq!(v.len(), 2, "{r}");
        assert!(v.iter().all(|&s| s > 0.0), "{r}");
        assert_eq!(r[k].as_f64().unwrap(), v[0].min(v[1]), "{r}");
    }
    // (JSON's decimal round trip may move the last bit.)
    let ratio = r["tiled_seconds"].as_f64().unwrap() / r["single_seconds"].as_f64().unwrap();
    let reported = r["tiled_over_single"].as_f64().unwrap();
    assert!((reported - ratio).abs() <= 1e-12 * ratio, "{r}");
}

/// The benchmark caps the `paper` reference by time, and says when its ratio is only a lower
/// bound.
#[test]
fn bench_caps_the_paper_reference_by_time() {
    let o = sfsfuse()
        .args([
            "bench",
            "--size",
            "64",
            "--paper-seconds",
            "0.5",
            "--progress",
            "lines",
            "--json",
        ])
        .output()
        .unwrap();
    let r = json_of(&o);
    let paper = &r["paper"];
    // Checked every 50 sweeps: the last chunk started under the cap and the reference stopped
    // past it, one chunk at most. (Judged on the times the bench saw, not on an average
    // sweep's: on a loaded machine one chunk can take far longer than the others.)
    let checked = r["paper_cap_checked_at"].as_f64().unwrap();
    let seconds = paper["seconds"].as_f64().unwrap();
    assert!(checked < 0.5 && seconds >= 0.5 && checked < seconds, "{r}");
    let iterations = paper["iterations"].as_u64().unwrap();
    assert!(iterations < 20000 && iterations.is_multiple_of(50), "{r}");
    assert_eq!(
        r["speedup_is_lower_bound"].as_bool().unwrap(),
        paper["seconds_to_tolerance"].is_null(),
        "{r}"
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("paper:"));
    let o = sfsfuse()
        .args(["bench", "--size", "64", "--paper-seconds", "0"])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--paper-seconds 0"));
}

/// A label given as a bare file name, in its own directory, whose pointer names the data file
/// in another letter case: found (it used to fail with an empty path).
#[test]
fn a_bare_label_name_finds_its_data_file_in_any_case() {
    let data = test_data().unwrap();
    let dir = std::env::temp_dir().join(format!("sfsfuse-bare-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::copy(data.join("lola_ldem4/LDEM_4.LBL"), dir.join("LDEM_4.LBL")).unwrap();
    std::os::unix::fs::symlink(data.join("lola_ldem4/LDEM_4.IMG"), dir.join("ldem_4.img")).unwrap();
    let o = sfsfuse()
        .args(["inspect", "--json", "LDEM_4.LBL"])
        .current_dir(&dir)
        .output()
        .unwrap();
    let r = json_of(&o);
    assert_eq!(r["lines"], 720);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A reader that goes away (`sfsfuse … | head`) is not an error and never a panic: the report
/// to a closed standard output and the progress lines to a closed standard error are dropped,
/// the command finishes its work and exits 0.
#[test]
fn a_closed_pipe_is_neither_a_panic_nor_a_failure() {
    let label = test_data().unwrap().join("lola_ldem4/LDEM_4.LBL");
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let o = sfsfuse()
        .arg("inspect")
        .arg(&label)
        .stdout(writer)
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{:?}: {err}", o.status);
    assert!(!err.contains("panicked"), "{err}");

    // Progress lines to a closed standard error: the benchmark still runs to its report.
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let o = sfsfuse()
        .args([
            "bench",
            "--size",
            "32",
            "--paper-seconds",
            "0.1",
            "--progress",
            "lines",
            "--json",
        ])
        .stderr(writer)
        .output()
        .unwrap();
    assert!(o.status.success(), "{:?}", o.status);
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(r["fusion_seconds"].as_f64().is_some_and(|s| s > 0.0), "{r}");
}

/// `synth --loc-offset EAST/NORTH` writes an observation whose LOC backplane misplaces every
/// pixel by that many metres on the 1737.4 km sphere (checked against the same scene written
/// without it), `--loc-drift` one whose error grows from none at the first line to that at the
/// last in proportion to the line, `--gain-trend` one whose radiance at line l is the plain
/// one's times exp(T·(l − 15.5)/1000) over its 32 lines, `--column-striping S` one whose every
/// detector column (sample) is the plain one's times a gain of its own, the same on every line
/// and band, with ln g spread by about S over the columns; the others are left alone, and what
/// is not an offset, a trend or a striping is refused.
#[test]
fn synth_writes_product_errors_where_asked() {
    let base = scratch("loc-offset");
    let write = |name: &str, extra: &[&str]| synth_two_suns(&base.join(name), extra);
    let plain = write("plain", &[]);
    let moved = write(
        "moved",
        &["--loc-offset", "0/0", "--loc-offset", "300/-200"],
    );
    let drifting = write("drifting", &["--loc-drift", "-310/620"]);
    let trending = write("trending", &["--gain-trend", "0", "--gain-trend", "0.5"]);
    let striped = write(
        "striped",
        &["--column-striping", "0", "--column-striping", "0.02"],
    );
    let loc =
        |dir: &std::path::Path, id: &str| le_values(&dir.join(format!("{id}_V03_LOC.IMG")), 8);
    let first = "M3G20991231T000000";
    assert_eq!(loc(&plain, first), loc(&moved, first));
    let second = "M3G20991231T010000";
    let (a, b) = (loc(&plain, second), loc(&moved, second));
    // Line-interleaved longitude, latitude, radius over 32 samples.
    let r = 1_737_400.0;
    for (la, lb) in a.chunks_exact(96).zip(b.chunks_exact(96)) {
        for s in 0..32 {
            let east = (lb[s] - la[s]).to_radians() * r * la[32 + s].to_radians().cos();
            let north = (lb[32 + s] - la[32 + s]).to_radians() * r;
            assert!((east - 300.0).abs() < 1e-3 && (north + 200.0).abs() < 1e-3);
            assert_eq!(la[64 + s], lb[64 + s]);
        }
    }
    // The first observation drifts: line i of 32 is off by i/31 of the drift.
    let (a, b) = (loc(&plain, first), loc(&drifting, first));
    assert_eq!(loc(&plain, second), loc(&drifting, second));
    for (i, (la, lb)) in a.chunks_exact(96).zip(b.chunks_exact(96)).enumerate() {
        let t = i as f64 / 31.0;
        for s in 0..32 {
            let east = (lb[s] - la[s]).to_radians() * r * la[32 + s].to_radians().cos();
            let north = (lb[32 + s] - la[32 + s]).to_radians() * r;
            assert!((east + 310.0 * t).abs() < 1e-3 && (north - 620.0 * t).abs() < 1e-3);
        }
    }
    let rdn =
        |dir: &std::path::Path, id: &str| le_values(&dir.join(format!("{id}_V03_RDN.IMG")), 4);
    assert_eq!(rdn(&plain, first), rdn(&trending, first));
    let (a, b) = (rdn(&plain, second), rdn(&trending, second));
    let per_line = a.len() / 32;
    for (i, (la, lb)) in a
        .chunks_exact(per_line)
        .zip(b.chunks_exact(per_line))
        .enumerate()
    {
        let g = (0.5 * (i as f64 - 15.5) / 1000.0).exp();
        for (x, y) in la.iter().zip(lb) {
            assert!((y - g * x).abs() <= 1e-6 * x.abs());
        }
    }
    assert_eq!(rdn(&plain, first), rdn(&striped, first));
    let b = rdn(&striped, second);
    // Line-interleaved: each line holds every band's 32 samples in turn.
    let ln_gain: Vec<f64> = (0..32).map(|s| (b[s] / a[s]).ln()).collect();
    for (k, (x, y)) in a.iter().zip(&b).enumerate() {
        let g = ln_gain[k % 32].exp();
        assert!((y - g * x).abs() <= 2e-6 * x.abs(), "value {k}");
    }
    let mean = ln_gain.iter().sum::<f64>() / 32.0;
    let spread = (ln_gain.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / 31.0).sqrt();
    assert!((0.012..0.028).contains(&spread), "ln g spread {spread}");
    synth_refuses(
        &base,
        &[
            (vec!["--gain-trend", "inf"], "within ±10"),
            (vec!["--column-striping", "0.9"], "from 0 to 0.5"),
            (vec!["--column-striping", "-0.01"], "from 0 to 0.5"),
            (vec!["--loc-offset", "300"], "EAST/NORTH"),
            (vec!["--loc-offset", "1e9/0"], "within 100 km"),
            (vec!["--loc-drift", "0/nan"], "within 100 km"),
            (
                vec![
                    "--loc-drift",
                    "0/0",
                    "--loc-drift",
                    "1/1",
                    "--loc-drift",
                    "2/2",
                ],
                "at most one per --sun",
            ),
            (
                vec![
                    "--loc-offset",
                    "0/0",
                    "--loc-offset",
                    "1/1",
                    "--loc-offset",
                    "2/2",
                ],
                "at most one per --sun",
            ),
        ],
    );
    std::fs::remove_dir_all(&base).unwrap();
}

/// The little-endian values of a raw product file: f64 for `bytes` = 8, f32 (widened exactly)
/// for 4.
fn le_values(path: &std::path::Path, bytes: usize) -> Vec<f64> {
    std::fs::read(path)
        .unwrap()
        .chunks_exact(bytes)
        .map(|c| match bytes {
            8 => f64::from_le_bytes(c.try_into().unwrap()),
            _ => f64::from(f32::from_le_bytes(c.try_into().unwrap())),
        })
        .collect()
}

/// `synth --pixel-factor F` writes an observation seen by a detector F grid pixels wide: its
/// swath holds ⌊32/F⌋² pixels, each radiance the mean of the F × F it spans in the same scene
/// written at the grid's pixel size, its LOC latitude the mean of theirs; `inspect` then reads
/// a pixel size F times the grid's; a factor of 0, or more values than `--sun`s, are refused.
#[test]
fn synth_writes_an_observation_with_coarser_pixels_where_asked() {
    let base = scratch("pixel-factor");
    let write = |name: &str, extra: &[&str]| synth_two_suns(&base.join(name), extra);
    let plain = write("plain", &[]);
    let coarse = write("coarse", &["--pixel-factor", "1", "--pixel-factor", "2"]);
    let read = |dir: &std::path::Path, file: &str, bytes: usize| le_values(&dir.join(file), bytes);
    let second = "M3G20991231T010000";
    let label = std::fs::read_to_string(coarse.join(format!("{second}_V03_L1B.LBL"))).unwrap();
    assert!(label.contains("LINES = 16") && label.contains("LINE_SAMPLES = 16"));
    // RDN line-interleaved: line, band, sample; band 0 here.
    let (fine, wide) = (
        read(&plain, &format!("{second}_V03_RDN.IMG"), 4),
        read(&coarse, &format!("{second}_V03_RDN.IMG"), 4),
    );
    let bands = fine.len() / (32 * 32);
    // LOC: line, then longitude, latitude, radius bands of its samples.
    let (floc, wloc) = (
        read(&plain, &format!("{second}_V03_LOC.IMG"), 8),
        read(&coarse, &format!("{second}_V03_LOC.IMG"), 8),
    );
    for a in 0..16 {
        for b in 0..16 {
            let px = |i: usize, j: usize| (2 * a + i, 2 * b + j);
            let quad = [px(0, 0), px(0, 1), px(1, 0), px(1, 1)];
            let mean = quad
                .iter()
                .map(|&(i, j)| fine[i * bands * 32 + j])
                .sum::<f64>()
                / 4.0;
            let got = wide[a * bands * 16 + b];
            assert!((got / mean - 1.0).abs() < 1e-6, "({a},{b}) {got} {mean}");
            let lat = quad
                .iter()
                .map(|&(i, j)| floc[i * 96 + 32 + j])
                .sum::<f64>()
                / 4.0;
            assert!((wloc[a * 48 + 16 + b] - lat).abs() < 1e-9);
        }
    }
    let o = sfsfuse()
        .args(["inspect", "--json"])
        .arg(coarse.join(format!("{second}_V03_L1B.LBL")))
        .output()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let size = v["pixel_size_m"].as_f64().unwrap();
    assert!((size / 280.0 - 1.0).abs() < 0.01, "{v}");
    synth_refuses(
        &base,
        &[
            (vec!["--pixel-factor", "0"], "at least 1"),
            (
                vec![
                    "--pixel-factor",
                    "1",
                    "--pixel-factor",
                    "2",
                    "--pixel-factor",
                    "2",
                ],
                "at most one per --sun",
            ),
        ],
    );
    std::fs::remove_dir_all(&base).unwrap();
}

/// `synth --sun-drift ΔAZ/ΔEL` writes an observation whose Sun moves along its strip: in its
/// OBS backplane line i of 32 has the Sun's azimuth ΔAZ·i/31 further round and its zenith
/// ΔEL·i/31 smaller than without the drift, at every sample; the observation without one is
/// written as before; a drift that takes a Sun below the horizon, one that is not two numbers
/// and more values than `--sun`s are refused.
#[test]
fn synth_writes_a_sun_moving_along_the_strip_where_asked() {
    let base = scratch("sun-drift");
    let write = |name: &str, extra: &[&str]| synth_two_suns(&base.join(name), extra);
    let plain = write("plain", &[]);
    let moving = write("moving", &["--sun-drift", "0/0", "--sun-drift", "20/-10"]);
    let obs =
        |dir: &std::path::Path, id: &str| le_values(&dir.join(format!("{id}_V03_OBS.IMG")), 4);
    let (first, second) = ("M3G20991231T000000", "M3G20991231T010000");
    assert_eq!(obs(&plain, first), obs(&moving, first));
    let (a, b) = (obs(&plain, second), obs(&moving, second));
    // Line-interleaved: each line holds the ten bands' 32 samples in turn, to-Sun azimuth first,
    // then to-Sun zenith.
    for (i, (la, lb)) in a.chunks_exact(320).zip(b.chunks_exact(320)).enumerate() {
        let t = i as f64 / 31.0;
        for s in 0..32 {
            let turned = (lb[s] - la[s] - 20.0 * t + 180.0).rem_euclid(360.0) - 180.0;
            assert!(
                turned.abs() < 1e-3,
                "line {i} sample {s}: azimuth {} against {}",
                lb[s],
                la[s]
            );
            assert!(
                (lb[32 + s] - la[32 + s] - 10.0 * t).abs() < 1e-3,
                "line {i} sample {s}"
            );
        }
    }
    synth_refuses(
        &base,
        &[
            (
                vec!["--sun-drift", "0/0", "--sun-drift", "0/-40"],
                "above the horizon",
            ),
            (vec!["--sun-drift", "10"], "ΔAZIMUTH/ΔELEVATION"),
            (
                vec![
                    "--sun-drift",
                    "0/0",
                    "--sun-drift",
                    "1/1",
                    "--sun-drift",
                    "2/2",
                ],
                "at most one per --sun",
            ),
        ],
    );
    std::fs::remove_dir_all(&base).unwrap();
}

/// `synth` with two Suns and each of `cases`' extra arguments fails, saying what is given.
fn synth_refuses(base: &std::path::Path, cases: &[(Vec<&str>, &str)]) {
    for (bad, says) in cases {
        let o = sfsfuse()
            .args([
                "synth", "--size", "32", "--sun", "105/30", "--sun", "225/35", "--out",
            ])
            .arg(base.join("bad"))
            .args(bad)
            .output()
            .unwrap();
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(says), "{bad:?}: {e}");
    }
}

/// `synth` of a 32² scene under Suns 105/30 and 225/35 with `extra` arguments into `out`
/// (which it returns), checked to succeed.
fn synth_two_suns(out: &std::path::Path, extra: &[&str]) -> std::path::PathBuf {
    let o = sfsfuse()
        .args([
            "synth", "--size", "32", "--sun", "105/30", "--sun", "225/35", "--out",
        ])
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    out.to_path_buf()
}

/// `--version` names the build: the crate version and the hash of the sources it was built
/// from (build.rs), the identity the plan, tile and run keys carry (`sfsfuse::BUILD`).
#[test]
fn version_names_the_build() {
    let o = sfsfuse().arg("--version").output().unwrap();
    assert!(o.status.success());
    let s = String::from_utf8(o.stdout).unwrap();
    let v = s
        .trim()
        .strip_prefix("sfsfuse ")
        .expect("starts with the name");
    assert_eq!(v, sfsfuse::BUILD);
    let (version, hash) = v.split_once("+src.").expect("version+src.hash");
    assert_eq!(version, env!("CARGO_PKG_VERSION"));
    assert!(
        hash.len() == 16 && hash.chars().all(|c| c.is_ascii_hexdigit()),
        "source hash {hash:?}"
    );
}

/// An observation whose LOC and OBS files are not at hand (the RDN-only `linerateNotConstant`
/// crop) still has its label's SOLAR_DISTANCE checked against the Moon's distance from the Sun
/// at START_TIME–STOP_TIME (0.988 783 AU in the label, the ephemeris within 2·10⁻⁴ AU of it);
/// the same label with SOLAR_DISTANCE 1.005 AU is described, then refused (exit status 1).
#[test]
fn inspect_checks_the_solar_distance_of_an_rdn_only_observation() {
    let data = test_data().unwrap();
    let src = data.join("m3_l1b_crops/linerateNotConstant");
    let label = src.join("M3G20081118T223204_V03_L1B_cropped.LBL");
    let r = inspect_json(&label);
    let c = &r["sun_ephemeris"];
    assert_eq!(c["pixels"], 0, "{r}");
    let d = c["distance_au"].as_f64().unwrap();
    assert!((d - 0.988783).abs() < 2e-4, "{d}");
    let dir = scratch("rdn-only-distance");
    std::fs::create_dir_all(&dir).unwrap();
    copy_files(&src, &dir);
    let copy = dir.join(label.file_name().unwrap());
    let text = std::fs::read_to_string(&copy).unwrap();
    let edited = with_line_replaced(&text, "SOLAR_DISTANCE", "SOLAR_DISTANCE = 1.005 <AU>");
    std::fs::write(&copy, edited).unwrap();
    let o = sfsfuse().arg("inspect").arg(&copy).output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("SOLAR_DISTANCE = 1.005 AU") && err.contains("AU off"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `text` with the line that starts with `key` replaced by `line`.
fn with_line_replaced(text: &str, key: &str, line: &str) -> String {
    text.split_inclusive('\n')
        .map(|l| {
            if l.trim_start().starts_with(key) {
                let end = &l[l.trim_end_matches(['\r', '\n']).len()..];
                format!("{line}{end}")
            } else {
                l.to_string()
            }
        })
        .collect()
}
