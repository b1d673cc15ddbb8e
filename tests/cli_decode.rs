//! End-to-end tests of reconstruction, products, evaluation, code selection and sweeps.

mod common;
use common::*;
use ndarray::{Array3, Ix2, Ix3};
use tcsense_sensor::npy::{read_npy, write_npy};

fn lidar(d: &std::path::Path) {
    ok(d, &["dataset", "lidar", "--count", "6", "--size", "8x8", "--sheet-probability", "0", "--seed", "4", "-o", "ds"]);
    ok(d, &["codes", "generate", "--tap-constraint", "--seed", "1", "-o", "codes.json"]);
}

#[test]
fn reconstruct_depth_ply_png_and_waveforms() {
    let d = tempdir();
    let d = d.path();
    lidar(d);
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--maxit", "50", "-o", "xhat.npy"]);
    let xh = read_npy(&d.join("xhat.npy")).unwrap();
    assert_eq!(xh.shape(), &[1, 32, 8, 8]);
    // products take the batch directly
    ok(d, &["depth", "xhat.npy", "--peaks", "2", "-o", "bdepth.npy", "--ply", "b.ply"]);
    assert_eq!(read_npy(&d.join("bdepth.npy")).unwrap().shape(), &[1, 2, 8, 8]);
    assert!(xh.iter().all(|&v| v >= 0.0), "nonneg by default");
    // single frames too, and the products
    let x0 = xh.index_axis(ndarray::Axis(0), 0).to_owned().into_dimensionality::<Ix3>().unwrap();
    write_npy(&d.join("x0.npy"), &x0.view()).unwrap();
    let out = ok(d, &["depth", "x0.npy", "--peaks", "2", "-o", "depth.npy", "--ply", "cloud.ply", "--png", "depth.png"]);
    assert!(out.contains("points"), "{out}");
    let dep = read_npy(&d.join("depth.npy")).unwrap();
    assert_eq!(dep.shape(), &[2, 8, 8]);
    let ply = std::fs::read_to_string(d.join("cloud.ply")).unwrap();
    assert!(ply.starts_with("ply\nformat ascii 1.0"));
    let n: usize = ply.lines().find(|l| l.starts_with("element vertex")).unwrap().split_whitespace().last().unwrap().parse().unwrap();
    assert_eq!(ply.lines().skip_while(|l| *l != "end_header").count() - 1, n);
    assert!(std::fs::read(d.join("depth.png")).unwrap().starts_with(b"\x89PNG"));
    // the truth cube's own depth equals the ground truth within a fraction of a bin
    let truth = read_npy(&d.join("ds/test/x_000.npy")).unwrap();
    write_npy(&d.join("t0.npy"), &truth.index_axis(ndarray::Axis(0), 0)).unwrap();
    ok(d, &["depth", "t0.npy", "--peaks", "1", "-o", "tdepth.npy"]);
    let td = read_npy(&d.join("tdepth.npy")).unwrap();
    let gt = read_npy(&d.join("ds/test/depth_000.npy")).unwrap();
    let bin_m = 299_792_458.0 * (1.0 / 607e6) / 2.0;
    for r in 0..8 {
        for c in 0..8 {
            assert!((td[[0, r, c]] - gt[[0, 0, r, c]]).abs() < 0.3 * bin_m as f32);
        }
    }
    ok(d, &["plot", "waveforms", "--cube", "t0.npy", "--cube", "x0.npy", "--pixel", "1,1", "--pixel", "6,5", "-o", "w.png"]);
    let csv = std::fs::read_to_string(d.join("w.csv")).unwrap();
    assert_eq!(csv.lines().count(), 1 + 2 * 32);
}

