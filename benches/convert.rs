//! Converter triangles/s (bundled scenes, end to end: import, build, compress, write) and
//! page decode MB/s (checksum + zstd + parse + index checks, per decoded byte; then the
//! renderer's decode, and its four-wide tree build alone), and the time to open an archive
//! of about 1 K and of about 100 K pages (it should not grow with the page count).

use canopy::convert::{convert, ConvertOptions};
use canopy::paging::{wide, Page};
use canopy_format::Archive;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::path::{Path, PathBuf};

fn scene(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("scenes")
        .join(name)
}

fn options(input: &str, output: &Path) -> ConvertOptions {
    ConvertOptions::new(vec![scene(input)], output.to_path_buf())
}

fn bench_convert(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut g = c.benchmark_group("convert");
    g.sample_size(10);
    for (name, tris) in [("bunny_box.glb", 69_465u64), ("sponza.glb", 263_167)] {
        let out = dir.path().join("out.canopy");
        g.throughput(Throughput::Elements(tris));
        g.bench_function(name, |b| b.iter(|| convert(&options(name, &out)).unwrap()));
    }
    g.finish();
}

fn bench_decode(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sponza.canopy");
    convert(&options("sponza.glb", &out)).unwrap();
    let a = Archive::open(&out).unwrap();
    let raw: u64 = a.entries().unwrap().iter().map(|e| e.raw_len as u64).sum();
    let mut g = c.benchmark_group("page_decode");
    g.sample_size(20);
    g.throughput(Throughput::Bytes(raw));
    g.bench_function("sponza_all_pages", |b| {
        b.iter(|| {
            for p in 0..a.page_count() {
                std::hint::black_box(a.read_page(p).unwrap());
            }
        })
    });
    // The renderer's decode: the above, then boxes dequantized, triangles expanded and the
    // four-wide tree built; and that build alone.
    g.bench_function("sponza_pages_for_traversal", |b| {
        b.iter(|| {
            for p in 0..a.page_count() {
                std::hint::black_box(Page::decode(&a, p).unwrap());
            }
        })
    });
    let pages: Vec<Page> = (0..a.page_count())
        .map(|p| Page::decode(&a, p).unwrap())
        .collect();
    g.bench_function("sponza_wide_build", |b| {
        b.iter(|| {
            for p in &pages {
                std::hint::black_box(wide::build(&p.bvh, p.roots));
            }
        })
    });
    g.finish();
}

/// One mesh of `n` small random triangles (OBJ), converted with small and with default pages.
fn bench_open(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("random.obj");
    let n = 1_000_000u32;
    let mut rng = 0x9E37_79B9_7F4A_7C15u64;
    let mut unit = || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng >> 40) as f32 / (1u64 << 24) as f32
    };
    let mut text = String::new();
    for _ in 0..n {
        let c = [unit() * 100.0, unit() * 100.0, unit() * 100.0];
        for _ in 0..3 {
            let v = [0, 1, 2].map(|a| c[a] + unit() * 0.1);
            text += &format!("v {} {} {}\n", v[0], v[1], v[2]);
        }
    }
    for t in 0..n {
        text += &format!("f {} {} {}\n", 3 * t + 1, 3 * t + 2, 3 * t + 3);
    }
    std::fs::write(&input, text).unwrap();
    let mut g = c.benchmark_group("open");
    for page_nodes in [1024, 10] {
        let out = dir.path().join(format!("pages{page_nodes}.canopy"));
        let mut o = ConvertOptions::new(vec![input.clone()], out.clone());
        o.page_nodes = page_nodes;
        convert(&o).unwrap();
        let pages = Archive::open(&out).unwrap().page_count();
        g.bench_function(format!("{pages}_pages"), |b| {
            b.iter(|| std::hint::black_box(Archive::open(&out).unwrap()))
        });
    }
    g.finish();
}

criterion_group!(benches, bench_convert, bench_decode, bench_open);
criterion_main!(benches);
