//! The streaming COG writer ([`CogWriter`]): tiles, predictors, overviews, IFDs, GDAL's
//! metadata and the file layout (see the module documentation of `export`).

use super::*;

/// Streams one float32 band into a COG in bounded memory: rows go in top to bottom
/// ([`CogWriter::push`]); as soon as a row of 256-px tiles of any level is complete it is
/// compressed (in parallel) into that level's temporary file, and its 2 × 2 means feed the
/// next level. [`CogWriter::finish`] then writes the header, every IFD and the tile data —
/// smallest overview first — into a temporary sibling and renames it into place. Memory is a
/// few tile rows per level, whatever the image size.
pub struct CogWriter {
    pub(super) path: PathBuf,
    pub(super) grid: Option<Grid>,
    pub(super) info: OwnedInfo,
    pub(super) container: Container,
    pub(super) format: SampleFormat,
    pub(super) levels: Vec<Level>,
    pub(super) stats: Stats,
    pub(super) done: bool,
}

/// [`BandInfo`] with owned strings (a writer outlives its caller's borrows).
pub(super) struct OwnedInfo {
    pub(super) description: String,
    pub(super) unit: String,
    pub(super) metadata: Vec<(String, String)>,
}

pub(super) struct Level {
    pub(super) w: usize,
    pub(super) h: usize,
    /// Rows received and not yet compressed (row-major, `w` wide).
    pub(super) buf: Vec<f32>,
    pub(super) rows_in: usize,
    pub(super) tmp: PathBuf,
    pub(super) file: std::io::BufWriter<std::fs::File>,
    /// Compressed size of each tile so far, row-major.
    pub(super) sizes: Vec<u64>,
}

impl CogWriter {
    /// A writer for a `width × height` float32 band to `path` (`grid` = None: no GeoTIFF
    /// tags).
    pub fn create(
        path: &Path,
        grid: Option<&Grid>,
        width: usize,
        height: usize,
        info: &BandInfo,
        container: Container,
    ) -> Result<Self> {
        Self::create_as(
            path,
            grid,
            width,
            height,
            info,
            container,
            SampleFormat::Float32,
        )
    }

    /// [`CogWriter::create`] with a choice of sample format.
    pub fn create_as(
        path: &Path,
        grid: Option<&Grid>,
        width: usize,
        height: usize,
        info: &BandInfo,
        container: Container,
        format: SampleFormat,
    ) -> Result<Self> {
        if width == 0 || height == 0 || width > u32::MAX as usize || height > u32::MAX as usize {
            return Err(Error::Usage(format!(
                "{}: cannot write a {height} × {width} image",
                path.display()
            )));
        }
        let mut dims = vec![(height, width)];
        while let Some(&(h, w)) = dims.last().filter(|(h, w)| *h.max(w) > TILE) {
            dims.push((h.div_ceil(2), w.div_ceil(2)));
        }
        let mut levels: Vec<Level> = Vec::with_capacity(dims.len());
        for (k, &(h, w)) in dims.iter().enumerate() {
            let tmp = crate::raster::tmp_name(&path.with_extension(format!("L{k}")));
            // Errors name the file the caller asked for, not the temporary.
            let f = match std::fs::File::create(&tmp) {
                Ok(f) => f,
                Err(e) => {
                    for l in &levels {
                        let _ = std::fs::remove_file(&l.tmp);
                    }
                    return Err(Error::io(path, e));
                }
            };
            levels.push(Level {
                w,
                h,
                buf: Vec::new(),
                rows_in: 0,
                tmp,
                file: std::io::BufWriter::new(f),
                sizes: Vec::new(),
            });
        }
        Ok(CogWriter {
            path: path.to_path_buf(),
            grid: grid.copied(),
            info: OwnedInfo {
                description: info.description.to_string(),
                unit: info.unit.to_string(),
                metadata: info
                    .metadata
                    .iter()
                    .map(|(k, v)| (k.to_string(), v.clone()))
                    .collect(),
            },
            container,
            format,
            levels,
            stats: Stats::default(),
            done: false,
        })
    }

