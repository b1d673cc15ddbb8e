//! Products of a reconstructed cube.
//!
//! **Peaks**: local maxima of a waveform above `min_rel` × its maximum, at least `min_sep`
//! bins apart, strongest first, refined by a parabola through the maximum and its two
//! neighbours: `δ = ½ (y₋ − y₊) / (y₋ − 2y₀ + y₊)`. A peak at bin-centre coordinate `p` is the
//! time `t = (p + ½)Δt` (bin `j` covers `[jΔt, (j+1)Δt)`); depth (range) `d = c·t/2`.

use crate::Result;
use ndarray::{Array2, Array3, ArrayView1, ArrayView3, Axis};
use rayon::prelude::*;
use std::path::Path;
use tcsense_datasets::grid::C;
use tcsense_datasets::lidar::Camera;
use tcsense_sensor::npy::atomic_write;

/// A detected peak.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Peak {
    /// Refined position in bin-centre coordinates (bin `j` is centred at `j`).
    pub position: f64,
    /// Parabola's peak value.
    pub amplitude: f64,
}

/// Peak detection settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeakOptions {
    /// Maximum peaks per pixel.
    pub max_peaks: usize,
    /// Ignore maxima below this fraction of the waveform's maximum.
    pub min_rel: f32,
    /// Minimal separation between peaks (bins).
    pub min_sep: usize,
}

impl Default for PeakOptions {
    fn default() -> Self {
        PeakOptions { max_peaks: 2, min_rel: 0.1, min_sep: 2 }
    }
}

/// Parabolic sub-bin offset of the maximum at `i` from its neighbours.
pub fn parabolic_offset(ym: f64, y0: f64, yp: f64) -> (f64, f64) {
    let den = ym - 2.0 * y0 + yp;
    if den.abs() < 1e-30 || den >= 0.0 {
        return (0.0, y0);
    }
    let delta = (0.5 * (ym - yp) / den).clamp(-0.5, 0.5);
    (delta, y0 - 0.25 * (ym - yp) * delta)
}

/// Peaks of one waveform (cyclic), ordered by time.
pub fn find_peaks(wave: &ArrayView1<'_, f32>, opts: &PeakOptions) -> Vec<Peak> {
    let t = wave.len();
    if t < 3 {
        return Vec::new();
    }
    let max = wave.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    if max <= 0.0 || !max.is_finite() {
        return Vec::new();
    }
    let thr = opts.min_rel * max;
    let mut cands: Vec<(usize, f32)> = (0..t)
        .filter_map(|i| {
            let (ym, y0, yp) = (wave[(i + t - 1) % t], wave[i], wave[(i + 1) % t]);
            // a maximum (plateaus count once, at their first bin)
            (y0 >= thr && y0 > ym && y0 >= yp).then_some((i, y0))
        })
        .collect();
    cands.sort_by(|a, b| b.1.total_cmp(&a.1));
    let mut chosen: Vec<usize> = Vec::new();
    for (i, _) in cands {
        let far = chosen.iter().all(|&j| {
            let d = i.abs_diff(j);
            d.min(t - d) >= opts.min_sep.max(1)
        });
        if far {
            chosen.push(i);
            if chosen.len() == opts.max_peaks {
                break;
            }
        }
    }
    let mut peaks: Vec<Peak> = chosen
        .into_iter()
        .map(|i| {
            let (ym, y0, yp) = (wave[(i + t - 1) % t] as f64, wave[i] as f64, wave[(i + 1) % t] as f64);
            let (delta, amp) = parabolic_offset(ym, y0, yp);
            Peak { position: i as f64 + delta, amplitude: amp }
        })
        .collect();
    peaks.sort_by(|a, b| a.position.total_cmp(&b.position));
    peaks
}

/// Range per return `[K, H, W]` (m, ordered by arrival, NaN where none) and amplitude `[K, H, W]`.
///
/// # Shapes
/// - `x`: `[T, H, W]` → `([K, H, W], [K, H, W])`
pub fn depth_map(x: &ArrayView3<'_, f32>, bin_width_s: f64, opts: &PeakOptions) -> (Array3<f32>, Array3<f32>) {
    let (_, h, w) = x.dim();
    let k = opts.max_peaks;
    let per_pixel: Vec<Vec<Peak>> = (0..h * w).into_par_iter().map(|p| find_peaks(&x.slice(ndarray::s![.., p / w, p % w]), opts)).collect();
    let mut depth = Array3::<f32>::from_elem((k, h, w), f32::NAN);
    let mut amp = Array3::<f32>::zeros((k, h, w));
    for (p, peaks) in per_pixel.iter().enumerate() {
        for (b, pk) in peaks.iter().enumerate() {
            let t = (pk.position + 0.5) * bin_width_s;
            depth[(b, p / w, p % w)] = (C * t / 2.0) as f32;
            amp[(b, p / w, p % w)] = pk.amplitude as f32;
        }
    }
    (depth, amp)
}

