//! Figures a person can read without the source: a title, axes with labelled ticks and
//! units, a legend, and a colour bar with units on every map.
//!
//! Drawn with `plotters` into an RGB buffer with the bundled DejaVu Sans (`infer/assets/`, its
//! licence beside it: no system font is needed) and written as PNG atomically.

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;
use std::path::Path;
use std::sync::Once;
use tcsense_sensor::npy::atomic_write;
use tcsense_sensor::Codes;

use crate::{InferError, Result};

const FONT: &str = "sans-serif";
static REGISTER: Once = Once::new();

fn register_font() {
    REGISTER.call_once(|| {
        // the bundled font is a valid TrueType file; a failure would show as missing text
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, include_bytes!("../assets/DejaVuSans.ttf"));
    });
}

/// Line colours: black first (the truth), then the tab10 palette.
pub const PALETTE: [RGBColor; 8] = [
    RGBColor(0, 0, 0),
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(255, 127, 14),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(23, 190, 207),
];
/// Tap colours of code figures (tab10).
const TAPS: [RGBColor; 8] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
    RGBColor(227, 119, 194),
    RGBColor(127, 127, 127),
    RGBColor(23, 190, 207),
];

/// Draw into a `w × h` RGB buffer with `draw`, then write it to `path` as PNG, atomically.
fn render(
    path: &Path,
    (w, h): (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> std::result::Result<(), String>,
) -> Result<()> {
    register_font();
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        draw(&root).map_err(|e| InferError::File { path: path.to_path_buf(), msg: format!("cannot draw the figure: {e}") })?;
        root.present().map_err(|e| InferError::File { path: path.to_path_buf(), msg: format!("cannot draw the figure: {e}") })?;
    }
    atomic_write(path, |out| {
        let mut enc = png::Encoder::new(out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(std::io::Error::other)?;
        writer.write_image_data(&buf).map_err(std::io::Error::other)?;
        writer.finish().map_err(std::io::Error::other)
    })?;
    Ok(())
}

fn err<E: std::fmt::Debug>(e: E) -> String {
    format!("{e:?}")
}

/// The legend of a chart: labels in `size` points on a white box at `position`.
fn legend<'a, CT: plotters::coord::CoordTranslate>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, CT>,
    size: u32,
    position: SeriesLabelPosition,
) -> std::result::Result<(), String> {
    chart
        .configure_series_labels()
        .label_font((FONT, size))
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .position(position)
        .draw()
        .map_err(err)
}

/// Each of `series` as a line with a dot at every point (colours from the palette's second
/// on), the points `keep` accepts, labelled for the legend.
fn marked_lines<'a, X, Y>(
    chart: &mut ChartContext<'a, BitMapBackend<'a>, Cartesian2d<X, Y>>,
    series: &[Series],
    keep: impl Fn(f64, f64) -> bool,
) -> std::result::Result<(), String>
where
    X: Ranged<ValueType = f64>,
    Y: Ranged<ValueType = f64>,
{
    for (i, s) in series.iter().enumerate() {
        let c = PALETTE[(i + 1) % PALETTE.len()];
        let pts: Vec<(f64, f64)> = s.points.iter().copied().filter(|&(x, y)| x.is_finite() && y.is_finite() && keep(x, y)).collect();
        chart.draw_series(pts.iter().map(|&p| Circle::new(p, 4, c.filled()))).map_err(err)?;
        chart
            .draw_series(LineSeries::new(pts, c.stroke_width(2)))
            .map_err(err)?
            .label(s.label.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
    }
    Ok(())
}

/// The extent `(x0, x1, y0, y1)` of the points of `series` that `keep` accepts (`x1 > x0`),
/// `empty` where there are none.
fn extent(series: &[Series], keep: impl Fn(f64, f64) -> bool, empty: (f64, f64, f64, f64)) -> (f64, f64, f64, f64) {
    let (mut x0, mut x1, mut y0, mut y1) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
    for &(x, y) in series.iter().flat_map(|s| s.points.iter()).filter(|&&(x, y)| x.is_finite() && y.is_finite() && keep(x, y)) {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if !x0.is_finite() {
        (x0, x1, y0, y1) = empty;
    }
    (x0, if x1 > x0 { x1 } else { x0 + 1.0 }, y0, y1)
}

/// A linear y range around `[y0, y1]` with 5 % room, or ±half of `max(|y0|, floor)` when
/// the values are constant.
fn padded(y0: f64, y1: f64, floor: f64) -> (f64, f64) {
    let pad = if y1 > y0 { 0.05 * (y1 - y0) } else { 0.5 * y0.abs().max(floor) };
    (y0 - pad, y1 + pad)
}

/// A logarithmic axis's range around `[lo, hi]` (both positive): whole decades, at least one.
fn decades(lo: f64, hi: f64) -> (f64, f64) {
    let (down, up) = (10f64.powf(lo.log10().floor()), 10f64.powf(hi.log10().ceil()));
    (down, up.max(down * 10.0))
}

/// One line of a chart.
#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    pub points: Vec<(f64, f64)>,
}

/// A line chart with a legend.
pub fn line_chart(path: &Path, title: &str, x_label: &str, y_label: &str, series: &[Series]) -> Result<()> {
    let (x0, x1, y0, y1) = extent(series, |_, _| true, (0.0, 1.0, 0.0, 1.0));
    let (y0, y1) = padded(y0, y1, 1.0);
    render(path, (900, 520), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, (FONT, 22))
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d(x0..x1, y0..y1)
            .map_err(err)?;
        chart.configure_mesh().x_desc(x_label).y_desc(y_label).label_style((FONT, 15)).axis_desc_style((FONT, 17)).draw().map_err(err)?;
        for (i, s) in series.iter().enumerate() {
            let c = PALETTE[i % PALETTE.len()];
            let pts: Vec<(f64, f64)> = s.points.iter().copied().filter(|(x, y)| x.is_finite() && y.is_finite()).collect();
            chart
                .draw_series(LineSeries::new(pts, c.stroke_width(2)))
                .map_err(err)?
                .label(s.label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
        }
        legend(&mut chart, 15, SeriesLabelPosition::UpperRight)?;
        Ok(())
    })
}

