//! The plan's registration of each observation ([`register`]): where its swath pixels lie on
//! the grid, against the DEM's shading or an earlier observation, estimated on segments along
//! its track so that a displacement that drifts along the strip is followed
//! (docs/science.md, "Registration").

use super::*;
use crate::ingest::INDEX_BLOCK;
use crate::registration::{Knot, Shift};

/// The displacement each observation is moved back by: its registration's where applied, none
/// elsewhere. Every ingest of the run uses it.
pub(super) fn shifts(registration: &[Registration]) -> Vec<Displacement> {
    registration
        .iter()
        .map(Registration::displacement)
        .collect()
}

impl Registration {
    /// The displacement the run moves the observation back by: `displacement` where applied
    /// (a plan written before displacements could drift records only `shift_m`: that one,
    /// constant), none otherwise.
    pub fn displacement(&self) -> Displacement {
        match (self.applied, self.shift_m) {
            (true, _) if !self.displacement.knots.is_empty() => self.displacement.clone(),
            (true, Some(m)) => Displacement::constant(m),
            _ => Displacement::default(),
        }
    }
}

/// One observation's registration ([`crate::registration`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Registration {
    /// The displacement found, grid pixels (`None`: not estimated, or no clear peak). Along
    /// the track (`along_track`), the mean of the segments' estimates that count (of all
    /// found, where none counts), its correlation the lowest of theirs.
    pub shift: Option<Shift>,
    /// The same along the grid's x and y, metres.
    pub shift_m: Option<[f64; 2]>,
    /// The observation (input index) it was placed relative to; `None`: against the DEM.
    #[serde(default)]
    pub relative_to: Option<usize>,
    /// The length, grid pixels, from which its estimate is applied, set by the Sun's elevation
    /// on its window (along the track, the shortest of the segments' placed as `relative_to`
    /// says, each set by its own window's Sun); `None` where nothing was estimated.
    #[serde(default)]
    pub min_px: Option<f64>,
    /// On one window, the Sun's elevation, degrees, `min_px` was set by (as
    /// [`Segment::sun_elevation_deg`]); along the track each segment records its own.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sun_elevation_deg: Option<f64>,
    /// Whether the run moves the observation back.
    pub applied: bool,
    /// Where its footprint spans two or more [`REGISTER_SEGMENT`]s along the track: each
    /// segment's estimate, in the order of the swath's lines.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub along_track: Vec<Segment>,
    /// What the run moves it back by where applied (no knot otherwise): one translation, or
    /// the segments' estimates that count as knots at their lines, carried linearly to the
    /// first and last lines the segments' windows hold.
    #[serde(default)]
    pub displacement: Displacement,
    /// What was done and why, in words.
    pub note: String,
}

/// One segment of an observation's track ([`Registration::along_track`]).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Segment {
    /// The swath line its estimate stands for: the mean line of the pixels on its window,
    /// weighted by their share of the correlation at the peak
    /// ([`crate::registration::where_estimated`]; the middle of the window's lines without an
    /// estimate).
    pub line: f64,
    /// Its window on the grid: first row, rows, first column, columns.
    pub window: [usize; 4],
    /// Its estimate, grid pixels (`None`: no clear peak), and in metres along x and y.
    pub shift: Option<Shift>,
    pub shift_m: Option<[f64; 2]>,
    /// Placed relative to the registration's `relative_to` (`false`: against the DEM, where
    /// the earlier observation had nothing usable on the segment).
    pub relative: bool,
    /// The length, grid pixels, from which its estimate counts towards moving the
    /// observation back.
    #[serde(default)]
    pub min_px: Option<f64>,
    /// The Sun's elevation, degrees, that length was set by: the observation's mean over its
    /// usable pixels on the segment's window (placed relative to another, the higher of the
    /// two observations' there). Over a long strip it changes along the track.
    #[serde(default)]
    pub sun_elevation_deg: Option<f64>,
}

/// The largest window, pixels on a side, an observation is registered on.
pub const REGISTER_WINDOW: usize = 512;

/// The length along the track, grid pixels, of the segments an observation's footprint is cut
/// into: a footprint of fewer than two segments is registered on one window (one
/// translation); a longer one on each segment, so that a displacement drifting along the
/// strip (M3's attitude drifts over an orbit) is followed. 256 px is 36 km at 140 m, long
/// enough for estimates as good as on one window (docs/science.md, "Registration").
pub const REGISTER_SEGMENT: usize = 256;

