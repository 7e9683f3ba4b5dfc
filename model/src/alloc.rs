//! The process's allocator settings for CPU work.

/// Makes glibc's malloc keep freed memory for the next allocation instead of handing it back to
/// the kernel. Every burn op on the CPU allocates its output afresh: a 2k-token prefill at 0.5B
/// makes buffers of 7-39 MB, which glibc by default maps per allocation and unmaps on free, so
/// each was zeroed and faulted in page by page again (page faults were ~8 % of a prefill's
/// samples). Measured on 2 cores: prefill 244 -> 291 tokens/s, vision tower 2.90 -> 2.68 s
/// (BENCHMARKS.md). Freed memory stays with the process (its peak is unchanged). Call it at the
/// start of `main`; a no-op off glibc.
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
