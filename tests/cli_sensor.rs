//! End-to-end tests of `tcsense codes …`, `sensor matrix` and `simulate` on tiny problems.

mod common;
use common::*;
use ndarray::{Array3, Ix3};
use tcsense_sensor::npy::{read_npy, write_npy};
use tcsense_sensor::Codes;

#[test]
fn generate_check_export_import_show() {
    let d = tempdir();
    let d = d.path();
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
            "3",
            "-o",
            "codes.json",
        ],
    );
    ok(d, &["codes", "check", "codes.json"]);
    // random codes: seed 3's alias (below 0.5 under the physical IRF) needs --force
    ok(d, &["codes", "export", "codes.json", "--force", "-o", "mem"]);
    let regs: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(d.join("mem/registers.json")).unwrap()).unwrap();
    assert_eq!(regs["ECLEN"], 3);
    assert_eq!(regs["channels"].as_array().unwrap().len(), 16);
    ok(d, &["codes", "import", "mem", "-o", "back.json"]);
    let a = Codes::load(&d.join("codes.json")).unwrap();
    let b = Codes::load(&d.join("back.json")).unwrap();
    for c in 0..16 {
        assert_eq!(a.channel(c), b.channel(c));
    }
    ok(d, &["codes", "show", "codes.json", "-o", "codes.png"]);
    let png = std::fs::read(d.join("codes.png")).unwrap();
    assert_eq!(&png[1..4], b"PNG");
    // same seed, same bytes
    ok(d, &["codes", "generate", "--tap-constraint", "--hamming", "2", "--window", "2", "--seed", "3", "-o", "again.json"]);
    assert_eq!(std::fs::read(d.join("codes.json")).unwrap(), std::fs::read(d.join("again.json")).unwrap());
}

#[test]
fn check_reports_violations_with_exit_1_and_export_refuses() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["codes", "generate", "--tap-constraint", "--hamming", "2", "--length", "16", "--seed", "1", "-o", "codes.json"]);
    // Break the tap constraint by hand: a second tap on at mask 0 of subpixel 0.
    let mut g = Codes::load(&d.join("codes.json")).unwrap();
    let on = (0..4).find(|&m| g.get(0, m, 0)).unwrap();
    g.set(0, (on + 1) % 4, 0, true);
    g.save(&d.join("bad.json")).unwrap();
    let o = run(d, &["codes", "check", "bad.json"]);
    assert_eq!(o.status.code(), Some(1));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("tap: mask 0, subpixel 0"), "{out}");
    fails(d, &["codes", "export", "bad.json", "-o", "mem"], &["bad.json", "violate"]);
    assert!(!d.join("mem/registers.json").exists());
}

