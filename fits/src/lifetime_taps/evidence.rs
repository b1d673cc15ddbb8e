//! The lifetime fit's evidence as a network's input (`tcsense_models::lifetime`,
//! `LifetimeInput::Costs`): [`crate::evidence`] on the costs of [`LifetimeTemplates::costs`],
//! which are squared residuals times the charge. A window of `n` lit pixels of `M` taps holds
//! `n·(M − 1)` numbers about its decay (each pixel's amplitude is its own), two of which the
//! lifetime and the background take. Templates pooled by likeness (`TapFitOptions::pool_like`)
//! give the window's log-likelihood pooled with the neighbours of like lifetime
//! ([`crate::evidence::similarity_pool`]) in its place, in the window's nats.

use ndarray::Array2;

pub use crate::evidence::{feature_channels, feature_channels_with, Evidence, EvidenceBuffers};

use super::LifetimeCosts;

/// The evidence of one frame from its costs, its intensity map and the taps per pixel `M`.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]` → [`Evidence`]
pub fn evidence(costs: &LifetimeCosts, intensity: &Array2<f32>, taps: usize, pool: usize) -> Evidence {
    evidence_with_windows(costs, intensity, taps, pool, &[])
}

/// [`evidence`] with the costs summed over the `wider` windows' sides besides the fit's own
/// window (multi-scale context: in dim light a cell's pixels of one lifetime agree over a wider
/// window than the fit's): their log-likelihoods after the fit's window's in `skip`, their
/// posteriors after the pixel's in the features ([`crate::evidence::evidence_with`]).
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]` → [`Evidence`] with skip
///   `[H, W, (1 + S)·G]`, features [`feature_channels_with`]`(G, pool, S)`
pub fn evidence_with_windows(costs: &LifetimeCosts, intensity: &Array2<f32>, taps: usize, pool: usize, wider: &[usize]) -> Evidence {
    evidence_into(costs, intensity, taps, pool, wider, EvidenceBuffers::default())
}

/// [`evidence_with_windows`] written into an earlier frame's `buffers`
/// ([`crate::evidence::evidence_into`]): the same numbers.
///
/// # Shapes
/// - as [`evidence_with_windows`]
pub fn evidence_into(
    costs: &LifetimeCosts,
    intensity: &Array2<f32>,
    taps: usize,
    pool: usize,
    wider: &[usize],
    buffers: EvidenceBuffers,
) -> Evidence {
    let (h, w, g) = (costs.height, costs.width, costs.points);
    let window = costs.window_sums();
    let mut rows = Vec::new();
    let sums: Vec<Vec<f32>> = wider
        .iter()
        .map(|&side| {
            let mut out = Vec::new();
            crate::engine::window_sums(&costs.pixel, &costs.lit, (h, w), g, side, &mut rows, &mut out);
            out
        })
        .collect();
    let sums: Vec<&[f32]> = sums.iter().map(|v| v.as_slice()).collect();
    if costs.pool_like > costs.window {
        // the window's log-likelihood pooled by likeness, in the window's nats
        let (pooled, noise) = costs.pooled_by_likeness(&window, taps);
        return crate::evidence::evidence_at_noise(&costs.volume(&pooled, taps), noise, intensity, pool, &sums, buffers);
    }
    let noise = costs.noise_level(&window, taps);
    crate::evidence::evidence_at_noise(&costs.volume(&window, taps), noise, intensity, pool, &sums, buffers)
}
