//! Every bad input gets its typed error, with the state untouched, and nothing panics.

use mfc::{
    AdrcParams, Channel, ChannelConfig, ControllerKind, EstimatorConfig, EstimatorKind,
    IntelligentController, IntelligentParams, LawConfig, MfcError, MimoController, Order,
    OutputMapConfig, PidParams, Reference,
};
use proptest::prelude::*;

fn warmed() -> Channel {
    let mut ch: Channel = Channel::new(&ChannelConfig::default()).unwrap();
    for k in 0..20 {
        ch.step(k as f64 * 0.01, 0.1 * k as f64, &Reference::constant(1.0))
            .unwrap();
    }
    ch
}

fn snapshot(ch: &Channel) -> String {
    format!("{ch:?}")
}

#[test]
fn bad_measurements_and_times_are_refused_state_untouched() {
    let mut ch = warmed();
    let before = snapshot(&ch);
    let r = Reference::constant(1.0);
    let cases: [(f64, f64, Reference); 7] = [
        (0.5, f64::NAN, r),
        (0.5, f64::INFINITY, r),
        (0.5, f64::NEG_INFINITY, r),
        (f64::NAN, 0.0, r),
        (0.19, 0.0, r), // same time as the last sample
        (0.05, 0.0, r), // back in time
        (
            0.5,
            0.0,
            Reference {
                y: 0.0,
                dy: f64::NAN,
                ddy: 0.0,
            },
        ),
    ];
    for (t, y, r) in cases {
        let err = ch.step(t, y, &r).unwrap_err();
        match err {
            MfcError::NonFinite { .. } | MfcError::TimeNotAdvancing { .. } => {}
            other => panic!("unexpected {other}"),
        }
        assert_eq!(snapshot(&ch), before, "state changed after {err}");
    }
    assert!(matches!(
        ch.step(0.19, 0.0, &r),
        Err(MfcError::TimeNotAdvancing { previous, current }) if previous == 0.19 && current == 0.19
    ));
    assert!(ch.report_applied(f64::NAN).is_err());
    assert_eq!(snapshot(&ch), before);
}

/// An intelligent controller from `p` and `e`, or why not.
fn make(p: IntelligentParams, e: EstimatorConfig) -> Result<(), MfcError> {
    IntelligentController::<256>::new(p, e).map(|_| ())
}

#[test]
fn bad_gains_are_refused() {
    let params = IntelligentParams::default();
    let est = EstimatorConfig::default();
    assert!(matches!(
        make(
            IntelligentParams {
                alpha: 0.0,
                ..params
            },
            est
        ),
        Err(MfcError::InvalidAlpha { .. })
    ));
    assert!(matches!(
        make(
            IntelligentParams {
                alpha: f64::NAN,
                ..params
            },
            est
        ),
        Err(MfcError::InvalidAlpha { .. })
    ));
    assert!(matches!(
        make(IntelligentParams { kp: -1.0, ..params }, est),
        Err(MfcError::InvalidParameter { name: "kp", .. })
    ));
    assert!(matches!(
        make(
            IntelligentParams {
                ki: f64::INFINITY,
                ..params
            },
            est
        ),
        Err(MfcError::InvalidParameter { name: "ki", .. })
    ));
    assert!(matches!(
        make(
            IntelligentParams {
                kd: f64::NAN,
                ..params
            },
            est
        ),
        Err(MfcError::InvalidParameter { name: "kd", .. })
    ));
}

#[test]
fn bad_orders_windows_and_estimators_are_refused() {
    let params = IntelligentParams::default();
    let est = EstimatorConfig::default();
    assert!(matches!(
        make(
            IntelligentParams {
                kind: ControllerKind::PD,
                ..params
            },
            est
        ),
        Err(MfcError::IncompatibleOrder {
            kind: ControllerKind::PD,
            order: Order::One
        })
    ));
    assert!(matches!(
        make(
            IntelligentParams {
                order: Order::Two,
                ..params
            },
            est
        ),
        Err(MfcError::IncompatibleOrder {
            kind: ControllerKind::P,
            order: Order::Two
        })
    ));
    assert!(matches!(
        make(params, EstimatorConfig { window: 0, ..est }),
        Err(MfcError::WindowTooShort { len: 0, min: 1, .. })
    ));
    let pd2 = IntelligentParams {
        kind: ControllerKind::PD,
        order: Order::Two,
        ..params
    };
    assert!(matches!(
        make(pd2, EstimatorConfig { window: 1, ..est }),
        Err(MfcError::WindowTooShort { len: 1, min: 2, .. })
    ));
    assert!(matches!(
        make(params, EstimatorConfig { window: 257, ..est }),
        Err(MfcError::WindowTooLong { .. })
    ));
    assert!(matches!(
        make(
            pd2,
            EstimatorConfig {
                kind: EstimatorKind::ClosedLoop,
                ..est
            }
        ),
        Err(MfcError::UnsupportedEstimatorOrder)
    ));
    assert!(matches!(
        make(
            params,
            EstimatorConfig {
                kind: EstimatorKind::LowPass { time_constant: 0.0 },
                ..est
            }
        ),
        Err(MfcError::InvalidParameter {
            name: "time_constant",
            ..
        })
    ));
}

