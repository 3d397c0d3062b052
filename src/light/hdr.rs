//! Radiance RGBE images (`.hdr`) read a scanline at a time, so an environment map of any
//! size is tiled as it is decoded and never held whole. The format is Greg Ward's, as
//! Radiance's `freadcolrs` reads it: a text header ending in a blank line, a resolution
//! line, then one scanline after another, each either flat RGBE pixels (with the old
//! run-length scheme, where a pixel (1, 1, 1, n) repeats the previous one) or, for widths of
//! 8 to 32767, the adaptive scheme whose four channels are run-length coded one after the
//! other. A texel is c · 2^(e − 136) per channel, 0 where e is 0 (as Mitsuba 3, pbrt-v4's
//! reader and the `image` crate decode it, with no half-unit offset). EXPOSURE lines are
//! not applied, as those readers do not.

use anyhow::{anyhow, bail, Result};
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};

/// An open Radiance image, positioned at its first scanline.
pub struct Reader {
    r: BufReader<File>,
    path: PathBuf,
    pub width: usize,
    pub height: usize,
    /// Scanlines run bottom to top ("+Y" in the resolution line).
    bottom_up: bool,
    /// Scanlines read so far.
    read: usize,
    rgbe: Vec<[u8; 4]>,
}

impl Reader {
    /// Opens `path` and reads its header and resolution line.
    pub fn open(path: &Path) -> Result<Reader> {
        let file = File::open(path).map_err(|e| anyhow!("{}: {e}", path.display()))?;
        let mut r = BufReader::new(file);
        let bad = |what: String| {
            anyhow!(
                "{}: not a readable Radiance .hdr image: {what}",
                path.display()
            )
        };
        let mut line = Vec::new();
        let mut first = true;
        loop {
            line.clear();
            let n = (&mut r)
                .take(4096)
                .read_until(b'\n', &mut line)
                .map_err(|e| bad(e.to_string()))?;
            if n == 0 || line.last() != Some(&b'\n') {
                return Err(bad("its header does not end in a blank line".into()));
            }
            let text = String::from_utf8_lossy(&line);
            let text = text.trim_end();
            if first && !text.starts_with("#?") {
                return Err(bad("it does not begin with #?RADIANCE".into()));
            }
            first = false;
            if text.is_empty() {
                break;
            }
            if let Some(format) = text.strip_prefix("FORMAT=") {
                if format != "32-bit_rle_rgbe" {
                    return Err(bad(format!("its pixels are {format}, not 32-bit_rle_rgbe")));
                }
            }
        }
        line.clear();
        (&mut r)
            .take(256)
            .read_until(b'\n', &mut line)
            .map_err(|e| bad(e.to_string()))?;
        let text = String::from_utf8_lossy(&line);
        let (bottom_up, height, width) = resolution(text.trim()).ok_or_else(|| {
            bad(format!(
                "resolution line {:?} is not \"-Y H +X W\" or \"+Y H +X W\"",
                text.trim()
            ))
        })?;
        if width as u64 > crate::exr_header::MAX_SIDE
            || height as u64 > crate::exr_header::MAX_SIDE
            || (width * height) as u64 > crate::exr_header::MAX_PIXELS
        {
            return Err(bad(format!(
                "{width}×{height} is larger than {} pixels a side or {} in all",
                crate::exr_header::MAX_SIDE,
                crate::exr_header::MAX_PIXELS
            )));
        }
        Ok(Reader {
            r,
            path: path.to_path_buf(),
            width,
            height,
            bottom_up,
            read: 0,
            rgbe: vec![[0; 4]; width],
        })
    }

    /// Decodes the next scanline into `out` (`width` texels, left to right) and returns its
    /// row, counted from the top.
    pub fn row(&mut self, out: &mut Vec<[f32; 3]>) -> Result<usize> {
        let k = self.read;
        if k >= self.height {
            bail!("{}: every scanline is read", self.path.display());
        }
        self.scanline().map_err(|e| {
            anyhow!(
                "{}: scanline {k} of {}: {e}",
                self.path.display(),
                self.height
            )
        })?;
        self.read += 1;
        out.clear();
        out.extend(self.rgbe.iter().map(|&p| texel(p)));
        Ok(if self.bottom_up {
            self.height - 1 - k
        } else {
            k
        })
    }

