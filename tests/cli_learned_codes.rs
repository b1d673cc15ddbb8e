//! Deep sensing end to end: `train … --learn-codes` (relaxed → projection → fine-tuning) and
//! `train … --init-from RUN` (a decoder fine-tuned on new codes).

mod common;
use common::*;
use tcsense_sensor::npy::read_npy;
use tcsense_sensor::Codes;

#[test]
fn learned_codes_are_exact_exportable_and_decode() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "2", "-o", "ds"]);
    ok(
        d,
        &["codes", "generate", "--tap-constraint", "--hamming", "2", "--window", "2", "--length", "8", "--seed", "1", "-o", "start.json"],
    );
    let out = ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "start.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "6",
            "--relaxed-epochs",
            "4",
            "--codes-lr",
            "0.5",
            "--learn-codes",
            "-o",
            "run",
        ],
    );
    assert!(out.contains("4 relaxed epochs") && out.contains("tap+H2+W2"), "{out}");
    // the learned codes' range alias is reported (a warning below the threshold) and recorded
    assert!(out.contains("range alias"), "{out}");
    let projection: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("run/relaxed/projection.json")).unwrap()).unwrap();
    let alias = projection["range_alias"].as_f64().unwrap();
    assert!(alias > 0.0 && alias <= 2f64.sqrt() && out.contains(&format!("{alias:.3}")), "{alias} {out}");
    // the learned codes meet the constraints exactly and say where they come from
    let learned = Codes::load(&d.join("run/codes.json")).unwrap();
    let start = Codes::load(&d.join("start.json")).unwrap();
    assert_eq!(learned.constraints, start.constraints);
    assert_ne!(learned.digest(), start.digest(), "the codes did not move");
    assert_eq!(learned.provenance["method"], "learned");
    assert_eq!(learned.provenance["start_codes"], start.digest().as_str());
    let solver = learned.provenance["projection"]["solver"].as_str().unwrap().to_string();
    assert!(solver == "argmax" || solver == "exact", "{solver}");
    ok(d, &["codes", "check", "run/codes.json"]);
    ok(d, &["codes", "export", "run/codes.json", "-o", "mem"]);
    // the relaxed phase logs its distance to feasibility per epoch; fine-tuning logs its own
    let log = std::fs::read_to_string(d.join("run/relaxed/codes_log.csv")).unwrap();
    assert_eq!(log.lines().count(), 5, "{log}");
    assert!(log.starts_with("epoch,step,tau,penalty_weight,tap_violations,hamming_violations,window_violations\n"));
    let last_tau: f64 = log.lines().last().unwrap().split(',').nth(2).unwrap().parse().unwrap();
    assert!((last_tau - 0.1).abs() < 1e-9, "the temperature ends at tau_end: {last_tau}");
    assert_eq!(std::fs::read_to_string(d.join("run/metrics.csv")).unwrap().lines().count(), 3);
    // the run decodes measurements of its learned codes
    ok(d, &["simulate", "--codes", "run/codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "x.npy"]);
    assert_eq!(read_npy(&d.join("x.npy")).unwrap().shape(), &[1, 8, 8, 8]);
    // a finished run resumes to nothing; measurements of the start codes are refused by their sidecar
    let out = ok(d, &["train", "admm-net", "--epochs", "6", "--resume", "-o", "run"]);
    assert!(out.contains("already trained"), "{out}");
    ok(d, &["simulate", "--codes", "start.json", "--cube", "ds/test/x_000.npy", "-o", "y0.npy"]);
    fails(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y0.npy", "-o", "x0.npy"], &["y0.meta.json", "codes"]);

    // the U-Net learns codes too
    ok(
        d,
        &[
            "train",
            "unet",
            "--dataset",
            "ds",
            "--codes",
            "start.json",
            "--base-width",
            "2",
            "--levels",
            "2",
            "--epochs",
            "3",
            "--relaxed-epochs",
            "2",
            "--learn-codes",
            "-o",
            "unet",
        ],
    );
    ok(d, &["codes", "check", "unet/codes.json"]);
    // its gradient reaches the codes through the per-pixel normalisation, dark pixels included:
    // every logged loss is finite (a NaN from √0 once stopped nothing and was logged)
    for phase in ["unet/relaxed/metrics.csv", "unet/metrics.csv"] {
        let text = std::fs::read_to_string(d.join(phase)).unwrap();
        let losses: Vec<f64> = text.lines().skip(1).map(|l| l.split(',').nth(2).unwrap().parse().unwrap()).collect();
        assert!(!losses.is_empty() && losses.iter().all(|l| l.is_finite()), "{phase}: {losses:?}");
    }
    // bad settings
    fails(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "start.json",
            "--epochs",
            "3",
            "--relaxed-epochs",
            "4",
            "--learn-codes",
            "-o",
            "bad",
        ],
        &["relaxed_epochs", "got 4"],
    );
    let o = run(d, &["train", "admm-net", "--dataset", "ds", "--codes", "start.json", "--hamming", "2", "-o", "bad2"]);
    assert_eq!(o.status.code(), Some(2), "--hamming needs --learn-codes");
    assert!(!d.join("bad").join("model.bpk").exists() && !d.join("bad2").exists());
}

/// `--objective range` trains a cube decoder (and with --learn-codes its codes) on the
/// waveforms' distance besides the cube's loss: the same run with the cube's loss alone learns
/// other codes, the run's config records it, and an objective that is not the network's or the
/// dataset's product is refused before anything is written.
#[test]
fn the_range_objective_reaches_the_codes() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "3", "-o", "ds"]);
    ok(
        d,
        &["codes", "generate", "--tap-constraint", "--hamming", "2", "--window", "2", "--length", "8", "--seed", "1", "-o", "start.json"],
    );
    let learn = |objective: &str, out: &str| {
        let mut args = vec![
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "start.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "3",
            "--relaxed-epochs",
            "2",
            "--codes-lr",
            "0.5",
            "--learn-codes",
            "-o",
            out,
        ];
        if !objective.is_empty() {
            args.extend(["--objective", objective]);
        }
        ok(d, &args)
    };
    let out = learn("range", "range");
    assert!(out.contains("earth mover's distance (objective range)"), "{out}");
    learn("", "mse");
    let config = |run: &str| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(d.join(run).join("config.json")).unwrap()).unwrap()
    };
    assert_eq!(config("range")["objective"], "range");
    assert!(config("mse").get("objective").is_none(), "written only when given");
    let codes = |run: &str| Codes::load(&d.join(run).join("relaxed/projected_codes.json")).unwrap();
    assert_ne!(codes("range").digest(), codes("mse").digest(), "the range objective did not change what the codes learned");
    let loss = |run: &str| -> f64 {
        let text = std::fs::read_to_string(d.join(run).join("relaxed/metrics.csv")).unwrap();
        text.lines().nth(1).unwrap().split(',').nth(2).unwrap().parse().unwrap()
    };
    assert!(loss("range") > loss("mse"), "the distance adds to the loss: {} vs {}", loss("range"), loss("mse"));
    ok(d, &["codes", "check", "range/codes.json"]);
    // a LiDAR dataset has no lifetimes; a depth network's loss is its range
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds", "--codes", "start.json", "--epochs", "1", "--objective", "lifetime", "-o", "bad"],
        &["manifest.json", "objective lifetime", "--objective range"],
    );
    fails(
        d,
        &["train", "unet", "--dataset", "ds", "--codes", "start.json", "--epochs", "1", "--objective", "mse", "-o", "bad2"],
        &["objective", "mse", "depth network: range"],
    );
    assert!(!d.join("bad").exists() && !d.join("bad2").exists());
}

