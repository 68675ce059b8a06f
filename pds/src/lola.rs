//! LRO LOLA GDR DEMs (LRO-L-LOLA-4-GDR): `LDEM_*` labels with an `^IMAGE` pointer, an `IMAGE`
//! object and an `IMAGE_MAP_PROJECTION` (docs/formats.md).
//!
//! Height above the reference sphere = DN × SCALING_FACTOR (in the IMAGE's UNIT, converted to
//! metres); radius = that + OFFSET, the reference sphere's radius (1737.4 km in every LOLA
//! GDR).
//! Simple cylindrical pixel centres, 1-based LINE/SAMPLE (DSMAP.CAT):
//! lon = CENTER_LONGITUDE + (SAMPLE − SAMPLE_PROJECTION_OFFSET − 1)/MAP_RESOLUTION,
//! lat = CENTER_LATITUDE − (LINE − LINE_PROJECTION_OFFSET − 1)/MAP_RESOLUTION.
//! Polar stereographic (DSMAP_POLAR.CAT), sphere R = A_AXIS_RADIUS, 1-based I = SAMPLE,
//! J = LINE: X = (I − SAMPLE_PROJECTION_OFFSET − 1)·MAP_SCALE, Y = (J − LINE_PROJECTION_OFFSET − 1)·MAP_SCALE
//! (the catalogue writes the offsets as N/2 − 0.5), r = √(X² + Y²),
//! lat = ±(90° − 2·atan(r / 2R)). Longitude follows the catalogue's prose, which every revision
//! keeps: "in the north, longitude 0 extends straight down from the centre and 90° E to the
//! right; in the south, longitude 0 extends straight up and 90° E to the right". With J growing
//! downwards that is lon = atan2(X, Y) in the north and atan2(X, −Y) in the south — the
//! revisions' formulas disagree with each other, the prose does not. It is PROJ's
//! `+proj=stere +lat_0=±90 +lon_0=0 +k=1` with map x = X, map y = −Y (IAU_2015:30130/30135).
//! This API is 0-based: line = LINE − 1, sample = SAMPLE − 1.

use crate::error::{Error, Result};
use crate::odl::{parse_label, Label, Object, Pointer};
use crate::raw::{locate, Raster};
use std::path::{Path, PathBuf};

/// The map projection of a GDR product.
#[derive(Debug, Clone, PartialEq)]
pub enum Projection {
    SimpleCylindrical {
        /// Pixels per degree.
        resolution: f64,
        center_lat: f64,
        center_lon: f64,
        line_offset: f64,
        sample_offset: f64,
    },
    /// Polar stereographic on the sphere of radius `radius_m`, true scale at the pole.
    PolarStereographic {
        /// True for the north pole (CENTER_LATITUDE = 90), false for the south (−90).
        north: bool,
        /// Metres per pixel at the pole (MAP_SCALE, exact).
        scale_m: f64,
        line_offset: f64,
        sample_offset: f64,
        radius_m: f64,
    },
}

/// An opened LOLA GDR DEM.
#[derive(Debug, Clone)]
pub struct LolaDem {
    pub label_path: PathBuf,
    pub label: Label,
    pub raster: Raster,
    /// Metres per DN: SCALING_FACTOR × the IMAGE UNIT in metres (METER or KILOMETER; absent
    /// = METER).
    pub scaling_factor: f64,
    /// Reference radius (OFFSET), converted to metres: radius = DN × [`Self::scaling_factor`] +
    /// OFFSET. `None` when the label gives none.
    pub offset: Option<f64>,
    pub projection: Projection,
    /// MAP_SCALE in metres per pixel, whatever unit the label used.
    pub map_scale_m: f64,
    /// A_AXIS_RADIUS in metres.
    pub radius_m: f64,
}

fn number(path: &Path, obj: &Object, key: &str) -> Result<f64> {
    optional_number(path, obj, key)?.ok_or_else(|| Error::missing(path, key))
}

/// `key (line N)` for messages, where the keyword is in `obj`.
fn at(obj: &Object, key: &str) -> String {
    obj.at(key)
}

/// A numeric keyword that may be absent; present, it must be a finite number.
fn optional_number(path: &Path, obj: &Object, key: &str) -> Result<Option<f64>> {
    let Some(v) = obj.get(key) else {
        return Ok(None);
    };
    match v.as_f64() {
        Some(x) if x.is_finite() => Ok(Some(x)),
        _ => Err(Error::invalid(
            path,
            &at(obj, key),
            format!("{v} is not a finite number"),
        )),
    }
}

