//! ENVI `.hdr` headers: `key = value` lines, `{ … }` lists that may span lines.

/// The comma-separated items of the `{ … }` value of `key` (case-insensitive), trimmed.
pub fn list(text: &str, key: &str) -> Option<Vec<String>> {
    let value = value(text, key)?;
    let inner = value.trim().strip_prefix('{')?.strip_suffix('}')?;
    Some(
        inner
            .split(',')
            .map(|s| s.trim().to_string())
            .filter(|s| !s.is_empty())
            .collect(),
    )
}

/// The raw value of `key`, including a multi-line `{ … }` block.
pub fn value(text: &str, key: &str) -> Option<String> {
    let mut lines = text.lines();
    while let Some(line) = lines.next() {
        let Some((k, v)) = line.split_once('=') else {
            continue;
        };
        if !k.trim().eq_ignore_ascii_case(key) {
            continue;
        }
        let mut v = v.trim().to_string();
        if v.starts_with('{') {
            while !v.contains('}') {
                v.push(' ');
                v.push_str(lines.next()?.trim());
            }
        }
        return Some(v);
    }
    None
}

#[cfg(test)]
mod tests {
    #[test]
    fn lists_span_lines() {
        let h = "ENVI\r\nsamples = 304\r\nwavelength = {\r\n 460.99, 500.92,\r\n 540.84}\r\nband names = {a, b}\r\n";
        assert_eq!(
            super::list(h, "Wavelength").unwrap(),
            vec!["460.99", "500.92", "540.84"]
        );
        assert_eq!(super::value(h, "samples").unwrap(), "304");
        assert!(super::list(h, "fwhm").is_none());
    }
}
