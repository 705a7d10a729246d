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
use fieldbus::opcua::{OpcUaUser, SessionSpec};
use support::plant_server::{
    free_port, root, scratch, summary, wait, went_on_after_the_reconnection, Server, ServerKind,
};

/// The safe value the scenarios write: distinct from anything the loop sends at rest.
const SAFE: f64 = 0.25;

/// The map's line for the outputs by subscription.
const SUBSCRIBE: &str = "sampling = \"subscribe\"\n";

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
    let mut lines = String::new();
    if let Some((u, p)) = user {
        std::fs::write(dir.join("password"), format!("{p}\n")).unwrap();
        lines = format!("user = {u:?}\npassword_file = \"password\"\n");
    }
    scenario_with(dir, port, reconnect_ms, duration, &lines)
}

/// The same with `lines` added to the `[plant.opcua]` table.
fn scenario_with(dir: &Path, port: u16, reconnect_ms: u64, duration: f64, lines: &str) -> PathBuf {
    let shipped = root().join("plants/servers/motor-steps-opcua.toml");
    let controller = root().join("plants/dc-motor/controllers/ipd.toml");
    let text = std::fs::read_to_string(shipped)
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
    let text = text.replace("[plant.opcua]\n", &format!("[plant.opcua]\n{lines}"));
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
    wait_for_an_input(|| server.node("Applied", user));
}

/// Wait (60 s at most) until `applied` reads other than 0: the agent's loop wrote.
fn wait_for_an_input(applied: impl Fn() -> f64) {
    let until = Instant::now() + Duration::from_secs(60);
    while applied() == 0.0 {
        assert!(Instant::now() < until, "the agent never wrote an input");
        std::thread::sleep(Duration::from_millis(200));
    }
}

/// SIGTERM to the agent a second into its loop: it exits 3 (no controller), its run
/// interrupted, the safe stop applied, after more than 50 periods.
fn interrupted_after_a_second(child: &mut Child, out: &Path) {
    std::thread::sleep(Duration::from_secs(1));
    let status = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(status.success());
    assert_eq!(wait(child, Duration::from_secs(30)), 3);
    let s = summary(out);
    assert_eq!(s["end"], "interrupted", "{s}");
    assert_eq!(s["safe_stop_applied"], true, "{s}");
    assert!(s["counters"]["periods"].as_u64().unwrap() > 50, "{s}");
}

#[test]
fn sigterm_leaves_the_safe_value_in_the_servers_input_node() {
    let dir = scratch("opcua", "sigterm");
    let user = Some(("operator", "s3cret"));
    let server = server(&["--user", "operator", "--password", "s3cret"]);
    let out = dir.join("out");
    let mut child = agent(&scenario(&dir, server.port, 0, 60.0, user), &out);
    wait_for_the_loop(&server, user);
    interrupted_after_a_second(&mut child, &out);
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
    // By Read, then by subscription (made again on the new server: the outputs the loop
    // gets after the restart move, where values left from the first server would not).
    for sampling in ["", SUBSCRIBE] {
        let dir = scratch("opcua", &format!("restart{}", sampling.len()));
        let port = free_port();
        let mut first = Server::start_as(ServerKind::OpcUa, port, &[]);
        let out = dir.join("out");
        let mut child = agent(&scenario_with(&dir, port, 20_000, 8.0, sampling), &out);
        wait_for_the_loop(&first, None);
        first.kill();
        std::thread::sleep(Duration::from_millis(500));
        let second = Server::start_as(ServerKind::OpcUa, port, &[]);
        assert_eq!(wait(&mut child, Duration::from_secs(90)), 3, "{sampling}");
        let what = if sampling.is_empty() {
            "by Read"
        } else {
            "by subscription"
        };
        went_on_after_the_reconnection(&out, what);
        assert_eq!(second.node("Input", None), SAFE);
        let last = distinct_outputs_in_the_last_second(&out);
        assert!(
            last > 10,
            "{sampling}: {last} distinct outputs in the last second"
        );
    }
}

/// How many distinct values the output took in the run's last second (`run.csv`).
fn distinct_outputs_in_the_last_second(out: &Path) -> usize {
    let text = std::fs::read_to_string(out.join("run.csv")).unwrap();
    let rows: Vec<(f64, String)> = text
        .lines()
        .skip(1)
        .filter_map(|l| {
            let mut f = l.split(',');
            let t = f.next()?.parse().ok()?;
            Some((t, f.nth(1)?.to_string()))
        })
        .collect();
    let end = rows.last().map_or(0.0, |r| r.0);
    let mut seen: Vec<&String> = rows
        .iter()
        .filter(|r| r.0 > end - 1.0)
        .map(|r| &r.1)
        .collect();
    seen.sort();
    seen.dedup();
    seen.len()
}

