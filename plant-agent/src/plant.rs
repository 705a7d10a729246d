//! The plant behind the agent: a [`Plant`] trait with two backends.
//!
//! * [`SimPlant`]: the AERO simulator, in process;
//! * [`DriverPlant`]: a separate process that talks to the real rig (a Quanser HIL program,
//!   a Python script, ...) over a line protocol on its stdin/stdout, so real hardware plugs
//!   in without recompiling. `plant-agent sim-driver` is a reference driver backed by the
//!   simulator.
//!
//! # Driver protocol (one line each way, ASCII, numbers as decimal floats)
//!
//! | agent sends | driver answers | meaning |
//! |---|---|---|
//! | (on start) | `hello channels=N` | the driver is ready and has `N` outputs and inputs |
//! | `read` | `y1 y2 ... yN` | measure the outputs now |
//! | `write v1 ... vN` | `ok a1 ... aN` | apply the inputs from now on; `a` is what was really applied (after the amplifier's limits) |
//! | `advance DT` | `ok` | simulated drivers advance their time by `DT` seconds; real ones ignore it |
//! | `stop` | `ok` | apply a safe stop and exit |
//!
//! Any request may be answered `err MESSAGE`. A driver that does not answer within the
//! agent's timeout is treated as failed: the agent stops.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use crate::aero::{AeroParams, AeroSim, CHANNELS};

/// Why the plant could not be driven.
#[derive(Debug, thiserror::Error)]
pub enum PlantError {
    /// The driver process could not be started or talked to.
    #[error("driver: {0}")]
    Driver(String),
    /// The driver did not answer in time.
    #[error("driver did not answer `{request}` within {timeout:?}")]
    Timeout {
        /// The request.
        request: String,
        /// The timeout.
        timeout: Duration,
    },
    /// The driver answered something that does not follow the protocol.
    #[error("driver answered {answer:?} to `{request}`")]
    Protocol {
        /// The request.
        request: String,
        /// The answer.
        answer: String,
    },
    /// Simulator parameters.
    #[error(transparent)]
    Params(#[from] crate::aero::ParamError),
}

/// A plant the agent can drive.
pub trait Plant: Send {
    /// Number of outputs (= number of inputs).
    fn channels(&self) -> usize;
    /// Measure the outputs now.
    fn read(&mut self) -> Result<Vec<f64>, PlantError>;
    /// Apply `v` from now on; returns what was really applied.
    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError>;
    /// Let `dt` seconds pass (simulators integrate; real plants ignore it: time passes).
    fn advance(&mut self, dt: f64) -> Result<(), PlantError>;
    /// Apply zeros and release the plant.
    fn stop(&mut self) -> Result<(), PlantError>;
}

/// The AERO simulator as a [`Plant`].
pub struct SimPlant {
    sim: AeroSim,
}

impl SimPlant {
    /// A simulated AERO.
    pub fn new(params: AeroParams, seed: u64) -> Result<Self, PlantError> {
        Ok(Self {
            sim: AeroSim::new(params, seed)?,
        })
    }

    /// The simulator (for its true state).
    pub fn sim(&self) -> &AeroSim {
        &self.sim
    }
}

fn pair(v: &[f64]) -> [f64; 2] {
    [
        v.first().copied().unwrap_or(0.0),
        v.get(1).copied().unwrap_or(0.0),
    ]
}

impl Plant for SimPlant {
    fn channels(&self) -> usize {
        CHANNELS
    }
    fn read(&mut self) -> Result<Vec<f64>, PlantError> {
        Ok(self.sim.measure().to_vec())
    }
    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        Ok(self.sim.apply(pair(v)).to_vec())
    }
    fn advance(&mut self, dt: f64) -> Result<(), PlantError> {
        self.sim.advance(dt);
        Ok(())
    }
    fn stop(&mut self) -> Result<(), PlantError> {
        self.sim.apply([0.0, 0.0]);
        Ok(())
    }
}

/// A plant behind an external driver process.
pub struct DriverPlant {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<String>,
    channels: usize,
    timeout: Duration,
}

