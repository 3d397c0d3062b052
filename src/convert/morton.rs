//! Morton codes: three grid coordinates' bits interleaved, x's highest, so that sorting by
//! the code walks the grid along a Z-order curve.

/// Bits of each coordinate a code can hold.
pub const MAX_BITS: u32 = 21;

/// `v`'s low 21 bits spread three apart (bit i to bit 3i).
fn spread(v: u32) -> u64 {
    let mut x = v as u64 & 0x1f_ffff;
    x = (x | x << 32) & 0x1f_0000_0000_ffff;
    x = (x | x << 16) & 0x1f_0000_ff00_00ff;
    x = (x | x << 8) & 0x100f_00f0_0f00_f00f;
    x = (x | x << 4) & 0x10c3_0c30_c30c_30c3;
    x = (x | x << 2) & 0x1249_2492_4924_9249;
    x
}

/// The code of grid cell `q` (each coordinate below 2^21): from the top, x's bit, y's,
/// z's, for each bit level in turn.
pub fn code(q: [u32; 3]) -> u64 {
    spread(q[0]) << 2 | spread(q[1]) << 1 | spread(q[2])
}

/// `0..n` sorted by the Morton code of `centre(k)` on a grid of 2^`bits` cells an axis over
/// the centres' bounds (a flat axis maps to cell 0), ties in index order. The centres are
/// found on demand, twice each: only the codes are held.
pub fn order(n: u32, bits: u32, centre: impl Fn(u32) -> [f64; 3]) -> Vec<u32> {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for k in 0..n {
        let c = centre(k);
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
    }
    let mut keyed: Vec<(u64, u32)> = (0..n)
        .map(|k| (code_in(centre(k), [lo, hi], bits), k))
        .collect();
    keyed.sort_unstable();
    keyed.into_iter().map(|(_, k)| k).collect()
}

/// The code of point `c` on a grid of 2^`bits` cells an axis over `bounds` (a flat axis
/// maps to cell 0; points outside clamp to the edge cells).
pub fn code_in(c: [f64; 3], [lo, hi]: [[f64; 3]; 2], bits: u32) -> u64 {
    let cells = (1u64 << bits) as f64;
    let q = [0, 1, 2].map(|a| {
        let e = hi[a] - lo[a];
        let t = if e > 0.0 { (c[a] - lo[a]) / e } else { 0.0 };
        ((t.max(0.0) * cells) as u64).min((1 << bits) - 1) as u32
    });
    code(q)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_interleave_the_bits_x_first() {
        // Bit by bit, as the definition reads.
        let slow = |q: [u32; 3]| {
            (0..MAX_BITS).rev().fold(0u64, |code, bit| {
                q.iter()
                    .fold(code, |code, &v| (code << 1) | ((v as u64 >> bit) & 1))
            })
        };
        let mut rng = crate::test_rng::TestRng::new(5);
        let top = (1u32 << MAX_BITS) - 1;
        for q in [
            [0, 0, 0],
            [top, top, top],
            [top, 0, 0],
            [0, 0, 1],
            [1, 0, 0],
        ] {
            assert_eq!(code(q), slow(q), "{q:?}");
        }
        for _ in 0..10_000 {
            let q = [0; 3].map(|_| (rng.f32() * top as f32) as u32 & top);
            assert_eq!(code(q), slow(q), "{q:?}");
        }
    }
}
