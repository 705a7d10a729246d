//! Untrusted input against the registry, without a network: the envelope holds whatever a
//! client asks, state stays bounded, and nothing changes before a message is validated.

mod common;
use common::{answered, Answer};
use controller_service::registry::{Served, MAX_SEQ_JUMP};
use controller_service::{Registry, ServiceConfig};
use proptest::prelude::*;
use protocol::{pb, PROTOCOL_VERSION};

/// Two AERO-like channels with a ±24 V envelope (from the output map, the default), a
/// one-sided heater channel with an explicit envelope and rate limit, and a template.
const CONFIG: &str = r#"
controller_id = "c1"
max_devices = 4

[[devices]]
id = "aero-1"
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 1.0, kp = 2.0 }, estimator = { window = 3 } }
output = { dead_zone = 10.0, min = -24.0, max = 24.0 }
reference = [{ kind = "constant", value = 1.0 }]
[[devices.channels]]
law = { law = "pid", params = { kp = 1.0 } }
output = { min = -24.0, max = 24.0 }

[[devices]]
id = "heater"
[[devices.channels]]
law = { law = "pid", params = { kp = 50.0, ki = 1.0 } }
envelope = { min = 0.0, max = 24.0, rate_limit = 100.0 }
reference = [{ kind = "constant", value = 40.0 }]

[[templates]]
pattern = "sim-$*"
[[templates.channels]]
law = { law = "pid", params = { kp = 2.0 } }
output = { min = -5.0, max = 5.0 }
"#;

fn registry() -> Registry {
    registry_with(CONFIG)
}

fn registry_with(text: &str) -> Registry {
    Registry::new(ServiceConfig::parse("test.toml", text).unwrap()).unwrap()
}

fn sample(id: &str, run: u64, seq: u64, t: f64, y: &[f64]) -> pb::Sample {
    pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: id.into(),
        seq,
        plant_time: t,
        outputs: y.to_vec(),
        run_id: run,
        ..Default::default()
    }
}

fn mode(c: &pb::Command) -> pb::Mode {
    pb::Mode::try_from(c.mode).unwrap()
}

/// Drive `aero-1` for `n` samples of run 7 from `seq0`, returning the last command.
fn run(r: &mut Registry, seq0: u64, n: u64) -> pb::Command {
    let mut last = None;
    for k in seq0..seq0 + n {
        last = Some(answered(r.answer(
            "aero-1",
            &sample("aero-1", 7, k, k as f64 * 0.01, &[0.0, 0.0]),
        )));
    }
    last.unwrap()
}

fn pid_law(kp: f64) -> pb::channel_config::Law {
    pb::channel_config::Law::Pid(pb::Pid {
        kp,
        ..Default::default()
    })
}

#[test]
fn a_law_only_change_keeps_the_limits() {
    // The bug a Python client hit: channels that set only the law used to drop the maps.
    let mut r = registry();
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        channels: vec![
            pb::ChannelConfig {
                law: Some(pid_law(1e6)),
                output: None,
            },
            pb::ChannelConfig {
                law: Some(pid_law(1e6)),
                output: None,
            },
        ],
        ..Default::default()
    };
    let rep = r.configure("aero-1", &req);
    assert!(rep.accepted, "{}", rep.reason);
    let cfg = rep.config.unwrap();
    assert_eq!(cfg.channels[0].output.unwrap().max, Some(24.0));
    assert_eq!(cfg.channels[0].output.unwrap().dead_zone, 10.0);
    // A huge gain on a big error: the command saturates at the envelope, never beyond.
    for k in 0..20u64 {
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", 7, k, k as f64 * 0.01, &[-100.0, 100.0]),
        ));
        assert!(c.v.iter().all(|v| v.abs() <= 24.0), "{:?}", c.v);
    }
    // An output map that leaves out its limits gets the envelope's.
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        channels: vec![
            pb::ChannelConfig {
                law: Some(pid_law(1.0)),
                output: Some(pb::OutputMap::default()),
            },
            pb::ChannelConfig {
                law: Some(pid_law(1.0)),
                output: Some(pb::OutputMap::default()),
            },
        ],
        ..Default::default()
    };
    let cfg = r.configure("aero-1", &req).config.unwrap();
    assert_eq!(cfg.channels[1].output.unwrap().min, Some(-24.0));
}

