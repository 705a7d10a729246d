//! `plant-agent run` as a process: however it ends (SIGTERM, a driver that hangs or
//! exits), the plant gets its safe stop, the record is written and the exit status and the
//! summary say what happened.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mfc-agent-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A one-channel scenario on the echo driver, logging the driver's requests to `log`.
fn scenario(dir: &Path, log: &Path, extra: &[&str]) -> PathBuf {
    // The `plant` crate's test driver, which its own driver tests use.
    let driver = format!(
        "{}/../plant/tests/fixtures/echo_driver.py",
        env!("CARGO_MANIFEST_DIR")
    );
    let mut argv = vec![
        "python3".to_string(),
        driver,
        "--log".into(),
        log.to_str().unwrap().into(),
    ];
    argv.extend(extra.iter().map(|s| s.to_string()));
    let text = format!(
        r#"name = "echo"
duration = 60.0
period = 0.01
[plant]
driver = {argv:?}
[[channels]]
name = "y"
reference = [{{ kind = "constant", value = 1.0 }}]
output = {{ min = -10.0, max = 10.0 }}
[controller]
name = "ip"
channels = [{{ law = "intelligent", params = {{ kind = "ip", alpha = 1.0, kp = 5.0 }} }}]
"#
    );
    let path = dir.join("scenario.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The agent alone on loopback (no controller anywhere): it runs on its local fallback.
fn agent(scenario: &Path, out: &Path) -> Child {
    Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--device", "echo-1", "--scenario"])
        .arg(scenario)
        .arg("--out")
        .arg(out)
        .args(["--listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .arg("--no-multicast-scouting")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

fn wait_for_lines(log: &Path, n: usize) {
    let until = Instant::now() + Duration::from_secs(30);
    while Instant::now() < until {
        let lines = std::fs::read_to_string(log).map_or(0, |t| t.lines().count());
        if lines >= n {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    panic!("the loop never ran: fewer than {n} driver requests");
}

fn wait(child: &mut Child, limit: Duration) -> i32 {
    let until = Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.code().expect("exited, not killed by a signal");
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("the agent did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

fn signal(child: &Child, sig: &str) {
    let status = Command::new("kill")
        .args([&format!("-{sig}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
}

#[test]
fn sigterm_mid_run_stops_the_plant_and_writes_the_record() {
    stopped_mid_run("TERM");
}

#[test]
fn sigint_mid_run_stops_the_plant_and_writes_the_record() {
    stopped_mid_run("INT");
}

/// A stop requested while the driver is still starting (before its `hello`) is kept: the
/// plant gets its safe stop as soon as it is there, and the record is written.
#[test]
fn sigterm_while_the_driver_starts_is_kept() {
    let dir = scratch("sigterm-start");
    let log = dir.join("driver.log");
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, &log, &["--hello-delay", "2"]), &out);
    std::thread::sleep(Duration::from_millis(500));
    signal(&child, "TERM");
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 3);
    let s = summary(&out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    let requests = std::fs::read_to_string(&log).unwrap();
    assert_eq!(requests.lines().last(), Some("stop"), "{requests}");
    assert!(out.join("run.csv").is_file());
}

fn stopped_mid_run(sig: &str) {
    let dir = scratch(&format!("sig{sig}"));
    let log = dir.join("driver.log");
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, &log, &[]), &out);
    wait_for_lines(&log, 300); // about 100 periods
    signal(&child, sig);
    // 3: stopped cleanly, but no controller ever answered (there is none here).
    assert_eq!(wait(&mut child, Duration::from_secs(20)), 3);
    let s = summary(&out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert_eq!(s["controller_reached"], false, "{s}");
    assert_eq!(s["link"], "never", "{s}");
    assert!(s["counters"]["fallbacks"].as_u64().unwrap() >= 1, "{s}");
    let periods = s["counters"]["periods"].as_u64().unwrap();
    assert!(periods >= 100, "{s}");
    let csv = std::fs::read_to_string(out.join("run.csv")).unwrap();
    assert_eq!(csv.lines().count() as u64, periods + 1, "a row per period");
    assert!(out.join("y.png").is_file() && out.join("y.svg").is_file());
    let requests = std::fs::read_to_string(&log).unwrap();
    assert_eq!(
        requests.lines().last(),
        Some("stop"),
        "the safe stop reached the driver"
    );
}

#[test]
fn a_driver_that_stops_answering_ends_the_run_with_its_record() {
    let dir = scratch("hang");
    let log = dir.join("driver.log");
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, &log, &["--hang-after", "600"]), &out);
    // Exit status 4: the plant failed (and its safe stop could not be confirmed).
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 4);
    let s = summary(&out);
    assert_eq!(s["end"], "plant_failed", "{s}");
    assert!(
        s["error"].as_str().unwrap().contains("did not answer"),
        "{s}"
    );
    assert_eq!(s["safe_stop_applied"], false, "{s}");
    let periods = s["counters"]["periods"].as_u64().unwrap();
    assert!(periods > 100, "{s}");
    let csv = std::fs::read_to_string(out.join("run.csv")).unwrap();
    assert_eq!(csv.lines().count() as u64, periods + 1);
}

#[test]
fn a_driver_that_exits_ends_the_run_with_its_record() {
    let dir = scratch("exit");
    let log = dir.join("driver.log");
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, &log, &["--exit-after", "600"]), &out);
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 4);
    let s = summary(&out);
    assert_eq!(s["end"], "plant_failed", "{s}");
    assert!(s["error"].as_str().unwrap().contains("exited"), "{s}");
    assert!(out.join("run.csv").is_file());
}

#[test]
fn bad_configuration_is_refused_before_touching_the_plant() {
    let dir = scratch("badcfg");
    let cfg = dir.join("agent.toml");
    std::fs::write(&cfg, "device = \"a\"\nhold_period = 3\n").unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--config"])
        .arg(&cfg)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("agent.toml") && err.contains("hold_period"),
        "{err}"
    );
    let out = Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--scenario", "2"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("device"));
}

/// An agent whose router is not there yet says so every 5 s instead of hanging in silence,
/// and a stop while it waits is still a safe stop of the (already opened) plant: exit 3,
/// and a record of a run that never started.
#[test]
fn sigterm_while_waiting_for_the_router_is_a_safe_stop() {
    let dir = scratch("no-router");
    let log = dir.join("driver.log");
    let out = dir.join("out");
    let zenoh = dir.join("client.json5");
    // A client that retries forever, as the generated deployment configs do.
    std::fs::write(
        &zenoh,
        format!(
            r#"{{ mode: "client", connect: {{ endpoints: ["tcp/127.0.0.1:{}"], timeout_ms: -1 }},
               scouting: {{ multicast: {{ enabled: false }} }} }}"#,
            free_port()
        ),
    )
    .unwrap();
    let stderr = dir.join("stderr.log");
    let stdout = dir.join("stdout.log");
    let mut child = Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--device", "echo-1", "--scenario"])
        .arg(scenario(&dir, &log, &[]))
        .arg("--out")
        .arg(&out)
        .arg("--zenoh-config")
        .arg(&zenoh)
        .env("RUST_LOG", "warn")
        .stdout(std::fs::File::create(&stdout).unwrap())
        .stderr(std::fs::File::create(&stderr).unwrap())
        .spawn()
        .unwrap();
    let until = Instant::now() + Duration::from_secs(30);
    while !std::fs::read_to_string(&stderr)
        .unwrap_or_default()
        .contains("not connected after")
    {
        assert!(
            child.try_wait().unwrap().is_none(),
            "the agent exited instead of waiting for its router"
        );
        assert!(Instant::now() < until, "no 'not connected' warning in 30 s");
        std::thread::sleep(Duration::from_millis(100));
    }
    signal(&child, "TERM");
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 3);
    let requests = std::fs::read_to_string(&log).unwrap();
    assert_eq!(requests.lines().last(), Some("stop"), "{requests}");
    let s = summary(&out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["link"], "never", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert_eq!(s["counters"]["periods"], 0, "{s}");
    let said = std::fs::read_to_string(&stdout).unwrap();
    assert!(said.contains("waiting for the router"), "{said}");
}
