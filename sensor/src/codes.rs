//! Exposure codes `g[n][m][l]` and the hardware constraints they must satisfy (paper II-D).
//!
//! A code set holds one binary sequence of `L` masks for every subpixel `n` of the block
//! (row-major, `n = (row mod bh)·bw + (col mod bw)`) and every tap `m`; code-memory channel
//! `c = n·M + m`. The codes loop: mask `L−1` is followed by mask 0, so every constraint is
//! checked cyclically.
//!
//! Constraints (each optional):
//! 1. **Tap**: at most one tap is on per subpixel at each mask; without a drain, exactly one.
//! 2. **Hamming distance `H`**: between masks `l` and `l+1 mod L` at most `H` of the block's
//!    `N·M` channel bits change.
//! 3. **Time window `W`**: every run of 1s and every run of 0s in a channel lasts at least
//!    `W` masks, counted cyclically (a constant channel has no runs to break).
//!
//! JSON format (`format: "tcsense-codes"`, `version: 1`): `taps`, `block: [bh, bw]`,
//! `length`, `drain`, `clock_hz`, `constraints: {tap, hamming, window}` (`null` = off),
//! optional `provenance`, and `bits[n][m]`: a string of `L` characters `'0'`/`'1'`, mask 0
//! first.

use crate::error::{invalid, Result, SensorError};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::Path;

/// Default clock of the prototype's coded exposure controller (607 MHz, `T_c ≈ 1.65 ns`).
pub const DEFAULT_CLOCK_HZ: f64 = 607e6;

/// Which hardware constraints a code set was designed under.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct Constraints {
    /// Tap constraint: at most (drain) / exactly (no drain) one tap on per subpixel and mask.
    pub tap: bool,
    /// Maximal Hamming distance `H` between adjacent masks over the block's `N·M` channels.
    pub hamming: Option<usize>,
    /// Minimal run length `W` of 1s and 0s in every channel.
    pub window: Option<usize>,
}

impl Constraints {
    /// A short human-readable label, e.g. `tap+H2+W2`, or `none`.
    pub fn label(&self) -> String {
        let mut parts = Vec::new();
        if self.tap {
            parts.push("tap".to_string());
        }
        if let Some(h) = self.hamming {
            parts.push(format!("H{h}"));
        }
        if let Some(w) = self.window {
            parts.push(format!("W{w}"));
        }
        if parts.is_empty() {
            "none".into()
        } else {
            parts.join("+")
        }
    }
}

/// The geometry of a code set: block, taps, masks and drain.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CodeShape {
    /// Block height `bh`.
    pub bh: usize,
    /// Block width `bw`.
    pub bw: usize,
    /// Taps `M` (1–8).
    pub taps: usize,
    /// Masks per cycle `L` (multiple of 8, 8–256).
    pub length: usize,
    /// Whether the modulator has a drain.
    pub drain: bool,
}

impl CodeShape {
    /// Check the hardware limits: `M` in 1..=8, `L` a multiple of 8 in 8..=256, block sides 1..=16.
    pub fn validate(self) -> Result<Self> {
        if !(1..=8).contains(&self.taps) {
            return Err(invalid("taps", self.taps, "1..=8"));
        }
        if self.length % 8 != 0 || !(8..=256).contains(&self.length) {
            return Err(invalid("length", self.length, "a multiple of 8 in 8..=256"));
        }
        if !(1..=16).contains(&self.bh) || !(1..=16).contains(&self.bw) {
            return Err(invalid("block", format!("{}x{}", self.bh, self.bw), "sides in 1..=16 (e.g. 2x2)"));
        }
        Ok(self)
    }

    /// Subpixels per block, `N = bh·bw`.
    pub fn subpixels(&self) -> usize {
        self.bh * self.bw
    }

    /// Code-memory channels, `N·M`.
    pub fn channels(&self) -> usize {
        self.subpixels() * self.taps
    }
}

/// Which constraint a violation breaks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum ConstraintKind {
    Tap,
    Hamming,
    Window,
}

/// One violation found by [`Codes::violations`].
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Violation {
    /// The constraint broken.
    pub kind: ConstraintKind,
    /// Mask index `l` (for Hamming: the transition `l → l+1 mod L`; for window: the run's first mask).
    pub mask: usize,
    /// Subpixel `n` (tap constraint) or `None`.
    pub subpixel: Option<usize>,
    /// Channel `c = n·M + m` (window constraint) or `None`.
    pub channel: Option<usize>,
    /// What was found.
    pub detail: String,
}

