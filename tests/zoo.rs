//! The model zoo (`zoo/NAME/`): every entry is listed and shown, opens, decodes a realistic
//! frame, exports to ONNX and gives burn's output through ONNX Runtime (on 1 and 2 threads)
//! within 1e-4 of its scale; and re-running its recorded recipe (`zoo/NAME/recipe.json`) from its
//! seed gives the training losses of its first steps as `zoo/NAME/first_steps.csv` records them.
//!
//! The deeper check, `cargo test --release --test zoo -- --ignored` (about 40 minutes on two
//! cores, so not in `scripts/test.sh`): the recipe re-run for one epoch logs the entry's first
//! training loss of `metrics.csv` exactly (`relaxed/metrics.csv` for learned codes; within
//! [`GPU_EPOCH_LOSS`] for a recipe trained with `--device gpu`, replayed on the CPU), so its
//! weights come from this code (and its validation metrics, exactly, or for a depth network,
//! whose ranges go through its read-out and the range fit, the detection rate within 1 % and the
//! errors within 25 %). `first_steps.csv` is written from a commit that passes it, by the quick
//! check with `TCSENSE_ZOO_RECORD_STEPS=1`. Needs ONNX Runtime in `.venv` (`scripts/setup.sh`).

mod common;

use common::*;
use ndarray::Array4;
use rand::{RngExt, SeedableRng};
use std::path::{Path, PathBuf};
use tcsense_infer::onnx::{export, ExportOptions};
use tcsense_infer::runtime::OnnxModel;
use tcsense_models::runs;
use tcsense_models::Device;

fn zoo_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("zoo")
}

/// The zoo's entries (directories with a run config), sorted.
fn entries() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(zoo_dir())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.path().join("config.json").is_file())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// The recipe's steps: tcsense argument lists, run in an empty directory in order.
fn recipe(name: &str) -> Vec<Vec<String>> {
    let path = zoo_dir().join(name).join("recipe.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e} (every zoo entry records its recipe)", path.display()));
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    v["steps"]
        .as_array()
        .expect("recipe.steps")
        .iter()
        .map(|s| s.as_array().expect("a step is a list of arguments").iter().map(|a| a.as_str().unwrap().to_string()).collect())
        .collect()
}

/// Max |a − b| over the scale of `b`.
fn rel_diff(a: &Array4<f32>, b: &Array4<f32>) -> f32 {
    assert_eq!(a.dim(), b.dim());
    let scale = b.iter().filter(|v| v.is_finite()).fold(0f32, |m, v| m.max(v.abs())).max(1e-12);
    a.iter().zip(b.iter()).filter(|(x, y)| x.is_finite() && y.is_finite()).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
}

#[test]
fn zoo_list_and_show_name_every_entry() {
    let d = tempdir();
    let names = entries();
    assert!(!names.is_empty(), "the zoo has entries");
    let list = ok(d.path(), &["zoo", "list"]);
    // the light each entry was trained in: the photon ladder's range, and ambient light where any
    assert!(list.contains("LIGHT") && list.contains("0.05–0.9") && list.contains("0.002–0.9, ambient 0–2"), "{list}");
    for n in &names {
        assert!(list.contains(n.as_str()), "zoo list names {n}: {list}");
        let show = ok(d.path(), &["zoo", "show", &format!("zoo:{n}")]);
        assert!(show.contains("# ") && show.contains("directory"), "zoo show {n} prints its provenance: {show}");
        // every entry on learned codes says how they fared against the designed codes, with
        // the same network, per test set; a baseline is marked in the listing
        let config = std::fs::read_to_string(zoo_dir().join(n).join("config.json")).unwrap();
        let learned = serde_json::from_str::<serde_json::Value>(&config).unwrap().get("learn_codes").is_some_and(|v| !v.is_null());
        let compared = zoo_dir().join(n).join("codes_comparison.json").exists();
        assert_eq!(learned, compared, "{n}: learned codes {learned}, comparison {compared}");
        if compared {
            let c: serde_json::Value =
                serde_json::from_str(&std::fs::read_to_string(zoo_dir().join(n).join("codes_comparison.json")).unwrap()).unwrap();
            let against = c["against"].as_str().unwrap();
            assert!(names.iter().any(|m| m == against), "{n} is compared with {against}, not in the zoo");
            assert!(
                show.contains(&format!("against     zoo:{against}")) && (show.contains("motorcycle") || show.contains("onset-0ns")),
                "{show}"
            );
            let mark = match c["verdict"].as_str().unwrap() {
                "baseline" => "learned†",
                "on-par" => "learned=",
                _ => "learned+",
            };
            let row = list.lines().find(|l| l.starts_with(&format!("{n} "))).unwrap();
            assert!(row.contains(mark), "{row}");
        }
    }
    fails(d.path(), &["zoo", "show", "no-such-entry"], &["zoo entry", "no-such-entry", "one of"]);
    fails(d.path(), &["export", "onnx", "--run", "zoo:no-such-entry", "-o", "x.onnx"], &["zoo:no-such-entry", "one of"]);
    assert!(!d.path().join("x.onnx").exists());
}

