//! A glTF buffer's bytes: read into memory (data URIs, side files, decoded meshopt
//! fallbacks), or a GLB's BIN chunk mapped from the file, so that a glb of millions of
//! placements or triangles is not held in memory: `release` lets the kernel drop the
//! mapped pages read so far, and a later read faults them back in from the page cache.

use memmap2::Mmap;
use std::ops::Deref;
use std::sync::Arc;

pub(super) enum Buffer {
    Owned(Vec<u8>),
    Mapped {
        map: Arc<Mmap>,
        at: usize,
        len: usize,
    },
}

impl Deref for Buffer {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Buffer::Owned(v) => v,
            Buffer::Mapped { map, at, len } => &map[*at..*at + *len],
        }
    }
}

impl Buffer {
    /// The bytes, to write into (a mapped buffer is copied first).
    pub(super) fn owned(&mut self) -> &mut Vec<u8> {
        if let Buffer::Mapped { .. } = self {
            *self = Buffer::Owned(self.to_vec());
        }
        match self {
            Buffer::Owned(v) => v,
            Buffer::Mapped { .. } => unreachable!("made owned above"),
        }
    }

    /// Drops this process's resident copies of a mapped buffer's pages.
    pub(super) fn release(&self) {
        let Buffer::Mapped { map, at, len } = self else {
            return;
        };
        // Whole pages: the first and last may hold bytes of the JSON chunk or past the end,
        // which fault back in as well if read again.
        let start = at & !4095;
        let end = (at + len).next_multiple_of(4096).min(map.len());
        #[cfg(unix)]
        // SAFETY: the mapping is read-only and private to this import; after MADV_DONTNEED
        // a read faults the same file bytes back in, so no reader can observe a change.
        unsafe {
            map.unchecked_advise_range(memmap2::UncheckedAdvice::DontNeed, start, end - start)
                .ok();
        }
        #[cfg(not(unix))]
        let _ = (start, end);
    }
}

/// Counts what an import reads and releases the mapped buffers (`Buffer::release`) every
/// `EVERY` items, which bounds what of a large glb stays resident.
#[derive(Default)]
pub(super) struct Releaser {
    since: u64,
}

/// Placements or triangles read between releases (a million placements are 40 MB of
/// columns; a million triangles about as much of vertices and indices).
const EVERY: u64 = 1 << 20;

impl Releaser {
    /// Notes `n` items read from `buffers`.
    pub(super) fn read(&mut self, n: u64, buffers: &[Buffer]) {
        self.since += n;
        if self.since >= EVERY {
            self.since = 0;
            buffers.iter().for_each(Buffer::release);
        }
    }
}
