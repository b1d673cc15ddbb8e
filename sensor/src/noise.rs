//! The sensor's noise model (DESIGN §3), in electrons:
//!
//! 1. scale the noiseless tap values `y` by `s` electrons per unit, chosen so that the brightest
//!    tap reaches `signal_fraction · full_well` (or given explicitly);
//! 2. Poisson shot noise: `e ~ Poisson(s·y)`;
//! 3. Gaussian read noise: `e += N(0, σ_read²)`;
//! 4. clip to `[0, full_well]`;
//! 5. quantise to `2^bits − 1` ADC steps over the full well (`bits = 0`: off).
//!
//! Mean and variance before clipping and quantisation: `E[e] = s·y`, `Var[e] = s·y + σ_read²`.
//! Randomness is drawn per fixed chunk of 4096 values from a generator seeded by
//! `(seed, chunk)`, so the output depends on the seed only, never on the thread count.

use crate::error::{invalid, Result};
use crate::params::NoiseParams;
use ndarray::{ArrayD, ArrayViewD};
use rand::rngs::StdRng;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal, Poisson};
use rayon::prelude::*;

const CHUNK: usize = 4096;

/// How tap values map to electrons.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Exposure {
    /// The brightest tap value is scaled to the noise model's `signal_fraction` of full well.
    Auto,
    /// A fixed number of electrons per unit of `y`.
    ElectronsPerUnit(f64),
}

impl Exposure {
    /// Electrons per unit of `y` (whose largest value is `peak`) under `noise`: the given
    /// number, checked, or the one that brings `peak` to `signal_fraction` of full well
    /// (`1` for a dark frame).
    pub fn electrons_per_unit(self, peak: f32, noise: &NoiseParams) -> Result<f64> {
        match self {
            Exposure::ElectronsPerUnit(s) if s > 0.0 && s <= MAX_ELECTRONS_PER_UNIT => Ok(s),
            Exposure::ElectronsPerUnit(s) => {
                Err(invalid("electrons_per_unit", s, format!("a positive number up to {MAX_ELECTRONS_PER_UNIT:e}")))
            }
            Exposure::Auto if peak > 0.0 => Ok(noise.signal_fraction * noise.full_well_e / peak as f64),
            Exposure::Auto => Ok(1.0),
        }
    }
}

/// The largest explicit scale of the noise model (electrons per unit of the input).
pub const MAX_ELECTRONS_PER_UNIT: f64 = 1e12;

/// Noisy measurements, in electrons, with the scale used.
#[derive(Debug, Clone)]
pub struct NoisyMeasurement {
    /// Noisy (clipped, quantised) tap values in electrons, same shape as the input.
    pub electrons: ArrayD<f32>,
    /// Electrons per unit of the noiseless input.
    pub electrons_per_unit: f64,
}

impl NoisyMeasurement {
    /// The noisy values back in the units of the noiseless input (`electrons / s`).
    pub fn in_input_units(&self) -> ArrayD<f32> {
        let s = self.electrons_per_unit as f32;
        if s.is_normal() {
            self.electrons.mapv(|e| e / s)
        } else {
            // a scale past f32's range (a faint input's): divided in f64
            let s = self.electrons_per_unit;
            self.electrons.mapv(|e| (e as f64 / s) as f32)
        }
    }
    /// ADC codes (digital numbers), `round(e / lsb)`; equals electrons when quantisation is off.
    pub fn in_adc_codes(&self, noise: &NoiseParams) -> ArrayD<f32> {
        match lsb(noise) {
            Some(l) => self.electrons.mapv(|e| (e as f64 / l).round() as f32),
            None => self.electrons.clone(),
        }
    }
}

fn lsb(noise: &NoiseParams) -> Option<f64> {
    (noise.adc_bits > 0).then(|| noise.full_well_e / ((1u64 << noise.adc_bits) - 1) as f64)
}

