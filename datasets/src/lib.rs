//! `tcsense-datasets`: synthetic transient datasets and their storage.
//!
//! - [`lidar`]: procedural 3-D scenes (planes, boxes, spheres, a back wall) seen by a pinhole
//!   camera, Lambertian textured albedo with `1/r²` fall-off, an optional weakly diffusive
//!   sheet (two returns), interreflection tails and ambient light, randomised by default
//!   (depth range, noise textures, slanted disks, sheet, ambient, interreflection). Returns
//!   arrive at `t = 2r/c` and are split linearly between neighbouring bins.
//! - [`flim`]: fluorescence decays, paper eq. (5), with three procedural channels; the
//!   paper's lifetimes (0.5–1.5, 1.5–2.5, 2.5–3.5 ns) and onset, or (default) randomised
//!   onset, IRF, lifetimes, background and brightness.
//! - [`knobs`]: the randomised knobs' ranges (uniform or log-uniform draws, fixed values).
//! - [`store`]: `manifest.json` + `.npy` shards per split; item `i` is a pure function of
//!   `(seed, i)`.
//! - [`import`]: users' cubes and depth/albedo maps into the same format.
//! - [`montage`]: a PNG overview of one item.
//! - [`grid`]: the reconstruction time grid `T = L·K` bins of `Δt = T_c/K`; [`error`].
//!
//! ```
//! use tcsense_datasets::{grid::TimeGrid, lidar::LidarParams};
//! let p = LidarParams { height: 8, width: 8, ..Default::default() };
//! let s = p.sample(&TimeGrid::default(), 1, 0);
//! assert_eq!(s.x.dim(), (32, 8, 8));
//! ```

pub mod error;
pub mod flim;
pub mod grid;
pub mod import;
pub mod knobs;
pub mod lidar;
pub mod montage;
pub mod store;

pub use error::{DatasetError, Result};
pub use grid::TimeGrid;
pub use store::{Dataset, Generator, Manifest};
