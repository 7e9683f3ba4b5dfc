//! The process's allocator settings for CPU work.

/// Makes glibc's malloc keep freed memory for the next allocation instead of handing it back to
/// the kernel. Every burn op on the CPU allocates its output afresh: a 2k-token prefill at 0.5B
/// makes buffers of 7-39 MB, which glibc by default maps per allocation and unmaps on free, so
/// each was zeroed and faulted in page by page again (page faults were ~8 % of a prefill's
/// samples). Measured on 2 cores: prefill 244 -> 291 tokens/s, vision tower 2.90 -> 2.68 s
/// (eval/journal/2026-11-26.md, "Decode past transformers on the AVX-512 Xeon: few-row products, the
/// KV cache in place, malloc kept"). Freed memory stays with the process (its peak is unchanged).
/// Call it at the start of `main`; a no-op off glibc.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets malloc's tunables (it takes the arena lock itself).
    unsafe {
        // serve allocations up to 32 MB (glibc's maximum) from the heap, not from fresh maps
        libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
        // return the heap's top to the kernel only past 1 GB free, and grow it 64 MB at a time
        libc::mallopt(libc::M_TRIM_THRESHOLD, i32::MAX);
        libc::mallopt(libc::M_TOP_PAD, 256 << 20);
    }
}

/// Lets a [`KeepLarge`] global allocator keep up to `bytes` of freed large blocks for reuse (0,
/// the start: none; lowering it hands the excess back now). A stage that makes and frees the same
/// large buffers at every step sets it while it runs (the language stage at real size), so that
/// other stages' peaks are not raised by blocks they would never reuse.
pub fn keep_large_blocks(bytes: usize) {
    KEEP_BYTES.store(bytes, Ordering::Relaxed);
    let mut freed = [(0usize, 0usize); SLOTS];
    {
        let mut k = kept();
        for f in freed.iter_mut() {
            if k.bytes <= bytes {
                break;
            }
            let Some(j) = (0..SLOTS).find(|&j| k.blocks[j].1 != 0) else { break };
            *f = k.blocks[j];
            k.bytes -= k.blocks[j].1;
            k.blocks[j] = (0, 0);
        }
    }
    for (a, s) in freed.into_iter().filter(|b| b.1 != 0) {
        unmap(a, s);
    }
}

/// A quarter of the machine's memory, at most 8 GB: what [`keep_large_blocks`] is given by the
/// stages that use it.
pub fn large_block_budget() -> usize {
    #[cfg(unix)]
    // SAFETY: `sysconf` reads a system constant.
    let pages = unsafe { libc::sysconf(libc::_SC_PHYS_PAGES) }.max(0) as usize;
    #[cfg(not(unix))]
    let pages = 0usize;
    (pages.saturating_mul(4096) / 4).min(8 << 30)
}

/// Bytes free to this user on the file system that holds `path` (or its deepest existing
/// ancestor, for a folder not made yet); `None` where it cannot be read.
pub fn free_disk(path: &std::path::Path) -> Option<u64> {
    let at = crate::io::resolved(path);
    let existing = at.ancestors().find(|p| p.exists())?;
    #[cfg(unix)]
    {
        use std::os::unix::ffi::OsStrExt;
        let c = std::ffi::CString::new(existing.as_os_str().as_bytes()).ok()?;
        let mut s = std::mem::MaybeUninit::<libc::statvfs>::uninit();
        // SAFETY: `c` is a NUL-terminated path and `s` is a buffer of the struct statvfs fills.
        let r = unsafe { libc::statvfs(c.as_ptr(), s.as_mut_ptr()) };
        if r != 0 {
            return None;
        }
        // SAFETY: statvfs returned 0, so it filled `s`.
        let s = unsafe { s.assume_init() };
        // both are 32-bit on some targets
        #[allow(clippy::unnecessary_cast)]
        Some((s.f_bavail as u64).saturating_mul(s.f_frsize as u64))
    }
    #[cfg(not(unix))]
    {
        let _ = existing;
        None
    }
}

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Blocks from this size up are [`KeepLarge`]'s: the ones glibc would map afresh per allocation
/// (its mapping threshold cannot pass 32 MB).
const LARGE: usize = 32 << 20;
/// Large blocks are whole 2 MB pages (what transparent huge pages need).
const HUGE_PAGE: usize = 2 << 20;
/// Freed large blocks kept at most (a step at real size frees a few dozen).
const SLOTS: usize = 48;

