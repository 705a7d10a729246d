//! What the service's own rules cost per sample, without the network: thousands of devices
//! (one iP channel each, as the load generator's), every one stepped once per iteration,
//! the way gateways' batches are served. Run: `cargo bench -p controller-service`.

use controller_service::registry::{Served, Via};
use controller_service::{Registry, ServiceConfig};
use protocol::auth::Kind;
use protocol::{pb, PROTOCOL_VERSION};

#[path = "../tests/load/mod.rs"]
mod load;
use load::CONFIG;

/// The service binary's allocator, so that the figures are the service's.
#[global_allocator]
static ALLOC: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    divan::main();
}

fn samples(devices: usize, k: u64) -> Vec<pb::Sample> {
    (0..devices).map(|i| load::sample(i, k, 0)).collect()
}

/// Every device's sample once through `Registry::handle_sample`, for a thousand and for ten
/// thousand devices (divide by the count for the cost per sample): the difference is what
/// the devices' state costs once it no longer fits the caches.
#[divan::bench(args = [1000, 10000])]
fn every_device_once(b: divan::Bencher, devices: usize) {
    each_device_stepped::<PLAIN>(b, devices);
}

/// [`every_device_once`] with the next sample's device asked for before each step
/// (`Registry::prefetch`), as the service served a gateway's batch until it found them by
/// slot: its state arrives while the sample before it is stepped.
#[divan::bench(args = [1000, 10000])]
fn every_device_once_ahead(b: divan::Bencher, devices: usize) {
    each_device_stepped::<AHEAD>(b, devices);
}

/// [`every_device_once_ahead`] with each position's device found in the slot it was
/// found in the iteration before (`Registry::handle_sample_at`, `prefetch_at`), as the
/// service serves a gateway's batch: no table lookup once the order is known.
#[divan::bench(args = [1000, 10000])]
fn every_device_once_by_slot(b: divan::Bencher, devices: usize) {
    each_device_stepped::<BY_SLOT>(b, devices);
}

/// How [`each_device_stepped`] finds each sample's device (a constant, so that each
/// form's code is its own loop): looked up, looked up with the next one asked for
/// first, or found in the slot remembered for its position, the next one asked for first.
const PLAIN: u8 = 0;
const AHEAD: u8 = 1;
const BY_SLOT: u8 = 2;

/// Each device's sample once per iteration, its device found as `MODE` says.
fn each_device_stepped<const MODE: u8>(b: divan::Bencher, devices: usize) {
    let mut r = Registry::new(ServiceConfig::parse("bench", CONFIG).unwrap()).unwrap();
    // One command written over and over, as the service's batches reuse theirs.
    let mut out = pb::Command::default();
    let mut slots = vec![None; devices];
    let mut k = 1;
    for _ in 0..20 {
        for (s, slot) in samples(devices, k).iter().zip(&mut slots) {
            r.handle_sample_at(slot, Via::key(&s.device_id), s, 0, &mut out);
        }
        k += 1;
    }
    let mut batch = samples(devices, k);
    b.bench_local(|| {
        for s in &mut batch {
            s.seq = k;
            s.plant_time = k as f64 * 0.01;
        }
        for (i, s) in batch.iter().enumerate() {
            if let Some(next) = batch.get(i + 1) {
                match MODE {
                    AHEAD => r.prefetch(&next.device_id),
                    BY_SLOT => r.prefetch_at(&mut slots[i + 1], &next.device_id),
                    _ => {}
                }
            }
            let via = Via::key(&s.device_id);
            divan::black_box(if MODE == BY_SLOT {
                r.handle_sample_at(&mut slots[i], via, s, k, &mut out)
            } else {
                r.handle_sample(via, s, k, &mut out)
            });
        }
        k += 1;
    });
}

