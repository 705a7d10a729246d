//! The operator is never blind: `mfcctl` ends within its `--timeout-ms`, opening the
//! session included, whatever the other end does. Against a router that accepts the
//! connection and then says nothing (zenoh's own open would wait 10 s), and against a
//! service that is stopped (SIGSTOP) while `mfcctl` asks it; and once the service resumes,
//! the answer comes again.
//!
//! The bound checked is the promise (the timeout) plus a margin for a busy machine,
//! `MFC_TEST_QUERY_MARGIN_MS` (default 2000 ms): what it catches is a command that waits
//! for the other end (10 s and more), not a slow machine.

use std::net::TcpListener;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use system_tests::{scratch_dir, SERIAL};

fn margin() -> Duration {
    let ms = std::env::var("MFC_TEST_QUERY_MARGIN_MS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2000);
    Duration::from_millis(ms)
}

/// `mfcctl ARGS` in this process; its output or error, and how long it took.
async fn ctl(args: &[&str]) -> (Result<String, String>, Duration) {
    let t0 = Instant::now();
    let cli = mfcctl::cli::MfcctlCli::try_parse_from(args).unwrap();
    let r = mfcctl::cli::run(cli).await.map_err(|e| format!("{e:#}"));
    (r, t0.elapsed())
}

struct Proc(Child);
impl Drop for Proc {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-CONT", &self.0.id().to_string()])
            .status();
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_silent_router_and_a_stopped_service_end_the_command_within_its_timeout() {
    let _s = SERIAL.lock().await;
    // A "router" that takes the connection and never answers.
    let tarpit = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = tarpit.local_addr().unwrap().port();
    let held = std::thread::spawn(move || {
        let mut kept = Vec::new();
        for c in tarpit.incoming().take(4) {
            kept.push(c);
        }
        std::thread::sleep(Duration::from_secs(30));
    });
    let silent = format!("tcp/127.0.0.1:{port}");
    let (r, took) = ctl(&[
        "mfcctl",
        "--mode",
        "client",
        "--connect",
        &silent,
        "--timeout-ms",
        "800",
        "status",
        "aero-1",
    ])
    .await;
    println!("silent router: {took:?}: {r:?}");
    let e = r.expect_err("no session, no answer");
    assert!(e.contains("no zenoh session within 800 ms"), "{e}");
    assert!(took < Duration::from_millis(800) + margin(), "{took:?}");
    drop(held);

    // A service, answering; then stopped; then resumed.
    let dir = scratch_dir("never-blind");
    std::fs::write(
        dir.join("service.toml"),
        "controller_id = \"c-1\"\n[[devices]]\nid = \"aero-1\"\n[[devices.channels]]\n",
    )
    .unwrap();
    let ep = format!("tcp/127.0.0.1:{}", transport::free_local_port().unwrap());
    let child = Command::new(env!("CARGO_BIN_EXE_service-under-test"))
        .args(["--config", dir.join("service.toml").to_str().unwrap()])
        .args(["--listen", &ep, "--no-multicast-scouting", "--mode", "peer"])
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("service.log")).unwrap())
        .spawn()
        .unwrap();
    let service = Proc(child);
    let args = |ms: &'static str| {
        [
            "mfcctl",
            "--connect",
            &ep,
            "--no-multicast-scouting",
            "--mode",
            "peer",
            "--timeout-ms",
            ms,
            "status",
            "aero-1",
        ]
        .map(str::to_string)
    };
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let a = args("1000");
        let (r, _) = ctl(&a.iter().map(String::as_str).collect::<Vec<_>>()).await;
        if r.is_ok() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the service never answered: {r:?}"
        );
    }
    let pid = service.0.id().to_string();
    assert!(Command::new("kill")
        .args(["-STOP", &pid])
        .status()
        .unwrap()
        .success());
    let a = args("1000");
    let (r, took) = ctl(&a.iter().map(String::as_str).collect::<Vec<_>>()).await;
    println!("stopped service: {took:?}: {r:?}");
    let e = r.expect_err("a stopped service does not answer");
    assert!(e.contains("no answer within 1000 ms"), "{e}");
    assert!(took < Duration::from_millis(1000) + margin(), "{took:?}");
    assert!(Command::new("kill")
        .args(["-CONT", &pid])
        .status()
        .unwrap()
        .success());
    let a = args("3000");
    let (r, took) = ctl(&a.iter().map(String::as_str).collect::<Vec<_>>()).await;
    println!("resumed: {took:?}");
    let text = r.expect("answered again once resumed");
    assert!(text.contains("answered by c-1"), "{text}");
}
