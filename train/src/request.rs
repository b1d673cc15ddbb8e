//! A training as a front end asks for it — the command line's flags, the Python module's
//! keyword arguments — resolved into a run's [`TrainConfig`], its codes and its sensor by the
//! rules of [`crate::setup`]. Both front ends fill a [`TrainRequest`] and call [`prepare`] and
//! [`run`]: the same options give the same run directory.
//!
//! ```
//! use tcsense_train::request::TrainRequest;
//! let r: TrainRequest = serde_json::from_value(serde_json::json!({ "decoder": "admm-net", "output": "run", "epochs": 3 })).unwrap();
//! assert_eq!((r.epochs, r.resume), (Some(3), false));
//! assert!(serde_json::from_value::<TrainRequest>(serde_json::json!({ "decoder": "unet", "output": "r", "epoch": 3 })).is_err());
//! ```

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use serde::{Deserialize, Serialize};
use tcsense_datasets::Dataset;
use tcsense_models::runs::{ModelConfig, CONFIG_FILE};
use tcsense_models::{AdmmNetConfig, Device, LifetimeInput, LifetimeNetConfig, Prior, UnetConfig, UnetHead, UnetInput};
use tcsense_sensor::waveform::{parse_irf_default, IrfSpec};
use tcsense_sensor::{Codes, Constraints};

use crate::deep_sensing::LearnCodes;
use crate::setup::{self, Architecture, MeasuredSensor};
use crate::{
    file_err, Augmentation, ConfidenceLoss, EpochMetrics, LifetimeError, Loss, LrSchedule, Objective, Progress, Result, TrainConfig,
    TrainError,
};

