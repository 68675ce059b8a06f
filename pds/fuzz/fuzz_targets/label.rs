//! Any bytes: the label parser returns a label or an error, never panics or hangs.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(l) = pds::parse_label(data) {
        for name in ["IMAGE", "RDN_IMAGE", "LOC_IMAGE", "OBS_IMAGE"] {
            let _ = l.pointer(name);
        }
        let _ = l.find("IMAGE_MAP_PROJECTION");
    }
});
