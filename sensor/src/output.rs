//! A command's outputs, written all or none.
//!
//! - [`Outputs`]: the files one command writes (`-o`, `--ply`, `--png`, …). [`Outputs::plan`]
//!   checks them before any work is done — two flags naming one path, a directory where a file
//!   goes, a parent that is a file — and each output is written to a staged sibling that
//!   [`Outputs::commit`] renames into place once every output is complete. A failure or an
//!   interruption before that leaves the previous files as they were and no staged file behind.
//! - [`replace_dir`]: a directory of outputs (a code-memory image, a stream's products) filled in
//!   a temporary sibling and renamed over the old one whole, so that no file of an earlier run
//!   survives beside the new ones; a directory holding files the command does not write is
//!   refused rather than replaced.

use crate::error::{Result, SensorError};
use std::path::{Component, Path, PathBuf};

/// The parent directory of `path` (`.` for a bare file name).
pub(crate) fn parent_of(path: &Path) -> PathBuf {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    }
}

/// `path` made absolute and lexically normal (`a/./b/../c` → `a/c`), for comparing outputs
/// that do not exist yet.
fn normal(path: &Path) -> PathBuf {
    let abs = if path.is_absolute() { path.to_path_buf() } else { std::env::current_dir().unwrap_or_default().join(path) };
    // an existing parent resolves symbolic links, so that two spellings of one file compare equal
    let (dir, name) = (parent_of(&abs), abs.file_name().map(|n| n.to_os_string()));
    let dir = std::fs::canonicalize(&dir).unwrap_or(dir);
    let mut out = PathBuf::new();
    for c in dir.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            c => out.push(c),
        }
    }
    if let Some(n) = name {
        out.push(n);
    }
    out
}

/// Check that the directory `dir` is one, or can be made one: no file stands at it or above it.
fn check_dir_possible(dir: &Path, of: &Path) -> Result<()> {
    let mut d = Some(dir);
    while let Some(p) = d {
        if p.as_os_str().is_empty() {
            break;
        }
        if p.exists() {
            if !p.is_dir() {
                return Err(SensorError::file(of, format!("cannot be written: {} is a file, not a directory", p.display())));
            }
            break;
        }
        d = p.parent();
    }
    Ok(())
}

/// The files one command writes, all or none (see the module docs).
#[derive(Debug, Default)]
pub struct Outputs {
    /// `(staged, final)` of every output written so far.
    staged: Vec<(PathBuf, PathBuf)>,
    committed: bool,
}

impl Outputs {
    /// Check the outputs `(flag, path)` a command is about to write: distinct paths, none an
    /// existing directory, every parent a directory or creatable. Errors name the flag and path.
    pub fn plan(outputs: &[(&str, &Path)]) -> Result<Outputs> {
        let mut seen: Vec<(&str, PathBuf)> = Vec::new();
        for &(flag, path) in outputs {
            if path.as_os_str().is_empty() || path.file_name().is_none() {
                return Err(SensorError::file(path, format!("{flag}: expected a file name")));
            }
            if path.is_dir() {
                return Err(SensorError::file(path, format!("{flag}: is a directory; expected a file to write")));
            }
            check_dir_possible(&parent_of(path), path)?;
            let n = normal(path);
            if let Some((other, _)) = seen.iter().find(|(_, p)| *p == n) {
                return Err(SensorError::file(path, format!("named by both {other} and {flag}; each output needs its own file")));
            }
            seen.push((flag, n));
        }
        Ok(Outputs::default())
    }

    /// Where to write the output `path` now: a staged sibling with the same extension, renamed
    /// over `path` by [`Outputs::commit`] (its parent is created here).
    pub fn stage(&mut self, path: &Path) -> Result<PathBuf> {
        let dir = parent_of(path);
        std::fs::create_dir_all(&dir).map_err(|e| SensorError::io(&dir, e))?;
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "out".into());
        // the extension stays last: writers that choose the format by it still see it
        let staged = dir.join(format!(".staged-{}-{}-{name}", std::process::id(), self.staged.len()));
        self.staged.push((staged.clone(), path.to_path_buf()));
        Ok(staged)
    }

    /// Rename every staged output into place.
    pub fn commit(mut self) -> Result<()> {
        self.committed = true;
        let staged = std::mem::take(&mut self.staged);
        for (i, (from, to)) in staged.iter().enumerate() {
            if let Err(e) = std::fs::rename(from, to) {
                for (f, _) in &staged[i..] {
                    let _ = std::fs::remove_file(f);
                }
                return Err(SensorError::io(to, e));
            }
        }
        Ok(())
    }
}

impl Drop for Outputs {
    fn drop(&mut self) {
        if !self.committed {
            for (f, _) in &self.staged {
                let _ = std::fs::remove_file(f);
            }
        }
    }
}

