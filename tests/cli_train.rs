//! End-to-end tests of `tcsense train admm-net`, `reconstruct admm-net` and `eval` with both decoders.

mod common;
use common::*;
use tcsense_sensor::npy::read_npy;

#[test]
fn train_resume_reconstruct_and_eval() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    let out = ok(
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
            "run",
        ],
    );
    assert!(out.contains("epoch    2"), "{out}");
    for f in
        ["config.json", "codes.json", "metrics.csv", "model.bpk", "checkpoint/model.bpk", "checkpoint/optim.bpk", "checkpoint/state.json"]
    {
        assert!(d.join("run").join(f).exists(), "{f} missing");
    }
    assert_eq!(std::fs::read_to_string(d.join("run/metrics.csv")).unwrap().lines().count(), 3);
    // resume for one more epoch
    let out = ok(d, &["train", "admm-net", "--epochs", "3", "--resume", "-o", "run"]);
    assert!(out.contains("epoch    3") && !out.contains("epoch    1 "), "{out}");
    let csv = std::fs::read_to_string(d.join("run/metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 4, "{csv}");
    assert!(csv.lines().nth(3).unwrap().starts_with("3,9,"), "{csv}");
    // training curves
    ok(d, &["plot", "training", "--run", "run", "-o", "curves.png"]);
    assert!(std::fs::metadata(d.join("curves.png")).unwrap().len() > 10_000);
    fails(d, &["plot", "training", "--run", "nowhere", "-o", "c2.png"], &["nowhere/metrics.csv"]);
    assert!(!d.join("c2.png").exists());
    // a second fresh run into the same directory is refused
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--epochs", "1", "-o", "run"], &["--resume"]);
    // a resume continues on its own dataset: another one named is refused, the same one taken
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "4", "-o", "ds2"]);
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds2", "--epochs", "4", "--resume", "-o", "run"],
        &["ds2", "the run's own", "--init-from"],
    );
    assert_eq!(std::fs::read_to_string(d.join("run/metrics.csv")).unwrap().lines().count(), 4, "the refused resume trained nothing");

    // a saved config starts a new run, with flag overrides
    ok(d, &["train", "admm-net", "--config", "run/config.json", "--codes", "codes.json", "--epochs", "1", "-o", "run2"]);
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run2/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["epochs"].as_u64(), cfg["model"]["channels"].as_u64(), cfg["seed"].as_u64()), (Some(1), Some(2), Some(3)));
    std::fs::write(d.join("bad.json"), "{\"epochs\": 1}").unwrap();
    fails(
        d,
        &["train", "admm-net", "--config", "bad.json", "--codes", "codes.json", "-o", "run3"],
        &["bad.json", "malformed training config"],
    );

    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "xhat.npy"]);
    let xh = read_npy(&d.join("xhat.npy")).unwrap();
    assert_eq!(xh.shape(), &[1, 8, 8, 8]);
    assert!(xh.iter().all(|v| v.is_finite()));
    let out = ok(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--decoder",
            "tval3",
            "--decoder",
            "admm-net:run",
            "--maxit",
            "20",
            "-o",
            "rep.json",
        ],
    );
    assert!(out.contains("tval3") && out.contains("admm-net:run"), "{out}");
    let rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("rep.json")).unwrap()).unwrap();
    assert_eq!(rep.as_array().unwrap().len(), 2);
}

#[test]
fn bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    fails(d, &["train", "admm-net", "--dataset", "ds", "-o", "run"], &["--codes"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--taps", "2", "--length", "8", "-o", "c2.json"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "16", "-o", "c16.json"]);
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "c16.json", "--epochs", "1", "-o", "run16"], &["T = "]);
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--epochs", "0", "-o", "run0"], &["epochs"]);
    fails(d, &["train", "admm-net", "--resume", "-o", "nothing"], &["no run to resume"]);
    // a loss that is not finite stops the training with a message, and no final weights are written
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
            "1",
            "--epochs",
            "2",
            "--lr",
            "1e30",
            "-o",
            "diverged",
        ],
        &["training diverged", "nothing was written", "lower --lr"],
    );
    // (it diverged before its first checkpoint: the new run is gone)
    assert!(!d.join("diverged").exists());
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--pause-after", "0", "-o", "runp"],
        &["--pause-after 0", "at least one epoch"],
    );
    assert!(!d.join("runp").exists());
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--stop-after-steps", "0", "-o", "runp"],
        &["--stop-after-steps 0", "at least one step"],
    );
    assert!(!d.join("runp").exists());
    // a recipe's first steps: each one's loss printed, then stopped without a checkpoint; the
    // same command starts over and prints the same losses
    let first =
        ["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--stages", "1", "--seed", "4", "--stop-after-steps", "2"];
    let steps = |out: &str| out.lines().filter(|l| l.starts_with("step ")).map(str::to_string).collect::<Vec<_>>();
    let out = ok(d, &[&first[..], &["-o", "runs"]].concat());
    assert_eq!(steps(&out).len(), 2, "{out}");
    assert!(out.contains("stopped after 2 steps") && steps(&out)[1].contains("train loss"), "{out}");
    assert!(!d.join("runs/checkpoint").exists(), "no checkpoint");
    assert_eq!(steps(&ok(d, &[&first[..], &["-o", "runs"]].concat())), steps(&out), "the same losses again");
    fails(d, &[&first[..], &["--pause-after", "1", "-o", "runs"]].concat(), &["--stop-after-steps", "--pause-after"]);
    fails(d, &["reconstruct", "admm-net", "--run", "nothing", "--measurements", "y.npy", "-o", "x.npy"], &["nothing", "config.json"]);
    fails(
        d,
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--lr-schedule", "linear", "-o", "runlr"],
        &["--lr-schedule", "linear"],
    );
    assert!(!d.join("runlr").exists());
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
            "-o",
            "run",
        ],
    );
    // new runs decay the learning rate along a cosine; the config records it
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["lr_schedule"]["kind"].as_str(), cfg["lr_schedule"]["final_fraction"].as_f64()), (Some("cosine"), Some(0.01)));
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "8", "--seed", "9", "-o", "other.json"]);
    fails(d, &["eval", "--dataset", "ds", "--codes", "other.json", "--decoder", "admm-net:run"], &["other codes"]);
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "magic"], &["unknown decoder"]);
    // a cube decoder's peaks refined in the tap domain: the same cube (PSNR), ranges beside it
    let out = ok(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--decoder",
            "admm-net:run",
            "--decoder",
            "admm-net:run+fit",
            "-o",
            "fit.json",
        ],
    );
    let rows: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("fit.json")).unwrap()).unwrap();
    let rows = rows.as_array().cloned().unwrap_or_default();
    assert_eq!(rows.len(), 2, "{out}");
    assert_eq!(rows[0]["psnr_db"], rows[1]["psnr_db"], "{out}");
    assert!(rows[1]["depth"][0]["detected"].as_u64().unwrap_or(0) > 0, "{out}");
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "unet:run+fit"], &["+fit after a decoder of cubes"]);
    // a build without the GPU backend says how to get one, and writes nothing
    if !cfg!(feature = "gpu") {
        fails(
            d,
            &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--device", "gpu", "-o", "rungpu"],
            &["--device", "--features gpu"],
        );
        assert!(!d.join("rungpu").exists());
        fails(
            d,
            &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "--device", "gpu", "-o", "xg.npy"],
            &["--features gpu"],
        );
        fails(
            d,
            &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "admm-net:run", "--device", "gpu"],
            &["--features gpu"],
        );
    }
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--device", "tpu", "-o", "runtpu"], &["--device", "tpu"]);
}

