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
#[serde(deny_unknown_fields)]
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
#[serde(deny_unknown_fields)]
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
    bits.chunks(8).map(|byte| byte.iter().enumerate().fold(0u8, |acc, (i, &b)| acc | ((b & 1) << (7 - i)))).collect()
}

/// Unpack `L/8` bytes into `L` bits, MSB first.
pub fn unpack_channel(bytes: &[u8]) -> Vec<u8> {
    bytes.iter().flat_map(|&byte| (0..8).map(move |i| (byte >> (7 - i)) & 1)).collect()
}

/// Whether `name` is a file [`export`] writes (the names an earlier export may have left).
fn is_export_file(name: &str) -> bool {
    name == "codes.bin"
        || name == "registers.json"
        || (name.len() > 6
            && name.starts_with("ch")
            && name.ends_with(".bin")
            && name[2..name.len() - 4].bytes().all(|b| b.is_ascii_digit()))
}

/// Write the code memory image to `dir`. Refuses infeasible codes. The directory is written
/// whole: an earlier export there is replaced (none of its channel files remain), a directory
/// holding other files is refused, and on error nothing changes.
pub fn export(codes: &Codes, dir: &Path) -> Result<Registers> {
    codes.ensure_feasible()?;
    let CodeShape { bh: _, bw, taps, length, drain } = codes.shape();
    let bpc = length / 8;
    let n_ch = codes.subpixels() * taps;
    crate::output::replace_dir(dir, &is_export_file, |tmp| {
        let mut combined = Vec::with_capacity(n_ch * bpc);
        let mut channels = Vec::with_capacity(n_ch);
        for c in 0..n_ch {
            let bytes = pack_channel(codes.channel(c));
            let file = format!("ch{c:02}.bin");
            write_bytes(&tmp.join(&file), &bytes)?;
            let n = c / taps;
            channels.push(ChannelEntry { channel: c, subpixel: n, row: n / bw, col: n % bw, tap: c % taps, file, offset: c * bpc });
            combined.extend_from_slice(&bytes);
        }
        write_bytes(&tmp.join("codes.bin"), &combined)?;
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
        write_bytes(&tmp.join("registers.json"), json.as_bytes())?;
        Ok(regs)
    })
}

/// A file name inside the export directory: one plain name, no path.
fn plain_name(reg_path: &Path, field: &str, name: &str) -> Result<()> {
    let p = Path::new(name);
    if name.is_empty() || p.components().count() != 1 || p.file_name().map(|n| n != p.as_os_str()).unwrap_or(true) {
        return Err(SensorError::file(reg_path, format!("field {field} is {name:?}; expected a file name inside the export directory")));
    }
    Ok(())
}

