//! Dataset storage: `DIR/manifest.json` plus `.npy` shards per split.
//!
//! ```text
//! DIR/manifest.json
//! DIR/train/x_000.npy          [S, T, H, W]   (S ≤ shard size)
//! DIR/train/depth_000.npy      [S, 2, H, W]   (LiDAR)
//! DIR/train/intensity_000.npy  [S, H, W]
//! DIR/val/…  DIR/test/…
//! ```
//!
//! The manifest records the kind, the generator's parameters, the seed, the time grid, the
//! per-item shape of every field and, per split, its size, the global index of its first
//! item and its shard files. Item `i` (global index over train, val, test in that order) is a
//! pure function of `(seed, i)`: training can draw the same samples on the fly without disk.
//! Generation writes into a temporary directory that is renamed into place at the end, so an
//! interrupted or failed run leaves nothing behind.

use crate::error::{file_err, invalid, DatasetError, Result};
use crate::flim::FlimParams;
use crate::grid::TimeGrid;
use crate::lidar::{LidarParams, BOUNCES};
use ndarray::{stack, ArrayD, Axis, IxDyn, Slice};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use tcsense_sensor::npy::{read_npy, write_bytes, write_npy};

/// Default items per shard file.
pub const DEFAULT_SHARD: usize = 16;

/// What a dataset holds.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Kind {
    Lidar,
    Flim,
    Imported,
}

/// One shard: its item count and a file per field.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Shard {
    pub count: usize,
    pub files: BTreeMap<String, String>,
}

/// One split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Split {
    pub name: String,
    pub count: usize,
    /// Global index of the split's first item.
    pub first_index: u64,
    pub shards: Vec<Shard>,
}

/// `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub kind: Kind,
    pub seed: Option<u64>,
    pub generator: serde_json::Value,
    pub grid: TimeGrid,
    pub bins: usize,
    pub bin_width_s: f64,
    /// Frame size `[H, W]`.
    pub size: [usize; 2],
    /// Per-item shape of every field.
    pub fields: BTreeMap<String, Vec<usize>>,
    pub splits: Vec<Split>,
}

/// A generator of items, each a pure function of `(seed, index)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Generator {
    Lidar(LidarParams),
    Flim(FlimParams),
}

/// One item: named fields.
pub type Item = Vec<(&'static str, ArrayD<f32>)>;

impl Generator {
    /// The dataset kind.
    pub fn kind(&self) -> Kind {
        match self {
            Generator::Lidar(_) => Kind::Lidar,
            Generator::Flim(_) => Kind::Flim,
        }
    }
    /// Frame size `(H, W)`.
    pub fn size(&self) -> (usize, usize) {
        match self {
            Generator::Lidar(p) => (p.height, p.width),
            Generator::Flim(p) => (p.height, p.width),
        }
    }
    /// Check parameters.
    pub fn validate(&self, grid: &TimeGrid) -> Result<()> {
        match self {
            Generator::Lidar(p) => p.validate(),
            Generator::Flim(p) => p.validate(grid),
        }
    }
    /// Per-item field shapes.
    pub fn fields(&self, grid: &TimeGrid) -> BTreeMap<String, Vec<usize>> {
        let (h, w) = self.size();
        let t = grid.bins();
        let mut f = BTreeMap::new();
        f.insert("x".into(), vec![t, h, w]);
        f.insert("intensity".into(), vec![h, w]);
        match self {
            Generator::Lidar(_) => {
                f.insert("depth".into(), vec![BOUNCES, h, w]);
            }
            Generator::Flim(_) => {
                f.insert("tau".into(), vec![3]);
                f.insert("weights".into(), vec![3, h, w]);
                f.insert("lifetime".into(), vec![h, w]);
                f.insert("onset".into(), vec![1]);
            }
        }
        f
    }
    /// Item `index`, a pure function of `(seed, index)`.
    pub fn item(&self, grid: &TimeGrid, seed: u64, index: u64) -> Item {
        match self {
            Generator::Lidar(p) => {
                let s = p.sample(grid, seed, index);
                vec![("x", s.x.into_dyn()), ("depth", s.depth.into_dyn()), ("intensity", s.intensity.into_dyn())]
            }
            Generator::Flim(p) => {
                let s = p.sample(grid, seed, index);
                vec![
                    ("x", s.x.into_dyn()),
                    ("tau", s.tau.into_dyn()),
                    ("weights", s.weights.into_dyn()),
                    ("lifetime", s.lifetime.into_dyn()),
                    ("intensity", s.intensity.into_dyn()),
                    ("onset", s.onset.into_dyn()),
                ]
            }
        }
    }
    fn params_json(&self) -> serde_json::Value {
        match self {
            Generator::Lidar(p) => serde_json::to_value(p).unwrap_or_default(),
            Generator::Flim(p) => serde_json::to_value(p).unwrap_or_default(),
        }
    }
    /// The paper's split proportions: LiDAR 63/10/10, FLIm 446/56/56.
    pub fn proportions(&self) -> [usize; 3] {
        match self {
            Generator::Lidar(_) => [63, 10, 10],
            Generator::Flim(_) => [446, 56, 56],
        }
    }
}

/// Split `count` items in the given proportions (train gets the remainder; val and test get at
/// least one item each when `count ≥ 3`).
pub fn split_counts(count: usize, proportions: [usize; 3]) -> [usize; 3] {
    let total: usize = proportions.iter().sum();
    let part = |p: usize| ((count * p) as f64 / total as f64).round() as usize;
    let (mut val, mut test) = (part(proportions[1]), part(proportions[2]));
    if count >= 3 {
        val = val.max(1);
        test = test.max(1);
    } else {
        val = 0;
        test = 0;
    }
    [count - val - test, val, test]
}

/// Options for writing a dataset.
pub struct WriteOptions<'a> {
    pub shard_size: usize,
    /// Replace an existing dataset directory.
    pub force: bool,
    /// Called once per finished item (from worker threads).
    pub progress: &'a (dyn Fn() + Sync),
    /// Set to stop early; nothing is written then.
    pub cancel: &'a AtomicBool,
}

