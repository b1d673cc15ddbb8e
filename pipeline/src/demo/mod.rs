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
//!
//! One file per concern: this one runs the steps in order; [`plan`] fixes what they do,
//! [`steps`] holds the steps' work (trainings, metric rows, decoded frames), [`figures`] draws
//! and [`report`] writes the page.

use crate::error::{bail, Context, PipelineError, Result};
use crate::write_json;
use ndarray::{Array2, Array3, Array4, Axis, Ix3, Ix4};
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use tcsense_datasets::flim::FlimParams;
use tcsense_datasets::lidar::LidarParams;
use tcsense_datasets::store::{self, Generator, WriteOptions, DEFAULT_SHARD};
use tcsense_datasets::{Dataset, TimeGrid};
use tcsense_infer::eval::{evaluate, EvalRow, EvalSettings};
use tcsense_infer::figures::{self as plot, Series};
use tcsense_infer::onnx::{export_to, ExportOptions};
use tcsense_infer::products::{depth_map, point_cloud, referenced_phasors, PeakOptions};
use tcsense_infer::registry::{names, open_decoder};
use tcsense_infer::report::{Block, Cell, Format, Report, Section, Table};
use tcsense_infer::selection::{evaluate as evaluate_codes, select, EvalSetup};
use tcsense_models::decoder::Control;
use tcsense_models::runs::{self, ModelConfig, CODES_FILE, CONFIG_FILE};
use tcsense_models::{AdmmNetConfig, Device, Prior, Tval3Options, UnetConfig};
use tcsense_sensor::codes::{Codes, DEFAULT_CLOCK_HZ};
use tcsense_sensor::design::{design, Criterion, DesignOptions, Objective, Quiet};
use tcsense_sensor::identify::{Light, DEFAULT_ALIAS_THRESHOLD};
use tcsense_sensor::measure::measure_batch;
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::nonideal::NonIdeal;
use tcsense_sensor::npy::{read_npy, write_bytes, write_npy};
use tcsense_sensor::params::{C, DEFAULT_LASER_FWHM_S, DEFAULT_TAP_TAU_S};
use tcsense_sensor::sweep::{simulate_sweep, SweepSettings};
use tcsense_sensor::{export, generate, Irf, NoiseParams, Sampling, Sensor, SensorParams};
use tcsense_train::deep_sensing::LearnCodes;
use tcsense_train::{train, TrainConfig, TrainError};

mod figures;
mod plan;
mod report;
mod steps;

use figures::*;
use plan::*;
use report::*;
use steps::*;

/// Share of the budget given to the four trainings (the rest: data, code selection, TVAL3,
/// evaluation, export, timing, figures: about 50 s of the default demo on two cores).
const TRAINING_SHARE: f64 = 0.8;
/// Share of the budget given to the bring-up of the non-ideal sensor (on top of the rest).
const BRINGUP_SHARE: f64 = 0.1;

/// The demo's real sensor: what a multitap pixel on the bench departs from the model by (5 %
/// tap gains, 2 % PRNU, a dark offset with a pattern, a diffusion tail, 0.1 ns gate skew and the
/// lab's 92.5 % modulation contrast), seeded.
fn bench_sensor(seed: u64) -> NonIdeal {
    NonIdeal {
        tap_gain: 0.05,
        prnu: 0.02,
        dark: 0.01,
        dark_fpn: 0.002,
        tail: 0.1,
        tail_tau_s: 1e-9,
        gate_skew_s: 0.1e-9,
        modulation_contrast: 0.925,
        seed,
        ..NonIdeal::default()
    }
}
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

pub use crate::observer::Observer;

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

/// The file that marks a directory as a demo's (so that an interrupted first run resumes).
const DEMO_MARKER: &str = ".tcsense-demo";