#[test]
fn reconstruct_with_a_run_from_an_earlier_build() {
    let d = tempdir();
    let d = d.path();
    let fx = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1");
    let (run, y) = (fx.display().to_string(), fx.join("y.npy").display().to_string());
    let out = ok(d, &["reconstruct", "admm-net", "--run", &run, "--measurements", &y, "-o", "xhat.npy"]);
    assert!(out.contains("admm-net"), "{out}");
    let got = read_npy(&d.join("xhat.npy")).unwrap();
    let want = read_npy(&fx.join("xhat.npy")).unwrap();
    assert_eq!(got.shape(), want.shape());
    let diff = got.iter().zip(want.iter()).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff < 1e-5, "differs from the earlier build's reconstruction by {diff}");
    fails(
        d,
        &["reconstruct", "admm-net", "--run", &run, "--measurements", &fx.join("xhat.npy").display().to_string(), "-o", "x2.npy"],
        &["xhat.npy", "8 tap images", "M = 4"],
    );
    assert!(!d.join("x2.npy").exists());
}

#[test]
fn train_reconstruct_and_eval_the_unet() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    let out = ok(
        d,
        &[
            "train",
            "unet",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--base-width",
            "4",
            "--levels",
            "2",
            "--epochs",
            "2",
            "--seed",
            "3",
            "-o",
            "unet",
        ],
    );
    assert!(out.contains("U-Net") && out.contains("depth_rmse_m"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("unet/config.json")).unwrap()).unwrap();
    assert_eq!(
        (cfg["decoder"].as_str(), cfg["model"]["returns"].as_u64(), cfg["model"]["levels"].as_u64()),
        (Some("unet"), Some(2), Some(2))
    );
    let out = ok(d, &["train", "unet", "--epochs", "3", "--resume", "-o", "unet"]);
    assert!(out.contains("epoch    3"), "{out}");
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "--noise", "-o", "y.npy"]);
    let out = ok(
        d,
        &["reconstruct", "unet", "--run", "unet", "--measurements", "y.npy", "-o", "depth.npy", "--ply", "cloud.ply", "--png", "depth.png"],
    );
    assert!(out.contains("confidence"), "{out}");
    let depth = read_npy(&d.join("depth.npy")).unwrap();
    let conf = read_npy(&d.join("depth.confidence.npy")).unwrap();
    assert_eq!((depth.shape(), conf.shape()), (&[1, 2, 8, 8][..], &[1, 2, 8, 8][..]));
    assert!(depth.iter().zip(conf.iter()).all(|(d, c)| d.is_nan() == (*c < 0.5)));
    assert!(d.join("cloud.ply").exists() && d.join("depth.png").exists());
    let out = ok(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--decoder",
            "tval3",
            "--decoder",
            "unet:unet",
            "--maxit",
            "10",
            "--noise",
            "-o",
            "rep.json",
        ],
    );
    assert!(out.contains("unet:unet"), "{out}");
    let rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("rep.json")).unwrap()).unwrap();
    assert_eq!(rep[1]["decoder"].as_str(), Some("unet:unet"));
    assert_eq!(rep[1]["depth"].as_array().unwrap().len(), 2, "depth errors per return");
    // bad input: a FLIm dataset has no range labels; a run of the other kind
    ok(d, &["dataset", "flim", "--count", "3", "--size", "8x8", "--length", "8", "-o", "f"]);
    fails(d, &["train", "unet", "--dataset", "f", "--codes", "codes.json", "--epochs", "1", "-o", "u2"], &["f", "no depth field"]);
    fails(d, &["train", "admm-net", "--resume", "-o", "unet"], &["unet run", "tcsense train unet"]);
    fails(d, &["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--levels", "9", "-o", "u3"], &["levels"]);
}

/// The photon ladder and ambient light in training, and the U-Net that reads the matched
/// filters: recorded in the config, kept on resume, changeable on a fine-tune only; absurd
/// ranges refused before a run directory exists.
#[test]
fn ladder_ambient_and_the_matched_input() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    let base = ["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--base-width", "4", "--levels", "2", "--seed", "3"];
    let args = |extra: &[&'static str]| [&base[..], extra].concat();
    let out = ok(d, &args(&["--input", "matched", "--signal", "0.002,0.9", "--ambient", "0,2", "--epochs", "1", "-o", "m"]));
    assert!(out.contains("matched filters + U-Net") && out.contains("signal [0.002, 0.9]") && out.contains("ambient [0.0, 2.0]"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("m/config.json")).unwrap()).unwrap();
    assert_eq!(cfg["model"]["input"].as_str(), Some("Matched"));
    assert_eq!((cfg["augment"]["signal_fraction"][0].as_f64(), cfg["augment"]["ambient"][1].as_f64()), (Some(0.002), Some(2.0)));
    // resume keeps the input; another is refused
    fails(d, &["train", "unet", "--input", "backprojection", "--epochs", "2", "--resume", "-o", "m"], &["--input", "Matched"]);
    // the same seed without ambient light trains other weights: the ambient reaches the measurements
    ok(d, &args(&["--input", "matched", "--signal", "0.002,0.9", "--epochs", "1", "-o", "m0"]));
    assert_ne!(std::fs::read(d.join("m/model.bpk")).unwrap(), std::fs::read(d.join("m0/model.bpk")).unwrap());
    // a fine-tune may change what the network reads
    ok(
        d,
        &[
            "train",
            "unet",
            "--init-from",
            "m",
            "--input",
            "backprojection",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--epochs",
            "1",
            "-o",
            "bp",
        ],
    );
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("bp/config.json")).unwrap()).unwrap();
    assert_eq!(cfg["model"]["input"].as_str(), Some("Backprojection"));
    // and the network decodes: reconstruct and eval take it
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "--noise", "-o", "y.npy"]);
    ok(d, &["reconstruct", "unet", "--run", "m", "--measurements", "y.npy", "-o", "depth.npy"]);
    assert_eq!(read_npy(&d.join("depth.npy")).unwrap().shape(), &[1, 2, 8, 8]);
    // absurd ranges: usage errors or refusals naming the field, and no run directory
    for (flag, value, needle) in [
        ("--signal", "0.5,0.1", "LO is above HI"),
        ("--signal", "0,1", "signal_fraction"),
        ("--signal", "0.1,1e9", "signal_fraction"),
        ("--ambient", "-1,2", "ambient"),
        ("--ambient", "0,1e6", "ambient"),
        ("--ambient", "nan,1", "LO,HI"),
    ] {
        fails(d, &args(&[flag, value, "--epochs", "1", "-o", "bad"]), &[needle]);
        assert!(!d.join("bad").exists(), "{flag} {value} left a run directory");
    }
    fails(d, &args(&["--signal", "0.01,0.5", "--no-augment", "--epochs", "1", "-o", "bad"]), &["--no-augment"]);
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--input", "matched", "-o", "bad"], &["--input"]);
}

