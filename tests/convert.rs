//! End-to-end conversion: every bundled scene converts and verifies, output is deterministic,
//! the chunked (out-of-core) path gives a valid archive, OBJ + MTL + TOML scene files work.

mod common;
use canopy_format::{Archive, Features};
use common::*;

#[test]
fn bundled_scenes_convert_and_verify() {
    let dir = tempfile::tempdir().unwrap();
    for name in [
        "cbox.glb",
        "bunny_box.glb",
        "sponza.glb",
        "bunny.ply",
        "caustics.glb",
    ] {
        let out = dir.path().join(format!("{name}.canopy"));
        ok(&["convert", s(&scene(name)), "-o", s(&out)]);
        let text = ok(&["inspect", "--verify", s(&out)]);
        assert!(text.contains("node size           128 bytes"), "{text}");
        assert!(text.contains("verify              ok"), "{text}");
        let a = Archive::open(&out).unwrap();
        assert_eq!(a.header.triangles, a.header.input_triangles);
    }
}

#[test]
fn scene_contents_are_recorded() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cbox.canopy");
    ok(&["convert", s(&scene("cbox.glb")), "-o", s(&out)]);
    let a = Archive::open(&out).unwrap();
    assert_eq!(a.header.input_triangles, 38);
    assert_eq!(a.cameras.len(), 1);
    assert_eq!((a.cameras[0].width, a.cameras[0].height), (256, 256));
    // Emitters, but no glossy or transmissive surfaces: those streams and passes are skipped.
    assert_eq!(
        a.header.features & (Features::EMITTERS | Features::GLOSSY | Features::TRANSMISSIVE),
        Features::EMITTERS
    );
    let light = a
        .materials
        .iter()
        .find(|m| canopy_format::name_str(&m.name) == "light")
        .unwrap();
    assert!(
        (light.emission[0] - 18.387).abs() < 1e-3,
        "emission = factor × strength"
    );
    assert_eq!(light.flags & canopy_format::MaterialRecord::DOUBLE_SIDED, 0);
}

#[test]
fn conversion_is_deterministic() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.canopy"), dir.path().join("b.canopy"));
    for out in [&a, &b] {
        ok(&["convert", s(&scene("bunny_box.glb")), "-o", s(out)]);
    }
    assert!(
        std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap(),
        "two conversions differ"
    );
}

#[test]
fn chunked_conversion_is_valid_and_deterministic() {
    // 100 MiB leaves room for ~10k triangles a chunk: the bunny splits into several chunks.
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a.canopy"), dir.path().join("b.canopy"));
    for out in [&a, &b] {
        let text = ok(&[
            "convert",
            s(&scene("bunny.ply")),
            "-o",
            s(out),
            "--mem-budget",
            "100MiB",
        ]);
        assert!(text.contains("chunks"), "expected several chunks: {text}");
    }
    ok(&["inspect", "--verify", s(&a)]);
    assert!(std::fs::read(&a).unwrap() == std::fs::read(&b).unwrap());
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(leftovers.len(), 2, "spill files left behind: {leftovers:?}");
}

#[test]
fn obj_with_mtl_and_scene_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("quad.mtl"),
        "newmtl lamp\nKd 0.5 0.5 0.5\nKe 4 4 4\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("quad.obj"),
        "mtllib quad.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nusemtl lamp\nf 1 2 3 4\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("tri.obj"),
        "v 0 0 1\nv 1 0 1\nv 0 1 1\nf -3 -2 -1\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("scene.toml"),
        "[[camera]]\nname = \"front\"\nposition = [0.5, 0.5, 3.0]\nlook_at = [0.5, 0.5, 0.0]\nwidth = 64\nheight = 32\n\n[[material]]\nname = \"default\"\nbase_color = [0.2, 0.4, 0.6]\n\n[[light]]\ntype = \"point\"\nposition = [0, 2, 0]\nintensity = 5.0\n",
    )
    .unwrap();
    let out = dir.path().join("o.canopy");
    let p = |n: &str| dir.path().join(n);
    ok(&[
        "convert",
        s(&p("quad.obj")),
        s(&p("tri.obj")),
        "--scene",
        s(&p("scene.toml")),
        "-o",
        s(&out),
    ]);
    ok(&["inspect", "--verify", s(&out)]);
    let a = Archive::open(&out).unwrap();
    assert_eq!(a.header.input_triangles, 3);
    assert_eq!(canopy_format::name_str(&a.cameras[0].name), "front");
    assert_eq!(a.lights.len(), 1);
    let names: Vec<String> = a
        .materials
        .iter()
        .map(|m| canopy_format::name_str(&m.name))
        .collect();
    assert_eq!(names, ["lamp", "default"]);
    assert!((a.materials[1].base_color[2] - 0.6).abs() < 1e-6);
    assert_ne!(a.header.features & Features::EMITTERS, 0);
    assert_ne!(a.header.features & Features::PUNCTUAL_LIGHTS, 0);
}

