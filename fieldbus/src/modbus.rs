//! The Modbus TCP bridge: a plant behind a Modbus server (a PLC, a drive, a gateway) as a
//! [`Plant`], through the map of its plant file ([`plant::modbus`]).
//!
//! Per period the agent reads (one request per block of the outputs' registers) and writes
//! (one request per run of contiguous inputs, then one per block of the applied values if
//! the map has them). Every way out writes each channel's `safe` value: the end of the
//! run and SIGTERM through [`Plant::stop`], an error through the agent's safe stop, a
//! dropped bridge through `Drop`; a lost connection is tried again for the map's
//! `reconnect_ms`, then the safe values go out on a new connection.
//!
//! Requests go through `tokio-modbus`'s synchronous client (its own current-thread
//! runtime): the agent runs plant I/O on a thread of its own, never on an async worker.
//! Answers are checked here, not by the library's debug assertions: a server that answers
//! fewer registers than asked, a NaN or a vanished register gives an error, never a panic.

use std::net::{SocketAddr, ToSocketAddrs};
use std::time::{Duration, Instant};

use plant::modbus::{plan_reads, plan_writes, Block, ModbusConfig, Point, RegisterKind};
use plant::scenario::ModbusPlant;
use plant::{Plant, PlantError};
use tokio_modbus::client::sync::{self, Client};
use tokio_modbus::{Request, Response, Slave};

use crate::reconnect::LinkOutage;

/// A plant behind a Modbus TCP server.
pub struct ModbusBridge {
    config: ModbusConfig,
    timeout: Duration,
    ctx: Option<sync::Context>,
    outputs: Vec<Point>,
    output_reads: Vec<Block>,
    /// The applied points the map has, and the reads that fetch them.
    applied: Vec<Point>,
    applied_reads: Vec<Block>,
    outage: LinkOutage,
    /// Where outages are timed from (the bridge's own monotonic clock).
    epoch: Instant,
    stopped: bool,
}

/// Why one attempt failed: the server said no (not worth another try), or the link did.
enum Failure {
    Answer(String),
    Link(String),
}

impl ModbusBridge {
    /// Connect to the server of `plant` (its map checked when the plant file was loaded).
    pub fn connect(plant: &ModbusPlant) -> Result<Self, PlantError> {
        let config = plant.config.clone();
        let outputs: Vec<Point> = config.channels.iter().map(|c| c.output).collect();
        let applied: Vec<Point> = config.channels.iter().filter_map(|c| c.applied).collect();
        let mut bridge = Self {
            output_reads: plan_reads(&outputs, config.max_gap),
            applied_reads: plan_reads(&applied, config.max_gap),
            outputs,
            applied,
            timeout: plant.timeout,
            ctx: None,
            outage: LinkOutage::default(),
            epoch: Instant::now(),
            // Nothing to stop until connected: a failed start must not spend the
            // reconnection budget on a safe stop.
            stopped: true,
            config,
        };
        let connect = Duration::from_millis(bridge.config.connect_timeout_ms);
        bridge.ctx = Some(
            bridge
                .open(connect)
                .map_err(|e| PlantError::Server(e.to_string()))?,
        );
        bridge.stopped = false;
        Ok(bridge)
    }

    /// Requests each period takes: reads of the outputs, and per write the write requests
    /// and the reads of the applied values.
    pub fn requests_per_period(&self) -> usize {
        let writes: Vec<(Point, Vec<u16>)> = self
            .config
            .channels
            .iter()
            .map(|c| (c.input, c.input.encode(c.safe).0))
            .collect();
        self.output_reads.len() + plan_writes(&writes).len() + self.applied_reads.len()
    }

    /// A connection, waiting at most `connect` for it.
    fn open(&self, connect: Duration) -> Result<sync::Context, std::io::Error> {
        let addr = resolve(&self.config.address)?;
        let mut ctx =
            sync::tcp::connect_slave_with_timeout(addr, Slave(self.config.unit), Some(connect))?;
        ctx.set_timeout(self.timeout);
        Ok(ctx)
    }

