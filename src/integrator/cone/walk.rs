//! One cone path: a loop over one path state. Each hit is an event — stop, a bounce, or a
//! diffuse hit whose light is stored — and every bounce goes through `Path::bounce`, which
//! applies `--max-depth`'s count, Russian roulette and the throughput the same way for
//! triangles, clusters and diffuse surfaces.

use super::node_brdf::{hit_emission, phong_lobe, reflect_lut, theta_norm};
use super::optics::{bent_tan, jitter};
use super::{ConeIntegrator, STORE_TAN};
use crate::integrator::direct::{emission_weight, escaped_light};
use crate::integrator::surface::{passes_through, MAX_PASSES};
use crate::integrator::{
    bsdf_term, on_side, sample_light, Counters, Receiver, Scene, ShadingPoint,
};
use crate::light_store::RadianceStore;
use crate::material::{cosine_hemisphere, Frame};
use crate::sampler::PixelSampler;
use crate::trace::{gamma, offset_origin, Cone, ConeHit, Hit, Ray, Tracer, NO_INSTANCE};
use canopy_format::codec::{snorm16_decode, unorm8_decode};
use canopy_format::{Node as NodeRecord, NodeFlags};
use glam::Vec3A as V;

/// What a diffuse hit does with the store once its sample is known.
#[derive(Clone, Copy)]
enum Keep {
    /// Its own sample, not stored (also a converged node, whose mean is the sample).
    Fresh,
    /// Its own sample, also added to the store.
    Store(u64),
    /// Adds its sample and answers with the store's mean.
    Answer(u64),
}

/// What one bounce needs to finish once the rest of the path is known.
struct Pending {
    keep: Keep,
    /// Where that node is: its page, as placed by an instance.
    place: Place,
    /// Radiance gathered here independent of the continuation: emission and light samples.
    direct: V,
    emission: V,
    albedo: V,
    /// Caustic light arriving here (E/π) from the light pass.
    caustic: V,
    /// Continuation weight (BSDF value · cos / pdf, roulette included).
    weight: V,
    diffuse: bool,
    /// Mean of the RGB throughput reaching this bounce from the eye: the weight of the
    /// sample it stores, so a cell's mean is the image's average of the cell (a cell's
    /// light varies across it, and the paths reaching each point carry different
    /// throughput).
    beta: f32,
}

impl Pending {
    /// What this bounce multiplies the path's throughput by.
    fn throughput(&self) -> V {
        self.weight * if self.diffuse { self.albedo } else { V::ONE }
    }
}

/// A node (global number), its page, the instance placing it (`NO_INSTANCE`: none) and
/// that instance's leaf: what a change to its stored light marks for the pull.
#[derive(Clone, Copy)]
struct Place {
    node: u64,
    page: u32,
    instance: u32,
    via: u64,
}

impl Place {
    fn mark(self, store: &RadianceStore) {
        store.mark_dirty_in(self.instance, self.page, self.via, self.node);
    }
}

/// A hit as shading sees it, with the bounce's sample numbers: sets 2k+1 (light choice,
/// light point, lobe) and 2k+2 (direction, roulette, jitter).
struct Here {
    p: V,
    /// The error bound of `p`.
    err: V,
    /// Unit geometric normal; zero on a node.
    ng: V,
    /// Distance from the ray's origin.
    t: f32,
    /// Toward the viewer.
    wo: V,
    front: bool,
    pick: f32,
    light: [f32; 2],
    lobe: f32,
    dir: [f32; 2],
    rr: f32,
    jitter: f32,
}

impl Here {
    /// None for a degenerate triangle.
    fn new(hit: &ConeHit, ray: &Ray, s: &PixelSampler, depth: u32) -> Option<Here> {
        let (p, err, ng, t) = match hit {
            ConeHit::Tri(h) => {
                let area = 0.5 * h.ng().length();
                if area.is_nan() || area <= 0.0 {
                    return None;
                }
                let (p, err) = h.point();
                (p, err, h.ng().normalize_or_zero(), h.t)
            }
            ConeHit::Node { t, .. } => {
                let p = ray.o + ray.d * *t;
                (p, p.abs() * gamma(7) + V::splat(1e-6), V::ZERO, *t)
            }
        };
        let [pick, l0, l1, lobe] = s.get4(2 * depth + 1);
        let [d0, d1, rr, jitter] = s.get4(2 * depth + 2);
        Some(Here {
            p,
            err,
            ng,
            t,
            wo: -ray.d,
            front: ng.dot(-ray.d) > 0.0,
            pick,
            light: [l0, l1],
            lobe,
            dir: [d0, d1],
            rr,
            jitter,
        })
    }
}

