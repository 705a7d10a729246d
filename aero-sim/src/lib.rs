//! A simulator of the Quanser AERO in half-quadrotor mode, as faithful as public data allow.
//!
//! States: pitch `θ`, `θ'`, yaw (azimuth) `ψ`, `ψ'`, and one first-order rotor lag per motor.
//!
//! ```text
//! Jp θ'' = Kpp Tp + Kpy Ty - Dp θ' - Ksp sin θ - m g r cos θ
//! Jy ψ'' = Kyp Tp + Kyy Ty - Dy ψ'
//! τr T'  = φ(V) - T                    (per motor)
//! ```
//!
//! `φ` is the measured voltage-to-torque curve with its soft dead zone, expressed in
//! "equivalent volts" (`φ(23.53 V) = 23.53`) so that the coupling gains keep the units of the
//! linear model (N m/V). `m g r cos θ` is the optional added mass (4 g at 0.165 m in the
//! paper's scenarios 3 and 4), which also adds `m r²` to both inertias.
//!
//! Motor voltages are `M v` (the mixing matrix; see [`AeroParams::mixing`] for the default),
//! saturated at ±24 V. Integration is RK4 at 1 kHz
//! or finer. The measurements are what the rig's encoders give: angles quantised to 2048
//! (pitch) and 4096 (yaw) counts per revolution, optional seeded noise, and the yaw velocity
//! as the backward difference of the quantised yaw angle over the sample period, in rad/ms
//! as in the paper.

use serde::{Deserialize, Serialize};

pub mod driver;
pub mod rng;

use crate::rng::Rng;

/// Gravity (m/s²).
const G: f64 = 9.81;

/// Voltage-to-torque curve of one rotor.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TorqueCurve {
    /// The measured half-quadrotor curve (soft dead zone below about 10 V).
    #[default]
    Measured,
    /// Torque proportional to voltage (the linear model), for checks.
    Linear,
}

/// Measured pitch torque (N m) against voltage, half-quadrotor mode (odd-symmetric).
const MEASURED: [(f64, f64); 9] = [
    (0.0, 0.0),
    (7.29, 0.00358),
    (9.29, 0.00537),
    (10.21, 0.00716),
    (12.68, 0.01075),
    (14.37, 0.01433),
    (16.05, 0.01791),
    (20.11, 0.02866),
    (23.53, 0.03940),
];

impl TorqueCurve {
    /// `φ(V)` in equivalent volts: odd in `V`, interpolated linearly between the measured
    /// points, and beyond 23.53 V extended along the last segment.
    pub fn eval(self, v: f64) -> f64 {
        match self {
            TorqueCurve::Linear => v,
            TorqueCurve::Measured => {
                let (last_v, last_tau) = MEASURED[MEASURED.len() - 1];
                let scale = last_v / last_tau;
                let a = v.abs();
                let mut tau = 0.0;
                for w in MEASURED.windows(2) {
                    let ((v0, t0), (v1, t1)) = (w[0], w[1]);
                    if a <= v1 || v1 == last_v {
                        tau = t0 + (t1 - t0) * (a - v0) / (v1 - v0);
                        break;
                    }
                }
                v.signum() * tau * scale
            }
        }
    }
}

