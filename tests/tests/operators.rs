//! Operators with names and roles, and every change on the record: the real service in a
//! process of its own, with an `[access]` section and an audit file, asked over real
//! Zenoh sessions by operators who name themselves in their request keys (as `mfcctl
//! --operator` does; under a deployment the router holds each certificate to its own
//! name, which the multi-host test shows).
//!
//! Asserted exactly: who may do what (a viewer reads and changes nothing, an operator
//! changes its own devices only, a widening needs an admin, an unlisted or unnamed asker
//! is refused), that a wildcard status query returns only what the asker may see, that
//! every decision is an audit entry (who, role, what moved from what to what, the result
//! and why), that the counters and the file agree with the entries, and that the trail
//! survives a restart of the service.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use protocol::{encode, keys, pb, PROTOCOL_VERSION};
use system_tests::{query, scratch_dir, SERIAL};
use transport::ops::{self, OpError, Operator};
use zenoh::Session;

const CONFIG: &str = r#"
controller_id = "c-ops"
audit = { path = "audit/c-ops.jsonl", rotate_bytes = 4096, keep = 3 }

[access]
verified = true
[[access.operators]]
name = "alice"
role = "operator"
devices = ["aero-1"]
[[access.operators]]
name = "vera"
role = "viewer"
[[access.operators]]
name = "root"
role = "admin"

[[devices]]
id = "aero-1"
[[devices.channels]]
law = { law = "pid", params = { kp = 4.0, ki = 8.0 } }
output = { min = -10.0, max = 10.0 }
envelope = { min = -10.0, max = 10.0 }

[[devices]]
id = "aero-2"
[[devices.channels]]
law = { law = "pid", params = { kp = 2.0 } }
output = { min = -5.0, max = 5.0 }
"#;

const T: Duration = Duration::from_secs(3);

struct Reaped(Child);
impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn spawn_service(dir: &std::path::Path, endpoint: &str, log: &str) -> Reaped {
    Command::new(env!("CARGO_BIN_EXE_service-under-test"))
        .args(["--config", dir.join("service.toml").to_str().unwrap()])
        .args(["--listen", endpoint, "--no-multicast-scouting"])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join(log)).unwrap())
        .spawn()
        .map(Reaped)
        .unwrap()
}

async fn status(s: &Session) -> Option<pb::ServiceStatus> {
    query(s, keys::service_status("c-ops"), None).await.ok()
}