/// A zoo whose comparison file is malformed or whose rows do not match its levels: `zoo list`
/// and `zoo show` refuse it with exit 2, naming the file, and no panic.
#[test]
fn a_malformed_codes_comparison_is_refused_naming_the_file() {
    let d = tempdir();
    let entry = d.path().join("zoo").join("x-learned");
    std::fs::create_dir_all(&entry).unwrap();
    for f in ["config.json", "codes.json", "model.bpk"] {
        std::fs::copy(zoo_dir().join("admm-lidar-learned").join(f), entry.join(f)).unwrap();
    }
    let good = std::fs::read_to_string(zoo_dir().join("admm-lidar-learned").join("codes_comparison.json")).unwrap();
    let zoo_cmd = |args: &[&str]| bin().current_dir(d.path()).env("TCSENSE_ZOO", d.path().join("zoo")).args(args).output().unwrap();
    for (text, needle) in [
        (r#"{"against": 3}"#.to_string(), "not a codes comparison"),
        (good.replacen("\"ratio\": [", "\"ratio\": [1.0, ", 1), "one value per level"),
    ] {
        std::fs::write(entry.join("codes_comparison.json"), text).unwrap();
        for args in [&["zoo", "list"][..], &["zoo", "show", "x-learned"]] {
            let o = zoo_cmd(args);
            let err = String::from_utf8_lossy(&o.stderr);
            assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
            assert!(err.contains("codes_comparison.json") && err.contains(needle) && !err.contains("panicked"), "{args:?}: {err}");
        }
    }
    std::fs::write(entry.join("codes_comparison.json"), good).unwrap();
    let list = zoo_cmd(&["zoo", "list"]);
    assert!(list.status.success() && String::from_utf8_lossy(&list.stdout).contains("learned†"));
}

/// A realistic frame for an entry: a scene of its kind (a generated LiDAR or FLIm test item,
/// 32×32) measured by the entry's sensor, with shot noise.
fn realistic_frame(run: &runs::LoadedRun, dir: &Path) -> Array4<f32> {
    let flim = matches!(run.spec.sampling, tcsense_sensor::Sampling::Heterodyne(_));
    let kind = if flim { "flim" } else { "lidar" };
    ok(dir, &["dataset", kind, "--count", "10", "--size", "32x32", "--seed", "9", "--force", "-o", "scene"]);
    let ds = tcsense_datasets::Dataset::open(&dir.join("scene")).unwrap();
    let x = ds.item("test", 0, "x").unwrap().into_dimensionality::<ndarray::Ix3>().unwrap();
    let plan = run.sensor.plan(32, 32).unwrap();
    let peak = x.iter().fold(0f32, |m, v| m.max(*v)).max(1e-12);
    // the brightest voxel at 5000 electrons, shot noise
    let x = x.mapv(|v| v / peak * 5000.0).insert_axis(ndarray::Axis(0));
    let mut y = plan.forward_batch(&x.view()).unwrap();
    let mut rng = rand::rngs::StdRng::seed_from_u64(4);
    y.mapv_inplace(|v| v + rng.random_range(-1.0f32..1.0) * v.max(0.0).sqrt());
    y
}

#[test]
fn every_entry_decodes_and_exports_with_burn_and_onnx_runtime_agreeing() {
    let d = tempdir();
    for name in entries() {
        let dir = zoo_dir().join(&name);
        let run = runs::load(&dir, &Device::flex()).unwrap_or_else(|e| panic!("zoo:{name} opens: {e}"));
        let y = realistic_frame(&run, d.path());
        let want = burn_outputs(&run, &y);
        // finite outputs; a depth is NaN only where its return's confidence is below one half
        // (a decoder that masks its own product: the U-Net on the range fit's evidence)
        assert!(want.iter().all(|o| o.iter().all(|v| !v.is_infinite())), "zoo:{name}: no infinite outputs");
        match (run.spec.model.name(), want.as_slice()) {
            ("unet", [depth, confidence]) => assert!(
                depth.iter().zip(confidence.iter()).all(|(d, c)| d.is_finite() || *c < 0.5) && confidence.iter().all(|c| c.is_finite()),
                "zoo:{name}: a depth wherever a return is confident"
            ),
            _ => assert!(want.iter().all(|o| o.iter().all(|v| v.is_finite())), "zoo:{name}: finite outputs"),
        }
        let onnx = d.path().join(format!("{name}.onnx"));
        std::fs::write(&onnx, export(&run, ExportOptions::default()).unwrap()).unwrap();
        for threads in [1, 2] {
            let got = OnnxModel::open(&onnx, threads)
                .unwrap_or_else(|e| panic!("{e} (run scripts/setup.sh to install ONNX Runtime into .venv)"))
                .run(y.view())
                .unwrap();
            for (k, want) in want.iter().enumerate() {
                let nan = got[k].iter().zip(want.iter()).filter(|(a, b)| a.is_nan() != b.is_nan()).count();
                assert_eq!(nan, 0, "zoo:{name}, output {k}, {threads} threads: ONNX Runtime and burn have values at other pixels");
                let diff = rel_diff(&got[k], want);
                assert!(diff <= 1e-4, "zoo:{name}, output {k}, {threads} threads: ONNX Runtime differs from burn by {diff:e} of the scale");
            }
        }
        // and the command line takes it by name
        ok(d.path(), &["export", "onnx", "--run", &format!("zoo:{name}"), "-o", &format!("{name}-cli.onnx")]);
        assert!(d.path().join(format!("{name}-cli.onnx")).exists());
    }
}

/// A setup step's output, shared by the entries whose recipes run the same step on the same
/// inputs (the same commands from an empty directory give the same bytes): the first to need it
/// makes it (the others wait for it), the later ones link it. A step's inputs are the steps
/// before it in its recipe, but for a dataset's generator, which reads no file.
#[derive(Default)]
struct SharedSteps(std::sync::Mutex<std::collections::HashMap<Vec<Vec<String>>, std::sync::Arc<std::sync::Mutex<Option<PathBuf>>>>>);

impl SharedSteps {
    /// Runs the last of `steps` (output `out`) in `dir`, or links the output of an earlier run
    /// of the same steps there.
    fn provide(&self, steps: &[Vec<String>], out: &str, dir: &Path) {
        let s = steps.last().expect("a step");
        let key = if s[0] == "dataset" { vec![s.clone()] } else { steps.to_vec() };
        let slot = self.0.lock().unwrap().entry(key).or_default().clone();
        let mut slot = slot.lock().unwrap_or_else(|e| e.into_inner());
        match slot.as_ref() {
            Some(earlier) => std::os::unix::fs::symlink(earlier, dir.join(out)).unwrap(),
            None => {
                ok(dir, &s.iter().map(String::as_str).collect::<Vec<_>>());
                *slot = Some(dir.join(out));
            }
        }
    }
}

/// The training steps whose losses `first_steps.csv` records and the quick replay compares.
const FIRST_STEPS: usize = 6;

/// The relative tolerance of a GPU-trained entry's first-epoch training loss re-run on the CPU
/// (the mean over the epoch's steps, each step's weights a little apart; measured on
/// `zoo:unet-lidar-evidence-8k`: 5.830392e-1 on the CPU against the H200's 5.830480e-1, 1.5e-5).
const GPU_EPOCH_LOSS: f64 = 1e-4;

/// Runs `check(name, dir, shared)` for every entry, two at a time: one training keeps about
/// 1.4 of 2 cores busy. A setup step that an earlier entry's recipe ran on the same inputs is
/// linked from there, not run again ([`SharedSteps`]: the LiDAR entries share one dataset, the
/// FLIm ones another, and most their codes); every entry's directory lives to the end, for the
/// links into it.
fn replay_every_entry(check: fn(&str, &Path, &SharedSteps)) {
    let names = entries();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let failed = std::sync::atomic::AtomicBool::new(false);
    let shared = SharedSteps::default();
    let dirs = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| loop {
                let k = next.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                if k >= names.len() || failed.load(std::sync::atomic::Ordering::SeqCst) {
                    break;
                }
                let d = tempdir();
                let replayed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| check(&names[k], d.path(), &shared)));
                dirs.lock().unwrap_or_else(|e| e.into_inner()).push(d);
                if let Err(e) = replayed {
                    failed.store(true, std::sync::atomic::Ordering::SeqCst);
                    std::panic::resume_unwind(e);
                }
            });
        }
    });
}

