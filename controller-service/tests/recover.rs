//! A restart puts every acknowledged change back in force, and an edited file is a change
//! of its own: the registry's side of "acknowledged means durable" (`Registry::trial`,
//! `Registry::commit`, `Registry::recover`, `registry::merge`), without a network.

use std::collections::BTreeMap;

use controller_service::journal::State;
use controller_service::registry::merge;
use controller_service::{Registry, ServiceConfig};
use protocol::{pb, PROTOCOL_VERSION};

const FILE: &str = r#"
controller_id = "c1"
[[devices]]
id = "rig"
[[devices.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 1.0, kp = 2.0 }, estimator = { window = 3 } }
envelope = { min = -24.0, max = 24.0 }
reference = [{ kind = "constant", value = 0.5 }]
[[devices.channels]]
law = { law = "pid", params = { kp = 1.0, ki = 0.5 } }
envelope = { min = -10.0, max = 10.0 }
[[templates]]
pattern = "tpl-$*"
[[templates.channels]]
law = { law = "pid", params = { kp = 2.0 } }
"#;

fn registry(text: &str) -> Registry {
    Registry::new(ServiceConfig::parse("test.toml", text).unwrap()).unwrap()
}

fn set(r: &mut Registry, dev: &str, ch: u32, what: &str, v: f64) -> pb::ConfigReply {
    let mut u = pb::ChannelUpdate {
        channel: ch,
        ..Default::default()
    };
    *protocol::convert::update_field(&mut u, what).unwrap() = Some(v);
    let req = pb::ConfigRequest {
        version: PROTOCOL_VERSION,
        updates: vec![u],
        ..Default::default()
    };
    r.configure(dev, &req)
}

fn param(c: &pb::DeviceConfig, ch: usize, what: &str) -> f64 {
    use pb::channel_config::Law;
    match (&c.channels[ch].law, what) {
        (Some(Law::Intelligent(l)), "kp") => l.kp,
        (Some(Law::Intelligent(l)), "alpha") => l.alpha,
        (Some(Law::Pid(p)), "kp") => p.kp,
        (Some(Law::Pid(p)), "ki") => p.ki,
        other => panic!("{other:?}"),
    }
}

fn max(c: &pb::DeviceConfig, ch: usize) -> f64 {
    c.envelope.as_ref().unwrap().channels[ch].max.unwrap()
}

/// The journaled state of `rig` after `changes` were made on a registry built from `file`.
fn journaled(file: &str, changes: impl FnOnce(&mut Registry)) -> BTreeMap<String, State> {
    let mut r = registry(file);
    changes(&mut r);
    let (config, version) = r.state_of("rig").unwrap();
    let file = r.file_config_of("rig").unwrap();
    BTreeMap::from([(
        "rig".to_string(),
        State {
            config,
            version,
            file,
        },
    )])
}

#[test]
fn a_tried_change_changes_nothing_and_is_made_as_tried() {
    let mut r = registry(FILE);
    let before = r.state_of("rig").unwrap();
    let (reply, trial) = r.trial("rig", |r| set(r, "rig", 0, "kp", 7.0));
    assert!(reply.accepted, "{}", reply.reason);
    let trial = trial.unwrap();
    assert_eq!(
        r.state_of("rig").unwrap(),
        before,
        "nothing changed by the trial"
    );
    assert_eq!(param(&trial.after.0, 0, "kp"), 7.0);
    assert_eq!(trial.changes.len(), 1);
    assert_eq!(trial.changes[0].what, "channel 0 kp");
    // A refusal is a refusal, and no trial; it is counted as any refusal is.
    let (reply, none) = r.trial("rig", |r| set(r, "rig", 0, "kp", 1e9));
    assert!(!reply.accepted && none.is_none());
    assert_eq!(r.device_status("rig").unwrap().last_error, reply.reason);
    // Made, it leaves what was tried.
    let made = r
        .commit("rig", &trial, |r| set(r, "rig", 0, "kp", 7.0))
        .unwrap();
    assert!(made.accepted);
    assert_eq!(r.state_of("rig").unwrap(), trial.after);
    // The same trial again finds the device moved on: withdrawn, nothing changes.
    let now = r.state_of("rig").unwrap();
    let again = r.commit("rig", &trial, |r| set(r, "rig", 0, "kp", 7.0));
    assert!(again.unwrap_err().contains("changed while"));
    assert_eq!(r.state_of("rig").unwrap(), now);
    // A change made otherwise than tried is undone.
    let (_, t) = r.trial("rig", |r| set(r, "rig", 0, "kp", 3.0));
    let odd = r.commit("rig", &t.unwrap(), |r| set(r, "rig", 0, "kp", 4.0));
    assert!(odd.unwrap_err().contains("another state"));
    assert_eq!(r.state_of("rig").unwrap(), now);
}

