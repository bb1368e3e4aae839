//! Helpers shared by the integration tests (each test file that needs one says `mod common;`).
#![allow(dead_code)]

pub mod shared_data;

/// Copies the folder `from` to `to`, recursively (a scratch copy of a dataset a test may change).
pub fn copy_dir(from: &std::path::Path, to: &std::path::Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for e in std::fs::read_dir(from)? {
        let e = e?;
        let target = to.join(e.file_name());
        if e.file_type()?.is_dir() {
            copy_dir(&e.path(), &target)?;
        } else {
            std::fs::copy(e.path(), target)?;
        }
    }
    Ok(())
}
