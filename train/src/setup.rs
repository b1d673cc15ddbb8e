//! Starting, resuming and fine-tuning a run: the rules that do not depend on how the settings
//! were given (the command line, the Python module or a config file).
//!
//! - The **architecture** of a run that continues another comes from that run: on `--resume`
//!   from its own `config.json`, with `--init-from RUN` from `RUN/config.json` (the weights
//!   must fit). Architecture settings a front end was given are checked against it and refused
//!   when they contradict it, naming the run's value; on a new run they shape the network.
//! - The **codes** of a resumed run are its `codes.json`, or, for a learned-codes run stopped
//!   before its projection, its start codes.
//! - A **measured sensor** (`--irf A.npy`, `--calibration DIR`) is checked against the codes and
//!   kept in the run as `sensor_matrix.npy`; it cannot change on `--resume`.

use std::path::{Path, PathBuf};

use tcsense_models::runs::{read_config_json, ModelConfig, RunSpec, CODES_FILE, CONFIG_FILE, SENSOR_MATRIX_FILE};
use tcsense_models::{LifetimeInput, Prior, UnetHead, UnetInput};
use tcsense_sensor::npy::write_npy;
use tcsense_sensor::{Codes, Sensor, SensorModel};

use crate::deep_sensing::START_CODES_FILE;
use crate::{file_err, ConfidenceLoss, LifetimeError, Result, TrainConfig, TrainError};

/// Architecture settings as a front end was given them (`None`: not given).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Architecture {
    /// ADMM-Net: unrolled stages `S`.
    pub stages: Option<usize>,
    /// ADMM-Net: CNN channels `CN`.
    pub channels: Option<usize>,
    /// ADMM-Net: the prior's convolutions.
    pub prior: Option<Prior>,
    /// U-Net: returns per pixel `K`.
    pub returns: Option<usize>,
    /// U-Net and lifetime decoder: channels of the first level.
    pub base_width: Option<usize>,
    /// U-Net and lifetime decoder: resolutions.
    pub levels: Option<usize>,
    /// U-Net: the range read-out.
    pub head: Option<UnetHead>,
    /// U-Net: what the network reads.
    pub input: Option<UnetInput>,
    /// Lifetime decoder: harmonics of the cycle.
    pub harmonics: Option<usize>,
    /// Lifetime decoder on the fit's evidence: points `G` of the lifetime grid.
    pub points: Option<usize>,
    /// Lifetime decoder on the fit's evidence: sides of the wider windows.
    pub windows: Option<Vec<usize>>,
    /// A decoder on the fit's evidence (U-Net, lifetime): the side of the neighbourhood its
    /// window is pooled over by likeness.
    pub pool_like: Option<usize>,
    /// Lifetime decoder on the fit's evidence: the side of the instrument's superpixels.
    pub instrument_blocks: Option<usize>,
    /// Lifetime decoder on the fit's evidence: a dim frame's instrument under the frame's
    /// mixture (false: on superpixels).
    pub instrument_mixture: Option<bool>,
    /// Lifetime decoder on the fit's evidence: its log-likelihood at a learned temperature.
    pub temper: Option<bool>,
    /// Lifetime decoder on the fit's evidence: its mode refined within a point of the fit's.
    pub refine_near_mode: Option<bool>,
    /// Lifetime decoder: what the network reads.
    pub lifetime_input: Option<LifetimeInput>,
}

