//! One training loop for every trainable decoder ([`Network`]): Adam, batches in an order
//! seeded by `(seed, epoch)`, measurements simulated on the fly with fresh noise seeded by
//! `(seed, step)` through the sensor's one physics entry (`tcsense_sensor::measure`),
//! validation after every epoch on the inference device through the decoder contract, and an
//! atomic checkpoint after every epoch. A run is a pure function of its config, so a resumed
//! run continues exactly where its checkpoint was taken.

use burn::module::{Module, ModuleMapper, ModuleVisitor, Param, ParamId};
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::{Device, Tensor, TensorData};
use ndarray::{Array4, Axis};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use tcsense_datasets::grid::C;
use tcsense_datasets::Dataset;
use tcsense_models::decoder::{Control, Decoder};
use tcsense_models::metrics::{depth_errors, mse, psnr};
use tcsense_models::net::{to_tensor, NetDecoder, Network, Prediction};
use tcsense_models::runs::{ModelConfig, CODES_FILE, CONFIG_FILE};
use tcsense_models::SensorTensors;
use tcsense_sensor::measure::{measure_batch, measure_batch_at, signal_exposure};
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::{Codes, FramePlan, NoiseParams, Sensor};

use crate::augment::DepthLabels;
use crate::config::Loss;
use crate::config::TrainConfig;
use crate::data::{load_cubes, load_depth, load_lifetime_labels};
use crate::deep_sensing::{LearnCodes, Learner};
use crate::loss::{depth_grid_loss, depth_loss, lifetime_loss, loss_fn};
use crate::run_dir::{
    latest_checkpoint, load_checkpoint, read_json, read_rows, save_checkpoint, write_json, write_rows, EpochMetrics, RunLock, RunState,
    METRICS_FILE,
};
use crate::{file_err, Result, TrainError};

/// Stream of the validation noise seeds, apart from the training steps' `(seed, step)`.
const VALIDATION_STREAM: u64 = 0x5641_4C49_4441_5445;

/// Callbacks for progress display.
pub trait Progress {
    /// After each optimiser step.
    fn step(&self, _epoch: usize, _step_in_epoch: usize, _steps_per_epoch: usize, _loss: f64) {}
    /// After each epoch's validation.
    fn epoch(&self, _m: &EpochMetrics) {}
}

/// No progress display.
pub struct Quiet;
impl Progress for Quiet {}

/// Validation metrics of a decoder over cubes `x` with measurements simulated with noise
/// seeded per item (the same every epoch): `val_mse`, `val_psnr_db` for decoders of cubes;
/// `val_depth_rmse_m`, `val_depth_mae_m`, `val_detection` (over all returns) against the
/// range labels `depth` for decoders of depth.
///
/// # Shapes
/// - `x`: `[N, T, H, W]`, `depth`: `[N, K, H, W]`
pub fn validate(
    decoder: &mut dyn Decoder,
    plan: &FramePlan,
    sensor: &Sensor,
    x: &Array4<f32>,
    depth: Option<&Array4<f32>>,
    noise: Option<&NoiseParams>,
    seed: u64,
) -> Result<Vec<(String, f64)>> {
    let n = x.dim().0;
    let never = AtomicBool::new(false);
    let (mut total_mse, mut total_psnr) = (0.0, 0.0);
    let (mut truth, mut detected, mut se, mut ae) = (0usize, 0usize, 0.0, 0.0);
    let mut lifetimes = false;
    for i in 0..n {
        let xi = x.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1)); // [1, T, H, W]
        let y = measure_batch(plan, &xi, noise, derive_seed(seed ^ VALIDATION_STREAM, i as u64))?;
        let out = decoder.decode(y.view(), sensor, &Control::quiet(&never))?;
        if let (Some(est), Some(l)) = (&out.lifetime, depth) {
            // τ_m where the truth holds a fluorophore: error (ns) where estimated, coverage
            lifetimes = true;
            let (est, l) = (est.index_axis(Axis(0), 0), l.index_axis(Axis(0), i));
            for ((&e, &t), &sig) in
                est.index_axis(Axis(0), 0).iter().zip(l.index_axis(Axis(0), 0).iter()).zip(l.index_axis(Axis(0), 4).iter())
            {
                if sig > 0.5 && t.is_finite() {
                    truth += 1;
                    if e.is_finite() {
                        detected += 1;
                        ae += (e as f64 * 1e9 - t as f64).abs();
                    }
                }
            }
        } else if let (Some(est), Some(d)) = (&out.depth, depth) {
            for e in depth_errors(&est.index_axis(Axis(0), 0), &d.index_axis(Axis(0), i)) {
                truth += e.truth;
                detected += e.detected;
                if e.detected > 0 {
                    se += e.rmse_m * e.rmse_m * e.detected as f64;
                    ae += e.mae_m * e.detected as f64;
                }
            }
        } else if let Some(pred) = &out.cube {
            let (p, t) = (pred.as_slice().unwrap_or(&[]), xi.as_slice().unwrap_or(&[]));
            total_mse += mse(p, t);
            total_psnr += psnr(p, t);
        } else {
            return Err(TrainError::InvalidParam {
                field: "decoder",
                got: decoder.name().into(),
                expected: "a cube, or depth with range labels".into(),
            });
        }
    }
    let per = |v: f64, k: usize| if k > 0 { v / k as f64 } else { f64::NAN };
    Ok(if lifetimes {
        vec![("val_lifetime_mae_ns".into(), per(ae, detected)), ("val_coverage".into(), per(detected as f64, truth))]
    } else if depth.is_some() {
        vec![
            ("val_depth_rmse_m".into(), per(se, detected).sqrt()),
            ("val_depth_mae_m".into(), per(ae, detected)),
            ("val_detection".into(), per(detected as f64, truth)),
        ]
    } else {
        vec![("val_mse".into(), per(total_mse, n)), ("val_psnr_db".into(), per(total_psnr, n))]
    })
}

