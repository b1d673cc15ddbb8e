//! `tcsense demo`: the toolkit's main job end to end on built-in defaults, with no input
//! files — the paper's prototype (4 taps, 2×2 blocks, L = 32, 607 MHz, tap + H 2 + W 2):
//! datasets, code design (random selection and deep sensing), code-memory export, TVAL3,
//! ADMM-Net and U-Net training within a time budget, ONNX export, ONNX Runtime, and
//! `DIR/report.html` with its figures.
//!
//! Glue only: every step is one call into the crates. Each step's outputs are written
//! atomically and a step whose outputs exist is skipped, so rerunning into the same
//! directory resumes (trainings continue from their checkpoints). The settings, and the
//! epochs sized to the budget from a measured step time, are fixed in `DIR/plan.json` on
//! the first run, so a resumed demo finishes the same run.

use crate::error::{bail, Context, PipelineError, Result};
use ndarray::{Array2, Array3, Array4, Axis, Ix3, Ix4};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use tcsense_datasets::store::{self, Generator, WriteOptions, DEFAULT_SHARD};
use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::{Dataset, TimeGrid};
use tcsense_infer::eval::{evaluate, open_decoder, EvalRow, EvalSettings};
use tcsense_infer::figures::{self, Series};
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::products::{depth_map, point_cloud, referenced_phasors, PeakOptions};
use tcsense_infer::report::{Block, Cell, Format, Report, Section, Table};
use tcsense_infer::selection::{evaluate as evaluate_codes, select, EvalSetup};
use tcsense_sensor::design::{design, Criterion, DesignOptions, Objective, Quiet};
use tcsense_sensor::identify::{Light, DEFAULT_ALIAS_THRESHOLD};
use tcsense_models::decoder::Control;
use tcsense_models::runs::{self, ModelConfig, CODES_FILE, CONFIG_FILE};
use tcsense_models::{AdmmNetConfig, Device, Prior, Tval3Options, UnetConfig};
use tcsense_sensor::codes::{Codes, DEFAULT_CLOCK_HZ};
use tcsense_sensor::measure::measure_batch;
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::npy::{read_npy, write_bytes, write_npy};
use tcsense_sensor::params::{C, DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::{export, generate, Irf, NoiseParams, Sampling, Sensor, SensorParams};
use tcsense_train::deep_sensing::LearnCodes;
use tcsense_train::{train, Progress, TrainConfig, TrainError};


/// Share of the budget given to the four trainings (the rest: data, code selection, TVAL3,
/// evaluation, export, timing, figures: about 50 s of the default demo on two cores).
const TRAINING_SHARE: f64 = 0.8;
/// Time per training step beyond the timed forward/backward/Adam step (ms): simulating the
/// batch's measurements, augmentation, validation, checkpoints (measured on the default demo).
const STEP_OVERHEAD_MS: f64 = 2.0;
/// Horizontal field of view of the rendered point clouds (the generator's default).
const FOV_DEG: f64 = 40.0;
/// The sensor's frame rate, the target of deployment (frames/s at 188×212).
const SENSOR_FPS: f64 = 21.0;

/// What a user asks of the demo; `None` takes the mode's default.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoOptions {
    /// About 2 minutes instead of about 10: 32×32 frames, fewer scenes, shorter training.
    pub quick: bool,
    /// Time for the whole demo in minutes (default 10, or 2 when `quick`): the training
    /// epochs are sized to it from a measured step time.
    pub budget_minutes: Option<f64>,
    /// Frame size `(H, W)` of the datasets (default 64×64, 32×32 when `quick`).
    pub size: Option<(usize, usize)>,
    /// LiDAR scenes (FLIm: half as many; default 400, 160 when `quick`).
    pub scenes: Option<usize>,
    /// Frame size `(H, W)` of the timing table (the sensor's 188×212).
    pub timing_size: (usize, usize),
    /// Seed of everything random (scenes, codes, weights, noise).
    pub seed: u64,
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions { quick: false, budget_minutes: None, size: None, scenes: None, timing_size: (188, 212), seed: 1 }
    }
}

/// Where a running demo reports to: the binary prints lines and draws progress bars, the
/// Python module writes lines to stderr. Called from the thread that runs the demo.
pub trait Observer: Sync {
    /// One line of the demo's log (steps, plans, files written, timings).
    fn line(&self, text: &str);
    /// Progress of a long step: `done` of `of` items of `what` (dataset scenes, evaluated
    /// frames); `done == of` ends it.
    fn items(&self, _what: &str, _done: usize, _of: usize) {}
    /// Where a training reports its steps and epochs.
    fn training(&self) -> &dyn Progress;
}

/// What a finished demo left behind.
#[derive(Debug, Clone, PartialEq)]
pub struct DemoSummary {
    /// `DIR/report.html`.
    pub report: PathBuf,
    /// Wall time of this invocation (s).
    pub seconds: f64,
    /// Whether it resumed a demo started before in the same directory.
    pub resumed: bool,
}

/// What the user asked for: a rerun into the same directory must ask for the same.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Request {
    quick: bool,
    budget_minutes: f64,
    size: [usize; 2],
    lidar_scenes: usize,
    flim_scenes: usize,
    timing_size: [usize; 2],
    seed: u64,
}

/// One training of the demo, sized to its share of the budget.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct TrainPlan {
    /// Run directory under `runs/`.
    name: String,
    /// What it is, for people.
    title: String,
    budget_s: f64,
    /// Measured median time of one step (batch 2) at the training crop.
    step_ms: f64,
    steps_per_epoch: usize,
    epochs: usize,
}

/// Everything the demo does, fixed on its first run (`plan.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct Plan {
    request: Request,
    /// Training crop (the frames when `None`).
    crop: Option<[usize; 2]>,
    /// Random code sets scored by TVAL3 in the selection, and the validation items scored.
    candidates: usize,
    select_items: usize,
    /// Test items of the metric tables.
    lidar_eval_items: usize,
    flim_eval_items: usize,
    /// Validation items per epoch.
    val_items: usize,
    timing_rounds: usize,
    trainings: Vec<TrainPlan>,
}

/// The trainings and their shares of the training budget. `zoo-lidar` fine-tunes the zoo's
/// LiDAR decoder ([`ZOO_ENTRY`]) to the selected codes in the time `admm-lidar` trains from
/// scratch; it is left out when the zoo does not hold that entry.
const TRAININGS: [(&str, &str, f64); 5] = [
    ("admm-lidar", "ADMM-Net on LiDAR, selected codes", 0.2),
    ("learned-lidar", "ADMM-Net on LiDAR, codes learned with it (deep sensing)", 0.2),
    ("unet-lidar", "Aᵀ + U-Net depth decoder on LiDAR, selected codes", 0.15),
    ("admm-flim", "ADMM-Net with the delay prior on FLIm (heterodyne K = 8), selected codes", 0.25),
    ("zoo-lidar", "ADMM-Net from the zoo (zoo:admm-lidar-delay), fine-tuned to the selected codes in the same time", 0.2),
];

/// The zoo entry the demo evaluates as shipped (on its own codes) and fine-tunes.
const ZOO_ENTRY: &str = "admm-lidar-delay";

/// The zoo entry's run directory and network, when the zoo holds it with the dataset's bins
/// (a binary installed without the source tree's `zoo/` and no `TCSENSE_ZOO` has none).
fn zoo_entry(ds: &Dataset) -> Option<(PathBuf, ModelConfig)> {
    zoo_entry_named(ZOO_ENTRY, ds)
}

/// The zoo's lifetime decoder, evaluated as shipped (on its own codes) in the FLIm table.
const ZOO_LIFETIME: &str = "lifetime-flim";

/// The zoo's FLIm ADMM-Net, evaluated as shipped (on its own codes) in the FLIm table.
const ZOO_FLIM_CUBE: &str = "admm-flim-delay";

/// Zoo entry `name`'s run directory and network, when the zoo holds it for the dataset's
/// sampling and bins with 4 taps.
fn zoo_entry_named(name: &str, ds: &Dataset) -> Option<(PathBuf, ModelConfig)> {
    let dir = tcsense_models::zoo::resolve(&format!("{}{name}", tcsense_models::zoo::PREFIX)).ok()?;
    let spec: runs::RunSpec = serde_json::from_value(runs::read_config_json(&dir.join(CONFIG_FILE)).ok()?).ok()?;
    (spec.sampling == ds.manifest.grid.sampling && spec.model.bins() == ds.manifest.bins && spec.model.taps() == 4).then_some((dir, spec.model))
}

impl Request {
    fn from_options(a: &DemoOptions) -> Result<Self> {
        let budget = a.budget_minutes.unwrap_or(if a.quick { 2.0 } else { 10.0 });
        if !(budget.is_finite() && budget > 0.0) {
            bail!("--budget-minutes {budget}: expected a positive number of minutes");
        }
        let (h, w) = a.size.unwrap_or(if a.quick { (32, 32) } else { (64, 64) });
        if h < 8 || w < 8 || h % 8 != 0 || w % 8 != 0 {
            bail!("--size {h}x{w}: expected multiples of 8 (the 2x2 block and the U-Net's 3 levels), at least 8x8");
        }
        let lidar = a.scenes.unwrap_or(if a.quick { 160 } else { 400 });
        if lidar < 30 {
            bail!("--scenes {lidar}: expected at least 30 (the paper's splits need 3 test items)");
        }
        let (th, tw) = a.timing_size;
        if th == 0 || tw == 0 || th % 4 != 0 || tw % 4 != 0 {
            bail!("--timing-size {th}x{tw}: expected multiples of 4");
        }
        Ok(Request { quick: a.quick, budget_minutes: budget, size: [h, w], lidar_scenes: lidar, flim_scenes: (lidar / 2).max(30), timing_size: [th, tw], seed: a.seed })
    }
}


