//! A minimal line chart for sweeps: one polyline with square markers per series, light grid
//! lines at every x value and at every decade when `log_y`. Values go to a CSV next to it,
//! so the picture carries no text.

use tcsense_sensor::show::Canvas;
use crate::Result;

const COLOURS: [[u8; 3]; 6] = [[31, 119, 180], [214, 39, 40], [44, 160, 44], [255, 127, 14], [148, 103, 189], [0, 0, 0]];

/// Draw `series` (name, points `(x, y)`) to a PNG; `y` on a log scale with `log_y`.
pub fn line_chart(path: &std::path::Path, series: &[(String, Vec<(f64, f64)>)], log_y: bool) -> Result<()> {
    let (w, h, pad) = (640usize, 400usize, 30usize);
    let mut cv = Canvas::new(w, h, [255, 255, 255]);
    let ty = |y: f64| if log_y { y.max(1e-300).log10() } else { y };
    let pts: Vec<(f64, f64)> = series.iter().flat_map(|s| s.1.iter().map(|&(x, y)| (x, ty(y)))).filter(|p| p.1.is_finite()).collect();
    if pts.is_empty() {
        return Ok(cv.save_png(path)?);
    }
    let (x0, x1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.0), a.1.max(p.0)));
    let (mut y0, mut y1) = pts.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |a, p| (a.0.min(p.1), a.1.max(p.1)));
    if log_y {
        y0 = y0.floor();
        y1 = y1.ceil().max(y0 + 1.0);
    } else if y1 <= y0 {
        y1 = y0 + 1.0;
    }
    let xs = if x1 > x0 { x1 - x0 } else { 1.0 };
    let px = |x: f64| pad + ((x - x0) / xs * (w - 2 * pad) as f64) as usize;
    let py = |y: f64| h - pad - ((y - y0) / (y1 - y0) * (h - 2 * pad) as f64) as usize;
    // grid
    for p in &pts {
        cv.rect(px(p.0), pad, 1, h - 2 * pad, [225, 225, 225]);
    }
    if log_y {
        let mut d = y0;
        while d <= y1 + 1e-9 {
            cv.rect(pad, py(d), w - 2 * pad, 1, [200, 200, 200]);
            d += 1.0;
        }
    }
    cv.rect(pad, h - pad, w - 2 * pad, 1, [0, 0, 0]);
    cv.rect(pad, pad, 1, h - 2 * pad, [0, 0, 0]);
    for (si, (_, s)) in series.iter().enumerate() {
        let col = COLOURS[si % COLOURS.len()];
        let sp: Vec<(usize, usize)> = s.iter().filter(|p| ty(p.1).is_finite()).map(|&(x, y)| (px(x), py(ty(y)))).collect();
        for win in sp.windows(2) {
            cv.line((win[0].0 as i64, win[0].1 as i64), (win[1].0 as i64, win[1].1 as i64), col);
        }
        for &(x, y) in &sp {
            cv.rect(x.saturating_sub(3), y.saturating_sub(3), 7, 7, col);
        }
    }
    Ok(cv.save_png(path)?)
}