#[test]
fn every_entry_reproduces_its_first_steps_from_its_recipe() {
    replay_every_entry(replay_first_steps);
}

#[test]
#[ignore = "about 40 minutes on two cores: cargo test --release --test zoo -- --ignored"]
fn every_entry_reproduces_its_first_logged_epoch_from_its_recipe() {
    replay_every_entry(replay_first_epoch);
}

/// Runs the setup steps of zoo entry `name`'s recipe in `dir`; its train step and that step's
/// run directory.
fn run_setup(name: &str, dir: &Path, shared: &SharedSteps) -> (Vec<String>, String, bool) {
    let steps = recipe(name);
    let (train, setup) = steps.split_last().expect("a recipe ends with its train command");
    assert_eq!(train[0], "train", "zoo:{name}: the recipe's last step trains");
    for (k, s) in setup.iter().enumerate() {
        match s.iter().position(|a| a == "-o").map(|i| s[i + 1].clone()) {
            Some(out) => shared.provide(&setup[..=k], &out, dir),
            None => {
                ok(dir, &s.iter().map(String::as_str).collect::<Vec<_>>());
            }
        }
    }
    let out = train.iter().position(|a| a == "-o" || a == "--output").map(|i| train[i + 1].clone()).expect("the train step names its run");
    let (train, gpu) = on_the_cpu(train);
    (train, out, gpu)
}

