//! One file over HTTP(S): resumable (HTTP Range), retried with exponential back-off, verified
//! (size, optional MD5), and never visible under its final name until complete.
//!
//! The transfer goes to `<name>.part` beside the destination. An existing `.part` is resumed
//! with `Range: bytes=<len>-` (a server answering 200 instead of 206 restarts it); only a
//! complete, verified file is renamed to its final name. Connection errors, timeouts, 5xx
//! answers and transfers cut short are retried; other 4xx answers are final.

use super::archive::Sources;
use crate::error::{Error, Result};
use crate::progress::Progress;
use md5::Md5;
use reqwest::blocking::Client;
use reqwest::header::{CONTENT_LENGTH, CONTENT_RANGE, RANGE};
use reqwest::StatusCode;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// How a file came to be there.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// Already present and verified: nothing downloaded.
    Cached,
    /// Downloaded (the bytes transferred in this run; less than the size when resumed).
    Downloaded { bytes: u64 },
}

/// What a downloaded file must be.
#[derive(Debug, Clone, Default)]
pub struct Expect {
    pub size: Option<u64>,
    pub md5: Option<String>,
}

/// An HTTP client with the sources' timeouts.
pub fn client(src: &Sources) -> Result<Client> {
    let t = Duration::from_secs_f64(src.timeout_s.max(0.001));
    Client::builder()
        .user_agent(concat!("sfsfuse/", env!("CARGO_PKG_VERSION")))
        .connect_timeout(t)
        .timeout(t)
        .build()
        .map_err(|e| Error::Usage(format!("cannot set up HTTP: {e}")))
}

fn part_path(dest: &Path) -> PathBuf {
    let mut n = dest
        .file_name()
        .map(|n| n.to_os_string())
        .unwrap_or_default();
    n.push(".part");
    dest.with_file_name(n)
}

/// Hex MD5 of a file.
pub fn file_md5(path: &Path) -> Result<String> {
    crate::raster::file_digest::<Md5>(path)
}

/// Does `path` exist and satisfy `expect`?
fn verified(path: &Path, expect: &Expect) -> Result<Option<String>> {
    let Ok(m) = std::fs::metadata(path) else {
        return Ok(Some("missing".into()));
    };
    if let Some(s) = expect.size {
        if m.len() != s {
            return Ok(Some(format!("{} bytes, the label says {s}", m.len())));
        }
    }
    if let Some(want) = &expect.md5 {
        let got = file_md5(path)?;
        if &got != want {
            return Ok(Some(format!("MD5 {got}, the manifest says {want}")));
        }
    }
    Ok(None)
}

/// Why one attempt failed, and whether another may succeed.
enum Attempt {
    Retry(String),
    Fatal(Error),
}

/// Fetch `url` to `dest` (see the module documentation).
pub fn fetch_file(
    client: &Client,
    url: &str,
    dest: &Path,
    expect: &Expect,
    src: &Sources,
    progress: &Progress,
) -> Result<Outcome> {
    if dest.exists() {
        match verified(dest, expect)? {
            None => return Ok(Outcome::Cached),
            Some(why) => {
                progress.note(&format!("{}: {why}; fetching again", dest.display()));
                std::fs::remove_file(dest).map_err(|e| Error::io(dest, e))?;
            }
        }
    }
    let part = part_path(dest);
    let attempts = src.retries.max(1);
    let mut transferred = 0u64;
    let mut last = String::new();
    for k in 0..attempts {
        if k > 0 {
            let wait = src.backoff_ms.saturating_mul(1u64 << (k - 1).min(16));
            progress.note(&format!(
                "{url}: {last}; retrying in {:.1} s ({}/{attempts})",
                wait as f64 / 1000.0,
                k + 1
            ));
            std::thread::sleep(Duration::from_millis(wait));
        }
        match attempt(client, url, &part, expect, progress, &mut transferred) {
            Ok(()) => {
                if let Some(why) = verified(&part, expect)? {
                    // A complete transfer that is wrong: the server's copy or the transfer is
                    // corrupt. Start over rather than resume into it.
                    let _ = std::fs::remove_file(&part);
                    last = format!("downloaded file is corrupt ({why})");
                    continue;
                }
                std::fs::File::open(&part)
                    .and_then(|f| f.sync_all())
                    .and_then(|()| std::fs::rename(&part, dest))
                    .map_err(|e| Error::io(dest, e))?;
                return Ok(Outcome::Downloaded { bytes: transferred });
            }
            Err(Attempt::Retry(why)) => last = why,
            Err(Attempt::Fatal(e)) => return Err(e),
        }
    }
    Err(Error::Usage(format!(
        "{url}: giving up after {attempts} attempt(s): {last} (a partial download, if any, stays in {} and is resumed next time)",
        part.display()
    )))
}

