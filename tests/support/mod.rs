//! Shared by the end-to-end tests: the synthetic scene as mission-format products, workflow
//! files over its grid, and running the binary.
#![allow(dead_code)]

use sfsfuse::synth::{generate, products, SceneSpec};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::OnceLock;

pub fn sfsfuse() -> Command {
    Command::new(env!("CARGO_BIN_EXE_sfsfuse"))
}

/// A fresh scratch directory `name` of this test process under the system's temporary
/// directory. The first call also sweeps away what earlier runs of this test binary left
/// there ([`sweep_stale_scratch`]).
pub fn scratch(name: &str) -> PathBuf {
    static SWEEP: std::sync::Once = std::sync::Once::new();
    SWEEP.call_once(sweep_stale_scratch);
    let d = std::env::temp_dir().join(format!(
        "sfsfuse-{}-{}-{name}",
        env!("CARGO_CRATE_NAME"),
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Removes the scratch directories `sfsfuse-<crate>-<pid>-*` of this test binary whose
/// process is no longer running. The products [`scene_products`] shares through a static are
/// never dropped (20–60 MB a run), and a failed test leaves its directory for inspection: swept
/// here, on the next run, they do not pile up. Only where `/proc` tells which processes run
/// (Linux); a directory whose process id is running again is left alone.
pub fn sweep_stale_scratch() {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let prefix = format!("sfsfuse-{}-", env!("CARGO_CRATE_NAME"));
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(rest) = name.to_str().and_then(|n| n.strip_prefix(&prefix)) else {
            continue;
        };
        let Some(pid) = rest.split('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        if pid != std::process::id() && !Path::new("/proc").join(pid.to_string()).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Products of one synthetic scene, written once per test binary.
pub fn scene_products(size: usize, seed: u64) -> &'static products::Products {
    static SMALL: OnceLock<products::Products> = OnceLock::new();
    static LARGE: OnceLock<products::Products> = OnceLock::new();
    let cell = if size <= 256 { &SMALL } else { &LARGE };
    cell.get_or_init(|| {
        let spec = SceneSpec {
            size,
            seed,
            ..SceneSpec::default()
        };
        let scene = generate(&spec);
        let grid = sfsfuse::demo::demo_grid(&spec).unwrap();
        products::write(&scene, &grid, &scratch(&format!("products-{size}"))).unwrap()
    })
}

/// The two overlapping strips of `workflows/synthetic_strips.toml` (the demo's first two Suns,
/// the second observation 5 % brighter) over the `size`² scene of `seed`, written as products
/// under a fresh scratch directory `name`, which is returned with them.
pub fn strip_products(size: usize, seed: u64, name: &str) -> (PathBuf, products::Products) {
    observation_products(
        size,
        seed,
        (&sfsfuse::synth::DEMO_SUNS[..2], &[1.0, 1.05], true),
        name,
    )
}

/// The `size`² scene of `seed` seen under `suns` (azimuth/elevation, degrees) with `gains`
/// (empty: all 1), each observation a strip of the columns when `strips`, written as products
/// under a fresh scratch directory `name`, which is returned with them.
pub fn observation_products(
    size: usize,
    seed: u64,
    (suns, gains, strips): (&[(f64, f64)], &[f64], bool),
    name: &str,
) -> (PathBuf, products::Products) {
    products_of(
        &spec_of(size, seed).with_observations(suns, gains, strips),
        name,
        &[],
    )
}

/// [`observation_products`] with each observation's Sun moving along the rows by
/// `drifts[k]` (Δazimuth/Δelevation, degrees, first row to last; `synth --sun-drift`).
pub fn drifting_sun_products(
    size: usize,
    seed: u64,
    suns: &[(f64, f64)],
    drifts: &[[f64; 2]],
    name: &str,
) -> (PathBuf, products::Products) {
    let spec = spec_of(size, seed)
        .with_observations(suns, &[], false)
        .with_sun_drifts(drifts)
        .unwrap();
    products_of(&spec, name, &[])
}

/// The synthetic scene of `size`² pixels and `seed`, otherwise the defaults.
fn spec_of(size: usize, seed: u64) -> SceneSpec {
    SceneSpec {
        size,
        seed,
        ..SceneSpec::default()
    }
}

/// The products of `spec` in a fresh scratch directory `name`, observation k's detector pixels
/// `pixel_factors[k]` grid pixels wide (missing: 1).
fn products_of(
    spec: &SceneSpec,
    name: &str,
    pixel_factors: &[usize],
) -> (PathBuf, products::Products) {
    products_in(spec, &scratch(name), &[], pixel_factors)
}

/// The products of `spec` in `dir`/products, observation k's LOC misplacing its pixels by
/// `loc_errors[k]` and its detector pixels `pixel_factors[k]` grid pixels wide (missing: none
/// and 1; `products::write_observed`).
fn products_in(
    spec: &SceneSpec,
    dir: &Path,
    loc_errors: &[products::ProductErrors],
    pixel_factors: &[usize],
) -> (PathBuf, products::Products) {
    let scene = generate(spec);
    let grid = sfsfuse::demo::demo_grid(spec).unwrap();
    let p = products::write_observed(
        &scene,
        &grid,
        &dir.join("products"),
        loc_errors,
        pixel_factors,
    )
    .unwrap();
    (dir.to_path_buf(), p)
}

/// [`observation_products`] written twice in a fresh scratch directory `name`: as they are
/// (`in_place/`) and with observation k's LOC misplacing its pixels by `loc_errors[k]`
/// (`moved/`; `synth --loc-offset`/`--loc-drift`).
pub fn observation_products_moved(
    size: usize,
    seed: u64,
    suns: &[(f64, f64)],
    loc_errors: &[products::ProductErrors],
    name: &str,
) -> (PathBuf, products::Products, products::Products) {
    let spec = spec_of(size, seed).with_observations(suns, &[], false);
    let dir = scratch(name);
    let (_, p) = products_in(&spec, &dir.join("in_place"), &[], &[]);
    let (_, q) = products_in(&spec, &dir.join("moved"), loc_errors, &[]);
    (dir, p, q)
}

/// [`observation_products`] with observation k's detector pixels `pixel_factors[k]` grid
/// pixels wide (`synth --pixel-factor`, `products::write_observed`).
pub fn coarse_observation_products(
    size: usize,
    seed: u64,
    suns: &[(f64, f64)],
    pixel_factors: &[usize],
    name: &str,
) -> (PathBuf, products::Products) {
    products_of(
        &spec_of(size, seed).with_observations(suns, &[], false),
        name,
        pixel_factors,
    )
}

/// A workflow over the scene's own grid (the region in map metres).
pub fn workflow(p: &products::Products, out: &Path, tile: usize, extra: &str) -> String {
    let half = p.grid.rows as f64 * p.grid.spacing / 2.0;
    format!(
        r#"kind = "orbital"
[inputs]
m3 = [{m3}]
lola = ["{lola}"]
solar_spectrum = "{solar}"
# The LOLA-like product samples a DEM whose own point spread is 4/√2 px every 3.38 px:
# σ = √(2.83² + 3.38²/12) ≈ 3.0 px (docs/workflows.md).
dem_psf_sigma_px = 3.0
[region]
x_min = {lo}
x_max = {half}
y_min = {lo}
y_max = {half}
[grid]
center_lat = -13.4
center_lon = 357.2
resolution_m = 140.0
[tiling]
tile_size = {tile}
[output]
directory = "{out}"
layers = ["dem", "albedo", "residual", "mask", "input_dem"]
{extra}
"#,
        m3 = p
            .m3_labels
            .iter()
            .map(|l| format!("{:?}", l.display().to_string()))
            .collect::<Vec<_>>()
            .join(", "),
        lola = p.lola_label.display(),
        solar = p.solar_table.display(),
        lo = -half,
        out = out.display(),
    )
}

/// [`workflow`] on a grid of `resolution_m` metres instead of the scene's 140 m, with the
/// DEM's point spread (3 px at 140 m) rescaled to that grid's pixels.
pub fn workflow_at(p: &products::Products, out: &Path, resolution_m: f64) -> String {
    workflow(p, out, 512, "")
        .replace(
            "resolution_m = 140.0",
            &format!("resolution_m = {resolution_m:.1}"),
        )
        .replace(
            "dem_psf_sigma_px = 3.0",
            &format!("dem_psf_sigma_px = {}", 3.0 * 140.0 / resolution_m),
        )
}

pub fn write_workflow(dir: &Path, text: &str) -> PathBuf {
    let p = dir.join("workflow.toml");
    std::fs::write(&p, text).unwrap();
    p
}

pub fn run_ok(args: &[&str], wf: &Path) {
    let o = sfsfuse().args(args).arg(wf).output().unwrap();
    assert!(
        o.status.success(),
        "sfsfuse {args:?} failed:\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

pub fn rmse(a: &ndarray::Array2<f64>, b: &ndarray::Array2<f64>) -> f64 {
    let s: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum();
    (s / a.len() as f64).sqrt()
}

/// A copy of `p`'s files in `dir`, with the copy's paths.
pub fn copy_products(p: &products::Products, dir: &Path) -> products::Products {
    let src = p.m3_label.parent().unwrap();
    std::fs::create_dir_all(dir).unwrap();
    for e in std::fs::read_dir(src).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), dir.join(e.file_name())).unwrap();
    }
    let mv = |f: &Path| dir.join(f.file_name().unwrap());
    products::Products {
        m3_label: mv(&p.m3_label),
        m3_labels: p.m3_labels.iter().map(|l| mv(l)).collect(),
        lola_label: mv(&p.lola_label),
        solar_table: mv(&p.solar_table),
        truth_dem: mv(&p.truth_dem),
        truth_albedo: mv(&p.truth_albedo),
        grid: p.grid,
        spec: p.spec.clone(),
    }
}

/// Rewrite the float32 samples of a band-interleaved-by-line cube in place:
/// `f(line, band, sample, value)`.
pub fn edit_bil(
    path: &Path,
    bands: usize,
    samples: usize,
    f: impl Fn(usize, usize, usize, f32) -> f32,
) {
    let mut b = std::fs::read(path).unwrap();
    for (k, c) in b.chunks_exact_mut(4).enumerate() {
        let (line, rest) = (k / (bands * samples), k % (bands * samples));
        let (band, sample) = (rest / samples, rest % samples);
        let v = f(
            line,
            band,
            sample,
            f32::from_le_bytes([c[0], c[1], c[2], c[3]]),
        );
        c.copy_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, b).unwrap();
}

/// An M3 solar spectrum table for `mode`'s band centres: a 5778 K black body at 1 AU.
pub fn blackbody_table(path: &Path, mode: pds::m3::Mode) {
    let rows: String = pds::m3::band_centres(mode)
        .iter()
        .map(|&w| format!("{w:.2} {:.4}\n", products::blackbody_irradiance(w)))
        .collect();
    std::fs::write(path, rows).unwrap();
}

/// max |a − b| over the pixels.
pub fn largest_difference(a: &ndarray::Array2<f64>, b: &ndarray::Array2<f64>) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// A copy of `p`'s product set in `dest` in which observation `k`'s LOC backplane puts every
/// pixel `shift_m` = [east, north] metres from where it lies (as a selenolocation error would),
/// with the products' paths pointing there.
pub fn displaced_products(
    p: &products::Products,
    k: usize,
    shift_m: [f64; 2],
    dest: &Path,
) -> products::Products {
    std::fs::create_dir_all(dest).unwrap();
    for e in std::fs::read_dir(p.m3_label.parent().unwrap()).unwrap() {
        let e = e.unwrap().path();
        if e.is_file() {
            std::fs::copy(&e, dest.join(e.file_name().unwrap())).unwrap();
        }
    }
    let at = |f: &Path| dest.join(f.file_name().unwrap());
    let obs = pds::m3::Observation::open(&at(&p.m3_labels[k])).unwrap();
    let loc = obs.part("LOC").unwrap();
    assert_eq!(loc.bands, 3);
    let bytes = std::fs::read(&loc.path).unwrap();
    let start = loc.offset as usize;
    let mut v: Vec<f64> = bytes[start..]
        .chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
        .collect();
    // Line-interleaved longitude, latitude, radius (PC_REAL 64): each line's longitudes, then
    // its latitudes. Metres on the 1737.4 km sphere.
    let r = 1_737_400.0;
    let n = loc.samples;
    for line in v.chunks_exact_mut(3 * n) {
        let (lon, rest) = line.split_at_mut(n);
        for (lo, la) in lon.iter_mut().zip(rest[..n].iter_mut()) {
            *lo += (shift_m[0] / (r * la.to_radians().cos())).to_degrees();
            *la += (shift_m[1] / r).to_degrees();
        }
    }
    let mut out = bytes[..start].to_vec();
    out.extend(v.iter().flat_map(|x| x.to_le_bytes()));
    std::fs::write(&loc.path, out).unwrap();
    let mut q = p.clone();
    q.m3_label = at(&p.m3_label);
    q.m3_labels = p.m3_labels.iter().map(|l| at(l)).collect();
    q.lola_label = at(&p.lola_label);
    q.solar_table = at(&p.solar_table);
    q
}
