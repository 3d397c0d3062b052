//! Owen-scrambled Sobol samples (Burley 2020, via `sobol_burley`), one independent
//! sequence per pixel. Past the table's dimensions a hash of (pixel, sample, dimension)
//! takes over, so unbounded path depth never runs out of numbers.

/// Samples for one pixel sample: `next` walks the dimensions in a fixed order, so a given
/// (seed, pixel, sample index) always draws the same numbers, whatever thread renders it.
pub struct PixelSampler {
    seed: u32,
    index: u32,
    dim: u32,
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
            dim: 0,
        }
    }

    pub fn next(&mut self) -> f32 {
        let d = self.dim;
        self.dim += 1;
        if d < sobol_burley::NUM_DIMENSIONS {
            sobol_burley::sample(self.index, d, self.seed)
        } else {
            let h = hash(self.seed ^ hash(self.index ^ hash(d)));
            (h >> 8) as f32 * (1.0 / (1u32 << 24) as f32)
        }
    }

    pub fn next2(&mut self) -> [f32; 2] {
        [self.next(), self.next()]
    }

    /// Jumps to the start of a bounce's dimensions, so every bounce uses the same slots
    /// whatever the previous bounce consumed.
    pub fn start_bounce(&mut self, bounce: u32, per_bounce: u32) {
        self.dim = 2 + bounce.saturating_mul(per_bounce);
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
            let mut p = PixelSampler::new(7, 12345, s);
            let [x, y] = p.next2();
            assert!((0.0..1.0).contains(&x) && (0.0..1.0).contains(&y));
            cells[(x * 16.0) as usize * 16 + (y * 16.0) as usize] += 1;
        }
        assert!(cells.iter().all(|&c| c == 1), "{cells:?}");
        let mut deep = PixelSampler::new(1, 2, 3);
        deep.start_bounce(1000, 7);
        for _ in 0..100 {
            assert!((0.0..1.0).contains(&deep.next()));
        }
    }
}
