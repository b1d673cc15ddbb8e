//! `tcsense-train`: training of the learned decoders with burn (the only crate with autodiff).
//!
//! ADMM-Net is trained with Adam (lr 1e-3), batch 2, loss RMSE + MAE (LiDAR) or RMSE (FLIm)
//! (paper Table 3). Measurements are simulated on the fly with the sensor model and fresh
//! shot and read noise at every step (full well 20 000 e⁻, σ = 40 e⁻), seeded by
//! `(seed, step)`; batches are drawn in an order seeded by `(seed, epoch)`. So a run is a pure
//! function of its config, and a resumed run continues exactly where the checkpoint was taken.
//!
//! A run directory holds `config.json`, `codes.json`, `metrics.csv` (one row per epoch),
//! `checkpoint/` (`model.bpk`, `optim.bpk`, `state.json`, replaced atomically after every
//! epoch) and `model.bpk` (the latest weights).

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor, TensorData};
use ndarray::{Array4, Axis, Ix4};
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::SeedableRng;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;
use tcsense_datasets::Dataset;
use tcsense_models::{AdmmNet, AdmmNetConfig, SensorTensors};
use tcsense_sensor::noise::{add_noise, derive_seed, Exposure};
use tcsense_sensor::npy::write_bytes;
use tcsense_sensor::{Codes, FramePlan, Irf, MeasurementMatrix, NoiseParams, Sampling, SensorParams};

/// Errors of the training crate.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error(transparent)]
    Sensor(#[from] tcsense_sensor::SensorError),
    #[error(transparent)]
    Dataset(#[from] tcsense_datasets::DatasetError),
    #[error("{}: {msg}", path.display())]
    File { path: PathBuf, msg: String },
    #[error("invalid {field}: got {got}, expected {expected}")]
    InvalidParam { field: &'static str, got: String, expected: String },
    #[error("interrupted; the last checkpoint is kept, continue with --resume")]
    Cancelled,
}

/// Result alias of the training crate.
pub type Result<T> = std::result::Result<T, TrainError>;

fn file_err(path: &Path, msg: impl ToString) -> TrainError {
    TrainError::File { path: path.to_path_buf(), msg: msg.to_string() }
}

/// Training loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Loss {
    /// `sqrt(mean((x̂ − x)²))` (FLIm).
    Rmse,
    /// RMSE + `mean(|x̂ − x|)` (LiDAR).
    RmseMae,
}

/// Everything that defines a run (saved as `config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    pub model: AdmmNetConfig,
    pub epochs: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    pub loss: Loss,
    pub seed: u64,
    /// Noise added to the simulated measurements (`None`: noise-free).
    pub noise: Option<NoiseParams>,
    pub sampling: Sampling,
    pub irf: Irf,
    /// Dataset directory the run was trained on.
    pub dataset: String,
    /// Use at most this many training / validation items.
    pub max_train_items: Option<usize>,
    pub max_val_items: Option<usize>,
}

impl TrainConfig {
    /// Defaults of the paper's Table 3 for a model config.
    pub fn new(model: AdmmNetConfig, dataset: &Path, loss: Loss, sampling: Sampling) -> Self {
        TrainConfig {
            model,
            epochs: 10,
            batch_size: 2,
            learning_rate: 1e-3,
            loss,
            seed: 0,
            noise: Some(NoiseParams { full_well_e: 20_000.0, read_noise_e: 40.0, signal_fraction: 0.8, adc_bits: 0 }),
            sampling,
            irf: Irf::Ideal,
            dataset: dataset.display().to_string(),
            max_train_items: None,
            max_val_items: None,
        }
    }

    fn validate(&self) -> Result<()> {
        let bad = |field: &'static str, got: String, expected: &str| Err(TrainError::InvalidParam { field, got, expected: expected.into() });
        if self.epochs == 0 {
            return bad("epochs", "0".into(), "at least 1");
        }
        if self.batch_size == 0 {
            return bad("batch_size", "0".into(), "at least 1");
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad("learning_rate", self.learning_rate.to_string(), "a positive number");
        }
        if self.model.stages == 0 || self.model.channels == 0 {
            return bad("model", format!("{} stages, {} channels", self.model.stages, self.model.channels), "at least one stage and one channel");
        }
        if let Some(n) = &self.noise {
            n.validate()?;
        }
        Ok(())
    }
}

