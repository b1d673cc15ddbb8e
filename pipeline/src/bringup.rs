//! `tcsense bringup`: from a laser-delay sweep of a sensor on the bench to decoders deployed for
//! it, as one resumable path.
//!
//! 1. **calibrate** the sensor from the sweep (`DIR/cal`: measured `A`, gain and dark maps, its
//!    report);
//! 2. **generate** training scenes for the sensor's grid (LiDAR, or FLIm for a heterodyne sweep);
//! 3. **fine-tune** each chosen zoo decoder to the calibrated sensor within the time budget
//!    (`DIR/runs/NAME`: its architecture from the zoo, epochs sized from a measured step time,
//!    residual gains and offsets drawn per item), resumable from its checkpoints;
//! 4. **check** every decoder on held-back scenes through the sensor the sweep recorded (a
//!    simulated bench records its non-idealities): on the ideal sensor, through the nominal model,
//!    with the calibration alone and calibrated + fine-tuned, beside TVAL3;
//! 5. **export** each to ONNX with the correction built in (`DIR/onnx/NAME.onnx`: it takes the
//!    sensor's raw tap images), as the better of the check's calibration alone and fine-tuned
//!    (`DIR/results/deployed.json`);
//! 6. **report** it all in `DIR/report.html`, with the time of every step.
//!
//! A step whose outputs exist is skipped, so rerunning into `DIR` resumes; `cancel` stops it
//! between steps and inside trainings (the last checkpoint kept).

use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{self, Generator, WriteOptions, DEFAULT_SHARD};
use tcsense_datasets::{Dataset, TimeGrid};
use tcsense_infer::eval::{evaluate, EvalRow, EvalSettings};
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::registry::open_decoder;
use tcsense_infer::report::{Block, Cell, Format, Report, Section, Table};
use tcsense_models::runs::{self, CONFIG_FILE, WEIGHTS_FILE};
use tcsense_models::{zoo, Device, Tval3Options};
use tcsense_sensor::calibration::{calibrate, Calibration, DESCRIPTION};
use tcsense_sensor::sweep::Sweep;
use tcsense_sensor::{Codes, Irf, NoiseParams, Sampling, Sensor, SensorModel};
use tcsense_train::request::{self, TrainRequest};

use crate::error::{bail, Result};
use crate::observer::Observer;
use crate::write_json;

/// Share of the budget given to the fine-tunings (the rest: calibration, data, export, check).
const TRAINING_SHARE: f64 = 0.8;
/// Residual tap gain, PRNU and dark offset a calibration leaves, drawn per training item.
const SENSOR_RESIDUE: [f64; 3] = [0.01, 0.005, 0.002];
/// A fine-tuning may run this many times its share of the budget (its epochs are sized from a
/// timed step, which a busy machine misjudges) before it is stopped.
const DEADLINE_SLACK: f64 = 1.25;
/// Seed stream of the held-back scenes (the training scenes use the seed itself).
const CHECK_SEED: u64 = 0xc4ec;
/// Time per step beyond the timed forward/backward/Adam step (ms): measurements, augmentation,
/// validation, checkpoints.
const STEP_OVERHEAD_MS: f64 = 2.0;

/// The check's condition of a decoder as given, its frames corrected and decoded with the
/// measured matrix.
const CALIBRATION_ALONE: &str = "calibration";
/// The check's condition of a decoder fine-tuned to the calibrated sensor.
const FINE_TUNED: &str = "calibration + fine-tuning";

/// Limits of a bring-up's settings.
const MAX_SIDE: usize = 4096;
const MIN_SCENES: usize = 4;
const MAX_SCENES: usize = 100_000;
const MAX_CHECK_ITEMS: usize = 10_000;
const MAX_EPOCHS: usize = 100_000;
const MAX_BUDGET_MINUTES: f64 = 7.0 * 24.0 * 60.0;
/// The record of what a bring-up directory was made from.
pub const INPUTS_FILE: &str = "inputs.json";

/// What every step of a bring-up is made from: the sweep's content, the codes, the sensor, the
/// decoders and the settings that shape the steps' outputs (not the budget: a rerun may give
/// the trainings more or less time). Recorded in `DIR/inputs.json` by the first run; a rerun
/// with other inputs is refused, naming each difference.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Inputs {
    /// Digest of the sweep's manifest and frames (dark, flat, delays).
    sweep: String,
    codes: String,
    sampling: String,
    irf: String,
    decoders: Vec<String>,
    epochs: Option<usize>,
    scenes: usize,
    size: [usize; 2],
    check_items: usize,
    seed: u64,
}