    /// Reads one scanline's RGBE pixels into `self.rgbe`.
    fn scanline(&mut self) -> Result<()> {
        let w = self.width;
        let mut head = [0u8; 4];
        self.r.read_exact(&mut head)?;
        let adaptive =
            (8..=0x7fff).contains(&w) && head[0] == 2 && head[1] == 2 && head[2] & 0x80 == 0;
        if !adaptive {
            return self.flat(head);
        }
        if (head[2] as usize) << 8 | head[3] as usize != w {
            bail!(
                "its run-length header gives width {}, not {w}",
                (head[2] as usize) << 8 | head[3] as usize
            );
        }
        for c in 0..4 {
            let mut i = 0;
            while i < w {
                let mut code = [0u8; 1];
                self.r.read_exact(&mut code)?;
                let (run, count) = match code[0] {
                    n if n > 128 => (true, (n - 128) as usize),
                    n => (false, n as usize),
                };
                if count == 0 || i + count > w {
                    bail!("a run of {count} at pixel {i} of {w}");
                }
                if run {
                    let mut v = [0u8; 1];
                    self.r.read_exact(&mut v)?;
                    self.rgbe[i..i + count].iter_mut().for_each(|p| p[c] = v[0]);
                } else {
                    let mut bytes = [0u8; 128];
                    self.r.read_exact(&mut bytes[..count])?;
                    for (p, &v) in self.rgbe[i..i + count].iter_mut().zip(&bytes) {
                        p[c] = v;
                    }
                }
                i += count;
            }
        }
        Ok(())
    }

    /// A scanline of flat pixels, `first` already read, with the old run-length scheme: a
    /// pixel (1, 1, 1, n) repeats the previous pixel n times, shifted left by 8 bits for each
    /// such pixel just before it.
    fn flat(&mut self, first: [u8; 4]) -> Result<()> {
        let w = self.width;
        let (mut i, mut shift, mut p) = (0, 0u32, first);
        loop {
            if p[0] == 1 && p[1] == 1 && p[2] == 1 {
                if i == 0 {
                    bail!("a repeat before any pixel");
                }
                let count = (p[3] as usize) << shift;
                if i + count > w {
                    bail!("a repeat of {count} at pixel {i} of {w}");
                }
                let prev = self.rgbe[i - 1];
                self.rgbe[i..i + count].fill(prev);
                i += count;
                shift += 8;
            } else {
                self.rgbe[i] = p;
                i += 1;
                shift = 0;
            }
            if i == w {
                return Ok(());
            }
            self.r.read_exact(&mut p)?;
        }
    }
}

/// "-Y H +X W" (top to bottom) or "+Y H +X W" (bottom to top): (bottom up, H, W).
fn resolution(line: &str) -> Option<(bool, usize, usize)> {
    let parts: Vec<&str> = line.split_ascii_whitespace().collect();
    let [y, h, "+X", w] = parts[..] else {
        return None;
    };
    let bottom_up = match y {
        "-Y" => false,
        "+Y" => true,
        _ => return None,
    };
    Some((bottom_up, h.parse().ok()?, w.parse().ok()?))
}

