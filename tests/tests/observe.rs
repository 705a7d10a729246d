//! What operators see of a networked run, over real Zenoh sessions: the Prometheus endpoint
//! scraped over HTTP agrees with the service's status; the MCAP recording opens with the
//! `mcap` crate's reader and its embedded protobuf schemas decode its messages without the
//! generated types; a replay of the recording through the same controller matches its
//! commands, and a recording altered by one sample value does not.

use std::collections::BTreeMap;
use std::time::Duration;

use mfc_lab::harness::{run_plant, service_config, PlantSpec, ServiceHandle};
use plant::scenario::{load_scenario, shipped_controller};
use plant_agent::observe::AgentMetrics;
use protocol::pb;
use system_tests::{scratch_dir, SERIAL};
use telemetry::{read_recording, RecordSpec, Recording, Topic};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// `GET /metrics` with a bare HTTP/1.1 request: the endpoint as Prometheus scrapes it.
async fn scrape(addr: std::net::SocketAddr) -> String {
    let mut s = tokio::net::TcpStream::connect(addr).await.expect("connect");
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        .await
        .unwrap();
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8(buf).expect("utf-8");
    assert!(text.starts_with("HTTP/1.1 200"), "{text}");
    let body = text.split_once("\r\n\r\n").map(|(_, b)| b).unwrap_or("");
    // Chunked or not, the sample lines are intact: chunk sizes are lines of hex digits
    // alone, which no metric line is.
    body.to_string()
}

/// `name{labels}` → value, from an exposition text.
fn samples(text: &str) -> BTreeMap<String, f64> {
    text.lines()
        .filter(|l| l.starts_with("mfc_"))
        .filter_map(|l| {
            let (k, v) = l.rsplit_once(' ')?;
            Some((k.to_string(), v.parse().ok()?))
        })
        .collect()
}

/// The agent's side of the run: its metrics count what its report counts, and its own
/// recording holds one sample per period and the commands it received.
fn judge_agent(run: &plant_agent::agent::AgentRun, agent_text: &str, plant_mcap: &std::path::Path) {
    let am = samples(agent_text);
    let counters = &run.report.counters;
    assert_eq!(
        am["mfc_agent_periods_total{device=\"aero-1\"}"],
        counters.periods as f64
    );
    assert_eq!(
        am["mfc_agent_commands_total{device=\"aero-1\"}"],
        counters.commands as f64
    );
    assert_eq!(
        am["mfc_agent_missing_total{device=\"aero-1\"}"],
        counters.missing as f64
    );
    let pc = read_recording(&std::fs::read(plant_mcap).unwrap()).unwrap();
    let sent = pc
        .messages
        .iter()
        .filter(|m| m.topic == Topic::Sample)
        .count();
    assert_eq!(
        sent as u64, counters.periods,
        "one sample recorded per period"
    );
    assert!(pc.messages.iter().any(|m| m.topic == Topic::Command));
    assert_eq!(pc.metadata["dropped"], "0");
}