/// How many bytes of freed large blocks [`KeepLarge`] may keep ([`keep_large_blocks`]).
static KEEP_BYTES: AtomicUsize = AtomicUsize::new(0);

struct Kept {
    /// `(address, size)` of the freed blocks, oldest first (`size` 0: an empty slot).
    blocks: [(usize, usize); SLOTS],
    bytes: usize,
}

static KEPT: Mutex<Kept> = Mutex::new(Kept { blocks: [(0, 0); SLOTS], bytes: 0 });

/// A global allocator for CPU work on large tensors: every burn op allocates its output afresh,
/// and at LLaVA-OneVision's size a language step makes and frees dozens of buffers of 0.1-1 GB
/// (the patch convolution's weight is 1 GB; Adam alone makes a dozen temporaries of its size).
/// glibc maps each afresh and unmaps it on free, so the kernel zeroes and faults in every page
/// again: 2.3 M page faults and more system than user time per step (measured). `KeepLarge`
/// maps blocks of 32 MB and up with transparent huge pages (a 512th of the faults), serves them
/// from the freed blocks of the same size it keeps while a stage allows it
/// ([`keep_large_blocks`]: no fault at all), and leaves smaller blocks to the system allocator. Declare it in a binary:
/// `#[global_allocator] static ALLOC: model::alloc::KeepLarge = model::alloc::KeepLarge;`
pub struct KeepLarge;

fn kept() -> std::sync::MutexGuard<'static, Kept> {
    KEPT.lock().unwrap_or_else(|e| e.into_inner())
}

