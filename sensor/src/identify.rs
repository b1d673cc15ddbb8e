//! Identifiability of a sensor configuration (codes + IRF + sampling + noise): what any
//! decoder can know from the taps, in closed form (DESIGN §4, "Identifiability").
//!
//! A block of `N` subpixels, each with `M` taps, sees one surface. A return at delay `τ` (bins,
//! continuous) is the datasets' sub-bin impulse, so subpixel `n` measures (the model of
//! `tcsense_fits::range`)
//!
//! ```text
//! μ_n = a_n·g_n(τ) + b_n·s_n,   g_n(τ) = (1 − f)·A[n][·][t₀] + f·A[n][·][t₀ + 1],  τ − ½ = t₀ + f,
//!                               s_n = Σ_t A[n][·][t]                               (cyclic in t)
//! ```
//!
//! in electrons, with shot and read noise: `var = μ + σ_read²`. A fluorescence decay of
//! lifetime `τ_f` starting at `t₀` is `x = a·D(τ_f, t₀) + b` with `D` the cyclic exponential,
//! averaged over each bin and of unit sum, so `μ_n = a_n·A_n D + b_n·s_n` (the model of the
//! fit to the taps).
//!
//! - **Alias**: the smallest distance between the unit block signatures `ĝ = g/‖g‖` of two
//!   returns at least two masks apart (`2K` bins; two returns closer than that are one pulse);
//!   0 means the taps cannot tell the two ranges apart whatever the decoder, `√2` orthogonal.
//!   For decays: two `(τ_f, t₀)` whose onsets are at least two masks apart.
//! - **Cramér–Rao bounds**: the Fisher information of the Gaussian approximation of the
//!   noise, `I = Jᵀ diag(1/var) J`, with the range `τ` (or `τ_f`, and `t₀` when fitted) shared
//!   by the block and an amplitude and a background per subpixel as nuisance parameters
//!   (profiled out per subpixel by a Schur complement, as the estimators fit them):
//!   `σ(τ) ≥ √([I⁻¹]_ττ)`. Evaluated at every delay (a few per bin) over the cycle: worst and
//!   mean.
//! - **Two returns**: the bound on both ranges of two equal returns (half the photons each) at
//!   a separation `δ`; they are *resolved* from the smallest `δ` at which `2σ₁ + 2σ₂ ≤ δ` at
//!   every position over the cycle.
//!
//! ```
//! use tcsense_sensor::{generate, identify, MeasurementMatrix, SensorParams, Irf};
//! let codes = generate::prototype_codes(1).unwrap();
//! let spec = SensorParams { irf: Irf::Ideal, ..SensorParams::from_codes(&codes) }.validate().unwrap();
//! let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
//! let light = identify::Light::default();
//! let r = identify::range_bound(&a, &light, 4);
//! assert!(r.worst_bins >= r.mean_bins && r.mean_bins > 0.0);
//! ```

use crate::matrix::MeasurementMatrix;
use crate::waveform::{decay_unit_sum, Cycle};
use serde::Serialize;

/// Masks two returns (or two onsets) must be apart to count as an alias: closer, they are one
/// pulse's neighbouring bins.
pub const ALIAS_MIN_MASKS: usize = 2;

/// The alias distance below which codes are refused for export unless forced, and warned
/// about by `codes check` (unit signatures are `√2` apart when orthogonal).
pub const DEFAULT_ALIAS_THRESHOLD: f64 = 0.5;

/// Ridge added to the nuisance block of the Fisher matrix, relative to its trace, so that a
/// subpixel whose amplitude and background cannot be told apart contributes nothing instead of
/// a division by zero.
const RIDGE: f64 = 1e-12;

/// The light and noise a bound is stated at, in electrons.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Light {
    /// Signal electrons per subpixel from the return (or the decay): what its taps collect in
    /// all when every mask opens a tap.
    pub photons: f64,
    /// Ambient (background) electrons per subpixel over the exposure, spread evenly over the
    /// cycle.
    pub ambient: f64,
    /// Gaussian read noise σ per tap (electrons).
    pub read_noise_e: f64,
}

impl Default for Light {
    /// 1 000 signal electrons, 100 ambient, the prototype's 40 e⁻ read noise.
    fn default() -> Self {
        Light { photons: 1000.0, ambient: 100.0, read_noise_e: 40.0 }
    }
}

/// The most electrons a [`Light`] takes per pixel (signal, ambient or read noise σ): far past
/// any pixel's full well, and where the bounds' sums of squares stay finite.
pub const MAX_LIGHT_E: f64 = 1e9;

