//! `sfsfuse bench`: speed and memory of the solvers, measured in one run so that ratios compare
//! like with like (docs/performance.md records the figures).
//!
//! (a) One surface solve at fixed albedo (the first stage's, σ_ρ = 100 px), both z-solvers
//!     started from the input DEM: time until the energy is within 0.1 % of the converged energy
//!     E* (the lowest energy either solver reached; the fast solver is run to a tight tolerance
//!     for it), and the ratio paper/fast. The `paper` reference is capped by sweeps and by
//!     time (default 40 s, so that the default bench takes about a minute and a half on two
//!     cores); where it stops short of the tolerance the ratio is a lower bound.
//! (b) The full fusion with the albedo loop and default parameters: seconds per megapixel and
//!     the process's peak resident memory during it (VmHWM after resetting it through
//!     /proc/self/clear_refs on Linux). What is resident at the reset counts: the fusion's
//!     inputs (image, DEM) and the process itself; the scene's truth, which nothing here
//!     reads, is freed before.

use crate::error::Result;
use crate::fusion::{fuse, initial_albedo, solve_fixed_albedo, FusionParams, SolverKind};
use crate::progress::Progress;
use crate::synth::{generate, SceneSpec};
use serde::Serialize;
use std::time::Instant;

/// One solver's convergence trace: (seconds, energy) after each iteration.
#[derive(Debug, Clone, Serialize)]
pub struct Trace {
    pub solver: SolverKind,
    pub iterations: usize,
    pub seconds: f64,
    pub final_energy: f64,
    /// Seconds until E ≤ E*·(1 + 10⁻³); None if never reached.
    pub seconds_to_tolerance: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    pub size: usize,
    pub threads: usize,
    pub converged_energy: f64,
    pub fast: Trace,
    pub paper: Trace,
    /// paper seconds-to-tolerance / fast seconds-to-tolerance (a lower bound when the paper
    /// solver did not reach the tolerance: then its total time is used).
    pub speedup: f64,
    pub speedup_is_lower_bound: bool,
    /// Seconds into the `paper` reference when it last found itself under its time cap and
    /// started another chunk of sweeps (it checks between chunks, so it ends one chunk past
    /// the cap at most).
    pub paper_cap_checked_at: f64,
    pub fusion_seconds: f64,
    pub fusion_seconds_per_megapixel: f64,
    pub fusion_peak_memory_mib: Option<f64>,
}

fn trace(samples: &[(f64, f64)], solver: SolverKind, target: f64) -> Trace {
    let last = samples.last().copied().unwrap_or((0.0, f64::NAN));
    Trace {
        solver,
        iterations: samples.len().saturating_sub(1),
        seconds: last.0,
        final_energy: last.1,
        seconds_to_tolerance: samples.iter().find(|(_, e)| *e <= target).map(|(t, _)| *t),
    }
}

fn timed_solve(
    scene: &crate::synth::Scene,
    params: &FusionParams,
    rho: &ndarray::Array2<f64>,
) -> Result<Vec<(f64, f64)>> {
    let pr = scene.problem();
    let mut z = scene.input_dem.clone();
    let mut samples = Vec::new();
    let t0 = Instant::now();
    solve_fixed_albedo(&pr, params, rho.view(), &mut z, &mut |e| {
        samples.push((t0.elapsed().as_secs_f64(), e.total))
    })?;
    Ok(samples)
}

