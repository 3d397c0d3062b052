//! `--integrator cone`: stochastic cone casts with diffuse radiance stored in the nodes
//! (004 §4.5–4.6, §4.8).
//!
//! Each cast is a ray that stops at the first node the cone's radius outgrows (eq. 4.12,
//! scaled by `--cone-scale`; 0 traces exact rays). Primary cones open by one pixel
//! (eq. 4.19) and are jittered in the pixel; after a diffuse bounce tan α = `--diffuse-tan`
//! (eq. 4.20) from the surface; a mirror keeps the cone and resamples the direction
//! uniformly inside it (eq. 4.14–4.16). Light samples are cones of the pixel's opening.
//! Every diffuse hit — a leaf triangle's cell or a whole node — adds a fresh sample of
//! its incident radiance (one light sample, one cosine-sampled bounce, emission masked at
//! the next hit as eq. 4.27 does) to the node's store and returns the node's mean
//! (eq. 4.24–4.25); a node whose counter reached the limit returns its mean without
//! recursing (§4.6.1). The pixel itself takes the fresh sample at the primary hit,
//! so visibility and direct light on screen are exact; stored means serve the bounces.
//! After each pass the store is pulled up the tree (§4.8) so nodes first met by wide cones
//! start from their children's light.
//!
//! Surfaces with specular or transmissive lobes are traced as the path tracer does (no
//! storage); a smooth bounce bends the cone by the surface's curvature (`bent_tan`). Nodes
//! are shaded with the cluster BRDF: a reflect / refract / diffuse choice from the node's
//! Fresnel table and refractiveness (§4.3), a Phong lobe about the heuristic direction
//! (eq. 4.7–4.11), and a Lambertian part with the area-weighted albedo and the Θ heuristic
//! of eq. 4.4 for light samples. When the light pass (`light_pass`, §4.7) runs, diffuse
//! hits add the caustic light it stored, and emission reached from a diffuse hit through
//! smooth bounces only is masked, so caustic paths count once. The emission seen at the
//! primary hit comes back apart from the rest, so the renderer can average it over more of
//! the pixel where the pixel straddles a lamp's silhouette (`seen_emission`).

pub mod light_pass;

use crate::integrator::path::power_heuristic;
use crate::integrator::{bsdf_term, sample_light, Counters, Receiver, Scene};
use crate::convert::MAX_LEAF_TRIS;
use crate::material::{cosine_hemisphere, Frame};
use crate::paging::{TriW, CHILD_PAGE, INNER, KIND_MASK, LEAF};
use crate::radiance::{weighted_mean, RadianceStore, SCREEN_LIMIT};
use crate::sampler::PixelSampler;
use crate::trace::{offset_origin, Cone, ConeHit, Ray, Tracer};
use canopy_format::codec::{rgbe64_decode, snorm16_decode, unorm8_decode};
use canopy_format::NodeFlags;
use glam::Vec3A as V;
use rayon::prelude::*;
use std::sync::atomic::Ordering::Relaxed;

/// Hits, counted from the eye, whose diffuse light the pixel takes from its own fresh
/// sample; deeper hits answer with their node's stored mean.
pub const FRESH: u32 = 1;

/// On-screen samples a cell needs before the pixel takes its indirect light from the
/// cell's mean instead of its own bounce.
pub const ON_SCREEN_MIN: u32 = 16;

/// See `radiance`: on-screen samples every cell takes, and the factor of √(visits·passes)
/// it keeps taking; measured on sponza, cbox and bunny_box (README, the cone integrator).
pub const SCREEN_FLOOR: f32 = 32.0;
pub const SCREEN_QUOTA: f32 = 0.25;

/// Default tan α after a diffuse bounce (004 eq. 4.20's d; `--diffuse-tan`). Deviation:
/// the thesis chose 0.3 by eye; measured against the path tracer, clusters standing in
/// for their triangles at that width biased the image mean by −0.95% on sponza and +7.1%
/// on 20 M bunnies, against −0.15% and +1.4% at 0.03, which cost sponza no time and the
/// bunnies 18% (README).
pub const DIFFUSE_TAN: f32 = 0.03;

/// Store key of a node's own light.
pub fn node_key(node: u64) -> u64 {
    node * (MAX_LEAF_TRIS as u64 + 1) * CELLS
}

