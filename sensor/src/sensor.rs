//! The sensor object: everything a decoder or a simulation needs to know about one sensor,
//! built once from one description.
//!
//! A [`Sensor`] holds the exposure codes `g`, the checked spec (IRF, sampling `K`), the nominal
//! measurement matrix `A [N, M, T]` of paper eqs. 1–4, an optional calibration (a measured `A`
//! and the dark and gain maps that correct raw tap images, `(y − d) / G`) and optional
//! non-idealities of a simulated sensor. The command line's sensor flags, the Python module's
//! keyword arguments, a run's `config.json` and an ONNX model's metadata all resolve into a
//! [`SensorModel`] and go through [`Sensor::build`]; decoders take `(y, &Sensor)`.
//!
//! ```
//! use tcsense_sensor::generate::prototype_codes;
//! use tcsense_sensor::sensor::{Sensor, SensorModel};
//! use tcsense_sensor::{Irf, Sampling};
//!
//! let codes = prototype_codes(7).unwrap();
//! let sensor = Sensor::build(codes, &SensorModel { sampling: Sampling::Oversample(2), irf: Irf::Ideal, ..Default::default() }).unwrap();
//! assert_eq!(sensor.matrix().bins(), 64); // T = L·K = 32·2
//! let x = ndarray::Array3::<f32>::ones((64, 4, 4));
//! let y = sensor.measure(&x.view().into_dyn(), &Default::default(), false, tcsense_sensor::noise::Exposure::Auto, 0).unwrap().into_input_units();
//! assert_eq!(y.shape(), &[4, 4, 4]); // [M, H, W]
//! ```

use std::path::{Path, PathBuf};

use ndarray::{Array4, ArrayView4, ArrayViewD, Axis, Ix4};
use serde::{Deserialize, Serialize};

use crate::calibration::{check_measurements_file, Calibration};
use crate::codes::Codes;
use crate::error::{invalid, Result, SensorError};
use crate::matrix::MeasurementMatrix;
use crate::measure::{measure, Measurement};
use crate::noise::Exposure;
use crate::nonideal::NonIdeal;
use crate::operator::FramePlan;
use crate::params::{Irf, NoiseParams, Sampling, SensorParams, SensorSpec};
use crate::sidecar::Sidecar;

/// How to build a sensor from its codes: the one description every front end resolves into.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SensorModel {
    /// Oversampling or heterodyne factor `K` (`T = L·K`).
    pub sampling: Sampling,
    /// The instrument response the nominal `A` is synthesised with.
    pub irf: Irf,
    /// A measured nominal `A [N, M, T]` (`.npy`) instead of the synthesised one.
    #[serde(default)]
    pub measured: Option<PathBuf>,
    /// A calibration directory (`tcsense calibrate`).
    #[serde(default)]
    pub calibration: Option<PathBuf>,
    /// The non-idealities of a simulated sensor (all off: the ideal sensor).
    #[serde(default)]
    pub nonideal: NonIdeal,
}

impl Default for SensorModel {
    fn default() -> Self {
        SensorModel { sampling: Sampling::Oversample(1), irf: Irf::Ideal, measured: None, calibration: None, nonideal: NonIdeal::default() }
    }
}

/// Units of simulated tap images.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Units {
    /// The units of the noiseless `A x` (noise rescaled back).
    #[default]
    Input,
    /// Electrons.
    Electrons,
    /// ADC codes.
    Adc,
}

impl Units {
    /// `input`, `electrons` or `adc`, as in a sidecar's `units`.
    pub fn name(self) -> &'static str {
        match self {
            Units::Input => "input",
            Units::Electrons => "electrons",
            Units::Adc => "adc",
        }
    }

    /// The units named `input`, `electrons` or `adc`.
    pub fn parse(name: &str) -> Result<Self> {
        match name {
            "input" => Ok(Units::Input),
            "electrons" => Ok(Units::Electrons),
            "adc" => Ok(Units::Adc),
            other => Err(invalid("units", other, "\"input\", \"electrons\" or \"adc\"")),
        }
    }
}

