//! Side files that lie about their sizes: light stores, bakes, EXR tiles and scene files,
//! crafted small, with their checksums recomputed so the lie reaches the decoder. Each is
//! refused with an error naming the field, in a child process whose peak RSS is measured:
//! within the budget + 64 MiB whatever the file declares.

mod common;

use canopy_format::bake_parts::BakeParts;
use common::*;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

const BUDGET: &str = "64MiB";
/// What a child may hold past the budget: the film, the binary, the allocator's slack.
const SLACK: u64 = 64 << 20;

/// Runs canopy; returns its exit code (None: killed by a signal), stderr and peak RSS.
/// The child is forked, not spawned with vfork: a vfork child's peak RSS would start from
/// this test process's own peak (they share the address space until exec). A forked
/// child starts from this process's current RSS, which the tests here keep small (their
/// zstd bombs are made by streaming). `CANOPY_BIN` runs another build instead (to show
/// these cases fail on a build without the checks).
#[allow(clippy::zombie_processes)] // reaped by wait4, which also gives its rusage
fn measured(args: &[&str]) -> (Option<i32>, String, u64) {
    let bin = std::env::var_os("CANOPY_BIN").unwrap_or(env!("CARGO_BIN_EXE_canopy").into());
    let mut cmd = Command::new(bin);
    // SAFETY: the hook does nothing; its presence makes std fork and exec.
    unsafe {
        std::os::unix::process::CommandExt::pre_exec(&mut cmd, || Ok(()));
    }
    let mut child = cmd
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run canopy");
    let mut err = String::new();
    child
        .stderr
        .take()
        .unwrap()
        .read_to_string(&mut err)
        .unwrap();
    let mut status = 0;
    // SAFETY: rusage is plain data; wait4 fills it for this child.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: waits for our own child, which has not been reaped.
    let pid = unsafe { libc::wait4(child.id() as i32, &mut status, 0, &mut usage) };
    assert_eq!(pid, child.id() as i32);
    let code = libc::WIFEXITED(status).then(|| libc::WEXITSTATUS(status));
    (code, err, usage.ru_maxrss as u64 * 1024)
}

/// Canopy refuses cleanly (exit 1), its error says `expect`, and its peak RSS stayed
/// within the budget + `SLACK`.
fn refused(args: &[&str], expect: &str) {
    let (code, err, rss) = measured(args);
    assert_eq!(code, Some(1), "{args:?} should fail cleanly: {err}");
    assert!(!err.contains("panicked"), "{args:?} panicked: {err}");
    assert!(
        err.contains(expect),
        "{args:?}: {err:?} should say {expect:?}"
    );
    assert!(
        rss < (64 << 20) + SLACK,
        "{args:?}: peak RSS {:.0} MiB",
        rss as f64 / 1048576.0
    );
}

/// cbox with its back wall rough metal (so a bake stores glossy coefficients), converted.
fn archive(dir: &Path) -> PathBuf {
    let glb = tiny_glb(dir, "c.glb", |json, _| {
        let m = &mut json["materials"][0]["pbrMetallicRoughness"];
        m["metallicFactor"] = 1.0.into();
        m["roughnessFactor"] = 0.4.into();
    });
    let out = dir.join("c.canopy");
    convert(&glb, &out, None);
    out
}

/// A 16×16, 1-spp cone render of `a` into `out`, with `extra` flags.
fn cone_args(a: &Path, out: &Path, extra: &[&str]) -> Vec<String> {
    let base = [
        "--quiet",
        "render",
        s(a),
        "-o",
        s(out),
        "--integrator",
        "cone",
    ];
    let size = ["--spp", "1", "--width", "16", "--height", "16"];
    [&base[..], &size, extra]
        .concat()
        .into_iter()
        .map(str::to_string)
        .collect()
}

fn strs(v: &[String]) -> Vec<&str> {
    v.iter().map(String::as_str).collect()
}

fn store(dir: &Path, a: &Path) -> Vec<u8> {
    let path = dir.join("l.store");
    ok(&strs(&cone_args(
        a,
        &dir.join("l.exr"),
        &["--store-out", s(&path)],
    )));
    std::fs::read(path).unwrap()
}

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn render_with_store(a: &Path, dir: &Path, store: &Path) -> Vec<String> {
    let extra = ["--mem-budget", BUDGET, "--store-in", s(store)];
    cone_args(a, &dir.join("r.exr"), &extra)
}

fn refused_store(a: &Path, dir: &Path, bytes: &[u8], expect: &str) {
    let path = write(dir, "m.store", bytes);
    refused(&strs(&render_with_store(a, dir, &path)), expect);
}

/// A header field at `at` set to `v`, the checksums recomputed.
fn with_u64(seed: &[u8], at: usize, v: u64) -> Vec<u8> {
    let mut b = seed.to_vec();
    b[at..at + 8].copy_from_slice(&v.to_le_bytes());
    canopy::light_store::file::reseal(&mut b);
    b
}

