//! End-to-end checks of the science core on synthetic scenes with known truth.

use sfsfuse::demo::score;
use sfsfuse::fusion::{fuse, initial_albedo, solve_fixed_albedo, FusionParams, SolverKind};
use sfsfuse::synth::{generate, rmse, SceneSpec};

/// The accuracy bar of the science-core issue, on a scene the defaults were not tuned on
/// (seed 10; seeds 7–9 give inputs under 20 m RMSE, too easy to count): 140 m/px, 1 % image noise, an input DEM 4× coarser with RMSE ≥ 20 m; the fused DEM
/// must be ≤ 10 m RMSE and at least 2× better than the input, the albedo ≤ 0.01 RMSE.
#[test]
fn meets_the_accuracy_bar_on_an_unseen_scene() {
    let spec = SceneSpec {
        size: 256,
        seed: 10,
        ..SceneSpec::default()
    };
    let scene = generate(&spec);
    assert_eq!(spec.spacing, 140.0);
    assert_eq!(spec.noise, 0.01);
    assert_eq!(spec.dem_factor, 4);
    let input = rmse(&scene.input_dem, &scene.truth_height);
    assert!(
        input >= 20.0,
        "the scene must be at least as hard as the seed's: input RMSE {input:.2} m"
    );
    let f = fuse(&scene.problem(), &FusionParams::default()).unwrap();
    let (height, albedo, albedo_lit) = score(&scene, &f);
    eprintln!("input {input:.2} m, fused {height:.2} m, albedo {albedo:.4} (lit {albedo_lit:.4})");
    assert!(height <= 10.0, "elevation RMSE {height:.2} m > 10 m");
    assert!(
        height * 2.0 <= input,
        "elevation RMSE {height:.2} m is not 2× below the input's {input:.2} m"
    );
    assert!(albedo <= 0.01, "albedo RMSE {albedo:.4} > 0.01");
}

/// Both z-solvers minimise the same energy: from the same start at fixed albedo the `paper`
/// iteration approaches the energy the fast solver reaches, and never goes below it.
#[test]
fn paper_and_fast_solvers_reach_the_same_energy() {
    solvers_agree(&SceneSpec {
        size: 32,
        seed: 3,
        ..SceneSpec::default()
    });
}

/// The same with two observations in overlapping strips, the second 4 % brighter: both solvers
/// minimise the summed energy (gains, edge ramps, weights).
#[test]
fn paper_and_fast_solvers_reach_the_same_energy_with_two_observations() {
    solvers_agree(
        &SceneSpec {
            size: 32,
            seed: 3,
            ..SceneSpec::default()
        }
        .with_observations(&sfsfuse::synth::DEMO_SUNS[..2], &[1.0, 1.04], true),
    );
}

/// The edge-aware membrane's energy (per-pixel weights from the starting surface, here the
/// truth, so that they are not uniform): the `paper` iteration approaches the fast solver's
/// minimum of it too.
#[test]
fn paper_and_fast_solvers_reach_the_same_energy_with_an_edge_aware_membrane() {
    let spec = SceneSpec {
        size: 32,
        seed: 3,
        ..SceneSpec::default()
    };
    let scene = generate(&spec);
    solvers_agree_from(&spec, FusionParams::edge_aware(), &scene.truth_height);
}

/// The edge-aware membrane (`FusionParams::edge_aware`, docs/science.md) on the unseen scene
/// of the accuracy bar, one Sun: at least 7 % below the default's elevation error (9.04 →
/// 8.23 m measured), the albedo no worse.
#[test]
fn the_edge_aware_membrane_lowers_single_image_errors() {
    let spec = SceneSpec {
        size: 256,
        seed: 10,
        ..SceneSpec::default()
    };
    let scene = generate(&spec);
    let plain = score(
        &scene,
        &fuse(&scene.problem(), &FusionParams::default()).unwrap(),
    );
    let edge = score(
        &scene,
        &fuse(&scene.problem(), &FusionParams::edge_aware()).unwrap(),
    );
    eprintln!(
        "plain {:.2} m, albedo {:.4}; edge-aware {:.2} m, albedo {:.4}",
        plain.0, plain.1, edge.0, edge.1
    );
    assert!(
        edge.0 <= 0.93 * plain.0,
        "{:.2} m vs {:.2} m",
        edge.0,
        plain.0
    );
    assert!(
        edge.1 <= plain.1 * 1.02,
        "albedo {:.4} vs {:.4}",
        edge.1,
        plain.1
    );
}

fn solvers_agree(spec: &SceneSpec) {
    let scene = generate(spec);
    solvers_agree_from(spec, FusionParams::default(), &scene.input_dem);
}

