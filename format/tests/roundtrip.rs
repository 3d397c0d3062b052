//! Property tests of the encodings: conservative quantization on random and adversarial
//! boxes, and every encoded field within the error bound FORMAT.md states.

use canopy_format::codec::*;
use canopy_format::Grid;
use proptest::prelude::*;

/// Code q on [lo, hi] decoded in each order FORMAT.md allows: separate operations, a fused
/// multiply-add, a multiply by the reciprocal of 65535, and both.
fn decodings(lo: f32, hi: f32, q: u16) -> [f32; 4] {
    let d = hi - lo;
    let t = q as f32 / 65535.0;
    let r = q as f32 * (1.0f32 / 65535.0);
    [lo + d * t, d.mul_add(t, lo), lo + d * r, d.mul_add(r, lo)].map(|v| match q {
        0 => lo,
        65535 => hi,
        _ => v.clamp(lo, hi),
    })
}

/// The box of codes `q` on `grid` in decoding order `k`.
fn decoded_in(grid: &Grid, q: &[u16; 6], k: usize) -> Box3 {
    let at = |a: usize, c: u16| decodings(grid.lo[a], grid.hi[a], c)[k];
    (
        [0, 1, 2].map(|a| at(a, q[a])),
        [0, 1, 2].map(|a| at(a, q[a + 3])),
    )
}

fn contains(outer: &Box3, inner: &Box3) -> bool {
    (0..3).all(|a| outer.0[a] <= inner.0[a] && inner.1[a] <= outer.1[a])
}

/// A coordinate from one of the adversarial regimes: ordinary, near ±1e7, tiny.
fn coord() -> impl Strategy<Value = f32> {
    prop_oneof![
        -1000.0f32..1000.0,
        (-1.0f32..1.0).prop_map(|x| 1.0e7 + x),
        (-1.0f32..1.0).prop_map(|x| -1.0e7 + x * 1e-3),
        (-1.0f32..1.0).prop_map(|x| x * 1e-6),
        (-1.0f32..1.0).prop_map(|x| 3.0e5 + x * 1e-6),
    ]
}

/// A parent box and a child box inside it (possibly flat or a single point).
type Box3 = ([f32; 3], [f32; 3]);

fn nested() -> impl Strategy<Value = (Box3, Box3)> {
    (
        prop::array::uniform3(coord()),
        prop::array::uniform3(0.0f32..1.0),
        prop::array::uniform3(0.0f32..1.0),
        prop::array::uniform3(prop_oneof![Just(0.0f32), 1e-6f32..1e-3, 0.1f32..1e4]),
        any::<bool>(),
    )
        .prop_map(|(lo, a, b, ext, flat)| {
            let hi = [0, 1, 2].map(|i| {
                if flat && i == 1 {
                    lo[i]
                } else {
                    lo[i] + ext[i]
                }
            });
            let c0 =
                [0, 1, 2].map(|i| (lo[i] + (hi[i] - lo[i]) * a[i].min(b[i])).clamp(lo[i], hi[i]));
            let c1 =
                [0, 1, 2].map(|i| (lo[i] + (hi[i] - lo[i]) * a[i].max(b[i])).clamp(c0[i], hi[i]));
            ((lo, hi), (c0, c1))
        })
}

/// A transform of the kinds scenes use: rotation (a unit quaternion), a scale per axis
/// (possibly mirrored), a translation, from the adversarial coordinates.
fn transform() -> impl Strategy<Value = canopy_format::InstanceRecord> {
    (
        prop::array::uniform4(-1.0f64..1.0),
        prop::array::uniform3(prop_oneof![0.01f64..100.0, -100.0f64..-0.01]),
        prop::array::uniform3(coord()),
    )
        .prop_map(|(q, s, t)| {
            let n = q.iter().map(|x| x * x).sum::<f64>().sqrt().max(1e-9);
            let [w, x, y, z] = q.map(|c| c / n);
            let r = [
                [
                    1.0 - 2.0 * (y * y + z * z),
                    2.0 * (x * y - w * z),
                    2.0 * (x * z + w * y),
                ],
                [
                    2.0 * (x * y + w * z),
                    1.0 - 2.0 * (x * x + z * z),
                    2.0 * (y * z - w * x),
                ],
                [
                    2.0 * (x * z - w * y),
                    2.0 * (y * z + w * x),
                    1.0 - 2.0 * (x * x + y * y),
                ],
            ];
            let mut to_world = [0f32; 12];
            for c in 0..3 {
                for row in 0..3 {
                    to_world[c * 3 + row] = (r[row][c] * s[c]) as f32;
                }
                to_world[9 + c] = t[c];
            }
            canopy_format::InstanceRecord {
                to_world,
                prototype_page: 0,
                reserved: [0; 12],
            }
        })
}

