//! The networked loop in lockstep: on a perfect link it is the offline run, exactly; on a
//! slow link the packetized horizon keeps the pitch where holding the late command does
//! not. Seeded, so every figure here is the same on every run.

use controller_service::config::Prediction;
use mfc_lab::harness::default_safety;
use mfc_lab::netsim::{simulate_net, LinkModel, Lossy};
use mfc_lab::offline::simulate;
use plant::scenario::{load_scenario, shipped_controller};

#[test]
fn on_a_perfect_link_the_service_and_the_agent_reproduce_the_offline_run() {
    let s = load_scenario("2").unwrap();
    for name in ["ipd", "pid", "adrc"] {
        let c = shipped_controller(name).unwrap();
        let offline = simulate(&s, &c, false).unwrap().summary;
        let net = simulate_net(
            &s,
            &c,
            Prediction::default(),
            &LinkModel::PERFECT,
            default_safety(&s),
        )
        .unwrap();
        for (a, b) in offline.channels.iter().zip(&net.channels) {
            assert!(
                (a.rms - b.rms).abs() <= 1e-12 * a.rms,
                "{name} {}: offline {} networked {}",
                a.name,
                a.rms,
                b.rms
            );
        }
        assert_eq!(net.counters.missing, 0, "{name}");
        // Every period answered: a command, or (while a window fills) warming up.
        let k = &net.counters;
        assert_eq!(k.commands + k.warming_up, k.periods, "{name}");
    }
}

#[test]
fn on_a_100_ms_round_trip_the_horizon_keeps_the_pitch() {
    let s = load_scenario("2").unwrap();
    let c = shipped_controller("ipd").unwrap();
    let link = LinkModel {
        delay: 0.05,
        jitter: 0.01,
        seed: 1,
        ..LinkModel::PERFECT
    };
    let run = |horizon| {
        simulate_net(
            &s,
            &c,
            Prediction {
                horizon,
                delay_compensation: false,
                ..Prediction::default()
            },
            &link,
            default_safety(&s),
        )
        .unwrap()
    };
    let (held, planned) = (run(0), run(10));
    // Late commands land in the period after next or later: with a horizon, each applies
    // its element for the period it lands in.
    assert!(
        planned.counters.horizon_late > 1000,
        "{:?}",
        planned.counters
    );
    assert_eq!(held.counters.horizon_late, 0);
    let (a, b) = (held.channels[1].rms, planned.channels[1].rms);
    assert!(b < 0.7 * a, "pitch RMS with a horizon {b}, without {a}");
}

#[test]
fn a_lossy_link_loses_what_it_says_and_the_same_seed_gives_the_same_run() {
    let s = load_scenario("1").unwrap();
    let c = shipped_controller("ipd").unwrap();
    let link = |lossy| LinkModel {
        loss: 0.3,
        lossy,
        seed: 7,
        ..LinkModel::PERFECT
    };
    let run = |l| simulate_net(&s, &c, Prediction::default(), &l, default_safety(&s)).unwrap();
    let up = run(link(Lossy::Up));
    assert!(up.samples_lost > 1000 && up.commands_lost == 0, "{up:?}");
    let down = run(link(Lossy::Down));
    assert!(
        down.samples_lost == 0 && down.commands_lost > 1000,
        "{down:?}"
    );
    let again = run(link(Lossy::Down));
    assert_eq!(down.channels[1].rms, again.channels[1].rms);
    assert_eq!(down.counters, again.counters);
    assert!(LinkModel {
        loss: 1.5,
        ..LinkModel::PERFECT
    }
    .check()
    .is_err());
}