/// Progress of a run after a checkpoint.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunState {
    /// Epochs completed.
    pub epoch: usize,
    /// Optimiser steps taken.
    pub step: u64,
    /// Seconds of training so far.
    pub seconds: f64,
}

/// One row of `metrics.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochMetrics {
    pub epoch: usize,
    pub step: u64,
    pub train_loss: f64,
    pub val_mse: f64,
    pub val_psnr: f64,
    pub seconds: f64,
}

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

/// Convert an ndarray batch to a tensor.
pub fn to_tensor(a: &Array4<f32>, device: &Device) -> Tensor<4> {
    let shape = a.dim();
    let data: Vec<f32> = a.iter().copied().collect();
    Tensor::from_data(TensorData::new(data, [shape.0, shape.1, shape.2, shape.3]), device)
}

/// Convert a tensor back to ndarray.
pub fn to_array(t: Tensor<4>) -> Result<Array4<f32>> {
    let [b, c, h, w] = t.dims();
    let v: Vec<f32> = t.into_data().try_into_vec::<f32>().map_err(|e| TrainError::InvalidParam { field: "tensor", got: format!("{e:?}"), expected: "f32 data".into() })?;
    Array4::from_shape_vec((b, c, h, w), v).map_err(|e| TrainError::InvalidParam { field: "tensor", got: e.to_string(), expected: "a [B, C, H, W] tensor".into() })
}

/// Simulate measurements of a batch: `y = A x` plus (optionally) noise seeded by `seed`,
/// returned in the units of `A x`.
///
/// # Shapes
/// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
pub fn simulate(plan: &FramePlan, x: &Array4<f32>, noise: Option<&NoiseParams>, seed: u64) -> Result<Array4<f32>> {
    let y = plan.forward_batch(&x.view())?;
    match noise {
        None => Ok(y),
        Some(n) => {
            let noisy = add_noise(&y.view().into_dyn(), n, Exposure::Auto, seed)?;
            noisy
                .in_input_units()
                .into_dimensionality::<Ix4>()
                .map_err(|e| TrainError::InvalidParam { field: "measurements", got: e.to_string(), expected: "[B, M, H, W]".into() })
        }
    }
}

/// The loss of a batch.
///
/// # Shapes
/// - `pred`, `truth`: `[B, T, H, W]` → `[1]`
pub fn loss_fn(loss: Loss, pred: Tensor<4>, truth: Tensor<4>) -> Tensor<1> {
    let d = pred - truth;
    let rmse = d.clone().powi_scalar(2).mean().sqrt();
    match loss {
        Loss::Rmse => rmse,
        Loss::RmseMae => rmse + d.abs().mean(),
    }
}

/// Mean MSE and PSNR of `model` over cubes `x` `[N, T, H, W]` with measurements simulated
/// with noise seeded per item (the same every epoch).
pub fn validate(model: &AdmmNet, sensor: &SensorTensors, plan: &FramePlan, x: &Array4<f32>, noise: Option<&NoiseParams>, seed: u64, device: &Device) -> Result<(f64, f64)> {
    let n = x.dim().0;
    if n == 0 {
        return Ok((f64::NAN, f64::NAN));
    }
    let (mut mse, mut psnr) = (0.0, 0.0);
    for i in 0..n {
        let xi = x.index_axis(Axis(0), i).insert_axis(Axis(0)).to_owned();
        let y = simulate(plan, &xi, noise, derive_seed(seed ^ 0x5641_4C49_4441_5445, i as u64))?;
        let pred = to_array(model.forward(to_tensor(&y, device), sensor))?;
        let m = pred.iter().zip(xi.iter()).map(|(a, b)| ((a - b) as f64).powi(2)).sum::<f64>() / xi.len() as f64;
        let peak = xi.iter().fold(0f32, |a, &v| a.max(v)) as f64;
        mse += m;
        psnr += if m > 0.0 { 10.0 * (peak * peak / m).log10() } else { f64::INFINITY };
    }
    Ok((mse / n as f64, psnr / n as f64))
}

