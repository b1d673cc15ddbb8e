//! End-to-end tests of `tcsense export onnx` and `tcsense infer`: a trained U-Net and
//! ADMM-Net exported, validated by onnx's full checker and onnxruntime-Python, streamed over
//! a stack, a directory of .npy and PNG frames; bad input and a missing runtime exit 2.

mod common;
use common::*;
use std::path::Path;
use tcsense_sensor::npy::{read_npy, write_npy};

fn python() -> std::path::PathBuf {
    let py = Path::new(env!("CARGO_MANIFEST_DIR")).join(".venv/bin/python");
    assert!(py.exists(), "{} missing: run scripts/setup.sh", py.display());
    py
}

fn check_onnx(dir: &Path, args: &[&str]) -> String {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/check_onnx.py");
    let o = std::process::Command::new(python()).current_dir(dir).arg(script).args(args).output().unwrap();
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    assert!(o.status.success(), "check_onnx.py {args:?}: {out}{}", String::from_utf8_lossy(&o.stderr));
    out
}

#[test]
fn export_check_and_stream_a_trained_unet() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    ok(
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
    let out = ok(d, &["export", "onnx", "--run", "unet", "-o", "unet.onnx"]);
    assert!(out.contains("multiples of 2x2") && out.contains("depth, confidence"), "{out}");
    // a stack of 3 noisy frames
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "--noise", "--seed", "1", "-o", "y0.npy"]);
    let y0 = read_npy(&d.join("y0.npy")).unwrap().index_axis_move(ndarray::Axis(0), 0); // [M, H, W]
    let frames: Vec<_> = (0..3).map(|i| y0.mapv(|v| v * (1.0 + i as f32))).collect();
    let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
    let stack = ndarray::stack(ndarray::Axis(0), &views).unwrap();
    write_npy(&d.join("stack.npy"), &stack.view()).unwrap();
    let out =
        ok(d, &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--products", "depth,ply", "--no-range-fit", "-o", "out"]);
    assert!(out.contains("3 frames") && out.contains("frames/s"), "{out}");
    let depth = read_npy(&d.join("out/depth.npy")).unwrap();
    let conf = read_npy(&d.join("out/confidence.npy")).unwrap();
    assert_eq!((depth.shape(), conf.shape()), (&[3, 2, 8, 8][..], &[3, 2, 8, 8][..]));
    assert!(depth.iter().zip(conf.iter()).all(|(d, c)| d.is_nan() == (*c < 0.5)));
    assert!(d.join("out/ply/frame_00002.ply").exists());
    // the U-Net is scale invariant: the three frames (y, 2y, 3y) give the same depth
    let f0 = depth.index_axis(ndarray::Axis(0), 0);
    let f2 = depth.index_axis(ndarray::Axis(0), 2);
    assert!(f0.iter().zip(f2.iter()).all(|(a, b)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-3));
    // burn (reconstruct unet) and ort (infer) agree on the first frame
    ok(d, &["reconstruct", "unet", "--run", "unet", "--measurements", "y0.npy", "--no-range-fit", "-o", "burn.npy"]);
    let burn = read_npy(&d.join("burn.npy")).unwrap();
    assert!(
        burn.iter().zip(f0.iter()).all(|(a, b)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-4 * 12.0),
        "burn and ort depth differ"
    );
    // by default infer refines the ranges in the tap domain as reconstruct does: the same product
    ok(d, &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "-o", "out-fit"]);
    ok(d, &["reconstruct", "unet", "--run", "unet", "--measurements", "y0.npy", "-o", "burn-fit.npy"]);
    let (fitted, burn_fit) = (read_npy(&d.join("out-fit/depth.npy")).unwrap(), read_npy(&d.join("burn-fit.npy")).unwrap());
    let fitted0 = fitted.index_axis(ndarray::Axis(0), 0);
    let moved = fitted0.iter().zip(f0.iter()).filter(|(a, b)| a.is_finite() && b.is_finite() && (*a - *b).abs() > 1e-3).count();
    assert!(moved > 0, "the range fit moved no return");
    let far =
        burn_fit.iter().zip(fitted0.iter()).filter(|(a, b)| a.is_nan() != b.is_nan() || (a.is_finite() && (*a - *b).abs() > 1e-2)).count();
    assert!(far == 0, "{far} ranges of infer differ from reconstruct unet's (both with the range fit)");
    // --depth-fit: the template fit through the model's sensor, the network skipped, equal to
    // reconstruct depth-fit on the same frame
    let out = ok(d, &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--depth-fit", "-o", "out-df"]);
    assert!(out.contains("0.0 ms per frame in ONNX Runtime"), "the network ran: {out}");
    ok(d, &["reconstruct", "depth-fit", "--codes", "unet/codes.json", "--measurements", "y0.npy", "-o", "df.npy"]);
    let (streamed, fitted) = (read_npy(&d.join("out-df/depth.npy")).unwrap(), read_npy(&d.join("df.npy")).unwrap());
    assert_eq!(streamed.shape(), &[3, 2, 8, 8]);
    let s0 = streamed.index_axis(ndarray::Axis(0), 0);
    assert!(s0.iter().any(|v| v.is_finite()), "no range fitted");
    assert!(
        s0.iter().zip(fitted.iter()).all(|(a, b)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-6),
        "infer --depth-fit and reconstruct depth-fit differ"
    );
    // pooled by likeness: infer --depth-fit --pool-like and reconstruct depth-fit-pooled agree
    ok(d, &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--depth-fit", "--pool-like", "9", "-o", "out-dp"]);
    ok(d, &["reconstruct", "depth-fit-pooled:9", "--codes", "unet/codes.json", "--measurements", "y0.npy", "-o", "dp.npy"]);
    let (streamed, fitted) = (read_npy(&d.join("out-dp/depth.npy")).unwrap(), read_npy(&d.join("dp.npy")).unwrap());
    let s0 = streamed.index_axis(ndarray::Axis(0), 0);
    assert!(s0.iter().any(|v| v.is_finite()), "no range fitted");
    assert!(
        s0.iter().zip(fitted.iter()).all(|(a, b)| (a.is_nan() && b.is_nan()) || (a - b).abs() < 1e-6),
        "infer --depth-fit --pool-like 9 and reconstruct depth-fit-pooled:9 differ"
    );
    // a clip level (as reconstruct takes it): the pixels of each frame with a tap at it get no
    // range and a confidence 0, the others the ranges they get without it
    let mut sorted: Vec<f32> = y0.iter().copied().collect();
    sorted.sort_by(f32::total_cmp);
    let level = sorted[sorted.len() * 9 / 10].to_string();
    for (plain, extra) in [("out-fit", None), ("out-df", Some("--depth-fit"))] {
        let mut args = vec!["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--clip-level", &level, "-o", "out-clip"];
        args.extend(extra);
        ok(d, &args);
        let (cut, conf, base) = (
            read_npy(&d.join("out-clip/depth.npy")).unwrap(),
            read_npy(&d.join("out-clip/confidence.npy")).unwrap(),
            read_npy(&d.join(plain).join("depth.npy")).unwrap(),
        );
        let l: f32 = level.parse().unwrap();
        let mut unread = [0usize; 3];
        for f in 0..3 {
            for i in 0..8 {
                for j in 0..8 {
                    let clipped = (0..4).any(|m| stack[[f, m, i, j]] >= l * (1.0 - 1e-6));
                    unread[f] += clipped as usize;
                    for k in 0..2 {
                        let (c, b) = (cut[[f, k, i, j]], base[[f, k, i, j]]);
                        assert!(
                            if clipped { c.is_nan() && conf[[f, k, i, j]] == 0.0 } else { c.to_bits() == b.to_bits() },
                            "{plain}, frame {f} ({i}, {j}): {c} against {b}"
                        );
                    }
                }
            }
        }
        assert!(unread[0] > 0 && unread[0] < 64 && unread[0] <= unread[1] && unread[1] <= unread[2], "{unread:?}");
    }
    fails(
        d,
        &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--depth-fit", "--pool-like", "12", "-o", "bad-dp"],
        &["--pool-like", "pool_like 12", "odd multiple"],
    );
    fails(
        d,
        &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--depth-fit", "--returns", "3", "-o", "bad-df"],
        &["--depth-fit", "--returns 3"],
    );
    fails(
        d,
        &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--lifetime-fit", "-o", "bad-df"],
        &["--lifetime-fit", "depth model"],
    );
    assert!(!d.join("bad-df").exists());
    // onnx full checker, shape inference, onnxruntime-Python equal to tcsense infer
    let out = check_onnx(d, &["unet.onnx", "--measurements", "stack.npy", "--compare", "out"]);
    assert!(out.contains("checker (full)") && out.contains("ok  depth") && out.contains("ok  confidence"), "{out}");

    // the same trained U-Net with the sensor matrix as an input gives the same depth
    ok(d, &["export", "onnx", "--run", "unet", "--matrix-input", "-o", "unet_m.onnx"]);
    ok(d, &["sensor", "matrix", "--codes", "unet/codes.json", "-o", "A.npy"]);
    ok(d, &["infer", "--model", "unet_m.onnx", "--measurements", "stack.npy", "--sensor-matrix", "A.npy", "--no-range-fit", "-o", "out_m"]);
    let dm = read_npy(&d.join("out_m/confidence.npy")).unwrap();
    let cb = read_npy(&d.join("out/confidence.npy")).unwrap();
    assert!(dm.iter().zip(cb.iter()).all(|(a, b)| (a - b).abs() < 1e-4), "matrix input vs baked confidence");
    let check = check_onnx(d, &["unet_m.onnx", "--measurements", "stack.npy", "--sensor-matrix", "A.npy", "--compare", "out_m"]);
    assert!(check.contains("ok  depth"), "{check}");

    // a directory of frames: a .npy and a 16-bit PNG of the same frame (taps side by side)
    std::fs::create_dir_all(d.join("frames")).unwrap();
    let f = y0.clone().into_dimensionality::<ndarray::Ix3>().unwrap();
    assert_eq!(f.dim(), (4, 8, 8));
    write_npy(&d.join("frames/a.npy"), &f.view()).unwrap();
    let (m, h, w) = f.dim();
    let mut pixels = Vec::with_capacity(h * m * w * 2);
    for r in 0..h {
        for tap in 0..m {
            for c in 0..w {
                pixels.extend_from_slice(&(f[(tap, r, c)].round().clamp(0.0, 65535.0) as u16).to_be_bytes());
            }
        }
    }
    let file = std::fs::File::create(d.join("frames/b.png")).unwrap();
    let mut enc = png::Encoder::new(file, (m * w) as u32, h as u32);
    enc.set_color(png::ColorType::Grayscale);
    enc.set_depth(png::BitDepth::Sixteen);
    enc.write_header().unwrap().write_image_data(&pixels).unwrap();
    ok(d, &["infer", "--model", "unet.onnx", "--measurements", "frames", "--no-range-fit", "-o", "out2"]);
    let depth = read_npy(&d.join("out2/depth.npy")).unwrap();
    assert_eq!(depth.shape(), &[2, 2, 8, 8]);
    let (a, b) = (depth.index_axis(ndarray::Axis(0), 0), depth.index_axis(ndarray::Axis(0), 1));
    let same = a.iter().zip(b.iter()).filter(|(x, y)| (x.is_nan() && y.is_nan()) || (*x - *y).abs() < 0.05).count();
    assert!(same >= 120, "the PNG frame (rounded to integers) gives the .npy frame's depth: {same}/128");

    // bad input: products a depth model cannot give, a frame off the frame rule, wrong taps,
    // a truncated stack, an empty directory, a missing model; nothing is written
    fails(
        d,
        &["infer", "--model", "unet.onnx", "--measurements", "stack.npy", "--products", "cube", "-o", "bad1"],
        &["--products", "cube"],
    );
    let odd = ndarray::Array3::<f32>::ones((4, 8, 7));
    write_npy(&d.join("odd.npy"), &odd.view()).unwrap();
    fails(d, &["infer", "--model", "unet.onnx", "--measurements", "odd.npy", "-o", "bad2"], &["odd.npy", "multiples of 2x2"]);
    let three = ndarray::Array3::<f32>::ones((3, 8, 8));
    write_npy(&d.join("three.npy"), &three.view()).unwrap();
    fails(d, &["infer", "--model", "unet.onnx", "--measurements", "three.npy", "-o", "bad3"], &["three.npy", "M = 4 taps"]);
    let bytes = std::fs::read(d.join("stack.npy")).unwrap();
    std::fs::write(d.join("cut.npy"), &bytes[..bytes.len() - 100]).unwrap();
    fails(d, &["infer", "--model", "unet.onnx", "--measurements", "cut.npy", "-o", "bad4"], &["cut.npy", "truncated"]);
    std::fs::create_dir_all(d.join("empty")).unwrap();
    fails(d, &["infer", "--model", "unet.onnx", "--measurements", "empty", "-o", "bad5"], &["empty", "no frames"]);
    fails(d, &["infer", "--model", "nope.onnx", "--measurements", "stack.npy", "-o", "bad6"], &["nope.onnx"]);
    // a frame of another size in the middle of a stream: the error names it and the frames
    // already decoded are not left behind as a partial output
    std::fs::create_dir_all(d.join("mixed")).unwrap();
    write_npy(&d.join("mixed/a.npy"), &f.view()).unwrap();
    write_npy(&d.join("mixed/b.npy"), &ndarray::Array3::<f32>::ones((4, 8, 4)).view()).unwrap();
    fails(d, &["infer", "--model", "unet.onnx", "--measurements", "mixed", "-o", "bad7"], &["b.npy", "first frame"]);
    for bad in ["bad1", "bad2", "bad3", "bad4", "bad5", "bad6", "bad7"] {
        let left: Vec<_> = std::fs::read_dir(d.join(bad)).map(|r| r.flatten().map(|e| e.path()).collect()).unwrap_or_default();
        assert!(left.is_empty(), "{bad}: {left:?} left behind");
    }
}

/// `infer --lifetime-fit`: lifetimes by the fit to the taps through an exported model's sensor,
/// the network skipped, equal to `reconstruct lifetime-fit` on the same frame and the same on a
/// brighter copy (the instrument estimated once, on the first frame).
#[test]
fn a_lifetime_model_streams_the_fit_to_the_taps() {
    let d = tempdir();
    let d = d.path();
    tiny_lidar_and_codes(d);
    ok(d, &["dataset", "flim", "--count", "4", "--size", "8x8", "--length", "8", "--heterodyne", "4", "--seed", "5", "-o", "f"]);
    ok(
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
            "1",
            "--seed",
            "3",
            "-o",
            "lt",
        ],
    );
    ok(d, &["export", "onnx", "--run", "lt", "-o", "lt.onnx"]);
    ok(
        d,
        &["simulate", "--codes", "codes.json", "--heterodyne", "4", "--cube", "f/test/x_000.npy", "--noise", "--seed", "1", "-o", "y0.npy"],
    );
    let y0 = read_npy(&d.join("y0.npy")).unwrap().index_axis_move(ndarray::Axis(0), 0);
    let frames = [y0.clone(), y0.mapv(|v| 2.0 * v)];
    let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
    write_npy(&d.join("stack.npy"), &ndarray::stack(ndarray::Axis(0), &views).unwrap().view()).unwrap();
    let out = ok(
        d,
        &[
            "infer",
            "--model",
            "lt.onnx",
            "--measurements",
            "stack.npy",
            "--lifetime-fit",
            "--products",
            "lifetime,intensity,phasor",
            "-o",
            "out",
        ],
    );
    assert!(out.contains("2 frames") && out.contains("0.0 ms per frame in ONNX Runtime"), "the network ran: {out}");
    ok(d, &["reconstruct", "lifetime-fit", "--codes", "codes.json", "--heterodyne", "4", "--measurements", "y0.npy", "-o", "fit.npy"]);
    let (streamed, fitted) = (read_npy(&d.join("out/lifetime.npy")).unwrap(), read_npy(&d.join("fit.npy")).unwrap());
    assert_eq!((streamed.shape(), read_npy(&d.join("out/phasor.npy")).unwrap().shape()), (&[2, 8, 8][..], &[2, 2, 8, 8][..]));
    let fitted0 = fitted.slice(ndarray::s![0, 0, .., ..]);
    assert!(fitted0.iter().any(|v| v.is_finite()), "no lifetime fitted");
    for f in 0..2 {
        let s = streamed.index_axis(ndarray::Axis(0), f);
        let bad = s
            .iter()
            .zip(fitted0.iter())
            .filter(|(a, b)| a.is_nan() != b.is_nan() || (a.is_finite() && (*a - *b).abs() > 1e-3 * b.abs()))
            .count();
        assert_eq!(bad, 0, "frame {f}: {bad} lifetimes differ from reconstruct lifetime-fit's\n{s:?}\n{fitted0:?}");
    }
    // a second stream into the same directory names only what it wrote, not the first's files
    let out =
        ok(d, &["infer", "--model", "lt.onnx", "--measurements", "stack.npy", "--lifetime-fit", "--products", "lifetime", "-o", "out"]);
    assert!(out.contains("lifetime.npy") && !out.contains("intensity.npy") && !out.contains("phasor.npy"), "{out}");
    // the fit gives lifetime, intensity and phasor only; its settings need --lifetime-fit
    fails(
        d,
        &["infer", "--model", "lt.onnx", "--measurements", "stack.npy", "--onset-ns", "2", "-o", "bad"],
        &["--onset-ns", "--lifetime-fit"],
    );
    // a lifetime model gives no depth for the range fit to replace
    fails(
        d,
        &["infer", "--model", "lt.onnx", "--measurements", "stack.npy", "--depth-fit", "-o", "bad"],
        &["--depth-fit", "lifetime model"],
    );
    assert!(!d.join("bad").exists());
}