impl Architecture {
    /// The given settings as `(flag, value given, model's value)` for `model` (settings of
    /// another network are named with the model's value `None`).
    fn against(&self, model: &ModelConfig) -> Vec<(&'static str, String, Option<String>)> {
        let s = |v: &dyn std::fmt::Debug| format!("{v:?}");
        let mut out = Vec::new();
        let mut put = |flag: &'static str, given: Option<String>, have: Option<String>| {
            if let Some(g) = given {
                out.push((flag, g, have));
            }
        };
        let (a, u, l) = match model {
            ModelConfig::AdmmNet(c) => (Some(c), None, None),
            ModelConfig::Unet(c) => (None, Some(c), None),
            ModelConfig::Lifetime(c) => (None, None, Some(c)),
        };
        put("stages", self.stages.map(|v| s(&v)), a.map(|c| s(&c.stages)));
        put("channels", self.channels.map(|v| s(&v)), a.map(|c| s(&c.channels)));
        put("prior", self.prior.map(|v| s(&v)), a.map(|c| s(&c.prior)));
        put("returns", self.returns.map(|v| s(&v)), u.map(|c| s(&c.returns)));
        put("head", self.head.map(|v| s(&v)), u.map(|c| s(&c.head)));
        put("input", self.input.map(|v| s(&v)), u.map(|c| s(&c.input)));
        put("base-width", self.base_width.map(|v| s(&v)), u.map(|c| s(&c.base_width)).or(l.map(|c| s(&c.base_width))));
        put("levels", self.levels.map(|v| s(&v)), u.map(|c| s(&c.levels)).or(l.map(|c| s(&c.levels))));
        put("harmonics", self.harmonics.map(|v| s(&v)), l.map(|c| s(&c.harmonics)));
        put("points", self.points.map(|v| s(&v)), l.map(|c| s(&c.points)));
        put("windows", self.windows.as_ref().map(|v| s(v)), l.map(|c| s(&c.windows)));
        put("pool_like", self.pool_like.map(|v| s(&v)), l.map(|c| s(&c.pool_like)).or(u.map(|c| s(&c.pool_like))));
        put("instrument_blocks", self.instrument_blocks.map(|v| s(&v)), l.map(|c| s(&c.instrument_blocks)));
        put("instrument_mixture", self.instrument_mixture.map(|v| s(&v)), l.map(|c| s(&c.instrument_mixture)));
        put("temper", self.temper.map(|v| s(&v)), l.map(|c| s(&c.temper)));
        put("refine_near_mode", self.refine_near_mode.map(|v| s(&v)), l.map(|c| s(&c.refine_near_mode)));
        put("input", self.lifetime_input.map(|v| s(&v)), l.map(|c| s(&c.input)));
        out
    }

    /// Shape a new run's network: every given setting replaces the default's. A setting of
    /// another network is refused.
    pub fn apply(&self, model: &mut ModelConfig) -> Result<()> {
        if let Some((flag, _, _)) = self.against(model).into_iter().find(|(_, _, have)| have.is_none()) {
            return Err(TrainError::InvalidParam {
                field: "architecture",
                got: format!("--{flag}"),
                expected: format!("settings of {}", model.name()),
            });
        }
        match model {
            ModelConfig::AdmmNet(c) => {
                c.stages = self.stages.unwrap_or(c.stages);
                c.channels = self.channels.unwrap_or(c.channels);
                c.prior = self.prior.unwrap_or(c.prior);
            }
            ModelConfig::Unet(c) => {
                c.returns = self.returns.unwrap_or(c.returns);
                c.base_width = self.base_width.unwrap_or(c.base_width);
                c.levels = self.levels.unwrap_or(c.levels);
                c.head = self.head.unwrap_or(c.head);
                c.input = self.input.unwrap_or(c.input);
                c.pool_like = self.pool_like.unwrap_or(c.pool_like);
            }
            ModelConfig::Lifetime(c) => {
                c.harmonics = self.harmonics.unwrap_or(c.harmonics);
                c.points = self.points.unwrap_or(c.points);
                c.windows = self.windows.clone().unwrap_or_else(|| c.windows.clone());
                c.pool_like = self.pool_like.unwrap_or(c.pool_like);
                c.instrument_blocks = self.instrument_blocks.unwrap_or(c.instrument_blocks);
                c.instrument_mixture = self.instrument_mixture.unwrap_or(c.instrument_mixture);
                c.temper = self.temper.unwrap_or(c.temper);
                c.refine_near_mode = self.refine_near_mode.unwrap_or(c.refine_near_mode);
                c.input = self.lifetime_input.unwrap_or(c.input);
                c.base_width = self.base_width.unwrap_or(c.base_width);
                c.levels = self.levels.unwrap_or(c.levels);
                // settings of the fit's evidence, given for a network on the harmonics
                if c.input != LifetimeInput::Costs {
                    let given = [
                        (self.points.is_some(), "points", c.points.to_string(), "the grid is the fit's evidence's"),
                        (
                            self.instrument_blocks.is_some(),
                            "instrument_blocks",
                            c.instrument_blocks.to_string(),
                            "the instrument is the fit's",
                        ),
                        (
                            self.instrument_mixture == Some(true),
                            "instrument_mixture",
                            "--instrument-mixture".into(),
                            "the instrument is the fit's",
                        ),
                        (
                            self.refine_near_mode == Some(true),
                            "refine_near_mode",
                            "--refine-near-mode".into(),
                            "the refinement is the fit's",
                        ),
                        (self.temper == Some(true), "temper", "--temper".into(), "the temperature weighs the fit's log-likelihood"),
                        (self.windows.is_some(), "windows", format!("{:?}", c.windows), "the windows are the fit's evidence's"),
                    ];
                    if let Some((_, field, got, why)) = given.into_iter().find(|g| g.0) {
                        return Err(TrainError::InvalidParam {
                            field,
                            got: format!("{got} with the harmonics input"),
                            expected: format!("--input costs: {why}"),
                        });
                    }
                } else if let Some(h) = self.harmonics {
                    // and the harmonics', given for a network on the fit's evidence
                    return Err(TrainError::InvalidParam {
                        field: "harmonics",
                        got: format!("{h} with the fit's evidence (input costs)"),
                        expected: "the harmonics input: a network on the evidence reads no harmonics".into(),
                    });
                }
            }
        }
        Ok(())
    }

    /// The source run's network for `--init-from` (in `model`), checked against the given
    /// settings, with the U-Net's input and the pooling by likeness of a network on the fit's
    /// evidence set where they are given: the weights fit either, so a fine-tune may change
    /// what the network reads.
    pub fn with_input(&self, model: &mut ModelConfig, run: &Path) -> Result<()> {
        Architecture { input: None, pool_like: None, ..self.clone() }.check(model, run)?;
        match (&mut *model, self.input) {
            (ModelConfig::Unet(c), Some(i)) => c.input = i,
            (m, Some(_)) => return Err(file_err(&run.join(CONFIG_FILE), format!("a {} run has no --input; leave it out", m.name()))),
            (_, None) => {}
        }
        match (model, self.pool_like) {
            (ModelConfig::Unet(c), Some(p)) => c.pool_like = p,
            (ModelConfig::Lifetime(c), Some(p)) => c.pool_like = p,
            (m, Some(_)) => return Err(file_err(&run.join(CONFIG_FILE), format!("a {} run has no --pool-like; leave it out", m.name()))),
            (_, None) => {}
        }
        Ok(())
    }

    /// Check the given settings against the network of the run at `run` (`--resume`,
    /// `--init-from`): one that differs is refused with the run's value and where it is kept.
    pub fn check(&self, model: &ModelConfig, run: &Path) -> Result<()> {
        for (flag, given, have) in self.against(model) {
            match have {
                None => {
                    return Err(file_err(
                        &run.join(CONFIG_FILE),
                        format!("a {} run has no --{flag}; leave it out (the architecture comes from the run)", model.name()),
                    ))
                }
                Some(h) if h != given => {
                    return Err(file_err(&run.join(CONFIG_FILE), format!("--{flag} {given} contradicts the run's {flag} {h} (field model.{}); the architecture comes from the run, so leave --{flag} out", flag.replace('-', "_"))));
                }
                Some(_) => {}
            }
        }
        Ok(())
    }
}