impl Measurement {
    /// The tap images in `units` (noiseless measurements are in the units of `A x` whatever is asked).
    pub fn in_units(self, units: Units, noise: &NoiseParams) -> ndarray::ArrayD<f32> {
        match self {
            Measurement::Noiseless(y) => y,
            Measurement::Noisy(n) => match units {
                Units::Input => n.in_input_units(),
                Units::Electrons => n.electrons,
                Units::Adc => n.in_adc_codes(noise),
            },
        }
    }

    /// What a tap clipped at the full well reads in `units` (the value [`Self::in_units`] gives
    /// it); `None` for noiseless measurements, which clip nothing.
    pub fn clip_level(&self, units: Units, noise: &NoiseParams) -> Option<f32> {
        match self {
            Measurement::Noiseless(_) => None,
            Measurement::Noisy(n) => {
                let full = crate::noise::NoisyMeasurement {
                    electrons: ndarray::ArrayD::from_elem(ndarray::IxDyn(&[1]), noise.full_well_e as f32),
                    electrons_per_unit: n.electrons_per_unit,
                };
                Measurement::Noisy(full).in_units(units, noise).iter().next().copied()
            }
        }
    }
}

/// One sensor: codes, spec, nominal `A`, and optionally a calibration and non-idealities.
#[derive(Debug, Clone)]
pub struct Sensor {
    codes: Codes,
    spec: SensorSpec,
    nominal: MeasurementMatrix,
    calibration: Option<Calibration>,
    nonideal: NonIdeal,
}

impl Sensor {
    /// The sensor `model` describes for `codes`: the spec checked, `A` synthesised (or loaded
    /// from `model.measured`), the calibration loaded and checked against both, the
    /// non-idealities checked. Errors name the file and field.
    pub fn build(codes: Codes, model: &SensorModel) -> Result<Self> {
        let spec = SensorParams { sampling: model.sampling, irf: model.irf, ..SensorParams::from_codes(&codes) }.validate()?;
        let nominal = match &model.measured {
            None => MeasurementMatrix::synthesize(&codes, &spec)?,
            Some(path) => MeasurementMatrix::load(path, &spec)?,
        };
        let mut s = Sensor::with_matrix(codes, spec, nominal)?;
        if let Some(dir) = &model.calibration {
            s = s.calibrated_from(dir)?;
        }
        s.with_nonideal(model.nonideal)
    }

    /// The ideal sensor of `codes` under `sampling` and `irf` (`A` synthesised).
    pub fn ideal(codes: Codes, sampling: Sampling, irf: Irf) -> Result<Self> {
        Sensor::build(codes, &SensorModel { sampling, irf, ..Default::default() })
    }

    /// A sensor whose nominal `A` is given (a run's measured matrix, an ONNX model's recorded
    /// values, an array), checked against the codes and spec.
    pub fn with_matrix(codes: Codes, spec: SensorSpec, nominal: MeasurementMatrix) -> Result<Self> {
        spec.check_codes(&codes)?;
        let (n, m, t) = nominal.a().dim();
        if (n, m, t) != (spec.subpixels(), spec.taps(), spec.bins()) {
            return Err(SensorError::Shape {
                what: "measurement matrix".into(),
                got: vec![n, m, t],
                expected: format!("[N, M, T] = [{}, {}, {}] of the codes and sampling", spec.subpixels(), spec.taps(), spec.bins()),
            });
        }
        Ok(Sensor { codes, spec, nominal, calibration: None, nonideal: NonIdeal::default() })
    }

    /// This sensor with the calibration in `dir` (checked against its codes and nominal `A`).
    pub fn calibrated_from(self, dir: &Path) -> Result<Self> {
        if !dir.is_dir() {
            return Err(SensorError::file(dir, "no such calibration directory (write one with `tcsense calibrate`)"));
        }
        let cal = Calibration::load(dir, &self.nominal, &self.codes)?;
        Ok(self.with_calibration(cal))
    }

    /// This sensor with `cal` (one computed in memory).
    pub fn with_calibration(mut self, cal: Calibration) -> Self {
        self.calibration = Some(cal);
        self
    }

    /// This sensor with the non-idealities `n` (checked).
    pub fn with_nonideal(mut self, n: NonIdeal) -> Result<Self> {
        self.nonideal = n.validate()?;
        Ok(self)
    }