#[test]
fn the_lifetime_decoder_on_the_fit_evidence_trains_decodes_and_refuses_what_does_not_fit() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    ok(d, &["dataset", "flim", "--count", "6", "--size", "8x8", "--length", "8", "--heterodyne", "2", "-o", "f"]);
    let train = |extra: &[&str], out: &str| -> Vec<String> {
        let mut a: Vec<String> =
            ["train", "lifetime", "--dataset", "f", "--codes", "codes.json", "--base-width", "4", "--levels", "2", "--seed", "3"]
                .iter()
                .map(|s| s.to_string())
                .collect();
        a.extend(extra.iter().map(|s| s.to_string()));
        a.extend(["-o".to_string(), out.to_string()]);
        a
    };
    // a coarser grid than the default 96 points: the runtime and the graph follow the run's
    let args = train(&["--input", "costs", "--points", "40", "--epochs", "1"], "ev");
    let out = ok(d, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains("the fit's evidence on 40 lifetimes") && out.contains("lifetime MAE"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("ev/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["model"]["input"].as_str(), cfg["model"]["points"].as_u64()), (Some("Costs"), Some(40)));
    let x = tcsense_sensor::npy::read_npy(&d.join("f/test/x_000.npy")).unwrap();
    tcsense_sensor::npy::write_npy(&d.join("x.npy"), &x.index_axis(ndarray::Axis(0), 0)).unwrap();
    ok(d, &["simulate", "--codes", "codes.json", "--heterodyne", "2", "--cube", "x.npy", "--noise", "-o", "y.npy"]);
    ok(d, &["reconstruct", "lifetime", "--run", "ev", "--measurements", "y.npy", "-o", "tau.npy"]);
    let tau = tcsense_sensor::npy::read_npy(&d.join("tau.npy")).unwrap();
    assert_eq!(tau.shape(), &[4, 8, 8]);
    // lifetimes on the grid (0.05–25 ns) where the confidence lets them through, one component
    assert!(tau.index_axis(ndarray::Axis(0), 0).iter().all(|t| t.is_nan() || (0.05e-9..=25.0001e-9).contains(t)));
    assert!(tau.index_axis(ndarray::Axis(0), 3).iter().all(|a| a.is_nan() || *a == 1.0));
    // the same through the exported graph and ONNX Runtime, the evidence computed by infer
    ok(d, &["export", "onnx", "--run", "ev", "-o", "ev.onnx"]);
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "y.npy", "-o", "inf"]);
    let streamed = tcsense_sensor::npy::read_npy(&d.join("inf/lifetime.npy")).unwrap();
    for (a, b) in streamed.iter().zip(tau.index_axis(ndarray::Axis(0), 0).iter()) {
        assert!((a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-4 * b.abs(), "infer {a:e} against reconstruct {b:e}");
    }
    // the onset given (a calibration): only the IRF width is fitted; the item's own onset reads
    // its lifetimes, one 10 ns later does not
    let onset_ns = read_npy(&d.join("f/test/onset_000.npy")).unwrap().iter().next().copied().unwrap() as f64 * 1e9;
    let truth = read_npy(&d.join("f/test/lifetime_000.npy")).unwrap().index_axis_move(ndarray::Axis(0), 0);
    let (right_ns, wrong_ns) = (format!("{onset_ns}"), format!("{}", onset_ns + 10.0));
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "y.npy", "--onset-ns", &right_ns, "-o", "inf-right"]);
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "y.npy", "--onset-ns", &wrong_ns, "-o", "inf-wrong"]);
    let error = |dir: &str| {
        let t = read_npy(&d.join(dir).join("lifetime.npy")).unwrap();
        let v: Vec<f64> =
            t.iter().zip(truth.iter()).filter(|(a, b)| a.is_finite() && b.is_finite()).map(|(a, b)| ((a - b) / b).abs() as f64).collect();
        assert!(!v.is_empty(), "{dir}: lifetimes");
        v.iter().sum::<f64>() / v.len() as f64
    };
    let (right, wrong) = (error("inf-right"), error("inf-wrong"));
    assert!(right < 0.5 * wrong, "relative lifetime error: onset {right_ns} ns {right}, {wrong_ns} ns {wrong}");
    fails(d, &["infer", "--model", "ev.onnx", "--measurements", "y.npy", "--onset-ns", "5000", "-o", "bad"], &["--onset-ns", "onset"]);
    assert!(!d.join("bad").exists());
    // a stream is a pipeline (the next frame's evidence and the last one's refinement beside
    // the graph): each frame of a stack comes out as alone, in its place
    ok(d, &["simulate", "--codes", "codes.json", "--heterodyne", "2", "--cube", "x.npy", "--noise", "--seed", "9", "-o", "y2.npy"]);
    let (y1, y2) = (read_npy(&d.join("y.npy")).unwrap(), read_npy(&d.join("y2.npy")).unwrap());
    let stack = ndarray::stack(ndarray::Axis(0), &[y1.view(), y2.view(), y1.view(), y2.view()]).unwrap();
    tcsense_sensor::npy::write_npy(&d.join("stack.npy"), &stack.view()).unwrap();
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "stack.npy", "-o", "inf4"]);
    let four = read_npy(&d.join("inf4/lifetime.npy")).unwrap();
    assert_eq!(four.shape(), &[4, 8, 8]);
    let same = |a: ndarray::ArrayViewD<'_, f32>, b: ndarray::ArrayViewD<'_, f32>| {
        a.iter().zip(b.iter()).all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()))
    };
    let streamed = streamed.view().into_dyn();
    assert!(same(four.index_axis(ndarray::Axis(0), 0), streamed.view()), "frame 0 of the stack is the frame alone");
    assert!(same(four.index_axis(ndarray::Axis(0), 2), streamed.view()), "frame 2 of the stack is the frame alone");
    assert!(same(four.index_axis(ndarray::Axis(0), 1), four.index_axis(ndarray::Axis(0), 3)), "frames 1 and 3 agree");
    assert!(!same(four.index_axis(ndarray::Axis(0), 1), streamed.view()), "another noise draw, other lifetimes");
    // a frame the evidence stage refuses mid-stream: exit 2 naming it, nothing written
    let frames = d.join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    let mut bad = y2.clone();
    bad[[1, 3, 3]] = f32::NAN;
    for (k, f) in [&y1, &y2, &bad, &y1].into_iter().enumerate() {
        tcsense_sensor::npy::write_npy(&frames.join(format!("f{k}.npy")), &f.view()).unwrap();
    }
    fails(d, &["infer", "--model", "ev.onnx", "--measurements", "frames", "-o", "inf-bad"], &["f2.npy", "finite"]);
    assert!(!d.join("inf-bad").exists(), "nothing written");
    // the photon ladder of lifetime decoders and its figure (lifetime MAE and coverage against the light)
    let out = ok(
        d,
        &[
            "eval",
            "--dataset",
            "f",
            "--codes",
            "codes.json",
            "--heterodyne",
            "2",
            "--decoder",
            "lifetime:ev",
            "--decoder",
            "lifetime-fit",
            "--decoder",
            "lifetime-fit:7",
            "--light",
            "0.8,0.02",
            "--plot",
            "curve.png",
            "-o",
            "ladder.json",
        ],
    );
    assert!(out.contains("wrote curve.png"), "{out}");
    let png = std::fs::read(d.join("curve.png")).unwrap();
    assert!(png.len() > 10_000 && png.starts_with(b"\x89PNG"), "a drawn figure");
    let rows: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("ladder.json")).unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 6, "three decoders at two light levels");
    // the fit over 7x7 windows is another fit than over the default 3x3
    let mae = |dec: &str, light: f64| {
        rows.iter()
            .find(|r| r["decoder"] == dec && r["light"]["signal_fraction"].as_f64() == Some(light))
            .and_then(|r| r["lifetime_mae_s"].as_f64())
            .unwrap_or_else(|| panic!("{dec} at {light}"))
    };
    assert_ne!(mae("lifetime-fit", 0.02), mae("lifetime-fit:7", 0.02));
    for bad in ["lifetime-fit:4", "lifetime-fit:65", "lifetime-fit:x"] {
        fails(d, &["eval", "--dataset", "f", "--codes", "codes.json", "--heterodyne", "2", "--decoder", bad], &[bad, "odd window side"]);
    }
    // wider windows: their log-likelihoods beside the fit's window's, weighted pixel by pixel,
    // the sum at a learned temperature; recorded, decoded, exported and streamed as the network
    // without them
    let args = train(
        &[
            "--input",
            "costs",
            "--points",
            "40",
            "--windows",
            "5,9",
            "--temper",
            "--grid-ce",
            "0.5",
            "--refine-near-mode",
            "--lifetime-error",
            "log",
            "--epochs",
            "1",
        ],
        "evw",
    );
    let out = ok(d, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains("with wider windows [5, 9]") && out.contains("its log-likelihood at a learned temperature"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("evw/config.json")).unwrap()).unwrap();
    assert_eq!(cfg["model"]["windows"], serde_json::json!([5, 9]));
    assert_eq!(cfg["model"]["temper"], serde_json::json!(true));
    assert_eq!(cfg["grid_ce_weight"], serde_json::json!(0.5));
    assert_eq!(cfg["model"]["refine_near_mode"], serde_json::json!(true));
    assert!(out.contains("its mode refined in the taps within a point of the fit's"), "{out}");
    assert!(out.contains("the grid's cross-entropy at 0.5"), "{out}");
    // the lifetimes' error on ln τ as asked, and a new run's confidence trained (weighted)
    assert_eq!(cfg["lifetime_error"], serde_json::json!("log"));
    assert_eq!(cfg["confidence_loss"], serde_json::json!("weighted"));
    assert!(out.contains("the lifetimes' error on ln τ") && out.contains("the confidence's cross-entropy weighted"), "{out}");
    // a fine-tune continues its source's loss unless told otherwise
    let loss_of = |run: &str| -> [serde_json::Value; 3] {
        let c: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join(run).join("config.json")).unwrap()).unwrap();
        [c["grid_ce_weight"].clone(), c["lifetime_error"].clone(), c["confidence_loss"].clone()]
    };
    ok(d, &["train", "lifetime", "--dataset", "f", "--codes", "codes.json", "--init-from", "evw", "--epochs", "1", "-o", "evw-ft"]);
    assert_eq!(loss_of("evw-ft"), [serde_json::json!(0.5), serde_json::json!("log"), serde_json::json!("weighted")]);
    let told = ["--grid-ce", "0", "--lifetime-error", "ns", "--confidence-loss", "stalled"];
    let mut args = vec!["train", "lifetime", "--dataset", "f", "--codes", "codes.json", "--init-from", "evw", "--epochs", "1"];
    args.extend(told);
    args.extend(["-o", "evw-ft2"]);
    ok(d, &args);
    assert_eq!(loss_of("evw-ft2"), [serde_json::json!(0.0), serde_json::json!("ns"), serde_json::json!("stalled")]);
    // each frame's instrument on superpixels as its photons ask (the runs before it: every
    // pixel), a dim frame's under the frame's mixture when asked (it decodes so anyway)
    assert_eq!(cfg["model"]["instrument_blocks"], serde_json::json!(0));
    assert_eq!(cfg["model"]["instrument_mixture"], serde_json::json!(false));
    assert!(out.contains("the instrument on superpixels as the photons ask"), "{out}");
    ok(d, &["reconstruct", "lifetime", "--run", "evw", "--measurements", "y.npy", "-o", "tau-w.npy"]);
    let tau_w = read_npy(&d.join("tau-w.npy")).unwrap();
    ok(d, &["export", "onnx", "--run", "evw", "-o", "evw.onnx"]);
    ok(d, &["infer", "--model", "evw.onnx", "--measurements", "y.npy", "-o", "inf-w"]);
    let streamed_w = read_npy(&d.join("inf-w/lifetime.npy")).unwrap();
    assert!(streamed_w.iter().any(|t| t.is_finite()), "lifetimes through the windows");
    for (a, b) in streamed_w.iter().zip(tau_w.index_axis(ndarray::Axis(0), 0).iter()) {
        assert!((a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-4 * b.abs(), "infer {a:e} against reconstruct {b:e} (windows)");
    }
    // refused: an even or too narrow side, windows of the harmonics, windows with learned codes
    for (windows, needle) in [("4", "windows"), ("3,9", "windows"), ("9,5", "windows")] {
        let args = train(&["--input", "costs", "--windows", windows, "--epochs", "1"], "bad");
        fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &[needle]);
    }
    let args = train(&["--windows", "5", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["windows", "--input costs"]);
    let args = train(&["--instrument-blocks", "2", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["instrument_blocks", "--input costs"]);
    let args = train(&["--instrument-mixture", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["instrument_mixture", "--input costs"]);
    let args = train(&["--temper", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["temper", "--input costs"]);
    let args = train(&["--refine-near-mode", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["refine_near_mode", "--input costs"]);
    let args = train(&["--grid-ce", "0", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["grid_ce_weight", "--input costs"]);
    let args = train(&["--confidence-loss", "stalled", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["confidence_loss", "--input costs"]);
    let args = train(&["--input", "costs", "--confidence-loss", "none", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["--confidence-loss", "none"]);
    let args = train(&["--input", "costs", "--grid-ce", "11", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["--grid-ce", "11"]);
    // absurd numbers, refused before anything is said of them or written (found by
    // scripts/probe_numbers.py --flim: 10¹¹ levels hung counting their FLOPs; a rate of 1e308
    // diverged and left a run without a checkpoint, which is now removed)
    for (flag, v, needle) in [
        ("--levels", "99999999999", "model.levels"),
        ("--base-width", "99999999999", "model.base_width"),
        ("--batch-size", "99999999999", "batch_size"),
        ("--lr", "1e308", "nothing was written"),
    ] {
        let args = ["train", "lifetime", "--input", "costs", "--dataset", "f", "--codes", "codes.json", "--epochs", "1", flag, v];
        fails(d, &[&args[..], &["-o", "absurd"]].concat(), &[needle]);
        assert!(!d.join("absurd").exists(), "{flag} {v}: a run left behind");
    }
    // one step in all: its loss is taken before the step, and the weights it leaves are not
    // finite (a run with them was written before the weights were checked)
    let args = ["train", "lifetime", "--input", "costs", "--dataset", "f", "--codes", "codes.json", "--epochs", "1", "--max-train", "1"];
    fails(d, &[&args[..], &["--batch-size", "1", "--lr", "1e308", "-o", "absurd"]].concat(), &["diverged", "nothing was written"]);
    assert!(!d.join("absurd").exists(), "one step at --lr 1e308: a run left behind");
    // the harmonics' count for a network that reads none
    let args = train(&["--input", "costs", "--harmonics", "5", "--epochs", "1"], "absurd");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["harmonics", "input costs"]);
    let args = train(&["--input", "costs", "--windows", "5", "--epochs", "2", "--relaxed-epochs", "1", "--learn-codes"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["learn_codes", "wider windows"]);
    assert!(!d.join("bad").exists());
    // deep sensing on the fit's evidence: the lifetime loss reaches the codes through the
    // evidence's differentiable copy (models/src/lifetime_evidence.rs); the codes come out exact
    let args = train(&["--input", "costs", "--points", "40", "--epochs", "2", "--relaxed-epochs", "1", "--learn-codes"], "evl");
    let out = ok(d, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains("1 relaxed epochs"), "{out}");
    ok(d, &["codes", "check", "evl/codes.json"]);
    let learned: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("evl/codes.json")).unwrap()).unwrap();
    assert_eq!(learned["provenance"]["method"], "learned");
    // refused: an input of another network; a U-Net input for a lifetime run; the graph with the matrix as an input
    fails(d, &["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--input", "harmonics", "-o", "u"], &["input", "harmonics"]);
    let args = train(&["--input", "matched", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["input", "matched"]);
    fails(d, &["export", "onnx", "--run", "ev", "--matrix-input", "-o", "m.onnx"], &["--matrix-input"]);
    // a lifetime grid for the harmonics, which have none; a grid of 2 points
    let args = train(&["--points", "40", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["points", "--input costs"]);
    let args = train(&["--input", "costs", "--points", "2", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["--points", "2"]);
    assert!(!d.join("bad").exists() && !d.join("m.onnx").exists());
}

/// The U-Net on the range fit's evidence: trains, reconstructs (depth NaN exactly where the
/// confidence is below one half), streams through its exported graph as reconstruct decodes,
/// takes its place on the photon ladder, and refuses what does not fit it.
#[test]
fn the_unet_on_the_range_fit_evidence_trains_decodes_and_streams_as_reconstruct() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    let train = |extra: &[&str], out: &str| -> Vec<String> {
        let mut a: Vec<String> = [
            "train",
            "unet",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--input",
            "costs",
            "--base-width",
            "4",
            "--levels",
            "2",
            "--seed",
            "3",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        a.extend(extra.iter().map(|s| s.to_string()));
        a.extend(["-o".to_string(), out.to_string()]);
        a
    };
    let args = train(&["--epochs", "1", "--signal", "0.01,0.9", "--ambient", "0,1"], "ev");
    let out = ok(d, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains("the range fit's evidence on 32 candidates") && out.contains("depth_rmse_m"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("ev/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["model"]["input"].as_str(), cfg["model"]["oversample"].as_u64()), (Some("Costs"), Some(4)));
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "--noise", "-o", "y.npy"]);
    ok(d, &["reconstruct", "unet", "--run", "ev", "--measurements", "y.npy", "-o", "depth.npy"]);
    let depth = read_npy(&d.join("depth.npy")).unwrap();
    let conf = read_npy(&d.join("depth.confidence.npy")).unwrap();
    assert_eq!(depth.shape(), &[1, 2, 8, 8]);
    assert!(depth.iter().zip(conf.iter()).all(|(d, c)| d.is_nan() == (*c < 0.5)));
    assert!(depth.iter().any(|v| v.is_finite()), "some returns");
    // the same through the exported graph and ONNX Runtime, the evidence and refinement by infer
    let out = ok(d, &["export", "onnx", "--run", "ev", "-o", "ev.onnx"]);
    assert!(out.contains("range fit's evidence"), "{out}");
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "y.npy", "-o", "inf"]);
    let streamed = read_npy(&d.join("inf/depth.npy")).unwrap();
    for (a, b) in streamed.iter().zip(depth.index_axis(ndarray::Axis(1), 0).iter()) {
        assert!((a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-4 * b.abs().max(1.0), "infer {a} against reconstruct {b}");
    }
    // streamed as a pipeline, each frame as alone and in its place; a dark frame (no evidence,
    // the graph not run) has no return and no confidence
    let y = read_npy(&d.join("y.npy")).unwrap();
    let y = if y.ndim() == 4 { y.index_axis(ndarray::Axis(0), 0).to_owned() } else { y };
    let dark = ndarray::ArrayD::<f32>::zeros(y.shape());
    let stack = ndarray::stack(ndarray::Axis(0), &[y.view(), dark.view(), y.view()]).unwrap();
    tcsense_sensor::npy::write_npy(&d.join("stack.npy"), &stack.view()).unwrap();
    ok(d, &["infer", "--model", "ev.onnx", "--measurements", "stack.npy", "-o", "inf3"]);
    let (three, conf3) = (read_npy(&d.join("inf3/depth.npy")).unwrap(), read_npy(&d.join("inf3/confidence.npy")).unwrap());
    assert_eq!(three.shape(), &[3, 2, 8, 8]);
    let bits = |a: ndarray::ArrayViewD<'_, f32>| a.iter().map(|v| if v.is_nan() { u32::MAX } else { v.to_bits() }).collect::<Vec<u32>>();
    let single = bits(streamed.view().into_dyn());
    assert_eq!(bits(three.index_axis(ndarray::Axis(0), 0)), single[single.len() - 2 * 64..], "frame 0 as alone");
    assert_eq!(bits(three.index_axis(ndarray::Axis(0), 2)), bits(three.index_axis(ndarray::Axis(0), 0)), "frame 2 as frame 0");
    assert!(three.index_axis(ndarray::Axis(0), 1).iter().all(|v| v.is_nan()), "no return in the dark");
    assert!(conf3.index_axis(ndarray::Axis(0), 1).iter().all(|&c| c == 0.0), "no confidence in the dark");
    // the photon ladder beside the fit
    ok(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--decoder",
            "unet:ev",
            "--decoder",
            "depth-fit",
            "--light",
            "0.8,0.02",
            "-o",
            "ladder.json",
        ],
    );
    let rows: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("ladder.json")).unwrap()).unwrap();
    assert_eq!(rows.as_array().unwrap().len(), 4, "two decoders at two light levels");
    // refused: the regression head on the evidence; the graph with the matrix as an input
    let args = train(&["--head", "regression", "--epochs", "1"], "bad");
    fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &["score-volume"]);
    fails(d, &["export", "onnx", "--run", "ev", "--matrix-input", "-o", "m.onnx"], &["--matrix-input"]);
    // deep sensing on the fit's evidence: the range loss reaches the codes through the
    // evidence's differentiable copy (models/src/range_evidence.rs); the codes come out exact
    let args = train(&["--epochs", "2", "--relaxed-epochs", "1", "--learn-codes"], "evl");
    let out = ok(d, &args.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(out.contains("1 relaxed epochs"), "{out}");
    ok(d, &["codes", "check", "evl/codes.json"]);
    // pooled by likeness: a fine-tune of the run may pool its window (the weights fit either);
    // recorded, decoded, exported and streamed as the network on the window alone
    let out = ok(
        d,
        &[
            "train",
            "unet",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--init-from",
            "ev",
            "--pool-like",
            "9",
            "--epochs",
            "1",
            "-o",
            "evp",
        ],
    );
    assert!(out.contains("its window pooled by likeness over 9×9"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("evp/config.json")).unwrap()).unwrap();
    assert_eq!(cfg["model"]["pool_like"], serde_json::json!(9));
    ok(d, &["reconstruct", "unet", "--run", "evp", "--measurements", "y.npy", "-o", "depth-p.npy"]);
    let pooled = read_npy(&d.join("depth-p.npy")).unwrap();
    assert!(pooled.iter().any(|v| v.is_finite()), "some returns pooled");
    let out = ok(d, &["export", "onnx", "--run", "evp", "-o", "evp.onnx"]);
    assert!(out.contains("pooled by likeness over 9×9"), "{out}");
    ok(d, &["infer", "--model", "evp.onnx", "--measurements", "y.npy", "-o", "inf-p"]);
    let streamed = read_npy(&d.join("inf-p/depth.npy")).unwrap();
    for (a, b) in streamed.iter().zip(pooled.index_axis(ndarray::Axis(1), 0).iter()) {
        assert!((a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-4 * b.abs().max(1.0), "infer {a} against reconstruct {b} (pooled)");
    }
    // a pixel's cross-entropy held at a cap: recorded, said, and continued by a fine-tune of
    // the run that does not set it
    let tune = |from: &str, extra: &[&str], out: &str| {
        let mut a = vec!["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--init-from", from, "--epochs", "1"];
        a.extend(extra);
        a.extend(["-o", out]);
        ok(d, &a)
    };
    let cap_of = |run: &str| -> serde_json::Value {
        serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(d.join(run).join("config.json")).unwrap()).unwrap()
            ["grid_nll_cap"]
            .clone()
    };
    let out = tune("evp", &["--grid-nll-cap", "4"], "evc");
    assert!(out.contains("each pixel's cross-entropy held at 4 nats"), "{out}");
    assert_eq!(cap_of("evc"), serde_json::json!(4.0));
    assert_eq!(cap_of("evp"), serde_json::Value::Null, "not written where not asked");
    let out = tune("evc", &[], "evc2");
    assert!(out.contains("held at 4 nats"), "{out}");
    assert_eq!(cap_of("evc2"), serde_json::json!(4.0));
    // (a run trained with it decodes: the cap is training's, not the network's)
    ok(d, &["reconstruct", "unet", "--run", "evc", "--measurements", "y.npy", "-o", "depth-c.npy"]);
    // refused: a cap out of its range (and below, a cap for a network on another input)
    fails(d, &["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--grid-nll-cap", "0", "-o", "bad"], &["--grid-nll-cap"]);
    // refused: a side that tiles no 3×3 windows, pooling without the evidence, learned codes
    for (extra, needle) in [
        (&["--pool-like", "4", "--epochs", "1"][..], "pool_like"),
        (&["--pool-like", "9", "--epochs", "2", "--relaxed-epochs", "1", "--learn-codes"][..], "learn_codes"),
    ] {
        let args = train(extra, "bad");
        fails(d, &args.iter().map(String::as_str).collect::<Vec<_>>(), &[needle]);
    }
    // refused on another input than the evidence: pooling it, capping its grid's cross-entropy
    for (flag, value, needles) in [("--pool-like", "9", ["pool_like", "costs"]), ("--grid-nll-cap", "4", ["grid_nll_cap", "score-volume"])]
    {
        let args =
            ["train", "unet", "--dataset", "ds", "--codes", "codes.json", "--input", "matched", flag, value, "--epochs", "1", "-o", "bad"];
        fails(d, &args, &needles);
    }
    assert!(!d.join("bad").exists() && !d.join("m.onnx").exists());
}

#[test]
fn train_and_eval_the_lifetime_decoder() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    ok(d, &["dataset", "flim", "--count", "6", "--size", "8x8", "--length", "8", "--heterodyne", "2", "-o", "f"]);
    let out = ok(
        d,
        &[
            "train",
            "lifetime",
            "--dataset",
            "f",
            "--codes",
            "codes.json",
            "--harmonics",
            "3",
            "--base-width",
            "4",
            "--levels",
            "2",
            "--epochs",
            "2",
            "--seed",
            "3",
            "-o",
            "lt",
        ],
    );
    assert!(out.contains("lifetime decoder") && out.contains("lifetime MAE"), "{out}");
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("lt/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["decoder"].as_str(), cfg["model"]["harmonics"].as_u64()), (Some("lifetime"), Some(3)));
    let out = ok(
        d,
        &[
            "eval",
            "--dataset",
            "f",
            "--codes",
            "codes.json",
            "--heterodyne",
            "2",
            "--decoder",
            "tval3",
            "--decoder",
            "lifetime:lt",
            "--maxit",
            "10",
            "--noise",
            "-o",
            "rep.json",
        ],
    );
    assert!(out.contains("lifetime:lt") && out.contains("within 0.2 ns"), "{out}");
    let rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("rep.json")).unwrap()).unwrap();
    for r in rep.as_array().unwrap() {
        let (share, cover) = (r["lifetime_within_02ns"].as_f64().unwrap(), r["lifetime_coverage"].as_f64().unwrap());
        assert!((0.0..=1.0).contains(&share) && share <= cover && cover <= 1.0, "{r}");
    }
    // bad input: a LiDAR dataset has no lifetimes; a run of the other kind; a lifetime decoder on LiDAR
    fails(
        d,
        &["train", "lifetime", "--dataset", "ds", "--codes", "codes.json", "--harmonics", "3", "--epochs", "1", "-o", "l2"],
        &["ds", "no lifetime field"],
    );
    fails(d, &["train", "unet", "--resume", "-o", "lt"], &["lifetime run", "tcsense train lifetime"]);
    fails(
        d,
        &["eval", "--dataset", "f", "--codes", "codes.json", "--heterodyne", "2", "--decoder", "unet:lt", "-o", "r2.json"],
        &["a lifetime run"],
    );
    fails(
        d,
        &["eval", "--dataset", "f", "--codes", "codes.json", "--heterodyne", "2", "--decoder", "unet-raw:lt", "-o", "r3.json"],
        &["a lifetime run, not unet", "lifetime:lt"],
    );
    assert!(!d.join("r3.json").exists());
    fails(d, &["train", "lifetime", "--dataset", "f", "--codes", "codes.json", "--harmonics", "99", "-o", "l3"], &["harmonics"]);
    // reconstruct lifetime: [4, H, W] with confidence and intensity beside it; another kind's subcommand refuses the run
    let x = tcsense_sensor::npy::read_npy(&d.join("f/test/x_000.npy")).unwrap();
    tcsense_sensor::npy::write_npy(&d.join("x.npy"), &x.index_axis(ndarray::Axis(0), 0)).unwrap();
    ok(d, &["simulate", "--codes", "codes.json", "--heterodyne", "2", "--cube", "x.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "lifetime", "--run", "lt", "--measurements", "y.npy", "-o", "tau.npy"]);
    assert_eq!(tcsense_sensor::npy::read_npy(&d.join("tau.npy")).unwrap().shape(), &[4, 8, 8]);
    assert_eq!(tcsense_sensor::npy::read_npy(&d.join("tau.intensity.npy")).unwrap().shape(), &[1, 8, 8]);
    fails(
        d,
        &["reconstruct", "unet", "--run", "lt", "--measurements", "y.npy", "-o", "d.npy"],
        &["lt", "decoder", "\"lifetime\"", "not unet", "name it lifetime:lt"],
    );
    fails(
        d,
        &["reconstruct", "unet", "--run", "lt", "--no-range-fit", "--measurements", "y.npy", "-o", "d.npy"],
        &["lt", "decoder", "\"lifetime\"", "not unet", "name it lifetime:lt"],
    );
    assert!(!d.join("d.npy").exists());
}

#[test]
fn broken_run_directories_exit_2_naming_the_file() {
    let d = tempdir();
    let d = d.path();
    let fx = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1");
    let y = fx.join("y.npy").display().to_string();
    let copy = |name: &str| {
        let dir = d.join(name);
        std::fs::create_dir_all(&dir).unwrap();
        for f in ["config.json", "codes.json", "model.bpk"] {
            std::fs::copy(fx.join(f), dir.join(f)).unwrap();
        }
        dir
    };
    // truncated weights
    let run = copy("truncated");
    let bytes = std::fs::read(run.join("model.bpk")).unwrap();
    std::fs::write(run.join("model.bpk"), &bytes[..bytes.len() / 2]).unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "truncated", "--measurements", &y, "-o", "x.npy"], &["model.bpk"]);
    // missing weights
    let run = copy("missing");
    std::fs::remove_file(run.join("model.bpk")).unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "missing", "--measurements", &y, "-o", "x.npy"], &["model.bpk", "no trained weights"]);
    // a config of another shape, and one that is not JSON
    let run = copy("foreign");
    std::fs::write(run.join("config.json"), "{\"decoder\": \"admm-net\", \"model\": {\"taps\": 2, \"bins\": 8, \"stages\": 2, \"channels\": 4, \"rho_init\": 0.1, \"eta_init\": 1.0}, \"sampling\": {\"mode\": \"oversample\", \"k\": 1}, \"irf\": {\"kind\": \"ideal\"}}").unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "foreign", "--measurements", &y, "-o", "x.npy"], &["config.json", "M = 2"]);
    // absurd numbers are refused before the network is built (not a terabyte allocation)
    std::fs::write(run.join("config.json"), "{\"decoder\": \"admm-net\", \"model\": {\"taps\": 4, \"bins\": 8, \"stages\": 2, \"channels\": 1000000000000, \"rho_init\": 0.1, \"eta_init\": 1.0}, \"sampling\": {\"mode\": \"oversample\", \"k\": 1}, \"irf\": {\"kind\": \"ideal\"}}").unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "foreign", "--measurements", &y, "-o", "x.npy"], &["config.json", "model.channels"]);
    std::fs::write(run.join("config.json"), "not json").unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "foreign", "--measurements", &y, "-o", "x.npy"], &["config.json", "malformed JSON"]);
    std::fs::write(run.join("config.json"), "{\"decoder\": \"magic\", \"model\": {}}").unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "foreign", "--measurements", &y, "-o", "x.npy"], &["config.json", "not a run config"]);
    assert!(!d.join("x.npy").exists(), "no output from a broken run");
}

