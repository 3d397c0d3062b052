//! Coefficient vectors coded along a node hierarchy (000 §3.1; 003 ch. 4 Alg. 1).
//!
//! A node's vector G is the weighted mean of its children's (area weights, as the pull in
//! `radiance` uses; 000's complete binary tree uses equal weights). Nodes down to the
//! bootstrap level m keep G; deeper nodes keep only their detail D = G − G(parent), so
//! G(j) = G(r) + Σ D along the path from r, j's level-m ancestor, down to j.
//!
//! 000 stores one vector H per binary node with G(left) = G + H and G(right) = G − H (the
//! sign is that of the child taken below each ancestor; NOTES-000-001 §A.3). Here a node
//! with k children stores k − 1 details and the heaviest child's is implied by
//! Σ w·D = 0; for two equal-weight children the stored detail is exactly H on the left
//! child. Details are computed from the exact G (not the truncated one, Alg. 1) and each
//! coefficient below the threshold is dropped (non-linear approximation).

use super::Coef;

/// A sparse coefficient vector: (index, value) sorted by index.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SparseVec<T>(pub Vec<(u32, T)>);

impl<T: Coef> SparseVec<T> {
    pub fn get(&self, index: u32) -> T {
        self.0
            .binary_search_by_key(&index, |&(i, _)| i)
            .map(|k| self.0[k].1)
            .unwrap_or_default()
    }

    /// self + s·other.
    pub fn add_scaled(&self, other: &SparseVec<T>, s: f32) -> SparseVec<T> {
        let (a, b) = (&self.0, &other.0);
        let (mut i, mut j) = (0, 0);
        let mut out = Vec::with_capacity(a.len().max(b.len()));
        while i < a.len() || j < b.len() {
            let ka = a.get(i).map_or(u32::MAX, |e| e.0);
            let kb = b.get(j).map_or(u32::MAX, |e| e.0);
            if ka < kb {
                out.push(a[i]);
                i += 1;
            } else if kb < ka {
                out.push((kb, b[j].1 * s));
                j += 1;
            } else {
                out.push((ka, a[i].1 + b[j].1 * s));
                i += 1;
                j += 1;
            }
        }
        SparseVec(out)
    }

    fn truncate(&self, threshold: f32) -> SparseVec<T> {
        let t2 = threshold * threshold;
        SparseVec(
            self.0
                .iter()
                .copied()
                .filter(|(_, c)| c.norm2() > 0.0 && c.norm2() >= t2)
                .collect(),
        )
    }
}

/// The shape of a hierarchy: children per node and a positive weight per node.
pub struct Shape<'a> {
    pub children: &'a [Vec<usize>],
    pub weight: &'a [f32],
    pub root: usize,
}

/// The coded hierarchy.
pub struct Coded<T> {
    /// G for nodes at depth ≤ m.
    avg: Vec<Option<SparseVec<T>>>,
    /// D for deeper nodes that are not their parent's implied (heaviest) child.
    delta: Vec<Option<SparseVec<T>>>,
    parent: Vec<Option<usize>>,
    depth: Vec<u32>,
    implied: Vec<bool>,
    children: Vec<Vec<usize>>,
    weight: Vec<f32>,
}

/// Codes the leaves' vectors `leaf(node)` up the hierarchy with bootstrap level `m`.
pub fn encode<T: Coef>(
    shape: &Shape,
    leaf: &dyn Fn(usize) -> SparseVec<T>,
    m: u32,
    threshold: f32,
) -> Coded<T> {
    let nodes = shape.children.len();
    let mut coded = Coded {
        avg: vec![None; nodes],
        delta: vec![None; nodes],
        parent: vec![None; nodes],
        depth: vec![0; nodes],
        implied: vec![false; nodes],
        children: shape.children.to_vec(),
        weight: shape.weight.to_vec(),
    };
    let g = exact_average(shape, leaf, shape.root, 0, m, threshold, &mut coded);
    coded.avg[shape.root] = Some(g.truncate(threshold));
    coded
}