fn physical_irf() -> Irf {
    Irf::Physical { laser_fwhm_s: DEFAULT_LASER_FWHM_S, tap_tau_s: DEFAULT_TAP_TAU_S }
}

/// The sensor of a dataset's grid with these codes (physical IRF).
fn sensor(codes: &Codes, ds: &Dataset) -> Result<Sensor> {
    Ok(Sensor::ideal(codes.clone(), ds.manifest.grid.sampling, physical_irf())?)
}

/// Numbered steps with their wall times.
struct Steps<'a> {
    obs: &'a dyn Observer,
    n: usize,
    of: usize,
    times: Vec<(String, f64)>,
}

impl Steps<'_> {
    fn run<T>(&mut self, what: &str, f: impl FnOnce() -> Result<T>) -> Result<T> {
        self.n += 1;
        self.obs.line(&format!("[{}/{}] {what}", self.n, self.of));
        let t0 = Instant::now();
        let v = f()?;
        self.times.push((what.to_string(), t0.elapsed().as_secs_f64()));
        Ok(v)
    }
}

fn cancelled(cancel: &AtomicBool) -> Result<()> {
    if cancel.load(Ordering::SeqCst) {
        bail!("interrupted; rerun the same command to resume");
    }
    Ok(())
}

/// Run the demo into `dir` (rerunning into the same directory resumes it). `cancel` stops
/// it at the next step or training step, leaving what is done for the rerun.
pub fn run(options: &DemoOptions, dir: &Path, obs: &dyn Observer, cancel: &AtomicBool) -> Result<DemoSummary> {
    let t_start = Instant::now();
    let request = Request::from_options(options)?;
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    for sub in ["codes", "runs", "onnx", "results", "figures", "frames"] {
        std::fs::create_dir_all(dir.join(sub)).with_context(|| format!("cannot create {}", dir.join(sub).display()))?;
    }
    let plan_path = dir.join("plan.json");
    let saved: Option<Plan> = if plan_path.exists() {
        let p: Plan = serde_json::from_slice(&std::fs::read(&plan_path).with_context(|| format!("cannot read {}", plan_path.display()))?)
            .with_context(|| format!("{}: not a demo plan; choose another output directory", plan_path.display()))?;
        if p.request != request {
            bail!(
                "{} holds a demo started with other settings ({}); rerun with the same flags to resume it, or choose another directory",
                dir.display(),
                serde_json::to_string(&p.request)?
            );
        }
        Some(p)
    } else {
        None
    };
    let resumed = saved.is_some();
    // datasets and (on a first run) the plan, then codes, the trainings, export, evaluation,
    // frames, timing and the report: `of` is fixed once the plan is known
    let mut steps = Steps { obs, n: 0, of: if saved.is_some() { 11 } else { 12 }, times: Vec::new() };
    let seed = request.seed;
    let [h, w] = request.size;
    let constraints = generate::PROTOTYPE_CONSTRAINTS;
    obs.line(&format!(
        "tcsense demo: the prototype sensor (4 taps, 2x2 blocks, L = 32, 607 MHz, {}), {h}x{w} frames, budget {} min, into {}{}",
        constraints.label(),
        request.budget_minutes,
        dir.display(),
        if saved.is_some() { " (resuming)" } else { "" }
    ));

    // 1. datasets
    let lidar_dir = dir.join("lidar");
    let flim_dir = dir.join("flim");
    steps.run("datasets: LiDAR with multipath and FLIm (heterodyne K = 8), randomised generators", || {
        let lidar = Generator::Lidar(LidarParams { height: h, width: w, ..Default::default() });
        generate_once(&lidar, &TimeGrid::default(), request.lidar_scenes, seed, &lidar_dir, obs, cancel)?;
        let flim = Generator::Flim(FlimParams { height: h, width: w, ..Default::default() });
        let grid = TimeGrid { sampling: Sampling::Heterodyne(8), ..TimeGrid::default() };
        generate_once(&flim, &grid, request.flim_scenes, seed.wrapping_add(1), &flim_dir, obs, cancel)
    })?;
    let lidar = Dataset::open(&lidar_dir)?;
    let flim = Dataset::open(&flim_dir)?;

    // the plan: sizes by mode, epochs from measured step times
    let plan = match saved {
        Some(p) => p,
        None => {
            let p = steps.run("plan: timing one training step of each network to size the epochs to the budget", || make_plan(&request, &lidar, &flim, obs))?;
            write_bytes(&plan_path, (serde_json::to_string_pretty(&p)? + "\n").as_bytes())?;
            p
        }
    };
    steps.of = steps.n + 1 + plan.trainings.len() + 5;
    for t in &plan.trainings {
        obs.line(&format!("  {:<14} {:>4} epochs × {:>4} steps × {:>6.1} ms ≈ {:>5.0} s  ({})", t.name, t.epochs, t.steps_per_epoch, t.step_ms, (t.epochs * t.steps_per_epoch) as f64 * t.step_ms / 1e3, t.title));
    }

    // 2. codes: one random draw, the best of `candidates` by TVAL3 (the paper's selection), and
    // codes designed for range identifiability (the demo's selected set), exported
    let random_path = dir.join("codes/random.json");
    let mse_path = dir.join("codes/best-mse.json");
    let selected_path = dir.join("codes/selected.json");
    let selection_path = dir.join("results/selection.json");
    steps.run("codes: random under the constraints, the best of several by TVAL3 (noise-free), and codes designed for range identifiability (selected), exported to the code memory", || {
        if !random_path.exists() {
            generate::prototype_codes(seed)?.save(&random_path)?;
        }
        if !selected_path.exists() || !selection_path.exists() || !mse_path.exists() {
            let x = lidar.load("val", "x")?.into_dimensionality::<Ix4>()?;
            let cubes: Vec<Array3<f32>> = x.axis_iter(Axis(0)).take(plan.select_items).map(|v| v.to_owned()).collect();
            let g = lidar.manifest.grid;
            let setup = EvalSetup { base: SensorParams { sampling: g.sampling, irf: physical_irf(), length: g.length, clock_hz: g.clock_hz, ..Default::default() }, tval3: Tval3Options::default() };
            let mut on = |c: &tcsense_infer::selection::Candidate| obs.line(&format!("  candidate seed {:>3}: TVAL3 MSE {:.4e}", c.seed, c.mse));
            let (best, all) = select(generate::PROTOTYPE_SHAPE, DEFAULT_CLOCK_HZ, constraints, plan.candidates, seed, &setup, &cubes, &mut on, cancel)?;
            // design by identifiability: closed form, seconds
            let spec = SensorParams { sampling: g.sampling, irf: physical_irf(), ..SensorParams::from_codes(&best) }.validate()?;
            let obj = Objective::new(Criterion::Range, &spec, Light::default(), DEFAULT_ALIAS_THRESHOLD);
            let designed = design(&obj, generate::PROTOTYPE_SHAPE, DEFAULT_CLOCK_HZ, constraints, &DesignOptions { seed, ..Default::default() }, &Quiet, cancel)?;
            let designed_mse = evaluate_codes(&designed.codes, &setup, &cubes, cancel)?;
            obs.line(&format!(
                "  designed for range identifiability: alias {:.3}, worst range bound {:.3} bins, TVAL3 MSE {designed_mse:.4e}",
                designed.score.alias, designed.score.worst
            ));
            let v = json!({
                "items": cubes.len(), "split": "val", "noise": "none",
                "candidates": all.iter().map(|c| json!({"seed": c.seed, "mse": c.mse})).collect::<Vec<_>>(),
                "designed": { "criterion": "range", "mse": designed_mse, "alias": designed.score.alias, "worst_bound_bins": designed.score.worst, "mean_bound_bins": designed.score.mean, "provenance": designed.codes.provenance },
            });
            write_bytes(&selection_path, (serde_json::to_string_pretty(&v)? + "\n").as_bytes())?;
            best.save(&mse_path)?;
            designed.codes.save(&selected_path)?;
        }
        export::export(&Codes::load(&selected_path)?, &dir.join("code-memory/selected"))?;
        Ok(())
    })?;
    let selected = Codes::load(&selected_path)?;

    // 3. trainings
    let runs_dir = dir.join("runs");
    let eval_noise = NoiseParams::default().validate()?;
    for t in &plan.trainings {
        cancelled(cancel)?;
        let (ds, ds_dir) = if t.name.ends_with("flim") { (&flim, &flim_dir) } else { (&lidar, &lidar_dir) };
        steps.run(&format!("training {}: {} epochs", t.title, t.epochs), || train_one(t, &plan, ds, ds_dir, &selected, &runs_dir.join(&t.name), obs, cancel))?;
    }
    let learned_dir = runs_dir.join("learned-lidar");
    let learned = Codes::load(&learned_dir.join(CODES_FILE))?;
    learned.save(&dir.join("codes/learned.json"))?;
    let regs = export::export(&learned, &dir.join("code-memory/learned"))?;
    obs.line(&format!("  learned codes exported to {}: {} channels of {} bytes, ECLEN = {}", dir.join("code-memory/learned").display(), regs.channel_count, regs.bytes_per_channel, regs.ECLEN));
    // what every code set of the demo lets the taps tell apart
    let ident = crate::identifiability::analyse(&[("random", &Codes::load(&random_path)?), ("best MSE", &Codes::load(&mse_path)?), ("selected", &selected), ("learned", &learned)], physical_irf())?;
    write_json(&dir.join("results/identifiability.json"), &ident)?;
    obs.line("  identifiability of the code sets (physical IRF, 1000 e⁻ signal):");
    for l in crate::identifiability::lines(&ident) {
        obs.line(&l);
    }

    // 4. ONNX export
    steps.run("ONNX export of every trained decoder (opset 17)", || {
        for t in &plan.trainings {
            let out = dir.join("onnx").join(format!("{}.onnx", t.name));
            if !out.exists() {
                let run = runs::load(&runs_dir.join(&t.name), &Device::flex())?;
                let bytes = export_to(&run, ExportOptions::default(), &out)?;
                obs.line(&format!("  wrote {} ({:.1} kB)", out.display(), bytes as f64 / 1e3));
            }
        }
        Ok(())
    })?;
    let onnx = |name: &str| format!("onnx:{}", dir.join("onnx").join(format!("{name}.onnx")).display());
    let run_of = |kind: &str, name: &str| format!("{kind}:{}", runs_dir.join(name).display());

    // 5. metric tables: every decoder on the same noisy measurements of the same test items
    let lidar_json = dir.join("results/lidar.json");
    let flim_json = dir.join("results/flim.json");
    steps.run("evaluation on the test splits (same noisy measurements for every decoder): TVAL3, burn and ONNX Runtime", || {
        let settings = |items| EvalSettings { split: "test".into(), items: Some(items), noise: Some(eval_noise), seed, sensor: None };
        let on_item = |label: &str, done: usize, of: usize| obs.items(label.rsplit('/').next().unwrap_or(label), done, of);
        // decoders as (table name, decoder spec), evaluated on one sensor; a row per decoder
        let rows_of = |ds: &Dataset, a: &Sensor, decoders: &[(&str, String)], items, row: &dyn Fn(&EvalRow, &str, &str) -> Value| -> Result<Vec<Value>> {
            let mut dec = decoders.iter().map(|(_, spec)| open_decoder(spec, &Tval3Options::default(), &Device::flex())).collect::<std::result::Result<Vec<_>, _>>()?;
            let r = evaluate(ds, a, &mut dec, &settings(items), &on_item, cancel)?;
            Ok(r.iter().zip(decoders).map(|(r, (name, spec))| row(r, name, engine(spec))).collect())
        };
        // a zoo entry decoded as shipped: on its own codes, with the same scenes and noise seeds
        let shipped_rows = |ds: &Dataset, zoo_dir: &Path, decoder: (&str, String), items: usize, row: &dyn Fn(&EvalRow, &str, &str) -> Value| -> Result<Vec<Value>> {
            let codes = Codes::load(&zoo_dir.join(CODES_FILE))?;
            rows_of(ds, &sensor(&codes, ds)?, &[decoder], items, row)
        };
        let cube_decoders = |run: &str| vec![("TVAL3", "tval3".to_string()), ("ADMM-Net", run_of("admm-net", run)), ("ADMM-Net", onnx(run))];
        if !lidar_json.exists() {
            let mut selected_set = cube_decoders("admm-lidar");
            selected_set.extend([("Aᵀ + U-Net", run_of("unet", "unet-lidar")), ("Aᵀ + U-Net", onnx("unet-lidar"))]);
            let mut rows = rows_of(&lidar, &sensor(&selected, &lidar)?, &selected_set, plan.lidar_eval_items, &|r, n, e| lidar_row(r, "selected", n, e))?;
            rows.extend(rows_of(&lidar, &sensor(&learned, &lidar)?, &cube_decoders("learned-lidar"), plan.lidar_eval_items, &|r, n, e| lidar_row(r, "learned", n, e))?);
            // the zoo's decoder fine-tuned to the selected codes, and as shipped on its own codes
            if let (true, Some((zoo_dir, _))) = (plan.trainings.iter().any(|t| t.name == "zoo-lidar"), zoo_entry(&lidar)) {
                let tuned = [("ADMM-Net (zoo, fine-tuned)", run_of("admm-net", "zoo-lidar"))];
                rows.extend(rows_of(&lidar, &sensor(&selected, &lidar)?, &tuned, plan.lidar_eval_items, &|r, n, e| lidar_row(r, "selected", n, e))?);
                let shipped = ("ADMM-Net (zoo, as shipped)", format!("admm-net:{}", zoo_dir.display()));
                rows.extend(shipped_rows(&lidar, &zoo_dir, shipped, plan.lidar_eval_items, &|r, n, e| lidar_row(r, "the zoo's", n, e))?);
            }
            write_json(&lidar_json, &json!({ "split": "test", "items": plan.lidar_eval_items, "noise": eval_noise, "noise_seed": seed, "frame": [h, w], "rows": rows }))?;
        }
        if !flim_json.exists() {
            let mut flim_set = cube_decoders("admm-flim");
            flim_set.push(("lifetime fit to the taps", "lifetime-fit".to_string()));
            let mut rows = rows_of(&flim, &sensor(&selected, &flim)?, &flim_set, plan.flim_eval_items, &|r, n, e| flim_row(r, "selected", n, e))?;
            // the zoo's FLIm decoders as shipped
            for (entry, name, kind) in [(ZOO_FLIM_CUBE, "ADMM-Net (zoo, as shipped, its own codes)", "admm-net"), (ZOO_LIFETIME, "lifetime decoder (zoo, as shipped, its own codes)", "lifetime")] {
                if let Some((zoo_dir, _)) = zoo_entry_named(entry, &flim) {
                    let shipped = (name, format!("{kind}:{}", zoo_dir.display()));
                    rows.extend(shipped_rows(&flim, &zoo_dir, shipped, plan.flim_eval_items, &|r, n, e| flim_row(r, "the zoo's", n, e))?);
                }
            }
            write_json(&flim_json, &json!({ "split": "test", "items": plan.flim_eval_items, "noise": eval_noise, "noise_seed": seed, "frame": [h, w], "rows": rows }))?;
        }
        Ok(())
    })?;

    // 6. one frame of each dataset through every decoder, kept for the figures
    steps.run("one test frame of each dataset through every decoder (for the figures)", || {
        decode_frames(dir, &lidar, &flim, &selected, &learned, &eval_noise, seed, cancel)
    })?;

    // 7. timing at the sensor's frame size
    let timing_json = dir.join("results/timing.json");
    steps.run(&format!("timing at {}x{}: ONNX Runtime (2 and 1 threads) and burn, per frame", request.timing_size[0], request.timing_size[1]), || {
        if timing_json.exists() {
            return Ok(());
        }
        let mut all = Vec::new();
        for name in ["unet-lidar", "admm-lidar", "admm-flim"] {
            cancelled(cancel)?;
            let run = runs::load(&runs_dir.join(name), &Device::flex())?;
            let model = dir.join("onnx").join(format!("{name}.onnx"));
            let t = tcsense_infer::timing::time_decoder(Some(&run), &model, (request.timing_size[0], request.timing_size[1]), &[2, 1], plan.timing_rounds)?;
            for e in &t.engines {
                obs.line(&format!("  {name:<12} {:<26} {:>9.1} ms/frame {:>7.1} frames/s", e.engine, e.ms_per_frame, e.frames_per_s));
            }
            all.push(json!({ "run": name, "timing": t }));
        }
        write_json(&timing_json, &json!({ "sensor_fps": SENSOR_FPS, "decoders": all }))
    })?;

    // 8. figures and the report
    let times: Vec<Value> = steps.times.iter().map(|(what, s)| json!({ "step": what, "seconds": s })).collect();
    steps.run("figures and report.html", || {
        let figs = draw_figures(dir, &lidar, &flim, &selected, &learned)?;
        let report = build_report(dir, &plan, &figs, &times, t_start.elapsed().as_secs_f64())?;
        report.write(&dir.join("report.html"))?;
        Ok(())
    })?;
    let total = t_start.elapsed().as_secs_f64();
    let record: Vec<Value> = steps.times.iter().map(|(what, s)| json!({ "step": what, "seconds": s })).collect();
    write_json(&dir.join("results/steps.json"), &json!({ "total_seconds": total, "steps": record }))?;
    obs.line(&format!("wrote {} in {:.0} s ({:.1} min)", dir.join("report.html").display(), total, total / 60.0));
    Ok(DemoSummary { report: dir.join("report.html"), seconds: total, resumed })
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    write_bytes(path, (serde_json::to_string_pretty(v)? + "\n").as_bytes())?;
    Ok(())
}

