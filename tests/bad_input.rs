//! Bad input of every kind gets a clear error naming the file and the problem, exit code 1,
//! no panic, and nothing at the output path.

mod common;
use common::*;
use std::path::{Path, PathBuf};

const TRI_PLY_HEADER: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n";

fn convert_fails(input: &Path, expect: &[&str]) {
    let out = input.with_extension("canopy");
    let err = fails(&["convert", s(input), "-o", s(&out)]);
    assert!(
        err.contains(&*input.file_name().unwrap().to_string_lossy()),
        "error does not name the file: {err}"
    );
    for e in expect {
        assert!(err.contains(e), "error lacks '{e}': {err}");
    }
    assert!(!out.exists(), "a failed conversion left {}", out.display());
    let stray: Vec<_> = std::fs::read_dir(input.parent().unwrap())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with('.'))
        .collect();
    assert!(stray.is_empty(), "temporary files left: {stray:?}");
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

#[test]
fn missing_file() {
    let dir = tempfile::tempdir().unwrap();
    convert_fails(&dir.path().join("absent.ply"), &["no such file"]);
}

#[test]
fn unknown_extension() {
    let dir = tempfile::tempdir().unwrap();
    convert_fails(
        &write(dir.path(), "mesh.stl", b"solid"),
        &["unknown input type"],
    );
}

#[test]
fn truncated_ply() {
    let dir = tempfile::tempdir().unwrap();
    let full = std::fs::read(scene("bunny.ply")).unwrap();
    convert_fails(
        &write(dir.path(), "cut.ply", &full[..full.len() / 2]),
        &["truncated"],
    );
}

#[test]
fn nan_and_infinite_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let nan = format!("{TRI_PLY_HEADER}0 0 0\nnan 1 0\n0 1 0\n3 0 1 2\n");
    convert_fails(
        &write(dir.path(), "nan.ply", nan.as_bytes()),
        &["non-finite"],
    );
    let inf = format!("{TRI_PLY_HEADER}0 0 0\n1 1e39 0\n0 1 0\n3 0 1 2\n");
    convert_fails(
        &write(dir.path(), "inf.ply", inf.as_bytes()),
        &["non-finite"],
    );
    convert_fails(
        &write(
            dir.path(),
            "nan.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 inf 0\nf 1 2 3\n",
        ),
        &["non-finite"],
    );
}

#[test]
fn out_of_range_index() {
    let dir = tempfile::tempdir().unwrap();
    let ply = format!("{TRI_PLY_HEADER}0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n");
    convert_fails(
        &write(dir.path(), "idx.ply", ply.as_bytes()),
        &["out of range"],
    );
    convert_fails(
        &write(
            dir.path(),
            "idx.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n",
        ),
        &["out of range"],
    );
}

#[test]
fn empty_mesh() {
    let dir = tempfile::tempdir().unwrap();
    let ply = "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n";
    convert_fails(&write(dir.path(), "empty.ply", ply.as_bytes()), &["empty"]);
}

#[test]
fn absurd_element_count() {
    let dir = tempfile::tempdir().unwrap();
    let ply = "ply\nformat binary_little_endian 1.0\nelement vertex 999999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n";
    convert_fails(&write(dir.path(), "huge.ply", ply.as_bytes()), &["claims"]);
}

#[test]
fn corrupt_glb() {
    let dir = tempfile::tempdir().unwrap();
    let mut glb = std::fs::read(scene("cbox.glb")).unwrap();
    for b in &mut glb[20..60] {
        *b = b'#';
    }
    convert_fails(&write(dir.path(), "bad.glb", &glb), &["not a valid glTF"]);
    convert_fails(
        &write(
            dir.path(),
            "short.glb",
            &std::fs::read(scene("cbox.glb")).unwrap()[..100],
        ),
        &["not a valid glTF"],
    );
}

/// A valid archive of the bunny to damage.
fn archive(dir: &Path) -> (PathBuf, Vec<u8>) {
    let p = dir.join("good.canopy");
    ok(&["convert", s(&scene("bunny.ply")), "-o", s(&p)]);
    let bytes = std::fs::read(&p).unwrap();
    (p, bytes)
}

