//! Measurements that say what they are: `simulate` writes `y.meta.json` next to `y.npy`, and
//! every decoder refuses tap images of another sensor (codes, sampling, IRF) with exit 2.

mod common;
use common::*;

#[test]
fn decoders_refuse_measurements_of_another_sensor() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "flim", "--count", "3", "--size", "8x8", "--length", "8", "--heterodyne", "2", "--seed", "3", "-o", "f"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "8", "--seed", "1", "-o", "codes.json"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "8", "--seed", "2", "-o", "other.json"]);
    let out = ok(
        d,
        &["simulate", "--codes", "codes.json", "--heterodyne", "2", "--cube", "f/test/x_000.npy", "--noise", "--seed", "5", "-o", "y.npy"],
    );
    assert!(out.contains("y.meta.json"), "{out}");
    let meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("y.meta.json")).unwrap()).unwrap();
    assert_eq!(
        (meta["format"].as_str(), meta["taps"].as_u64(), meta["bins"].as_u64(), meta["seed"].as_u64()),
        (Some("tcsense-measurements"), Some(4), Some(16), Some(5))
    );
    assert_eq!(meta["sampling"]["mode"].as_str(), Some("heterodyne"));
    assert_eq!(meta["noise"]["full_well_e"].as_f64(), Some(20000.0));

    // the sensor it was taken with decodes it
    ok(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--heterodyne", "2", "--measurements", "y.npy", "--maxit", "5", "-o", "x.npy"],
    );
    // the case: heterodyne tap images decoded without --heterodyne, and with other codes
    fails(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--maxit", "5", "-o", "bad1.npy"],
        &["y.meta.json", "bins", "heterodyne"],
    );
    fails(
        d,
        &[
            "reconstruct",
            "tval3",
            "--codes",
            "other.json",
            "--heterodyne",
            "2",
            "--measurements",
            "y.npy",
            "--maxit",
            "5",
            "-o",
            "bad2.npy",
        ],
        &["y.meta.json", "codes_digest"],
    );
    // same codes and sampling, another IRF
    fails(
        d,
        &[
            "reconstruct",
            "tval3",
            "--codes",
            "codes.json",
            "--heterodyne",
            "2",
            "--irf",
            "physical",
            "--measurements",
            "y.npy",
            "--maxit",
            "5",
            "-o",
            "bad3.npy",
        ],
        &["y.meta.json", "matrix_digest"],
    );
    assert!(!d.join("bad1.npy").exists() && !d.join("bad2.npy").exists() && !d.join("bad3.npy").exists());

    // a learned decoder trained on other codes, as a run and exported
    ok(
        d,
        &["train", "admm-net", "--dataset", "f", "--codes", "other.json", "--stages", "1", "--channels", "2", "--epochs", "1", "-o", "run"],
    );
    fails(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "bad4.npy"], &["y.meta.json", "codes_digest"]);
    ok(d, &["export", "onnx", "--run", "run", "-o", "m.onnx"]);
    fails(d, &["infer", "--model", "m.onnx", "--measurements", "y.npy", "-o", "bad5"], &["y.meta.json", "codes_digest"]);
    assert!(!d.join("bad5").exists());

    // without the sidecar nothing is checked (a sensor's raw dump); a broken one is refused
    // a clip level that no tap image can have is refused, naming the field (not every pixel
    // masked, or none)
    let text = std::fs::read_to_string(d.join("y.meta.json")).unwrap();
    let mut meta: serde_json::Value = serde_json::from_str(&text).unwrap();
    meta["clip_level"] = serde_json::json!(-5.0);
    std::fs::write(d.join("y.meta.json"), meta.to_string()).unwrap();
    fails(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "bad7.npy"], &["y.meta.json", "clip_level"]);
    assert!(!d.join("bad7.npy").exists());
    std::fs::write(d.join("y.meta.json"), text).unwrap();
    std::fs::rename(d.join("y.meta.json"), d.join("kept.json")).unwrap();
    ok(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "x2.npy"]);
    std::fs::write(d.join("y.meta.json"), "{\"format\": \"tcsense-measurements\"}").unwrap();
    fails(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--heterodyne", "2", "--measurements", "y.npy", "-o", "bad6.npy"],
        &["y.meta.json", "not a measurement sidecar"],
    );
}