/// `value` of `key` in `obj` must lie within `lo..=hi` (`what` says why).
fn within(
    path: &Path,
    obj: &Object,
    key: &str,
    value: f64,
    lo: f64,
    hi: f64,
    what: &str,
) -> Result<f64> {
    if (lo..=hi).contains(&value) {
        Ok(value)
    } else {
        Err(Error::invalid(
            path,
            &at(obj, key),
            format!("{value} is outside {lo}..{hi}: {what}"),
        ))
    }
}

/// Largest |LINE/SAMPLE_PROJECTION_OFFSET| accepted, pixels: a global 1024 px/deg product is
/// 368 640 samples wide; offsets beyond a few million pixels describe no lunar product.
const MAX_PROJECTION_OFFSET: f64 = 1e7;

/// A LINE/SAMPLE_PROJECTION_OFFSET within ±[`MAX_PROJECTION_OFFSET`].
fn projection_offset(path: &Path, map: &Object, key: &str) -> Result<f64> {
    let v = number(path, map, key)?;
    within(
        path,
        map,
        key,
        v,
        -MAX_PROJECTION_OFFSET,
        MAX_PROJECTION_OFFSET,
        "no lunar product is that large",
    )
}

/// `value` must be a positive, finite number; the error names the keyword and the value.
fn positive(path: &Path, key: &str, value: f64, unit: &str) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(
            path,
            key,
            format!("{value}{unit} must be positive"),
        ))
    }
}

/// Convert a length with unit (km or m; none = `default_unit`) to metres.
fn metres(path: &Path, obj: &Object, key: &str, default_unit: &str) -> Result<f64> {
    let v = obj.get(key).ok_or_else(|| Error::missing(path, key))?;
    let x = v
        .as_f64()
        .ok_or_else(|| Error::invalid(path, key, format!("{v} is not a number")))?;
    let unit = v.unit().unwrap_or(default_unit).to_ascii_lowercase();
    match unit.split('/').next().unwrap_or("") {
        "km" => Ok(x * 1000.0),
        "m" | "meter" | "meters" | "metre" => Ok(x),
        other => Err(Error::invalid(
            path,
            key,
            format!("unit <{other}> is not a length"),
        )),
    }
}

/// Resolve a pointer in `obj` to (file, byte offset); `record_bytes` from the enclosing file object.
pub(crate) fn resolve(
    label_path: &Path,
    obj: &Object,
    name: &str,
    record_bytes: Option<u64>,
) -> Result<(PathBuf, u64)> {
    let p = obj
        .pointer(name)
        .ok_or_else(|| Error::missing(label_path, &format!("^{name}")))?;
    let p = p.map_err(|why| Error::invalid(label_path, &format!("^{name}"), why))?;
    let rec = |n: u64| -> Result<u64> {
        if n == 0 {
            return Err(Error::invalid(
                label_path,
                &format!("^{name}"),
                "record 0: records count from 1",
            ));
        }
        let rb = record_bytes.ok_or_else(|| {
            Error::missing(label_path, "RECORD_BYTES (needed by a record pointer)")
        })?;
        Ok((n - 1).saturating_mul(rb))
    };
    let byte = |n: u64| -> Result<u64> {
        n.checked_sub(1).ok_or_else(|| {
            Error::invalid(
                label_path,
                &format!("^{name}"),
                "byte 0: byte offsets count from 1",
            )
        })
    };
    Ok(match p {
        Pointer::File(f) => (locate(label_path, &f)?, 0),
        Pointer::FileRecord(f, n) => (locate(label_path, &f)?, rec(n)?),
        Pointer::FileBytes(f, n) => (locate(label_path, &f)?, byte(n)?),
        Pointer::Record(n) => (label_path.to_path_buf(), rec(n)?),
        Pointer::Bytes(n) => (label_path.to_path_buf(), byte(n)?),
    })
}

