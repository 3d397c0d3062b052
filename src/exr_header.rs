//! An OpenEXR file's windows, read and checked before any pixel is decoded: a header may
//! declare any size in a few hundred bytes, so an image is refused by its declared size,
//! not by the allocation that size would make.

use anyhow::{bail, Context, Result};
use std::io::Read;
use std::path::Path;

/// Widest and tallest image (data or display window) Canopy reads.
pub const MAX_SIDE: u64 = 65_536;
/// Most pixels an image (data or display window) may hold: 2^27, a 16,384 × 8,192 frame.
pub const MAX_PIXELS: u64 = 1 << 27;
/// Bytes a decoded pixel takes (linear RGB f32).
pub const PIXEL_BYTES: u64 = 12;

/// The sizes an EXR file declares.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Windows {
    /// Width and height of the pixels stored (the first layer's data window).
    pub data: [u64; 2],
    /// Width and height of the frame (the display window).
    pub display: [u64; 2],
}

impl Windows {
    /// Bytes the stored pixels take decoded.
    pub fn data_bytes(&self) -> u64 {
        self.data[0] * self.data[1] * PIXEL_BYTES
    }
}

/// Reads `path`'s headers and checks them: windows not inverted, inside `MAX_SIDE` and
/// `MAX_PIXELS`, flat (not deep) data, and no more chunks than pixels.
pub fn check(path: &Path) -> Result<Windows> {
    let name = path.display();
    if !path.is_file() {
        bail!("{name}: no such file (or not a regular file)");
    }
    let mut head = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(1 << 20).read_to_end(&mut head))
        .with_context(|| format!("{name}: cannot read"))?;
    if head.get(..4) != Some(&[0x76, 0x2f, 0x31, 0x01][..]) {
        bail!("{name}: not an OpenEXR image (bad magic number)");
    }
    for (attr, b) in boxes(&head) {
        if b[2] < b[0] || b[3] < b[1] {
            bail!(
                "{name}: the {attr} is inverted (min ({}, {}), max ({}, {}))",
                b[0],
                b[1],
                b[2],
                b[3]
            );
        }
    }
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| anyhow::anyhow!("{name}: not a readable OpenEXR image: {e}"))?;
    let Some(first) = meta.headers.first() else {
        bail!("{name}: an OpenEXR file with no layer");
    };
    for h in &meta.headers {
        if h.deep {
            bail!("{name}: deep data (Canopy reads flat images)");
        }
        let size = [h.layer_size.x() as u64, h.layer_size.y() as u64];
        within(&name, "data window", size)?;
        if h.chunk_count as u64 > size[0] * size[1] {
            bail!(
                "{name}: {} chunks for {}x{} pixels",
                h.chunk_count,
                size[0],
                size[1]
            );
        }
    }
    let display = first.shared_attributes.display_window.size;
    let display = [display.x() as u64, display.y() as u64];
    within(&name, "display window", display)?;
    Ok(Windows {
        data: [first.layer_size.x() as u64, first.layer_size.y() as u64],
        display,
    })
}

/// A window's size against the documented maximum.
fn within(name: &impl std::fmt::Display, what: &str, [w, h]: [u64; 2]) -> Result<()> {
    if w > MAX_SIDE || h > MAX_SIDE || w * h > MAX_PIXELS {
        bail!(
            "{name}: a {w}x{h} {what}; Canopy reads images up to {MAX_SIDE} pixels a side and {MAX_PIXELS} pixels in all"
        );
    }
    Ok(())
}

/// Refuses `bytes` of decoded pixels over `budget` (`--mem-budget`), naming what they are.
pub fn fits_budget(budget: Option<u64>, bytes: u64, what: &str) -> Result<()> {
    match budget {
        Some(b) if bytes > b => bail!(
            "{what} take {:.1} MiB decoded, more than --mem-budget {}",
            bytes as f64 / 1048576.0,
            crate::units::format_size(b)
        ),
        _ => Ok(()),
    }
}

/// The box attributes (`dataWindow`, `displayWindow`) of the first header, as written
/// (x_min, y_min, x_max, y_max): the exr crate orders each box's corners, which would hide
/// an inverted one.
fn boxes(head: &[u8]) -> Vec<(&'static str, [i32; 4])> {
    let mut out = Vec::new();
    let mut at = 8;
    let string = |at: &mut usize| -> Option<&[u8]> {
        let len = head.get(*at..)?.iter().position(|&c| c == 0)?;
        let s = &head[*at..*at + len];
        *at += len + 1;
        Some(s)
    };
    while let Some(attr) = string(&mut at) {
        if attr.is_empty() {
            break;
        }
        let Some(kind) = string(&mut at) else { break };
        let Some(size) = head.get(at..at + 4) else {
            break;
        };
        let size = u32::from_le_bytes(size.try_into().expect("4 bytes")) as usize;
        at += 4;
        let Some(value) = head.get(at..at.saturating_add(size)) else {
            break;
        };
        at += size;
        let which = match attr {
            b"dataWindow" => "data window",
            b"displayWindow" => "display window",
            _ => continue,
        };
        if kind == b"box2i" && value.len() == 16 {
            let v = |k: usize| i32::from_le_bytes(value[4 * k..4 * k + 4].try_into().expect("4"));
            out.push((which, [v(0), v(1), v(2), v(3)]));
        }
    }
    out
}
