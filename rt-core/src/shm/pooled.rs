//! An iceoryx2 service variant whose loans do not touch the heap in steady state.
//!
//! # Why
//!
//! iceoryx2 0.10 wraps every loaned sample's bookkeeping (`ChunkMutInnerSharedState`: the
//! chunk offset, its pointer and a handle on the publisher's state) in the service's
//! `ArcThreadSafetyPolicy`. For `ipc::Service` that is `SingleThreaded<T>`, an `Rc<T>`, so
//! **each `Publisher::loan`/`loan_uninit`/`send_copy` makes one heap allocation** (and frees it
//! when the sample is sent). The payload itself is in shared memory; only this small
//! reference-counted state is on the heap. No iceoryx2 setting avoids it (the thread-safe
//! variants use an `Arc` the same way).
//!
//! # How
//!
//! [`Ipc`] is `ipc::Service` with one type changed: its `ArcThreadSafetyPolicy` is [`PooledRc`],
//! a single-threaded reference-counted pointer like `Rc` whose blocks come from a small free
//! list of the calling thread (one list per block layout, [`POOL_CLASSES`] layouts, at most
//! [`POOL_BLOCKS`] blocks kept per layout). The first loans allocate from the global allocator
//! as before (warm-up, counted by `alloc_count`); a freed block goes back to its thread's list
//! and the next loan takes it from there, so a publisher that loans, sends and loans again
//! reuses the same one or two blocks forever and never calls the allocator.
//!
//! Everything in shared memory (segments, connections, events, monitoring, static and dynamic
//! configs) uses exactly `ipc::Service`'s types, so an [`Ipc`] port talks to `ipc::Service`
//! ports of other processes (or threads) and vice versa; the policy is a process-local detail.
//! Like `SingleThreaded`, a [`PooledRc`] is neither `Send` nor `Sync`: ports stay on the thread
//! that created them.
#![allow(unsafe_code)]

use core::fmt::Debug;
use core::marker::PhantomData;
use core::ops::Deref;
use core::ptr::NonNull;
use std::alloc::Layout;
use std::cell::{Cell, RefCell};

use iceoryx2::prelude::ZeroCopySend;
use iceoryx2_bb_elementary_traits::testing::abandonable::Abandonable;
use iceoryx2_cal::arc_sync_policy::{ArcSyncPolicy, ArcSyncPolicyCreationError, LockGuard};
use iceoryx2_cal::shm_allocator::bump_allocator::BumpAllocator;
use iceoryx2_cal::shm_allocator::pool_allocator::PoolAllocator;
use iceoryx2_cal::{
    bag, dynamic_storage, event, hash, monitoring, reactor, resizable_shared_memory, serialize,
    shared_memory, static_storage, zero_copy_connection,
};

/// `ipc::Service` whose per-loan bookkeeping comes from a per-thread pool (see the module
/// docs). Interoperates with `iceoryx2::prelude::ipc::Service` ports.
#[derive(Debug, Clone)]
pub struct Ipc {}

impl iceoryx2::service::Service for Ipc {
    type StaticStorage = static_storage::recommended::Ipc;
    type ConfigSerializer = serialize::recommended::Recommended;
    type PersistentDynamicStorage<T: Debug + Send + Sync + ZeroCopySend + 'static> =
        dynamic_storage::recommended::PersistentIpc<T>;
    type Bag = bag::recommended::Recommended;
    type DynamicStorage<T: Debug + Send + Sync + ZeroCopySend + 'static> =
        dynamic_storage::recommended::Ipc<T>;
    type ServiceNameHasher = hash::recommended::Recommended;
    type SharedMemory = shared_memory::recommended::Ipc<PoolAllocator>;
    type ResizableSharedMemory = resizable_shared_memory::recommended::Ipc<PoolAllocator>;
    type Connection = zero_copy_connection::recommended::Ipc;
    type Event = event::recommended::Ipc;
    type Monitoring = monitoring::recommended::Ipc;
    type Reactor = reactor::recommended::Ipc;
    type ArcThreadSafetyPolicy<T: Send + Debug + Abandonable> = PooledRc<T>;
    type BlackboardMgmt<KeyType: Send + Sync + Debug + ZeroCopySend + 'static> =
        dynamic_storage::recommended::Ipc<KeyType>;
    type BlackboardPayload = shared_memory::recommended::Ipc<BumpAllocator>;
    type UniqueId = iceoryx2::unique_id_generator::unique_system_id::UniqueSystemId;
}

