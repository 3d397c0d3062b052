//! Textures into the archive. Each image is read row by row (PNG streamed, so a texture
//! never has to fit in memory; JPEG, TGA and interlaced PNG are decoded whole), its MIP
//! pyramid built as the rows arrive (a 2×2 box filter in linear space, pbrt-v4's
//! `MIPMap` without its resampling to powers of two: odd sizes drop their last row or
//! column), cut into `TILE`² tiles and compressed in parallel.

use crate::import::TextureSource;
use anyhow::{anyhow, bail, Context, Result};
use canopy_format::codec::{bilinear, linear_to_srgb, texel_to_linear};
use canopy_format::validate::MAX_TEXELS;
use canopy_format::{encode_tile, name_bytes, ArchiveWriter, TextureRecord, TILE, TILE_BYTES};
use rayon::prelude::*;
use std::io::{BufRead, BufReader, Cursor, Read};

/// Tiles gathered before they are compressed together.
const BATCH: usize = 64;

/// Levels at most this many texels on a side are kept in memory for the triangles' means:
/// 87 KB a texture (a 256 cap took 1.4 MB each, 26 MB more RSS on textured Sponza).
const COARSE: u32 = 64;

/// A texture's coarse levels (each at most `COARSE` on a side), in linear RGBA, for the
/// converter's per-triangle texture means.
#[derive(Clone, serde::Serialize, serde::Deserialize)]
pub struct Coarse {
    /// The pyramid level of `levels[0]`.
    first: u32,
    levels: Vec<Vec<f32>>,
}

impl Coarse {
    /// Whether these levels are texture `t`'s: each level's texel count is the size
    /// `level_size` gives, and `first` is within the pyramid.
    pub fn fits(&self, t: &TextureRecord) -> bool {
        !self.levels.is_empty()
            && self.first as u64 + self.levels.len() as u64 <= t.levels.max(1) as u64
            && self.levels.iter().enumerate().all(|(i, l)| {
                let (w, h) = t.level_size(self.first + i as u32);
                l.len() as u64 == 4 * w as u64 * h as u64
            })
    }

    /// The mean of texture `t` over a triangle with texture coordinates `uv`: the triangle
    /// split by its midpoints into four, each read bilinearly at its texture-space centroid
    /// on the level whose texel spans a quarter triangle's extent. A triangle across a
    /// sharp edge of the texture (half white, half black) gets within a few percent of the
    /// exact mean where one lookup at its centroid, a level coarser, could be 25% off.
    pub fn mean_over(&self, t: &TextureRecord, uv: &[[f32; 2]; 3]) -> [f32; 4] {
        let extent = [0, 1]
            .map(|k| {
                let (lo, hi) = uv.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| {
                    (lo.min(p[k]), hi.max(p[k]))
                });
                hi - lo
            })
            .into_iter()
            .fold(0.0f32, f32::max);
        let size = t.width.max(t.height) as f32;
        let want = (0.5 * extent * size).max(1.0).log2().ceil();
        let last = self.first + self.levels.len() as u32 - 1;
        let l = if want.is_finite() {
            (want as u32).clamp(self.first, last)
        } else {
            last
        };
        let (w, h) = t.level_size(l);
        let texels = &self.levels[(l - self.first) as usize];
        let mid = |a: usize, b: usize| [0, 1].map(|k| 0.5 * (uv[a][k] + uv[b][k]));
        let (ab, bc, ca) = (mid(0, 1), mid(1, 2), mid(2, 0));
        let quarters = [
            [uv[0], ab, ca],
            [ab, uv[1], bc],
            [ca, bc, uv[2]],
            [ab, bc, ca],
        ];
        let mut sum = [0.0f32; 4];
        for q in quarters {
            let c = [0, 1].map(|k| (q[0][k] + q[1][k] + q[2][k]) / 3.0);
            if !(c[0].is_finite() && c[1].is_finite()) {
                return [0.0; 4];
            }
            let v = bilinear(c, (w, h), [t.wrap(0), t.wrap(1)], |x, y| {
                let at = ((y * w + x) * 4) as usize;
                std::array::from_fn(|k| texels[at + k])
            });
            for k in 0..4 {
                sum[k] += 0.25 * v[k];
            }
        }
        sum
    }
}

