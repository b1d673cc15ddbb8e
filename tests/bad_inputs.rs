//! The bad-input corpus (`tests/corpus/`, written by `scripts/make_bad_corpus.py`) fed to
//! every command that reads that kind of file: each case must exit with status 2, name the
//! file in its message, not panic, and leave the working directory exactly as it was (no
//! output, no temporary file). Also: unwritable output paths, a full disk, a run directory
//! with a missing, truncated or foreign checkpoint, a dataset whose shards are missing or
//! do not match, and sizes too large for memory.

mod common;
use common::*;
use ndarray::Array3;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::SystemTime;
use tcsense_sensor::npy::write_npy;

const CORPUS: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/corpus");

/// Every file of `tests/corpus/KIND`, sorted.
fn corpus(kind: &str) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(Path::new(CORPUS).join(kind))
        .unwrap_or_else(|e| panic!("corpus {kind}: {e}"))
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    assert!(!v.is_empty(), "corpus {kind} is empty");
    v
}

fn name(p: &Path) -> String {
    p.file_name().unwrap().to_string_lossy().into_owned()
}

/// Every file under `dir` with its size and modification time.
fn snapshot(dir: &Path) -> BTreeMap<PathBuf, (u64, SystemTime)> {
    fn walk(d: &Path, root: &Path, out: &mut BTreeMap<PathBuf, (u64, SystemTime)>) {
        for e in std::fs::read_dir(d).unwrap() {
            let e = e.unwrap();
            let m = e.metadata().unwrap();
            let rel = e.path().strip_prefix(root).unwrap().to_path_buf();
            if m.is_dir() {
                out.insert(rel.clone(), (0, SystemTime::UNIX_EPOCH));
                walk(&e.path(), root, out);
            } else {
                out.insert(rel, (m.len(), m.modified().unwrap()));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

/// The corpus runner: counts cases per command.
struct Corpus {
    dir: PathBuf,
    counts: BTreeMap<String, usize>,
    failures: Vec<String>,
}

impl Corpus {
    /// Run `args` with every `@` replaced by `arg`; expect exit `status`, a message with every
    /// needle, no panic, and `dir` unchanged.
    fn refuse_with(&mut self, args: &[&str], arg: &str, needles: &[&str], status: i32) {
        let args: Vec<String> = args.iter().map(|a| a.replace('@', arg)).collect();
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        let before = snapshot(&self.dir);
        let o = run(&self.dir, &refs);
        let err = String::from_utf8_lossy(&o.stderr);
        let mut problems = Vec::new();
        if o.status.code() != Some(status) {
            problems.push(format!("exit {:?}, expected {status}", o.status.code()));
        }
        if err.contains("panicked") {
            problems.push("panicked".into());
        }
        for n in needles {
            if !err.contains(n) {
                problems.push(format!("message lacks {n:?}"));
            }
        }
        let after = snapshot(&self.dir);
        if before != after {
            let new: Vec<_> = after.keys().filter(|k| before.get(*k) != after.get(*k)).collect();
            problems.push(format!("changed the working directory: {new:?}"));
        }
        if !problems.is_empty() {
            self.failures.push(format!("tcsense {}: {}; stderr: {}", refs.join(" "), problems.join(", "), err.trim()));
        }
        const WITH_SUBCOMMANDS: &[&str] = &["codes", "dataset", "reconstruct", "train", "export", "bench", "sensor", "plot", "sweep"];
        let command = if WITH_SUBCOMMANDS.contains(&refs[0]) { refs[..2].join(" ") } else { refs[0].to_string() };
        *self.counts.entry(command).or_default() += 1;
    }

    /// Print the cases per command and fail with every case that went wrong.
    fn finish(&self, what: &str) {
        eprintln!("{what}: cases per command: {:?}", self.counts);
        assert!(
            self.failures.is_empty(),
            "{} of {} {what} cases failed:\n{}",
            self.failures.len(),
            self.counts.values().sum::<usize>(),
            self.failures.join("\n")
        );
    }

    fn refuse(&mut self, args: &[&str], arg: &str, needles: &[&str]) {
        self.refuse_with(args, arg, needles, 2)
    }

    /// Copy `src` (a corpus file) into the working directory under its own name.
    fn place(&self, src: &Path) -> String {
        let n = name(src);
        std::fs::copy(src, self.dir.join(&n)).unwrap();
        n
    }

    /// A copy of the directory `from` (relative) called `to`, with `file` replaced by `bytes`
    /// (`None`: removed).
    fn variant_dir(&self, from: &str, to: &str, file: &str, bytes: Option<&[u8]>) -> String {
        copy_dir(&self.dir.join(from), &self.dir.join(to));
        match bytes {
            Some(b) => std::fs::write(self.dir.join(to).join(file), b).unwrap(),
            None => std::fs::remove_file(self.dir.join(to).join(file)).unwrap(),
        }
        to.to_string()
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &to.join(e.file_name()));
        } else {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// A working directory with valid inputs: `codes.json` (L = 8, 4 taps, 2×2), `ds/` (tiny
/// LiDAR), `run/` (a trained ADMM-Net), `y.npy` [4, 8, 8], `x.npy` [8, 8, 8], `m.onnx`.
fn setup() -> (tempfile::TempDir, Corpus) {
    let t = tempdir();
    let d = t.path().to_path_buf();
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/admm-net-run-v1");
    copy_dir(&fixture, &d.join("run"));
    std::fs::copy(fixture.join("codes.json"), d.join("codes.json")).unwrap();
    std::fs::copy(fixture.join("y.npy"), d.join("y.npy")).unwrap();
    write_npy(&d.join("x.npy"), &Array3::<f32>::from_elem((8, 8, 8), 0.5).view()).unwrap();
    ok(&d, &["dataset", "lidar", "--count", "8", "--size", "8x8", "--length", "8", "--seed", "2", "-o", "ds"]);
    ok(&d, &["export", "onnx", "--run", "run", "-o", "m.onnx"]);
    (t, Corpus { dir: d, counts: BTreeMap::new(), failures: Vec::new() })
}

/// What each `.npy` corpus file's message must say besides its name.
fn npy_needle(file: &str) -> &'static str {
    match file {
        "empty.npy" | "garbage.npy" => "not a .npy file",
        "truncated.npy" | "huge-shape.npy" => "truncated",
        "header-truncated.npy" => "truncated .npy header",
        "bad-version.npy" => "expected 1, 2 or 3",
        "complex.npy" | "float16.npy" | "object.npy" | "structured.npy" | "unicode.npy" => "expected float32",
        "rank1.npy" | "rank5.npy" => "expected",
        "zero-size.npy" => "expected",
        f if f.starts_with("nan-") || f.starts_with("inf-") => "finite",
        f => panic!("no needle for corpus file {f}"),
    }
}

#[test]
fn npy_corpus_every_reader() {
    let (_t, mut c) = setup();
    let cube_slots: &[&[&str]] = &[
        &["simulate", "--codes", "codes.json", "--cube", "@", "-o", "out.npy"],
        &["depth", "@", "--length", "8", "-o", "out.npy"],
        &["lifetime", "@", "--length", "8", "-o", "out.npy"],
        &["dataset", "import", "--cube", "@", "--length", "8", "-o", "imported"],
        &["plot", "waveforms", "--cube", "@", "--pixel", "1,1", "-o", "w.png"],
    ];
    let tap_slots: &[&[&str]] = &[
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "@", "-o", "out.npy"],
        &["reconstruct", "admm-net", "--run", "run", "--measurements", "@", "-o", "out.npy"],
        &["infer", "--model", "m.onnx", "--measurements", "@", "-o", "out"],
    ];
    let format_slots: &[&[&str]] = &[
        &["sensor", "matrix", "--codes", "codes.json", "--irf", "@", "-o", "out.npy"],
        &["dataset", "import", "--depth", "@", "--length", "8", "-o", "imported"],
    ];
    for f in corpus("npy") {
        let n = c.place(&f);
        let is_value = n.starts_with("nan-") || n.starts_with("inf-");
        let mut slots: Vec<&[&str]> = Vec::new();
        if !is_value || n.ends_with("-cube.npy") {
            slots.extend(cube_slots);
        }
        if !is_value || n.ends_with("-taps.npy") {
            slots.extend(tap_slots);
        }
        if !is_value {
            slots.extend(format_slots);
        }
        for s in slots {
            c.refuse(s, &n, &[&n, npy_needle(&n)]);
        }
        std::fs::remove_file(c.dir.join(&n)).unwrap();
    }
    c.finish("npy corpus");
}

#[test]
fn codes_corpus_every_reader() {
    let (_t, mut c) = setup();
    let slots: &[&[&str]] = &[
        &["codes", "export", "@", "-o", "mem"],
        &["codes", "show", "@", "-o", "c.png"],
        &["simulate", "--codes", "@", "--cube", "x.npy", "-o", "out.npy"],
        &["reconstruct", "tval3", "--codes", "@", "--measurements", "y.npy", "-o", "out.npy"],
        &["sensor", "matrix", "--codes", "@", "-o", "out.npy"],
        &["train", "admm-net", "--dataset", "ds", "--codes", "@", "--epochs", "1", "-o", "newrun"],
        &["eval", "--dataset", "ds", "--codes", "@", "--decoder", "tval3", "-o", "table.json"],
        &["codes", "check", "@"],
    ];
    for f in corpus("codes") {
        let n = c.place(&f);
        for s in slots {
            if n == "breaks-tap-constraint.json" && s[1] == "check" {
                // `codes check` reports violations with exit status 1
                c.refuse_with(s, &n, &[&n, "tap"], 1);
            } else if n == "breaks-tap-constraint.json" && s[1] == "show" {
                // `codes show` draws the violations (marked red)
                ok(&c.dir, &s.iter().map(|a| a.replace('@', &n)).collect::<Vec<_>>().iter().map(String::as_str).collect::<Vec<_>>());
                std::fs::remove_file(c.dir.join("c.png")).unwrap();
            } else {
                c.refuse(s, &n, &[&n]);
            }
        }
        std::fs::remove_file(c.dir.join(&n)).unwrap();
    }
    c.finish("codes corpus");
}

/// Every command that opens a run directory for inference, with `@` the run.
const RUN_SLOTS: &[&[&str]] = &[
    &["reconstruct", "admm-net", "--run", "@", "--measurements", "y.npy", "-o", "out.npy"],
    &["export", "onnx", "--run", "@", "-o", "m2.onnx"],
    &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "admm-net:@", "-o", "table.json"],
    &["bench", "infer", "--run", "@", "--size", "8x8", "--reps", "1"],
];
/// Resuming a run, with `@` the run.
const RESUME: &[&str] = &["train", "admm-net", "--dataset", "ds", "--resume", "--epochs", "3", "-o", "@"];

/// Config faults that only training reads (inference takes the network, sampling and IRF of a
/// run and does not read its learning rate or batch size).
const TRAINING_ONLY: &[&str] = &["missing-field.json", "negative-learning-rate.json", "wrong-type.json", "zero-batch.json"];

#[test]
fn config_and_checkpoint_corpus() {
    let (_t, mut c) = setup();
    // `trun`: a run trained by this build, with a checkpoint to resume from
    ok(
        &c.dir,
        &[
            "train",
            "admm-net",
            "--dataset",
            "ds",
            "--codes",
            "codes.json",
            "--epochs",
            "1",
            "--stages",
            "2",
            "--channels",
            "4",
            "--no-augment",
            "-o",
            "trun",
        ],
    );
    for f in corpus("config") {
        let n = c.place(&f);
        c.refuse(&["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--config", "@", "-o", "newrun"], &n, &[&n]);
        std::fs::remove_file(c.dir.join(&n)).unwrap();
        let stem = n.trim_end_matches(".json");
        let bytes = std::fs::read(&f).unwrap();
        if !TRAINING_ONLY.contains(&n.as_str()) {
            let run = c.variant_dir("run", &format!("run-{stem}"), "config.json", Some(&bytes));
            for s in RUN_SLOTS {
                c.refuse(s, &run, &[&format!("{run}/config.json")]);
            }
        }
        let run = c.variant_dir("trun", &format!("trun-{stem}"), "config.json", Some(&bytes));
        c.refuse(RESUME, &run, &[&format!("{run}/config.json")]);
    }
    // weights: missing, empty, truncated, garbage; codes missing
    let bpk = std::fs::read(c.dir.join("run/model.bpk")).unwrap();
    let faults: Vec<(&str, &str, Option<Vec<u8>>)> = vec![
        ("missing", "model.bpk", None),
        ("empty", "model.bpk", Some(Vec::new())),
        ("truncated", "model.bpk", Some(bpk[..bpk.len() / 2].to_vec())),
        ("garbage", "model.bpk", Some(b"not a checkpoint at all".repeat(20))),
        ("no-codes", "codes.json", None),
    ];
    for (what, file, bytes) in &faults {
        let run = c.variant_dir("run", &format!("run-{what}"), file, bytes.as_deref());
        for s in RUN_SLOTS {
            c.refuse(s, &run, &[&format!("{run}/{file}")]);
        }
    }
    // the checkpoint a resume reads: its weights, optimiser state and progress
    let ckpt = std::fs::read(c.dir.join("trun/checkpoint/model.bpk")).unwrap();
    let optim = std::fs::read(c.dir.join("trun/checkpoint/optim.bpk")).unwrap();
    let faults: Vec<(&str, &str, Option<Vec<u8>>)> = vec![
        ("weights-truncated", "checkpoint/model.bpk", Some(ckpt[..ckpt.len() / 2].to_vec())),
        ("weights-garbage", "checkpoint/model.bpk", Some(b"garbage".repeat(30))),
        ("weights-missing", "checkpoint/model.bpk", None),
        ("optim-truncated", "checkpoint/optim.bpk", Some(optim[..optim.len() / 2].to_vec())),
        ("state-garbage", "checkpoint/state.json", Some(b"{\"epoch\": \"one\"}".to_vec())),
        ("state-missing", "checkpoint/state.json", None),
        ("no-codes", "codes.json", None),
    ];
    for (what, file, bytes) in &faults {
        let run = c.variant_dir("trun", &format!("trun-{what}"), file, bytes.as_deref());
        c.refuse(RESUME, &run, &[&format!("{run}/{file}")]);
    }
    // weights of another architecture: the config says 8 channels, the weights have 4
    let cfg = std::fs::read_to_string(c.dir.join("run/config.json")).unwrap().replace("\"channels\": 4", "\"channels\": 8");
    let run = c.variant_dir("run", "run-foreign", "config.json", Some(cfg.as_bytes()));
    for s in RUN_SLOTS {
        c.refuse(s, &run, &[&format!("{run}/model.bpk")]);
    }
    c.finish("run-directory corpus");
}

#[test]
fn manifest_and_shard_corpus() {
    let (_t, mut c) = setup();
    let slots: &[&[&str]] = &[
        &["train", "admm-net", "--dataset", "@", "--codes", "codes.json", "--epochs", "1", "-o", "newrun"],
        &["eval", "--dataset", "@", "--codes", "codes.json", "--decoder", "tval3", "-o", "table.json"],
        &["codes", "select", "--dataset", "@", "--length", "8", "--candidates", "1", "-o", "best.json"],
        &["dataset", "show", "@", "-o", "item.png"],
    ];
    for f in corpus("manifest") {
        let n = f.file_stem().unwrap().to_string_lossy().into_owned();
        let ds = c.variant_dir("ds", &format!("ds-{n}"), "manifest.json", Some(&std::fs::read(&f).unwrap()));
        let needle = match n.as_str() {
            "missing-shard" => format!("{ds}/train/x_009.npy"),
            _ => format!("{ds}/manifest.json"),
        };
        for s in slots {
            c.refuse(s, &ds, &[&needle]);
        }
    }
    // shards that do not match the manifest: another shape, truncated, not a .npy, missing
    write_npy(&c.dir.join("wrong.npy"), &Array3::<f32>::zeros((6, 8, 4)).view()).unwrap();
    let wrong = std::fs::read(c.dir.join("wrong.npy")).unwrap();
    std::fs::remove_file(c.dir.join("wrong.npy")).unwrap();
    let good = std::fs::read(c.dir.join("ds/train/x_000.npy")).unwrap();
    let shards: Vec<(&str, Option<Vec<u8>>)> = vec![
        ("shape", Some(wrong)),
        ("truncated", Some(good[..good.len() - 64].to_vec())),
        ("garbage", Some(b"garbage".to_vec())),
        ("gone", None),
    ];
    for (what, bytes) in shards {
        let ds = c.variant_dir("ds", &format!("ds-shard-{what}"), "train/x_000.npy", bytes.as_deref());
        for s in slots {
            c.refuse(s, &ds, &[&format!("{ds}/train/x_000.npy")]);
        }
    }
    c.finish("dataset corpus");
}

#[test]
fn onnx_corpus_every_reader() {
    let (_t, mut c) = setup();
    let slots: &[&[&str]] = &[
        &["infer", "--model", "@", "--measurements", "y.npy", "-o", "out"],
        &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "onnx:@", "-o", "table.json"],
        &["bench", "infer", "--model", "@", "--size", "8x8", "--reps", "1"],
    ];
    for f in corpus("onnx") {
        let n = c.place(&f);
        for s in slots {
            c.refuse(s, &n, &[&n]);
        }
        std::fs::remove_file(c.dir.join(&n)).unwrap();
    }
    // a model that does not match the measurements (taps) or a sensor matrix of another shape
    write_npy(&c.dir.join("y6.npy"), &Array3::<f32>::ones((6, 8, 8)).view()).unwrap();
    c.refuse(&["infer", "--model", "m.onnx", "--measurements", "@", "-o", "out"], "y6.npy", &["y6.npy", "M = 4"]);
    ok(&c.dir, &["export", "onnx", "--run", "run", "--matrix-input", "-o", "mi.onnx"]);
    write_npy(&c.dir.join("A.npy"), &Array3::<f32>::ones((4, 4, 9)).view()).unwrap();
    c.refuse(
        &["infer", "--model", "mi.onnx", "--measurements", "y.npy", "--sensor-matrix", "@", "-o", "out"],
        "A.npy",
        &["A.npy", "(4, 4, 8)"],
    );
    c.finish("onnx corpus");
}

#[test]
fn unwritable_outputs_are_refused() {
    let (_t, mut c) = setup();
    std::fs::write(c.dir.join("file.txt"), "a regular file, not a directory").unwrap();
    let slots: &[&[&str]] = &[
        &["codes", "generate", "--length", "8", "-o", "@/c.json"],
        &["codes", "export", "codes.json", "--force", "-o", "@/mem"],
        &["codes", "show", "codes.json", "-o", "@/c.png"],
        &["sensor", "matrix", "--codes", "codes.json", "-o", "@/A.npy"],
        &["simulate", "--codes", "codes.json", "--cube", "x.npy", "-o", "@/y.npy"],
        &["reconstruct", "tval3", "--codes", "codes.json", "--measurements", "y.npy", "--maxit", "2", "-o", "@/x.npy"],
        &["reconstruct", "admm-net", "--run", "run", "--measurements", "y.npy", "-o", "@/x.npy"],
        &["depth", "x.npy", "--length", "8", "-o", "@/d.npy"],
        &["lifetime", "x.npy", "--length", "8", "-o", "@/t.npy"],
        &["dataset", "lidar", "--count", "4", "--size", "8x8", "--length", "8", "-o", "@/ds"],
        &["dataset", "flim", "--count", "4", "--size", "8x8", "--length", "8", "-o", "@/ds"],
        &["train", "admm-net", "--dataset", "ds", "--codes", "codes.json", "--epochs", "1", "-o", "@/run"],
        &["export", "onnx", "--run", "run", "-o", "@/m.onnx"],
        &["infer", "--model", "m.onnx", "--measurements", "y.npy", "-o", "@/out"],
        &["eval", "--dataset", "ds", "--codes", "codes.json", "--decoder", "tval3", "--maxit", "2", "-o", "@/t.json"],
        &["plot", "waveforms", "--cube", "x.npy", "--pixel", "1,1", "-o", "@/w.png"],
    ];
    for s in slots {
        c.refuse(s, "file.txt", &["file.txt"]);
    }
    c.finish("unwritable-output");
}

/// A full disk, simulated by a file-size limit (`ulimit -f`, with SIGXFSZ ignored so that the
/// write fails with EFBIG): the command fails with status 2 naming the output, the previous
/// file is left intact and no temporary file remains.
#[test]
fn full_disk_leaves_the_previous_file_intact() {
    let (_t, mut c) = setup();
    write_npy(&c.dir.join("big.npy"), &Array3::<f32>::from_elem((8, 64, 64), 1.0).view()).unwrap();
    std::fs::write(c.dir.join("out.npy"), b"previous contents").unwrap();
    let cases: &[&[&str]] = &[
        &["simulate", "--codes", "codes.json", "--cube", "big.npy", "-o", "out.npy"],
        &["sensor", "matrix", "--codes", "codes.json", "-o", "out.npy"],
        &["depth", "big.npy", "--length", "8", "-o", "out.npy"],
    ];
    let exe = env!("CARGO_BIN_EXE_tcsense");
    for args in cases {
        let before = snapshot(&c.dir);
        // 1 block of 512 bytes: the .npy header fits, the data does not
        let script = "trap '' XFSZ; ulimit -f 1; exec \"$0\" \"$@\"";
        let o = std::process::Command::new("sh").current_dir(&c.dir).arg("-c").arg(script).arg(exe).args(*args).output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?} on a full disk: {err}");
        assert!(err.contains("out.npy") && !err.contains("panicked"), "{args:?}: {err}");
        assert_eq!(std::fs::read(c.dir.join("out.npy")).unwrap(), b"previous contents");
        assert_eq!(before, snapshot(&c.dir), "{args:?} left a file behind");
        *c.counts.entry(args[0].to_string()).or_default() += 1;
    }
    c.finish("full-disk");
}

#[test]
fn sizes_too_large_for_memory_are_refused_up_front() {
    let (_t, mut c) = setup();
    c.refuse(&["dataset", "lidar", "--count", "100000", "--size", "4096x4096", "--length", "256", "-o", "@"], "big", &["GiB"]);
    c.refuse(&["dataset", "flim", "--count", "100000", "--size", "4096x4096", "-o", "@"], "big", &["GiB"]);
    c.refuse(&["bench", "infer", "--decoder", "unet", "--size", "@", "--reps", "1"], "65536x65536", &["GiB"]);
    c.finish("memory");
}
