//! Several observations of one scene (docs/science.md, "Several observations"): accuracy against
//! the single images, albedo, gains, strips and their edges, selection, determinism.

use sfsfuse::demo::score;
use sfsfuse::fusion::{fuse, Fusion, FusionParams, Selection};
use sfsfuse::synth::{generate, rmse, Scene, SceneSpec, DEMO_SUNS};

/// The fixed scene: 256² at 140 m/px, 1 % noise, input DEM 4× coarser (seed 10: ≥ 20 m RMSE).
fn base() -> SceneSpec {
    SceneSpec {
        size: 256,
        seed: 10,
        ..SceneSpec::default()
    }
}

/// The fixed scene under `suns` (gains 1) fused with `params`: its elevation RMSE and the
/// fused heights.
fn fused_with(suns: &[(f64, f64)], params: FusionParams) -> (f64, ndarray::Array2<f64>) {
    let scene = generate(&base().with_observations(suns, &[], false));
    let f = fuse(&scene.problem(), &params).unwrap();
    (score(&scene, &f).0, f.height)
}

fn fused(spec: &SceneSpec) -> (Scene, Fusion) {
    let scene = generate(spec);
    let f = fuse(&scene.problem(), &FusionParams::default()).unwrap();
    (scene, f)
}

/// Two Suns 120° apart in azimuth, then three; the second observation 5 % brighter and the
/// third 3 % darker than the first (calibration differences). The bars: elevation RMSE ≤ 0.65×
/// the better single image with two, ≤ 0.55× with three (this scene: 0.461× and 0.358×,
/// docs/science.md), albedo RMSE ≤ 0.008, gains recovered.
#[test]
fn two_and_three_illuminations_beat_the_better_single_image() {
    let spec = base();
    let input = rmse(&generate(&spec).input_dem, &generate(&spec).truth_height);
    assert!(input >= 20.0, "input RMSE {input:.2} m");
    let single: Vec<f64> = (0..3)
        .map(|k| {
            let (scene, f) = fused(&spec.clone().with_observations(
                &DEMO_SUNS[k..k + 1],
                &[],
                false,
            ));
            score(&scene, &f).0
        })
        .collect();
    let gains = [1.0, 1.05, 0.97];
    let mut results = Vec::new();
    for n in [2, 3] {
        let (scene, f) = fused(&spec.clone().with_observations(
            &DEMO_SUNS[..n],
            &gains[..n],
            false,
        ));
        let (h, albedo, _) = score(&scene, &f);
        let better = single[..n].iter().copied().fold(f64::INFINITY, f64::min);
        eprintln!(
            "{n} illuminations: {h:.2} m ({:.3}× the better single image, {better:.2} m), albedo {albedo:.4}, gains {:?}",
            h / better,
            f.gains
        );
        for (g, want) in f.gains.iter().zip(gains) {
            assert!((g / want - 1.0).abs() < 0.003, "gain {g} for {want}");
        }
        assert!(
            albedo <= 0.008,
            "{n} illuminations: albedo RMSE {albedo:.4}"
        );
        assert!(f.observations.iter().all(|&c| c as usize <= n));
        results.push((n, h, better));
    }
    let (_, h2, b2) = results[0];
    let (_, h3, b3) = results[1];
    assert!(h2 <= 0.65 * b2, "two: {h2:.2} m vs {b2:.2} m");
    assert!(h3 <= 0.55 * b3, "three: {h3:.2} m vs {b3:.2} m");
    assert!(h3 <= 5.0, "three: {h3:.2} m > 5 m");
    assert!(h3 < h2, "a third Sun must help: {h3:.2} m vs {h2:.2} m");
}