fn inspect_fails(path: &Path, expect: &str) {
    let err = fails(&["inspect", "--verify", s(path)]);
    assert!(
        err.contains(&*path.file_name().unwrap().to_string_lossy()),
        "error does not name the file: {err}"
    );
    assert!(err.contains(expect), "error lacks '{expect}': {err}");
}

#[test]
fn truncated_archive() {
    let dir = tempfile::tempdir().unwrap();
    let (_, bytes) = archive(dir.path());
    for cut in [0, 5, 100, bytes.len() / 2, bytes.len() - 1] {
        let p = write(dir.path(), "cut.canopy", &bytes[..cut]);
        let err = fails(&["inspect", "--verify", s(&p)]);
        assert!(
            err.contains("cut.canopy")
                && (err.contains("truncated") || err.contains("not a Canopy archive")),
            "cut at {cut}: {err}"
        );
    }
}

#[test]
fn flipped_byte_in_a_page() {
    let dir = tempfile::tempdir().unwrap();
    let (good, bytes) = archive(dir.path());
    let a = canopy_format::Archive::open(&good).unwrap();
    let e = a.entry(a.page_count() / 2).unwrap();
    let mut bad = bytes.clone();
    bad[e.offset as usize + e.compressed_len as usize / 2] ^= 0x10;
    inspect_fails(&write(dir.path(), "flip.canopy", &bad), "checksum mismatch");
    // A flipped byte in the tables or the header is caught too.
    let mut bad = bytes.clone();
    let last = bad.len() - 10;
    bad[last] ^= 1;
    inspect_fails(&write(dir.path(), "table.canopy", &bad), "checksum");
    let mut bad = bytes;
    bad[40] ^= 1;
    inspect_fails(&write(dir.path(), "header.canopy", &bad), "checksum");
}

#[test]
fn wrong_magic() {
    let dir = tempfile::tempdir().unwrap();
    let (_, mut bytes) = archive(dir.path());
    bytes[0] = b'X';
    inspect_fails(
        &write(dir.path(), "magic.canopy", &bytes),
        "not a Canopy archive",
    );
    inspect_fails(&scene("cbox.glb"), "not a Canopy archive");
}

#[test]
fn newer_format_version() {
    let dir = tempfile::tempdir().unwrap();
    let (_, mut bytes) = archive(dir.path());
    bytes[8..10].copy_from_slice(&(canopy_format::VERSION_MAJOR + 1).to_le_bytes());
    inspect_fails(
        &write(dir.path(), "future.canopy", &bytes),
        "newer than this canopy reads",
    );
}

#[test]
fn older_format_version() {
    let dir = tempfile::tempdir().unwrap();
    let (_, mut bytes) = archive(dir.path());
    bytes[8..10].copy_from_slice(&1u16.to_le_bytes());
    let path = write(dir.path(), "old.canopy", &bytes);
    inspect_fails(&path, "older than this canopy reads");
    inspect_fails(&path, "canopy convert");
}

#[test]
fn missing_archive_and_bad_sizes() {
    let dir = tempfile::tempdir().unwrap();
    inspect_fails(&dir.path().join("nothing.canopy"), "No such file");
    let out = dir.path().join("o.canopy");
    let cbox = scene("cbox.glb");
    let convert =
        |out: &str, budget: &str| fails(&["convert", s(&cbox), "-o", out, "--mem-budget", budget]);
    assert!(convert(s(&out), "12 parsecs").contains("unknown size unit"));
    assert!(convert(s(&out), "1MiB").contains("too small"));
    assert!(convert("/nonexistent-dir/x.canopy", "1GiB").contains("/nonexistent-dir"));
    assert!(!out.exists());
}

