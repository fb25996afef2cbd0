//! A counting global allocator: wraps the system allocator and counts allocations and
//! reallocations per thread, so a test can prove that a real-time loop allocates nothing after
//! warm-up:
//!
//! ```ignore
//! #[global_allocator]
//! static A: rt_core::alloc_count::CountingAlloc = rt_core::alloc_count::CountingAlloc;
//! let before = AllocCounter::snapshot();
//! run_loop();
//! assert_eq!(AllocCounter::snapshot().since(before).allocs, 0);
//! ```
//!
//! Counters are `thread_local` `Cell`s (const-initialised, no destructor, so reading them
//! inside the allocator cannot itself allocate or recurse); a snapshot therefore sees only the
//! calling thread's allocations. Frees are counted too (not an error in a loop, but a hint).
//!
//! Finding the allocations: [`AllocSites::start`] makes the calling thread capture a backtrace
//! (unresolved, cheap-ish) at each of its allocations, up to a bound; [`AllocSites::take`] stops
//! and returns them, [`AllocSites::report`] groups them by call stack (symbolised then, off the
//! real-time path). A diagnostic only: capturing allocates, guarded against recursion by a
//! thread-local flag; those allocations are not counted (with tracing on, the counters still
//! show the traced code's own allocations).
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

thread_local! {
    static ALLOCS: Cell<u64> = const { Cell::new(0) };
    static REALLOCS: Cell<u64> = const { Cell::new(0) };
    static FREES: Cell<u64> = const { Cell::new(0) };
    static BYTES: Cell<u64> = const { Cell::new(0) };
    /// Capture a backtrace at each allocation of this thread (see [`AllocSites`]).
    static TRACING: Cell<bool> = const { Cell::new(false) };
    /// Set while a capture runs (its own allocations are not captured).
    static IN_TRACE: Cell<bool> = const { Cell::new(false) };
}

/// Captured allocation backtraces (size, stack) of threads that called [`AllocSites::start`].
static SITES: std::sync::Mutex<Vec<(usize, std::backtrace::Backtrace)>> = std::sync::Mutex::new(Vec::new());
/// Most backtraces kept.
const MAX_SITES: usize = 20_000;

fn capture(size: usize) {
    let tracing = TRACING.try_with(Cell::get).unwrap_or(false);
    if !tracing || IN_TRACE.try_with(Cell::get).unwrap_or(true) {
        return;
    }
    let _ = IN_TRACE.try_with(|c| c.set(true));
    let bt = std::backtrace::Backtrace::force_capture();
    if let Ok(mut sites) = SITES.lock() {
        if sites.len() < MAX_SITES {
            sites.push((size, bt));
        }
    }
    let _ = IN_TRACE.try_with(|c| c.set(false));
}

/// Allocation-site capture for the calling thread (a diagnostic; see the module docs).
#[derive(Debug)]
pub struct AllocSites;

impl AllocSites {
    /// Starts capturing the calling thread's allocations.
    pub fn start() {
        let _ = TRACING.try_with(|c| c.set(true));
    }

    /// Stops capturing on the calling thread and returns everything captured so far (by any
    /// thread).
    pub fn take() -> Vec<(usize, std::backtrace::Backtrace)> {
        let _ = TRACING.try_with(|c| c.set(false));
        let _ = IN_TRACE.try_with(|c| c.set(true));
        let out = SITES
            .lock()
            .map(|mut s| std::mem::take(&mut *s))
            .unwrap_or_default();
        let _ = IN_TRACE.try_with(|c| c.set(false));
        out
    }

    /// Groups captured backtraces by their frames (symbolised here), most frequent first:
    /// (count, bytes, stack text). Frames of the allocator and std's backtrace machinery are
    /// left out; `max_frames` frames are kept per stack.
    pub fn report(
        sites: &[(usize, std::backtrace::Backtrace)],
        max_frames: usize,
    ) -> Vec<(u64, u64, String)> {
        let mut groups: std::collections::HashMap<String, (u64, u64)> = std::collections::HashMap::new();
        for (size, bt) in sites {
            let text = bt.to_string();
            let frames: Vec<&str> = text
                .lines()
                .map(str::trim)
                .filter(|l| !l.starts_with("at "))
                .filter(|l| {
                    !(l.contains("alloc_count")
                        || l.contains("backtrace")
                        || l.contains("__rust_")
                        || l.contains("alloc::alloc::"))
                })
                .take(max_frames)
                .collect();
            let key = frames.join("\n");
            let e = groups.entry(key).or_insert((0, 0));
            e.0 += 1;
            e.1 += *size as u64;
        }
        let mut out: Vec<(u64, u64, String)> = groups.into_iter().map(|(k, (n, b))| (n, b, k)).collect();
        out.sort_by(|a, b| b.0.cmp(&a.0).then(b.1.cmp(&a.1)));
        out
    }
}

fn bump(c: &'static std::thread::LocalKey<Cell<u64>>, n: u64) {
    // The backtrace capture's own allocations are the diagnostic's, not the traced code's.
    if IN_TRACE.try_with(Cell::get).unwrap_or(false) {
        return;
    }
    // try_with: during thread teardown the slot may be gone; then the event is not counted.
    let _ = c.try_with(|c| c.set(c.get().wrapping_add(n)));
}

/// The system allocator with per-thread counting. Install with `#[global_allocator]`.
#[derive(Debug, Clone, Copy, Default)]
pub struct CountingAlloc;

// SAFETY: every method forwards to `System` with the caller's arguments unchanged, so the
// GlobalAlloc contract is exactly System's; the counting touches only const thread-locals
// (no allocation, no panic). Only while a thread traces (`AllocSites`) does `capture` allocate,
// re-entering this allocator with the `IN_TRACE` guard set (so it does not recurse further and
// takes no lock twice).
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS, 1);
        bump(&BYTES, layout.size() as u64);
        capture(layout.size());
        // SAFETY: forwarded contract (see the impl).
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS, 1);
        bump(&BYTES, layout.size() as u64);
        capture(layout.size());
        // SAFETY: forwarded contract (see the impl).
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        bump(&FREES, 1);
        // SAFETY: forwarded contract: `ptr` came from this allocator (i.e. System) with `layout`.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        bump(&REALLOCS, 1);
        bump(&BYTES, new_size as u64);
        capture(new_size);
        // SAFETY: forwarded contract (see the impl).
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

/// The calling thread's allocation counters at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct AllocCounter {
    pub allocs: u64,
    pub reallocs: u64,
    pub frees: u64,
    pub bytes: u64,
}

impl AllocCounter {
    /// The calling thread's counters (all 0 unless [`CountingAlloc`] is the global allocator).
    pub fn snapshot() -> AllocCounter {
        let get = |c: &'static std::thread::LocalKey<Cell<u64>>| c.try_with(Cell::get).unwrap_or(0);
        AllocCounter {
            allocs: get(&ALLOCS),
            reallocs: get(&REALLOCS),
            frees: get(&FREES),
            bytes: get(&BYTES),
        }
    }

    /// Events between `earlier` and `self`.
    pub fn since(self, earlier: AllocCounter) -> AllocCounter {
        AllocCounter {
            allocs: self.allocs.wrapping_sub(earlier.allocs),
            reallocs: self.reallocs.wrapping_sub(earlier.reallocs),
            frees: self.frees.wrapping_sub(earlier.frees),
            bytes: self.bytes.wrapping_sub(earlier.bytes),
        }
    }

    /// Allocations plus reallocations (what "allocates nothing" must keep at 0).
    pub fn allocations(self) -> u64 {
        self.allocs + self.reallocs
    }
}
