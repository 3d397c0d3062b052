//! Spill files: triangles streamed to disk between conversion passes.
//!
//! Spill files have no name: they are created unlinked in the output's directory
//! (`O_TMPFILE`, or created and unlinked at once), so the kernel reclaims them when the
//! process ends, even by SIGKILL, and nothing of a conversion is left behind.
//!
//! A record is 40 bytes (positions and material). Triangles with shading normals or
//! curvature add a 16-byte attribute record, flagged in the material's top bit (texture
//! coordinates a 24-byte one, flagged in the next bit; vertex colours other than white a
//! 24-byte one, flagged in the bit after; a second set of texture coordinates a 24-byte
//! one, flagged in the bit after that), so meshes
//! without normals cost 40 bytes a triangle on disk instead of 56: spill I/O is most of the
//! time a conversion larger than the page cache's dirty limit spends.

use crate::import::{SpillTri, WHITE};
use anyhow::{bail, Context, Result};
use bytemuck::{Pod, Zeroable};
use std::fs::File;
use std::io::{BufWriter, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender};
use std::thread::JoinHandle;

const HAS_ATTR: u32 = 1 << 31;
/// A 24-byte texture-coordinate record follows (after the attribute record, if any).
const HAS_UV: u32 = 1 << 30;
/// A 24-byte vertex-colour record follows (after the texture coordinates, if any).
const HAS_COLOUR: u32 = 1 << 29;
/// A 24-byte record of the second texture coordinates follows (last).
const HAS_UV2: u32 = 1 << 28;
const FLAGS: u32 = HAS_ATTR | HAS_UV | HAS_COLOUR | HAS_UV2;

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Rec {
    p: [[f32; 3]; 3],
    material: u32,
}

#[repr(C)]
#[derive(Clone, Copy, Pod, Zeroable)]
struct Attr {
    n: [u32; 3],
    curvature: f32,
}

/// Triangles between the record starts a spill file keeps (`Spill::parts`).
pub const MARK_TRIANGLES: u64 = 1 << 20;

/// Writes spill records to a file, or (`At`) to a range of one that several writers share.
pub struct SpillWriter<W: Write = File> {
    out: BufWriter<W>,
    /// Bytes written so far: where the next record starts.
    written: u64,
    /// Triangles written so far.
    count: u64,
    /// Where the records of triangles 0, `MARK_TRIANGLES`, 2·`MARK_TRIANGLES`… start.
    marks: Vec<u64>,
    /// The shortest and the longest record written.
    lengths: [u64; 2],
    /// The directory, for messages (the file has no name).
    path: PathBuf,
}

/// A file written from `offset` on with positioned writes, so that writers on other
/// threads may fill other ranges of it at once.
pub struct At<'a> {
    file: &'a File,
    offset: u64,
}

impl Write for At<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.file.write_at(buf, self.offset)?;
        self.offset += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

/// The spill record's flags and its length in bytes for `t`.
fn layout(t: &SpillTri) -> (u32, u64) {
    let attr = t.n != [0; 3] || t.curvature != 0.0;
    let uv = t.uv != [[0.0; 2]; 3];
    let colour = t.colour != [WHITE; 3];
    let uv2 = t.uv2 != [[0.0; 2]; 3];
    let flag = |on: bool, bit: u32| if on { bit } else { 0 };
    let flags =
        flag(attr, HAS_ATTR) | flag(uv, HAS_UV) | flag(colour, HAS_COLOUR) | flag(uv2, HAS_UV2);
    (flags, record_len(flags))
}

/// Bytes a record with these flags takes: 40, 16 more with attributes, 24 more for each of
/// the texture coordinates, the colours and the second texture coordinates.
fn record_len(flags: u32) -> u64 {
    let has = |bit: u32| (flags & bit != 0) as u64;
    40 + 16 * has(HAS_ATTR) + 24 * (has(HAS_UV) + has(HAS_COLOUR) + has(HAS_UV2))
}

/// A spill file: unnamed in `dir`, or named `path` (a cluster conversion's chunk file),
/// replacing what is there.
pub fn create_file(dir: &Path, named: Option<&Path>) -> Result<File> {
    match named {
        None => unnamed(dir),
        Some(path) => File::create(path)
            .with_context(|| format!("{}: cannot create a chunk file", path.display())),
    }
}

