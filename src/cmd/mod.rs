//! One module per subcommand family.

pub mod bench;
pub mod codes;
pub mod dataset;
pub mod demo;
pub mod deploy;
pub mod design;
pub mod eval;
pub mod recon;
pub mod sensor;
pub mod train;

/// Parse `HxW` (e.g. `2x2`, `188x212`).
pub fn parse_hw(s: &str) -> Result<(usize, usize), String> {
    let (a, b) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("{s:?} is not of the form HxW (e.g. 2x2)"))?;
    let p = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("{s:?} is not of the form HxW (e.g. 2x2)"));
    Ok((p(a)?, p(b)?))
}