/// How the path leaves a bounce.
struct Bounce {
    ray: Ray,
    cone: Cone,
    /// A smooth (delta) bounce: emission hit next takes full weight.
    delta: bool,
    pdf: f32,
    /// A diffuse bounce starts a new chain for caustic masking; `smooth` continues one.
    diffuse: bool,
    smooth: bool,
    /// The point and normal the bounce's light sample was chosen from, for MIS.
    from: Option<(V, V)>,
}

/// A Lambertian triangle or a cluster's diffuse part: its light is stored.
struct Diffuse {
    frame: Frame,
    albedo: V,
    key: u64,
    /// The cluster's normal (its length is the cluster's flatness), None on a triangle.
    cluster_n: Option<V>,
    /// Light nearer than this counts as if at this distance.
    min_dist: f32,
    /// Side of the light cell (0 for a node, which the cone resolved by stopping there).
    side: f32,
}

enum Event {
    Stop,
    Bounce(Bounce),
    Diffuse(Diffuse),
}

/// The state carried from bounce to bounce.
struct Path {
    stack: Vec<Pending>,
    ray: Ray,
    cone: Cone,
    /// Light samples test visibility with the primary cone's opening, from the surface.
    shadow_cone: Cone,
    depth: u32,
    prev_delta: bool,
    prev_pdf: f32,
    /// The last glossy point and its normal, where its light sample was chosen.
    prev: (V, V),
    /// With the light pass on, emission reached from a Lambertian surface through smooth
    /// bounces only (D S* S L) is the light pass's caustic and masked here (004 §4.7).
    mask_caustics: bool,
    smooth_chain: bool,
    /// Diffuse bounces taken so far.
    diffuse_bounces: u32,
    /// The product of the stacked bounces' throughput.
    beta: V,
    /// The environment's light where the path left the scene.
    escaped: V,
}

impl Path {
    /// Emission the hit sends to the viewer, weighted as the estimator needs it.
    fn emission(&self, scene: &Scene, hit: &ConeHit, at: &Here) -> V {
        let le = hit_emission(scene, hit, &self.ray, &self.cone);
        if le == V::ZERO {
            return le;
        }
        if self.prev_delta {
            return if self.mask_caustics && self.smooth_chain {
                V::ZERO
            } else {
                le
            };
        }
        match hit {
            // After a diffuse or glossy bounce: MIS against the light sample, as the path
            // tracer does. Deviation: eq. 4.27 masks emission after a diffuse bounce and
            // gives the light sample full weight, whose 1/d² near a large emitter (a wall
            // meeting a lamp) left fireflies in the stored light and a stored mean that
            // is typically low (−0.8% on a lamp-ceilinged box). A node stands in for its
            // emitters only at the LOD `--cone-scale` asks for, and stays masked.
            ConeHit::Tri(h) => {
                let area = 0.5 * h.ng().length();
                let (from, pdf) = (self.prev, self.prev_pdf);
                le * emission_weight(scene, h, (at.ng, area), at.wo, from, pdf, h.t * h.t)
            }
            _ => V::ZERO,
        }
    }

    /// The environment's light the path meets where it leaves the scene, weighted as
    /// emission met by a BSDF ray is (the point value: not filtered over the cone).
    fn escape(&mut self, scene: &Scene) {
        self.escaped = match self.prev_delta {
            true if self.mask_caustics && self.smooth_chain => V::ZERO,
            true => escaped_light(scene, self.ray.d, None),
            false => escaped_light(scene, self.ray.d, Some((self.prev, self.prev_pdf))),
        };
    }

    /// Takes a bounce: one more segment, the new ray and cone, then Russian roulette on
    /// the throughput after the second bounce (a survivor's weight divided by its survival
    /// probability). False when the path ends.
    fn bounce(&mut self, b: Bounce, u_rr: f32) -> bool {
        self.prev_delta = b.delta;
        self.prev_pdf = b.pdf;
        if let Some(from) = b.from {
            self.prev = from;
        }
        self.smooth_chain = b.diffuse || (self.smooth_chain && b.smooth);
        self.diffuse_bounces += b.diffuse as u32;
        self.ray = b.ray;
        self.cone = b.cone;
        self.depth += 1;
        let Some(last) = self.stack.last_mut() else {
            return true;
        };
        if self.depth > 1 {
            let q = (self.beta * last.throughput()).max_element().min(1.0);
            if q <= 0.0 || u_rr >= q {
                return false;
            }
            last.weight /= q;
        }
        self.beta *= last.throughput();
        true
    }

