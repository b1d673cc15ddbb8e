//! The training config, `RUN/config.json`: the network and sensor model of the run
//! ([`RunSpec`], what inference reads back) plus the training settings (paper Table 3).

use serde::{Deserialize, Serialize};
use std::path::Path;
use tcsense_models::net::Prediction;
use tcsense_models::runs::{ModelConfig, RunSpec};
use tcsense_sensor::{Irf, NoiseParams, Sampling};

use crate::augment::Augmentation;
use crate::{Result, TrainError};

/// Training loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Loss {
    /// `sqrt(mean((x̂ − x)²))` (FLIm).
    Rmse,
    /// RMSE + `mean(|x̂ − x|)` (LiDAR).
    RmseMae,
    /// RMSE + MAE of the cube, plus the same of every pixel's waveform divided by its own
    /// peak ([`crate::loss::pixel_weights`]): dim pixels count for the shape of their return as
    /// much as bright ones (LiDAR decoders whose range maps matter in dark parts of a scene).
    RmseMaePixel,
}

/// What a run is trained for (`tcsense train --objective`): the product its users read.
///
/// A cube decoder (the ADMM-Net) is trained on the cube's loss
/// ([`Loss`]) alone under `mse`; under `range` or `lifetime` it adds
/// [`crate::loss::waveform_emd`]: the earth mover's distance between every pixel's predicted
/// and true waveform, each normalised to unit sum. For one return it is the range error in
/// bins; for a decay of the same onset it is the lifetime error in bins (the distance between
/// two exponentials' distributions is the difference of their means). A depth network's loss
/// is its range already and a lifetime network's its lifetime: they take `range` and
/// `lifetime` respectively and nothing else. With `--learn-codes` the product's loss reaches
/// the codes through the decoder and `A(θ)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Objective {
    /// The cube's loss ([`Loss`]) alone.
    Mse,
    /// Ranges: the cube's loss plus the waveforms' earth mover's distance over the pixels with
    /// a return (LiDAR).
    Range,
    /// Lifetimes: the cube's loss plus the waveforms' earth mover's distance over the pixels
    /// with a fluorophore (FLIm).
    Lifetime,
}

impl Objective {
    /// Every objective, in the order the command line lists them.
    pub const ALL: [Objective; 3] = [Objective::Mse, Objective::Range, Objective::Lifetime];

    /// The name `--objective` and `config.json` spell.
    pub fn name(self) -> &'static str {
        match self {
            Objective::Mse => "mse",
            Objective::Range => "range",
            Objective::Lifetime => "lifetime",
        }
    }
}

/// How a lifetime network's error in its lifetimes (`τ_m`, `τ₁`, `τ₂`) is measured in its loss.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum LifetimeError {
    /// The absolute error in ns (configs written before the choice).
    #[default]
    Ns,
    /// The absolute error of `ln τ`, times [`crate::loss::LOG_ERROR_NS`] (an error of 1 %
    /// costs what 0.02 ns does in `ns`): a relative error, so that the dimmest items and the
    /// longest lifetimes, whose errors in ns are largest, do not make up the loss.
    Log,
}

/// How a lifetime network on a grid learns its confidence of a fluorophore: the binary
/// cross-entropy that weighs a missed fluorophore [`crate::loss::COVERAGE_WEIGHT`] times a
/// false one, written one of two ways.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ConfidenceLoss {
    /// `w·m·softplus(−l) + (1 − m)·softplus(l)` with `softplus(x) = relu(x) + ln(1 + e^−|x|)`:
    /// at `l = 0` both parts' gradients are 0 in burn, so a head that starts at 0 never learns
    /// its confidence (½ everywhere: every pixel gets a lifetime). How the networks of configs
    /// written before the choice were trained; kept so that they replay.
    Stalled,
    /// The same value as `(w·m + 1 − m)·softplus(l) − w·m·l` with burn's `ln(1 + eˡ)`, whose
    /// gradient at 0 is `(1 − m)/2 − w·m/2`: the confidence trains (new runs).
    Weighted,
}

