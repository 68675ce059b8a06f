//! A label and a data file from the input (split at the first 0xFF 0x00 pair): the product
//! readers open and read them or return an error, never panic, and never allocate more than
//! the data file can back.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::sync::OnceLock;

fn dir() -> &'static std::path::Path {
    static D: OnceLock<std::path::PathBuf> = OnceLock::new();
    D.get_or_init(|| {
        let d = std::env::temp_dir().join(format!("pds-fuzz-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        d
    })
}

fuzz_target!(|data: &[u8]| {
    let split = data
        .windows(2)
        .position(|w| w == [0xFF, 0x00])
        .unwrap_or(data.len());
    let (label, rest) = data.split_at(split);
    let image = rest.get(2..).unwrap_or(&[]);
    let d = dir();
    let lbl = d.join("P.LBL");
    std::fs::write(&lbl, label).unwrap();
    std::fs::write(d.join("D.IMG"), image).unwrap();
    if let Ok(dem) = pds::lola::LolaDem::open(&lbl) {
        let n = dem.lines().min(4);
        let _ = dem.read_heights(0, n);
        let _ = dem.pixel(10.0, -20.0);
    }
    if let Ok(o) = pds::m3::Observation::open(&lbl) {
        let _ = o.rdn.read_band(0, 0, o.rdn.lines.min(2));
        let _ = o.nearest_band(1209.6);
        let _ = o.bracket(1209.6);
        for part in ["LOC", "OBS"] {
            if let Ok(r) = o.part(part) {
                let _ = r.read_band(r.bands - 1, 0, r.lines.min(2));
            }
        }
    }
});
