//! Forward `y = A x` and adjoint `x = Aᵀ y` of the sensor on whole frames.
//!
//! The operator is block-diagonal: pixel `(X, Y)` of subpixel type `n = (X mod bh)·bw + (Y mod bw)`
//! sees `y[m, X, Y] = Σ_j A[n][m][j] · x[j, X, Y]`. A [`FramePlan`] expands `A` once per frame
//! size into per-row coefficient tables `[bh, T, M, W]`, so both directions are contiguous
//! multiply-adds over image rows, parallel over rows (rayon) and free of allocation inside
//! the loops.
//!
//! ```
//! use tcsense_sensor::{codes::*, generate::random_codes, matrix::MeasurementMatrix, params::SensorParams};
//! let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 8, drain: false };
//! let g = random_codes(shape, 607e6, Constraints { tap: true, ..Default::default() }, 1).unwrap();
//! let spec = SensorParams::from_codes(&g).validate().unwrap();
//! let a = MeasurementMatrix::synthesize(&g, &spec).unwrap();
//! let plan = a.plan(4, 4).unwrap();
//! let x = ndarray::Array3::<f32>::ones((8, 4, 4));
//! let y = plan.forward(&x.view()).unwrap();
//! // exactly one tap on per mask: the taps share all the light
//! assert_eq!(y.sum(), 8.0 * 16.0);
//! ```

use crate::error::{Result, SensorError};
use crate::matrix::MeasurementMatrix;
use ndarray::parallel::prelude::*;
use ndarray::{Array3, Array4, ArrayView3, ArrayView4, ArrayViewMut3, Axis};

/// Forward/adjoint for frames of a fixed size `H × W`.
#[derive(Debug, Clone)]
pub struct FramePlan {
    h: usize,
    w: usize,
    m: usize,
    t: usize,
    bh: usize,
    /// Coefficients `[bh, T, M, W]`: `A[n(r, col)][m][t]` for a row of type `r mod bh`.
    coef: Vec<f32>,
}

impl MeasurementMatrix {
    /// Prepare forward/adjoint for `H × W` frames; both must be multiples of the block.
    pub fn plan(&self, h: usize, w: usize) -> Result<FramePlan> {
        let (bh, bw) = self.block();
        if h == 0 || w == 0 || h % bh != 0 || w % bw != 0 {
            return Err(SensorError::Shape {
                what: "frame".into(),
                got: vec![h, w],
                expected: format!("a non-empty H×W with H a multiple of {bh} and W a multiple of {bw} (the pixel block)"),
            });
        }
        let (m, t) = (self.taps(), self.bins());
        let a = self.a();
        let mut coef = vec![0f32; bh * t * m * w];
        for rb in 0..bh {
            for j in 0..t {
                for mm in 0..m {
                    let base = ((rb * t + j) * m + mm) * w;
                    for col in 0..w {
                        coef[base + col] = a[(rb * bw + col % bw, mm, j)];
                    }
                }
            }
        }
        Ok(FramePlan { h, w, m, t, bh, coef })
    }
}

impl FramePlan {
    /// Frame height `H`.
    pub fn height(&self) -> usize {
        self.h
    }
    /// Frame width `W`.
    pub fn width(&self) -> usize {
        self.w
    }
    /// Taps `M`.
    pub fn taps(&self) -> usize {
        self.m
    }
    /// Bins `T`.
    pub fn bins(&self) -> usize {
        self.t
    }

    /// The `W` coefficients `A[n(r, col)][m][j]` of frame row `r`, tap `m`, bin `j`, one per
    /// column: what a solver working on its own layout needs to apply `A` row by row.
    pub fn row_coefficients(&self, r: usize, j: usize, m: usize) -> &[f32] {
        &self.coef[(((r % self.bh) * self.t + j) * self.m + m) * self.w..][..self.w]
    }

    fn check(&self, what: &str, got: &[usize], lead: usize) -> Result<()> {
        if got != [lead, self.h, self.w] {
            let name = if lead == self.t { "[T, H, W]" } else { "[M, H, W]" };
            return Err(SensorError::Shape {
                what: what.into(),
                got: got.to_vec(),
                expected: format!("{name} = [{lead}, {}, {}]", self.h, self.w),
            });
        }
        Ok(())
    }

    /// `y = A x`.
    ///
    /// # Shapes
    /// - `x`: `[T, H, W]` → `y`: `[M, H, W]`
    pub fn forward(&self, x: &ArrayView3<'_, f32>) -> Result<Array3<f32>> {
        let mut y = Array3::zeros((self.m, self.h, self.w));
        self.forward_into(x, &mut y.view_mut())?;
        Ok(y)
    }

