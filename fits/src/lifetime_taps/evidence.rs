//! The fit's evidence as a network's input: what a learned lifetime decoder reads instead of
//! the raw taps (`tcsense_models::lifetime`, `LifetimeInput::Costs`).
//!
//! The costs of [`LifetimeTemplates::costs`] are squared residuals times the charge, in the
//! measurements' units. Divided by twice the frame's noise level they become negative
//! log-likelihoods in nats, whatever the gain, the exposure and the read noise: the level is
//! the median over the lit pixels of the window's least cost per degree of freedom (a window
//! of `n` lit pixels of `M` taps holds `n·(M − 1)` numbers about its decay, two of which the
//! lifetime and the background take). Then:
//!
//! ```text
//! skip     [G, H, W] = −(Ĉ_win − min_g Ĉ_win)                 the fit's log-likelihood of every lifetime
//! features [G/pool + 2, H, W] = (G/pool)·Σ_pool softmax_g(−Ĉ_pixel),  ln(I / median I), lit
//! ```
//!
//! The network adds a learned log-prior to `skip` (so with a zero prior its most probable
//! lifetime is the fit's), read from the per-pixel posteriors of a neighbourhood, which is
//! what lets it pool pixels of like lifetime beyond the fit's fixed window.

use ndarray::{Array2, Array3};

use super::LifetimeCosts;

/// Bounds of the log-intensity channel.
const LOG_INTENSITY_CLAMP: f32 = 10.0;

/// The network's input for one frame (see the module's notes).
#[derive(Debug, Clone)]
pub struct Evidence {
    /// The fit's log-likelihood of every lifetime of the grid, window summed, `[G, H, W]`
    /// (0 at the best; 0 everywhere at an unlit pixel).
    pub skip: Array3<f32>,
    /// Per-pixel posteriors pooled over `pool` points of the grid, log relative intensity and
    /// the lit mask, `[G/pool + 2, H, W]`.
    pub features: Array3<f32>,
    /// The frame's noise level: twice it turns a cost into nats.
    pub noise: f32,
}

/// Channels of [`Evidence::features`] for a grid of `points` pooled by `pool`.
pub fn feature_channels(points: usize, pool: usize) -> usize {
    points.div_ceil(pool) + 2
}

/// The evidence of one frame from its costs, its intensity map and the taps per pixel `M`.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]` → [`Evidence`]
pub fn evidence(costs: &LifetimeCosts, intensity: &Array2<f32>, taps: usize, pool: usize) -> Evidence {
    let (g, h, w) = (costs.points, costs.height, costs.width);
    let pool = pool.max(1);
    let window = costs.window_sums();
    let half = costs.window / 2;
    // the noise level: median least window cost per degree of freedom
    let mut per_dof: Vec<f32> = Vec::new();
    for i in 0..h {
        for j in 0..w {
            let p = i * w + j;
            if !costs.lit[p] {
                continue;
            }
            let mut n = 0usize;
            for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
                for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                    n += costs.lit[ii * w + jj] as usize;
                }
            }
            let dof = (n * taps.saturating_sub(1)).saturating_sub(2).max(1) as f32;
            let least = window[p * g..(p + 1) * g].iter().fold(f32::INFINITY, |a, &b| a.min(b));
            if least.is_finite() {
                per_dof.push(least.max(0.0) / dof);
            }
        }
    }
    let noise = median(&mut per_dof).filter(|v| *v > 0.0 && v.is_finite()).unwrap_or(1.0);
    let nats = 1.0 / (2.0 * noise);
    let mut skip = Array3::<f32>::zeros((g, h, w));
    let channels = feature_channels(g, pool);
    let pooled = channels - 2;
    let mut features = Array3::<f32>::zeros((channels, h, w));
    let mut lit_intensity: Vec<f32> = (0..h * w).filter(|&p| costs.lit[p]).map(|p| intensity[(p / w, p % w)]).collect();
    let reference = median(&mut lit_intensity).filter(|v| *v > 0.0).unwrap_or(1.0);
    let mut post = vec![0f32; g];
    for p in 0..h * w {
        let (i, j) = (p / w, p % w);
        let s = intensity[(i, j)];
        features[(channels - 2, i, j)] =
            if s > 0.0 { (s / reference).ln().clamp(-LOG_INTENSITY_CLAMP, LOG_INTENSITY_CLAMP) } else { -LOG_INTENSITY_CLAMP };
        if !costs.lit[p] {
            continue;
        }
        features[(channels - 1, i, j)] = 1.0;
        let win = &window[p * g..(p + 1) * g];
        let least = win.iter().fold(f32::INFINITY, |a, &b| a.min(b));
        for k in 0..g {
            skip[(k, i, j)] = -(win[k] - least) * nats;
        }
        let own = &costs.pixel[p * g..(p + 1) * g];
        let least = own.iter().fold(f32::INFINITY, |a, &b| a.min(b));
        let mut total = 0f32;
        for k in 0..g {
            post[k] = (-(own[k] - least) * nats).exp();
            total += post[k];
        }
        for k in 0..g {
            features[(k / pool, i, j)] += post[k] / total * pooled as f32;
        }
    }
    Evidence { skip, features, noise }
}

/// The median of `v` (reordered), `None` when empty.
fn median(v: &mut [f32]) -> Option<f32> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    Some(*m)
}
