//! `--integrator pbgi`: point-based global illumination over the archive's hierarchy
//! (003 ch. 2; Christensen 2008 as cited there).
//!
//! The bake (`bake`) stores in every node the direct light it reflects diffusely. At the
//! first non-specular hit x the renderer adds the emission seen, direct light with the path
//! tracer's light sample, and one bounce of indirect light gathered from the hierarchy:
//! - the cut: from the root, a node is splatted whole when x lies outside its bounding
//!   sphere and the sphere's solid angle π r²/d² is at most `--pbgi-angle` times the
//!   smallest micro-buffer texel's; otherwise its children are visited. Nodes wholly below
//!   x's tangent plane are skipped;
//! - a splatted node covers its projected area toward x over d² and sends the light it
//!   reflects that way (`bake::Directional`, read from the page's baked block); seen from behind it is a dark occluder;
//! - leaves too close for their solid angle are resolved by exact rays: one ray, jittered
//!   inside the texel, through every texel the leaf's bounding sphere may cover; the hit
//!   sends the direct light it reflects toward x (its BSDF, one light sample), opaque;
//! - `microbuffer` composites and convolves with x's BSDF (003 eq. 2.1).
//!
//! Smooth mirrors and glass are followed exactly (one sampled bounce each, up to
//! `SMOOTH_DEPTH`), so a perfectly specular surface degrades to the exact estimator
//! (000 §A.8). Only one indirect bounce is gathered: compare with `--max-depth 3` of the
//! path tracer (camera → x → node → light). A smooth lobe layered over a diffuse one is not
//! sampled (its delta part is lost).

pub mod bake;
pub mod cluster;
pub mod microbuffer;

use super::{bsdf_term, sample_light, Counters, Integrator, PixelSample, Receiver, Scene, Stats};
use crate::material::{Bsdf, Frame};
use crate::paging::{NodeRef, Page, TNode};
use crate::trace::{offset_origin, Cone, Hit, Ray, Tracer};
use crate::wavelet::cube;
use anyhow::Result;
use bake::{Directional, Hash};
use glam::{Vec3, Vec3A as V};
use microbuffer::{MicroBuffer, Texels};
use std::cell::RefCell;
use std::f32::consts::PI;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::time::Instant;

/// Smooth bounces followed before giving up on a path.
const SMOOTH_DEPTH: u32 = 8;

/// A node is near (its children are visited) while x is within this many bounding radii.
const NEAR: f32 = 1.5;

/// PBGI's parameters (its command-line flags, refused under another integrator).
#[derive(Clone, Debug, clap::Args)]
#[command(next_help_heading = "Point-based GI (--integrator pbgi)")]
pub struct PbgiSettings {
    /// The cut's threshold: a node is splatted whole when its bounding sphere subtends at
    /// most this many of the micro-buffer's smallest texels. Smaller is more exact and
    /// slower; at 0 the cut reaches every leaf, and leaves wider than a texel (or near
    /// the receiver) are resolved by exact rays.
    #[arg(long = "pbgi-angle", default_value_t = 1.0, value_parser = crate::units::parse_non_negative)]
    pub angle: f32,
    /// Micro-buffer texels per cube-face side (even): the hemicube has 3·n² texels.
    #[arg(long = "pbgi-resolution", default_value_t = 8, value_parser = parse_resolution)]
    pub resolution: usize,
    /// Light samples per triangle in the bake.
    #[arg(long = "bake-samples", default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=65536))]
    pub bake_samples: u32,
    /// FPBGI (003 ch. 3): receivers of each 16×16 tile grouped into at most this many
    /// clusters (k-means on position and normal), each sharing one cut and its far splats;
    /// 0 gathers every receiver alone (plain PBGI). The thesis's 100 per 32×32 tile is 25
    /// here.
    #[arg(long = "receiver-clusters", default_value_t = 0)]
    pub clusters: usize,
    /// FPBGI's near/far test: a node is far for a whole cluster when the cluster's radius
    /// is at most this fraction of the distance to the node (r/d ≤ ε; the thesis prints
    /// the inverse, NOTES-002-003 B.2). Smaller shares less and errs less.
    #[arg(long = "cluster-far", default_value_t = 0.01, requires = "clusters", value_parser = crate::units::parse_non_negative)]
    pub far: f32,
    /// Baked light from `canopy bake` (default: bake before the first pass, counted in the
    /// render time, into an unnamed scratch file).
    #[arg(long, value_name = "FILE", conflicts_with = "bake_samples")]
    pub radiance: Option<PathBuf>,
}

