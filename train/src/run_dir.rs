//! The training side of a run directory (the layout is in `tcsense_models::runs`):
//! checkpoints replaced atomically after every epoch, the progress state, `metrics.csv`, and
//! the latest weights at the top of the directory.
//!
//! ```text
//! RUN/checkpoint/{model.bpk, optim.bpk, state.json}   written to checkpoint.tmp/, then renamed
//! RUN/metrics.csv                                      epoch,step,train_loss,<validation columns>,seconds
//! RUN/model.bpk                                        written as model-new.bpk, then renamed
//! ```

use burn::module::Module;
use burn::optim::ModuleOptimizer;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use tcsense_models::runs::{WEIGHTS_FILE, WEIGHTS_STEM};
use tcsense_sensor::npy::write_bytes;

use crate::{file_err, Result};

/// The checkpoint directory.
pub const CHECKPOINT_DIR: &str = "checkpoint";
/// The previous checkpoint while a new one is moved into place.
const CHECKPOINT_OLD: &str = "checkpoint.old";
/// A checkpoint being written.
const CHECKPOINT_TMP: &str = "checkpoint.tmp";
/// The metrics log.
pub const METRICS_FILE: &str = "metrics.csv";
/// The progress state inside a checkpoint.
pub const STATE_FILE: &str = "state.json";
/// Training seconds per epoch, the run's only clock reading.
pub const TIMING_FILE: &str = "timing.csv";

/// Progress of a run after a checkpoint.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RunState {
    /// Epochs completed.
    pub epoch: usize,
    /// Optimiser steps taken.
    pub step: u64,
    /// Seconds of training so far (kept in `timing.csv`, not in `state.json`: a clock in the
    /// checkpoint would make two runs of one seed differ).
    #[serde(default, skip_serializing)]
    pub seconds: f64,
    /// Digest of the dataset's manifest the run started on: a resume on a dataset that changed
    /// since is refused (absent in runs from before it was recorded, which are not checked).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dataset: Option<String>,
}

/// One row of `metrics.csv`.
#[derive(Debug, Clone, PartialEq)]
pub struct EpochMetrics {
    pub epoch: usize,
    pub step: u64,
    pub train_loss: f64,
    /// Validation metrics by column name: `val_mse`, `val_psnr_db` for cube networks;
    /// `val_depth_rmse_m`, `val_depth_mae_m`, `val_detection` for depth networks.
    pub val: Vec<(String, f64)>,
    pub seconds: f64,
}

impl EpochMetrics {
    /// A validation metric by column name (NaN if the row has none of that name).
    pub fn get(&self, name: &str) -> f64 {
        self.val.iter().find(|(n, _)| n == name).map_or(f64::NAN, |(_, v)| *v)
    }
}

/// Write `v` as pretty JSON, atomically.
pub fn write_json<T: Serialize>(path: &Path, v: &T) -> Result<()> {
    let s = serde_json::to_string_pretty(v).map_err(|e| file_err(path, e))? + "\n";
    Ok(write_bytes(path, s.as_bytes())?)
}

/// Read JSON into `T`.
pub fn read_json<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| file_err(path, e))?;
    serde_json::from_str(&text).map_err(|e| file_err(path, format!("malformed JSON: {e}")))
}

/// The checkpoint to resume from: `checkpoint/`, or `checkpoint.old/` when a kill came while
/// the new one was being moved into place; `None` when the run has none yet (killed in its
/// first epoch); an error naming `checkpoint/state.json` when one is there but incomplete.
pub fn latest_checkpoint(run: &Path) -> Result<Option<PathBuf>> {
    let ckpt = run.join(CHECKPOINT_DIR);
    let old = run.join(CHECKPOINT_OLD);
    if ckpt.join(STATE_FILE).exists() {
        Ok(Some(ckpt))
    } else if old.join(STATE_FILE).exists() {
        Ok(Some(old))
    } else if ckpt.exists() || old.exists() {
        Err(file_err(&ckpt.join(STATE_FILE), "incomplete checkpoint: the progress state is missing"))
    } else {
        Ok(None)
    }
}