/// Train (or resume) a run in `run` on the CPU.
pub fn train(
    cfg: &TrainConfig,
    codes: &Codes,
    run: &Path,
    resume: bool,
    progress: &dyn Progress,
    cancel: &AtomicBool,
) -> Result<Vec<EpochMetrics>> {
    train_on(cfg, codes, run, resume, &Device::flex(), progress, cancel)
}

/// Train (or resume) a run in `run` on `device` (without autodiff: the loop adds it; see
/// `tcsense_models::device`). The run directory is the same on every device: a run started on
/// one resumes on another.
pub fn train_on(
    cfg: &TrainConfig,
    codes: &Codes,
    run: &Path,
    resume: bool,
    device: &Device,
    progress: &dyn Progress,
    cancel: &AtomicBool,
) -> Result<Vec<EpochMetrics>> {
    let device = &device.clone().without_autodiff();
    match &cfg.run.model {
        ModelConfig::AdmmNet(m) => train_with(cfg, codes, run, resume, device, progress, cancel, |device| m.init(device)),
        ModelConfig::Unet(m) => train_with(cfg, codes, run, resume, device, progress, cancel, |device| m.init(device)),
        ModelConfig::Lifetime(m) => train_with(cfg, codes, run, resume, device, progress, cancel, |device| m.init(device)),
    }
}

/// A fixed-codes run, or the three phases of deep sensing (see [`crate::deep_sensing`]).
#[allow(clippy::too_many_arguments)]
fn train_with<M: Network>(
    cfg: &TrainConfig,
    codes: &Codes,
    run: &Path,
    resume: bool,
    device: &Device,
    progress: &dyn Progress,
    cancel: &AtomicBool,
    init: impl Fn(&Device) -> M,
) -> Result<Vec<EpochMetrics>> {
    cfg.validate()?;
    let start = match &cfg.init_from {
        Some(dir) if !resume || latest_checkpoint(run)?.is_none() => {
            Some(tcsense_models::runs::load_network(Path::new(dir), init(&device.clone().autodiff()))?)
        }
        _ => None,
    };
    let Some(lc) = &cfg.learn_codes else {
        return Ok(fit(cfg, codes, run, resume, device, progress, cancel, &init, cfg.epochs, start, None)?.0);
    };
    lc.validate(cfg.epochs)?;
    let relaxed = run.join(crate::deep_sensing::RELAXED_DIR);
    // the codes the relaxed phase starts from, kept for its resumption
    let start_file = run.join(crate::deep_sensing::START_CODES_FILE);
    let codes = &if resume && start_file.exists() { Codes::load(&start_file)? } else { codes.clone() };
    let projection_file = relaxed.join(crate::deep_sensing::PROJECTION_FILE);
    let (net, projected) = if projection_file.exists() {
        if !resume {
            return Err(file_err(run, "a run already exists here; pass --resume to continue it or choose another directory"));
        }
        let net = tcsense_models::runs::load_network(&relaxed, init(&device.clone().autodiff()))?;
        (net, Codes::load(&relaxed.join("projected_codes.json"))?)
    } else {
        std::fs::create_dir_all(run).map_err(|e| file_err(run, e))?;
        let _lock = RunLock::acquire(run)?;
        if !start_file.exists() {
            codes.save(&start_file)?;
        }
        write_json(&run.join(CONFIG_FILE), cfg)?;
        let (_, net, learner) = fit(cfg, codes, &relaxed, resume, device, progress, cancel, &init, lc.relaxed_epochs, start, Some(lc))?;
        let learner = learner.expect("a relaxed run has a code learner");
        let p = crate::deep_sensing::project_and_record(&learner, codes, cfg, &relaxed)?;
        p.save(&run.join(CODES_FILE))?;
        (net, p)
    };
    Ok(fit(cfg, &projected, run, resume, device, progress, cancel, &init, cfg.epochs - lc.relaxed_epochs, Some(net), None)?.0)
}