#[test]
fn lifetime_map_of_a_flim_cube() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "flim", "--paper", "--count", "3", "--size", "8x8", "--seed", "3", "-o", "f"]);
    let x = read_npy(&d.join("f/train/x_000.npy")).unwrap();
    write_npy(&d.join("x.npy"), &x.index_axis(ndarray::Axis(0), 0)).unwrap();
    ok(d, &["lifetime", "x.npy", "-o", "tau.npy", "--phasor", "ph.npy", "--png", "tau.png"]);
    let tau = read_npy(&d.join("tau.npy")).unwrap().into_dimensionality::<Ix2>().unwrap();
    let truth = read_npy(&d.join("f/train/lifetime_000.npy")).unwrap();
    // single-channel pixels recover their lifetime closely; mixtures give a value between the channels
    let mut n = 0;
    for ((r, c), &t) in tau.indexed_iter() {
        let g = truth[[0, r, c]];
        if t.is_finite() && g.is_finite() {
            assert!(t > 0.4e-9 && t < 3.6e-9, "tau {t}");
            n += 1;
        }
    }
    assert!(n > 0);
    assert_eq!(read_npy(&d.join("ph.npy")).unwrap().shape(), &[2, 8, 8]);
    // bad settings of the fit: nothing is written
    fails(d, &["lifetime", "x.npy", "--components", "3", "-o", "t2.npy"], &["--components", "1, 2 or auto"]);
    fails(d, &["lifetime", "x.npy", "--irf-fwhm-ns=-1", "-o", "t2.npy"], &["--irf-fwhm-ns", "≥ 0"]);
    write_npy(&d.join("irf5.npy"), &ndarray::Array1::<f32>::ones(5).view()).unwrap();
    fails(d, &["lifetime", "x.npy", "--irf", "irf5.npy", "-o", "t2.npy"], &["irf5.npy", "[5]", "one per bin"]);
    assert!(!d.join("t2.npy").exists());
}

/// Issue 27: `tcsense lifetime` on true cubes against an independent pure-numpy reconvolution
/// fit (scripts/lifetime_reference.py; numpy from scripts/setup.sh's .venv) and the truth.
#[test]
fn lifetime_fit_agrees_with_a_numpy_reference() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let python = root.join(".venv/bin/python");
    assert!(python.exists(), "{} missing: run scripts/setup.sh (numpy for the reference fit)", python.display());
    let d = tempdir();
    let o = std::process::Command::new(python)
        .arg(root.join("scripts/lifetime_reference.py"))
        .arg(env!("CARGO_BIN_EXE_tcsense"))
        .arg(d.path())
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "reference fit: {out}{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.contains("tcsense vs numpy reference"), "{out}");
}

