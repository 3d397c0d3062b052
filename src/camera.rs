//! Pinhole camera from the archive's camera record (glTF perspective: looks down −z).

use crate::trace::Ray;
use canopy_format::CameraRecord;
use glam::Vec3A as V;

#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub pos: V,
    x: V,
    y: V,
    z: V,
    pub tan_half: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    pub fn new(rec: &CameraRecord, width: u32, height: u32) -> Camera {
        let m = rec.to_world;
        let col = |i: usize| V::new(m[3 * i], m[3 * i + 1], m[3 * i + 2]);
        Camera {
            x: col(0).normalize_or_zero(),
            y: col(1).normalize_or_zero(),
            z: col(2).normalize_or_zero(),
            pos: col(3),
            tan_half: (rec.yfov * 0.5).tan(),
            width,
            height,
        }
    }

    /// Ray through film position (px, py) in pixels, y down.
    pub fn ray(&self, px: f32, py: f32) -> Ray {
        let aspect = self.width as f32 / self.height as f32;
        let sx = (2.0 * px / self.width as f32 - 1.0) * self.tan_half * aspect;
        let sy = (1.0 - 2.0 * py / self.height as f32) * self.tan_half;
        Ray {
            o: self.pos,
            d: (self.x * sx + self.y * sy - self.z).normalize(),
            t_max: f32::INFINITY,
        }
    }
}
