//! Arbitrary text as a workflow file: `Workflow::parse` accepts it or returns an error naming
//! the file (and, for TOML faults, the line); it never panics.
#![no_main]
use libfuzzer_sys::fuzz_target;
use std::path::Path;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let path = Path::new("/fuzz/workflow.toml");
    if let Err(e) = sfsfuse::workflow::Workflow::parse(&text, path, Path::new("/fuzz")) {
        let _ = e.to_string();
    }
});
