//! The lifetime fit's evidence as a network's input (`tcsense_models::lifetime`,
//! `LifetimeInput::Costs`): [`crate::evidence`] on the costs of [`LifetimeTemplates::costs`],
//! which are squared residuals times the charge. A window of `n` lit pixels of `M` taps holds
//! `n·(M − 1)` numbers about its decay (each pixel's amplitude is its own), two of which the
//! lifetime and the background take.

use ndarray::Array2;

pub use crate::evidence::{feature_channels, Evidence};

use super::LifetimeCosts;
use crate::evidence::CostVolume;

/// The evidence of one frame from its costs, its intensity map and the taps per pixel `M`.
///
/// # Shapes
/// - `costs`: of `[H·W·G]`, `intensity`: `[H, W]` → [`Evidence`]
pub fn evidence(costs: &LifetimeCosts, intensity: &Array2<f32>, taps: usize, pool: usize) -> Evidence {
    let window = costs.window_sums();
    let volume = CostVolume {
        pixel: &costs.pixel,
        window: &window,
        lit: &costs.lit,
        points: costs.points,
        height: costs.height,
        width: costs.width,
        side: costs.window,
        free_per_pixel: taps.saturating_sub(1),
        shared: 2,
    };
    crate::evidence::evidence(&volume, intensity, pool)
}