fn parse_resolution(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(n) if (2..=64).contains(&n) && n.is_multiple_of(2) => Ok(n),
        _ => Err(format!("{s:?}: an even number from 2 to 64")),
    }
}

impl Default for PbgiSettings {
    /// The command line's defaults.
    fn default() -> PbgiSettings {
        super::flag_defaults()
    }
}

/// What PBGI adds to the render's statistics.
#[derive(Clone, Debug, serde::Serialize)]
pub struct PbgiStats {
    pub pbgi_angle: f32,
    pub pbgi_resolution: usize,
    pub bake_seconds: f64,
    pub bake_samples: u64,
    /// Nodes splatted whole, and texels resolved by exact rays, over the render.
    pub splatted_nodes: u64,
    pub near_rays: u64,
    pub receiver_clusters: usize,
    pub clustered_receivers: u64,
}

pub struct PbgiIntegrator {
    settings: PbgiSettings,
    /// Light samples the bake took (0 when read from a file).
    bake_samples: u64,
    texels: Texels,
    seed: u32,
    bake_s: f64,
    splatted: AtomicU64,
    near_rays: AtomicU64,
    /// Receivers gathered through a cluster's field.
    clusters: AtomicU64,
}

/// Per-thread scratch reused across receivers.
#[derive(Default)]
struct Scratch {
    mb: MicroBuffer,
    near: Vec<bool>,
    stack: Vec<(u32, u32)>,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

impl PbgiIntegrator {
    pub fn new(settings: &PbgiSettings, seed: u32) -> PbgiIntegrator {
        PbgiIntegrator {
            settings: settings.clone(),
            texels: Texels::new(settings.resolution),
            bake_samples: 0,
            seed,
            bake_s: 0.0,
            splatted: AtomicU64::new(0),
            near_rays: AtomicU64::new(0),
            clusters: AtomicU64::new(0),
        }
    }

    /// Radiance along the camera ray up to the receiver x, the first non-specular hit:
    /// emission seen and direct light; and x with the path weight to it, when one bounce
    /// of indirect light is still to be gathered there.
    fn first_hit(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample) -> (V, Option<Pending>) {
        let (mut ray, mut beta, mut l) = (px.ray, V::ONE, V::ZERO);
        for depth in 0..SMOOTH_DEPTH {
            let Some(hit) = tr.closest_hit(&ray) else {
                break;
            };
            scene.touched.insert(hit.leaf);
            let Some(s) = Surface::at(scene, &hit, ray.d) else {
                break;
            };
            l += beta * s.emitted;
            if scene.last_segment(depth) || s.absorbs {
                break;
            }
            let [u_pick, ul0, ul1, u_lobe] = px.sampler.get4(2 * depth + 1);
            if s.bsdf.has_smooth_only() {
                let [ud0, ud1, ..] = px.sampler.get4(2 * depth + 2);
                let Some(bs) = s.bsdf.sample(s.wo_l, u_lobe, [ud0, ud1]) else {
                    break;
                };
                beta *= bs.weight;
                let wi = s.frame.to_world(bs.wi).normalize();
                ray = Ray {
                    o: offset_origin(s.p, s.err, s.ng, wi),
                    d: wi,
                    t_max: f32::INFINITY,
                };
                continue;
            }
            l += beta * s.direct(scene, tr, [u_pick, ul0, ul1]);
            if scene.last_segment(depth + 1) {
                break;
            }
            let key = ((px.at as u64) << 20 ^ px.index as u64) ^ (self.seed as u64) << 52;
            return (l, Some(Pending { s, beta, key }));
        }
        (l, None)
    }