fn attempt(
    client: &Client,
    url: &str,
    part: &Path,
    expect: &Expect,
    progress: &Progress,
    transferred: &mut u64,
) -> std::result::Result<(), Attempt> {
    let have = std::fs::metadata(part).map(|m| m.len()).unwrap_or(0);
    if expect.size.is_some_and(|s| have >= s) {
        // Complete (or over-long: verification decides).
        return Ok(());
    }
    let mut req = client.get(url);
    if have > 0 {
        req = req.header(RANGE, format!("bytes={have}-"));
    }
    let resp = req.send().map_err(|e| Attempt::Retry(describe(&e)))?;
    let (file, start) = open_part(&resp, have, part, url)?;
    let total = resp
        .headers()
        .get(CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok())
        .map(|n| n + start);
    if let (Some(t), Some(s)) = (total, expect.size) {
        if t != s {
            let _ = std::fs::remove_file(part);
            return Err(Attempt::Fatal(Error::Usage(format!(
                "{url}: the server offers {t} bytes but the label says {s}: wrong file or damaged archive"
            ))));
        }
    }
    let name = part
        .file_name()
        .map(|n| n.to_string_lossy().trim_end_matches(".part").to_string())
        .unwrap_or_default();
    progress.bytes(&name, expect.size.or(total), start);
    let got = stream_into(resp, file, part, start, progress, transferred)?;
    if let Some(t) = total.or(expect.size) {
        if got < t {
            return Err(Attempt::Retry(format!(
                "transfer ended after {got} of {t} bytes"
            )));
        }
    }
    Ok(())
}

/// The part file to write a response into, and the byte it starts at, by the response's
/// status: appended to where a resumed (206) response starts exactly at its end (`have`
/// bytes), otherwise written anew; a refused resume (416), a server error, 408 or 429 is
/// retried (the part file removed where it cannot be resumed), any other status is fatal.
fn open_part(
    resp: &reqwest::blocking::Response,
    have: u64,
    part: &Path,
    url: &str,
) -> std::result::Result<(std::fs::File, u64), Attempt> {
    Ok(match resp.status() {
        StatusCode::PARTIAL_CONTENT if have > 0 => {
            // The range must start where the part file ends.
            let ok = resp
                .headers()
                .get(CONTENT_RANGE)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.strip_prefix("bytes "))
                .and_then(|v| v.split('-').next())
                .and_then(|v| v.parse::<u64>().ok())
                == Some(have);
            if !ok {
                let _ = std::fs::remove_file(part);
                return Err(Attempt::Retry(
                    "the server resumed at another offset; restarting".into(),
                ));
            }
            let f = std::fs::OpenOptions::new()
                .append(true)
                .open(part)
                .map_err(|e| Attempt::Fatal(Error::io(part, e)))?;
            (f, have)
        }
        StatusCode::OK | StatusCode::PARTIAL_CONTENT => {
            let f = std::fs::File::create(part).map_err(|e| Attempt::Fatal(Error::io(part, e)))?;
            (f, 0)
        }
        StatusCode::RANGE_NOT_SATISFIABLE => {
            let _ = std::fs::remove_file(part);
            return Err(Attempt::Retry(
                "the server refused to resume (416); restarting".into(),
            ));
        }
        s if s.is_server_error()
            || s == StatusCode::TOO_MANY_REQUESTS
            || s == StatusCode::REQUEST_TIMEOUT =>
        {
            return Err(Attempt::Retry(format!("HTTP {s}")));
        }
        s => {
            return Err(Attempt::Fatal(Error::Usage(format!(
                "{url}: HTTP {s}{}",
                if s == StatusCode::NOT_FOUND {
                    ": not in the archive (check the product ID and the base URL, docs/fetch.md)"
                } else {
                    ""
                }
            ))))
        }
    })
}

/// Stream the response's body into `file` (which holds the first `start` bytes), counting
/// each chunk in `transferred` and `progress`; returns the bytes the part file then holds. A
/// transfer cut short is retried (what arrived stays, to be resumed).
fn stream_into(
    mut resp: reqwest::blocking::Response,
    mut file: std::fs::File,
    part: &Path,
    start: u64,
    progress: &Progress,
    transferred: &mut u64,
) -> std::result::Result<u64, Attempt> {
    let mut buf = vec![0u8; 1 << 16];
    let mut got = start;
    loop {
        let n = match resp.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) => {
                let _ = file.flush();
                progress.finish();
                return Err(Attempt::Retry(format!(
                    "transfer cut after {got} bytes: {e}"
                )));
            }
        };
        file.write_all(&buf[..n])
            .map_err(|e| Attempt::Fatal(Error::io(part, e)))?;
        got += n as u64;
        *transferred += n as u64;
        progress.advance(n as u64);
    }
    file.flush()
        .map_err(|e| Attempt::Fatal(Error::io(part, e)))?;
    progress.finish();
    Ok(got)
}

/// A reqwest error in words a user can act on.
fn describe(e: &reqwest::Error) -> String {
    if e.is_timeout() {
        "timed out (no answer within the timeout)".into()
    } else if e.is_connect() {
        format!("cannot connect: {e}")
    } else {
        e.to_string()
    }
}
