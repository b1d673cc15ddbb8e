//! A real sensor's departures from the ideal model (issue 29): what calibration measures and
//! what decoders must survive.
//!
//! The nominal sensor is `y = A x` per pixel. A real multitap pixel at `p` (subpixel type
//! `n(p)`) gives, in electrons,
//!
//! `e[m, p] = s · G[m, p] · (A' x_p)[m] + d[m, p]`, `A'[n] = diag(g) · X · (A[n] ⊛ h_tail)(· − δ)`
//!
//! - `g[m] = 1 + u_m`, `u_m ~ U(−tap_gain, tap_gain)`: per-tap gain mismatch;
//! - `G[m, p] = 1 + N(0, prnu²)`: per-pixel, per-tap gain (photo-response non-uniformity);
//! - `d[m, p] = full_well · (dark + N(0, dark_fpn²))` (≥ 0): dark offset with fixed-pattern noise;
//! - `X = (1 − c)·I + c/(M − 1)·(11ᵀ − I)`: tap crosstalk, a share `c` of each tap's charge
//!   leaks evenly into the other taps;
//! - `h_tail`: diffusion tail: a share `tail` of the charge generated in bin `j` is collected
//!   later, over the bins `j + k` with weights `∝ exp(−kΔt/tail_tau)` (cyclic), so
//!   `A'[·, ·, j] = (1 − tail)·A[·, ·, j] + tail·Σ_{k≥1} w_k A[·, ·, j + k]`;
//! - `δ = shift`: the whole response arrives `δ` late (drift), linearly interpolated between
//!   bins (cyclic): `A'[·, ·, j] = A[·, ·, j − δ/Δt]`;
//! - `δ_m = gate_skew · v_m`, `v_m ~ U(−1, 1)`: each tap's gate opens `δ_m` late (skew between
//!   the taps' gate drivers): tap `m`'s row is delayed by `δ_m` the same way;
//! - a modulation contrast `C < 1` (what a lab measures of a multitap pixel: the lab's four-tap
//!   pixels report 92.5 %) is the crosstalk `c` it implies: with `1 − c` in the open tap and
//!   `c/(M − 1)` in each other, `C = (q_open − q_other)/(q_open + q_other)`, so
//!   `c = (1 − C) / ((1 + C)/(M − 1) + 1 − C)`;
//! - `κ = nonlinearity`: the collected charge is compressed near full well `F`,
//!   `e' = e·(1 − κ·e/F)` (κ ≤ ½ keeps it monotone; at full well the response is `1 − κ` of the
//!   linear one). A delay sweep at one level cannot see it: calibration leaves it in the residual.
//!
//! All are circular convolutions in time or mixes of taps, so they commute with the heterodyne
//! sum and act on the final `A`. The random parts are drawn from `seed` alone (the same seed,
//! the same sensor), in a fixed order, independent of the thread count.
//!
//! ```
//! use tcsense_sensor::nonideal::NonIdeal;
//! let n = NonIdeal { tap_gain: 0.05, prnu: 0.02, tail: 0.25, tail_tau_s: 2e-9, ..NonIdeal::default() };
//! assert!(NonIdeal { tail: 0.25, ..NonIdeal::default() }.validate().is_err(), "a tail needs its time constant");
//! assert!(n.validate().is_ok() && !n.is_ideal());
//! assert!(NonIdeal { prnu: -0.1, ..NonIdeal::default() }.validate().is_err());
//! ```

use ndarray::{Array3, Array4, ArrayView4};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use serde::{Deserialize, Serialize};

use crate::error::{invalid, Result};
use crate::matrix::MeasurementMatrix;
use crate::noise::{add_noise, derive_seed, Exposure, NoisyMeasurement};
use crate::params::NoiseParams;

