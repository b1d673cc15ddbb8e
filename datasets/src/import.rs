//! Import of users' data into the dataset format:
//! - transient cubes (`.npy`, `[T, H, W]` or `[F, T, H, W]`, e.g. from a transient renderer);
//! - depth maps (range, m) with optional albedo maps (`.npy` or 8/16-bit grayscale PNG),
//!   rendered into single-return cubes like the LiDAR generator (`ρ/r²`, sub-bin split).
//!
//! Everything is checked before anything is written: the number of bins against the grid,
//! the frame size against the pixel block, finiteness, non-negative depths inside the
//! unambiguous range.

use crate::error::{file_err, invalid, Result};
use crate::grid::{TimeGrid, C};
use crate::lidar::BOUNCES;
use crate::store::{finish_output, prepare_output, write_manifest, write_shard, Item, Kind, Manifest, Split};
use ndarray::{s, Array2, Array3, ArrayD, Axis, Ix2};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tcsense_sensor::npy::{ensure_finite, read_npy};

/// What to import.
#[derive(Debug, Clone)]
pub enum Source {
    /// Transient cubes.
    Cubes(Vec<PathBuf>),
    /// Depth maps (scaled by `depth_scale` to metres) with optional albedo maps (one per depth map).
    DepthMaps { depth: Vec<PathBuf>, albedo: Vec<PathBuf>, depth_scale: f64 },
}

/// Import settings.
#[derive(Debug, Clone)]
pub struct ImportOptions {
    pub grid: TimeGrid,
    /// Pixel block the frames must tile.
    pub block: (usize, usize),
    /// Split to put everything in.
    pub split: String,
    pub shard_size: usize,
    pub force: bool,
}

/// Read a 2-D map from `.npy` (rank 2) or a grayscale PNG (8 or 16 bit, raw values).
pub fn read_map(path: &Path) -> Result<Array2<f32>> {
    let is_png = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("png"));
    if !is_png {
        let a = read_npy(path)?;
        let nd = a.ndim();
        let shape = a.shape().to_vec();
        let a = a
            .into_dimensionality::<Ix2>()
            .map_err(|_| file_err(path, format!("map has shape {shape:?} (rank {nd}), expected rank 2 [H, W]")))?;
        ensure_finite(&a.view(), "map").map_err(|e| e.in_file(path))?;
        return Ok(a);
    }
    Ok(tcsense_sensor::show::read_gray_png(path)?)
}

fn check_frame(path: &Path, h: usize, w: usize, block: (usize, usize)) -> Result<()> {
    if h == 0 || w == 0 || h % block.0 != 0 || w % block.1 != 0 {
        return Err(file_err(path, format!("frame {h}x{w} is not a multiple of the {}x{} pixel block", block.0, block.1)));
    }
    Ok(())
}

