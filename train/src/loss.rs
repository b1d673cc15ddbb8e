//! Training losses (paper Table 3): RMSE for FLIm cubes, RMSE + MAE for LiDAR cubes.

use burn::tensor::Tensor;

use crate::config::Loss;

/// The loss of a batch.
///
/// # Shapes
/// - `pred`, `truth`: `[B, T, H, W]` → `[1]`
pub fn loss_fn(loss: Loss, pred: Tensor<4>, truth: Tensor<4>) -> Tensor<1> {
    let d = pred - truth;
    let rmse = d.clone().powi_scalar(2).mean().sqrt();
    match loss {
        Loss::Rmse => rmse,
        Loss::RmseMae => rmse + d.abs().mean(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;

    #[test]
    fn rmse_and_mae_values() {
        let device = Device::flex();
        let pred = Tensor::<4>::from_floats([[[[1.0, 2.0], [3.0, 4.0]]]], &device);
        let truth = Tensor::<4>::from_floats([[[[1.0, 0.0], [3.0, 0.0]]]], &device);
        // differences 0, 2, 0, 4: RMSE = sqrt(20/4), MAE = 6/4
        let rmse: f32 = loss_fn(Loss::Rmse, pred.clone(), truth.clone()).into_scalar();
        let both: f32 = loss_fn(Loss::RmseMae, pred, truth).into_scalar();
        assert!((rmse - 5f32.sqrt()).abs() < 1e-6, "{rmse}");
        assert!((both - (5f32.sqrt() + 1.5)).abs() < 1e-6, "{both}");
    }
}
