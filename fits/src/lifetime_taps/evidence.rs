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
//! skip     [H, W, G] = −(Ĉ_win − min_g Ĉ_win)                 the fit's log-likelihood of every lifetime
//! features [H, W, G/pool + 2] = (G/pool)·Σ_pool softmax_g(−Ĉ_pixel),  ln(I / median I), lit
//! ```
//!
//! The network adds a learned log-prior to `skip` (so with a zero prior its most probable
//! lifetime is the fit's), read from the per-pixel posteriors of a neighbourhood, which is
//! what lets it pool pixels of like lifetime beyond the fit's fixed window.

use ndarray::{Array2, Array3};
use rayon::prelude::*;

use super::LifetimeCosts;

/// Bounds of the log-intensity channel.
const LOG_INTENSITY_CLAMP: f32 = 10.0;

/// The network's input for one frame (see the module's notes), pixel-major.
#[derive(Debug, Clone)]
pub struct Evidence {
    /// The fit's log-likelihood of every lifetime of the grid, window summed, `[H, W, G]`
    /// (0 at the best; 0 everywhere at an unlit pixel).
    pub skip: Array3<f32>,
    /// Per-pixel posteriors pooled over `pool` points of the grid, log relative intensity and
    /// the lit mask, `[H, W, G/pool + 2]`.
    pub features: Array3<f32>,
    /// The frame's noise level: twice it turns a cost into nats.
    pub noise: f32,
}

/// Channels of [`Evidence::features`] for a grid of `points` pooled by `pool`.
pub fn feature_channels(points: usize, pool: usize) -> usize {
    points.div_ceil(pool.max(1)) + 2
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
    let lit = &costs.lit;
    // the noise level: median least window cost per degree of freedom
    let mut per_dof: Vec<f32> = (0..h)
        .into_par_iter()
        .flat_map_iter(|i| {
            let window = &window;
            (0..w).filter_map(move |j| {
                let p = i * w + j;
                if !lit[p] {
                    return None;
                }
                let mut n = 0usize;
                for ii in i.saturating_sub(half)..(i + half + 1).min(h) {
                    for jj in j.saturating_sub(half)..(j + half + 1).min(w) {
                        n += lit[ii * w + jj] as usize;
                    }
                }
                let dof = (n * taps.saturating_sub(1)).saturating_sub(2).max(1) as f32;
                let least = window[p * g..(p + 1) * g].iter().fold(f32::INFINITY, |a, &b| a.min(b));
                least.is_finite().then(|| least.max(0.0) / dof)
            })
        })
        .collect();
    let noise = median(&mut per_dof).filter(|v| *v > 0.0 && v.is_finite()).unwrap_or(1.0);
    let nats = 1.0 / (2.0 * noise);
    let channels = feature_channels(g, pool);
    let pooled = channels - 2;
    let mut lit_intensity: Vec<f32> = (0..h * w).filter(|&p| lit[p]).map(|p| intensity[(p / w, p % w)]).collect();
    let reference = median(&mut lit_intensity).filter(|v| *v > 0.0).unwrap_or(1.0);
    let mut skip = vec![0f32; h * w * g];
    let mut features = vec![0f32; h * w * channels];
    skip.par_chunks_mut(w * g).zip(features.par_chunks_mut(w * channels)).enumerate().for_each(|(i, (srow, frow))| {
        let mut post = vec![0f32; g];
        for j in 0..w {
            let p = i * w + j;
            let (sp, fp) = (&mut srow[j * g..(j + 1) * g], &mut frow[j * channels..(j + 1) * channels]);
            let s = intensity[(i, j)];
            fp[channels - 2] =
                if s > 0.0 { (s / reference).ln().clamp(-LOG_INTENSITY_CLAMP, LOG_INTENSITY_CLAMP) } else { -LOG_INTENSITY_CLAMP };
            if !lit[p] {
                continue;
            }
            fp[channels - 1] = 1.0;
            let win = &window[p * g..(p + 1) * g];
            let least = win.iter().fold(f32::INFINITY, |a, &b| a.min(b));
            for (o, &c) in sp.iter_mut().zip(win) {
                *o = -(c - least) * nats;
            }
            let own = &costs.pixel[p * g..(p + 1) * g];
            let least = own.iter().fold(f32::INFINITY, |a, &b| a.min(b));
            let mut total = 0f32;
            for (q, &c) in post.iter_mut().zip(own) {
                *q = (-(c - least) * nats).exp();
                total += *q;
            }
            let scale = pooled as f32 / total;
            for (k, &q) in post.iter().enumerate() {
                fp[k / pool] += q * scale;
            }
        }
    });
    let shape = |c: usize, v: Vec<f32>| Array3::from_shape_vec((h, w, c), v).expect("[H, W, C] buffer");
    Evidence { skip: shape(g, skip), features: shape(channels, features), noise }
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
