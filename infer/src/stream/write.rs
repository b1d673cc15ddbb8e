//! How a stream's products reach the disk: `.npy` stacks written frame by frame into
//! temporary files, and the products of one frame.

use super::*;
use ndarray::Array2;
use tcsense_models::decoder::set_where;

/// An `f32` `.npy` stack written frame by frame into a temporary file, renamed on
/// [`NpyStackWriter::finish`]; dropped unfinished, the temporary file is removed.
pub struct NpyStackWriter {
    pub(super) path: PathBuf,
    tmp: PathBuf,
    out: Option<BufWriter<File>>,
    expected: usize,
    written: usize,
}

impl NpyStackWriter {
    /// A writer of an array of `shape` (its values come in C order through `push`).
    pub fn create(path: &Path, shape: &[usize]) -> Result<Self> {
        let header = f32_header(shape).map_err(|e| file_err(path, e))?;
        let dir = path.parent().filter(|d| !d.as_os_str().is_empty()).map_or_else(|| PathBuf::from("."), Path::to_path_buf);
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
        let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
        let mut out = BufWriter::new(File::create(&tmp).map_err(|e| file_err(path, e))?);
        out.write_all(&header).map_err(|e| file_err(path, e))?;
        Ok(NpyStackWriter { path: path.to_path_buf(), tmp, out: Some(out), expected: shape.iter().product(), written: 0 })
    }

    /// Append values (C order).
    pub fn push<'a>(&mut self, values: impl IntoIterator<Item = &'a f32>) -> Result<()> {
        let Some(out) = self.out.as_mut() else { return Err(file_err(&self.path, "written after finish")) };
        let mut buf = Vec::new();
        for v in values {
            buf.extend_from_slice(&v.to_le_bytes());
        }
        self.written += buf.len() / 4;
        out.write_all(&buf).map_err(|e| file_err(&self.path, e))
    }

    /// Flush, check the count and rename into place.
    pub fn finish(mut self) -> Result<()> {
        let out = self.out.take().ok_or_else(|| file_err(&self.path, "finished twice"))?;
        let result = (|| {
            if self.written != self.expected {
                return Err(file_err(&self.path, format!("{} values written, {} expected", self.written, self.expected)));
            }
            let file = out.into_inner().map_err(|e| file_err(&self.path, e.into_error()))?;
            file.sync_all().map_err(|e| file_err(&self.path, e))?;
            std::fs::rename(&self.tmp, &self.path).map_err(|e| file_err(&self.path, e))
        })();
        if result.is_err() {
            let _ = std::fs::remove_file(&self.tmp);
        }
        result
    }
}

