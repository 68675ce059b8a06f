//! `sfsfuse inspect PATH`: what a PDS product is — kind, mode, dimensions, bands and
//! wavelengths, geographic extent, map projection, value ranges.

use crate::error::{Error, Result};
use pds::lola::{LolaDem, Projection};
use pds::m3::Observation;
use serde::Serialize;
use std::path::Path;

#[derive(Debug, Clone, Serialize)]
pub struct Range {
    pub min: f64,
    pub max: f64,
}

impl Range {
    fn of(values: impl Iterator<Item = f64>) -> Option<Range> {
        values.filter(|v| v.is_finite()).fold(None, |r, v| match r {
            None => Some(Range { min: v, max: v }),
            Some(Range { min, max }) => Some(Range {
                min: min.min(v),
                max: max.max(v),
            }),
        })
    }
}

/// What `inspect` says of an M3 L1B observation.
#[derive(Debug, Clone, Serialize)]
pub struct M3Inspection {
    pub label: String,
    pub mode: String,
    pub lines: usize,
    pub samples: usize,
    pub bands: usize,
    pub wavelengths_nm: Vec<f64>,
    pub wavelength_source: String,
    pub solar_distance_au: f64,
    /// Longitude (east) and latitude ranges from LOC, when the LOC file is present.
    pub longitude_deg: Option<Range>,
    pub latitude_deg: Option<Range>,
    /// Why LOC could not be read, if it could not.
    pub loc_problem: Option<String>,
    /// Pixel size on the ground from LOC, metres ([`crate::ingest::ground_sample_distance`]):
    /// what `run` compares with the grid's.
    pub pixel_size_m: Option<f64>,
    /// Radiance range of the first band, W/(m² µm sr).
    pub radiance_band0: Option<Range>,
    /// Illumination from OBS, degrees, when the OBS file is present: incidence (to-Sun
    /// zenith), emission (to-M3 zenith), phase, and the Sun's azimuth (clockwise from
    /// north).
    pub incidence_deg: Option<Range>,
    pub emission_deg: Option<Range>,
    pub phase_deg: Option<Range>,
    pub sun_azimuth_deg: Option<Range>,
    /// Why OBS could not be read, if it could not.
    pub obs_problem: Option<String>,
    /// START_TIME and STOP_TIME, UTC, as the label gives them.
    pub start_time: Option<String>,
    pub stop_time: Option<String>,
    /// OBS's Sun and the label's SOLAR_DISTANCE against the ephemeris at those times
    /// ([`crate::ingest::SunCheck`]), when the label gives START_TIME (the distance alone,
    /// `pixels` 0, where LOC or OBS does not read); `run` refuses the observation beyond what
    /// it allows.
    pub sun_ephemeris: Option<crate::ingest::SunCheck>,
    /// Why `run` refuses the observation on that check, if it does
    /// ([`crate::ingest::check_sun_ephemeris`]).
    pub sun_problem: Option<String>,
    /// Detector column striping of the radiance at `column_striping_nm`, the band nearest
    /// the run's default wavelength ([`crate::striping`], on every line; what `run` measures
    /// on the reflectance and divides out with `[inputs] destripe`), and why it was not
    /// measured where it was not.
    pub column_striping_nm: Option<f64>,
    pub column_striping: Option<crate::striping::Striping>,
    pub column_striping_note: Option<String>,
    /// Whether LOC's, and OBS's, file is beside the label but cannot be read as it
    /// describes it (truncated, wrong size, a malformed object): bad input, which
    /// `sfsfuse inspect` reports by its exit status after the description. A part whose
    /// file is absent is only described as such (a download may hold the radiance alone).
    pub loc_unreadable: bool,
    pub obs_unreadable: bool,
}

