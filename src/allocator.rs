//! How the binaries' allocator (mimalloc) treats freed memory, and why.
//!
//! A Monte Carlo step allocates and frees large buffers every iteration (per-pixel samples, tape
//! values, gradients, the denoiser's weights: tens of MB, sized by the batch's covered pixels, so
//! they differ from step to step). By default mimalloc v3 hands freed memory back to the kernel a
//! second after it is freed (its `purge_delay`), and the kernel zeroes every page faulted in again:
//! `perf` showed `clear_page_erms` at 9 % of a 4-spp step on the hotdog, and a default hotdog
//! run's system time fell from 18.5 to 5.4 s with this change and the denoiser's rework. Keeping
//! freed pages adds little to the peak (the pages were live at the peak anyway; 0.78 → 0.86 GB on
//! that run); the resident size just stays near the peak until the process ends. Measured in
//! docs/performance.md,
//! *Allocator: keeping freed pages*.

/// mimalloc's `mi_option_purge_delay`, index 15 of `mi_option_t` in both its v2 and v3 headers.
/// libmimalloc-sys names most options but not this one; `tests/allocator.rs` checks the index
/// against the option's documented default, so a header change fails the suite instead of
/// setting another option.
pub const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Tells mimalloc never to return freed pages to the kernel (purge delay −1). Call once, first
/// thing in `main`, from a binary whose global allocator is mimalloc. An explicit
/// `MIMALLOC_PURGE_DELAY` in the environment still wins, so a user can restore the default.
pub fn keep_freed_pages() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
        return;
    }
    // SAFETY: mi_option_set only stores a value in mimalloc's option table; any index within
    // the enum is valid, and this one is checked by tests/allocator.rs.
    unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, -1) };
}
