//! Sensor parameters: raw [`SensorParams`] → [`SensorParams::validate`] → checked [`SensorSpec`].
//!
//! Defaults are the paper's prototype: 2×2 block, 4 taps without drain, `L = 32` masks at
//! 607 MHz (`T_c ≈ 1.65 ns`), Gaussian laser pulse of 2.55 ns FWHM, full well 20 000 e⁻,
//! read noise σ = 40 e⁻. The reconstruction grid has `T = L·K` bins of `Δt = T_c/K`.

use crate::codes::{CodeShape, Codes, DEFAULT_CLOCK_HZ};
use crate::error::{invalid, Result};
use serde::{Deserialize, Serialize};

/// Speed of light (m/s): a delay `t` is a range `C·t/2`.
pub const C: f64 = 299_792_458.0;

/// How the fine time grid relates to the code clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "mode", content = "k")]
pub enum Sampling {
    /// `K`-fold oversampling of the code clock (`K = 1`: one bin per mask).
    Oversample(usize),
    /// Heterodyne sweep: `K` cycles, each delaying the scene by `Δ = T_c/K` against the codes.
    Heterodyne(usize),
}

impl Sampling {
    /// The factor `K`.
    pub fn k(&self) -> usize {
        match *self {
            Sampling::Oversample(k) | Sampling::Heterodyne(k) => k,
        }
    }

    /// The sampling the factors name, as the `--oversample K` / `--heterodyne K` flags do
    /// (T = L·K); `default` when neither is given. Both at once is an error.
    pub fn from_factors(oversample: Option<usize>, heterodyne: Option<usize>, default: Sampling) -> Result<Sampling> {
        match (oversample, heterodyne) {
            (Some(o), Some(h)) => Err(invalid(
                "sampling",
                format!("oversample {o} and heterodyne {h}"),
                "one of oversample and heterodyne (T = L·K either way)",
            )),
            (None, Some(k)) => Ok(Sampling::Heterodyne(k)),
            (Some(k), None) => Ok(Sampling::Oversample(k)),
            (None, None) => Ok(default),
        }
    }
}

/// The instrument response used to build the measurement matrix.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "kind")]
pub enum Irf {
    /// Rectangular gates only: `A[n][m][j]` is the code bit of the mask containing bin `j`.
    Ideal,
    /// Gaussian laser pulse (FWHM, s) ⋆ first-order tap response (time constant, s), eq. (4).
    Physical { laser_fwhm_s: f64, tap_tau_s: f64 },
}

/// The largest `signal_fraction`: 100× overexposed.
pub const MAX_SIGNAL_FRACTION: f64 = 100.0;

/// The largest full well the noise model takes (electrons): far past any pixel's (a model without
/// clipping takes it), and where every charge stays finite in `f32`.
pub const MAX_FULL_WELL_E: f64 = 1e12;

/// How the signal is brought to electrons before noise is added.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct NoiseParams {
    /// Full-well capacity in electrons (clip level).
    pub full_well_e: f64,
    /// Gaussian read noise σ in electrons.
    pub read_noise_e: f64,
    /// The brightest tap value is scaled to this fraction of the full well (above 1 the
    /// brightest taps saturate and clip: an overexposed frame).
    pub signal_fraction: f64,
    /// ADC resolution in bits over the full well; 0 disables quantisation.
    pub adc_bits: u32,
}

impl Default for NoiseParams {
    fn default() -> Self {
        NoiseParams { full_well_e: 20_000.0, read_noise_e: 40.0, signal_fraction: 0.8, adc_bits: 12 }
    }
}

impl NoiseParams {
    /// Check ranges.
    pub fn validate(self) -> Result<Self> {
        if !(self.full_well_e > 0.0 && self.full_well_e <= MAX_FULL_WELL_E) {
            return Err(invalid(
                "full_well",
                self.full_well_e,
                format!("a positive number of electrons up to {MAX_FULL_WELL_E:e} (e.g. 20000)"),
            ));
        }
        if !(self.read_noise_e >= 0.0 && self.read_noise_e <= self.full_well_e) {
            return Err(invalid("read_noise", self.read_noise_e, "a non-negative number of electrons up to the full well (e.g. 40)"));
        }
        if !(self.signal_fraction > 0.0 && self.signal_fraction <= MAX_SIGNAL_FRACTION) {
            return Err(invalid(
                "signal_fraction",
                self.signal_fraction,
                format!("a fraction of full well in (0, {MAX_SIGNAL_FRACTION}] (above 1 the brightest taps clip)"),
            ));
        }
        if self.adc_bits > 24 {
            return Err(invalid("adc_bits", self.adc_bits, "0 (off) or 1..=24"));
        }
        Ok(self)
    }
}

