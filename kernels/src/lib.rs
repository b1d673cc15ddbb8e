//! `tcsense-kernels`: the hand-written CPU kernels under tcsense's learned decoders, each
//! registered as a burn backend extension with a handwritten backward pass.
//!
//! - [`conv`]: 3×3 "same" convolutions on `f32` NCHW buffers as im2col GEMMs — forward, input
//!   gradient and weight gradient — with three column-shifted copies per band of rows.
//! - [`conv_op`]: [`conv_op::conv3x3`], that convolution as a burn op (`Flex` and
//!   `Autodiff<Flex>`), used by ADMM-Net's prior and by any network with 3×3 convs.
//! - [`delay`]: the delay-tap convolution of ADMM-Net's delay-equivariant prior — a 3×3
//!   convolution over the frame of the bins `t − d`, `t`, `t + d` (circular in `t`) — whose
//!   im2col reads the three bins straight from the input; [`delay_op`]'s
//!   [`delay_op::delay_conv3x3`] is it as a burn op.
//! - [`pixel`]: the block-periodic per-pixel sensor operators in frame layout —
//!   `y(r, c) = P_{n(r,c)} x(r, c)` ([`pixel::pixel_linear`]: `A`, `Aᵀ`, the back-projection)
//!   and ADMM-Net's exact data-consistency solve `x = (AᵀA + ρI)⁻¹ v` through Woodbury
//!   ([`pixel::pixel_dc`]) — with `n(r, c) = (r mod bh)·bw + (c mod bw)` (paper eq. 4).
//! - [`resample`]: the U-Net's 2×2 max-pooling and nearest up-sampling by 2, forward and
//!   backward, one pass over the output each.
//! - [`timing`]: the median timer every `tcsense bench` figure comes from.
//!
//! This is the only crate of the workspace with `unsafe` code, in three kinds of places, each
//! with a `SAFETY` note: the calls into `gemm::gemm` (an `unsafe fn`; every view is
//! bounds-checked before it) in [`conv`]; the disjoint parallel writes into output planes
//! through `plane::SharedOut` (used by [`conv`]'s bands, the direct loops' bands and
//! [`pixel`]'s `par_bands`); glibc's `mallopt` in [`keep_freed_memory`]; and `signal` in [`quiet_broken_pipe`]. SIMD dispatch is
//! also only here: `gemm` picks AVX2/AVX-512 at run time, and the per-pixel loops and the
//! direct convolution loops are compiled for the best extension this CPU has through
//! `pulp::Arch::dispatch`.
//!
//! The kernels run on the CPU `flex` device (with or without autodiff). On any other device
//! (burn's wgpu backend, cargo feature `gpu` of the workspace) [`conv_op::conv3x3`],
//! [`delay_op::delay_conv3x3`] (as roll + concatenate + conv),
//! [`resample::max_pool2`] and [`resample::upsample2`] run burn's composed ops instead, and
//! `tcsense_models::SensorTensors` its block-layout version of the pixel operators: see
//! [`runs_kernels`].
//!
//! ```
//! use burn::tensor::{Device, Tensor};
//! use tcsense_kernels::conv_op::conv3x3;
//!
//! let device = Device::flex();
//! // a 3×3 kernel that is 1 at its centre is the identity
//! let x = Tensor::<4>::from_floats([[[[1.0, 2.0], [3.0, 4.0]]]], &device); // [B, C, H, W] = [1, 1, 2, 2]
//! let k = Tensor::<4>::from_floats([[[[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]]], &device);
//! let y = conv3x3(x.clone(), k, Tensor::zeros([1], &device));
//! assert_eq!(y.into_data(), x.into_data());
//! ```

pub mod conv;
pub mod conv_op;
pub mod delay;
pub mod delay_op;
mod direct;
pub mod pixel;
mod plane;
pub mod resample;
pub mod timing;

use burn::tensor::Device;

/// Whether the custom kernels of this crate run on `device`: the CPU `flex` device, with or
/// without autodiff. Elsewhere the ops fall back to burn's composed ones, which every backend
/// has (the kernels are registered for `Flex` and `Autodiff<Flex>` only).
pub fn runs_kernels(device: &Device) -> bool {
    device.clone().without_autodiff() == Device::flex()
}

/// Keep the memory of freed tensors in the process for the next ones (glibc only; elsewhere a
/// no-op). glibc's malloc serves blocks over its mmap threshold (at most 32 MiB) with fresh
/// mappings and unmaps them on free, so a training step whose tensors exceed it — the delay
/// prior's activations at T = 256 are 34 MB — faults in and zeroes every page of them again at
/// every step (measured: 21 % of such a step in `clear_page` and the page-fault handler). This
/// turns mmap off for large blocks and never trims the heap. Call it once, early, from a
/// front end (the `tcsense` binary does).
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes malloc's tuning parameters; it is called before any other
    // thread of this crate exists, and glibc serialises it against concurrent allocations.
    #[allow(unsafe_code)]
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
    }
}

/// Restore the default disposition of SIGPIPE (Rust's runtime ignores it), so that output
/// piped into a reader that stops early (`tcsense … | head`) ends the process quietly, as for
/// any Unix tool, rather than with a panic in `println!`. Call it once, early, from a front
/// end (the `tcsense` binary does), before any thread starts; a no-op off Unix.
pub fn quiet_broken_pipe() {
    #[cfg(unix)]
    // SAFETY: `signal` with SIG_DFL installs no handler (no code runs in signal context); it is
    // called before any other thread exists.
    #[allow(unsafe_code)]
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