/// The size of the large block that serves `layout` (whole huge pages), or `None` for the system
/// allocator. Sizes are not rounded further: rounded to eight classes per power of two (so that
/// nearby sizes would share blocks), a real-size language step took 8-11 s instead of 6.4-7.6
/// (60 % more user time; likely blocks of one power-of-two size sharing cache sets).
fn large_size(layout: Layout) -> Option<usize> {
    (layout.size() >= LARGE && layout.align() <= 4096).then(|| layout.size().div_ceil(HUGE_PAGE) * HUGE_PAGE)
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn map(size: usize) -> *mut u8 {
    // SAFETY: an anonymous private mapping touches no existing memory; failure is checked.
    unsafe {
        let p = libc::mmap(
            std::ptr::null_mut(),
            size,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
            -1,
            0,
        );
        if p == libc::MAP_FAILED {
            return std::ptr::null_mut();
        }
        libc::madvise(p, size, libc::MADV_HUGEPAGE);
        p as *mut u8
    }
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn unmap(addr: usize, size: usize) {
    // SAFETY: `addr..addr + size` is a whole mapping made by `map` and no longer used.
    unsafe {
        libc::munmap(addr as *mut libc::c_void, size);
    }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn map(size: usize) -> *mut u8 {
    // SAFETY: a non-zero size with page alignment is a valid layout.
    unsafe { System.alloc(Layout::from_size_align_unchecked(size, 4096)) }
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn unmap(addr: usize, size: usize) {
    // SAFETY: the block was allocated by `map` with this size and alignment.
    unsafe { System.dealloc(addr as *mut u8, Layout::from_size_align_unchecked(size, 4096)) }
}

/// A kept block of exactly `size` bytes (the newest), taken out of the keep.
fn take(size: usize) -> Option<*mut u8> {
    let mut k = kept();
    let i = (0..SLOTS).rev().find(|&i| k.blocks[i].1 == size)?;
    let (addr, _) = k.blocks[i];
    k.blocks[i] = (0, 0);
    k.bytes -= size;
    Some(addr as *mut u8)
}

/// Keeps the freed block `addr` of `size` bytes, handing the oldest kept ones back to the system
/// while the budget or the slots are short (or this one back, when it alone is over the budget).
fn keep(addr: usize, size: usize) {
    let budget = KEEP_BYTES.load(Ordering::Relaxed);
    if size > budget {
        return unmap(addr, size);
    }
    let mut freed = [(0usize, 0usize); SLOTS];
    {
        let mut k = kept();
        let mut n = 0;
        while k.bytes + size > budget || k.blocks.iter().all(|b| b.1 != 0) {
            let Some(i) = (0..SLOTS).find(|&i| k.blocks[i].1 != 0) else { break };
            freed[n] = k.blocks[i];
            n += 1;
            k.bytes -= k.blocks[i].1;
            k.blocks[i] = (0, 0);
        }
        // compact toward the front (oldest first) and append
        let mut live: [(usize, usize); SLOTS] = [(0, 0); SLOTS];
        let mut m = 0;
        for b in k.blocks.iter().filter(|b| b.1 != 0) {
            live[m] = *b;
            m += 1;
        }
        live[m] = (addr, size);
        k.blocks = live;
        k.bytes += size;
    }
    for (a, s) in freed.into_iter().filter(|b| b.1 != 0) {
        unmap(a, s);
    }
}

// SAFETY: large blocks come from whole private mappings (page-aligned, so any alignment up to
// 4096 holds) that only the caller uses until it frees them; everything else is `System`'s.
unsafe impl GlobalAlloc for KeepLarge {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match large_size(layout) {
            Some(size) => take(size).unwrap_or_else(|| map(size)),
            // SAFETY: the caller's layout contract, passed on.
            None => unsafe { System.alloc(layout) },
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match large_size(layout) {
            Some(size) => match take(size) {
                Some(p) => {
                    // SAFETY: the kept block holds `size >= layout.size()` writable bytes.
                    unsafe { std::ptr::write_bytes(p, 0, layout.size()) };
                    p
                }
                // a fresh mapping reads as zeros
                None => map(size),
            },
            // SAFETY: the caller's layout contract, passed on.
            None => unsafe { System.alloc_zeroed(layout) },
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        match large_size(layout) {
            Some(size) => keep(ptr as usize, size),
            // SAFETY: `ptr` came from `System.alloc` with this layout.
            None => unsafe { System.dealloc(ptr, layout) },
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: the caller's contract: `layout.align()` is a power of two, `new_size` valid for it.
        let new = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        match (large_size(layout), large_size(new)) {
            // SAFETY: both small: `System` made `ptr` and resizes it.
            (None, None) => unsafe { System.realloc(ptr, layout, new_size) },
            (Some(a), Some(b)) if a == b => ptr,
            _ => {
                // SAFETY: a fresh block for `new`, the old one copied (the shorter length) and freed.
                unsafe {
                    let p = self.alloc(new);
                    if !p.is_null() {
                        std::ptr::copy_nonoverlapping(ptr, p, layout.size().min(new_size));
                        self.dealloc(ptr, layout);
                    }
                    p
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A large block freed while the budget allows it is served again (same address, contents
    /// kept for `alloc`, zeroed for `alloc_zeroed`); over the budget, or with none, it is not kept;
    /// `realloc` across the threshold keeps the contents.
    #[test]
    fn freed_large_blocks_are_reused_within_the_budget_and_zeroed_on_request() {
        let a = KeepLarge;
        let layout = Layout::from_size_align(LARGE + 12345, 64).unwrap();
        // SAFETY: every block is used within its layout and freed with the layout it was made with.
        unsafe {
            keep_large_blocks(4 * LARGE);
            let p = a.alloc(layout);
            assert!(!p.is_null());
            std::ptr::write_bytes(p, 7, layout.size());
            a.dealloc(p, layout);
            let q = a.alloc_zeroed(layout);
            assert_eq!(q, p, "the kept block serves the same size");
            let s = std::slice::from_raw_parts(q, layout.size());
            assert!(s.iter().all(|&x| x == 0), "alloc_zeroed of a kept block is zeroed");
            std::ptr::write_bytes(q, 9, 1000);
            // grow it past another huge page: contents move with it
            let r = a.realloc(q, layout, layout.size() + (4 << 20));
            assert_eq!(std::slice::from_raw_parts(r, 1000), &[9u8; 1000][..]);
            let grown = Layout::from_size_align(layout.size() + (4 << 20), 64).unwrap();
            // shrink below the threshold: the system allocator's from here
            let small = a.realloc(r, grown, 4096);
            assert_eq!(std::slice::from_raw_parts(small, 1000), &[9u8; 1000][..]);
            a.dealloc(small, Layout::from_size_align(4096, 64).unwrap());
            // nothing kept with no budget: the kept blocks are handed back
            keep_large_blocks(0);
            assert_eq!(kept().bytes, 0);
            let p = a.alloc(layout);
            a.dealloc(p, layout);
            assert_eq!(kept().bytes, 0, "no budget, nothing kept");
        }
    }
}
