//! Training-time augmentation, applied to each batch of cubes before the sensor is simulated
//! (so the measurements are always physical):
//!
//! - **cyclic time shifts**: the codes loop every cycle, so rolling a cube by `k` bins is the
//!   scene seen through an instrument delay of `k·Δt` (cables, trigger, optics) — exactly the
//!   generator's scene with its onset or delay moved by `k` bins (tested in `datasets`);
//! - **flips** of rows and columns;
//! - **crops**: a random window of a fixed size (a multiple of the pixel block);
//! - **brightness**: a per-item factor, log-uniform, so that the network sees tap images over
//!   decades of scale instead of cubes normalised to a peak of 1;
//! - **noise level**: per item, a full well, a read noise and the fraction of full well the
//!   brightest tap reaches (the photon count), each drawn from its range: the photon ladder
//!   that `tcsense eval --light` measures decoders on;
//! - **ambient light**: per item, a constant background in every bin, `ambient` times the
//!   frame's mean signal per pixel and bin (`1/SBR`, as `eval --sbr`), with the exposure set
//!   by the signal alone (ambient adds photons and shot noise; it does not dim the signal).
//!
//! Every draw comes from a generator seeded by `(seed, step)`, so a run stays a pure function
//! of its config and resumes exactly.

use ndarray::{s, Array4, ArrayView3, ArrayView4, Axis};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};
use tcsense_datasets::knobs::draw;
use tcsense_sensor::noise::derive_seed;
use tcsense_sensor::params::MAX_SIGNAL_FRACTION;
use tcsense_sensor::NoiseParams;

use crate::{Result, TrainError};

/// The most ambient light an augmentation draws: 100 times the signal (SBR 0.01, where
/// photon-efficient single-photon LiDAR is judged).
pub const MAX_AMBIENT: f64 = 100.0;

/// Stream of the augmentation draws, apart from the noise's `(seed, step)`.
const AUGMENT_STREAM: u64 = 0x4155_474D_454E_5421;

/// Augmentation settings (`config.json`'s `augment`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Augmentation {
    /// Roll each cube by a uniform number of bins along time.
    pub time_shift: bool,
    /// Flip each cube's rows and columns, each with probability ½.
    pub flips: bool,
    /// Crop each item to a random `[H, W]` window (a multiple of the block); `None`: whole frames.
    pub crop: Option<[usize; 2]>,
    /// Brightness factor per item, log-uniform in `[lo, hi]`.
    pub brightness: [f64; 2],
    /// Full well per item (e⁻), log-uniform.
    pub full_well_e: [f64; 2],
    /// Read noise per item (e⁻), uniform.
    pub read_noise_e: [f64; 2],
    /// Fraction of full well the brightest tap reaches, per item, log-uniform.
    pub signal_fraction: [f64; 2],
    /// What a calibration leaves of a real sensor's non-idealities, drawn afresh per item
    /// after the measurement: `[tap gain, PRNU, dark]` — tap gains uniform in `1 ± g`, pixel
    /// gains `1 + N(0, p²)` per pixel and tap, and offsets `N(0, d²)` times the item's
    /// brightest tap. All zero (the default): off.
    #[serde(default, skip_serializing_if = "is_off")]
    pub sensor_residue: [f64; 3],
    /// Ambient light per item, uniform in `[lo, hi]`: the background per bin over the mean
    /// signal per pixel and bin (`1/SBR`: 1 is as much ambient as signal). `[0, 0]` (the
    /// default, and configs written before it): none.
    #[serde(default, skip_serializing_if = "no_ambient")]
    pub ambient: [f64; 2],
}

fn no_ambient(r: &[f64; 2]) -> bool {
    r[1] == 0.0
}

fn is_off(r: &[f64; 3]) -> bool {
    r.iter().all(|&v| v == 0.0)
}

impl Default for Augmentation {
    /// Shifts and flips on, no crop, brightness over two decades, full well 10 000–40 000 e⁻,
    /// read noise 10–60 e⁻, brightest tap at 5–90 % of full well (500 to 36 000 e⁻, against the
    /// paper's 16 000).
    fn default() -> Self {
        Augmentation {
            time_shift: true,
            flips: true,
            crop: None,
            brightness: [0.01, 1.0],
            full_well_e: [1e4, 4e4],
            read_noise_e: [10.0, 60.0],
            signal_fraction: [0.05, 0.9],
            sensor_residue: [0.0; 3],
            ambient: [0.0; 2],
        }
    }
}

