//! The `.relight` file: one view's samples, the light cells its transfer reads (with
//! the points that light is gathered at) and each pixel's compressed transfer row. Layout
//! in `format/FORMAT.md` ("Relight files"); everything is checked when it is read: sizes
//! against the header's counts, the checksum, every index against what it indexes.

use super::cells::GatherPoint;
use super::view::ViewRay;
use anyhow::{bail, ensure, Context, Result};
use bytemuck::{Pod, Zeroable};
use half::f16;
use std::io::Write;
use std::path::{Path, PathBuf};
use xxhash_rust::xxh3::{xxh3_64, Xxh3};

pub const MAGIC: [u8; 8] = *b"CNPYRLT\0";
pub const VERSION: u32 = 1;
/// Longest archive path stored.
const MAX_PATH: usize = 4096;

#[derive(Clone, Copy, Debug, Pod, Zeroable)]
#[repr(C)]
pub struct Header {
    pub magic: [u8; 8],
    pub version: u32,
    pub width: u32,
    pub height: u32,
    /// View samples per pixel.
    pub spp: u32,
    /// Transfer paths per view sample.
    pub paths: u32,
    /// Most coefficients per pixel.
    pub coefficients: u32,
    pub seed: u32,
    pub path_len: u32,
    pub views: u64,
    pub cells: u64,
    pub points: u64,
    pub coefs: u64,
    pub emits: u64,
    /// The archive's `header_checksum`, so a relight refuses an archive changed since.
    pub archive_header: u64,
    /// Camera name, zero-padded (empty: the archive's first, or the default view).
    pub camera: [u8; 64],
}

const _: () = assert!(std::mem::size_of::<Header>() == 152);

/// A pixel's emission record: a material and the light its lamps send the pixel directly.
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
#[repr(C)]
pub struct Coef {
    pub index: u32,
    pub w: [f32; 3],
}

/// A relight file in memory.
pub struct RelightFile {
    pub header: Header,
    pub archive: PathBuf,
    pub views: Vec<ViewRay>,
    /// Per cell, its first point; `cells + 1` entries.
    pub cell_first: Vec<u64>,
    pub points: Vec<GatherPoint>,
    /// Per pixel, its first coefficient; `width × height + 1` entries.
    pub row_first: Vec<u64>,
    /// Per coefficient of the rows, the cell it reads (index into the cells) and the light
    /// it carries from that cell's mean arriving light E/π to the pixel.
    pub coef_cell: Vec<u32>,
    pub coef_w: Vec<[f16; 3]>,
    /// Per pixel, its first emission record; `width × height + 1` entries.
    pub emit_first: Vec<u64>,
    pub emits: Vec<Coef>,
}

impl RelightFile {
    pub fn camera(&self) -> Option<String> {
        let name = canopy_format::name_str(&self.header.camera);
        (!name.is_empty()).then_some(name)
    }

    pub fn write(&self, path: &Path) -> Result<()> {
        crate::image::write_atomically(path, |tmp| {
            let f = std::fs::File::create(tmp)?;
            let mut w = Hashing(std::io::BufWriter::new(f), Xxh3::new());
            let archive = self.archive.to_string_lossy();
            w.write_all(bytemuck::bytes_of(&self.header))?;
            w.write_all(archive.as_bytes())?;
            w.write_all(bytemuck::cast_slice(&self.views))?;
            w.write_all(bytemuck::cast_slice(&self.cell_first))?;
            w.write_all(bytemuck::cast_slice(&self.points))?;
            w.write_all(bytemuck::cast_slice(&self.row_first))?;
            w.write_all(bytemuck::cast_slice(&self.coef_cell))?;
            w.write_all(bytemuck::cast_slice(&self.coef_w))?;
            w.write_all(bytemuck::cast_slice(&self.emit_first))?;
            w.write_all(bytemuck::cast_slice(&self.emits))?;
            let sum = w.1.digest();
            w.0.write_all(&sum.to_le_bytes())?;
            w.0.flush()?;
            Ok(())
        })
    }

