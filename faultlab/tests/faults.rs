//! The loop survives loss, latency, bursts, outages and a controller crash: real Zenoh
//! sessions through the impairment relay, real time, fixed seeds (a failure replays).

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use faultlab::campaign::{run_case, CaseOptions};
use faultlab::profile::{GilbertElliott, Impairment, Outage, Profile};
use faultlab::relay::Link;
use plant_agent::agent::{run_agent, Fallback, LoopMode};
use plant_agent::demo::{agent_config, rand_id, service_config};
use plant_agent::plant::SimPlant;
use plant_agent::scenario::{load_scenario, shipped_controller, Scenario};

static SERIAL: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

fn scenario(duration: f64) -> Scenario {
    let mut s = load_scenario("2").unwrap();
    s.duration = duration;
    s
}

fn profile(name: &str, imp: Impairment) -> Profile {
    Profile {
        name: name.into(),
        seed: 42,
        both: imp,
        up: None,
        down: None,
    }
}

/// 10 % random loss keeps the MFC's RMS within 1.5x of the unimpaired run with no
/// fallback. With 20 ± 5 ms one-way latency on top (40 ms round trips: every command lands
/// four periods late) the loop stays bounded and safe, but the example bar (1.5x)
/// is NOT met: the pitch RMS about doubles (see README, "Faults"). This test asserts the
/// safety envelope there, not the bar.
#[tokio::test(flavor = "multi_thread")]
async fn loss_and_latency_degrade_gracefully() {
    let _s = SERIAL.lock().await;
    let s = scenario(15.0);
    let c = [shipped_controller("ipd").unwrap()];
    let opts = CaseOptions::default();
    let base = run_case(
        &s,
        &c,
        &profile("none", Impairment::default()),
        Link::Udp,
        &opts,
    )
    .await
    .unwrap();
    let b = &base[0].report;

    let loss = Impairment {
        loss: 0.10,
        ..Default::default()
    };
    let hit = run_case(&s, &c, &profile("loss-10", loss), Link::Udp, &opts)
        .await
        .unwrap();
    let h = &hit[0].report;
    assert!(
        hit[0].relay.up.lost > 100,
        "the relay did lose packets: {:?}",
        hit[0].relay
    );
    assert_eq!(h.fallbacks, 0, "{h:?}");
    for (mb, mh) in b.channels.iter().zip(&h.channels) {
        let ratio = mh.rms / mb.rms;
        eprintln!(
            "loss-10 {}: {:.3e} vs {:.3e}: ratio {ratio:.2}",
            mb.name, mh.rms, mb.rms
        );
        assert!(ratio < 1.5, "loss-10 {}: ratio {ratio}", mb.name);
    }

    let both = Impairment {
        loss: 0.10,
        delay_ms: 20.0,
        jitter_ms: 5.0,
        ..Default::default()
    };
    let hit = run_case(
        &s,
        &c,
        &profile("loss-10-latency-20", both),
        Link::Udp,
        &opts,
    )
    .await
    .unwrap();
    let h = &hit[0].report;
    assert!(
        h.late as f64 > 0.5 * h.periods as f64,
        "commands do land late: {h:?}"
    );
    for (mb, mh) in b.channels.iter().zip(&h.channels) {
        eprintln!(
            "loss-10-latency-20 {}: ratio {:.2}",
            mb.name,
            mh.rms / mb.rms
        );
        assert!(
            mh.saturated_fraction < 0.3,
            "{}: runaway to saturation",
            mh.name
        );
    }
    assert!(
        h.channels[1].max_abs < 0.05,
        "pitch excursion {}",
        h.channels[1].max_abs
    );
}

