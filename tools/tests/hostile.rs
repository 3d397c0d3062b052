//! Archives whose checksums are all valid but whose contents lie: each is refused with an
//! error naming what is wrong, by open, by `--verify`, or by the render (never a panic or a
//! hang). Each case here passed every check, or panicked or hung, before the reader
//! validated structure.

use canopy::render::render;
use canopy_format::InstanceRecord;
use canopy_format::{Archive, Node, NodeFlags, NoteRecord};
use canopy_tools::fuzz::{self, paged, Parts};
use std::path::Path;

/// The glb seed (emitter over glass, normals) converted with 3-node pages: several pages,
/// child-page links.
fn seed(dir: &Path) -> Parts {
    let archives = fuzz::seed_archives(dir).unwrap();
    archives.into_iter().next().unwrap().0
}

/// The Stanford bunny (scenes/bunny.ply, 70 K triangles) with a camera and a lamp, in
/// 512-node pages: pages with deep in-page trees and full leaves.
fn bunny(dir: &Path) -> Parts {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let scene = dir.join("scene.toml");
    std::fs::write(&scene, "[[camera]]\nposition = [0.0, 0.1, 0.4]\nlook_at = [0.0, 0.1, 0.0]\n\n[[light]]\ntype = \"point\"\nposition = [0.0, 0.3, 0.3]\nintensity = 1.0\n").unwrap();
    let out = dir.join("bunny.canopy");
    let mut o =
        canopy::convert::ConvertOptions::new(vec![root.join("scenes/bunny.ply")], out.clone());
    o.scene = Some(scene);
    canopy::convert::convert(&o).unwrap();
    Parts::read(&out).unwrap()
}

fn node(p: &Parts, page: usize, i: usize) -> Node {
    bytemuck::pod_read_unaligned(&p.pages[page][32 + i * 128..32 + (i + 1) * 128])
}

fn set_node(p: &mut Parts, page: usize, i: usize, n: &Node) {
    p.pages[page][32 + i * 128..32 + (i + 1) * 128].copy_from_slice(bytemuck::bytes_of(n));
}

/// Open, verify every page and render with both integrators (the path tracer alone on an
/// instanced archive): the first error met.
fn first_error(path: &Path, dir: &Path) -> Option<String> {
    let a = match Archive::open(path) {
        Ok(a) => a,
        Err(e) => return Some(format!("{e:#}")),
    };
    let mut s = match canopy::inspect::summarize(&a) {
        Ok(s) => s,
        Err(e) => return Some(format!("{e:#}")),
    };
    if let Err(e) = canopy::inspect::verify(&a, &mut s, false) {
        return Some(format!("{e:#}"));
    }
    let usable = fuzz::integrators().into_iter();
    for i in usable.filter(|i| i.check_archive(&a).is_ok()) {
        if let Err(e) = render(&fuzz::tiny_render(path, dir, i)) {
            return Some(format!("{e:#}"));
        }
    }
    None
}

/// A page whose first node is an inner node in that page (not a leaf, not a page link).
fn inner_page(p: &Parts) -> usize {
    (0..p.pages.len())
        .find(|&i| {
            let n = node(p, i, 0);
            !n.is_leaf() && !n.has_child_page()
        })
        .expect("a page with an in-page inner node")
}

/// A lie's edit (each lie: what it is, the edit, what the error must say).
type Edit = Box<dyn Fn(&mut Parts)>;

