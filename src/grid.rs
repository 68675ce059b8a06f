//! One georeferenced, locally metric raster grid on the Moon sphere (R = 1 737 400 m), and the
//! pure geometry that puts data on it: map projections (through `proj4rs`, which matches
//! PROJ 9.1.1 to < 1e-6 m on these projections), the rotation of east-north-up vectors into the
//! grid frame, interpolation kernels, and the triangulation that maps a scattered swath
//! (M3 LOC longitude/latitude per pixel) onto the grid. No I/O here: `ingest` reads files.
//!
//! Conventions (docs/architecture.md): arrays are `[row, col]`, row 0 at the grid's north
//! (map +y) edge; the grid frame is map +x (≈ east), map +y (≈ north), up. A grid is
//! `rows × cols` square pixels of `spacing` metres whose outer corner is at map (x0, y0):
//! pixel (r, c) has its centre at (x0 + (c + ½)·ε, y0 − (r + ½)·ε), GDAL's geotransform
//! (x0, ε, 0, y0, 0, −ε).

use ndarray::{Array2, ArrayView2, Zip};
use proj4rs::proj::Proj;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// The IAU 2015 Moon sphere radius (IAU_2015:30100), metres.
pub const MOON_RADIUS_M: f64 = 1_737_400.0;

/// A projected coordinate reference system on the Moon sphere.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Crs {
    /// Equirectangular (plate carrée), true scale on the equator; `lon_0` = 0 is
    /// IAU_2015:30110, 180 is 30115 (the LDEM IMG files). Not locally metric away from the
    /// equator: not for shape from shading.
    Equirectangular { lon_0: f64 },
    /// Polar stereographic, true scale at the pole, longitude 0 towards map −y in the north and
    /// +y in the south (IAU_2015:30130 / 30135; LOLA's polar products).
    PolarStereographic { north: bool },
    /// Oblique stereographic centred on (lat_0, lon_0), scale 1 at the centre: conformal, so
    /// x and y spacing stay equal; the default for shape from shading.
    Stereographic { lat_0: f64, lon_0: f64 },
    /// Orthographic centred on (lat_0, lon_0): the view from far above the centre.
    Orthographic { lat_0: f64, lon_0: f64 },
}

/// What went wrong with a grid or a projection.
#[derive(Debug, thiserror::Error)]
pub enum GridError {
    #[error("projection `{def}`: {why}")]
    Projection { def: String, why: String },
    #[error("grid: {0}")]
    Invalid(String),
}

impl Crs {
    /// The PROJ string, written as PROJ itself writes the IAU_2015 definitions.
    pub fn proj_string(&self) -> String {
        let tail = "+x_0=0 +y_0=0 +R=1737400 +units=m +no_defs";
        match *self {
            Crs::Equirectangular { lon_0 } => {
                format!("+proj=eqc +lat_ts=0 +lat_0=0 +lon_0={lon_0} {tail}")
            }
            Crs::PolarStereographic { north } => {
                let lat = if north { 90 } else { -90 };
                format!("+proj=stere +lat_0={lat} +lon_0=0 +k=1 {tail}")
            }
            Crs::Stereographic { lat_0, lon_0 } => {
                format!("+proj=stere +lat_0={lat_0} +lon_0={lon_0} +k=1 {tail}")
            }
            Crs::Orthographic { lat_0, lon_0 } => {
                format!("+proj=ortho +lat_0={lat_0} +lon_0={lon_0} {tail}")
            }
        }
    }

