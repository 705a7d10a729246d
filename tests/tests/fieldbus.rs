//! Plants from the factory floor with no code: the DC motor behind a Modbus TCP server
//! (pymodbus) and behind an OPC UA server (asyncua), servers we did not write, controlled
//! over Zenoh through the controller service, track as their offline twin (the same physics
//! as a driver, its commands landing the run's round trip after the tick, or its values as
//! old as a subscription makes them) does, and are left with their safe value in the server.

use mfc_lab::harness::{run_fleet, service_config};
use mfc_lab::offline::IoTiming;
use plant::modbus::RegisterKind;
use plant::scenario::{load_scenario, PlantSource, Scenario};
use plant_agent::agent::End;
use system_tests::{holding_twin, rms_ratio_bound, served_plant, SERIAL};

#[path = "../../plant-agent/tests/support/plant_server.rs"]
mod plant_server;
use plant_server::{free_port, root, Server, ServerKind};

const SAFE: f64 = 0.25;

fn load(rel: &str) -> Scenario {
    let mut s = load_scenario(root().join(rel).to_str().unwrap()).unwrap();
    s.duration = 9.0;
    s
}

/// The server's file on `server`, with the test's safe value.
fn pointed(mut s: Scenario, server: &Server) -> Scenario {
    match &mut s.plant {
        PlantSource::Modbus(m) => {
            m.config.address = server.address();
            m.config.channels[0].safe = SAFE;
        }
        PlantSource::OpcUa(o) => {
            o.config.endpoint = server.address();
            o.config.channels[0].safe = SAFE;
        }
        other => panic!("a plant behind a server, not {other:?}"),
    }
    s
}

/// What the server's input holds now (off the async worker: the probes block).
fn input_now(server: &Server) -> f64 {
    tokio::task::block_in_place(|| match server.protocol {
        ServerKind::Modbus => server.value(RegisterKind::Holding, 0),
        ServerKind::OpcUa => server.node("Input", None),
    })
}

/// Where the twin's command meets its plant.
#[derive(Clone, Copy)]
enum Writes {
    /// As `IoTiming` says.
    AsTimed,
    /// Also the run's median round trip after the tick (sample to command, measured by the
    /// agent): a bridge that reads at the tick writes no earlier.
    AfterRoundTrip,
}

/// The slowest median round trip a run may have (a fifth of the 10 ms period): the twin
/// that writes after it absorbs the delay, so the delay itself is judged here.
const MAX_RTT_P50_US: f64 = 2000.0;

/// The largest fraction of a run's ticks that may come more than half a period late for
/// its tracking to be judged: beyond it the host, not the loop, is what the run measured.
const MAX_OVERRUNS: f64 = 0.02;