/// The fit to the tap images (`reconstruct lifetime-fit`, `eval --decoder lifetime-fit`) on
/// noise-free measurements of the paper's FLIm scenes; a LiDAR dataset is refused.
#[test]
fn lifetime_fit_to_the_taps() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["dataset", "flim", "--paper", "--count", "10", "--size", "16x16", "--seed", "3", "-o", "f"]);
    ok(
        d,
        &[
            "codes",
            "generate",
            "--taps",
            "4",
            "--block",
            "2x2",
            "--length",
            "32",
            "--tap-constraint",
            "--hamming",
            "2",
            "--window",
            "2",
            "--seed",
            "1",
            "-o",
            "codes.json",
        ],
    );
    let x = read_npy(&d.join("f/test/x_000.npy")).unwrap();
    write_npy(&d.join("x.npy"), &x.index_axis(ndarray::Axis(0), 0)).unwrap();
    let sensor = ["--codes", "codes.json", "--irf", "physical", "--heterodyne", "8"];
    ok(d, &[&["simulate", "--cube", "x.npy", "-o", "y.npy"][..], &sensor[..]].concat());
    ok(d, &[&["reconstruct", "lifetime-fit", "--measurements", "y.npy", "-o", "tau.npy", "--png", "tau.png"][..], &sensor[..]].concat());
    let tau = read_npy(&d.join("tau.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    assert_eq!(tau.dim(), (4, 16, 16));
    let truth = read_npy(&d.join("f/test/lifetime_000.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    let intensity = read_npy(&d.join("f/test/intensity_000.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    let peak = intensity.index_axis(ndarray::Axis(0), 0).iter().fold(0f32, |a, &b| a.max(b));
    let mut errs: Vec<f32> = Vec::new();
    for ((r, c), &g) in truth.index_axis(ndarray::Axis(0), 0).indexed_iter() {
        if g.is_finite() && intensity[[0, r, c]] > 0.02 * peak {
            errs.push((tau[[0, r, c]] - g).abs() / g);
        }
    }
    errs.sort_by(f32::total_cmp);
    assert!(errs.len() > 20 && errs[errs.len() / 2] < 0.05, "median relative error {} of {} pixels", errs[errs.len() / 2], errs.len());
    assert!(read_npy(&d.join("tau.confidence.npy")).unwrap().shape() == [1, 16, 16]);
    let out = ok(d, &[&["eval", "--dataset", "f", "--items", "1", "--decoder", "lifetime-fit"][..], &sensor[..]].concat());
    assert!(out.contains("lifetime-fit") && out.contains("lifetime MAE"), "{out}");
    // a LiDAR dataset has no lifetimes; bad fit settings exit 2
    lidar(d);
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "lifetime-fit"], &["no lifetime field"]);
    fails(
        d,
        &[&["reconstruct", "lifetime-fit", "--measurements", "y.npy", "-o", "t2.npy", "--window", "2"][..], &sensor[..]].concat(),
        &["--window", "odd"],
    );
    assert!(!d.join("t2.npy").exists());
}

#[test]
fn eval_select_and_sweep() {
    let d = tempdir();
    let d = d.path();
    lidar(d);
    let out = ok(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--maxit", "30", "-o", "report.json"]);
    assert!(out.contains("tval3"), "{out}");
    let rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("report.json")).unwrap()).unwrap();
    assert!(rep[0]["mse"].as_f64().unwrap() > 0.0 && rep[0]["mse"].as_f64().unwrap() < 0.05);
    let out = ok(
        d,
        &["codes", "select", "--dataset", "ds", "--tap-constraint", "--candidates", "3", "--maxit", "20", "--seed", "5", "-o", "best.json"],
    );
    assert_eq!(out.lines().filter(|l| l.trim_start().starts_with(|c: char| c.is_ascii_digit())).count(), 3, "{out}");
    ok(d, &["codes", "check", "best.json"]);
    ok(d, &["sweep", "constraints", "--dataset", "ds", "--items", "1", "--maxit", "10", "-o", "sw"]);
    let summary = std::fs::read_to_string(d.join("sw/summary.csv")).unwrap();
    assert_eq!(summary.lines().count(), 6, "{summary}");
    assert!(std::fs::read(d.join("sw/sweep.png")).unwrap().starts_with(b"\x89PNG"));
}

#[test]
fn bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["codes", "generate", "--tap-constraint", "--seed", "1", "-o", "codes.json"]);
    write_npy(&d.join("y5.npy"), &Array3::<f32>::zeros((5, 4, 4)).view()).unwrap();
    fails(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y5.npy", "-o", "x.npy"],
        &["y5.npy", "5 tap images", "M = 4"],
    );
    write_npy(&d.join("y.npy"), &Array3::<f32>::zeros((4, 4, 4)).view()).unwrap();
    fails(d, &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--mu=-1", "-o", "x.npy"], &["mu", "positive"]);
    fails(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--tv-weights", "1,1", "-o", "x.npy"],
        &["--tv-weights"],
    );
    assert!(!d.join("x.npy").exists());
    write_npy(&d.join("c.npy"), &Array3::<f32>::zeros((30, 4, 4)).view()).unwrap();
    fails(d, &["depth", "c.npy", "-o", "d.npy"], &["c.npy", "not a multiple of L = 32"]);
    fails(d, &["lifetime", "missing.npy", "-o", "t.npy"], &["missing.npy"]);
    fails(d, &["plot", "waveforms", "--cube", "c.npy", "--pixel", "9,9", "-o", "p.png"], &["outside"]);
    fails(d, &["eval", "--dataset", "nowhere", "--codes", "codes.json"], &["nowhere", "manifest.json"]);
    fails(d, &["sweep", "taps", "--dataset", "nowhere", "-o", "s"], &["nowhere"]);
}

