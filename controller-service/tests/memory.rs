//! What a device costs in memory: the heap a registry holds for ten thousand plants of the
//! load generator's kind (one iP channel, a 10-interval window), counted by a wrapper
//! around the service's allocator, the part of it that is the controller's, and the
//! resident memory the registry adds to a process of its own. The controller's estimator
//! keeps the window's intervals and no more (see `mfc::Estimator`); the controller and the
//! service's own state per device are bounded here. `loadgen bench` measures the whole
//! service's resident memory.
//!
//! `cargo test --release -p controller-service --test memory -- --nocapture` prints the
//! breakdown.

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
/// round trips and sequence numbers, configuration, reference and the table's entry (1430
/// on 2026-11-28, what only rare events need boxed; 1678 before).
const SERVICE_STATE: f64 = 1536.0;

/// Most heap a controller of one iP channel with a 10-interval window may hold (bytes):
/// its channel and the window's ring (1072 on 2026-11-28). A ring of the estimator's whole
/// capacity (256 intervals, 6 KiB) does not fit, nor a second copy of the channel's
/// configuration (184 bytes) beside the one its law and map hold.
const CONTROLLER: f64 = 1536.0;

/// Most resident memory the registry may add per device, in a process of its own without
/// huge pages, as the service runs (bytes): the heap above and the allocator's rounding
/// of it into size classes and pages (2757 on 2026-11-28; 2789 before what only rare
/// events need was boxed).
const RESIDENT: f64 = 3072.0;

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
fn a_device_holds_its_controller_and_at_most_one_and_a_half_kibibytes_more() {
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
    assert!(
        controller <= CONTROLLER,
        "{controller:.0} bytes per controller"
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
            plants: 1000,
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

/// This process's resident memory (bytes), from `/proc/self/status`.
fn resident() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    let kib: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().strip_suffix("kB"))
        .and_then(|v| v.trim().parse().ok())
        .expect("VmRSS in kB");
    kib * 1024.0
}

/// Set in the child process of [`the_registry_adds_little_resident_memory_per_device`].
const CHILD: &str = "MFC_MEMORY_RESIDENT_CHILD";

/// The resident memory a registry of ten thousand serving devices adds, measured in a child
/// process running this test alone: in this one, memory that other tests freed would be
/// reused and hide part of it. The heap counted beside it tells the allocator's share.
#[test]
fn the_registry_adds_little_resident_memory_per_device() {
    if std::env::var_os(CHILD).is_some() {
        // As the service runs by default (`huge_pages = false`): with huge pages the
        // growth comes in steps of 2 MiB, 210 bytes a device at this size.
        controller_service::cli::huge_pages(false).expect("huge pages off");
        let (rss, heap) = (resident(), live());
        let (r, _) = serving();
        let (rss, heap) = (
            (resident() - rss) / DEVICES as f64,
            (live() - heap) as f64 / DEVICES as f64,
        );
        assert_eq!(r.device_count(), DEVICES);
        println!("resident per device: {rss:.0} heap per device: {heap:.0}");
        return;
    }
    let out = std::process::Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "the_registry_adds_little_resident_memory_per_device",
            "--nocapture",
            "--test-threads=1",
        ])
        .env(CHILD, "1")
        .output()
        .expect("the test binary runs again");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "child failed: {stdout}");
    let figures: Vec<f64> = stdout
        .lines()
        .find_map(|l| l.split("resident per device: ").nth(1))
        .expect("the child's figures")
        .split(" heap per device: ")
        .map(|v| v.parse().unwrap())
        .collect();
    let (rss, heap) = (figures[0], figures[1]);
    eprintln!("resident memory per device: {rss:.0} bytes, for {heap:.0} bytes of heap");
    // The count saw the devices, and the pages holding them are resident.
    assert!(heap >= 1024.0 && rss >= heap * 0.9, "{rss} for {heap}");
    assert!(rss <= RESIDENT, "{rss:.0} bytes resident per device");
}
