//! LiDAR scenes with multipath: a pinhole camera at the origin looking along `+z` (image
//! rows along `+y`, columns along `+x`) at planes, boxes and spheres in front of a back wall.
//!
//! Each visible surface returns an impulse of area `ρ·|cos θ| / r²` (Lambertian albedo `ρ`
//! with a procedural texture, light source at the camera, `1/r²` fall-off) at time
//! `t = 2r/c`, split linearly between neighbouring bins. Optional effects:
//! - a weakly diffusive **sheet** (plane `z = z_s` in front of everything): a weak first
//!   return `ρ_s·|cos θ|/r_s²`, and every return behind it attenuated by its round-trip
//!   transmission `τ_s²` (the paper's experiment, Fig. 15);
//! - **interreflection tails**: an exponentially decaying tail after an object's return,
//!   carrying a fraction `κ` of its energy with time constant `τ_ir`;
//! - **ambient light**: a constant level per bin proportional to the pixel's albedo.
//!
//! **Domain randomisation** ([`LidarRandomization`], on by default; `None` is the generator
//! above with its fixed ranges): back walls anywhere up to the end of the unambiguous range
//! and steeper tilts, objects from close to the camera to the wall, procedural-noise albedo
//! (fractal value noise) besides checkers, slanted disks ("slopes") besides boxes and
//! spheres, wider sheet transmittance, reflectance and distance ranges, an ambient level and
//! interreflection tails of random strength on random objects.
//!
//! The cube is scaled so that its largest voxel is 1 (depths are not affected). Ground
//! truth: cube `[T, H, W]`, depth (range `r`, m) per bounce `[2, H, W]` ordered by arrival
//! (NaN where there is none), intensity `[H, W]` (the direct returns' total area, same scale).

use crate::error::{invalid, Result};
use crate::grid::{TimeGrid, C};
use crate::knobs::{check_range, draw};
use ndarray::{Array2, Array3, Axis};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use serde::{Deserialize, Serialize};

/// Bounces recorded in the depth ground truth (sheet + object).
pub const BOUNCES: usize = 2;

/// A surface.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Shape {
    /// Infinite plane through `point` with unit `normal`.
    Plane { point: [f64; 3], normal: [f64; 3] },
    /// Sphere.
    Sphere { center: [f64; 3], radius: f64 },
    /// Axis-aligned box.
    Cuboid { min: [f64; 3], max: [f64; 3] },
    /// Flat disk through `center` with unit `normal`: a slanted surface patch.
    Disk { center: [f64; 3], normal: [f64; 3], radius: f64 },
}

/// A textured Lambertian object.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Object {
    pub shape: Shape,
    /// Base albedo in (0, 1].
    pub albedo: f64,
    /// Checker texture period (m); 0 = uniform.
    pub texture_period: f64,
    /// Texture contrast in [0, 1): albedo varies between `albedo·(1−contrast)` and `albedo`.
    pub texture_contrast: f64,
    /// Interreflection tail: fraction `κ` of the return and time constant (s).
    pub tail: Option<(f64, f64)>,
    /// Fractal value-noise texture of this seed instead of checkers (period
    /// `texture_period`, contrast `texture_contrast`).
    #[serde(default)]
    pub noise_seed: Option<u64>,
}

/// A weakly diffusive sheet at `z = depth`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sheet {
    pub z: f64,
    pub reflectance: f64,
    pub transmission: f64,
}

/// A scene.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    pub objects: Vec<Object>,
    pub sheet: Option<Sheet>,
    /// Ambient level per bin relative to the cube's peak, times the pixel's albedo.
    pub ambient: f64,
    /// Instrument delay (s): every return arrives at `2r/c + delay` (cyclically); the depth
    /// ground truth stays the true range.
    #[serde(default)]
    pub delay_s: f64,
}

/// Pinhole camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    pub height: usize,
    pub width: usize,
    /// Horizontal field of view (degrees).
    pub fov_deg: f64,
}

impl Camera {
    /// Unit ray direction through the centre of pixel `(r, c)`.
    pub fn ray(&self, r: usize, c: usize) -> [f64; 3] {
        let f = (self.width as f64 / 2.0) / (self.fov_deg.to_radians() / 2.0).tan();
        let d = [(c as f64 + 0.5 - self.width as f64 / 2.0) / f, (r as f64 + 0.5 - self.height as f64 / 2.0) / f, 1.0];
        let n = norm(d);
        [d[0] / n, d[1] / n, d[2] / n]
    }
}