/// Pixels next to a shadow one Sun casts are often part in shadow, which the reflectance does
/// not model; where another Sun sees such a pixel cleanly, the shadowed image's weight there
/// drops to `shadow_edge_weight`, and to `shadow_edge_weight_all` where two others do
/// (docs/science.md, "Several observations"). Three Suns 25–35° high cast shadows in most
/// craters: 3.93 m with the full weights, 3.67 m with the factor (this scene, measured
/// 2026-12-04); the test asks for at least 5 % lower.
#[test]
fn pixels_next_to_a_shadow_count_less_where_another_sun_sees_them() {
    let scene = generate(&base().with_observations(&DEMO_SUNS[..3], &[1.0, 1.05, 0.97], false));
    let run = |p: FusionParams| score(&scene, &fuse(&scene.problem(), &p).unwrap()).0;
    let full = run(FusionParams {
        shadow_edge_weight: 1.0,
        shadow_edge_weight_all: 1.0,
        ..FusionParams::default()
    });
    let edged = run(FusionParams::default());
    eprintln!("full weights {full:.3} m, shadow-edge factor {edged:.3} m");
    assert!(edged <= 0.95 * full, "{edged:.3} m vs {full:.3} m");
}

/// Three Suns 15° high (docs/science.md, "Three low Suns"): their shadows are long and many,
/// and the pixels along their edges, part in shadow, are left to the two other images
/// (β_all × 0.1 under Suns up to 20°), the rays of E_S hold in full the pixels the other two
/// carry (ω_all → 1 under Suns up to 20°), and the DEM term keeps the weight it has with two
/// Suns (no every-direction factor under Suns up to 20° on average). Before these rules three
/// 15° Suns missed the 0.55× bar: this scene 5.09 m, 0.579× the best single image (8.79 m),
/// held-out seeds 3 / 5 at 512² 0.635 / 0.637×; with them 4.56 m, 0.519× (measured
/// 2026-12-07).
#[test]
fn three_low_suns_beat_the_best_single_image() {
    let suns = [(105.0, 15.0), (225.0, 15.0), (345.0, 15.0)];
    let best = suns
        .iter()
        .map(|&s| fused_with(&[s], FusionParams::default()).0)
        .fold(f64::INFINITY, f64::min);
    let three = fused_with(&suns, FusionParams::default()).0;
    eprintln!(
        "three 15° Suns {three:.3} m, best alone {best:.3} m ({:.3}×)",
        three / best
    );
    assert!(three <= 0.55 * best, "{three:.3} m vs {best:.3} m");
}

/// Partial shadow (`partial_shadow`, docs/science.md "Partial shadow"): the pixels just past a
/// cast shadow are part in shadow, and compared with f·R, f their lit share on the surface,
/// they stop reading as slopes rising towards the Sun. Two Suns 20° high (45/20 + 135/20),
/// whose shadows are long and many, must come out at least 3 % lower with it than without
/// (this scene, measured 2026-12-07: 5.26 → 5.01 m). One of them alone must come out exactly
/// as without: where no other observation sees a pixel the share is not taken (it made one
/// Sun's tiles depend on the window).
#[test]
fn pixels_part_in_shadow_are_modelled_as_such() {
    let without = || FusionParams {
        partial_shadow: false,
        ..FusionParams::default()
    };
    let (single, z) = fused_with(&[(45.0, 20.0)], FusionParams::default());
    let (single_without, z_without) = fused_with(&[(45.0, 20.0)], without());
    assert_eq!(
        z, z_without,
        "one observation: {single:.3} vs {single_without:.3} m"
    );
    let suns = [(45.0, 20.0), (135.0, 20.0)];
    let pair = fused_with(&suns, FusionParams::default()).0;
    let pair_without = fused_with(&suns, without()).0;
    eprintln!("one 20° Sun {single:.3} m, two {pair:.3} m (without {pair_without:.3} m)");
    assert!(
        pair <= 0.97 * pair_without,
        "{pair:.3} vs {pair_without:.3} m"
    );
}