/// The network of the trained run at `source` (its `config.json`), for `--init-from`: the
/// architecture its weights fit.
pub fn model_of_run(source: &Path) -> Result<ModelConfig> {
    let path = source.join(CONFIG_FILE);
    if !path.exists() {
        return Err(file_err(
            source,
            format!("not a run directory ({CONFIG_FILE} missing); --init-from takes a run of `tcsense train` or zoo:NAME"),
        ));
    }
    let v = read_config_json(&path)?;
    let spec: RunSpec = serde_json::from_value(v).map_err(|e| file_err(&path, format!("not a run config: {e}")))?;
    Ok(spec.model)
}

/// The model of a run started from `source` (`--init-from`): `source`'s architecture, for the
/// `proposed` model's taps and bins (and, for a U-Net, its range, that of the new data). With
/// `from_config` (the proposed model came from a config file) the two must agree.
pub fn model_for_init(source: &Path, proposed: &ModelConfig, from_config: bool) -> Result<ModelConfig> {
    let (taps, bins) = (proposed.taps(), proposed.bins());
    let mut model = model_of_run(source)?;
    let path = source.join(CONFIG_FILE);
    if model.name() != proposed.name() {
        return Err(file_err(&path, format!("a {} run; fine-tune it with `tcsense train {}`", model.name(), model.name())));
    }
    if (model.taps(), model.bins()) != (taps, bins) {
        return Err(file_err(&path, format!("its network takes M = {} taps and T = {} bins; the codes and dataset give M = {taps}, T = {bins}: fine-tuning keeps the network's shape", model.taps(), model.bins())));
    }
    if let (ModelConfig::Unet(m), ModelConfig::Unet(p)) = (&mut model, proposed) {
        m.range_m = p.range_m;
    }
    if from_config && &model != proposed {
        // a config file's network that is not the run's
        let got = serde_json::to_string(proposed).unwrap_or_default();
        let want = serde_json::to_string(&model).unwrap_or_default();
        return Err(file_err(&path, format!("the config's network {got} is not this run's {want}; the weights fit only the run's")));
    }
    Ok(model)
}