/// Area-weighted sums over a subtree's triangles: area, area·normal, area·emission,
/// area·p_reflect at the five cosines, and its vertices.
#[derive(Default)]
struct Sums {
    area: f64,
    normal: [f64; 3],
    emission: [f64; 3],
    reflect: [f64; 5],
    verts: Vec<[f32; 3]>,
}

/// p_reflect(cos θ) of the scene's materials from the physics, not the converter's code:
/// a white metal reflects everything; Lambertian materials (specular 0) nothing; smooth
/// glass by Schlick with F0 = ((η−1)/(η+1))² = 0.04.
fn p_reflect(m: &canopy_format::MaterialRecord, c: f64) -> f64 {
    if m.metallic == 1.0 {
        1.0
    } else if m.specular == 0.0 {
        0.0
    } else {
        0.04 + 0.96 * (1.0 - c).powi(5)
    }
}

fn subtree(a: &Archive, pages: &[canopy_format::PageContents], pg: u32, i: usize, s: &mut Sums) {
    let n = &pages[pg as usize].nodes[i];
    if n.is_leaf() {
        let c = &pages[pg as usize];
        for t in &c.tris[n.link[0] as usize..(n.link[0] + n.link[1]) as usize] {
            let p = t.v.map(|k| c.verts[k as usize].map(f64::from));
            let e1 = [0, 1, 2].map(|k| p[1][k] - p[0][k]);
            let e2 = [0, 1, 2].map(|k| p[2][k] - p[0][k]);
            let x = [
                e1[1] * e2[2] - e1[2] * e2[1],
                e1[2] * e2[0] - e1[0] * e2[2],
                e1[0] * e2[1] - e1[1] * e2[0],
            ];
            let len = (x[0] * x[0] + x[1] * x[1] + x[2] * x[2]).sqrt();
            let area = 0.5 * len;
            let m = &a.materials[t.material as usize];
            s.area += area;
            s.normal = [0, 1, 2].map(|k| s.normal[k] + area * x[k] / len);
            s.emission = [0, 1, 2].map(|k| s.emission[k] + area * m.emission[k] as f64);
            for (k, c) in [0.0, 0.25, 0.5, 0.75, 1.0].into_iter().enumerate() {
                s.reflect[k] += area * p_reflect(m, c);
            }
            s.verts.extend(t.v.map(|k| c.verts[k as usize]));
        }
    } else if n.has_child_page() {
        subtree(a, pages, n.link[0], 0, s);
        subtree(a, pages, n.link[0], 1, s);
    } else {
        subtree(a, pages, pg, n.link[0] as usize, s);
        subtree(a, pages, pg, n.link[1] as usize, s);
    }
}

/// Every node's cluster attributes (004 §4.2–4.4) against sums over its subtree's
/// triangles: area, the un-normalized area-weighted normal, emission, the five-sample
/// Fresnel table, and a radius that holds every vertex.
#[test]
fn cluster_attributes_are_area_weighted_means_of_their_triangles() {
    use canopy_format::codec::{rgbe64_decode, snorm16_decode, unorm8_decode};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("c.canopy");
    ok(&[
        "--quiet",
        "convert",
        s(&scene("caustics.glb")),
        "-o",
        s(&out),
        "--page-nodes",
        "64",
    ]);
    let a = Archive::open(&out).unwrap();
    let pages: Vec<_> = (0..a.page_count())
        .map(|p| a.read_page(p).unwrap())
        .collect();
    let mut checked = 0;
    for (pg, c) in pages.iter().enumerate() {
        let grid = a.grid(pg as u32).unwrap();
        let step = (0..3)
            .map(|k| ((grid.hi[k] - grid.lo[k]) / 65535.0).powi(2))
            .sum::<f32>()
            .sqrt();
        for (i, n) in c.nodes.iter().enumerate() {
            let mut s = Sums::default();
            subtree(&a, &pages, pg as u32, i, &mut s);
            let what = format!("page {pg} node {i}");
            assert!(
                (n.area as f64 / s.area - 1.0).abs() < 1e-4,
                "{what}: area {} against {}",
                n.area,
                s.area
            );
            let normal = n.normal.map(snorm16_decode);
            let emission = rgbe64_decode(n.emission);
            for k in 0..3 {
                let want = s.normal[k] / s.area;
                assert!(
                    (normal[k] as f64 - want).abs() < 1e-3,
                    "{what}: normal {normal:?}, want {:?}",
                    s.normal.map(|x| x / s.area)
                );
                let want = s.emission[k] / s.area;
                assert!(
                    (emission[k] as f64 - want).abs() <= 1e-4 * want + 1e-6,
                    "{what}: emission {emission:?}"
                );
            }
            for k in 0..5 {
                let want = s.reflect[k] / s.area;
                let got = unorm8_decode(n.reflectiveness[k]) as f64;
                assert!(
                    (got - want).abs() < 0.6 / 255.0 + 1e-4,
                    "{what}: p_reflect[{k}] {got} against {want}"
                );
            }
            let cen = [0, 1, 2].map(|k| grid.dequant(k, n.centroid[k]));
            let far = s
                .verts
                .iter()
                .map(|v| (0..3).map(|k| (v[k] - cen[k]).powi(2)).sum::<f32>().sqrt())
                .fold(0.0, f32::max);
            assert!(
                far <= n.radius * (1.0 + 1e-5) + step + 1e-6,
                "{what}: a vertex {far} from the centroid, radius {}",
                n.radius
            );
            checked += 1;
        }
    }
    assert_eq!(checked as u64, a.header.nodes);
}

