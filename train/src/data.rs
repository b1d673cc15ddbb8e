//! Training data from a dataset directory.

use ndarray::{Array4, Axis, Ix4};
use tcsense_datasets::Dataset;

use crate::{file_err, Result};

/// Load the cubes of a split, `[N, T, H, W]`, at most `max` of them.
pub fn load_cubes(ds: &Dataset, split: &str, max: Option<usize>) -> Result<Array4<f32>> {
    let x = ds.load(split, "x")?;
    let x = x.into_dimensionality::<Ix4>().map_err(|e| file_err(&ds.dir, format!("field x of split {split}: {e}")))?;
    let n = max.unwrap_or(x.dim().0).min(x.dim().0);
    Ok(x.slice_axis(Axis(0), ndarray::Slice::from(0..n)).to_owned())
}

/// Load the range labels of a split's first `k` returns, `[N, K, H, W]` (m, NaN where none),
/// at most `max` items; datasets without a `depth` field (FLIm, imported cubes) cannot train
/// a depth network.
pub fn load_depth(ds: &Dataset, split: &str, max: Option<usize>, k: usize) -> Result<Array4<f32>> {
    if !ds.manifest.fields.contains_key("depth") {
        return Err(file_err(&ds.dir, "no depth field: a depth network trains on LiDAR data (tcsense dataset lidar or dataset import --depth)"));
    }
    let d = ds.load(split, "depth")?.into_dimensionality::<Ix4>().map_err(|e| file_err(&ds.dir, format!("field depth of split {split}: {e}")))?;
    let (n, bounces, _, _) = d.dim();
    if k == 0 || k > bounces {
        return Err(file_err(&ds.dir, format!("the depth field has {bounces} returns per pixel; the network wants {k}")));
    }
    let n = max.unwrap_or(n).min(n);
    Ok(d.slice(ndarray::s![..n, ..k, .., ..]).to_owned())
}
