//! The run's opened inputs: M3 observations, DEM products (LOLA GDR or GeoTIFF) with their
//! effective resolution, the solar tables (one per observation by its mode), the model.

use super::*;

/// The opened inputs of an orbital run.
pub(super) struct Inputs {
    pub(super) obs: Vec<Observation>,
    pub(super) lola: Vec<Dem>,
    /// Each DEM's offsets between its tracks, taken out of its heights wherever the run reads
    /// it, once the plan has estimated them or read them back ([`Inputs::set_dem_tracks`]).
    pub(super) dem_tracks: Vec<std::sync::OnceLock<ingest::TrackOffsets>>,
    /// The solar tables of `[inputs] solar_spectrum`.
    pub(super) solar: Vec<SolarSpectrum>,
    /// Each observation's table in `solar` ([`solar_per_observation`]).
    pub(super) solar_of: Vec<usize>,
    pub(super) model: Box<dyn ReflectanceModel>,
}

impl Inputs {
    /// Fetch what `[fetch]` lists (cached files are not downloaded again), then open.
    pub(super) fn open(o: &Orbital, progress: &Progress) -> Result<Self> {
        if let Some(f) = &o.fetch {
            progress.stage("fetching inputs");
            crate::fetch::fetch(&f.products, &f.directory, &f.sources, progress)?;
            progress.finish();
        }
        let obs: Vec<Observation> = o
            .inputs
            .m3
            .iter()
            .map(|p| Observation::open(p))
            .collect::<std::result::Result<_, _>>()?;
        check_distinct(&obs)?;
        let solar: Vec<SolarSpectrum> = o
            .inputs
            .solar_spectrum
            .iter()
            .map(|p| SolarSpectrum::read(p))
            .collect::<std::result::Result<_, _>>()?;
        let solar_of = solar_per_observation(&solar, &obs)?;
        let lola: Vec<Dem> = o
            .inputs
            .lola
            .iter()
            .map(|p| Dem::open(p))
            .collect::<Result<_>>()?;
        Ok(Inputs {
            obs,
            dem_tracks: lola.iter().map(|_| std::sync::OnceLock::new()).collect(),
            lola,
            solar,
            solar_of,
            model: o.photometry.build(),
        })
    }

    /// Take each DEM's track offsets (the plan's, in `lola` order; `None`: none) out of every
    /// later read of it. Set once: a second call leaves the first offsets.
    pub(super) fn set_dem_tracks(&self, tracks: &[Option<ingest::TrackOffsets>]) {
        for (cell, t) in self.dem_tracks.iter().zip(tracks) {
            if let Some(t) = t {
                let _ = cell.set(t.clone());
            }
        }
    }

    /// Observation `k`'s solar table.
    pub(super) fn solar(&self, k: usize) -> &SolarSpectrum {
        &self.solar[self.solar_of[k]]
    }

    /// Each observation's L1B label path as text, in `[inputs] m3` order: how the plan's
    /// errors and the run record name the observations.
    pub(super) fn labels(&self) -> Vec<String> {
        self.obs
            .iter()
            .map(|obs| obs.label_path.display().to_string())
            .collect()
    }

    /// Every file the run reads.
    pub(super) fn files(&self) -> Result<Vec<PathBuf>> {
        let mut v = Vec::new();
        for o in &self.obs {
            v.push(o.label_path.clone());
            v.push(o.rdn.path.clone());
            for part in ["LOC", "OBS"] {
                v.push(o.part(part)?.path);
            }
        }
        for d in &self.lola {
            match d {
                Dem::Pds(d) => v.extend([d.label_path.clone(), d.raster.path.clone()]),
                Dem::GeoTiff(d) => v.push(d.path.clone()),
            }
        }
        v.extend(self.solar.iter().map(|s| s.path.clone()));
        v.dedup();
        Ok(v)
    }
}

/// A PDS product's PRODUCT_ID, else its label's file name (without the extension).
pub(super) fn product_id(label: &pds::Label, path: &Path) -> String {
    label
        .get("PRODUCT_ID")
        .and_then(|v| v.as_str())
        .map(str::to_string)
        .unwrap_or_else(|| {
            path.file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default()
        })
}