#[test]
fn explicit_widening_through_a_config_change_is_refused_and_changes_nothing() {
    let mut r = registry();
    let before = r.config_of("aero-1").unwrap();
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        updates: vec![pb::ChannelUpdate {
            channel: 1,
            max: Some(30.0),
            kp: Some(3.0),
            ..Default::default()
        }],
        ..Default::default()
    };
    let rep = r.configure("aero-1", &req);
    assert!(!rep.accepted);
    assert!(rep.reason.contains("updates[0].max 30"), "{}", rep.reason);
    assert_eq!(r.config_of("aero-1").unwrap(), before);
    assert_eq!(r.service_status(0.0).requests_refused, 1);
}

#[test]
fn one_gain_changes_without_resending_the_rest() {
    let mut r = registry();
    let before = r.config_of("aero-1").unwrap();
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        updates: vec![pb::ChannelUpdate {
            channel: 0,
            kp: Some(5.0),
            ..Default::default()
        }],
        ..Default::default()
    };
    let rep = r.configure("aero-1", &req);
    assert!(rep.accepted, "{}", rep.reason);
    let after = rep.config.unwrap();
    let law = |c: &pb::DeviceConfig| match c.channels[0].law.unwrap() {
        pb::channel_config::Law::Intelligent(i) => i,
        other => panic!("{other:?}"),
    };
    assert_eq!(law(&after).kp, 5.0);
    assert_eq!(law(&after).alpha, law(&before).alpha);
    assert_eq!(after.channels[0].output, before.channels[0].output);
    assert_eq!(after.channels[1], before.channels[1]);
    assert_eq!(after.reference, before.reference);
    // A parameter the law does not have is refused by name; so is a channel out of range.
    for (u, needle) in [
        (
            pb::ChannelUpdate {
                channel: 1,
                alpha: Some(2.0),
                ..Default::default()
            },
            "no alpha",
        ),
        (
            pb::ChannelUpdate {
                channel: 2,
                kp: Some(1.0),
                ..Default::default()
            },
            "2 channels",
        ),
        (
            pb::ChannelUpdate {
                channel: 0,
                kp: Some(f64::NAN),
                ..Default::default()
            },
            "updates[0]",
        ),
    ] {
        let rep = r.configure(
            "aero-1",
            &pb::ConfigRequest {
                version: PROTOCOL_VERSION,
                updates: vec![u],
                ..Default::default()
            },
        );
        assert!(
            !rep.accepted && rep.reason.contains(needle),
            "{needle}: {}",
            rep.reason
        );
    }
    // A new law through an update keeps the output map.
    let rep = r.configure(
        "aero-1",
        &pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            updates: vec![pb::ChannelUpdate {
                channel: 0,
                law: Some(pb::channel_update::Law::Pid(pb::Pid {
                    kp: 1.0,
                    ..Default::default()
                })),
                ki: Some(0.5),
                ..Default::default()
            }],
            ..Default::default()
        },
    );
    assert!(rep.accepted, "{}", rep.reason);
    let cfg = rep.config.unwrap();
    assert_eq!(cfg.channels[0].output, before.channels[0].output);
    assert!(matches!(
        cfg.channels[0].law,
        Some(pb::channel_config::Law::Pid(pb::Pid { ki, .. })) if ki == 0.5
    ));
}

fn envelope(limits: &[(Option<f64>, Option<f64>, Option<f64>)]) -> pb::EnvelopeRequest {
    pb::EnvelopeRequest {
        version: PROTOCOL_VERSION,
        envelope: Some(pb::Envelope {
            channels: limits
                .iter()
                .map(|&(min, max, rate_limit)| pb::ChannelLimits {
                    min,
                    max,
                    rate_limit,
                })
                .collect(),
        }),
        reason: "test".into(),
    }
}