impl iceoryx2::service::internal::ServiceInternal<Ipc> for Ipc {}

/// Block layouts (size, alignment) a thread's pool keeps apart.
pub const POOL_CLASSES: usize = 16;
/// Free blocks kept per layout; more are returned to the global allocator.
pub const POOL_BLOCKS: usize = 64;

/// One layout's free list: an intrusive singly linked list through the free blocks (each free
/// block's first word points to the next), so pushing and popping never allocate.
#[derive(Clone, Copy)]
struct Class {
    /// `size == 0`: unused.
    size: usize,
    align: usize,
    head: *mut u8,
    len: usize,
}

const UNUSED: Class = Class {
    size: 0,
    align: 0,
    head: core::ptr::null_mut(),
    len: 0,
};

struct Pool {
    classes: [Class; POOL_CLASSES],
}

impl Drop for Pool {
    fn drop(&mut self) {
        for c in &mut self.classes {
            while let Some(block) = pop(c) {
                // SAFETY: every block in a class was allocated by `std::alloc::alloc` with the
                // class's layout (`take`/`give` only file blocks under their own layout).
                unsafe { std::alloc::dealloc(block, Layout::from_size_align_unchecked(c.size, c.align)) };
            }
        }
    }
}

thread_local! {
    static POOL: RefCell<Pool> = const { RefCell::new(Pool { classes: [UNUSED; POOL_CLASSES] }) };
}

fn pop(c: &mut Class) -> Option<*mut u8> {
    if c.head.is_null() {
        return None;
    }
    let block = c.head;
    // SAFETY: a non-null head is a free block of at least one pointer's size and alignment
    // (`can_pool`), whose first word `push` wrote.
    c.head = unsafe { block.cast::<*mut u8>().read() };
    c.len -= 1;
    Some(block)
}

/// Blocks must hold the free-list link.
fn can_pool(layout: Layout) -> bool {
    layout.size() >= size_of::<*mut u8>() && layout.align() >= align_of::<*mut u8>()
}

/// A free block of `layout` from the calling thread's pool, or from the global allocator.
fn take(layout: Layout) -> Option<NonNull<u8>> {
    let pooled = POOL
        .try_with(|p| {
            let mut p = p.try_borrow_mut().ok()?;
            let c = p
                .classes
                .iter_mut()
                .find(|c| c.size == layout.size() && c.align == layout.align())?;
            pop(c)
        })
        .ok()
        .flatten();
    match pooled {
        Some(b) => NonNull::new(b),
        // SAFETY: `layout` has a non-zero size (`can_pool` is checked by the caller).
        None => NonNull::new(unsafe { std::alloc::alloc(layout) }),
    }
}

/// Returns a block of `layout` (from [`take`]) to the calling thread's pool, or to the global
/// allocator when the pool is full or gone (thread teardown).
///
/// # Safety
/// `block` came from [`take`] with the same `layout`, holds no live value, and is not used again.
unsafe fn give(block: NonNull<u8>, layout: Layout) {
    let kept = POOL
        .try_with(|p| {
            let Ok(mut p) = p.try_borrow_mut() else {
                return false;
            };
            let slot = p
                .classes
                .iter()
                .position(|c| c.size == layout.size() && c.align == layout.align())
                .or_else(|| p.classes.iter().position(|c| c.size == 0));
            let Some(c) = slot.and_then(|i| p.classes.get_mut(i)) else {
                return false;
            };
            if c.len >= POOL_BLOCKS {
                return false;
            }
            c.size = layout.size();
            c.align = layout.align();
            // SAFETY: the block is free, at least a pointer in size and alignment (`can_pool`).
            unsafe { block.as_ptr().cast::<*mut u8>().write(c.head) };
            c.head = block.as_ptr();
            c.len += 1;
            true
        })
        .unwrap_or(false);
    if !kept {
        // SAFETY: the caller guarantees `block` was allocated with `layout` (by `take`, i.e.
        // `std::alloc::alloc`, or a pool block that came from it).
        unsafe { std::alloc::dealloc(block.as_ptr(), layout) };
    }
}