/// The most segments a footprint is cut into: a longer one is cut into segments longer than
/// [`REGISTER_SEGMENT`], each registered on a window of at most [`REGISTER_WINDOW`] px along
/// the track at its middle, so the plan's registration costs at most this many windows per
/// observation however long the region.
pub const REGISTER_MAX_SEGMENTS: usize = 8;

/// The widest DEM point spread σ_B, grid pixels, against which an observation is registered:
/// beyond it the DEM's shading holds too little to place an image to a pixel.
pub const REGISTER_MAX_PSF: f64 = 8.0;

/// The smallest side, grid pixels, of two observations' common window for one to be placed
/// relative to the other.
const RELATIVE_MIN_SIDE: f64 = 64.0;

/// One window's estimate ([`Context::estimate`]).
struct Found {
    /// First row, rows, first column, columns of the grid.
    window: [usize; 4],
    shift: Option<Shift>,
    /// Placed relative to the earlier observation (`false`: against the DEM).
    relative: bool,
    /// The swath line it stands for ([`crate::registration::where_estimated`]).
    line: Option<f64>,
    /// The first and last swath lines on the window.
    extent: Option<(f64, f64)>,
    /// The mean Sun elevation, degrees, over the observation's usable pixels on the window
    /// and, placed relative to another, over that one's
    /// ([`crate::registration::mean_sun_elevation_deg`]; NaN where there are none).
    sun_elevation_deg: [f64; 2],
}

/// From what length an estimate is applied ([`Context::apply_from`]).
struct ApplyFrom {
    /// The length, grid pixels.
    px: f64,
    /// The Sun's elevation, degrees, that set it (NaN without one).
    elevation_deg: f64,
    /// Where the length comes from, in words.
    why: String,
}

impl ApplyFrom {
    /// The elevation where there is one.
    fn elevation(&self) -> Option<f64> {
        self.elevation_deg.is_finite().then_some(self.elevation_deg)
    }
}

/// The run-wide quantities a registration window is estimated with.
struct Context<'a> {
    o: &'a Orbital,
    inputs: &'a Inputs,
    grid: &'a Grid,
    swaths: &'a [SwathIndex],
    psf: f64,
    params: &'a FusionParams,
    scale: f64,
    /// Each observation's mean Sun over its pixels on the grid, degrees (azimuth, elevation;
    /// [`super::plan::Plan::sun_deg`]): its elevation sets from what length an estimate is
    /// applied where the estimate's window gives none.
    sun_deg: &'a [Option<[f64; 2]>],
}