/// With the plant stopped nothing moves any more, so a status and a scrape taken one after
/// the other agree exactly. Returns the device's status and the scrape's text.
async fn status_and_scrape_agree(
    client: &zenoh::Session,
    addr: std::net::SocketAddr,
) -> (pb::DeviceStatus, String) {
    let status = transport::ops::services(client, Duration::from_secs(2))
        .await
        .unwrap();
    let text = scrape(addr).await;
    let m = samples(&text);
    assert_eq!(status.len(), 1);
    let st = &status[0];
    let d = st
        .devices
        .iter()
        .find(|d| d.device_id == "aero-1")
        .expect("the device in the status");
    let dl = "controller=\"controller-1\",device=\"aero-1\"";
    let get = |name: &str| -> f64 {
        *m.get(&format!("{name}{{{dl}}}"))
            .unwrap_or_else(|| panic!("no {name} in\n{text}"))
    };
    for (name, want) in [
        ("mfc_device_samples_total", d.samples),
        ("mfc_device_commands_total", d.commands),
        ("mfc_device_lost_total", d.lost),
        ("mfc_device_recovered_total", d.recovered),
        ("mfc_device_duplicates_total", d.duplicates),
        ("mfc_device_stale_total", d.stale),
        ("mfc_device_rejected_total", d.rejected),
        ("mfc_device_superseded_total", d.superseded),
        ("mfc_device_off_remote_total", d.samples_off_remote),
        ("mfc_device_clamped_total", d.clamped),
        ("mfc_device_restarts_total", d.restarts),
    ] {
        assert_eq!(get(name), want as f64, "{name}");
    }
    assert!(d.samples > 400, "{d:?}");
    for (i, f) in d.f_est.iter().enumerate() {
        let k = format!("mfc_device_f_estimate{{{dl},channel=\"{i}\"}}");
        let v = m[&k];
        assert!(v == *f || (v.is_nan() && f.is_nan()), "{k}: {v} vs {f}");
    }
    let sl = "{controller=\"controller-1\"}";
    for (name, want) in [
        ("mfc_service_queue_full_total", st.queue_full),
        ("mfc_service_undecodable_total", st.undecodable),
        ("mfc_service_unknown_samples_total", st.unknown_samples),
        ("mfc_service_rejected_total", st.rejected),
    ] {
        assert_eq!(m[&format!("{name}{sl}")], want as f64, "{name}");
    }
    assert_eq!(m[&format!("mfc_service_devices{sl}")], 1.0);
    // Histograms: one round trip per sample that carried one, one CPU time per answer.
    let rtts = get("mfc_device_loop_rtt_seconds_count");
    assert!(rtts > 0.0 && rtts <= d.samples as f64, "{rtts}");
    let cpus = get("mfc_device_sample_cpu_seconds_count");
    assert!(
        cpus >= d.commands as f64 && cpus <= d.samples as f64,
        "{cpus}"
    );
    assert!(text.contains(&format!(
        "mfc_device_loop_rtt_seconds_bucket{{{dl},le=\"0.01\"}}"
    )));
    // The service-wide series: every device's counters summed, and histograms over every
    // sample (here the one device's, all in once the plant has stopped).
    for (name, want) in [
        ("mfc_devices_samples_total", d.samples),
        ("mfc_devices_commands_total", d.commands),
        ("mfc_devices_lost_total", d.lost),
        ("mfc_service_device_series", 1),
    ] {
        assert_eq!(m[&format!("{name}{sl}")], want as f64, "{name}");
    }
    assert_eq!(
        m[&format!("mfc_devices_remote{sl}")],
        get("mfc_device_remote")
    );
    assert_eq!(m[&format!("mfc_service_loop_rtt_seconds_count{sl}")], rtts);
    assert_eq!(
        m[&format!("mfc_service_sample_cpu_seconds_count{sl}")],
        cpus
    );
    (d.clone(), text)
}