/// Load a checkpoint's weights into `model`, its optimiser state and its progress.
pub fn load_checkpoint<M: Module>(dir: &Path, model: M, optim: ModuleOptimizer) -> Result<(M, ModuleOptimizer, RunState)> {
    let state: RunState = read_json(&dir.join(STATE_FILE))?;
    let model = model.try_load_file(dir.join(WEIGHTS_STEM)).map_err(|e| file_err(&dir.join(WEIGHTS_FILE), e))?;
    let optim = optim.load(dir.join(OPTIMIZER_FILE)).map_err(|e| file_err(&dir.join(OPTIMIZER_FILE), e))?;
    Ok((model, optim, state))
}

/// The optimiser state inside a checkpoint.
pub const OPTIMIZER_FILE: &str = "optim.bpk";

/// Write the optimiser state to `path` with its entries sorted by name: burn collects them
/// from a hash map, so the same state would otherwise come out in another order every run
/// (same seed, same bytes covers this file too). Parameter ids are fixed by the seeded init.
fn save_optimizer(optim: &ModuleOptimizer, path: &Path) -> Result<()> {
    let err = |e: &dyn std::fmt::Display| file_err(path, e.to_string());
    let bytes = optim.into_bytes().map_err(|e| err(&e))?;
    let reader = burn_pack::Reader::from_bytes(bytes).map_err(|e| err(&e))?;
    let (scalars, metadata) = (reader.scalars().clone(), reader.metadata().clone());
    let mut tensors = reader.into_tensors().map_err(|e| err(&e))?;
    tensors.sort_by(|a, b| a.name.cmp(&b.name));
    let mut writer = burn_pack::Writer::new(tensors).auto_extension(false);
    for (k, v) in &scalars {
        writer = writer.with_scalar(k, *v);
    }
    for (k, v) in &metadata {
        writer = writer.with_metadata(k, v);
    }
    writer.write_to_file(path).map_err(|e| err(&e))
}

/// Write a checkpoint (weights, optimiser, progress) and the latest weights, each replaced
/// atomically: a kill at any point leaves a complete checkpoint behind.
/// `extra` writes more files into the checkpoint (e.g. learned code logits) before it is
/// moved into place.
pub fn save_checkpoint<M: Module>(
    run: &Path,
    model: &M,
    optim: &ModuleOptimizer,
    state: &RunState,
    extra: &dyn Fn(&Path) -> Result<()>,
) -> Result<()> {
    let tmp = run.join(CHECKPOINT_TMP);
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| file_err(&tmp, e))?;
    model.clone().save_file(tmp.join(WEIGHTS_STEM)).map_err(|e| file_err(&tmp.join(WEIGHTS_FILE), e))?;
    save_optimizer(optim, &tmp.join(OPTIMIZER_FILE))?;
    extra(&tmp)?;
    write_json(&tmp.join(STATE_FILE), state)?;
    failpoint("checkpoint-written");
    let (ckpt, old) = (run.join(CHECKPOINT_DIR), run.join(CHECKPOINT_OLD));
    if ckpt.join(STATE_FILE).exists() {
        // the complete checkpoint becomes the old one; a kill from here on leaves it to resume from
        let _ = std::fs::remove_dir_all(&old);
        std::fs::rename(&ckpt, &old).map_err(|e| file_err(&ckpt, e))?;
        failpoint("checkpoint-renamed");
    } else {
        // an earlier kill between the renames: checkpoint.old/ is the complete one, keep it
        let _ = std::fs::remove_dir_all(&ckpt);
    }
    std::fs::rename(&tmp, &ckpt).map_err(|e| file_err(&ckpt, e))?;
    failpoint("checkpoint-placed");
    let _ = std::fs::remove_dir_all(&old);
    // latest weights at the top of the run directory, replaced atomically
    let weights = run.join(WEIGHTS_FILE);
    model.clone().save_file(run.join("model-new")).map_err(|e| file_err(&weights, e))?;
    failpoint("weights-written");
    std::fs::rename(run.join("model-new.bpk"), &weights).map_err(|e| file_err(&weights, e))?;
    Ok(())
}

