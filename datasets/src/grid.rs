//! The reconstruction time grid: `T = L·K` bins of `Δt = T_c/K`; bin `j` covers `[jΔt, (j+1)Δt)`.

use crate::error::{invalid, Result};
use serde::{Deserialize, Serialize};
use tcsense_sensor::{Sampling, SensorSpec};

/// Speed of light (m/s).
pub use tcsense_sensor::C;

/// A time grid tied to a code clock.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TimeGrid {
    /// Masks per cycle `L`.
    pub length: usize,
    /// Code clock (Hz).
    pub clock_hz: f64,
    /// Oversampling or heterodyne factor `K`.
    pub sampling: Sampling,
}

impl TimeGrid {
    /// Check ranges (`L` multiple of 8 in 8..=256, `K` in 1..=64, a clock of 1 MHz to 10 GHz).
    pub fn validate(self) -> Result<Self> {
        if self.length % 8 != 0 || !(8..=256).contains(&self.length) {
            return Err(invalid("length", self.length, "a multiple of 8 in 8..=256"));
        }
        if !(1..=64).contains(&self.sampling.k()) {
            return Err(invalid("K", self.sampling.k(), "1..=64"));
        }
        tcsense_sensor::codes::check_clock(self.clock_hz)?;
        Ok(self)
    }
    /// The grid of a sensor spec.
    pub fn of(spec: &SensorSpec) -> Self {
        TimeGrid { length: spec.params().length, clock_hz: spec.params().clock_hz, sampling: spec.sampling() }
    }
    /// Bins `T = L·K`.
    pub fn bins(&self) -> usize {
        self.length * self.sampling.k()
    }
    /// Bin width `Δt` (s).
    pub fn bin_width_s(&self) -> f64 {
        1.0 / (self.clock_hz * self.sampling.k() as f64)
    }
    /// Cycle `L·T_c` (s).
    pub fn cycle_s(&self) -> f64 {
        self.length as f64 / self.clock_hz
    }
    /// The grid as the waveforms see it: `T` bins of `Δt`, period `L·T_c`.
    pub fn cycle(&self) -> tcsense_sensor::waveform::Cycle {
        tcsense_sensor::waveform::Cycle { bins: self.bins(), dt_s: self.bin_width_s(), period_s: self.cycle_s() }
    }
    /// Unambiguous range `L·T_c·c/2` (m).
    pub fn range_m(&self) -> f64 {
        self.cycle_s() * C / 2.0
    }
    /// Add an impulse of area `a` arriving at time `t` (s) into `wave` (`T` bins), split
    /// linearly between the two bins whose centres enclose `t` (cyclic).
    pub fn splat(&self, wave: &mut [f32], t: f64, a: f64) {
        let n = wave.len() as f64;
        let u = (t / self.bin_width_s() - 0.5).rem_euclid(n);
        let j0 = u.floor();
        let frac = u - j0;
        let j0 = j0 as usize % wave.len();
        let j1 = (j0 + 1) % wave.len();
        wave[j0] += (a * (1.0 - frac)) as f32;
        wave[j1] += (a * frac) as f32;
    }
}

impl Default for TimeGrid {
    fn default() -> Self {
        TimeGrid { length: 32, clock_hz: 607e6, sampling: Sampling::Oversample(1) }
    }
}