/// Where one observation carries a pixel in a run where others overlap (the other's cast
/// shadow, the ring beside it, a strip's own part), the last stage's passes invert its albedo at
/// `multi_albedo_sigma_single` (2 px), sharper than a single image's last stage (4 px): beside
/// pixels that two Suns pin down, one image's shading at 2–4 px is better taken as albedo than
/// as slope. Two 20° Suns from north and south, whose shadows fill half of every large crater
/// each, must come out at least 1 % lower than with the 4 px of before; one Sun alone must come
/// out exactly as before, whatever the width.
#[test]
fn the_albedo_where_one_observation_carries_a_pixel_is_sharper() {
    let wide = || FusionParams {
        multi_albedo_sigma_single: 4.0,
        ..FusionParams::default()
    };
    let (_, z) = fused_with(&[(0.0, 20.0)], FusionParams::default());
    let (_, z_wide) = fused_with(&[(0.0, 20.0)], wide());
    assert_eq!(z, z_wide, "one observation");
    let suns = [(0.0, 20.0), (180.0, 20.0)];
    let pair = fused_with(&suns, FusionParams::default()).0;
    let pair_wide = fused_with(&suns, wide()).0;
    eprintln!("two 20° Suns {pair:.3} m (with 4 px {pair_wide:.3} m)");
    assert!(pair <= 0.99 * pair_wide, "{pair:.3} vs {pair_wide:.3} m");
}

/// High Suns: the example pair of `sfsfuse synth --help` (azimuth/elevation 110°/55° and
/// 250°/60°) and two Suns exactly 90° apart in azimuth, both 55° high. Under a high Sun the
/// shading changes little with slope, and a membrane weighted as under a low one held the
/// surface to the DEM's gradients: 0.805× and 0.766× the better single image before the
/// membrane followed the images' stiffness and walls (this scene now: 0.431× and 0.455×,
/// docs/science.md).
#[test]
fn two_high_suns_beat_the_better_single_image() {
    let spec = base();
    let single = |sun: (f64, f64)| {
        let (scene, f) = fused(&spec.clone().with_observations(&[sun], &[], false));
        score(&scene, &f).0
    };
    for pair in [
        [(110.0, 55.0), (250.0, 60.0)],
        [(90.0, 55.0), (180.0, 55.0)],
    ] {
        let better = single(pair[0]).min(single(pair[1]));
        let (scene, f) = fused(&spec.clone().with_observations(&pair, &[1.0, 1.05], false));
        let (h, albedo, _) = score(&scene, &f);
        eprintln!(
            "Suns {pair:?}: {h:.2} m ({:.3}× the better single image, {better:.2} m), albedo {albedo:.4}",
            h / better
        );
        assert!(h <= 0.65 * better, "{pair:?}: {h:.2} m vs {better:.2} m");
        assert!(albedo <= 0.008, "{pair:?}: albedo RMSE {albedo:.4}");
        // The 5 m target, met by the example pair on this scene since the DEM term
        // and the membrane yield further under high Suns (`multi_delta_factor_high_sun` 0.05,
        // `multi_eta_stiffness` 8: 5.19 → 4.88 m; docs/science.md, "S₀ = 8"), and further
        // where they see east–west slopes (`multi_delta_factor_high_sun_east_west` 0.02:
        // 4.83 m), and the last stage's alternation run nearer its limit (4.65 m).
        if pair[0] == (110.0, 55.0) {
            assert!(h <= 5.0, "{pair:?}: {h:.2} m over the 5 m target");
        }
    }
}

/// A low and a high Sun from nearly opposite sides (95°/25° and 245°/60°): the high Sun alone
/// carries the crater floors the low one shadows, and a membrane and DEM term weighted as
/// under one observation flattened them (0.69–0.71× the better single image through `run` on
/// held-out scenes before; docs/science.md, "A low and a high Sun"). Where the low Sun's image
/// counts towards the regularisers' coverage (`multi_shadow_coverage`) the pair must meet the
/// 0.65× bar and do better than without it.
#[test]
fn a_low_and_a_high_sun_beat_the_better_single_image() {
    let spec = base();
    let suns = [(95.0, 25.0), (245.0, 60.0)];
    let single = |sun: (f64, f64)| {
        let (scene, f) = fused(&spec.clone().with_observations(&[sun], &[], false));
        score(&scene, &f).0
    };
    let better = single(suns[0]).min(single(suns[1]));
    let scene = generate(&spec.clone().with_observations(&suns, &[1.0, 1.05], false));
    let run = |p: FusionParams| score(&scene, &fuse(&scene.problem(), &p).unwrap()).0;
    let without = run(FusionParams {
        multi_shadow_coverage: 0.0,
        ..FusionParams::default()
    });
    let with = run(FusionParams::default());
    eprintln!(
        "better single {better:.3} m; pair without {without:.3} m ({:.3}×), with {with:.3} m ({:.3}×)",
        without / better,
        with / better
    );
    assert!(with <= 0.65 * better, "{with:.3} m vs {better:.3} m");
    assert!(with <= 0.97 * without, "{with:.3} m vs {without:.3} m");
}

