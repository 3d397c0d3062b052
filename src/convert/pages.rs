//! Cutting a tree into pages (treelets) and encoding them.
//!
//! A page holds the subtrees under one sibling pair (the root page: under the root) down to
//! the nodes where packing cut the tree (see `Plan::new`); those get `CHILD_PAGE` links to
//! the pages holding their children. Pages are numbered breadth-first so the top of the tree comes first;
//! nodes within a page are in depth-first order.

use super::aggregate::round_up;
use super::tree::{Kind, Tree};
use crate::import::WHITE;
use canopy_format::{Grid, NodeFlags, PageContents, Streams, Tri};
use std::collections::{HashMap, VecDeque};

pub struct PagePlan {
    pub roots: Vec<u32>,
    /// Tree nodes in page order (depth-first from the roots).
    pub nodes: Vec<u32>,
    /// (plan index, tree node) whose children are this page's roots.
    pub parent: Option<(u32, u32)>,
}

pub struct Plan {
    pub pages: Vec<PagePlan>,
    /// Per tree node: (plan index, local index); NONE for nodes outside the plan.
    place: Vec<(u32, u32)>,
    /// Per tree node: plan index of the page holding its children if it is a cut, else NONE.
    child_plan: Vec<u32>,
}

const NONE: u32 = u32::MAX;

/// FxHash-style multiplicative hasher: the vertex keys are not attacker-chosen and SipHash
/// cost a tenth of conversion time.
#[derive(Default)]
struct FastHasher(u64);
impl std::hash::Hasher for FastHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u64(b as u64);
        }
    }
    fn write_u16(&mut self, v: u16) {
        self.write_u64(v as u64);
    }
    fn write_u32(&mut self, v: u32) {
        self.write_u64(v as u64);
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (self.0.rotate_left(5) ^ v).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }
}
type FastMap<K, V> = HashMap<K, V, std::hash::BuildHasherDefault<FastHasher>>;

/// A page vertex's identity: the bits of its position, normal, two sets of texture
/// coordinates and colour, packed into five words that hash as five multiplications.
#[derive(PartialEq, Eq)]
struct VertexKey([u64; 5]);

impl VertexKey {
    fn new(p: [f32; 3], n: u32, uv: [[f32; 2]; 2], c: [u16; 4]) -> VertexKey {
        let pair = |a: u32, b: u32| a as u64 | (b as u64) << 32;
        let [x, y, z] = p.map(f32::to_bits);
        let [[u, v], [u2, v2]] = uv.map(|t| t.map(f32::to_bits));
        let c = c.iter().fold(0u64, |w, &k| w << 16 | k as u64);
        VertexKey([pair(x, y), pair(z, n), pair(u, v), pair(u2, v2), c])
    }
}

impl std::hash::Hash for VertexKey {
    fn hash<H: std::hash::Hasher>(&self, state: &mut H) {
        for w in self.0 {
            state.write_u64(w);
        }
    }
}

impl Plan {
    pub fn new(tree: &Tree, roots: Vec<u32>, max_nodes: usize) -> Plan {
        // Bottom-up packing (tree nodes are stored children first): a node's open cluster
        // grows with its children's until it would pass half a page; then the two children's
        // clusters are closed together as one page (siblings share a page), so every page
        // but the top ones holds between about max/2 and max nodes.
        let half = (max_nodes / 2).max(1) as u32;
        let mut open = vec![0u32; tree.nodes.len()];
        let mut cut = vec![false; tree.nodes.len()];
        for (i, n) in tree.nodes.iter().enumerate() {
            open[i] = match n.kind {
                Kind::Inner([l, r]) if 1 + open[l as usize] + open[r as usize] <= half => {
                    1 + open[l as usize] + open[r as usize]
                }
                Kind::Inner(_) => {
                    cut[i] = true;
                    1
                }
                _ => 1,
            };
        }
        let mut plan = Plan {
            pages: Vec::new(),
            place: vec![(NONE, NONE); tree.nodes.len()],
            child_plan: vec![NONE; tree.nodes.len()],
        };
        let mut pending = VecDeque::from([(roots, None)]);
        while let Some((roots, parent)) = pending.pop_front() {
            let idx = plan.pages.len() as u32;
            if let Some((_, n)) = parent {
                plan.child_plan[n as usize] = idx;
            }
            // Roots take local indices 0 and 1; then each root's subtree depth-first.
            let mut nodes = roots.clone();
            let mut stack = Vec::new();
            for &r in roots.iter().rev() {
                stack.push((r, true));
            }
            while let Some((n, is_root)) = stack.pop() {
                if !is_root {
                    nodes.push(n);
                }
                let local = if is_root {
                    roots.iter().position(|&x| x == n).unwrap()
                } else {
                    nodes.len() - 1
                };
                plan.place[n as usize] = (idx, local as u32);
                if let Kind::Inner([l, r]) = tree.nodes[n as usize].kind {
                    if cut[n as usize] {
                        pending.push_back((vec![l, r], Some((idx, n))));
                    } else {
                        stack.extend([(r, false), (l, false)]);
                    }
                }
            }
            plan.pages.push(PagePlan {
                roots,
                nodes,
                parent,
            });
        }
        plan
    }

