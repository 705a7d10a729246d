//! A restored snapshot continues exactly where the original would have.
#![cfg(feature = "snapshot")]

use mfc::snapshot::{from_bytes, to_bytes};
use mfc::{
    AdrcParams, ChannelConfig, ChannelOutput, ControllerKind, LawConfig, MimoController, Order,
    OutputMapConfig, PidParams, Reference,
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
                        ..params
                    },
                    estimator,
                },
                other => other,
            },
        ),
        law(LawConfig::Pid {
            params: PidParams {
                kp: 2.0,
                ki: 1.0,
                kd: 0.1,
                ..Default::default()
            },
        }),
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

proptest! {
    /// Corrupted or truncated snapshots are refused, never a panic.
    #[test]
    fn corrupted_snapshots_are_refused(cut in 0usize..20_000, flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..8)) {
        let mut m = mimo();
        drive(&mut m, 0, 50);
        let mut bytes = to_bytes(&m).unwrap();
        bytes.truncate(cut.min(bytes.len()));
        for (i, x) in flips {
            if !bytes.is_empty() {
                let n = bytes.len();
                bytes[i % n] ^= x;
            }
        }
        if let Ok(mut restored) = from_bytes::<MimoController>(&bytes) {
            // Whatever decoded must still be steppable without panicking.
            let mut out = vec![ChannelOutput::default(); restored.len()];
            let y = vec![0.0; restored.len()];
            let r = vec![Reference::default(); restored.len()];
            let _ = restored.step(1e6, &y, &r, &mut out);
        }
    }
}
