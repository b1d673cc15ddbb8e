//! The waveform mathematics every crate shares: where a pixel sits in the code block, the
//! periodic decay of a fluorophore on the time grid, the Gaussian instrument response as a
//! cyclic kernel, `erf`, and the parsing of an IRF description (`ideal`, `physical`, `A.npy`).
//!
//! One home, so that the dataset generator, the bounds of `codes analyze` and the fits in the
//! tap domain integrate the same decay and blur it with the same kernel: a dataset's waveform
//! and the template a fit matches it with agree to the last bit.
//!
//! The excitation repeats every code cycle `P = T·Δt`, so a decay that starts at `t₀` is the
//! periodic sum `D_τ(t) = Σ_k e^{−(t − t₀ + kP)/τ}`, here integrated exactly over each bin
//! (the tail of the previous cycle's pulse included):
//!
//! ```
//! use tcsense_sensor::waveform::{decay_bin_averages, subpixel, Cycle, IrfKernel};
//!
//! let c = Cycle::new(64, 0.2e-9);
//! let d = decay_bin_averages(c, 2e-9, 3.1e-9); // [T]
//! // the average of the periodic decay over a cycle is τ/P
//! let mean = d.iter().sum::<f64>() / 64.0;
//! assert!((mean - 2e-9 / c.period_s).abs() < 1e-12);
//! // a Gaussian IRF keeps the area
//! let blurred = IrfKernel::gaussian(c, 0.5e-9).apply(&d);
//! assert!((blurred.iter().sum::<f64>() - d.iter().sum::<f64>()).abs() < 1e-9);
//! // pixel (3, 2) of a 2×2 block is subpixel n = (3 mod 2)·2 + 2 mod 2 = 2
//! assert_eq!(subpixel(3, 2, (2, 2)), 2);
//! ```

use std::path::PathBuf;

use crate::{Irf, SensorError};

/// The subpixel `n(i, j) = (i mod bh)·bw + (j mod bw)` of pixel row `i`, column `j` in a code
/// block of `bh × bw` (paper eq. 4): the index of its matrix `A[n]`.
#[inline]
pub fn subpixel(i: usize, j: usize, (bh, bw): (usize, usize)) -> usize {
    (i % bh) * bw + j % bw
}

/// The subpixel of flat pixel index `p = i·w + j` of a frame `w` pixels wide ([`subpixel`]).
#[inline]
pub fn subpixel_flat(p: usize, w: usize, block: (usize, usize)) -> usize {
    subpixel(p / w, p % w, block)
}

/// A cycle's time grid: `bins` bins of `dt_s`, period `period_s` (`bins·dt_s`, or the
/// caller's own statement of it, e.g. `L·T_c`, which may differ in the last bit).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Cycle {
    pub bins: usize,
    pub dt_s: f64,
    pub period_s: f64,
}

impl Cycle {
    /// `bins` bins of `dt_s`; the period is `bins·dt_s`.
    pub fn new(bins: usize, dt_s: f64) -> Cycle {
        Cycle { bins, dt_s, period_s: bins as f64 * dt_s }
    }
}

/// `erf(x)` (Abramowitz & Stegun 7.1.26, |error| < 1.5e-7).
pub fn erf(x: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.327_591_1 * x.abs());
    let poly = t * (0.254_829_592 + t * (-0.284_496_736 + t * (1.421_413_741 + t * (-1.453_152_027 + t * 1.061_405_429))));
    (1.0 - poly * (-x * x).exp()).copysign(x)
}

