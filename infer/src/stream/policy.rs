//! What a stream writes: the kinds of exported models, the products asked for, and the
//! phasor of a pixel's lifetimes.

use super::*;

/// What an exported model gives, from its metadata's decoder name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelKind {
    /// A transient cube (ADMM-Net).
    Cube,
    /// Depth of K returns with confidences (the U-Net).
    Depth,
    /// Lifetimes, confidence and intensity (the lifetime decoder).
    Lifetime,
}

impl ModelKind {
    /// The kind of a model whose metadata names `decoder`.
    pub fn of(decoder: &str) -> ModelKind {
        match decoder {
            "unet" => ModelKind::Depth,
            "lifetime" => ModelKind::Lifetime,
            _ => ModelKind::Cube,
        }
    }

    /// The products this kind of model can give, and those written when none are asked for.
    pub fn products(self) -> (&'static [&'static str], &'static str) {
        match self {
            ModelKind::Cube => (&["cube", "depth", "peaks", "ply", "lifetime", "intensity", "phasor"], "cube"),
            ModelKind::Depth => (&["depth", "ply"], "depth"),
            ModelKind::Lifetime => (&["lifetime", "intensity", "phasor"], "lifetime,intensity"),
        }
    }
}

/// What to write.
#[derive(Debug, Clone, PartialEq)]
pub struct Products {
    pub cube: bool,
    pub depth: bool,
    pub peaks: bool,
    pub ply: bool,
    /// The amplitude-weighted mean lifetime `[H, W]` (s): a cube's by the reconvolution fit.
    pub lifetime: bool,
    /// The photo-charge per pixel `[H, W]`.
    pub intensity: bool,
    /// The IRF-referenced phasor `(g, s)` at the cycle's first harmonic, `[2, H, W]`.
    pub phasor: bool,
    /// Returns per pixel from a cube (peak detection).
    pub returns: usize,
    /// Camera field of view for point clouds (degrees).
    pub fov_deg: f64,
    /// Lifetimes (and intensity, phasor) by the fit to the taps through the model's sensor
    /// ([`tcsense_fits::lifetime_taps::LifetimeTemplates`], the instrument estimated once on the first frame
    /// unless its `onset_s` is given) instead of the model's own; `None`: the model's.
    pub lifetime_fit: Option<TapFitOptions>,
    /// The decays' onset `t₀` (s) when known (a calibration, a bright reference): a lifetime
    /// network on the fit's evidence then fits only the IRF width on the first frame instead
    /// of the onset too (which a dim first frame places a few tenths of a nanosecond off).
    pub onset_s: Option<f64>,
    /// A depth model's ranges refined by the fit in the tap domain, as `reconstruct unet`
    /// applies it ([`tcsense_fits::range`]); `None`: as the network gives them.
    pub range_fit: Option<RangeFitOptions>,
    /// Depth (and the point cloud, the confidence) by the template fit of ranges to the taps
    /// through the model's sensor ([`tcsense_fits::depth`]) instead of the model's;
    /// `None`: the model's.
    pub depth_fit: Option<DepthFitOptions>,
    /// What a tap clipped at the full well reads, in the frames' units (as read, before any
    /// calibration): the pixels with a tap at it get no range and no lifetime; `None`: none.
    pub clip_level: Option<f32>,
}

impl Products {
    /// Parse a comma-separated list (`cube,depth,peaks,ply,lifetime,intensity,phasor`) for a
    /// model of `kind`.
    pub fn parse(list: &str, kind: ModelKind) -> Result<Self> {
        let mut p = Products {
            cube: false,
            depth: false,
            peaks: false,
            ply: false,
            lifetime: false,
            intensity: false,
            phasor: false,
            returns: 2,
            fov_deg: 40.0,
            lifetime_fit: None,
            onset_s: None,
            range_fit: Some(RangeFitOptions::default()),
            depth_fit: None,
            clip_level: None,
        };
        let (allowed, _) = kind.products();
        for item in list.split(',').map(str::trim).filter(|s| !s.is_empty()) {
            let (known, _) = ModelKind::Cube.products(); // a cube model gives every product
            if !known.contains(&item) {
                return Err(InferError::InvalidParam {
                    field: "--products",
                    got: item.into(),
                    expected: format!("a comma-separated list of {}", known.join(", ")),
                });
            }
            if !allowed.contains(&item) {
                let what = match kind {
                    ModelKind::Cube => "a cube",
                    ModelKind::Depth => "depth directly",
                    ModelKind::Lifetime => "lifetimes directly",
                };
                return Err(InferError::InvalidParam {
                    field: "--products",
                    got: list.into(),
                    expected: format!("{}: this model estimates {what}", allowed.join(", ")),
                });
            }
            match item {
                "cube" => p.cube = true,
                "depth" => p.depth = true,
                "peaks" => p.peaks = true,
                "ply" => p.ply = true,
                "lifetime" => p.lifetime = true,
                "intensity" => p.intensity = true,
                _ => p.phasor = true,
            }
        }
        if !(p.cube || p.depth || p.peaks || p.ply || p.lifetime || p.intensity || p.phasor) {
            return Err(InferError::InvalidParam { field: "--products", got: list.into(), expected: "at least one product".into() });
        }
        Ok(p)
    }

    /// Whether the model must run: a product asked for comes from it (not every product comes
    /// from the fit to the taps).
    pub fn need_model(&self) -> bool {
        self.cube
            || self.peaks
            || ((self.depth || self.ply) && self.depth_fit.is_none())
            || ((self.lifetime || self.intensity || self.phasor) && self.lifetime_fit.is_none())
    }
}

/// The phasor `(g, s)` at angular frequency `ω` of a pixel's decay from its lifetimes: the
/// components' semicircle points weighted by their intensity fractions `α_iτ_i / Σ α_jτ_j`.
pub fn phasor_of_components(tau1: f32, tau2: f32, alpha1: f32, omega: f64) -> (f32, f32) {
    if !(tau1.is_finite() && tau2.is_finite() && alpha1.is_finite()) {
        return (f32::NAN, f32::NAN);
    }
    let (t1, t2, a1) = (tau1 as f64, tau2 as f64, (alpha1 as f64).clamp(0.0, 1.0));
    let (i1, i2) = (a1 * t1, (1.0 - a1) * t2);
    let total = (i1 + i2).max(1e-300);
    let point = |t: f64| {
        let wt = omega * t;
        (1.0 / (1.0 + wt * wt), wt / (1.0 + wt * wt))
    };
    let (p1, p2) = (point(t1), point(t2));
    (((i1 * p1.0 + i2 * p2.0) / total) as f32, ((i1 * p1.1 + i2 * p2.1) / total) as f32)
}