impl Light {
    /// `Err(what was expected)` for values the bounds cannot use.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.photons > 0.0 && self.photons <= MAX_LIGHT_E) {
            return Err(format!("photons {}: expected a positive number of electrons up to {MAX_LIGHT_E:e}", self.photons));
        }
        if !(self.ambient >= 0.0 && self.ambient <= MAX_LIGHT_E) {
            return Err(format!("ambient {}: expected a non-negative number of electrons up to {MAX_LIGHT_E:e}", self.ambient));
        }
        if !(self.read_noise_e >= 0.0 && self.read_noise_e <= MAX_LIGHT_E) {
            return Err(format!("read noise {}: expected a non-negative number of electrons up to {MAX_LIGHT_E:e}", self.read_noise_e));
        }
        Ok(())
    }
}

/// `A` as f64 with its geometry: `a[(n·M + m)·T + t]`.
#[derive(Debug, Clone)]
pub struct Columns {
    a: Vec<f64>,
    n: usize,
    m: usize,
    t: usize,
    /// Bins per mask `K`.
    k: usize,
    bin_width_s: f64,
}

impl Columns {
    /// The matrix of a sensor whose grid has `k` bins per mask (`T = L·K`).
    pub fn new(a: &MeasurementMatrix, k: usize) -> Columns {
        let (n, m, t) = a.a().dim();
        Columns { a: a.a().iter().map(|&v| v as f64).collect(), n, m, t, k: k.max(1), bin_width_s: a.bin_width_s() }
    }

    /// From raw values `[N·M·T]` (e.g. codes through a precomputed code basis).
    pub fn from_values(a: Vec<f64>, n: usize, m: usize, t: usize, k: usize, bin_width_s: f64) -> Columns {
        debug_assert_eq!(a.len(), n * m * t);
        Columns { a, n, m, t, k: k.max(1), bin_width_s }
    }

    /// Bins `T`.
    pub fn bins(&self) -> usize {
        self.t
    }
    /// Entries of a block signature, `N·M`.
    pub fn channels(&self) -> usize {
        self.n * self.m
    }
    fn at(&self, c: usize, t: usize) -> f64 {
        self.a[c * self.t + t % self.t]
    }
    /// Smallest separation (bins) between two returns that counts as an alias.
    pub fn min_shift(&self) -> usize {
        (ALIAS_MIN_MASKS * self.k).min(self.t / 2).max(1)
    }
    /// `s = Σ_t A[·][·][t]`, `[N·M]`: the taps of a flat background of one unit per bin.
    fn background(&self) -> Vec<f64> {
        (0..self.channels()).map(|c| self.a[c * self.t..(c + 1) * self.t].iter().sum()).collect()
    }
    /// `g(τ)` and `∂g/∂τ`, `[N·M]` each, of a return at `τ` bins.
    fn return_at(&self, tau: f64, g: &mut [f64], dg: &mut [f64]) {
        let u = tau - 0.5;
        let t0 = u.floor();
        let f = u - t0;
        let t0 = (t0 as i64).rem_euclid(self.t as i64) as usize;
        for c in 0..self.channels() {
            let (a0, a1) = (self.at(c, t0), self.at(c, t0 + 1));
            g[c] = (1.0 - f) * a0 + f * a1;
            dg[c] = a1 - a0;
        }
    }
    /// `A·x` over the block, `[N·M]`.
    fn apply(&self, x: &[f64], out: &mut [f64]) {
        for (c, o) in out.iter_mut().enumerate() {
            *o = self.a[c * self.t..(c + 1) * self.t].iter().zip(x).map(|(a, x)| a * x).sum();
        }
    }
}

/// The closest pair of returns (range alias), bins on the sensor's grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Alias {
    /// Distance between their unit block signatures (0: the same taps; √2: orthogonal).
    pub distance: f64,
    /// The earlier bin.
    pub bin: usize,
    /// The later bin (cyclic).
    pub other: usize,
}

/// The range alias: over every pair of bins at least [`Columns::min_shift`] apart.
pub fn range_alias(a: &Columns) -> Alias {
    let (t, nm) = (a.t, a.channels());
    let mut unit = vec![0.0; t * nm];
    for j in 0..t {
        let norm = (0..nm).map(|c| a.at(c, j).powi(2)).sum::<f64>().sqrt();
        for c in 0..nm {
            unit[j * nm + c] = if norm > 0.0 { a.at(c, j) / norm } else { 0.0 };
        }
    }
    let ms = a.min_shift();
    let mut best = Alias { distance: f64::INFINITY, bin: 0, other: 0 };
    for j in 0..t {
        for shift in ms..=t - ms {
            let o = (j + shift) % t;
            if o < j && shift != t - shift {
                continue; // each unordered pair once
            }
            let d2: f64 = unit[j * nm..(j + 1) * nm].iter().zip(&unit[o * nm..(o + 1) * nm]).map(|(x, y)| (x - y) * (x - y)).sum();
            if d2 < best.distance {
                best = Alias { distance: d2, bin: j.min(o), other: j.max(o) };
            }
        }
    }
    best.distance = best.distance.sqrt();
    best
}