/// Register every observation ([`Registration`]), in input order, on windows of at most
/// [`REGISTER_WINDOW`]² pixels ([`crate::registration::estimate`], searched over
/// `[inputs] register_search_px`), one per [`REGISTER_SEGMENT`] of its footprint along the
/// track (one for a shorter footprint):
/// - one that overlaps an observation listed before it (the one it overlaps most) is placed
///   relative to that one: against the single-image fusion of the earlier observation (moved
///   by its own displacement) on their common window, rendered under the later one's Sun and
///   view. The fused relief is as sharp as the image, so the estimate's bias is a few tenths
///   of a pixel; applied from twice the longest such bias measured under Suns as high as the
///   higher of the two ([`crate::registration::relative_apply_px`], at least 0.75 px);
/// - any other (the first listed, or one overlapping none before it) is placed against the DEM
///   rendered under its own Sun and view, applied from `[inputs] register_min_px` or, by
///   default, from twice the longest bias measured under a Sun as high as its own
///   ([`crate::registration::dem_apply_px`], at least 1.25 px).
///
/// Each Sun's elevation is its mean over the observation's usable pixels on the window the
/// estimate is made on ([`crate::registration::mean_sun_elevation_deg`]), so each segment of
/// a long strip is judged by its own Sun.
///
/// An estimate counts where the peak's correlation reaches
/// [`crate::registration::APPLY_CORRELATION`]; the observation is moved back when one that
/// counts is at least as long as its threshold: by it alone, or, along the track, by the
/// displacement through every one that counts.
pub(super) fn register(
    o: &Orbital,
    inputs: &Inputs,
    grid: &Grid,
    swaths: &[SwathIndex],
    psf: f64,
    params: &FusionParams,
    (scale, sun_deg): (f64, &[Option<[f64; 2]>]),
) -> Result<Vec<Registration>> {
    let cx = Context {
        o,
        inputs,
        grid,
        swaths,
        psf,
        params,
        scale,
        sun_deg,
    };
    let mut out: Vec<Registration> = Vec::with_capacity(inputs.obs.len());
    let boxes: Vec<Option<[f64; 4]>> = swaths.iter().map(|ix| footprint_box(grid, ix)).collect();
    for k in 0..inputs.obs.len() {
        if !o.inputs.register {
            out.push(not("not registered: [inputs] register = false".into()));
            continue;
        }
        if psf > REGISTER_MAX_PSF {
            out.push(not(format!(
                "not registered: the DEM's point spread σ_B = {psf:.1} px is wider than {REGISTER_MAX_PSF} px, too wide to place the image to a pixel"
            )));
            continue;
        }
        let Some(own) = boxes[k] else {
            out.push(not(
                "not registered: the observation does not reach the region".into(),
            ));
            continue;
        };
        // The earlier observation it overlaps most, on a window of at least 64 px a side.
        let partner = (0..k)
            .filter_map(|j| {
                let b = intersect(own, boxes[j]?)?;
                let (h, w) = (b[1] - b[0] + 1.0, b[3] - b[2] + 1.0);
                (h >= RELATIVE_MIN_SIDE && w >= RELATIVE_MIN_SIDE).then_some((j, b, h * w))
            })
            .fold(None, |best: Option<(usize, [f64; 4], f64)>, c| match best {
                Some(b) if b.2 >= c.2 => Some(b),
                _ => Some(c),
            });
        let (area, partner) = match partner {
            Some((j, b, _)) => (b, Some(j)),
            None => (own, None),
        };
        let pieces = segments(area, along_rows(grid, &swaths[k]));
        let estimates = |prior: &Displacement| -> Result<Vec<_>> {
            let mut found = Vec::with_capacity(pieces.len());
            for &piece in &pieces {
                let (win, at) = window_on(grid, piece);
                let with = partner.map(|j| (j, &out[j]));
                found.push(cx.estimate(k, (&win, at), prior, with)?);
            }
            Ok(found)
        };
        let none = Displacement::default();
        let mut found = estimates(&none)?;
        out.push(if found.len() == 1 {
            let f = found.pop().expect("one");
            let relative_to = f.relative.then_some(partner).flatten();
            one_window(&cx, k, f, relative_to)
        } else {
            // Each segment's estimate is that of its middle only where the displacement is
            // the same along it: where it drifts, the peak is smeared and falls short. So once
            // moved back, each segment is estimated again and what is left added.
            let first = along_track(&cx, k, found, partner, &none);
            if first.applied {
                along_track(
                    &cx,
                    k,
                    estimates(&first.displacement)?,
                    partner,
                    &first.displacement,
                )
            } else {
                first
            }
        });
    }
    Ok(out)
}

/// A registration that estimated nothing, with its reason.
fn not(note: String) -> Registration {
    Registration {
        shift: None,
        shift_m: None,
        relative_to: None,
        min_px: None,
        sun_elevation_deg: None,
        applied: false,
        along_track: Vec::new(),
        displacement: Displacement::default(),
        note,
    }
}