#[test]
fn same_seed_same_weights_bytes() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    for run in ["a", "b", "c"] {
        let seed = if run == "c" { "4" } else { "3" };
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
                seed,
                "-o",
                run,
            ],
        );
    }
    let read = |p: &str| std::fs::read(d.join(p)).unwrap();
    // every file of the run, the optimiser's included, but the one clock reading
    let files = files_under(&d.join("a"));
    for f in [
        "model.bpk",
        "metrics.csv",
        "config.json",
        "codes.json",
        "checkpoint/model.bpk",
        "checkpoint/optim.bpk",
        "checkpoint/state.json",
        "timing.csv",
    ] {
        assert!(files.iter().any(|p| p == f), "the run has {f}: {files:?}");
    }
    for f in files.iter().filter(|f| *f != "timing.csv") {
        assert!(read(&format!("a/{f}")) == read(&format!("b/{f}")), "same seed, same bytes in {f}");
    }
    assert_eq!(files, files_under(&d.join("b")));
    assert_ne!(read("a/model.bpk"), read("c/model.bpk"), "another seed, other weights");
    assert_ne!(read("a/checkpoint/optim.bpk"), read("c/checkpoint/optim.bpk"), "another seed, other moments");
}

#[test]
fn a_second_training_into_the_same_run_is_refused() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    // the first one runs long enough for the second to meet it
    let mut first = bin()
        .current_dir(d)
        .args([
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
            "100000",
            "-o",
            "run",
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let lock = d.join("run/.lock");
    for _ in 0..200 {
        if lock.exists() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    assert!(lock.exists(), "the first training holds run/.lock");
    fails(d, &["train", "admm-net", "--epochs", "3", "--resume", "-o", "run"], &["run", "another training", &first.id().to_string()]);
    // killed (SIGKILL) after its first checkpoint: its lock is stale and the next training takes it over
    for _ in 0..600 {
        if d.join("run/checkpoint/state.json").exists() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    first.kill().unwrap();
    first.wait().unwrap();
    assert!(lock.exists(), "a killed process leaves its lock behind");
    ok(d, &["train", "admm-net", "--epochs", "1", "--resume", "-o", "run"]);
    assert!(!lock.exists(), "the lock is released at the end");
}

#[test]
fn a_delay_prior_run_records_its_prior_and_keeps_it() {
    let d = tempdir();
    let d = d.path();
    // 16 bins: more than the prior's largest dilation; 8 are refused
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "16", "--seed", "2", "-o", "ds"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "16", "--seed", "1", "-o", "codes.json"]);
    std::fs::create_dir(d.join("short")).unwrap();
    tiny_lidar_and_codes(&d.join("short"));
    fails(
        &d.join("short"),
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--prior", "delay", "-o", "run"],
        &["model.bins", "more than 9 bins"],
    );
    assert!(!d.join("short/run").exists());
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--prior",
            "delay",
            "--stages",
            "1",
            "--epochs",
            "1",
            "--seed",
            "3",
            "-o",
            "run",
        ],
    );
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run/config.json")).unwrap()).unwrap();
    // a few channels per bin by default
    assert_eq!((cfg["model"]["prior"].as_str(), cfg["model"]["channels"].as_u64()), (Some("Delay"), Some(4)), "{cfg}");
    fails(d, &["train", "admm-net", "--prior", "bins", "--epochs", "2", "--resume", "-o", "run"], &["--prior", "Delay"]);
    assert_eq!(std::fs::read_to_string(d.join("run/metrics.csv")).unwrap().lines().count(), 2, "the refused resume trained nothing");
    ok(d, &["train", "admm-net", "--epochs", "2", "--resume", "-o", "run"]);
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "xhat.npy"]);
    let xh = read_npy(&d.join("xhat.npy")).unwrap();
    assert!(xh.shape() == [1, 16, 8, 8] && xh.iter().all(|v| v.is_finite()));
    fails(d, &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--prior", "time", "-o", "run2"], &["--prior", "time"]);
    // a saved delay-prior config keeps its channels when --prior delay is given again
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--prior",
            "delay",
            "--channels",
            "2",
            "--stages",
            "1",
            "--epochs",
            "1",
            "-o",
            "run3",
        ],
    );
    ok(d, &["train", "admm-net", "--config", "run3/config.json", "--codes", "codes.json", "--prior", "delay", "-o", "run4"]);
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run4/config.json")).unwrap()).unwrap();
    assert_eq!((cfg["model"]["prior"].as_str(), cfg["model"]["channels"].as_u64()), (Some("Delay"), Some(2)), "{cfg}");

    // fine-tuning takes the architecture from the run it starts from: no flag restates it
    ok(d, &["train", "admm-net", "--init-from", "run3", "--dataset", "ds", "--codes", "codes.json", "--epochs", "1", "-o", "tuned"]);
    let cfg: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("tuned/config.json")).unwrap()).unwrap();
    assert_eq!(
        (cfg["model"]["prior"].as_str(), cfg["model"]["channels"].as_u64(), cfg["model"]["stages"].as_u64()),
        (Some("Delay"), Some(2), Some(1)),
        "{cfg}"
    );
    assert_eq!(cfg["init_from"].as_str(), Some("run3"));
    // a flag that agrees is accepted; one that contradicts it is refused naming the run's value
    ok(
        d,
        &[
            "train",
            "admm-net",
            "--init-from",
            "run3",
            "--stages",
            "1",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--epochs",
            "1",
            "-o",
            "tuned2",
        ],
    );
    fails(
        d,
        &["train", "admm-net", "--init-from", "run3", "--stages", "3", "--dataset", "ds", "--codes", "codes.json", "-o", "tuned3"],
        &["run3/config.json", "--stages 3", "stages 1", "model.stages"],
    );
    fails(
        d,
        &["train", "admm-net", "--init-from", "run3", "--preset", "lidar", "--dataset", "ds", "--codes", "codes.json", "-o", "tuned3"],
        &["run3/config.json", "stages 1"],
    );
    fails(
        d,
        &["train", "unet", "--init-from", "run3", "--dataset", "ds", "--codes", "codes.json", "-o", "tuned3"],
        &["run3/config.json", "admm-net run", "tcsense train admm-net"],
    );
    fails(
        d,
        &["train", "admm-net", "--init-from", "nowhere", "--dataset", "ds", "--codes", "codes.json", "-o", "tuned3"],
        &["nowhere", "config.json missing"],
    );
    // the same on --resume: the run's architecture, flags checked against it
    fails(
        d,
        &["train", "admm-net", "--channels", "8", "--epochs", "2", "--resume", "-o", "tuned"],
        &["tuned/config.json", "--channels 8", "channels 2"],
    );
    assert!(!d.join("tuned3").exists(), "a refused fine-tuning writes nothing");
}