    /// Append rows (each `width` wide) below those already pushed.
    pub fn push(&mut self, rows: ArrayView2<f64>) -> Result<()> {
        let l = &self.levels[0];
        if rows.ncols() != l.w || l.rows_in + rows.nrows() > l.h {
            return Err(Error::Usage(format!(
                "{}: pushing {} × {} rows at row {} of a {} × {} image",
                self.path.display(),
                rows.nrows(),
                rows.ncols(),
                l.rows_in,
                l.h,
                l.w
            )));
        }
        if self.format == SampleFormat::Byte {
            super::check_byte_values(&self.path, rows, l.rows_in)?;
        }
        let v: Vec<f32> = rows.iter().map(|&x| x as f32).collect();
        self.stats.add(&v);
        self.push_level(0, v, rows.nrows())
            .map_err(|e| final_name(&self.path, e))
    }

    pub(super) fn push_level(&mut self, k: usize, rows: Vec<f32>, n: usize) -> Result<()> {
        let lv = &mut self.levels[k];
        lv.buf.extend_from_slice(&rows);
        lv.rows_in += n;
        loop {
            let lv = &mut self.levels[k];
            let buffered = lv.buf.len() / lv.w;
            let last = lv.rows_in == lv.h;
            if !(buffered >= TILE || (last && buffered > 0)) {
                return Ok(());
            }
            let take = buffered.min(TILE);
            let band: Vec<f32> = lv.buf.drain(..take * lv.w).collect();
            let band = Array2::from_shape_vec((take, lv.w), band).expect("band shape");
            let format = self.format;
            let lv = &mut self.levels[k];
            for t in compress_level(band.view(), format) {
                lv.file.write_all(&t).map_err(|e| Error::io(&lv.tmp, e))?;
                lv.sizes.push(t.len() as u64);
            }
            if k + 1 < self.levels.len() {
                let half = halve(band.view(), format);
                let n = half.nrows();
                self.push_level(k + 1, half.into_raw_vec_and_offset().0, n)?;
            }
        }
    }

    /// Write the file (see the type's documentation).
    pub fn finish(mut self) -> Result<()> {
        let res = self.assemble().map_err(|e| final_name(&self.path, e));
        self.cleanup();
        res
    }

    pub(super) fn assemble(&mut self) -> Result<()> {
        if let Some(l) = self.levels.iter().find(|l| l.rows_in != l.h) {
            return Err(Error::Usage(format!(
                "{}: {} of {} rows were written",
                self.path.display(),
                l.rows_in,
                l.h
            )));
        }
        for l in &mut self.levels {
            l.file.flush().map_err(|e| Error::io(&l.tmp, e))?;
        }
        let info = BandInfo {
            description: &self.info.description,
            unit: &self.info.unit,
            metadata: &self
                .info
                .metadata
                .iter()
                .map(|(k, v)| (k.as_str(), v.clone()))
                .collect::<Vec<_>>(),
        };
        let xml = gdal_metadata(&info, &self.stats);
        let layout = self.layout(&xml);
        let tmp = crate::raster::tmp_name(&self.path);
        let res = self
            .write_file(&tmp, &xml, &layout)
            .and_then(|()| std::fs::rename(&tmp, &self.path).map_err(|e| Error::io(&self.path, e)));
        if res.is_err() {
            let _ = std::fs::remove_file(&tmp);
        }
        res
    }