/// The largest batch taken (items a step; a batch larger than the training split is the split).
pub const MAX_BATCH: usize = 65_536;

/// How the learning rate moves over a run's optimiser steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case", tag = "kind")]
pub enum LrSchedule {
    /// `learning_rate` on every step (the paper's Table 3; configs written before schedules).
    #[default]
    Constant,
    /// Half a cosine from `learning_rate` at the first step down to
    /// `final_fraction · learning_rate` at the run's last step (`epochs × steps per epoch`),
    /// after a linear warm-up over `warmup_steps`. Short budgets end on small steps instead of
    /// on batch-2 noise.
    Cosine {
        /// Fraction of the learning rate reached at the last step, in `[0, 1]`.
        final_fraction: f64,
        /// Steps of linear warm-up from 0 (0: none).
        warmup_steps: usize,
    },
}

impl LrSchedule {
    /// The cosine schedule of new runs: down to 1 % of the rate, 50 warm-up steps.
    pub const COSINE: LrSchedule = LrSchedule::Cosine { final_fraction: 0.01, warmup_steps: 50 };

    /// The learning rate of optimiser step `step` (1-based) of `total` steps, with peak `lr`.
    pub fn rate(&self, lr: f64, step: u64, total: u64) -> f64 {
        match *self {
            LrSchedule::Constant => lr,
            LrSchedule::Cosine { final_fraction, warmup_steps } => {
                let warm = warmup_steps as u64;
                if step <= warm && warm > 0 {
                    return lr * step as f64 / warm as f64;
                }
                let span = total.saturating_sub(warm).max(1) as f64;
                let p = ((step.saturating_sub(warm)) as f64 / span).clamp(0.0, 1.0);
                lr * (final_fraction + (1.0 - final_fraction) * 0.5 * (1.0 + (std::f64::consts::PI * p).cos()))
            }
        }
    }

    fn validate(&self) -> Result<()> {
        match *self {
            LrSchedule::Cosine { final_fraction, .. } if !(0.0..=1.0).contains(&final_fraction) => Err(TrainError::InvalidParam {
                field: "lr_schedule.final_fraction",
                got: final_fraction.to_string(),
                expected: "a fraction in [0, 1]".into(),
            }),
            _ => Ok(()),
        }
    }
}

/// The noise every training run adds to its simulated measurements unless told otherwise:
/// full well 20 000 e⁻, read noise σ = 40 e⁻, brightest tap at 80 % of full well, no ADC.
pub const TRAINING_NOISE: NoiseParams = NoiseParams { full_well_e: 20_000.0, read_noise_e: 40.0, signal_fraction: 0.8, adc_bits: 0 };

/// Everything that defines a run (saved as `config.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// The network (`decoder` + `model`), sampling and IRF: what inference needs.
    #[serde(flatten)]
    pub run: RunSpec,
    pub epochs: usize,
    pub batch_size: usize,
    pub learning_rate: f64,
    /// How the learning rate moves over the run (absent in older configs: constant).
    #[serde(default)]
    pub lr_schedule: LrSchedule,
    pub loss: Loss,
    /// What the run is trained for (absent: the network's own loss, `mse` for cube decoders).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub objective: Option<Objective>,
    pub seed: u64,
    /// Noise added to the simulated measurements (`None`: noise-free).
    pub noise: Option<NoiseParams>,
    /// Dataset directory the run was trained on.
    pub dataset: String,
    /// Use at most this many training / validation items.
    pub max_train_items: Option<usize>,
    pub max_val_items: Option<usize>,
    /// Training-time augmentation (`None`, and in configs written before it existed: off).
    #[serde(default)]
    pub augment: Option<Augmentation>,
    /// Deep sensing: learn the codes with the decoder (`None`: the codes are fixed).
    #[serde(default)]
    pub learn_codes: Option<crate::deep_sensing::LearnCodes>,
    /// Start from the weights of this run (fine-tuning on new codes or a recalibrated sensor).
    #[serde(default)]
    pub init_from: Option<String>,
    /// A lifetime network on a grid: the weight of its log-posterior's cross-entropy in the
    /// loss (`None`, and in configs written before it: [`crate::loss::GRID_CE_WEIGHT`]); 0
    /// trains the posterior's mean alone, which a sharp but wrong likelihood does not punish
    /// more than its error.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid_ce_weight: Option<f64>,
    /// A lifetime network: how its lifetimes' error is measured (`None`, and in configs
    /// written before it: in ns).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lifetime_error: Option<LifetimeError>,
    /// A lifetime network on a grid: how its confidence is trained (`None`, and in configs
    /// written before it: [`ConfidenceLoss::Stalled`]; new runs: `Weighted`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub confidence_loss: Option<ConfidenceLoss>,
    /// A network on a range grid (the U-Net's score volume): the cross-entropy in nats above
    /// which a pixel's loss is held at that value (`None`: not held). A pixel whose likelihood
    /// is sharp and wrong (pooled across an edge, a wall that wraps the cycle) then costs its
    /// cap and gives no gradient, instead of bending the learned prior of every pixel to it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grid_nll_cap: Option<f64>,
}

