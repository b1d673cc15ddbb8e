//! `tcsense train …`: the flags as a `tcsense_train::request::TrainRequest` (the training
//! crate resolves it into the run), progress bars, pausing and Ctrl-C.

use anyhow::{bail, Result};
use clap::{Args, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;
use std::process::ExitCode;
use tcsense_train::request::{self, TrainRequest};
use tcsense_train::{EpochMetrics, Progress, TrainError};

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
    /// Train ADMM-Net (cubes) on a dataset with fixed codes.
    AdmmNet {
        #[command(flatten)]
        common: TrainArgs,
        #[command(flatten)]
        net: AdmmArgs,
    },
    /// Train the Aᵀ + U-Net depth decoder on a LiDAR dataset (its range ground truth).
    Unet {
        #[command(flatten)]
        common: TrainArgs,
        #[command(flatten)]
        net: UnetArgs,
    },
    /// Train the lifetime decoder on a FLIm dataset (its lifetime ground truth): tap images to
    /// the mean lifetime, two components and their fraction, and a confidence per pixel.
    Lifetime {
        #[command(flatten)]
        common: TrainArgs,
        #[command(flatten)]
        net: LifetimeArgs,
    },
}

/// Lifetime-decoder size.
#[derive(Args)]
pub struct LifetimeArgs {
    /// Harmonics of the cycle the time axis is pooled to (input channels 2K + 2) [default: 16].
    #[arg(long)]
    harmonics: Option<usize>,
    /// Channels of the U-Net's first level (doubled per level) [default: 16].
    #[arg(long)]
    base_width: Option<usize>,
    /// Resolutions (frames are padded inside the model to a multiple of 2^(levels−1)) [default: 3].
    #[arg(long)]
    levels: Option<usize>,
    /// With `--input costs`: points of the log grid of lifetimes over 0.05–25 ns whose costs the
    /// fit's evidence holds (fewer is faster, more is finer before the refinement) [default: 96].
    #[arg(long, value_parser = super::count_in(3, 1024))]
    points: Option<usize>,
    /// With `--input costs`: sides of wider windows (odd, increasing, above the fit's 3, e.g.
    /// `5,9,15`) whose log-likelihoods the network adds to the fit's 3×3 window's, each with a
    /// weight it sets pixel by pixel (in dim light a cell's pixels agree over a wider window)
    /// [default: none].
    #[arg(long, value_delimiter = ',', num_args = 1.., value_parser = super::count_in(1, 63))]
    windows: Option<Vec<usize>>,
    /// With `--input costs`: pool the fit's 3×3 window's log-likelihood with the neighbouring
    /// windows of like lifetime that tile this side (9, 15, 21…) before the learned prior is
    /// added, as `lifetime-fit-pooled` does: the untrained network is that fit [default: none].
    #[arg(long, value_parser = super::count_in(1, 63))]
    pool_like: Option<usize>,
    /// With `--input costs`: fit each frame's onset and IRF width on superpixels of this side
    /// (in blocks of the mosaic; each subpixel type's taps summed over one), 1 for every pixel
    /// alone [default: 0, from the frame's photons: every pixel alone where they suffice, else
    /// its brightest pixels under the frame's mixture of lifetimes].
    #[arg(long, value_parser = super::count_in(0, 64))]
    instrument_blocks: Option<usize>,
    /// With `--input costs`: in training, fit a dim frame's onset and IRF width on its
    /// brightest pixels under the frame's mixture of lifetimes and background shares, as every
    /// run decodes, instead of on superpixels (about 5× slower to train) [default: off].
    #[arg(long)]
    instrument_mixture: bool,
    /// With `--input costs`: weigh the fit's log-likelihood by a temperature the network sets
    /// pixel by pixel (`e^{clip(2·o_t, −4, 1)}`, 1 untrained), so that it may soften evidence
    /// that is sharp and wrong (pooled across an edge, a biased instrument) [default: off].
    #[arg(long)]
    temper: bool,
    /// With `--input costs`: the weight of the log-posterior's cross-entropy over the lifetime
    /// grid in the loss, beside the lifetime's absolute error (0 trains the posterior's mean
    /// alone) [default: 0.2].
    #[arg(long, value_parser = super::number_in(0.0, 10.0))]
    grid_ce: Option<f64>,
    /// With `--input costs`: refine the posterior's mode in the tap domain wherever it is
    /// within one point of the grid of the fit's own argmin (not only at it): the fit's
    /// precision in bright light where the network's mode and the fit's differ by a point
    /// [default: off].
    #[arg(long)]
    refine_near_mode: bool,
    /// The lifetimes' error in the loss: in `ns`, or of `ln τ` (`log`, counted as 2 ns per
    /// unit: a relative error, so that dim items and long lifetimes do not make up the loss)
    /// [default: ns].
    #[arg(long, value_enum)]
    lifetime_error: Option<LifetimeErrorArg>,
    /// With `--input costs`: how the confidence of a fluorophore is trained. `weighted`: the
    /// cross-entropy that weighs a missed fluorophore 8 times a false one; `stalled`: the same
    /// written as runs before this choice had it, whose gradient vanishes at the untrained head,
    /// so the confidence stays at ½ and every pixel gets a lifetime (kept to replay the zoo
    /// entries trained with it) [default: weighted].
    #[arg(long, value_enum)]
    confidence_loss: Option<ConfidenceLossArg>,
    /// What the network reads: `harmonics` of Aᵀy turned by the frame's own phase, or `costs`,
    /// the fit to the taps' log-likelihood of every lifetime of a log grid (the instrument
    /// fitted to the frame), to which it adds a learned log-prior [default: harmonics].
    #[arg(long, value_enum)]
    input: Option<LifetimeInputArg>,
}

