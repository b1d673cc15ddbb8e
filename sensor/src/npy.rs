//! `.npy` I/O and atomic file writes.
//!
//! Reads NumPy `.npy` files (format versions 1–3) of any real dtype — `f4`, `f8`, signed and
//! unsigned integers of 1–8 bytes, `b1`, either byte order, C or Fortran order — into `f32`
//! arrays, and writes little-endian `f32` arrays (version 1.0, 64-byte aligned header).
//! Every write goes to a temporary file in the target directory and is renamed into place,
//! so a crash or an error never leaves a half-written output.

use crate::error::{Result, SensorError};
use ndarray::{ArrayD, ArrayView, Dimension, IxDyn, ShapeBuilder};
use std::io::Write;
use std::path::Path;

const MAGIC: &[u8] = b"\x93NUMPY";

/// Write a file atomically: `fill` writes into a temporary file next to `path`, which is then
/// renamed over `path`. On error the temporary file is removed and `path` is untouched.
pub fn atomic_write<F>(path: &Path, fill: F) -> Result<()>
where
    F: FnOnce(&mut dyn Write) -> std::io::Result<()>,
{
    let dir = crate::output::parent_of(path);
    if !dir.is_dir() {
        std::fs::create_dir_all(&dir).map_err(|e| SensorError::io(&dir, e))?;
    }
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let result = (|| -> std::io::Result<()> {
        let file = std::fs::File::create(&tmp)?;
        let mut w = std::io::BufWriter::new(file);
        fill(&mut w)?;
        w.flush()?;
        w.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(SensorError::io(path, e));
    }
    Ok(())
}

/// Write `bytes` to `path` atomically.
pub fn write_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    atomic_write(path, |w| w.write_all(bytes))
}

/// Write an `f32` array as `.npy` (little-endian `<f4`, C order), atomically.
pub fn write_npy<D: Dimension>(path: &Path, a: &ArrayView<'_, f32, D>) -> Result<()> {
    let header = f32_header(a.shape()).map_err(|e| SensorError::file(path, e))?;
    atomic_write(path, |w| {
        w.write_all(&header)?;
        let mut buf = Vec::with_capacity(a.len() * 4);
        for v in a.iter() {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        w.write_all(&buf)
    })
}

/// Read a `.npy` file of any real dtype into an `f32` array in C order.
pub fn read_npy(path: &Path) -> Result<ArrayD<f32>> {
    let bytes = std::fs::read(path).map_err(|e| SensorError::io(path, e))?;
    parse_npy(&bytes).map_err(|msg| SensorError::file(path, msg))
}

/// Parse `.npy` bytes; the error is a message without the file name.
pub fn parse_npy(bytes: &[u8]) -> std::result::Result<ArrayD<f32>, String> {
    let h = parse_header(bytes)?;
    if h.shape.contains(&0) {
        return Err(format!("shape {:?} has an axis of length 0, expected a non-empty array", h.shape));
    }
    let count = h.count();
    let data = &bytes[h.data_offset..];
    if data.len() < count * h.size {
        return Err(format!(
            "npy data truncated: shape {:?} of {} needs {} bytes, file has {}",
            h.shape,
            h.descr,
            count * h.size,
            data.len()
        ));
    }
    let mut values = vec![0f32; count];
    h.decode_into(&data[..count * h.size], &mut values);
    let arr = if h.fortran {
        ArrayD::from_shape_vec(IxDyn(&h.shape).f(), values).map_err(|e| e.to_string())?
    } else {
        ArrayD::from_shape_vec(IxDyn(&h.shape), values).map_err(|e| e.to_string())?
    };
    Ok(if arr.is_standard_layout() { arr } else { arr.as_standard_layout().into_owned() })
}

/// A parsed `.npy` header.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyHeader {
    /// The dtype as written, e.g. `<f4`.
    pub descr: String,
    little: bool,
    kind: char,
    /// Bytes per value.
    pub size: usize,
    pub fortran: bool,
    pub shape: Vec<usize>,
    /// Where the data starts.
    pub data_offset: usize,
}

impl NpyHeader {
    /// Values in the array.
    pub fn count(&self) -> usize {
        self.shape.iter().product()
    }

    /// Decode `bytes` (whole values of this dtype) into `out` as f32.
    pub fn decode_into(&self, bytes: &[u8], out: &mut [f32]) {
        for (chunk, o) in bytes.chunks_exact(self.size).zip(out.iter_mut()) {
            let mut b = [0u8; 8];
            b[..self.size].copy_from_slice(chunk);
            if !self.little && self.size > 1 {
                b[..self.size].reverse();
            }
            *o = decode(self.kind, self.size, b);
        }
    }
}

