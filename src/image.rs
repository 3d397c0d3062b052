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

    /// An OpenEXR image's pixels (its data window), wherever it lies in its frame.
    /// An 8-bit sRGB PNG's pixels, linearised (alpha dropped).
    pub fn read_png_linear(path: &Path) -> Result<Image> {
        let img = image::open(path)
            .with_context(|| format!("{}: not a readable PNG image", path.display()))?
            .into_rgba8();
        let pixels = img
            .pixels()
            .map(|p| {
                let [r, g, b, _] = canopy_format::codec::texel_to_linear(&p.0, true);
                [r, g, b]
            })
            .collect();
        Ok(Image {
            width: img.width(),
            height: img.height(),
            pixels,
        })
    }

    pub fn read_exr(path: &Path) -> Result<Image> {
        Ok(Self::read_exr_framed(path)?.0)
    }

    pub fn write_exr(&self, path: &Path) -> Result<()> {
        self.write_exr_framed(path, &Frame::whole(self))
    }

    /// OpenEXR with the image as the data window at `frame.origin` inside a display window
    /// of `frame.display` (a tile of a larger frame, as OpenEXR intends), and `frame.tags`
    /// as text attributes of the file.
    pub fn write_exr_framed(&self, path: &Path, frame: &Frame) -> Result<()> {
        use exr::prelude::*;
        let w = self.width as usize;
        let mut attributes = LayerAttributes {
            layer_position: Vec2(frame.origin[0] as i32, frame.origin[1] as i32),
            ..Default::default()
        };
        for (k, v) in &frame.tags {
            attributes.other.insert(
                Text::new_or_panic(k.as_str()),
                exr::meta::attribute::AttributeValue::Text(Text::new_or_panic(v.as_str())),
            );
        }
        let pixels = |p: Vec2<usize>| {
            let v = self.pixels[p.y() * w + p.x()];
            (v[0], v[1], v[2])
        };
        let layer = Layer::new(
            (w, self.height as usize),
            attributes,
            Encoding::FAST_LOSSLESS,
            SpecificChannels::rgb(pixels),
        );
        let mut image = exr::image::Image::from_layer(layer);
        image.attributes.display_window = IntegerBounds::new(
            Vec2(0, 0),
            Vec2(frame.display[0] as usize, frame.display[1] as usize),
        );
        write_atomically(path, |tmp| {
            image
                .write()
                .to_file(tmp)
                .map_err(|e| anyhow::anyhow!("{e}"))
        })
    }

    /// An OpenEXR image with where it lies in its display window and its text attributes.
    pub fn read_exr_framed(path: &Path) -> Result<(Self, Frame)> {
        use exr::prelude::*;
        crate::exr_header::check(path)?;
        let bad = |e: exr::error::Error| {
            anyhow::anyhow!("{}: not a readable OpenEXR image: {e}", path.display())
        };
        let read = read()
            .no_deep_data()
            .largest_resolution_level()
            .rgba_channels(
                |res, _| Self::new(res.width() as u32, res.height() as u32),
                |img: &mut Self, pos, (r, g, b, _a): (f32, f32, f32, f32)| {
                    let i = pos.y() * img.width as usize + pos.x();
                    img.pixels[i] = [r, g, b];
                },
            )
            .first_valid_layer()
            .all_attributes()
            .from_file(path)
            .map_err(bad)?;
        let display = read.attributes.display_window;
        let at = read.layer_data.attributes.layer_position - display.position;
        if display.size.x() > u32::MAX as usize
            || display.size.y() > u32::MAX as usize
            || at.x() < 0
            || at.y() < 0
        {
            bail!(
                "{}: the data window is not inside the display window",
                path.display()
            );
        }
        let mut tags: Vec<(String, String)> = read
            .layer_data
            .attributes
            .other
            .iter()
            .filter_map(|(k, v)| match v {
                exr::meta::attribute::AttributeValue::Text(t) => {
                    Some((k.to_string(), t.to_string()))
                }
                _ => None,
            })
            .collect();
        tags.sort();
        let frame = Frame {
            display: [display.size.x() as u32, display.size.y() as u32],
            origin: [at.x() as u32, at.y() as u32],
            tags,
        };
        Ok((read.layer_data.channel_data.pixels, frame))
    }

    /// sRGB PNG: clamp to [0, 1] after `exposure` (a scale), then the sRGB transfer curve.
    pub fn write_png(&self, path: &Path, exposure: f32) -> Result<()> {
        write_png_rgb(path, self.width, self.height, &self.srgb8(exposure))
    }

    /// The PNG file `write_png` writes, in memory.
    pub fn png_bytes(&self, exposure: f32) -> Result<Vec<u8>> {
        let mut out = Vec::new();
        encode_png(&mut out, self.width, self.height, &self.srgb8(exposure))?;
        Ok(out)
    }

    fn srgb8(&self, exposure: f32) -> Vec<u8> {
        self.pixels
            .iter()
            .flat_map(|p| p.map(|v| (srgb(v * exposure) * 255.0 + 0.5) as u8))
            .collect()
    }
}

/// Where an image lies in the frame it belongs to, and what made it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frame {
    /// Width and height of the whole frame (the EXR display window).
    pub display: [u32; 2],
    /// The image's top-left pixel in the frame (the data window's position).
    pub origin: [u32; 2],
    /// (name, value) text attributes, sorted by name.
    pub tags: Vec<(String, String)>,
}

impl Frame {
    /// An image that is its whole frame, without tags.
    pub fn whole(img: &Image) -> Frame {
        Frame {
            display: [img.width, img.height],
            origin: [0, 0],
            tags: Vec::new(),
        }
    }

    /// The value of tag `name`, if present.
    pub fn tag(&self, name: &str) -> Option<&str> {
        self.tags
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
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
        encode_png(std::io::BufWriter::new(file), width, height, rgb)
    })
}

fn encode_png(out: impl std::io::Write, width: u32, height: u32, rgb: &[u8]) -> Result<()> {
    let mut enc = png::Encoder::new(out, width, height);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header()?;
    w.write_image_data(rgb)?;
    w.finish()?;
    Ok(())
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