/// Two strips overlapping by a third of the region, the second 5 % brighter: better in the
/// overlap by at least a quarter, the single-strip parts keep the single-image bar (≤ 10 m, at
/// least 2× below the input), and no step at either strip edge — the column means of the
/// error (the "row-mean error" across an edge that runs along the columns) change
/// across an edge by ≤ 0.2× the RMSE. (Before E_DEM weighed the DEM's track offsets, the
/// error's column means kept the input DEM's own stripes, 1.5 m across column 85, and the
/// test took them out by differencing with the single full-coverage solution; that solution
/// now removes its stripes where its one Sun sees them, differently from the strips', and
/// the difference would measure its residual stripes — 1.46 m across column 171 — not an
/// edge.)
/// Where two Suns overlap, the last stage's albedo (σ_ρ 0.5 px) is nearly per pixel and
/// follows the surface it is inverted from: a second pass, inverting it from the surface the
/// first solved, moves the joint minimum on (docs/science.md, "Two passes of the last stage":
/// on this scene 4.60 → 4.52 m for the demo's pair and 5.43 → 5.23 m for the pair mirrored
/// about the east–west line, measured 2026-12-04). The test asks each pair for at least 1 %
/// lower with two passes than with one, and one observation for the same result bit for bit
/// (it has no such stage).
#[test]
fn a_second_pass_of_the_last_stage_lowers_the_error_of_two_suns() {
    let run = |suns: &[(f64, f64)], passes: usize| {
        fused_with(
            suns,
            FusionParams {
                multi_albedo_passes: passes,
                ..FusionParams::default()
            },
        )
    };
    for pair in [[DEMO_SUNS[0], DEMO_SUNS[1]], [(45.0, 30.0), (135.0, 30.0)]] {
        let ((one, _), (two, _)) = (run(&pair, 1), run(&pair, 2));
        eprintln!("Suns {pair:?}: one pass {one:.3} m, two passes {two:.3} m");
        assert!(two <= 0.99 * one, "{pair:?}: {two:.3} m vs {one:.3} m");
    }
    let (single1, single2) = (run(&DEMO_SUNS[..1], 1), run(&DEMO_SUNS[..1], 2));
    assert_eq!(single1.1, single2.1, "one observation must not change");
}

/// Where two Suns leave one direction of slope to the albedo (two high Suns 90° apart, whose
/// images change alike for a slope along their azimuths' bisector), the plain alternation of
/// albedo and surface in the last stage settles slowly: each pass takes about a third off the
/// way left to its limit. Each pass's step now lets the albedo follow the slopes
/// (`multi_albedo_coupling`, docs/science.md "The alternation run to its limit": through `run`
/// on a 512² scene 6.13 m after three plain passes, 5.11 after eight, 4.99 after thirty, and
/// 5.12 m with the default five coupled ones). The test asks the default for at least three
/// quarters of the way from three plain passes to sixteen, and for the same limit: sixteen
/// coupled passes within 1 % of sixteen plain ones.
#[test]
fn the_last_stage_alternates_albedo_and_surface_to_near_its_limit() {
    let run = |passes: usize, coupling: f64| {
        fused_with(
            &[(45.0, 55.0), (135.0, 55.0)],
            FusionParams {
                multi_albedo_passes: passes,
                multi_albedo_coupling: coupling,
                ..FusionParams::default()
            },
        )
        .0
    };
    let defaults = FusionParams::default();
    let (three, limit) = (run(3, 0.0), run(16, 0.0));
    let default = run(defaults.multi_albedo_passes, defaults.multi_albedo_coupling);
    let coupled_limit = run(16, defaults.multi_albedo_coupling);
    eprintln!(
        "plain: three passes {three:.3} m, sixteen {limit:.3} m; default {default:.3} m; sixteen coupled {coupled_limit:.3} m"
    );
    assert!(three - default >= 0.75 * (three - limit), "{default:.3} m");
    assert!(
        (coupled_limit - limit).abs() <= 0.01 * limit,
        "{coupled_limit:.3} m vs {limit:.3} m"
    );
}