impl TrainConfig {
    /// One line for people: the network, the schedule, the loss, the noise and the augmentation.
    pub fn summary(&self) -> String {
        let network = match &self.run.model {
            ModelConfig::AdmmNet(m) => format!("ADMM-Net S = {}, CN = {}, M = {}, T = {}", m.stages, m.channels, m.taps, m.bins),
            ModelConfig::Lifetime(m) => format!(
                "lifetime decoder: {}, U-Net base width {}, {} levels, M = {}, T = {}, {:.2} GFLOP per 188x212 frame",
                match m.input {
                    tcsense_models::LifetimeInput::Harmonics => format!("{} harmonics", m.harmonics),
                    tcsense_models::LifetimeInput::Costs =>
                        format!(
                            "the fit's evidence on {} lifetimes {}–{} ns (pooled by {}){}",
                            m.points,
                            m.tau_range_ns[0],
                            m.tau_range_ns[1],
                            m.pool,
                            if m.windows.is_empty() { String::new() } else { format!(" with wider windows {:?}", m.windows) }
                        ) + &if m.pool_like == 0 {
                            String::new()
                        } else {
                            format!(", its window pooled by likeness over {0}×{0}", m.pool_like)
                        } + &match m.instrument_blocks {
                            0 if m.instrument_mixture => ", a dim frame's instrument under the frame's mixture".to_string(),
                            0 => ", the instrument on superpixels as the photons ask (decoded under the frame's mixture)".to_string(),
                            1 => ", the instrument on every pixel".to_string(),
                            s => format!(", the instrument on superpixels of {s}×{s} blocks"),
                        } + if m.temper { ", its log-likelihood at a learned temperature" } else { "" }
                            + if m.refine_near_mode { ", its mode refined in the taps within a point of the fit's" } else { "" },
                },
                m.base_width,
                m.levels,
                m.taps,
                m.bins,
                m.flops(188, 212) / 1e9
            ),
            ModelConfig::Unet(m) => format!(
                "{} + U-Net K = {}, base width {}, {} levels, M = {}, T = {}, range {:.2} m, {:.2} GFLOP per 188x212 frame",
                match m.input {
                    tcsense_models::UnetInput::Matched => "matched filters".to_string(),
                    tcsense_models::UnetInput::Costs =>
                        format!("the range fit's evidence on {} candidates (pooled by {})", m.candidates(), m.pool)
                            + &if m.pool_like == 0 {
                                String::new()
                            } else {
                                format!(", its window pooled by likeness over {0}×{0}", m.pool_like)
                            },
                    tcsense_models::UnetInput::Backprojection => "Aᵀ".to_string(),
                },
                m.returns,
                m.base_width,
                m.levels,
                m.taps,
                m.bins,
                m.range_m,
                m.flops(188, 212) / 1e9
            ),
        };
        format!(
            "{network}; {} epochs, batch {}, lr {} ({}), loss {:?}{}, noise {}, augmentation {}",
            self.epochs,
            self.batch_size,
            self.learning_rate,
            match self.lr_schedule {
                LrSchedule::Constant => "constant".to_string(),
                LrSchedule::Cosine { final_fraction, warmup_steps } => format!("cosine to {final_fraction}×, {warmup_steps} warm-up steps"),
            },
            self.loss,
            match self.objective {
                Some(o @ (Objective::Range | Objective::Lifetime)) if self.run.model.prediction() == Prediction::Cube =>
                    format!(" + the waveforms' earth mover's distance (objective {})", o.name()),
                _ => String::new(),
            } + &self.grid_ce_weight.map_or(String::new(), |w| format!(", the grid's cross-entropy at {w}"))
                + if self.lifetime_error == Some(LifetimeError::Log) { ", the lifetimes' error on ln τ" } else { "" }
                + if self.confidence_loss == Some(ConfidenceLoss::Weighted) { ", the confidence's cross-entropy weighted" } else { "" }
                + &self.grid_nll_cap.map_or(String::new(), |c| format!(", each pixel's cross-entropy held at {c} nats")),
            if self.noise.is_some() { "shot + read" } else { "off" },
            match &self.augment {
                None => "off".to_string(),
                Some(g) => format!(
                    "shifts {}, flips {}, crop {}, brightness {:?}, signal {:?} of full well{}{}",
                    g.time_shift,
                    g.flips,
                    g.crop.map_or("none".into(), |[h, w]| format!("{h}x{w}")),
                    g.brightness,
                    g.signal_fraction,
                    if g.ambient[1] > 0.0 { format!(", ambient {:?} of the signal (1/SBR)", g.ambient) } else { String::new() },
                    if g.sensor_residue.iter().any(|&v| v != 0.0) {
                        format!(", sensor residue (tap gain, PRNU, dark) {:?}", g.sensor_residue)
                    } else {
                        String::new()
                    }
                ),
            }
        )
    }