/// Parse the header at the start of `bytes` (which need hold only the header).
pub fn parse_header(bytes: &[u8]) -> std::result::Result<NpyHeader, String> {
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err("not a .npy file (missing the \\x93NUMPY magic)".into());
    }
    let major = bytes[6];
    let (hlen, start) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated .npy header".into());
            }
            (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
        }
        v => return Err(format!("unsupported .npy format version {v} (expected 1, 2 or 3)")),
    };
    let header = bytes.get(start..start + hlen).ok_or("truncated .npy header")?;
    let header = std::str::from_utf8(header).map_err(|_| "npy header is not text")?;
    let descr = dict_value(header, "descr").ok_or("npy header has no 'descr'")?;
    let descr = descr.trim_matches(|c| c == '\'' || c == '"');
    let fortran = dict_value(header, "fortran_order").ok_or("npy header has no 'fortran_order'")?.starts_with("True");
    let shape_s = dict_value(header, "shape").ok_or("npy header has no 'shape'")?;
    let shape: Vec<usize> = shape_s
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().map_err(|_| format!("bad shape entry {s:?} in npy header")))
        .collect::<std::result::Result<_, _>>()?;
    let (little, kind, size) = parse_descr(descr)?;
    shape.iter().try_fold(size, |acc, &d| acc.checked_mul(d)).ok_or_else(|| format!("shape {shape:?} is too large"))?;
    Ok(NpyHeader { descr: descr.to_string(), little, kind, size, fortran, shape, data_offset: start + hlen })
}

/// The `.npy` header of a little-endian `f32` C-order array of `shape` (version 1.0, padded
/// to 64 bytes).
pub fn f32_header(shape: &[usize]) -> std::result::Result<Vec<u8>, String> {
    let shape_str = match shape.len() {
        1 => format!("({},)", shape[0]),
        _ => format!("({})", shape.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", ")),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_str}, }}");
    // Total header (magic 6 + version 2 + len 2 + dict + '\n') is a multiple of 64.
    let unpadded = MAGIC.len() + 2 + 2 + header.len() + 1;
    header.push_str(&" ".repeat((64 - unpadded % 64) % 64));
    header.push('\n');
    let hlen = u16::try_from(header.len()).map_err(|_| "npy header too long".to_string())?;
    let mut out = Vec::with_capacity(10 + header.len());
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[1, 0]);
    out.extend_from_slice(&hlen.to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    Ok(out)
}

fn dict_value<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let k1 = format!("'{key}'");
    let k2 = format!("\"{key}\"");
    let pos = header.find(&k1).or_else(|| header.find(&k2))? + k1.len();
    let rest = header[pos..].trim_start().strip_prefix(':')?.trim_start();
    if rest.starts_with('(') {
        let end = rest.find(')')?;
        Some(&rest[..=end])
    } else {
        let end = rest.find([',', '}']).unwrap_or(rest.len());
        Some(rest[..end].trim())
    }
}

fn parse_descr(d: &str) -> std::result::Result<(bool, char, usize), String> {
    const EXPECTED: &str = "expected float32/float64, an integer type or bool";
    if d.starts_with('[') || d.starts_with('(') {
        return Err(format!("unsupported structured dtype (record fields), {EXPECTED}"));
    }
    if d.ends_with('O') {
        return Err(format!("unsupported dtype {d:?} (Python objects, a pickle), {EXPECTED}"));
    }
    let mut chars = d.chars();
    let order = chars.next().ok_or("empty dtype")?;
    let little = match order {
        '<' | '|' | '=' => true,
        '>' => false,
        _ => return Err(format!("unsupported dtype {d:?}")),
    };
    let kind = chars.next().ok_or("empty dtype")?;
    let size: usize = chars.as_str().parse().map_err(|_| format!("unsupported dtype {d:?}"))?;
    let ok = matches!((kind, size), ('f', 4) | ('f', 8) | ('i', 1 | 2 | 4 | 8) | ('u', 1 | 2 | 4 | 8) | ('b', 1));
    if !ok {
        return Err(format!("unsupported dtype {d:?} (expected float32/float64, an integer type or bool)"));
    }
    Ok((little, kind, size))
}

fn decode(kind: char, size: usize, b: [u8; 8]) -> f32 {
    match (kind, size) {
        ('f', 4) => f32::from_le_bytes([b[0], b[1], b[2], b[3]]),
        ('f', 8) => f64::from_le_bytes(b) as f32,
        ('i', 1) => b[0] as i8 as f32,
        ('i', 2) => i16::from_le_bytes([b[0], b[1]]) as f32,
        ('i', 4) => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        ('i', 8) => i64::from_le_bytes(b) as f32,
        ('u', 1) | ('b', 1) => b[0] as f32,
        ('u', 2) => u16::from_le_bytes([b[0], b[1]]) as f32,
        ('u', 4) => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f32,
        _ => u64::from_le_bytes(b) as f32,
    }
}