/// The recipe's train step as the replay runs it, on the CPU, and whether the entry was trained
/// on a GPU (`--device gpu`, dropped here: burn's wgpu backend agrees with the CPU to about 1e-4
/// of each step's loss, `train/tests/gpu.rs`, so its whole epoch matches within a tolerance, not
/// byte for byte; its first steps are recorded on the CPU).
fn on_the_cpu(train: &[String]) -> (Vec<String>, bool) {
    match train.iter().position(|a| a == "--device") {
        Some(i) => {
            let gpu = train.get(i + 1).is_some_and(|d| d == "gpu");
            let mut cpu = train.to_vec();
            cpu.drain(i..(i + 2).min(train.len()));
            (cpu, gpu)
        }
        None => (train.to_vec(), false),
    }
}

/// Replays zoo entry `name`'s recipe in `dir` for its first [`FIRST_STEPS`] steps: their
/// training losses (`epoch,step,train_loss`, as `metrics.csv` prints a loss) are those of
/// `zoo/NAME/first_steps.csv`, and the run's config is the entry's. With
/// `TCSENSE_ZOO_RECORD_STEPS=1` the file is written instead.
fn replay_first_steps(name: &str, dir: &Path, shared: &SharedSteps) {
    let (train, out, _) = run_setup(name, dir, shared);
    let mut args: Vec<&str> = train.iter().map(String::as_str).collect();
    let n = FIRST_STEPS.to_string();
    args.extend(["--stop-after-steps", &n]);
    let stdout = ok(dir, &args);
    assert!(stdout.contains(&format!("stopped after {FIRST_STEPS} steps")), "{stdout}");
    // "step    1  epoch    1  step in epoch      1  train loss 6.089269e1"
    let got: Vec<String> = stdout
        .lines()
        .filter(|l| l.starts_with("step "))
        .map(|l| {
            let w: Vec<&str> = l.split_whitespace().collect();
            assert_eq!(w.len(), 11, "a step line: {l}");
            format!("{},{},{}", w[3], w[7], w[10])
        })
        .collect();
    assert_eq!(got.len(), FIRST_STEPS, "zoo:{name}: one line per step: {stdout}");
    let path = zoo_dir().join(name).join("first_steps.csv");
    let text = format!("epoch,step,train_loss\n{}\n", got.join("\n"));
    if std::env::var_os("TCSENSE_ZOO_RECORD_STEPS").is_some_and(|v| v == "1") {
        std::fs::write(&path, text).unwrap();
    } else {
        let want = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{}: {e} (every zoo entry records its first steps' losses)", path.display()));
        assert_eq!(
            text,
            want,
            "zoo:{name}: the first {FIRST_STEPS} steps' training losses re-run from its recipe (left) against {}",
            path.display()
        );
    }
    check_config(name, &dir.join(&out));
}

/// The re-run's config is the entry's (as this build reads the entry's: fields added since, at
/// their defaults).
fn check_config(name: &str, run: &Path) {
    let cfg = |p: &Path| serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(p.join("config.json")).unwrap()).unwrap();
    let (zc, rc) = (tcsense_models::runs::upgrade_config(cfg(&zoo_dir().join(name))), cfg(run));
    for key in ["decoder", "model", "sampling", "irf", "epochs", "batch_size", "learning_rate", "seed", "augment"] {
        assert_eq!(zc[key], rc[key], "zoo:{name}: config.{key} of the re-run");
    }
}