/// Side of a triangle's light-cell grid at most (16×16 over the barycentrics): a triangle
/// much larger than `CELL_FRACTION` of the scene keeps light per cell, so a wall lit
/// unevenly is not one average.
pub const GRID: u64 = 16;
pub const CELLS: u64 = GRID * GRID;
/// Target cell size as a fraction of the scene's bounding diagonal.
pub const CELL_FRACTION: f32 = 1.0 / 128.0;

/// Side n of a triangle's n×n cell grid, from its longest edge.
pub fn grid(tri: &TriW, cell_size: f32) -> f32 {
    let p = tri.p.map(V::from);
    let edge = (p[1] - p[0])
        .length()
        .max((p[2] - p[1]).length())
        .max((p[0] - p[2]).length());
    (edge / cell_size).ceil().clamp(1.0, GRID as f32)
}

/// Side of the light cells on this archive's large triangles: `CELL_FRACTION` of the
/// scene's diagonal.
pub fn cell_size(h: &canopy_format::Header) -> f32 {
    (V::from(h.bounds_max) - V::from(h.bounds_min)).length() * CELL_FRACTION
}

/// Cell of a hit inside its triangle: an n×n grid over (b1, b2).
pub fn cell_of(tri: &TriW, b: [f32; 3], cell_size: f32) -> u64 {
    let n = grid(tri, cell_size);
    let i = (b[1] * n).min(n - 1.0).max(0.0) as u64;
    let j = (b[2] * n).min(n - 1.0).max(0.0) as u64;
    i * GRID + j
}

/// The cells of a triangle with their areas: a grid square inside the triangle (i + j ≤
/// n − 2) covers 2/n² of its area, one on the diagonal (i + j = n − 1) half that.
pub fn cells(tri: &TriW, cell_size: f32) -> impl Iterator<Item = (u64, f32)> {
    let n = grid(tri, cell_size) as u64;
    let area = tri_area(tri);
    let full = 2.0 * area / (n * n) as f32;
    (0..n).flat_map(move |i| {
        (0..n - i).map(move |j| (i * GRID + j, if i + j + 1 == n { full / 2.0 } else { full }))
    })
}

pub fn tri_area(tri: &TriW) -> f32 {
    let p = tri.p.map(V::from);
    0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
}

/// Store key of a cell of the k-th triangle of a leaf: leaves keep light per triangle (they
/// may face different ways) and per cell; the leaf's own key gets their area-weighted mean.
pub fn tri_key(leaf: u64, k: u32, cell: u64) -> u64 {
    node_key(leaf) + (1 + k as u64) * CELLS + cell
}

/// What one bounce needs to finish once the rest of the path is known.
struct Pending {
    /// Store key (global node number) when this bounce's diffuse light is stored.
    node: Option<u64>,
    /// Page holding that node.
    page: u32,
    /// Radiance gathered here independent of the continuation: emission and light samples.
    direct: V,
    emission: V,
    albedo: V,
    /// Caustic light arriving here (E/π) from the light pass.
    caustic: V,
    /// Continuation weight (BSDF value · cos / pdf, roulette included).
    weight: V,
    diffuse: bool,
}

/// Jitters a direction uniformly inside the cone of half-angle atan(tan α) (eq. 4.14–4.16)
/// and moves the origin so the cone's virtual apex stays put (Fig. 7).
pub fn jitter(o: V, d: V, cone: &Cone, u: [f32; 2]) -> (V, V) {
    if cone.tan_a <= 0.0 {
        return (o, d);
    }
    let cos_a = 1.0 / (1.0 + cone.tan_a * cone.tan_a).sqrt();
    let z = (1.0 - cos_a) * u[0] + cos_a;
    let phi = 2.0 * std::f32::consts::PI * u[1];
    let s = (1.0 - z * z).max(0.0).sqrt();
    let f = Frame::new(d);
    let nd = f
        .to_world(V::new(s * phi.cos(), s * phi.sin(), z))
        .normalize();
    // The apex sits r0 / tan α behind the origin; keep it and start on the old origin plane.
    let apex = o - d * (cone.r0 / cone.tan_a);
    let t = (o - apex).dot(d) / nd.dot(d).max(1e-6);
    (apex + nd * t, nd)
}