struct Inner<T> {
    count: Cell<usize>,
    value: T,
}

/// A single-threaded reference-counted pointer (like `Rc`) whose block comes from the calling
/// thread's pool; iceoryx2's `ArcThreadSafetyPolicy` of [`Ipc`].
pub struct PooledRc<T: Send + Debug + Abandonable> {
    ptr: NonNull<Inner<T>>,
    /// Owns an `Inner<T>`; `NonNull` also makes the type `!Send + !Sync` (the count is a `Cell`).
    _owns: PhantomData<Inner<T>>,
}

impl<T: Send + Debug + Abandonable> PooledRc<T> {
    fn inner(&self) -> &Inner<T> {
        // SAFETY: `ptr` points to an initialised `Inner<T>` that lives while any clone (this one
        // included) does.
        unsafe { self.ptr.as_ref() }
    }

    /// How many pointers share the value.
    pub fn count(&self) -> usize {
        self.inner().count.get()
    }
}

impl<T: Send + Debug + Abandonable> Debug for PooledRc<T> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("PooledRc")
            .field("value", &self.inner().value)
            .finish()
    }
}

impl<T: Send + Debug + Abandonable> Clone for PooledRc<T> {
    fn clone(&self) -> Self {
        let c = &self.inner().count;
        c.set(c.get() + 1);
        PooledRc {
            ptr: self.ptr,
            _owns: PhantomData,
        }
    }
}

impl<T: Send + Debug + Abandonable> Drop for PooledRc<T> {
    fn drop(&mut self) {
        let c = &self.inner().count;
        let n = c.get() - 1;
        c.set(n);
        if n == 0 {
            // SAFETY: the last pointer: nobody else can reach the value. It is dropped first (its
            // own drop may release other pooled blocks; no pool borrow is held here), then its
            // block goes back, allocated by `take` with this same layout.
            unsafe {
                core::ptr::drop_in_place(&raw mut (*self.ptr.as_ptr()).value);
                give(self.ptr.cast(), Layout::new::<Inner<T>>());
            }
        }
    }
}

impl<T: Send + Debug + Abandonable> Abandonable for PooledRc<T> {
    unsafe fn abandon_in_place(this: NonNull<Self>) {
        // As iceoryx2's `SingleThreaded`: the last pointer abandons the value (and leaks its
        // block), any other pointer is simply dropped.
        // SAFETY: the caller hands over a valid `PooledRc` it will not use again.
        unsafe {
            let ptr = this.as_ref().ptr;
            if (*ptr.as_ptr()).count.get() == 1 {
                T::abandon_in_place(NonNull::new_unchecked(&raw mut (*ptr.as_ptr()).value));
            } else {
                core::ptr::drop_in_place(this.as_ptr());
            }
        }
    }
}

/// Access to a [`PooledRc`]'s value (single-threaded: no lock to take).
#[derive(Debug)]
pub struct Guard<'parent, T> {
    value: &'parent T,
}

impl<T> Deref for Guard<'_, T> {
    type Target = T;
    fn deref(&self) -> &T {
        self.value
    }
}

impl<'parent, T: Send + Debug + Abandonable> LockGuard<'parent, T> for Guard<'parent, T> {}

impl<T: Send + Debug + Abandonable> ArcSyncPolicy<T> for PooledRc<T> {
    type LockGuard<'parent>
        = Guard<'parent, T>
    where
        Self: 'parent,
        T: 'parent;

    fn new(value: T) -> Result<Self, ArcSyncPolicyCreationError> {
        let layout = Layout::new::<Inner<T>>();
        // `Inner` starts with a `usize`: always at least a pointer in size and alignment.
        if !can_pool(layout) {
            return Err(ArcSyncPolicyCreationError::InternalFailure);
        }
        let block = take(layout).ok_or(ArcSyncPolicyCreationError::InsufficientResources)?;
        let ptr = block.cast::<Inner<T>>();
        // SAFETY: `block` is a free block with `Inner<T>`'s layout.
        unsafe {
            ptr.as_ptr().write(Inner {
                count: Cell::new(1),
                value,
            })
        };
        Ok(PooledRc {
            ptr,
            _owns: PhantomData,
        })
    }

