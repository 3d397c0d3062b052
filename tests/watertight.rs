//! Watertightness: rays that hit the input mesh hit the archive's leaves at the same
//! triangle, found by walking the archive's (quantized, conservative) hierarchy.

mod common;
use canopy::import::ply::read_mesh;
use canopy_format::{Archive, PageContents};
use common::*;

type V = [f64; 3];

fn sub(a: V, b: V) -> V {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: V, b: V) -> V {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn dot(a: V, b: V) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn v(p: [f32; 3]) -> V {
    p.map(f64::from)
}

/// Möller–Trumbore in f64; the same function on both sides, so identical vertices give
/// identical answers.
fn hit(o: V, d: V, t: [[f32; 3]; 3]) -> Option<f64> {
    let (p0, p1, p2) = (v(t[0]), v(t[1]), v(t[2]));
    let (e1, e2) = (sub(p1, p0), sub(p2, p0));
    let p = cross(d, e2);
    let det = dot(e1, p);
    if det.abs() < 1e-300 {
        return None;
    }
    let s = sub(o, p0);
    let u = dot(s, p) / det;
    let q = cross(s, e1);
    let w = dot(d, q) / det;
    let t = dot(e2, q) / det;
    (u >= 0.0 && w >= 0.0 && u + w <= 1.0 && t > 0.0).then_some(t)
}

/// Slab test with the box widened by a few ulps (robust traversal, Ize 2013).
fn hits_box(o: V, d: V, lo: [f32; 3], hi: [f32; 3], tmax: f64) -> bool {
    let (mut t0, mut t1) = (0.0f64, tmax);
    for a in 0..3 {
        let inv = 1.0 / d[a];
        let (mut n, mut f) = ((lo[a] as f64 - o[a]) * inv, (hi[a] as f64 - o[a]) * inv);
        if n > f {
            std::mem::swap(&mut n, &mut f);
        }
        t0 = t0.max(n);
        t1 = t1.min(f * (1.0 + 1e-12));
        if t0 > t1 {
            return false;
        }
    }
    true
}

/// Closest hit through the archive hierarchy: (t, triangle vertices).
fn trace(a: &Archive, pages: &[PageContents], o: V, d: V) -> Option<(f64, [[f32; 3]; 3])> {
    let mut best: Option<(f64, [[f32; 3]; 3])> = None;
    let root = a.header.root_page;
    let mut stack: Vec<(u32, u32)> = vec![(root, 0)];
    while let Some((page, i)) = stack.pop() {
        let c = &pages[page as usize];
        let n = &c.nodes[i as usize];
        let (lo, hi) = a.grid(page).unwrap().dequant_box(&n.bounds);
        if !hits_box(o, d, lo, hi, best.map_or(f64::INFINITY, |b| b.0)) {
            continue;
        }
        if n.is_leaf() {
            for t in &c.tris[n.link[0] as usize..(n.link[0] + n.link[1]) as usize] {
                let tri = t.v.map(|k| c.verts[k as usize]);
                if let Some(th) = hit(o, d, tri) {
                    if best.is_none_or(|b| th < b.0) {
                        best = Some((th, tri));
                    }
                }
            }
        } else if n.has_child_page() {
            stack.extend([(n.link[0], 0), (n.link[0], 1)]);
        } else {
            stack.extend([(page, n.link[0]), (page, n.link[1])]);
        }
    }
    best
}

fn check(budget: &str) {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bunny.canopy");
    ok(&[
        "convert",
        s(&scene("bunny.ply")),
        "-o",
        s(&out),
        "--mem-budget",
        budget,
    ]);
    let a = Archive::open(&out).unwrap();
    let pages: Vec<PageContents> = (0..a.page_count())
        .map(|p| a.read_page(p).unwrap())
        .collect();
    let (verts, tris) = read_mesh(&scene("bunny.ply")).unwrap();
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in &verts {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] as f64);
            hi[k] = hi[k].max(p[k] as f64);
        }
    }
    let centre = [0, 1, 2].map(|k| (lo[k] + hi[k]) / 2.0);
    let radius = (0..3).map(|k| (hi[k] - lo[k]).powi(2)).sum::<f64>().sqrt();
    let mut rng = TestRng::new(12345);
    let mut rnd = || rng.f64();
    let (mut hits, mut mismatches) = (0, 0);
    for _ in 0..600 {
        // From a random point on a sphere around the mesh towards a random point inside it.
        let z = 2.0 * rnd() - 1.0;
        let phi = std::f64::consts::TAU * rnd();
        let r = (1.0 - z * z).sqrt();
        let o = [
            centre[0] + radius * r * phi.cos(),
            centre[1] + radius * r * phi.sin(),
            centre[2] + radius * z,
        ];
        let target = [0, 1, 2].map(|k| lo[k] + (hi[k] - lo[k]) * rnd());
        let d = sub(target, o);
        let truth = tris
            .iter()
            .filter_map(|t| {
                let tri = t.map(|i| verts[i as usize]);
                hit(o, d, tri).map(|th| (th, tri))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        let got = trace(&a, &pages, o, d);
        if let Some((t, tri)) = truth {
            hits += 1;
            match got {
                Some((tg, trig)) if tg == t && trig == tri => {}
                _ => mismatches += 1,
            }
        } else if got.is_some() {
            mismatches += 1;
        }
    }
    assert!(
        hits > 200,
        "too few rays hit the bunny ({hits}) for the test to mean anything"
    );
    assert_eq!(
        mismatches, 0,
        "{mismatches} of {hits} hits differ between input and archive"
    );
}

#[test]
fn archive_leaves_are_the_input_triangles() {
    check("2GiB");
}

#[test]
fn chunked_archive_leaves_are_the_input_triangles() {
    check("100MiB");
}

/// An icosphere of radius 1 (20·4^levels triangles), closed, wound outwards, as OBJ.
fn icosphere(levels: u32) -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut verts: Vec<[f32; 3]> = [
        [-1., t, 0.],
        [1., t, 0.],
        [-1., -t, 0.],
        [1., -t, 0.],
        [0., -1., t],
        [0., 1., t],
        [0., -1., -t],
        [0., 1., -t],
        [t, 0., -1.],
        [t, 0., 1.],
        [-t, 0., -1.],
        [-t, 0., 1.],
    ]
    .to_vec();
    let mut faces: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    let unit = |p: [f32; 3]| {
        let l = (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]).sqrt();
        p.map(|x| x / l)
    };
    for v in &mut verts {
        *v = unit(*v);
    }
    for _ in 0..levels {
        let mut mid = std::collections::HashMap::new();
        let mut next = Vec::new();
        for f in &faces {
            let m = [0, 1, 2].map(|k| {
                let (a, b) = (f[k].min(f[(k + 1) % 3]), f[k].max(f[(k + 1) % 3]));
                *mid.entry((a, b)).or_insert_with(|| {
                    let (p, q) = (verts[a as usize], verts[b as usize]);
                    verts.push(unit([0, 1, 2].map(|i| (p[i] + q[i]) / 2.0)));
                    verts.len() as u32 - 1
                })
            });
            next.extend([
                [f[0], m[0], m[2]],
                [f[1], m[1], m[0]],
                [f[2], m[2], m[1]],
                m,
            ]);
        }
        faces = next;
    }
    (verts, faces)
}

