//! M3 solar spectrum tables (`M3{G|T}20110224_RFL_SOLAR_SPEC.TAB`): one row per band, two
//! whitespace-separated columns — wavelength (nm) and solar irradiance at 1 AU
//! (W/(m² µm)); CRLF or LF line ends.

use crate::error::{Error, Result};
use crate::m3::Mode;
use std::path::{Path, PathBuf};

#[derive(Debug, Clone)]
pub struct SolarSpectrum {
    pub path: PathBuf,
    /// (wavelength nm, irradiance W/(m² µm) at 1 AU), strictly increasing in wavelength.
    pub rows: Vec<(f64, f64)>,
}

impl SolarSpectrum {
    pub fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read(path).map_err(|e| Error::Io {
            path: path.into(),
            source: e,
        })?;
        let text = String::from_utf8(text).map_err(|e| Error::Size {
            path: path.into(),
            why: format!(
                "not text: invalid UTF-8 at byte offset {}",
                e.utf8_error().valid_up_to()
            ),
        })?;
        let mut rows: Vec<(f64, f64)> = Vec::new();
        for (k, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let bad = |why: &str| Error::invalid(path, &format!("line {}", k + 1), why.to_string());
            let mut cols = line.split_whitespace();
            let (Some(a), Some(b), None) = (cols.next(), cols.next(), cols.next()) else {
                return Err(bad(
                    "expected two columns: wavelength (nm) and irradiance (W/(m² µm))",
                ));
            };
            let (w, e): (f64, f64) = (
                a.parse().map_err(|_| bad("wavelength is not a number"))?,
                b.parse().map_err(|_| bad("irradiance is not a number"))?,
            );
            if !(w.is_finite() && e.is_finite() && e > 0.0) {
                return Err(bad(
                    "wavelength and irradiance must be finite, irradiance positive",
                ));
            }
            if rows.last().is_some_and(|&(p, _)| w <= p) {
                return Err(bad("wavelengths must increase"));
            }
            rows.push((w, e));
        }
        if rows.len() < 2 {
            return Err(Error::Size {
                path: path.into(),
                why: format!("{} rows: a spectrum needs at least 2", rows.len()),
            });
        }
        Ok(SolarSpectrum {
            path: path.into(),
            rows,
        })
    }

    /// The M3 instrument mode whose band sampling the table follows: one row per band, so 85
    /// rows are GLOBAL and 256 TARGET; any other length is told by the file name
    /// (`M3G…`/`M3T…`, any case); `None` when neither says.
    pub fn mode(&self) -> Option<Mode> {
        match self.rows.len() {
            85 => return Some(Mode::Global),
            256 => return Some(Mode::Target),
            _ => {}
        }
        let name = self
            .path
            .file_name()?
            .to_string_lossy()
            .to_ascii_uppercase();
        if name.starts_with("M3G") {
            Some(Mode::Global)
        } else if name.starts_with("M3T") {
            Some(Mode::Target)
        } else {
            None
        }
    }

    /// Irradiance at 1 AU interpolated linearly at `nm`; `None` outside the table.
    pub fn at(&self, nm: f64) -> Option<f64> {
        let k = self.rows.iter().position(|&(w, _)| w >= nm)?;
        if k == 0 {
            return (self.rows[0].0 == nm).then_some(self.rows[0].1);
        }
        let ((w0, e0), (w1, e1)) = (self.rows[k - 1], self.rows[k]);
        Some(e0 + (e1 - e0) * (nm - w0) / (w1 - w0))
    }
}

/// Bidirectional reflectance r = L·d²/E₁AU (sr⁻¹) from radiance L (W/(m² µm sr)), the Sun
/// distance d in AU (for M3: SOLAR_DISTANCE + OBS band 6) and the irradiance at 1 AU
/// (W/(m² µm)) at the band's wavelength. I/F = π·r (docs/formats.md).
pub fn reflectance(radiance: f64, sun_distance_au: f64, irradiance_1au: f64) -> f64 {
    radiance * sun_distance_au * sun_distance_au / irradiance_1au
}