/// 30 % bursty loss stays bounded: no runaway to saturation, the pitch stays near its
/// reference.
#[tokio::test(flavor = "multi_thread")]
async fn bursty_loss_30_stays_bounded() {
    let _s = SERIAL.lock().await;
    let s = scenario(12.0);
    let c = [shipped_controller("ipd").unwrap()];
    let ge = GilbertElliott {
        p_good_bad: 0.107,
        p_bad_good: 0.25,
        loss_good: 0.0,
        loss_bad: 1.0,
    };
    let imp = Impairment {
        burst: Some(ge),
        ..Default::default()
    };
    let opts = CaseOptions {
        record: true,
        ..CaseOptions::default()
    };
    let r = run_case(&s, &c, &profile("burst-30", imp), Link::Udp, &opts)
        .await
        .unwrap();
    let rep = &r[0].report;
    eprintln!("{rep:?}\nrelay: {:?}", r[0].relay);
    assert!(
        rep.missing as f64 > 0.2 * rep.periods as f64,
        "bursts bit: {} missing",
        rep.missing
    );
    // No runaway: a loop running away sits at the limit; this one may touch it (the
    // dead-zone compensation swings the pitch voltage) but never stays there.
    for (i, m) in rep.channels.iter().enumerate() {
        let mut longest = 0;
        let mut run = 0;
        for row in &r[0].rows {
            if row.v[i].abs() >= 24.0 - 1e-9 {
                run += 1;
                longest = longest.max(run);
            } else {
                run = 0;
            }
        }
        eprintln!(
            "{}: saturated {:.2}, longest stretch {longest} periods",
            m.name, m.saturated_fraction
        );
        assert!(
            m.saturated_fraction < 0.25,
            "{}: saturated {:.2}",
            m.name,
            m.saturated_fraction
        );
        assert!(
            longest < 50,
            "{}: at the limit for {longest} periods in a row",
            m.name
        );
    }
    assert!(
        rep.channels[1].max_abs < 0.1,
        "pitch worst {}",
        rep.channels[1].max_abs
    );
}

/// After a 1 s outage (at 4 s), the loop holds, falls back locally, and remote tracking
/// is back within 1 s of the link's return.
#[tokio::test(flavor = "multi_thread")]
async fn one_second_outage_recovers_within_a_second() {
    let _s = SERIAL.lock().await;
    let s = scenario(10.0);
    let c = [shipped_controller("ipd").unwrap()];
    let imp = Impairment {
        outages: vec![Outage {
            start_s: 4.0,
            duration_s: 1.0,
        }],
        ..Default::default()
    };
    for link in [Link::Udp, Link::Tcp] {
        let opts = CaseOptions {
            record: true,
            ..CaseOptions::default()
        };
        let r = run_case(&s, &c, &profile("outage", imp.clone()), link, &opts)
            .await
            .unwrap();
        let rows = &r[0].rows;
        let rep = &r[0].report;
        eprintln!("{link:?}: {rep:?}");
        assert_eq!(rep.fallbacks, 1, "{link:?}: one fallback");
        // The relay's clock starts a little before the plant's: find the outage in the rows.
        let first_fallback = rows
            .iter()
            .find(|r| r.mode == LoopMode::Fallback)
            .unwrap()
            .t;
        let back = rows
            .iter()
            .filter(|r| r.t > first_fallback && r.mode == LoopMode::Remote)
            .map(|r| r.t)
            .next()
            .unwrap();
        let outage_end = first_fallback - 0.06 + 1.0;
        eprintln!("{link:?}: fallback at {first_fallback:.2} s, remote again at {back:.2} s");
        assert!(
            back - outage_end < 1.0,
            "{link:?}: remote control back {:.2} s after the link",
            back - outage_end
        );
        assert!(rows
            .iter()
            .filter(|r| r.t > back + 0.5)
            .all(|r| r.mode == LoopMode::Remote));
        // Tracking after recovery is as good as before the outage.
        let worst = |from: f64, to: f64| {
            rows.iter()
                .filter(|r| r.t >= from && r.t < to)
                .map(|r| (r.y[1] - r.y_ref[1]).abs())
                .fold(0.0, f64::max)
        };
        let (before, after) = (worst(1.0, 3.9), worst(back + 1.0, 10.0));
        eprintln!("{link:?}: pitch worst before {before:.4}, after {after:.4}");
        assert!(after < 2.0 * before.max(0.01), "{link:?}");
    }
}