/// The information a subpixel's taps hold on `k ≤ 2` shared parameters, with its own
/// amplitude and background profiled out: `F_ss − F_sν F_νν⁻¹ F_νs`.
///
/// `shared[i][m]` is `∂μ_m/∂θ_i`, `amp[m]` and `bg[m]` the derivatives by the nuisance
/// parameters (`bg` omitted when the background is not fitted), `var[m]` the tap's variance.
fn profiled_info(shared: &[&[f64]], amp: &[f64], bg: Option<&[f64]>, var: &[f64], out: &mut [[f64; 2]; 2]) {
    let dot = |u: &[f64], v: &[f64]| -> f64 { u.iter().zip(v).zip(var).map(|((a, b), s)| a * b / s).sum() };
    let k = shared.len();
    let mut fss = [[0.0; 2]; 2];
    for i in 0..k {
        for j in 0..k {
            fss[i][j] = dot(shared[i], shared[j]);
        }
    }
    let nu: Vec<&[f64]> = match bg {
        Some(b) => vec![amp, b],
        None => vec![amp],
    };
    let q = nu.len();
    let mut fnn = [[0.0; 2]; 2];
    for i in 0..q {
        for j in 0..q {
            fnn[i][j] = dot(nu[i], nu[j]);
        }
    }
    let ridge = RIDGE * (0..q).map(|i| fnn[i][i]).sum::<f64>().max(f64::MIN_POSITIVE);
    for (i, row) in fnn.iter_mut().enumerate().take(q) {
        row[i] += ridge;
    }
    // F_νν⁻¹ (1×1 or 2×2)
    let inv = if q == 1 {
        [[1.0 / fnn[0][0], 0.0], [0.0, 0.0]]
    } else {
        let det = fnn[0][0] * fnn[1][1] - fnn[0][1] * fnn[1][0];
        [[fnn[1][1] / det, -fnn[0][1] / det], [-fnn[1][0] / det, fnn[0][0] / det]]
    };
    let mut fsn = [[0.0; 2]; 2];
    for i in 0..k {
        for j in 0..q {
            fsn[i][j] = dot(shared[i], nu[j]);
        }
    }
    for i in 0..k {
        for j in 0..k {
            let mut s = 0.0;
            for p in 0..q {
                for r in 0..q {
                    s += fsn[i][p] * inv[p][r] * fsn[j][r];
                }
            }
            out[i][j] += fss[i][j] - s;
        }
    }
}

/// `√([I⁻¹]₀₀)` of a 1×1 or 2×2 information matrix; infinite where it is singular.
fn bound_of(info: &[[f64; 2]; 2], k: usize) -> f64 {
    let v = if k == 1 {
        1.0 / info[0][0]
    } else {
        let det = info[0][0] * info[1][1] - info[0][1] * info[1][0];
        if det <= info[0][0] * info[1][1] * 1e-12 {
            f64::INFINITY
        } else {
            info[1][1] / det
        }
    };
    if v.is_finite() && v > 0.0 {
        v.sqrt()
    } else {
        f64::INFINITY
    }
}

/// Per-subpixel weights of a `window × window` neighbourhood centred on a pixel of type
/// `centre` (how many of each type it holds); the block itself is every type once.
///
/// # Shapes
/// - returns `[N]`, `N = bh·bw`
pub fn window_weights(block: (usize, usize), window: usize, centre: usize) -> Vec<f64> {
    let (bh, bw) = block;
    let (cr, cc) = ((centre / bw) as i64, (centre % bw) as i64);
    let r = (window / 2) as i64;
    let mut w = vec![0.0; bh * bw];
    for dr in -r..=r {
        for dc in -r..=r {
            let (row, col) = ((cr + dr).rem_euclid(bh as i64) as usize, (cc + dc).rem_euclid(bw as i64) as usize);
            w[row * bw + col] += 1.0;
        }
    }
    w
}

/// The range bound over the cycle ([`range_bound`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RangeBound {
    /// Delays evaluated (bins).
    pub delays_bins: Vec<f64>,
    /// `σ(τ)` bound at each delay (bins).
    pub sigma_bins: Vec<f64>,
    /// Worst over the cycle (bins) and where.
    pub worst_bins: f64,
    pub worst_at_bins: f64,
    /// Mean over the cycle (bins).
    pub mean_bins: f64,
    /// Bin width (s), to state the bound in metres: `σ·c·Δt/2`.
    pub bin_width_s: f64,
}

