//! Tiles with halos and the weights that blend them into a seamless mosaic (pure; no I/O).
//!
//! The grid is cut into cores of `tile_size` pixels (the last row/column of cores may be
//! smaller); each tile is solved on its core widened by `halo` pixels on every side (clipped
//! to the grid), so that every filter and the solver's boundary see context. In the mosaic,
//! pixel t (centre coordinate t + ½ along an axis) takes from a tile whose core spans [a, b)
//! the weight ramp_a(t)·ramp_b(t), with
//! ramp_a(t) = clamp((t + ½ − (a − h)) / 2h, 0, 1) (1 at the grid's first edge) and
//! ramp_b(t) = clamp(((b + h) − (t + ½)) / 2h, 0, 1) (1 at the grid's last edge),
//! h the blend half-width (≤ halo; by default halo / 2), and the product of both axes. Neighbouring ramps cross at the shared core
//! edge and sum to 1 there, so the weights of all tiles sum to 1 at every pixel (a partition
//! of unity) and only the inner h pixels of each halo are used: the rest, nearest the tile's
//! artificial boundary, is discarded.

use serde::{Deserialize, Serialize};

/// A rectangle of grid pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Window {
    pub r0: usize,
    pub c0: usize,
    pub rows: usize,
    pub cols: usize,
}