/// Both solvers from `start` at the first stage's albedo, with `base`'s energy.
fn solvers_agree_from(spec: &SceneSpec, base: FusionParams, start: &ndarray::Array2<f64>) {
    let scene = generate(spec);
    let pr = scene.problem();
    let rho = initial_albedo(&pr, &base).unwrap();
    let mut zf = start.clone();
    let fast = FusionParams {
        max_iterations: 200,
        tolerance: 1e-12,
        step_tolerance: 0.0,
        cg_tolerance: 1e-6,
        cg_iterations: 500,
        ..base.clone()
    };
    let lf = solve_fixed_albedo(&pr, &fast, rho.view(), &mut zf, &mut |_| {}).unwrap();
    let mut zp = start.clone();
    let paper = FusionParams {
        solver: SolverKind::Paper,
        max_iterations: 20000,
        tolerance: 1e-13,
        ..base.clone()
    };
    let lp = solve_fixed_albedo(&pr, &paper, rho.view(), &mut zp, &mut |_| {}).unwrap();
    let (e0, ef, ep) = (
        lf[0].energy.total,
        lf.last().unwrap().energy.total,
        lp.last().unwrap().energy.total,
    );
    eprintln!(
        "start {e0:.10e}, fast {ef:.10e} ({} its), paper {ep:.10e} ({} sweeps)",
        lf.len() - 1,
        lp.len() - 1
    );
    assert!(ef < 0.9 * e0, "the fast solver barely moved: {e0} → {ef}");
    assert!(
        ep >= ef * (1.0 - 1e-6),
        "paper went below the fast solver's minimum: {ep} < {ef}"
    );
    assert!(
        ep <= ef * (1.0 + 1e-2),
        "paper did not approach the same minimum: {ep} vs {ef}"
    );
    assert!(
        lp.windows(2)
            .all(|w| w[1].energy.total <= w[0].energy.total),
        "paper energy must not increase"
    );
    assert!(
        rmse(&zf, &zp) < 2.0,
        "the two minimisers differ by {:.2} m RMS",
        rmse(&zf, &zp)
    );
    assert_eq!(paper.solver, SolverKind::Paper);
}

/// The same inputs give bit-identical outputs with 1 and 2 threads.
#[test]
fn results_do_not_depend_on_the_thread_count() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let scene = generate(&SceneSpec {
                    size: 64,
                    seed: 11,
                    ..SceneSpec::default()
                });
                let f = fuse(&scene.problem(), &FusionParams::default()).unwrap();
                (scene.image, f.height, f.albedo)
            })
    };
    let (i1, h1, a1) = run(1);
    let (i2, h2, a2) = run(2);
    let bits = |a: &ndarray::Array2<f64>| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&i1), bits(&i2));
    assert_eq!(bits(&h1), bits(&h2));
    assert_eq!(bits(&a1), bits(&a2));
}

/// Bad problems are refused with a message naming the problem.
#[test]
fn bad_problems_are_reported() {
    let scene = generate(&SceneSpec {
        size: 16,
        seed: 1,
        ..SceneSpec::default()
    });
    let mut dem = scene.input_dem.clone();
    dem[(3, 5)] = f64::NAN;
    let mut pr = scene.problem();
    pr.dem = dem.view();
    let e = fuse(&pr, &FusionParams::default()).unwrap_err().to_string();
    assert!(e.contains("row 3") && e.contains("column 5"), "{e}");
    let small = ndarray::Array2::<f64>::zeros((8, 8));
    let mut pr = scene.problem();
    pr.dem = small.view();
    let e = fuse(&pr, &FusionParams::default()).unwrap_err().to_string();
    assert!(e.contains("(16, 16)") && e.contains("(8, 8)"), "{e}");
    let dark = ndarray::Array2::<f64>::zeros((16, 16));
    let mut pr = scene.problem();
    pr.observations[0].image = dark.view();
    let e = fuse(&pr, &FusionParams::default()).unwrap_err().to_string();
    assert!(e.contains("no pixel"), "{e}");
    // A point spread that is no number is refused by its name, not through the membrane
    // parameters the rule for a coarse DEM would derive from it.
    for psf in [f64::NAN, -1.0, f64::INFINITY] {
        let mut pr = scene.problem();
        pr.dem_psf_sigma = psf;
        let e = fuse(&pr, &FusionParams::default()).unwrap_err().to_string();
        assert!(e.contains("dem_psf_sigma"), "{psf}: {e}");
    }
    let params = FusionParams {
        eta: -1.0,
        ..FusionParams::default()
    };
    let e = fuse(&scene.problem(), &params).unwrap_err().to_string();
    assert!(e.contains("eta"), "{e}");
    for (name, params) in [
        (
            "step_tolerance",
            FusionParams {
                step_tolerance: -0.01,
                ..FusionParams::default()
            },
        ),
        (
            "curvature_residual",
            FusionParams {
                curvature_residual: f64::NAN,
                ..FusionParams::default()
            },
        ),
    ] {
        let e = fuse(&scene.problem(), &params).unwrap_err().to_string();
        assert!(e.contains(name), "{e}");
    }
}

