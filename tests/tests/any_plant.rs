//! Any plant, any number of channels, end to end: driver plants of 1, 3 and 16 channels run
//! offline in lockstep and over Zenoh through the service, with the same files.

use std::path::{Path, PathBuf};

use mfc_lab::harness::{run_fleet, service_config};
use mfc_lab::offline::{simulate, IoTiming};
use plant::scenario::{load_scenario, Scenario};
use plant_agent::agent::End;
use system_tests::{
    holding_twin, lags_ratio_bound, scratch_dir, served_plant, workspace_root, SERIAL,
};

/// A scenario of `n` coupled first-order lags (`plants/coupled-lags`), each channel with
/// its own smooth step, and an iP per channel (alpha = b_i / tau_i, the driver's input
/// gain over its time constant).
fn lags(dir: &Path, n: usize, duration: f64) -> PathBuf {
    let driver = workspace_root().join("plants/coupled-lags/coupled_lags.py");
    let mut text = format!(
        "name = \"lags-{n}\"\nduration = {duration:.1}\nperiod = 0.01\n\n[plant]\ndriver = [\"python3\", {:?}, \"--channels\", \"{n}\", \"--seed\", \"7\"]\n\n",
        driver.to_str().unwrap()
    );
    for i in 0..n {
        text += &format!(
            "[[channels]]\nname = \"y{i}\"\nreference = [{{ kind = \"smooth_step\", start = {:.2}, duration = 0.5, height = {:.2} }}]\noutput = {{ min = -10.0, max = 10.0 }}\n\n",
            0.3 + 0.2 * i as f64 % 2.0,
            1.0 - 0.1 * (i % 5) as f64
        );
    }
    text += "[controller]\nname = \"ip\"\n";
    for i in 0..n {
        let (b, tau) = (1.0 + 0.1 * i as f64, 0.5 + 0.25 * i as f64);
        text += &format!(
            "[[controller.channels]]\nlaw = \"intelligent\"\nparams = {{ kind = \"ip\", order = \"one\", alpha = {}, kp = 5.0 }}\nestimator = {{ window = 10 }}\n",
            b / tau
        );
    }
    let path = dir.join(format!("lags-{n}.toml"));
    std::fs::write(&path, text).unwrap();
    path
}

fn load(path: &Path) -> Scenario {
    load_scenario(path.to_str().unwrap()).unwrap()
}

/// Offline, in lockstep, as fast as the driver answers: every channel tracks its step.
#[test]
fn driver_plants_of_1_3_and_16_channels_run_offline() {
    // Not real time, but it loads the cores: keep it off the real-time test's timing.
    let _serial = SERIAL.blocking_lock();
    let dir = scratch_dir("lags-offline");
    for n in [1, 3, 16] {
        let s = load(&lags(&dir, n, 3.0));
        assert_eq!(s.channels.len(), n);
        let r = simulate(&s, &s.controller, true).unwrap();
        assert!(r.summary.completed);
        assert_eq!(r.record.len(), s.steps());
        assert_eq!(r.record.traces.len(), n);
        for (i, tr) in r.record.traces.iter().enumerate() {
            let last = tr.y.len() - 1;
            let err = (tr.y[last] - tr.y_ref[last]).abs();
            assert!(err < 0.05, "lags-{n} y{i}: final error {err}");
            assert!(
                tr.v.iter().all(|v| (-10.0..=10.0).contains(v)),
                "inputs inside the actuator range"
            );
        }
    }
}

// Bound on a networked coupled-lags channel's RMS over its offline twin's. That the loop
// is served is shown by the counters (a command for 95 % of the periods, no fallback);
// this bound catches a channel served the wrong values. On an idle machine the 16-channel
// chain gives 1.03 on its first channel up to 1.24 on its last (its slow channels feel the
// command's delay within the period, and the coupling adds it up); with the other core
// kept busy, the same. The bound, 2.0 by default, is [`lags_ratio_bound`]
// (`MFC_TEST_LAGS_RATIO`).
//
// The ratio is judged against a twin that holds where the run held. A held period is the
// plant driven by a stale input for a whole period, and how many there are is the
// machine's doing, not the service's: one CI run on an overloaded machine (round trip p99
// 9 ms, 15 held periods of 401 for the 16-channel plant, 59 for the 1-channel one) gave
// 2.01 on channel 10 against the plain twin. Until 12-03 a group whose plants held more
// than 2 % of periods was run again, at most three times, and the test failed if none
// kept time; the twin now holds the same periods (`simulate_holding`), so every run is
// judged, and the counters (commands for 95 % of periods, no fallback) still fail a loop
// that holds for want of a controller.

/// Over Zenoh through the service: a 1-channel and a 3-channel plant on one service, then
/// a 16-channel one; each is served (commands, no fallback) and tracks within
/// [`lags_ratio_bound`] of its offline twin, holding where the run held.
#[tokio::test(flavor = "multi_thread")]
async fn driver_plants_of_1_3_and_16_channels_run_through_the_service() {
    let _serial = SERIAL.lock().await;
    let dir = scratch_dir("lags-network");
    for group in [vec![1usize, 3], vec![16]] {
        let scenarios: Vec<Scenario> = group.iter().map(|n| load(&lags(&dir, *n, 4.0))).collect();
        let mut config = controller_service::ServiceConfig::default();
        let mut plants = Vec::new();
        for s in &scenarios {
            let id = s.name.clone();
            config
                .devices
                .extend(service_config(s, &s.controller, std::slice::from_ref(&id)).devices);
            plants.push(served_plant(s, &s.controller, &id));
        }
        let runs = run_fleet(plants, config).await.unwrap();
        for (s, r) in scenarios.iter().zip(&runs) {
            let rep = &r.report;
            eprintln!("{}", rep.headline());
            assert_eq!(rep.end, End::Completed, "{rep:?}");
            assert!(rep.safe_stop_applied && rep.controller_reached);
            assert_eq!(rep.exit_code(), 0);
            assert_eq!(rep.channels.len(), s.channels.len());
            let k = &rep.counters;
            eprintln!(
                "{}: {k:?}; overruns {}, rtt p50 {:.0} p99 {:.0} us",
                s.name, rep.overruns, rep.rtt_p50_us, rep.rtt_p99_us
            );
            assert!(
                (k.commands + k.warming_up) as f64 >= 0.95 * k.periods as f64,
                "{}: {k:?}",
                s.name
            );
            assert_eq!(k.fallbacks, 0, "{}: {k:?}", s.name);
            // The record has every channel's columns, and a mode a period.
            assert_eq!(r.record.traces.len(), s.channels.len());
            assert_eq!(r.record.modes.len(), r.record.len());
            let offline = holding_twin(s, &s.controller, IoTiming::default(), r);
            for (net, off) in r.report.channels.iter().zip(&offline.channels) {
                let ratio = net.rms / off.rms;
                eprintln!(
                    "{} {}: ratio {ratio:.3} (the twin holding the run's {} held periods)",
                    s.name, net.name, k.holding_periods
                );
                assert!(
                    ratio < lags_ratio_bound(),
                    "{} {}: ratio {ratio}",
                    s.name,
                    net.name
                );
            }
        }
    }
}