/// Where Suns overlap, the pixel-scale shrink of the correction (`nyquist_shrink`, waves near
/// the Nyquist frequency scaled by 1 − s) takes out error the images do not hold there
/// (docs/science.md, "The pixel-scale shrink": on this scene 3.55 → 3.15 m for three Suns and
/// 5.21 → 5.00 m for the pair mirrored about the east–west line, measured 2026-12-05). The
/// test asks each for at least 3 % lower with it than without, and one observation, which it
/// leaves alone, for the same result bit for bit.
#[test]
fn the_pixel_scale_shrink_lowers_the_error_where_suns_overlap() {
    let run = |suns: &[(f64, f64)], shrink: f64| {
        fused_with(
            suns,
            FusionParams {
                nyquist_shrink: shrink,
                ..FusionParams::default()
            },
        )
    };
    let default = FusionParams::default().nyquist_shrink;
    assert!(default > 0.0);
    for suns in [&DEMO_SUNS[..3], &[(45.0, 30.0), (135.0, 30.0)][..]] {
        let ((off, _), (on, _)) = (run(suns, 0.0), run(suns, default));
        eprintln!("Suns {suns:?}: without the shrink {off:.3} m, with it {on:.3} m");
        assert!(on <= 0.97 * off, "{suns:?}: {on:.3} m vs {off:.3} m");
    }
    let (off, on) = (run(&DEMO_SUNS[..1], 0.0), run(&DEMO_SUNS[..1], default));
    assert_eq!(off.1, on.1, "one observation must not change");
}

/// The DEM term yields further (δ × `multi_delta_factor_east_west` instead of
/// `multi_delta_factor`) only where the images measure east–west slopes free of albedo: a pair
/// whose difference runs mostly east–west (0/45 + 120/40, share 0.30) gains at least 2 % (this
/// scene: 4.75 → 4.57 m, docs/science.md "The DEM term where the images see east–west slopes"),
/// while two Suns mirrored about the east–west line, which see those slopes only together with
/// the albedo, are solved exactly as without the rule.
#[test]
fn the_dem_term_yields_further_only_where_the_images_see_east_west_slopes() {
    let run = |suns: &[(f64, f64)], f_ew: f64| {
        fused_with(
            suns,
            FusionParams {
                multi_delta_factor_east_west: f_ew,
                ..FusionParams::default()
            },
        )
    };
    let defaults = FusionParams::default();
    let (off, on) = (
        defaults.multi_delta_factor,
        defaults.multi_delta_factor_east_west,
    );
    assert!(on < off);
    let open = [(0.0, 45.0), (120.0, 40.0)];
    let ((without, _), (with, _)) = (run(&open, off), run(&open, on));
    eprintln!("Suns {open:?}: without the rule {without:.3} m, with it {with:.3} m");
    assert!(with <= 0.98 * without, "{with:.3} m vs {without:.3} m");
    let mirrored = [(45.0, 30.0), (135.0, 30.0)];
    let ((_, a), (_, b)) = (run(&mirrored, off), run(&mirrored, on));
    assert_eq!(
        a, b,
        "Suns mirrored about the east–west line must not change"
    );
}

