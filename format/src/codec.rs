//! Scalar encodings used by the node record. Each function states its error bound; the
//! property tests in `tests/roundtrip.rs` check those bounds.

/// Mantissa widths of the 64-bit shared-exponent HDR colour (004 §4.2: E8 R19 G19 B18).
const RGBE_BITS: [u32; 3] = [19, 19, 18];
const RGBE_BIAS: i32 = 128;

use std::sync::OnceLock;

/// Encodes a non-negative RGB radiance as E8R19G19B18 (bits 63..56 exponent, then R, G, B).
///
/// Negative, NaN and values below 2^-128 encode as zero; values are clamped to 2^127.
/// Error bound per channel: |c - decode(c)| <= max(r, g, b) * 2^-17.
pub fn rgbe64_encode(rgb: [f32; 3]) -> u64 {
    let c = rgb.map(|v| {
        if v.is_finite() && v > 0.0 {
            v.min(1.7e38)
        } else {
            0.0
        }
    });
    let m = c[0].max(c[1]).max(c[2]);
    if m < f32::MIN_POSITIVE {
        return 0;
    }
    // Exponent e with m / 2^(e-bias) in [0.5, 1).
    let e = (m.log2().floor() as i32 + 1).clamp(1 - RGBE_BIAS, 127);
    let scale = (2.0f64).powi(-e);
    let mut bits = ((e + RGBE_BIAS) as u64) << 56;
    let mut shift = 56;
    for (v, b) in c.iter().zip(RGBE_BITS) {
        shift -= b;
        let max = (1u64 << b) - 1;
        let q = ((*v as f64) * scale * (1u64 << b) as f64 + 0.5).floor() as u64;
        bits |= q.min(max) << shift;
    }
    bits
}

/// Decodes an E8R19G19B18 colour.
pub fn rgbe64_decode(bits: u64) -> [f32; 3] {
    let e = (bits >> 56) as i32;
    if e == 0 {
        return [0.0; 3];
    }
    let scale = (2.0f64).powi(e - RGBE_BIAS);
    let mut out = [0.0f32; 3];
    let mut shift = 56;
    for (o, b) in out.iter_mut().zip(RGBE_BITS) {
        shift -= b;
        let q = (bits >> shift) & ((1u64 << b) - 1);
        *o = (q as f64 / (1u64 << b) as f64 * scale) as f32;
    }
    out
}

/// Opaque white in a page's colour stream (linear unorm16 RGBA): the colour of a vertex
/// whose input had none.
pub const WHITE: [u16; 4] = [u16::MAX; 4];

/// An sRGB-encoded value in [0, 1] to linear (IEC 61966-2-1).
pub fn srgb_decode(v: f32) -> f32 {
    if v <= 0.04045 {
        v / 12.92
    } else {
        ((v + 0.055) / 1.055).powf(2.4)
    }
}

/// sRGB-encoded byte to linear (`srgb_decode` of value/255, from a table).
pub fn srgb_to_linear(c: u8) -> f32 {
    static LUT: OnceLock<[f32; 256]> = OnceLock::new();
    LUT.get_or_init(|| std::array::from_fn(|i| srgb_decode(i as f32 / 255.0)))[c as usize]
}

/// Linear value in [0, 1] to the nearest sRGB-encoded byte (a 2¹⁶-entry table: its step is
/// under a twentieth of a byte even at the dark end).
pub fn linear_to_srgb(v: f32) -> u8 {
    static LUT: OnceLock<Vec<u8>> = OnceLock::new();
    let lut = LUT.get_or_init(|| {
        (0..=65535u32)
            .map(|i| {
                let v = i as f32 / 65535.0;
                let s = if v <= 0.0031308 {
                    12.92 * v
                } else {
                    1.055 * v.powf(1.0 / 2.4) - 0.055
                };
                (s * 255.0).round().clamp(0.0, 255.0) as u8
            })
            .collect()
    });
    lut[(v.clamp(0.0, 1.0) * 65535.0).round() as usize]
}

/// An RGBA8 texel in linear values: RGB through `srgb_to_linear` when `srgb`, alpha always
/// linear (FORMAT.md, "Textures").
pub fn texel_to_linear(px: &[u8], srgb: bool) -> [f32; 4] {
    let c = |v: u8| {
        if srgb {
            srgb_to_linear(v)
        } else {
            v as f32 / 255.0
        }
    };
    [c(px[0]), c(px[1]), c(px[2]), px[3] as f32 / 255.0]
}