/// `∫_bin j e^{−(u − t₀)/τ} du` over each bin of the cycle, for a decay starting at `onset_s`
/// (taken modulo the period) and the tail of the previous cycle's, unnormalised: the one
/// integral behind [`decay_unit_sum`] and [`decay_bin_averages`].
///
/// # Shapes
/// - returns `[T]`
pub fn decay_integrals(c: Cycle, tau_s: f64, onset_s: f64) -> Vec<f64> {
    let (dt, p) = (c.dt_s, c.period_s);
    let t0 = onset_s.rem_euclid(p);
    // e^x, the last one kept: a bin's upper edge is the next bin's lower edge, the same argument
    // (the same bits), so each edge's exponential is computed once
    let mut last = (f64::NAN, f64::NAN);
    let mut exp = |x: f64| -> f64 {
        if x.to_bits() != last.0.to_bits() {
            last = (x, x.exp());
        }
        last.1
    };
    // ∫_a^b e^{−(u−s)/τ} du for a ≥ s
    let mut seg = |a: f64, b: f64, s: f64| {
        let lower = exp(-(a - s) / tau_s);
        tau_s * (lower - exp(-(b - s) / tau_s))
    };
    (0..c.bins)
        .map(|j| {
            let (a, b) = (j as f64 * dt, (j + 1) as f64 * dt);
            let mut v = 0.0;
            // at or after the onset: this cycle's pulse
            if b > t0 {
                v += seg(a.max(t0), b, t0);
            }
            // before the onset: the tail of the previous cycle's pulse
            if a < t0 {
                v += seg(a, b.min(t0), t0 - p);
            }
            v
        })
        .collect()
}

/// The periodic decay of unit sum over the cycle (the share of a decay's photons in each bin).
///
/// # Shapes
/// - returns `[T]`
pub fn decay_unit_sum(c: Cycle, tau_s: f64, onset_s: f64) -> Vec<f64> {
    let norm = 1.0 / (tau_s * (1.0 - (-c.period_s / tau_s).exp()));
    decay_integrals(c, tau_s, onset_s).into_iter().map(|v| v * norm).collect()
}

/// Bin averages of the periodic unit decay `D_τ(t) = Σ_k e^{−(t − t₀ + kP)/τ}` (peak value
/// about 1 for `τ ≪ P`; its mean over the cycle is `τ/P`).
///
/// # Shapes
/// - returns `[T]`
pub fn decay_bin_averages(c: Cycle, tau_s: f64, onset_s: f64) -> Vec<f64> {
    let norm = 1.0 / (1.0 - (-c.period_s / tau_s).exp());
    decay_integrals(c, tau_s, onset_s).into_iter().map(|v| v * norm / c.dt_s).collect()
}

/// An instrument response as a cyclic kernel `k[d]`, `d = −r..=r` bins, applied with
/// [`IrfKernel::apply`] (area kept).
#[derive(Debug, Clone, PartialEq)]
pub struct IrfKernel {
    taps: Vec<f64>,
    reach: usize,
    total: f64,
}

impl IrfKernel {
    /// A delta: no blur.
    pub fn delta() -> IrfKernel {
        IrfKernel { taps: vec![1.0], reach: 0, total: 1.0 }
    }

    /// A Gaussian of FWHM `fwhm_s` (`σ = FWHM/√(8 ln 2)`) integrated over each bin, out to 4σ
    /// (the mass beyond is 6·10⁻⁵) and at most half the cycle; a delta for a FWHM ≤ 0.
    pub fn gaussian(c: Cycle, fwhm_s: f64) -> IrfKernel {
        if fwhm_s <= 0.0 || c.bins == 0 {
            return IrfKernel::delta();
        }
        let sigma = fwhm_s / (8.0 * 2f64.ln()).sqrt() / c.dt_s; // in bins
        let reach = ((4.0 * sigma).ceil() as usize).min(c.bins / 2).max(1);
        let cdf = |x: f64| 0.5 * (1.0 + erf(x / (sigma * std::f64::consts::SQRT_2)));
        let taps: Vec<f64> = (0..=2 * reach).map(|i| i as f64 - reach as f64).map(|d| cdf(d + 0.5) - cdf(d - 0.5)).collect();
        let total = taps.iter().sum();
        IrfKernel { taps, reach, total }
    }

