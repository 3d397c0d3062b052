//! Patches: a triangle too large to carry one baked value is split by midpoints into 4^k
//! congruent patches, each baked on its own, their means pulled up a pyramid (level j holds
//! 4^j patches; the children of patch i are 4i..4i+3; level 0 is the triangle). PBGI's near
//! field reads the finest patch under each texel's ray.

use crate::sampler::Hash;
use canopy_format::bake::MAX_PATCH_DEPTH;
use glam::Vec3A as V;

/// Subdivision depth giving patches of area at most `a_max` (capped).
pub fn depth(area: f32, a_max: f32) -> u32 {
    let mut k = 0;
    let mut a = area;
    while a > a_max && k < MAX_PATCH_DEPTH {
        a *= 0.25;
        k += 1;
    }
    k
}

/// The four children of a triangle: three corners and the middle, all wound as the parent.
pub fn children(t: [V; 3]) -> [[V; 3]; 4] {
    let [a, b, c] = t;
    let (ab, bc, ca) = ((a + b) * 0.5, (b + c) * 0.5, (c + a) * 0.5);
    [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
}

/// Patch `i` of level `j`.
pub fn patch(t: [V; 3], j: u32, i: usize) -> [V; 3] {
    (0..j)
        .rev()
        .fold(t, |t, level| children(t)[(i >> (2 * level)) & 3])
}

/// Which child of a triangle holds the point of barycentrics `b`, and its barycentrics
/// in that child (the inverse of `children`'s midpoint split).
pub fn locate(b: [f32; 3]) -> (usize, [f32; 3]) {
    let [b0, b1, b2] = b;
    if b0 >= 0.5 {
        (0, [2.0 * b0 - 1.0, 2.0 * b1, 2.0 * b2])
    } else if b1 >= 0.5 {
        (1, [2.0 * b0, 2.0 * b1 - 1.0, 2.0 * b2])
    } else if b2 >= 0.5 {
        (2, [2.0 * b0, 2.0 * b1, 2.0 * b2 - 1.0])
    } else {
        (3, [1.0 - 2.0 * b2, 1.0 - 2.0 * b0, 1.0 - 2.0 * b1])
    }
}

/// Where level `j`'s patches start in a pyramid (levels 0..=k in order).
pub fn level_start(j: u32) -> usize {
    ((1usize << (2 * j)) - 1) / 3
}

/// The pyramid of levels 0..=k from the finest level's values (4^k of them).
pub fn pyramid(finest: &[V], k: u32) -> Vec<[f32; 3]> {
    let mut levels = vec![finest.to_vec()];
    for _ in 0..k {
        let below = levels.last().expect("a level");
        let up: Vec<V> = below
            .chunks(4)
            .map(|c| c.iter().sum::<V>() * 0.25)
            .collect();
        levels.push(up);
    }
    levels.iter().rev().flatten().map(|v| (*v).into()).collect()
}

/// The barycentrics (weights of vertices 0, 1, 2) of a point `q` in triangle `v`'s plane.
pub fn barycentrics(v: [V; 3], q: V) -> [f32; 3] {
    let (e1, e2, d) = (v[1] - v[0], v[2] - v[0], q - v[0]);
    let c = e1.cross(e2);
    let inv = 1.0 / c.length_squared();
    let (b1, b2) = (d.cross(e2).dot(c) * inv, e1.cross(d).dot(c) * inv);
    [1.0 - b1 - b2, b1, b2]
}

/// A uniform point of triangle `tri` (the unit square folded onto it).
pub fn uniform_point(tri: [V; 3], rng: &mut Hash) -> V {
    let (mut a, mut b) = (rng.f32(), rng.f32());
    if a + b > 1.0 {
        (a, b) = (1.0 - a, 1.0 - b);
    }
    tri[0] + (tri[1] - tri[0]) * a + (tri[2] - tri[0]) * b
}

/// The longer of a patch's two sides from vertex 0: the footprint its texture reads span.
pub fn side(tri: [V; 3]) -> f32 {
    (tri[1] - tri[0]).length().max((tri[2] - tri[0]).length())
}

#[cfg(test)]
mod tests {
    use super::*;
    use canopy_format::bake::pyramid_len;

    /// A scalene triangle, not in a coordinate plane.
    const TRIANGLE: [V; 3] = [
        V::new(0.0, 0.0, 0.0),
        V::new(4.0, 0.0, 1.0),
        V::new(1.0, 3.0, 0.0),
    ];

    #[test]
    fn patches_tile_their_triangle_and_keep_its_winding() {
        let t = TRIANGLE;
        let normal = (t[1] - t[0]).cross(t[2] - t[0]);
        for j in 0..=3 {
            let mut area = 0.0;
            let mut centroid = V::ZERO;
            for i in 0..1 << (2 * j) {
                let p = patch(t, j, i);
                let n = (p[1] - p[0]).cross(p[2] - p[0]);
                assert!(n.dot(normal) > 0.0, "level {j} patch {i} flipped");
                area += 0.5 * n.length();
                centroid += (p[0] + p[1] + p[2]) / 3.0 * (0.5 * n.length());
            }
            let whole = 0.5 * normal.length();
            assert!((area - whole).abs() < 1e-4 * whole, "level {j}: {area}");
            let c = (t[0] + t[1] + t[2]) / 3.0;
            assert!((centroid / area - c).length() < 1e-4, "level {j}");
        }
        // A child of patch i at level j is a patch of i's children.
        let p = patch(t, 2, 9);
        assert_eq!(children(p)[3], patch(t, 3, 4 * 9 + 3));
    }

    #[test]
    fn locate_finds_the_patch_that_holds_a_point() {
        let t = TRIANGLE;
        let mut rng = crate::test_rng::TestRng::new(3);
        for _ in 0..200 {
            let (mut u, mut v) = (rng.f32(), rng.f32());
            if u + v > 1.0 {
                (u, v) = (1.0 - u, 1.0 - v);
            }
            let b = [1.0 - u - v, u, v];
            let q = t[0] * b[0] + t[1] * b[1] + t[2] * b[2];
            let (mut bb, mut index, mut tri) = (b, 0, t);
            for _ in 0..4 {
                let (c, next) = locate(bb);
                (bb, index, tri) = (next, 4 * index + c, children(tri)[c]);
                let back = tri[0] * bb[0] + tri[1] * bb[1] + tri[2] * bb[2];
                assert!((back - q).length() < 1e-4, "{back} vs {q}");
                assert!(
                    bb.iter().all(|&x| x >= -1e-5) && (bb.iter().sum::<f32>() - 1.0).abs() < 1e-4
                );
            }
            assert_eq!(patch(t, 4, index), tri);
        }
    }

    #[test]
    fn each_pyramid_value_is_the_mean_of_its_children() {
        let k = 3;
        let finest: Vec<V> = (0..64).map(|i| V::splat(i as f32)).collect();
        let p = pyramid(&finest, k);
        assert_eq!(p.len(), pyramid_len(k) as usize);
        for j in 0..k {
            for i in 0..1usize << (2 * j) {
                let parent = V::from(p[level_start(j) + i]);
                let kids: V = (0..4)
                    .map(|c| V::from(p[level_start(j + 1) + 4 * i + c]))
                    .sum();
                assert!((parent - kids * 0.25).length() < 1e-5);
            }
        }
        assert_eq!(V::from(p[level_start(k) + 17]), finest[17]);
        assert_eq!(level_start(k + 1), p.len());
        assert_eq!(pyramid(&finest[..1], 0), vec![[0.0; 3]]);
        assert_eq!(depth(1.0, 1.0), 0);
        assert_eq!(depth(1.01, 1.0), 1);
        assert_eq!(depth(1e9, 1.0), MAX_PATCH_DEPTH);
    }
}
