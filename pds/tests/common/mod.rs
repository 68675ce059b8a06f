//! Shared by the real-file tests of both crates (the root crate's tests include this file with
//! `#[path]`), so there is one rule for finding the vendored mission samples and external tools.

use std::path::PathBuf;

/// `tests/data` of the project root: the real mission samples vendored with the repository
/// (tests/data/MANIFEST.md gives their provenance). Always present in a checkout, so these
/// tests never skip.
#[allow(dead_code)]
pub fn test_data() -> Option<PathBuf> {
    // The project root is this crate's manifest directory or its parent (for `pds/`).
    let manifest = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let root = if manifest.join("pds").is_dir() {
        manifest
    } else {
        manifest.join("..")
    };
    let p = root.join("tests/data");
    assert!(
        p.join("MANIFEST.md").is_file(),
        "{} is missing: the vendored samples are part of the repository",
        p.display()
    );
    Some(p)
}

/// The path of an external tool (PROJ's `proj`, GDAL's `gdalinfo`) a test compares against.
/// Such tests are `#[ignore]`d, so that a machine without the tools reports them as ignored in
/// the summary instead of passing them quietly; `.ci/run` installs the tools and runs
/// `cargo test -- --include-ignored`. Asked for and missing, the tool is a failure that says
/// what to install.
#[allow(dead_code)]
pub fn external_tool(name: &str, package: &str) -> PathBuf {
    std::env::var_os("PATH")
        .and_then(|paths| {
            std::env::split_paths(&paths)
                .map(|d| d.join(name))
                .find(|p| p.is_file())
        })
        .unwrap_or_else(|| {
            panic!("this test needs `{name}`: install it (Debian: {package}), or leave out --include-ignored")
        })
}

/// Run PROJ's `proj` with the PROJ string `def` on "lon lat" lines; its "x y" lines, with
/// 6 decimals.
#[allow(dead_code)]
pub fn proj_forward(proj: &std::path::Path, def: &str, input: &str) -> String {
    use std::io::Write;
    use std::process::{Command, Stdio};
    let mut child = Command::new(proj)
        .args(def.split(' '))
        .args(["-f", "%.6f"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("proj starts");
    child
        .stdin
        .take()
        .expect("a stdin pipe")
        .write_all(input.as_bytes())
        .expect("proj reads its input");
    String::from_utf8(child.wait_with_output().expect("proj ends").stdout)
        .expect("proj prints text")
}