/// Decoding a thousand-sample batch and encoding its thousand commands as the echo
/// anchor of `loadgen` does (decoded whole, [`echoed`] for each sample): the protobuf part
/// of a batch, for comparison; with `true`, the batch's MAC checked and the commands'
/// batch sealed too (`protocol::auth`: one MAC each way per batch).
#[divan::bench(args = [false, true])]
fn thousand_decode_encode(b: divan::Bencher, authenticated: bool) {
    let key = protocol::auth::Secret::random().unwrap().gateway("gw");
    let bytes = protocol::encode(&pb::SampleBatch {
        version: PROTOCOL_VERSION,
        gateway_id: "gw".into(),
        samples: samples(1000, 1),
        ..Default::default()
    });
    let bytes = if authenticated {
        key.seal(Kind::SampleBatch, bytes)
    } else {
        bytes
    };
    b.bench_local(|| {
        let body = if authenticated {
            key.open(Kind::SampleBatch, &bytes).unwrap()
        } else {
            &bytes[..]
        };
        let batch: pb::SampleBatch = protocol::decode(body).unwrap();
        let out = pb::CommandBatch {
            version: PROTOCOL_VERSION,
            gateway_id: batch.gateway_id.clone(),
            commands: batch.samples.iter().map(echoed).collect(),
            controller_id: "echo".into(),
            ..Default::default()
        };
        let bytes = protocol::encode_command_batch(&out);
        divan::black_box(if authenticated {
            key.seal(Kind::CommandBatch, bytes)
        } else {
            bytes
        });
    });
}

/// The echo's command for a sample (`loadgen`'s `echo::command_for`, which a benchmark of
/// the service cannot depend on): zeros of the sample's width, stamped with the clock.
fn echoed(s: &pb::Sample) -> pb::Command {
    let n = s.outputs.len();
    pb::Command {
        version: PROTOCOL_VERSION,
        device_id: s.device_id.clone(),
        seq: s.seq,
        u: vec![0.0; n],
        v: vec![0.0; n],
        controller_unix_ns: protocol::unix_ns(),
        mode: pb::Mode::Control as i32,
        sample_sent_unix_ns: s.sent_unix_ns,
        controller_id: "echo".into(),
        run_id: s.run_id,
        ..Default::default()
    }
}

/// A thousand-sample gateway batch served the way the service's worker serves one
/// (`service::core`'s `serve_batch`, without the network and the metrics): the batch read
/// as a view, each sample decoded into a buffer kept from batch to batch, its device
/// found by slot and stepped (`Registry::handle_sample_at`, the next one asked for
/// ahead), and the answers encoded into one command batch. Beside
/// [`thousand_decode_encode`] (what the echo does with a batch), the difference is the
/// service's own work per sample; `docs/scale.md` counts both in instructions.
#[divan::bench]
fn thousand_served(b: divan::Bencher) {
    let mut r = Registry::new(ServiceConfig::parse("bench", CONFIG).unwrap()).unwrap();
    // The gateway's shard, once a batch, as the worker finds it.
    let home = protocol::shard_of("gw");
    let mut slots = vec![None; 1000];
    let mut commands = vec![pb::Command::default(); 1000];
    let mut k = 1;
    for _ in 0..20 {
        for ((s, slot), out) in samples(1000, k).iter().zip(&mut slots).zip(&mut commands) {
            let served = r.handle_sample_at(slot, Via::gateway(&s.device_id, home), s, 0, out);
            if k == 20 {
                // Warmed up: every sample answered with a command (not refused, not the
                // cheap path of a duplicate), as every one the benchmark serves.
                assert!(matches!(served, Served::Answered { send: true, .. }));
                assert_eq!(out.mode, pb::Mode::Control as i32, "{}", out.error);
            }
        }
        k += 1;
    }
    // A payload as zenoh hands it over: the view's samples are slices of it, not copies.
    let bytes = protocol::Bytes::from(protocol::encode(&pb::SampleBatch {
        version: PROTOCOL_VERSION,
        gateway_id: "gw".into(),
        samples: samples(1000, k),
        ..Default::default()
    }));
    let mut decoded = vec![pb::Sample::default(); 1000];
    b.bench_local(|| {
        let view: protocol::SampleBatchView = protocol::decode_from(bytes.clone()).unwrap();
        for (raw, s) in view.samples.iter().zip(&mut decoded) {
            protocol::SampleBatchView::read_sample(raw, s).unwrap();
            // The same bytes every time: each iteration is the devices' next period.
            (s.seq, s.plant_time) = (k, k as f64 * 0.01);
            protocol::keys::check_id(&s.device_id).unwrap();
        }
        for (i, s) in decoded.iter().enumerate() {
            if let Some(next) = decoded.get(i + 1) {
                r.prefetch_at(&mut slots[i + 1], &next.device_id);
            }
            let via = Via::gateway(&s.device_id, home);
            r.handle_sample_at(&mut slots[i], via, s, k, &mut commands[i]);
        }
        let out = pb::CommandBatch {
            version: PROTOCOL_VERSION,
            gateway_id: view.gateway_id,
            commands: std::mem::take(&mut commands),
            controller_id: "load".into(),
            ..Default::default()
        };
        let bytes = protocol::encode_command_batch(&out);
        commands = out.commands;
        k += 1;
        divan::black_box(bytes)
    });
}