    /// The exposure codes.
    pub fn codes(&self) -> &Codes {
        &self.codes
    }
    /// The checked spec (sampling, IRF, clock).
    pub fn spec(&self) -> &SensorSpec {
        &self.spec
    }
    /// The nominal `A` (synthesised or measured), what the sensor was designed to be.
    pub fn nominal(&self) -> &MeasurementMatrix {
        &self.nominal
    }
    /// The `A` decoders use: the calibration's when there is one, else the nominal.
    pub fn matrix(&self) -> &MeasurementMatrix {
        self.calibration.as_ref().map_or(&self.nominal, |c| &c.matrix)
    }
    /// The calibration, if any.
    pub fn calibration(&self) -> Option<&Calibration> {
        self.calibration.as_ref()
    }
    /// The non-idealities of the simulated sensor.
    pub fn nonideal(&self) -> &NonIdeal {
        &self.nonideal
    }
    /// Taps `M`.
    pub fn taps(&self) -> usize {
        self.nominal.taps()
    }
    /// Bins `T = L·K` of the reconstruction grid.
    pub fn bins(&self) -> usize {
        self.nominal.bins()
    }
    /// The code block `(bh, bw)`.
    pub fn block(&self) -> (usize, usize) {
        self.nominal.block()
    }
    /// Width of one bin (s).
    pub fn bin_width_s(&self) -> f64 {
        self.spec.bin_width_s()
    }
    /// The forward/adjoint plan of [`Self::matrix`] for `h × w` frames.
    pub fn plan(&self, h: usize, w: usize) -> Result<FramePlan> {
        self.matrix().plan(h, w)
    }

    /// Raw tap images corrected for the calibration's dark and gain maps, `(y − d) / G`; `y`
    /// unchanged without a calibration.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, M, H, W]`
    pub fn correct(&self, y: ArrayView4<'_, f32>) -> Result<Array4<f32>> {
        match &self.calibration {
            Some(c) => c.correct(&y),
            None => Ok(y.to_owned()),
        }
    }

    /// The checks on tap images stored in `path` before they are decoded: their sidecar, when
    /// there is one, names this sensor's codes, sampling and nominal matrix; with a
    /// calibration, the sweep's units.
    pub fn check_measurements(&self, path: &Path) -> Result<()> {
        check_measurements_file(path, &self.nominal, &self.codes, self.calibration.as_ref())
    }

    /// What the sensor reads out for cubes `x`: `A x`, with the non-idealities when it has
    /// any (gains, dark, crosstalk, tail and drift, in electrons), and with shot and read
    /// noise, clipping and quantisation when `noisy`, seeded by `seed`.
    ///
    /// # Shapes
    /// - `x`: `[T, H, W]` → `[M, H, W]`, or `[B, T, H, W]` → `[B, M, H, W]`
    pub fn measure(&self, x: &ArrayViewD<'_, f32>, noise: &NoiseParams, noisy: bool, exposure: Exposure, seed: u64) -> Result<Measurement> {
        let rank = x.ndim();
        if !(rank == 3 || rank == 4) || x.shape()[rank - 3] != self.spec.bins() {
            return Err(SensorError::Shape {
                what: "cube".into(),
                got: x.shape().to_vec(),
                expected: format!("[T, H, W] or [B, T, H, W] with T = L·K = {} bins", self.spec.bins()),
            });
        }
        let (h, w) = (x.shape()[rank - 2], x.shape()[rank - 1]);
        if self.nonideal.is_ideal() {
            return measure(&self.plan(h, w)?, x, noisy.then_some(noise), exposure, seed);
        }
        let real = self.nonideal.realise(self.matrix(), h, w)?;
        let batch = if rank == 3 { x.view().insert_axis(Axis(0)) } else { x.view() };
        let batch = batch.into_dimensionality::<Ix4>().map_err(|e| invalid("cube", format!("{:?}", x.shape()), e.to_string()))?;
        let mut e = real.measure(&batch, noise, noisy, exposure, seed)?;
        if rank == 3 {
            e.electrons = e.electrons.index_axis_move(Axis(0), 0);
        }
        Ok(Measurement::Noisy(e))
    }