/// Post-order: returns the node's exact G and stores its children's codes, so at most
/// one set of child vectors per level is alive (Alg. 1).
fn exact_average<T: Coef>(
    shape: &Shape,
    leaf: &dyn Fn(usize) -> SparseVec<T>,
    node: usize,
    depth: u32,
    m: u32,
    threshold: f32,
    coded: &mut Coded<T>,
) -> SparseVec<T> {
    coded.depth[node] = depth;
    let kids = &shape.children[node];
    if kids.is_empty() {
        return leaf(node);
    }
    let gs: Vec<SparseVec<T>> = kids
        .iter()
        .map(|&c| {
            coded.parent[c] = Some(node);
            exact_average(shape, leaf, c, depth + 1, m, threshold, coded)
        })
        .collect();
    let total: f32 = kids.iter().map(|&c| shape.weight[c]).sum();
    let mut g = SparseVec(Vec::new());
    for (&c, gc) in kids.iter().zip(&gs) {
        g = g.add_scaled(gc, shape.weight[c] / total);
    }
    let heaviest = heaviest_child(kids, shape.weight);
    for (&c, gc) in kids.iter().zip(gs) {
        if depth < m {
            coded.avg[c] = Some(gc.truncate(threshold));
        } else if c == heaviest {
            coded.implied[c] = true;
        } else {
            coded.delta[c] = Some(gc.add_scaled(&g, -1.0).truncate(threshold));
        }
    }
    g
}

/// The child whose detail is implied: the heaviest, the last of equals.
fn heaviest_child(kids: &[usize], weight: &[f32]) -> usize {
    let mut best = kids[0];
    for &c in kids {
        if weight[c] >= weight[best] {
            best = c;
        }
    }
    best
}

impl<T: Coef> Coded<T> {
    /// The node's reconstructed vector.
    pub fn vector(&self, node: usize) -> SparseVec<T> {
        if let Some(g) = &self.avg[node] {
            return g.clone();
        }
        let parent = self.parent[node].expect("a node without G has a parent");
        self.vector(parent).add_scaled(&self.detail(node), 1.0)
    }

    /// A deep node's detail: stored, or implied by its siblings' (Σ w·D = 0).
    fn detail(&self, node: usize) -> SparseVec<T> {
        if !self.implied[node] {
            return self.delta[node].clone().unwrap_or_default();
        }
        let parent = self.parent[node].expect("an implied child has a parent");
        let mut d = SparseVec(Vec::new());
        for &s in &self.children[parent] {
            if s != node {
                d = d.add_scaled(&self.detail(s), -self.weight[s] / self.weight[node]);
            }
        }
        d
    }

    /// Coefficients stored over the whole hierarchy.
    pub fn stored_coefficients(&self) -> usize {
        self.avg
            .iter()
            .chain(&self.delta)
            .flatten()
            .map(|v| v.0.len())
            .sum()
    }

    /// Bytes those coefficients take: a u32 index and the value each.
    pub fn stored_bytes(&self) -> usize {
        self.stored_coefficients() * (4 + std::mem::size_of::<T>())
    }

    pub fn depth(&self, node: usize) -> u32 {
        self.depth[node]
    }

    /// What node keeps: its average G (depth ≤ m) or its detail D (deeper, not implied);
    /// None when it keeps nothing.
    pub fn stored(&self, node: usize) -> Option<(Kept, &SparseVec<T>)> {
        match (&self.avg[node], &self.delta[node]) {
            (Some(g), _) => Some((Kept::Average, g)),
            (None, Some(d)) => Some((Kept::Detail, d)),
            _ => None,
        }
    }
}

/// The two things a node can keep.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kept {
    Average,
    Detail,
}

/// What a node kept, or may keep, in FORMAT.md's words.
fn kept_name(k: Option<Kept>) -> &'static str {
    match k {
        Some(Kept::Average) => "an average G (kind 0)",
        Some(Kept::Detail) => "a detail D (kind 1)",
        None => "nothing",
    }
}