/// A DEM 14× coarser than the image (2 km posting under 140 m/px, today's noise model): with
/// σ_B and σ_DEM following the DEM's resolution and the membrane of
/// `fusion::coarse_dem_membrane`, the fused error is ≤ 0.4× the input's, on the 512² scene
/// and on two 256² ones (with the plain membrane those were at 0.414× and 0.468×).
#[test]
fn a_dem_14_times_coarser_is_refined_below_0_4_of_its_error() {
    for (size, seed) in [(512, 1), (256, 10), (256, 2)] {
        let spec = SceneSpec {
            size,
            seed,
            dem_factor: 14,
            ..SceneSpec::default()
        };
        let scene = generate(&spec);
        let params = FusionParams {
            sigma_dem: sfsfuse::fusion::dem_sigma(14.0),
            ..FusionParams::default()
        };
        let f = fuse(&scene.problem(), &params).unwrap();
        let (e_in, e_out) = (
            rmse(&scene.input_dem, &scene.truth_height),
            rmse(&f.height, &scene.truth_height),
        );
        eprintln!(
            "14× coarse DEM, {size}², seed {seed}: {e_in:.2} m → {e_out:.2} m ({:.3}×)",
            e_out / e_in
        );
        assert!(
            e_out <= 0.4 * e_in,
            "{size}², seed {seed}: {e_out:.2} m > 0.4 × {e_in:.2} m"
        );
    }
}

/// The membrane rule for a coarse DEM: nothing changes up to 5× (the 4× scenes every other
/// bar is measured on keep their membrane), the edge-aware membrane in full from 7×, a
/// continuous ramp between, and the weight where several observations overlap (η × the
/// multi factor) kept throughout. The rule is applied once: its result has the flag cleared.
#[test]
fn the_coarse_dem_membrane_ramps_in_between_5_and_7_times_coarser() {
    use sfsfuse::fusion::{
        coarse_dem_membrane, dem_psf_sigma, COARSE_DEM_EDGE_SLOPE, COARSE_DEM_ETA,
    };
    let base = FusionParams::default();
    let at = |f: f64| coarse_dem_membrane(&base, dem_psf_sigma(f));
    for f in [1.0, 4.0, 5.0] {
        let p = at(f);
        assert_eq!((p.eta, p.edge_membrane_slope), (base.eta, 0.0), "{f}×");
        assert!(!p.coarse_dem_membrane);
    }
    for f in [7.0, 14.0, 54.0] {
        let p = at(f);
        assert!((p.eta - COARSE_DEM_ETA).abs() < 1e-12, "{f}×: η {}", p.eta);
        assert!((p.edge_membrane_slope - COARSE_DEM_EDGE_SLOPE).abs() < 1e-12);
    }
    let mut last = (base.eta, f64::INFINITY);
    for k in 1..40 {
        let p = at(5.0 + 0.05 * k as f64);
        assert!(
            p.eta >= last.0 && p.edge_membrane_slope <= last.1,
            "not monotone at {k}"
        );
        assert!((p.eta * p.multi_eta_factor - base.eta * base.multi_eta_factor).abs() < 1e-12);
        last = (p.eta, p.edge_membrane_slope);
    }
    // Off, already edge-aware, or applied once: unchanged.
    let off = FusionParams {
        coarse_dem_membrane: false,
        ..base.clone()
    };
    assert_eq!(coarse_dem_membrane(&off, dem_psf_sigma(14.0)).eta, base.eta);
    let edge = FusionParams::edge_aware();
    assert_eq!(
        coarse_dem_membrane(&edge, dem_psf_sigma(14.0)).eta,
        edge.eta
    );
    let once = at(14.0);
    assert_eq!(coarse_dem_membrane(&once, dem_psf_sigma(14.0)), once);
}

