//! The film: per-pixel sums of a window's samples, in tiles.

use crate::image::Image;

/// Per-pixel sums of a tile's samples: R, G, B and the luminance squared.
pub type Sums = [f64; 4];

/// Side of a tile, the unit of parallel work.
pub const TILE: u32 = 16;

pub struct Film {
    /// x0, x1, y0, y1 of the window in image pixels (half-open).
    window: [u32; 4],
    sums: Vec<Sums>,
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
            sums: vec![[0.0; 4]; w as usize * h as usize],
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
    pub fn add(&mut self, tile: [u32; 4], sums: &[Sums]) {
        let w = tile[1] - tile[0];
        for (i, v) in sums.iter().enumerate() {
            let at = self.index(tile[0] + i as u32 % w, tile[2] + i as u32 / w);
            for (s, x) in self.sums[at].iter_mut().zip(v) {
                *s += x;
            }
        }
    }

    /// Adds light summed over a window pixel's samples that the integrator held back
    /// (`Integrator::held_back`); it is not in the sample variance.
    pub fn add_held_back(&mut self, at: usize, rgb: [f32; 3]) {
        if let Some(s) = self.sums.get_mut(at) {
            for (s, x) in s.iter_mut().zip(rgb) {
                *s += x as f64;
            }
        }
    }

    /// The mean of `samples` samples per pixel.
    pub fn image(&self, samples: u32) -> Image {
        let mut img = Image::new(self.width(), self.height());
        for (p, s) in img.pixels.iter_mut().zip(&self.sums) {
            *p = [0, 1, 2].map(|k| (s[k] / samples as f64) as f32);
        }
        img
    }

    /// The image's relative noise after `samples` samples per pixel: the RMS over pixels of
    /// the standard error of each pixel's mean luminance (from its sample variance), over
    /// the image's mean luminance. Infinite below two samples, 0 for a black image.
    pub fn noise(&self, samples: u32) -> f64 {
        if samples < 2 {
            return f64::INFINITY;
        }
        let n = samples as f64;
        let mean: f64 = self
            .sums
            .iter()
            .map(|s| luminance([s[0], s[1], s[2]]) / n)
            .sum();
        if mean <= 0.0 {
            return 0.0;
        }
        let count = self.sums.len() as f64;
        (self.sample_variance(samples) / n).sqrt() / (mean / count)
    }

    /// The mean over pixels of the sample variance of one sample's luminance, after
    /// `samples` samples per pixel (0 below two).
    pub fn sample_variance(&self, samples: u32) -> f64 {
        if samples < 2 || self.sums.is_empty() {
            return 0.0;
        }
        let n = samples as f64;
        let var: f64 = self
            .sums
            .iter()
            .map(|s| {
                let y = luminance([s[0], s[1], s[2]]) / n;
                ((s[3] / n - y * y) * n / (n - 1.0)).max(0.0)
            })
            .sum();
        var / self.sums.len() as f64
    }

    /// Bytes of the sums and of the image made from them.
    pub fn bytes(&self) -> u64 {
        self.sums.len() as u64 * (32 + 12)
    }
}

/// Rec. 709 luminance (`material::REC709`), in f64 for the film's sums.
pub fn luminance(c: [f64; 3]) -> f64 {
    let [r, g, b] = crate::material::REC709;
    r * c[0] + g * c[1] + b * c[2]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two samples per pixel, 0 and 2 in every channel: mean 1, sample variance 2, so the
    /// standard error of each mean is 1 and the relative noise 1/1.
    #[test]
    fn noise_is_the_standard_error_over_the_mean() {
        let mut film = Film::new([0, 4, 0, 2]);
        let y2 = luminance([2.0; 3]).powi(2);
        for tile in film.tiles.clone() {
            film.add(tile, &vec![[2.0, 2.0, 2.0, y2]; 8]);
        }
        assert!((film.noise(2) - 1.0).abs() < 1e-9, "{}", film.noise(2));
        assert_eq!(film.noise(1), f64::INFINITY);
        // Samples 0 and 2 (luminance): the sample variance of one sample is 2.
        let v = film.sample_variance(2);
        assert!((v - 2.0).abs() < 1e-9, "{v}");
        assert_eq!(film.sample_variance(1), 0.0);
        // Equal samples: no noise.
        let mut flat = Film::new([0, 4, 0, 2]);
        for tile in flat.tiles.clone() {
            flat.add(
                tile,
                &vec![[2.0, 2.0, 2.0, 2.0 * luminance([1.0; 3]).powi(2)]; 8],
            );
        }
        assert!(flat.noise(2).abs() < 1e-9);
    }
}