/// A server that answers nonsense: a NaN, a node that vanishes, then silence; the first
/// two also through a subscription. There the NaN is published, and the bridge's Read that
/// confirms the subscription once a second may see it first when the publication is late
/// (a loaded machine): either is the subscription path refusing it, so both are accepted,
/// but not the plain Read's message.
#[test]
fn a_hostile_server_gets_a_clear_error_and_the_safe_stop() {
    const NAN: &str = "ns=2;s=Plant.Output holds no finite number";
    for (flag, says, safe_stop, sampling) in [
        ("--nan-after", &["holds no finite number"][..], true, ""),
        ("--vanish-after", &["BadNodeIdUnknown"], true, ""),
        ("--silent-after", &["timed out"], false, ""),
        (
            "--nan-after",
            &[
                &*format!("subscription to the outputs: {NAN}"),
                &*format!("read confirming the subscription: {NAN}"),
            ],
            true,
            SUBSCRIBE,
        ),
        ("--vanish-after", &["BadNodeIdUnknown"], true, SUBSCRIBE),
    ] {
        let dir = scratch("opcua", &format!("{}{}", &flag[2..], sampling.len()));
        let server = server(&[flag, "1"]);
        let out = dir.join("out");
        let mut child = agent(&scenario_with(&dir, server.port, 0, 60.0, sampling), &out);
        assert_eq!(wait(&mut child, Duration::from_secs(60)), 4, "{flag}");
        let s = summary(&out);
        assert_eq!(s["end"], "plant_failed", "{flag}: {s}");
        let error = s["error"].as_str().unwrap();
        assert!(says.iter().any(|w| error.contains(w)), "{flag}: {error}");
        assert_eq!(s["safe_stop_applied"], safe_stop, "{flag}: {s}");
        if safe_stop {
            assert_eq!(server.node("Input", None), SAFE, "{flag}");
        }
    }
}

/// `plant-agent probe opcua` with `args`: its exit code, stdout and stderr.
fn probe(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_plant-agent"))
        .args(["probe", "opcua"])
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into(),
        String::from_utf8_lossy(&out.stderr).into(),
    )
}

/// A user's certificate and key made by the server's script: `{prefix}.der`, `{prefix}.pem`.
fn user_certificate(prefix: &Path) {
    let ok = Command::new(support::plant_server::python())
        .arg(root().join("plants/servers/opcua_plant.py"))
        .arg("--make-certificate")
        .arg(prefix)
        .status()
        .unwrap()
        .success();
    assert!(ok, "making a user certificate");
}

/// The lines of a map that asks for Basic256Sha256 with SignAndEncrypt, the PKI in `pki`
/// and the user as the certificate `user.der` (all beside the scenario).
const SECURE: &str = "security_policy = \"Basic256Sha256\"\nsecurity_mode = \"SignAndEncrypt\"\n\
    pki_dir = \"pki\"\nuser_certificate = \"user.der\"\nuser_private_key = \"user.pem\"\n";

/// The agent's first `error:` line, once it exits 1 (refused before the loop).
fn refused(scenario: &Path, dir: &Path) -> String {
    let log = dir.join("refused.log");
    let mut child = agent_to(
        scenario,
        &dir.join("out-refused"),
        std::fs::File::create(&log).unwrap().into(),
    );
    let code = wait(&mut child, Duration::from_secs(60));
    let said = std::fs::read_to_string(&log).unwrap();
    assert_eq!(code, 1, "{said}");
    said.lines()
        .find(|l| l.starts_with("error:"))
        .unwrap_or_default()
        .to_string()
}

