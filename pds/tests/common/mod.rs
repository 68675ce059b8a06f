//! Shared by the real-file tests.

use std::path::PathBuf;

/// ../shared/data beside the project root; `None` (skip, with a message) outside that layout,
/// but a failure when CI is set, so that a missing checkout can never hide a failure there.
pub fn shared_data() -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    if p.is_dir() {
        return Some(p);
    }
    assert!(
        std::env::var_os("CI").is_none(),
        "CI is set but {} is missing: the real-file tests cannot be skipped in CI",
        p.display()
    );
    eprintln!(
        "skipping: {} not found (run from the project checkout beside shared/)",
        p.display()
    );
    None
}