/// One rendered sample.
#[derive(Debug, Clone)]
pub struct LidarSample {
    /// Transient cube `[T, H, W]`.
    pub x: Array3<f32>,
    /// Range per bounce `[2, H, W]` (m), NaN where there is none.
    pub depth: Array3<f32>,
    /// Direct-return intensity `[H, W]`.
    pub intensity: Array2<f32>,
}

/// Random scene generator settings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LidarParams {
    pub height: usize,
    pub width: usize,
    pub fov_deg: f64,
    /// Objects in front of the back wall: 1..=max_objects.
    pub max_objects: usize,
    /// Probability that a sample has a diffusive sheet.
    pub sheet_probability: f64,
    /// Add interreflection tails to objects.
    pub interreflection: bool,
    /// Ambient level (0 = dark room, as in the paper).
    pub ambient: f64,
    /// Domain randomisation (`None`, and in manifests written before it existed: the fixed
    /// ranges of the generator without it).
    #[serde(default)]
    pub randomization: Option<LidarRandomization>,
}

impl Default for LidarParams {
    /// 64×64, 40°, up to 4 objects, a sheet in half the scenes, randomised
    /// ([`LidarRandomization::default`]).
    fn default() -> Self {
        LidarParams { randomization: Some(LidarRandomization::default()), ..LidarParams::paper() }
    }
}

/// Ranges of the randomised LiDAR knobs; a range `[lo, hi]` with `lo == hi` fixes the knob.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LidarRandomization {
    /// Distance of the back wall's farthest corner, as a fraction of the unambiguous range.
    pub wall_range: [f64; 2],
    /// Largest tilt of the back wall (slope in x and y).
    pub wall_tilt: f64,
    /// Object distances, as a fraction of the wall's.
    pub object_range: [f64; 2],
    /// Probability that a surface has a fractal-noise texture instead of checkers.
    pub noise_texture: f64,
    /// At most this many slanted disks per scene.
    pub max_slopes: usize,
    /// Sheet round-trip transmittance per pass, reflectance, and distance as a fraction of the
    /// nearest surface's.
    pub sheet_transmission: [f64; 2],
    pub sheet_reflectance: [f64; 2],
    pub sheet_distance: [f64; 2],
    /// Ambient level, added to `LidarParams::ambient`.
    pub ambient: [f64; 2],
    /// Probability that an object has an interreflection tail, and its fraction `κ`.
    pub interreflection_probability: f64,
    pub interreflection: [f64; 2],
}

impl Default for LidarRandomization {
    fn default() -> Self {
        LidarRandomization {
            wall_range: [0.3, 0.97],
            wall_tilt: 0.6,
            object_range: [0.1, 0.9],
            noise_texture: 0.7,
            max_slopes: 3,
            sheet_transmission: [0.3, 0.95],
            sheet_reflectance: [0.001, 0.05],
            sheet_distance: [0.15, 0.85],
            ambient: [0.0, 0.02],
            interreflection_probability: 0.3,
            interreflection: [0.02, 0.3],
        }
    }
}

impl LidarRandomization {
    /// Check the ranges.
    pub fn validate(&self) -> Result<()> {
        check_range("wall_range", self.wall_range, 0.05, 0.99)?;
        check_range("object_range", self.object_range, 0.01, 0.99)?;
        check_range("sheet_transmission", self.sheet_transmission, 0.0, 1.0)?;
        check_range("sheet_reflectance", self.sheet_reflectance, 0.0, 1.0)?;
        check_range("sheet_distance", self.sheet_distance, 0.01, 0.99)?;
        check_range("ambient", self.ambient, 0.0, 10.0)?;
        check_range("interreflection", self.interreflection, 0.0, 10.0)?;
        for (name, p) in [("noise_texture", self.noise_texture), ("interreflection_probability", self.interreflection_probability)] {
            if !(0.0..=1.0).contains(&p) {
                return Err(invalid(name, p, "a probability in [0, 1]"));
            }
        }
        if !(0.0..=2.0).contains(&self.wall_tilt) {
            return Err(invalid("wall_tilt", self.wall_tilt, "a slope in [0, 2]"));
        }
        if self.max_slopes > 64 {
            return Err(invalid("max_slopes", self.max_slopes, "0..=64"));
        }
        Ok(())
    }
}

/// The highest fixed ambient level (relative to the peak voxel: a signal-to-background ratio of
/// 1/1000 at the brightest voxel).
pub const MAX_AMBIENT: f64 = 1000.0;

