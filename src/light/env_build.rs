//! An environment map built as its texels are decoded, in any order, without holding the
//! map: texels gather in bands a tile high, and a band full of texels is written out as
//! tiles (`env_tiles`), whole in memory or to a temporary file to be paged. On the way the
//! builder keeps what sampling and the map's mean need: each row's sum, and the brightest
//! texel that reaches each cell of the sampling grid.

use super::env_tiles::{
    tile_scale, Paged, Store, Tiles, PAGED_TABLE_BYTES, SIDE, TEXELS, TILE_BYTES, TILE_COST,
};
use crate::image::Image;
use crate::material::luminance;
use anyhow::{anyhow, bail, Result};
use glam::Vec3A as V;
use half::f16;
use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::Path;

/// Most cells of the sampling grid: a map with more texel patches is sampled over
/// power-of-two blocks of them (a 2k × 1k map over 2 × 2, a 16k × 8k one over 16 × 16),
/// which keeps the sampling tables near 6 MiB whatever the map's size.
pub const MAX_CELLS: usize = 1 << 19;

/// The sampling grid over (u, v) ∈ [0, 1)² for a `width` × `height` map: its columns and
/// rows. Cell (I, J) spans u ∈ [I, I + 1) / columns and v ∈ [J, J + 1) / rows; at full
/// resolution a column per texel and a row per patch between two texel rows.
pub fn grid_size(width: usize, height: usize) -> [usize; 2] {
    let mut f = 1;
    while width.div_ceil(f) * (height - 1).div_ceil(f) > MAX_CELLS {
        f *= 2;
    }
    [width.div_ceil(f), (height - 1).div_ceil(f)]
}

/// The cells (first, last; columns may wrap) where texel (i, j)'s bilinear weight is not
/// zero: u ∈ ((i − ½) / w, (i + 3/2) / w) and v ∈ ((j − 1) / (h − 1), (j + 1) / (h − 1)).
fn reach(i: usize, j: usize, [w, h]: [usize; 2], [cols, rows]: [usize; 2]) -> [[i64; 2]; 2] {
    let floor = |a: i64, b: i64| a.div_euclid(b);
    let ceil = |a: i64, b: i64| -(-a).div_euclid(b);
    let (i, j, w, h, c, r) = (
        i as i64,
        j as i64,
        w as i64,
        h as i64,
        cols as i64,
        rows as i64,
    );
    let u = [
        floor((2 * i - 1) * c, 2 * w),
        ceil((2 * i + 3) * c, 2 * w) - 1,
    ];
    let v = [
        floor((j - 1) * r, h - 1).max(0),
        (ceil((j + 1) * r, h - 1) - 1).min(r - 1),
    ];
    [u, v]
}

/// A band of texel rows, one tile high, as it fills.
struct Band {
    texels: Vec<[f32; 3]>,
    filled: usize,
}

enum Sink {
    Whole(Vec<f16>),
    /// A temporary file, and the tiles its map may hold resident when paged.
    File(File, u64),
}

/// What a finished build gives the environment.
pub struct Built {
    pub tiles: Tiles,
    /// Per sampling cell (row-major), the brightest luminance that reaches it.
    pub brightest: Vec<f32>,
    pub grid: [usize; 2],
    /// Per texel row, the sum of its texels.
    pub row_sums: Vec<[f64; 3]>,
    /// Texels with a negative channel (taken as 0).
    pub negative: u64,
    /// A hash of the map as stored: its size and every tile's halves and scale.
    pub hash: u64,
}

pub struct Builder {
    size: [usize; 2],
    strength: f32,
    grid: [usize; 2],
    bands: HashMap<usize, Band>,
    sink: Result<Sink, String>,
    scale: Vec<f32>,
    /// Per tile, a hash of its stored halves and scale.
    hashes: Vec<u64>,
    row_sums: Vec<[f64; 3]>,
    brightest: Vec<f32>,
    negative: u64,
    not_finite: Option<(usize, usize, [f32; 3])>,
}

impl Builder {
    /// A `width` × `height` map whose texels are multiplied by `strength`, held whole, or
    /// written to a temporary file and paged `capacity` tiles at a time when
    /// `capacity` is Some.
    pub fn new(width: usize, height: usize, strength: f32, capacity: Option<u64>) -> Builder {
        let tiles = Tiles::count(width, height);
        let sink = match capacity {
            None => Ok(Sink::Whole(vec![f16::ZERO; tiles * 3 * TEXELS])),
            Some(c) => tempfile::tempfile()
                .map(|f| Sink::File(f, c))
                .map_err(|e| format!("creating a temporary file for the environment's tiles: {e}")),
        };
        let grid = grid_size(width, height);
        Builder {
            size: [width, height],
            strength,
            grid,
            bands: HashMap::new(),
            sink,
            scale: vec![1.0; tiles],
            hashes: vec![0; tiles],
            row_sums: vec![[0.0; 3]; height],
            brightest: vec![0.0; grid[0] * grid[1]],
            negative: 0,
            not_finite: None,
        }
    }

