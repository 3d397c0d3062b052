//! The film: per-pixel sums of a window's samples, in tiles.

use crate::image::Image;

/// Side of a tile, the unit of parallel work.
pub const TILE: u32 = 16;

pub struct Film {
    /// x0, x1, y0, y1 of the window in image pixels (half-open).
    window: [u32; 4],
    sums: Vec<[f64; 3]>,
    pub tiles: Vec<[u32; 4]>,
}

impl Film {
    pub fn new(window: [u32; 4]) -> Film {
        let (w, h) = (window[1] - window[0], window[3] - window[2]);
        let tiles = (0..h.div_ceil(TILE))
            .flat_map(|ty| (0..w.div_ceil(TILE)).map(move |tx| (tx, ty)))
            .map(|(tx, ty)| {
                let x0 = window[0] + tx * TILE;
                let y0 = window[2] + ty * TILE;
                [
                    x0,
                    (x0 + TILE).min(window[1]),
                    y0,
                    (y0 + TILE).min(window[3]),
                ]
            })
            .collect();
        Film {
            window,
            sums: vec![[0.0; 3]; w as usize * h as usize],
            tiles,
        }
    }

    pub fn width(&self) -> u32 {
        self.window[1] - self.window[0]
    }

    pub fn height(&self) -> u32 {
        self.window[3] - self.window[2]
    }

    /// Index in the window of image pixel (x, y).
    pub fn index(&self, x: u32, y: u32) -> usize {
        ((y - self.window[2]) * self.width() + x - self.window[0]) as usize
    }

    /// Adds a tile's per-pixel sums (row-major within the tile).
    pub fn add(&mut self, tile: [u32; 4], sums: &[[f64; 3]]) {
        let w = tile[1] - tile[0];
        for (i, v) in sums.iter().enumerate() {
            let at = self.index(tile[0] + i as u32 % w, tile[2] + i as u32 / w);
            for (s, x) in self.sums[at].iter_mut().zip(v) {
                *s += x;
            }
        }
    }

    /// The mean of `samples` samples per pixel.
    pub fn image(&self, samples: u32) -> Image {
        let mut img = Image::new(self.width(), self.height());
        for (p, s) in img.pixels.iter_mut().zip(&self.sums) {
            *p = s.map(|v| (v / samples as f64) as f32);
        }
        img
    }

    /// Bytes of the sums and of the image made from them.
    pub fn bytes(&self) -> u64 {
        self.sums.len() as u64 * (24 + 12)
    }
}
