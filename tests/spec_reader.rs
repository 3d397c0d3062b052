//! A second decoder, written from `format/FORMAT.md` alone: it reads archives as bytes at the
//! spec's offsets (no `canopy_format` type), decodes node boxes and centroids in every order
//! the spec allows (separate f32 operations, fused multiply-add, multiply by the reciprocal
//! of 65535) and checks the nesting and containment FORMAT.md promises: every child's box
//! inside its parent's, every triangle inside its leaf's box, every node's sphere around its
//! decoded centroid holding its subtree's vertices. On the bundled scenes and on random
//! meshes, tiny ones far from the origin among them.

mod common;
use common::*;
use proptest::prelude::*;
use std::path::Path;

// Offsets and sizes from FORMAT.md.
const HEADER_ROOT_PAGE: usize = 88;
const HEADER_PAGES: usize = 152;
const HEADER_NODE_SIZE: usize = 184;
const PAGE_HEADER: usize = 32;
const TRI_SIZE: usize = 8;
const LEAF: u8 = 1;
const CHILD_PAGE: u8 = 2;
const INSTANCE: u8 = 32;
const INSTANCE_RECORD: usize = 64;
const ORDERS: usize = 4;

fn u16_at(b: &[u8], o: usize) -> u16 {
    u16::from_le_bytes(b[o..o + 2].try_into().unwrap())
}
fn u32_at(b: &[u8], o: usize) -> u32 {
    u32::from_le_bytes(b[o..o + 4].try_into().unwrap())
}
fn u64_at(b: &[u8], o: usize) -> u64 {
    u64::from_le_bytes(b[o..o + 8].try_into().unwrap())
}
fn f32_at(b: &[u8], o: usize) -> f32 {
    f32::from_le_bytes(b[o..o + 4].try_into().unwrap())
}
fn vec3_at(b: &[u8], o: usize) -> [f32; 3] {
    [0, 1, 2].map(|i| f32_at(b, o + 4 * i))
}

/// Code q on [lo, hi] in decoding order k.
fn decode(lo: f32, hi: f32, q: u16, k: usize) -> f32 {
    let t = q as f32 / 65535.0;
    let r = q as f32 * (1.0f32 / 65535.0);
    let d = hi - lo;
    match q {
        0 => lo,
        65535 => hi,
        _ => [lo + d * t, d.mul_add(t, lo), lo + d * r, d.mul_add(r, lo)][k].clamp(lo, hi),
    }
}

struct Page {
    node_size: usize,
    lo: [f32; 3],
    hi: [f32; 3],
    raw: Vec<u8>,
    nodes: usize,
    tris: usize,
    verts: usize,
}

impl Page {
    fn node(&self, i: usize) -> &[u8] {
        let o = PAGE_HEADER + i * self.node_size;
        &self.raw[o..o + self.node_size]
    }

    fn decoded_box(&self, i: usize, k: usize) -> ([f32; 3], [f32; 3]) {
        let n = self.node(i);
        let at = |a: usize, f: usize| decode(self.lo[a], self.hi[a], u16_at(n, 2 * f), k);
        ([0, 1, 2].map(|a| at(a, a)), [0, 1, 2].map(|a| at(a, a + 3)))
    }

    fn centroid(&self, i: usize, k: usize) -> [f32; 3] {
        let n = self.node(i);
        [0, 1, 2].map(|a| decode(self.lo[a], self.hi[a], u16_at(n, 64 + 2 * a), k))
    }

    fn vertex(&self, v: usize) -> [f32; 3] {
        vec3_at(
            &self.raw,
            PAGE_HEADER + self.nodes * self.node_size + self.tris * TRI_SIZE + 12 * v,
        )
    }

    /// Instance record `r` of the page (2.7, PAGED_INSTANCES): after the vertex streams the
    /// page header announces. Its transform as rows (column 3 the translation) and its
    /// prototype's root page.
    fn instance(&self, r: usize) -> ([[f64; 4]; 3], usize) {
        let streams = 12
            + 4 * (u32_at(&self.raw, 20) != 0) as usize
            + 8 * u32_at(&self.raw, 24) as usize
            + 8 * (u32_at(&self.raw, 28) != 0) as usize;
        let o = PAGE_HEADER
            + self.nodes * self.node_size
            + self.tris * TRI_SIZE
            + self.verts * streams
            + r * INSTANCE_RECORD;
        let m = std::array::from_fn(|row| {
            std::array::from_fn(|col| f32_at(&self.raw, o + 4 * (3 * col + row)) as f64)
        });
        (m, u32_at(&self.raw, o + 48) as usize)
    }

