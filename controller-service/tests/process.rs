//! The `controller-service` binary as a real process: it serves, reports its status, and
//! shuts down cleanly on SIGTERM (its liveliness token disappears at once).

use std::process::{Command, Stdio};
use std::time::Duration;

use protocol::{keys, pb};
use transport::ZenohArgs;

#[tokio::test(flavor = "multi_thread")]
async fn serves_and_stops_cleanly_on_sigterm() {
    let dir = std::env::temp_dir().join(format!("svc-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let config = dir.join("service.toml");
    std::fs::write(
        &config,
        "controller_id = \"proc\"\n[[devices]]\nid = \"d1\"\n[[devices.channels]]\n",
    )
    .unwrap();
    let port = transport::free_local_port().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut child = Command::new(env!("CARGO_BIN_EXE_controller-service"))
        .args([
            "--config",
            config.to_str().unwrap(),
            "--mode",
            "peer",
            "--listen",
            &endpoint,
            "--no-multicast-scouting",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();

    let session = ZenohArgs::loopback(None, vec![endpoint])
        .open()
        .await
        .unwrap();
    // Wait for the service's liveliness token.
    let up = transport::wait_for_token(
        &session,
        &keys::alive_controller("proc"),
        Duration::from_secs(10),
    )
    .await;
    assert!(up, "the service never came up");
    let status: pb::ServiceStatus = protocol::decode(
        &transport::get_first(&session, &keys::service_status("proc"), None)
            .await
            .unwrap(),
    )
    .unwrap();
    assert_eq!(status.devices.len(), 1);
    assert_eq!(status.devices[0].device_id, "d1");

    let watcher = session
        .liveliness()
        .declare_subscriber(keys::alive_controller("proc"))
        .await
        .unwrap();
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    // The token goes at once on a clean exit (not after zenoh's 10 s lease).
    let gone = tokio::time::timeout(Duration::from_secs(3), watcher.recv_async()).await;
    let kind = gone.map(|r| r.map(|s| s.kind()));
    assert!(
        matches!(kind, Ok(Ok(zenoh::sample::SampleKind::Delete))),
        "{kind:?}"
    );
    let status = child.wait().unwrap();
    assert!(status.success(), "exit status {status}");

    // A bad configuration is refused with the file and the field, and a non-zero exit.
    std::fs::write(
        &config,
        "controller_id = \"proc\"\n[[devices]]\nid = \"bad id\"\n[[devices.channels]]\n",
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_controller-service"))
        .args(["--config", config.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("service.toml") && err.contains("devices[0].id"),
        "{err}"
    );
    let _ = session.close().await;
}