impl Inputs {
    fn of(o: &BringupOptions, decoders: &[String], sweep: &Sweep, codes: &Codes) -> Inputs {
        // the manifest, then the frames, dark and flat values in order, streamed (no copy of the sweep)
        let manifest = serde_json::to_vec(&sweep.manifest).unwrap_or_default();
        let values = sweep.frames.iter().chain(sweep.dark.iter()).chain(sweep.flat.iter().flatten());
        Inputs {
            sweep: tcsense_sensor::digest::digest(manifest.into_iter().chain(values.flat_map(|v| v.to_le_bytes()))),
            codes: codes.digest(),
            sampling: format!("{:?}", o.sampling),
            irf: format!("{:?}", o.irf),
            decoders: decoders.to_vec(),
            epochs: o.epochs,
            scenes: o.scenes,
            size: [o.size.0, o.size.1],
            check_items: o.check_items,
            seed: o.seed,
        }
    }

    /// Refuse `dir` when it holds a bring-up of other inputs, or something that is no bring-up.
    fn check_resume(&self, dir: &Path) -> Result<()> {
        let path = dir.join(INPUTS_FILE);
        if dir.exists() && !dir.is_dir() {
            bail!("{}: exists and is not a directory; choose a new output directory", dir.display());
        }
        let empty = std::fs::read_dir(dir).map(|mut d| d.next().is_none()).unwrap_or(true);
        if empty {
            return Ok(());
        }
        let Ok(text) = std::fs::read_to_string(&path) else {
            bail!(
                "{}: the directory holds files but no {INPUTS_FILE}, so it is not a bring-up to resume; choose a new output directory",
                dir.display()
            );
        };
        let saved: Inputs = serde_json::from_str(&text).map_err(|e| {
            crate::PipelineError::Invalid(format!(
                "{}: not a bring-up's record of its inputs ({e}); choose a new output directory",
                path.display()
            ))
        })?;
        let (a, b) = (serde_json::to_value(&saved)?, serde_json::to_value(self)?);
        let differences: Vec<String> = a
            .as_object()
            .into_iter()
            .flatten()
            .filter(|(k, v)| b.get(k.as_str()) != Some(v))
            .map(|(k, v)| format!("{k}: {v} then, {} now", b.get(k.as_str()).cloned().unwrap_or(Value::Null)))
            .collect();
        if !differences.is_empty() {
            bail!(
                "{} was brought up from other inputs ({}); rerun with the same sweep, codes and settings to resume it, or choose a new output directory",
                dir.display(),
                differences.join("; ")
            );
        }
        Ok(())
    }
}

/// What to bring up.
#[derive(Debug, Clone)]
pub struct BringupOptions {
    /// The sweep directory (`sweep.json`).
    pub sweep: PathBuf,
    /// The codes the sensor runs (`codes.json`).
    pub codes: PathBuf,
    /// The sensor's sampling and nominal instrument response.
    pub sampling: Sampling,
    pub irf: Irf,
    /// Decoders to fine-tune: zoo entries (`NAME` or `zoo:NAME`) or trained run directories
    /// (empty: the zoo's designed-codes entries of the sensor's domain).
    pub decoders: Vec<String>,
    /// The whole path's time budget (min).
    pub budget_minutes: f64,
    /// Epochs of every fine-tuning instead of the budget's (no deadline then).
    pub epochs: Option<usize>,
    /// Training scenes generated, and their frame size.
    pub scenes: usize,
    pub size: (usize, usize),
    /// Held-back scenes of the check.
    pub check_items: usize,
    pub seed: u64,
}

/// What a bring-up left behind.
#[derive(Debug, Clone)]
pub struct BringupSummary {
    pub report: PathBuf,
    /// The exported models, one per decoder.
    pub models: Vec<PathBuf>,
    /// Every step's wall time (s).
    pub steps: Vec<(String, f64)>,
}

/// A decoder to bring up: a zoo entry or a trained run.
struct Source {
    /// As given (for messages).
    label: String,
    /// Its name under `runs/` and `onnx/`: the entry's or the run directory's.
    name: String,
    dir: PathBuf,
    model: tcsense_models::runs::ModelConfig,
}

impl Source {
    /// `NAME` or `zoo:NAME` (a zoo entry), or a run directory.
    fn open(spec: &str) -> Result<Source> {
        let full = if spec.contains(':') || Path::new(spec).exists() { spec.to_string() } else { format!("zoo:{spec}") };
        let dir = zoo::resolve(&full)?;
        let model = tcsense_train::setup::model_of_run(&dir)?;
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| spec.to_string());
        Ok(Source { label: full, name, dir, model })
    }
}