/// `Page::decode` turns each node record into the traversal view the tracer reads: the
/// kind from the flags, the links, the decoded box; and each triangle into its vertices.
#[test]
fn decoded_pages_keep_every_node_kind_and_link() {
    use canopy::paging::{NodeRef, Page};
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("b.canopy");
    ok(&[
        "--quiet",
        "convert",
        s(&scene("bunny.ply")),
        "-o",
        s(&out),
        "--page-nodes",
        "31",
    ]);
    let a = Archive::open(&out).unwrap();
    let mut kinds = [0u32; 3];
    for pg in 0..a.page_count() {
        let c = a.read_page(pg).unwrap();
        let p = Page::decode(&a, pg).unwrap();
        assert_eq!(
            (p.first_node, p.nodes.len()),
            (a.entry(pg).unwrap().first_node, c.nodes.len())
        );
        for (n, t) in c.nodes.iter().zip(&p.bvh) {
            let want = if n.is_leaf() {
                kinds[0] += 1;
                NodeRef::Leaf {
                    first: n.link[0],
                    count: n.link[1],
                }
            } else if n.has_child_page() {
                kinds[1] += 1;
                NodeRef::ChildPage(n.link[0])
            } else {
                kinds[2] += 1;
                NodeRef::Inner(n.link[0], n.link[1])
            };
            assert_eq!(t.link(), want, "page {pg}");
            assert_eq!((t.lo, t.hi), a.grid(pg).unwrap().dequant_box(&n.bounds));
        }
        assert_eq!(p.tri_count() as usize, c.tris.len());
        for (i, tri) in c.tris.iter().enumerate() {
            let w = p.tri(i as u32).expect("a leaf holds every triangle");
            assert_eq!(w.p, tri.v.map(|k| c.verts[k as usize]));
            assert_eq!(w.material, tri.material as u32);
        }
    }
    assert!(
        kinds.iter().all(|&k| k > 10),
        "leaves, page links, inner nodes: {kinds:?}"
    );
}

/// EXT_mesh_gpu_instancing: a mesh placed three times is stored once with an instance per
/// placement (input triangles count every copy); `--flatten-instances` stores every copy.
/// Both span the same scene (the instanced bounds are conservative: they may only grow,
/// by rounding). A mesh placed once is stored as it is; unequal accessor counts are a
/// clear error.
#[test]
fn gpu_instanced_meshes_are_stored_once() {
    let dir = tempfile::tempdir().unwrap();
    let archive = |input: &std::path::Path, flatten: bool| {
        let out = input.with_extension(if flatten { "flat.canopy" } else { "canopy" });
        let mut args = vec!["--quiet", "convert", s(input), "-o", s(&out)];
        if flatten {
            args.push("--flatten-instances");
        }
        ok(&args);
        ok(&["inspect", s(&out), "--verify"]);
        Archive::open(&out).unwrap().header
    };
    let base = archive(&scene("cbox.glb"), false);
    let one = archive(
        &gpu_instanced(dir.path(), "one.glb", "floor", &[[0.0; 3]], &[]),
        false,
    );
    assert_eq!(
        (one.triangles, one.features),
        (base.triangles, base.features)
    );
    assert_eq!(
        (one.bounds_min, one.bounds_max),
        (base.bounds_min, base.bounds_max)
    );
    let far = base.bounds_max[0] + 10.0;
    let places = [[0.0; 3], [far, 0.0, 0.0], [0.0, 0.0, -far]];
    let input = gpu_instanced(dir.path(), "three.glb", "floor", &places, &[]);
    let flat = archive(&input, true);
    let shared = archive(&input, false);
    let mesh = (flat.triangles - base.triangles) / 2;
    assert!(mesh > 0 && flat.triangles == base.triangles + 2 * mesh);
    assert_eq!(flat.features & Features::INSTANCES, 0);
    assert_ne!(shared.features & Features::INSTANCES, 0);
    let report = ok(&["inspect", s(&input.with_extension("canopy"))]);
    assert!(
        report.contains("instances           3 of 1 prototypes"),
        "{report}"
    );
    assert_eq!(shared.input_triangles, flat.triangles);
    assert_eq!(shared.triangles, base.triangles);
    assert!(
        flat.bounds_max[0] > far && flat.bounds_min[2] < -far / 2.0,
        "{flat:?}"
    );
    for a in 0..3 {
        let slack = 1e-5 * (flat.bounds_max[a] - flat.bounds_min[a]);
        assert!(shared.bounds_min[a] <= flat.bounds_min[a]);
        assert!(shared.bounds_max[a] >= flat.bounds_max[a]);
        assert!(shared.bounds_min[a] >= flat.bounds_min[a] - slack);
        assert!(shared.bounds_max[a] <= flat.bounds_max[a] + slack);
    }
    let bad = gpu_instanced(
        dir.path(),
        "bad.glb",
        "floor",
        &[[0.0; 3], [1.0; 3]],
        &[[1.0; 3]],
    );
    let err = fails(&["convert", s(&bad), "-o", s(&dir.path().join("bad.canopy"))]);
    assert!(
        err.contains("bad.glb") && err.contains("one count"),
        "{err}"
    );
    assert!(!dir.path().join("bad.canopy").exists());
}

