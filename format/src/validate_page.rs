//! What a reader checks of a page: its page-table entry before the page is read, and its
//! decompressed contents before a node of it is used (`format/FORMAT.md`, "What a reader
//! must check").

use crate::node::{Node, NodeFlags};
use crate::records::*;
use crate::validate::{box_ok, check_instance, finite, non_negative, paged_instances, zeroed};
use crate::writer::{raw_page_len, PageContents, Streams};

/// One page-table entry (its checksum already checked), in constant time: its bytes inside
/// the page area at an aligned offset, `raw_len` what its counts imply, counts within what
/// the header allows, node numbers inside the header's total, finite ordered bounds, and its
/// place in the page tree (the root page has no parent, level 0, one root and the scene
/// bounds; every other page names another page as parent and holds 2 roots). That the
/// parent really links it, one level up, is checked when the parent's link is followed.
pub fn check_entry(h: &Header, page: u32, e: &PageEntry) -> Result<(), String> {
    let end = e.offset.checked_add(e.compressed_len as u64);
    if e.offset < 256
        || !e.offset.is_multiple_of(ALIGN)
        || end.is_none_or(|end| end > h.materials.offset)
    {
        return Err(format!(
            "bytes {}+{} not an aligned range of the page area",
            e.offset, e.compressed_len
        ));
    }
    let ph = PageHeader {
        magic: PAGE_MAGIC,
        node_count: e.node_count,
        tri_count: e.tri_count,
        vert_count: e.vert_count,
        instance_count: e.instance_count,
        has_normals: (h.features & Features::SHADING_NORMALS != 0) as u32,
        has_uvs: Streams::of(h.features).uv_sets(),
        has_colours: (h.features & Features::COLOURS != 0) as u32,
    };
    if e.node_count == 0 || e.node_count > h.page_nodes_max {
        return Err(format!(
            "{} nodes (1 to the header's {} per page)",
            e.node_count, h.page_nodes_max
        ));
    }
    // Leaves hold every triangle once, at most max_leaf_triangles each: this bounds what a
    // page can make the reader allocate.
    if e.tri_count as u64 > e.node_count as u64 * h.max_leaf_triangles as u64
        || e.vert_count > (u16::MAX as u32 + 1).min(e.tri_count.saturating_mul(3))
    {
        return Err(format!(
            "{} triangles and {} vertices in {} nodes",
            e.tri_count, e.vert_count, e.node_count
        ));
    }
    if raw_page_len(&ph, h.node_size) != e.raw_len as usize {
        return Err("page-table counts are inconsistent".into());
    }
    // Each record is named by one instance leaf of the page; pages number them
    // consecutively (consecutiveness is `verify`'s).
    let instances = match paged_instances(h) {
        true => h.instances.count as u64,
        false => 0,
    };
    if e.instance_count > e.node_count
        || e.first_instance as u64 + e.instance_count as u64 > instances
        || instances == 0 && e.first_instance != 0
    {
        return Err(format!(
            "instances {}+{} in {} nodes, beyond the archive's {instances} paged instances",
            e.first_instance, e.instance_count, e.node_count
        ));
    }
    if e.first_node
        .checked_add(e.node_count as u64)
        .is_none_or(|n| n > h.nodes)
    {
        return Err(format!(
            "nodes {}+{} beyond the archive's {}",
            e.first_node, e.node_count, h.nodes
        ));
    }
    if !box_ok(&e.bounds_min, &e.bounds_max) {
        return Err(format!(
            "bounds {:?}..{:?} are not a finite box",
            e.bounds_min, e.bounds_max
        ));
    }
    if page == h.root_page {
        if (e.parent_page, e.parent_node, e.level, e.root_count) != (NONE, NONE, 0, 1) {
            return Err(format!(
                "the root page names parent {}/{} at level {} with {} roots (expected none, level 0, one root)",
                e.parent_page as i64, e.parent_node as i64, e.level, e.root_count
            ));
        }
        if e.bounds_min != h.bounds_min || e.bounds_max != h.bounds_max {
            return Err("the root page's bounds are not the scene bounds".into());
        }
    } else if e.parent_page == NONE && h.features & Features::INSTANCES != 0 {
        // A prototype's root page: instances link it (checked at open).
        if (e.parent_node, e.level, e.root_count) != (NONE, 0, 1) {
            return Err(format!(
                "a page without parent at level {} with {} roots (a prototype's root page is level 0 with one root)",
                e.level, e.root_count
            ));
        }
    } else if e.parent_page >= h.pages.count || e.parent_page == page || e.root_count != 2 {
        return Err(format!(
            "parent page {} of {} pages, {} roots (a child page names another page and holds 2)",
            e.parent_page as i64, h.pages.count, e.root_count
        ));
    }
    Ok(())
}