/// Generate a dataset unless a complete one is there (a partial one is never left: the
/// generator writes atomically).
fn generate_once(gen: &Generator, grid: &TimeGrid, count: usize, seed: u64, out: &Path, obs: &dyn Observer, cancel: &AtomicBool) -> Result<()> {
    if out.join("manifest.json").exists() && Dataset::open(out).is_ok() {
        return Ok(());
    }
    let what = out.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let progress = || obs.items(&what, done.fetch_add(1, Ordering::Relaxed) + 1, count);
    let m = store::generate(gen, grid, count, seed, out, &WriteOptions { shard_size: DEFAULT_SHARD, force: true, progress: &progress, cancel })?;
    obs.line(&format!("  wrote {}: {count} scenes, {}x{}, T = {} bins of {:.1} ps", out.display(), m.size[0], m.size[1], m.bins, m.bin_width_s * 1e12));
    Ok(())
}

/// The model of a training.
fn model_of(name: &str, ds: &Dataset) -> ModelConfig {
    let (m, t) = (4, ds.manifest.bins);
    if name.starts_with("zoo") {
        if let Some((_, model)) = zoo_entry(ds) {
            return model;
        }
    }
    if name.starts_with("unet") {
        let range_m = C * ds.manifest.bin_width_s * t as f64 / 2.0;
        ModelConfig::Unet(UnetConfig::new(m, t, range_m).with_head(tcsense_models::UnetHead::ScoreVolume))
    } else if name.ends_with("flim") {
        // onsets anywhere in the cycle: the delay-equivariant prior, 4 channels per bin
        ModelConfig::AdmmNet(AdmmNetConfig::cpu(m, t).with_prior(Prior::Delay).with_channels(4).with_normalize(true))
    } else {
        ModelConfig::AdmmNet(AdmmNetConfig::cpu(m, t).with_normalize(true))
    }
}