impl Context<'_> {
    /// Observation `k`'s displacement on window `win` once moved back by `prior`: relative to
    /// observation j of `partner` (with its registration, already made) where that one fused
    /// alone has something usable there (`true`), else against the DEM; with the swath line
    /// it was estimated at ([`crate::registration::where_estimated`]).
    fn estimate(
        &self,
        k: usize,
        (win, window): (&Grid, [usize; 4]),
        prior: &Displacement,
        partner: Option<(usize, &Registration)>,
    ) -> Result<Found> {
        let (o, inputs) = (self.o, self.inputs);
        let pr = projector(&win.crs)?;
        let geo = win.geographic(&pr);
        let dem = dem_on(o, inputs, &geo)?;
        let ingest = |k: usize, shift: &Displacement| {
            ingest::m3_on_grid_with_lines(
                &inputs.obs[k],
                inputs.solar(k),
                o.inputs.wavelength_nm,
                win,
                &pr,
                geo.bearing.view(),
                Some(&self.swaths[k]),
                shift,
                true,
            )
            .map(|(img, lines)| (img, lines.expect("asked for")))
        };
        let (img, lines) = ingest(k, prior)?;
        let (sun, view) = (
            Directions::PerPixel(img.sun.view().into()),
            Directions::PerPixel(img.view.view().into()),
        );
        // The earlier observation fused alone on the common window; `None`: place against
        // the DEM.
        let mut partner_sun = f64::NAN;
        let fused = match partner {
            Some((j, r)) => {
                let other = [(j, ingest(j, &r.displacement())?.0)];
                partner_sun = crate::registration::mean_sun_elevation_deg(
                    other[0].1.reflectance.view(),
                    other[0].1.sun.view(),
                );
                let mut filled = dem.clone();
                crate::pipeline::lab::fill_holes(&mut filled);
                let problem = Problem {
                    observations: fusion_observations(&other),
                    dem: filled.view(),
                    spacing: self.grid.spacing,
                    dem_psf_sigma: self.psf,
                    model: inputs.model.as_ref(),
                    intensity_scale: Some(self.scale),
                    gains: None,
                    noise_weights: None,
                    blur: None,
                    selection: o.inputs.selection(),
                };
                // Nothing of the earlier observation usable there (all in shadow, say):
                // against the DEM on the same window.
                fusion::fuse(&problem, self.params).ok().map(|f| f.height)
            }
            None => None,
        };
        let own_sun =
            crate::registration::mean_sun_elevation_deg(img.reflectance.view(), img.sun.view());
        let sun_elevation_deg = [
            own_sun,
            if fused.is_some() {
                partner_sun
            } else {
                f64::NAN
            },
        ];
        // The fused relief is as sharp as the image; the DEM's is blurred by σ_B, and casts
        // its shadows under a lower Sun to make up for its lower rims.
        let against_psf = if fused.is_some() { 0.0 } else { self.psf };
        let rendered = crate::registration::render_lowered(
            fused.as_ref().map_or(dem.view(), |f| f.view()),
            self.grid.spacing,
            inputs.model.as_ref(),
            (&sun, &view),
            against_psf,
        );
        let est = crate::registration::estimate(
            img.reflectance.view(),
            rendered.view(),
            against_psf,
            o.inputs.register_search_px,
        );
        let line = est.as_ref().and_then(|s| {
            crate::registration::where_estimated(
                img.reflectance.view(),
                rendered.view(),
                against_psf,
                s,
                lines.view(),
            )
        });
        let extent =
            lines
                .iter()
                .filter(|l| l.is_finite())
                .fold(None, |e: Option<(f64, f64)>, &l| {
                    let l = f64::from(l);
                    Some(e.map_or((l, l), |(a, b)| (a.min(l), b.max(l))))
                });
        Ok(Found {
            window,
            shift: est,
            relative: fused.is_some(),
            line,
            extent,
            sun_elevation_deg,
        })
    }

    /// What an estimate is made against, in words.
    fn against(&self, relative_to: Option<usize>) -> String {
        match relative_to {
            Some(j) => format!(
                "relative to observation {} ({}), fused alone",
                j + 1,
                self.inputs.obs[j].label_path.display()
            ),
            None => "against the DEM's shading".to_string(),
        }
    }

    /// The length from which observation `k`'s estimate, made as `relative_to` says
    /// ([`Context::against`]) on a window under the Suns `sun` ([`Found::sun_elevation_deg`]),
    /// is applied ([`ApplyFrom`]). Where the window gives no elevation, the observation's
    /// mean over the region.
    fn apply_from(&self, k: usize, relative_to: Option<usize>, sun: [f64; 2]) -> ApplyFrom {
        let elevation = |i: usize, k: usize| {
            if sun[i].is_finite() {
                sun[i]
            } else {
                self.sun_deg[k].map_or(f64::NAN, |s| s[1])
            }
        };
        match (relative_to, self.o.inputs.register_min_px) {
            (Some(j), _) => {
                let higher = elevation(0, k).max(elevation(1, j));
                ApplyFrom {
                    px: crate::registration::relative_apply_px(higher),
                    elevation_deg: higher,
                    why: format!(
                        "twice the longest bias of such an estimate where the higher Sun stands {higher:.0}° high"
                    ),
                }
            }
            (None, Some(m)) => ApplyFrom {
                px: m,
                elevation_deg: elevation(0, k),
                why: "[inputs] register_min_px".to_string(),
            },
            (None, None) => {
                let el = elevation(0, k);
                ApplyFrom {
                    px: crate::registration::dem_apply_px(el, self.psf),
                    elevation_deg: el,
                    why: format!(
                        "twice the longest bias of such an estimate under a Sun {el:.0}° high, the DEM's point spread {:.1} px",
                        self.psf
                    ),
                }
            }
        }
    }

    /// Metres along the grid's x and y of a displacement in grid pixels.
    fn metres(&self, s: &Shift) -> [f64; 2] {
        [s.cols * self.grid.spacing, -s.rows * self.grid.spacing]
    }
}