/// A batch after augmentation: cubes, their depth labels and, per item, the noise model to
/// measure it with.
#[derive(Debug, Clone)]
pub struct Augmented {
    /// `[B, T, H', W']`.
    pub x: Array4<f32>,
    /// Range labels `[B, K, H', W']` (m, NaN where none), moved with the cube: flipped,
    /// cropped, and shifted by the time shift's range `k·c·Δt/2` (cyclically, re-sorted into
    /// arrival order).
    pub depth: Option<Array4<f32>>,
    /// Per-pixel label maps `[B, C, H', W']` (lifetimes), flipped and cropped with the cube
    /// (a delay or a brightness does not change them).
    pub maps: Option<Array4<f32>>,
    /// One noise model per item (from `base` with this item's levels).
    pub noise: Vec<NoiseParams>,
    /// The brightness factor of each item.
    pub gains: Vec<f32>,
    /// Ambient light of each item: a constant to add to every bin of its cube `x` before it
    /// is measured (in the cube's units, brightness included; 0: none).
    pub ambient: Vec<f32>,
}

/// Range labels to move with the cubes.
#[derive(Debug, Clone, Copy)]
pub struct DepthLabels<'a> {
    /// `[B, K, H, W]` (m, NaN where none).
    pub depth: ArrayView4<'a, f32>,
    /// Range of one time bin, `c·Δt/2` (m).
    pub bin_m: f64,
    /// Unambiguous range, `c·L·T_c/2` (m).
    pub range_m: f64,
}

