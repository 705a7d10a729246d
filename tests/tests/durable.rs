//! Acknowledged means durable, on the real service binary over real Zenoh sessions, with
//! a plant's samples flowing: two changes acknowledged (a gain and a constant reference),
//! then the restarts an operator meets:
//! * `kill -9`, restarted over a snapshot taken *before* the changes;
//! * `kill -9`, restarted over a snapshot taken *after* them;
//! * a clean stop (SIGTERM), restarted;
//! * the service's file edited while it was stopped (another gain of the same channel).
//!
//! Every acknowledged change is in force afterwards and in the audit trail, and the file's
//! edit is in force too, recorded as a change of its own.
//!
//! Then a full disk under the audit file (root only: a small tmpfs, filled): a change is
//! refused and says why, nothing of it is in force, not even after a restart.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use protocol::{keys, pb, PROTOCOL_VERSION};
use system_tests::{scratch_dir, SERIAL};
use transport::ops;
use zenoh::Session;

const TIMEOUT: Duration = Duration::from_secs(3);

fn config(dir: &Path, audit: &Path, alpha: f64) -> String {
    format!(
        r#"controller_id = "controller-1"
[[devices]]
id = "aero-1"
[[devices.channels]]
law = {{ law = "intelligent", params = {{ kind = "ip", alpha = {alpha:?}, kp = 9.0 }}, estimator = {{ window = 3 }} }}
envelope = {{ min = -24.0, max = 24.0 }}
reference = [{{ kind = "constant", value = 0.2 }}]
[[devices.channels]]
law = {{ law = "pid", params = {{ kp = 1.0 }} }}
envelope = {{ min = -24.0, max = 24.0 }}
[snapshots]
dir = "{snap}"
interval_ms = 200
[audit]
path = "{audit}"
"#,
        snap = dir.join("snap").display(),
        audit = audit.display(),
    )
}

/// The service's process, killed when the test ends.
struct Service(Child);

impl Drop for Service {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl Service {
    fn start(dir: &Path, endpoint: &str, log: &str) -> Self {
        let child = Command::new(env!("CARGO_BIN_EXE_service-under-test"))
            .args(["--config", dir.join("service.toml").to_str().unwrap()])
            .args([
                "--listen",
                endpoint,
                "--no-multicast-scouting",
                "--mode",
                "peer",
            ])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join(log)).unwrap())
            .spawn()
            .unwrap();
        Self(child)
    }

    fn signal(&mut self, sig: &str) {
        let ok = Command::new("kill")
            .args([sig, &self.0.id().to_string()])
            .status()
            .unwrap();
        assert!(ok.success());
        let _ = self.0.wait();
    }
}