/// Load the cubes of a split, `[N, T, H, W]`, at most `max` of them.
pub fn load_cubes(ds: &Dataset, split: &str, max: Option<usize>) -> Result<Array4<f32>> {
    let x = ds.load(split, "x")?;
    let x = x.into_dimensionality::<Ix4>().map_err(|e| file_err(&ds.dir, format!("field x of split {split}: {e}")))?;
    let n = max.unwrap_or(x.dim().0).min(x.dim().0);
    Ok(x.slice_axis(Axis(0), ndarray::Slice::from(0..n)).to_owned())
}

/// Build the measurement matrix of a run.
pub fn matrix(codes: &Codes, cfg: &TrainConfig) -> Result<MeasurementMatrix> {
    let spec = SensorParams { sampling: cfg.sampling, irf: cfg.irf, ..SensorParams::from_codes(codes) }.validate()?;
    Ok(MeasurementMatrix::synthesize(codes, &spec)?)
}

fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<()> {
    let s = serde_json::to_string_pretty(v).map_err(|e| file_err(path, e))? + "\n";
    Ok(write_bytes(path, s.as_bytes())?)
}

fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_err(path, format!("malformed JSON: {e}")))
}

const CSV_HEADER: &str = "epoch,step,train_loss,val_mse,val_psnr_db,seconds\n";

/// Load a trained run: config, codes and the latest weights (on `device`).
pub fn load_run(run: &Path, device: &Device) -> Result<(TrainConfig, Codes, AdmmNet)> {
    let cfg: TrainConfig = read_json(&run.join("config.json"))?;
    let codes = Codes::load(&run.join("codes.json"))?;
    let weights = run.join("model.bpk");
    if !weights.exists() {
        return Err(file_err(&weights, "no trained weights; train at least one epoch"));
    }
    let model = cfg.model.init(device).try_load_file(run.join("model")).map_err(|e| file_err(&weights, e))?;
    Ok((cfg, codes, model))
}