    /// The grid and GDAL metadata `xml` of level `k`: the full-resolution level's only.
    fn main_tags<'a>(&'a self, k: usize, xml: &'a str) -> Option<(Option<&'a Grid>, &'a str)> {
        (k == 0).then_some((self.grid.as_ref(), xml))
    }

    /// Where everything goes: the header and the ghost block, each level's IFD (tags with the
    /// level's `xml` metadata), then the tiles, smallest overview first and full resolution
    /// last, each as its 4-byte size, its bytes and a copy of its last 4 bytes (COG's
    /// leader and trailer). BigTIFF where the data would pass 4 GiB (or when asked for).
    fn layout(&self, xml: &str) -> Layout {
        let data_bytes: u64 = self
            .levels
            .iter()
            .flat_map(|l| &l.sizes)
            .map(|s| s + 8)
            .sum();
        let ntiles: u64 = self.levels.iter().map(|l| l.sizes.len() as u64).sum();
        let big = self.container == Container::BigTiff
            || data_bytes + 1_000_000 + 64 * ntiles > u32::MAX as u64;
        let width = Width { big };
        let header_len = if big { 16 } else { 8 };
        let mut pos = (header_len + ghost_block().len()) as u64;
        pos += pos % 2;
        let mut ifd_pos = Vec::new();
        for (k, l) in self.levels.iter().enumerate() {
            ifd_pos.push(pos);
            let tags = level_tags(
                k,
                (l.h, l.w),
                &l.sizes,
                self.main_tags(k, xml),
                &width,
                &[],
                self.format,
            );
            pos += ifd_size(&tags, &width);
            pos += pos % 2;
        }
        let mut offsets: Vec<Vec<u64>> = vec![Vec::new(); self.levels.len()];
        let data_start = pos;
        for k in (0..self.levels.len()).rev() {
            for s in &self.levels[k].sizes {
                offsets[k].push(pos + 4);
                pos += s + 8;
            }
        }
        Layout {
            width,
            ifd_pos,
            offsets,
            data_start,
            len: pos,
        }
    }

    /// The whole file at `tmp` as `layout` places it, synced to disk.
    fn write_file(&self, tmp: &Path, xml: &str, layout: &Layout) -> Result<()> {
        let Layout {
            width,
            ifd_pos,
            offsets,
            data_start,
            len,
        } = layout;
        let f = std::fs::File::create(tmp).map_err(|e| Error::io(tmp, e))?;
        let mut out = std::io::BufWriter::new(f);
        let mut head = Vec::with_capacity(*data_start as usize);
        if width.big {
            head.extend_from_slice(b"II\x2b\x00\x08\x00\x00\x00");
            head.extend_from_slice(&ifd_pos[0].to_le_bytes());
        } else {
            head.extend_from_slice(b"II\x2a\x00");
            head.extend_from_slice(&(ifd_pos[0] as u32).to_le_bytes());
        }
        head.extend_from_slice(&ghost_block());
        for (k, l) in self.levels.iter().enumerate() {
            pad_to(&mut head, ifd_pos[k]);
            let tags = level_tags(
                k,
                (l.h, l.w),
                &l.sizes,
                self.main_tags(k, xml),
                width,
                &offsets[k],
                self.format,
            );
            let next = ifd_pos.get(k + 1).copied().unwrap_or(0);
            write_ifd(&mut head, &tags, ifd_pos[k], next, width);
        }
        pad_to(&mut head, *data_start);
        out.write_all(&head).map_err(|e| Error::io(tmp, e))?;
        for l in self.levels.iter().rev() {
            let mut r = std::io::BufReader::new(
                std::fs::File::open(&l.tmp).map_err(|e| Error::io(&l.tmp, e))?,
            );
            let mut t = Vec::new();
            for &s in &l.sizes {
                t.resize(s as usize, 0);
                r.read_exact(&mut t).map_err(|e| Error::io(&l.tmp, e))?;
                out.write_all(&(s as u32).to_le_bytes())
                    .map_err(|e| Error::io(tmp, e))?;
                out.write_all(&t).map_err(|e| Error::io(tmp, e))?;
                out.write_all(&t[t.len() - 4..])
                    .map_err(|e| Error::io(tmp, e))?;
            }
        }
        let f = out
            .into_inner()
            .map_err(|e| Error::io(tmp, e.into_error()))?;
        f.sync_all().map_err(|e| Error::io(tmp, e))?;
        debug_assert_eq!(f.metadata().map(|m| m.len()).unwrap_or(*len), *len);
        Ok(())
    }

    pub(super) fn cleanup(&mut self) {
        if !self.done {
            for l in &self.levels {
                let _ = std::fs::remove_file(&l.tmp);
            }
            self.done = true;
        }
    }
}