/// Each observation once. The same L1B product listed twice (by the same label, or by copies
/// whose labels give the same PRODUCT_ID) would count each of its pixels twice: twice its
/// weight in E_I, an `observations` layer of 2 where one image sees the ground, and the
/// several-observation rules (docs/science.md, "Several observations") where there is one
/// Sun.
pub(super) fn check_distinct(obs: &[Observation]) -> Result<()> {
    let key = |o: &Observation| {
        (
            std::fs::canonicalize(&o.label_path).unwrap_or_else(|_| o.label_path.clone()),
            product_id(&o.label, &o.label_path).to_ascii_uppercase(),
        )
    };
    let keys: Vec<_> = obs.iter().map(key).collect();
    for (j, b) in keys.iter().enumerate() {
        if let Some(i) = keys[..j].iter().position(|a| a.0 == b.0 || a.1 == b.1) {
            return Err(Error::Usage(format!(
                "[inputs] m3 lists the observation {} twice (entries {} and {}: {} and {}): each observation may be listed once — remove one of them",
                b.1,
                i + 1,
                j + 1,
                obs[i].label_path.display(),
                obs[j].label_path.display()
            )));
        }
    }
    Ok(())
}

/// Each observation's solar table, as an index into `tables`: the table of its
/// INSTRUMENT_MODE_ID, else one whose mode neither its row count nor its name tells (the first
/// such). The table must follow the observation's band sampling: M3's GLOBAL and TARGET modes
/// have different bands, and a table of the other mode gives the wrong irradiance for the band
/// (its band passes differ) without any other sign. Two tables of one mode are refused: which
/// one holds would be a guess.
pub(super) fn solar_per_observation(
    tables: &[SolarSpectrum],
    obs: &[Observation],
) -> Result<Vec<usize>> {
    let name = pds::m3::Mode::keyword;
    for (j, b) in tables.iter().enumerate() {
        if let Some(a) = tables[..j]
            .iter()
            .find(|a| a.mode().is_some() && a.mode() == b.mode())
        {
            return Err(Error::Usage(format!(
                "[inputs] solar_spectrum lists two {}-mode tables ({} and {}): give one per mode",
                name(b.mode().expect("checked")),
                a.path.display(),
                b.path.display()
            )));
        }
    }
    obs.iter()
        .map(|o| {
            let of_mode = tables.iter().position(|t| t.mode() == Some(o.mode));
            let unknown = tables.iter().position(|t| t.mode().is_none());
            of_mode.or(unknown).ok_or_else(|| {
                let listed: Vec<String> = tables
                    .iter()
                    .map(|t| {
                        format!(
                            "{} ({}-mode, {} rows)",
                            t.path.display(),
                            t.mode().map_or("unknown", name),
                            t.rows.len()
                        )
                    })
                    .collect();
                Error::Usage(format!(
                    "{} has INSTRUMENT_MODE_ID = {} but [inputs] solar_spectrum has no {} table: {}; add the {} table (M3{}20110224_RFL_SOLAR_SPEC.TAB; a list holds one table per mode)",
                    o.label_path.display(),
                    name(o.mode),
                    name(o.mode),
                    listed.join(", "),
                    name(o.mode),
                    if o.mode == pds::m3::Mode::Global { "G" } else { "T" }
                ))
            })
        })
        .collect()
}

/// An input DEM: a LOLA GDR (PDS3 label) or a GeoTIFF on the Moon sphere.
pub(super) enum Dem {
    Pds(LolaDem),
    GeoTiff(ingest::GeoTiffDem),
}

impl Dem {
    /// `.tif`/`.tiff` is a GeoTIFF; anything else a PDS3 label.
    pub(super) fn open(p: &Path) -> Result<Dem> {
        let ext = p
            .extension()
            .and_then(|e| e.to_str())
            .unwrap_or("")
            .to_ascii_lowercase();
        Ok(if ext == "tif" || ext == "tiff" {
            Dem::GeoTiff(ingest::GeoTiffDem::open(p)?)
        } else {
            Dem::Pds(LolaDem::open(p)?)
        })
    }