    /// The emission seen at the primary hit goes back apart (the caller may average it
    /// over more of the pixel); the rest unwinds: each bounce's value is its emission plus
    /// what it scatters of the next.
    fn unwind(mut self, store: &RadianceStore) -> (V, V) {
        let seen = self
            .stack
            .first_mut()
            .map_or(V::ZERO, |b| std::mem::take(&mut b.emission));
        let mut tail = self.escaped;
        while let Some(b) = self.stack.pop() {
            let incoming = b.direct + b.weight * tail;
            tail = if b.diffuse {
                let scattered = match b.keep {
                    Keep::Fresh => incoming,
                    Keep::Store(key) => {
                        store.add(key, incoming.to_array(), b.beta);
                        b.place.mark(store);
                        incoming
                    }
                    Keep::Answer(key) => {
                        b.place.mark(store);
                        V::from(store.add(key, incoming.to_array(), b.beta).0)
                    }
                };
                b.emission + b.albedo * (scattered + b.caustic)
            } else {
                b.emission + incoming
            };
        }
        (tail, seen)
    }
}

/// The chance that a hit on a cell holding `n` samples adds one: 1 while n ≤ A (`reuse`),
/// then A/n, never below 1/A: a stored sample serves n/A reads on average, never more than
/// A, where a frozen cell's first samples serve every later read (one rare bright sample
/// among them moved a whole image's mean by 2%, docs/cone-room.md). Which hits add is
/// chosen before their sample is known, so the cell's mean stays that of the hits it
/// stands for.
fn feed_chance(n: u32, reuse: u32) -> f32 {
    let a = reuse.max(1) as f32;
    (a / n as f32).clamp(1.0 / a, 1.0)
}

/// A fresh cone of tan α = `spread` from the surface (r0 = 0: a frustum whose first disc is
/// the incoming footprint would start rays beside walls and leak light).
fn widened(cone: &Cone) -> Cone {
    Cone {
        r0: 0.0,
        tan_a: cone.spread,
        ..*cone
    }
}

/// Whether a cone's triangle hit falls in an alpha hole (mask) or, under blend, is passed
/// with probability 1 − alpha, as the path tracer does. Nodes are opaque.
fn through_hole(scene: &Scene, hit: &ConeHit, at: &Here, passes: u32) -> bool {
    let ConeHit::Tri(h) = hit else {
        return false;
    };
    passes_through(scene.opacity_at(h), at.dir[0], passes)
}