/// A line chart with a logarithmic y axis (values ≤ 0 are left out).
pub fn log_chart(path: &Path, title: &str, x_label: &str, y_label: &str, series: &[Series]) -> Result<()> {
    let (x0, x1, y0, y1) = extent(series, |_, y| y > 0.0, (0.0, 1.0, 1.0, 10.0));
    let (y0, y1) = (10f64.powf(y0.log10().floor()), 10f64.powf(y1.log10().ceil().max(y0.log10().floor() + 1.0)));
    render(path, (900, 520), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, (FONT, 22))
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(90)
            .build_cartesian_2d(x0..x1, (y0..y1).log_scale())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .y_label_formatter(&|v| format!("{v:.0e}"))
            .label_style((FONT, 15))
            .axis_desc_style((FONT, 17))
            .draw()
            .map_err(err)?;
        marked_lines(&mut chart, series, |_, y| y > 0.0)?;
        legend(&mut chart, 15, SeriesLabelPosition::UpperRight)?;
        Ok(())
    })
}

/// The photon-efficiency curve of decoders: on the left the median error against the light
/// (both axes logarithmic), with `bounds` (e.g. each code set's Cramér–Rao bound) dashed; on
/// the right the share within a tolerance (0–100 %) against the light. Series share their
/// labels and colours across the panels; points with a non-positive or non-finite value are
/// left out.
pub fn photon_curve(
    path: &Path,
    title: &str,
    x_label: &str,
    error_label: &str,
    share_label: &str,
    errors: &[Series],
    shares: &[Series],
    bounds: &[Series],
) -> Result<()> {
    let all: Vec<Series> = errors.iter().chain(bounds).cloned().collect();
    let (x0, x1, y0, y1) = extent(&all, |x, y| x > 0.0 && y > 0.0, (1.0, 10.0, 0.1, 10.0));
    let ((x0, x1), (y0, y1)) = (decades(x0, x1), decades(y0, y1));
    // the legend is a strip below both panels, three entries a line: the bounds (dashed, as
    // drawn on the left), then the decoders (their colours are the same in both panels)
    let bound_style = |k: usize| {
        let shade = (k.min(2) * 80) as u8;
        (RGBColor(shade, shade, shade).stroke_width(2), [(8, 6), (3, 4), (14, 4)][k.min(2)])
    };
    let entries = bounds.len() + errors.len().max(shares.len());
    // three entries a line where the labels fit (about 8 px a character), else two
    let longest = bounds.iter().chain(errors).chain(shares).map(|s| s.label.chars().count()).max().unwrap_or(0);
    let columns = if 40 + 8 * longest <= 450 { 3 } else { 2 };
    let legend_rows = entries.div_ceil(columns) as u32;
    let legend_h = 16 + 26 * legend_rows;
    render(path, (1400, 560 + legend_h), |root| {
        let (title_area, body) = root.split_vertically(40);
        title_area.titled(title, (FONT, 22)).map_err(err)?;
        let (body, legend_area) = body.split_vertically(520);
        let (left, right) = body.split_horizontally(700);
        let mut chart = ChartBuilder::on(&left)
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(error_label)
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| if *v >= 1.0 { format!("{v:.0}") } else { format!("{v}") })
            .label_style((FONT, 15))
            .axis_desc_style((FONT, 17))
            .draw()
            .map_err(err)?;
        for (k, b) in bounds.iter().enumerate() {
            let pts: Vec<(f64, f64)> =
                b.points.iter().copied().filter(|(x, y)| *x > 0.0 && *y > 0.0 && x.is_finite() && y.is_finite()).collect();
            let (style, (dash, gap)) = bound_style(k);
            chart.draw_series(DashedLineSeries::new(pts, dash, gap, style)).map_err(err)?;
        }
        marked_lines(&mut chart, errors, |x, y| x > 0.0 && y > 0.0)?;
        let mut chart = ChartBuilder::on(&right)
            .margin(12)
            .x_label_area_size(48)
            .y_label_area_size(70)
            .build_cartesian_2d((x0..x1).log_scale(), 0f64..100f64)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(share_label)
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| format!("{v:.0}"))
            .label_style((FONT, 15))
            .axis_desc_style((FONT, 17))
            .draw()
            .map_err(err)?;
        marked_lines(&mut chart, shares, |x, _| x > 0.0)?;
        // the strip: a sample of each line and its label
        let decoders = if errors.len() >= shares.len() { errors } else { shares };
        let font = (FONT, 15).into_font();
        for e in 0..entries {
            let (col, row) = ((e % columns) as i32, (e / columns) as i32);
            let (x, y) = (40 + col * (1350 / columns as i32), 14 + row * 26);
            if let Some(b) = bounds.get(e) {
                let (style, (dash, gap)) = bound_style(e);
                let mut at = x;
                while at < x + 30 {
                    legend_area.draw(&PathElement::new(vec![(at, y), ((at + dash).min(x + 30), y)], style)).map_err(err)?;
                    at += dash + gap;
                }
                legend_area.draw(&Text::new(b.label.clone(), (x + 40, y - 8), font.clone())).map_err(err)?;
            } else {
                let i = e - bounds.len();
                let c = PALETTE[(i + 1) % PALETTE.len()];
                legend_area.draw(&PathElement::new(vec![(x, y), (x + 30, y)], c.stroke_width(2))).map_err(err)?;
                legend_area.draw(&Circle::new((x + 15, y), 4, c.filled())).map_err(err)?;
                legend_area.draw(&Text::new(decoders[i].label.clone(), (x + 40, y - 8), font.clone())).map_err(err)?;
            }
        }
        Ok(())
    })
}

