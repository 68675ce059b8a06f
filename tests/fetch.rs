//! `sfsfuse fetch` against a local HTTP server on 127.0.0.1, started by each test, serving the
//! real files of tests/data in the PDS archive layout: complete downloads, resuming after a
//! cut transfer, corruption, 404, time-outs, no partial file under a final name, and no path
//! traversal from a label.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::{Arc, Mutex};
use std::time::Duration;

#[path = "../pds/tests/common/mod.rs"]
mod common;
use common::test_data;

/// What the server does for a path.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Behaviour {
    Serve,
    /// Send the headers for the whole file, then only this many bytes, and hang up; serve
    /// normally from the next request on.
    CutOnce(usize),
    /// Accept, read the request, answer nothing for two seconds.
    Hang,
}

/// (path, Range header) of every request, in order.
type RequestLog = Mutex<Vec<(String, Option<String>)>>;

struct Server {
    base: String,
    log: Arc<RequestLog>,
    behaviour: Arc<Mutex<HashMap<String, Behaviour>>>,
}

impl Server {
    fn start(files: HashMap<String, Vec<u8>>) -> Server {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let base = format!("http://{}", listener.local_addr().unwrap());
        let log = Arc::new(Mutex::new(Vec::new()));
        let behaviour: Arc<Mutex<HashMap<String, Behaviour>>> =
            Arc::new(Mutex::new(HashMap::new()));
        let files = Arc::new(files);
        let (l, b) = (log.clone(), behaviour.clone());
        std::thread::spawn(move || {
            // Bounded: the test process ends the thread; each connection is served once.
            for stream in listener.incoming().flatten().take(500) {
                let (files, l, b) = (files.clone(), l.clone(), b.clone());
                std::thread::spawn(move || serve(stream, &files, &l, &b));
            }
        });
        Server {
            base,
            log,
            behaviour,
        }
    }
    fn set(&self, path: &str, b: Behaviour) {
        self.behaviour.lock().unwrap().insert(path.to_string(), b);
    }
    fn requests(&self, path: &str) -> Vec<Option<String>> {
        self.log
            .lock()
            .unwrap()
            .iter()
            .filter(|(p, _)| p == path)
            .map(|(_, r)| r.clone())
            .collect()
    }
}

fn serve(
    mut s: TcpStream,
    files: &HashMap<String, Vec<u8>>,
    log: &RequestLog,
    b: &Mutex<HashMap<String, Behaviour>>,
) {
    s.set_read_timeout(Some(Duration::from_secs(5))).ok();
    let mut r = BufReader::new(s.try_clone().unwrap());
    let mut first = String::new();
    if r.read_line(&mut first).is_err() {
        return;
    }
    let path = first.split_whitespace().nth(1).unwrap_or("").to_string();
    let mut range = None;
    loop {
        let mut line = String::new();
        if r.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
            break;
        }
        if let Some(v) = line.to_ascii_lowercase().strip_prefix("range:") {
            range = Some(v.trim().to_string());
        }
    }
    log.lock().unwrap().push((path.clone(), range.clone()));
    let how = b
        .lock()
        .unwrap()
        .get(&path)
        .copied()
        .unwrap_or(Behaviour::Serve);
    let Some(body) = files.get(&path) else {
        let _ = s.write_all(
            b"HTTP/1.1 404 Not Found\r\nContent-Length: 9\r\nConnection: close\r\n\r\nnot found",
        );
        return;
    };
    match how {
        Behaviour::Hang => {
            std::thread::sleep(Duration::from_secs(2));
            return;
        }
        Behaviour::CutOnce(n) => {
            b.lock().unwrap().insert(path.clone(), Behaviour::Serve);
            let head = format!(
                "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                body.len()
            );
            let _ = s.write_all(head.as_bytes());
            let _ = s.write_all(&body[..n.min(body.len())]);
            let _ = s.flush();
            let _ = s.shutdown(std::net::Shutdown::Both);
            return;
        }
        Behaviour::Serve => {}
    }
    let start = range
        .as_deref()
        .and_then(|r| r.strip_prefix("bytes="))
        .and_then(|r| r.strip_suffix('-'))
        .and_then(|r| r.parse::<usize>().ok());
    let head = match start {
        Some(a) if a < body.len() => format!(
            "HTTP/1.1 206 Partial Content\r\nContent-Range: bytes {a}-{}/{}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
            body.len() - 1,
            body.len(),
            body.len() - a
        ),
        Some(_) => "HTTP/1.1 416 Range Not Satisfiable\r\nContent-Length: 0\r\nConnection: close\r\n\r\n".to_string(),
        None => format!("HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n", body.len()),
    };
    let _ = s.write_all(head.as_bytes());
    if !head.starts_with("HTTP/1.1 416") {
        let _ = s.write_all(&body[start.unwrap_or(0)..]);
    }
}