/// Every metric the shipped Grafana dashboard plots exists in a real scrape.
fn dashboard_plots_what_is_exported(exposed: &str) {
    let dash: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            system_tests::workspace_root().join("deploy/grafana/mfc-dashboard.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let mut plotted = 0;
    for p in dash["panels"].as_array().unwrap() {
        for t in p["targets"].as_array().unwrap() {
            let expr = t["expr"].as_str().unwrap();
            for word in expr.split(|c: char| !(c.is_ascii_alphanumeric() || c == '_')) {
                if word.starts_with("mfc_") {
                    plotted += 1;
                    // A series, or a family declared with none yet (the worst devices when
                    // none missed a sample).
                    assert!(
                        exposed.contains(&format!("\n{word}"))
                            || exposed.contains(&format!("# TYPE {word} ")),
                        "the dashboard plots {word}, which nothing exports"
                    );
                }
            }
        }
    }
    assert!(plotted >= 10);
}

/// The recording, read with the mcap crate's own reader: every channel's schema is a
/// protobuf descriptor set that decodes its messages by name, with no generated code.
fn recording_decodes_without_generated_code(bytes: &[u8], d: &pb::DeviceStatus) {
    let summary = mcap::Summary::read(bytes)
        .unwrap()
        .expect("a finished file");
    let mut decoded: BTreeMap<String, usize> = BTreeMap::new();
    for msg in mcap::MessageStream::new(bytes).unwrap() {
        let msg = msg.unwrap();
        let schema = msg.channel.schema.as_ref().expect("a schema");
        assert_eq!(schema.encoding, "protobuf");
        assert_eq!(msg.channel.message_encoding, "protobuf");
        let pool = prost_reflect::DescriptorPool::decode(schema.data.as_ref()).unwrap();
        let desc = pool.get_message_by_name(&schema.name).expect("the message");
        let dm = prost_reflect::DynamicMessage::decode(desc, msg.data.as_ref()).unwrap();
        if schema.name == "mfc.v1.Sample" {
            let outputs = dm.get_field_by_name("outputs").unwrap();
            assert_eq!(outputs.as_list().unwrap().len(), 2);
        }
        if schema.name == "mfc.v1.Command" {
            let r = dm.get_field_by_name("reference").unwrap();
            assert_eq!(
                r.as_list().unwrap().len(),
                2,
                "y* recorded with each command"
            );
        }
        *decoded.entry(msg.channel.topic.clone()).or_default() += 1;
    }
    assert!(summary.channels.len() >= 4, "{decoded:?}");
    assert!(
        decoded["/mfc/aero-1/sample"] as u64 >= d.samples,
        "{decoded:?}"
    );
    assert!(
        decoded["/mfc/aero-1/command"] as u64 >= d.commands,
        "{decoded:?}"
    );
    assert_eq!(decoded["/mfc/aero-1/config_request"], 1, "{decoded:?}");
    assert!(
        decoded["/mfc/aero-1/config"] >= 2,
        "at the start and after the change"
    );
}

/// A replay through the same controller gives the same commands; a recording cut short
/// replays up to the cut and says so; one with a sample altered by 1 mrad does not match.
fn replays(bytes: &[u8], d: &pb::DeviceStatus, dir: &std::path::Path) {
    let r = controller_service::replay::replay(bytes, 1e-9).unwrap();
    assert!(r.matched, "{}", controller_service::replay::render(&r));
    let dr = &r.devices[0];
    assert_eq!(dr.compared, d.commands, "every command compared");
    assert_eq!((dr.changes, dr.changes_refused), (1, 0));
    println!("{}", controller_service::replay::render(&r));

    // A recording whose writer was killed (cut at 60 %: no summary, no footer).
    let cut = controller_service::replay::replay(&bytes[..bytes.len() * 6 / 10], 1e-9).unwrap();
    assert!(cut.matched, "{}", controller_service::replay::render(&cut));
    assert!(
        cut.notes.iter().any(|n| n.contains("cut short")),
        "{:?}",
        cut.notes
    );
    let compared = cut.devices[0].compared;
    assert!(
        compared > 100 && compared < d.commands,
        "{compared} of {}",
        d.commands
    );

    // One output moved by 1 mrad, a third of the way in: the replay must see the
    // controller answer differently from there on.
    let c = read_recording(bytes).unwrap();
    let altered = dir.join("altered.mcap");
    let w = Recording::create(&RecordSpec::at(&altered), "test").unwrap();
    for (name, data) in &c.attachments {
        w.attach(name, "application/octet-stream", data.clone());
    }
    let samples_seen = c
        .messages
        .iter()
        .filter(|m| m.topic == Topic::Sample)
        .count();
    let mut k = 0;
    for m in &c.messages {
        let mut data = m.data.clone();
        if m.topic == Topic::Sample {
            k += 1;
            if k == samples_seen / 3 {
                let mut s: pb::Sample = protocol::decode(&data).unwrap();
                s.outputs[1] += 1e-3;
                data = protocol::encode(&s);
            }
        }
        w.record(&m.device, m.topic, m.log_ns, m.publish_ns, data);
    }
    w.finish().unwrap();
    let r = controller_service::replay::replay(&std::fs::read(&altered).unwrap(), 1e-9).unwrap();
    assert!(!r.matched, "{}", controller_service::replay::render(&r));
    assert!(r.devices[0].mismatches > 0);
}

#[tokio::test(flavor = "multi_thread")]
async fn metrics_match_the_status_and_a_recording_decodes_and_replays() {
    let _s = SERIAL.lock().await;
    let dir = scratch_dir("observe");
    let mut s = load_scenario("1").unwrap();
    s.duration = 6.0;
    let c = shipped_controller("ipd").unwrap();
    let mut config = service_config(&s, &c, &["aero-1".into()]);
    config.metrics = Some(telemetry::MetricsSpec {
        listen: "127.0.0.1:0".into(),
        devices: vec!["aero-1".into()],
        ..telemetry::MetricsSpec::default()
    });
    config.record = Some(RecordSpec::at(dir.join("service.mcap")));
    let service = ServiceHandle::start(config, None).await.unwrap();
    let addr = service.metrics.expect("a metrics endpoint");
    let ep = service.endpoint.clone();
    // The agent's side: its metrics and its own recording.
    let agent_metrics = std::sync::Arc::new(AgentMetrics::new(telemetry::Metrics::new()));
    let agent_rec =
        Recording::create(&RecordSpec::at(dir.join("plant.mcap")), "plant-agent").unwrap();
    let mut spec = PlantSpec::new(&s, &c, "aero-1");
    spec.loop_config.observers.metrics = Some(agent_metrics.clone());
    spec.loop_config.observers.recording = Some(agent_rec.clone());
    let plant = tokio::spawn(run_plant(vec![ep.clone()], spec, true));
    // A partial gain change and a reference change while it runs: the replay must apply
    // them where they happened.
    let client = service.client().await.unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let upd = transport::ops::parse_update(1, &["kp=12".to_string()]).unwrap();
    let now = transport::ops::update(&client, "aero-1", upd, Duration::from_secs(2))
        .await
        .expect("a partial gain change, accepted");
    // A single service: the change lives with it alone, and the reply says so.
    assert_eq!(now.held_by, ["controller-1"]);
    let now = now.config;
    assert_eq!(now.channels.len(), 2);
    let mid = scrape(addr).await;
    assert!(
        samples(&mid)
            .get("mfc_device_samples_total{controller=\"controller-1\",device=\"aero-1\"}")
            .is_some_and(|&n| n > 0.0),
        "{mid}"
    );
    let run = plant.await.unwrap().unwrap();
    assert!(run.report.controller_reached);
    agent_rec.finish().unwrap();
    let agent_text = agent_metrics.metrics().render();
    judge_agent(&run, &agent_text, &dir.join("plant.mcap"));
    let (d, text) = status_and_scrape_agree(&client, addr).await;
    service.stop().await.unwrap();
    dashboard_plots_what_is_exported(&format!("{text}\n{agent_text}"));
    let bytes = std::fs::read(dir.join("service.mcap")).unwrap();
    recording_decodes_without_generated_code(&bytes, &d);
    replays(&bytes, &d, &dir);
}

/// The service's own binary (`service-under-test` runs the same `cli::main_with_args`):
/// `--metrics` serves while it runs, `--record` writes a finished file when SIGTERM stops
/// it (summary, footer, nothing dropped), and a second start keeps the first file.
#[tokio::test(flavor = "multi_thread")]
async fn the_service_binary_serves_metrics_and_finishes_its_recording_on_sigterm() {
    let _s = SERIAL.lock().await;
    let dir = scratch_dir("observe-bin");
    let mut s = load_scenario("1").unwrap();
    s.duration = 3.0;
    let c = shipped_controller("ipd").unwrap();
    let config = service_config(&s, &c, &["aero-1".into()]);
    let file = dir.join("service.toml");
    std::fs::write(&file, toml::to_string(&config).unwrap()).unwrap();
    let rec = dir.join("service.mcap");
    for round in 0..2 {
        let endpoint = format!("tcp/127.0.0.1:{}", transport::free_local_port().unwrap());
        let metrics = format!("127.0.0.1:{}", transport::free_local_port().unwrap());
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_service-under-test"))
            .args(["--config", file.to_str().unwrap(), "--listen", &endpoint])
            .args(["--no-multicast-scouting", "--metrics", &metrics])
            .args(["--record", rec.to_str().unwrap()])
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap();
        let probe = transport::ZenohArgs::loopback(None, vec![endpoint.clone()])
            .open()
            .await
            .unwrap();
        let up = transport::wait_for_token(
            &probe,
            &protocol::keys::alive_controller("controller-1"),
            Duration::from_secs(20),
        )
        .await;
        let _ = probe.close().await;
        assert!(up, "the service never came up");
        let run = run_plant(vec![endpoint], PlantSpec::new(&s, &c, "aero-1"), true)
            .await
            .unwrap();
        assert!(run.report.controller_reached);
        // The plant has stopped; the last of its samples may still be in the service's
        // inbox: read until two scrapes agree. By default the service-wide series only:
        // every device's samples summed.
        let key = "mfc_devices_samples_total{controller=\"controller-1\"}";
        let mut served = -1.0;
        for _ in 0..50 {
            let now = samples(&scrape(metrics.parse().unwrap()).await)[key];
            if now == served {
                break;
            }
            served = now;
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        assert!(served >= 250.0, "{served}");
        // SIGTERM: the service's clean stop, which must finish the file.
        let pid = child.id().to_string();
        let killed = std::process::Command::new("kill")
            .args(["-TERM", &pid])
            .status()
            .unwrap();
        assert!(killed.success());
        let status = tokio::task::spawn_blocking(move || child.wait())
            .await
            .unwrap()
            .unwrap();
        assert!(status.success(), "{status:?}");
        let bytes = std::fs::read(&rec).unwrap();
        let c = read_recording(&bytes).unwrap();
        assert!(!c.truncated, "round {round}: the file was not finished");
        assert_eq!(c.metadata["dropped"], "0");
        let sampled = c
            .messages
            .iter()
            .filter(|m| m.topic == Topic::Sample)
            .count();
        assert_eq!(sampled as f64, served, "every sample served is in the file");
        let r = controller_service::replay::replay(&bytes, 1e-9).unwrap();
        assert!(r.matched, "{}", controller_service::replay::render(&r));
    }
    // The second start kept the first file under a name with the time.
    let kept = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| {
            let n = e.file_name().to_string_lossy().into_owned();
            n.starts_with("service.") && n.ends_with(".mcap") && n != "service.mcap"
        })
        .count();
    assert_eq!(kept, 1);
}
