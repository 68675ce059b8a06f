//! Binary rasters as PDS3 labels describe them: sample types, interleaving, windowed reads.
//!
//! Reads use positioned I/O (`pread`) of exactly the requested line window, so a GB-sized
//! product never has to fit in memory, and nothing is allocated from a size the file cannot
//! back: every layout is checked against the file's length first.

use crate::error::{Error, Result};
use crate::odl::Object;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

/// PDS3 SAMPLE_TYPE × SAMPLE_BITS combinations that occur in M3 and LOLA products.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SampleType {
    U8,
    I16Le,
    I16Be,
    I32Le,
    I32Be,
    F32Le,
    F32Be,
    F64Le,
    F64Be,
}

impl SampleType {
    /// From the label's SAMPLE_TYPE and SAMPLE_BITS.
    pub fn from_label(kind: &str, bits: i64) -> Option<Self> {
        let k = kind.to_ascii_uppercase();
        Some(match (k.as_str(), bits) {
            ("UNSIGNED_INTEGER" | "MSB_UNSIGNED_INTEGER" | "LSB_UNSIGNED_INTEGER", 8) => {
                SampleType::U8
            }
            ("LSB_INTEGER" | "PC_INTEGER" | "VAX_INTEGER", 16) => SampleType::I16Le,
            ("MSB_INTEGER" | "INTEGER" | "SUN_INTEGER", 16) => SampleType::I16Be,
            ("LSB_INTEGER" | "PC_INTEGER" | "VAX_INTEGER", 32) => SampleType::I32Le,
            ("MSB_INTEGER" | "INTEGER" | "SUN_INTEGER", 32) => SampleType::I32Be,
            ("PC_REAL", 32) => SampleType::F32Le,
            ("IEEE_REAL" | "REAL" | "FLOAT" | "SUN_REAL", 32) => SampleType::F32Be,
            ("PC_REAL", 64) => SampleType::F64Le,
            ("IEEE_REAL" | "REAL" | "FLOAT" | "SUN_REAL", 64) => SampleType::F64Be,
            _ => return None,
        })
    }

    pub fn bytes(self) -> usize {
        match self {
            SampleType::U8 => 1,
            SampleType::I16Le | SampleType::I16Be => 2,
            SampleType::I32Le | SampleType::I32Be | SampleType::F32Le | SampleType::F32Be => 4,
            SampleType::F64Le | SampleType::F64Be => 8,
        }
    }

    fn decode(self, b: &[u8]) -> f64 {
        match self {
            SampleType::U8 => b[0] as f64,
            SampleType::I16Le => i16::from_le_bytes([b[0], b[1]]) as f64,
            SampleType::I16Be => i16::from_be_bytes([b[0], b[1]]) as f64,
            SampleType::I32Le => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            SampleType::I32Be => i32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
            SampleType::F32Le => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            SampleType::F32Be => f32::from_be_bytes([b[0], b[1], b[2], b[3]]) as f64,
            SampleType::F64Le => f64::from_le_bytes(b[..8].try_into().expect("8 bytes")),
            SampleType::F64Be => f64::from_be_bytes(b[..8].try_into().expect("8 bytes")),
        }
    }
}

/// How bands are interleaved (BAND_STORAGE_TYPE).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Interleave {
    /// LINE_INTERLEAVED (BIL): for each line, every band's samples.
    Line,
    /// BAND_SEQUENTIAL (BSQ).
    Band,
    /// SAMPLE_INTERLEAVED (BIP).
    Sample,
}

/// A raster's layout in a file.
#[derive(Debug, Clone)]
pub struct Raster {
    pub path: PathBuf,
    pub lines: usize,
    pub samples: usize,
    pub bands: usize,
    pub sample_type: SampleType,
    pub interleave: Interleave,
    /// Byte offset of the first sample.
    pub offset: u64,
}

fn positive(label: &Path, obj: &Object, key: &str) -> Result<usize> {
    let v = obj
        .get(key)
        .ok_or_else(|| Error::missing(label, &format!("{key} in OBJECT {}", obj.name)))?;
    let at = obj.at(key);
    let n = v
        .as_i64()
        .ok_or_else(|| Error::invalid(label, &at, format!("{v} is not an integer")))?;
    if n <= 0 {
        return Err(Error::invalid(label, &at, format!("{n} must be positive")));
    }
    usize::try_from(n).map_err(|_| Error::invalid(label, &at, "too large"))
}

