//! GeoKeys (GeoTIFF tags 34735–34737) for the lunar CRSs, both ways: written from a [`Crs`],
//! read back into one (or refused with the key that does not fit).

use super::*;

/// The three GeoTIFF key tags.
pub(super) struct GeoKeys {
    pub(super) directory: Vec<u16>,
    pub(super) doubles: Vec<f64>,
    pub(super) ascii: String,
}

/// GeoKeys (OGC GeoTIFF 1.1) for a user-defined projected CRS on the Moon sphere:
/// a user-defined geographic CRS (2048 = 32767) whose citation names datum, ellipsoid and
/// prime meridian in the form GDAL reads ("GCS Name = …|Datum = …|Ellipsoid = …|Primem = …|"),
/// semi-axes 1 737 400 m, and the coordinate transformation with its parameters.
pub(super) fn geokeys(crs: &Crs) -> GeoKeys {
    let mut keys: Vec<(u16, u16, u16, u16)> = Vec::new(); // (id, location, count, value)
    let mut dbl = Vec::new();
    let mut asc = String::new();
    let mut push_ascii = |keys: &mut Vec<(u16, u16, u16, u16)>, id: u16, s: &str| {
        let start = asc.len() as u16;
        asc.push_str(s);
        asc.push('|');
        keys.push((id, 34737, (s.len() + 1) as u16, start));
    };
    let mut push_dbl = |keys: &mut Vec<(u16, u16, u16, u16)>, id: u16, v: f64| {
        keys.push((id, 34736, 1, dbl.len() as u16));
        dbl.push(v);
    };
    keys.push((1024, 0, 1, 1)); // GTModelType: projected
    keys.push((1025, 0, 1, 1)); // GTRasterType: PixelIsArea
    push_ascii(&mut keys, 1026, &crs.name());
    keys.push((2048, 0, 1, 32767)); // GeodeticCRS: user-defined
    push_ascii(
        &mut keys,
        2049,
        "GCS Name = Moon (2015) - Sphere / Ocentric|Datum = Moon (2015) - Sphere|Ellipsoid = Moon (2015) - Sphere|Primem = Reference Meridian",
    );
    keys.push((2050, 0, 1, 32767)); // GeodeticDatum: user-defined
    keys.push((2054, 0, 1, 9102)); // GeogAngularUnits: degree
    keys.push((2056, 0, 1, 32767)); // Ellipsoid: user-defined
    push_dbl(&mut keys, 2057, MOON_RADIUS_M);
    push_dbl(&mut keys, 2058, MOON_RADIUS_M);
    keys.push((3072, 0, 1, 32767)); // ProjectedCRS: user-defined
    keys.push((3074, 0, 1, 32767)); // Projection: user-defined
    let (ct, params): (u16, Vec<(u16, f64)>) = match *crs {
        // CT_Equirectangular: ProjCenterLat, ProjCenterLong, ProjStdParallel1.
        Crs::Equirectangular { lon_0 } => (17, vec![(3078, 0.0), (3088, lon_0), (3089, 0.0)]),
        // CT_PolarStereographic: ProjNatOriginLat, ProjScaleAtNatOrigin, ProjStraightVertPoleLong.
        Crs::PolarStereographic { north } => (
            15,
            vec![
                (3081, if north { 90.0 } else { -90.0 }),
                (3092, 1.0),
                (3095, 0.0),
            ],
        ),
        // CT_Stereographic: ProjCenterLong, ProjCenterLat, ProjScaleAtNatOrigin.
        Crs::Stereographic { lat_0, lon_0 } => {
            (14, vec![(3088, lon_0), (3089, lat_0), (3092, 1.0)])
        }
        // CT_Orthographic: ProjCenterLong, ProjCenterLat.
        Crs::Orthographic { lat_0, lon_0 } => (21, vec![(3088, lon_0), (3089, lat_0)]),
    };
    keys.push((3075, 0, 1, ct));
    keys.push((3076, 0, 1, 9001)); // ProjLinearUnits: metre
    for (id, v) in params.into_iter().chain([(3082, 0.0), (3083, 0.0)]) {
        push_dbl(&mut keys, id, v);
    }
    keys.sort_by_key(|k| k.0);
    let mut directory = vec![1, 1, 0, keys.len() as u16];
    for (id, loc, count, value) in keys {
        directory.extend_from_slice(&[id, loc, count, value]);
    }
    GeoKeys {
        directory,
        doubles: dbl,
        ascii: asc,
    }
}