/// Physical parameters of the AERO. Every field has the documented default, so a plant file
/// only lists what differs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AeroParams {
    /// Pitch inertia Jp (kg m²). Default 0.0219 (AERO 2: 0.0232).
    pub jp: f64,
    /// Yaw inertia Jy (kg m²). Default 0.0220 (AERO 2: 0.0238).
    pub jy: f64,
    /// Pitch restoring stiffness Ksp (N m/rad), applied as `Ksp sin θ`. Default 0.0375.
    pub ksp: f64,
    /// Pitch viscous damping Dp (N m s/rad). Default 0.0071.
    pub dp: f64,
    /// Yaw viscous damping Dy (N m s/rad). Default 0.0220.
    pub dy: f64,
    /// Pitch motor on pitch, Kpp (N m/V). Default 0.0011.
    pub kpp: f64,
    /// Yaw motor on yaw, Kyy (N m/V). Default 0.0022.
    pub kyy: f64,
    /// Yaw motor on pitch, Kpy (N m/V). Default 0.0021.
    pub kpy: f64,
    /// Pitch motor on yaw, Kyp (N m/V). Default -0.0027.
    pub kyp: f64,
    /// Voltage-to-torque curve. Default: measured.
    pub torque_curve: TorqueCurve,
    /// Rotor (motor + propeller) lag time constant (s). Default 0.05 (range 0.03 to 0.15).
    pub rotor_time_constant: f64,
    /// Motor voltages = mixing · channel outputs; row 0 is the table's "yaw motor", row 1
    /// its "pitch motor" (in half-quadrotor mode, simply the two rotors).
    ///
    /// Default `[[0, 1], [-1, 0]]`: channel 1 (azimuth velocity) drives the rotor whose
    /// reaction torque dominates yaw (|Kyp| > Kyy), reversed so that a positive `u` speeds
    /// the azimuth up; channel 2 (pitch) drives the rotor whose torque dominates pitch
    /// (Kpy > Kpp). Each output is then mainly influenced by its own input, as the paper
    /// states. With the identity each output is dominated by the *other* input, and every
    /// per-channel iP of a grid over alpha, Kp and window fell into a coupled oscillation.
    pub mixing: [[f64; 2]; 2],
    /// Amplifier saturation (V): bounds each channel output and again each motor voltage
    /// after mixing. Default 24.
    pub max_voltage: f64,
    /// Pitch encoder counts per revolution (0: no quantisation). Default 2048.
    pub pitch_counts: u32,
    /// Yaw encoder counts per revolution (0: no quantisation). Default 4096.
    pub yaw_counts: u32,
    /// Standard deviation of Gaussian noise added to the measured pitch (rad). Default 0.
    pub pitch_noise: f64,
    /// Standard deviation of Gaussian noise added to the measured yaw angle (rad). Default 0.
    pub yaw_noise: f64,
    /// Added mass at the rotor arm (kg). Default 0; the paper's scenarios 3 and 4: 0.004.
    pub added_mass: f64,
    /// Distance of the added mass from the pivot (m). Default 0.165.
    pub added_mass_arm: f64,
    /// Mechanical pitch stop (rad): the arm stops dead there. Default 1.08 (about 62°).
    pub pitch_limit: f64,
    /// Largest internal integration step (s), at most 0.001. Default 0.001.
    pub integration_step: f64,
    /// Initial pitch (rad), within ±`pitch_limit`. Default 0.
    pub initial_pitch: f64,
}

impl Default for AeroParams {
    fn default() -> Self {
        Self {
            jp: 0.0219,
            jy: 0.0220,
            ksp: 0.0375,
            dp: 0.0071,
            dy: 0.0220,
            kpp: 0.0011,
            kyy: 0.0022,
            kpy: 0.0021,
            kyp: -0.0027,
            torque_curve: TorqueCurve::Measured,
            rotor_time_constant: 0.05,
            mixing: [[0.0, 1.0], [-1.0, 0.0]],
            max_voltage: 24.0,
            pitch_counts: 2048,
            yaw_counts: 4096,
            pitch_noise: 0.0,
            yaw_noise: 0.0,
            added_mass: 0.0,
            added_mass_arm: 0.165,
            pitch_limit: 1.08,
            integration_step: 0.001,
            initial_pitch: 0.0,
        }
    }
}

/// The paper's added mass (kg), scenarios 3 and 4: what the `added_mass` switch (scenario
/// file, `aero-sim` flag) puts in [`AeroParams::added_mass`].
pub const PAPER_ADDED_MASS: f64 = 0.004;

