//! Run directories (CONVENTIONS habit 8): what `tcsense train` writes and every later command
//! takes. A run directory opens as a [`Decoder`] with one call, [`open`], without the
//! training crate.
//!
//! ```text
//! RUN/config.json     the run's config: {"decoder": "admm-net", "model": {…}, "sampling", "irf", …}
//! RUN/codes.json      the exposure codes it was trained with
//! RUN/model.bpk       the latest weights (burnpack)
//! RUN/metrics.csv     one row per epoch            (written by tcsense-train)
//! RUN/checkpoint/     weights, optimiser, progress (written by tcsense-train)
//! ```
//!
//! The network is rebuilt from its config and the weights loaded into it:
//! `config.init(&device).load_file(RUN/model)` (habit 1). Runs written before the `decoder`
//! field existed are ADMM-Net runs and open as such ([`upgrade_config`]).

use burn::module::Module;
use burn::tensor::Device;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tcsense_sensor::{Codes, Irf, Sampling, Sensor, SensorModel};

use crate::admm::{AdmmNet, AdmmNetConfig};
use crate::decoder::Decoder;
use crate::lifetime::{LifetimeNet, LifetimeNetConfig};
use crate::net::NetDecoder;
use crate::unet::{Unet, UnetConfig};
use crate::{ModelError, Result};

/// The run's config, `RUN/config.json`.
pub const CONFIG_FILE: &str = "config.json";
/// The run's exposure codes, `RUN/codes.json`.
pub const CODES_FILE: &str = "codes.json";
/// The latest weights, `RUN/model.bpk` (burn appends the extension to this stem).
pub const WEIGHTS_STEM: &str = "model";
/// The file name burn writes for [`WEIGHTS_STEM`].
pub const WEIGHTS_FILE: &str = "model.bpk";

/// The network of a run and its hyper-parameters, stored as `"decoder"` (the tag) and
/// `"model"` (the config) in `config.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "decoder", content = "model", rename_all = "kebab-case")]
pub enum ModelConfig {
    /// ADMM-Net ([`crate::admm`]).
    AdmmNet(AdmmNetConfig),
    /// Aᵀ + U-Net ([`crate::unet`]).
    Unet(UnetConfig),
    /// The lifetime decoder ([`crate::lifetime`]).
    Lifetime(LifetimeNetConfig),
}

/// The names of the trainable networks, as `config.json`'s `decoder`, training requests,
/// exported models' metadata and the decoder registry spell them.
pub mod network_names {
    /// ADMM-Net.
    pub const ADMM_NET: &str = "admm-net";
    /// The Aᵀ + U-Net.
    pub const UNET: &str = "unet";
    /// The lifetime network.
    pub const LIFETIME: &str = "lifetime";
    /// All of them.
    pub const ALL: [&str; 3] = [ADMM_NET, UNET, LIFETIME];
}

