//! The bake: direct light reflected diffusely by every node, the point cloud PBGI gathers
//! (003 ch. 2, phase 1). Leaves estimate each triangle's reflected radiance ρ·E/π with
//! light samples (light tree and shadow rays) at random points of the triangle. Emission
//! is left out: the renderer adds direct light with the path tracer's estimator, so the
//! cloud carries only reflected light (with `walk`'s walks, of every bounce).
//!
//! A node keeps what it shows each way, not one mean: per cube axis a_k, its projected
//! area P_k = Σ A·max(0, n·a_k) and reflected power Q_k = Σ A·B·max(0, n·a_k) over its
//! triangles (both add up the tree, deepest pages first). Seen from ω they give the area
//! turned toward ω, exactly for boxes and axis-aligned walls (`Directional::toward`;
//! Christensen 2008 projects the same two quantities on spherical harmonics). A node that sent its
//! mean light every way, covering A·Θ/d² (004 eq. 4.4), overstated the bunny's indirect
//! light on bunny_box by half (README).

use super::glossy::{self, GlossyMaps, WaveletMode};
use super::patch;
pub use super::settings::BakeSettings;
use super::surface::Shading;
use super::walk::Walks;
use crate::integrator::{sample_light, Receiver, Scene};
use crate::material::luminance;
use crate::paging::{deepest_first, Corners, NodeRef, Page};
use crate::sampler::Hash;
use crate::trace::{gamma, Cone, Tracer};
use crate::wavelet::tree::SparseVec;
use anyhow::{bail, Result};
use canopy_format::bake::{
    BakeFile, BakeInfo, BakedBlock, BakedNode, RadianceWriter, MAX_PATCH_DEPTH,
};
use glam::Vec3A as V;
use rayon::prelude::*;
use std::f32::consts::FRAC_1_PI;
use std::path::Path;

/// What a node shows along each cube axis (+x, −x, +y, −y, +z, −z): the file's record.
pub trait Directional: Sized {
    fn add(&mut self, o: &Self);
    /// A surface of area `a`, unit normal `n`, reflecting radiance `b`.
    fn patch(a: f32, n: V, b: V) -> Self;
    /// Projected area and reflected power seen from direction `w` (unit, node → viewer).
    fn toward(&self, w: V) -> (f32, V);
}

impl Directional for BakedNode {
    fn add(&mut self, o: &BakedNode) {
        for k in 0..6 {
            self.area[k] += o.area[k];
            self.power[k] = (V::from(self.power[k]) + V::from(o.power[k])).into();
        }
    }

    fn patch(a: f32, n: V, b: V) -> BakedNode {
        let mut d = BakedNode::default();
        for (k, w) in axis_cosines(n).into_iter().enumerate() {
            d.area[k] = a * w;
            d.power[k] = (b * (a * w)).into();
        }
        d
    }

    /// Σ_k max(0, ω·a_k)·P_k: for a flat patch A·Σ over the axes where n and ω agree in
    /// sign of |n_k·ω_k|, so exactly A·n·ω when they agree on every axis (as on the walls
    /// of axis-aligned rooms), more when they do not; for a box exactly its silhouette;
    /// for a ball up to √3 its silhouette. Weights max(0, ω·a_k)², which sum to one (an
    /// "ambient cube"), are exact for a ball but give a wall seen at 60° half its area:
    /// the image means of two rooms fell 0.4% short with them. Power alike.
    fn toward(&self, w: V) -> (f32, V) {
        let mut area = 0.0;
        let mut power = V::ZERO;
        for (k, c) in axis_cosines(w).into_iter().enumerate() {
            area += c * self.area[k];
            power += V::from(self.power[k]) * c;
        }
        (area, power)
    }
}

/// max(0, ±v) per axis, in the order +x, −x, +y, −y, +z, −z.
fn axis_cosines(v: V) -> [f32; 6] {
    [
        v.x.max(0.0),
        (-v.x).max(0.0),
        v.y.max(0.0),
        (-v.y).max(0.0),
        v.z.max(0.0),
        (-v.z).max(0.0),
    ]
}

