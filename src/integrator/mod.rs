//! Integrators and the scene state they share.

pub mod cone;
pub mod path;

use crate::camera::Camera;
use crate::light::Lights;
use crate::material::{Bsdf, Frame, Material};
use crate::paging::PageCache;
use crate::trace::{offset_origin, Cone, Tracer};
use glam::Vec3A as V;
use path::power_heuristic;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;

pub struct Scene {
    pub cache: Arc<PageCache>,
    pub materials: Vec<Material>,
    pub lights: Lights,
    pub camera: Camera,
    /// Longest path in segments (1: emitters seen directly); None for unbounded.
    pub max_depth: Option<u32>,
    /// One bit per node of the archive: leaves hit (ancestors are added at the end).
    pub touched: NodeSet,
    /// Pages whose stored light changed since the last pull (cone integrator).
    pub dirty: Vec<std::sync::atomic::AtomicBool>,
}

/// Per-thread counters, summed once per tile.
#[derive(Default, Clone, Copy)]
pub struct Counters {
    pub paths: u64,
    /// Samples whose radiance came out NaN or infinite: counted (the stats report them; a
    /// correct render has none) and added as zero so one bad sample cannot spoil a pixel.
    pub nonfinite: u64,
}

impl Counters {
    /// `v`, or zero (counted) when it is not finite.
    pub fn finite(&mut self, v: glam::Vec3A) -> glam::Vec3A {
        if v.is_finite() {
            v
        } else {
            self.nonfinite += 1;
            glam::Vec3A::ZERO
        }
    }
}

/// A concurrent bit set over the archive's global node numbers.
pub struct NodeSet {
    bits: Vec<AtomicU64>,
}

impl NodeSet {
    pub fn new(nodes: u64) -> NodeSet {
        NodeSet {
            bits: (0..nodes.div_ceil(64)).map(|_| AtomicU64::new(0)).collect(),
        }
    }
    pub fn bytes(&self) -> u64 {
        self.bits.len() as u64 * 8
    }
    #[inline]
    pub fn insert(&self, i: u64) {
        let (w, b) = ((i / 64) as usize, 1u64 << (i % 64));
        if let Some(word) = self.bits.get(w) {
            if word.load(Relaxed) & b == 0 {
                word.fetch_or(b, Relaxed);
            }
        }
    }
    pub fn contains(&self, i: u64) -> bool {
        self.bits
            .get((i / 64) as usize)
            .is_some_and(|w| w.load(Relaxed) & (1 << (i % 64)) != 0)
    }
    pub fn count(&self) -> u64 {
        self.bits
            .iter()
            .map(|w| w.load(Relaxed).count_ones() as u64)
            .sum()
    }
}

/// `f` for `sample_light` at a surface with this BSDF: (value · |cos θ|, pdf) for a
/// direction, in the frame whose local outgoing direction is `wo_l`.
pub fn bsdf_term(frame: Frame, bsdf: Bsdf, wo_l: V) -> impl Fn(V) -> (V, f32) {
    move |wi| {
        let wl = frame.to_local(wi);
        let (f, pdf) = bsdf.eval(wo_l, wl);
        (f * wl.z.abs(), pdf)
    }
}

/// Where a light sample is taken.
pub struct Receiver {
    pub p: V,
    /// The error bound of `p`.
    pub err: V,
    /// Unit geometric normal, for the shadow ray's offset.
    pub n: V,
    /// The normal the light chooser may weigh by |cos θ| (zero when the surface takes light
    /// from below its normal too, as a cluster's Θ does).
    pub facing: V,
    /// Light nearer than this counts as if at this distance (1/d² clamped).
    pub min_dist: f32,
}

impl Receiver {
    /// A triangle's point with its exact normal.
    pub fn surface(p: V, err: V, n: V) -> Receiver {
        Receiver {
            p,
            err,
            n,
            facing: n,
            min_dist: 0.0,
        }
    }
}

/// One light sample with MIS against the BSDF: `f(wi)` returns (value · cos, BSDF pdf).
/// Visibility is tested with `shadow_cone` (scale 0: an exact ray; the cone integrator uses
/// the pixel's opening, so distant occluders are tested at a coarse level and far pages
/// need not load).
pub fn sample_light(
    scene: &Scene,
    tr: &mut Tracer,
    at: &Receiver,
    shadow_cone: &Cone,
    u: [f32; 3],
    f: impl Fn(V) -> (V, f32),
) -> V {
    let Some(ls) = scene.lights.sample(at.p, at.facing, u[0], [u[1], u[2]]) else {
        return V::ZERO;
    };
    let (fv, pdf_b) = f(ls.wi);
    if fv.max_element() <= 0.0 {
        return V::ZERO;
    }
    let from = offset_origin(at.p, at.err, at.n, ls.wi);
    if tr.cone_occluded(&ls.shadow_ray(from), shadow_cone) {
        return V::ZERO;
    }
    let w = if ls.pdf > 0.0 {
        power_heuristic(ls.pdf, pdf_b)
    } else {
        1.0
    };
    let clamp = if ls.dist < at.min_dist {
        (ls.dist / at.min_dist).powi(2)
    } else {
        1.0
    };
    fv * ls.weight * w * clamp
}
