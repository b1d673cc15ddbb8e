//! The measurement matrix `A [N, M, T]` (paper eqs. 3–4, DESIGN §3).
//!
//! For subpixel type `n`, tap `m` and fine bin `j` (width `Δt = T_c/K`),
//! `A[n][m][j] = (1/Δt) ∫_bin j ((g_nm ∗ h_m) ⋆ l)(τ) dτ`: the fraction of the light arriving
//! during bin `j` that ends up in tap `m`. Time is cyclic with period `L·T_c`.
//!
//! - `Irf::Ideal`: rectangular gates, no blur — `A[n][m][j] = g[n][m][⌊j/K⌋]`, so
//!   `y = A x` is a plain sum of code bits over the cube.
//! - `Irf::Physical`: gate ∗ first-order tap response `h(t) = e^{−t/τ}/τ`, correlated with a
//!   unit-area Gaussian laser pulse; computed on a super-sampled cyclic grid, then averaged
//!   over each bin. Σ_m A[n][m][j] = 1 still holds for codes with exactly one tap on.
//! - Heterodyne (`K` cycles, the scene delayed by `kΔ` in cycle `k`):
//!   `A_het[n][m][j] = Σ_k A[n][m][(j + k) mod T]` on the fine grid.
//! - A measured `A` (`.npy`, `[N, M, T]`) replaces the synthetic one.

use crate::codes::Codes;
use crate::error::{Result, SensorError};
use crate::npy;
use crate::params::{Irf, Sampling, SensorSpec};
use ndarray::{Array2, Array3, ArrayView3, Axis, Ix3};
use rayon::prelude::*;
use std::path::Path;

/// Upper bound on super-samples per fine bin of the physical IRF.
const MAX_SUPERSAMPLE: usize = 64;

/// A measurement matrix `A [N, M, T]` with the block geometry it repeats over.
#[derive(Debug, Clone, PartialEq)]
pub struct MeasurementMatrix {
    a: Array3<f32>,
    block: (usize, usize),
    bin_width_s: f64,
}

/// The matched filters' regulariser ([`MeasurementMatrix::matched_filters`]): a column whose
/// part outside the ambient's span is below `ε` of its norm is damped towards zero.
pub const MATCHED_EPS: f64 = 1e-3;

impl MeasurementMatrix {
    /// A fingerprint of `A` (its shape, block and f32 values; FNV-1a, 16 hex digits): the
    /// codes, IRF and sampling in one number.
    pub fn digest(&self) -> String {
        let (n, m, t) = self.a().dim();
        let (bh, bw) = self.block();
        let head = [n, m, t, bh, bw].into_iter().flat_map(|v| (v as u64).to_le_bytes());
        let values: Vec<u8> = self.a().iter().flat_map(|v| v.to_le_bytes()).collect();
        crate::digest::digest(head.chain(values))
    }

    /// Build `A` from codes and a sensor spec (IRF and sampling from the spec).
    ///
    /// # Shapes
    /// - returns `A`: `[N, M, T]`, `N = bh·bw`, `T = L·K`.
    pub fn synthesize(codes: &Codes, spec: &SensorSpec) -> Result<Self> {
        spec.check_codes(codes)?;
        let k = spec.sampling().k();
        let dt = spec.bin_width_s();
        let fine = match spec.irf() {
            Irf::Ideal => ideal(codes, k),
            Irf::Physical { laser_fwhm_s, tap_tau_s } => physical(codes, k, dt, laser_fwhm_s, tap_tau_s),
        };
        let a = match spec.sampling() {
            Sampling::Oversample(_) => fine,
            Sampling::Heterodyne(_) => heterodyne_sum(&fine.view(), k),
        };
        Ok(MeasurementMatrix { a, block: codes.block(), bin_width_s: dt })
    }

