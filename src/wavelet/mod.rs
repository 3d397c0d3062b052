//! Haar wavelets on cube maps: the radiance representation of wavelet PBGI (000 §3.1,
//! 003 ch. 4) and the micro-buffer's directions.
//!
//! - [`haar`]: the orthonormal non-standard 2D Haar transform of one square face, its
//!   sparse truncation and the point query that walks one root-to-leaf path;
//! - [`cube`]: cube-map geometry (faces, texel directions, exact texel solid angles and
//!   cosine integrals);
//! - [`tree`]: coefficient vectors coded along a node hierarchy as detail vectors with
//!   averages kept down to a bootstrap level m (000 §3.1, "G/H").
//!
//! No crate does these (the Haar crates found transform 1D signals or images without the
//! sparse point query), so they are written here.

pub mod cube;
pub mod haar;
pub mod tree;

use std::ops::{Add, Mul, Sub};

/// What a coefficient can be: a scalar or an RGB triple.
pub trait Coef:
    Copy + Default + Add<Output = Self> + Sub<Output = Self> + Mul<f32, Output = Self>
{
    /// Squared magnitude (the quantity Parseval preserves).
    fn norm2(self) -> f32;
}

impl Coef for f32 {
    fn norm2(self) -> f32 {
        self * self
    }
}

impl Coef for glam::Vec3 {
    fn norm2(self) -> f32 {
        self.length_squared()
    }
}