/// The zoo entries brought up by default for a sensor of `sampling`.
fn default_decoders(sampling: Sampling) -> Vec<String> {
    match sampling {
        Sampling::Heterodyne(_) => vec!["lifetime-flim-designed".into()],
        Sampling::Oversample(_) => vec!["unet-lidar-designed".into(), "admm-lidar-designed".into()],
    }
}

/// Bring the sensor of `options` up into `dir` (see the module docs).
pub fn run(options: &BringupOptions, dir: &Path, obs: &dyn Observer, cancel: &AtomicBool) -> Result<BringupSummary> {
    // everything checked before anything is written
    let Checked { codes, nominal, sweep, names, entries } = checked_inputs(options)?;
    let (h, w) = options.size;
    // what the steps are made from: a directory brought up from other inputs is refused, never
    // resumed with them
    let inputs = Inputs::of(options, &names, &sweep, &codes);
    inputs.check_resume(dir)?;
    std::fs::create_dir_all(dir).map_err(|e| crate::PipelineError::Io { path: dir.to_path_buf(), cause: e })?;
    write_json(&dir.join(INPUTS_FILE), &serde_json::to_value(&inputs)?)?;
    // a step done by an earlier run keeps the time it took then
    let steps_path = dir.join("results/steps.json");
    let earlier: Value = std::fs::read_to_string(&steps_path).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or(Value::Null);
    let earlier_s =
        |name: &str| earlier["steps"].as_array().and_then(|a| a.iter().find(|s| s["step"] == name)).and_then(|s| s["seconds"].as_f64());
    let mut steps: Vec<(String, f64)> = Vec::new();
    // `f` returns whether it did the work (false: its outputs were there)
    let mut step = |name: &str, f: &mut dyn FnMut() -> Result<bool>| -> Result<()> {
        if cancel.load(Ordering::Relaxed) {
            bail!("interrupted before {name}; rerun into {} to resume", dir.display());
        }
        obs.line(&format!("{name} …"));
        let t0 = Instant::now();
        let worked = f()?;
        let s = t0.elapsed().as_secs_f64();
        let s = if worked { s } else { earlier_s(name).unwrap_or(s) };
        obs.line(&format!("  {name}: {s:.1} s{}", if worked { "" } else { " (done by an earlier run)" }));
        steps.push((name.to_string(), s));
        write_json(&steps_path, &json!({ "steps": steps.iter().map(|(n, s)| json!({ "step": n, "seconds": s })).collect::<Vec<_>>() }))?;
        Ok(())
    };

    // 1. calibration
    let cal_dir = dir.join("cal");
    step("calibration from the sweep", &mut || {
        if cal_dir.join(DESCRIPTION).exists() {
            return Ok(false);
        }
        let cal = calibrate(&sweep, nominal.nominal(), &codes, options.sampling)?;
        cal.save(&cal_dir)?;
        tcsense_infer::calibration_report::write_calibration_report(&cal, nominal.nominal(), &cal_dir)?;
        obs.line(&format!(
            "  wrote {}: tap gains {:?}, RMS residual {:.2e} of the peak",
            cal_dir.display(),
            cal.meta.tap_gains,
            cal.meta.residual_rms
        ));
        Ok(true)
    })?;
    let calibrated = nominal.clone().calibrated_from(&cal_dir)?;
    let Some(cal) = calibrated.calibration().cloned() else { bail!("{}: no calibration was loaded", cal_dir.display()) };

    // 2. training scenes on the sensor's grid
    let data = dir.join("data");
    let flim = matches!(options.sampling, Sampling::Heterodyne(_));
    step("training scenes", &mut || {
        if data.join("manifest.json").exists() && Dataset::open(&data).is_ok() {
            return Ok(false);
        }
        let done = std::sync::atomic::AtomicUsize::new(0);
        let progress = || obs.items("scenes", done.fetch_add(1, Ordering::Relaxed) + 1, options.scenes);
        generate_scenes(options, &codes, (h, w), options.scenes, options.seed, &data, &progress, cancel)?;
        Ok(true)
    })?;
    let ds = Dataset::open(&data)?;
    let train_items = ds.manifest.splits.iter().find(|s| s.name == "train").map_or(0, |s| s.count).max(1);

    // 3. fine-tuning, each decoder its share of the budget
    let share_s = TRAINING_SHARE * options.budget_minutes * 60.0 / entries.len().max(1) as f64;
    let runs_dir = dir.join("runs");
    let tuning = Tuning { options, calibrated: &calibrated, data: &data, cal_dir: &cal_dir, share_s, train_items, obs, cancel };
    for e in &entries {
        let out = runs_dir.join(&e.name);
        step(&format!("fine-tuning {} to the calibrated sensor", e.name), &mut || tuning.fine_tune(e, &out))?;
    }

    // 4. the check on held-back scenes through the sensor the sweep recorded
    let check_path = dir.join("results/check.json");
    let truth = sweep.manifest.sensor;
    step("check on held-back scenes", &mut || {
        if check_path.exists() {
            return Ok(false);
        }
        let Some(truth) = truth else {
            write_json(&check_path, &json!({ "truth": null, "rows": [] }))?;
            obs.line("  the sweep records no sensor (a real bench): the check needs scenes of known truth through it; skipped");
            return Ok(true);
        };
        // held-back scenes at the calibrated frame size (the correction maps are per pixel),
        // drawn with another seed than the training scenes
        let [ch, cw] = cal.meta.size;
        let check_dir = dir.join("check-scenes");
        if !(check_dir.join("manifest.json").exists() && Dataset::open(&check_dir).is_ok()) {
            // the training split of this set holds about 80 % of it
            let count = (options.check_items as f64 / 0.75).ceil() as usize + 2;
            generate_scenes(options, &codes, (ch, cw), count, options.seed ^ CHECK_SEED, &check_dir, &|| {}, cancel)?;
        }
        let ds = Dataset::open(&check_dir)?;
        let noise = Some(NoiseParams::default().validate()?);
        let split = "train";
        let settings = |real: bool| EvalSettings {
            split: split.into(),
            items: Some(options.check_items),
            noise,
            seed: options.seed,
            sensor: real.then_some(truth),
            sbr: None,
        };
        let mut rows = Vec::new();
        let mut eval = |decoder: &str, spec: String, condition: &str, sensor: &Sensor, real: bool| -> Result<()> {
            let mut d = vec![open_decoder(&spec, &Tval3Options::default(), &Device::flex())?];
            let r = evaluate(&ds, sensor, &mut d, &settings(real), &|_, _, _| {}, cancel)?;
            rows.push(row(&r[0], decoder, condition));
            obs.line(&format!("  {decoder:<24} {condition:<26} {}", r[0].line()));
            Ok(())
        };
        let tval3 = "tval3";
        eval(tval3, "tval3".into(), "ideal sensor", &nominal, false)?;
        eval(tval3, "tval3".into(), "nominal model", &nominal, true)?;
        eval(tval3, "tval3".into(), CALIBRATION_ALONE, &calibrated, true)?;
        for e in &entries {
            let own = Codes::load(&e.dir.join(runs::CODES_FILE))?.digest() == codes.digest();
            if own {
                let original = format!("{}:{}", e.model.name(), e.dir.display());
                eval(&e.name, original.clone(), "ideal sensor", &nominal, false)?;
                eval(&e.name, original.clone(), "nominal model", &nominal, true)?;
                eval(&e.name, original, CALIBRATION_ALONE, &calibrated, true)?;
            }
            // the same frames as the rows above (the truth realised on the nominal sensor, corrected
            // by the calibration); the fine-tuned run's own matrix is the calibration's
            let tuned = format!("{}:{}", e.model.name(), runs_dir.join(&e.name).display());
            eval(&e.name, tuned, FINE_TUNED, &calibrated, true)?;
        }
        let items = ds.manifest.splits.iter().find(|s| s.name == split).map_or(0, |s| s.count).min(options.check_items);
        write_json(&check_path, &json!({ "truth": truth, "split": split, "items": items, "rows": rows }))?;
        Ok(true)
    })?;

    // 5. export, each decoder as the better of the check's "calibration alone" and
    // "calibration + fine-tuning" (fine-tuned where the check cannot tell), the correction built in
    let onnx_dir = dir.join("onnx");
    let deployed_path = dir.join("results/deployed.json");
    let mut models = Vec::new();
    let mut deployed = Vec::new();
    let check_rows: Value = std::fs::read_to_string(&check_path).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or(Value::Null);
    for e in &entries {
        let alone = better_alone(&check_rows, &e.name, flim);
        deployed.push(json!({
            "decoder": e.name,
            "condition": if alone { CALIBRATION_ALONE } else { FINE_TUNED },
            "model": format!("onnx/{}.onnx", e.name),
        }));
    }
    step("ONNX export with the calibration built in", &mut || {
        let mut worked = false;
        for (e, d) in entries.iter().zip(&deployed) {
            let out = onnx_dir.join(format!("{}.onnx", e.name));
            if !out.exists() {
                let from = if d["condition"] == CALIBRATION_ALONE { e.dir.clone() } else { runs_dir.join(&e.name) };
                let run = runs::load(&from, &Device::flex())?;
                let bytes = export_to(&run, ExportOptions { calibration: Some(&cal), ..Default::default() }, &out)?;
                obs.line(&format!(
                    "  wrote {} ({:.1} kB, {}), raw {} tap images of {}x{}",
                    out.display(),
                    bytes as f64 / 1e3,
                    d["condition"].as_str().unwrap_or_default(),
                    cal.meta.units,
                    cal.meta.size[0],
                    cal.meta.size[1]
                ));
                worked = true;
            }
            models.push(out);
        }
        if worked || !deployed_path.exists() {
            write_json(&deployed_path, &json!({ "deployed": deployed }))?;
        }
        Ok(worked)
    })?;
    let deployed: Value = serde_json::from_str(
        &std::fs::read_to_string(&deployed_path).map_err(|e| crate::PipelineError::Io { path: deployed_path.clone(), cause: e })?,
    )?;

    // 6. the report
    let total: f64 = steps.iter().map(|(_, s)| s).sum();
    let report = dir.join("report.html");
    let check: Value = serde_json::from_str(
        &std::fs::read_to_string(&check_path).map_err(|e| crate::PipelineError::Io { path: check_path.clone(), cause: e })?,
    )?;
    write_json(
        &dir.join("results/steps.json"),
        &json!({ "steps": steps.iter().map(|(n, s)| json!({ "step": n, "seconds": s })).collect::<Vec<_>>(), "total_s": total }),
    )?;
    build_report(options, &names, &cal, &check, &deployed, &steps, total, flim).write(&report)?;
    obs.line(&format!("wrote {} ({total:.0} s in all)", report.display()));
    Ok(BringupSummary { report, models, steps })
}