impl<'a> SpillWriter<At<'a>> {
    /// A writer of `file` from byte `offset`; `path` names it in messages.
    pub fn at(file: &'a File, offset: u64, buffer: usize, path: &Path) -> SpillWriter<At<'a>> {
        SpillWriter {
            out: BufWriter::with_capacity(buffer, At { file, offset }),
            written: 0,
            count: 0,
            marks: Vec::new(),
            lengths: [u64::MAX, 0],
            path: path.to_path_buf(),
        }
    }

    /// Writes out what is buffered.
    pub fn flush(mut self) -> Result<()> {
        self.out
            .flush()
            .with_context(|| format!("{}: writing", self.path.display()))
    }
}

impl SpillWriter {
    /// An unnamed spill file in `dir`.
    pub fn create(dir: &Path, buffer: usize) -> Result<SpillWriter> {
        Ok(SpillWriter::over(
            unnamed(dir)?,
            buffer,
            dir.join("(spill file)"),
        ))
    }

    /// A writer of `file` from its start; `path` names it in messages.
    pub fn over(file: File, buffer: usize, path: PathBuf) -> SpillWriter {
        SpillWriter {
            out: BufWriter::with_capacity(buffer, file),
            written: 0,
            count: 0,
            marks: Vec::new(),
            lengths: [u64::MAX, 0],
            path,
        }
    }

    /// Flushes and returns the spill, ready to read.
    pub fn finish(self) -> Result<Spill> {
        let err = || format!("{}: writing", self.path.display());
        let file = self
            .out
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(err)?;
        let [short, long] = self.lengths;
        Ok(Spill {
            file,
            path: self.path,
            count: Some(self.count),
            marks: self.marks,
            record_len: (short == long).then_some(long),
        })
    }
}

impl<W: Write> SpillWriter<W> {
    /// Triangles written so far.
    pub fn count(&self) -> u64 {
        self.count
    }

    /// Where the next record will start, for `for_each_in`.
    pub fn position(&self) -> u64 {
        self.written
    }

    pub fn write(&mut self, t: &SpillTri) -> Result<()> {
        if t.material & FLAGS != 0 {
            bail!("material index {} is out of range", t.material);
        }
        let (flags, bytes) = layout(t);
        let attr = flags & HAS_ATTR != 0;
        let uv = flags & HAS_UV != 0;
        let colour = flags & HAS_COLOUR != 0;
        let uv2 = flags & HAS_UV2 != 0;
        if self.count.is_multiple_of(MARK_TRIANGLES) {
            self.marks.push(self.written);
        }
        let rec = Rec {
            p: t.p,
            material: t.material | flags,
        };
        let mut r = self.out.write_all(bytemuck::bytes_of(&rec));
        if attr && r.is_ok() {
            let a = Attr {
                n: t.n,
                curvature: t.curvature,
            };
            r = self.out.write_all(bytemuck::bytes_of(&a));
        }
        if uv && r.is_ok() {
            r = self.out.write_all(bytemuck::bytes_of(&t.uv));
        }
        if colour && r.is_ok() {
            r = self.out.write_all(bytemuck::bytes_of(&t.colour));
        }
        if uv2 && r.is_ok() {
            r = self.out.write_all(bytemuck::bytes_of(&t.uv2));
        }
        self.written += bytes;
        self.count += 1;
        self.lengths = [self.lengths[0].min(bytes), self.lengths[1].max(bytes)];
        r.with_context(|| format!("{}: writing spill file", self.path.display()))
    }
}

/// A spill writer on a thread of its own: triangles go to it in batches, so that encoding
/// and writing them overlaps the work that produces them (an importer's parsing).
pub struct Background {
    batch: Vec<SpillTri>,
    to: Option<SyncSender<Vec<SpillTri>>>,
    /// Batches the writer is done with, to be filled again.
    back: Receiver<Vec<SpillTri>>,
    writer: Option<JoinHandle<Result<Spill>>>,
}

/// Triangles a batch holds (128 KiB of them).
const BATCH: usize = 1024;

impl Background {
    /// A writer of `w`'s file on its own thread.
    pub fn new(mut w: SpillWriter) -> Background {
        let (to, from) = sync_channel::<Vec<SpillTri>>(8);
        let (give_back, back) = sync_channel(8);
        let writer = std::thread::spawn(move || {
            for mut batch in from {
                batch.iter().try_for_each(|t| w.write(t))?;
                batch.clear();
                // The producer may be gone or have batches enough.
                let _ = give_back.try_send(batch);
            }
            w.finish()
        });
        Background {
            batch: Vec::with_capacity(BATCH),
            to: Some(to),
            back,
            writer: Some(writer),
        }
    }