/// Geometry converts in bounded memory: 2 M triangles (464 bytes each in flight, 900 MiB
/// whole) under `--mem-budget 98MiB`, the least it accepts, peak at no more than the
/// budget in resident memory, code and buffers included (the process's own high-water
/// mark); without a budget the same conversion peaks near 710 MiB. At this budget the
/// partition writes 489 chunk files, whose write buffers share 16 MiB (at 256 KiB each
/// they would take 122 MiB).
#[test]
fn geometry_converts_within_the_memory_budget() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("grid.ply");
    grid_ply(&ply, 1000);
    let arc = dir.path().join("g.canopy");
    let args = [
        "--quiet",
        "convert",
        s(&ply),
        "-o",
        s(&arc),
        "--mem-budget",
        "98MiB",
        "--json",
    ];
    let report: serde_json::Value = serde_json::from_str(&ok(&args)).unwrap();
    assert_eq!(report["input_triangles"], 2_000_000, "{report}");
    let peak = report["peak_rss_bytes"].as_u64().unwrap();
    assert!(
        peak <= 98 << 20,
        "peak RSS {} MiB over a 98 MiB budget",
        peak >> 20
    );
    let verify = ok(&["inspect", s(&arc), "--verify"]);
    assert!(verify.contains("verify              ok"), "{verify}");
}

/// A scan's PLY in the Stanford layout: its faces as one `tristrips` list with −1 restarts.
/// It converts to the triangles (and windings) of the same mesh given as faces, and renders
/// the same image.
#[test]
fn ply_triangle_strips_with_restarts_convert_like_faces() {
    let dir = tempfile::tempdir().unwrap();
    let header = |element: &str, n: usize| {
        format!("ply\nformat ascii 1.0\nelement vertex 6\nproperty float x\nproperty float y\nproperty float z\nelement {element} {n}\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n2 0 0\n0 1 0\n1 1 0\n2 1 0\n")
    };
    // 0 3 1 4 | 1 4 2 5: four triangles, the second and fourth of each run turned.
    let strips = header("tristrips", 1) + "9 0 3 1 4 -1 1 4 2 5\n";
    let faces = header("face", 4) + "3 0 3 1\n3 1 3 4\n3 1 4 2\n3 2 4 5\n";
    let toml = "[[camera]]\nposition = [1.0, 0.5, -2.0]\nlook_at = [1.0, 0.5, 0.0]\nwidth = 16\nheight = 12\n\
                [[material]]\nname = \"default\"\nbase_color = [0.5, 0.5, 0.5]\ndouble_sided = false\n\
                [[light]]\ntype = \"point\"\nposition = [1.0, 0.5, -1.0]\nintensity = 2.0\n";
    std::fs::write(dir.path().join("scene.toml"), toml).unwrap();
    let mut images = Vec::new();
    for (name, text) in [("strips.ply", strips), ("faces.ply", faces)] {
        let ply = dir.path().join(name);
        std::fs::write(&ply, text).unwrap();
        let arc = dir.path().join(format!("{name}.canopy"));
        let scene_file = dir.path().join("scene.toml");
        ok(&[
            "--quiet",
            "convert",
            s(&ply),
            "--scene",
            s(&scene_file),
            "-o",
            s(&arc),
        ]);
        let report: serde_json::Value =
            serde_json::from_str(&ok(&["inspect", s(&arc), "--json"])).unwrap();
        assert_eq!(report["triangles"], 4, "{name}");
        images.push(
            render(
                &arc,
                &dir.path().join(format!("{name}.exr")),
                &["--spp", "4"],
            )
            .0,
        );
    }
    assert!(images[0].mean()[0] > 0.0, "the lit side faces the camera");
    assert_eq!(images[0].pixels, images[1].pixels);
}