/// A point mapped by `m` (rows of f32) in f32, by separate operations or fused ones.
fn mapped(m: &[[f32; 4]; 3], p: [f32; 3], fused: bool) -> [f32; 3] {
    [0, 1, 2].map(|r| {
        let [a, b, c, t] = m[r];
        if fused {
            a.mul_add(p[0], b.mul_add(p[1], c.mul_add(p[2], t)))
        } else {
            a * p[0] + b * p[1] + c * p[2] + t
        }
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(4000))]

    /// An instance's box holds its prototype's box mapped by the transform in f32, with or
    /// without fused multiply-adds, at the corners and inside (FORMAT.md, Instances).
    #[test]
    fn instance_boxes_hold_the_mapped_prototype(((lo, hi), _) in nested(), r in transform(), t in prop::array::uniform3(0.0f32..1.0)) {
        let (wlo, whi) = r.world_box(lo, hi);
        let m = r.matrix().map(|row| row.map(|x| x as f32));
        let inside = [0, 1, 2].map(|a| (lo[a] + (hi[a] - lo[a]) * t[a]).clamp(lo[a], hi[a]));
        for corner in 0..9 {
            let p = match corner {
                8 => inside,
                c => [0, 1, 2].map(|a| if c >> a & 1 == 0 { lo[a] } else { hi[a] }),
            };
            for fused in [false, true] {
                let q = mapped(&m, p, fused);
                prop_assert!(contains(&(wlo, whi), &(q, q)), "{q:?} outside {wlo:?}..{whi:?}");
            }
        }
    }


    #[test]
    fn quantized_boxes_are_conservative_and_nested(((plo, phi), (clo, chi)) in nested()) {
        let grid = Grid { lo: plo, hi: phi };
        let parent_q = grid.quantize_box(plo, phi, None);
        let child_q = grid.quantize_box(clo, chi, Some(&parent_q));
        for k in 0..4 {
            let parent = decoded_in(&grid, &parent_q, k);
            prop_assert!(contains(&parent, &(plo, phi)), "order {k}: parent {parent:?} misses {plo:?}..{phi:?}");
            let child = decoded_in(&grid, &child_q, k);
            prop_assert!(contains(&child, &(clo, chi)), "order {k}: child {child:?} misses {clo:?}..{chi:?}");
            prop_assert!(contains(&parent, &child));
            // Tightness: at most one grid step plus twice the decoding margin per side.
            for a in 0..3 {
                let step = (phi[a] as f64 - plo[a] as f64) / 65535.0;
                let slack = (step + 2.0 * grid.margin(a)) as f32;
                prop_assert!(clo[a] - child.0[a] <= slack && child.1[a] - chi[a] <= slack);
            }
        }
        prop_assert_eq!(grid.dequant_box(&child_q), decoded_in(&grid, &child_q, 0));
    }

    #[test]
    fn points_inside_are_inside_the_quantized_box(lo in prop::array::uniform3(coord()), ext in prop::array::uniform3(0.0f32..10.0), t in prop::array::uniform3(0.0f32..1.0)) {
        let hi = [0, 1, 2].map(|i| lo[i] + ext[i]);
        let p = [0, 1, 2].map(|i| (lo[i] + ext[i] * t[i]).clamp(lo[i], hi[i]));
        let grid = Grid { lo, hi };
        let q = grid.quantize_box(p, p, None);
        for a in 0..3 {
            let near = grid.quantize_nearest(a, p[a]);
            let step = (hi[a] as f64 - lo[a] as f64) / 65535.0;
            for k in 0..4 {
                let b = decoded_in(&grid, &q, k);
                prop_assert!(b.0[a] <= p[a] && p[a] <= b.1[a], "order {k}: {b:?} misses {p:?}");
                // The centroid's bound in FORMAT.md: half a step plus the decoding margin.
                let c = decodings(lo[a], hi[a], near)[k] as f64;
                prop_assert!((c - p[a] as f64).abs() <= step / 2.0 + grid.margin(a), "order {k}: {c} for {}", p[a]);
            }
        }
    }

    #[test]
    fn rgbe64_within_bound(rgb in prop::array::uniform3(prop_oneof![0.0f32..1.0, 0.0f32..1e6, 0.0f32..1e-20])) {
        let d = rgbe64_decode(rgbe64_encode(rgb));
        let m = rgb[0].max(rgb[1]).max(rgb[2]);
        for i in 0..3 {
            prop_assert!((d[i] - rgb[i]).abs() <= m * 2f32.powi(-17) + 1e-38, "{rgb:?} -> {d:?}");
        }
    }

    #[test]
    fn unorm8_snorm16_f16_within_bound(x in 0.0f32..1.0, y in -1.0f32..1.0, z in -60000.0f32..60000.0) {
        prop_assert!((unorm8_decode(unorm8(x)) - x).abs() <= 0.5 / 255.0 + 1e-7);
        prop_assert!((snorm16_decode(snorm16(y)) - y).abs() <= 0.5 / 32767.0 + 1e-7);
        prop_assert!((f16_decode(f16_encode(z)) - z).abs() <= z.abs() * 2f32.powi(-11) + 6e-8);
    }

    #[test]
    fn octahedral_normals_within_bound(v in prop::array::uniform3(-1.0f32..1.0)) {
        let l = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        prop_assume!(l > 1e-3);
        let n = v.map(|x| x / l);
        let d = oct_decode(oct_encode(n));
        let dot = n[0] * d[0] + n[1] * d[1] + n[2] * d[2];
        let cross = [n[1] * d[2] - n[2] * d[1], n[2] * d[0] - n[0] * d[2], n[0] * d[1] - n[1] * d[0]];
        let angle = (cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2]).sqrt().atan2(dot);
        prop_assert!(angle < 1e-4, "{n:?} -> {d:?}: {angle} rad");
    }
}

