//! The rules for samples, configuration and status, without a network.

mod common;
use common::{answered, Answer};
use controller_service::registry::Served;
use controller_service::snapshot;
use controller_service::{Registry, ServiceConfig};
use protocol::convert::channel_to_pb;
use protocol::{pb, PROTOCOL_VERSION};

const CONFIG: &str = r#"
controller_id = "c1"
[[devices]]
id = "aero-1"
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 1.0, kp = 2.0 }, estimator = { window = 3 } }
reference = [{ kind = "constant", value = 1.0 }]
[[devices.channels]]
law = { law = "pid", params = { kp = 1.0 } }

[[templates]]
pattern = "sim-$*"
[[templates.channels]]
law = { law = "pid", params = { kp = 2.0 } }
"#;

fn registry() -> Registry {
    Registry::new(ServiceConfig::parse("test.toml", CONFIG).unwrap()).unwrap()
}

fn sample(id: &str, seq: u64, t: f64, y: &[f64]) -> pb::Sample {
    pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: id.into(),
        seq,
        plant_time: t,
        outputs: y.to_vec(),
        run_id: 42,
        ..Default::default()
    }
}

#[test]
fn answers_every_sample_with_its_sequence() {
    let mut r = registry();
    for k in 0..10u64 {
        let c = answered(r.answer("aero-1", &sample("aero-1", k, k as f64 * 0.01, &[0.0, 0.5])));
        assert_eq!(c.seq, k);
        // The iP channel's window is 3 intervals: it warms up on the first 3 samples.
        let expected = if k < 3 {
            pb::Mode::WarmingUp
        } else {
            pb::Mode::Control
        };
        assert_eq!(c.mode, expected as i32, "seq {k}");
        assert_eq!(c.v.len(), 2);
        assert_eq!(c.controller_id, "c1");
    }
    let s = r.device_status("aero-1").unwrap();
    assert_eq!((s.samples, s.commands, s.lost), (10, 10, 0));
}

#[test]
fn duplicates_stale_and_lost() {
    let mut r = registry();
    let first = answered(r.answer("aero-1", &sample("aero-1", 5, 0.05, &[0.0, 0.0])));
    // Duplicate: the same command again.
    let again = answered(r.answer("aero-1", &sample("aero-1", 5, 0.05, &[0.0, 0.0])));
    assert_eq!(
        protocol::encode(&first),
        protocol::encode(&again),
        "byte for byte"
    );
    // Older: stale, nothing moves.
    let before = r.device_status("aero-1").unwrap();
    let stale = answered(r.answer("aero-1", &sample("aero-1", 3, 0.03, &[9.0, 9.0])));
    assert_eq!(stale.mode, pb::Mode::Stale as i32);
    assert!(stale.v.is_empty());
    let after = r.device_status("aero-1").unwrap();
    assert_eq!(
        (after.last_seq, after.plant_time),
        (before.last_seq, before.plant_time)
    );
    // A jump: 6..=8 lost.
    answered(r.answer("aero-1", &sample("aero-1", 9, 0.09, &[0.0, 0.0])));
    let s = r.device_status("aero-1").unwrap();
    assert_eq!((s.duplicates, s.stale, s.lost), (1, 1, 3));
}

#[test]
fn bad_samples_are_rejected_with_a_reason_and_change_nothing() {
    let mut r = registry();
    answered(r.answer("aero-1", &sample("aero-1", 1, 0.01, &[0.0, 0.0])));
    let cases = [
        (sample("aero-1", 2, 0.02, &[f64::NAN, 0.0]), "non-finite"),
        (sample("aero-1", 2, 0.02, &[0.0]), "expected 2 outputs"),
        (sample("aero-1", 2, 0.01, &[0.0, 0.0]), "does not advance"),
        (sample("other", 2, 0.02, &[0.0, 0.0]), "device id"),
    ];
    for (s, needle) in cases {
        let c = answered(r.answer("aero-1", &s));
        assert_eq!(c.mode, pb::Mode::Rejected as i32, "{needle}");
        assert!(c.error.contains(needle), "{}: {needle}", c.error);
    }
    let s = r.device_status("aero-1").unwrap();
    assert_eq!((s.rejected, s.last_seq, s.commands), (4, 1, 1));
    // And the device still works (still warming up its 3-interval window).
    let c = answered(r.answer("aero-1", &sample("aero-1", 2, 0.02, &[0.0, 0.0])));
    assert_eq!(c.mode, pb::Mode::WarmingUp as i32);
    assert_eq!(c.seq, 2);
}

#[test]
fn unknown_devices_are_refused_templates_provision() {
    let mut r = registry();
    assert_eq!(
        r.answer("ghost", &sample("ghost", 0, 0.0, &[0.0])),
        Err(Served::Unknown)
    );
    let c = answered(r.answer("sim-7", &sample("sim-7", 0, 0.0, &[0.3])));
    assert_eq!(c.v.len(), 1);
    let st = r.service_status(1.0);
    assert_eq!(st.unknown_samples, 1);
    assert_eq!(st.unknown_devices, vec!["ghost".to_string()]);
    assert!(r.device_status("sim-7").unwrap().from_template);
}

#[test]
fn a_restarted_plant_resets_its_state() {
    let mut r = registry();
    for k in 0..5u64 {
        answered(r.answer(
            "aero-1",
            &sample("aero-1", 100 + k, 10.0 + k as f64 * 0.01, &[0.0, 0.0]),
        ));
    }
    let mut s = sample("aero-1", 0, 0.0, &[0.0, 0.0]);
    s.run_id = 43;
    let c = answered(r.answer("aero-1", &s));
    // Answered, and warming up again: the state was reset for the new run.
    assert_eq!((c.seq, c.mode), (0, pb::Mode::WarmingUp as i32));
}

