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
//! With the light importance on (`--pbgi-light-importance γ` above 0), the BRDF alone
//! refines it to 2n² a face ([`BRDF_LEVELS`]); past that a leaf splits only where F_l
//! also holds, L(q)/2^Δq > γ·L̄ ([`Amb::refine`]): its incident luminance, halved per
//! level Δq past n², above γ times the hemisphere's mean luminance L̄. 000 compares
//! L(q)/2^Δq with γ in absolute radiance; relative to L̄ the knob does not depend on the
//! scene's exposure. Each fragment keeps the node that made it (the per-texel node list),
//! so a leaf that splits hands its nodes back to be traversed again and splatted onto its
//! children only; its hits are dropped, and the children take their own rays, but a
//! traced ray is handed to the child it passes through. Under `--pbgi-gather rays` each leaf's
//! ray is traced instead of the cut ([`Amb::rays`]).

use super::brdf_table::RES;
use super::microbuffer::square;
use crate::material::luminance;
use crate::wavelet::{cube, haar};
use glam::{Vec3, Vec3A};

/// Levels past the base n² that the BRDF importance F_ρ alone refines; deeper splits
/// also need the light importance F_l (000 §3.2 starts from 16² refined by the BRDF).
pub const BRDF_LEVELS: u8 = 1;

/// The tag of a fragment no node made (a traced or rasterized hit).
const NO_NODE: u64 = u64::MAX;

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
    /// The refinement round that made it: splats land only on leaves of the current one.
    round: u16,
    /// It holds its parent's traced ray ([`Amb::refine`] with `keep_rays`).
    held: bool,
}

#[derive(Clone, Copy, Debug)]
struct Fragment {
    cell: u32,
    depth: f32,
    id: u64,
    /// The node it came from, for re-traversal when its cell splits ([`NO_NODE`]: a hit).
    node: u64,
    coverage: f32,
    radiance: Vec3,
}

#[derive(Default)]
pub struct Amb {
    n: usize,
    cells: Vec<Cell>,
    /// Per texel of the base cube (6n²): its cell, or u32::MAX below the horizon.
    roots: Vec<u32>,
    /// Cell index of each leaf, split leaves included (their cells have children).
    leaves: Vec<u32>,
    /// Where in its square each leaf's ray passes ([`Amb::rays`]).
    jitters: Vec<[f32; 2]>,
    frags: Vec<Fragment>,
    round: u16,
    /// The hemisphere's mean incident luminance after the first fill (L̄).
    mean: f32,
    /// Leaves split by the light importance since [`Amb::init`].
    pub light_splits: u64,
}

impl Amb {
    /// Starts over at `n` texels a face side (even, dividing RES), splitting every cell
    /// `split(face, res, x, y)` asks for, down to RES.
    pub fn init(&mut self, n: usize, split: impl Fn(usize, usize, usize, usize) -> bool) {
        self.n = n;
        self.cells.clear();
        self.leaves.clear();
        self.frags.clear();
        self.jitters.clear();
        self.round = 0;
        self.mean = 0.0;
        self.light_splits = 0;
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
                        round: 0,
                        held: false,
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

    /// Leaves not split.
    pub fn leaf_count(&self) -> usize {
        self.live().count()
    }

    /// Indices of the leaves not split.
    fn live(&self) -> impl Iterator<Item = usize> + '_ {
        (0..self.leaves.len()).filter(|&j| self.cells[self.leaves[j] as usize].child == 0)
    }