/// The Cramér–Rao bound of a single return's range at `per_bin` delays in every bin, the block
/// (every subpixel type once) seeing the return.
pub fn range_bound(a: &MeasurementMatrix, light: &Light, per_bin: usize) -> RangeBound {
    let n = a.subpixels();
    range_bound_weighted(&Columns::new(a, 1), light, per_bin, &vec![1.0; n])
}

/// [`range_bound`] on precomputed columns with per-subpixel weights `[N]` (a window's counts,
/// [`window_weights`]).
pub fn range_bound_weighted(a: &Columns, light: &Light, per_bin: usize, weights: &[f64]) -> RangeBound {
    let per_bin = per_bin.max(1);
    let t = a.t;
    let mut delays = Vec::with_capacity(t * per_bin);
    let mut sigma = Vec::with_capacity(t * per_bin);
    let mut scratch = Scratch::new(a);
    for j in 0..t {
        for i in 0..per_bin {
            let tau = j as f64 + 0.5 + (i as f64 + 0.5) / per_bin as f64;
            delays.push(tau.rem_euclid(t as f64));
            sigma.push(range_sigma(a, light, tau, weights, &mut scratch));
        }
    }
    let (worst_i, worst) = sigma.iter().enumerate().fold((0, 0.0f64), |(bi, bv), (i, &v)| if v > bv { (i, v) } else { (bi, bv) });
    let mean = sigma.iter().sum::<f64>() / sigma.len() as f64;
    RangeBound {
        worst_at_bins: delays[worst_i],
        worst_bins: worst,
        mean_bins: mean,
        delays_bins: delays,
        sigma_bins: sigma,
        bin_width_s: a.bin_width_s,
    }
}

/// Buffers of one bound evaluation.
struct Scratch {
    s: Vec<f64>,
    g: Vec<f64>,
    dg: Vec<f64>,
    var: Vec<f64>,
    dmu: Vec<f64>,
}

impl Scratch {
    fn new(a: &Columns) -> Scratch {
        Scratch { s: a.background(), g: vec![0.0; a.channels()], dg: vec![0.0; a.channels()], var: vec![0.0; a.m], dmu: vec![0.0; a.m] }
    }
}

/// The bound `σ(τ)` (bins) of a single return at `tau` bins, subpixel `n` weighted by
/// `weights[n]`.
pub fn range_bound_at(a: &Columns, light: &Light, tau: f64, weights: &[f64]) -> f64 {
    range_sigma(a, light, tau, weights, &mut Scratch::new(a))
}

fn range_sigma(a: &Columns, light: &Light, tau: f64, weights: &[f64], sc: &mut Scratch) -> f64 {
    let m = a.m;
    let b = light.ambient / a.t as f64;
    a.return_at(tau, &mut sc.g, &mut sc.dg);
    let mut info = [[0.0; 2]; 2];
    for (sub, &w) in weights.iter().enumerate() {
        if w == 0.0 {
            continue;
        }
        let r = sub * m..(sub + 1) * m;
        for k in 0..m {
            let c = sub * m + k;
            sc.var[k] = ((light.photons * sc.g[c] + b * sc.s[c]).max(0.0) + light.read_noise_e.powi(2)).max(1e-12);
            sc.dmu[k] = light.photons * sc.dg[c];
        }
        let mut one = [[0.0; 2]; 2];
        profiled_info(&[&sc.dmu], &sc.g[r.clone()], Some(&sc.s[r]), &sc.var, &mut one);
        info[0][0] += w * one[0][0];
    }
    bound_of(&info, 1)
}

/// Two returns' resolution ([`two_returns`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TwoReturns {
    /// Separations evaluated (bins) and the worst bound on either range over the cycle.
    pub separations_bins: Vec<f64>,
    pub worst_sigma_bins: Vec<f64>,
    /// The smallest separation at which `2σ₁ + 2σ₂ ≤ δ` at every position (bins); `None` when
    /// no separation up to half the cycle resolves them.
    pub resolved_bins: Option<f64>,
}

