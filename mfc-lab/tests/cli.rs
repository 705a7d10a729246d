//! The `mfc-lab` commands, run as a user would.

use std::process::Command;

fn lab() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mfc-lab"))
}

/// Run `cmd` and insist that it succeeds, showing its stderr if not.
fn succeed(cmd: &mut Command) -> std::process::Output {
    let out = cmd.output().unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    out
}

#[test]
fn sim_writes_timeseries_summary_and_plots() {
    let dir = tempfile::tempdir().unwrap();
    succeed(
        lab()
            .args(["sim", "--scenario", "4", "--controller", "ipd", "--out"])
            .arg(dir.path()),
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["scenario"], "scenario-4");
    assert_eq!(summary["controller"], "ipd");
    assert!(
        summary.get("timing").is_none(),
        "a lockstep run has no timing"
    );
    for ch in summary["channels"].as_array().unwrap() {
        for key in ["name", "rms", "max_abs", "iae", "saturated_fraction"] {
            assert!(!ch[key].is_null(), "{key}");
        }
    }
    let csv = std::fs::read_to_string(dir.path().join("run.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next().unwrap(),
        "t,azimuth_velocity_ref,azimuth_velocity,azimuth_velocity_u,azimuth_velocity_v,azimuth_velocity_f_est,pitch_ref,pitch,pitch_u,pitch_v,pitch_f_est"
    );
    assert_eq!(lines.count(), 4001);
    for name in ["azimuth_velocity", "pitch"] {
        for ext in ["png", "svg"] {
            let meta = std::fs::metadata(dir.path().join(format!("{name}.{ext}"))).unwrap();
            assert!(meta.len() > 10_000, "{name}.{ext} too small");
        }
    }
}

#[test]
fn tune_output_is_usable_by_sim() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("adrc.toml");
    let out = lab()
        .args([
            "tune",
            "--scenario",
            "1",
            "--controller",
            "adrc",
            "--budget",
            "6",
            "--out",
        ])
        .arg(&file)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    succeed(
        lab()
            .args(["sim", "--scenario", "3", "--controller"])
            .arg(&file)
            .arg("--out")
            .arg(dir.path().join("run")),
    );
}

/// `tune --family`: gains for a slice of the robustness family, written with the command
/// that made them and usable by `sim` and `robust`; the margins said before and after.
#[test]
fn a_family_tuning_says_its_margins_and_writes_a_usable_law() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("ipd-rotor.toml");
    let out = succeed(
        lab()
            .args([
                "tune",
                "--scenario",
                "1",
                "--controller",
                "ipd",
                "--budget",
                "4",
            ])
            .args(["--family", "--factors", "rotor", "--random", "1", "--out"])
            .arg(&file),
    );
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(said.contains("over 4 variations of scenario-1"), "{said}");
    assert!(said.contains("start: against the best baseline"), "{said}");
    assert!(said.contains("tuned: against the best baseline"), "{said}");
    // "worst margin X (start Y)": numbers, and the search kept nothing worse than its start.
    let margin = |after: &str| -> f64 {
        let rest = &said[said.find(after).unwrap() + after.len()..];
        rest.split([' ', ')']).next().unwrap().parse().unwrap()
    };
    let (tuned, start) = (margin("worst margin "), margin("(start "));
    assert!(
        tuned.is_finite() && start.is_finite() && tuned <= start,
        "{said}"
    );
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(
        text.starts_with(
            "# Written by `mfc-lab tune --scenario 1 --controller ipd --budget 4 --seed 1 \
             --family --random 1 --family-seed 1 --baselines pid,adrc --bound 2 --factors rotor`"
        ),
        "{text}"
    );
    succeed(
        lab()
            .args([
                "robust",
                "--scenario",
                "1",
                "--factors",
                "rotor",
                "--random",
                "0",
            ])
            .arg("--controllers")
            .arg(&file)
            .arg("--out")
            .arg(dir.path().join("robust")),
    );
}