/// Read an exported code memory back into codes (from `registers.json` and the channel files).
/// Every field is honoured or refused: the shape and clock are checked as codes are, `ECLEN`,
/// `bytes_per_channel`, `channel_count`, `bit_order` and `combined_layout` must be this
/// format's, every channel entry must sit where the layout puts it, the combined image must
/// hold exactly the channels' bytes and agree with the channel files, and the codes must meet
/// the constraints they declare.
pub fn import(dir: &Path) -> Result<Codes> {
    let reg_path = dir.join("registers.json");
    let text = std::fs::read_to_string(&reg_path).map_err(|e| SensorError::io(&reg_path, e))?;
    let regs: Registers = serde_json::from_str(&text).map_err(|e| SensorError::file(&reg_path, format!("malformed registers: {e}")))?;
    let bad = |msg: String| SensorError::file(&reg_path, msg);
    let shape = CodeShape { bh: regs.block[0], bw: regs.block[1], taps: regs.taps, length: regs.length, drain: regs.drain };
    let mut codes = Codes::zeros(shape, regs.clock_hz, regs.constraints).map_err(|e| e.in_file(&reg_path))?;
    // the shape is valid from here: L is a positive multiple of 8
    let bpc = regs.length / 8;
    if regs.ECLEN != bpc - 1 {
        return Err(bad(format!("field ECLEN is {}; expected L/8 - 1 = {} for length {}", regs.ECLEN, bpc - 1, regs.length)));
    }
    if regs.bytes_per_channel != bpc {
        return Err(bad(format!("field bytes_per_channel is {}; expected L/8 = {bpc} for length {}", regs.bytes_per_channel, regs.length)));
    }
    let n_ch = codes.subpixels() * regs.taps;
    if regs.channel_count != n_ch {
        return Err(bad(format!(
            "field channel_count is {}; expected N·M = {n_ch} for block {}x{} and {} taps",
            regs.channel_count, regs.block[0], regs.block[1], regs.taps
        )));
    }
    if regs.bit_order != BIT_ORDER {
        return Err(bad(format!("field bit_order is {:?}; this reader takes only {BIT_ORDER:?}", regs.bit_order)));
    }
    if regs.combined_layout != LAYOUT {
        return Err(bad(format!("field combined_layout is {:?}; this reader takes only {LAYOUT:?}", regs.combined_layout)));
    }
    if regs.channels.len() != n_ch {
        return Err(bad(format!("field channels lists {} channels; expected N·M = {n_ch}", regs.channels.len())));
    }
    plain_name(&reg_path, "combined_file", &regs.combined_file)?;
    let comb_path = dir.join(&regs.combined_file);
    let combined = std::fs::read(&comb_path).map_err(|e| SensorError::io(&comb_path, e))?;
    if combined.len() != n_ch * bpc {
        return Err(SensorError::file(
            &comb_path,
            format!(
                "{} bytes; expected N·M·L/8 = {n_ch}·{bpc} = {} (channel-major, nothing after the last channel)",
                combined.len(),
                n_ch * bpc
            ),
        ));
    }
    let bw = regs.block[1];
    for (c, ch) in regs.channels.iter().enumerate() {
        let (n, tap) = (c / regs.taps, c % regs.taps);
        let expected = (c, n, n / bw, n % bw, tap, c * bpc);
        if (ch.channel, ch.subpixel, ch.row, ch.col, ch.tap, ch.offset) != expected {
            return Err(bad(format!(
                "field channels[{c}] is channel {} (subpixel {}, row {}, col {}, tap {}, offset {}); expected channel {c} (subpixel {n}, row {}, col {}, tap {tap}, offset {}) as the channel-major layout places it",
                ch.channel,
                ch.subpixel,
                ch.row,
                ch.col,
                ch.tap,
                ch.offset,
                n / bw,
                n % bw,
                c * bpc
            )));
        }
        plain_name(&reg_path, &format!("channels[{c}].file"), &ch.file)?;
        let p = dir.join(&ch.file);
        let bytes = std::fs::read(&p).map_err(|e| SensorError::io(&p, e))?;
        if bytes.len() != bpc {
            return Err(SensorError::file(&p, format!("{} bytes, expected L/8 = {bpc}", bytes.len())));
        }
        if combined[c * bpc..(c + 1) * bpc] != bytes[..] {
            return Err(SensorError::file(&comb_path, format!("bytes of channel {c} differ from {}", ch.file)));
        }
        for (l, b) in unpack_channel(&bytes).into_iter().enumerate() {
            codes.set(n, tap, l, b == 1);
        }
    }
    codes.ensure_feasible().map_err(|e| e.in_file(&reg_path))?;
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

    /// Every field of `registers.json` is honoured or refused, and the combined image holds
    /// exactly the channels; a re-export replaces the directory whole.
    #[test]
    fn import_refuses_every_field_it_does_not_honour() {
        let dir = crate::npy::tests::tempdir();
        let shape = CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        let g = random_codes(shape, 607e6, Constraints { tap: true, hamming: None, window: None }, 1).unwrap();
        export(&g, &dir).unwrap();
        let text = std::fs::read_to_string(dir.join("registers.json")).unwrap();
        let cases: Vec<(String, &str)> = vec![
            (text.replacen("\"ECLEN\": 1", "\"ECLEN\": 7", 1), "ECLEN"),
            (text.replacen("\"length\": 16", "\"length\": 0", 1), "length"),
            (text.replacen("\"bytes_per_channel\": 2", "\"bytes_per_channel\": 3", 1), "bytes_per_channel"),
            (text.replacen("\"channel_count\": 16", "\"channel_count\": 15", 1), "channel_count"),
            (text.replacen("msb-first", "lsb-first", 1), "bit_order"),
            (text.replacen("channel-major", "tap-major", 1), "combined_layout"),
            (text.replacen("\"codes.bin\"", "\"../codes.bin\"", 1), "combined_file"),
            (text.replacen("\"tap\": 1", "\"tap\": 2", 1), "channels[1]"),
            (text.replacen("\"ch03.bin\"", "\"/etc/passwd\"", 1), "channels[3].file"),
            (text.replacen("{", "{\n  \"extra\": 1,", 1), "unknown field"),
        ];
        for (bad, field) in cases {
            std::fs::write(dir.join("registers.json"), &bad).unwrap();
            let e = import(&dir).unwrap_err().to_string();
            assert!(e.contains("registers.json") && e.contains(field), "{field}: {e}");
        }
        std::fs::write(dir.join("registers.json"), &text).unwrap();
        // trailing bytes after the last channel
        let mut comb = std::fs::read(dir.join("codes.bin")).unwrap();
        comb.push(0);
        std::fs::write(dir.join("codes.bin"), &comb).unwrap();
        let e = import(&dir).unwrap_err().to_string();
        assert!(e.contains("codes.bin") && e.contains("nothing after the last channel"), "{e}");
        comb.pop();
        // codes that break their declared constraints (two taps open at once), consistently
        // in the channel file and the image
        comb[0] = 0xff;
        comb[2] = 0xff;
        std::fs::write(dir.join("codes.bin"), &comb).unwrap();
        std::fs::write(dir.join("ch00.bin"), &comb[0..2]).unwrap();
        std::fs::write(dir.join("ch01.bin"), &comb[2..4]).unwrap();
        let e = import(&dir).unwrap_err().to_string();
        assert!(e.contains("registers.json") && e.contains("violate"), "{e}");
        // a re-export replaces the directory whole: a smaller code set leaves no extra channel
        let small = random_codes(CodeShape { bh: 1, bw: 1, taps: 2, length: 8, drain: false }, 607e6, Constraints::default(), 2).unwrap();
        export(&small, &dir).unwrap();
        let mut names: Vec<String> =
            std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        names.sort();
        assert_eq!(names, ["ch00.bin", "ch01.bin", "codes.bin", "registers.json"]);
        assert_eq!(import(&dir).unwrap().digest(), small.digest());
    }
}