#[test]
fn overlapping_strips_are_better_in_the_overlap_and_show_no_edge() {
    let spec = base();
    let n = spec.size;
    let (scene, f) = fused(
        &spec
            .clone()
            .with_observations(&DEMO_SUNS[..2], &[1.0, 1.05], true),
    );
    // Strips of width ⅔n overlapping by ⅓n, to the nearest column: [0, 171) and [85, 256).
    let (a, b) = (85, 171);
    assert_eq!(scene.spec.columns, Some([0, b]));
    assert_eq!(scene.more[0].spec.columns, Some([a, n]));
    let d = &f.height - &scene.truth_height;
    let part = |c0: usize, c1: usize| {
        let s = d.slice(ndarray::s![.., c0..c1]);
        (s.iter().map(|x| x * x).sum::<f64>() / s.len() as f64).sqrt()
    };
    let input = rmse(&scene.input_dem, &scene.truth_height);
    let (left, overlap, right, all) = (part(0, a), part(a, b), part(b, n), part(0, n));
    eprintln!("strips: one strip {left:.2} / {right:.2} m, overlap {overlap:.2} m, all {all:.2} m");
    for one in [left, right] {
        assert!(one <= 10.0 && 2.0 * one <= input, "{one:.2} m");
    }
    assert!(
        overlap <= 0.70 * 0.5 * (left + right),
        "overlap {overlap:.2} m vs {left:.2} / {right:.2} m"
    );
    // Where both strips cover a pixel, both are counted; outside, one.
    assert_eq!(f.observations[(n / 2, n / 2)], 2);
    assert_eq!(f.observations[(n / 2, 5)], 1);
    assert_eq!(f.observations[(n / 2, n - 5)], 1);
    let col: Vec<f64> = (0..n).map(|j| d.column(j).mean().unwrap()).collect();
    for edge in [a, b] {
        let l = col[edge - 8..edge].iter().sum::<f64>() / 8.0;
        let r = col[edge..edge + 8].iter().sum::<f64>() / 8.0;
        eprintln!(
            "edge at column {edge}: column-mean step {:.2} m",
            (l - r).abs()
        );
        assert!(
            (l - r).abs() <= 0.2 * all,
            "step {:.2} m at column {edge}",
            (l - r).abs()
        );
    }
}

/// A low Sun added to a good observation: its image is dim, and its photometric model error
/// (cast and partial shadows, grazing incidence) grows faster than its brightness falls. With
/// the noise weight ν_k = (Ī/Ī_k)² of before (a fixed relative error) the 10°-high image
/// weighed several times the 30° one and the pair came out worse than the 30° image alone
/// (1.03×); with ν_k = Ī/Ī_k (shot noise, `observations::noise_weight`) it is 0.94× (this
/// scene, docs/science.md "Several observations"). The test asks for at most 0.97×, and for
/// the weights of the record: the dim image's ν above the bright one's, by less than the
/// square of their brightness ratio.
#[test]
fn a_low_sun_added_to_a_good_observation_does_not_make_it_worse() {
    let spec = base();
    let suns = [(105.0, 30.0), (100.0, 10.0)];
    let (scene, f) = fused(&spec.clone().with_observations(&suns[..1], &[], false));
    let alone = score(&scene, &f).0;
    let (scene, f) = fused(&spec.clone().with_observations(&suns, &[], false));
    let both = score(&scene, &f).0;
    let nu = &f.noise_weights;
    eprintln!(
        "105/30 alone {alone:.2} m, with 100/10 {both:.2} m ({:.3}×), noise weights {nu:?}",
        both / alone
    );
    assert!(
        both <= 0.97 * alone,
        "adding a 10° Sun: {both:.2} m against {alone:.2} m alone"
    );
    // ν_k = Ī/Ī_k: the dim image weighs more, and ν_0·Ī_0 = ν_1·Ī_1 = Ī.
    let mean = |k: usize| {
        let (s, n) = scene.problem().observations[k].valid_sum(f.gains[k]);
        s / n as f64
    };
    assert!(nu[1] > nu[0], "{nu:?}");
    assert!(
        (nu[0] * mean(0) / (nu[1] * mean(1)) - 1.0).abs() < 1e-9,
        "ν·Ī_k differs between the observations: {nu:?}"
    );
}

