//! One summary line for the tests that read the shared data folder: how many there are, and which of
//! them skip here because their data is missing. With `RECONSTRUCT_REQUIRE_SHARED=1` (set by `.ci/run`)
//! any skip fails this test (and the skipping test itself).

mod common;

use std::io::Write;

use common::shared_data::{missing, required, shared_dir, NEEDS, REQUIRE_ENV};

#[test]
fn shared_data_summary() {
    let skipped: Vec<&str> = NEEDS.iter().map(|(t, _)| *t).filter(|t| !missing(t).is_empty()).collect();
    let line = if skipped.is_empty() {
        format!("shared data {}: all {} tests that need it run", shared_dir().display(), NEEDS.len())
    } else {
        format!("shared data {}: {} of {} tests that need it are SKIPPED: {}", shared_dir().display(), skipped.len(), NEEDS.len(), skipped.join(", "))
    };
    let _ = writeln!(std::io::stderr(), "{line}");
    assert!(skipped.is_empty() || !required(), "{REQUIRE_ENV}=1 and {line}");
}

/// Each registered test names at least one path, and every path is relative to the shared folder.
#[test]
fn the_registry_is_well_formed() {
    for (test, paths) in NEEDS {
        assert!(test.contains("::") && !paths.is_empty(), "{test}");
        assert!(paths.iter().all(|p| !p.starts_with('/') && !p.contains("..")), "{test}: {paths:?}");
    }
}
