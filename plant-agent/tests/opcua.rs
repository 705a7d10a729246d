//! `plant-agent run` on a plant behind an OPC UA server we did not write (asyncua,
//! `plants/servers/opcua_plant.py`, hosting the DC motor's physics in real time): however
//! the run ends (SIGTERM, a server killed, a node that reads NaN or vanishes, a server that
//! falls silent, a refused login), the agent says why, never panics, and the safe value is
//! in the server's input node wherever a server is there to take it.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod support {
    pub mod plant_server;
}
use support::plant_server::{free_port, root, scratch, summary, wait, Server, ServerKind};

/// The safe value the scenarios write: distinct from anything the loop sends at rest.
const SAFE: f64 = 0.25;

fn server(flags: &[&str]) -> Server {
    Server::start_as(ServerKind::OpcUa, free_port(), flags)
}

/// The shipped OPC UA motor file on `port`, with the reconnection budget, duration and an
/// optional user (its password in a file next to the scenario).
fn scenario(
    dir: &Path,
    port: u16,
    reconnect_ms: u64,
    duration: f64,
    user: Option<(&str, &str)>,
) -> PathBuf {
    let shipped = root().join("plants/servers/motor-steps-opcua.toml");
    let controller = root().join("plants/dc-motor/controllers/ipd.toml");
    let mut text = std::fs::read_to_string(shipped)
        .unwrap()
        .replace("127.0.0.1:4840", &format!("127.0.0.1:{port}"))
        .replace("timeout_ms = 20", "timeout_ms = 500")
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
    if let Some((u, p)) = user {
        std::fs::write(dir.join("password"), format!("{p}\n")).unwrap();
        text = text.replace(
            "[plant.opcua]\n",
            &format!("[plant.opcua]\nuser = {u:?}\npassword_file = \"password\"\n"),
        );
    }
    let path = dir.join("scenario.toml");
    std::fs::write(&path, text).unwrap();
    path
}

fn agent(scenario: &Path, out: &Path) -> Child {
    agent_to(scenario, out, Stdio::null())
}

/// The agent with its log going to `stderr` (a pipe nobody reads would fill and stall it).
fn agent_to(scenario: &Path, out: &Path, stderr: Stdio) -> Child {
    Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["run", "--device", "motor-1", "--scenario"])
        .arg(scenario)
        .arg("--out")
        .arg(out)
        .args(["--listen", &format!("tcp/127.0.0.1:{}", free_port())])
        .arg("--no-multicast-scouting")
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap()
}

fn wait_for_the_loop(server: &Server, user: Option<(&str, &str)>) {
    let until = Instant::now() + Duration::from_secs(60);
    while server.node("Applied", user) == 0.0 {
        assert!(Instant::now() < until, "the agent never wrote an input");
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[test]
fn sigterm_leaves_the_safe_value_in_the_servers_input_node() {
    let dir = scratch("opcua", "sigterm");
    let user = Some(("operator", "s3cret"));
    let server = server(&["--user", "operator", "--password", "s3cret"]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, server.port, 0, 60.0, user), &out);
    wait_for_the_loop(&server, user);
    std::thread::sleep(Duration::from_secs(1));
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    assert_eq!(wait(&mut child, Duration::from_secs(30)), 3);
    let s = summary(&out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert!(s["counters"]["periods"].as_u64().unwrap() > 50, "{s}");
    assert_eq!(server.node("Input", user), SAFE);
    assert_eq!(server.node("Applied", user), SAFE, "the plant applies it");
}

#[test]
fn a_wrong_password_is_refused_before_the_loop_with_the_reason() {
    let dir = scratch("opcua", "password");
    let server = server(&["--user", "operator", "--password", "s3cret"]);
    let out = dir.join("out");
    let log = dir.join("agent.log");
    let mut child = agent_to(
        &scenario(&dir, server.port, 0, 5.0, Some(("operator", "wrong"))),
        &out,
        std::fs::File::create(&log).unwrap().into(),
    );
    let code = wait(&mut child, Duration::from_secs(60));
    let said = std::fs::read_to_string(&log).unwrap();
    assert_eq!(code, 1, "{said}");
    let error = said
        .lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_default();
    assert!(error.contains(&server.address()), "{said}");
    assert!(
        error.contains("BadUserAccessDenied"),
        "the server's reason: {error}"
    );
    assert!(
        server.node("Applied", Some(("operator", "s3cret"))) == 0.0,
        "nothing was written"
    );
}

#[test]
fn a_server_killed_and_restarted_within_the_budget_is_reconnected() {
    let dir = scratch("opcua", "restart");
    let port = free_port();
    let mut first = Server::start_as(ServerKind::OpcUa, port, &[]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, port, 20_000, 8.0, None), &out);
    wait_for_the_loop(&first, None);
    first.kill();
    std::thread::sleep(Duration::from_millis(500));
    let second = Server::start_as(ServerKind::OpcUa, port, &[]);
    assert_eq!(wait(&mut child, Duration::from_secs(90)), 3);
    let s = summary(&out);
    assert_eq!(
        s["end"], "completed",
        "the run went on after the reconnection: {s}"
    );
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert!(
        s["overruns"].as_u64().unwrap() > 0,
        "the outage cost periods: {s}"
    );
    assert_eq!(second.node("Input", None), SAFE);
}

/// A server that answers nonsense: a NaN, a node that vanishes, then silence.
#[test]
fn a_hostile_server_gets_a_clear_error_and_the_safe_stop() {
    for (flag, says, safe_stop) in [
        ("--nan-after", "holds no finite number", true),
        ("--vanish-after", "BadNodeIdUnknown", true),
        ("--silent-after", "timed out", false),
    ] {
        let dir = scratch("opcua", &flag[2..]);
        let server = server(&[flag, "1"]);
        let out = dir.join("out");
        let mut child = agent(&scenario(&dir, server.port, 0, 60.0, None), &out);
        assert_eq!(wait(&mut child, Duration::from_secs(60)), 4, "{flag}");
        let s = summary(&out);
        assert_eq!(s["end"], "plant_failed", "{flag}: {s}");
        let error = s["error"].as_str().unwrap();
        assert!(error.contains(says), "{flag}: {error}");
        assert_eq!(s["safe_stop_applied"], safe_stop, "{flag}: {s}");
        if safe_stop {
            assert_eq!(server.node("Input", None), SAFE, "{flag}");
        }
    }
}