/// An image as RGBA8 rows, top row first.
trait Rows {
    fn size(&self) -> (u32, u32);
    /// Fills `out` (width × 4 bytes) with the next row.
    fn next_row(&mut self, out: &mut [u8]) -> Result<()>;
}

/// A non-interlaced PNG, decoded one row at a time.
struct PngRows<R: BufRead + std::io::Seek> {
    reader: png::Reader<R>,
    size: (u32, u32),
    color: png::ColorType,
}

impl<R: BufRead + std::io::Seek> Rows for PngRows<R> {
    fn size(&self) -> (u32, u32) {
        self.size
    }

    fn next_row(&mut self, out: &mut [u8]) -> Result<()> {
        let row = self
            .reader
            .next_row()?
            .ok_or_else(|| anyhow!("the image data ends early"))?;
        let data = row.data();
        let channels = self.color.samples();
        if data.len() < self.size.0 as usize * channels {
            bail!("a row of {} bytes", data.len());
        }
        for (px, src) in out.chunks_exact_mut(4).zip(data.chunks_exact(channels)) {
            px.copy_from_slice(&match channels {
                1 => [src[0], src[0], src[0], 255],
                2 => [src[0], src[0], src[0], src[1]],
                3 => [src[0], src[1], src[2], 255],
                _ => [src[0], src[1], src[2], src[3]],
            });
        }
        Ok(())
    }
}

/// A whole decoded image.
struct WholeRows {
    image: image::RgbaImage,
    next: u32,
}

impl Rows for WholeRows {
    fn size(&self) -> (u32, u32) {
        self.image.dimensions()
    }

    fn next_row(&mut self, out: &mut [u8]) -> Result<()> {
        let w = self.image.width() as usize * 4;
        let at = self.next as usize * w;
        out.copy_from_slice(&self.image.as_raw()[at..at + w]);
        self.next += 1;
        Ok(())
    }
}

/// Refuses sizes the archive cannot hold.
fn check_size(w: u32, h: u32) -> Result<()> {
    if w == 0 || h == 0 {
        bail!("the image is {w}×{h} texels (empty)");
    }
    if w as u64 * h as u64 > MAX_TEXELS {
        bail!("the image is {w}×{h} texels (at most {MAX_TEXELS} in all)");
    }
    Ok(())
}

fn open_source(src: &TextureSource) -> Result<Box<dyn Read + Send>> {
    match (&src.bytes, &src.file) {
        (Some(b), _) => Ok(Box::new(Cursor::new(b.as_ref().clone()))),
        (None, Some(path)) => {
            let f = std::fs::File::open(path)
                .with_context(|| format!("{}: cannot open texture", path.display()))?;
            Ok(Box::new(f))
        }
        (None, None) => bail!("texture '{}' has no source", src.name),
    }
}

/// Seekable buffered reader over a source (PNG and `image` need `Seek`).
fn seekable(src: &TextureSource) -> Result<Box<dyn ReadSeek>> {
    match (&src.bytes, &src.file) {
        (Some(b), _) => Ok(Box::new(Cursor::new(b.as_ref().clone()))),
        (None, Some(path)) => {
            let f = std::fs::File::open(path)
                .with_context(|| format!("{}: cannot open texture", path.display()))?;
            Ok(Box::new(BufReader::with_capacity(1 << 20, f)))
        }
        (None, None) => bail!("texture '{}' has no source", src.name),
    }
}

trait ReadSeek: BufRead + std::io::Seek + Send {}
impl<T: BufRead + std::io::Seek + Send> ReadSeek for T {}