/// A description of one product.
#[derive(Debug, Clone, Serialize)]
#[serde(tag = "kind")]
pub enum Inspection {
    #[serde(rename = "M3 L1B")]
    M3(Box<M3Inspection>),
    #[serde(rename = "LOLA GDR")]
    Lola {
        label: String,
        lines: usize,
        samples: usize,
        projection: String,
        map_scale_m: f64,
        radius_m: f64,
        longitude_deg: Range,
        latitude_deg: Range,
        /// Heights above the 1737.4 km sphere (DN × SCALING_FACTOR + OFFSET − 1737.4 km,
        /// `ingest::lola_heights`), metres.
        height_m: Option<Range>,
        /// Why the heights cannot be the Moon's, if they cannot (outside
        /// `ingest::LUNAR_HEIGHT_RANGE_M`; `run` refuses them).
        height_problem: Option<String>,
    },
    #[serde(rename = "GeoTIFF")]
    GeoTiff {
        path: String,
        width: usize,
        height: usize,
        crs: String,
        /// Pixel size, metres (on the Moon sphere for a geographic file).
        pixel_m: f64,
        /// GDAL geotransform: x0, dx, 0, y0, 0, −dy.
        geotransform: [f64; 6],
        nodata: Option<f64>,
        /// The GDAL metadata items (tag 42112), name and value.
        metadata: Vec<(String, String)>,
    },
}

/// The bytes that open a TIFF or BigTIFF file, either byte order.
fn is_tiff(head: &[u8]) -> bool {
    head.starts_with(b"II*\0")
        || head.starts_with(b"MM\0*")
        || head.starts_with(b"II+\0")
        || head.starts_with(b"MM\0+")
}

/// The label beside the data file `path` that points at it (case-insensitively), if any.
fn label_of(path: &Path) -> Option<std::path::PathBuf> {
    let name = path.file_name()?.to_string_lossy().to_ascii_uppercase();
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut labels: Vec<_> = std::fs::read_dir(dir)
        .ok()?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e.eq_ignore_ascii_case("lbl")))
        .collect();
    labels.sort();
    labels.into_iter().find(|l| {
        pds::read_label_bytes(l).is_ok_and(|b| {
            String::from_utf8_lossy(&b)
                .to_ascii_uppercase()
                .contains(&name)
        })
    })
}

/// The items of GDAL's metadata XML (`<Item name="N" …>V</Item>`), in order.
fn gdal_items(xml: &str) -> Vec<(String, String)> {
    xml.split("<Item ")
        .skip(1)
        .filter_map(|item| {
            let name = item.split("name=\"").nth(1)?.split('"').next()?;
            let value = item.split_once('>')?.1.split("</Item>").next()?;
            let band = item
                .split("sample=\"")
                .nth(1)
                .and_then(|v| v.split('"').next())
                .map(|b| format!(" (band {})", b.parse::<usize>().map_or(0, |b| b + 1)))
                .unwrap_or_default();
            Some((format!("{name}{band}"), value.to_string()))
        })
        .collect()
}

fn inspect_geotiff(path: &Path) -> Result<Inspection> {
    use tiff::decoder::Decoder;
    use tiff::tags::Tag;
    let dem = crate::ingest::GeoTiffDem::open(path)?;
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let metadata = Decoder::new(std::io::BufReader::new(f))
        .ok()
        .and_then(|mut d| d.get_tag_ascii_string(Tag::Unknown(42112)).ok())
        .map(|x| gdal_items(&x))
        .unwrap_or_default();
    Ok(Inspection::GeoTiff {
        path: path.display().to_string(),
        width: dem.width,
        height: dem.height,
        crs: match &dem.crs {
            crate::export::GeoTiffCrs::Projected(c) => {
                format!("{} ({})", c.name(), c.proj_string())
            }
            crate::export::GeoTiffCrs::Geographic => {
                "longitude/latitude on the Moon sphere (+proj=longlat +R=1737400)".into()
            }
        },
        pixel_m: dem.pixel_m(),
        geotransform: dem.geotransform,
        nodata: dem.nodata,
        metadata,
    })
}

/// Lines read per window when scanning a product for its value range.
const WINDOW: usize = 256;

fn scan<E>(
    lines: usize,
    mut read: impl FnMut(usize, usize) -> std::result::Result<Vec<f64>, E>,
) -> std::result::Result<Option<Range>, E> {
    let mut acc: Option<Range> = None;
    for first in (0..lines).step_by(WINDOW) {
        let r = Range::of(read(first, WINDOW.min(lines - first))?.into_iter());
        acc = match (acc, r) {
            (Some(a), Some(b)) => Some(Range {
                min: a.min.min(b.min),
                max: a.max.max(b.max),
            }),
            (a, b) => a.or(b),
        };
    }
    Ok(acc)
}