    /// The IAU_2015 code this CRS is, where it is one.
    pub fn iau_2015(&self) -> Option<&'static str> {
        match *self {
            Crs::Equirectangular { lon_0: 0.0 } => Some("IAU_2015:30110"),
            Crs::Equirectangular { lon_0: 180.0 } => Some("IAU_2015:30115"),
            Crs::PolarStereographic { north: true } => Some("IAU_2015:30130"),
            Crs::PolarStereographic { north: false } => Some("IAU_2015:30135"),
            _ => None,
        }
    }

    /// WKT2 (ISO 19162:2019) with the IAU 2015 Moon sphere (IAU_2015:30100) as the base
    /// geographic CRS and the projection as an EPSG method with EPSG parameter codes.
    pub fn wkt(&self) -> String {
        let deg = r#"ANGLEUNIT["degree",0.0174532925199433]"#;
        let m = r#"LENGTHUNIT["metre",1]"#;
        let p = |name: &str, v: f64, unit: &str, id: u32| {
            format!(r#"PARAMETER["{name}",{v},{unit},ID["EPSG",{id}]]"#)
        };
        let (method, params) = match *self {
            Crs::Equirectangular { lon_0 } => (
                r#"METHOD["Equidistant Cylindrical",ID["EPSG",1028]]"#,
                vec![
                    p("Latitude of 1st standard parallel", 0.0, deg, 8823),
                    p("Longitude of natural origin", lon_0, deg, 8802),
                ],
            ),
            Crs::PolarStereographic { north } => (
                r#"METHOD["Polar Stereographic (variant A)",ID["EPSG",9810]]"#,
                vec![
                    p(
                        "Latitude of natural origin",
                        if north { 90.0 } else { -90.0 },
                        deg,
                        8801,
                    ),
                    p("Longitude of natural origin", 0.0, deg, 8802),
                    p(
                        "Scale factor at natural origin",
                        1.0,
                        r#"SCALEUNIT["unity",1]"#,
                        8805,
                    ),
                ],
            ),
            Crs::Stereographic { lat_0, lon_0 } => (
                r#"METHOD["Stereographic"]"#,
                vec![
                    p("Latitude of natural origin", lat_0, deg, 8801),
                    p("Longitude of natural origin", lon_0, deg, 8802),
                    p(
                        "Scale factor at natural origin",
                        1.0,
                        r#"SCALEUNIT["unity",1]"#,
                        8805,
                    ),
                ],
            ),
            Crs::Orthographic { lat_0, lon_0 } => (
                r#"METHOD["Orthographic",ID["EPSG",9840]]"#,
                vec![
                    p("Latitude of natural origin", lat_0, deg, 8801),
                    p("Longitude of natural origin", lon_0, deg, 8802),
                ],
            ),
        };
        let mut params = params;
        params.push(p("False easting", 0.0, m, 8806));
        params.push(p("False northing", 0.0, m, 8807));
        format!(
            r#"PROJCRS["{name}",BASEGEOGCRS["Moon (2015) - Sphere / Ocentric",DATUM["Moon (2015) - Sphere",ELLIPSOID["Moon (2015) - Sphere",1737400,0,{m}]],PRIMEM["Reference Meridian",0,{deg}],ID["IAU",30100,2015]],CONVERSION["{conv}",{method},{params}],CS[Cartesian,2],AXIS["easting (E)",east,ORDER[1],{m}],AXIS["northing (N)",north,ORDER[2],{m}]]"#,
            name = self.name(),
            conv = self.name(),
            params = params.join(","),
        )
    }

    /// A short human name ("Moon stereographic centred 9.5°N 37.9°E").
    pub fn name(&self) -> String {
        match *self {
            Crs::Equirectangular { lon_0 } => format!("Moon (2015) equirectangular, lon_0 {lon_0}"),
            Crs::PolarStereographic { north } => format!(
                "Moon (2015) {} polar stereographic",
                if north { "north" } else { "south" }
            ),
            Crs::Stereographic { lat_0, lon_0 } => {
                format!("Moon (2015) stereographic centred at lat {lat_0}, lon {lon_0}")
            }
            Crs::Orthographic { lat_0, lon_0 } => {
                format!("Moon (2015) orthographic centred at lat {lat_0}, lon {lon_0}")
            }
        }
    }

    fn validate(&self) -> Result<(), GridError> {
        let bad = |what: &str, v: f64, lim: f64| {
            (!(v.is_finite() && v.abs() <= lim))
                .then(|| GridError::Invalid(format!("{what} = {v} must lie in [−{lim}, {lim}]")))
        };
        let e = match *self {
            Crs::Equirectangular { lon_0 } => bad("lon_0", lon_0, 360.0),
            Crs::PolarStereographic { .. } => None,
            Crs::Stereographic { lat_0, lon_0 } | Crs::Orthographic { lat_0, lon_0 } => {
                bad("lat_0", lat_0, 90.0).or(bad("lon_0", lon_0, 360.0))
            }
        };
        e.map_or(Ok(()), Err)
    }

    /// The forward and inverse projection between (lon, lat) in degrees and map metres.
    pub fn projector(&self) -> Result<Projector, GridError> {
        self.validate()?;
        let def = self.proj_string();
        let make = |d: &str| {
            Proj::from_proj_string(d).map_err(|e| GridError::Projection {
                def: d.to_string(),
                why: e.to_string(),
            })
        };
        Ok(Projector {
            geo: make("+proj=longlat +R=1737400 +no_defs")?,
            map: make(&def)?,
            crs: *self,
        })
    }
}

/// Projects between geographic (east longitude, planetocentric latitude, degrees) and map
/// coordinates (metres) of one [`Crs`].
#[derive(Clone)]
pub struct Projector {
    geo: Proj,
    map: Proj,
    pub crs: Crs,
}

impl std::fmt::Debug for Projector {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Projector({})", self.crs.proj_string())
    }
}

impl Projector {
    /// Map (x, y) of (lon, lat) in degrees; `None` where the projection is undefined (the far
    /// side of an orthographic view, the antipode of a stereographic centre).
    pub fn forward(&self, lon: f64, lat: f64) -> Option<(f64, f64)> {
        if !(lon.is_finite() && lat.is_finite() && lat.abs() <= 90.0) {
            return None;
        }
        let mut p = (lon.to_radians(), lat.to_radians(), 0.0);
        proj4rs::transform::transform(&self.geo, &self.map, &mut p).ok()?;
        (p.0.is_finite() && p.1.is_finite()).then_some((p.0, p.1))
    }

    /// (lon, lat) in degrees of map (x, y); longitude in (−180, 180].
    pub fn inverse(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        if !(x.is_finite() && y.is_finite()) {
            return None;
        }
        let mut p = (x, y, 0.0);
        proj4rs::transform::transform(&self.map, &self.geo, &mut p).ok()?;
        let (lon, lat) = (p.0.to_degrees(), p.1.to_degrees());
        (lon.is_finite() && lat.is_finite()).then_some((lon, lat))
    }

    /// The grid bearing of true north at (lon, lat): the angle θ, clockwise from map +y, of
    /// the direction in which latitude increases (central differences over ±0.001°, one-sided
    /// next to a pole). 0 on the central meridian of every projection here.
    pub fn north_bearing(&self, lon: f64, lat: f64) -> Option<f64> {
        let d = 1e-3;
        let (a, b) = ((lat - d).max(-90.0), (lat + d).min(90.0));
        let (x0, y0) = self.forward(lon, a)?;
        let (x1, y1) = self.forward(lon, b)?;
        let (dx, dy) = (x1 - x0, y1 - y0);
        (dx != 0.0 || dy != 0.0).then(|| dx.atan2(dy))
    }
}