impl Window {
    pub fn len(&self) -> usize {
        self.rows * self.cols
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// One unit of work.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tile {
    pub id: usize,
    /// The pixels this tile is responsible for.
    pub core: Window,
    /// The pixels it is solved on: the core plus the halo, clipped to the grid.
    pub ext: Window,
}

/// The smallest m ≥ n whose prime factors are 2, 3, 5 and 7 only: lengths the FFT behind
/// [`crate::spectral::Dct2d`] transforms fast. (A 1104-px window, 2⁴·3·23 — a 1024-px core with
/// 40-px halos — takes 1.85× as long per 2-D DCT as a 1120-px one, 2⁵·5·7.)
pub fn smooth_len(n: usize) -> usize {
    let smooth = |mut m: usize| {
        for p in [2, 3, 5, 7] {
            while m.is_multiple_of(p) {
                m /= p;
            }
        }
        m == 1
    };
    (n.max(1)..)
        .find(|&m| smooth(m))
        .expect("7-smooth numbers are unbounded")
}

/// The tiles of a `rows × cols` grid, numbered row-major from 0. Each window is the core
/// widened by `halo` on every side, then widened further, as far as the grid allows, to a
/// length of [`smooth_len`] (towards the grid's far edge first): more context for the same
/// core, and a fast transform.
pub fn layout(rows: usize, cols: usize, tile_size: usize, halo: usize) -> Vec<Tile> {
    let tile_size = tile_size.max(1);
    let axis = |n: usize| -> Vec<(usize, usize, usize, usize)> {
        (0..n.div_ceil(tile_size))
            .map(|k| {
                let a = k * tile_size;
                let b = (a + tile_size).min(n);
                let mut ea = a.saturating_sub(halo);
                let mut eb = (b + halo).min(n);
                let want = smooth_len(eb - ea);
                if want <= n {
                    eb = (ea + want).min(n);
                    ea = eb - want;
                }
                (a, b - a, ea, eb - ea)
            })
            .collect()
    };
    let (ry, rx) = (axis(rows), axis(cols));
    let mut tiles = Vec::with_capacity(ry.len() * rx.len());
    for &(r0, nr, er0, enr) in &ry {
        for &(c0, nc, ec0, enc) in &rx {
            tiles.push(Tile {
                id: tiles.len(),
                core: Window {
                    r0,
                    c0,
                    rows: nr,
                    cols: nc,
                },
                ext: Window {
                    r0: er0,
                    c0: ec0,
                    rows: enr,
                    cols: enc,
                },
            });
        }
    }
    tiles
}

/// The blend weight along one axis of pixel `t` for a core [a, a + n) of a grid of `len`
/// pixels, with ramps of half-width `h`.
fn ramp(t: usize, a: usize, n: usize, len: usize, h: f64) -> f64 {
    let x = t as f64 + 0.5;
    let b = a + n;
    let lo = if a == 0 || h == 0.0 {
        if t >= a || a == 0 {
            1.0
        } else {
            0.0
        }
    } else {
        ((x - (a as f64 - h)) / (2.0 * h)).clamp(0.0, 1.0)
    };
    let hi = if b >= len || h == 0.0 {
        if t < b || b >= len {
            1.0
        } else {
            0.0
        }
    } else {
        (((b as f64 + h) - x) / (2.0 * h)).clamp(0.0, 1.0)
    };
    lo * hi
}

/// The mosaic weight of `tile` at grid pixel (r, c) of a `rows × cols` grid, with ramps of
/// half-width `h` pixels (at most the halo; the default is halo / 2).
pub fn weight(tile: &Tile, rows: usize, cols: usize, h: f64, r: usize, c: usize) -> f64 {
    ramp(r, tile.core.r0, tile.core.rows, rows, h) * ramp(c, tile.core.c0, tile.core.cols, cols, h)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_cover_the_grid_and_weights_sum_to_one() {
        for (rows, cols, size, halo) in [
            (100, 70, 32, 10),
            (64, 64, 64, 8),
            (50, 131, 16, 9),
            (7, 5, 4, 3),
        ] {
            let tiles = layout(rows, cols, size, halo);
            let mut sum = vec![0.0f64; rows * cols];
            let mut owners = vec![0usize; rows * cols];
            for t in &tiles {
                assert!(t.ext.r0 + t.ext.rows <= rows && t.ext.c0 + t.ext.cols <= cols);
                for r in t.core.r0..t.core.r0 + t.core.rows {
                    for c in t.core.c0..t.core.c0 + t.core.cols {
                        owners[r * cols + c] += 1;
                    }
                }
                for r in 0..rows {
                    for c in 0..cols {
                        let w = weight(t, rows, cols, halo as f64 / 2.0, r, c);
                        let inside = (t.ext.r0..t.ext.r0 + t.ext.rows).contains(&r)
                            && (t.ext.c0..t.ext.c0 + t.ext.cols).contains(&c);
                        // Weight only where the tile has data, and only the inner half-halo.
                        assert!(
                            w == 0.0 || inside,
                            "tile {} weighs ({r},{c}) outside its window",
                            t.id
                        );
                        sum[r * cols + c] += w;
                    }
                }
            }
            assert!(
                owners.iter().all(|&n| n == 1),
                "cores must partition the grid"
            );
            for (k, s) in sum.iter().enumerate() {
                assert!(
                    (s - 1.0).abs() < 1e-12,
                    "{rows}×{cols}/{size}/{halo}: weight sum {s} at {k}"
                );
            }
        }
    }

    #[test]
    fn windows_have_smooth_lengths_where_the_grid_allows() {
        assert_eq!(smooth_len(1104), 1120);
        assert_eq!(smooth_len(1024), 1024);
        assert_eq!(smooth_len(296), 300);
        assert_eq!(smooth_len(11), 12);
        for t in layout(3000, 1100, 1024, 40) {
            let (e, c) = (t.ext, t.core);
            // The halo is still there, and only grows.
            assert!(
                e.r0 <= c.r0.saturating_sub(40) && e.r0 + e.rows >= (c.r0 + c.rows + 40).min(3000)
            );
            assert!(
                e.c0 <= c.c0.saturating_sub(40) && e.c0 + e.cols >= (c.c0 + c.cols + 40).min(1100)
            );
            assert_eq!(e.rows, smooth_len(e.rows), "{t:?}");
            assert_eq!(e.cols, smooth_len(e.cols), "{t:?}");
        }
        // One tile over the whole width of 1100 = 2²·5²·11: no smooth length fits.
        let t = layout(500, 1100, 2048, 40);
        assert_eq!((t[0].ext.rows, t[0].ext.cols), (500, 1100));
    }

    #[test]
    fn ramps_cross_at_the_core_edge() {
        let tiles = layout(1, 40, 20, 8);
        // Pixels 19 and 20 straddle the edge between the two cores at 20.
        let w = |t: usize, c: usize| weight(&tiles[t], 1, 40, 4.0, 0, c);
        assert!((w(0, 19) - 0.5625).abs() < 1e-12 && (w(1, 19) - 0.4375).abs() < 1e-12);
        assert_eq!(w(0, 15), 1.0);
        assert_eq!(w(0, 24), 0.0);
        assert_eq!(w(1, 15), 0.0);
    }
}
