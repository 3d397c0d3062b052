//! Fixed-size records streamed to disk, and sorted there: what the converter keeps of
//! millions of instance placements, so that memory holds a bounded run of them whatever
//! their number. Files are unnamed, as the triangle spills are (`spill`).

use anyhow::{Context, Result};
use bytemuck::Pod;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

/// Records being written to an unnamed file.
pub struct RecordWriter<T> {
    out: BufWriter<File>,
    count: u64,
    path: PathBuf,
    _t: PhantomData<T>,
}

/// A finished file of records.
pub struct Records<T> {
    file: File,
    count: u64,
    path: PathBuf,
    _t: PhantomData<T>,
}

const BUFFER: usize = 256 << 10;

impl<T: Pod> RecordWriter<T> {
    /// An unnamed file of records in `dir`.
    pub fn create(dir: &Path) -> Result<Self> {
        Ok(RecordWriter {
            out: BufWriter::with_capacity(BUFFER, super::spill::unnamed(dir)?),
            count: 0,
            path: dir.join("(spill file)"),
            _t: PhantomData,
        })
    }

    pub fn push(&mut self, r: &T) -> Result<()> {
        self.count += 1;
        self.out
            .write_all(bytemuck::bytes_of(r))
            .with_context(|| format!("{}: writing", self.path.display()))
    }

    pub fn len(&self) -> u64 {
        self.count
    }

    pub fn finish(self) -> Result<Records<T>> {
        let file = self
            .out
            .into_inner()
            .map_err(|e| e.into_error())
            .with_context(|| format!("{}: writing", self.path.display()))?;
        Ok(Records {
            file,
            count: self.count,
            path: self.path,
            _t: PhantomData,
        })
    }
}

impl<T: Pod> Records<T> {
    pub fn len(&self) -> u64 {
        self.count
    }

    /// Calls `f` on every record, in order.
    pub fn for_each(&mut self, mut f: impl FnMut(T) -> Result<()>) -> Result<()> {
        let mut it = self.iter()?;
        while let Some(r) = it.next_record()? {
            f(r)?;
        }
        Ok(())
    }

    /// A reader from the first record.
    fn iter(&mut self) -> Result<RecordReader<'_, T>> {
        self.file
            .seek(SeekFrom::Start(0))
            .with_context(|| format!("{}: reading", self.path.display()))?;
        Ok(RecordReader {
            input: BufReader::with_capacity(BUFFER, &self.file),
            left: self.count,
            path: &self.path,
            _t: PhantomData,
        })
    }
}

struct RecordReader<'a, T> {
    input: BufReader<&'a File>,
    left: u64,
    path: &'a Path,
    _t: PhantomData<T>,
}

impl<T: Pod> RecordReader<'_, T> {
    fn next_record(&mut self) -> Result<Option<T>> {
        if self.left == 0 {
            return Ok(None);
        }
        self.left -= 1;
        let mut r = T::zeroed();
        self.input
            .read_exact(bytemuck::bytes_of_mut(&mut r))
            .with_context(|| format!("{}: reading", self.path.display()))?;
        Ok(Some(r))
    }
}

/// Most runs merged at once (each holds a file open and a read buffer).
const MAX_RUNS: u64 = 256;

/// Calls `f` on `records` in ascending order of `key` (ties in input order): runs of at
/// most `run` records (more where that would make over `MAX_RUNS` runs) are sorted in
/// memory and spilled to `dir`, then merged, so memory holds one run and a read buffer
/// per run.
pub fn for_each_sorted<T: Pod, K: Ord + Copy>(
    records: &mut Records<T>,
    key: impl Fn(&T) -> K,
    run: usize,
    dir: &Path,
    mut f: impl FnMut(T) -> Result<()>,
) -> Result<()> {
    let run = run.max(records.len().div_ceil(MAX_RUNS) as usize).max(1);
    let mut runs = Vec::new();
    let mut buf: Vec<T> = Vec::with_capacity(run.min(records.len() as usize));
    let spill_run = |buf: &mut Vec<T>, runs: &mut Vec<Records<T>>| -> Result<()> {
        buf.sort_by_key(&key);
        let mut w = RecordWriter::create(dir)?;
        for r in buf.drain(..) {
            w.push(&r)?;
        }
        runs.push(w.finish()?);
        Ok(())
    };
    records.for_each(|r| {
        buf.push(r);
        match buf.len() == run {
            true => spill_run(&mut buf, &mut runs),
            false => Ok(()),
        }
    })?;
    if runs.is_empty() {
        // One run: no need to go to disk.
        buf.sort_by_key(&key);
        return buf.into_iter().try_for_each(f);
    }
    if !buf.is_empty() {
        spill_run(&mut buf, &mut runs)?;
    }
    drop(buf);
    let mut readers = runs
        .iter_mut()
        .map(|r| r.iter())
        .collect::<Result<Vec<_>>>()?;
    // The smallest key on top; ties to the earlier run, which holds the earlier records.
    let mut heads = BinaryHeap::new();
    for (i, r) in readers.iter_mut().enumerate() {
        if let Some(x) = r.next_record()? {
            heads.push(std::cmp::Reverse((key(&x), i, Head(x))));
        }
    }
    while let Some(std::cmp::Reverse((_, i, Head(x)))) = heads.pop() {
        if let Some(y) = readers[i].next_record()? {
            heads.push(std::cmp::Reverse((key(&y), i, Head(y))));
        }
        f(x)?;
    }
    Ok(())
}

/// A record in the merge heap, ordered by its key and run alone.
struct Head<T>(T);

impl<T> PartialEq for Head<T> {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}
impl<T> Eq for Head<T> {}
impl<T> PartialOrd for Head<T> {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl<T> Ord for Head<T> {
    fn cmp(&self, _: &Self) -> std::cmp::Ordering {
        std::cmp::Ordering::Equal
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sorting through spilled runs gives what a stable in-memory sort gives, for run
    /// lengths that split the input unevenly, one run, and runs of one record.
    #[test]
    fn spilled_runs_merge_to_a_stable_sort() {
        let dir = std::env::temp_dir();
        let mut rng = crate::test_rng::TestRng::new(7);
        let input: Vec<[u32; 2]> = (0..10_000u32)
            .map(|i| [(rng.f32() * 97.0) as u32, i])
            .collect();
        let mut want = input.clone();
        want.sort_by_key(|r| r[0]);
        for run in [1, 3, 1000, 4096, 20_000] {
            // Runs of 1 and 3 are widened to `MAX_RUNS` runs.
            let mut w = RecordWriter::create(&dir).unwrap();
            for r in &input {
                w.push(r).unwrap();
            }
            let mut records = w.finish().unwrap();
            let mut got = Vec::new();
            for_each_sorted(
                &mut records,
                |r| r[0],
                run,
                &dir,
                |r| {
                    got.push(r);
                    Ok(())
                },
            )
            .unwrap();
            assert_eq!(got, want, "runs of {run}");
        }
    }
}