/// Rotate a vector from local east-north-up into the grid frame (map +x, map +y, up), given
/// the grid bearing θ of true north there ([`Projector::north_bearing`]):
/// x = e·cos θ + n·sin θ, y = −e·sin θ + n·cos θ, up unchanged. Exact for the conformal
/// projections (stereographic, polar stereographic), where east is 90° clockwise from north
/// on the map too.
pub fn enu_to_grid(v: [f64; 3], bearing: f64) -> [f64; 3] {
    let (s, c) = bearing.sin_cos();
    [v[0] * c + v[1] * s, -v[0] * s + v[1] * c, v[2]]
}

/// A rectangle in longitude and latitude, degrees (east longitudes; `lon_min > lon_max` is not
/// allowed: give lon_max > 180 to cross the 180° meridian, e.g. 170 to 190).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LonLatBox {
    pub lon_min: f64,
    pub lon_max: f64,
    pub lat_min: f64,
    pub lat_max: f64,
}

impl LonLatBox {
    pub fn validate(&self) -> Result<(), GridError> {
        let ok = self.lat_min.is_finite()
            && self.lat_max.is_finite()
            && self.lon_min.is_finite()
            && self.lon_max.is_finite()
            && -90.0 <= self.lat_min
            && self.lat_min < self.lat_max
            && self.lat_max <= 90.0
            && self.lon_min < self.lon_max
            && self.lon_max - self.lon_min <= 360.0;
        if ok {
            Ok(())
        } else {
            Err(GridError::Invalid(format!(
                "region lon {}..{}, lat {}..{} is not a rectangle on the Moon (need lat_min < lat_max within ±90, lon_min < lon_max, at most 360° wide)",
                self.lon_min, self.lon_max, self.lat_min, self.lat_max
            )))
        }
    }

    /// The centre, for a local projection.
    pub fn centre(&self) -> (f64, f64) {
        (
            0.5 * (self.lon_min + self.lon_max),
            0.5 * (self.lat_min + self.lat_max),
        )
    }

    /// Points along the border, `n` per edge.
    fn border(&self, n: usize) -> impl Iterator<Item = (f64, f64)> + '_ {
        (0..=n).flat_map(move |k| {
            let t = k as f64 / n as f64;
            let lon = self.lon_min + t * (self.lon_max - self.lon_min);
            let lat = self.lat_min + t * (self.lat_max - self.lat_min);
            [
                (lon, self.lat_min),
                (lon, self.lat_max),
                (self.lon_min, lat),
                (self.lon_max, lat),
            ]
        })
    }
}

/// A raster grid: `rows × cols` square pixels of `spacing` metres, outer corner at map
/// (x0, y0) (north-west), in `crs`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Grid {
    pub crs: Crs,
    pub rows: usize,
    pub cols: usize,
    pub x0: f64,
    pub y0: f64,
    pub spacing: f64,
}

/// The most pixels one grid may have (2³¹: a 46 000² region); larger regions are split into
/// several runs.
pub const MAX_PIXELS: usize = 1 << 31;

impl Grid {
    /// A validated grid.
    pub fn new(
        crs: Crs,
        rows: usize,
        cols: usize,
        x0: f64,
        y0: f64,
        spacing: f64,
    ) -> Result<Self, GridError> {
        crs.validate()?;
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(GridError::Invalid(format!(
                "spacing {spacing} m must be a positive number"
            )));
        }
        if rows == 0 || cols == 0 || rows.checked_mul(cols).is_none_or(|n| n > MAX_PIXELS) {
            return Err(GridError::Invalid(format!(
                "{rows} × {cols} pixels: need at least 1 × 1 and at most {MAX_PIXELS} pixels"
            )));
        }
        if !(x0.is_finite() && y0.is_finite()) {
            return Err(GridError::Invalid(format!(
                "origin ({x0}, {y0}) is not finite"
            )));
        }
        Ok(Grid {
            crs,
            rows,
            cols,
            x0,
            y0,
            spacing,
        })
    }

    /// The smallest grid in `crs` with pixels of `spacing` metres aligned to multiples of the
    /// spacing (so grids of one CRS and spacing share pixel edges) that covers `region`.
    pub fn covering(crs: Crs, region: &LonLatBox, spacing: f64) -> Result<Self, GridError> {
        region.validate()?;
        let pr = crs.projector()?;
        let (mut xmin, mut xmax, mut ymin, mut ymax) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
        let (clon, clat) = region.centre();
        for (lon, lat) in region.border(256).chain([(clon, clat)]) {
            let (x, y) = pr.forward(lon, lat).ok_or_else(|| {
                GridError::Invalid(format!(
                    "region point lon {lon}, lat {lat} cannot be projected in {}: choose a projection centred on the region",
                    crs.name()
                ))
            })?;
            xmin = xmin.min(x);
            xmax = xmax.max(x);
            ymin = ymin.min(y);
            ymax = ymax.max(y);
        }
        if !(spacing.is_finite() && spacing > 0.0) {
            return Err(GridError::Invalid(format!(
                "spacing {spacing} m must be a positive number"
            )));
        }
        let (c0, c1) = ((xmin / spacing).floor(), (xmax / spacing).ceil());
        let (r0, r1) = ((ymin / spacing).floor(), (ymax / spacing).ceil());
        let cols = (c1 - c0).max(1.0);
        let rows = (r1 - r0).max(1.0);
        if cols * rows > MAX_PIXELS as f64 {
            return Err(GridError::Invalid(format!(
                "the region needs {rows} × {cols} pixels at {spacing} m: more than {MAX_PIXELS}; use a coarser spacing or a smaller region"
            )));
        }
        Grid::new(
            crs,
            rows as usize,
            cols as usize,
            c0 * spacing,
            r1 * spacing,
            spacing,
        )
    }

    /// Map coordinates of the centre of pixel (row, col); fractional indices are allowed.
    pub fn xy(&self, row: f64, col: f64) -> (f64, f64) {
        (
            self.x0 + (col + 0.5) * self.spacing,
            self.y0 - (row + 0.5) * self.spacing,
        )
    }

    /// Fractional (row, col) of map (x, y), pixel centres at whole numbers.
    pub fn pixel(&self, x: f64, y: f64) -> (f64, f64) {
        (
            (self.y0 - y) / self.spacing - 0.5,
            (x - self.x0) / self.spacing - 0.5,
        )
    }

    /// GDAL's geotransform (x0, ε, 0, y0, 0, −ε): corner convention, north up.
    pub fn geotransform(&self) -> [f64; 6] {
        [self.x0, self.spacing, 0.0, self.y0, 0.0, -self.spacing]
    }

    /// The sub-grid of rows `r0..r0 + rows`, cols `c0..c0 + cols` (may extend past this grid:
    /// tiles with halos do).
    pub fn window(&self, r0: isize, c0: isize, rows: usize, cols: usize) -> Grid {
        Grid {
            rows,
            cols,
            x0: self.x0 + c0 as f64 * self.spacing,
            y0: self.y0 - r0 as f64 * self.spacing,
            ..*self
        }
    }

    /// (lon, lat) of every pixel centre and the grid bearing of north there; NaN where the
    /// projection is undefined.
    pub fn geographic(&self, pr: &Projector) -> Geographic {
        let mut lon = Array2::from_elem((self.rows, self.cols), f64::NAN);
        let mut lat = lon.clone();
        let mut bearing = lon.clone();
        Zip::indexed(&mut lon)
            .and(&mut lat)
            .and(&mut bearing)
            .par_for_each(|(r, c), lo, la, b| {
                let (x, y) = self.xy(r as f64, c as f64);
                if let Some((o, a)) = pr.inverse(x, y) {
                    *lo = o;
                    *la = a;
                    *b = pr.north_bearing(o, a).unwrap_or(f64::NAN);
                }
            });
        Geographic { lon, lat, bearing }
    }
}

