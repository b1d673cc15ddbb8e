//! What an exported model carries in its `metadata_props`: the codes and sensor model it was
//! trained with, its outputs and their units, and the frame-size rule. One key per field, so
//! any ONNX runtime (Netron, Python's `onnx`, C++) shows them as written.

use std::path::Path;

use tcsense_models::runs::{LoadedRun, ModelConfig};
use tcsense_sensor::{Codes, Irf, MeasurementMatrix, Sampling, Sensor, SensorParams, SensorSpec};

use super::ExportOptions;

use crate::{InferError, Result};

/// The `format` key's value.
pub const FORMAT: &str = "tcsense-onnx";
/// The metadata version this build writes and reads.
pub const VERSION: u32 = 1;

/// The metadata of an exported tcsense model.
#[derive(Debug, Clone, PartialEq)]
pub struct OnnxMeta {
    /// `admm-net`, `unet` or `lifetime`.
    pub decoder: String,
    /// Taps `M`.
    pub taps: usize,
    /// Bins `T`.
    pub bins: usize,
    /// The code block `(bh, bw)`.
    pub block: (usize, usize),
    /// Frames must be `H × W` with `H`, `W` multiples of these.
    pub frame_multiple: (usize, usize),
    /// Returns `K` of a depth model (0 for cube models).
    pub returns: usize,
    /// Largest depth (m) of a depth model (0 for cube models).
    pub range_m: f64,
    /// Bin width `Δt` (s).
    pub bin_s: f64,
    /// Code clock (Hz).
    pub clock_hz: f64,
    pub sampling: Sampling,
    pub irf: Irf,
    /// The exposure codes (as `codes.json`).
    pub codes: Codes,
    /// The sensor matrix is the input `sensor_matrix` rather than baked in.
    pub matrix_input: bool,
    /// The values of `A [N, M, T]` when it is not the one the codes and sensor model give (a
    /// measured or calibrated sensor); key `sensor_matrix_values`.
    pub matrix_values: Option<Vec<f32>>,
    /// The calibration built into the graph; key `calibration`.
    pub calibration: Option<CalibrationNote>,
    /// A decoder on a fit's evidence with a calibration: its dark and gain maps, which the
    /// runtime applies to the raw tap images before the evidence (the graph reads the evidence,
    /// not the taps); key `calibration_maps`.
    pub correction: Option<CorrectionMaps>,
    /// A lifetime decoder on the fit's evidence: the lifetime grid the runtime computes the
    /// evidence on; key `evidence`.
    pub evidence: Option<EvidenceNote>,
    /// A U-Net on the range fit's evidence: the candidate ranges the runtime computes the
    /// evidence on; key `range_evidence`.
    pub range_evidence: Option<RangeEvidenceNote>,
    /// A U-Net on the range fit's evidence as one graph from the taps (`export onnx
    /// --from-taps`): the graph refines its first return in the tap domain itself, and the
    /// runtime adds no range fit; key `refined_in_graph`.
    pub refined_in_graph: bool,
}

/// The candidate ranges of a U-Net on the range fit's evidence
/// ([`tcsense_models::UnetInput::Costs`]): `C = T·oversample` around the code cycle.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RangeEvidenceNote {
    /// Candidates per bin.
    pub oversample: usize,
    /// Candidates pooled per feature channel.
    pub pool: usize,
    /// The side of the neighbourhood the fit's window is pooled over by likeness before the
    /// graph (0: none, as in models exported before it).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pool_like: usize,
}

impl RangeEvidenceNote {
    /// The settings of the range fit whose evidence the model reads, for `returns` per pixel
    /// (as the network computes them: [`tcsense_models::Unet::fit_options`]).
    pub fn fit_options(&self, returns: usize) -> tcsense_fits::depth::DepthFitOptions {
        tcsense_fits::depth::DepthFitOptions {
            pool_like: self.pool_like,
            ..tcsense_fits::depth::DepthFitOptions::for_evidence(self.oversample, returns)
        }
    }
}