impl DriverPlant {
    /// Start `program args...` and wait (up to `timeout`) for its `hello`.
    pub fn spawn(program: &str, args: &[String], timeout: Duration) -> Result<Self, PlantError> {
        let mut child = Command::new(program)
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| PlantError::Driver(format!("starting {program}: {e}")))?;
        let stdin = child
            .stdin
            .take()
            .ok_or_else(|| PlantError::Driver("no stdin".into()))?;
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| PlantError::Driver("no stdout".into()))?;
        let (tx, lines) = mpsc::channel();
        // A reader thread turns the blocking pipe into a channel we can wait on with a
        // timeout: a hung driver must not hang the agent.
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut plant = Self {
            child,
            stdin,
            lines,
            channels: 0,
            timeout,
        };
        let hello = plant.answer("(start)")?;
        plant.channels = hello
            .strip_prefix("hello channels=")
            .and_then(|n| n.trim().parse().ok())
            .filter(|n| *n > 0)
            .ok_or(PlantError::Protocol {
                request: "(start)".into(),
                answer: hello.clone(),
            })?;
        Ok(plant)
    }

    fn answer(&mut self, request: &str) -> Result<String, PlantError> {
        match self.lines.recv_timeout(self.timeout) {
            Ok(line) => match line.strip_prefix("err ") {
                Some(msg) => Err(PlantError::Driver(format!("`{request}`: {msg}"))),
                None => Ok(line),
            },
            Err(mpsc::RecvTimeoutError::Timeout) => Err(PlantError::Timeout {
                request: request.into(),
                timeout: self.timeout,
            }),
            Err(mpsc::RecvTimeoutError::Disconnected) => Err(PlantError::Driver(format!(
                "exited before answering `{request}`"
            ))),
        }
    }

    fn request(&mut self, request: &str) -> Result<String, PlantError> {
        writeln!(self.stdin, "{request}")
            .and_then(|()| self.stdin.flush())
            .map_err(|e| PlantError::Driver(format!("writing `{request}`: {e}")))?;
        self.answer(request)
    }

    fn numbers(&self, request: &str, text: &str) -> Result<Vec<f64>, PlantError> {
        let values: Result<Vec<f64>, _> = text.split_whitespace().map(str::parse).collect();
        match values {
            Ok(v) if v.len() == self.channels && v.iter().all(|x| x.is_finite()) => Ok(v),
            _ => Err(PlantError::Protocol {
                request: request.into(),
                answer: text.into(),
            }),
        }
    }
}

impl Plant for DriverPlant {
    fn channels(&self) -> usize {
        self.channels
    }
    fn read(&mut self) -> Result<Vec<f64>, PlantError> {
        let a = self.request("read")?;
        self.numbers("read", &a)
    }
    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        let req = format!(
            "write {}",
            v.iter()
                .map(|x| format!("{x:e}"))
                .collect::<Vec<_>>()
                .join(" ")
        );
        let a = self.request(&req)?;
        let rest = a.strip_prefix("ok").ok_or(PlantError::Protocol {
            request: req.clone(),
            answer: a.clone(),
        })?;
        self.numbers(&req, rest)
    }
    fn advance(&mut self, dt: f64) -> Result<(), PlantError> {
        let req = format!("advance {dt:e}");
        let a = self.request(&req)?;
        if a.trim() == "ok" {
            Ok(())
        } else {
            Err(PlantError::Protocol {
                request: req,
                answer: a,
            })
        }
    }
    fn stop(&mut self) -> Result<(), PlantError> {
        let a = self.request("stop");
        let _ = self.child.wait();
        a.map(|_| ())
    }
}

impl Drop for DriverPlant {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            let _ = writeln!(self.stdin, "stop");
            let _ = self.stdin.flush();
            std::thread::sleep(Duration::from_millis(50));
            let _ = self.child.kill();
            let _ = self.child.wait();
        }
    }
}

/// Serve the driver protocol on `input`/`output` with a simulated AERO: the reference
/// driver (`plant-agent sim-driver`) and the fake rig of the bridge's tests.
pub fn serve_sim_driver(
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
                    Ok(v) if v.len() == CHANNELS => {
                        let a = sim.apply(pair(&v));
                        format!("ok {:e} {:e}", a[0], a[1])
                    }
                    _ => format!("err write needs {CHANNELS} numbers"),
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
            _ => format!("err unknown request {line:?}"),
        };
        writeln!(output, "{reply}")?;
        output.flush()?;
    }
    Ok(())
}
