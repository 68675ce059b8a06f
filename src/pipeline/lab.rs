//! Laboratory workflows: an intensity image and a range-scan depth map on one pixel grid.

use super::*;

/// Read a single-band raster (TIFF or PNG) for lab mode.
pub(super) fn read_raster(path: &Path) -> Result<Array2<f64>> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .unwrap_or("")
        .to_ascii_lowercase();
    match ext.as_str() {
        "tif" | "tiff" => Ok(crate::export::read_tiff(path)?.data),
        "png" => crate::quicklook::read_png(path),
        _ => Err(Error::Usage(format!(
            "{}: give a .tif/.tiff or .png raster",
            path.display()
        ))),
    }
}

/// Fill holes (NaN) in a depth map with the mean of their valid 8-neighbours, repeatedly,
/// inward from the hole's edge (deterministic: each sweep reads the previous sweep).
pub(super) fn fill_holes(a: &mut Array2<f64>) -> usize {
    let (h, w) = a.dim();
    let holes = a.iter().filter(|v| !v.is_finite()).count();
    for _ in 0..h.max(w) {
        let prev = a.clone();
        let mut left = 0;
        for r in 0..h {
            for c in 0..w {
                if prev[(r, c)].is_finite() {
                    continue;
                }
                let (mut s, mut n) = (0.0, 0);
                for dr in -1isize..=1 {
                    for dc in -1isize..=1 {
                        let (rr, cc) = (r as isize + dr, c as isize + dc);
                        if (0..h as isize).contains(&rr) && (0..w as isize).contains(&cc) {
                            let v = prev[(rr as usize, cc as usize)];
                            if v.is_finite() {
                                s += v;
                                n += 1;
                            }
                        }
                    }
                }
                if n > 0 {
                    a[(r, c)] = s / n as f64;
                } else {
                    left += 1;
                }
            }
        }
        if left == 0 {
            break;
        }
    }
    holes
}

pub(super) fn run_lab(l: &Lab, wf: &Workflow, progress: &Progress) -> Result<RunSummary> {
    let out = &l.output.directory;
    std::fs::create_dir_all(out).map_err(|e| Error::io(out, e))?;
    progress.stage("reading the image and the depth map");
    let (image, depth) = lab_inputs(l, progress)?;
    let model = l.photometry.build();
    if let ModelSpec::Hapke(_) = l.photometry {
        progress.note("lab workflow with the Hapke model: intensities must be bidirectional reflectance (sr⁻¹)");
    }
    let d = |x: crate::workflow::Direction| crate::synth::direction(x.zenith_deg, x.azimuth_deg);
    let problem = Problem::single(
        image.view(),
        Directions::Uniform(d(l.illumination.light)),
        Directions::Uniform(d(l.illumination.view)),
        depth.view(),
        l.inputs.pixel_size_m,
        l.inputs.depth_psf_sigma_px,
        model.as_ref(),
    );
    progress.stage("fusing");
    let t0 = Instant::now();
    let params: &FusionParams = &l.solver;
    let f = fusion::fuse(&problem, params)?;
    let seconds = t0.elapsed().as_secs_f64();
    progress.finish();
    drop(problem);
    let dim = image.dim();
    let fused = TileLayers::fused(f, TileSums::default(), depth, image);
    let layers = &fused.layers;
    let files = checksums(&[l.inputs.image.clone(), l.inputs.depth.clone()], progress)?;
    let key = run_key(wf, &files);
    let outputs = write_lab_layers(l, layers, &key)?;
    let record = RunRecord {
        tool: "sfsfuse",
        version: crate::BUILD,
        workflow: wf,
        run_key: key,
        inputs: files,
        grid: None,
        crs_wkt: None,
        halo: None,
        intensity_scale: None,
        dem_psf_sigma: None,
        resolution_source: None,
        dem_resolution_m: None,
        dem_resolution_source: None,
        sigma_dem: None,
        dem_track_weight: None,
        dem_track_source: None,
        high_sun_east_west: None,
        high_sun_east_west_source: None,
        dem_tracks: Vec::new(),
        membrane: None,
        reference: None,
        threads: rayon::current_num_threads(),
        tiles: vec![lab_tile(&fused, dim, seconds)],
        sanity: None,
        observations: Vec::new(),
        metrics: {
            let mut m = MetricsAcc::new();
            m.add(layers);
            m.finish()
        },
        outputs: outputs.clone(),
    };
    let path = write_record(out, &record)?;
    Ok(RunSummary {
        output_directory: out.clone(),
        tiles_total: 1,
        tiles_run: 1,
        tiles_skipped: 0,
        mosaic: true,
        outputs,
        record: Some(path),
        sanity: None,
        seconds: 0.0,
    })
}