/// A seed for stream `stream` derived from `seed` (SplitMix64 finaliser).
pub fn derive_seed(seed: u64, stream: u64) -> u64 {
    let mut z = seed ^ stream.wrapping_add(1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// Apply the noise model to noiseless tap values `y` (any shape, e.g. `[M, H, W]` or `[B, M, H, W]`).
pub fn add_noise(y: &ArrayViewD<'_, f32>, noise: &NoiseParams, exposure: Exposure, seed: u64) -> Result<NoisyMeasurement> {
    let noise = noise.validate()?;
    let scale = exposure.electrons_per_unit(y.iter().fold(0f32, |a, &v| a.max(v)), &noise)?;
    let input: Vec<f32> = y.iter().copied().collect();
    let mut out = vec![0f32; input.len()];
    let read = Normal::new(0.0, noise.read_noise_e).map_err(|e| invalid("read_noise", noise.read_noise_e, e.to_string()))?;
    let q = lsb(&noise);
    out.par_chunks_mut(CHUNK).zip(input.par_chunks(CHUNK)).enumerate().for_each(|(ci, (o, inp))| {
        let mut rng = StdRng::seed_from_u64(derive_seed(seed, ci as u64));
        for (d, &v) in o.iter_mut().zip(inp) {
            let lambda = (v as f64 * scale).max(0.0);
            let shot = if lambda > 0.0 { Poisson::new(lambda).map(|p| p.sample(&mut rng)).unwrap_or(lambda) } else { 0.0 };
            let mut e = shot + if noise.read_noise_e > 0.0 { read.sample(&mut rng) } else { 0.0 };
            e = e.clamp(0.0, noise.full_well_e);
            if let Some(l) = q {
                e = (e / l).round() * l;
            }
            *d = e as f32;
        }
    });
    let electrons =
        ArrayD::from_shape_vec(y.raw_dim(), out).map_err(|e| invalid("noise input", format!("{:?}", y.shape()), e.to_string()))?;
    Ok(NoisyMeasurement { electrons, electrons_per_unit: scale })
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array1;

    #[test]
    fn mean_and_variance_match_the_model() {
        let noise = NoiseParams { full_well_e: 1e9, read_noise_e: 40.0, signal_fraction: 1.0, adc_bits: 0 };
        let n = 200_000;
        for &level in &[0.0f32, 10.0, 2500.0] {
            let y = Array1::from_elem(n, level).into_dyn();
            let out = add_noise(&y.view(), &noise, Exposure::ElectronsPerUnit(1.0), 3).unwrap();
            let v: Vec<f64> = out.electrons.iter().map(|&e| e as f64).collect();
            let mean = v.iter().sum::<f64>() / n as f64;
            let var = v.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
            let want_var = level as f64 + 1600.0;
            if level > 100.0 {
                // standard error of the mean ≈ sqrt(var/n) ≈ 0.14; of the variance ≈ var·sqrt(2/n) ≈ 0.3 %
                assert!((mean - level as f64).abs() < 0.7, "mean {mean} for {level}");
                assert!((var / want_var - 1.0).abs() < 0.02, "var {var} want {want_var}");
            } else {
                // clipping at 0 biases low levels upwards: the mean of max(N(μ, σ²), 0)
                assert!(mean > level as f64);
            }
        }
    }

    #[test]
    fn clipping_quantisation_scale_and_seed() {
        let noise = NoiseParams { full_well_e: 20_000.0, read_noise_e: 40.0, signal_fraction: 0.5, adc_bits: 8 };
        let y = Array1::from_vec(vec![0.0f32, 1.0, 2.0, 4.0]).into_dyn();
        let a = add_noise(&y.view(), &noise, Exposure::Auto, 9).unwrap();
        assert!((a.electrons_per_unit - 2500.0).abs() < 1e-9, "brightest tap -> 50 % of full well");
        let lsb = 20_000.0 / 255.0;
        for &e in a.electrons.iter() {
            let k = e as f64 / lsb;
            assert!((k - k.round()).abs() < 1e-3 && (0.0..=20_000.0).contains(&(e as f64)));
        }
        let b = add_noise(&y.view(), &noise, Exposure::Auto, 9).unwrap();
        assert_eq!(a.electrons, b.electrons);
        let over = add_noise(&y.view(), &noise, Exposure::ElectronsPerUnit(1e6), 9).unwrap();
        assert_eq!(over.electrons[3], 20_000.0, "clipped at full well");
        let codes = a.in_adc_codes(&noise);
        assert!(codes.iter().all(|&c| c == c.round() && c <= 255.0));
    }
}