    fn lock(&self) -> Guard<'_, T> {
        Guard {
            value: &self.inner().value,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::rc::Rc;

    /// Counts its drops and abandons.
    #[derive(Debug)]
    struct Probe {
        drops: Rc<Cell<u32>>,
        abandons: Rc<Cell<u32>>,
        _nested: Option<PooledRc<Leaf>>,
    }
    // SAFETY (test only): never sent to another thread; `ArcSyncPolicy` asks for `Send`.
    unsafe impl Send for Probe {}

    impl Drop for Probe {
        fn drop(&mut self) {
            self.drops.set(self.drops.get() + 1);
        }
    }

    impl Abandonable for Probe {
        unsafe fn abandon_in_place(this: NonNull<Self>) {
            // SAFETY: the caller passes a valid value.
            let a = unsafe { &this.as_ref().abandons };
            a.set(a.get() + 1);
        }
    }

    #[derive(Debug)]
    struct Leaf(u64);
    impl Abandonable for Leaf {
        unsafe fn abandon_in_place(_this: NonNull<Self>) {}
    }

    fn probe(drops: &Rc<Cell<u32>>, nested: Option<PooledRc<Leaf>>) -> Probe {
        Probe {
            drops: drops.clone(),
            abandons: Rc::new(Cell::new(0)),
            _nested: nested,
        }
    }

    #[test]
    fn counts_clones_and_drops_once() {
        let drops = Rc::new(Cell::new(0));
        let a = PooledRc::new(probe(&drops, None)).unwrap();
        let b = a.clone();
        assert_eq!((a.count(), b.count()), (2, 2));
        assert_eq!(b.lock().drops.get(), 0);
        drop(a);
        assert_eq!((b.count(), drops.get()), (1, 0));
        drop(b);
        assert_eq!(drops.get(), 1);
    }

    #[test]
    fn reuses_blocks() {
        let first = PooledRc::new(Leaf(1)).unwrap();
        let addr = first.ptr.as_ptr() as usize;
        drop(first);
        // The freed block is the head of its class: the next one of this layout reuses it.
        let second = PooledRc::new(Leaf(2)).unwrap();
        assert_eq!(second.ptr.as_ptr() as usize, addr);
        assert_eq!(second.lock().0, 2);
    }

    #[test]
    fn nested_pointers_released_in_drop() {
        let drops = Rc::new(Cell::new(0));
        let leaf = PooledRc::new(Leaf(7)).unwrap();
        let outer = PooledRc::new(probe(&drops, Some(leaf.clone()))).unwrap();
        assert_eq!(leaf.count(), 2);
        drop(outer);
        assert_eq!((drops.get(), leaf.count()), (1, 1));
        for i in 0..3 * POOL_BLOCKS as u64 {
            // Many live at once: more than a class keeps; the rest go back to the allocator.
            let many: Vec<_> = (0..POOL_BLOCKS as u64 + 5)
                .map(|j| PooledRc::new(Leaf(i + j)).unwrap())
                .collect();
            assert!(many.iter().enumerate().all(|(j, p)| p.lock().0 == i + j as u64));
        }
    }

    #[test]
    fn abandon_last_pointer() {
        let drops = Rc::new(Cell::new(0));
        let p = probe(&drops, None);
        let abandons = p.abandons.clone();
        let a = PooledRc::new(p).unwrap();
        let b = a.clone();
        let mut b = core::mem::ManuallyDrop::new(b);
        // SAFETY: `b` is valid and not used again.
        unsafe { PooledRc::abandon_in_place(NonNull::from(&mut *b)) };
        assert_eq!((a.count(), drops.get(), abandons.get()), (1, 0, 0));
        let mut a = core::mem::ManuallyDrop::new(a);
        // SAFETY: as above; the value is abandoned (not dropped) and its block leaks.
        unsafe { PooledRc::abandon_in_place(NonNull::from(&mut *a)) };
        assert_eq!((drops.get(), abandons.get()), (0, 1));
    }
}
