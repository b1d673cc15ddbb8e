//! The wave-4 commands under bad input (`codes analyze|select|export|import`, `reconstruct
//! depth-fit|lifetime-fit`, `infer --depth-fit|--lifetime-fit`, `simulate --sweep`, `calibrate`,
//! `bringup`, the demo): every number bounded before anything is allocated, every output
//! exclusive and written whole, every resume checked against what its steps were made from,
//! every field of a format honoured or refused, and messages that name the flag. Each case
//! exits with status 2, names what was wrong, does not panic and leaves the working directory
//! as it was; the paths that must work are checked to give the right values.

mod common;
use common::*;
use ndarray::{Array3, Array4};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tcsense_sensor::npy::{read_npy, write_npy};

const CORPUS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/corpus");

/// Every file under `dir` with its bytes (directories as `None`).
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, Option<Vec<u8>>> {
    fn walk(d: &Path, root: &Path, out: &mut BTreeMap<PathBuf, Option<Vec<u8>>>) {
        for e in std::fs::read_dir(d).unwrap() {
            let e = e.unwrap();
            let rel = e.path().strip_prefix(root).unwrap().to_path_buf();
            if e.file_type().unwrap().is_dir() {
                out.insert(rel, None);
                walk(&e.path(), root, out);
            } else {
                out.insert(rel, Some(std::fs::read(e.path()).unwrap()));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// Runs refusals and collects every one that went wrong, so that one run lists them all.
struct Probe {
    dir: PathBuf,
    cases: usize,
    failures: Vec<String>,
}

impl Probe {
    /// `tcsense args` must exit 2 with every needle in its message (each message saying an OS
    /// error once), no panic, and no change to the working directory.
    fn refuse(&mut self, args: &[&str], needles: &[&str]) {
        self.cases += 1;
        let before = snapshot(&self.dir);
        let o = run(&self.dir, args);
        let err = String::from_utf8_lossy(&o.stderr).into_owned();
        let mut problems = Vec::new();
        if o.status.code() != Some(2) {
            problems.push(format!("exit {:?}", o.status.code()));
        }
        if err.contains("panicked") {
            problems.push("panicked".into());
        }
        for n in needles {
            if !err.contains(n) {
                problems.push(format!("message lacks {n:?}"));
            }
        }
        if err.matches("(os error").count() > 1 {
            problems.push("an OS error said twice".into());
        }
        let after = snapshot(&self.dir);
        if before != after {
            let changed: Vec<_> = after.keys().chain(before.keys()).filter(|k| before.get(*k) != after.get(*k)).collect();
            problems.push(format!("changed the working directory: {changed:?}"));
        }
        if !problems.is_empty() {
            self.failures.push(format!("tcsense {}: {}; stderr: {}", args.join(" "), problems.join(", "), err.trim()));
        }
    }

    fn finish(self, what: &str) {
        eprintln!("{what}: {} cases", self.cases);
        assert!(
            self.failures.is_empty(),
            "{} of {} {what} cases went wrong:\n{}",
            self.failures.len(),
            self.cases,
            self.failures.join("\n")
        );
    }
}

/// A working directory with the fixture's codes (L = 8) and the zoo's designed LiDAR codes
/// (L = 32, no alias), taps of both, a cube, a tiny sweep, and ONNX models: the fixture's
/// ADMM-Net (`m.onnx`, a cube model) and the zoo's designed U-Net (`unet.onnx`).
fn setup() -> (tempfile::TempDir, Probe) {
    let t = tempdir();
    let d = t.path().to_path_buf();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let fixture = root.join("tests/fixtures/admm-net-run-v1");
    std::fs::copy(fixture.join("codes.json"), d.join("codes.json")).unwrap();
    std::fs::copy(fixture.join("y.npy"), d.join("y.npy")).unwrap();
    std::fs::copy(root.join("zoo/admm-lidar-designed/codes.json"), d.join("dcodes.json")).unwrap();
    write_npy(&d.join("x.npy"), &Array3::<f32>::from_elem((8, 8, 8), 0.5).view()).unwrap();
    // a LiDAR frame through the designed codes: one surface at bin 11.3
    let mut x = Array3::<f32>::zeros((32, 16, 16));
    for r in 0..16 {
        for c in 0..16 {
            x[(11, r, c)] = 0.7;
            x[(12, r, c)] = 0.3;
        }
    }
    write_npy(&d.join("x32.npy"), &x.view()).unwrap();
    ok(&d, &["simulate", "--codes", "dcodes.json", "--irf", "physical", "--cube", "x32.npy", "-o", "y32.npy"]);
    let y = read_npy(&d.join("y32.npy")).unwrap();
    let stack = ndarray::stack(ndarray::Axis(0), &[y.view(), y.view(), y.view()]).unwrap();
    write_npy(&d.join("stack3.npy"), &stack.view()).unwrap();
    write_npy(&d.join("stack2.npy"), &stack.slice(ndarray::s![..2, .., .., ..]).view()).unwrap();
    write_npy(&d.join("empty.npy"), &Array4::<f32>::zeros((0, 4, 16, 16)).view()).unwrap();
    ok(&d, &["export", "onnx", "--run", &fixture.display().to_string(), "-o", "m.onnx"]);
    ok(&d, &["export", "onnx", "--run", "zoo:admm-lidar-designed", "-o", "admm.onnx"]);
    ok(&d, &["export", "onnx", "--run", "zoo:unet-lidar-designed", "-o", "unet.onnx"]);
    ok(&d, &["simulate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "--size", "8x8", "--average", "2"]);
    (t, Probe { dir: d, cases: 0, failures: Vec::new() })
}

#[test]
fn absurd_numbers_are_refused_before_anything_is_allocated() {
    let (_t, mut p) = setup();
    let fit = |extra: &[&'static str]| -> Vec<&'static str> {
        let mut a =
            vec!["reconstruct", "depth-fit", "--codes", "dcodes.json", "--irf", "physical", "--measurements", "y32.npy", "-o", "d.npy"];
        a.extend(extra);
        a
    };
    // every command that builds an IRF, and from a model's metadata (range-checked, no overflow)
    p.refuse(&["codes", "analyze", "dcodes.json", "--laser-fwhm-ns", "1e20"], &["laser_fwhm", "1 µs"]);
    p.refuse(&["codes", "analyze", "dcodes.json", "--tap-tau-ns", "1e20"], &["tap_tau", "1 µs"]);
    p.refuse(
        &["sensor", "matrix", "--codes", "dcodes.json", "--irf", "physical", "--laser-fwhm-ns", "1e300", "-o", "A.npy"],
        &["laser_fwhm"],
    );
    p.refuse(&fit(&["--laser-fwhm-ns", "inf"]), &["laser_fwhm"]);
    p.refuse(&["lifetime", "x.npy", "--length", "8", "--irf-fwhm-ns", "1e20", "-o", "t.npy"], &["--irf-fwhm-ns"]);
    // counts and sizes
    p.refuse(
        &["codes", "select", "--criterion", "range", "--candidates", "1000000000000", "--tap-constraint", "-o", "s.json"],
        &["--candidates", "1000000"],
    );
    p.refuse(&["codes", "select", "--criterion", "range", "--search", "100000000000", "--tap-constraint", "-o", "s.json"], &["--search"]);
    p.refuse(&fit(&["--window", "1000001"]), &["window 1000001", "63"]);
    p.refuse(&fit(&["--window", "18446744073709551615"]), &["window 18446744073709551615"]);
    p.refuse(
        &[
            "reconstruct",
            "lifetime-fit",
            "--codes",
            "codes.json",
            "--heterodyne",
            "8",
            "--measurements",
            "y.npy",
            "--window",
            "1000001",
            "-o",
            "t.npy",
        ],
        &["window", "63"],
    );
    p.refuse(&["simulate", "--codes", "dcodes.json", "--sweep", "sw", "--size", "1000000000000x2"], &["--size", "65536"]);
    p.refuse(&["simulate", "--codes", "dcodes.json", "--sweep", "sw", "--size", "60000x60000"], &["GiB"]);
    p.refuse(&["simulate", "--codes", "dcodes.json", "--sweep", "sw", "--size", "8x8", "--average", "100000000"], &["--average"]);
    // times that mean nothing
    for flag in ["--gate-skew-ns", "--shift-ns"] {
        p.refuse(
            &["simulate", "--codes", "dcodes.json", "--sweep", "sw", "--size", "8x8", flag, "1e30"],
            &[&flag[2..flag.len() - 3].replace('-', "_")],
        );
    }
    p.refuse(
        &["simulate", "--codes", "dcodes.json", "--cube", "x32.npy", "--tail", "0.2", "--tail-tau-ns", "1e30", "-o", "yy.npy"],
        &["tail_tau"],
    );
    p.refuse(
        &[
            "reconstruct",
            "lifetime-fit",
            "--codes",
            "codes.json",
            "--heterodyne",
            "8",
            "--measurements",
            "y.npy",
            "--onset-ns",
            "1e30",
            "-o",
            "t.npy",
        ],
        &["onset", "1 µs"],
    );
    p.refuse(
        &["infer", "--model", "m.onnx", "--measurements", "y.npy", "--lifetime-fit", "--onset-ns", "1e30", "-o", "out"],
        &["onset", "1 µs"],
    );
    // the neighbourhood pooled by likeness: an odd multiple of the window, bounded
    for side in ["11", "12", "100000"] {
        p.refuse(
            &["infer", "--model", "m.onnx", "--measurements", "y.npy", "--lifetime-fit", "--pool-like", side, "-o", "out"],
            &["--pool-like"],
        );
    }
    p.refuse(&["infer", "--model", "m.onnx", "--measurements", "y.npy", "--pool-like", "15", "-o", "out"], &["--lifetime-fit"]);
    for name in ["lifetime-fit-pooled:4", "lifetime-fit-pooled:x", "lifetime-fit-pooled:99999999999999999999"] {
        p.refuse(
            &["reconstruct", name, "--codes", "codes.json", "--heterodyne", "8", "--measurements", "y.npy", "-o", "t.npy"],
            &["lifetime-fit-pooled:N", "odd multiple"],
        );
    }
    // the instrument's superpixels: bounded
    p.refuse(
        &["train", "lifetime", "--input", "costs", "--dataset", "nods", "--codes", "dcodes.json", "--instrument-blocks", "65", "-o", "r"],
        &["--instrument-blocks"],
    );
    // threads, budgets, scenes, epochs
    p.refuse(&["--threads", "100000", "zoo", "list"], &["--threads", "256"]);
    p.refuse(&["--threads", "0", "zoo", "list"], &["--threads"]);
    p.refuse(&["infer", "--model", "m.onnx", "--measurements", "y.npy", "--ort-threads", "1000", "-o", "out"], &["--ort-threads", "256"]);
    let bringup = |flag: &'static str, v: &'static str| -> Vec<&'static str> {
        vec!["bringup", "--sweep", "sweep", "--codes", "codes.json", "--decoder", "admm-lidar-designed", flag, v, "-o", "bu"]
    };
    p.refuse(&bringup("--budget-minutes", "inf"), &["--budget-minutes"]);
    p.refuse(&bringup("--budget-minutes", "NaN"), &["--budget-minutes"]);
    p.refuse(&bringup("--scenes", "1000000000000"), &["--scenes"]);
    p.refuse(&bringup("--epochs", "0"), &["--epochs"]);
    p.refuse(&bringup("--check-items", "0"), &["--check-items"]);
    p.refuse(&bringup("--size", "100000x100000"), &["--size"]);
    // the older commands' counts (found by scripts/probe_numbers.py --all)
    p.refuse(&["depth", "x.npy", "--length", "8", "--peaks", "18446744073709551615", "-o", "d.npy"], &["--peaks", "16"]);
    p.refuse(&["sweep", "constraints", "--dataset", "nods", "--candidates", "99999999999", "-o", "swc"], &["--candidates"]);
    p.refuse(&["bench", "range-fit", "--size", "8x8", "--frames", "99999999999"], &["--frames"]);
    p.refuse(&["demo", "--quick", "--budget-minutes", "1e308", "-o", "demo"], &["--budget-minutes"]);
    p.refuse(&["demo", "--quick", "--scenes", "18446744073709551615", "-o", "demo"], &["--scenes"]);
    p.refuse(
        &["train", "unet", "--dataset", "nods", "--codes", "dcodes.json", "--returns", "18446744073709551615", "-o", "r"],
        &["--returns"],
    );
    // found by scripts/probe_numbers.py --flim: a clock of 1e-300 MHz, settings of TVAL3 that
    // the closed-form criteria do not use, a tail's time constant without a tail
    p.refuse(&["dataset", "flim", "--count", "2", "--size", "8x8", "--clock-mhz", "1e-300", "-o", "df"], &["clock_hz", "1 MHz"]);
    p.refuse(
        &[
            "codes",
            "select",
            "--criterion",
            "range",
            "--tap-constraint",
            "--candidates",
            "4",
            "--search",
            "4",
            "--mu",
            "NaN",
            "-o",
            "s.json",
        ],
        &["mu", "NaN"],
    );
    p.refuse(&["simulate", "--codes", "dcodes.json", "--cube", "x32.npy", "--tail-tau-ns", "NaN", "-o", "yy.npy"], &["tail_tau"]);
    // values that mean nothing
    p.refuse(
        &["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--products", "ply", "--fov", "NaN", "-o", "out"],
        &["--fov"],
    );
    p.refuse(&fit(&["--ply", "c.ply", "--fov", "NaN"]), &["--fov"]);
    p.refuse(&["depth", "x.npy", "--length", "8", "--ply", "c.ply", "--fov", "1e9", "-o", "d.npy"], &["--fov"]);
    // finite but past any sensor: each was taken and gave NaN, infinite or zero output
    let sim = |flag: &'static str, v: &'static str| -> Vec<&'static str> {
        vec!["simulate", "--codes", "dcodes.json", "--cube", "x32.npy", "--noise", flag, v, "-o", "yy.npy"]
    };
    p.refuse(&sim("--full-well", "1e308"), &["full_well", "up to 1e12"]);
    p.refuse(&sim("--read-noise", "1e300"), &["read_noise", "up to the full well"]);
    p.refuse(&sim("--electrons-per-unit", "1e308"), &["electrons_per_unit", "up to 1e12"]);
    p.refuse(&["dataset", "lidar", "--count", "2", "--size", "8x8", "--ambient", "1e308", "-o", "dl"], &["ambient", "up to 1000"]);
    for flag in ["--photons", "--ambient", "--read-noise"] {
        p.refuse(&["codes", "analyze", "dcodes.json", flag, "1e308"], &[flag, "up to 1e9"]);
    }
    p.refuse(&["codes", "analyze", "dcodes.json", "--alias-threshold", "1e308"], &["--alias-threshold", "[0, 1.414]"]);
    p.refuse(&["lifetime", "x.npy", "--length", "8", "--clock-mhz", "inf", "-o", "t.npy"], &["--clock-mhz", "10000"]);
    p.refuse(&["lifetime", "x.npy", "--bin-width-ps", "1e308", "-o", "t.npy"], &["--bin-width-ps"]);
    p.refuse(&["depth", "x.npy", "--length", "8", "--min-rel", "NaN", "-o", "d.npy"], &["--min-rel"]);
    // finite values whose sums overflow f32: a cube gave infinite taps, tap images NaN maps
    write_npy(&p.dir.join("huge_x.npy"), &Array3::<f32>::from_elem((32, 16, 16), 3e38).view()).unwrap();
    write_npy(&p.dir.join("huge_y.npy"), &Array3::<f32>::from_elem((4, 16, 16), 1e35).view()).unwrap();
    p.refuse(&["simulate", "--codes", "dcodes.json", "--irf", "physical", "--cube", "huge_x.npy", "-o", "yy.npy"], &["huge_x.npy", "1e30"]);
    p.refuse(&fit(&[]).iter().map(|a| if *a == "y32.npy" { "huge_y.npy" } else { a }).collect::<Vec<_>>(), &["huge_y.npy", "1e30"]);
    p.refuse(&["infer", "--model", "unet.onnx", "--measurements", "huge_y.npy", "-o", "out"], &["huge_y.npy", "1e30"]);
    p.finish("absurd numbers");
}

#[test]
fn contradictions_and_messages() {
    let (_t, mut p) = setup();
    // contradictory flags
    p.refuse(
        &["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--depth-fit", "--no-range-fit", "-o", "out"],
        &["--no-range-fit", "--depth-fit"],
    );
    p.refuse(
        &["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--returns", "5", "-o", "out"],
        &["--returns 5", "2 return(s)"],
    );
    p.refuse(
        &["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "--depth-fit", "--returns", "3", "-o", "out"],
        &["--returns 3"],
    );
    p.refuse(&["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "--no-range-fit", "-o", "out"], &["--no-range-fit"]);
    // a decoder that brings its own sensor refuses the flags of another, rather than ignore them
    for flag in [["--irf", "physical"], ["--laser-fwhm-ns", "1.5"], ["--tap-tau-ns", "0.5"], ["--oversample", "2"]] {
        let mut args = vec!["reconstruct", "admm-net", "--run", "zoo:admm-lidar-designed", "--measurements", "y32.npy", "-o", "d.npy"];
        args.extend(flag);
        p.refuse(&args, &[flag[0], "brings its own sensor", "--calibration"]);
    }
    // the lifetime fit's settings are refused by decoders that do not take them, rather than
    // ignored; a known onset is refused by every decoder that fits none
    for (decoder, flag) in [
        ("zoo:admm-lidar-designed", ["--window", "5"]),
        ("zoo:admm-lidar-designed", ["--tau-ns", "1,2"]),
        ("zoo:admm-lidar-designed", ["--min-intensity", "0.1"]),
        ("depth-fit", ["--tau-ns", "1,2"]),
    ] {
        let mut args = vec!["reconstruct", decoder, "--measurements", "y32.npy", "-o", "d.npy"];
        if decoder == "depth-fit" {
            args.extend(["--codes", "dcodes.json"]);
        }
        args.extend(flag);
        p.refuse(&args, &[flag[0], "lifetime-fit", decoder]);
    }
    p.refuse(
        &["reconstruct", "zoo:admm-lidar-designed", "--no-background", "--measurements", "y32.npy", "-o", "d.npy"],
        &["--no-background"],
    );
    p.refuse(
        &["reconstruct", "depth-fit", "--codes", "dcodes.json", "--onset-ns", "3", "--measurements", "y32.npy", "-o", "d.npy"],
        &["--onset-ns", "depth-fit fits no onset"],
    );
    p.refuse(
        &["reconstruct", "zoo:admm-lidar-designed", "--onset-ns", "3", "--measurements", "y32.npy", "-o", "d.npy"],
        &["onset", "ADMM-Net"],
    );
    p.refuse(
        &["infer", "--model", "admm.onnx", "--measurements", "stack2.npy", "--depth-fit", "--lifetime-fit", "-o", "out"],
        &["--depth-fit", "--lifetime-fit"],
    );
    // a fit that does not suit the model is refused for what it is, not by a product list
    for products in [None, Some("lifetime"), Some("depth")] {
        let mut args = vec!["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--lifetime-fit", "-o", "out"];
        if let Some(l) = products {
            args.extend(["--products", l]);
        }
        p.cases += 1;
        let o = run(&p.dir, &args);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{err}");
        assert!(err.contains("--lifetime-fit") && err.contains("depth model") && !err.contains("ask for"), "{args:?}: {err}");
    }
    // the fits' settings name the setting, not a dump of the options
    for args in [
        vec![
            "reconstruct",
            "depth-fit",
            "--codes",
            "dcodes.json",
            "--irf",
            "physical",
            "--measurements",
            "y32.npy",
            "--window",
            "4",
            "-o",
            "d.npy",
        ],
        vec!["infer", "--model", "m.onnx", "--measurements", "y.npy", "--lifetime-fit", "--onset-ns", "1e9", "-o", "out"],
    ] {
        p.cases += 1;
        let err = String::from_utf8_lossy(&run(&p.dir, &args).stderr).into_owned();
        assert!(!err.contains("Options {") && !err.contains("{ "), "{args:?}: {err}");
    }
    // an empty stack; a code memory whose ECLEN would underflow; an OS error said once
    p.refuse(&["infer", "--model", "admm.onnx", "--measurements", "empty.npy", "-o", "out"], &["empty.npy", "no tap image"]);
    p.refuse(&["codes", "show", "nofile.json", "-o", "c.png"], &["nofile.json", "No such file"]);
    p.refuse(&["infer", "--model", "nomodel.onnx", "--measurements", "y.npy", "-o", "out"], &["nomodel.onnx"]);
    p.finish("contradictions and messages");
}

#[test]
fn outputs_are_exclusive_whole_and_never_left_behind() {
    let (_t, mut p) = setup();
    let d = p.dir.clone();
    std::fs::create_dir(d.join("adir")).unwrap();
    std::fs::write(d.join("afile"), b"a file").unwrap();
    let fit = ["reconstruct", "depth-fit", "--codes", "dcodes.json", "--irf", "physical", "--measurements", "y32.npy"];
    let with = |extra: &[&'static str]| -> Vec<&'static str> { fit.iter().copied().chain(extra.iter().copied()).collect() };
    // a refused --ply leaves no depth map or confidence behind
    p.refuse(&with(&["-o", "d.npy", "--ply", "adir"]), &["adir", "--ply", "directory"]);
    p.refuse(&with(&["-o", "d.npy", "--png", "afile/x.png"]), &["afile", "not a directory"]);
    // two flags naming one file
    p.refuse(&with(&["-o", "same.npy", "--ply", "same.npy"]), &["same.npy", "-o", "--ply"]);
    p.refuse(&with(&["-o", "d.npy", "--png", "./d.confidence.npy"]), &["d.confidence.npy"]);
    p.refuse(&["depth", "x.npy", "--length", "8", "-o", "s.npy", "--png", "s.npy"], &["s.npy", "named by both"]);
    p.refuse(&["lifetime", "x.npy", "--length", "8", "-o", "t.npy", "--phasor", "t.npy"], &["t.npy", "--phasor"]);
    // an infer refusal leaves no output directory
    p.refuse(&["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--products", "cube", "-o", "out"], &["--products"]);
    // … and so does a stream that fails midway (its second frame of another size)
    std::fs::create_dir(d.join("frames")).unwrap();
    std::fs::copy(d.join("y32.npy"), d.join("frames/f0.npy")).unwrap();
    write_npy(&d.join("frames/f1.npy"), &Array3::<f32>::ones((4, 8, 8)).view()).unwrap();
    p.refuse(&["infer", "--model", "admm.onnx", "--measurements", "frames", "-o", "out"], &["f1.npy"]);
    // an output directory holding other files is not replaced
    std::fs::write(d.join("adir/notes.txt"), b"mine").unwrap();
    p.refuse(&["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "-o", "adir"], &["adir", "notes.txt"]);
    p.refuse(&["codes", "export", "dcodes.json", "-o", "adir"], &["adir", "notes.txt"]);
    p.refuse(&["simulate", "--codes", "dcodes.json", "--sweep", "adir", "--size", "8x8", "--average", "2"], &["adir", "notes.txt"]);
    p.finish("exclusive outputs");

    // the paths that work: outputs appear together, and a rerun replaces a directory whole
    let out = ok(&d, &with(&["-o", "d.npy", "--ply", "d.ply", "--png", "d.png"]));
    for f in ["d.npy", "d.confidence.npy", "d.ply", "d.png"] {
        assert!(d.join(f).is_file(), "{f} missing: {out}");
    }
    assert!(std::fs::read_dir(&d).unwrap().all(|e| !e.unwrap().file_name().to_string_lossy().starts_with('.')), "a staged file remains");
    ok(&d, &["infer", "--model", "unet.onnx", "--measurements", "stack3.npy", "--products", "depth,ply", "-o", "o"]);
    assert_eq!(std::fs::read_dir(d.join("o/ply")).unwrap().count(), 3);
    ok(&d, &["infer", "--model", "unet.onnx", "--measurements", "stack2.npy", "--products", "ply", "-o", "o"]);
    let mut names: Vec<String> =
        std::fs::read_dir(d.join("o")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names, ["ply"], "the earlier run's depth.npy and confidence.npy are gone");
    assert_eq!(std::fs::read_dir(d.join("o/ply")).unwrap().count(), 2, "the earlier run's third frame is gone");
    ok(&d, &["codes", "export", "dcodes.json", "-o", "mem"]);
    assert_eq!(std::fs::read_dir(d.join("mem")).unwrap().count(), 18);
    ok(&d, &["codes", "generate", "--taps", "2", "--block", "1x1", "--length", "8", "--seed", "1", "-o", "small.json"]);
    ok(&d, &["codes", "export", "small.json", "--force", "-o", "mem"]);
    let mut names: Vec<String> =
        std::fs::read_dir(d.join("mem")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names, ["ch00.bin", "ch01.bin", "codes.bin", "registers.json"], "no channel file of the first export remains");
}

/// `infer --depth-fit` on a cube model (a documented path that panicked) gives the ranges
/// `reconstruct depth-fit` gives, without running the network.
#[test]
fn depth_fit_through_a_cube_model_equals_the_fit() {
    let t = tempdir();
    let d = t.path();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    std::fs::copy(root.join("zoo/admm-lidar-designed/codes.json"), d.join("dcodes.json")).unwrap();
    // four surfaces, one per 8×8 quadrant, at bins 7, 8, 9 and 10
    let quadrant_bin = |r: usize, c: usize| 7 + 2 * (r / 8) + c / 8;
    let mut x = Array3::<f32>::zeros((32, 16, 16));
    for r in 0..16 {
        for c in 0..16 {
            x[(quadrant_bin(r, c), r, c)] = 1.0;
        }
    }
    write_npy(&d.join("x.npy"), &x.view()).unwrap();
    ok(d, &["simulate", "--codes", "dcodes.json", "--irf", "physical", "--cube", "x.npy", "-o", "y.npy"]);
    ok(d, &["export", "onnx", "--run", "zoo:admm-lidar-designed", "-o", "admm.onnx"]);
    ok(d, &["infer", "--model", "admm.onnx", "--measurements", "y.npy", "--products", "depth", "--depth-fit", "-o", "out"]);
    ok(d, &["reconstruct", "depth-fit", "--codes", "dcodes.json", "--irf", "physical", "--measurements", "y.npy", "-o", "fit.npy"]);
    let (a, b) = (read_npy(&d.join("out/depth.npy")).unwrap(), read_npy(&d.join("fit.npy")).unwrap());
    assert_eq!(a.shape(), b.shape());
    let first = a.index_axis(ndarray::Axis(0), 0);
    assert_eq!(first.iter().filter(|v| v.is_finite()).count(), 256, "every pixel has a first return");
    for (u, v) in a.iter().zip(b.iter()) {
        assert!((u.is_nan() && v.is_nan()) || (u - v).abs() < 1e-4, "{u} vs {v}");
    }
    // away from the quadrants' edges (the fit's window straddles them), each surface's range:
    // the centre of its bin, (j + ½)·c/(2·607 MHz)
    let bin_m = 299_792_458.0 / 607e6 / 2.0;
    for r in (0..16).filter(|r| !(6..10).contains(r)) {
        for c in (0..16).filter(|c| !(6..10).contains(c)) {
            let want = (quadrant_bin(r, c) as f64 + 0.5) * bin_m;
            assert!((first[[r, c]] as f64 - want).abs() < 0.1 * bin_m, "({r}, {c}): {} vs {want}", first[[r, c]]);
        }
    }
}

/// Every field of `registers.json` and `sweep.json` is honoured or refused: each corpus variant
/// is refused by every reader, naming the file.
#[test]
fn registers_and_sweep_corpus() {
    let (_t, mut p) = setup();
    let d = p.dir.clone();
    ok(&d, &["codes", "export", "codes.json", "--force", "-o", "mem"]);
    let good = std::fs::read(d.join("mem/registers.json")).unwrap();
    let mut variants: Vec<PathBuf> = std::fs::read_dir(Path::new(CORPUS).join("registers")).unwrap().map(|e| e.unwrap().path()).collect();
    variants.sort();
    assert!(variants.len() >= 15);
    for v in &variants {
        std::fs::write(d.join("mem/registers.json"), std::fs::read(v).unwrap()).unwrap();
        p.refuse(&["codes", "import", "mem", "-o", "back.json"], &["mem/registers.json"]);
    }
    // the image's bytes: one byte after the last channel; a channel file that disagrees
    std::fs::write(d.join("mem/registers.json"), &good).unwrap();
    let image = std::fs::read(d.join("mem/codes.bin")).unwrap();
    std::fs::write(d.join("mem/codes.bin"), [image.as_slice(), &[0]].concat()).unwrap();
    p.refuse(&["codes", "import", "mem", "-o", "back.json"], &["mem/codes.bin", "nothing after the last channel"]);
    std::fs::write(d.join("mem/codes.bin"), &image).unwrap();
    // an imported code memory is one `codes check` accepts, bit for bit the exported codes
    ok(&d, &["codes", "import", "mem", "-o", "back.json"]);
    let (a, b) = (tcsense_sensor::Codes::load(&d.join("back.json")).unwrap(), tcsense_sensor::Codes::load(&d.join("codes.json")).unwrap());
    assert_eq!(a.digest(), b.digest());
    std::fs::remove_file(d.join("back.json")).unwrap();

    let good = std::fs::read(d.join("sweep/sweep.json")).unwrap();
    let mut variants: Vec<PathBuf> = std::fs::read_dir(Path::new(CORPUS).join("sweep")).unwrap().map(|e| e.unwrap().path()).collect();
    variants.sort();
    assert!(variants.len() >= 12);
    for v in &variants {
        std::fs::write(d.join("sweep/sweep.json"), std::fs::read(v).unwrap()).unwrap();
        let name = v.file_name().unwrap().to_string_lossy().into_owned();
        let needle = if name == "missing-frames.json" { "sweep/nothing.npy" } else { "sweep/sweep.json" };
        p.refuse(&["calibrate", "--codes", "codes.json", "--irf", "physical", "--sweep", "sweep", "-o", "cal"], &[needle]);
        p.refuse(
            &["bringup", "--sweep", "sweep", "--codes", "codes.json", "--decoder", "admm-lidar-designed", "--epochs", "1", "-o", "bu"],
            &[needle],
        );
    }
    std::fs::write(d.join("sweep/sweep.json"), &good).unwrap();
    p.finish("registers and sweep corpus");
}

/// A resumed bring-up checks what its steps were made from: another sweep, seed, size or
/// epochs is refused with the difference named, and the same inputs resume.
#[test]
fn resumes_check_their_inputs() {
    let (_t, mut p) = setup();
    let d = p.dir.clone();
    let zoo_codes = Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo/admm-lidar-designed/codes.json");
    std::fs::copy(zoo_codes, d.join("codes32.json")).unwrap();
    ok(
        &d,
        &[
            "simulate",
            "--codes",
            "codes32.json",
            "--irf",
            "physical",
            "--sweep",
            "s1",
            "--size",
            "8x8",
            "--average",
            "2",
            "--tap-gain",
            "0.05",
            "--sensor-seed",
            "1",
        ],
    );
    ok(
        &d,
        &[
            "simulate",
            "--codes",
            "codes32.json",
            "--irf",
            "physical",
            "--sweep",
            "s2",
            "--size",
            "8x8",
            "--average",
            "2",
            "--tap-gain",
            "0.05",
            "--sensor-seed",
            "2",
        ],
    );
    let base = [
        "bringup",
        "--codes",
        "codes32.json",
        "--decoder",
        "admm-lidar-designed",
        "--scenes",
        "4",
        "--size",
        "8x8",
        "--check-items",
        "1",
        "-o",
        "bu",
    ];
    let args = |sweep: &'static str, extra: &[&'static str]| -> Vec<&'static str> {
        base.iter().copied().chain(["--sweep", sweep]).chain(extra.iter().copied()).collect()
    };
    ok(&d, &args("s1", &["--epochs", "1"]));
    p.refuse(&args("s2", &["--epochs", "1"]), &["bu", "other inputs", "sweep:"]);
    p.refuse(&args("s1", &["--epochs", "2"]), &["epochs: 1 then, 2 now"]);
    p.refuse(&args("s1", &["--epochs", "1", "--seed", "9"]), &["seed: 1 then, 9 now"]);
    p.refuse(&args("s1", &["--epochs", "1", "--irf", "ideal"]), &["irf:", "\"Ideal\" now"]);
    let again = ok(&d, &args("s1", &["--epochs", "1"]));
    assert_eq!(again.matches("done by an earlier run").count(), 5, "{again}");
    // a directory that is no bring-up's, and one that is no demo's, are never written into
    std::fs::create_dir(d.join("other")).unwrap();
    std::fs::write(d.join("other/keep.txt"), b"mine").unwrap();
    p.refuse(&["bringup", "--sweep", "s1", "--codes", "codes32.json", "--epochs", "1", "-o", "other"], &["other", "inputs.json"]);
    p.refuse(&["demo", "--quick", "-o", "other"], &["other", "no demo"]);
    p.finish("resume");
}
