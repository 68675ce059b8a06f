//! `sfsfuse demo`: the built-in job. Generates the synthetic scene, fuses it, writes the
//! products and a quick-look, and measures the result against the known truth.

use crate::error::{Error, Result};
use crate::export::{write_geotiff, BandInfo};
use crate::fusion::{fuse, FusionParams};
use crate::grid::{Crs, Grid};
use crate::quicklook::{
    diverging, diverging_ramp, grey, grey_ramp, hillshade, quantiles, rgb, scale_bar, write_sheet,
    ColourBar, Panel,
};
use crate::synth::{generate, rmse, Scene, SceneSpec};
use ndarray::Array2;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// What the demo measured.
#[derive(Debug, Clone, Serialize)]
pub struct DemoReport {
    pub size: usize,
    pub spacing_m: f64,
    pub seed: u64,
    pub image_noise: f64,
    pub input_dem_factor: usize,
    /// Sun of each observation: (azimuth, elevation), degrees.
    pub suns: Vec<(f64, f64)>,
    /// The radiometric gains the fusion estimated, relative to the first observation.
    pub gains: Vec<f64>,
    /// Elevation RMSE of the LOLA-like input DEM against the truth, metres.
    pub input_rmse_m: f64,
    /// Elevation RMSE of the fused DEM against the truth, metres.
    pub result_rmse_m: f64,
    /// input_rmse_m / result_rmse_m.
    pub improvement: f64,
    /// Albedo (Hapke w) RMSE over all pixels.
    pub albedo_rmse: f64,
    /// Albedo RMSE over the pixels that carried photometric information.
    pub albedo_rmse_lit: f64,
    /// Fraction of pixels in shadow in the truth rendering.
    pub shadow_fraction: f64,
    pub iterations: usize,
    pub threads: usize,
    pub generate_seconds: f64,
    pub fusion_seconds: f64,
    pub megapixels_per_second: f64,
    pub outputs: Vec<PathBuf>,
    /// The quick look's error panel spans ± this many metres (`None` without products).
    pub quicklook_error_limit_m: Option<f64>,
    pub params: FusionParams,
    /// Per albedo stage: σ_ρ, and E with each term after every iteration.
    pub stages: Vec<crate::fusion::StageReport>,
}

/// The demo's quick look: the image, hillshades of the input, fused and true DEMs (one light),
/// the error of the fused DEM against the truth with its colour bar, and the albedo. The error
/// panel spans ± `error_limit` metres, or by default the 99th percentile of |fused − true|;
/// returns the span used.
fn write_quicklook(
    path: &Path,
    scene: &Scene,
    f: &crate::fusion::Fusion,
    error_limit: Option<f64>,
) -> Result<f64> {
    let eps = scene.spec.spacing;
    let shade = |z: &Array2<f64>| rgb(&hillshade(z, eps));
    let mut input = shade(&scene.input_dem);
    scale_bar(&mut input, eps);
    let err = &f.height - &scene.truth_height;
    let limit = error_limit.unwrap_or_else(|| {
        quantiles(&err.mapv(f64::abs), 0.0, 0.99)
            .map_or(1.0, |q| q.1)
            .max(0.01)
    });
    let stretched = |a: &Array2<f64>, title: &str, digits: usize| {
        let r = quantiles(a, 0.01, 0.99).unwrap_or((0.0, 1.0));
        Panel {
            title: title.into(),
            picture: grey(a, r),
            bar: Some(ColourBar {
                ramp: grey_ramp,
                low: format!("{:.*}", digits, r.0),
                high: format!("{:.*}", digits, r.1),
            }),
        }
    };
    let panels = [
        stretched(&scene.image, "image I, sr-1", 4),
        Panel {
            title: "input DEM, light az 315 el 45".into(),
            picture: input,
            bar: None,
        },
        Panel {
            title: "fused DEM, same light".into(),
            picture: shade(&f.height),
            bar: None,
        },
        Panel {
            title: "true DEM, same light".into(),
            picture: shade(&scene.truth_height),
            bar: None,
        },
        Panel {
            title: "fused - true, m".into(),
            picture: diverging(&err, limit),
            bar: Some(ColourBar {
                ramp: diverging_ramp,
                low: format!("-{limit:.1}"),
                high: format!("+{limit:.1}"),
            }),
        },
        stretched(&f.albedo, "albedo w", 3),
    ];
    write_sheet(path, &panels, 3)?;
    Ok(limit)
}

