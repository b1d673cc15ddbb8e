//! Median timings for `tcsense bench` (printed, never asserted): one warm-up call, then the
//! median of `reps` timed calls, which is robust to the odd slow call on a shared machine.

use std::time::Instant;

/// The median of `samples` ordered by `key` (the upper median for an even count); `None` when
/// there are none.
pub fn median_by<T: Copy>(samples: &[T], key: impl Fn(&T) -> f64) -> Option<T> {
    let mut s = samples.to_vec();
    s.sort_by(|a, b| key(a).total_cmp(&key(b)));
    s.get(s.len() / 2).copied()
}

/// Call `f` once to warm up, then `reps` times (at least once), and return the median time of
/// one call in milliseconds; the first error ends the measurement.
pub fn median_ms<E>(mut f: impl FnMut() -> Result<(), E>, reps: usize) -> Result<f64, E> {
    f()?;
    let mut times = Vec::with_capacity(reps.max(1));
    for _ in 0..reps.max(1) {
        let t0 = Instant::now();
        f()?;
        times.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    Ok(median_by(&times, |t| *t).unwrap_or(f64::NAN))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_and_even_counts_and_errors() {
        assert_eq!(median_by(&[5.0, 1.0, 3.0], |v| *v), Some(3.0));
        assert_eq!(median_by(&[4.0, 1.0, 3.0, 2.0], |v| *v), Some(3.0));
        assert_eq!(median_by(&[(1, 9.0), (2, 1.0), (3, 5.0)], |v| v.1), Some((3, 5.0)));
        assert_eq!(median_by::<f64>(&[], |v| *v), None);
        let mut calls = 0;
        let t = median_ms::<()>(
            || {
                calls += 1;
                Ok(())
            },
            4,
        )
        .unwrap();
        assert_eq!(calls, 5, "one warm-up and four timed calls");
        assert!(t >= 0.0);
        assert_eq!(median_ms(|| Err::<(), _>("boom"), 3), Err("boom"));
    }
}