/// The non-idealities of a sensor (all zero: the ideal sensor). Recorded in the sidecar of
/// simulated measurements.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct NonIdeal {
    /// Per-tap gain mismatch: gains uniform in `[1 − tap_gain, 1 + tap_gain]`.
    #[serde(default)]
    pub tap_gain: f64,
    /// Per-pixel, per-tap gain σ (PRNU), relative.
    #[serde(default)]
    pub prnu: f64,
    /// Mean dark offset, as a fraction of the full well.
    #[serde(default)]
    pub dark: f64,
    /// Dark fixed-pattern noise σ, as a fraction of the full well.
    #[serde(default)]
    pub dark_fpn: f64,
    /// Share of each tap's charge that leaks into the other taps.
    #[serde(default)]
    pub crosstalk: f64,
    /// Share of the charge collected late (diffusion tail).
    #[serde(default)]
    pub tail: f64,
    /// Time constant of the tail (s).
    #[serde(default)]
    pub tail_tau_s: f64,
    /// Delay of the whole response (s), drift.
    #[serde(default)]
    pub shift_s: f64,
    /// Skew of the taps' gates (s): tap `m` opens `gate_skew_s · v_m` late, `v_m ~ U(−1, 1)`.
    #[serde(default)]
    pub gate_skew_s: f64,
    /// Modulation contrast `C` of the pixel (0: not given; 1: no leakage), stated instead of
    /// `crosstalk`.
    #[serde(default)]
    pub modulation_contrast: f64,
    /// Response compression near full well, `e' = e·(1 − κ·e/F)` (`κ` in `[0, 0.5]`).
    #[serde(default)]
    pub nonlinearity: f64,
    /// Seed of the random parts (tap gains, PRNU, dark pattern).
    #[serde(default)]
    pub seed: u64,
}

/// Streams of [`derive_seed`] for the random parts.
const STREAM_TAP: u64 = 0x7a9;
const STREAM_PRNU: u64 = 0x9a1;
const STREAM_DARK: u64 = 0xda4;
const STREAM_SKEW: u64 = 0x5e3;