#[test]
fn configuration_is_all_or_nothing() {
    let mut r = registry();
    let before = r.config_of("aero-1").unwrap();
    let pid = |kp| mfc::ChannelConfig {
        law: mfc::LawConfig::Pid {
            params: mfc::PidParams {
                kp,
                ..Default::default()
            },
        },
        ..Default::default()
    };
    let (good, bad) = (pid(5.0), pid(f64::NAN));
    let req = |a: &mfc::ChannelConfig, b: &mfc::ChannelConfig| pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        channels: vec![channel_to_pb(a), channel_to_pb(b)],
        ..Default::default()
    };
    let reply = r.configure("aero-1", &req(&good, &bad));
    assert!(
        !reply.accepted && reply.reason.contains("channels[1]"),
        "{}",
        reply.reason
    );
    assert_eq!(r.config_of("aero-1").unwrap(), before);
    let short = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        channels: vec![channel_to_pb(&good)],
        ..Default::default()
    };
    assert!(r.configure("aero-1", &short).reason.contains("2 channels"));
    assert!(!r.configure("nope", &short).accepted);
    let reply = r.configure("aero-1", &req(&good, &good));
    assert!(reply.accepted, "{}", reply.reason);
    assert_ne!(r.config_of("aero-1").unwrap(), before);
}