/// The registration of observation `k` estimated on one window (`found`), placed as
/// `relative_to` says.
fn one_window(cx: &Context, k: usize, found: Found, relative_to: Option<usize>) -> Registration {
    let search = cx.o.inputs.register_search_px;
    let what = cx.against(relative_to);
    let (win, est) = (found.window, found.shift);
    let from = cx.apply_from(k, relative_to, found.sun_elevation_deg);
    let (min_px, why) = (from.px, &from.why);
    match est {
        None => Registration {
            relative_to,
            ..not(format!(
                "not registered: no clear peak of the image's correlation {what} within {search} px on {} × {} px (a peak under {} or on the search's edge, or under {} px in common)",
                win[1],
                win[3],
                crate::registration::MIN_CORRELATION,
                crate::registration::MIN_PIXELS
            ))
        },
        Some(s) => {
            let strong = s.correlation >= crate::registration::APPLY_CORRELATION;
            let applied = strong && s.length() >= min_px;
            let m = cx.metres(&s);
            Registration {
                shift: Some(s),
                shift_m: Some(m),
                relative_to,
                min_px: Some(min_px),
                sun_elevation_deg: from.elevation(),
                applied,
                along_track: Vec::new(),
                displacement: if applied {
                    Displacement::constant(m)
                } else {
                    Displacement::default()
                },
                note: format!(
                    "displaced {:.2} px ({:.0} m) {what} (correlation {:.3}, {:.3} in place): {}",
                    s.length(),
                    s.length() * cx.grid.spacing,
                    s.correlation,
                    s.correlation_in_place,
                    if applied {
                        "moved back".to_string()
                    } else if !strong {
                        format!(
                            "left in place (a correlation under {} leaves the estimate too uncertain to act on)",
                            crate::registration::APPLY_CORRELATION
                        )
                    } else {
                        format!(
                            "left in place (under {min_px:.2} px, {why})"
                        )
                    }
                ),
            }
        }
    }
}

/// The segments of observation `k` from what was found on each, ordered by swath line: each
/// at the line it was estimated at (without an estimate, the middle of its window's lines),
/// its estimate with `prior` (what the image was already moved back by) added, and the length
/// it is applied from (relative to `partner` or against the DEM, as it was placed).
fn placed_segments(
    cx: &Context,
    (k, partner): (usize, Option<usize>),
    found: Vec<Found>,
    prior: &Displacement,
) -> Vec<Segment> {
    let index = &cx.swaths[k];
    let mut segs: Vec<Segment> = found
        .into_iter()
        .map(|f| {
            let (window, relative) = (f.window, f.relative);
            let from = cx.apply_from(k, partner.filter(|_| relative), f.sun_elevation_deg);
            // Without an estimate (display only): the middle of the window's lines.
            let line = f
                .line
                .or(f.extent.map(|(a, b)| 0.5 * (a + b)))
                .unwrap_or(0.5 * index.lines as f64);
            let [x, y] = prior.at(line).map(|m| m / cx.grid.spacing);
            let shift = f.shift.map(|s| Shift {
                rows: s.rows - y,
                cols: s.cols + x,
                ..s
            });
            Segment {
                line,
                window,
                shift_m: shift.as_ref().map(|s| cx.metres(s)),
                shift,
                relative,
                min_px: Some(from.px),
                sun_elevation_deg: from.elevation(),
            }
        })
        .collect();
    segs.sort_by(|a, b| a.line.total_cmp(&b.line));
    segs
}

/// The mean of the segments' estimates (each must have one): the mean displacement, the
/// smallest correlations, the pixels summed; `None` for no segment.
fn mean_shift(found: &[&Segment]) -> Option<Shift> {
    (!found.is_empty()).then(|| {
        let n = found.len() as f64;
        let e = |s: &&Segment| s.shift.expect("found");
        Shift {
            rows: found.iter().map(|s| e(s).rows).sum::<f64>() / n,
            cols: found.iter().map(|s| e(s).cols).sum::<f64>() / n,
            correlation: found.iter().map(|s| e(s).correlation).fold(1.0, f64::min),
            correlation_in_place: found
                .iter()
                .map(|s| e(s).correlation_in_place)
                .fold(1.0, f64::min),
            pixels: found.iter().map(|s| e(s).pixels).sum(),
        }
    })
}

