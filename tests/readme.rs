//! README.md is true to the tree: every path its layout names exists, and its list of which
//! crate uses which is exactly the `tcsense-*` dependencies of the Cargo.toml files.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn readme() -> String {
    std::fs::read_to_string(root().join("README.md")).unwrap()
}

/// The fenced block that follows `after` in the README.
fn block_after(text: &str, after: &str) -> String {
    let at = text.find(after).unwrap_or_else(|| panic!("README.md has no {after:?}"));
    let rest = &text[at..];
    let open = rest.find("```\n").expect("a fenced block") + 4;
    let close = rest[open..].find("```").expect("a closed block");
    rest[open..open + close].to_string()
}

#[test]
fn every_path_the_layout_names_exists() {
    let layout = block_after(&readme(), "## Layout");
    let mut checked = 0;
    for line in layout.lines() {
        // the directory that starts the line
        if let Some(dir) = line.split_whitespace().next().filter(|w| w.ends_with('/') && !line.starts_with(' ')) {
            assert!(root().join(dir).is_dir(), "README layout names {dir}, which is not a directory");
            checked += 1;
        }
    }
    // every `file.rs` or `dir/` in backquotes names a file of the crate of its paragraph
    let mut crate_dir = String::new();
    for line in layout.lines() {
        if !line.starts_with(' ') {
            crate_dir = line.split_whitespace().next().unwrap_or_default().to_string();
        }
        for (i, part) in line.split('`').enumerate() {
            if i % 2 == 1 && (part.ends_with(".rs") || part.ends_with('/')) && !part.contains(' ') {
                let found = [Path::new(&crate_dir).join("src").join(part), Path::new(&crate_dir).join(part)]
                    .iter()
                    .any(|p| root().join(p).exists());
                assert!(found, "README layout names `{part}` under {crate_dir}, which does not exist");
                checked += 1;
            }
        }
    }
    assert!(checked > 20, "only {checked} paths checked");
}

/// The `tcsense-*` dependencies of a Cargo.toml's `[dependencies]`.
fn dependencies(manifest: &Path) -> BTreeSet<String> {
    let text = std::fs::read_to_string(manifest).unwrap();
    let mut in_deps = false;
    let mut out = BTreeSet::new();
    for line in text.lines() {
        if line.starts_with('[') {
            in_deps = line.trim() == "[dependencies]";
        } else if in_deps {
            if let Some(name) = line.strip_prefix("tcsense-").and_then(|l| l.split(|c: char| !c.is_ascii_alphanumeric()).next()) {
                out.insert(name.to_string());
            }
        }
    }
    out
}

#[test]
fn the_crate_arrows_are_the_cargo_dependencies() {
    let arrows = block_after(&readme(), "Each crate and the crates it uses");
    let drawn: BTreeMap<String, BTreeSet<String>> = arrows
        .lines()
        .filter_map(|l| l.split_once('→'))
        .map(|(from, to)| (from.trim().to_string(), to.split(',').map(|s| s.trim().to_string()).collect()))
        .collect();
    let crates = ["sensor", "datasets", "kernels", "fits", "models", "train", "infer", "pipeline", "python"];
    let mut actual: BTreeMap<String, BTreeSet<String>> =
        crates.iter().map(|c| (c.to_string(), dependencies(&root().join(c).join("Cargo.toml")))).filter(|(_, d)| !d.is_empty()).collect();
    actual.insert("tcsense".into(), dependencies(&root().join("Cargo.toml")));
    assert_eq!(drawn, actual, "README's crate list against the Cargo.toml files");
    // and no circle: peel off crates whose dependencies are all peeled, until none is left
    let mut left: BTreeMap<String, BTreeSet<String>> = drawn.clone();
    for leaf in ["sensor", "kernels"] {
        left.entry(leaf.into()).or_default();
    }
    while !left.is_empty() {
        let ready: Vec<String> = left.iter().filter(|(_, d)| d.iter().all(|x| !left.contains_key(x))).map(|(c, _)| c.clone()).collect();
        assert!(!ready.is_empty(), "a circle among {:?}", left.keys().collect::<Vec<_>>());
        for c in ready {
            left.remove(&c);
        }
    }
}
