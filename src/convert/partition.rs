//! Stage 2, partition: when the triangles exceed one chunk's budget, a Morton histogram of
//! their centroids splits space into chunks that fit, and a second pass over the spill file
//! distributes the triangles to one file per chunk.

use super::spill::{self, Spill, SpillWriter};
use super::stages;
use crate::progress;
use anyhow::Result;
use rayon::prelude::*;
use std::fs::File;
use std::path::{Path, PathBuf};

const MORTON_BITS: u32 = 7;

/// Bytes all chunk files' write buffers take together while partitioning.
const BUFFERS: usize = 16 << 20;

/// 21-bit Morton code of a point in the box (7 bits an axis): the histogram bin.
fn morton(p: [f32; 3], lo: [f32; 3], hi: [f32; 3]) -> u32 {
    let cells = (1u32 << MORTON_BITS) as f32;
    let q = [0, 1, 2].map(|a| {
        let e = hi[a] - lo[a];
        let t = if e > 0.0 { (p[a] - lo[a]) / e } else { 0.0 };
        ((t * cells) as u32).min((1 << MORTON_BITS) - 1)
    });
    super::morton::code(q) as u32
}

/// Consecutive Morton-bin ranges, each holding at most `cap` triangles (unless one bin alone
/// holds more). Returns the chunk index of each bin.
fn chunk_of_bins(hist: &[u64], cap: u64) -> (Vec<u32>, u32) {
    let mut chunk = vec![0u32; hist.len()];
    let (mut cur, mut fill) = (0u32, 0u64);
    for (b, &h) in hist.iter().enumerate() {
        if fill > 0 && fill + h > cap {
            cur += 1;
            fill = 0;
        }
        fill += h;
        chunk[b] = cur;
    }
    (chunk, cur + 1)
}

/// The chunk files of `total` triangles in `spilled` (centroids inside `lo..hi`), each at
/// most `cap` triangles unless one Morton bin alone holds more. They are unnamed files in
/// `dir`, or with `named` the work directory's chunk files (`stages::chunk_file`).
///
/// Both passes run on `PARTS` ranges of the spill at once. When every record has one
/// length, each range's triangles go to their own place in each chunk file (after those of
/// the ranges before it), so the files hold the triangles in spill order as one pass
/// writes them; otherwise the second pass runs alone.
pub fn partition(
    spilled: Spill,
    total: u64,
    [lo, hi]: [[f32; 3]; 2],
    cap: u64,
    dir: &Path,
    named: Option<&Path>,
    show: bool,
) -> Result<Vec<Spill>> {
    let name = |k: u32| named.map(|work| stages::chunk_file(work, k));
    if total <= cap {
        return match named {
            None => Ok(vec![spilled]),
            Some(_) => {
                let file = spill::create_file(dir, name(0).as_deref())?;
                let mut out = SpillWriter::over(file, 1 << 20, name(0).unwrap_or_default());
                spill::for_each(&spilled, |t| out.write(t))?;
                Ok(vec![out.finish()?])
            }
        };
    }
    let parts = spilled.parts(PARTS);
    let counted = parts
        .par_iter()
        .map(|&(start, count)| histogram(&spilled, start, count, [lo, hi]))
        .collect::<Result<Vec<_>>>()?;
    let mut hist = vec![0u64; 1 << (3 * MORTON_BITS)];
    for part in &counted {
        hist.iter_mut().zip(part).for_each(|(h, p)| *h += p);
    }
    let (chunk, n) = chunk_of_bins(&hist, cap);
    drop(hist);
    let files = (0..n)
        .map(|k| spill::create_file(dir, name(k).as_deref()))
        .collect::<Result<Vec<_>>>()?;
    let paths: Vec<PathBuf> = (0..n)
        .map(|k| name(k).unwrap_or_else(|| dir.join("(chunk file)")))
        .collect();
    let bar = progress::bar(show, total, "partitioning");
    let split = Split {
        spilled: &spilled,
        bins: &chunk,
        box_: [lo, hi],
        files: &files,
        paths: &paths,
        bar: &bar,
    };
    let counts = match spilled.record_len() {
        Some(len) => {
            // Each range's share of each chunk, and where it starts in the chunk's file.
            let shares: Vec<Vec<u64>> = counted
                .iter()
                .map(|part| {
                    let mut share = vec![0u64; n as usize];
                    part.iter()
                        .zip(&chunk)
                        .for_each(|(h, &c)| share[c as usize] += h);
                    share
                })
                .collect();
            drop(counted);
            split.in_parts(&parts, &shares, len)?
        }
        None => {
            drop(counted);
            split.in_one()?
        }
    };
    bar.finish_and_clear();
    Ok(files
        .into_iter()
        .zip(&paths)
        .zip(counts)
        .map(|((f, p), c)| Spill::written(f, p, c))
        .collect())
}

/// Ranges of the spill read at once in each pass.
const PARTS: usize = 2;

/// The Morton histogram of the triangles of one range of a spill.
fn histogram(spilled: &Spill, start: u64, count: u64, [lo, hi]: [[f32; 3]; 2]) -> Result<Vec<u64>> {
    let mut hist = vec![0u64; 1 << (3 * MORTON_BITS)];
    spill::for_each_in(spilled, start, count, |t| {
        hist[morton(t.centroid(), lo, hi) as usize] += 1;
        Ok(())
    })?;
    Ok(hist)
}