/// Unchecked sensor parameters (what a user or a config file says).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SensorParams {
    /// Pixel block `(bh, bw)`.
    pub block: (usize, usize),
    /// Taps `M` (1–8).
    pub taps: usize,
    /// Whether the modulator has a drain.
    pub drain: bool,
    /// Masks per cycle `L` (multiple of 8, 8–256).
    pub length: usize,
    /// Code clock in Hz.
    pub clock_hz: f64,
    /// Oversampling or heterodyne factor `K`.
    pub sampling: Sampling,
    /// Instrument response.
    pub irf: Irf,
    /// Noise settings.
    pub noise: NoiseParams,
}

/// Default laser pulse FWHM of the paper's experiment (2.55 ns).
pub const DEFAULT_LASER_FWHM_S: f64 = 2.55e-9;
/// Default first-order tap time constant (0.3 ns; the prototype modulates up to ~300 MHz).
pub const DEFAULT_TAP_TAU_S: f64 = 0.3e-9;
/// The longest laser pulse width or tap time constant a sensor model takes (s): far beyond any
/// time-compressive sensor's cycle, short enough that the response's kernel stays a few
/// cycles long.
pub const MAX_RESPONSE_S: f64 = 1e-6;

impl Default for SensorParams {
    fn default() -> Self {
        SensorParams {
            block: (2, 2),
            taps: 4,
            drain: false,
            length: 32,
            clock_hz: DEFAULT_CLOCK_HZ,
            sampling: Sampling::Oversample(1),
            irf: Irf::Ideal,
            noise: NoiseParams::default(),
        }
    }
}

impl SensorParams {
    /// Parameters taking block, taps, drain, length and clock from a code set.
    pub fn from_codes(codes: &Codes) -> Self {
        let s = codes.shape();
        SensorParams { block: (s.bh, s.bw), taps: s.taps, drain: s.drain, length: s.length, clock_hz: codes.clock_hz, ..Default::default() }
    }

    /// Check every parameter against the hardware's limits.
    pub fn validate(self) -> Result<SensorSpec> {
        CodeShape { bh: self.block.0, bw: self.block.1, taps: self.taps, length: self.length, drain: self.drain }.validate()?;
        crate::codes::check_clock(self.clock_hz)?;
        let k = self.sampling.k();
        if !(1..=64).contains(&k) {
            let field = match self.sampling {
                Sampling::Oversample(_) => "oversample",
                Sampling::Heterodyne(_) => "heterodyne",
            };
            return Err(invalid(field, k, "K in 1..=64"));
        }
        if let Irf::Physical { laser_fwhm_s, tap_tau_s } = self.irf {
            if !(laser_fwhm_s.is_finite() && (0.0..=MAX_RESPONSE_S).contains(&laser_fwhm_s)) {
                return Err(invalid("laser_fwhm", laser_fwhm_s, "a duration from 0 to 1 µs (1e-6 s; e.g. 2.55e-9)"));
            }
            if !(tap_tau_s.is_finite() && (0.0..=MAX_RESPONSE_S).contains(&tap_tau_s)) {
                return Err(invalid("tap_tau", tap_tau_s, "a time constant from 0 to 1 µs (1e-6 s; e.g. 0.3e-9)"));
            }
        }
        self.noise.validate()?;
        Ok(SensorSpec { p: self })
    }
}

/// Checked sensor parameters; only this type reaches the simulator.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorSpec {
    p: SensorParams,
}