/// A plant's samples of `aero-1` every 10 ms, until the task is dropped.
fn samples(session: Session) -> tokio::task::JoinHandle<()> {
    tokio::spawn(async move {
        let p = transport::control_publisher(&session, keys::sample("aero-1"))
            .await
            .unwrap();
        for seq in 0u64.. {
            let s = pb::Sample {
                version: PROTOCOL_VERSION,
                device_id: "aero-1".into(),
                seq,
                plant_time: seq as f64 * 0.01,
                outputs: vec![0.1, 0.0],
                run_id: 5,
                ..Default::default()
            };
            let _ = p.put(protocol::encode(&s)).await;
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
}

/// The configuration once the service answers (it was just started).
async fn config_now(s: &Session) -> pb::DeviceConfig {
    for _ in 0..100 {
        if let Ok(c) = ops::config(s, "aero-1", Duration::from_millis(500)).await {
            return c;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("the service did not answer in 60 s");
}

fn ip(c: &pb::DeviceConfig) -> (f64, f64) {
    match &c.channels[0].law {
        Some(pb::channel_config::Law::Intelligent(l)) => (l.alpha, l.kp),
        other => panic!("{other:?}"),
    }
}

fn reference(c: &pb::DeviceConfig) -> f64 {
    match &c.reference.as_ref().unwrap().channels[0].pieces[..] {
        [pb::Piece {
            shape: Some(pb::piece::Shape::Constant(k)),
        }] => k.value,
        other => panic!("{other:?}"),
    }
}

fn constant(v: f64) -> pb::Reference {
    let piece = |v| pb::Piece {
        shape: Some(pb::piece::Shape::Constant(pb::Constant { value: v })),
    };
    pb::Reference {
        channels: vec![
            pb::ChannelReference {
                pieces: vec![piece(v)],
            },
            pb::ChannelReference {
                pieces: vec![piece(0.0)],
            },
        ],
        start_time: 0.0,
    }
}

fn copy_dir(from: &Path, to: &Path) {
    let _ = std::fs::remove_dir_all(to);
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

/// Wait for the snapshot of `aero-1` to be written after now; a copy of the directory.
async fn snapshot_after(dir: &Path, name: &str) -> PathBuf {
    let file = dir.join("snap/aero-1.snap");
    let before = std::fs::metadata(&file).and_then(|m| m.modified()).ok();
    for _ in 0..50 {
        tokio::time::sleep(Duration::from_millis(100)).await;
        let now = std::fs::metadata(&file).and_then(|m| m.modified()).ok();
        if now.is_some() && now != before {
            let to = dir.join(name);
            copy_dir(&dir.join("snap"), &to);
            return to;
        }
    }
    panic!("no snapshot written in 5 s");
}

/// The entries of the audit file (the current one: the test writes few).
fn audit_file(path: &Path) -> Vec<pb::AuditEntry> {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    text.lines()
        .filter_map(controller_service::audit::from_line)
        .collect()
}

/// Both acknowledged changes (and their entries, by number) are in force and recorded.
async fn both_in_force(s: &Session, audit: &Path, acked: &[u64], when: &str) -> pb::DeviceConfig {
    let c = config_now(s).await;
    assert_eq!(ip(&c).1, 12.0, "{when}: the acknowledged kp");
    assert_eq!(reference(&c), 0.35, "{when}: the acknowledged reference");
    let file: Vec<u64> = audit_file(audit).iter().map(|e| e.n).collect();
    let served = ops::audit(s, Some("aero-1"), TIMEOUT).await.unwrap();
    let kept: Vec<u64> = served
        .iter()
        .flat_map(|l| &l.entries)
        .map(|e| e.n)
        .collect();
    for n in acked {
        assert!(file.contains(n), "{when}: entry {n} in the audit file");
        assert!(
            kept.contains(n),
            "{when}: entry {n} in the service's audit trail"
        );
    }
    c
}

#[tokio::test(flavor = "multi_thread")]
async fn acknowledged_changes_survive_every_restart_and_a_full_disk_refuses() {
    let _s = SERIAL.lock().await;
    let dir = scratch_dir("durable");
    let full = FullDisk::mount(&dir.join("audit"));
    let audit = dir.join("audit/audit.jsonl");
    std::fs::write(dir.join("service.toml"), config(&dir, &audit, 1.0)).unwrap();
    let endpoint = format!("tcp/127.0.0.1:{}", transport::free_local_port().unwrap());
    let mut service = Service::start(&dir, &endpoint, "1.log");
    let s = transport::ZenohArgs::loopback(None, vec![endpoint.clone()])
        .open()
        .await
        .unwrap();
    let feeder = samples(s.clone());
    let start = config_now(&s).await;
    assert_eq!(ip(&start), (1.0, 9.0));
    let before = snapshot_after(&dir, "snap-before").await;

    // Two changes, each acknowledged on the service's disk.
    let kp = ops::parse_update(0, &["kp=12".into()]).unwrap();
    let a = ops::update(&s, "aero-1", kp, TIMEOUT).await.unwrap();
    let b = ops::set_reference(&s, "aero-1", constant(0.35), TIMEOUT)
        .await
        .unwrap();
    assert!(
        a.durable && b.durable,
        "durable: {} {}",
        a.durable,
        b.durable
    );
    assert_eq!(a.held_by, ["controller-1"]);
    let acked: Vec<u64> = ops::audit(&s, Some("aero-1"), TIMEOUT).await.unwrap()[0]
        .entries
        .iter()
        .filter(|e| e.accepted)
        .map(|e| e.n)
        .collect();
    assert_eq!(acked.len(), 2, "two accepted entries");
    let after = snapshot_after(&dir, "snap-after").await;

    for (k, (snap, how)) in [(&before, "older"), (&after, "newer")]
        .into_iter()
        .enumerate()
    {
        service.signal("-KILL");
        copy_dir(snap, &dir.join("snap"));
        service = Service::start(&dir, &endpoint, &format!("kill-{k}.log"));
        let when = format!("kill -9, restarted over the {how} snapshot");
        both_in_force(&s, &audit, &acked, &when).await;
        println!("{when}: kp 12 and reference 0.35 in force, both entries in the audit trail");
    }
    service.signal("-TERM");
    service = Service::start(&dir, &endpoint, "clean.log");
    both_in_force(&s, &audit, &acked, "a clean stop, restarted").await;

    // The file edited while stopped: alpha 0.5 on the same channel.
    service.signal("-TERM");
    std::fs::write(dir.join("service.toml"), config(&dir, &audit, 0.5)).unwrap();
    service = Service::start(&dir, &endpoint, "edited.log");
    let c = both_in_force(&s, &audit, &acked, "the file edited").await;
    assert_eq!(ip(&c).0, 0.5, "the file's edit in force");
    let entries = audit_file(&audit);
    let edit = entries.iter().find(|e| e.action == "configuration file");
    let edit = edit.expect("the file's edit recorded as a change");
    assert!(edit.operator.starts_with("file ") && edit.operator.ends_with("service.toml"));
    let moved: Vec<_> = edit
        .changes
        .iter()
        .map(|c| (c.what.as_str(), c.old.as_str(), c.new.as_str()))
        .collect();
    assert_eq!(moved, [("channel 0 alpha", "1", "0.5")]);
    println!(
        "the file edited: alpha 0.5 in force beside the acknowledged kp 12, recorded as {:?}",
        edit.reason
    );

    match full {
        Some(full) => full_disk(&s, &dir, &endpoint, &audit, &full, service).await,
        None => println!(
            "full disk: not tried (it needs root, to mount a small tmpfs under the audit file)"
        ),
    }
    feeder.abort();
    let _ = s.close().await;
}

/// The disk under the audit file filled to its last byte: a change is refused and says
/// why, and neither it nor anything unrecorded is in force, before or after a restart.
async fn full_disk(
    s: &Session,
    dir: &Path,
    endpoint: &str,
    audit: &Path,
    full: &FullDisk,
    service: Service,
) {
    let mut service = service;
    full.fill();
    let mut refused = None;
    let mut accepted = Vec::new();
    // The file's last page may still take a line or two: changes until one is refused.
    for k in 0..20 {
        let v = f64::from(13 + k);
        let u = ops::parse_update(0, &[format!("kp={v}")]).unwrap();
        match ops::update(s, "aero-1", u, TIMEOUT).await {
            Ok(c) => {
                assert_eq!(ip(&c.config).1, v);
                accepted.push(v);
            }
            Err(e) => {
                refused = Some((v, e.to_string()));
                break;
            }
        }
    }
    let (kp, why) = refused.expect("a change refused on a full disk");
    assert!(
        why.contains("audit file could not be written") && why.contains("nothing changed"),
        "{why}"
    );
    assert!(why.contains("No space left on device"), "{why}");
    let last = accepted.last().copied().unwrap_or(12.0);
    let c = config_now(s).await;
    assert_eq!(ip(&c).1, last, "the refused kp {kp} is not in force");
    let log = ops::audit(s, Some("aero-1"), TIMEOUT).await.unwrap();
    let refusal = log[0].entries.iter().rev().find(|e| !e.accepted).unwrap();
    assert!(
        refusal.reason.contains("No space left"),
        "{}",
        refusal.reason
    );
    println!("full disk: kp={kp} refused ({why}); kp {last} in force ({} accepted first, into the file's last page)", accepted.len());
    full.free();
    service.signal("-KILL");
    let _service = Service::start(dir, endpoint, "after-full.log");
    let c = config_now(s).await;
    assert_eq!(
        ip(&c).1,
        last,
        "after a restart too: nothing in force that is not recorded"
    );
    let file = audit_file(audit);
    assert!(
        file.iter()
            .all(|e| !e.changes.iter().any(|c| c.new == format!("{kp}"))),
        "the refused change is not in the file"
    );
}

/// A small tmpfs mounted under the audit file's directory (root only), unmounted at the end.
struct FullDisk {
    at: PathBuf,
    filler: PathBuf,
}

impl FullDisk {
    fn mount(at: &Path) -> Option<Self> {
        std::fs::create_dir_all(at).unwrap();
        let ok = Command::new("mount")
            .args([
                "-t",
                "tmpfs",
                "-o",
                "size=1m",
                "tmpfs",
                at.to_str().unwrap(),
            ])
            .stderr(Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        ok.then(|| Self {
            at: at.to_path_buf(),
            filler: at.join("filler"),
        })
    }

    /// Fill what is left, to the last byte.
    fn fill(&self) {
        use std::io::Write;
        let mut f = std::fs::File::create(&self.filler).unwrap();
        let chunk = vec![0u8; 4096];
        while f.write_all(&chunk).is_ok() {}
        while f.write_all(&[0u8]).is_ok() {}
    }

    fn free(&self) {
        std::fs::remove_file(&self.filler).unwrap();
    }
}

impl Drop for FullDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount")
            .args(["-l", self.at.to_str().unwrap()])
            .status();
    }
}