    /// `y = A x` into a preallocated `y`.
    ///
    /// # Shapes
    /// - `x`: `[T, H, W]`, `y`: `[M, H, W]`
    pub fn forward_into(&self, x: &ArrayView3<'_, f32>, y: &mut ArrayViewMut3<'_, f32>) -> Result<()> {
        self.check("cube x", x.shape(), self.t)?;
        self.check("measurements y", y.shape(), self.m)?;
        let owned;
        let xs = match x.as_slice() {
            Some(s) => s,
            None => {
                owned = x.as_standard_layout().into_owned();
                owned.as_slice().unwrap_or(&[])
            }
        };
        let (h, w, m, t, bh) = (self.h, self.w, self.m, self.t, self.bh);
        y.axis_iter_mut(Axis(1)).into_par_iter().enumerate().for_each_init(
            || vec![0f32; m * w],
            |acc, (r, mut yrow)| {
                // yrow: [M, W]
                acc.fill(0.0);
                let rb = r % bh;
                for j in 0..t {
                    let xr = &xs[(j * h + r) * w..][..w];
                    for mm in 0..m {
                        let cf = &self.coef[((rb * t + j) * m + mm) * w..][..w];
                        let out = &mut acc[mm * w..(mm + 1) * w];
                        for ((o, &c), &v) in out.iter_mut().zip(cf).zip(xr) {
                            *o += c * v;
                        }
                    }
                }
                for (mm, mut row) in yrow.axis_iter_mut(Axis(0)).enumerate() {
                    for (d, &s) in row.iter_mut().zip(&acc[mm * w..(mm + 1) * w]) {
                        *d = s;
                    }
                }
            },
        );
        Ok(())
    }

    /// `x = Aᵀ y`.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]` → `x`: `[T, H, W]`
    pub fn adjoint(&self, y: &ArrayView3<'_, f32>) -> Result<Array3<f32>> {
        let mut x = Array3::zeros((self.t, self.h, self.w));
        self.adjoint_into(y, &mut x.view_mut())?;
        Ok(x)
    }

    /// `x = Aᵀ y` into a preallocated `x`.
    ///
    /// # Shapes
    /// - `y`: `[M, H, W]`, `x`: `[T, H, W]`
    pub fn adjoint_into(&self, y: &ArrayView3<'_, f32>, x: &mut ArrayViewMut3<'_, f32>) -> Result<()> {
        self.check("measurements y", y.shape(), self.m)?;
        self.check("cube x", x.shape(), self.t)?;
        let owned;
        let ys = match y.as_slice() {
            Some(s) => s,
            None => {
                owned = y.as_standard_layout().into_owned();
                owned.as_slice().unwrap_or(&[])
            }
        };
        let (h, w, m, t, bh) = (self.h, self.w, self.m, self.t, self.bh);
        x.axis_iter_mut(Axis(1)).into_par_iter().enumerate().for_each_init(
            || vec![0f32; w],
            |acc, (r, mut xrow)| {
                // xrow: [T, W]
                let rb = r % bh;
                for (j, mut out_row) in xrow.axis_iter_mut(Axis(0)).enumerate() {
                    // Accumulate straight into the output row when it is contiguous.
                    let contiguous = out_row.as_slice_mut().is_some();
                    let dst: &mut [f32] = match out_row.as_slice_mut() {
                        Some(d) => d,
                        None => &mut acc[..],
                    };
                    dst.fill(0.0);
                    for mm in 0..m {
                        let cf = &self.coef[((rb * t + j) * m + mm) * w..][..w];
                        let yr = &ys[(mm * h + r) * w..][..w];
                        for ((o, &c), &v) in dst.iter_mut().zip(cf).zip(yr) {
                            *o += c * v;
                        }
                    }
                    if !contiguous {
                        for (d, &s) in out_row.iter_mut().zip(acc.iter()) {
                            *d = s;
                        }
                    }
                }
            },
        );
        Ok(())
    }

    /// `AᵀA x`.
    ///
    /// # Shapes
    /// - `x`: `[T, H, W]` → `[T, H, W]`
    pub fn normal(&self, x: &ArrayView3<'_, f32>) -> Result<Array3<f32>> {
        let y = self.forward(x)?;
        self.adjoint(&y.view())
    }

    /// Forward on a batch.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, M, H, W]`
    pub fn forward_batch(&self, x: &ArrayView4<'_, f32>) -> Result<Array4<f32>> {
        let b = x.dim().0;
        let mut y = Array4::zeros((b, self.m, self.h, self.w));
        for (xb, mut yb) in x.axis_iter(Axis(0)).zip(y.axis_iter_mut(Axis(0))) {
            self.forward_into(&xb, &mut yb)?;
        }
        Ok(y)
    }

    /// Adjoint on a batch.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn adjoint_batch(&self, y: &ArrayView4<'_, f32>) -> Result<Array4<f32>> {
        let b = y.dim().0;
        let mut x = Array4::zeros((b, self.t, self.h, self.w));
        for (yb, mut xb) in y.axis_iter(Axis(0)).zip(x.axis_iter_mut(Axis(0))) {
            self.adjoint_into(&yb, &mut xb)?;
        }
        Ok(x)
    }
}
