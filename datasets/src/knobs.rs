//! Randomised knobs: a range `[lo, hi]` per knob, drawn uniformly or log-uniformly, with
//! `lo == hi` fixing the knob to that value (the generators' fixed settings for the paper's
//! studies, and the training augmentation's).

use crate::error::{invalid, Result};
use rand::rngs::StdRng;
use rand::RngExt;

/// A draw from `range`: uniform, or log-uniform with `log` (for positive ranges); the value
/// itself when `lo == hi`.
pub fn draw(rng: &mut StdRng, range: [f64; 2], log: bool) -> f64 {
    let [lo, hi] = range;
    if lo >= hi {
        lo
    } else if log && lo > 0.0 {
        rng.random_range(lo.ln()..hi.ln()).exp()
    } else {
        rng.random_range(lo..hi)
    }
}

/// Check that `range` is finite, ordered and within `[min, max]`.
pub fn check_range(name: &'static str, range: [f64; 2], min: f64, max: f64) -> Result<()> {
    let [lo, hi] = range;
    if lo.is_finite() && hi.is_finite() && min <= lo && lo <= hi && hi <= max {
        Ok(())
    } else {
        Err(invalid(name, format!("{range:?}"), format!("a range LO ≤ HI within [{min:e}, {max:e}]")))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn draws_stay_in_range_and_log_draws_spread_over_decades() {
        let mut rng = StdRng::seed_from_u64(1);
        assert_eq!(draw(&mut rng, [0.3, 0.3], true), 0.3);
        let lin: Vec<f64> = (0..1000).map(|_| draw(&mut rng, [0.01, 1.0], false)).collect();
        let log: Vec<f64> = (0..1000).map(|_| draw(&mut rng, [0.01, 1.0], true)).collect();
        assert!(lin.iter().chain(&log).all(|v| (0.01..=1.0).contains(v)));
        // below 0.1: about 9 % of uniform draws, about half of log-uniform ones
        let below = |v: &[f64]| v.iter().filter(|&&x| x < 0.1).count();
        assert!(below(&lin) < 150 && (400..600).contains(&below(&log)), "{} {}", below(&lin), below(&log));
        assert!(check_range("k", [0.2, 0.1], 0.0, 1.0).is_err());
        assert!(check_range("k", [0.1, f64::NAN], 0.0, 1.0).is_err());
        assert!(check_range("k", [0.1, 2.0], 0.0, 1.0).unwrap_err().to_string().contains("k"));
        check_range("k", [0.1, 0.1], 0.0, 1.0).unwrap();
    }
}