    /// One bounce of indirect light at `s` from the cut, the near rays and the micro-buffer.
    /// With a cluster's `field`, its far splats are taken as they are and the cut starts
    /// from its near nodes instead of the root.
    fn gather(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        key: u64,
        field: Option<&Field>,
    ) -> V {
        SCRATCH.with_borrow_mut(|sc| {
            let texels = &self.texels;
            sc.mb.clear();
            sc.near.clear();
            sc.near.resize(texels.dir.len(), false);
            sc.stack.clear();
            match field {
                Some(f) => {
                    for far in &f.far {
                        self.splat(s, far, &mut sc.mb);
                    }
                    sc.stack.extend_from_slice(&f.near);
                }
                None => {
                    let root = tr.page_handle(scene.cache.root_page());
                    sc.stack
                        .extend((0..root.roots.min(root.bvh.len() as u32)).map(|r| (root.id, r)));
                }
            }
            self.cut(scene, tr, s, sc);
            let mut rng = Hash::new(key);
            let mut rays = 0;
            for &k in &texels.upper {
                if sc.near[k as usize] {
                    rays += 1;
                    self.near_ray(scene, tr, s, k as usize, &mut rng, &mut sc.mb);
                }
            }
            self.near_rays.fetch_add(rays, Relaxed);
            let incident = sc.mb.resolve(texels, |_| Vec3::ZERO);
            let f = MicroBuffer::convolve(texels, &incident, |w| {
                Vec3::from(s.bsdf.eval(s.wo_l, V::from(w)).0)
            });
            V::from(f)
        })
    }

    /// Walks the hierarchy from the nodes on `sc.stack`: far nodes are splatted, near
    /// leaves mark the texels their bounding sphere may cover.
    fn cut(&self, scene: &Scene, tr: &mut Tracer, s: &Surface, sc: &mut Scratch) {
        let Some(&(first, _)) = sc.stack.last() else {
            return;
        };
        let mut page = tr.page_handle(first);
        let mut splatted = 0;
        while let Some((pid, i)) = sc.stack.pop() {
            if page.id != pid {
                page = tr.page_handle(pid);
            }
            let Some(node) = page.bvh.get(i as usize) else {
                continue;
            };
            let (c, r) = node_sphere(node);
            let v = c - s.p;
            if v.dot(s.n) < -r {
                continue;
            }
            if let Some(far) = self.far(&page, i, c, r, s.p) {
                splatted += 1;
                scene.touched.insert(far.id);
                self.splat(s, &far, &mut sc.mb);
                continue;
            }
            match node.link() {
                NodeRef::Leaf { .. } => self.mark_near(s, v, v.length(), r, &mut sc.near),
                NodeRef::Inner(l, rr) => sc.stack.extend([(pid, l), (pid, rr)]),
                NodeRef::ChildPage(cp) => sc.stack.extend([(cp, 0), (cp, 1)]),
            }
        }
        self.splatted.fetch_add(splatted, Relaxed);
    }

    /// Node i of `page` (bounding sphere c, r) as one splat seen from p, when its sphere
    /// subtends at most `--pbgi-angle` smallest texels and p lies outside NEAR radii.
    fn far(&self, page: &Page, i: u32, c: V, r: f32, p: V) -> Option<Far> {
        let texels = &self.texels;
        let omega_max = self.settings.angle * texels.min_solid_angle;
        let node = page.bvh.get(i as usize)?;
        // A leaf within one texel is splatted even when the cut asks for more.
        let limit = if matches!(node.link(), NodeRef::Leaf { .. }) {
            omega_max.max(texels.min_solid_angle)
        } else {
            omega_max
        };
        let v = c - p;
        let d = v.length();
        if !(d > NEAR * r && PI * r * r <= limit * d * d) {
            return None;
        }
        let shown = page.baked.get(i as usize).copied().unwrap_or_default();
        // Seen from behind, a node still hides what lies beyond it.
        let (front, power) = shown.toward(-v / d);
        let back = shown.toward(v / d).0;
        let area = front.max(back);
        let sends = if area > 0.0 { power / area } else { V::ZERO };
        Some(Far {
            w: v / d,
            d,
            omega: area / (d * d),
            id: page.first_node + i as u64,
            sends: Vec3::from(sends),
        })
    }

