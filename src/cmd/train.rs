//! `tcsense train …`: resolves flags and a config file into a `TrainConfig`, shows progress.

use anyhow::{bail, Context, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_datasets::store::Kind;
use tcsense_datasets::Dataset;
use tcsense_models::runs::{ModelConfig, CODES_FILE, CONFIG_FILE};
use tcsense_models::AdmmNetConfig;
use tcsense_sensor::Codes;
use tcsense_train::{train, Augmentation, EpochMetrics, Loss, Progress, TrainConfig, TrainError};

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
    /// Train without augmentation (new runs augment by default: cyclic time shifts, flips,
    /// brightness over two decades and a noise level per item).
    #[arg(long, conflicts_with = "crop")]
    no_augment: bool,
    /// Train on random HxW crops of the frames (a multiple of the pixel block).
    #[arg(long, value_parser = super::parse_hw)]
    crop: Option<(usize, usize)>,
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

pub fn run(cmd: TrainCmd) -> Result<ExitCode> {
    let TrainCmd::AdmmNet(a) = cmd;
    let run_dir = &a.output;
    // base config: the saved one on --resume, a given file, or built from the dataset
    let saved = run_dir.join(CONFIG_FILE);
    let mut cfg = if a.resume {
        if !saved.exists() {
            bail!("{}: no run to resume ({CONFIG_FILE} missing)", run_dir.display());
        }
        TrainConfig::load(&saved)?
    } else if let Some(p) = &a.config {
        TrainConfig::load(p)?
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
        let mut cfg = TrainConfig::new(ModelConfig::AdmmNet(model), ds_path, loss, ds.manifest.grid.sampling);
        cfg.augment = Some(Augmentation::default());
        cfg
    };
    if a.no_augment {
        cfg.augment = None;
    }
    if let Some((h, w)) = a.crop {
        cfg.augment = Some(Augmentation { crop: Some([h, w]), ..cfg.augment.unwrap_or_default() });
    }
    if let Some(d) = &a.dataset {
        cfg.dataset = d.display().to_string();
    }
    match &mut cfg.run.model {
        ModelConfig::AdmmNet(m) => {
            if let Some(v) = a.stages {
                m.stages = v;
            }
            if let Some(v) = a.channels {
                m.channels = v;
            }
        }
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
        cfg.run.irf = super::sensor::parse_irf(irf)?;
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
        (None, true) => Codes::load(&run_dir.join(CODES_FILE))?,
        (None, false) => bail!("--codes is required"),
    };
    if codes.taps() != cfg.run.model.taps() {
        bail!("the codes have {} taps but the model expects M = {}", codes.taps(), cfg.run.model.taps());
    }
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(1);
    pb.set_style(ProgressStyle::with_template("[{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}").unwrap_or_else(|_| ProgressStyle::default_bar()).progress_chars("=> "));
    let network = match &cfg.run.model {
        ModelConfig::AdmmNet(m) => format!("ADMM-Net S = {}, CN = {}, M = {}, T = {}", m.stages, m.channels, m.taps, m.bins),
    };
    println!(
        "{network}; {} epochs, batch {}, lr {}, loss {:?}, noise {}, augmentation {}",
        cfg.epochs,
        cfg.batch_size,
        cfg.learning_rate,
        cfg.loss,
        if cfg.noise.is_some() { "shot + read" } else { "off" },
        match &cfg.augment {
            None => "off".to_string(),
            Some(g) => format!("shifts {}, flips {}, crop {}, brightness {:?}, signal {:?} of full well", g.time_shift, g.flips, g.crop.map_or("none".into(), |[h, w]| format!("{h}x{w}")), g.brightness, g.signal_fraction),
        }
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
