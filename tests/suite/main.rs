//! The integration tests as one binary (one link, and one process that compiles wgpu's kernels
//! once), in data-flow order. Run one part with e.g. `cargo test -p chatsplat-tests --test suite vlm::`.

// The splatting op: CPU kernels against the f64 oracle, hard and fuzzed inputs, burn backends.
mod cpu_kernel;

mod cpu_hard_cases;

mod cpu_fuzz;

mod dense_baseline;

mod backends;

mod optimize;

// Captures: loaders of every format, .ply files.
mod loaders;

mod loaders_formats;

mod ply;

// Every parser a user feeds, fuzzed.
mod parsers_fuzz;

// Geometry, the synthetic scenes and their questions, the VLM, the language stage.
mod geometry;

// Per-view masks from any segmenter matched across views through the Gaussians.
mod masks;

mod synth;

mod vlm;

mod tabletop_vlm;

mod language;

mod token_mixer;

mod language_hard_cases;

mod compact;

// Segment Anything: parity with transformers' SamModel on a tiny random checkpoint.
mod sam;

// Models named by their Hugging Face id, from a loopback hub.
mod hub;

// The house: no circle in any crate's module graph (ARCHITECTURE.md).
mod module_graph;

/// The suite's allocator: the system's, noting the largest single allocation a thread asks for
/// while [`track_allocations`] is on (the parser fuzzing checks that no corrupt header makes a
/// parser allocate before it has checked the sizes against the bytes present).
struct Tracking;

thread_local! {
    static TRACKING: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    static LARGEST: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

fn note(size: usize) {
    // `try_with`: no panic while the thread's locals are being torn down
    let _ = TRACKING.try_with(|on| {
        if on.get() {
            let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
        }
    });
}

// SAFETY: every method forwards to `System` with the caller's arguments unchanged; `note` only
// reads and writes two const-initialised thread-local cells (no allocation, no reentrancy).
unsafe impl std::alloc::GlobalAlloc for Tracking {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: forwarded as received (the caller upholds `GlobalAlloc::alloc`'s contract).
        unsafe { std::alloc::System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        note(layout.size());
        // SAFETY: as above.
        unsafe { std::alloc::System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        // SAFETY: as above; `ptr` came from this allocator, i.e. from `System`.
        unsafe { std::alloc::System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        // SAFETY: as above.
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static ALLOCATOR: Tracking = Tracking;

/// Starts (resetting the largest seen) or stops noting this thread's allocations.
pub(crate) fn track_allocations(on: bool) {
    TRACKING.with(|t| t.set(on));
    if on {
        LARGEST.with(|l| l.set(0));
    }
}

/// The largest single allocation of this thread since [`track_allocations`]`(true)`.
pub(crate) fn largest_allocation() -> usize {
    LARGEST.with(|l| l.get())
}