/// Phasors `[2, H, W]` (g, s; NaN below `min_intensity` of the brightest pixel's total) at the
/// cycle's first harmonic, as a phasor analysis of a measurement uses them: each waveform's
/// constant background (its minimum) removed, and the phase referenced to the frame's onset
/// — rotated by `−ω·t₀`, `t₀` the centre of the peak bin of the frame's summed decay (what a
/// calibration with a reference sample does for the instrument's delay) — so single
/// exponentials fall on the universal semicircle wherever the decay starts in the cycle.
///
/// # Shapes
/// - `x`: `[T, H, W]` → `[2, H, W]`
pub fn referenced_phasors(x: &ArrayView3<'_, f32>, min_intensity: f32) -> Array3<f32> {
    let (t, h, w) = x.dim();
    let omega = 2.0 * std::f64::consts::PI / t as f64; // per bin
    let total = x.sum_axis(Axis(1)).sum_axis(Axis(1)); // [T]
    let peak = total.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).map_or(0, |(j, _)| j);
    let t0 = peak as f64 + 0.5;
    let mut sums = Array2::<f64>::zeros((h, w));
    let mut out = Array3::<f32>::from_elem((2, h, w), f32::NAN);
    for r in 0..h {
        for c in 0..w {
            let wave = x.slice(ndarray::s![.., r, c]);
            let bg = wave.iter().fold(f32::INFINITY, |m, &v| m.min(v));
            let (mut sum, mut g, mut s) = (0f64, 0f64, 0f64);
            for (j, &v) in wave.iter().enumerate() {
                let v = (v - bg) as f64;
                let phase = omega * (j as f64 + 0.5 - t0);
                sum += v;
                g += v * phase.cos();
                s += v * phase.sin();
            }
            sums[(r, c)] = sum;
            if sum > 0.0 {
                out[(0, r, c)] = (g / sum) as f32;
                out[(1, r, c)] = (s / sum) as f32;
            }
        }
    }
    let max = sums.iter().fold(0f64, |m, &v| m.max(v));
    for ((r, c), &sum) in sums.indexed_iter() {
        if sum <= min_intensity as f64 * max {
            out[(0, r, c)] = f32::NAN;
            out[(1, r, c)] = f32::NAN;
        }
    }
    out
}

/// Each finite range of `depth` `[K, H, W]` as `(return, row, column, [x, y, z])`, camera
/// coordinates in metres through a pinhole camera with horizontal field of view `fov_deg`.
fn camera_points<'a>(depth: &'a ArrayView3<'_, f32>, fov_deg: f64) -> impl Iterator<Item = (usize, usize, usize, [f64; 3])> + 'a {
    let (k, h, w) = depth.dim();
    let cam = Camera { height: h, width: w, fov_deg };
    (0..k).flat_map(move |b| (0..h).flat_map(move |r| (0..w).map(move |c| (b, r, c)))).filter_map(move |(b, r, c)| {
        let d = depth[(b, r, c)];
        d.is_finite().then(|| {
            let ray = cam.ray(r, c);
            (b, r, c, [ray[0] * d as f64, ray[1] * d as f64, ray[2] * d as f64])
        })
    })
}

/// The points `[x, y, z, return]` (camera coordinates in metres, return index from 0) of a
/// range map `[K, H, W]` seen through a pinhole camera with horizontal field of view
/// `fov_deg`; NaN ranges give no point.
pub fn point_cloud(depth: &ArrayView3<'_, f32>, fov_deg: f64) -> Vec<[f32; 4]> {
    camera_points(depth, fov_deg).map(|(b, _, _, p)| [p[0] as f32, p[1] as f32, p[2] as f32, b as f32]).collect()
}

/// Write a point cloud (ASCII PLY: x y z in metres, bounce index, amplitude) from a range map
/// `[K, H, W]` seen through a pinhole camera with horizontal field of view `fov_deg`.
pub fn write_ply(path: &Path, depth: &ArrayView3<'_, f32>, amp: &ArrayView3<'_, f32>, fov_deg: f64) -> Result<usize> {
    let pts: Vec<(f64, f64, f64, usize, f32)> =
        camera_points(depth, fov_deg).map(|(b, r, c, p)| (p[0], p[1], p[2], b, amp[(b, r, c)])).collect();
    let n = pts.len();
    atomic_write(path, |wr| {
        writeln!(wr, "ply\nformat ascii 1.0\ncomment tcsense point cloud: x y z (m), bounce, amplitude")?;
        writeln!(wr, "element vertex {n}\nproperty float x\nproperty float y\nproperty float z\nproperty uchar bounce\nproperty float amplitude\nend_header")?;
        for (x, y, z, b, a) in &pts {
            writeln!(wr, "{x:.6} {y:.6} {z:.6} {b} {a:.6}")?;
        }
        Ok(())
    })?;
    Ok(n)
}

