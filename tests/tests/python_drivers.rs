//! The Python plant drivers share one serve loop (`plants/driver_loop.py`); their own test,
//! `plants/test_drivers.py` (standard-library `unittest`), feeds the loop and every driver
//! bad requests and asserts the same `err` answers from each, with nothing changed. Run here
//! so that `cargo test` runs it: the drivers need only `python3`, like the other driver tests.

use std::process::Command;

use system_tests::workspace_root;

#[test]
fn the_python_drivers_refuse_bad_requests_alike() {
    let run = Command::new("python3")
        .arg(workspace_root().join("plants/test_drivers.py"))
        .arg("-v")
        .output()
        .expect("running python3 plants/test_drivers.py");
    // unittest reports on stderr: one line per test, then "Ran N tests" and "OK".
    let report = String::from_utf8_lossy(&run.stderr);
    eprintln!("{report}");
    assert!(run.status.success(), "plants/test_drivers.py failed");
    let ran: usize = report
        .lines()
        .find_map(|l| l.strip_prefix("Ran ")?.split(' ').next()?.parse().ok())
        .unwrap_or_else(|| panic!("no \"Ran N tests\" in:\n{report}"));
    // A script that exits 0 having run nothing (or skipped its tests) fails.
    assert!(ran >= 9, "only {ran} tests ran");
    assert_eq!(report.trim_end().lines().last(), Some("OK"), "{report}");
}