    /// The DEM at the grid's points ([`ingest::lola_on_grid_tracked`] with `tracks`, the
    /// product's track offsets; [`ingest::geotiff_on_grid`]).
    pub(super) fn on_grid(
        &self,
        geo: &crate::grid::Geographic,
        method: crate::grid::Interpolation,
        tracks: Option<&ingest::TrackOffsets>,
    ) -> Result<Option<Array2<f64>>> {
        match self {
            Dem::Pds(d) => ingest::lola_on_grid_tracked(d, geo, method, tracks),
            Dem::GeoTiff(d) => ingest::geotiff_on_grid(d, geo, method),
        }
    }

    /// Pixel size, metres.
    pub(super) fn pixel_m(&self) -> f64 {
        match self {
            Dem::Pds(d) => d.map_scale_m,
            Dem::GeoTiff(d) => d.pixel_m(),
        }
    }

    /// Whether this DEM shows its altimeter tracks at latitude `lat` (degrees): a gridded LOLA
    /// product (PRODUCT_ID or file name `LDEM…`) whose pixels are narrower east–west than the
    /// gap between tracks there ([`LOLA_TRACK_GAP_M`] × cos(latitude)). Then each track is a
    /// strip of pixels and its offset a stripe, which E_DEM's track weighting is for; wider
    /// pixels average several tracks. A simple cylindrical product's pixels narrow with
    /// cos(latitude) as the gaps do, so the answer is its MAP_SCALE against 600 m at every
    /// latitude (LDEM_64 and finer: yes; LDEM_16 and coarser: no); a polar stereographic
    /// product's pixels keep their MAP_SCALE.
    pub(super) fn resolves_tracks(&self, lat: f64) -> bool {
        self.product_id().is_some_and(|id| id.starts_with("LDEM"))
            && self.pixel_east_m(lat) < LOLA_TRACK_GAP_M * lat.to_radians().cos().abs()
    }

    /// East–west width of a pixel at latitude `lat` (degrees), metres: 2πR·cos(lat)/(360·
    /// MAP_RESOLUTION) for a simple cylindrical product (px/deg of longitude), MAP_SCALE for a
    /// polar stereographic one (its scale at the pole; a pixel 12° from it covers 1 % less
    /// ground) and a GeoTIFF.
    fn pixel_east_m(&self, lat: f64) -> f64 {
        match self {
            Dem::Pds(d) => match d.projection {
                pds::lola::Projection::SimpleCylindrical { resolution, .. } => {
                    2.0 * std::f64::consts::PI * d.radius_m * lat.to_radians().cos().abs()
                        / (360.0 * resolution)
                }
                pds::lola::Projection::PolarStereographic { .. } => d.map_scale_m,
            },
            Dem::GeoTiff(d) => d.pixel_m(),
        }
    }

    /// A PDS product's PRODUCT_ID (else its label's file name), upper case; `None` for a
    /// GeoTIFF.
    fn product_id(&self) -> Option<String> {
        let Dem::Pds(d) = self else { return None };
        Some(product_id(&d.label, &d.label_path).to_ascii_uppercase())
    }

    /// The spacing of the independent heights behind the DEM at latitude `lat` (degrees), and
    /// why. A LOLA-only GDR (`LDEM_*`) is gridded from altimeter tracks and interpolated
    /// between them: where its pixels are finer than the gaps between tracks, MAP_SCALE
    /// overstates its resolution. The gaps are about [`LOLA_TRACK_GAP_M`] at the equator and
    /// shrink with cos(latitude) as the polar orbits converge. Other DEMs (SLDEM2015, merged
    /// with stereo and not interpolated; GeoTIFFs) are taken at their pixel size.
    pub(super) fn effective_resolution(&self, lat: f64) -> (f64, String) {
        let pixel = self.pixel_m();
        let Some(id) = self.product_id() else {
            return (pixel, "GeoTIFF pixel size".into());
        };
        if !id.starts_with("LDEM") {
            return (pixel, format!("{id}: MAP_SCALE"));
        }
        let gap = LOLA_TRACK_GAP_M * lat.to_radians().cos().abs();
        if gap > pixel {
            (
                gap,
                format!("{id}: LOLA track gap {LOLA_TRACK_GAP_M} m × cos(latitude {lat:.2}°), coarser than MAP_SCALE {pixel:.1} m"),
            )
        } else {
            (
                pixel,
                format!("{id}: MAP_SCALE (coarser than the LOLA track gap {gap:.0} m)"),
            )
        }
    }
}