    /// The sidecar of tap images this sensor measured (codes, sampling, matrix, noise, units).
    pub fn sidecar(&self, noise: Option<NoiseParams>, seed: Option<u64>, units: &str) -> Sidecar {
        let mut s = Sidecar::new(&self.codes, &self.nominal, self.spec.sampling(), noise, seed, units);
        s.sensor = (!self.nonideal.is_ideal()).then_some(self.nonideal);
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::prototype_codes;

    fn codes() -> Codes {
        prototype_codes(3).unwrap()
    }

    #[test]
    fn build_synthesises_and_checks() {
        let s = Sensor::build(codes(), &SensorModel { sampling: Sampling::Heterodyne(4), ..Default::default() }).unwrap();
        assert_eq!(s.matrix().a().dim(), (4, 4, 128));
        assert!(s.calibration().is_none());
        let e = Sensor::build(codes(), &SensorModel { sampling: Sampling::Oversample(0), ..Default::default() }).unwrap_err().to_string();
        assert!(e.contains("oversample"), "{e}");
        let e = Sensor::build(codes(), &SensorModel { calibration: Some("/nonexistent/cal".into()), ..Default::default() })
            .unwrap_err()
            .to_string();
        assert!(e.contains("/nonexistent/cal") && e.contains("tcsense calibrate"), "{e}");
        let bad = NonIdeal { prnu: 0.9, ..Default::default() };
        let e = Sensor::build(codes(), &SensorModel { nonideal: bad, ..Default::default() }).unwrap_err().to_string();
        assert!(e.contains("prnu"), "{e}");
    }

    #[test]
    fn with_matrix_refuses_a_matrix_of_other_shape() {
        let c = codes();
        let spec = SensorParams::from_codes(&c).validate().unwrap();
        let other = SensorParams { sampling: Sampling::Oversample(2), ..SensorParams::from_codes(&c) }.validate().unwrap();
        let a = MeasurementMatrix::synthesize(&c, &other).unwrap();
        let e = Sensor::with_matrix(c, spec, a).unwrap_err().to_string();
        assert!(e.contains("[4, 4, 64]") && e.contains("[N, M, T] = [4, 4, 32]"), "{e}");
    }

    #[test]
    fn measure_is_a_x_on_the_ideal_sensor_and_gains_on_a_real_one() {
        let s = Sensor::ideal(codes(), Sampling::Oversample(1), Irf::Ideal).unwrap();
        let x = ndarray::Array4::<f32>::from_shape_fn((2, 32, 4, 4), |(b, t, i, j)| ((b + t * 3 + i + 2 * j) % 7) as f32);
        let noise = NoiseParams::default();
        let y = s.measure(&x.view().into_dyn(), &noise, false, Exposure::Auto, 0).unwrap().into_input_units();
        let want = s.plan(4, 4).unwrap().forward_batch(&x.view()).unwrap();
        assert_eq!(y.into_dimensionality::<Ix4>().unwrap(), want);
        // a tap gain of 30 %: the same cube reads out differently, seeded, and the same seed gives the same bytes
        let real = s.clone().with_nonideal(NonIdeal { tap_gain: 0.3, seed: 5, ..Default::default() }).unwrap();
        let one = real.measure(&x.view().into_dyn(), &noise, false, Exposure::Auto, 0).unwrap().in_units(Units::Input, &noise);
        let two = real.measure(&x.view().into_dyn(), &noise, false, Exposure::Auto, 0).unwrap().in_units(Units::Input, &noise);
        assert_eq!(one, two);
        let rel = (&one - &want.into_dyn()).mapv(f32::abs).sum() / one.mapv(f32::abs).sum();
        assert!(rel > 0.01, "tap gains change the read-out by {rel}");
        assert!(real.sidecar(None, None, "input").sensor.is_some());
        let e = s.measure(&ndarray::ArrayD::<f32>::zeros(vec![31, 4, 4]).view(), &noise, false, Exposure::Auto, 0).unwrap_err().to_string();
        assert!(e.contains("T = L·K = 32"), "{e}");
    }

    #[test]
    fn units_parse_and_name_round_trip() {
        for u in [Units::Input, Units::Electrons, Units::Adc] {
            assert_eq!(Units::parse(u.name()).unwrap(), u);
        }
        assert!(Units::parse("volts").unwrap_err().to_string().contains("\"electrons\""));
    }
}
