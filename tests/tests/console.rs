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

/// The console, as a process, with the operator's flags, connected to `ep`; its HTTP
/// port once it listens.
async fn start_console(ep: &str, scratch: &std::path::Path) -> (tokio::process::Child, u16) {
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
async fn served_for_a_while(operator: &zenoh::Session, dev: &str) {
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

/// Drive the page with `tests/browser/console.mjs` in Chromium, starting `late` once the
/// page has loaded; fail unless the script ends well within [`SCRIPT_DEADLINE`].
async fn run_browser(
    port: u16,
    (scratch, shots): (&std::path::Path, &std::path::Path),
    ep: &str,
    late: &mfc_lab::harness::PlantSpec,
) -> BrowserRun {
    let tools = browser_tools();
    let (node, prefix, chromium) = (&tools["node"], &tools["prefix"], &tools["chromium"]);
    let profile = scratch.join("chromium-profile");
    std::fs::create_dir_all(&profile).unwrap();
    let started = Instant::now();
    let mut script = tokio::process::Command::new(node)
        .arg(workspace_root().join("tests/browser/console.mjs"))
        .env("MFC_CONSOLE_URL", format!("http://127.0.0.1:{port}/"))
        .env("MFC_NODE_PREFIX", prefix)
        .env("MFC_CHROMIUM", chromium)
        .env("MFC_CONSOLE_DEVICE", "aero-1")
        .env("MFC_CONSOLE_LATE_DEVICE", "aero-2")
        .env("MFC_CONSOLE_SCREENSHOTS", shots)
        .env("MFC_CONSOLE_PROFILE", &profile)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("running node on tests/browser/console.mjs");
    let stderr = script.stderr.take().unwrap();
    let errors = tokio::spawn(async move {
        let mut text = String::new();
        let mut lines = BufReader::new(stderr).lines();
        while let Ok(Some(l)) = lines.next_line().await {
            text.push_str(&l);
            text.push('\n');
        }
        text
    });
    let mut lines = BufReader::new(script.stdout.take().unwrap()).lines();
    let mut stages: Vec<(String, serde_json::Value)> = Vec::new();
    let mut late_plant = None;
    let read = tokio::time::timeout(SCRIPT_DEADLINE, async {
        while let Ok(Some(line)) = lines.next_line().await {
            eprintln!("browser: {line}");
            let Some(rest) = line.strip_prefix("STAGE ") else {
                continue;
            };
            let (name, data) = rest.split_once(' ').unwrap_or((rest, "{}"));
            if name == "loaded" && late_plant.is_none() {
                late_plant = Some(tokio::spawn(run_plant(
                    vec![ep.to_string()],
                    late.clone(),
                    true,
                )));
            }
            stages.push((
                name.to_string(),
                serde_json::from_str(data).unwrap_or_default(),
            ));
        }
    })
    .await;
    let status = tokio::time::timeout(Duration::from_secs(30), script.wait()).await;
    let stderr = errors.await.unwrap_or_default();
    let names: Vec<&str> = stages.iter().map(|(n, _)| n.as_str()).collect();
    assert!(
        read.is_ok(),
        "the browser script did not end within {SCRIPT_DEADLINE:?}; stages {names:?}\n{stderr}"
    );
    let ok = matches!(&status, Ok(Ok(st)) if st.success());
    assert!(
        ok,
        "the browser script failed ({status:?}) after stages {names:?}:\n{stderr}\n(screenshots \
         in {}, the console's log in {})",
        shots.display(),
        scratch.join("console.log").display()
    );
    assert_eq!(
        names,
        [
            "loaded",
            "plots",
            "appeared",
            "gain",
            "audit",
            "envelope-refused",
            "reference",
            "gone",
            "done"
        ],
        "{stderr}"
    );
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
    let counters = &stages[8].1["counters"];
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

/// The service's configuration after the page: kp of channel 1 is 12, and nothing else
/// changed but the reference the page set (the refused max never reached the service:
/// the console refused it, so the service counted no refusal).
fn judge_change(before: &pb::DeviceConfig, after: &pb::DeviceConfig) {
    assert_eq!(law_kp(&after.channels[1]), Some(12.0), "{after:?}");
    assert_eq!(after.channels[0], before.channels[0], "channel 0 untouched");
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
    for f in ["console-gain.png", "console-fleet.png"] {
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
    let (mut console, port) = start_console(&ep, &scratch).await;

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
    for f in ["console-gain.png", "console-fleet.png"] {
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