/// The lifetime grid of a lifetime decoder on the fit's evidence
/// ([`tcsense_models::LifetimeInput::Costs`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EvidenceNote {
    /// Points `G` of the log grid.
    pub points: usize,
    /// Grid points pooled per feature channel.
    pub pool: usize,
    /// Lifetimes the grid spans (ns).
    pub tau_range_ns: [f64; 2],
    /// Sides of the wider windows whose evidence the graph reads after the fit's own window's
    /// (none in models exported before them).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub windows: Vec<usize>,
    /// Side of the neighbourhood the fit's window's log-likelihood is pooled over by likeness
    /// before the graph (0: none, as in models exported before it).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub pool_like: usize,
    /// Side, in blocks of the mosaic, of the superpixels each frame's instrument is fitted on
    /// (0: from the frame's photons, every pixel alone where they suffice, else the brightest
    /// pixels under the frame's mixture of lifetimes; 1, every pixel, in models exported before it).
    #[serde(default = "one")]
    pub instrument_blocks: usize,
    /// With `instrument_blocks` 0, a dim frame's instrument under the frame's mixture (every
    /// model exported since; false, on superpixels, in models exported before it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub instrument_mixture: bool,
    /// The graph's mode refined in the tap domain within a point of the fit's argmin (false,
    /// only at it, in models exported before it).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub refine_near_mode: bool,
}

fn one() -> usize {
    1
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

impl EvidenceNote {
    /// Channels of the graph's evidence input (the pooled posteriors of the pixel and of the
    /// wider windows, the log intensity, the lit mask) and of its log-likelihood input.
    pub fn channels(&self) -> (usize, usize) {
        (
            tcsense_fits::lifetime_taps::evidence::feature_channels_with(self.points, self.pool, self.windows.len()),
            (1 + self.windows.len()) * self.points,
        )
    }

    /// The settings of the fit whose evidence the model reads (as the network computes them).
    pub fn fit_options(&self) -> tcsense_fits::lifetime_taps::TapFitOptions {
        let [lo, hi] = self.tau_range_ns;
        tcsense_fits::lifetime_taps::TapFitOptions {
            tau_range_s: [lo * 1e-9, hi * 1e-9],
            points: self.points,
            min_intensity: 0.0,
            pool_like: self.pool_like,
            instrument_blocks: self.instrument_blocks,
            instrument_mixture: self.instrument_mixture,
            refine_near_mode: self.refine_near_mode,
            ..Default::default()
        }
    }
}

/// What an exported model records of the calibration built into it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CalibrationNote {
    /// The frame size `[H, W]` its dark and gain maps have (the model's only frame size).
    pub size: [usize; 2],
    /// Units of the raw tap images it expects (those of the sweep).
    pub units: String,
    /// Digest of the calibrated matrix.
    pub matrix_digest: String,
    /// The sweep it was measured from.
    pub sweep: String,
}

/// The dark and gain maps of a calibration, `d` and `G` `[M, H, W]` in C order, for a runtime
/// that corrects raw tap images itself, `(y − d) / G`.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CorrectionMaps {
    pub dark: Vec<f32>,
    pub gain: Vec<f32>,
}