#[test]
fn init_from_starts_from_a_trained_decoder() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "2",
            "--seed",
            "3",
            "-o",
            "a",
        ],
    );
    // a vanishing learning rate: b's weights stay a's, so b decodes as a does (a fresh seed would not)
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "1",
            "--seed",
            "9",
            "--lr",
            "1e-12",
            "--init-from",
            "a",
            "-o",
            "b",
        ],
    );
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "1",
            "--seed",
            "9",
            "--lr",
            "1e-12",
            "-o",
            "c",
        ],
    );
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    for r in ["a", "b", "c"] {
        ok(d, &["reconstruct", "admm-net", "--run", r, "--measurements", "y.npy", "-o", &format!("x{r}.npy")]);
    }
    let (xa, xb, xc) = (read_npy(&d.join("xa.npy")).unwrap(), read_npy(&d.join("xb.npy")).unwrap(), read_npy(&d.join("xc.npy")).unwrap());
    let diff = |u: &ndarray::ArrayD<f32>, v: &ndarray::ArrayD<f32>| u.iter().zip(v).map(|(p, q)| (p - q).abs()).fold(0f32, f32::max);
    let peak = xa.iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(diff(&xa, &xb) < 1e-4 * peak, "b differs from a by {}", diff(&xa, &xb));
    assert!(diff(&xa, &xc) > 1e-3 * peak, "a fresh run decodes like a");
    // a recalibrated sensor: a measured matrix (here the physical IRF's) replaces the synthetic
    // one; the run keeps it and decodes with it
    ok(d, &["sensor", "matrix", "--codes", "codes.json", "--irf", "physical", "-o", "measured.npy"]);
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--stages",
            "1",
            "--channels",
            "2",
            "--epochs",
            "1",
            "--init-from",
            "a",
            "--irf",
            "measured.npy",
            "-o",
            "m",
        ],
    );
    assert_eq!(std::fs::read(d.join("m/sensor_matrix.npy")).unwrap(), std::fs::read(d.join("measured.npy")).unwrap());
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("m/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["measured"].as_bool(), cfg["init_from"].as_str()), (Some(true), Some("a")));
    ok(d, &["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "ds/test/x_000.npy", "-o", "yp.npy"]);
    ok(d, &["reconstruct", "admm-net", "--run", "m", "--measurements", "yp.npy", "-o", "xm.npy"]);
    ok(d, &["export", "onnx", "--run", "m", "-o", "m.onnx"]);
    // a matrix of another shape, or learning codes through a measured matrix, is refused
    ok(d, &["sensor", "matrix", "--codes", "codes.json", "--oversample", "2", "-o", "k2.npy"]);
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--epochs", "1", "--irf", "k2.npy", "-o", "m2"],
        &["k2.npy", "[4, 4, 8]"],
    );
    fails(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--epochs",
            "3",
            "--learn-codes",
            "--irf",
            "measured.npy",
            "-o",
            "m3",
        ],
        &["learn_codes", "measured"],
    );
    assert!(!d.join("m2").exists() && !d.join("m3").exists());
    // another network than the run's is refused before anything is written, naming the run's value
    fails(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--stages",
            "2",
            "--channels",
            "2",
            "--epochs",
            "1",
            "--init-from",
            "a",
            "-o",
            "e",
        ],
        &["a/config.json", "--stages 2", "stages 1"],
    );
    assert!(!d.join("e").exists());
}