#[test]
fn bad_config_files_are_refused() {
    for (text, needle) in [
        ("controller_id = \"a/b\"", "controller_id"),
        ("[[devices]]\nid = \"x\"\nchannels = []", "devices[0].channels"),
        ("[[devices]]\nid = \"x\"\nchanels = []", "chanels"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nlaw = { law = \"intelligent\", params = { alpha = 0.0 } }", "devices[0].channels[0]"),
        ("[[templates]]\npattern = \"a//b\"\n[[templates.channels]]", "templates[0].pattern"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\n[[devices]]\nid = \"x\"\n[[devices.channels]]", "duplicate"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nlaw = { law = \"pid\", params = { kp = 1e7 } }", "kp = 1e7 is outside [-1e6, 1e6]"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nbounds = { gain = [0.0, 1.0] }", "bounds.gain"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nbounds = { kp = [2.0, 1.0] }", "bounds.kp"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nrange = [1.0, -1.0]", "devices[0].channels[0].range"),
        ("[[devices]]\nid = \"x\"\n[[devices.channels]]\nrange = [-1.0, 1.0]\nreference = [{ kind = \"constant\", value = 2.0 }]", "outside the channel's range"),
        ("[metrics]\nworst = 5000", "metrics.worst = 5000"),
        ("[metrics]\ndevices = [\"a\", \"b\"]\nmax_devices = 1", "max_devices = 1"),
        ("[metrics]\nper_device = 1", "per_device"),
    ] {
        let e = ServiceConfig::parse("svc.toml", text).unwrap_err().to_string();
        assert!(e.contains("svc.toml") && e.contains(needle), "{needle}: {e}");
    }
}

#[test]
fn the_reference_can_be_steered_live() {
    use mfc::trajectory::Piece;
    let mut r = registry();
    answered(r.answer("aero-1", &sample("aero-1", 0, 0.0, &[0.0, 0.0])));
    let pieces = vec![
        vec![Piece::Constant { value: 3.0 }],
        vec![Piece::Constant { value: -1.0 }],
    ];
    let update = pb::ReferenceUpdate {
        version: PROTOCOL_VERSION,
        reference: Some(protocol::convert::reference_to_pb(&pieces, 0.0)),
    };
    assert!(r.set_reference("aero-1", &update).accepted);
    let cfg = r.config_of("aero-1").unwrap();
    assert_eq!(
        protocol::convert::reference_from_pb(cfg.reference.as_ref().unwrap())
            .unwrap()
            .0,
        pieces
    );
    // A reference for the wrong number of channels is refused.
    let bad = pb::ReferenceUpdate {
        version: PROTOCOL_VERSION,
        reference: Some(protocol::convert::reference_to_pb(&pieces[..1], 0.0)),
    };
    let reply = r.set_reference("aero-1", &bad);
    assert!(!reply.accepted && reply.reason.contains("2 channels"));
    assert_eq!(r.device_status("aero-1").unwrap().references_refused, 1);
}

/// Restore `dir`'s snapshots into `r`: how many were restored and refused.
fn loaded(r: &mut Registry, dir: &std::path::Path) -> (usize, usize) {
    let l = snapshot::load_dir(r, dir);
    (l.restored, l.refused.len())
}

/// A registry restored from a snapshot answers the next samples exactly as the original
/// would have (same state, same reference phase); a configuration changed since is kept.
#[test]
fn snapshots_restore_state_and_reference_phase() {
    let mut a = registry();
    for k in 0..50u64 {
        answered(a.answer(
            "aero-1",
            &sample("aero-1", k, k as f64 * 0.01, &[0.1 * k as f64, 0.2]),
        ));
    }
    let dir = std::env::temp_dir().join(format!("snap-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(snapshot::save_dir(&a, &dir).unwrap(), 1);
    let mut b = registry();
    assert_eq!(loaded(&mut b, &dir), (1, 0));
    for k in 50..80u64 {
        let s = sample("aero-1", k, k as f64 * 0.01, &[0.1 * k as f64, 0.2]);
        let (ca, cb) = (
            answered(a.answer("aero-1", &s)),
            answered(b.answer("aero-1", &s)),
        );
        assert_eq!((ca.u, ca.v), (cb.u, cb.v), "seq {k}");
    }
    assert_eq!(
        a.device_status("aero-1").unwrap().samples,
        b.device_status("aero-1").unwrap().samples
    );
    // A sample answered before the state was saved (by this service before a restart,
    // or by the member that handed the device over) is not answered a second time,
    // even STALE: it counts as a duplicate and moves nothing.
    let mut c = registry();
    assert_eq!(loaded(&mut c, &dir), (1, 0));
    let before = c.device_status("aero-1").unwrap();
    let last = sample("aero-1", 49, 0.49, &[4.9, 0.2]);
    assert_eq!(c.answer("aero-1", &last), Err(Served::AlreadyAnswered));
    let st = c.device_status("aero-1").unwrap();
    assert_eq!(
        (st.duplicates, st.last_seq, st.commands),
        (before.duplicates + 1, 49, before.commands)
    );
    let next = sample("aero-1", 50, 0.50, &[5.0, 0.2]);
    assert_eq!(answered(c.answer("aero-1", &next)).seq, 50);
    // Once this service has answered a sample, a duplicate of it gets that answer again.
    assert_eq!(answered(c.answer("aero-1", &next)).seq, 50);
    // A corrupt file is refused. A configuration changed since the snapshot stays in
    // force: the snapshot brings the control state back (its counts, its estimators), never
    // the configuration, which the file (or the journal, `Registry::recover`) decides.
    std::fs::write(dir.join("junk.snap"), b"not a snapshot").unwrap();
    let changed = CONFIG.replace("kp = 2.0", "kp = 3.0");
    let mut c = Registry::new(ServiceConfig::parse("test.toml", &changed).unwrap()).unwrap();
    let file = c.config_of("aero-1").unwrap();
    assert_eq!(loaded(&mut c, &dir), (1, 1));
    assert_eq!(
        c.config_of("aero-1").unwrap(),
        file,
        "the file's configuration in force"
    );
    assert_eq!(
        c.device_status("aero-1").unwrap().samples,
        a.device_status("aero-1").unwrap().samples - 30,
        "the snapshot's control state"
    );
    let next = sample("aero-1", 50, 0.50, &[5.0, 0.2]);
    assert_eq!(answered(c.answer("aero-1", &next)).seq, 50);
}

/// A device whose commands carry a horizon: an iPD (n = 2) with a smooth dead-zone map on
/// channel 0, a PID on channel 1, an envelope with a rate limit.
const PREDICTING: &str = r#"
controller_id = "c1"
[[devices]]
id = "rig-1"
prediction = { horizon = 6 }
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ipd", order = "two", alpha = 0.2, kp = 9.0, kd = 3.0, derivative_observer = 30.0 }, estimator = { window = 4 } }
output = { dead_zone = 10.0, smoothing = 2.0, min = -24.0, max = 24.0 }
envelope = { min = -24.0, max = 24.0, rate_limit = 300.0 }
reference = [{ kind = "sine", amplitude = 0.2, period = 1.0 }]
[[devices.channels]]
law = { law = "pid", params = { kp = 1.0 } }
output = { min = -5.0, max = 5.0 }
reference = [{ kind = "constant", value = 1.0 }]
"#;

fn predicting(extra: &str) -> Registry {
    let text = PREDICTING.replace("prediction = { horizon = 6 }", extra);
    Registry::new(ServiceConfig::parse("test.toml", &text).unwrap()).unwrap()
}

#[test]
fn a_horizon_is_whole_periods_of_outputs_inside_the_envelope() {
    let mut r = predicting("prediction = { horizon = 6 }");
    let h = 0.01;
    let mut seen = 0;
    for k in 0..40u64 {
        let t = k as f64 * h;
        let y = [0.1 * (6.0 * t).sin(), 0.2];
        let c = answered(r.answer("rig-1", &sample("rig-1", k, t, &y)));
        if c.mode != pb::Mode::Control as i32 {
            assert!(c.horizon.is_empty(), "no horizon while warming up");
            continue;
        }
        // The period is known after a few samples; from then on, six periods of two.
        if c.horizon.is_empty() {
            assert!(k < 8, "no horizon at sample {k}");
            continue;
        }
        seen += 1;
        assert_eq!(c.horizon.len(), 6 * 2);
        let mut prev = c.v[0];
        for j in 0..6 {
            let (a, b) = (c.horizon[2 * j], c.horizon[2 * j + 1]);
            assert!(a.is_finite() && (-24.0..=24.0).contains(&a), "{a}");
            // The rate limit holds from v through every element (300 V/s, 10 ms).
            assert!((a - prev).abs() <= 3.0 * (1.0 + 1e-9), "{prev} -> {a}");
            prev = a;
            // The PID has no model to predict with: it holds its output.
            assert_eq!(b, c.v[1]);
            assert!((-5.0..=5.0).contains(&b));
        }
    }
    assert!(seen > 20, "{seen} commands with a horizon");
}

#[test]
fn delay_compensation_lengthens_the_horizon_to_the_round_trip() {
    let mut r = predicting("prediction = { horizon = 2, delay_compensation = true }");
    let h = 0.01;
    let mut last = None;
    for k in 0..60u64 {
        let t = k as f64 * h;
        let mut s = sample("rig-1", k, t, &[0.0, 0.2]);
        // The plant reports 56 ms round trips: commands land 5 or 6 periods late.
        s.last_rtt_us = 56_000;
        last = Some(answered(r.answer("rig-1", &s)));
    }
    let c = last.unwrap();
    assert_eq!(c.mode, pb::Mode::Control as i32);
    // round(56 ms / 10 ms) = 6 periods, more than the configured 2.
    assert_eq!(c.horizon.len(), 6 * 2);
    // Without reports of the round trip, the configured horizon.
    let mut r = predicting("prediction = { horizon = 2, delay_compensation = true }");
    let mut last = None;
    for k in 0..60u64 {
        let t = k as f64 * h;
        last = Some(answered(
            r.answer("rig-1", &sample("rig-1", k, t, &[0.0, 0.2])),
        ));
    }
    assert_eq!(last.unwrap().horizon.len(), 2 * 2);
}

#[test]
fn a_horizon_longer_than_the_limit_is_refused_with_its_field() {
    let text = PREDICTING.replace("horizon = 6", "horizon = 101");
    let e = ServiceConfig::parse("test.toml", &text)
        .unwrap_err()
        .to_string();
    assert!(e.contains("devices[0].prediction.horizon"), "{e}");
}

#[test]
fn the_trend_of_f_defaults_to_half_and_is_refused_outside_0_to_2_with_its_field() {
    let config = ServiceConfig::parse("test.toml", PREDICTING).unwrap();
    assert_eq!(config.devices[0].prediction.trend, 0.5);
    assert_eq!(config.devices[0].prediction.trend_at_rest, 0.0);
    let text = PREDICTING.replace("horizon = 6", "horizon = 6, trend = 0, trend_at_rest = 0.5");
    let config = ServiceConfig::parse("test.toml", &text).unwrap();
    assert_eq!(config.devices[0].prediction.trend, 0.0);
    assert_eq!(config.devices[0].prediction.trend_at_rest, 0.5);
    for field in ["trend", "trend_at_rest"] {
        for bad in ["-0.1", "2.5", "nan"] {
            let text = PREDICTING.replace("horizon = 6", &format!("horizon = 6, {field} = {bad}"));
            let e = ServiceConfig::parse("test.toml", &text)
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!("devices[0].prediction.{field}`")),
                "{bad}: {e}"
            );
        }
    }
}

/// With an estimate filter on the iPD, the horizon follows the trend of `F` by default,
/// and `trend = 0` gives back the held `F`: the commands' own outputs are the same, their
/// horizons differ once the estimate moves.
#[test]
fn the_trend_changes_the_horizon_not_the_command() {
    // Without the envelope's rate limit, which would clip both horizons alike.
    let filtered = PREDICTING
        .replace(
            "derivative_observer = 30.0",
            "derivative_observer = 30.0, estimate_filter = 0.05",
        )
        .replace("rate_limit = 300.0", "rate_limit = 1e6");
    let run = |prediction: &str| {
        let text = filtered.replace("prediction = { horizon = 6 }", prediction);
        let mut r = Registry::new(ServiceConfig::parse("test.toml", &text).unwrap()).unwrap();
        (0..40u64)
            .map(|k| {
                let t = k as f64 * 0.01;
                answered(r.answer(
                    "rig-1",
                    // Near the reference (0.2 sin 2πt), so that the outputs stay unsaturated.
                    &sample("rig-1", k, t, &[0.19 * (6.0 * t).sin(), 0.2]),
                ))
            })
            .collect::<Vec<_>>()
    };
    let (trend, held) = (
        run("prediction = { horizon = 6 }"),
        run("prediction = { horizon = 6, trend = 0 }"),
    );
    let mut differ = 0;
    for (a, b) in trend.iter().zip(&held) {
        assert_eq!(a.v, b.v);
        assert_eq!(a.horizon.len(), b.horizon.len());
        differ += usize::from(a.horizon != b.horizon);
    }
    assert!(differ > 10, "{differ} horizons differ");
}

/// A lost sample whose copy comes with the next one: the controller steps on it, and the
/// next command is the one it would have been had the sample arrived (only the counters
/// differ). A copy that does not fit is ignored.
#[test]
fn a_lost_sample_is_recovered_from_the_copy_the_next_one_carries() {
    let text = CONFIG.replace("estimator = { window = 3 }", "estimator = { window = 5 }");
    let make = || Registry::new(ServiceConfig::parse("test.toml", &text).unwrap()).unwrap();
    let (mut seen, mut gap, mut bad) = (make(), make(), make());
    let y = |k: u64| [0.3 * (k as f64 * 0.1).sin(), 0.1 * k as f64];
    let with_applied = |k: u64| {
        let mut s = sample("aero-1", k, k as f64 * 0.01, &y(k));
        s.applied = vec![0.1 * k as f64, -0.2];
        s
    };
    for k in 0..20 {
        for r in [&mut seen, &mut gap, &mut bad] {
            answered(r.answer("aero-1", &with_applied(k)));
        }
    }
    // Sample 20 reaches only `seen`; sample 21 carries it again.
    answered(seen.answer("aero-1", &with_applied(20)));
    let mut next = with_applied(21);
    let lost = with_applied(20);
    next.previous_plant_time = vec![lost.plant_time, 0.19];
    next.previous_outputs = [lost.outputs.clone(), y(19).to_vec()].concat();
    next.previous_applied = [lost.applied.clone(), vec![1.9, -0.2]].concat();
    let a = answered(seen.answer("aero-1", &with_applied(21)));
    let b = answered(gap.answer("aero-1", &next));
    assert_eq!(a.u, b.u, "the command as if sample 20 had arrived");
    // The iP's estimate (the PID channel has none: NaN).
    assert_eq!(a.f_est[0], b.f_est[0]);
    let st = gap.device_status("aero-1").unwrap();
    assert_eq!((st.lost, st.recovered), (1, 1));
    // A copy with a non-finite value is not used: the gap stays.
    let mut broken = next.clone();
    broken.previous_outputs[0] = f64::NAN;
    let c = answered(bad.answer("aero-1", &broken));
    assert_eq!(c.mode, pb::Mode::Control as i32);
    assert_ne!(c.f_est[0], a.f_est[0]);
    let st = bad.device_status("aero-1").unwrap();
    assert_eq!((st.lost, st.recovered), (1, 0));
}

/// A shard handed to a member that never saw its devices: template devices are provisioned
/// there from the handed state and continue where the previous owner left them (a
/// handover is never a restart); a device no template of the receiver matches is refused
/// with its reason, and nothing else changes.
#[test]
fn a_handed_shard_provisions_its_template_devices() {
    let mut a = registry();
    let id = "sim-7";
    for k in 0..30u64 {
        answered(a.answer(id, &sample(id, k, k as f64 * 0.01, &[0.1 * k as f64])));
    }
    let shard = protocol::shard_of(id);
    let state = a.shard_state(shard);
    assert!(state.devices.iter().any(|d| d.snapshot.id == id));
    let mut b = registry();
    assert!(!b.serves(id));
    let restored = b.restore_shard(&state);
    assert!(restored.refused.is_empty(), "{:?}", restored.refused);
    assert!(b.serves(id) && b.device_status(id).unwrap().from_template);
    let next = sample(id, 30, 0.30, &[3.0]);
    let (ca, cb) = (answered(a.answer(id, &next)), answered(b.answer(id, &next)));
    assert_eq!(
        cb.mode,
        pb::Mode::Control as i32,
        "no warm-up after a handover"
    );
    assert_eq!((ca.u, ca.v), (cb.u, cb.v));
    // A receiver without the template refuses the device, saying why.
    let bare = CONFIG.split("[[templates]]").next().unwrap();
    let mut c = Registry::new(ServiceConfig::parse("test.toml", bare).unwrap()).unwrap();
    let refused = c.restore_shard(&state).refused;
    assert_eq!(refused.len(), 1);
    assert!(
        refused[0].1.contains("cannot serve it here"),
        "{:?}",
        refused[0]
    );
    assert!(!c.serves(id));
}

/// A leasing plant (`SAMPLE_FLAGS_LEASE`): the registry stamps every answer with the
/// lease and says whether this member sends it: a claim on a vacant lease, the holder's
/// epoch once it holds it, nothing while another holds it (the state still steps), and a
/// precheck refusal follows the same rule.
#[test]
fn a_leasing_plant_is_answered_by_its_holder_only() {
    use controller_service::registry::Via;
    let mut r = registry();
    r.set_instance(7);
    let leased = |seq: u64, holder: &str, instance: u64, epoch: u64| pb::Sample {
        flags: pb::SampleFlags::Lease as u32,
        lease_holder: holder.into(),
        lease_instance: instance,
        lease_epoch: epoch,
        ..sample("aero-1", seq, seq as f64 * 0.01, &[0.0, 0.5])
    };
    let mut out = pb::Command::default();
    let step = |r: &mut Registry, s: &pb::Sample, out: &mut pb::Command| match r.handle_sample(
        Via::key("aero-1"),
        s,
        1,
        out,
    ) {
        Served::Answered { send, .. } => send,
        other => panic!("not answered: {other:?}"),
    };
    // Vacant at the run's start: everyone is cold, the preferred member claims at once.
    assert!(step(&mut r, &leased(0, "", 0, 0), &mut out));
    assert_eq!(out.mode, pb::Mode::WarmingUp as i32);
    assert_eq!(
        (out.claim, out.lease_epoch, out.lease_instance, out.run_id),
        (true, 1, 7, 42)
    );
    // Vacant again later, still warming up: a cold member lets a warm one claim first.
    for k in 1..3 {
        assert!(!step(&mut r, &leased(k, "", 0, 1), &mut out), "seq {k}");
    }
    // Warm: it claims epoch 2 at once; granted, it answers under it.
    assert!(step(&mut r, &leased(3, "", 0, 1), &mut out));
    assert_eq!((out.claim, out.lease_epoch), (true, 2));
    assert!(step(&mut r, &leased(4, "c1", 7, 2), &mut out));
    assert_eq!((out.claim, out.lease_epoch), (false, 2));
    // Another process with the same id holds it: quiet, though still stepped.
    assert!(!step(&mut r, &leased(5, "c1", 8, 3), &mut out));
    assert!(!step(&mut r, &leased(6, "c2", 0, 4), &mut out));
    let s = r.device_status("aero-1").unwrap();
    assert_eq!((s.samples, s.lease_fenced, s.lease_claims), (7, 2, 2));
    assert_eq!((s.lease_holder.as_str(), s.lease_epoch), ("c2", 4));
    // A refusal is sent by the holder only.
    let (cmd, send) = r
        .refuse_sample("aero-1", &leased(7, "c2", 0, 4), "bad".into(), 1, true)
        .unwrap();
    assert!(!send && cmd.mode == pb::Mode::Rejected as i32);
    let (cmd, send) = r
        .refuse_sample("aero-1", &leased(8, "c1", 7, 5), "bad".into(), 1, true)
        .unwrap();
    assert!(send);
    assert_eq!((cmd.lease_epoch, cmd.run_id), (5, 42));
    // A plant without leases is answered by the preferred member only, unstamped.
    let plain = sample("aero-1", 9, 0.09, &[0.0, 0.5]);
    assert!(step(&mut r, &plain, &mut out));
    assert_eq!((out.claim, out.lease_epoch), (false, 0));
    let via = Via::key("aero-1").preferred(false);
    let plain = sample("aero-1", 10, 0.10, &[0.0, 0.5]);
    assert!(matches!(
        r.handle_sample(via, &plain, 1, &mut out),
        Served::Answered { send: false, .. }
    ));
}

/// With keys, a run id is the plant's own and runs are ordered (`plant::run_id`): a sample
/// of an older run is a captured run played back, answered STALE and changing nothing,
/// while a newer run restarts the device at once. Only a stream of the older run with
/// nothing of the run in force between (a plant whose clock went back) is followed, after
/// 64 samples; without keys, an older run id restarts the device as any other.
#[test]
fn with_keys_an_older_run_is_a_replay_and_a_newer_one_a_restart() {
    let with_run = |seq: u64, run: u64| pb::Sample {
        run_id: run,
        ..sample("aero-1", seq, seq as f64 * 0.01, &[0.0, 0.5])
    };
    let mut r = registry();
    r.set_secret(Some(protocol::auth::Secret::random().unwrap()));
    for k in 1..=10 {
        answered(r.answer("aero-1", &with_run(k, 1000)));
    }
    let starts = r.device_status("aero-1").unwrap().restarts;
    // A replay of run 900 between the plant's own samples: never followed.
    for k in 1..=100u64 {
        let c = answered(r.answer("aero-1", &with_run(k, 900)));
        assert_eq!(c.mode, pb::Mode::Stale as i32, "replayed sample {k}");
        if k % 10 == 0 {
            let own = answered(r.answer("aero-1", &with_run(10 + k / 10, 1000)));
            assert_ne!(own.mode, pb::Mode::Stale as i32);
        }
    }
    assert_eq!(r.device_status("aero-1").unwrap().restarts, starts);
    // A newer run: a restart, at once.
    let c = answered(r.answer("aero-1", &with_run(1, 2000)));
    assert_ne!(c.mode, pb::Mode::Stale as i32);
    assert_eq!(r.device_status("aero-1").unwrap().restarts, starts + 1);
    // An older run alone, 64 samples in a row: the plant is there, followed.
    let modes: Vec<i32> = (1..=64u64)
        .map(|k| answered(r.answer("aero-1", &with_run(k, 1500))).mode)
        .collect();
    assert!(modes[..63].iter().all(|&m| m == pb::Mode::Stale as i32));
    assert_ne!(modes[63], pb::Mode::Stale as i32);
    assert_eq!(r.device_status("aero-1").unwrap().restarts, starts + 2);
    // Without keys, an older run id is a restart like any other.
    let mut open = registry();
    answered(open.answer("aero-1", &with_run(1, 1000)));
    let starts = open.device_status("aero-1").unwrap().restarts;
    let c = answered(open.answer("aero-1", &with_run(1, 900)));
    assert_ne!(c.mode, pb::Mode::Stale as i32);
    assert_eq!(open.device_status("aero-1").unwrap().restarts, starts + 1);
}

/// Nothing acknowledged is lost, the registry's part: a change made while holding the
/// plant's lease is numbered after the ones before it; a handed state replaces a member's
/// only if it is not older; a change to hold is taken only from the member that holds the
/// lease as the receiver last heard it; and the holder's state puts the receiver in step.
#[test]
fn a_newer_state_wins_and_a_change_is_held_only_from_the_holder() {
    use controller_service::registry::Via;
    let member = |id: &str| {
        let mut cfg = ServiceConfig::parse("test.toml", CONFIG).unwrap();
        cfg.controller_id = id.into();
        let mut r = Registry::new(cfg).unwrap();
        let fleet: std::collections::BTreeSet<String> =
            ["c1", "c2", "c3"].iter().map(|s| s.to_string()).collect();
        r.set_view(&fleet);
        r
    };
    let leased = |seq: u64, holder: &str, epoch: u64| pb::Sample {
        flags: pb::SampleFlags::Lease as u32,
        lease_holder: holder.into(),
        lease_epoch: epoch,
        ..sample("aero-1", seq, seq as f64 * 0.01, &[0.0, 0.5])
    };
    let step = |r: &mut Registry, s: &pb::Sample| {
        let mut out = pb::Command::default();
        r.handle_sample(Via::key("aero-1"), s, 1, &mut out);
    };
    let kp = |kp: f64| {
        let mut u = pb::ChannelUpdate::default();
        *protocol::convert::update_field(&mut u, "kp").unwrap() = Some(kp);
        pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            updates: vec![u],
            ..Default::default()
        }
    };
    let shard = protocol::shard_of("aero-1");
    let (mut a, mut b, mut c) = (member("c1"), member("c2"), member("c3"));
    // c1 claims the vacant lease (a lease names only a claimant: `Claimer` commands only
    // with a state that claimed it), and the plant grants it.
    step(&mut a, &leased(0, "", 0));
    for r in [&mut a, &mut b, &mut c] {
        step(r, &leased(1, "c1", 1));
    }
    let before = a.devices_state(shard, &["aero-1"]);
    assert!(!b.in_step("aero-1"), "b never got the holder's state");
    // c1 holds the lease: its change is numbered, and b, its partner, holds it.
    assert!(a.configure("aero-1", &kp(3.0)).accepted);
    let held = b.hold_shard(&a.devices_state(shard, &["aero-1"]));
    assert_eq!((held.restored, held.refused.len()), (1, 0), "{held:?}");
    assert_eq!(b.config_of("aero-1"), a.config_of("aero-1"));
    assert!(b.in_step("aero-1"), "the holder's state puts it in step");
    // The state from before the change never replaces the newer one.
    let stale = b.restore_shard(&before);
    assert_eq!(stale.restored, 0);
    assert!(stale.refused[0].1.contains("newer"), "{stale:?}");
    assert_eq!(b.config_of("aero-1"), a.config_of("aero-1"));
    // A change made by a member that does not hold the lease is not numbered, and is not
    // held by a partner that heard another holder.
    assert!(c.configure("aero-1", &kp(9.0)).accepted);
    let forged = b.hold_shard(&c.devices_state(shard, &["aero-1"]));
    assert_eq!(forged.restored, 0);
    assert!(forged.refused[0].1.contains("does not hold"), "{forged:?}");
    // Nor is a change by the former holder once a later holder was heard.
    step(&mut b, &leased(2, "c3", 2));
    assert!(a.configure("aero-1", &kp(4.0)).accepted);
    let late = b.hold_shard(&a.devices_state(shard, &["aero-1"]));
    assert_eq!(late.restored, 0);
    assert!(late.refused[0].1.contains("heard here since"), "{late:?}");
    assert!(!b.in_step("aero-1"), "it missed epoch 2's holder");
}

/// A member silent for more than half its session's liveliness lease (paused, or no
/// sample reached it) may have been dropped from the holder's view meanwhile, and the
/// holder acknowledges changes without it then: it counts itself behind until a holder's
/// state reaches it (the fleet's simulation, seed 138492: 680 ms under a 500 ms lease).
#[test]
fn a_silence_over_half_the_liveliness_lease_leaves_a_member_behind() {
    use controller_service::registry::Via;
    let ms = 1_000_000u64;
    let run = |lease: Option<std::time::Duration>, silence_ms: u64| {
        let mut cfg = ServiceConfig::parse("test.toml", CONFIG).unwrap();
        cfg.controller_id = "c2".into();
        let mut r = Registry::new(cfg).unwrap();
        r.set_view(&["c1", "c2"].iter().map(|s| s.to_string()).collect());
        if let Some(lease) = lease {
            r.set_liveliness_lease(lease);
        }
        let mut t = ms;
        let step = |r: &mut Registry, seq: u64, t: u64| {
            let s = pb::Sample {
                flags: pb::SampleFlags::Lease as u32,
                lease_holder: "c1".into(),
                lease_epoch: 1,
                ..sample("aero-1", seq, seq as f64 * 0.01, &[0.0, 0.5])
            };
            r.handle_sample(Via::key("aero-1"), &s, t, &mut pb::Command::default());
        };
        step(&mut r, 0, t);
        // The holder's state: in step under epoch 1.
        let holder = {
            let mut cfg = ServiceConfig::parse("test.toml", CONFIG).unwrap();
            cfg.controller_id = "c1".into();
            let mut a = Registry::new(cfg).unwrap();
            a.set_view(&["c1", "c2"].iter().map(|s| s.to_string()).collect());
            let vacant = pb::Sample {
                flags: pb::SampleFlags::Lease as u32,
                ..sample("aero-1", 0, 0.0, &[0.0, 0.5])
            };
            a.handle_sample(Via::key("aero-1"), &vacant, t, &mut pb::Command::default());
            let granted = pb::Sample {
                flags: pb::SampleFlags::Lease as u32,
                lease_holder: "c1".into(),
                lease_epoch: 1,
                ..sample("aero-1", 1, 0.01, &[0.0, 0.5])
            };
            a.handle_sample(Via::key("aero-1"), &granted, t, &mut pb::Command::default());
            a.devices_state(protocol::shard_of("aero-1"), &["aero-1"])
        };
        r.hold_shard(&holder);
        assert!(r.in_step("aero-1"), "the holder's state puts it in step");
        for seq in 1..10 {
            t += 10 * ms;
            step(&mut r, seq, t);
        }
        t += silence_ms * ms;
        step(&mut r, 10 + silence_ms / 10, t);
        r.in_step("aero-1")
    };
    // zenoh's default lease (10 s): a second of silence is the limit.
    assert!(run(None, 900), "900 ms under the default");
    assert!(!run(None, 1100), "1.1 s under the default");
    // The deployment's 1 s lease: half of it.
    let second = Some(std::time::Duration::from_secs(1));
    assert!(run(second, 450), "450 ms under a 1 s lease");
    assert!(!run(second, 680), "680 ms under a 1 s lease");
}

/// A device of two AERO-like channels (iP on a first-order model, iPD on a second-order
/// one, +-24 V), after ten samples 10 ms apart: its period is known.
fn aero_with_period() -> Registry {
    let text = r#"
controller_id = "c1"
[[devices]]
id = "aero-1"
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 1.0, kp = 2.0 }, estimator = { window = 3 } }
output = { dead_zone = 1.0, min = -24.0, max = 24.0 }
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ipd", order = "two", alpha = 1.0, kp = 9.0, kd = 3.0 }, estimator = { window = 3 } }
output = { min = -24.0, max = 24.0 }
"#;
    let mut r = Registry::new(ServiceConfig::parse("test.toml", text).unwrap()).unwrap();
    for k in 0..10u64 {
        answered(r.answer("aero-1", &sample("aero-1", k, k as f64 * 0.01, &[0.0, 0.0])));
    }
    r
}

