//! The `sfsfuse` command line.

use clap::{Parser, Subcommand};
use sfsfuse::fusion::{FusionParams, SolverKind};
use sfsfuse::synth::SceneSpec;
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "sfsfuse",
    version = sfsfuse::BUILD,
    about = "Shape-from-shading fusion of lunar imagery (M3) with laser altimetry (LOLA)"
)]
struct Cli {
    /// Worker threads (default: all cores). Results are bit-identical for any count.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run the built-in job: fuse a synthetic lunar scene with known truth and score the result.
    Demo(DemoArgs),
    /// Describe a PDS product (M3 L1B or LOLA GDR label): kind, size, bands, extent, ranges.
    Inspect(InspectArgs),
    /// Run a workflow file: M3 + LOLA (or a lab image + range scan) in, fused GeoTIFFs out.
    /// Tiles already finished are skipped, so an interrupted run resumes where it stopped.
    Run(RunArgs),
    /// Download M3 L1B observations, LOLA GDR DEMs and M3 solar spectra from the PDS by
    /// product ID: resumable, retried, verified against the label, cached.
    Fetch(FetchArgs),
    /// Submit a workflow's tiles to a cluster: an array job of tile batches and a mosaic job
    /// that runs after it (docs/cluster.md). Resubmitting submits only missing tiles.
    Submit(SubmitArgs),
    /// Write the synthetic scene as mission-format products (an M3-like L1B observation per
    /// `--sun`, a LOLA-like GDR DEM, a solar spectrum table, truth GeoTIFFs) for
    /// `workflows/synthetic.toml` and its siblings.
    Synth(SynthArgs),
    /// Benchmark the solvers on one synthetic scene and print timings and ratios.
    Bench(BenchArgs),
}