/// One lone sample (a device on its own key) decoded and its command encoded; with
/// `true`, the sample's MAC checked and the command sealed under the device's key: what
/// the proof of origin adds per sample where there is no batch to share it.
#[divan::bench(args = [false, true])]
fn lone_decode_encode(b: divan::Bencher, authenticated: bool) {
    let key = protocol::auth::Secret::random().unwrap().device("load-0");
    let mut s = samples(1, 1).remove(0);
    s.previous_outputs = vec![0.5; 3];
    s.previous_applied = vec![1.0; 3];
    s.previous_plant_time = vec![0.0; 3];
    let bytes = protocol::encode(&s);
    let bytes = if authenticated {
        key.seal(Kind::Sample, bytes)
    } else {
        bytes
    };
    b.bench_local(|| {
        let body = if authenticated {
            key.open(Kind::Sample, &bytes).unwrap()
        } else {
            &bytes[..]
        };
        let s: pb::Sample = protocol::decode(body).unwrap();
        let cmd = pb::Command {
            version: PROTOCOL_VERSION,
            device_id: s.device_id,
            seq: s.seq,
            u: vec![0.0],
            v: vec![0.0],
            f_est: vec![0.0],
            controller_id: "bench".into(),
            lease_epoch: 1,
            run_id: s.run_id,
            ..Default::default()
        };
        let bytes = protocol::encode(&cmd);
        divan::black_box(if authenticated {
            key.seal(Kind::Command, bytes)
        } else {
            bytes
        });
    });
}

/// A fleet's handover of a thousand devices (every shard's state, as an owner hands them
/// to a member joining): taken from the owner, encoded, decoded and restored on the
/// newcomer. Divide by 1000 for the cost per device; `docs/scale.md` scales it to a shard of
/// a million-plant plan.
#[divan::bench]
fn thousand_devices_handed_over(b: divan::Bencher) {
    let config = || ServiceConfig::parse("bench", CONFIG).unwrap();
    let mut owner = Registry::new(config()).unwrap();
    let mut out = pb::Command::default();
    for k in 1..=20 {
        for s in samples(1000, k) {
            owner.handle_sample(Via::key(&s.device_id), &s, 0, &mut out);
        }
    }
    b.bench_local(|| {
        let mut newcomer = Registry::new(config()).unwrap();
        let mut restored = 0;
        for shard in 0..protocol::SHARDS {
            let state = owner.shard_state(shard);
            let bytes = controller_service::snapshot::encode_shard(&state).unwrap();
            let state = controller_service::snapshot::decode_shard(&bytes).unwrap();
            restored += newcomer.restore_shard(&state).restored;
        }
        assert_eq!(restored, 1000);
        newcomer
    });
}