/// A partial change of one channel of `aero-1`.
type Edit = fn(&mut pb::ChannelUpdate);

fn set(r: &mut Registry, ch: u32, f: Edit) -> pb::ConfigReply {
    let mut u = pb::ChannelUpdate {
        channel: ch,
        ..Default::default()
    };
    f(&mut u);
    r.configure(
        "aero-1",
        &pb::ConfigRequest {
            version: PROTOCOL_VERSION,
            updates: vec![u],
            ..Default::default()
        },
    )
}

/// The issue's absurd settings, each refused with its reason from the registry (every
/// client's way in), the configuration in force unchanged; a sane change still accepted;
/// only the values a change moves are checked.
#[test]
fn absurd_gains_are_refused_and_change_nothing() {
    let mut r = aero_with_period();
    let before = r.config_of("aero-1").unwrap();
    let cases: [(u32, Edit, &str); 6] = [
        (
            1,
            |u| u.kp = Some(1e308),
            "kp = 1e308 is outside [-4e4, 4e4] ((2/h)^2",
        ),
        (1, |u| u.kd = Some(1e308), "kd = 1e308"),
        (
            0,
            |u| u.alpha = Some(1e-300),
            "alpha = 1e-300 is outside |x| in [1e-6, 1e6]",
        ),
        (
            0,
            |u| u.dead_zone = Some(1e308),
            "dead_zone = 1e308 is outside [0, 24]",
        ),
        // Finite and inside the table, but the loop at 10 ms diverges beyond 2/h = 200.
        (
            0,
            |u| u.kp = Some(250.0),
            "kp = 250 is outside [-200, 200] ((2/h)^1",
        ),
        (
            1,
            |u| u.kd = Some(250.0),
            "kd = 250 is outside [-200, 200] ((2/h)^1",
        ),
    ];
    for (ch, f, want) in cases {
        let reply = set(&mut r, ch, f);
        assert!(!reply.accepted, "{want}");
        assert!(reply.reason.contains(want), "{want}: {}", reply.reason);
        assert_eq!(r.config_of("aero-1").unwrap(), before, "{want}");
    }
    // A sane change is still accepted, and a value just inside a derived bound too.
    assert!(set(&mut r, 0, |u| u.kp = Some(150.0)).accepted);
    assert!(set(&mut r, 0, |u| u.dead_zone = Some(8.0)).accepted);
    // The envelope narrowed to +-5 V: the dead zone in force (8) is now beyond its bound,
    // which blocks no change of another value, only a move of the dead zone itself.
    let limits = |m: f64| pb::ChannelLimits {
        min: Some(-m),
        max: Some(m),
        rate_limit: None,
    };
    let narrow = pb::EnvelopeRequest {
        version: PROTOCOL_VERSION,
        envelope: Some(pb::Envelope {
            channels: vec![limits(5.0), limits(5.0)],
        }),
        reason: "test".into(),
    };
    assert!(r.change_envelope("aero-1", &narrow).accepted);
    let kp = set(&mut r, 0, |u| u.kp = Some(100.0));
    assert!(kp.accepted, "{}", kp.reason);
    let dz = set(&mut r, 0, |u| u.dead_zone = Some(6.0));
    assert!(
        dz.reason.contains("dead_zone = 6 is outside [0, 5]"),
        "{}",
        dz.reason
    );
}

