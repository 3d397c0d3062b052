//! The `.relight` file: one view's samples, the light cells its transfer reads (with
//! the points that light is gathered at) and each pixel's compressed transfer row. Layout
//! in `format/FORMAT.md` ("The relight file"). It is written section by section as the
//! precompute streams (`Writer`), and read mapped (`RelightFile`): a frame touches the rows
//! and points in place, so the operating system pages them like the archive's pages and
//! the file need not fit in memory. Everything is checked when it is opened: sizes against
//! the header's counts, the checksum, every index against what it indexes.

use super::cells::GatherPoint;
use super::view::ViewRay;
use anyhow::{bail, ensure, Context, Result};
use bytemuck::{Pod, Zeroable};
use canopy_format::atomic::AtomicFile;
use half::f16;
use std::ops::Range;
use std::path::{Path, PathBuf};
use xxhash_rust::xxh3::Xxh3;

pub const MAGIC: [u8; 8] = *b"CNPYRLT\0";
pub const VERSION: u32 = 4;
/// Longest archive path stored.
const MAX_PATH: usize = 4096;
/// Every section starts at a multiple of this (zero bytes pad the one before), so the
/// mapped file's sections are read in place.
const ALIGN: usize = 8;
const HLEN: usize = std::mem::size_of::<Header>();

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
    pub skies: u64,
    /// The archive's `header_checksum`, so a relight refuses an archive changed since.
    pub archive_header: u64,
    /// Camera name, zero-padded (empty: the archive's first, or the default view).
    pub camera: [u8; 64],
}

const _: () = assert!(HLEN == 160 && HLEN.is_multiple_of(ALIGN));

impl Header {
    pub fn pixels(&self) -> u64 {
        self.width as u64 * self.height as u64
    }
}

/// A pixel's emission record: a material and the light its lamps send the pixel directly.
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
#[repr(C)]
pub struct Coef {
    pub index: u32,
    pub w: [f32; 3],
}

/// A pixel's record of the environment its transfer met after a smooth bounce or through a
/// surface: the direction it was met along, and the weight on the environment's radiance
/// there.
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
#[repr(C)]
pub struct Sky {
    pub d: [f32; 3],
    pub w: [f32; 3],
}

/// Where each section lies in the file, in the order they are written.
#[derive(Clone, Debug, Default)]
struct Sections {
    path: Range<usize>,
    views: Range<usize>,
    points: Range<usize>,
    cell_first: Range<usize>,
    row_first: Range<usize>,
    coef_cell: Range<usize>,
    coef_w: Range<usize>,
    emit_first: Range<usize>,
    emits: Range<usize>,
    sky_first: Range<usize>,
    skies: Range<usize>,
    /// The file's length, the checksum's 8 bytes included.
    len: usize,
}

/// The sections' places for the counts `h` gives.
fn layout(h: &Header) -> Result<Sections> {
    let pixels = h.pixels();
    let mut at = HLEN;
    let mut next = |n: u64, size: usize| -> Result<Range<usize>> {
        let len = usize::try_from(n)
            .ok()
            .and_then(|n| n.checked_mul(size))
            .context("counts overflow")?;
        let start = at;
        let end = start.checked_add(len).context("counts overflow")?;
        at = end
            .checked_next_multiple_of(ALIGN)
            .context("counts overflow")?;
        Ok(start..end)
    };
    let cells = h.cells.checked_add(1).context("counts overflow")?;
    let mut s = Sections {
        path: next(h.path_len as u64, 1)?,
        views: next(h.views, std::mem::size_of::<ViewRay>())?,
        points: next(h.points, std::mem::size_of::<GatherPoint>())?,
        cell_first: next(cells, 8)?,
        row_first: next(pixels + 1, 8)?,
        coef_cell: next(h.coefs, 4)?,
        coef_w: next(h.coefs, 6)?,
        emit_first: next(pixels + 1, 8)?,
        emits: next(h.emits, std::mem::size_of::<Coef>())?,
        sky_first: next(pixels + 1, 8)?,
        skies: next(h.skies, std::mem::size_of::<Sky>())?,
        len: 0,
    };
    s.len = at.checked_add(8).context("counts overflow")?;
    Ok(s)
}

/// The checksum: xxh3-64 of the bytes after the header (to the checksum), then the header
/// (written last, once the counts are known).
fn checksum(body: &[u8], header: &[u8]) -> u64 {
    let mut h = Xxh3::new();
    h.update(body);
    h.update(header);
    h.digest()
}