/// Bytes a whole-image decode takes per texel: the decoder's buffer and the RGBA copy.
const WHOLE_BYTES_PER_TEXEL: u64 = 8;

/// The image's rows: streamed for non-interlaced PNG; JPEG, TGA, WebP, KTX2 and interlaced
/// PNG are decoded whole, refused when that would take more than `whole_limit` bytes.
fn open_rows(src: &TextureSource, whole_limit: u64) -> Result<Box<dyn Rows>> {
    let mut magic = Vec::with_capacity(12);
    open_source(src)?.take(12).read_to_end(&mut magic)?;
    if magic == super::ktx2::MAGIC {
        let mut bytes = Vec::new();
        open_source(src)?
            .take(whole_limit)
            .read_to_end(&mut bytes)?;
        let image = super::ktx2::decode(&bytes, whole_limit)?;
        check_size(image.width(), image.height())?;
        return Ok(Box::new(WholeRows { image, next: 0 }));
    }
    if magic.starts_with(b"\x89PNG\r\n\x1a\n") {
        let mut d = png::Decoder::new(seekable(src)?);
        d.set_transformations(png::Transformations::normalize_to_color8());
        d.set_limits(png::Limits { bytes: 1 << 30 });
        let info = d.read_header_info()?;
        let (w, h, interlaced) = (info.width, info.height, info.interlaced);
        check_size(w, h)?;
        if !interlaced {
            let reader = d.read_info()?;
            let (color, _) = reader.output_color_type();
            return Ok(Box::new(PngRows {
                reader,
                size: (w, h),
                color,
            }));
        }
    }
    let mut r = image::ImageReader::new(seekable(src)?).with_guessed_format()?;
    if r.format().is_none() {
        let ext = src.name.rsplit('.').next().unwrap_or("");
        r.set_format(
            image::ImageFormat::from_extension(ext)
                .ok_or_else(|| anyhow!("not a PNG, JPEG, TGA or WebP image"))?,
        );
    }
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(whole_limit);
    r.limits(limits);
    let format = r.format().expect("set above");
    let (w, h) = image::ImageReader::with_format(seekable(src)?, format).into_dimensions()?;
    check_size(w, h)?;
    let need = w as u64 * h as u64 * WHOLE_BYTES_PER_TEXEL;
    if need > whole_limit {
        bail!(
            "the image is {w}×{h} texels and {format:?} is decoded whole: about {} MiB, more than the memory budget leaves ({} MiB); save it as a non-interlaced PNG, which streams, or raise --mem-budget",
            need >> 20,
            whole_limit >> 20
        );
    }
    let image = r.decode()?.to_rgba8();
    Ok(Box::new(WholeRows { image, next: 0 }))
}

/// One level of a pyramid under construction: rows arrive in order, whole strips of `TILE`
/// rows become tiles, and pairs of rows become the next level's rows.
struct Level {
    w: u32,
    h: u32,
    /// Index of the level's first tile within the texture.
    first_tile: u32,
    strip: Vec<u8>,
    rows: u32,
    /// Linear rows waiting for the rows below them: one for an even height, two for an odd
    /// one (whose next-level rows each take three).
    pending: Vec<Vec<f32>>,
    /// The level's linear texels, when it is coarse enough to keep.
    keep: Option<Vec<f32>>,
    next: Option<Box<Level>>,
}

impl Level {
    fn new(t: &TextureRecord, l: u32, first_tile: u32) -> Level {
        let (w, h) = t.level_size(l);
        let (tx, ty) = t.level_tiles(l);
        Level {
            w,
            h,
            first_tile,
            strip: Vec::with_capacity(w as usize * 4 * TILE as usize),
            rows: 0,
            pending: Vec::new(),
            keep: (w.max(h) <= COARSE).then(|| Vec::with_capacity(w as usize * h as usize * 4)),
            next: (l + 1 < t.levels).then(|| Box::new(Level::new(t, l + 1, first_tile + tx * ty))),
        }
    }