/// The crop window `[r0, c0, h, w]` of `src`, flipped as asked.
///
/// # Shapes
/// - `src`: `[C, H, W]` → `[C, h, w]`
fn window(src: ArrayView3<'_, f32>, [r0, c0, ch, cw]: [usize; 4], flip_r: bool, flip_c: bool) -> ArrayView3<'_, f32> {
    let w = src.slice_move(s![.., r0..r0 + ch, c0..c0 + cw]);
    match (flip_r, flip_c) {
        (false, false) => w,
        (true, false) => w.slice_move(s![.., ..;-1, ..]),
        (false, true) => w.slice_move(s![.., .., ..;-1]),
        (true, true) => w.slice_move(s![.., ..;-1, ..;-1]),
    }
}

/// Stream of the sensor-residue draws.
const RESIDUE_STREAM: u64 = 0x5245_5349_4455_4521;

impl Augmentation {
    /// Perturb measured tap images `y` (`[B, M, H, W]`) by the sensor residue (see
    /// [`Augmentation::sensor_residue`]), item `i` from its own generator seeded by
    /// `(seed, step, i)`; a no-op when the residue is off.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]`, in place
    pub fn perturb(&self, y: &mut Array4<f32>, seed: u64, step: u64) {
        let [g, p, d] = self.sensor_residue;
        if is_off(&self.sensor_residue) {
            return;
        }
        let unit = rand_distr::Normal::new(0.0f64, 1.0).expect("unit normal");
        for (i, mut item) in y.outer_iter_mut().enumerate() {
            let mut rng = StdRng::seed_from_u64(derive_seed(derive_seed(seed ^ RESIDUE_STREAM, step), i as u64));
            let peak = item.iter().fold(0f32, |m, v| m.max(v.abs())) as f64;
            for mut tap in item.outer_iter_mut() {
                let gain = if g > 0.0 { 1.0 + rng.random_range(-g..=g) } else { 1.0 };
                for v in tap.iter_mut() {
                    let pixel = 1.0 + p * rand_distr::Distribution::sample(&unit, &mut rng);
                    let offset = d * peak * rand_distr::Distribution::sample(&unit, &mut rng);
                    *v = (*v as f64 * gain * pixel + offset) as f32;
                }
            }
        }
    }

    /// Check the ranges against a frame of `h × w` with pixel block `block`.
    pub fn validate(&self, h: usize, w: usize, block: (usize, usize)) -> Result<()> {
        self.validate_ranges()?;
        if let Some([ch, cw]) = self.crop {
            if ch == 0 || cw == 0 || ch > h || cw > w || ch % block.0 != 0 || cw % block.1 != 0 {
                return Err(TrainError::InvalidParam {
                    field: "augment.crop",
                    got: format!("{ch}x{cw}"),
                    expected: format!("a window within the {h}x{w} frames, a multiple of the {}x{} block", block.0, block.1),
                });
            }
        }
        Ok(())
    }

    /// Check the ranges that need no frame (all but the crop's fit).
    pub fn validate_ranges(&self) -> Result<()> {
        let bad =
            |field: &'static str, got: String, expected: &str| Err(TrainError::InvalidParam { field, got, expected: expected.into() });
        let [g, p, d] = self.sensor_residue;
        if !(g.is_finite()
            && p.is_finite()
            && d.is_finite()
            && (0.0..=0.5).contains(&g)
            && (0.0..=0.2).contains(&p)
            && (0.0..=0.1).contains(&d))
        {
            return bad(
                "augment.sensor_residue",
                format!("{:?}", self.sensor_residue),
                "[tap gain ≤ 0.5, PRNU ≤ 0.2, dark ≤ 0.1], each ≥ 0",
            );
        }
        for (name, r, lo) in [
            ("augment.brightness", self.brightness, 1e-6),
            ("augment.full_well_e", self.full_well_e, 1.0),
            ("augment.signal_fraction", self.signal_fraction, 1e-6),
        ] {
            if !(r[0].is_finite() && r[1].is_finite() && lo <= r[0] && r[0] <= r[1]) {
                return bad(name, format!("{r:?}"), "a range LO ≤ HI of positive numbers");
            }
        }
        if self.signal_fraction[1] > MAX_SIGNAL_FRACTION {
            return bad(
                "augment.signal_fraction",
                format!("{:?}", self.signal_fraction),
                &format!("fractions of full well up to {MAX_SIGNAL_FRACTION}"),
            );
        }
        let [a0, a1] = self.ambient;
        if !(a0.is_finite() && a1.is_finite() && 0.0 <= a0 && a0 <= a1 && a1 <= MAX_AMBIENT) {
            return bad(
                "augment.ambient",
                format!("{:?}", self.ambient),
                &format!("a range 0 ≤ LO ≤ HI ≤ {MAX_AMBIENT} of ambient over signal (1/SBR)"),
            );
        }
        if !(self.read_noise_e[0] >= 0.0 && self.read_noise_e[0] <= self.read_noise_e[1] && self.read_noise_e[1].is_finite()) {
            return bad("augment.read_noise_e", format!("{:?}", self.read_noise_e), "a range 0 ≤ LO ≤ HI");
        }
        Ok(())
    }

    /// The frame size the network trains on.
    pub fn frame(&self, h: usize, w: usize) -> (usize, usize) {
        self.crop.map_or((h, w), |[ch, cw]| (ch, cw))
    }

    /// Augment batch `x` (and its depth labels or label maps) for optimiser step `step`; `base`
    /// is the run's noise model (its ADC setting is kept).
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, T, H', W']` (`H' × W'` the crop, else `H × W`); labels
    ///   `[B, K, H, W]` → `[B, K, H', W']`; maps `[B, C, H, W]` → `[B, C, H', W']`
    #[allow(clippy::too_many_arguments)]
    pub fn apply(
        &self,
        x: &ArrayView4<'_, f32>,
        labels: Option<DepthLabels<'_>>,
        maps: Option<ArrayView4<'_, f32>>,
        base: &NoiseParams,
        block: (usize, usize),
        seed: u64,
        step: u64,
    ) -> Augmented {
        let mut rng = StdRng::seed_from_u64(derive_seed(seed ^ AUGMENT_STREAM, step));
        let (b, t, h, w) = x.dim();
        let (ch, cw) = self.frame(h, w);
        let mut out = Array4::<f32>::zeros((b, t, ch, cw));
        let mut depth_out = labels.map(|l| Array4::<f32>::from_elem((b, l.depth.dim().1, ch, cw), f32::NAN));
        let mut maps_out = maps.map(|m| Array4::<f32>::zeros((b, m.dim().1, ch, cw)));
        let mut noise = Vec::with_capacity(b);
        let mut gains = Vec::with_capacity(b);
        let mut ambient = Vec::with_capacity(b);
        for (i, mut dst) in out.outer_iter_mut().enumerate() {
            let shift = if self.time_shift { rng.random_range(0..t) } else { 0 };
            let (flip_r, flip_c) = if self.flips { (rng.random_bool(0.5), rng.random_bool(0.5)) } else { (false, false) };
            // crop origins on the block grid, so every pixel keeps its subpixel type
            let r0 = rng.random_range(0..=(h - ch) / block.0) * block.0;
            let c0 = rng.random_range(0..=(w - cw) / block.1) * block.1;
            let gain = draw(&mut rng, self.brightness, true) as f32;
            gains.push(gain);
            let area = [r0, c0, ch, cw];
            let window_x = window(x.index_axis(Axis(0), i), area, flip_r, flip_c);
            if let (Some(l), Some(d)) = (labels, depth_out.as_mut()) {
                let mut di = d.index_axis_mut(Axis(0), i);
                di.assign(&window(l.depth.index_axis(Axis(0), i), area, flip_r, flip_c));
                let delay = shift as f64 * l.bin_m;
                for mut px in di.lanes_mut(Axis(0)) {
                    // shift every return, wrap around the cycle, keep arrival order (NaN last)
                    let mut v: Vec<f32> = px
                        .iter()
                        .map(|&d| if d.is_finite() { (d as f64 + delay).rem_euclid(l.range_m) as f32 } else { f32::NAN })
                        .collect();
                    v.sort_by(|a, b| a.is_nan().cmp(&b.is_nan()).then(a.total_cmp(b)));
                    px.iter_mut().zip(v).for_each(|(p, v)| *p = v);
                }
            }
            if let (Some(m), Some(mo)) = (maps, maps_out.as_mut()) {
                mo.index_axis_mut(Axis(0), i).assign(&window(m.index_axis(Axis(0), i), area, flip_r, flip_c));
            }
            for j in 0..t {
                // roll: bin j of the source lands in bin j + shift
                dst.index_axis_mut(Axis(0), (j + shift) % t).zip_mut_with(&window_x.index_axis(Axis(0), j), |d, &v| *d = v * gain);
            }
            noise.push(NoiseParams {
                full_well_e: draw(&mut rng, self.full_well_e, true),
                read_noise_e: draw(&mut rng, self.read_noise_e, false),
                signal_fraction: draw(&mut rng, self.signal_fraction, true),
                adc_bits: base.adc_bits,
            });
            // drawn last, so runs without ambient light keep their draws
            let share = if no_ambient(&self.ambient) { 0.0 } else { draw(&mut rng, self.ambient, false) };
            ambient.push((share * dst.sum() as f64 / dst.len().max(1) as f64) as f32);
        }
        Augmented { x: out, depth: depth_out, maps: maps_out, noise, gains, ambient }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array4;

    fn cube() -> Array4<f32> {
        Array4::from_shape_fn((2, 8, 4, 6), |(b, j, r, c)| (b * 1000 + j * 100 + r * 10 + c) as f32)
    }

    #[test]
    fn shifts_flips_crops_and_levels() {
        let x = cube();
        let base = NoiseParams::default();
        let off = Augmentation {
            time_shift: false,
            flips: false,
            crop: None,
            brightness: [1.0, 1.0],
            full_well_e: [2e4, 2e4],
            read_noise_e: [40.0, 40.0],
            signal_fraction: [0.8, 0.8],
            sensor_residue: [0.0; 3],
            ambient: [0.0; 2],
        };
        let same = off.apply(&x.view(), None, None, &base, (2, 2), 1, 1);
        assert_eq!(same.x, x, "everything off is the identity");
        assert!(same
            .noise
            .iter()
            .all(|n| n.full_well_e == 2e4 && n.read_noise_e == 40.0 && n.signal_fraction == 0.8 && n.adc_bits == base.adc_bits));

        // a time shift is a roll of every pixel's waveform by the same number of bins
        let shifted = Augmentation { time_shift: true, ..off }.apply(&x.view(), None, None, &base, (2, 2), 1, 2).x;
        for b in 0..2 {
            let k = (0..8).find(|&k| shifted[(b, k, 0, 0)] == x[(b, 0, 0, 0)]).expect("a roll of the waveform");
            for j in 0..8 {
                for r in 0..4 {
                    for c in 0..6 {
                        assert_eq!(shifted[(b, (j + k) % 8, r, c)], x[(b, j, r, c)]);
                    }
                }
            }
        }

        // flips and crops move pixels, never change a waveform; crops stay on the block grid
        let cropped = Augmentation { flips: true, crop: Some([2, 4]), ..off };
        cropped.validate(4, 6, (2, 2)).unwrap();
        for step in 0..8 {
            let out = cropped.apply(&x.view(), None, Some(x.slice(s![.., 0..2, .., ..])), &base, (2, 2), 3, step);
            let a = out.x;
            // label maps move with the pixels
            let maps = out.maps.expect("maps in, maps out");
            assert_eq!(maps, a.slice(s![.., 0..2, .., ..]));
            assert_eq!(a.dim(), (2, 8, 2, 4));
            for b in 0..2 {
                let v = a[(b, 0, 0, 0)] as usize - b * 1000;
                let (r, c) = (v / 10 % 10, v % 10);
                for j in 0..8 {
                    assert_eq!(a[(b, j, 0, 0)], x[(b, j, r, c)], "one pixel's waveform");
                }
            }
        }
        for step in 0..8 {
            let a = Augmentation { crop: Some([2, 4]), ..off }.apply(&x.view(), None, None, &base, (2, 2), 3, step).x;
            let v = a[(0, 0, 0, 0)] as usize;
            assert!((v / 10 % 10) % 2 == 0 && (v % 10) % 2 == 0, "crop origin ({}, {}) on the 2x2 block grid", v / 10 % 10, v % 10);
        }
        assert!(Augmentation { crop: Some([3, 4]), ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { sensor_residue: [0.0, 0.5, 0.0], ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { crop: Some([6, 4]), ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { brightness: [1.0, 0.5], ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { ambient: [2.0, 1.0], ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { ambient: [0.0, 1e3], ..off }.validate(4, 6, (2, 2)).is_err());
        assert!(Augmentation { ambient: [0.0, f64::NAN], ..off }.validate(4, 6, (2, 2)).is_err());

        // ambient light: 1/SBR times each item's mean signal per pixel and bin (none by default)
        assert!(off.apply(&x.view(), None, None, &base, (2, 2), 1, 1).ambient.iter().all(|&b| b == 0.0));
        let lit = Augmentation { ambient: [2.0, 2.0], ..off }.apply(&x.view(), None, None, &base, (2, 2), 1, 1);
        for (i, b) in lit.ambient.iter().enumerate() {
            let mean = x.index_axis(Axis(0), i).mean().unwrap();
            assert!((b / (2.0 * mean) - 1.0).abs() < 1e-5, "item {i}: ambient {b}, mean signal {mean}");
        }
        let drawn = Augmentation { ambient: [0.0, 4.0], ..off }.apply(&x.view(), None, None, &base, (2, 2), 1, 1);
        assert_eq!(drawn.x, lit.x, "the ambient draw leaves the other draws as they were");

        // brightness and noise levels are drawn in their ranges, seeded by (seed, step)
        let d = Augmentation::default();
        let a1 = d.apply(&x.view(), None, None, &base, (2, 2), 7, 3);
        for (i, g) in a1.gains.iter().enumerate() {
            let ratio = a1.x.index_axis(Axis(0), i).iter().map(|v| v.abs()).sum::<f32>()
                / x.index_axis(Axis(0), i).iter().map(|v| v.abs()).sum::<f32>();
            assert!((ratio / g - 1.0).abs() < 1e-4, "item {i}: scaled by {ratio}, gain {g}");
        }
        let a2 = d.apply(&x.view(), None, None, &base, (2, 2), 7, 3);
        let a3 = d.apply(&x.view(), None, None, &base, (2, 2), 7, 4);
        assert_eq!(a1.x, a2.x);
        assert_ne!(a1.x, a3.x);
        for n in a1.noise.iter().chain(&a3.noise) {
            assert!(
                (1e4..=4e4).contains(&n.full_well_e)
                    && (10.0..=60.0).contains(&n.read_noise_e)
                    && (0.05..=0.9).contains(&n.signal_fraction)
            );
        }
        let gains: Vec<f32> = (0..200)
            .map(|s| {
                d.apply(&x.view(), None, None, &base, (2, 2), 7, s).x.iter().map(|v| v.abs()).sum::<f32>()
                    / x.iter().map(|v| v.abs()).sum::<f32>()
            })
            .collect();
        assert!(gains.iter().any(|&g| g < 0.05) && gains.iter().any(|&g| g > 0.5), "brightness over two decades");
    }

    #[test]
    fn sensor_residue_perturbs_as_specified_and_is_seeded() {
        let aug = Augmentation { sensor_residue: [0.05, 0.02, 0.01], ..Augmentation::default() };
        let y = Array4::<f32>::from_elem((2, 4, 16, 16), 1.0);
        let (mut a, mut b, mut c) = (y.clone(), y.clone(), y.clone());
        aug.perturb(&mut a, 3, 7);
        aug.perturb(&mut b, 3, 7);
        aug.perturb(&mut c, 3, 8);
        assert_eq!(a, b, "same seed and step, same bytes");
        assert_ne!(a, c, "another step, other draws");
        for item in a.outer_iter() {
            for tap in item.outer_iter() {
                let v: Vec<f64> = tap.iter().map(|&v| v as f64).collect();
                let mean = v.iter().sum::<f64>() / v.len() as f64;
                let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len() as f64).sqrt();
                assert!((mean - 1.0).abs() <= 0.05 + 0.01, "tap gain within 1 ± 0.05: mean {mean}");
                // pixel gain 2 % and offsets 1 % of the peak: σ ≈ 2.2 %
                assert!(sd > 0.015 && sd < 0.03, "per-pixel scatter {sd}");
            }
        }
        let mut off = y.clone();
        Augmentation::default().perturb(&mut off, 3, 7);
        assert_eq!(off, y, "off by default");
    }
}