/// Lies in the header, the page table and the material and camera tables.
fn table_lies(base: &Parts) -> Vec<(&'static str, Edit, &'static str)> {
    let root = base.header.root_page as usize;
    vec![
        (
            "inverted page bounds",
            Box::new(|p| p.entries[0].bounds_min[0] = p.entries[0].bounds_max[0] + 1.0),
            "not a finite box",
        ),
        (
            "NaN page bounds",
            Box::new(|p| p.entries[0].bounds_max[1] = f32::NAN),
            "not a finite box",
        ),
        (
            "infinite scene bounds",
            Box::new(|p| p.header.bounds_min[2] = f32::NEG_INFINITY),
            "not a finite box",
        ),
        (
            "root page with a parent",
            Box::new(move |p| p.entries[root].parent_page = 0),
            "root page names parent",
        ),
        (
            "root page at level 1",
            Box::new(move |p| p.entries[root].level = 1),
            "root page",
        ),
        (
            "root page with a parent node",
            Box::new(move |p| p.entries[root].parent_node = 0),
            "root page",
        ),
        (
            "child page one level off",
            Box::new(move |p| {
                let c = (0..p.entries.len()).find(|&i| i != root).unwrap();
                p.entries[c].level += 1;
            }),
            "level",
        ),
        (
            "version 0",
            Box::new(|p| p.header.version_major = 0),
            "version 0",
        ),
        (
            "header depth",
            Box::new(|p| p.header.depth += 1),
            "levels deep",
        ),
        (
            "header bounds not the vertices'",
            Box::new(move |p| {
                p.header.bounds_max[0] += 1.0;
                p.entries[root].bounds_max[0] += 1.0;
            }),
            "vertices span",
        ),
        (
            "input triangles",
            Box::new(|p| p.header.input_triangles += 1),
            "input triangles",
        ),
        ("vertices", Box::new(|p| p.header.vertices += 1), "vertices"),
        (
            "unknown required feature bit",
            Box::new(|p| p.header.features |= 1 << 40),
            "required feature bits 0x10000000000 unknown",
        ),
        (
            "emitters feature cleared",
            Box::new(|p| p.header.features &= !canopy_format::Features::EMITTERS),
            "emitters feature",
        ),
        (
            "max leaf 0",
            Box::new(|p| p.header.max_leaf_triangles = 0),
            "triangles per leaf",
        ),
        (
            "page nodes max 1",
            Box::new(|p| p.header.page_nodes_max = 1),
            "nodes",
        ),
        (
            "node total far past what the pages hold",
            Box::new(|p| p.header.nodes = 1 << 40),
            "nodes in",
        ),
        (
            "node total below the page count",
            Box::new(|p| p.header.nodes = p.header.pages.count as u64 - 1),
            "nodes in",
        ),
        (
            "a note that is not UTF-8",
            Box::new(|p| p.notes.push(NoteRecord { text: [0xFF; 256] })),
            "is not UTF-8",
        ),
        (
            "a note with bytes after its end",
            Box::new(|p| {
                let mut n = NoteRecord::new("a");
                n.text[2] = b'b';
                p.notes.push(n);
            }),
            "after its end",
        ),
        (
            "instance records in an archive without instances",
            Box::new(|p| p.entries[0].first_instance = 1),
            "paged instances",
        ),
        (
            "material NaN",
            Box::new(|p| p.materials[0].roughness = f32::NAN),
            "material 0",
        ),
        (
            "material base colour 2",
            Box::new(|p| p.materials[0].base_color[1] = 2.0),
            "material 0",
        ),
        (
            "camera NaN",
            Box::new(|p| p.cameras[0].to_world[4] = f32::NAN),
            "camera 0",
        ),
        (
            "camera fov 0",
            Box::new(|p| p.cameras[0].yfov = 0.0),
            "camera 0",
        ),
    ]
}

/// Lies in the nodes and triangles of a page that holds a leaf.
fn node_lies(base: &Parts) -> Vec<(&'static str, Edit, &'static str)> {
    let leaf_page = (0..base.pages.len())
        .find(|&i| (0..base.entries[i].node_count as usize).any(|k| node(base, i, k).is_leaf()))
        .unwrap();
    let leaf = (0..base.entries[leaf_page].node_count as usize)
        .find(|&k| node(base, leaf_page, k).is_leaf())
        .unwrap();
    let node_edit = |page: usize, i: usize, f: fn(&mut Node)| -> Edit {
        Box::new(move |p: &mut Parts| {
            let mut n = node(p, page, i);
            f(&mut n);
            set_node(p, page, i, &n);
        })
    };
    vec![
        (
            "node area NaN",
            node_edit(leaf_page, leaf, |n| n.area = f32::NAN),
            "area",
        ),
        (
            "node radius negative",
            node_edit(leaf_page, leaf, |n| n.radius = -1.0),
            "radius",
        ),
        (
            "node curvature NaN",
            node_edit(leaf_page, leaf, |n| n.curvature = 0x7e00),
            "curvature",
        ),
        (
            "node ior infinite",
            node_edit(leaf_page, leaf, |n| n.ior = 0x7c00),
            "ior",
        ),
        (
            "unknown node flag",
            node_edit(leaf_page, leaf, |n| n.flags |= 0x80),
            "unknown flags",
        ),
        (
            "leaf and page link",
            node_edit(leaf_page, leaf, |n| n.flags |= NodeFlags::CHILD_PAGE),
            "both a leaf",
        ),
        (
            "leaf emissive flag flipped",
            node_edit(leaf_page, leaf, |n| n.flags ^= NodeFlags::EMISSIVE),
            "emissive",
        ),
        (
            "reserved node byte",
            node_edit(leaf_page, leaf, |n| n.reserved1[3] = 9),
            "reserved",
        ),
        (
            "triangle material out of range",
            Box::new(move |p| {
                let n = node(p, leaf_page, leaf);
                let at = 32
                    + p.entries[leaf_page].node_count as usize * 128
                    + n.link[0] as usize * 8
                    + 6;
                p.pages[leaf_page][at..at + 2].copy_from_slice(&200u16.to_le_bytes());
            }),
            "material index out of range",
        ),
    ]
}

