//! The reference plant driver: the simulated AERO behind the agent's line protocol
//! (`plant-agent/DRIVER.md`), on any reader and writer.
//!
//! It is what a driver for a real rig should do, in a few lines: answer `hello`, serve
//! `read`, `write`, `advance` and `stop`, refuse what it does not understand with `err` and
//! keep serving, and apply a safe stop (zero volts) both on `stop` and when its input ends
//! (the agent died or closed the pipe): a rig must never keep the last voltage because its
//! master went away.

use std::io::{BufRead, Write};

use crate::{AeroParams, AeroSim, CHANNELS};

fn pair(v: &[f64]) -> [f64; 2] {
    [
        v.first().copied().unwrap_or(0.0),
        v.get(1).copied().unwrap_or(0.0),
    ]
}

/// Serve the driver protocol on `input`/`output` with a simulated AERO until `stop` or the
/// end of `input`; both end in a safe stop.
pub fn serve(
    params: AeroParams,
    seed: u64,
    input: impl BufRead,
    mut output: impl Write,
) -> std::io::Result<()> {
    let mut sim = match AeroSim::new(params, seed) {
        Ok(s) => s,
        Err(e) => {
            writeln!(output, "err {e}")?;
            return Ok(());
        }
    };
    writeln!(output, "hello channels={CHANNELS}")?;
    output.flush()?;
    for line in input.lines() {
        let line = line?;
        let mut words = line.split_whitespace();
        let reply = match words.next() {
            Some("read") => {
                let y = sim.measure();
                format!("{:e} {:e}", y[0], y[1])
            }
            Some("write") => {
                let v: Result<Vec<f64>, _> = words.map(str::parse::<f64>).collect();
                match v {
                    Ok(v) if v.len() == CHANNELS && v.iter().all(|x| x.is_finite()) => {
                        let a = sim.apply(pair(&v));
                        format!("ok {:e} {:e}", a[0], a[1])
                    }
                    _ => format!("err write needs {CHANNELS} finite numbers"),
                }
            }
            Some("advance") => match words.next().and_then(|w| w.parse::<f64>().ok()) {
                Some(dt) if dt.is_finite() && dt >= 0.0 => {
                    sim.advance(dt);
                    "ok".into()
                }
                _ => "err advance needs a duration".into(),
            },
            Some("stop") => {
                sim.apply([0.0, 0.0]);
                writeln!(output, "ok")?;
                output.flush()?;
                return Ok(());
            }
            _ => format!("err unknown request {:?}", truncate(&line, 80)),
        };
        writeln!(output, "{reply}")?;
        output.flush()?;
    }
    // End of input: the agent is gone. Safe stop, as on `stop`.
    sim.apply([0.0, 0.0]);
    Ok(())
}

/// At most `n` characters of `s`, so an error never echoes a huge line back.
fn truncate(s: &str, n: usize) -> &str {
    match s.char_indices().nth(n) {
        Some((i, _)) => &s[..i],
        None => s,
    }
}