/// Describe the product at `path`: an M3 L1B or LOLA GDR label, or a GeoTIFF. A data file
/// (`.IMG`, …) is refused with the label to give instead. Only a label's bytes are read, however
/// large the file.
pub fn inspect(path: &Path) -> Result<Inspection> {
    let bytes = pds::read_label_bytes(path)?;
    if is_tiff(&bytes) {
        return inspect_geotiff(path);
    }
    let label = pds::parse_label(&bytes).map_err(|e| not_a_label(path, &bytes, e))?;
    if label.child("RDN_FILE").is_some() {
        return inspect_m3(path);
    }
    if label.find("IMAGE_MAP_PROJECTION").is_some() {
        return inspect_lola(path);
    }
    Err(Error::Usage(format!("{}: a PDS3 label, but neither an M3 L1B observation (no RDN_FILE object) nor a LOLA GDR (no IMAGE_MAP_PROJECTION)", path.display())))
}

/// Why `path`, whose first bytes are `bytes`, does not parse as a label: a data file some
/// label beside it points to (name that label), other binary data, or a label with a syntax
/// error (`e`, with its byte offset).
fn not_a_label(path: &Path, bytes: &[u8], e: pds::odl::ParseError) -> Error {
    if let Some(l) = label_of(path) {
        return Error::Usage(format!(
            "{} is a data file, not a label: inspect its label {} instead",
            path.display(),
            l.display()
        ));
    }
    let binary = bytes.iter().take(4096).any(|&b| b == 0);
    if binary {
        return Error::Usage(format!(
            "{} is neither a PDS3 label nor a GeoTIFF (binary data, and no label beside it points to it): give the product's label (.LBL) or a GeoTIFF",
            path.display()
        ));
    }
    Error::Pds(pds::Error::Label {
        path: path.into(),
        source: e,
    })
}

/// An M3 L1B observation: its mode, size, wavelengths, Sun distance, the ranges of its LOC
/// longitudes and latitudes, pixel size, first radiance band and OBS angles (what cannot be
/// read of LOC or OBS is said rather than failing the whole).
fn inspect_m3(path: &Path) -> Result<Inspection> {
    let o = Observation::open(path)?;
    let (mut lon, mut lat, mut problem, mut pixel_size_m) = (None, None, None, None);
    // A part's problem, and whether its file is there but unreadable.
    let note = |e: pds::Error| (Some(e.to_string()), !matches!(e, pds::Error::Absent { .. }));
    let (mut loc_unreadable, mut obs_unreadable) = (false, false);
    match o.part("LOC") {
        Ok(loc) => {
            lon = scan(loc.lines, |f, n| loc.read_band(0, f, n))?;
            lat = scan(loc.lines, |f, n| loc.read_band(1, f, n))?;
            pixel_size_m = crate::ingest::ground_sample_distance(&o).ok();
        }
        Err(e) => (problem, loc_unreadable) = note(e),
    }
    let rad = scan(o.rdn.lines, |f, n| o.rdn.read_band(0, f, n))?;
    let mut ill = [None, None, None, None];
    let mut obs_problem = None;
    match o.part("OBS") {
        Ok(obs) => {
            // OBS bands: 0 Sun azimuth, 1 Sun zenith, 3 M3 zenith, 4 phase.
            for (k, band) in [1, 3, 4, 0].into_iter().enumerate() {
                ill[k] = scan(obs.lines, |f, n| obs.read_band(band, f, n))?;
            }
        }
        Err(e) => (obs_problem, obs_unreadable) = note(e),
    }
    let [incidence_deg, emission_deg, phase_deg, sun_azimuth_deg] = ill;
    let sun_ephemeris = if problem.is_none() && obs_problem.is_none() {
        crate::ingest::sun_check(&o)?
    } else {
        crate::ingest::label_sun_check(&o)
    };
    let sun_problem = sun_ephemeris.and_then(|c| {
        crate::ingest::check_sun_ephemeris(&o, &c)
            .err()
            .map(|e| e.to_string())
    });
    let (column_striping_nm, column_striping, column_striping_note) = striping_of(&o)?;
    Ok(Inspection::M3(Box::new(M3Inspection {
        label: path.display().to_string(),
        mode: o.mode.keyword().into(),
        lines: o.rdn.lines,
        samples: o.rdn.samples,
        bands: o.rdn.bands,
        wavelengths_nm: o.wavelengths.clone(),
        wavelength_source: o.wavelength_source.clone(),
        solar_distance_au: o.solar_distance_au,
        longitude_deg: lon,
        latitude_deg: lat,
        loc_problem: problem,
        pixel_size_m,
        radiance_band0: rad,
        incidence_deg,
        emission_deg,
        phase_deg,
        sun_azimuth_deg,
        obs_problem,
        start_time: o.start_time.map(|t| t.to_string()),
        stop_time: o.stop_time.map(|t| t.to_string()),
        sun_ephemeris,
        sun_problem,
        column_striping_nm,
        column_striping,
        column_striping_note,
        loc_unreadable,
        obs_unreadable,
    })))
}

