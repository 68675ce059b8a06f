//! Arbitrary bytes as a GeoTIFF DEM: `GeoTiffDem::open` refuses it or opens it, and a DEM that
//! opens is resampled onto a small lunar grid; neither panics nor allocates more than the file
//! can back.
#![no_main]
use libfuzzer_sys::fuzz_target;
use sfsfuse::grid::{Crs, Grid, Interpolation};
use std::sync::OnceLock;

fn dir() -> &'static std::path::Path {
    static D: OnceLock<std::path::PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("sfsfuse-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let path = dir().join("D.tif");
    std::fs::write(&path, data).unwrap();
    let Ok(dem) = sfsfuse::ingest::GeoTiffDem::open(&path) else {
        return;
    };
    let crs = Crs::Equirectangular { lon_0: 0.0 };
    let Ok(grid) = Grid::new(crs, 4, 4, -280.0, 280.0, 140.0) else {
        return;
    };
    let Ok(pr) = grid.crs.projector() else {
        return;
    };
    let geo = grid.geographic(&pr);
    let _ = sfsfuse::ingest::geotiff_on_grid(&dem, &geo, Interpolation::Bilinear);
});