/// The body replaced by one zstd frame of `records` followed by zeros to `len` bytes,
/// made by streaming (no buffer of `len`), `entries` declared.
fn with_body(seed: &[u8], entries: u64, records: &[u8], len: usize) -> Vec<u8> {
    use std::io::Write;
    let mut b = seed[..128].to_vec();
    b[40..48].copy_from_slice(&entries.to_le_bytes());
    let mut z = zstd::stream::write::Encoder::new(Vec::new(), 1).unwrap();
    z.write_all(records).unwrap();
    let zeros = vec![0u8; 1 << 20];
    let mut left = len.saturating_sub(records.len());
    while left > 0 {
        let n = left.min(zeros.len());
        z.write_all(&zeros[..n]).unwrap();
        left -= n;
    }
    b.extend(z.finish().unwrap());
    canopy::light_store::file::reseal(&mut b);
    b
}

#[test]
fn light_stores_that_lie_about_their_sizes_or_keys_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let a = archive(d);
    let seed = store(d, &a);
    let entries = u64::from_le_bytes(seed[40..48].try_into().unwrap());
    assert!(entries > 1, "the seed store holds light");
    // The seed itself is read.
    let path = write(d, "seed.store", &seed);
    ok(&strs(&render_with_store(&a, d, &path)));
    // 2^32 entries in a 6 KB file: the key space and the budget both refuse it.
    refused_store(&a, d, &with_u64(&seed, 40, 1 << 32), "entries 4294967296");
    // A valid frame of 1 GiB of zeros behind a header declaring 2^24 entries.
    refused_store(
        &a,
        d,
        &with_body(&seed, 1 << 24, &[], 1 << 30),
        "entries 16777216",
    );
    // The seed's records then zeros to 2.2 GB: as many entries as the keys allow, or as
    // the seed; the reader stops at the first record past them.
    let raw = zstd::decode_all(&seed[128..]).unwrap();
    let bomb = with_body(&seed, entries + 1000, &raw, 2_200_000_000);
    refused_store(&a, d, &bomb, "keys not increasing");
    let bomb = with_body(&seed, entries, &raw, 2_200_000_000);
    refused_store(
        &a,
        d,
        &bomb,
        &format!("body_len {} for {entries} entries", bomb.len() - 128),
    );
    let longer = with_body(&seed, entries, &raw, raw.len() + 640);
    refused_store(&a, d, &longer, "holds more than");
    // Keys: u64::MAX, and an instance's key in an archive without instances.
    let last = raw.len() - 64;
    for key in [
        u64::MAX,
        2 * u64::from_le_bytes(raw[last..last + 8].try_into().unwrap()) + (1 << 40),
    ] {
        let mut r = raw.clone();
        r[last..last + 8].copy_from_slice(&key.to_le_bytes());
        refused_store(
            &a,
            d,
            &with_body(&seed, entries, &r, 0),
            "key outside the archive",
        );
    }
    // Reserved bytes, in a record and in the header.
    let mut r = raw.clone();
    r[60] = 1;
    refused_store(&a, d, &with_body(&seed, entries, &r, 0), "reserved bytes");
    refused_store(&a, d, &with_u64(&seed, 96, 7), "reserved header bytes");
    // A wrong header size is named as such, not as a version.
    let mut h = seed.clone();
    h[12] = 64;
    canopy::light_store::file::reseal(&mut h);
    refused_store(&a, d, &h, "header_size 64, not 128");
    // body_len lying past the file.
    let mut l = seed.clone();
    canopy::light_store::file::reseal(&mut l);
    l[64..72].copy_from_slice(&(1u64 << 40).to_le_bytes());
    let mut hh = canopy::light_store::file::header_of(&l).unwrap();
    hh.entries = entries;
    canopy::light_store::file::set_header(&mut l, &hh);
    refused_store(&a, d, &l, "corrupt");
}

fn bake(dir: &Path, a: &Path) -> Vec<u8> {
    let path = dir.join("b.radiance");
    ok(&[
        "--quiet",
        "bake",
        s(a),
        "-o",
        s(&path),
        "--bake-samples",
        "1",
    ]);
    std::fs::read(path).unwrap()
}

/// Both readers of a bake refuse it: `inspect --verify` and a PBGI render.
fn refused_bake(a: &Path, dir: &Path, bytes: &[u8], expect: &str) {
    let path = write(dir, "m.radiance", bytes);
    refused(
        &[
            "inspect",
            s(a),
            "--bake",
            s(&path),
            "--verify",
            "--mem-budget",
            BUDGET,
        ],
        expect,
    );
    refused(
        &[
            "--quiet",
            "render",
            s(a),
            "-o",
            s(&dir.join("p.exr")),
            "--integrator",
            "pbgi",
            "--spp",
            "1",
            "--width",
            "16",
            "--height",
            "16",
            "--mem-budget",
            BUDGET,
            "--bake-in",
            s(&path),
        ],
        expect,
    );
}