impl OnnxMeta {
    /// The metadata of `run` exported with `opts`.
    pub fn of_run(run: &LoadedRun, opts: ExportOptions<'_>) -> Self {
        let (bh, bw) = run.sensor.matrix().block();
        let (frame_multiple, returns, range_m) = match &run.spec.model {
            ModelConfig::AdmmNet(_) => ((bh, bw), 0, 0.0),
            ModelConfig::Unet(c) => {
                let s = c.stride();
                // (one graph from the taps gives the first return alone)
                ((lcm(bh, s), lcm(bw, s)), if opts.from_taps { 1 } else { c.returns }, c.range_m)
            }
            ModelConfig::Lifetime(c) => {
                let s = c.stride();
                ((lcm(bh, s), lcm(bw, s)), 0, 0.0)
            }
        };
        OnnxMeta {
            decoder: run.spec.model.name().to_string(),
            taps: run.sensor.matrix().taps(),
            bins: run.sensor.matrix().bins(),
            block: (bh, bw),
            frame_multiple,
            returns,
            range_m,
            bin_s: run.sensor.matrix().bin_width_s(),
            clock_hz: run.sensor.codes().clock_hz,
            sampling: run.spec.sampling,
            irf: run.spec.irf,
            codes: run.sensor.codes().clone(),
            matrix_input: opts.matrix_input,
            matrix_values: match opts.calibration {
                Some(c) => Some(c.matrix.a().iter().copied().collect()),
                None => run.spec.measured.then(|| run.sensor.matrix().a().iter().copied().collect()),
            },
            calibration: opts.calibration.map(|c| CalibrationNote {
                size: c.meta.size,
                units: c.meta.units.clone(),
                matrix_digest: c.meta.matrix_digest.clone(),
                sweep: c.meta.sweep.clone(),
            }),
            correction: opts
                .calibration
                .filter(|_| run.spec.model.reads_evidence())
                .map(|c| CorrectionMaps { dark: c.dark.iter().copied().collect(), gain: c.gain.iter().copied().collect() }),
            evidence: match &run.spec.model {
                ModelConfig::Lifetime(c) if c.input == tcsense_models::LifetimeInput::Costs => Some(EvidenceNote {
                    points: c.points,
                    pool: c.pool,
                    tau_range_ns: c.tau_range_ns,
                    windows: c.windows.clone(),
                    pool_like: c.pool_like,
                    instrument_blocks: c.instrument_blocks,
                    // (as every run decodes, whatever its training used)
                    instrument_mixture: true,
                    refine_near_mode: c.refine_near_mode,
                }),
                _ => None,
            },
            refined_in_graph: opts.from_taps,
            range_evidence: match &run.spec.model {
                ModelConfig::Unet(c) if c.input == tcsense_models::UnetInput::Costs && !opts.from_taps => {
                    Some(RangeEvidenceNote { oversample: c.oversample, pool: c.pool, pool_like: c.pool_like })
                }
                _ => None,
            },
        }
    }

