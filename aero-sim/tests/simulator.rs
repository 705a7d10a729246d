//! The AERO simulator conserves what it should and agrees with the linear model.

use aero_sim::{AeroParams, AeroSim, TorqueCurve};

fn ideal() -> AeroParams {
    AeroParams {
        pitch_counts: 0,
        yaw_counts: 0,
        ..AeroParams::default()
    }
}

#[test]
fn no_input_no_gravity_stays_at_rest() {
    let mut sim = AeroSim::new(AeroParams::default(), 7).unwrap();
    for _ in 0..1000 {
        let y = sim.measure();
        assert_eq!(y, [0.0, 0.0]);
        sim.apply([0.0, 0.0]);
        sim.advance(0.01);
    }
    let s = sim.state();
    assert_eq!(
        (s.pitch, s.pitch_rate, s.yaw, s.yaw_rate),
        (0.0, 0.0, 0.0, 0.0)
    );
}

/// Without damping or input, the pitch pendulum's energy and the yaw momentum are
/// conserved (RK4 at 1 kHz: drift below 1e-8 relative over 20 s).
#[test]
fn undamped_free_motion_conserves_energy_and_momentum() {
    let p = AeroParams {
        dp: 0.0,
        dy: 0.0,
        initial_pitch: 0.4,
        ..ideal()
    };
    let (jp, ksp, jy) = (p.jp, p.ksp, p.jy);
    let mut sim = AeroSim::new(p, 0).unwrap();
    // Spin the yaw up briefly, then coast.
    sim.apply([5.0, 0.0]);
    sim.advance(0.2);
    sim.apply([0.0, 0.0]);
    // Let the rotor lag die out (its torque decays as exp(-t/0.05)).
    sim.advance(2.0);
    let energy = |s: aero_sim::AeroState| {
        0.5 * jp * s.pitch_rate * s.pitch_rate + ksp * (1.0 - s.pitch.cos())
    };
    let (e0, m0) = (energy(sim.state()), jy * sim.state().yaw_rate);
    assert!(e0 > 1e-4 && m0.abs() > 1e-4);
    for _ in 0..2000 {
        sim.advance(0.01);
        let s = sim.state();
        assert!((energy(s) - e0).abs() <= 1e-8 * e0 + 1e-12, "energy drift");
        assert!(
            (jy * s.yaw_rate - m0).abs() <= 1e-9 * m0.abs() + 1e-12,
            "momentum"
        );
    }
}

/// A constant voltage gives the steady state of the linear model:
/// Dy ψ' = Kyy m0 + Kyp m1 and Ksp θ = Kpp m1 + Kpy m0 (small angle), m = mixing · v.
#[test]
fn constant_voltage_reaches_the_linear_steady_state() {
    let p = AeroParams {
        torque_curve: TorqueCurve::Linear,
        ..ideal()
    };
    let v = [1.5, -0.8];
    let m = [
        p.mixing[0][0] * v[0] + p.mixing[0][1] * v[1],
        p.mixing[1][0] * v[0] + p.mixing[1][1] * v[1],
    ];
    let yaw_rate = (p.kyy * m[0] + p.kyp * m[1]) / p.dy;
    let pitch_linear = (p.kpp * m[1] + p.kpy * m[0]) / p.ksp;
    let mut sim = AeroSim::new(p.clone(), 0).unwrap();
    sim.apply(v);
    sim.advance(150.0);
    let s = sim.state();
    assert!(
        (s.yaw_rate - yaw_rate).abs() < 1e-6 * yaw_rate.abs().max(1.0),
        "{} vs {yaw_rate}",
        s.yaw_rate
    );
    // The pendulum is sin θ; the linear model says θ: 0.3 % apart at this angle.
    assert!(pitch_linear.abs() > 0.02);
    assert!(
        (s.pitch - pitch_linear).abs() < 0.005 * pitch_linear.abs(),
        "{} vs {pitch_linear}",
        s.pitch
    );
    assert!(
        (s.pitch.sin() - pitch_linear).abs() < 1e-6,
        "exact with the sine"
    );
    // The measured azimuth velocity is in rad/ms.
    let y = sim.measure();
    sim.advance(0.01);
    let y2 = sim.measure();
    assert!((y2[0] - yaw_rate / 1000.0).abs() < 1e-8, "{:?} {:?}", y, y2);
}

#[test]
fn added_mass_sags_the_arm_as_predicted() {
    let p = AeroParams {
        added_mass: 0.004,
        ..ideal()
    };
    let torque = 0.004 * 9.81 * p.added_mass_arm;
    let mut sim = AeroSim::new(p.clone(), 0).unwrap();
    sim.advance(120.0);
    let theta = sim.state().pitch;
    // Ksp sin θ + m g r cos θ = 0.
    assert!((p.ksp * theta.sin() + torque * theta.cos()).abs() < 1e-7);
    assert!((-0.19..-0.15).contains(&theta), "{theta}");
}

#[test]
fn encoders_quantise_like_the_rig() {
    let mut sim = AeroSim::new(
        AeroParams {
            initial_pitch: 0.123_456,
            ..AeroParams::default()
        },
        0,
    )
    .unwrap();
    let step = std::f64::consts::TAU / 2048.0;
    let y = sim.measure();
    assert!(((y[1] / step) - (y[1] / step).round()).abs() < 1e-9);
    assert!((y[1] - 0.123_456).abs() <= step / 2.0);
    // Yaw velocity: backward difference of the 4096-count angle over the period.
    sim.apply([8.0, 0.0]);
    for _ in 0..300 {
        sim.advance(0.01);
        let y = sim.measure();
        let counts = y[0] * 1000.0 * 0.01 / (std::f64::consts::TAU / 4096.0);
        assert!((counts - counts.round()).abs() < 1e-6, "{counts}");
    }
}

#[test]
fn noise_is_seeded() {
    let p = AeroParams {
        pitch_noise: 0.01,
        yaw_noise: 0.001,
        ..AeroParams::default()
    };
    let run = |seed| {
        let mut sim = AeroSim::new(p.clone(), seed).unwrap();
        (0..50)
            .map(|_| {
                sim.advance(0.01);
                sim.measure()
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(run(3), run(3));
    assert_ne!(run(3), run(4));
}

#[test]
fn bad_parameters_are_refused() {
    for (p, field) in [
        (
            AeroParams {
                jp: 0.0,
                ..AeroParams::default()
            },
            "jp",
        ),
        (
            AeroParams {
                dy: -1.0,
                ..AeroParams::default()
            },
            "dy",
        ),
        (
            AeroParams {
                kpy: f64::NAN,
                ..AeroParams::default()
            },
            "kpy",
        ),
        (
            AeroParams {
                integration_step: 0.002,
                ..AeroParams::default()
            },
            "integration_step",
        ),
        (
            AeroParams {
                initial_pitch: 2.0,
                ..AeroParams::default()
            },
            "initial_pitch",
        ),
        (
            AeroParams {
                mixing: [[f64::INFINITY, 0.0], [0.0, 1.0]],
                ..AeroParams::default()
            },
            "mixing",
        ),
    ] {
        let e = AeroSim::new(p, 0).unwrap_err();
        assert_eq!(e.field, field);
    }
}

/// The shipped plant file is the defaults written out, nothing more.
#[test]
fn shipped_plant_file_is_the_defaults() {
    let text = include_str!("../../plants/aero/plant.toml");
    let p: AeroParams = toml::from_str(text).unwrap();
    assert_eq!(p, AeroParams::default());
}