impl fmt::Display for Violation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let kind = match self.kind {
            ConstraintKind::Tap => "tap",
            ConstraintKind::Hamming => "hamming",
            ConstraintKind::Window => "window",
        };
        write!(f, "{kind}: mask {}", self.mask)?;
        if let Some(n) = self.subpixel {
            write!(f, ", subpixel {n}")?;
        }
        if let Some(c) = self.channel {
            write!(f, ", channel {c}")?;
        }
        write!(f, ": {}", self.detail)
    }
}

/// A set of exposure codes `g[n][m][l]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Codes {
    shape: CodeShape,
    /// Clock of the coded exposure controller (Hz); mask period `T_c = 1/clock_hz`.
    pub clock_hz: f64,
    /// The constraints the codes were designed under (and are checked against).
    pub constraints: Constraints,
    /// Free-form provenance (generator, seed, selection score…), kept in the JSON file.
    pub provenance: serde_json::Value,
    /// Bits `[N][M][L]`, flattened, each 0 or 1.
    bits: Vec<u8>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CodesFile {
    format: String,
    version: u32,
    taps: usize,
    block: [usize; 2],
    length: usize,
    drain: bool,
    clock_hz: f64,
    constraints: Constraints,
    #[serde(default, skip_serializing_if = "serde_json::Value::is_null")]
    provenance: serde_json::Value,
    bits: Vec<Vec<String>>,
}

impl Codes {
    /// Codes with every bit 0, to be filled with [`Codes::set`].
    pub fn zeros(shape: CodeShape, clock_hz: f64, constraints: Constraints) -> Result<Self> {
        let shape = shape.validate()?;
        check_clock(clock_hz)?;
        check_constraint_params(&constraints, &shape)?;
        Ok(Codes { shape, clock_hz, constraints, provenance: serde_json::Value::Null, bits: vec![0; shape.channels() * shape.length] })
    }

    /// The geometry (block, taps, length, drain).
    pub fn shape(&self) -> CodeShape {
        self.shape
    }
    /// Taps `M`.
    pub fn taps(&self) -> usize {
        self.shape.taps
    }
    /// Subpixels per block `N`.
    pub fn subpixels(&self) -> usize {
        self.shape.subpixels()
    }
    /// Masks per cycle `L`.
    pub fn length(&self) -> usize {
        self.shape.length
    }
    /// Block `(bh, bw)`.
    pub fn block(&self) -> (usize, usize) {
        (self.shape.bh, self.shape.bw)
    }
    /// Whether the modulator has a drain.
    pub fn drain(&self) -> bool {
        self.shape.drain
    }
    /// Mask period `T_c` in seconds.
    pub fn clock_period_s(&self) -> f64 {
        1.0 / self.clock_hz
    }

    /// Bit `g[n][m][l]`.
    #[inline]
    pub fn get(&self, n: usize, m: usize, l: usize) -> bool {
        self.bits[(n * self.shape.taps + m) * self.shape.length + l] != 0
    }

    /// Set bit `g[n][m][l]`.
    #[inline]
    pub fn set(&mut self, n: usize, m: usize, l: usize, on: bool) {
        let i = (n * self.shape.taps + m) * self.shape.length + l;
        self.bits[i] = on as u8;
    }

    /// The `L` bits of channel `c = n·M + m`.
    pub fn channel(&self, c: usize) -> &[u8] {
        let l = self.shape.length;
        &self.bits[c * l..(c + 1) * l]
    }

    /// Every violation of the declared constraints, in the order tap, Hamming, window.
    pub fn violations(&self) -> Vec<Violation> {
        self.violations_of(&self.constraints)
    }