/// Opening of a cone after a smooth bounce at distance `t` off a surface of mean
/// curvature `kappa` (signed about the normal on the outgoing side, positive for convex);
/// `cos_o`, `cos_i`: cosines of the outgoing and new directions with that normal; `eta`:
/// relative index across the surface.
///
/// Deviation: eq. 4.21–4.22 scale tan α by (1 ∓ κ·b·cos θ), which mixes a curvature
/// (1/length) into a dimensionless factor, so b would depend on the scene's units. This
/// uses the ray-differential terms the thesis cites instead (Igehy 1999, as in pbrt-v3
/// §10.1.3): the footprint r sees normals turn by κ·r, which adds 2κr·cos θ to a reflected
/// opening and μκr to a refracted one (μ = cos θo/η − cos θi), whose own spread shrinks by
/// η. The new cone starts at the surface with r0 = 0: a frustum starting as wide as the
/// footprint would stop at the mirror's own neighbouring nodes. A focusing surface (negative
/// result) gives an exact ray until the next bounce, which only makes the level finer.
pub fn bent_tan(cone: &Cone, t: f32, kappa: f32, cos_o: f32, cos_i: f32, eta: f32) -> f32 {
    let r = cone.radius(t);
    let tan = if cos_i > 0.0 {
        cone.tan_a + 2.0 * kappa * r * cos_o
    } else {
        let mu = cos_o / eta - cos_i.abs();
        cone.tan_a / eta + mu * kappa * r
    };
    tan.clamp(0.0, cone.spread)
}

/// ∫ Θ dω / π over the sphere for eq. 4.4's Θ = (1 − |n|)/4 + ⟨n, ω⟩ (clamped at 0) with
/// a normal of length `len`: 1 for a flat cluster and for a closed one (|n| = 0), less
/// between (0.78 at |n| = 0.5). Light samples divide Θ by it so a cluster reflects its
/// albedo under uniform light, as its cosine-sampled bounce does; Θ as printed darkened
/// sponza's clusters (about 15% of the default cones' bias there).
pub fn theta_norm(len: f32) -> f32 {
    let len = len.clamp(0.0, 1.0);
    let a = (1.0 - len) / 4.0;
    // Θ > 0 for cos > c0.
    let c0 = if len > 0.0 {
        (-a / len).max(-1.0)
    } else {
        -1.0
    };
    2.0 * (a * (1.0 - c0) + len * (1.0 - c0 * c0) / 2.0)
}

/// p_reflect at cos θ from the node's five-sample table (004 §4.3.1), linearly
/// interpolated.
fn reflect_lut(lut: [u8; 5], c: f32) -> f32 {
    let x = c.clamp(0.0, 1.0) * 4.0;
    let i = (x as usize).min(3);
    let f = x - i as f32;
    unorm8_decode(lut[i]) * (1.0 - f) + unorm8_decode(lut[i + 1]) * f
}

/// Samples the cluster's Phong lobe (004 eq. 4.7–4.11): shininess s' = s|n| + (1 − |n|)
/// about r' = r|n| + ω(1 − |n|), with s from the GGX roughness (s = 2/α² − 2); a sample
/// below the cluster's plane is mirrored back above it rather than rejected, keeping the
/// lobe's energy. `n`: unit normal on the side of `wo`, `len`: the cluster normal's length.
/// Returns the direction and s'.
fn phong_lobe(n: V, len: f32, wo: V, roughness: u8, u: [f32; 2]) -> (V, f32) {
    let r = 2.0 * n.dot(wo) * n - wo;
    let axis = (r * len + wo * (1.0 - len)).normalize_or(n);
    let a = unorm8_decode(roughness).powi(2).max(1e-3);
    let s = (2.0 / (a * a) - 2.0).clamp(1.0, 1e4) * len + (1.0 - len);
    let cos_t = u[0].powf(1.0 / (s + 1.0));
    let sin_t = (1.0 - cos_t * cos_t).max(0.0).sqrt();
    let phi = 2.0 * std::f32::consts::PI * u[1];
    let mut wi = Frame::new(axis)
        .to_world(V::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t))
        .normalize();
    if wi.dot(n) < 0.0 {
        wi -= 2.0 * wi.dot(n) * n;
    }
    (wi, s)
}