/// Selection: at most one observation per pixel, or an incidence window that leaves one out.
#[test]
fn selection_limits_the_observations_per_pixel() {
    let spec = SceneSpec { size: 64, ..base() }.with_observations(&DEMO_SUNS[..2], &[], false);
    let scene = generate(&spec);
    let run = |sel: Selection| {
        let mut pr = scene.problem();
        pr.selection = sel;
        fuse(&pr, &FusionParams::default()).unwrap()
    };
    let one = run(Selection {
        max_per_pixel: 1,
        ..Selection::default()
    });
    assert!(one.observations.iter().all(|&c| c <= 1));
    assert!(one.observations.iter().any(|&c| c == 1));
    // The same with the observation kept at a pixel there taken as 2× coarser (σ = 0.87 px,
    // its pixel 4 grid pixels): its score is divided by 4 and the other one is kept instead,
    // wherever the other one is usable.
    let kept = |f: &Fusion, k: usize| f.used_by[k].iter().filter(|&&u| u).count();
    let first = usize::from(kept(&one, 1) > kept(&one, 0));
    let mut pr = scene.problem();
    pr.selection = Selection {
        max_per_pixel: 1,
        ..Selection::default()
    };
    let mut blur = vec![0.0; 2];
    blur[first] = sfsfuse::fusion::blur::sigma_px(280.0, 140.0);
    pr.blur = Some(blur);
    let coarse = fuse(&pr, &FusionParams::default()).unwrap();
    eprintln!(
        "kept: {} / {} sharp, {} / {} with the one kept most 2× coarser",
        kept(&one, 0),
        kept(&one, 1),
        kept(&coarse, 0),
        kept(&coarse, 1)
    );
    assert!(kept(&coarse, 1 - first) > kept(&one, 1 - first) + kept(&one, first) / 2);
    // The first Sun is 60° from the zenith, the second 55°: a window of 50–58° keeps the second.
    let window = run(Selection {
        min_incidence_deg: 50.0,
        max_incidence_deg: 58.0,
        ..Selection::default()
    });
    assert_eq!(window.used_by[0].iter().filter(|&&u| u).count(), 0);
    assert!(window.used_by[1].iter().filter(|&&u| u).count() > 3000);
    // Nothing in the window: refused, not silently the input DEM.
    let mut pr = scene.problem();
    pr.selection = Selection {
        min_incidence_deg: 10.0,
        max_incidence_deg: 20.0,
        ..Selection::default()
    };
    assert!(fuse(&pr, &FusionParams::default()).is_err());
}

/// Several observations give bit-identical outputs with 1 and 2 threads.
#[test]
fn several_observations_do_not_depend_on_the_thread_count() {
    let run = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                let spec = SceneSpec {
                    size: 64,
                    seed: 11,
                    ..SceneSpec::default()
                }
                .with_observations(&DEMO_SUNS[..3], &[1.0, 1.02, 0.99], true);
                let (_, f) = fused(&spec);
                (f.height, f.albedo, f.gains)
            })
    };
    let (h1, a1, g1) = run(1);
    let (h2, a2, g2) = run(2);
    let bits = |a: &ndarray::Array2<f64>| a.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&h1), bits(&h2));
    assert_eq!(bits(&a1), bits(&a2));
    assert_eq!(
        g1.iter().map(|g| g.to_bits()).collect::<Vec<_>>(),
        g2.iter().map(|g| g.to_bits()).collect::<Vec<_>>()
    );
}

/// `image` as a detector `f` times coarser than the grid sees it: f × f block means, carried
/// back onto the grid bilinearly (block centres at their pixels' centre), as the ingest does
/// with a swath coarser than the grid.
fn coarser(image: &ndarray::Array2<f64>, f: usize) -> ndarray::Array2<f64> {
    let n = image.nrows();
    let nc = n / f;
    let block = ndarray::Array2::from_shape_fn((nc, nc), |(a, b)| {
        image
            .slice(ndarray::s![a * f..(a + 1) * f, b * f..(b + 1) * f])
            .mean()
            .unwrap()
    });
    sfsfuse::synth::bilinear_from_blocks(&block, f, n)
}