    /// A measured response (one value per bin of the cycle) as a centred kernel: the response
    /// itself with its peak moved to bin 0, so that a fitted onset carries its delay.
    pub fn measured(irf: &[f64]) -> IrfKernel {
        let n = irf.len();
        let s: f64 = irf.iter().sum::<f64>().max(1e-300);
        let reach = n / 2;
        let peak = irf.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(i, _)| i);
        let taps = (0..=2 * reach).map(|i| if i < n { irf[(peak + n + i - reach) % n] / s } else { 0.0 }).collect();
        IrfKernel { taps, reach, total: 1.0 }
    }

    /// The kernel's weights `(d, k[d] / Σk)` at offsets `d = −r..=r` bins (they sum to 1).
    pub fn weights(&self) -> impl Iterator<Item = (isize, f64)> + '_ {
        self.taps.iter().enumerate().map(|(i, k)| (i as isize - self.reach as isize, k / self.total))
    }

    /// Cyclic convolution `(k ⊛ v)[j] = Σ_d k[d]·v[j − d] / Σ_d k[d]`.
    ///
    /// # Shapes
    /// - `v`: `[T]` → `[T]`
    pub fn apply(&self, v: &[f64]) -> Vec<f64> {
        let n = v.len();
        if self.reach == 0 || n == 0 {
            return v.to_vec();
        }
        // `v` cyclically extended by the reach on both sides, `ext[q] = v[(q − r) mod n]`, so that
        // tap `i` (offset `d = i − r`) reads `v[(j − d) mod n] = ext[j + 2r − i]`: no modulo per
        // multiply-add, and each output's products added in the taps' order as before (the same
        // bits), the outputs a vector at a time
        let r = self.reach;
        let ext: Vec<f64> = (0..n + 2 * r).map(|q| v[(q + n - r % n) % n]).collect();
        let mut out = vec![0f64; n];
        for (i, &k) in self.taps.iter().enumerate() {
            let src = &ext[2 * r - i..2 * r - i + n];
            if i == 0 {
                out.iter_mut().zip(src).for_each(|(o, &x)| *o = k * x);
            } else {
                out.iter_mut().zip(src).for_each(|(o, &x)| *o += k * x);
            }
        }
        out.iter_mut().for_each(|o| *o /= self.total);
        out
    }
}

/// An instrument response as a user names it: a model, or a measured matrix file.
#[derive(Debug, Clone, PartialEq)]
pub enum IrfSpec {
    /// `ideal` or `physical`.
    Model(Irf),
    /// A measured matrix `A.npy` `[N, M, T]`.
    Measured(PathBuf),
}

/// What [`parse_irf`] accepts, for messages.
pub const IRF_CHOICES: &str =
    "`ideal` (rectangular gates), `physical` (laser pulse ⋆ tap response) or a measured matrix file `A.npy` [N, M, T]";

/// Parse an IRF description: `ideal`, `physical` (with this laser pulse FWHM and tap time
/// constant, s) or a path ending in `.npy`, a measured matrix. `field` names the flag or key
/// in the error.
pub fn parse_irf(desc: &str, laser_fwhm_s: f64, tap_tau_s: f64, field: &'static str) -> Result<IrfSpec, SensorError> {
    match desc {
        "ideal" => Ok(IrfSpec::Model(Irf::Ideal)),
        "physical" => Ok(IrfSpec::Model(Irf::Physical { laser_fwhm_s, tap_tau_s })),
        p if p.ends_with(".npy") => Ok(IrfSpec::Measured(PathBuf::from(p))),
        other => Err(SensorError::InvalidParam { field, got: format!("{other:?}"), expected: IRF_CHOICES.into() }),
    }
}