/// The onset and IRF width `infer` reports (ns), and the frames they were searched on.
fn instrument_of(out: &str) -> (f64, f64, usize) {
    let line = out.lines().find(|l| l.starts_with("instrument: ")).unwrap_or_else(|| panic!("no instrument line: {out}"));
    let num = |after: &str| -> f64 {
        let rest = &line[line.find(after).unwrap_or_else(|| panic!("{after:?} in {line}")) + after.len()..];
        rest.split_whitespace().next().unwrap().parse().unwrap()
    };
    let frames = if line.contains("from the first frame") { 1 } else { num("from ") as usize };
    (num("onset "), num("IRF "), frames)
}

/// A dim recording's instrument is searched on its frames of the first's scene, summed: the
/// same onset as the sum given as one frame, where a stack of other scenes (and a bright
/// frame) keeps the first frame's.
#[test]
fn a_dim_recording_sums_its_frames_for_the_instrument() {
    let d = tempdir();
    let d = d.path();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    std::fs::copy(root.join("zoo/lifetime-flim-designed/codes.json"), d.join("codes.json")).unwrap();
    ok(d, &["dataset", "flim", "--count", "12", "--size", "32x32", "--heterodyne", "8", "--seed", "4", "-o", "f"]);
    ok(d, &["export", "onnx", "--run", "zoo:lifetime-flim-evidence-fast", "-o", "fast.onnx"]);
    let sim_of = |cube: &str, signal: &str, seed: u64, out: &str| {
        let seed = seed.to_string();
        let args = ["simulate", "--codes", "codes.json", "--heterodyne", "8", "--irf", "physical", "--noise", "--cube", cube];
        ok(d, &[&args[..], &["--signal-fraction", signal, "--seed", &seed, "-o", out]].concat());
        read_npy(&d.join(out)).unwrap().into_dimensionality::<ndarray::Ix4>().unwrap()
    };
    let sim = |signal: &str, seed: u64, out: &str| sim_of("f/test/x_000.npy", signal, seed, out);
    // eight noisy frames of one scene, dim
    let frames: Vec<_> = (0..8).map(|s| sim("0.02", 10 + s, "y.npy").index_axis_move(ndarray::Axis(0), 0)).collect();
    let views: Vec<_> = frames.iter().map(|f| f.view()).collect();
    write_npy(&d.join("rec.npy"), &ndarray::stack(ndarray::Axis(0), &views).unwrap().view()).unwrap();
    let sum = frames.iter().skip(1).fold(frames[0].clone(), |a, b| a + b);
    write_npy(&d.join("sum.npy"), &sum.view()).unwrap();
    write_npy(&d.join("first.npy"), &frames[0].view()).unwrap();
    let infer =
        |m: &str, extra: &[&str]| ok(d, &[&["infer", "--model", "fast.onnx", "--measurements", m][..], extra, &["-o", "out"]].concat());
    for extra in [&[][..], &["--lifetime-fit"][..]] {
        let (onset, width, n) = instrument_of(&infer("rec.npy", extra));
        assert_eq!(n, 8, "{extra:?}: every frame of the scene summed");
        let (onset_sum, width_sum, one) = instrument_of(&infer("sum.npy", extra));
        assert_eq!(one, 1);
        assert!(
            (onset - onset_sum).abs() < 1e-3 && (width - width_sum).abs() < 1e-3,
            "{extra:?}: {onset} {width} against {onset_sum} {width_sum}"
        );
    }
    // the truth (the item's onset); the summed frames' onset is the nearer
    let truth = read_npy(&d.join("f/test/onset_000.npy")).unwrap()[[0, 0]] as f64 * 1e9;
    let (onset, _, _) = instrument_of(&infer("rec.npy", &["--lifetime-fit"]));
    let (onset_first, _, _) = instrument_of(&infer("first.npy", &["--lifetime-fit"]));
    println!("onset {onset:.3} ns from the recording, {onset_first:.3} from its first frame; the truth {truth:.3}");
    assert!((onset - truth).abs() < (onset_first - truth).abs(), "{onset} against {onset_first}, the truth {truth}");
    // frames of other scenes are not summed; nor is a bright frame's instrument
    let scenes = sim_of("f/train/x_000.npy", "0.02", 3, "scenes.npy");
    assert!(scenes.dim().0 > 1);
    assert_eq!(instrument_of(&infer("scenes.npy", &["--lifetime-fit"])).2, 1);
    sim("0.8", 3, "bright.npy");
    let bright = read_npy(&d.join("bright.npy")).unwrap();
    let b0 = bright.index_axis(ndarray::Axis(0), 0);
    let bright = ndarray::stack(ndarray::Axis(0), &[b0.view(), b0.view(), b0.view()]).unwrap();
    write_npy(&d.join("bright3.npy"), &bright.view()).unwrap();
    assert_eq!(instrument_of(&infer("bright3.npy", &["--lifetime-fit"])).2, 1);
}