/// An observation with pixels twice the grid's (M3's second optical period over a grid at the
/// first's pixel size) overlapping a sharp one: taken as sharp it reads its blur as flatter
/// relief; modelled as the reflectance averaged over its pixel (`Problem::blur`, σ from
/// `blur::sigma_px`; docs/science.md, "Images coarser than the grid") the pair gains. This
/// scene: 5.48 m taken as sharp, 4.73 m modelled (6.00 and 5.16 m with three passes of the last
/// stage instead of eight; the sharp image alone 8.06 m); the albedo, inverted from the image
/// with the rendering's shading within its kernel put back, is better than taken as sharp.
#[test]
fn an_observation_coarser_than_the_grid_is_modelled_as_its_blur() {
    use sfsfuse::fusion::blur;
    let mut scene = generate(&base().with_observations(&DEMO_SUNS[..2], &[], false));
    scene.more[0].image = coarser(&scene.more[0].image, 2);
    let sigma = blur::sigma_px(280.0, 140.0);
    let mut results = Vec::new();
    for b in [None, Some(vec![0.0, sigma])] {
        let mut pr = scene.problem();
        pr.blur = b;
        let f = fuse(&pr, &FusionParams::default()).unwrap();
        results.push(score(&scene, &f));
    }
    eprintln!("taken as sharp / modelled as its blur (m, albedo): {results:.4?}");
    let ((sharp, sharp_albedo, _), (modelled, albedo, _)) = (results[0], results[1]);
    assert!(modelled < 0.92 * sharp, "{results:?}");
    // The final albedo sharpened: 0.0053 here against 0.0056 taken as sharp (0.0055 inverted
    // from the blurred image as it is, measured with three passes).
    assert!(albedo < sharp_albedo && albedo <= 0.0054, "{results:?}");
}

/// Cast shadows as height constraints (`shadow_weight`, docs/science.md "Cast shadows"): a
/// pixel an image sees in shadow must lie below the Sun's horizon. Two Suns 20° high cast
/// shadows in most craters, whose floors E_I then leaves to the DEM and the membrane (too
/// shallow); with E_S the pair's error is at least 5 % lower. One Sun alone has no E_S by
/// default (`shadow_weight_alone` 0: a pixel no other observation sees is held by a single
/// ray, and under low Suns tiles then ended metres from the whole region): the same result as
/// without it; opted in, it is no worse (this scene, measured 2026-12-06: 5.45 → 5.04 m, one
/// Sun 8.15 → 7.96 m opted in). At λ = 2 (the default since 2026-12-07) the pair is at least
/// 1 % lower again than at λ = 1 (measured: 4.887 m without, 4.446 m at λ = 1, 4.377 m at 2).
#[test]
fn cast_shadows_lower_the_error_of_two_low_suns() {
    let run = |suns: &[(f64, f64)], weight: f64, alone: f64| {
        fused_with(
            suns,
            FusionParams {
                shadow_weight: weight,
                shadow_weight_alone: alone,
                ..FusionParams::default()
            },
        )
        .0
    };
    let pair = [(315.0, 20.0), (45.0, 20.0)];
    let (off, on) = (run(&pair, 0.0, 0.0), run(&pair, 1.0, 0.0));
    let default = run(&pair, FusionParams::default().shadow_weight, 0.0);
    let one = &pair[..1];
    let (single_off, single_default, single_on) =
        (run(one, 0.0, 0.0), run(one, 1.0, 0.0), run(one, 1.0, 1.0));
    eprintln!(
        "two 20° Suns: {off:.3} m without E_S, {on:.3} m with it at λ = 1, {default:.3} m at the default; one: {single_off:.3} m, {single_on:.3} m opted in"
    );
    assert!(on <= 0.95 * off, "{on:.3} m vs {off:.3} m");
    assert!(default <= 0.99 * on, "{default:.3} m vs {on:.3} m at λ = 1");
    assert_eq!(single_default, single_off);
    assert!(
        single_on <= single_off,
        "{single_on:.3} m vs {single_off:.3} m"
    );
}