/// Speed against accuracy of decoders: one series per decoder, its points `(frames/s, error)`
/// at each light level in `levels`' order (both axes logarithmic), so that a decoder is a
/// vertical run of dots at its speed from its error in bright light to its error in dim light;
/// each dot is labelled with its level. Points with a non-positive or non-finite value are left
/// out.
pub fn speed_accuracy(path: &Path, title: &str, x_label: &str, y_label: &str, series: &[Series], levels: &[String]) -> Result<()> {
    let keep = |x: f64, y: f64| x > 0.0 && y > 0.0;
    let (x0, x1, y0, y1) = extent(series, keep, (1.0, 10.0, 0.1, 10.0));
    // a decade below the lowest error left free for the legend
    let ((x0, x1), (y0, y1)) = (decades(x0, x1), decades(y0, y1));
    let y0 = y0 / 10.0;
    render(path, (1000, 640), |root| {
        let (title_area, body) = root.split_vertically(40);
        title_area.titled(title, (FONT, 22)).map_err(err)?;
        let mut chart = ChartBuilder::on(&body)
            .margin(14)
            .x_label_area_size(48)
            .y_label_area_size(80)
            .build_cartesian_2d((x0..x1).log_scale(), (y0..y1).log_scale())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc(x_label)
            .y_desc(y_label)
            .x_label_formatter(&|v| if *v >= 1.0 { format!("{v:.0}") } else { format!("{v}") })
            .y_label_formatter(&|v| if *v >= 1.0 { format!("{v:.0}") } else { format!("{v}") })
            .label_style((FONT, 15))
            .axis_desc_style((FONT, 17))
            .draw()
            .map_err(err)?;
        marked_lines(&mut chart, series, keep)?;
        for (i, s) in series.iter().enumerate() {
            let c = PALETTE[(i + 1) % PALETTE.len()];
            let labelled = s.points.iter().zip(levels).filter(|((x, y), _)| x.is_finite() && y.is_finite() && keep(*x, *y));
            chart
                .draw_series(labelled.map(|(&(x, y), l)| Text::new(format!(" {l}"), (x, y), (FONT, 12).into_font().color(&c))))
                .map_err(err)?;
        }
        // fast and accurate is the lower right, seldom reached
        legend(&mut chart, 14, SeriesLabelPosition::LowerRight)?;
        Ok(())
    })
}