/// Sizes by mode, and epochs from a measured training step of each network.
fn make_plan(r: &Request, lidar: &Dataset, flim: &Dataset, obs: &dyn Observer) -> Result<Plan> {
    let [h, w] = r.size;
    let crop = if h > 32 && w > 32 { Some([32, 32]) } else { None };
    let [ch, cw] = crop.unwrap_or(r.size);
    let codes = generate::prototype_codes(r.seed)?;
    let budget_s = r.budget_minutes * 60.0 * TRAINING_SHARE;
    let mut trainings = Vec::new();
    for (name, title, share) in TRAININGS {
        let ds = if name.ends_with("flim") { flim } else { lidar };
        if name.starts_with("zoo") && zoo_entry(ds).is_none() {
            obs.line(&format!("  {name}: skipped, the zoo has no entry {ZOO_ENTRY} for these bins (see TCSENSE_ZOO)"));
            continue;
        }
        let a = sensor(&codes, ds)?;
        let step = tcsense_train::bench::bench_step(a.matrix(), &model_of(name, ds), ch, cw, 3)?.step_ms;
        // learning the codes adds the operators' rebuild from A(θ) and the logits' step
        let step = if name.starts_with("learned") { step * 1.3 } else { step } + STEP_OVERHEAD_MS;
        let train_items = ds.manifest.splits.iter().find(|s| s.name == "train").map_or(0, |s| s.count);
        let steps_per_epoch = train_items.div_ceil(2).max(1);
        let fit = (share * budget_s / (step / 1e3 * steps_per_epoch as f64)).floor() as usize;
        // deep sensing needs relaxed epochs and at least one on the projected codes
        let epochs = fit.max(if name.starts_with("learned") { 3 } else { 1 });
        obs.line(&format!("  {name}: {step:.1} ms per step at {ch}x{cw}, {steps_per_epoch} steps per epoch → {epochs} epochs"));
        trainings.push(TrainPlan { name: name.into(), title: title.into(), budget_s: share * budget_s, step_ms: step, steps_per_epoch, epochs });
    }
    let q = r.quick;
    Ok(Plan {
        request: r.clone(),
        crop,
        candidates: if q { 4 } else { 8 },
        select_items: if q { 1 } else { 2 },
        lidar_eval_items: if q { 4 } else { 8 },
        flim_eval_items: if q { 2 } else { 4 },
        val_items: if q { 4 } else { 8 },
        timing_rounds: if q { 2 } else { 3 },
        trainings,
    })
}

/// Train (or resume) one run of the plan.
#[allow(clippy::too_many_arguments)]
fn train_one(t: &TrainPlan, plan: &Plan, ds: &Dataset, ds_dir: &Path, codes: &Codes, run: &Path, obs: &dyn Observer, cancel: &AtomicBool) -> Result<()> {
    let resume = run.join(CONFIG_FILE).exists();
    let cfg = if resume {
        TrainConfig::load(&run.join(CONFIG_FILE))?
    } else {
        let mut cfg = TrainConfig::for_dataset(model_of(&t.name, ds), ds_dir, ds);
        cfg.run.irf = physical_irf();
        cfg.epochs = t.epochs;
        cfg.seed = plan.request.seed;
        cfg.max_val_items = Some(plan.val_items);
        if let Some(c) = plan.crop {
            cfg.augment = cfg.augment.map(|g| tcsense_train::Augmentation { crop: Some(c), ..g });
        }
        if t.name.starts_with("learned") {
            cfg.learn_codes = Some(LearnCodes::new(codes.constraints, t.epochs));
        }
        if t.name.starts_with("zoo") {
            let Some((zoo_dir, _)) = zoo_entry(ds) else { bail!("the plan fine-tunes zoo:{ZOO_ENTRY}, but the zoo no longer holds it (see TCSENSE_ZOO)") };
            cfg.init_from = Some(zoo_dir.display().to_string());
        }
        cfg
    };
    let start = if resume && t.name.starts_with("learned") && !run.join(CODES_FILE).exists() { Codes::load(&run.join(tcsense_train::deep_sensing::START_CODES_FILE))? } else if resume { Codes::load(&run.join(CODES_FILE))? } else { codes.clone() };
    let res = train(&cfg, &start, run, resume, obs.training(), cancel);
    match res {
        Ok(_) => Ok(()),
        Err(TrainError::Cancelled) => bail!("interrupted; the last checkpoint in {} is kept: rerun the same command to resume", run.display()),
        Err(e) => Err(e.into()),
    }
}

/// The engine that runs a decoder given by its spec (`tval3`, `KIND:RUN`, `onnx:MODEL`).
fn engine(spec: &str) -> &'static str {
    if spec.starts_with("onnx:") {
        "ONNX Runtime"
    } else if spec == "tval3" {
        "Rust (TVAL3)"
    } else if spec == "lifetime-fit" {
        "Rust (fit to the taps)"
    } else {
        "burn (flex)"
    }
}

/// A row of a metric table: what every decoder has, and the domain's own metrics `own`.
fn result_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str, own: Value) -> Value {
    let mut row = json!({
        "decoder": decoder,
        "codes": codes,
        "engine": engine,
        "items": r.items,
        "mse": r.mse,
        "psnr_db": r.psnr_db,
        "ms_per_frame": r.seconds_per_frame * 1e3,
    });
    if let (Some(row), Value::Object(own)) = (row.as_object_mut(), own) {
        row.extend(own);
    }
    row
}

fn lidar_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str) -> Value {
    let own = json!({
        "range_rmse_m": r.depth.iter().map(|d| d.rmse_m).collect::<Vec<_>>(),
        "range_mae_m": r.depth.iter().map(|d| d.mae_m).collect::<Vec<_>>(),
        "detection_pct": r.depth.iter().map(|d| 100.0 * d.detection_rate()).collect::<Vec<_>>(),
    });
    result_row(r, codes, decoder, engine, own)
}

fn flim_row(r: &EvalRow, codes: &str, decoder: &str, engine: &str) -> Value {
    let own = json!({
        "lifetime_mae_ns": r.lifetime_mae_s.map(|v| v * 1e9),
        "lifetime_within_02ns_pct": r.lifetime_within_02ns.map(|v| v * 100.0),
    });
    result_row(r, codes, decoder, engine, own)
}

