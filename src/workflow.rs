//! Workflow files (TOML): what a run reads, where on the Moon, on which grid, with which
//! photometric model and solver parameters, how it is tiled, and what it writes. The schema is
//! documented in docs/workflows.md; examples are in `workflows/`.
//!
//! Every table refuses unknown keys (a typo is an error naming the key, never a silently
//! ignored setting). Relative paths resolve against the workflow file's directory.
//! [`Workflow::load`] returns the workflow with every default made explicit, which is what
//! the run record stores.

use crate::error::{Error, Result};
use crate::fusion::FusionParams;
use crate::grid::{Crs, Interpolation, LonLatBox};
use crate::photometry::{Hapke, ModelSpec};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A workflow: an orbital run (M3 + LOLA) or a laboratory run (image + range scan).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Workflow {
    Orbital(Box<Orbital>),
    Lab(Box<Lab>),
}

/// M3 L1B observations and LOLA GDR DEMs fused on a lunar grid, tile by tile.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Orbital {
    /// The file's `kind = "orbital"`, read when the struct is parsed on its own (so that TOML
    /// errors keep their line); [`Workflow`]'s tag carries it otherwise.
    #[serde(default, skip_serializing)]
    pub kind: Option<String>,
    pub inputs: OrbitalInputs,
    /// Absent: the whole swath of the first observation.
    #[serde(default)]
    pub region: Option<Region>,
    #[serde(default)]
    pub grid: GridSpec,
    #[serde(default = "default_model")]
    pub photometry: ModelSpec,
    #[serde(default)]
    pub solver: FusionParams,
    #[serde(default)]
    pub tiling: Tiling,
    pub output: Output,
    /// Products to fetch from the PDS before the run (skipped when already present).
    #[serde(default)]
    pub fetch: Option<FetchSpec>,
    /// Whether `[solver] sigma_dem` was given. Absent, the run sets σ_DEM from the input DEM's
    /// effective resolution ([`crate::fusion::dem_sigma`]); the plan and run keys include this flag.
    #[serde(skip)]
    pub sigma_dem_given: bool,
    /// Whether `[solver] dem_track_weight` was given. Absent, the plan keeps the default only
    /// where the DEM is a gridded LOLA product whose tracks run along the grid's columns
    /// (`pipeline::plan::track_weight`); the plan and run keys include this flag.
    #[serde(skip)]
    pub dem_track_weight_given: bool,
    /// Whether `[solver] multi_delta_factor_high_sun_east_west` was given. Absent, the plan
    /// keeps the default only where no observation shows detector column striping
    /// (`pipeline::plan::high_sun_east_west`); the plan and run keys include this flag.
    #[serde(skip)]
    pub high_sun_east_west_given: bool,
}

/// `[fetch]`: what `sfsfuse run` downloads first (docs/fetch.md).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FetchSpec {
    /// Where the products go; `[inputs]` names files in it.
    pub directory: PathBuf,
    /// Product IDs, as for `sfsfuse fetch`.
    pub products: Vec<String>,
    /// Archive base URLs, checksum manifests, retries, time-out.
    #[serde(default)]
    pub sources: crate::fetch::archive::Sources,
}