/// A test hook for the kill-and-resume test: with `TCSENSE_FAILPOINT=NAME@N` in the
/// environment the process dies (abort: no destructor, no cleanup, like SIGKILL) the N-th
/// time it reaches the point `NAME` of a checkpoint write. Without the variable it does
/// nothing.
fn failpoint(name: &str) {
    use std::sync::atomic::{AtomicUsize, Ordering};
    static HITS: AtomicUsize = AtomicUsize::new(0);
    let Ok(spec) = std::env::var("TCSENSE_FAILPOINT") else { return };
    let Some((point, n)) = spec.split_once('@') else { return };
    if point == name && n.parse::<usize>().ok() == Some(HITS.fetch_add(1, Ordering::SeqCst) + 1) {
        std::process::abort();
    }
}

/// Write `metrics.csv` (the validation columns of the first row name the header) and, beside
/// it, `timing.csv` (`epoch,seconds`: training seconds so far). The clock is kept out of
/// every other file of the run, so two runs of one seed write the same bytes but for it.
pub fn write_rows(path: &Path, rows: &[EpochMetrics]) -> Result<()> {
    let names: Vec<&str> = rows.first().map(|r| r.val.iter().map(|(n, _)| n.as_str()).collect()).unwrap_or_default();
    let mut s = format!("epoch,step,train_loss{}\n", names.iter().map(|n| format!(",{n}")).collect::<String>());
    let mut t = String::from("epoch,seconds\n");
    for r in rows {
        let vals: String = r.val.iter().map(|(n, v)| if n.ends_with("_db") { format!(",{v:.3}") } else { format!(",{v:.6e}") }).collect();
        s.push_str(&format!("{},{},{:.6e}{vals}\n", r.epoch, r.step, r.train_loss));
        t.push_str(&format!("{},{:.2}\n", r.epoch, r.seconds));
    }
    write_bytes(&timing_path(path), t.as_bytes())?;
    Ok(write_bytes(path, s.as_bytes())?)
}

/// `timing.csv` beside a `metrics.csv`.
fn timing_path(metrics: &Path) -> PathBuf {
    metrics.with_file_name(TIMING_FILE)
}