    /// Every violation of the given constraints (cyclic across the loop boundary).
    pub fn violations_of(&self, c: &Constraints) -> Vec<Violation> {
        let CodeShape { taps, length: len, drain, .. } = self.shape;
        let n_sub = self.subpixels();
        let mut out = Vec::new();
        if c.tap {
            for l in 0..len {
                for n in 0..n_sub {
                    let on: Vec<usize> = (0..taps).filter(|&m| self.get(n, m, l)).collect();
                    if on.len() > 1 || (!drain && on.is_empty()) {
                        let detail = if on.is_empty() {
                            "no tap on, but a modulator without drain needs exactly one".to_string()
                        } else {
                            format!("taps {on:?} on together, at most one allowed")
                        };
                        out.push(Violation { kind: ConstraintKind::Tap, mask: l, subpixel: Some(n), channel: None, detail });
                    }
                }
            }
        }
        if let Some(h) = c.hamming {
            let channels = self.shape.channels();
            for l in 0..len {
                let next = (l + 1) % len;
                let flips: Vec<usize> = (0..channels).filter(|&ch| self.channel(ch)[l] != self.channel(ch)[next]).collect();
                if flips.len() > h {
                    out.push(Violation {
                        kind: ConstraintKind::Hamming,
                        mask: l,
                        subpixel: None,
                        channel: None,
                        detail: format!(
                            "{} bits change from mask {l} to mask {next} (channels {flips:?}), at most {h} allowed",
                            flips.len()
                        ),
                    });
                }
            }
        }
        if let Some(w) = c.window {
            for ch in 0..self.shape.channels() {
                for run in cyclic_runs(self.channel(ch)) {
                    if run.len < w {
                        out.push(Violation {
                            kind: ConstraintKind::Window,
                            mask: run.start,
                            subpixel: Some(ch / taps),
                            channel: Some(ch),
                            detail: format!(
                                "run of {} {}s starting at mask {} lasts {} mask(s), at least {w} required",
                                run.len, run.value, run.start, run.len
                            ),
                        });
                    }
                }
            }
        }
        out
    }

    /// Fail with [`SensorError::Infeasible`] if the codes break their declared constraints.
    pub fn ensure_feasible(&self) -> Result<()> {
        let v = self.violations();
        match v.first() {
            None => Ok(()),
            Some(first) => Err(SensorError::Infeasible { count: v.len(), first: first.to_string() }),
        }
    }

    /// A fingerprint of the code bits and their shape (FNV-1a, 16 hex digits): equal codes,
    /// equal digests, whatever their provenance or clock.
    pub fn digest(&self) -> String {
        let CodeShape { bh, bw, taps, length, drain } = self.shape;
        let head = [bh, bw, taps, length, drain as usize].into_iter().flat_map(|v| (v as u64).to_le_bytes());
        crate::digest::digest(head.chain(self.bits.iter().copied()))
    }

    /// Hamming distance between mask `l` and mask `l+1 mod L` over all channels.
    pub fn hamming_at(&self, l: usize) -> usize {
        let next = (l + 1) % self.length();
        (0..self.shape.channels()).filter(|&c| self.channel(c)[l] != self.channel(c)[next]).count()
    }

    /// Serialise to the JSON format.
    pub fn to_json(&self) -> String {
        let (taps, len) = (self.shape.taps, self.shape.length);
        let bits = (0..self.subpixels())
            .map(|n| (0..taps).map(|m| (0..len).map(|l| if self.get(n, m, l) { '1' } else { '0' }).collect()).collect())
            .collect();
        let f = CodesFile {
            format: "tcsense-codes".into(),
            version: 1,
            taps,
            block: [self.shape.bh, self.shape.bw],
            length: len,
            drain: self.shape.drain,
            clock_hz: self.clock_hz,
            constraints: self.constraints,
            provenance: self.provenance.clone(),
            bits,
        };
        // Serialising plain data cannot fail.
        serde_json::to_string_pretty(&f).unwrap_or_default() + "\n"
    }

    /// Parse the JSON format; errors name the field and what was expected.
    pub fn from_json(text: &str) -> std::result::Result<Self, String> {
        let f: CodesFile = serde_json::from_str(text).map_err(|e| format!("malformed codes JSON: {e}"))?;
        if f.format != "tcsense-codes" {
            return Err(format!("field 'format' is {:?}, expected \"tcsense-codes\"", f.format));
        }
        if f.version != 1 {
            return Err(format!("field 'version' is {}, expected 1", f.version));
        }
        let shape = CodeShape { bh: f.block[0], bw: f.block[1], taps: f.taps, length: f.length, drain: f.drain };
        let mut codes = Codes::zeros(shape, f.clock_hz, f.constraints).map_err(|e| e.to_string())?;
        codes.provenance = f.provenance;
        if f.bits.len() != shape.subpixels() {
            return Err(format!(
                "field 'bits' has {} subpixel entries, expected {} (block {}x{})",
                f.bits.len(),
                shape.subpixels(),
                shape.bh,
                shape.bw
            ));
        }
        for (n, per_tap) in f.bits.iter().enumerate() {
            if per_tap.len() != shape.taps {
                return Err(format!("field 'bits[{n}]' has {} tap entries, expected {} taps", per_tap.len(), shape.taps));
            }
            for (m, s) in per_tap.iter().enumerate() {
                if s.len() != shape.length {
                    return Err(format!("field 'bits[{n}][{m}]' has {} characters, expected length {}", s.len(), shape.length));
                }
                for (l, ch) in s.chars().enumerate() {
                    match ch {
                        '0' => {}
                        '1' => codes.set(n, m, l, true),
                        other => return Err(format!("field 'bits[{n}][{m}]' has {other:?} at mask {l}, expected '0' or '1'")),
                    }
                }
            }
        }
        Ok(codes)
    }