/// Decode one test item of each dataset (with the evaluation's noise for that item) with every
/// decoder and keep the inputs and outputs in `DIR/frames/` as `.npy`; which items, in
/// `DIR/frames/frames.json`.
#[allow(clippy::too_many_arguments)]
fn decode_frames(dir: &Path, lidar: &Dataset, flim: &Dataset, selected: &Codes, learned: &Codes, noise: &NoiseParams, seed: u64, cancel: &AtomicBool) -> Result<()> {
    let frames = dir.join("frames");
    let runs_dir = dir.join("runs");
    let ctl = Control::quiet(cancel);
    // the LiDAR frame: the first test item with a return behind a sheet in ≥ 5 % of its pixels
    let depth = lidar.load("test", "depth")?.into_dimensionality::<Ix4>()?;
    let (n, k, fh, fw) = depth.dim();
    let lidar_index = if k > 1 { (0..n).find(|&i| depth.slice(ndarray::s![i, 1, .., ..]).iter().filter(|v| v.is_finite()).count() * 20 >= fh * fw).unwrap_or(0) } else { 0 };
    write_json(&frames.join("frames.json"), &json!({ "lidar_test_index": lidar_index, "flim_test_index": 0 }))?;
    let item = |ds: &Dataset, i: usize| -> Result<Array4<f32>> {
        let x = ds.load("test", "x")?.into_dimensionality::<Ix4>()?;
        Ok(x.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1)).to_owned())
    };
    let jobs: [FrameJob<'_>; 3] = [
        ("lidar", lidar, selected, vec![("tval3", "tval3".into()), ("admm", format!("admm-net:{}", runs_dir.join("admm-lidar").display())), ("unet", format!("unet:{}", runs_dir.join("unet-lidar").display()))]),
        ("lidar-learned", lidar, learned, vec![("admm", format!("admm-net:{}", runs_dir.join("learned-lidar").display()))]),
        ("flim", flim, selected, vec![("tval3", "tval3".into()), ("admm", format!("admm-net:{}", runs_dir.join("admm-flim").display())), ("fit", "lifetime-fit".into())]),
    ];
    for (tag, ds, codes, decoders) in jobs {
        let a = sensor(codes, ds)?;
        let index = if tag.starts_with("lidar") { lidar_index } else { 0 };
        let x = item(ds, index)?;
        let (_, _, fh, fw) = x.dim();
        let y_path = frames.join(format!("{tag}-y.npy"));
        // the evaluation's noise for this item
        let y = measure_batch(&a.plan(fh, fw)?, &x.view(), Some(noise), derive_seed(seed, index as u64))?;
        write_npy(&y_path, &y.index_axis(Axis(0), 0).to_owned().view())?;
        // the truth, once per dataset (`lidar-learned` shares `lidar`'s)
        let x_path = frames.join(format!("{}-x.npy", tag.split('-').next().unwrap_or(tag)));
        if !x_path.exists() {
            write_npy(&x_path, &x.index_axis(Axis(0), 0).to_owned().view())?;
        }
        for (name, spec) in decoders {
            let out_cube = frames.join(format!("{tag}-{name}.npy"));
            let out_depth = frames.join(format!("{tag}-{name}-depth.npy"));
            let out_lifetime = frames.join(format!("{tag}-{name}-lifetime.npy"));
            if out_cube.exists() || out_depth.exists() || out_lifetime.exists() {
                continue;
            }
            let mut d = open_decoder(&spec, &Tval3Options::default(), &Device::flex())?;
            let out = d.decoder.decode(y.view(), &a, &ctl).map_err(|e| PipelineError::Invalid(format!("{spec}: {e}")))?;
            if let Some(c) = out.cube {
                write_npy(&out_cube, &c.index_axis(Axis(0), 0).to_owned().view())?;
            }
            if let Some(dp) = out.depth {
                write_npy(&out_depth, &dp.index_axis(Axis(0), 0).to_owned().view())?;
            }
            if let Some(l) = out.lifetime {
                write_npy(&out_lifetime, &l.index_axis(Axis(0), 0).to_owned().view())?;
            }
        }
    }
    Ok(())
}

/// One dataset's test frame through decoders: (file tag, dataset, codes, [(name, decoder spec)]).
type FrameJob<'a> = (&'a str, &'a Dataset, &'a Codes, Vec<(&'a str, String)>);

fn read3(path: &Path) -> Result<Array3<f32>> {
    read_npy(path)?.into_dimensionality::<Ix3>().with_context(|| format!("{}: expected a rank-3 array", path.display()))
}

/// Three distinct pixels worth looking at: `first` where it exists, the centre, `last`, and
/// the quarter points where those coincide.
fn pick_pixels(h: usize, w: usize, first: Option<(usize, usize)>, last: Option<(usize, usize)>) -> Vec<(usize, usize)> {
    let mut v: Vec<(usize, usize)> = Vec::new();
    for p in [first, Some((h / 2, w / 2)), last, Some((h / 4, w / 4)), Some((3 * h / 4, 3 * w / 4))].into_iter().flatten() {
        if !v.contains(&p) && v.len() < 3 {
            v.push(p);
        }
    }
    v
}

/// Which figures were drawn (file names under `figures/`).
struct Figures {
    files: Vec<&'static str>,
}

fn draw_figures(dir: &Path, lidar: &Dataset, flim: &Dataset, selected: &Codes, learned: &Codes) -> Result<Figures> {
    let f = dir.join("figures");
    let fr = dir.join("frames");
    let mut files = Vec::new();
    let mut out = |name: &'static str| {
        files.push(name);
        f.join(name)
    };
    // codes
    figures::codes(&out("codes-random.png"), "random codes", &Codes::load(&dir.join("codes/random.json"))?)?;
    figures::codes(&out("codes-selected.png"), "selected codes (designed for range identifiability)", selected)?;
    figures::codes(&out("codes-best-mse.png"), "the best random codes by TVAL3 MSE", &Codes::load(&dir.join("codes/best-mse.json"))?)?;
    let ident = read_json(&dir.join("results/identifiability.json"))?;
    crate::identifiability::draw(&ident, &out("identifiability-range.png"), &out("identifiability-lifetime.png"))?;
    figures::codes(&out("codes-learned.png"), "learned codes (deep sensing, projected)", learned)?;
    let sel = read_json(&dir.join("results/selection.json"))?;
    let pts: Vec<(f64, f64)> = sel["candidates"].as_array().map(|a| a.iter().filter_map(|c| Some((c["seed"].as_f64()?, c["mse"].as_f64()?))).collect()).unwrap_or_default();
    figures::log_chart(&out("selection.png"), "Code selection: TVAL3 MSE of each random candidate (noise-free)", "candidate seed", "MSE of the reconstruction", &[Series { label: "candidate".into(), points: pts }])?;

    // tap images of the LiDAR frame
    let y = read3(&fr.join("lidar-y.npy"))?;
    let taps: Vec<(String, Array2<f32>)> = (0..y.dim().0).map(|m| (format!("tap {m}"), y.index_axis(Axis(0), m).to_owned())).collect();
    let panels: Vec<(&str, ndarray::ArrayView2<f32>)> = taps.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    figures::maps(&out("taps.png"), "Tap images of the LiDAR test frame (noisy, selected codes)", &panels, "tap signal (units of A·x)", None)?;

    // LiDAR: waveforms, depth maps, errors, point clouds
    let bin_w = lidar.manifest.bin_width_s;
    let range_m = C * bin_w * lidar.manifest.bins as f64 / 2.0;
    let x = read3(&fr.join("lidar-x.npy"))?;
    let (_, h, w) = x.dim();
    let index = read_json(&fr.join("frames.json"))?["lidar_test_index"].as_u64().unwrap_or(0) as usize;
    let truth_d = lidar.load("test", "depth")?.into_dimensionality::<Ix4>()?.index_axis(Axis(0), index).to_owned();
    let tv = read3(&fr.join("lidar-tval3.npy"))?;
    let admm = read3(&fr.join("lidar-admm.npy"))?;
    let admm_l = read3(&fr.join("lidar-learned-admm.npy"))?;
    let unet_d = read3(&fr.join("lidar-unet-depth.npy"))?;
    let two = truth_d.dim().0 > 1;
    let second = if two { truth_d.index_axis(Axis(0), 1).indexed_iter().filter(|(_, v)| v.is_finite()).min_by_key(|((r, c), _)| r.abs_diff(h / 2) + c.abs_diff(w / 2)).map(|(p, _)| p) } else { None };
    let far = truth_d.index_axis(Axis(0), 0).indexed_iter().filter(|(_, v)| v.is_finite()).max_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let pixels = pick_pixels(h, w, second, far);
    figures::waveforms(&out("waveforms-lidar.png"), &[("truth", x.view()), ("TVAL3", tv.view()), ("ADMM-Net", admm.view()), ("ADMM-Net, learned codes", admm_l.view())], &pixels, Some(bin_w * 1e9))?;
    let peaks = PeakOptions { max_peaks: 2, ..Default::default() };
    let d_tv = depth_map(&tv.view(), bin_w, &peaks).0;
    let d_admm = depth_map(&admm.view(), bin_w, &peaks).0;
    let k = truth_d.dim().0.min(2);
    let mut panels: Vec<(String, Array2<f32>)> = Vec::new();
    let mut errors: Vec<(String, Array2<f32>)> = Vec::new();
    for b in 0..k {
        let t = truth_d.index_axis(Axis(0), b).to_owned();
        panels.push((format!("truth, return {}", b + 1), t.clone()));
        for (name, d) in [("TVAL3", &d_tv), ("ADMM-Net", &d_admm), ("Aᵀ + U-Net", &unet_d)] {
            let est = if b < d.dim().0 { d.index_axis(Axis(0), b).to_owned() } else { Array2::from_elem((h, w), f32::NAN) };
            let err = ndarray::Zip::from(&est).and(&t).map_collect(|&e, &t| if e.is_finite() && t.is_finite() { (e - t).abs() } else { f32::NAN });
            panels.push((format!("{name}, return {}", b + 1), est));
            errors.push((format!("{name}, return {}", b + 1), err));
        }
    }
    let pv: Vec<(&str, ndarray::ArrayView2<f32>)> = panels.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    figures::maps(&out("depth.png"), "Range of the two returns: truth and each decoder (grey: no return)", &pv, "range (m)", Some((0.0, range_m)))?;
    let ev: Vec<(&str, ndarray::ArrayView2<f32>)> = errors.iter().map(|(n, a)| (n.as_str(), a.view())).collect();
    let emax = errors.iter().flat_map(|(_, a)| a.iter().copied()).filter(|v| v.is_finite()).fold(0f32, f32::max).max(1e-3) as f64;
    figures::maps(&out("depth-error.png"), "Absolute range error where truth and estimate have a return", &ev, "|range error| (m)", Some((0.0, emax.min(range_m / 4.0))))?;
    let clouds = [("truth", point_cloud(&truth_d.view(), FOV_DEG)), ("ADMM-Net (peaks of the cube)", point_cloud(&d_admm.view(), FOV_DEG)), ("Aᵀ + U-Net (direct depth)", point_cloud(&unet_d.view(), FOV_DEG))];
    let clouds: Vec<(&str, Vec<[f32; 4]>)> = clouds.into_iter().collect();
    figures::point_clouds(&out("point-cloud.png"), "Point clouds of the test frame (camera coordinates)", &clouds)?;

    // FLIm: waveforms, lifetime maps, phasors
    let fbin = flim.manifest.bin_width_s;
    let fx = read3(&fr.join("flim-x.npy"))?;
    let (_, fh, fw) = fx.dim();
    let ftv = read3(&fr.join("flim-tval3.npy"))?;
    let fadmm = read3(&fr.join("flim-admm.npy"))?;
    let truth_tau = flim.load("test", "lifetime")?.into_dimensionality::<Ix3>()?.index_axis(Axis(0), 0).to_owned();
    let short = truth_tau.indexed_iter().filter(|(_, v)| v.is_finite() && **v > 0.0).min_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let long = truth_tau.indexed_iter().filter(|(_, v)| v.is_finite() && **v > 0.0).max_by(|a, b| a.1.total_cmp(b.1)).map(|(p, _)| p);
    let pixels = pick_pixels(fh, fw, short, long);
    figures::waveforms(&out("waveforms-flim.png"), &[("truth", fx.view()), ("TVAL3", ftv.view()), ("ADMM-Net", fadmm.view())], &pixels, Some(fbin * 1e9))?;
    // the reconvolution fit (IRF fitted) of each cube, the fit to the taps as it was decoded
    let lt = |c: &Array3<f32>| tcsense_infer::lifetime::fit_cube(&c.view(), fbin, &tcsense_infer::lifetime::FitOptions::default()).lifetimes.index_axis(Axis(0), 0).to_owned();
    let (tau_x, tau_tv, tau_admm) = (lt(&fx), lt(&ftv), lt(&fadmm));
    let tau_fit = read3(&fr.join("flim-fit-lifetime.npy"))?.index_axis(Axis(0), 0).to_owned();
    let ns = |a: &Array2<f32>| a.mapv(|v| v * 1e9);
    let truth_ns = truth_tau.mapv(|v| if v > 0.0 { v * 1e9 } else { f32::NAN });
    let maps = [("truth (generator)", truth_ns), ("fit to the true cube", ns(&tau_x)), ("TVAL3 + fit", ns(&tau_tv)), ("ADMM-Net + fit", ns(&tau_admm)), ("fit to the taps", ns(&tau_fit))];
    let hi = maps[0].1.iter().copied().filter(|v| v.is_finite()).fold(0f32, f32::max).max(0.5) as f64 * 1.2;
    let mv: Vec<(&str, ndarray::ArrayView2<f32>)> = maps.iter().map(|(n, a)| (*n, a.view())).collect();
    figures::maps(&out("lifetime.png"), "Fluorescence lifetime map of one test frame (grey: no fit)", &mv, "lifetime τ (ns)", Some((0.0, hi)))?;
    let phasors = |x: &Array3<f32>| -> Vec<(f64, f64)> {
        let p = referenced_phasors(&x.view(), 0.02);
        (0..fh * fw).map(|i| (p[(0, i / fw, i % fw)] as f64, p[(1, i / fw, i % fw)] as f64)).collect()
    };
    let period = fbin * flim.manifest.bins as f64;
    figures::phasor(&out("phasor.png"), &format!("Phasors of the test frame (first harmonic, period {:.2} ns)", period * 1e9), &[("truth", phasors(&fx)), ("TVAL3", phasors(&ftv)), ("ADMM-Net", phasors(&fadmm))], period)?;

    // training curves
    let runs_dir = dir.join("runs");
    let mut lidar_runs = vec![("ADMM-Net, selected codes", runs_dir.join("admm-lidar")), ("ADMM-Net, learned codes", runs_dir.join("learned-lidar"))];
    if runs_dir.join("zoo-lidar").join(tcsense_train::run_dir::METRICS_FILE).exists() {
        lidar_runs.push(("ADMM-Net from the zoo, fine-tuned", runs_dir.join("zoo-lidar")));
    }
    training_figure(&out("training-lidar.png"), &lidar_runs)?;
    training_figure(&out("training-unet.png"), &[("Aᵀ + U-Net", runs_dir.join("unet-lidar"))])?;
    training_figure(&out("training-flim.png"), &[("ADMM-Net, FLIm", runs_dir.join("admm-flim"))])?;
    Ok(Figures { files })
}

