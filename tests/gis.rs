//! The georeferenced grid and the GeoTIFF export checked against independent implementations:
//! PROJ's own `proj` for the projections, the tiff crate's decoder and GDAL itself
//! (`gdalinfo -json`, `gdalsrsinfo`, its Python bindings and its COG validator) for the files.
//! Outside CI the GDAL/PROJ checks skip when the tools are missing; `.ci/run` installs them.

use ndarray::Array2;
use sfsfuse::export::{read_tiff, write_geotiff, write_geotiff_as, BandInfo, Container};
use sfsfuse::grid::{Crs, Grid};
use std::path::{Path, PathBuf};
use std::process::Command;

#[path = "../pds/tests/common/mod.rs"]
mod common;
use common::external_tool;

const COG_VALIDATOR: &str =
    "/usr/lib/python3/dist-packages/osgeo_utils/samples/validate_cloud_optimized_geotiff.py";

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("sfsfuse-gis-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn crss() -> Vec<Crs> {
    vec![
        Crs::Stereographic {
            lat_0: -13.4,
            lon_0: 357.2,
        },
        Crs::Orthographic {
            lat_0: 9.5,
            lon_0: 38.0,
        },
        Crs::PolarStereographic { north: true },
        Crs::PolarStereographic { north: false },
        Crs::Equirectangular { lon_0: 0.0 },
        Crs::Equirectangular { lon_0: 180.0 },
    ]
}

/// A test raster with structure at every scale, exact float32 values and a no-data hole.
fn pattern(rows: usize, cols: usize) -> Array2<f64> {
    Array2::from_shape_fn((rows, cols), |(r, c)| {
        if (40..60).contains(&r) && (100..130).contains(&c) {
            f64::NAN
        } else {
            let v = (r as f64 * 0.37).sin() * 800.0 + c as f64 * 1.25 - 1234.5;
            (v as f32) as f64
        }
    })
}

fn info() -> BandInfo<'static> {
    BandInfo {
        description: "test height",
        unit: "m",
        metadata: &[],
    }
}

fn run(cmd: &mut Command) -> String {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{cmd:?} failed: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8(o.stdout).unwrap()
}

#[test]
#[ignore = "needs PROJ's `proj` (proj-bin); .ci/run runs it"]
fn projections_match_proj() {
    let proj = external_tool("proj", "proj-bin");
    let points = [
        (357.2, -13.4),
        (-3.5, -12.0),
        (38.0, 9.5),
        (40.1, 11.0),
        (129.2, -89.0),
        (200.0, 85.5),
        (10.0, 0.0),
        (181.0, -40.0),
    ];
    for crs in crss() {
        let pr = crs.projector().unwrap();
        let usable: Vec<_> = points
            .iter()
            .filter_map(|&(lon, lat)| pr.forward(lon, lat).map(|xy| ((lon, lat), xy)))
            .filter(|&(_, (x, y))| x.abs() < 3e6 && y.abs() < 3e6)
            .collect();
        assert!(usable.len() >= 2, "{crs:?}");
        let input: String = usable
            .iter()
            .map(|((lon, lat), _)| format!("{lon} {lat}\n"))
            .collect();
        let out = common::proj_forward(&proj, &crs.proj_string(), &input);
        for ((_, (x, y)), row) in usable.iter().zip(out.lines()) {
            let v: Vec<f64> = row.split_whitespace().map(|t| t.parse().unwrap()).collect();
            assert!(
                (v[0] - x).abs() < 1e-3 && (v[1] - y).abs() < 1e-3,
                "{crs:?}: proj {row}, ours {x} {y}"
            );
        }
    }
}

/// PROJ parses our WKT2 back to our PROJ string for every CRS.
#[test]
#[ignore = "needs PROJ's `projinfo` (proj-bin); .ci/run runs it"]
fn wkt_means_the_same_to_proj() {
    let projinfo = external_tool("projinfo", "proj-bin");
    for crs in crss() {
        let out = run(Command::new(&projinfo)
            .args(["-o", "PROJ", "-q"])
            .arg(crs.wkt()));
        let got = out.trim().trim_end_matches(" +type=crs");
        assert_eq!(got, crs.proj_string(), "{crs:?}");
    }
}