    fn now(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// Run `op` on the connection, connecting first if there is none; a link failure drops
    /// the connection (an answer may still be in flight) and is tried again while the
    /// outage is within `reconnect_ms`.
    fn with_link<T>(
        &mut self,
        what: &str,
        mut op: impl FnMut(&mut sync::Context) -> Result<T, Failure>,
    ) -> Result<T, PlantError> {
        // Stopping: one try on the connection as it stands, or on a new one if it was lost.
        let budget = if self.stopped {
            0.0
        } else {
            self.config.reconnect_ms as f64 / 1000.0
        };
        loop {
            // A connection is waited for no longer than the outage may still last.
            let full = Duration::from_millis(self.config.connect_timeout_ms);
            let left = Duration::from_secs_f64(self.outage.left(self.now(), budget));
            let connect = if left.is_zero() {
                full
            } else {
                full.min(left.max(Duration::from_millis(50)))
            };
            let attempt = match self.ctx.as_mut() {
                Some(ctx) => op(ctx),
                None => match self.open(connect) {
                    Ok(ctx) => {
                        tracing::info!(server = %self.config.address, "Modbus: connected again");
                        op(self.ctx.insert(ctx))
                    }
                    Err(e) => Err(Failure::Link(format!("connecting: {e}"))),
                },
            };
            match attempt {
                Ok(v) => {
                    self.outage.cleared();
                    return Ok(v);
                }
                Err(Failure::Answer(e)) => {
                    return Err(PlantError::Server(format!(
                        "{} {what}: {e}",
                        self.config.address
                    )))
                }
                Err(Failure::Link(e)) => {
                    self.ctx = None;
                    let now = self.now();
                    if !self.outage.failed(now, budget) {
                        return Err(PlantError::Server(format!(
                            "{} {what}: {e} (reconnect_ms = {})",
                            self.config.address, self.config.reconnect_ms
                        )));
                    }
                    tracing::warn!(server = %self.config.address, "Modbus {what}: {e}; trying again");
                    // A refused connection fails at once: do not spin.
                    let pause = self.outage.left(now, budget).min(0.05);
                    std::thread::sleep(Duration::from_secs_f64(pause));
                }
            }
        }
    }

    /// Read `blocks` and decode `points` from them.
    fn read_points(
        &mut self,
        what: &str,
        blocks: &[Block],
        points: &[Point],
    ) -> Result<Vec<f64>, PlantError> {
        let mut values = vec![f64::NAN; points.len()];
        for b in blocks {
            let words = self.with_link(what, |ctx| read_block(ctx, b))?;
            for &(i, at) in &b.values {
                let p = &points[i];
                let slice = words.get(usize::from(at)..usize::from(at + p.width()));
                values[i] = slice.and_then(|w| p.decode(w)).ok_or_else(|| {
                    PlantError::Server(format!(
                        "{} {what}: {:?} {} holds no finite number ({:?})",
                        self.config.address,
                        p.kind,
                        p.address,
                        slice.unwrap_or_default()
                    ))
                })?;
            }
        }
        Ok(values)
    }

    fn write_inputs(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        let (writes, given): (Vec<(Point, Vec<u16>)>, Vec<f64>) = self
            .config
            .channels
            .iter()
            .zip(v)
            .map(|(c, &x)| {
                let (words, given) = c.input.encode(x);
                ((c.input, words), given)
            })
            .unzip();
        // Every block is tried even if one fails (a safe stop must reach every channel the
        // server still takes); the first failure is the one reported.
        let mut first = None;
        for b in plan_writes(&writes) {
            if let Err(e) =
                self.with_link("write", |ctx| write_block(ctx, b.kind, b.start, &b.words))
            {
                if !self.stopped {
                    return Err(e);
                }
                first.get_or_insert(e);
            }
        }
        first.map_or(Ok(given), Err)
    }
}

impl Plant for ModbusBridge {
    fn channels(&self) -> usize {
        self.config.channels.len()
    }