/// A lab run's image and depth map: on one pixel grid, the depth's no-data value made NaN,
/// scaled to metres by `depth_scale`, and its holes filled from their neighbours
/// ([`fill_holes`], said through `progress`). A depth map without a valid value is refused.
fn lab_inputs(l: &Lab, progress: &Progress) -> Result<(Array2<f64>, Array2<f64>)> {
    let image = read_raster(&l.inputs.image)?;
    let mut depth = read_raster(&l.inputs.depth)?;
    if image.dim() != depth.dim() {
        return Err(Error::Usage(format!(
            "{} is {:?} pixels but {} is {:?}: the image and the depth map must share one pixel grid",
            l.inputs.image.display(),
            image.dim(),
            l.inputs.depth.display(),
            depth.dim()
        )));
    }
    if let Some(nd) = l.inputs.depth_nodata {
        depth.mapv_inplace(|v| if v == nd { f64::NAN } else { v });
    }
    depth.mapv_inplace(|v| v * l.inputs.depth_scale);
    if depth.iter().all(|v| !v.is_finite()) {
        return Err(Error::Usage(format!(
            "{}: the depth map has no valid value",
            l.inputs.depth.display()
        )));
    }
    let filled = fill_holes(&mut depth);
    if filled > 0 {
        progress.note(&format!(
            "depth map: {filled} missing values filled from their neighbours"
        ));
    }
    Ok((image, depth))
}

/// Write the layers the lab workflow asks for (`layers` in [`TILE_LAYERS`] order) as TIFFs
/// without georeferencing (a lab object is not on the Moon), each carrying the build and the
/// run key; their paths in the workflow's order.
fn write_lab_layers(l: &Lab, layers: &[Array2<f64>; 7], key: &str) -> Result<Vec<PathBuf>> {
    let meta = [
        ("SFSFUSE_VERSION", crate::BUILD.to_string()),
        ("RUN_KEY", key.to_string()),
    ];
    let mut outputs = Vec::new();
    for &layer in &l.output.layers {
        let k = stored_index(layer);
        let (description, unit) = layer_info(layer, false);
        let path = l.output.directory.join(format!("{}.tif", layer.name()));
        let mut w = CogWriter::create_as(
            &path,
            None,
            layers[k].ncols(),
            layers[k].nrows(),
            &BandInfo {
                description,
                unit,
                metadata: &meta,
            },
            Container::Auto,
            sample_format(layer),
        )?;
        w.push(layers[k].view())?;
        w.finish()?;
        outputs.push(path);
    }
    Ok(outputs)
}

/// The run record's one tile of a lab run: the whole image, fused (a lab run writes no tile
/// file, so it has no key or checksum).
fn lab_tile(t: &TileLayers, (rows, cols): (usize, usize), seconds: f64) -> TileRecord {
    let whole = Window {
        r0: 0,
        c0: 0,
        rows,
        cols,
    };
    TileRecord {
        id: 0,
        key: String::new(),
        core: whole,
        ext: whole,
        status: t.status.into(),
        photometric_pixels: t.photometric,
        sanity: t.sanity.clone(),
        layers_sha256: String::new(),
        iterations: fusion::total_iterations(&t.stages),
        seconds,
        stages: t.stages.clone(),
    }
}