fn default_model() -> ModelSpec {
    ModelSpec::Hapke(Hapke::moon())
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OrbitalInputs {
    /// M3 L1B labels (`*_L1B.LBL`). Where several cover a pixel, all of them are fused, each
    /// with its own geometry, shadows, weight and radiometric gain (docs/science.md, "Several
    /// observations"); the first listed is the gains' reference.
    pub m3: Vec<PathBuf>,
    /// DEMs: LOLA GDR labels (`LDEM_*.LBL`), or GeoTIFFs (`.tif`) of heights in metres above
    /// the 1737.4 km sphere on the Moon sphere CRS (docs/workflows.md). Where several cover a
    /// pixel, the first listed is used.
    pub lola: Vec<PathBuf>,
    /// M3 solar spectrum table (`M3G20110224_RFL_SOLAR_SPEC.TAB` for global mode), or a list
    /// of one per instrument mode where GLOBAL and TARGET observations are mixed
    /// (`["…/M3G20110224_RFL_SOLAR_SPEC.TAB", "…/M3T20110224_RFL_SOLAR_SPEC.TAB"]`): each
    /// observation takes the table of its INSTRUMENT_MODE_ID.
    #[serde(
        deserialize_with = "one_or_more_paths",
        serialize_with = "one_or_more_paths_out"
    )]
    pub solar_spectrum: Vec<PathBuf>,
    /// Wavelength of the reflectance used for shape from shading, nm (bands are blended
    /// linearly to reach it).
    #[serde(default = "default_wavelength")]
    pub wavelength_nm: f64,
    /// σ, in grid pixels, of the input DEM's point spread relative to the grid. Absent:
    /// [`crate::fusion::dem_psf_sigma`] of the first DEM's effective resolution over the grid's
    /// (docs/science.md, "The DEM's effective resolution").
    #[serde(default)]
    pub dem_psf_sigma_px: Option<f64>,
    /// The first DEM's effective resolution, metres: the spacing of the independent heights
    /// behind it. Absent: its pixel size, or for a LOLA-only GDR the larger of that and the
    /// ground-track gap at the region's latitude (docs/science.md).
    #[serde(default)]
    pub dem_resolution_m: Option<f64>,
    /// At most this many observations per pixel, the best by weight × emission cosine
    /// (absent or 0: all of them).
    #[serde(default)]
    pub max_observations_per_pixel: usize,
    /// Pixels whose Sun is closer to the zenith than this are not used, degrees (default 0).
    #[serde(default)]
    pub min_incidence_deg: Option<f64>,
    /// Pixels whose Sun is lower than this are not used, degrees (default 90: the horizon);
    /// weights fade over the 10° before it.
    #[serde(default)]
    pub max_incidence_deg: Option<f64>,
    /// Register each observation ([`crate::registration`]): estimate its displacement in the
    /// plan, against the DEM's shading or an earlier observation it overlaps, and move it back
    /// where that is long enough (`register_min_px`; default true; false: neither estimated
    /// nor applied).
    #[serde(default = "default_true")]
    pub register: bool,
    /// The displacement against the DEM's shading, grid pixels, from which the plan applies
    /// it, when the correlation at its peak reaches
    /// [`crate::registration::APPLY_CORRELATION`]. Default: twice the longest bias such an
    /// estimate showed on undisplaced synthetic scenes under a Sun as high as the
    /// observation's mean Sun on the estimate's window, and longer for a DEM coarser than those scenes', at least 1.25 px
    /// ([`crate::registration::dem_apply_px`]; with LDEM_64 under a 140 m grid 1.25 px under
    /// Suns 13–40° high, 1.5 px at 10°, 2.8 px at 60°; docs/science.md "Registration").
    /// Estimates relative to another observation follow their own rule
    /// ([`crate::registration::relative_apply_px`]).
    #[serde(default)]
    pub register_min_px: Option<f64>,
    /// How far the displacement is searched, grid pixels in each axis (default 16).
    #[serde(default = "default_register_search_px")]
    pub register_search_px: usize,
    /// Estimate, besides each observation's gain, a trend of it along the track
    /// ([`crate::fusion::gains::GainTrend`]) where observations overlap over
    /// [`crate::fusion::gains::MIN_TREND_LINES`] lines or more, and divide the image by
    /// it at every ingest (default true; false: one gain per observation; docs/science.md,
    /// "Several observations").
    #[serde(default = "default_true")]
    pub gain_trend: bool,
    /// Refuse an observation whose OBS Sun lies more than
    /// [`crate::ingest::MAX_SUN_EPHEMERIS_DEG`] from where the Sun stood at its label's
    /// START_TIME–STOP_TIME, or whose SOLAR_DISTANCE is more than
    /// [`crate::ingest::MAX_SOLAR_DISTANCE_OFF_AU`] from the Moon's distance from the Sun
    /// then ([`crate::ingest::check_sun_ephemeris`]; default true; labels
    /// without START_TIME, as `synth`'s, are not checked). False only for simulated products
    /// whose labels keep a real observation's times.
    #[serde(default = "default_true")]
    pub check_sun_ephemeris: bool,
    /// Divide each observation's radiance by its detector columns' relative gains, estimated
    /// over the whole swath ([`crate::striping`]; default true). The estimate shrinks towards
    /// no correction where the terrain, not a stripe, explains a column's difference, so
    /// images without striping are left as they are. False to use the radiance as
    /// calibrated; run.json records the estimate either way.
    #[serde(default = "default_true")]
    pub destripe: bool,
    /// Take a gridded LOLA product's offsets between its tracks out of its heights, estimated
    /// along its columns over the region (`ingest::lola_track_offsets`; default true; only
    /// for a simple cylindrical LDEM whose pixels resolve the tracks). The estimate shrinks
    /// towards no correction where terrain, not an offset, explains a column's difference, so
    /// a DEM without track offsets is left as it is. False to use the heights as gridded;
    /// run.json records the estimate either way.
    #[serde(default = "default_true")]
    pub dem_destripe: bool,
}

fn default_true() -> bool {
    true
}

fn default_register_search_px() -> usize {
    16
}

impl OrbitalInputs {
    /// The observation selection these options give.
    pub fn selection(&self) -> crate::fusion::Selection {
        let d = crate::fusion::Selection::default();
        crate::fusion::Selection {
            max_per_pixel: self.max_observations_per_pixel,
            min_incidence_deg: self.min_incidence_deg.unwrap_or(d.min_incidence_deg),
            max_incidence_deg: self.max_incidence_deg.unwrap_or(d.max_incidence_deg),
        }
    }
}

/// The wavelength a run uses unless told otherwise, nm: M3's band at 1209.57 nm, where the
/// Moon's reflectance is high and mostly free of mineral absorptions.
pub const DEFAULT_WAVELENGTH_NM: f64 = 1209.6;

fn default_wavelength() -> f64 {
    DEFAULT_WAVELENGTH_NM
}

/// The region to reconstruct: a longitude/latitude box, or a box in map metres of the grid's
/// projection. Exactly one of the two.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Region {
    pub lon_min: Option<f64>,
    pub lon_max: Option<f64>,
    pub lat_min: Option<f64>,
    pub lat_max: Option<f64>,
    pub x_min: Option<f64>,
    pub x_max: Option<f64>,
    pub y_min: Option<f64>,
    pub y_max: Option<f64>,
}

/// Which of the two forms a [`Region`] takes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RegionKind {
    LonLat(LonLatBox),
    /// (x_min, x_max, y_min, y_max), metres.
    Map([f64; 4]),
}

impl Region {
    pub fn kind(&self) -> Result<RegionKind> {
        let ll = [self.lon_min, self.lon_max, self.lat_min, self.lat_max];
        let xy = [self.x_min, self.x_max, self.y_min, self.y_max];
        let all = |a: &[Option<f64>; 4]| a.iter().all(Option::is_some);
        let none = |a: &[Option<f64>; 4]| a.iter().all(Option::is_none);
        if all(&ll) && none(&xy) {
            let b = LonLatBox {
                lon_min: ll[0].unwrap_or_default(),
                lon_max: ll[1].unwrap_or_default(),
                lat_min: ll[2].unwrap_or_default(),
                lat_max: ll[3].unwrap_or_default(),
            };
            b.validate()
                .map_err(|e| Error::Usage(format!("[region]: {e}")))?;
            Ok(RegionKind::LonLat(b))
        } else if all(&xy) && none(&ll) {
            let v = xy.map(Option::unwrap_or_default);
            if !(v.iter().all(|x| x.is_finite()) && v[0] < v[1] && v[2] < v[3]) {
                return Err(Error::Usage(format!(
                    "[region]: x {}..{}, y {}..{} must have x_min < x_max and y_min < y_max",
                    v[0], v[1], v[2], v[3]
                )));
            }
            Ok(RegionKind::Map(v))
        } else {
            Err(Error::Usage(
                "[region]: give either all of lon_min, lon_max, lat_min, lat_max or all of x_min, x_max, y_min, y_max (metres in the grid projection), not a mix".into(),
            ))
        }
    }
}

