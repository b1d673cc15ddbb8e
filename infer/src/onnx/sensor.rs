//! The sensor's block-periodic per-pixel operators as plain ONNX convolutions.
//!
//! Pixel `(r, c)` has subpixel type `n = (r mod bh)·bw + (c mod bw)` and its own small matrix
//! `W_n [C_out, C_in]` (`A_n`, `A_nᵀ`, the back-projection, the data-consistency solve). In
//! *block layout* `[B, N·C, H/bh, W/bw]` (channel `n·C + c`) such an operator is two plain
//! convolutions: a `Conv` with a `bh × bw` kernel and stride (output channel `n·C_out + c`
//! sees only kernel tap `(n / bw, n mod bw)`) goes from frames to blocks, and a
//! `ConvTranspose` with the same kernel and stride (input channel `n·C_in + k` writes only
//! subpixel `n`) goes back to frames, with the matrices in either. ADMM's x-update
//! `(AᵀA + ρI)⁻¹(Aᵀy + ρd) = d + Aᵀ(ρI + AAᵀ)⁻¹(y − Ad)` is then a `Conv` with `A_n` to
//! `N·M` block channels and a `ConvTranspose` with `A_nᵀ(ρI + A_nA_nᵀ)⁻¹` back: two
//! convolutions through `M` channels instead of a `T × T` product per pixel. (`DepthToSpace`
//! would express the same; ONNX Runtime's runs several times slower than the transposed
//! convolution, and only for square blocks.)
//!
//! The matrices come either from the exported run (baked in as initializers, computed in f64)
//! or from a graph input `sensor_matrix [N, M, T]`, from which the graph itself forms `Aᵀ`,
//! the Gram matrices `A_nA_nᵀ`, their largest eigenvalue (power iteration) and the inverses
//! `(cI + A_nA_nᵀ)⁻¹` (Newton–Schulz, from `X₀ = I/tr`), so a recalibrated sensor needs no
//! new export.

use super::graph::{Attr, Graph};
use tcsense_sensor::MeasurementMatrix;

/// Newton–Schulz iterations for `(cI + AAᵀ)⁻¹`: from `X₀ = I/tr`, the residual's largest
/// eigenvalue starts at `1 − λ_min/tr` and squares every step, so 30 steps reach f32
/// precision for condition numbers up to about 10⁷.
const NEWTON_SCHULZ_STEPS: usize = 30;
/// Power-iteration steps for the largest eigenvalue of each `A_nA_nᵀ` (Rayleigh quotient).
const POWER_STEPS: usize = 30;
/// The back-projection's regularisation `ε = EPS_REL·λ_max` (as [`tcsense_models::SensorTensors`]).
pub const EPS_REL: f64 = 1e-3;

/// Where the per-subpixel matrices come from.
enum Source {
    /// Computed at export, in f64: `A [N, M, T]`, `(ε, (A_nA_nᵀ) [N, M, M])` and the
    /// matched filters `F [N, T, M]`.
    Baked { a: Vec<f64>, gram: Vec<f64>, eps: f64, matched: Vec<f64> },
    /// Computed in the graph from the input `[N, M, T]`: names of `A`, `Aᵀ [N, T, M]`, the
    /// Gram matrices `[1, N, M, M]` and `ε` (shape `[1]`).
    Input { a: String, at: String, gram: String, eps: String },
}

/// The sensor operators of one code set, as graph nodes.
pub struct SensorGraph {
    n: usize,
    m: usize,
    t: usize,
    block: (usize, usize),
    src: Source,
}

/// A per-subpixel matrix stack `[N, C_out, C_in]`: constant or a graph value.
pub enum Mats {
    Const(Vec<f64>),
    Value(String),
}

