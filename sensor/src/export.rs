//! Export of exposure codes to the sensor's code memory (paper II-B, Figs. 6–7).
//!
//! The coded exposure controller holds `N·M` channels (channel `c = n·M + m`: tap `m` of
//! subpixel `n`), each `L/8` bytes, read one byte per channel at a time (`ADR = 0 … L/8−1`)
//! into shift registers. Register `ECLEN = L/8 − 1`.
//!
//! Files written to the export directory:
//! - `chCC.bin`: channel `CC` (two digits), `L/8` bytes;
//! - `codes.bin`: the combined memory image, channel-major: channel `c` occupies bytes
//!   `[c·L/8, (c+1)·L/8)`;
//! - `registers.json`: `ECLEN`, the channel map (channel → subpixel, row, column, tap, file,
//!   offset), the bit order, and the code set's metadata.
//!
//! **Bit order**: mask `l` is bit `7 − (l mod 8)` of byte `l / 8` (most significant bit
//! first: the first mask shifted out is the MSB of the first byte).
//!
//! Codes that violate their declared constraints are refused.

use crate::codes::{CodeShape, Codes, Constraints};
use crate::error::{Result, SensorError};
use crate::npy::write_bytes;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// One entry of the channel map.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChannelEntry {
    pub channel: usize,
    pub subpixel: usize,
    pub row: usize,
    pub col: usize,
    pub tap: usize,
    pub file: String,
    pub offset: usize,
}

/// `registers.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[allow(non_snake_case)]
pub struct Registers {
    pub ECLEN: usize,
    pub length: usize,
    pub bytes_per_channel: usize,
    pub channel_count: usize,
    pub bit_order: String,
    pub combined_file: String,
    pub combined_layout: String,
    pub taps: usize,
    pub block: [usize; 2],
    pub drain: bool,
    pub clock_hz: f64,
    pub constraints: Constraints,
    pub channels: Vec<ChannelEntry>,
}

const BIT_ORDER: &str = "msb-first: mask l is bit 7-(l%8) of byte l/8";
const LAYOUT: &str = "channel-major: channel c at bytes [c*L/8, (c+1)*L/8)";

/// Pack one channel's `L` bits into `L/8` bytes, MSB first.
pub fn pack_channel(bits: &[u8]) -> Vec<u8> {
    bits.chunks(8)
        .map(|byte| byte.iter().enumerate().fold(0u8, |acc, (i, &b)| acc | ((b & 1) << (7 - i))))
        .collect()
}

/// Unpack `L/8` bytes into `L` bits, MSB first.
pub fn unpack_channel(bytes: &[u8]) -> Vec<u8> {
    bytes.iter().flat_map(|&byte| (0..8).map(move |i| (byte >> (7 - i)) & 1)).collect()
}

/// Write the code memory image to `dir` (created if needed). Refuses infeasible codes.
pub fn export(codes: &Codes, dir: &Path) -> Result<Registers> {
    codes.ensure_feasible()?;
    let CodeShape { bh: _, bw, taps, length, drain } = codes.shape();
    let bpc = length / 8;
    let n_ch = codes.subpixels() * taps;
    std::fs::create_dir_all(dir).map_err(|e| SensorError::io(dir, e))?;
    let mut combined = Vec::with_capacity(n_ch * bpc);
    let mut channels = Vec::with_capacity(n_ch);
    for c in 0..n_ch {
        let bytes = pack_channel(codes.channel(c));
        let file = format!("ch{c:02}.bin");
        write_bytes(&dir.join(&file), &bytes)?;
        let n = c / taps;
        channels.push(ChannelEntry { channel: c, subpixel: n, row: n / bw, col: n % bw, tap: c % taps, file, offset: c * bpc });
        combined.extend_from_slice(&bytes);
    }
    write_bytes(&dir.join("codes.bin"), &combined)?;
    let (bh, bw) = codes.block();
    let regs = Registers {
        ECLEN: bpc - 1,
        length,
        bytes_per_channel: bpc,
        channel_count: n_ch,
        bit_order: BIT_ORDER.into(),
        combined_file: "codes.bin".into(),
        combined_layout: LAYOUT.into(),
        taps,
        block: [bh, bw],
        drain,
        clock_hz: codes.clock_hz,
        constraints: codes.constraints,
        channels,
    };
    let json = serde_json::to_string_pretty(&regs).unwrap_or_default() + "\n";
    write_bytes(&dir.join("registers.json"), json.as_bytes())?;
    Ok(regs)
}