/// `reconstruct` gives a lifetime network on the fit's evidence a known onset as `infer`
/// gives its exported graph one: the same lifetimes, and nearer the truth than at a wrong onset.
#[test]
fn a_known_onset_reaches_a_lifetime_network_in_reconstruct_as_in_infer() {
    let d = tempdir();
    let d = d.path();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    std::fs::copy(root.join("zoo/lifetime-flim-designed/codes.json"), d.join("codes.json")).unwrap();
    ok(d, &["dataset", "flim", "--count", "4", "--size", "32x32", "--heterodyne", "8", "--onset-ns", "30", "--seed", "4", "-o", "f"]);
    let args = ["simulate", "--codes", "codes.json", "--heterodyne", "8", "--irf", "physical", "--noise", "--cube", "f/test/x_000.npy"];
    ok(d, &[&args[..], &["--signal-fraction", "0.1", "--seed", "3", "-o", "y.npy"]].concat());
    let truth = read_npy(&d.join("f/test/lifetime_000.npy")).unwrap();
    let truth = truth.index_axis(ndarray::Axis(0), 0);
    let net = "zoo:lifetime-flim-evidence-fast";
    let lifetimes = |out: &str, onset: Option<&str>| {
        let mut args = vec!["reconstruct", net, "--measurements", "y.npy", "-o", out];
        args.extend(onset.map(|t| ["--onset-ns", t]).into_iter().flatten());
        ok(d, &args);
        read_npy(&d.join(out)).unwrap().index_axis_move(ndarray::Axis(0), 0).index_axis_move(ndarray::Axis(0), 0)
    };
    let mae = |est: &ndarray::ArrayD<f32>| {
        let errs: Vec<f64> =
            est.iter().zip(truth.iter()).filter(|(e, t)| e.is_finite() && t.is_finite()).map(|(e, t)| (e - t).abs() as f64).collect();
        assert!(errs.len() > 100, "{} lifetimes", errs.len());
        errs.iter().sum::<f64>() / errs.len() as f64 * 1e9
    };
    let (known, wrong, fitted) = (lifetimes("known.npy", Some("30")), lifetimes("wrong.npy", Some("34")), lifetimes("fitted.npy", None));
    let (m_known, m_wrong) = (mae(&known), mae(&wrong));
    println!("MAE {m_known:.3} ns at the true onset, {m_wrong:.3} at 4 ns late, {:.3} fitted", mae(&fitted));
    assert!(m_known < 0.5 * m_wrong, "{m_known} against {m_wrong}");
    assert!(known.iter().zip(fitted.iter()).any(|(a, b)| a != b), "the onset given changed nothing");
    // the exported graph with `infer --onset-ns`: the same lifetimes
    ok(d, &["export", "onnx", "--run", net, "-o", "fast.onnx"]);
    let out = ok(d, &["infer", "--model", "fast.onnx", "--measurements", "y.npy", "--onset-ns", "30", "-o", "out"]);
    assert!(out.contains("the onset given"), "{out}");
    let streamed = read_npy(&d.join("out/lifetime.npy")).unwrap();
    let streamed = streamed.index_axis(ndarray::Axis(0), 0);
    let off = known
        .iter()
        .zip(streamed.iter())
        .filter(|(a, b)| a.is_nan() != b.is_nan() || (a.is_finite() && (*a - *b).abs() > 1e-4 * b.abs()))
        .count();
    assert_eq!(off, 0, "{off} lifetimes differ between reconstruct and infer");
    // `eval --onset-ns`: the dataset's onset to the decoders that fit one (the fit, the network
    // on its evidence), the harmonics network decoding as without it
    let eval = |onset: &str, out: &str| -> Vec<f64> {
        let args = ["eval", "--dataset", "f", "--codes", "codes.json", "--heterodyne", "8", "--irf", "physical", "--light", "0.1"];
        let decoders = ["--decoder", "lifetime-fit", "--decoder", net, "--decoder", "zoo:lifetime-flim-designed"];
        let printed = ok(d, &[&args[..], &decoders, &["--seed", "3", "--onset-ns", onset, "-o", out]].concat());
        assert!(printed.contains(&format!("the onset given: {onset} ns")), "{printed}");
        let rows: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join(out)).unwrap()).unwrap();
        let rows = rows.as_array().unwrap();
        assert!(rows.iter().all(|r| (r["onset_given_s"].as_f64().unwrap() * 1e9 - onset.parse::<f64>().unwrap()).abs() < 1e-9));
        rows.iter().map(|r| r["lifetime_mae_s"].as_f64().unwrap() * 1e9).collect()
    };
    let (at_truth, late) = (eval("30", "e30.json"), eval("34", "e34.json"));
    println!("eval: MAE {at_truth:?} ns at the true onset, {late:?} at 4 ns late");
    assert!(at_truth[0] < 0.5 * late[0] && at_truth[1] < 0.5 * late[1], "{at_truth:?} against {late:?}");
    assert_eq!(at_truth[2], late[2], "the harmonics network fits no onset");
    let ds = ["eval", "--dataset", "f", "--codes", "codes.json", "--heterodyne", "8", "--decoder", "tval3"];
    fails(d, &[&ds[..], &["--onset-ns", "2000"]].concat(), &["--onset-ns"]);
}

