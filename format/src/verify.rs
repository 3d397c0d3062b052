//! Full check of an archive, beyond what every read checks (`validate`): every triangle inside
//! its leaf's box, every child page inside its node's box, each node's flags what its contents
//! imply, and the header's depth, bounds, triangle total and features what the pages hold.

use crate::error::{FormatError, Result};
use crate::node::NodeFlags;
use crate::reader::Archive;
use crate::records::Features;

/// Flags an inner node takes from its children.
const AGGREGATE: u8 = NodeFlags::EMISSIVE | NodeFlags::GLOSSY | NodeFlags::TRANSMISSIVE;

/// What one page contributed.
#[derive(Clone, Debug, Default)]
pub struct PageReport {
    /// Child pages, with the in-page depth and the flags of the node that links each.
    pub child_pages: Vec<(u32, u32, u8)>,
    pub leaves: u64,
    pub triangles: u64,
    /// Sum over leaves of (pages on the root-to-leaf path).
    pub path_pages_sum: u64,
    pub max_node_depth: u32,
    /// Union of the roots' aggregate flags.
    pub root_flags: u8,
    /// Instance leaves: (instance, its prototype page, the leaf's aggregate flags).
    pub instance_leaves: Vec<(u32, u32, u8)>,
    /// Exact bounds of the page's vertices (empty box for a page without triangles).
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

fn contains(outer: &([f32; 3], [f32; 3]), inner: &([f32; 3], [f32; 3])) -> bool {
    (0..3).all(|a| outer.0[a] <= inner.0[a] && inner.1[a] <= outer.1[a])
}

impl Archive {
    /// Checks one page (its structure was checked when it was read).
    pub fn verify_page(&self, page: u32) -> Result<PageReport> {
        let c = self.read_page(page)?;
        let e = self.entry(page)?;
        let err = |what: String| FormatError::BadPage {
            path: self.path().to_path_buf(),
            page,
            what,
        };
        let grid = e.grid();
        let mut report = PageReport {
            lo: [f32::INFINITY; 3],
            hi: [f32::NEG_INFINITY; 3],
            ..Default::default()
        };
        for p in &c.verts {
            report.lo = [0, 1, 2].map(|a| report.lo[a].min(p[a]));
            report.hi = [0, 1, 2].map(|a| report.hi[a].max(p[a]));
        }
        let roots = e.root_count as usize;
        let mut depth = vec![0u32; c.nodes.len()];
        let mut root_box: Option<([f32; 3], [f32; 3])> = None;
        // Children follow their parents (checked at read), so one forward pass sees every
        // node after its parent.
        for (i, node) in c.nodes.iter().enumerate() {
            let b = grid.dequant_box(&node.bounds);
            let d = depth[i];
            if i < roots {
                report.root_flags |= node.flags & AGGREGATE;
                root_box = Some(root_box.map_or(b, |r| {
                    (
                        [0, 1, 2].map(|a| r.0[a].min(b.0[a])),
                        [0, 1, 2].map(|a| r.1[a].max(b.1[a])),
                    )
                }));
            }
            report.max_node_depth = report.max_node_depth.max(d);
            if node.is_instance() {
                let (number, inst) = match crate::validate::paged_instances(&self.header) {
                    true => (
                        e.first_instance + node.link[0],
                        &c.instances[node.link[0] as usize],
                    ),
                    false => (node.link[0], &self.instances[node.link[0] as usize]),
                };
                let proto = self.entry(inst.prototype_page)?;
                let world = inst.world_box(proto.bounds_min, proto.bounds_max);
                if !contains(&b, &world) {
                    return Err(err(format!(
                        "instance leaf {i}: its prototype's box {world:?} is outside it"
                    )));
                }
                report
                    .instance_leaves
                    .push((number, inst.prototype_page, node.flags & AGGREGATE));
                report.lo = [0, 1, 2].map(|a| report.lo[a].min(world.0[a]));
                report.hi = [0, 1, 2].map(|a| report.hi[a].max(world.1[a]));
            } else if node.is_leaf() {
                report.leaves += 1;
                report.triangles += node.link[1] as u64;
                report.path_pages_sum += e.level as u64 + 1;
                let tris = &c.tris[node.link[0] as usize..(node.link[0] + node.link[1]) as usize];
                let emits = tris.iter().any(|t| {
                    self.materials[t.material as usize]
                        .emission
                        .iter()
                        .any(|&x| x > 0.0)
                });
                if emits != (node.flags & NodeFlags::EMISSIVE != 0) {
                    return Err(err(format!(
                        "leaf {i}: its emissive flag disagrees with its triangles' materials"
                    )));
                }
                for t in tris {
                    for &v in &t.v {
                        let p = c.verts[v as usize];
                        if !contains(&b, &(p, p)) {
                            return Err(err(format!(
                                "leaf {i}: vertex {p:?} outside its bounds {b:?}"
                            )));
                        }
                    }
                }
            } else if node.has_child_page() {
                let child = self.entry(node.link[0])?;
                if !contains(&b, &(child.bounds_min, child.bounds_max)) {
                    return Err(err(format!(
                        "node {i}: child page {} extends outside it",
                        node.link[0]
                    )));
                }
                report
                    .child_pages
                    .push((node.link[0], d, node.flags & AGGREGATE));
            } else {
                let [l, r] = node.link.map(|x| x as usize);
                if (c.nodes[l].flags | c.nodes[r].flags) & AGGREGATE != node.flags & AGGREGATE {
                    return Err(err(format!(
                        "node {i}: its flags are not the union of its children's"
                    )));
                }
                depth[l] = d + 1;
                depth[r] = d + 1;
            }
        }
        if let Some(r) = root_box {
            if !contains(&r, &(e.bounds_min, e.bounds_max)) {
                return Err(err("root nodes do not cover the page bounds".into()));
            }
        }
        Ok(report)
    }