    fn splat(&self, s: &Surface, f: &Far, mb: &mut MicroBuffer) {
        let dir = Vec3::from(s.frame.to_local(f.w));
        mb.splat(&self.texels, dir, f.d, f.omega, f.id, f.sends);
    }

    /// A cluster's shared part of the cut (003 §3), walked for its active receiver x_C:
    /// a node is far for the whole cluster when its radius R ≤ ε·d (d from x_C to the
    /// node's centre: sharing the splat errs by about R/d in direction); far nodes are
    /// splatted from x_C when small enough, else visited further; near nodes are left for
    /// each receiver to refine.
    /// A node is dropped only when it lies below every member's tangent plane, so a
    /// cluster of one makes exactly PBGI's cut.
    fn field(&self, scene: &Scene, tr: &mut Tracer, members: &[&Surface], xc: &Surface) -> Field {
        let radius = members
            .iter()
            .map(|m| (m.p - xc.p).length())
            .fold(0.0, f32::max);
        let mut field = Field::default();
        let mut stack: Vec<(u32, u32)> = Vec::new();
        let mut page = tr.page_handle(scene.cache.root_page());
        stack.extend((0..page.roots.min(page.bvh.len() as u32)).map(|r| (page.id, r)));
        while let Some((pid, i)) = stack.pop() {
            if page.id != pid {
                page = tr.page_handle(pid);
            }
            let Some(node) = page.bvh.get(i as usize) else {
                continue;
            };
            let (c, r) = node_sphere(node);
            if members.iter().all(|m| (c - m.p).dot(m.n) < -r) {
                continue;
            }
            if radius > self.settings.far * (c - xc.p).length() {
                field.near.push((pid, i));
                continue;
            }
            if let Some(far) = self.far(&page, i, c, r, xc.p) {
                scene.touched.insert(far.id);
                field.far.push(far);
                continue;
            }
            match node.link() {
                NodeRef::Leaf { .. } => field.near.push((pid, i)),
                NodeRef::Inner(l, rr) => stack.extend([(pid, l), (pid, rr)]),
                NodeRef::ChildPage(cp) => stack.extend([(cp, 0), (cp, 1)]),
            }
        }
        self.splatted.fetch_add(field.far.len() as u64, Relaxed);
        field
    }

    /// FPBGI over one batch: receivers clustered, one field per cluster, each receiver's
    /// gather starting from its cluster's field.
    fn sample_clustered(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        let firsts: Vec<(V, Option<Pending>)> =
            pxs.iter().map(|px| self.first_hit(scene, tr, px)).collect();
        let at: Vec<usize> = (0..firsts.len())
            .filter(|&i| firsts[i].1.is_some())
            .collect();
        let pending: Vec<&Pending> = at.iter().filter_map(|&i| firsts[i].1.as_ref()).collect();
        let p: Vec<V> = pending.iter().map(|q| q.s.p).collect();
        let n: Vec<V> = pending.iter().map(|q| q.s.n).collect();
        let mut out: Vec<V> = firsts.iter().map(|f| f.0).collect();
        for cl in cluster::kmeans(&p, &n, self.settings.clusters) {
            let members: Vec<&Surface> = cl.members.iter().map(|&m| &pending[m].s).collect();
            let field = self.field(scene, tr, &members, &pending[cl.active].s);
            for &m in &cl.members {
                let q = pending[m];
                out[at[m]] += q.beta * self.gather(scene, tr, &q.s, q.key, Some(&field));
            }
        }
        self.clusters.fetch_add(p.len() as u64, Relaxed);
        out.into_iter()
            .map(|l| {
                c.paths += 1;
                c.finite(l)
            })
            .collect()
    }