/// The projection family of the grid.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ProjectionKind {
    /// Centred on the region (or on `center_lat`/`center_lon`): the default for SfS.
    #[default]
    Stereographic,
    Orthographic,
    /// North or south by the sign of the region's centre latitude.
    PolarStereographic,
    Equirectangular,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GridSpec {
    pub projection: ProjectionKind,
    /// Projection centre; absent = the region's centre (filled in by [`Workflow::load`] when
    /// the region is a longitude/latitude box, else by the run from the swath).
    pub center_lat: Option<f64>,
    pub center_lon: Option<f64>,
    /// Pixel size, metres. Absent: the first observation's ground sample distance from its
    /// LOC backplane ([`crate::ingest::ground_sample_distance`]; ≈ 140 m for M3 global mode
    /// from the 100 km orbit, ≈ 280 m from 200 km); the plan records which.
    pub resolution_m: Option<f64>,
    /// How the DEM is resampled to the grid.
    pub dem_interpolation: Interpolation,
}

impl Default for GridSpec {
    fn default() -> Self {
        GridSpec {
            projection: ProjectionKind::Stereographic,
            center_lat: None,
            center_lon: None,
            resolution_m: None,
            dem_interpolation: Interpolation::Bicubic,
        }
    }
}

impl GridSpec {
    /// The CRS, given the centre (lat, lon) to use where the spec leaves it open.
    pub fn crs(&self, centre: (f64, f64)) -> Crs {
        let lat_0 = self.center_lat.unwrap_or(centre.0);
        let lon_0 = self.center_lon.unwrap_or(centre.1);
        match self.projection {
            ProjectionKind::Stereographic => Crs::Stereographic { lat_0, lon_0 },
            ProjectionKind::Orthographic => Crs::Orthographic { lat_0, lon_0 },
            ProjectionKind::PolarStereographic => Crs::PolarStereographic {
                north: lat_0 >= 0.0,
            },
            ProjectionKind::Equirectangular => Crs::Equirectangular {
                lon_0: self.center_lon.unwrap_or(0.0),
            },
        }
    }
}

/// How the region is cut into tiles.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Tiling {
    /// Edge of a tile's core, pixels. Each tile is solved on (core + 2·halo)²: with the default
    /// halo of 40 px that is 1.16× the core's work at 1024, 1.34× at 512 (docs/workflows.md).
    pub tile_size: usize,
    /// Overlap on each side, pixels; absent = [`auto_halo`]: ⌈4 × the largest Gaussian σ⌉ a
    /// tile applies (the fine albedo stages, σ_DEM, the DEM's point spread, and where several
    /// observations are listed the overlap passes' widths), at least [`MIN_HALO`] (with several
    /// observations [`MIN_HALO_SEVERAL`]) and, where cast shadows act, 4/3 of their rays' reach.
    pub halo: Option<usize>,
    /// Half-width, pixels, of the band around each core edge where neighbouring tiles are
    /// blended; at most the halo. Absent = halo / 4.
    pub blend: Option<usize>,
}

impl Default for Tiling {
    fn default() -> Self {
        Tiling {
            tile_size: 1024,
            halo: None,
            blend: None,
        }
    }
}

/// Output layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Hash)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// Fused height, metres above the 1737.4 km sphere (lab: the depth unit × depth_scale).
    Dem,
    /// Albedo (Hapke w for the Hapke model).
    Albedo,
    /// |I − R| at the solution; no data where the pixel carried no photometric information.
    Residual,
    /// Codes (Byte): 0 fused from shading, 1 seen by an observation but not photometric
    /// (shadow, refused pixel), 2 seen by none (the input DEM).
    Mask,
    /// The input DEM on the grid, for comparison.
    InputDem,
    /// The observed reflectance I on the grid (orbital: at the wavelength, from the first
    /// observation covering each pixel), sr⁻¹; the lab: the intensity image.
    Image,
    /// How many observations carried photometric information at each pixel (0 where none).
    Observations,
}