impl SensorGraph {
    /// Operators with `A` baked in.
    pub fn baked(a: &MeasurementMatrix) -> Self {
        let (n, m, t) = a.a().dim();
        let av: Vec<f64> = a.a().iter().map(|&v| v as f64).collect();
        let (lambda, _) = a.gram_eigen();
        let lmax = lambda.iter().fold(0f64, |acc, &l| acc.max(l.max(0.0) as f32 as f64)).max(1e-12);
        let gram = a.gram().iter().copied().collect();
        let matched = a.matched_filters().iter().copied().collect();
        SensorGraph { n, m, t, block: a.block(), src: Source::Baked { a: av, gram, eps: EPS_REL * lmax, matched } }
    }

    /// Operators computed in the graph from the input `input [N, M, T]` (its name).
    pub fn from_input(g: &mut Graph, input: &str, n: usize, m: usize, t: usize, block: (usize, usize)) -> Self {
        let at = g.node("Transpose", &[input], &[Attr::Ints("perm", &[0, 2, 1])]); // [N, T, M]
        let gram = g.op("MatMul", &[input, &at]); // [N, M, M]
                                                  // λ_max of each A_nA_nᵀ by power iteration from the ones vector (the Gram matrices are
                                                  // non-negative, so their Perron vector is not orthogonal to it)
        let mut v = g.weight("power_v0", &[n, m, 1], &vec![1.0; n * m]);
        let ax1 = g.ints("axis1", &[1]);
        for _ in 0..POWER_STEPS {
            let gv = g.op("MatMul", &[&gram, &v]);
            let norm = g.node("ReduceL2", &[&gv], &[Attr::Ints("axes", &[1]), Attr::Int("keepdims", 1)]);
            v = g.op("Div", &[&gv, &norm]);
        }
        let gv = g.op("MatMul", &[&gram, &v]);
        let vgv = g.op("Mul", &[&v, &gv]);
        let rayleigh = g.node("ReduceSum", &[&vgv, &ax1], &[Attr::Int("keepdims", 0)]); // [N, 1] (v has unit norm)
        let lmax = g.node("ReduceMax", &[&rayleigh], &[Attr::Int("keepdims", 0)]); // []
        let floor = g.scalar("lmax_floor", 1e-12);
        let lmax = g.op("Max", &[&lmax, &floor]);
        let rel = g.scalar("eps_rel", EPS_REL as f32);
        let eps = g.op("Mul", &[&lmax, &rel]);
        let shape1 = g.ints("shape1", &[1]);
        let eps = g.op("Reshape", &[&eps, &shape1]);
        let axis0 = g.ints("axis0", &[0]);
        let gram4 = g.op("Unsqueeze", &[&gram, &axis0]); // [1, N, M, M]
        SensorGraph { n, m, t, block, src: Source::Input { a: input.to_string(), at, gram: gram4, eps } }
    }

    /// Subpixel types `N`.
    pub fn subpixels(&self) -> usize {
        self.n
    }

    /// Measurements in block layout (for [`Self::pinv`] and [`Self::x_update`]).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, N·M, H/bh, W/bw]`
    pub fn measurement_blocks(&self, g: &mut Graph, y: &str) -> String {
        self.to_blocks(g, y, self.m)
    }

    /// The back-projection `Aᵀ(AAᵀ + εI)⁻¹y`: one transposed convolution.
    ///
    /// # Shapes
    /// - `yb`: `[B, N·M, H/bh, W/bw]` (from [`Self::measurement_blocks`]) → `[B, T, H, W]`
    pub fn pinv(&self, g: &mut Graph, yb: &str) -> String {
        let (n, m, t) = (self.n, self.m, self.t);
        let mats = match &self.src {
            Source::Baked { a, gram, eps, .. } => {
                let mut w = vec![0f64; n * t * m];
                for k in 0..n {
                    let inv = spd_inverse(&gram[k * m * m..(k + 1) * m * m], m, *eps);
                    for j in 0..t {
                        for c in 0..m {
                            w[(k * t + j) * m + c] = (0..m).map(|r| a[(k * m + r) * t + j] * inv[r * m + c]).sum();
                        }
                    }
                }
                Mats::Const(w)
            }
            Source::Input { at, eps, .. } => {
                let k = self.inverses(g, eps); // [1, N, M, M]
                let axis0 = g.ints("axis0", &[0]);
                let k = g.op("Squeeze", &[&k, &axis0]); // [N, M, M]
                Mats::Value(g.op("MatMul", &[at, &k])) // [N, T, M]
            }
        };
        let w = self.back_weight(g, "pinv", mats, t, m);
        self.from_blocks(g, yb, &w)
    }