/// What a front end asks of a training (`None`/`false`: not given). Names and values are the
/// command line's (`tcsense train DECODER --flag`), with `-` as `_`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainRequest {
    /// `admm-net`, `unet` or `lifetime`.
    pub decoder: String,
    /// The run directory.
    pub output: PathBuf,
    pub dataset: Option<PathBuf>,
    pub codes: Option<PathBuf>,
    /// A training config JSON (as written to `RUN/config.json`); the other fields override it.
    pub config: Option<PathBuf>,
    /// Continue the run in `output` from its last checkpoint.
    pub resume: bool,
    /// Start from the weights (and the architecture) of a trained run or `zoo:NAME`.
    pub init_from: Option<PathBuf>,
    /// ADMM-Net: `cpu`, `lidar` or `flim`.
    pub preset: Option<String>,
    pub stages: Option<usize>,
    pub channels: Option<usize>,
    /// ADMM-Net: `bins` or `delay`.
    pub prior: Option<String>,
    pub returns: Option<usize>,
    pub base_width: Option<usize>,
    pub levels: Option<usize>,
    /// U-Net: `score-volume` or `regression`.
    pub head: Option<String>,
    /// U-Net: `backprojection` or `matched` (what the network reads).
    pub input: Option<String>,
    pub harmonics: Option<usize>,
    /// Lifetime decoder on the fit's evidence: points of the lifetime grid.
    pub points: Option<usize>,
    /// Lifetime decoder on the fit's evidence: sides of the wider windows (`[5, 9, 15]`).
    pub windows: Option<Vec<usize>>,
    /// A decoder on the fit's evidence (U-Net, lifetime): the side of the neighbourhood its
    /// window's log-likelihood is pooled over by likeness.
    pub pool_like: Option<usize>,
    /// Lifetime decoder on the fit's evidence: the side (in blocks) of the superpixels of each
    /// frame's instrument (0: from its photons).
    pub instrument_blocks: Option<usize>,
    /// Lifetime decoder on the fit's evidence: weigh the log-likelihood by a temperature the
    /// network sets pixel by pixel.
    pub temper: Option<bool>,
    /// Lifetime decoder on the fit's evidence: the weight of the grid's cross-entropy in the
    /// loss.
    pub grid_ce: Option<f64>,
    /// U-Net on a range grid: the cross-entropy (nats) at which a pixel's loss is held.
    pub grid_nll_cap: Option<f64>,
    /// Lifetime decoder: the lifetimes' error in the loss, `ns` or `log` (of `ln τ`).
    pub lifetime_error: Option<String>,
    /// Lifetime decoder on the fit's evidence: how its confidence is trained, `weighted` (new
    /// runs) or `stalled` (as runs before the choice were: it does not train).
    pub confidence_loss: Option<String>,
    /// Lifetime decoder on the fit's evidence: refine the mode in the tap domain within a point
    /// of the fit's argmin.
    pub refine_near_mode: Option<bool>,
    /// Lifetime decoder on the fit's evidence: a dim frame's instrument in training under the
    /// frame's mixture (else on superpixels).
    pub instrument_mixture: Option<bool>,
    pub epochs: Option<usize>,
    pub lr: Option<f64>,
    /// `cosine` or `constant`.
    pub lr_schedule: Option<String>,
    pub batch_size: Option<usize>,
    /// `rmse`, `rmse-mae` or `rmse-mae-pixel`.
    pub loss: Option<String>,
    /// `mse`, `range` or `lifetime`: what the run is trained for ([`crate::Objective`]).
    pub objective: Option<String>,
    pub no_noise: bool,
    /// `ideal`, `physical` or a measured matrix `A.npy`.
    pub irf: Option<String>,
    /// A calibration directory: train for the calibrated sensor.
    pub calibration: Option<PathBuf>,
    pub max_train: Option<usize>,
    pub max_val: Option<usize>,
    pub seed: Option<u64>,
    pub no_augment: bool,
    /// Residual tap gain, PRNU and dark offset a calibration leaves, drawn per item.
    pub sensor_residue: Option<[f64; 3]>,
    pub crop: Option<[usize; 2]>,
    /// The photon ladder trained on: the brightest tap's fraction of full well per item,
    /// log-uniform in `[lo, hi]`.
    pub signal: Option<[f64; 2]>,
    /// Ambient light per item, `1/SBR` uniform in `[lo, hi]` (see `Augmentation::ambient`).
    pub ambient: Option<[f64; 2]>,
    pub learn_codes: bool,
    pub tap_constraint: bool,
    pub hamming: Option<usize>,
    pub window: Option<usize>,
    pub relaxed_epochs: Option<usize>,
    pub codes_lr: Option<f64>,
    pub alias_weight: Option<f64>,
    pub alias_threshold: Option<f64>,
}

/// A training ready to run: the run's config, codes and measured sensor.
#[derive(Debug, Clone)]
pub struct Prepared {
    pub cfg: TrainConfig,
    pub codes: Codes,
    pub measured: Option<MeasuredSensor>,
    pub output: PathBuf,
    pub resume: bool,
}

fn bad(field: &'static str, got: &str, expected: &str) -> TrainError {
    TrainError::InvalidParam { field, got: got.into(), expected: expected.into() }
}

fn preset(name: &str, m: usize, t: usize) -> Result<AdmmNetConfig> {
    Ok(match name {
        "cpu" => AdmmNetConfig::cpu(m, t),
        "lidar" => AdmmNetConfig::lidar(m, t),
        "flim" => AdmmNetConfig::flim(m, t),
        other => return Err(bad("preset", other, "cpu, lidar or flim")),
    })
}

