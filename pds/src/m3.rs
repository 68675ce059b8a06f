//! Chandrayaan-1 M3 Level 1B observations (CH1M3_0003; docs/formats.md): one detached label for
//! the radiance (RDN), location (LOC) and geometry (OBS) images, each in an `X_FILE` object
//! holding `^X_IMAGE`, `RECORD_BYTES` (one line of all bands), `FILE_RECORDS` (lines) and an
//! inner `X_IMAGE` object; all band-interleaved by line, little-endian.
//!
//! * RDN: PC_REAL 32, radiance W/(m² µm sr), 85 bands (global mode) or 256 (target mode).
//! * LOC: PC_REAL 64, bands longitude (east, °), planetocentric latitude (°), radius (m).
//! * OBS: PC_REAL 32, bands to-Sun azimuth, to-Sun zenith, to-M3 azimuth, to-M3 zenith, phase,
//!   to-Sun path length minus the scene mean (AU), to-M3 path length (m), facet slope, facet
//!   aspect, facet cos i (angles in degrees, azimuths clockwise from north).
//!
//! Band wavelengths come from the RDN ENVI header's `wavelength` list when it is next to the
//! label, else from the built-in L1B band-centre tables (data/m3_wavelengths.json, identical to
//! the real headers to 0.01 nm); a file with fewer bands than its mode holds the first ones.

use crate::error::{Error, Result};
use crate::lola::{read_label, resolve};
use crate::odl::{Label, Value};
use crate::raw::{locate, Raster};
use crate::time::UtcTime;
use std::path::{Path, PathBuf};

/// M3's two instrument modes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    Global,
    Target,
}

impl Mode {
    /// The label's INSTRUMENT_MODE_ID value for this mode.
    pub fn keyword(self) -> &'static str {
        match self {
            Mode::Global => "GLOBAL",
            Mode::Target => "TARGET",
        }
    }
}

/// Built-in band centres (nm) for a mode.
pub fn band_centres(mode: Mode) -> Vec<f64> {
    let text = include_str!("../data/m3_wavelengths.json");
    let key = match mode {
        Mode::Global => "\"GWL\"",
        Mode::Target => "\"TWL\"",
    };
    let start = text.find(key).expect("table key") + key.len();
    let open = start + text[start..].find('[').expect("table list");
    let close = open + text[open..].find(']').expect("table end");
    text[open + 1..close]
        .split(',')
        .map(|s| s.trim().parse().expect("table number"))
        .collect()
}

/// The range SOLAR_DISTANCE must lie in, AU: the Earth–Sun distance spans 0.983–1.017 AU
/// over the year and the Moon stays within 0.003 AU of the Earth, so anything outside
/// 0.97–1.03 AU is not a distance of the Moon from the Sun (and would scale every
/// reflectance by d²).
pub const SUN_DISTANCE_AU: [f64; 2] = [0.97, 1.03];

/// An opened L1B observation.
#[derive(Debug, Clone)]
pub struct Observation {
    pub label_path: PathBuf,
    pub label: Label,
    pub mode: Mode,
    /// SOLAR_DISTANCE, the scene-mean Sun distance, AU.
    pub solar_distance_au: f64,
    pub rdn: Raster,
    /// Centre wavelength (nm) of each RDN band in the file.
    pub wavelengths: Vec<f64>,
    /// Where the wavelengths came from.
    pub wavelength_source: String,
    /// START_TIME and STOP_TIME, UTC ([`time_of`]; `None` where the label has none or says
    /// N/A, UNK or NULL).
    pub start_time: Option<UtcTime>,
    pub stop_time: Option<UtcTime>,
}

/// Two bands around a wavelength and the linear weight of the second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Bracket {
    pub lower: usize,
    pub upper: usize,
    pub weight_upper: f64,
}

/// The UTC time of `keyword` in `label` (PDS3 date/time, [`UtcTime::parse`]): `None` where
/// the label has no such keyword or gives one of PDS3's missing-value constants (N/A, UNK,
/// NULL); an error naming the keyword where the value is not a time.
pub fn time_of(path: &Path, label: &Label, keyword: &str) -> Result<Option<UtcTime>> {
    let Some(v) = label.get(keyword) else {
        return Ok(None);
    };
    let text = match v.bare() {
        Value::Symbol(s) | Value::Text(s) => s.as_str(),
        other => {
            return Err(Error::invalid(
                path,
                &label.root.at(keyword),
                format!("{other:?} is not a date/time"),
            ))
        }
    };
    if ["N/A", "UNK", "NULL"]
        .iter()
        .any(|m| text.trim().eq_ignore_ascii_case(m))
    {
        return Ok(None);
    }
    UtcTime::parse(text)
        .map(Some)
        .map_err(|why| Error::invalid(path, &label.root.at(keyword), format!("{text}: {why}")))
}

