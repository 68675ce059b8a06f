//! Product IDs → archive URLs, and a label → the files it points to (pure; no I/O).
//!
//! Layouts (docs/fetch.md):
//! * M3 Level 1B (CH1-ORB-L-M3-4-L1B-RADIANCE-V3.0, volume CH1M3_0003), PDS Imaging Node:
//!   `{m3_base}/CH1M3_0003/DATA/{period}/{YYYYMM}/L1B/{ID}_V03_L1B.LBL`, where the period
//!   directory is `20081118_20090214` (optical period 1) or `20090415_20090816` (period 2).
//! * M3 solar spectra, with the reflectance calibration files of CH1M3_0004:
//!   `{m3_base}/CH1M3_0004/CALIB/{NAME}.TAB`.
//! * LOLA GDR (LRO-L-LOLA-4-GDR-V1.0), PDS Geosciences Node:
//!   `{lola_base}/{cylindrical|polar}/{img|float_img}/{name}.lbl` in lower case (as the node
//!   serves them); polar products are those named `LDEM_<lat>{N|S}_…`.

use crate::error::{Error, Result};
use pds::odl::{Label, Object, Pointer};

/// Where products are fetched from (defaults: the PDS nodes that host them).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Sources {
    /// Root of the M3 volumes (CH1M3_0003, CH1M3_0004).
    pub m3_base: String,
    /// The `lola_gdr` directory of the LOLA archive.
    pub lola_base: String,
    /// Optional md5sum-style manifests (`<md5>  <name or path>` per line) checked after each
    /// download, e.g. a volume's checksum list or one made by a mirror.
    pub checksums: Vec<String>,
    /// Attempts per file (connection errors, timeouts, 5xx and cut transfers are retried;
    /// 4xx are not).
    pub retries: u32,
    /// First back-off between attempts, milliseconds; doubled each time.
    pub backoff_ms: u64,
    /// Seconds without progress (connect or read) before a request is abandoned.
    pub timeout_s: f64,
}

impl Default for Sources {
    fn default() -> Self {
        Sources {
            m3_base: "https://planetarydata.jpl.nasa.gov/img/data/m3".into(),
            lola_base: "https://pds-geosciences.wustl.edu/lro/lro-l-lola-3-rdr-v1/lrolol_1xxx/data/lola_gdr".into(),
            checksums: Vec::new(),
            retries: 5,
            backoff_ms: 1000,
            timeout_s: 60.0,
        }
    }
}

/// A product a user can name.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Product {
    /// An M3 L1B observation, e.g. `M3G20090106T113423`.
    M3(String),
    /// A LOLA GDR product, e.g. `LDEM_64`, `LDEM_512_00N_15N_330_360`, `LDEM_85S_40M`.
    Lola(String),
    /// An M3 solar spectrum table, e.g. `M3G20110224_RFL_SOLAR_SPEC`.
    Solar(String),
}

fn is_m3_id(s: &str) -> bool {
    let b = s.as_bytes();
    b.len() == 18
        && s.starts_with("M3")
        && matches!(b[2], b'G' | b'T')
        && b[3..11].iter().all(u8::is_ascii_digit)
        && b[11] == b'T'
        && b[12..].iter().all(u8::is_ascii_digit)
}

impl Product {
    /// Recognise a product ID (case-insensitive); the error says which forms are known.
    pub fn parse(id: &str) -> Result<Product> {
        let u = id.trim().to_ascii_uppercase();
        let u = u
            .strip_suffix(".LBL")
            .or_else(|| u.strip_suffix(".TAB"))
            .unwrap_or(&u)
            .to_string();
        let safe = !u.is_empty() && u.bytes().all(|c| c.is_ascii_alphanumeric() || c == b'_');
        if safe && is_m3_id(&u) {
            return Ok(Product::M3(u));
        }
        if safe && u.starts_with("LDEM_") && u.len() > 5 {
            return Ok(Product::Lola(u));
        }
        if safe && (u.starts_with("M3G") || u.starts_with("M3T")) && u.ends_with("_RFL_SOLAR_SPEC")
        {
            return Ok(Product::Solar(u));
        }
        Err(Error::Usage(format!(
            "`{id}` is not a product ID sfsfuse can fetch: give an M3 L1B observation (M3G20090106T113423), a LOLA GDR (LDEM_64, LDEM_512_00N_15N_330_360, LDEM_85S_40M) or an M3 solar spectrum (M3G20110224_RFL_SOLAR_SPEC)"
        )))
    }

