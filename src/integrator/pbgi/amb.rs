//! The importance-driven adaptive micro-buffer of WPBGI (000 §3.2; NOTES-000-001 A.4):
//! a hemicube quadtree in the receiver's local frame, refined where the BRDF varies.
//!
//! It starts as the uniform hemicube of n² texels a face and splits a cell while the
//! receiver's BRDF table keeps a detail coefficient inside it ([`BrdfTable::varies`]):
//! the BRDF importance F_ρ, read from the subdivision of the table's own quadtree as 000
//! asks, down to the table's resolution. A node is splatted as a square of its solid
//! angle on the grid of the leaf under its centre; a fragment on a coarser leaf covers
//! its share of it, one on a cell that is split further covers each leaf under it. Each
//! leaf composites its fragments front to back as the uniform micro-buffer does.
//!
//! Not built: the light importance F_l and the per-texel node lists re-splatted when a
//! texel splits (000 Alg. 2). The cut's nodes are chosen by the leaf under them, so a
//! node over the lobe is already refined to the lobe's texels. Under `--pbgi-rays` each
//! leaf's ray is traced instead ([`Amb::rays`]).

use super::brdf_table::{BrdfTable, RES};
use super::microbuffer::square;
use crate::wavelet::{cube, haar};
use glam::Vec3;

#[derive(Clone, Copy, Debug)]
struct Cell {
    face: u8,
    level: u8,
    x: u16,
    y: u16,
    /// First of four children (0: a leaf).
    child: u32,
    /// Index among the leaves, for a leaf.
    leaf: u32,
}

#[derive(Clone, Copy, Debug)]
struct Fragment {
    leaf: u32,
    depth: f32,
    id: u64,
    coverage: f32,
    radiance: Vec3,
}

#[derive(Default)]
pub struct Amb {
    n: usize,
    cells: Vec<Cell>,
    /// Per texel of the base cube (6n²): its cell, or u32::MAX below the horizon.
    roots: Vec<u32>,
    /// Cell index of each leaf.
    leaves: Vec<u32>,
    frags: Vec<Fragment>,
}

impl Amb {
    /// Starts over at `n` texels a face side (even, dividing RES), splitting every cell
    /// `split(face, res, x, y)` asks for, down to RES.
    pub fn init(&mut self, n: usize, split: impl Fn(usize, usize, usize, usize) -> bool) {
        self.n = n;
        self.cells.clear();
        self.leaves.clear();
        self.frags.clear();
        self.roots.clear();
        self.roots.resize(6 * n * n, u32::MAX);
        for face in 0..5 {
            let rows = if face == 4 { 0 } else { n / 2 };
            for y in rows..n {
                for x in 0..n {
                    self.roots[face * n * n + y * n + x] = self.cells.len() as u32;
                    self.cells.push(Cell {
                        face: face as u8,
                        level: 0,
                        x: x as u16,
                        y: y as u16,
                        child: 0,
                        leaf: 0,
                    });
                }
            }
        }
        let mut i = 0;
        while i < self.cells.len() {
            let c = self.cells[i];
            let res = n << c.level;
            if res < RES && split(c.face as usize, res, c.x as usize, c.y as usize) {
                self.cells[i].child = self.cells.len() as u32;
                for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                    self.cells.push(Cell {
                        level: c.level + 1,
                        x: 2 * c.x + dx,
                        y: 2 * c.y + dy,
                        ..c
                    });
                }
            } else {
                self.cells[i].leaf = self.leaves.len() as u32;
                self.leaves.push(i as u32);
            }
            i += 1;
        }
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    /// Resolution and cube texel index of a cell.
    fn texel(&self, c: &Cell) -> (usize, usize) {
        let res = self.n << c.level;
        let k = c.face as usize * res * res + c.y as usize * res + c.x as usize;
        (res, k)
    }

    /// The cell at (x, y) of `face` at `level`, or the leaf above it; None below the
    /// horizon.
    fn descend(&self, face: usize, level: u8, x: usize, y: usize) -> Option<usize> {
        let n = self.n;
        let root = self.roots[face * n * n + (y >> level) * n + (x >> level)];
        if root == u32::MAX {
            return None;
        }
        let mut at = root as usize;
        while self.cells[at].level < level && self.cells[at].child != 0 {
            let shift = level - self.cells[at].level - 1;
            let quad = ((x >> shift) & 1) + 2 * ((y >> shift) & 1);
            at = self.cells[at].child as usize + quad;
        }
        Some(at)
    }