/// Train (or resume) a run in `run`.
pub fn train(cfg: &TrainConfig, codes: &Codes, run: &Path, resume: bool, progress: &dyn Progress, cancel: &AtomicBool) -> Result<Vec<EpochMetrics>> {
    cfg.validate()?;
    codes.ensure_feasible()?;
    let ds = Dataset::open(Path::new(&cfg.dataset))?;
    let a = matrix(codes, cfg)?;
    if a.bins() != ds.manifest.bins || a.taps() != cfg.model.taps || a.bins() != cfg.model.bins {
        return Err(TrainError::InvalidParam {
            field: "model/codes",
            got: format!("T = {}, M = {} (model T = {}, M = {})", a.bins(), a.taps(), cfg.model.bins, cfg.model.taps),
            expected: format!("the dataset's T = {} and the codes' M", ds.manifest.bins),
        });
    }
    let train_x = load_cubes(&ds, "train", cfg.max_train_items)?;
    let val_x = load_cubes(&ds, "val", cfg.max_val_items)?;
    if train_x.dim().0 == 0 {
        return Err(file_err(&ds.dir, "the train split is empty"));
    }
    let (_, _, h, w) = train_x.dim();
    let plan = a.plan(h, w)?;
    let device = Device::flex().autodiff();
    let infer_device = Device::flex();
    let sensor = SensorTensors::new(&a, h, w, &device)?;
    let sensor_val = SensorTensors::new(&a, h, w, &infer_device)?;

    std::fs::create_dir_all(run).map_err(|e| file_err(run, e))?;
    let ckpt = run.join("checkpoint");
    let (mut model, mut optim, mut state, mut rows) = if resume {
        let dir = if ckpt.join("state.json").exists() { ckpt.clone() } else { run.join("checkpoint.old") };
        let saved: TrainConfig = read_json(&run.join("config.json"))?;
        if saved.model != cfg.model || saved.seed != cfg.seed || saved.batch_size != cfg.batch_size {
            return Err(file_err(&run.join("config.json"), "the run was started with a different model, seed or batch size; resume with the saved config"));
        }
        let state: RunState = read_json(&dir.join("state.json"))?;
        let model = cfg.model.init(&device).try_load_file(dir.join("model")).map_err(|e| file_err(&dir.join("model.bpk"), e))?;
        let optim = AdamConfig::new().init().load(dir.join("optim")).map_err(|e| file_err(&dir.join("optim.bpk"), e))?;
        let rows = read_rows(&run.join("metrics.csv"), state.epoch)?;
        (model, optim, state, rows)
    } else {
        if ckpt.exists() {
            return Err(file_err(run, "a run already exists here; pass --resume to continue it or choose another directory"));
        }
        // seeded initial weights: the same config gives the same run
        device.seed(cfg.seed);
        (cfg.model.init(&device), AdamConfig::new().init(), RunState::default(), Vec::new())
    };
    write_json(&run.join("config.json"), cfg)?;
    codes.save(&run.join("codes.json"))?;

    let n = train_x.dim().0;
    let steps_per_epoch = n.div_ceil(cfg.batch_size);
    let mut out = Vec::new();
    for epoch in state.epoch..cfg.epochs {
        let t0 = Instant::now();
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut StdRng::seed_from_u64(derive_seed(cfg.seed, epoch as u64)));
        let mut loss_sum = 0.0;
        for (bi, idx) in order.chunks(cfg.batch_size).enumerate() {
            if cancel.load(Ordering::Relaxed) {
                return Err(TrainError::Cancelled);
            }
            let views: Vec<_> = idx.iter().map(|&i| train_x.index_axis(Axis(0), i)).collect();
            let xb = ndarray::stack(Axis(0), &views).map_err(|e| TrainError::InvalidParam { field: "batch", got: e.to_string(), expected: "equal item shapes".into() })?;
            state.step += 1;
            let yb = simulate(&plan, &xb, cfg.noise.as_ref(), derive_seed(cfg.seed, state.step))?;
            let pred = model.forward(to_tensor(&yb, &device), &sensor);
            let loss = loss_fn(cfg.loss, pred, to_tensor(&xb, &device));
            let l: f32 = loss.clone().into_scalar();
            let grads = GradientsParams::from_grads(loss.backward(), &model);
            model = optim.step(cfg.learning_rate, model, grads);
            loss_sum += l as f64;
            progress.step(epoch, bi + 1, steps_per_epoch, l as f64);
        }
        let valid = model.valid().to_device(&infer_device);
        let (val_mse, val_psnr) = validate(&valid, &sensor_val, &plan, &val_x, cfg.noise.as_ref(), cfg.seed, &infer_device)?;
        state.epoch = epoch + 1;
        state.seconds += t0.elapsed().as_secs_f64();
        let m = EpochMetrics { epoch: epoch + 1, step: state.step, train_loss: loss_sum / steps_per_epoch as f64, val_mse, val_psnr, seconds: state.seconds };
        rows.push(m.clone());
        save_checkpoint(run, &model, &optim, &state)?;
        write_rows(&run.join("metrics.csv"), &rows)?;
        progress.epoch(&m);
        out.push(m);
    }
    Ok(out)
}

fn save_checkpoint(run: &Path, model: &AdmmNet, optim: &burn::optim::ModuleOptimizer, state: &RunState) -> Result<()> {
    let tmp = run.join("checkpoint.tmp");
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| file_err(&tmp, e))?;
    model.clone().save_file(tmp.join("model")).map_err(|e| file_err(&tmp.join("model.bpk"), e))?;
    optim.save(tmp.join("optim")).map_err(|e| file_err(&tmp.join("optim.bpk"), e))?;
    write_json(&tmp.join("state.json"), state)?;
    let (ckpt, old) = (run.join("checkpoint"), run.join("checkpoint.old"));
    let _ = std::fs::remove_dir_all(&old);
    if ckpt.exists() {
        std::fs::rename(&ckpt, &old).map_err(|e| file_err(&ckpt, e))?;
    }
    std::fs::rename(&tmp, &ckpt).map_err(|e| file_err(&ckpt, e))?;
    let _ = std::fs::remove_dir_all(&old);
    // latest weights at the top of the run directory, replaced atomically
    model.clone().save_file(run.join("model-new")).map_err(|e| file_err(&run.join("model.bpk"), e))?;
    std::fs::rename(run.join("model-new.bpk"), run.join("model.bpk")).map_err(|e| file_err(&run.join("model.bpk"), e))?;
    Ok(())
}