    /// Texels whose directions may meet a sphere of radius r at offset v (length d).
    fn mark_near(&self, s: &Surface, v: V, d: f32, r: f32, near: &mut [bool]) {
        let texels = &self.texels;
        if d <= r {
            texels.upper.iter().for_each(|&k| near[k as usize] = true);
            return;
        }
        let axis = Vec3::from(s.frame.to_local(v / d));
        let half = (r / d).asin();
        for &k in &texels.upper {
            let k = k as usize;
            // A texel's directions lie within about √(2Ω) of its centre direction.
            let spread = (2.0 * texels.solid_angle[k]).sqrt();
            if texels.dir[k].dot(axis).clamp(-1.0, 1.0).acos() <= half + spread {
                near[k] = true;
            }
        }
    }

    /// An exact ray through texel k, jittered inside it: its hit is splatted opaque with
    /// the direct light it reflects toward x.
    fn near_ray(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        s: &Surface,
        k: usize,
        rng: &mut Hash,
        mb: &mut MicroBuffer,
    ) {
        let n = self.texels.n;
        let corners = cube::texel_corners(k, n);
        let (a, b) = (rng.f32(), rng.f32());
        let local = corners[0] + (corners[1] - corners[0]) * a + (corners[3] - corners[0]) * b;
        let wi = s.frame.to_world(V::from(local.normalize())).normalize();
        if wi.dot(s.n) <= 0.0 {
            return;
        }
        let ray = Ray {
            o: offset_origin(s.p, s.err, s.ng, wi),
            d: wi,
            t_max: f32::INFINITY,
        };
        let Some(hit) = tr.closest_hit(&ray) else {
            return;
        };
        scene.touched.insert(hit.leaf);
        let sends = match Surface::at(scene, &hit, wi) {
            Some(h) if !h.absorbs && !h.bsdf.has_smooth_only() => {
                h.direct(scene, tr, [rng.f32(), rng.f32(), rng.f32()])
            }
            _ => V::ZERO,
        };
        mb.splat(
            &self.texels,
            self.texels.dir[k],
            hit.t,
            self.texels.solid_angle[k],
            u64::MAX - k as u64,
            Vec3::from(sends),
        );
    }
}

/// The bounding sphere of a node's decoded box.
fn node_sphere(node: &TNode) -> (V, f32) {
    let (lo, hi) = (V::from(node.lo), V::from(node.hi));
    ((lo + hi) * 0.5, (hi - lo).length() * 0.5)
}

/// A receiver whose indirect bounce is still to be gathered.
struct Pending {
    s: Surface,
    /// Path weight from the camera to x.
    beta: V,
    /// Seed of its exact rays.
    key: u64,
}

/// A node splatted whole, as seen from the point its cut was walked for.
#[derive(Clone, Copy, Debug)]
struct Far {
    /// Unit world direction to the node's centre, and the distance.
    w: V,
    d: f32,
    omega: f32,
    id: u64,
    sends: Vec3,
}

/// What a cluster's receivers share: far splats and the near nodes to refine.
#[derive(Default)]
struct Field {
    far: Vec<Far>,
    near: Vec<(u32, u32)>,
}

/// A hit prepared for shading.
struct Surface {
    p: V,
    err: V,
    /// Unit geometric normal (winding side) and the normal on the side of `wo`.
    ng: V,
    n: V,
    frame: Frame,
    bsdf: Bsdf,
    wo_l: V,
    emitted: V,
    absorbs: bool,
}

impl Surface {
    fn at(scene: &Scene, hit: &Hit, d: V) -> Option<Surface> {
        let m = &scene.materials[hit.tri.material as usize];
        let ng_raw = hit.ng();
        let len = ng_raw.length();
        if len.is_nan() || len <= 0.0 {
            return None;
        }
        let ng = ng_raw / len;
        let wo = -d.normalize();
        let front = ng.dot(wo) > 0.0;
        let (p, err) = hit.point();
        let n = if front { ng } else { -ng };
        let frame = Frame::new(n);
        Some(Surface {
            p,
            err,
            ng,
            n,
            frame,
            bsdf: m.bsdf(front),
            wo_l: frame.to_local(wo),
            emitted: m.emitted(front),
            absorbs: m.absorbs(front),
        })
    }