impl Layer {
    pub const ALL: [Layer; 7] = [
        Layer::Dem,
        Layer::Albedo,
        Layer::Residual,
        Layer::Mask,
        Layer::InputDem,
        Layer::Image,
        Layer::Observations,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Layer::Dem => "dem",
            Layer::Albedo => "albedo",
            Layer::Residual => "residual",
            Layer::Mask => "mask",
            Layer::InputDem => "input_dem",
            Layer::Image => "image",
            Layer::Observations => "observations",
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Output {
    pub directory: PathBuf,
    #[serde(default = "default_layers")]
    pub layers: Vec<Layer>,
}

fn default_layers() -> Vec<Layer> {
    vec![Layer::Dem, Layer::Albedo, Layer::Residual, Layer::Mask]
}

/// The seed's laboratory experiments: an intensity image and a range-scan depth map of a small
/// object, both rasters on one pixel grid (TIFF or PNG), known light and view directions.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lab {
    /// As [`Orbital::kind`].
    #[serde(default, skip_serializing)]
    pub kind: Option<String>,
    pub inputs: LabInputs,
    pub illumination: Illumination,
    #[serde(default = "default_lab_model")]
    pub photometry: ModelSpec,
    #[serde(default)]
    pub solver: FusionParams,
    pub output: Output,
}

fn default_lab_model() -> ModelSpec {
    ModelSpec::Lambert
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabInputs {
    /// Intensity image (TIFF or PNG, first channel).
    pub image: PathBuf,
    /// Depth map from the range scanner, same size (TIFF or PNG); larger = closer to the
    /// camera (height), in the depth unit.
    pub depth: PathBuf,
    /// Metres per depth unit (e.g. 0.001 for millimetres).
    #[serde(default = "one")]
    pub depth_scale: f64,
    /// Pixel size on the object, metres.
    pub pixel_size_m: f64,
    /// Values of the depth map that mean "no measurement" (in addition to NaN).
    #[serde(default)]
    pub depth_nodata: Option<f64>,
    /// σ, in pixels, of the range scanner's point spread on the image grid (0 = the scan is
    /// as sharp as the image).
    #[serde(default)]
    pub depth_psf_sigma_px: f64,
}

fn one() -> f64 {
    1.0
}

/// A path, or a non-empty list of paths.
fn one_or_more_paths<'de, D: serde::Deserializer<'de>>(
    d: D,
) -> std::result::Result<Vec<PathBuf>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum OneOrMore {
        One(PathBuf),
        More(Vec<PathBuf>),
    }
    match OneOrMore::deserialize(d).map_err(|_| {
        serde::de::Error::custom("expected a file name, or a list of them (one table per M3 mode)")
    })? {
        OneOrMore::One(p) => Ok(vec![p]),
        OneOrMore::More(v) if !v.is_empty() => Ok(v),
        OneOrMore::More(_) => Err(serde::de::Error::custom("the list is empty: give a table")),
    }
}

/// One path as a string, several as a list (a workflow of one table is recorded as before).
fn one_or_more_paths_out<S: serde::Serializer>(
    v: &[PathBuf],
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    match v {
        [one] => one.serialize(s),
        more => more.serialize(s),
    }
}

/// A direction as zenith/azimuth in degrees (azimuth clockwise from image up), in the image
/// frame: x right, y up, z towards the camera.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Direction {
    pub zenith_deg: f64,
    pub azimuth_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Illumination {
    pub light: Direction,
    #[serde(default = "nadir")]
    pub view: Direction,
}

fn nadir() -> Direction {
    Direction {
        zenith_deg: 0.0,
        azimuth_deg: 0.0,
    }
}

impl Workflow {
    /// Read, parse and resolve the workflow at `path`.
    pub fn load(path: &Path) -> Result<Workflow> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        // Absolute, so the resolved workflow (and the plan key hashed from it) is the same
        // however the path was spelled: `w.toml`, `./w.toml` or `/data/w.toml`.
        let abs = std::path::absolute(path).map_err(|e| Error::io(path, e))?;
        let base = normalise(abs.parent().unwrap_or(Path::new("/")));
        Workflow::parse(&text, path, &base)
    }

    /// Parse `text` (named `path` in errors), resolving relative paths against `base`.
    pub fn parse(text: &str, path: &Path, base: &Path) -> Result<Workflow> {
        // Parsed as the struct its `kind` names, not through the tagged enum: serde buffers a
        // tagged enum's content and its errors lose the key's line.
        let toml_err = |e: toml::de::Error| {
            Error::Usage(format!("{}: {}", path.display(), e.to_string().trim_end()))
        };
        let table: toml::Table = toml::from_str(text).map_err(toml_err)?;
        let mut wf = match table.get("kind").and_then(|k| k.as_str()) {
            Some("orbital") => Workflow::Orbital(Box::new(toml::from_str(text).map_err(toml_err)?)),
            Some("lab") => Workflow::Lab(Box::new(toml::from_str(text).map_err(toml_err)?)),
            Some(other) => {
                return Err(Error::Usage(format!(
                    "{}: kind = \"{other}\": expected \"orbital\" or \"lab\"",
                    path.display()
                )))
            }
            None => {
                return Err(Error::Usage(format!(
                "{}: the top-level key kind = \"orbital\" or \"lab\" is missing (or not a string)",
                path.display()
            )))
            }
        };
        let check = Check {
            path,
            base,
            table: &table,
        };
        match &mut wf {
            Workflow::Orbital(o) => check.orbital(o)?,
            Workflow::Lab(l) => check.lab(l)?,
        }
        Ok(wf)
    }
}

/// What the checks of a parsed workflow need: the file's name (for errors), the folder its
/// relative paths are resolved against, and its table (to tell a `[solver]` key given from
/// one defaulted).
struct Check<'a> {
    path: &'a Path,
    base: &'a Path,
    table: &'a toml::Table,
}

