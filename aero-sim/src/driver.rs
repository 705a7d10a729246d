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
/// end of `input`; both end in a safe stop. Returns the voltages applied at the end (what
/// a test checks: zero), or `None` if the simulator could not be built (said with `err`).
pub fn serve(
    params: AeroParams,
    seed: u64,
    input: impl BufRead,
    mut output: impl Write,
) -> std::io::Result<Option<[f64; 2]>> {
    let mut sim = match AeroSim::new(params, seed) {
        Ok(s) => s,
        Err(e) => {
            writeln!(output, "err {e}")?;
            return Ok(None);
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
                return Ok(Some(sim.applied()));
            }
            _ => format!("err unknown request {:?}", truncate(&line, 80)),
        };
        writeln!(output, "{reply}")?;
        output.flush()?;
    }
    // End of input: the agent is gone. Safe stop, as on `stop`.
    sim.apply([0.0, 0.0]);
    Ok(Some(sim.applied()))
}

/// At most `n` characters of `s`, so an error never echoes a huge line back.
fn truncate(s: &str, n: usize) -> &str {
    match s.char_indices().nth(n) {
        Some((i, _)) => &s[..i],
        None => s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The agent writes 20 V and goes away without `stop`: the rig ends at zero volts.
    #[test]
    fn end_of_input_leaves_the_rig_at_zero_volts() {
        let mut out = Vec::new();
        let end = serve(
            AeroParams::default(),
            1,
            &b"write 20 20\nadvance 0.1\n"[..],
            &mut out,
        )
        .unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(text.contains("\nok 2"), "the write was applied: {text}");
        assert_eq!(end, Some([0.0, 0.0]));
    }

    /// Likewise on `stop`, which is answered.
    #[test]
    fn stop_leaves_the_rig_at_zero_volts_and_answers() {
        let mut out = Vec::new();
        let end = serve(
            AeroParams::default(),
            1,
            &b"write -20 20\nstop\nread\n"[..],
            &mut out,
        )
        .unwrap();
        let text = String::from_utf8(out).unwrap();
        assert!(text.trim_end().ends_with("ok"), "{text}");
        assert_eq!(end, Some([0.0, 0.0]));
    }
}