/// Every node's vector, parents before children, from what each node kept
/// ([`Coded::stored`]): the reader's side of [`encode`], with the same bootstrap level m.
/// Fails when a node kept something its place in the tree rules out.
pub fn decode_all<T: Coef>(
    shape: &Shape,
    m: u32,
    kept: &dyn Fn(usize) -> Option<(Kept, SparseVec<T>)>,
) -> Result<Vec<SparseVec<T>>, String> {
    let mut g = vec![SparseVec(Vec::new()); shape.children.len()];
    let mut stack = vec![(shape.root, 0u32)];
    let expect = |node: usize, want: Option<Kept>| match kept(node) {
        None => Ok(SparseVec(Vec::new())),
        Some((k, v)) if Some(k) == want => Ok(v),
        Some((k, _)) => Err(format!(
            "node {node} keeps {} where its place in the tree allows {}",
            kept_name(Some(k)),
            kept_name(want)
        )),
    };
    g[shape.root] = expect(shape.root, Some(Kept::Average))?;
    while let Some((node, depth)) = stack.pop() {
        let kids = &shape.children[node];
        if kids.is_empty() {
            continue;
        }
        if depth < m {
            for &c in kids {
                g[c] = expect(c, Some(Kept::Average))?;
            }
        } else {
            let heaviest = heaviest_child(kids, shape.weight);
            let mut implied = SparseVec(Vec::new());
            for &c in kids.iter().filter(|&&c| c != heaviest) {
                let d = expect(c, Some(Kept::Detail))?;
                implied = implied.add_scaled(&d, -shape.weight[c] / shape.weight[heaviest]);
                g[c] = g[node].add_scaled(&d, 1.0);
            }
            expect(heaviest, None)?;
            g[heaviest] = g[node].add_scaled(&implied, 1.0);
        }
        stack.extend(kids.iter().map(|&c| (c, depth + 1)));
    }
    Ok(g)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// Children per node, weights, and leaf vectors.
    type Tree = (Vec<Vec<usize>>, Vec<f32>, Vec<Vec<(u32, f32)>>);

    /// A random hierarchy: node i > 0 hangs under a random earlier node.
    fn random_tree() -> impl Strategy<Value = Tree> {
        (2usize..40).prop_flat_map(|n| {
            (
                proptest::collection::vec(any::<prop::sample::Index>(), n - 1),
                proptest::collection::vec(0.1f32..10.0, n),
                proptest::collection::vec(
                    proptest::collection::vec((0u32..24, -5.0f32..5.0), 0..8),
                    n,
                ),
            )
                .prop_map(|(parents, w, vals)| {
                    let n = w.len();
                    let mut children = vec![Vec::new(); n];
                    for (i, p) in parents.iter().enumerate() {
                        children[p.index(i + 1)].push(i + 1);
                    }
                    let vals = vals
                        .into_iter()
                        .map(|mut v| {
                            v.sort_by_key(|e| e.0);
                            v.dedup_by_key(|e| e.0);
                            v
                        })
                        .collect();
                    (children, w, vals)
                })
        })
    }

    /// Exact G of every node by direct recursion.
    fn exact(
        children: &[Vec<usize>],
        w: &[f32],
        vals: &[Vec<(u32, f32)>],
        node: usize,
    ) -> Vec<f64> {
        if children[node].is_empty() {
            let mut v = vec![0.0; 24];
            for &(i, x) in &vals[node] {
                v[i as usize] = x as f64;
            }
            return v;
        }
        let total: f64 = children[node].iter().map(|&c| w[c] as f64).sum();
        let mut g = vec![0.0; 24];
        for &c in &children[node] {
            for (a, b) in g.iter_mut().zip(exact(children, w, vals, c)) {
                *a += b * w[c] as f64 / total;
            }
        }
        g
    }

    fn code(
        children: &[Vec<usize>],
        w: &[f32],
        vals: &[Vec<(u32, f32)>],
        m: u32,
        t: f32,
    ) -> Coded<f32> {
        let shape = Shape {
            children,
            weight: w,
            root: 0,
        };
        encode(&shape, &|i| SparseVec(vals[i].clone()), m, t)
    }

    /// Worst per-coefficient error the truncation allows: t at the level-m ancestor and
    /// per step below it t, or t·(W − w)/w for an implied child of weight w.
    fn bound(c: &Coded<f32>, node: usize, t: f32) -> f32 {
        if c.avg[node].is_some() {
            return t;
        }
        let p = c.parent[node].unwrap();
        let step = if c.implied[node] {
            let others: f32 = c.children[p]
                .iter()
                .filter(|&&s| s != node)
                .map(|&s| c.weight[s])
                .sum();
            t * others / c.weight[node]
        } else {
            t
        };
        bound(c, p, t) + step
    }

    proptest! {
        #[test]
        fn threshold_zero_reconstructs_every_node_for_every_m((children, w, vals) in random_tree(), m in 0u32..12) {
            let c = code(&children, &w, &vals, m, 0.0);
            for node in 0..children.len() {
                let want = exact(&children, &w, &vals, node);
                let got = c.vector(node);
                for (i, x) in want.iter().enumerate() {
                    prop_assert!((got.get(i as u32) as f64 - x).abs() < 1e-4, "node {node} coef {i}");
                }
            }
        }

        #[test]
        fn decoding_what_each_node_keeps_gives_every_vector((children, w, vals) in random_tree(), m in 0u32..6, t in 0.0f32..1.0) {
            let c = code(&children, &w, &vals, m, t);
            let shape = Shape { children: &children, weight: &w, root: 0 };
            let all = decode_all(&shape, m, &|i| c.stored(i).map(|(k, v)| (k, v.clone()))).unwrap();
            for (node, got) in all.iter().enumerate() {
                let want = c.vector(node);
                for i in 0..24 {
                    prop_assert!((got.get(i) - want.get(i)).abs() < 1e-4, "node {node} coef {i}");
                }
            }
        }

        #[test]
        fn stored_bytes_fall_as_the_threshold_grows((children, w, vals) in random_tree(), m in 0u32..6) {
            let mut last = usize::MAX;
            for t in [0.0, 0.01, 0.1, 0.3, 1.0, 3.0, 10.0] {
                let bytes = code(&children, &w, &vals, m, t).stored_bytes();
                prop_assert!(bytes <= last, "t {t}: {bytes} > {last}");
                last = bytes;
            }
            prop_assert_eq!(last, 0);
        }

        #[test]
        fn truncation_error_stays_within_the_path_bound((children, w, vals) in random_tree(), m in 0u32..6, t in 0.0f32..2.0) {
            let c = code(&children, &w, &vals, m, t);
            for node in 0..children.len() {
                let want = exact(&children, &w, &vals, node);
                let got = c.vector(node);
                let b = bound(&c, node, t) + 1e-4;
                for (i, x) in want.iter().enumerate() {
                    let e = (got.get(i as u32) as f64 - x).abs() as f32;
                    prop_assert!(e <= b, "node {node} coef {i}: error {e} > bound {b}");
                }
            }
        }
    }

    #[test]
    fn binary_equal_weights_store_h_on_the_left_child_with_000s_signs() {
        // Root 0 with children 1 (left) and 2 (right), both leaves.
        let children = vec![vec![1, 2], vec![], vec![]];
        let w = vec![2.0, 1.0, 1.0];
        let vals = vec![vec![], vec![(0, 3.0), (1, 1.0)], vec![(0, 1.0), (1, 5.0)]];
        let c = code(&children, &w, &vals, 0, 0.0);
        // G = (G− + G+)/2, H = (G− − G+)/2 (000 §3.1).
        let (g, h) = ([2.0, 3.0], [1.0, -2.0]);
        assert_eq!(
            c.stored_coefficients(),
            4,
            "root G and one H, two coefficients each"
        );
        let left = c.delta[1].as_ref().unwrap();
        assert!(c.implied[2] && c.delta[2].is_none());
        for i in 0..2 {
            assert_eq!(c.vector(0).get(i), g[i as usize]);
            assert_eq!(left.get(i), h[i as usize]);
            assert_eq!(c.vector(1).get(i), g[i as usize] + h[i as usize]);
            assert_eq!(c.vector(2).get(i), g[i as usize] - h[i as usize]);
        }
    }

    /// A very bright small emitter seen in glossy maps: leaves whose faces vary between 1
    /// and 6 with one texel at 10⁴, coded with a threshold and decoded back to texels, ring at most as
    /// far as the truncation allows: per coefficient t at a node of depth ≤ m and t more
    /// per level below (equal weights), each texel summing the 1 + 3·log₂ n coefficients
    /// of its Haar path with amplitudes at most 1. No texel is NaN, none falls below
    /// minus that bound, and threshold 0 gives every texel back.
    #[test]
    fn a_bright_spike_rings_within_the_truncation_bound() {
        let n = 8;
        // A complete binary tree of depth 3: node i has children 2i + 1, 2i + 2.
        let children: Vec<Vec<usize>> = (0..15)
            .map(|i| {
                if i < 7 {
                    vec![2 * i + 1, 2 * i + 2]
                } else {
                    Vec::new()
                }
            })
            .collect();
        let w = vec![1.0; 15];
        let mut rng = crate::test_rng::TestRng::new(5);
        let leaf_faces: Vec<Vec<f32>> = (0..15)
            .map(|_| {
                let mut f: Vec<f32> = (0..n * n).map(|_| 1.0 + 5.0 * rng.f32()).collect();
                f[(rng.f32() * (n * n) as f32) as usize % (n * n)] = 1e4;
                f
            })
            .collect();
        let leaf = |i: usize| {
            let mut f = leaf_faces[i].clone();
            super::super::haar::forward(&mut f, n);
            SparseVec(
                f.into_iter()
                    .enumerate()
                    .map(|(k, c)| (k as u32, c))
                    .collect(),
            )
        };
        let shape = Shape {
            children: &children,
            weight: &w,
            root: 0,
        };
        let stored = |t: f32| encode(&shape, &leaf, 1, t).stored_coefficients();
        assert!(stored(1.0) < stored(0.0) && stored(100.0) < stored(1.0));
        let texels = |t: f32| {
            let coded = encode(&shape, &leaf, 1, t);
            let g =
                decode_all(&shape, 1, &|i| coded.stored(i).map(|(k, v)| (k, v.clone()))).unwrap();
            g.into_iter()
                .map(|v| {
                    let mut f = vec![0.0; n * n];
                    for (k, c) in v.0 {
                        f[k as usize] = c;
                    }
                    super::super::haar::inverse(&mut f, n);
                    f
                })
                .collect::<Vec<_>>()
        };
        let exact = texels(0.0);
        for i in 7..15 {
            for (a, b) in exact[i].iter().zip(&leaf_faces[i]) {
                assert!((a - b).abs() < 1e-2 * b, "leaf {i}: {a} for {b}");
            }
        }
        let path = 1.0 + 3.0 * (n as f32).log2();
        for t in [1.0, 10.0, 100.0] {
            let got = texels(t);
            for (node, (g, e)) in got.iter().zip(&exact).enumerate() {
                let depth = (node + 1).ilog2() as f32;
                let bound = t * depth.max(1.0) * path + 1e-2;
                for (a, b) in g.iter().zip(e) {
                    assert!(
                        a.is_finite() && (a - b).abs() <= bound,
                        "t {t}, node {node}: {a} for {b}, bound {bound}"
                    );
                    assert!(*a >= -bound);
                }
            }
        }
    }
}
