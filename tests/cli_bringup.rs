//! `tcsense bringup` end to end on a tiny simulated bench (a sweep of a non-ideal sensor →
//! calibration → the zoo's decoder fine-tuned to it → an ONNX model that takes raw tap images →
//! the check and the report), resuming, and its refusals.

mod common;

use common::*;
use std::path::Path;
use tcsense_sensor::npy::{read_npy, write_npy};

/// The simulated bench sensor's non-idealities, as `simulate` takes them.
const BENCH_SENSOR: &[&str] = &[
    "--tap-gain",
    "0.05",
    "--prnu",
    "0.02",
    "--dark",
    "0.01",
    "--gate-skew-ns",
    "0.1",
    "--modulation-contrast",
    "0.925",
    "--sensor-seed",
    "7",
];

fn bench(dir: &Path) {
    let zoo_codes = Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo/admm-lidar-designed/codes.json");
    std::fs::copy(zoo_codes, dir.join("codes.json")).unwrap();
    let sweep =
        ["simulate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "--size", "8x8", "--noise", "--average", "16"];
    ok(dir, &[&sweep[..], BENCH_SENSOR].concat());
}

/// `raw.npy`: the first held-back scene of a bring-up into `out/` through the bench sensor, with
/// noise, in electrons (the sweep's units).
fn raw_frames(dir: &Path) {
    let scene = ["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "out/check-scenes/test/x_000.npy"];
    ok(dir, &[&scene[..], &["--units", "electrons", "--noise"], BENCH_SENSOR, &["-o", "raw.npy"]].concat());
}

const BRINGUP: &[&str] = &[
    "bringup",
    "--sweep",
    "sweep",
    "--codes",
    "codes.json",
    "--decoder",
    "admm-lidar-designed",
    "--budget-minutes",
    "0.05",
    "--epochs",
    "2",
    "--scenes",
    "8",
    "--size",
    "16x16",
    "--check-items",
    "2",
    "-o",
    "out",
];

#[test]
fn a_sweep_becomes_a_deployed_decoder_with_a_report() {
    let d = tempdir();
    let dir = d.path();
    bench(dir);
    let out = ok(dir, BRINGUP);
    assert!(out.contains("wrote out/report.html"), "{out}");
    for f in [
        "cal/calibration.json",
        "cal/report.html",
        "runs/admm-lidar-designed/model.bpk",
        "runs/admm-lidar-designed/sensor_matrix.npy",
        "onnx/admm-lidar-designed.onnx",
        "results/check.json",
        "results/steps.json",
        "report.html",
    ] {
        assert!(dir.join("out").join(f).exists(), "out/{f} missing");
    }
    // fine-tuned from the zoo entry, for the calibrated sensor
    let cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/runs/admm-lidar-designed/config.json")).unwrap()).unwrap();
    assert!(cfg["init_from"].as_str().unwrap().ends_with("zoo/admm-lidar-designed") && cfg["measured"] == true, "{cfg}");
    // the check: TVAL3 and the zoo decoder under three conditions, the fine-tuned one, each with a range error
    let check: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("out/results/check.json")).unwrap()).unwrap();
    let rows = check["rows"].as_array().unwrap();
    let conditions: Vec<(&str, &str)> = rows.iter().map(|r| (r["decoder"].as_str().unwrap(), r["condition"].as_str().unwrap())).collect();
    assert_eq!(conditions.len(), 7, "{conditions:?}");
    assert!(
        conditions.contains(&("tval3", "calibration"))
            && conditions.contains(&("admm-lidar-designed", "calibration + fine-tuning"))
            && conditions.contains(&("admm-lidar-designed", "ideal sensor"))
    );
    assert!(rows.iter().all(|r| r["first_return_median_m"].as_f64().is_some_and(|v| v.is_finite() && v < 3.0)), "{rows:?}");
    assert_eq!(check["truth"]["gate_skew_s"].as_f64().map(|v| (v * 1e12).round()), Some(100.0));
    let html = std::fs::read_to_string(dir.join("out/report.html")).unwrap();
    assert!(
        html.contains("calibration + fine-tuning")
            && html.contains("data-ptr=\"/rows/6/first_return_median_m\"")
            && html.contains("cal/fit.png")
    );
    let steps: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("out/results/steps.json")).unwrap()).unwrap();
    assert_eq!(steps["steps"].as_array().unwrap().len(), 5, "calibration, scenes, one fine-tuning, export, check");
    // a rerun resumes: every step's outputs are there, and their times are kept
    let again = ok(dir, BRINGUP);
    assert_eq!(again.matches("done by an earlier run").count(), 5, "{again}");
    let steps2: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("out/results/steps.json")).unwrap()).unwrap();
    assert_eq!(steps2["steps"], steps["steps"]);
    // the exported model takes the sensor's raw tap images (electrons, the sweep's units)
    raw_frames(dir);
    ok(dir, &["infer", "--model", "out/onnx/admm-lidar-designed.onnx", "--measurements", "raw.npy", "-o", "inf"]);
    assert!(dir.join("inf").exists());
}