    /// The leaf a local direction falls in, None below the horizon.
    fn leaf_at(&self, dir: Vec3) -> Option<usize> {
        let (face, s, t) = cube::face_st(dir);
        let k = cube::texel_at(face, s, t, RES);
        let levels = (RES / self.n).trailing_zeros() as u8;
        self.descend(face, levels, k % RES, (k / RES) % RES)
    }

    /// Solid angle of the leaf a local direction falls in (the cut's yardstick there).
    pub fn solid_angle_toward(&self, dir: Vec3) -> Option<f32> {
        let c = self.cells[self.leaf_at(dir)?];
        let (res, k) = self.texel(&c);
        Some(cube::texel_solid_angle(k, res))
    }

    /// Each leaf's ray through the point (a, b) of its square (`jitter(leaf)`), in the local
    /// frame, with the weight of its light as [`super::microbuffer::Texels::ray`] has it,
    /// without the cosine (the table holds it): dω/dA there times the leaf's area over its
    /// solid angle, so its mean over the leaf is 1.
    pub fn rays<'a>(
        &'a self,
        jitter: impl Fn(u32) -> [f32; 2] + 'a,
    ) -> impl Iterator<Item = (u32, Vec3, f32)> + 'a {
        self.leaves.iter().enumerate().map(move |(j, &c)| {
            let (res, k) = self.texel(&self.cells[c as usize]);
            let corners = cube::texel_corners(k, res);
            let (u, v) = (corners[1] - corners[0], corners[3] - corners[0]);
            let [a, b] = jitter(j as u32);
            let local = corners[0] + u * a + v * b;
            let r = local.length();
            let weight = u.cross(v).length() / r.powi(3) / cube::texel_solid_angle(k, res);
            (j as u32, local / r, weight)
        })
    }

    /// Splats a node seen in local direction `dir` (unit) at `depth`, subtending
    /// `solid_angle`, sending `radiance`: a square of that solid angle on the grid of the
    /// leaf under its centre, as [`super::microbuffer::MicroBuffer::splat`] lays it.
    pub fn splat(&mut self, dir: Vec3, depth: f32, solid_angle: f32, id: u64, radiance: Vec3) {
        if dir.z <= 0.0 || solid_angle.is_nan() || solid_angle <= 0.0 {
            return;
        }
        let Some(under) = self.leaf_at(dir) else {
            return;
        };
        let level = self.cells[under].level;
        let (m, k) = self.texel(&self.cells[under]);
        let (face, s, t) = cube::face_st(dir);
        let texels = solid_angle / cube::texel_solid_angle(k, m);
        for (x, y, coverage) in square(s, t, m, texels) {
            let Some(at) = self.descend(face, level, x, y) else {
                continue;
            };
            self.cover(
                at,
                level,
                Fragment {
                    leaf: 0,
                    depth,
                    id,
                    coverage,
                    radiance,
                },
            );
        }
    }

    /// Adds fragment `f` (its coverage of a cell at `level`) to cell `at`'s leaves.
    fn cover(&mut self, at: usize, level: u8, f: Fragment) {
        let c = self.cells[at];
        if c.child == 0 {
            let share = 0.25f32.powi((level - c.level) as i32);
            self.frags.push(Fragment {
                leaf: c.leaf,
                coverage: f.coverage * share,
                ..f
            });
            return;
        }
        for q in 0..4 {
            self.cover(c.child as usize + q, c.level + 1, f);
        }
    }

    /// Fills leaf `leaf` whole with an opaque fragment (a traced or rasterized hit).
    pub fn fill(&mut self, leaf: u32, depth: f32, id: u64, radiance: Vec3) {
        self.frags.push(Fragment {
            leaf,
            depth,
            id,
            coverage: 1.0,
            radiance,
        });
    }

    /// Incident radiance per leaf: its fragments composited front to back by depth (node
    /// number breaking ties), the open rest black.
    pub fn resolve(&mut self) -> Vec<Vec3> {
        self.frags.sort_unstable_by(|a, b| {
            (a.leaf, a.depth)
                .partial_cmp(&(b.leaf, b.depth))
                .unwrap_or(std::cmp::Ordering::Equal)
                .then(a.id.cmp(&b.id))
        });
        let mut out = vec![Vec3::ZERO; self.leaves.len()];
        let mut open = vec![1.0f32; self.leaves.len()];
        for f in &self.frags {
            let o = &mut open[f.leaf as usize];
            let take = f.coverage.min(*o);
            out[f.leaf as usize] += f.radiance * take;
            *o -= take;
        }
        out
    }

    /// The reflected radiance: the leaves' light spread over the table's RES² texels a
    /// face, Haar-transformed, and multiplied with the BRDF's kept coefficients (000 §3.3's
    /// D = UW, taken as the inner product that gives one ω_o's outgoing radiance).
    pub fn reflect(&self, incident: &[Vec3], table: &BrdfTable, theta_o: f32) -> Vec3 {
        let mut faces = vec![vec![Vec3::ZERO; RES * RES]; 5];
        for (j, &c) in self.leaves.iter().enumerate() {
            let c = self.cells[c as usize];
            let block = RES / (self.n << c.level);
            let face = &mut faces[c.face as usize];
            for y in 0..block {
                let row = (c.y as usize * block + y) * RES + c.x as usize * block;
                face[row..row + block].fill(incident[j]);
            }
        }
        for f in &mut faces {
            haar::forward(f, RES);
        }
        table.product(theta_o, &faces)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::Bsdf;
    use glam::Vec3A as V;

    fn table() -> BrdfTable {
        let bsdf = Bsdf {
            diffuse: V::ZERO,
            f0: V::splat(0.9),
            f90: V::ONE,
            alpha: 0.09,
            trans: 0.0,
            tint: V::ONE,
            eta: 1.5,
        };
        BrdfTable::new(&bsdf, super::super::brdf_table::THRESHOLD)
    }

    /// Leaves' solid angles sum to 2π whatever the refinement, and refinement follows the
    /// BRDF: leaves are finer toward the mirror direction than away from it.
    #[test]
    fn leaves_tile_the_hemisphere_and_are_finest_at_the_lobe() {
        let table = table();
        let theta = 0.6f32;
        let mut amb = Amb::default();
        amb.init(8, |f, r, x, y| table.varies(theta, f, r, x, y));
        let total: f64 = amb
            .leaves
            .iter()
            .map(|&c| {
                let (res, k) = amb.texel(&amb.cells[c as usize]);
                cube::texel_solid_angle(k, res) as f64
            })
            .sum();
        assert!((total - 2.0 * std::f64::consts::PI).abs() < 1e-4, "{total}");
        let mirror = Vec3::new(-theta.sin(), 0.0, theta.cos());
        let away = Vec3::new(theta.sin(), 0.3, 0.5).normalize();
        let (at, far) = (amb.solid_angle_toward(mirror), amb.solid_angle_toward(away));
        assert!(at.unwrap() * 16.0 <= far.unwrap(), "{at:?} {far:?}");
    }

    /// A uniform environment of radiance 1, splatted as the leaves' own squares in any
    /// order, reflects the directional albedo, the same bits in every order.
    #[test]
    fn splat_order_does_not_change_the_reflection() {
        let table = table();
        let theta = 0.3f32;
        let mut amb = Amb::default();
        amb.init(8, |f, r, x, y| table.varies(theta, f, r, x, y));
        let squares: Vec<(Vec3, f32)> = amb
            .leaves
            .iter()
            .map(|&c| {
                let (res, k) = amb.texel(&amb.cells[c as usize]);
                (cube::texel_dir(k, res), cube::texel_solid_angle(k, res))
            })
            .collect();
        let mut results = Vec::new();
        for order in [false, true] {
            amb.frags.clear();
            let mut list: Vec<(usize, &(Vec3, f32))> = squares.iter().enumerate().collect();
            if order {
                list.reverse();
            }
            for (i, &(d, o)) in list {
                amb.splat(d, 1.0, o, i as u64, Vec3::ONE);
            }
            let incident = amb.resolve();
            results.push(amb.reflect(&incident, &table, theta));
        }
        assert_eq!(results[0], results[1]);
        let mut ones = Amb::default();
        ones.init(8, |_, _, _, _| false);
        let flat: Vec<Vec3> = vec![Vec3::ONE; ones.leaf_count()];
        let albedo = ones.reflect(&flat, &table, theta);
        let rel = ((results[0] - albedo) / albedo).abs().max_element();
        assert!(rel < 0.02, "{} against {albedo}", results[0]);
    }
}