/// The loss settings of a run that a fine-tune of it continues with unless told otherwise
/// (the fields of [`crate::TrainConfig`] of the same names).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct RunLoss {
    pub grid_ce_weight: Option<f64>,
    pub lifetime_error: Option<LifetimeError>,
    pub confidence_loss: Option<ConfidenceLoss>,
    pub grid_nll_cap: Option<f64>,
}

/// The loss settings of the run at `source` that a fine-tune of it continues with unless told
/// otherwise: the grid's cross-entropy weight, the lifetimes' error, the confidence's loss (a
/// lifetime network on a grid written before the choice: [`ConfidenceLoss::Stalled`], as it
/// was trained) and the range grid's cap on a pixel's cross-entropy.
pub fn loss_of_run(source: &Path) -> Result<RunLoss> {
    let path = source.join(CONFIG_FILE);
    let v = read_config_json(&path)?;
    let field = |key: &str| v.get(key).filter(|x| !x.is_null()).cloned();
    let parse = |key: &str, x: serde_json::Value| file_err(&path, format!("{key} {x}: not a setting this build knows"));
    let number = |key: &str| field(key).map(|x| x.as_f64().ok_or_else(|| parse(key, x.clone()))).transpose();
    let ce = number("grid_ce_weight")?;
    let error = field("lifetime_error").map(|x| serde_json::from_value(x.clone()).map_err(|_| parse("lifetime_error", x))).transpose()?;
    let confidence =
        field("confidence_loss").map(|x| serde_json::from_value(x.clone()).map_err(|_| parse("confidence_loss", x))).transpose()?;
    let grid = model_of_run(source)?.lifetime_grid().is_some();
    Ok(RunLoss {
        grid_ce_weight: ce,
        lifetime_error: error,
        confidence_loss: confidence.or(grid.then_some(ConfidenceLoss::Stalled)),
        grid_nll_cap: number("grid_nll_cap")?,
    })
}