/// The epochs of a run, a learned-codes run's relaxed phase (`RUN/relaxed/`) first, its
/// fine-tuning on the projected codes continuing the epoch, step and time count.
fn run_rows(run: &Path) -> Result<Vec<tcsense_train::EpochMetrics>> {
    use tcsense_train::run_dir::{read_rows, METRICS_FILE};
    let relaxed = run.join("relaxed").join(METRICS_FILE);
    let mut rows = if relaxed.exists() { read_rows(&relaxed, usize::MAX)? } else { Vec::new() };
    let (e0, s0, t0) = rows.last().map_or((0, 0, 0.0), |m| (m.epoch, m.step, m.seconds));
    for mut m in read_rows(&run.join(METRICS_FILE), usize::MAX)? {
        m.epoch += e0;
        m.step += s0;
        m.seconds += t0;
        rows.push(m);
    }
    Ok(rows)
}

fn training_figure(path: &Path, runs: &[(&str, PathBuf)]) -> Result<()> {
    let (mut loss, mut val) = (Vec::new(), Vec::new());
    let mut val_name = String::new();
    for (label, r) in runs {
        let rows = run_rows(r)?;
        val_name = rows.first().and_then(|m| m.val.first()).map(|(n, _)| n.clone()).unwrap_or_default();
        loss.push(Series { label: label.to_string(), points: rows.iter().map(|m| (m.epoch as f64, m.train_loss)).collect() });
        val.push(Series { label: label.to_string(), points: rows.iter().map(|m| (m.epoch as f64, m.get(&val_name))).collect() });
    }
    let label = match val_name.as_str() {
        "val_mse" => "validation MSE of the cube",
        "val_depth_rmse_m" => "validation range RMSE of the returns (m)",
        _ => "validation metric",
    };
    figures::training_curves(path, &loss, &val, label)?;
    Ok(())
}

/// A table row per entry of `results["rows"]` (the parsed `file`): the `text` fields as they
/// are, then each `(pointer into the row, format)` as a sourced number.
fn result_rows(file: &str, results: &Value, text: &[&str], numbers: &[(&str, Format)]) -> Vec<Vec<Cell>> {
    let rows = results["rows"].as_array().map_or(0, |r| r.len());
    (0..rows)
        .map(|i| {
            let row = &results["rows"][i];
            let mut cells: Vec<Cell> = text.iter().map(|k| Cell::text(row[*k].as_str().unwrap_or(""))).collect();
            cells.extend(numbers.iter().map(|&(k, f)| Cell::from_json(file, results, &format!("/rows/{i}/{k}"), f)));
            cells
        })
        .collect()
}

/// One sentence per metric (JSON pointer into a row, label, format, unit): which row of
/// `results` has the lowest value and what TVAL3 gets, read from the results themselves so
/// the text follows whatever the run measured.
fn findings(results: &Value, metrics: &[(&str, &str, Format, &str)]) -> String {
    let rows = results["rows"].as_array().cloned().unwrap_or_default();
    let name = |r: &Value| format!("{} ({} codes, {})", r["decoder"].as_str().unwrap_or(""), r["codes"].as_str().unwrap_or("selected"), r["engine"].as_str().unwrap_or(""));
    let mut out = Vec::new();
    for &(ptr, label, format, unit) in metrics {
        let val = |r: &Value| r.pointer(&format!("/{ptr}")).and_then(Value::as_f64).filter(|v| v.is_finite());
        let show = |v: f64| format!("{}{unit}", format.show(Some(v)));
        let best = rows.iter().filter_map(|r| val(r).map(|v| (r, v))).min_by(|a, b| a.1.total_cmp(&b.1));
        let tval3 = rows.iter().find(|r| r["decoder"] == "TVAL3").and_then(val);
        if let Some((r, v)) = best {
            let vs = match tval3 {
                Some(t) if r["decoder"] != "TVAL3" => format!(" against TVAL3's {}", show(t)),
                _ => String::new(),
            };
            out.push(format!("Lowest {label}: {}, {}{vs}.", name(r), show(v)));
        }
    }
    out.join(" ")
}