/// One decoded page, in time linear in its size: every node's kind, links and values; the
/// in-page nodes form a forest under the page's roots (each non-root node the child of
/// exactly one node before it); every triangle in exactly one leaf; vertices finite.
/// `entry` reads another page's entry (checked).
pub fn check_page(
    h: &Header,
    materials: usize,
    entry: &dyn Fn(u32) -> Result<PageEntry, String>,
    page: u32,
    c: &PageContents,
) -> Result<(), String> {
    let (n, t, v) = (c.nodes.len(), c.tris.len(), c.verts.len());
    let e = &entry(page)?;
    let roots = e.root_count as usize;
    // Boxes are compared decoded: where the grid is finer than f32 near its values (or
    // flat), several codes decode alike and a min code may exceed its max code.
    let grid = e.grid();
    let boxes: Vec<_> = c
        .nodes
        .iter()
        .map(|n| grid.dequant_box(&n.bounds))
        .collect();
    let mut parents = vec![0u8; n];
    let mut covered = vec![false; t];
    let paged = paged_instances(h);
    let mut named = vec![false; c.instances.len()];
    for (i, node) in c.nodes.iter().enumerate() {
        if (0..3).any(|a| boxes[i].0[a] > boxes[i].1[a]) {
            return Err(format!("node {i}: inverted bounds {:?}", boxes[i]));
        }
        check_node(h, entry, (page, e), i, node).map_err(|what| format!("node {i}: {what}"))?;
        let [a, b] = node.link.map(|x| x as usize);
        if node.is_instance() {
            // No triangles of the page: its geometry is the prototype's record.
            if paged && std::mem::replace(&mut named[a], true) {
                return Err(format!("node {i}: instance record {a} is named twice"));
            }
        } else if node.is_leaf() {
            if a.checked_add(b).is_none_or(|end| end > t) || b == 0 {
                return Err(format!(
                    "node {i}: triangles {a}+{b} outside the page's {t}"
                ));
            }
            for slot in &mut covered[a..a + b] {
                if std::mem::replace(slot, true) {
                    return Err(format!("node {i}: a triangle belongs to two leaves"));
                }
            }
        } else if !node.has_child_page() {
            if a <= i || b <= i || a >= n || b >= n || a == b {
                return Err(format!(
                    "node {i}: children {a}, {b} not after it inside the page ({n} nodes)"
                ));
            }
            for ch in [a, b] {
                parents[ch] += 1;
                if parents[ch] > 1 {
                    return Err(format!("node {ch} is the child of two nodes"));
                }
                if !nests(&boxes[i], &boxes[ch]) {
                    return Err(format!("node {ch} extends outside its parent {i}"));
                }
            }
        }
    }
    if let Some(i) = (0..n).find(|&i| (parents[i] == 0) != (i < roots)) {
        return Err(if i < roots {
            format!("root node {i} is the child of another node")
        } else {
            format!("node {i} is not reachable from the page roots")
        });
    }
    if let Some(i) = covered.iter().position(|c| !c) {
        return Err(format!("triangle {i} is in no leaf"));
    }
    if let Some(i) = named.iter().position(|c| !c) {
        return Err(format!("instance record {i} is named by no leaf"));
    }
    for (i, r) in c.instances.iter().enumerate() {
        check_placed(h, entry, r).map_err(|what| format!("instance record {i}: {what}"))?;
    }
    for (i, tri) in c.tris.iter().enumerate() {
        if tri.v.iter().any(|&x| x as usize >= v) || tri.material as usize >= materials {
            return Err(format!(
                "triangle {i}: vertex or material index out of range"
            ));
        }
    }
    if let Some(i) = c.verts.iter().position(|p| !finite(p)) {
        return Err(format!("vertex {i} is not finite: {:?}", c.verts[i]));
    }
    for (set, uvs) in [&c.uvs, &c.uvs2].into_iter().enumerate() {
        if let Some(i) = uvs.iter().position(|uv| !finite(uv)) {
            return Err(format!(
                "texture coordinate {i} of set {set} is not finite: {:?}",
                uvs[i]
            ));
        }
    }
    Ok(())
}