/// Texel coordinate `x` wrapped into 0..n by a `TextureRecord` wrap mode (glTF's repeat,
/// clamp to edge, mirrored repeat).
pub fn wrap_texel(x: i64, n: u32, mode: u32) -> u32 {
    let n = n as i64;
    (match mode {
        crate::TextureRecord::WRAP_CLAMP => x.clamp(0, n - 1),
        crate::TextureRecord::WRAP_MIRROR => {
            let m = x.rem_euclid(2 * n);
            if m >= n {
                2 * n - 1 - m
            } else {
                m
            }
        }
        _ => x.rem_euclid(n),
    }) as u32
}

/// Bilinear interpolation at texture coordinates `uv` over a level of `size` texels (texel
/// centres at half-integers, pbrt-v4's `MIPMap::Bilerp`), coordinates wrapped by the
/// `TextureRecord` modes `wrap`; `texel(x, y)` gives the linear RGBA of an in-range texel.
pub fn bilinear(
    uv: [f32; 2],
    size: (u32, u32),
    wrap: [u32; 2],
    mut texel: impl FnMut(u32, u32) -> [f32; 4],
) -> [f32; 4] {
    let x = uv[0] * size.0 as f32 - 0.5;
    let y = uv[1] * size.1 as f32 - 0.5;
    let (x0, y0) = (x.floor(), y.floor());
    let (dx, dy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as i64, y0 as i64);
    let mut out = [0.0; 4];
    for (ox, oy, wgt) in [
        (0, 0, (1.0 - dx) * (1.0 - dy)),
        (1, 0, dx * (1.0 - dy)),
        (0, 1, (1.0 - dx) * dy),
        (1, 1, dx * dy),
    ] {
        if wgt > 0.0 {
            let c = texel(
                wrap_texel(x0 + ox, size.0, wrap[0]),
                wrap_texel(y0 + oy, size.1, wrap[1]),
            );
            for k in 0..4 {
                out[k] += wgt * c[k];
            }
        }
    }
    out
}

/// PNG's Paeth predictor (RFC 2083 §6.6) from the left, upper and upper-left bytes.
fn paeth(a: u8, b: u8, c: u8) -> u8 {
    let p = a as i16 + b as i16 - c as i16;
    let (pa, pb, pc) = (
        (p - a as i16).abs(),
        (p - b as i16).abs(),
        (p - c as i16).abs(),
    );
    if pa <= pb && pa <= pc {
        a
    } else if pb <= pc {
        b
    } else {
        c
    }
}

/// A texture tile's stored form (FORMAT.md, "Textures"): the RGBA8 texels of a
/// `side` × `side` tile as four planes (R, G, B, A), each byte minus its Paeth prediction
/// (mod 256; neighbours outside the tile count as 0). Photographs compress about a third
/// smaller under zstd this way than as interleaved texels.
pub fn tile_filter(texels: &[u8], side: usize) -> Vec<u8> {
    let mut out = vec![0u8; texels.len()];
    let at = |x: usize, y: usize, c: usize| texels[(y * side + x) * 4 + c];
    for c in 0..4 {
        for y in 0..side {
            for x in 0..side {
                let a = if x > 0 { at(x - 1, y, c) } else { 0 };
                let b = if y > 0 { at(x, y - 1, c) } else { 0 };
                let d = if x > 0 && y > 0 {
                    at(x - 1, y - 1, c)
                } else {
                    0
                };
                out[(c * side + y) * side + x] = at(x, y, c).wrapping_sub(paeth(a, b, d));
            }
        }
    }
    out
}

/// The texels `tile_filter` stored.
pub fn tile_unfilter(stored: &[u8], side: usize) -> Vec<u8> {
    let mut t = vec![0u8; stored.len()];
    for c in 0..4 {
        for y in 0..side {
            for x in 0..side {
                let at = |x: usize, y: usize| t[(y * side + x) * 4 + c];
                let a = if x > 0 { at(x - 1, y) } else { 0 };
                let b = if y > 0 { at(x, y - 1) } else { 0 };
                let d = if x > 0 && y > 0 { at(x - 1, y - 1) } else { 0 };
                t[(y * side + x) * 4 + c] =
                    stored[(c * side + y) * side + x].wrapping_add(paeth(a, b, d));
            }
        }
    }
    t
}