/// Per-pixel geography of a grid: east longitude and latitude of each centre (degrees), and the
/// grid bearing of true north there (radians, clockwise from map +y); NaN where undefined.
#[derive(Debug, Clone)]
pub struct Geographic {
    pub lon: Array2<f64>,
    pub lat: Array2<f64>,
    pub bearing: Array2<f64>,
}

/// Interpolation kernel for resampling a regular raster.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Interpolation {
    /// Bilinear: 2 × 2 support.
    Bilinear,
    /// Keys' cubic convolution with a = −½ (Catmull–Rom; reproduces quadratics): 4 × 4 support.
    #[default]
    Bicubic,
}

/// Keys (1981) cubic convolution weight with a = −½ at offset t.
fn keys(t: f64) -> f64 {
    let t = t.abs();
    if t <= 1.0 {
        (1.5 * t - 2.5) * t * t + 1.0
    } else if t < 2.0 {
        ((-0.5 * t + 2.5) * t - 4.0) * t + 2.0
    } else {
        0.0
    }
}

/// Positions within this many pixels of a centre are taken to be on it.
const NODE_TOLERANCE: f64 = 1e-9;

/// Whole and fractional part of a position, with positions within [`NODE_TOLERANCE`] of a
/// whole number snapped onto it: the support of an interpolation (and so whether it touches
/// no-data) must not hinge on rounding, or one map pixel could be data on one window of a grid
/// and no-data on another.
fn split(x: f64) -> (isize, f64) {
    let n = x.round();
    if (x - n).abs() <= NODE_TOLERANCE {
        (n as isize, 0.0)
    } else {
        (x.floor() as isize, x - x.floor())
    }
}

/// Interpolate `src` at fractional (row, col) (centres at whole numbers). Columns wrap modulo
/// `src.ncols()` when `wrap_cols` (a product spanning 360° of longitude); otherwise a support
/// that leaves the raster, or touches a NaN, gives NaN (no data propagates, never invents).
pub fn interpolate(
    src: ArrayView2<f64>,
    row: f64,
    col: f64,
    method: Interpolation,
    wrap_cols: bool,
) -> f64 {
    if !(row.is_finite() && col.is_finite()) {
        return f64::NAN;
    }
    let (nr, nc) = (src.nrows() as isize, src.ncols() as isize);
    let ((r0, tr), (c0, tc)) = (split(row), split(col));
    let (lo, n) = match method {
        Interpolation::Bilinear => (0, 2),
        Interpolation::Bicubic => (-1, 4),
    };
    let weight = |t: f64, k: isize| match method {
        Interpolation::Bilinear => {
            if k == 0 {
                1.0 - t
            } else {
                t
            }
        }
        Interpolation::Bicubic => keys(t - k as f64),
    };
    let mut acc = 0.0;
    for i in lo..lo + n {
        let r = r0 + i;
        let wr = weight(tr, i);
        if wr == 0.0 {
            continue;
        }
        if r < 0 || r >= nr {
            return f64::NAN;
        }
        for j in lo..lo + n {
            let wc = weight(tc, j);
            if wc == 0.0 {
                continue;
            }
            let mut c = c0 + j;
            if wrap_cols {
                c = c.rem_euclid(nc);
            } else if c < 0 || c >= nc {
                return f64::NAN;
            }
            let v = src[(r as usize, c as usize)];
            if !v.is_finite() {
                return f64::NAN;
            }
            acc += wr * wc * v;
        }
    }
    acc
}

/// Tolerance, in grid pixels and in barycentric weight, for a grid pixel centre to count as
/// inside a swath triangle.
const EDGE_TOLERANCE: f64 = 1e-7;