    fn read(&mut self) -> Result<Vec<f64>, PlantError> {
        let (blocks, points) = (self.output_reads.clone(), self.outputs.clone());
        self.read_points("read of the outputs", &blocks, &points)
    }

    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        if v.len() != self.channels() || v.iter().any(|x| !x.is_finite()) {
            return Err(PlantError::Server(format!("refusing to write {v:?}")));
        }
        let mut given = self.write_inputs(v)?;
        if !self.applied.is_empty() {
            let (blocks, points) = (self.applied_reads.clone(), self.applied.clone());
            let mut read = self
                .read_points("read of the applied values", &blocks, &points)?
                .into_iter();
            for (c, g) in self.config.channels.iter().zip(given.iter_mut()) {
                if c.applied.is_some() {
                    *g = read.next().unwrap_or(*g);
                }
            }
        }
        Ok(given)
    }

    fn advance(&mut self, _dt: f64) -> Result<(), PlantError> {
        // A real plant: time passes on its own.
        Ok(())
    }

    fn stop(&mut self) -> Result<(), PlantError> {
        self.stopped = true;
        let safe: Vec<f64> = self.config.channels.iter().map(|c| c.safe).collect();
        // However the outage stood, the safe values get one try of their own (on a new
        // connection if the last was lost): not a second reconnection budget.
        self.outage.cleared();
        let r = self.write_inputs(&safe).map(|_| ());
        self.ctx = None;
        r
    }
}

impl Drop for ModbusBridge {
    fn drop(&mut self) {
        if !self.stopped {
            if let Err(e) = crate::off_async(|| self.stop()) {
                tracing::error!(server = %self.config.address, "Modbus safe stop on drop failed: {e}");
            }
        }
    }
}

fn resolve(address: &str) -> Result<SocketAddr, std::io::Error> {
    address.to_socket_addrs()?.next().ok_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!("{address}: no address"),
        )
    })
}

fn read_block(ctx: &mut sync::Context, b: &Block) -> Result<Vec<u16>, Failure> {
    let request = match b.kind {
        RegisterKind::Coil => Request::ReadCoils(b.start, b.count),
        RegisterKind::DiscreteInput => Request::ReadDiscreteInputs(b.start, b.count),
        RegisterKind::Input => Request::ReadInputRegisters(b.start, b.count),
        RegisterKind::Holding => Request::ReadHoldingRegisters(b.start, b.count),
    };
    let words: Vec<u16> = match call(ctx, request)? {
        Response::ReadCoils(bits) | Response::ReadDiscreteInputs(bits) => {
            bits.into_iter().map(u16::from).collect()
        }
        Response::ReadInputRegisters(w) | Response::ReadHoldingRegisters(w) => w,
        other => return Err(Failure::Answer(format!("answered {other:?}"))),
    };
    if words.len() < usize::from(b.count) {
        return Err(Failure::Answer(format!(
            "answered {} of the {} {:?} values asked from {}",
            words.len(),
            b.count,
            b.kind,
            b.start
        )));
    }
    Ok(words)
}

fn write_block(
    ctx: &mut sync::Context,
    kind: RegisterKind,
    start: u16,
    words: &[u16],
) -> Result<(), Failure> {
    let request = match (kind, words) {
        (RegisterKind::Coil, [w]) => Request::WriteSingleCoil(start, *w != 0),
        (RegisterKind::Coil, _) => {
            Request::WriteMultipleCoils(start, words.iter().map(|&w| w != 0).collect())
        }
        (_, [w]) => Request::WriteSingleRegister(start, *w),
        _ => Request::WriteMultipleRegisters(start, words.to_vec().into()),
    };
    call(ctx, request).map(|_| ())
}

fn call(ctx: &mut sync::Context, request: Request<'static>) -> Result<Response, Failure> {
    match ctx.call(request) {
        Ok(Ok(r)) => Ok(r),
        Ok(Err(exception)) => Err(Failure::Answer(format!("exception {exception}"))),
        Err(tokio_modbus::Error::Transport(e)) => Err(Failure::Link(e.to_string())),
        // A frame that does not answer the request: the stream can no longer be trusted.
        Err(tokio_modbus::Error::Protocol(e)) => Err(Failure::Link(e.to_string())),
    }
}