/// An RGBE pixel's linear value.
fn texel([r, g, b, e]: [u8; 4]) -> [f32; 3] {
    if e == 0 {
        return [0.0; 3];
    }
    let f = 2f64.powi(e as i32 - 136);
    [r, g, b].map(|c| (c as f64 * f) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// Every texel of `path`, read scanline by scanline, in rows from the top.
    fn read_all(path: &Path) -> Result<(usize, usize, Vec<[f32; 3]>)> {
        let mut r = Reader::open(path)?;
        let (w, h) = (r.width, r.height);
        let mut all = vec![[0.0; 3]; w * h];
        let mut row = Vec::new();
        for _ in 0..h {
            let j = r.row(&mut row)?;
            all[j * w..(j + 1) * w].copy_from_slice(&row);
        }
        Ok((w, h, all))
    }

    /// The `image` crate's decode of the same file, texel for texel.
    fn image_crate(path: &Path) -> Vec<[f32; 3]> {
        let img = image::open(path).unwrap().into_rgb32f();
        img.pixels().map(|p| p.0).collect()
    }

    /// The bundled sky and maps the `image` crate encodes (adaptive run lengths at widths of
    /// 8 and more, flat pixels below) read as the `image` crate reads them, bit for bit.
    #[test]
    fn scanlines_decode_as_the_image_crate_decodes_them() {
        let sky = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes/env/sky.hdr");
        assert_eq!(read_all(&sky).unwrap().2, image_crate(&sky));
        let dir = tempfile::tempdir().unwrap();
        let mut rng = TestRng::new(4);
        for (w, h) in [(300, 7), (5, 4), (8, 3), (40, 2)] {
            // Runs of equal texels among random ones, so both kinds of code appear.
            let px: Vec<image::Rgb<f32>> = (0..w * h)
                .map(|k| match (k / 13) % 3 {
                    0 => image::Rgb([0.5, 2.0, 1e-3]),
                    _ => image::Rgb([rng.f32() * 100.0, rng.f32(), rng.f32() * 1e-4]),
                })
                .collect();
            let path = dir.path().join(format!("{w}x{h}.hdr"));
            let f = std::io::BufWriter::new(File::create(&path).unwrap());
            image::codecs::hdr::HdrEncoder::new(f)
                .encode(&px, w, h)
                .unwrap();
            let (rw, rh, texels) = read_all(&path).unwrap();
            assert_eq!((rw, rh), (w, h));
            assert_eq!(texels, image_crate(&path), "{w}×{h}");
        }
    }

    /// Old run lengths (a pixel (1, 1, 1, n) repeating the previous, consecutive ones
    /// shifting by 8 bits) and bottom-up scanlines.
    #[test]
    fn old_run_lengths_and_bottom_up_rows() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("old.hdr");
        let mut bytes = b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n+Y 2 +X 300\n".to_vec();
        // Bottom row (read first): one pixel, repeated 43 + (1 << 8) = 299 times more.
        bytes.extend([128, 64, 32, 129, 1, 1, 1, 43, 1, 1, 1, 1]);
        // Top row: 300 flat pixels of e = 0.
        bytes.extend(std::iter::repeat_n([7u8, 7, 7, 0], 300).flatten());
        std::fs::write(&path, &bytes).unwrap();
        let (w, h, texels) = read_all(&path).unwrap();
        assert_eq!((w, h), (300, 2));
        assert!(texels[..300].iter().all(|t| *t == [0.0; 3]));
        assert!(texels[300..].iter().all(|t| *t == [1.0, 0.5, 0.25]));
    }

    /// Damage is an error naming the file and what is wrong, never a panic.
    #[test]
    fn damaged_files_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        let sky = std::fs::read(
            std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenes/env/sky.hdr"),
        )
        .unwrap();
        let cases: Vec<(&str, Vec<u8>)> = vec![
            ("truncated", sky[..sky.len() / 2].to_vec()),
            ("no signature", sky[2..].to_vec()),
            (
                "xyze",
                b"#?RADIANCE\nFORMAT=32-bit_rle_xyze\n\n-Y 2 +X 2\n".to_vec(),
            ),
            ("sideways", b"#?RADIANCE\n\n+X 2 -Y 2\n".to_vec()),
            ("huge", b"#?RADIANCE\n\n-Y 100000 +X 100000\n".to_vec()),
            (
                "no blank line",
                b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n".to_vec(),
            ),
            (
                "bad run",
                b"#?RADIANCE\n\n-Y 1 +X 8\n\x02\x02\x00\x08\xff\x01".to_vec(),
            ),
        ];
        for (name, bytes) in cases {
            let path = dir.path().join(format!("{name}.hdr"));
            std::fs::write(&path, bytes).unwrap();
            let err = read_all(&path).unwrap_err().to_string();
            assert!(err.contains(&format!("{name}.hdr")), "{name}: {err}");
        }
    }
}