/// `sfsfuse demo`'s options.
#[derive(clap::Args)]
struct DemoArgs {
    /// Directory for the products (DEM, albedo, residual, quick-look).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Scene size in pixels (square).
    #[arg(long, default_value_t = 512)]
    size: usize,
    /// Random seed of the scene.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// z-solver.
    #[arg(long, value_enum, default_value_t = SolverKind::Fast)]
    solver: SolverKind,
    /// Observations of the scene, each under its own Sun (azimuths 105°, 225°, 345°, 45°,
    /// 165°, 285°; elevations 25–35°), with independent noise, fused together.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=6))]
    observations: u8,
    /// Each observation covers only a strip of the columns, overlapping its neighbours
    /// by half a strip.
    #[arg(long)]
    strips: bool,
    /// The quick look's error panel spans ± this many metres (default: the 99th
    /// percentile of |fused − true|), so that quick looks of several runs compare.
    #[arg(long, value_name = "METRES")]
    error_limit: Option<f64>,
    /// Print the report as JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse inspect`'s options.
#[derive(clap::Args)]
struct InspectArgs {
    /// The product's PDS3 label.
    path: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse run`'s options.
#[derive(clap::Args)]
struct RunArgs {
    /// The workflow (TOML; docs/workflows.md).
    workflow: PathBuf,
    /// Run only these tiles, e.g. `3`, `0,4` or `2-5`, and no mosaic (cluster tasks).
    #[arg(long)]
    tile: Option<String>,
    /// Only blend finished tiles into the products and write the run record.
    #[arg(long, conflicts_with = "tile")]
    mosaic: bool,
    /// List the tiles (id, core and halo windows, done or not) and exit.
    #[arg(long, conflicts_with_all = ["tile", "mosaic"])]
    list_tiles: bool,
    /// Progress display: bars on a terminal (auto), log lines, or nothing.
    #[arg(long, value_enum, default_value_t = ProgressArg::Auto)]
    progress: ProgressArg,
    /// Print the summary as JSON.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse fetch`'s options.
#[derive(clap::Args)]
struct FetchArgs {
    /// Product IDs: M3G20090106T113423, LDEM_64, M3G20110224_RFL_SOLAR_SPEC, …
    #[arg(required = true)]
    ids: Vec<String>,
    /// Target directory (default: $SFSFUSE_CACHE, else $XDG_CACHE_HOME/sfsfuse, else
    /// ~/.cache/sfsfuse).
    #[arg(long)]
    to: Option<PathBuf>,
    /// Root of the M3 volumes (default: the PDS Imaging Node).
    #[arg(long)]
    m3_base: Option<String>,
    /// The LOLA `lola_gdr` directory (default: the PDS Geosciences Node).
    #[arg(long)]
    lola_base: Option<String>,
    /// md5sum-style manifest URL(s) to verify downloads against.
    #[arg(long)]
    checksums: Vec<String>,
    /// Attempts per file.
    #[arg(long)]
    retries: Option<u32>,
    /// Seconds without progress before a request is abandoned.
    #[arg(long)]
    timeout: Option<f64>,
    /// Progress display.
    #[arg(long, value_enum, default_value_t = ProgressArg::Auto)]
    progress: ProgressArg,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse submit`'s options.
#[derive(clap::Args)]
struct SubmitArgs {
    /// The workflow (its output directory must be on a file system the nodes share).
    workflow: PathBuf,
    #[arg(long, value_enum, default_value_t = sfsfuse::cluster::Scheduler::Slurm)]
    scheduler: sfsfuse::cluster::Scheduler,
    /// Array tasks running at once.
    #[arg(long)]
    max_parallel: Option<usize>,
    /// Tiles per array task.
    #[arg(long, default_value_t = 1)]
    tiles_per_task: usize,
    /// Partition (SLURM) or queue (PBS).
    #[arg(long)]
    partition: Option<String>,
    /// CPUs (and threads) per task.
    #[arg(long, default_value_t = 1)]
    cpus_per_task: usize,
    /// Wall-clock limit per task, e.g. 02:00:00.
    #[arg(long)]
    time: Option<String>,
    /// Memory per task, e.g. 8G.
    #[arg(long)]
    mem: Option<String>,
    /// When the mosaic job starts: after the array in any case (it then checks every tile
    /// and lists missing ones), or only if every task succeeded.
    #[arg(long, value_enum, default_value_t = sfsfuse::cluster::Dependency::Afterany)]
    dependency: sfsfuse::cluster::Dependency,
    /// Print the scripts; submit nothing.
    #[arg(long)]
    dry_run: bool,
    #[arg(long, value_enum, default_value_t = ProgressArg::Auto)]
    progress: ProgressArg,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse bench`'s options.
#[derive(clap::Args)]
struct BenchArgs {
    /// Scene size in pixels (square).
    #[arg(long, default_value_t = 1024)]
    size: usize,
    /// Sweep limit for the `paper` solver.
    #[arg(long, default_value_t = 20000)]
    paper_sweeps: usize,
    /// Time limit for the `paper` solver, seconds: the paper/fast ratio is then a lower
    /// bound.
    #[arg(long, default_value_t = 40.0)]
    paper_seconds: f64,
    /// Progress display.
    #[arg(long, value_enum, default_value_t = ProgressArg::Auto)]
    progress: ProgressArg,
    /// Benchmark `sfsfuse run` instead: one tile against tiles of `--tile` px.
    #[arg(long)]
    pipeline: bool,
    /// Tile size for `--pipeline`.
    #[arg(long, default_value_t = 512)]
    tile: usize,
    /// For `--pipeline`: run each (one tile, tiled) this many times, alternately, and
    /// compare their fastest runs (the ones the machine disturbed least).
    #[arg(long, default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=20))]
    repeat: u32,
    /// Benchmark the fusion's cost against the number of observations instead: one scene
    /// seen by 1 … N observations (at most 6).
    #[arg(long, conflicts_with = "pipeline", value_parser = clap::value_parser!(u8).range(1..=6))]
    observations: Option<u8>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum ProgressArg {
    Auto,
    Lines,
    Quiet,
}

fn progress_of(p: ProgressArg) -> sfsfuse::progress::Progress {
    use sfsfuse::progress::{Mode, Progress};
    Progress::new(match p {
        ProgressArg::Auto => Mode::Auto,
        ProgressArg::Lines => Mode::Lines,
        ProgressArg::Quiet => Mode::Quiet,
    })
}

/// `sfsfuse synth`'s options.
#[derive(clap::Args)]
struct SynthArgs {
    /// Directory for the products.
    #[arg(long, default_value = "out/synthetic/products")]
    out: PathBuf,
    /// Scene size in pixels (square).
    #[arg(long, default_value_t = 512)]
    size: usize,
    /// Random seed of the scene.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The Sun of each observation as AZIMUTH/ELEVATION in degrees (azimuth clockwise
    /// from north), e.g. `--sun 110/55 --sun 250/60`: one L1B product set per `--sun`.
    /// Default: one observation, Sun at 105/30.
    #[arg(long = "sun", value_parser = sfsfuse::synth::parse_sun)]
    suns: Vec<(f64, f64)>,
    /// How the Sun of each observation moves along its strip, as ΔAZIMUTH/ΔELEVATION in
    /// degrees (in `--sun` order; missing ones are 0/0): from its `--sun` at the first line
    /// to that much further at the last, in proportion to the line, as the local time and
    /// latitude change along a polar orbit's track, e.g. `--sun 105/20 --sun-drift 0/15`.
    #[arg(long = "sun-drift", allow_hyphen_values = true, value_parser = sfsfuse::synth::parse_sun_drift)]
    sun_drifts: Vec<[f64; 2]>,
    /// Radiometric gain of each further observation relative to the first (in `--sun`
    /// order from the second on; missing ones are 1).
    #[arg(long = "gain")]
    gains: Vec<f64>,
    /// Each observation covers only a strip of the columns, overlapping its neighbours
    /// by half a strip.
    #[arg(long)]
    strips: bool,
    /// A selenolocation error of each observation as EAST/NORTH metres (in `--sun` order;
    /// missing ones are 0/0): its LOC backplane puts every pixel that far from where it
    /// lies, e.g. `--loc-offset 0/0 --loc-offset 150/150`. `run` registers it back
    /// (docs/science.md, "Registration").
    #[arg(long = "loc-offset", allow_hyphen_values = true, value_parser = sfsfuse::synth::parse_offset)]
    loc_offsets: Vec<[f64; 2]>,
    /// A selenolocation error that drifts along each observation's strip, as EAST/NORTH
    /// metres (in `--sun` order; missing ones are 0/0): added to `--loc-offset` in
    /// proportion to the swath line, from none at the first line to all of it at the last,
    /// as an attitude drift would, e.g. `--loc-drift 840/0`. `run` registers it on
    /// segments along the strip (docs/science.md, "Registration").
    #[arg(long = "loc-drift", allow_hyphen_values = true, value_parser = sfsfuse::synth::parse_offset)]
    loc_drifts: Vec<[f64; 2]>,
    /// A gain drifting along each observation's strip (in `--sun` order; missing ones
    /// are 0): its radiance multiplied by exp(T·(l − l_mid)/1000) at swath line l, T the
    /// change of ln g per 1000 lines, e.g. `--gain-trend 0 --gain-trend 0.2`. `run`
    /// estimates it where observations overlap (`[inputs] gain_trend`, on by default;
    /// docs/science.md, "Several observations").
    #[arg(long = "gain-trend", allow_hyphen_values = true)]
    gain_trends: Vec<f64>,
    /// Residual detector column striping of each observation (in `--sun` order; missing
    /// ones are 0): each detector column's radiance multiplied by its own gain
    /// exp(S·N(0, 1)), S the RMS of ln g, e.g. `--column-striping 0.01` for 1 %. `run`
    /// estimates the gains over each swath and divides them out (`[inputs] destripe`, on by
    /// default; docs/science.md, "Detector column striping").
    #[arg(long = "column-striping", allow_hyphen_values = true)]
    column_striping: Vec<f64>,
    /// Each observation's detector pixel as F grid pixels (in `--sun` order; missing ones
    /// are 1): its swath holds F × F block means of the image, as M3's second optical
    /// period (200 km, ≈ 280 m pixels) sees a region gridded at the first's 140 m, e.g.
    /// `--pixel-factor 1 --pixel-factor 2` (docs/science.md, "Images coarser than the
    /// grid").
    #[arg(long = "pixel-factor")]
    pixel_factors: Vec<usize>,
    /// Centre of the scene's stereographic grid as LAT/LON in degrees (default: crater
    /// Alphonsus, -13.4/357.2). Scenes wider than ≈ 1100 px at 140 m reach longitude 0°
    /// from Alphonsus, which the LOLA-like writer does not handle: centre them further east.
    #[arg(long, allow_hyphen_values = true, value_parser = sfsfuse::demo::parse_center)]
    center: Option<(f64, f64)>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// `sfsfuse synth`: the options checked, the scene generated and written as mission-format
/// products ([`sfsfuse::synth::products::write_observed`]), and what was written reported.
fn synth(a: SynthArgs) -> Result<(), sfsfuse::Error> {
    let SynthArgs {
        out,
        size,
        seed,
        suns,
        sun_drifts,
        gains,
        strips,
        loc_offsets,
        loc_drifts,
        gain_trends,
        column_striping,
        pixel_factors,
        center,
        json,
    } = a;
    if pixel_factors.len() > suns.len().max(1) {
        return Err(sfsfuse::Error::Usage(format!(
            "{} --pixel-factor values for {} observation(s): give at most one per --sun",
            pixel_factors.len(),
            suns.len().max(1)
        )));
    }
    for (name, n) in [
        ("--sun-drift", sun_drifts.len()),
        ("--loc-offset", loc_offsets.len()),
        ("--loc-drift", loc_drifts.len()),
        ("--gain-trend", gain_trends.len()),
        ("--column-striping", column_striping.len()),
    ] {
        if n > suns.len().max(1) {
            return Err(sfsfuse::Error::Usage(format!(
                "{n} {name} values for {} observation(s): give at most one per --sun",
                suns.len().max(1)
            )));
        }
    }
    if let Some(t) = gain_trends
        .iter()
        .find(|t| !(t.is_finite() && t.abs() <= 10.0))
    {
        return Err(sfsfuse::Error::Usage(format!(
            "--gain-trend {t}: a change of ln g per 1000 lines must be a number within ±10"
        )));
    }
    if let Some(s) = column_striping
        .iter()
        .find(|s| !(s.is_finite() && (0.0..=0.5).contains(*s)))
    {
        return Err(sfsfuse::Error::Usage(format!(
            "--column-striping {s}: the RMS of ln g over the detector columns must be a number from 0 to 0.5"
        )));
    }
    let n = loc_offsets
        .len()
        .max(loc_drifts.len())
        .max(gain_trends.len())
        .max(column_striping.len());
    let loc_errors: Vec<sfsfuse::synth::products::ProductErrors> = (0..n)
        .map(|k| sfsfuse::synth::products::ProductErrors {
            offset_m: loc_offsets.get(k).copied().unwrap_or_default(),
            drift_m: loc_drifts.get(k).copied().unwrap_or_default(),
            gain_trend: gain_trends.get(k).copied().unwrap_or_default(),
            column_striping: column_striping.get(k).copied().unwrap_or_default(),
        })
        .collect();
    if let Some(g) = gains.iter().find(|g| !(g.is_finite() && **g > 0.0)) {
        return Err(sfsfuse::Error::Usage(format!(
            "--gain {g}: a gain must be a positive number"
        )));
    }
    if gains.len() >= suns.len().max(1) {
        return Err(sfsfuse::Error::Usage(format!(
            "{} --gain values for {} observation(s): give one per --sun after the first",
            gains.len(),
            suns.len().max(1)
        )));
    }
    let mut all_gains = vec![1.0];
    all_gains.extend(&gains);
    let spec = SceneSpec {
        size,
        seed,
        ..SceneSpec::default()
    };
    let spec = if suns.is_empty() {
        spec
    } else {
        spec.with_observations(&suns, &all_gains, strips)
    };
    let spec = spec
        .with_sun_drifts(&sun_drifts)
        .map_err(sfsfuse::Error::Usage)?;
    if size < 16 {
        return Err(sfsfuse::Error::Usage(format!(
            "--size {size} is too small: use at least 16"
        )));
    }
    let scene = sfsfuse::synth::generate(&spec);
    let grid = match center {
        Some((lat, lon)) => sfsfuse::demo::grid_at(&spec, lat, lon)?,
        None => sfsfuse::demo::demo_grid(&spec)?,
    };
    let p =
        sfsfuse::synth::products::write_observed(&scene, &grid, &out, &loc_errors, &pixel_factors)?;
    let labels: Vec<String> = p
        .m3_labels
        .iter()
        .map(|l| l.display().to_string())
        .collect();
    let table = format!(
        "M3-like L1B label   {}\nLOLA-like GDR label {}\nsolar spectrum      {}\ntruth DEM           {}\ntruth albedo        {}\n",
        labels.join("\n                    "),
        p.lola_label.display(),
        p.solar_table.display(),
        p.truth_dem.display(),
        p.truth_albedo.display()
    );
    emit(json, &p, table)?;
    Ok(())
}

/// `--threads N`: the global pool's size. Each worker holds a tile's arrays: far more
/// threads than cores only multiplies memory (100 000 threads never finished starting), so a
/// count beyond 16 × the cores (at least 64) is refused rather than guessed at.
fn set_threads(n: usize) -> Result<(), sfsfuse::Error> {
    let cores = std::thread::available_parallelism().map_or(1, |c| c.get());
    let cap = (16 * cores).max(64);
    if n == 0 || n > cap {
        return Err(sfsfuse::Error::Usage(format!(
            "--threads {n}: give 1 to {cap} (16 × the {cores} cores here, at least 64); without --threads every core is used"
        )));
    }
    rayon::ThreadPoolBuilder::new()
        .num_threads(n)
        .build_global()
        .map_err(|e| sfsfuse::Error::Usage(format!("--threads {n}: {e}")))?;
    Ok(())
}

/// `run --list-tiles`: a line per tile with its core and halo windows and whether it is done.
fn tile_table(tiles: &[sfsfuse::pipeline::TileStatus]) -> String {
    tiles
        .iter()
        .map(|t| {
            format!(
                "{:5}  core rows {}..{} cols {}..{}  with halo rows {}..{} cols {}..{}  {}\n",
                t.id,
                t.core.r0,
                t.core.r0 + t.core.rows,
                t.core.c0,
                t.core.c0 + t.core.cols,
                t.ext.r0,
                t.ext.r0 + t.ext.rows,
                t.ext.c0,
                t.ext.c0 + t.ext.cols,
                if t.done { "done" } else { "pending" }
            )
        })
        .collect()
}

fn run(cli: Cli) -> Result<(), sfsfuse::Error> {
    if let Some(n) = cli.threads {
        set_threads(n)?;
    }
    match cli.command {
        Command::Demo(a) => demo(a),
        Command::Inspect(a) => inspect(a),
        Command::Run(a) => run_workflow(a),
        Command::Fetch(a) => fetch(a),
        Command::Submit(a) => submit(a),
        Command::Synth(a) => synth(a),
        Command::Bench(a) => bench(a),
    }
}

/// `sfsfuse demo`: the demo scene with the asked observations, fused and scored.
fn demo(a: DemoArgs) -> Result<(), sfsfuse::Error> {
    let spec = SceneSpec {
        size: a.size,
        seed: a.seed,
        ..SceneSpec::default()
    }
    .with_observations(
        &sfsfuse::synth::DEMO_SUNS[..a.observations as usize],
        &[],
        a.strips,
    );
    let params = match a.solver {
        SolverKind::Fast => FusionParams::default(),
        SolverKind::Paper => FusionParams::paper(),
    };
    let report = sfsfuse::demo::run(&spec, &params, Some(&a.out), a.error_limit)?;
    emit(a.json, &report, report.table())
}

/// `sfsfuse inspect`.
fn inspect(a: InspectArgs) -> Result<(), sfsfuse::Error> {
    let i = sfsfuse::inspect::inspect(&a.path)?;
    emit(a.json, &i, i.table())?;
    match i.unreadable() {
        Some(why) => Err(sfsfuse::Error::Usage(why)),
        None => Ok(()),
    }
}

/// `sfsfuse run`: the tile list, some tiles, the mosaic only, or the whole run.
fn run_workflow(a: RunArgs) -> Result<(), sfsfuse::Error> {
    let wf = sfsfuse::workflow::Workflow::load(&a.workflow)?;
    let progress = progress_of(a.progress);
    if a.list_tiles {
        let tiles = sfsfuse::pipeline::list_tiles(&wf, &progress)?;
        return emit(a.json, &tiles, tile_table(&tiles));
    }
    let req = sfsfuse::pipeline::Request {
        tiles: a
            .tile
            .map(|t| sfsfuse::pipeline::parse_tiles(&t))
            .transpose()?,
        mosaic_only: a.mosaic,
    };
    let summary = sfsfuse::pipeline::run(&wf, &req, &progress)?;
    drop(progress);
    emit(a.json, &summary, summary.table())
}

/// `sfsfuse fetch`: the archive's defaults overridden by the options given.
fn fetch(a: FetchArgs) -> Result<(), sfsfuse::Error> {
    let mut src = sfsfuse::fetch::archive::Sources::default();
    if let Some(b) = a.m3_base {
        src.m3_base = b;
    }
    if let Some(b) = a.lola_base {
        src.lola_base = b;
    }
    src.checksums = a.checksums;
    if let Some(r) = a.retries {
        src.retries = r;
    }
    if let Some(t) = a.timeout {
        src.timeout_s = t;
    }
    let dir = a.to.unwrap_or_else(sfsfuse::fetch::default_dir);
    let progress = progress_of(a.progress);
    let fetched = sfsfuse::fetch::fetch(&a.ids, &dir, &src, &progress)?;
    drop(progress);
    emit(a.json, &fetched, sfsfuse::fetch::table(&fetched))
}

/// `sfsfuse submit`.
fn submit(a: SubmitArgs) -> Result<(), sfsfuse::Error> {
    let wf = sfsfuse::workflow::Workflow::load(&a.workflow)?;
    let opts = sfsfuse::cluster::Options {
        scheduler: a.scheduler,
        max_parallel: a.max_parallel,
        tiles_per_task: a.tiles_per_task,
        partition: a.partition,
        cpus_per_task: a.cpus_per_task,
        time: a.time,
        mem: a.mem,
        dependency: a.dependency,
        dry_run: a.dry_run,
    };
    let progress = progress_of(a.progress);
    let s = sfsfuse::cluster::submit(&a.workflow, &wf, &opts, &progress)?;
    drop(progress);
    emit(a.json, &s, s.table())
}

/// `sfsfuse bench`: the cost against the number of observations, the pipeline's tiles
/// against one tile, or the solvers against each other.
fn bench(a: BenchArgs) -> Result<(), sfsfuse::Error> {
    if let Some(n) = a.observations {
        let progress = progress_of(a.progress);
        let report = sfsfuse::bench::run_observations(a.size, n as usize, &progress)?;
        drop(progress);
        return emit(a.json, &report, report.table());
    }
    if a.pipeline {
        let report = sfsfuse::bench::run_pipeline(a.size, a.tile, a.repeat as usize)?;
        return emit(a.json, &report, report.table());
    }
    if !(a.paper_seconds.is_finite() && a.paper_seconds > 0.0) {
        return Err(sfsfuse::Error::Usage(format!(
            "--paper-seconds {}: give a positive number of seconds",
            a.paper_seconds
        )));
    }
    let progress = progress_of(a.progress);
    let report = sfsfuse::bench::run(a.size, a.paper_sweeps, a.paper_seconds, &progress)?;
    drop(progress);
    emit(a.json, &report, report.table())
}

/// Print a report as JSON or as its table. A reader that has gone away (`sfsfuse … | head`)
/// is not an error: what it wanted it has, and the command's work is done (as ripgrep does);
/// any other failure to write is.
fn emit<T: serde::Serialize>(json: bool, value: &T, table: String) -> Result<(), sfsfuse::Error> {
    let text = if json {
        let mut t = serde_json::to_string_pretty(value).map_err(|e| {
            sfsfuse::Error::Usage(format!("the report cannot be written as JSON: {e}"))
        })?;
        t.push('\n');
        t
    } else {
        table
    };
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => {
            Err(sfsfuse::Error::io("<standard output>", e))
        }
        _ => Ok(()),
    }
}

/// The solvers allocate and free many megapixel-sized arrays per iteration. glibc serves
/// allocations above its mmap threshold (128 KiB by default) with fresh zeroed mappings, so each
/// one costs page faults; keeping blocks up to 32 MiB on the heap and not trimming it lets them be
/// reused (≈ 10 % of the fusion time on a 1 MP scene).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn tune_allocator() {
    // SAFETY: mallopt only changes allocator parameters; called before any other thread exists.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn tune_allocator() {}

fn main() -> ExitCode {
    tune_allocator();
    match run(Cli::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // Nothing more to do if standard error itself is gone.
            let _ = writeln!(std::io::stderr(), "sfsfuse: error: {e}");
            ExitCode::FAILURE
        }
    }
}