pub fn unorm8(v: f32) -> u8 {
    if v.is_nan() {
        return 0;
    }
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

pub fn unorm8_decode(q: u8) -> f32 {
    q as f32 / 255.0
}

/// [-1, 1] as value*32767, rounded to nearest. Error <= 0.5/32767.
pub fn snorm16(v: f32) -> i16 {
    if v.is_nan() {
        return 0;
    }
    (v.clamp(-1.0, 1.0) * 32767.0).round() as i16
}

pub fn snorm16_decode(q: i16) -> f32 {
    (q as f32 / 32767.0).max(-1.0)
}

/// IEEE 754 binary16 bits, round to nearest even (relative error <= 2^-11 in the normal range).
pub fn f16_encode(v: f32) -> u16 {
    half::f16::from_f32(v).to_bits()
}

pub fn f16_decode(bits: u16) -> f32 {
    half::f16::from_bits(bits).to_f32()
}

/// The normal stream's "no shading normal" code: x = y = −32768, which `snorm16` never
/// writes. A reader shades such a vertex with the face normal.
pub const NO_NORMAL: u32 = 0x8000_8000;

/// Unit vector as two snorm16 octahedral coordinates packed in a u32 (x low, y high).
/// Angular error below 1e-4 rad. A zero or non-finite vector has no direction: `NO_NORMAL`.
pub fn oct_encode(n: [f32; 3]) -> u32 {
    let l1 = n[0].abs() + n[1].abs() + n[2].abs();
    if l1.is_nan() || l1 <= 0.0 || !l1.is_finite() {
        return NO_NORMAL;
    }
    let (mut x, mut y) = (n[0] / l1, n[1] / l1);
    if n[2] < 0.0 {
        let (ox, oy) = (x, y);
        x = (1.0 - oy.abs()) * ox.signum();
        y = (1.0 - ox.abs()) * oy.signum();
    }
    oct_pack(x, y)
}

fn oct_pack(x: f32, y: f32) -> u32 {
    (snorm16(x) as u16 as u32) | ((snorm16(y) as u16 as u32) << 16)
}

pub fn oct_decode(bits: u32) -> [f32; 3] {
    let x = snorm16_decode(bits as u16 as i16);
    let y = snorm16_decode((bits >> 16) as u16 as i16);
    let z = 1.0 - x.abs() - y.abs();
    let t = (-z).max(0.0);
    let (x, y) = (x - t * x.signum(), y - t * y.signum());
    let l = (x * x + y * y + z * z).sqrt();
    [x / l, y / l, z / l]
}

/// The grid a page quantizes its node bounds on: 65535 steps per axis between `lo` and `hi`.
///
/// `dequant(0) == lo`, `dequant(65535) == hi` exactly, and every decoding order a reader may
/// use (separate f32 operations, a fused multiply-add, a multiply by the reciprocal of 65535)
/// is monotone in the code and within `DECODE_ULPS` ulps of the exact value. The writer
/// picks codes whose exact value is that margin on the conservative side, so the decoded
/// box contains the true box in every such order (004 §4.2 keeps positions in float for
/// that reason; we keep the guarantee and spend 2 bytes per coordinate).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Grid {
    pub lo: [f32; 3],
    pub hi: [f32; 3],
}

pub const QMAX: u16 = u16::MAX;

/// Bound, in ulps of max(|lo|, |hi|), on how far any IEEE-correct f32 evaluation of
/// lo + (hi − lo)·q/65535 lies from its exact value: hi − lo rounds by ≤ 1 ulp, q/65535 (or
/// q·(1/65535)) by ≤ 2 relative units, the product by ≤ 1 and, at most 2·max(|lo|, |hi|)
/// large, by ≤ 6 ulps in all; the sum by ≤ ½ ulp. FORMAT.md states it.
pub const DECODE_ULPS: f64 = 8.0;

/// Spacing of f32 values just above |m| (the smallest subnormal for 0).
pub fn ulp(m: f32) -> f64 {
    let a = m.abs();
    (a.next_up() - a) as f64
}

