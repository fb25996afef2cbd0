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
#![allow(unsafe_code)]

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

thread_local! {
    static ALLOCS: Cell<u64> = const { Cell::new(0) };
    static REALLOCS: Cell<u64> = const { Cell::new(0) };
    static FREES: Cell<u64> = const { Cell::new(0) };
    static BYTES: Cell<u64> = const { Cell::new(0) };
}

fn bump(c: &'static std::thread::LocalKey<Cell<u64>>, n: u64) {
    // try_with: during thread teardown the slot may be gone; then the event is not counted.
    let _ = c.try_with(|c| c.set(c.get().wrapping_add(n)));
}

/// The system allocator with per-thread counting. Install with `#[global_allocator]`.
#[derive(Debug, Clone, Copy, Default)]
pub struct CountingAlloc;

// SAFETY: every method forwards to `System` with the caller's arguments unchanged, so the
// GlobalAlloc contract is exactly System's; the counting touches only const thread-locals
// (no allocation, no panic).
unsafe impl GlobalAlloc for CountingAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS, 1);
        bump(&BYTES, layout.size() as u64);
        // SAFETY: forwarded contract (see the impl).
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        bump(&ALLOCS, 1);
        bump(&BYTES, layout.size() as u64);
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