/// Absurd references: refused with the piece and the reason, nothing changed; a sane one
/// accepted, and the samples after it answered (the reference stays finite).
#[test]
fn absurd_references_are_refused_and_change_nothing() {
    use mfc::trajectory::Piece;
    let mut r = aero_with_period();
    let refs = |pieces: Vec<Piece>| pb::ReferenceUpdate {
        version: PROTOCOL_VERSION,
        reference: Some(protocol::convert::reference_to_pb(
            &[pieces, vec![Piece::Constant { value: 0.0 }]],
            0.0,
        )),
    };
    let sine = |period: f64| Piece::Sine {
        amplitude: 1.0,
        period,
        phase: 0.0,
        start: 0.0,
        end: f64::INFINITY,
        fade: 0.0,
    };
    let before = r.config_of("aero-1").unwrap();
    for (pieces, want) in [
        (vec![Piece::Constant { value: 1e308 }], "reaches 1e308"),
        (
            vec![sine(1e-300)],
            "period: 1e-300 s is shorter than 0.02 s",
        ),
        (
            vec![sine(0.015)],
            "shorter than 0.02 s (two of the device's periods)",
        ),
        (
            vec![Piece::Ramp {
                start: 0.0,
                end: 1e12,
                slope: 1.0,
            }],
            "end: 1e12 s is beyond",
        ),
    ] {
        let reply = r.set_reference("aero-1", &refs(pieces));
        assert!(
            !reply.accepted && reply.reason.contains(want),
            "{want}: {}",
            reply.reason
        );
        assert_eq!(r.config_of("aero-1").unwrap(), before, "{want}");
    }
    assert!(r.set_reference("aero-1", &refs(vec![sine(0.05)])).accepted);
    for k in 10..20u64 {
        let c = answered(r.answer("aero-1", &sample("aero-1", k, k as f64 * 0.01, &[0.0, 0.0])));
        assert_eq!(c.mode, pb::Mode::Control as i32, "{c:?}");
    }
}