/// Gap between LOLA ground tracks at the equator that a gridded product interpolates across,
/// metres. After 20 000+ polar orbits the equator has been crossed ≈ 40 000 times (a mean
/// spacing near 300 m), unevenly: gaps of a kilometre and, in places, several kilometres
/// remain. 600 m stands for the gaps a gridded product typically bridges; it errs low of the
/// kilometre gaps because an overestimated point spread costs far more than an underestimated
/// one (E_DEM then deconvolves: docs/science.md, "The DEM's resolution").
pub const LOLA_TRACK_GAP_M: f64 = 600.0;

/// How every ingest of a run places and corrects each observation (the plan's): its swath
/// index ([`Plan::swaths`]), its registration's displacement ([`super::register::shifts`]) and
/// its gain trend ([`Plan::gain_trends`]); none where those are shorter.
#[derive(Clone, Copy)]
pub(super) struct Placing<'a> {
    pub(super) swaths: &'a [SwathIndex],
    pub(super) shifts: &'a [Displacement],
    pub(super) trends: &'a [Option<GainTrend>],
}

/// Every observation whose swath reaches `grid`, on it, placed and corrected as `placing` says
/// (an image with a gain trend divided by it at each pixel's swath line), in input order with
/// its index: reflectance NaN where the geometry is not finite; observations without a finite
/// pixel are left out.
pub(super) fn observations_on(
    o: &Orbital,
    inputs: &Inputs,
    placing: Placing,
    grid: &Grid,
    pr: &Projector,
    bearing: ndarray::ArrayView2<f64>,
) -> Result<Vec<(usize, ingest::ImageOnGrid)>> {
    Ok(
        observations_with_lines(o, inputs, placing, grid, (pr, bearing), false)?
            .into_iter()
            .map(|(k, img, _)| (k, img))
            .collect(),
    )
}

/// One observation on a grid: its input index, its image, and its swath lines where asked for
/// ([`observations_with_lines`]).
pub(super) type Shot = (usize, ingest::ImageOnGrid, Option<Array2<f32>>);

/// [`observations_on`], with each observation's swath lines on the grid where `with_lines`
/// ([`ingest::m3_on_grid_with_lines`]).
pub(super) fn observations_with_lines(
    o: &Orbital,
    inputs: &Inputs,
    placing: Placing,
    grid: &Grid,
    (pr, bearing): (&Projector, ndarray::ArrayView2<f64>),
    with_lines: bool,
) -> Result<Vec<Shot>> {
    let mut shots = Vec::new();
    for (k, (obs, index)) in inputs.obs.iter().zip(placing.swaths).enumerate() {
        let none = Displacement::default();
        let shift = placing.shifts.get(k).unwrap_or(&none);
        if index.lines_for(&ingest::reach(grid, shift)).is_none() {
            continue;
        }
        let trend = placing.trends.get(k).copied().flatten();
        let (mut img, lines) = ingest::m3_on_grid_with_lines(
            obs,
            inputs.solar(k),
            o.inputs.wavelength_nm,
            grid,
            pr,
            bearing,
            Some(index),
            shift,
            with_lines || trend.is_some(),
        )?;
        if let (Some(t), Some(lines)) = (trend, &lines) {
            Zip::from(&mut img.reflectance)
                .and(lines)
                .par_for_each(|r, &l| *r /= t.factor(f64::from(l)));
        }
        Zip::from(&mut img.reflectance)
            .and(&img.sun)
            .and(&img.view)
            .for_each(|r, s, v| {
                if !(s[2].is_finite() && v[2].is_finite()) {
                    *r = f64::NAN;
                }
            });
        if img.reflectance.iter().any(|r| r.is_finite()) {
            shots.push((k, img, lines.filter(|_| with_lines)));
        }
    }
    Ok(shots)
}