/// A parameter that is out of its physical range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("plant parameter `{field}` = {value}: {reason}")]
pub struct ParamError {
    /// The field's name as a plant file spells it (`jp`, `mixing`, ...).
    pub field: &'static str,
    /// The offending value; for `mixing`, the first non-finite entry.
    pub value: f64,
    /// What it must be.
    pub reason: &'static str,
}

impl AeroParams {
    /// Check every field against its physical range and report the first that is out;
    /// [`AeroSim::new`] refuses parameters that fail it.
    pub fn validate(&self) -> Result<(), ParamError> {
        let positive = [
            ("jp", self.jp),
            ("jy", self.jy),
            ("max_voltage", self.max_voltage),
            ("integration_step", self.integration_step),
            ("pitch_limit", self.pitch_limit),
        ];
        for (field, value) in positive {
            if !(value.is_finite() && value > 0.0) {
                return Err(ParamError {
                    field,
                    value,
                    reason: "must be finite and > 0",
                });
            }
        }
        let non_negative = [
            ("ksp", self.ksp),
            ("dp", self.dp),
            ("dy", self.dy),
            ("rotor_time_constant", self.rotor_time_constant),
            ("pitch_noise", self.pitch_noise),
            ("yaw_noise", self.yaw_noise),
            ("added_mass", self.added_mass),
            ("added_mass_arm", self.added_mass_arm),
        ];
        for (field, value) in non_negative {
            if !(value.is_finite() && value >= 0.0) {
                return Err(ParamError {
                    field,
                    value,
                    reason: "must be finite and >= 0",
                });
            }
        }
        let finite = [
            ("kpp", self.kpp),
            ("kyy", self.kyy),
            ("kpy", self.kpy),
            ("kyp", self.kyp),
            ("initial_pitch", self.initial_pitch),
        ];
        for (field, value) in finite
            .into_iter()
            .chain(self.mixing.iter().flatten().map(|v| ("mixing", *v)))
        {
            if !value.is_finite() {
                return Err(ParamError {
                    field,
                    value,
                    reason: "must be finite",
                });
            }
        }
        if self.integration_step > 0.001 {
            return Err(ParamError {
                field: "integration_step",
                value: self.integration_step,
                reason: "must be at most 0.001 s (1 kHz)",
            });
        }
        if self.initial_pitch.abs() > self.pitch_limit {
            return Err(ParamError {
                field: "initial_pitch",
                value: self.initial_pitch,
                reason: "must lie within the pitch limit",
            });
        }
        Ok(())
    }
}

/// The true (unmeasured) state of the rig.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct AeroState {
    /// Pitch θ (rad).
    pub pitch: f64,
    /// Pitch rate θ' (rad/s).
    pub pitch_rate: f64,
    /// Yaw ψ (rad).
    pub yaw: f64,
    /// Yaw rate ψ' (rad/s).
    pub yaw_rate: f64,
    /// Rotor torque states (equivalent volts): yaw motor, pitch motor.
    pub rotor: [f64; 2],
}

/// The simulated AERO.
#[derive(Debug, Clone)]
pub struct AeroSim {
    p: AeroParams,
    /// The true state, which [`AeroSim::measure`] quantises and adds noise to.
    x: AeroState,
    /// Saturated motor voltages being applied.
    motors: [f64; 2],
    /// Channel outputs being applied (after saturation).
    applied: [f64; 2],
    /// Simulated time (s), advanced only by [`AeroSim::advance`].
    t: f64,
    /// Measurement noise, seeded so that a run replays.
    rng: Rng,
    /// Last yaw reading (time, quantised angle) and the rate derived from it (rad/s).
    last_yaw: Option<(f64, f64)>,
    last_rate: f64,
    /// The same from the true yaw, for [`AeroSim::truth`].
    last_true_yaw: f64,
    last_true_rate: f64,
    /// Arrivals of the pitch arm at its stop.
    stop_hits: usize,
    /// Whether the arm is at its stop now, so that resting there counts as one hit.
    at_stop: bool,
}