#[derive(Clone, Copy, ValueEnum)]
enum LifetimeErrorArg {
    Ns,
    Log,
}

#[derive(Clone, Copy, ValueEnum)]
enum ConfidenceLossArg {
    Weighted,
    Stalled,
}

#[derive(Clone, Copy, ValueEnum)]
enum LifetimeInputArg {
    Harmonics,
    Costs,
}

#[derive(Clone, Copy, ValueEnum)]
enum InputArg {
    Backprojection,
    Matched,
    Costs,
}

/// ADMM-Net size.
#[derive(Args)]
pub struct AdmmArgs {
    /// Model size [default: cpu].
    #[arg(long, value_enum)]
    preset: Option<Preset>,
    /// Unrolled stages (overrides the preset).
    #[arg(long)]
    stages: Option<usize>,
    /// CNN channels (overrides the preset; per bin for `--prior delay`).
    #[arg(long)]
    channels: Option<usize>,
    /// The prior's convolutions: `bins` — over the frame with the bins as channels (the
    /// paper's); `delay` — over time and the frame, circular in time, so the network treats
    /// every delay (onset, cable length, trigger) alike; its channels default to 4 per bin
    /// (8 with the paper's presets). New runs only.
    #[arg(long, value_enum)]
    prior: Option<PriorArg>,
}

#[derive(Clone, Copy, ValueEnum)]
enum HeadArg {
    ScoreVolume,
    Regression,
}

#[derive(Clone, Copy, ValueEnum)]
enum PriorArg {
    Bins,
    Delay,
}

/// U-Net size.
#[derive(Args)]
pub struct UnetArgs {
    /// How the range is read out: `score-volume` (a score per bin and return, the range their
    /// soft-argmax: sub-bin precision) or `regression` (one sigmoid per return over the whole
    /// range, as runs before the score volume).
    /// [default: score-volume]
    #[arg(long, value_enum)]
    head: Option<HeadArg>,
    /// Returns per pixel: 1 (first surface) or 2 (and the one behind a diffusive sheet)
    /// [default: 2].
    #[arg(long, value_parser = super::count_in(1, 2))]
    returns: Option<usize>,
    /// Channels of the first level (doubled per level) [default: 8].
    #[arg(long)]
    base_width: Option<usize>,
    /// Resolutions (frames are padded inside the model to a multiple of 2^(levels−1)) [default: 3].
    #[arg(long)]
    levels: Option<usize>,
    /// What the network reads: `backprojection` (Aᵀy through the code bits) or `matched` (the
    /// range fit's matched filters at every bin, ambient light projected out: the fit's own
    /// evidence, for the network's spatial prior). With --init-from it may change: the weights
    /// fit either [default: backprojection].
    #[arg(long, value_enum)]
    input: Option<InputArg>,
    /// With `--input costs`: pool the fit's 3×3 window's log-likelihood with the neighbouring
    /// windows of like range that tile this side (9, 15, 21…) before the learned prior is
    /// added, as `depth-fit-pooled` does: the untrained network is that fit. With --init-from
    /// it may change: the weights fit either [default: none].
    #[arg(long, value_parser = super::count_in(1, 63))]
    pool_like: Option<usize>,
    /// With `--input costs`: hold each pixel's cross-entropy in the loss at this many nats, so
    /// that a pixel whose (pooled) likelihood is sharp and wrong costs no more and gives no
    /// gradient, instead of bending the learned prior of every pixel (a fine-tune continues
    /// its source's) [default: not held].
    #[arg(long, value_name = "NATS", value_parser = super::number_in(0.1, 100.0))]
    grid_nll_cap: Option<f64>,
}