/// The grid indices `lo..=hi` (within `0..n`) between the least and greatest of three
/// coordinates, widened by [`EDGE_TOLERANCE`]; `None` when no index falls in between.
fn span(x: [f64; 3], n: usize) -> Option<(usize, usize)> {
    let lo = (x[0].min(x[1]).min(x[2]) - EDGE_TOLERANCE).ceil().max(0.0);
    let hi = (x[0].max(x[1]).max(x[2]) + EDGE_TOLERANCE)
        .floor()
        .min(n as f64 - 1.0);
    (lo <= hi).then_some((lo as usize, hi as usize))
}

/// Where each grid pixel centre falls in a swath whose pixel (line, sample) centres are at map
/// positions given by `lon`/`lat` (degrees, NaN = unknown): fractional (line, sample) per grid
/// pixel, NaN outside the swath.
///
/// The swath is treated as a mesh: each cell between four neighbouring pixel centres is split
/// into two triangles, projected into the grid, and every grid centre inside a triangle gets
/// the barycentric blend of the triangle's (line, sample). Neighbouring triangles share edges,
/// so the covered area has no holes; outside the outermost centres stays no-data. Where a
/// swath folds over itself (it does not in orbital push-broom data), the later line wins —
/// deterministic, the same for any thread count.
pub fn swath_positions(
    grid: &Grid,
    pr: &Projector,
    lon: ArrayView2<f64>,
    lat: ArrayView2<f64>,
) -> (Array2<f64>, Array2<f64>) {
    let (gr, gc) = swath_grid_positions(grid, pr, lon, lat);
    swath_positions_from(grid, gr.view(), gc.view(), 0)
}

/// Grid (row, column) of every swath pixel centre whose map position is `lon`/`lat` (degrees);
/// NaN where it does not project.
pub fn swath_grid_positions(
    grid: &Grid,
    pr: &Projector,
    lon: ArrayView2<f64>,
    lat: ArrayView2<f64>,
) -> (Array2<f64>, Array2<f64>) {
    let mut gr = Array2::from_elem(lon.dim(), f64::NAN);
    let mut gc = gr.clone();
    Zip::from(&mut gr)
        .and(&mut gc)
        .and(lon)
        .and(lat)
        .par_for_each(|r, c, &lo, &la| {
            if let Some((x, y)) = pr.forward(lo, la) {
                (*r, *c) = grid.pixel(x, y);
            }
        });
    (gr, gc)
}

/// The samples `[s0, s1)` of a swath (grid positions `gr`, `gc` of its pixel centres,
/// [`swath_grid_positions`]) that [`swath_positions`] and a bilinear interpolation of the
/// swath can use on `grid`: every sample within L + 1 grid pixels of the grid, L the longest
/// edge of the swath's mesh, widened by two samples on each side (a triangle that reaches a
/// grid pixel has its vertices within L of it, and the interpolation's neighbours are the
/// triangle's). `None` where no sample is that near. A tile narrower than the swath then
/// resamples only its own part of each line, with the same values as the whole line gives.
pub fn swath_samples(
    grid: &Grid,
    gr: ArrayView2<f64>,
    gc: ArrayView2<f64>,
) -> Option<(usize, usize)> {
    let (nl, ns) = gr.dim();
    let mut edge = 0.0f64;
    for i in 0..nl {
        for j in 0..ns {
            for (a, b) in [(i, j + 1), (i + 1, j), (i + 1, j + 1)] {
                if a < nl && b < ns {
                    let d = (gr[(a, b)] - gr[(i, j)]).hypot(gc[(a, b)] - gc[(i, j)]);
                    if d.is_finite() {
                        edge = edge.max(d);
                    }
                }
            }
        }
    }
    let m = edge + 1.0;
    let (rows, cols) = (grid.rows as f64, grid.cols as f64);
    let (mut lo, mut hi) = (usize::MAX, 0);
    Zip::indexed(gr).and(gc).for_each(|(_, j), &r, &c| {
        if r >= -m && r <= rows - 1.0 + m && c >= -m && c <= cols - 1.0 + m {
            lo = lo.min(j);
            hi = hi.max(j);
        }
    });
    (lo <= hi).then(|| (lo.saturating_sub(2), (hi + 3).min(ns)))
}

/// Every [`SAMPLE_STRIDE`]-th sample of each line (and the last): enough to bound the samples
/// that can reach a window ([`swath_sample_superset`]) at a fraction of the projections.
pub const SAMPLE_STRIDE: usize = 8;

