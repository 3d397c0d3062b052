//! The archive's camera (glTF convention: looks down −z): a pinhole, or an orthographic
//! view whose rays are parallel.

use crate::trace::Ray;
use canopy_format::CameraRecord;
use glam::Vec3A as V;

#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub pos: V,
    x: V,
    y: V,
    z: V,
    /// tan of half the vertical field of view (perspective), or half the view's height in
    /// world units (orthographic).
    half_height: f32,
    orthographic: bool,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    pub fn new(rec: &CameraRecord, width: u32, height: u32) -> Camera {
        let m = rec.to_world;
        let col = |i: usize| V::new(m[3 * i], m[3 * i + 1], m[3 * i + 2]);
        let orthographic = rec.projection == CameraRecord::ORTHOGRAPHIC;
        Camera {
            x: col(0).normalize_or_zero(),
            y: col(1).normalize_or_zero(),
            z: col(2).normalize_or_zero(),
            pos: col(3),
            half_height: match orthographic {
                true => rec.ymag,
                false => (rec.yfov * 0.5).tan(),
            },
            orthographic,
            width,
            height,
        }
    }

    /// Ray through film position (px, py) in pixels, y down.
    pub fn ray(&self, px: f32, py: f32) -> Ray {
        let aspect = self.width as f32 / self.height as f32;
        let sx = (2.0 * px / self.width as f32 - 1.0) * self.half_height * aspect;
        let sy = (1.0 - 2.0 * py / self.height as f32) * self.half_height;
        let (o, d) = match self.orthographic {
            true => (self.pos + self.x * sx + self.y * sy, -self.z),
            false => (self.pos, (self.x * sx + self.y * sy - self.z).normalize()),
        };
        Ray {
            o,
            d,
            t_max: f32::INFINITY,
        }
    }

    /// A pixel's height on the film: an angle (perspective) or a length (orthographic).
    fn pixel(&self) -> f32 {
        2.0 * self.half_height / self.height.max(1) as f32
    }

    /// The width of a pixel's view at point `p`: its angle times the distance from the
    /// pinhole, or the same everywhere for an orthographic view.
    pub fn footprint(&self, p: V) -> f32 {
        let pixel = self.pixel();
        match self.orthographic {
            true => pixel,
            false => pixel * (p - self.pos).length(),
        }
    }

    /// A primary cone's radius at distance 0 and its growth with distance (004 eq. 4.19:
    /// one pixel's spacing): a pixel's angle from a pinhole, a pixel's width for an
    /// orthographic view.
    pub fn cone(&self) -> (f32, f32) {
        let pixel = self.pixel();
        match self.orthographic {
            true => (pixel, 0.0),
            false => (0.0, pixel),
        }
    }
}