impl ModelConfig {
    /// The decoder's name as `config.json`, `eval` and `reconstruct` spell it.
    pub fn name(&self) -> &'static str {
        match self {
            ModelConfig::AdmmNet(_) => network_names::ADMM_NET,
            ModelConfig::Unet(_) => network_names::UNET,
            ModelConfig::Lifetime(_) => network_names::LIFETIME,
        }
    }

    /// What the network predicts (its [`crate::net::Network::PREDICTION`]).
    pub fn prediction(&self) -> crate::net::Prediction {
        match self {
            ModelConfig::AdmmNet(_) => crate::net::Prediction::Cube,
            ModelConfig::Unet(_) => crate::net::Prediction::Depth,
            ModelConfig::Lifetime(_) => crate::net::Prediction::Lifetime,
        }
    }

    /// Floating-point operations of the forward pass on one `h × w` frame.
    pub fn flops(&self, h: usize, w: usize) -> f64 {
        match self {
            ModelConfig::AdmmNet(c) => c.flops(h, w),
            ModelConfig::Unet(c) => c.flops(h, w),
            ModelConfig::Lifetime(c) => c.flops(h, w),
        }
    }

    /// Taps `M` the network takes.
    pub fn taps(&self) -> usize {
        match self {
            ModelConfig::AdmmNet(c) => c.taps,
            ModelConfig::Unet(c) => c.taps,
            ModelConfig::Lifetime(c) => c.taps,
        }
    }

    /// A lifetime network's grid of lifetimes (`ln τ₀` in ns, step) where it reads the fit's
    /// evidence ([`crate::LifetimeInput::Costs`]).
    pub fn lifetime_grid(&self) -> Option<(f64, f64)> {
        match self {
            ModelConfig::Lifetime(c) => c.log_grid_ns(),
            _ => None,
        }
    }

    /// A depth network's grid of candidate ranges (`u = r·scale − offset`, cyclic) where it
    /// reads the range fit's evidence ([`crate::UnetInput::Costs`]).
    pub fn range_grid(&self) -> Option<(f64, f64)> {
        match self {
            ModelConfig::Unet(c) => c.range_grid(),
            _ => None,
        }
    }

    /// Whether the network reads a fit's evidence (its runtime computes the evidence from the
    /// taps) rather than the taps themselves.
    pub fn reads_evidence(&self) -> bool {
        self.lifetime_grid().is_some() || self.range_grid().is_some()
    }

    /// Returns `K` per pixel a depth network estimates (1 for networks of cubes).
    pub fn returns(&self) -> usize {
        match self {
            ModelConfig::AdmmNet(_) | ModelConfig::Lifetime(_) => 1,
            ModelConfig::Unet(c) => c.returns,
        }
    }

    /// Check the hyper-parameters against sane bounds (a config with absurd numbers would
    /// otherwise ask for terabytes when the network is built).
    pub fn validate(&self) -> Result<()> {
        let bad =
            |field: &'static str, got: String, expected: &str| Err(ModelError::InvalidParam { field, got, expected: expected.into() });
        let (taps, bins) = (self.taps(), self.bins());
        if !(1..=64).contains(&taps) {
            return bad("model.taps", taps.to_string(), "1..=64 taps");
        }
        if !(1..=16384).contains(&bins) {
            return bad("model.bins", bins.to_string(), "1..=16384 bins");
        }
        match self {
            ModelConfig::AdmmNet(c) => {
                if !(1..=64).contains(&c.stages) {
                    return bad("model.stages", c.stages.to_string(), "1..=64 stages");
                }
                if !(1..=1024).contains(&c.channels) {
                    return bad("model.channels", c.channels.to_string(), "1..=1024 channels");
                }
                let reach = crate::admm::DELAY_DILATIONS[2];
                if c.prior == crate::admm::Prior::Delay && bins <= reach {
                    return bad(
                        "model.bins",
                        bins.to_string(),
                        &format!("more than {reach} bins for the delay prior (its largest dilation)"),
                    );
                }
                if !(c.rho_init.is_finite() && c.rho_init > 0.0 && c.eta_init.is_finite()) {
                    return bad("model.rho_init", format!("{}, eta_init {}", c.rho_init, c.eta_init), "rho_init > 0 and a finite eta_init");
                }
            }
            ModelConfig::Unet(c) => {
                if !(1..=4).contains(&c.returns) {
                    return bad("model.returns", c.returns.to_string(), "1..=4 returns");
                }
                if !(1..=256).contains(&c.base_width) {
                    return bad("model.base_width", c.base_width.to_string(), "1..=256 channels");
                }
                if !(1..=6).contains(&c.levels) {
                    return bad("model.levels", c.levels.to_string(), "1..=6 levels");
                }
                if !(c.range_m.is_finite() && c.range_m > 0.0) {
                    return bad("model.range_m", c.range_m.to_string(), "a positive range in metres");
                }
                if let Err(e) = c.validate() {
                    return bad(
                        "model",
                        e,
                        "1–16 candidates per bin, a pool of 1 to the candidates, the score-volume head, pool_like 0 or an odd multiple of 3 up to 63 on the fit's evidence",
                    );
                }
            }
            ModelConfig::Lifetime(c) => {
                let harmonics = c.input == crate::LifetimeInput::Harmonics;
                if harmonics && !(1..=bins / 2).contains(&c.harmonics) {
                    return bad("model.harmonics", c.harmonics.to_string(), &format!("1..={} harmonics (half the {bins} bins)", bins / 2));
                }
                if !(1..=256).contains(&c.base_width) {
                    return bad("model.base_width", c.base_width.to_string(), "1..=256 channels");
                }
                if !(1..=6).contains(&c.levels) {
                    return bad("model.levels", c.levels.to_string(), "1..=6 levels");
                }
                let [lo, hi] = c.tau_range_ns;
                if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo < hi) {
                    return bad("model.tau_range_ns", format!("{:?}", c.tau_range_ns), "0 < lo < hi (ns)");
                }
                if let Err(e) = c.validate() {
                    return bad(
                        "model",
                        e,
                        "a lifetime grid of 3–1024 points, a pool of 1 to points, wider windows of increasing odd sides",
                    );
                }
            }
        }
        Ok(())
    }

    /// Bins `T` of the cube it reconstructs.
    pub fn bins(&self) -> usize {
        match self {
            ModelConfig::AdmmNet(c) => c.bins,
            ModelConfig::Unet(c) => c.bins,
            ModelConfig::Lifetime(c) => c.bins,
        }
    }
}