/// What a GeoTIFF's GeoKeys say its CRS is, when it is one of ours.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GeoTiffCrs {
    Projected(Crs),
    /// Longitude/latitude in degrees on the Moon sphere.
    Geographic,
}

/// Read the CRS from GeoKeys (tags 34735/34736): the Moon sphere (semi-major axis 1 737 400 m,
/// no flattening) with one of the coordinate transformations `geokeys` writes — CT 17
/// (equirectangular, standard parallel 0), 15 (polar stereographic, pole longitude 0), 14/16
/// (stereographic, scale 1), 21 (orthographic) — metres, no false easting/northing; or a
/// geographic model. Anything else is refused with the key that does not fit.
pub fn crs_from_geokeys(path: &Path, dir: &[u16], doubles: &[f64]) -> Result<GeoTiffCrs> {
    let bad = |why: String| {
        Error::Usage(format!("{}: GeoKeys: {why}; give a DEM on the IAU 2015 Moon sphere in an equirectangular, polar stereographic, stereographic or orthographic projection (or reproject it with gdalwarp)", path.display()))
    };
    if dir.len() < 4 || dir[0] != 1 {
        return Err(bad("no GeoKey directory".into()));
    }
    let n = dir[3] as usize;
    if dir.len() < 4 + 4 * n {
        return Err(bad("the key directory is shorter than it says".into()));
    }
    let key = |id: u16| -> Option<f64> {
        dir[4..4 + 4 * n]
            .chunks_exact(4)
            .find(|k| k[0] == id)
            .and_then(|k| match k[1] {
                0 => Some(k[3] as f64),
                34736 => doubles.get(k[3] as usize).copied(),
                _ => None,
            })
    };
    let a = key(2057).ok_or_else(|| {
        bad("no semi-major axis (key 2057): not a Moon CRS sphere sfsfuse can check".into())
    })?;
    let b = key(2058).unwrap_or(a);
    let inv_f = key(2059).unwrap_or(0.0);
    if (a - MOON_RADIUS_M).abs() > 1.0 || (b - a).abs() > 1.0 || inv_f != 0.0 {
        return Err(bad(format!(
            "the ellipsoid is a = {a} m, b = {b} m, 1/f = {inv_f}, not the 1 737 400 m Moon sphere"
        )));
    }
    match key(1024).map(|v| v as u16) {
        Some(2) => return Ok(GeoTiffCrs::Geographic),
        Some(1) => {}
        other => {
            return Err(bad(format!(
                "model type (key 1024) {other:?} is neither projected nor geographic"
            )))
        }
    }
    if key(3076).is_some_and(|u| u != 9001.0) {
        return Err(bad("linear units (key 3076) are not metres".into()));
    }
    if key(3082).unwrap_or(0.0) != 0.0 || key(3083).unwrap_or(0.0) != 0.0 {
        return Err(bad(
            "false easting/northing (keys 3082/3083) are not 0".into()
        ));
    }
    let lat = key(3089).or(key(3081)).unwrap_or(0.0);
    let lon = key(3088).or(key(3080)).unwrap_or(0.0);
    let crs = match key(3075).map(|v| v as u16) {
        Some(17) => {
            if key(3078).unwrap_or(0.0) != 0.0 || lat != 0.0 {
                return Err(bad(
                    "equirectangular with a standard parallel or origin latitude other than 0"
                        .into(),
                ));
            }
            Crs::Equirectangular { lon_0: lon }
        }
        Some(15) => {
            if key(3095).unwrap_or(0.0) != 0.0 {
                return Err(bad(
                    "polar stereographic with a pole longitude (key 3095) other than 0".into(),
                ));
            }
            Crs::PolarStereographic {
                north: key(3081).unwrap_or(lat) > 0.0,
            }
        }
        Some(14) | Some(16) => {
            if key(3092).or(key(3093)).unwrap_or(1.0) != 1.0 {
                return Err(bad("stereographic with a scale factor other than 1".into()));
            }
            Crs::Stereographic {
                lat_0: lat,
                lon_0: lon,
            }
        }
        Some(21) => Crs::Orthographic {
            lat_0: lat,
            lon_0: lon,
        },
        other => {
            return Err(bad(format!(
                "coordinate transformation (key 3075) {other:?} is not one sfsfuse reads"
            )))
        }
    };
    Ok(GeoTiffCrs::Projected(crs))
}
