//! `tcsense train …` and `tcsense reconstruct admm-net`.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use ndarray::{Array4, ArrayD, Axis, Ix3, Ix4};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use tcsense_datasets::store::Kind;
use tcsense_datasets::Dataset;
use tcsense_models::{AdmmNet, AdmmNetConfig, SensorTensors};
use tcsense_sensor::npy::{ensure_finite, read_npy, write_npy};
use tcsense_sensor::Codes;
use tcsense_train::{load_run, matrix, to_array, to_tensor, train, EpochMetrics, Loss, Progress, TrainConfig, TrainError};

use super::dataset::interrupt_flag;

/// Model size presets.
#[derive(Clone, Copy, ValueEnum)]
pub enum Preset {
    /// S = 5 stages, CN = 16 channels: trains in minutes on two cores.
    Cpu,
    /// The paper's LiDAR network: S = 9, CN = 128.
    Lidar,
    /// The paper's FLIm network: S = 9, CN = 32.
    Flim,
}

#[derive(Subcommand)]
pub enum TrainCmd {
    /// Train ADMM-Net on a dataset with fixed codes.
    AdmmNet(TrainArgs),
}

#[derive(Args)]
pub struct TrainArgs {
    /// Dataset directory.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Codes JSON file.
    #[arg(long)]
    codes: Option<PathBuf>,
    /// A training config JSON (as written to RUN/config.json); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Model size.
    #[arg(long, value_enum, default_value = "cpu")]
    preset: Preset,
    /// Unrolled stages (overrides the preset).
    #[arg(long)]
    stages: Option<usize>,
    /// CNN channels (overrides the preset).
    #[arg(long)]
    channels: Option<usize>,
    /// Epochs.
    #[arg(long)]
    epochs: Option<usize>,
    /// Learning rate.
    #[arg(long)]
    lr: Option<f64>,
    /// Batch size.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Loss (default: rmse-mae for LiDAR, rmse for FLIm).
    #[arg(long, value_enum)]
    loss: Option<LossArg>,
    /// Train on noise-free measurements.
    #[arg(long)]
    no_noise: bool,
    /// Instrument response: ideal or physical.
    #[arg(long)]
    irf: Option<String>,
    /// Use at most N training items.
    #[arg(long)]
    max_train: Option<usize>,
    /// Use at most N validation items.
    #[arg(long)]
    max_val: Option<usize>,
    /// Seed (weights, batch order, noise).
    #[arg(long)]
    seed: Option<u64>,
    /// Continue the run in the output directory from its last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Run directory.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum LossArg {
    Rmse,
    RmseMae,
}

struct Bar {
    pb: ProgressBar,
}

impl Progress for Bar {
    fn step(&self, epoch: usize, i: usize, n: usize, loss: f64) {
        if i == 1 {
            self.pb.set_length(n as u64);
            self.pb.set_position(0);
        }
        self.pb.set_position(i as u64);
        self.pb.set_message(format!("epoch {} loss {loss:.4e}", epoch + 1));
    }
    fn epoch(&self, m: &EpochMetrics) {
        self.pb.suspend(|| println!("epoch {:>4}  step {:>6}  train loss {:.4e}  val MSE {:.4e}  PSNR {:.2} dB  {:.0} s", m.epoch, m.step, m.train_loss, m.val_mse, m.val_psnr, m.seconds));
    }
}

fn read_config(path: &Path) -> Result<TrainConfig> {
    let text = std::fs::read_to_string(path).with_context(|| format!("{}: cannot read", path.display()))?;
    serde_json::from_str(&text).map_err(|e| anyhow::anyhow!("{}: malformed training config: {e}", path.display()))
}