impl TrainRequest {
    /// The architecture settings given (a preset gives its stages and channels).
    pub fn architecture(&self) -> Result<Architecture> {
        let p = self.preset.as_deref().map(|p| preset(p, 1, 1)).transpose()?;
        let prior = match self.prior.as_deref() {
            None => None,
            Some("bins") => Some(Prior::Bins),
            Some("delay") => Some(Prior::Delay),
            Some(other) => return Err(bad("prior", other, "bins or delay")),
        };
        let head = match self.head.as_deref() {
            None => None,
            Some("score-volume") => Some(UnetHead::ScoreVolume),
            Some("regression") => Some(UnetHead::Regression),
            Some(other) => return Err(bad("head", other, "score-volume or regression")),
        };
        let lifetime = self.decoder == tcsense_models::runs::network_names::LIFETIME;
        let (input, lifetime_input) = match (self.input.as_deref(), lifetime) {
            (None, _) => (None, None),
            (Some("harmonics"), true) => (None, Some(LifetimeInput::Harmonics)),
            (Some("costs"), true) => (None, Some(LifetimeInput::Costs)),
            (Some(other), true) => return Err(bad("input", other, "harmonics or costs")),
            (Some("backprojection"), false) => (Some(UnetInput::Backprojection), None),
            (Some("matched"), false) => (Some(UnetInput::Matched), None),
            (Some("costs"), false) => (Some(UnetInput::Costs), None),
            (Some(other), false) => return Err(bad("input", other, "backprojection, matched or costs")),
        };
        Ok(Architecture {
            stages: self.stages.or(p.as_ref().map(|c| c.stages)),
            channels: self.channels.or(p.as_ref().map(|c| c.channels)),
            prior,
            returns: self.returns,
            base_width: self.base_width,
            levels: self.levels,
            head,
            input,
            harmonics: self.harmonics,
            points: self.points,
            windows: self.windows.clone(),
            pool_like: self.pool_like,
            instrument_blocks: self.instrument_blocks,
            instrument_mixture: self.instrument_mixture,
            temper: self.temper,
            refine_near_mode: self.refine_near_mode,
            lifetime_input,
        })
    }

    /// The default network of a new run for `m` taps and `t` bins over `range_m` (U-Net).
    fn default_model(&self, m: usize, t: usize, range_m: f64) -> Result<ModelConfig> {
        use tcsense_models::runs::network_names::{ADMM_NET, LIFETIME, UNET};
        Ok(match self.decoder.as_str() {
            ADMM_NET => ModelConfig::AdmmNet(preset(self.preset.as_deref().unwrap_or("cpu"), m, t)?.with_normalize(true)),
            UNET => ModelConfig::Unet(
                UnetConfig::new(m, t, range_m).with_returns(2).with_base_width(8).with_levels(3).with_head(UnetHead::ScoreVolume),
            ),
            LIFETIME => ModelConfig::Lifetime(LifetimeNetConfig::new(m, t).with_harmonics(16).with_base_width(16).with_levels(3)),
            other => return Err(bad("decoder", other, "admm-net, unet or lifetime")),
        })
    }

    fn kind_check(&self, cfg: &TrainConfig) -> Result<()> {
        let name = cfg.run.model.name();
        if name != self.decoder {
            return Err(file_err(&self.output, format!("this is a {name} run; train it with `tcsense train {name}`")));
        }
        Ok(())
    }
}