/// A run's cubes and labels: the train and validation splits `[N, T, H, W]`, and the range
/// labels of the first `K` returns `[N, K, H, W]` (depth networks) or the lifetime labels
/// `[N, 5, H, W]` (lifetime networks).
struct Splits {
    train_x: Array4<f32>,
    val_x: Array4<f32>,
    train_labels: Option<Array4<f32>>,
    val_labels: Option<Array4<f32>>,
}

impl Splits {
    /// The splits `M` trains on, at most `cfg`'s item counts.
    fn load<M: Network>(cfg: &TrainConfig, ds: &Dataset) -> Result<Splits> {
        let (tn, vn) = (cfg.max_train_items, cfg.max_val_items);
        let (train_labels, val_labels) = match M::PREDICTION {
            Prediction::Cube => (None, None),
            Prediction::Depth => {
                let k = cfg.run.model.returns();
                (Some(load_depth(ds, "train", tn, k)?), Some(load_depth(ds, "val", vn, k)?))
            }
            Prediction::Lifetime => (Some(load_lifetime_labels(ds, "train", tn)?), Some(load_lifetime_labels(ds, "val", vn)?)),
        };
        let splits = Splits { train_x: load_cubes(ds, "train", tn)?, val_x: load_cubes(ds, "val", vn)?, train_labels, val_labels };
        if splits.train_x.dim().0 == 0 {
            return Err(file_err(&ds.dir, "the train split is empty"));
        }
        Ok(splits)
    }
}

/// The sensor of a run in every form its loop needs: the [`Sensor`], its frame plans for
/// validation (whole frames) and training (the augmentation's crop), and its tensors for the
/// training frames.
struct Sensing {
    sensor: Sensor,
    plan: FramePlan,
    train_plan: FramePlan,
    tensors: SensorTensors,
}

/// One batch as the network sees it: cubes `[B, T, H, W]` (after augmentation), labels, tap
/// images `[B, M, H, W]`, each item's loss scale (its peak) and what the sensor saw where
/// ambient light was added (for deep sensing's gradient).
struct Batch {
    x: Array4<f32>,
    labels: Option<Array4<f32>>,
    y: Array4<f32>,
    scales: Option<Vec<f32>>,
    lit: Option<Array4<f32>>,
}

/// The measurements of batch `x` (labels `labels`) at optimiser step `step`: through the
/// augmentation and its light ladder where the run has one, else the frames as they are.
fn measure_step<M: Network>(
    cfg: &TrainConfig,
    s: &Sensing,
    x: Array4<f32>,
    labels: Option<Array4<f32>>,
    step: u64,
    (bin_m, range_m): (f64, f64),
) -> Result<Batch> {
    let noise_seed = derive_seed(cfg.seed, step);
    let Some(aug) = &cfg.augment else {
        let y = measure_batch(&s.plan, &x.view(), cfg.noise.as_ref(), noise_seed)?;
        return Ok(Batch { x, labels, y, scales: None, lit: None });
    };
    let noise = &cfg.noise;
    let lifetimes = M::PREDICTION == Prediction::Lifetime;
    let depth = labels.as_ref().filter(|_| !lifetimes).map(|d| DepthLabels { depth: d.view(), bin_m, range_m });
    let maps = labels.as_ref().filter(|_| lifetimes).map(|d| d.view());
    let out = aug.apply(&x.view(), depth, maps, noise.as_ref().unwrap_or(&crate::config::TRAINING_NOISE), s.sensor.block(), cfg.seed, step);
    let mut y = measure_items(&s.train_plan, &out.x, noise.as_ref().map(|_| out.noise.as_slice()), &out.ambient, noise_seed)?;
    aug.perturb(&mut y, cfg.seed, step);
    // each item's loss on its own scale: its peak, brightness included
    let peaks: Vec<f32> = out.x.outer_iter().map(|xi| xi.iter().fold(0f32, |m, v| m.max(v.abs())).max(1e-12)).collect();
    // what the sensor saw (ambient light included), for deep sensing's gradient
    let lit = out.ambient.iter().any(|&b| b > 0.0).then(|| {
        let mut l = out.x.clone();
        l.outer_iter_mut().zip(&out.ambient).for_each(|(mut li, &b)| li += b);
        l
    });
    Ok(Batch { x: out.x, labels: out.depth.or(out.maps), y, scales: Some(peaks), lit })
}