/// A DEM as fine as the grid or finer (no point spread to undo): the result is no worse than
/// the input.
#[test]
fn a_dem_as_fine_as_the_grid_is_not_made_worse() {
    let spec = SceneSpec {
        size: 256,
        seed: 10,
        dem_factor: 1,
        ..SceneSpec::default()
    };
    let scene = generate(&spec);
    // As fine as the grid, and SLDEM2015-like (59 m) under 140 m.
    for factor in [1.0, 59.0 / 140.0] {
        let params = FusionParams {
            sigma_dem: sfsfuse::fusion::dem_sigma(factor),
            ..FusionParams::default()
        };
        let mut pr = scene.problem();
        pr.dem_psf_sigma = sfsfuse::fusion::dem_psf_sigma(factor);
        let f = fuse(&pr, &params).unwrap();
        let (e_in, e_out) = (
            rmse(&scene.input_dem, &scene.truth_height),
            rmse(&f.height, &scene.truth_height),
        );
        eprintln!("fine DEM (factor {factor:.2}): {e_in:.2} m → {e_out:.2} m");
        assert!(e_out <= e_in, "{e_out:.2} m > the input's {e_in:.2} m");
    }
}

/// Where the image does not reach, the result is the input DEM: an image covering only the
/// middle half of the columns leaves the DEM untouched beyond the 3σ_DEM band, and the
/// correction fades monotonically across the band (no step, no ring).
#[test]
fn no_relief_is_invented_where_the_image_does_not_reach() {
    let spec = SceneSpec {
        size: 256,
        seed: 10,
        ..SceneSpec::default()
    };
    let mut scene = generate(&spec);
    let n = spec.size;
    let (c0, c1) = (n / 4, 3 * n / 4);
    for ((_, j), v) in scene.image.indexed_iter_mut() {
        if j < c0 || j >= c1 {
            *v = f64::NAN;
        }
    }
    let params = FusionParams::default();
    let f = fuse(&scene.problem(), &params).unwrap();
    let band = sfsfuse::fusion::support::band(params.sigma_dem).1;
    let col_rms = |j: usize| {
        let s: f64 = (0..n)
            .map(|i| (f.height[(i, j)] - scene.input_dem[(i, j)]).powi(2))
            .sum();
        (s / n as f64).sqrt()
    };
    let dist = |j: usize| {
        if j < c0 {
            (c0 - j) as f64
        } else if j >= c1 {
            (j + 1 - c1) as f64
        } else {
            0.0
        }
    };
    let beyond: Vec<f64> = (0..n).filter(|&j| dist(j) > band).map(col_rms).collect();
    let worst = beyond.iter().cloned().fold(0.0, f64::max);
    assert!(worst <= 0.5, "change beyond the band {worst:.3} m RMS");
    // Across the band, on both sides, the change only fades.
    for side in [
        (0..c0).rev().collect::<Vec<_>>(),
        (c1..n).collect::<Vec<_>>(),
    ] {
        for w in side.windows(2) {
            let (a, b) = (col_rms(w[0]), col_rms(w[1]));
            assert!(
                b <= a + 0.05,
                "columns {} → {}: {a:.3} → {b:.3} m",
                w[0],
                w[1]
            );
        }
    }
    // On the image the fusion still works.
    let (mut e_in, mut e_out, mut k) = (0.0, 0.0, 0.0);
    for ((i, j), &z) in f.height.indexed_iter() {
        if dist(j) == 0.0 {
            e_in += (scene.input_dem[(i, j)] - scene.truth_height[(i, j)]).powi(2);
            e_out += (z - scene.truth_height[(i, j)]).powi(2);
            k += 1.0;
        }
    }
    let (e_in, e_out) = ((e_in / k).sqrt(), (e_out / k).sqrt());
    eprintln!("on the image: {e_in:.2} m → {e_out:.2} m; beyond the band ≤ {worst:.4} m");
    assert!(
        e_out <= 0.5 * e_in,
        "on the image {e_out:.2} m vs input {e_in:.2} m"
    );
}