    /// Wrap a given (e.g. measured) `A [N, M, T]`, checking its shape against the spec.
    pub fn from_array(a: Array3<f32>, spec: &SensorSpec) -> Result<Self> {
        let (n, m, t) = a.dim();
        if n != spec.subpixels() || m != spec.taps() || t != spec.bins() {
            return Err(SensorError::Shape {
                what: "measurement matrix A".into(),
                got: vec![n, m, t],
                expected: format!(
                    "[N, M, T] = [{}, {}, {}] (block {}x{}, {} taps, T = L·K = {})",
                    spec.subpixels(),
                    spec.taps(),
                    spec.bins(),
                    spec.params().block.0,
                    spec.params().block.1,
                    spec.taps(),
                    spec.bins()
                ),
            });
        }
        npy::ensure_finite(&a.view(), "measurement matrix A")?;
        Ok(MeasurementMatrix { a, block: spec.params().block, bin_width_s: spec.bin_width_s() })
    }

    /// The same sensor geometry (block, bin width) with other values of `A`, e.g. a real
    /// sensor's or a calibrated one.
    ///
    /// # Shapes
    /// - `a`: `[N, M, T]`, the shape of `self`
    pub fn with_values(&self, a: Array3<f32>) -> Result<Self> {
        if a.dim() != self.a.dim() {
            let (n, m, t) = self.a.dim();
            return Err(SensorError::Shape {
                what: "measurement matrix A".into(),
                got: a.shape().to_vec(),
                expected: format!("[N, M, T] = [{n}, {m}, {t}]"),
            });
        }
        npy::ensure_finite(&a.view(), "measurement matrix A")?;
        Ok(MeasurementMatrix { a, block: self.block, bin_width_s: self.bin_width_s })
    }

    /// Load a measured `A [N, M, T]` from `.npy`; errors name the file.
    pub fn load(path: &Path, spec: &SensorSpec) -> Result<Self> {
        let a = npy::read_npy(path)?;
        let shape = a.shape().to_vec();
        let a = a
            .into_dimensionality::<Ix3>()
            .map_err(|_| SensorError::file(path, format!("measurement matrix of shape {shape:?}, expected rank 3 [N, M, T]")))?;
        MeasurementMatrix::from_array(a, spec).map_err(|e| e.in_file(path))
    }

    /// Save `A` as `.npy` (`[N, M, T]`, float32).
    pub fn save(&self, path: &Path) -> Result<()> {
        npy::write_npy(path, &self.a.view())
    }