impl ConeIntegrator {
    /// Radiance along a primary cone, as (everything but the emission seen at the primary
    /// hit, that emission).
    pub(super) fn radiance(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        ray: Ray,
        s: &PixelSampler,
        c: &mut Counters,
    ) -> (V, V) {
        let mut path = Path {
            stack: Vec::new(),
            ray,
            cone: self.primary,
            shadow_cone: Cone {
                r0: 0.0,
                ..self.primary
            },
            depth: 0,
            prev_delta: true,
            prev_pdf: 0.0,
            prev: (V::ZERO, V::ZERO),
            mask_caustics: self.store.photons() > 0,
            smooth_chain: false,
            diffuse_bounces: 0,
            beta: V::ONE,
            escaped: V::ZERO,
        };
        let alpha = scene.textures.has_alpha();
        let mut passes = 0;
        loop {
            let Some(hit) = tr.cone_hit(&path.ray, &path.cone) else {
                path.escape(scene);
                break;
            };
            let Some(at) = Here::new(&hit, &path.ray, s, path.depth) else {
                break;
            };
            if alpha && passes < MAX_PASSES && through_hole(scene, &hit, &at, passes) {
                // A cut-out: the cone goes on unchanged (its width kept) past the surface.
                passes += 1;
                path.cone.r0 = path.cone.radius(at.t);
                path.ray.o = offset_origin(at.p, at.err, at.ng, path.ray.d);
                continue;
            }
            let place = match &hit {
                ConeHit::Tri(h) => {
                    scene.touch(h);
                    Place {
                        node: h.leaf,
                        page: h.page,
                        instance: h.instance,
                        via: h.instance_leaf,
                    }
                }
                ConeHit::Node { node, page, .. } => {
                    scene.touched.insert(*node);
                    Place {
                        node: *node,
                        page: *page,
                        instance: NO_INSTANCE,
                        via: 0,
                    }
                }
            };
            let mut pend = Pending {
                keep: Keep::Fresh,
                place,
                direct: V::ZERO,
                emission: path.emission(scene, &hit, &at),
                albedo: V::ZERO,
                caustic: V::ZERO,
                weight: V::ZERO,
                diffuse: false,
                beta: path.beta.element_sum() / 3.0,
            };
            // `--max-depth` counts segments as the path tracer does: a hit on the last one
            // keeps the emission it sees and scatters nothing.
            let event = if scene.last_segment(path.depth) {
                Event::Stop
            } else {
                match &hit {
                    ConeHit::Tri(h) => self.triangle(scene, tr, &path, h, &at, &mut pend),
                    ConeHit::Node { node, record, .. } => {
                        self.cluster(&path, *node, record, &at, &mut pend)
                    }
                }
            };
            let event = match event {
                Event::Diffuse(d) => self.diffuse(scene, tr, &path, d, &at, &mut pend),
                e => e,
            };
            path.stack.push(pend);
            let Event::Bounce(b) = event else {
                break;
            };
            if !path.bounce(b, at.rr) {
                break;
            }
        }
        c.paths += 1;
        let (rest, seen) = path.unwind(&self.store);
        (c.finite(rest), c.finite(seen))
    }

    /// A leaf triangle: Lambertian ones store light; others take one exact path-tracing
    /// step, nothing stored.
    fn triangle(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        path: &Path,
        h: &Hit,
        at: &Here,
        pend: &mut Pending,
    ) -> Event {
        let shaded = scene.material_at_cone(h, &path.ray, &path.cone);
        let sp = ShadingPoint::new(h, at.ng, at.wo, &shaded);
        if sp.absorbs {
            return Event::Stop;
        }
        // Inside a mesh with a volume, what this hit sends on is attenuated on the way.
        let through = sp.through(h.t * path.ray.d.length());
        let ShadingPoint {
            ng,
            n,
            frame,
            bsdf,
            wo_l,
            ..
        } = sp;
        let wo = at.wo;
        // Stored light is kept per geometric normal: a normal-mapped surface takes the
        // exact step below instead.
        if shaded.m.is_pure_diffuse() && shaded.normal.is_none() {
            let cell = self.keys.cell_of(&h.tri, h.b);
            return Event::Diffuse(Diffuse {
                frame: Frame::new(n),
                albedo: bsdf.diffuse,
                key: super::tri_key(self.keys, h, !at.front, cell),
                cluster_n: None,
                min_dist: 0.0,
                side: self.keys.side(&h.tri),
            });
        }
        if !bsdf.has_smooth_only() {
            pend.direct += through
                * sample_light(
                    scene,
                    tr,
                    &Receiver::surface(at.p, at.err, ng),
                    &path.shadow_cone,
                    [at.pick, at.light[0], at.light[1]],
                    bsdf_term(frame, n, bsdf, wo_l),
                );
        }
        let Some(bs) = bsdf.sample(wo_l, at.lobe, at.dir) else {
            return Event::Stop;
        };
        let wi = frame.to_world(bs.wi).normalize();
        if !on_side(&frame, n, wi) {
            return Event::Stop;
        }
        pend.weight = bs.weight * through;
        // A smooth surface bends the cone by its curvature (eq. 4.21–4.22) and the
        // direction is resampled inside the incoming opening (eq. 4.14–4.16, Fig. 7). A
        // glossy bounce starts a fresh diffuse-width cone.
        let o = offset_origin(at.p, at.err, ng, wi);
        let cone = &path.cone;
        let (o, d, cone) = if bs.delta && cone.scale > 0.0 {
            let (o, d) = jitter(o, wi, cone, [at.jitter, at.rr]);
            let kappa = if at.front { h.curvature } else { -h.curvature };
            let tan_a = bent_tan(cone, h.t, kappa, wo.dot(n), wi.dot(n), bsdf.eta);
            let bent = Cone {
                r0: 0.0,
                tan_a,
                ..*cone
            };
            (o, d, bent)
        } else {
            (o, wi, widened(cone))
        };
        Event::Bounce(Bounce {
            ray: Ray {
                o,
                d,
                t_max: f32::INFINITY,
            },
            cone,
            delta: bs.delta,
            pdf: bs.pdf,
            diffuse: false,
            smooth: bs.delta,
            from: Some((at.p, ng)),
        })
    }

