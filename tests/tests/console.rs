//! The browser console, in a real browser: a service and a simulated AERO over real Zenoh
//! sessions on loopback, the console as a process of its own, and Debian's Chromium driven
//! by playwright-core (`tests/browser/console.mjs`). The page must list the device, its
//! plots must advance, a gain changed in the page must reach the service as a partial
//! change, a limit outside the envelope must be refused by the console itself, and a
//! second plant started while the page is open must appear and, when it ends, be marked
//! gone.
//!
//! `tests/browser/setup.sh` installs what the browser part needs when it is absent
//! (`chromium` from Debian, as root; `playwright-core`, pinned, from npm); `.ci/run` runs
//! it first. If it cannot, this test fails and says why: it never passes without a
//! browser. Screenshots go to a scratch directory, or to `MFC_CONSOLE_SCREENSHOTS`
//! (relative to the workspace root) when set: `MFC_CONSOLE_SCREENSHOTS=docs/figures`
//! refreshes the ones in the docs.

use std::collections::BTreeMap;
use std::process::Stdio;
use std::time::{Duration, Instant};

use mfc_lab::harness::{run_plant, service_config, ServiceHandle};
use plant::scenario::{load_scenario, shipped_controller};
use protocol::pb;
use system_tests::{scratch_dir, served_plant, workspace_root, SERIAL};
use tokio::io::{AsyncBufReadExt, BufReader};
use transport::ops;

/// Whatever the machine's load, the whole browser part must end within this.
const SCRIPT_DEADLINE: Duration = Duration::from_secs(300);

/// `tests/browser/setup.sh`'s `KEY=VALUE` lines.
fn browser_tools() -> BTreeMap<String, String> {
    let setup = std::process::Command::new("bash")
        .arg(workspace_root().join("tests/browser/setup.sh"))
        .output()
        .expect("running tests/browser/setup.sh");
    assert!(
        setup.status.success(),
        "tests/browser/setup.sh failed: the console's browser test needs Debian's chromium \
         (apt-get install chromium, as root) and playwright-core from npm (the registry the \
         first time):\n{}",
        String::from_utf8_lossy(&setup.stderr)
    );
    String::from_utf8_lossy(&setup.stdout)
        .lines()
        .filter_map(|l| l.split_once('='))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect()
}