/// Waveforms at pixels, one panel per pixel and one line per cube (the first black: the
/// truth), like the paper's Figs. 18 and 20.
///
/// # Shapes
/// - `cubes`: `(name, [T, H, W])`; `pixels`: `(row, column)`
pub fn waveforms(
    path: &Path,
    cubes: &[(&str, ndarray::ArrayView3<'_, f32>)],
    pixels: &[(usize, usize)],
    bin_ns: Option<f64>,
) -> Result<()> {
    let panels = pixels.len().max(1);
    let x_label = match bin_ns {
        Some(b) => format!("time (ns, bins of {b:.3} ns)"),
        None => "time bin".to_string(),
    };
    let scale = bin_ns.unwrap_or(1.0);
    render(path, ((420 * panels) as u32 + 40, 460), |root| {
        let (title_area, body) = root.split_vertically(40);
        title_area.titled("Waveforms at chosen pixels", (FONT, 22)).map_err(err)?;
        for (area, &(r, c)) in body.split_evenly((1, panels)).iter().zip(pixels) {
            let t = cubes.first().map_or(1, |x| x.1.dim().0);
            let peak = cubes.iter().flat_map(|(_, x)| (0..x.dim().0).map(move |j| x[(j, r, c)])).fold(1e-12f32, f32::max) as f64;
            let low = cubes.iter().flat_map(|(_, x)| (0..x.dim().0).map(move |j| x[(j, r, c)])).fold(0f32, f32::min) as f64;
            let mut chart = ChartBuilder::on(area)
                .caption(format!("pixel (row {r}, column {c})"), (FONT, 16))
                .margin(8)
                .x_label_area_size(44)
                .y_label_area_size(70)
                .build_cartesian_2d(0.0..(t as f64 - 1.0).max(1.0) * scale, low..peak * 1.08)
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_desc(x_label.as_str())
                .y_desc("intensity (a.u.)")
                .label_style((FONT, 13))
                .axis_desc_style((FONT, 14))
                .draw()
                .map_err(err)?;
            for (i, (name, x)) in cubes.iter().enumerate() {
                let colour = PALETTE[i % PALETTE.len()];
                let pts: Vec<(f64, f64)> = (0..x.dim().0).map(|j| (j as f64 * scale, x[(j, r, c)] as f64)).collect();
                chart
                    .draw_series(LineSeries::new(pts, colour.stroke_width(2)))
                    .map_err(err)?
                    .label(name.to_string())
                    .legend(move |(px, py)| PathElement::new(vec![(px, py), (px + 20, py)], colour.stroke_width(2)));
            }
            legend(&mut chart, 13, SeriesLabelPosition::UpperRight)?;
        }
        Ok(())
    })
}

/// Training curves side by side: the training loss and a validation metric against the
/// epoch, one line per run.
pub fn training_curves(path: &Path, loss: &[Series], val: &[Series], val_label: &str) -> Result<()> {
    let bounds = |series: &[Series]| {
        let (x0, x1, y0, y1) = extent(series, |_, _| true, (0.0, 1.0, 0.0, 1.0));
        let (y0, y1) = padded(y0, y1, 1e-9);
        (x0, x1, y0, y1)
    };
    render(path, (1200, 500), |root| {
        let (title_area, body) = root.split_vertically(40);
        title_area.titled("Training curves", (FONT, 22)).map_err(err)?;
        let panels = body.split_evenly((1, 2));
        for (area, (series, y_label)) in panels.iter().zip([(loss, "training loss (batch mean)"), (val, val_label)]) {
            let (x0, x1, y0, y1) = bounds(series);
            let mut chart = ChartBuilder::on(area)
                .margin(10)
                .x_label_area_size(44)
                .y_label_area_size(80)
                .build_cartesian_2d(x0..x1, y0..y1)
                .map_err(err)?;
            chart
                .configure_mesh()
                .x_desc("epoch")
                .x_label_formatter(&|v| if (v - v.round()).abs() < 1e-9 { format!("{v:.0}") } else { String::new() })
                .y_desc(y_label)
                .label_style((FONT, 14))
                .axis_desc_style((FONT, 15))
                .draw()
                .map_err(err)?;
            for (i, s) in series.iter().enumerate() {
                let c = PALETTE[(i + 1) % PALETTE.len()];
                chart.draw_series(s.points.iter().map(|&p| Circle::new(p, 3, c.filled()))).map_err(err)?;
                chart
                    .draw_series(LineSeries::new(s.points.clone(), c.stroke_width(2)))
                    .map_err(err)?
                    .label(s.label.clone())
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c.stroke_width(2)));
            }
            legend(&mut chart, 14, SeriesLabelPosition::UpperRight)?;
        }
        Ok(())
    })
}

