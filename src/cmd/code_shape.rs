//! The code geometry and constraint flags that `codes generate`, `codes project`, `codes
//! select` and `codes design` share.

use clap::Args;
use tcsense_sensor::codes::{CodeShape, Constraints, DEFAULT_CLOCK_HZ};

/// Geometry and constraint flags shared by code generation and selection.
#[derive(Args, Clone)]
pub struct DesignArgs {
    /// Taps M (1–8).
    #[arg(long, default_value_t = 4)]
    pub taps: usize,
    /// Pixel block bh×bw.
    #[arg(long, default_value = "2x2", value_parser = super::parse_hw)]
    pub block: (usize, usize),
    /// Masks per cycle L (multiple of 8, 8–256).
    #[arg(long, default_value_t = 32)]
    pub length: usize,
    /// The modulator has a drain (with the tap constraint: at most one tap on).
    #[arg(long)]
    pub drain: bool,
    /// Code clock in MHz.
    #[arg(long, default_value_t = DEFAULT_CLOCK_HZ / 1e6)]
    pub clock_mhz: f64,
    /// Tap constraint: one tap (drain included) on per subpixel at each mask.
    #[arg(long)]
    pub tap_constraint: bool,
    /// Hamming-distance constraint: at most H bits change between adjacent masks.
    #[arg(long, value_name = "H")]
    pub hamming: Option<usize>,
    /// Time-window constraint: every run of 1s and 0s lasts at least W masks.
    #[arg(long, value_name = "W")]
    pub window: Option<usize>,
}

impl DesignArgs {
    pub fn shape(&self) -> CodeShape {
        CodeShape { bh: self.block.0, bw: self.block.1, taps: self.taps, length: self.length, drain: self.drain }
    }
    pub fn constraints(&self) -> Constraints {
        Constraints { tap: self.tap_constraint, hamming: self.hamming, window: self.window }
    }
    pub fn clock_hz(&self) -> f64 {
        self.clock_mhz * 1e6
    }
}