/// Writes a relight file section by section, in the order of `Sections`; nothing appears
/// at the path until `commit`, which checks the sections against the header's counts.
pub struct Writer {
    out: AtomicFile,
    hash: Xxh3,
}

impl Writer {
    /// Starts the file at `path`, its first section the archive's path.
    pub fn create(path: &Path, archive: &Path) -> Result<Writer> {
        let out = AtomicFile::create(path, HLEN)
            .with_context(|| format!("{}: cannot write", path.display()))?;
        let mut w = Writer {
            out,
            hash: Xxh3::new(),
        };
        w.section(archive.to_string_lossy().as_bytes())?;
        Ok(w)
    }

    /// Appends `items` to the section being written.
    pub fn put<T: Pod>(&mut self, items: &[T]) -> Result<()> {
        let bytes: &[u8] = bytemuck::cast_slice(items);
        self.hash.update(bytes);
        Ok(self.out.write_all(bytes)?)
    }

    /// Writes a whole section: `items`, then its padding.
    pub fn section<T: Pod>(&mut self, items: &[T]) -> Result<()> {
        self.put(items)?;
        self.end()
    }

    /// Ends a section: zero bytes to the next multiple of 8.
    pub fn end(&mut self) -> Result<()> {
        let pad = (self.out.len() as usize).next_multiple_of(ALIGN) - self.out.len() as usize;
        self.put(&[0u8; ALIGN][..pad])
    }

    /// Writes the checksum and `header`, and names the file.
    pub fn commit(mut self, header: &Header) -> Result<()> {
        let s = layout(header)?;
        ensure!(
            self.out.len() as usize + 8 == s.len,
            "{} bytes written where the header's counts make {}",
            self.out.len() + 8,
            s.len
        );
        self.hash.update(bytemuck::bytes_of(header));
        let sum = self.hash.digest();
        self.out.write_all(&sum.to_le_bytes())?;
        self.out.commit(bytemuck::bytes_of(header))?;
        Ok(())
    }
}

/// A relight file, mapped: its sections are read in place.
pub struct RelightFile {
    pub header: Header,
    pub archive: PathBuf,
    map: memmap2::Mmap,
    at: Sections,
}

impl RelightFile {
    pub fn camera(&self) -> Option<String> {
        let name = canopy_format::name_str(&self.header.camera);
        (!name.is_empty()).then_some(name)
    }

    /// The view samples, `spp` per pixel.
    pub fn views(&self) -> &[ViewRay] {
        self.slice(&self.at.views)
    }

    /// The gather points, cell by cell.
    pub fn points(&self) -> &[GatherPoint] {
        self.slice(&self.at.points)
    }

    /// Per cell, its first point; `cells + 1` entries.
    pub fn cell_first(&self) -> &[u64] {
        self.slice(&self.at.cell_first)
    }

    /// Per pixel, its first coefficient; `width × height + 1` entries.
    pub fn row_first(&self) -> &[u64] {
        self.slice(&self.at.row_first)
    }

    /// Per coefficient of the rows, the cell it reads (an index into the cells).
    pub fn coef_cell(&self) -> &[u32] {
        self.slice(&self.at.coef_cell)
    }

    /// Per coefficient, the light it carries from its cell's mean arriving light E/π to
    /// the pixel.
    pub fn coef_w(&self) -> &[[f16; 3]] {
        self.slice(&self.at.coef_w)
    }

    /// Per pixel, its first emission record; `width × height + 1` entries.
    pub fn emit_first(&self) -> &[u64] {
        self.slice(&self.at.emit_first)
    }

    pub fn emits(&self) -> &[Coef] {
        self.slice(&self.at.emits)
    }

    /// Per pixel, its first sky record (one more at the end).
    pub fn sky_first(&self) -> &[u64] {
        self.slice(&self.at.sky_first)
    }

    /// The sky records, pixel by pixel.
    pub fn skies(&self) -> &[Sky] {
        self.slice(&self.at.skies)
    }

    /// A section in place: every section starts at a multiple of 8 of a page-aligned map.
    fn slice<T: Pod>(&self, r: &Range<usize>) -> &[T] {
        bytemuck::cast_slice(&self.map[r.clone()])
    }