/// The registration of observation `k` estimated on two or more segments along its track
/// (`found`: each segment's window, estimate, whether it was placed relative to `partner`, and
/// the swath line it was estimated at), the image moved back by `prior` (its estimates are
/// what is left: `prior` is added to them).
fn along_track(
    cx: &Context,
    k: usize,
    found: Vec<Found>,
    partner: Option<usize>,
    prior: &Displacement,
) -> Registration {
    // The lines the segments' windows hold together.
    let extent = found
        .iter()
        .filter_map(|f| f.extent)
        .reduce(|(a, b), (c, d)| (a.min(c), b.max(d)));
    let segs = placed_segments(cx, (k, partner), found, prior);
    let relative_to = partner.filter(|_| segs.iter().any(|s| s.relative));
    let threshold = |s: &Segment| s.min_px.unwrap_or(f64::INFINITY);
    let counts = |s: &&Segment| {
        s.shift
            .is_some_and(|e| e.correlation >= crate::registration::APPLY_CORRELATION)
    };
    let strong: Vec<&Segment> = segs.iter().filter(counts).collect();
    let applied = strong
        .iter()
        .any(|s| s.shift.is_some_and(|e| e.length() >= threshold(s)));
    // The mean of the estimates that count (of all found where none counts).
    let found: Vec<&Segment> = if strong.is_empty() {
        segs.iter().filter(|s| s.shift.is_some()).collect()
    } else {
        strong.clone()
    };
    let shift = mean_shift(&found);
    let displacement = if applied {
        knots(&strong, extent)
    } else {
        Displacement::default()
    };
    let what = cx.against(relative_to);
    let listed: Vec<String> = segs
        .iter()
        .map(|s| match s.shift {
            Some(e) => format!(
                "line {:.0}: {:.2} px (correlation {:.3})",
                s.line,
                e.length(),
                e.correlation
            ),
            None => format!("line {:.0}: no clear peak", s.line),
        })
        .collect();
    let verdict = if applied {
        let ends = [
            displacement.knots.first().expect("applied"),
            displacement.knots.last().expect("applied"),
        ]
        .map(|k| k.m[0].hypot(k.m[1]) / cx.grid.spacing);
        format!(
            "moved back along the track ({:.2} px at its first line, {:.2} px at its last)",
            ends[0], ends[1]
        )
    } else if strong.is_empty() {
        format!(
            "left in place (no segment reaches a correlation of {})",
            crate::registration::APPLY_CORRELATION
        )
    } else {
        let under: Vec<String> = strong
            .iter()
            .filter_map(|s| s.min_px)
            .map(|m| format!("{m:.2}"))
            .collect();
        format!(
            "left in place (every estimate under the length it is applied from, {} px)",
            under.join(" / ")
        )
    };
    Registration {
        shift_m: shift.as_ref().map(|s| cx.metres(s)),
        shift,
        relative_to,
        min_px: Some(
            segs.iter()
                .filter(|s| s.relative == relative_to.is_some())
                .filter_map(|s| s.min_px)
                .reduce(f64::min)
                .unwrap_or_else(|| cx.apply_from(k, relative_to, [f64::NAN; 2]).px),
        ),
        sun_elevation_deg: None,
        applied,
        note: format!(
            "registered {what} on {} segments along the track ({}): {verdict}",
            segs.len(),
            listed.join("; ")
        ),
        along_track: segs,
        displacement,
    }
}

