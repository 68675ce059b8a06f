//! `sfsfuse submit`: hand a workflow's tiles to a cluster scheduler (docs/cluster.md).
//!
//! The run is planned on the submitting host (`plan.json`, on the shared file system), the
//! tiles not yet done are grouped into batches of `tiles_per_task`, and two jobs are written:
//! an **array job** whose task *k* runs `sfsfuse run WORKFLOW --tile <batch k>`, and a
//! **mosaic job** that runs `sfsfuse run WORKFLOW --mosaic` once the array has ended. The
//! mosaic job depends on the array with `afterany` by default: it then always starts, and
//! `--mosaic` itself refuses to blend unless every tile is finished, failing with the list of
//! missing tiles (with `afterok` a failed task would leave it pending for ever, saying
//! nothing). Resubmitting submits only the tiles still missing.
//!
//! Script text is made by pure functions; only [`submit`] writes files and runs `sbatch`/`qsub`.

use crate::error::{Error, Result};
use crate::pipeline;
use crate::progress::Progress;
use crate::raster::write_atomic;
use crate::workflow::Workflow;
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::process::Command;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Scheduler {
    /// SLURM: `sbatch --array`, `--dependency`.
    Slurm,
    /// PBS Pro / OpenPBS: `qsub -J`, `-W depend=`.
    Pbs,
}

/// When the mosaic job may start.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Dependency {
    /// After the array ends however it ended; the mosaic then checks every tile itself.
    Afterany,
    /// Only if every task succeeded (otherwise the scheduler never starts it).
    Afterok,
}

impl Dependency {
    fn word(self) -> &'static str {
        match self {
            Dependency::Afterany => "afterany",
            Dependency::Afterok => "afterok",
        }
    }
}

/// How to submit.
#[derive(Debug, Clone)]
pub struct Options {
    pub scheduler: Scheduler,
    /// Tasks of the array running at once (SLURM `%K`).
    pub max_parallel: Option<usize>,
    /// Tiles per array task (small tiles batched so the scheduler is not flooded).
    pub tiles_per_task: usize,
    pub partition: Option<String>,
    /// CPUs per task (also the task's `--threads`).
    pub cpus_per_task: usize,
    /// Wall-clock limit per task, scheduler syntax (e.g. `02:00:00`).
    pub time: Option<String>,
    /// Memory per task, scheduler syntax (e.g. `8G`).
    pub mem: Option<String>,
    pub dependency: Dependency,
    /// Print the scripts, submit nothing.
    pub dry_run: bool,
}

/// What was (or would be) submitted.
#[derive(Debug, Clone, Serialize)]
pub struct Submission {
    pub scheduler: Scheduler,
    pub tiles_total: usize,
    pub tiles_pending: usize,
    /// The `--tile` argument of each array task.
    pub batches: Vec<String>,
    pub tiles_script: Option<PathBuf>,
    pub mosaic_script: PathBuf,
    pub tiles_job: Option<String>,
    pub mosaic_job: Option<String>,
    /// The scripts' text (shown by `--dry-run`).
    pub scripts: Vec<(PathBuf, String)>,
    /// The command lines that submit them, the mosaic's depending on the tiles' job id (shell
    /// syntax; what `--dry-run` would run).
    pub commands: Vec<String>,
}

/// The shell command lines that submit `tiles` (if any) and then `mosaic` after it.
fn submit_commands(
    scheduler: Scheduler,
    dep: &str,
    tiles: Option<&Path>,
    mosaic: &Path,
) -> Vec<String> {
    let q = |p: &Path| quote(&p.display().to_string());
    let mut v = Vec::new();
    match scheduler {
        Scheduler::Slurm => match tiles {
            Some(t) => {
                v.push(format!("tiles=$(sbatch --parsable {})", q(t)));
                v.push(format!(
                    "sbatch --parsable --dependency={dep}:$tiles {}",
                    q(mosaic)
                ));
            }
            None => v.push(format!("sbatch --parsable {}", q(mosaic))),
        },
        Scheduler::Pbs => match tiles {
            Some(t) => {
                v.push(format!("tiles=$(qsub {})", q(t)));
                v.push(format!("qsub -W depend={dep}:$tiles {}", q(mosaic)));
            }
            None => v.push(format!("qsub {}", q(mosaic))),
        },
    }
    v
}