/// Resolve a request into a run's config, codes and sensor (nothing is written yet).
pub fn prepare(req: &TrainRequest) -> Result<Prepared> {
    // `zoo:NAME` is the zoo's run directory
    let resolved = req.init_from.as_ref().map(|r| tcsense_models::zoo::resolve(&r.to_string_lossy())).transpose()?;
    let req = &TrainRequest { init_from: resolved, ..req.clone() };
    let run_dir = &req.output;
    let arch = req.architecture()?;
    // the network: the run's own on resume; the source run's with init_from; else a config
    // file's or the defaults, shaped by the architecture settings
    let mut cfg = if req.resume {
        // a training that holds the run (even one that has not written its config yet) is
        // what the resume meets, not a missing run
        crate::run_dir::RunLock::free(run_dir)?;
        let saved = run_dir.join(CONFIG_FILE);
        if !saved.exists() {
            return Err(file_err(run_dir, format!("no run to resume ({CONFIG_FILE} missing)")));
        }
        let cfg = TrainConfig::load(&saved)?;
        req.kind_check(&cfg)?;
        arch.check(&cfg.run.model, run_dir)?;
        // a resume trains on the run's own dataset: another one named is refused, not ignored
        if let Some(ds) = &req.dataset {
            let same = |p: &Path| std::fs::canonicalize(p).unwrap_or_else(|_| p.to_path_buf());
            if same(ds) != same(Path::new(&cfg.dataset)) {
                return Err(bad("dataset", &ds.display().to_string(), &format!("the run's own, {} (its {CONFIG_FILE}): a resume continues on the data it started on; start a new run (or fine-tune with --init-from) for other data", cfg.dataset)));
            }
        }
        cfg
    } else {
        let (mut cfg, from_config) = match &req.config {
            Some(p) => (TrainConfig::load(p)?, true),
            None => {
                let ds_path = req
                    .dataset
                    .as_ref()
                    .ok_or_else(|| bad("dataset", "none", "a dataset directory (--dataset), or a config (--config) or --resume"))?;
                let ds = Dataset::open(ds_path)?;
                let codes_path = req.codes.as_ref().ok_or_else(|| bad("codes", "none", "a codes JSON file (--codes)"))?;
                let codes = Codes::load(codes_path)?;
                let t = ds.manifest.bins;
                // depth up to the unambiguous range of the dataset's cycle
                let range_m = tcsense_datasets::grid::C * ds.manifest.bin_width_s * t as f64 / 2.0;
                (TrainConfig::for_dataset(req.default_model(codes.taps(), t, range_m)?, ds_path, &ds), false)
            }
        };
        req.kind_check(&cfg)?;
        match &req.init_from {
            Some(src) => {
                cfg.run.model = setup::model_for_init(src, &cfg.run.model, from_config)?;
                // the input may change on a fine-tune: the weights fit either
                arch.with_input(&mut cfg.run.model, src)?;
            }
            None => {
                let before = cfg.run.model.clone();
                arch.apply(&mut cfg.run.model)?;
                // the delay prior's convolutions run at every bin: a few channels per bin (a
                // config that already has the delay prior keeps its channels)
                if let (ModelConfig::AdmmNet(m), ModelConfig::AdmmNet(b)) = (&mut cfg.run.model, &before) {
                    if m.prior == Prior::Delay && b.prior != Prior::Delay && req.channels.is_none() {
                        m.channels = if matches!(req.preset.as_deref(), Some("lidar" | "flim")) { 8 } else { 4 };
                    }
                }
            }
        }
        cfg
    };
    if let Some(r) = req.sensor_residue {
        cfg.augment = Some(Augmentation { sensor_residue: r, ..cfg.augment.unwrap_or_default() });
    }
    if req.no_augment {
        if req.crop.is_some() {
            return Err(bad("no_augment", "with a crop", "either no augmentation or a crop (a crop is an augmentation)"));
        }
        cfg.augment = None;
    }
    if let Some(crop) = req.crop {
        cfg.augment = Some(Augmentation { crop: Some(crop), ..cfg.augment.unwrap_or_default() });
    }
    for (field, given) in [("signal", req.signal.is_some()), ("ambient", req.ambient.is_some())] {
        if given && req.no_augment {
            return Err(bad(
                "no_augment",
                &format!("with {field}"),
                &format!("either no augmentation or a {field} range (the photon ladder is drawn by the augmentation)"),
            ));
        }
    }
    if let Some(r) = req.signal {
        cfg.augment = Some(Augmentation { signal_fraction: r, ..cfg.augment.unwrap_or_default() });
    }
    if let Some(r) = req.ambient {
        cfg.augment = Some(Augmentation { ambient: r, ..cfg.augment.unwrap_or_default() });
    }
    if let Some(d) = &req.dataset {
        cfg.dataset = d.display().to_string();
    }
    cfg.epochs = req.epochs.unwrap_or(cfg.epochs);
    cfg.learning_rate = req.lr.unwrap_or(cfg.learning_rate);
    if let Some(s) = req.lr_schedule.as_deref() {
        cfg.lr_schedule = match s {
            "constant" => LrSchedule::Constant,
            "cosine" => LrSchedule::COSINE,
            other => return Err(bad("lr_schedule", other, "cosine or constant")),
        };
    }
    cfg.batch_size = req.batch_size.unwrap_or(cfg.batch_size);
    if let Some(l) = req.loss.as_deref() {
        cfg.loss = match l {
            "rmse" => Loss::Rmse,
            "rmse-mae" => Loss::RmseMae,
            "rmse-mae-pixel" => Loss::RmseMaePixel,
            other => return Err(bad("loss", other, "rmse, rmse-mae or rmse-mae-pixel")),
        };
    }
    if let Some(o) = req.objective.as_deref() {
        let found = Objective::ALL.into_iter().find(|k| k.name() == o);
        cfg.objective = Some(found.ok_or_else(|| bad("objective", o, "mse, range or lifetime"))?);
    }
    // a fine-tune continues its source run's loss, where the request does not set it
    if let (Some(src), false, None) = (&req.init_from, req.resume, &req.config) {
        let l = setup::loss_of_run(src)?;
        (cfg.grid_ce_weight, cfg.lifetime_error, cfg.confidence_loss, cfg.grid_nll_cap) =
            (l.grid_ce_weight, l.lifetime_error, l.confidence_loss, l.grid_nll_cap);
        if cfg.run.model.lifetime_grid().is_none() {
            // (a fine-tune onto the harmonics input: its grid's settings do not apply)
            (cfg.grid_ce_weight, cfg.confidence_loss) = (None, None);
        }
        if cfg.run.model.range_grid().is_none() {
            cfg.grid_nll_cap = None;
        }
    }
    if req.grid_ce.is_some() {
        cfg.grid_ce_weight = req.grid_ce;
    }
    if req.grid_nll_cap.is_some() {
        cfg.grid_nll_cap = req.grid_nll_cap;
    }
    if let Some(e) = req.lifetime_error.as_deref() {
        cfg.lifetime_error = Some(match e {
            "ns" => LifetimeError::Ns,
            "log" => LifetimeError::Log,
            other => return Err(bad("lifetime_error", other, "ns or log")),
        });
    }
    if let Some(c) = req.confidence_loss.as_deref() {
        cfg.confidence_loss = Some(match c {
            "weighted" => ConfidenceLoss::Weighted,
            "stalled" => ConfidenceLoss::Stalled,
            other => return Err(bad("confidence_loss", other, "weighted or stalled")),
        });
    } else if !req.resume && cfg.confidence_loss.is_none() && cfg.run.model.lifetime_grid().is_some() {
        // a new lifetime network on a grid trains its confidence (a resumed run keeps its own)
        cfg.confidence_loss = Some(ConfidenceLoss::Weighted);
    }
    if req.no_noise {
        cfg.noise = None;
    }
    // a measured matrix replaces the synthetic sensor (a recalibrated instrument)
    let mut measured = None;
    if let Some(desc) = req.irf.as_deref() {
        match parse_irf_default(desc, "irf").map_err(|_| bad("irf", desc, "ideal, physical or a measured matrix A.npy"))? {
            IrfSpec::Measured(p) => measured = Some(MeasuredSensor::Matrix(p)),
            IrfSpec::Model(irf) => (cfg.run.irf, cfg.run.measured) = (irf, false),
        }
    }
    if let Some(dir) = &req.calibration {
        if measured.is_some() {
            return Err(bad(
                "calibration",
                &dir.display().to_string(),
                "either a calibration or a measured matrix (irf A.npy): both give the sensor matrix",
            ));
        }
        measured = Some(MeasuredSensor::Calibration(dir.clone()));
    }
    if let Some(m) = &measured {
        setup::use_measured_sensor(&mut cfg, m, req.resume)?;
    }
    if req.max_train.is_some() {
        cfg.max_train_items = req.max_train;
    }
    if req.max_val.is_some() {
        cfg.max_val_items = req.max_val;
    }
    cfg.seed = req.seed.unwrap_or(cfg.seed);
    let codes = setup::run_codes(run_dir, req.codes.as_deref(), req.resume)?;
    if let Some(r) = &req.init_from {
        cfg.init_from = Some(r.display().to_string());
    }
    if req.learn_codes && !req.resume {
        let given = req.tap_constraint || req.hamming.is_some() || req.window.is_some();
        let constraints =
            if given { Constraints { tap: req.tap_constraint, hamming: req.hamming, window: req.window } } else { codes.constraints };
        let mut lc = LearnCodes::new(constraints, cfg.epochs);
        lc.relaxed_epochs = req.relaxed_epochs.unwrap_or(lc.relaxed_epochs);
        lc.codes_lr = req.codes_lr.unwrap_or(lc.codes_lr);
        lc.alias_weight = req.alias_weight.unwrap_or(lc.alias_weight);
        lc.alias_threshold = req.alias_threshold.unwrap_or(lc.alias_threshold);
        cfg.learn_codes = Some(lc);
    }
    if codes.taps() != cfg.run.model.taps() {
        return Err(bad("codes", &format!("{} taps", codes.taps()), &format!("the model's M = {}", cfg.run.model.taps())));
    }
    // every setting checked before anything is said of it (a summary of 10¹¹ levels would
    // count their FLOPs) or written
    cfg.validate()?;
    Ok(Prepared { cfg, codes, measured, output: run_dir.clone(), resume: req.resume })
}