/// A photometric slope bias does not tilt the region (docs/science.md, "Long wavelengths"):
/// the image of a plane sloping by s = 0.002 eastwards over a flat DEM, solved at the true
/// albedo. Where E_DEM measures only gradients, a uniform bias enters through the region's
/// edges and the whole surface tilts by a fixed fraction of s, so its height error grows with
/// the region's width; with the DEM's heights held beyond ℓ the tilt stays in bands along the
/// edges and the middle half keeps the DEM's level.
#[test]
fn a_photometric_slope_bias_does_not_tilt_the_region() {
    use sfsfuse::fusion::{Directions, Problem};
    use sfsfuse::photometry::{Hapke, ReflectanceModel};
    use sfsfuse::synth::direction;
    let (n, eps, slope, w) = (192, 140.0, 0.002, 0.44);
    let model = Hapke::moon();
    let (sun, view) = (direction(60.0, 105.0), direction(0.0, 0.0));
    let r = model.shade_observed(slope, 0.0, w, &sun, &view).r;
    assert!(r > 0.0);
    let image = ndarray::Array2::from_elem((n, n), r);
    let dem = ndarray::Array2::<f64>::zeros((n, n));
    let pr = Problem::single(
        image.view(),
        Directions::Uniform(sun),
        Directions::Uniform(view),
        dem.view(),
        eps,
        sfsfuse::fusion::dem_psf_sigma(4.0),
        &model,
    );
    let rho = ndarray::Array2::from_elem((n, n), w);
    // Least-squares slope of the column means over the middle half of the columns.
    let middle_slope = |z: &ndarray::Array2<f64>| {
        let cols: Vec<(f64, f64)> = (n / 4..3 * n / 4)
            .map(|j| (j as f64 * eps, z.column(j).mean().unwrap()))
            .collect();
        let m = cols.len() as f64;
        let (mx, my) = cols
            .iter()
            .fold((0.0, 0.0), |(a, b), &(x, y)| (a + x / m, b + y / m));
        let sxy: f64 = cols.iter().map(|&(x, y)| (x - mx) * (y - my)).sum();
        let sxx: f64 = cols.iter().map(|&(x, _)| (x - mx) * (x - mx)).sum();
        sxy / sxx
    };
    let solve = |length: f64| {
        let params = FusionParams {
            dem_height_length_px: length,
            ..FusionParams::default()
        };
        let mut z = dem.clone();
        solve_fixed_albedo(&pr, &params, rho.view(), &mut z, &mut |_| {}).unwrap();
        middle_slope(&z)
    };
    let (held, free) = (
        solve(FusionParams::default().dem_height_length_px),
        solve(0.0),
    );
    eprintln!(
        "middle-half slope: {held:.2e} with heights held, {free:.2e} with gradients only (bias {slope:.0e})"
    );
    // The bias does reach the solution where only gradients are compared (the case this
    // guards against: ≈ 23 % of s here, as the track weighting lets the image decide
    // east–west slopes that persist along the columns, 3 % without it; a 12 m tilt across
    // the 27 km scene, growing with its width) …
    assert!(free.abs() >= 0.02 * slope, "gradients only: {free:.2e}");
    // … and the middle half keeps the DEM's level where the heights are held beyond ℓ.
    assert!(
        held.abs() <= 0.2 * free.abs(),
        "heights held: {held:.2e} against {free:.2e}"
    );
}

/// The input DEM's track offsets (the synthetic LOLA-like DEM offsets each coarse column, as
/// near-polar tracks offset north–south strips of a gridded product) are east–west slopes that
/// the Sun in the east-south-east shows in the image. With E_DEM's track weighting
/// (`dem_track_weight`, docs/science.md "The DEM's tracks") the image, not the DEM, decides
/// them: the column means of the fused error (where the offsets live) and the error as a
/// whole come out lower than with the plain term (`dem_track_weight = 1`).
#[test]
fn the_dem_track_offsets_give_way_to_the_image() {
    let scene = generate(&SceneSpec {
        size: 256,
        seed: 10,
        ..SceneSpec::default()
    });
    let column_means = |z: &ndarray::Array2<f64>| {
        let d = z - &scene.truth_height;
        let means: Vec<f64> = d.columns().into_iter().map(|c| c.mean().unwrap()).collect();
        let m = means.iter().sum::<f64>() / means.len() as f64;
        (means.iter().map(|x| (x - m).powi(2)).sum::<f64>() / means.len() as f64).sqrt()
    };
    let run = |weight: f64| {
        let params = FusionParams {
            dem_track_weight: weight,
            ..FusionParams::default()
        };
        let f = fuse(&scene.problem(), &params).unwrap();
        (score(&scene, &f).0, column_means(&f.height))
    };
    let input = column_means(&scene.input_dem);
    let (plain, plain_cols) = run(1.0);
    let (tracks, tracks_cols) = run(FusionParams::default().dem_track_weight);
    eprintln!(
        "column means of the error: input {input:.2} m, plain {plain_cols:.2} m, track-weighted {tracks_cols:.2} m; RMSE {plain:.2} → {tracks:.2} m"
    );
    assert!(
        tracks_cols <= 0.8 * plain_cols,
        "column means {tracks_cols:.2} m against {plain_cols:.2} m with the plain term"
    );
    assert!(
        tracks <= plain - 0.1,
        "RMSE {tracks:.2} m against {plain:.2} m"
    );
}
