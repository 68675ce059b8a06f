//! The build's identity: a hash of the sources this build compiles (`src/`, `pds/src/`) and of
//! `Cargo.lock` (the dependencies' versions), exported as `SFSFUSE_SOURCE_ID`. Plan, tile and
//! run keys carry it (`sfsfuse::BUILD`), so that an output directory written by another build
//! of the same version number is planned and fused again rather than reused.

use std::path::{Path, PathBuf};

/// Every file under `dir`, recursively.
fn files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            files(&p, out);
        } else {
            out.push(p);
        }
    }
}

/// FNV-1a, 64 bits, continued from `h`.
fn fnv(mut h: u64, bytes: &[u8]) -> u64 {
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn main() {
    let root = PathBuf::from(std::env::var_os("CARGO_MANIFEST_DIR").expect("set by cargo"));
    let mut all = Vec::new();
    for d in ["src", "pds/src"] {
        files(&root.join(d), &mut all);
        println!("cargo:rerun-if-changed={d}");
    }
    all.push(root.join("Cargo.lock"));
    println!("cargo:rerun-if-changed=Cargo.lock");
    // Paths relative to the root, '/'-separated, in sorted order: the same tree gives the same
    // identity wherever and on whatever system it is built.
    let mut named: Vec<(String, PathBuf)> = all
        .into_iter()
        .filter_map(|p| {
            let rel = p.strip_prefix(&root).ok()?;
            let name: Vec<String> = rel
                .components()
                .map(|c| c.as_os_str().to_string_lossy().into_owned())
                .collect();
            Some((name.join("/"), p))
        })
        .collect();
    named.sort();
    let mut h = 0xcbf2_9ce4_8422_2325;
    for (name, path) in &named {
        let Ok(bytes) = std::fs::read(path) else {
            continue;
        };
        h = fnv(h, name.as_bytes());
        h = fnv(h, &[0]);
        h = fnv(h, &(bytes.len() as u64).to_le_bytes());
        h = fnv(h, &bytes);
    }
    println!("cargo:rustc-env=SFSFUSE_SOURCE_ID={h:016x}");
}