/// Scores of a fusion against a scene's truth: (height RMSE, albedo RMSE, albedo RMSE on lit
/// pixels).
pub fn score(scene: &Scene, f: &crate::fusion::Fusion) -> (f64, f64, f64) {
    let (mut s, mut n) = (0.0, 0usize);
    for ((a, t), lit) in f.albedo.iter().zip(&scene.truth_albedo).zip(&f.photometric) {
        if *lit {
            s += (a - t) * (a - t);
            n += 1;
        }
    }
    let lit = if n > 0 {
        (s / n as f64).sqrt()
    } else {
        f64::NAN
    };
    (
        rmse(&f.height, &scene.truth_height),
        rmse(&f.albedo, &scene.truth_albedo),
        lit,
    )
}

/// Where the demo's synthetic scene is put on the Moon: a local stereographic grid centred on
/// the crater Alphonsus (13.4° S, 2.8° W), as in the seed, so the products open in a GIS at a
/// real place with a real lunar CRS.
pub fn demo_grid(spec: &SceneSpec) -> Result<Grid> {
    grid_at(spec, -13.4, 357.2)
}

/// The scene's grid on a local stereographic projection centred at (`lat`, `lon`) degrees.
pub fn grid_at(spec: &SceneSpec, lat: f64, lon: f64) -> Result<Grid> {
    let half = spec.size as f64 * spec.spacing / 2.0;
    Grid::new(
        Crs::Stereographic {
            lat_0: lat,
            lon_0: lon,
        },
        spec.size,
        spec.size,
        -half,
        half,
        spec.spacing,
    )
    .map_err(|e| Error::Usage(e.to_string()))
}

/// `LAT/LON` in degrees: latitude within ±80 (the stereographic grid of a scene must stay off
/// the pole), longitude any finite value (taken modulo 360).
pub fn parse_center(text: &str) -> std::result::Result<(f64, f64), String> {
    let (lat, lon) = crate::synth::parse_pair(text)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .ok_or_else(|| format!("{text:?}: give LAT/LON in finite degrees, e.g. -13.4/30"))?;
    if lat.abs() > 80.0 {
        return Err(format!("{text:?}: latitude {lat} is beyond ±80°"));
    }
    Ok((lat, lon.rem_euclid(360.0)))
}

/// Write the demo's products to `dir`, their paths appended to `outputs`: the fused DEM,
/// albedo and residual, the input and truth DEMs and the image, each a COG on the demo's grid
/// ([`demo_grid`]) with the build and the scene in its metadata, then the quick look. Returns
/// the quick look's error-panel span (metres).
fn write_products(
    dir: &Path,
    spec: &SceneSpec,
    scene: &Scene,
    fusion: &crate::fusion::Fusion,
    error_limit: Option<f64>,
    outputs: &mut Vec<PathBuf>,
) -> Result<f64> {
    let grid = demo_grid(spec)?;
    let meta = [
        ("SFSFUSE_VERSION", crate::BUILD.to_string()),
        ("SFSFUSE_SCENE", format!("synthetic, seed {}", spec.seed)),
    ];
    let layers: [(&str, &Array2<f64>, &str, &str); 6] = [
        (
            "dem",
            &fusion.height,
            "fused height above the 1737.4 km sphere",
            "m",
        ),
        (
            "albedo",
            &fusion.albedo,
            "Hapke single-scattering albedo w",
            "",
        ),
        (
            "residual",
            &fusion.residual,
            "|I - R| at the solution, sr^-1; no data without photometric information",
            "sr-1",
        ),
        (
            "input_dem",
            &scene.input_dem,
            "synthetic LOLA-like input height",
            "m",
        ),
        (
            "truth_dem",
            &scene.truth_height,
            "synthetic truth height",
            "m",
        ),
        (
            "image",
            &scene.image,
            "synthetic image, bidirectional reflectance",
            "sr-1",
        ),
    ];
    for (stem, a, description, unit) in layers {
        let path = dir.join(format!("{stem}.tif"));
        let info = BandInfo {
            description,
            unit,
            metadata: &meta,
        };
        write_geotiff(&path, &grid, a.view(), &info)?;
        outputs.push(path);
    }
    let ql = dir.join("quicklook.png");
    let limit = write_quicklook(&ql, scene, fusion, error_limit)?;
    outputs.push(ql);
    Ok(limit)
}

