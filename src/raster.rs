//! File helpers at the I/O edge. Atomic output: every product is written under a temporary sibling name, synced, and
//! renamed into place, so a reader (or a resumed run) never sees a half-written file.

use crate::error::{Error, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Write `bytes` to `path` atomically (temporary sibling + fsync + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes))
}

/// Write `path` atomically from what `fill` streams into a buffered writer on the temporary
/// sibling (then fsync + rename): for products too large to assemble in memory first. On any
/// error the temporary is removed and the error names `path`.
pub fn write_atomic_with(
    path: &Path,
    fill: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let tmp = tmp_name(path);
    let res = (|| {
        let mut w = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(&tmp)?);
        fill(&mut w)?;
        let f = w.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, e));
    }
    Ok(())
}

/// Hex digest (SHA-256, MD5, …) of a file's contents, streamed in 1 MiB reads.
pub fn file_digest<D: sha2::Digest>(path: &Path) -> Result<String> {
    use std::io::Read;
    let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut h = D::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = f.read(&mut buf).map_err(|e| Error::io(path, e))?;
        if n == 0 {
            break;
        }
        h.update(&buf[..n]);
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

/// `<name>.<pid>.tmp` beside `path`: unique per process, so concurrent writers (cluster tasks
/// on a shared file system) never share a temporary.
pub fn tmp_name(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".{}.tmp", std::process::id()));
    path.with_file_name(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn atomic_write_leaves_no_temporary_and_names_the_path_on_error() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-atomic-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.bin");
        write_atomic(&p, b"first").unwrap();
        write_atomic(&p, b"second").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"second");
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert_eq!(names, ["a.bin"]);
        let missing = dir.join("no/such/dir/b.bin");
        let e = write_atomic(&missing, b"x").unwrap_err().to_string();
        assert!(e.contains("no/such/dir/b.bin"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_failing_stream_leaves_neither_output_nor_temporary() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-stream-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("cube.img");
        write_atomic_with(&p, |w| {
            for line in 0..3u8 {
                w.write_all(&[line; 4])?;
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(
            std::fs::read(&p).unwrap(),
            [0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2]
        );
        let q = dir.join("broken.img");
        let e = write_atomic_with(&q, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("the source ran dry"))
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("broken.img") && e.contains("ran dry"), "{e}");
        let mut names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        names.sort();
        assert_eq!(names, ["cube.img"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