/// The first connections to a secure server, as its operators would go through them with
/// the probe `args` (which makes the bridge's certificate in `pki`): each refusal says
/// which certificate to trust where, and each side's operator trusts it (the server's
/// trusted certificates are in `spki/trusted`).
fn trust_each_other(args: &[&str], pki: &Path, spki: &Path) {
    // The server refuses the bridge's new certificate: its operator trusts it.
    let (code, _, err) = probe(args);
    assert_eq!(code, 1, "{err}");
    let own = pki.join("own/cert.der");
    assert!(err.contains("made the bridge's certificate"), "{err}");
    assert!(err.contains("BadCertificateUntrusted"), "{err}");
    assert!(
        err.contains(&format!(
            "refused the bridge: have it trust {}",
            own.display()
        )),
        "{err}"
    );
    std::fs::copy(&own, spki.join("trusted/plant-agent.der")).unwrap();
    // The bridge refuses the server's certificate: its operator checks it and trusts it.
    let (code, _, err) = probe(args);
    assert_eq!(code, 1, "{err}");
    let rejected: Vec<PathBuf> = std::fs::read_dir(pki.join("rejected"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    assert_eq!(rejected.len(), 1, "{rejected:?}");
    assert!(
        err.contains(&format!("it is in {}", rejected[0].display())),
        "{err}"
    );
    let name = rejected[0].file_name().unwrap();
    std::fs::rename(&rejected[0], pki.join("trusted").join(name)).unwrap();
    assert_eq!(
        std::fs::read(pki.join("trusted").join(name)).unwrap(),
        std::fs::read(spki.join("own/cert.der")).unwrap(),
        "the certificate refused is the server's"
    );
    let (code, out, err) = probe(args);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("ns=2;s=Plant.Output"), "{out}");
}

/// A server that speaks only Basic256Sha256 with SignAndEncrypt and knows its one user by
/// a certificate. The agent will not start without a certificate of its own and says how
/// to make one; the probe makes it; each side refuses the other until its operator trusts
/// the other's certificate, and each refusal says which certificate to trust where; then
/// the loop runs signed and encrypted, and SIGTERM leaves the safe value. A map asking for
/// no security is told what the server offers; a stranger's user certificate is refused.
#[test]
fn a_secure_server_is_reached_once_each_side_trusts_the_other() {
    let dir = scratch("opcua", "secure");
    user_certificate(&dir.join("user"));
    user_certificate(&dir.join("stranger"));
    let spki = dir.join("server-pki");
    let server = server(&[
        "--security",
        "Basic256Sha256_SignAndEncrypt",
        "--pki",
        spki.to_str().unwrap(),
        "--user-certificate",
        dir.join("user.der").to_str().unwrap(),
    ]);
    let scenario = scenario_with(&dir, server.port, 0, 60.0, SECURE);
    let error = refused(&scenario, &dir);
    assert!(error.contains("--create-keypair"), "{error}");

    let pki = dir.join("pki");
    let endpoint = server.address();
    let user = dir.join("user.der");
    let key = dir.join("user.pem");
    let args = [
        endpoint.as_str(),
        "--security-policy",
        "Basic256Sha256",
        "--security-mode",
        "SignAndEncrypt",
        "--pki-dir",
        pki.to_str().unwrap(),
        "--create-keypair",
        "--user-certificate",
        user.to_str().unwrap(),
        "--user-private-key",
        key.to_str().unwrap(),
        "--depth",
        "2",
    ];
    trust_each_other(&args, &pki, &spki);

    // Trusted both ways: the loop runs, and SIGTERM leaves the safe value.
    let out = dir.join("out");
    let mut child = agent(&scenario, &out);
    let mut spec = SessionSpec::plain(&endpoint, Duration::from_secs(10));
    spec.policy = "Basic256Sha256".into();
    spec.mode = "SignAndEncrypt".into();
    spec.pki_dir = Some(pki.clone());
    spec.identity = OpcUaUser::Certificate {
        cert: user.clone(),
        key: key.clone(),
    };
    wait_for_an_input(|| server.node_with(&spec, "Applied"));
    interrupted_after_a_second(&mut child, &out);
    assert_eq!(server.node_with(&spec, "Input"), SAFE);

    // No security asked of a server that has none to offer, and a stranger for a user.
    let plain = scenario_with(&dir, server.port, 0, 5.0, "");
    let error = refused(&plain, &dir);
    assert!(
        error.contains("no endpoint with None/None; it offers Basic256Sha256/SignAndEncrypt"),
        "{error}"
    );
    let stranger = scenario_with(
        &dir,
        server.port,
        0,
        5.0,
        &SECURE.replace("\"user.", "\"stranger."),
    );
    let error = refused(&stranger, &dir);
    assert!(error.contains("BadUserAccessDenied"), "{error}");
    assert!(
        !error.contains("trust"),
        "not a matter of certificates: {error}"
    );
    assert_eq!(
        server.node_with(&spec, "Input"),
        SAFE,
        "nothing written since"
    );
}