/// The bound on two returns of equal amplitude (half the photons each, amplitudes and a
/// background fitted per subpixel) against their separation, from one bin (or a quarter mask,
/// whichever is more) in steps of a quarter mask up to half the cycle, the worst over the first
/// return at two positions per bin.
pub fn two_returns(a: &Columns, light: &Light, weights: &[f64]) -> TwoReturns {
    let (t, m) = (a.t, a.m);
    let step = (a.k as f64 / 4.0).max(0.25);
    let s = a.background();
    let b = light.ambient / t as f64;
    let half = light.photons / 2.0;
    let nm = a.channels();
    let (mut g1, mut d1, mut g2, mut d2) = (vec![0.0; nm], vec![0.0; nm], vec![0.0; nm], vec![0.0; nm]);
    let mut var = vec![0.0; m];
    let mut seps = Vec::new();
    let mut worst = Vec::new();
    let mut resolved = None;
    let positions: Vec<f64> = (0..t * 2).map(|i| 0.75 + i as f64 * 0.5).collect();
    let mut delta = step.max(1.0);
    while delta <= t as f64 / 2.0 {
        let mut w_sigma = 0.0f64;
        for &p in &positions {
            a.return_at(p, &mut g1, &mut d1);
            a.return_at(p + delta, &mut g2, &mut d2);
            // shared: τ₁, τ₂; nuisance per subpixel: a₁, a₂, b (profiled out by [`schur_2`])
            let mut info = [[0.0f64; 5]; 5];
            for (sub, &w) in weights.iter().enumerate() {
                if w == 0.0 {
                    continue;
                }
                for (k, v) in var.iter_mut().enumerate() {
                    let c = sub * m + k;
                    *v = (half * (g1[c] + g2[c]) + b * s[c]).max(0.0) + light.read_noise_e.powi(2);
                    *v = v.max(1e-12);
                }
                let r = sub * m..(sub + 1) * m;
                let cols: [Vec<f64>; 5] = [
                    d1[r.clone()].iter().map(|d| half * d).collect(),
                    d2[r.clone()].iter().map(|d| half * d).collect(),
                    g1[r.clone()].to_vec(),
                    g2[r.clone()].to_vec(),
                    s[r].to_vec(),
                ];
                // profile this subpixel's nuisance (rows 2..5) out of its 5×5 information
                let mut f = [[0.0f64; 5]; 5];
                for i in 0..5 {
                    for j in 0..5 {
                        f[i][j] = cols[i].iter().zip(&cols[j]).zip(&var).map(|((x, y), v)| x * y / v).sum();
                    }
                }
                let schur = schur_2(&f);
                for i in 0..2 {
                    for j in 0..2 {
                        info[i][j] += w * schur[i][j];
                    }
                }
            }
            let det = info[0][0] * info[1][1] - info[0][1] * info[1][0];
            let (s1, s2) = if det > 1e-12 * info[0][0] * info[1][1] && det > 0.0 {
                ((info[1][1] / det).sqrt(), (info[0][0] / det).sqrt())
            } else {
                (f64::INFINITY, f64::INFINITY)
            };
            w_sigma = w_sigma.max(s1.max(s2));
        }
        seps.push(delta);
        worst.push(w_sigma);
        if resolved.is_none() && 4.0 * w_sigma <= delta {
            resolved = Some(delta);
        }
        delta += step;
    }
    TwoReturns { separations_bins: seps, worst_sigma_bins: worst, resolved_bins: resolved }
}

/// `F₀₀ − F₀ν F_νν⁻¹ F_ν₀` for the first two parameters of a 5×5 information matrix whose
/// last three are nuisance.
fn schur_2(f: &[[f64; 5]; 5]) -> [[f64; 2]; 2] {
    let mut nn = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            nn[i][j] = f[i + 2][j + 2];
        }
    }
    let ridge = RIDGE * (nn[0][0] + nn[1][1] + nn[2][2]).max(f64::MIN_POSITIVE);
    for (i, row) in nn.iter_mut().enumerate() {
        row[i] += ridge;
    }
    let inv = inverse_3(&nn);
    let mut out = [[0.0; 2]; 2];
    for i in 0..2 {
        for j in 0..2 {
            let mut s = 0.0;
            for p in 0..3 {
                for r in 0..3 {
                    s += f[i][p + 2] * inv[p][r] * f[j][r + 2];
                }
            }
            out[i][j] = f[i][j] - s;
        }
    }
    out
}

fn inverse_3(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let c = |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let cof = [
        [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
        [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
        [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
    ];
    let det = m[0][0] * cof[0][0] + m[0][1] * cof[0][1] + m[0][2] * cof[0][2];
    let mut inv = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            inv[i][j] = cof[j][i] / det;
        }
    }
    inv
}

/// Lifetimes (s) the FLIm measures are stated over: `count` points, log-spaced over 0.2–8 ns.
pub fn lifetime_grid(count: usize) -> Vec<f64> {
    let (lo, hi) = (0.2e-9f64, 8e-9f64);
    let count = count.max(2);
    (0..count).map(|i| lo * (hi / lo).powf(i as f64 / (count - 1) as f64)).collect()
}

/// The lifetime bound at one lifetime ([`lifetime_bound`]), over the onsets of the cycle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LifetimePoint {
    /// The lifetime (s).
    pub tau_s: f64,
    /// `σ(τ_f)` (s) with the onset known: mean and worst over the onsets.
    pub known_mean_s: f64,
    pub known_worst_s: f64,
    /// `σ(τ_f)` (s) with the onset fitted by the block: mean and worst over the onsets.
    pub fitted_mean_s: f64,
    pub fitted_worst_s: f64,
}