#[test]
fn rgbe64_special_values() {
    assert_eq!(rgbe64_encode([0.0; 3]), 0);
    assert_eq!(
        rgbe64_decode(rgbe64_encode([f32::NAN, -1.0, 0.0])),
        [0.0; 3]
    );
    let big = rgbe64_decode(rgbe64_encode([f32::INFINITY, 1.0, 0.0]));
    assert_eq!(
        big[0], 0.0,
        "infinity is not a radiance; it encodes as zero"
    );
    let d = rgbe64_decode(rgbe64_encode([1e30, 1.0, 0.0]));
    assert!((d[0] - 1e30).abs() <= 1e30 * 2f32.powi(-17));
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// A tile's stored form gives back its texels exactly, smooth or random.
    #[test]
    fn tile_filter_round_trips(seed in any::<u64>(), smooth in any::<bool>()) {
        let side = 64usize;
        let mut x = seed | 1;
        let texels: Vec<u8> = (0..side * side * 4)
            .map(|i| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                if smooth { ((i / 4 % side + i / 4 / side) as u64 + (x & 3)) as u8 } else { x as u8 }
            })
            .collect();
        let stored = canopy_format::codec::tile_filter(&texels, side);
        prop_assert_eq!(canopy_format::codec::tile_unfilter(&stored, side), texels);
    }
}

#[test]
fn wrap_modes_fold_as_gltf_says() {
    let r: Vec<u32> = (-5..9)
        .map(|x| wrap_texel(x, 4, canopy_format::TextureRecord::WRAP_REPEAT))
        .collect();
    assert_eq!(r, [3, 0, 1, 2, 3, 0, 1, 2, 3, 0, 1, 2, 3, 0]);
    let m: Vec<u32> = (-5..9)
        .map(|x| wrap_texel(x, 4, canopy_format::TextureRecord::WRAP_MIRROR))
        .collect();
    assert_eq!(m, [3, 3, 2, 1, 0, 0, 1, 2, 3, 3, 2, 1, 0, 0]);
    let c: Vec<u32> = (-2..6)
        .map(|x| wrap_texel(x, 4, canopy_format::TextureRecord::WRAP_CLAMP))
        .collect();
    assert_eq!(c, [0, 0, 0, 1, 2, 3, 3, 3]);
}