impl Check<'_> {
    /// `p` resolved against the workflow's folder, when relative.
    fn abs(&self, p: &mut PathBuf) {
        if p.is_relative() {
            *p = normalise(&self.base.join(&*p));
        }
    }

    /// A usage error naming the workflow file.
    fn fail(&self, why: String) -> Error {
        Error::Usage(format!("{}: {why}", self.path.display()))
    }

    /// Whether `[solver] KEY` is in the file (serde's defaults hide it).
    fn given(&self, key: &str) -> bool {
        self.table.get("solver").and_then(|t| t.get(key)).is_some()
    }

    /// An orbital workflow's paths resolved and its values checked against each other.
    fn orbital(&self, o: &mut Orbital) -> Result<()> {
        o.inputs.m3.iter_mut().for_each(|p| self.abs(p));
        o.inputs.lola.iter_mut().for_each(|p| self.abs(p));
        o.inputs.solar_spectrum.iter_mut().for_each(|p| self.abs(p));
        self.abs(&mut o.output.directory);
        if let Some(f) = &mut o.fetch {
            self.abs(&mut f.directory);
            for id in &f.products {
                crate::fetch::archive::Product::parse(id)
                    .map_err(|e| self.fail(format!("[fetch] products: {e}")))?;
            }
        }
        if o.inputs.m3.is_empty() {
            return Err(self.fail("[inputs] m3 lists no observation".into()));
        }
        if o.inputs.lola.is_empty() {
            return Err(self.fail("[inputs] lola lists no DEM".into()));
        }
        if !(o.inputs.wavelength_nm.is_finite() && o.inputs.wavelength_nm > 0.0) {
            return Err(self.fail(format!(
                "[inputs] wavelength_nm = {} must be positive",
                o.inputs.wavelength_nm
            )));
        }
        if let Some(r) = o.grid.resolution_m.filter(|r| !(r.is_finite() && *r > 0.0)) {
            return Err(self.fail(format!("[grid] resolution_m = {r} must be positive")));
        }
        if o.tiling.tile_size < 16 {
            return Err(self.fail(format!(
                "[tiling] tile_size = {} must be at least 16",
                o.tiling.tile_size
            )));
        }
        if let Some(r) = &o.region {
            if let RegionKind::LonLat(b) = r.kind().map_err(|e| self.fail(e.to_string()))? {
                // Fill in the projection centre: the run record shows it.
                let (lon, lat) = b.centre();
                o.grid.center_lat.get_or_insert(lat);
                o.grid.center_lon.get_or_insert(lon);
            } else if (o.grid.center_lat.is_none() || o.grid.center_lon.is_none())
                && o.grid.projection != ProjectionKind::Equirectangular
            {
                return Err(self.fail("a [region] in map metres needs [grid] center_lat and center_lon: the metres are in that projection".into()));
            }
        }
        if let (Some(halo), Some(blend)) = (o.tiling.halo, o.tiling.blend) {
            if blend > halo {
                return Err(self.fail(format!("[tiling] blend = {blend} must not exceed the halo ({halo} px): tiles have no data beyond it")));
            }
        }
        if let Some(r) = o.inputs.dem_resolution_m {
            if !(r.is_finite() && r > 0.0) {
                return Err(self.fail(format!(
                    "[inputs] dem_resolution_m = {r} must be a positive number of metres"
                )));
            }
        }
        let r = &o.inputs;
        if let Some(m) = r.register_min_px {
            if !(m.is_finite() && m >= 0.0) {
                return Err(self.fail(format!(
                    "[inputs] register_min_px = {m} must be a number of pixels ≥ 0"
                )));
            }
        }
        if !(1..=256).contains(&r.register_search_px) {
            return Err(self.fail(format!(
                "[inputs] register_search_px = {} must be 1 to 256 pixels",
                r.register_search_px
            )));
        }
        let sel = o.inputs.selection();
        let ok = (0.0..90.0).contains(&sel.min_incidence_deg)
            && sel.max_incidence_deg > sel.min_incidence_deg
            && sel.max_incidence_deg <= 90.0;
        if !ok {
            return Err(self.fail(format!(
                "[inputs] min_incidence_deg = {} and max_incidence_deg = {} must satisfy 0 ≤ min < max ≤ 90",
                sel.min_incidence_deg, sel.max_incidence_deg
            )));
        }
        o.sigma_dem_given = self.given("sigma_dem");
        o.dem_track_weight_given = self.given("dem_track_weight");
        o.high_sun_east_west_given = self.given("multi_delta_factor_high_sun_east_west");
        // A membrane the workflow sets is the one it gets: the rule for a coarse DEM
        // (fusion::coarse_dem_membrane) stays off unless asked for by name.
        if !self.given("coarse_dem_membrane")
            && ["eta", "edge_membrane_slope", "multi_eta_factor"]
                .iter()
                .any(|k| self.given(k))
        {
            o.solver.coarse_dem_membrane = false;
        }
        validate_solver(&o.solver).map_err(|e| self.fail(e))?;
        validate_layers(&o.output.layers).map_err(|e| self.fail(e))?;
        Ok(())
    }

    /// A laboratory workflow's paths resolved and its values checked.
    fn lab(&self, l: &mut Lab) -> Result<()> {
        // A range scan has no altimeter tracks: E_DEM's track weighting is off unless
        // asked for.
        if !self.given("dem_track_weight") {
            l.solver.dem_track_weight = 1.0;
        }
        self.abs(&mut l.inputs.image);
        self.abs(&mut l.inputs.depth);
        self.abs(&mut l.output.directory);
        if !(l.inputs.pixel_size_m.is_finite() && l.inputs.pixel_size_m > 0.0) {
            return Err(self.fail(format!(
                "[inputs] pixel_size_m = {} must be positive",
                l.inputs.pixel_size_m
            )));
        }
        if !(l.inputs.depth_psf_sigma_px.is_finite() && l.inputs.depth_psf_sigma_px >= 0.0) {
            return Err(self.fail(format!(
                "[inputs] depth_psf_sigma_px = {} must be ≥ 0",
                l.inputs.depth_psf_sigma_px
            )));
        }
        if !(l.inputs.depth_scale.is_finite() && l.inputs.depth_scale != 0.0) {
            return Err(self.fail(format!(
                "[inputs] depth_scale = {} must be a non-zero number",
                l.inputs.depth_scale
            )));
        }
        for (what, d) in [
            ("light", l.illumination.light),
            ("view", l.illumination.view),
        ] {
            check_direction(what, d).map_err(|e| self.fail(e))?;
        }
        validate_solver(&l.solver).map_err(|e| self.fail(e))?;
        validate_layers(&l.output.layers).map_err(|e| self.fail(e))?;
        Ok(())
    }
}

/// `[illumination] what` must stand above the object's plane (zenith 0 ≤ z < 90°) with a finite
/// azimuth: a light at or below it lights nothing, a camera there sees nothing.
fn check_direction(what: &str, d: Direction) -> std::result::Result<(), String> {
    if !(d.zenith_deg.is_finite() && (0.0..90.0).contains(&d.zenith_deg)) {
        return Err(format!(
            "[illumination] {what} zenith_deg = {} must be at least 0 and below 90 (above the object's plane)",
            d.zenith_deg
        ));
    }
    if !d.azimuth_deg.is_finite() {
        return Err(format!(
            "[illumination] {what} azimuth_deg = {} must be a finite number of degrees",
            d.azimuth_deg
        ));
    }
    Ok(())
}