    /// How a lifetime network's loss is taken: the config's choices, and where it names none,
    /// those of configs written before them ([`crate::loss::LifetimeTerms::default`]).
    pub fn lifetime_terms(&self) -> crate::loss::LifetimeTerms {
        let before = crate::loss::LifetimeTerms::default();
        crate::loss::LifetimeTerms {
            ce_weight: self.grid_ce_weight.unwrap_or(before.ce_weight),
            error: self.lifetime_error.unwrap_or(before.error),
            confidence: self.confidence_loss.unwrap_or(before.confidence),
        }
    }

    /// Defaults of the paper's Table 3 for a model config.
    pub fn new(model: ModelConfig, dataset: &Path, loss: Loss, sampling: Sampling) -> Self {
        TrainConfig {
            run: RunSpec { model, sampling, irf: Irf::Ideal, measured: false },
            epochs: 10,
            batch_size: 2,
            learning_rate: 1e-3,
            lr_schedule: LrSchedule::Constant,
            loss,
            objective: None,
            seed: 0,
            noise: Some(TRAINING_NOISE),
            dataset: dataset.display().to_string(),
            max_train_items: None,
            max_val_items: None,
            augment: None,
            learn_codes: None,
            init_from: None,
            grid_ce_weight: None,
            lifetime_error: None,
            confidence_loss: None,
            grid_nll_cap: None,
        }
    }

    /// A new run of `model` on the dataset at `path`: the loss of its kind (RMSE + MAE for
    /// LiDAR cubes, RMSE for FLIm; depth networks use their own), its sampling, the default
    /// augmentation and the cosine learning-rate schedule.
    pub fn for_dataset(model: ModelConfig, path: &Path, ds: &tcsense_datasets::Dataset) -> Self {
        let loss = if ds.manifest.kind == tcsense_datasets::store::Kind::Flim { Loss::Rmse } else { Loss::RmseMae };
        let mut cfg = TrainConfig::new(model, path, loss, ds.manifest.grid.sampling);
        cfg.augment = Some(Augmentation::default());
        cfg.lr_schedule = LrSchedule::COSINE;
        cfg
    }