impl Drop for CogWriter {
    /// An abandoned writer leaves no temporary behind.
    fn drop(&mut self) {
        self.cleanup();
    }
}

/// An I/O error on one of the writer's temporaries, reported against the file the caller asked
/// for (a full disk while writing `residual.tif` names `residual.tif`; the temporaries are
/// removed).
pub(super) fn final_name(path: &Path, e: Error) -> Error {
    match e {
        Error::Io { source, .. } => Error::Io {
            path: path.to_path_buf(),
            source,
        },
        e => e,
    }
}

/// GDAL's structural metadata block (gcore/gdal_priv.h, COG driver): a fixed first line giving
/// the size of the rest.
pub(super) fn ghost_block() -> Vec<u8> {
    let body = "LAYOUT=IFDS_BEFORE_DATA\nBLOCK_ORDER=ROW_MAJOR\nBLOCK_LEADER=SIZE_AS_UINT4\nBLOCK_TRAILER=LAST_4_BYTES_REPEATED\nKNOWN_INCOMPATIBLE_EDITION=NO\n ";
    format!(
        "GDAL_STRUCTURAL_METADATA_SIZE={:06} bytes\n{body}",
        body.len()
    )
    .into_bytes()
}

pub(super) fn pad_to(out: &mut Vec<u8>, pos: u64) {
    debug_assert!(out.len() as u64 <= pos);
    out.resize(pos as usize, 0);
}

/// The next overview: each pixel the mean of the valid (non-NaN) pixels of its 2 × 2 block
/// (float32), or the first valid pixel in row order (Byte).
pub(super) fn halve(a: ArrayView2<f32>, format: SampleFormat) -> Array2<f32> {
    let (h, w) = a.dim();
    if format == SampleFormat::Byte {
        return Array2::from_shape_fn((h.div_ceil(2), w.div_ceil(2)), |(r, c)| {
            (2 * r..(2 * r + 2).min(h))
                .flat_map(|i| (2 * c..(2 * c + 2).min(w)).map(move |j| (i, j)))
                .map(|ij| a[ij])
                .find(|v| !v.is_nan())
                .unwrap_or(f32::NAN)
        });
    }
    Array2::from_shape_fn((h.div_ceil(2), w.div_ceil(2)), |(r, c)| {
        let (mut s, mut n) = (0.0f64, 0u32);
        for i in 2 * r..(2 * r + 2).min(h) {
            for j in 2 * c..(2 * c + 2).min(w) {
                let v = a[(i, j)];
                if v.is_finite() {
                    s += v as f64;
                    n += 1;
                }
            }
        }
        if n == 0 {
            f32::NAN
        } else {
            (s / n as f64) as f32
        }
    })
}

/// zlib level of the tiles' DEFLATE: 1, the fastest (greedy matching). On the products of
/// `sfsfuse run` (float predictor first) level 6, zlib's and GDAL's default, gives files only
/// ≈ 5 % smaller and takes ≈ 4× as long, which was ≈ 10 % of a whole run on a 512² region
/// (docs/performance.md). `gdal_translate -co COMPRESS=DEFLATE -co ZLEVEL=9` recompresses for an
/// archive.
pub(super) const DEFLATE_LEVEL: u32 = 1;