/// What inference needs from `config.json`: the network and the sensor model it was trained
/// with (the training settings beside them are the training crate's).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSpec {
    #[serde(flatten)]
    pub model: ModelConfig,
    pub sampling: Sampling,
    pub irf: Irf,
    /// The sensor is a measured (recalibrated) matrix kept in the run as
    /// [`SENSOR_MATRIX_FILE`], not one synthesised from the codes and the IRF (`false` in runs
    /// written before it existed).
    #[serde(default)]
    pub measured: bool,
}

/// A run's measured sensor matrix `[N, M, T]` (when [`RunSpec::measured`]).
pub const SENSOR_MATRIX_FILE: &str = "sensor_matrix.npy";

impl RunSpec {
    /// The sensor model of this run: its sampling and IRF, and the measured matrix in the run
    /// directory `dir` when it has one.
    pub fn sensor_model(&self, dir: &Path) -> SensorModel {
        SensorModel {
            sampling: self.sampling,
            irf: self.irf,
            measured: self.measured.then(|| dir.join(SENSOR_MATRIX_FILE)),
            ..Default::default()
        }
    }

    /// The run's sensor for `codes`: the measured matrix in the run directory `dir` when it
    /// has one (its shape checked against the codes and sampling), else the one synthesised
    /// from the codes under the run's sampling and IRF.
    pub fn sensor(&self, dir: &Path, codes: Codes) -> Result<Sensor> {
        Ok(Sensor::build(codes, &self.sensor_model(dir))?)
    }
}

fn file_err(path: &Path, msg: impl ToString) -> ModelError {
    ModelError::File { path: path.to_path_buf(), msg: msg.to_string() }
}

/// Bring a config written by an earlier build up to date: add `"decoder": "admm-net"` where
/// that field is missing (all such runs are ADMM-Net runs), `"normalize": false` to
/// ADMM-Net models written before the input normalisation existed, `"prior": "Bins"` to
/// those written before the delay prior and `"input": "Backprojection"` to U-Nets written
/// before the matched filters, `"input": "Harmonics"` (96 points pooled by 2) to lifetime
/// decoders written before the fit's evidence, no wider windows to those written before them;
/// other configs are returned unchanged.
pub fn upgrade_config(mut v: serde_json::Value) -> serde_json::Value {
    if let Some(obj) = v.as_object_mut() {
        if obj.contains_key("model") && !obj.contains_key("decoder") {
            obj.insert("decoder".into(), serde_json::Value::String(network_names::ADMM_NET.into()));
        }
        if obj.get("decoder").and_then(|d| d.as_str()) == Some(network_names::ADMM_NET) {
            if let Some(model) = obj.get_mut("model").and_then(|m| m.as_object_mut()) {
                model.entry("normalize").or_insert(serde_json::Value::Bool(false));
                model.entry("prior").or_insert(serde_json::Value::String("Bins".into()));
            }
        }
        if obj.get("decoder").and_then(|d| d.as_str()) == Some("unet") {
            if let Some(model) = obj.get_mut("model").and_then(|m| m.as_object_mut()) {
                model.entry("input").or_insert(serde_json::Value::String("Backprojection".into()));
                // runs written before the range fit's evidence (which they do not read)
                model.entry("oversample").or_insert(serde_json::Value::from(4));
                model.entry("pool").or_insert(serde_json::Value::from(4));
                // and before the evidence pooled by likeness
                model.entry("pool_like").or_insert(serde_json::Value::from(0));
            }
        }
        if obj.get("decoder").and_then(|d| d.as_str()) == Some(network_names::LIFETIME) {
            // runs written before the fit's evidence read the harmonics
            if let Some(model) = obj.get_mut("model").and_then(|m| m.as_object_mut()) {
                model.entry("input").or_insert(serde_json::Value::String("Harmonics".into()));
                model.entry("points").or_insert(serde_json::Value::from(96));
                model.entry("pool").or_insert(serde_json::Value::from(2));
                // and before the wider windows of the evidence
                model.entry("windows").or_insert(serde_json::Value::Array(Vec::new()));
                // and before the evidence pooled by likeness
                model.entry("pool_like").or_insert(serde_json::Value::from(0));
                // and before the instrument's superpixels: every pixel (the harmonics fit none)
                let costs = model.get("input").and_then(|i| i.as_str()) == Some("Costs");
                model.entry("instrument_blocks").or_insert(serde_json::Value::from(if costs { 1 } else { 0 }));
                // and before the learned temperature
                model.entry("temper").or_insert(serde_json::Value::from(false));
                // and before the refinement near the mode
                model.entry("refine_near_mode").or_insert(serde_json::Value::from(false));
                // and before the frame's mixture in training: superpixels (the default still)
                model.entry("instrument_mixture").or_insert(serde_json::Value::from(false));
            }
        }
    }
    v
}

