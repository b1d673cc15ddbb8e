//! Helpers of the crate's tests.

use ndarray::Axis;

/// Noise on taps `[M, H, W]`: Gaussian of the charge's variance (Poisson-like, from twelve
/// uniforms of a splitmix64 stream seeded by `seed`), at `photons` per pixel, or with
/// `by_charge` the frame's brightest pixel at `photons` and every other in proportion to its
/// charge (shot noise as a sensor has it).
pub(crate) fn noise(y: &ndarray::Array3<f32>, photons: f64, seed: u64, by_charge: bool) -> ndarray::Array3<f32> {
    // a splitmix64 stream of uniforms
    let mut state = seed;
    let mut uniform = move || {
        state = state.wrapping_add(0x9E3779B97F4A7C15);
        let mut z = state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58476D1CE4E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D049BB133111EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    };
    let (m, h, w) = y.dim();
    let mut out = y.clone();
    let peak = y.sum_axis(Axis(0)).iter().fold(0f32, |a, &b| a.max(b));
    for i in 0..h {
        for j in 0..w {
            let s: f32 = (0..m).map(|k| y[(k, i, j)]).sum();
            let scale = photons / if by_charge { peak } else { s } as f64;
            for k in 0..m {
                let e = y[(k, i, j)] as f64 * scale;
                let n: f64 = (0..12).map(|_| uniform()).sum::<f64>() - 6.0;
                out[(k, i, j)] = ((e + e.max(0.0).sqrt() * n).max(0.0) / scale) as f32;
            }
        }
    }
    out
}