impl Submission {
    pub fn table(&self) -> String {
        let mut s = String::new();
        if self.mosaic_job.is_none() {
            for (path, text) in &self.scripts {
                s.push_str(&format!("# ---- {} ----\n{text}\n", path.display()));
            }
            s.push_str("# ---- submit with ----\n");
            for c in &self.commands {
                s.push_str(&format!("{c}\n"));
            }
        }
        s.push_str(&format!(
            "{} of {} tiles pending, in {} task(s)\n",
            self.tiles_pending,
            self.tiles_total,
            self.batches.len()
        ));
        if let Some(j) = &self.tiles_job {
            s.push_str(&format!("tiles job  {j}\n"));
        }
        if let Some(j) = &self.mosaic_job {
            s.push_str(&format!("mosaic job {j}\n"));
        }
        s
    }
}

/// `'…'` for bash, with embedded quotes escaped.
fn quote(s: &str) -> String {
    format!("'{}'", s.replace('\'', r"'\''"))
}

/// Group tile ids into `--tile` arguments of at most `per` tiles each.
pub fn batches(ids: &[usize], per: usize) -> Vec<String> {
    ids.chunks(per.max(1))
        .map(|c| pipeline::tile_spec(c, ","))
        .collect()
}

/// Everything a script needs.
pub struct ScriptSpec<'a> {
    pub exe: &'a Path,
    pub workflow: &'a Path,
    pub logs: &'a Path,
    pub name: &'a str,
    pub opts: &'a Options,
}

fn common_directives(prefix: &str, spec: &ScriptSpec, job: &str) -> Vec<String> {
    let o = spec.opts;
    let mut d = Vec::new();
    match o.scheduler {
        Scheduler::Slurm => {
            d.push(format!("{prefix} --job-name={}-{job}", spec.name));
            d.push(format!("{prefix} --cpus-per-task={}", o.cpus_per_task));
            d.push(format!("{prefix} --ntasks=1"));
            if let Some(p) = &o.partition {
                d.push(format!("{prefix} --partition={p}"));
            }
            if let Some(t) = &o.time {
                d.push(format!("{prefix} --time={t}"));
            }
            if let Some(m) = &o.mem {
                d.push(format!("{prefix} --mem={m}"));
            }
        }
        Scheduler::Pbs => {
            d.push(format!("{prefix} -N {}-{job}", spec.name));
            let mut sel = format!("{prefix} -l select=1:ncpus={}", o.cpus_per_task);
            if let Some(m) = &o.mem {
                sel.push_str(&format!(
                    ":mem={}",
                    m.to_ascii_lowercase().replace('g', "gb")
                ));
            }
            d.push(sel);
            if let Some(p) = &o.partition {
                d.push(format!("{prefix} -q {p}"));
            }
            if let Some(t) = &o.time {
                d.push(format!("{prefix} -l walltime={t}"));
            }
            d.push(format!("{prefix} -j oe"));
        }
    }
    d
}

/// The array job's script.
pub fn tiles_script(spec: &ScriptSpec, batches: &[String]) -> String {
    let o = spec.opts;
    let n = batches.len();
    let (prefix, index) = match o.scheduler {
        Scheduler::Slurm => ("#SBATCH", "${SLURM_ARRAY_TASK_ID}"),
        Scheduler::Pbs => ("#PBS", "${PBS_ARRAY_INDEX:-0}"),
    };
    let mut d = common_directives(prefix, spec, "tiles");
    match o.scheduler {
        Scheduler::Slurm => {
            let throttle = o.max_parallel.map_or(String::new(), |k| format!("%{k}"));
            d.push(format!("#SBATCH --array=0-{}{throttle}", n - 1));
            d.push(format!(
                "#SBATCH --output={}/tiles-%A_%a.log",
                spec.logs.display()
            ));
        }
        Scheduler::Pbs => {
            // PBS arrays need at least two subjobs; one batch is a plain job (index 0).
            if n > 1 {
                d.push(format!("#PBS -J 0-{}", n - 1));
            }
            d.push(format!("#PBS -o {}/", spec.logs.display()));
        }
    }
    let list: Vec<String> = batches.iter().map(|b| quote(b)).collect();
    format!(
        "#!/bin/bash\n# sfsfuse {ver}: tiles of {wf}\n{dirs}\nset -euo pipefail\nBATCHES=({list})\nexec {exe} --threads {cpus} run {wf_q} --progress lines --tile \"${{BATCHES[{index}]}}\"\n",
        ver = env!("CARGO_PKG_VERSION"),
        wf = spec.workflow.display(),
        dirs = d.join("\n"),
        list = list.join(" "),
        exe = quote(&spec.exe.display().to_string()),
        cpus = o.cpus_per_task,
        wf_q = quote(&spec.workflow.display().to_string()),
    )
}