/// A cube as glTF with 32-bit float positions and normals, or quantized as
/// KHR_mesh_quantization ships it: 16-bit unsigned positions scaled by its node, normals as
/// normalized signed bytes.
fn cube_gltf(dir: &std::path::Path, quantized: bool) -> std::path::PathBuf {
    let corners: Vec<[i32; 3]> = (0..8).map(|i| [i & 1, i >> 1 & 1, i >> 2 & 1]).collect();
    let idx: [u16; 36] = [
        0, 2, 1, 1, 2, 3, 4, 5, 6, 5, 7, 6, 0, 1, 4, 1, 5, 4, 2, 6, 3, 3, 6, 7, 0, 4, 2, 2, 4, 6,
        1, 3, 5, 3, 7, 5,
    ];
    // Each corner's normal points out along the diagonal: ±73/127 (±0.57) per axis.
    let n8 = |c: i32| if c == 1 { 73i8 } else { -73 };
    let mut bin: Vec<u8> = Vec::new();
    let (pos_type, nrm_type, node_scale) = if quantized {
        for c in &corners {
            c.iter()
                .for_each(|&v| bin.extend((v as u16 * 1000).to_le_bytes()));
            bin.extend([0, 0]); // 4-byte element alignment
        }
        for c in &corners {
            bin.extend(c.map(|v| n8(v) as u8));
            bin.push(0);
        }
        (5123, 5120, 0.001f32)
    } else {
        for c in &corners {
            c.iter().for_each(|&v| bin.extend((v as f32).to_le_bytes()));
        }
        for c in &corners {
            c.iter()
                .for_each(|&v| bin.extend((n8(v) as f32 / 127.0).to_le_bytes()));
        }
        (5126, 5126, 1.0)
    };
    let (stride_p, stride_n) = if quantized { (8, 4) } else { (12, 12) };
    let idx_at = bin.len();
    bin.extend(idx.iter().flat_map(|i| i.to_le_bytes()));
    use base64::Engine;
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    let mut doc = serde_json::json!({
        "asset": {"version": "2.0"},
        "scene": 0, "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "scale": [node_scale, node_scale, node_scale]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2}]}],
        "buffers": [{"byteLength": bin.len(), "uri": uri}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": 8 * stride_p, "byteStride": stride_p},
            {"buffer": 0, "byteOffset": 8 * stride_p, "byteLength": 8 * stride_n, "byteStride": stride_n},
            {"buffer": 0, "byteOffset": idx_at, "byteLength": 72}
        ],
        "accessors": [
            {"bufferView": 0, "componentType": pos_type, "count": 8, "type": "VEC3",
             "min": [0, 0, 0], "max": if quantized { [1000, 1000, 1000] } else { [1, 1, 1] }},
            {"bufferView": 1, "componentType": nrm_type, "normalized": quantized, "count": 8, "type": "VEC3"},
            {"bufferView": 2, "componentType": 5123, "count": 36, "type": "SCALAR"}
        ]
    });
    if quantized {
        doc["extensionsUsed"] = serde_json::json!(["KHR_mesh_quantization"]);
        doc["extensionsRequired"] = serde_json::json!(["KHR_mesh_quantization"]);
    }
    let path = dir.join(if quantized { "q.gltf" } else { "f.gltf" });
    std::fs::write(&path, doc.to_string()).unwrap();
    path
}

/// KHR_mesh_quantization: the quantized cube converts to the float cube's triangles (the
/// same bounds) and renders its image (shading normals included) with nothing but its
/// file name.
#[test]
fn quantized_meshes_convert_like_their_float_twins() {
    let dir = tempfile::tempdir().unwrap();
    let mut images = Vec::new();
    for quantized in [false, true] {
        let gltf = cube_gltf(dir.path(), quantized);
        let arc = dir.path().join(format!("{quantized}.canopy"));
        ok(&["--quiet", "convert", s(&gltf), "-o", s(&arc)]);
        let report: serde_json::Value =
            serde_json::from_str(&ok(&["inspect", s(&arc), "--json"])).unwrap();
        assert_eq!(report["triangles"], 12);
        let flags = ["--spp", "4", "--width", "24", "--height", "18"];
        images.push(render(&arc, &dir.path().join(format!("{quantized}.exr")), &flags).0);
    }
    let worst = images[0]
        .pixels
        .iter()
        .zip(&images[1].pixels)
        .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-4, "largest pixel difference {worst}");
}

/// Texture coordinates as normalized signed bytes (KHR_mesh_quantization allows them; the
/// gltf crate's own reader has no case for them) convert, read by the importer.
#[test]
fn quantized_texture_coordinates_convert() {
    let dir = tempfile::tempdir().unwrap();
    textured::solid_png(&dir.path().join("t.png"), 4, [200, 100, 50, 255]);
    let mut bin: Vec<u8> = [0.0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    bin.extend([0, 0, 127, 0, 0, 127, 0, 0]);
    use base64::Engine;
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&bin)
    );
    let doc = serde_json::json!({
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0, "TEXCOORD_0": 1}, "material": 0}]}],
        "materials": [{"pbrMetallicRoughness": {"baseColorTexture": {"index": 0}}}],
        "textures": [{"source": 0}], "images": [{"uri": "t.png"}],
        "buffers": [{"byteLength": bin.len(), "uri": uri}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 8}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5120, "normalized": true, "count": 3, "type": "VEC2"}
        ],
        "extensionsUsed": ["KHR_mesh_quantization"], "extensionsRequired": ["KHR_mesh_quantization"]
    });
    let gltf = dir.path().join("uv.gltf");
    std::fs::write(&gltf, doc.to_string()).unwrap();
    let arc = dir.path().join("uv.canopy");
    ok(&["--quiet", "convert", s(&gltf), "-o", s(&arc)]);
    let (img, _) = render(
        &arc,
        &dir.path().join("uv.exr"),
        &["--spp", "2", "--width", "8", "--height", "6"],
    );
    assert!(
        all_finite(&img) && img.mean()[0] > img.mean()[2],
        "the texture's orange shows"
    );
}

