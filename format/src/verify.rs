//! Full structural check of an archive: every page decodes, every link is valid and used once,
//! every child box lies inside its parent's box and every triangle inside its leaf's box.

use crate::error::{FormatError, Result};
use crate::node::Node;
use crate::reader::Archive;
use crate::records::NONE;

/// What one page contributed.
#[derive(Clone, Debug, Default)]
pub struct PageReport {
    pub child_pages: Vec<u32>,
    pub leaves: u64,
    pub triangles: u64,
    /// Sum over leaves of (pages on the root-to-leaf path).
    pub path_pages_sum: u64,
    pub max_node_depth: u32,
}

fn contains(outer: &([f32; 3], [f32; 3]), inner: &([f32; 3], [f32; 3])) -> bool {
    (0..3).all(|a| outer.0[a] <= inner.0[a] && inner.1[a] <= outer.1[a])
}

impl Archive {
    /// Checks one page. `depth_base` is the node depth of the page's roots, when known.
    pub fn verify_page(&self, page: u32) -> Result<PageReport> {
        let c = self.read_page(page)?;
        let e = self.pages[page as usize];
        let err = |what: String| FormatError::BadPage {
            path: self.path().to_path_buf(),
            page,
            what,
        };
        let is_root = page == self.header.root_page;
        if is_root != (e.parent_page == NONE) || e.root_count != if is_root { 1 } else { 2 } {
            return Err(err("root/parent fields are inconsistent".into()));
        }
        if !is_root {
            let parent = self
                .pages
                .get(e.parent_page as usize)
                .ok_or_else(|| err("parent page out of range".into()))?;
            if e.level != parent.level + 1 {
                return Err(err(format!(
                    "level {} under a page of level {}",
                    e.level, parent.level
                )));
            }
        }
        if c.verts.iter().flatten().any(|x| !x.is_finite()) {
            return Err(err("non-finite vertex".into()));
        }
        let grid = e.grid();
        let mut seen = vec![false; c.nodes.len()];
        let mut report = PageReport::default();
        let mut stack: Vec<(usize, u32)> =
            (0..e.root_count as usize).rev().map(|r| (r, 0)).collect();
        let mut root_box: Option<([f32; 3], [f32; 3])> = None;
        while let Some((i, depth)) = stack.pop() {
            let node: &Node = c
                .nodes
                .get(i)
                .ok_or_else(|| err(format!("root {i} missing")))?;
            if std::mem::replace(&mut seen[i], true) {
                return Err(err(format!("node {i} reached twice")));
            }
            let b = grid.dequant_box(&node.bounds);
            if i < e.root_count as usize {
                root_box = Some(root_box.map_or(b, |r| {
                    (
                        [0, 1, 2].map(|a| r.0[a].min(b.0[a])),
                        [0, 1, 2].map(|a| r.1[a].max(b.1[a])),
                    )
                }));
            }
            report.max_node_depth = report.max_node_depth.max(depth);
            if node.is_leaf() {
                report.leaves += 1;
                report.triangles += node.link[1] as u64;
                report.path_pages_sum += e.level as u64 + 1;
                for t in &c.tris[node.link[0] as usize..(node.link[0] + node.link[1]) as usize] {
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
                let child = &self.pages[node.link[0] as usize];
                if !contains(&b, &(child.bounds_min, child.bounds_max)) {
                    return Err(err(format!(
                        "node {i}: child page {} extends outside it",
                        node.link[0]
                    )));
                }
                report.child_pages.push(node.link[0]);
            } else {
                for ch in node.link {
                    let cb = grid.dequant_box(&c.nodes[ch as usize].bounds);
                    if !contains(&b, &cb) {
                        return Err(err(format!("node {ch} extends outside its parent {i}")));
                    }
                    stack.push((ch as usize, depth + 1));
                }
            }
        }
        if let Some(i) = seen.iter().position(|s| !s) {
            return Err(err(format!(
                "node {i} is not reachable from the page roots"
            )));
        }
        if let Some(r) = root_box {
            if !contains(&r, &(e.bounds_min, e.bounds_max)) {
                return Err(err("root nodes do not cover the page bounds".into()));
            }
        }
        Ok(report)
    }

    /// Combines per-page reports: every non-root page linked exactly once, totals match.
    pub fn verify_totals(&self, reports: &[PageReport]) -> Result<()> {
        let corrupt = |what: String| FormatError::Corrupt {
            path: self.path().to_path_buf(),
            what,
        };
        let mut linked = vec![0u32; self.pages.len()];
        for r in reports {
            for &c in &r.child_pages {
                linked[c as usize] += 1;
            }
        }
        for (i, &n) in linked.iter().enumerate() {
            let want = (i as u32 != self.header.root_page) as u32;
            if n != want {
                return Err(corrupt(format!(
                    "page {i} is linked {n} times (expected {want})"
                )));
            }
        }
        let tris: u64 = reports.iter().map(|r| r.triangles).sum();
        if tris != self.header.triangles {
            return Err(corrupt(format!(
                "leaves hold {tris} triangles, header says {}",
                self.header.triangles
            )));
        }
        Ok(())
    }
}