/// How to bake.
#[derive(Clone, Copy, Debug)]
pub struct BakeParams {
    /// Light samples per triangle, and per finest patch of a subdivided one.
    pub samples: u32,
    pub seed: u32,
    /// Finest patch side as a fraction of the scene's diagonal.
    pub patch_size: f32,
    /// None: all bounces.
    pub bounces: Option<u32>,
    pub wavelet: WaveletMode,
    pub wavelet_n: usize,
    pub wavelet_threshold: f32,
}

impl BakeParams {
    /// The file's record of a bake holding `bounces` bounces (None: all).
    fn info(&self, scene: &Scene, bounces: Option<u32>, maps: Option<&GlossyMaps>) -> BakeInfo {
        BakeInfo {
            environment: environment_id(scene),
            bounces: bounces.unwrap_or(canopy_format::bake::ALL_BOUNCES),
            samples_per_triangle: self.samples,
            seed: self.seed,
            patch_size: self.patch_size,
            wavelet_n: maps.map_or(0, |m| m.n as u32),
            wavelet_threshold: maps.map_or(0.0, |m| m.threshold),
        }
    }

    /// The glossy maps this scene gets under `--wavelet`.
    fn maps(&self, scene: &Scene) -> Result<Option<GlossyMaps>> {
        let glossy = glossy::any_glossy(scene);
        let archive = &scene.cache.archive;
        let on = match self.wavelet {
            WaveletMode::Off => false,
            // Glossy maps sum light up the tree, which holds none for instances.
            WaveletMode::Auto => glossy && !crate::integrator::has_instances(archive),
            WaveletMode::On if glossy => {
                crate::integrator::refuse_instances(archive, "--wavelet on")?;
                true
            }
            WaveletMode::On => bail!(
                "--wavelet on: no material of {} is a rough metal or rough dielectric, so there is no glossy light to store",
                archive.path().display()
            ),
        };
        Ok(on.then(|| GlossyMaps::new(self.wavelet_n, self.wavelet_threshold)))
    }
}

/// Bakes into a bake file at `path` (it appears only when complete); returns the
/// light samples taken and the bytes of the blocks decoded.
pub fn bake_file(
    scene: &Scene,
    p: &BakeParams,
    path: &Path,
    progress: &dyn Fn(u64),
) -> Result<(u64, u64)> {
    let archive = &scene.cache.archive;
    let maps = p.maps(scene)?;
    let mut out = RadianceWriter::create(path, archive, p.info(scene, p.bounces, maps.as_ref()))?;
    let samples = bake_bounces(scene, p, maps.as_ref(), &mut out, progress)?;
    let decoded = out.decoded_bytes();
    out.finish()?;
    Ok((samples, decoded))
}

/// The identity a bake file records for the scene's environment.
pub fn environment_id(scene: &Scene) -> u64 {
    scene.lights.env.as_ref().map_or(
        canopy_format::bake::NO_ENVIRONMENT,
        crate::light::Environment::id,
    )
}

/// A bake read with `--bake-in` was lit by the render's environment: the same map, strength,
/// rotation and sampling, or none for both (files that record none are taken as they are).
pub fn check_environment(file: &BakeFile, scene: &Scene, path: &Path) -> Result<()> {
    let (baked, now) = (file.header.environment, environment_id(scene));
    if baked == 0 || baked == now {
        return Ok(());
    }
    let render = scene
        .lights
        .env
        .as_ref()
        .map_or("none".to_string(), |e| e.name.clone());
    let baked = match baked {
        canopy_format::bake::NO_ENVIRONMENT => "with no environment light; this render has one",
        _ => "under another environment than this render's",
    };
    bail!(
        "{} was baked {baked} ({render}): bake again with the render's --env or --sky flags",
        path.display()
    )
}

