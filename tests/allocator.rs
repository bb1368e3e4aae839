//! The allocator option `reconstruct::allocator` sets is mimalloc's purge delay: the index we
//! pass is checked against that option's default (1000 ms in mimalloc v3, unique among its
//! options), and setting it reads back.

use libmimalloc_sys::mi_option_get;
use reconstruct::allocator::{keep_freed_pages, MI_OPTION_PURGE_DELAY};

#[test]
fn purge_delay_index_is_the_purge_delay_and_is_set() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
        eprintln!("MIMALLOC_PURGE_DELAY is set in the environment; the default cannot be checked");
        return;
    }
    // SAFETY: reading an option is always valid.
    let before = unsafe { mi_option_get(MI_OPTION_PURGE_DELAY) };
    assert_eq!(before, 1000, "option {MI_OPTION_PURGE_DELAY} is not mimalloc v3's purge_delay (default 1000 ms)");
    keep_freed_pages();
    let after = unsafe { mi_option_get(MI_OPTION_PURGE_DELAY) };
    assert_eq!(after, -1);
}