    /// Reflected direct light toward `wo`: one light sample at full weight (the cloud
    /// holds no emission, so nothing else samples the emitters).
    fn direct(&self, scene: &Scene, tr: &mut Tracer, u: [f32; 3]) -> V {
        let f = bsdf_term(self.frame, self.bsdf, self.wo_l);
        sample_light(
            scene,
            tr,
            &Receiver::surface(self.p, self.err, self.ng),
            &Cone::EXACT,
            u,
            |wi| (f(wi).0, 0.0),
        )
    }
}

impl Integrator for PbgiIntegrator {
    /// The first pass bakes (or reads `--radiance`) and attaches the light to the pages,
    /// so time budgets count the bake.
    fn begin_pass(&mut self, scene: &Scene, first: u32, _count: u32) -> Result<u64> {
        if first > 0 {
            return Ok(0);
        }
        let t = Instant::now();
        let archive = &scene.cache.archive;
        let file = match &self.settings.radiance {
            Some(path) => canopy_format::radiance::RadianceFile::open(path, archive)?,
            None => {
                let (file, samples) =
                    bake::bake_scratch(scene, self.settings.bake_samples, self.seed)?;
                self.bake_samples = samples;
                file
            }
        };
        scene.cache.attach_radiance(file)?;
        self.bake_s = t.elapsed().as_secs_f64();
        Ok(self.bake_samples)
    }

    fn sample(&self, scene: &Scene, tr: &mut Tracer, px: &PixelSample, c: &mut Counters) -> V {
        let (mut l, pending) = self.first_hit(scene, tr, px);
        if let Some(q) = pending {
            l += q.beta * self.gather(scene, tr, &q.s, q.key, None);
        }
        c.paths += 1;
        c.finite(l)
    }

    fn sample_tile(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        pxs: &[PixelSample],
        c: &mut Counters,
    ) -> Vec<V> {
        if self.settings.clusters == 0 {
            return pxs.iter().map(|px| self.sample(scene, tr, px, c)).collect();
        }
        self.sample_clustered(scene, tr, pxs, c)
    }

    fn passes(&self) -> Vec<String> {
        let s = &self.settings;
        vec![
            match &s.radiance {
                Some(path) => format!("bake: read from {} ({:.2} s)", path.display(), self.bake_s),
                None => format!(
                    "bake: direct light reflected by every node, {} light samples per triangle ({:.2} s)",
                    s.bake_samples, self.bake_s
                ),
            },
            format!(
                "pbgi: one indirect bounce from a cut at {} texels' solid angle into a {}² hemicube micro-buffer; near leaves by exact rays",
                s.angle, s.resolution
            ),
        ]
    }

    fn stats(&self) -> Stats {
        Stats::Pbgi(PbgiStats {
            pbgi_angle: self.settings.angle,
            pbgi_resolution: self.settings.resolution,
            bake_seconds: self.bake_s,
            bake_samples: self.bake_samples,
            splatted_nodes: self.splatted.load(Relaxed),
            near_rays: self.near_rays.load(Relaxed),
            receiver_clusters: self.settings.clusters,
            clustered_receivers: self.clusters.load(Relaxed),
        })
    }

    fn seconds(&self) -> Vec<(&'static str, f64)> {
        vec![("bake", self.bake_s)]
    }
}