/// The inputs of a bring-up, loaded and checked before anything is written.
struct Checked {
    codes: Codes,
    nominal: Sensor,
    sweep: Sweep,
    names: Vec<String>,
    entries: Vec<Source>,
}

/// Load the codes, the nominal sensor, the sweep and the decoders to fine-tune, and check the
/// settings and the training scenes' working set.
fn checked_inputs(options: &BringupOptions) -> Result<Checked> {
    let codes = Codes::load(&options.codes)?;
    let nominal = Sensor::build(codes.clone(), &SensorModel { sampling: options.sampling, irf: options.irf, ..Default::default() })?;
    let sweep = Sweep::load(&options.sweep)?;
    let names = if options.decoders.is_empty() { default_decoders(options.sampling) } else { options.decoders.clone() };
    let mut entries = Vec::new();
    for n in &names {
        let e = Source::open(n)?;
        if (e.model.taps(), e.model.bins()) != (nominal.taps(), nominal.bins()) {
            bail!(
                "{}: its network takes M = {} taps and T = {} bins, the sensor gives M = {}, T = {} (check --oversample/--heterodyne)",
                e.label,
                e.model.taps(),
                e.model.bins(),
                nominal.taps(),
                nominal.bins()
            );
        }
        if entries.iter().any(|o: &Source| o.name == e.name) {
            bail!("{}: two decoders named {:?}; give each once", e.label, e.name);
        }
        entries.push(e);
    }
    let (h, w) = options.size;
    let (bh, bw) = nominal.block();
    if h == 0 || w == 0 || h > MAX_SIDE || w > MAX_SIDE || h % bh != 0 || w % bw != 0 {
        bail!("bring-up settings: --size {h}x{w}: expected whole {bh}x{bw} blocks, each side from 1 to {MAX_SIDE} pixels");
    }
    if !(MIN_SCENES..=MAX_SCENES).contains(&options.scenes) {
        bail!("bring-up settings: --scenes {}: expected {MIN_SCENES} to {MAX_SCENES} training scenes", options.scenes);
    }
    if !(1..=MAX_CHECK_ITEMS).contains(&options.check_items) {
        bail!("bring-up settings: --check-items {}: expected 1 to {MAX_CHECK_ITEMS} held-back scenes", options.check_items);
    }
    if !(options.budget_minutes.is_finite() && options.budget_minutes > 0.0 && options.budget_minutes <= MAX_BUDGET_MINUTES) {
        bail!(
            "bring-up settings: --budget-minutes {}: expected a time above 0 and at most {MAX_BUDGET_MINUTES} minutes (a week)",
            options.budget_minutes
        );
    }
    if let Some(e) = options.epochs.filter(|e| !(1..=MAX_EPOCHS).contains(e)) {
        bail!("bring-up settings: --epochs {e}: expected 1 to {MAX_EPOCHS} epochs");
    }
    // the training scenes' working set, before anything is calibrated or generated
    let item_bytes = 4.0 * (h * w) as f64 * (nominal.bins() + nominal.taps() + 4) as f64;
    tcsense_sensor::mem::check_fits(
        &format!("{} training scenes of {h}x{w}", options.scenes),
        item_bytes * options.scenes as f64,
        "use fewer --scenes or a smaller --size",
    )?;
    Ok(Checked { codes, nominal, sweep, names, entries })
}