    /// A node hit as a whole, shaded with the cluster BRDF (§4.3): reflect with
    /// p_reflect(Θ), refract with refractiveness·(1 − p_reflect) (eq. 4.1), else diffuse
    /// (eq. 4.2) with the area-weighted albedo.
    fn cluster(
        &self,
        path: &Path,
        node: u64,
        raw: &NodeRecord,
        at: &Here,
        pend: &mut Pending,
    ) -> Event {
        let wo = at.wo;
        let nn = V::from(raw.normal.map(snorm16_decode));
        let len = nn.length();
        let n = if len > 1e-6 { nn / len } else { wo };
        let n = if n.dot(wo) < 0.0 { -n } else { n };
        let mut rho = V::from(raw.diffuse.map(unorm8_decode));
        if raw.flags & (NodeFlags::GLOSSY | NodeFlags::TRANSMISSIVE) != 0 {
            let nl = if nn.dot(wo) < 0.0 { -nn } else { nn };
            let theta = ((1.0 - len) / 4.0 + nl.dot(wo)).clamp(0.0, 1.0);
            let p_r = reflect_lut(raw.reflectiveness, theta);
            let p_t = unorm8_decode(raw.refractiveness) * (1.0 - p_r);
            if at.lobe < p_r + p_t {
                let (wi, weight, smooth) = if at.lobe < p_r {
                    let (wi, s) = phong_lobe(n, len, wo, raw.roughness, at.dir);
                    let tint = V::from(raw.specular_tint.map(unorm8_decode));
                    (wi, tint, s >= 1e3)
                } else {
                    // Through a transmissive cluster or its alpha holes: straight on,
                    // tinted by the mean tint of what passes (its lensing is below the
                    // level of detail the cone asked for).
                    let passing = unorm8_decode(raw.refractiveness);
                    let tint = V::from(raw.translucency.map(unorm8_decode)) / passing.max(1e-3);
                    (-wo, tint, true)
                };
                // A near-mirror or glass cluster keeps the cone and stands for a smooth
                // bounce (its caustics are the light pass's); a glossy one widens the cone.
                let tan_a = if smooth {
                    path.cone.tan_a
                } else {
                    path.cone.spread
                };
                pend.weight = weight;
                let side = if wi.dot(n) > 0.0 { n } else { wi };
                return Event::Bounce(Bounce {
                    ray: Ray {
                        o: offset_origin(at.p, at.err, side, wi),
                        d: wi,
                        t_max: f32::INFINITY,
                    },
                    cone: Cone {
                        r0: 0.0,
                        tan_a,
                        ..path.cone
                    },
                    delta: true,
                    pdf: 0.0,
                    diffuse: false,
                    smooth,
                    from: None,
                });
            }
            let p_d = 1.0 - p_r - p_t;
            rho = if p_d > 1e-3 { rho / p_d } else { V::ZERO };
        }
        // A cluster is shaded at its box entry point, which can lie next to a lamp inside
        // the same box; light closer than the cluster's radius is taken at that radius, as
        // a disc of that size would receive it (bounded, like clamping virtual point lights).
        Event::Diffuse(Diffuse {
            frame: Frame::new(n),
            albedo: rho,
            key: self.keys.node(node),
            cluster_n: Some(if nn.dot(n) < 0.0 { -nn } else { nn }),
            min_dist: raw.radius,
            side: 0.0,
        })
    }