impl NonIdeal {
    /// Check the ranges; errors name the field.
    pub fn validate(self) -> Result<Self> {
        let frac = |field: &'static str, v: f64, max: f64| -> Result<()> {
            if !(v.is_finite() && (0.0..=max).contains(&v)) {
                return Err(invalid(field, v, format!("a fraction in [0, {max}]")));
            }
            Ok(())
        };
        frac("tap_gain", self.tap_gain, 0.5)?;
        frac("prnu", self.prnu, 0.2)?;
        frac("dark", self.dark, 0.5)?;
        frac("dark_fpn", self.dark_fpn, 0.1)?;
        frac("crosstalk", self.crosstalk, 0.5)?;
        frac("tail", self.tail, 0.9)?;
        // times: up to 1 µs, far beyond any cycle of these sensors (a drift or skew is taken
        // modulo the cycle; beyond that a value means nothing and loses its precision)
        let max = crate::params::MAX_RESPONSE_S;
        if self.tail > 0.0 && !(self.tail_tau_s.is_finite() && self.tail_tau_s > 0.0 && self.tail_tau_s <= max) {
            return Err(invalid("tail_tau", self.tail_tau_s, "a positive time constant up to 1 µs (1e-6 s) when tail > 0"));
        }
        // without a tail its time constant goes unused, but a value that means nothing is refused
        if !(self.tail_tau_s.is_finite() && (0.0..=max).contains(&self.tail_tau_s)) {
            return Err(invalid("tail_tau", self.tail_tau_s, "a time constant from 0 to 1 µs (1e-6 s)"));
        }
        if !(self.shift_s.is_finite() && self.shift_s.abs() <= max) {
            return Err(invalid("shift", self.shift_s, "a delay from −1 µs to 1 µs (s)"));
        }
        if !(self.gate_skew_s.is_finite() && (0.0..=max).contains(&self.gate_skew_s)) {
            return Err(invalid("gate_skew", self.gate_skew_s, "a non-negative delay up to 1 µs (1e-6 s)"));
        }
        if !(self.modulation_contrast == 0.0 || (self.modulation_contrast > 0.0 && self.modulation_contrast <= 1.0)) {
            return Err(invalid("modulation_contrast", self.modulation_contrast, "a contrast in (0, 1] (e.g. 0.925), or 0 for none given"));
        }
        if self.modulation_contrast > 0.0 && self.crosstalk > 0.0 {
            return Err(invalid(
                "modulation_contrast",
                self.modulation_contrast,
                "either a modulation contrast or a crosstalk share, not both (they state the same leakage)",
            ));
        }
        frac("nonlinearity", self.nonlinearity, 0.5)?;
        Ok(self)
    }

    /// True when every non-ideality is off.
    pub fn is_ideal(&self) -> bool {
        self.tap_gain == 0.0
            && self.prnu == 0.0
            && self.dark == 0.0
            && self.dark_fpn == 0.0
            && self.crosstalk == 0.0
            && self.tail == 0.0
            && self.shift_s == 0.0
            && self.gate_skew_s == 0.0
            && (self.modulation_contrast == 0.0 || self.modulation_contrast == 1.0)
            && self.nonlinearity == 0.0
    }

    /// The crosstalk share of `taps` taps: `crosstalk`, or the one a modulation contrast implies.
    pub fn leakage(&self, taps: usize) -> f64 {
        let c = self.modulation_contrast;
        if c > 0.0 && taps > 1 {
            (1.0 - c) / ((1.0 + c) / (taps - 1) as f64 + 1.0 - c)
        } else {
            self.crosstalk
        }
    }

    /// The taps' gate delays `δ_m` (s).
    pub fn gate_delays(&self, taps: usize) -> Vec<f64> {
        let mut rng = StdRng::seed_from_u64(derive_seed(self.seed, STREAM_SKEW));
        (0..taps).map(|_| if self.gate_skew_s > 0.0 { self.gate_skew_s * rng.random_range(-1.0..=1.0) } else { 0.0 }).collect()
    }

    /// The per-tap gains `g [M]`.
    pub fn tap_gains(&self, taps: usize) -> Vec<f64> {
        let mut rng = StdRng::seed_from_u64(derive_seed(self.seed, STREAM_TAP));
        (0..taps).map(|_| 1.0 + if self.tap_gain > 0.0 { rng.random_range(-self.tap_gain..=self.tap_gain) } else { 0.0 }).collect()
    }

    /// The real sensor's matrix `A' = diag(g)·X·(A ⊛ h_tail)(· − δ)` (see the module docs).
    ///
    /// # Shapes
    /// - `a`: `[N, M, T]` → `[N, M, T]`
    pub fn matrix(&self, a: &MeasurementMatrix) -> Result<MeasurementMatrix> {
        let nominal = a.a();
        let (_, m, t) = nominal.dim();
        let dt = a.bin_width_s();
        let mut out = nominal.mapv(|v| v as f64);
        // drift and the taps' gate skew: A'[m, j] = A[m, j − (δ + δ_m)/Δt], linear
        // interpolation, cyclic
        let skew = self.gate_delays(m);
        if self.shift_s != 0.0 || skew.iter().any(|&d| d != 0.0) {
            let src = out.clone();
            for ((k, r, j), v) in out.indexed_iter_mut() {
                let s = (self.shift_s + skew[r]) / dt;
                let (whole, frac) = (s.floor(), s - s.floor());
                let j0 = (j as i64 - whole as i64).rem_euclid(t as i64) as usize;
                let j1 = (j0 + t - 1) % t;
                *v = (1.0 - frac) * src[(k, r, j0)] + frac * src[(k, r, j1)];
            }
        }
        // diffusion tail: A'[j] = (1 − η)A[j] + η Σ_{k ≥ 1} w_k A[j + k]
        if self.tail > 0.0 {
            let w: Vec<f64> = (1..t).map(|k| (-(k as f64) * dt / self.tail_tau_s).exp()).collect();
            let total: f64 = w.iter().sum();
            let src = out.clone();
            for ((k, r, j), v) in out.indexed_iter_mut() {
                let late: f64 = w.iter().enumerate().map(|(i, wi)| wi * src[(k, r, (j + i + 1) % t)]).sum();
                *v = (1.0 - self.tail) * src[(k, r, j)] + self.tail * late / total.max(f64::MIN_POSITIVE);
            }
        }
        // crosstalk between taps (or the modulation contrast's leakage), then the tap gains
        let g = self.tap_gains(m);
        let leak = self.leakage(m);
        let src = out.clone();
        for ((k, r, j), v) in out.indexed_iter_mut() {
            let others: f64 = (0..m).filter(|&q| q != r).map(|q| src[(k, q, j)]).sum();
            let mixed = if m > 1 { (1.0 - leak) * src[(k, r, j)] + leak / (m - 1) as f64 * others } else { src[(k, r, j)] };
            *v = g[r] * mixed;
        }
        a.with_values(out.mapv(|v| v as f32))
    }

    /// The per-pixel gain `G [M, H, W]` and dark offset `d [M, H, W]` (fraction of the full
    /// well) of an `H × W` sensor.
    pub fn maps(&self, taps: usize, h: usize, w: usize) -> (Array3<f32>, Array3<f32>) {
        let mut rng = StdRng::seed_from_u64(derive_seed(self.seed, STREAM_PRNU));
        let unit = Normal::new(0.0, 1.0).expect("unit normal");
        let gain = Array3::from_shape_simple_fn((taps, h, w), || (1.0 + self.prnu * unit.sample(&mut rng)).max(0.05) as f32);
        let mut rng = StdRng::seed_from_u64(derive_seed(self.seed, STREAM_DARK));
        let dark = Array3::from_shape_simple_fn((taps, h, w), || (self.dark + self.dark_fpn * unit.sample(&mut rng)).max(0.0) as f32);
        (gain, dark)
    }

    /// This sensor, realised for `H × W` frames of the nominal sensor `a`.
    pub fn realise(&self, a: &MeasurementMatrix, h: usize, w: usize) -> Result<RealSensor> {
        let s = self.validate()?;
        let matrix = s.matrix(a)?;
        let (gain, dark) = s.maps(a.taps(), h, w);
        Ok(RealSensor { matrix, gain, dark, nonlinearity: s.nonlinearity })
    }
}