/// The Cramér–Rao bound of the lifetime of a single-exponential decay, for each lifetime of
/// `taus_s`, at `onsets` onsets spread evenly over the cycle, the block seeing the decay.
pub fn lifetime_bound(a: &Columns, light: &Light, taus_s: &[f64], onsets: usize, weights: &[f64]) -> Vec<LifetimePoint> {
    let onsets = onsets.max(1);
    let period = a.t as f64 * a.bin_width_s;
    taus_s
        .iter()
        .map(|&tau| {
            let (mut km, mut kw, mut fm, mut fw) = (0.0, 0.0f64, 0.0, 0.0f64);
            for o in 0..onsets {
                let t0 = (o as f64 + 0.5) / onsets as f64 * period;
                let (k1, f1) = lifetime_bound_at(a, light, tau, t0, weights);
                km += k1 / onsets as f64;
                kw = kw.max(k1);
                fm += f1 / onsets as f64;
                fw = fw.max(f1);
            }
            LifetimePoint { tau_s: tau, known_mean_s: km, known_worst_s: kw, fitted_mean_s: fm, fitted_worst_s: fw }
        })
        .collect()
}

/// The bound `σ(τ_f)` (s) of a decay of lifetime `tau_s` starting at `onset_s`, with the onset
/// known and with it fitted: `(known, fitted)`.
pub fn lifetime_bound_at(a: &Columns, light: &Light, tau_s: f64, onset_s: f64, weights: &[f64]) -> (f64, f64) {
    let (t, m, nm) = (a.t, a.m, a.channels());
    let dt = a.bin_width_s;
    let s = a.background();
    let b = light.ambient / t as f64;
    let (mut sig, mut sp, mut sm, mut op, mut om) = (vec![0.0; nm], vec![0.0; nm], vec![0.0; nm], vec![0.0; nm], vec![0.0; nm]);
    let (ht, h0) = (tau_s * 1e-4, dt * 1e-3);
    a.apply(&decay_unit_sum(Cycle::new(t, dt), tau_s, onset_s), &mut sig);
    a.apply(&decay_unit_sum(Cycle::new(t, dt), tau_s + ht, onset_s), &mut sp);
    a.apply(&decay_unit_sum(Cycle::new(t, dt), tau_s - ht, onset_s), &mut sm);
    a.apply(&decay_unit_sum(Cycle::new(t, dt), tau_s, onset_s + h0), &mut op);
    a.apply(&decay_unit_sum(Cycle::new(t, dt), tau_s, onset_s - h0), &mut om);
    let mut var = vec![0.0; m];
    let mut known = [[0.0; 2]; 2];
    let mut fitted = [[0.0; 2]; 2];
    for (sub, &w) in weights.iter().enumerate() {
        if w == 0.0 {
            continue;
        }
        let r = sub * m..(sub + 1) * m;
        for (k, v) in var.iter_mut().enumerate() {
            let c = sub * m + k;
            *v = ((light.photons * sig[c] + b * s[c]).max(0.0) + light.read_noise_e.powi(2)).max(1e-12);
        }
        let dtau: Vec<f64> = r.clone().map(|c| light.photons * (sp[c] - sm[c]) / (2.0 * ht)).collect();
        let don: Vec<f64> = r.clone().map(|c| light.photons * (op[c] - om[c]) / (2.0 * h0)).collect();
        let mut one = [[0.0; 2]; 2];
        profiled_info(&[&dtau], &sig[r.clone()], Some(&s[r.clone()]), &var, &mut one);
        known[0][0] += w * one[0][0];
        let mut two = [[0.0; 2]; 2];
        profiled_info(&[&dtau, &don], &sig[r.clone()], Some(&s[r]), &var, &mut two);
        for i in 0..2 {
            for j in 0..2 {
                fitted[i][j] += w * two[i][j];
            }
        }
    }
    (bound_of(&known, 1), bound_of(&fitted, 2))
}