#[derive(Args)]
pub struct TrainArgs {
    /// Dataset directory.
    #[arg(long)]
    dataset: Option<PathBuf>,
    #[command(flatten)]
    device: super::DeviceArgs,
    /// Codes JSON file.
    #[arg(long)]
    codes: Option<PathBuf>,
    /// A training config JSON (as written to RUN/config.json); flags override it.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Epochs.
    #[arg(long)]
    epochs: Option<usize>,
    /// Learning rate (the peak of the schedule).
    #[arg(long)]
    lr: Option<f64>,
    /// Learning-rate schedule: `cosine` (new runs: half a cosine down to 1 % over the run
    /// after 50 warm-up steps) or `constant` (the paper's).
    #[arg(long, value_enum)]
    lr_schedule: Option<ScheduleArg>,
    /// Batch size.
    #[arg(long)]
    batch_size: Option<usize>,
    /// Loss (default: rmse-mae for LiDAR, rmse for FLIm).
    #[arg(long, value_enum)]
    loss: Option<LossArg>,
    /// What the run is trained for, the product its users read: `mse` (the cube's loss
    /// alone), `range` or `lifetime` (a cube decoder adds the earth mover's distance between
    /// every pixel's predicted and true waveform: the range or lifetime error in bins). With
    /// --learn-codes it is what the codes are learned for. Default: the network's own (cube
    /// decoders mse; depth networks range; lifetime networks lifetime).
    #[arg(long, value_enum)]
    objective: Option<ObjectiveArg>,
    /// Train on noise-free measurements.
    #[arg(long)]
    no_noise: bool,
    /// Instrument response: ideal, physical, or a measured (recalibrated) sensor matrix
    /// A.npy [N, M, T], which the run keeps as sensor_matrix.npy and uses in training and
    /// inference.
    #[arg(long)]
    irf: Option<String>,
    /// Train for a calibrated sensor (`tcsense calibrate`): its measured matrix replaces the
    /// model's (kept as sensor_matrix.npy); decode its raw tap images with the same
    /// `--calibration DIR`. With --init-from this fine-tunes a decoder to the real sensor.
    #[arg(long, value_name = "DIR")]
    calibration: Option<PathBuf>,
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
    /// Augmentation: after each measurement, perturb the tap images by what a calibration
    /// leaves of a real sensor, drawn per item: tap gains 1 ± G, pixel gains 1 + N(0, P²),
    /// offsets N(0, D²) × the brightest tap (e.g. 0.01,0.005,0.002), so the decoder tolerates it.
    #[arg(long, value_name = "G,P,D", value_delimiter = ',', num_args = 1, conflicts_with = "no_augment")]
    sensor_residue: Option<Vec<f64>>,
    /// Train on random HxW crops of the frames (a multiple of the pixel block).
    #[arg(long, value_parser = super::parse_hw)]
    crop: Option<(usize, usize)>,
    /// The photon ladder: each item's brightest tap at a fraction of the full well drawn
    /// log-uniformly from LO,HI (default 0.05,0.9; e.g. 0.002,0.9 down to where `eval --light`
    /// reaches).
    #[arg(long, value_name = "LO,HI", value_parser = super::parse_range, allow_hyphen_values = true, conflicts_with = "no_augment")]
    signal: Option<(f64, f64)>,
    /// Ambient light: each item gets a background of 1/SBR times its mean signal, drawn
    /// uniformly from LO,HI (e.g. 0,2: from none to twice the signal; at most 100).
    #[arg(long, value_name = "LO,HI", value_parser = super::parse_range, allow_hyphen_values = true, conflicts_with = "no_augment")]
    ambient: Option<(f64, f64)>,
    /// Continue the run in the output directory from its last checkpoint.
    #[arg(long)]
    resume: bool,
    /// Stop after N epochs of this invocation with the run's checkpoint in place (the schedule
    /// stays that of --epochs): long trainings go in slices, `--resume --pause-after N` each.
    #[arg(long, value_name = "N")]
    pause_after: Option<usize>,
    /// Stop after N optimiser steps of this invocation, printing each step's training loss, and
    /// keep no checkpoint: a quick check that a recipe runs and starts as it did (the zoo's
    /// replay compares these losses with the entry's `first_steps.csv`).
    #[arg(long, value_name = "N", conflicts_with_all = ["pause_after", "resume"])]
    stop_after_steps: Option<usize>,
    /// Start from the weights of a trained run of the same network (fine-tuning on new codes,
    /// another IRF or a recalibrated sensor); `zoo:NAME` starts from a zoo entry. The network's
    /// architecture comes from that run (flags that contradict it are refused).
    #[arg(long, value_name = "RUN", value_parser = super::parse_run)]
    init_from: Option<PathBuf>,
    /// Deep sensing: learn the codes with the decoder, starting from --codes; after the relaxed
    /// epochs they are projected exactly onto the constraints (those of --codes, or the flags
    /// below) and the decoder is fine-tuned on them. RUN/codes.json is the result.
    #[arg(long)]
    learn_codes: bool,
    /// Learned codes: the tap constraint.
    #[arg(long, requires = "learn_codes")]
    tap_constraint: bool,
    /// Learned codes: at most H bits change between adjacent masks.
    #[arg(long, value_name = "H", requires = "learn_codes")]
    hamming: Option<usize>,
    /// Learned codes: every run of 1s and 0s lasts at least W masks.
    #[arg(long, value_name = "W", requires = "learn_codes")]
    window: Option<usize>,
    /// Learned codes: epochs of joint training on relaxed codes (default: two thirds).
    #[arg(long, requires = "learn_codes")]
    relaxed_epochs: Option<usize>,
    /// Learned codes: Adam learning rate of the code logits.
    #[arg(long, requires = "learn_codes")]
    codes_lr: Option<f64>,
    /// Learned codes: weight of the identifiability term, a squared hinge on the range alias
    /// (pairs of ranges two masks or more apart whose taps are closer than --alias-threshold);
    /// 0 leaves it out (default 1).
    #[arg(long, requires = "learn_codes")]
    alias_weight: Option<f64>,
    /// Learned codes: the alias distance the identifiability term enforces and the projection
    /// onto the constraints keeps, pulling towards the start codes where needed (default 0.5).
    #[arg(long, requires = "learn_codes")]
    alias_threshold: Option<f64>,
    /// Run directory.
    #[arg(short, long)]
    output: PathBuf,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum LossArg {
    Rmse,
    RmseMae,
    /// RMSE + MAE, plus the same on every pixel's waveform divided by its peak (dim pixels'
    /// returns count as much as bright ones')
    RmseMaePixel,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ObjectiveArg {
    Mse,
    Range,
    Lifetime,
}

#[derive(Clone, Copy, ValueEnum)]
pub enum ScheduleArg {
    Constant,
    Cosine,
}

/// Training progress: a bar over the steps of an epoch, a line per epoch.
pub(crate) struct Bar {
    pub pb: ProgressBar,
    /// `--pause-after N`: after N epochs of this invocation the flag is raised, the loop stops
    /// at the next step (the epoch's checkpoint is written), and the run resumes later.
    pub pause: Option<(usize, std::sync::Arc<std::sync::atomic::AtomicBool>)>,
    pub epochs_done: std::sync::atomic::AtomicUsize,
    /// `--stop-after-steps N`: each step's loss is printed, and after N steps the flag is
    /// raised and the loop stops before the next one.
    pub stop_after_steps: Option<(usize, std::sync::Arc<std::sync::atomic::AtomicBool>)>,
    pub steps_done: std::sync::atomic::AtomicUsize,
}

impl Bar {
    pub fn new() -> Self {
        let pb = ProgressBar::new(1);
        pb.set_style(
            ProgressStyle::with_template("[{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        Bar { pb, pause: None, epochs_done: Default::default(), stop_after_steps: None, steps_done: Default::default() }
    }
}

impl Progress for Bar {
    fn step(&self, epoch: usize, i: usize, n: usize, loss: f64) {
        if i == 1 {
            self.pb.set_length(n as u64);
            self.pb.set_position(0);
        }
        self.pb.set_position(i as u64);
        self.pb.set_message(format!("epoch {} loss {loss:.4e}", epoch + 1));
        if let Some((n, flag)) = &self.stop_after_steps {
            let done = self.steps_done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
            // the format of metrics.csv's train_loss
            self.pb.suspend(|| println!("step {done:>4}  epoch {:>4}  step in epoch {i:>6}  train loss {loss:.6e}", epoch + 1));
            if done >= *n {
                flag.store(true, std::sync::atomic::Ordering::SeqCst);
            }
        }
    }
    fn epoch(&self, m: &EpochMetrics) {
        let val: String = m
            .val
            .iter()
            .map(|(n, v)| match n.trim_start_matches("val_") {
                "psnr_db" => format!("  PSNR {v:.2} dB"),
                "detection" => format!("  detection {:.1} %", v * 100.0),
                "coverage" => format!("  coverage {:.1} %", v * 100.0),
                "lifetime_mae_ns" => format!("  lifetime MAE {v:.3} ns"),
                n => format!("  {} {v:.4e}", n.replace('_', " ")),
            })
            .collect();
        self.pb.suspend(|| {
            println!("epoch {:>4}  step {:>6}  train loss {:.4e}  val{val}  {:.0} s", m.epoch, m.step, m.train_loss, m.seconds)
        });
        let done = self.epochs_done.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1;
        if let Some((n, flag)) = &self.pause {
            if done >= *n {
                flag.store(true, std::sync::atomic::Ordering::SeqCst);
            }
        }
    }
}

/// The network a new run starts with.
enum NetArgs {
    Admm(AdmmArgs),
    Unet(UnetArgs),
    Lifetime(LifetimeArgs),
}

/// A value enum's command-line name (`score-volume`, `rmse-mae`).
fn name_of<T: ValueEnum>(v: T) -> Option<String> {
    v.to_possible_value().map(|p| p.get_name().to_string())
}

impl TrainArgs {
    /// The flags as the training crate's request (the same as Python's keyword arguments).
    fn request(&self, net: &NetArgs) -> Result<TrainRequest> {
        if let Some(r) = &self.sensor_residue {
            if r.len() != 3 {
                bail!("--sensor-residue {r:?}: expected three numbers G,P,D (tap gain, PRNU, dark), e.g. 0.01,0.005,0.002");
            }
        }
        let mut req = TrainRequest {
            output: self.output.clone(),
            dataset: self.dataset.clone(),
            codes: self.codes.clone(),
            config: self.config.clone(),
            resume: self.resume,
            init_from: self.init_from.clone(),
            epochs: self.epochs,
            lr: self.lr,
            lr_schedule: self.lr_schedule.and_then(name_of),
            batch_size: self.batch_size,
            loss: self.loss.and_then(name_of),
            objective: self.objective.and_then(name_of),
            no_noise: self.no_noise,
            irf: self.irf.clone(),
            calibration: self.calibration.clone(),
            max_train: self.max_train,
            max_val: self.max_val,
            seed: self.seed,
            no_augment: self.no_augment,
            sensor_residue: self.sensor_residue.as_ref().map(|r| [r[0], r[1], r[2]]),
            crop: self.crop.map(|(h, w)| [h, w]),
            signal: self.signal.map(|(lo, hi)| [lo, hi]),
            ambient: self.ambient.map(|(lo, hi)| [lo, hi]),
            learn_codes: self.learn_codes,
            tap_constraint: self.tap_constraint,
            hamming: self.hamming,
            window: self.window,
            relaxed_epochs: self.relaxed_epochs,
            codes_lr: self.codes_lr,
            alias_weight: self.alias_weight,
            alias_threshold: self.alias_threshold,
            ..Default::default()
        };
        match net {
            NetArgs::Admm(n) => {
                req.decoder = tcsense_models::runs::network_names::ADMM_NET.into();
                (req.preset, req.stages, req.channels, req.prior) =
                    (n.preset.and_then(name_of), n.stages, n.channels, n.prior.and_then(name_of));
            }
            NetArgs::Unet(n) => {
                req.decoder = "unet".into();
                (req.head, req.returns, req.base_width, req.levels, req.input, req.pool_like) =
                    (n.head.and_then(name_of), n.returns, n.base_width, n.levels, n.input.and_then(name_of), n.pool_like);
                req.grid_nll_cap = n.grid_nll_cap;
            }
            NetArgs::Lifetime(n) => {
                req.decoder = "lifetime".into();
                (req.harmonics, req.base_width, req.levels, req.input, req.points, req.windows, req.pool_like) =
                    (n.harmonics, n.base_width, n.levels, n.input.and_then(name_of), n.points, n.windows.clone(), n.pool_like);
                req.instrument_blocks = n.instrument_blocks;
                req.instrument_mixture = n.instrument_mixture.then_some(true);
                req.temper = n.temper.then_some(true);
                req.grid_ce = n.grid_ce;
                req.refine_near_mode = n.refine_near_mode.then_some(true);
                req.lifetime_error = n.lifetime_error.and_then(name_of);
                req.confidence_loss = n.confidence_loss.and_then(name_of);
            }
        }
        Ok(req)
    }
}

pub fn run(cmd: TrainCmd) -> Result<ExitCode> {
    let (a, net) = match cmd {
        TrainCmd::AdmmNet { common, net } => (common, NetArgs::Admm(net)),
        TrainCmd::Unet { common, net } => (common, NetArgs::Unet(net)),
        TrainCmd::Lifetime { common, net } => (common, NetArgs::Lifetime(net)),
    };
    let run_dir = &a.output;
    // the device first: a missing GPU backend or adapter writes nothing
    let device = a.device.device()?;
    let prepared = request::prepare(&a.request(&net)?)?;
    let cfg = &prepared.cfg;
    println!("{}", cfg.summary());
    if let Some(lc) = &cfg.learn_codes {
        println!("{}", lc.summary(cfg.epochs));
    }
    if a.pause_after == Some(0) {
        bail!("--pause-after 0: expected at least one epoch");
    }
    if a.stop_after_steps == Some(0) {
        bail!("--stop-after-steps 0: expected at least one step");
    }
    let cancel = interrupt_flag();
    let pb = ProgressBar::new(1);
    pb.set_style(
        ProgressStyle::with_template("[{bar:30}] {pos}/{len} steps {per_sec} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    let bar = Bar {
        pb: pb.clone(),
        pause: a.pause_after.map(|n| (n, cancel.clone())),
        epochs_done: Default::default(),
        stop_after_steps: a.stop_after_steps.map(|n| (n, cancel.clone())),
        steps_done: Default::default(),
    };
    let res = request::run(&prepared, &device, &bar, &cancel);
    pb.finish_and_clear();
    match res {
        Ok(rows) => {
            if let Some(last) = rows.last() {
                let (name, v) = last.val.first().map_or(("val", f64::NAN), |(n, v)| (n.as_str(), *v));
                println!("wrote {}: epoch {}, {name} {v:.4e}", run_dir.display(), last.epoch);
                if let Some(lc) = &cfg.learn_codes {
                    report_learned_alias(run_dir, lc.alias_threshold);
                }
            } else {
                println!("{}: already trained for {} epochs", run_dir.display(), cfg.epochs);
            }
            Ok(ExitCode::SUCCESS)
        }
        Err(TrainError::Cancelled) if a.pause_after.is_some_and(|n| bar.epochs_done.load(std::sync::atomic::Ordering::SeqCst) >= n) => {
            println!(
                "paused after {} epochs: {} holds the checkpoint; continue with --resume",
                a.pause_after.unwrap_or(0),
                run_dir.display()
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(TrainError::Cancelled) if a.stop_after_steps.is_some_and(|n| bar.steps_done.load(std::sync::atomic::Ordering::SeqCst) >= n) => {
            println!(
                "stopped after {} steps as asked: {} keeps no checkpoint of them (train again to start over)",
                a.stop_after_steps.unwrap_or(0),
                run_dir.display()
            );
            Ok(ExitCode::SUCCESS)
        }
        Err(TrainError::Cancelled) => bail!("interrupted; the last checkpoint in {} is kept, continue with --resume", run_dir.display()),
        Err(e) => Err(e.into()),
    }
}

/// After deep sensing: the learned codes' range alias (from `RUN/relaxed/projection.json`), with
/// a warning where it fell below the threshold (`codes export` refuses such codes without
/// `--force`; a lower `--codes-lr` or a higher `--alias-weight` keeps them apart).
fn report_learned_alias(run_dir: &std::path::Path, threshold: f64) {
    let path = run_dir.join(tcsense_train::deep_sensing::RELAXED_DIR).join(tcsense_train::deep_sensing::PROJECTION_FILE);
    let alias = std::fs::read_to_string(&path)
        .ok()
        .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        .and_then(|v| v["range_alias"].as_f64());
    match alias {
        Some(a) if a < threshold => println!(
            "warning: the learned codes' range alias is {a:.3}, below {threshold}: two ranges give nearly the same taps, and `codes export` refuses them without --force (try a lower --codes-lr or a higher --alias-weight)"
        ),
        Some(a) => println!("learned codes: range alias {a:.3} (at least {threshold})"),
        None => {}
    }
}