    fn triangle(&self, t: usize) -> [[f32; 3]; 3] {
        let o = PAGE_HEADER + self.nodes * self.node_size + t * TRI_SIZE;
        [0, 1, 2].map(|j| self.vertex(u16_at(&self.raw, o + 2 * j) as usize))
    }
}

fn read_pages(file: &[u8]) -> (Vec<Page>, usize) {
    let table = u64_at(file, HEADER_PAGES) as usize;
    let count = u32_at(file, HEADER_PAGES + 8) as usize;
    let stride = u32_at(file, HEADER_PAGES + 12) as usize;
    let node_size = u32_at(file, HEADER_NODE_SIZE) as usize;
    let pages = (0..count)
        .map(|p| {
            let e = &file[table + p * stride..table + (p + 1) * stride];
            let off = u64_at(e, 0) as usize;
            let frame = &file[off..off + u32_at(e, 8) as usize];
            Page {
                node_size,
                lo: vec3_at(e, 60),
                hi: vec3_at(e, 72),
                raw: zstd::bulk::decompress(frame, u32_at(e, 12) as usize).unwrap(),
                nodes: u32_at(e, 32) as usize,
                tris: u32_at(e, 36) as usize,
                verts: u32_at(e, 40) as usize,
            }
        })
        .collect();
    (pages, u32_at(file, HEADER_ROOT_PAGE) as usize)
}

fn inside(outer: &([f32; 3], [f32; 3]), inner: &([f32; 3], [f32; 3])) -> bool {
    (0..3).all(|a| outer.0[a] <= inner.0[a] && inner.1[a] <= outer.1[a])
}

/// What the walk found: nodes and vertices checked, instance leaves, the prototypes
/// walked (each once), and every broken promise.
#[derive(Default)]
struct Findings {
    nodes: usize,
    vertices: usize,
    instances: usize,
    prototypes: std::collections::BTreeSet<usize>,
    broken: Vec<String>,
}

/// Instance leaf `i` of page `p`: its box holds the prototype's root-page grid mapped by the
/// record's transform (corners in f64); the prototype's tree is walked once, in its own space.
fn instance_leaf(pages: &[Page], p: usize, i: usize, k: usize, f: &mut Findings) {
    let page = &pages[p];
    let n = page.node(i);
    let bx = page.decoded_box(i, k);
    let (m, proto) = page.instance(u32_at(n, 12) as usize);
    f.instances += 1;
    let (lo, hi) = (pages[proto].lo, pages[proto].hi);
    for corner in 0..8 {
        let c = [0, 1, 2].map(|a| if corner >> a & 1 == 0 { lo[a] } else { hi[a] } as f64);
        let w = m.map(|row| row[0] * c[0] + row[1] * c[1] + row[2] * c[2] + row[3]);
        if (0..3).any(|a| w[a] < bx.0[a] as f64 || w[a] > bx.1[a] as f64) {
            f.broken.push(format!(
                "order {k}: page {p} instance leaf {i}: prototype corner {w:?} outside {bx:?}"
            ));
        }
    }
    if f.prototypes.insert(proto) {
        walk(pages, proto, 0, k, &mut Vec::new(), f);
    }
}

