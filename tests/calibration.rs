//! The real-sensor loop end to end: a sensor with known non-idealities → `simulate --sweep` →
//! `calibrate` → decoders with `--calibration` (reconstruct, train, export with the correction
//! in the ONNX graph), and sweeps that calibration must refuse.

mod common;

use common::*;
use ndarray::{Array3, Array4, Axis, Ix3};
use std::path::Path;
use tcsense_models::runs;
use tcsense_sensor::calibration::Calibration;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::npy::{read_npy, write_npy};

/// The sensor of these tests: 5 % tap gains, 2 % PRNU, dark offset with a pattern.
const SENSOR: &[&str] = &["--tap-gain", "0.05", "--prnu", "0.02", "--dark", "0.01", "--dark-fpn", "0.002", "--sensor-seed", "7"];

fn with<'a>(base: &[&'a str], more: &[&'a str]) -> Vec<&'a str> {
    base.iter().chain(more).copied().collect()
}

/// A scene of one return per pixel (T = 8 bins, 8×8), bins and brightness varying.
fn scene(dir: &Path) {
    let x = Array3::from_shape_fn((8, 8, 8), |(j, r, c)| {
        let peak = (r * 3 + c) % 8;
        let d = (j as i64 - peak as i64).rem_euclid(8).min((peak as i64 - j as i64).rem_euclid(8)) as f32;
        (0.3 + 0.1 * ((r + c) % 5) as f32) * (-d * d).exp()
    });
    write_npy(&dir.join("x.npy"), &x.view()).unwrap();
}

fn cube(dir: &Path, name: &str) -> Array3<f32> {
    let c = read_npy(&dir.join(name)).unwrap().into_dimensionality::<Ix3>().unwrap();
    let n = c.mapv(|v| v * v).sum().sqrt();
    c.mapv(|v| v / n)
}

fn dist(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
    (a - b).mapv(|v| v * v).sum().sqrt()
}

#[test]
fn a_sweep_calibrates_and_decoders_use_it() {
    let d = tempdir();
    let dir = d.path();
    tiny_lidar_and_codes(dir);
    scene(dir);
    let sweep = with(
        &[
            "simulate",
            "--codes",
            "codes.json",
            "--irf",
            "physical",
            "--sweep",
            "sweep",
            "--size",
            "8x8",
            "--noise",
            "--average",
            "64",
            "--seed",
            "3",
        ],
        SENSOR,
    );
    ok(dir, &sweep);
    let out = ok(dir, &["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "-o", "cal"]);
    assert!(out.contains("tap gains"), "{out}");
    for f in [
        "calibration.json",
        "A.npy",
        "gain.npy",
        "dark.npy",
        "residual.npy",
        "report.html",
        "gain.png",
        "dark.png",
        "residual.png",
        "fit.png",
        "responses_0.png",
    ] {
        assert!(dir.join("cal").join(f).exists(), "cal/{f} missing");
    }
    // the tap gains come back within 1 % (relative to their mean)
    let meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("cal/calibration.json")).unwrap()).unwrap();
    let truth = NonIdeal { tap_gain: 0.05, seed: 7, ..NonIdeal::default() }.tap_gains(4);
    let mean = truth.iter().sum::<f64>() / 4.0;
    for (m, want) in truth.iter().enumerate() {
        let got = meta["tap_gains"][m].as_f64().unwrap();
        assert!((got - want / mean).abs() < 0.01, "tap {m}: gain {got}, true {}", want / mean);
    }
    let html = std::fs::read_to_string(dir.join("cal/report.html")).unwrap();
    assert!(html.contains("data-ptr=\"/tap_gains/0\"") && html.contains("fit.png"));

    // the scene through the real sensor (raw electrons) and through the ideal one
    ok(
        dir,
        &with(
            &["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "x.npy", "--units", "electrons", "-o", "y_real.npy"],
            SENSOR,
        ),
    );
    let tval3 = |y: &str, out: &str, cal: &str| {
        let mut a = vec!["reconstruct", "tval3", "--codes", "codes.json", "--irf", "physical", "--measurements", y, "-o", out];
        if !cal.is_empty() {
            a.extend(["--calibration", cal]);
        }
        ok(dir, &a);
    };
    tval3("y_real.npy", "x_nominal.npy", "");
    tval3("y_real.npy", "x_cal.npy", "cal");
    // perfect knowledge: the calibration of a noise-free sweep is the true sensor
    ok(
        dir,
        &with(&["simulate", "--codes", "codes.json", "--irf", "physical", "--sweep", "clean", "--size", "8x8", "--average", "1"], SENSOR),
    );
    ok(dir, &["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "clean", "-o", "oracle", "--no-report"]);
    tval3("y_real.npy", "x_oracle.npy", "oracle");
    let (oracle, nominal, cal) = (cube(dir, "x_oracle.npy"), cube(dir, "x_nominal.npy"), cube(dir, "x_cal.npy"));
    let (e_nom, e_cal) = (dist(&nominal, &oracle), dist(&cal, &oracle));
    assert!(e_cal < 0.02 && e_cal * 5.0 < e_nom, "calibrated decoding is {e_cal} from perfect knowledge's, the nominal model's {e_nom}");
    // without tap gains the true sensor's matrix is the nominal one: corrected raw frames are
    // the ideal sensor's frames (up to the exposure scale) within the sweep's noise
    ok(dir, &["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "x.npy", "-o", "y_ideal.npy"]);
    let prnu_dark: &[&str] = &["--prnu", "0.02", "--dark", "0.01", "--dark-fpn", "0.002", "--sensor-seed", "7"];
    ok(
        dir,
        &with(
            &[
                "simulate",
                "--codes",
                "codes.json",
                "--irf",
                "physical",
                "--sweep",
                "sweep2",
                "--size",
                "8x8",
                "--noise",
                "--average",
                "64",
                "--seed",
                "4",
            ],
            prnu_dark,
        ),
    );
    ok(dir, &["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep2", "-o", "cal2", "--no-report"]);
    ok(
        dir,
        &with(
            &["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "x.npy", "--units", "electrons", "-o", "y_real2.npy"],
            prnu_dark,
        ),
    );
    let frame =
        |name: &str| -> Array4<f32> { read_npy(&dir.join(name)).unwrap().into_dimensionality::<Ix3>().unwrap().insert_axis(Axis(0)) };
    let (ideal, raw) = (frame("y_ideal.npy"), frame("y_real2.npy"));
    let codes = tcsense_sensor::Codes::load(&dir.join("codes.json")).unwrap();
    let spec = tcsense_sensor::SensorParams {
        irf: tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
        ..tcsense_sensor::SensorParams::from_codes(&codes)
    }
    .validate()
    .unwrap();
    let nominal = tcsense_sensor::MeasurementMatrix::synthesize(&codes, &spec).unwrap();
    let cal2 = Calibration::load(&dir.join("cal2"), &nominal, &codes).unwrap();
    let corrected = cal2.correct(&raw.view()).unwrap();
    let off = |y: &Array4<f32>| {
        let scale = y.sum() / ideal.sum();
        (y.mapv(|v| v / scale) - &ideal).iter().fold(0f32, |m, &v| m.max(v.abs())) / ideal.iter().fold(0f32, |m, &v| m.max(v))
    };
    let (e_cal, e_raw) = (off(&corrected), off(&raw));
    assert!(e_cal < 0.015 && e_cal * 3.0 < e_raw, "corrected frames are {e_cal} of the peak from the ideal sensor's, raw ones {e_raw}");

    // a learned decoder: reconstruct with --calibration, and its ONNX export with the
    // correction in the graph gives the same cube from the raw frame
    ok(
        dir,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--irf",
            "physical",
            "--epochs",
            "1",
            "--stages",
            "2",
            "--channels",
            "4",
            "--no-augment",
            "-o",
            "run",
        ],
    );
    ok(dir, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y_real.npy", "--calibration", "cal", "-o", "x_net.npy"]);
    ok(dir, &["export", "onnx", "--run", "run", "--calibration", "cal", "-o", "cal.onnx"]);
    let y: Array4<f32> = read_npy(&dir.join("y_real.npy")).unwrap().into_dimensionality::<Ix3>().unwrap().insert_axis(Axis(0));
    let mut model = tcsense_infer::runtime::OnnxModel::open(&dir.join("cal.onnx"), 1)
        .unwrap_or_else(|e| panic!("{e} (run scripts/setup.sh to install ONNX Runtime into .venv)"));
    assert_eq!(model.meta.calibration.as_ref().map(|c| c.size), Some([8, 8]));
    let ort = model.run(y.view()).unwrap().remove(0).index_axis_move(Axis(0), 0);
    let burn = read_npy(&dir.join("x_net.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    let scale = burn.iter().fold(0f32, |m, &v| m.max(v.abs()));
    let diff = (&ort - &burn).iter().fold(0f32, |m, &v| m.max(v.abs()));
    assert!(diff <= 1e-4 * scale, "ORT with the built-in correction differs from burn by {diff} (scale {scale})");
    // the model takes only frames of the calibration's size
    assert!(model.run(Array4::<f32>::zeros((1, 4, 4, 4)).view()).is_err());

    // fine-tuning to the calibrated sensor: the run keeps its matrix
    ok(
        dir,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--calibration",
            "cal",
            "--init-from",
            "run",
            "--epochs",
            "1",
            "--stages",
            "2",
            "--channels",
            "4",
            "--no-augment",
            "-o",
            "tuned",
        ],
    );
    let tuned = runs::load(&dir.join("tuned"), &tcsense_models::Device::flex()).unwrap();
    let cal_a = read_npy(&dir.join("cal/A.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    assert_eq!(tuned.sensor.matrix().a(), cal_a.view());
    let c = Calibration::load(&dir.join("cal"), tuned.sensor.nominal(), tuned.sensor.codes()).unwrap();
    assert_eq!(c.matrix.a(), cal_a.view());
}

#[test]
fn bad_sweeps_and_calibrations_exit_2() {
    let d = tempdir();
    let dir = d.path();
    tiny_lidar_and_codes(dir);
    ok(dir, &with(&["simulate", "--codes", "codes.json", "--sweep", "sweep", "--size", "8x8", "--average", "2", "--noise"], SENSOR));
    let manifest = std::fs::read_to_string(dir.join("sweep/sweep.json")).unwrap();
    let m: serde_json::Value = serde_json::from_str(&manifest).unwrap();
    let cal = |sweep: &str| {
        vec!["calibrate", "--codes", "codes.json", "--sweep", sweep, "-o", "cal"].into_iter().map(String::from).collect::<Vec<_>>()
    };
    let variant = |name: &str, edit: &dyn Fn(&mut serde_json::Value)| {
        let to = dir.join(name);
        std::fs::create_dir_all(&to).unwrap();
        for f in std::fs::read_dir(dir.join("sweep")).unwrap() {
            let f = f.unwrap();
            std::fs::copy(f.path(), to.join(f.file_name())).unwrap();
        }
        let mut v = m.clone();
        edit(&mut v);
        std::fs::write(to.join("sweep.json"), serde_json::to_string(&v).unwrap()).unwrap();
    };
    let refuse = |sweep: &str, needles: &[&str]| {
        let args = cal(sweep);
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        fails(dir, &args, needles);
        assert!(!dir.join("cal").exists(), "a refused calibration left output behind");
    };
    // delays that leave most of the cycle out
    variant("half", &|v| {
        let n = v["delays_s"].as_array().unwrap().len();
        v["delays_s"] = serde_json::json!((0..n).map(|i| i as f64 * 1e-11).collect::<Vec<_>>());
    });
    refuse("half", &["delays_s", "does not cover the cycle"]);
    // a delay outside the cycle
    variant("late", &|v| v["delays_s"][0] = serde_json::json!(1.0));
    refuse("late", &["delays_s[0]", "outside the code cycle"]);
    // saturated frames
    variant("saturated", &|v| v["full_scale"] = serde_json::json!(100.0));
    refuse("saturated", &["saturated", "full_scale"]);
    // one delay too few
    variant("short", &|v| {
        v["delays_s"].as_array_mut().unwrap().pop();
    });
    refuse("short", &["delays_s", "one delay per frame"]);
    // dark frames of the wrong shape
    variant("darkshape", &|_| {});
    write_npy(&dir.join("darkshape/dark.npy"), &Array4::<f32>::zeros((2, 3, 8, 8)).view()).unwrap();
    refuse("darkshape", &["dark", "[3, 8, 8]"]);
    // another sensor's codes
    ok(dir, &["codes", "generate", "--tap-constraint", "--length", "8", "--seed", "9", "-o", "other.json"]);
    fails(dir, &["calibrate", "--codes", "other.json", "--sweep", "sweep", "-o", "cal"], &["codes_digest"]);
    assert!(!dir.join("cal").exists());
    // a good calibration, used on frames of another size
    ok(dir, &["calibrate", "--codes", "codes.json", "--sweep", "sweep", "-o", "cal", "--no-report"]);
    write_npy(&dir.join("x4.npy"), &Array3::<f32>::from_shape_fn((8, 4, 4), |(j, r, c)| ((j + r + c) % 3) as f32).view()).unwrap();
    ok(dir, &["simulate", "--codes", "codes.json", "--cube", "x4.npy", "--units", "electrons", "--noise", "-o", "y4.npy"]);
    fails(
        dir,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y4.npy", "--calibration", "cal", "-o", "out.npy"],
        &["y4.npy", "8, 8"],
    );
    assert!(!dir.join("out.npy").exists());
    // measurements in other units than the calibration's
    ok(dir, &["simulate", "--codes", "codes.json", "--cube", "x4.npy", "-o", "y_input.npy"]);
    fails(
        dir,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y_input.npy", "--calibration", "cal", "-o", "out.npy"],
        &["units", "electrons"],
    );
    // a calibration directory that is not one
    fails(
        dir,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y4.npy", "--calibration", "sweep", "-o", "out.npy"],
        &["calibration.json"],
    );
    // non-idealities out of range
    fails(dir, &["simulate", "--codes", "codes.json", "--sweep", "s2", "--prnu", "0.9"], &["prnu"]);
    // the training augmentation's sensor residue: three numbers in range
    fails(
        dir,
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--epochs", "1", "--sensor-residue", "0.01,0.005", "-o", "r1"],
        &["--sensor-residue", "three numbers"],
    );
    fails(
        dir,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--epochs",
            "1",
            "--sensor-residue",
            "0.01,0.5,0.002",
            "-o",
            "r2",
        ],
        &["sensor_residue", "PRNU"],
    );
}

#[test]
fn gate_skew_and_modulation_contrast_calibrate_back_and_bad_values_exit_2() {
    let d = tempdir();
    let dir = d.path();
    tiny_lidar_and_codes(dir);
    let real: &[&str] = &["--gate-skew-ns", "0.3", "--modulation-contrast", "0.925", "--sensor-seed", "5"];
    ok(
        dir,
        &with(&["simulate", "--codes", "codes.json", "--irf", "physical", "--sweep", "clean", "--size", "8x8", "--average", "1"], real),
    );
    ok(dir, &["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "clean", "-o", "cal", "--no-report"]);
    let codes = tcsense_sensor::Codes::load(&dir.join("codes.json")).unwrap();
    let nominal = tcsense_sensor::Sensor::ideal(
        codes.clone(),
        tcsense_sensor::Sampling::Oversample(1),
        tcsense_sensor::Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
    )
    .unwrap();
    let truth =
        NonIdeal { gate_skew_s: 0.3e-9, modulation_contrast: 0.925, seed: 5, ..NonIdeal::default() }.matrix(nominal.matrix()).unwrap();
    let cal = Calibration::load(&dir.join("cal"), nominal.matrix(), &codes).unwrap();
    // the calibrated A is the skewed, leaking sensor's (up to the brightness), not the nominal one
    let off = |a: ndarray::ArrayView3<'_, f32>| {
        let scale = truth.a().sum() / a.sum();
        let peak = truth.a().iter().fold(0f32, |p, &v| p.max(v));
        (&a.mapv(|v| v * scale) - &truth.a()).mapv(f32::abs).iter().fold(0f32, |p, &v| p.max(v)) / peak
    };
    let (e_cal, e_nom) = (off(cal.matrix.a()), off(nominal.matrix().a()));
    assert!(e_cal < 0.01 && e_nom > 0.05, "calibrated A off by {e_cal} of the peak, the nominal A by {e_nom}");
    // the sidecar of simulated frames records the non-idealities
    scene(dir);
    ok(
        dir,
        &with(&["simulate", "--codes", "codes.json", "--irf", "physical", "--cube", "x.npy", "--nonlinearity", "0.2", "-o", "y.npy"], real),
    );
    let meta = std::fs::read_to_string(dir.join("y.meta.json")).unwrap();
    assert!(meta.contains("\"gate_skew_s\"") && meta.contains("0.925") && meta.contains("\"nonlinearity\": 0.2"), "{meta}");
    // out of range, or two statements of the same leakage
    let sim = |more: &[&'static str]| with(&["simulate", "--codes", "codes.json", "--cube", "x.npy", "-o", "bad.npy"], more);
    fails(dir, &sim(&["--modulation-contrast", "1.5"]), &["--modulation-contrast 1.5", "(0, 1]"]);
    fails(dir, &sim(&["--nonlinearity", "0.7"]), &["nonlinearity", "0.5"]);
    fails(dir, &sim(&["--gate-skew-ns=-1"]), &["gate_skew", "non-negative"]);
    fails(dir, &sim(&["--crosstalk", "0.1", "--modulation-contrast", "0.9"]), &["--modulation-contrast", "--crosstalk"]);
    assert!(!dir.join("bad.npy").exists());
}