/// A non-ideal sensor realised for one frame size: its true matrix, gain and dark maps.
#[derive(Debug, Clone)]
pub struct RealSensor {
    /// `A'` (`[N, M, T]`).
    pub matrix: MeasurementMatrix,
    /// `G` (`[M, H, W]`).
    pub gain: Array3<f32>,
    /// `d` (`[M, H, W]`), fraction of the full well.
    pub dark: Array3<f32>,
    /// `κ`: the response's compression near full well.
    pub nonlinearity: f64,
}

impl RealSensor {
    /// Measure cubes `x` (`[B, T, H, W]`) in electrons: `s·G·(A'x) + d`, then (with `noisy`)
    /// shot and read noise, clipping and quantisation of `noise`. `exposure` sets `s`
    /// (`Auto`: the brightest signal tap of the batch at `signal_fraction` of full well).
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → electrons `[B, M, H, W]`
    pub fn measure(
        &self,
        x: &ArrayView4<'_, f32>,
        noise: &NoiseParams,
        noisy: bool,
        exposure: Exposure,
        seed: u64,
    ) -> Result<NoisyMeasurement> {
        let noise = noise.validate()?;
        let (_, _, h, w) = x.dim();
        let (_, gh, gw) = self.gain.dim();
        if (h, w) != (gh, gw) {
            return Err(invalid("frame size", format!("{h}x{w}"), format!("{gh}x{gw}, the size the sensor was realised for")));
        }
        let plan = self.matrix.plan(h, w)?;
        let mut y: Array4<f32> = plan.forward_batch(x)?;
        for mut frame in y.outer_iter_mut() {
            frame *= &self.gain;
        }
        let s = exposure.electrons_per_unit(y.iter().fold(0f32, |a, &v| a.max(v)), &noise)?;
        let fw = noise.full_well_e as f32;
        let mut mean = y.mapv(|v| v * s as f32);
        for mut frame in mean.outer_iter_mut() {
            frame.zip_mut_with(&self.dark, |e, d| *e += d * fw);
        }
        if self.nonlinearity > 0.0 {
            // e' = e·(1 − κ·e/F) up to full well (monotone for κ ≤ ½)
            let k = self.nonlinearity as f32;
            mean.mapv_inplace(|e| {
                let e = e.clamp(0.0, fw);
                e * (1.0 - k * e / fw)
            });
        }
        let electrons = if noisy {
            add_noise(&mean.view().into_dyn(), &noise, Exposure::ElectronsPerUnit(1.0), seed)?.electrons
        } else {
            mean.mapv(|e| e.clamp(0.0, fw)).into_dyn()
        };
        Ok(NoisyMeasurement { electrons, electrons_per_unit: s })
    }

    /// The dark offset in electrons (`[M, H, W]`).
    pub fn dark_electrons(&self, noise: &NoiseParams) -> Array3<f32> {
        self.dark.mapv(|d| d * noise.full_well_e as f32)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::{CodeShape, Constraints};
    use crate::generate::random_codes;
    use crate::SensorParams;

    fn nominal() -> MeasurementMatrix {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        let codes = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 3).unwrap();
        MeasurementMatrix::synthesize(&codes, &SensorParams::from_codes(&codes).validate().unwrap()).unwrap()
    }

