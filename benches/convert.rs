//! Converter triangles/s (bundled scenes, end to end: import, build, compress, write) and
//! page decode MB/s (checksum + zstd + parse + index checks, per decoded byte; then the
//! renderer's decode, and its four-wide tree build alone).

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
    let raw: u64 = a.pages.iter().map(|e| e.raw_len as u64).sum();
    let mut g = c.benchmark_group("page_decode");
    g.sample_size(20);
    g.throughput(Throughput::Bytes(raw));
    g.bench_function("sponza_all_pages", |b| {
        b.iter(|| {
            for p in 0..a.pages.len() as u32 {
                std::hint::black_box(a.read_page(p).unwrap());
            }
        })
    });
    // The renderer's decode: the above, then boxes dequantized, triangles expanded and the
    // four-wide tree built; and that build alone.
    g.bench_function("sponza_pages_for_traversal", |b| {
        b.iter(|| {
            for p in 0..a.pages.len() as u32 {
                std::hint::black_box(Page::decode(&a, p).unwrap());
            }
        })
    });
    let pages: Vec<Page> = (0..a.pages.len() as u32)
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

criterion_group!(benches, bench_convert, bench_decode);
criterion_main!(benches);