/// The files under `dir`, as sorted paths relative to it.
fn files_under(dir: &std::path::Path) -> Vec<String> {
    fn walk(root: &std::path::Path, dir: &std::path::Path, out: &mut Vec<String>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_string_lossy().into_owned());
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.sort();
    out
}

/// A resume checks what the run trains on: a dataset regenerated at the same path since the run
/// started is refused, naming its manifest; the unchanged one resumes.
#[test]
fn resume_refuses_a_changed_dataset() {
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
            "1",
            "-o",
            "run",
        ],
    );
    let state: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("run/checkpoint/state.json")).unwrap()).unwrap();
    assert_eq!(state["dataset"].as_str().map(str::len), Some(16), "{state}");
    std::fs::rename(d.join("ds"), d.join("ds-first")).unwrap();
    ok(d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "7", "-o", "ds"]);
    fails(d, &["train", "admm-net", "--epochs", "2", "--resume", "-o", "run"], &["ds/manifest.json", "dataset changed", "digest"]);
    assert_eq!(std::fs::read_to_string(d.join("run/metrics.csv")).unwrap().lines().count(), 2, "the refused resume trained nothing");
    std::fs::remove_dir_all(d.join("ds")).unwrap();
    std::fs::rename(d.join("ds-first"), d.join("ds")).unwrap();
    let out = ok(d, &["train", "admm-net", "--epochs", "2", "--resume", "-o", "run"]);
    assert!(out.contains("epoch    2"), "{out}");
}