/// Read a run config (or a config given to `train --config`) as JSON, upgraded.
pub fn read_config_json(path: &Path) -> Result<serde_json::Value> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| file_err(path, format!("malformed JSON: {e}")))?;
    Ok(upgrade_config(v))
}

/// A run directory opened for inference.
pub struct Run {
    pub dir: PathBuf,
    pub spec: RunSpec,
    /// The sensor it was trained for: the codes it was trained with, `A` of those codes under
    /// the run's sampling and IRF (or the run's measured matrix).
    pub sensor: Sensor,
    /// The trained network behind the decoder contract.
    pub decoder: Box<dyn Decoder>,
}

/// Load the latest weights of a run into its network, on `device`.
pub fn load_network<M: Module>(dir: &Path, model: M) -> Result<M> {
    let weights = dir.join(WEIGHTS_FILE);
    if !weights.exists() {
        return Err(file_err(&weights, "no trained weights; train at least one epoch"));
    }
    model.try_load_file(dir.join(WEIGHTS_STEM)).map_err(|e| file_err(&weights, e))
}

/// A trained network of either kind, as loaded from a run directory.
#[derive(Debug)]
pub enum TrainedNet {
    AdmmNet(AdmmNet),
    Unet(Unet),
    Lifetime(LifetimeNet),
}

/// A run directory loaded with its network as a concrete module (for exporters; [`open`]
/// wraps the same network behind the decoder contract).
#[derive(Debug)]
pub struct LoadedRun {
    pub dir: PathBuf,
    pub spec: RunSpec,
    pub sensor: Sensor,
    pub net: TrainedNet,
}

/// The fields of a run's `config.json` that only training reads (`tcsense_train::TrainConfig`
/// owns them; its tests keep this list equal to its fields). Inference refuses a config with
/// a field that is neither these nor the [`RunSpec`]'s.
pub const TRAINING_KEYS: &[&str] = &[
    "epochs",
    "batch_size",
    "learning_rate",
    "lr_schedule",
    "loss",
    "objective",
    "seed",
    "noise",
    "dataset",
    "max_train_items",
    "max_val_items",
    "augment",
    "learn_codes",
    "init_from",
    "grid_ce_weight",
    "lifetime_error",
    "confidence_loss",
    "grid_nll_cap",
];

