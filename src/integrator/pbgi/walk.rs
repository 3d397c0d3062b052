//! Random walks over the bake. The bake's indirect light: walks from a patch that read
//! the direct bake at every vertex (000 Alg. 1's bounces summed in one pass). A walk
//! leaves the patch along a cosine-distributed direction; at each surface it meets it
//! adds what the direct bake holds there (or, where the bake holds nothing, a light
//! sample as the path tracer takes it: `hit_light`), then samples that surface's BSDF and
//! goes on, ended by Russian roulette (pbrt-v4 `PathIntegrator`). Its mean is the patch's
//! incident indirect radiance over all bounces, so the cloud converges to full global
//! illumination at a cost that grows with the walks, not with bounces gathered one at a
//! time. At render time, light leaving a surface the bake holds nothing for (glossy and
//! specular ones, back faces) is followed the same way up to the next surface the bake
//! covers, whose light then holds every bounce past it (`onward`).

use super::super::direct::escaped_light;
use super::super::surface::{hole_number, on_side, scattering_hit, Missed};
use super::super::{roulette, Scene};
use super::surface::{hit_light, Surface};
use crate::material::{cosine_hemisphere, Frame};
use crate::sampler::Hash;
use crate::trace::{offset_origin, Hit, Ray, Tracer};
use glam::Vec3A as V;

/// How far walks go: `vertices` surfaces at most past the patch (None: until Russian
/// roulette ends them).
#[derive(Clone, Copy, Debug)]
pub struct Walks {
    pub count: u32,
    pub vertices: Option<u32>,
}

/// Longest walk even without a limit: a closed box of white walls keeps its walks
/// alive through roulette only while their weight stays 1.
const MAX_VERTICES: u32 = 256;

/// Where a walk ends: at Russian roulette or its length (the bake's walks, reading the
/// direct bake), or at the first surface the bake covers (render time: the cloud holds
/// every bounce from there).
#[derive(Clone, Copy, PartialEq)]
enum Until {
    Roulette(u32),
    Baked,
}

impl Walks {
    /// The indirect radiance patch `tri` (front normal `ng`, rounding bound `err`) reflects,
    /// over `count` walks: each from a uniform point q of it along a direction
    /// cosine-distributed about q's shading normal, weighed by q's albedo (f·cos/pdf of a
    /// diffuse lobe); a direction below the surface takes nothing, as `on_side` has it.
    pub fn reflected(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        tri: [V; 3],
        (err, ng): (V, V),
        shading: &super::surface::Shading,
        rng: &mut Hash,
    ) -> V {
        let most = self.vertices.unwrap_or(MAX_VERTICES).min(MAX_VERTICES);
        let side = super::patch::side(tri);
        let mut sum = V::ZERO;
        for _ in 0..self.count {
            let q = super::patch::uniform_point(tri, rng);
            let (rho, n) = shading.at(q, side);
            let w = Frame::new(n)
                .to_world(cosine_hemisphere([rng.f32(), rng.f32()]))
                .normalize();
            if ng.dot(w) <= 0.0 {
                continue;
            }
            let ray = Ray {
                o: offset_origin(q, err, ng, w),
                d: w,
                t_max: f32::INFINITY,
            };
            sum += rho * walk(scene, tr, ray, rng, (Until::Roulette(most), false));
        }
        sum / self.count.max(1) as f32
    }
}

/// The light a surface the bake holds nothing for reflects toward `-d` (the hit's ray
/// direction) beyond its direct light: a walk from it, by its BSDF, to the first surface
/// the bake covers. `seed` draws the walk's numbers.
pub(super) fn onward(scene: &Scene, tr: &mut Tracer, hit: &Hit, d: V, seed: u64) -> V {
    let mut rng = Hash::new(seed);
    let Some(sp) = Surface::at(scene, hit, d) else {
        return V::ZERO;
    };
    match scatter(&sp, &mut rng) {
        Some((ray, beta, delta)) => beta * walk(scene, tr, ray, &mut rng, (Until::Baked, delta)),
        None => V::ZERO,
    }
}

/// Light arriving along `ray` that the bake and the surfaces beyond send back. Emission is
/// direct light, which the bake samples at every vertex; it is added only where a smooth
/// surface's delta lobe led to it (or to the sky), which no light sample reaches; `delta`
/// says the ray left by one.
fn walk(
    scene: &Scene,
    tr: &mut Tracer,
    mut ray: Ray,
    rng: &mut Hash,
    (until, mut delta): (Until, bool),
) -> V {
    let (mut l, mut beta) = (V::ZERO, V::ONE);
    let most = match until {
        Until::Roulette(n) => n,
        Until::Baked => MAX_VERTICES,
    };
    for depth in 0..most {
        let holes = hole_number(ray.d);
        let s = match scattering_hit(scene, tr, &mut ray, holes, &mut 0) {
            Ok(s) => s,
            Err(Missed::Left) if delta => {
                l += beta * escaped_light(scene, ray.d, None);
                break;
            }
            Err(_) => break,
        };
        let Some(sp) = Surface::at(scene, &s.hit, ray.d) else {
            break;
        };
        beta *= sp.through(s.length(&ray));
        let page = tr.page_handle(s.hit.page);
        let u = || [0; 6].map(|_| rng.f32());
        let (sends, sampled) = hit_light(scene, tr, &page, &s.hit, ray.d, u);
        l += beta * sends;
        if delta {
            l += beta * sp.emitted;
        }
        if depth + 1 == most || (until == Until::Baked && !sampled) {
            break;
        }
        let Some((next, weight, is_delta)) = scatter(&sp, rng) else {
            break;
        };
        (beta, delta) = (beta * weight, is_delta);
        if !roulette(&mut beta, || rng.f32()) {
            break;
        }
        ray = next;
    }
    l
}

/// The ray a surface's BSDF sends on, its weight f·cos/pdf and whether a delta lobe chose
/// it; None where it absorbs, the sample fails or leaves on the wrong side.
fn scatter(sp: &Surface, rng: &mut Hash) -> Option<(Ray, V, bool)> {
    if sp.absorbs {
        return None;
    }
    let bs = sp.bsdf.sample(sp.wo_l, rng.f32(), [rng.f32(), rng.f32()])?;
    let wi = sp.frame.to_world(bs.wi).normalize();
    if !on_side(&sp.frame, sp.n, wi) || !bs.weight.is_finite() || bs.weight.max_element() <= 0.0 {
        return None;
    }
    let ray = Ray {
        o: offset_origin(sp.p, sp.err, sp.ng, wi),
        d: wi,
        t_max: f32::INFINITY,
    };
    Some((ray, bs.weight, bs.delta))
}

impl super::PbgiIntegrator {
    /// What a gather's hit sends back along `w` (`hit_light`), and, where the cloud holds
    /// every bounce and the bake holds nothing for the surface, the light beyond its
    /// direct light (`onward`); the flag says it was not read from the bake.
    pub(super) fn hit_sends(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        page: &crate::paging::Page,
        hit: &Hit,
        w: V,
        u: impl FnOnce() -> [f32; 6],
    ) -> (V, bool) {
        let mut drawn = [0.0; 6];
        let (l, sampled) = hit_light(scene, tr, page, hit, w, || {
            drawn = u();
            drawn
        });
        if !sampled || !self.onward {
            return (l, sampled);
        }
        let seed = (drawn[4].to_bits() as u64) << 32 | drawn[5].to_bits() as u64;
        (l + onward(scene, tr, hit, w, seed), true)
    }
}
