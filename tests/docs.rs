//! Every command README.md and `docs/` show works as written.
//!
//! - ```` ```sh ```` blocks run, in order, page by page, with `bash -euo pipefail` in a fresh
//!   directory that holds the repository's `zoo/` (the pages say: run from the repository's
//!   root) and with the `tcsense` this test built first on the `PATH`. A failing command fails
//!   the test with the page, the block and the output.
//! - ```` ```text ```` blocks are synopses (the command map, option lists): each of their
//!   `tcsense SUB …` lines must name commands that exist (`tcsense SUB … --help` succeeds), with
//!   `a|b` alternatives checked one by one.
//! - README's two commands (`scripts/demo.sh`, `scripts/test.sh`) are the indented lines:
//!   `.ci/run` runs the second; `tests/demo.rs` runs the demo on its quick budget.
//!
//! ```` ```python ```` blocks are run by the Python suite (`python/tests/test_docs.py`).

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The pages: README.md and every `docs/*.md`, sorted.
fn pages() -> Vec<PathBuf> {
    let mut out = vec![root().join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root().join("docs"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    docs.sort();
    out.extend(docs);
    out
}

/// The fenced blocks of a Markdown page: `(info string, first line number, body)`.
fn blocks(text: &str) -> Vec<(String, usize, String)> {
    let mut out = Vec::new();
    let mut open: Option<(String, usize, String)> = None;
    for (i, line) in text.lines().enumerate() {
        match (&mut open, line.strip_prefix("```")) {
            (None, Some(info)) => open = Some((info.trim().to_string(), i + 1, String::new())),
            (Some(_), Some(_)) => out.extend(open.take()),
            (Some((_, _, body)), None) => {
                body.push_str(line);
                body.push('\n');
            }
            (None, None) => {}
        }
    }
    out
}

/// The subcommand paths a synopsis line `tcsense a b|c --flag …` names: `[a, b]`, `[a, c]`.
fn synopsis_commands(line: &str) -> Vec<Vec<String>> {
    let mut paths: Vec<Vec<String>> = vec![Vec::new()];
    for tok in line.split_whitespace().skip(1) {
        let is_word = |w: &str| {
            !w.is_empty()
                && w.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
                && w.starts_with(|c: char| c.is_ascii_lowercase())
        };
        let alts: Vec<&str> = tok.split('|').collect();
        if !alts.iter().all(|a| is_word(a)) {
            break;
        }
        paths = paths.into_iter().flat_map(|p| alts.iter().map(move |a| [p.clone(), vec![a.to_string()]].concat())).collect();
    }
    paths
}

#[test]
fn the_synopses_name_commands_that_exist() {
    let mut checked = 0;
    for page in pages() {
        let text = std::fs::read_to_string(&page).unwrap();
        for (info, line, body) in blocks(&text) {
            if info != "text" {
                continue;
            }
            for l in body.lines().filter(|l| l.starts_with("tcsense ")) {
                for path in synopsis_commands(l) {
                    let o = common::bin().args(&path).arg("--help").output().unwrap();
                    assert!(
                        o.status.success(),
                        "{}:{line}: `tcsense {} --help` failed: {}\n(synopsis: {l})",
                        page.display(),
                        path.join(" "),
                        String::from_utf8_lossy(&o.stderr)
                    );
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 40, "only {checked} synopsis commands found");
}

/// Run one page's `sh` blocks in order in `dir`.
fn run_page(page: &Path, dir: &Path) -> usize {
    let text = std::fs::read_to_string(page).unwrap();
    let bin_dir = Path::new(env!("CARGO_BIN_EXE_tcsense")).parent().unwrap().to_path_buf();
    let path = format!("{}:{}", bin_dir.display(), std::env::var("PATH").unwrap_or_default());
    let mut ran = 0;
    for (info, line, body) in blocks(&text) {
        if info != "sh" {
            continue;
        }
        let o = Command::new("bash").args(["-euo", "pipefail", "-c", &body]).current_dir(dir).env("PATH", &path).output().unwrap();
        assert!(
            o.status.success(),
            "{}:{line}: the block failed (exit {:?})\n--- block\n{body}--- stdout\n{}--- stderr\n{}",
            page.display(),
            o.status.code(),
            String::from_utf8_lossy(&o.stdout),
            String::from_utf8_lossy(&o.stderr)
        );
        ran += body.lines().filter(|l| l.starts_with("tcsense ")).count();
    }
    ran
}

#[test]
fn every_command_of_the_pages_runs_as_written() {
    let mut ran = 0;
    for page in pages() {
        let tmp = common::tempdir();
        std::os::unix::fs::symlink(root().join("zoo"), tmp.path().join("zoo")).unwrap();
        ran += run_page(&page, tmp.path());
    }
    assert!(ran >= 30, "only {ran} commands ran");
}

#[test]
fn the_parser_finds_blocks_and_commands() {
    let md = "a\n```sh\ntcsense codes check c.json\n```\n```text\ntcsense train admm-net|unet … -o RUN\n```\n";
    let b = blocks(md);
    assert_eq!(b.len(), 2);
    assert_eq!((b[0].0.as_str(), b[0].1, b[0].2.as_str()), ("sh", 2, "tcsense codes check c.json\n"));
    assert_eq!(
        synopsis_commands(b[1].2.lines().next().unwrap()),
        vec![vec!["train".to_string(), "admm-net".into()], vec!["train".into(), "unet".into()]]
    );
    assert_eq!(synopsis_commands("tcsense bench forward | dataset"), vec![vec!["bench".to_string(), "forward".into()]]);
    assert_eq!(synopsis_commands("tcsense depth xhat.npy [--peaks 2]"), vec![vec!["depth".to_string()]]);
}