/// Bakes into an unnamed scratch file (a render without `--bake-in`) and opens it.
pub fn bake_scratch(scene: &Scene, p: &BakeParams) -> Result<(BakeFile, u64)> {
    let archive = &scene.cache.archive;
    let maps = p.maps(scene)?;
    let mut out = RadianceWriter::temporary(archive, p.info(scene, p.bounces, maps.as_ref()))?;
    let samples = bake_bounces(scene, p, maps.as_ref(), &mut out, &|_| {})?;
    let file = out.finish()?;
    let r = BakeFile::from_file(file, Path::new("(temporary bake)"), archive)?;
    Ok((r, samples))
}

/// Bakes `p.bounces` bounces into `last`: the direct bake alone for one; otherwise the
/// direct bake is made first and attached to the pages, and the final one adds to every
/// patch what walks reading it find (`walk`). Returns the light samples taken.
fn bake_bounces(
    scene: &Scene,
    p: &BakeParams,
    maps: Option<&GlossyMaps>,
    last: &mut RadianceWriter,
    progress: &dyn Fn(u64),
) -> Result<u64> {
    if p.bounces == Some(1) {
        return bake(scene, p, maps, last, progress, None);
    }
    let archive = &scene.cache.archive;
    let mut out = RadianceWriter::temporary(archive, p.info(scene, Some(1), maps))?;
    let mut samples = bake(scene, p, maps, &mut out, progress, None)?;
    let file = out.finish()?;
    scene.cache.attach_bake(BakeFile::from_file(
        file,
        Path::new("(the direct bake)"),
        archive,
    )?)?;
    let walks = Walks {
        count: p.samples,
        vertices: p.bounces.map(|n| n - 1),
    };
    samples += bake(scene, p, maps, last, progress, Some(&walks))?;
    Ok(samples)
}

/// Pages baked at once: enough to keep every thread busy, few enough that memory holds
/// only their blocks and two records per page finished (its roots, which parents read).
const BATCH: usize = 64;

/// Bakes every page of the archive, writing each page's block to `out` as it is done;
/// returns the light samples taken. With `walks`, each patch also reflects the indirect
/// light walks from it find in the direct bake attached to the pages.
fn bake(
    scene: &Scene,
    p: &BakeParams,
    maps: Option<&GlossyMaps>,
    out: &mut RadianceWriter,
    progress: &dyn Fn(u64),
    walks: Option<&Walks>,
) -> Result<u64> {
    let cache = &scene.cache;
    let archive = &cache.archive;
    let diag = (V::from(archive.header.bounds_max) - V::from(archive.header.bounds_min)).length();
    // A right isosceles triangle of side patch_size·diagonal.
    let a_max = 0.5 * (p.patch_size * diag).powi(2);
    let mut roots = vec![[BakedNode::default(); 2]; cache.entries.len()];
    let mut glossy_roots: Vec<Vec<SparseVec<glam::Vec3>>> = vec![Vec::new(); cache.entries.len()];
    let mut samples = 0;
    let scene_tree = crate::paging::in_scene_tree(&cache.entries, archive.header.root_page);
    let (pages, placed): (Vec<u32>, Vec<u32>) =
        (0..cache.entries.len() as u32).partition(|&p| scene_tree[p as usize]);
    for id in placed {
        out.push(id, &unbaked_block(&cache.entries[id as usize]))?;
        progress(1);
    }
    // Glossy vectors of the level below, which only this level's pages read.
    let mut below: Vec<u32> = Vec::new();
    for level in deepest_first(&cache.entries, pages) {
        for batch in level.chunks(BATCH) {
            let done = Done {
                roots: &roots,
                glossy: &glossy_roots,
            };
            let baked: Vec<(u32, BakedBlock, Vec<SparseVec<glam::Vec3>>, u64)> = batch
                .par_iter()
                .map_init(
                    || Tracer::new(cache),
                    |tr, &id| {
                        let page = tr.page_handle(id);
                        let mut job = PageJob {
                            scene,
                            tr,
                            p,
                            a_max,
                            walks,
                            maps,
                        };
                        let (block, g, n) = job.bake_page(&page, &done);
                        (id, block, g, n)
                    },
                )
                .collect();
            for (id, block, g, n) in baked {
                for (r, v) in roots[id as usize].iter_mut().zip(&block.nodes) {
                    *r = *v;
                }
                glossy_roots[id as usize] = g;
                out.push(id, &block)?;
                samples += n;
                progress(1);
            }
        }
        for id in std::mem::replace(&mut below, level) {
            glossy_roots[id as usize] = Vec::new();
        }
    }
    if let Some(e) = scene.error() {
        anyhow::bail!(e);
    }
    Ok(samples)
}

