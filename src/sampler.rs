//! Owen-scrambled Sobol samples (Burley 2020, via `sobol_burley`), one independent
//! sequence per pixel. Past the table's dimensions a hash of (pixel, sample, set) takes
//! over, so unbounded path depth never runs out of numbers.

/// Samples for one pixel sample, drawn in 4-D sets (one SIMD evaluation each): a given
/// (seed, pixel, sample index, set) always gives the same numbers, whatever thread renders.
pub struct PixelSampler {
    seed: u32,
    index: u32,
}

fn hash(mut x: u32) -> u32 {
    // lowbias32 (Chris Wellons).
    x ^= x >> 16;
    x = x.wrapping_mul(0x7feb_352d);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846c_a68b);
    x ^= x >> 16;
    x
}

impl PixelSampler {
    pub fn new(seed: u32, pixel: u32, sample: u32) -> PixelSampler {
        // Sobol supports 2^16 samples per sequence; each further block gets a new sequence.
        PixelSampler {
            seed: hash(seed ^ hash(pixel ^ hash(sample >> 16))),
            index: sample & 0xffff,
        }
    }

    /// Dimensions 4·set .. 4·set + 4.
    pub fn get4(&self, set: u32) -> [f32; 4] {
        if set < sobol_burley::NUM_DIMENSION_SETS_4D {
            sobol_burley::sample_4d(self.index, set, self.seed)
        } else {
            let h = hash(self.seed ^ hash(self.index ^ hash(set)));
            [0u32, 1, 2, 3].map(|k| (hash(h ^ k) >> 8) as f32 * (1.0 / (1u32 << 24) as f32))
        }
    }
}

/// SplitMix64: independent uniforms from a seed alone, without a shared generator (a
/// triangle's bake samples, a record's gathers).
pub struct Hash(u64);

impl Hash {
    pub fn new(seed: u64) -> Hash {
        Hash(seed)
    }

    pub fn f32(&mut self) -> f32 {
        (self.u64() >> 40) as f32 / (1u64 << 24) as f32
    }

    /// Six uniforms, as shading a hit takes them (a light sample, then a lobe ray).
    pub fn u6(&mut self) -> [f32; 6] {
        [(); 6].map(|_| self.f32())
    }

    pub fn u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_are_in_unit_interval_and_stratified() {
        // 256 samples of one 2-D pixel pattern: every cell of a 16×16 grid gets one
        // (Sobol (0,2)-sequence property, kept by Owen scrambling).
        let mut cells = [0u32; 256];
        for s in 0..256 {
            let [x, y, ..] = PixelSampler::new(7, 12345, s).get4(0);
            assert!((0.0..1.0).contains(&x) && (0.0..1.0).contains(&y));
            cells[(x * 16.0) as usize * 16 + (y * 16.0) as usize] += 1;
        }
        assert!(cells.iter().all(|&c| c == 1), "{cells:?}");
        // Past the Sobol table the hash takes over, still in [0, 1).
        let deep = PixelSampler::new(1, 2, 3);
        for set in 60..200 {
            assert!(deep.get4(set).iter().all(|v| (0.0..1.0).contains(v)));
        }
    }
}