#[test]
fn the_envelope_narrows_freely_widens_only_if_the_file_allows() {
    let mut r = registry();
    let narrow = envelope(&[
        (Some(-12.0), Some(12.0), None),
        (Some(-6.0), Some(6.0), None),
    ]);
    let rep = r.change_envelope("aero-1", &narrow);
    assert!(rep.accepted, "{}", rep.reason);
    let cfg = rep.config.unwrap();
    assert_eq!(
        cfg.channels[0].output.unwrap().max,
        Some(12.0),
        "map narrowed to fit"
    );
    assert_eq!(r.device_status("aero-1").unwrap().envelope_changes, 1);
    let c = run(&mut r, 0, 20);
    assert!(c.v[0].abs() <= 12.0 && c.v[1].abs() <= 6.0, "{:?}", c.v);
    let wide = envelope(&[
        (Some(-24.0), Some(24.0), None),
        (Some(-24.0), Some(24.0), None),
    ]);
    let rep = r.change_envelope("aero-1", &wide);
    assert!(
        !rep.accepted && rep.reason.contains("allow_remote_widening"),
        "{}",
        rep.reason
    );
    // Nor can a config change step past the narrowed envelope.
    let rep = r.configure(
        "aero-1",
        &pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            updates: vec![pb::ChannelUpdate {
                channel: 0,
                max: Some(20.0),
                ..Default::default()
            }],
            ..Default::default()
        },
    );
    assert!(!rep.accepted);
    // Malformed envelopes are refused.
    for bad in [
        envelope(&[(Some(1.0), Some(-1.0), None), (None, None, None)]),
        envelope(&[(None, None, Some(-3.0)), (None, None, None)]),
        envelope(&[(None, None, None)]),
    ] {
        assert!(!r.change_envelope("aero-1", &bad).accepted);
    }
    // With the file's permission, widening works.
    let mut open = registry_with(&CONFIG.replace(
        "max_devices = 4",
        "max_devices = 4\nallow_remote_widening = true",
    ));
    let wider = envelope(&[
        (Some(-30.0), Some(30.0), None),
        (Some(-24.0), Some(24.0), None),
    ]);
    assert!(open.change_envelope("aero-1", &wider).accepted);
}

#[test]
fn a_one_sided_rate_limited_envelope_holds_through_any_gain() {
    let mut r = registry();
    let rep = r.configure(
        "heater",
        &pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            updates: vec![pb::ChannelUpdate {
                channel: 0,
                // The largest gain the bounds let through (`controller_service::bounds`).
                kp: Some(1e6),
                ..Default::default()
            }],
            ..Default::default()
        },
    );
    assert!(rep.accepted, "{}", rep.reason);
    let mut prev: Option<f64> = None;
    for k in 0..200u64 {
        // The temperature swings wildly around the 40 degree setpoint.
        let y = if k % 7 < 3 { 100.0 } else { -50.0 };
        let c = answered(r.answer("heater", &sample("heater", 1, k, k as f64 * 0.01, &[y])));
        let v = c.v[0];
        assert!((0.0..=24.0).contains(&v), "seq {k}: {v}");
        if let Some(p) = prev {
            assert!((v - p).abs() <= 100.0 * 0.01 + 1e-9, "seq {k}: {p} -> {v}");
        }
        prev = Some(v);
    }
}

#[test]
fn a_bad_sample_with_a_new_run_id_does_not_restart_the_device() {
    let mut r = registry();
    assert_eq!(mode(&run(&mut r, 0, 10)), pb::Mode::Control);
    let mut nan = sample("aero-1", 99, 10, 0.1, &[f64::NAN, 0.0]);
    assert_eq!(
        mode(&answered(r.answer("aero-1", &nan))),
        pb::Mode::Rejected
    );
    nan.device_id = "someone-else".into();
    assert_eq!(
        mode(&answered(r.answer("aero-1", &nan))),
        pb::Mode::Rejected
    );
    // The real plant carries on in control: no warm-up.
    assert_eq!(mode(&run(&mut r, 10, 1)), pb::Mode::Control);
    assert_eq!(r.device_status("aero-1").unwrap().restarts, 1);
}

#[test]
fn no_sequence_number_can_lock_a_device() {
    let mut r = registry();
    run(&mut r, 0, 10);
    let wild = sample("aero-1", 7, u64::MAX, 0.2, &[0.0, 0.0]);
    let c = answered(r.answer("aero-1", &wild));
    assert_eq!(mode(&c), pb::Mode::Rejected);
    assert!(c.error.contains("jumps"), "{}", c.error);
    assert_eq!(mode(&run(&mut r, 10, 1)), pb::Mode::Control);
    // A jump within the bound is an outage: counted as lost, answered.
    let far = 10 + MAX_SEQ_JUMP;
    let c = answered(r.answer("aero-1", &sample("aero-1", 7, far, 100.0, &[0.0, 0.0])));
    assert_eq!(mode(&c), pb::Mode::Control);
    assert_eq!(r.device_status("aero-1").unwrap().lost, MAX_SEQ_JUMP - 1);
    // A new run may start anywhere, u64::MAX included, and the arithmetic does not wrap:
    // the next run starts again from 1.
    let top = answered(r.answer("aero-1", &sample("aero-1", 8, u64::MAX, 0.0, &[0.0, 0.0])));
    assert_eq!(mode(&top), pb::Mode::WarmingUp);
    let again = answered(r.answer("aero-1", &sample("aero-1", 9, 1, 0.0, &[0.0, 0.0])));
    assert_eq!(mode(&again), pb::Mode::WarmingUp);
    assert_eq!(r.device_status("aero-1").unwrap().lost, MAX_SEQ_JUMP - 1);
}

