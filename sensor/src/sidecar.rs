//! Measurements that say what they are: a small JSON sidecar next to `y.npy`, `y.meta.json`,
//! naming the sensor that produced the tap images — the codes (digest), block, taps, length,
//! clock, sampling, bins and a digest of the measurement matrix `A` itself (codes, IRF and
//! sampling in one number), plus the noise settings and seed of a simulation.
//!
//! `tcsense simulate` writes one; every decoder that reads `y.npy` checks it when it is there
//! and refuses measurements of another sensor (exit 2, naming the sidecar and the field). A
//! sensor's own software can write the same file (the format is documented in docs/formats.md).

use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

use crate::codes::Codes;
use crate::error::{Result, SensorError};
use crate::matrix::MeasurementMatrix;
use crate::npy::write_bytes;
use crate::params::{NoiseParams, Sampling};

/// The `format` field of a sidecar.
pub const FORMAT: &str = "tcsense-measurements";
/// The sidecar version this build writes and reads.
pub const VERSION: u32 = 1;

/// The sidecar of a measurement file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    pub format: String,
    pub version: u32,
    /// Taps `M`.
    pub taps: usize,
    /// Code block `[bh, bw]`.
    pub block: [usize; 2],
    /// Masks `L` per cycle.
    pub length: usize,
    /// Code clock (Hz).
    pub clock_hz: f64,
    pub sampling: Sampling,
    /// Bins `T` of the sensor model.
    pub bins: usize,
    /// [`Codes::digest`] of the codes.
    pub codes_digest: String,
    /// [`MeasurementMatrix::digest`] of `A` (codes, IRF and sampling).
    pub matrix_digest: String,
    /// Noise of a simulation (`null`: noise-free or not simulated).
    #[serde(default)]
    pub noise: Option<NoiseParams>,
    /// Seed of a simulation's noise.
    #[serde(default)]
    pub seed: Option<u64>,
    /// What the values are (`input` units of the cube, `electrons`, `adc` codes, or a
    /// sensor's own word).
    pub units: String,
    /// A simulated sensor's non-idealities (tap gains, PRNU, dark, crosstalk, tail, drift and
    /// their seed); absent for the ideal sensor.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sensor: Option<crate::nonideal::NonIdeal>,
    /// What a tap clipped at the full well reads, in `units`: a pixel with a tap at it cannot
    /// be read (absent: not known, or noise off).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clip_level: Option<f32>,
}

impl Sidecar {
    /// The sidecar of measurements of `a` (from `codes` under `sampling`).
    pub fn new(
        codes: &Codes,
        a: &MeasurementMatrix,
        sampling: Sampling,
        noise: Option<NoiseParams>,
        seed: Option<u64>,
        units: &str,
    ) -> Self {
        let (bh, bw) = codes.block();
        Sidecar {
            format: FORMAT.into(),
            version: VERSION,
            taps: codes.taps(),
            block: [bh, bw],
            length: codes.length(),
            clock_hz: codes.clock_hz,
            sampling,
            bins: a.bins(),
            codes_digest: codes.digest(),
            matrix_digest: a.digest(),
            noise,
            seed,
            units: units.into(),
            sensor: None,
            clip_level: None,
        }
    }

    /// The sidecar's path for the measurement file `y`: `y.npy` → `y.meta.json`.
    pub fn path_for(y: &Path) -> PathBuf {
        y.with_extension("meta.json")
    }

    /// Write the sidecar of `y` (atomically).
    pub fn write_for(&self, y: &Path) -> Result<PathBuf> {
        let path = Self::path_for(y);
        let text = serde_json::to_string_pretty(self).map_err(|e| SensorError::file(&path, e.to_string()))?;
        write_bytes(&path, text.as_bytes())?;
        Ok(path)
    }

    /// The sidecar of `y`, if there is one.
    pub fn read_for(y: &Path) -> Result<Option<Self>> {
        let path = Self::path_for(y);
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| SensorError::io(&path, e))?;
        let s: Sidecar = serde_json::from_str(&text).map_err(|e| SensorError::file(&path, format!("not a measurement sidecar: {e}")))?;
        if s.format != FORMAT || s.version != VERSION {
            return Err(SensorError::file(
                &path,
                format!("format {:?} version {}; expected {FORMAT:?} version {VERSION}", s.format, s.version),
            ));
        }
        if let Some(c) = s.clip_level.filter(|c| !(c.is_finite() && *c > 0.0 && *c <= crate::npy::MAX_VALUE)) {
            return Err(SensorError::file(
                &path,
                format!("clip_level {c}: expected a positive level in the tap images' units, up to 1e30"),
            ));
        }
        Ok(Some(s))
    }

    /// Check that measurements with this sidecar (at `path`) come from the sensor `a` (and
    /// `codes`, when known); the error names the first field that differs.
    pub fn check(&self, path: &Path, a: &MeasurementMatrix, codes: Option<&Codes>) -> Result<()> {
        if self.matrix_digest == a.digest() {
            return Ok(());
        }
        let (bh, bw) = a.block();
        let what = if self.taps != a.taps() {
            format!("taps: the measurements have M = {}, the decoder's sensor M = {}", self.taps, a.taps())
        } else if self.block != [bh, bw] {
            format!("block: the measurements come from {}x{} blocks, the decoder's sensor has {bh}x{bw}", self.block[0], self.block[1])
        } else if codes.is_some_and(|c| c.digest() != self.codes_digest) {
            format!(
                "codes_digest: the measurements were taken with other codes ({}) than the decoder's ({})",
                self.codes_digest,
                codes.map(Codes::digest).unwrap_or_default()
            )
        } else if self.bins != a.bins() {
            format!(
                "bins: the measurements' sensor model has T = {} bins ({:?}), the decoder's T = {} (check --oversample/--heterodyne)",
                self.bins,
                self.sampling,
                a.bins()
            )
        } else {
            format!(
                "matrix_digest: the measurement matrix differs ({} vs the decoder's {}): another IRF, sampling or calibration",
                self.matrix_digest,
                a.digest()
            )
        };
        Err(SensorError::file(path, format!("{what}; decode them with the sensor they were taken with")))
    }
}

pub use crate::digest::digest;
