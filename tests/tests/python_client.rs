//! The Python client proves the wire contract: `clients/python/tests/conformance.py`, run by
//! the venv that `clients/python/setup.sh` makes (pinned zenoh and protobuf, the module
//! generated from the same `.proto`), acts as plant and operator against the real service
//! binary. `.ci/run` runs the setup first; on a fresh machine this test runs it itself
//! (pip needs PyPI then), and fails, saying why, if it cannot.

use std::process::Command;

use system_tests::{scratch_dir, workspace_root, SERIAL};

#[test]
fn the_python_client_conforms_to_the_contract() {
    let _s = SERIAL.blocking_lock();
    let root = workspace_root();
    let setup = Command::new("bash")
        .arg(root.join("clients/python/setup.sh"))
        .output()
        .expect("running clients/python/setup.sh");
    assert!(
        setup.status.success(),
        "clients/python/setup.sh failed (it needs python3 with venv and pip, and PyPI the \
         first time):\n{}",
        String::from_utf8_lossy(&setup.stderr)
    );
    let stdout = String::from_utf8_lossy(&setup.stdout);
    let python = stdout
        .lines()
        .last()
        .expect("setup.sh prints the venv's python")
        .trim();
    let summary = scratch_dir("python-client").join("conformance.json");
    let run = Command::new(python)
        .arg(root.join("clients/python/tests/conformance.py"))
        .args(["--service-bin", env!("CARGO_BIN_EXE_service-under-test")])
        .arg("--json")
        .arg(&summary)
        .output()
        .expect("running the conformance test");
    let report = String::from_utf8_lossy(&run.stdout);
    eprintln!("{report}");
    assert!(
        run.status.success(),
        "conformance failed:\n{report}\n{}",
        String::from_utf8_lossy(&run.stderr)
    );
    // The summary must say what ran: a script that exits 0 having checked nothing fails.
    let text = std::fs::read_to_string(&summary).expect("the conformance summary");
    let count = |field: &str| -> u64 {
        let at = text
            .find(&format!("\"{field}\": "))
            .unwrap_or_else(|| panic!("{field} in {text}"));
        text[at + field.len() + 4..]
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .and_then(|n| n.parse().ok())
            .unwrap_or_else(|| panic!("{field} in {text}"))
    };
    assert_eq!(count("failed"), 0, "{text}");
    assert!(count("passed") >= 20, "too few checks ran: {text}");
}
