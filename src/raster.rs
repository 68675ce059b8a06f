//! Raster output in the ENVI format (a raw little-endian float32 band plus a `.hdr` text header),
//! which GDAL, QGIS and ENVI open directly. Files are written under a temporary name and renamed
//! into place, so a reader never sees a half-written file.
//!
//! Header keys written (ENVI header specification): `samples`, `lines`, `bands = 1`,
//! `header offset = 0`, `file type = ENVI Standard`, `data type = 4` (float32),
//! `interleave = bsq`, `byte order = 0` (little-endian), `data ignore value` (NaN is used for
//! no data), `band names`, `description`, and `pixel size` as a comment-free `map info`-less
//! `sfsfuse pixel size = ε` key (the grid is not georeferenced until the export issue lands).

use crate::error::{Error, Result};
use ndarray::Array2;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Write `bytes` to `path` atomically (temporary sibling + rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let tmp = tmp_name(path);
    let res = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if let Err(e) = res {
        let _ = std::fs::remove_file(&tmp);
        return Err(Error::io(path, e));
    }
    Ok(())
}

fn tmp_name(path: &Path) -> PathBuf {
    let mut name = path
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    name.push(format!(".{}.tmp", std::process::id()));
    path.with_file_name(name)
}

/// Write one float32 band `<stem>.img` + `<stem>.hdr` in `dir`; returns the `.img` path.
pub fn write_envi(
    dir: &Path,
    stem: &str,
    a: &Array2<f64>,
    band_name: &str,
    description: &str,
    spacing: f64,
) -> Result<PathBuf> {
    let (lines, samples) = a.dim();
    let mut bytes = Vec::with_capacity(lines * samples * 4);
    for v in a.iter() {
        bytes.extend_from_slice(&(*v as f32).to_le_bytes());
    }
    let img = dir.join(format!("{stem}.img"));
    let hdr = dir.join(format!("{stem}.hdr"));
    let header = format!(
        "ENVI\ndescription = {{{description}}}\nsamples = {samples}\nlines = {lines}\nbands = 1\nheader offset = 0\nfile type = ENVI Standard\ndata type = 4\ninterleave = bsq\nbyte order = 0\ndata ignore value = nan\nband names = {{{band_name}}}\nsfsfuse pixel size = {spacing}\n"
    );
    write_atomic(&img, &bytes)?;
    write_atomic(&hdr, header.as_bytes())?;
    Ok(img)
}

/// Read back a band written by [`write_envi`] (tests and tools).
pub fn read_envi(img: &Path) -> Result<Array2<f32>> {
    let hdr = img.with_extension("hdr");
    let text = std::fs::read_to_string(&hdr).map_err(|e| Error::io(&hdr, e))?;
    let key = |k: &str| -> Result<usize> {
        text.lines()
            .find_map(|l| {
                l.split_once('=')
                    .filter(|(a, _)| a.trim() == k)
                    .map(|(_, b)| b.trim().to_string())
            })
            .ok_or_else(|| Error::Usage(format!("{}: no `{k}` key", hdr.display())))?
            .parse()
            .map_err(|_| Error::Usage(format!("{}: `{k}` is not a whole number", hdr.display())))
    };
    let (samples, lines) = (key("samples")?, key("lines")?);
    let bytes = std::fs::read(img).map_err(|e| Error::io(img, e))?;
    if bytes.len() != samples * lines * 4 {
        return Err(Error::Usage(format!(
            "{}: {} bytes, the header says {} × {} float32 = {}",
            img.display(),
            bytes.len(),
            lines,
            samples,
            samples * lines * 4
        )));
    }
    let v: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    Array2::from_shape_vec((lines, samples), v).map_err(|e| Error::Usage(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn envi_round_trip_and_no_temporary_left() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-envi-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let a = Array2::from_shape_fn((3, 5), |(i, j)| i as f64 * 10.0 + j as f64 + 0.5);
        let img = write_envi(&dir, "t", &a, "height", "test", 140.0).unwrap();
        let b = read_envi(&img).unwrap();
        assert_eq!(b.dim(), (3, 5));
        assert!(a.iter().zip(b.iter()).all(|(x, y)| (*x as f32) == *y));
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().into_string().unwrap())
            .collect();
        assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
        // A truncated file is reported with its path and sizes.
        std::fs::write(&img, [0u8; 7]).unwrap();
        let err = read_envi(&img).unwrap_err().to_string();
        assert!(err.contains("t.img") && err.contains("7 bytes"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