/// The closest pair of decays ([`lifetime_alias`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LifetimeAlias {
    /// Distance between their unit block signatures.
    pub distance: f64,
    /// The two decays: lifetime (s) and onset (bins).
    pub tau1_s: f64,
    pub onset1_bins: f64,
    pub tau2_s: f64,
    pub onset2_bins: f64,
}

/// The lifetime alias: the two decays `(τ_f, t₀)`, `τ_f` from `taus_s` and `t₀` at `onsets`
/// points over the cycle, with onsets at least two masks apart, whose unit block signatures
/// are closest.
pub fn lifetime_alias(a: &Columns, taus_s: &[f64], onsets: usize) -> LifetimeAlias {
    let (t, nm) = (a.t, a.channels());
    let dt = a.bin_width_s;
    let onsets = onsets.max(1);
    let mut sigs: Vec<(f64, f64, Vec<f64>)> = Vec::with_capacity(taus_s.len() * onsets);
    let mut sig = vec![0.0; nm];
    for &tau in taus_s {
        for o in 0..onsets {
            let ob = (o as f64 + 0.5) / onsets as f64 * t as f64;
            a.apply(&decay_unit_sum(Cycle::new(t, dt), tau, ob * dt), &mut sig);
            let norm = sig.iter().map(|v| v * v).sum::<f64>().sqrt();
            sigs.push((tau, ob, sig.iter().map(|v| if norm > 0.0 { v / norm } else { 0.0 }).collect()));
        }
    }
    let min_gap = a.min_shift() as f64;
    let mut best = LifetimeAlias { distance: f64::INFINITY, tau1_s: 0.0, onset1_bins: 0.0, tau2_s: 0.0, onset2_bins: 0.0 };
    for i in 0..sigs.len() {
        for j in i + 1..sigs.len() {
            let g = (sigs[i].1 - sigs[j].1).rem_euclid(t as f64);
            if g.min(t as f64 - g) < min_gap - 1e-9 {
                continue;
            }
            let d2: f64 = sigs[i].2.iter().zip(&sigs[j].2).map(|(x, y)| (x - y) * (x - y)).sum();
            if d2 < best.distance {
                best = LifetimeAlias { distance: d2, tau1_s: sigs[i].0, onset1_bins: sigs[i].1, tau2_s: sigs[j].0, onset2_bins: sigs[j].1 };
            }
        }
    }
    best.distance = best.distance.sqrt();
    best
}

/// Everything `codes analyze` reports of a configuration.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Report {
    /// The light the bounds are stated at.
    pub light: Light,
    /// Bins per mask `K`, bins `T`, bin width (s).
    pub bins_per_mask: usize,
    pub bins: usize,
    pub bin_width_s: f64,
    /// The range alias (returns at least two masks apart).
    pub range_alias: Alias,
    /// The single-return range bound over the cycle.
    pub range: RangeBound,
    /// Two returns of half the photons each.
    pub two_returns: TwoReturns,
    /// The lifetime alias and bounds (FLIm measures; `None` when not asked for).
    pub lifetime_alias: Option<LifetimeAlias>,
    pub lifetime: Option<Vec<LifetimePoint>>,
}

/// Settings of [`analyze`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnalyzeOptions {
    /// Delays per bin of the range bound.
    pub per_bin: usize,
    /// The lifetime measures too (FLIm).
    pub lifetime: bool,
    /// Lifetimes of the grid (0.2–8 ns) and onsets over the cycle.
    pub lifetimes: usize,
    pub onsets: usize,
}

impl Default for AnalyzeOptions {
    fn default() -> Self {
        AnalyzeOptions { per_bin: 4, lifetime: false, lifetimes: 16, onsets: 64 }
    }
}

