//! The light sources' tests: sampling, the tree's probabilities, photon emission.

use super::*;

use crate::test_rng::TestRng as Rng;

fn scattered_lights(rng: &mut Rng) -> Lights {
    let emitters = (0..200)
        .filter_map(|k| {
            let c = rng.v(10.0);
            let p = [c + rng.v(0.5), c + rng.v(0.5), c + rng.v(0.5)];
            Emitter::triangle(p, V::new(1.0, 2.0, 0.5) * rng.f32(), k % 5 == 0)
        })
        .collect();
    let punctual = vec![
        Punctual::Spot {
            pos: V::new(0.0, 8.0, 0.0),
            dir: V::NEG_Y,
            intensity: V::splat(40.0),
            cos_outer: 0.7,
            cos_inner: 0.9,
        },
        Punctual::Spot {
            pos: V::new(3.0, -2.0, 1.0),
            dir: V::NEG_Z,
            intensity: V::splat(5.0),
            cos_outer: -1.0,
            cos_inner: -1.0,
        },
        Punctual::Directional {
            dir: V::new(0.3, -1.0, 0.2).normalize(),
            irradiance: V::splat(2.0),
        },
    ];
    Lights::new(emitters, punctual, None, V::ZERO, 20.0)
}

/// MIS weighs a BSDF-sampled hit on a lamp with `pick_pdf` converted to solid angle;
/// that must be the pdf `sample` returned for the same point, or the two strategies
/// double-count or lose light.
#[test]
fn a_lamp_hit_has_the_pdf_its_light_sample_had() {
    let mut rng = Rng::new(0x51ab_1e5e_ed00_0001);
    let lights = scattered_lights(&mut rng);
    let mut checked = 0;
    for _ in 0..5000 {
        let p = rng.v(15.0);
        let n = rng.v(1.0).normalize();
        let Some(ls) = lights.sample(p, n, rng.f32(), [rng.f32(), rng.f32()]) else {
            continue;
        };
        if ls.pdf == 0.0 {
            continue;
        }
        let (q, _, normal) = ls.point.unwrap();
        // The lamp holding q: its normal, and sub-triangle areas that add up to its own.
        let a = |x: V, y: V, z: V| 0.5 * (y - x).cross(z - x).length();
        let (i, e) = lights
            .emitters
            .iter()
            .enumerate()
            .find(|(_, e)| {
                let sum = a(q, e.p[1], e.p[2]) + a(e.p[0], q, e.p[2]) + a(e.p[0], e.p[1], q);
                e.n == normal && (sum / e.area - 1.0).abs() < 1e-3
            })
            .expect("the sampled point lies on a lamp");
        let d2 = (q - p).length_squared();
        let cos_l = ls.wi.dot(e.n).abs();
        let hit_pdf = lights.pdf_li((p, n), Some(i as u32), d2, cos_l, e.area);
        assert!(
            (hit_pdf / ls.pdf - 1.0).abs() < 1e-3,
            "light sample pdf {} against the hit's {hit_pdf}",
            ls.pdf
        );
        checked += 1;
    }
    assert!(checked > 1000, "{checked} lamp samples");
}

#[test]
fn tree_probabilities_sum_to_at_most_one_and_are_what_sampling_returns() {
    let mut rng = Rng::new(0x9e37_79b9_7f4a_7c15);
    let lights = scattered_lights(&mut rng);
    let count = lights.emitters.len() + lights.punctual.len();
    for _ in 0..50 {
        let p = rng.v(15.0);
        let n = rng.v(1.0).normalize();
        let pmf: Vec<f32> = (0..count).map(|i| lights.tree.pmf(p, n, i)).collect();
        // Below 1 by what descends into subtrees whose bound is loose: there sampling
        // finds no light, which is no bias, as only lights that cannot reach p are left.
        let total: f32 = pmf.iter().sum();
        assert!(
            total <= 1.0 + 1e-5 && total > 0.5,
            "probabilities at {p} sum to {total}"
        );
        let draws = 4000;
        let mut hits = vec![0u32; count];
        for k in 0..draws {
            let u = (k as f32 + rng.f32()) / draws as f32;
            let Some((i, q)) = lights.tree.sample(p, n, u) else {
                continue;
            };
            let rel = (q - pmf[i]).abs() / pmf[i];
            assert!(
                rel < 1e-5,
                "sampled light {i}: pmf {q} but {} by walking",
                pmf[i]
            );
            hits[i] += 1;
        }
        for (i, &h) in hits.iter().enumerate() {
            let expect = pmf[i] * draws as f32;
            // Stratified u: each light's count is within one stratum per tree level of
            // its expectation; 4σ of an unstratified count bounds that loosely.
            let slack = 4.0 * expect.sqrt() + 12.0;
            assert!(
                (h as f32 - expect).abs() <= slack,
                "light {i}: {h} draws, {expect} expected"
            );
        }
    }
}