    /// The matrix, `[N, M, T]`.
    pub fn a(&self) -> ArrayView3<'_, f32> {
        self.a.view()
    }
    /// Block `(bh, bw)`.
    pub fn block(&self) -> (usize, usize) {
        self.block
    }
    /// Subpixels `N`.
    pub fn subpixels(&self) -> usize {
        self.a.dim().0
    }
    /// Taps `M`.
    pub fn taps(&self) -> usize {
        self.a.dim().1
    }
    /// Bins `T`.
    pub fn bins(&self) -> usize {
        self.a.dim().2
    }
    /// Bin width `Δt` (s).
    pub fn bin_width_s(&self) -> f64 {
        self.bin_width_s
    }

    /// The Gram matrices `A_nA_nᵀ` of every subpixel type, accumulated in f64: the one `AAᵀ`
    /// behind TVAL3's scaling and the learned decoders' back-projection and data consistency.
    ///
    /// # Shapes
    /// - returns `[N, M, M]`
    pub fn gram(&self) -> Array3<f64> {
        let (n, m, t) = self.a.dim();
        Array3::from_shape_fn((n, m, m), |(k, i, j)| (0..t).map(|l| self.a[(k, i, l)] as f64 * self.a[(k, j, l)] as f64).sum())
    }

    /// The eigen-decomposition `A_nA_nᵀ = Q_n Λ_n Q_nᵀ` of every Gram matrix (cyclic Jacobi
    /// rotations, to f64 precision).
    ///
    /// # Shapes
    /// - returns eigenvalues `[N, M]` and eigenvectors `[N, M, M]`, where `q[(n, r, i)]` is
    ///   component `r` of eigenvector `i` (the columns of `Q_n`)
    pub fn gram_eigen(&self) -> (Array2<f64>, Array3<f64>) {
        let g = self.gram();
        let (n, m, _) = g.dim();
        let mut lambda = Array2::zeros((n, m));
        let mut q = Array3::zeros((n, m, m));
        for k in 0..n {
            let gk: Vec<f64> = g.index_axis(Axis(0), k).iter().copied().collect();
            let (l, v) = symmetric_eigen(&gk, m);
            for r in 0..m {
                lambda[(k, r)] = l[r];
                for c in 0..m {
                    q[(k, r, c)] = v[r * m + c];
                }
            }
        }
        (lambda, q)
    }

    /// `λ_max(A_nA_nᵀ)` over the subpixel types (`‖A‖²` of the per-pixel operator).
    pub fn max_gram_eigenvalue(&self) -> f64 {
        self.gram_eigen().0.iter().fold(0f64, |a, &b| a.max(b))
    }

    /// The matched filters of the range fit at the bin centres, ambient projected out: row `t`
    /// of `F_n` is `ĝ_n(t)ᵀ = (P_n a_{n,t})ᵀ / ‖P_n a_{n,t}‖`, where `a_{n,t}` is column `t` of
    /// `A_n` (the template of a return at bin `t`'s centre, the IRF included), `s_n = A_n 1`
    /// the template of ambient light and `P_n = I − s_n s_nᵀ/‖s_n‖²`. So `(F_n y)_t` is the
    /// correlation of the taps with a return at bin `t` after the best ambient level is
    /// removed, and its square over `‖P_n y‖²` the share of the taps that one return there
    /// explains: `argmax_t (F_n y)_t` is the per-pixel least-squares range on the bin grid
    /// (`a ≥ 0`, ambient free). A column with (almost) nothing outside the ambient's span gets
    /// a (nearly) zero row: the division is by `‖P a‖ + ε²‖a‖²/‖P a‖` ([`MATCHED_EPS`]), the
    /// same in f64 here and in f32 in the networks, so that rounding is never normalised up
    /// to a unit row. Computed in f64.
    ///
    /// # Shapes
    /// - returns `[N, T, M]`
    pub fn matched_filters(&self) -> Array3<f64> {
        let (n, m, t) = self.a.dim();
        let mut f = Array3::zeros((n, t, m));
        for k in 0..n {
            let s: Vec<f64> = (0..m).map(|i| (0..t).map(|l| self.a[(k, i, l)] as f64).sum()).collect();
            let ss: f64 = s.iter().map(|v| v * v).sum();
            for l in 0..t {
                let col: Vec<f64> = (0..m).map(|i| self.a[(k, i, l)] as f64).collect();
                let along = if ss > 0.0 { col.iter().zip(&s).map(|(a, b)| a * b).sum::<f64>() / ss } else { 0.0 };
                let p: Vec<f64> = col.iter().zip(&s).map(|(a, b)| a - along * b).collect();
                let pp: f64 = p.iter().map(|v| v * v).sum();
                let aa: f64 = col.iter().map(|v| v * v).sum();
                let scale = pp.sqrt() / (pp + MATCHED_EPS * MATCHED_EPS * aa).max(f64::MIN_POSITIVE);
                for i in 0..m {
                    f[(k, l, i)] = p[i] * scale;
                }
            }
        }
        f
    }
}

/// Eigen-decomposition of a symmetric `n × n` matrix (row-major) by cyclic Jacobi rotations:
/// returns `(eigenvalues, Q)` with `Q[j·n + i]` the `j`-th component of eigenvector `i`.
fn symmetric_eigen(a: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut m = a.to_vec();
    let mut q = vec![0.0; n * n];
    for i in 0..n {
        q[i * n + i] = 1.0;
    }
    for _sweep in 0..100 {
        let off: f64 = (0..n).flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j))).map(|(i, j)| m[i * n + j].powi(2)).sum();
        let scale: f64 = m.iter().map(|v| v * v).sum::<f64>().max(f64::MIN_POSITIVE);
        if off <= 1e-30 * scale {
            break;
        }
        for p in 0..n {
            for r in p + 1..n {
                let apr = m[p * n + r];
                if apr.abs() < 1e-300 {
                    continue;
                }
                let theta = (m[r * n + r] - m[p * n + p]) / (2.0 * apr);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (mkp, mkr) = (m[k * n + p], m[k * n + r]);
                    m[k * n + p] = c * mkp - s * mkr;
                    m[k * n + r] = s * mkp + c * mkr;
                }
                for k in 0..n {
                    let (mpk, mrk) = (m[p * n + k], m[r * n + k]);
                    m[p * n + k] = c * mpk - s * mrk;
                    m[r * n + k] = s * mpk + c * mrk;
                }
                for k in 0..n {
                    let (qkp, qkr) = (q[k * n + p], q[k * n + r]);
                    q[k * n + p] = c * qkp - s * qkr;
                    q[k * n + r] = s * qkp + c * qkr;
                }
            }
        }
    }
    ((0..n).map(|i| m[i * n + i]).collect(), q)
}