/// `bench kernels` runs on a tiny frame and prints every operation with a speed-up figure.
#[test]
fn bench_kernels_prints_every_op() {
    let d = tempdir();
    let out = ok(d.path(), &["bench", "kernels", "--size", "8x8", "--channels", "4", "--reps", "1"]);
    for op in ["conv 3x3 forward", "conv 3x3 input grad", "conv 3x3 weight grad", "data consistency", "back-projection"] {
        let line = out.lines().find(|l| l.starts_with(op)).unwrap_or_else(|| panic!("no {op:?} row in:\n{out}"));
        assert!(line.trim_end().ends_with('x'), "{line}");
    }
}

#[test]
fn bench_bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    fails(d, &["bench", "forward", "--size", "5x5", "--reps", "1"], &["multiple of 2"]);
    fails(d, &["bench", "tval3", "--bins", "30"], &["--bins 30", "multiple of 32"]);
    fails(d, &["bench", "train", "--bins", "30"], &["--bins 30", "multiple of 32"]);
    fails(d, &["bench", "train", "--bins", "32,40"], &["--bins 32,40", "multiple of 32"]);
    fails(d, &["bench", "train", "--delay-path", "fast"], &["--delay-path", "kernel", "composed"]);
    fails(d, &["bench", "train", "--size", "7x8"], &["--size 7x8", "even"]);
    fails(d, &["bench", "range-fit", "--size", "7x8"], &["--size 7x8", "even frame"]);
    fails(d, &["bench", "range-fit", "--size", "0x8"], &["--size", "0x8", "from 1 to"]);
    fails(d, &["bench", "range-fit", "--size", "3x8"], &["--size 3x8", "even frame"]);
    fails(d, &["bench", "dataset", "--size", "0x8"], &["size"]);
    fails(d, &["bench", "kernels", "--size", "5x5"], &["5x5", "even"]);
    fails(d, &["bench", "kernels", "--bins", "20"], &["--bins 20", "multiple of 32"]);
}