/// The viridis colour map at `t` ∈ [0, 1].
pub fn viridis(t: f64) -> RGBColor {
    const STOPS: [(f64, f64, f64); 6] =
        [(68.0, 1.0, 84.0), (65.0, 68.0, 135.0), (42.0, 120.0, 142.0), (34.0, 168.0, 132.0), (122.0, 209.0, 81.0), (253.0, 231.0, 37.0)];
    let t = if t.is_finite() { t.clamp(0.0, 1.0) } else { 0.0 } * (STOPS.len() - 1) as f64;
    let i = (t.floor() as usize).min(STOPS.len() - 2);
    let f = t - i as f64;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    let mix = |u: f64, v: f64| (u + (v - u) * f).round() as u8;
    RGBColor(mix(a.0, b.0), mix(a.1, b.1), mix(a.2, b.2))
}

/// A map `[H, W]` in viridis with a colour bar labelled `unit` (NaN grey, "no value" in the
/// legend); pixel axes with row 0 at the top.
pub fn map(path: &Path, title: &str, values: &ndarray::ArrayView2<'_, f32>, unit: &str) -> Result<()> {
    maps(path, title, &[("", values.view())], unit, None)
}

/// The finite extent of `panels` (`hi > lo`), or `(0, 1)` when nothing is finite.
fn value_range(panels: &[(&str, ndarray::ArrayView2<'_, f32>)]) -> (f64, f64) {
    let finite = panels.iter().flat_map(|(_, v)| v.iter().copied()).filter(|v| v.is_finite());
    let (lo, hi) = finite.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v as f64), b.max(v as f64)));
    if lo.is_finite() {
        (lo, if hi > lo { hi } else { lo + 1.0 })
    } else {
        (0.0, 1.0)
    }
}

/// Maps side by side on one colour scale (`range`, else the panels' finite extent) with one
/// colour bar labelled `unit`; each panel titled, with pixel axes (row 0 at the top); NaN
/// grey with a "no value" legend entry. At most four panels per row.
///
/// # Shapes
/// - `panels`: `(title, [H, W])`, all the same size
pub fn maps(
    path: &Path,
    title: &str,
    panels: &[(&str, ndarray::ArrayView2<'_, f32>)],
    unit: &str,
    range: Option<(f64, f64)>,
) -> Result<()> {
    let Some((_, first)) = panels.first() else {
        return Err(InferError::File { path: path.to_path_buf(), msg: "no maps to draw".into() });
    };
    let (h, w) = first.dim();
    let (lo, hi) = range.filter(|(a, b)| b > a && a.is_finite() && b.is_finite()).unwrap_or_else(|| value_range(panels));
    let any_nan = panels.iter().any(|(_, v)| v.iter().any(|x| !x.is_finite()));
    let cols = panels.len().min(4);
    let rows = panels.len().div_ceil(cols);
    let side = if panels.len() == 1 { 560 } else { 340usize };
    let (pw, ph) = if w >= h { (side, (side * h / w.max(1)).max(100)) } else { ((side * w / h.max(1)).max(100), side) };
    let (cell_w, cell_h) = (pw + 80, ph + 90);
    let top = if panels.len() == 1 { 0 } else { 44 };
    let (fw, fh) = ((cell_w * cols + 200) as u32, (cell_h * rows + top + 20) as u32);
    render(path, (fw, fh), |root| {
        let (title_area, body) = root.split_vertically(top as u32);
        if top > 0 {
            title_area.titled(title, (FONT, 22)).map_err(err)?;
        }
        let (grid, right) = body.split_horizontally((cell_w * cols) as u32);
        let cells = grid.split_evenly((rows, cols));
        let grey = RGBColor(160, 160, 160);
        for (area, (name, values)) in cells.iter().zip(panels) {
            let caption = if panels.len() == 1 { title.to_string() } else { name.to_string() };
            let mut chart = ChartBuilder::on(area)
                .caption(caption, (FONT, if panels.len() == 1 { 20 } else { 16 }))
                .margin(8)
                .x_label_area_size(40)
                .y_label_area_size(50)
                .build_cartesian_2d(0.0..w as f64, h as f64..0.0)
                .map_err(err)?;
            chart
                .configure_mesh()
                .disable_mesh()
                .x_desc("column (pixel)")
                .y_desc("row (pixel)")
                .x_labels(5)
                .y_labels(5)
                .x_label_formatter(&|v| format!("{v:.0}"))
                .y_label_formatter(&|v| format!("{v:.0}"))
                .label_style((FONT, 13))
                .axis_desc_style((FONT, 14))
                .draw()
                .map_err(err)?;
            chart
                .draw_series(values.indexed_iter().map(|((r, c), &v)| {
                    let colour = if v.is_finite() { viridis((v as f64 - lo) / (hi - lo)) } else { grey };
                    Rectangle::new([(c as f64, r as f64), (c as f64 + 1.0, r as f64 + 1.0)], colour.filled())
                }))
                .map_err(err)?;
            if any_nan && values.iter().any(|x| !x.is_finite()) {
                chart
                    .draw_series(std::iter::empty::<Rectangle<(f64, f64)>>())
                    .map_err(err)?
                    .label("no value")
                    .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], grey.filled()));
                legend(&mut chart, 13, SeriesLabelPosition::LowerRight)?;
            }
        }
        // the colour bar
        let mut bar = ChartBuilder::on(&right)
            .margin_top(40)
            .margin_bottom(52)
            .margin_left(10)
            .margin_right(24)
            .set_label_area_size(LabelAreaPosition::Right, 100)
            .build_cartesian_2d(0.0..1.0, lo..hi)
            .map_err(err)?;
        bar.configure_mesh()
            .disable_mesh()
            .disable_x_axis()
            .y_desc(unit)
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .draw()
            .map_err(err)?;
        let steps = 128;
        bar.draw_series((0..steps).map(|i| {
            let (a, b) = (lo + (hi - lo) * i as f64 / steps as f64, lo + (hi - lo) * (i + 1) as f64 / steps as f64);
            Rectangle::new([(0.0, a), (1.0, b)], viridis((i as f64 + 0.5) / steps as f64).filled())
        }))
        .map_err(err)?;
        Ok(())
    })
}

