//! `sfsfuse submit` on a real single-node SLURM (started by `.ci/slurm-up` in CI): the
//! synthetic workflow submitted as an array of tile batches plus a mosaic job gives files
//! bit-identical to a local `sfsfuse run`; resubmitting submits only what is missing; a
//! failed tile makes the mosaic job fail naming the missing tiles. Outside CI, where no SLURM
//! runs, the tests skip with a message; with CI=true they must run.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

mod support;
use support::{run_ok, scene_products, scratch, sfsfuse, workflow, write_workflow};

/// Asserts that a SLURM controller answers with a node that takes jobs. The tests that need
/// one are `#[ignore]`d, so that a machine without SLURM reports them as ignored; `.ci/run`
/// starts one and runs them. A node still `completing` another test's jobs takes new ones
/// once it is done: the state is asked again for up to 30 s before giving up.
fn slurm() {
    let ready = || {
        Command::new("sinfo")
            .args(["-h", "-o", "%T"])
            .output()
            .is_ok_and(|o| {
                o.status.success()
                    && String::from_utf8_lossy(&o.stdout)
                        .lines()
                        .any(|l| ["idle", "mixed", "allocated", "completing"].contains(&l.trim()))
            })
    };
    let start = Instant::now();
    let mut up = ready();
    while !up && start.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_secs(1));
        up = ready();
    }
    assert!(
        up,
        "this test needs a SLURM cluster: no node answers `sinfo` (run .ci/slurm-up as root), or leave out --include-ignored"
    );
}

/// Wait until none of `jobs` is queued or running.
fn wait(jobs: &[String]) {
    let t0 = Instant::now();
    loop {
        let o = Command::new("squeue")
            .args(["-h", "-o", "%i %T", "-j", &jobs.join(",")])
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&o.stdout).to_string();
        if text.trim().is_empty() {
            return;
        }
        assert!(
            t0.elapsed() < Duration::from_secs(600),
            "jobs still queued after 10 minutes:\n{text}"
        );
        std::thread::sleep(Duration::from_millis(500));
    }
}

fn submit(wf: &Path, extra: &[&str]) -> serde_json::Value {
    let o = sfsfuse()
        .args([
            "submit",
            "--scheduler",
            "slurm",
            "--json",
            "--progress",
            "quiet",
        ])
        .args(extra)
        .arg(wf)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "submit failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    serde_json::from_slice(&o.stdout).unwrap()
}

fn jobs(s: &serde_json::Value) -> Vec<String> {
    ["tiles_job", "mosaic_job"]
        .iter()
        .filter_map(|k| s[k].as_str().map(String::from))
        .collect()
}

fn products_of(out: &Path) -> Vec<(String, Vec<u8>)> {
    ["dem", "albedo", "residual", "mask"]
        .iter()
        .map(|n| {
            (
                n.to_string(),
                std::fs::read(out.join(format!("{n}.tif")))
                    .unwrap_or_else(|e| panic!("{n}.tif: {e}")),
            )
        })
        .collect()
}