const LOLA_DIR: &str = "/lola_gdr/cylindrical/img";
const M3_DIR: &str = "/m3/CH1M3_0003/DATA/20081118_20090214/200901/L1B";

/// LDEM_4 as the Geosciences Node serves it (lower-case names).
fn lola_files(data: &Path) -> HashMap<String, Vec<u8>> {
    let mut f = HashMap::new();
    f.insert(
        format!("{LOLA_DIR}/ldem_4.lbl"),
        std::fs::read(data.join("lola_ldem4/LDEM_4.LBL")).unwrap(),
    );
    f.insert(
        format!("{LOLA_DIR}/ldem_4.img"),
        std::fs::read(data.join("lola_ldem4/LDEM_4.IMG")).unwrap(),
    );
    f
}

/// An ENVI header padded to exactly `bytes` (the size the label states).
fn envi_header(bytes: usize, extra: &str) -> Vec<u8> {
    let mut h = format!("ENVI\ndescription = {{test fixture}}\n{extra}").into_bytes();
    assert!(h.len() < bytes);
    h.resize(bytes - 1, b' ');
    h.push(b'\n');
    h
}

/// The real global-mode crop M3G20090106T113423 as the Imaging Node would serve it. The crop
/// ships no ENVI headers, so headers of the sizes its label states are made here; its UTC
/// table's records lost their CR when it was cropped (56-byte records, the label says 57), so
/// CRs are put back as in the archive.
fn m3_files(data: &Path) -> HashMap<String, Vec<u8>> {
    let d = data.join("m3_l1b_crops/reverseDescending");
    let id = "M3G20090106T113423_V03";
    let mut f = HashMap::new();
    f.insert(
        format!("{M3_DIR}/{id}_L1B.LBL"),
        std::fs::read(d.join(format!("{id}_L1B_cropped.LBL"))).unwrap(),
    );
    for part in ["RDN", "LOC", "OBS"] {
        let name = format!("{id}_{part}_cropped.IMG");
        f.insert(
            format!("{M3_DIR}/{name}"),
            std::fs::read(d.join(&name)).unwrap(),
        );
    }
    let tim = std::fs::read_to_string(d.join(format!("{id}_TIM_cropped.TAB"))).unwrap();
    f.insert(
        format!("{M3_DIR}/{id}_TIM_cropped.TAB"),
        tim.replace("\r\n", "\n").replace('\n', "\r\n").into_bytes(),
    );
    let wl: Vec<String> = ["460.99", "500.92", "540.84"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    f.insert(
        format!("{M3_DIR}/{id}_RDN.HDR"),
        envi_header(35648, &format!("wavelength = {{{}}}\n", wl.join(", "))),
    );
    f.insert(format!("{M3_DIR}/{id}_LOC.HDR"), envi_header(371, ""));
    f.insert(format!("{M3_DIR}/{id}_OBS.HDR"), envi_header(706, ""));
    f
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("sfsfuse-fetch-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn fetch(server: &Server, to: &Path, ids: &[&str], extra: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_sfsfuse"))
        .arg("fetch")
        .args(ids)
        .arg("--to")
        .arg(to)
        .args([
            "--m3-base",
            &format!("{}/m3", server.base),
            "--lola-base",
            &format!("{}/lola_gdr", server.base),
        ])
        .args(["--progress", "lines", "--json"])
        .args(extra)
        .output()
        .unwrap()
}

fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|r| {
            r.filter_map(|e| e.ok())
                .map(|e| e.file_name().to_string_lossy().to_string())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn fetches_lola_and_m3_completely_and_then_from_the_cache() {
    let Some(data) = test_data() else { return };
    let mut files = lola_files(&data);
    files.extend(m3_files(&data));
    let server = Server::start(files);
    let to = scratch("complete");
    let o = fetch(&server, &to, &["LDEM_4", "M3G20090106T113423"], &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        std::fs::read(to.join("LDEM_4.IMG")).unwrap(),
        std::fs::read(data.join("lola_ldem4/LDEM_4.IMG")).unwrap()
    );
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(r[0]["files"].as_array().unwrap().len(), 2);
    // Label, RDN, RDN header, LOC, LOC header, OBS, OBS header, UTC table.
    assert_eq!(r[1]["files"].as_array().unwrap().len(), 8);
    // The fetched observation opens and is the crop.
    let obs = pds::m3::Observation::open(&to.join("M3G20090106T113423_V03_L1B.LBL")).unwrap();
    assert_eq!((obs.rdn.lines, obs.rdn.samples), (5, 304));
    assert!(names(&to).iter().all(|n| !n.ends_with(".part")));
    // Again: nothing is downloaded twice.
    let before = server.log.lock().unwrap().len();
    let o = fetch(&server, &to, &["LDEM_4", "M3G20090106T113423"], &[]);
    assert!(o.status.success());
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    for p in r.as_array().unwrap() {
        for f in p["files"].as_array().unwrap() {
            assert_eq!(f["outcome"], "cached", "{f}");
        }
    }
    assert_eq!(
        server.log.lock().unwrap().len(),
        before,
        "the cache was not used"
    );
    std::fs::remove_dir_all(&to).unwrap();
}

#[test]
fn a_cut_transfer_is_resumed_with_a_range_request() {
    let Some(data) = test_data() else { return };
    let server = Server::start(lola_files(&data));
    let img = format!("{LOLA_DIR}/ldem_4.img");
    server.set(&img, Behaviour::CutOnce(700_000));
    let to = scratch("resume");
    let o = fetch(&server, &to, &["LDEM_4"], &["--retries", "3"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(
        std::fs::read(to.join("LDEM_4.IMG")).unwrap(),
        std::fs::read(data.join("lola_ldem4/LDEM_4.IMG")).unwrap()
    );
    let reqs = server.requests(&img);
    assert_eq!(reqs.len(), 2, "{reqs:?}");
    assert_eq!(reqs[0], None);
    assert_eq!(
        reqs[1].as_deref(),
        Some("bytes=700000-"),
        "the second request must resume"
    );
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(
        r[0]["files"][1]["outcome"]["downloaded"]["bytes"],
        2_073_600
    );
    std::fs::remove_dir_all(&to).unwrap();
}

#[test]
fn corrupt_missing_and_silent_servers_give_clear_errors_and_no_final_file() {
    let Some(data) = test_data() else { return };
    // Corrupt: a flipped byte, caught by the MD5 manifest; the file never gets its name.
    let mut files = lola_files(&data);
    let good = files[&format!("{LOLA_DIR}/ldem_4.img")].clone();
    let md5: String = {
        use md5::Digest;
        md5::Md5::digest(&good)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    };
    files.get_mut(&format!("{LOLA_DIR}/ldem_4.img")).unwrap()[12345] ^= 0xff;
    files.insert(
        "/MD5SUMS".into(),
        format!("{md5}  data/lola_gdr/cylindrical/img/LDEM_4.IMG\n").into_bytes(),
    );
    let server = Server::start(files);
    let to = scratch("corrupt");
    let o = fetch(
        &server,
        &to,
        &["LDEM_4"],
        &[
            "--checksums",
            &format!("{}/MD5SUMS", server.base),
            "--retries",
            "2",
        ],
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("corrupt") && e.contains(&md5),
        "{e}"
    );
    assert!(!to.join("LDEM_4.IMG").exists());
    // Truncated on the server: the label's size (RECORD_BYTES × FILE_RECORDS) catches it.
    let mut files = lola_files(&data);
    files
        .get_mut(&format!("{LOLA_DIR}/ldem_4.img"))
        .unwrap()
        .truncate(1_000_000);
    let server = Server::start(files);
    let to = scratch("short");
    let o = fetch(&server, &to, &["LDEM_4"], &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("1000000") && e.contains("2073600"),
        "{e}"
    );
    assert!(!to.join("LDEM_4.IMG").exists());
    // 404: the URL is named, and there is no retry.
    let server = Server::start(lola_files(&data));
    let to = scratch("404");
    let o = fetch(&server, &to, &["LDEM_16"], &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("404") && e.contains("ldem_16.lbl"),
        "{e}"
    );
    assert_eq!(server.requests(&format!("{LOLA_DIR}/ldem_16.lbl")).len(), 1);
    assert!(names(&to).is_empty(), "{:?}", names(&to));
    // A server that never answers: a time-out, retried, then a clear error.
    let server = Server::start(lola_files(&data));
    server.set(&format!("{LOLA_DIR}/ldem_4.lbl"), Behaviour::Hang);
    let to = scratch("timeout");
    let t0 = std::time::Instant::now();
    let o = fetch(
        &server,
        &to,
        &["LDEM_4"],
        &["--timeout", "0.3", "--retries", "2"],
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("timed out") && e.contains("2 attempt"),
        "{e}"
    );
    assert!(t0.elapsed() < Duration::from_secs(20));
    assert!(!to.join("LDEM_4.LBL").exists());
    for d in ["corrupt", "short", "404", "timeout"] {
        let _ = std::fs::remove_dir_all(scratch(d));
    }
}

#[test]
fn names_in_a_label_cannot_leave_the_target_directory() {
    let Some(data) = test_data() else { return };
    let mut files = lola_files(&data);
    let label = String::from_utf8(files[&format!("{LOLA_DIR}/ldem_4.lbl")].clone()).unwrap();
    let evil = label.replace(
        "^IMAGE                    = \"LDEM_4.IMG\"",
        "^IMAGE                    = \"../../escape.IMG\"",
    );
    assert_ne!(evil, label);
    files.insert(format!("{LOLA_DIR}/ldem_4.lbl"), evil.into_bytes());
    files.insert("/escape.img".into(), vec![0u8; 10]);
    let server = Server::start(files);
    let to = scratch("traversal").join("deep/er");
    let o = fetch(&server, &to, &["LDEM_4"], &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("../../escape.IMG") && e.contains("refusing"),
        "{e}"
    );
    assert!(!to.join("../../escape.IMG").exists());
    assert!(server.requests("/escape.img").is_empty());
    // Unknown IDs are refused before any request.
    let o = fetch(&server, &to, &["../../etc/passwd"], &[]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("not a product ID"));
    let _ = std::fs::remove_dir_all(scratch("traversal"));
}

/// `[fetch]` in a workflow: `sfsfuse run` downloads what is missing, then runs on it.
#[test]
fn run_fetches_missing_inputs_first() {
    let Some(data) = test_data() else { return };
    let server = Server::start(lola_files(&data));
    let dir = scratch("workflow");
    std::fs::create_dir_all(&dir).unwrap();
    let spec = sfsfuse::synth::SceneSpec {
        size: 64,
        seed: 2,
        ..Default::default()
    };
    let scene = sfsfuse::synth::generate(&spec);
    let grid = sfsfuse::demo::demo_grid(&spec).unwrap();
    let p = sfsfuse::synth::products::write(&scene, &grid, &dir.join("synthetic")).unwrap();
    let wf = format!(
        r#"kind = "orbital"
[inputs]
m3 = ["{m3}"]
lola = ["data/LDEM_4.LBL"]
solar_spectrum = "{solar}"
[region]
x_min = -4480.0
x_max = 4480.0
y_min = -4480.0
y_max = 4480.0
[grid]
center_lat = -13.4
center_lon = 357.2
[solver]
albedo_sigmas = [8.0, 4.0]
[output]
directory = "out"
[fetch]
directory = "data"
products = ["LDEM_4"]
[fetch.sources]
lola_base = "{base}/lola_gdr"
retries = 2
"#,
        m3 = p.m3_label.display(),
        solar = p.solar_table.display(),
        base = server.base,
    );
    std::fs::write(dir.join("w.toml"), wf).unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_sfsfuse"))
        .args(["run", "--progress", "lines"])
        .arg(dir.join("w.toml"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(dir.join("data/LDEM_4.IMG").is_file() && dir.join("out/dem.tif").is_file());
    let rec: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("out/run.json")).unwrap()).unwrap();
    let img = rec["inputs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|i| i["path"].as_str().unwrap().ends_with("LDEM_4.IMG"))
        .unwrap();
    assert_eq!(
        img["sha256"],
        sfsfuse::pipeline::file_sha256(&data.join("lola_ldem4/LDEM_4.IMG")).unwrap()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