/// `reconstruct depth-fit` and `eval --decoder depth-fit[:K]`: ranges fitted to the taps with no
/// network, a warning on codes that alias, and bad settings refused (exit 2, nothing written).
#[test]
fn depth_fit_to_the_taps() {
    let d = tempdir();
    let d = d.path();
    lidar(d);
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    let out =
        run(d, &["reconstruct", "depth-fit", "--codes", "codes.json", "--measurements", "y.npy", "--returns", "1", "-o", "depth.npy"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    // random codes through the ideal gates alias exactly (bins 8 and 26): the whole-cycle search
    // is warned about
    assert!(err.contains("warning: these codes alias") && err.contains("bins 8 and 26"), "{err}");
    let depth = read_npy(&d.join("depth.npy")).unwrap();
    assert_eq!(&depth.shape()[1..], &[1, 8, 8]);
    let truth = read_npy(&d.join("ds/test/depth_000.npy")).unwrap();
    let (est, first) = (depth.index_axis(ndarray::Axis(0), 0), truth.index_axis(ndarray::Axis(0), 0));
    let placed = est.iter().zip(first.index_axis(ndarray::Axis(0), 0).iter()).filter(|(e, t)| e.is_finite() && t.is_finite()).count();
    assert!(placed > 32, "{placed} of 64 pixels got a range");
    // a wider window for the fit (the network-seeded refinement's own window keeps its default)
    let out = run(
        d,
        &[
            "reconstruct",
            "depth-fit",
            "--codes",
            "codes.json",
            "--measurements",
            "y.npy",
            "--returns",
            "1",
            "--window",
            "5",
            "-o",
            "d5.npy",
        ],
    );
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(&read_npy(&d.join("d5.npy")).unwrap().shape()[1..], &[1, 8, 8]);
    // any registry name reaches reconstruct: a cube decoder with its peaks refined in the tap
    // domain writes the cube and, beside it, the ranges with their confidence
    let out = ok(d, &["reconstruct", "tval3+fit", "--codes", "codes.json", "--measurements", "y.npy", "--maxit", "20", "-o", "tv.npy"]);
    assert!(out.contains("tv.depth.npy"), "{out}");
    // (y.npy is a batch of one, [1, M, H, W], and so are the outputs)
    assert_eq!(&read_npy(&d.join("tv.npy")).unwrap().shape()[2..], &[8, 8], "the cube [1, T, H, W]");
    assert_eq!(read_npy(&d.join("tv.depth.npy")).unwrap().shape(), &[1, 2, 8, 8]);
    assert_eq!(read_npy(&d.join("tv.confidence.npy")).unwrap().shape(), &[1, 2, 8, 8]);
    // the ranges' products come with them; a decoder of cubes alone has none to give
    let out = ok(
        d,
        &[
            "reconstruct",
            "tval3+fit",
            "--codes",
            "codes.json",
            "--measurements",
            "y.npy",
            "--maxit",
            "5",
            "--ply",
            "tv.ply",
            "-o",
            "tv5.npy",
        ],
    );
    assert!(out.contains("tv.ply") && d.join("tv.ply").exists(), "{out}");
    fails(
        d,
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--maxit", "5", "--ply", "c.ply", "-o", "cube.npy"],
        &["--ply", "no ranges", "tval3+fit"],
    );
    assert!(!d.join("c.ply").exists() && !d.join("cube.npy").exists(), "a refused command leaves no file");
    fails(d, &["reconstruct", "depth-fit:1", "--measurements", "y.npy", "-o", "nocodes.npy"], &["--codes", "any sensor"]);
    fails(
        d,
        &["reconstruct", "tval3", "--run", "ds", "--codes", "codes.json", "--measurements", "y.npy", "-o", "x.npy"],
        &["--run", "tval3"],
    );
    fails(
        d,
        &["reconstruct", "magic", "--codes", "codes.json", "--measurements", "y.npy", "-o", "x.npy"],
        &["unknown decoder", "depth-fit[:K]"],
    );
    assert!(!d.join("nocodes.npy").exists() && !d.join("x.npy").exists());
    let out = ok(
        d,
        &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "depth-fit", "--decoder", "depth-fit:1", "-o", "rep.json"],
    );
    assert!(out.contains("depth-fit:1") && out.contains("median"), "{out}");
    fails(
        d,
        &["reconstruct", "depth-fit", "--codes", "codes.json", "--measurements", "y.npy", "--window", "2", "-o", "bad.npy"],
        &["window 2", "odd"],
    );
    fails(
        d,
        &["reconstruct", "depth-fit", "--codes", "codes.json", "--measurements", "y.npy", "--returns", "3", "-o", "bad.npy"],
        &["returns 3", "1 or 2"],
    );
    assert!(!d.join("bad.npy").exists());
    fails(
        d,
        &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "depth-fit:3"],
        &["depth-fit:3", "depth-fit:1 or depth-fit:2"],
    );
}