/// The second pass: the spill's triangles written to their chunks' files.
struct Split<'a> {
    spilled: &'a Spill,
    /// The chunk of each Morton bin.
    bins: &'a [u32],
    box_: [[f32; 3]; 2],
    files: &'a [File],
    paths: &'a [PathBuf],
    bar: &'a indicatif::ProgressBar,
}

impl Split<'_> {
    /// Writes the triangles of `start..start + count` to the chunk files, each chunk's
    /// from `offsets[chunk]` on; returns how many went to each chunk.
    fn range(
        &self,
        (start, count): (u64, u64),
        offsets: &[u64],
        buffers: usize,
    ) -> Result<Vec<u64>> {
        // The chunks' write buffers share `BUFFERS` (part of the converter's fixed memory):
        // at a small budget there are many chunks, and 256 KiB each would outgrow it.
        let buffer = (buffers / self.files.len().max(1)).clamp(16 << 10, 256 << 10);
        let mut outs: Vec<_> = self
            .files
            .iter()
            .zip(offsets)
            .zip(self.paths)
            .map(|((f, &at), path)| SpillWriter::at(f, at, buffer, path))
            .collect();
        let [lo, hi] = self.box_;
        let mut done = 0u64;
        spill::for_each_in(self.spilled, start, count, |t| {
            outs[self.bins[morton(t.centroid(), lo, hi) as usize] as usize].write(t)?;
            done += 1;
            if done.is_multiple_of(65536) {
                self.bar.inc(65536);
            }
            Ok(())
        })?;
        let counts = outs.iter().map(SpillWriter::count).collect();
        outs.into_iter().try_for_each(SpillWriter::flush)?;
        Ok(counts)
    }

    /// The second pass over the whole spill at once.
    fn in_one(&self) -> Result<Vec<u64>> {
        self.range((0, u64::MAX), &vec![0; self.files.len()], BUFFERS)
    }

    /// The second pass over `parts` at once, part `p`'s records of chunk `k` starting after
    /// those of the parts before it (`shares[p][k]` records of `len` bytes each).
    fn in_parts(&self, parts: &[(u64, u64)], shares: &[Vec<u64>], len: u64) -> Result<Vec<u64>> {
        let mut offsets = vec![0u64; self.files.len()];
        let starts: Vec<Vec<u64>> = shares
            .iter()
            .map(|share| {
                let at = offsets.clone();
                offsets
                    .iter_mut()
                    .zip(share)
                    .for_each(|(o, s)| *o += s * len);
                at
            })
            .collect();
        let counts = parts
            .par_iter()
            .zip(&starts)
            .map(|(&part, at)| self.range(part, at, BUFFERS / parts.len()))
            .collect::<Result<Vec<_>>>()?;
        Ok((0..self.files.len())
            .map(|k| counts.iter().map(|c| c[k]).sum())
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::convert::spill::MARK_TRIANGLES;
    use crate::import::SpillTri;

    /// `n` triangles along x, triangle `i` at x = i (its number, exact in f32); with
    /// `mixed`, every third carries a curvature, so records differ in length.
    fn spill_of(dir: &Path, n: u32, mixed: bool) -> Spill {
        let mut w = SpillWriter::create(dir, 1 << 20).unwrap();
        for i in 0..n {
            let x = i as f32;
            let y = (i.wrapping_mul(2654435761) % 1000) as f32 * 1e-3;
            w.write(&SpillTri {
                p: [[x, y, 0.0], [x + 0.5, y, 0.0], [x, y + 0.5, 0.5]],
                curvature: if mixed && i % 3 == 0 { 1.0 } else { 0.0 },
                ..Default::default()
            })
            .unwrap();
        }
        w.finish().unwrap()
    }

    /// Every triangle lands in exactly one chunk, and each chunk holds at most `cap`
    /// triangles, in spill order.
    fn check(files: &[Spill], n: u32, cap: u64) {
        let mut seen = vec![false; n as usize];
        for f in files {
            let tris = spill::read_all(f).unwrap();
            assert!(tris.len() as u64 <= cap, "{} > {cap}", tris.len());
            let xs: Vec<f32> = tris.iter().map(|t| t.p[0][0]).collect();
            assert!(xs.windows(2).all(|w| w[0] < w[1]), "spill order kept");
            for &x in &xs {
                assert!(!std::mem::replace(&mut seen[x as usize], true));
            }
        }
        assert!(seen.iter().all(|&s| s), "a triangle was lost");
    }

    #[test]
    fn ranges_partitioned_at_once_write_what_one_pass_writes() {
        let dir = tempfile::tempdir().unwrap();
        let n = (MARK_TRIANGLES + MARK_TRIANGLES / 2) as u32;
        let bounds = [[0.0, 0.0, 0.0], [n as f32, 1.0, 1.0]];
        let cap = n as u64 / 5;
        let mut bytes = Vec::new();
        for mixed in [false, true] {
            let spilled = spill_of(dir.path(), n, mixed);
            assert_eq!(spilled.parts(PARTS).len(), 2);
            let files = partition(spilled, n as u64, bounds, cap, dir.path(), None, false).unwrap();
            assert!(files.len() >= 5);
            check(&files, n, cap);
            // With uniform records the ranges are split at once; with mixed ones in one
            // pass: the chunks' triangles agree but for the curvatures.
            let xs: Vec<Vec<u32>> = files
                .iter()
                .map(|f| {
                    spill::read_all(f)
                        .unwrap()
                        .iter()
                        .map(|t| t.p[0][0] as u32)
                        .collect()
                })
                .collect();
            bytes.push(xs);
        }
        assert_eq!(bytes[0], bytes[1]);
    }
}