pub fn run(cmd: TrainCmd) -> Result<ExitCode> {
    let TrainCmd::AdmmNet(a) = cmd;
    let run_dir = &a.output;
    // base config: the saved one on --resume, a given file, or built from the dataset
    let saved = run_dir.join("config.json");
    let mut cfg = if a.resume {
        if !saved.exists() {
            bail!("{}: no run to resume (config.json missing)", run_dir.display());
        }
        read_config(&saved)?
    } else if let Some(p) = &a.config {
        read_config(p)?
    } else {
        let ds_path = a.dataset.as_ref().context("--dataset is required (or --config / --resume)")?;
        let ds = Dataset::open(ds_path)?;
        let codes_path = a.codes.as_ref().context("--codes is required")?;
        let codes = Codes::load(codes_path)?;
        let (m, t) = (codes.taps(), ds.manifest.bins);
        let model = match a.preset {
            Preset::Cpu => AdmmNetConfig::cpu(m, t),
            Preset::Lidar => AdmmNetConfig::lidar(m, t),
            Preset::Flim => AdmmNetConfig::flim(m, t),
        };
        let loss = if ds.manifest.kind == Kind::Flim { Loss::Rmse } else { Loss::RmseMae };
        TrainConfig::new(model, ds_path, loss, ds.manifest.grid.sampling)
    };
    if let Some(d) = &a.dataset {
        cfg.dataset = d.display().to_string();
    }
    if let Some(v) = a.stages {
        cfg.model.stages = v;
    }
    if let Some(v) = a.channels {
        cfg.model.channels = v;
    }
    if let Some(v) = a.epochs {
        cfg.epochs = v;
    }
    if let Some(v) = a.lr {
        cfg.learning_rate = v;
    }
    if let Some(v) = a.batch_size {
        cfg.batch_size = v;
    }
    if let Some(l) = a.loss {
        cfg.loss = match l {
            LossArg::Rmse => Loss::Rmse,
            LossArg::RmseMae => Loss::RmseMae,
        };
    }
    if a.no_noise {
        cfg.noise = None;
    }
    if let Some(irf) = &a.irf {
        cfg.irf = super::sensor::parse_irf(irf)?;
    }
    if a.max_train.is_some() {
        cfg.max_train_items = a.max_train;
    }
    if a.max_val.is_some() {
        cfg.max_val_items = a.max_val;
    }
    if let Some(s) = a.seed {
        cfg.seed = s;
    }
    let codes = match (&a.codes, a.resume) {
        (Some(p), _) => Codes::load(p)?,
        (None, true) => Codes::load(&run_dir.join("codes.json"))?,
        (None, false) => bail!("--codes is required"),
    };
    if codes.taps() != cfg.model.taps {
        bail!("the codes have {} taps but the model expects M = {}", codes.taps(), cfg.model.taps);
    }
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(1);
    pb.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
    println!(
        "ADMM-Net S = {}, CN = {}, M = {}, T = {}; {} epochs, batch {}, lr {}, loss {:?}, noise {}",
        cfg.model.stages,
        cfg.model.channels,
        cfg.model.taps,
        cfg.model.bins,
        cfg.epochs,
        cfg.batch_size,
        cfg.learning_rate,
        cfg.loss,
        if cfg.noise.is_some() { "shot + read" } else { "off" }
    );
    let res = train(&cfg, &codes, run_dir, a.resume, &Bar { pb: pb.clone() }, &cancel);
    pb.finish_and_clear();
    match res {
        Ok(rows) => {
            if let Some(last) = rows.last() {
                println!("wrote {}: epoch {}, val MSE {:.4e}", run_dir.display(), last.epoch, last.val_mse);
            } else {
                println!("{}: already trained for {} epochs", run_dir.display(), cfg.epochs);
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(TrainError::Cancelled) => bail!("interrupted; the last checkpoint in {} is kept, continue with --resume", run_dir.display()),
        Err(e) => Err(e.into()),
    }
}

/// A loaded ADMM-Net run ready for inference on the CPU.
pub struct AdmmRunner {
    pub model: AdmmNet,
    pub cfg: TrainConfig,
    pub codes: Codes,
    device: tcsense_models::Device,
    a: tcsense_sensor::MeasurementMatrix,
    sensor: Option<SensorTensors>,
}

impl AdmmRunner {
    pub fn open(run: &Path) -> Result<Self> {
        let device = tcsense_models::Device::flex();
        let (cfg, codes, model) = load_run(run, &device)?;
        let a = matrix(&codes, &cfg)?;
        Ok(AdmmRunner { model, cfg, codes, device, a, sensor: None })
    }

    /// Reconstruct a batch.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn run(&mut self, y: &Array4<f32>) -> Result<Array4<f32>> {
        let (_, m, h, w) = y.dim();
        if m != self.cfg.model.taps {
            bail!("{m} tap images, but the model expects M = {}", self.cfg.model.taps);
        }
        let fits = self.sensor.as_ref().is_some_and(|s| (s.height, s.width) == (h, w));
        if !fits {
            self.sensor = Some(SensorTensors::new(&self.a, h, w, &self.device)?);
        }
        let sensor = self.sensor.as_ref().context("sensor tensors")?;
        Ok(to_array(self.model.forward(to_tensor(y, &self.device), sensor))?)
    }
}

pub fn reconstruct(run: &Path, measurements: &Path, output: &Path) -> Result<ExitCode> {
    let mut r = AdmmRunner::open(run)?;
    let y = read_npy(measurements)?;
    ensure_finite(&y.view(), "measurements").map_err(|e| e.in_file(measurements))?;
    let (batch, y4): (bool, Array4<f32>) = match y.ndim() {
        3 => (false, y.into_dimensionality::<Ix3>()?.insert_axis(Axis(0))),
        4 => (true, y.into_dimensionality::<Ix4>()?),
        _ => bail!("{}: measurements have shape {:?}, expected [M, H, W] or [B, M, H, W]", measurements.display(), y.shape()),
    };
    let t0 = std::time::Instant::now();
    let mut outs = Vec::new();
    for i in 0..y4.dim().0 {
        let yi = y4.index_axis(Axis(0), i).insert_axis(Axis(0)).to_owned();
        outs.push(r.run(&yi).map_err(|e| anyhow::anyhow!("{}: {e:#}", measurements.display()))?);
    }
    let views: Vec<_> = outs.iter().map(|x| x.view()).collect();
    let x = ndarray::concatenate(Axis(0), &views)?;
    let out: ArrayD<f32> = if batch { x.into_dyn() } else { x.index_axis(Axis(0), 0).to_owned().into_dyn() };
    write_npy(output, &out.view())?;
    println!("wrote {}: x̂ {:?} ({:.1} ms per frame)", output.display(), out.shape(), t0.elapsed().as_secs_f64() * 1e3 / y4.dim().0 as f64);
    Ok(ExitCode::SUCCESS)
}
