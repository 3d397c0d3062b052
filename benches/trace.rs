//! Traversal rays/s on the paged tree (one thread, all pages resident): primary rays
//! through the scene camera, and incoherent rays (closest hit and any hit) from points on
//! surfaces in random directions, as a path tracer's bounces are.
//!
//! With `CANOPY_BENCH_RAYS=DIR` it also writes each scene's triangles and both ray sets to
//! DIR as little-endian f32 (`NAME.tris`: 9 per triangle; `NAME.primary`, `NAME.bounce`:
//! origin and direction, 6 per ray), for `tools/embree_compare.py` to trace the same rays.

use canopy::camera::Camera;
use canopy::convert::{convert, ConvertOptions};
use canopy::paging::PageCache;
use canopy::trace::{Ray, Tracer};
use canopy_format::Archive;
use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use glam::Vec3A as V;
use std::path::Path;
use std::sync::Arc;

const RAYS: usize = 4096;

fn rays(cache: &PageCache) -> (Vec<Ray>, Vec<Ray>) {
    let a = &cache.archive;
    let cam = Camera::new(&a.cameras[0], 64, 64);
    let primary: Vec<Ray> = (0..RAYS)
        .map(|i| cam.ray((i % 64) as f32 + 0.5, (i / 64 % 64) as f32 + 0.5))
        .collect();
    // Bounce rays: start where primary rays hit, leave in hashed directions.
    let mut tr = Tracer::new(cache);
    let mut seed = 1u64;
    let mut u = || {
        seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (seed >> 40) as f32 / (1u64 << 24) as f32 * 2.0 - 1.0
    };
    let bounce: Vec<Ray> = primary
        .iter()
        .filter_map(|r| tr.closest_hit(r))
        .map(|h| {
            let (p, _) = h.point();
            let n = h.ng().normalize();
            let d = V::new(u(), u(), u()).normalize();
            let d = if d.dot(n) < 0.0 { -d } else { d };
            Ray {
                o: p + n * 1e-3,
                d,
                t_max: f32::INFINITY,
            }
        })
        .collect();
    (primary, bounce)
}

/// Writes `name`'s triangles and rays to `dir` (see the module comment).
fn write_rays(dir: &Path, name: &str, cache: &PageCache, sets: [(&str, &[Ray]); 2]) {
    let f32s = |values: &mut dyn Iterator<Item = f32>| -> Vec<u8> {
        values.flat_map(f32::to_le_bytes).collect()
    };
    let pages = 0..cache.archive.page_count();
    let tris: Vec<f32> = pages
        .flat_map(|id| {
            let page = cache.get(id);
            (0..page.tri_count()).filter_map(move |i| page.tri(i))
        })
        .flat_map(|t| t.p.into_iter().flatten())
        .collect();
    let write = |ext: &str, bytes: Vec<u8>| {
        let path = dir.join(format!("{name}.{ext}"));
        std::fs::write(&path, bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    };
    write("tris", f32s(&mut tris.into_iter()));
    for (ext, rays) in sets {
        let mut values = rays
            .iter()
            .flat_map(|r| r.o.to_array().into_iter().chain(r.d.to_array()));
        write(ext, f32s(&mut values));
    }
}

fn bench_trace(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut g = c.benchmark_group("trace");
    for name in ["bunny_box", "sponza"] {
        let out = dir.path().join(format!("{name}.canopy"));
        let scene = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("scenes/{name}.glb"));
        convert(&ConvertOptions::new(vec![scene], out.clone())).unwrap();
        let cache = PageCache::new(Arc::new(Archive::open(&out).unwrap()), None, 1).unwrap();
        let (primary, bounce) = rays(&cache);
        if let Some(dir) = std::env::var_os("CANOPY_BENCH_RAYS") {
            let sets = [("primary", &primary[..]), ("bounce", &bounce[..])];
            write_rays(Path::new(&dir), name, &cache, sets);
        }
        let mut tr = Tracer::new(&cache);
        g.throughput(Throughput::Elements(primary.len() as u64));
        g.bench_function(format!("{name}/primary closest"), |b| {
            b.iter(|| {
                primary
                    .iter()
                    .filter(|r| tr.closest_hit(r).is_some())
                    .count()
            })
        });
        g.throughput(Throughput::Elements(bounce.len() as u64));
        g.bench_function(format!("{name}/bounce closest"), |b| {
            b.iter(|| {
                bounce
                    .iter()
                    .filter(|r| tr.closest_hit(r).is_some())
                    .count()
            })
        });
        g.bench_function(format!("{name}/bounce any"), |b| {
            b.iter(|| bounce.iter().filter(|r| tr.occluded(r)).count())
        });
    }
    g.finish();
}

criterion_group!(benches, bench_trace);
criterion_main!(benches);