/// Replays zoo entry `name`'s recipe in `dir` up to its first epoch and checks it against the
/// entry's log.
fn replay_first_epoch(name: &str, dir: &Path, shared: &SharedSteps) {
    let (train, out, gpu) = run_setup(name, dir, shared);
    let mut args: Vec<&str> = train.iter().map(String::as_str).collect();
    args.extend(["--pause-after", "1"]);
    let stdout = ok(dir, &args);
    // (a recipe of one epoch — a short fine-tune — runs to its end)
    let one_epoch = train.iter().position(|a| a == "--epochs").is_some_and(|i| train[i + 1] == "1");
    assert!(stdout.contains("paused after 1 epochs") || (one_epoch && stdout.contains("epoch 1")), "{stdout}");
    let first = |p: &Path| std::fs::read_to_string(p).unwrap().lines().nth(1).map(str::to_string).unwrap_or_default();
    // the clock is in timing.csv; a metrics.csv from before it ends in seconds
    let strip = |row: String, header: &str| {
        if header.ends_with(",seconds") {
            row.rsplit_once(',').map(|(a, _)| a.to_string()).unwrap_or(row)
        } else {
            row
        }
    };
    // an entry with learned codes starts with its relaxed phase, a run of its own in RUN/relaxed
    let phase = if train.iter().any(|a| a == "--learn-codes") { "relaxed" } else { "" };
    let zoo_metrics = zoo_dir().join(name).join(phase).join("metrics.csv");
    let header = std::fs::read_to_string(&zoo_metrics).unwrap().lines().next().unwrap_or_default().to_string();
    let want = strip(first(&zoo_metrics), &header);
    let got = first(&dir.join(&out).join(phase).join("metrics.csv"));
    assert!(!want.is_empty(), "zoo:{name} logs its epochs");
    // epoch, step and training loss: the same bytes (the weights' path is this code's), or for
    // an entry trained on a GPU the loss within GPU_EPOCH_LOSS
    let (gv, wv): (Vec<&str>, Vec<&str>) = (got.split(',').collect(), want.split(',').collect());
    assert_eq!(gv.len(), wv.len(), "zoo:{name}: the first epoch re-run from its recipe: {got} against {want}");
    if gpu {
        assert_eq!(gv[..2], wv[..2], "zoo:{name}: the first epoch re-run from its recipe: {got} against {want}");
        let (g, w): (f64, f64) = (gv[2].parse().unwrap(), wv[2].parse().unwrap());
        assert!(
            (g - w).abs() <= GPU_EPOCH_LOSS * w.abs(),
            "zoo:{name}: the first epoch's training loss re-run on the CPU: {got} against the GPU's {want} (within {GPU_EPOCH_LOSS})"
        );
    } else {
        assert_eq!(gv[..3], wv[..3], "zoo:{name}: the first epoch's training loss re-run from its recipe: {got} against {want}");
    }
    // validation: exact for cube and lifetime networks. A depth network's ranges go through
    // its read-out and the range fit in the tap domain, both improved since the U-Net entry
    // logged its first epoch (the local soft-argmax moved its epoch-1 RMSE 1.836 → 2.110 m,
    // MAE 1.318 → 1.246 m: a one-epoch network's scores are spread over the range); its
    // detection rate within 1 %, its errors within 25 %
    let columns: Vec<&str> = header.split(',').collect();
    for (k, (g, w)) in gv.iter().zip(&wv).enumerate().skip(3) {
        let (g, w): (f64, f64) = (g.parse().unwrap(), w.parse().unwrap());
        let tolerance = match columns.get(k) {
            _ if !header.contains("depth") => 0.0,
            Some(&"val_detection") => 0.01,
            _ => 0.25,
        };
        assert!(
            (g - w).abs() <= tolerance * w.abs(),
            "zoo:{name}: validation column {k} of the first epoch re-run: {got} against {want} (within {tolerance})"
        );
    }
    // the first epoch's checkpoint is a resumable run of the recorded config
    check_config(name, &dir.join(&out));
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join(&out).join(phase).join("checkpoint/state.json")).unwrap()).unwrap();
    assert_eq!(state["epoch"], 1, "zoo:{name}: paused after one epoch, its checkpoint in place");
}