    /// Combines per-page reports: every non-root page linked exactly once by a node with its
    /// roots' flags, nodes numbered consecutively in table order, and the header's nodes,
    /// vertices, triangles, depth, bounds and features what pages hold.
    pub fn verify_totals(&self, reports: &[PageReport]) -> Result<()> {
        let corrupt = |what: String| FormatError::Corrupt {
            path: self.path().to_path_buf(),
            what,
        };
        let h = &self.header;
        let entries = self.entries()?;
        let (mut nodes, mut vertices, mut instances) = (0u64, 0u64, 0u64);
        for (i, e) in entries.iter().enumerate() {
            if e.first_node != nodes {
                return Err(corrupt(format!(
                    "page {i}: first node {}, expected {nodes} (pages number nodes consecutively)",
                    e.first_node
                )));
            }
            if e.first_instance as u64 != instances {
                return Err(corrupt(format!(
                    "page {i}: first instance {}, expected {instances} (pages number instances consecutively)",
                    e.first_instance
                )));
            }
            nodes += e.node_count as u64;
            instances += e.instance_count as u64;
            vertices += e.vert_count as u64;
        }
        if crate::validate::paged_instances(h) && instances != h.instances.count as u64 {
            return Err(corrupt(format!(
                "the pages hold {instances} instance records, the header says {}",
                h.instances.count
            )));
        }
        if (nodes, vertices) != (h.nodes, h.vertices) {
            return Err(corrupt(format!(
                "the page table holds {nodes} nodes and {vertices} vertices, header says {} and {}",
                h.nodes, h.vertices
            )));
        }
        let mut linked = vec![0u32; entries.len()];
        let mut prototype = vec![false; entries.len()];
        for r in reports {
            for &(inst, p, flags) in &r.instance_leaves {
                let p = p as usize;
                prototype[p] = true;
                if reports[p].root_flags != flags {
                    return Err(corrupt(format!(
                        "instance {inst}: its leaf's flags disagree with prototype page {p}"
                    )));
                }
            }
            for &(c, _, flags) in &r.child_pages {
                linked[c as usize] += 1;
                if reports[c as usize].root_flags != flags {
                    return Err(corrupt(format!(
                        "page {c}: its roots' flags disagree with the node that links it"
                    )));
                }
            }
        }
        for (i, &n) in linked.iter().enumerate() {
            let want = (i as u32 != h.root_page && !prototype[i]) as u32;
            if n != want {
                return Err(corrupt(format!(
                    "page {i} is linked {n} times (expected {want})"
                )));
            }
        }
        let tris: u64 = reports.iter().map(|r| r.triangles).sum();
        if tris != h.triangles {
            return Err(corrupt(format!(
                "leaves hold {tris} triangles, header says {}",
                h.triangles
            )));
        }
        // Depth of each page's roots: parents sit at lower levels, so visit by level.
        let mut order: Vec<usize> = (0..entries.len()).collect();
        order.sort_by_key(|&i| entries[i].level);
        let mut root_depth = vec![0u32; entries.len()];
        let mut depth = 0;
        for &p in &order {
            for &(c, d, _) in &reports[p].child_pages {
                root_depth[c as usize] = root_depth[p] + d + 1;
            }
            depth = depth.max(root_depth[p] + reports[p].max_node_depth);
        }
        if depth != h.depth {
            return Err(corrupt(format!(
                "the tree is {depth} levels deep, header says {}",
                h.depth
            )));
        }
        // The scene's tree: prototypes' pages hold object-space vertices, and instance
        // leaves count by their boxes (in their page's report).
        let mut in_scene = vec![false; entries.len()];
        in_scene[h.root_page as usize] = true;
        for &p in &order {
            for &(c, _, _) in &reports[p].child_pages {
                in_scene[c as usize] = in_scene[p];
            }
        }
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for r in reports
            .iter()
            .zip(&in_scene)
            .filter(|(_, &s)| s)
            .map(|(r, _)| r)
        {
            for a in 0..3 {
                lo[a] = lo[a].min(r.lo[a]);
                hi[a] = hi[a].max(r.hi[a]);
            }
        }
        if (lo, hi) != (h.bounds_min, h.bounds_max) {
            return Err(corrupt(format!(
                "vertices span {lo:?}..{hi:?}, header says {:?}..{:?}",
                h.bounds_min, h.bounds_max
            )));
        }
        let scene = reports[h.root_page as usize].root_flags;
        for (flag, feature, name) in [
            (NodeFlags::EMISSIVE, Features::EMITTERS, "emitters"),
            (NodeFlags::GLOSSY, Features::GLOSSY, "glossy"),
            (
                NodeFlags::TRANSMISSIVE,
                Features::TRANSMISSIVE,
                "transmissive",
            ),
        ] {
            if (scene & flag != 0) != (h.features & feature != 0) {
                return Err(corrupt(format!(
                    "the {name} feature disagrees with the root node"
                )));
            }
        }
        Ok(())
    }
}