/// The renderer's `Tracer` aimed exactly at the shared edges and vertices of a closed mesh,
/// from inside and from outside: a watertight intersector never lets one through.
#[test]
fn tracer_rays_through_shared_edges_and_vertices_never_slip_through() {
    use canopy::trace::{Ray, Tracer};
    use glam::Vec3A;
    let (verts, faces) = icosphere(3);
    let mut obj = String::new();
    for p in &verts {
        obj += &format!("v {:e} {:e} {:e}\n", p[0], p[1], p[2]);
    }
    for f in &faces {
        obj += &format!("f {} {} {}\n", f[0] + 1, f[1] + 1, f[2] + 1);
    }
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("ico.obj");
    std::fs::write(&input, obj).unwrap();
    let arc = dir.path().join("ico.canopy");
    // Small pages, so neighbouring triangles also sit in different pages.
    ok(&[
        "--quiet",
        "convert",
        s(&input),
        "-o",
        s(&arc),
        "--page-nodes",
        "15",
    ]);
    let a = std::sync::Arc::new(Archive::open(&arc).unwrap());
    assert!(a.page_count() > 20);
    let cache = canopy::paging::PageCache::new(a, None, 1).unwrap();
    let mut tr = Tracer::new(&cache);
    let mut targets: Vec<Vec3A> = verts.iter().map(|&p| Vec3A::from(p)).collect();
    for f in &faces {
        for k in 0..3 {
            let (p, q) = (
                Vec3A::from(verts[f[k] as usize]),
                Vec3A::from(verts[f[(k + 1) % 3] as usize]),
            );
            targets.push((p + q) * 0.5);
            targets.push(p + (q - p) * 0.3);
        }
    }
    let mut rng = TestRng::new(99);
    let mut rnd = || rng.f32();
    let (mut fired, mut slipped) = (0, Vec::new());
    for t in &targets {
        // From the centre, and from 10 units out along a random direction that enters the
        // sphere at the target.
        let out = loop {
            let d = Vec3A::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize();
            if d.dot(*t) < -0.2 {
                break d;
            }
        };
        for ray in [
            Ray {
                o: Vec3A::ZERO,
                d: *t,
                t_max: f32::INFINITY,
            },
            Ray {
                o: *t - out * 10.0,
                d: out,
                t_max: f32::INFINITY,
            },
        ] {
            fired += 1;
            match tr.closest_hit(&ray) {
                Some(h) if (ray.o + ray.d * h.t - *t).length() < 1e-3 => {}
                other => slipped.push((ray.o, ray.d, other.map(|h| h.t))),
            }
        }
    }
    assert!(fired > 10_000, "{fired} rays");
    assert!(
        slipped.is_empty(),
        "{} of {fired} rays slipped: {:?}",
        slipped.len(),
        &slipped[..slipped.len().min(5)]
    );
}

