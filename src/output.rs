//! A run's output directory: one writer at a time, no stale temporaries, nothing left behind
//! by a run that wrote nothing.
//!
//! * [`OutputDir::open`] takes an advisory lock on `<dir>/.sfsfuse.lock` (`flock`): exclusive
//!   for a whole run or a mosaic, shared for `--tile` tasks, which a cluster runs side by side
//!   on one directory. A run that cannot get it is refused with the lock's path and its
//!   holder's pid and host, rather than computing every tile a second time.
//! * Holding the exclusive lock, no other sfsfuse process writes here, so every `*.tmp` file
//!   (the temporaries of [`crate::raster::write_atomic`] and the COG writer) is left over from
//!   a killed run and is removed.
//! * When the run fails and the directory did not exist before it, whatever the run created
//!   that holds no file (the lock, empty folders) is removed again.

use crate::error::{Error, Result};
use std::fs::{File, TryLockError};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The lock file's name inside the output directory.
pub const LOCK_NAME: &str = ".sfsfuse.lock";

/// An output directory held for a run (the lock is released when this is dropped).
pub struct OutputDir {
    dir: PathBuf,
    created: bool,
    _lock: File,
}

impl OutputDir {
    /// Create `dir` if needed and lock it: `exclusive` for a whole run or a mosaic, shared
    /// for tile tasks. With the exclusive lock, stale temporaries are removed (their count is
    /// returned).
    pub fn open(dir: &Path, exclusive: bool) -> Result<(OutputDir, usize)> {
        let created = !dir.exists();
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let path = dir.join(LOCK_NAME);
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .read(true)
            .write(true)
            .open(&path)
            .map_err(|e| Error::io(&path, e))?;
        let got = if exclusive {
            f.try_lock()
        } else {
            f.try_lock_shared()
        };
        match got {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                let holder = holder.trim();
                return Err(Error::Usage(format!(
                    "{} is locked by another sfsfuse run or tile task (the last whole run to hold it signed: {}): wait for it to finish, or give this run another [output] directory",
                    path.display(),
                    if holder.is_empty() { "nobody" } else { holder }
                )));
            }
            Err(TryLockError::Error(e)) => return Err(Error::io(&path, e)),
        }
        if exclusive {
            let host = std::fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
            f.set_len(0).map_err(|e| Error::io(&path, e))?;
            writeln!(f, "pid {} on {}", std::process::id(), host.trim())
                .map_err(|e| Error::io(&path, e))?;
        }
        let out = OutputDir {
            dir: dir.to_path_buf(),
            created,
            _lock: f,
        };
        let swept = if exclusive { out.sweep()? } else { 0 };
        Ok((out, swept))
    }

    /// Remove every `*.tmp` file in the directory and its `tiles/`.
    fn sweep(&self) -> Result<usize> {
        let mut n = 0;
        for d in [self.dir.clone(), self.dir.join("tiles")] {
            let Ok(entries) = std::fs::read_dir(&d) else {
                continue;
            };
            for e in entries.flatten() {
                let p = e.path();
                if p.is_file() && p.extension().is_some_and(|x| x == "tmp") {
                    std::fs::remove_file(&p).map_err(|e| Error::io(&p, e))?;
                    n += 1;
                }
            }
        }
        Ok(n)
    }

    /// After a failed run: if the directory is new and holds no file but the lock, remove it.
    pub fn abandon(self) {
        if !self.created || holds_files(&self.dir) {
            return;
        }
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Whether `dir` (recursively) holds any file other than the lock.
fn holds_files(dir: &Path) -> bool {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return false;
    };
    entries.flatten().any(|e| {
        let p = e.path();
        if p.is_dir() {
            holds_files(&p)
        } else {
            e.file_name() != LOCK_NAME
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_writer_stale_temporaries_and_nothing_left_behind() {
        let base = std::env::temp_dir().join(format!("sfsfuse-outdir-{}", std::process::id()));
        let dir = base.join("run");
        let (a, swept) = OutputDir::open(&dir, true).unwrap();
        assert_eq!(swept, 0);
        // A second exclusive or shared holder is refused, naming the lock and the holder.
        for exclusive in [true, false] {
            let e = OutputDir::open(&dir, exclusive).err().unwrap().to_string();
            assert!(
                e.contains(".sfsfuse.lock") && e.contains(&format!("pid {}", std::process::id())),
                "{e}"
            );
        }
        // Nothing written: abandoning the new directory removes it.
        a.abandon();
        assert!(!dir.exists());
        // Stale temporaries go; other files stay, and so does the directory.
        std::fs::create_dir_all(dir.join("tiles")).unwrap();
        for f in [
            "dem.tif.123.tmp",
            "tiles/tile_00000.sfstile.9.tmp",
            "dem.tif",
        ] {
            std::fs::write(dir.join(f), b"x").unwrap();
        }
        let (b, swept) = OutputDir::open(&dir, true).unwrap();
        assert_eq!(swept, 2);
        assert!(dir.join("dem.tif").exists());
        b.abandon();
        assert!(dir.join("dem.tif").exists());
        // Tile tasks share the lock with each other.
        let (s1, _) = OutputDir::open(&dir, false).unwrap();
        let (s2, _) = OutputDir::open(&dir, false).unwrap();
        assert!(OutputDir::open(&dir, true).is_err());
        drop((s1, s2));
        std::fs::remove_dir_all(&base).unwrap();
    }
}