#[test]
fn a_restart_puts_the_journaled_state_back_over_the_file() {
    let states = journaled(FILE, |r| {
        assert!(set(r, "rig", 0, "kp", 12.0).accepted);
        assert!(set(r, "rig", 1, "ki", 0.25).accepted);
    });
    let mut r = registry(FILE);
    let rec = r.recover(&states);
    assert_eq!((rec.restored, rec.file_changes.len()), (1, 0));
    let c = r.config_of("rig").unwrap();
    assert_eq!((param(&c, 0, "kp"), param(&c, 1, "ki")), (12.0, 0.25));
    assert_eq!(r.state_of("rig").unwrap().0, states["rig"].config);
}

#[test]
fn an_edited_file_wins_only_for_what_it_changed_and_says_so() {
    // Live: kp 12 on channel 0, envelope of channel 1 narrowed to 6.
    let states = journaled(FILE, |r| {
        assert!(set(r, "rig", 0, "kp", 12.0).accepted);
        let env = pb::EnvelopeRequest {
            version: PROTOCOL_VERSION,
            envelope: Some(pb::Envelope {
                channels: vec![
                    pb::ChannelLimits {
                        min: Some(-24.0),
                        max: Some(24.0),
                        rate_limit: None,
                    },
                    pb::ChannelLimits {
                        min: Some(-10.0),
                        max: Some(6.0),
                        rate_limit: None,
                    },
                ],
            }),
            reason: "test".into(),
        };
        assert!(r.change_envelope("rig", &env).accepted);
    });
    // The file, meanwhile: alpha 0.5 on channel 0 (kp untouched), kp 3 on channel 1.
    let edited = FILE
        .replace("alpha = 1.0, kp = 2.0", "alpha = 0.5, kp = 2.0")
        .replace("kp = 1.0, ki = 0.5", "kp = 3.0, ki = 0.5");
    let mut r = registry(&edited);
    let rec = r.recover(&states);
    assert_eq!(rec.restored, 0);
    let [fc] = &rec.file_changes[..] else {
        panic!("{rec:?}")
    };
    let c = r.config_of("rig").unwrap();
    assert_eq!(param(&c, 0, "kp"), 12.0, "live, the file left it");
    assert_eq!(param(&c, 0, "alpha"), 0.5, "the file's edit");
    assert_eq!(param(&c, 1, "kp"), 3.0, "the file's edit");
    assert_eq!(max(&c, 1), 6.0, "the live narrowing, the file left it");
    // The record to journal: the state in force, the new file as its base, what moved.
    assert_eq!(fc.state.config, c);
    assert_eq!(fc.state.file, r.file_config_of("rig").unwrap());
    let moved: Vec<_> = fc
        .changes
        .iter()
        .map(|c| (c.what.as_str(), c.old.as_str(), c.new.as_str()))
        .collect();
    assert_eq!(
        moved,
        [("channel 0 alpha", "1", "0.5"), ("channel 1 kp", "1", "3")]
    );
    // The next start with that record and the same file: as it is, no change.
    let next = BTreeMap::from([("rig".to_string(), fc.state.clone())]);
    let mut again = registry(&edited);
    let rec = again.recover(&next);
    assert_eq!((rec.restored, rec.file_changes.len()), (1, 0));
    assert_eq!(again.config_of("rig").unwrap(), c);
}