impl Grid {
    pub fn dequant(&self, axis: usize, q: u16) -> f32 {
        let (lo, hi) = (self.lo[axis], self.hi[axis]);
        match q {
            0 => lo,
            QMAX => hi,
            _ => (lo + (hi - lo) * (q as f32 / QMAX as f32)).clamp(lo, hi),
        }
    }

    /// The exact value of code `q` (in f64, whose own rounding is 2⁻²⁹ of an f32 ulp).
    pub fn exact(&self, axis: usize, q: u16) -> f64 {
        let (lo, hi) = (self.lo[axis] as f64, self.hi[axis] as f64);
        lo + (hi - lo) * q as f64 / QMAX as f64
    }

    /// Most any decoding order may stray from `exact` on this axis.
    pub fn margin(&self, axis: usize) -> f64 {
        DECODE_ULPS * ulp(self.lo[axis].abs().max(self.hi[axis].abs()))
    }

    fn estimate(&self, axis: usize, v: f64) -> u16 {
        let (lo, hi) = (self.lo[axis] as f64, self.hi[axis] as f64);
        let t = if hi > lo { (v - lo) / (hi - lo) } else { 0.0 };
        (t * QMAX as f64).clamp(0.0, QMAX as f64) as u16
    }

    /// Largest code that decodes ≤ v in every decoding order (0 when v ≤ lo + margin).
    pub fn quantize_down(&self, axis: usize, v: f32) -> u16 {
        let limit = v as f64 - self.margin(axis);
        let ok = |q: u16| q == 0 || self.exact(axis, q) <= limit;
        let e = self.estimate(axis, limit);
        if let Some(q) = [e, e.saturating_sub(1), e.saturating_add(1)]
            .into_iter()
            .find(|&q| ok(q) && (q == QMAX || !ok(q + 1)))
        {
            return q;
        }
        // Rounding put the estimate off; binary search the monotone predicate.
        let (mut a, mut b) = (0u32, QMAX as u32 + 1); // ok(a), !ok(b)
        while b - a > 1 {
            let m = (a + b) / 2;
            if ok(m as u16) {
                a = m
            } else {
                b = m
            }
        }
        a as u16
    }

    /// Smallest code that decodes ≥ v in every decoding order (QMAX when v ≥ hi − margin).
    pub fn quantize_up(&self, axis: usize, v: f32) -> u16 {
        let limit = v as f64 + self.margin(axis);
        let ok = |q: u16| q == QMAX || self.exact(axis, q) >= limit;
        let e = self.estimate(axis, limit).saturating_add(1);
        if let Some(q) = [e, e.saturating_sub(1), e.saturating_add(1)]
            .into_iter()
            .find(|&q| ok(q) && (q == 0 || !ok(q - 1)))
        {
            return q;
        }
        let (mut a, mut b) = (-1i32, QMAX as i32); // !ok(a), ok(b)
        while b - a > 1 {
            let m = (a + b) / 2;
            if ok(m as u16) {
                b = m
            } else {
                a = m
            }
        }
        b as u16
    }

    /// Conservative quantization of a box, clamped inside `parent` codes so that nesting in
    /// code space (and therefore in decoded space) holds by construction.
    pub fn quantize_box(&self, lo: [f32; 3], hi: [f32; 3], parent: Option<&[u16; 6]>) -> [u16; 6] {
        let mut q = [0u16; 6];
        for a in 0..3 {
            q[a] = self.quantize_down(a, lo[a]);
            q[a + 3] = self.quantize_up(a, hi[a]);
            if let Some(p) = parent {
                q[a] = q[a].max(p[a]);
                q[a + 3] = q[a + 3].min(p[a + 3]);
            }
        }
        q
    }

    pub fn dequant_box(&self, q: &[u16; 6]) -> ([f32; 3], [f32; 3]) {
        let lo = [0, 1, 2].map(|a| self.dequant(a, q[a]));
        let hi = [0, 1, 2].map(|a| self.dequant(a, q[a + 3]));
        (lo, hi)
    }

    /// Nearest code to v by exact value (not conservative), for points such as the cluster
    /// centroid: in any decoding order the error is at most half a grid step plus `margin`.
    pub fn quantize_nearest(&self, axis: usize, v: f32) -> u16 {
        let e = self.estimate(axis, v as f64);
        let dist = |q: u16| (self.exact(axis, q) - v as f64).abs();
        if e < QMAX && dist(e + 1) < dist(e) {
            e + 1
        } else {
            e
        }
    }
}