    pub fn name(&self) -> &str {
        match self {
            Product::M3(s) | Product::Lola(s) | Product::Solar(s) => s,
        }
    }

    /// The URL of the product's label (or of the table itself for solar spectra), and the
    /// name it is stored under locally.
    pub fn first_url(&self, src: &Sources) -> Result<(String, String)> {
        let trim = |b: &str| b.trim_end_matches('/').to_string();
        Ok(match self {
            Product::M3(id) => {
                let (date, ym) = (&id[3..11], &id[3..9]);
                let period = if date <= "20090216" {
                    "20081118_20090214"
                } else if ("20090415"..="20090816").contains(&date) {
                    "20090415_20090816"
                } else {
                    return Err(Error::Usage(format!(
                        "{id}: M3 observed from 2008-11-18 to 2009-02-14 and from 2009-04-15 to 2009-08-16; {date} is outside both"
                    )));
                };
                let name = format!("{id}_V03_L1B.LBL");
                (
                    format!(
                        "{}/CH1M3_0003/DATA/{period}/{ym}/L1B/{name}",
                        trim(&src.m3_base)
                    ),
                    name,
                )
            }
            Product::Solar(n) => {
                let name = format!("{n}.TAB");
                (
                    format!("{}/CH1M3_0004/CALIB/{name}", trim(&src.m3_base)),
                    name,
                )
            }
            Product::Lola(n) => {
                let polar = n[5..].split('_').next().is_some_and(|f| {
                    f.len() > 1
                        && (f.ends_with('N') || f.ends_with('S'))
                        && f[..f.len() - 1].bytes().all(|c| c.is_ascii_digit())
                });
                let kind = if polar { "polar" } else { "cylindrical" };
                let sub = if n.ends_with("_FLOAT") {
                    "float_img"
                } else {
                    "img"
                };
                let name = format!("{n}.LBL");
                (
                    format!(
                        "{}/{kind}/{sub}/{}",
                        trim(&src.lola_base),
                        name.to_ascii_lowercase()
                    ),
                    name,
                )
            }
        })
    }
}

/// A file name found in a label or a manifest is used as a file name only: one path component
/// of letters, digits, `_`, `-` and `.`, not starting with a dot. Anything else (`../x`,
/// `/etc/x`, `a/b`, `C:x`) is refused, so no label or server can make sfsfuse write outside
/// the target directory.
pub fn safe_name(name: &str, source: &str) -> Result<String> {
    let ok = !name.is_empty()
        && name.len() <= 255
        && !name.starts_with('.')
        && name
            .bytes()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, b'_' | b'-' | b'.'));
    if ok {
        Ok(name.to_string())
    } else {
        Err(Error::Usage(format!(
            "{source}: refusing the file name {name:?}: only plain names (letters, digits, _ - .) are fetched, never paths"
        )))
    }
}

/// A file a label points to, with the size the label implies when it implies one.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Part {
    pub name: String,
    pub size: Option<u64>,
}

