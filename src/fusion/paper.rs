//! The seed's iteration (Eq. 2, after Horn 1989), kept as the faithful reference:
//!
//! p⁽ⁿ⁺¹⁾ = z_x⁽ⁿ⁾ + (1/γ)·F_x,  q⁽ⁿ⁺¹⁾ = z_y⁽ⁿ⁾ + (1/γ)·F_y,  z⁽ⁿ⁺¹⁾ = z̄⁽ⁿ⁾ − (ε²/κ)(p_x + q_y),
//!
//! F the force of the intensity, DEM and membrane terms at z⁽ⁿ⁾. Substituting the p-update into
//! the Jacobi sweep (κ = 4) gives z⁽ⁿ⁺¹⁾ = z⁽ⁿ⁾ − ε²/(2κγ)·∂E/∂z exactly, which is how it is
//! computed here, so that it descends the same discrete energy as the fast solver. Should a
//! sweep raise E (γ too small for stability), γ is doubled: a safeguard, reported in the record.

use super::objective::{Energy, Iterate, Objective};
use super::{ops, FusionParams, IterationRecord};
use ndarray::{Array2, ArrayView2};

const KAPPA: f64 = 4.0;

pub fn minimise(
    obj: &Objective,
    z: &mut Array2<f64>,
    rho: ArrayView2<f64>,
    params: &FusionParams,
    observe: &mut dyn FnMut(&Energy),
) -> Vec<IterationRecord> {
    let eps = obj.problem.spacing;
    let mut gamma = params.gamma;
    let (
        Iterate {
            mut photo,
            mut zh,
            mut energy,
        },
        mut log,
    ) = super::start(obj, z, rho, observe);
    let mut iteration = 0;
    while iteration < params.max_iterations {
        let g = obj.gradient(z.view(), zh.clone(), &photo);
        let tau = eps * eps / (2.0 * KAPPA * gamma);
        let mut trial = z.clone();
        trial.scaled_add(-tau, &g);
        let Iterate {
            photo: tp,
            zh: th,
            energy: mut te,
        } = obj.evaluate(&trial, rho);
        if te.total > energy.total {
            gamma *= 2.0;
            if gamma > 1e12 * params.gamma {
                break;
            }
            continue;
        }
        iteration += 1;
        // E_int of the auxiliary gradients: (p, q)⁽ⁿ⁺¹⁾ − ∇z⁽ⁿ⁾ = τ·(κ/ε²)… expressed per pixel as
        // the squared size of the z-update in slope units, Σ(τ·∂E/∂z/ε)².
        te.integrability = ops::dot(g.view(), g.view()) * (tau / eps) * (tau / eps);
        let gain = (energy.total - te.total) / energy.total.max(f64::MIN_POSITIVE);
        (*z, photo, zh, energy) = (trial, tp, th, te);
        observe(&energy);
        log.push(IterationRecord {
            iteration,
            energy,
            inner: 0,
            max_step: tau * ops::max_abs(g.view()),
        });
        if gain < params.tolerance {
            break;
        }
    }
    log
}