/// The network, optimiser, state and metrics a run continues from: its latest checkpoint
/// when resuming (checked against the config and the dataset's digest), else `start` or a
/// seeded initialisation.
#[allow(clippy::type_complexity)]
fn start_or_resume<M: Network>(
    cfg: &TrainConfig,
    run: &Path,
    resume: bool,
    manifest: (&Path, &str),
    learner: Option<&mut Learner>,
    init: &impl Fn(&Device) -> M,
    start: Option<M>,
    device: &Device,
) -> Result<(M, ModuleOptimizer, RunState, Vec<EpochMetrics>)> {
    let (manifest, ds_digest) = manifest;
    let fresh = |start: Option<M>| {
        (
            start.unwrap_or_else(|| seeded_init(device, cfg.seed, init)),
            AdamConfig::new().init(),
            RunState { dataset: Some(ds_digest.to_string()), ..RunState::default() },
            Vec::new(),
        )
    };
    if !resume {
        if run.join(crate::run_dir::CHECKPOINT_DIR).exists() {
            return Err(file_err(run, "a run already exists here; pass --resume to continue it or choose another directory"));
        }
        return Ok(fresh(start));
    }
    let saved = TrainConfig::load(&run.join(CONFIG_FILE))?;
    if saved.run.model != cfg.run.model || saved.seed != cfg.seed || saved.batch_size != cfg.batch_size {
        return Err(file_err(
            &run.join(CONFIG_FILE),
            "the run was started with a different model, seed or batch size; resume with the saved config",
        ));
    }
    // killed before its first checkpoint: start over, as the run would have
    let Some(ckpt) = latest_checkpoint(run)? else { return Ok(fresh(start)) };
    let (model, optim, mut state) = load_checkpoint(&ckpt, init(device), AdamConfig::new().init())?;
    if let Some(then) = state.dataset.as_ref().filter(|d| **d != ds_digest) {
        return Err(file_err(
            manifest,
            format!("the dataset changed since the run started (its manifest's digest {then} then, {ds_digest} now); resume on the data the run started on, or start a new run (or fine-tune with --init-from) on this one"),
        ));
    }
    if let Some(l) = learner {
        l.load(&ckpt)?;
    }
    let rows = read_rows(&run.join(METRICS_FILE), state.epoch)?;
    // the clock is in timing.csv (state.json has it only from before that file)
    if let Some(last) = rows.last().filter(|r| r.epoch == state.epoch && r.seconds > 0.0) {
        state.seconds = last.seconds;
    }
    Ok((model, optim, state, rows))
}

