//! Images: linear RGB float pixels, written as OpenEXR (the `exr` crate) and as a
//! tone-mapped sRGB PNG preview. Files are written to a temporary name and renamed, so an
//! interrupted write never leaves a file that looks complete.

use anyhow::{bail, Context, Result};
use std::path::Path;

#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// Row-major, y down.
    pub pixels: Vec<[f32; 3]>,
}

impl Image {
    pub fn new(width: u32, height: u32) -> Image {
        Image {
            width,
            height,
            pixels: vec![[0.0; 3]; width as usize * height as usize],
        }
    }

    pub fn mean(&self) -> [f64; 3] {
        let mut s = [0f64; 3];
        for p in &self.pixels {
            for c in 0..3 {
                s[c] += p[c] as f64;
            }
        }
        s.map(|v| v / self.pixels.len().max(1) as f64)
    }

    pub fn read_exr(path: &Path) -> Result<Image> {
        if !path.exists() {
            bail!("{}: no such file", path.display());
        }
        let img = exr::prelude::read_first_rgba_layer_from_file(
            path,
            |res, _| Image::new(res.width() as u32, res.height() as u32),
            |img: &mut Image, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                let i = pos.y() * img.width as usize + pos.x();
                img.pixels[i] = [r, g, b];
            },
        )
        .with_context(|| format!("{}: not a readable OpenEXR image", path.display()))?;
        Ok(img.layer_data.channel_data.pixels)
    }

    pub fn write_exr(&self, path: &Path) -> Result<()> {
        let w = self.width as usize;
        write_atomically(path, |tmp| {
            exr::prelude::write_rgb_file(tmp, w, self.height as usize, |x, y| {
                let p = self.pixels[y * w + x];
                (p[0], p[1], p[2])
            })
            .map_err(|e| anyhow::anyhow!("{e}"))
        })
    }

    /// sRGB PNG: clamp to [0, 1] after `exposure` (a scale), then the sRGB transfer curve.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<()> {
        let bytes: Vec<u8> = self
            .pixels
            .iter()
            .flat_map(|p| p.map(|v| (srgb(v * exposure) * 255.0 + 0.5) as u8))
            .collect();
        write_png_rgb(path, self.width, self.height, &bytes)
    }
}

fn srgb(v: f32) -> f32 {
    let v = if v.is_finite() {
        v.clamp(0.0, 1.0)
    } else {
        0.0
    };
    if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    }
}

pub fn write_png_rgb(path: &Path, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    write_atomically(path, |tmp| {
        let file = std::fs::File::create(tmp)?;
        let mut enc = png::Encoder::new(std::io::BufWriter::new(file), width, height);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header()?;
        w.write_image_data(rgb)?;
        w.finish()?;
        Ok(())
    })
}

fn temp_name(path: &Path) -> Result<std::path::PathBuf> {
    let name = path
        .file_name()
        .with_context(|| format!("{}: not a file path", path.display()))?;
    Ok(path.with_file_name(format!(
        ".{}.tmp-{}",
        name.to_string_lossy(),
        std::process::id()
    )))
}

/// Runs `write` on a temporary path beside `path`, then renames it into place.
pub fn write_atomically(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let tmp = temp_name(path)?;
    let r = write(&tmp).and_then(|()| Ok(std::fs::rename(&tmp, path)?));
    if r.is_err() {
        std::fs::remove_file(&tmp).ok();
    }
    r.with_context(|| format!("{}: cannot write", path.display()))
}

/// Whether two paths name one existing file (the same device and inode on Unix).
pub fn same_file(a: &std::path::Path, b: &std::path::Path) -> bool {
    match (std::fs::metadata(a), std::fs::metadata(b)) {
        #[cfg(unix)]
        (Ok(x), Ok(y)) => {
            use std::os::unix::fs::MetadataExt;
            (x.dev(), x.ino()) == (y.dev(), y.ino())
        }
        #[cfg(not(unix))]
        (Ok(_), Ok(_)) => a.canonicalize().ok() == b.canonicalize().ok(),
        _ => false,
    }
}

/// Fails early if an image could not be written at `path` (missing directory, no
/// permission, a directory in the way), so a long render does not end in a lost result.
pub fn check_writable(path: &Path) -> Result<()> {
    if path.is_dir() {
        bail!("{}: is a directory", path.display());
    }
    let tmp = temp_name(path)?;
    std::fs::write(&tmp, b"").with_context(|| format!("{}: cannot write here", path.display()))?;
    std::fs::remove_file(&tmp).ok();
    Ok(())
}