/// `A[n][m][j] = g[n][m][⌊j/K⌋]`. Shape `[N, M, L·K]`.
fn ideal(codes: &Codes, k: usize) -> Array3<f32> {
    let (n, m, l) = (codes.subpixels(), codes.taps(), codes.length());
    Array3::from_shape_fn((n, m, l * k), |(n, m, j)| codes.get(n, m, j / k) as u8 as f32)
}

/// Physical IRF on the fine grid. Shape `[N, M, L·K]`.
fn physical(codes: &Codes, k: usize, dt: f64, fwhm: f64, tau: f64) -> Array3<f32> {
    let (n_sub, taps, len) = (codes.subpixels(), codes.taps(), codes.length());
    let irf = PhysicalIrf::new(len, k, dt, fwhm, tau);
    let mut a = Array3::<f32>::zeros((n_sub, taps, len * k));
    let channels: Vec<(usize, Vec<f32>)> = (0..n_sub * taps).into_par_iter().map(|c| (c, irf.row(codes.channel(c)))).collect();
    for (c, row) in channels {
        a.index_axis_mut(Axis(0), c / taps).index_axis_mut(Axis(0), c % taps).assign(&ndarray::ArrayView1::from(&row[..]));
    }
    a
}

/// The physical IRF of one channel on a super-sampled cyclic grid.
struct PhysicalIrf {
    k: usize,
    /// Super-samples per fine bin.
    s: usize,
    kernel: Vec<(isize, f64)>,
    decay: f64,
    t: usize,
}

impl PhysicalIrf {
    fn new(len: usize, k: usize, dt: f64, fwhm: f64, tau: f64) -> Self {
        let t = len * k;
        let sigma = fwhm / (2.0 * (2.0 * std::f64::consts::LN_2).sqrt());
        let finest = [sigma, tau].into_iter().filter(|&v| v > 0.0).fold(f64::INFINITY, f64::min);
        let mut s = if finest.is_finite() { (dt / (finest / 8.0)).ceil() as usize } else { 1 };
        s = s.clamp(1, MAX_SUPERSAMPLE);
        while s > 1 && t * s > (1 << 20) {
            s /= 2;
        }
        let delta = dt / s as f64;
        let kernel = laser_kernel(sigma, delta, t * s);
        let decay = if tau > 0.0 { (-delta / tau).exp() } else { 0.0 };
        PhysicalIrf { k, s, kernel, decay, t }
    }

    /// `A`'s row `[T]` of a channel with gate bits `g [L]` (0 or 1; linear in them).
    fn row(&self, g: &[u8]) -> Vec<f32> {
        let (k, s, t) = (self.k, self.s, self.t);
        let p = t * s;
        // Gate on the super grid: mask l covers super-samples [l·K·S, (l+1)·K·S).
        let g: Vec<f64> = (0..p).map(|q| g[q / (k * s)] as f64).collect();
        let geff = first_order_cyclic(&g, self.decay);
        // the kernel's offsets run from `lo` to `hi` in steps of one: `geff` cyclically extended,
        // `ext[u] = geff[(u + lo) mod P]`, reads `geff[(q + d) mod P]` at `ext[q + d − lo]` with
        // no modulo per multiply-add (the products added in the same order: the same bits)
        let (lo, hi) = (self.kernel.first().map_or(0, |x| x.0), self.kernel.last().map_or(0, |x| x.0));
        debug_assert!(self.kernel.iter().enumerate().all(|(i, x)| x.0 == lo + i as isize));
        let ext: Vec<f64> = (0..p + (hi - lo) as usize).map(|u| geff[(u as isize + lo).rem_euclid(p as isize) as usize]).collect();
        let weights: Vec<f64> = self.kernel.iter().map(|x| x.1).collect();
        let mut row = vec![0f32; t];
        for (j, out) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for q in j * s..(j + 1) * s {
                for (w, x) in weights.iter().zip(&ext[q..q + weights.len()]) {
                    acc += w * x;
                }
            }
            *out = (acc / s as f64) as f32;
        }
        row
    }
}