/// Exact rays and widening cones walk the four-wide tree built at page decode; a cone
/// whose radius does not grow walks the binary tree throughout. A cone and its mirror
/// (r0 and tan α negated) have the same radius |r0 + t·tan α| bit for bit, so the binary
/// walk of the mirror is the reference for the four-wide walk of the cone: on random rays
/// and cones through bunny_box in small pages (links between pages everywhere, and a budget
/// that evicts) both meet the same thing (the same node, or a triangle) at the same
/// distance, any-hit agrees with closest-hit, and exact rays agree with `Cone::EXACT`.
#[test]
fn the_four_wide_walk_finds_what_the_binary_walk_finds() {
    use canopy::trace::{Cone, ConeHit, Ray, Tracer};
    use glam::Vec3A;
    let dir = tempfile::tempdir().unwrap();
    let arc = dir.path().join("b.canopy");
    ok(&[
        "--quiet",
        "convert",
        s(&scene("bunny_box.glb")),
        "-o",
        s(&arc),
        "--page-nodes",
        "15",
    ]);
    let a = std::sync::Arc::new(Archive::open(&arc).unwrap());
    let (lo, hi) = (
        Vec3A::from(a.header.bounds_min),
        Vec3A::from(a.header.bounds_max),
    );
    let diag = (hi - lo).length();
    let cache = canopy::paging::PageCache::new(a, Some(2 << 20), 1).unwrap();
    let mut tr = Tracer::new(&cache);
    let mut rng = TestRng::new(7);
    let mut rnd = || rng.f32();
    let (mut hits, mut stops) = (0, 0);
    let seen = |h: Option<ConeHit>| match h {
        Some(ConeHit::Tri(h)) => Some((h.t, u64::MAX, h.leaf, h.slot)),
        Some(ConeHit::Node { node, t, .. }) => Some((t, node, 0, 0)),
        None => None,
    };
    for i in 0..20_000 {
        let o = lo + (hi - lo) * Vec3A::new(rnd(), rnd(), rnd());
        let d = Vec3A::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize();
        let t_max = if i % 2 == 0 {
            f32::INFINITY
        } else {
            rnd() * 2.0 * diag
        };
        let ray = Ray { o, d, t_max };
        let cone = Cone {
            r0: rnd() * 0.01 * diag,
            tan_a: rnd() * 0.5,
            scale: [0.0, 1.0, 2.0][i % 3],
            spread: 0.0,
        };
        let mirror = Cone {
            r0: -cone.r0,
            tan_a: -cone.tan_a,
            ..cone
        };
        let wide = seen(tr.cone_hit(&ray, &cone));
        assert_eq!(
            wide,
            seen(tr.cone_hit(&ray, &mirror)),
            "ray {i}: {ray:?} {cone:?}"
        );
        let occluded = tr.cone_occluded(&ray, &cone);
        assert_eq!(occluded, wide.is_some(), "ray {i}: {ray:?} {cone:?}");
        assert_eq!(occluded, tr.cone_occluded(&ray, &mirror), "ray {i}");
        let exact = tr.closest_hit(&ray).map(|h| h.t);
        if cone.scale == 0.0 {
            assert_eq!(exact, wide.map(|w| w.0), "ray {i}: {ray:?}");
        }
        assert_eq!(tr.occluded(&ray), exact.is_some(), "ray {i}: {ray:?}");
        hits += exact.is_some() as u32;
        stops += wide.is_some_and(|w| w.1 != u64::MAX) as u32;
    }
    assert!(stops > 1_000, "only {stops} cones stopped at a node");
    assert!(
        hits > 5_000 && cache.stats().pages_evicted > 0,
        "{hits} hits"
    );
}