/// A primitive Canopy does not render (lines here) is named at convert time, with what is
/// done instead; the triangles beside it convert.
#[test]
fn primitives_that_are_not_triangles_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let gltf = cube_gltf(dir.path(), false);
    let mut doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&gltf).unwrap()).unwrap();
    let lines = serde_json::json!({"attributes": {"POSITION": 0}, "indices": 2, "mode": 1});
    doc["meshes"][0]["primitives"]
        .as_array_mut()
        .unwrap()
        .push(lines);
    doc["meshes"][0]["name"] = "box".into();
    std::fs::write(&gltf, doc.to_string()).unwrap();
    let arc = dir.path().join("l.canopy");
    let err = succeeds_saying(&["--quiet", "convert", s(&gltf), "-o", s(&arc)]);
    assert!(
        err.contains("mesh 'box' primitive 1 draws Lines") && err.contains("skipped"),
        "{err}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&ok(&["inspect", s(&arc), "--json"])).unwrap();
    assert_eq!(report["triangles"], 12);
    let listed = ok(&["inspect", s(&arc)]);
    assert!(
        listed.contains("not carried         1") && listed.contains("primitive 1 draws Lines"),
        "{listed}"
    );
}

/// Converts `plain` and its compressed `twin` (bundled scenes), renders each with `flags`
/// and independent seeds, and checks the twin has the plain file's triangles, its bounds
/// within `step`, and its image within noise.
fn assert_twins(plain: &str, twin: &str, flags: &[&str], step: f64) {
    let dir = tempfile::tempdir().unwrap();
    let mut runs = Vec::new();
    for (name, seed) in [(plain, "1"), (twin, "2")] {
        let arc = dir.path().join(format!("{seed}.canopy"));
        ok(&["--quiet", "convert", s(&scene(name)), "-o", s(&arc)]);
        let report: serde_json::Value =
            serde_json::from_str(&ok(&["inspect", s(&arc), "--json"])).unwrap();
        let flags = [flags, &["--seed", seed]].concat();
        let img = render(&arc, &dir.path().join(format!("{seed}.exr")), &flags).0;
        runs.push((report, img));
    }
    let (a, b) = (&runs[0].0, &runs[1].0);
    assert_eq!(a["triangles"], b["triangles"], "{twin}");
    for key in ["bounds_min", "bounds_max"] {
        for k in 0..3 {
            let (p, q) = (a[key][k].as_f64().unwrap(), b[key][k].as_f64().unwrap());
            assert!((p - q).abs() <= step, "{twin}: {key}[{k}]: {p} vs {q}");
        }
    }
    assert_mean_within_noise(&runs[1].1, &runs[0].1, twin);
}

/// A copy of bundled scene `name` with `edit` applied to its GLB bytes (after the
/// JSON chunk, whose length it is given), converted: the error, which must be clean.
fn convert_edited(name: &str, edit: impl Fn(&mut Vec<u8>, usize)) -> String {
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = std::fs::read(scene(name)).unwrap();
    let json_len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
    edit(&mut bytes, json_len);
    let broken = dir.path().join("broken.glb");
    std::fs::write(&broken, bytes).unwrap();
    let out = dir.path().join("broken.canopy");
    let err = fails(&["convert", s(&broken), "-o", s(&out)]);
    assert!(!out.exists(), "no archive is left behind");
    err
}

/// KHR_draco_mesh_compression: `scenes/draco/spheres.glb`, `scenes/env/spheres.glb`
/// encoded by Google's reference encoder (`tools/draco_variant.py`, 14-bit positions),
/// converts to the plain file's triangles, its bounds within the quantization step (the
/// 4-unit span over 2^14), and renders its image within noise. Draco data that does not
/// decode is refused by name.
#[test]
fn draco_meshes_convert_like_their_plain_twins() {
    let flags = ["--spp", "32", "--width", "64", "--height", "48"];
    assert_twins(
        "env/spheres.glb",
        "draco/spheres.glb",
        &flags,
        4.0 / 16384.0,
    );
    let err = convert_edited("draco/spheres.glb", |b, json| {
        let bin = 20 + json + 8;
        b[bin..bin + 64].iter_mut().for_each(|x| *x ^= 0x5a);
    });
    assert!(err.contains("KHR_draco_mesh_compression"), "{err}");
}