#[test]
fn admm_net_export_with_the_matrix_as_input_and_eval_through_ort() {
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
            "2",
            "--channels",
            "2",
            "--epochs",
            "1",
            "--seed",
            "3",
            "-o",
            "run",
        ],
    );
    ok(d, &["export", "onnx", "--run", "run", "-o", "baked.onnx"]);
    ok(d, &["export", "onnx", "--run", "run", "--matrix-input", "-o", "input.onnx"]);
    ok(d, &["sensor", "matrix", "--codes", "codes.json", "-o", "A.npy"]);
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "ds/test/x_000.npy", "-o", "y.npy"]);
    ok(d, &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "burn.npy"]);
    let burn = read_npy(&d.join("burn.npy")).unwrap();
    let scale = burn.iter().fold(0f32, |m, v| m.max(v.abs()));
    for (model, extra) in [("baked.onnx", vec![]), ("input.onnx", vec!["--sensor-matrix", "A.npy"])] {
        let out_dir = format!("out-{model}");
        let mut args =
            vec!["infer", "--model", model, "--measurements", "y.npy", "--products", "cube,depth,peaks,lifetime", "-o", &out_dir];
        args.extend(extra.iter().copied());
        ok(d, &args);
        let cube = read_npy(&d.join(&out_dir).join("cube.npy")).unwrap();
        assert_eq!(cube.shape(), burn.shape());
        let diff = cube.iter().zip(burn.iter()).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff <= 1e-4 * scale, "{model}: ort differs from burn by {diff} (scale {scale})");
        assert_eq!(read_npy(&d.join(&out_dir).join("depth.npy")).unwrap().shape(), &[1, 2, 8, 8]);
        assert_eq!(read_npy(&d.join(&out_dir).join("lifetime.npy")).unwrap().shape(), &[1, 8, 8]);
    }
    let out = check_onnx(d, &["input.onnx", "--measurements", "y.npy", "--sensor-matrix", "A.npy", "--compare", "out-input.onnx"]);
    assert!(out.contains("ok  cube"), "{out}");
    // eval through the contract: the exported model next to the run it came from
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
            "onnx:baked.onnx",
            "-o",
            "rep.json",
        ],
    );
    let rep: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("rep.json")).unwrap()).unwrap();
    let (a, b) = (rep[0]["psnr_db"].as_f64().unwrap(), rep[1]["psnr_db"].as_f64().unwrap());
    assert!((a - b).abs() < 1e-3, "burn {a} dB vs ort {b} dB: {out}");
    // a sensor matrix of the wrong shape; a baked model given one
    let small = ndarray::Array3::<f32>::ones((4, 4, 4));
    write_npy(&d.join("A4.npy"), &small.view()).unwrap();
    fails(
        d,
        &["infer", "--model", "input.onnx", "--measurements", "y.npy", "--sensor-matrix", "A4.npy", "-o", "bad"],
        &["A4.npy", "[N, M, T]"],
    );
    fails(
        d,
        &["infer", "--model", "baked.onnx", "--measurements", "y.npy", "--sensor-matrix", "A.npy", "-o", "bad"],
        &["A.npy", "--matrix-input"],
    );
}

