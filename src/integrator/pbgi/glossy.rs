//! Glossy light in the cloud: the radiance wavelet PBGI gathers (000 §3.1; 003 ch. 4).
//!
//! A node of a rough metal or rough dielectric surface reflects direct light unevenly:
//! what it sends toward a receiver depends on the direction. Its glossy intensity
//! I(ω) = Σ A·max(0, n·ω)·L_g(ω) over its glossy triangles (L_g: the light reflected by
//! the specular lobes alone, the diffuse part being in `bake::Directional`) is tabulated
//! at the texel centres of an n×n cube map in the global frame, Haar-transformed per face
//! and divided by the node's weight, so that a node's vector G is its children's
//! weighted mean and weight × G its intensity (`paging::coefs`). Leaves estimate it with
//! light samples at area-weighted points of their glossy triangles, one sample serving
//! every texel. Perfect mirrors and glass are left out: the renderer follows them exactly.

use super::patch::uniform_point;
use crate::integrator::{sample_light, Receiver, Scene};
use crate::material::{Bsdf, Frame, Material};
use crate::paging::coefs::{weight, PageShape, BOOTSTRAP};
use crate::paging::{NodeRef, Page};
use crate::sampler::Hash;
use crate::trace::{gamma, Cone, Tracer};
use crate::wavelet::tree::{encode, SparseVec};
use crate::wavelet::{cube, haar};
use canopy_format::bake::{BakedNode, CoefBlock};
use glam::{Vec3, Vec3A as V};
use std::cell::Cell;

/// Whether the bake stores glossy coefficients (`--wavelet`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum WaveletMode {
    /// When some material is rough metal or rough dielectric.
    Auto,
    /// Always (an error when no material is glossy).
    On,
    Off,
}

/// A material whose rough specular lobes the coefficients hold.
pub fn stores_glossy(m: &Material) -> bool {
    !m.is_pure_diffuse() && !m.has_delta_lobe()
}

/// Whether some material of the scene has rough specular lobes.
pub fn any_glossy(scene: &Scene) -> bool {
    scene.materials.iter().any(stores_glossy)
}

/// How a bake tabulates glossy light: texel centres of the n×n cube map and the relative
/// truncation threshold.
pub struct GlossyMaps {
    pub n: usize,
    pub threshold: f32,
    dirs: Vec<V>,
}

impl GlossyMaps {
    pub fn new(n: usize, threshold: f32) -> GlossyMaps {
        GlossyMaps {
            n,
            threshold,
            dirs: (0..6 * n * n)
                .map(|k| V::from(cube::texel_dir(k, n)))
                .collect(),
        }
    }

    /// A leaf's glossy intensity per texel (dense), `None` when none of its triangles is
    /// glossy: `samples` light samples at area-weighted points of its glossy triangles.
    pub fn leaf(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        page: &Page,
        tris: std::ops::Range<u32>,
        samples: u32,
        rng: &mut Hash,
    ) -> Option<Vec<Vec3>> {
        let glossy: Vec<(u32, f32)> = tris
            .filter_map(|t| {
                let tri = page.tri(t)?;
                let m = scene.materials.get(tri.material as usize)?;
                let v = tri.p.map(V::from);
                let a = 0.5 * (v[1] - v[0]).cross(v[2] - v[0]).length();
                (stores_glossy(m) && a > 0.0 && a.is_finite()).then_some((t, a))
            })
            .collect();
        if glossy.is_empty() {
            return None;
        }
        let total: f32 = glossy.iter().map(|g| g.1).sum();
        let mut map = vec![Vec3::ZERO; self.dirs.len()];
        for _ in 0..samples {
            let mut pick = rng.f32() * total;
            let &(t, _) = glossy
                .iter()
                .find(|g| {
                    pick -= g.1;
                    pick < 0.0
                })
                .unwrap_or(&glossy[glossy.len() - 1]);
            let Some(tri) = page.tri(t) else {
                continue;
            };
            let bsdf = Bsdf {
                diffuse: V::ZERO,
                ..scene
                    .mean_material_over(tri.material, &page.corners(t))
                    .bsdf(true)
            };
            self.sample(scene, tr, tri.p.map(V::from), bsdf, rng, &mut map);
        }
        let scale = total / samples as f32;
        map.iter_mut().for_each(|v| *v *= scale);
        Some(map)
    }