/// The displacement through the estimates that count (at least one), ordered by line: one
/// translation for one; for more, knots at their lines, and at the first and last of `lines`
/// (those the segments' windows hold), there carried linearly from the nearest two. Beyond
/// them it stays constant: where an observation is placed relative to another over part of its
/// length only, the drift found there is not carried along the rest.
fn knots(strong: &[&Segment], lines: Option<(f64, f64)>) -> Displacement {
    let mut knots: Vec<Knot> = strong
        .iter()
        .map(|s| Knot {
            line: s.line,
            m: s.shift_m.expect("counts"),
        })
        .collect();
    // Two segments' middles at one line (a track across the rows of a narrow window): one
    // translation, their mean.
    knots.dedup_by(|b, a| {
        let same = b.line - a.line < INDEX_BLOCK as f64;
        if same {
            a.m = [0, 1].map(|c| 0.5 * (a.m[c] + b.m[c]));
        }
        same
    });
    if knots.len() < 2 {
        return Displacement::constant(knots[0].m);
    }
    if let Some((lo, hi)) = lines {
        let carry = |a: Knot, b: Knot, line: f64| Knot {
            line,
            m: [0, 1].map(|c| a.m[c] + (line - a.line) / (b.line - a.line) * (b.m[c] - a.m[c])),
        };
        let n = knots.len();
        if lo < knots[0].line {
            knots.insert(0, carry(knots[0], knots[1], lo));
        }
        if hi > knots[knots.len() - 1].line {
            knots.push(carry(knots[n - 2], knots[n - 1], hi));
        }
    }
    Displacement { knots }
}

/// Whether the swath's track runs along the grid's rows (down the columns, as a polar orbit's
/// does on a north-up grid) rather than along its columns: its blocks' middles move further in
/// rows than in columns from its first block on the grid to its last.
fn along_rows(grid: &Grid, index: &SwathIndex) -> bool {
    let middles: Vec<(f64, f64)> = index
        .boxes
        .iter()
        .flatten()
        .map(|b| grid.pixel(0.5 * (b[0] + b[1]), 0.5 * (b[2] + b[3])))
        .collect();
    match (middles.first(), middles.last()) {
        (Some(a), Some(b)) => (b.0 - a.0).abs() >= (b.1 - a.1).abs(),
        _ => true,
    }
}

/// Box `b` (of [`footprint_box`]) cut along the track into ⌊length / L⌋ equal segments, at
/// most [`REGISTER_MAX_SEGMENTS`] (itself where that is under two). L is
/// [`REGISTER_SEGMENT`], or longer where the box is narrow: a segment must hold twice the
/// pixels an estimate needs ([`crate::registration::MIN_PIXELS`]) across the box's width
/// (capped at [`REGISTER_WINDOW`], as its window is), so that a narrow strip registered on
/// one window before is not left unregistered on segments too small for an estimate.
fn segments(b: [f64; 4], rows: bool) -> Vec<[f64; 4]> {
    let ((lo, hi), (a, z)) = if rows {
        ((b[0], b[1]), (b[2], b[3]))
    } else {
        ((b[2], b[3]), (b[0], b[1]))
    };
    let width = (z - a + 1.0).min(REGISTER_WINDOW as f64);
    let least = (2 * crate::registration::MIN_PIXELS) as f64 / width;
    let n = (((hi - lo + 1.0) / least.max(REGISTER_SEGMENT as f64)).floor() as usize)
        .min(REGISTER_MAX_SEGMENTS);
    if n < 2 {
        return vec![b];
    }
    let step = (hi - lo + 1.0) / n as f64;
    (0..n)
        .map(|i| {
            let (a, z) = (lo + i as f64 * step, lo + (i + 1) as f64 * step - 1.0);
            if rows {
                [a, z, b[2], b[3]]
            } else {
                [b[0], b[1], a, z]
            }
        })
        .collect()
}