/// The file may widen or narrow a bound.
#[test]
fn the_file_widens_or_narrows_a_bound() {
    let text = r#"
controller_id = "c1"
[[devices]]
id = "aero-1"
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 1.0, kp = 2.0 }, estimator = { window = 3 } }
bounds = { kp = [0.0, 1000.0], alpha = [0.5, 2.0] }
"#;
    let mut r = Registry::new(ServiceConfig::parse("test.toml", text).unwrap()).unwrap();
    for k in 0..10u64 {
        answered(r.answer("aero-1", &sample("aero-1", k, k as f64 * 0.01, &[0.0])));
    }
    // Wider than the derived 200: the file decides.
    let wide = set(&mut r, 0, |u| u.kp = Some(500.0));
    assert!(wide.accepted, "{}", wide.reason);
    let narrow = set(&mut r, 0, |u| u.alpha = Some(3.0));
    let want = "alpha = 3 is outside [0.5, 2] (set in the service's file";
    assert!(
        !narrow.accepted && narrow.reason.contains(want),
        "{}",
        narrow.reason
    );
    // A value inside the file's bound: accepted.
    let other = set(&mut r, 0, |u| u.alpha = Some(1.5));
    assert!(other.accepted, "{}", other.reason);
}

/// A REJECTED sample arrived: the gap it leaves is not counted as lost; a sample that
/// never came is.
#[test]
fn rejected_samples_are_not_counted_as_lost() {
    let mut r = registry();
    for k in 0..5u64 {
        answered(r.answer("aero-1", &sample("aero-1", k, k as f64 * 0.01, &[0.0, 0.0])));
    }
    // Ten samples with a NaN output: answered REJECTED.
    for k in 5..15u64 {
        let c = answered(r.answer(
            "aero-1",
            &sample("aero-1", k, k as f64 * 0.01, &[f64::NAN, 0.0]),
        ));
        assert_eq!(c.mode, pb::Mode::Rejected as i32);
    }
    // 15 is lost on the way; 16 is good.
    answered(r.answer("aero-1", &sample("aero-1", 16, 0.16, &[0.0, 0.0])));
    let st = r.device_status("aero-1").unwrap();
    assert_eq!((st.rejected, st.lost), (10, 1), "{st:?}");
}