/// `a/./b/../c` → `a/c`, lexically (no file system access; a leading `..` is kept).
fn normalise(p: &Path) -> PathBuf {
    use std::path::Component;
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir
                if matches!(out.components().next_back(), Some(Component::Normal(_))) =>
            {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// `[solver]`'s values in their ranges ([`crate::fusion::validate_params`]), checked when the
/// workflow is loaded rather than when the first tile's fusion starts.
fn validate_solver(p: &FusionParams) -> std::result::Result<(), String> {
    crate::fusion::validate_params(p).map_err(|e| format!("[solver] {e}"))
}

fn validate_layers(layers: &[Layer]) -> std::result::Result<(), String> {
    if layers.is_empty() {
        return Err("[output] layers is empty: nothing would be written".into());
    }
    let mut seen = std::collections::HashSet::new();
    for l in layers {
        if !seen.insert(l) {
            return Err(format!("[output] layers names {} twice", l.name()));
        }
    }
    Ok(())
}

/// The smallest halo a tile gets, pixels: the anchoring to the reference (σ = halo/4) must
/// stay wider than the coarse reference's blocks.
pub const MIN_HALO: usize = 32;

/// The smallest halo where several observations are used, pixels. Where Suns overlap E_DEM
/// weighs 0.2 δ and the membrane turns edge-aware, so the height part of E_DEM (ℓ =
/// `dem_height_length_px`, 30 px) screens the window's edge less than where one image is used:
/// with 40 px, tiles of 128 px ended 0.13–0.18 × the RMSE from the whole region at hundreds of
/// pixels; with 80 px, 0.05–0.08 × (docs/science.md, "Tiles").
pub const MIN_HALO_SEVERAL: usize = 80;

/// ⌈4 × the largest Gaussian σ a tile applies⌉ (its albedo stages, final albedo, σ_DEM
/// combined with the DEM's point spread `dem_psf`, and with the track weighting's σ_t along
/// the columns), at least [`MIN_HALO`] pixels: with the
/// default blend of halo/4, every pixel a tile contributes to the mosaic is ≥ 3σ inside its
/// window. It also covers the photometric support band (3 σ_DEM,
/// [`crate::fusion::support::band`]). With a coarse reference (`reference`,
/// [`crate::fusion::pyramid`]) the first albedo stage is the plan's, solved over the whole
/// region, and does not count. Where cast shadows act (`shadow_weight` > 0, or
/// `partial_shadow`, whose lit shares walk as far, with `several` observations listed; with
/// one, only E_S raised by `shadow_weight_alone`) it is also at least
/// ⌈4/3 × `shadow_reach_px`⌉: every pixel a tile gives the mosaic (≥ 3/4 halo inside the
/// window) then has its whole ray inside the window, as it does on the whole region. With
/// `several` observations listed it is at least [`MIN_HALO_SEVERAL`].
pub fn auto_halo(p: &FusionParams, dem_psf: f64, reference: bool, several: bool) -> usize {
    let dem = p
        .sigma_dem
        .hypot(dem_psf)
        .max(crate::fusion::support::band(p.sigma_dem).1 / 3.0);
    let stages = if reference {
        p.albedo_sigmas.get(1..).unwrap_or(&[])
    } else {
        &p.albedo_sigmas[..]
    };
    let tracks = if p.dem_track_weight < 1.0 {
        p.dem_track_sigma_px.hypot(dem)
    } else {
        0.0
    };
    // Where observations overlap, the last stage's passes also low-pass the multi-coverage
    // (`fusion::near_overlap`) and the albedo at `multi_albedo_sigma_single`.
    let overlap = if several {
        let last = p.albedo_sigmas.last().copied().unwrap_or(0.0);
        (crate::fusion::NEAR_OVERLAP_SIGMA_FACTOR * last).max(p.multi_albedo_sigma_single)
    } else {
        0.0
    };
    let largest = stages
        .iter()
        .copied()
        .chain([p.final_albedo_sigma, dem, tracks, overlap])
        .fold(0.0f64, f64::max);
    // E_S and the lit shares act only where another observation sees the pixel, unless E_S is
    // asked for on pixels one observation carries alone.
    let rays_act = (several && (p.shadow_weight > 0.0 || p.partial_shadow))
        || (p.shadow_weight > 0.0 && p.shadow_weight_alone > 0.0);
    let rays = if rays_act {
        (4 * p.shadow_reach_px).div_ceil(3)
    } else {
        0
    };
    let least = if several { MIN_HALO_SEVERAL } else { MIN_HALO };
    ((4.0 * largest).ceil() as usize).max(least).max(rays)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A range scan has no altimeter tracks: a lab workflow leaves E_DEM's track weighting off
    /// (1) unless `[solver] dem_track_weight` is given.
    #[test]
    fn lab_workflows_leave_the_track_weighting_off_unless_given() {
        let lab = r#"kind = "lab"
[inputs]
image = "image.tif"
depth = "depth.png"
pixel_size_m = 5e-4
[illumination]
light = { zenith_deg = 50.0, azimuth_deg = 120.0 }
[output]
directory = "out"
"#;
        let weight = |text: &str| match Workflow::parse(text, Path::new("w.toml"), Path::new("."))
            .unwrap()
        {
            Workflow::Lab(l) => l.solver.dem_track_weight,
            Workflow::Orbital(_) => panic!("a lab workflow"),
        };
        assert_eq!(weight(lab), 1.0);
        let refusal = |text: &str| {
            Workflow::parse(text, Path::new("w.toml"), Path::new("."))
                .unwrap_err()
                .to_string()
        };
        let given = lab.replace("[output]", "[solver]\ndem_track_weight = 0.2\n[output]");
        assert_eq!(weight(&given), 0.2);
        for (light, want) in [
            (
                "zenith_deg = 95.0, azimuth_deg = 120.0",
                "light zenith_deg = 95 must be at least 0 and below 90",
            ),
            (
                "zenith_deg = nan, azimuth_deg = 120.0",
                "light zenith_deg = NaN",
            ),
            (
                "zenith_deg = 50.0, azimuth_deg = inf",
                "light azimuth_deg = inf",
            ),
        ] {
            let bad = lab.replace("zenith_deg = 50.0, azimuth_deg = 120.0", light);
            assert_ne!(bad, lab);
            let e = refusal(&bad);
            assert!(e.contains("w.toml") && e.contains(want), "{e}");
        }
        // `[solver]` values out of their ranges, each refused naming the key: the reasons.
        let solver =
            |line: &str| refusal(&lab.replace("[output]", &format!("[solver]\n{line}\n[output]")));
        let e = solver("max_iterations = 0");
        assert!(e.contains("w.toml") && e.contains("max_iterations"), "{e}");
        let e = solver("multi_albedo_passes = 0");
        assert!(
            e.contains("w.toml") && e.contains("multi_albedo_passes") && e.contains("at least 1"),
            "{e}"
        );
        // A coupling above 1 would take more than the albedo's direction out of the Hessian.
        let e = solver("multi_albedo_coupling = 1.2");
        assert!(
            e.contains("w.toml") && e.contains("multi_albedo_coupling") && e.contains("[0, 1]"),
            "{e}"
        );
        // No albedo stage: no surface solve at all, the DEM would come out unchanged.
        let e = solver("albedo_sigmas = []");
        assert!(
            e.contains("w.toml") && e.contains("albedo_sigmas is empty"),
            "{e}"
        );
        // A shrink beyond 1 would turn the Nyquist wave over; NaN is no number at all.
        for value in ["1.5", "-0.1", "nan"] {
            let e = solver(&format!("nyquist_shrink = {value}"));
            assert!(
                e.contains("w.toml") && e.contains("nyquist_shrink") && e.contains("[0, 1]"),
                "{value}: {e}"
            );
        }
        // The east–west rule's factor: 0 or beyond 1 refused; a workflow that lowers
        // `multi_delta_factor` under it is accepted (the rule is then off).
        for value in ["0.0", "1.5", "nan"] {
            let e = solver(&format!("multi_delta_factor_east_west = {value}"));
            assert!(
                e.contains("w.toml")
                    && e.contains("multi_delta_factor_east_west")
                    && e.contains("(0, 1]"),
                "{value}: {e}"
            );
        }
        let lowered = lab.replace("[output]", "[solver]\nmulti_delta_factor = 0.1\n[output]");
        assert!(Workflow::parse(&lowered, Path::new("w.toml"), Path::new(".")).is_ok());
        assert_eq!(FusionParams::default().dem_track_weight, 0.1);
    }

    const MINIMAL: &str = r#"
kind = "orbital"
[inputs]
m3 = ["obs/M3G_L1B.LBL"]
lola = ["/abs/LDEM_64.LBL"]
solar_spectrum = "cal/solar.tab"
[region]
lon_min = 355.0
lon_max = 359.0
lat_min = -15.0
lat_max = -11.0
[output]
directory = "out"
"#;

    #[test]
    fn defaults_are_filled_and_paths_resolved() {
        let wf = Workflow::parse(MINIMAL, Path::new("w.toml"), Path::new("/data/run")).unwrap();
        let Workflow::Orbital(o) = wf else { panic!() };
        assert_eq!(o.inputs.m3[0], Path::new("/data/run/obs/M3G_L1B.LBL"));
        assert_eq!(normalise(Path::new("w/../out/./x")), Path::new("out/x"));
        assert_eq!(normalise(Path::new("../a/b/../c")), Path::new("../a/c"));
        assert_eq!(o.inputs.lola[0], Path::new("/abs/LDEM_64.LBL"));
        assert_eq!(o.output.directory, Path::new("/data/run/out"));
        assert_eq!(
            o.inputs.solar_spectrum,
            [Path::new("/data/run/cal/solar.tab")]
        );
        // One table is written back as a string (run.json records such a workflow as
        // before), one per mode as a list, each resolved.
        let json = serde_json::to_value(&o.inputs).unwrap();
        assert_eq!(json["solar_spectrum"], "/data/run/cal/solar.tab");
        let two = MINIMAL.replace(
            "solar_spectrum = \"cal/solar.tab\"",
            "solar_spectrum = [\"cal/M3G.TAB\", \"/t/M3T.TAB\"]",
        );
        let Workflow::Orbital(t) =
            Workflow::parse(&two, Path::new("w.toml"), Path::new("/r")).unwrap()
        else {
            panic!()
        };
        assert_eq!(
            t.inputs.solar_spectrum,
            [Path::new("/r/cal/M3G.TAB"), Path::new("/t/M3T.TAB")]
        );
        assert_eq!(
            serde_json::to_value(&t.inputs).unwrap()["solar_spectrum"],
            serde_json::json!(["/r/cal/M3G.TAB", "/t/M3T.TAB"])
        );
        for (bad, want) in [("[]", "the list is empty"), ("3", "or a list of them")] {
            let text = MINIMAL.replace("\"cal/solar.tab\"", bad);
            let e = Workflow::parse(&text, Path::new("w.toml"), Path::new("/r"))
                .unwrap_err()
                .to_string();
            assert!(e.contains("w.toml") && e.contains(want), "{e}");
        }
        assert_eq!(o.inputs.wavelength_nm, 1209.6);
        // The grid spacing comes from the observation unless given.
        assert_eq!(o.grid.resolution_m, None);
        assert_eq!(
            (o.grid.center_lat, o.grid.center_lon),
            (Some(-13.0), Some(357.0))
        );
        // The halo depends on the DEM (σ_DEM, its point spread): the plan sets it. With a DEM
        // 4× coarser the largest σ is the first albedo stage, 100 px, when tiles solve it;
        // with the plan's coarse reference it is the track weighting's 9 px along the columns
        // through the DEM term's blur (σ_DEM 2 px, point spread 4/√2 px): 4·√(81 + 4 + 8) =
        // 38.6 px, under the second albedo stage's 4 × 10 px.
        assert_eq!(o.tiling.halo, None);
        assert!(!o.sigma_dem_given);
        let psf = crate::fusion::dem_psf_sigma(4.0);
        assert_eq!(auto_halo(&o.solver, psf, false, false), 400);
        assert_eq!(auto_halo(&o.solver, psf, true, false), 40);
        // Several observations: at least 80 px.
        assert_eq!(auto_halo(&o.solver, psf, true, true), 80);
        assert_eq!(auto_halo(&o.solver, psf, false, true), 400);
        // There the overlap passes low-pass the multi-coverage at twice the last albedo stage's
        // σ_ρ: a last stage of 25 px asks for 4 × 50 px, only where several are listed.
        let mut wide = o.solver.clone();
        wide.albedo_sigmas = vec![100.0, 25.0];
        assert_eq!(auto_halo(&wide, psf, true, true), 200);
        assert_eq!(auto_halo(&wide, psf, true, false), 100);
        // The default rays (40 px) fit in 3/4 of the 80 px of several observations; longer
        // ones widen it, 90 px → 120 px, where they act: with several observations listed,
        // and with one only where E_S is raised on pixels one observation carries alone.
        assert_eq!(o.solver.shadow_reach_px, 40);
        let mut longer = o.solver.clone();
        longer.shadow_reach_px = 90;
        assert_eq!(auto_halo(&longer, psf, true, true), 120);
        assert_eq!(auto_halo(&longer, psf, true, false), 40);
        longer.shadow_weight_alone = 1.0;
        assert_eq!(auto_halo(&longer, psf, true, false), 120);
        longer.shadow_weight = 0.0;
        assert_eq!(auto_halo(&longer, psf, true, false), 40);
        // The partial shadow's lit shares walk as far.
        assert_eq!(auto_halo(&longer, psf, true, true), 120);
        longer.partial_shadow = false;
        assert_eq!(auto_halo(&longer, psf, true, true), 80);
        let given = MINIMAL.replace("[output]", "[solver]\nsigma_dem = 5.0\n[output]");
        let Workflow::Orbital(g) =
            Workflow::parse(&given, Path::new("w.toml"), Path::new(".")).unwrap()
        else {
            panic!()
        };
        assert!(g.sigma_dem_given);
        assert_eq!(o.photometry, ModelSpec::Hapke(Hapke::moon()));
        assert_eq!(o.solver, FusionParams::default());
    }

    /// The membrane rule for a coarse DEM is on by default, off when the workflow sets the
    /// membrane itself, and on again when it names the rule.
    #[test]
    fn a_membrane_the_workflow_sets_turns_the_coarse_dem_rule_off() {
        let rule = |solver: &str| {
            let text = MINIMAL.replace("[output]", &format!("[solver]\n{solver}\n[output]"));
            let Workflow::Orbital(o) =
                Workflow::parse(&text, Path::new("w.toml"), Path::new(".")).unwrap()
            else {
                panic!()
            };
            o.solver.coarse_dem_membrane
        };
        assert!(rule("delta = 40.0"));
        assert!(!rule("eta = 0.2"));
        assert!(!rule("edge_membrane_slope = 0.05"));
        assert!(!rule("multi_eta_factor = 3.0"));
        assert!(rule("eta = 0.2\ncoarse_dem_membrane = true"));
        assert!(!rule("coarse_dem_membrane = false"));
    }

    #[test]
    fn unknown_keys_and_mixed_regions_are_refused_with_their_names() {
        let typo = MINIMAL.replace("[output]", "[output]\nlayer = [\"dem\"]");
        let e = Workflow::parse(&typo, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("w.toml") && e.contains("layer"), "{e}");
        let solver = MINIMAL.replace("[output]", "[solver]\ndelat = 3.0\n[output]");
        let e = Workflow::parse(&solver, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("delat"), "{e}");
        // Out-of-range solver values are refused on loading, with the file, the key and the
        // value, for both kinds of workflow.
        for (line, key) in [
            ("eta = -0.1", "eta = -0.1"),
            ("cg_iterations = 0", "cg_iterations = 0"),
            ("cg_tolerance = 1.5", "cg_tolerance = 1.5"),
            ("dem_track_weight = 2.0", "dem_track_weight = 2"),
        ] {
            let bad = MINIMAL.replace("[output]", &format!("[solver]\n{line}\n[output]"));
            let e = Workflow::parse(&bad, Path::new("w.toml"), Path::new("."))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("w.toml") && e.contains("[solver]") && e.contains(key),
                "{line}: {e}"
            );
        }
        let kind = MINIMAL.replace("kind = \"orbital\"", "kind = \"orbit\"");
        let e = Workflow::parse(&kind, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("kind = \"orbit\"") && e.contains("\"orbital\" or \"lab\""),
            "{e}"
        );
        let no_kind = MINIMAL.replace("kind = \"orbital\"", "");
        let e = Workflow::parse(&no_kind, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("w.toml") && e.contains("kind"), "{e}");
        let mixed = MINIMAL.replace("lat_max = -11.0", "lat_max = -11.0\nx_min = 0.0");
        let e = Workflow::parse(&mixed, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("[region]") && e.contains("not a mix"), "{e}");
        let e = Workflow::parse("kind = \"satellite\"", Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("satellite"), "{e}");
    }

    #[test]
    fn a_metric_region_needs_a_projection_centre() {
        let m = MINIMAL.replace(
            "lon_min = 355.0\nlon_max = 359.0\nlat_min = -15.0\nlat_max = -11.0",
            "x_min = -1000.0\nx_max = 1000.0\ny_min = -500.0\ny_max = 500.0",
        );
        let e = Workflow::parse(&m, Path::new("w.toml"), Path::new("."))
            .unwrap_err()
            .to_string();
        assert!(e.contains("center_lat"), "{e}");
        let ok = m.replace(
            "[output]",
            "[grid]\ncenter_lat = -13.4\ncenter_lon = 357.2\n[output]",
        );
        Workflow::parse(&ok, Path::new("w.toml"), Path::new(".")).unwrap();
    }
}