/// Point clouds rendered in perspective, one panel per cloud (like the paper's Fig. 17):
/// camera coordinates in metres (x right, y up, z away from the camera), points coloured by
/// their return (first surface, behind a diffusive sheet).
///
/// # Shapes
/// - `clouds`: `(title, points)`, a point `[x, y, z, return]`
pub fn point_clouds(path: &Path, title: &str, clouds: &[(&str, Vec<[f32; 4]>)]) -> Result<()> {
    let panels = clouds.len().max(1);
    let all = clouds.iter().flat_map(|(_, p)| p.iter()).filter(|p| p.iter().all(|v| v.is_finite()));
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in all {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] as f64);
            hi[k] = hi[k].max(p[k] as f64);
        }
    }
    for k in 0..3 {
        if !lo[k].is_finite() {
            (lo[k], hi[k]) = (0.0, 1.0);
        } else if hi[k] <= lo[k] {
            hi[k] = lo[k] + 1.0;
        }
    }
    render(path, ((560 * panels) as u32, 560), |root| {
        let (title_area, body) = root.split_vertically(40);
        title_area.titled(title, (FONT, 22)).map_err(err)?;
        for (area, (name, points)) in body.split_evenly((1, panels)).iter().zip(clouds) {
            // plotters' 3-D axes: x across, y up, z into the picture
            let mut chart = ChartBuilder::on(area)
                .caption(*name, (FONT, 16))
                .margin(20)
                .build_cartesian_3d(lo[0]..hi[0], lo[1]..hi[1], lo[2]..hi[2])
                .map_err(err)?;
            chart.with_projection(|mut pb| {
                pb.yaw = 0.6;
                pb.pitch = 0.25;
                pb.scale = 0.8;
                pb.into_matrix()
            });
            chart.configure_axes().light_grid_style(BLACK.mix(0.1)).max_light_lines(3).label_style((FONT, 12)).draw().map_err(err)?;
            let label = |x: f64, y: f64, z: f64, s: &str| Text::new(s.to_string(), (x, y, z), (FONT, 14));
            chart
                .draw_series([
                    label(hi[0], lo[1], lo[2], "x (m)"),
                    label(lo[0], hi[1], lo[2], "y (m)"),
                    label(lo[0], lo[1], hi[2], "z (m, depth)"),
                ])
                .map_err(err)?;
            for ret in 0..2usize {
                let c = PALETTE[ret + 1];
                let pts = points.iter().filter(|p| p[3] as usize == ret && p.iter().all(|v| v.is_finite()));
                chart
                    .draw_series(pts.map(|p| Circle::new((p[0] as f64, p[1] as f64, p[2] as f64), 1, c.filled())))
                    .map_err(err)?
                    .label(if ret == 0 { "return 1 (first surface)" } else { "return 2 (behind the sheet)" })
                    .legend(move |(x, y)| Circle::new((x + 7, y), 4, c.filled()));
            }
            chart
                .configure_series_labels()
                .label_font((FONT, 13))
                .background_style(WHITE.mix(0.9))
                .border_style(BLACK)
                .position(SeriesLabelPosition::UpperRight)
                .draw()
                .map_err(err)?;
        }
        Ok(())
    })
}

