//! Proof of origin on real Zenoh sessions: a service with keys, a real AERO plant with its
//! device key, and a forger beside them that may put and reply on every key (as any
//! holder of a service certificate may) but holds no key. While the plant runs:
//! * forged samples of new runs on the plant's key: every one counted as `forged`, none
//!   restarts the device (one run started, the plant's; its sample count is the plant's own);
//! * forged commands on the plant's command key: every one refused unread by the plant
//!   (`auth.forged` equals the number sent), none applied;
//! * a forged status reply beside the real one: an operator with the operators' key is
//!   shown the real status every time, and one with a bare session could be fooled.
//!
//! Counts and invariants only, no timing.

use std::time::Duration;

use mfc_lab::harness::{default_safety, open_session, service_config, ServiceHandle};
use plant_agent::agent::{open_plant, run_loop, ControllerLink, LoopConfig};
use protocol::{encode, keys, pb, PROTOCOL_VERSION};
use system_tests::{query, SERIAL};
use transport::ops;

/// Forged samples and forged commands sent while the plant runs.
const FORGED: u64 = 40;
/// Status queries an operator makes while the forger replies too.
const QUERIES: usize = 10;
/// What the forger's status says: a value no real run of a few seconds reaches.
const FAKE_SAMPLES: u64 = 999_999;

fn forged_sample(run: u64, seq: u64) -> Vec<u8> {
    encode(&pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: "aero-1".into(),
        seq,
        plant_time: seq as f64 * 0.01,
        outputs: vec![0.0, 0.0],
        run_id: run,
        ..Default::default()
    })
}

fn forged_command(seq: u64) -> Vec<u8> {
    // Shaped like a holder's command, with a MAC of the right length under no key.
    let mut bytes = encode(&pb::Command {
        version: PROTOCOL_VERSION,
        device_id: "aero-1".into(),
        seq,
        mode: pb::Mode::Control as i32,
        u: vec![24.0, 24.0],
        v: vec![24.0, 24.0],
        controller_id: "controller-1".into(),
        ..Default::default()
    });
    bytes.extend_from_slice(&[0xA2, 0x06, 0x20]);
    bytes.extend_from_slice(&[0x5A; 32]);
    bytes
}

/// The AERO run, with the device's key.
async fn keyed_plant(
    sc: plant::scenario::Scenario,
    c: plant::scenario::ControllerSet,
    secret: protocol::auth::Secret,
    endpoint: String,
) -> plant_agent::agent::AgentRun {
    let session = open_session(None, vec![endpoint], true).await.unwrap();
    let mut safety = default_safety(&sc);
    safety.hold_periods += system_tests::margin_periods();
    let mut cfg = LoopConfig::new(&sc, &c, "aero-1", safety);
    cfg.auth = Some(secret.device("aero-1"));
    let p = open_plant(&sc, sc.seed).await.unwrap();
    let run = run_loop(&session, p, &cfg, plant::run_id(), std::future::pending()).await;
    let _ = session.close().await;
    run.unwrap()
}

/// An operator with the operators' key asks for the status while the forger replies too:
/// shown the controller's every time. Without the key the forger's reply is as good as
/// the controller's (printed, not judged: what the key is for).
async fn ask_beside_the_forger(asker: &zenoh::Session, secret: &protocol::auth::Secret) {
    let operator = ops::Operator {
        session: asker.clone(),
        key: Some(secret.operator()),
        name: None,
    };
    for _ in 0..QUERIES {
        let st = ops::device_status(&operator, "aero-1", Duration::from_secs(2))
            .await
            .unwrap();
        assert_ne!(
            st.samples, FAKE_SAMPLES,
            "a forged reply was shown to a keyed operator"
        );
        assert!(st.samples > 0);
    }
    let mut fooled = 0;
    for _ in 0..QUERIES {
        if let Ok(st) = ops::device_status(asker, "aero-1", Duration::from_secs(2)).await {
            fooled += usize::from(st.samples == FAKE_SAMPLES);
        }
    }
    // A device nobody serves: the controller says so, the forger refuses in its own words.
    for _ in 0..QUERIES {
        let e = ops::device_status(&operator, "aero-9", Duration::from_secs(2))
            .await
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("does not serve") && !e.contains(FORGED_REFUSAL),
            "a keyed operator shown: {e}"
        );
    }
    let mut fooled_err = 0;
    for _ in 0..QUERIES {
        if let Err(e) = ops::device_status(asker, "aero-9", Duration::from_secs(2)).await {
            fooled_err += usize::from(e.to_string().contains(FORGED_REFUSAL));
        }
    }
    eprintln!(
        "keyed operator: {QUERIES}/{QUERIES} real replies and refusals; unkeyed: fooled \
         {fooled}/{QUERIES}, shown the forged refusal {fooled_err}/{QUERIES}"
    );
}

