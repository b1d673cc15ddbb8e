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
