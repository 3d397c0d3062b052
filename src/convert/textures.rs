//! Textures into the archive. Each image is read row by row (PNG streamed, so a texture
//! never has to fit in memory; JPEG, TGA and interlaced PNG are decoded whole), its MIP
//! pyramid built as the rows arrive (a 2×2 box filter in linear space, pbrt-v4's
//! `MIPMap` without its resampling to powers of two: odd sizes drop their last row or
//! column), cut into `TILE`² tiles and compressed in parallel.

use crate::import::TextureSource;
use anyhow::{anyhow, bail, Context, Result};
use canopy_format::codec::{linear_to_srgb, texel_to_linear};
use canopy_format::validate::MAX_TEXELS;
use canopy_format::{encode_tile, name_bytes, ArchiveWriter, TextureRecord, TILE, TILE_BYTES};
use rayon::prelude::*;
use std::io::{BufRead, BufReader, Cursor, Read};

/// Tiles gathered before they are compressed together.
const BATCH: usize = 64;

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

fn open_rows(src: &TextureSource) -> Result<Box<dyn Rows>> {
    let mut magic = [0u8; 8];
    let got = open_source(src)?.read(&mut magic)?;
    if got == 8 && magic == *b"\x89PNG\r\n\x1a\n" {
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
                .ok_or_else(|| anyhow!("not a PNG, JPEG or TGA image"))?,
        );
    }
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_TEXELS * 8);
    r.limits(limits);
    let format = r.format();
    let (w, h) = image::ImageReader::with_format(seekable(src)?, format.expect("set above"))
        .into_dimensions()?;
    check_size(w, h)?;
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
    /// A linear row waiting for the row below it.
    pending: Option<Vec<f32>>,
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
            pending: None,
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
        let Some(next) = self.next.as_mut() else {
            return;
        };
        let lin: Vec<f32> = row
            .chunks_exact(4)
            .flat_map(|p| texel_to_linear(p, srgb))
            .collect();
        let pair = if self.h == 1 {
            lin
        } else {
            match self.pending.take() {
                None => {
                    self.pending = Some(lin);
                    return;
                }
                Some(above) => above.iter().zip(&lin).map(|(a, b)| 0.5 * (a + b)).collect(),
            }
        };
        let w2 = next.w as usize;
        let mut down = vec![0u8; w2 * 4];
        for x in 0..w2 {
            let (a, b) = (2 * x, (2 * x + 1).min(self.w as usize - 1));
            for c in 0..4 {
                let v = 0.5 * (pair[a * 4 + c] + pair[b * 4 + c]);
                down[x * 4 + c] = if srgb && c < 3 {
                    linear_to_srgb(v)
                } else {
                    (v * 255.0).round().clamp(0.0, 255.0) as u8
                };
            }
        }
        next.push(&down, srgb, out);
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

/// Reads texture `src`, writes its pyramid's tiles, and returns its record.
pub fn write_texture(
    writer: &mut ArchiveWriter,
    src: &TextureSource,
    zstd_level: i32,
) -> Result<TextureRecord> {
    let mut rows = open_rows(src)?;
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
    Ok(rec)
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