#[test]
fn a_file_that_changes_a_law_or_the_channels_replaces_what_it_changed_whole() {
    let states = journaled(FILE, |r| {
        assert!(set(r, "rig", 0, "kp", 12.0).accepted);
        assert!(set(r, "rig", 1, "kp", 4.0).accepted);
    });
    // Channel 1 becomes an iP in the file: its law is the file's, whole; channel 0 keeps
    // its live kp.
    let edited = FILE.replace(
        r#"law = { law = "pid", params = { kp = 1.0, ki = 0.5 } }"#,
        r#"law = { law = "intelligent", params = { kind = "ip", alpha = 2.0, kp = 1.5 }, estimator = { window = 3 } }"#,
    );
    let mut r = registry(&edited);
    let rec = r.recover(&states);
    assert_eq!(rec.file_changes.len(), 1);
    let c = r.config_of("rig").unwrap();
    assert_eq!(param(&c, 0, "kp"), 12.0);
    assert_eq!((param(&c, 1, "kp"), param(&c, 1, "alpha")), (1.5, 2.0));
    // One channel less in the file: the file's whole, and the record says why.
    let fewer = FILE.replace(
        "[[devices.channels]]\nlaw = { law = \"pid\", params = { kp = 1.0, ki = 0.5 } }\nenvelope = { min = -10.0, max = 10.0 }\n",
        "",
    );
    let mut r = registry(&fewer);
    let rec = r.recover(&states);
    let [fc] = &rec.file_changes[..] else {
        panic!("{rec:?}")
    };
    assert!(fc.how.contains("whole"), "{}", fc.how);
    assert_eq!(
        r.config_of("rig").unwrap(),
        r.file_config_of("rig").unwrap()
    );
}

#[test]
fn journaled_devices_of_templates_come_back_and_others_are_named() {
    let mut r = registry(FILE);
    // A template device exists once provisioned; its changed state is journaled.
    let mut t = registry(FILE);
    let s = pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: "tpl-7".into(),
        seq: 1,
        plant_time: 0.01,
        outputs: vec![0.0],
        run_id: 1,
        ..Default::default()
    };
    let mut cmd = pb::Command::default();
    t.handle_sample(
        controller_service::registry::Via::key("tpl-7"),
        &s,
        1,
        &mut cmd,
    );
    assert!(set(&mut t, "tpl-7", 0, "kp", 5.0).accepted);
    let (config, version) = t.state_of("tpl-7").unwrap();
    let file = t.file_config_of("tpl-7").unwrap();
    let mut states = BTreeMap::from([(
        "tpl-7".to_string(),
        State {
            config,
            version,
            file: file.clone(),
        },
    )]);
    states.insert(
        "gone".into(),
        State {
            config: file.clone(),
            version: Default::default(),
            file,
        },
    );
    let rec = r.recover(&states);
    assert_eq!(rec.restored, 1);
    assert_eq!(
        param(&r.config_of("tpl-7").unwrap(), 0, "kp"),
        5.0,
        "provisioned at the start, as journaled"
    );
    let [(gone, why)] = &rec.dropped[..] else {
        panic!("{rec:?}")
    };
    assert_eq!(gone, "gone");
    assert!(why.contains("not served"), "{why}");
}

/// The merge's rules on their own: per setting, the file's where the file moved it.
#[test]
fn merge_takes_each_setting_from_whoever_moved_it() {
    let base = registry(FILE).config_of("rig").unwrap();
    let with = |f: &dyn Fn(&mut Registry)| {
        let mut r = registry(FILE);
        f(&mut r);
        r.config_of("rig").unwrap()
    };
    let live = with(&|r| {
        set(r, "rig", 0, "kp", 12.0);
    });
    assert_eq!(
        merge(&base, &live, &base).unwrap(),
        live,
        "an unedited file keeps the live state"
    );
    assert_eq!(
        merge(&base, &base, &live).unwrap(),
        live,
        "no live change: the file's"
    );
    let file = with(&|r| {
        set(r, "rig", 0, "kp", 3.0);
    });
    assert_eq!(
        param(&merge(&base, &live, &file).unwrap(), 0, "kp"),
        3.0,
        "both moved it: the file's"
    );
    let reference = with(&|r| {
        let u = pb::ReferenceUpdate {
            version: PROTOCOL_VERSION,
            reference: Some(pb::Reference {
                channels: vec![
                    pb::ChannelReference {
                        pieces: vec![pb::Piece {
                            shape: Some(pb::piece::Shape::Constant(pb::Constant { value: 0.1 })),
                        }],
                    },
                    pb::ChannelReference::default(),
                ],
                start_time: 3.0,
            }),
        };
        assert!(r.set_reference("rig", &u).accepted);
    });
    let m = merge(&base, &reference, &file).unwrap();
    assert_eq!(
        m.reference, reference.reference,
        "the live reference, the file left it"
    );
    assert_eq!(param(&m, 0, "kp"), 3.0);
}
