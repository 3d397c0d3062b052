//! Deterministic uniforms for the tests: proptest's ChaCha generator from a seed. The unit
//! tests reach it as `crate::test_rng`, the integration tests through `tests/common`.

use proptest::prelude::RngExt;

pub struct TestRng(proptest::test_runner::TestRng);

#[allow(dead_code)]
impl TestRng {
    pub fn new(seed: u64) -> TestRng {
        let mut bytes = [0u8; 32];
        bytes[..8].copy_from_slice(&seed.to_le_bytes());
        TestRng(proptest::test_runner::TestRng::from_seed(
            proptest::test_runner::RngAlgorithm::ChaCha,
            &bytes,
        ))
    }

    /// A uniform in [0, 1).
    pub fn f32(&mut self) -> f32 {
        self.0.random()
    }

    /// A uniform in [0, 1).
    pub fn f64(&mut self) -> f64 {
        self.0.random()
    }

    /// A point uniform in the cube of half-side `scale` about the origin.
    pub fn v(&mut self, scale: f32) -> glam::Vec3A {
        glam::Vec3A::new(self.f32() - 0.5, self.f32() - 0.5, self.f32() - 0.5) * (2.0 * scale)
    }
}
