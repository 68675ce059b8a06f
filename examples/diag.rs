use sfsfuse::fusion::ops::gradient;
use sfsfuse::photometry::ReflectanceModel;
use sfsfuse::synth::{generate, SceneSpec};

fn main() {
    let crime = std::env::var("CRIME").is_ok();
    let mut spec = SceneSpec {
        size: 256,
        ..Default::default()
    };
    if let Ok(v) = std::env::var("DMIN") {
        spec.crater_min_px = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("DENS") {
        spec.crater_density = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("STRIPE") {
        spec.dem_stripe_m = v.parse().unwrap();
    }
    if let Ok(v) = std::env::var("DNOISE") {
        spec.dem_noise_m = v.parse().unwrap();
    }
    let mut scene = generate(&spec);
    if crime {
        let (p, q) = gradient(scene.truth_height.view(), scene.spec.spacing);
        for ((i, j), v) in scene.image.indexed_iter_mut() {
            *v = scene
                .model
                .shade(
                    p[(i, j)],
                    q[(i, j)],
                    scene.truth_albedo[(i, j)],
                    &scene.sun,
                    &scene.view,
                )
                .r;
        }
    }
    let (p, q) = gradient(scene.truth_height.view(), scene.spec.spacing);
    let mut s = 0.0;
    let mut s2 = 0.0;
    let mut n = 0.0;
    let mut mean = 0.0;
    for ((i, j), &v) in scene.image.indexed_iter() {
        if scene.shadow[(i, j)] {
            continue;
        }
        let r = scene
            .model
            .shade(
                p[(i, j)],
                q[(i, j)],
                scene.truth_albedo[(i, j)],
                &scene.sun,
                &scene.view,
            )
            .r;
        let r2 = scene
            .model
            .shade(
                -p[(i, j)],
                -q[(i, j)],
                scene.truth_albedo[(i, j)],
                &scene.sun,
                &scene.view,
            )
            .r;
        s += (v - r) * (v - r);
        s2 += (v - r2) * (v - r2);
        mean += v;
        n += 1.0;
    }
    let args: Vec<String> = std::env::args().collect();
    let mut params = sfsfuse::fusion::FusionParams::default();
    for kv in args.iter().skip(1) {
        let (k, v) = kv.split_once('=').unwrap();
        match k {
            "delta" => params.delta = v.parse().unwrap(),
            "eta" => params.eta = v.parse().unwrap(),
            "sdem" => params.sigma_dem = v.parse().unwrap(),
            "it" => params.max_iterations = v.parse().unwrap(),
            "psf" => {}
            _ => panic!(),
        }
    }
    let pr = scene.problem();
    let mut z = scene.input_dem.clone();
    let log = sfsfuse::fusion::solve_fixed_albedo(
        &pr,
        &params,
        scene.truth_albedo.view(),
        &mut z,
        &mut |_| {},
    )
    .unwrap();
    let e = log.last().unwrap().energy;
    println!(
        "fixed truth albedo: rmse {:.2} (input {:.2}) its {} E {:.3e} I {:.3e} D {:.3e} M {:.3e}",
        sfsfuse::synth::rmse(&z, &scene.truth_height),
        sfsfuse::synth::rmse(&scene.input_dem, &scene.truth_height),
        log.len() - 1,
        e.total,
        e.intensity,
        e.dem,
        e.membrane
    );
    let mut zt = scene.truth_height.clone();
    let mut p0 = params.clone();
    p0.max_iterations = 0;
    let log = sfsfuse::fusion::solve_fixed_albedo(
        &pr,
        &p0,
        scene.truth_albedo.view(),
        &mut zt,
        &mut |_| {},
    )
    .unwrap();
    let e = log.last().unwrap().energy;
    println!(
        "energy at truth: E {:.3e} I {:.3e} D {:.3e} M {:.3e}",
        e.total, e.intensity, e.dem, e.membrane
    );
    println!(
        "mean {:.4} rms(I - R(truth)) {:.5}  with flipped gradient {:.5}",
        mean / n,
        (s / n).sqrt(),
        (s2 / n).sqrt()
    );
}

#[allow(dead_code)]
pub fn fixed() {}