/// The bounding box [row₀, row₁, col₀, col₁] (grid pixels, inclusive, clipped to the grid) of
/// the swath's blocks that reach `grid`; `None`: none does.
fn footprint_box(grid: &Grid, index: &SwathIndex) -> Option<[f64; 4]> {
    let (mut r0, mut r1, mut c0, mut c1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for b in index.boxes.iter().flatten() {
        let (ra, ca) = grid.pixel(b[0], b[3]);
        let (rb, cb) = grid.pixel(b[1], b[2]);
        let (ra, rb) = (ra.max(0.0), rb.min(grid.rows as f64 - 1.0));
        let (ca, cb) = (ca.max(0.0), cb.min(grid.cols as f64 - 1.0));
        if ra <= rb && ca <= cb {
            (r0, r1, c0, c1) = (r0.min(ra), r1.max(rb), c0.min(ca), c1.max(cb));
        }
    }
    (r0 <= r1).then_some([r0, r1, c0, c1])
}

/// The common part of two boxes of [`footprint_box`].
fn intersect(a: [f64; 4], b: [f64; 4]) -> Option<[f64; 4]> {
    let r = [
        a[0].max(b[0]),
        a[1].min(b[1]),
        a[2].max(b[2]),
        a[3].min(b[3]),
    ];
    (r[0] <= r[1] && r[2] <= r[3]).then_some(r)
}

/// A window of at most [`REGISTER_WINDOW`]² pixels of `grid` centred on the middle of box `b`
/// (of [`footprint_box`]), as large as the box, with its first row, rows, first column and
/// columns.
fn window_on(grid: &Grid, b: [f64; 4]) -> (Grid, [usize; 4]) {
    let place = |lo: f64, hi: f64, n: usize| {
        let size = REGISTER_WINDOW
            .min((hi - lo + 1.0).ceil() as usize)
            .clamp(1, n);
        let mid = 0.5 * (lo + hi);
        let start = (mid - 0.5 * size as f64 + 0.5)
            .round()
            .clamp(0.0, (n - size) as f64) as usize;
        (start, size)
    };
    let (rs, rn) = place(b[0], b[1], grid.rows);
    let (cs, cn) = place(b[2], b[3], grid.cols);
    (
        grid.window(rs as isize, cs as isize, rn, cn),
        [rs, rn, cs, cn],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A footprint is cut into ⌊length/256⌋ equal segments along the track (longer ones where
    /// it is narrow, at most 8), itself under two.
    #[test]
    fn a_footprint_is_cut_into_segments_along_the_track() {
        let b = [0.0, 511.0, 10.0, 300.0];
        assert_eq!(
            segments(b, true),
            vec![[0.0, 255.0, 10.0, 300.0], [256.0, 511.0, 10.0, 300.0]]
        );
        assert_eq!(
            segments([0.0, 510.0, 10.0, 300.0], true),
            vec![[0.0, 510.0, 10.0, 300.0]]
        );
        let across = segments([5.0, 300.0, 0.0, 767.0], false);
        assert_eq!(across.len(), 3);
        assert_eq!(across[1], [5.0, 300.0, 256.0, 511.0]);
        // A long footprint: eight segments of 1024 px.
        let long = segments([0.0, 8191.0, 0.0, 300.0], true);
        assert_eq!(long.len(), REGISTER_MAX_SEGMENTS);
        assert_eq!(long[7], [7168.0, 8191.0, 0.0, 300.0]);
        // A strip 64 px wide: segments of at least 2 · 16384 / 64 = 512 px, so 1500 px make
        // two, and 1000 px one.
        assert_eq!(segments([0.0, 1499.0, 0.0, 63.0], true).len(), 2);
        assert_eq!(segments([0.0, 999.0, 0.0, 63.0], true).len(), 1);
    }

    fn segment(line: f64, m: [f64; 2]) -> Segment {
        Segment {
            line,
            window: [0; 4],
            shift: None,
            shift_m: Some(m),
            relative: false,
            min_px: None,
            sun_elevation_deg: None,
        }
    }

    /// The knots are the estimates at their lines, carried linearly to the first and last
    /// lines the segments hold; one estimate, or two at one line, give one translation.
    #[test]
    fn the_displacement_runs_through_the_estimates_to_the_region_s_ends() {
        let (a, b) = (segment(128.0, [100.0, 0.0]), segment(384.0, [300.0, -20.0]));
        let d = knots(&[&a, &b], Some((0.0, 511.0)));
        let lines: Vec<f64> = d.knots.iter().map(|k| k.line).collect();
        assert_eq!(lines, [0.0, 128.0, 384.0, 511.0]);
        // 200 m and −20 m over 256 lines, carried 128 lines back and 127 on.
        let close = |u: [f64; 2], v: [f64; 2]| (u[0] - v[0]).abs() + (u[1] - v[1]).abs() < 1e-9;
        assert!(close(d.knots[0].m, [0.0, 10.0]), "{d:?}");
        assert!(close(d.knots[3].m, [399.21875, -29.921875]), "{d:?}");
        assert!(close(d.at(256.0), [200.0, -10.0]));
        assert_eq!(
            knots(&[&a], Some((0.0, 511.0))),
            Displacement::constant([100.0, 0.0])
        );
        let same = segment(140.0, [200.0, 10.0]);
        assert_eq!(
            knots(&[&a, &same], Some((0.0, 511.0))),
            Displacement::constant([150.0, 5.0])
        );
    }
}