    /// Takes one row of this level; completed tiles go to `out` as (index, texels).
    fn push(&mut self, row: &[u8], srgb: bool, out: &mut Vec<(u32, Vec<u8>)>) {
        self.strip.extend_from_slice(row);
        self.rows += 1;
        if self.rows.is_multiple_of(TILE) || self.rows == self.h {
            self.flush(out);
        }
        if self.next.is_none() && self.keep.is_none() {
            return;
        }
        let lin: Vec<f32> = row
            .chunks_exact(4)
            .flat_map(|p| texel_to_linear(p, srgb))
            .collect();
        if let Some(k) = self.keep.as_mut() {
            k.extend_from_slice(&lin);
        }
        let Some(y) = self.next.as_ref().map(|n| n.rows as usize) else {
            return;
        };
        self.pending.push(lin);
        let Some(pair) = self.reduce_down(y) else {
            return;
        };
        let Some(next) = self.next.as_mut() else {
            return;
        };
        let w2 = next.w as usize;
        let mut down = vec![0u8; w2 * 4];
        for x in 0..w2 {
            for c in 0..4 {
                let v = reduce_across(&pair, self.w as usize, x, c);
                down[x * 4 + c] = if srgb && c < 3 {
                    linear_to_srgb(v)
                } else {
                    (v * 255.0).round().clamp(0.0, 255.0) as u8
                };
            }
        }
        next.push(&down, srgb, out);
    }

    /// The next level's row from the rows `pending` holds, once it holds them all: the two
    /// rows' mean for an even height, three rows weighed by `odd_weights` for an odd one
    /// (the last kept as the first of the next three), the row itself for a height of one.
    /// `y`: the next level's row this makes.
    fn reduce_down(&mut self, y: usize) -> Option<Vec<f32>> {
        let h = self.h as usize;
        match self.pending.len() {
            _ if h == 1 => self.pending.pop(),
            2 if h.is_multiple_of(2) => {
                let (a, b) = (&self.pending[0], &self.pending[1]);
                let row = a.iter().zip(b).map(|(a, b)| 0.5 * (a + b)).collect();
                self.pending.clear();
                Some(row)
            }
            3 => {
                let [w0, w1, w2] = odd_weights(h, y);
                let [a, b, c] = [0, 1, 2].map(|k| &self.pending[k]);
                let row = (0..a.len())
                    .map(|i| w0 * a[i] + w1 * b[i] + w2 * c[i])
                    .collect();
                self.pending.drain(..2);
                Some(row)
            }
            _ => None,
        }
    }

    /// Cuts the rows gathered so far (one strip) into tiles.
    fn flush(&mut self, out: &mut Vec<(u32, Vec<u8>)>) {
        let ty = (self.rows - 1) / TILE;
        let tiles_x = self.w.div_ceil(TILE);
        let row_bytes = self.w as usize * 4;
        let strip_rows = self.strip.len() / row_bytes;
        for tx in 0..tiles_x {
            let mut tile = vec![0u8; TILE_BYTES as usize];
            let x0 = (tx * TILE) as usize * 4;
            let x1 = (((tx + 1) * TILE).min(self.w) as usize) * 4;
            for r in 0..strip_rows {
                let src = &self.strip[r * row_bytes + x0..r * row_bytes + x1];
                tile[r * TILE as usize * 4..][..src.len()].copy_from_slice(src);
            }
            out.push((self.first_tile + ty * tiles_x + tx, tile));
        }
        self.strip.clear();
    }
}

/// The box filter's weights for a level of odd size n = 2m + 1 halved to m (as in NVIDIA's
/// non-power-of-two mipmapping): next-level texel i takes source texels 2i, 2i + 1 and
/// 2i + 2 with weights (m − i)/n, m/n and (i + 1)/n, so every source texel weighs m/n in
/// all and the level's mean is kept.
fn odd_weights(n: usize, i: usize) -> [f32; 3] {
    let m = (n - 1) / 2;
    [(m - i) as f32, m as f32, (i + 1) as f32].map(|w| w / n as f32)
}