    pub fn write(&mut self, t: &SpillTri) -> Result<()> {
        self.batch.push(*t);
        if self.batch.len() == BATCH {
            self.send()?;
        }
        Ok(())
    }

    /// Sends the batch; a writer that stopped returns its error.
    fn send(&mut self) -> Result<()> {
        let next = self
            .back
            .try_recv()
            .unwrap_or_else(|_| Vec::with_capacity(BATCH));
        let batch = std::mem::replace(&mut self.batch, next);
        let sent = self.to.as_ref().map(|to| to.send(batch).is_ok());
        if sent != Some(true) {
            self.to = None;
            return self.join().map(drop);
        }
        Ok(())
    }

    /// The writer's result once it has written everything sent.
    fn join(&mut self) -> Result<Spill> {
        self.to = None;
        match self.writer.take().map(JoinHandle::join) {
            Some(Ok(result)) => result,
            Some(Err(_)) => bail!("the spill writer thread panicked"),
            None => bail!("the spill writer has stopped"),
        }
    }

    /// Writes what is left and returns the spill, ready to read.
    pub fn finish(mut self) -> Result<Spill> {
        if !self.batch.is_empty() {
            self.send()?;
        }
        self.join()
    }
}

/// An unnamed file in `dir` (see the module's notes).
pub fn unnamed(dir: &Path) -> Result<File> {
    tempfile::tempfile_in(dir)
        .with_context(|| format!("{}: cannot create a spill file", dir.display()))
}

/// A finished spill file.
pub struct Spill {
    file: File,
    path: PathBuf,
    /// Its triangles, when this process wrote it.
    count: Option<u64>,
    /// Where the records of triangles 0, `MARK_TRIANGLES`, 2·`MARK_TRIANGLES`… start (empty when not known).
    marks: Vec<u64>,
    /// The length of every record, when all have one and this process wrote them.
    record_len: Option<u64>,
}

impl Spill {
    /// A named spill file, as `SpillWriter::create_named` wrote it.
    pub fn open(path: &Path) -> Result<Spill> {
        let file = File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
        Ok(Spill {
            file,
            path: path.to_path_buf(),
            count: None,
            marks: Vec::new(),
            record_len: None,
        })
    }

    /// A spill file of `count` triangles that writers `at` its ranges filled.
    pub fn written(file: File, path: &Path, count: u64) -> Spill {
        Spill {
            file,
            path: path.to_path_buf(),
            count: Some(count),
            marks: Vec::new(),
            record_len: None,
        }
    }

    /// The length of every record, when all have one (known for spills this process wrote
    /// through one writer).
    pub fn record_len(&self) -> Option<u64> {
        self.record_len
    }