    /// Load from a JSON file and refuse codes that break their declared constraints (no
    /// sensor would take them); errors name the file.
    pub fn load(path: &Path) -> Result<Self> {
        let codes = Codes::load_unchecked(path)?;
        codes.ensure_feasible().map_err(|e| SensorError::file(path, e.to_string()))?;
        Ok(codes)
    }

    /// Load from a JSON file without checking the declared constraints (for `codes check`,
    /// which reports the violations); errors name the file.
    pub fn load_unchecked(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| SensorError::io(path, e))?;
        Codes::from_json(&text).map_err(|msg| SensorError::file(path, msg))
    }

    /// Save to a JSON file atomically.
    pub fn save(&self, path: &Path) -> Result<()> {
        crate::npy::write_bytes(path, self.to_json().as_bytes())
    }
}

/// The code clocks taken (Hz): a coded exposure controller's, from 1 MHz (a cycle of 256 masks
/// in 256 µs) to 10 GHz.
pub const CLOCK_RANGE_HZ: [f64; 2] = [1e6, 10e9];

/// Refuse a code clock outside [`CLOCK_RANGE_HZ`].
pub fn check_clock(clock_hz: f64) -> Result<()> {
    let [lo, hi] = CLOCK_RANGE_HZ;
    if !(clock_hz.is_finite() && (lo..=hi).contains(&clock_hz)) {
        return Err(invalid("clock_hz", clock_hz, "a frequency from 1 MHz to 10 GHz (e.g. 607e6)"));
    }
    Ok(())
}

fn check_constraint_params(c: &Constraints, shape: &CodeShape) -> Result<()> {
    if let Some(w) = c.window {
        if w == 0 || w > shape.length {
            return Err(invalid("window", w, format!("1..={} (the code length)", shape.length)));
        }
    }
    Ok(())
}

/// A maximal run of equal bits in a cyclic sequence.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Run {
    /// First mask of the run.
    pub start: usize,
    /// Length in masks.
    pub len: usize,
    /// The bit value (0 or 1).
    pub value: u8,
}

