//! Store keys: which node, triangle and light cell a stored value belongs to.
//!
//! A leaf keeps light per triangle (its triangles may face different ways), per side (a
//! thin two-sided surface, a leaf or a banner, takes different light on each) and, on large
//! triangles, per cell of an n×n grid over the barycentrics, so a wall lit unevenly is not
//! one average; the leaf's own key gets their area-weighted mean.

use crate::paging::TriW;
use crate::trace::NO_INSTANCE;
use canopy_format::Header;
use glam::Vec3A as V;

/// Side of a triangle's light-cell grid at most (16×16 over the barycentrics).
pub const GRID: u64 = 16;
pub const CELLS: u64 = GRID * GRID;
/// Target cell size as a fraction of the scene's bounding diagonal.
pub const CELL_FRACTION: f32 = 1.0 / 128.0;

/// The key layout of one archive: per node, its own key, then `CELLS` keys for each side
/// of each of a leaf's at most `max_leaf_triangles` triangles. A prototype's nodes take
/// one such range per instance (`placed`), so copies in different light keep their own.
#[derive(Clone, Copy, Debug)]
pub struct Keys {
    stride: u64,
    /// Keys of every node of every placement.
    total: u64,
    /// The archive's node count: the distance between two instances' node numbers.
    nodes: u64,
    /// Side of the light cells on large triangles: `CELL_FRACTION` of the scene's diagonal.
    pub cell_size: f32,
}

impl Keys {
    /// None when the keys of every node of every instance do not fit in a u64.
    pub fn new(h: &Header) -> Option<Keys> {
        let stride = (2 * h.max_leaf_triangles as u64 + 1) * CELLS;
        let total = (h.instances.count as u64 + 1)
            .checked_mul(h.nodes)?
            .checked_mul(stride)?;
        Some(Keys {
            stride,
            total,
            nodes: h.nodes,
            cell_size: (V::from(h.bounds_max) - V::from(h.bounds_min)).length() * CELL_FRACTION,
        })
    }

    /// The number node `node` is keyed by as placed by `instance` (`NO_INSTANCE`: outside
    /// every instance, its own number): `node + (instance + 1) × nodes`.
    pub fn placed(&self, instance: u32, node: u64) -> u64 {
        match instance {
            NO_INSTANCE => node,
            i => node + (i as u64 + 1) * self.nodes,
        }
    }

    /// Keys in all: every node of the archive and of every instance's placement.
    pub fn count(&self) -> u64 {
        self.total
    }

    /// Keys per node: its own and its triangles' cells (a store's block).
    pub fn block(&self) -> u64 {
        self.stride
    }

    /// Key of a node's own light.
    pub fn node(&self, node: u64) -> u64 {
        node * self.stride
    }

    /// Key of a cell of the k-th triangle of a leaf, on its front or `back` side.
    pub fn tri(&self, leaf: u64, k: u32, back: bool, cell: u64) -> u64 {
        self.node(leaf) + (1 + 2 * k as u64 + back as u64) * CELLS + cell
    }

    /// Side n of a triangle's n×n cell grid, from its longest edge.
    pub fn grid(&self, tri: &TriW) -> f32 {
        (longest_edge(tri) / self.cell_size)
            .ceil()
            .clamp(1.0, GRID as f32)
    }

    /// Side of a triangle's cells: its longest edge over the grid's side.
    pub fn side(&self, tri: &TriW) -> f32 {
        longest_edge(tri) / self.grid(tri)
    }

    /// Cell of a hit inside its triangle: an n×n grid over (b1, b2).
    pub fn cell_of(&self, tri: &TriW, b: [f32; 3]) -> u64 {
        let n = self.grid(tri);
        let i = (b[1] * n).min(n - 1.0).max(0.0) as u64;
        let j = (b[2] * n).min(n - 1.0).max(0.0) as u64;
        i * GRID + j
    }

    /// The cells of a triangle with their areas: a grid square inside the triangle (i + j ≤
    /// n − 2) covers 2/n² of its area, one on the diagonal (i + j = n − 1) half that.
    pub fn cells(&self, tri: &TriW) -> impl Iterator<Item = (u64, f32)> {
        let n = self.grid(tri) as u64;
        let full = 2.0 * tri_area(tri) / (n * n) as f32;
        (0..n).flat_map(move |i| {
            (0..n - i).map(move |j| (i * GRID + j, if i + j + 1 == n { full / 2.0 } else { full }))
        })
    }
}

fn longest_edge(tri: &TriW) -> f32 {
    let p = tri.p.map(V::from);
    (p[1] - p[0])
        .length()
        .max((p[2] - p[1]).length())
        .max((p[0] - p[2]).length())
}

pub fn tri_area(tri: &TriW) -> f32 {
    let p = tri.p.map(V::from);
    0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_partition_the_triangle_and_keys_do_not_collide() {
        let mut h: Header = bytemuck::Zeroable::zeroed();
        h.bounds_max = [128.0, 0.0, 0.0];
        h.max_leaf_triangles = 8;
        h.nodes = 5;
        h.instances.count = 2;
        let k = Keys::new(&h).unwrap();
        let tri = TriW {
            p: [[0.0; 3], [5.5, 0.0, 0.0], [0.0, 3.0, 0.0]],
            material: 0,
        };
        // Longest edge √(5.5² + 3²) = 6.26 cells of side 1.
        assert_eq!(k.grid(&tri), 7.0);
        let total: f32 = k.cells(&tri).map(|(_, a)| a).sum();
        assert!((total - tri_area(&tri)).abs() < 1e-4 * total, "{total}");
        // Every hit lands in a listed cell.
        for (b1, b2) in [
            (0.0, 0.0),
            (0.99, 0.0),
            (0.0, 0.99),
            (0.5, 0.49),
            (0.3, 0.3),
        ] {
            let c = k.cell_of(&tri, [1.0 - b1 - b2, b1, b2]);
            assert!(k.cells(&tri).any(|(x, _)| x == c), "({b1}, {b2}) -> {c}");
        }
        // The last cell of the last triangle of node n stays below node n + 1's key.
        assert!(k.tri(3, 7, true, CELLS - 1) < k.node(4));
        assert!(k.tri(3, 0, false, 0) > k.node(3));
        assert!(k.tri(3, 0, false, CELLS - 1) < k.tri(3, 0, true, 0));
        assert!(k.tri(3, 0, true, CELLS - 1) < k.tri(3, 1, false, 0));
        // Each instance's nodes number after the scene's and the previous instance's.
        assert_eq!(k.placed(NO_INSTANCE, 4), 4);
        assert!(k.tri(k.placed(NO_INSTANCE, 4), 7, true, CELLS - 1) < k.node(k.placed(0, 0)));
        assert!(k.tri(k.placed(0, 4), 7, true, CELLS - 1) < k.node(k.placed(1, 0)));
        // Keys that would not fit in 64 bits are refused, not wrapped.
        h.instances.count = u32::MAX;
        h.nodes = 1 << 40;
        assert!(Keys::new(&h).is_none());
    }
}