/// Radiance along a primary cone, as (everything but the emission seen at the primary
/// hit, that emission).
pub fn radiance(
    scene: &Scene,
    store: &RadianceStore,
    tr: &mut Tracer,
    ray: Ray,
    cone: Cone,
    s: &PixelSampler,
    c: &mut Counters,
) -> (V, V) {
    let mut stack: Vec<Pending> = Vec::new();
    let h = &scene.cache.archive.header;
    let cell_size = cell_size(h);
    let mut ray = ray;
    // Light samples test visibility with the primary cone's opening, from the surface.
    let shadow_cone = Cone { r0: 0.0, ..cone };
    let mut cone = cone;
    let mut prev_delta = true;
    let mut prev_pdf = 0.0f32;
    // The last glossy point and its normal, where its light sample was chosen.
    let mut prev = (V::ZERO, V::ZERO);
    let mut tail = V::ZERO;
    let mut depth = 0u32;
    // With the light pass on, emission reached from a Lambertian surface through smooth
    // bounces only (D S* S L) is the light pass's caustic and masked here (004 §4.7).
    let mask_caustics = store.photons() > 0;
    let mut smooth_chain = false;
    loop {
        let [u_pick, ul0, ul1, u_lobe] = s.get4(2 * depth + 1);
        let [ud0, ud1, u_rr, u_j] = s.get4(2 * depth + 2);
        let Some(hit) = tr.cone_hit(&ray, &cone) else {
            break;
        };
        let (p, err, ng, wo) = match &hit {
            ConeHit::Tri(h) => {
                let (p, err) = h.point();
                (p, err, h.ng().normalize_or_zero(), -ray.d)
            }
            ConeHit::Node { t, .. } => {
                let p = ray.o + ray.d * *t;
                (
                    p,
                    p.abs() * crate::trace::gamma(7) + V::splat(1e-6),
                    V::ZERO,
                    -ray.d,
                )
            }
        };
        let mut pend = Pending {
            node: None,
            page: match &hit {
                ConeHit::Tri(h) => h.page,
                ConeHit::Node { page, .. } => *page,
            },
            direct: V::ZERO,
            emission: V::ZERO,
            albedo: V::ZERO,
            caustic: V::ZERO,
            weight: V::ZERO,
            diffuse: false,
        };
        // Shading frame and material.
        // A cluster is shaded at its box entry point, which can lie next to a lamp inside the
        // same box; light closer than the cluster's radius is taken at that radius, as a
        // disc of that size would receive it (bounded, like clamping virtual point lights).
        let mut min_dist = 0.0f32;
        // `--max-depth` counts segments as the path tracer does: a hit on the last one
        // keeps the emission it sees and scatters nothing (no light sample, no bounce).
        let last = scene.max_depth.is_some_and(|m| depth + 1 >= m);
        let (frame, albedo, node_key, cluster_n) = match &hit {
            ConeHit::Tri(h) => {
                let m = &scene.materials[h.tri.material as usize];
                let area = 0.5 * h.ng().length();
                if area.is_nan() || area <= 0.0 {
                    break;
                }
                let front = ng.dot(wo) > 0.0;
                let le = m.emitted(front);
                if le != V::ZERO {
                    if prev_delta {
                        if !(mask_caustics && smooth_chain) {
                            pend.emission = le;
                        }
                    } else if matches!(stack.last(), Some(p) if !p.diffuse) {
                        // After a glossy bounce: MIS against the light sample, as the path
                        // tracer does; after a diffuse bounce emission is masked (eq. 4.27).
                        let dist2 = h.t * h.t;
                        let lp = scene.lights.pick_pdf(prev.0, prev.1, &h.tri.p) * dist2
                            / (ng.dot(wo).abs() * area);
                        pend.emission = le * power_heuristic(prev_pdf, lp);
                    }
                }
                if last || (!front && !m.double_sided && m.transmission == 0.0) {
                    stack.push(pend);
                    break;
                }
                let n = if front { ng } else { -ng };
                let bsdf = m.bsdf(front);
                scene.touched.insert(h.leaf);
                if !m.is_pure_diffuse() {
                    // Not purely diffuse: one exact path-tracing step, nothing stored.
                    let frame = Frame::new(n);
                    let wo_l = frame.to_local(wo);
                    if !bsdf.has_smooth_only() {
                        pend.direct += sample_light(
                            scene,
                            tr,
                            &Receiver::surface(p, err, ng),
                            &shadow_cone,
                            [u_pick, ul0, ul1],
                            bsdf_term(frame, bsdf, wo_l),
                        );
                    }
                    let Some(bs) = bsdf.sample(wo_l, u_lobe, [ud0, ud1]) else {
                        stack.push(pend);
                        break;
                    };
                    let wi = frame.to_world(bs.wi).normalize();
                    pend.weight = bs.weight;
                    prev_delta = bs.delta;
                    smooth_chain &= bs.delta;
                    prev_pdf = bs.pdf;
                    prev = (p, ng);
                    // A smooth surface bends the cone by its curvature (eq. 4.21–4.22) and
                    // the direction is resampled inside the incoming opening (eq. 4.14–4.16,
                    // Fig. 7). A glossy bounce starts a fresh diffuse-width cone.
                    let o = offset_origin(p, err, ng, wi);
                    let (o, d) = if bs.delta && cone.scale > 0.0 {
                        let (o, d) = jitter(o, wi, &cone, [u_j, u_rr]);
                        let kappa = if front { h.curvature } else { -h.curvature };
                        cone = Cone {
                            r0: 0.0,
                            tan_a: bent_tan(&cone, h.t, kappa, wo.dot(n), wi.dot(n), bsdf.eta),
                            ..cone
                        };
                        (o, d)
                    } else {
                        cone = Cone {
                            r0: 0.0,
                            tan_a: cone.spread,
                            ..cone
                        };
                        (o, wi)
                    };
                    ray = Ray {
                        o,
                        d,
                        t_max: f32::INFINITY,
                    };
                    stack.push(pend);
                    depth += 1;
                    if !roulette(&mut stack, depth, u_rr) {
                        break;
                    }
                    continue;
                }
                let cell = cell_of(&h.tri, h.b, cell_size);
                (
                    Frame::new(n),
                    bsdf.diffuse,
                    tri_key(h.leaf, h.slot, cell),
                    None,
                )
            }
            ConeHit::Node {
                node, record: raw, ..
            } => {
                scene.touched.insert(*node);
                let key = node_key(*node);
                let nn = V::from(raw.normal.map(snorm16_decode));
                let len = nn.length();
                let n = if len > 1e-6 { nn / len } else { wo };
                let n = if n.dot(wo) < 0.0 { -n } else { n };
                if prev_delta && !(mask_caustics && smooth_chain) {
                    pend.emission = hit_emission(scene, &hit, wo);
                }
                if last {
                    stack.push(pend);
                    break;
                }
                let mut rho = V::from(raw.diffuse.map(unorm8_decode));
                min_dist = raw.radius;
                if raw.flags & (NodeFlags::GLOSSY | NodeFlags::TRANSMISSIVE) != 0 {
                    // Cluster BRDF (§4.3): reflect with p_reflect(Θ), refract with
                    // refractiveness·(1 − p_reflect) (eq. 4.1), else diffuse (eq. 4.2).
                    let nl = if nn.dot(wo) < 0.0 { -nn } else { nn };
                    let theta = ((1.0 - len) / 4.0 + nl.dot(wo)).clamp(0.0, 1.0);
                    let p_r = reflect_lut(raw.reflectiveness, theta);
                    let p_t = unorm8_decode(raw.refractiveness) * (1.0 - p_r);
                    if u_lobe < p_r + p_t {
                        let (wi, weight, smooth) = if u_lobe < p_r {
                            let (wi, s) = phong_lobe(n, len, wo, raw.roughness, [ud0, ud1]);
                            let tint = V::from(raw.specular_tint.map(unorm8_decode));
                            (wi, tint, s >= 1e3)
                        } else {
                            // Through a transmissive cluster: straight on, tinted (its
                            // lensing is below the level of detail the cone asked for).
                            let tint = V::from(raw.translucency.map(unorm8_decode));
                            (-wo, tint, true)
                        };
                        // A near-mirror or glass cluster keeps the cone and stands for a
                        // smooth bounce (its caustics are the light pass's); a glossy one
                        // widens the cone.
                        let tan_a = if smooth { cone.tan_a } else { cone.spread };
                        pend.weight = weight;
                        prev_delta = true;
                        prev_pdf = 0.0;
                        smooth_chain &= smooth;
                        cone = Cone {
                            r0: 0.0,
                            tan_a,
                            ..cone
                        };
                        ray = Ray {
                            o: offset_origin(p, err, if wi.dot(n) > 0.0 { n } else { wi }, wi),
                            d: wi,
                            t_max: f32::INFINITY,
                        };
                        stack.push(pend);
                        depth += 1;
                        if !roulette(&mut stack, depth, u_rr) {
                            break;
                        }
                        continue;
                    }
                    let p_d = 1.0 - p_r - p_t;
                    rho = if p_d > 1e-3 { rho / p_d } else { V::ZERO };
                }
                (
                    Frame::new(n),
                    rho,
                    key,
                    Some(if nn.dot(n) < 0.0 { -nn } else { nn }),
                )
            }
        };
        pend.albedo = albedo;
        pend.diffuse = true;
        pend.node = Some(node_key);
        let entry = if depth == 0 {
            store.visit(node_key)
        } else {
            store.get(node_key)
        };
        if mask_caustics {
            pend.caustic = entry
                .and_then(|e| store.caustic(&e))
                .map_or(V::ZERO, V::from);
        }
        // A converged node answers from its store (§4.6.1); on screen only for its
        // indirect part, the light sample below stays fresh.
        if depth >= FRESH {
            if let Some(e) = entry.filter(|e| e.n >= store.limit) {
                let (v, _) = e.value().unwrap_or(([0.0; 3], 0));
                pend.node = None;
                pend.direct = V::from(v);
                stack.push(pend);
                break;
            }
        }
        // Light sample: cos θ, or Θ = (1−|n|)/4 + ⟨n, ω⟩ for a cluster (eq. 4.4). Emission
        // is masked at the next hit (eq. 4.27), so the light sample takes full weight.
        let theta = |wi: V| match cluster_n {
            Some(nn) => {
                let len = nn.length();
                ((1.0 - len) / 4.0 + nn.dot(wi)).max(0.0) / theta_norm(len)
            }
            None => frame.n.dot(wi).max(0.0),
        };
        let shade_n = if ng == V::ZERO { frame.n } else { ng };
        let at = Receiver {
            p,
            err,
            n: shade_n,
            facing: if cluster_n.is_some() {
                V::ZERO
            } else {
                shade_n
            },
            min_dist,
        };
        pend.direct = sample_light(scene, tr, &at, &shadow_cone, [u_pick, ul0, ul1], |wi| {
            (V::splat(theta(wi) * std::f32::consts::FRAC_1_PI), 0.0)
        });
        // On screen a cell traces only some of its pixels' bounces: it keeps sampling while
        // it holds fewer than max(SCREEN_FLOOR, SCREEN_QUOTA·√(visits·k)) samples after k
        // passes, which with P pixels on it is a fraction ∝ 1/√P of their bounces. The
        // other pixels cost their primary cone and light sample only (the thesis's 4× per
        // iteration once stored light has converged, §5.8), and the cell's error still
        // falls with time. 1/√P minimizes error × cost when the light sample's variance
        // and the indirect light's are alike: err² ∝ 1 + 1/(f·P), cost ∝ 1 + f.
        if let Some(e) = entry.filter(|e| depth == 0 && e.ni >= ON_SCREEN_MIN) {
            let passes = store.passes() as f32;
            let quota = SCREEN_FLOOR.max(SCREEN_QUOTA * (e.visits as f32 * passes).sqrt());
            if e.ni >= SCREEN_LIMIT || e.ni as f32 >= quota {
                if let Some(ind) = e.indirect_mean(ON_SCREEN_MIN) {
                    pend.node = None;
                    pend.direct += V::from(ind);
                    stack.push(pend);
                    break;
                }
            }
        }
        // Cosine-sampled bounce; weight 1 (the albedo is applied when unwinding).
        let wi = frame.to_world(cosine_hemisphere([ud0, ud1])).normalize();
        pend.weight = V::ONE;
        stack.push(pend);
        // A diffuse bounce starts a fresh cone of tan α = `spread` at the surface (eq. 4.20);
        // its direction is already random (cosine-weighted), so it is not jittered again, and
        // starting at r0 = 0 keeps the origin on the surface: a frustum whose first disc is
        // the incoming footprint would start rays beside walls and leak light.
        cone = Cone {
            r0: 0.0,
            tan_a: cone.spread,
            ..cone
        };
        let (o, d) = (offset_origin(p, err, shade_n, wi), wi);
        ray = Ray {
            o,
            d,
            t_max: f32::INFINITY,
        };
        prev_delta = false;
        prev_pdf = 0.0;
        smooth_chain = true;
        depth += 1;
        if !roulette(&mut stack, depth, u_rr) {
            break;
        }
    }
    // The emission seen at the primary hit goes back apart (the caller may average it
    // over more of the pixel); the rest unwinds: each bounce's value is its emission plus
    // what it scatters of the next.
    let seen = stack
        .first_mut()
        .map_or(V::ZERO, |b| std::mem::take(&mut b.emission));
    while let Some(b) = stack.pop() {
        let incoming = b.direct + b.weight * tail;
        if b.node.is_some() {
            if let Some(d) = scene.dirty.get(b.page as usize) {
                d.store(true, Relaxed);
            }
        }
        tail = if b.diffuse {
            let scattered = match b.node {
                // On screen the light sample is the path's own and the indirect part the
                // cell's mean once it has a few samples: a final gather from the store
                // (§5.8 gathers only from converged nodes). The sample feeds both.
                Some(key) if stack.len() < FRESH as usize => {
                    let indirect = b.weight * tail;
                    store
                        .add_on_screen(key, incoming.to_array(), indirect.to_array())
                        .and_then(|e| e.indirect_mean(ON_SCREEN_MIN))
                        .map_or(incoming, |m| b.direct + V::from(m))
                }
                Some(key) => V::from(store.add(key, incoming.to_array()).0),
                None => b.direct,
            };
            b.emission + b.albedo * (scattered + b.caustic)
        } else {
            b.emission + incoming
        };
    }
    c.paths += 1;
    (c.finite(tail), c.finite(seen))
}