/// A conversion killed with SIGKILL at any moment leaves nothing of itself in the output
/// directory: spill files and the archive being written have no name until it is complete.
#[test]
fn killed_conversion_leaves_nothing_behind() {
    let dir = tempfile::tempdir().unwrap();
    // A 2M-triangle grid, big enough to still be converting when killed.
    let input = dir.path().join("grid.ply");
    grid_ply(&input, 1000);
    let out = dir.path().join("grid.canopy");
    let mut killed = 0;
    // Moments through import, partition and build (a small budget makes several chunks).
    for ms in [30u64, 150, 400, 900, 1600, 2500] {
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_canopy"))
            .args([
                "convert",
                s(&input),
                "-o",
                s(&out),
                "--quiet",
                "--mem-budget",
                "300MiB",
            ])
            .spawn()
            .unwrap();
        std::thread::sleep(std::time::Duration::from_millis(ms));
        child.kill().unwrap();
        let status = child.wait().unwrap();
        if !status.success() {
            killed += 1;
            assert!(
                !out.exists(),
                "killed at {ms} ms: a file at the output path"
            );
        }
        std::fs::remove_file(&out).ok();
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n != "grid.ply")
            .collect();
        assert!(left.is_empty(), "killed at {ms} ms, left behind: {left:?}");
    }
    assert!(
        killed >= 3,
        "only {killed} kills landed before the conversion ended"
    );
}

/// A named temporary left by a writer that died where unnamed files were unavailable is
/// removed by the next conversion into that directory; a live process's is kept.
#[test]
fn the_next_conversion_removes_a_dead_writers_temporary() {
    let dir = tempfile::tempdir().unwrap();
    let dead = dir.path().join(".x.canopy.tmp-2147480000");
    let live = dir
        .path()
        .join(format!(".x.canopy.tmp-{}", std::process::id()));
    std::fs::write(&dead, b"half").unwrap();
    std::fs::write(&live, b"busy").unwrap();
    ok(&[
        "convert",
        s(&scene("cbox.glb")),
        "-o",
        s(&dir.path().join("x.canopy")),
    ]);
    assert!(!dead.exists(), "a dead writer's temporary was kept");
    assert!(live.exists(), "a live writer's temporary was removed");
}

/// Spec-invalid accessors that panicked inside the gltf crate, and a buffer whose declared
/// length disagrees with the BIN chunk, are clear errors.
#[test]
fn invalid_gltf_accessors_and_buffers() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let pos = |j: &serde_json::Value| {
        j["meshes"][0]["primitives"][0]["attributes"]["POSITION"]
            .as_u64()
            .unwrap() as usize
    };
    let idx = |j: &serde_json::Value| {
        j["meshes"][0]["primitives"][0]["indices"].as_u64().unwrap() as usize
    };
    let stride = tiny_glb(d, "stride.glb", |j, _| {
        let v = j["accessors"][pos(j)]["bufferView"].as_u64().unwrap() as usize;
        j["bufferViews"][v]["byteStride"] = 4.into();
    });
    convert_fails(&stride, &["stride 4 for 12-byte elements"]);
    let float_idx = tiny_glb(d, "fidx.glb", |j, _| {
        let i = idx(j);
        j["accessors"][i]["componentType"] = 5126.into();
        j["accessors"][i]["type"] = "VEC3".into();
    });
    convert_fails(&float_idx, &["indices accessor", "the spec requires"]);
    let short = tiny_glb(d, "short.glb", |j, bin| {
        bin.truncate(bin.len() - 64);
        let _ = j;
    });
    convert_fails(&short, &["BIN chunk holds"]);
    let long = tiny_glb(d, "long.glb", |j, _| {
        let n = j["buffers"][0]["byteLength"].as_u64().unwrap();
        j["buffers"][0]["byteLength"] = (n - 400).into();
    });
    convert_fails(&long, &["BIN chunk holds"]);
    let count = tiny_glb(d, "count.glb", |j, _| {
        let p = pos(j);
        j["accessors"][p]["count"] = 100000000.into();
    });
    convert_fails(&count, &["elements need"]);
    let bad_accessor = tiny_glb(d, "acc.glb", |j, _| {
        j["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 999.into();
    });
    convert_fails(&bad_accessor, &["names accessor 999"]);
}