/// `count` scenes of the sensor's domain (FLIm on a heterodyne grid, else LiDAR) of `size`,
/// seeded by `seed`, on the codes' grid, into `dir`.
#[allow(clippy::too_many_arguments)]
fn generate_scenes(
    options: &BringupOptions,
    codes: &Codes,
    (h, w): (usize, usize),
    count: usize,
    seed: u64,
    dir: &Path,
    progress: &(dyn Fn() + Sync),
    cancel: &AtomicBool,
) -> Result<()> {
    let gen = if matches!(options.sampling, Sampling::Heterodyne(_)) {
        Generator::Flim(FlimParams { height: h, width: w, ..Default::default() })
    } else {
        Generator::Lidar(LidarParams { height: h, width: w, ..Default::default() })
    };
    let grid = TimeGrid { length: codes.length(), clock_hz: codes.clock_hz, sampling: options.sampling };
    store::generate(&gen, &grid, count, seed, dir, &WriteOptions { shard_size: DEFAULT_SHARD, force: true, progress, cancel })?;
    Ok(())
}

/// What every fine-tuning of a bring-up shares: the settings, the calibrated sensor, the
/// training scenes, the calibration and each decoder's share of the budget.
struct Tuning<'a> {
    options: &'a BringupOptions,
    calibrated: &'a Sensor,
    data: &'a Path,
    cal_dir: &'a Path,
    share_s: f64,
    train_items: usize,
    obs: &'a dyn Observer,
    cancel: &'a AtomicBool,
}