/// A range `[c0, c1)` of samples that contains [`swath_samples`]' range for `grid`, found by
/// projecting only every [`SAMPLE_STRIDE`]-th sample of each line (longitudes `lon`, latitudes
/// `lat`, degrees): the samples within 3·L_c + 4 grid pixels of the grid, L_c the longest edge
/// between neighbouring projected samples, widened by a stride and the two samples
/// [`swath_samples`] adds on each side. A sample within L + 1 of the grid (L the fine mesh's
/// longest edge, ≤ L_c) lies within L_c of a projected neighbour, which is then within the
/// margin. `None` where no projected sample is near: the caller projects the whole lines.
pub fn swath_sample_superset(
    grid: &Grid,
    pr: &Projector,
    lon: ArrayView2<f64>,
    lat: ArrayView2<f64>,
) -> Option<(usize, usize)> {
    let (nl, ns) = lon.dim();
    if ns == 0 || nl == 0 {
        return None;
    }
    let mut picks: Vec<usize> = (0..ns).step_by(SAMPLE_STRIDE).collect();
    if picks.last() != Some(&(ns - 1)) {
        picks.push(ns - 1);
    }
    let at = |i: usize, j: usize| {
        pr.forward(lon[(i, j)], lat[(i, j)])
            .map(|(x, y)| grid.pixel(x, y))
            .filter(|(r, c)| r.is_finite() && c.is_finite())
    };
    let pos: Vec<Vec<Option<(f64, f64)>>> = (0..nl)
        .into_par_iter()
        .map(|i| picks.iter().map(|&j| at(i, j)).collect())
        .collect();
    let dist = |a: Option<(f64, f64)>, b: Option<(f64, f64)>| match (a, b) {
        (Some(a), Some(b)) => (a.0 - b.0).hypot(a.1 - b.1),
        _ => 0.0,
    };
    let mut edge = 0.0f64;
    for i in 0..nl {
        for k in 0..picks.len() {
            if k + 1 < picks.len() {
                edge = edge.max(dist(pos[i][k], pos[i][k + 1]));
            }
            if i + 1 < nl {
                edge = edge.max(dist(pos[i][k], pos[i + 1][k]));
            }
        }
    }
    let m = 3.0 * edge + 4.0;
    let (rows, cols) = (grid.rows as f64, grid.cols as f64);
    let (mut lo, mut hi) = (usize::MAX, 0);
    for row in &pos {
        for (&j, p) in picks.iter().zip(row) {
            if let Some((r, c)) = *p {
                if r >= -m && r <= rows - 1.0 + m && c >= -m && c <= cols - 1.0 + m {
                    lo = lo.min(j);
                    hi = hi.max(j);
                }
            }
        }
    }
    (lo <= hi).then(|| {
        (
            lo.saturating_sub(SAMPLE_STRIDE + 2),
            (hi + SAMPLE_STRIDE + 3).min(ns),
        )
    })
}