impl LidarParams {
    /// Check ranges.
    pub fn validate(&self) -> Result<()> {
        if self.height == 0 || self.width == 0 || self.height > 4096 || self.width > 4096 {
            return Err(invalid("size", format!("{}x{}", self.height, self.width), "1..=4096 on each side"));
        }
        if !(self.fov_deg > 1.0 && self.fov_deg <= 120.0) {
            return Err(invalid("fov", self.fov_deg, "degrees in (1, 120]"));
        }
        if !(0.0..=1.0).contains(&self.sheet_probability) {
            return Err(invalid("sheet_probability", self.sheet_probability, "a probability in [0, 1]"));
        }
        if !(self.ambient >= 0.0 && self.ambient <= MAX_AMBIENT) {
            return Err(invalid("ambient", self.ambient, format!("a non-negative level up to {MAX_AMBIENT} (relative to the peak voxel)")));
        }
        if self.max_objects == 0 || self.max_objects > 64 {
            return Err(invalid("max_objects", self.max_objects, "1..=64"));
        }
        if let Some(r) = &self.randomization {
            r.validate()?;
        }
        Ok(())
    }

    /// The generator without randomisation: 64×64, 40°, up to 4 objects, a sheet in half the
    /// scenes, walls within 70–90 % of the range, checker textures.
    pub fn paper() -> Self {
        LidarParams {
            height: 64,
            width: 64,
            fov_deg: 40.0,
            max_objects: 4,
            sheet_probability: 0.5,
            interreflection: false,
            ambient: 0.0,
            randomization: None,
        }
    }

    fn camera(&self) -> Camera {
        Camera { height: self.height, width: self.width, fov_deg: self.fov_deg }
    }

    /// The random scene of item `index` (a pure function of `(seed, index)`).
    pub fn scene(&self, grid: &TimeGrid, seed: u64, index: u64) -> Scene {
        if let Some(r) = &self.randomization {
            return self.random_scene(r, grid, seed, index);
        }
        let mut rng = StdRng::seed_from_u64(tcsense_sensor::noise::derive_seed(seed, index));
        let range = grid.range_m();
        let cam = self.camera();
        let half_x = (cam.fov_deg.to_radians() / 2.0).tan();
        let half_y = half_x * cam.height as f64 / cam.width as f64;
        let mut objects = Vec::new();
        let tex = |rng: &mut StdRng| (rng.random_range(0.05..0.5) * range / 8.0, rng.random_range(0.0..0.6));
        let tail = |rng: &mut StdRng, on: bool| on.then(|| (rng.random_range(0.02..0.1), rng.random_range(0.5e-9..3e-9)));
        // back wall, slightly tilted; its farthest corner stays within 90 % of the range
        let mut tilt = [rng.random_range(-0.25..0.25), rng.random_range(-0.15..0.15)];
        let corners = [(0, 0), (0, cam.width - 1), (cam.height - 1, 0), (cam.height - 1, cam.width - 1)];
        let min_den = |tilt: [f64; 2]| {
            corners
                .iter()
                .map(|&(r, c)| {
                    let d = cam.ray(r, c);
                    d[2] - tilt[0] * d[0] - tilt[1] * d[1]
                })
                .fold(f64::INFINITY, f64::min)
        };
        if min_den(tilt) < 0.3 {
            tilt = [0.0, 0.0];
        }
        let zw = rng.random_range(0.7..0.9) * range * min_den(tilt);
        // nearest z of any surface, to keep the sheet in front of everything
        let mut z_near = zw * min_den(tilt);
        let (p, t) = tex(&mut rng);
        objects.push(Object {
            shape: Shape::Plane { point: [0.0, 0.0, zw], normal: normalize([tilt[0], tilt[1], -1.0]) },
            albedo: rng.random_range(0.3..0.9),
            texture_period: p,
            texture_contrast: t,
            tail: tail(&mut rng, self.interreflection),
            noise_seed: None,
        });
        // floor with probability ½
        if rng.random_bool(0.5) {
            let yf = rng.random_range(0.3..0.8) * half_y * zw;
            z_near = z_near.min(yf / half_y);
            let (p, t) = tex(&mut rng);
            objects.push(Object {
                shape: Shape::Plane { point: [0.0, yf, 0.0], normal: [0.0, -1.0, 0.0] },
                albedo: rng.random_range(0.2..0.8),
                texture_period: p,
                texture_contrast: t,
                tail: tail(&mut rng, self.interreflection),
                noise_seed: None,
            });
        }
        let n_obj = rng.random_range(1..=self.max_objects);
        for _ in 0..n_obj {
            let z = rng.random_range(0.25..0.6) * zw;
            let cx = rng.random_range(-0.8..0.8) * half_x * z;
            let cy = rng.random_range(-0.8..0.8) * half_y * z;
            let size = rng.random_range(0.08..0.3) * half_x * z;
            z_near = z_near.min(z - 1.5 * size);
            let shape = if rng.random_bool(0.5) {
                Shape::Sphere { center: [cx, cy, z], radius: size }
            } else {
                let s = [size * rng.random_range(0.5..1.5), size * rng.random_range(0.5..1.5), size * rng.random_range(0.5..1.5)];
                Shape::Cuboid { min: [cx - s[0], cy - s[1], z - s[2]], max: [cx + s[0], cy + s[1], z + s[2]] }
            };
            let (p, t) = tex(&mut rng);
            objects.push(Object {
                shape,
                albedo: rng.random_range(0.2..1.0),
                texture_period: p,
                texture_contrast: t,
                tail: tail(&mut rng, self.interreflection),
                noise_seed: None,
            });
        }
        let sheet = rng.random_bool(self.sheet_probability).then(|| Sheet {
            z: rng.random_range(0.3..0.7) * z_near,
            reflectance: rng.random_range(0.002..0.02),
            transmission: rng.random_range(0.6..0.9),
        });
        Scene { objects, sheet, ambient: self.ambient, delay_s: 0.0 }
    }