impl SensorSpec {
    /// The parameters.
    pub fn params(&self) -> &SensorParams {
        &self.p
    }
    /// Code geometry.
    pub fn shape(&self) -> CodeShape {
        CodeShape { bh: self.p.block.0, bw: self.p.block.1, taps: self.p.taps, length: self.p.length, drain: self.p.drain }
    }
    /// Subpixels per block `N`.
    pub fn subpixels(&self) -> usize {
        self.p.block.0 * self.p.block.1
    }
    /// Taps `M`.
    pub fn taps(&self) -> usize {
        self.p.taps
    }
    /// Bins of the reconstruction grid, `T = L·K`.
    pub fn bins(&self) -> usize {
        self.p.length * self.p.sampling.k()
    }
    /// Mask period `T_c` (s).
    pub fn clock_period_s(&self) -> f64 {
        1.0 / self.p.clock_hz
    }
    /// Bin width `Δt = T_c/K` (s).
    pub fn bin_width_s(&self) -> f64 {
        self.clock_period_s() / self.p.sampling.k() as f64
    }
    /// Code cycle `L·T_c` (s): the unambiguous time range.
    pub fn cycle_s(&self) -> f64 {
        self.p.length as f64 * self.clock_period_s()
    }
    /// Sampling mode.
    pub fn sampling(&self) -> Sampling {
        self.p.sampling
    }
    /// Instrument response.
    pub fn irf(&self) -> Irf {
        self.p.irf
    }
    /// Noise settings.
    pub fn noise(&self) -> NoiseParams {
        self.p.noise
    }
    /// Check that a code set fits this sensor (block, taps, length, drain).
    pub fn check_codes(&self, codes: &Codes) -> Result<()> {
        let (a, b) = (self.shape(), codes.shape());
        if a != b {
            return Err(invalid(
                "codes",
                format!("block {}x{}, {} taps, L = {}, drain {}", b.bh, b.bw, b.taps, b.length, b.drain),
                format!("block {}x{}, {} taps, L = {}, drain {} as the sensor", a.bh, a.bw, a.taps, a.length, a.drain),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sampling_from_factors_takes_one_or_the_default() {
        let d = Sampling::Oversample(1);
        assert_eq!(Sampling::from_factors(None, None, d).unwrap(), d);
        assert_eq!(Sampling::from_factors(None, None, Sampling::Heterodyne(8)).unwrap(), Sampling::Heterodyne(8));
        assert_eq!(Sampling::from_factors(Some(4), None, d).unwrap(), Sampling::Oversample(4));
        assert_eq!(Sampling::from_factors(None, Some(8), d).unwrap(), Sampling::Heterodyne(8));
        let e = Sampling::from_factors(Some(2), Some(8), d).unwrap_err().to_string();
        assert!(e.contains("oversample 2 and heterodyne 8"), "{e}");
    }

    #[test]
    fn validate_rejects_bad_values() {
        let ok = SensorParams::default().validate().unwrap();
        assert_eq!(ok.bins(), 32);
        assert!((ok.bin_width_s() - 1.0 / 607e6).abs() < 1e-18);
        let e = SensorParams { length: 30, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("length: got 30, expected a multiple of 8"), "{e}");
        let e = SensorParams { taps: 9, ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("taps"));
        for clock_hz in [1e-294, 0.5e6, 11e9, f64::NAN] {
            let e = SensorParams { clock_hz, ..Default::default() }.validate().unwrap_err().to_string();
            assert!(e.contains("clock_hz") && e.contains("1 MHz to 10 GHz"), "{e}");
        }
        let e = SensorParams { sampling: Sampling::Heterodyne(0), ..Default::default() }.validate().unwrap_err();
        assert!(e.to_string().contains("heterodyne"));
        let p = SensorParams { sampling: Sampling::Heterodyne(8), ..Default::default() }.validate().unwrap();
        assert_eq!(p.bins(), 256);
        for (fwhm, tau, field) in
            [(1e20, 0.3e-9, "laser_fwhm"), (f64::NAN, 0.3e-9, "laser_fwhm"), (2.55e-9, 2e-6, "tap_tau"), (2.55e-9, -1e-9, "tap_tau")]
        {
            let e =
                SensorParams { irf: Irf::Physical { laser_fwhm_s: fwhm, tap_tau_s: tau }, ..Default::default() }.validate().unwrap_err();
            assert!(e.to_string().contains(field) && e.to_string().contains("1 µs"), "{e}");
        }
        assert!((p.bin_width_s() - 206e-12).abs() < 1e-12, "Δ ≈ 206 ps at 607 MHz");
    }

    #[test]
    fn noise_params_are_bounded() {
        assert!(NoiseParams::default().validate().is_ok());
        assert!(NoiseParams { full_well_e: MAX_FULL_WELL_E, read_noise_e: 1e4, ..Default::default() }.validate().is_ok());
        for full_well_e in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e308, 1.01 * MAX_FULL_WELL_E] {
            let e = NoiseParams { full_well_e, ..Default::default() }.validate().unwrap_err().to_string();
            assert!(e.contains("full_well") && e.contains("up to 1e12"), "{e}");
        }
        for read_noise_e in [-1.0, f64::NAN, f64::INFINITY, 1e308, 20_001.0] {
            let e = NoiseParams { read_noise_e, ..Default::default() }.validate().unwrap_err().to_string();
            assert!(e.contains("read_noise") && e.contains("up to the full well"), "{e}");
        }
    }
}