/// Number of outputs and inputs of the AERO.
pub const CHANNELS: usize = 2;
/// Names of the outputs, in the order [`AeroSim::measure`] returns them.
pub const CHANNEL_NAMES: [&str; 2] = ["azimuth_velocity", "pitch"];
/// Units of the outputs: the azimuth velocity is in rad/ms, as in the paper, not rad/s.
pub const CHANNEL_UNITS: [&str; 2] = ["rad/ms", "rad"];

impl AeroSim {
    /// A rig at rest (at `initial_pitch`), rotors stopped, noise seeded by `seed`.
    pub fn new(params: AeroParams, seed: u64) -> Result<Self, ParamError> {
        params.validate()?;
        let x = AeroState {
            pitch: params.initial_pitch,
            ..Default::default()
        };
        Ok(Self {
            p: params,
            x,
            motors: [0.0; 2],
            applied: [0.0; 2],
            t: 0.0,
            rng: Rng::new(seed),
            last_yaw: None,
            last_rate: 0.0,
            last_true_yaw: 0.0,
            last_true_rate: 0.0,
            stop_hits: 0,
            at_stop: false,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &AeroParams {
        &self.p
    }

    /// The true state, unquantised and noise-free (for checks: a controller only ever sees
    /// [`AeroSim::measure`]).
    pub fn state(&self) -> AeroState {
        self.x
    }

    /// How many times the pitch arm has hit its mechanical stop; resting against it counts
    /// once. Reported by the plant agent as the plant's limit hits.
    pub fn stop_hits(&self) -> usize {
        self.stop_hits
    }

    /// Simulated time (s).
    pub fn time(&self) -> f64 {
        self.t
    }

    fn quantise(angle: f64, counts: u32) -> f64 {
        if counts == 0 {
            return angle;
        }
        let step = std::f64::consts::TAU / f64::from(counts);
        (angle / step).round() * step
    }

    /// Read the sensors now: `[azimuth velocity (rad/ms), pitch (rad)]`. The first reading
    /// reports a velocity of 0 (no earlier angle to difference against).
    pub fn measure(&mut self) -> [f64; 2] {
        let mut pitch = Self::quantise(self.x.pitch, self.p.pitch_counts);
        let mut yaw = Self::quantise(self.x.yaw, self.p.yaw_counts);
        if self.p.pitch_noise > 0.0 {
            pitch += self.p.pitch_noise * self.rng.normal();
        }
        if self.p.yaw_noise > 0.0 {
            yaw += self.p.yaw_noise * self.rng.normal();
        }
        match self.last_yaw {
            // A second reading at the same instant repeats the last derived rate.
            Some((t0, _)) if self.t <= t0 => {}
            Some((t0, y0)) => {
                self.last_rate = (yaw - y0) / (self.t - t0);
                self.last_true_rate = (self.x.yaw - self.last_true_yaw) / (self.t - t0);
                self.last_yaw = Some((self.t, yaw));
                self.last_true_yaw = self.x.yaw;
            }
            None => {
                self.last_yaw = Some((self.t, yaw));
                self.last_true_yaw = self.x.yaw;
            }
        }
        [self.last_rate / 1000.0, pitch]
    }

    /// What the last [`AeroSim::measure`] would have read with perfect sensors: the true
    /// pitch, and the true yaw's rate over the same interval (rad/ms). A benchmark judges
    /// what the plant did on this, so that a noisier or coarser sensor is not scored as
    /// tracking error the controller could never remove.
    pub fn truth(&self) -> [f64; 2] {
        [self.last_true_rate / 1000.0, self.x.pitch]
    }

    /// Apply the channel outputs `v` from now on (saturated at ±max_voltage, a non-finite
    /// value read as 0); returns what was applied, in channel terms.
    pub fn apply(&mut self, v: [f64; 2]) -> [f64; 2] {
        let vmax = self.p.max_voltage;
        let sat = |x: f64| {
            if x.is_finite() {
                x.clamp(-vmax, vmax)
            } else {
                0.0
            }
        };
        let v = [sat(v[0]), sat(v[1])];
        let m = self.p.mixing;
        self.motors = [
            sat(m[0][0] * v[0] + m[0][1] * v[1]),
            sat(m[1][0] * v[0] + m[1][1] * v[1]),
        ];
        self.applied = v;
        v
    }

    /// What is being applied, in channel terms.
    pub fn applied(&self) -> [f64; 2] {
        self.applied
    }

    /// Advance the simulation by `dt` seconds with the applied voltages held, in equal RK4
    /// steps no longer than `integration_step`. A `dt` that is not finite and > 0 does
    /// nothing.
    pub fn advance(&mut self, dt: f64) {
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        let n = (dt / self.p.integration_step).ceil().max(1.0) as usize;
        let h = dt / n as f64;
        for _ in 0..n {
            self.rk4(h);
        }
        self.t += dt;
    }

    fn rk4(&mut self, h: f64) {
        let x = to_vec(&self.x);
        let k1 = self.deriv(&x);
        let k2 = self.deriv(&axpy(&x, &k1, h / 2.0));
        let k3 = self.deriv(&axpy(&x, &k2, h / 2.0));
        let k4 = self.deriv(&axpy(&x, &k3, h));
        let mut next = x;
        for i in 0..6 {
            next[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
        }
        if next[0].abs() > self.p.pitch_limit {
            // The arm hits its stop and stays there until pushed back.
            next[0] = next[0].clamp(-self.p.pitch_limit, self.p.pitch_limit);
            next[1] = 0.0;
            if !self.at_stop {
                self.stop_hits += 1;
            }
            self.at_stop = true;
        } else if next[0].abs() < self.p.pitch_limit {
            self.at_stop = false;
        }
        self.x = from_vec(&next);
    }

    fn deriv(&self, x: &[f64; 6]) -> [f64; 6] {
        let p = &self.p;
        let [theta, theta_d, _psi, psi_d, rotor_y, rotor_p] = *x;
        let lag = p.rotor_time_constant > 0.0;
        let curve = |v: f64| p.torque_curve.eval(v);
        // Without a lag, the rotors follow the voltage at once.
        let (ty, tp) = if lag {
            (rotor_y, rotor_p)
        } else {
            (curve(self.motors[0]), curve(self.motors[1]))
        };
        let m = p.added_mass;
        let r = p.added_mass_arm;
        let jp = p.jp + m * r * r;
        let jy = p.jy + m * r * r * theta.cos().powi(2);
        let tau_p = p.kpp * tp + p.kpy * ty
            - p.dp * theta_d
            - p.ksp * theta.sin()
            - m * G * r * theta.cos();
        let tau_y = p.kyp * tp + p.kyy * ty - p.dy * psi_d;
        let (ty_d, tp_d) = if lag {
            (
                (curve(self.motors[0]) - ty) / p.rotor_time_constant,
                (curve(self.motors[1]) - tp) / p.rotor_time_constant,
            )
        } else {
            (0.0, 0.0)
        };
        [theta_d, tau_p / jp, psi_d, tau_y / jy, ty_d, tp_d]
    }
}

fn to_vec(s: &AeroState) -> [f64; 6] {
    [
        s.pitch,
        s.pitch_rate,
        s.yaw,
        s.yaw_rate,
        s.rotor[0],
        s.rotor[1],
    ]
}

fn from_vec(x: &[f64; 6]) -> AeroState {
    AeroState {
        pitch: x[0],
        pitch_rate: x[1],
        yaw: x[2],
        yaw_rate: x[3],
        rotor: [x[4], x[5]],
    }
}

fn axpy(x: &[f64; 6], k: &[f64; 6], s: f64) -> [f64; 6] {
    let mut out = *x;
    for i in 0..6 {
        out[i] += s * k[i];
    }
    out
}