/// Plot waveforms: one panel per pixel, one line per cube (e.g. truth, TVAL3, ADMM-Net),
/// like the paper's Figs. 18 and 20 ([`crate::figures::waveforms`]); also returns the
/// values as CSV text.
///
/// # Shapes
/// - `cubes`: `(name, [T, H, W])`
pub fn plot_waveforms(path: &Path, cubes: &[(&str, ArrayView3<'_, f32>)], pixels: &[(usize, usize)]) -> Result<String> {
    let mut csv = String::from("pixel_row,pixel_col,bin");
    for (name, _) in cubes {
        csv.push(',');
        csv.push_str(name);
    }
    csv.push('\n');
    for &(r, c) in pixels {
        let t = cubes.first().map_or(0, |c| c.1.dim().0);
        for j in 0..t {
            csv.push_str(&format!("{r},{c},{j}"));
            for (_, x) in cubes {
                csv.push_str(&format!(",{}", x.get((j, r, c)).copied().unwrap_or(f32::NAN)));
            }
            csv.push('\n');
        }
    }
    crate::figures::waveforms(path, cubes, pixels, None)?;
    Ok(csv)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array1;

    /// A delayed single exponential on a constant background lands on the universal
    /// semicircle at its lifetime, wherever its onset is in the cycle; a dim pixel is NaN.
    #[test]
    fn referenced_phasors_put_exponentials_on_the_semicircle() {
        let t = 256;
        for (onset, tau_bins) in [(3usize, 10.0f64), (140, 25.0), (250, 6.0)] {
            let mut x = ndarray::Array3::<f32>::zeros((t, 1, 2));
            for j in 0..t {
                // periodic decay starting at `onset` (wraps around the cycle), background 0.05
                let age = (j + t - onset) % t;
                x[(j, 0, 0)] = (0.05 + (-(age as f64) / tau_bins).exp()) as f32;
                x[(j, 0, 1)] = 1e-6 * x[(j, 0, 0)];
            }
            let p = referenced_phasors(&x.view(), 0.02);
            let (g, s) = (p[(0, 0, 0)] as f64, p[(1, 0, 0)] as f64);
            // on the circle (g − ½)² + s² = ¼, at the phase of a sampled exponential
            // Σ qᵏ e^{iωk} = 1/(1 − q e^{iω}), q = e^{−1/τ}: s/g = q sin ω / (1 − q cos ω) ≈ ωτ
            let (w, q) = (2.0 * std::f64::consts::PI / t as f64, (-1.0 / tau_bins).exp());
            let want = q * w.sin() / (1.0 - q * w.cos());
            assert!(((g - 0.5).powi(2) + s * s - 0.25).abs() < 0.01, "onset {onset}: ({g}, {s}) off the circle");
            assert!((s / g - want).abs() < 0.01 * want, "onset {onset}: s/g {} want {want}", s / g);
            assert!(p[(0, 0, 1)].is_nan());
        }
    }

    #[test]
    fn parabolic_refinement_recovers_a_sub_bin_offset() {
        // Gaussian pulse, σ = 1.2 bins, centred at 10.3 (bin-centre coordinates)
        for &centre in &[10.3f64, 10.0, 9.62, 10.49] {
            let wave = Array1::from_iter((0..32).map(|j| (-(j as f64 - centre).powi(2) / (2.0 * 1.2f64.powi(2))).exp() as f32));
            let p = find_peaks(&wave.view(), &PeakOptions { max_peaks: 1, ..Default::default() });
            assert_eq!(p.len(), 1);
            assert!((p[0].position - centre).abs() < 0.05, "found {} want {centre}", p[0].position);
        }
    }

    #[test]
    fn two_returns_are_found_in_time_order() {
        let mut wave = Array1::<f32>::zeros(32);
        for j in 0..32 {
            let j = j as f64;
            wave[j as usize] = (0.4 * (-(j - 5.2).powi(2) / 2.0).exp() + (-(j - 20.7).powi(2) / 2.0).exp()) as f32;
        }
        let p = find_peaks(&wave.view(), &PeakOptions::default());
        assert_eq!(p.len(), 2);
        assert!((p[0].position - 5.2).abs() < 0.1 && (p[1].position - 20.7).abs() < 0.1, "{p:?}");
        let x = wave.clone().into_shape_with_order((32, 1, 1)).unwrap();
        let dt = 1.65e-9;
        let (d, _) = depth_map(&x.view(), dt, &PeakOptions::default());
        assert!((d[(1, 0, 0)] as f64 - C * (20.7 + 0.5) * dt / 2.0).abs() < 0.02);
    }
}