/// The data files a detached label points to (every `^…IMAGE`, `^…HEADER`, `^…TABLE` or
/// `^…QUBE` pointer `= "FILE"` or `("FILE", n)`, at any depth; pointers to documentation in
/// other volume directories, such as `^DESCRIPTION` or `^DATA_SET_MAP_PROJECTION`, are not
/// data and are skipped), with expected sizes: RECORD_BYTES × FILE_RECORDS of the object
/// holding the pointer when its RECORD_TYPE is FIXED_LENGTH, else the `BYTES` of the object
/// the pointer names. Pointers to byte offsets within the label itself are skipped.
pub fn parts(label: &Label, source: &str) -> Result<Vec<Part>> {
    let mut out: Vec<Part> = Vec::new();
    fn walk(o: &Object, source: &str, out: &mut Vec<Part>) -> Result<()> {
        let data = |k: &str| {
            let k = k.to_ascii_uppercase();
            ["IMAGE", "HEADER", "TABLE", "QUBE"]
                .iter()
                .any(|s| k.ends_with(s))
        };
        let keys: Vec<String> = o
            .attributes
            .iter()
            .filter_map(|a| a.key.strip_prefix('^'))
            .filter(|k| data(k))
            .map(str::to_string)
            .collect();
        for key in keys {
            let file = match o.pointer(&key) {
                Some(Ok(
                    Pointer::File(f) | Pointer::FileRecord(f, _) | Pointer::FileBytes(f, _),
                )) => f,
                _ => continue,
            };
            let name = safe_name(&file, source)?;
            let fixed = o
                .get("RECORD_TYPE")
                .and_then(|v| v.as_str())
                .is_some_and(|t| t.eq_ignore_ascii_case("FIXED_LENGTH"));
            let num = |obj: &Object, k: &str| {
                obj.get(k)
                    .and_then(|v| v.as_i64())
                    .filter(|&n| n >= 0)
                    .map(|n| n as u64)
            };
            let size = if fixed {
                num(o, "RECORD_BYTES")
                    .zip(num(o, "FILE_RECORDS"))
                    .and_then(|(a, b)| a.checked_mul(b))
            } else {
                o.child(&key).and_then(|c| num(c, "BYTES"))
            };
            match out.iter_mut().find(|p| p.name.eq_ignore_ascii_case(&name)) {
                Some(p) => p.size = p.size.or(size),
                None => out.push(Part { name, size }),
            }
        }
        for c in &o.children {
            walk(c, source, out)?;
        }
        Ok(())
    }
    walk(&label.root, source, &mut out)?;
    Ok(out)
}