/// `eval --light`: every decoder at every level of the photon ladder on the same items, the
/// errors growing as the light falls, ambient light (`--sbr`) costing accuracy, and the curve.
#[test]
fn eval_photon_ladder() {
    let t = tempdir();
    let d = t.path();
    let zoo_codes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo/unet-lidar-designed/codes.json");
    std::fs::copy(zoo_codes, d.join("codes.json")).unwrap();
    ok(d, &["dataset", "lidar", "--count", "12", "--size", "16x16", "--seed", "5", "-o", "ds"]);
    let ladder = [
        "eval",
        "--dataset",
        "ds",
        "--split",
        "train",
        "--items",
        "4",
        "--codes",
        "codes.json",
        "--irf",
        "physical",
        "--decoder",
        "depth-fit",
        "--decoder",
        "tval3",
        "--maxit",
        "20",
        "--light",
        "0.8,0.01",
    ];
    let with = |extra: &[&'static str]| -> Vec<&'static str> { ladder.iter().copied().chain(extra.iter().copied()).collect() };
    let out = ok(d, &with(&["--plot", "curve.png", "-o", "t.json"]));
    assert!(out.contains("16000 e⁻ in the brightest tap") && out.contains("200 e⁻ in the brightest tap"), "{out}");
    let rows: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("t.json")).unwrap()).unwrap();
    let rows = rows.as_array().unwrap();
    assert_eq!(rows.len(), 4, "two decoders at two levels");
    let at = |name: &str, level: f64| {
        rows.iter().find(|r| r["decoder"] == name && r["light"]["signal_fraction"].as_f64() == Some(level)).unwrap().clone()
    };
    for name in ["depth-fit", "tval3"] {
        let (bright, dim) = (at(name, 0.8), at(name, 0.01));
        let (eb, ed) = (bright["depth_median_m"][0].as_f64().unwrap(), dim["depth_median_m"][0].as_f64().unwrap());
        let (sb, sd) = (bright["depth_within_half_bin"][0].as_f64().unwrap(), dim["depth_within_half_bin"][0].as_f64().unwrap());
        assert!(ed > 2.0 * eb && sd < sb && (0.0..=1.0).contains(&sb), "{name}: median {eb} → {ed} m, within half a bin {sb} → {sd}");
        assert_eq!(bright["light"]["signal_electrons"].as_f64(), Some(16000.0));
        assert!(bright["light"]["sbr"].is_null());
    }
    // the fit near the bound in bright light: within half a bin for most first returns
    assert!(at("depth-fit", 0.8)["depth_within_half_bin"][0].as_f64().unwrap() > 0.6);
    let csv = std::fs::read_to_string(d.join("t.csv")).unwrap();
    assert!(
        csv.lines()
            .next()
            .unwrap()
            .ends_with("bounce1_within_half_bin,bounce2_within_half_bin,signal_fraction,signal_electrons,sbr,lifetime_false_share,lifetime_mae_common_s,lifetime_common_share")
            && csv.lines().count() == 5,
        "{csv}"
    );
    let png = std::fs::read(d.join("curve.png")).unwrap();
    assert!(png.starts_with(b"\x89PNG") && png.len() > 20_000);
    // ambient light as strong as the signal costs the fit accuracy at the same level and seeds
    ok(d, &with(&["--sbr", "1", "-o", "amb.json"]));
    let amb: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("amb.json")).unwrap()).unwrap();
    let fit_amb = amb
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["decoder"] == "depth-fit" && r["light"]["signal_fraction"].as_f64() == Some(0.8))
        .unwrap()
        .clone();
    assert_eq!(fit_amb["light"]["sbr"].as_f64(), Some(1.0));
    let (clean, ambient) = (at("depth-fit", 0.8)["depth_median_m"][0].as_f64().unwrap(), fit_amb["depth_median_m"][0].as_f64().unwrap());
    assert!(ambient > clean, "ambient {ambient} vs none {clean}");
    assert!(fit_amb.get("clipped_share").is_none(), "nothing clipped at SBR 1: {fit_amb}");
    // fifty times as much ambient as signal light fills the wells in bright light: the pixels
    // with a clipped tap get no range (counted against detection), the others are read as before
    let out = ok(d, &with(&["--sbr", "0.02", "-o", "sat.json"]));
    assert!(out.contains("of the pixels have a tap clipped at the full well"), "{out}");
    let sat: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("sat.json")).unwrap()).unwrap();
    for r in sat.as_array().unwrap().iter().filter(|r| r["light"]["signal_fraction"].as_f64() == Some(0.8)) {
        let share = r["clipped_share"].as_f64().unwrap_or(0.0);
        let first = &r["depth"][0];
        let detected = first["detected"].as_f64().unwrap() / first["truth"].as_f64().unwrap();
        assert!(share > 0.5 && detected <= 1.0 - share + 1e-9, "{}: {share} clipped, {detected} detected", r["decoder"]);
    }
    fails(d, &with(&["--light", "0"]), &["--light"]);
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--light", "NaN"], &["--light"]);
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--light", "0.5", "--sbr=-1"], &["--sbr"]);
    fails(d, &["eval", "--dataset", "ds", "--codes", "codes.json", "--plot", "c.png"], &["--light"]);
    fails(
        d,
        &["eval", "--dataset", "ds", "--codes", "codes.json", "--light", "0.5", "--plot", "t.json", "-o", "t.json"],
        &["t.json", "named by both"],
    );
}