    /// Splits every leaf where both importances hold (`varies(face, res, x, y)`: F_ρ;
    /// F_l against `incident`, this round's [`Amb::resolve`]), drops the fragments of the
    /// split leaves (but under `keep_rays` their traced rays go to the children they pass
    /// through) and moves to a new round. Returns the first new leaf and the nodes
    /// recorded in the split leaves, to be traversed again onto the new ones; None when
    /// no leaf splits.
    pub fn refine(
        &mut self,
        incident: &[Vec3],
        (gamma, keep_rays): (f32, bool),
        varies: impl Fn(usize, usize, usize, usize) -> bool,
    ) -> Option<(usize, Vec<u64>)> {
        let lum = |j: usize| luminance(Vec3A::from(incident[j]));
        if self.round == 0 {
            let (mut sum, mut area) = (0.0f64, 0.0f64);
            for j in self.live() {
                let omega = self.solid_angle(j) as f64;
                sum += lum(j) as f64 * omega;
                area += omega;
            }
            self.mean = (sum / area.max(f64::MIN_POSITIVE)) as f32;
        }
        let first = self.leaves.len();
        let split: Vec<usize> = self
            .live()
            .filter(|&j| {
                let c = self.cells[self.leaves[j] as usize];
                let res = self.n << c.level;
                res < RES
                    && lum(j) / (1u32 << c.level) as f32 > gamma * self.mean
                    && varies(c.face as usize, res, c.x as usize, c.y as usize)
            })
            .map(|j| self.leaves[j] as usize)
            .collect();
        if split.is_empty() {
            return None;
        }
        self.round += 1;
        for &at in &split {
            let c = self.cells[at];
            self.cells[at].child = self.cells.len() as u32;
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                self.leaves.push(self.cells.len() as u32);
                self.cells.push(Cell {
                    level: c.level + 1,
                    x: 2 * c.x + dx,
                    y: 2 * c.y + dy,
                    leaf: self.leaves.len() as u32 - 1,
                    round: self.round,
                    held: false,
                    ..c
                });
            }
        }
        self.light_splits += split.len() as u64;
        if keep_rays {
            split.iter().for_each(|&at| self.pass_ray_down(at));
        }
        let cells = &self.cells;
        let mut nodes: Vec<u64> = self
            .frags
            .iter()
            .filter(|f| cells[f.cell as usize].child != 0 && f.node != NO_NODE)
            .map(|f| f.node)
            .collect();
        nodes.sort_unstable();
        nodes.dedup();
        self.frags.retain(|f| cells[f.cell as usize].child == 0);
        Some((first, nodes))
    }

    /// Solid angle of leaf j.
    fn solid_angle(&self, j: usize) -> f32 {
        let (res, k) = self.texel(&self.cells[self.leaves[j] as usize]);
        cube::texel_solid_angle(k, res)
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

    /// The ray of each leaf from `first` on that holds none yet, through the point (a, b)
    /// of its square (`jitter(leaf)`), in the local frame, with the weight of its light as
    /// [`super::microbuffer::Texels::ray`] has it, without the cosine (the table holds
    /// it): dω/dA there times the leaf's area over its solid angle, so its mean over the
    /// leaf is 1.
    pub fn rays(
        &mut self,
        first: usize,
        jitter: impl Fn(u32) -> [f32; 2],
    ) -> Vec<(u32, Vec3, f32)> {
        self.jitters.resize(self.leaves.len(), [0.0; 2]);
        let mut out = Vec::new();
        for j in first.min(self.leaves.len())..self.leaves.len() {
            let c = self.leaves[j] as usize;
            if self.cells[c].held {
                continue;
            }
            self.jitters[j] = jitter(j as u32);
            let (local, weight) = self.ray_at(c, self.jitters[j]);
            out.push((j as u32, local, weight));
        }
        out
    }

    /// Direction and weight of cell `at`'s ray through (a, b) of its square.
    fn ray_at(&self, at: usize, [a, b]: [f32; 2]) -> (Vec3, f32) {
        let (res, k) = self.texel(&self.cells[at]);
        let corners = cube::texel_corners(k, res);
        let (u, v) = (corners[1] - corners[0], corners[3] - corners[0]);
        let local = corners[0] + u * a + v * b;
        let r = local.length();
        let weight = u.cross(v).length() / r.powi(3) / cube::texel_solid_angle(k, res);
        (local / r, weight)
    }

    /// Hands a split leaf's traced ray (and its hit, if any) to the child it passes
    /// through, which then traces none: it is uniform inside that child too.
    fn pass_ray_down(&mut self, at: usize) {
        let parent = self.cells[at];
        let [a, b] = self.jitters[parent.leaf as usize];
        let (dx, dy) = ((a >= 0.5) as usize, (b >= 0.5) as usize);
        let child = parent.child as usize + dx + 2 * dy;
        let jit = [2.0 * a - dx as f32, 2.0 * b - dy as f32];
        let ratio = self.ray_at(child, jit).1 / self.ray_at(at, [a, b]).1;
        self.cells[child].held = true;
        self.jitters.resize(self.leaves.len(), [0.0; 2]);
        self.jitters[self.cells[child].leaf as usize] = jit;
        for f in &mut self.frags {
            if f.cell as usize == at && f.node == NO_NODE {
                f.cell = child as u32;
                f.radiance *= ratio;
            }
        }
    }

    /// Splats a node seen in local direction `dir` (unit) at `depth`, subtending
    /// `solid_angle`, sending `radiance`: a square of that solid angle on the grid of the
    /// leaf under its centre, as [`super::microbuffer::MicroBuffer::splat`] lays it, onto
    /// this round's leaves only. `node` names it for re-traversal.
    pub fn splat(
        &mut self,
        dir: Vec3,
        depth: f32,
        solid_angle: f32,
        (id, node): (u64, u64),
        radiance: Vec3,
    ) {
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
                    cell: 0,
                    depth,
                    id,
                    node,
                    coverage,
                    radiance,
                },
            );
        }
    }

    /// Adds fragment `f` (its coverage of a cell at `level`) to cell `at`'s leaves of this
    /// round.
    fn cover(&mut self, at: usize, level: u8, f: Fragment) {
        let c = self.cells[at];
        if c.child == 0 {
            if c.round != self.round {
                return;
            }
            let share = 0.25f32.powi((level - c.level) as i32);
            self.frags.push(Fragment {
                cell: at as u32,
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
            cell: self.leaves[leaf as usize],
            depth,
            id,
            node: NO_NODE,
            coverage: 1.0,
            radiance,
        });
    }

    /// Incident radiance per leaf: its fragments composited front to back by depth (node
    /// number breaking ties), the open rest black (split leaves have none).
    pub fn resolve(&mut self) -> Vec<Vec3> {
        self.frags.sort_unstable_by(|a, b| {
            (a.cell, a.depth)
                .partial_cmp(&(b.cell, b.depth))
                .unwrap_or(std::cmp::Ordering::Equal)
                .then(a.id.cmp(&b.id))
        });
        let mut out = vec![Vec3::ZERO; self.leaves.len()];
        let mut open = vec![1.0f32; self.leaves.len()];
        for f in &self.frags {
            let leaf = self.cells[f.cell as usize].leaf as usize;
            let o = &mut open[leaf];
            let take = f.coverage.min(*o);
            out[leaf] += f.radiance * take;
            *o -= take;
        }
        out
    }

    /// The leaves' light spread over RES² texels a face and Haar-transformed, for the
    /// product with the BRDF's kept coefficients ([`BrdfTable::product`]: 000 §3.3's
    /// D = UW, taken as the inner product that gives one ω_o's outgoing radiance).
    pub fn faces(&self, incident: &[Vec3]) -> Vec<Vec<Vec3>> {
        let mut faces = vec![vec![Vec3::ZERO; RES * RES]; 5];
        for j in self.live() {
            let c = self.cells[self.leaves[j] as usize];
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
        faces
    }

    /// The harmonic mean over the leaves of the distance to their nearest hit (leaves
    /// that met nothing count as infinitely far; infinite when none met anything). Every
    /// leaf counts once, so the lobe, where the leaves are finest, weighs most.
    pub fn harmonic_depth(&self) -> f32 {
        let mut nearest = vec![f32::INFINITY; self.cells.len()];
        for f in &self.frags {
            let d = &mut nearest[f.cell as usize];
            *d = d.min(f.depth);
        }
        let leaves = self.live().count();
        let inverse: f32 = self
            .live()
            .map(|j| 1.0 / nearest[self.leaves[j] as usize].max(1e-6))
            .sum();
        leaves as f32 / inverse
    }
}

#[cfg(test)]
mod tests {
    use super::super::brdf_table::BrdfTable;
    use super::*;
    use crate::material::Bsdf;
    use glam::Vec3A as V;

    fn table() -> BrdfTable {
        let bsdf = Bsdf {
            diffuse: V::ZERO,
            f0: V::splat(0.9),
            f90: V::ONE,
            alpha: 0.09,
            eta: 1.5,
            ..Bsdf::lambert(V::ZERO)
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
        let total: f64 = (0..amb.leaves.len())
            .map(|j| amb.solid_angle(j) as f64)
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
                amb.splat(d, 1.0, o, (i as u64, i as u64), Vec3::ONE);
            }
            let incident = amb.resolve();
            results.push(table.product(theta, &amb.faces(&incident)));
        }
        assert_eq!(results[0], results[1]);
        let mut ones = Amb::default();
        ones.init(8, |_, _, _, _| false);
        let flat: Vec<Vec3> = vec![Vec3::ONE; ones.leaf_count()];
        let albedo = table.product(theta, &ones.faces(&flat));
        let rel = ((results[0] - albedo) / albedo).abs().max_element();
        assert!(rel < 0.02, "{} against {albedo}", results[0]);
    }

    /// (face, res, x, y) of each leaf not split, with its index.
    fn live_leaves(amb: &Amb) -> Vec<((u8, usize, u16, u16), usize)> {
        amb.live()
            .map(|j| {
                let c = amb.cells[amb.leaves[j] as usize];
                ((c.face, amb.n << c.level, c.x, c.y), j)
            })
            .collect()
    }

    /// A leaf splits exactly where the BRDF varies inside it and its luminance, halved per
    /// level, exceeds γ times the hemisphere's mean (000 §3.2's F = F_l·F_ρ), and the
    /// leaves still tile the hemisphere.
    #[test]
    fn light_importance_splits_exactly_where_the_light_is_bright() {
        let table = table();
        let theta = 0.5f32;
        let varies = |f, r, x, y| table.varies(theta, f, r, x, y);
        let mut amb = Amb::default();
        amb.init(8, |f, r, x, y| r < 8 << BRDF_LEVELS && varies(f, r, x, y));
        // Brighter toward the mirror direction's side, smoothly.
        let light = |d: Vec3| Vec3::splat(0.2 + (-8.0 * d.x).exp());
        let rays = amb.rays(0, |_| [0.5, 0.5]);
        for &(j, d, _) in &rays {
            amb.fill(j, 1.0, j as u64, light(d));
        }
        let incident = amb.resolve();
        let before = live_leaves(&amb);
        let (mut sum, mut area) = (0.0f64, 0.0f64);
        for &(_, j) in &before {
            let omega = amb.solid_angle(j) as f64;
            sum += luminance(Vec3A::from(incident[j])) as f64 * omega;
            area += omega;
        }
        let mean = (sum / area) as f32;
        // γ puts the median of the varying leaves' luminance between γ·L̄ and 2γ·L̄.
        let mut lums: Vec<f32> = before
            .iter()
            .filter(|&&((f, r, x, y), _)| varies(f as usize, r, x as usize, y as usize))
            .map(|&(_, j)| luminance(Vec3A::from(incident[j])))
            .collect();
        lums.sort_by(f32::total_cmp);
        let gamma = lums[lums.len() / 2] / (1.5 * mean);
        let (first, nodes) = amb
            .refine(&incident, (gamma, false), varies)
            .expect("bright leaves split");
        assert!(nodes.is_empty(), "hits are no nodes");
        assert_eq!(first, before.len());
        let (mut split, mut kept, mut halved) = (0, 0, 0);
        for &((face, res, x, y), j) in &before {
            let level = (res / 8).trailing_zeros();
            let lum = luminance(Vec3A::from(incident[j]));
            let brdf = res < RES && varies(face as usize, res, x as usize, y as usize);
            let expect = brdf && lum / (1 << level) as f32 > gamma * mean;
            // Bright enough at the base level but not at its own.
            halved += (brdf && !expect && lum > gamma * mean) as u32;
            let is_split = amb.cells[amb.leaves[j] as usize].child != 0;
            assert_eq!(is_split, expect, "leaf {face} {res} {x} {y}");
            if is_split {
                split += 1;
            } else {
                kept += 1;
            }
        }
        assert!(
            split > 0 && kept > 0 && halved > 0,
            "{split} split, {kept} kept, {halved} halved"
        );
        assert_eq!(amb.light_splits, split);
        let total: f64 = live_leaves(&amb)
            .iter()
            .map(|&(_, j)| amb.solid_angle(j) as f64)
            .sum();
        assert!((total - 2.0 * std::f64::consts::PI).abs() < 1e-4, "{total}");
        // The split leaves' traced hits are gone: the new leaves are open.
        let after = amb.resolve();
        assert!(after[first..].iter().all(|l| *l == Vec3::ZERO));
    }

    /// Re-splatting the nodes a split leaf recorded gives the leaves what splatting every
    /// node into the finer micro-buffer built directly gives them (NOTES-000-001 A.4).
    #[test]
    fn resplatted_nodes_fill_split_leaves_as_a_direct_build_does() {
        let table = table();
        let theta = 0.4f32;
        let varies = |f, r, x, y| table.varies(theta, f, r, x, y);
        let mut rng = crate::test_rng::TestRng::new(14);
        let finest = cube::texel_solid_angle(0, RES);
        let nodes: Vec<(Vec3, f32, f32, Vec3)> = (0..3000)
            .map(|_| {
                let d = Vec3::new(rng.f32() - 0.5, rng.f32() - 0.5, rng.f32()).normalize();
                let l = Vec3::new(rng.f32(), rng.f32(), rng.f32());
                (d, 1.0 + rng.f32(), finest * (0.5 + 3.0 * rng.f32()), l)
            })
            .collect();
        let splat = |amb: &mut Amb, i: usize| {
            let (d, depth, omega, l) = nodes[i];
            amb.splat(d, depth, omega, (i as u64, i as u64), l);
        };
        let mut amb = Amb::default();
        amb.init(8, |f, r, x, y| r < 8 << BRDF_LEVELS && varies(f, r, x, y));
        (0..nodes.len()).for_each(|i| splat(&mut amb, i));
        let mut incident = amb.resolve();
        let mut rounds = 0;
        while let Some((_, again)) = amb.refine(&incident, (0.0, false), varies) {
            again.iter().for_each(|&i| splat(&mut amb, i as usize));
            incident = amb.resolve();
            rounds += 1;
        }
        assert!(rounds >= 2, "{rounds} rounds");
        let split = |f: usize, r: usize, x: usize, y: usize| {
            let level = (r / 8).trailing_zeros() as u8;
            amb.descend(f, level, x, y)
                .is_some_and(|at| amb.cells[at].level == level && amb.cells[at].child != 0)
        };
        let mut direct = Amb::default();
        direct.init(8, split);
        (0..nodes.len()).for_each(|i| splat(&mut direct, i));
        let flat = direct.resolve();
        let progressive: std::collections::HashMap<_, _> = live_leaves(&amb).into_iter().collect();
        let leaves = live_leaves(&direct);
        assert_eq!(leaves.len(), progressive.len());
        let (mut worst, mut energy) = (0.0f32, [0.0f64; 2]);
        for (key, j) in leaves {
            let omega = direct.solid_angle(j) as f64;
            let p = incident[progressive[&key]];
            worst = worst.max((p - flat[j]).abs().max_element());
            energy[0] += (p.x + p.y + p.z) as f64 * omega;
            energy[1] += (flat[j].x + flat[j].y + flat[j].z) as f64 * omega;
        }
        assert!(worst < 0.05, "a leaf differs by {worst}");
        assert!((energy[0] / energy[1] - 1.0).abs() < 2e-3, "{energy:?}");
    }

    /// A split leaf's traced ray, handed to the child it passes through, is that child's
    /// own ray at the same point: the same direction, its light reweighted for the
    /// child's square; the other children trace theirs.
    #[test]
    fn a_split_leafs_ray_serves_the_child_it_passes_through() {
        let table = table();
        let theta = 0.7f32;
        let varies = |f, r, x, y| table.varies(theta, f, r, x, y);
        let light = |d: Vec3| Vec3::new(1.0 + d.x, 2.0 - d.y, 0.5 + d.z);
        let mut amb = Amb::default();
        amb.init(8, |f, r, x, y| r < 8 << BRDF_LEVELS && varies(f, r, x, y));
        let jitter = |j: u32| [(j % 7) as f32 / 7.0, (j % 5) as f32 / 5.0 + 0.1];
        for (j, d, w) in amb.rays(0, jitter) {
            amb.fill(j, 1.0, j as u64, light(d) * w);
        }
        let incident = amb.resolve();
        let (first, _) = amb.refine(&incident, (0.0, true), varies).unwrap();
        let fresh = amb.rays(first, jitter);
        let held: Vec<usize> = (first..amb.leaves.len())
            .filter(|&j| amb.cells[amb.leaves[j] as usize].held)
            .collect();
        assert_eq!(held.len() * 4, amb.leaves.len() - first);
        assert_eq!(fresh.len(), 3 * held.len());
        assert!(fresh.iter().all(|&(j, _, _)| !held.contains(&(j as usize))));
        let incident = amb.resolve();
        for j in held {
            let (d, w) = amb.ray_at(amb.leaves[j] as usize, amb.jitters[j]);
            let own = light(d) * w;
            assert!((incident[j] - own).abs().max_element() < 1e-5 * own.max_element());
        }
    }
}