    /// A randomised scene ([`LidarRandomization`]).
    fn random_scene(&self, r: &LidarRandomization, grid: &TimeGrid, seed: u64, index: u64) -> Scene {
        let mut rng = StdRng::seed_from_u64(tcsense_sensor::noise::derive_seed(seed, index));
        let range = grid.range_m();
        let cam = self.camera();
        let half_x = (cam.fov_deg.to_radians() / 2.0).tan();
        let half_y = half_x * cam.height as f64 / cam.width as f64;
        let corners = [(0, 0), (0, cam.width - 1), (cam.height - 1, 0), (cam.height - 1, cam.width - 1)];
        let min_den = |tilt: [f64; 2]| {
            corners
                .iter()
                .map(|&(rr, c)| {
                    let d = cam.ray(rr, c);
                    d[2] - tilt[0] * d[0] - tilt[1] * d[1]
                })
                .fold(f64::INFINITY, f64::min)
        };
        // a surface's look: checkers or fractal noise, albedo, interreflection tail
        let look = |rng: &mut StdRng, albedo: (f64, f64)| {
            let noise = rng.random_bool(r.noise_texture);
            let period = rng.random_range(0.02..0.4) * range / 8.0;
            let contrast = rng.random_range(0.0..if noise { 0.9 } else { 0.6 });
            let tail = (rng.random_bool(r.interreflection_probability) && (self.interreflection || r.interreflection[1] > 0.0))
                .then(|| (draw(rng, r.interreflection, true), rng.random_range(0.3e-9..4e-9)));
            (rng.random_range(albedo.0..albedo.1), period, contrast, tail, noise.then(|| rng.random::<u64>()))
        };
        let object = |rng: &mut StdRng, shape: Shape, albedo: (f64, f64)| {
            let (albedo, texture_period, texture_contrast, tail, noise_seed) = look(rng, albedo);
            Object { shape, albedo, texture_period, texture_contrast, tail, noise_seed }
        };
        // back wall: its farthest corner at a random fraction of the range
        let mut tilt = [rng.random_range(-r.wall_tilt..=r.wall_tilt), rng.random_range(-r.wall_tilt..=r.wall_tilt) * 0.6];
        if min_den(tilt) < 0.3 {
            tilt = [0.0, 0.0];
        }
        let far = draw(&mut rng, r.wall_range, false) * range;
        // plane z = zw + tilt·(x, y): the range along ray d is zw / den(d); the largest is at the smallest den
        let zw = far * min_den(tilt);
        // the wall's nearest depth z = t·d_z over the corners (t = zw / den)
        let mut z_near = corners
            .iter()
            .map(|&(rr, c)| {
                let d = cam.ray(rr, c);
                zw * d[2] / (d[2] - tilt[0] * d[0] - tilt[1] * d[1])
            })
            .fold(f64::INFINITY, f64::min);
        let mut objects =
            vec![object(&mut rng, Shape::Plane { point: [0.0, 0.0, zw], normal: normalize([tilt[0], tilt[1], -1.0]) }, (0.2, 1.0))];
        if rng.random_bool(0.5) {
            let yf = rng.random_range(0.2..0.9) * half_y * zw;
            z_near = z_near.min(yf / half_y);
            let normal = normalize([0.0, -1.0, rng.random_range(-0.2..0.2)]);
            objects.push(object(&mut rng, Shape::Plane { point: [0.0, yf, 0.0], normal }, (0.1, 0.9)));
        }
        let n_obj = rng.random_range(1..=self.max_objects);
        let n_slopes = rng.random_range(0..=r.max_slopes);
        for i in 0..n_obj + n_slopes {
            let z = draw(&mut rng, r.object_range, false) * zw;
            let cx = rng.random_range(-0.9..0.9) * half_x * z;
            let cy = rng.random_range(-0.9..0.9) * half_y * z;
            let size = rng.random_range(0.05..0.35) * half_x * z;
            z_near = z_near.min(z - 1.5 * size);
            let shape = if i >= n_obj {
                // a slanted disk: normal within ~70° of the view axis
                let normal = normalize([rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5), -1.0]);
                Shape::Disk { center: [cx, cy, z], normal, radius: size * 1.5 }
            } else if rng.random_bool(0.5) {
                Shape::Sphere { center: [cx, cy, z], radius: size }
            } else {
                let e = [size * rng.random_range(0.3..1.7), size * rng.random_range(0.3..1.7), size * rng.random_range(0.3..1.7)];
                Shape::Cuboid { min: [cx - e[0], cy - e[1], z - e[2]], max: [cx + e[0], cy + e[1], z + e[2]] }
            };
            objects.push(object(&mut rng, shape, (0.1, 1.0)));
        }
        let z_near = z_near.max(0.02 * range);
        let sheet = rng.random_bool(self.sheet_probability).then(|| Sheet {
            z: draw(&mut rng, r.sheet_distance, false) * z_near,
            reflectance: draw(&mut rng, r.sheet_reflectance, true),
            transmission: draw(&mut rng, r.sheet_transmission, false),
        });
        Scene { objects, sheet, ambient: self.ambient + draw(&mut rng, r.ambient, false), delay_s: 0.0 }
    }

    /// Render item `index`.
    pub fn sample(&self, grid: &TimeGrid, seed: u64, index: u64) -> LidarSample {
        render(&self.scene(grid, seed, index), &self.camera(), grid)
    }
}