/// Emission a cone's hit sends back along the cone: a lamp triangle's from its emitting
/// side(s), a cluster's when its normal faces the cone (or it has none).
fn hit_emission(scene: &Scene, hit: &ConeHit, wo: V) -> V {
    match hit {
        ConeHit::Tri(h) => scene.materials[h.tri.material as usize].emitted(h.ng().dot(wo) > 0.0),
        ConeHit::Node { record, .. } => {
            let nn = V::from(record.normal.map(snorm16_decode));
            if nn.dot(wo) > 0.0 || nn.length() <= 1e-6 {
                V::from(rgbe64_decode(record.emission))
            } else {
                V::ZERO
            }
        }
    }
}

/// Emission seen directly along a primary cone: the part of a pixel's value that only
/// its primary hit decides, which `radiance` returns apart so a pixel on an emitter's
/// silhouette can average it over more positions than it shades.
pub fn seen_emission(
    scene: &Scene,
    tr: &mut Tracer,
    ray: &Ray,
    cone: &Cone,
    c: &mut Counters,
) -> V {
    let Some(hit) = tr.cone_hit(ray, cone) else {
        return V::ZERO;
    };
    scene.touched.insert(match &hit {
        ConeHit::Tri(h) => h.leaf,
        ConeHit::Node { node, .. } => *node,
    });
    c.finite(hit_emission(scene, &hit, -ray.d))
}