#[test]
fn simulate_ideal_equals_direct_sum_and_noise_is_seeded() {
    let d = tempdir();
    let d = d.path();
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "16", "--seed", "5", "-o", "codes.json"]);
    let x = Array3::from_shape_fn((32, 4, 6), |(j, r, c)| ((j * 13 + r * 7 + c * 3) % 17) as f32 * 0.25);
    write_npy(&d.join("x.npy"), &x.view()).unwrap();
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "x.npy", "--oversample", "2", "-o", "y.npy"]);
    let y = read_npy(&d.join("y.npy")).unwrap().into_dimensionality::<Ix3>().unwrap();
    assert_eq!(y.dim(), (4, 4, 6));
    let g = Codes::load(&d.join("codes.json")).unwrap();
    for m in 0..4 {
        for r in 0..4 {
            for c in 0..6 {
                let n = (r % 2) * 2 + c % 2;
                let want: f32 = (0..32).filter(|&j| g.get(n, m, j / 2)).map(|j| x[(j, r, c)]).sum();
                assert!((y[(m, r, c)] - want).abs() < 1e-4);
            }
        }
    }
    // matrix written by `sensor matrix` can be loaded back as a measured A and gives the same y
    ok(d, &["sensor", "matrix", "--codes", "codes.json", "--oversample", "2", "-o", "A.npy"]);
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "x.npy", "--irf", "A.npy", "--oversample", "2", "-o", "y2.npy"]);
    assert_eq!(std::fs::read(d.join("y.npy")).unwrap(), std::fs::read(d.join("y2.npy")).unwrap());
    // noise: same seed same bytes, other seed differs
    let noisy = |seed: &str, out: &str| {
        ok(
            d,
            &[
                "simulate",
                "--codes",
                "codes.json",
                "--cube",
                "x.npy",
                "--oversample",
                "2",
                "--noise",
                "--full-well",
                "20000",
                "--read-noise",
                "40",
                "--seed",
                seed,
                "-o",
                out,
            ],
        )
    };
    noisy("1", "n1.npy");
    noisy("1", "n1b.npy");
    noisy("2", "n2.npy");
    assert_eq!(std::fs::read(d.join("n1.npy")).unwrap(), std::fs::read(d.join("n1b.npy")).unwrap());
    assert_ne!(std::fs::read(d.join("n1.npy")).unwrap(), std::fs::read(d.join("n2.npy")).unwrap());
    // heterodyne and physical IRF run on the fine grid
    ok(d, &["simulate", "--codes", "codes.json", "--cube", "x.npy", "--heterodyne", "2", "--irf", "physical", "-o", "yh.npy"]);
}

#[test]
fn bad_inputs_exit_2_with_clear_messages() {
    let d = tempdir();
    let d = d.path();
    std::fs::write(d.join("broken.json"), "{ \"format\": \"tcsense-codes\", ").unwrap();
    fails(d, &["codes", "check", "broken.json"], &["broken.json", "malformed codes JSON"]);
    fails(d, &["codes", "generate", "--length", "30", "-o", "c.json"], &["length", "got 30", "multiple of 8"]);
    assert!(!d.join("c.json").exists());
    ok(d, &["codes", "generate", "--tap-constraint", "--length", "8", "-o", "codes.json"]);
    let text = std::fs::read_to_string(d.join("codes.json")).unwrap().replace("\"length\": 8", "\"length\": 12");
    std::fs::write(d.join("len12.json"), text).unwrap();
    fails(d, &["codes", "show", "len12.json", "-o", "x.png"], &["len12.json", "multiple of 8"]);
    fails(d, &["codes", "check", "missing.json"], &["missing.json"]);
    // block does not divide the frame
    write_npy(&d.join("odd.npy"), &Array3::<f32>::zeros((8, 5, 4)).view()).unwrap();
    fails(d, &["simulate", "--codes", "codes.json", "--cube", "odd.npy", "-o", "y.npy"], &["odd.npy", "multiple of 2"]);
    // wrong rank
    write_npy(&d.join("flat.npy"), &ndarray::Array2::<f32>::zeros((8, 4)).view()).unwrap();
    fails(d, &["simulate", "--codes", "codes.json", "--cube", "flat.npy", "-o", "y.npy"], &["flat.npy", "rank 2", "[T, H, W]"]);
    // NaN
    let mut x = Array3::<f32>::zeros((8, 4, 4));
    x[(3, 1, 2)] = f32::NAN;
    write_npy(&d.join("nan.npy"), &x.view()).unwrap();
    fails(d, &["simulate", "--codes", "codes.json", "--cube", "nan.npy", "-o", "y.npy"], &["nan.npy", "non-finite", "[3, 1, 2]"]);
    // wrong number of bins
    write_npy(&d.join("t16.npy"), &Array3::<f32>::zeros((16, 4, 4)).view()).unwrap();
    fails(d, &["simulate", "--codes", "codes.json", "--cube", "t16.npy", "-o", "y.npy"], &["t16.npy", "16 time bins", "T = L·K = 8"]);
    // measured A of the wrong shape
    write_npy(&d.join("A.npy"), &Array3::<f32>::zeros((4, 4, 9)).view()).unwrap();
    fails(d, &["sensor", "matrix", "--codes", "codes.json", "--irf", "A.npy", "-o", "B.npy"], &["A.npy", "[N, M, T] = [4, 4, 8]"]);
    fails(d, &["sensor", "matrix", "--codes", "codes.json", "--irf", "gaussian", "-o", "B.npy"], &["--irf", "ideal"]);
    // not an npy file
    std::fs::write(d.join("junk.npy"), b"hello").unwrap();
    fails(d, &["simulate", "--codes", "codes.json", "--cube", "junk.npy", "-o", "y.npy"], &["junk.npy", "not a .npy file"]);
    assert!(!d.join("y.npy").exists(), "no output after a failure");
}