impl MeasurementMatrix {
    /// The code basis `G [L, T]` of a sensor: `A` is linear in the code bits, the same map
    /// for every channel, so `A[n][m][·] = Σ_l g[n][m][l] · G[l][·]` — row `l` is the row of a
    /// channel open during mask `l` only (through the spec's IRF, oversampling or heterodyne
    /// sum). Learned codes train through this map (`tcsense_models::codes`).
    ///
    /// # Shapes
    /// - returns `G`: `[L, T]`, `T = L·K`.
    pub fn code_basis(spec: &SensorSpec) -> Array2<f32> {
        let (len, k) = (spec.shape().length, spec.sampling().k());
        let t = len * k;
        let unit = |l: usize| -> Vec<u8> { (0..len).map(|i| u8::from(i == l)).collect() };
        let fine = Array3::from_shape_vec(
            (1, len, t),
            match spec.irf() {
                Irf::Ideal => (0..len).flat_map(|l| (0..t).map(move |j| if j / k == l { 1.0 } else { 0.0 })).collect(),
                Irf::Physical { laser_fwhm_s, tap_tau_s } => {
                    let irf = PhysicalIrf::new(len, k, spec.bin_width_s(), laser_fwhm_s, tap_tau_s);
                    (0..len).flat_map(|l| irf.row(&unit(l))).collect()
                }
            },
        )
        .expect("L·T values");
        let a = match spec.sampling() {
            Sampling::Oversample(_) => fine,
            Sampling::Heterodyne(_) => heterodyne_sum(&fine.view(), k),
        };
        a.index_axis_move(Axis(0), 0)
    }
}

/// Cyclic steady state of `y[p] = a·y[p−1] + (1−a)·(g[p] + g[p−1])/2`: the first-order
/// response `e^{−t/τ}/τ` with `a = e^{−δ/τ}`, unit DC gain and mean delay `τ` (to `O(δ²/τ)`).
fn first_order_cyclic(g: &[f64], a: f64) -> Vec<f64> {
    if a == 0.0 {
        return g.to_vec();
    }
    let n = g.len();
    let u: Vec<f64> = (0..n).map(|p| 0.5 * (g[p] + g[(p + n - 1) % n])).collect();
    let pass = |y0: f64, out: &mut Vec<f64>| {
        out.clear();
        let mut y = y0;
        for &v in &u {
            y = a * y + (1.0 - a) * v;
            out.push(y);
        }
    };
    let mut out = Vec::with_capacity(g.len());
    pass(0.0, &mut out);
    let last = out.last().copied().unwrap_or(0.0);
    let y0 = last / (1.0 - a.powi(g.len() as i32));
    pass(y0, &mut out);
    out
}

/// Unit-sum Gaussian kernel `(offset, weight)` on a cyclic grid of `p` samples of width `delta`.
fn laser_kernel(sigma: f64, delta: f64, p: usize) -> Vec<(isize, f64)> {
    if sigma <= 0.0 || sigma < delta / 8.0 {
        return vec![(0, 1.0)];
    }
    let pi = p as isize;
    // in f64 first: a pulse of many cycles must not overflow the offsets
    let reach_f = (6.0 * sigma / delta).ceil();
    // A pulse wider than half the cycle wraps: cover one whole period and add its images (as
    // many periods as the pulse reaches, at least 4).
    let (offsets, images) = if 2.0 * reach_f < p as f64 {
        let reach = reach_f as isize;
        (-reach..=reach, 0)
    } else {
        (-(pi / 2)..=(pi - pi / 2 - 1), ((reach_f / p as f64).ceil() as isize).clamp(4, 64))
    };
    let mut k: Vec<(isize, f64)> = offsets
        .map(|d| {
            let w: f64 = (-images..=images)
                .map(|i: isize| {
                    let x = (d + i * pi) as f64 * delta;
                    (-x * x / (2.0 * sigma * sigma)).exp()
                })
                .sum();
            (d, w)
        })
        .collect();
    let total: f64 = k.iter().map(|x| x.1).sum();
    for x in &mut k {
        x.1 /= total;
    }
    k
}

