//! Up-front memory checks: a request whose working set cannot fit is refused with the
//! estimate, instead of ending in an out-of-memory kill halfway.

use crate::error::{Result, SensorError};

/// Memory the system can still give (Linux `MemAvailable`), in bytes; `None` where unknown.
pub fn available_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/meminfo").ok()?;
    let kb: u64 = s.lines().find(|l| l.starts_with("MemAvailable:"))?.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Refuse `what` when its estimated working set `bytes` exceeds the available memory;
/// `hint` says how to shrink it.
pub fn check_fits(what: &str, bytes: f64, hint: &str) -> Result<()> {
    let Some(avail) = available_bytes() else { return Ok(()) };
    if bytes > avail as f64 {
        return Err(SensorError::InvalidParam {
            field: "size",
            got: format!("{what} needs about {:.1} GiB of memory", bytes / (1u64 << 30) as f64),
            expected: format!("at most the {:.1} GiB available; {hint}", avail as f64 / (1u64 << 30) as f64),
        });
    }
    Ok(())
}