/// Import `source` into a new dataset at `dir`.
pub fn import(source: &Source, opts: &ImportOptions, dir: &Path) -> Result<Manifest> {
    let grid = opts.grid.validate()?;
    let t = grid.bins();
    if opts.shard_size == 0 {
        return Err(invalid("shard_size", 0, "at least 1"));
    }
    let mut items: Vec<Item> = Vec::new();
    let mut size: Option<(usize, usize, PathBuf)> = None;
    let mut check_size = |path: &Path, h: usize, w: usize| -> Result<()> {
        check_frame(path, h, w, opts.block)?;
        match &size {
            Some((h0, w0, p0)) if (*h0, *w0) != (h, w) => {
                Err(file_err(path, format!("frame {h}x{w} differs from {h0}x{w0} of {}", p0.display())))
            }
            Some(_) => Ok(()),
            None => {
                size = Some((h, w, path.to_path_buf()));
                Ok(())
            }
        }
    };
    match source {
        Source::Cubes(paths) => {
            if paths.is_empty() {
                return Err(invalid("cube", "none", "at least one --cube file"));
            }
            for p in paths {
                let a = tcsense_sensor::npy::read_cube(p, true)?;
                let cubes: Vec<ArrayD<f32>> = if a.ndim() == 3 { vec![a] } else { a.axis_iter(Axis(0)).map(|v| v.to_owned()).collect() };
                for c in cubes {
                    let sh = c.shape().to_vec();
                    if sh[0] != t {
                        return Err(file_err(
                            p,
                            format!(
                                "cube has {} time bins, expected T = L·K = {t} for the grid (L = {}, K = {})",
                                sh[0],
                                grid.length,
                                grid.sampling.k()
                            ),
                        ));
                    }
                    check_size(p, sh[1], sh[2])?;
                    let intensity = c.sum_axis(Axis(0));
                    items.push(vec![("x", c), ("intensity", intensity)]);
                }
            }
        }
        Source::DepthMaps { depth, albedo, depth_scale } => {
            if depth.is_empty() {
                return Err(invalid("depth", "none", "at least one --depth map"));
            }
            if !albedo.is_empty() && albedo.len() != depth.len() {
                return Err(invalid("albedo", albedo.len(), format!("one albedo map per depth map ({})", depth.len())));
            }
            if !(depth_scale.is_finite() && *depth_scale > 0.0) {
                return Err(invalid("depth_scale", depth_scale, "a positive number of metres per unit"));
            }
            let range = grid.range_m();
            for (k, dp) in depth.iter().enumerate() {
                let d = read_map(dp)?.mapv(|v| v * *depth_scale as f32);
                let (h, w) = d.dim();
                check_size(dp, h, w)?;
                if let Some(((r, c), v)) = d.indexed_iter().find(|(_, v)| **v < 0.0) {
                    return Err(file_err(dp, format!("negative depth {v} m at pixel ({r}, {c}); depths must be ≥ 0 (0 = no return)")));
                }
                if let Some(((r, c), v)) = d.indexed_iter().find(|(_, v)| **v as f64 >= range) {
                    return Err(file_err(
                        dp,
                        format!("depth {v} m at pixel ({r}, {c}) is beyond the unambiguous range {range:.3} m (L·T_c·c/2)"),
                    ));
                }
                let alb = match albedo.get(k) {
                    Some(ap) => {
                        let a = read_map(ap)?;
                        if a.dim() != (h, w) {
                            return Err(file_err(ap, format!("albedo map {:?} differs from depth map {:?}", a.dim(), (h, w))));
                        }
                        if a.iter().any(|v| *v < 0.0) {
                            return Err(file_err(ap, "negative albedo; values must be ≥ 0"));
                        }
                        a
                    }
                    None => Array2::ones((h, w)),
                };
                items.push(render_depth(&d, &alb, &grid));
            }
        }
    }
    let (h, w, _) = size.ok_or_else(|| invalid("input", "empty", "at least one frame"))?;
    let fields: BTreeMap<String, Vec<usize>> = items[0].iter().map(|(name, a)| (name.to_string(), a.shape().to_vec())).collect();
    let tmp = prepare_output(dir, opts.force)?;
    let result = (|| -> Result<Manifest> {
        let mut shards = Vec::new();
        for (si, chunk) in items.chunks(opts.shard_size).enumerate() {
            shards.push(write_shard(&tmp, &opts.split, si, chunk)?);
        }
        let manifest = Manifest {
            format: "tcsense-dataset".into(),
            version: 1,
            kind: Kind::Imported,
            seed: None,
            generator: serde_json::json!({ "source": match source {
                Source::Cubes(p) => serde_json::json!({"cubes": p.iter().map(|p| p.display().to_string()).collect::<Vec<_>>()}),
                Source::DepthMaps { depth, albedo, depth_scale } => serde_json::json!({
                    "depth": depth.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
                    "albedo": albedo.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
                    "depth_scale": depth_scale,
                }),
            }}),
            grid,
            bins: t,
            bin_width_s: grid.bin_width_s(),
            size: [h, w],
            fields,
            splits: vec![Split { name: opts.split.clone(), count: items.len(), first_index: 0, shards }],
        };
        write_manifest(&tmp, &manifest)?;
        Ok(manifest)
    })();
    finish_output(tmp, dir, result)
}

/// Single-return cube from a range map (m, 0 = no return) and an albedo map.
fn render_depth(d: &Array2<f32>, alb: &Array2<f32>, grid: &TimeGrid) -> Item {
    let (h, w) = d.dim();
    let mut x = Array3::<f32>::zeros((grid.bins(), h, w));
    let mut depth = Array3::<f32>::from_elem((BOUNCES, h, w), f32::NAN);
    let mut intensity = Array2::<f32>::zeros((h, w));
    let mut wave = vec![0f32; grid.bins()];
    for r in 0..h {
        for c in 0..w {
            let range = d[(r, c)] as f64;
            if range <= 0.0 {
                continue;
            }
            wave.fill(0.0);
            let a = alb[(r, c)] as f64 / (range * range);
            grid.splat(&mut wave, 2.0 * range / C, a);
            x.slice_mut(s![.., r, c]).assign(&ndarray::ArrayView1::from(&wave[..]));
            depth[(0, r, c)] = range as f32;
            intensity[(r, c)] = a as f32;
        }
    }
    let peak = x.iter().fold(0f32, |m, &v| m.max(v));
    if peak > 0.0 {
        x.mapv_inplace(|v| v / peak);
        intensity.mapv_inplace(|v| v / peak);
    }
    vec![("x", x.into_dyn()), ("depth", depth.into_dyn()), ("intensity", intensity.into_dyn())]
}