/// The forger's refusal, as it would read to an operator.
const FORGED_REFUSAL: &str = "FORGED: device retired";

#[tokio::test(flavor = "multi_thread")]
async fn forged_samples_commands_and_replies_change_nothing() {
    use plant::scenario::{load_scenario, shipped_controller};

    let _s = SERIAL.lock().await;
    let mut sc = load_scenario("2").unwrap();
    sc.duration = 6.0;
    let c = shipped_controller("ipd").unwrap();
    let ids = ["aero-1".to_string()];
    let service = ServiceHandle::start_keyed(service_config(&sc, &c, &ids), None)
        .await
        .unwrap();
    let secret = service.secret.clone().unwrap();
    let endpoint = service.endpoint.clone();

    // The plant, with its device key.
    let plant = tokio::spawn(keyed_plant(
        sc.clone(),
        c.clone(),
        secret.clone(),
        endpoint.clone(),
    ));

    // The forger: no key, but free to put and to reply on every key.
    let forger = open_session(None, vec![endpoint.clone()], true)
        .await
        .unwrap();
    let fake = pb::DeviceStatus {
        version: PROTOCOL_VERSION,
        device_id: "aero-1".into(),
        samples: FAKE_SAMPLES,
        ..Default::default()
    };
    let fake_bytes = encode(&fake);
    let _rogue = forger
        .declare_queryable(keys::status("aero-1"))
        .callback(move |q| {
            use zenoh::Wait;
            let _ = q.reply(q.key_expr().clone(), fake_bytes.clone()).wait();
        })
        .await
        .unwrap();
    let _rogue_err = forger
        .declare_queryable(keys::status("aero-9"))
        .callback(|q| {
            use zenoh::Wait;
            let _ = q.reply_err(FORGED_REFUSAL).wait();
        })
        .await
        .unwrap();
    // Let the plant's run start before the forgeries.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let sample_key = keys::shard_sample("aero-1");
    for i in 0..FORGED {
        forger
            .put(&sample_key, forged_sample(1000 + i, 1 + i))
            .await
            .unwrap();
        forger
            .put(keys::command("aero-1"), forged_command(100_000 + i))
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(20)).await;
    }

    // Operators ask while the forger answers too.
    let asker = open_session(None, vec![endpoint.clone()], true)
        .await
        .unwrap();
    ask_beside_the_forger(&asker, &secret).await;

    let run = plant.await.unwrap();
    let r = &run.report;
    eprintln!("{}", r.headline());
    assert!(r.completed() && r.safe_stop_applied, "{r:?}");
    assert_eq!(r.link, ControllerLink::Kept, "{r:?}");
    assert!(r.auth.authenticated);
    assert_eq!(
        r.auth.forged, FORGED,
        "every forged command refused unread, and counted"
    );
    // No forged command was judged: nothing malformed, stale or from the future either.
    let k = &r.counters;
    assert_eq!(k.malformed + k.future, 0, "{k:?}");

    let st: pb::ServiceStatus = query(&asker, keys::service_status("controller-1"), None)
        .await
        .unwrap();
    assert!(st.authenticated);
    assert_eq!(
        st.forged, FORGED,
        "every forged sample counted, before decoding"
    );
    let dev = st.devices.iter().find(|d| d.device_id == "aero-1").unwrap();
    // `restarts` counts run starts: the plant's own, and no forged one.
    assert_eq!(
        dev.restarts, 1,
        "a forged run restarted the device: {dev:?}"
    );
    // Only the plant's own samples were taken: each of its periods is a sample taken or
    // one counted lost (published with `Drop`, a sample may be dropped on a starved
    // machine), and nothing more.
    assert_eq!(
        dev.samples + dev.lost,
        k.periods,
        "only the plant's own samples were taken: {dev:?}"
    );
    assert_eq!((dev.rejected, dev.stale), (0, 0), "{dev:?}");
    for s in [forger, asker] {
        let _ = s.close().await;
    }
    service.stop().await.unwrap();
}

