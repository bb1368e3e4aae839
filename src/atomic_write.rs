//! Files and folders written whole or not at all: everything is first written under a temporary
//! name beside its destination, then renamed over it (a rename within one file system is atomic).
//! A run killed at any moment (SIGKILL included) therefore leaves either the previous version or the
//! new one, never half a file; a rerun redoes what was cut short. This guards against the process
//! dying, not against a power cut (nothing is fsynced). Leftover temporaries (`.NAME.partial…`)
//! are overwritten by the next attempt.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

/// The temporary name of `path`: hidden, in the same folder, keeping the extension (writers that
/// choose the format from the extension still see it), e.g. `dir/.kd.partial.png` for `dir/kd.png`.
pub fn partial_path(path: &Path) -> PathBuf {
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let name = match path.extension() {
        Some(ext) => format!(".{stem}.partial.{}", ext.to_string_lossy()),
        None => format!(".{stem}.partial"),
    };
    path.with_file_name(name)
}

/// Writes `path` through `write` (called with the temporary path), then renames it into place.
pub fn replace_file(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create the folder {}", dir.display()))?;
    }
    let tmp = partial_path(path);
    write(&tmp)?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))
}

/// Writes `bytes` to `path` atomically.
pub fn write(path: &Path, bytes: impl AsRef<[u8]>) -> Result<()> {
    replace_file(path, |tmp| std::fs::write(tmp, bytes.as_ref()).with_context(|| format!("cannot write {}", tmp.display())))
}

/// Replaces the folder `dir` by one that `fill` writes (into a fresh temporary folder). Between
/// removing the old folder and renaming the new one in, a kill leaves no folder at all, never a
/// mixed one; callers redo the whole folder on rerun.
pub fn replace_dir(dir: &Path, fill: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let tmp = partial_path(dir);
    if tmp.exists() {
        std::fs::remove_dir_all(&tmp).with_context(|| format!("cannot remove the leftover {}", tmp.display()))?;
    }
    std::fs::create_dir_all(&tmp).with_context(|| format!("cannot create {}", tmp.display()))?;
    fill(&tmp)?;
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot remove the old {}", dir.display()))?;
    }
    std::fs::rename(&tmp, dir).with_context(|| format!("cannot move {} to {}", tmp.display(), dir.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn files_and_folders_are_replaced_whole() -> Result<()> {
        let dir = std::env::temp_dir().join(format!("reconstruct-atomic-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let file = dir.join("a.json");
        write(&file, "1")?;
        assert_eq!(partial_path(&file), dir.join(".a.partial.json"));
        // A writer that fails leaves the old content in place.
        let failed = replace_file(&file, |tmp| {
            std::fs::write(tmp, "half")?;
            anyhow::bail!("killed")
        });
        assert!(failed.is_err());
        assert_eq!(std::fs::read_to_string(&file)?, "1");
        write(&file, "2")?;
        assert_eq!(std::fs::read_to_string(&file)?, "2");

        let sub = dir.join("model");
        replace_dir(&sub, |d| Ok(std::fs::write(d.join("old.txt"), "x")?))?;
        replace_dir(&sub, |d| Ok(std::fs::write(d.join("new.txt"), "y")?))?;
        assert!(sub.join("new.txt").is_file() && !sub.join("old.txt").exists(), "the new folder replaces the old one whole");
        assert!(replace_dir(&sub, |_| anyhow::bail!("killed")).is_err());
        assert!(sub.join("new.txt").is_file(), "a failed fill keeps the old folder");
        std::fs::remove_dir_all(&dir)?;
        Ok(())
    }
}