/// Poll the service status until `done` holds or 30 s pass; the last status either way.
async fn settle(s: &Session, done: impl Fn(&pb::ServiceStatus) -> bool) -> pb::ServiceStatus {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(st) = status(s).await {
            if done(&st) || tokio::time::Instant::now() > deadline {
                return st;
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the service never answered"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn op(s: &Session, name: Option<&str>) -> Operator {
    Operator {
        session: s.clone(),
        key: None,
        name: name.map(str::to_string),
    }
}

/// `who` sets `field` of aero-N's channel 0; the refusal's reason, or `None` if accepted.
async fn set(s: &Session, who: Option<&str>, dev: &str, field: &str) -> Option<String> {
    let u = ops::parse_update(0, &[field.to_string()]).unwrap();
    match ops::update(&op(s, who), dev, u, T).await {
        Ok(_) => None,
        Err(OpError::Refused { reason, .. }) => Some(reason),
        Err(e) => panic!("{who:?} set {field}: {e}"),
    }
}

async fn envelope(s: &Session, who: &str, min: f64, max: f64) -> Option<String> {
    let env = pb::Envelope {
        channels: vec![pb::ChannelLimits {
            min: Some(min),
            max: Some(max),
            rate_limit: None,
        }],
    };
    match ops::change_envelope(&op(s, Some(who)), "aero-1", env, "test", T).await {
        Ok(_) => None,
        Err(OpError::Refused { reason, .. }) => Some(reason),
        Err(e) => panic!("{who} envelope: {e}"),
    }
}

/// A reference put (no reply) under `who`'s name.
async fn put_reference(s: &Session, who: &str, value: f64) {
    let u = pb::ReferenceUpdate {
        version: PROTOCOL_VERSION,
        reference: Some(protocol::convert::reference_to_pb(
            &[vec![mfc::trajectory::Piece::Constant { value }]],
            0.0,
        )),
    };
    s.put(keys::by(&keys::reference("aero-1"), who), encode(&u))
        .await
        .unwrap();
}

/// The audit entries of `dev` as `vera` sees them: (operator, accepted, action).
async fn trail(s: &Session, dev: &str) -> Vec<pb::AuditEntry> {
    let logs = ops::audit(&op(s, Some("vera")), Some(dev), T)
        .await
        .unwrap();
    logs.into_iter().next().unwrap().entries
}

fn expect_refusal(got: Option<String>, says: &str) {
    let why = got.unwrap_or_else(|| panic!("accepted; expected a refusal saying {says:?}"));
    assert!(why.contains(says), "{why:?} does not say {says:?}");
}

/// Every request the test makes, in order; the entries must say exactly this.
async fn make_requests(s: &Session, dir: &std::path::Path) {
    // Accepted: an operator's gain on its own device; its entry is fsynced before the
    // reply comes, so the file holds it the moment the operator is told.
    assert_eq!(set(s, Some("alice"), "aero-1", "kp=5").await, None);
    let file = std::fs::read_to_string(dir.join("audit/c-ops.jsonl")).unwrap_or_default();
    assert!(
        file.lines()
            .any(|l| l.contains("\"operator\":\"alice\"") && l.contains("channel 0 kp")),
        "acknowledged before it was on the record: {file:?}"
    );
    // Refused, each with its reason.
    expect_refusal(
        set(s, Some("vera"), "aero-1", "kp=6").await,
        "is a viewer; this needs an operator",
    );
    expect_refusal(
        set(s, Some("mallory"), "aero-1", "kp=6").await,
        "\"mallory\" is not listed",
    );
    expect_refusal(set(s, None, "aero-1", "kp=6").await, "named operators only");
    expect_refusal(
        set(s, Some("alice"), "aero-2", "kp=6").await,
        "may not act on device \"aero-2\"",
    );
    expect_refusal(set(s, Some("alice"), "aero-1", "kp=1e308").await, "kp");
    // Widening needs an admin, and an admin still needs the file's permission.
    expect_refusal(
        envelope(s, "alice", -12.0, 12.0).await,
        "this needs an admin",
    );
    expect_refusal(
        envelope(s, "root", -12.0, 12.0).await,
        "allow_remote_widening",
    );
    assert_eq!(envelope(s, "alice", -8.0, 8.0).await, None);
    // Reference puts: applied or refused silently, recorded either way.
    put_reference(s, "alice", 0.5).await;
    put_reference(s, "vera", 0.7).await;
}

/// Reads: by role and devices; a wildcard status query returns what the asker may see.
async fn reads_by_role(s: &Session) {
    // Reads: by role and devices.
    assert!(ops::config(&op(s, Some("vera")), "aero-2", T).await.is_ok());
    let e = ops::config(&op(s, Some("alice")), "aero-2", T)
        .await
        .unwrap_err();
    assert!(e.to_string().contains("may not act on device"), "{e}");
    let e = ops::config(&op(s, Some("mallory")), "aero-1", T)
        .await
        .unwrap_err();
    assert!(e.to_string().contains("not listed"), "{e}");
    // A wildcard status query returns what the asker may see, and nothing else.
    for (who, sees) in [
        ("alice", vec!["aero-1"]),
        ("vera", vec!["aero-1", "aero-2"]),
    ] {
        let key = keys::by(&keys::all_devices("status"), who);
        let replies = s.get(&key).timeout(T).await.unwrap();
        let mut got = Vec::new();
        while let Ok(r) = replies.recv_async().await {
            let st: pb::DeviceStatus =
                protocol::decode(&r.result().unwrap().payload().to_bytes()).unwrap();
            got.push(st.device_id);
        }
        got.sort();
        assert_eq!(got, sees, "{who}'s wildcard status");
    }
}

/// Every entry's fields agree with its result; the accepted ones say what moved.
fn entries_say_what_moved(entries: &[pb::AuditEntry]) {
    for e in entries {
        assert_eq!(
            (e.member.as_str(), e.device_id.as_str()),
            ("c-ops", "aero-1")
        );
        let role = match e.operator.as_str() {
            "alice" => "operator",
            "vera" => "viewer",
            "root" => "admin",
            _ => "",
        };
        assert_eq!(e.role, role, "{e:?}");
        assert!(e.verified, "the file says names are verified: {e:?}");
        assert_eq!(e.reason.is_empty(), e.accepted, "{e:?}");
        assert_eq!(e.asked.is_empty(), e.accepted, "{e:?}");
        assert_eq!(e.changes.is_empty(), !e.accepted, "{e:?}");
    }
    let moved = |i: usize| -> Vec<(String, String, String)> {
        entries[i]
            .changes
            .iter()
            .map(|c| (c.what.clone(), c.old.clone(), c.new.clone()))
            .collect()
    };
    assert_eq!(
        moved(0),
        [("channel 0 kp".to_string(), "4".to_string(), "5".to_string())]
    );
    assert!(
        moved(7).iter().any(|(w, o, n)| w == "channel 0 envelope"
            && o.starts_with("[-10, 10]")
            && n.starts_with("[-8, 8]")),
        "{:?}",
        moved(7)
    );
    assert!(
        moved(8)
            .iter()
            .any(|(w, _, n)| w == "channel 0 reference" && n.contains("0.5")),
        "{:?}",
        moved(8)
    );
    assert!(entries[4].asked.contains("1e308"), "{:?}", entries[4].asked);
}

#[tokio::test(flavor = "multi_thread")]
async fn operators_act_by_role_and_every_decision_is_on_the_record() {
    let _s = SERIAL.lock().await;
    let dir = scratch_dir("operators");
    std::fs::write(dir.join("service.toml"), CONFIG).unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", transport::free_local_port().unwrap());
    let mut service = spawn_service(&dir, &endpoint, "service-1.log");
    let s = transport::ZenohArgs::loopback(None, vec![endpoint.clone()])
        .open()
        .await
        .unwrap();
    settle(&s, |_| true).await;

    reads_by_role(&s).await;

    make_requests(&s, &dir).await;
    let expected: [(&str, bool, &str); 10] = [
        ("alice", true, "configuration"),
        ("vera", false, "configuration"),
        ("mallory", false, "configuration"),
        ("anonymous", false, "configuration"),
        ("alice", false, "configuration"),
        ("alice", false, "envelope"),
        ("root", false, "envelope"),
        ("alice", true, "envelope"),
        ("alice", true, "reference"),
        ("vera", false, "reference"),
    ];
    // The puts are not answered: wait for their entries.
    let st = settle(&s, |st| {
        st.changes_accepted + st.changes_refused >= 11 && st.audit_written >= 11
    })
    .await;
    let entries = trail(&s, "aero-1").await;
    let got: Vec<(&str, bool, &str)> = entries
        .iter()
        .map(|e| (e.operator.as_str(), e.accepted, e.action.as_str()))
        .collect();
    assert_eq!(got, expected);
    entries_say_what_moved(&entries);
    let other = trail(&s, "aero-2").await;
    assert_eq!(other.len(), 1);
    assert!(other[0].reason.contains("may not act"), "{other:?}");

    // The counters and the file agree with the entries: 3 accepted, 8 refused, 11 lines
    // fsynced (across the rotation at 4 KiB), nothing unwritten.
    assert_eq!((st.changes_accepted, st.changes_refused), (3, 8), "{st:?}");
    assert_eq!(
        (st.audit_written, st.audit_errors, st.audit_unwritten),
        (11, 0, 0),
        "{st:?}"
    );
    let mut lines = Vec::new();
    for f in [
        "audit/c-ops.jsonl.2",
        "audit/c-ops.jsonl.1",
        "audit/c-ops.jsonl",
    ] {
        if let Ok(text) = std::fs::read_to_string(dir.join(f)) {
            // Every line an entry, but the checkpoint a rotation starts a file with (each
            // device's latest state, `controller_service::journal`).
            use controller_service::journal::{read_line, Line};
            lines.extend(text.lines().filter_map(|l| match read_line(l) {
                Line::Record(r) => Some(r.entry),
                Line::Checkpoint(..) => None,
                Line::Torn => panic!("{f}: not an entry: {l}"),
            }));
        }
    }
    assert!(
        dir.join("audit/c-ops.jsonl.1").exists(),
        "4 KiB of entries rotated the file"
    );
    let mut on_record = entries.clone();
    on_record.extend(other.clone());
    on_record.sort_by_key(|e| e.n);
    assert_eq!(lines, on_record);

    // A restart gives every device its trail back from the file.
    let _ = Command::new("kill")
        .args(["-TERM", &service.0.id().to_string()])
        .status();
    let _ = service.0.wait();
    service = spawn_service(&dir, &endpoint, "service-2.log");
    settle(&s, |_| true).await;
    assert_eq!(trail(&s, "aero-1").await, entries);
    assert_eq!(trail(&s, "aero-2").await, other);
    let _ = s.close().await;
    drop(service);
}