fn write_rows(path: &Path, rows: &[EpochMetrics]) -> Result<()> {
    let mut s = String::from(CSV_HEADER);
    for r in rows {
        s.push_str(&format!("{},{},{:.6e},{:.6e},{:.3},{:.2}\n", r.epoch, r.step, r.train_loss, r.val_mse, r.val_psnr, r.seconds));
    }
    Ok(write_bytes(path, s.as_bytes())?)
}

fn read_rows(path: &Path, upto: usize) -> Result<Vec<EpochMetrics>> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(Vec::new()) };
    let mut rows = Vec::new();
    for line in text.lines().skip(1) {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != 6 {
            return Err(file_err(path, format!("row {line:?} does not have 6 fields")));
        }
        let p = |s: &str| s.parse::<f64>().map_err(|_| file_err(path, format!("bad number {s:?}")));
        let epoch = p(f[0])? as usize;
        if epoch <= upto {
            rows.push(EpochMetrics { epoch, step: p(f[1])? as u64, train_loss: p(f[2])?, val_mse: p(f[3])?, val_psnr: p(f[4])?, seconds: p(f[5])? });
        }
    }
    Ok(rows)
}

/// Timings of one training step.
#[derive(Debug, Clone, Copy)]
pub struct StepTiming {
    pub step_ms: f64,
    pub forward_ms: f64,
    pub backward_ms: f64,
    pub optim_ms: f64,
}

/// Median time of a training step (batch 2, random cubes) at `h × w`.
pub fn bench_step(a: &MeasurementMatrix, model_cfg: &AdmmNetConfig, h: usize, w: usize, steps: usize) -> Result<StepTiming> {
    let device = Device::flex().autodiff();
    device.seed(1);
    let sensor = SensorTensors::new(a, h, w, &device)?;
    let plan = a.plan(h, w)?;
    let mut model = model_cfg.init(&device);
    let mut optim = AdamConfig::new().init();
    let t = a.bins();
    let x = Array4::from_shape_fn((2, t, h, w), |(b, j, r, c)| if (j + r / 8 + c / 8 + b) % 11 == 0 { 1.0 } else { 0.0 });
    let y = simulate(&plan, &x, None, 0)?;
    let mut times: Vec<[f64; 3]> = Vec::new();
    for _ in 0..steps.max(1) + 1 {
        let t0 = Instant::now();
        let pred = model.forward(to_tensor(&y, &device), &sensor);
        let loss = loss_fn(Loss::RmseMae, pred, to_tensor(&x, &device));
        let _: f32 = loss.clone().into_scalar();
        let t1 = Instant::now();
        let grads = GradientsParams::from_grads(loss.backward(), &model);
        let t2 = Instant::now();
        model = optim.step(1e-3, model, grads);
        let _ = model.rhos();
        let t3 = Instant::now();
        times.push([(t1 - t0).as_secs_f64(), (t2 - t1).as_secs_f64(), (t3 - t2).as_secs_f64()]);
    }
    times.remove(0); // warm-up
    times.sort_by(|a, b| (a[0] + a[1] + a[2]).total_cmp(&(b[0] + b[1] + b[2])));
    let m = times[times.len() / 2];
    Ok(StepTiming { step_ms: (m[0] + m[1] + m[2]) * 1e3, forward_ms: m[0] * 1e3, backward_ms: m[1] * 1e3, optim_ms: m[2] * 1e3 })
}