    #[test]
    fn each_non_ideality_does_what_it_says() {
        let a = nominal();
        let (n, m, t) = a.a().dim();
        let dt = a.bin_width_s();
        // the ideal sensor is the nominal one
        assert_eq!(NonIdeal::default().matrix(&a).unwrap(), a);
        // a shift by two whole bins rolls the response
        let s = NonIdeal { shift_s: 2.0 * dt, ..NonIdeal::default() }.matrix(&a).unwrap();
        for (k, r, j) in [(0, 0, 0), (1, 2, 5), (3, 3, 15)] {
            assert_eq!(s.a()[(k, r, j)], a.a()[(k, r, (j + t - 2) % t)]);
        }
        // the tail keeps every column's charge (Σ_j A unchanged) and moves a share later
        let tl = NonIdeal { tail: 0.25, tail_tau_s: dt, ..NonIdeal::default() }.matrix(&a).unwrap();
        for k in 0..n {
            for r in 0..m {
                let (s0, s1): (f64, f64) = (0..t).fold((0.0, 0.0), |(p, q), j| (p + a.a()[(k, r, j)] as f64, q + tl.a()[(k, r, j)] as f64));
                assert!((s0 - s1).abs() < 1e-4 * s0.max(1.0), "tail changes the total: {s0} {s1}");
            }
        }
        let expect = 0.75 * a.a()[(0, 0, 3)] as f64
            + 0.25 * (1..t).map(|k| (-(k as f64)).exp() * a.a()[(0, 0, (3 + k) % t)] as f64).sum::<f64>()
                / (1..t).map(|k| (-(k as f64)).exp()).sum::<f64>();
        assert!((tl.a()[(0, 0, 3)] as f64 - expect).abs() < 1e-6);
        // crosstalk keeps Σ_m A per bin; gains scale whole tap rows
        let x = NonIdeal { crosstalk: 0.1, ..NonIdeal::default() }.matrix(&a).unwrap();
        let col = |mm: &MeasurementMatrix, k: usize, j: usize| (0..m).map(|r| mm.a()[(k, r, j)] as f64).sum::<f64>();
        assert!((col(&x, 2, 7) - col(&a, 2, 7)).abs() < 1e-6);
        assert!(x.a()[(0, 0, 0)] != a.a()[(0, 0, 0)] || x.a()[(0, 1, 0)] != a.a()[(0, 1, 0)]);
        let ni = NonIdeal { tap_gain: 0.08, seed: 4, ..NonIdeal::default() };
        let g = ni.tap_gains(m);
        assert!(g.iter().all(|v| (v - 1.0).abs() <= 0.08) && g.iter().any(|v| (v - 1.0).abs() > 0.01));
        let gm = ni.matrix(&a).unwrap();
        assert!((gm.a()[(1, 2, 9)] as f64 - g[2] * a.a()[(1, 2, 9)] as f64).abs() < 1e-6);
        assert_ne!(NonIdeal { seed: 5, ..ni }.tap_gains(m), g, "another seed, other gains");
    }