/// The column striping of `o`'s radiance in the band nearest the run's default wavelength
/// ([`crate::workflow::DEFAULT_WAVELENGTH_NM`]): ln L of every positive radiance, block by
/// block over every line ([`crate::striping::ColumnProfiles`]); the band's wavelength, the
/// estimate, and why there is none (the band set does not reach that wavelength, too few
/// lines).
fn striping_of(
    o: &Observation,
) -> Result<(
    Option<f64>,
    Option<crate::striping::Striping>,
    Option<String>,
)> {
    use crate::striping::{BLOCK_LINES, MIN_BLOCKS};
    let nm = crate::workflow::DEFAULT_WAVELENGTH_NM;
    let band = match o.bracket(nm) {
        Ok(b) if b.weight_upper >= 0.5 => b.upper,
        Ok(b) => b.lower,
        Err(e) => return Ok((None, None, Some(format!("not measured: {e}")))),
    };
    let mut profiles = crate::striping::ColumnProfiles::default();
    let (lines, samples) = (o.rdn.lines, o.rdn.samples);
    for first in (0..lines).step_by(WINDOW) {
        let n = WINDOW.min(lines - first);
        let v = o.rdn.read_band(band, first, n)?;
        let ln = ndarray::Array2::from_shape_vec((n, samples), v)
            .map_err(|e| Error::Usage(e.to_string()))?
            .mapv(|l| if l > 0.0 { l.ln() } else { f64::NAN });
        profiles.add_lines(ln.view());
    }
    let estimate = profiles.gains().map(|g| g.summary);
    let note = match estimate {
        Some(e) if e.blocks >= MIN_BLOCKS => None,
        _ => Some(format!(
            "not measured: {lines} lines make {} blocks of {BLOCK_LINES} with a usable column, {MIN_BLOCKS} needed",
            estimate.map_or(0, |e| e.blocks)
        )),
    };
    Ok((Some(o.wavelengths[band]), estimate, note))
}

/// Why a LOLA product's height range cannot be the Moon's: an end outside
/// [`crate::ingest::LUNAR_HEIGHT_RANGE_M`], which `run` refuses.
fn not_lunar(h: &Range) -> Option<String> {
    let [lo, hi] = crate::ingest::LUNAR_HEIGHT_RANGE_M;
    (h.min < lo || h.max > hi).then(|| {
        format!(
            "heights outside {lo} … {hi} m are not the Moon's (its surface lies within −9.1 … +10.8 km of the 1737.4 km sphere): a fill value, radii instead of heights, or a wrong SCALING_FACTOR, OFFSET or UNIT; `run` refuses such pixels"
        )
    })
}

