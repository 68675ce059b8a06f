use sfsfuse::fusion::{fuse, FusionParams};
use sfsfuse::synth::{generate, rmse, SceneSpec};
use std::time::Instant;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args.get(1).map(|s| s.parse().unwrap()).unwrap_or(256);
    let seed: u64 = args.get(2).map(|s| s.parse().unwrap()).unwrap_or(1);
    let mut params = FusionParams::default();
    let mut spec = SceneSpec {
        size,
        seed,
        ..Default::default()
    };
    for kv in args.iter().skip(3) {
        let (k, v) = kv.split_once('=').unwrap();
        match k {
            "delta" => params.delta = v.parse().unwrap(),
            "eta" => params.eta = v.parse().unwrap(),
            "sdem" => params.sigma_dem = v.parse().unwrap(),
            "sig" => params.albedo_sigmas = v.split(',').map(|x| x.parse().unwrap()).collect(),
            "fin" => params.final_albedo_sigma = v.parse().unwrap(),
            "it" => params.max_iterations = v.parse().unwrap(),
            "cg" => params.cg_iterations = v.parse().unwrap(),
            "tol" => params.tolerance = v.parse().unwrap(),
            "dmin" => spec.crater_min_px = v.parse().unwrap(),
            "dens" => spec.crater_density = v.parse().unwrap(),
            "stripe" => spec.dem_stripe_m = v.parse().unwrap(),
            "dnoise" => spec.dem_noise_m = v.parse().unwrap(),
            "inc" => spec.sun_incidence_deg = v.parse().unwrap(),
            _ => panic!("{k}"),
        }
    }
    let t = Instant::now();
    let scene = generate(&spec);
    let tg = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let f = fuse(&scene.problem(), &params).unwrap();
    let tf = t.elapsed().as_secs_f64();
    let shadow = scene.shadow.iter().filter(|&&s| s).count() as f64 / scene.shadow.len() as f64;
    // Compare heights after removing the mean offset? No: absolute.
    println!(
        "in {:.2} m  out {:.2} m  albedo {:.4}  iters {}  gen {:.2}s fuse {:.2}s shadow {:.3}",
        rmse(&scene.input_dem, &scene.truth_height),
        rmse(&f.height, &scene.truth_height),
        rmse(&f.albedo, &scene.truth_albedo),
        f.iterations(),
        tg,
        tf,
        shadow
    );
    let (il, ih) = split(&(&scene.input_dem - &scene.truth_height));
    let (ol, oh) = split(&(&f.height - &scene.truth_height));
    println!("  error low/high: input {il:.2}/{ih:.2}  output {ol:.2}/{oh:.2}");
    if std::env::var("SAVE").is_ok() {
        let e = &f.height - &scene.truth_height;
        save("/tmp/err_out.png", &e, -40.0, 40.0);
        save(
            "/tmp/err_in.png",
            &(&scene.input_dem - &scene.truth_height),
            -40.0,
            40.0,
        );
        save("/tmp/img.png", &scene.image, 0.0, 0.05);
        save(
            "/tmp/alb_err.png",
            &(&f.albedo - &scene.truth_albedo),
            -0.05,
            0.05,
        );
        save("/tmp/alb.png", &scene.truth_albedo, 0.2, 0.6);
    }
    for s in &f.stages {
        let l = s.iterations.last().unwrap();
        println!(
            "  σρ {:5.1}: {} it ({} cg total) E {:.4e} I {:.4e} D {:.4e} M {:.4e} {:.2}s",
            s.sigma_rho,
            s.iterations.len() - 1,
            s.iterations.iter().map(|r| r.inner).sum::<usize>(),
            l.energy.total,
            l.energy.intensity,
            l.energy.dem,
            l.energy.membrane,
            s.seconds
        );
    }
}

pub fn split(err: &ndarray::Array2<f64>) -> (f64, f64) {
    let n = err.nrows();
    let dct = sfsfuse::spectral::Dct2d::new(n, err.ncols());
    let lo = sfsfuse::spectral::gaussian_filter(&dct, err, 6.0);
    let hi = err - &lo;
    let r =
        |a: &ndarray::Array2<f64>| (a.iter().map(|x| x * x).sum::<f64>() / a.len() as f64).sqrt();
    (r(&lo), r(&hi))
}

pub fn save(path: &str, a: &ndarray::Array2<f64>, lo: f64, hi: f64) {
    let (h, w) = a.dim();
    let data: Vec<u8> = a
        .iter()
        .map(|v| (((v - lo) / (hi - lo)).clamp(0.0, 1.0) * 255.0) as u8)
        .collect();
    let f = std::fs::File::create(path).unwrap();
    let mut e = png::Encoder::new(std::io::BufWriter::new(f), w as u32, h as u32);
    e.set_color(png::ColorType::Grayscale);
    e.set_depth(png::BitDepth::Eight);
    e.write_header().unwrap().write_image_data(&data).unwrap();
}