/// `A_het[n][m][j] = Σ_{k<K} A[n][m][(j + k) mod T]`.
///
/// # Shapes
/// - `fine`: `[N, M, T]` → `[N, M, T]`
pub fn heterodyne_sum(fine: &ArrayView3<'_, f32>, k: usize) -> Array3<f32> {
    let t = fine.dim().2;
    let mut out = Array3::<f32>::zeros(fine.dim());
    for ((n, m, j), v) in out.indexed_iter_mut() {
        *v = (0..k).map(|kk| fine[(n, m, (j + kk) % t)]).sum();
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::{CodeShape, Constraints};
    use crate::generate::random_codes;
    use crate::params::SensorParams;

    fn codes() -> Codes {
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        random_codes(shape, 607e6, Constraints { tap: true, hamming: Some(2), window: Some(2) }, 5).unwrap()
    }

    fn spec(c: &Codes, sampling: Sampling, irf: Irf) -> SensorSpec {
        SensorParams { sampling, irf, ..SensorParams::from_codes(c) }.validate().unwrap()
    }

    /// `A` is the code bits times the code basis, for every IRF and sampling.
    #[test]
    fn matrix_is_bits_times_the_code_basis() {
        let c = codes();
        let phys = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
        for (sampling, irf) in [
            (Sampling::Oversample(1), Irf::Ideal),
            (Sampling::Oversample(2), Irf::Ideal),
            (Sampling::Oversample(2), phys),
            (Sampling::Heterodyne(4), Irf::Ideal),
            (Sampling::Heterodyne(4), phys),
        ] {
            let sp = spec(&c, sampling, irf);
            let a = MeasurementMatrix::synthesize(&c, &sp).unwrap();
            let g = MeasurementMatrix::code_basis(&sp);
            assert_eq!(g.dim(), (16, 16 * sampling.k()));
            let peak = a.a().iter().fold(0f32, |m, v| m.max(v.abs()));
            for ((n, m, j), &v) in a.a().indexed_iter() {
                let from_basis: f32 = (0..16).map(|l| c.get(n, m, l) as u8 as f32 * g[(l, j)]).sum();
                assert!((v - from_basis).abs() <= 1e-5 * peak, "{sampling:?} {irf:?} [{n}, {m}, {j}]: {v} vs {from_basis}");
            }
        }
    }

    /// The matched filters see a return at its bin, whatever the ambient level, and no ambient.
    #[test]
    fn matched_filters_find_the_return_and_ignore_ambient() {
        let c = codes();
        let a = MeasurementMatrix::synthesize(
            &c,
            &spec(&c, Sampling::Oversample(1), Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }),
        )
        .unwrap();
        let f = a.matched_filters();
        let (n, m, t) = a.a().dim();
        let mut checked = 0;
        assert_eq!(f.dim(), (n, t, m));
        for k in 0..n {
            let s: Vec<f64> = (0..m).map(|i| a.a().index_axis(Axis(0), k).row(i).iter().map(|&v| v as f64).sum()).collect();
            let informative: Vec<bool> = (0..t)
                .map(|l| {
                    let row = f.index_axis(Axis(0), k);
                    let norm: f64 = row.row(l).iter().map(|v| v * v).sum::<f64>().sqrt();
                    // a column along the ambient's template carries no range: a zero row
                    let col: Vec<f64> = (0..m).map(|i| a.a()[(k, i, l)] as f64).collect();
                    let cos = col.iter().zip(&s).map(|(a, b)| a * b).sum::<f64>()
                        / (col.iter().map(|v| v * v).sum::<f64>() * s.iter().map(|v| v * v).sum::<f64>()).sqrt();
                    assert!(
                        (norm - 1.0).abs() < 1e-4 || (norm < 1e-6 && (cos - 1.0).abs() < 1e-9),
                        "row {l} of type {k}: norm {norm}, column at cos {cos} to the ambient"
                    );
                    let amb: f64 = row.row(l).iter().zip(&s).map(|(a, b)| a * b).sum();
                    assert!(amb.abs() < 1e-9 * s.iter().map(|v| v.abs()).sum::<f64>(), "ambient leaks: {amb}");
                    norm > 0.5
                })
                .collect();
            if informative.iter().filter(|&&i| i).count() < t / 2 {
                continue;
            }
            checked += 1;
            for t0 in [0, 5, t - 1].into_iter().filter(|&t0| informative[t0]) {
                // a return at bin t0 under ambient light five times the return's weight
                let y: Vec<f64> = (0..m).map(|i| 3.0 * a.a()[(k, i, t0)] as f64 + 5.0 * s[i]).collect();
                let corr: Vec<f64> = (0..t).map(|l| (0..m).map(|i| f[(k, l, i)] * y[i]).sum()).collect();
                let best = (0..t).max_by(|&i, &j| corr[i].total_cmp(&corr[j])).unwrap();
                // M = 4 taps (two in some types): the best may tie within 10⁻⁵, never beat it
                assert!(
                    corr[t0] >= corr[best] - 1e-5 * corr[best].abs(),
                    "type {k}, return at {t0}: best {best}; {corr:?}; column {:?} s {s:?}",
                    a.a().index_axis(Axis(0), k).column(t0)
                );
            }
        }
        assert!(checked >= 2, "{checked} subpixel types with range information");
    }

    #[test]
    fn ideal_is_the_code_bits_oversampled() {
        let c = codes();
        let a = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(4), Irf::Ideal)).unwrap();
        assert_eq!(a.a().dim(), (4, 4, 64));
        for n in 0..4 {
            for m in 0..4 {
                for j in 0..64 {
                    assert_eq!(a.a()[(n, m, j)], c.get(n, m, j / 4) as u8 as f32);
                }
            }
        }
    }

    #[test]
    fn physical_conserves_charge_and_tends_to_ideal() {
        let c = codes();
        let phys = Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 };
        let a = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(2), phys)).unwrap();
        // exactly one tap on at every mask -> the taps' responses sum to one at every delay
        for n in 0..4 {
            for j in 0..32 {
                let s: f32 = (0..4).map(|m| a.a()[(n, m, j)]).sum();
                assert!((s - 1.0).abs() < 1e-4, "sum {s}");
            }
        }
        // a wide pulse blurs: entries strictly between 0 and 1 appear
        assert!(a.a().iter().any(|&v| v > 0.05 && v < 0.95));
        // a vanishing pulse and tap response give the ideal matrix
        let tiny = Irf::Physical { laser_fwhm_s: 1e-15, tap_tau_s: 0.0 };
        let p = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(2), tiny)).unwrap();
        let i = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(2), Irf::Ideal)).unwrap();
        let err = (&p.a() - &i.a()).iter().fold(0f32, |m, v| m.max(v.abs()));
        assert!(err < 1e-6, "max |phys - ideal| = {err}");
    }

    /// A channel's row through the physical IRF is the double sum as written, with a modulo
    /// per multiply-add: the same bits, for a narrow pulse and for one that wraps the cycle.
    #[test]
    fn physical_rows_are_the_cyclic_sum_written_out() {
        for (len, k, fwhm, tau) in [(8, 2, 0.8e-9, 0.3e-9), (8, 1, 30e-9, 0.0), (5, 4, 0.2e-9, 1e-9)] {
            let irf = PhysicalIrf::new(len, k, 1e-9, fwhm, tau);
            let g: Vec<u8> = (0..len).map(|l| u8::from(l % 3 != 1)).collect();
            let (s, t) = (irf.s, irf.t);
            let p = t * s;
            let fine: Vec<f64> = (0..p).map(|q| g[q / (k * s)] as f64).collect();
            let geff = first_order_cyclic(&fine, irf.decay);
            let want: Vec<f32> = (0..t)
                .map(|j| {
                    let mut acc = 0.0;
                    for q in j * s..(j + 1) * s {
                        for &(d, w) in &irf.kernel {
                            acc += w * geff[(q as isize + d).rem_euclid(p as isize) as usize];
                        }
                    }
                    (acc / s as f64) as f32
                })
                .collect();
            assert!(irf.kernel.len() > 1, "a blurring pulse");
            assert_eq!(irf.row(&g).iter().map(|v| v.to_bits()).collect::<Vec<_>>(), want.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
        }
    }

    #[test]
    fn tap_response_delays_the_gate() {
        // A single 8-mask window: a slow tap response moves its centre of mass later.
        let shape = CodeShape { bh: 1, bw: 1, taps: 1, length: 32, drain: true };
        let mut c = Codes::zeros(shape, 607e6, Constraints::default()).unwrap();
        for l in 8..16 {
            c.set(0, 0, l, true);
        }
        let com = |irf| {
            let a = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(1), irf)).unwrap();
            let row = a.a().index_axis(Axis(0), 0).index_axis(Axis(0), 0).to_owned();
            let total: f32 = row.sum();
            (row.iter().enumerate().map(|(j, v)| (j as f32 + 0.5) * v).sum::<f32>() / total, total)
        };
        let (c_ideal, s_ideal) = com(Irf::Ideal);
        let tau = 1.0 / 607e6; // one mask
        let (c_slow, s_slow) = com(Irf::Physical { laser_fwhm_s: 0.0, tap_tau_s: tau });
        assert!((c_ideal - 12.0).abs() < 1e-4);
        // the first-order response delays the centre of mass by τ (= 1 bin)
        assert!((c_slow - c_ideal - 1.0).abs() < 0.02, "shift {}", c_slow - c_ideal);
        assert!((s_slow - s_ideal).abs() < 1e-3, "area is kept");
    }

    #[test]
    fn heterodyne_is_a_shifted_sum() {
        let c = codes();
        let fine = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Oversample(8), Irf::Ideal)).unwrap();
        let het = MeasurementMatrix::synthesize(&c, &spec(&c, Sampling::Heterodyne(8), Irf::Ideal)).unwrap();
        let t = 128;
        for j in [0, 5, 127] {
            let want: f32 = (0..8).map(|k| fine.a()[(1, 2, (j + k) % t)]).sum();
            assert_eq!(het.a()[(1, 2, j)], want);
        }
    }

    #[test]
    fn jacobi_diagonalises() {
        let a = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 1.0];
        let (l, q) = symmetric_eigen(&a, 3);
        for i in 0..3 {
            for r in 0..3 {
                let aq: f64 = (0..3).map(|c| a[r * 3 + c] * q[c * 3 + i]).sum();
                assert!((aq - l[i] * q[r * 3 + i]).abs() < 1e-10);
            }
        }
    }

    #[test]
    fn gram_eigen_reconstructs_a_at() {
        let c = codes();
        let a = MeasurementMatrix::synthesize(
            &c,
            &spec(&c, Sampling::Oversample(2), Irf::Physical { laser_fwhm_s: 2.55e-9, tap_tau_s: 0.3e-9 }),
        )
        .unwrap();
        let g = a.gram();
        let (l, q) = a.gram_eigen();
        let (n, m, _) = g.dim();
        for k in 0..n {
            for i in 0..m {
                for j in 0..m {
                    let direct: f64 = (0..a.bins()).map(|t| a.a()[(k, i, t)] as f64 * a.a()[(k, j, t)] as f64).sum();
                    let back: f64 = (0..m).map(|e| q[(k, i, e)] * l[(k, e)] * q[(k, j, e)]).sum();
                    assert!((g[(k, i, j)] - direct).abs() < 1e-9 && (back - direct).abs() < 1e-9 * (1.0 + direct.abs()));
                }
            }
        }
        let lmax = l.iter().fold(0f64, |a, &b| a.max(b));
        assert_eq!(a.max_gram_eigenvalue(), lmax);
        assert!(lmax > 0.0);
    }
}
