//! View samples (the deep frame buffer of 001 §5 and Hašan et al. §3): for each camera
//! sample, the first surface along the camera path that is not a perfect mirror or glass,
//! with the throughput of the smooth bounces before it. Light arriving there is what a
//! relight computes, direct light at once and indirect light through the transfer.

use crate::integrator::surface::{scattering_hit, Missed};
use crate::integrator::{Scene, ShadingPoint};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Ray, Tracer};
use glam::Vec3A as V;

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

/// Where a view ray ends. Nearly every view sample is a surface, so boxing the shading
/// point would only add an allocation to each.
#[allow(clippy::large_enum_variant)]
pub enum Seen {
    Surface(ShadingPoint),
    /// It left the scene along its direction.
    Sky,
    Nothing,
}

impl ViewRay {
    fn ray(&self) -> Ray {
        Ray {
            o: V::from(self.o),
            d: V::from(self.d),
            t_max: f32::INFINITY,
        }
    }

    /// Traces the ray again: the surface it meets, prepared for shading.
    pub fn trace(&self, scene: &Scene, tr: &mut Tracer) -> Seen {
        if V::from(self.beta).max_element() <= 0.0 {
            return Seen::Nothing;
        }
        let mut ray = self.ray();
        let mut passes = self.passes;
        match scattering_hit(scene, tr, &mut ray, self.u, &mut passes) {
            Ok(s) => Seen::Surface(s.shading(scene, &ray)),
            Err(Missed::Left) => Seen::Sky,
            Err(Missed::Degenerate) => Seen::Nothing,
        }
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