/// The head of the file at `path` where a PDS3 label can be: at most
/// [`crate::odl::MAX_LABEL_BYTES`] + 1 bytes, so that reading the label attached to a
/// multi-gigabyte product costs only the label.
pub fn read_label_bytes(path: &Path) -> Result<Vec<u8>> {
    use std::io::Read;
    let io = |e| Error::Io {
        path: path.into(),
        source: e,
    };
    let f = std::fs::File::open(path).map_err(io)?;
    let mut bytes = Vec::new();
    f.take(crate::odl::MAX_LABEL_BYTES as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    Ok(bytes)
}

/// Read and parse the PDS3 label at `path` (detached, or attached at the head of a product).
pub fn read_label(path: &Path) -> Result<Label> {
    let bytes = read_label_bytes(path)?;
    parse_label(&bytes).map_err(|e| Error::Label {
        path: path.into(),
        source: e,
    })
}

/// `RECORD_BYTES` of the object holding the image (absent: `None`); present, a whole number
/// of bytes ≥ 1.
fn record_bytes(path: &Path, holder: &Object) -> Result<Option<u64>> {
    match optional_number(path, holder, "RECORD_BYTES")? {
        None => Ok(None),
        Some(r) if r >= 1.0 && r.fract() == 0.0 => Ok(Some(r as u64)),
        Some(r) => Err(Error::invalid(
            path,
            &at(holder, "RECORD_BYTES"),
            format!("{r} must be a whole number of bytes ≥ 1"),
        )),
    }
}

/// The IMAGE object's DN → radius in metres, as (factor, offset): radius = DN·factor + offset,
/// from `SCALING_FACTOR` (absent: DN are heights; present, not 0), `OFFSET` (absent: `None`) and
/// `UNIT` (the `*_FLOAT` products are in kilometres, the integer ones in metres; absent:
/// metres). A unit this reader does not know is refused rather than taken as metres.
fn height_scale(path: &Path, image: &Object) -> Result<(f64, Option<f64>)> {
    let scaling_factor = optional_number(path, image, "SCALING_FACTOR")?.unwrap_or(1.0);
    if scaling_factor == 0.0 {
        return Err(Error::invalid(
            path,
            &at(image, "SCALING_FACTOR"),
            "0 would make every height 0",
        ));
    }
    let unit = image
        .get("UNIT")
        .and_then(|v| v.as_str())
        .unwrap_or("METER");
    let unit_m = match unit.to_ascii_uppercase().as_str() {
        "METER" | "METERS" | "METRE" | "METRES" | "M" => 1.0,
        "KILOMETER" | "KILOMETERS" | "KILOMETRE" | "KILOMETRES" | "KM" => 1000.0,
        other => {
            return Err(Error::invalid(
                path,
                "UNIT",
                format!("{other} is not a length unit this reader knows"),
            ))
        }
    };
    let offset = optional_number(path, image, "OFFSET")?.map(|o| o * unit_m);
    Ok((scaling_factor * unit_m, offset))
}

/// A simple cylindrical (equirectangular) map: `MAP_RESOLUTION` px/deg and the scale positive,
/// the standard parallel `CENTER_LATITUDE` not a pole, `CENTER_LONGITUDE` within ±360°, and
/// the projection offsets. With the standard parallel at the equator, MAP_SCALE must be the
/// equator's degree over MAP_RESOLUTION, 2π·A_AXIS_RADIUS/360/MAP_RESOLUTION, within 1 %
/// (the label says the same thing twice; a radius or resolution that disagrees is not this
/// product's).
fn simple_cylindrical(
    path: &Path,
    map: &Object,
    map_scale_m: f64,
    radius_m: f64,
) -> Result<Projection> {
    let resolution = number(path, map, "MAP_RESOLUTION")?;
    positive(path, "MAP_RESOLUTION", resolution, "")?;
    positive(path, "MAP_SCALE", map_scale_m, " m/pix")?;
    let lat = number(path, map, "CENTER_LATITUDE")?;
    let equator = 2.0 * std::f64::consts::PI * radius_m / 360.0 / resolution;
    if lat == 0.0 && (map_scale_m / equator - 1.0).abs() > 0.01 {
        return Err(Error::invalid(
            path,
            &at(map, "MAP_SCALE"),
            format!("{map_scale_m} m/pix disagrees with A_AXIS_RADIUS = {radius_m} m and MAP_RESOLUTION = {resolution} px/deg, which make {equator:.2} m/pix at the equator: one of the three is wrong"),
        ));
    }
    let center_lat = within(
        path,
        map,
        "CENTER_LATITUDE",
        lat,
        -89.999,
        89.999,
        "a simple cylindrical projection's standard parallel cannot be a pole",
    )?;
    let lon = number(path, map, "CENTER_LONGITUDE")?;
    let center_lon = within(
        path,
        map,
        "CENTER_LONGITUDE",
        lon,
        -360.0,
        360.0,
        "longitudes are degrees",
    )?;
    Ok(Projection::SimpleCylindrical {
        resolution,
        center_lat,
        center_lon,
        line_offset: projection_offset(path, map, "LINE_PROJECTION_OFFSET")?,
        sample_offset: projection_offset(path, map, "SAMPLE_PROJECTION_OFFSET")?,
    })
}

/// A polar stereographic map: centred on ±90° (which pole), longitude 0 on the vertical axis
/// as LOLA's polar products have it, the scale positive, and the projection offsets.
fn polar_stereographic(
    path: &Path,
    map: &Object,
    map_scale_m: f64,
    radius_m: f64,
) -> Result<Projection> {
    let center_lat = number(path, map, "CENTER_LATITUDE")?;
    let north = if center_lat == 90.0 {
        true
    } else if center_lat == -90.0 {
        false
    } else {
        return Err(Error::invalid(
            path,
            "CENTER_LATITUDE",
            format!("{center_lat}: a polar stereographic product is centred on ±90"),
        ));
    };
    let center_lon = number(path, map, "CENTER_LONGITUDE")?;
    if center_lon.rem_euclid(360.0) != 0.0 {
        return Err(Error::invalid(
            path,
            "CENTER_LONGITUDE",
            format!("{center_lon}: LOLA polar products have longitude 0 on the vertical axis; other orientations are not supported"),
        ));
    }
    positive(path, "MAP_SCALE", map_scale_m, " m/pix")?;
    Ok(Projection::PolarStereographic {
        north,
        scale_m: map_scale_m,
        line_offset: projection_offset(path, map, "LINE_PROJECTION_OFFSET")?,
        sample_offset: projection_offset(path, map, "SAMPLE_PROJECTION_OFFSET")?,
        radius_m,
    })
}

impl LolaDem {
    /// Open the product described by the label at `path` (detached or attached).
    pub fn open(path: &Path) -> Result<Self> {
        let label = read_label(path)?;
        let holder = label.child("UNCOMPRESSED_FILE").unwrap_or(&label.root);
        let record_bytes = record_bytes(path, holder)?;
        let (data, offset) = resolve(path, holder, "IMAGE", record_bytes)?;
        let image = holder
            .child("IMAGE")
            .ok_or_else(|| Error::missing(path, "OBJECT = IMAGE"))?;
        let raster = Raster::from_object(path, image, data, offset)?;
        let (scaling_factor, ref_offset) = height_scale(path, image)?;
        let map = label
            .find("IMAGE_MAP_PROJECTION")
            .ok_or_else(|| Error::missing(path, "OBJECT = IMAGE_MAP_PROJECTION"))?;
        let kind = map
            .get("MAP_PROJECTION_TYPE")
            .and_then(|v| v.as_str())
            .ok_or_else(|| Error::missing(path, "MAP_PROJECTION_TYPE"))?;
        let map_scale_m = metres(path, map, "MAP_SCALE", "km/pix")?;
        let radius_m = metres(path, map, "A_AXIS_RADIUS", "km")?;
        let projection = if kind.eq_ignore_ascii_case("SIMPLE CYLINDRICAL")
            || kind.eq_ignore_ascii_case("EQUIRECTANGULAR")
        {
            simple_cylindrical(path, map, map_scale_m, radius_m)?
        } else if kind.eq_ignore_ascii_case("POLAR STEREOGRAPHIC") {
            polar_stereographic(path, map, map_scale_m, radius_m)?
        } else {
            return Err(Error::invalid(
                path,
                "MAP_PROJECTION_TYPE",
                format!("{kind} is not supported (simple cylindrical and polar stereographic are)"),
            ));
        };
        positive(path, "A_AXIS_RADIUS", radius_m, " m")?;
        let dem = LolaDem {
            label_path: path.into(),
            map_scale_m,
            radius_m,
            label,
            raster,
            scaling_factor,
            offset: ref_offset,
            projection,
        };
        dem.check_extent()?;
        Ok(dem)
    }

    /// A simple cylindrical product's edges from its projection (the outer edges of its
    /// first and last lines and samples) must be those its label states, where it states
    /// them (MAXIMUM_LATITUDE, MINIMUM_LATITUDE, WESTERNMOST_LONGITUDE, EASTERNMOST_LONGITUDE;
    /// longitudes modulo 360°), within 0.75 pixel: a CENTER_LONGITUDE, projection offset or
    /// MAP_RESOLUTION off by a pixel or more places every height elsewhere.
    fn check_extent(&self) -> Result<()> {
        let Projection::SimpleCylindrical { resolution, .. } = self.projection else {
            return Ok(());
        };
        let Some(map) = self.label.find("IMAGE_MAP_PROJECTION") else {
            return Ok(());
        };
        let (lines, samples) = (self.lines() as f64, self.samples() as f64);
        // lonlat takes 0-based centres: the outer edges are at −0.5 and n − 0.5.
        let (west, north) = self.lonlat(-0.5, -0.5);
        let (east, south) = self.lonlat(lines - 0.5, samples - 0.5);
        let tolerance = 0.75 / resolution;
        // (keyword, the edge the projection places, whether it is a longitude: modulo 360°)
        let edges = [
            ("MAXIMUM_LATITUDE", north, false),
            ("MINIMUM_LATITUDE", south, false),
            ("WESTERNMOST_LONGITUDE", west, true),
            ("EASTERNMOST_LONGITUDE", east, true),
        ];
        for (key, edge, longitude) in edges {
            if let Some(stated) = optional_number(&self.label_path, map, key)? {
                let diff = if longitude {
                    ((edge - stated + 180.0).rem_euclid(360.0) - 180.0).abs()
                } else {
                    (edge - stated).abs()
                };
                if diff > tolerance {
                    return Err(Error::invalid(
                        &self.label_path,
                        &at(map, key),
                        format!("{stated}° is not the product's edge, {edge:.4}°, that CENTER_LATITUDE, CENTER_LONGITUDE, MAP_RESOLUTION and the LINE/SAMPLE_PROJECTION_OFFSETs place for its {lines} lines × {samples} samples: one of them is wrong"),
                    ));
                }
            }
        }
        Ok(())
    }

    pub fn lines(&self) -> usize {
        self.raster.lines
    }
    pub fn samples(&self) -> usize {
        self.raster.samples
    }

    /// Raw DNs of lines `first..first + count`.
    pub fn read_dn(&self, first: usize, count: usize) -> Result<Vec<f64>> {
        self.raster.read_band(0, first, count)
    }

    /// Heights above the reference sphere of radius [`Self::offset`] (DN × SCALING_FACTOR), metres.
    pub fn read_heights(&self, first: usize, count: usize) -> Result<Vec<f64>> {
        Ok(self
            .read_dn(first, count)?
            .into_iter()
            .map(|d| d * self.scaling_factor)
            .collect())
    }

    /// (east longitude, latitude) in degrees of the centre of 0-based pixel (line, sample);
    /// fractional positions are points inside the pixel grid.
    pub fn lonlat(&self, line: f64, sample: f64) -> (f64, f64) {
        match self.projection {
            Projection::SimpleCylindrical {
                resolution,
                center_lat,
                center_lon,
                line_offset,
                sample_offset,
            } => (
                center_lon + (sample - sample_offset) / resolution,
                center_lat - (line - line_offset) / resolution,
            ),
            Projection::PolarStereographic {
                north,
                scale_m,
                line_offset,
                sample_offset,
                radius_m,
            } => {
                let x = (sample - sample_offset) * scale_m;
                let y = (line - line_offset) * scale_m;
                let colat = 2.0 * (0.5 * x.hypot(y) / radius_m).atan().to_degrees();
                if north {
                    (x.atan2(y).to_degrees().rem_euclid(360.0), 90.0 - colat)
                } else {
                    (x.atan2(-y).to_degrees().rem_euclid(360.0), colat - 90.0)
                }
            }
        }
    }

    /// Fractional 0-based (line, sample) of a longitude (east, any range) and latitude.
    pub fn pixel(&self, lon: f64, lat: f64) -> (f64, f64) {
        match self.projection {
            Projection::SimpleCylindrical {
                resolution,
                center_lat,
                center_lon,
                line_offset,
                sample_offset,
            } => {
                let line = line_offset + (center_lat - lat) * resolution;
                // Longitude is periodic: the 360° turn in [−0.5, 360·res − 0.5) contains the
                // whole product (it spans at most one turn).
                let turn = 360.0 * resolution;
                let sample = sample_offset + (lon - center_lon) * resolution;
                let sample = (sample + 0.5).rem_euclid(turn) - 0.5;
                (line, sample)
            }
            Projection::PolarStereographic {
                north,
                scale_m,
                line_offset,
                sample_offset,
                radius_m,
            } => {
                let colat = if north { 90.0 - lat } else { lat + 90.0 };
                let r = 2.0 * radius_m * (0.5 * colat.to_radians()).tan();
                let (s, c) = lon.to_radians().sin_cos();
                let (x, y) = if north {
                    (r * s, r * c)
                } else {
                    (r * s, -r * c)
                };
                (line_offset + y / scale_m, sample_offset + x / scale_m)
            }
        }
    }
}
