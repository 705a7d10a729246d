//! The anchor: the least a controller over Zenoh must do. It decodes each sample (or
//! batch), answers with a command of the same `seq` (zero volts) on the device's (or the
//! gateway's) command key, express, from inside zenoh's callback, with a publisher declared
//! once per key. No state, no control law, no queue: whatever the service costs beyond
//! this is the service's own.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use protocol::{decode, encode, encode_command_batch, keys, pb, PROTOCOL_VERSION};
use zenoh::pubsub::Publisher;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::{Session, Wait};

/// Publishers the echo keeps (one per key it answered on); beyond, it puts without one.
const PUBLISHERS: usize = 100_000;

type Publishers = Arc<Mutex<HashMap<String, Publisher<'static>>>>;

fn answer(session: &Session, pubs: &Publishers, key: String, payload: Vec<u8>) {
    let mut map = pubs
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    if !map.contains_key(&key) && map.len() < PUBLISHERS {
        if let Ok(p) = session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Drop)
            .priority(Priority::RealTime)
            .express(true)
            .wait()
        {
            map.insert(key.clone(), p);
        }
    }
    let _ = match map.get(&key) {
        Some(p) => p.put(payload).wait(),
        None => session.put(key, payload).express(true).wait(),
    };
}

fn command_for(s: &pb::Sample) -> pb::Command {
    let n = s.outputs.len();
    pb::Command {
        version: PROTOCOL_VERSION,
        device_id: s.device_id.clone(),
        seq: s.seq,
        u: vec![0.0; n],
        v: vec![0.0; n],
        controller_unix_ns: protocol::unix_ns(),
        f_est: Vec::new(),
        mode: pb::Mode::Control as i32,
        sample_sent_unix_ns: s.sent_unix_ns,
        controller_id: "echo".into(),
        error: String::new(),
        horizon: Vec::new(),
        reference: Vec::new(),
        run_id: s.run_id,
        ..Default::default()
    }
}

/// Serve as the echo anchor on `session` until `stop` resolves.
pub async fn serve(
    session: Session,
    stop: impl std::future::Future<Output = ()>,
) -> Result<(), zenoh::Error> {
    let pubs: Publishers = Arc::default();
    let single_cb = || {
        let (session2, pubs) = (session.clone(), pubs.clone());
        move |s: zenoh::sample::Sample| {
            let Ok(sample) = decode::<pb::Sample>(&s.payload().to_bytes()) else {
                return;
            };
            let Some(dev) = keys::device_of(s.key_expr().as_str()) else {
                return;
            };
            answer(
                &session2,
                &pubs,
                keys::command(dev),
                encode(&command_for(&sample)),
            );
        }
    };
    let batch_cb = || {
        let (session2, pubs) = (session.clone(), pubs.clone());
        move |s: zenoh::sample::Sample| {
            let Ok(batch) = decode::<pb::SampleBatch>(&s.payload().to_bytes()) else {
                return;
            };
            let Some(gw) = keys::gateway_of(s.key_expr().as_str()) else {
                return;
            };
            let out = pb::CommandBatch {
                version: PROTOCOL_VERSION,
                gateway_id: gw.to_string(),
                commands: batch.samples.iter().map(command_for).collect(),
                controller_id: "echo".into(),
                mac: Vec::new(),
            };
            // The service's own batch encoder: the anchor is not made dearer than the
            // service by the codec.
            let payload = encode_command_batch(&out);
            answer(&session2, &pubs, keys::gateway_commands(gw), payload);
        }
    };
    // The keys with and without a shard segment, as the service takes them.
    let mut subs = Vec::new();
    for k in [
        keys::all_devices("sample"),
        format!("{}/shard/*/device/*/sample", keys::PREFIX),
    ] {
        subs.push(session.declare_subscriber(k).callback(single_cb()).await?);
    }
    for k in [
        keys::all_gateways("samples"),
        format!("{}/shard/*/gateway/*/samples", keys::PREFIX),
    ] {
        subs.push(session.declare_subscriber(k).callback(batch_cb()).await?);
    }
    let token = session
        .liveliness()
        .declare_token(keys::alive_controller("echo"))
        .await?;
    stop.await;
    drop(token);
    drop(subs);
    pubs.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .clear();
    session.close().await
}
