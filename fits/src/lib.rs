//! `tcsense-fits`: the fits in the measurement domain, one home for the estimators that match
//! the sensor's templates to the tap images (or a cube) pixel by pixel, with no network.
//!
//! - [`engine`]: what every fit runs on — costs per pixel and candidate summed over a window
//!   by one box filter, one argmin, one refinement (parabola or golden sections).
//! - [`range`]: the range of one or two returns refined near a decoder's estimate (the
//!   U-Net's range fit, `NAME+fit`).
//! - [`depth`]: ranges from nothing — every candidate of the cycle at once as dense linear
//!   algebra, the window's best, polished by [`range`] (the `depth-fit` decoder).
//! - [`evidence`]: a fit's costs as a network's input — the log-likelihood of every candidate
//!   and the per-pixel posteriors (the depth and lifetime networks on the fits' evidence).
//! - [`lifetime_taps`]: lifetimes fitted to the tap images, with the onset and IRF fitted to
//!   the frame (the `lifetime-fit` decoder), and its costs on the lifetime grid as the evidence
//!   a network reads ([`lifetime_taps::evidence`], the lifetime network on the evidence).
//! - [`lifetime_cube`]: lifetimes of a reconstructed cube — a reconvolution fit of one or two
//!   exponentials (`tcsense lifetime`).
//!
//! Why a crate of its own: the fits are used by the networks' crate (the U-Net ends in the
//! range fit) and by inference (the decoders built on them, the streaming `infer`), and they
//! need nothing of either — only the sensor's matrix and waveforms (`tcsense_sensor`). Below
//! both, they are one place, and the decoder contract's adapters around them live with the
//! other decoders in `tcsense_infer::fitted`.

pub mod depth;
pub mod engine;
pub mod evidence;
pub mod lifetime_cube;
pub mod lifetime_taps;
pub mod range;
#[cfg(test)]
mod testing;

/// Run `f` compiled for AVX2 and FMA where this CPU has them (chosen at run time), so a
/// loop of multiply-adds vectorises beyond the baseline SSE2 (the instrument search's
/// correlations: a stream's start-up). Code reached from `f` must be
/// inlined into it (`#[inline(always)]`, on the closure too) to be compiled that way. Not AVX-512:
/// measured on a stream of lifetime frames, its wider loops made the process slower (the
/// cores' clock falls, for ONNX Runtime's work beside them too). The per-frame loops of the
/// costs and the window sums gained nothing measurable from AVX2 and stay baseline. The numbers are those of
/// the baseline to the bit: Rust neither reorders float sums nor fuses a multiply and an add,
/// whatever the extension.
#[inline(always)]
pub(crate) fn simd<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if let Some(v3) = pulp::x86::V3::try_new() {
        return pulp::Simd::vectorize(v3, f);
    }
    f()
}