/// EXT_meshopt_compression: `scenes/meshopt/bumps.glb`, `scenes/bumps/bumps.gltf` as
/// meshoptimizer's gltfpack 1.3 ships it (`-cc -vpf`: meshopt streams, the exponential
/// filter on float positions, quantized texture coordinates, the normal map embedded),
/// converts to the plain triangles and renders the plain image within noise. A stream
/// cut short is refused by name.
#[test]
fn meshopt_meshes_convert_like_their_plain_twins() {
    let flags = ["--spp", "16", "--width", "80", "--height", "60"];
    assert_twins("bumps/bumps.gltf", "meshopt/bumps.glb", &flags, 1e-5);
    let err = convert_edited("meshopt/bumps.glb", |b, json| {
        let text = String::from_utf8(b[20..20 + json].to_vec()).unwrap();
        // The first stream's length: shorter than its data.
        let ext = text
            .find("\"EXT_meshopt_compression\":{\"buffer\"")
            .unwrap();
        let at = ext + text[ext..].find("\"byteLength\":").unwrap() + 13;
        let text = format!(
            "{}1{}",
            &text[..at],
            &text[at..].trim_start_matches(char::is_numeric)
        );
        let text = format!("{text:<json$}");
        b[20..20 + json].copy_from_slice(&text.as_bytes()[..json]);
    });
    assert!(
        err.contains("EXT_meshopt_compression") && err.contains("buffer view"),
        "{err}"
    );
}

/// What Canopy does not read is named, never dropped in silence: an extension a material
/// uses (its materials listed, the file converts; the archive's notes and `inspect` list
/// it) and an extension the file requires (refused by name, no archive written).
#[test]
fn unread_gltf_features_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let used = tiny_glb(dir.path(), "used.glb", |j, _| {
        j["materials"][0]["extensions"] = serde_json::json!({
            "KHR_materials_iridescence": {"iridescenceFactor": 1.0},
            "KHR_materials_clearcoat": {"clearcoatFactor": 1.0}
        });
        j["extensionsUsed"] = serde_json::json!([
            "KHR_materials_iridescence",
            "KHR_materials_clearcoat",
            "KHR_xmp_json_ld"
        ]);
        j["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"] =
            j["meshes"][0]["primitives"][0]["attributes"]["POSITION"].clone();
    });
    let out = dir.path().join("used.canopy");
    let err = succeeds_saying(&["convert", s(&used), "-o", s(&out)]);
    assert!(
        err.contains("use KHR_materials_iridescence, which Canopy does not render"),
        "{err}"
    );
    assert!(
        err.contains("KHR_xmp_json_ld, which Canopy does not read"),
        "{err}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&ok(&["inspect", s(&out), "--json"])).unwrap();
    let notes: Vec<&str> = report["notes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n.as_str().unwrap())
        .collect();
    assert_eq!(notes.len(), 2, "{notes:?}");
    assert!(notes
        .iter()
        .any(|n| n.contains("use KHR_materials_iridescence")));
    assert!(notes.iter().any(|n| n.contains("KHR_xmp_json_ld")));
    let required = tiny_glb(dir.path(), "required.glb", |j, _| {
        j["extensionsUsed"] = serde_json::json!(["KHR_materials_variants"]);
        j["extensionsRequired"] = serde_json::json!(["KHR_materials_variants"]);
    });
    let out = dir.path().join("required.canopy");
    let err = fails(&["convert", s(&required), "-o", s(&out)]);
    assert!(
        err.contains("requires KHR_materials_variants, which Canopy does not read"),
        "{err}"
    );
    assert!(!out.exists());
}

/// Sparse accessors (glTF 3.6.2.3): positions with no buffer view (zeros) and three
/// substitutions make one triangle with the substituted corners; a substitution past the
/// accessor's elements is refused by name.
#[test]
fn sparse_positions_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let gltf = |index2: u16| {
        let mut bin: Vec<u8> = [1u16, 2, index2, 0]
            .iter()
            .flat_map(|i| i.to_le_bytes())
            .collect();
        bin.extend(
            [1.0f32, 0.0, 0.0, 0.0, 2.0, 0.0]
                .iter()
                .flat_map(|v| v.to_le_bytes()),
        );
        bin.extend([0.0f32, 0.0, 0.5].iter().flat_map(|v| v.to_le_bytes()));
        use base64::Engine;
        let uri = format!(
            "data:application/octet-stream;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&bin)
        );
        serde_json::json!({
            "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}],
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "buffers": [{"byteLength": bin.len(), "uri": uri}],
            "bufferViews": [
                {"buffer": 0, "byteOffset": 0, "byteLength": 8},
                {"buffer": 0, "byteOffset": 8, "byteLength": 36}
            ],
            "accessors": [{"componentType": 5126, "count": 3, "type": "VEC3",
                "min": [0, 0, 0], "max": [1, 2, 0.5],
                "sparse": {"count": 3,
                    "indices": {"bufferView": 0, "componentType": 5123},
                    "values": {"bufferView": 1}}}]
        })
        .to_string()
    };
    // Elements 1, 2 and 0 replaced: (1, 0, 0), (0, 2, 0), (0, 0, 0.5).
    let good = dir.path().join("sparse.gltf");
    std::fs::write(&good, gltf(0)).unwrap();
    let arc = dir.path().join("sparse.canopy");
    ok(&["--quiet", "convert", s(&good), "-o", s(&arc)]);
    let report: serde_json::Value =
        serde_json::from_str(&ok(&["inspect", s(&arc), "--json"])).unwrap();
    assert_eq!(report["triangles"], 1);
    assert_eq!(report["bounds_max"], serde_json::json!([1.0, 2.0, 0.5]));
    let bad = dir.path().join("past.gltf");
    std::fs::write(&bad, gltf(7)).unwrap();
    let err = fails(&["convert", s(&bad), "-o", s(&dir.path().join("past.canopy"))]);
    assert!(err.contains("sparse storage: an index is past"), "{err}");
}