impl Observation {
    /// Open the observation whose L1B label is at `path` (RDN required; LOC and OBS on demand).
    pub fn open(path: &Path) -> Result<Self> {
        let label = read_label(path)?;
        let mode = match label.get("INSTRUMENT_MODE_ID").and_then(|v| v.as_str()) {
            Some(m) if m.eq_ignore_ascii_case("GLOBAL") => Mode::Global,
            Some(m) if m.eq_ignore_ascii_case("TARGET") => Mode::Target,
            Some(m) => {
                return Err(Error::invalid(
                    path,
                    &label.root.at("INSTRUMENT_MODE_ID"),
                    format!("{m} is neither GLOBAL nor TARGET"),
                ))
            }
            None => return Err(Error::missing(path, "INSTRUMENT_MODE_ID")),
        };
        let sd = label
            .get("SOLAR_DISTANCE")
            .ok_or_else(|| Error::missing(path, "SOLAR_DISTANCE"))?;
        let solar_distance_au = sd
            .as_f64()
            .filter(|d| (SUN_DISTANCE_AU[0]..=SUN_DISTANCE_AU[1]).contains(d))
            .ok_or_else(|| {
                Error::invalid(
                    path,
                    &label.root.at("SOLAR_DISTANCE"),
                    format!(
                        "{sd} is not a Sun distance of the Moon in AU ({} to {}: the Earth's orbit spans 0.983–1.017 AU, the Moon's ±0.003 AU about it)",
                        SUN_DISTANCE_AU[0], SUN_DISTANCE_AU[1]
                    ),
                )
            })?;
        if let Some(u) = sd.unit().filter(|u| !u.eq_ignore_ascii_case("AU")) {
            return Err(Error::invalid(
                path,
                &label.root.at("SOLAR_DISTANCE"),
                format!("unit <{u}>, expected <AU>"),
            ));
        }
        let rdn = part_of(path, &label, "RDN")?;
        let (wl, src) = match envi_wavelengths(path, &label)? {
            Some(w) => w,
            None => (
                band_centres(mode),
                "built-in L1B band-centre table".to_string(),
            ),
        };
        if wl.len() < rdn.bands {
            return Err(Error::invalid(
                path,
                "RDN_IMAGE BANDS",
                format!(
                    "{} bands but only {} wavelengths are known ({src})",
                    rdn.bands,
                    wl.len()
                ),
            ));
        }
        let wavelengths = wl[..rdn.bands].to_vec();
        let start_time = time_of(path, &label, "START_TIME")?;
        let stop_time = time_of(path, &label, "STOP_TIME")?;
        Ok(Observation {
            label_path: path.into(),
            label,
            mode,
            solar_distance_au,
            rdn,
            wavelengths,
            wavelength_source: src,
            start_time,
            stop_time,
        })
    }

    /// The raster of one part (`RDN`, `LOC` or `OBS`), validated against its label and file.
    pub fn part(&self, part: &str) -> Result<Raster> {
        part_of(&self.label_path, &self.label, part)
    }

    /// The mode's full band-centre list (from the ENVI header when that was read).
    fn band_set(&self) -> Vec<f64> {
        if self.wavelength_source.starts_with("built-in") {
            band_centres(self.mode)
        } else {
            self.wavelengths.clone()
        }
    }

    /// The band nearest to `nm` in the mode's band set, refused when the file does not hold it.
    pub fn nearest_band(&self, nm: f64) -> Result<usize> {
        let table = self.band_set();
        let k = table
            .iter()
            .enumerate()
            .min_by(|a, b| (a.1 - nm).abs().total_cmp(&(b.1 - nm).abs()))
            .map(|(k, _)| k)
            .ok_or_else(|| Error::invalid(&self.label_path, "wavelength", "no bands"))?;
        if k >= self.rdn.bands {
            return Err(Error::invalid(&self.label_path, "RDN_IMAGE BANDS", format!("the band nearest {nm} nm is band {k} ({} nm), but this file holds only the first {} bands", table[k], self.rdn.bands)));
        }
        Ok(k)
    }