    /// The records split into at most `n` consecutive ranges of whole `MARK_TRIANGLES`s, as (start,
    /// triangles) for `for_each_in`; the last runs to the end.
    pub fn parts(&self, n: usize) -> Vec<(u64, u64)> {
        let marks = self.marks.len().max(1);
        let n = n.clamp(1, marks);
        (0..n)
            .map(|p| {
                let first = p * marks / n;
                let start = self.marks.get(first).copied().unwrap_or(0);
                let count = match p + 1 == n {
                    true => u64::MAX,
                    false => ((p + 1) * marks / n - first) as u64 * MARK_TRIANGLES,
                };
                (start, count)
            })
            .collect()
    }
}

/// Calls `f` on every triangle of a spill file, in order.
pub fn for_each(spill: &Spill, f: impl FnMut(&SpillTri) -> Result<()>) -> Result<()> {
    for_each_in(spill, 0, u64::MAX, f)
}

/// Calls `f` on the `count` triangles (or up to the end) from byte `start`, a record start
/// `SpillWriter::position` returned. Records are parsed from 1 MiB blocks read at once.
pub fn for_each_in(
    spill: &Spill,
    start: u64,
    count: u64,
    mut f: impl FnMut(&SpillTri) -> Result<()>,
) -> Result<()> {
    let path = &spill.path;
    let mut r = Blocks {
        file: &spill.file,
        offset: start,
        buf: vec![0; 1 << 20],
        pos: 0,
        end: 0,
    };
    let err = || format!("{}: reading spill", path.display());
    for _ in 0..count {
        if !r.hold(40).with_context(err)? {
            if count == u64::MAX && r.pos == r.end {
                return Ok(());
            }
            bail!("{}: the spill file ends early", path.display());
        }
        let rec: Rec = bytemuck::pod_read_unaligned(&r.buf[r.pos..r.pos + 40]);
        let flags = rec.material;
        let len = record_len(flags) as usize;
        if !r.hold(len).with_context(err)? {
            bail!("{}: the spill file ends early", path.display());
        }
        let mut t = SpillTri {
            p: rec.p,
            material: flags & !FLAGS,
            ..Default::default()
        };
        let mut at = r.pos + 40;
        let mut take = |n: usize| {
            at += n;
            &r.buf[at - n..at]
        };
        if flags & HAS_ATTR != 0 {
            let a: Attr = bytemuck::pod_read_unaligned(take(16));
            t.n = a.n;
            t.curvature = a.curvature;
        }
        if flags & HAS_UV != 0 {
            t.uv = bytemuck::pod_read_unaligned(take(24));
        }
        if flags & HAS_COLOUR != 0 {
            t.colour = bytemuck::pod_read_unaligned(take(24));
        }
        if flags & HAS_UV2 != 0 {
            t.uv2 = bytemuck::pod_read_unaligned(take(24));
        }
        r.pos += len;
        f(&t)?;
    }
    Ok(())
}

/// A file read in blocks from `offset` on (positioned reads, so that readers on other
/// threads may share the file): `buf[pos..end]` holds the bytes not yet parsed.
struct Blocks<'a> {
    file: &'a File,
    offset: u64,
    buf: Vec<u8>,
    pos: usize,
    end: usize,
}