#[test]
fn a_stray_run_cannot_lock_the_real_plant_out() {
    let mut r = registry();
    run(&mut r, 0, 100);
    // One valid sample of another run restarts the device (it cannot be told from a
    // restart). The real plant's run is then retired: its samples are late ones at first,
    // and after the reorder window the real plant is taken back.
    answered(r.answer("aero-1", &sample("aero-1", 666, 5, 0.0, &[0.0, 0.0])));
    let mut modes = Vec::new();
    for k in 100..300u64 {
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", 7, k, k as f64 * 0.01, &[0.0, 0.0]),
        ));
        modes.push(mode(&c));
    }
    let stale = modes.iter().filter(|m| **m == pb::Mode::Stale).count() as u64;
    assert!(
        stale < controller_service::registry::REORDER_WINDOW,
        "{stale}"
    );
    assert_eq!(modes.last(), Some(&pb::Mode::Control));
}

/// A heater sample reporting what its actuator holds.
fn heater(run: u64, seq: u64, t: f64, y: f64, held: f64) -> pb::Sample {
    pb::Sample {
        applied: vec![held],
        ..sample("heater", run, seq, t, &[y])
    }
}

/// Drive the heater (100 V/s envelope) as a plant would: apply each command, report it.
/// Returns the value held after the last one.
fn drive_heater(r: &mut Registry, run: u64, seqs: std::ops::Range<u64>, held: f64) -> f64 {
    let mut held = held;
    for k in seqs {
        let c = answered(r.answer("heater", &heater(run, k, k as f64 * 0.01, 20.0, held)));
        assert_eq!(mode(&c), pb::Mode::Control, "seq {k}: {}", c.error);
        assert!(
            (c.v[0] - held).abs() <= 1.0 + 2e-9,
            "seq {k}: {held} -> {}",
            c.v[0]
        );
        held = c.v[0];
    }
    held
}

#[test]
fn a_leap_of_plant_time_neither_opens_the_rate_limit_nor_locks_the_device() {
    use controller_service::registry::RESYNC_AFTER;
    let mut r = registry();
    let held = drive_heater(&mut r, 1, 1..50, 0.0);
    // The next sample in sequence, but with the plant's clock a day ahead.
    let c = answered(r.answer("heater", &heater(1, 50, 86_400.0, 20.0, held)));
    assert_eq!(mode(&c), pb::Mode::Control);
    assert!(
        (c.v[0] - held).abs() <= 100.0 * 2.0 * 0.01 * (1.0 + 2e-9),
        "a day of plant time opened the rate limit: {held} -> {}",
        c.v[0]
    );
    // The real clock carries on: refused (time does not advance) until RESYNC_AFTER of its
    // samples in a row, then followed as a new run.
    let before = r.device_status("heater").unwrap();
    let mut refused = 0;
    let mut k = 51;
    let first = loop {
        let c = answered(r.answer("heater", &heater(1, k, k as f64 * 0.01, 20.0, held)));
        if mode(&c) == pb::Mode::Control {
            break c;
        }
        assert_eq!(mode(&c), pb::Mode::Rejected);
        assert!(c.error.contains("does not advance"), "{}", c.error);
        refused += 1;
        k += 1;
        assert!(refused < 10 * RESYNC_AFTER, "the device is locked out");
    };
    assert_eq!(refused, RESYNC_AFTER - 1);
    // The first command of the resynchronised run: one period's step from what is held.
    assert!(
        (first.v[0] - held).abs() <= 1.0 + 2e-9,
        "{held} -> {}",
        first.v[0]
    );
    let after = r.device_status("heater").unwrap();
    assert_eq!(after.restarts, before.restarts + 1, "followed as a new run");
    assert_eq!(after.rejected, before.rejected + u64::from(refused));
}

#[test]
fn leaps_in_a_row_do_not_open_the_rate_limit() {
    let mut r = registry();
    let mut held = drive_heater(&mut r, 1, 1..30, 0.0);
    // Four leaps of 1000 s in a row: the period estimate (the lower median of the last
    // eight intervals) does not move, so each step stays within two periods' worth.
    let mut t = 0.29;
    for k in 30..34u64 {
        t += 1000.0;
        let c = answered(r.answer("heater", &heater(1, k, t, 20.0, held)));
        assert_eq!(mode(&c), pb::Mode::Control, "{}", c.error);
        assert!(
            (c.v[0] - held).abs() <= 100.0 * 2.0 * 0.01 * (1.0 + 2e-9),
            "leap {k}: {held} -> {}",
            c.v[0]
        );
        held = c.v[0];
    }
}

