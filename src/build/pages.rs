//! Cutting a tree into pages (treelets) and encoding them.
//!
//! A page holds the subtrees under one sibling pair (the root page: under the root) down to
//! the nodes where packing cut the tree (see `Plan::new`); those get `CHILD_PAGE` links to
//! the pages holding their children. Pages are numbered breadth-first so the top of the tree comes first;
//! nodes within a page are in depth-first order.

use super::tree::{Kind, Tree};
use canopy_format::codec::oct_encode;
use canopy_format::{Grid, NodeFlags, PageContents, Tri};
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
    /// For each tree node in a page: (plan index, local index).
    place: HashMap<u32, (u32, u32)>,
    /// Cut nodes: tree node -> plan index of the page holding its children.
    child_plan: HashMap<u32, u32>,
}

impl Plan {
    pub fn new(tree: &Tree, roots: Vec<u32>, max_nodes: usize) -> Plan {
        // Bottom-up packing (tree nodes are stored children first): a node's open cluster
        // grows with its children's until it would pass half a page; then the two children's
        // clusters are closed together as one page (siblings share a page), so every page
        // but the top ones holds between about max/2 and max nodes.
        let half = (max_nodes / 2).max(1) as u32;
        let mut open = vec![0u32; tree.nodes.len()];
        let mut cut = std::collections::HashSet::new();
        for (i, n) in tree.nodes.iter().enumerate() {
            open[i] = match n.kind {
                Kind::Inner([l, r]) if 1 + open[l as usize] + open[r as usize] <= half => {
                    1 + open[l as usize] + open[r as usize]
                }
                Kind::Inner(_) => {
                    cut.insert(i as u32);
                    1
                }
                _ => 1,
            };
        }
        let mut plan = Plan {
            pages: Vec::new(),
            place: HashMap::new(),
            child_plan: HashMap::new(),
        };
        let mut pending = VecDeque::from([(roots, None)]);
        while let Some((roots, parent)) = pending.pop_front() {
            let idx = plan.pages.len() as u32;
            if let Some((_, n)) = parent {
                plan.child_plan.insert(n, idx);
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
                plan.place.insert(
                    n,
                    (
                        idx,
                        if is_root {
                            roots.iter().position(|&x| x == n).unwrap() as u32
                        } else {
                            nodes.len() as u32 - 1
                        },
                    ),
                );
                if let Kind::Inner([l, r]) = tree.nodes[n as usize].kind {
                    if cut.contains(&n) {
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
        self.pages[page].parent.map(|(_, n)| self.place[&n])
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
        normals: bool,
    ) -> (PageContents, Vec<(u32, u32)>) {
        let p = &self.pages[page];
        let grid = self.grid(tree, page);
        let mut out = PageContents::default();
        let mut externals = Vec::new();
        let mut verts: HashMap<([u32; 3], u32), u16> = HashMap::new();
        let mut parent_q: HashMap<u32, [u16; 6]> = HashMap::new();
        for (local, &id) in p.nodes.iter().enumerate() {
            let b = &tree.nodes[id as usize];
            let mut node = b.cluster.encode();
            node.bounds = grid.quantize_box(b.lo, b.hi, parent_q.get(&id));
            let c = b.cluster.mean_centroid();
            node.centroid =
                [0, 1, 2].map(|a| grid.quantize_nearest(a, c[a].clamp(b.lo[a], b.hi[a])));
            match b.kind {
                Kind::Inner([l, r]) => match self.child_plan.get(&id) {
                    Some(&child) => {
                        node.flags |= NodeFlags::CHILD_PAGE;
                        node.link = [base + child, 0];
                    }
                    None => {
                        node.link = [self.place[&l].1, self.place[&r].1];
                        parent_q.insert(l, node.bounds);
                        parent_q.insert(r, node.bounds);
                    }
                },
                Kind::External { page } => {
                    node.flags |= NodeFlags::CHILD_PAGE;
                    node.link = [page, 0];
                    externals.push((page, local as u32));
                }
                Kind::Leaf { first, count } => {
                    node.flags |= NodeFlags::LEAF;
                    node.link = [out.tris.len() as u32, count];
                    for t in &tree.tris[first as usize..(first + count) as usize] {
                        let mut v = [0u16; 3];
                        for k in 0..3 {
                            let key = (t.p[k].map(f32::to_bits), if normals { t.n[k] } else { 0 });
                            v[k] = *verts.entry(key).or_insert_with(|| {
                                out.verts.push(t.p[k]);
                                if normals {
                                    out.normals.push(if t.n[k] == 0 {
                                        oct_encode([0.0, 0.0, 1.0])
                                    } else {
                                        t.n[k]
                                    });
                                }
                                u16::try_from(out.verts.len() - 1)
                                    .expect("page vertex count fits u16")
                            });
                        }
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