#[test]
fn bakes_that_lie_about_their_sizes_or_kinds_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let a = archive(d);
    let seed = bake(d, &a);
    let parts = BakeParts::read(&seed).unwrap();
    assert!(
        parts.header.wavelet_n > 0,
        "the seed bake holds glossy light"
    );
    assert!(
        parts.write() == seed,
        "taking apart and putting back is exact"
    );
    ok(&[
        "inspect",
        s(&a),
        "--bake",
        s(&write(d, "ok.radiance", &seed)),
        "--verify",
    ]);
    // A block declaring 357,913,760 patches, its bytes a frame of zeros.
    let big = (0..parts.blocks.len())
        .max_by_key(|&i| parts.entries[i].node_count)
        .unwrap();
    let mut p = parts.clone();
    let e = &mut p.entries[big];
    let fixed = e.raw_len as u64 - e.patch_count as u64 * 12;
    // As many as a u32 raw_len can declare, every size consistent with it.
    let patches = 357_913_760.min((u32::MAX as u64 - fixed) / 12);
    e.patch_count = patches as u32;
    e.raw_len = (fixed + 12 * patches) as u32;
    p.blocks[big] = vec![0; 1 << 20];
    refused_bake(&a, d, &p.write(), &format!("patch_count {patches}"));
    // The same count behind a block whose frame holds just what it declares: the
    // triangles' pyramids, read first, name the lie before the patches are inflated.
    let mut p = parts.clone();
    let tris = (p.entries[big].raw_len as u64
        - p.entries[big].node_count as u64 * 96
        - p.entries[big].patch_count as u64 * 12) as usize;
    let nodes = p.entries[big].node_count as usize * 96;
    if tris > 0 {
        p.entries[big].patch_count += 1;
        p.entries[big].raw_len += 12;
        p.blocks[big].splice(nodes + tris..nodes + tris, [0u8; 12]);
        refused_bake(&a, d, &p.write(), "pyramids end at");
    }
    // wavelet_n 64, beyond what bake writes.
    let mut p = parts.clone();
    p.header.wavelet_n = 64;
    refused_bake(&a, d, &p.write(), "wavelet_n 64");
    // A coefficient record's kind flipped: render and --verify refuse it alike, in
    // FORMAT.md's words.
    let mut p = parts.clone();
    let (i, at) = coef_record(&p, &a);
    let kind = u32::from_le_bytes(p.blocks[i][at + 4..at + 8].try_into().unwrap());
    p.blocks[i][at + 4..at + 8].copy_from_slice(&(1 - kind).to_le_bytes());
    refused_bake(&a, d, &p.write(), "where its place in the tree allows");
}

/// A block with a coefficient record, and where its first record lies in the block:
/// after the nodes, `patch_of` (one u32 per triangle of the archive's page), the patches
/// and the section's two counts.
fn coef_record(p: &BakeParts, a: &Path) -> (usize, usize) {
    let pages = canopy_format::Archive::open(a).unwrap().entries().unwrap();
    for (i, (e, b)) in p.entries.iter().zip(&p.blocks).enumerate() {
        let start = e.node_count as usize * 96
            + pages[i].tri_count as usize * 4
            + e.patch_count as usize * 12;
        let records = u32::from_le_bytes(b[start..start + 4].try_into().unwrap());
        if records > 0 {
            return (i, start + 8);
        }
    }
    panic!("no block holds a coefficient record");
}

/// A one-pixel tile as `render --crop` writes it (with the attributes `assemble` wants),
/// its data or display window's box at `field` rewritten.
fn exr_with(dir: &Path, name: &str, field: &[u8], b: [i32; 4]) -> PathBuf {
    let p = dir.join(name);
    let tags = ["canopy.archive", "canopy.settings", "canopy.seed"]
        .map(|k| (k.to_string(), "x".to_string()))
        .to_vec();
    let frame = canopy::image::Frame {
        display: [1, 1],
        origin: [0, 0],
        tags,
    };
    canopy::image::Image::new(1, 1)
        .write_exr_framed(&p, &frame)
        .unwrap();
    patch(&p, field, b"box2i", &b.map(i32::to_le_bytes).concat());
    p
}

/// Rewrites attribute `field` (of type `kind`) of an EXR's header with `value`.
fn patch(p: &Path, field: &[u8], kind: &[u8], value: &[u8]) {
    let mut bytes = std::fs::read(p).unwrap();
    let key = [field, b"\0", kind, b"\0"].concat();
    let at = bytes.windows(key.len()).position(|w| w == key).unwrap() + key.len() + 4;
    bytes[at..at + value.len()].copy_from_slice(value);
    std::fs::write(p, bytes).unwrap();
}