#[test]
fn geotiff_reads_back_exactly_with_the_tiff_crate() {
    let dir = scratch("tiffcrate");
    let a = pattern(600, 530);
    for (k, container) in [Container::Auto, Container::BigTiff]
        .into_iter()
        .enumerate()
    {
        let grid = Grid::new(crss()[0], 600, 530, -37100.0, 42000.0, 140.0).unwrap();
        let p = dir.join(format!("t{k}.tif"));
        write_geotiff_as(&p, &grid, a.view(), &info(), container).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..4], if k == 0 { b"II*\0" } else { b"II+\0" });
        let t = read_tiff(&p).unwrap();
        assert_eq!(t.data.dim(), (600, 530));
        for (x, y) in t.data.iter().zip(a.iter()) {
            assert!(x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()));
        }
        assert_eq!(t.geotransform, Some(grid.geotransform()));
        assert!(t.nodata.unwrap().is_nan());
        // 600 → 300 → 150 px: full resolution and two overviews.
        assert_eq!(t.images, 3);
    }
    // Errors name the file; nothing is left under the final name or a temporary one.
    let grid = Grid::new(crss()[0], 10, 10, 0.0, 0.0, 1.0).unwrap();
    let e = write_geotiff(&dir.join("x.tif"), &grid, a.view(), &info())
        .unwrap_err()
        .to_string();
    assert!(e.contains("x.tif") && e.contains("600"), "{e}");
    let e = write_geotiff(
        &dir.join("no/dir/y.tif"),
        &grid,
        pattern(10, 10).view(),
        &info(),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("no/dir/y.tif"), "{e}");
    let names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert!(
        names.iter().all(|n| n == "t0.tif" || n == "t1.tif"),
        "{names:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// GDAL's view of a file through its Python bindings: how far (metres) the file's CRS maps a set
/// of lunar points from the CRS the IAU_2015 code (or `reference`, a PROJ string) maps them —
/// equivalence as a GIS uses it — whether the base geographic CRS is IAU_2015:30100, and the
/// full band as raw little-endian float32 (no numpy needed).
fn gdal_python(path: &Path, reference: &str) -> (f64, Vec<f32>) {
    let script = r#"
import sys
from osgeo import gdal, osr
gdal.UseExceptions()
ds = gdal.Open(sys.argv[1])
def srs(text):
    s = osr.SpatialReference()
    s.SetFromUserInput(text)
    s.SetAxisMappingStrategy(osr.OAMS_TRADITIONAL_GIS_ORDER)
    return s
f = srs(ds.GetProjection())
ref = srs(sys.argv[2])
geog = srs('IAU_2015:30100')
assert f.CloneGeogCS().IsSame(geog, ['IGNORE_DATA_AXIS_TO_SRS_AXIS_MAPPING=YES']), 'base CRS is not IAU_2015:30100'
a = osr.CoordinateTransformation(geog, f)
b = osr.CoordinateTransformation(geog, ref)
worst = 0.0
for lon, lat in [(0, 89), (45, 80), (-120, 75.5), (10, -85), (200, -70), (357.2, -13.4), (38, 9.5), (40, 11), (-3, -12), (170, 3)]:
    try:
        p = a.TransformPoint(lon, lat)
        q = b.TransformPoint(lon, lat)
    except Exception:
        continue
    if all(abs(v) < 1e7 for v in p[:2] + q[:2]):
        worst = max(worst, abs(p[0] - q[0]), abs(p[1] - q[1]))
sys.stderr.write('%r\n' % worst)
band = ds.GetRasterBand(1)
sys.stdout.buffer.write(band.ReadRaster(0, 0, ds.RasterXSize, ds.RasterYSize, buf_type=gdal.GDT_Float32))
"#;
    let o = Command::new("/usr/bin/python3")
        .args(["-c", script])
        .arg(path)
        .arg(reference)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "{err}");
    let worst: f64 = err.trim().parse().unwrap();
    let v = o
        .stdout
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    (worst, v)
}

/// Where the test grids of each CRS start.
fn test_grid(crs: Crs) -> Grid {
    let (x0, y0) = match crs {
        Crs::PolarStereographic { .. } => (-200_000.0, 150_000.0),
        _ => (-37_100.0, 42_000.0),
    };
    Grid::new(crs, 600, 530, x0, y0, 140.0).unwrap()
}