    /// Texel (i, j)'s value.
    pub fn put(&mut self, i: usize, j: usize, rgb: [f32; 3]) {
        let [w, h] = self.size;
        if i >= w || j >= h {
            return;
        }
        if !rgb.iter().all(|c| c.is_finite()) {
            self.not_finite.get_or_insert((i, j, rgb));
            return;
        }
        if rgb.iter().any(|&c| c < 0.0) {
            self.negative += 1;
        }
        let v = V::from(rgb).max(V::ZERO) * self.strength;
        for (s, c) in self.row_sums[j].iter_mut().zip(v.to_array()) {
            *s += c as f64;
        }
        let lum = luminance(v);
        let [[u0, u1], [v0, v1]] = reach(i, j, self.size, self.grid);
        let cols = self.grid[0] as i64;
        for row in v0..=v1 {
            for col in u0..=u1 {
                let cell = row as usize * self.grid[0] + col.rem_euclid(cols) as usize;
                self.brightest[cell] = self.brightest[cell].max(lum);
            }
        }
        let b = j / SIDE;
        let rows = SIDE.min(h - b * SIDE);
        let band = self.bands.entry(b).or_insert_with(|| Band {
            texels: vec![[0.0; 3]; rows * w],
            filled: 0,
        });
        band.texels[(j % SIDE) * w + i] = v.to_array();
        band.filled += 1;
        if band.filled == rows * w {
            let band = self.bands.remove(&b).expect("a full band");
            self.write_band(b, &band.texels);
        }
    }

    /// Band `b`'s tiles, each scaled by its power of two and stored as halves.
    fn write_band(&mut self, b: usize, texels: &[[f32; 3]]) {
        let w = self.size[0];
        let rows = texels.len() / w;
        let across = w.div_ceil(SIDE);
        for tx in 0..across {
            let t = b * across + tx;
            let cols = tx * SIDE..(w.min((tx + 1) * SIDE));
            let texel = |r: usize, c: usize| texels[r * w + c];
            let max = (0..rows)
                .flat_map(|r| cols.clone().map(move |c| (r, c)))
                .flat_map(|(r, c)| texel(r, c))
                .fold(0.0f32, f32::max);
            let scale = tile_scale(max);
            self.scale[t] = scale;
            let mut tile = vec![f16::ZERO; 3 * TEXELS];
            for r in 0..rows {
                for c in cols.clone() {
                    let k = 3 * (r * SIDE + c - tx * SIDE);
                    for (q, x) in texel(r, c).into_iter().enumerate() {
                        tile[k + q] = f16::from_f32(x / scale);
                    }
                }
            }
            let bytes: Vec<u8> = tile.iter().flat_map(|h| h.to_le_bytes()).collect();
            let mut hash = xxhash_rust::xxh3::Xxh3::new();
            hash.update(&bytes);
            hash.update(&scale.to_le_bytes());
            self.hashes[t] = hash.digest();
            self.store_tile(t, &tile, &bytes);
        }
    }

    /// Tile `t`, as halves and as their little-endian bytes (what the file holds).
    fn store_tile(&mut self, t: usize, tile: &[f16], bytes: &[u8]) {
        let Ok(sink) = &mut self.sink else { return };
        match sink {
            Sink::Whole(all) => all[t * 3 * TEXELS..(t + 1) * 3 * TEXELS].copy_from_slice(tile),
            Sink::File(f, _) => {
                if let Err(e) = f.write_all_at(bytes, (t * TILE_BYTES) as u64) {
                    self.sink = Err(format!("writing the environment's tiles: {e}"));
                }
            }
        }
    }