impl Raster {
    /// The layout an IMAGE-like object (`LINES`, `LINE_SAMPLES`, `SAMPLE_TYPE`, `SAMPLE_BITS`,
    /// optional `BANDS`, `BAND_STORAGE_TYPE`) describes, in `data` from byte `offset`; checked
    /// against the file's length.
    pub fn from_object(label: &Path, obj: &Object, data: PathBuf, offset: u64) -> Result<Self> {
        let lines = positive(label, obj, "LINES")?;
        let samples = positive(label, obj, "LINE_SAMPLES")?;
        let bands = if obj.get("BANDS").is_some() {
            positive(label, obj, "BANDS")?
        } else {
            1
        };
        let kind = obj
            .get("SAMPLE_TYPE")
            .and_then(|v| v.as_str())
            .ok_or_else(|| Error::missing(label, "SAMPLE_TYPE"))?;
        let bits = match obj.get("SAMPLE_BITS") {
            None => return Err(Error::missing(label, "SAMPLE_BITS")),
            Some(v) => v.as_i64().ok_or_else(|| {
                Error::invalid(
                    label,
                    &obj.at("SAMPLE_BITS"),
                    format!("{v} is not an integer"),
                )
            })?,
        };
        let sample_type = SampleType::from_label(kind, bits).ok_or_else(|| {
            Error::invalid(
                label,
                &obj.at("SAMPLE_TYPE"),
                format!("{kind} with SAMPLE_BITS = {bits} is not supported"),
            )
        })?;
        let interleave = match obj.get("BAND_STORAGE_TYPE").and_then(|v| v.as_str()) {
            None => Interleave::Band,
            Some(s) if s.eq_ignore_ascii_case("LINE_INTERLEAVED") => Interleave::Line,
            Some(s) if s.eq_ignore_ascii_case("BAND_SEQUENTIAL") => Interleave::Band,
            Some(s) if s.eq_ignore_ascii_case("SAMPLE_INTERLEAVED") => Interleave::Sample,
            Some(s) => {
                return Err(Error::invalid(
                    label,
                    &obj.at("BAND_STORAGE_TYPE"),
                    format!("{s} is not supported"),
                ))
            }
        };
        let r = Raster {
            path: data,
            lines,
            samples,
            bands,
            sample_type,
            interleave,
            offset,
        };
        r.check_length()?;
        Ok(r)
    }

    /// Bytes the raster occupies, or an error if that overflows.
    pub fn byte_len(&self) -> Option<u64> {
        (self.lines as u64)
            .checked_mul(self.samples as u64)?
            .checked_mul(self.bands as u64)?
            .checked_mul(self.sample_type.bytes() as u64)
    }

    fn check_length(&self) -> Result<()> {
        let need = self
            .byte_len()
            .and_then(|n| n.checked_add(self.offset))
            .ok_or_else(|| Error::Size {
                path: self.path.clone(),
                why: "the label's dimensions overflow 64 bits".into(),
            })?;
        let have = std::fs::metadata(&self.path)
            .map_err(|e| Error::Io {
                path: self.path.clone(),
                source: e,
            })?
            .len();
        if have < need {
            return Err(Error::Size {
                path: self.path.clone(),
                why: format!("file is {have} bytes but the label needs {need} ({} lines × {} samples × {} bands × {} bytes from byte offset {}): truncated or wrong label", self.lines, self.samples, self.bands, self.sample_type.bytes(), self.offset),
            });
        }
        Ok(())
    }

    /// Band `band` (0-based) of lines `first..first + count`, row-major.
    pub fn read_band(&self, band: usize, first: usize, count: usize) -> Result<Vec<f64>> {
        if band >= self.bands || first.checked_add(count).is_none_or(|e| e > self.lines) {
            return Err(Error::Size {
                path: self.path.clone(),
                why: format!(
                    "band {band}, lines {first}..{} requested from {} bands × {} lines",
                    first.saturating_add(count),
                    self.bands,
                    self.lines
                ),
            });
        }
        let f = File::open(&self.path).map_err(|e| Error::Io {
            path: self.path.clone(),
            source: e,
        })?;
        let b = self.sample_type.bytes();
        let (s, nb) = (self.samples as u64, self.bands as u64);
        let mut out = Vec::with_capacity(count * self.samples);
        let read = |off: u64, buf: &mut [u8]| {
            f.read_exact_at(buf, off).map_err(|e| Error::Io {
                path: self.path.clone(),
                source: std::io::Error::new(
                    e.kind(),
                    format!("reading {} bytes at byte offset {off}: {e}", buf.len()),
                ),
            })
        };
        match self.interleave {
            Interleave::Line | Interleave::Band => {
                let mut buf = vec![0u8; self.samples * b];
                for l in first as u64..(first + count) as u64 {
                    let idx = match self.interleave {
                        Interleave::Line => (l * nb + band as u64) * s,
                        _ => (band as u64 * self.lines as u64 + l) * s,
                    };
                    read(self.offset + idx * b as u64, &mut buf)?;
                    out.extend(buf.chunks_exact(b).map(|c| self.sample_type.decode(c)));
                }
            }
            Interleave::Sample => {
                let mut buf = vec![0u8; self.samples * self.bands * b];
                for l in first as u64..(first + count) as u64 {
                    read(self.offset + l * s * nb * b as u64, &mut buf)?;
                    out.extend(
                        buf.chunks_exact(b * self.bands)
                            .map(|c| self.sample_type.decode(&c[band * b..])),
                    );
                }
            }
        }
        Ok(out)
    }
}

/// Find `name` next to the label, matching the file name case-insensitively (PDS names are
/// upper case; archives and copies are not always); [`Error::Absent`] when it is not there.
pub fn locate(label: &Path, name: &str) -> Result<PathBuf> {
    if name.contains('/') || name.contains('\\') || name == ".." || name == "." {
        return Err(Error::invalid(
            label,
            "pointer",
            format!("file name {name:?} is not a plain file name"),
        ));
    }
    // A bare file name's parent is "": the current directory.
    let dir = match label.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let exact = dir.join(name);
    if exact.is_file() {
        return Ok(exact);
    }
    let entries = std::fs::read_dir(dir).map_err(|e| Error::Io {
        path: dir.into(),
        source: e,
    })?;
    for e in entries.flatten() {
        if e.file_name().to_string_lossy().eq_ignore_ascii_case(name) {
            return Ok(e.path());
        }
    }
    Err(Error::Absent {
        path: label.into(),
        file: name.into(),
        dir: dir.into(),
    })
}