/// The loop for one network type; `init` builds the untrained network on a device, `start`
/// (if given) replaces it when the run starts, and `learn` trains codes with it.
#[allow(clippy::too_many_arguments)]
fn fit<M: Network>(
    cfg: &TrainConfig,
    codes: &Codes,
    run: &Path,
    resume: bool,
    on: &Device,
    progress: &dyn Progress,
    cancel: &AtomicBool,
    init: &impl Fn(&Device) -> M,
    epochs: usize,
    start: Option<M>,
    learn: Option<&LearnCodes>,
) -> Result<(Vec<EpochMetrics>, M, Option<Learner>)> {
    cfg.validate()?;
    codes.ensure_feasible()?;
    let ds = Dataset::open(Path::new(&cfg.dataset))?;
    // what the run trains on, recorded in its checkpoints and checked when it resumes
    let manifest = ds.dir.join("manifest.json");
    let ds_digest = tcsense_sensor::digest::digest(std::fs::read(&manifest).map_err(|e| file_err(&manifest, e))?);
    let sensor = cfg.run.sensor(run, codes.clone())?;
    let model_cfg = &cfg.run.model;
    if sensor.bins() != ds.manifest.bins || sensor.taps() != model_cfg.taps() || sensor.bins() != model_cfg.bins() {
        return Err(TrainError::InvalidParam {
            field: "model/codes",
            got: format!("T = {}, M = {} (model T = {}, M = {})", sensor.bins(), sensor.taps(), model_cfg.bins(), model_cfg.taps()),
            expected: format!("the dataset's T = {} and the codes' M", ds.manifest.bins),
        });
    }
    // a product objective must be the dataset's: ranges of LiDAR, lifetimes of FLIm
    let (own, kind, lacks) = match ds.manifest.kind {
        tcsense_datasets::store::Kind::Flim => (crate::Objective::Lifetime, "FLIm", "ranges"),
        _ => (crate::Objective::Range, "LiDAR", "lifetimes"),
    };
    if let Some(o) = cfg.objective.filter(|&o| o != crate::Objective::Mse && o != own) {
        let msg = format!(
            "objective {}: a {kind} dataset has no {lacks} (its product is the {}: --objective {})",
            o.name(),
            own.name(),
            own.name()
        );
        return Err(file_err(&manifest, msg));
    }
    let data = Splits::load::<M>(cfg, &ds)?;
    let (bin_m, range_m) = (C * sensor.bin_width_s() / 2.0, C * sensor.bin_width_s() * sensor.bins() as f64 / 2.0);
    let (_, _, h, w) = data.train_x.dim();
    // the frame the network trains on: the crop of the augmentation, else the whole frame
    let (th, tw) = match &cfg.augment {
        Some(aug) => {
            aug.validate(h, w, sensor.block())?;
            aug.frame(h, w)
        }
        None => (h, w),
    };
    let infer_device = on.clone();
    let device = on.clone().autodiff();
    let mut sensing = Sensing {
        plan: sensor.plan(h, w)?,
        train_plan: sensor.plan(th, tw)?,
        tensors: SensorTensors::new(sensor.matrix(), th, tw, &device)?,
        sensor,
    };
    let mut learner = learn.map(|lc| Learner::new(lc, codes, &cfg.run, &device)).transpose()?;

    std::fs::create_dir_all(run).map_err(|e| file_err(run, e))?;
    let _lock = RunLock::acquire(run)?;
    let (mut model, mut optim, mut state, mut rows) =
        start_or_resume(cfg, run, resume, (&manifest, &ds_digest), learner.as_mut(), init, start, &device)?;
    write_json(&run.join(CONFIG_FILE), cfg)?;
    let mut codes_log = match &learner {
        Some(l) => {
            sensing = sensing_for(cfg, &l.hard, (h, w), (th, tw), &device)?;
            l.hard.save(&run.join(CODES_FILE))?;
            crate::deep_sensing::read_log(&run.join(crate::deep_sensing::CODES_LOG), state.epoch)
        }
        None => {
            codes.save(&run.join(CODES_FILE))?;
            Vec::new()
        }
    };

    let n = data.train_x.dim().0;
    let steps_per_epoch = n.div_ceil(cfg.batch_size);
    let mut out = Vec::new();
    let total_steps = (epochs * steps_per_epoch).max(1) as f64;
    for epoch in state.epoch..epochs {
        let t0 = Instant::now();
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut StdRng::seed_from_u64(derive_seed(cfg.seed, epoch as u64)));
        let mut loss_sum = 0.0;
        for (bi, idx) in order.chunks(cfg.batch_size).enumerate() {
            if cancel.load(Ordering::Relaxed) {
                return Err(TrainError::Cancelled);
            }
            state.step += 1;
            // the schedule spans this phase's steps (each phase of deep sensing has its own)
            let lr = cfg.lr_schedule.rate(cfg.learning_rate, (epoch * steps_per_epoch + bi + 1) as u64, total_steps as u64);
            if let Some(l) = learner.as_mut() {
                l.schedule(state.step as f64 / total_steps);
                if l.refresh()? {
                    sensing = sensing_for(cfg, &l.hard, (h, w), (th, tw), &device)?;
                }
            }
            let xb = data.train_x.select(Axis(0), idx); // [B, T, H, W]
            let lb = data.train_labels.as_ref().map(|d| d.select(Axis(0), idx)); // [B, K, H, W] or [B, 5, H, W]
            let batch = measure_step::<M>(cfg, &sensing, xb, lb, state.step, (bin_m, range_m))?;
            let target = match (&batch.labels, M::PREDICTION) {
                (Some(l), Prediction::Lifetime) => {
                    Target::Lifetime { labels: l, grid: cfg.run.model.lifetime_grid(), terms: cfg.lifetime_terms() }
                }
                (Some(d), _) => Target::Depth { depth: d, range_m, grid: cfg.run.model.range_grid(), cap: cfg.grid_nll_cap },
                (None, _) => Target::Cube {
                    x: &batch.x,
                    scales: batch.scales.as_deref(),
                    emd: matches!(cfg.objective, Some(crate::Objective::Range | crate::Objective::Lifetime)),
                },
            };
            let l;
            (model, l) = match learner.as_mut() {
                Some(learner) => {
                    let seen = batch.lit.as_ref().unwrap_or(&batch.x);
                    step_learned(model, &mut optim, learner, cfg, lr, &sensing.tensors, seen, &batch.y, target, &device)
                }
                None => step(model, &mut optim, cfg, lr, &sensing.tensors, &batch.y, target, &device),
            };
            if !l.is_finite() {
                // the step already moved the weights: stop before a NaN checkpoint is written
                return Err(TrainError::Diverged { loss: l, epoch: epoch + 1, step: state.step, kept: true });
            }
            loss_sum += l;
            progress.step(epoch, bi + 1, steps_per_epoch, l);
        }
        // a step's loss is taken before it moves the weights: the epoch's last step can leave
        // them infinite with every loss finite (a learning rate far too high)
        if !weights_finite(&model) {
            return Err(TrainError::Diverged { loss: f64::NAN, epoch: epoch + 1, step: state.step, kept: true });
        }
        let mut valid = NetDecoder::new(model_cfg.name(), model.valid().to_device(&infer_device), infer_device.clone());
        let val =
            validate(&mut valid, &sensing.plan, &sensing.sensor, &data.val_x, data.val_labels.as_ref(), cfg.noise.as_ref(), cfg.seed)?;
        state.epoch = epoch + 1;
        state.seconds += t0.elapsed().as_secs_f64();
        let m =
            EpochMetrics { epoch: epoch + 1, step: state.step, train_loss: loss_sum / steps_per_epoch as f64, val, seconds: state.seconds };
        rows.push(m.clone());
        // the epoch's row first: a kill before the checkpoint lands leaves a row past the
        // checkpoint, which a resume drops and logs again (the other order would lose it)
        write_rows(&run.join(METRICS_FILE), &rows)?;
        match &learner {
            Some(l) => {
                codes_log.push(crate::deep_sensing::log_line(epoch + 1, state.step, l));
                crate::deep_sensing::write_log(&run.join(crate::deep_sensing::CODES_LOG), &codes_log)?;
                save_checkpoint(run, &model, &optim, &state, &|dir| l.save(dir))?;
                l.hard.save(&run.join(CODES_FILE))?;
            }
            None => save_checkpoint(run, &model, &optim, &state, &|_| Ok(()))?,
        }
        progress.epoch(&m);
        out.push(m);
    }
    Ok((out, model, learner))
}