/// Russian roulette after the second bounce on the product of the bounces' weights and
/// albedos; a survivor's weight is divided by its survival probability.
fn roulette(stack: &mut [Pending], depth: u32, u: f32) -> bool {
    if depth <= 1 {
        return true;
    }
    let beta = stack.iter().fold(V::ONE, |b, p| {
        b * p.weight * if p.diffuse { p.albedo } else { V::ONE }
    });
    let q = beta.max_element().min(1.0);
    if q <= 0.0 || u >= q {
        return false;
    }
    if let Some(last) = stack.last_mut() {
        last.weight /= q;
    }
    true
}

/// Pull (004 §4.8): every inner node of the resident pages whose light changed (and of
/// their ancestor pages) gets the area-weighted mean of
/// its children's stored light, deepest pages first so page roots are ready for their
/// parents. Evicted pages are skipped, not reloaded: their nodes keep the values of the
/// last pull (the store itself never loses samples).
pub fn pull(scene: &Scene, store: &RadianceStore) {
    let archive = &scene.cache.archive;
    let dirty = |i: u32| scene.dirty[i as usize].swap(false, Relaxed);
    let mut pages: Vec<u32> = (0..archive.pages.len() as u32)
        .filter(|&i| dirty(i))
        .collect();
    // A changed page changes its parent page's cut node: pull the ancestors too.
    let mut seen: std::collections::HashSet<u32> = pages.iter().copied().collect();
    let mut i = 0;
    while i < pages.len() {
        let parent = archive.pages[pages[i] as usize].parent_page;
        if parent != canopy_format::NONE && seen.insert(parent) {
            pages.push(parent);
        }
        i += 1;
    }
    pages.sort_by_key(|&i| std::cmp::Reverse(archive.pages[i as usize].level));
    // Pages of one level are independent: pull them in parallel, level by level.
    for level in
        pages.chunk_by(|a, b| archive.pages[*a as usize].level == archive.pages[*b as usize].level)
    {
        level.par_iter().for_each(|&id| pull_page(scene, store, id));
    }
}