/// Walks node `i` of page `p` in decoding order `k`; `spheres` are the ancestors' (and its
/// own, pushed here) decoded centroids and radii, which every vertex below must lie in.
fn walk(
    pages: &[Page],
    p: usize,
    i: usize,
    k: usize,
    spheres: &mut Vec<([f32; 3], f32)>,
    f: &mut Findings,
) {
    let page = &pages[p];
    let n = page.node(i);
    let bx = page.decoded_box(i, k);
    spheres.push((page.centroid(i, k), f32_at(n, 24)));
    f.nodes += 1;
    let (flags, link) = (n[38], [u32_at(n, 12), u32_at(n, 16)]);
    if flags & INSTANCE != 0 {
        instance_leaf(pages, p, i, k, f);
    } else if flags & LEAF != 0 {
        for t in link[0]..link[0] + link[1] {
            for v in page.triangle(t as usize) {
                f.vertices += 1;
                if !inside(&bx, &(v, v)) {
                    f.broken.push(format!(
                        "order {k}: page {p} leaf {i}: vertex {v:?} outside {bx:?}"
                    ));
                }
                for (c, r) in spheres.iter() {
                    let d = (0..3)
                        .map(|a| (v[a] as f64 - c[a] as f64).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    if d > *r as f64 {
                        f.broken.push(format!("order {k}: page {p} leaf {i}: vertex {v:?} at {d} from a centroid {c:?}, radius {r}"));
                    }
                }
            }
        }
    } else if flags & CHILD_PAGE != 0 {
        let c = link[0] as usize;
        for root in 0..2 {
            if !inside(&bx, &pages[c].decoded_box(root, k)) {
                f.broken.push(format!(
                    "order {k}: page {c} root {root} outside page {p} node {i}"
                ));
            }
            walk(pages, c, root, k, spheres, f);
        }
    } else {
        for c in link {
            if !inside(&bx, &page.decoded_box(c as usize, k)) {
                f.broken.push(format!(
                    "order {k}: page {p} node {c} outside its parent {i}"
                ));
            }
            walk(pages, p, c as usize, k, spheres, f);
        }
    }
    spheres.pop();
}

/// Checks an archive in every decoding order; returns the nodes visited per order.
fn check(archive: &Path) -> usize {
    check_counting(archive).0
}

/// `check`, also returning the instance leaves met per order.
fn check_counting(archive: &Path) -> (usize, usize) {
    let file = std::fs::read(archive).unwrap();
    let (pages, root) = read_pages(&file);
    let (mut visited, mut instances) = (0, 0);
    for k in 0..ORDERS {
        let mut f = Findings::default();
        walk(&pages, root, 0, k, &mut Vec::new(), &mut f);
        assert!(
            f.broken.is_empty(),
            "{}: {} broken promises, first: {:?}",
            archive.display(),
            f.broken.len(),
            &f.broken[..f.broken.len().min(5)]
        );
        assert!(f.vertices > 0);
        (visited, instances) = (f.nodes, f.instances);
    }
    (visited, instances)
}

#[test]
fn bundled_scenes_keep_every_promise_in_every_decoding_order() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["cbox.glb", "bunny_box.glb", "sponza.glb"] {
        let out = dir.path().join(format!("{name}.canopy"));
        convert(&scene(name), &out, None);
        let file = std::fs::read(&out).unwrap();
        let nodes = u64_at(&file, 40) as usize;
        assert_eq!(check(&out), nodes, "{name}: the walk reaches every node");
    }
}

/// An instanced archive (2.7: the records in the pages that hold their leaves): every node
/// is reached, scene tree and each prototype once, every instance leaf holds its record's
/// placed prototype box, and the pages hold as many records as the header counts.
#[test]
fn instanced_archives_keep_every_promise_in_every_decoding_order() {
    let dir = tempfile::tempdir().unwrap();
    let grid: Vec<[f32; 3]> = (0..40)
        .flat_map(|i| (0..30).map(move |j| [1.5 * i as f32, 0.1 * j as f32, 1.1 * j as f32]))
        .collect();
    let scales: Vec<[f32; 3]> = (0..grid.len())
        .map(|i| [0.01 + 0.001 * (i % 7) as f32; 3])
        .collect();
    let input = gpu_instanced(dir.path(), "field.glb", "smallbox", &grid, &scales);
    let out = dir.path().join("field.canopy");
    convert(&input, &out, None);
    let file = std::fs::read(&out).unwrap();
    let nodes = u64_at(&file, 40) as usize;
    // The instance table's count (192 + 8), its record size 0: the records are paged.
    let (count, size) = (u32_at(&file, 200) as usize, u32_at(&file, 204));
    assert_eq!((count, size), (grid.len(), 0));
    let (visited, instances) = check_counting(&out);
    assert_eq!(visited, nodes, "the walk reaches every node");
    assert_eq!(instances, count, "one leaf per record");
    let table = u64_at(&file, HEADER_PAGES) as usize;
    let stride = u32_at(&file, HEADER_PAGES + 12) as usize;
    let mut next = 0;
    for p in 0..u32_at(&file, HEADER_PAGES + 8) as usize {
        let e = &file[table + p * stride..];
        assert_eq!(
            u32_at(e, 92) as usize,
            next,
            "page {p} numbers its records on"
        );
        next += u32_at(e, 44) as usize;
    }
    assert_eq!(next, count);
}