/// Channel `c` of next-level texel `x` from a row of `w` linear texels: the mean of texels
/// 2x and 2x + 1 for an even width (the texel itself for a width of one), three texels
/// weighed by `odd_weights` for an odd width.
fn reduce_across(row: &[f32], w: usize, x: usize, c: usize) -> f32 {
    let t = |k: usize| row[k * 4 + c];
    match w {
        1 => t(0),
        w if w.is_multiple_of(2) => 0.5 * (t(2 * x) + t(2 * x + 1)),
        w => {
            let [w0, w1, w2] = odd_weights(w, x);
            w0 * t(2 * x) + w1 * t(2 * x + 1) + w2 * t(2 * x + 2)
        }
    }
}

/// Reads texture `src`, writes its pyramid's tiles, and returns its record and coarse
/// levels.
pub fn write_texture(
    writer: &mut ArchiveWriter,
    src: &TextureSource,
    zstd_level: i32,
    whole_limit: u64,
) -> Result<(TextureRecord, Coarse)> {
    let mut rows = open_rows(src, whole_limit)?;
    let (w, h) = rows.size();
    let mut rec = TextureRecord {
        name: name_bytes(&src.name),
        width: w,
        height: h,
        levels: TextureRecord::full_levels(w, h),
        first_tile: 0,
        flags: src.srgb as u32 | src.wrap[0] << 8 | src.wrap[1] << 10,
        mean: [0.0; 4],
        reserved: [0; 4],
    };
    rec.first_tile = writer.reserve_tiles(rec.tile_count())?;
    let mut top = Level::new(&rec, 0, 0);
    let mut row = vec![0u8; w as usize * 4];
    let mut sum = [0f64; 4];
    let mut ready = Vec::new();
    for y in 0..h {
        rows.next_row(&mut row)
            .with_context(|| format!("row {y} of {h}"))?;
        for p in row.chunks_exact(4) {
            let t = texel_to_linear(p, src.srgb);
            for c in 0..4 {
                sum[c] += t[c] as f64;
            }
        }
        top.push(&row, src.srgb, &mut ready);
        if ready.len() >= BATCH || y + 1 == h {
            put_tiles(
                writer,
                rec.first_tile,
                std::mem::take(&mut ready),
                zstd_level,
            )?;
        }
    }
    rec.mean = sum.map(|s| (s / (w as f64 * h as f64)).clamp(0.0, 1.0) as f32);
    let mut coarse = Coarse {
        first: 0,
        levels: Vec::new(),
    };
    let mut level = Some(&mut top);
    let mut l = 0;
    while let Some(lv) = level {
        match lv.keep.take() {
            Some(k) if coarse.levels.is_empty() => {
                coarse.first = l;
                coarse.levels.push(k);
            }
            Some(k) => coarse.levels.push(k),
            None => {}
        }
        l += 1;
        level = lv.next.as_deref_mut();
    }
    Ok((rec, coarse))
}