impl Tuning<'_> {
    /// Fine-tune zoo decoder `e` into `out` within its share of the budget (or resume it);
    /// whether it did any work.
    fn fine_tune(&self, e: &Source, out: &Path) -> Result<bool> {
        let Tuning { options, calibrated, data, cal_dir, share_s, train_items, obs, cancel } = *self;
        let (h, w) = options.size;
        let resume = out.join(CONFIG_FILE).exists();
        let req = if resume {
            TrainRequest { decoder: e.model.name().into(), output: out.to_path_buf(), resume: true, ..Default::default() }
        } else {
            let epochs = match options.epochs {
                Some(n) => n,
                None => {
                    let ms = tcsense_train::bench::bench_step(calibrated.matrix(), &e.model, h, w, 3)?.step_ms + STEP_OVERHEAD_MS;
                    let n = ((share_s / (ms / 1e3 * train_items.div_ceil(2) as f64)).floor() as usize).max(1);
                    obs.line(&format!("  {}: {ms:.1} ms per step at {h}x{w}, {train_items} items → {n} epochs in {share_s:.0} s", e.name));
                    n
                }
            };
            TrainRequest {
                decoder: e.model.name().into(),
                output: out.to_path_buf(),
                dataset: Some(data.to_path_buf()),
                codes: Some(options.codes.clone()),
                init_from: Some(e.dir.clone()),
                calibration: Some(cal_dir.to_path_buf()),
                // the nominal sensor the calibration was measured against (raw frames name it)
                irf: Some(match options.irf {
                    Irf::Ideal => "ideal".into(),
                    Irf::Physical { .. } => "physical".into(),
                }),
                sensor_residue: Some(SENSOR_RESIDUE),
                epochs: Some(epochs),
                seed: Some(options.seed),
                ..Default::default()
            }
        };
        let prepared = request::prepare(&req)?;
        if resume && out.join(WEIGHTS_FILE).exists() && done_epochs(&out) >= prepared.cfg.epochs {
            return Ok(false);
        }
        // the share is a budget, not an estimate: past DEADLINE_SLACK of it the training stops
        // at the next step with its checkpoint kept (the model; a rerun continues it)
        let (stop, finished) = (AtomicBool::new(false), AtomicBool::new(false));
        let deadline =
            std::time::Duration::from_secs_f64(if options.epochs.is_some() { f64::INFINITY } else { share_s * DEADLINE_SLACK }.min(1e9));
        let res = std::thread::scope(|sc| {
            sc.spawn(|| {
                let t0 = Instant::now();
                while !finished.load(Ordering::Relaxed) {
                    if cancel.load(Ordering::Relaxed) || t0.elapsed() > deadline {
                        stop.store(true, Ordering::Relaxed);
                        break;
                    }
                    std::thread::sleep(std::time::Duration::from_millis(100));
                }
            });
            let r = request::run(&prepared, &Device::flex(), obs.training(), &stop);
            finished.store(true, Ordering::Relaxed);
            r
        });
        match res {
            Err(tcsense_train::TrainError::Cancelled) if !cancel.load(Ordering::Relaxed) => {
                obs.line(&format!("  {}: its share of the budget is spent after {} of {} epochs; its last checkpoint is the model (rerun into the directory to continue)", e.name, done_epochs(&out), prepared.cfg.epochs));
            }
            r => {
                r?;
            }
        }
        Ok(true)
    }
}