/// An archive rewritten as a later minor version might write it: every table record 8 bytes
/// longer and an optional feature bit this reader does not know. FORMAT.md says readers
/// skip the one and ignore the other; the scene must read, verify and render as before.
#[test]
fn longer_records_and_unknown_optional_features_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &good, None);
    let file = std::fs::read(&good).unwrap();
    let xxh3 = xxhash_rust::xxh3::xxh3_64;
    let table = |at: usize| {
        (
            u64_at(&file, at) as usize,
            u32_at(&file, at + 8) as usize,
            u32_at(&file, at + 12) as usize,
        )
    };
    let start = table(104).0;
    let mut out = file[..start].to_vec();
    let mut header = file[..256].to_vec();
    let mut grow = |out: &mut Vec<u8>, at: usize, entry: bool| {
        let (offset, count, size) = table(at);
        header[at..at + 8].copy_from_slice(&(out.len() as u64).to_le_bytes());
        header[at + 12..at + 16].copy_from_slice(&(size as u32 + 8).to_le_bytes());
        for r in file[offset..offset + count * size].chunks(size) {
            let mut rec = [r, &[0u8; 8][..]].concat();
            if entry {
                rec[84..92].fill(0);
                let c = xxh3(&rec);
                rec[84..92].copy_from_slice(&c.to_le_bytes());
            }
            out.extend_from_slice(&rec);
        }
    };
    // Materials, cameras, lights, (2.1) instances, (2.2) textures and tiles, (2.3) the
    // environment, back to back.
    for at in [104, 120, 136, 192, 208, 224, 240] {
        grow(&mut out, at, false);
    }
    let tables = xxh3(&out[start..]);
    out.resize(out.len().next_multiple_of(64), 0);
    grow(&mut out, 152, true);
    header[56..64].copy_from_slice(&(out.len() as u64).to_le_bytes());
    header[168..176].copy_from_slice(&tables.to_le_bytes());
    let features = u64_at(&header, 16) | 1 << 20;
    header[16..24].copy_from_slice(&features.to_le_bytes());
    header[176..184].fill(0);
    let h = xxh3(&header);
    header[176..184].copy_from_slice(&h.to_le_bytes());
    out[..256].copy_from_slice(&header);
    let later = dir.path().join("later.canopy");
    std::fs::write(&later, &out).unwrap();
    assert!(ok(&["inspect", "--verify", s(&later)]).contains("verify              ok"));
    let args = [
        "--integrator",
        "path",
        "--width",
        "24",
        "--height",
        "24",
        "--spp",
        "2",
    ];
    let (a, _) = render(&good, &dir.path().join("a.exr"), &args);
    let (b, _) = render(&later, &dir.path().join("b.exr"), &args);
    assert_eq!(a.pixels, b.pixels);
}

/// A version 2.0 file (before instances: minor 0, the instance table's bytes reserved and
/// zero) still opens, verifies and renders as the 2.1 file it was rewritten from (its
/// instance record size is 0, which a reader must not divide by).
#[test]
fn version_2_0_archives_still_open() {
    let dir = tempfile::tempdir().unwrap();
    let good = dir.path().join("cbox.canopy");
    convert(&scene("cbox.glb"), &good, None);
    let mut file = std::fs::read(&good).unwrap();
    assert_eq!(u32_at(&file, 196), 0, "cbox has no instances");
    file[10..12].copy_from_slice(&0u16.to_le_bytes());
    file[192..256].fill(0);
    file[176..184].fill(0);
    let h = xxhash_rust::xxh3::xxh3_64(&file[..256]);
    file[176..184].copy_from_slice(&h.to_le_bytes());
    let old = dir.path().join("old.canopy");
    std::fs::write(&old, &file).unwrap();
    let report = ok(&["inspect", "--verify", s(&old)]);
    assert!(report.contains("format version      2.0"), "{report}");
    assert!(report.contains("verify              ok"), "{report}");
    let args = ["--width", "24", "--height", "24", "--spp", "2"];
    let (a, _) = render(&good, &dir.path().join("a.exr"), &args);
    let (b, _) = render(&old, &dir.path().join("b.exr"), &args);
    assert_eq!(a.pixels, b.pixels);
}

/// A random mesh of `n` triangles around `origin`, `size` across, as OBJ text.
fn obj(origin: [f32; 3], size: f32, coords: &[f32]) -> String {
    let mut s = String::new();
    for v in coords.chunks(3) {
        let p = [0, 1, 2].map(|a| origin[a] + size * v[a]);
        s += &format!("v {:e} {:e} {:e}\n", p[0], p[1], p[2]);
    }
    for t in 0..coords.len() / 9 {
        s += &format!("f {} {} {}\n", 3 * t + 1, 3 * t + 2, 3 * t + 3);
    }
    s
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    #[test]
    fn random_meshes_keep_every_promise(
        origin in prop::array::uniform3(prop_oneof![Just(0.0f32), -1e6f32..1e6, Just(3.0e5)]),
        size in prop_oneof![Just(1e-3f32), 1e-2f32..10.0, Just(1e4)],
        coords in prop::collection::vec(0.0f32..1.0, 9..9 * 3000),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("m.obj");
        let coords = &coords[..coords.len() / 9 * 9];
        std::fs::write(&input, obj(origin, size, coords)).unwrap();
        let out = dir.path().join("m.canopy");
        let mut opts = canopy::convert::ConvertOptions::new(vec![input], out.clone());
        opts.page_nodes = 16;
        canopy::convert::convert(&opts).unwrap();
        check(&out);
    }
}