    /// The names of the model's outputs.
    pub fn outputs(&self) -> &'static [&'static str] {
        match self.decoder.as_str() {
            "unet" => &["depth", "confidence"],
            "lifetime" => &["lifetime", "confidence", "intensity"],
            _ => &["cube"],
        }
    }

    /// The graph's inputs: the measurements (and the matrix), or the evidence computed from them.
    pub fn graph_inputs(&self) -> Vec<&'static str> {
        use super::{EVIDENCE_INPUT, INPUT, LOG_LIKELIHOOD_INPUT, MATRIX_INPUT};
        match (self.evidence.is_some() || self.range_evidence.is_some(), self.matrix_input) {
            (true, _) => vec![EVIDENCE_INPUT, LOG_LIKELIHOOD_INPUT],
            (false, true) => vec![INPUT, MATRIX_INPUT],
            (false, false) => vec![INPUT],
        }
    }

    /// The graph's outputs: [`Self::outputs`] but the intensity where the runtime computes
    /// the evidence (and with it the intensity).
    pub fn graph_outputs(&self) -> &'static [&'static str] {
        if self.range_evidence.is_some() {
            &[super::MODE_RANGE_OUTPUT, super::FIRST_CONFIDENCE_OUTPUT]
        } else if self.evidence.is_some() {
            &["lifetime", "confidence"]
        } else {
            self.outputs()
        }
    }

    /// The key/value pairs written to `metadata_props`.
    pub fn to_props(&self) -> Vec<(String, String)> {
        let json = |v: serde_json::Result<String>| v.unwrap_or_default();
        let mut p = vec![
            ("format", FORMAT.to_string()),
            ("version", VERSION.to_string()),
            ("decoder", self.decoder.clone()),
            ("taps", self.taps.to_string()),
            ("bins", self.bins.to_string()),
            ("block", format!("{}x{}", self.block.0, self.block.1)),
            ("frame_multiple", format!("{}x{}", self.frame_multiple.0, self.frame_multiple.1)),
            ("bin_s", format!("{:e}", self.bin_s)),
            ("clock_hz", format!("{}", self.clock_hz)),
            ("sampling", json(serde_json::to_string(&self.sampling))),
            ("irf", json(serde_json::to_string(&self.irf))),
            ("codes", self.codes.to_json()),
            ("matrix_input", self.matrix_input.to_string()),
            ("outputs", self.outputs().join(",")),
        ];
        if let Some(v) = &self.matrix_values {
            p.push(("sensor_matrix_values", json(serde_json::to_string(v))));
        }
        if let Some(c) = &self.calibration {
            p.push(("calibration", json(serde_json::to_string(c))));
        }
        if let Some(c) = &self.correction {
            p.push(("calibration_maps", json(serde_json::to_string(c))));
        }
        if let Some(e) = &self.evidence {
            p.push(("evidence", json(serde_json::to_string(e))));
        }
        if let Some(e) = &self.range_evidence {
            p.push(("range_evidence", json(serde_json::to_string(e))));
        }
        if self.refined_in_graph {
            p.push(("refined_in_graph", "true".into()));
        }
        if self.decoder == "unet" {
            p.push(("returns", self.returns.to_string()));
            p.push(("range_m", format!("{}", self.range_m)));
            p.push(("units", "measurements: tap images, any scale; depth: m (c*t/2 from the start of the code cycle); confidence: probability in [0, 1] that the return exists".into()));
        } else if self.decoder == "lifetime" {
            p.push(("units", "measurements: tap images, any scale; lifetime: channels tau_m (amplitude-weighted mean), tau_1 <= tau_2 in s and the amplitude fraction alpha_1 of tau_1; confidence: probability in [0, 1] that the pixel holds a fluorophore; intensity: the sum of the tap images".into()));
        } else {
            p.push((
                "units",
                "measurements: tap images, any scale; cube: the measurements' scale per time bin (bin j covers [j*bin_s, (j+1)*bin_s))"
                    .into(),
            ));
        }
        p.into_iter().map(|(k, v)| (k.to_string(), v)).collect()
    }

    /// Read the metadata back through `get` (key → value); errors name `path` and the key.
    pub fn from_props(path: &Path, get: impl Fn(&str) -> Option<String>) -> Result<Self> {
        let err = |key: &str, msg: String| InferError::File { path: path.to_path_buf(), msg: format!("metadata_props[{key:?}]: {msg}") };
        let req = |key: &str| get(key).ok_or_else(|| err(key, "missing; is this a model exported by `tcsense export onnx`?".into()));
        let format = req("format")?;
        if format != FORMAT {
            return Err(err("format", format!("got {format:?}, expected {FORMAT:?}")));
        }
        let version: u32 = req("version")?.parse().map_err(|e| err("version", format!("{e}")))?;
        if version != VERSION {
            return Err(err("version", format!("got {version}, this build reads version {VERSION}")));
        }
        let num = |key: &str| -> Result<usize> {
            req(key)?.parse::<usize>().map_err(|e| err(key, format!("{e}; expected a non-negative integer")))
        };
        let float = |key: &str| -> Result<f64> { req(key)?.parse::<f64>().map_err(|e| err(key, format!("{e}; expected a number"))) };
        let pair = |key: &str| -> Result<(usize, usize)> {
            let v = req(key)?;
            let (a, b) = v.split_once('x').ok_or_else(|| err(key, format!("got {v:?}, expected HxW")))?;
            match (a.parse::<usize>(), b.parse::<usize>()) {
                (Ok(a), Ok(b)) if a > 0 && b > 0 => Ok((a, b)),
                _ => Err(err(key, format!("got {v:?}, expected HxW with positive integers"))),
            }
        };
        let decoder = req("decoder")?;
        if !tcsense_models::runs::network_names::ALL.contains(&decoder.as_str()) {
            return Err(err("decoder", format!("got {decoder:?}, expected \"admm-net\", \"unet\" or \"lifetime\"")));
        }
        let codes = Codes::from_json(&req("codes")?).map_err(|e| err("codes", e))?;
        let sampling: Sampling = serde_json::from_str(&req("sampling")?).map_err(|e| err("sampling", e.to_string()))?;
        let irf: Irf = serde_json::from_str(&req("irf")?).map_err(|e| err("irf", e.to_string()))?;
        let matrix_input = match req("matrix_input")?.as_str() {
            "true" => true,
            "false" => false,
            v => return Err(err("matrix_input", format!("got {v:?}, expected true or false"))),
        };
        let refined_in_graph = match get("refined_in_graph").as_deref() {
            None | Some("false") => false,
            Some("true") if decoder == "unet" => true,
            Some(v) => return Err(err("refined_in_graph", format!("got {v:?}, expected true (a U-Net's graph from the taps) or false"))),
        };
        let (returns, range_m) = if decoder == "unet" { (num("returns")?, float("range_m")?) } else { (0, 0.0) };
        let matrix_values: Option<Vec<f32>> = get("sensor_matrix_values")
            .map(|v| {
                serde_json::from_str(&v).map_err(|e| err("sensor_matrix_values", format!("{e}; expected a JSON array of N·M·T numbers")))
            })
            .transpose()?;
        let calibration: Option<CalibrationNote> =
            get("calibration").map(|v| serde_json::from_str(&v).map_err(|e| err("calibration", e.to_string()))).transpose()?;
        let correction: Option<CorrectionMaps> = get("calibration_maps")
            .map(|v| {
                serde_json::from_str(&v).map_err(|e| err("calibration_maps", format!("{e}; expected {{\"dark\": [...], \"gain\": [...]}}")))
            })
            .transpose()?;
        let evidence: Option<EvidenceNote> =
            get("evidence").map(|v| serde_json::from_str(&v).map_err(|e| err("evidence", e.to_string()))).transpose()?;
        if let Some(e) = &evidence {
            let opts = e.fit_options();
            let sides = e.windows.windows(2).all(|p| p[0] < p[1])
                && e.windows.iter().all(|&s| s % 2 == 1 && s > opts.window && s <= tcsense_fits::range::MAX_WINDOW)
                && e.windows.len() <= 8;
            let fine = opts.validate().is_ok() && (3..=1024).contains(&e.points) && (1..=e.points).contains(&e.pool) && sides;
            if decoder != "lifetime" || !fine {
                return Err(err(
                    "evidence",
                    format!(
                        "{e:?}: expected a lifetime decoder's grid of 3–1024 points over 0 < lo < hi ns, a pool of 1 to points, wider windows of increasing odd sides up to {}, a neighbourhood pooled by likeness of 0 or an odd side above 3, the instrument's superpixels of 0 to {} blocks",
                        tcsense_fits::range::MAX_WINDOW,
                        tcsense_fits::lifetime_taps::MAX_INSTRUMENT_BLOCKS
                    ),
                ));
            }
        }
        let range_evidence: Option<RangeEvidenceNote> =
            get("range_evidence").map(|v| serde_json::from_str(&v).map_err(|e| err("range_evidence", e.to_string()))).transpose()?;
        if let Some(e) = &range_evidence {
            let bins = num("bins")?;
            if decoder != "unet" || !(1..=16).contains(&e.oversample) || !(1..=bins * e.oversample).contains(&e.pool) {
                return Err(err(
                    "range_evidence",
                    format!("{e:?}: expected a U-Net's 1–16 candidates per bin and a pool of 1 to the candidates"),
                ));
            }
        }
        if let Some(c) = &correction {
            let Some(cal) = &calibration else {
                return Err(err("calibration_maps", "without a calibration note (key \"calibration\")".into()));
            };
            let n = num("taps")? * cal.size[0] * cal.size[1];
            let dark_fine = c.dark.len() == n && c.dark.iter().all(|v| v.is_finite());
            let gain_fine = c.gain.len() == n && c.gain.iter().all(|v| v.is_finite() && *v > 0.0);
            if !(dark_fine && gain_fine) || (evidence.is_none() && range_evidence.is_none()) {
                return Err(err(
                    "calibration_maps",
                    format!(
                        "{} dark and {} gain values: expected M·H·W = {n} of each for the calibrated frame size {}x{}, finite, gains above 0, for a decoder on a fit's evidence",
                        c.dark.len(),
                        c.gain.len(),
                        cal.size[0],
                        cal.size[1]
                    ),
                ));
            }
        }
        let meta = OnnxMeta {
            correction,
            evidence,
            range_evidence,
            decoder,
            taps: num("taps")?,
            bins: num("bins")?,
            block: pair("block")?,
            frame_multiple: pair("frame_multiple")?,
            returns,
            range_m,
            bin_s: float("bin_s")?,
            clock_hz: float("clock_hz")?,
            sampling,
            irf,
            codes,
            matrix_input,
            matrix_values,
            calibration,
            refined_in_graph,
        };
        // the codes and sensor model must give the declared shape
        let a = meta.matrix().map_err(|e| err("codes", e.to_string()))?;
        if a.taps() != meta.taps || a.bins() != meta.bins || a.block() != meta.block {
            return Err(err(
                "codes",
                format!(
                    "the codes give M = {}, T = {}, block {:?}; the metadata says M = {}, T = {}, block {:?}",
                    a.taps(),
                    a.bins(),
                    a.block(),
                    meta.taps,
                    meta.bins,
                    meta.block
                ),
            ));
        }
        Ok(meta)
    }

    /// The sensor spec of the model's codes, sampling and IRF.
    pub fn spec(&self) -> Result<SensorSpec> {
        Ok(SensorParams { sampling: self.sampling, irf: self.irf, ..SensorParams::from_codes(&self.codes) }.validate()?)
    }

    /// The model's sensor: its codes, sampling and IRF, with the recorded matrix of a measured
    /// or calibrated sensor.
    pub fn sensor(&self) -> Result<Sensor> {
        Ok(Sensor::with_matrix(self.codes.clone(), self.spec()?, self.matrix()?)?)
    }

    /// The measurement matrix of the model: the recorded values of a measured or calibrated
    /// sensor, else the one its codes and sensor model give.
    pub fn matrix(&self) -> Result<MeasurementMatrix> {
        let synthetic = MeasurementMatrix::synthesize(&self.codes, &self.spec()?)?;
        match &self.matrix_values {
            None => Ok(synthetic),
            Some(v) => {
                let a = ndarray::Array3::from_shape_vec(synthetic.a().dim(), v.clone()).map_err(|e| InferError::InvalidParam {
                    field: "sensor_matrix_values",
                    got: format!("{} values", v.len()),
                    expected: format!("N·M·T = {} ({e})", synthetic.a().len()),
                })?;
                Ok(synthetic.with_values(a)?)
            }
        }
    }
}

fn gcd(a: usize, b: usize) -> usize {
    if b == 0 {
        a
    } else {
        gcd(b, a % b)
    }
}

/// Least common multiple.
pub fn lcm(a: usize, b: usize) -> usize {
    a / gcd(a, b).max(1) * b
}