#[test]
fn a_one_sided_lamp_facing_away_is_never_chosen() {
    let tri = |z: f32, flip: bool, two_sided: bool| {
        let (a, b) = (V::new(1.0, 0.0, z), V::new(0.0, 1.0, z));
        let p = if flip {
            [V::new(0.0, 0.0, z), b, a]
        } else {
            [V::new(0.0, 0.0, z), a, b]
        };
        Emitter::triangle(p, V::ONE, two_sided).unwrap()
    };
    // Normals +z: the lamp at z = 1 faces away from the origin, the one at z = −1 faces it.
    let lights = Lights::new(
        vec![
            tri(1.0, false, false),
            tri(-1.0, false, false),
            tri(2.0, false, true),
        ],
        Vec::new(),
        None,
        V::ZERO,
        5.0,
    );
    let (p, n) = (V::new(0.2, 0.2, 0.0), V::ZERO);
    assert_eq!(lights.tree.pmf(p, n, 0), 0.0);
    assert!(lights.tree.pmf(p, n, 1) > 0.0);
    assert!(
        lights.tree.pmf(p, n, 2) > 0.0,
        "a two-sided lamp lights both sides"
    );
    for k in 0..1000 {
        let (i, _) = lights.tree.sample(p, n, k as f32 / 1000.0).unwrap();
        assert_ne!(i, 0);
    }
    assert!(lights.sample(p, n, 0.5, [0.5, 0.5]).is_some());
}

/// Two spheres of one-sided lamps, outward normals.
fn lamp_spheres() -> Vec<Emitter> {
    let mut out = Vec::new();
    for (c, r, le) in [
        (V::new(0.0, 3.0, 0.0), 0.5, 20.0),
        (V::new(6.0, 4.0, 1.0), 0.8, 8.0),
    ] {
        let (nlat, nlon) = (12, 24);
        let at = |i: usize, j: usize| {
            let th = PI * i as f32 / nlat as f32;
            let ph = 2.0 * PI * j as f32 / nlon as f32;
            c + r * V::new(th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin())
        };
        for i in 0..nlat {
            for j in 0..nlon {
                let q = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)];
                for t in [[q[0], q[1], q[2]], [q[0], q[2], q[3]]] {
                    let Some(e) = Emitter::triangle(t, V::splat(le), false) else {
                        continue;
                    };
                    let outward = (t[0] + t[1] + t[2]) / 3.0 - c;
                    let t = if e.n.dot(outward) < 0.0 {
                        [t[0], t[2], t[1]]
                    } else {
                        t
                    };
                    out.extend(Emitter::triangle(t, V::splat(le), false));
                }
            }
        }
    }
    out
}

/// Irradiance at `p` with normal `n` from the lamps by a fine midpoint rule: each
/// triangle cut into k² pieces.
fn irradiance(emitters: &[Emitter], p: V, n: V) -> f64 {
    let k = 12;
    let mut e = 0.0f64;
    for l in emitters {
        let (du, dv) = ((l.p[1] - l.p[0]) / k as f32, (l.p[2] - l.p[0]) / k as f32);
        for a in 0..k {
            for b in 0..k - a {
                let base = l.p[0] + du * a as f32 + dv * b as f32;
                let mut pieces = vec![base + (du + dv) / 3.0];
                if a + b + 1 < k {
                    pieces.push(base + (du + dv) * (2.0 / 3.0));
                }
                for q in pieces {
                    let d = q - p;
                    let d2 = d.length_squared();
                    let w = d / d2.sqrt();
                    let (cs, cl) = (n.dot(w), -l.n.dot(w));
                    if cs > 0.0 && cl > 0.0 {
                        let da = l.area / (k * k) as f32;
                        e += (l.le.x * cs * cl * da / d2) as f64;
                    }
                }
            }
        }
    }
    e
}

