//! A picture of a code set, like the paper's Fig. 12: one row per channel (grouped by
//! subpixel, taps in order), one column per mask; a cell is filled with its tap's colour
//! when on. A strip below shows the Hamming distance of each transition `l → l+1` (bar
//! height ∝ bits changed), and masks involved in a violation are marked red on top.

use crate::codes::Codes;
use crate::error::{Result, SensorError};
use crate::npy::atomic_write;
use std::path::Path;

const TAP_COLOURS: [[u8; 3]; 8] = [
    [31, 119, 180],
    [255, 127, 14],
    [44, 160, 44],
    [148, 103, 189],
    [140, 86, 75],
    [227, 119, 194],
    [127, 127, 127],
    [23, 190, 207],
];

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
            SensorError::Io { path, source } => SensorError::file(path, format!("cannot write PNG: {source}")),
            e => e,
        })
    }
}

/// Render codes to a canvas (`cell` pixels per bit).
pub fn render(codes: &Codes, cell: usize) -> Canvas {
    let (n_sub, taps, len) = (codes.subpixels(), codes.taps(), codes.length());
    let gap = cell.max(2) / 2;
    let margin = cell;
    let strip = 4 * cell;
    let grid_h = n_sub * taps * cell + (n_sub - 1) * gap;
    let width = 2 * margin + len * cell;
    let height = margin + cell / 2 + gap + grid_h + gap + strip + margin;
    let mut cv = Canvas::new(width, height, [255, 255, 255]);
    // violation markers
    let bad: Vec<usize> = codes.violations().iter().map(|v| v.mask).collect();
    for &l in &bad {
        cv.rect(margin + l * cell, margin, cell, cell / 2, [214, 39, 40]);
    }
    let top = margin + cell / 2 + gap;
    for n in 0..n_sub {
        for m in 0..taps {
            let y = top + (n * taps + m) * cell + n * gap;
            // light background row
            cv.rect(margin, y, len * cell, cell, if m % 2 == 0 { [242, 242, 242] } else { [232, 232, 232] });
            for l in 0..len {
                if codes.get(n, m, l) {
                    cv.rect(margin + l * cell, y + 1, cell.saturating_sub(1).max(1), cell.saturating_sub(2).max(1), TAP_COLOURS[m % 8]);
                }
            }
        }
    }
    // Hamming strip
    let base = top + grid_h + gap;
    let max_h = (0..len).map(|l| codes.hamming_at(l)).max().unwrap_or(0).max(1);
    cv.rect(margin, base + strip - 1, len * cell, 1, [0, 0, 0]);
    for l in 0..len {
        let hd = codes.hamming_at(l);
        let bar = hd * (strip - 2) / max_h;
        cv.rect(margin + l * cell + cell / 2, base + strip - 1 - bar, cell.max(2) / 2, bar, [60, 60, 60]);
    }
    cv
}

/// Render codes to a PNG file.
pub fn save_png(codes: &Codes, path: &Path) -> Result<()> {
    let cell = if codes.length() > 128 { 4 } else { 10 };
    render(codes, cell).save_png(path)
}