/// Generate a dataset of `count` items into `dir`.
pub fn generate(gen: &Generator, grid: &TimeGrid, count: usize, seed: u64, dir: &Path, opts: &WriteOptions<'_>) -> Result<Manifest> {
    let grid = grid.validate()?;
    gen.validate(&grid)?;
    if count == 0 {
        return Err(invalid("count", 0, "at least 1 item"));
    }
    if opts.shard_size == 0 {
        return Err(invalid("shard_size", 0, "at least 1"));
    }
    // a shard is held in memory (and copied once to stack it) while the threads make items
    let item_bytes: f64 = gen.fields(&grid).values().map(|s| 4.0 * s.iter().product::<usize>() as f64).sum();
    let in_flight = opts.shard_size.min(count) + 2 * rayon::current_num_threads();
    tcsense_sensor::mem::check_fits(
        &format!("{count} items of {:.1} MiB in shards of {}", item_bytes / (1u64 << 20) as f64, opts.shard_size.min(count)),
        2.0 * item_bytes * in_flight as f64,
        "use a smaller --size, fewer bins (--length, --heterodyne/--oversample) or a smaller --shard-size",
    )?;
    let counts = split_counts(count, gen.proportions());
    let tmp = prepare_output(dir, opts.force)?;
    let result = (|| -> Result<Manifest> {
        let mut splits = Vec::new();
        let mut first = 0u64;
        for (name, &n) in ["train", "val", "test"].iter().zip(&counts) {
            let mut shards = Vec::new();
            let split_dir = tmp.join(name);
            std::fs::create_dir_all(&split_dir).map_err(|e| tcsense_sensor::SensorError::io(&split_dir, e))?;
            for (si, start) in (0..n).step_by(opts.shard_size).enumerate() {
                let end = (start + opts.shard_size).min(n);
                let items: Vec<Option<Item>> = (start..end)
                    .into_par_iter()
                    .map(|i| {
                        if opts.cancel.load(Ordering::Relaxed) {
                            return None;
                        }
                        let item = gen.item(&grid, seed, first + i as u64);
                        (opts.progress)();
                        Some(item)
                    })
                    .collect();
                let items: Vec<Item> = items.into_iter().collect::<Option<_>>().ok_or(DatasetError::Cancelled)?;
                shards.push(write_shard(&tmp, name, si, &items)?);
            }
            splits.push(Split { name: name.to_string(), count: n, first_index: first, shards });
            first += n as u64;
        }
        let (h, w) = gen.size();
        let manifest = Manifest {
            format: "tcsense-dataset".into(),
            version: 1,
            kind: gen.kind(),
            seed: Some(seed),
            generator: gen.params_json(),
            grid,
            bins: grid.bins(),
            bin_width_s: grid.bin_width_s(),
            size: [h, w],
            fields: gen.fields(&grid),
            splits,
        };
        write_manifest(&tmp, &manifest)?;
        Ok(manifest)
    })();
    finish_output(tmp, dir, result)
}