#[test]
fn light_tree_samples_are_unbiased_and_beat_sampling_by_power() {
    let mut rng = Rng::new(7);
    let emitters = lamp_spheres();
    let area: f32 = emitters.iter().map(|e| e.area).sum();
    let le_area: Vec<f32> = emitters.iter().map(|e| e.le.x * e.area).collect();
    let total: f32 = le_area.iter().sum();
    let reference = Lights::new(lamp_spheres(), Vec::new(), None, V::ZERO, 10.0);
    assert!(area > 0.0);
    for (p, n) in [
        (V::new(0.0, 0.0, 0.0), V::Y),
        (V::new(2.0, 1.0, -1.0), V::new(0.2, 1.0, 0.1).normalize()),
        (V::new(4.0, 4.0, 3.0), V::new(0.0, 0.0, -1.0)),
    ] {
        let exact = irradiance(&emitters, p, n);
        let draws = 40_000;
        let (mut s1, mut s2, mut q1, mut q2) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for _ in 0..draws {
            let v = reference
                .sample(p, n, rng.f32(), [rng.f32(), rng.f32()])
                .map_or(0.0, |ls| (ls.weight.x * n.dot(ls.wi).max(0.0)) as f64);
            s1 += v;
            s2 += v * v;
            // Sampling by power alone: a triangle in proportion to Le·A, a point on it.
            let x = rng.f32() * total;
            let i = le_area
                .iter()
                .scan(0.0, |acc, w| {
                    *acc += w;
                    Some(*acc)
                })
                .position(|c| c > x)
                .unwrap_or(emitters.len() - 1);
            let e = &emitters[i];
            let (q, _, _) = e.point([rng.f32(), rng.f32()]);
            let d = q - p;
            let w = d.normalize();
            let (cs, cl) = (n.dot(w).max(0.0), (-e.n.dot(w)).max(0.0));
            let v = (e.le.x * cs * cl / d.length_squared() * total / e.le.x) as f64;
            q1 += v;
            q2 += v * v;
        }
        let nd = draws as f64;
        let (mean, var) = (s1 / nd, s2 / nd - (s1 / nd).powi(2));
        let var_power = q2 / nd - (q1 / nd).powi(2);
        let sigma = (var / nd).sqrt();
        assert!(
            (mean - exact).abs() < 4.0 * sigma + 2e-3 * exact,
            "at {p}: tree estimate {mean} ± {sigma}, midpoint rule {exact}"
        );
        assert!(
            var < 0.5 * var_power,
            "at {p}: variance {var} with the tree, {var_power} by power"
        );
    }
}

/// Split by material, every lamp triangle a hit names is found in its material's set, as
/// the same triangle; a set holds only its material's lamps, and all of them.
#[test]
fn lamps_split_by_material_keep_their_hit_table() {
    let mut rng = Rng::new(11);
    let mut lights = scattered_lights(&mut rng);
    for (i, e) in lights.emitters.iter_mut().enumerate() {
        e.material = (i % 3) as u32;
    }
    let table: HashMap<(u64, u32), u32> = (0..lights.emitters.len() as u32)
        .map(|i| ((7 + i as u64 / 4, i % 4), i))
        .collect();
    lights.by_leaf = table.clone();
    let whole: Vec<(u32, [V; 3])> = lights.emitters.iter().map(|e| (e.material, e.p)).collect();
    let split = lights.by_material();
    assert_eq!(split.len(), 3);
    for (m, set) in &split {
        let mine = whole.iter().filter(|e| e.0 == *m).count();
        assert_eq!(
            set.emitters.len(),
            mine,
            "material {m}: its lamps, all of them"
        );
        assert!(set.emitters.iter().all(|e| e.material == *m));
        assert!(set.punctual.is_empty() && set.env.is_none());
    }
    for (&(leaf, slot), &i) in &table {
        let (m, p) = whole[i as usize];
        let set = &split[&m];
        let j = set
            .emitter_at(leaf, slot)
            .expect("the hit's lamp is in its set");
        assert_eq!(set.emitters[j as usize].p, p, "the same triangle");
    }
}