/// [`parse_irf`] with the sensor's default laser pulse and tap response.
pub fn parse_irf_default(desc: &str, field: &'static str) -> Result<IrfSpec, SensorError> {
    parse_irf(desc, crate::params::DEFAULT_LASER_FWHM_S, crate::params::DEFAULT_TAP_TAU_S, field)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erf_matches_tabulated_values() {
        assert!((erf(0.5) - 0.520_499_877_8).abs() < 2e-7 && (erf(-1.2) + 0.910_313_978_2).abs() < 2e-7);
    }

    #[test]
    fn decays_integrate_exactly() {
        let c = Cycle::new(64, 0.2e-9);
        let (tau, t0) = (2e-9, 3.1e-9);
        let u = decay_unit_sum(c, tau, t0);
        assert!((u.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        // onset 3.1 ns = bin 15.5: the cyclic tail before it is tiny but not zero
        assert!(u[15] > u[14] * 10.0 && u[16] > u[15] && u[14] > 0.0, "{:?}", &u[12..18]);
        // bin averages: the unit-sum decay times τ/Δt (so their mean is τ/P)
        let avg = decay_bin_averages(c, tau, t0);
        for (a, b) in avg.iter().zip(&u) {
            assert!((a - b * tau / c.dt_s).abs() < 1e-9 * a.max(1e-12));
        }
        // an onset a whole period later is the same decay
        let later = decay_integrals(c, tau, t0 + c.period_s);
        assert!(later.iter().zip(decay_integrals(c, tau, t0)).all(|(a, b)| (a - b).abs() < 1e-18));
    }

    #[test]
    fn kernels_keep_the_area_and_widen_the_rise() {
        let c = Cycle::new(64, 0.2e-9);
        let d = decay_bin_averages(c, 1e-9, 3e-9);
        let g = IrfKernel::gaussian(c, 0.6e-9);
        let b = g.apply(&d);
        assert!((b.iter().sum::<f64>() - d.iter().sum::<f64>()).abs() < 1e-9);
        // blurred, the bin before the onset gains light and the peak falls
        assert!(b[14] > d[14] && b[15] < d[15]);
        assert_eq!(IrfKernel::gaussian(c, 0.0).apply(&d), d);
        // a measured delta at bin 7 is a delta at 0 (its delay is the onset's)
        let mut m = vec![0.0; 64];
        m[7] = 2.0;
        assert_eq!(IrfKernel::measured(&m).apply(&d), d);
    }

    #[test]
    fn kernels_apply_as_the_cyclic_sum_written_out() {
        // the sum as the docs write it, one modulo per multiply-add: the same bits
        let naive = |k: &IrfKernel, v: &[f64]| -> Vec<f64> {
            let n = v.len();
            (0..n).map(|j| k.taps.iter().enumerate().map(|(i, t)| t * v[(j + k.reach + n - i) % n]).sum::<f64>() / k.total).collect()
        };
        let mut state = 12345u64;
        let mut next = || {
            state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for n in [1usize, 2, 5, 16, 33, 256] {
            let v: Vec<f64> = (0..n).map(|_| next()).collect();
            let measured: Vec<f64> = (0..n).map(|_| next()).collect();
            let c = Cycle::new(n, 0.2e-9);
            for k in [
                IrfKernel::gaussian(c, 0.3e-9),
                IrfKernel::gaussian(c, 2e-9),
                IrfKernel::gaussian(c, 50e-9),
                IrfKernel::measured(&measured),
            ] {
                let (got, want) = (k.apply(&v), naive(&k, &v));
                assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "n {n}, reach {}: {got:?} != {want:?}", k.reach);
            }
        }
    }

    /// Each bin's two edges written out (two exponentials a bin): the same bits as the
    /// integrals that compute each edge once.
    #[test]
    fn decay_integrals_are_each_bins_edges_written_out() {
        let c = Cycle::new(64, 0.4e-9);
        for (tau, onset) in [(0.3e-9, 0.0), (2.5e-9, 7.3e-9), (9e-9, 25.6e-9), (1e-9, -3.1e-9), (4e-9, 0.4e-9 * 17.0)] {
            let t0 = f64::rem_euclid(onset, c.period_s);
            let seg = |a: f64, b: f64, s: f64| tau * ((-(a - s) / tau).exp() - (-(b - s) / tau).exp());
            let want: Vec<f64> = (0..c.bins)
                .map(|j| {
                    let (a, b) = (j as f64 * c.dt_s, (j + 1) as f64 * c.dt_s);
                    let mut v = 0.0;
                    if b > t0 {
                        v += seg(a.max(t0), b, t0);
                    }
                    if a < t0 {
                        v += seg(a, b.min(t0), t0 - c.period_s);
                    }
                    v
                })
                .collect();
            let got = decay_integrals(c, tau, onset);
            assert!(got.iter().zip(&want).all(|(x, y)| x.to_bits() == y.to_bits()), "τ {tau}, onset {onset}");
        }
    }

    #[test]
    fn irf_descriptions_parse_or_name_what_is_expected() {
        assert_eq!(parse_irf("ideal", 1.0, 2.0, "--irf").unwrap(), IrfSpec::Model(Irf::Ideal));
        assert_eq!(parse_irf("physical", 1.0, 2.0, "--irf").unwrap(), IrfSpec::Model(Irf::Physical { laser_fwhm_s: 1.0, tap_tau_s: 2.0 }));
        assert_eq!(parse_irf("m/A.npy", 1.0, 2.0, "--irf").unwrap(), IrfSpec::Measured("m/A.npy".into()));
        let e = parse_irf("gauss", 1.0, 2.0, "--irf").unwrap_err().to_string();
        assert!(e.contains("--irf") && e.contains("\"gauss\"") && e.contains("physical"), "{e}");
    }
}