    /// The two bands around `nm` in the mode's band set, with the linear weight of the upper.
    pub fn bracket(&self, nm: f64) -> Result<Bracket> {
        let table = self.band_set();
        let upper = table
            .iter()
            .position(|&w| w >= nm)
            .filter(|&u| u > 0)
            .ok_or_else(|| {
                Error::invalid(
                    &self.label_path,
                    "wavelength",
                    format!("{nm} nm is outside the band set"),
                )
            })?;
        if upper >= self.rdn.bands {
            return Err(Error::invalid(&self.label_path, "RDN_IMAGE BANDS", format!("{nm} nm lies between bands {} and {upper}, but this file holds only the first {} bands", upper - 1, self.rdn.bands)));
        }
        let (a, b) = (table[upper - 1], table[upper]);
        Ok(Bracket {
            lower: upper - 1,
            upper,
            weight_upper: (nm - a) / (b - a),
        })
    }
}

/// The raster of one part of an observation, validated against its label and file:
/// RECORD_BYTES = LINE_SAMPLES × BANDS × bytes, FILE_RECORDS = LINES, file length =
/// RECORD_BYTES × FILE_RECORDS.
fn part_of(path: &Path, label: &Label, part: &str) -> Result<Raster> {
    let file_obj = format!("{part}_FILE");
    let img_obj = format!("{part}_IMAGE");
    let holder = label
        .child(&file_obj)
        .ok_or_else(|| Error::missing(path, &format!("OBJECT = {file_obj}")))?;
    let image = holder
        .child(&img_obj)
        .ok_or_else(|| Error::missing(path, &format!("OBJECT = {img_obj} in {file_obj}")))?;
    let count = |key: &str| -> Result<i64> {
        let v = holder
            .get(key)
            .ok_or_else(|| Error::missing(path, &format!("{key} in {file_obj}")))?;
        match v.as_i64() {
            Some(n) if n >= 1 => Ok(n),
            _ => Err(Error::invalid(
                path,
                &format!("{} in {file_obj}", holder.at(key)),
                format!("{v} is not a positive integer"),
            )),
        }
    };
    let record_bytes = count("RECORD_BYTES")?;
    let records = count("FILE_RECORDS")?;
    let (data, offset) = resolve(path, holder, &img_obj, Some(record_bytes.max(0) as u64))?;
    let r = Raster::from_object(path, image, data, offset)?;
    let line_bytes = (r.samples * r.bands * r.sample_type.bytes()) as i64;
    if record_bytes != line_bytes {
        return Err(Error::invalid(
            path,
            &format!("RECORD_BYTES in {file_obj}"),
            format!(
                "{record_bytes}, but one line of {} samples × {} bands is {line_bytes} bytes",
                r.samples, r.bands
            ),
        ));
    }
    if records != r.lines as i64 {
        return Err(Error::invalid(
            path,
            &format!("FILE_RECORDS in {file_obj}"),
            format!("{records}, but LINES = {}", r.lines),
        ));
    }
    let len = std::fs::metadata(&r.path)
        .map_err(|e| Error::Io {
            path: r.path.clone(),
            source: e,
        })?
        .len();
    let want = record_bytes as u64 * records as u64 + offset;
    if len != want {
        return Err(Error::Size {
            path: r.path.clone(),
            why: format!("file is {len} bytes, RECORD_BYTES × FILE_RECORDS = {want}"),
        });
    }
    Ok(r)
}

/// `wavelength = { … }` from the RDN ENVI header next to the label, if present.
fn envi_wavelengths(label_path: &Path, label: &Label) -> Result<Option<(Vec<f64>, String)>> {
    let Some(holder) = label.child("RDN_HDR_FILE") else {
        return Ok(None);
    };
    let Some(Ok(crate::odl::Pointer::File(name))) = holder.pointer("RDN_ENVI_HEADER") else {
        return Ok(None);
    };
    let Ok(hdr) = locate(label_path, &name) else {
        return Ok(None);
    };
    let text = std::fs::read_to_string(&hdr).map_err(|e| Error::Io {
        path: hdr.clone(),
        source: e,
    })?;
    let Some(list) = crate::envi::list(&text, "wavelength") else {
        return Ok(None);
    };
    let wl = list
        .iter()
        .map(|s| s.parse::<f64>())
        .collect::<std::result::Result<Vec<_>, _>>()
        .map_err(|_| Error::invalid(&hdr, "wavelength", "not a list of numbers"))?;
    Ok(Some((wl, hdr.display().to_string())))
}
