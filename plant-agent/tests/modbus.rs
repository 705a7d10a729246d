//! `plant-agent run` on a plant behind a Modbus TCP server we did not write (pymodbus,
//! `plants/servers/modbus_plant.py`, hosting the DC motor's physics in real time): however
//! the run ends (SIGTERM, a server killed, a server that answers nonsense or nothing), the
//! agent says why, never panics, and the safe values are in the server's registers
//! wherever a server is there to take them.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use plant::modbus::RegisterKind;

/// The safe value the scenarios write: distinct from anything the loop sends at rest.
const SAFE: f64 = 0.25;

mod support {
    pub mod plant_server;
}
use support::plant_server::{
    free_port, root, scratch, summary, wait, went_on_after_the_reconnection, Server,
};

/// The shipped motor scenario on `port`, with the reconnection budget and duration given
/// and the test's safe value; the controller by absolute path.
fn scenario(dir: &Path, port: u16, reconnect_ms: u64, duration: f64) -> PathBuf {
    let shipped = root().join("plants/servers/motor-steps-modbus.toml");
    let text = std::fs::read_to_string(&shipped).unwrap();
    let controller = root().join("plants/dc-motor/controllers/ipd.toml");
    let text = text
        .replace("127.0.0.1:5020", &format!("127.0.0.1:{port}"))
        .replace("timeout_ms = 20", "timeout_ms = 200")
        .replace(
            "reconnect_ms = 2000",
            &format!("reconnect_ms = {reconnect_ms}"),
        )
        .replace("safe = 0.0", &format!("safe = {SAFE}"))
        .replace("duration = 20.0", &format!("duration = {duration}"))
        .replace(
            "\"../dc-motor/controllers/ipd.toml\"",
            &format!("{:?}", controller.to_str().unwrap()),
        );
    let path = dir.join("scenario.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// The agent alone on loopback: no controller anywhere, the plant runs on its local law.
fn agent(scenario: &Path, out: &Path) -> Child {
    agent_with(scenario, out, &[])
}

fn agent_with(scenario: &Path, out: &Path, flags: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--device", "motor-1", "--scenario"])
        .arg(scenario)
        .args(flags)
        .arg("--out")
        .arg(out)
        .args(["--listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .arg("--no-multicast-scouting")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// Wait until the loop has driven the plant: the applied input moved off 0.
fn wait_for_the_loop(server: &Server) {
    let until = Instant::now() + Duration::from_secs(30);
    while server.value(RegisterKind::Input, 2) == 0.0 {
        assert!(Instant::now() < until, "the agent never wrote an input");
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn sigterm_leaves_the_safe_values_in_the_servers_registers() {
    let dir = scratch("modbus", "sigterm");
    let server = Server::start(free_port(), &[]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, server.port, 0, 60.0), &out);
    wait_for_the_loop(&server);
    std::thread::sleep(Duration::from_secs(2));
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    // 3: no controller ever answered (the agent ran on its local law), safe stop applied.
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 3);
    let s = summary(&out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert!(s["counters"]["periods"].as_u64().unwrap() > 100, "{s}");
    assert_eq!(server.value(RegisterKind::Holding, 0), SAFE);
    assert_eq!(
        server.value(RegisterKind::Input, 2),
        SAFE,
        "the plant applies it"
    );
}

/// With no controller and the safe-stop fallback, the plant applies the map's safe value
/// in every period of the run (not zero): the start and the fallback write what the map
/// says is safe.
#[test]
fn the_safe_stop_fallback_writes_the_maps_safe_values() {
    let dir = scratch("modbus", "fallback");
    let server = Server::start(free_port(), &[]);
    let out = dir.join("out");
    let mut child = agent_with(
        &scenario(&dir, server.port, 0, 3.0),
        &out,
        &["--fallback", "safe-stop"],
    );
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 3);
    let s = summary(&out);
    assert_eq!(s["end"], "completed", "{s}");
    let periods = s["counters"]["periods"].as_u64().unwrap();
    let safe = s["counters"]["safe_stop_periods"].as_u64().unwrap();
    assert!(safe + 10 >= periods && safe > 0, "{s}");
    // What the plant applied, period by period (the server's applied register, in the
    // record): the safe value throughout, under the fallback too.
    let csv = std::fs::read_to_string(out.join("run.csv")).unwrap();
    let mut rows = csv.lines();
    let header: Vec<&str> = rows.next().unwrap().split(',').collect();
    let v = header.iter().position(|c| *c == "load_angle_v").unwrap();
    let applied: Vec<f64> = rows
        .map(|r| r.split(',').nth(v).unwrap().parse().unwrap())
        .collect();
    assert_eq!(applied.len() as u64, periods);
    assert!(applied.iter().all(|&a| a == SAFE), "{applied:?}");
}

#[test]
fn a_server_killed_and_restarted_within_the_budget_is_reconnected() {
    let dir = scratch("modbus", "restart");
    let port = free_port();
    let mut server = Server::start(port, &[]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, port, 10_000, 6.0), &out);
    wait_for_the_loop(&server);
    server.kill();
    std::thread::sleep(Duration::from_millis(500));
    let server = Server::start(port, &[]);
    assert_eq!(wait(&mut child, Duration::from_secs(60)), 3);
    went_on_after_the_reconnection(&out, "modbus");
    assert_eq!(server.value(RegisterKind::Holding, 0), SAFE);
}

#[test]
fn a_server_lost_for_good_ends_the_run_and_says_why() {
    let dir = scratch("modbus", "lost");
    let mut server = Server::start(free_port(), &[]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, server.port, 300, 60.0), &out);
    wait_for_the_loop(&server);
    server.kill();
    // 4: the plant failed; its safe stop could not be confirmed (nobody to take it).
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 4);
    let s = summary(&out);
    assert_eq!(s["end"], "plant_failed", "{s}");
    let error = s["error"].as_str().unwrap();
    assert!(error.contains(&server.address()), "{error}");
    assert!(error.contains("reconnect_ms = 300"), "{error}");
    assert_eq!(s["safe_stop_applied"], false, "{s}");
}

/// A server that answers nonsense: a NaN, a register that vanishes, then silence.
#[test]
fn a_hostile_server_gets_a_clear_error_and_the_safe_stop() {
    for (flag, says, safe_stop) in [
        ("--nan-after", "holds no finite number", true),
        ("--vanish-after", "Illegal data address", true),
        ("--silent-after", "deadline has elapsed", false),
    ] {
        let dir = scratch("modbus", &flag[2..]);
        let server = Server::start(free_port(), &[flag, "1"]);
        let out = dir.join("out");
        let mut child = agent(&scenario(&dir, server.port, 0, 60.0), &out);
        assert_eq!(wait(&mut child, Duration::from_secs(60)), 4, "{flag}");
        let s = summary(&out);
        assert_eq!(s["end"], "plant_failed", "{flag}: {s}");
        let error = s["error"].as_str().unwrap();
        assert!(error.contains(says), "{flag}: {error}");
        assert_eq!(s["safe_stop_applied"], safe_stop, "{flag}: {s}");
        if safe_stop {
            assert_eq!(server.value(RegisterKind::Holding, 0), SAFE, "{flag}");
        }
    }
}