/// The block of a page in a prototype's tree: its light depends on where each instance
/// places it, so the bake holds nothing there (zero nodes; every triangle's one patch
/// zero), and the render reads none of it (`surface::hit_light` lights instanced hits
/// itself).
fn unbaked_block(e: &canopy_format::PageEntry) -> BakedBlock {
    let tris = e.tri_count as usize;
    BakedBlock {
        nodes: vec![BakedNode::default(); e.node_count as usize],
        patch_of: vec![0; tris],
        patches: if tris > 0 { vec![[0.0; 3]] } else { Vec::new() },
        coefs: Default::default(),
    }
}

/// What deeper pages left for their parents: their roots' records and glossy vectors.
struct Done<'a> {
    roots: &'a [[BakedNode; 2]],
    glossy: &'a [Vec<SparseVec<glam::Vec3>>],
}

/// One page's bake and what it needs.
struct PageJob<'a, 'b> {
    scene: &'a Scene,
    tr: &'b mut Tracer<'a>,
    p: &'a BakeParams,
    a_max: f32,
    walks: Option<&'a Walks>,
    maps: Option<&'a GlossyMaps>,
}

impl PageJob<'_, '_> {
    /// One page's block: nodes children before parents (a page stores parents first; child
    /// pages' roots are already in `done`), triangles larger than `a_max` as patches, and
    /// with glossy maps the coefficients; also the exact glossy vectors of its roots.
    fn bake_page(
        &mut self,
        page: &Page,
        done: &Done,
    ) -> (BakedBlock, Vec<SparseVec<glam::Vec3>>, u64) {
        let mut block = BakedBlock {
            nodes: vec![BakedNode::default(); page.bvh.len()],
            patch_of: vec![0; page.tri_count() as usize],
            patches: Vec::new(),
            coefs: Default::default(),
        };
        let mut leaf_maps = vec![None; page.bvh.len()];
        let mut samples = 0;
        for i in (0..page.bvh.len()).rev() {
            let mut d = BakedNode::default();
            match page.bvh[i].link() {
                NodeRef::Leaf { first, count } => {
                    let end = (first + count).min(page.tri_count());
                    for k in first..end {
                        let key = ((page.first_node + i as u64) << 4) | (k - first) as u64;
                        let Some(tri) = page.tri(k) else {
                            continue;
                        };
                        let corners = page.corners(k);
                        // The first pass's direct light, attached to the page.
                        let direct = page.baked.patches_of(k as usize).and_then(|(depth, at)| {
                            let at = at + patch::level_start(depth);
                            let finest = page.baked.patches.get(at..at + (1 << (2 * depth)))?;
                            Some((depth, finest))
                        });
                        let light = match (self.walks, direct) {
                            (Some(w), Some((depth, finest))) => {
                                Light::WithIndirect(w, depth, finest)
                            }
                            _ => Light::Direct,
                        };
                        let t = triangle(
                            self.scene,
                            self.tr,
                            (&tri, corners),
                            self.p,
                            (self.a_max, key),
                            light,
                        );
                        samples += t.samples;
                        d.add(&t.node);
                        block.patch_of[k as usize] = t.depth << 28 | block.patches.len() as u32;
                        block.patches.extend(t.pyramid);
                    }
                    if let Some(m) = self.maps {
                        let mut rng = Hash::new(
                            self.p.seed as u64
                                ^ (page.first_node + i as u64).wrapping_mul(0xA24B_AED4_963E_E407),
                        );
                        leaf_maps[i] = m.leaf(
                            self.scene,
                            self.tr,
                            page,
                            first..end,
                            self.p.samples,
                            &mut rng,
                        );
                    }
                }
                NodeRef::Inner(l, r) => {
                    let (l, r) = (block.nodes[l as usize], block.nodes[r as usize]);
                    d.add(&l);
                    d.add(&r);
                }
                NodeRef::ChildPage(c) => {
                    for r in done.roots.get(c as usize).into_iter().flatten() {
                        d.add(r);
                    }
                }
                // Placed light is not baked (`unbaked_block`): an instance adds none.
                NodeRef::Instance(_) => {}
            }
            block.nodes[i] = d;
        }
        let Some(m) = self.maps else {
            return (block, Vec::new(), samples);
        };
        let nodes = &block.nodes;
        let leaf = |i: usize| {
            leaf_maps[i]
                .clone()
                .map(|dense| m.vector(dense, crate::paging::coefs::weight(&nodes[i])))
        };
        let child_roots = |c: u32| {
            let (recs, vecs) = (done.roots.get(c as usize), done.glossy.get(c as usize));
            match (recs, vecs) {
                (Some(r), Some(v)) => r
                    .iter()
                    .zip(v)
                    .map(|(r, v)| (crate::paging::coefs::weight(r), v.clone()))
                    .collect(),
                _ => Vec::new(),
            }
        };
        let (coefs, roots) = m.code_page(page, nodes, &leaf, &child_roots);
        block.coefs = coefs;
        (block, roots, samples)
    }
}