#[test]
fn a_missing_onnx_runtime_exits_2_with_the_install_hint() {
    let d = tempdir();
    let d = d.path();
    let o = bin()
        .current_dir(d)
        .env("ORT_DYLIB_PATH", d.join("nowhere.so"))
        .args(["infer", "--model", "m.onnx", "--measurements", "y.npy", "-o", "out"])
        .output()
        .unwrap();
    std::fs::write(d.join("m.onnx"), b"x").unwrap();
    let o2 = bin()
        .current_dir(d)
        .env("ORT_DYLIB_PATH", d.join("nowhere.so"))
        .args(["infer", "--model", "m.onnx", "--measurements", "y.npy", "-o", "out"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o2.stderr);
    assert_eq!(o.status.code(), Some(2));
    assert_eq!(o2.status.code(), Some(2), "{err}");
    assert!(err.contains("scripts/setup.sh") && err.contains("ORT_DYLIB_PATH") && !err.contains("panicked"), "{err}");
    assert!(!d.join("out").exists());
}

#[test]
fn export_and_bench_infer_bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    fails(d, &["export", "onnx", "--run", "nowhere", "-o", "m.onnx"], &["nowhere", "config.json"]);
    let fx = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1");
    std::fs::create_dir_all(d.join("broken")).unwrap();
    for f in ["config.json", "codes.json"] {
        std::fs::copy(fx.join(f), d.join("broken").join(f)).unwrap();
    }
    fails(d, &["export", "onnx", "--run", "broken", "-o", "m.onnx"], &["model.bpk", "no trained weights"]);
    assert!(!d.join("m.onnx").exists());
    fails(d, &["bench", "infer", "--decoder", "magic", "--size", "8x8"], &["--decoder", "unet, admm-net or lifetime"]);
    fails(d, &["bench", "infer", "--decoder", "unet", "--size", "8x8", "--ort-threads", "0"], &["--ort-threads"]);
    fails(d, &["bench", "infer", "--decoder", "unet", "--size", "6x6", "--reps", "1"], &["--size 6x6", "multiples of 4x4"]);
}