#[test]
fn bad_bringups_exit_2_and_write_nothing() {
    let d = tempdir();
    let dir = d.path();
    bench(dir);
    let with = |pairs: &[(&'static str, &'static str)]| -> Vec<&'static str> {
        let mut a = BRINGUP.to_vec();
        for (flag, v) in pairs {
            match a.iter().position(|x| x == flag) {
                Some(i) => a[i + 1] = v,
                None => a.extend([*flag, *v]),
            }
        }
        a
    };
    fails(dir, &with(&[("--sweep", "nosweep")]), &["nosweep"]);
    fails(dir, &with(&[("--decoder", "no-such-entry")]), &["no-such-entry"]);
    fails(dir, &with(&[("--heterodyne", "8")]), &["zoo:admm-lidar-designed", "T = 256"]);
    fails(dir, &with(&[("--size", "15x16")]), &["--size 15x16"]);
    assert!(!dir.join("out").exists(), "a refused bring-up writes nothing");
}

/// A decoder on a fit's evidence brought up: its graph reads the evidence, so the calibration's
/// dark and gain maps travel in the model's metadata and its runtime corrects the raw frames
/// before the evidence; deployed as the better of the calibration alone and fine-tuned.
#[test]
fn a_decoder_on_the_fits_evidence_is_brought_up_and_corrects_raw_frames() {
    let d = tempdir();
    let dir = d.path();
    bench(dir);
    let mut args = BRINGUP.to_vec();
    let i = args.iter().position(|a| *a == "admm-lidar-designed").unwrap();
    args[i] = "unet-lidar-evidence";
    let out = ok(dir, &args);
    assert!(out.contains("wrote out/report.html"), "{out}");
    let check: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("out/results/check.json")).unwrap()).unwrap();
    let error = |condition: &str| {
        check["rows"].as_array().unwrap().iter().find(|r| r["decoder"] == "unet-lidar-evidence" && r["condition"] == condition).unwrap()
            ["first_return_median_m"]
            .as_f64()
            .unwrap()
    };
    let (alone, tuned) = (error("calibration"), error("calibration + fine-tuning"));
    assert!(alone.is_finite() && tuned.is_finite() && alone < 3.0, "{check}");
    // deployed as the better of the two
    let deployed: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("out/results/deployed.json")).unwrap()).unwrap();
    let want = if alone < tuned { "calibration" } else { "calibration + fine-tuning" };
    assert_eq!(deployed["deployed"][0]["condition"], want, "{deployed} against {alone} / {tuned}");
    let html = std::fs::read_to_string(dir.join("out/report.html")).unwrap();
    assert!(html.contains("deployed as") && html.contains(want));
    // raw frames of a held-back scene through the bench sensor, in the sweep's units
    raw_frames(dir);
    ok(dir, &["infer", "--model", "out/onnx/unet-lidar-evidence.onnx", "--measurements", "raw.npy", "-o", "inf"]);
    // the same network without the calibration built in, on frames corrected by hand with the
    // calibration's maps, gives the same depth: the model corrects the raw frames itself
    let from = if want == "calibration" { "zoo:unet-lidar-evidence" } else { "out/runs/unet-lidar-evidence" };
    ok(dir, &["export", "onnx", "--run", from, "--calibration", "out/cal", "-o", "again.onnx"]);
    ok(dir, &["infer", "--model", "again.onnx", "--measurements", "raw.npy", "-o", "inf-again"]);
    assert_eq!(std::fs::read(dir.join("inf/depth.npy")).unwrap(), std::fs::read(dir.join("inf-again/depth.npy")).unwrap());
    let cal = dir.join("out/cal");
    let (dark, gain) = (read_npy(&cal.join("dark.npy")).unwrap(), read_npy(&cal.join("gain.npy")).unwrap());
    let raw = read_npy(&dir.join("raw.npy")).unwrap();
    assert_eq!(raw.shape()[raw.ndim() - 3..], *dark.shape(), "raw frames [.., M, H, W]");
    let corrected = (&raw - &dark) / &gain;
    write_npy(&dir.join("corrected.npy"), &corrected.view()).unwrap();
    // (the raw frames again without their sidecar, which names the nominal sensor)
    write_npy(&dir.join("bare.npy"), &raw.view()).unwrap();
    // the raw model refuses frames of another size than the calibration's; a model without the
    // calibration on the corrected frames, through the calibrated matrix (the fine-tuned run's)
    ok(dir, &["export", "onnx", "--run", "out/runs/unet-lidar-evidence", "-o", "plain.onnx"]);
    ok(dir, &["export", "onnx", "--run", "out/runs/unet-lidar-evidence", "--calibration", "out/cal", "-o", "tuned.onnx"]);
    ok(dir, &["infer", "--model", "tuned.onnx", "--measurements", "raw.npy", "-o", "inf-tuned"]);
    ok(dir, &["infer", "--model", "plain.onnx", "--measurements", "corrected.npy", "-o", "inf-plain"]);
    let a = read_npy(&dir.join("inf-tuned/depth.npy")).unwrap();
    let b = read_npy(&dir.join("inf-plain/depth.npy")).unwrap();
    assert_eq!(a.shape(), b.shape());
    let mut compared = 0;
    for (x, y) in a.iter().zip(b.iter()) {
        assert_eq!(x.is_nan(), y.is_nan(), "{a:?} against {b:?}");
        if x.is_finite() {
            assert!((x - y).abs() < 1e-4, "{x} against {y}");
            compared += 1;
        }
    }
    assert!(compared > 0, "no depth to compare: {a:?}");
    // and differ from the same model on the uncorrected frames
    ok(dir, &["infer", "--model", "plain.onnx", "--measurements", "bare.npy", "-o", "inf-raw"]);
    assert_ne!(std::fs::read(dir.join("inf-raw/depth.npy")).unwrap(), std::fs::read(dir.join("inf-plain/depth.npy")).unwrap());
}