/// Side files that are not regular files are refused before they are read: an OBJ whose
/// material library is /dev/zero allocated until the process aborted.
#[test]
fn side_files_must_be_regular_files() {
    let dir = tempfile::tempdir().unwrap();
    let obj = write(
        dir.path(),
        "zero.obj",
        b"mtllib /dev/zero\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    );
    let err = fails(&["convert", s(&obj), "-o", s(&dir.path().join("z.canopy"))]);
    assert!(
        err.contains("/dev/zero") && err.contains("not a regular file"),
        "{err}"
    );
    let cbox = scene("cbox.glb");
    let err = fails(&[
        "convert",
        s(&cbox),
        "-o",
        s(&dir.path().join("z.canopy")),
        "--scene",
        "/dev/zero",
    ]);
    assert!(err.contains("not a regular file"), "{err}");
    let err = fails(&["inspect", s(dir.path())]);
    assert!(err.contains("not a regular file"), "{err}");
    // A line with no end is refused at its bound, not read whole.
    let mut long = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n# ".to_vec();
    long.resize(long.len() + (2 << 20), b'x');
    convert_fails(&write(dir.path(), "long.obj", &long), &["longer than"]);
    assert_eq!(
        std::fs::read_dir(dir.path()).unwrap().count(),
        2,
        "only the inputs remain"
    );
}

/// Float flags refuse NaN and infinities, and --threads refuses a count no machine uses.
#[test]
fn absurd_flag_values_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("c.canopy");
    ok(&["--quiet", "convert", s(&scene("cbox.glb")), "-o", s(&a)]);
    let o = dir.path().join("o.exr");
    for (flag, v) in [
        ("--exposure", "nan"),
        ("--exposure", "inf"),
        ("--cone-scale", "NaN"),
        ("--diffuse-tan=-1", ""),
        ("--threads", "100000"),
        ("--threads", "0"),
    ] {
        let mut args = vec!["render", s(&a), "-o", s(&o), "--spp", "1", flag];
        args.extend((!v.is_empty()).then_some(v));
        let err = fails(&args);
        let name = flag.split('=').next().unwrap();
        assert!(err.contains(name), "{flag} {v}: {err}");
    }
    assert!(!o.exists());
}

/// 20,000 coincident triangles: the build splits them by count into full leaves under a
/// balanced subtree (PLOC paired equal boxes one pair per sweep, quadratic in their number).
#[test]
fn coincident_triangles_build_a_balanced_tree() {
    let dir = tempfile::tempdir().unwrap();
    let mut obj = String::from("v 0 0 0\nv 1 0 0\nv 0 1 0\n");
    for _ in 0..20000 {
        obj.push_str("f 1 2 3\n");
    }
    let input = write(dir.path(), "same.obj", obj.as_bytes());
    let out = dir.path().join("same.canopy");
    ok(&["--quiet", "convert", s(&input), "-o", s(&out)]);
    let a = canopy_format::Archive::open(&out).unwrap();
    // 2,500 full leaves: a balanced tree is 12 levels deep.
    assert_eq!(a.header.triangles, 20000);
    assert!(a.header.depth <= 13, "depth {}", a.header.depth);
    assert!(
        a.header.nodes <= 2 * 2500 + 2,
        "{} nodes: leaves not full",
        a.header.nodes
    );
}

/// A glTF document (JSON, buffer embedded) with one triangle mesh used by `nodes`.
fn gltf_doc(nodes: serde_json::Value, scene_nodes: serde_json::Value, primitives: usize) -> String {
    let pos: Vec<u8> = [0f32, 0., 0., 1., 0., 0., 0., 1., 0.]
        .iter()
        .flat_map(|x| x.to_le_bytes())
        .collect();
    use base64::Engine;
    let uri = format!(
        "data:application/octet-stream;base64,{}",
        base64::engine::general_purpose::STANDARD.encode(&pos)
    );
    let prim = serde_json::json!({"attributes": {"POSITION": 0}});
    serde_json::json!({
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": scene_nodes}],
        "nodes": nodes, "meshes": [{"primitives": vec![prim; primitives]}],
        "buffers": [{"byteLength": 36, "uri": uri}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0.0, 0.0, 0.0], "max": [1.0, 1.0, 0.0]}]
    })
    .to_string()
}