/// Reset the peak-RSS counter (Linux); false where unsupported. What the allocator keeps of
/// earlier measurements is handed back to the system first (`sfsfuse` tells glibc never to
/// trim its heap, for speed: without this, a measurement's peak would include the memory the
/// one before it freed).
fn reset_peak() -> bool {
    release_free_memory();
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn release_free_memory() {
    // SAFETY: malloc_trim only returns free heap pages to the system.
    unsafe {
        libc::malloc_trim(0);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn release_free_memory() {}

fn peak_mib() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

/// Sweeps of the `paper` solver between checks of its time budget.
const PAPER_CHUNK: usize = 50;

/// The `paper` solver from the input DEM, in chunks of [`PAPER_CHUNK`] sweeps, until
/// `max_sweeps`, `max_seconds`, or the energy stagnates (a chunk stops early); the samples of
/// every sweep, timed from the start.
fn timed_paper(
    scene: &crate::synth::Scene,
    rho: &ndarray::Array2<f64>,
    max_sweeps: usize,
    max_seconds: f64,
    progress: &Progress,
) -> Result<(Vec<(f64, f64)>, f64)> {
    let pr = scene.problem();
    let mut z = scene.input_dem.clone();
    let mut samples: Vec<(f64, f64)> = Vec::new();
    let t0 = Instant::now();
    let mut done = 0;
    let mut checked = 0.0;
    progress.steps(
        &format!(
            "paper solver (reference, at most {max_seconds} s), chunks of {PAPER_CHUNK} sweeps"
        ),
        max_sweeps.div_ceil(PAPER_CHUNK) as u64,
    );
    loop {
        let now = t0.elapsed().as_secs_f64();
        if done >= max_sweeps || now >= max_seconds {
            break;
        }
        checked = now;
        let n = PAPER_CHUNK.min(max_sweeps - done);
        let params = FusionParams {
            max_iterations: n,
            tolerance: 1e-12,
            ..FusionParams::paper()
        };
        let before = samples.len();
        solve_fixed_albedo(&pr, &params, rho.view(), &mut z, &mut |e| {
            samples.push((t0.elapsed().as_secs_f64(), e.total))
        })?;
        // Each call logs its starting state as iteration 0: keep it only once.
        if before > 0 && samples.len() > before {
            samples.remove(before);
        }
        let swept = samples.len() - before.max(1);
        done += n;
        progress.step(&format!(
            "paper: {} sweeps, {:.0} s",
            samples.len() - 1,
            t0.elapsed().as_secs_f64()
        ));
        if swept < n {
            break;
        }
    }
    progress.finish();
    Ok((samples, checked))
}

pub fn run(
    size: usize,
    paper_sweeps: usize,
    paper_seconds: f64,
    progress: &Progress,
) -> Result<BenchReport> {
    progress.stage(&format!("synthetic scene {size}²"));
    // Neither solve reads the truth: free it, so that the peak of (b) is the fusion's own
    // (its inputs, the image and the DEM, stay).
    let scene = generate(&SceneSpec {
        size,
        ..SceneSpec::default()
    })
    .without_truth();
    progress.finish();
    let base = FusionParams::default();
    let rho = initial_albedo(&scene.problem(), &base)?;

    // Run to the energy's own stagnation, not to the default step criterion.
    let fast_params = FusionParams {
        max_iterations: 100,
        tolerance: 1e-9,
        step_tolerance: 0.0,
        ..base.clone()
    };
    progress.stage("fast solver to convergence");
    let fast = timed_solve(&scene, &fast_params, &rho)?;
    progress.finish();
    let (paper, paper_cap_checked_at) =
        timed_paper(&scene, &rho, paper_sweeps, paper_seconds, progress)?;
    let best = fast
        .iter()
        .chain(&paper)
        .map(|s| s.1)
        .fold(f64::INFINITY, f64::min);
    let target = best * (1.0 + 1e-3);
    let ft = trace(&fast, SolverKind::Fast, target);
    let pt = trace(&paper, SolverKind::Paper, target);
    let fast_t = ft.seconds_to_tolerance.unwrap_or(ft.seconds);
    let (paper_t, lower) = match pt.seconds_to_tolerance {
        Some(t) => (t, false),
        None => (pt.seconds, true),
    };

    // The solves' starting albedo is not the fusion's (it makes its own).
    drop(rho);
    progress.stage("full fusion at default parameters");
    let peak_ok = reset_peak();
    let t0 = Instant::now();
    fuse(&scene.problem(), &base)?;
    let fusion_seconds = t0.elapsed().as_secs_f64();
    progress.finish();
    let mp = (size * size) as f64 / 1e6;
    Ok(BenchReport {
        size,
        threads: rayon::current_num_threads(),
        converged_energy: best,
        fast: ft,
        paper: pt,
        speedup: paper_t / fast_t,
        speedup_is_lower_bound: lower,
        paper_cap_checked_at,
        fusion_seconds,
        fusion_seconds_per_megapixel: fusion_seconds / mp,
        fusion_peak_memory_mib: if peak_ok { peak_mib() } else { None },
    })
}

impl BenchReport {
    pub fn table(&self) -> String {
        let fmt = |t: &Trace| {
            format!(
                "{:>6} iterations, {:8.2} s total, E = {:.6e}, within 0.1 % of E* after {}",
                t.iterations,
                t.seconds,
                t.final_energy,
                t.seconds_to_tolerance
                    .map(|s| format!("{s:.2} s"))
                    .unwrap_or_else(|| "— (not reached)".into())
            )
        };
        let mut s = format!(
            "scene {0}×{0} ({1:.2} MP), {2} threads\n",
            self.size,
            (self.size * self.size) as f64 / 1e6,
            self.threads
        );
        s += &format!(
            "(a) surface solve at fixed albedo, E* = {:.6e}\n",
            self.converged_energy
        );
        s += &format!("    fast : {}\n", fmt(&self.fast));
        s += &format!("    paper: {}\n", fmt(&self.paper));
        s += &format!(
            "    paper/fast time to 0.1 %: {}{:.1}×\n",
            if self.speedup_is_lower_bound {
                "≥ "
            } else {
                ""
            },
            self.speedup
        );
        s += &format!(
            "(b) full fusion with albedo loop: {:.2} s, {:.2} s/MP",
            self.fusion_seconds, self.fusion_seconds_per_megapixel
        );
        match self.fusion_peak_memory_mib {
            Some(m) => s += &format!(", peak resident memory {m:.0} MiB\n"),
            None => s += ", peak memory not measurable on this platform\n",
        }
        s
    }
}

/// `sfsfuse bench --pipeline`: `sfsfuse run` on the synthetic scene written as mission-format
/// products, as one tile and tiled, in one process (so the ratio compares like with like),
/// `repeats` times each, alternately: wall time of the whole run (plan, ingest, fusion, mosaic,
/// COG writing, checksums), seconds per megapixel, and peak resident memory of each. The
/// times compared are each configuration's fastest run: on a shared 2-core machine single
/// runs vary by ±20 %, and the fastest is the one the machine disturbed least (every run is
/// in `*_samples_seconds`); the peaks are the first runs' (every run's in
/// `*_samples_peak_memory_mib`).
#[derive(Debug, Clone, Serialize)]
pub struct PipelineBench {
    pub size: usize,
    pub tile_size: usize,
    pub halo: usize,
    pub tiles: usize,
    pub threads: usize,
    /// Runs of each configuration.
    pub repeats: usize,
    /// The fastest run of each.
    pub single_seconds: f64,
    pub tiled_seconds: f64,
    /// Every run's wall time, in order.
    pub single_samples_seconds: Vec<f64>,
    pub tiled_samples_seconds: Vec<f64>,
    /// Every run's peak resident memory, in order.
    pub single_samples_peak_memory_mib: Vec<Option<f64>>,
    pub tiled_samples_peak_memory_mib: Vec<Option<f64>>,
    /// tiled / single wall time (fastest runs).
    pub tiled_over_single: f64,
    pub single_seconds_per_megapixel: f64,
    pub tiled_seconds_per_megapixel: f64,
    pub single_peak_memory_mib: Option<f64>,
    pub tiled_peak_memory_mib: Option<f64>,
}

pub fn run_pipeline(size: usize, tile_size: usize, repeats: usize) -> Result<PipelineBench> {
    let repeats = repeats.max(1);
    use crate::progress::{Mode, Progress};
    use crate::workflow::Workflow;
    let spec = SceneSpec {
        size,
        ..SceneSpec::default()
    };
    let dir = std::env::temp_dir().join(format!("sfsfuse-bench-pipeline-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let scene = generate(&spec);
    let grid = crate::demo::demo_grid(&spec)?;
    let p = crate::synth::products::write(&scene, &grid, &dir.join("products"))?;
    drop(scene);
    let half = size as f64 * spec.spacing / 2.0;
    let workflow = |tile: usize, out: &str| {
        format!(
            "kind = \"orbital\"\n[inputs]\nm3 = [{:?}]\nlola = [{:?}]\nsolar_spectrum = {:?}\ndem_psf_sigma_px = 3.0\n[region]\nx_min = {}\nx_max = {half}\ny_min = {}\ny_max = {half}\n[grid]\ncenter_lat = -13.4\ncenter_lon = 357.2\nresolution_m = {}\n[tiling]\ntile_size = {tile}\n[output]\ndirectory = {out:?}\n",
            p.m3_label.display().to_string(),
            p.lola_label.display().to_string(),
            p.solar_table.display().to_string(),
            -half,
            -half,
            spec.spacing
        )
    };
    let quiet = Progress::new(Mode::Quiet);
    let timed = |tile: usize, name: &str| -> Result<(f64, Option<f64>, usize, usize)> {
        let path = dir.join(format!("{name}.toml"));
        crate::raster::write_atomic(&path, workflow(tile, name).as_bytes())?;
        let wf = Workflow::load(&path)?;
        let peak_ok = reset_peak();
        let t0 = Instant::now();
        let s = crate::pipeline::run(&wf, &crate::pipeline::Request::default(), &quiet)?;
        let secs = t0.elapsed().as_secs_f64();
        // The halo the plan chose (the workflow leaves it to the plan), from the run record.
        let halo = s
            .record
            .as_ref()
            .and_then(|p| std::fs::read(p).ok())
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
            .and_then(|v| v["halo"].as_u64())
            .unwrap_or(0) as usize;
        Ok((
            secs,
            if peak_ok { peak_mib() } else { None },
            s.tiles_total,
            halo,
        ))
    };
    let (mut singles, mut tileds) = (Vec::new(), Vec::new());
    let (mut single_mems, mut tiled_mems) = (Vec::new(), Vec::new());
    let (mut halo, mut tiles) = (0, 0);
    for r in 0..repeats {
        // A fresh output directory each time: a run would reuse the tiles of the one before.
        let (secs, mem, _, h) = timed(size.max(tile_size), &format!("single{r}"))?;
        let _ = std::fs::remove_dir_all(dir.join(format!("single{r}")));
        halo = h;
        singles.push(secs);
        single_mems.push(mem);
        let (secs, mem, n, _) = timed(tile_size, &format!("tiled{r}"))?;
        let _ = std::fs::remove_dir_all(dir.join(format!("tiled{r}")));
        tiles = n;
        tileds.push(secs);
        tiled_mems.push(mem);
    }
    // The first runs' peaks: later runs start from the allocator's state after the earlier
    // ones (each run's peak is in the samples).
    let (single_mem, tiled_mem) = (single_mems[0], tiled_mems[0]);
    let _ = std::fs::remove_dir_all(&dir);
    let fastest = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let (single, tiled) = (fastest(&singles), fastest(&tileds));
    let mp = (size * size) as f64 / 1e6;
    Ok(PipelineBench {
        size,
        tile_size,
        halo,
        tiles,
        threads: rayon::current_num_threads(),
        repeats,
        single_seconds: single,
        tiled_seconds: tiled,
        single_samples_seconds: singles,
        tiled_samples_seconds: tileds,
        single_samples_peak_memory_mib: single_mems,
        tiled_samples_peak_memory_mib: tiled_mems,
        tiled_over_single: tiled / single,
        single_seconds_per_megapixel: single / mp,
        tiled_seconds_per_megapixel: tiled / mp,
        single_peak_memory_mib: single_mem,
        tiled_peak_memory_mib: tiled_mem,
    })
}

impl PipelineBench {
    pub fn table(&self) -> String {
        let mem = |m: Option<f64>| m.map_or("n/a".to_string(), |m| format!("{m:.0} MiB"));
        format!(
            "sfsfuse run on {0}×{0} px synthetic products, {1} threads, halo {2} px, fastest of {12} runs each\n  one tile:            {3:.2} s ({4:.2} s/MP), peak {5}\n  {6} {13} of {7} px:  {8:.2} s ({9:.2} s/MP), peak {10}\n  tiled / single:      {11:.2}×\n",
            self.size,
            self.threads,
            self.halo,
            self.single_seconds,
            self.single_seconds_per_megapixel,
            mem(self.single_peak_memory_mib),
            self.tiles,
            self.tile_size,
            self.tiled_seconds,
            self.tiled_seconds_per_megapixel,
            mem(self.tiled_peak_memory_mib),
            self.tiled_over_single,
            self.repeats,
            if self.tiles == 1 { "tile" } else { "tiles" }
        )
    }
}

/// `sfsfuse bench --observations N`: the whole fusion (all albedo stages) of one scene seen
/// by 1, 2, …, N observations under the demo's Suns, every observation covering every pixel,
/// timed in one run; cost per observation relative to one.
#[derive(Debug, Clone, Serialize)]
pub struct ObservationsBench {
    pub size: usize,
    pub threads: usize,
    /// (observations, seconds, seconds / the one-observation seconds, elevation RMSE m).
    pub runs: Vec<(usize, f64, f64, f64)>,
}

pub fn run_observations(size: usize, max: usize, progress: &Progress) -> Result<ObservationsBench> {
    let max = max.clamp(1, crate::synth::DEMO_SUNS.len());
    let mut runs: Vec<(usize, f64, f64, f64)> = Vec::new();
    progress.steps("observations", max as u64);
    for n in 1..=max {
        let spec = SceneSpec {
            size,
            ..SceneSpec::default()
        }
        .with_observations(&crate::synth::DEMO_SUNS[..n], &[], false);
        let scene = generate(&spec);
        let t0 = Instant::now();
        let f = fuse(&scene.problem(), &FusionParams::default())?;
        let secs = t0.elapsed().as_secs_f64();
        let one = runs.first().map_or(secs, |r| r.1);
        runs.push((
            n,
            secs,
            secs / one,
            crate::synth::rmse(&f.height, &scene.truth_height),
        ));
        progress.step(&format!("{n} observation(s): {secs:.2} s"));
    }
    progress.finish();
    Ok(ObservationsBench {
        size,
        threads: rayon::current_num_threads(),
        runs,
    })
}

impl ObservationsBench {
    pub fn table(&self) -> String {
        let mut s = format!(
            "fusion of one {0}×{0} px scene seen by 1…{1} observations (every pixel covered by all), {2} threads\n  observations   seconds   × one   elevation RMSE\n",
            self.size,
            self.runs.len(),
            self.threads
        );
        for (n, secs, ratio, rmse) in &self.runs {
            s.push_str(&format!(
                "  {n:>12}   {secs:>7.2}   {ratio:>5.2}   {rmse:>8.2} m\n"
            ));
        }
        s
    }
}