    /// The finished map; `path` names it in errors.
    pub fn finish(mut self, path: &Path) -> Result<Built> {
        if let Some((i, j, rgb)) = self.not_finite {
            bail!(
                "{}: texel ({i}, {j}) of the environment map is not finite ({rgb:?})",
                path.display()
            );
        }
        // Bands the file left short keep zeros where it gave nothing.
        let mut short: Vec<(usize, Band)> = self.bands.drain().collect();
        short.sort_by_key(|(b, _)| *b);
        for (b, band) in short {
            self.write_band(b, &band.texels);
        }
        let [w, h] = self.size;
        let store = match self.sink.map_err(|e| anyhow!("{}: {e}", path.display()))? {
            Sink::Whole(all) => Store::Whole(all),
            Sink::File(f, capacity) => Store::Paged(Paged::new(f, Tiles::count(w, h), capacity)),
        };
        let all: Vec<u8> = [w as u64, h as u64]
            .iter()
            .chain(&self.hashes)
            .flat_map(|x| x.to_le_bytes())
            .collect();
        Ok(Built {
            hash: xxhash_rust::xxh3::xxh3_64(&all),
            tiles: Tiles::new(w, h, self.scale, store),
            brightest: self.brightest,
            grid: self.grid,
            row_sums: self.row_sums,
            negative: self.negative,
        })
    }
}

/// Bytes of the sampling tables for a grid of `cols` × `rows` cells (each cell's
/// cumulative sum and density; each row's own).
pub fn density_bytes([cols, rows]: [usize; 2]) -> u64 {
    (cols * rows * 12 + rows * 44) as u64
}

/// Tiles a map may hold resident when it is paged under `share` bytes (its sampling
/// tables included), or None where it is held whole (no budget, or the whole map fits).
pub fn paged_capacity(width: usize, height: usize, share: Option<u64>) -> Option<u64> {
    let share = share?;
    let tiles = Tiles::count(width, height);
    let tables = density_bytes(grid_size(width, height)) + tiles as u64 * PAGED_TABLE_BYTES;
    let whole = (tiles * TILE_BYTES) as u64;
    (whole + tables > share).then(|| (share.saturating_sub(tables) / TILE_COST).max(16))
}

/// Reads the equirectangular map in `path` (.exr a block at a time, .hdr a scanline at a
/// time) into a builder.
pub fn read_map(path: &Path, strength: f32, share: Option<u64>) -> Result<Built> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    let builder = match ext.as_deref() {
        Some("exr") => read_exr(path, strength, share)?,
        Some("hdr") => read_hdr(path, strength, share)?,
        _ => bail!(
            "{}: an environment map is an equirectangular OpenEXR (.exr) or Radiance (.hdr) image",
            path.display()
        ),
    };
    builder.finish(path)
}

/// Checks a map's size before a texel is read.
fn check_size(path: &Path, w: usize, h: usize) -> Result<()> {
    if w < 2 || h < 2 {
        bail!(
            "{}: a {w}×{h} environment map; it needs at least 2×2 texels",
            path.display()
        );
    }
    Ok(())
}