/// glTF nodes form trees: a node that is its own ancestor, or the child of two nodes (40
/// levels of two children each made 2⁴⁰ instances), is refused before any triangle is read.
#[test]
fn gltf_node_cycles_and_shared_children_are_refused() {
    use serde_json::json;
    let dir = tempfile::tempdir().unwrap();
    let cycle = gltf_doc(
        json!([{"mesh": 0, "children": [1]}, {"children": [0]}]),
        json!([0]),
        1,
    );
    convert_fails(
        &write(dir.path(), "cycle.gltf", cycle.as_bytes()),
        &["its own ancestor"],
    );
    let mut nodes: Vec<_> = (0..40)
        .map(|k| json!({"children": [k + 1, k + 1]}))
        .collect();
    nodes.push(json!({"mesh": 0}));
    let dag = gltf_doc(json!(nodes), json!([0]), 1);
    convert_fails(
        &write(dir.path(), "dag.gltf", dag.as_bytes()),
        &["glTF nodes form trees"],
    );
}

/// Primitives without a material share one default material (one each would make
/// 65,536 of them fail with "more than 65535 materials").
#[test]
fn primitives_without_a_material_share_one_default() {
    let dir = tempfile::tempdir().unwrap();
    let doc = gltf_doc(
        serde_json::json!([{"mesh": 0}, {"mesh": 0}]),
        serde_json::json!([0, 1]),
        3,
    );
    let input = write(dir.path(), "plain.gltf", doc.as_bytes());
    let out = dir.path().join("plain.canopy");
    ok(&["--quiet", "convert", s(&input), "-o", s(&out)]);
    let a = canopy_format::Archive::open(&out).unwrap();
    assert_eq!((a.header.input_triangles, a.materials.len()), (6, 1));
}

/// `convert` never writes over one of its inputs (`-o` naming the input, by any path), and
/// `inspect` refuses a FIFO at once instead of blocking on it for a writer.
#[test]
fn outputs_never_overwrite_inputs_and_fifos_do_not_block() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("cbox.glb");
    std::fs::copy(scene("cbox.glb"), &input).unwrap();
    let sub = dir.path().join("sub");
    std::fs::create_dir(&sub).unwrap();
    let roundabout = sub.join("..").join("cbox.glb");
    for out in [&input, &roundabout] {
        let err = fails(&["convert", s(&input), "-o", s(out)]);
        assert!(err.contains("would overwrite the input"), "{err}");
    }
    assert_eq!(
        std::fs::read(&input).unwrap(),
        std::fs::read(scene("cbox.glb")).unwrap()
    );
    let fifo = dir.path().join("fifo.canopy");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status();
    if made.is_ok_and(|s| s.success()) {
        let err = fails(&["inspect", s(&fifo)]);
        assert!(err.contains("not a regular file"), "{err}");
        let err = fails(&["convert", s(&fifo), "-o", s(&dir.path().join("f.canopy"))]);
        assert!(err.contains("not a regular file"), "{err}");
    }
}

/// `render --stats`, `-o` and `compare --diff` refuse paths that would overwrite an input.
#[test]
fn render_and_compare_outputs_never_overwrite_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let a = dir.path().join("c.canopy");
    ok(&["--quiet", "convert", s(&scene("cbox.glb")), "-o", s(&a)]);
    let before = std::fs::read(&a).unwrap();
    let o = dir.path().join("o.exr");
    let err = fails(&["render", s(&a), "-o", s(&o), "--spp", "1", "--stats", s(&a)]);
    assert!(err.contains("overwrite the archive"), "{err}");
    assert_eq!(std::fs::read(&a).unwrap(), before);
    ok(&["--quiet", "render", s(&a), "-o", s(&o), "--spp", "1"]);
    let img = std::fs::read(&o).unwrap();
    let err = fails(&["compare", s(&o), s(&o), "--diff", s(&o)]);
    assert!(err.contains("overwrite an input"), "{err}");
    assert_eq!(std::fs::read(&o).unwrap(), img);
}