/// md5sum-style manifest lines: `<32 hex>  <name or path>` (a `*` before the name, for binary
/// mode, is allowed). Returns (lower-case file name, md5).
pub fn parse_manifest(text: &str) -> Vec<(String, String)> {
    text.lines()
        .filter_map(|l| {
            let mut it = l.split_whitespace();
            let h = it.next()?;
            let p = it.next()?.trim_start_matches('*');
            (h.len() == 32 && h.bytes().all(|c| c.is_ascii_hexdigit())).then(|| {
                let name = p.rsplit(['/', '\\']).next().unwrap_or(p);
                (name.to_ascii_lowercase(), h.to_ascii_lowercase())
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_resolve_to_the_archive_layout() {
        let s = Sources::default();
        let (u, n) = Product::parse("m3g20090106t113423")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert_eq!(u, "https://planetarydata.jpl.nasa.gov/img/data/m3/CH1M3_0003/DATA/20081118_20090214/200901/L1B/M3G20090106T113423_V03_L1B.LBL");
        assert_eq!(n, "M3G20090106T113423_V03_L1B.LBL");
        let (u, _) = Product::parse("M3G20090609T183254")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert!(u.contains("/20090415_20090816/200906/L1B/"), "{u}");
        assert!(Product::parse("M3G20090301T000000")
            .unwrap()
            .first_url(&s)
            .is_err());
        let (u, n) = Product::parse("LDEM_64").unwrap().first_url(&s).unwrap();
        assert_eq!(u, "https://pds-geosciences.wustl.edu/lro/lro-l-lola-3-rdr-v1/lrolol_1xxx/data/lola_gdr/cylindrical/img/ldem_64.lbl");
        assert_eq!(n, "LDEM_64.LBL");
        let (u, _) = Product::parse("LDEM_85S_40M")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert!(u.ends_with("/polar/img/ldem_85s_40m.lbl"), "{u}");
        let (u, _) = Product::parse("LDEM_512_00N_15N_330_360")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert!(
            u.ends_with("/cylindrical/img/ldem_512_00n_15n_330_360.lbl"),
            "{u}"
        );
        let (u, _) = Product::parse("LDEM_16_FLOAT")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert!(
            u.ends_with("/cylindrical/float_img/ldem_16_float.lbl"),
            "{u}"
        );
        let (u, _) = Product::parse("M3G20110224_RFL_SOLAR_SPEC")
            .unwrap()
            .first_url(&s)
            .unwrap();
        assert!(
            u.ends_with("/CH1M3_0004/CALIB/M3G20110224_RFL_SOLAR_SPEC.TAB"),
            "{u}"
        );
        for bad in [
            "",
            "../etc/passwd",
            "LDEM_64/../../x",
            "M3X20090106T113423",
            "hello",
        ] {
            assert!(Product::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn names_from_labels_cannot_be_paths() {
        for ok in ["LDEM_64.IMG", "M3G20090106T113423_V03_RDN.IMG", "a-b.c"] {
            assert!(safe_name(ok, "x").is_ok());
        }
        for bad in [
            "../x.IMG",
            "/etc/passwd",
            "a/b.IMG",
            "..",
            ".hidden",
            "C:\\x",
            "x y",
            "",
        ] {
            let e = safe_name(bad, "lbl").unwrap_err().to_string();
            assert!(e.contains("lbl"), "{e}");
        }
    }

    #[test]
    fn parts_and_sizes_come_from_the_label() {
        let text = b"PDS_VERSION_ID = PDS3\r\nOBJECT = RDN_FILE\r\n  ^RDN_IMAGE = \"A_RDN.IMG\"\r\n  RECORD_TYPE = FIXED_LENGTH\r\n  RECORD_BYTES = 100\r\n  FILE_RECORDS = 7\r\n  OBJECT = RDN_IMAGE\r\n    LINES = 7\r\n  END_OBJECT = RDN_IMAGE\r\nEND_OBJECT = RDN_FILE\r\nOBJECT = RDN_HDR_FILE\r\n  ^RDN_ENVI_HEADER = \"A_RDN.HDR\"\r\n  RECORD_TYPE = VARIABLE_LENGTH\r\n  OBJECT = RDN_ENVI_HEADER\r\n    BYTES = 321\r\n  END_OBJECT = RDN_ENVI_HEADER\r\nEND_OBJECT = RDN_HDR_FILE\r\nEND\r\n";
        let label = pds::parse_label(text).unwrap();
        let p = parts(&label, "x.LBL").unwrap();
        assert_eq!(
            p,
            [
                Part {
                    name: "A_RDN.IMG".into(),
                    size: Some(700)
                },
                Part {
                    name: "A_RDN.HDR".into(),
                    size: Some(321)
                }
            ]
        );
        let evil = pds::parse_label(
            b"OBJECT = F\r\n^IMAGE = \"../../evil.IMG\"\r\nEND_OBJECT = F\r\nEND\r\n",
        )
        .unwrap();
        assert!(parts(&evil, "evil.LBL")
            .unwrap_err()
            .to_string()
            .contains("../../evil.IMG"));
    }

    #[test]
    fn manifests_parse_md5sum_lines() {
        let m = parse_manifest("d41d8cd98f00b204e9800998ecf8427e  DATA/LDEM_64.IMG\nnot a line\n0123456789abcdef0123456789ABCDEF *x.lbl\n");
        assert_eq!(
            m,
            [
                (
                    "ldem_64.img".into(),
                    "d41d8cd98f00b204e9800998ecf8427e".into()
                ),
                ("x.lbl".into(), "0123456789abcdef0123456789abcdef".into())
            ]
        );
    }
}