    pub fn read(path: &Path) -> Result<RelightFile> {
        let bytes =
            std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
        parse(&bytes).with_context(|| format!("{}: not a valid relight file", path.display()))
    }
}

/// A writer that hashes what it writes.
struct Hashing<W>(W, Xxh3);

impl<W: Write> Write for Hashing<W> {
    fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
        let n = self.0.write(b)?;
        self.1.update(&b[..n]);
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.0.flush()
    }
}

/// Splits `n` items of `T` off the front of `rest`.
fn take<T: Pod>(rest: &mut &[u8], n: u64) -> Result<Vec<T>> {
    let len = (n as usize)
        .checked_mul(std::mem::size_of::<T>())
        .context("counts overflow")?;
    ensure!(rest.len() >= len, "truncated");
    let (a, b) = rest.split_at(len);
    *rest = b;
    Ok(bytemuck::pod_collect_to_vec(a))
}

/// Offsets that start at 0, never fall and end at `count`.
fn check_offsets(what: &str, first: &[u64], count: u64) -> Result<()> {
    ensure!(
        first.first() == Some(&0),
        "{what}: offsets do not start at 0"
    );
    ensure!(
        first.windows(2).all(|w| w[0] <= w[1]),
        "{what}: offsets fall"
    );
    ensure!(
        first.last() == Some(&count),
        "{what}: offsets end at {:?}, not at the {count} stored",
        first.last()
    );
    Ok(())
}