/// Wait until something accepts TCP connections on `port`.
async fn wait_for_port(port: u16, deadline: Duration) -> bool {
    let end = Instant::now() + deadline;
    while Instant::now() < end {
        if tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_ok()
        {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    false
}

fn law_kp(c: &pb::ChannelConfig) -> Option<f64> {
    match &c.law {
        Some(pb::channel_config::Law::Intelligent(i)) => Some(i.kp),
        _ => None,
    }
}

/// The console, as a process, with the operator's flags and `extra`, connected to `ep`;
/// its HTTP port once it listens.
async fn start_console(
    ep: &str,
    scratch: &std::path::Path,
    extra: &[&str],
) -> (tokio::process::Child, u16) {
    let port = transport::free_local_port().unwrap();
    let log = std::fs::File::create(scratch.join("console.log")).unwrap();
    let mut console = tokio::process::Command::new(env!("CARGO_BIN_EXE_console-under-test"))
        .args([
            "--connect",
            ep,
            "--mode",
            "peer",
            "--no-multicast-scouting",
            "--listen-http",
            &format!("127.0.0.1:{port}"),
        ])
        .args(extra)
        .stdout(Stdio::null())
        .stderr(log)
        .kill_on_drop(true)
        .spawn()
        .expect("starting the console");
    assert!(
        wait_for_port(port, Duration::from_secs(60)).await,
        "the console did not listen on {port} ({:?}); its log:\n{}",
        console.try_wait(),
        std::fs::read_to_string(scratch.join("console.log")).unwrap_or_default()
    );
    (console, port)
}

/// Wait until the service has served `dev` for a while.
async fn served_for_a_while(operator: &impl ops::Asker, dev: &str) {
    let end = Instant::now() + Duration::from_secs(60);
    loop {
        let st = ops::device_status(operator, dev, Duration::from_secs(2)).await;
        if st.as_ref().is_ok_and(|st| st.samples > 100) {
            break;
        }
        assert!(Instant::now() < end, "{dev} is not served: {st:?}");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// What the browser script reported: its stages, each with its data; and the second plant
/// it had started once the page loaded.
struct BrowserRun {
    stages: Vec<(String, serde_json::Value)>,
    late_plant: Option<tokio::task::JoinHandle<anyhow::Result<plant_agent::agent::AgentRun>>>,
    secs: f64,
}

/// Run `tests/browser/{script}` in Chromium with `vars` (besides the tools' and the
/// profile's); `on_stage` sees each stage as it comes. Fails unless the script ends well
/// within [`SCRIPT_DEADLINE`] having passed exactly `want` stages; its stages.
async fn drive(
    script: &str,
    vars: &[(&str, String)],
    (scratch, shots): (&std::path::Path, &std::path::Path),
    want: &[&str],
    mut on_stage: impl FnMut(&str),
) -> Vec<(String, serde_json::Value)> {
    let tools = browser_tools();
    let profile = scratch.join(format!("chromium-profile-{script}"));
    std::fs::create_dir_all(&profile).unwrap();
    let mut child = tokio::process::Command::new(&tools["node"])
        .arg(workspace_root().join("tests/browser").join(script))
        .env("MFC_NODE_PREFIX", &tools["prefix"])
        .env("MFC_CHROMIUM", &tools["chromium"])
        .env("MFC_CONSOLE_SCREENSHOTS", shots)
        .env("MFC_CONSOLE_PROFILE", &profile)
        .envs(vars.iter().map(|(k, v)| (k, v)))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .unwrap_or_else(|e| panic!("running node on tests/browser/{script}: {e}"));
    let stderr = child.stderr.take().unwrap();
    let errors = tokio::spawn(async move {
        let mut text = String::new();
        let mut lines = BufReader::new(stderr).lines();
        while let Ok(Some(l)) = lines.next_line().await {
            text.push_str(&l);
            text.push('\n');
        }
        text
    });
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    let mut stages: Vec<(String, serde_json::Value)> = Vec::new();
    let read = tokio::time::timeout(SCRIPT_DEADLINE, async {
        while let Ok(Some(line)) = lines.next_line().await {
            eprintln!("browser: {line}");
            let Some(rest) = line.strip_prefix("STAGE ") else {
                continue;
            };
            let (name, data) = rest.split_once(' ').unwrap_or((rest, "{}"));
            on_stage(name);
            stages.push((
                name.to_string(),
                serde_json::from_str(data).unwrap_or_default(),
            ));
        }
    })
    .await;
    let status = tokio::time::timeout(Duration::from_secs(30), child.wait()).await;
    let stderr = errors.await.unwrap_or_default();
    let names: Vec<&str> = stages.iter().map(|(n, _)| n.as_str()).collect();
    assert!(
        read.is_ok(),
        "{script} did not end within {SCRIPT_DEADLINE:?}; stages {names:?}\n{stderr}"
    );
    let ok = matches!(&status, Ok(Ok(st)) if st.success());
    assert!(
        ok,
        "{script} failed ({status:?}) after stages {names:?}:\n{stderr}\n(screenshots in {}, \
         the console's log in {})",
        shots.display(),
        scratch.join("console.log").display()
    );
    assert_eq!(names, want, "{stderr}");
    stages
}

/// Drive the page with `tests/browser/console.mjs` in Chromium, starting `late` once the
/// page has loaded; fail unless the script ends well within [`SCRIPT_DEADLINE`].
async fn run_browser(
    port: u16,
    dirs: (&std::path::Path, &std::path::Path),
    ep: &str,
    late: &mfc_lab::harness::PlantSpec,
) -> BrowserRun {
    let started = Instant::now();
    let mut late_plant = None;
    let vars = [
        ("MFC_CONSOLE_URL", format!("http://127.0.0.1:{port}/")),
        ("MFC_CONSOLE_DEVICE", "aero-1".into()),
        ("MFC_CONSOLE_LATE_DEVICE", "aero-2".into()),
    ];
    let want = [
        "loaded",
        "plots",
        "appeared",
        "gain",
        "audit",
        "envelope-refused",
        "reference",
        "commission",
        "gone",
        "done",
    ];
    let stages = drive("console.mjs", &vars, dirs, &want, |name| {
        if name == "loaded" && late_plant.is_none() {
            late_plant = Some(tokio::spawn(run_plant(
                vec![ep.to_string()],
                late.clone(),
                true,
            )));
        }
    })
    .await;
    BrowserRun {
        stages,
        late_plant,
        secs: started.elapsed().as_secs_f64(),
    }
}

/// What the page saw: plots advancing in plant time with more points, none of the loops'
/// messages refused, most samples joined to their command.
fn judge_page(stages: &[(String, serde_json::Value)]) {
    let plots = &stages[1].1;
    let (t1, t2) = (
        plots["first"]["y0"]["last"].as_f64().unwrap(),
        plots["second"]["y0"]["last"].as_f64().unwrap(),
    );
    assert!(t2 >= t1 + 1.0, "{plots}");
    // A few periods of warm-up and losses aside.
    // The accepted gain in the audit view: who (the console's operator, unverified: the
    // service has no access section) and what moved.
    let row = stages[4].1["row"].as_str().unwrap_or_default();
    assert!(
        row.contains("channel 1 kp: 9 → 12") && row.contains("unverified"),
        "{row}"
    );
    let counters = &stages[9].1["counters"];
    for k in [
        "bad_id",
        "bad_values",
        "oversized",
        "undecodable",
        "devices_refused",
    ] {
        assert_eq!(counters[k].as_u64(), Some(0), "{k}: {counters}");
    }
    let (samples, commands) = (
        counters["samples"].as_u64().unwrap(),
        counters["commands"].as_u64().unwrap(),
    );
    assert!(samples > 500 && commands * 10 > samples * 8, "{counters}");
}

/// The service's configuration after the page: kp of channel 1 is 12, channel 0's alpha
/// the one commissioning found, and nothing else changed but the reference the page set
/// (the refused max never reached the service: the console refused it, so the service
/// counted no refusal).
fn judge_change(before: &pb::DeviceConfig, after: &pb::DeviceConfig) {
    assert_eq!(law_kp(&after.channels[1]), Some(12.0), "{after:?}");
    let alpha = match &after.channels[0].law {
        Some(pb::channel_config::Law::Intelligent(i)) => i.alpha,
        other => panic!("{other:?}"),
    };
    // The shipped iP's 1e-3; commissioning the azimuth velocity finds 1.5-2.8e-4
    // (docs/commissioning.md).
    assert!((5e-5..1e-3).contains(&alpha), "alpha {alpha}");
    let mut expected0 = before.channels[0];
    if let Some(pb::channel_config::Law::Intelligent(i)) = &mut expected0.law {
        i.alpha = alpha;
    }
    assert_eq!(
        after.channels[0], expected0,
        "only alpha changed on channel 0"
    );
    assert_eq!(
        after.channels[1].output, before.channels[1].output,
        "channel 1's output map untouched (max=100 was refused)"
    );
    let mut expected = before.channels[1];
    if let Some(pb::channel_config::Law::Intelligent(i)) = &mut expected.law {
        i.kp = 12.0;
    }
    assert_eq!(after.channels[1], expected, "only kp changed on channel 1");
    assert_eq!(after.envelope, before.envelope);
    let r = after.reference.clone().unwrap_or_default();
    let constant = |ch: usize| match r.channels.get(ch).and_then(|c| c.pieces.first()) {
        Some(pb::Piece {
            shape: Some(pb::piece::Shape::Constant(c)),
        }) => Some(c.value),
        _ => None,
    };
    assert_eq!(constant(1), Some(0.05), "{r:?}");
}

#[tokio::test(flavor = "multi_thread")]
async fn the_console_shows_live_devices_and_changes_one_gain() {
    let _s = SERIAL.lock().await;
    let started = Instant::now();
    let scratch = scratch_dir("console");
    let shots = match std::env::var("MFC_CONSOLE_SCREENSHOTS") {
        Ok(d) if !d.is_empty() => workspace_root().join(d),
        _ => scratch.join("screenshots"),
    };
    std::fs::create_dir_all(&shots).unwrap();
    for f in [
        "console-gain.png",
        "console-fleet.png",
        "console-commission.png",
    ] {
        let _ = std::fs::remove_file(shots.join(f));
    }

    // A service for two AEROs; aero-1 runs throughout (the test stops it), aero-2 starts
    // once the page is open and ends after 15 s of plant time.
    let mut s = load_scenario("1").unwrap();
    s.duration = 180.0;
    let c = shipped_controller("ipd").unwrap();
    let ids = ["aero-1".to_string(), "aero-2".to_string()];
    let service = ServiceHandle::start(service_config(&s, &c, &ids), None)
        .await
        .unwrap();
    let ep = service.endpoint.clone();
    let plant = tokio::spawn(run_plant(
        vec![ep.clone()],
        served_plant(&s, &c, "aero-1"),
        true,
    ));
    let mut late = s.clone();
    late.duration = 15.0;
    let late = served_plant(&late, &c, "aero-2");
    let (mut console, port) = start_console(&ep, &scratch, &[]).await;

    // What the service holds before the page changes anything.
    let operator = service.client().await.unwrap();
    let timeout = Duration::from_secs(2);
    served_for_a_while(&operator, "aero-1").await;
    let before = ops::config(&operator, "aero-1", timeout).await.unwrap();
    let refused_before = ops::services(&operator, timeout).await.unwrap()[0].requests_refused;
    assert_eq!(law_kp(&before.channels[1]), Some(9.0), "{before:?}");

    let browser = run_browser(port, (&scratch, &shots), &ep, &late).await;
    judge_page(&browser.stages);
    let after = ops::config(&operator, "aero-1", timeout).await.unwrap();
    judge_change(&before, &after);
    let refused_after = ops::services(&operator, timeout).await.unwrap()[0].requests_refused;
    assert_eq!(
        refused_after, refused_before,
        "the service saw no refused request"
    );
    for f in [
        "console-gain.png",
        "console-fleet.png",
        "console-commission.png",
    ] {
        let len = std::fs::metadata(shots.join(f)).map_or(0, |m| m.len());
        assert!(len > 10_000, "screenshot {f}: {len} bytes");
    }
    eprintln!(
        "console test: browser part {:.1} s, whole test {:.1} s, screenshots in {}",
        browser.secs,
        started.elapsed().as_secs_f64(),
        shots.display()
    );

    // Stop everything this test started.
    let _ = console.kill().await;
    plant.abort();
    if let Some(p) = browser.late_plant {
        let _ = p.await;
    }
    let _ = operator.close().await;
    service.stop().await.unwrap();
}

// ---- the console with logins -------------------------------------------------------------

/// One HTTPS request to the console on `port`, checking its certificate against `ca`,
/// with the client certificate `client` (`(cert, key)`) if any; the status, the head
/// (lowercase) and the JSON body, or why the connection failed.
async fn https(
    port: u16,
    ca: &std::path::Path,
    client: Option<(&std::path::Path, &std::path::Path)>,
    (method, path, body): (&str, &str, Option<&str>),
) -> Result<(u16, String, serde_json::Value), String> {
    use rustls::pki_types::ServerName;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let pem = |p: &std::path::Path| std::fs::read(p).unwrap();
    let mut roots = rustls::RootCertStore::empty();
    for c in rustls_pemfile::certs(&mut &pem(ca)[..]) {
        roots.add(c.unwrap()).unwrap();
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots);
    let config = match client {
        Some((cert, key)) => {
            let certs = rustls_pemfile::certs(&mut &pem(cert)[..])
                .collect::<Result<Vec<_>, _>>()
                .unwrap();
            let key = rustls_pemfile::private_key(&mut &pem(key)[..])
                .unwrap()
                .unwrap();
            builder.with_client_auth_cert(certs, key).unwrap()
        }
        None => builder.with_no_client_auth(),
    };
    let tcp = tokio::net::TcpStream::connect(("127.0.0.1", port))
        .await
        .map_err(|e| e.to_string())?;
    let name = ServerName::IpAddress(std::net::IpAddr::from([127, 0, 0, 1]).into());
    let mut tls = tokio_rustls::TlsConnector::from(std::sync::Arc::new(config))
        .connect(name, tcp)
        .await
        .map_err(|e| format!("handshake: {e}"))?;
    let body = body.unwrap_or("");
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    tls.write_all(req.as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut buf = Vec::new();
    // TLS 1.3 reports a refused client certificate on the first read.
    let read = tls.read_to_end(&mut buf).await;
    if buf.is_empty() {
        return Err(format!("no answer: {read:?}"));
    }
    let text = String::from_utf8_lossy(&buf);
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    let json = serde_json::from_str(body).unwrap_or_default();
    Ok((status, head.to_ascii_lowercase(), json))
}

/// The console's settings as `mfc-deploy` wrote them for console `desk` (its people alice,
/// an operator, and vera, a viewer, who log in with their certificates; HTTPS with its
/// certificate for 127.0.0.1), with a password hash added for each, as the file says to.
fn login_settings(pki: &std::path::Path, alice_hash: &str) -> std::path::PathBuf {
    let path = pki.join("consoles/desk/desk.console.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let vera = mfc_console::cli::hash_password("vera-sees-only").unwrap();
    let mut out = String::new();
    for line in text.lines() {
        out.push_str(line);
        out.push('\n');
        for (who, hash) in [("alice", alice_hash), ("vera", vera.as_str())] {
            if line == format!("name = \"{who}\"") {
                out.push_str(&format!("password_hash = \"{hash}\"\n"));
            }
        }
    }
    let hashes = out
        .lines()
        .filter(|l| l.starts_with("password_hash = "))
        .count();
    assert_eq!(hashes, 2, "{out}");
    std::fs::write(&path, out).unwrap();
    path
}

/// `mfc-console --hash-password`, the way an operator makes a user's hash.
fn hash_with_the_binary(password: &str) -> String {
    use std::io::Write;
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_console-under-test"))
        .arg("--hash-password")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    writeln!(child.stdin.take().unwrap(), "{password}").unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    let hash = String::from_utf8(out.stdout).unwrap().trim().to_string();
    assert!(hash.starts_with("$argon2id$"), "{hash}");
    assert!(mfc_console::cli::verify_password(&hash, password));
    assert!(!mfc_console::cli::verify_password(&hash, "another"));
    hash
}

/// Who may read and change on the service in the login test: the console's people, the
/// console's own polls, and the test's judge.
const LOGIN_ACCESS: &str = r#"
verified = false
operators = [
  { name = "alice", role = "operator" },
  { name = "vera", role = "viewer" },
  { name = "desk", role = "viewer" },
  { name = "judge", role = "viewer" },
]
"#;

/// What plain HTTPS clients (no browser) get from the console with logins, after the
/// browser's part: each is held to who its certificate or password says it is.
async fn https_clients_are_held_to_who_they_are(
    port: u16,
    pki: &std::path::Path,
    theirs: &std::path::Path,
) {
    let ca = pki.join("ca/ca.pem");
    let cert = |dir: &std::path::Path, n: &str| {
        let d = dir.join(format!("operators/{n}/{n}"));
        (d.with_extension("pem"), d.with_extension("key"))
    };
    let ask = |client: Option<(std::path::PathBuf, std::path::PathBuf)>,
               req: (&'static str, &'static str, Option<&'static str>)| {
        let ca = ca.clone();
        async move {
            https(
                port,
                &ca,
                client.as_ref().map(|(c, k)| (c.as_path(), k.as_path())),
                req,
            )
            .await
        }
    };
    let get = |p| ("GET", p, None);
    // Nobody: the page (it holds the login form), and no API.
    assert_eq!(ask(None, get("/")).await.unwrap().0, 200);
    for p in ["/api/devices", "/api/me", "/api/devices/aero-1/audit"] {
        let (s, _, b) = ask(None, get(p)).await.unwrap();
        assert_eq!(s, 401, "{p}: {b}");
    }
    // alice's certificate: she is alice, an operator, by certificate.
    let (s, _, b) = ask(Some(cert(pki, "alice")), get("/api/me")).await.unwrap();
    assert_eq!(
        (s, &b["name"], &b["role"], &b["proof"]),
        (
            200,
            &"alice".into(),
            &"operator".into(),
            &"certificate".into()
        ),
        "{b}"
    );
    // vera's: her change is refused before it reaches the service.
    let change = (
        "POST",
        "/api/devices/aero-1/gains",
        Some(r#"{"channel": 1, "fields": {"kp": 11}}"#),
    );
    let (s, _, b) = ask(Some(cert(pki, "vera")), change).await.unwrap();
    assert_eq!(s, 403, "{b}");
    assert!(
        b["reason"].as_str().unwrap_or_default().contains("viewer"),
        "{b}"
    );
    // alice of another CA: no connection at all.
    let r = ask(Some(cert(theirs, "alice")), get("/api/me")).await;
    assert!(r.is_err(), "a certificate of another CA was taken: {r:?}");
    // A password login gives a cookie no script reads, no other site sends, only over TLS.
    let login = (
        "POST",
        "/api/login",
        Some(r#"{"name": "alice", "password": "alice-changes-gains"}"#),
    );
    let (s, head, b) = ask(None, login).await.unwrap();
    assert_eq!(s, 200, "{b}");
    let cookie = head
        .lines()
        .find(|l| l.starts_with("set-cookie:"))
        .unwrap_or_default();
    for attr in [
        "mfc_session=",
        "httponly",
        "samesite=strict",
        "secure",
        "path=/",
    ] {
        assert!(cookie.contains(attr), "{attr} not in {cookie:?}");
    }
    // Guessing vera's password: after five wrong ones her name is locked, and even the
    // right one is refused until the lock ends.
    for guess in ["a", "b", "c", "d", "e"] {
        let body = format!(r#"{{"name": "vera", "password": "{guess}"}}"#);
        let (s, _, b) = https(port, &ca, None, ("POST", "/api/login", Some(&body)))
            .await
            .unwrap();
        assert_eq!(s, 401, "{b}");
    }
    let right = (
        "POST",
        "/api/login",
        Some(r#"{"name": "vera", "password": "vera-sees-only"}"#),
    );
    let (s, head, b) = ask(None, right).await.unwrap();
    assert_eq!(s, 429, "{b}");
    assert!(head.contains("retry-after: 30"), "{head}");
}

/// The service's record after the browser's part: alice's change, accepted, under her
/// name, and nothing from vera (the console refused her before the service saw anything).
async fn judge_login_audit(judge: &ops::Operator) {
    let logs = ops::audit(judge, Some("aero-1"), Duration::from_secs(3))
        .await
        .unwrap();
    let entries: Vec<&pb::AuditEntry> = logs.iter().flat_map(|l| &l.entries).collect();
    assert_eq!(entries.len(), 1, "{entries:?}");
    let e = entries[0];
    assert_eq!(
        (e.operator.as_str(), e.role.as_str(), e.accepted),
        ("alice", "operator", true),
        "{e:?}"
    );
    let kp: Vec<_> = e
        .changes
        .iter()
        .map(|c| (c.what.as_str(), c.old.as_str(), c.new.as_str()))
        .collect();
    assert_eq!(kp, [("channel 1 kp", "9", "12")], "{e:?}");
}

/// A fleet's PKI and bundles in `dir` (`mfc-deploy`'s): its CA, the operators' and, with
/// `console`, the bundle of console `desk` reached at 127.0.0.1, for alice and vera.
fn login_pki(dir: &std::path::Path, operators: &str, console: bool) {
    let desk = "consoles = [{ name = \"desk\", hosts = [\"127.0.0.1\"], people = [\"alice\", \"vera\"] }]\n";
    let inv = mfc_deploy::Inventory::parse(&format!(
        "services = [\"svc\"]\noperators = [{operators}]\n{}[router]\nhosts = [\"127.0.0.1\"]\n",
        if console { desk } else { "" }
    ))
    .unwrap();
    mfc_deploy::generate(&inv, dir, &[], time::OffsetDateTime::now_utc()).unwrap();
}

#[tokio::test(flavor = "multi_thread")]
async fn the_console_with_logins_refuses_strangers_and_viewers() {
    let _s = SERIAL.lock().await;
    let scratch = scratch_dir("console-login");
    let shots = match std::env::var("MFC_CONSOLE_SCREENSHOTS") {
        Ok(d) if !d.is_empty() => workspace_root().join(d),
        _ => scratch.join("screenshots"),
    };
    std::fs::create_dir_all(&shots).unwrap();
    let (pki, theirs) = (scratch.join("pki"), scratch.join("theirs"));
    login_pki(
        &pki,
        "\"alice\", { name = \"vera\", role = \"viewer\" }",
        true,
    );
    login_pki(&theirs, "\"alice\"", false);

    let mut s = load_scenario("1").unwrap();
    s.duration = 180.0;
    let c = shipped_controller("ipd").unwrap();
    let mut cfg = service_config(&s, &c, &["aero-1".to_string()]);
    cfg.access = Some(toml::from_str(LOGIN_ACCESS).unwrap());
    let service = ServiceHandle::start(cfg, None).await.unwrap();
    let ep = service.endpoint.clone();
    let plant = tokio::spawn(run_plant(
        vec![ep.clone()],
        served_plant(&s, &c, "aero-1"),
        true,
    ));
    let settings = login_settings(&pki, &hash_with_the_binary("alice-changes-gains"));
    let args = ["--config", settings.to_str().unwrap(), "--operator", "desk"];
    let (mut console, port) = start_console(&ep, &scratch, &args).await;
    let judge = ops::Operator {
        session: service.client().await.unwrap(),
        key: None,
        name: Some("judge".into()),
    };
    served_for_a_while(&judge, "aero-1").await;
    let before = ops::config(&judge, "aero-1", Duration::from_secs(3))
        .await
        .unwrap();
    assert_eq!(law_kp(&before.channels[1]), Some(9.0), "{before:?}");

    let vars = [
        ("MFC_CONSOLE_URL", format!("https://127.0.0.1:{port}/")),
        ("MFC_CONSOLE_DEVICE", "aero-1".into()),
        ("MFC_LOGIN_OPERATOR", "alice:alice-changes-gains".into()),
        ("MFC_LOGIN_VIEWER", "vera:vera-sees-only".into()),
    ];
    let want = ["refused", "wrong", "viewer", "out", "operator", "done"];
    let stages = drive("login.mjs", &vars, (&scratch, &shots), &want, |_| {}).await;
    let who = stages[2].1["who"].as_str().unwrap_or_default();
    assert!(who.contains("vera") && who.contains("viewer"), "{who}");
    let after = ops::config(&judge, "aero-1", Duration::from_secs(3))
        .await
        .unwrap();
    assert_eq!(law_kp(&after.channels[1]), Some(12.0), "{after:?}");
    judge_login_audit(&judge).await;
    https_clients_are_held_to_who_they_are(port, &pki, &theirs).await;

    let _ = console.kill().await;
    plant.abort();
    let _ = judge.session.close().await;
    service.stop().await.unwrap();
}