/// Every tile of one level, DEFLATE-compressed after the floating-point predictor; tiles at the
/// right and bottom edges are padded with no-data.
pub(super) fn compress_level(a: ArrayView2<f32>, format: SampleFormat) -> Vec<Vec<u8>> {
    let (h, w) = a.dim();
    let (ty, tx) = (h.div_ceil(TILE), w.div_ceil(TILE));
    (0..ty * tx)
        .into_par_iter()
        .map(|t| {
            let (r0, c0) = ((t / tx) * TILE, (t % tx) * TILE);
            let mut raw = Vec::with_capacity(TILE * TILE * 4);
            let mut row = vec![f32::NAN; TILE];
            for r in r0..r0 + TILE {
                row.fill(f32::NAN);
                if r < h {
                    for (c, v) in row
                        .iter_mut()
                        .enumerate()
                        .take(w.saturating_sub(c0).min(TILE))
                    {
                        *v = a[(r, c0 + c)];
                    }
                }
                match format {
                    SampleFormat::Float32 => raw.extend_from_slice(&float_predictor(&row)),
                    SampleFormat::Byte => raw.extend_from_slice(&byte_predictor(&row)),
                }
            }
            let mut z = ZlibEncoder::new(Vec::new(), Compression::new(DEFLATE_LEVEL));
            z.write_all(&raw).expect("writing to memory");
            z.finish().expect("writing to memory")
        })
        .collect()
}

/// TIFF Technical Note 3's floating-point predictor on one row: the bytes of the (big-endian)
/// values are regrouped by significance (all most significant bytes first), then each byte is
/// replaced by its difference from the previous one (libtiff `fpDiff`).
pub(super) fn float_predictor(row: &[f32]) -> Vec<u8> {
    let n = row.len();
    let mut b = vec![0u8; 4 * n];
    for (i, v) in row.iter().enumerate() {
        for (k, byte) in v.to_be_bytes().into_iter().enumerate() {
            b[k * n + i] = byte;
        }
    }
    for j in (1..b.len()).rev() {
        b[j] = b[j].wrapping_sub(b[j - 1]);
    }
    b
}

/// TIFF's horizontal predictor (Predictor = 2) on one row of bytes (NaN → [`BYTE_NODATA`]):
/// each byte minus its left neighbour, modulo 256.
pub(super) fn byte_predictor(row: &[f32]) -> Vec<u8> {
    let b: Vec<u8> = row.iter().map(|&v| super::byte_sample(v)).collect();
    let mut out = b.clone();
    for j in 1..b.len() {
        out[j] = b[j].wrapping_sub(b[j - 1]);
    }
    out
}

/// Offsets are 4 bytes (classic TIFF) or 8 (BigTIFF).
/// Where [`CogWriter::assemble`] puts each part of the file: the offset width, each level's
/// IFD, each level's tile offsets (past each tile's 4-byte leader), where the tiles start and
/// the file's length.
struct Layout {
    width: Width,
    ifd_pos: Vec<u64>,
    offsets: Vec<Vec<u64>>,
    data_start: u64,
    len: u64,
}

pub(super) struct Width {
    pub(super) big: bool,
}

/// One IFD entry: tag, field type, count, and the value bytes (little-endian).
pub(super) struct Entry {
    pub(super) tag: u16,
    pub(super) kind: u16,
    pub(super) count: u64,
    pub(super) bytes: Vec<u8>,
}

pub(super) const SHORT: u16 = 3;
pub(super) const LONG: u16 = 4;
pub(super) const ASCII: u16 = 2;
pub(super) const DOUBLE: u16 = 12;
pub(super) const LONG8: u16 = 16;

/// An entry of `kind` holding the little-endian bytes of each value.
fn numbers<T: Copy, const N: usize>(tag: u16, kind: u16, v: &[T], le: fn(T) -> [u8; N]) -> Entry {
    Entry {
        tag,
        kind,
        count: v.len() as u64,
        bytes: v.iter().flat_map(|&x| le(x)).collect(),
    }
}
pub(super) fn shorts(tag: u16, v: &[u16]) -> Entry {
    numbers(tag, SHORT, v, u16::to_le_bytes)
}
pub(super) fn longs(tag: u16, v: &[u32]) -> Entry {
    numbers(tag, LONG, v, u32::to_le_bytes)
}
pub(super) fn doubles(tag: u16, v: &[f64]) -> Entry {
    numbers(tag, DOUBLE, v, f64::to_le_bytes)
}
pub(super) fn ascii(tag: u16, s: &str) -> Entry {
    let mut bytes = s.as_bytes().to_vec();
    bytes.push(0);
    Entry {
        tag,
        kind: ASCII,
        count: bytes.len() as u64,
        bytes,
    }
}