fn parse(bytes: &[u8]) -> Result<RelightFile> {
    let hlen = std::mem::size_of::<Header>();
    ensure!(
        bytes.len() >= hlen + 8,
        "{} bytes is shorter than a header",
        bytes.len()
    );
    let header: Header = bytemuck::pod_read_unaligned(&bytes[..hlen]);
    ensure!(
        header.magic == MAGIC,
        "bad magic (a .relight file is written by `canopy relight ARCHIVE -o VIEW.relight`)"
    );
    ensure!(
        header.version == VERSION,
        "version {} (this canopy reads {VERSION})",
        header.version
    );
    let (body, sum) = bytes.split_at(bytes.len() - 8);
    let sum = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
    ensure!(
        xxh3_64(body) == sum,
        "checksum mismatch (the file is damaged or truncated)"
    );
    let h = &header;
    let pixels = h.width as u64 * h.height as u64;
    ensure!(
        pixels > 0 && h.spp > 0,
        "an empty view ({}x{}, {} samples per pixel)",
        h.width,
        h.height,
        h.spp
    );
    ensure!(
        pixels.checked_mul(h.spp as u64) == Some(h.views),
        "{} view samples for {pixels} pixels of {} samples",
        h.views,
        h.spp
    );
    ensure!(
        (h.path_len as usize) <= MAX_PATH,
        "archive path of {} bytes",
        h.path_len
    );
    let mut rest = &body[hlen..];
    let path: Vec<u8> = take(&mut rest, h.path_len as u64)?;
    let archive = PathBuf::from(String::from_utf8(path).context("archive path is not UTF-8")?);
    let views = take(&mut rest, h.views)?;
    let cell_first: Vec<u64> = take(
        &mut rest,
        h.cells.checked_add(1).context("counts overflow")?,
    )?;
    let points = take(&mut rest, h.points)?;
    let row_first: Vec<u64> = take(&mut rest, pixels + 1)?;
    let coef_cell: Vec<u32> = take(&mut rest, h.coefs)?;
    let coef_w: Vec<[f16; 3]> = take(&mut rest, h.coefs)?;
    let emit_first: Vec<u64> = take(&mut rest, pixels + 1)?;
    let emits: Vec<Coef> = take(&mut rest, h.emits)?;
    ensure!(
        rest.is_empty(),
        "{} bytes after the last section",
        rest.len()
    );
    check_offsets("cells", &cell_first, h.points)?;
    check_offsets("rows", &row_first, h.coefs)?;
    check_offsets("emission", &emit_first, h.emits)?;
    if let Some(c) = coef_cell.iter().find(|&&c| c as u64 >= h.cells) {
        bail!("a coefficient names cell {c} of {}", h.cells);
    }
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    ensure!(
        coef_w.iter().flatten().all(|x| x.is_finite()) && emits.iter().all(|c| finite(&c.w)),
        "a coefficient is not finite"
    );
    ensure!(
        points
            .iter()
            .all(|p: &GatherPoint| finite(&p.p) && finite(&p.n)),
        "a gather point is not finite"
    );
    ensure!(
        views
            .iter()
            .all(|v: &ViewRay| finite(&v.o) && finite(&v.d) && finite(&v.beta)),
        "a view ray is not finite"
    );
    Ok(RelightFile {
        header,
        archive,
        views,
        cell_first,
        points,
        row_first,
        coef_cell,
        coef_w,
        emit_first,
        emits,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// A small valid file: a 2×1 view of 1 sample a pixel reading 2 cells.
    fn small() -> RelightFile {
        let archive = PathBuf::from("/a.canopy");
        let view = ViewRay {
            o: [0.0; 3],
            d: [0.0, 0.0, 1.0],
            beta: [1.0; 3],
            u: 0.5,
            passes: 0,
        };
        let point = GatherPoint {
            p: [1.0, 2.0, 3.0],
            n: [0.0, 1.0, 0.0],
        };
        let mut camera = [0u8; 64];
        camera[..4].copy_from_slice(b"main");
        RelightFile {
            header: Header {
                magic: MAGIC,
                version: VERSION,
                width: 2,
                height: 1,
                spp: 1,
                paths: 4,
                coefficients: 8,
                seed: 0,
                path_len: archive.to_string_lossy().len() as u32,
                views: 2,
                cells: 2,
                points: 3,
                coefs: 3,
                emits: 1,
                archive_header: 7,
                camera,
            },
            archive,
            views: vec![view; 2],
            cell_first: vec![0, 1, 3],
            points: vec![point; 3],
            row_first: vec![0, 2, 3],
            coef_cell: vec![0, 1, 1],
            coef_w: vec![[f16::from_f32(0.5); 3]; 3],
            emit_first: vec![0, 0, 1],
            emits: vec![Coef {
                index: 0,
                w: [2.0; 3],
            }],
        }
    }

    #[test]
    fn a_written_file_reads_back_and_damage_is_refused_not_panicked_on() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.relight");
        small().write(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let back = parse(&bytes).unwrap();
        assert_eq!(back.camera().as_deref(), Some("main"));
        assert_eq!(back.coef_cell, vec![0, 1, 1]);
        assert_eq!(back.archive, PathBuf::from("/a.canopy"));
        // Any byte changed, with the checksum made to match: refused with a reason or read
        // as a file whose every index is in range; never a panic.
        let mut rng = TestRng::new(5);
        let body = bytes.len() - 8;
        let mut refused = 0;
        for _ in 0..4000 {
            let mut b = bytes.clone();
            let at = ((rng.f64() * body as f64) as usize).min(body - 1);
            b[at] ^= 1 << ((rng.f32() * 8.0) as u32).min(7);
            let sum = xxh3_64(&b[..body]);
            b[body..].copy_from_slice(&sum.to_le_bytes());
            match parse(&b) {
                Err(_) => refused += 1,
                Ok(f) => {
                    assert!(f.coef_cell.iter().all(|&c| (c as u64) < f.header.cells));
                    assert_eq!(*f.row_first.last().unwrap(), f.header.coefs);
                }
            }
        }
        assert!(
            refused > 1000,
            "only {refused} of 4000 damaged files refused"
        );
        // Without the checksum fixed, any change is refused.
        let mut b = bytes.clone();
        b[body / 2] ^= 4;
        let Err(e) = parse(&b) else {
            panic!("a damaged file was read");
        };
        assert!(format!("{e:#}").contains("checksum"));
    }
}