/// Run a prepared training on `device`: the measured sensor written into the run first (checked
/// against the codes), then [`crate::train_on`] (resumable, `cancel` stops it with the last
/// checkpoint kept).
///
/// A new run that diverges before its first checkpoint leaves nothing behind: its directory,
/// made by this call, is removed (there is nothing to resume from).
pub fn run(p: &Prepared, device: &Device, progress: &dyn Progress, cancel: &AtomicBool) -> Result<Vec<EpochMetrics>> {
    let fresh = !p.resume && !p.output.exists();
    let res = (|| {
        if let Some(m) = &p.measured {
            setup::write_measured_sensor(&p.cfg, &p.codes, m, &p.output)?;
        }
        crate::train_on(&p.cfg, &p.codes, &p.output, p.resume, device, progress, cancel)
    })();
    match res {
        Err(TrainError::Diverged { loss, epoch, step, .. }) if fresh && discard_unstarted(&p.output) => {
            Err(TrainError::Diverged { loss, epoch, step, kept: false })
        }
        res => res,
    }
}

/// Remove run directory `run` if no checkpoint was ever written into it; whether it was.
fn discard_unstarted(run: &Path) -> bool {
    matches!(crate::run_dir::latest_checkpoint(run), Ok(None)) && std::fs::remove_dir_all(run).is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run without a checkpoint is removed (what a fresh run that diverged wrote); one with
    /// a checkpoint, or a half-written one, is kept.
    #[test]
    fn only_a_run_without_a_checkpoint_is_discarded() {
        let t = tempfile::tempdir().unwrap();
        let run = t.path().join("r");
        std::fs::create_dir_all(&run).unwrap();
        std::fs::write(run.join(CONFIG_FILE), "{}").unwrap();
        assert!(discard_unstarted(&run) && !run.exists());
        let ckpt = run.join(crate::run_dir::CHECKPOINT_DIR);
        std::fs::create_dir_all(&ckpt).unwrap();
        assert!(!discard_unstarted(&run) && run.exists(), "an incomplete checkpoint is kept for the user to see");
        std::fs::write(ckpt.join(crate::run_dir::STATE_FILE), "{}").unwrap();
        assert!(!discard_unstarted(&run) && ckpt.exists());
    }
}