/// A triangle baked: its record, and its patch pyramid of depth `depth`.
struct BakedTriangle {
    node: BakedNode,
    depth: u32,
    pyramid: Vec<[f32; 3]>,
    samples: u64,
}

/// What a triangle's bake adds up: its direct light alone, or the direct light a first
/// pass baked (its depth and finest patches) and the walks' indirect light.
#[derive(Clone, Copy)]
enum Light<'a> {
    Direct,
    WithIndirect(&'a Walks, u32, &'a [[f32; 3]]),
}

/// A triangle's reflected radiance ρ·E/π, as a patch; split into 4^k patches baked one by
/// one when it is larger than `a_max`.
fn triangle(
    scene: &Scene,
    tr: &mut Tracer,
    (t, corners): (&crate::paging::TriW, Corners),
    p: &BakeParams,
    (a_max, key): (f32, u64),
    light: Light,
) -> BakedTriangle {
    let v = t.p.map(V::from);
    let cross = (v[1] - v[0]).cross(v[2] - v[0]);
    let area = 0.5 * cross.length();
    let rho = scene.mean_material(t.material).bsdf(true).diffuse;
    let dark = |node| BakedTriangle {
        node,
        depth: 0,
        pyramid: vec![[0.0; 3]],
        samples: 0,
    };
    if area.is_nan() || area <= 0.0 {
        return dark(BakedNode::default());
    }
    let ng = cross / (2.0 * area);
    if rho.max_element() <= 0.0 {
        return dark(BakedNode::patch(area, ng, V::ZERO));
    }
    let err = (v[0].abs() + v[1].abs() + v[2].abs()) * gamma(7);
    let (k, mut finest, samples) = match light {
        Light::Direct => direct_patches(scene, tr, (t, corners), p, (a_max, key), (ng, err)),
        Light::WithIndirect(_, k, direct) => (k, direct.iter().map(|&l| V::from(l)).collect(), 0),
    };
    if let Light::WithIndirect(walks, ..) = light {
        // Every finest patch takes its own walks, and a triangle smaller than a patch its
        // share of a patch's: the image's error from the bake follows the walks per area
        // seen. Walks pooled over groups of patches flattened the indirect light where it
        // changes fastest, in corners, which gathers nearby weigh most (docs/pbgi.md).
        let count = match k {
            0 => per_area(walks.count, area, a_max),
            _ => walks.count,
        };
        let own = Walks { count, ..*walks };
        let shading = Shading::new(scene, (t, corners), ng);
        for (i, f) in finest.iter_mut().enumerate() {
            let mut rng = seeded(p, patch_key(key, i) ^ 0x5bd1_e995);
            let tri = patch::patch(v, k, i);
            *f += own.reflected(scene, tr, tri, (err, ng), &shading, &mut rng);
        }
    }
    let mean = finest.iter().sum::<V>() / finest.len() as f32;
    let present = coverage(scene, (t, corners), &mut seeded(p, key ^ 0xC0FE_u64 << 44));
    BakedTriangle {
        node: BakedNode::patch(area * present, ng, mean),
        depth: k,
        samples,
        pyramid: patch::pyramid(&finest, k),
    }
}