/// Read the rows of `metrics.csv` up to epoch `upto` (the checkpoint's); none if it is missing.
/// Their seconds come from `timing.csv` beside it (or the last column of a `metrics.csv`
/// written before the clock moved out; 0 when neither has it).
pub fn read_rows(path: &Path, upto: usize) -> Result<Vec<EpochMetrics>> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(Vec::new()) };
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().unwrap_or_default().split(',').collect();
    if header.len() < 3 || header[..3] != ["epoch", "step", "train_loss"] {
        return Err(file_err(path, format!("header {header:?} lacks epoch,step,train_loss,…")));
    }
    let old = header.last() == Some(&"seconds");
    let names = &header[3..header.len() - old as usize];
    let p = |path: &Path, s: &str| s.parse::<f64>().map_err(|_| file_err(path, format!("bad number {s:?}")));
    let timing = timing_path(path);
    let mut seconds = std::collections::HashMap::new();
    if let Ok(t) = std::fs::read_to_string(&timing) {
        for line in t.lines().skip(1) {
            let (e, s) = line.split_once(',').ok_or_else(|| file_err(&timing, format!("row {line:?} is not epoch,seconds")))?;
            seconds.insert(p(&timing, e)? as usize, p(&timing, s)?);
        }
    }
    let mut rows = Vec::new();
    for line in lines {
        let f: Vec<&str> = line.split(',').collect();
        if f.len() != header.len() {
            return Err(file_err(path, format!("row {line:?} does not have {} fields", header.len())));
        }
        let epoch = p(path, f[0])? as usize;
        if epoch <= upto {
            let val = names.iter().zip(&f[3..3 + names.len()]).map(|(n, v)| Ok((n.to_string(), p(path, v)?))).collect::<Result<_>>()?;
            let secs = match seconds.get(&epoch) {
                Some(s) => *s,
                None if old => p(path, f[f.len() - 1])?,
                None => 0.0,
            };
            rows.push(EpochMetrics { epoch, step: p(path, f[1])? as u64, train_loss: p(path, f[2])?, val, seconds: secs });
        }
    }
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_rows_round_trip_and_stop_at_the_checkpoint() {
        let dir = std::env::temp_dir().join(format!("tcsense-rows-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(METRICS_FILE);
        let val = vec![("val_mse".to_string(), 1e-3), ("val_psnr_db".to_string(), 30.0)];
        let rows: Vec<EpochMetrics> = (1..=3)
            .map(|e| EpochMetrics { epoch: e, step: 3 * e as u64, train_loss: 0.5 / e as f64, val: val.clone(), seconds: e as f64 })
            .collect();
        write_rows(&path, &rows).unwrap();
        assert!(std::fs::read_to_string(&path).unwrap().starts_with("epoch,step,train_loss,val_mse,val_psnr_db\n"));
        assert_eq!(std::fs::read_to_string(dir.join(TIMING_FILE)).unwrap(), "epoch,seconds\n1,1.00\n2,2.00\n3,3.00\n");
        let back = read_rows(&path, 2).unwrap();
        assert_eq!(back.len(), 2);
        assert_eq!((back[1].epoch, back[1].step, back[1].seconds), (2, 6, 2.0));
        assert!((back[1].train_loss - 0.25).abs() < 1e-9);
        assert_eq!((back[1].get("val_psnr_db"), back[1].get("val_mse")), (30.0, 1e-3));
        // a metrics.csv from before timing.csv: its last column is the clock
        std::fs::remove_file(dir.join(TIMING_FILE)).unwrap();
        std::fs::write(&path, "epoch,step,train_loss,val_mse,seconds\n1,2,3,4,5\n").unwrap();
        let back = read_rows(&path, 5).unwrap();
        assert_eq!((back[0].get("val_mse"), back[0].seconds), (4.0, 5.0));
        std::fs::write(&path, "epoch,step,train_loss,val_mse,seconds\n1,2,3\n").unwrap();
        assert!(read_rows(&path, 5).unwrap_err().to_string().contains("5 fields"));
        assert!(read_rows(&dir.join("missing.csv"), 5).unwrap().is_empty());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

/// The lock file of a run directory that a training process holds.
pub const LOCK_FILE: &str = ".lock";

/// A run directory held by this process: created exclusively (`RUN/.lock` with the pid), so
/// a second training into the same directory is refused instead of interleaving; removed on
/// drop. A lock left by a process that no longer runs (killed) is taken over.
#[derive(Debug)]
pub struct RunLock {
    path: PathBuf,
}

impl RunLock {
    /// Take the lock of `run` (which must exist).
    pub fn acquire(run: &Path) -> Result<Self> {
        use std::io::Write;
        let path = run.join(LOCK_FILE);
        for _ in 0..2 {
            match std::fs::OpenOptions::new().write(true).create_new(true).open(&path) {
                Ok(mut f) => {
                    writeln!(f, "{}", std::process::id()).map_err(|e| file_err(&path, e))?;
                    return Ok(RunLock { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    Self::free(run)?;
                    // the holder is gone (killed): take the lock over
                    let _ = std::fs::remove_file(&path);
                }
                Err(e) => return Err(file_err(&path, e)),
            }
        }
        Err(file_err(&path, "cannot take the run directory's lock"))
    }

    /// `Ok` unless another running training holds `run`'s lock (one that is starting, too,
    /// before it has written anything else there): a resume is refused then, naming it.
    pub fn free(run: &Path) -> Result<()> {
        let path = run.join(LOCK_FILE);
        let holder = std::fs::read_to_string(&path).ok().and_then(|s| s.trim().parse::<u32>().ok());
        match holder {
            Some(pid) if process_alive(pid) => Err(file_err(
                run,
                format!(
                    "another training (process {pid}) is writing this run directory; wait for it or stop it (its lock is {})",
                    path.display()
                ),
            )),
            _ => Ok(()),
        }
    }
}

impl Drop for RunLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether process `pid` runs (Linux: `/proc/PID`; elsewhere assume it does).
fn process_alive(pid: u32) -> bool {
    if pid == std::process::id() {
        return true;
    }
    let proc_dir = Path::new("/proc");
    if proc_dir.is_dir() {
        proc_dir.join(pid.to_string()).exists()
    } else {
        true
    }
}