    /// Opens and checks the file at `path`, and lets the kernel drop the pages the check
    /// read (a frame faults back those it reads).
    pub fn read(path: &Path) -> Result<RelightFile> {
        let cannot = || format!("{}: cannot read", path.display());
        // Stat before opening: opening a FIFO for reading would block until a writer came.
        ensure!(
            std::fs::metadata(path).with_context(cannot)?.is_file(),
            "{}: not a file",
            path.display()
        );
        let file = std::fs::File::open(path).with_context(cannot)?;
        // SAFETY: read-only mapping; every access is within the length checked in `parse`.
        let map = unsafe { memmap2::Mmap::map(&file) }.with_context(cannot)?;
        let (header, archive, at) =
            parse(&map).with_context(|| format!("{}: not a valid relight file", path.display()))?;
        #[cfg(unix)]
        // SAFETY: the mapping is read-only and shared; after MADV_DONTNEED a read faults
        // the same file bytes back in, so no reader can observe a change.
        unsafe {
            map.unchecked_advise(memmap2::UncheckedAdvice::DontNeed)
                .ok();
        }
        Ok(RelightFile {
            header,
            archive,
            map,
            at,
        })
    }
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

/// The header and the checks that need only it.
fn parse_header(bytes: &[u8]) -> Result<Header> {
    ensure!(
        bytes.len() >= HLEN + 8,
        "{} bytes is shorter than a header",
        bytes.len()
    );
    let h: Header = bytemuck::pod_read_unaligned(&bytes[..HLEN]);
    ensure!(
        h.magic == MAGIC,
        "bad magic (a .relight file is written by `canopy relight ARCHIVE -o VIEW.relight`)"
    );
    ensure!(
        h.version == VERSION,
        "version {} (this canopy reads {VERSION}: run `canopy relight` on the archive again)",
        h.version
    );
    let pixels = h.pixels();
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
    Ok(h)
}

fn parse(bytes: &[u8]) -> Result<(Header, PathBuf, Sections)> {
    let h = parse_header(bytes)?;
    let s = layout(&h)?;
    ensure!(
        bytes.len() == s.len,
        "{} bytes where the header's counts make {}",
        bytes.len(),
        s.len
    );
    let (body, sum) = bytes.split_at(bytes.len() - 8);
    let sum = u64::from_le_bytes(sum.try_into().expect("8 bytes"));
    ensure!(
        checksum(&body[HLEN..], &body[..HLEN]) == sum,
        "checksum mismatch (the file is damaged or truncated)"
    );
    let sections = [
        &s.path,
        &s.views,
        &s.points,
        &s.cell_first,
        &s.row_first,
        &s.coef_cell,
        &s.coef_w,
        &s.emit_first,
        &s.emits,
        &s.sky_first,
        &s.skies,
    ];
    let pads = sections
        .windows(2)
        .map(|w| w[0].end..w[1].start)
        .chain(std::iter::once(s.skies.end..s.len - 8));
    for pad in pads {
        ensure!(
            bytes[pad].iter().all(|&b| b == 0),
            "padding between sections is not zero"
        );
    }
    let archive = PathBuf::from(
        std::str::from_utf8(&bytes[s.path.clone()]).context("archive path is not UTF-8")?,
    );
    let cast = |r: &Range<usize>| &bytes[r.clone()];
    check_offsets("cells", bytemuck::cast_slice(cast(&s.cell_first)), h.points)?;
    check_offsets("rows", bytemuck::cast_slice(cast(&s.row_first)), h.coefs)?;
    check_offsets(
        "emission",
        bytemuck::cast_slice(cast(&s.emit_first)),
        h.emits,
    )?;
    check_offsets("sky", bytemuck::cast_slice(cast(&s.sky_first)), h.skies)?;
    let coef_cell: &[u32] = bytemuck::cast_slice(cast(&s.coef_cell));
    if let Some(c) = coef_cell.iter().find(|&&c| c as u64 >= h.cells) {
        bail!("a coefficient names cell {c} of {}", h.cells);
    }
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    let coef_w: &[[f16; 3]] = bytemuck::cast_slice(cast(&s.coef_w));
    let emits: &[Coef] = bytemuck::cast_slice(cast(&s.emits));
    let skies: &[Sky] = bytemuck::cast_slice(cast(&s.skies));
    ensure!(
        coef_w.iter().flatten().all(|x| x.is_finite())
            && emits.iter().all(|c| finite(&c.w))
            && skies.iter().all(|c| finite(&c.w) && finite(&c.d)),
        "a coefficient is not finite"
    );
    let points: &[GatherPoint] = bytemuck::cast_slice(cast(&s.points));
    ensure!(
        points
            .iter()
            .all(|p| finite(&p.p) && finite(&p.n) && finite(&p.s)),
        "a gather point is not finite"
    );
    let views: &[ViewRay] = bytemuck::cast_slice(cast(&s.views));
    ensure!(
        views
            .iter()
            .all(|v| finite(&v.o) && finite(&v.d) && finite(&v.beta)),
        "a view ray is not finite"
    );
    Ok((h, archive, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::TestRng;

    /// Writes a small valid file: a 2×1 view of 1 sample a pixel reading 2 cells.
    fn small(path: &Path) {
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
            s: [0.0, 0.6, 0.8],
        };
        let mut camera = [0u8; 64];
        camera[..4].copy_from_slice(b"main");
        let header = Header {
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
            skies: 1,
            archive_header: 7,
            camera,
        };
        let mut w = Writer::create(path, &archive).unwrap();
        w.section(&[view; 2]).unwrap();
        w.section(&[point; 3]).unwrap();
        w.section(&[0u64, 1, 3]).unwrap();
        w.section(&[0u64, 2, 3]).unwrap();
        w.section(&[0u32, 1, 1]).unwrap();
        w.section(&[[f16::from_f32(0.5); 3]; 3]).unwrap();
        w.section(&[0u64, 0, 1]).unwrap();
        let emit = Coef {
            index: 0,
            w: [2.0; 3],
        };
        w.section(&[emit]).unwrap();
        w.section(&[0u64, 1, 1]).unwrap();
        let sky = Sky {
            d: [0.0, 1.0, 0.0],
            w: [0.25; 3],
        };
        w.section(&[sky]).unwrap();
        w.commit(&header).unwrap();
    }

    /// `bytes` at an 8-byte-aligned address, as a mapped file is.
    fn parse_aligned(bytes: &[u8]) -> Result<(Header, PathBuf, Sections)> {
        let mut words = vec![0u64; bytes.len().div_ceil(8)];
        let b: &mut [u8] = bytemuck::cast_slice_mut(&mut words);
        b[..bytes.len()].copy_from_slice(bytes);
        parse(&b[..bytes.len()])
    }

    #[test]
    fn a_written_file_reads_back_and_damage_is_refused_not_panicked_on() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.relight");
        small(&path);
        let back = RelightFile::read(&path).unwrap();
        assert_eq!(back.camera().as_deref(), Some("main"));
        assert_eq!(back.coef_cell(), &[0, 1, 1]);
        assert_eq!(back.cell_first(), &[0, 1, 3]);
        assert_eq!(back.emits()[0].w, [2.0; 3]);
        assert_eq!(back.sky_first(), &[0, 1, 1]);
        assert_eq!(back.skies()[0].w, [0.25; 3]);
        assert_eq!(back.archive, PathBuf::from("/a.canopy"));
        let bytes = std::fs::read(&path).unwrap();
        // Any byte changed, with the checksum made to match: refused with a reason or read
        // as a file whose every index is in range; never a panic.
        let mut rng = TestRng::new(5);
        let body = bytes.len() - 8;
        let mut refused = 0;
        for _ in 0..4000 {
            let mut b = bytes.clone();
            let at = ((rng.f64() * body as f64) as usize).min(body - 1);
            b[at] ^= 1 << ((rng.f32() * 8.0) as u32).min(7);
            let sum = checksum(&b[HLEN..body], &b[..HLEN]);
            b[body..].copy_from_slice(&sum.to_le_bytes());
            match parse_aligned(&b) {
                Err(_) => refused += 1,
                Ok((h, _, s)) => {
                    let cells: &[u32] = bytemuck::cast_slice(&b[s.coef_cell.clone()]);
                    assert!(cells.iter().all(|&c| (c as u64) < h.cells));
                    let rows: &[u64] = bytemuck::cast_slice(&b[s.row_first.clone()]);
                    assert_eq!(*rows.last().unwrap(), h.coefs);
                }
            }
        }
        assert!(
            refused > 1000,
            "only {refused} of 4000 damaged files refused"
        );
        // Without the checksum fixed, any change is refused, and so is a cut file.
        let mut b = bytes.clone();
        b[body / 2] ^= 4;
        let e = parse_aligned(&b).expect_err("a damaged file was read");
        assert!(format!("{e:#}").contains("checksum"));
        let e = parse_aligned(&bytes[..body - 16]).expect_err("a cut file was read");
        assert!(format!("{e:#}").contains("header's counts make"));
    }

    #[test]
    fn a_writer_whose_sections_disagree_with_the_header_names_no_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("v.relight");
        let mut w = Writer::create(&path, Path::new("/a.canopy")).unwrap();
        w.put(&[0u64; 3]).unwrap();
        let h = Header {
            magic: MAGIC,
            version: VERSION,
            width: 1,
            height: 1,
            spp: 1,
            views: 1,
            path_len: 9,
            ..Zeroable::zeroed()
        };
        assert!(w.commit(&h).is_err());
        assert!(!path.exists());
    }
}