/// A LOLA GDR: its size, projection, scale, radius and the ranges of its longitudes,
/// latitudes and heights.
fn inspect_lola(path: &Path) -> Result<Inspection> {
    let d = LolaDem::open(path)?;
    let (lines, samples) = (d.lines() as f64, d.samples() as f64);
    let (projection, lon_range, lat_range) = match d.projection {
        Projection::SimpleCylindrical {
            resolution,
            center_lon,
            ..
        } => {
            let (lon0, lat0) = d.lonlat(-0.5, -0.5);
            let (lon1, lat1) = d.lonlat(lines - 0.5, samples - 0.5);
            (
                format!("simple cylindrical, {resolution} px/deg, centre longitude {center_lon}°"),
                (lon0.min(lon1), lon0.max(lon1)),
                (lat0.min(lat1), lat0.max(lat1)),
            )
        }
        Projection::PolarStereographic { north, scale_m, .. } => {
            // Latitude runs from the pole to the farthest point of the border (a corner).
            let corners = [
                (-0.5, -0.5),
                (-0.5, samples - 0.5),
                (lines - 0.5, -0.5),
                (lines - 0.5, samples - 0.5),
            ];
            let far = corners
                .iter()
                .map(|&(l, s)| d.lonlat(l, s).1.abs())
                .fold(90.0f64, f64::min);
            let pole = if north { "north" } else { "south" };
            let lat = if north { (far, 90.0) } else { (-90.0, -far) };
            (
                format!("polar stereographic ({pole} pole), {scale_m} m/pix at the pole"),
                (0.0, 360.0),
                lat,
            )
        }
    };
    // Heights above the 1737.4 km sphere, as a run reads them.
    let heights = scan(d.lines(), |f, n| crate::ingest::lola_heights(&d, f, n))?;
    Ok(Inspection::Lola {
        label: path.display().to_string(),
        lines: d.lines(),
        samples: d.samples(),
        projection,
        map_scale_m: d.map_scale_m,
        radius_m: d.radius_m,
        longitude_deg: Range {
            min: lon_range.0,
            max: lon_range.1,
        },
        latitude_deg: Range {
            min: lat_range.0,
            max: lat_range.1,
        },
        height_problem: heights.as_ref().and_then(not_lunar),
        height_m: heights,
    })
}

impl Inspection {
    /// Why the product is bad input although it could be described: the first part whose
    /// file is present but unreadable (`None` when every part present reads).
    pub fn unreadable(&self) -> Option<String> {
        match self {
            Inspection::M3(m) => [
                (&m.loc_problem, &m.loc_unreadable),
                (&m.obs_problem, &m.obs_unreadable),
            ]
            .into_iter()
            .find_map(|(p, &bad)| p.as_ref().filter(|_| bad))
            .map(|e| {
                format!("{e} (the rest of the observation is described above; `run` refuses it)")
            })
            .or_else(|| {
                let p = m.sun_problem.as_ref()?;
                Some(format!(
                    "{p} (the observation is described above; `run` refuses it)"
                ))
            }),
            _ => None,
        }
    }