#[test]
fn normal_driving_with_a_lost_sample_is_not_clipped() {
    let mut r = registry();
    // The first command starts from what is held (0 V) where the PID wants 24 V: clipped.
    let held = drive_heater(&mut r, 1, 1..2, 0.0);
    let start = r.device_status("heater").unwrap().clamped;
    // From then on the law's own rate limit keeps it within reach, a lost sample (seq 50)
    // included.
    let held = drive_heater(&mut r, 1, 2..50, held);
    drive_heater(&mut r, 1, 51..100, held);
    let st = r.device_status("heater").unwrap();
    assert_eq!(st.clamped, start, "{st:?}");
    assert_eq!(st.lost, 1);
}

#[test]
fn a_sequence_jump_inside_the_bound_locks_out_for_at_most_resync_after() {
    use controller_service::registry::RESYNC_AFTER;
    let mut r = registry();
    run(&mut r, 0, 20);
    let c = answered(r.answer(
        "aero-1",
        &sample("aero-1", 7, MAX_SEQ_JUMP / 2, 0.21, &[0.0, 0.0]),
    ));
    assert_eq!(mode(&c), pb::Mode::Control);
    let mut stale = 0;
    for k in 21..21 + u64::from(RESYNC_AFTER) {
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", 7, k, 0.21 + k as f64 * 0.01, &[0.0, 0.0]),
        ));
        if mode(&c) == pb::Mode::Stale {
            stale += 1;
        }
    }
    assert_eq!(stale, RESYNC_AFTER - 1);
    // Followed again (a fresh run: the estimators warm up).
    let c = answered(r.answer(
        "aero-1",
        &sample("aero-1", 7, 21 + u64::from(RESYNC_AFTER), 2.0, &[0.0, 0.0]),
    ));
    assert_ne!(mode(&c), pb::Mode::Stale);
    assert_ne!(mode(&c), pb::Mode::Rejected, "{}", c.error);
}

#[test]
fn scattered_refusals_never_resync_a_device() {
    let mut r = registry();
    run(&mut r, 0, 20);
    // Old samples replayed out of order (no stream of their own): stale, every one.
    for k in 0..500u64 {
        let seq = (k * 7919) % 19;
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", 7, seq, seq as f64 * 0.01, &[0.0, 0.0]),
        ));
        assert_eq!(mode(&c), pb::Mode::Stale, "replay {k} (seq {seq})");
    }
    assert_eq!(r.device_status("aero-1").unwrap().restarts, 1);
    assert_eq!(mode(&run(&mut r, 20, 1)), pb::Mode::Control);
}

#[test]
fn the_first_command_of_a_run_moves_from_what_the_plant_applies() {
    let mut r = registry();
    // The plant starts while its own controller holds 12 V: the service's first command
    // stays there (no period known yet), the next ones move at most 100 V/s * 10 ms.
    let c = answered(r.answer("heater", &heater(1, 1, 0.01, 20.0, 12.0)));
    assert_eq!(c.v, vec![12.0]);
    let held = drive_heater(&mut r, 1, 2..30, 12.0);
    // The plant restarts (a new run) and reports 3 V: one period's step from there.
    let c = answered(r.answer("heater", &heater(2, 1, 0.01, 20.0, 3.0)));
    assert!(
        (c.v[0] - 3.0).abs() <= 1.0 + 2e-9,
        "{held} / 3 -> {}",
        c.v[0]
    );
    // Without a report, from the last command sent to the device.
    let last = c.v[0];
    let c = answered(r.answer("heater", &sample("heater", 3, 1, 0.01, &[20.0])));
    assert!((c.v[0] - last).abs() <= 1.0 + 2e-9, "{last} -> {}", c.v[0]);
}

#[test]
fn after_a_restore_the_first_command_moves_from_what_the_plant_applies() {
    let mut r = registry();
    let held = drive_heater(&mut r, 1, 1..100, 0.0);
    let snaps = r.snapshots();
    let mut fresh = registry();
    for s in &snaps {
        fresh.restore(s).unwrap();
    }
    // The plant ran on its fallback meanwhile and holds 2 V now.
    let c = answered(fresh.answer("heater", &heater(1, 130, 1.3, 20.0, 2.0)));
    assert!(
        (c.v[0] - 2.0).abs() <= 1.0 + 2e-9,
        "before the restore {held}, now 2 V -> {}",
        c.v[0]
    );
}