/// Whether every float parameter of `model` is finite.
fn weights_finite<M: Module>(model: &M) -> bool {
    struct Finite(bool);
    impl ModuleVisitor for Finite {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            if self.0 {
                let s: f32 = param.val().abs().sum().into_scalar::<f32>();
                self.0 = s.is_finite();
            }
        }
    }
    let mut v = Finite(true);
    model.visit(&mut v);
    v.0
}

/// The sensor of `codes` for validation (whole frames `hw`) and training (frames `thw`).
fn sensing_for(cfg: &TrainConfig, codes: &Codes, hw: (usize, usize), thw: (usize, usize), device: &Device) -> Result<Sensing> {
    let sensor = Sensor::ideal(codes.clone(), cfg.run.sampling, cfg.run.irf)?;
    Ok(Sensing {
        plan: sensor.plan(hw.0, hw.1)?,
        train_plan: sensor.plan(thw.0, thw.1)?,
        tensors: SensorTensors::new(sensor.matrix(), thw.0, thw.1, device)?,
        sensor,
    })
}

/// One Adam step of the network and the code logits on a batch whose measurements carry the
/// codes' gradient; returns the updated network and the batch loss.
///
/// # Shapes
/// - `x`: `[B, T, H, W]` (what was measured), `y`: `[B, M, H, W]`
#[allow(clippy::too_many_arguments)]
fn step_learned<M: Network>(
    model: M,
    optim: &mut ModuleOptimizer,
    learner: &mut Learner,
    cfg: &TrainConfig,
    lr: f64,
    sensor: &SensorTensors,
    x: &Array4<f32>,
    y: &Array4<f32>,
    target: Target<'_>,
    device: &Device,
) -> (M, f64) {
    let (yt, a, penalty) = learner.measurements(x, y, device);
    let pred = model.train_output(yt, &sensor.clone().with_matrix(a));
    let loss = objective(cfg.loss, pred, target, device) + penalty;
    let l: f32 = loss.clone().into_scalar();
    let mut grads = loss.backward();
    let net_grads = GradientsParams::from_module(&mut grads, &model);
    let code_grads = GradientsParams::from_module(&mut grads, &learner.logits);
    learner.step(code_grads);
    (optim.step(lr, model, net_grads), l as f64)
}