/// Fill the output directory `dir` whole: `fill` writes into a fresh temporary sibling, which
/// then replaces `dir` (the old one removed only once the new one is complete). An existing
/// `dir` is replaced only when every entry in it is one `ours` accepts (the command's own files);
/// otherwise it is refused, naming the first foreign entry. On error nothing changes.
pub fn replace_dir<T, E: From<SensorError>>(
    dir: &Path,
    ours: &dyn Fn(&str) -> bool,
    fill: impl FnOnce(&Path) -> std::result::Result<T, E>,
) -> std::result::Result<T, E> {
    if dir.as_os_str().is_empty() || dir.file_name().is_none() {
        return Err(E::from(SensorError::file(dir, "expected a directory name for the output")));
    }
    if dir.exists() {
        if !dir.is_dir() {
            return Err(E::from(SensorError::file(dir, "exists and is a file; expected a directory for the output")));
        }
        let entries = std::fs::read_dir(dir).map_err(|e| E::from(SensorError::io(dir, e)))?;
        for e in entries {
            let e = e.map_err(|e| E::from(SensorError::io(dir, e)))?;
            let name = e.file_name().to_string_lossy().into_owned();
            if !ours(&name) {
                return Err(E::from(SensorError::file(
                    dir,
                    format!("exists and holds {name:?}, which this command does not write; choose a new directory or remove it (an output directory is replaced whole)"),
                )));
            }
        }
    }
    let parent = parent_of(dir);
    check_dir_possible(&parent, dir).map_err(E::from)?;
    std::fs::create_dir_all(&parent).map_err(|e| E::from(SensorError::io(&parent, e)))?;
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let tmp = parent.join(format!(".{name}.{}.tmp", std::process::id()));
    let old = parent.join(format!(".{name}.{}.old", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let result = std::fs::create_dir_all(&tmp).map_err(|e| E::from(SensorError::io(&tmp, e))).and_then(|_| fill(&tmp));
    let value = match result {
        Ok(v) => v,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
    };
    // the old directory moves aside first, so that a failed rename leaves it in place
    let had_old = dir.exists();
    if had_old {
        if let Err(e) = std::fs::rename(dir, &old) {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(E::from(SensorError::io(dir, e)));
        }
    }
    if let Err(e) = std::fs::rename(&tmp, dir) {
        if had_old {
            let _ = std::fs::rename(&old, dir);
        }
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(E::from(SensorError::io(dir, e)));
    }
    if had_old {
        let _ = std::fs::remove_dir_all(&old);
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_refuses_one_path_twice_and_directories() {
        let dir = crate::npy::tests::tempdir();
        let a = dir.join("a.npy");
        let e = Outputs::plan(&[("-o", &a), ("--ply", &dir.join("./a.npy"))]).unwrap_err().to_string();
        assert!(e.contains("named by both -o and --ply"), "{e}");
        let e = Outputs::plan(&[("--ply", &dir)]).unwrap_err().to_string();
        assert!(e.contains("--ply: is a directory"), "{e}");
        std::fs::write(dir.join("file"), b"x").unwrap();
        let e = Outputs::plan(&[("-o", &dir.join("file/x.npy"))]).unwrap_err().to_string();
        assert!(e.contains("is a file, not a directory"), "{e}");
        Outputs::plan(&[("-o", &a), ("--png", &dir.join("a.png"))]).unwrap();
    }

    #[test]
    fn staged_outputs_appear_together_or_not_at_all() {
        let dir = crate::npy::tests::tempdir();
        let (a, b) = (dir.join("a.txt"), dir.join("sub/b.txt"));
        std::fs::write(&a, b"old").unwrap();
        // dropped before commit: the old file stays, nothing staged remains
        let mut o = Outputs::plan(&[("-o", &a), ("--b", &b)]).unwrap();
        std::fs::write(o.stage(&a).unwrap(), b"new").unwrap();
        drop(o);
        assert_eq!(std::fs::read(&a).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1, "only a.txt: the staged file is gone");
        // committed: both in place
        let mut o = Outputs::plan(&[("-o", &a), ("--b", &b)]).unwrap();
        let sa = o.stage(&a).unwrap();
        assert!(sa.to_string_lossy().ends_with("a.txt"));
        std::fs::write(sa, b"new").unwrap();
        std::fs::write(o.stage(&b).unwrap(), b"bee").unwrap();
        o.commit().unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"new");
        assert_eq!(std::fs::read(&b).unwrap(), b"bee");
    }

    #[test]
    fn replace_dir_replaces_whole_and_refuses_foreign_directories() {
        let root = crate::npy::tests::tempdir();
        let out = root.join("out");
        let ours = |n: &str| n.ends_with(".bin");
        replace_dir(&out, &ours, |d| -> Result<()> {
            std::fs::write(d.join("a.bin"), b"1").unwrap();
            std::fs::write(d.join("b.bin"), b"2").unwrap();
            Ok(())
        })
        .unwrap();
        // a second, smaller output leaves no file of the first
        replace_dir(&out, &ours, |d| -> Result<()> {
            std::fs::write(d.join("a.bin"), b"3").unwrap();
            Ok(())
        })
        .unwrap();
        let names: Vec<_> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(names, vec![std::ffi::OsString::from("a.bin")]);
        // a failure changes nothing and leaves no temporary directory
        let e = replace_dir(&out, &ours, |d| -> Result<()> {
            std::fs::write(d.join("a.bin"), b"4").unwrap();
            Err(SensorError::file(d, "failed"))
        });
        assert!(e.is_err());
        assert_eq!(std::fs::read(out.join("a.bin")).unwrap(), b"3");
        assert_eq!(std::fs::read_dir(&root).unwrap().count(), 1);
        // a directory with a file the command does not write is refused
        std::fs::write(out.join("notes.txt"), b"mine").unwrap();
        let e = replace_dir(&out, &ours, |_| -> Result<()> { Ok(()) }).unwrap_err().to_string();
        assert!(e.contains("notes.txt") && e.contains("does not write"), "{e}");
        assert!(out.join("notes.txt").exists());
    }
}
