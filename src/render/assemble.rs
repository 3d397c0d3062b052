//! `canopy assemble`: tiles rendered with `--crop` (each an OpenEXR image whose data window
//! lies in the frame's display window) joined into the frame. Tiles must come from one
//! archive with one set of settings and seed (their EXR attributes say so), cover the frame
//! exactly once, and the frame is written atomically.

use crate::image::{check_writable, same_file, Frame, Image};
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

/// The attributes every tile of a frame must share, with what a mismatch means.
const SHARED: [(&str, &str); 3] = [
    ("canopy.archive", "from another archive"),
    ("canopy.settings", "with other settings"),
    ("canopy.seed", "with another seed"),
];

/// What an assembly made.
#[derive(Debug, serde::Serialize)]
pub struct Assembled {
    pub width: u32,
    pub height: u32,
    pub tiles: usize,
}

impl std::fmt::Display for Assembled {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(
            f,
            "{}x{} from {} tiles",
            self.width, self.height, self.tiles
        )
    }
}

/// Joins `tiles` into one image written to `out`; any disagreement, overlap or gap is an
/// error naming the tiles, and then nothing is written. Every tile's header is checked
/// first: the frame (RGB and the owner of each pixel) and the largest tile must fit in
/// `budget` (`--mem-budget`) before anything is decoded.
pub fn assemble(tiles: &[PathBuf], out: &Path, budget: Option<u64>) -> Result<Assembled> {
    let Some(first_path) = tiles.first() else {
        bail!("no tiles given");
    };
    for (i, t) in tiles.iter().enumerate() {
        if same_file(t, out) {
            bail!(
                "{}: the output would overwrite the tile {}",
                out.display(),
                t.display()
            );
        }
        if let Some(d) = tiles[..i].iter().find(|u| same_file(u, t)) {
            bail!("{}: given twice (also as {})", t.display(), d.display());
        }
    }
    check_writable(out)?;
    let windows = tiles
        .iter()
        .map(|t| crate::exr_header::check(t))
        .collect::<Result<Vec<_>>>()?;
    let [fw, fh] = windows[0].display;
    let largest = windows.iter().map(|w| w.data_bytes()).max().unwrap_or(0);
    crate::exr_header::fits_budget(
        budget,
        fw * fh * (crate::exr_header::PIXEL_BYTES + 4) + largest,
        &format!("the {fw}x{fh} frame and its largest tile"),
    )?;
    let (_, first) = Image::read_exr_framed(first_path)?;
    for (key, _) in SHARED {
        if first.tag(key).is_none() {
            bail!(
                "{}: no {key} attribute: not an image canopy render wrote",
                first_path.display()
            );
        }
    }
    let [w, h] = first.display;
    let mut frame = Image::new(w, h);
    // The tile that wrote each pixel.
    let mut owner = vec![u32::MAX; w as usize * h as usize];
    for (i, path) in tiles.iter().enumerate() {
        let (img, f) = Image::read_exr_framed(path)?;
        agree(path, &f, first_path, &first)?;
        let [x0, y0] = f.origin;
        if x0 as u64 + img.width as u64 > w as u64 || y0 as u64 + img.height as u64 > h as u64 {
            bail!(
                "{}: its data window leaves the {w}x{h} frame",
                path.display()
            );
        }
        for y in 0..img.height {
            for x in 0..img.width {
                let at = ((y0 + y) * w + x0 + x) as usize;
                if owner[at] != u32::MAX {
                    bail!(
                        "{} and {} overlap at pixel ({}, {})",
                        tiles[owner[at] as usize].display(),
                        path.display(),
                        x0 + x,
                        y0 + y
                    );
                }
                owner[at] = i as u32;
                frame.pixels[at] = img.pixels[(y * img.width + x) as usize];
            }
        }
    }
    let gaps = owner.iter().filter(|&&o| o == u32::MAX).count();
    if let Some(at) = owner.iter().position(|&o| o == u32::MAX) {
        bail!(
            "the tiles leave {gaps} pixels of the {w}x{h} frame uncovered, the first at ({}, {})",
            at as u32 % w,
            at as u32 / w
        );
    }
    let whole = Frame {
        display: [w, h],
        origin: [0, 0],
        tags: first.tags.clone(),
    };
    frame.write_exr_framed(out, &whole)?;
    Ok(Assembled {
        width: w,
        height: h,
        tiles: tiles.len(),
    })
}

/// A tile's frame size and shared attributes are the first tile's.
fn agree(path: &Path, f: &Frame, first_path: &Path, first: &Frame) -> Result<()> {
    if f.display != first.display {
        bail!(
            "{}: a {}x{} frame, but {} is from a {}x{} frame",
            path.display(),
            f.display[0],
            f.display[1],
            first_path.display(),
            first.display[0],
            first.display[1]
        );
    }
    for (key, what) in SHARED {
        if f.tag(key) != first.tag(key) {
            bail!(
                "{}: rendered {what} than {} ({key}: {:?} vs {:?})",
                path.display(),
                first_path.display(),
                f.tag(key).unwrap_or("none"),
                first.tag(key).unwrap_or("none")
            );
        }
    }
    Ok(())
}