    /// Read a config file (a run's `config.json` or one given to `train --config`); configs
    /// written before the `decoder` field are ADMM-Net configs.
    /// Unknown fields and invalid settings are refused with the file named.
    pub fn load(path: &Path) -> Result<Self> {
        let in_file = |msg: String| TrainError::File { path: path.to_path_buf(), msg };
        let v = tcsense_models::runs::read_config_json(path)?;
        let cfg: TrainConfig = serde_json::from_value(v.clone()).map_err(|e| in_file(format!("malformed training config: {e}")))?;
        tcsense_sensor::json::reject_unknown_keys(&v, &tcsense_sensor::json::keys_of(&cfg)).map_err(in_file)?;
        cfg.validate().map_err(|e| in_file(e.to_string()))?;
        Ok(cfg)
    }

    /// Check the settings before any work starts.
    pub fn validate(&self) -> Result<()> {
        let bad =
            |field: &'static str, got: String, expected: &str| Err(TrainError::InvalidParam { field, got, expected: expected.into() });
        if let Some(w) = self.grid_ce_weight {
            if !(w.is_finite() && (0.0..=10.0).contains(&w)) {
                return bad("grid_ce_weight", w.to_string(), "a weight from 0 to 10");
            }
            if self.run.model.lifetime_grid().is_none() {
                return bad(
                    "grid_ce_weight",
                    format!("{w} for {}", self.run.model.name()),
                    "a lifetime network on the fit's evidence (train lifetime --input costs): the weight is of its grid's cross-entropy",
                );
            }
        }
        if let Some(c) = self.grid_nll_cap {
            if !(c.is_finite() && (0.1..=100.0).contains(&c)) {
                return bad("grid_nll_cap", c.to_string(), "a cross-entropy from 0.1 to 100 nats");
            }
            if self.run.model.range_grid().is_none() {
                return bad(
                    "grid_nll_cap",
                    format!("{c} for {}", self.run.model.name()),
                    "a U-Net on a range grid (train unet --head score-volume): the cap is of its grid's cross-entropy",
                );
            }
        }
        if let Some(e) = self.lifetime_error {
            if !matches!(self.run.model, ModelConfig::Lifetime(_)) {
                return bad("lifetime_error", format!("{e:?} for {}", self.run.model.name()), "a lifetime network (train lifetime)");
            }
        }
        if let Some(c) = self.confidence_loss {
            if self.run.model.lifetime_grid().is_none() {
                return bad(
                    "confidence_loss",
                    format!("{c:?} for {}", self.run.model.name()),
                    "a lifetime network on the fit's evidence (train lifetime --input costs): the choice is of its grid's confidence",
                );
            }
        }
        self.run.model.validate()?;
        if self.epochs == 0 {
            return bad("epochs", "0".into(), "at least 1");
        }
        if !(1..=MAX_BATCH).contains(&self.batch_size) {
            return bad("batch_size", self.batch_size.to_string(), "1 to 65 536 items a step");
        }
        if !(self.learning_rate.is_finite() && self.learning_rate > 0.0) {
            return bad("learning_rate", self.learning_rate.to_string(), "a positive number");
        }
        self.lr_schedule.validate()?;
        match &self.run.model {
            ModelConfig::AdmmNet(m) if m.stages == 0 || m.channels == 0 => {
                return bad("model", format!("{} stages, {} channels", m.stages, m.channels), "at least one stage and one channel");
            }
            ModelConfig::AdmmNet(_) => {}
            ModelConfig::Unet(m) => {
                let fits = m.base_width > 0
                    && (1..=6).contains(&m.levels)
                    && (1..=2).contains(&m.returns)
                    && m.range_m.is_finite()
                    && m.range_m > 0.0;
                if !fits {
                    return bad(
                        "model",
                        format!("base width {}, {} levels, {} returns, range {} m", m.base_width, m.levels, m.returns, m.range_m),
                        "base width ≥ 1, 1–6 levels, 1 or 2 returns, a positive range",
                    );
                }
            }
            ModelConfig::Lifetime(m) => {
                if let Err(e) = m.validate() {
                    return bad("model", e, "a lifetime grid 0 < lo < hi, 3–1024 points, a pool of 1 to points");
                }
            }
        }
        if let Some(n) = &self.noise {
            n.validate()?;
        }
        if let Some(g) = &self.augment {
            g.validate_ranges()?;
        }
        if let Some(o) = self.objective {
            let fits = match self.run.model.prediction() {
                Prediction::Cube => true,
                Prediction::Depth => o == Objective::Range,
                Prediction::Lifetime => o == Objective::Lifetime,
            };
            if !fits {
                return bad(
                    "objective",
                    o.name().into(),
                    &format!("the {} network's own product (a depth network: range; a lifetime network: lifetime; a cube decoder: mse, range or lifetime)", self.run.model.name()),
                );
            }
        }
        if let Some(lc) = &self.learn_codes {
            lc.validate(self.epochs)?;
            // a network on the fit's evidence pooled by likeness (U-Net, lifetime)
            let pooled = match &self.run.model {
                ModelConfig::Lifetime(c) => ("a lifetime network", c.pool_like),
                ModelConfig::Unet(c) => ("a U-Net", c.pool_like),
                ModelConfig::AdmmNet(_) => ("", 0),
            };
            if pooled.1 != 0 {
                return bad(
                    "learn_codes",
                    format!("{} pooled by likeness over {1}×{1}", pooled.0, pooled.1),
                    "the fit's own window only: the evidence's differentiable copy does not pool by likeness yet",
                );
            }
            if let ModelConfig::Lifetime(c) = &self.run.model {
                if !c.windows.is_empty() {
                    return bad(
                        "learn_codes",
                        format!("a lifetime network with wider windows {:?}", c.windows),
                        "the fit's own window only: the evidence's differentiable copy has no wider windows yet",
                    );
                }
            }
            if self.run.measured {
                return bad("learn_codes", "a measured sensor matrix".into(), "a synthetic sensor (codes are learned through the IRF model; fine-tune on a measured matrix afterwards with --init-from)");
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tcsense_models::runs::TRAINING_KEYS;
    use tcsense_models::AdmmNetConfig;

    /// A cube decoder takes any objective; a depth network only its range, and a config
    /// without one is written as before it existed.
    #[test]
    fn the_objective_matches_the_network() {
        let admm = TrainConfig::new(ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8)), Path::new("ds"), Loss::Rmse, Sampling::Oversample(1));
        assert!(!serde_json::to_string(&admm).expect("json").contains("objective"));
        for o in Objective::ALL {
            assert!(TrainConfig { objective: Some(o), ..admm.clone() }.validate().is_ok(), "{o:?}");
            // the name is serde's
            assert_eq!(serde_json::to_value(o).expect("json"), o.name());
        }
        let unet = TrainConfig::new(
            ModelConfig::Unet(tcsense_models::UnetConfig::new(4, 8, 10.0)),
            Path::new("ds"),
            Loss::RmseMae,
            Sampling::Oversample(1),
        );
        assert!(TrainConfig { objective: Some(Objective::Range), ..unet.clone() }.validate().is_ok());
        for o in [Objective::Mse, Objective::Lifetime] {
            let e = TrainConfig { objective: Some(o), ..unet.clone() }.validate().expect_err("refused").to_string();
            assert!(e.contains("objective") && e.contains(o.name()), "{e}");
        }
    }

    /// The weight of a lifetime grid's cross-entropy: only for a lifetime network on a grid,
    /// from 0 to 10, and a config without one is written as before it existed.
    #[test]
    fn the_grid_cross_entropy_weight_is_a_lifetime_grid_networks() {
        use tcsense_models::{LifetimeInput, LifetimeNetConfig};
        let grid = TrainConfig::new(
            ModelConfig::Lifetime(LifetimeNetConfig::new(4, 64).with_input(LifetimeInput::Costs)),
            Path::new("ds"),
            Loss::Rmse,
            Sampling::Heterodyne(4),
        );
        assert!(!serde_json::to_string(&grid).expect("json").contains("grid_ce_weight"));
        for w in [0.0, 0.2, 10.0] {
            assert!(TrainConfig { grid_ce_weight: Some(w), ..grid.clone() }.validate().is_ok(), "{w}");
        }
        for w in [-0.1, 10.5, f64::NAN] {
            let e = TrainConfig { grid_ce_weight: Some(w), ..grid.clone() }.validate().expect_err("refused").to_string();
            assert!(e.contains("grid_ce_weight") && e.contains("0 to 10"), "{e}");
        }
        let harmonics = TrainConfig {
            run: RunSpec { model: ModelConfig::Lifetime(LifetimeNetConfig::new(4, 64)), ..grid.run.clone() },
            grid_ce_weight: Some(0.0),
            ..grid.clone()
        };
        let e = harmonics.validate().expect_err("refused").to_string();
        assert!(e.contains("grid_ce_weight") && e.contains("--input costs"), "{e}");
    }

    /// The cap on a pixel's cross-entropy: only for a U-Net on a range grid, from 0.1 to 100
    /// nats, and a config without one is written as before it existed.
    #[test]
    fn the_grid_cross_entropy_cap_is_a_range_grid_networks() {
        use tcsense_models::{UnetConfig, UnetHead, UnetInput};
        let grid = TrainConfig::new(
            ModelConfig::Unet(UnetConfig { input: UnetInput::Costs, head: UnetHead::ScoreVolume, ..UnetConfig::new(4, 8, 10.0) }),
            Path::new("ds"),
            Loss::Rmse,
            Sampling::Heterodyne(4),
        );
        assert!(!serde_json::to_string(&grid).expect("json").contains("grid_nll_cap"));
        for c in [0.1, 6.0, 100.0] {
            let capped = TrainConfig { grid_nll_cap: Some(c), ..grid.clone() };
            assert!(capped.validate().is_ok(), "{c}: {:?}", capped.validate());
            assert!(capped.summary().contains(&format!("held at {c} nats")), "{}", capped.summary());
        }
        for c in [0.0, 101.0, f64::NAN, f64::INFINITY] {
            let e = TrainConfig { grid_nll_cap: Some(c), ..grid.clone() }.validate().expect_err("refused").to_string();
            assert!(e.contains("grid_nll_cap") && e.contains("0.1 to 100"), "{e}");
        }
        for model in [ModelConfig::Unet(UnetConfig::new(4, 8, 10.0)), ModelConfig::Lifetime(tcsense_models::LifetimeNetConfig::new(4, 64))]
        {
            let e = TrainConfig { run: RunSpec { model, ..grid.run.clone() }, grid_nll_cap: Some(6.0), ..grid.clone() }
                .validate()
                .expect_err("refused")
                .to_string();
            assert!(e.contains("grid_nll_cap") && e.contains("score-volume"), "{e}");
        }
    }

    /// The lifetimes' error is a lifetime network's choice and the confidence's loss a grid
    /// network's; configs without them are written (and so replay) as before they existed.
    #[test]
    fn the_lifetime_loss_choices_are_lifetime_networks_and_absent_when_not_given() {
        use tcsense_models::{LifetimeInput, LifetimeNetConfig};
        let grid = TrainConfig::new(
            ModelConfig::Lifetime(LifetimeNetConfig::new(4, 64).with_input(LifetimeInput::Costs)),
            Path::new("ds"),
            Loss::Rmse,
            Sampling::Heterodyne(4),
        );
        let json = serde_json::to_string(&grid).expect("json");
        assert!(!json.contains("lifetime_error") && !json.contains("confidence_loss"), "{json}");
        let chosen =
            TrainConfig { lifetime_error: Some(LifetimeError::Log), confidence_loss: Some(ConfidenceLoss::Weighted), ..grid.clone() };
        assert!(chosen.validate().is_ok());
        let json = serde_json::to_value(&chosen).expect("json");
        assert_eq!((json["lifetime_error"].as_str(), json["confidence_loss"].as_str()), (Some("log"), Some("weighted")));
        let harmonics = TrainConfig {
            run: RunSpec { model: ModelConfig::Lifetime(LifetimeNetConfig::new(4, 64)), ..grid.run.clone() },
            ..grid.clone()
        };
        assert!(TrainConfig { lifetime_error: Some(LifetimeError::Log), ..harmonics.clone() }.validate().is_ok());
        let e = TrainConfig { confidence_loss: Some(ConfidenceLoss::Stalled), ..harmonics }.validate().expect_err("refused").to_string();
        assert!(e.contains("confidence_loss") && e.contains("--input costs"), "{e}");
        let admm = TrainConfig::new(ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8)), Path::new("ds"), Loss::Rmse, Sampling::Oversample(1));
        let e = TrainConfig { lifetime_error: Some(LifetimeError::Ns), ..admm }.validate().expect_err("refused").to_string();
        assert!(e.contains("lifetime_error") && e.contains("lifetime network"), "{e}");
    }

    /// Inference checks a run's config against `RunSpec`'s fields and `TRAINING_KEYS`: the
    /// list must stay equal to what `TrainConfig` adds.
    #[test]
    fn training_keys_are_the_fields_training_adds() {
        let mut cfg =
            TrainConfig::new(ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8)), Path::new("ds"), Loss::Rmse, Sampling::Oversample(1));
        // (written only when given)
        cfg.objective = Some(Objective::Range);
        cfg.grid_ce_weight = Some(0.0);
        cfg.lifetime_error = Some(LifetimeError::Log);
        cfg.confidence_loss = Some(ConfidenceLoss::Weighted);
        cfg.grid_nll_cap = Some(4.0);
        let all = tcsense_sensor::json::keys_of(&cfg);
        let spec = tcsense_sensor::json::keys_of(&cfg.run);
        let mut extra: Vec<&str> = all.iter().filter(|k| !spec.contains(k)).map(String::as_str).collect();
        let mut expected = TRAINING_KEYS.to_vec();
        extra.sort_unstable();
        expected.sort_unstable();
        assert_eq!(extra, expected);
    }

    #[test]
    fn cosine_schedule_warms_up_then_decays_to_its_final_fraction() {
        let s = LrSchedule::Cosine { final_fraction: 0.01, warmup_steps: 10 };
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(s.rate(1e-3, 1, 110), 1e-4));
        assert!(close(s.rate(1e-3, 5, 110), 5e-4));
        assert!(close(s.rate(1e-3, 10, 110), 1e-3));
        // halfway through the decay: the mean of the two ends
        assert!(close(s.rate(1e-3, 60, 110), 1e-3 * (0.01 + 0.99 * 0.5)));
        assert!(close(s.rate(1e-3, 110, 110), 1e-5));
        // monotone after the warm-up
        let rates: Vec<f64> = (10..=110).map(|k| s.rate(1e-3, k, 110)).collect();
        assert!(rates.windows(2).all(|w| w[1] < w[0]));
        assert!(close(LrSchedule::Constant.rate(2e-3, 77, 110), 2e-3));
        let bad = TrainConfig {
            lr_schedule: LrSchedule::Cosine { final_fraction: 1.5, warmup_steps: 0 },
            ..TrainConfig::new(ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8)), Path::new("ds"), Loss::Rmse, Sampling::Oversample(1))
        };
        assert!(bad.validate().is_err());
        // a config from before schedules reads as constant
        let mut v = serde_json::to_value(TrainConfig::new(
            ModelConfig::AdmmNet(AdmmNetConfig::new(4, 8)),
            Path::new("ds"),
            Loss::Rmse,
            Sampling::Oversample(1),
        ))
        .unwrap();
        v.as_object_mut().unwrap().remove("lr_schedule");
        assert_eq!(serde_json::from_value::<TrainConfig>(v).unwrap().lr_schedule, LrSchedule::Constant);
    }
}