/// A hot-standby group with keys: heartbeats are sealed with the members' key. A forger's
/// heartbeats claiming a far higher term leave the active member active (counted as
/// forged); the same heartbeat sealed with the members' key makes it stand by (the
/// control: the forger's did arrive, and would have won without the seal).
#[tokio::test(flavor = "multi_thread")]
async fn a_forged_heartbeat_does_not_make_the_active_member_stand_by() {
    use controller_service::config::{StandbyRole, StandbySpec};
    use plant::scenario::{load_scenario, shipped_controller};

    let _s = SERIAL.lock().await;
    let sc = load_scenario("2").unwrap();
    let c = shipped_controller("ipd").unwrap();
    let mut cfg = service_config(&sc, &c, &["aero-1".to_string()]);
    cfg.standby = Some(StandbySpec {
        group: "g1".into(),
        role: StandbyRole::Active,
        heartbeat_ms: 10,
        takeover_ms: 30,
    });
    let service = ServiceHandle::start_keyed(cfg, None).await.unwrap();
    let secret = service.secret.clone().unwrap();
    let forger = open_session(None, vec![service.endpoint.clone()], true)
        .await
        .unwrap();
    let status = || async {
        query::<pb::ServiceStatus>(&forger, keys::service_status("controller-1"), None)
            .await
            .unwrap()
    };
    // Past the start-up grace, in which an active member listens for another one.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(status().await.active, "active at start");
    let key = keys::heartbeat("g1");
    let hb = encode(&pb::Heartbeat {
        version: PROTOCOL_VERSION,
        controller_id: "rogue".into(),
        term: 1_000_000,
    });
    // Each kind of heartbeat is kept up while the status is read: 30 ms after the last
    // one a member that stood by takes over again, under a higher term, as it should.
    let beat = |bytes: Vec<u8>| {
        let (forger, key) = (forger.clone(), key.clone());
        tokio::spawn(async move {
            loop {
                let _ = forger.put(&key, bytes.clone()).await;
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        })
    };
    // Five reads, 100 ms apart, while the heartbeats go on: every one must be active
    // under forged heartbeats; under a member's, one standing by is the proof (a busy
    // machine may pause the sender past the takeover time between them).
    let reads = || async {
        let mut v = Vec::new();
        for _ in 0..5 {
            tokio::time::sleep(Duration::from_millis(100)).await;
            v.push(status().await);
        }
        v
    };
    let forged = beat(hb.clone());
    let during = reads().await;
    forged.abort();
    assert!(
        during.iter().all(|s| s.active),
        "a forged heartbeat made the active member stand by"
    );
    assert!(
        during.last().unwrap().forged > 0,
        "the forged heartbeats arrived, and were counted"
    );
    let sealed = secret
        .member()
        .seal_in(protocol::auth::Kind::Handover, &[key.as_bytes()], hb);
    let member = beat(sealed);
    let stood_by = reads().await.iter().any(|s| !s.active);
    member.abort();
    assert!(
        stood_by,
        "control: a member's heartbeat with a higher term makes it stand by"
    );
    let _ = forger.close().await;
    service.stop().await.unwrap();
}
