//! Forward-mode dual numbers: a value with `N` first partial derivatives.
//!
//! Used to differentiate the Hapke roughness correction through μ0 and μ (docs/photometry.md:
//! "forward-mode dual numbers are the least error-prone way") and the H function through w.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// `v + Σ d[k]·εₖ` with εₖ² = εₖεⱼ = 0.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dual<const N: usize> {
    /// The value.
    pub v: f64,
    /// ∂v/∂xₖ.
    pub d: [f64; N],
}

impl<const N: usize> Dual<N> {
    /// A constant: all partials zero.
    pub fn constant(v: f64) -> Self {
        Self { v, d: [0.0; N] }
    }

    /// The `k`-th independent variable with value `v`.
    pub fn var(v: f64, k: usize) -> Self {
        let mut d = [0.0; N];
        d[k] = 1.0;
        Self { v, d }
    }

    /// Chain rule: f(self) with f(v) = `fv`, f'(v) = `dfv`.
    fn chain(self, fv: f64, dfv: f64) -> Self {
        let mut d = self.d;
        for x in &mut d {
            *x *= dfv;
        }
        Self { v: fv, d }
    }

    pub fn sqrt(self) -> Self {
        let s = self.v.sqrt();
        self.chain(s, 0.5 / s)
    }
    pub fn exp(self) -> Self {
        let e = self.v.exp();
        self.chain(e, e)
    }
    pub fn ln(self) -> Self {
        self.chain(self.v.ln(), 1.0 / self.v)
    }
    pub fn tan(self) -> Self {
        let t = self.v.tan();
        self.chain(t, 1.0 + t * t)
    }
    pub fn acos(self) -> Self {
        self.chain(self.v.acos(), -1.0 / (1.0 - self.v * self.v).sqrt())
    }
    pub fn recip(self) -> Self {
        self.chain(1.0 / self.v, -1.0 / (self.v * self.v))
    }
    /// `self^e` for a constant exponent.
    pub fn powf(self, e: f64) -> Self {
        self.chain(self.v.powf(e), e * self.v.powf(e - 1.0))
    }
    /// Clamp the value to `[lo, hi]`; outside the range the partials become zero.
    pub fn clamp(self, lo: f64, hi: f64) -> Self {
        if self.v < lo {
            Self::constant(lo)
        } else if self.v > hi {
            Self::constant(hi)
        } else {
            self
        }
    }
}

impl<const N: usize> Add for Dual<N> {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        let mut d = self.d;
        for (x, y) in d.iter_mut().zip(o.d) {
            *x += y;
        }
        Self { v: self.v + o.v, d }
    }
}
impl<const N: usize> Sub for Dual<N> {
    type Output = Self;
    fn sub(self, o: Self) -> Self {
        self + (-o)
    }
}
impl<const N: usize> Neg for Dual<N> {
    type Output = Self;
    fn neg(self) -> Self {
        self.chain(-self.v, -1.0)
    }
}
impl<const N: usize> Mul for Dual<N> {
    type Output = Self;
    fn mul(self, o: Self) -> Self {
        let mut d = [0.0; N];
        for (k, x) in d.iter_mut().enumerate() {
            *x = self.d[k] * o.v + self.v * o.d[k];
        }
        Self { v: self.v * o.v, d }
    }
}
impl<const N: usize> Div for Dual<N> {
    type Output = Self;
    fn div(self, o: Self) -> Self {
        let inv = 1.0 / o.v;
        let mut d = [0.0; N];
        for (k, x) in d.iter_mut().enumerate() {
            *x = (self.d[k] - self.v * inv * o.d[k]) * inv;
        }
        Self { v: self.v * inv, d }
    }
}
impl<const N: usize> Add<f64> for Dual<N> {
    type Output = Self;
    fn add(self, o: f64) -> Self {
        Self {
            v: self.v + o,
            d: self.d,
        }
    }
}
impl<const N: usize> Sub<f64> for Dual<N> {
    type Output = Self;
    fn sub(self, o: f64) -> Self {
        Self {
            v: self.v - o,
            d: self.d,
        }
    }
}
impl<const N: usize> Mul<f64> for Dual<N> {
    type Output = Self;
    fn mul(self, o: f64) -> Self {
        self.chain(self.v * o, o)
    }
}
impl<const N: usize> Div<f64> for Dual<N> {
    type Output = Self;
    fn div(self, o: f64) -> Self {
        self.chain(self.v / o, 1.0 / o)
    }
}
impl<const N: usize> Add<Dual<N>> for f64 {
    type Output = Dual<N>;
    fn add(self, o: Dual<N>) -> Dual<N> {
        o + self
    }
}
impl<const N: usize> Sub<Dual<N>> for f64 {
    type Output = Dual<N>;
    fn sub(self, o: Dual<N>) -> Dual<N> {
        (-o) + self
    }
}
impl<const N: usize> Mul<Dual<N>> for f64 {
    type Output = Dual<N>;
    fn mul(self, o: Dual<N>) -> Dual<N> {
        o * self
    }
}
impl<const N: usize> Div<Dual<N>> for f64 {
    type Output = Dual<N>;
    fn div(self, o: Dual<N>) -> Dual<N> {
        Dual::constant(self) / o
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn derivatives_match_central_differences() {
        let f =
            |x: Dual<1>| ((x * 2.0).exp() / (1.0 + x.tan()) - x.sqrt().ln() * x.acos()).powf(1.3);
        for &x0 in &[0.1, 0.3, 0.7] {
            let a = f(Dual::var(x0, 0));
            let h = 1e-6;
            let num = (f(Dual::constant(x0 + h)).v - f(Dual::constant(x0 - h)).v) / (2.0 * h);
            assert!(
                (a.d[0] - num).abs() < 1e-7 * num.abs().max(1.0),
                "{} vs {num}",
                a.d[0]
            );
        }
    }
}
