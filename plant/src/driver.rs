//! The driver bridge: any plant behind a separate process that speaks a line protocol on
//! its stdin/stdout (`plant-agent/DRIVER.md`), as a [`Plant`]: a real rig's driver, a
//! Python simulator, ... Real hardware and user simulators plug in without recompiling.
//!
//! # Driver protocol (one line each way, ASCII, numbers as decimal floats)
//!
//! | agent sends | driver answers | meaning |
//! |---|---|---|
//! | (on start) | `hello channels=N` | the driver is ready and has `N` outputs and inputs |
//! | `read` | `y1 y2 ... yN` | measure the outputs now |
//! | `write v1 ... vN` | `ok a1 ... aN` | apply the inputs from now on; `a` is what was really applied (after the actuator's limits) |
//! | `advance DT` | `ok` | simulated drivers advance their time by `DT` seconds; real ones ignore it |
//! | `stop` | `ok` | apply a safe stop and exit |
//! | (end of input) | (exit) | the agent is gone: apply a safe stop and exit |
//!
//! Any request may be answered `err MESSAGE`. A driver that does not answer within the
//! timeout is treated as failed.

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use crate::scenario::DriverCommand;
use crate::{Plant, PlantError};

/// Longest wait for a driver's `hello`: interpreters and vendor SDKs start slowly.
pub const HELLO_TIMEOUT: Duration = Duration::from_secs(10);

/// A plant behind an external driver process.
pub struct DriverPlant {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<String>,
    channels: usize,
    timeout: Duration,
    /// Answers still owed by the driver: requests that timed out. A slow driver may still
    /// send them, and they must not pass for the answer to a later request.
    owed: usize,
}

impl DriverPlant {
    /// Start a driver as a scenario describes it, and wait for its `hello`.
    pub fn start(cmd: &DriverCommand) -> Result<Self, PlantError> {
        let (program, args) = cmd
            .argv
            .split_first()
            .ok_or_else(|| PlantError::Driver("empty driver command".into()))?;
        Self::spawn(
            program,
            args,
            cmd.dir.as_deref(),
            HELLO_TIMEOUT.max(cmd.timeout),
            cmd.timeout,
        )
    }

    /// Start `program args...` (in `dir`, if given), wait up to `hello_timeout` for its
    /// `hello`, then allow `timeout` per request.
    pub fn spawn(
        program: &str,
        args: &[String],
        dir: Option<&std::path::Path>,
        hello_timeout: Duration,
        timeout: Duration,
    ) -> Result<Self, PlantError> {
        let mut command = Command::new(program);
        command
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit());
        if let Some(d) = dir {
            command.current_dir(d);
        }
        let mut child = command.spawn().map_err(|e| {
            PlantError::Driver(format!(
                "starting {program}{}: {e}",
                dir.map(|d| format!(" in {}", d.display()))
                    .unwrap_or_default()
            ))
        })?;
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
            timeout: hello_timeout,
            owed: 0,
        };
        let hello = plant.answer("(start)")?;
        plant.timeout = timeout;
        plant.channels = hello
            .strip_prefix("hello channels=")
            .and_then(|n| n.trim().parse().ok())
            .filter(|n| (1..=crate::scenario::MAX_CHANNELS).contains(n))
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
            Err(mpsc::RecvTimeoutError::Timeout) => {
                self.owed += 1;
                Err(PlantError::Timeout {
                    request: request.into(),
                    timeout: self.timeout,
                })
            }
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
        // The answers owed for requests that timed out come first, if at all: skip that
        // many, so that only the driver's answer to `stop` itself confirms the safe stop.
        let owed = std::mem::take(&mut self.owed);
        let a = writeln!(self.stdin, "stop")
            .and_then(|()| self.stdin.flush())
            .map_err(|e| PlantError::Driver(format!("writing `stop`: {e}")))
            .and_then(|()| {
                for _ in 0..owed {
                    if let Err(mpsc::RecvTimeoutError::Disconnected) =
                        self.lines.recv_timeout(self.timeout)
                    {
                        return Err(PlantError::Driver("exited before answering `stop`".into()));
                    }
                }
                self.answer("stop")
            });
        self.reap();
        match a {
            Ok(a) if a.trim() == "ok" => Ok(()),
            Ok(a) => Err(PlantError::Protocol {
                request: "stop".into(),
                answer: a,
            }),
            Err(e) => Err(e),
        }
    }
}

impl DriverPlant {
    /// Wait a moment for the driver to exit after `stop` (or after its input closed),
    /// then kill it: a driver that ignores `stop` must not keep the agent from ending.
    fn reap(&mut self) {
        let until = std::time::Instant::now() + Duration::from_secs(2);
        while std::time::Instant::now() < until {
            if !matches!(self.child.try_wait(), Ok(None)) {
                return;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for DriverPlant {
    fn drop(&mut self) {
        if let Ok(None) = self.child.try_wait() {
            // Dropped without `stop` (an error path): ask for the safe stop, then make sure
            // the process is gone.
            let _ = writeln!(self.stdin, "stop");
            let _ = self.stdin.flush();
            self.reap();
        }
    }
}
