//! What a device costs in memory: the heap a registry holds for ten thousand plants of the
//! load generator's kind (one iP channel, a 10-interval window), counted by a wrapper
//! around the service's allocator, and the part of it that is the controller's. The
//! controller's estimator keeps a ring of `mfc::DEFAULT_CAPACITY` intervals of which a step
//! touches only the window's (see `mfc::Estimator`); the rest, the service's own state per
//! device, is bounded here. `loadgen bench` measures the whole process's resident memory.
//!
//! `cargo test -p controller-service --test memory -- --nocapture` prints the breakdown.

use std::alloc::{GlobalAlloc, Layout};
use std::sync::atomic::{AtomicIsize, Ordering};

use controller_service::registry::Via;
use controller_service::{Registry, ServiceConfig};
use protocol::{pb, PROTOCOL_VERSION};

/// Live heap bytes, through the service binary's allocator.
struct Counting;

static LIVE: AtomicIsize = AtomicIsize::new(0);

// SAFETY: every call goes to mimalloc unchanged; the counter only observes.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        LIVE.fetch_add(layout.size() as isize, Ordering::Relaxed);
        unsafe { mimalloc::MiMalloc.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        LIVE.fetch_sub(layout.size() as isize, Ordering::Relaxed);
        unsafe { mimalloc::MiMalloc.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        LIVE.fetch_add(
            new_size as isize - layout.size() as isize,
            Ordering::Relaxed,
        );
        unsafe { mimalloc::MiMalloc.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

mod load;
use load::CONFIG;

const DEVICES: usize = 10_000;

/// Most heap a device may hold beside its controller (bytes): its counters, windows of
/// round trips and sequence numbers, configuration, reference and the table's entry.
const SERVICE_STATE: f64 = 3072.0;

/// Sample `k` of device `i`, from a plant reporting its round trips (so that the device
/// keeps their window).
fn sample(i: usize, k: u64) -> pb::Sample {
    pb::Sample {
        last_rtt_us: 500,
        ..load::sample(i, k, 0)
    }
}

/// The tests of this file one at a time: the count is the process's.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn live() -> isize {
    LIVE.load(Ordering::Relaxed)
}

/// A registry serving every device, each 20 samples in (its window full).
fn serving() -> (Registry, pb::Command) {
    let mut r = Registry::new(ServiceConfig::parse("memory", CONFIG).unwrap()).unwrap();
    let mut out = pb::Command::default();
    for k in 1..=20 {
        for i in 0..DEVICES {
            let s = sample(i, k);
            r.handle_sample(Via::key(&s.device_id), &s, 0, &mut out);
        }
    }
    (r, out)
}

#[test]
fn a_device_holds_its_controller_and_at_most_three_kibibytes_more() {
    let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let config = ServiceConfig::parse("memory", CONFIG).unwrap();
    let channels: Vec<mfc::ChannelConfig> = vec![mfc::ChannelConfig {
        law: mfc::LawConfig::intelligent(
            mfc::ControllerKind::P,
            mfc::Order::One,
            2.0,
            [5.0, 0.0, 0.0],
            10,
        ),
        output: mfc::OutputMapConfig {
            min: -10.0,
            max: 10.0,
            ..Default::default()
        },
    }];
    // The controller alone, as the registry builds it.
    let before = live();
    let controllers: Vec<mfc::MimoController> = (0..DEVICES)
        .map(|_| mfc::MimoController::new(&channels).unwrap())
        .collect();
    let controller = (live() - before) as f64 / DEVICES as f64;
    drop(controllers);

    drop(config);
    let before = live();
    let (r, _) = serving();
    assert_eq!(r.device_count(), DEVICES, "every device was admitted");
    let last = r.device_status("load-9999").unwrap();
    assert_eq!(last.samples, 20, "every sample was served: {last:?}");
    let device = (live() - before) as f64 / DEVICES as f64;
    eprintln!(
        "heap per device: {device:.0} bytes: the controller {controller:.0} (mfc::Channel {} \
         bytes, of which its estimator {}), the service's own state {:.0}",
        std::mem::size_of::<mfc::Channel>(),
        std::mem::size_of::<mfc::Estimator>(),
        device - controller,
    );
    assert!(
        device - controller <= SERVICE_STATE,
        "{:.0} bytes per device beside its controller",
        device - controller
    );
    // The count saw the devices: each holds at least its controller.
    assert!(
        controller >= std::mem::size_of::<mfc::Channel>() as f64,
        "{controller}"
    );
}

/// What a plant costs on the wire (a gateway's batch of a thousand, one way and the other)
/// and in a fleet's handover (its share of the shards' states): the inputs of the plan for
/// a million plants (`docs/scale.md`). Every shard's state decodes, and together they hold
/// every device once.
#[test]
fn what_a_plant_costs_on_the_wire_and_in_a_handover() {
    let _alone = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let (r, command) = serving();
    let (mut handed, mut devices) = (0, 0);
    for shard in 0..protocol::SHARDS {
        let state = r.shard_state(shard);
        let bytes = controller_service::snapshot::encode_shard(&state).unwrap();
        let back = controller_service::snapshot::decode_shard(&bytes).unwrap();
        assert_eq!(back.devices.len(), state.devices.len());
        handed += bytes.len();
        devices += state.devices.len();
    }
    assert_eq!(
        devices, DEVICES,
        "every device in exactly one shard's state"
    );
    let batch = |resend| {
        protocol::encode(&pb::SampleBatch {
            version: PROTOCOL_VERSION,
            gateway_id: "gw-0".into(),
            samples: (0..1000)
                .map(|i| pb::Sample {
                    last_rtt_us: 500,
                    ..load::sample(i, 21, resend)
                })
                .collect(),
            mac: Vec::new(),
        })
        .len()
    };
    let commands = protocol::encode(&pb::CommandBatch {
        version: PROTOCOL_VERSION,
        gateway_id: "gw-0".into(),
        commands: vec![command; 1000],
        controller_id: "memory".into(),
        mac: Vec::new(),
    })
    .len();
    let (plain, resent) = (batch(0), batch(3));
    eprintln!(
        "per plant: sample {:.0} bytes ({:.0} with 3 resent), command {:.0} bytes, \
         in batches of 1000; handover {:.0} bytes",
        plain as f64 / 1000.0,
        resent as f64 / 1000.0,
        commands as f64 / 1000.0,
        handed as f64 / DEVICES as f64,
    );
    assert!(plain < resent && commands > 0);
}