/// `tune --family`'s bad input refused with the reason, nothing written.
#[test]
fn a_family_tuning_refuses_bad_flags_with_the_reason() {
    let dir = tempfile::tempdir().unwrap();
    for (flags, says) in [
        (["--bound", "0.5"], "--bound must be a ratio of 1 or more"),
        (["--chatter", "0"], "--chatter must be a positive number"),
        (
            ["--factors", "rotor,mass,rotor"],
            "--factors names `rotor` twice",
        ),
        (["--threads", "0"], "--threads"),
    ] {
        let out = lab()
            .args([
                "tune",
                "--controller",
                "ipd",
                "--budget",
                "1",
                "--family",
                "--out",
            ])
            .arg(dir.path().join("x.toml"))
            .args(flags)
            .output()
            .unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{err}");
    }
    // Another plant's baselines are its own files: the AERO's default says so.
    let heater = concat!(env!("CARGO_MANIFEST_DIR"), "/../plants/heater");
    let out = lab()
        .args(["tune", "--budget", "1", "--family", "--scenario"])
        .arg(format!("{heater}/scenarios/heater-steps.toml"))
        .arg("--start")
        .arg(format!("{heater}/controllers/ipd.toml"))
        .arg("--out")
        .arg(dir.path().join("h.toml"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("`pid` (--baselines"), "{err}");
    // The family's flags mean nothing without it, and a late timing is not the family's.
    for flags in [&["--random", "2"][..], &["--family", "--value-age-ms", "2"]] {
        let out = lab()
            .args(["tune", "--controller", "ipd", "--budget", "1", "--out"])
            .arg(dir.path().join("y.toml"))
            .args(flags)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{flags:?}");
        assert!(!dir.path().join("y.toml").exists(), "{flags:?}");
    }
}

#[test]
fn bad_input_gives_a_clear_error_and_exit_code() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(
        &bad,
        "name = \"x\"\nduration = 1.0\ncontroller = \"ip\"\nchanels = []\n",
    )
    .unwrap();
    let out = lab()
        .args(["sim", "--scenario"])
        .arg(&bad)
        .arg("--out")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("bad.toml") && err.contains("chanels"), "{err}");
    let out = lab()
        .args(["tune", "--controller", "lqr", "--out", "x.toml"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown controller kind `lqr`"));
    // Two entries of one name would each be measured against the other's perfect link.
    let shipped = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../plants/aero/controllers/ipd.toml"
    );
    let out = lab()
        .args(["netsim", "--controllers"])
        .arg(format!("ipd+h10,{shipped}+h10"))
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("both named \"ipd+h10\""), "{err}");
    for (flag, value, says) in [
        ("--max-age", "2000", "--max-age 2000"),
        ("--duration", "0", "--duration must be at least one period"),
        ("--jitter", "1.5", "--jitter must be between 0 and 1"),
    ] {
        let out = lab().args(["netsim", flag, value]).output().unwrap();
        assert!(!out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{flag}: {err}");
    }
    for (args, says) in [
        (
            &["--value-age-ms", "-1"][..],
            "--value-age-ms must be a number of milliseconds, 0 or more, not -1",
        ),
        (
            &["--write-delay-ms", "nan"],
            "--write-delay-ms must be a number of milliseconds, 0 or more, not NaN",
        ),
        (
            &["--value-age-ms", "6", "--write-delay-ms", "4"],
            "a value 0.006 s old and a write 0.004 s late take a whole 0.01 s period",
        ),
    ] {
        let out = lab()
            .args(["sim", "--duration", "1", "--out"])
            .arg(dir.path())
            .args(args)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(says), "{args:?}: {err}");
    }
}

/// A run with its I/O off the sample instant says so, on the terminal and in its summary;
/// a law tuned so says so in its file.
#[test]
fn a_late_timing_is_said_by_sim_and_tune() {
    let dir = tempfile::tempdir().unwrap();
    let out = succeed(
        lab()
            .args(["sim", "--duration", "2", "--value-age-ms", "1.5"])
            .args(["--write-delay-ms", "0.5", "--out"])
            .arg(dir.path()),
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("each value 1.5 ms old and each write 0.5 ms late"),
        "{text}"
    );
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["timing"]["value_age"], 1.5e-3);
    assert_eq!(summary["timing"]["write_delay"], 0.5e-3);
    let out = lab()
        .args(["sim", "--compare", "--value-age-ms", "1"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("--compare runs the lockstep loop"), "{err}");
    // A law tuned for late values: its file says with which timing, and the command.
    let file = dir.path().join("pid-late.toml");
    succeed(
        lab()
            .args([
                "tune",
                "--scenario",
                "1",
                "--controller",
                "pid",
                "--budget",
                "2",
            ])
            .args(["--value-age-ms", "2", "--out"])
            .arg(&file),
    );
    let text = std::fs::read_to_string(&file).unwrap();
    let first = text.lines().next().unwrap();
    assert!(
        first.contains("tune --scenario 1 --controller pid --budget 2 --seed 1 --value-age-ms 2`"),
        "the command that made it, as given: {first}"
    );
    assert!(text.contains("(seed 1, each value 2 ms old)"), "{text}");
}

fn plants() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../plants")
}

/// `sim` and `tune` on scenarios that name driver plants (the heater's one-sided actuator,
/// the motor with backlash): in lockstep, no network, the record and a usable controller.
#[test]
fn sim_and_tune_run_driver_plants() {
    let dir = tempfile::tempdir().unwrap();
    let heater = plants().join("heater/scenarios/heater-steps.toml");
    succeed(
        lab()
            .args(["sim", "--scenario"])
            .arg(&heater)
            .arg("--out")
            .arg(dir.path().join("heater")),
    );
    let summary: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("heater/summary.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(summary["scenario"], "heater-steps");
    let ch = &summary["channels"][0];
    assert_eq!(ch["name"], "temperature");
    // The heater's actuator is 0..24 V: voltages between 0 and 10 V are reachable (no
    // AERO dead-zone map), and the run tracks within a degree RMS.
    assert!(ch["rms"].as_f64().unwrap() < 1.0, "{summary}");
    let csv = std::fs::read_to_string(dir.path().join("heater/run.csv")).unwrap();
    let v: Vec<f64> = csv
        .lines()
        .skip(1)
        .map(|l| l.split(',').nth(4).unwrap().parse().unwrap())
        .collect();
    assert_eq!(v.len(), 4001);
    assert!(v.iter().all(|v| (0.0..=24.0).contains(v)));
    assert!(
        v.iter().any(|v| *v > 1.0 && *v < 9.0),
        "inside the AERO's dead zone"
    );

    let motor = plants().join("dc-motor/scenarios/motor-steps.toml");
    let tuned = dir.path().join("pid.toml");
    let out = succeed(
        lab()
            .args(["tune", "--scenario"])
            .arg(&motor)
            .arg("--start")
            .arg(plants().join("dc-motor/controllers/start/pid.toml"))
            .args(["--budget", "4", "--out"])
            .arg(&tuned),
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("in 4 runs"));
    succeed(
        lab()
            .args(["sim", "--scenario"])
            .arg(&motor)
            .arg("--controller")
            .arg(&tuned)
            .arg("--out")
            .arg(dir.path().join("motor")),
    );
    // A controller for another channel count is refused, naming both counts.
    let out = lab()
        .args(["sim", "--scenario"])
        .arg(&motor)
        .args(["--controller", "ipd"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("1 channel") && err.contains("2 law"), "{err}");
}