impl Blocks<'_> {
    /// Makes at least `n` unparsed bytes available (moving the rest to the front and reading
    /// on); false when the file ends first.
    fn hold(&mut self, n: usize) -> std::io::Result<bool> {
        if self.end - self.pos >= n {
            return Ok(true);
        }
        self.buf.copy_within(self.pos..self.end, 0);
        self.end -= self.pos;
        self.pos = 0;
        while self.end < n {
            match self.file.read_at(&mut self.buf[self.end..], self.offset) {
                Ok(0) => return Ok(false),
                Ok(k) => {
                    self.end += k;
                    self.offset += k as u64;
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(true)
    }
}

/// Every triangle of a spill file, in order.
pub fn read_all(spill: &Spill) -> Result<Vec<SpillTri>> {
    let mut out = Vec::with_capacity(spill.count.unwrap_or(0) as usize);
    for_each(spill, |t| {
        out.push(*t);
        Ok(())
    })?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_with_and_without_attributes() {
        let dir = tempfile::tempdir().unwrap();
        let tris: Vec<SpillTri> = (0..1000u32)
            .map(|i| SpillTri {
                p: [
                    [i as f32, -1.5, 2.0],
                    [0.25, i as f32 * 1e-3, 7.0],
                    [1e7, -1e-7, 3.0],
                ],
                n: if i % 3 == 0 { [i, i + 1, 7] } else { [0; 3] },
                material: i % 5,
                curvature: if i % 7 == 0 { i as f32 * 0.5 } else { 0.0 },
                uv: if i % 4 == 1 {
                    [[i as f32, 0.5], [-2.0, 1e-3], [0.0, 7.0]]
                } else {
                    [[0.0; 2]; 3]
                },
                colour: if i % 6 == 2 {
                    [[i as u16, 0, 7, 65535], WHITE, [1, 2, 3, 4]]
                } else {
                    [WHITE; 3]
                },
                uv2: if i % 5 == 3 {
                    [[0.0; 2], [-(i as f32), 2.5], [1.0, 0.0]]
                } else {
                    [[0.0; 2]; 3]
                },
            })
            .collect();
        let mut w = SpillWriter::create(dir.path(), 4096).unwrap();
        for t in &tris {
            w.write(t).unwrap();
        }
        let spill = w.finish().unwrap();
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            0,
            "a spill file has no name"
        );
        let attrs = tris
            .iter()
            .filter(|t| t.n != [0; 3] || t.curvature != 0.0)
            .count() as u64;
        let uvs = tris.iter().filter(|t| t.uv != [[0.0; 2]; 3]).count() as u64;
        let colours = tris.iter().filter(|t| t.colour != [WHITE; 3]).count() as u64;
        let uvs2 = tris.iter().filter(|t| t.uv2 != [[0.0; 2]; 3]).count() as u64;
        let len = spill.file.metadata().unwrap().len();
        assert_eq!(
            len,
            tris.len() as u64 * 40 + attrs * 16 + (uvs + colours + uvs2) * 24
        );
        assert_eq!(read_all(&spill).unwrap(), tris);
    }

    #[test]
    fn a_truncated_record_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SpillWriter::create(dir.path(), 4096).unwrap();
        w.write(&SpillTri::default()).unwrap();
        let spill = w.finish().unwrap();
        spill.file.set_len(30).unwrap();
        assert!(read_all(&spill).is_err());
    }

    /// Triangles `0..n`, told apart by their first vertex's x.
    fn numbered(n: u32) -> Vec<SpillTri> {
        (0..n)
            .map(|i| SpillTri {
                p: [[i as f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                curvature: (i % 2) as f32,
                ..Default::default()
            })
            .collect()
    }

    #[test]
    fn a_background_writer_writes_what_the_writer_writes() {
        let dir = tempfile::tempdir().unwrap();
        let tris = numbered(5 * BATCH as u32 + 17);
        let mut w = Background::new(SpillWriter::create(dir.path(), 4096).unwrap());
        tris.iter().for_each(|t| w.write(t).unwrap());
        let spill = w.finish().unwrap();
        assert_eq!(spill.count, Some(tris.len() as u64));
        assert_eq!(read_all(&spill).unwrap(), tris);
        // Marks where ranges may start: the first record, and none beyond the triangles.
        assert_eq!(spill.marks, vec![0]);
        assert_eq!(spill.parts(2), vec![(0, u64::MAX)]);
    }

    #[test]
    fn a_background_writer_reports_the_writers_error() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = Background::new(SpillWriter::create(dir.path(), 4096).unwrap());
        let bad = SpillTri {
            material: HAS_UV,
            ..Default::default()
        };
        w.write(&bad).unwrap();
        let more = numbered(3 * BATCH as u32);
        let sent: Result<()> = more.iter().try_for_each(|t| w.write(t));
        let err = sent.and_then(|_| w.finish().map(drop)).unwrap_err();
        assert!(format!("{err:#}").contains("out of range"), "{err:#}");
    }

    #[test]
    fn ranges_start_at_the_marked_records() {
        let dir = tempfile::tempdir().unwrap();
        let n = 2 * MARK_TRIANGLES + 5;
        let mut w = SpillWriter::create(dir.path(), 1 << 20).unwrap();
        for i in 0..n {
            let t = SpillTri {
                p: [[i as f32, 0.0, 0.0]; 3],
                curvature: (i % 3 == 0) as u32 as f32,
                ..Default::default()
            };
            w.write(&t).unwrap();
        }
        let spill = w.finish().unwrap();
        assert_eq!(spill.marks.len(), 3);
        let parts = spill.parts(2);
        assert_eq!(parts.len(), 2);
        assert_eq!(parts[0], (0, MARK_TRIANGLES));
        let mut seen = 0u64;
        for (start, count) in parts {
            for_each_in(&spill, start, count, |t| {
                assert_eq!(t.p[0][0], seen as f32);
                seen += 1;
                Ok(())
            })
            .unwrap();
        }
        assert_eq!(seen, n);
    }
}