fn put_tiles(
    writer: &mut ArchiveWriter,
    first: u32,
    tiles: Vec<(u32, Vec<u8>)>,
    zstd_level: i32,
) -> Result<()> {
    let encoded = tiles
        .into_par_iter()
        .map(|(i, t)| encode_tile(&t, zstd_level).map(|e| (i, e)))
        .collect::<std::io::Result<Vec<_>>>()?;
    for (i, e) in encoded {
        writer.put_tile(first + i, &e)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 4² texture, left half white and right half black, with its 2² and 1² levels.
    fn halves() -> (TextureRecord, Coarse) {
        let texel = |x: usize| {
            if x < 2 {
                [1.0f32; 4]
            } else {
                [0.0, 0.0, 0.0, 1.0]
            }
        };
        let l0: Vec<f32> = (0..16).flat_map(|i| texel(i % 4)).collect();
        let l1: Vec<f32> = (0..4)
            .flat_map(|i| {
                if i % 2 == 0 {
                    [1.0f32; 4]
                } else {
                    [0.0, 0.0, 0.0, 1.0]
                }
            })
            .collect();
        let rec = TextureRecord {
            name: [0; 24],
            width: 4,
            height: 4,
            levels: 3,
            first_tile: 0,
            flags: TextureRecord::WRAP_CLAMP << 8 | TextureRecord::WRAP_CLAMP << 10,
            mean: [0.5, 0.5, 0.5, 1.0],
            reserved: [0; 4],
        };
        let coarse = Coarse {
            first: 0,
            levels: vec![l0, l1, vec![0.5, 0.5, 0.5, 1.0]],
        };
        (rec, coarse)
    }

    #[test]
    fn a_triangle_takes_the_mean_of_the_texels_under_it() {
        let (rec, coarse) = halves();
        // Small triangles inside one half see that half; one spanning the texture, the mean.
        let left = coarse.mean_over(&rec, &[[0.1, 0.1], [0.2, 0.1], [0.1, 0.2]]);
        let right = coarse.mean_over(&rec, &[[0.8, 0.8], [0.9, 0.8], [0.8, 0.9]]);
        assert_eq!(left[0], 1.0);
        assert_eq!(right[0], 0.0);
        // The lower-left half of the texture: three quarters of its area is white.
        let half = coarse.mean_over(&rec, &[[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]);
        assert!((half[0] - 0.75).abs() < 0.05, "{half:?}");
        // Its mirror image: a quarter white.
        let mirror = coarse.mean_over(&rec, &[[1.0, 0.0], [0.0, 0.0], [1.0, 1.0]]);
        assert!((mirror[0] - 0.25).abs() < 0.05, "{mirror:?}");
    }

    /// Every level of an odd-sized texture keeps level 0's mean, to the 8-bit rounding of
    /// the levels between (half a step each): the last row and column count. Here they are
    /// the texture's only white texels, so a pyramid that dropped them would be dark.
    #[test]
    fn every_level_of_an_odd_sized_texture_keeps_its_mean() {
        for (w, h) in [(7u32, 5u32), (5, 1), (1, 9), (13, 6), (6, 13)] {
            let texel = |x: u32, y: u32| match x == w - 1 || y == h - 1 {
                true => 255u8,
                false => ((x * 37 + y * 11) % 200) as u8,
            };
            let rec = TextureRecord {
                name: [0; 24],
                width: w,
                height: h,
                levels: TextureRecord::full_levels(w, h),
                first_tile: 0,
                flags: 0,
                mean: [0.0; 4],
                reserved: [0; 4],
            };
            let mut top = Level::new(&rec, 0, 0);
            let mut tiles = Vec::new();
            for y in 0..h {
                let row: Vec<u8> = (0..w).flat_map(|x| [texel(x, y); 4]).collect();
                top.push(&row, false, &mut tiles);
            }
            tiles.sort_by_key(|t| t.0);
            assert_eq!(tiles.len() as u32, rec.levels, "{w}×{h}: one tile a level");
            let mean = |l: u32| {
                let (lw, lh) = rec.level_size(l);
                let tile = &tiles[l as usize].1;
                let sum: u64 = (0..lh)
                    .flat_map(|y| (0..lw).map(move |x| (y * TILE + x) as usize * 4))
                    .map(|i| tile[i] as u64)
                    .sum();
                sum as f64 / (255.0 * (lw * lh) as f64)
            };
            for l in 1..rec.levels {
                let bound = l as f64 * 0.5 / 255.0 + 1e-6;
                assert!(
                    (mean(l) - mean(0)).abs() <= bound,
                    "{w}×{h}, level {l}: mean {} against level 0's {}",
                    mean(l),
                    mean(0)
                );
            }
        }
    }
}