/// The codes a run trains with: `codes` when given; on resume the run's `codes.json`, or the
/// start codes of a learned-codes run stopped before its projection.
pub fn run_codes(run: &Path, codes: Option<&Path>, resume: bool) -> Result<Codes> {
    Ok(match (codes, resume) {
        (Some(p), _) => Codes::load(p)?,
        (None, true) if !run.join(CODES_FILE).exists() && run.join(START_CODES_FILE).exists() => Codes::load(&run.join(START_CODES_FILE))?,
        (None, true) => Codes::load(&run.join(CODES_FILE))?,
        (None, false) => {
            return Err(TrainError::InvalidParam { field: "codes", got: "none".into(), expected: "a codes JSON file (--codes)".into() })
        }
    })
}

/// Where a run's measured sensor matrix comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum MeasuredSensor {
    /// A measured `A [N, M, T]` (`.npy`).
    Matrix(PathBuf),
    /// A calibration directory: its measured matrix.
    Calibration(PathBuf),
}

/// Mark `cfg` as trained for a measured sensor (refused on resume: a run's sensor does not
/// change).
pub fn use_measured_sensor(cfg: &mut TrainConfig, source: &MeasuredSensor, resume: bool) -> Result<()> {
    if resume {
        let what = match source {
            MeasuredSensor::Matrix(p) => format!("--irf {}", p.display()),
            MeasuredSensor::Calibration(d) => format!("--calibration {}", d.display()),
        };
        return Err(TrainError::InvalidParam {
            field: "sensor",
            got: what,
            expected: "no new sensor on --resume (a run's sensor does not change); start a new run from it with --init-from".into(),
        });
    }
    cfg.run.measured = true;
    Ok(())
}

/// Write the measured sensor of a new run into `run` (`sensor_matrix.npy`), checked against
/// the codes and the run's sampling: the matrix of `A.npy`, or the calibration's (its codes
/// and geometry checked against the nominal sensor).
pub fn write_measured_sensor(cfg: &TrainConfig, codes: &Codes, source: &MeasuredSensor, run: &Path) -> Result<()> {
    cfg.validate()?;
    let model = match source {
        MeasuredSensor::Matrix(p) => {
            SensorModel { sampling: cfg.run.sampling, irf: cfg.run.irf, measured: Some(p.clone()), ..Default::default() }
        }
        MeasuredSensor::Calibration(d) => {
            SensorModel { sampling: cfg.run.sampling, irf: cfg.run.irf, calibration: Some(d.clone()), ..Default::default() }
        }
    };
    let sensor = Sensor::build(codes.clone(), &model)?;
    if run.join("checkpoint").exists() || run.join(crate::deep_sensing::RELAXED_DIR).exists() {
        return Err(file_err(run, "a run already exists here; pass --resume to continue it or choose another directory"));
    }
    write_npy(&run.join(SENSOR_MATRIX_FILE), &sensor.matrix().a().view())?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fine-tune of a zoo entry continues its loss: `-fast` was trained with the grid's
    /// cross-entropy at its default and the stalled confidence (its config names neither),
    /// `lifetime-flim-pooled` with the posterior's mean alone on `ln τ`; a harmonics network
    /// has no grid to set.
    #[test]
    fn a_fine_tune_reads_its_sources_loss() {
        let zoo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../zoo");
        let stalled = RunLoss { confidence_loss: Some(ConfidenceLoss::Stalled), ..Default::default() };
        assert_eq!(loss_of_run(&zoo.join("lifetime-flim-evidence-fast")).unwrap(), stalled);
        assert_eq!(
            loss_of_run(&zoo.join("lifetime-flim-pooled")).unwrap(),
            RunLoss { grid_ce_weight: Some(0.0), lifetime_error: Some(LifetimeError::Log), ..stalled }
        );
        assert_eq!(loss_of_run(&zoo.join("lifetime-flim-designed")).unwrap(), RunLoss::default());
        assert_eq!(loss_of_run(&zoo.join("unet-lidar-evidence-pooled")).unwrap(), RunLoss::default());
    }
}