/// A phasor plot: the per-pixel phasors `(g, s)` of each decoder as a point cloud, with the
/// universal semicircle where single exponentials lie and the lifetimes marked on it at the
/// first harmonic `ω = 2π / period_s`. Drawn over `g ∈ [0.4, 1]`, where lifetimes up to
/// about a sixth of the period lie (phasors outside are left out).
pub fn phasor(path: &Path, title: &str, series: &[(&str, Vec<(f64, f64)>)], period_s: f64) -> Result<()> {
    render(path, (760, 520), |root| {
        let mut chart = ChartBuilder::on(root)
            .caption(title, (FONT, 20))
            .margin(12)
            .x_label_area_size(46)
            .y_label_area_size(60)
            .build_cartesian_2d(0.4..1.08, -0.02..0.52)
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("g (cosine component)")
            .y_desc("s (sine component)")
            .label_style((FONT, 14))
            .axis_desc_style((FONT, 15))
            .draw()
            .map_err(err)?;
        let circle: Vec<(f64, f64)> = (0..=100)
            .map(|i| {
                let a = std::f64::consts::PI * i as f64 / 180.0;
                (0.5 + 0.5 * a.cos(), 0.5 * a.sin())
            })
            .collect();
        chart
            .draw_series(LineSeries::new(circle, BLACK.stroke_width(1)))
            .map_err(err)?
            .label("single exponentials")
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], BLACK));
        // lifetimes on the circle: g = 1/(1+(ωτ)²), s = ωτ/(1+(ωτ)²)
        let omega = 2.0 * std::f64::consts::PI / period_s;
        for tau_ns in [0.5, 1.0, 2.0, 4.0, 8.0] {
            let wt = omega * tau_ns * 1e-9;
            let (g, s) = (1.0 / (1.0 + wt * wt), wt / (1.0 + wt * wt));
            chart.draw_series([Circle::new((g, s), 3, BLACK.filled())]).map_err(err)?;
            chart.draw_series([Text::new(format!("{tau_ns} ns"), (g + 0.01, s + 0.03), (FONT, 12))]).map_err(err)?;
        }
        for (i, (name, pts)) in series.iter().enumerate() {
            let c = PALETTE[(i + 1) % PALETTE.len()];
            chart
                .draw_series(
                    pts.iter()
                        .filter(|(g, s)| (0.4..1.08).contains(g) && (-0.02..0.52).contains(s))
                        .map(|&p| Circle::new(p, 2, c.mix(0.6).filled())),
                )
                .map_err(err)?
                .label(name.to_string())
                .legend(move |(x, y)| Circle::new((x + 7, y), 4, c.filled()));
        }
        legend(&mut chart, 13, SeriesLabelPosition::UpperRight)?;
        Ok(())
    })
}