#[test]
fn bad_maps_and_baselines_are_refused() {
    assert!(matches!(
        mfc::OutputMap::new(OutputMapConfig {
            min: 1.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidParameter { .. })
    ));
    assert!(matches!(
        mfc::OutputMap::new(OutputMapConfig {
            dead_zone: -1.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidParameter {
            name: "dead_zone",
            ..
        })
    ));
    assert!(matches!(
        mfc::Pid::new(PidParams {
            kp: 1.0,
            ki: -1.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidParameter { .. })
    ));
    assert!(matches!(
        mfc::Pid::new(PidParams {
            out_min: 1.0,
            out_max: 0.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidParameter { .. })
    ));
    assert!(matches!(
        mfc::Adrc::new(AdrcParams {
            b0: 0.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidAlpha { .. })
    ));
    assert!(matches!(
        mfc::Adrc::new(AdrcParams {
            wo: -3.0,
            ..Default::default()
        }),
        Err(MfcError::InvalidParameter { name: "wo", .. })
    ));
}

#[test]
fn refused_reconfiguration_changes_nothing() {
    let mut ch = warmed();
    let before = snapshot(&ch);
    let bad = ChannelConfig {
        law: LawConfig::Intelligent {
            params: IntelligentParams {
                alpha: 0.0,
                ..Default::default()
            },
            estimator: EstimatorConfig::default(),
        },
        output: OutputMapConfig {
            max: 5.0,
            ..Default::default()
        },
    };
    assert!(ch.reconfigure(&bad).is_err());
    let bad_map = ChannelConfig {
        output: OutputMapConfig {
            max: -5.0,
            ..Default::default()
        },
        ..ChannelConfig::default()
    };
    assert!(ch.reconfigure(&bad_map).is_err());
    assert_eq!(snapshot(&ch), before);
}

#[test]
fn mimo_checks_every_channel_before_moving_any() {
    let mut mimo: MimoController = MimoController::new(&[ChannelConfig::default(); 2]).unwrap();
    let r = [Reference::constant(0.0); 2];
    let mut out = [mfc::ChannelOutput::default(); 2];
    mimo.step(0.0, &[0.0, 0.0], &r, &mut out).unwrap();
    let before = format!("{mimo:?}");
    assert!(matches!(
        mimo.step(0.01, &[0.0, f64::NAN], &r, &mut out),
        Err(MfcError::NonFinite { .. })
    ));
    assert!(matches!(
        mimo.step(0.01, &[0.0], &r, &mut out),
        Err(MfcError::DimensionMismatch {
            expected: 2,
            got: 1
        })
    ));
    let bad = ChannelConfig {
        law: LawConfig::Pid {
            params: PidParams {
                kp: f64::NAN,
                ..Default::default()
            },
        },
        ..ChannelConfig::default()
    };
    assert!(mimo.reconfigure(&[ChannelConfig::default(), bad]).is_err());
    assert_eq!(format!("{mimo:?}"), before);
}

proptest! {
    /// No sequence of arbitrary floats, finite or not, makes a channel panic; every output
    /// it gives is finite.
    #[test]
    fn arbitrary_input_never_panics(
        law in 0usize..3,
        samples in proptest::collection::vec((any::<f64>(), any::<f64>(), any::<f64>(), any::<f64>()), 1..200),
    ) {
        let law = match law {
            0 => LawConfig::default(),
            1 => LawConfig::Pid { params: PidParams::default() },
            _ => LawConfig::Adrc { params: AdrcParams::default() },
        };
        let mut ch: Channel = Channel::new(&ChannelConfig { law, output: OutputMapConfig::AERO }).unwrap();
        for (t, y, r, v) in samples {
            if let Ok(o) = ch.step(t, y, &Reference::constant(r)) {
                prop_assert!(o.v.is_finite());
            }
            let _ = ch.report_applied(v);
        }
    }
}