/// Every measure of a configuration: `a` the sensor's matrix on a grid of `k` bins per mask.
pub fn analyze(a: &MeasurementMatrix, k: usize, light: &Light, opts: &AnalyzeOptions) -> Report {
    let cols = Columns::new(a, k);
    let weights = vec![1.0; a.subpixels()];
    let taus = lifetime_grid(opts.lifetimes);
    Report {
        light: *light,
        bins_per_mask: cols.k,
        bins: cols.t,
        bin_width_s: cols.bin_width_s,
        range_alias: range_alias(&cols),
        range: range_bound_weighted(&cols, light, opts.per_bin, &weights),
        two_returns: two_returns(&cols, light, &weights),
        lifetime_alias: opts.lifetime.then(|| lifetime_alias(&cols, &taus, opts.onsets.min(cols.t))),
        lifetime: opts.lifetime.then(|| lifetime_bound(&cols, light, &taus, opts.onsets, &weights)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{generate, Irf, SensorParams};

    fn matrix(seed: u64, irf: Irf) -> MeasurementMatrix {
        let codes = generate::prototype_codes(seed).unwrap();
        let spec = SensorParams { irf, ..SensorParams::from_codes(&codes) }.validate().unwrap();
        MeasurementMatrix::synthesize(&codes, &spec).unwrap()
    }

    /// The range alias finds a planted pair of proportional signatures, and nothing closer.
    #[test]
    fn range_alias_finds_proportional_block_signatures() {
        let codes = generate::prototype_codes(1).unwrap();
        let spec = SensorParams { length: 16, ..SensorParams::from_codes(&codes) }.validate().unwrap();
        // every bin its own direction (a distinct tap lit per subpixel pattern), then bin 11
        // made 3 × bin 4: the same taps up to scale, 7 bins apart
        let mut a = ndarray::Array3::<f32>::zeros((4, 4, 16));
        for l in 0..16 {
            a[(l % 4, l / 4, l)] = 1.0;
            a[((l + 1) % 4, (l / 4 + 1) % 4, l)] = 0.5;
        }
        let fresh = range_alias(&Columns::new(&MeasurementMatrix::from_array(a.clone(), &spec).unwrap(), 1));
        assert!(fresh.distance > 1.0, "{fresh:?}");
        for i in 0..16 {
            a[(i / 4, i % 4, 11)] = 3.0 * a[(i / 4, i % 4, 4)];
        }
        let alias = range_alias(&Columns::new(&MeasurementMatrix::from_array(a, &spec).unwrap(), 1));
        assert_eq!((alias.bin, alias.other), (4, 11), "{alias:?}");
        assert!(alias.distance < 1e-6, "{alias:?}");
    }

    #[test]
    fn codes_with_two_equal_columns_alias_exactly() {
        let a = matrix(1, Irf::Ideal);
        let mut v = a.a().to_owned();
        let col = v.index_axis(ndarray::Axis(2), 3).to_owned();
        v.index_axis_mut(ndarray::Axis(2), 20).assign(&col);
        let b = a.with_values(v).unwrap();
        let al = range_alias(&Columns::new(&b, 1));
        assert!(al.distance < 1e-9, "{al:?}");
        assert_eq!((al.bin, al.other), (3, 20));
    }

    /// The profiled Fisher information against a direct inverse of the full 3×3 matrix.
    #[test]
    fn profiled_information_is_the_schur_complement() {
        let d = [1.0, -2.0, 0.5, 3.0];
        let g = [0.2, 0.3, 0.1, 0.4];
        let s = [8.0, 7.0, 9.0, 8.0];
        let var = [100.0, 200.0, 150.0, 120.0];
        let mut out = [[0.0; 2]; 2];
        profiled_info(&[&d], &g, Some(&s), &var, &mut out);
        let cols = [&d[..], &g[..], &s[..]];
        let mut f = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                f[i][j] = (0..4).map(|k| cols[i][k] * cols[j][k] / var[k]).sum();
            }
        }
        let inv = inverse_3(&f);
        assert!((out[0][0] - 1.0 / inv[0][0]).abs() < 1e-9 * out[0][0], "{} vs {}", out[0][0], 1.0 / inv[0][0]);
    }

    #[test]
    fn bound_falls_as_one_over_root_photons_without_read_noise() {
        let a = matrix(2, Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 });
        let lo = Light { photons: 1000.0, ambient: 0.0, read_noise_e: 0.0 };
        let hi = Light { photons: 4000.0, ..lo };
        let (r1, r4) = (range_bound(&a, &lo, 2), range_bound(&a, &hi, 2));
        assert!((r1.mean_bins / r4.mean_bins - 2.0).abs() < 1e-6, "{} {}", r1.mean_bins, r4.mean_bins);
    }

    #[test]
    fn lifetime_bound_is_smaller_with_the_onset_known() {
        let codes = generate::prototype_codes(1).unwrap();
        let spec = SensorParams {
            irf: Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 },
            sampling: crate::Sampling::Heterodyne(8),
            ..SensorParams::from_codes(&codes)
        }
        .validate()
        .unwrap();
        let a = MeasurementMatrix::synthesize(&codes, &spec).unwrap();
        let cols = Columns::new(&a, 8);
        let pts = lifetime_bound(&cols, &Light::default(), &[1e-9, 4e-9], 16, &[1.0; 4]);
        for p in &pts {
            assert!(p.known_mean_s > 0.0 && p.known_mean_s <= p.fitted_mean_s * (1.0 + 1e-9), "{p:?}");
            assert!(p.known_worst_s >= p.known_mean_s);
        }
        let al = lifetime_alias(&cols, &lifetime_grid(4), 16);
        assert!(al.distance > 0.0 && al.distance.is_finite());
    }
}