fn norm(v: [f64; 3]) -> f64 {
    (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
}
fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = norm(v);
    [v[0] / n, v[1] / n, v[2] / n]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Nearest hit of a ray from the origin: `(range, unit normal)`.
fn intersect(shape: &Shape, d: [f64; 3]) -> Option<(f64, [f64; 3])> {
    const EPS: f64 = 1e-9;
    match *shape {
        Shape::Plane { point, normal } => {
            let den = dot(d, normal);
            if den.abs() < EPS {
                return None;
            }
            let t = dot(point, normal) / den;
            (t > EPS).then_some((t, normal))
        }
        Shape::Disk { center, normal, radius } => {
            let den = dot(d, normal);
            if den.abs() < EPS {
                return None;
            }
            let t = dot(center, normal) / den;
            let p = [d[0] * t - center[0], d[1] * t - center[1], d[2] * t - center[2]];
            (t > EPS && dot(p, p) <= radius * radius).then_some((t, normal))
        }
        Shape::Sphere { center, radius } => {
            let b = dot(d, center);
            let disc = b * b - (dot(center, center) - radius * radius);
            if disc < 0.0 {
                return None;
            }
            let s = disc.sqrt();
            let t = if b - s > EPS { b - s } else { b + s };
            if t <= EPS {
                return None;
            }
            let p = [d[0] * t, d[1] * t, d[2] * t];
            Some((t, normalize([p[0] - center[0], p[1] - center[1], p[2] - center[2]])))
        }
        Shape::Cuboid { min, max } => {
            let (mut t0, mut t1) = (f64::NEG_INFINITY, f64::INFINITY);
            let mut axis = 0;
            for a in 0..3 {
                if d[a].abs() < EPS {
                    if 0.0 < min[a] || 0.0 > max[a] {
                        return None;
                    }
                    continue;
                }
                let (mut ta, mut tb) = (min[a] / d[a], max[a] / d[a]);
                if ta > tb {
                    std::mem::swap(&mut ta, &mut tb);
                }
                if ta > t0 {
                    t0 = ta;
                    axis = a;
                }
                t1 = t1.min(tb);
            }
            if t0 > t1 || t0 <= EPS {
                return None;
            }
            let mut n = [0.0; 3];
            n[axis] = -d[axis].signum();
            Some((t0, n))
        }
    }
}

/// Smooth 3-D value noise in `[0, 1]`: hashed lattice values, trilinear with a smoothstep.
fn value_noise(p: [f64; 3], seed: u64) -> f64 {
    let cell = p.map(f64::floor);
    let f = [p[0] - cell[0], p[1] - cell[1], p[2] - cell[2]].map(|v| v * v * (3.0 - 2.0 * v));
    let lattice = |dx: i64, dy: i64, dz: i64| {
        let (x, y, z) = (cell[0] as i64 + dx, cell[1] as i64 + dy, cell[2] as i64 + dz);
        let h = tcsense_sensor::noise::derive_seed(
            seed,
            (x as u64).wrapping_mul(0x9E37_79B9)
                ^ (y as u64).wrapping_mul(0x85EB_CA6B).rotate_left(21)
                ^ (z as u64).wrapping_mul(0xC2B2_AE35).rotate_left(42),
        );
        (h >> 11) as f64 / (1u64 << 53) as f64
    };
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let x00 = lerp(lattice(0, 0, 0), lattice(1, 0, 0), f[0]);
    let x10 = lerp(lattice(0, 1, 0), lattice(1, 1, 0), f[0]);
    let x01 = lerp(lattice(0, 0, 1), lattice(1, 0, 1), f[0]);
    let x11 = lerp(lattice(0, 1, 1), lattice(1, 1, 1), f[0]);
    lerp(lerp(x00, x10, f[1]), lerp(x01, x11, f[1]), f[2])
}

/// Fractal (fBm) value noise in `[0, 1]`: four octaves, each twice as fine and half as strong.
fn fractal_noise(p: [f64; 3], seed: u64) -> f64 {
    let (mut sum, mut amp, mut norm, mut scale) = (0.0, 1.0, 0.0, 1.0);
    for octave in 0..4u64 {
        sum += amp * value_noise(p.map(|v| v * scale), seed.wrapping_add(octave));
        norm += amp;
        amp *= 0.5;
        scale *= 2.0;
    }
    sum / norm
}

fn texture(o: &Object, p: [f64; 3]) -> f64 {
    if o.texture_period <= 0.0 || o.texture_contrast <= 0.0 {
        return o.albedo;
    }
    if let Some(seed) = o.noise_seed {
        return o.albedo * (1.0 - o.texture_contrast * fractal_noise(p.map(|v| v / o.texture_period), seed));
    }
    let k = p.iter().map(|v| (v / o.texture_period).floor() as i64).sum::<i64>();
    if k.rem_euclid(2) == 0 {
        o.albedo
    } else {
        o.albedo * (1.0 - o.texture_contrast)
    }
}

/// Render a scene on a time grid.
///
/// # Shapes
/// - returns `x`: `[T, H, W]`, `depth`: `[2, H, W]`, `intensity`: `[H, W]`
pub fn render(scene: &Scene, cam: &Camera, grid: &TimeGrid) -> LidarSample {
    let (h, w, t) = (cam.height, cam.width, grid.bins());
    let mut x = Array3::<f32>::zeros((t, h, w));
    let mut depth = Array3::<f32>::from_elem((BOUNCES, h, w), f32::NAN);
    let mut intensity = Array2::<f32>::zeros((h, w));
    let mut albedo_map = Array2::<f32>::zeros((h, w));
    let dt = grid.bin_width_s();
    let mut wave = vec![0f32; t];
    for r in 0..h {
        for c in 0..w {
            wave.fill(0.0);
            let d = cam.ray(r, c);
            let mut bounce = 0;
            let mut total = 0.0;
            let mut atten = 1.0;
            if let Some(s) = scene.sheet {
                if d[2] > 0.0 {
                    let rs = s.z / d[2];
                    let a = s.reflectance * d[2] / (rs * rs);
                    grid.splat(&mut wave, 2.0 * rs / C + scene.delay_s, a);
                    depth[(bounce, r, c)] = rs as f32;
                    bounce += 1;
                    total += a;
                    atten = s.transmission * s.transmission;
                }
            }
            let hit =
                scene.objects.iter().filter_map(|o| intersect(&o.shape, d).map(|(rng, n)| (rng, n, o))).min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((range, n, o)) = hit {
                let p = [d[0] * range, d[1] * range, d[2] * range];
                let alb = texture(o, p);
                let a = atten * alb * dot(n, d).abs() / (range * range);
                let t0 = 2.0 * range / C + scene.delay_s;
                grid.splat(&mut wave, t0, a);
                if let Some((kappa, tau)) = o.tail {
                    // bin-integrated exponential tail starting at t0, total area κ·a
                    for (j, v) in wave.iter_mut().enumerate() {
                        let (lo, hi) = (j as f64 * dt - t0, (j + 1) as f64 * dt - t0);
                        let (lo, hi) = (lo.max(0.0), hi.max(0.0));
                        *v += (kappa * a * ((-lo / tau).exp() - (-hi / tau).exp())) as f32;
                    }
                }
                depth[(bounce.min(BOUNCES - 1), r, c)] = range as f32;
                total += a;
                albedo_map[(r, c)] = alb as f32;
            }
            intensity[(r, c)] = total as f32;
            for (j, v) in wave.iter().enumerate() {
                x[(j, r, c)] = *v;
            }
        }
    }
    let peak = x.iter().fold(0f32, |m, &v| m.max(v));
    if peak > 0.0 {
        x.mapv_inplace(|v| v / peak);
        intensity.mapv_inplace(|v| v / peak);
    }
    if scene.ambient > 0.0 {
        for mut plane in x.axis_iter_mut(Axis(0)) {
            plane.zip_mut_with(&albedo_map, |v, &a| *v += scene.ambient as f32 * a);
        }
    }
    LidarSample { x, depth, intensity }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> TimeGrid {
        TimeGrid::default()
    }

    fn wall(z: f64) -> Object {
        Object {
            shape: Shape::Plane { point: [0.0, 0.0, z], normal: [0.0, 0.0, -1.0] },
            albedo: 0.5,
            texture_period: 0.0,
            texture_contrast: 0.0,
            tail: None,
            noise_seed: None,
        }
    }

    #[test]
    fn plane_return_lands_at_the_right_fractional_bin() {
        let g = grid();
        let cam = Camera { height: 2, width: 2, fov_deg: 1.2 };
        let z = 2.3456;
        let s = render(&Scene { objects: vec![wall(z)], sheet: None, ambient: 0.0, delay_s: 0.0 }, &cam, &g);
        for r in 0..2 {
            for c in 0..2 {
                let range = s.depth[(0, r, c)] as f64;
                let d = cam.ray(r, c);
                assert!((range - z / d[2]).abs() < 1e-5);
                let wave: Vec<f64> = (0..32).map(|j| s.x[(j, r, c)] as f64).collect();
                let centroid: f64 = wave.iter().enumerate().map(|(j, v)| (j as f64 + 0.5) * v).sum::<f64>() / wave.iter().sum::<f64>();
                let want = 2.0 * range / C / g.bin_width_s();
                assert!((centroid - want).abs() < 1e-3, "centroid {centroid} bins, want {want}");
                // exactly two bins are lit
                assert_eq!(wave.iter().filter(|&&v| v > 0.0).count(), 2);
                assert!(s.depth[(1, r, c)].is_nan());
            }
        }
    }

    #[test]
    fn sheet_gives_two_returns_with_the_right_ratio() {
        let g = grid();
        let cam = Camera { height: 1, width: 1, fov_deg: 1.0 };
        let sheet = Sheet { z: 0.4, reflectance: 0.01, transmission: 0.8 };
        let s = render(&Scene { objects: vec![wall(2.0)], sheet: Some(sheet), ambient: 0.0, delay_s: 0.0 }, &cam, &g);
        let (r1, r2) = (s.depth[(0, 0, 0)] as f64, s.depth[(1, 0, 0)] as f64);
        assert!((r1 - 0.4).abs() < 1e-6 && (r2 - 2.0).abs() < 1e-6, "{r1} {r2}");
        let wave: Vec<f64> = (0..32).map(|j| s.x[(j, 0, 0)] as f64).collect();
        let b1 = 2.0 * 0.4 / C / g.bin_width_s() - 0.5; // bin-centre coordinate of the first return
        let split = b1.floor() as usize + 2;
        let first: f64 = wave[..split].iter().sum();
        let second: f64 = wave[split..].iter().sum();
        // ratio = (ρ_s / r_s²) / (τ² ρ / r²) at normal incidence
        let want = (0.01 / 0.16) / (0.64 * 0.5 / 4.0);
        assert!((first / second - want).abs() / want < 1e-4, "ratio {} want {want}", first / second);
    }

    #[test]
    fn generator_is_deterministic_and_in_range() {
        for random in [None, Some(LidarRandomization::default())] {
            let p = LidarParams {
                height: 8,
                width: 8,
                sheet_probability: 1.0,
                interreflection: true,
                randomization: random,
                ..LidarParams::paper()
            };
            let g = grid();
            let a = p.sample(&g, 3, 5);
            let b = p.sample(&g, 3, 5);
            let c = p.sample(&g, 3, 6);
            assert_eq!(a.x, b.x);
            assert_ne!(a.x, c.x);
            let peak = a.x.iter().fold(0f32, |m, &v| m.max(v));
            let ambient = p.scene(&g, 3, 5).ambient as f32;
            assert!(peak >= 1.0 - 1e-6 && peak <= 1.0 + ambient + 1e-6, "peak {peak}, ambient {ambient}");
            let range = g.range_m() as f32;
            assert!(a.depth.iter().filter(|v| !v.is_nan()).all(|&d| d > 0.0 && d < range));
            // the sheet is the first bounce everywhere
            let wall_sheet = a.depth.index_axis(Axis(0), 0);
            let objects = a.depth.index_axis(Axis(0), 1);
            assert!(wall_sheet.iter().zip(objects.iter()).all(|(&s, &o)| s < o), "sheet in front of every object");
        }
    }

    #[test]
    fn randomised_scenes_cover_the_range_and_the_new_looks() {
        let g = grid();
        let r = LidarRandomization::default();
        let p = LidarParams { height: 16, width: 16, ..Default::default() };
        let fixed = LidarParams { height: 16, width: 16, ..LidarParams::paper() };
        let range = g.range_m();
        let far =
            |p: &LidarParams, i: u64| p.sample(&g, 1, i).depth.iter().filter(|v| v.is_finite()).fold(0f32, |m, &v| m.max(v)) as f64 / range;
        let random_far: Vec<f64> = (0..60).map(|i| far(&p, i)).collect();
        let fixed_far: Vec<f64> = (0..60).map(|i| far(&fixed, i)).collect();
        // the fixed generator keeps every wall within 90 % of the range; the randomised one
        // reaches past it and also puts walls close
        assert!(fixed_far.iter().all(|&f| f <= 0.9 + 1e-6), "{fixed_far:?}");
        assert!(random_far.iter().any(|&f| f > 0.93) && random_far.iter().any(|&f| f < 0.45), "{random_far:?}");
        assert!(random_far.iter().all(|&f| f < r.wall_range[1] + 1e-6));
        let scenes: Vec<Scene> = (0..60).map(|i| p.scene(&g, 1, i)).collect();
        let objects = || scenes.iter().flat_map(|s| s.objects.iter());
        assert!(objects().any(|o| matches!(o.shape, Shape::Disk { .. })), "slanted disks");
        let noisy = objects().filter(|o| o.noise_seed.is_some()).count() as f64 / objects().count() as f64;
        assert!((noisy - r.noise_texture).abs() < 0.1, "{noisy} of the surfaces have noise textures");
        assert!(objects().any(|o| o.tail.is_some_and(|(k, _)| k > 0.1)), "strong interreflection tails");
        let sheets: Vec<Sheet> = scenes.iter().filter_map(|s| s.sheet).collect();
        assert!(
            sheets.iter().any(|s| s.transmission < 0.5)
                && sheets.iter().all(|s| (r.sheet_transmission[0]..=r.sheet_transmission[1]).contains(&s.transmission))
        );
        assert!(scenes.iter().any(|s| s.ambient > 0.01) && scenes.iter().all(|s| s.ambient <= r.ambient[1]));
        // fractal noise varies smoothly within [0, 1]
        let v: Vec<f64> = (0..200).map(|i| fractal_noise([i as f64 * 0.05, 0.3, 1.7], 4)).collect();
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
        assert!(v.windows(2).all(|w| (w[0] - w[1]).abs() < 0.2), "smooth");
        assert!(v.iter().cloned().fold(0.0, f64::max) - v.iter().cloned().fold(1.0, f64::min) > 0.2, "varies");
        assert!(LidarRandomization { wall_range: [0.5, 1.5], ..r }.validate().is_err());
    }

    #[test]
    fn an_instrument_delay_is_a_cyclic_time_shift() {
        let g = grid();
        let p = LidarParams { height: 8, width: 8, sheet_probability: 1.0, ..Default::default() };
        let scene = p.scene(&g, 2, 7);
        let cam = p.camera();
        let base = render(&scene, &cam, &g);
        let k = 13;
        let delayed = render(&Scene { delay_s: k as f64 * g.bin_width_s(), ..scene.clone() }, &cam, &g);
        let t = g.bins();
        for j in 0..t {
            for (a, b) in delayed.x.index_axis(Axis(0), (j + k) % t).iter().zip(base.x.index_axis(Axis(0), j).iter()) {
                assert!((a - b).abs() < 1e-5, "bin {j}: {a} vs {b}");
            }
        }
        assert_eq!(delayed.depth, base.depth, "the true range does not move");
    }
}