/// Create a fresh temporary directory next to `dir`; refuse an existing dataset unless `force`.
pub(crate) fn prepare_output(dir: &Path, force: bool) -> Result<PathBuf> {
    if dir.exists() && !force {
        let empty = std::fs::read_dir(dir).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty {
            return Err(file_err(dir, "output directory exists and is not empty; pass --force to replace it"));
        }
    }
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "dataset".into());
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    std::fs::create_dir_all(&parent).map_err(|e| tcsense_sensor::SensorError::io(&parent, e))?;
    let tmp = parent.join(format!(".{name}.{}.tmp", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| tcsense_sensor::SensorError::io(&tmp, e))?;
    Ok(tmp)
}

/// Rename the temporary directory into place on success; remove it on failure.
pub(crate) fn finish_output<T>(tmp: PathBuf, dir: &Path, result: Result<T>) -> Result<T> {
    match result {
        Ok(v) => {
            if dir.exists() {
                std::fs::remove_dir_all(dir).map_err(|e| tcsense_sensor::SensorError::io(dir, e))?;
            }
            std::fs::rename(&tmp, dir).map_err(|e| tcsense_sensor::SensorError::io(dir, e))?;
            Ok(v)
        }
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            Err(e)
        }
    }
}

/// Write one shard of items (all with the same fields) under `root/split/`.
pub(crate) fn write_shard(root: &Path, split: &str, index: usize, items: &[Item]) -> Result<Shard> {
    let mut files = BTreeMap::new();
    let Some(first) = items.first() else {
        return Ok(Shard { count: 0, files });
    };
    for (fi, (name, _)) in first.iter().enumerate() {
        let views: Vec<_> = items.iter().map(|it| it[fi].1.view()).collect();
        let stacked = stack(Axis(0), &views).map_err(|e| invalid("item shapes", name, e.to_string()))?;
        let rel = format!("{split}/{name}_{index:03}.npy");
        write_npy(&root.join(&rel), &stacked.view())?;
        files.insert(name.to_string(), rel);
    }
    Ok(Shard { count: items.len(), files })
}

pub(crate) fn write_manifest(root: &Path, m: &Manifest) -> Result<()> {
    let json = serde_json::to_string_pretty(m).map_err(|e| invalid("manifest", "", e.to_string()))? + "\n";
    Ok(write_bytes(&root.join("manifest.json"), json.as_bytes())?)
}

/// An opened dataset.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub dir: PathBuf,
    pub manifest: Manifest,
}

impl Manifest {
    /// Parse and check the text of a `manifest.json`; the error is a message without the
    /// file name.
    pub fn parse(text: &str) -> std::result::Result<Manifest, String> {
        let v: serde_json::Value = serde_json::from_str(text).map_err(|e| format!("malformed manifest: {e}"))?;
        let manifest: Manifest = serde_json::from_value(v.clone()).map_err(|e| format!("malformed manifest: {e}"))?;
        tcsense_sensor::json::reject_unknown_keys(&v, &tcsense_sensor::json::keys_of(&manifest))?;
        if manifest.format != "tcsense-dataset" || manifest.version != 1 {
            return Err(format!("format {:?} version {}, expected \"tcsense-dataset\" version 1", manifest.format, manifest.version));
        }
        manifest.grid.validate().map_err(|e| format!("field 'grid': {e}"))?;
        if manifest.grid.bins() != manifest.bins {
            return Err(format!("field 'bins' is {}, but the grid gives T = L·K = {}", manifest.bins, manifest.grid.bins()));
        }
        manifest.check_layout()?;
        Ok(manifest)
    }
}