/// The maximal runs of a cyclic bit sequence; empty if the sequence is constant.
pub fn cyclic_runs(bits: &[u8]) -> Vec<Run> {
    let len = bits.len();
    // A run starts at l when bits[l] differs from bits[l-1 mod L].
    let starts: Vec<usize> = (0..len).filter(|&l| bits[l] != bits[(l + len - 1) % len]).collect();
    starts
        .iter()
        .enumerate()
        .map(|(i, &s)| {
            let next = starts[(i + 1) % starts.len()];
            let run_len = (next + len - s - 1) % len + 1;
            Run { start: s, len: run_len, value: bits[s] }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shape(bh: usize, bw: usize, taps: usize, length: usize, drain: bool) -> CodeShape {
        CodeShape { bh, bw, taps, length, drain }
    }

    #[test]
    fn runs_wrap_around() {
        let r = cyclic_runs(&[1, 0, 0, 1, 1, 1, 1, 1]);
        // runs: 0s at 1..3 (len 2), 1s at 3..=0 wrapping (len 6)
        assert_eq!(r, vec![Run { start: 1, len: 2, value: 0 }, Run { start: 3, len: 6, value: 1 }]);
        assert!(cyclic_runs(&[1; 8]).is_empty());
    }

    #[test]
    fn checker_catches_each_constraint_including_wrap() {
        let c = Constraints { tap: true, hamming: Some(2), window: Some(2) };
        let mut g = Codes::zeros(shape(1, 2, 2, 8, false), DEFAULT_CLOCK_HZ, c).unwrap();
        // Feasible: subpixel 0 on tap 0 for masks 0..4, tap 1 for 4..8; subpixel 1 constant tap 1.
        for l in 0..8 {
            g.set(0, if l < 4 { 0 } else { 1 }, l, true);
            g.set(1, 1, l, true);
        }
        assert!(g.violations().is_empty(), "{:?}", g.violations());

        // Tap: two taps on at mask 5 of subpixel 0 -> also a window break.
        let mut t = g.clone();
        t.set(0, 0, 5, true);
        let v = t.violations_of(&Constraints { tap: true, ..Default::default() });
        assert_eq!(v.len(), 1);
        assert_eq!((v[0].kind, v[0].mask, v[0].subpixel), (ConstraintKind::Tap, 5, Some(0)));
        // No tap on without drain.
        let mut t = g.clone();
        t.set(1, 1, 3, false);
        let v = t.violations_of(&Constraints { tap: true, ..Default::default() });
        assert_eq!((v.len(), v[0].mask, v[0].subpixel), (1, 3, Some(1)));

        // Hamming across the loop boundary: both subpixels switch taps at 3 -> 4 and at 7 -> 0.
        let mut h2 = Codes::zeros(g.shape(), DEFAULT_CLOCK_HZ, c).unwrap();
        for l in 0..8 {
            h2.set(0, if l < 4 { 0 } else { 1 }, l, true);
            h2.set(1, if l < 4 { 0 } else { 1 }, l, true);
        }
        let v = h2.violations_of(&Constraints { hamming: Some(2), ..Default::default() });
        let masks: Vec<usize> = v.iter().map(|v| v.mask).collect();
        assert_eq!(masks, vec![3, 7], "the 7 -> 0 transition is checked");
        assert!(v.iter().all(|v| v.kind == ConstraintKind::Hamming));

        // Window across the boundary: a run of one 1 at mask 7 that is not continued at mask 0.
        let mut w = Codes::zeros(shape(1, 1, 1, 8, true), DEFAULT_CLOCK_HZ, c).unwrap();
        for l in [0, 1, 2] {
            w.set(0, 0, l, true);
        }
        assert!(w.violations_of(&Constraints { window: Some(2), ..Default::default() }).is_empty());
        w.set(0, 0, 7, true); // now run 7..=2 wraps (len 4): still fine
        assert!(w.violations_of(&Constraints { window: Some(2), ..Default::default() }).is_empty());
        w.set(0, 0, 5, true); // a lone 1 at 5 and a lone 0 at 6
        let v = w.violations_of(&Constraints { window: Some(2), ..Default::default() });
        let got: Vec<(usize, Option<usize>)> = v.iter().map(|v| (v.mask, v.channel)).collect();
        assert_eq!(got, vec![(5, Some(0)), (6, Some(0))]);
        // a run of 0s that wraps: 1s only at 2..6 -> 0s at 6,7,0,1 (len 4) fine with W=4, 1s len 4
        let mut w2 = Codes::zeros(shape(1, 1, 1, 8, true), DEFAULT_CLOCK_HZ, c).unwrap();
        for l in 2..6 {
            w2.set(0, 0, l, true);
        }
        assert!(w2.violations_of(&Constraints { window: Some(4), ..Default::default() }).is_empty());
        let v = w2.violations_of(&Constraints { window: Some(5), ..Default::default() });
        assert_eq!(v.iter().map(|v| v.mask).collect::<Vec<_>>(), vec![2, 6]);
    }

    #[test]
    fn json_roundtrip_and_errors() {
        let c = Constraints { tap: true, hamming: Some(2), window: None };
        let mut g = Codes::zeros(shape(2, 2, 3, 16, true), 500e6, c).unwrap();
        g.set(3, 2, 15, true);
        g.set(0, 1, 0, true);
        g.provenance = serde_json::json!({"seed": 7});
        let back = Codes::from_json(&g.to_json()).unwrap();
        assert_eq!(back, g);
        let bad = g.to_json().replace("\"length\": 16", "\"length\": 12");
        assert!(Codes::from_json(&bad).unwrap_err().contains("multiple of 8"));
        let bad = g.to_json().replacen("0000000000000001", "000000000000000x", 1);
        assert!(Codes::from_json(&bad).unwrap_err().contains("expected '0' or '1'"));
        assert!(Codes::from_json("{").unwrap_err().contains("malformed"));
    }
}