/// Read an exported code memory back into codes (from `registers.json` and the channel files),
/// checking that the combined image agrees with the channel files.
pub fn import(dir: &Path) -> Result<Codes> {
    let reg_path = dir.join("registers.json");
    let text = std::fs::read_to_string(&reg_path).map_err(|e| SensorError::io(&reg_path, e))?;
    let regs: Registers = serde_json::from_str(&text).map_err(|e| SensorError::file(&reg_path, format!("malformed registers: {e}")))?;
    if regs.ECLEN + 1 != regs.length / 8 {
        return Err(SensorError::file(&reg_path, format!("ECLEN = {} does not match length {} (expected L/8 - 1 = {})", regs.ECLEN, regs.length, regs.length / 8 - 1)));
    }
    let shape = CodeShape { bh: regs.block[0], bw: regs.block[1], taps: regs.taps, length: regs.length, drain: regs.drain };
    let mut codes = Codes::zeros(shape, regs.clock_hz, regs.constraints).map_err(|e| e.in_file(&reg_path))?;
    if regs.channels.len() != codes.subpixels() * regs.taps {
        return Err(SensorError::file(&reg_path, format!("{} channels listed, expected N·M = {}", regs.channels.len(), codes.subpixels() * regs.taps)));
    }
    let comb_path = dir.join(&regs.combined_file);
    let combined = std::fs::read(&comb_path).map_err(|e| SensorError::io(&comb_path, e))?;
    for ch in &regs.channels {
        let p = dir.join(&ch.file);
        let bytes = std::fs::read(&p).map_err(|e| SensorError::io(&p, e))?;
        if bytes.len() != regs.bytes_per_channel {
            return Err(SensorError::file(&p, format!("{} bytes, expected L/8 = {}", bytes.len(), regs.bytes_per_channel)));
        }
        if combined.get(ch.offset..ch.offset + bytes.len()) != Some(&bytes[..]) {
            return Err(SensorError::file(&comb_path, format!("bytes of channel {} differ from {}", ch.channel, ch.file)));
        }
        if ch.subpixel >= codes.subpixels() || ch.tap >= regs.taps {
            return Err(SensorError::file(&reg_path, format!("channel {} maps to subpixel {} tap {}, out of range", ch.channel, ch.subpixel, ch.tap)));
        }
        for (l, b) in unpack_channel(&bytes).into_iter().enumerate() {
            codes.set(ch.subpixel, ch.tap, l, b == 1);
        }
    }
    Ok(codes)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::random_codes;

    #[test]
    fn pack_is_msb_first() {
        let mut bits = vec![0u8; 16];
        bits[0] = 1;
        bits[9] = 1;
        bits[15] = 1;
        assert_eq!(pack_channel(&bits), vec![0x80, 0x41]);
        assert_eq!(unpack_channel(&[0x80, 0x41]), bits);
    }

    #[test]
    fn export_roundtrip_and_refusal() {
        let dir = crate::npy::tests::tempdir();
        let shape = CodeShape { bh: 2, bw: 3, taps: 3, length: 24, drain: true };
        let c = Constraints { tap: true, hamming: Some(2), window: Some(2) };
        let g = random_codes(shape, 607e6, c, 4).unwrap();
        let regs = export(&g, &dir).unwrap();
        assert_eq!(regs.ECLEN, 2);
        assert_eq!(std::fs::read(dir.join("ch17.bin")).unwrap().len(), 3);
        assert_eq!(std::fs::read(dir.join("codes.bin")).unwrap().len(), 18 * 3);
        let back = import(&dir).unwrap();
        for ch in 0..18 {
            assert_eq!(back.channel(ch), g.channel(ch));
        }
        // Infeasible codes are refused and nothing new is written.
        let mut bad = g.clone();
        bad.set(0, 0, 0, true);
        bad.set(0, 1, 0, true);
        let dir2 = dir.join("bad");
        let e = export(&bad, &dir2).unwrap_err();
        assert!(e.to_string().contains("violate"), "{e}");
        assert!(!dir2.exists());
    }
}