/// Every input on one window of the grid: the observations that reach it
/// ([`observations_on`]) and the DEM ([`dem_on`]; NaN where no product covers a pixel).
pub(super) struct Ingested {
    pub(super) shots: Vec<(usize, ingest::ImageOnGrid)>,
    pub(super) dem: Array2<f64>,
}

/// [`Ingested`] on `window` (a tile's window, or a band of the reference's rows).
pub(super) fn ingest_window(
    o: &Orbital,
    inputs: &Inputs,
    placing: Placing,
    window: &Grid,
) -> Result<Ingested> {
    let pr = projector(&window.crs)?;
    let geo = window.geographic(&pr);
    // The DEM first: the observations need only the bearings, and the longitudes and
    // latitudes are freed before their swath arrays are read.
    let dem = dem_on(o, inputs, &geo)?;
    let crate::grid::Geographic { lon, lat, bearing } = geo;
    drop((lon, lat));
    let shots = observations_on(o, inputs, placing, window, &pr, bearing.view())?;
    Ok(Ingested { shots, dem })
}

/// The fusion's view of [`observations_on`]'s images.
pub(super) fn fusion_observations(
    shots: &[(usize, ingest::ImageOnGrid)],
) -> Vec<fusion::Observation<'_>> {
    shots.iter().map(|(_, img)| fusion_view(img)).collect()
}

/// The fusion's view of one image on the grid: its reflectance and per-pixel Sun and view
/// vectors.
pub(super) fn fusion_view(img: &ingest::ImageOnGrid) -> fusion::Observation<'_> {
    fusion::Observation {
        image: img.reflectance.view(),
        sun: Directions::PerPixel(img.sun.view().into()),
        view: Directions::PerPixel(img.view.view().into()),
    }
}