/// Run the demo into `dir` (rerunning into the same directory resumes it). `cancel` stops
/// it at the next step or training step, leaving what is done for the rerun.
pub fn run(options: &DemoOptions, dir: &Path, obs: &dyn Observer, cancel: &AtomicBool) -> Result<DemoSummary> {
    let t_start = Instant::now();
    let request = Request::from_options(options)?;
    let plan_path = dir.join("plan.json");
    let saved = open_demo_dir(dir, &request, &plan_path)?;
    let resumed = saved.is_some();
    // datasets and (on a first run) the plan, then codes, the trainings, export, evaluation,
    // frames, timing and the report: `of` is fixed once the plan is known
    let mut steps = Steps { obs, n: 0, of: if saved.is_some() { 12 } else { 13 }, times: Vec::new() };
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
            let p = steps.run("plan: timing one training step of each network to size the epochs to the budget", || {
                make_plan(&request, &lidar, &flim, obs)
            })?;
            write_bytes(&plan_path, (serde_json::to_string_pretty(&p)? + "\n").as_bytes())?;
            p
        }
    };
    steps.of = steps.n + 1 + plan.trainings.len() + 8;
    for t in &plan.trainings {
        obs.line(&format!(
            "  {:<14} {:>4} epochs × {:>4} steps × {:>6.1} ms ≈ {:>5.0} s  ({})",
            t.name,
            t.epochs,
            t.steps_per_epoch,
            t.step_ms,
            (t.epochs * t.steps_per_epoch) as f64 * t.step_ms / 1e3,
            t.title
        ));
    }

    // 2. codes: one random draw, the best of `candidates` by TVAL3 (the paper's selection), and
    // codes designed for range identifiability (the demo's selected set), exported
    let random_path = dir.join("codes/random.json");
    let mse_path = dir.join("codes/best-mse.json");
    let selected_path = dir.join("codes/selected.json");
    steps.run("codes: random under the constraints, the best of several by TVAL3 (noise-free), and codes designed for range identifiability (selected), exported to the code memory", || {
        choose_codes(dir, &lidar, &plan, seed, obs, cancel)
    })?;
    let selected = Codes::load(&selected_path)?;

    // 3. trainings
    let runs_dir = dir.join("runs");
    let eval_noise = NoiseParams::default().validate()?;
    for t in &plan.trainings {
        cancelled(cancel)?;
        let (ds, ds_dir) = if t.name.ends_with("flim") { (&flim, &flim_dir) } else { (&lidar, &lidar_dir) };
        steps.run(&format!("training {}: {} epochs", t.title, t.epochs), || {
            train_one(t, &plan, ds, ds_dir, &selected, &runs_dir.join(&t.name), obs, cancel)
        })?;
    }
    let learned = code_sets_compared(dir, &runs_dir, [&random_path, &mse_path], &selected, obs)?;

    // 4. ONNX export
    steps.run("ONNX export of every trained decoder (opset 17)", || {
        for t in &plan.trainings {
            let out = dir.join("onnx").join(format!("{}.onnx", t.name));
            if older_than(&out, &runs_dir.join(&t.name).join(runs::WEIGHTS_FILE)) {
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
        let settings = |items| EvalSettings { split: "test".into(), items: Some(items), noise: Some(eval_noise), seed, sensor: None, sbr: None };
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
        let cube_decoders = |run: &str| vec![("TVAL3", names::TVAL3.to_string()), ("ADMM-Net", run_of(names::ADMM_NET, run)), ("ADMM-Net", onnx(run))];
        if !lidar_json.exists() {
            // the template fit to the taps is a row of every code set: the model the networks must beat
            let fit = ("range fit to the taps (2 returns)", names::DEPTH_FIT.to_string());
            let mut selected_set = cube_decoders("admm-lidar");
            selected_set.extend([("Aᵀ + U-Net", run_of(names::UNET, "unet-lidar")), ("Aᵀ + U-Net", onnx("unet-lidar")), fit.clone()]);
            let mut rows = rows_of(&lidar, &sensor(&selected, &lidar)?, &selected_set, plan.lidar_eval_items, &|r, n, e| lidar_row(r, "selected", n, e))?;
            let mut learned_set = cube_decoders("learned-lidar");
            learned_set.push(fit);
            rows.extend(rows_of(&lidar, &sensor(&learned, &lidar)?, &learned_set, plan.lidar_eval_items, &|r, n, e| lidar_row(r, "learned", n, e))?);
            // the zoo's decoder fine-tuned to the selected codes, and as shipped on its own codes
            if let (true, Some((zoo_dir, _))) = (plan.trainings.iter().any(|t| t.name == "zoo-lidar"), zoo_entry(&lidar)) {
                let tuned = [("ADMM-Net (zoo, fine-tuned)", run_of(names::ADMM_NET, "zoo-lidar"))];
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
            for (entry, name, kind) in [(ZOO_FLIM_CUBE, "ADMM-Net (zoo, as shipped, its own codes)", names::ADMM_NET), (ZOO_LIFETIME, "lifetime decoder (zoo, as shipped, its own codes)", names::LIFETIME)] {
                if let Some((zoo_dir, _)) = zoo_entry_named(entry, &flim) {
                    let shipped = (name, format!("{kind}:{}", zoo_dir.display()));
                    rows.extend(shipped_rows(&flim, &zoo_dir, shipped, plan.flim_eval_items, &|r, n, e| flim_row(r, "the zoo's", n, e))?);
                }
            }
            write_json(&flim_json, &json!({ "split": "test", "items": plan.flim_eval_items, "noise": eval_noise, "noise_seed": seed, "frame": [h, w], "rows": rows }))?;
        }
        Ok(())
    })?;

    // 5b. the light axis: the decoders of each application at every rung of a photon ladder,
    // beside the codes' Cramér–Rao bound (`results/photon-*.json`, `figures/photon-*.png`)
    steps.run(
        "photon-efficiency curves: the template fits beside the networks at signal 0.8, 0.1, 0.02 and 0.005 of the full well",
        || {
            photon_curves(
                dir,
                &lidar,
                &flim,
                &selected,
                &learned,
                &runs_dir,
                plan.lidar_eval_items,
                plan.flim_eval_items,
                &eval_noise,
                seed,
                obs,
                cancel,
            )
        },
    )?;

    // 6. one frame of each dataset through every decoder, kept for the figures
    steps.run("one test frame of each dataset through every decoder (for the figures)", || {
        decode_frames(dir, &lidar, &flim, &selected, &learned, &eval_noise, seed, cancel)
    })?;

    // 7. timing at the sensor's frame size
    steps.run(
        &format!("timing at {}x{}: ONNX Runtime (2 and 1 threads) and burn, per frame", request.timing_size[0], request.timing_size[1]),
        || time_decoders(dir, &runs_dir, &request, &plan, obs, cancel),
    )?;

    // 7b. the LiDAR decoders as deployed, timed at the sensor's frame size beside their errors
    // on the photon ladder (`results/speed-lidar.json`, `figures/speed-accuracy-lidar.png`)
    steps.run(
        &format!(
            "deployed speed against accuracy: the LiDAR decoders (the fits, ONNX Runtime with the fits around it) on {SPEED_FRAMES} frames of {}x{}",
            request.timing_size[0], request.timing_size[1]
        ),
        || {
            let size = (request.timing_size[0], request.timing_size[1]);
            speed_against_accuracy(dir, &lidar, &selected, size, plan.timing_rounds, &eval_noise, seed, cancel)
        },
    )?;

    // 8. a non-ideal sensor brought up: its delay sweep, the calibration, the demo's LiDAR
    // decoders fine-tuned to it, ONNX for its raw tap images, the check (`crate::bringup`)
    steps.run("bring-up of a non-ideal sensor: delay sweep, calibration, the LiDAR decoders fine-tuned to it, ONNX for its raw tap images, the check", || {
        bring_up(dir, &runs_dir, &selected, &selected_path, &lidar, &request, &plan, obs, cancel)
    })?;

    // 9. figures and the report
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

/// Make `dir` a demo's directory, or find the plan of the demo it holds: a directory of
/// something else is refused, and a demo started with other settings is never resumed.
fn open_demo_dir(dir: &Path, request: &Request, plan_path: &Path) -> Result<Option<Plan>> {
    // a directory of something else is never written into: only a demo's (its plan) is resumed
    let holds_files = std::fs::read_dir(dir).map(|mut d| d.next().is_some()).unwrap_or(false);
    if dir.exists() && !dir.is_dir() {
        bail!("{}: exists and is not a directory; choose another output directory", dir.display());
    }
    let marker = dir.join(DEMO_MARKER);
    if holds_files && !plan_path.exists() && !marker.exists() {
        bail!(
            "{}: the directory holds files but is no demo's (no plan.json), so it is not resumed; choose another output directory",
            dir.display()
        );
    }
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    // marks the directory as a demo's from its first moment (plan.json comes after the datasets)
    write_bytes(&marker, b"a tcsense demo directory: rerun `tcsense demo` into it to resume\n")?;
    for sub in ["codes", "runs", "onnx", "results", "figures", "frames"] {
        std::fs::create_dir_all(dir.join(sub)).with_context(|| format!("cannot create {}", dir.join(sub).display()))?;
    }
    let saved: Option<Plan> = if plan_path.exists() {
        let p: Plan = serde_json::from_slice(&std::fs::read(&plan_path).with_context(|| format!("cannot read {}", plan_path.display()))?)
            .with_context(|| format!("{}: not a demo plan; choose another output directory", plan_path.display()))?;
        if p.request != *request {
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
    Ok(saved)
}

/// The demo's code sets: one random draw (`codes/random.json`), the best of the plan's
/// candidates by TVAL3 (`codes/best-mse.json`, the paper's selection) and codes designed for
/// range identifiability (`codes/selected.json`, the set the demo decodes with), the
/// selection's record in `results/selection.json`, and the selected set exported to the code
/// memory. Sets already there are kept.
fn choose_codes(dir: &Path, lidar: &Dataset, plan: &Plan, seed: u64, obs: &dyn Observer, cancel: &AtomicBool) -> Result<()> {
    let constraints = generate::PROTOTYPE_CONSTRAINTS;
    let random_path = dir.join("codes/random.json");
    let mse_path = dir.join("codes/best-mse.json");
    let selected_path = dir.join("codes/selected.json");
    let selection_path = dir.join("results/selection.json");
    if !random_path.exists() {
        generate::prototype_codes(seed)?.save(&random_path)?;
    }
    if !selected_path.exists() || !selection_path.exists() || !mse_path.exists() {
        let x = lidar.load("val", "x")?.into_dimensionality::<Ix4>()?;
        let cubes: Vec<Array3<f32>> = x.axis_iter(Axis(0)).take(plan.select_items).map(|v| v.to_owned()).collect();
        let g = lidar.manifest.grid;
        let setup = EvalSetup {
            base: SensorParams { sampling: g.sampling, irf: physical_irf(), length: g.length, clock_hz: g.clock_hz, ..Default::default() },
            tval3: Tval3Options::default(),
        };
        let mut on =
            |c: &tcsense_infer::selection::Candidate| obs.line(&format!("  candidate seed {:>3}: TVAL3 MSE {:.4e}", c.seed, c.mse));
        let (best, all) =
            select(generate::PROTOTYPE_SHAPE, DEFAULT_CLOCK_HZ, constraints, plan.candidates, seed, &setup, &cubes, &mut on, cancel)?;
        // design by identifiability: closed form, seconds
        let sensor = Sensor::ideal(best.clone(), g.sampling, physical_irf())?;
        let obj = Objective::new(Criterion::Range, sensor.spec(), Light::default(), DEFAULT_ALIAS_THRESHOLD);
        let designed = design(
            &obj,
            generate::PROTOTYPE_SHAPE,
            DEFAULT_CLOCK_HZ,
            constraints,
            &DesignOptions { seed, ..Default::default() },
            &Quiet,
            cancel,
        )?;
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
}

/// The codes deep sensing learned (`runs/learned-lidar`), saved and exported to the code
/// memory, and the identifiability of every code set of the demo (random, best MSE, `selected`,
/// learned; `others` the first two files) in `results/identifiability.json`.
fn code_sets_compared(dir: &Path, runs_dir: &Path, others: [&Path; 2], selected: &Codes, obs: &dyn Observer) -> Result<Codes> {
    let learned_dir = runs_dir.join("learned-lidar");
    let learned = Codes::load(&learned_dir.join(CODES_FILE))?;
    learned.save(&dir.join("codes/learned.json"))?;
    let regs = export::export(&learned, &dir.join("code-memory/learned"))?;
    obs.line(&format!(
        "  learned codes exported to {}: {} channels of {} bytes, ECLEN = {}",
        dir.join("code-memory/learned").display(),
        regs.channel_count,
        regs.bytes_per_channel,
        regs.ECLEN
    ));
    // what every code set of the demo lets the taps tell apart
    let ident = crate::identifiability::analyse(
        &[("random", &Codes::load(others[0])?), ("best MSE", &Codes::load(others[1])?), ("selected", &selected), ("learned", &learned)],
        physical_irf(),
    )?;
    write_json(&dir.join("results/identifiability.json"), &ident)?;
    obs.line("  identifiability of the code sets (physical IRF, 1000 e⁻ signal):");
    for l in crate::identifiability::lines(&ident) {
        obs.line(&l);
    }
    Ok(learned)
}

/// The demo's decoders timed at the sensor's frame size (ONNX Runtime on 2 and 1 threads,
/// burn) into `results/timing.json`, unless there already.
fn time_decoders(dir: &Path, runs_dir: &Path, request: &Request, plan: &Plan, obs: &dyn Observer, cancel: &AtomicBool) -> Result<()> {
    if dir.join("results/timing.json").exists() {
        return Ok(());
    }
    let mut all = Vec::new();
    for name in ["unet-lidar", "admm-lidar", "admm-flim"] {
        cancelled(cancel)?;
        let run = runs::load(&runs_dir.join(name), &Device::flex())?;
        let model = dir.join("onnx").join(format!("{name}.onnx"));
        let t = tcsense_infer::timing::time_decoder(
            Some(&run),
            &model,
            (request.timing_size[0], request.timing_size[1]),
            &[2, 1],
            plan.timing_rounds,
        )?;
        for e in &t.engines {
            obs.line(&format!("  {name:<12} {:<26} {:>9.1} ms/frame {:>7.1} frames/s", e.engine, e.ms_per_frame, e.frames_per_s));
        }
        all.push(json!({ "run": name, "timing": t }));
    }
    write_json(&dir.join("results/timing.json"), &json!({ "sensor_fps": SENSOR_FPS, "decoders": all }))
}

/// A non-ideal sensor brought up (`crate::bringup`, into `bringup/`): its delay sweep, the
/// calibration, the demo's LiDAR decoders fine-tuned to it, ONNX for its raw tap images, the
/// check.
#[allow(clippy::too_many_arguments)]
fn bring_up(
    dir: &Path,
    runs_dir: &Path,
    selected: &Codes,
    selected_path: &Path,
    lidar: &Dataset,
    request: &Request,
    plan: &Plan,
    obs: &dyn Observer,
    cancel: &AtomicBool,
) -> Result<()> {
    let (seed, [h, w]) = (request.seed, request.size);
    let sweep = dir.join("bench-sweep");
    if !sweep.join(tcsense_sensor::sweep::MANIFEST).exists() {
        let a = sensor(selected, lidar)?;
        let settings = SweepSettings {
            size: (h, w),
            average: 64,
            noise: NoiseParams::default(),
            noisy: true,
            adc: false,
            png: false,
            level: 0.7,
            seed,
        };
        simulate_sweep(a.nominal(), a.codes(), &bench_sensor(seed), &settings, &sweep)?;
    }
    let options = crate::bringup::BringupOptions {
        sweep,
        codes: selected_path.to_path_buf(),
        sampling: lidar.manifest.grid.sampling,
        irf: physical_irf(),
        decoders: ["admm-lidar", "unet-lidar"].iter().map(|n| runs_dir.join(n).display().to_string()).collect(),
        budget_minutes: request.budget_minutes * BRINGUP_SHARE,
        // fixed, so that a resumed demo finds its fine-tunings done whatever the machine's load
        epochs: Some(if request.quick { 2 } else { 8 }),
        scenes: (request.lidar_scenes / 4).max(8),
        size: (h, w),
        check_items: plan.lidar_eval_items,
        seed,
    };
    crate::bringup::run(&options, &dir.join("bringup"), obs, cancel)?;
    Ok(())
}

/// Generate a dataset unless a complete one is there (a partial one is never left: the
/// generator writes atomically).
fn generate_once(
    gen: &Generator,
    grid: &TimeGrid,
    count: usize,
    seed: u64,
    out: &Path,
    obs: &dyn Observer,
    cancel: &AtomicBool,
) -> Result<()> {
    if out.join("manifest.json").exists() && Dataset::open(out).is_ok() {
        return Ok(());
    }
    let what = out.file_name().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let done = std::sync::atomic::AtomicUsize::new(0);
    let progress = || obs.items(&what, done.fetch_add(1, Ordering::Relaxed) + 1, count);
    let m = store::generate(
        gen,
        grid,
        count,
        seed,
        out,
        &WriteOptions { shard_size: DEFAULT_SHARD, force: true, progress: &progress, cancel },
    )?;
    obs.line(&format!(
        "  wrote {}: {count} scenes, {}x{}, T = {} bins of {:.1} ps",
        out.display(),
        m.size[0],
        m.size[1],
        m.bins,
        m.bin_width_s * 1e12
    ));
    Ok(())
}

/// Whether the product `out` must be made again from `source`: it is missing, or `source` was
/// written after it (a run trained again since its export). A missing `source` keeps `out`.
fn older_than(out: &Path, source: &Path) -> bool {
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    match (modified(out), modified(source)) {
        (Some(made), Some(source)) => source > made,
        (None, _) => true,
        (Some(_), None) => false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_export_older_than_its_run_is_made_again() {
        let d = std::env::temp_dir().join(format!("tcsense-stale-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let (out, weights) = (d.join("x.onnx"), d.join("model.bpk"));
        assert!(older_than(&out, &weights), "a missing export is made");
        std::fs::write(&out, b"onnx").unwrap();
        assert!(!older_than(&out, &weights), "an export without weights beside it is kept");
        std::fs::write(&weights, b"bpk").unwrap();
        let t = std::time::SystemTime::now();
        let at = |p: &Path, s: std::time::SystemTime| std::fs::File::options().write(true).open(p).unwrap().set_modified(s).unwrap();
        at(&out, t);
        at(&weights, t - std::time::Duration::from_secs(60));
        assert!(!older_than(&out, &weights), "an export newer than its weights is kept");
        at(&weights, t + std::time::Duration::from_secs(60));
        assert!(older_than(&out, &weights), "weights trained again after the export: exported again");
        std::fs::remove_dir_all(&d).unwrap();
    }

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
