//! View samples (the deep frame buffer of 001 §5 and Hašan et al. §3): for each camera
//! sample, the first surface along the camera path that is not a perfect mirror or glass,
//! with the throughput of the smooth bounces before it. Light arriving there is what a
//! relight computes, direct light at once and indirect light through the transfer.

use crate::integrator::surface::{scattering_hit, Missed};
use crate::integrator::{Scene, ShadingPoint};
use crate::material::{Bsdf, Frame};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;
use rustc_hash::FxHashMap;

/// Most smooth bounces followed before a view sample (deeper chains end black).
const MAX_SMOOTH: u32 = 16;

/// The last segment of a camera path: re-tracing it finds the view sample's surface again
/// (or its escape), with the alpha holes decided alike (`u`, `passes`).
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct ViewRay {
    pub o: [f32; 3],
    pub d: [f32; 3],
    /// Throughput of the smooth bounces before it (zero: the sample is black).
    pub beta: [f32; 3],
    pub u: f32,
    pub passes: u32,
}

/// Where a view ray ends: a surface that reflects light (one whose lobes are all smooth,
/// or that absorbs, reflects no direct light and is `Nothing`), or the sky.
pub enum Seen {
    Surface(Surface),
    /// It left the scene along its direction.
    Sky,
    Nothing,
}

/// A view sample's surface as a relight shades it: what next-event estimation reads of
/// its shading point, kept small (a view holds 16 a pixel), its BSDF by number in a
/// `Bsdfs` table (most view samples share their material's).
#[derive(Clone, Copy)]
pub struct Surface {
    pub p: [f32; 3],
    pub err: [f32; 3],
    /// Unit geometric normal, turned to the side seen.
    pub n: [f32; 3],
    /// The shading frame's normal (the frame is made from it alone).
    pub shading: [f32; 3],
    pub wo_l: [f32; 3],
    pub bsdf: u32,
}

impl Surface {
    pub fn frame(&self) -> Frame {
        Frame::new(V::from(self.shading))
    }
}

/// Distinct BSDFs, each once.
#[derive(Default)]
pub struct Bsdfs {
    pub list: Vec<Bsdf>,
    index: FxHashMap<[u32; 24], u32>,
}

impl Bsdfs {
    /// `b`'s number, added if new.
    fn intern(&mut self, b: &Bsdf) -> u32 {
        let mut key = [0u32; 24];
        key[..18].copy_from_slice(&b.glossy_key());
        key[18..21].copy_from_slice(&b.diffuse.to_array().map(f32::to_bits));
        key[21..].copy_from_slice(&b.tint.to_array().map(f32::to_bits));
        let n = self.list.len() as u32;
        *self.index.entry(key).or_insert_with(|| {
            self.list.push(*b);
            n
        })
    }

    /// Adds `other`'s BSDFs and renumbers `seen`, which numbered them in `other`.
    pub fn merge(&mut self, other: &Bsdfs, seen: &mut [Seen]) {
        let numbers: Vec<u32> = other.list.iter().map(|b| self.intern(b)).collect();
        for s in seen {
            if let Seen::Surface(x) = s {
                x.bsdf = numbers[x.bsdf as usize];
            }
        }
    }
}

impl ViewRay {
    fn ray(&self) -> Ray {
        Ray {
            o: V::from(self.o),
            d: V::from(self.d),
            t_max: f32::INFINITY,
        }
    }

    /// Traces the ray again: the surface it meets, prepared for shading, its BSDF numbered
    /// in `bsdfs`.
    pub fn trace(&self, scene: &Scene, tr: &mut Tracer, bsdfs: &mut Bsdfs) -> Seen {
        if V::from(self.beta).max_element() <= 0.0 {
            return Seen::Nothing;
        }
        let mut ray = self.ray();
        let mut passes = self.passes;
        let sp = match scattering_hit(scene, tr, &mut ray, self.u, &mut passes) {
            Ok(s) => s.shading(scene, &ray),
            Err(Missed::Left) => return Seen::Sky,
            Err(Missed::Degenerate) => return Seen::Nothing,
        };
        if sp.absorbs || sp.bsdf.has_smooth_only() {
            return Seen::Nothing;
        }
        Seen::Surface(Surface {
            p: sp.p.into(),
            err: sp.err.into(),
            n: sp.n.into(),
            shading: sp.frame.n.into(),
            wo_l: sp.wo_l.into(),
            bsdf: bsdfs.intern(&sp.bsdf),
        })
    }
}

/// The view sample of the camera ray `ray`: its smooth bounces followed (choices drawn
/// from `s`'s sets 1..), and the shading point reached. `lamp` is told
/// each lamp met on the way, by material, with the light it sends along the path.
pub fn view_sample(
    scene: &Scene,
    tr: &mut Tracer,
    mut ray: Ray,
    s: &PixelSampler,
    lamp: &mut impl FnMut(u32, V),
) -> (ViewRay, Option<ShadingPoint>) {
    let mut beta = V::ONE;
    let mut passes = 0u32;
    let black = |ray: &Ray| ViewRay {
        o: ray.o.into(),
        d: ray.d.into(),
        beta: [0.0; 3],
        u: 0.0,
        passes: 0,
    };
    for bounce in 0..MAX_SMOOTH {
        let [u, u_lobe, u0, u1] = s.get4(1 + bounce);
        let at = ViewRay {
            o: ray.o.into(),
            d: ray.d.into(),
            beta: beta.into(),
            u,
            passes,
        };
        let scatter = match scattering_hit(scene, tr, &mut ray, u, &mut passes) {
            Ok(s) => s,
            Err(Missed::Left) => return (at, None),
            Err(Missed::Degenerate) => return (black(&ray), None),
        };
        let sp = scatter.shading(scene, &ray);
        beta *= sp.through(scatter.length(&ray));
        let at = ViewRay {
            beta: beta.into(),
            ..at
        };
        let material = scatter.hit.tri.material;
        if sp.emitted.max_element() > 0.0 {
            lamp(material, beta * sp.emitted);
        }
        // A surface with lobes to sample is the view sample; so is one with none at all
        // (a black lamp), where the path ends.
        let smooth = sp.bsdf.has_smooth_only() && sp.bsdf.delta_share(sp.wo_l) > 0.0;
        if sp.absorbs || !smooth {
            return (at, Some(sp));
        }
        let Some(bs) = sp.bsdf.sample_delta(sp.wo_l, u_lobe, [u0, u1]) else {
            return (black(&ray), None);
        };
        let wi = sp.frame.to_world(bs.wi).normalize();
        beta *= bs.weight;
        if !beta.is_finite() || beta.max_element() <= 0.0 {
            return (black(&ray), None);
        }
        ray = Ray {
            o: offset_origin(sp.p, sp.err, sp.ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        passes = 0;
    }
    (black(&ray), None)
}
