//! The offline loop with its I/O off the sample instant (`IoTiming`): refused when it does
//! not fit in a period, the lockstep run when zero, and a late value costs tracking.

use mfc_lab::offline::{simulate, simulate_timed, IoTiming, RunError};
use plant::scenario::{load_scenario, Scenario};

fn scenario() -> Scenario {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../plants/aero/scenarios");
    let mut s = load_scenario(&format!("{root}/2-complex.toml")).unwrap();
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
        (timing(-1e-3, 0.0), "not negative"),
        (timing(0.0, f64::NAN), "not negative"),
        (timing(f64::INFINITY, 0.0), "not negative"),
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

#[test]
fn no_delay_is_the_lockstep_run_and_a_later_value_tracks_worse() {
    let s = scenario();
    let pitch = |t: IoTiming| {
        let r = simulate_timed(&s, &s.controller, false, t).unwrap().summary;
        assert!(r.completed, "{t:?}");
        r.channels[1].rms
    };
    let lockstep = simulate(&s, &s.controller, false).unwrap().summary;
    let zero = simulate_timed(&s, &s.controller, false, IoTiming::default()).unwrap();
    assert_eq!(zero.summary, lockstep, "zero delays change nothing");
    let rms: Vec<f64> = [0.0, 3e-3, 6e-3, 9e-3]
        .iter()
        .map(|&a| pitch(timing(a, 0.0)))
        .collect();
    assert!(
        rms.windows(2).all(|w| w[1] > w[0]),
        "pitch RMS by age: {rms:?}"
    );
    let late_write = pitch(timing(0.0, 6e-3));
    assert!(late_write > rms[0], "{late_write} against {}", rms[0]);
}