/// The DEM on the grid's points: at each, the first product that covers it (NaN where none).
/// A product the grid does not reach is skipped; one that cannot be read, or whose heights
/// are not the Moon's ([`ingest::LUNAR_HEIGHT_RANGE_M`]), is an error.
pub(super) fn dem_on(
    o: &Orbital,
    inputs: &Inputs,
    geo: &crate::grid::Geographic,
) -> Result<Array2<f64>> {
    let mut dem = Array2::from_elem(geo.lon.dim(), f64::NAN);
    for (d, tracks) in inputs.lola.iter().zip(&inputs.dem_tracks) {
        let Some(h) = d.on_grid(geo, o.grid.dem_interpolation, tracks.get())? else {
            continue;
        };
        Zip::from(&mut dem).and(&h).for_each(|a, &b| {
            if a.is_nan() {
                *a = b;
            }
        });
    }
    Ok(dem)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// LDEM_4's label with MAP_RESOLUTION `res` px/deg (and its MAP_SCALE), in a scratch
    /// directory beside a link to its data. Its stated edges (MAXIMUM_LATITUDE and the rest)
    /// are dropped: at `res` px/deg its 720 × 1440 pixels no longer span the globe, and a label
    /// that stated them would be refused for disagreeing with itself.
    fn ldem(res: f64) -> Dem {
        let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/lola_ldem4");
        let dir = std::env::temp_dir().join(format!("sfsfuse-ldem-{res}-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scale = 2.0 * std::f64::consts::PI * 1_737_400.0 / 360.0 / res;
        let label = std::fs::read_to_string(data.join("LDEM_4.LBL"))
            .unwrap()
            .replace("= 4 <pix/deg>", &format!("= {res} <pix/deg>"))
            .replace("= 7580.84 <m/pix>", &format!("= {scale:.2} <m/pix>"))
            .lines()
            .filter(|l| {
                ![
                    "MAXIMUM_LATITUDE",
                    "MINIMUM_LATITUDE",
                    "WESTERNMOST_LONGITUDE",
                    "EASTERNMOST_LONGITUDE",
                ]
                .iter()
                .any(|k| l.trim_start().starts_with(k))
            })
            .collect::<Vec<_>>()
            .join("\n");
        std::fs::write(dir.join("LDEM_4.LBL"), label).unwrap();
        let img = dir.join("LDEM_4.IMG");
        if !img.exists() {
            std::os::unix::fs::symlink(data.join("LDEM_4.IMG"), &img).unwrap();
        }
        let d = LolaDem::open(&dir.join("LDEM_4.LBL")).unwrap();
        std::fs::remove_dir_all(&dir).unwrap();
        Dem::Pds(d)
    }

    /// A solar table of `rows` rows (wavelength, irradiance) named `name` in `dir`.
    fn table(dir: &std::path::Path, name: &str, rows: usize) -> SolarSpectrum {
        let text: String = (0..rows)
            .map(|i| format!("{} 1000.0\n", 400.0 + 10.0 * i as f64))
            .collect();
        std::fs::write(dir.join(name), text).unwrap();
        SolarSpectrum::read(&dir.join(name)).unwrap()
    }

    /// Each observation takes the table of its mode from a list of one per mode, in any
    /// order; a mode without its table, and two tables of one mode, are refused by name; a
    /// table whose mode neither its rows nor its name tells serves any observation.
    #[test]
    fn each_observation_takes_the_solar_table_of_its_mode() {
        let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
        let crop = |d: &str, id: &str| {
            Observation::open(&data.join(format!("m3_l1b_crops/{d}/{id}_V03_L1B_cropped.LBL")))
                .unwrap()
        };
        let obs = [
            crop("forwardDescending", "M3G20081129T171431"),
            crop("forwardAscending", "M3T20090630T083407"),
        ];
        let dir = std::env::temp_dir().join(format!("sfsfuse-solar-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let target =
            SolarSpectrum::read(&data.join("m3_calibration/m3t20110224_rfl_solar_spec.tab"))
                .unwrap();
        let global = table(&dir, "global.tab", 85);
        let unknown = table(&dir, "solar.tab", 10);
        let tables = [target.clone(), global.clone()];
        assert_eq!(solar_per_observation(&tables, &obs).unwrap(), [1, 0]);
        let e = solar_per_observation(std::slice::from_ref(&global), &obs)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("M3T20090630T083407_V03_L1B_cropped.LBL has INSTRUMENT_MODE_ID = TARGET")
                && e.contains("global.tab (GLOBAL-mode, 85 rows)")
                && e.contains("add the TARGET table (M3T20110224_RFL_SOLAR_SPEC.TAB"),
            "{e}"
        );
        let e = solar_per_observation(&[global.clone(), target, global], &obs)
            .unwrap_err()
            .to_string();
        assert!(e.contains("two GLOBAL-mode tables"), "{e}");
        assert_eq!(solar_per_observation(&[unknown], &obs).unwrap(), [0, 0]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// A simple cylindrical pixel narrows east–west with cos(latitude) as the gaps between
    /// LOLA's tracks do: 64 px/deg (474 m at the equator, under the 600-m gap) resolves the
    /// tracks at every latitude, 16 and 4 px/deg (1.9 and 7.6 km) at none. (The rule compared
    /// the equator's 474 m with the gap at the latitude before, and turned the weighting off
    /// above 38°.)
    #[test]
    fn a_simple_cylindrical_lola_grid_resolves_its_tracks_at_every_latitude_or_none() {
        for lat in [0.0, 30.0, 45.0, -60.0, 80.0] {
            assert!(ldem(64.0).resolves_tracks(lat), "64 px/deg at {lat}°");
            assert!(!ldem(16.0).resolves_tracks(lat), "16 px/deg at {lat}°");
            assert!(!ldem(4.0).resolves_tracks(lat), "4 px/deg at {lat}°");
        }
    }
}