    /// `Aᵀy`.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn adjoint(&self, g: &mut Graph, y: &str) -> String {
        let (n, m, t) = (self.n, self.m, self.t);
        let mats = match &self.src {
            Source::Baked { a, .. } => {
                let mut w = vec![0f64; n * t * m];
                for k in 0..n {
                    for j in 0..t {
                        for c in 0..m {
                            w[(k * t + j) * m + c] = a[(k * m + c) * t + j];
                        }
                    }
                }
                Mats::Const(w)
            }
            Source::Input { at, .. } => Mats::Value(at.clone()),
        };
        let w = self.back_weight(g, "adjoint", mats, t, m);
        let blocks = self.to_blocks(g, y, m);
        self.from_blocks(g, &blocks, &w)
    }

    /// The matched filters `F y` ([`tcsense_sensor::MeasurementMatrix::matched_filters`]): from
    /// an input matrix the graph forms them itself (`s = A1`, `P = I − ssᵀ/‖s‖²`, the columns
    /// `Pa` times `‖Pa‖/(‖Pa‖² + ε²‖a‖²)`).
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]` → `[B, T, H, W]`
    pub fn matched(&self, g: &mut Graph, y: &str) -> String {
        let (m, t) = (self.m, self.t);
        let mats = match &self.src {
            Source::Baked { matched, .. } => Mats::Const(matched.clone()),
            Source::Input { a, .. } => {
                let ax2 = g.ints("axis2", &[2]);
                let ax1 = g.ints("axis1", &[1]);
                let s = g.node("ReduceSum", &[a, &ax2], &[Attr::Int("keepdims", 1)]); // [N, M, 1]
                let st = g.node("Transpose", &[&s], &[Attr::Ints("perm", &[0, 2, 1])]); // [N, 1, M]
                let ss = g.op("MatMul", &[&st, &s]); // [N, 1, 1]
                let tiny = g.scalar("tiny_ss", 1e-30);
                let ss = g.op("Max", &[&ss, &tiny]);
                let sa = g.op("MatMul", &[&st, a]); // [N, 1, T]
                let along = g.op("Div", &[&sa, &ss]);
                let proj = g.op("Mul", &[&s, &along]); // [N, M, T]
                let p = g.op("Sub", &[a, &proj]);
                let p2 = g.op("Mul", &[&p, &p]);
                let pp = g.node("ReduceSum", &[&p2, &ax1], &[Attr::Int("keepdims", 1)]); // [N, 1, T]
                let a2 = g.op("Mul", &[a, a]);
                let aa = g.node("ReduceSum", &[&a2, &ax1], &[Attr::Int("keepdims", 1)]);
                let eps2 = g.scalar("matched_eps2", (tcsense_sensor::matrix::MATCHED_EPS * tcsense_sensor::matrix::MATCHED_EPS) as f32);
                let aa = g.op("Mul", &[&aa, &eps2]);
                let den = g.op("Add", &[&pp, &aa]);
                let den = g.op("Max", &[&den, &tiny]);
                let pp = g.op("Add", &[&pp, &tiny]);
                let num = g.op("Sqrt", &[&pp]);
                let scale = g.op("Div", &[&num, &den]);
                let f = g.op("Mul", &[&p, &scale]); // [N, M, T]
                Mats::Value(g.node("Transpose", &[&f], &[Attr::Ints("perm", &[0, 2, 1])]))
                // [N, T, M]
            }
        };
        let w = self.back_weight(g, "matched", mats, t, m);
        let blocks = self.to_blocks(g, y, m);
        self.from_blocks(g, &blocks, &w)
    }

    /// `D Aᵀy`: the adjoint followed by a fixed linear map `D [F, T]` of the time axis, folded
    /// into one `F × M` matrix per subpixel (`D A_nᵀ`), so the `T`-channel cube is never formed.
    ///
    /// # Shapes
    /// - `y`: `[B, M, H, W]`, `d`: `[F, T]` row-major → `[B, F, H, W]`
    pub fn adjoint_then(&self, g: &mut Graph, y: &str, d: &[f32], f: usize) -> String {
        let (n, m, t) = (self.n, self.m, self.t);
        let mats = match &self.src {
            Source::Baked { a, .. } => {
                let mut w = vec![0f64; n * f * m];
                for k in 0..n {
                    for r in 0..f {
                        for c in 0..m {
                            w[(k * f + r) * m + c] = (0..t).map(|j| d[r * t + j] as f64 * a[(k * m + c) * t + j]).sum();
                        }
                    }
                }
                Mats::Const(w)
            }
            Source::Input { at, .. } => {
                let dn = g.weight("time_map", &[f, t], d);
                Mats::Value(g.op("MatMul", &[&dn, at])) // [N, F, M]
            }
        };
        let w = self.back_weight(g, "adjoint_then", mats, f, m);
        let blocks = self.to_blocks(g, y, m);
        self.from_blocks(g, &blocks, &w)
    }

    /// Weights of the stages' x-updates: the frame-to-block `A` convolution (shared) and, per
    /// `ρ`, the block-to-frame transposed convolution with `A_nᵀ(ρI + A_nA_nᵀ)⁻¹` (see
    /// [`Self::x_update`]).
    pub fn dc_weights(&self, g: &mut Graph, rhos: &[f64]) -> DcWeights {
        let (n, m, t) = (self.n, self.m, self.t);
        let (a_mats, stages): (Mats, Vec<Mats>) = match &self.src {
            Source::Baked { a, gram, .. } => {
                let stages = rhos
                    .iter()
                    .map(|&rho| {
                        let mut back = vec![0f64; n * t * m];
                        for k in 0..n {
                            let inv = spd_inverse(&gram[k * m * m..(k + 1) * m * m], m, rho);
                            for j in 0..t {
                                for c in 0..m {
                                    back[(k * t + j) * m + c] = (0..m).map(|r| a[(k * m + r) * t + j] * inv[r * m + c]).sum::<f64>();
                                }
                            }
                        }
                        Mats::Const(back)
                    })
                    .collect();
                (Mats::Const(a.clone()), stages)
            }
            Source::Input { a, at, .. } => {
                let c: Vec<f32> = rhos.iter().map(|&r| r as f32).collect();
                let cs = g.weight("rhos", &[rhos.len()], &c);
                let k = self.inverses(g, &cs); // [S, N, M, M]
                let axis0 = g.ints("axis0", &[0]);
                let at4 = g.op("Unsqueeze", &[at, &axis0]); // [1, N, T, M]
                let w = g.op("MatMul", &[&at4, &k]); // [S, N, T, M]
                let stages = (0..rhos.len())
                    .map(|s| {
                        let idx = g.ints("stage", &[s as i64]);
                        let ws = g.node("Gather", &[&w, &idx], &[Attr::Int("axis", 0)]); // [1, N, T, M]
                        Mats::Value(g.op("Squeeze", &[&ws, &axis0]))
                    })
                    .collect();
                (Mats::Value(a.clone()), stages)
            }
        };
        let a = self.frame_weight(g, "dc_a", a_mats, m, t);
        let ct = stages.into_iter().map(|back| self.back_weight(g, "dc_back", back, t, m)).collect();
        DcWeights { a, ct }
    }

    /// `A x` in block layout.
    ///
    /// # Shapes
    /// - `x`: `[B, T, H, W]` → `[B, N·M, H/bh, W/bw]`
    pub fn forward_blocks(&self, g: &mut Graph, x: &str, w: &DcWeights) -> String {
        self.forward_conv(g, x, &w.a)
    }

    /// The frame-to-block convolution (kernel and stride the block) with weight `w` from
    /// [`Self::frame_weight`].
    fn forward_conv(&self, g: &mut Graph, x: &str, w: &str) -> String {
        let (bh, bw) = self.block;
        g.node("Conv", &[x, w], &[Attr::Ints("kernel_shape", &[bh as i64, bw as i64]), Attr::Ints("strides", &[bh as i64, bw as i64])])
    }

    /// ADMM's x-update of stage `s`, `x = (AᵀA + ρI)⁻¹(Aᵀy + ρd)`, as
    /// `x = d + Aᵀ(ρI + AAᵀ)⁻¹(y − Ad)` (the push-through identity; forming the right-hand
    /// side and dividing by `ρ` would cancel terms `λ/ρ` times larger than the result, and
    /// rounding with them: see `tcsense_models::sensor_tensors`). One strided convolution
    /// (`Ad`), a subtraction in block layout, one transposed convolution and one full-frame
    /// addition.
    ///
    /// # Shapes
    /// - `d`: `[B, T, H, W]`, `yb`: `[B, N·M, H/bh, W/bw]` → `[B, T, H, W]`
    pub fn x_update(&self, g: &mut Graph, d: &str, yb: &str, w: &DcWeights, s: usize) -> String {
        let ad = self.forward_blocks(g, d, w);
        let r = g.op("Sub", &[yb, &ad]);
        let back = self.from_blocks(g, &r, &w.ct[s]);
        g.op("Add", &[d, &back])
    }

    /// `(cI + A_nA_nᵀ)⁻¹` for each `c` of `cs` (`[S]`, or `[1]`) and subpixel, by Newton–Schulz:
    /// `[S, N, M, M]`.
    fn inverses(&self, g: &mut Graph, cs: &str) -> String {
        let Source::Input { gram, .. } = &self.src else { unreachable!("inverses are formed in the graph only from an input matrix") };
        let m = self.m;
        let eye = g.weight("eye", &[1, 1, m, m], &eye_scaled(m, 1.0));
        let shape = g.ints("shape", &[-1, 1, 1, 1]);
        let c4 = g.op("Reshape", &[cs, &shape]); // [S, 1, 1, 1]
        let ci = g.op("Mul", &[&c4, &eye]);
        let b = g.op("Add", &[gram, &ci]); // [S, N, M, M]
        let diag = g.op("Mul", &[&b, &eye]);
        let axes = g.ints("axes", &[2, 3]);
        let tr = g.node("ReduceSum", &[&diag, &axes], &[Attr::Int("keepdims", 1)]); // [S, N, 1, 1]
        let mut x = g.op("Div", &[&eye, &tr]);
        let two_i = g.weight("two_eye", &[1, 1, m, m], &eye_scaled(m, 2.0));
        for _ in 0..NEWTON_SCHULZ_STEPS {
            let bx = g.op("MatMul", &[&b, &x]);
            let r = g.op("Sub", &[&two_i, &bx]);
            x = g.op("MatMul", &[&x, &r]);
        }
        x
    }

    /// The frame-to-block convolution's weight `[N·C_out, C_in, bh, bw]` from `[N, C_out, C_in]`.
    fn frame_weight(&self, g: &mut Graph, hint: &str, mats: Mats, cout: usize, cin: usize) -> String {
        let (n, (bh, bw)) = (self.n, self.block);
        match mats {
            Mats::Const(w) => {
                let mut k = vec![0f32; n * cout * cin * bh * bw];
                for s in 0..n {
                    for o in 0..cout {
                        for i in 0..cin {
                            k[((s * cout + o) * cin + i) * n + s] = w[(s * cout + o) * cin + i] as f32;
                        }
                    }
                }
                g.weight(hint, &[n * cout, cin, bh, bw], &k)
            }
            Mats::Value(v) => {
                let mask = g.weight("subpixel_onehot", &[n, 1, 1, n], &eye_scaled(n, 1.0));
                let axis3 = g.ints("axis3", &[3]);
                let v4 = g.op("Unsqueeze", &[&v, &axis3]); // [N, C_out, C_in, 1]
                let k = g.op("Mul", &[&v4, &mask]); // [N, C_out, C_in, N]
                let shape = g.ints("shape", &[(n * cout) as i64, cin as i64, bh as i64, bw as i64]);
                g.op("Reshape", &[&k, &shape])
            }
        }
    }

    /// The block-to-frame transposed convolution's weight `[N·C_in, C_out, bh, bw]` from
    /// `[N, C_out, C_in]`: input channel `n·C_in + k` of a block writes only its subpixel
    /// `(n / bw, n mod bw)`, with weight `W_n[:, k]`. It is the frame-to-block weight of the
    /// transposed matrices `W_nᵀ`.
    fn back_weight(&self, g: &mut Graph, hint: &str, mats: Mats, cout: usize, cin: usize) -> String {
        let n = self.n;
        let transposed = match mats {
            Mats::Const(w) => {
                let mut wt = vec![0f64; w.len()];
                for s in 0..n {
                    for o in 0..cout {
                        for i in 0..cin {
                            wt[(s * cin + i) * cout + o] = w[(s * cout + o) * cin + i];
                        }
                    }
                }
                Mats::Const(wt)
            }
            Mats::Value(v) => Mats::Value(g.node("Transpose", &[&v], &[Attr::Ints("perm", &[0, 2, 1])])),
        };
        self.frame_weight(g, hint, transposed, cin, cout)
    }

    /// Frames to block layout: `[B, C, H, W]` → `[B, N·C, H/bh, W/bw]` (channel `n·C + c`),
    /// the frame-to-block convolution with `W_n = I`.
    fn to_blocks(&self, g: &mut Graph, x: &str, c: usize) -> String {
        let eye: Vec<f64> = (0..self.n).flat_map(|_| eye_scaled(c, 1.0)).map(f64::from).collect();
        let w = self.frame_weight(g, "to_blocks", Mats::Const(eye), c, c);
        self.forward_conv(g, x, &w)
    }

    /// Block layout `[B, N·C_in, H', W']` to frames `[B, C_out, H, W]` through the per-subpixel
    /// matrices (weight from [`Self::back_weight`]): one `ConvTranspose` with stride = kernel =
    /// the block, which ONNX Runtime runs as a GEMM and a scatter.
    fn from_blocks(&self, g: &mut Graph, x: &str, w: &str) -> String {
        let (bh, bw) = self.block;
        g.node(
            "ConvTranspose",
            &[x, w],
            &[Attr::Ints("kernel_shape", &[bh as i64, bw as i64]), Attr::Ints("strides", &[bh as i64, bw as i64])],
        )
    }
}

/// The data-consistency weights of all stages.
pub struct DcWeights {
    a: String,
    ct: Vec<String>,
}

fn eye_scaled(m: usize, s: f32) -> Vec<f32> {
    (0..m * m).map(|i| if i / m == i % m { s } else { 0.0 }).collect()
}

/// `(G + cI)⁻¹` of a symmetric positive (semi-)definite `m × m` matrix `G` (row-major), by
/// Gauss–Jordan elimination with partial pivoting in f64.
pub fn spd_inverse(gram: &[f64], m: usize, c: f64) -> Vec<f64> {
    let mut a: Vec<f64> = (0..m * m).map(|i| gram[i] + if i / m == i % m { c } else { 0.0 }).collect();
    let mut inv: Vec<f64> = eye_scaled(m, 1.0).into_iter().map(f64::from).collect();
    for k in 0..m {
        let p = (k..m).max_by(|&i, &j| a[i * m + k].abs().total_cmp(&a[j * m + k].abs())).unwrap_or(k);
        if p != k {
            for j in 0..m {
                a.swap(k * m + j, p * m + j);
                inv.swap(k * m + j, p * m + j);
            }
        }
        let piv = a[k * m + k];
        for j in 0..m {
            a[k * m + j] /= piv;
            inv[k * m + j] /= piv;
        }
        for i in 0..m {
            if i != k {
                let f = a[i * m + k];
                if f != 0.0 {
                    for j in 0..m {
                        a[i * m + j] -= f * a[k * m + j];
                        inv[i * m + j] -= f * inv[k * m + j];
                    }
                }
            }
        }
    }
    inv
}