/// Load a run directory on `device`: its config, codes, sensor model and latest weights.
pub fn load(dir: &Path, device: &Device) -> Result<LoadedRun> {
    let cfg_path = dir.join(CONFIG_FILE);
    let v = read_config_json(&cfg_path)?;
    let spec: RunSpec = serde_json::from_value(v.clone()).map_err(|e| file_err(&cfg_path, format!("not a run config: {e}")))?;
    let mut known = tcsense_sensor::json::keys_of(&spec);
    known.extend(TRAINING_KEYS.iter().map(|k| k.to_string()));
    tcsense_sensor::json::reject_unknown_keys(&v, &known).map_err(|e| file_err(&cfg_path, e))?;
    spec.model.validate().map_err(|e| file_err(&cfg_path, e))?;
    let codes = Codes::load(&dir.join(CODES_FILE))?;
    let sensor = spec.sensor(dir, codes)?;
    let a = sensor.matrix();
    if a.taps() != spec.model.taps() || a.bins() != spec.model.bins() {
        return Err(file_err(
            &cfg_path,
            format!(
                "the model takes M = {} taps and T = {} bins, but its codes give M = {}, T = {}",
                spec.model.taps(),
                spec.model.bins(),
                a.taps(),
                a.bins()
            ),
        ));
    }
    let net = match &spec.model {
        ModelConfig::AdmmNet(c) => TrainedNet::AdmmNet(load_network(dir, c.init(device))?),
        ModelConfig::Unet(c) => TrainedNet::Unet(load_network(dir, c.init(device))?),
        ModelConfig::Lifetime(c) => TrainedNet::Lifetime(load_network(dir, c.init(device))?),
    };
    Ok(LoadedRun { dir: dir.to_path_buf(), spec, sensor, net })
}

/// Open a run directory as a decoder on `device`: its config, codes, sensor model and latest
/// weights.
pub fn open(dir: &Path, device: &Device) -> Result<Run> {
    open_with(dir, device, true)
}

/// [`open`], with a U-Net's ranges refined in the tap domain ([`tcsense_fits::range`], the
/// default) or as the network outputs them (`range_fit: false`).
pub fn open_with(dir: &Path, device: &Device, range_fit: bool) -> Result<Run> {
    open_opts(dir, device, &OpenOptions { range_fit, ..Default::default() })
}

/// How a run's network decodes ([`open_opts`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OpenOptions {
    /// A U-Net's ranges refined in the tap domain (the default) or as the network gives them.
    pub range_fit: bool,
    /// The decays' onset (s) when known, for a lifetime network on the fit's evidence
    /// ([`crate::lifetime::LifetimeNet::with_onset`]).
    pub onset_s: Option<f64>,
    /// Whether a network that fits no onset refuses `onset_s` (an error naming it) or decodes
    /// without it (a dataset's onset given to every decoder of an evaluation).
    pub onset_strict: bool,
}

impl Default for OpenOptions {
    fn default() -> Self {
        OpenOptions { range_fit: true, onset_s: None, onset_strict: true }
    }
}

/// [`open`] with [`OpenOptions`].
pub fn open_opts(dir: &Path, device: &Device, opts: &OpenOptions) -> Result<Run> {
    let LoadedRun { dir, spec, sensor, net } = load(dir, device)?;
    let name = spec.model.name();
    let no_onset = |what: &str| -> Result<()> {
        match opts.onset_s.filter(|_| opts.onset_strict) {
            Some(t) => Err(ModelError::InvalidParam {
                field: "onset",
                got: format!("{} ns", (t * 1e15).round() / 1e6),
                expected: format!("no onset for {} ({what}): a known onset is for a lifetime network on the fit's evidence", dir.display()),
            }),
            None => Ok(()),
        }
    };
    let decoder: Box<dyn Decoder> = match net {
        TrainedNet::AdmmNet(net) => {
            no_onset("an ADMM-Net")?;
            Box::new(NetDecoder::new(name, net, device.clone()))
        }
        TrainedNet::Unet(net) => {
            no_onset("a depth U-Net")?;
            if opts.range_fit {
                Box::new(NetDecoder::new(name, net, device.clone()))
            } else {
                Box::new(NetDecoder::new(name, net, device.clone()).without_range_fit())
            }
        }
        TrainedNet::Lifetime(net) => {
            let takes = net.input_kind() == crate::lifetime::LifetimeInput::Costs;
            let onset = opts.onset_s.filter(|_| takes || opts.onset_strict);
            let net = net.with_onset(onset).map_err(|msg| ModelError::InvalidParam {
                field: "onset",
                got: format!("{} ns", (opts.onset_s.unwrap_or(0.0) * 1e15).round() / 1e6),
                expected: format!("{}: {msg}", dir.display()),
            })?;
            Box::new(NetDecoder::new(name, net, device.clone()))
        }
    };
    Ok(Run { dir, spec, sensor, decoder })
}