/// An instance record of a page: as `check_instance`, and its prototype page a tree's root
/// page (no parent, level 0, one root, not the scene's root page).
fn check_placed(
    h: &Header,
    entry: &dyn Fn(u32) -> Result<PageEntry, String>,
    r: &InstanceRecord,
) -> Result<(), String> {
    check_instance(h, r)?;
    let p = r.prototype_page;
    let e = entry(p)?;
    if p == h.root_page || e.parent_page != NONE || e.root_count != 1 {
        return Err(format!("page {p} is not a prototype's root page"));
    }
    Ok(())
}

type Box3 = ([f32; 3], [f32; 3]);

/// The child's decoded box inside the parent's.
fn nests(parent: &Box3, child: &Box3) -> bool {
    (0..3).all(|a| parent.0[a] <= child.0[a] && child.1[a] <= parent.1[a])
}

fn check_node(
    h: &Header,
    entry: &dyn Fn(u32) -> Result<PageEntry, String>,
    (page, e): (u32, &PageEntry),
    i: usize,
    node: &Node,
) -> Result<(), String> {
    if node.flags & !NodeFlags::ALL != 0 {
        return Err(format!("unknown flags {:#x}", node.flags));
    }
    let cluster = [
        node.area,
        node.radius,
        crate::codec::f16_decode(node.curvature).abs(),
        crate::codec::f16_decode(node.ior),
    ];
    if !non_negative(&cluster) {
        return Err(format!(
            "area {}, radius {}, curvature or ior not finite and non-negative",
            node.area, node.radius
        ));
    }
    if node.reserved0 != 0 || !zeroed(&node.reserved1) {
        return Err("reserved bytes are not zero".into());
    }
    if node.coef != NONE {
        return Err(format!(
            "coefficient offset {} (there is no coefficient stream)",
            node.coef
        ));
    }
    if node.is_instance() {
        return if !node.is_leaf() || node.has_child_page() {
            Err("an instance that is not a plain leaf".into())
        } else if node.link[0] >= instance_links(h, e) || node.link[1] != 0 {
            Err(format!(
                "instance {} of {}",
                node.link[0],
                instance_links(h, e)
            ))
        } else if node.flags & NodeFlags::EMISSIVE != 0 {
            Err("an emissive instance (emitters are never instanced)".into())
        } else {
            Ok(())
        };
    }
    match (node.is_leaf(), node.has_child_page()) {
        (true, true) => Err("both a leaf and a page link".into()),
        (true, false) if node.link[1] > h.max_leaf_triangles => Err(format!(
            "{} triangles in a leaf (the header allows {})",
            node.link[1], h.max_leaf_triangles
        )),
        (false, true) => {
            let a = node.link[0];
            if a >= h.pages.count || a == h.root_page || node.link[1] != 0 {
                return Err(format!("child page {a} of {} pages", h.pages.count));
            }
            let child = entry(a)?;
            if (child.parent_page, child.parent_node) != (page, i as u32)
                || Some(child.level) != e.level.checked_add(1)
            {
                Err(format!(
                    "child page {a} does not name this node as its parent one level up"
                ))
            } else {
                Ok(())
            }
        }
        _ => Ok(()),
    }
}

/// How many instances an instance leaf of a page may name: its page's records
/// (PAGED_INSTANCES) or the instance table's.
fn instance_links(h: &Header, e: &PageEntry) -> u32 {
    match paged_instances(h) {
        true => e.instance_count,
        false => h.instances.count,
    }
}