#[test]
fn a_plant_without_a_run_id_recovers_from_its_restart() {
    let mut r = registry();
    for k in 1..=300u64 {
        answered(r.answer(
            "aero-1",
            &sample("aero-1", 0, k, k as f64 * 0.01, &[0.0, 0.0]),
        ));
    }
    // A late sample is still stale...
    let late = answered(r.answer("aero-1", &sample("aero-1", 0, 290, 2.9, &[0.0, 0.0])));
    assert_eq!(mode(&late), pb::Mode::Stale);
    // ...but the plant starting again at seq 1, time 0.01, is a new run.
    let c = answered(r.answer("aero-1", &sample("aero-1", 0, 1, 0.01, &[0.0, 0.0])));
    assert_eq!(mode(&c), pb::Mode::WarmingUp);
    for k in 2..20u64 {
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", 0, k, k as f64 * 0.01, &[0.0, 0.0]),
        ));
        assert_ne!(mode(&c), pb::Mode::Stale);
        assert_ne!(mode(&c), pb::Mode::Rejected, "{}", c.error);
    }
    // Even if its first samples after the restart were lost.
    let c = answered(r.answer("aero-1", &sample("aero-1", 0, 1, 0.01, &[0.0, 0.0])));
    assert_eq!(mode(&c), pb::Mode::WarmingUp);
}

#[test]
fn echoed_strings_are_capped_and_unknown_ids_bounded() {
    let mut r = registry();
    let huge = "x".repeat(1 << 20);
    let c = answered(r.answer("aero-1", &sample(&huge, 7, 0, 0.0, &[0.0, 0.0])));
    assert!(c.error.len() < 200, "{} bytes", c.error.len());
    assert!(r.device_status("aero-1").unwrap().last_error.len() < 200);
    for k in 0..10_000 {
        let id = format!("ghost-{k}");
        assert_eq!(
            r.answer(&id, &sample(&id, 1, 0, 0.0, &[0.0])),
            Err(Served::Unknown)
        );
    }
    let st = r.service_status(0.0);
    assert_eq!(st.unknown_samples, 10_000);
    assert_eq!(st.unknown_devices.len(), 64);
    assert_eq!(st.devices.len(), 2);
    // Templates provision up to max_devices (4, two declared), then refuse and count.
    for k in 0..10 {
        let id = format!("sim-{k}");
        let o = r.answer(&id, &sample(&id, 1, 0, 0.0, &[0.0]));
        assert_eq!(o.is_ok(), k < 2, "{id}");
    }
    let st = r.service_status(0.0);
    assert_eq!((st.devices.len(), st.device_table_full), (4, 8));
}

/// One operation of the property test.
#[derive(Debug, Clone)]
enum Op {
    Sample {
        dev: usize,
        run: u64,
        seq: Option<u64>,
        dt: f64,
        y: Vec<f64>,
    },
    Update {
        dev: usize,
        channel: u32,
        kp: Option<f64>,
        alpha: Option<f64>,
        min: Option<f64>,
        max: Option<f64>,
        rate: Option<f64>,
    },
    Envelope {
        dev: usize,
        lo: f64,
        hi: f64,
    },
    Reference {
        dev: usize,
        value: f64,
        channels: usize,
    },
}

fn value() -> impl Strategy<Value = f64> {
    prop_oneof![
        8 => -100.0..100.0f64,
        1 => Just(f64::NAN),
        1 => Just(f64::INFINITY),
        1 => Just(1e300),
        1 => Just(-1e300),
    ]
}

fn op() -> impl Strategy<Value = Op> {
    let ids = 0..4usize;
    prop_oneof![
        8 => (ids.clone(), prop_oneof![8 => Just(1u64), 1 => Just(2), 1 => any::<u64>()],
              // None: the next sequence number, as a plant sends it.
              prop_oneof![6 => Just(None), 3 => (0..1000u64).prop_map(Some), 1 => any::<u64>().prop_map(Some)],
              prop_oneof![6 => Just(0.01), 1 => -1.0..1.0f64, 1 => Just(f64::NAN)],
              proptest::collection::vec(value(), 0..4))
            .prop_map(|(dev, run, seq, dt, y)| Op::Sample { dev, run, seq, dt, y }),
        2 => (ids.clone(), 0..3u32, proptest::option::of(value()), proptest::option::of(value()),
              proptest::option::of(value()), proptest::option::of(value()), proptest::option::of(value()))
            .prop_map(|(dev, channel, kp, alpha, min, max, rate)| Op::Update { dev, channel, kp, alpha, min, max, rate }),
        1 => (ids.clone(), value(), value()).prop_map(|(dev, lo, hi)| Op::Envelope { dev, lo, hi }),
        1 => (ids, value(), 0..3usize).prop_map(|(dev, value, channels)| Op::Reference { dev, value, channels }),
    ]
}

