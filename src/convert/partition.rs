//! Stage 2, partition: when the triangles exceed one chunk's budget, a Morton histogram of
//! their centroids splits space into chunks that fit, and a second pass over the spill file
//! distributes the triangles to one file per chunk.

use super::spill::{self, Spill, SpillWriter};
use super::stages;
use crate::progress;
use anyhow::Result;
use std::path::Path;

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
pub fn partition(
    spilled: Spill,
    total: u64,
    [lo, hi]: [[f32; 3]; 2],
    cap: u64,
    dir: &Path,
    named: Option<&Path>,
    show: bool,
) -> Result<Vec<Spill>> {
    let create = |k: u32, buffer: usize| match named {
        Some(work) => SpillWriter::create_named(&stages::chunk_file(work, k), buffer),
        None => SpillWriter::create(dir, buffer),
    };
    if total <= cap {
        return match named {
            None => Ok(vec![spilled]),
            Some(_) => {
                let mut out = create(0, 1 << 20)?;
                spill::for_each(&spilled, |t| out.write(t))?;
                Ok(vec![out.finish()?])
            }
        };
    }
    let mut hist = vec![0u64; 1 << (3 * MORTON_BITS)];
    spill::for_each(&spilled, |t| {
        hist[morton(t.centroid(), lo, hi) as usize] += 1;
        Ok(())
    })?;
    let (chunk, n) = chunk_of_bins(&hist, cap);
    drop(hist);
    // The chunks' write buffers share `BUFFERS` (part of the converter's fixed memory):
    // at a small budget there are many chunks, and 256 KiB each would outgrow it.
    let buffer = (BUFFERS / n.max(1) as usize).clamp(16 << 10, 256 << 10);
    let mut outs = (0..n)
        .map(|k| create(k, buffer))
        .collect::<Result<Vec<_>>>()?;
    let bar = progress::bar(show, total, "partitioning");
    let mut done = 0u64;
    spill::for_each(&spilled, |t| {
        outs[chunk[morton(t.centroid(), lo, hi) as usize] as usize].write(t)?;
        done += 1;
        if done.is_multiple_of(65536) {
            bar.set_position(done);
        }
        Ok(())
    })?;
    bar.finish_and_clear();
    drop(spilled);
    outs.into_iter().map(SpillWriter::finish).collect()
}