/// The tags of one level; `offsets` may be empty while laying out (the sizes are the same).
pub(super) fn level_tags(
    level: usize,
    (h, w): (usize, usize),
    sizes: &[u64],
    main: Option<(Option<&Grid>, &str)>,
    width: &Width,
    offsets: &[u64],
    format: SampleFormat,
) -> Vec<Entry> {
    let n = sizes.len();
    let byte_nodata = BYTE_NODATA.to_string();
    let (bits, predictor, sample_format, nodata) = match format {
        SampleFormat::Float32 => (32, 3, 3, "nan"),
        SampleFormat::Byte => (8, 2, 1, byte_nodata.as_str()),
    };
    let offsets: Vec<u64> = if offsets.is_empty() {
        vec![0; n]
    } else {
        offsets.to_vec()
    };
    let mut e = vec![
        longs(254, &[u32::from(level > 0)]),
        longs(256, &[w as u32]),
        longs(257, &[h as u32]),
        shorts(258, &[bits]),
        shorts(259, &[8]),
        shorts(262, &[1]),
        shorts(277, &[1]),
        shorts(284, &[1]),
        shorts(317, &[predictor]),
        shorts(322, &[TILE as u16]),
        shorts(323, &[TILE as u16]),
        if width.big {
            numbers(324, LONG8, &offsets, u64::to_le_bytes)
        } else {
            longs(324, &offsets.iter().map(|&x| x as u32).collect::<Vec<_>>())
        },
        longs(325, &sizes.iter().map(|&t| t as u32).collect::<Vec<_>>()),
        shorts(339, &[sample_format]),
        ascii(42113, nodata),
    ];
    if let Some((grid, xml)) = main {
        if let Some(grid) = grid {
            let s = grid.spacing;
            e.push(doubles(33550, &[s, s, 0.0]));
            e.push(doubles(33922, &[0.0, 0.0, 0.0, grid.x0, grid.y0, 0.0]));
            let keys = geokeys(&grid.crs);
            e.push(shorts(34735, &keys.directory));
            e.push(doubles(34736, &keys.doubles));
            e.push(ascii(34737, &keys.ascii));
        }
        e.push(ascii(42112, xml));
    }
    e.sort_by_key(|x| x.tag);
    e
}

/// GDAL's XML metadata (tag 42112): band description, unit and statistics, and dataset items.
pub(super) fn gdal_metadata(info: &BandInfo, stats: &Stats) -> String {
    let esc = |s: &str| {
        s.replace('&', "&amp;")
            .replace('<', "&lt;")
            .replace('>', "&gt;")
    };
    let mut s = String::from("<GDALMetadata>\n");
    for (k, v) in info.metadata {
        s.push_str(&format!("  <Item name=\"{}\">{}</Item>\n", esc(k), esc(v)));
    }
    s.push_str(&format!(
        "  <Item name=\"DESCRIPTION\" sample=\"0\" role=\"description\">{}</Item>\n",
        esc(info.description)
    ));
    if !info.unit.is_empty() {
        s.push_str(&format!(
            "  <Item name=\"UNITTYPE\" sample=\"0\" role=\"unittype\">{}</Item>\n",
            esc(info.unit)
        ));
    }
    for (k, v) in stats.items() {
        s.push_str(&format!("  <Item name=\"{k}\" sample=\"0\">{v}</Item>\n"));
    }
    s.push_str("</GDALMetadata>");
    s
}