/// [`swath_positions`] from the grid positions of the samples `[sample_offset, …)` of each
/// line ([`swath_grid_positions`], [`swath_samples`]); the samples it returns count from the
/// swath's first, as the whole line's would.
pub fn swath_positions_from(
    grid: &Grid,
    gr: ArrayView2<f64>,
    gc: ArrayView2<f64>,
    sample_offset: usize,
) -> (Array2<f64>, Array2<f64>) {
    let (nl, ns) = gr.dim();
    let mut line = Array2::from_elem((grid.rows, grid.cols), f64::NAN);
    let mut sample = line.clone();
    let mut fill = |v: [(f64, f64, f64, f64); 3]| {
        // v[k] = (grid row, grid col, swath line, swath sample).
        if v.iter().any(|p| !(p.0.is_finite() && p.1.is_finite())) {
            return;
        }
        // The bounding box and the barycentric test share one tolerance, so a grid pixel
        // centre on a triangle's edge or vertex (as when the swath and the grid share a
        // lattice) is filled whatever rounding put it a hair outside: one pixel gets the same
        // value on every window of the grid.
        let (Some((rmin, rmax)), Some((cmin, cmax))) = (
            span(v.map(|p| p.0), grid.rows),
            span(v.map(|p| p.1), grid.cols),
        ) else {
            return;
        };
        let det = (v[1].1 - v[0].1) * (v[2].0 - v[0].0) - (v[2].1 - v[0].1) * (v[1].0 - v[0].0);
        if det.abs() < 1e-12 {
            return;
        }
        // Barycentric tolerance: points on a shared edge belong to both triangles.
        let tol = -EDGE_TOLERANCE;
        for r in rmin..=rmax {
            for c in cmin..=cmax {
                let (y, x) = (r as f64, c as f64);
                let b1 =
                    ((x - v[0].1) * (v[2].0 - v[0].0) - (v[2].1 - v[0].1) * (y - v[0].0)) / det;
                let b2 =
                    ((v[1].1 - v[0].1) * (y - v[0].0) - (x - v[0].1) * (v[1].0 - v[0].0)) / det;
                let b0 = 1.0 - b1 - b2;
                if b0 >= tol && b1 >= tol && b2 >= tol {
                    line[(r, c)] = b0 * v[0].2 + b1 * v[1].2 + b2 * v[2].2;
                    sample[(r, c)] = b0 * v[0].3 + b1 * v[1].3 + b2 * v[2].3;
                }
            }
        }
    };
    for i in 0..nl.saturating_sub(1) {
        for j in 0..ns.saturating_sub(1) {
            let p =
                |a: usize, b: usize| (gr[(a, b)], gc[(a, b)], a as f64, (b + sample_offset) as f64);
            let (a, b, c, d) = (p(i, j), p(i, j + 1), p(i + 1, j), p(i + 1, j + 1));
            fill([a, b, d]);
            fill([a, d, c]);
        }
    }
    (line, sample)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A stereographic CRS centred on (0°, 0°) and its projector.
    fn centred() -> (Crs, Projector) {
        let crs = Crs::Stereographic {
            lat_0: 0.0,
            lon_0: 0.0,
        };
        (crs, crs.projector().unwrap())
    }

    /// The longitudes and latitudes of an `nl` × `ns` swath whose pixel (line, sample) lies at
    /// map point `place(line, sample)`, rotated by `deg` about the origin.
    fn swath_lon_lat(
        pr: &Projector,
        (nl, ns): (usize, usize),
        deg: f64,
        place: impl Fn(f64, f64) -> (f64, f64),
    ) -> (Array2<f64>, Array2<f64>) {
        let (a, s) = (deg.to_radians().cos(), deg.to_radians().sin());
        let mut lon = Array2::zeros((nl, ns));
        let mut lat = Array2::zeros((nl, ns));
        for ((l, m), v) in lon.indexed_iter_mut() {
            let (u, w) = place(l as f64, m as f64);
            (*v, lat[(l, m)]) = pr.inverse(u * a - w * s, u * s + w * a).unwrap();
        }
        (lon, lat)
    }

    /// A position a rounding error off a centre interpolates as the centre itself: its
    /// support does not reach a no-data neighbour.
    #[test]
    fn positions_a_hair_off_a_centre_do_not_touch_no_data_beyond_it() {
        let mut a = Array2::from_shape_fn((3, 3), |(i, j)| (i * 3 + j) as f64);
        a[(1, 2)] = f64::NAN;
        a[(2, 1)] = f64::NAN;
        for m in [Interpolation::Bilinear, Interpolation::Bicubic] {
            for (r, c) in [(1.0 + 1e-12, 1.0 + 1e-12), (1.0 - 1e-12, 1.0), (1.0, 1.0)] {
                assert_eq!(interpolate(a.view(), r, c, m, false), 4.0, "({r}, {c})");
            }
            assert!(interpolate(a.view(), 1.0, 1.0 + 1e-6, m, false).is_nan());
        }
        assert_eq!(split(2.0 - 1e-12), (2, 0.0));
        assert_eq!(split(-1e-12), (0, 0.0));
        assert_eq!(split(0.25), (0, 0.25));
    }

    /// A grid centre on a triangle vertex or edge is filled even when rounding puts the
    /// vertex a hair past it.
    #[test]
    fn swath_triangles_cover_grid_centres_on_their_edges() {
        assert_eq!(span([3.0 + 1e-12, 5.5, 4.0], 10), Some((3, 5)));
        assert_eq!(span([2.0, 3.0 - 1e-12, 2.5], 10), Some((2, 3)));
        assert_eq!(span([2.2, 2.9, 2.5], 10), None);
        assert_eq!(span([-1.0, 12.0, 3.0], 10), Some((0, 9)));
    }

    #[test]
    fn keys_kernel_reproduces_quadratics_and_bilinear_planes() {
        let src = Array2::from_shape_fn((8, 8), |(r, c)| {
            let (y, x) = (r as f64, c as f64);
            0.5 * y * y - 0.25 * x * y + 3.0 * x + 1.0
        });
        let f = |y: f64, x: f64| 0.5 * y * y - 0.25 * x * y + 3.0 * x + 1.0;
        for (r, c) in [(3.3, 4.7), (2.0, 2.5), (4.99, 3.01)] {
            let v = interpolate(src.view(), r, c, Interpolation::Bicubic, false);
            assert!((v - f(r, c)).abs() < 1e-9, "{v} vs {}", f(r, c));
        }
        let plane = Array2::from_shape_fn((4, 4), |(r, c)| 2.0 * r as f64 - c as f64);
        let v = interpolate(plane.view(), 1.25, 2.5, Interpolation::Bilinear, false);
        assert!((v - (2.5 - 2.5)).abs() < 1e-12);
        // Off the raster, or touching NaN: no data.
        assert!(interpolate(plane.view(), 0.5, 3.5, Interpolation::Bilinear, false).is_nan());
        assert!(interpolate(src.view(), 0.5, 3.0, Interpolation::Bicubic, false).is_nan());
        // Wrapping columns (a 360° product).
        let w = interpolate(plane.view(), 1.0, 3.5, Interpolation::Bilinear, true);
        assert!((w - 0.5 * ((2.0 - 3.0) + 2.0)).abs() < 1e-12);
        let mut holed = plane.clone();
        holed[(2, 2)] = f64::NAN;
        assert!(interpolate(holed.view(), 1.5, 1.5, Interpolation::Bilinear, false).is_nan());
    }

    #[test]
    fn projections_round_trip_and_north_points_north() {
        for crs in [
            Crs::Stereographic {
                lat_0: -13.4,
                lon_0: 357.2,
            },
            Crs::Orthographic {
                lat_0: 9.5,
                lon_0: 38.0,
            },
            Crs::PolarStereographic { north: false },
            Crs::Equirectangular { lon_0: 180.0 },
        ] {
            let pr = crs.projector().unwrap();
            let (lon, lat) = match crs {
                Crs::PolarStereographic { .. } => (129.2, -85.0),
                Crs::Stereographic { .. } => (-1.5, -12.0),
                _ => (39.0, 10.2),
            };
            let (x, y) = pr.forward(lon, lat).unwrap();
            let (lo, la) = pr.inverse(x, y).unwrap();
            assert!(
                ((lo - lon + 540.0).rem_euclid(360.0) - 180.0).abs() < 1e-9
                    && (la - lat).abs() < 1e-9
            );
            // A step north moves the point along the bearing.
            let b = pr.north_bearing(lon, lat).unwrap();
            let (x1, y1) = pr.forward(lon, lat + 0.01).unwrap();
            let d = (x1 - x).atan2(y1 - y);
            assert!((d - b).abs() < 1e-4, "{crs:?}: {d} vs {b}");
        }
        // South polar: 90° E lies on map +x, and north (increasing latitude) points away
        // from the pole, so along map +x as well.
        let pr = Crs::PolarStereographic { north: false }
            .projector()
            .unwrap();
        let b = pr.north_bearing(90.0, -80.0).unwrap();
        assert!((b - std::f64::consts::FRAC_PI_2).abs() < 1e-6, "{b}");
        let v = enu_to_grid([0.0, 1.0, 0.0], b);
        assert!((v[0] - 1.0).abs() < 1e-6 && v[1].abs() < 1e-6);
        // …and east there points along map −y (towards the bottom of the map).
        let e = enu_to_grid([1.0, 0.0, 0.0], b);
        assert!(e[0].abs() < 1e-6 && (e[1] + 1.0).abs() < 1e-6);
    }

    #[test]
    fn covering_grid_contains_the_region_and_is_aligned() {
        let region = LonLatBox {
            lon_min: 355.0,
            lon_max: 359.0,
            lat_min: -15.0,
            lat_max: -11.0,
        };
        let (clon, clat) = region.centre();
        let crs = Crs::Stereographic {
            lat_0: clat,
            lon_0: clon,
        };
        let g = Grid::covering(crs, &region, 100.0).unwrap();
        assert_eq!(g.x0 % 100.0, 0.0);
        assert_eq!(g.y0 % 100.0, 0.0);
        // 4° of latitude ≈ 121 km ≈ 1213 px.
        assert!((1200..1240).contains(&g.rows), "{}", g.rows);
        let pr = crs.projector().unwrap();
        for (lon, lat) in region.border(16) {
            let (x, y) = pr.forward(lon, lat).unwrap();
            let (r, c) = g.pixel(x, y);
            assert!(r >= -0.5 && c >= -0.5 && r <= g.rows as f64 - 0.5 && c <= g.cols as f64 - 0.5);
        }
        assert!(Grid::covering(
            crs,
            &LonLatBox {
                lat_min: 5.0,
                ..region
            },
            100.0
        )
        .is_err());
        assert!(Grid::covering(crs, &region, -1.0).is_err());
    }

    #[test]
    fn swath_mesh_fills_without_holes_and_inverts_the_mapping() {
        // A synthetic swath: 40 lines × 30 samples, rotated 20° against the grid and skewed,
        // in a stereographic grid at the centre.
        let (crs, pr) = centred();
        let g = Grid::new(crs, 50, 50, -2500.0, 2500.0, 100.0).unwrap();
        let (a, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
        let (lon, lat) = swath_lon_lat(&pr, (40, 30), 20.0, |l, m| {
            (m * 130.0 - 1900.0, 2400.0 - l * 120.0 + m * 5.0)
        });
        let (line, sample) = swath_positions(&g, &pr, lon.view(), lat.view());
        // The placement is affine in map coordinates, so each grid centre has an exact
        // (line, sample), which barycentric interpolation reproduces: inside the swath's
        // outermost centres every pixel is filled with it (no holes), outside none is.
        let mut inside = 0;
        for ((r, c), &l) in line.indexed_iter() {
            let (x, y) = g.xy(r as f64, c as f64);
            let (u, v) = (x * a + y * s, -x * s + y * a);
            let m = (u + 1900.0) / 130.0;
            let l_exp = (2400.0 - v + 5.0 * m) / 120.0;
            let strictly_in =
                (1e-6..39.0 - 1e-6).contains(&l_exp) && (1e-6..29.0 - 1e-6).contains(&m);
            let strictly_out =
                !(-1e-6..=39.0 + 1e-6).contains(&l_exp) || !(-1e-6..=29.0 + 1e-6).contains(&m);
            if strictly_in {
                inside += 1;
                assert!(
                    (l - l_exp).abs() < 1e-6 && (sample[(r, c)] - m).abs() < 1e-6,
                    "({r},{c}): {l} {} vs {l_exp} {m}",
                    sample[(r, c)]
                );
            } else if strictly_out {
                assert!(
                    l.is_nan() && sample[(r, c)].is_nan(),
                    "({r},{c}) outside the swath got {l}"
                );
            }
        }
        assert!(inside > 1000, "{inside}");
    }

    /// Projecting every 8th sample bounds the samples a window needs: on a curved, rotated
    /// swath wider than the windows, the superset holds [`swath_samples`]' range of the whole
    /// lines, and the resampling from it is the whole lines' to the bit.
    #[test]
    fn a_sample_superset_resamples_a_window_as_the_whole_lines_do() {
        let (crs, pr) = centred();
        let g = Grid::new(crs, 120, 120, -6000.0, 6000.0, 100.0).unwrap();
        // 60 lines × 203 samples of ≈ 70 m, bent along the line (a quadratic in the sample),
        // rotated 25°.
        let ns = 203;
        let (lon, lat) = swath_lon_lat(&pr, (60, ns), 25.0, |l, m| {
            let u = m * 70.0 - 7000.0;
            (u, 5800.0 - l * 190.0 + 2e-4 * u * u)
        });
        let mut narrower = 0;
        for (r0, c0) in [(0, 0), (40, 70), (80, 10), (10, 90), (60, 60)] {
            let w = g.window(r0, c0, 40, 30);
            let (gr, gc) = swath_grid_positions(&w, &pr, lon.view(), lat.view());
            let Some((s0, s1)) = swath_samples(&w, gr.view(), gc.view()) else {
                continue;
            };
            let (u0, u1) = swath_sample_superset(&w, &pr, lon.view(), lat.view()).unwrap();
            assert!(
                u0 <= s0 && s1 <= u1,
                "window ({r0}, {c0}): {s0}..{s1} not in {u0}..{u1}"
            );
            narrower += usize::from(u1 - u0 < ns);
            let cols = ndarray::s![.., s0..s1];
            let whole = swath_positions_from(&w, gr.slice(cols), gc.slice(cols), s0);
            let sub = ndarray::s![.., u0..u1];
            let (sr, sc) = swath_grid_positions(&w, &pr, lon.slice(sub), lat.slice(sub));
            let (t0, t1) = swath_samples(&w, sr.view(), sc.view()).unwrap();
            let within = ndarray::s![.., t0..t1];
            let part = swath_positions_from(&w, sr.slice(within), sc.slice(within), u0 + t0);
            for (x, y) in whole
                .0
                .iter()
                .zip(&part.0)
                .chain(whole.1.iter().zip(&part.1))
            {
                assert!(
                    x.to_bits() == y.to_bits(),
                    "window ({r0}, {c0}): {x} vs {y}"
                );
            }
        }
        assert!(narrower >= 3, "{narrower}");
    }
}