/// Whether the check found decoder `name` as given (the calibration alone) more accurate than
/// fine-tuned: a lower lifetime MAE (`flim`) or first-return median error. False where the check
/// has no row of either (a real bench, a decoder on other codes than the sensor's): fine-tuned.
fn better_alone(check: &Value, name: &str, flim: bool) -> bool {
    let key = if flim { "lifetime_mae_ns" } else { "first_return_median_m" };
    let error =
        |condition: &str| check["rows"].as_array()?.iter().find(|r| r["decoder"] == name && r["condition"] == condition)?[key].as_f64();
    matches!((error(CALIBRATION_ALONE), error(FINE_TUNED)), (Some(a), Some(t)) if a < t)
}

/// Epochs a run has logged.
fn done_epochs(run: &Path) -> usize {
    std::fs::read_to_string(run.join("metrics.csv")).map_or(0, |t| t.lines().count().saturating_sub(1))
}

/// One row of the check: the decoder, the condition and its metrics.
fn row(r: &EvalRow, decoder: &str, condition: &str) -> Value {
    json!({
        "decoder": decoder,
        "condition": condition,
        "psnr_db": r.psnr_db,
        "first_return_median_m": r.depth_median_m.first().copied(),
        "detected": r.depth.first().map(|d| d.detection_rate()),
        "lifetime_mae_ns": r.lifetime_mae_s.map(|v| v * 1e9),
        "seconds_per_frame": r.seconds_per_frame,
    })
}

