//! A restored snapshot continues exactly where the original would have.
#![cfg(feature = "snapshot")]

use mfc::snapshot::{from_bytes, to_bytes};
use mfc::{
    AdrcParams, Channel, ChannelConfig, ChannelOutput, ControllerKind, LawConfig, MimoController,
    Order, OutputMapConfig, PidParams, Reference, DEFAULT_CAPACITY,
};
use proptest::prelude::*;

fn mimo() -> MimoController {
    let law = |l| ChannelConfig {
        law: l,
        output: OutputMapConfig::AERO,
    };
    MimoController::new(&[
        law(LawConfig::intelligent(
            ControllerKind::PI,
            Order::One,
            2.0,
            [3.0, 1.0, 0.0],
            17,
        )),
        // With the hold filter taking over at 4 s, after the snapshot: the restored
        // controller must know how long its reference has rested.
        law(
            match LawConfig::intelligent(ControllerKind::PD, Order::Two, 0.1, [9.0, 0.0, 3.0], 20) {
                LawConfig::Intelligent { params, estimator } => LawConfig::Intelligent {
                    params: mfc::IntelligentParams {
                        estimate_filter: 0.05,
                        hold_estimate_filter: 0.3,
                        hold_after: 4.0,
                        feedforward_within_range: true,
                        ..params
                    },
                    estimator,
                },
                other => other,
            },
        ),
        // A rate limit: the map keeps the last output, part of the state.
        ChannelConfig {
            law: LawConfig::Pid {
                params: PidParams {
                    kp: 2.0,
                    ki: 1.0,
                    kd: 0.1,
                    ..Default::default()
                },
            },
            output: OutputMapConfig {
                rate_limit: Some(200.0),
                ..OutputMapConfig::AERO
            },
        },
        law(LawConfig::Adrc {
            params: AdrcParams::default(),
        }),
    ])
    .unwrap()
}

fn drive(m: &mut MimoController, from: usize, to: usize) -> Vec<[f64; 4]> {
    let mut out = [ChannelOutput::default(); 4];
    (from..to)
        .map(|k| {
            let t = k as f64 * 0.01;
            let y = [
                (t * 0.7).sin(),
                (t * 1.3).cos() * 0.2,
                t * 0.01,
                -0.3 + (t * 2.1).sin() * 0.1,
            ];
            let r = [Reference::constant(0.1); 4];
            m.step(t, &y, &r, &mut out).unwrap();
            [out[0].v, out[1].v, out[2].v, out[3].v]
        })
        .collect()
}

#[test]
fn restored_state_continues_bit_for_bit() {
    let mut a = mimo();
    drive(&mut a, 0, 300);
    let bytes = to_bytes(&a).unwrap();
    let mut b: MimoController = from_bytes(&bytes).unwrap();
    let (va, vb) = (drive(&mut a, 300, 600), drive(&mut b, 300, 600));
    assert_eq!(va, vb);
    assert!(bytes.len() < 64 * 1024, "{} bytes", bytes.len());
}

/// A law whose model's order changed live (an iPI of order one becoming an iPD of order
/// two, the same estimator: its running sums then serve order two) restores and continues
/// bit for bit, whether the change is still pending at the snapshot or has been made.
#[test]
fn an_order_changed_live_restores_bit_for_bit() {
    let ipd = LawConfig::intelligent(ControllerKind::PD, Order::Two, 0.5, [9.0, 0.0, 3.0], 17);
    for steps_after in [0, 1, 40] {
        let mut a = mimo();
        drive(&mut a, 0, 150);
        let mut configs: Vec<ChannelConfig> = a.channels().iter().map(|c| c.config()).collect();
        configs[0].law = ipd;
        a.reconfigure(&configs).unwrap();
        drive(&mut a, 150, 150 + steps_after);
        let mut b: MimoController = from_bytes(&to_bytes(&a).unwrap()).unwrap();
        let from = 150 + steps_after;
        let (va, vb) = (
            drive(&mut a, from, from + 300),
            drive(&mut b, from, from + 300),
        );
        assert_eq!(va, vb, "{steps_after} steps after the change");
        assert!(va.iter().all(|v| v[0].is_finite()));
    }
}