/// The numbers of the bake's estimate with key `key`.
fn seeded(p: &BakeParams, key: u64) -> Hash {
    Hash::new(p.seed as u64 ^ key.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

/// The key of patch `i` of the triangle with key `key`.
fn patch_key(key: u64, i: usize) -> u64 {
    key ^ ((i as u64 + 1) << 40)
}

/// `count` scaled to a triangle of `area` smaller than a patch of `a_max`: its share, at
/// least one. Small triangles then take samples at the density patches take them.
fn per_area(count: u32, area: f32, a_max: f32) -> u32 {
    ((count as f32 * area / a_max).ceil() as u32).clamp(1, count)
}

/// A triangle's direct light as patches: their depth, their finest level's light, and the
/// light samples taken (with a shadow's edge across them, a coarser level first too). A
/// triangle smaller than a patch takes its share of a patch's samples (`per_area`).
fn direct_patches(
    scene: &Scene,
    tr: &mut Tracer,
    (t, corners): (&crate::paging::TriW, Corners),
    p: &BakeParams,
    (a_max, key): (f32, u64),
    (ng, err): (V, V),
) -> (u32, Vec<V>, u64) {
    let v = t.p.map(V::from);
    let shading = Shading::new(scene, (t, corners), ng);
    let mut direct = |tri: [V; 3], key: u64, samples: u32| {
        let mut rng = seeded(p, key);
        let (mut sum, mut sum_y2) = (V::ZERO, 0.0);
        let side = patch::side(tri);
        for _ in 0..samples {
            let q = patch::uniform_point(tri, &mut rng);
            let (rho, n) = shading.at(q, side);
            // Light sampling alone (BSDF pdf 0 gives it full weight): nothing else samples
            // the emitters here. A tilted normal takes no light from below the surface,
            // as `on_side` has it.
            let l = sample_light(
                scene,
                tr,
                &Receiver::surface(q, err, ng),
                &Cone::EXACT,
                [rng.f32(), rng.f32(), rng.f32()],
                |wi| match ng.dot(wi) > 0.0 {
                    true => (rho * (FRAC_1_PI * n.dot(wi).max(0.0)), 0.0),
                    false => (V::ZERO, 0.0),
                },
            );
            sum += l;
            sum_y2 += luminance(l) * luminance(l);
        }
        let n = samples as f32;
        let mean = sum / n;
        let var = (sum_y2 / n - luminance(mean).powi(2)).max(0.0) / (n - 1.0).max(1.0);
        Patch { l: mean, var }
    };
    let area = 0.5 * (v[1] - v[0]).cross(v[2] - v[0]).length();
    let mut k = patch::depth(area, a_max);
    let whole = per_area(p.samples, area, a_max);
    let mut level = |k: u32| -> Vec<Patch> {
        match k {
            0 => vec![direct(v, key, whole)],
            _ => (0..1usize << (2 * k))
                .map(|i| direct(patch::patch(v, k, i), patch_key(key, i), p.samples))
                .collect(),
        }
    };
    let mut patches = level(k);
    let mut samples = match k {
        0 => whole as u64,
        _ => p.samples as u64 * patches.len() as u64,
    };
    // A shadow's edge across the patches: bake them REFINE levels finer, so that a
    // contact's shadow is not averaged with the light beside it (on the showroom the gold
    // bunny's base, whose glossy bounce sees its plinth's top, was 1.6% dark).
    if k > 0 && k < MAX_PATCH_DEPTH && disagree(&patches) {
        k = (k + REFINE).min(MAX_PATCH_DEPTH);
        patches = level(k);
        samples += p.samples as u64 * patches.len() as u64;
    }
    (k, patches.iter().map(|p| p.l).collect(), samples)
}

/// Points a masked or blended triangle's coverage is estimated at.
const COVERAGE_SAMPLES: u32 = 32;

/// The share of a triangle that is there under its material's alpha (1 without a mask or
/// blend): the mean opacity at `COVERAGE_SAMPLES` uniform points, read as the path tracer
/// reads it (level 0, the cutoff applied). A node's splat then hides and sends only what
/// is there, as the cone integrator's clusters take coverage (glTF 2.0 §3.9.4).
fn coverage(scene: &Scene, (t, c): (&crate::paging::TriW, Corners), rng: &mut Hash) -> f32 {
    if !scene.textures.has_alpha() || !scene.textures.varies(t.material) {
        return 1.0;
    }
    let sum: f32 = (0..COVERAGE_SAMPLES)
        .map(|_| {
            let (mut a, mut b) = (rng.f32(), rng.f32());
            if a + b > 1.0 {
                (a, b) = (1.0 - a, 1.0 - b);
            }
            scene.opacity(t.material, &c, [1.0 - a - b, a, b])
        })
        .sum();
    sum / COVERAGE_SAMPLES as f32
}

/// A patch's baked light and the variance of its luminance's estimate.
#[derive(Clone, Copy, Debug)]
struct Patch {
    l: V,
    var: f32,
}

/// Levels finer a triangle's patches are baked where `disagree` finds a shadow's edge.
const REFINE: u32 = 2;

/// Whether some four sibling patches differ by more than their mean luminance (a
/// shadow's edge, not a gradient across them) and by more than three standard errors
/// of the difference (not the bake's noise).
fn disagree(patches: &[Patch]) -> bool {
    patches.chunks(4).any(|c| {
        let y = |p: &Patch| luminance(p.l);
        let lo = c.iter().min_by(|a, b| y(a).total_cmp(&y(b)));
        let hi = c.iter().max_by(|a, b| y(a).total_cmp(&y(b)));
        let (Some(lo), Some(hi)) = (lo, hi) else {
            return false;
        };
        let mean = c.iter().map(y).sum::<f32>() / c.len() as f32;
        let d = y(hi) - y(lo);
        d > mean && d * d > 9.0 * (hi.var + lo.var)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn patches_disagree_across_a_shadows_edge_not_across_a_gradient_or_noise() {
        let p = |y: f32, var: f32| Patch {
            l: V::splat(y),
            var,
        };
        let lit = [p(1.0, 1e-4); 4];
        assert!(!disagree(&lit));
        let edge = [p(1.0, 1e-4), p(1.0, 1e-4), p(0.05, 1e-4), p(1.0, 1e-4)];
        assert!(disagree(&edge), "a shadowed patch beside lit ones");
        assert!(disagree(&[lit, edge].concat()), "in any group of four");
        let gradient = [p(0.8, 1e-4), p(1.0, 1e-4), p(1.2, 1e-4), p(1.0, 1e-4)];
        assert!(!disagree(&gradient), "light falling off across the patches");
        let noisy = [p(1.0, 0.2), p(1.0, 0.2), p(0.05, 0.2), p(1.0, 0.2)];
        assert!(!disagree(&noisy), "a difference within the bake's noise");
    }

    #[test]
    fn a_patch_shows_its_area_along_each_axis_and_nothing_behind() {
        let b = V::new(1.0, 2.0, 3.0);
        for n in [V::X, V::NEG_Y, V::Z] {
            let d = BakedNode::patch(2.0, n, b);
            let (area, power) = d.toward(n);
            assert!((area - 2.0).abs() < 1e-6 && (power - b * 2.0).abs().max_element() < 1e-6);
            assert_eq!(d.toward(-n).0, 0.0);
        }
        // An oblique patch shows at least A·max(0, n·ω), exactly that where n and ω agree
        // in sign on every axis, and its own light from every front direction.
        let n = V::new(1.0, 2.0, -2.0).normalize();
        let d = BakedNode::patch(3.0, n, b);
        let mut rng = crate::test_rng::TestRng::new(3);
        for _ in 0..200 {
            let w = V::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5).normalize();
            let (area, power) = d.toward(w);
            let exact = 3.0 * n.dot(w).max(0.0);
            assert!(area >= exact - 1e-5, "{w}: {area} below {exact}");
            if (0..3).all(|k| n[k] * w[k] >= 0.0) {
                assert!((area - exact).abs() < 1e-5, "{w}: {area} vs {exact}");
            }
            if area > 1e-3 {
                assert!((power / area - b).abs().max_element() < 1e-3);
            }
        }
    }

    /// Faces of the box [0, e] with outward normals, as nodes.
    fn boxed(e: V, b: V) -> BakedNode {
        let mut sum = BakedNode::default();
        for (k, n) in [V::X, V::NEG_X, V::Y, V::NEG_Y, V::Z, V::NEG_Z]
            .into_iter()
            .enumerate()
        {
            let a = match k / 2 {
                0 => e.y * e.z,
                1 => e.x * e.z,
                _ => e.x * e.y,
            };
            sum.add(&BakedNode::patch(a, n, b));
        }
        sum
    }

    #[test]
    fn a_box_shows_its_silhouette_and_a_ball_at_most_root_3_times_its_own() {
        let e = V::new(1.0, 2.0, 0.5);
        let cube = boxed(e, V::ONE);
        let mut ball = BakedNode::default();
        let mut rng = crate::test_rng::TestRng::new(5);
        let normals: Vec<V> = (0..4000)
            .map(|_| V::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5))
            .filter(|v| v.length() > 0.1 && v.length() < 0.5)
            .map(|v| v.normalize())
            .collect();
        // Equal patches over uniform directions: a ball of silhouette area 1.
        for &n in &normals {
            ball.add(&BakedNode::patch(4.0 / normals.len() as f32, n, V::ONE));
        }
        for _ in 0..200 {
            let w = V::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32() - 0.5).normalize();
            let silhouette = w.x.abs() * e.y * e.z + w.y.abs() * e.x * e.z + w.z.abs() * e.x * e.y;
            let (area, power) = cube.toward(w);
            assert!(
                (area - silhouette).abs() < 1e-4,
                "{w}: {area} vs {silhouette}"
            );
            assert!((power - V::splat(area)).abs().max_element() < 1e-4);
            let area = ball.toward(w).0;
            assert!(area > 0.95 && area < 1.8, "{w}: ball shows {area}");
        }
    }

    #[test]
    fn nodes_add_their_childrens_area_and_power() {
        let mut sum = BakedNode::patch(1.0, V::X, V::ONE);
        sum.add(&BakedNode::patch(1.0, V::NEG_X, V::ZERO));
        let w = V::new(1.0, 1.0, 0.0).normalize();
        let (area, power) = sum.toward(w);
        // The +x patch at 45°; the −x one is turned away.
        assert!((area - 0.5f32.sqrt()).abs() < 1e-6, "{area}");
        assert!((power.x - area).abs() < 1e-6);
        // Seen along −x only the dark patch shows.
        assert_eq!(sum.toward(V::NEG_X).1, V::ZERO);
    }
}