/// KHR_materials_pbrSpecularGlossiness, even required, converts: its materials shaded as
/// metallic-roughness, named in a warning that says how.
#[test]
fn specular_glossiness_materials_convert_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let glb = tiny_glb(dir.path(), "sg.glb", |j, _| {
        j["materials"][0]["extensions"] = serde_json::json!({
            "KHR_materials_pbrSpecularGlossiness": {
                "diffuseFactor": [0.2, 0.4, 0.6, 1.0], "specularFactor": [0.04, 0.04, 0.04],
                "glossinessFactor": 0.7}});
        let ext = serde_json::json!(["KHR_materials_pbrSpecularGlossiness"]);
        j["extensionsUsed"] = ext.clone();
        j["extensionsRequired"] = ext;
    });
    let out = dir.path().join("sg.canopy");
    let err = succeeds_saying(&["convert", s(&glb), "-o", s(&out)]);
    assert!(
        err.contains("uses KHR_materials_pbrSpecularGlossiness: shaded as metallic-roughness"),
        "{err}"
    );
    ok(&["inspect", s(&out)]);
}

/// KHR_materials_unlit: with every material of the Cornell box unlit (the lamp's emission
/// taken away), each pixel that sees one surface shows exactly its base colour: the
/// surfaces reflect nothing and emit their colour. Only pixels on edges, which average two
/// surfaces (7% at 96 × 96), may differ.
#[test]
fn unlit_materials_show_their_base_colour() {
    let dir = tempfile::tempdir().unwrap();
    let glb = tiny_glb(dir.path(), "unlit.glb", |j, _| {
        for m in j["materials"].as_array_mut().unwrap() {
            m["extensions"] = serde_json::json!({"KHR_materials_unlit": {}});
            m.as_object_mut().unwrap().remove("emissiveFactor");
        }
        j["extensionsUsed"] = serde_json::json!(["KHR_materials_unlit"]);
    });
    let colours: Vec<[f32; 3]> = [
        [0.885809, 0.698859, 0.666422],
        [0.570068, 0.0430135, 0.0443706],
        [0.105421, 0.37798, 0.076425],
        [0.45, 0.3, 0.9],
        [0.936461, 0.740433, 0.705267],
        // The background above the box: no light reaches it.
        [0.0; 3],
    ]
    .to_vec();
    let arc = dir.path().join("unlit.canopy");
    ok(&["--quiet", "convert", s(&glb), "-o", s(&arc)]);
    let flags = ["--spp", "4", "--width", "96", "--height", "96"];
    let (img, _) = render(&arc, &dir.path().join("o.exr"), &flags);
    let plain = img
        .pixels
        .iter()
        .filter(|p| {
            colours
                .iter()
                .any(|c| (0..3).all(|k| (p[k] - c[k]).abs() < 1e-5))
        })
        .count();
    assert!(
        plain * 10 >= img.pixels.len() * 9,
        "{plain} of {} pixels show a base colour",
        img.pixels.len()
    );
}

/// A scan's texture coordinates (which Canopy does not apply: PLY names no image) are
/// named at convert, with what is used instead, and listed by `inspect`; the mesh still
/// converts, its colours applied.
#[test]
fn ply_texture_coordinates_are_named_and_listed() {
    let dir = tempfile::tempdir().unwrap();
    let ply = dir.path().join("c.ply");
    std::fs::write(
        &ply,
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty float s\nproperty float t\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 255 0 0 0 0\n1 0 0 0 255 0 1 0\n0 1 0 0 0 255 0 1\n3 0 1 2\n",
    )
    .unwrap();
    let out = dir.path().join("c.canopy");
    let err = succeeds_saying(&["convert", s(&ply), "-o", s(&out)]);
    let said = "its vertices carry s, t, which Canopy does not apply";
    assert!(err.contains(said), "{err}");
    let listed = ok(&["inspect", s(&out)]);
    assert!(listed.contains(said), "{listed}");
    assert!(listed.contains("vertex-colours"), "{listed}");
}