    #[test]
    fn gate_skew_contrast_and_nonlinearity_do_what_they_say() {
        let a = nominal();
        let (_, m, t) = a.a().dim();
        let dt = a.bin_width_s();
        // each tap's row is delayed by its own gate delay (whole bins here: rolled exactly)
        let ni = NonIdeal { gate_skew_s: 3.0 * dt, seed: 2, ..NonIdeal::default() };
        let d = ni.gate_delays(m);
        assert!(d.iter().all(|v| v.abs() <= 3.0 * dt) && d.iter().any(|v| v.abs() > 0.5 * dt), "{d:?}");
        assert!(d.windows(2).any(|w| w[0] != w[1]), "the taps are skewed against each other");
        let sk = ni.matrix(&a).unwrap();
        for r in 0..m {
            let s = d[r] / dt;
            let (whole, frac) = (s.floor(), s - s.floor());
            for j in [0, 5, t - 1] {
                let j0 = (j as i64 - whole as i64).rem_euclid(t as i64) as usize;
                let want = (1.0 - frac) * a.a()[(1, r, j0)] as f64 + frac * a.a()[(1, r, (j0 + t - 1) % t)] as f64;
                assert!((sk.a()[(1, r, j)] as f64 - want).abs() < 1e-6, "tap {r} bin {j}");
            }
        }
        // a modulation contrast of 92.5 % on 4 taps: the open tap keeps 1 − c, each other c/3,
        // and (open − other)/(open + other) is the contrast again
        let mc = NonIdeal { modulation_contrast: 0.925, ..NonIdeal::default() };
        let c = mc.leakage(4);
        assert!((c - 0.075 / (1.925 / 3.0 + 0.075)).abs() < 1e-12);
        let (open, other) = (1.0 - c, c / 3.0);
        assert!(((open - other) / (open + other) - 0.925).abs() < 1e-12);
        assert_eq!(mc.matrix(&a).unwrap(), NonIdeal { crosstalk: c, ..NonIdeal::default() }.matrix(&a).unwrap());
        assert!(NonIdeal { modulation_contrast: 0.9, crosstalk: 0.1, ..NonIdeal::default() }
            .validate()
            .unwrap_err()
            .to_string()
            .contains("not both"));
        assert!(NonIdeal { modulation_contrast: 1.2, ..NonIdeal::default() }.validate().is_err());
        // a tail's time constant that means nothing, with or without the tail
        for tail_tau_s in [f64::NAN, -1e-9, f64::INFINITY, 2e-6] {
            let e = NonIdeal { tail_tau_s, ..NonIdeal::default() }.validate().unwrap_err().to_string();
            assert!(e.contains("tail_tau"), "{e}");
        }
        assert!(NonIdeal { modulation_contrast: 1.0, ..NonIdeal::default() }.is_ideal());
        // κ = 0.2: half a full well reads 10 % low, a tenth 2 % low, monotone up to full well
        let real = NonIdeal { nonlinearity: 0.2, ..NonIdeal::default() }.realise(&a, 2, 2).unwrap();
        let noise = NoiseParams { adc_bits: 0, ..NoiseParams::default() };
        let x = Array4::<f32>::from_elem((1, a.bins(), 2, 2), 1.0);
        let y = a.plan(2, 2).unwrap().forward_batch(&x.view()).unwrap();
        let peak = y.iter().fold(0f32, |p, &v| p.max(v));
        let linear = |s: f64| y.mapv(|v| v * s as f32);
        for frac in [0.1f64, 0.5] {
            let s = frac * 20_000.0 / peak as f64;
            let e = real.measure(&x.view(), &noise, false, Exposure::ElectronsPerUnit(s), 0).unwrap().electrons;
            let (got, lin) = (e.iter().fold(0f32, |p, &v| p.max(v)) as f64, linear(s).iter().fold(0f32, |p, &v| p.max(v)) as f64);
            assert!((got / lin - (1.0 - 0.2 * frac)).abs() < 1e-4, "at {frac} of full well: {got} vs linear {lin}");
        }
        assert!(NonIdeal { nonlinearity: 0.6, ..NonIdeal::default() }.validate().is_err());
    }

    #[test]
    fn measurements_carry_gain_and_dark_and_are_seeded() {
        let a = nominal();
        let ni = NonIdeal { prnu: 0.02, dark: 0.01, dark_fpn: 0.002, seed: 9, ..NonIdeal::default() };
        let real = ni.realise(&a, 4, 6).unwrap();
        let (g, d) = ni.maps(4, 4, 6);
        assert_eq!((real.gain.clone(), real.dark.clone()), (g, d));
        let sd = (real.gain.mapv(|v| (v as f64 - 1.0).powi(2)).mean().unwrap()).sqrt();
        assert!(sd > 0.01 && sd < 0.03, "PRNU σ {sd}");
        let x = Array4::<f32>::from_elem((1, a.bins(), 4, 6), 0.5);
        let noise = NoiseParams { adc_bits: 0, ..NoiseParams::default() };
        let clean = real.measure(&x.view(), &noise, false, Exposure::ElectronsPerUnit(100.0), 0).unwrap();
        let y = a.plan(4, 6).unwrap().forward_batch(&x.view()).unwrap();
        for (idx, &e) in clean.electrons.indexed_iter() {
            let (b, r, i, j) = (idx[0], idx[1], idx[2], idx[3]);
            let want = 100.0 * real.gain[(r, i, j)] * y[(b, r, i, j)] + real.dark[(r, i, j)] * 20_000.0;
            assert!((e - want).abs() < 1e-2 * want.max(1.0), "{e} vs {want}");
        }
        let n1 = real.measure(&x.view(), &noise, true, Exposure::Auto, 3).unwrap();
        let n2 = real.measure(&x.view(), &noise, true, Exposure::Auto, 3).unwrap();
        assert_eq!(n1.electrons, n2.electrons);
        assert!(real.measure(&Array4::<f32>::zeros((1, a.bins(), 2, 2)).view(), &noise, false, Exposure::Auto, 0).is_err());
    }
}