/// What a decoded controller must be (the decoder's promise, `mfc::snapshot`): each
/// channel's configuration is one the constructor accepts, its output map and (for the
/// intelligent laws, the ones whose parameters a channel shows) its law run that
/// configuration, and stepping it gives finite commands or an error: never a panic, never
/// a NaN. (Not that the commands lie inside the map's limits: a rate-limited map's memory
/// outside them, as a plant's report can leave it too, drags the output with it; the
/// service's final envelope check is what clips that.) Returns how many steps produced
/// commands.
fn assert_valid(m: &mut MimoController) -> usize {
    for (i, c) in m.channels().iter().enumerate() {
        let cfg = c.config();
        assert!(
            Channel::<DEFAULT_CAPACITY>::new(&cfg).is_ok(),
            "channel {i}: {cfg:?}"
        );
        assert_eq!(c.output_map().config(), &cfg.output, "channel {i}");
        if let (Some(l), LawConfig::Intelligent { params, estimator }) = (c.intelligent(), cfg.law)
        {
            assert_eq!(l.params(), &params, "channel {i}");
            assert_eq!(l.estimator().config(), &estimator, "channel {i}");
        }
    }
    let n = m.len();
    let mut out = vec![ChannelOutput::default(); n];
    let y = vec![0.1; n];
    let r = vec![Reference::constant(0.2); n];
    let mut stepped = 0;
    // The snapshot was taken after t = 0.49 s: carry on from there.
    for k in 50..60 {
        if m.step(k as f64 * 0.01, &y, &r, &mut out).is_ok() {
            stepped += 1;
            assert!(out.iter().all(|o| o.v.is_finite()), "{out:?}");
        }
    }
    stepped
}

fn snapshot() -> Vec<u8> {
    let mut m = mimo();
    drive(&mut m, 0, 50);
    to_bytes(&m).unwrap()
}

/// Every single-byte corruption of a snapshot (three patterns at every position) is
/// refused or gives a valid controller. Before the decoder checked the channels, some of
/// these restored laws and maps that differed from their channel's configuration, among
/// them PIDs with inverted limits, which panicked at their first step.
#[test]
fn every_corrupted_byte_is_refused_or_valid() {
    let bytes = snapshot();
    let (mut refused, mut decoded, mut stepped) = (0, 0, 0);
    for i in 0..bytes.len() {
        for x in [0x01u8, 0x80, 0xff] {
            let mut b = bytes.clone();
            b[i] ^= x;
            match from_bytes::<MimoController>(&b) {
                Err(_) => refused += 1,
                Ok(mut m) => {
                    decoded += 1;
                    stepped += assert_valid(&mut m);
                }
            }
        }
    }
    eprintln!("{refused} refused, {decoded} decoded ({stepped} steps with commands)");
    // Both outcomes occur (a flipped bit of a measurement is a valid state), and the
    // decoded ones were stepped: the test judged something.
    assert!(refused > 0 && decoded > 0 && stepped > 0);
}

proptest! {
    /// A truncated snapshot is refused; a corrupted one (several bytes changed, truncated
    /// or whole) is refused or is a valid controller; never a panic.
    #[test]
    fn corrupted_snapshots_are_refused(
        cut in proptest::option::of(any::<usize>()),
        flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8),
    ) {
        let mut bytes = snapshot();
        if let Some(cut) = cut {
            bytes.truncate(cut % bytes.len());
            prop_assert!(from_bytes::<MimoController>(&bytes).is_err(), "truncated to {}", bytes.len());
        }
        for (i, x) in flips {
            if !bytes.is_empty() {
                let n = bytes.len();
                bytes[i % n] ^= x;
            }
        }
        if let Ok(mut restored) = from_bytes::<MimoController>(&bytes) {
            assert_valid(&mut restored);
        }
    }
}