/// The device's random generator is global: seeding it and drawing the initial weights happen
/// under one lock, so runs started in parallel (tests, tools) still get their seed's weights.
static SEEDED_INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Initial weights drawn from the device generator seeded with `seed`: the same config gives
/// the same run. burn initialises parameters lazily, on first use, so every parameter is
/// touched before the lock is released.
pub(crate) fn seeded_init<M: Module>(device: &Device, seed: u64, init: impl Fn(&Device) -> M) -> M {
    struct Touch;
    impl ModuleVisitor for Touch {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            drop(param.val());
        }
    }
    /// Parameter ids numbered in visiting order: burn draws them at random, and they are
    /// stored in the weights and optimiser files, so same seed, same bytes needs them fixed.
    struct Renumber(u64);
    impl ModuleMapper for Renumber {
        fn map_float<const D: usize>(&mut self, mut param: Param<Tensor<D>>) -> Param<Tensor<D>> {
            self.0 += 1;
            param.id = ParamId::from(self.0);
            param
        }
    }
    let _guard = SEEDED_INIT.lock().unwrap_or_else(|e| e.into_inner());
    // drawn on the CPU whatever the device, so a seed gives the same weights on every device
    let host = if device.is_autodiff() { Device::flex().autodiff() } else { Device::flex() };
    host.seed(seed);
    let model = init(&host);
    model.visit(&mut Touch);
    let model = model.map(&mut Renumber(0));
    // `fork` keeps the parameters leaves of the autodiff graph (`to_device` would not)
    if host == *device {
        model
    } else {
        model.fork(device)
    }
}

/// Measure each item of `x` with its own noise model (`None`: noise-free), item `i`'s noise
/// seeded by `(seed, i)`, under its ambient light `ambient[i]` (a constant added to every
/// bin; the exposure stays the one that brings the unlit item's brightest tap to its
/// `signal_fraction`, as `tcsense eval --sbr` measures).
///
/// # Shapes
/// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
fn measure_items(plan: &FramePlan, x: &Array4<f32>, noise: Option<&[NoiseParams]>, ambient: &[f32], seed: u64) -> Result<Array4<f32>> {
    let mut y = Array4::zeros((x.dim().0, plan.taps(), plan.height(), plan.width()));
    for (i, mut yi) in y.outer_iter_mut().enumerate() {
        let xi = x.slice_axis(Axis(0), ndarray::Slice::from(i..i + 1));
        let item_seed = derive_seed(seed, i as u64);
        let item = match (noise, ambient.get(i).copied().filter(|&b| b > 0.0)) {
            (Some(n), Some(b)) => {
                measure_batch_at(plan, &xi.mapv(|v| v + b).view(), Some(&n[i]), signal_exposure(plan, &xi, &n[i])?, item_seed)?
            }
            (n, Some(b)) => measure_batch(plan, &xi.mapv(|v| v + b).view(), n.map(|n| &n[i]), item_seed)?,
            (n, None) => measure_batch(plan, &xi, n.map(|n| &n[i]), item_seed)?,
        };
        yi.assign(&item.index_axis(Axis(0), 0));
    }
    Ok(y)
}