#[test]
#[ignore = "needs a running SLURM (.ci/slurm-up); .ci/run runs it"]
fn slurm_array_and_mosaic_match_a_local_run() {
    slurm();
    let p = scene_products(256, 10);
    let dir = scratch("slurm");
    let solver = "[solver]\nalbedo_sigmas = [30.0, 10.0, 4.0]";
    let (local, cluster) = (dir.join("local"), dir.join("cluster"));
    for (name, out) in [("l", &local), ("c", &cluster)] {
        std::fs::create_dir_all(dir.join(name)).unwrap();
        write_workflow(&dir.join(name), &workflow(p, out, 96, solver));
    }
    run_ok(
        &["run", "--progress", "quiet"],
        &dir.join("l/workflow.toml"),
    );
    let wf = dir.join("c/workflow.toml");
    // 9 tiles in batches of 4: 3 array tasks, at most 2 at once.
    let s = submit(&wf, &["--tiles-per-task", "4", "--max-parallel", "2"]);
    assert_eq!(s["tiles_total"], 9);
    assert_eq!(s["batches"], serde_json::json!(["0-3", "4-7", "8"]));
    wait(&jobs(&s));
    assert!(
        cluster.join("run.json").is_file(),
        "the mosaic job did not finish; logs in {}",
        cluster.join("cluster/logs").display()
    );
    for ((name, a), (_, b)) in products_of(&local).iter().zip(&products_of(&cluster)) {
        assert!(a == b, "{name}.tif from SLURM differs from the local run");
    }
    // Resubmitting after losing a tile submits that tile only, and the mosaic again.
    std::fs::remove_file(cluster.join("tiles/tile_00005.sfstile")).unwrap();
    std::fs::remove_file(cluster.join("dem.tif")).unwrap();
    let s = submit(&wf, &["--tiles-per-task", "4"]);
    assert_eq!(s["tiles_pending"], 1);
    assert_eq!(s["batches"], serde_json::json!(["5"]));
    wait(&jobs(&s));
    for ((name, a), (_, b)) in products_of(&local).iter().zip(&products_of(&cluster)) {
        assert!(a == b, "{name}.tif differs after resubmission");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
#[ignore = "needs a running SLURM (.ci/slurm-up); .ci/run runs it"]
fn a_failed_tile_makes_the_mosaic_job_fail_with_the_missing_tiles() {
    slurm();
    let p = scene_products(256, 10);
    let dir = scratch("slurm-fail");
    let out = dir.join("out");
    // The region runs east past the DEM: the eastern tiles cannot be fused. (Without the
    // plan's coarse reference, which would refuse the region before submitting anything.)
    let text = workflow(
        p,
        &out,
        128,
        "[solver]\nalbedo_sigmas = [30.0, 10.0, 4.0]\ncoarse_factor = 1",
    )
    .replace("x_max = 17920", "x_max = 40000");
    let wf = write_workflow(&dir, &text);
    let s = submit(&wf, &["--tiles-per-task", "1"]);
    wait(&jobs(&s));
    assert!(!out.join("dem.tif").exists() && !out.join("run.json").exists());
    let logs: Vec<_> = std::fs::read_dir(out.join("cluster/logs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    let mosaic = logs
        .iter()
        .find(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with("mosaic-")
        })
        .expect("a mosaic log");
    let log = std::fs::read_to_string(mosaic).unwrap();
    assert!(
        log.contains("cannot mosaic") && log.contains("missing"),
        "{log}"
    );
    let failed_task = logs.iter().any(|p| {
        std::fs::read_to_string(p)
            .unwrap_or_default()
            .contains("no LOLA DEM")
    });
    assert!(failed_task, "no tile task log names the cause");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Without a scheduler: `--dry-run` prints both scripts and submits nothing (SLURM and PBS).
#[test]
fn dry_run_prints_the_scripts() {
    let p = scene_products(256, 10);
    let dir = scratch("dry");
    let out = dir.join("out");
    let wf = write_workflow(
        &dir,
        &workflow(p, &out, 128, "[solver]\nalbedo_sigmas = [30.0, 10.0, 4.0]"),
    );
    for (sched, want, submit) in [
        (
            "slurm",
            "#SBATCH --array=0-1",
            [
                "tiles=$(sbatch --parsable ",
                "sbatch --parsable --dependency=afterany:$tiles ",
            ],
        ),
        (
            "pbs",
            "#PBS -J 0-1",
            ["tiles=$(qsub ", "qsub -W depend=afterany:$tiles "],
        ),
    ] {
        let o = sfsfuse()
            .args([
                "submit",
                "--dry-run",
                "--progress",
                "quiet",
                "--tiles-per-task",
                "2",
                "--scheduler",
                sched,
            ])
            .arg(&wf)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let text = String::from_utf8_lossy(&o.stdout);
        assert!(
            text.contains(want) && text.contains("--mosaic") && text.contains("--tile"),
            "{text}"
        );
        // The command lines that would submit them, the mosaic after the tiles.
        for line in submit {
            assert!(text.contains(line), "{line}: {text}");
        }
        assert!(!out.join("cluster").exists(), "a dry run wrote files");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