    pub fn table(&self) -> String {
        let r = |r: &Option<Range>| {
            r.as_ref()
                .map(|r| format!("{:.4} … {:.4}", r.min, r.max))
                .unwrap_or_else(|| "—".into())
        };
        match self {
            Inspection::M3(m) => {
                let M3Inspection {
                    label,
                    mode,
                    lines,
                    samples,
                    bands,
                    wavelengths_nm,
                    wavelength_source,
                    solar_distance_au,
                    longitude_deg,
                    latitude_deg,
                    loc_problem,
                    pixel_size_m,
                    radiance_band0,
                    incidence_deg,
                    emission_deg,
                    phase_deg,
                    sun_azimuth_deg,
                    obs_problem,
                    start_time,
                    stop_time,
                    sun_ephemeris,
                    column_striping_nm,
                    column_striping,
                    column_striping_note,
                    ..
                } = &**m;
                let mut s = format!("{label}\n  kind           M3 Level 1B, {mode} mode\n  size           {lines} lines × {samples} samples × {bands} bands\n");
                let wl = if wavelengths_nm.len() > 6 {
                    format!(
                        "{:.2} … {:.2} nm",
                        wavelengths_nm[0],
                        wavelengths_nm[wavelengths_nm.len() - 1]
                    )
                } else {
                    wavelengths_nm
                        .iter()
                        .map(|w| format!("{w:.2}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                        + " nm"
                };
                s += &format!("  wavelengths    {wl} ({wavelength_source})\n  Sun distance   {solar_distance_au} AU\n");
                s += &format!(
                    "  longitude      {}°E\n  latitude       {}°\n",
                    r(longitude_deg),
                    r(latitude_deg)
                );
                if let Some(p) = loc_problem {
                    s += &format!("  LOC            {p}\n");
                }
                if let Some(d) = pixel_size_m {
                    s += &format!("  pixel size     {d:.1} m (LOC: geometric mean of the median across- and along-track spacings)\n");
                }
                s += &format!("  radiance b0    {} W/(m² µm sr)\n", r(radiance_band0));
                s += &format!(
                    "  incidence      {}°\n  emission       {}°\n  phase          {}°\n  Sun azimuth    {}° (clockwise from north)\n",
                    r(incidence_deg),
                    r(emission_deg),
                    r(phase_deg),
                    r(sun_azimuth_deg)
                );
                if let Some(p) = obs_problem {
                    s += &format!("  OBS            {p}\n");
                }
                let t = |t: &Option<String>| t.clone().unwrap_or_else(|| "—".into());
                s += &format!(
                    "  time           {} … {} UTC\n",
                    t(start_time),
                    t(stop_time)
                );
                s += &match sun_ephemeris {
                    Some(c) if c.pixels == 0 => format!(
                        "  Sun vs time    the Sun {:.5} AU away (SOLAR_DISTANCE refused beyond ±{:.4} AU of it); OBS not compared (no LOC/OBS pixel read)\n",
                        c.distance_au, c.distance_allowed_au
                    ),
                    Some(c) => format!(
                        "  Sun vs time    OBS's Sun at most {:.3}° from the ephemeris's over {} px (refused above {:.2}°); the Sun {:.5} AU away (SOLAR_DISTANCE refused beyond ±{:.4} AU of it)\n",
                        c.worst_deg, c.pixels, c.allowed_deg, c.distance_au, c.distance_allowed_au
                    ),
                    None => "  Sun vs time    not checked (no START_TIME)\n".into(),
                };
                let at = column_striping_nm.map_or(String::new(), |nm| format!(" at {nm:.2} nm"));
                s += &match (column_striping, column_striping_note) {
                    (_, Some(note)) => format!("  striping       {note}\n"),
                    (Some(c), None) if c.columns == 0 => format!(
                        "  striping       none stands out between neighbouring detector columns{at} (terrain left in each column's estimate {:.2} %, {} blocks)\n",
                        100.0 * c.noise_rms, c.blocks
                    ),
                    (Some(c), None) => format!(
                        "  striping       {:.2} % RMS between neighbouring detector columns{at} (terrain left {:.2} %, {} blocks; `run` divides {} columns' gains out, {:.2} % RMS)\n",
                        100.0 * c.stripe_rms, 100.0 * c.noise_rms, c.blocks, c.columns, 100.0 * c.correction_rms
                    ),
                    (None, None) => String::new(),
                };
                s
            }
            Inspection::GeoTiff {
                path,
                width,
                height,
                crs,
                pixel_m,
                geotransform,
                nodata,
                metadata,
            } => {
                let mut s = format!(
                    "{path}\n  kind           GeoTIFF\n  size           {width} × {height} px\n  CRS            {crs}\n  pixel          {pixel_m:.3} m\n  origin         ({}, {}) (upper-left corner)\n  no-data        {}\n",
                    geotransform[0],
                    geotransform[3],
                    nodata.map_or("—".into(), |v| v.to_string())
                );
                for (k, v) in metadata {
                    s += &format!("  {k:<14} {v}\n");
                }
                s
            }
            Inspection::Lola {
                label,
                lines,
                samples,
                projection,
                map_scale_m,
                radius_m,
                longitude_deg,
                latitude_deg,
                height_m,
                height_problem,
            } => {
                let mut s = format!(
                    "{label}\n  kind           LOLA GDR DEM\n  size           {lines} lines × {samples} samples\n  projection     {projection}\n  scale          {map_scale_m} m/px on a {radius_m} m sphere\n  longitude      {:.4} … {:.4}°E\n  latitude       {:.4} … {:.4}°\n  height         {} m above the 1737.4 km sphere\n",
                    longitude_deg.min, longitude_deg.max, latitude_deg.min, latitude_deg.max, r(height_m)
                );
                if let Some(p) = height_problem {
                    s += &format!("  warning        {p}\n");
                }
                s
            }
        }
    }
}