/// Everything GDAL must find in a file written on `grid` with values `a`: size, geotransform,
/// type, NaN no-data, unit, 256² blocks, two overviews, COG layout, DEFLATE, our PROJ string,
/// a CRS equivalent to the IAU_2015 one, the values bit for bit, and COG validity.
fn check_with_gdal(p: &Path, grid: &Grid, a: &Array2<f64>) {
    let (gdalinfo, gdalsrsinfo) = (
        external_tool("gdalinfo", "gdal-bin"),
        external_tool("gdalsrsinfo", "gdal-bin"),
    );
    assert!(
        Path::new(COG_VALIDATOR).is_file(),
        "this test needs GDAL's COG validator: install python3-gdal"
    );
    let crs = grid.crs;
    let j: serde_json::Value =
        serde_json::from_str(&run(Command::new(&gdalinfo).arg("-json").arg(p))).unwrap();
    assert_eq!(j["size"], serde_json::json!([grid.cols, grid.rows]));
    let gt: Vec<f64> = j["geoTransform"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_f64().unwrap())
        .collect();
    assert_eq!(gt, grid.geotransform());
    let band = &j["bands"][0];
    assert_eq!(band["type"], "Float32");
    assert_eq!(band["noDataValue"], "NaN");
    assert_eq!(band["unit"], "m");
    assert_eq!(band["block"], serde_json::json!([256, 256]));
    assert_eq!(band["overviews"].as_array().unwrap().len(), 2);
    assert_eq!(j["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"], "COG");
    assert_eq!(j["metadata"]["IMAGE_STRUCTURE"]["COMPRESSION"], "DEFLATE");
    // GDAL's own PROJ string of the file's CRS is ours, with the Moon radius.
    let p4 = run(Command::new(&gdalsrsinfo).args(["-o", "proj4"]).arg(p));
    assert_eq!(p4.trim(), crs.proj_string(), "{crs:?}");
    // Against the IAU_2015 code where there is one, else PROJ's reading of our string.
    let proj_string = crs.proj_string();
    let reference = crs.iau_2015().unwrap_or(&proj_string);
    let (worst, v) = gdal_python(p, reference);
    assert!(
        worst < 1e-6,
        "{crs:?}: GDAL maps points {worst} m away from {reference}"
    );
    assert_eq!(v.len(), a.len());
    for (x, y) in v.iter().zip(a.iter()) {
        assert!((*x as f64).to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()));
    }
    let out = run(Command::new("/usr/bin/python3").arg(COG_VALIDATOR).arg(p));
    assert!(out.contains("is a valid cloud optimized GeoTIFF"), "{out}");
}