/// Codes like the paper's Fig. 12: one row per channel (subpixel `n`, tap `m`), one column per
/// mask, a cell in the tap's colour when on; below, the bits changed at each transition
/// `l → l+1` against the Hamming limit; violated masks marked red on top.
pub fn codes(path: &Path, name: &str, codes: &Codes) -> Result<()> {
    let (n_sub, taps, len) = (codes.subpixels(), codes.taps(), codes.length());
    let rows = n_sub * taps;
    let (bh, bw) = codes.block();
    let method = codes.provenance.get("method").and_then(|v| v.as_str()).unwrap_or("");
    let title = format!(
        "{name}: {taps} taps, {bh}×{bw} block, L = {len}, constraints {}{}",
        codes.constraints.label(),
        if method.is_empty() { String::new() } else { format!(" ({method})") }
    );
    let tc_ns = 1e9 / codes.clock_hz;
    let bad: Vec<usize> = codes.violations().iter().map(|v| v.mask).collect();
    let height = (rows * 18 + 260).clamp(420, 1400) as u32;
    render(path, (1000, height), |root| {
        let (top, bottom) = root.split_vertically(height - 190);
        let mut chart = ChartBuilder::on(&top)
            .caption(&title, (FONT, 20))
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(90)
            .build_cartesian_2d(0.0..len as f64, rows as f64..0.0)
            .map_err(err)?;
        chart
            .configure_mesh()
            .disable_mesh()
            .x_desc(format!("mask l (T_c = {tc_ns:.2} ns each)"))
            .y_desc("subpixel n, tap m")
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|_| String::new())
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 15))
            .draw()
            .map_err(err)?;
        // row labels at the rows' centres
        if rows <= 64 {
            for c in 0..rows {
                let (px, py) = chart.backend_coord(&(0.0, c as f64 + 0.5));
                top.draw(&Text::new(format!("n{} m{}", c / taps, c % taps), (px - 52, py - 6), (FONT, 12))).map_err(err)?;
            }
        }
        let shade = [RGBColor(244, 244, 244), RGBColor(228, 228, 228)];
        chart
            .draw_series(
                (0..rows).map(|c| Rectangle::new([(0.0, c as f64 + 0.02), (len as f64, c as f64 + 0.98)], shade[(c / taps) % 2].filled())),
            )
            .map_err(err)?;
        chart
            .draw_series((0..rows).flat_map(|c| {
                let (n, m) = (c / taps, c % taps);
                (0..len).filter(move |&l| codes.get(n, m, l)).map(move |l| {
                    Rectangle::new([(l as f64 + 0.05, c as f64 + 0.1), (l as f64 + 0.95, c as f64 + 0.9)], TAPS[m % 8].filled())
                })
            }))
            .map_err(err)?;
        for m in 0..taps {
            chart
                .draw_series(std::iter::empty::<Rectangle<(f64, f64)>>())
                .map_err(err)?
                .label(format!("tap {m}"))
                .legend(move |(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], TAPS[m % 8].filled()));
        }
        if !bad.is_empty() {
            chart
                .draw_series(bad.iter().map(|&l| Rectangle::new([(l as f64, 0.0), (l as f64 + 1.0, 0.3)], RED.filled())))
                .map_err(err)?
                .label("violation")
                .legend(|(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], RED.filled()));
        }
        legend(&mut chart, 13, SeriesLabelPosition::UpperRight)?;

        let hd: Vec<usize> = (0..len).map(|l| codes.hamming_at(l)).collect();
        let limit = codes.constraints.hamming;
        let ymax = hd.iter().copied().max().unwrap_or(0).max(limit.unwrap_or(0)).max(1) as f64 + 0.5;
        let mut strip = ChartBuilder::on(&bottom)
            .margin(10)
            .x_label_area_size(40)
            .y_label_area_size(90)
            .build_cartesian_2d(0.0..len as f64, 0.0..ymax)
            .map_err(err)?;
        strip
            .configure_mesh()
            .disable_x_mesh()
            .x_desc("transition l → l+1")
            .y_desc("bits changed")
            .x_label_formatter(&|v| format!("{v:.0}"))
            .y_label_formatter(&|v| if (v - v.round()).abs() < 1e-9 { format!("{v:.0}") } else { String::new() })
            .label_style((FONT, 13))
            .axis_desc_style((FONT, 15))
            .draw()
            .map_err(err)?;
        strip
            .draw_series(
                hd.iter()
                    .enumerate()
                    .map(|(l, &d)| Rectangle::new([(l as f64 + 0.2, 0.0), (l as f64 + 0.8, d as f64)], RGBColor(80, 80, 80).filled())),
            )
            .map_err(err)?
            .label("Hamming distance")
            .legend(|(x, y)| Rectangle::new([(x, y - 6), (x + 14, y + 6)], RGBColor(80, 80, 80).filled()));
        if let Some(hl) = limit {
            strip
                .draw_series(LineSeries::new(vec![(0.0, hl as f64), (len as f64, hl as f64)], RED.stroke_width(2)))
                .map_err(err)?
                .label(format!("limit H = {hl}"))
                .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], RED.stroke_width(2)));
        }
        legend(&mut strip, 13, SeriesLabelPosition::UpperRight)?;
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn png_size(path: &Path) -> (u32, u32) {
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
        let reader = dec.read_info().unwrap();
        let info = reader.info();
        (info.width, info.height)
    }

    /// Every figure renders, with text: the font draws dark pixels in the caption band.
    #[test]
    fn figures_render_with_text() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("lines.png");
        line_chart(
            &p,
            "Training loss",
            "epoch",
            "loss",
            &[Series { label: "train".into(), points: vec![(1.0, 0.5), (2.0, 0.3), (3.0, 0.2)] }],
        )
        .unwrap();
        assert_eq!(png_size(&p), (900, 520));
        let m = ndarray::Array2::from_shape_fn((8, 12), |(r, c)| if r == 3 && c == 4 { f32::NAN } else { (r * 12 + c) as f32 });
        let p = dir.path().join("map.png");
        map(&p, "Range of return 1", &m.view(), "range (m)").unwrap();
        let shape = tcsense_sensor::codes::CodeShape { bh: 2, bw: 2, taps: 4, length: 16, drain: false };
        let c = tcsense_sensor::generate::random_codes(
            shape,
            607e6,
            tcsense_sensor::Constraints { tap: true, hamming: Some(2), window: Some(2) },
            1,
        )
        .unwrap();
        let p = dir.path().join("codes.png");
        codes(&p, "codes.json", &c).unwrap();
        // caption text: dark pixels in the top band of the image
        let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&p).unwrap()));
        let mut reader = dec.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        let band = &buf[..(info.width as usize * 3 * 30)];
        assert!(band.chunks(3).filter(|px| px.iter().all(|&v| v < 100)).count() > 50, "no caption text drawn");
    }
}
