//! Measures the bias of the registration against the DEM on undisplaced synthetic scenes, the
//! numbers behind `registration::DEM_BIAS` and `registration::shadow_lowering`
//! (docs/science.md, "Registration"): for each Sun elevation, 3 seeds × 8 azimuths, the
//! longest and the mean length of the estimates whose correlation reaches
//! `APPLY_CORRELATION`, with the DEM's shadows cast under the Sun itself and as a run casts
//! them, under the Sun lowered by `shadow_lowering`.
//!
//!     cargo run --release --example registration_bias -- 10,15,20,25,30,45 [DEM_FACTOR] [SIZE]

use sfsfuse::fusion::Directions;
use sfsfuse::registration::{estimate, render_lowered, shadow_lowering, APPLY_CORRELATION};
use sfsfuse::synth::{generate, SceneSpec};

/// The longest and summed lengths of the estimates that count, how many count, and how many
/// do not.
#[derive(Default)]
struct Lengths {
    longest: f64,
    sum: f64,
    counted: usize,
    not: usize,
}

/// The elevations, the DEM factor and the size from the command line; `None` when one does
/// not parse.
fn parse(args: &[String]) -> Option<(Vec<f64>, usize, usize)> {
    let elevations = args
        .get(1)?
        .split(',')
        .map(|x| x.parse::<f64>().ok())
        .collect::<Option<Vec<_>>>()?;
    let dem_factor = args.get(2).map_or(Some(4), |s| s.parse().ok())?;
    let size = args.get(3).map_or(Some(256), |s| s.parse().ok())?;
    Some((elevations, dem_factor, size))
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let Some((elevations, dem_factor, size)) = parse(&args) else {
        eprintln!(
            "usage: registration_bias ELEVATIONS [DEM_FACTOR] [SIZE]: elevations in degrees, comma-separated, \
             the DEM's coarseness (default 4) and the scene's side in pixels (default 256), e.g. 10,20,30 4 256"
        );
        std::process::exit(2);
    };
    for &el in &elevations {
        let mut lengths = [Lengths::default(), Lengths::default()];
        let mut cut = 0.0;
        for seed in [10u64, 1, 3] {
            for az in (0..8).map(|k| 45.0 * f64::from(k)) {
                let sc = generate(&SceneSpec {
                    size,
                    seed,
                    sun_incidence_deg: 90.0 - el,
                    sun_azimuth_deg: az,
                    dem_factor,
                    ..SceneSpec::default()
                });
                let pr = sc.problem();
                let (sun, view) = (sc.sun.directions(size, size), Directions::Uniform(sc.view));
                cut = shadow_lowering(el, pr.dem_psf_sigma);
                for (l, psf) in lengths.iter_mut().zip([0.0, pr.dem_psf_sigma]) {
                    let r = render_lowered(pr.dem, pr.spacing, pr.model, (&sun, &view), psf);
                    match estimate(sc.image.view(), r.view(), pr.dem_psf_sigma, 8) {
                        Some(s) if s.correlation >= APPLY_CORRELATION => {
                            l.longest = l.longest.max(s.length());
                            l.sum += s.length();
                            l.counted += 1;
                        }
                        _ => l.not += 1,
                    }
                }
            }
        }
        let show = |l: &Lengths| {
            format!(
                "longest {:.2} px, mean {:.2} px ({} without a clear peak or under {APPLY_CORRELATION})",
                l.longest,
                l.sum / l.counted.max(1) as f64,
                l.not
            )
        };
        println!(
            "Sun {el}°, DEM {dem_factor}× coarser, {size}²: shadows under the Sun: {}; under {:.2} of it: {}",
            show(&lengths[0]),
            1.0 - cut,
            show(&lengths[1])
        );
    }
}