const IDS: [&str; 4] = ["aero-1", "heater", "sim-a", "ghost"];

fn limits_of(r: &Registry, id: &str) -> Vec<(f64, f64)> {
    r.device_status(id)
        .map(|s| {
            s.envelope
                .unwrap()
                .channels
                .iter()
                .map(|l| {
                    (
                        l.min.unwrap_or(f64::NEG_INFINITY),
                        l.max.unwrap_or(f64::INFINITY),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

/// The samples of [`the_envelope_holds_and_state_stays_bounded`], each answer checked:
/// the registry under test, the envelopes of its file, each device's clock and next
/// sequence number, and what is known of the heater's commands.
struct Stream {
    r: Registry,
    file: Vec<Vec<(f64, f64)>>,
    t: [f64; 4],
    next: [u64; 4],
    /// What the heater's actuator holds: it applies every CONTROL command and says so.
    held: f64,
    /// The heater's samples answered with a command (run, seq, time), and the largest
    /// interval between two answered consecutive ones of a run: the service's period
    /// estimate (a median of such intervals) is never above it. A sequence number is the
    /// run's: the same one in another run is another sample.
    answered: Option<(u64, u64, f64)>,
    longest: f64,
}

impl Stream {
    fn new(r: Registry) -> Self {
        let file = IDS.iter().map(|id| limits_of(&r, id)).collect();
        Self {
            r,
            file,
            t: [0.0; 4],
            next: [1; 4],
            held: 0.0,
            answered: None,
            longest: 0.0,
        }
    }

    /// Send device `dev`'s sample (`seq` or the next, `dt` after its last), and check the
    /// answer: finite values inside the envelope in force and the file's.
    fn sample(
        &mut self,
        dev: usize,
        run: u64,
        seq: Option<u64>,
        dt: f64,
        y: &[f64],
    ) -> Result<(), TestCaseError> {
        let seq = seq.unwrap_or(self.next[dev]);
        self.next[dev] = seq.wrapping_add(1);
        // A NaN time is one bad sample, not a clock broken for good.
        let time = if dt.is_nan() {
            f64::NAN
        } else {
            self.t[dev] += dt;
            self.t[dev]
        };
        let id = IDS[dev];
        let mut s = sample(id, run, seq, time, y);
        if id == "heater" {
            s.applied = vec![self.held];
        }
        let env = limits_of(&self.r, id);
        let Ok(c) = self.r.answer(id, &s) else {
            return Ok(());
        };
        prop_assert_eq!(c.seq, seq);
        let env = if env.is_empty() {
            limits_of(&self.r, id)
        } else {
            env
        };
        for (i, v) in c.v.iter().enumerate() {
            prop_assert!(v.is_finite(), "{}: {:?}", id, c.v);
            prop_assert!(
                env[i].0 <= *v && *v <= env[i].1,
                "{}: {} outside {:?}",
                id,
                v,
                env[i]
            );
            if let Some(f) = self.file[dev].get(i) {
                prop_assert!(
                    f.0 <= *v && *v <= f.1,
                    "{}: {} outside the file's {:?}",
                    id,
                    v,
                    f
                );
            }
        }
        prop_assert!(c.error.len() < 300);
        if id == "heater" {
            self.heater_rate(&c, run, time, env[0])?;
        }
        Ok(())
    }

    /// The heater's command `c` moved from what its actuator holds by no more than the
    /// rate limit (100 V/s) allows.
    fn heater_rate(
        &mut self,
        c: &pb::Command,
        run: u64,
        time: f64,
        env: (f64, f64),
    ) -> Result<(), TestCaseError> {
        let seq = c.seq;
        let computed = c.mode == pb::Mode::Control as i32 || c.mode == pb::Mode::WarmingUp as i32;
        // Plant time since the run's last answered sample: within a run, before a period
        // is known, the limit's time step is that (at most 1 s); a new run's first command
        // moves at most one period.
        let in_run = self.answered.filter(|(r, _, _)| *r == run);
        let since = in_run.map_or(0.0, |(_, _, tq)| (time - tq).clamp(0.0, 1.0));
        let resent = in_run.is_some_and(|(_, q, _)| q == seq);
        if computed && !resent {
            if let Some((_, q, tq)) = in_run {
                if seq == q.wrapping_add(1) {
                    self.longest = self.longest.max(time - tq);
                }
            }
            self.answered = Some((run, seq, time));
        }
        if c.mode == pb::Mode::Control as i32 {
            // Over at most two periods, from what the actuator holds, whatever the plant's
            // clock did; unless a narrowed envelope forced the command to its edge.
            let (v, held) = (c.v[0], self.held);
            let inside = env.0 <= held && held <= env.1;
            let step = 100.0 * (2.0 * self.longest).max(since);
            prop_assert!(
                !inside || (v - held).abs() <= step * (1.0 + 2e-9) + 1e-12,
                "heater: {} -> {} (longest interval {}, since {})",
                held,
                v,
                self.longest,
                since
            );
            self.held = v;
        }
        Ok(())
    }
}

/// A case the property test found (2026-11-28): the heater's run 2 answers its seq 710,
/// then run 1 starts with the same number at an earlier time. The check once took run
/// 1's 710 for a resend of run 2's, never counted the run's first interval, and allowed
/// the next command no step at all, where the service rightly moved it by 1 V in 10 ms.
#[test]
fn a_sequence_number_is_its_runs() {
    let mut stream = Stream::new(registry());
    let heater = 1;
    for (run, seq, dt, y) in [
        (2, Some(710), 0.01, 0.0),
        (1, Some(709), 0.01, f64::NAN),
        (1, None, -0.25632273391113297, 0.0),
        (1, None, 0.01, 0.0),
    ] {
        stream.sample(heater, run, seq, dt, &[y]).unwrap();
    }
    assert!(
        stream.held > 0.99,
        "the last command moved: {}",
        stream.held
    );
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1024))]
    /// Random sequences of samples, configuration changes, envelope changes and reference
    /// updates, valid and not: no panic; every command carries finite values inside the
    /// envelope in force when it was computed, and never outside the file's envelope
    /// (remote widening is off); state stays bounded.
    #[test]
    fn the_envelope_holds_and_state_stays_bounded(ops in proptest::collection::vec(op(), 1..200)) {
        let mut stream = Stream::new(registry());
        for op in ops {
            let r = &mut stream.r;
            match op {
                Op::Sample { dev, run, seq, dt, y } => {
                    stream.sample(dev, run, seq, dt, &y)?;
                }
                Op::Update { dev, channel, kp, alpha, min, max, rate } => {
                    let req = pb::ConfigRequest {
                        version: PROTOCOL_VERSION,
                        updates: vec![pb::ChannelUpdate { channel, kp, alpha, min, max, rate_limit: rate, ..Default::default() }],
                        ..Default::default()
                    };
                    let before = r.config_of(IDS[dev]);
                    let rep = r.configure(IDS[dev], &req);
                    if !rep.accepted {
                        prop_assert_eq!(r.config_of(IDS[dev]), before, "a refused request changed nothing");
                    }
                }
                Op::Envelope { dev, lo, hi } => {
                    let n = limits_of(r, IDS[dev]).len();
                    let req = envelope(&vec![(Some(lo), Some(hi), None); n]);
                    let before = limits_of(r, IDS[dev]);
                    let rep = r.change_envelope(IDS[dev], &req);
                    let after = limits_of(r, IDS[dev]);
                    if rep.accepted {
                        for (b, a) in before.iter().zip(&after) {
                            prop_assert!(a.0 >= b.0 && a.1 <= b.1, "widened {:?} -> {:?}", b, a);
                        }
                    } else {
                        prop_assert_eq!(before, after);
                    }
                }
                Op::Reference { dev, value, channels } => {
                    let pieces = vec![vec![mfc::trajectory::Piece::Constant { value }]; channels];
                    let u = pb::ReferenceUpdate {
                        version: PROTOCOL_VERSION,
                        reference: Some(protocol::convert::reference_to_pb(&pieces, 0.0)),
                    };
                    let _ = r.set_reference(IDS[dev], &u);
                }
            }
        }
        let st = stream.r.service_status(0.0);
        prop_assert!(st.devices.len() <= 4);
        prop_assert!(st.unknown_devices.len() <= 64);
        for d in &st.devices {
            prop_assert!(d.last_error.len() < 300, "{}", d.last_error.len());
        }
    }
}
