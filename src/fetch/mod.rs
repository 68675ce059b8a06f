//! `sfsfuse fetch`: M3 L1B observations, LOLA GDR DEMs and M3 solar spectra from the PDS by
//! product ID (docs/fetch.md). A product's label is fetched first; the data files are the ones
//! it points to, with the sizes it implies; every file is resumable, retried, verified, and
//! cached (a file already present and verified is not downloaded again). At the end each
//! product is opened with the `pds` readers, so a fetched product is one `sfsfuse run` can use.

pub mod archive;
pub mod download;

use crate::error::{Error, Result};
use crate::progress::Progress;
use archive::{parts, Product, Sources};
use download::{fetch_file, Expect, Outcome};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// One fetched product.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Fetched {
    pub product: String,
    /// The label (or the table, for solar spectra): what a workflow names.
    pub path: PathBuf,
    pub files: Vec<FetchedFile>,
}

#[derive(Debug, Clone, serde::Serialize)]
pub struct FetchedFile {
    pub path: PathBuf,
    pub url: String,
    pub outcome: Outcome,
}

/// The default cache directory: `$SFSFUSE_CACHE`, else `$XDG_CACHE_HOME/sfsfuse`, else
/// `~/.cache/sfsfuse`.
pub fn default_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("SFSFUSE_CACHE") {
        return d.into();
    }
    if let Some(d) = std::env::var_os("XDG_CACHE_HOME") {
        return PathBuf::from(d).join("sfsfuse");
    }
    std::env::var_os("HOME").map_or_else(
        || PathBuf::from(".sfsfuse-cache"),
        |h| PathBuf::from(h).join(".cache/sfsfuse"),
    )
}

/// Fetch every product in `ids` into `dir`.
pub fn fetch(
    ids: &[String],
    dir: &Path,
    src: &Sources,
    progress: &Progress,
) -> Result<Vec<Fetched>> {
    let products = ids
        .iter()
        .map(|i| Product::parse(i))
        .collect::<Result<Vec<_>>>()?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let client = download::client(src)?;
    // Checksum manifests, read into memory (they are small).
    let mut md5: HashMap<String, String> = HashMap::new();
    for url in &src.checksums {
        let resp = client
            .get(url)
            .send()
            .and_then(|r| r.error_for_status())
            .map_err(|e| Error::Usage(format!("checksum manifest {url}: {e}")))?;
        let text = resp
            .text()
            .map_err(|e| Error::Usage(format!("checksum manifest {url}: {e}")))?;
        md5.extend(archive::parse_manifest(&text));
    }
    let expect = |name: &str, size: Option<u64>| Expect {
        size,
        md5: md5.get(&name.to_ascii_lowercase()).cloned(),
    };
    let mut out = Vec::new();
    for p in &products {
        let (url, name) = p.first_url(src)?;
        let first = dir.join(&name);
        progress.note(&format!("{}: {url}", p.name()));
        let outcome = fetch_file(&client, &url, &first, &expect(&name, None), src, progress)?;
        let mut files = vec![FetchedFile {
            path: first.clone(),
            url: url.clone(),
            outcome,
        }];
        if !matches!(p, Product::Solar(_)) {
            let bytes = std::fs::read(&first).map_err(|e| Error::io(&first, e))?;
            let label = pds::parse_label(&bytes).map_err(|e| {
                Error::Pds(pds::Error::Label {
                    path: first.clone(),
                    source: e,
                })
            })?;
            let base = url.rsplit_once('/').map_or(url.as_str(), |(b, _)| b);
            for part in parts(&label, &first.display().to_string())? {
                // The Geosciences Node serves LOLA files under lower-case names.
                let remote = if matches!(p, Product::Lola(_)) {
                    part.name.to_ascii_lowercase()
                } else {
                    part.name.clone()
                };
                let purl = format!("{base}/{remote}");
                let path = dir.join(&part.name);
                let outcome = fetch_file(
                    &client,
                    &purl,
                    &path,
                    &expect(&part.name, part.size),
                    src,
                    progress,
                )?;
                files.push(FetchedFile {
                    path,
                    url: purl,
                    outcome,
                });
            }
        }
        // What was fetched must open as the product it claims to be.
        match p {
            Product::M3(_) => {
                let o = pds::m3::Observation::open(&first)?;
                for part in ["LOC", "OBS"] {
                    o.part(part)?;
                }
            }
            Product::Lola(_) => {
                pds::lola::LolaDem::open(&first)?;
            }
            Product::Solar(_) => {
                pds::solar::SolarSpectrum::read(&first)?;
            }
        }
        out.push(Fetched {
            product: p.name().to_string(),
            path: first,
            files,
        });
    }
    Ok(out)
}

/// A plain-text report.
pub fn table(f: &[Fetched]) -> String {
    let mut s = String::new();
    for p in f {
        s.push_str(&format!("{}  {}\n", p.product, p.path.display()));
        for file in &p.files {
            let how = match file.outcome {
                Outcome::Cached => "cached".to_string(),
                Outcome::Downloaded { bytes } => format!("downloaded {bytes} bytes"),
            };
            s.push_str(&format!("    {}  ({how})\n", file.path.display()));
        }
    }
    s
}