/// An OpenEXR map, its first layer's R, G and B, decoded a block at a time.
fn read_exr(path: &Path, strength: f32, share: Option<u64>) -> Result<Builder> {
    use exr::prelude::*;
    let windows = crate::exr_header::check(path)?;
    let [w, h] = windows.data.map(|s| s as usize);
    check_size(path, w, h)?;
    let capacity = paged_capacity(w, h, share);
    let read = read()
        .no_deep_data()
        .largest_resolution_level()
        .rgba_channels(
            |res, _| Builder::new(res.width(), res.height(), strength, capacity),
            |b: &mut Builder, pos, (r, g, bl, _a): (f32, f32, f32, f32)| {
                b.put(pos.x(), pos.y(), [r, g, bl])
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .map_err(|e| anyhow!("{}: not a readable OpenEXR image: {e}", path.display()))?;
    Ok(read.layer_data.channel_data.pixels)
}

/// A Radiance RGBE map, decoded a scanline at a time.
fn read_hdr(path: &Path, strength: f32, share: Option<u64>) -> Result<Builder> {
    let mut r = super::hdr::Reader::open(path)?;
    let [w, h] = [r.width, r.height];
    check_size(path, w, h)?;
    let mut b = Builder::new(w, h, strength, paged_capacity(w, h, share));
    let mut row = Vec::with_capacity(w);
    for _ in 0..h {
        let j = r.row(&mut row)?;
        for (i, &p) in row.iter().enumerate() {
            b.put(i, j, p);
        }
    }
    Ok(b)
}

/// A map from texels held in memory (row-major), for tests and uniform maps.
pub fn from_image(img: &Image) -> Builder {
    let w = img.width as usize;
    let mut b = Builder::new(w, img.height as usize, 1.0, None);
    for (k, p) in img.pixels.iter().enumerate() {
        b.put(k % w, k / w, *p);
    }
    b
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// A 200 × 130 map (tiles cut at its edges) of smooth values, a sun of 10⁶ and a dark
    /// corner, fed in `order` at strength 2.
    fn build(order: &[usize], capacity: Option<u64>) -> Built {
        let (w, h) = (200, 130);
        let mut b = Builder::new(w, h, 2.0, capacity);
        for &k in order {
            let (i, j) = (k % w, k / w);
            b.put(i, j, texel_value(i, j).map(|c| c / 2.0));
        }
        b.finish(Path::new("test")).unwrap()
    }

    /// Texel (i, j) of the map `build` makes, with its strength of 2.
    fn texel_value(i: usize, j: usize) -> [f32; 3] {
        match (i, j) {
            (150..=152, 20..=21) => [2e6, 1.8e6, 1.6e6],
            (0..=9, 0..=9) => [0.0; 3],
            _ => [
                0.02 * i as f32,
                0.04 * j as f32,
                2.0 + (i * j) as f32 * 2e-3,
            ],
        }
    }

    /// In order or shuffled, held whole or paged a few tiles at a time, every texel reads
    /// back within half's rounding (2^-11 of its tile's range), the sun included.
    #[test]
    fn texels_read_back_in_any_order_whole_or_paged() {
        let n = 200 * 130;
        let mut shuffled: Vec<usize> = (0..n).collect();
        let mut rng = TestRng::new(3);
        for k in (1..n).rev() {
            shuffled.swap(k, (rng.f32() * (k + 1) as f32) as usize % (k + 1));
        }
        let whole = build(&(0..n).collect::<Vec<_>>(), None);
        let paged = build(&shuffled, Some(2));
        assert!(!whole.tiles.paged() && paged.tiles.paged());
        let mut range = [[0.0f32; 4]; 3];
        for k in 0..n {
            let r = &mut range[k / 200 / SIDE][k % 200 / SIDE];
            *r = texel_value(k % 200, k / 200).into_iter().fold(*r, f32::max);
        }
        for j in 0..130 {
            for i in 0..200 {
                let want = V::from(texel_value(i, j));
                let a = whole.tiles.texel(i, j);
                assert_eq!(a, paged.tiles.texel(i, j), "({i}, {j})");
                let tol = range[j / SIDE][i / SIDE] * 2f32.powi(-11);
                assert!(
                    (a - want).abs().max_element() <= tol,
                    "({i}, {j}): {a} vs {want}"
                );
            }
        }
        let s = paged.tiles.stats();
        assert!(s.env_tiles_loaded > 12 && s.env_tiles_evicted > 0, "{s:?}");
        assert_eq!(whole.row_sums, paged.row_sums);
        assert_eq!(whole.brightest, paged.brightest);
    }

    /// Each sampling cell's weight is at least the brightness of the bilinear map at any
    /// point inside it (the density never misses light), at full and reduced resolution.
    #[test]
    fn every_cell_is_weighted_by_the_brightest_light_it_holds() {
        for (w, h) in [(200, 130), (2048, 1025)] {
            let grid = grid_size(w, h);
            let mut b = Builder::new(w, h, 1.0, None);
            for j in 0..h {
                for i in 0..w {
                    let lit = (i * 7 + j * 3) % 97 == 0;
                    b.put(i, j, if lit { [5.0; 3] } else { [0.0; 3] });
                }
            }
            let built = b.finish(Path::new("test")).unwrap();
            let mut rng = TestRng::new(11);
            for _ in 0..20_000 {
                let (u, v) = (rng.f32(), rng.f32());
                let x = u * w as f32 - 0.5;
                let y = v * (h - 1) as f32;
                let (i0, j0) = (x.floor(), (y as usize).min(h - 2));
                let (fx, fy) = (x - i0, y - j0 as f32);
                let i0 = (i0 as isize).rem_euclid(w as isize) as usize;
                let t = |i: usize, j: usize| luminance(built.tiles.texel(i % w, j));
                let le = (t(i0, j0) * (1.0 - fx) + t(i0 + 1, j0) * fx) * (1.0 - fy)
                    + (t(i0, j0 + 1) * (1.0 - fx) + t(i0 + 1, j0 + 1) * fx) * fy;
                let cell = (v * grid[1] as f32) as usize * grid[0] + (u * grid[0] as f32) as usize;
                assert!(
                    le <= built.brightest[cell] + 1e-6,
                    "{w}×{h} ({u}, {v}): {le}"
                );
            }
        }
        assert_eq!(grid_size(200, 130), [200, 129]);
        assert_eq!(grid_size(2048, 1025), [1024, 512]);
    }
}