/// Run the demo on `spec`, writing products to `out` when given; the quick look's error panel
/// spans ± `error_limit` metres when given (so that quick looks of several runs compare).
pub fn run(
    spec: &SceneSpec,
    params: &FusionParams,
    out: Option<&Path>,
    error_limit: Option<f64>,
) -> Result<DemoReport> {
    if spec.size < 16 {
        return Err(Error::Usage(format!(
            "--size {} is too small: use at least 16",
            spec.size
        )));
    }
    if let Some(l) = error_limit.filter(|l| !(l.is_finite() && *l > 0.0)) {
        return Err(Error::Usage(format!(
            "--error-limit {l}: give the error panel's span as a positive number of metres"
        )));
    }
    // Fail before computing if the products cannot be written.
    if let Some(dir) = out {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    }
    let t0 = Instant::now();
    let scene = generate(spec);
    let generate_seconds = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let fusion = fuse(&scene.problem(), params)?;
    let fusion_seconds = t1.elapsed().as_secs_f64();
    let (result_rmse_m, albedo_rmse, albedo_rmse_lit) = score(&scene, &fusion);
    let input_rmse_m = rmse(&scene.input_dem, &scene.truth_height);
    let mut outputs = Vec::new();
    let mut quicklook_error_limit_m = None;
    if let Some(dir) = out {
        quicklook_error_limit_m = Some(write_products(
            dir,
            spec,
            &scene,
            &fusion,
            error_limit,
            &mut outputs,
        )?);
    }
    let shadow_fraction =
        scene.shadow.iter().filter(|&&s| s).count() as f64 / scene.shadow.len() as f64;
    Ok(DemoReport {
        size: spec.size,
        spacing_m: spec.spacing,
        seed: spec.seed,
        image_noise: spec.noise,
        input_dem_factor: spec.dem_factor,
        suns: std::iter::once((spec.sun_azimuth_deg, 90.0 - spec.sun_incidence_deg))
            .chain(
                spec.more
                    .iter()
                    .map(|m| (m.sun_azimuth_deg, 90.0 - m.sun_incidence_deg)),
            )
            .collect(),
        gains: fusion.gains.clone(),
        input_rmse_m,
        result_rmse_m,
        improvement: input_rmse_m / result_rmse_m,
        albedo_rmse,
        albedo_rmse_lit,
        shadow_fraction,
        iterations: fusion.iterations(),
        threads: rayon::current_num_threads(),
        generate_seconds,
        fusion_seconds,
        megapixels_per_second: (spec.size * spec.size) as f64 / 1e6 / fusion_seconds,
        outputs,
        quicklook_error_limit_m,
        params: params.clone(),
        stages: fusion.stages.clone(),
    })
}

impl DemoReport {
    /// A plain-text table.
    pub fn table(&self) -> String {
        let mut s = String::new();
        let mut row = |k: &str, v: String| s.push_str(&format!("{k:<34} {v}\n"));
        row(
            "scene",
            format!(
                "{0}×{0} px at {1} m/px, seed {2}, {3:.0} % image noise, input DEM {4}× coarser",
                self.size,
                self.spacing_m,
                self.seed,
                self.image_noise * 100.0,
                self.input_dem_factor
            ),
        );
        let suns: Vec<String> = self
            .suns
            .iter()
            .map(|(a, e)| format!("{a:.0}/{e:.0}"))
            .collect();
        row(
            "observations (Sun azimuth/elevation)",
            format!("{}: {}", self.suns.len(), suns.join(", ")),
        );
        if self.gains.len() > 1 {
            let g: Vec<String> = self.gains.iter().map(|g| format!("{g:.4}")).collect();
            row("estimated gains", g.join(", "));
        }
        row(
            "input DEM elevation RMSE",
            format!("{:.2} m", self.input_rmse_m),
        );
        row(
            "fused DEM elevation RMSE",
            format!(
                "{:.2} m  ({:.2}× lower)",
                self.result_rmse_m, self.improvement
            ),
        );
        row(
            "albedo RMSE (all / lit pixels)",
            format!("{:.4} / {:.4}", self.albedo_rmse, self.albedo_rmse_lit),
        );
        row(
            "shadowed pixels",
            format!("{:.1} %", self.shadow_fraction * 100.0),
        );
        row(
            "iterations (Gauss–Newton or sweeps)",
            format!("{}", self.iterations),
        );
        row(
            "fusion wall time",
            format!("{:.2} s on {} threads", self.fusion_seconds, self.threads),
        );
        row(
            "throughput",
            format!(
                "{:.3} MP/s ({:.2} s/MP)",
                self.megapixels_per_second,
                1.0 / self.megapixels_per_second
            ),
        );
        for o in &self.outputs {
            row("wrote", o.display().to_string());
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centres_parse_and_bad_ones_are_refused() {
        assert_eq!(parse_center("-13.4/30").unwrap(), (-13.4, 30.0));
        assert_eq!(parse_center("10/-2.8").unwrap(), (10.0, 357.2));
        for bad in ["", "-13.4", "a/3", "3/inf", "81/0"] {
            assert!(parse_center(bad).is_err(), "{bad}");
        }
    }
}
