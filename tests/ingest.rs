//! Real products onto grids: LOLA LDEM_4 and an M3 L1B crop from tests/data (vendored).

use pds::lola::LolaDem;
use pds::m3::Observation;
use pds::solar::SolarSpectrum;
use sfsfuse::grid::{Crs, Grid, Interpolation, LonLatBox};
use sfsfuse::ingest::{lola_on_grid, m3_on_grid};
use sfsfuse::photometry::widen;

#[path = "../pds/tests/common/mod.rs"]
mod common;
use common::test_data;

mod support;

#[test]
fn ldem4_on_its_own_grid_gives_its_own_heights() {
    let Some(data) = test_data() else { return };
    let dem = LolaDem::open(&data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    // docs/formats.md: GDAL georeferences LDEM_4 as equirectangular lon_0 = 180 on the 1737.4 km
    // sphere, upper-left corner (−5 458 203.08, 2 729 101.54), exact scale 2π·1737400/360/4.
    let s = 2.0 * std::f64::consts::PI * 1_737_400.0 / 360.0 / 4.0;
    let (x0, y0) = (-720.0 * s, 360.0 * s);
    assert!((x0 + 5_458_203.08).abs() < 0.01 && (y0 - 2_729_101.54).abs() < 0.01);
    let crs = Crs::Equirectangular { lon_0: 180.0 };
    let pr = crs.projector().unwrap();
    let dn = dem.read_dn(0, 720).unwrap();
    // Windows across the 0°/360° seam, at high southern latitude and at the equator.
    for (r0, c0) in [(600usize, 1420usize), (350, 700), (0, 0)] {
        let g = Grid::new(crs, 20, 40, x0, y0, s)
            .unwrap()
            .window(r0 as isize, c0 as isize, 20, 40);
        let geo = g.geographic(&pr);
        for method in [Interpolation::Bilinear, Interpolation::Bicubic] {
            let h = lola_on_grid(&dem, &geo, method).unwrap().unwrap();
            for ((r, c), v) in h.indexed_iter() {
                let want = dn[(r0 + r) * 1440 + (c0 + c) % 1440] * 0.5;
                if r0 == 0 && r < 2 {
                    // Bicubic support leaves the product at its northern edge: no data.
                    assert!(
                        v.is_nan() || method == Interpolation::Bilinear || (v - want).abs() < 1e-6
                    );
                    continue;
                }
                assert!(
                    (v - want).abs() < 1e-6,
                    "{method:?} ({r0}+{r},{c0}+{c}): {v} vs {want}"
                );
            }
        }
    }
}

/// A 2 km local stereographic grid over 180–195° E, 66–75° S, around crater Antoniadi.
fn antoniadi_grid() -> (Grid, Crs) {
    let region = LonLatBox {
        lon_min: 180.0,
        lon_max: 195.0,
        lat_min: -75.0,
        lat_max: -66.0,
    };
    let (lon_0, lat_0) = region.centre();
    let crs = Crs::Stereographic { lat_0, lon_0 };
    (Grid::covering(crs, &region, 2000.0).unwrap(), crs)
}

#[test]
fn antoniadi_is_the_deepest_point_of_a_local_grid() {
    let Some(data) = test_data() else { return };
    let dem = LolaDem::open(&data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    let (g, crs) = antoniadi_grid();
    let pr = crs.projector().unwrap();
    let geo = g.geographic(&pr);
    let h = lola_on_grid(&dem, &geo, Interpolation::Bicubic)
        .unwrap()
        .unwrap();
    assert!(h.iter().all(|v| v.is_finite()));
    let ((r, c), min) = h.indexed_iter().fold(
        ((0, 0), f64::MAX),
        |a, (i, &v)| if v < a.1 { (i, v) } else { a },
    );
    // MANIFEST: min DN −17757 (−8878.5 m) at 70.375°S 187.625°E; one LDEM_4 pixel is 7.6 km.
    let (x, y) = pr.forward(187.625, -70.375).unwrap();
    let (x1, y1) = g.xy(r as f64, c as f64);
    assert!(
        (x - x1).hypot(y - y1) < 7600.0,
        "deepest grid point {} m away",
        (x - x1).hypot(y - y1)
    );
    assert!((min + 8878.5).abs() < 150.0, "{min}");
}

#[test]
fn m3_global_crop_on_a_local_grid() {
    let Some(data) = test_data() else { return };
    let label = data.join("m3_l1b_crops/reverseDescending/M3G20090106T113423_V03_L1B_cropped.LBL");
    let label = if label.is_file() {
        label
    } else {
        std::fs::read_dir(data.join("m3_l1b_crops/reverseDescending"))
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("lbl")))
            .unwrap()
    };
    let obs = Observation::open(&label).unwrap();
    let solar =
        SolarSpectrum::read(&data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab")).unwrap();
    let loc = obs.part("LOC").unwrap();
    let n = loc.lines;
    let lon = loc.read_band(0, 0, n).unwrap();
    let lat = loc.read_band(1, 0, n).unwrap();
    let (lo_min, lo_max) = lon
        .iter()
        .fold((f64::MAX, f64::MIN), |a, &v| (a.0.min(v), a.1.max(v)));
    let (la_min, la_max) = lat
        .iter()
        .fold((f64::MAX, f64::MIN), |a, &v| (a.0.min(v), a.1.max(v)));
    let region = LonLatBox {
        lon_min: lo_min,
        lon_max: lo_max,
        lat_min: la_min,
        lat_max: la_max,
    };
    // Centred on the middle pixel of the strip (5 lines: its lon/lat box centre may miss it).
    let mid = (n / 2) * loc.samples + loc.samples / 2;
    let crs = Crs::Stereographic {
        lat_0: lat[mid],
        lon_0: lon[mid],
    };
    let g = Grid::covering(crs, &region, 140.0).unwrap();
    let pr = crs.projector().unwrap();
    let geo = g.geographic(&pr);
    // 500.92 nm is global band 1, held by the crop (which keeps only the first 3 bands).
    let img = m3_on_grid(
        &obs,
        &solar,
        500.92,
        &g,
        &pr,
        geo.bearing.view(),
        None,
        &Default::default(),
    )
    .unwrap();
    assert_eq!(img.bands, (1, 1));
    assert_eq!(img.lines, (0, n));
    let filled: Vec<_> = img
        .reflectance
        .indexed_iter()
        .filter(|(_, v)| v.is_finite())
        .map(|(i, _)| i)
        .collect();
    // The crop is 5 lines × 304 samples of ~140 m: about 4 × 303 grid pixels inside.
    assert!(filled.len() > 800, "{}", filled.len());
    // Reflectance lies within the range r = L·d²/E of the swath's own pixels.
    let obsr = obs.part("OBS").unwrap();
    let rad = obs.rdn.read_band(1, 0, n).unwrap();
    let doff = obsr.read_band(5, 0, n).unwrap();
    let e = solar.at(500.92).unwrap();
    let r_swath: Vec<f64> = rad
        .iter()
        .zip(&doff)
        .map(|(l, d)| l * (obs.solar_distance_au + d).powi(2) / e)
        .collect();
    let (rmin, rmax) = r_swath
        .iter()
        .fold((f64::MAX, f64::MIN), |a, &v| (a.0.min(v), a.1.max(v)));
    assert!(rmin > 0.0);
    for &i in &filled {
        let v = img.reflectance[i];
        assert!(
            v >= rmin - 1e-12 && v <= rmax + 1e-12,
            "{v} outside [{rmin}, {rmax}]"
        );
    }
    // The rotation into the grid frame keeps zenith and phase: they stay within the swath's
    // OBS ranges (bands 2, 4 and 5).
    let range = |b: usize| {
        let v = obsr.read_band(b, 0, n).unwrap();
        v.iter()
            .fold((f64::MAX, f64::MIN), |a, &x| (a.0.min(x), a.1.max(x)))
    };
    let (sz, vz, ph) = (range(1), range(3), range(4));
    let deg = |x: f64| x.clamp(-1.0, 1.0).acos().to_degrees();
    for &i in &filled {
        let (s, v) = (widen(&img.sun[i]), widen(&img.view[i]));
        let tol = 1e-3;
        assert!(deg(s[2]) >= sz.0 - tol && deg(s[2]) <= sz.1 + tol);
        assert!(deg(v[2]) >= vz.0 - tol && deg(v[2]) <= vz.1 + tol);
        let g = deg(s[0] * v[0] + s[1] * v[1] + s[2] * v[2]);
        assert!(
            g >= ph.0 - 0.01 && g <= ph.1 + 0.01,
            "phase {g} outside {ph:?}"
        );
    }
    // Near the projection centre grid north is true north: the grid azimuth of the Sun equals
    // OBS band 1 at the nearest swath pixel.
    let az = obsr.read_band(0, 0, n).unwrap();
    let (xc, yc) = (0.0, 0.0);
    let (rc, cc) = g.pixel(xc, yc);
    let i = (rc.round() as usize, cc.round() as usize);
    let s = widen(&img.sun[i]);
    assert!(s[0].is_finite(), "the grid centre lies inside the crop");
    let (glon, glat) = (geo.lon[i], geo.lat[i]);
    let k = (0..lon.len())
        .min_by(|&a, &b| {
            let d = |k: usize| (lon[k] - glon).powi(2) + (lat[k] - glat).powi(2);
            d(a).total_cmp(&d(b))
        })
        .unwrap();
    let grid_az = s[0].atan2(s[1]).to_degrees().rem_euclid(360.0);
    let diff = (grid_az - az[k] + 540.0).rem_euclid(360.0) - 180.0;
    assert!(diff.abs() < 0.5, "grid azimuth {grid_az} vs OBS {}", az[k]);
}

#[test]
fn a_grid_outside_the_product_is_refused_with_its_name() {
    let Some(data) = test_data() else { return };
    let label = std::fs::read_dir(data.join("m3_l1b_crops/reverseDescending"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("lbl")))
        .unwrap();
    let obs = Observation::open(&label).unwrap();
    let solar =
        SolarSpectrum::read(&data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab")).unwrap();
    let crs = Crs::Stereographic {
        lat_0: -40.0,
        lon_0: 100.0,
    };
    let g = Grid::new(crs, 10, 10, -700.0, 700.0, 140.0).unwrap();
    let pr = crs.projector().unwrap();
    let e = m3_on_grid(
        &obs,
        &solar,
        500.92,
        &g,
        &pr,
        g.geographic(&pr).bearing.view(),
        None,
        &Default::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains(&label.file_name().unwrap().to_string_lossy().to_string())
            && e.contains("no pixel"),
        "{e}"
    );
    // 1209.6 nm is not in this crop (it keeps 3 bands): the error says which band is missing.
    let g2 = Grid::covering(
        Crs::Stereographic {
            lat_0: 9.5,
            lon_0: 38.0,
        },
        &LonLatBox {
            lon_min: 37.5,
            lon_max: 38.5,
            lat_min: 9.0,
            lat_max: 10.0,
        },
        500.0,
    )
    .unwrap();
    let pr2 = g2.crs.projector().unwrap();
    let e = m3_on_grid(
        &obs,
        &solar,
        1209.6,
        &g2,
        &pr2,
        g2.geographic(&pr2).bearing.view(),
        None,
        &Default::default(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("RDN_IMAGE BANDS"), "{e}");
}

/// The Antoniadi grid's heights from LDEM_4 with its label edited by `label` and pixel
/// (`line`, `sample`) (0-based) of its data set to DN `dn`, in `dir`.
fn edited_ldem4_on_antoniadi(
    dir: &std::path::Path,
    label: impl Fn(&str) -> String,
    pixel: Option<(usize, usize, i16)>,
) -> sfsfuse::Result<Option<ndarray::Array2<f64>>> {
    let data = test_data().unwrap().join("lola_ldem4");
    std::fs::create_dir_all(dir).unwrap();
    let text = std::fs::read_to_string(data.join("LDEM_4.LBL")).unwrap();
    std::fs::write(dir.join("LDEM_4.LBL"), label(&text)).unwrap();
    let mut img = std::fs::read(data.join("LDEM_4.IMG")).unwrap();
    if let Some((line, sample, dn)) = pixel {
        let at = 2 * (line * 1440 + sample);
        img[at..at + 2].copy_from_slice(&dn.to_le_bytes());
    }
    std::fs::write(dir.join("LDEM_4.IMG"), img).unwrap();
    let dem = LolaDem::open(&dir.join("LDEM_4.LBL")).unwrap();
    let (g, crs) = antoniadi_grid();
    lola_on_grid(
        &dem,
        &g.geographic(&crs.projector().unwrap()),
        Interpolation::Bicubic,
    )
}

/// Heights are taken above the 1737.4 km sphere of the grid's CRS whatever the product's
/// reference sphere (OFFSET), and a value no lunar surface can have — here LDEM_4's deepest
/// pixel overwritten with the int16 fill −32768 (−16 384 m) — is refused naming the data
/// file, the pixel (1-based, as PDS counts) and its value; so is a GeoTIFF holding radii.
#[test]
fn dem_values_that_are_not_lunar_heights_are_refused_by_pixel() {
    let dir = std::env::temp_dir().join(format!("sfsfuse-lunar-heights-{}", std::process::id()));
    let same = |t: &str| t.to_string();
    let want = edited_ldem4_on_antoniadi(&dir, same, None)
        .unwrap()
        .unwrap();
    // OFFSET 1737.0 km: heights 400 m lower above 1737.4 km; no OFFSET: DN × 0.5 as they are.
    let lower = edited_ldem4_on_antoniadi(
        &dir,
        |t: &str| {
            t.replace(
                "OFFSET                = 1737400.",
                "OFFSET                = 1737000.",
            )
        },
        None,
    )
    .unwrap()
    .unwrap();
    let no_offset = edited_ldem4_on_antoniadi(
        &dir,
        |t: &str| t.replace("OFFSET                = 1737400.", ""),
        None,
    )
    .unwrap()
    .unwrap();
    for ((w, l), n) in want.iter().zip(&lower).zip(&no_offset) {
        assert!((w - 400.0 - l).abs() < 1e-6, "{w} {l}");
        assert_eq!(w, n);
    }
    // MANIFEST: LDEM_4's minimum at 70.375°S 187.625°E is line 642, sample 751 (1-based).
    let err = edited_ldem4_on_antoniadi(&dir, same, Some((641, 750, i16::MIN)))
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("LDEM_4.IMG")
            && err.contains("line 642, sample 751")
            && err.contains("height -16384 m is not on the Moon")
            && err.contains("0 more pixel(s)"),
        "{err}"
    );
    // The same pixel at −12 000 m, a kilometre deeper than any point on the Moon, passes the
    // bound exactly; one DN deeper does not.
    let edge = edited_ldem4_on_antoniadi(&dir, same, Some((641, 750, -24000)));
    assert!(edge.is_ok(), "{edge:?}");
    let err = edited_ldem4_on_antoniadi(&dir, same, Some((641, 750, -24001)))
        .unwrap_err()
        .to_string();
    assert!(err.contains("height -12000.5 m"), "{err}");
    // A GeoTIFF of radii (height + 1737.4 km) instead of heights.
    use sfsfuse::export::{write_geotiff, BandInfo};
    use sfsfuse::ingest::{geotiff_on_grid, GeoTiffDem};
    let (eqc, heights) = ldem4_heights();
    let radii = heights + 1_737_400.0;
    let tif = dir.join("radii.tif");
    let info = BandInfo {
        description: "LDEM_4 radii",
        unit: "m",
        metadata: &[],
    };
    write_geotiff(&tif, &eqc, radii.view(), &info).unwrap();
    let (g, crs) = antoniadi_grid();
    let err = geotiff_on_grid(
        &GeoTiffDem::open(&tif).unwrap(),
        &g.geographic(&crs.projector().unwrap()),
        Interpolation::Bicubic,
    )
    .unwrap_err()
    .to_string();
    assert!(
        err.contains("radii.tif") && err.contains("is not on the Moon"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A DEM given as a GeoTIFF: LDEM_4 written as a COG on its own equirectangular lattice, and
/// GDAL's strip-organised LZW copy of it, give the same heights on a local grid as the PDS
/// product; a GeoTIFF on the Earth is refused.
/// LDEM_4's own grid (GDAL's georeferencing of it: equirectangular, lon_0 = 180°, on the
/// 1737.4 km sphere, 2π·1737400/360/4 m a pixel) and its heights on it.
fn ldem4_heights() -> (Grid, ndarray::Array2<f64>) {
    let dem = LolaDem::open(&test_data().unwrap().join("lola_ldem4/LDEM_4.LBL")).unwrap();
    let s = 2.0 * std::f64::consts::PI * 1_737_400.0 / 360.0 / 4.0;
    let eqc = Grid::new(
        Crs::Equirectangular { lon_0: 180.0 },
        720,
        1440,
        -720.0 * s,
        360.0 * s,
        s,
    )
    .unwrap();
    let h = ndarray::Array2::from_shape_vec((720, 1440), dem.read_heights(0, 720).unwrap());
    (eqc, h.unwrap())
}

/// LDEM_4 written by us as a GeoTIFF in `dir`, with the Antoniadi grid's geography and the
/// PDS product resampled onto it: (GeoTIFF, geography, expected heights, LDEM_4's pixel in m).
fn ldem4_geotiff(
    dir: &std::path::Path,
) -> (
    std::path::PathBuf,
    sfsfuse::grid::Geographic,
    ndarray::Array2<f64>,
    f64,
) {
    use sfsfuse::export::{write_geotiff, BandInfo};
    let data = test_data().unwrap();
    let dem = LolaDem::open(&data.join("lola_ldem4/LDEM_4.LBL")).unwrap();
    let (eqc, h) = ldem4_heights();
    let s = eqc.spacing;
    std::fs::create_dir_all(dir).unwrap();
    let tif = dir.join("ldem4.tif");
    write_geotiff(
        &tif,
        &eqc,
        h.view(),
        &BandInfo {
            description: "LDEM_4 heights",
            unit: "m",
            metadata: &[],
        },
    )
    .unwrap();
    let (g, crs) = antoniadi_grid();
    let geo = g.geographic(&crs.projector().unwrap());
    let want = lola_on_grid(&dem, &geo, Interpolation::Bicubic)
        .unwrap()
        .unwrap();
    (tif, geo, want, s)
}

/// Each GeoTIFF DEM of `files` has LDEM_4's pixel size and resamples to `want` within 1 mm.
fn resample_like_the_pds_product(
    files: &[std::path::PathBuf],
    geo: &sfsfuse::grid::Geographic,
    want: &ndarray::Array2<f64>,
    s: f64,
) {
    use sfsfuse::ingest::{geotiff_on_grid, GeoTiffDem};
    for f in files {
        let d = GeoTiffDem::open(f).unwrap();
        assert!(
            (d.pixel_m() - s).abs() < 1e-3,
            "{}: pixel {} m",
            f.display(),
            d.pixel_m()
        );
        let got = geotiff_on_grid(&d, geo, Interpolation::Bicubic)
            .unwrap()
            .unwrap();
        let worst = got
            .iter()
            .zip(want)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(
            worst < 1e-3,
            "{}: differs from the PDS product by {worst} m",
            f.display()
        );
    }
}

/// LDEM_4 as our own tiled COG resamples exactly like the PDS product.
#[test]
fn geotiff_dems_resample_like_the_pds_product() {
    let dir = std::env::temp_dir().join(format!("sfsfuse-geotiff-dem-{}", std::process::id()));
    let (tif, geo, want, s) = ldem4_geotiff(&dir);
    resample_like_the_pds_product(&[tif], &geo, &want, s);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The same through files GDAL writes: strips with LZW, and a warp to longitude/latitude on
/// the IAU Moon sphere; the same pixels labelled as on the Earth are refused by name.
#[test]
#[ignore = "needs GDAL (gdal-bin); .ci/run runs it"]
fn gdal_written_geotiff_dems_resample_like_the_pds_product() {
    use sfsfuse::ingest::GeoTiffDem;
    let dir = std::env::temp_dir().join(format!("sfsfuse-gdal-dem-{}", std::process::id()));
    let (tif, geo, want, s) = ldem4_geotiff(&dir);
    let gdal_translate = common::external_tool("gdal_translate", "gdal-bin");
    let gdalwarp = common::external_tool("gdalwarp", "gdal-bin");
    let gdal = |tool: &std::path::Path, args: &[&str], out: &std::path::Path| {
        let o = std::process::Command::new(tool)
            .args(args)
            .arg(&tif)
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let strips = dir.join("strips.tif");
    gdal(
        &gdal_translate,
        &[
            "-q",
            "-co",
            "TILED=NO",
            "-co",
            "COMPRESS=LZW",
            "-co",
            "BLOCKYSIZE=7",
        ],
        &strips,
    );
    // Warped to longitude/latitude on the IAU Moon sphere, on the same 0.25° lattice.
    let geog = dir.join("geographic.tif");
    gdal(
        &gdalwarp,
        &[
            "-q",
            "-t_srs",
            "IAU_2015:30100",
            "-r",
            "near",
            "-te",
            "0",
            "-90",
            "360",
            "90",
            "-tr",
            "0.25",
            "0.25",
        ],
        &geog,
    );
    resample_like_the_pds_product(&[strips, geog], &geo, &want, s);
    let earth = dir.join("earth.tif");
    gdal(
        &gdal_translate,
        &[
            "-q",
            "-a_srs",
            "EPSG:4326",
            "-a_ullr",
            "-180",
            "90",
            "180",
            "-90",
        ],
        &earth,
    );
    let e = GeoTiffDem::open(&earth).unwrap_err().to_string();
    assert!(e.contains("earth.tif") && e.contains("6378137"), "{e}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A tile's image is the window of the whole region's image, value for value and no-data for
/// no-data, even where grid centres fall exactly on swath pixel centres (the synthetic swath
/// shares the grid's lattice): a pixel that is data on one window and no-data on another
/// would make tiled and single-tile runs disagree there. The same with the observation moved
/// back by a displacement that drifts along the swath (registration along the track).
#[test]
fn m3_on_a_window_is_the_window_of_m3_on_the_whole_grid() {
    use sfsfuse::ingest::survey;
    use sfsfuse::registration::Displacement;
    let p = support::scene_products(256, 10);
    let obs = Observation::open(&p.m3_label).unwrap();
    let solar = SolarSpectrum::read(&p.solar_table).unwrap();
    let pr = p.grid.crs.projector().unwrap();
    let nm = 1209.6;
    let index = survey(&obs, &solar, nm, &p.grid, &pr).unwrap().index;
    let drifting = Displacement::through(&[(20.0, [0.0, 0.0]), (230.0, [310.0, -170.0])]);
    let (mut compared, mut finite) = (0, 0);
    for shift in [Displacement::default(), drifting] {
        let on = |g: &Grid| {
            m3_on_grid(
                &obs,
                &solar,
                nm,
                g,
                &pr,
                g.geographic(&pr).bearing.view(),
                Some(&index),
                &shift,
            )
        };
        let whole = on(&p.grid).unwrap();
        for (r0, c0, rows, cols) in [(101, -37, 96, 150), (0, 128, 128, 128), (150, 19, 106, 77)] {
            let w = on(&p.grid.window(r0, c0, rows, cols)).unwrap();
            for ((i, j), &b) in w.reflectance.indexed_iter() {
                let (r, c) = (i as isize + r0, j as isize + c0);
                if r < 0 || c < 0 || r >= p.grid.rows as isize || c >= p.grid.cols as isize {
                    continue;
                }
                let a = whole.reflectance[(r as usize, c as usize)];
                assert!(
                (a - b).abs() <= 1e-9 * a.abs() || (a.is_nan() && b.is_nan()),
                "window at ({r0}, {c0}): pixel ({r}, {c}) is {b} on the window, {a} on the whole grid"
            );
                compared += 1;
                finite += usize::from(a.is_finite());
            }
        }
    }
    assert!(
        compared > 60_000 && finite > compared / 2,
        "{finite} of {compared}"
    );
}

/// The measured M3 solar table passes the plausibility check at every band (docs/formats.md:
/// ≈ 478 W/(m² µm) at 1209.6 nm), within 0.95–1.22× of a 5778 K black body as
/// docs/science.md says; the same table in another unit (×10, or W/(m² nm): ÷1000) is refused,
/// naming the file and the wavelength.
#[test]
fn a_solar_table_in_another_unit_is_refused() {
    let Some(data) = test_data() else { return };
    let path = data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab");
    let solar = SolarSpectrum::read(&path).unwrap();
    let e = sfsfuse::ingest::irradiance_at(&solar, 1209.6).unwrap();
    assert!((e - 478.0).abs() < 2.0, "{e}");
    let ratios: Vec<f64> = solar
        .rows
        .iter()
        .map(|&(w, e)| e / sfsfuse::ingest::blackbody_irradiance(w))
        .collect();
    let (lo, hi) = ratios
        .iter()
        .fold((f64::MAX, f64::MIN), |m, &r| (m.0.min(r), m.1.max(r)));
    assert!(lo > 0.94 && hi < 1.23, "{lo} … {hi}");
    for w in solar.rows.iter().map(|r| r.0) {
        sfsfuse::ingest::irradiance_at(&solar, w).unwrap();
    }
    for scale in [10.0, 1e-3] {
        let mut wrong = solar.clone();
        wrong.rows.iter_mut().for_each(|r| r.1 *= scale);
        let err = sfsfuse::ingest::irradiance_at(&wrong, 1209.6)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("m3t20110224_rfl_solar_spec.tab")
                && err.contains("1209.6 nm")
                && err.contains("W/(m² µm) at 1 AU"),
            "{err}"
        );
    }
}

/// The vendored M3 crop `stem` in `m3_l1b_crops/dir`, opened.
fn real_crop(data: &std::path::Path, dir: &str, stem: &str) -> Observation {
    let dir = data.join("m3_l1b_crops").join(dir);
    Observation::open(&dir.join(format!("{stem}_V03_L1B_cropped.LBL"))).unwrap()
}

/// The Sun that OBS gives at each pixel of the three vendored M3 crops (to-Sun azimuth and
/// zenith at LOC's longitude and latitude; computed by the M3 team from the mission's SPICE
/// kernels) agrees with `ephemeris` at the label's START_TIME–STOP_TIME within 0.02°
/// (measured 0.002–0.006°) over 2008-11, 2009-01 and 2009-06, near 29° S, 9° N and 63° N.
/// Counting the azimuths the other way (counter-clockwise from north) puts it 16–36° off.
/// The labels' SOLAR_DISTANCE agrees with the ephemeris's distance within 1.3·10⁻⁴ AU.
#[test]
fn obs_suns_of_real_crops_agree_with_the_ephemeris() {
    use sfsfuse::ephemeris::{angle_deg, days_since_j2000, local_to_moon, sun_in_moon_frame};
    let data = test_data().unwrap();
    for (dir, stem) in [
        ("forwardAscending", "M3T20090630T083407"),
        ("forwardDescending", "M3G20081129T171431"),
        ("reverseDescending", "M3G20090106T113423"),
    ] {
        let o = real_crop(&data, dir, stem);
        let c = sfsfuse::ingest::sun_check(&o).unwrap().unwrap();
        assert_eq!(c.pixels, o.rdn.lines * o.rdn.samples, "{dir}");
        assert!(c.worst_deg < 0.02, "{dir}: {c:?}");
        assert!(c.allowed_deg < 1.01, "{dir}: {c:?}");
        // The same pixels with mirrored azimuths, against the Sun at START_TIME.
        let (loc, obs) = (o.part("LOC").unwrap(), o.part("OBS").unwrap());
        let band = |r: &pds::raw::Raster, b| r.read_band(b, 0, r.lines).unwrap();
        let (lon, lat, az, zen) = (band(&loc, 0), band(&loc, 1), band(&obs, 0), band(&obs, 1));
        let sun = sun_in_moon_frame(days_since_j2000(&o.start_time.unwrap()));
        let least = (0..lon.len())
            .map(|k| angle_deg(local_to_moon(lon[k], lat[k], 360.0 - az[k], zen[k]), sun))
            .fold(f64::INFINITY, f64::min);
        assert!(least > 10.0, "{dir}: {least}");
    }
    // The labels' SOLAR_DISTANCE (computed by the M3 team) against the Moon's distance from
    // the Sun at START_TIME–STOP_TIME: within 1.3·10⁻⁴ AU on all four labels, where the
    // Earth's differs from it by up to 2.5·10⁻³ AU.
    for (dir, stem) in [
        ("forwardAscending", "M3T20090630T083407"),
        ("forwardDescending", "M3G20081129T171431"),
        ("reverseDescending", "M3G20090106T113423"),
        ("linerateNotConstant", "M3G20081118T223204"),
    ] {
        let o = real_crop(&data, dir, stem);
        let (a, b) = (
            days_since_j2000(&o.start_time.unwrap()),
            days_since_j2000(&o.stop_time.unwrap()),
        );
        let d = sfsfuse::ephemeris::sun_distance_au(0.5 * (a + b));
        assert!(
            (d - o.solar_distance_au).abs() < 2e-4,
            "{dir}: {d} against {}",
            o.solar_distance_au
        );
    }
}

/// The scratch of a test process that no longer runs is swept away; this process's own is not.
/// (Process ids stop below 2²², so 4294967294 never runs.)
#[test]
fn scratch_left_by_finished_test_runs_is_swept() {
    if !std::path::Path::new("/proc/self").exists() {
        return;
    }
    let tmp = std::env::temp_dir();
    let crate_name = env!("CARGO_CRATE_NAME");
    let stale = tmp.join(format!("sfsfuse-{crate_name}-4294967294-left"));
    let own = tmp.join(format!("sfsfuse-{crate_name}-{}-kept", std::process::id()));
    for d in [&stale, &own] {
        std::fs::create_dir_all(d.join("sub")).unwrap();
        std::fs::write(d.join("sub/f"), b"x").unwrap();
    }
    support::sweep_stale_scratch();
    assert!(!stale.exists(), "{} was not swept", stale.display());
    assert!(own.exists(), "{} was swept", own.display());
    std::fs::remove_dir_all(&own).unwrap();
}