/// `bench decoders`: the speed of each decoder on a stream at a frame size larger than the
/// dataset's items, beside its error on the ladder; the one-return fit is faster than the
/// two-return fit; the files and the figure; bad settings refused with nothing written.
#[test]
fn bench_decoders_speed_beside_accuracy() {
    let t = tempdir();
    let d = t.path();
    let zoo_codes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo/unet-lidar-designed/codes.json");
    std::fs::copy(zoo_codes, d.join("codes.json")).unwrap();
    ok(d, &["dataset", "lidar", "--count", "12", "--size", "16x16", "--seed", "5", "-o", "ds"]);
    let bench = [
        "bench",
        "decoders",
        "--dataset",
        "ds",
        "--split",
        "train",
        "--items",
        "3",
        "--codes",
        "codes.json",
        "--irf",
        "physical",
        "--decoder",
        "depth-fit:1",
        "--decoder",
        "depth-fit",
        "--rounds",
        "3",
    ];
    let with = |extra: &[&'static str]| -> Vec<&'static str> { bench.iter().copied().chain(extra.iter().copied()).collect() };
    let out = ok(d, &with(&["--light", "0.8,0.01", "--frame", "24x40", "--frames", "4", "-o", "b/bench.json"]));
    assert!(out.contains("4 frames of 24x40") && out.contains("depth-fit:1") && out.contains("wrote b/bench.json"), "{out}");
    let doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("b/bench.json")).unwrap()).unwrap();
    let speed = doc["speed"].as_array().unwrap();
    assert_eq!(speed.len(), 2);
    let fps = |i: usize| speed[i]["frames_per_s"].as_f64().unwrap();
    assert!(fps(0) > 0.0 && fps(1) > 0.0 && speed[0]["frames"] == 4 && speed[0]["rounds"] == 3, "{speed:?}");
    let acc = doc["accuracy"].as_array().unwrap();
    assert_eq!(acc.len(), 4, "two decoders at two levels");
    let within = |name: &str, level: f64| {
        acc.iter().find(|r| r["decoder"] == name && r["light"]["signal_fraction"].as_f64() == Some(level)).unwrap()["depth_within_half_bin"]
            [0]
        .as_f64()
        .unwrap()
    };
    assert!(within("depth-fit", 0.8) > 0.6 && within("depth-fit", 0.01) < within("depth-fit", 0.8));
    let csv = std::fs::read_to_string(d.join("b/bench.csv")).unwrap();
    assert!(csv.starts_with("decoder,frames_per_s,ms_per_frame,signal_fraction") && csv.lines().count() == 5, "{csv}");
    for png in ["b/bench.png", "b/bench.photon.png"] {
        let bytes = std::fs::read(d.join(png)).unwrap();
        assert!(bytes.starts_with(b"\x89PNG") && bytes.len() > 20_000, "{png}");
    }
    // bad settings: exit 2, nothing written
    fails(d, &with(&["--frame", "25x40", "--frames", "2", "-o", "bad/b.json"]), &["--frame", "block"]);
    fails(d, &with(&["--frames", "0", "-o", "bad/b.json"]), &["--frames"]);
    fails(d, &with(&["--frames", "100000", "--frame", "65536x65536", "-o", "bad/b.json"]), &["--frames", "GiB"]);
    fails(d, &with(&["--light", "2", "-o", "bad/b.json"]), &["--light"]);
    fails(
        d,
        &["bench", "decoders", "--dataset", "nowhere", "--codes", "codes.json", "--decoder", "depth-fit", "-o", "bad/b.json"],
        &["nowhere"],
    );
    assert!(!d.join("bad").exists(), "a refused bench leaves no files");
}

