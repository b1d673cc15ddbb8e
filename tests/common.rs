//! Helpers shared by the end-to-end tests: run the binary, check exit codes and messages.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ndarray::Array4;
use tcsense_models::net::{to_array, to_tensor, Network};
use tcsense_models::runs::{LoadedRun, TrainedNet};
use tcsense_models::{Device, SensorTensors};

pub fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_tcsense"))
}

pub fn run(dir: &Path, args: &[&str]) -> Output {
    bin().current_dir(dir).args(args).output().expect("run tcsense")
}

pub fn ok(dir: &Path, args: &[&str]) -> String {
    let o = run(dir, args);
    assert!(o.status.success(), "tcsense {args:?} failed: {}", String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// Assert exit status 2, a message containing every `needle`, and no panic.
pub fn fails(dir: &Path, args: &[&str], needles: &[&str]) {
    let o = run(dir, args);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "tcsense {args:?}: expected exit 2, stderr: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    for n in needles {
        assert!(err.contains(n), "tcsense {args:?}: message {err:?} lacks {n:?}");
    }
}

pub fn tempdir() -> tempfile::TempDir {
    tempfile::tempdir().expect("tempdir")
}

pub fn p(dir: &Path, name: &str) -> PathBuf {
    dir.join(name)
}

/// A tiny LiDAR dataset `ds` (8 items, 8×8, L = 8) and tap-constrained codes `codes.json`
/// (L = 8) in `dir`: what the training and deployment tests start from.
pub fn tiny_lidar_and_codes(dir: &Path) {
    ok(dir, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "2", "-o", "ds"]);
    ok(dir, &["codes", "generate", "--tap-constraint", "--length", "8", "--seed", "1", "-o", "codes.json"]);
}

/// burn's prediction of `run` on `y`, as the exported graph gives it: the cube; depth and
/// confidence; or lifetimes (s), confidence and intensity.
pub fn burn_outputs(run: &LoadedRun, y: &Array4<f32>) -> Vec<Array4<f32>> {
    let device = Device::flex();
    let (_, _, h, w) = y.dim();
    let st = SensorTensors::new(run.sensor.matrix(), h, w, &device).unwrap();
    let yt = to_tensor(&y.view(), &device);
    match &run.net {
        TrainedNet::AdmmNet(net) => vec![to_array(net.predict(yt, &st)).unwrap()],
        TrainedNet::Unet(net) => match net.decode_frames(&y.view(), &st) {
            // (the network on the range fit's evidence: its product, refined in the tap domain)
            Some(out) => {
                let (depth, conf) = tcsense_models::net::split_depth(&out);
                vec![depth, conf]
            }
            None => {
                let (depth, conf) = net.forward(yt, &st);
                vec![to_array(depth).unwrap(), to_array(conf).unwrap()]
            }
        },
        TrainedNet::Lifetime(net) => {
            // burn gives ns and the confidence logit; the graph seconds and the probability
            // (the network on the fit's evidence: its product, the modes refined in the tap domain)
            let out = net.decode_frames(&y.view(), &st).unwrap_or_else(|| to_array(net.predict(yt.clone(), &st)).unwrap());
            let mut l = out.slice(ndarray::s![.., ..4, .., ..]).to_owned();
            l.slice_mut(ndarray::s![.., ..3, .., ..]).mapv_inplace(|t| t * 1e-9);
            let conf = out.slice(ndarray::s![.., 4..5, .., ..]).mapv(|v| 1.0 / (1.0 + (-v).exp()));
            vec![l, conf, to_array(tcsense_models::lifetime::intensity(yt)).unwrap()]
        }
    }
}