/// A controller service in a process of its own (`faultlab serve` runs the same library
/// code as the `controller-service` binary).
fn service_process(args: &[&str]) -> Child {
    Command::new(env!("CARGO_BIN_EXE_faultlab"))
        .arg("serve")
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// Wait (at most 20 s) until controller `id` is up, as its liveliness token says.
async fn wait_for_controller(endpoint: &str, id: &str) {
    let session = transport::ZenohArgs::loopback(None, vec![endpoint.to_string()])
        .open()
        .await
        .unwrap();
    let up = transport::wait_for_token(
        &session,
        &protocol::keys::alive_controller(id),
        Duration::from_secs(20),
    )
    .await;
    let _ = session.close().await;
    assert!(up, "controller {id} at {endpoint} never came up");
}

fn start_service(config: &std::path::Path, endpoint: &str) -> Child {
    Command::new(env!("CARGO_BIN_EXE_faultlab"))
        .arg("serve")
        .args([
            "--config",
            config.to_str().unwrap(),
            "--listen",
            endpoint,
            "--no-multicast-scouting",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// kill -9 the controller service mid-run: the agent notices within its command deadline
/// (not zenoh's 10 s lease), holds, falls back, stays in bounds; a restarted service
/// restores the device from its last snapshot (state, counters, reference phase) and
/// remote control resumes.
#[tokio::test(flavor = "multi_thread")]
async fn controller_crash_and_restart() {
    let _s = SERIAL.lock().await;
    let s = scenario(12.0);
    let c = shipped_controller("ipd").unwrap();
    let dir = std::env::temp_dir().join(format!("crash-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let cfg_file = dir.join("service.toml");
    let mut svc = service_config(&s, &c, &["aero-1".into()]);
    svc.snapshots = Some(controller_service::config::SnapshotSpec {
        dir: dir.join("snapshots"),
        interval_ms: 200,
    });
    std::fs::write(&cfg_file, toml::to_string(&svc).unwrap()).unwrap();
    let port = transport::free_local_port().unwrap();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let mut service = start_service(&cfg_file, &endpoint);
    wait_for_controller(&endpoint, "controller-1").await;

    let mut agent = agent_config(
        &s,
        &c,
        "aero-1",
        5,
        Fallback::Local,
        Some(dir.join("run.csv")),
    );
    agent.max_age = 10;
    let plant_endpoint = endpoint.clone();
    let params = s.plant.clone();
    let run = tokio::spawn(async move {
        let session = transport::ZenohArgs::loopback(None, vec![plant_endpoint])
            .open()
            .await
            .unwrap();
        let mut plant = SimPlant::new(params, 1).unwrap();
        let out = run_agent(&session, &mut plant, &agent, rand_id(9)).await;
        let _ = session.close().await;
        out
    });
    tokio::time::sleep(Duration::from_secs(4)).await;
    service.kill().unwrap(); // SIGKILL: no clean close, no liveliness goodbye
    let _ = service.wait();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let mut restarted = start_service(&cfg_file, &endpoint);
    let (report, rows) = run.await.unwrap().unwrap();
    // The restarted service counts every sample since the start: it resumed from the
    // snapshot (about 380 samples before the kill) rather than from zero.
    let client = transport::ZenohArgs::loopback(None, vec![endpoint.clone()])
        .open()
        .await
        .unwrap();
    let status: protocol::pb::DeviceStatus = protocol::decode(
        &transport::get_first(&client, &protocol::keys::status("aero-1"), None)
            .await
            .unwrap(),
    )
    .unwrap();
    let _ = client.close().await;
    let _ = restarted.kill();
    let _ = restarted.wait();
    // Without the snapshot it could have seen at most the 600 periods after the restart.
    let after_restart = rows.iter().filter(|r| r.t > 6.0).count() as u64;
    eprintln!(
        "status after restart: {} samples, {} lost; {after_restart} periods since the restart",
        status.samples, status.lost
    );
    assert!(
        status.samples > after_restart + 100,
        "restored counters: {status:?}"
    );
    assert!(
        status.lost > 100,
        "the seq gap of the outage is counted: {status:?}"
    );

    eprintln!("{report:?}");
    assert_eq!(report.fallbacks, 1);
    // From the last remote period to the fallback: hold_periods plus at most one.
    let first_fb = rows
        .iter()
        .position(|r| r.mode == LoopMode::Fallback)
        .unwrap();
    let last_remote = rows[..first_fb]
        .iter()
        .rposition(|r| r.mode == LoopMode::Remote)
        .unwrap();
    assert!(
        first_fb - last_remote <= 7,
        "fallback after {} periods",
        first_fb - last_remote
    );
    // Control resumed after the restart and stayed in bounds throughout.
    let back = rows[first_fb..]
        .iter()
        .position(|r| r.mode == LoopMode::Remote)
        .map(|p| p + first_fb);
    let back = back.expect("remote control never resumed");
    eprintln!(
        "killed ~4.0 s, fallback at {:.2} s, restart ~6.0 s, remote again at {:.2} s",
        rows[first_fb].t, rows[back].t
    );
    assert!(rows[back].t < 10.0);
    let worst = rows
        .iter()
        .map(|r| (r.y[1] - r.y_ref[1]).abs())
        .fold(0.0, f64::max);
    assert!(worst < 0.05, "pitch error reached {worst} rad");
    assert!(rows.iter().all(|r| r.y[1].abs() < 1.0), "pitch stop");
}

/// Hot standby: two services for the same device, one active, one warm (fed the same
/// samples, publishing nothing). kill -9 the active one: the standby takes over within 5
/// periods through the heartbeat, no fallback, and no sample gets two commands.
#[tokio::test(flavor = "multi_thread")]
async fn hot_standby_takes_over_within_five_periods() {
    let _s = SERIAL.lock().await;
    let s = scenario(8.0);
    let c = shipped_controller("ipd").unwrap();
    let dir = std::env::temp_dir().join(format!("standby-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (pa, pb) = (
        transport::free_local_port().unwrap(),
        transport::free_local_port().unwrap(),
    );
    let (ea, eb) = (format!("tcp/127.0.0.1:{pa}"), format!("tcp/127.0.0.1:{pb}"));
    let write = |name: &str, id: &str, role: &str| {
        let mut cfg = service_config(&s, &c, &["aero-1".into()]);
        cfg.controller_id = id.into();
        let text = format!(
            "{}\n[standby]\ngroup = \"g1\"\nrole = \"{role}\"\n",
            toml::to_string(&cfg)
                .unwrap()
                .replace("templates = []\n", "")
        );
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    };
    let (fa, fb) = (
        write("a.toml", "ctl-a", "active"),
        write("b.toml", "ctl-b", "standby"),
    );
    let mut a = start_service(&fa, &ea);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let mut b = service_process(&[
        "--config",
        fb.to_str().unwrap(),
        "--listen",
        &eb,
        "--connect",
        &ea,
        "--no-multicast-scouting",
    ]);
    wait_for_controller(&ea, "ctl-a").await;
    wait_for_controller(&eb, "ctl-b").await;
    // Let the standby hear the active one's heartbeats (its start-up grace is 1 s).
    tokio::time::sleep(Duration::from_millis(1200)).await;

    let mut agent = agent_config(
        &s,
        &c,
        "aero-1",
        5,
        Fallback::Local,
        Some(dir.join("run.csv")),
    );
    agent.max_age = 10;
    let params = s.plant.clone();
    let endpoints = vec![ea.clone(), eb.clone()];
    let run = tokio::spawn(async move {
        let session = transport::ZenohArgs::loopback(None, endpoints)
            .open()
            .await
            .unwrap();
        let mut plant = SimPlant::new(params, 1).unwrap();
        let out = run_agent(&session, &mut plant, &agent, rand_id(11)).await;
        let _ = session.close().await;
        out
    });
    tokio::time::sleep(Duration::from_secs(3)).await;
    a.kill().unwrap();
    let _ = a.wait();
    let (report, rows) = run.await.unwrap().unwrap();
    let _ = b.kill();
    let _ = b.wait();
    eprintln!("{report:?}");
    assert_eq!(report.duplicate_commands, 0, "a sample got two commands");
    assert_eq!(report.fallbacks, 0, "the takeover came before the fallback");
    // The longest run of periods without a command, after the first second.
    let mut longest = 0;
    let mut run_len = 0;
    for r in rows.iter().filter(|r| r.t > 1.0) {
        if r.mode == LoopMode::Remote {
            run_len = 0;
        } else {
            run_len += 1;
            longest = longest.max(run_len);
        }
    }
    eprintln!("longest gap without a command: {longest} periods");
    assert!(longest <= 5, "takeover took {longest} periods");
    assert!((report.commands + report.warming_up) as f64 > 0.97 * report.periods as f64);
}
