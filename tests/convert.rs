//! End-to-end conversion: every bundled scene converts and verifies, output is deterministic,
//! the chunked (out-of-core) path gives a valid archive, OBJ + MTL + TOML scene files work.

mod common;
use canopy_format::{Archive, Features};
use common::*;

#[test]
fn bundled_scenes_convert_and_verify() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["cbox.glb", "bunny_box.glb", "sponza.glb", "bunny.ply"] {
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
