//! A plant from the factory floor with no code: the DC motor behind a Modbus TCP server we
//! did not write (pymodbus), controlled over Zenoh through the controller service, tracks
//! as its offline twin (the same physics as a driver, in lockstep) does, and is left with
//! its safe value in the server's register.

use mfc_lab::harness::{run_fleet, service_config};
use mfc_lab::offline::simulate;
use plant::modbus::RegisterKind;
use plant::scenario::{load_scenario, PlantSource};
use plant_agent::agent::End;
use system_tests::{max_held_fraction, rms_ratio_bound, served_plant, SERIAL};

#[path = "../../plant-agent/tests/support/modbus_server.rs"]
mod modbus_server;
use modbus_server::{free_port, root, Server};

#[tokio::test(flavor = "multi_thread")]
async fn a_modbus_plant_tracks_through_the_service_as_its_offline_twin() {
    const ATTEMPTS: usize = 3;
    const SAFE: f64 = 0.25;
    let _serial = SERIAL.lock().await;
    let shipped = root().join("plants/servers/motor-steps-modbus.toml");
    let mut modbus = load_scenario(shipped.to_str().unwrap()).unwrap();
    modbus.duration = 9.0;
    let mut twin = load_scenario(
        root()
            .join("plants/dc-motor/scenarios/motor-steps.toml")
            .to_str()
            .unwrap(),
    )
    .unwrap();
    twin.duration = modbus.duration;
    assert_eq!(modbus.controller, twin.controller, "the same law on both");
    let offline = simulate(&twin, &twin.controller, false).unwrap().summary;
    for attempt in 1..=ATTEMPTS {
        let server = Server::start(free_port(), &[]);
        let PlantSource::Modbus(m) = &mut modbus.plant else {
            panic!("the shipped file is a Modbus plant")
        };
        m.config.address = server.address();
        m.config.channels[0].safe = SAFE;
        let id = "motor-1".to_string();
        let config = service_config(&modbus, &modbus.controller, std::slice::from_ref(&id));
        let plants = vec![served_plant(&modbus, &modbus.controller, &id)];
        let run = run_fleet(plants, config).await.unwrap().remove(0);
        let rep = &run.report;
        eprintln!("attempt {attempt}: {}", rep.headline());
        assert_eq!(rep.end, End::Completed, "{rep:?}");
        assert!(rep.safe_stop_applied && rep.controller_reached, "{rep:?}");
        let k = &rep.counters;
        assert!(
            (k.commands + k.warming_up) as f64 >= 0.95 * k.periods as f64,
            "served: {k:?}"
        );
        assert_eq!(k.fallbacks, 0, "{k:?}");
        // The probe is a blocking client (its own runtime): off the async worker.
        let left = tokio::task::block_in_place(|| server.value(RegisterKind::Holding, 0));
        assert_eq!(left, SAFE, "the safe value was left");
        let held = k.holding_periods as f64 / k.periods.max(1) as f64;
        if held > max_held_fraction() {
            eprintln!(
                "attempt {attempt}: {:.1} % of periods held: not judged",
                100.0 * held
            );
            continue;
        }
        let ratio = rep.channels[0].rms / offline.channels[0].rms;
        eprintln!(
            "attempt {attempt}: RMS {:.3e} over Modbus, {:.3e} offline: ratio {ratio:.3}; rtt p50 {:.0} us, overruns {}",
            rep.channels[0].rms, offline.channels[0].rms, rep.rtt_p50_us, rep.overruns
        );
        assert!(ratio < rms_ratio_bound(), "ratio {ratio}");
        return;
    }
    panic!(
        "no attempt of {ATTEMPTS} had its commands in time: this machine cannot judge tracking now"
    );
}
