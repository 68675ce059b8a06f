//! The fast z-solver: Gauss–Newton on E(z) with R linearised in (z_x, z_y) — plus the residual
//! curvature at pixels with large |I − R| — each step solved by conjugate gradients in the DCT
//! basis, preconditioned by the DCT-diagonal operator of the quadratic terms (docs/science.md), with a
//! backtracking line search on the true energy. A stage ends when no height moves by more than
//! `step_tolerance` × ε in a step (or E stagnates, or `max_iterations`).

use super::objective::{Energy, Iterate, Objective, Photo};
use super::{ops, FusionParams, IterationRecord};
use crate::spectral;
use ndarray::{Array2, ArrayView2, Zip};

/// Dᵀ(H + M)D·v for the photometric term: H = Σ_k 2w_k(a_k, b_k)ᵀ(a_k, b_k) the per-pixel
/// Gauss–Newton Hessian in (p, q) ([`Photo::gn`]), M the residual curvature of
/// [`Objective::curvature`], both acting on (D_x v, D_y v).
fn data_normal(
    obj: &Objective,
    photo: &Photo,
    curv: &Array2<[f64; 3]>,
    v: &Array2<f64>,
) -> Array2<f64> {
    let eps = obj.problem.spacing;
    let (vx, vy) = ops::gradient(v.view(), eps);
    let mut u = Array2::zeros(v.dim());
    let mut w = Array2::zeros(v.dim());
    Zip::indexed(&mut u)
        .and(&mut w)
        .and(&photo.gn)
        .and(curv)
        .par_for_each(|ij, u, w, h, m| {
            let (x, y) = (vx[ij], vy[ij]);
            *u = (h[0] + m[0]) * x + (h[1] + m[1]) * y;
            *w = (h[1] + m[1]) * x + (h[2] + m[2]) * y;
        });
    let mut out = ops::gradient_adjoint(u.view(), w.view(), eps);
    if let Some(k) = &obj.tie {
        Zip::from(&mut out)
            .and(k)
            .and(v)
            .par_for_each(|o, &k, &v| *o += 2.0 * k * v);
    }
    out
}

/// Preconditioned CG for (Dᵀ(H + M)D + 2K + H_Q + H_R)Δ (H_R the DEM term's relief field,
/// [`Objective::relief_hessian`]) = −g in DCT coefficients (K the tie's
/// per-pixel weight); returns (Δ, iterations). Without a tie no term sees the mean height, which
/// stays the DEM's; with one, the mean is solved for too.
fn newton_step(
    obj: &Objective,
    photo: &Photo,
    curv: &Array2<[f64; 3]>,
    hq: &Array2<f64>,
    g: &Array2<f64>,
    params: &FusionParams,
) -> (Array2<f64>, usize) {
    let (ny, nx) = g.dim();
    let e2 = obj.problem.spacing * obj.problem.spacing;
    let n = curv.len() as f64;
    let (ax, ay) = curv
        .iter()
        .zip(&photo.gn)
        .fold((0.0, 0.0), |(x, y), (m, h)| {
            (x + (m[0] + h[0]) / n, y + (m[2] + h[2]) / n)
        });
    let cx = spectral::central_symbol(nx);
    let cy = spectral::central_symbol(ny);
    let tie = obj.tie.as_ref().map(|k| 2.0 * ops::sum(k.view()) / n);
    let mut minv = spectral::separable(&cy, &cx, |sy, sx| (ax * sx + ay * sy) / e2);
    if obj.dem_relief.is_some() {
        // The relief field lowers δ where several observations overlap: precondition with
        // its mean.
        minv += &obj.quadratic_hessian_with(obj.delta * (1.0 - obj.mean_relief()));
    } else {
        minv += hq;
    }
    minv += tie.unwrap_or(0.0);
    minv.mapv_inplace(|m| if m > 0.0 { 1.0 / m } else { 0.0 });
    let fixed_mean = tie.is_none();
    if fixed_mean {
        minv[(0, 0)] = 0.0; // the mean height is fixed by the DEM
    }
    let apply = |d: &Array2<f64>| {
        let v = obj.dct.inverse(d);
        let mut out = obj.dct.forward(&data_normal(obj, photo, curv, &v));
        Zip::from(&mut out)
            .and(hq)
            .and(d)
            .par_for_each(|o, &h, &x| *o += h * x);
        if let Some(rh) = obj.relief_hessian(d) {
            out.scaled_add(obj.delta, &rh);
        }
        if fixed_mean {
            out[(0, 0)] = 0.0;
        }
        out
    };
    let mut r = obj.dct.forward(g).mapv(|x| -x);
    if fixed_mean {
        r[(0, 0)] = 0.0;
    }
    let mut y = Array2::zeros(r.dim());
    let mut s = &r * &minv;
    let mut d = s.clone();
    let mut rs = ops::dot(r.view(), s.view());
    let r0 = ops::dot(r.view(), r.view()).sqrt();
    let mut it = 0;
    while it < params.cg_iterations && r0 > 0.0 {
        it += 1;
        let ad = apply(&d);
        let dad = ops::dot(d.view(), ad.view());
        if dad <= 0.0 {
            break;
        }
        let alpha = rs / dad;
        y.scaled_add(alpha, &d);
        r.scaled_add(-alpha, &ad);
        if ops::dot(r.view(), r.view()).sqrt() <= params.cg_tolerance * r0 {
            break;
        }
        s = &r * &minv;
        let rs_new = ops::dot(r.view(), s.view());
        let beta = rs_new / rs;
        rs = rs_new;
        d = &s + &(d * beta);
    }
    (obj.dct.inverse(&y), it)
}

pub fn minimise(
    obj: &Objective,
    z: &mut Array2<f64>,
    rho: ArrayView2<f64>,
    params: &FusionParams,
    observe: &mut dyn FnMut(&Energy),
) -> Vec<IterationRecord> {
    let hq = obj.quadratic_hessian();
    let (
        Iterate {
            mut photo,
            mut zh,
            mut energy,
        },
        mut log,
    ) = super::start(obj, z, rho, observe);
    for iteration in 1..=params.max_iterations {
        let g = obj.gradient(z.view(), &zh, &photo);
        let curv = obj.curvature(z.view(), rho, &photo, params.curvature_residual);
        let (step, inner) = newton_step(obj, &photo, &curv, &hq, &g, params);
        let slope = ops::dot(g.view(), step.view());
        if slope >= 0.0 {
            break;
        }
        let mut t = 1.0;
        let mut accepted = None;
        for _ in 0..12 {
            let mut trial = z.clone();
            trial.scaled_add(t, &step);
            let Iterate {
                photo: tp,
                zh: th,
                energy: te,
            } = obj.evaluate(&trial, rho);
            if te.total <= energy.total + 1e-4 * t * slope {
                accepted = Some((trial, tp, th, te));
                break;
            }
            t *= 0.5;
        }
        let Some((nz, np, nh, ne)) = accepted else {
            break;
        };
        let gain = (energy.total - ne.total) / energy.total.max(f64::MIN_POSITIVE);
        let moved = t * ops::max_abs(step.view());
        (*z, photo, zh, energy) = (nz, np, nh, ne);
        observe(&energy);
        log.push(IterationRecord {
            iteration,
            energy,
            inner,
            max_step: moved,
        });
        if gain < params.tolerance || moved < params.step_tolerance * obj.problem.spacing {
            break;
        }
    }
    log
}
