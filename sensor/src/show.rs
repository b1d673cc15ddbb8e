//! A plain RGB canvas written as PNG (the dataset montage of `dataset show`). Figures with
//! text — titles, axes, legends, colour bars — are drawn by `tcsense_infer::figures`.

use crate::error::{Result, SensorError};
use crate::npy::atomic_write;
use ndarray::{Array2, ArrayView2};
use std::path::Path;

/// Read a single-channel grayscale PNG (8 or 16 bit) as its raw values (`[H, W]`): what a
/// sensor's software writes for tap images and depth maps.
pub fn read_gray_png(path: &Path) -> Result<Array2<f32>> {
    let err = |msg: String| SensorError::file(path, msg);
    let f = std::fs::File::open(path).map_err(|e| SensorError::io(path, e))?;
    let mut reader = png::Decoder::new(std::io::BufReader::new(f)).read_info().map_err(|e| err(format!("cannot decode PNG: {e}")))?;
    let mut buf = vec![0u8; reader.output_buffer_size().ok_or_else(|| err("PNG too large".into()))?];
    let info = reader.next_frame(&mut buf).map_err(|e| err(format!("cannot decode PNG: {e}")))?;
    if info.color_type != png::ColorType::Grayscale {
        return Err(err(format!("PNG colour type {:?}, expected single-channel grayscale", info.color_type)));
    }
    let (w, h) = (info.width as usize, info.height as usize);
    let vals: Vec<f32> = match info.bit_depth {
        png::BitDepth::Sixteen => (0..h * w)
            .map(|i| {
                u16::from_be_bytes([buf[(i / w) * info.line_size + (i % w) * 2], buf[(i / w) * info.line_size + (i % w) * 2 + 1]]) as f32
            })
            .collect(),
        png::BitDepth::Eight => (0..h * w).map(|i| buf[(i / w) * info.line_size + i % w] as f32).collect(),
        d => return Err(err(format!("PNG bit depth {d:?}, expected 8 or 16"))),
    };
    Array2::from_shape_vec((h, w), vals).map_err(|e| err(e.to_string()))
}

/// Write `[H, W]` values as a 16-bit grayscale PNG, rounded and clamped to `0..=65535`
/// (atomically).
pub fn write_gray_png16(path: &Path, values: &ArrayView2<'_, f32>) -> Result<()> {
    let (h, w) = values.dim();
    let data: Vec<u8> = values.iter().flat_map(|&v| (v.round().clamp(0.0, 65535.0) as u16).to_be_bytes()).collect();
    atomic_write(path, |out| {
        let mut enc = png::Encoder::new(out, w as u32, h as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Sixteen);
        let mut writer = enc.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(&data).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)
    })
}

/// An RGB image in memory.
pub struct Canvas {
    pub width: usize,
    pub height: usize,
    pub rgb: Vec<u8>,
}

impl Canvas {
    /// A canvas filled with `bg`.
    pub fn new(width: usize, height: usize, bg: [u8; 3]) -> Self {
        let mut rgb = Vec::with_capacity(width * height * 3);
        for _ in 0..width * height {
            rgb.extend_from_slice(&bg);
        }
        Canvas { width, height, rgb }
    }

    /// Fill a rectangle (clipped to the canvas).
    pub fn rect(&mut self, x: usize, y: usize, w: usize, h: usize, c: [u8; 3]) {
        for yy in y..(y + h).min(self.height) {
            for xx in x..(x + w).min(self.width) {
                let i = (yy * self.width + xx) * 3;
                self.rgb[i..i + 3].copy_from_slice(&c);
            }
        }
    }

    /// A 2-pixel-wide straight line from `(x0, y0)` to `(x1, y1)` (Bresenham; clipped).
    pub fn line(&mut self, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: [u8; 3]) {
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        loop {
            if x >= 0 && y >= 0 {
                self.rect(x as usize, y as usize, 2, 2, c);
            }
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// Write as an 8-bit RGB PNG, atomically.
    pub fn save_png(&self, path: &Path) -> Result<()> {
        let (w, h) = (self.width as u32, self.height as u32);
        atomic_write(path, |out| {
            let mut enc = png::Encoder::new(out, w, h);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            let mut writer = enc.write_header().map_err(std::io::Error::other)?;
            writer.write_image_data(&self.rgb).map_err(std::io::Error::other)?;
            writer.finish().map_err(std::io::Error::other)
        })
        .map_err(|e| match e {
            SensorError::Io { path, cause } => SensorError::file(path, format!("cannot write PNG: {cause}")),
            e => e,
        })
    }
}