/// What a batch is trained against.
#[derive(Debug, Clone, Copy)]
pub(crate) enum Target<'a> {
    /// The cubes `[B, T, H, W]`, and a scale per item when augmented (the loss is taken on
    /// `x/s` and `x̂/s`, so dim items weigh as much as bright ones); `emd`: the waveforms'
    /// earth mover's distance is added ([`crate::Objective::Range`], `Lifetime`).
    Cube { x: &'a Array4<f32>, scales: Option<&'a [f32]>, emd: bool },
    /// Range labels `[B, K, H, W]` (m, NaN where none), the unambiguous range and the
    /// network's grid of candidate ranges where it has one (`u = r·scale − offset`, cyclic).
    Depth { depth: &'a Array4<f32>, range_m: f64, grid: Option<(f64, f64)>, cap: Option<f64> },
    /// Lifetime labels `[B, 5, H, W]` ([`crate::data::load_lifetime_labels`]) and the
    /// network's lifetime grid where it has one (`ln τ₀` in ns, step).
    /// `terms`: how the loss is taken (the run's config).
    Lifetime { labels: &'a Array4<f32>, grid: Option<(f64, f64)>, terms: crate::loss::LifetimeTerms },
}

/// The loss of a prediction against its target.
///
/// # Shapes
/// - `pred`: `[B, T, H, W]` or `[B, 2K, H, W]` → `[1]`
pub(crate) fn objective(loss: Loss, pred: Tensor<4>, target: Target<'_>, device: &Device) -> Tensor<1> {
    match target {
        Target::Cube { x, scales, emd } => {
            let truth = to_tensor(&x.view(), device);
            // the product's term on the cube as predicted (its scale does not enter)
            let emd = emd.then(|| crate::loss::waveform_emd(pred.clone(), truth.clone()).mul_scalar(crate::loss::EMD_WEIGHT));
            let cube = match scales {
                None => loss_fn(loss, pred, truth),
                Some(s) => {
                    let inv = Tensor::<4>::from_data(
                        TensorData::new(s.iter().map(|s| 1.0 / s).collect::<Vec<f32>>(), [s.len(), 1, 1, 1]),
                        device,
                    );
                    loss_fn(loss, pred * inv.clone(), truth * inv)
                }
            };
            match emd {
                Some(e) => cube + e,
                None => cube,
            }
        }
        Target::Depth { depth, range_m, grid, cap } => {
            let mask = depth.mapv(|d| if d.is_finite() { 1.0 } else { 0.0 });
            let filled = depth.mapv(|d| if d.is_finite() { d } else { 0.0 });
            let (depth, mask) = (to_tensor(&filled.view(), device), to_tensor(&mask.view(), device));
            match grid {
                // (the grid's offset is half a bin: the tolerance of "within half a bin")
                Some(grid) => depth_grid_loss(pred, depth, mask, grid, grid.1, cap),
                None => depth_loss(pred, depth, mask, range_m),
            }
        }
        Target::Lifetime { labels, grid, terms } => {
            let filled = labels.mapv(|v| if v.is_finite() { v } else { 0.0 });
            let distinct = ndarray::Zip::from(labels.index_axis(Axis(1), 1))
                .and(labels.index_axis(Axis(1), 2))
                .map_collect(|a, b| if (a - b).abs() > 1e-3 { 1f32 } else { 0.0 })
                .insert_axis(Axis(1));
            lifetime_loss(pred, to_tensor(&filled.view(), device), to_tensor(&distinct.view(), device), grid, terms)
        }
    }
}

/// One Adam step on a batch; returns the updated network and the batch loss.
///
/// # Shapes
/// - `y`: `[B, M, H, W]`; the target as in [`Target`]
#[allow(clippy::too_many_arguments)]
pub(crate) fn step<M: Network>(
    model: M,
    optim: &mut ModuleOptimizer,
    cfg: &TrainConfig,
    lr: f64,
    sensor: &SensorTensors,
    y: &Array4<f32>,
    target: Target<'_>,
    device: &Device,
) -> (M, f64) {
    let pred = model.train_output(to_tensor(&y.view(), device), sensor);
    let loss = objective(cfg.loss, pred, target, device);
    let l: f32 = loss.clone().into_scalar();
    let grads = GradientsParams::from_grads(loss.backward(), &model);
    (optim.step(lr, model, grads), l as f64)
}

/// Read `state.json` of a run's checkpoint (for tests and tools).
pub fn run_state(run: &Path) -> Result<RunState> {
    let ckpt = latest_checkpoint(run)?
        .ok_or_else(|| file_err(&run.join(crate::run_dir::CHECKPOINT_DIR).join(crate::run_dir::STATE_FILE), "no checkpoint yet"))?;
    read_json(&ckpt.join(crate::run_dir::STATE_FILE))
}