/// The largest magnitude of a cube's or a tap image's value: the sums the decoders and the
/// sensor take over thousands of them stay finite in `f32` (whose range ends at 3.4e38).
pub const MAX_VALUE: f32 = 1e30;

/// The logical (row-major) position `flat` of an array of `shape` as an index.
fn unravel(flat: usize, shape: &[usize]) -> Vec<usize> {
    let mut index = vec![0; shape.len()];
    let mut rest = flat;
    for (i, &n) in shape.iter().enumerate().rev() {
        index[i] = rest % n.max(1);
        rest /= n.max(1);
    }
    index
}

/// Check that every value of `a` is finite; the error names `what` and the first bad index.
pub fn ensure_finite<D: Dimension>(a: &ArrayView<'_, f32, D>, what: &str) -> Result<()> {
    if let Some((flat, v)) = a.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(SensorError::NonFinite { what: what.to_string(), index: unravel(flat, a.shape()), value: *v });
    }
    Ok(())
}

/// [`ensure_finite`], and every value within ±[`MAX_VALUE`] (a cube's, a tap image's).
pub fn ensure_usable<D: Dimension>(a: &ArrayView<'_, f32, D>, what: &str) -> Result<()> {
    ensure_finite(a, what)?;
    if let Some((flat, v)) = a.iter().enumerate().find(|(_, v)| v.abs() > MAX_VALUE) {
        return Err(SensorError::TooLarge { what: what.to_string(), index: unravel(flat, a.shape()), value: *v });
    }
    Ok(())
}

/// Read a transient cube `[T, H, W]` (or a batch `[B, T, H, W]` when `allow_batch`), checking
/// rank and finiteness. The error names the file.
pub fn read_cube(path: &Path, allow_batch: bool) -> Result<ArrayD<f32>> {
    let a = read_npy(path)?;
    let ok = a.ndim() == 3 || (allow_batch && a.ndim() == 4);
    if !ok {
        let expected = if allow_batch { "rank 3 [T, H, W] or rank 4 [B, T, H, W]" } else { "rank 3 [T, H, W]" };
        return Err(SensorError::file(path, format!("array has shape {:?} (rank {}), expected {expected}", a.shape(), a.ndim())));
    }
    ensure_usable(&a.view(), "cube").map_err(|e| e.in_file(path))?;
    Ok(a)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use ndarray::Array3;
    use std::path::PathBuf;

    #[test]
    fn roundtrip_f32() {
        let dir = tempdir();
        let p = dir.join("a.npy");
        let a = Array3::from_shape_fn((2, 3, 4), |(i, j, k)| (i * 100 + j * 10 + k) as f32 - 7.5);
        write_npy(&p, &a.view()).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!((bytes[8] as usize + 10) % 64, 0, "header aligned to 64 bytes");
        let b = read_npy(&p).unwrap();
        assert_eq!(b.shape(), &[2, 3, 4]);
        assert_eq!(b.into_dimensionality::<ndarray::Ix3>().unwrap(), a);
    }

    #[test]
    fn reads_f8_int_and_fortran() {
        // Hand-built headers as numpy writes them.
        let mk = |descr: &str, fortran: bool, shape: &str, data: &[u8]| {
            let mut h = format!("{{'descr': '{descr}', 'fortran_order': {}, 'shape': {shape}, }}", if fortran { "True" } else { "False" });
            h.push('\n');
            let mut v = MAGIC.to_vec();
            v.extend_from_slice(&[1, 0]);
            v.extend_from_slice(&(h.len() as u16).to_le_bytes());
            v.extend_from_slice(h.as_bytes());
            v.extend_from_slice(data);
            v
        };
        let f8: Vec<u8> = [1.5f64, -2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let a = parse_npy(&mk("<f8", false, "(2,)", &f8)).unwrap();
        assert_eq!(a.as_slice().unwrap(), &[1.5, -2.0]);
        let u2: Vec<u8> = [1u16, 2, 3, 4, 5, 6].iter().flat_map(|v| v.to_be_bytes()).collect();
        // Fortran order [2, 3]: memory holds columns.
        let a = parse_npy(&mk(">u2", true, "(2, 3)", &u2)).unwrap();
        assert_eq!(a.as_slice().unwrap(), &[1.0, 3.0, 5.0, 2.0, 4.0, 6.0]);
        assert!(parse_npy(&mk("<c8", false, "(1,)", &[0; 8])).unwrap_err().contains("unsupported dtype"));
        assert!(parse_npy(&mk("<f4", false, "(4,)", &[0; 8])).unwrap_err().contains("truncated"));
        assert!(parse_npy(b"hello world").unwrap_err().contains("magic"));
    }

    pub(crate) fn tempdir() -> PathBuf {
        let d = std::env::temp_dir().join(format!(
            "tcsense-test-{}-{}",
            std::process::id(),
            std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos()
        ));
        std::fs::create_dir_all(&d).unwrap();
        d
    }
}