/// The mosaic job's script (its dependency is given on the command line at submission).
pub fn mosaic_script(spec: &ScriptSpec) -> String {
    let o = spec.opts;
    let prefix = match o.scheduler {
        Scheduler::Slurm => "#SBATCH",
        Scheduler::Pbs => "#PBS",
    };
    let mut d = common_directives(prefix, spec, "mosaic");
    match o.scheduler {
        Scheduler::Slurm => d.push(format!(
            "#SBATCH --output={}/mosaic-%j.log",
            spec.logs.display()
        )),
        Scheduler::Pbs => d.push(format!("#PBS -o {}/", spec.logs.display())),
    }
    format!(
        "#!/bin/bash\n# sfsfuse {ver}: mosaic of {wf}; fails, listing them, if any tile is missing\n{dirs}\nset -euo pipefail\nexec {exe} --threads {cpus} run {wf_q} --progress lines --mosaic\n",
        ver = env!("CARGO_PKG_VERSION"),
        wf = spec.workflow.display(),
        dirs = d.join("\n"),
        exe = quote(&spec.exe.display().to_string()),
        cpus = o.cpus_per_task,
        wf_q = quote(&spec.workflow.display().to_string()),
    )
}

/// Run a submission command and return the job id it prints.
fn submit_cmd(mut cmd: Command, what: &str) -> Result<String> {
    let shown = format!("{cmd:?}");
    let o = cmd.output().map_err(|e| {
        Error::Usage(format!(
            "cannot run {what} ({shown}): {e} — is the scheduler's client installed and on PATH? Use --dry-run to see the scripts"
        ))
    })?;
    if !o.status.success() {
        return Err(Error::Usage(format!(
            "{shown} failed: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        )));
    }
    let out = String::from_utf8_lossy(&o.stdout).trim().to_string();
    // sbatch --parsable prints "ID" or "ID;cluster"; qsub prints "ID.server".
    let id = out.split(';').next().unwrap_or("").trim().to_string();
    if id.is_empty() {
        return Err(Error::Usage(format!("{shown} printed no job id")));
    }
    Ok(id)
}

/// Submit the tile script (when there are pending tiles) and the mosaic script after it, with
/// `opts.dependency` on the tile job: (the tile job's id, the mosaic job's id).
fn enqueue(
    opts: &Options,
    tiles: Option<&Path>,
    mosaic_script: &Path,
) -> Result<(Option<String>, String)> {
    let dep = opts.dependency.word();
    let (program, parsable): (&str, &[&str]) = match opts.scheduler {
        Scheduler::Slurm => ("sbatch", &["--parsable"]),
        Scheduler::Pbs => ("qsub", &[]),
    };
    let mut mosaic = Command::new(program);
    mosaic.args(parsable);
    let tiles_job = match tiles {
        Some(script) => {
            let mut c = Command::new(program);
            c.args(parsable).arg(script);
            let id = submit_cmd(c, program)?;
            match opts.scheduler {
                Scheduler::Slurm => mosaic.arg(format!("--dependency={dep}:{id}")),
                Scheduler::Pbs => mosaic.arg("-W").arg(format!("depend={dep}:{id}")),
            };
            Some(id)
        }
        None => None,
    };
    mosaic.arg(mosaic_script);
    Ok((tiles_job, submit_cmd(mosaic, program)?))
}

/// Plan the workflow at `wf_path`, write the scripts and submit them (see the module).
pub fn submit(
    wf_path: &Path,
    wf: &Workflow,
    opts: &Options,
    progress: &Progress,
) -> Result<Submission> {
    let Workflow::Orbital(o) = wf else {
        return Err(Error::Usage(
            "a lab workflow is one piece of work; run it with `sfsfuse run`".into(),
        ));
    };
    if opts.tiles_per_task == 0 || opts.cpus_per_task == 0 || opts.max_parallel == Some(0) {
        return Err(Error::Usage(
            "--tiles-per-task, --cpus-per-task and --max-parallel must be at least 1".into(),
        ));
    }
    let tiles = pipeline::list_tiles(wf, progress)?;
    let pending: Vec<usize> = tiles.iter().filter(|t| !t.done).map(|t| t.id).collect();
    let b = batches(&pending, opts.tiles_per_task);
    let exe = std::env::current_exe()
        .map_err(|e| Error::Usage(format!("cannot find the sfsfuse executable: {e}")))?;
    let workflow = wf_path.canonicalize().map_err(|e| Error::io(wf_path, e))?;
    let out = o
        .output
        .directory
        .canonicalize()
        .map_err(|e| Error::io(&o.output.directory, e))?;
    let dir = out.join("cluster");
    let logs = dir.join("logs");
    let name = format!(
        "sfsfuse-{}",
        workflow
            .file_stem()
            .map_or("run".into(), |s| s.to_string_lossy().to_string())
    );
    let spec = ScriptSpec {
        exe: &exe,
        workflow: &workflow,
        logs: &logs,
        name: &name,
        opts,
    };
    let ext = match opts.scheduler {
        Scheduler::Slurm => "sbatch",
        Scheduler::Pbs => "pbs",
    };
    let tiles_path = dir.join(format!("tiles.{ext}"));
    let mosaic_path = dir.join(format!("mosaic.{ext}"));
    let mut scripts = Vec::new();
    if !b.is_empty() {
        scripts.push((tiles_path.clone(), tiles_script(&spec, &b)));
    }
    scripts.push((mosaic_path.clone(), mosaic_script(&spec)));
    let mut sub = Submission {
        scheduler: opts.scheduler,
        tiles_total: tiles.len(),
        tiles_pending: pending.len(),
        batches: b.clone(),
        tiles_script: (!b.is_empty()).then(|| tiles_path.clone()),
        mosaic_script: mosaic_path.clone(),
        tiles_job: None,
        mosaic_job: None,
        scripts,
        commands: submit_commands(
            opts.scheduler,
            opts.dependency.word(),
            (!b.is_empty()).then_some(tiles_path.as_path()),
            &mosaic_path,
        ),
    };
    if opts.dry_run {
        return Ok(sub);
    }
    std::fs::create_dir_all(&logs).map_err(|e| Error::io(&logs, e))?;
    for (p, text) in &sub.scripts {
        write_atomic(p, text.as_bytes())?;
    }
    let (tiles_job, mosaic_job) = enqueue(opts, sub.tiles_script.as_deref(), &mosaic_path)?;
    (sub.tiles_job, sub.mosaic_job) = (tiles_job, Some(mosaic_job));
    progress.note(&format!(
        "submitted {} tile task(s) and the mosaic; logs in {}",
        sub.batches.len(),
        logs.display()
    ));
    Ok(sub)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(s: Scheduler) -> Options {
        Options {
            scheduler: s,
            max_parallel: Some(3),
            tiles_per_task: 2,
            partition: Some("short".into()),
            cpus_per_task: 4,
            time: Some("01:00:00".into()),
            mem: Some("8G".into()),
            dependency: Dependency::Afterany,
            dry_run: true,
        }
    }

    #[test]
    fn batches_group_pending_tiles() {
        assert_eq!(batches(&[0, 1, 2, 3, 4], 2), ["0-1", "2-3", "4"]);
        assert_eq!(batches(&[1, 5, 6, 9], 3), ["1,5-6", "9"]);
        assert!(batches(&[], 4).is_empty());
    }

    #[test]
    fn slurm_and_pbs_scripts_carry_the_array_and_the_tile_batches() {
        let (exe, wf, logs) = (
            Path::new("/opt/bin/sfsfuse"),
            Path::new("/data/it's.toml"),
            Path::new("/data/out/cluster/logs"),
        );
        let o = opts(Scheduler::Slurm);
        let spec = ScriptSpec {
            exe,
            workflow: wf,
            logs,
            name: "sfsfuse-x",
            opts: &o,
        };
        let s = tiles_script(&spec, &["0-1".into(), "2-3".into(), "4".into()]);
        for want in [
            "#SBATCH --array=0-2%3",
            "#SBATCH --partition=short",
            "#SBATCH --cpus-per-task=4",
            "#SBATCH --time=01:00:00",
            "#SBATCH --mem=8G",
            "BATCHES=('0-1' '2-3' '4')",
            "--tile \"${BATCHES[${SLURM_ARRAY_TASK_ID}]}\"",
            "'/data/it'\\''s.toml'",
            "--threads 4",
        ] {
            assert!(s.contains(want), "missing {want:?} in\n{s}");
        }
        assert!(mosaic_script(&spec).contains("--mosaic"));
        let p = opts(Scheduler::Pbs);
        let spec = ScriptSpec { opts: &p, ..spec };
        let s = tiles_script(&spec, &["0-1".into(), "2".into()]);
        for want in [
            "#PBS -J 0-1",
            "#PBS -l select=1:ncpus=4:mem=8gb",
            "#PBS -q short",
            "#PBS -l walltime=01:00:00",
            "${BATCHES[${PBS_ARRAY_INDEX:-0}]}",
        ] {
            assert!(s.contains(want), "missing {want:?} in\n{s}");
        }
        // One batch: no array (PBS arrays need two subjobs).
        assert!(!tiles_script(&spec, &["0".into()]).contains("-J"));
    }
}
