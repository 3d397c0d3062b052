//! A memory ceiling per fuzz case: a counting global allocator (installed by the binary
//! that wants it, `#[global_allocator] static A: Counting = Counting;`) that ends the
//! process, naming the case, when a case's live heap would pass its ceiling. A declared
//! size that reaches an allocation is caught at the request, before the system allocator
//! would abort on it or the machine would swap.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering::Relaxed};
use std::sync::Mutex;

/// Live heap bytes.
static LIVE: AtomicUsize = AtomicUsize::new(0);
/// Live bytes when the current case began, and the most since.
static BASE: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);
/// The ceiling above `BASE` (0: none).
static CEILING: AtomicU64 = AtomicU64::new(0);
static INSTALLED: AtomicBool = AtomicBool::new(false);
/// What the current case is, for the message.
pub static CASE: Mutex<String> = Mutex::new(String::new());

/// Exit status of a run ended by a case over its ceiling.
pub const OVER_CEILING: i32 = 4;

pub struct Counting;

// SAFETY: every call is forwarded to the system allocator; the counters are atomics.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        admit(layout.size());
        let p = System.alloc(layout);
        if !p.is_null() {
            count(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        admit(layout.size());
        let p = System.alloc_zeroed(layout);
        if !p.is_null() {
            count(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout);
        LIVE.fetch_sub(layout.size(), Relaxed);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        admit(new_size.saturating_sub(layout.size()));
        let p = System.realloc(ptr, layout, new_size);
        if !p.is_null() {
            LIVE.fetch_sub(layout.size(), Relaxed);
            count(new_size);
        }
        p
    }
}

fn count(size: usize) {
    INSTALLED.store(true, Relaxed);
    let now = LIVE.fetch_add(size, Relaxed) + size;
    PEAK.fetch_max(now, Relaxed);
}

/// Ends the process, naming the case, if `more` bytes would take the case past its
/// ceiling. Writes with `libc::write` and leaves with `_exit`: nothing here may allocate.
fn admit(more: usize) {
    let ceiling = CEILING.load(Relaxed) as usize;
    if ceiling == 0 {
        return;
    }
    let over = LIVE.load(Relaxed).saturating_add(more);
    if over.saturating_sub(BASE.load(Relaxed)) <= ceiling {
        return;
    }
    let say = |b: &[u8]| {
        // SAFETY: writes a valid buffer to standard error.
        unsafe { libc::write(2, b.as_ptr().cast(), b.len()) };
    };
    say(b"OVER MEMORY CEILING: case ");
    if let Ok(what) = CASE.try_lock() {
        say(what.as_bytes());
    }
    say(b" asked for more heap than its ceiling\n");
    // SAFETY: ends the process at once, as the hang watchdog does.
    unsafe { libc::_exit(OVER_CEILING) };
}

/// Starts a case: its ceiling counts from the heap live now.
pub fn begin_case(ceiling: u64) {
    let now = LIVE.load(Relaxed);
    BASE.store(now, Relaxed);
    PEAK.store(now, Relaxed);
    CEILING.store(ceiling, Relaxed);
}

/// Ends a case: the most heap it held above its start (None when the counting allocator
/// is not installed), and no ceiling until the next case.
pub fn end_case() -> Option<u64> {
    CEILING.store(0, Relaxed);
    INSTALLED
        .load(Relaxed)
        .then(|| PEAK.load(Relaxed).saturating_sub(BASE.load(Relaxed)) as u64)
}