/// An edit of instance `k`'s record, wherever the archive keeps it.
fn record_edit(k: u32, f: fn(&mut InstanceRecord)) -> Edit {
    Box::new(move |p: &mut Parts| paged::edit_record(p, k, f))
}

/// Lies about instances, in the instanced seed (a glass floor placed three times), its
/// records in its pages or in the instance table.
fn instance_lies(base: &Parts) -> Vec<(&'static str, Edit, &'static str)> {
    assert!(
        paged::record(base, 2).is_some(),
        "the seed has three instances"
    );
    assert!(
        paged::record(base, 3).is_none(),
        "the seed has three instances"
    );
    let root = base.header.root_page;
    let proto = paged::record(base, 0).unwrap().prototype_page as usize;
    let (page, leaf) = (0..base.pages.len())
        .flat_map(|p| (0..base.entries[p].node_count as usize).map(move |k| (p, k)))
        .find(|&(p, k)| node(base, p, k).is_instance())
        .expect("an instance leaf");
    let child = (0..base.entries.len())
        .find(|&i| base.entries[i].parent_page != canopy_format::NONE)
        .expect("a child page");
    let node_edit = move |f: fn(&mut Node)| -> Edit {
        Box::new(move |p: &mut Parts| {
            let mut n = node(p, page, leaf);
            f(&mut n);
            set_node(p, page, leaf, &n);
        })
    };
    vec![
        (
            "instance of the root page",
            Box::new(move |p| paged::edit_record(p, 0, |r| r.prototype_page = root)),
            "not a prototype's root page",
        ),
        (
            "instance of a child page",
            Box::new(move |p| paged::edit_record(p, 1, |r| r.prototype_page = child as u32)),
            "not a prototype's root page",
        ),
        (
            "instance of no page",
            record_edit(2, |r| r.prototype_page = 1 << 20),
            "prototype page",
        ),
        (
            "singular transform",
            record_edit(0, |r| r.to_world[..9].fill(0.0)),
            "invertible",
        ),
        (
            "NaN transform",
            record_edit(1, |r| r.to_world[10] = f32::NAN),
            "invertible",
        ),
        (
            "reserved instance byte",
            record_edit(2, |r| r.reserved[4] = 1),
            "reserved",
        ),
        (
            "instances feature cleared",
            Box::new(|p| {
                use canopy_format::Features;
                p.header.features &= !(Features::INSTANCES | Features::PAGED_INSTANCES)
            }),
            "5 input triangles but 3 stored",
        ),
        (
            "instance moved away from its leaf",
            record_edit(0, |r| r.to_world[9] += 100.0),
            "outside it",
        ),
        (
            "a prototype's root page given a level",
            Box::new(move |p| p.entries[proto].level = 1),
            "level",
        ),
        (
            "instance leaf naming no instance",
            node_edit(|n| n.link[0] = 7),
            "instance 7 of",
        ),
        (
            "emissive instance leaf",
            node_edit(|n| n.flags |= NodeFlags::EMISSIVE),
            "emissive instance",
        ),
        (
            "instance leaf with a page link",
            node_edit(|n| n.flags |= NodeFlags::CHILD_PAGE),
            "not a plain leaf",
        ),
    ]
}

