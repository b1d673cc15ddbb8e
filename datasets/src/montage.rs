//! `dataset show`: a montage of one item — intensity, depth (first and second bounce) or
//! lifetime map, and the waveforms of a few pixels — as a PNG.

use crate::error::Result;
use crate::store::{Dataset, Kind};
use ndarray::{ArrayView2, ArrayView3, Ix2, Ix3};
use std::path::Path;
use tcsense_sensor::show::Canvas;

const WAVE_COLOURS: [[u8; 3]; 4] = [[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40]];

/// A perceptually ordered colour map (dark blue → yellow) for `v ∈ [0, 1]`.
pub fn colormap(v: f32) -> [u8; 3] {
    let stops: [[f32; 3]; 5] = [[68., 1., 84.], [59., 82., 139.], [33., 145., 140.], [94., 201., 98.], [253., 231., 37.]];
    let v = v.clamp(0.0, 1.0) * 4.0;
    let i = (v.floor() as usize).min(3);
    let f = v - i as f32;
    std::array::from_fn(|k| (stops[i][k] * (1.0 - f) + stops[i + 1][k] * f) as u8)
}

fn draw_map(cv: &mut Canvas, x0: usize, y0: usize, scale: usize, map: &ArrayView2<'_, f32>, gray: bool) {
    let finite: Vec<f32> = map.iter().copied().filter(|v| v.is_finite()).collect();
    let lo = finite.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = finite.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = if hi > lo { hi - lo } else { 1.0 };
    for ((r, c), &v) in map.indexed_iter() {
        let col = if !v.is_finite() {
            [0, 0, 0]
        } else if gray {
            let g = (255.0 * (v - lo.min(0.0)) / (hi - lo.min(0.0)).max(1e-12)) as u8;
            [g, g, g]
        } else {
            colormap((v - lo) / span)
        };
        cv.rect(x0 + c * scale, y0 + r * scale, scale, scale, col);
    }
}

fn draw_waves(cv: &mut Canvas, x0: usize, y0: usize, w: usize, h: usize, x: &ArrayView3<'_, f32>, pixels: &[(usize, usize)]) {
    cv.rect(x0, y0, w, h, [250, 250, 250]);
    cv.rect(x0, y0 + h - 1, w, 1, [0, 0, 0]);
    cv.rect(x0, y0, 1, h, [0, 0, 0]);
    let t = x.dim().0;
    let peak = pixels.iter().flat_map(|&(r, c)| (0..t).map(move |j| x[(j, r, c)])).fold(1e-12f32, f32::max);
    for (k, &(r, c)) in pixels.iter().enumerate() {
        let pt = |j: usize| {
            let px = x0 as i64 + 2 + (j as i64 * (w as i64 - 4)) / (t.max(2) as i64 - 1);
            let py = (y0 + h) as i64 - 2 - ((x[(j, r, c)] / peak) * (h as f32 - 4.0)) as i64;
            (px, py)
        };
        for j in 1..t {
            cv.line(pt(j - 1), pt(j), WAVE_COLOURS[k % 4]);
        }
    }
}

/// Write a montage PNG of item `index` of `split`.
pub fn montage(ds: &Dataset, split: &str, index: usize, out: &Path) -> Result<()> {
    let x = ds.item(split, index, "x")?.into_dimensionality::<Ix3>().map_err(|e| crate::error::invalid("x", "", e.to_string()))?;
    let (_, h, w) = x.dim();
    let scale = (192 / h.max(w)).max(1);
    let (tw, th) = (w * scale, h * scale);
    let pad = 8;
    let intensity = ds
        .item(split, index, "intensity")?
        .into_dimensionality::<Ix2>()
        .map_err(|e| crate::error::invalid("intensity", "", e.to_string()))?;
    let mut maps: Vec<(ndarray::Array2<f32>, bool)> = vec![(intensity, true)];
    match ds.manifest.kind {
        Kind::Flim => {
            let lt = ds
                .item(split, index, "lifetime")?
                .into_dimensionality::<Ix2>()
                .map_err(|e| crate::error::invalid("lifetime", "", e.to_string()))?;
            maps.push((lt, false));
        }
        _ => {
            if ds.manifest.fields.contains_key("depth") {
                let d = ds
                    .item(split, index, "depth")?
                    .into_dimensionality::<Ix3>()
                    .map_err(|e| crate::error::invalid("depth", "", e.to_string()))?;
                for b in 0..d.dim().0 {
                    maps.push((d.index_axis(ndarray::Axis(0), b).to_owned(), false));
                }
            }
        }
    }
    let wave_w = 2 * tw;
    let width = pad + maps.len() * (tw + pad) + wave_w + pad;
    let height = th + 2 * pad;
    let mut cv = Canvas::new(width, height, [255, 255, 255]);
    for (k, (m, gray)) in maps.iter().enumerate() {
        draw_map(&mut cv, pad + k * (tw + pad), pad, scale, &m.view(), *gray);
    }
    // waveforms at four pixels spread over the frame, marked on the intensity image
    let pixels = [(h / 4, w / 4), (h / 4, 3 * w / 4), (3 * h / 4, w / 4), (3 * h / 4, 3 * w / 4)];
    for (k, &(r, c)) in pixels.iter().enumerate() {
        cv.rect(pad + c * scale, pad + r * scale, scale.max(3), scale.max(3), WAVE_COLOURS[k]);
    }
    draw_waves(&mut cv, pad + maps.len() * (tw + pad), pad, wave_w, th, &x.view(), &pixels);
    Ok(cv.save_png(out)?)
}