/// Material values a sloppy MTL writes (Kd 1.2, Ni 0.5, Ke −1) are clamped into glTF's
/// ranges as the renderer reads them; NaN is refused, naming the material and the field.
#[test]
fn mtl_values_are_clamped_and_nan_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let obj = write(
        dir.path(),
        "m.obj",
        b"mtllib m.mtl\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl x\nf 1 2 3\n",
    );
    write(
        dir.path(),
        "m.mtl",
        b"newmtl x\nKd 1.2 0.5 -0.1\nNi 0.5\nKe -1 0 2\n",
    );
    let out = dir.path().join("m.canopy");
    ok(&["--quiet", "convert", s(&obj), "-o", s(&out)]);
    let m = canopy_format::Archive::open(&out).unwrap().materials[0];
    assert_eq!(
        (m.base_color, m.ior, m.emission),
        ([1.0, 0.5, 0.0, 1.0], 1.5, [0.0, 0.0, 2.0])
    );
    std::fs::remove_file(&out).unwrap();
    write(dir.path(), "m.mtl", b"newmtl x\nNi nan\n");
    convert_fails(&obj, &["material 'x'", "ior is NaN"]);
}

/// A flag of an integrator that will not run is refused with exit status 2, naming the
/// flag, for every command that renders; the same flag is accepted where it applies.
#[test]
fn a_cone_flag_under_the_path_tracer_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let out = dir.path().join("o.exr");
    let (a, o) = (s(&arc), s(&out));
    let small = ["--spp", "1", "--width", "8", "--height", "8"];
    for (cmd, flag) in [
        (vec!["render", a, "-o", o], ["--cone-scale", "2"]),
        (
            vec!["render", a, "-o", o, "--integrator", "path"],
            ["--light-pass", "on"],
        ),
        (
            vec!["npp", a, "-o", s(dir.path()), "--integrators", "path"],
            ["--edge-rays", "0"],
        ),
        (
            vec!["eval", a, "--reference", o, "--integrators", "path"],
            ["--photons", "9"],
        ),
    ] {
        let args: Vec<&str> = cmd.iter().chain(&flag).copied().collect();
        let run = canopy(&args);
        let err = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(flag[0]) && err.contains("--integrator cone"),
            "{args:?}: {err}"
        );
    }
    let args: Vec<&str> = [
        "render",
        a,
        "-o",
        o,
        "--integrator",
        "cone",
        "--cone-scale",
        "2",
    ]
    .into_iter()
    .chain(small)
    .collect();
    ok(&args);
}

/// `npp` and `eval` take `--integrators`; a single `--integrator`, a noise target that is
/// not a positive number or a `--store-out` (each cone run would overwrite it) is a usage
/// error (status 2) that says so.
#[test]
fn npp_and_eval_refuse_a_single_integrator_and_a_bad_noise_target() {
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("c.canopy");
    convert(&scene("cbox.glb"), &arc, None);
    let (a, d) = (s(&arc), s(dir.path()));
    for (args, says) in [
        (
            vec!["npp", a, "-o", d, "--integrator", "cone"],
            "--integrators",
        ),
        (
            vec!["eval", a, "--reference", a, "--integrator", "cone"],
            "--integrators",
        ),
        (vec!["npp", a, "-o", d, "--noise", "0"], "positive"),
        (vec!["npp", a, "-o", d, "--noise", "NaN"], "positive"),
        (vec!["npp", a, "-o", d, "--spp", "0"], "--spp"),
        (
            vec!["eval", a, "--reference", a, "--store-out", "x.store"],
            "--store-out applies to canopy render",
        ),
    ] {
        let run = canopy(&args);
        let err = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(says), "{args:?}: {err}");
    }
    assert!(!dir.path().join("npp.csv").exists());
}