pub(super) fn ifd_size(tags: &[Entry], w: &Width) -> u64 {
    let (head, entry, next, inline) = if w.big { (8, 20, 8, 8) } else { (2, 12, 4, 4) };
    let extra: u64 = tags
        .iter()
        .filter(|t| t.bytes.len() > inline)
        .map(|t| t.bytes.len() as u64 + (t.bytes.len() as u64 % 2))
        .sum();
    head + entry * tags.len() as u64 + next + extra
}

/// Serialise one IFD at file position `at` (== `out.len()`), with out-of-line values after it.
pub(super) fn write_ifd(out: &mut Vec<u8>, tags: &[Entry], at: u64, next: u64, w: &Width) {
    debug_assert_eq!(out.len() as u64, at);
    let (head, entry, nextb, inline) = if w.big {
        (8u64, 20u64, 8u64, 8usize)
    } else {
        (2, 12, 4, 4)
    };
    let mut extra_pos = at + head + entry * tags.len() as u64 + nextb;
    let mut extra = Vec::new();
    if w.big {
        out.extend_from_slice(&(tags.len() as u64).to_le_bytes());
    } else {
        out.extend_from_slice(&(tags.len() as u16).to_le_bytes());
    }
    for t in tags {
        out.extend_from_slice(&t.tag.to_le_bytes());
        out.extend_from_slice(&t.kind.to_le_bytes());
        if w.big {
            out.extend_from_slice(&t.count.to_le_bytes());
        } else {
            out.extend_from_slice(&(t.count as u32).to_le_bytes());
        }
        if t.bytes.len() <= inline {
            let mut v = t.bytes.clone();
            v.resize(inline, 0);
            out.extend_from_slice(&v);
        } else {
            if w.big {
                out.extend_from_slice(&extra_pos.to_le_bytes());
            } else {
                out.extend_from_slice(&(extra_pos as u32).to_le_bytes());
            }
            extra.extend_from_slice(&t.bytes);
            extra_pos += t.bytes.len() as u64;
            if t.bytes.len() % 2 == 1 {
                extra.push(0);
                extra_pos += 1;
            }
        }
    }
    if w.big {
        out.extend_from_slice(&next.to_le_bytes());
    } else {
        out.extend_from_slice(&(next as u32).to_le_bytes());
    }
    out.extend_from_slice(&extra);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn statistics_are_gdals_over_finite_values() {
        let mut st = Stats::default();
        st.add(&[1.0, 2.0, f32::NAN]);
        st.add(&[3.0]);
        let items: std::collections::HashMap<_, _> = st.items().into_iter().collect();
        assert_eq!(items["STATISTICS_MINIMUM"], "1");
        assert_eq!(items["STATISTICS_MAXIMUM"], "3");
        assert_eq!(items["STATISTICS_MEAN"], "2");
        let sd: f64 = items["STATISTICS_STDDEV"].parse().unwrap();
        assert!((sd - (2.0f64 / 3.0).sqrt()).abs() < 1e-15);
        assert_eq!(items["STATISTICS_VALID_PERCENT"], "75");
        assert!(Stats::default().items().is_empty());
    }

    #[test]
    fn float_predictor_matches_its_definition() {
        // Two values: bytes regrouped by significance, then differenced.
        let b = float_predictor(&[1.0, 2.0]);
        // 1.0 = 3F 80 00 00, 2.0 = 40 00 00 00 → planes 3F 40 | 80 00 | 00 00 | 00 00.
        let planes = [0x3Fu8, 0x40, 0x80, 0x00, 0, 0, 0, 0];
        let mut want = planes;
        for j in (1..8).rev() {
            want[j] = planes[j].wrapping_sub(planes[j - 1]);
        }
        assert_eq!(b, want);
    }

    #[test]
    fn overviews_average_valid_pixels_only() {
        let a = Array2::from_shape_vec(
            (3, 3),
            vec![1.0, 3.0, 5.0, f32::NAN, 2.0, 7.0, 4.0, 4.0, f32::NAN],
        )
        .unwrap();
        let h = halve(a.view(), SampleFormat::Float32);
        assert_eq!(h.dim(), (2, 2));
        assert_eq!(h[(0, 0)], 2.0);
        assert_eq!(h[(0, 1)], 6.0);
        assert_eq!(h[(1, 0)], 4.0);
        assert!(h[(1, 1)].is_nan());
        // Byte bands (counts, classes): the first valid pixel, never a mean.
        let b = halve(a.view(), SampleFormat::Byte);
        assert_eq!(b[(0, 0)], 1.0);
        assert_eq!(b[(0, 1)], 5.0);
        assert_eq!(b[(1, 0)], 4.0);
        assert!(b[(1, 1)].is_nan());
    }

    /// An I/O failure on a temporary is reported against the file asked for, and nothing is
    /// left behind: here the final assembly's temporary cannot be created (a directory is in
    /// its place), as a full disk or a lost mount would fail it.
    #[test]
    fn write_errors_name_the_final_file() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-cogerr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("residual.tif");
        let blocker = crate::raster::tmp_name(&path);
        std::fs::create_dir_all(&blocker).unwrap();
        let info = BandInfo {
            description: "x",
            unit: "",
            metadata: &[],
        };
        let mut w = CogWriter::create(&path, None, 3, 2, &info, Container::Auto).unwrap();
        w.push(Array2::from_elem((2, 3), 1.0).view()).unwrap();
        let e = w.finish().unwrap_err();
        match &e {
            Error::Io { path: p, .. } => assert_eq!(p, &path, "{e}"),
            other => panic!("not an I/O error: {other}"),
        }
        std::fs::remove_dir(&blocker).unwrap();
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
        assert!(left.is_empty(), "{left:?}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn byte_predictor_differences_bytes_and_marks_no_data() {
        assert_eq!(
            byte_predictor(&[3.0, 5.0, 2.0, f32::NAN]),
            vec![3, 2, 253, 253]
        );
    }

    /// A Byte band round-trips through the tiff crate with its no-data value, and values that
    /// do not fit are refused naming the file and the pixel.
    #[test]
    fn byte_bands_round_trip_and_refuse_what_does_not_fit() {
        let dir = std::env::temp_dir().join(format!("sfsfuse-byte-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("count.tif");
        let a = Array2::from_shape_fn((300, 270), |(i, j)| {
            if i == 7 && j == 9 {
                f64::NAN
            } else {
                ((i + 2 * j) % 5) as f64
            }
        });
        let info = BandInfo {
            description: "a count",
            unit: "",
            metadata: &[],
        };
        let mut w = CogWriter::create_as(
            &path,
            None,
            270,
            300,
            &info,
            Container::Auto,
            SampleFormat::Byte,
        )
        .unwrap();
        w.push(a.view()).unwrap();
        w.finish().unwrap();
        let r = read_tiff(&path).unwrap();
        assert_eq!(r.nodata, Some(255.0));
        assert_eq!(r.images, 2);
        for ((i, j), &v) in r.data.indexed_iter() {
            let want = if (i, j) == (7, 9) { 255.0 } else { a[(i, j)] };
            assert_eq!(v, want, "({i}, {j})");
        }
        let mut w = CogWriter::create_as(
            &path,
            None,
            2,
            1,
            &info,
            Container::Auto,
            SampleFormat::Byte,
        )
        .unwrap();
        let e = w
            .push(Array2::from_elem((1, 2), 2.5).view())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("count.tif") && e.contains("2.5") && e.contains("row 0"),
            "{e}"
        );
        drop(w);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn ghost_block_declares_its_own_size() {
        let g = String::from_utf8(ghost_block()).unwrap();
        let (first, rest) = g.split_once('\n').unwrap();
        let n: usize = first
            .trim_start_matches("GDAL_STRUCTURAL_METADATA_SIZE=")
            .trim_end_matches(" bytes")
            .parse()
            .unwrap();
        assert_eq!(n, rest.len());
    }
}
