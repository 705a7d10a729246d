//! The offline loop with its I/O off the sample instant (`IoTiming`): refused when it does
//! not fit in a period, the lockstep run's figures when zero, and a late value or write
//! costs tracking and is recorded in the summary; held periods (a live run's missed
//! deadlines, replayed) leave the plant's input as it was.

use mfc_lab::offline::{simulate_holding, simulate_timed, IoTiming, RunError};
use plant::scenario::{load_scenario, Scenario};

const ROOT: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../plants/aero/scenarios");

/// The AERO's scenario 2, its first 20 s.
fn scenario() -> Scenario {
    let mut s = load_scenario(&format!("{ROOT}/2-complex.toml")).unwrap();
    s.duration = 20.0;
    s
}

fn timing(value_age: f64, write_delay: f64) -> IoTiming {
    IoTiming {
        value_age,
        write_delay,
    }
}

#[test]
fn a_timing_outside_the_period_is_refused_with_both_figures() {
    let s = scenario();
    for (t, says) in [
        (timing(-1e-3, 0.0), "at least 0 s, not -0.001 s"),
        (
            timing(0.0, f64::NAN),
            "finite and at least 0 s, not 0 s and NaN s",
        ),
        (timing(f64::INFINITY, 0.0), "not inf s"),
        (timing(6e-3, 4e-3), "0.006 s old and a write 0.004 s late"),
        (timing(0.0, 0.01), "period or more"),
    ] {
        match simulate_timed(&s, &s.controller, false, t) {
            Err(e @ RunError::Timing(_)) => {
                assert!(e.to_string().contains(says), "{t:?}: {e}")
            }
            other => panic!("{t:?} accepted: {:?}", other.map(|r| r.summary)),
        }
    }
    assert!(simulate_timed(&s, &s.controller, false, timing(5e-3, 4.9e-3)).is_ok());
}

/// With no delay the run is the lockstep one, whose figures the docs quote
/// (`docs/results-aero.md`, scenario 2 with the iPD: 8.578e-5 rad/s and 7.316e-3 rad).
#[test]
fn no_delay_gives_the_quoted_lockstep_figures() {
    let mut s = scenario();
    s.duration = load_scenario(&format!("{ROOT}/2-complex.toml"))
        .unwrap()
        .duration;
    let r = simulate_timed(&s, &s.controller, false, IoTiming::default())
        .unwrap()
        .summary;
    let rms: Vec<String> = r
        .channels
        .iter()
        .map(|c| format!("{:.3e}", c.rms))
        .collect();
    assert_eq!(rms, ["8.578e-5", "7.316e-3"]);
    assert_eq!(r.timing, None);
}

#[test]
fn a_later_value_or_write_tracks_worse_and_is_recorded() {
    let s = scenario();
    let run = |t: IoTiming| {
        let r = simulate_timed(&s, &s.controller, false, t).unwrap().summary;
        assert!(r.completed, "{t:?}");
        assert_eq!(r.timing, Some(t).filter(|t| *t != IoTiming::default()));
        r.channels[1].rms
    };
    let rms: Vec<f64> = [0.0, 3e-3, 6e-3, 9e-3]
        .iter()
        .map(|&a| run(timing(a, 0.0)))
        .collect();
    assert!(
        rms.windows(2).all(|w| w[1] > w[0]),
        "pitch RMS by age: {rms:?}"
    );
    let late_write = run(timing(0.0, 6e-3));
    assert!(late_write > rms[0], "{late_write} against {}", rms[0]);
}

/// A held period writes nothing: the input recorded is the one before it, the run's other
/// periods are written as usual, holding nothing is the timed run to the bit, and holding
/// a stretch costs tracking.
#[test]
fn a_held_period_keeps_the_input_it_had() {
    let s = scenario();
    let t = timing(1e-3, 0.0);
    let plain = simulate_timed(&s, &s.controller, true, t).unwrap();
    let none = simulate_holding(&s, &s.controller, true, t, &[]).unwrap();
    assert_eq!(plain.summary.channels, none.summary.channels);
    let n = plain.record.t.len();
    // Every fourth period from 5 s to 6 s held, as a starved host might.
    let held: Vec<bool> = (0..n)
        .map(|k| (500..600).contains(&k) && k % 4 == 0)
        .collect();
    let run = simulate_holding(&s, &s.controller, true, t, &held).unwrap();
    for (k, _) in held.iter().enumerate().filter(|(_, h)| **h) {
        for tr in &run.record.traces {
            assert_eq!(tr.v[k], tr.v[k - 1], "period {k} wrote");
        }
    }
    let moved = (0..n)
        .filter(|&k| !held[k] && k > 0)
        .any(|k| run.record.traces.iter().any(|tr| tr.v[k] != tr.v[k - 1]));
    assert!(moved, "the other periods were written");
    assert!(
        run.summary.channels[1].rms > plain.summary.channels[1].rms,
        "holding cost nothing: {} against {}",
        run.summary.channels[1].rms,
        plain.summary.channels[1].rms
    );
}