#[test]
#[ignore = "needs GDAL (gdal-bin, python3-gdal); .ci/run runs it"]
fn gdal_reads_crs_geotransform_nodata_and_values_and_validates_the_cog() {
    let dir = scratch("gdal");
    let a = pattern(600, 530);
    for (k, crs) in crss().into_iter().enumerate() {
        let grid = test_grid(crs);
        let p = dir.join(format!("c{k}.tif"));
        write_geotiff(&p, &grid, a.view(), &info()).unwrap();
        check_with_gdal(&p, &grid, &a);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A Byte band (the `mask` and `observations` layers): GDAL reads it as Byte with no-data 255,
/// the values exactly, and the COG validator accepts it.
#[test]
#[ignore = "needs GDAL (gdal-bin, python3-gdal); .ci/run runs it"]
fn gdal_reads_byte_bands_as_byte_cogs() {
    let dir = scratch("gdal-byte");
    let grid = test_grid(crss()[0]);
    let a = byte_pattern(&grid);
    let p = dir.join("count.tif");
    let mut w = sfsfuse::export::CogWriter::create_as(
        &p,
        Some(&grid),
        grid.cols,
        grid.rows,
        &BandInfo {
            description: "observations",
            unit: "",
            metadata: &[],
        },
        Container::Auto,
        sfsfuse::export::SampleFormat::Byte,
    )
    .unwrap();
    w.push(a.view()).unwrap();
    w.finish().unwrap();
    check_byte_cog(&p, &grid, &a);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A count pattern with one no-data pixel, for the Byte writers.
fn byte_pattern(grid: &Grid) -> Array2<f64> {
    Array2::from_shape_fn((grid.rows, grid.cols), |(r, c)| {
        if r == 3 && c == 4 {
            f64::NAN
        } else {
            ((r / 7 + c / 11) % 4) as f64
        }
    })
}

/// GDAL reads `p` as a valid Byte COG with no-data 255, two overviews and the values of `a`.
fn check_byte_cog(p: &Path, grid: &Grid, a: &Array2<f64>) {
    let gdalinfo = external_tool("gdalinfo", "gdal-bin");
    let j: serde_json::Value =
        serde_json::from_str(&run(Command::new(&gdalinfo).arg("-json").arg(p))).unwrap();
    let band = &j["bands"][0];
    assert_eq!(band["type"], "Byte");
    assert_eq!(band["noDataValue"], 255.0);
    assert_eq!(band["overviews"].as_array().unwrap().len(), 2);
    assert_eq!(j["metadata"]["IMAGE_STRUCTURE"]["LAYOUT"], "COG");
    let ps = grid.crs.proj_string();
    let (_, v) = gdal_python(p, grid.crs.iau_2015().unwrap_or(&ps));
    for (x, y) in v.iter().zip(a.iter()) {
        let want = if y.is_nan() { 255.0 } else { *y };
        assert_eq!(*x as f64, want);
    }
    let out = run(Command::new("/usr/bin/python3").arg(COG_VALIDATOR).arg(p));
    assert!(out.contains("is a valid cloud optimized GeoTIFF"), "{out}");
}

/// The optional GDAL writer (`--features gdal`) meets the same bar, and its files read back
/// exactly with the tiff crate too.
#[cfg(feature = "gdal")]
#[test]
#[ignore = "needs GDAL (gdal-bin, python3-gdal); .ci/run runs it"]
fn gdal_cog_driver_output_passes_the_same_checks() {
    let dir = scratch("gdal-writer");
    let a = pattern(600, 530);
    for (k, crs) in crss().into_iter().enumerate() {
        let grid = test_grid(crs);
        let p = dir.join(format!("g{k}.tif"));
        sfsfuse::export::gdal::write_geotiff(&p, &grid, a.view(), &info()).unwrap();
        let t = read_tiff(&p).unwrap();
        assert_eq!(t.geotransform, Some(grid.geotransform()));
        for (x, y) in t.data.iter().zip(a.iter()) {
            assert!(x.to_bits() == y.to_bits() || (x.is_nan() && y.is_nan()));
        }
        check_with_gdal(&p, &grid, &a);
    }
    let names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
    // Byte bands (counts, the mask): the same checks as the pure-Rust writer's, and the same
    // values through the tiff crate.
    let grid = test_grid(crss()[0]);
    let b = byte_pattern(&grid);
    let p = dir.join("count.tif");
    let band = BandInfo {
        description: "observations",
        unit: "",
        metadata: &[],
    };
    sfsfuse::export::gdal::write_geotiff_as(
        &p,
        &grid,
        b.view(),
        &band,
        sfsfuse::export::SampleFormat::Byte,
    )
    .unwrap();
    check_byte_cog(&p, &grid, &b);
    let t = read_tiff(&p).unwrap();
    assert_eq!(t.nodata, Some(255.0));
    for (x, y) in t.data.iter().zip(b.iter()) {
        assert!(x == y || (*x == 255.0 && y.is_nan()), "{x} against {y}");
    }
    let e = sfsfuse::export::gdal::write_geotiff_as(
        &dir.join("bad.tif"),
        &grid,
        b.mapv(|v| v + 0.5).view(),
        &band,
        sfsfuse::export::SampleFormat::Byte,
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("bad.tif") && e.contains("not a whole number"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The streaming writer does not care how rows arrive: 37 at a time gives the same bytes as
/// all at once, and an abandoned writer leaves nothing behind.
#[test]
fn streamed_rows_give_the_same_file() {
    use sfsfuse::export::CogWriter;
    let dir = scratch("stream");
    let a = pattern(600, 530);
    let grid = Grid::new(crss()[0], 600, 530, -37100.0, 42000.0, 140.0).unwrap();
    write_geotiff(&dir.join("whole.tif"), &grid, a.view(), &info()).unwrap();
    let mut w = CogWriter::create(
        &dir.join("rows.tif"),
        Some(&grid),
        530,
        600,
        &info(),
        Container::Auto,
    )
    .unwrap();
    for r0 in (0..600).step_by(37) {
        w.push(a.slice(ndarray::s![r0..(r0 + 37).min(600), ..]))
            .unwrap();
    }
    w.finish().unwrap();
    assert!(
        std::fs::read(dir.join("whole.tif")).unwrap()
            == std::fs::read(dir.join("rows.tif")).unwrap()
    );
    // Too few rows: finish refuses, and neither the product nor a temporary is left.
    let mut w = CogWriter::create(
        &dir.join("short.tif"),
        Some(&grid),
        530,
        600,
        &info(),
        Container::Auto,
    )
    .unwrap();
    w.push(a.slice(ndarray::s![0..100, ..])).unwrap();
    let e = w.finish().unwrap_err().to_string();
    assert!(e.contains("short.tif") && e.contains("100 of 600"), "{e}");
    let w = CogWriter::create(
        &dir.join("dropped.tif"),
        None,
        530,
        600,
        &info(),
        Container::Auto,
    )
    .unwrap();
    drop(w);
    let mut names: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    names.sort();
    assert_eq!(names, ["rows.tif", "whole.tif"]);
    std::fs::remove_dir_all(&dir).unwrap();
}