    /// A diffuse hit: adds a fresh sample of its incident light to its store entry (one
    /// light sample, one cosine-sampled bounce) or, converged, answers from the store.
    fn diffuse(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        path: &Path,
        d: Diffuse,
        at: &Here,
        pend: &mut Pending,
    ) -> Event {
        let store = &self.store;
        pend.albedo = d.albedo;
        pend.diffuse = true;
        // A path's first diffuse hit (seen from the eye, directly or through smooth and
        // glossy bounces) takes its own sample and feeds the store; after a diffuse bounce
        // a hit answers from the store (004 §4.6). It answers only where a diffuse
        // bounce's footprint at its distance covers the cell (a node is covered: the cone
        // stopped there), so a cell never stands in for light that varies inside it at the
        // scale the bounce sees (a room's corners); only those hits add to it.
        let resolved = d.side <= 2.0 * STORE_TAN * at.t;
        // Stored light stands for every bounce after its hit: under a finite
        // `--max-depth` a later hit would read more bounces than its path has left
        // (bunny_box at depth 3: +6.0 / +2.9 / +1.6%), so the store is neither fed nor
        // read there and each hit takes its own sample.
        pend.keep = match path.diffuse_bounces {
            _ if scene.max_depth.is_some() => Keep::Fresh,
            0 => Keep::Store(d.key),
            _ if resolved => Keep::Answer(d.key),
            _ => Keep::Fresh,
        };
        let entry = match pend.keep {
            Keep::Answer(_) => store.read(d.key),
            _ => store.get(d.key),
        };
        // Reads past the reuse bound stop at the cell's mean; first hits past it keep their
        // own sample without adding it, so a cell's samples keep the mix of first hits and
        // reads that its mean stands for.
        let n = entry.map_or(0, |e| e.n);
        let thinned = at.jitter >= feed_chance(n, self.settings.cone_reuse);
        if thinned && matches!(pend.keep, Keep::Store(_)) {
            pend.keep = Keep::Fresh;
        }
        if path.mask_caustics {
            pend.caustic = entry
                .and_then(|e| store.caustic(&e))
                .map_or(V::ZERO, V::from);
        }
        // A converged node (§4.6.1) or a thinned read answers from its store without
        // recursing.
        let stops = |e: &crate::light_store::Entry| e.n >= store.limit || thinned;
        if let (Keep::Answer(_), Some(e)) = (pend.keep, entry.filter(stops)) {
            let (v, _) = e.value().unwrap_or(([0.0; 3], 0));
            pend.keep = Keep::Fresh;
            pend.direct = V::from(v);
            return Event::Stop;
        }
        // Light sample: cos θ, or Θ = (1−|n|)/4 + ⟨n, ω⟩ for a cluster (eq. 4.4), weighted
        // by MIS against the bounce's cosine pdf; `Path::emission` weights the other side.
        // A bounce that stops at an emitting node (only at `--cone-scale` > 0) adds no
        // emission, so that node's share of the MIS is lost with the level of detail.
        let theta = |wi: V| match d.cluster_n {
            Some(nn) => {
                let len = nn.length();
                ((1.0 - len) / 4.0 + nn.dot(wi)).max(0.0) / theta_norm(len)
            }
            None => d.frame.n.dot(wi).max(0.0),
        };
        let shade_n = if at.ng == V::ZERO { d.frame.n } else { at.ng };
        let receiver = Receiver {
            p: at.p,
            err: at.err,
            n: shade_n,
            facing: if d.cluster_n.is_some() {
                V::ZERO
            } else {
                shade_n
            },
            min_dist: d.min_dist,
        };
        let u = [at.pick, at.light[0], at.light[1]];
        let cos_pdf = |wi: V| d.frame.n.dot(wi).max(0.0) * std::f32::consts::FRAC_1_PI;
        pend.direct = sample_light(scene, tr, &receiver, &path.shadow_cone, u, |wi| {
            (
                V::splat(theta(wi) * std::f32::consts::FRAC_1_PI),
                cos_pdf(wi),
            )
        });
        // Cosine-sampled bounce; weight 1 (the albedo is applied when unwinding). Its
        // direction is already random, so it is not jittered again (eq. 4.20).
        let wi = d.frame.to_world(cosine_hemisphere(at.dir)).normalize();
        pend.weight = V::ONE;
        let from = (receiver.p, receiver.facing);
        Event::Bounce(Bounce {
            ray: Ray {
                o: offset_origin(at.p, at.err, shade_n, wi),
                d: wi,
                t_max: f32::INFINITY,
            },
            cone: widened(&path.cone),
            delta: false,
            pdf: cos_pdf(wi),
            diffuse: true,
            smooth: true,
            from: Some(from),
        })
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
    match &hit {
        ConeHit::Tri(h) => scene.touch(h),
        ConeHit::Node { node, .. } => scene.touched.insert(*node),
    }
    c.finite(hit_emission(scene, &hit, ray, cone))
}
