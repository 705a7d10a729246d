//! The reference driver (`aero-sim` on stdin/stdout) behaves exactly as the simulator in
//! process, refuses bad requests without dying, and applies a safe stop on `stop` and on
//! the end of its input.

use std::io::{BufRead, BufReader, Write};
use std::process::{Command, Stdio};

use aero_sim::{AeroParams, AeroSim};

fn parse(line: &str) -> Vec<f64> {
    line.trim_start_matches("ok")
        .split_whitespace()
        .map(|w| w.parse().unwrap())
        .collect()
}

#[test]
fn the_driver_is_the_simulator() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_aero-sim"))
        .args(["--seed", "3"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut input = child.stdin.take().unwrap();
    let mut output = BufReader::new(child.stdout.take().unwrap()).lines();
    // hello comes first, unasked.
    assert_eq!(output.next().unwrap().unwrap(), "hello channels=2");
    let mut ask = |req: &str| {
        writeln!(input, "{req}").unwrap();
        input.flush().unwrap();
        output.next().unwrap().unwrap()
    };
    let mut sim = AeroSim::new(AeroParams::default(), 3).unwrap();
    for k in 0..200 {
        let v = [
            12.0 * (k as f64 * 0.05).sin(),
            30.0 * (k as f64 * 0.03).cos(),
        ];
        let answer = ask(&format!("write {:e} {:e}", v[0], v[1]));
        assert_eq!(parse(&answer), sim.apply(v).to_vec(), "applied (saturated)");
        assert_eq!(ask("advance 0.01"), "ok");
        sim.advance(0.01);
        // Full-precision floats on the wire: bit-identical.
        assert_eq!(parse(&ask("read")), sim.measure().to_vec());
    }
    assert!(ask("write 1").starts_with("err "), "wrong count");
    assert!(ask("write NaN 1").starts_with("err "), "non-finite");
    assert!(ask("fly").starts_with("err unknown request"));
    assert!(ask("advance -1").starts_with("err "));
    assert_eq!(ask("stop"), "ok");
    assert!(child.wait().unwrap().success());
}

/// The process exits cleanly when its input ends (the safe stop itself is checked on
/// `driver::serve`, where the rig can be seen).
#[test]
fn end_of_input_is_a_clean_exit() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_aero-sim"))
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    {
        let mut input = child.stdin.take().unwrap();
        writeln!(input, "write 20 20").unwrap();
    } // closed: EOF
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("hello channels=2"));
    assert!(lines.next().unwrap().starts_with("ok "));
    assert_eq!(lines.next(), None);
}
