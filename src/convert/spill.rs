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
use std::io::{BufRead, BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

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

pub struct SpillWriter {
    out: BufWriter<File>,
    /// Bytes written so far: where the next record starts.
    written: u64,
    /// The directory, for messages (the file has no name).
    path: PathBuf,
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

    /// A spill file named `path` (a cluster conversion's chunk file), replacing what is there.
    pub fn create_named(path: &Path, buffer: usize) -> Result<SpillWriter> {
        let file = File::create(path)
            .with_context(|| format!("{}: cannot create a chunk file", path.display()))?;
        Ok(SpillWriter::over(file, buffer, path.to_path_buf()))
    }

    /// A writer of `file` from its start; `path` names it in messages.
    fn over(file: File, buffer: usize, path: PathBuf) -> SpillWriter {
        SpillWriter {
            out: BufWriter::with_capacity(buffer, file),
            written: 0,
            path,
        }
    }

    /// Where the next record will start, for `for_each_in`.
    pub fn position(&self) -> u64 {
        self.written
    }

    pub fn write(&mut self, t: &SpillTri) -> Result<()> {
        if t.material & FLAGS != 0 {
            bail!("material index {} is out of range", t.material);
        }
        let attr = t.n != [0; 3] || t.curvature != 0.0;
        let uv = t.uv != [[0.0; 2]; 3];
        let colour = t.colour != [WHITE; 3];
        let uv2 = t.uv2 != [[0.0; 2]; 3];
        let flag = |on: bool, bit: u32| if on { bit } else { 0 };
        let rec = Rec {
            p: t.p,
            material: t.material
                | flag(attr, HAS_ATTR)
                | flag(uv, HAS_UV)
                | flag(colour, HAS_COLOUR)
                | flag(uv2, HAS_UV2),
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
        self.written += 40 + 16 * attr as u64 + 24 * (uv as u64 + colour as u64 + uv2 as u64);
        r.with_context(|| format!("{}: writing spill file", self.path.display()))
    }

    /// Flushes and returns the spill, ready to read.
    pub fn finish(self) -> Result<Spill> {
        let err = || format!("{}: writing", self.path.display());
        let file = self
            .out
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(err)?;
        Ok(Spill {
            file,
            path: self.path,
        })
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
}

impl Spill {
    /// A named spill file, as `SpillWriter::create_named` wrote it.
    pub fn open(path: &Path) -> Result<Spill> {
        let file = File::open(path).with_context(|| format!("{}: cannot open", path.display()))?;
        Ok(Spill {
            file,
            path: path.to_path_buf(),
        })
    }
}

/// Calls `f` on every triangle of a spill file, in order.
pub fn for_each(spill: &Spill, f: impl FnMut(&SpillTri) -> Result<()>) -> Result<()> {
    for_each_in(spill, 0, u64::MAX, f)
}

/// Calls `f` on the `count` triangles (or up to the end) from byte `start`, a record start
/// `SpillWriter::position` returned.
pub fn for_each_in(
    spill: &Spill,
    start: u64,
    count: u64,
    mut f: impl FnMut(&SpillTri) -> Result<()>,
) -> Result<()> {
    let path = &spill.path;
    let mut file = &spill.file;
    file.seek(SeekFrom::Start(start))
        .with_context(|| format!("{}: seeking", path.display()))?;
    let mut r = BufReader::with_capacity(1 << 20, file);
    let err = || format!("{}: reading spill", path.display());
    for _ in 0..count {
        if r.fill_buf().with_context(err)?.is_empty() {
            if count == u64::MAX {
                return Ok(());
            }
            bail!("{}: the spill file ends early", path.display());
        }
        let mut rec = Rec::zeroed();
        r.read_exact(bytemuck::bytes_of_mut(&mut rec))
            .with_context(err)?;
        let mut t = SpillTri {
            p: rec.p,
            material: rec.material & !FLAGS,
            ..Default::default()
        };
        if rec.material & HAS_ATTR != 0 {
            let mut a = Attr::zeroed();
            r.read_exact(bytemuck::bytes_of_mut(&mut a))
                .with_context(err)?;
            t.n = a.n;
            t.curvature = a.curvature;
        }
        if rec.material & HAS_UV != 0 {
            r.read_exact(bytemuck::bytes_of_mut(&mut t.uv))
                .with_context(err)?;
        }
        if rec.material & HAS_COLOUR != 0 {
            r.read_exact(bytemuck::bytes_of_mut(&mut t.colour))
                .with_context(err)?;
        }
        if rec.material & HAS_UV2 != 0 {
            r.read_exact(bytemuck::bytes_of_mut(&mut t.uv2))
                .with_context(err)?;
        }
        f(&t)?;
    }
    Ok(())
}

pub fn read_all(spill: &Spill) -> Result<Vec<SpillTri>> {
    let mut out = Vec::new();
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
}