/// The plant behind `protocol`'s server (its file `file`, changed by `adapt`) tracks
/// through the service within the usual bound of its offline twin, run with the I/O
/// timing `timing` (and `writes`) and holding where the run held: the median of `judged`
/// runs' RMS ratios.
///
/// Until 12-03 a run holding more than 2 % of its periods was not judged, and the test
/// failed when fewer than three of five were: a CI run on a busy host held 2.2 to 6.8 %
/// of the Modbus runs' periods (commands back after the period's end) and judged one. A
/// held period is a deadline missed, which the lockstep twin never does; the twin now
/// misses the same ones, and the served-periods count still fails a loop that holds for
/// want of a controller. What no twin can replay is a host that starves the loop itself:
/// ticks more than half a period late ([`MAX_OVERRUNS`]). On 12-03, on a host with 14 %
/// of its CPU stolen, such runs of the subscription's loop (5 to 21 % of periods
/// overrun, commands 2 to 5 ms late) fell into a ±12 V limit cycle after a step (ratios
/// 20 to 85), which this law does with a few milliseconds more delay; those runs are
/// reported and not judged, and the test fails if fewer than `judged` of `judged + 2`
/// kept time.
async fn tracks_as_its_twin(
    protocol: ServerKind,
    file: &str,
    adapt: fn(&mut Scenario),
    (timing, writes): (IoTiming, Writes),
    judged: usize,
) {
    let _serial = SERIAL.lock().await;
    let twin = load("plants/dc-motor/scenarios/motor-steps.toml");
    let mut ratios = Vec::with_capacity(judged);
    let attempts = judged + 2;
    for attempt in 1..=attempts {
        let server = Server::start_as(protocol, free_port(), &[]);
        let mut s = pointed(load(file), &server);
        adapt(&mut s);
        assert_eq!(s.controller, twin.controller, "the same law on both");
        let id = "motor-1".to_string();
        let config = service_config(&s, &s.controller, std::slice::from_ref(&id));
        let run = run_fleet(vec![served_plant(&s, &s.controller, &id)], config)
            .await
            .unwrap()
            .remove(0);
        let rep = &run.report;
        eprintln!("{protocol:?} attempt {attempt}: {}", rep.headline());
        assert_eq!(rep.end, End::Completed, "{rep:?}");
        assert!(rep.safe_stop_applied && rep.controller_reached, "{rep:?}");
        let k = &rep.counters;
        if rep.overruns as f64 > MAX_OVERRUNS * k.periods as f64 {
            eprintln!(
                "attempt {attempt}: {} of {} ticks overran: the host starved the loop, not \
                 judged ({k:?})",
                rep.overruns, k.periods
            );
            continue;
        }
        assert!(
            (k.commands + k.warming_up) as f64 >= 0.95 * k.periods as f64,
            "served: {k:?}"
        );
        assert_eq!(k.fallbacks, 0, "{k:?}");
        assert_eq!(input_now(&server), SAFE, "the safe value was left");
        assert!(
            rep.rtt_p50_us < MAX_RTT_P50_US,
            "median round trip {} us",
            rep.rtt_p50_us
        );
        let timing = match writes {
            Writes::AsTimed => timing,
            Writes::AfterRoundTrip => IoTiming {
                write_delay: timing.write_delay + rep.rtt_p50_us * 1e-6,
                ..timing
            },
        };
        // The twin holds where the run held: a busy machine's late commands are in both.
        let offline = holding_twin(&twin, &twin.controller, timing, &run);
        let ratio = rep.channels[0].rms / offline.channels[0].rms;
        eprintln!(
            "{protocol:?} attempt {attempt}: RMS {:.3e} through the server, {:.3e} offline \
             ({timing:?}, holding the run's {} held periods): ratio {ratio:.3}; rtt p50 {:.0} \
             us, overruns {}",
            rep.channels[0].rms,
            offline.channels[0].rms,
            k.holding_periods,
            rep.rtt_p50_us,
            rep.overruns
        );
        ratios.push(ratio);
        if ratios.len() == judged {
            ratios.sort_by(f64::total_cmp);
            let median = ratios[judged / 2];
            assert!(
                median < rms_ratio_bound(),
                "median ratio {median} of {ratios:?}"
            );
            return;
        }
    }
    panic!(
        "{} of {attempts} attempts kept time, {judged} needed: this host cannot judge \
         tracking now",
        ratios.len()
    );
}

/// By Read: the bridge reads at the tick and writes once the command is back, which a
/// real-time server applies when it arrives, and this loop loses 12 % to a write 0.3 ms
/// late (`docs/fieldbus.md`). Against the lockstep twin the ratio was a draw on the host's
/// speed: Modbus 1.06 to 1.13 on 11-27, 1.39 in a CI run on 11-29; OPC UA 0.89 to 1.13
/// then, 1.31 to 1.40 on an idle machine on 11-29, with round trips of 0.4-0.5 ms. So the
/// twin writes the run's median round trip after the tick, which is about the live loop's
/// own delay (the server answers a Read with its plant as it is when the request arrives,
/// after the tick, and applies a write when that arrives, later than the round trip by
/// about as much), the round trip itself is bounded, and the median of three runs is
/// judged.
#[tokio::test(flavor = "multi_thread")]
async fn a_modbus_plant_tracks_through_the_service_as_its_offline_twin() {
    tracks_as_its_twin(
        ServerKind::Modbus,
        "plants/servers/motor-steps-modbus.toml",
        |_| (),
        (IoTiming::default(), Writes::AfterRoundTrip),
        3,
    )
    .await;
}

/// As for Modbus.
#[tokio::test(flavor = "multi_thread")]
async fn an_opcua_plant_tracks_through_the_service_as_its_offline_twin() {
    tracks_as_its_twin(
        ServerKind::OpcUa,
        "plants/servers/motor-steps-opcua.toml",
        |_| (),
        (IoTiming::default(), Writes::AfterRoundTrip),
        3,
    )
    .await;
}