/// Median inference time (ms) of one `h × w` frame on the CPU without autodiff.
pub fn bench_forward(a: &MeasurementMatrix, model_cfg: &AdmmNetConfig, h: usize, w: usize, reps: usize) -> Result<f64> {
    let device = Device::flex();
    device.seed(1);
    let sensor = SensorTensors::new(a, h, w, &device)?;
    let model = model_cfg.init(&device);
    let y = Array4::from_shape_fn((1, a.taps(), h, w), |(_, m, r, c)| ((m + r + c) % 7) as f32 * 0.1);
    let mut times = Vec::new();
    for _ in 0..reps.max(1) + 1 {
        let t0 = Instant::now();
        let out = to_array(model.forward(to_tensor(&y, &device), &sensor))?;
        std::hint::black_box(out);
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    times.remove(0);
    times.sort_by(f64::total_cmp);
    Ok(times[times.len() / 2])
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_datasets::lidar::LidarParams;
    use tcsense_datasets::store::{generate, Generator, WriteOptions};
    use tcsense_datasets::TimeGrid;
    use tcsense_sensor::codes::{CodeShape, Constraints};
    use tcsense_sensor::generate::random_codes;

    fn tmp() -> PathBuf {
        let d = std::env::temp_dir().join(format!("tcsense-train-{}-{}", std::process::id(), std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()));
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn setup(dir: &Path) -> (TrainConfig, Codes) {
        let gen = Generator::Lidar(LidarParams { height: 8, width: 8, ..Default::default() });
        let grid = TimeGrid { length: 8, ..TimeGrid::default() };
        let cancel = AtomicBool::new(false);
        generate(&gen, &grid, 8, 1, &dir.join("ds"), &WriteOptions { shard_size: 8, force: false, progress: &|| {}, cancel: &cancel }).unwrap();
        let codes = random_codes(CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false }, 607e6, Constraints { tap: true, ..Default::default() }, 2).unwrap();
        let model = AdmmNetConfig::new(4, 8).with_stages(2).with_channels(4);
        let mut cfg = TrainConfig::new(model, &dir.join("ds"), Loss::RmseMae, Sampling::Oversample(1));
        cfg.epochs = 2;
        cfg.learning_rate = 1e-2;
        (cfg, codes)
    }

    fn weights_output(run: &Path, y: &Array4<f32>) -> Vec<f32> {
        let device = Device::flex();
        let (cfg, codes, model) = load_run(run, &device).unwrap();
        let a = matrix(&codes, &cfg).unwrap();
        let st = SensorTensors::new(&a, 8, 8, &device).unwrap();
        to_array(model.forward(to_tensor(y, &device), &st)).unwrap().iter().copied().collect()
    }

    #[test]
    fn training_reduces_loss_saves_and_resumes() {
        let dir = tmp();
        let (cfg, codes) = setup(&dir);
        let mut long = cfg.clone();
        long.epochs = 6;
        let m = train(&long, &codes, &dir.join("run"), false, &Quiet, &AtomicBool::new(false)).unwrap();
        assert_eq!(m.len(), 6);
        assert!(m[5].train_loss < m[0].train_loss, "loss {} -> {}", m[0].train_loss, m[5].train_loss);
        let csv = std::fs::read_to_string(dir.join("run/metrics.csv")).unwrap();
        assert_eq!(csv.lines().count(), 7);

        // save -> load gives identical outputs
        let y = Array4::from_shape_fn((1, 4, 8, 8), |(_, m, r, c)| ((m + r * 3 + c) % 5) as f32 * 0.2);
        let a1 = weights_output(&dir.join("run"), &y);
        let a2 = weights_output(&dir.join("run"), &y);
        assert_eq!(a1, a2);

        // 2 epochs straight == 1 epoch + resume for 1 more
        train(&cfg, &codes, &dir.join("straight"), false, &Quiet, &AtomicBool::new(false)).unwrap();
        let mut one = cfg.clone();
        one.epochs = 1;
        train(&one, &codes, &dir.join("resumed"), false, &Quiet, &AtomicBool::new(false)).unwrap();
        let state: RunState = read_json(&dir.join("resumed/checkpoint/state.json")).unwrap();
        assert_eq!((state.epoch, state.step), (1, 3));
        let more = train(&cfg, &codes, &dir.join("resumed"), true, &Quiet, &AtomicBool::new(false)).unwrap();
        assert_eq!(more.len(), 1);
        assert_eq!((more[0].epoch, more[0].step), (2, 6), "continues from the saved step");
        let s = weights_output(&dir.join("straight"), &y);
        let r = weights_output(&dir.join("resumed"), &y);
        let diff = s.iter().zip(&r).fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(diff < 1e-4, "resumed run differs from the straight run by {diff}");
        // a fresh run refuses to overwrite
        assert!(train(&cfg, &codes, &dir.join("straight"), false, &Quiet, &AtomicBool::new(false)).is_err());
    }
}