/// A tiled EXR of one 1×1 tile, then made to declare a `side`² data window in one tile of
/// that size: a consistent file of a few hundred bytes whose one chunk would decode to
/// `side`² pixels.
fn huge_tiled(dir: &Path, side: i32) -> PathBuf {
    use exr::prelude::*;
    let p = dir.join("huge.exr");
    let encoding = Encoding {
        compression: Compression::Uncompressed,
        blocks: Blocks::Tiles(Vec2(1, 1)),
        line_order: LineOrder::Increasing,
    };
    let pixels = SpecificChannels::rgb(|_: Vec2<usize>| (0f32, 0f32, 0f32));
    let layer = Layer::new((1, 1), LayerAttributes::default(), encoding, pixels);
    exr::image::Image::from_layer(layer)
        .write()
        .to_file(&p)
        .unwrap();
    patch(
        &p,
        b"dataWindow",
        b"box2i",
        &[0, 0, side - 1, side - 1].map(i32::to_le_bytes).concat(),
    );
    let tile = [(side as u32).to_le_bytes(), (side as u32).to_le_bytes()].concat();
    patch(&p, b"tiles", b"tiledesc", &tile);
    p
}

#[test]
fn exr_images_that_declare_huge_or_inverted_windows_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let good = d.join("good.exr");
    canopy::image::Image::new(1, 1).write_exr(&good).unwrap();
    let out = d.join("out.exr");
    let huge = huge_tiled(d, 100_000);
    assert!(std::fs::metadata(&huge).unwrap().len() < 1000);
    refused(
        &["compare", s(&huge), s(&good)],
        "100000x100000 data window",
    );
    refused(
        &["assemble", s(&huge), "-o", s(&out)],
        "100000x100000 data window",
    );
    let frame = exr_with(d, "frame.exr", b"displayWindow", [0, 0, 69_999, 69_999]);
    refused(
        &["assemble", s(&frame), "-o", s(&out)],
        "70000x70000 display window",
    );
    let inverted = exr_with(d, "inv.exr", b"displayWindow", [0, 0, -5, 0]);
    refused(
        &["assemble", s(&inverted), "-o", s(&out)],
        "display window is inverted",
    );
    // Within the documented maximum but not the budget: refused before decoding.
    let big = exr_with(d, "big.exr", b"displayWindow", [0, 0, 8191, 8191]);
    refused(
        &["assemble", s(&big), "-o", s(&out), "--mem-budget", BUDGET],
        "more than --mem-budget 64MiB",
    );
    assert!(!out.exists(), "nothing written");
}

#[test]
fn scene_files_with_degenerate_directions_or_cones_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cases = [
        (
            "up = [0.0, 0.0, 0.0]",
            "is zero or along the view direction",
        ),
        ("up = [nan, 1.0, 0.0]", "must be finite"),
        (
            "up = [0.0, 0.0, -1.0]",
            "is zero or along the view direction",
        ),
        ("yfov_degrees = 0.0", "yfov_degrees 0"),
    ];
    let bunny = scene("bunny.ply");
    let out = d.join("x.canopy");
    let refused = |toml: &str| {
        let path = write(d, "s.toml", toml.as_bytes());
        fails(&["convert", s(&bunny), "-o", s(&out), "--scene", s(&path)])
    };
    let base = "[[camera]]\nposition = [0.0, 0.0, 4.0]\nlook_at = [0.0, 0.0, 0.0]\n";
    for (line, expect) in cases {
        let err = refused(&format!("{base}{line}\n"));
        assert!(err.contains(expect), "{line}: {err}");
    }
    let spot = "[[light]]\ntype = \"spot\"\nposition = [0.0, 1.0, 0.0]\nouter_cone_degrees = 0.0\n";
    let err = refused(spot);
    assert!(err.contains("outer 0°"), "{err}");
    assert!(!d.join("x.canopy").exists());
}

/// The background page loader holds the cache only while its guard lives, so a render
/// that fails half-way (a side file refused after the loader started) leaves no thread
/// and no cache behind; the fuzz harness met thousands of such threads before.
#[test]
fn the_page_loader_lets_go_of_the_cache_when_its_guard_drops() {
    use std::sync::Arc;
    let dir = tempfile::tempdir().unwrap();
    let a = archive(dir.path());
    let archive = Arc::new(canopy_format::Archive::open(&a).unwrap());
    let cache = canopy::paging::PageCache::new(archive, Some(64 << 20), 1).unwrap();
    let loader = cache.start_prefetch();
    assert!(Arc::strong_count(&cache) > 1, "the loader shares the cache");
    drop(loader);
    assert_eq!(Arc::strong_count(&cache), 1, "nothing else holds the cache");
}