/// The same with the outputs by subscription (the server samples them every millisecond,
/// the default at a 10 ms period, and publishes the changes): no Read per period, and
/// values older than a Read's, by up to a sampling plus a publishing interval (2 ms). This
/// loop is that sensitive: offline, a value 0.5 ms old costs it 16 % of its RMS and 1 ms
/// 30 % (`mfc-lab sim --value-age-ms`), and against the lockstep twin the ratio was a draw
/// on when asyncua's Python event loop sampled and published (0.95 to 1.50 in single runs;
/// medians of three 1.30 and 1.37 failed on 11-28). So the twin reads each value 1 ms
/// before the tick, the sampling interval the bridge asks for; the live runs behaved about
/// so (their medians of three against the lockstep twin, 1.16 to 1.37, are where 0.5 to
/// 1.5 ms of age puts it). That widens what passes, and says by how much: the bound 1.3 on
/// this twin is 1.69 on the lockstep one, so a bridge serving values 3 ms old would pass
/// (1.13 of this twin) where 5 ms (2.04) or a period's worth (about 100) fails
/// (`docs/fieldbus.md`). Judged on the median of three runs, as one run's ratio still
/// spreads by a third.
#[tokio::test(flavor = "multi_thread")]
async fn an_opcua_plant_by_subscription_tracks_as_its_offline_twin() {
    tracks_as_its_twin(
        ServerKind::OpcUa,
        "plants/servers/motor-steps-opcua.toml",
        |s| match &mut s.plant {
            PlantSource::OpcUa(o) => {
                // The default sampling interval: a tenth of the period, 1 ms.
                o.config.sampling = plant::opcua::Sampling::Subscribe;
                assert_eq!(o.sampling_interval, std::time::Duration::from_millis(1));
            }
            other => panic!("an OPC UA plant, not {other:?}"),
        },
        (
            IoTiming {
                value_age: 1e-3,
                write_delay: 0.0,
            },
            Writes::AsTimed,
        ),
        3,
    )
    .await;
}

/// A gateway agent hosting a plant behind each server (and a driver plant beside them) in
/// one batch per period: each is served under its own device and left at its safe value.
#[tokio::test(flavor = "multi_thread")]
async fn a_gateway_hosts_plants_behind_servers_beside_a_driver() {
    use mfc_lab::harness::{default_safety, ServiceHandle};
    use plant_agent::agent::{open_plant, LoopConfig};

    let _serial = SERIAL.lock().await;
    let modbus = Server::start_as(ServerKind::Modbus, free_port(), &[]);
    let opcua = Server::start_as(ServerKind::OpcUa, free_port(), &[]);
    let scenarios = [
        pointed(load("plants/servers/motor-steps-modbus.toml"), &modbus),
        pointed(load("plants/servers/motor-steps-opcua.toml"), &opcua),
        load("plants/dc-motor/scenarios/motor-steps.toml"),
    ];
    let ids: Vec<String> = ["cell-modbus", "cell-opcua", "cell-driver"]
        .map(String::from)
        .to_vec();
    let mut config = controller_service::ServiceConfig::default();
    for (s, id) in scenarios.iter().zip(&ids) {
        config
            .devices
            .extend(service_config(s, &s.controller, std::slice::from_ref(id)).devices);
    }
    let service = ServiceHandle::start_keyed(config, None).await.unwrap();
    let secret = service.secret.clone().unwrap();
    let session = service.client().await.unwrap();
    let mut plants = Vec::new();
    for (s, id) in scenarios.iter().zip(&ids) {
        let mut safety = default_safety(s);
        safety.hold_periods += system_tests::margin_periods();
        let plant = open_plant(s, s.seed).await.unwrap();
        plants.push((plant, LoopConfig::new(s, &s.controller, id, safety)));
    }
    let runs = plant_agent::gateway::run_gateway(
        &session,
        "cell-f",
        plants,
        Some(secret.gateway("cell-f")),
        plant::run_id,
        std::future::pending(),
    )
    .await
    .unwrap();
    let status: protocol::pb::ServiceStatus = system_tests::query(
        &session,
        protocol::keys::service_status("controller-1"),
        None,
    )
    .await
    .unwrap();
    let _ = session.close().await;
    service.stop().await.unwrap();
    // Everything first, so that a failure shows every plant's counts and the service's.
    eprintln!(
        "service: {} batches superseded, {} dropped for a full queue; lost per device: {:?}",
        status.superseded_batches,
        status.queue_full,
        status
            .devices
            .iter()
            .map(|d| (d.device_id.as_str(), d.lost))
            .collect::<Vec<_>>()
    );
    let reports: Vec<_> = runs.into_iter().map(|r| r.unwrap().report).collect();
    for r in &reports {
        eprintln!("{}: {:?}", r.headline(), r.counters);
    }
    for (r, id) in reports.iter().zip(&ids) {
        assert_eq!(&r.device_id, id);
        assert!(r.completed() && r.safe_stop_applied, "{r:?}");
        assert_eq!(r.link, plant_agent::agent::ControllerLink::Kept, "{r:?}");
        let k = &r.counters;
        assert!(
            (k.commands + k.warming_up) as f64 >= 0.95 * k.periods as f64,
            "{id}: {k:?}"
        );
    }
    assert_eq!(input_now(&modbus), SAFE);
    assert_eq!(input_now(&opcua), SAFE);
}