impl Manifest {
    /// The frame size, the field shapes and the splits agree with each other, and every shard
    /// path stays inside the dataset directory.
    fn check_layout(&self) -> std::result::Result<(), String> {
        let [h, w] = self.size;
        if h == 0 || w == 0 {
            return Err(format!("field 'size' is {:?}, expected a non-empty frame [H, W]", self.size));
        }
        if let Some(x) = self.fields.get("x") {
            if x != &[self.bins, h, w] {
                return Err(format!("field 'fields.x' is {x:?}, expected [bins, H, W] = {:?}", [self.bins, h, w]));
            }
        }
        for (name, shape) in &self.fields {
            shape
                .iter()
                .try_fold(4usize, |acc, &d| acc.checked_mul(d))
                .filter(|&b| b > 0 && b <= 1 << 40)
                .ok_or_else(|| format!("field 'fields.{name}' is {shape:?}, expected a non-empty item shape"))?;
        }
        for split in &self.splits {
            let sum: usize = split.shards.iter().map(|s| s.count).sum();
            if sum != split.count {
                return Err(format!("split {:?}: 'count' is {}, but its shards hold {sum} items", split.name, split.count));
            }
            for shard in &split.shards {
                if !shard.files.keys().eq(self.fields.keys()) {
                    let got: Vec<&String> = shard.files.keys().collect();
                    let want: Vec<&String> = self.fields.keys().collect();
                    return Err(format!("split {:?}: a shard has files for {got:?}, expected one per field {want:?}", split.name));
                }
                for rel in shard.files.values() {
                    let inside = Path::new(rel).components().all(|c| matches!(c, std::path::Component::Normal(_)));
                    if !inside || rel.is_empty() {
                        return Err(format!(
                            "split {:?}: shard path {rel:?}, expected a relative path inside the dataset directory",
                            split.name
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

impl Dataset {
    /// Open `DIR/manifest.json` and check that every shard it lists is there with the shape the
    /// manifest gives (headers only); errors name the file and field.
    pub fn open(dir: &Path) -> Result<Self> {
        let path = dir.join("manifest.json");
        let text = std::fs::read_to_string(&path).map_err(|e| tcsense_sensor::SensorError::io(&path, e))?;
        let manifest = Manifest::parse(&text).map_err(|msg| file_err(&path, msg))?;
        let ds = Dataset { dir: dir.to_path_buf(), manifest };
        ds.check_shards()?;
        Ok(ds)
    }

    /// Every shard file exists, holds a `.npy` header of shape `[count, …item shape]` and is
    /// long enough for its data.
    fn check_shards(&self) -> Result<()> {
        use std::io::Read;
        for split in &self.manifest.splits {
            for shard in &split.shards {
                for (field, rel) in &shard.files {
                    let path = self.dir.join(rel);
                    let file = std::fs::File::open(&path).map_err(|e| tcsense_sensor::SensorError::io(&path, e))?;
                    let len = file.metadata().map_err(|e| tcsense_sensor::SensorError::io(&path, e))?.len();
                    let mut head = Vec::new();
                    file.take(1 << 17).read_to_end(&mut head).map_err(|e| tcsense_sensor::SensorError::io(&path, e))?;
                    let h = tcsense_sensor::npy::parse_header(&head).map_err(|msg| file_err(&path, msg))?;
                    let mut want = vec![shard.count];
                    want.extend_from_slice(&self.manifest.fields[field]);
                    if h.shape != want {
                        return Err(file_err(&path, format!("shape {:?}, expected {want:?} from the manifest", h.shape)));
                    }
                    let need = h.data_offset as u64 + (h.count() * h.size) as u64;
                    if len < need {
                        return Err(file_err(&path, format!("npy data truncated: {len} bytes, expected {need} for shape {:?}", h.shape)));
                    }
                }
            }
        }
        Ok(())
    }

    /// The split called `name`.
    pub fn split(&self, name: &str) -> Result<&Split> {
        self.manifest.splits.iter().find(|s| s.name == name).ok_or_else(|| {
            let names: Vec<&str> = self.manifest.splits.iter().map(|s| s.name.as_str()).collect();
            file_err(self.dir.join("manifest.json"), format!("no split {name:?}; the dataset has {names:?}"))
        })
    }

    /// Load one field of a whole split, `[count, …item shape]`.
    pub fn load(&self, split: &str, field: &str) -> Result<ArrayD<f32>> {
        self.load_first(split, field, None)
    }

    /// Load one field of the first `max` items of a split (all where `None`),
    /// `[min(max, count), …item shape]`: only the shards that hold them are read, each straight
    /// into the result (a training run on 640 of a FLIm split's 1 278 cubes of 4 MB read the
    /// whole split and copied it twice).
    pub fn load_first(&self, split: &str, field: &str, max: Option<usize>) -> Result<ArrayD<f32>> {
        let s = self.split(split)?;
        let item_shape = self
            .manifest
            .fields
            .get(field)
            .ok_or_else(|| file_err(self.dir.join("manifest.json"), format!("no field {field:?} in 'fields'")))?;
        let listed: usize = s.shards.iter().map(|sh| sh.count).sum();
        let n = max.unwrap_or(listed).min(listed);
        let mut shape = vec![n];
        shape.extend_from_slice(item_shape);
        let mut out = ArrayD::zeros(IxDyn(&shape));
        let mut at = 0;
        for sh in &s.shards {
            if at == n {
                break;
            }
            let rel = sh
                .files
                .get(field)
                .ok_or_else(|| file_err(self.dir.join("manifest.json"), format!("a shard of {split} lacks field {field:?}")))?;
            let path = self.dir.join(rel);
            let a = read_npy(&path)?;
            let mut want = vec![sh.count];
            want.extend_from_slice(item_shape);
            if a.shape() != want.as_slice() {
                return Err(file_err(&path, format!("shape {:?}, expected {want:?} from the manifest", a.shape())));
            }
            let take = sh.count.min(n - at);
            out.slice_axis_mut(Axis(0), Slice::from(at..at + take)).assign(&a.slice_axis(Axis(0), Slice::from(0..take)));
            at += take;
        }
        Ok(out)
    }

    /// Load one item's field (`[…item shape]`), index within the split.
    pub fn item(&self, split: &str, index: usize, field: &str) -> Result<ArrayD<f32>> {
        let s = self.split(split)?;
        if index >= s.count {
            return Err(invalid("index", index, format!("0..{} (items in split {split})", s.count)));
        }
        let mut offset = index;
        for sh in &s.shards {
            if offset < sh.count {
                let rel = sh.files.get(field).ok_or_else(|| file_err(self.dir.join("manifest.json"), format!("no field {field:?}")))?;
                let a = read_npy(&self.dir.join(rel))?;
                return Ok(a.index_axis(Axis(0), offset).to_owned());
            }
            offset -= sh.count;
        }
        Err(invalid("index", index, "an item listed in the manifest"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The first `max` items read from the shards that hold them are the whole split's first
    /// items, across a shard boundary, and `None` or too large a `max` gives the whole split.
    #[test]
    fn the_first_items_of_a_split_are_read_from_their_shards_only() {
        let dir = std::env::temp_dir().join(format!("tcsense-store-first-{}", std::process::id()));
        let gen = Generator::Lidar(crate::lidar::LidarParams { height: 8, width: 8, ..Default::default() });
        let grid = TimeGrid { length: 8, ..TimeGrid::default() };
        let cancel = AtomicBool::new(false);
        generate(&gen, &grid, 20, 4, &dir, &WriteOptions { shard_size: 3, force: true, progress: &|| {}, cancel: &cancel })
            .expect("a dataset");
        let ds = Dataset::open(&dir).expect("the dataset opens");
        let all = ds.load("train", "x").expect("the split");
        assert!(all.shape()[0] > 3 && ds.split("train").expect("train").shards.len() > 1, "{:?}", all.shape());
        for max in [1, 3, 5] {
            let first = ds.load_first("train", "x", Some(max)).expect("the first items");
            assert_eq!(first.shape()[0], max);
            assert_eq!(first, all.slice_axis(Axis(0), Slice::from(0..max)));
        }
        assert_eq!(ds.load_first("train", "x", Some(1000)).expect("all items"), all);
        assert_eq!(ds.load_first("train", "depth", None).expect("all labels").shape()[0], all.shape()[0]);
        // the shards after the items asked for are not read: a missing one does not matter
        let last = ds.split("train").expect("train").shards.last().expect("a shard").files["x"].clone();
        std::fs::remove_file(dir.join(last)).expect("the last shard removed");
        assert!(ds.load_first("train", "x", Some(3)).is_ok());
        assert!(ds.load("train", "x").is_err(), "the whole split needs the removed shard");
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn splits_follow_the_paper() {
        assert_eq!(split_counts(83, [63, 10, 10]), [63, 10, 10]);
        assert_eq!(split_counts(558, [446, 56, 56]), [446, 56, 56]);
        assert_eq!(split_counts(8, [63, 10, 10]), [6, 1, 1]);
        assert_eq!(split_counts(2, [63, 10, 10]), [2, 0, 0]);
    }
}