/// Lies only an archive with paged instance records can tell.
fn paged_lies(base: &Parts) -> Vec<(&'static str, Edit, &'static str)> {
    let holder = (0..base.entries.len())
        .find(|&i| base.entries[i].instance_count > 0)
        .expect("a page with records");
    vec![
        (
            "records numbered past the instance count",
            Box::new(move |p| p.entries[holder].first_instance += 3),
            "paged instances",
        ),
        (
            "paged records in a 2.6 archive",
            Box::new(|p| p.header.version_minor = 6),
            "before 2.7",
        ),
    ]
}

#[test]
fn checksum_valid_lies_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let base = seed(dir.path());
    let path = dir.path().join("lie.canopy");
    refuse_all(
        &base,
        table_lies(&base).into_iter().chain(node_lies(&base)),
        dir.path(),
    );
    // The instanced seed with its records in its pages (2.7) and in the instance table (2.6).
    let paged = fuzz::seed_archives(dir.path()).unwrap()[3].0.clone();
    let table = paged::unpaged(&paged);
    assert!(table.instances.len() == 3 && paged.instances.is_empty());
    for instanced in [&paged, &table] {
        refuse_all(instanced, instance_lies(instanced).into_iter(), dir.path());
    }
    refuse_all(&paged, paged_lies(&paged).into_iter(), dir.path());
    // The unchanged archives pass, so each refusal above is the edit's doing.
    for p in [&base, &paged, &table] {
        std::fs::write(&path, p.assemble()).unwrap();
        assert_eq!(first_error(&path, dir.path()), None);
    }
}

/// Each edit of `base` is refused with an error naming the file and containing its text.
fn refuse_all(
    base: &Parts,
    lies: impl Iterator<Item = (&'static str, Edit, &'static str)>,
    dir: &Path,
) {
    let path = dir.join("lie.canopy");
    for (what, edit, expect) in lies {
        let mut p = base.clone();
        edit(&mut p);
        std::fs::write(&path, p.assemble()).unwrap();
        let err = first_error(&path, dir).unwrap_or_else(|| panic!("{what}: accepted"));
        assert!(
            err.contains("lie.canopy"),
            "{what}: the error does not name the file: {err}"
        );
        assert!(
            err.contains(expect),
            "{what}: expected '{expect}' in: {err}"
        );
    }
}

/// A page whose nodes form a DAG (node k with children k+1 and k+2) made `render` run for
/// ever; it is refused when the page is read, by `inspect` and `render` alike.
#[test]
fn a_dag_inside_a_page_is_refused_when_read() {
    let dir = tempfile::tempdir().unwrap();
    let mut p = bunny(dir.path());
    let pg = inner_page(&p);
    let n = p.entries[pg].node_count as usize;
    assert!(n >= 3);
    for k in 0..n - 2 {
        let mut x = node(&p, pg, k);
        x.flags &= !(NodeFlags::LEAF | NodeFlags::CHILD_PAGE);
        x.link = [k as u32 + 1, k as u32 + 2];
        set_node(&mut p, pg, k, &x);
    }
    let path = dir.path().join("dag.canopy");
    std::fs::write(&path, p.assemble()).unwrap();
    let a = Archive::open(&path).unwrap();
    let Err(err) = a.read_page(pg as u32) else {
        panic!("the DAG page was accepted");
    };
    assert!(format!("{err}").contains("child of two nodes"), "{err}");
    for i in fuzz::integrators() {
        let Err(err) = render(&fuzz::tiny_render(&path, dir.path(), i.clone())) else {
            panic!("{:?}: the DAG archive rendered", i.kind());
        };
        assert!(
            format!("{err:#}").contains(&format!("page {pg}")),
            "{err:#}"
        );
    }
}

/// A leaf holding more triangles than the header's maximum (the renderer keys stored light
/// by a leaf's triangle slot) is refused when its page is read.
#[test]
fn a_leaf_over_the_header_maximum_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let mut p = bunny(dir.path());
    p.header.max_leaf_triangles = 2;
    let path = dir.path().join("leaf.canopy");
    std::fs::write(&path, p.assemble()).unwrap();
    let err = first_error(&path, dir.path()).expect("refused");
    // Caught at open where a page's triangles exceed nodes × maximum, else at its leaves.
    assert!(
        err.contains("triangles in a leaf") || err.contains("triangles and"),
        "{err}"
    );
}