    /// Where the page's parent node sits, as (plan index, local index).
    pub fn parent_of(&self, page: usize) -> Option<(u32, u32)> {
        self.pages[page].parent.map(|(_, n)| self.place[n as usize])
    }

    /// The page grid: exact union of the roots' bounds.
    pub fn grid(&self, tree: &Tree, page: usize) -> Grid {
        let mut g = Grid {
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
        };
        for &r in &self.pages[page].roots {
            let n = &tree.nodes[r as usize];
            for a in 0..3 {
                g.lo[a] = g.lo[a].min(n.lo[a]);
                g.hi[a] = g.hi[a].max(n.hi[a]);
            }
        }
        g
    }

    /// Encodes page `page`; `base` is the archive index of plan page 0. Returns the contents
    /// and the (external page, local node) links whose parents the writer must record.
    pub fn encode(
        &self,
        tree: &Tree,
        page: usize,
        base: u32,
        streams: Streams,
    ) -> (PageContents, Vec<(u32, u32)>) {
        let p = &self.pages[page];
        let grid = self.grid(tree, page);
        let mut out = PageContents::default();
        let mut externals = Vec::new();
        let mut verts: FastMap<VertexKey, u16> =
            FastMap::with_capacity_and_hasher(2 * p.nodes.len(), Default::default());
        // Quantized bounds of each node's parent, by local index (roots have none).
        let mut parent_q: Vec<Option<[u16; 6]>> = vec![None; p.nodes.len()];
        for (local, &id) in p.nodes.iter().enumerate() {
            let b = &tree.nodes[id as usize];
            let mut node = b.cluster.encode();
            node.bounds = grid.quantize_box(b.lo, b.hi, parent_q[local].as_ref());
            let c = b.cluster.mean_centroid();
            node.centroid =
                [0, 1, 2].map(|a| grid.quantize_nearest(a, c[a].clamp(b.lo[a], b.hi[a])));
            node.radius = decoded_radius(&grid, node.centroid, c, b.cluster.radius);
            match b.kind {
                Kind::Inner([l, r]) => match self.child_plan[id as usize] {
                    NONE => {
                        node.link = [self.place[l as usize].1, self.place[r as usize].1];
                        for c in node.link {
                            parent_q[c as usize] = Some(node.bounds);
                        }
                    }
                    child => {
                        node.flags |= NodeFlags::CHILD_PAGE;
                        node.link = [base + child, 0];
                    }
                },
                Kind::Instance { index } => {
                    node.flags |= NodeFlags::LEAF | NodeFlags::INSTANCE;
                    node.link = [out.instances.len() as u32, 0];
                    out.instances.push(tree.instances[index as usize]);
                }
                Kind::External { page } => {
                    node.flags |= NodeFlags::CHILD_PAGE;
                    node.link = [page, 0];
                    externals.push((page, local as u32));
                }
                Kind::Leaf { first, count } => {
                    node.flags |= NodeFlags::LEAF;
                    node.link = [out.tris.len() as u32, count];
                    for t in &tree.tris[first as usize..(first + count) as usize] {
                        let v = [0, 1, 2].map(|k| {
                            let n = if streams.normals { t.n[k] } else { 0 };
                            let uv = if streams.uvs { t.uv[k] } else { [0.0; 2] };
                            let uv2 = if streams.uvs2 { t.uv2[k] } else { [0.0; 2] };
                            let c = if streams.colours { t.colour[k] } else { WHITE };
                            *verts
                                .entry(VertexKey::new(t.p[k], n, [uv, uv2], c))
                                .or_insert_with(|| {
                                    out.verts.push(t.p[k]);
                                    if streams.normals {
                                        out.normals.push(t.n[k]);
                                    }
                                    if streams.uvs {
                                        out.uvs.push(uv);
                                    }
                                    if streams.uvs2 {
                                        out.uvs2.push(uv2);
                                    }
                                    if streams.colours {
                                        out.colours.push(c);
                                    }
                                    u16::try_from(out.verts.len() - 1)
                                        .expect("page vertex count fits u16")
                                })
                        });
                        out.tris.push(Tri {
                            v,
                            material: t.material as u16,
                        });
                    }
                }
            }
            out.nodes.push(node);
        }
        (out, externals)
    }
}

/// A radius around the decoded centroid code `q` from one of `r` around the mean `c`: the
/// triangle inequality, with the most any decoding order may move the decoded point.
fn decoded_radius(grid: &Grid, q: [u16; 3], c: [f32; 3], r: f32) -> f32 {
    let sq = |v: [f64; 3]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
    let moved = sq([0, 1, 2].map(|a| grid.exact(a, q[a]) - c[a] as f64));
    let stray = sq([0, 1, 2].map(|a| grid.margin(a)));
    round_up(r as f64 + moved + stray)
}