#[allow(clippy::too_many_arguments)]
fn build_report(
    o: &BringupOptions,
    names: &[String],
    cal: &Calibration,
    check: &Value,
    deployed: &Value,
    steps: &[(String, f64)],
    total: f64,
    flim: bool,
) -> Report {
    let mut sections = Vec::new();
    sections.push(Section {
        id: "steps".into(),
        title: "The path and its time".into(),
        blocks: vec![
            Block::Text(format!(
                "From the sweep {} of the codes {} to decoders deployed for the calibrated sensor: {} (fine-tuned within a budget of {} min). A step done by an earlier run into the same directory shows the time it took then.",
                o.sweep.display(),
                o.codes.display(),
                names.join(", "),
                o.budget_minutes
            )),
            Block::Table(Table {
                caption: format!("Wall time of every step ({total:.0} s in all)"),
                headers: vec!["step".into(), "seconds".into()],
                rows: steps.iter().enumerate().map(|(i, (n, _))| vec![Cell::text(n.clone()), Cell::from_json("results/steps.json", &json!({ "steps": steps.iter().map(|(_, s)| json!({ "seconds": s })).collect::<Vec<_>>() }), &format!("/steps/{i}/seconds"), Format::Fixed(1))]).collect(),
            }),
        ],
    });
    let gains: Vec<String> = cal.meta.tap_gains.iter().map(|g| format!("{g:.4}")).collect();
    sections.push(Section {
        id: "calibration".into(),
        title: "Calibration".into(),
        blocks: vec![
            Block::Text(format!(
                "Measured from {} delays: tap gains [{}], RMS residual {:.2e} of the peak, gain and dark maps of {}x{} pixels in {}. The calibration's own page, cal/report.html, shows the maps, the fit and the responses.",
                cal.meta.delays,
                gains.join(", "),
                cal.meta.residual_rms,
                cal.meta.size[0],
                cal.meta.size[1],
                cal.meta.units
            )),
            Block::Figure { src: "cal/fit.png".into(), caption: "The sweep's mean response per tap against the calibrated model (cal/report.html has the rest).".into() },
        ],
    });
    let metric: (&str, &str, Format) = if flim {
        ("lifetime MAE (ns)", "lifetime_mae_ns", Format::Fixed(3))
    } else {
        ("first-return median error (m)", "first_return_median_m", Format::Fixed(3))
    };
    let rows: Vec<Vec<Cell>> = check["rows"]
        .as_array()
        .map(|rs| {
            rs.iter()
                .enumerate()
                .map(|(i, r)| {
                    vec![
                        Cell::text(r["decoder"].as_str().unwrap_or_default()),
                        Cell::text(r["condition"].as_str().unwrap_or_default()),
                        Cell::from_json("results/check.json", check, &format!("/rows/{i}/{}", metric.1), metric.2),
                        Cell::from_json("results/check.json", check, &format!("/rows/{i}/psnr_db"), Format::Fixed(2)),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    let text = if check["truth"].is_null() {
        "The sweep records no sensor: it comes from a real bench, and held-back scenes of known truth through that sensor are what the check needs. Decode frames of known scenes with the exported models to check them.".to_string()
    } else {
        format!(
            "{} held-back scenes (the {} split of check-scenes/, at the calibrated frame size), through the sensor the sweep recorded (its non-idealities: {}), with noise: every decoder on the ideal sensor, through the nominal model (the raw tap images decoded as if the sensor were ideal), with the calibration alone (the decoder as given, frames corrected, decoded with the measured matrix) and calibrated + fine-tuned. A decoder trained on other codes than the sensor's has only the last row.",
            check["items"],
            check["split"].as_str().unwrap_or("test"),
            check["truth"]
        )
    };
    sections.push(Section {
        id: "check".into(),
        title: "Decoders on the ideal sensor, the nominal model, the calibration and the fine-tuning".into(),
        blocks: vec![
            Block::Text(text),
            Block::Table(Table {
                caption: format!("{} and cube PSNR (dB) per decoder and condition", metric.0),
                headers: vec!["decoder".into(), "condition".into(), metric.0.into(), "PSNR (dB)".into()],
                rows,
            }),
        ],
    });
    let models: Vec<String> =
        names.iter().map(|n| format!("tcsense infer --model onnx/{n}.onnx --measurements RAW.npy -o out/{n}")).collect();
    let chosen: Vec<Vec<Cell>> = deployed["deployed"]
        .as_array()
        .map(|ds| {
            ds.iter()
                .map(|d| {
                    vec![
                        Cell::text(d["decoder"].as_str().unwrap_or_default()),
                        Cell::text(d["condition"].as_str().unwrap_or_default()),
                        Cell::text(d["model"].as_str().unwrap_or_default()),
                    ]
                })
                .collect()
        })
        .unwrap_or_default();
    sections.push(Section {
        id: "deploy".into(),
        title: "Deployed models".into(),
        blocks: vec![
            Block::Text(format!(
                "Each decoder is deployed as the better of its check's rows \"{CALIBRATION_ALONE}\" (the decoder as given) and \"{FINE_TUNED}\" (fine-tuned where the check has no row of either). Each takes the sensor's raw tap images: the calibration's dark and gain correction is in the graph, or, for a decoder on a fit's evidence, in the model's metadata, applied by its runtime before the evidence."
            )),
            Block::Table(Table {
                caption: "The deployed models (results/deployed.json)".into(),
                headers: vec!["decoder".into(), "deployed as".into(), "model".into()],
                rows: chosen,
            }),
            Block::Code(models.join("\n")),
        ],
    });
    Report { title: "Sensor bring-up".into(), subtitle: format!("{} → {}", o.sweep.display(), names.join(", ")), sections }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The deployed condition is the check's lower error of the decoder's calibration alone and
    /// fine-tuned, by the domain's metric; fine-tuned where either row or value is missing.
    #[test]
    fn the_better_of_the_calibration_alone_and_fine_tuned_is_deployed() {
        let check = json!({ "rows": [
            { "decoder": "a", "condition": CALIBRATION_ALONE, "lifetime_mae_ns": 0.20, "first_return_median_m": 0.5 },
            { "decoder": "a", "condition": FINE_TUNED, "lifetime_mae_ns": 0.25, "first_return_median_m": 0.4 },
            { "decoder": "b", "condition": FINE_TUNED, "lifetime_mae_ns": 0.25 },
            { "decoder": "c", "condition": CALIBRATION_ALONE, "lifetime_mae_ns": null },
            { "decoder": "c", "condition": FINE_TUNED, "lifetime_mae_ns": 0.3 },
        ]});
        assert!(better_alone(&check, "a", true), "FLIm: the lower lifetime MAE");
        assert!(!better_alone(&check, "a", false), "LiDAR: the lower range error");
        assert!(!better_alone(&check, "b", true), "no row of the calibration alone (other codes)");
        assert!(!better_alone(&check, "c", true), "no value");
        assert!(!better_alone(&json!({ "truth": null, "rows": [] }), "a", true), "a real bench's empty check");
    }
}