#[test]
fn import_and_select_bad_inputs_exit_2() {
    let d = tempdir();
    let d = d.path();
    fails(d, &["codes", "import", "nowhere", "-o", "c.json"], &["registers.json"]);
    std::fs::create_dir_all(d.join("mem")).unwrap();
    std::fs::write(d.join("mem/registers.json"), "{\"ECLEN\": 3}").unwrap();
    fails(d, &["codes", "import", "mem", "-o", "c.json"], &["registers.json", "malformed registers"]);
    fails(d, &["codes", "select", "--dataset", "nowhere", "--candidates", "2", "-o", "best.json"], &["nowhere", "manifest.json"]);
    assert!(!d.join("c.json").exists() && !d.join("best.json").exists());
}

/// `codes project`: logits that favour a feasible code give exactly that code; random logits
/// give codes that pass `codes check` and export; bad logits exit 2.
#[test]
fn project_logits_onto_the_constraints() {
    let d = tempdir();
    let d = d.path();
    let flags = ["--taps", "4", "--block", "2x2", "--length", "16", "--tap-constraint", "--hamming", "2", "--window", "2"];
    let mut gen = vec!["codes", "generate", "--seed", "4", "-o", "target.json"];
    gen.extend(flags);
    ok(d, &gen);
    let target = tcsense_sensor::Codes::load(&d.join("target.json")).unwrap();
    let mut logits = ndarray::Array3::<f32>::from_shape_fn((4, 4, 16), |(n, c, l)| ((n * 5 + c * 3 + l * 7) % 13) as f32 * 0.1);
    for n in 0..4 {
        for l in 0..16 {
            let m = (0..4).find(|&m| target.get(n, m, l)).unwrap();
            logits[(n, m, l)] += 5.0;
        }
    }
    write_npy(&d.join("logits.npy"), &logits.view()).unwrap();
    let mut cmd = vec!["codes", "project", "--logits", "logits.npy", "-o", "p.json"];
    cmd.extend(flags);
    let out = ok(d, &cmd);
    assert!(out.contains("Argmax"), "{out}");
    let p = tcsense_sensor::Codes::load(&d.join("p.json")).unwrap();
    assert_eq!(p.digest(), target.digest());
    // random logits: an exact projection that passes the checker and exports
    let noise = ndarray::Array3::<f32>::from_shape_fn((4, 4, 16), |(n, c, l)| (((n * 31 + c * 17 + l * 11) % 23) as f32 - 11.0) * 0.2);
    write_npy(&d.join("noise.npy"), &noise.view()).unwrap();
    let mut cmd = vec!["codes", "project", "--logits", "noise.npy", "-o", "q.json"];
    cmd.extend(flags);
    let out = ok(d, &cmd);
    assert!(out.contains("Exact"), "{out}");
    ok(d, &["codes", "check", "q.json"]);
    ok(d, &["codes", "export", "q.json", "-o", "mem"]);
    // logits of the wrong shape: C = 5 without a drain
    write_npy(&d.join("c5.npy"), &ndarray::Array3::<f32>::zeros((4, 5, 16)).view()).unwrap();
    let mut cmd = vec!["codes", "project", "--logits", "c5.npy", "-o", "r.json"];
    cmd.extend(flags);
    fails(d, &cmd, &["c5.npy", "[N, C, L] = [4, 4, 16]"]);
    assert!(!d.join("r.json").exists());
}