/// A pixel with a tap clipped at the full well gets no range: from the clip level `simulate`
/// records beside the measurements, or one given (`--clip-level`, in the tap images' units);
/// the other pixels keep the ranges they get without it.
#[test]
fn clipped_pixels_get_no_range() {
    let d = tempdir();
    let d = d.path();
    lidar(d);
    let fit = |y: &str, out: &str, extra: &[&str]| -> String {
        let args: Vec<&str> = ["reconstruct", "depth-fit", "--codes", "codes.json", "--measurements", y, "-o", out]
            .iter()
            .copied()
            .chain(extra.iter().copied())
            .collect();
        ok(d, &args)
    };
    // noise at the automatic exposure (brightest tap at 80 % of full well): nothing clipped
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "--noise", "--seed", "2", "-o", "y.npy"]);
    let meta: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("y.meta.json")).unwrap()).unwrap();
    let clip = meta["clip_level"].as_f64().unwrap();
    let y = read_npy(&d.join("y.npy")).unwrap();
    assert!(y.iter().all(|&v| (v as f64) < clip) && y.iter().fold(0f32, |m, &v| m.max(v)) as f64 > 0.7 * clip, "clip {clip}");
    let out = fit("y.npy", "plain.npy", &[]);
    assert!(!out.contains("clipped"), "{out}");
    let plain = read_npy(&d.join("plain.npy")).unwrap();
    // a level inside the taps' range: the pixels with a tap at it or above lose their ranges
    let mut sorted: Vec<f32> = y.iter().copied().collect();
    sorted.sort_by(f32::total_cmp);
    let level = sorted[sorted.len() * 3 / 4];
    let out = fit("y.npy", "cut.npy", &["--clip-level", &level.to_string()]);
    let cut = read_npy(&d.join("cut.npy")).unwrap();
    let conf = read_npy(&d.join("cut.confidence.npy")).unwrap();
    let mut unread = 0;
    for i in 0..8 {
        for j in 0..8 {
            let clipped = (0..4).any(|m| y[[0, m, i, j]] >= level.to_string().parse::<f32>().unwrap() * (1.0 - 1e-6));
            unread += clipped as usize;
            for k in 0..2 {
                let (c, p) = (cut[[0, k, i, j]], plain[[0, k, i, j]]);
                if clipped {
                    assert!(c.is_nan() && conf[[0, k, i, j]] == 0.0, "({i}, {j})");
                } else {
                    assert!(c.to_bits() == p.to_bits(), "({i}, {j}): {c} against {p}");
                }
            }
        }
    }
    assert!(unread > 8 && unread < 64, "{unread} pixels clipped");
    assert!(out.contains(&format!("{unread} pixels with a tap clipped at the full well")), "{out}");
    // a simulation that fills the wells: every pixel clipped, from its sidecar alone
    ok(
        d,
        &[
            "simulate",
            "--codes",
            "codes.json",
            "--cube",
            "ds/test/x_000.npy",
            "--noise",
            "--electrons-per-unit",
            "1e9",
            "--seed",
            "2",
            "-o",
            "full.npy",
        ],
    );
    let out = fit("full.npy", "full-d.npy", &[]);
    assert!(out.contains("64 pixels with a tap clipped") && out.contains("returns per bounce [0, 0]"), "{out}");
    fails(
        d,
        &["reconstruct", "depth-fit", "--codes", "codes.json", "--measurements", "y.npy", "-o", "z.npy", "--clip-level=-1"],
        &["--clip-level"],
    );
    assert!(!d.join("z.npy").exists());
}
