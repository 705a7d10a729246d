//! Exact simulators of test plants under zero-order hold, shared by the integration tests.
#![allow(dead_code)]

/// Exact samples of the ultra-local model `y^(n) = F + alpha u` with `u` held between the
/// given sample times. Returns `(t, y, u_applied_over_previous_interval)` per sample.
pub fn ultra_local(
    order: u8,
    f: f64,
    alpha: f64,
    times: &[f64],
    inputs: &[f64],
    y0: f64,
    dy0: f64,
) -> Vec<(f64, f64, f64)> {
    let mut out = Vec::with_capacity(times.len());
    let (mut y, mut dy) = (y0, dy0);
    out.push((times[0], y, 0.0));
    for k in 1..times.len() {
        let h = times[k] - times[k - 1];
        let acc = f + alpha * inputs[k - 1];
        if order == 1 {
            y += h * acc;
        } else {
            y += h * dy + 0.5 * h * h * acc;
            dy += h * acc;
        }
        out.push((times[k], y, inputs[k - 1]));
    }
    out
}

/// A plant `x' = g(x, u)` integrated by RK4 with `sub` sub-steps per sample period.
pub struct Rk4Plant<const N: usize> {
    pub x: [f64; N],
    pub deriv: fn(&[f64; N], f64) -> [f64; N],
}

impl<const N: usize> Rk4Plant<N> {
    pub fn advance(&mut self, h: f64, u: f64, sub: usize) {
        let dt = h / sub as f64;
        for _ in 0..sub {
            let f = self.deriv;
            let k1 = f(&self.x, u);
            let k2 = f(&add(&self.x, &k1, dt / 2.0), u);
            let k3 = f(&add(&self.x, &k2, dt / 2.0), u);
            let k4 = f(&add(&self.x, &k3, dt), u);
            for i in 0..N {
                self.x[i] += dt / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
            }
        }
    }
}

fn add<const N: usize>(x: &[f64; N], k: &[f64; N], s: f64) -> [f64; N] {
    let mut out = *x;
    for i in 0..N {
        out[i] += s * k[i];
    }
    out
}

pub fn rms(e: &[f64]) -> f64 {
    (e.iter().map(|x| x * x).sum::<f64>() / e.len().max(1) as f64).sqrt()
}