/// `export onnx --from-taps` of the zoo's U-Net on the range fit's evidence: one graph from
/// the tap images, which onnx's full checker passes and onnxruntime-Python runs with the file
/// alone, giving what `tcsense infer` writes by default (the graph refines its ranges itself;
/// NaN where no return, in the same pixels); other models are refused with exit status 2 and
/// no file.
#[test]
fn an_evidence_unet_exports_as_one_graph_from_the_taps() {
    let d = tempdir();
    let d = d.path();
    let codes = Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo/unet-lidar-evidence-8k/codes.json");
    let codes = codes.to_str().unwrap();
    ok(d, &["dataset", "lidar", "--count", "1", "--size", "16x16", "--seed", "2", "-o", "ds"]);
    ok(d, &["simulate", "--codes", codes, "--irf", "physical", "--cube", "ds/train/x_000.npy", "--noise", "--seed", "1", "-o", "y.npy"]);
    let out = ok(d, &["export", "onnx", "--run", "zoo:unet-lidar-evidence-8k", "--from-taps", "-o", "taps.onnx"]);
    assert!(out.contains("one graph from the taps"), "{out}");
    ok(d, &["infer", "--model", "taps.onnx", "--measurements", "y.npy", "-o", "out"]);
    let depth = read_npy(&d.join("out/depth.npy")).unwrap();
    assert_eq!(depth.shape(), &[1, 1, 16, 16], "one frame, one return");
    assert!(depth.iter().filter(|v| v.is_finite()).count() > 128, "returns on most pixels");
    let check = check_onnx(d, &["taps.onnx", "--measurements", "y.npy", "--compare", "out"]);
    assert!(check.contains("inputs ['measurements']") && check.contains("ok  depth") && check.contains("ok  confidence"), "{check}");
    fails(
        d,
        &["export", "onnx", "--run", "zoo:unet-lidar-designed", "--from-taps", "-o", "bad.onnx"],
        &["--from-taps", "range fit's evidence"],
    );
    assert!(!d.join("bad.onnx").exists());
    // eval's onnx-raw decoder: the graph's own product; a missing model or none named is refused
    let report = ok(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--split",
            "train",
            "--items",
            "1",
            "--codes",
            codes,
            "--irf",
            "physical",
            "--decoder",
            "onnx-raw:taps.onnx",
            "-o",
            "raw.json",
        ],
    );
    assert!(report.contains("onnx-raw:taps.onnx"), "{report}");
    fails(
        d,
        &[
            "eval",
            "--dataset",
            "ds",
            "--split",
            "train",
            "--items",
            "1",
            "--codes",
            codes,
            "--decoder",
            "onnx-raw:nope.onnx",
            "-o",
            "bad.json",
        ],
        &["nope.onnx", "no such file"],
    );
    fails(
        d,
        &["eval", "--dataset", "ds", "--split", "train", "--items", "1", "--codes", codes, "--decoder", "onnx-raw", "-o", "bad.json"],
        &["onnx-raw:MODEL.onnx"],
    );
    assert!(!d.join("bad.json").exists());
}