fn read_json(path: &Path) -> Result<Value> {
    serde_json::from_slice(&std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?).with_context(|| format!("{}: not JSON", path.display()))
}

fn build_report(dir: &Path, plan: &Plan, figs: &Figures, times: &[Value], total_s: f64) -> Result<Report> {
    let fig = |name: &str, caption: &str| -> Block {
        debug_assert!(figs.files.contains(&name), "figure {name} not drawn");
        Block::Figure { src: format!("figures/{name}"), caption: caption.into() }
    };
    let r = &plan.request;
    let mut sections = Vec::new();

    // overview
    let mut training_rows = Vec::new();
    for t in &plan.trainings {
        let rows = run_rows(&dir.join("runs").join(&t.name))?;
        let last = rows.last();
        training_rows.push(vec![
            Cell::text(&t.title),
            Cell::text(format!("runs/{}", t.name)),
            Cell::text(last.map_or("0".into(), |m| m.epoch.to_string())),
            Cell::text(last.map_or("0".into(), |m| m.step.to_string())),
            Cell::text(format!("{:.1}", t.step_ms)),
            Cell::text(format!("{:.0}", last.map_or(0.0, |m| m.seconds))),
            Cell::text(last.and_then(|m| m.val.first()).map_or("–".into(), |(n, v)| format!("{} {}", n.trim_start_matches("val_").replace('_', " "), if n.ends_with("_m") { format!("{v:.3} m") } else { format!("{v:.3e}") }))),
        ]);
    }
    let mut step_rows: Vec<Vec<Cell>> = times.iter().map(|t| vec![Cell::text(t["step"].as_str().unwrap_or("")), Cell::text(format!("{:.1}", t["seconds"].as_f64().unwrap_or(f64::NAN)))]).collect();
    step_rows.push(vec![Cell::text("this run of tcsense demo, in all"), Cell::text(format!("{total_s:.1}"))]);
    sections.push(Section {
        id: "overview".into(),
        title: "What was done".into(),
        blocks: vec![
            Block::Text(format!(
                "The prototype sensor of the paper (4 taps, 2×2 pixel blocks, L = 32 masks at 607 MHz, constraints tap + Hamming H = 2 + window W = 2, physical IRF) was simulated on two synthetic datasets with randomised scenes: LiDAR with multipath ({} scenes of {}×{} pixels, T = 32 bins of 51.5 ps) and fluorescence lifetime imaging ({} scenes, heterodyne K = 8, T = 256). Codes were drawn at random under the constraints, the best of {} by TVAL3 was kept for comparison (the paper's selection), the selected codes were designed for range identifiability (no alias, the smallest worst-case range bound; see Exposure codes), and codes were also learned jointly with an ADMM-Net (deep sensing, with a hinge on the range alias in the loss) and projected exactly onto the constraints; both sets are exported to the sensor's code memory. TVAL3, ADMM-Net and the Aᵀ + U-Net depth decoder reconstruct the same noisy tap images (shot and read noise, full well 20 000 e⁻, σ 40 e⁻); the trained decoders are exported to ONNX and run again through ONNX Runtime. Budget: {} minutes{}.",
                r.lidar_scenes, r.size[0], r.size[1], r.flim_scenes, plan.candidates, r.budget_minutes, if r.quick { " (--quick)" } else { "" }
            )),
            Block::Table(Table { caption: "Trainings (epochs sized to the budget from a measured step time; batch 2, Adam, lr 10⁻³, augmentation on)".into(), headers: vec!["network".into(), "run directory".into(), "epochs".into(), "steps".into(), "ms per step (planned)".into(), "training time (s)".into(), "last validation".into()], rows: training_rows }),
        ],
    });
    let run_log = Section {
        id: "run".into(),
        title: "This run".into(),
        blocks: vec![
            Block::Table(Table { caption: "Steps of this run of the demo and their wall time (a resumed run times only what it did)".into(), headers: vec!["step".into(), "seconds".into()], rows: step_rows }),
            Block::Text(format!("Everything this report shows is in {}: plan.json (the settings and the epochs sized to the budget), results/*.json (every number of the tables), runs/ (the training runs: config.json, metrics.csv, checkpoints, model.bpk, codes.json), onnx/, code-memory/, codes/, the datasets lidar/ and flim/, frames/ (the tap images and reconstructions of the frames shown, .npy) and figures/.", dir.display())),
        ],
    };

    // codes
    let sel = read_json(&dir.join("results/selection.json"))?;
    let ident = read_json(&dir.join("results/identifiability.json"))?;
    let n_cand = sel["candidates"].as_array().map_or(0, |a| a.len());
    let mut cand_rows = Vec::new();
    for i in 0..n_cand {
        cand_rows.push(vec![Cell::from_json("results/selection.json", &sel, &format!("/candidates/{i}/seed"), Format::Fixed(0)), Cell::from_json("results/selection.json", &sel, &format!("/candidates/{i}/mse"), Format::Sci(3))]);
    }
    let regs = std::fs::read_to_string(dir.join("code-memory/learned/registers.json")).unwrap_or_default();
    let proj = read_json(&dir.join("runs/learned-lidar/relaxed/projection.json"))?;
    let psrc = "runs/learned-lidar/relaxed/projection.json";
    let projection = Table {
        caption: "Projection of the learned codes onto the constraints (the relaxed codes' hard version, and the bits the exact projection changed)".into(),
        headers: ["solver", "violations before (tap / Hamming / window)", "bits changed", "of bits"].map(String::from).to_vec(),
        rows: vec![vec![
            Cell::text(proj["solver"].as_str().unwrap_or("")),
            Cell::text(format!("{} / {} / {}", proj["relaxed_violations"]["tap"], proj["relaxed_violations"]["hamming"], proj["relaxed_violations"]["window"])),
            Cell::from_json(psrc, &proj, "/bits_changed", Format::Fixed(0)),
            Cell::from_json(psrc, &proj, "/bits", Format::Fixed(0)),
        ]],
    };
    sections.push(Section {
        id: "codes".into(),
        title: "Exposure codes".into(),
        blocks: vec![
            Block::Text("Each row is one code channel: subpixel n of the 2×2 block and tap m; a coloured cell means the tap collects light during that mask. The strip below counts the bits that change between adjacent masks against the Hamming limit; red marks on top would flag violated masks (there are none: every exported set passes the checker).".into()),
            fig("codes-random.png", "One random code set under the constraints (seed of the demo)."),
            fig("codes-selected.png", "The selected code set: designed for range identifiability (tcsense codes select --criterion range: the best of 20 000 random sets by alias and worst-case range bound, then a local search that keeps every constraint exact)."),
            fig("codes-best-mse.png", "The paper's selection: the random candidate with the lowest TVAL3 MSE."),
            fig("codes-learned.png", "Codes learned jointly with ADMM-Net (relaxed, straight-through training, then the exact projection onto tap + H 2 + W 2, then fine-tuning)."),
            fig("selection.png", "TVAL3 MSE of every random candidate on the validation scenes (noise-free, as in the paper's selection)."),
            Block::Table(Table { caption: "Code selection by TVAL3 MSE (results/selection.json)".into(), headers: vec!["candidate seed".into(), "TVAL3 MSE".into()], rows: cand_rows }),
            Block::Text("Selection by TVAL3 MSE over typical scenes does not see a range the codes erase: two returns whose tap signatures are nearly equal cost little MSE on average, but a surface at one of them is placed at the other by every decoder. The table and figures below measure what each code set lets the taps tell apart; the selected set was designed for it.".into()),
            Block::Table(crate::identifiability::table(&ident, "results/identifiability.json", &|name| match name {
                "best MSE" => sel["candidates"].as_array().and_then(|a| a.iter().filter_map(|c| c["mse"].as_f64()).reduce(f64::min)),
                "selected" => sel["designed"]["mse"].as_f64(),
                _ => None,
            })),
            fig("identifiability-range.png", "Cramér–Rao bound of a single return's range at every delay of the cycle, per code set (LiDAR grid): where two ranges alias the bound peaks."),
            fig("identifiability-lifetime.png", "Cramér–Rao bound of the lifetime (onset known), worst over the onsets, per code set (FLIm grid, heterodyne K = 8)."),
            Block::Table(projection),
            Block::Text("Both sets are written to the sensor's code memory: code-memory/selected/ and code-memory/learned/ hold one binary per channel (chNN.bin), the combined image codes.bin and the registers (ECLEN = L/8 − 1). Write them to the sensor with your acquisition software, or read them back with tcsense codes import. The learned set's registers:".into()),
            Block::Code(regs),
        ],
    });

    // tap images
    sections.push(Section {
        id: "taps".into(),
        title: "Tap images".into(),
        blocks: vec![
            Block::Text("What the sensor reads out for one LiDAR test frame: one image per tap, each pixel the light of its 2×2 subpixel's code channel integrated over the frame, with shot and read noise (as in the paper's Fig. 15b). These are the decoders' only input.".into()),
            fig("taps.png", "The four tap images of the LiDAR test frame shown below (selected codes)."),
        ],
    });

    // LiDAR
    let lj = read_json(&dir.join("results/lidar.json"))?;
    let src = "results/lidar.json";
    let rows = result_rows(src, &lj, &["decoder", "codes", "engine"], &[
        ("mse", Format::Sci(3)),
        ("psnr_db", Format::Fixed(2)),
        ("range_rmse_m/0", Format::Fixed(3)),
        ("range_rmse_m/1", Format::Fixed(3)),
        ("detection_pct/0", Format::Fixed(1)),
        ("detection_pct/1", Format::Fixed(1)),
        ("ms_per_frame", Format::Fixed(1)),
    ]);
    let findings_lidar = findings(&lj, &[("mse", "MSE", Format::Sci(3), ""), ("range_rmse_m/0", "range RMSE of return 1", Format::Fixed(3), " m"), ("range_rmse_m/1", "range RMSE of return 2", Format::Fixed(3), " m")]);
    sections.push(Section {
        id: "lidar".into(),
        title: "LiDAR with multipath".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("LiDAR test split, {} items, noisy (in the style of the paper's Table 4). Every decoder of a code set sees the same measurements; the learned-codes rows measure the same scenes with the same noise seeds through their own codes, as does the zoo's decoder as shipped (zoo:admm-lidar-delay, trained for hours on the prototype's codes); the zoo's decoder fine-tuned to the selected codes had the training time of ADMM-Net from scratch. Range errors over the pixels where the truth and the decoder both have that return; the U-Net estimates range directly and has no cube (no MSE).", plan.lidar_eval_items),
                headers: ["decoder", "codes", "engine", "MSE", "PSNR (dB)", "range RMSE return 1 (m)", "range RMSE return 2 (m)", "detected return 1 (%)", "detected return 2 (%)", "time per frame (ms)"].map(String::from).to_vec(),
                rows,
            }),
            Block::Text(findings_lidar),
            fig("waveforms-lidar.png", "Waveforms at three pixels of one test frame (the first with a diffusive sheet) against the truth (as in the paper's Fig. 18): the pixel nearest the centre with a return behind the sheet, the centre, the farthest first return (quarter points where these coincide)."),
            fig("depth.png", "Range of the first and second return, truth and each decoder (TVAL3 and ADMM-Net by peak detection in the cube, the U-Net directly); one colour scale over the unambiguous range."),
            fig("depth-error.png", "Absolute range error of each decoder and return."),
            fig("point-cloud.png", "The same frame as point clouds (pinhole camera, 40° field of view; as in the paper's Fig. 17)."),
        ],
    });

    // FLIm
    let fj = read_json(&dir.join("results/flim.json"))?;
    let src = "results/flim.json";
    let rows = result_rows(src, &fj, &["decoder", "engine"], &[("mse", Format::Sci(3)), ("psnr_db", Format::Fixed(2)), ("lifetime_mae_ns", Format::Fixed(3)), ("lifetime_within_02ns_pct", Format::Fixed(1)), ("ms_per_frame", Format::Fixed(1))]);
    let findings_flim = findings(&fj, &[("mse", "MSE", Format::Sci(3), ""), ("lifetime_mae_ns", "lifetime MAE", Format::Fixed(3), " ns")]);
    sections.push(Section {
        id: "flim".into(),
        title: "Fluorescence lifetime imaging".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("FLIm test split, {} items, noisy, selected codes (in the style of the paper's Table 5). Lifetime error: mean absolute error of the amplitude-weighted mean lifetime over the pixels holding a fluorophore (a cube's by the reconvolution fit with the IRF fitted; the fit to the taps and the lifetime decoder have no cube, so no MSE). The zoo's decoders as shipped (zoo:admm-flim-delay, trained for 3.8 hours, and zoo:lifetime-flim, 39 minutes, on the prototype's codes) measure the same scenes with the same noise seeds through their own codes.", plan.flim_eval_items),
                headers: ["decoder", "engine", "MSE", "PSNR (dB)", "lifetime MAE (ns)", "within 0.2 ns (%)", "time per frame (ms)"].map(String::from).to_vec(),
                rows,
            }),
            Block::Text(findings_flim),
            fig("waveforms-flim.png", "Decays at three pixels of FLIm test frame 0 (shortest and longest true lifetime, centre) against the truth (as in the paper's Fig. 20)."),
            fig("lifetime.png", "Lifetime map: the generator's amplitude-weighted mean lifetimes, the reconvolution fit to the true cube (the fit's own error), the fits to each decoder's cube, and the lifetimes fitted to the tap images directly."),
            fig("phasor.png", "Phasor plot of every pixel (first harmonic, background removed, phase referenced to the frame's decay onset at the peak of its summed decay): single exponentials lie on the semicircle, mixtures of lifetimes inside it."),
        ],
    });

    // training
    sections.push(Section {
        id: "training".into(),
        title: "Training curves".into(),
        blocks: vec![
            fig("training-lidar.png", "ADMM-Net on LiDAR with the selected codes and with codes learned jointly (metrics.csv of each run; the learned run's relaxed epochs, then its fine-tuning on the projected codes), and the zoo's ADMM-Net fine-tuned to the selected codes in the same time as the run from scratch: what starting from the zoo buys."),
            fig("training-unet.png", "Aᵀ + U-Net: depth loss and validation range RMSE."),
            fig("training-flim.png", "ADMM-Net on FLIm."),
        ],
    });

    // deployment timing
    let tj = read_json(&dir.join("results/timing.json"))?;
    let src = "results/timing.json";
    let mut rows = Vec::new();
    for (i, d) in tj["decoders"].as_array().cloned().unwrap_or_default().iter().enumerate() {
        for (j, e) in d["timing"]["engines"].as_array().cloned().unwrap_or_default().iter().enumerate() {
            let p = |k: &str| format!("/decoders/{i}/timing/engines/{j}/{k}");
            let fps = e["frames_per_s"].as_f64().unwrap_or(0.0);
            rows.push(vec![
                Cell::text(format!("runs/{}", d["run"].as_str().unwrap_or(""))),
                Cell::text(e["engine"].as_str().unwrap_or("")),
                Cell::from_json(src, &tj, &p("ms_per_frame"), Format::Fixed(1)),
                Cell::from_json(src, &tj, &p("frames_per_s"), Format::Fixed(1)),
                Cell::text(if fps >= SENSOR_FPS { "yes" } else { "no" }),
            ]);
        }
    }
    let (th, tw) = (r.timing_size[0], r.timing_size[1]);
    sections.push(Section {
        id: "deployment".into(),
        title: "Deployment: ONNX and timing".into(),
        blocks: vec![
            Block::Table(Table {
                caption: format!("Time per {th}×{tw} frame, batch 1, median of {} interleaved rounds on this machine ({} threads available); the sensor delivers {SENSOR_FPS} frames/s.", plan.timing_rounds, rayon::current_num_threads()),
                headers: ["decoder", "engine", "ms per frame", "frames/s", "keeps up with the sensor"].map(String::from).to_vec(),
                rows,
            }),
            Block::Text("Each trained decoder is exported to onnx/NAME.onnx (opset 17; input measurements [B, 4, H, W], the raw tap images; output cube [B, T, H, W] or depth and confidence [B, 2, H, W]; codes, clock and sensor model in the metadata). Run them on recorded tap images with:".into()),
            Block::Code(format!(
                "tcsense infer --model {0}/onnx/unet-lidar.onnx --measurements {0}/frames/lidar-y.npy --products depth,ply -o out/\ntcsense infer --model {0}/onnx/admm-flim.onnx --measurements {0}/frames/flim-y.npy --products cube,lifetime -o out/\ntcsense eval --dataset {0}/lidar --codes {0}/codes/selected.json --irf physical --decoder tval3 --decoder onnx:{0}/onnx/admm-lidar.onnx --noise",
                dir.display()
            )),
        ],
    });
    sections.push(run_log);
    // results first: what was done, the two applications, then how (codes, tap images,
    // training), deployment and the run's log
    let order = ["overview", "lidar", "flim", "codes", "taps", "training", "deployment", "run"];
    sections.sort_by_key(|s| order.iter().position(|o| *o == s.id).unwrap_or(order.len()));
    let version = env!("CARGO_PKG_VERSION");
    Ok(Report {
        title: "tcsense demo report".into(),
        subtitle: format!("tcsense {version}; prototype sensor 4 taps, 2×2, L = 32, 607 MHz; {}×{} frames; budget {} min; seed {}; written by `tcsense demo{}`", r.size[0], r.size[1], r.budget_minutes, r.seed, if r.quick { " --quick" } else { "" }),
        sections,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_are_distinct_and_in_the_frame() {
        assert_eq!(pick_pixels(8, 8, Some((4, 4)), Some((1, 2))), vec![(4, 4), (1, 2), (2, 2)]);
        assert_eq!(pick_pixels(8, 8, None, Some((7, 7))), vec![(4, 4), (7, 7), (2, 2)]);
        assert_eq!(pick_pixels(8, 8, Some((0, 1)), Some((7, 7))), vec![(0, 1), (4, 4), (7, 7)]);
        assert_eq!(engine("tval3"), "Rust (TVAL3)");
        assert_eq!(engine("onnx:m.onnx"), "ONNX Runtime");
        assert_eq!(engine("admm-net:r"), "burn (flex)");
    }
}