impl Drop for NpyStackWriter {
    fn drop(&mut self) {
        if self.out.is_some() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

pub(super) struct Writers {
    pub(super) cube: Option<NpyStackWriter>,
    pub(super) depth: Option<NpyStackWriter>,
    pub(super) second: Option<NpyStackWriter>,
    pub(super) lifetime: Option<NpyStackWriter>,
    pub(super) intensity: Option<NpyStackWriter>,
    pub(super) phasor: Option<NpyStackWriter>,
}

/// Phasors `(g, s)` of every pixel as two planes `[2, H·W]`, flat.
fn planes(phasors: impl Iterator<Item = (f32, f32)>) -> Vec<f32> {
    let (g, s): (Vec<f32>, Vec<f32>) = phasors.unzip();
    g.into_iter().chain(s).collect()
}

/// The products of frame `i` from the model's outputs (`[1, C, H, W]` each).
#[allow(clippy::too_many_arguments)]
pub(super) fn write_frame(
    i: usize,
    outs: Vec<Array4<f32>>,
    fitted: Option<TapFit>,
    ranges: Option<Array3<f32>>,
    wr: &mut Writers,
    p: &Products,
    kind: ModelKind,
    bin_s: f64,
    bins: usize,
    peak_opts: &PeakOptions,
    out: &Path,
    unread: Option<&Array2<bool>>,
) -> Result<()> {
    let omega = 2.0 * std::f64::consts::PI / (bins as f64 * bin_s);
    if let Some(fit) = &fitted {
        // lifetime, intensity and phasor (one exponential) by the fit to the taps
        if let Some(w) = wr.lifetime.as_mut() {
            w.push(fit.lifetime.iter())?;
        }
        if let Some(w) = wr.intensity.as_mut() {
            w.push(fit.intensity.iter())?;
        }
        if let Some(w) = wr.phasor.as_mut() {
            w.push(planes(fit.lifetime.iter().map(|&t| phasor_of_components(t, t, 1.0, omega))).iter())?;
        }
    }
    let by_model = fitted.is_none();
    if let Some(depth) = &ranges {
        // depth by the template fit: a confidence of 1 where a return was placed
        let confidence = depth.mapv(|d| if d.is_finite() { 1.0f32 } else { 0.0 });
        if let Some(w) = wr.depth.as_mut() {
            w.push(depth.iter())?;
        }
        if let Some(w) = wr.second.as_mut() {
            w.push(confidence.iter())?;
        }
        if p.ply {
            write_ply(&out.join("ply").join(format!("frame_{i:05}.ply")), &depth.view(), &confidence.view(), p.fov_deg)?;
        }
    }
    let depth_by_model = ranges.is_none();
    // the model's outputs: none when every product asked for comes from a fit to the taps
    let Some(first) = outs.first() else { return Ok(()) };
    match kind {
        ModelKind::Cube => {
            let cube: ArrayView3<'_, f32> = first.index_axis(Axis(0), 0);
            if let Some(w) = wr.cube.as_mut() {
                w.push(cube.iter())?;
            }
            if depth_by_model && (p.depth || p.peaks || p.ply) {
                let (mut depth, mut amp) = depth_map(&cube, bin_s, peak_opts);
                if let Some(u) = unread {
                    set_where(&mut depth, &u.view(), f32::NAN);
                    set_where(&mut amp, &u.view(), 0.0);
                }
                if let Some(w) = wr.depth.as_mut() {
                    w.push(depth.iter())?;
                }
                if let Some(w) = wr.second.as_mut() {
                    w.push(amp.iter())?;
                }
                if p.ply {
                    write_ply(&out.join("ply").join(format!("frame_{i:05}.ply")), &depth.view(), &amp.view(), p.fov_deg)?;
                }
            }
            if by_model && (p.lifetime || p.phasor) {
                // the reconvolution fit (IRF fitted to the frame)
                let mut fit = tcsense_fits::lifetime_cube::fit_cube(&cube, bin_s, &tcsense_fits::lifetime_cube::FitOptions::default());
                if let Some(u) = unread {
                    set_where(&mut fit.lifetimes, &u.view(), f32::NAN);
                    set_where(&mut fit.phasor, &u.view(), f32::NAN);
                }
                if let Some(w) = wr.lifetime.as_mut() {
                    w.push(fit.lifetimes.index_axis(Axis(0), 0).iter())?;
                }
                if let Some(w) = wr.phasor.as_mut() {
                    w.push(fit.phasor.iter())?;
                }
            }
            if let Some(w) = wr.intensity.as_mut().filter(|_| by_model) {
                w.push(cube.sum_axis(Axis(0)).iter())?;
            }
        }
        ModelKind::Depth if depth_by_model => {
            let mut depth = outs[0].clone();
            mask_depth(&mut depth, &outs[1]);
            if let Some(w) = wr.depth.as_mut() {
                w.push(depth.iter())?;
            }
            if let Some(w) = wr.second.as_mut() {
                w.push(outs[1].iter())?;
            }
            if p.ply {
                write_ply(
                    &out.join("ply").join(format!("frame_{i:05}.ply")),
                    &depth.index_axis(Axis(0), 0),
                    &outs[1].index_axis(Axis(0), 0),
                    p.fov_deg,
                )?;
            }
        }
        ModelKind::Lifetime if by_model => {
            // lifetime [1, 4, H, W] (τ_m, τ₁, τ₂ in s, α₁), confidence and intensity [1, 1, H, W]
            let mut lifetime = outs[0].clone();
            tcsense_models::net::mask_lifetime(&mut lifetime, &outs[1]);
            let l = lifetime.index_axis(Axis(0), 0);
            if let Some(w) = wr.lifetime.as_mut() {
                w.push(l.index_axis(Axis(0), 0).iter())?;
            }
            if let Some(w) = wr.intensity.as_mut() {
                w.push(outs[2].iter())?;
            }
            if let Some(w) = wr.phasor.as_mut() {
                let (_, h, wd) = l.dim();
                w.push(
                    planes(
                        (0..h * wd)
                            .map(|q| phasor_of_components(l[(1, q / wd, q % wd)], l[(2, q / wd, q % wd)], l[(3, q / wd, q % wd)], omega)),
                    )
                    .iter(),
                )?;
            }
        }
        ModelKind::Lifetime | ModelKind::Depth => {}
    }
    Ok(())
}

/// No range and no lifetime where `unread` (`[H, W]`: a tap clipped at the full well): a
/// depth or lifetime model's confidence 0 there (its ranges and lifetimes are masked by it
/// downstream, and its ranges set NaN now), the fit's lifetimes and ranges NaN.
pub(super) fn without_pixels(
    unread: &Array2<bool>,
    kind: ModelKind,
    outs: &mut [Array4<f32>],
    fitted: Option<&mut TapFit>,
    ranges: Option<&mut Array3<f32>>,
) {
    let unread = unread.view();
    match (kind, outs) {
        (ModelKind::Depth | ModelKind::Lifetime, [maps, confidence, ..]) => {
            set_where(maps, &unread, f32::NAN);
            set_where(confidence, &unread, 0.0);
        }
        _ => {}
    }
    if let Some(fit) = fitted {
        set_where(&mut fit.lifetime, &unread, f32::NAN);
    }
    if let Some(r) = ranges {
        set_where(r, &unread, f32::NAN);
    }
}