/// One part a node's light is the mean of: a triangle of a leaf or a child node.
struct Part {
    /// Stored diffuse light and the samples behind it (the fewest of its cells).
    diffuse: Option<([f32; 3], u32)>,
    caustic: [f32; 3],
    area: f32,
}

fn pull_page(scene: &Scene, store: &RadianceStore, id: u32) {
    let Some(page) = scene.cache.get_resident(id) else {
        return;
    };
    let h = &scene.cache.archive.header;
    let cell_size = cell_size(h);
    let caustics = store.photons() > 0;
    let node_part = |key: u64, area: f32| {
        let e = store.get(node_key(key));
        Part {
            diffuse: e.and_then(|e| e.value()),
            caustic: e.map_or([0.0; 3], |e| e.caustic),
            area,
        }
    };
    for (i, n) in page.bvh.iter().enumerate().rev() {
        let a = n.a & !KIND_MASK;
        let here = page.first_node + i as u64;
        let parts: Vec<Part> = match n.a & KIND_MASK {
            LEAF => (0..n.b)
                .filter_map(|k| {
                    let t = page.tris.get((a + k) as usize)?;
                    let cells: Vec<_> = cells(t, cell_size)
                        .map(|(cell, area)| (store.get(tri_key(here, k, cell)), area))
                        .collect();
                    // Diffuse: the lit cells' means weighted by their samples. Caustic: all
                    // cells by area, an unlit cell counting as dark.
                    let lit: Vec<_> = cells
                        .iter()
                        .filter_map(|(e, _)| e.and_then(|e| e.value()))
                        .collect();
                    let diffuse = weighted_mean(lit.iter().map(|&(v, c)| (v, c as f32)))
                        .zip(lit.iter().map(|&(_, c)| c).min());
                    let caustic = weighted_mean(
                        cells
                            .iter()
                            .map(|(e, area)| (e.map_or([0.0; 3], |e| e.caustic), *area)),
                    )
                    .unwrap_or_default();
                    Some(Part {
                        diffuse,
                        caustic,
                        area: tri_area(t),
                    })
                })
                .collect(),
            INNER => [a, n.b]
                .map(|c| node_part(page.first_node + c as u64, page.nodes[c as usize].area))
                .into(),
            CHILD_PAGE => {
                let Some(child) = scene.cache.get_resident(a) else {
                    continue;
                };
                let (Some(l), Some(r)) = (child.nodes.first(), child.nodes.get(1)) else {
                    continue;
                };
                vec![
                    node_part(child.first_node, l.area),
                    node_part(child.first_node + 1, r.area),
                ]
            }
            _ => continue,
        };
        // A leaf takes the mean over its lit triangles; an inner node needs both children.
        let lit = parts.iter().filter(|p| p.diffuse.is_some());
        let complete = n.a & KIND_MASK == LEAF || parts.iter().all(|p| p.diffuse.is_some());
        if let (true, Some(samples)) = (
            complete,
            lit.clone().filter_map(|p| p.diffuse.map(|d| d.1)).min(),
        ) {
            let mean = weighted_mean(lit.filter_map(|p| p.diffuse.map(|d| (d.0, p.area))));
            if let Some(v) = mean {
                store.set_pulled(node_key(here), v, samples);
            }
        }
        if caustics {
            let c = weighted_mean(parts.iter().map(|p| (p.caustic, p.area))).unwrap_or_default();
            if c.iter().any(|&v| v > 0.0) {
                store.set_caustic(node_key(here), c);
            }
        }
    }
}