/// A slot remembered for a position of a gateway's batch serves only the device it holds
/// now: a hint that names another device's slot, or no slot at all, finds the sample's
/// own device by its id, and the hint is set to that device's slot.
#[test]
fn a_remembered_slot_serves_only_its_own_device() {
    use controller_service::registry::Via;

    let mut r = registry();
    let mut out = pb::Command::default();
    let (mut one, mut two) = (None, None);
    for (k, (id, slot)) in [("sim-1", &mut one), ("sim-2", &mut two)]
        .into_iter()
        .enumerate()
    {
        let s = sample(id, 1, 0.01, &[0.0]);
        let served = r.handle_sample_at(slot, Via::key(id), &s, k as u64, &mut out);
        assert!(
            matches!(served, Served::Answered { .. }),
            "{id}: {served:?}"
        );
    }
    let (one_slot, two_slot) = (one.unwrap(), two.unwrap());
    assert_ne!(one_slot, two_slot);
    // sim-1's sample with sim-2's slot, then with a slot that does not exist.
    for (seq, hint) in [(2, Some(two_slot)), (3, Some(u32::MAX))] {
        let mut hint = hint;
        let s = sample("sim-1", seq, 0.01 * seq as f64, &[0.0]);
        let served = r.handle_sample_at(&mut hint, Via::key("sim-1"), &s, 0, &mut out);
        assert!(matches!(served, Served::Answered { .. }), "{served:?}");
        assert_eq!(hint, Some(one_slot), "the hint set to sim-1's own slot");
        assert_eq!(out.device_id, "sim-1");
        assert_eq!(out.seq, seq);
    }
    let samples = |id| r.device_status(id).unwrap().samples;
    assert_eq!((samples("sim-1"), samples("sim-2")), (3, 1));
    // A hint for an id that is not served stays unset, and the sample is refused.
    let mut hint = Some(one_slot);
    let s = sample("nobody", 1, 0.01, &[0.0]);
    let served = r.handle_sample_at(&mut hint, Via::key("nobody"), &s, 0, &mut out);
    assert!(matches!(served, Served::Unknown), "{served:?}");
    assert_eq!(hint, None);
}
