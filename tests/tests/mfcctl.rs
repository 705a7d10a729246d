//! The operator's command line against a real service with a plant running, over real
//! Zenoh sessions: list, read, change one gain, steer the reference, narrow the envelope,
//! and a refused change reported as an error.

use std::time::Duration;

use clap::Parser;
use mfc_lab::harness::{run_plant, service_config, PlantSpec, ServiceHandle};
use mfcctl::cli::{run, MfcctlCli};
use plant::scenario::{load_scenario, shipped_controller};
use system_tests::SERIAL;

async fn ctl(endpoint: &str, args: &[&str]) -> anyhow::Result<String> {
    let mut argv = vec![
        "mfcctl",
        "--connect",
        endpoint,
        "--no-multicast-scouting",
        "--mode",
        "peer",
    ];
    argv.extend_from_slice(args);
    run(MfcctlCli::try_parse_from(argv)?).await
}

#[tokio::test(flavor = "multi_thread")]
async fn the_operator_reads_and_changes_a_running_device() {
    let _s = SERIAL.lock().await;
    let mut s = load_scenario("1").unwrap();
    s.duration = 8.0;
    let c = shipped_controller("ipd").unwrap();
    let service = ServiceHandle::start(service_config(&s, &c, &["aero-1".into()]), None)
        .await
        .unwrap();
    let ep = service.endpoint.clone();
    let plant = tokio::spawn(run_plant(
        vec![ep.clone()],
        PlantSpec::new(&s, &c, "aero-1"),
        true,
    ));
    tokio::time::sleep(Duration::from_secs(2)).await;

    let text = ctl(&ep, &["services"]).await.unwrap();
    assert!(
        text.contains("controller-1") && text.contains("active"),
        "{text}"
    );
    let text = ctl(&ep, &["devices"]).await.unwrap();
    assert!(
        text.contains("aero-1") && text.contains("controller-1"),
        "{text}"
    );
    let json = ctl(&ep, &["--json", "status", "aero-1"]).await.unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert!(v["samples"].as_u64().unwrap() > 100, "{json}");

    // One gain of the pitch loop (its iPD has kp 9: e'' + 3 e' + kp e = 0 stays well damped),
    // nothing else.
    let before = ctl(&ep, &["--json", "config", "aero-1"]).await.unwrap();
    let before: serde_json::Value = serde_json::from_str(&before).unwrap();
    let text = ctl(&ep, &["set", "aero-1", "--channel", "1", "kp=12"])
        .await
        .unwrap();
    assert!(text.contains("kp 12 "), "{text}");
    assert!(
        text.contains("acknowledged: held by "),
        "who holds the change: {text}"
    );
    let after = ctl(&ep, &["--json", "config", "aero-1"]).await.unwrap();
    let after: serde_json::Value = serde_json::from_str(&after).unwrap();
    assert_eq!(
        after["channels"][0], before["channels"][0],
        "channel 0 untouched"
    );
    assert_eq!(
        after["channels"][1]["output"],
        before["channels"][1]["output"]
    );
    assert_eq!(after["envelope"], before["envelope"]);

    // A parameter the law does not have, and a limit outside the envelope: refused, with
    // the controller's reason.
    let e = ctl(&ep, &["set", "aero-1", "--channel", "1", "b0=3"])
        .await
        .unwrap_err();
    assert!(e.to_string().contains("no b0"), "{e:#}");
    let e = ctl(&ep, &["set", "aero-1", "--channel", "1", "max=100"])
        .await
        .unwrap_err();
    assert!(e.to_string().contains("envelope"), "{e:#}");

    // Steer the reference and narrow the envelope; both read back.
    let text = ctl(&ep, &["reference", "aero-1", "--constant", "0,0.05"])
        .await
        .unwrap();
    assert!(text.contains("reference"), "{text}");
    let text = ctl(
        &ep,
        &[
            "envelope",
            "aero-1",
            "--channel",
            "1",
            "--min",
            "-20",
            "--max",
            "20",
            "--reason",
            "test",
        ],
    )
    .await
    .unwrap();
    assert!(text.contains("envelope: [-20, 20]"), "{text}");
    let text = ctl(&ep, &["status", "aero-1"]).await.unwrap();
    assert!(text.contains("envelope changes 1"), "{text}");
    // A device nobody serves: an error that says so.
    let e = ctl(&ep, &["status", "nobody"]).await.unwrap_err();
    assert!(e.to_string().contains("does not serve"), "{e:#}");

    let done = plant.await.unwrap().unwrap();
    eprintln!("{}", done.report.headline());
    assert!(done.report.completed());
    // The pitch followed the new reference of 0.05 rad: its mean over the last 2 s (the
    // AERO's pitch ripples by about 0.015 rad around its setpoint).
    let pitch = &done.record.traces[1].y;
    let tail = &pitch[pitch.len() - 200..];
    let mean = tail.iter().sum::<f64>() / tail.len() as f64;
    assert!(
        (mean - 0.05).abs() < 0.02,
        "pitch over the last 2 s: mean {mean}"
    );
    service.stop().await.unwrap();
}
