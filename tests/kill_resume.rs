//! Training survives being killed: a run killed at any moment — mid-epoch, or at each step of
//! a checkpoint write (`TCSENSE_FAILPOINT`, which aborts the process there with no cleanup,
//! like SIGKILL) — resumes with `--resume` to the same bytes of `model.bpk` and the same
//! `metrics.csv` (but for the seconds column) as a run that was never interrupted.

mod common;
use common::*;
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

const EPOCHS: &str = "4";

fn train_cmd(dir: &Path, run: &str, resume: bool) -> Command {
    let mut c = bin();
    c.current_dir(dir).args([
        "--threads",
        "2",
        "train",
        "admm-net",
        "--dataset",
        "ds",
        "--codes",
        "codes.json",
        "--epochs",
        EPOCHS,
        "--stages",
        "2",
        "--channels",
        "4",
        "--seed",
        "5",
        "-o",
        run,
    ]);
    if resume {
        c.arg("--resume");
    }
    c
}

/// Train `run`, dying at failpoint `point` (`NAME@N`).
fn die_at(dir: &Path, run: &str, resume: bool, point: &str) {
    let o = train_cmd(dir, run, resume).env("TCSENSE_FAILPOINT", point).output().unwrap();
    assert!(!o.status.success(), "{run}: expected to die at {point}");
    assert_eq!(o.status.code(), None, "{run}: killed by a signal at {point}, stderr: {}", String::from_utf8_lossy(&o.stderr));
}

/// Resume `run` to the end.
fn resume(dir: &Path, run: &str) {
    let o = train_cmd(dir, run, true).output().unwrap();
    assert!(o.status.success(), "{run}: resume failed: {}", String::from_utf8_lossy(&o.stderr));
}

/// `metrics.csv` without the wall-clock column.
fn metrics(dir: &Path, run: &str) -> Vec<String> {
    std::fs::read_to_string(dir.join(run).join("metrics.csv")).unwrap().lines().map(|l| l.rsplit_once(',').unwrap().0.to_string()).collect()
}

fn assert_same_as_straight(dir: &Path, run: &str) {
    let straight = std::fs::read(dir.join("straight/model.bpk")).unwrap();
    let got = std::fs::read(dir.join(run).join("model.bpk")).unwrap();
    assert!(got == straight, "{run}: model.bpk differs from the uninterrupted run's");
    assert_eq!(metrics(dir, run), metrics(dir, "straight"), "{run}: metrics.csv");
    assert_eq!(metrics(dir, run).len(), 1 + EPOCHS.parse::<usize>().unwrap());
    for leftover in ["checkpoint.tmp", "checkpoint.old", "model-new.bpk", ".lock"] {
        assert!(!dir.join(run).join(leftover).exists(), "{run}: {leftover} left behind");
    }
}

#[test]
fn killed_runs_resume_to_the_uninterrupted_weights() {
    let t = tempdir();
    let d = t.path();
    tiny_lidar_and_codes(d);
    let o = train_cmd(d, "straight", false).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // each step of a checkpoint write, in different epochs
    for (run, point) in [
        ("first-epoch", "checkpoint-written@1"), // before the first checkpoint exists: starts over
        ("tmp-written", "checkpoint-written@3"),
        ("between-renames", "checkpoint-renamed@1"), // only checkpoint.old/ is complete
        ("placed", "checkpoint-placed@2"),
        ("weights", "weights-written@2"), // the checkpoint is new, the top model.bpk not yet
    ] {
        die_at(d, run, false, point);
        resume(d, run);
        assert_same_as_straight(d, run);
    }

    // killed twice: between the renames, then again in the resumed run's next write
    die_at(d, "twice", false, "checkpoint-renamed@1");
    die_at(d, "twice", true, "checkpoint-written@1");
    resume(d, "twice");
    assert_same_as_straight(d, "twice");

    // SIGKILL at a moment chosen by the clock: as soon as the first epoch is logged
    let mut child = train_cmd(d, "sigkill", false).stderr(std::process::Stdio::null()).spawn().unwrap();
    let deadline = Instant::now() + Duration::from_secs(120);
    while std::fs::read_to_string(d.join("sigkill/metrics.csv")).map_or(0, |s| s.lines().count()) < 2 {
        assert!(Instant::now() < deadline, "the run never logged an epoch");
        std::thread::sleep(Duration::from_millis(2));
    }
    child.kill().unwrap(); // SIGKILL
    let status = child.wait().unwrap();
    if status.success() {
        eprintln!("the run finished before the kill landed; resuming a finished run");
    }
    resume(d, "sigkill");
    assert_same_as_straight(d, "sigkill");
}

/// Deep sensing survives kills too: in the relaxed phase (its checkpoint carries the code
/// logits and their optimiser), right after the projection, and in the fine-tuning phase.
#[test]
fn killed_learned_code_runs_resume_to_the_same_codes_and_weights() {
    let t = tempdir();
    let d = t.path();
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "2", "-o", "ds"]);
    ok(
        d,
        &["codes", "generate", "--tap-constraint", "--hamming", "2", "--window", "2", "--length", "8", "--seed", "1", "-o", "codes.json"],
    );
    let cmd = |run: &str, resume: bool| {
        let mut c = train_cmd(d, run, resume);
        c.args(["--learn-codes", "--relaxed-epochs", "2", "--codes-lr", "0.5"]);
        c
    };
    let o = cmd("straight", false).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for (run, point) in [("relaxed", "checkpoint-written@2"), ("projected", "checkpoint-written@3"), ("finetune", "checkpoint-renamed@2")] {
        let o = cmd(run, false).env("TCSENSE_FAILPOINT", point).output().unwrap();
        assert_eq!(o.status.code(), None, "{run}: killed at {point}");
        let o = cmd(run, true).output().unwrap();
        assert!(o.status.success(), "{run}: resume failed: {}", String::from_utf8_lossy(&o.stderr));
        for f in ["codes.json", "model.bpk", "relaxed/model.bpk", "relaxed/checkpoint/code_logits.bpk"] {
            assert!(
                std::fs::read(d.join(run).join(f)).unwrap() == std::fs::read(d.join("straight").join(f)).unwrap(),
                "{run}: {f} differs from the uninterrupted run's"
            );
        }
    }
}