    /// One light sample at a uniform point of triangle `p`, reflected by `bsdf` toward
    /// every texel centre in front of it and added to `map` (radiance × cosine).
    fn sample(
        &self,
        scene: &Scene,
        tr: &mut Tracer,
        p: [V; 3],
        bsdf: Bsdf,
        rng: &mut Hash,
        map: &mut [Vec3],
    ) {
        let cross = (p[1] - p[0]).cross(p[2] - p[0]);
        let ng = cross.normalize();
        let q = uniform_point(p, rng);
        let err = (p[0].abs() + p[1].abs() + p[2].abs()) * gamma(7);
        let wi = Cell::new(V::ZERO);
        // Light sampling alone, as the diffuse bake: E·(cos/pdf) now, the BSDF per texel.
        let e = sample_light(
            scene,
            tr,
            &Receiver::surface(q, err, ng),
            &Cone::EXACT,
            [rng.f32(), rng.f32(), rng.f32()],
            |w| {
                wi.set(w);
                (V::splat(ng.dot(w).max(0.0)), 0.0)
            },
        );
        if e.max_element() <= 0.0 {
            return;
        }
        let frame = Frame::new(ng);
        let wi_l = frame.to_local(wi.get());
        for (m, &w) in map.iter_mut().zip(&self.dirs) {
            let c = ng.dot(w);
            if c > 0.0 {
                *m += Vec3::from(bsdf.eval(frame.to_local(w), wi_l).0 * e * c);
            }
        }
    }

    /// A dense map as a coefficient vector: each face Haar-transformed, divided by `w`.
    pub fn vector(&self, mut dense: Vec<Vec3>, w: f32) -> SparseVec<Vec3> {
        let nn = self.n * self.n;
        let mut out = Vec::new();
        for (f, face) in dense.chunks_mut(nn).enumerate() {
            haar::forward(face, self.n);
            out.extend(
                face.iter()
                    .enumerate()
                    .filter(|(_, c)| **c != Vec3::ZERO)
                    .map(|(i, &c)| ((f * nn + i) as u32, c / w)),
            );
        }
        SparseVec(out)
    }

    /// Codes a page: `leaf(i)` gives leaf i's vector, `child_roots` the exact vectors and
    /// weights of a child page's roots. Returns the block's coefficients and the exact G
    /// of the page's roots, which its parent page reads. The threshold is relative to the
    /// largest coefficient (RGB length) of the page's roots: 000 §3.1's absolute L²
    /// threshold (0.002) depends on the scene's units of light, and a page in shadow
    /// would lose all its detail under one scaled to the brightest page.
    pub fn code_page(
        &self,
        page: &Page,
        nodes: &[BakedNode],
        leaf: &dyn Fn(usize) -> Option<SparseVec<Vec3>>,
        child_roots: &dyn Fn(u32) -> Vec<(f32, SparseVec<Vec3>)>,
    ) -> (CoefBlock, Vec<SparseVec<Vec3>>) {
        let shape = PageShape::new(&page.bvh, page.roots, nodes);
        let mut g = vec![SparseVec::default(); page.bvh.len()];
        for i in (0..page.bvh.len()).rev() {
            let (parts, total): (Vec<(f32, SparseVec<Vec3>)>, f32) = match page.bvh[i].link() {
                NodeRef::Leaf { .. } => (leaf(i).map(|v| (1.0, v)).into_iter().collect(), 1.0),
                NodeRef::ChildPage(c) => (child_roots(c), weight(&nodes[i])),
                // Glossy maps are not made for instanced archives (`BakeParams::maps`).
                NodeRef::Instance(_) => (Vec::new(), 1.0),
                NodeRef::Inner(l, r) => {
                    let kids = [l, r].map(|c| (shape.weight[c as usize], g[c as usize].clone()));
                    (kids.to_vec(), kids[0].0 + kids[1].0)
                }
            };
            g[i] = parts.iter().fold(SparseVec::default(), |acc, (w, v)| {
                acc.add_scaled(v, w / total)
            });
        }
        let roots = &shape.children[shape.root()];
        let largest = roots
            .iter()
            .flat_map(|&r| g[r].0.iter().map(|c| c.1.length()))
            .fold(0.0, f32::max);
        let coded = encode(
            &shape.shape(),
            &|i| g.get(i).cloned().unwrap_or_default(),
            BOOTSTRAP,
            self.threshold * largest,
        );
        let (records, values) = crate::paging::coefs::records(
            |i| coded.stored(i).map(|(k, v)| (k, v.clone())),
            g.len(),
        );
        let root_g = roots.iter().map(|&r| g[r].clone()).collect();
        (CoefBlock { records, values }, root_g)
    }
}
