//! The OPC UA bridge: a plant behind an OPC UA server as a [`Plant`], through the node ids
//! of its plant file ([`plant::opcua`]).
//!
//! Per period: one Read of every output (or, with `sampling = "subscribe"`, the last
//! values the server's subscription published, no request, and a Read once a second to
//! confirm the nodes are still there), one Write of every input
//! (each in the type the server declared for it, learned from its value at connection),
//! one Read of the applied values if the map has them. The client (`async-opcua`) runs its session's event loop
//! (keep-alives, reconnection) on a runtime of the bridge's own with one worker; the agent's
//! plant thread blocks on each request with the map's timeout. A failing request is tried
//! again while the outage lasts less than `reconnect_ms` (the event loop reconnects behind
//! it); a node's bad status, a value that is not a number or a type the bridge cannot write
//! ends the run. Every way out writes the safe values, as for Modbus.

mod nodelay;
mod session;
mod subscription;

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use opcua::client::Session;
use opcua::types::{
    DataValue, NodeId, ReadValueId, TimestampsToReturn, Variant, VariantScalarTypeId, WriteValue,
};
use plant::opcua::Sampling;
use plant::scenario::OpcUaPlant;
use plant::{Plant, PlantError};

use crate::reconnect::LinkOutage;
pub(crate) use session::open_session;
pub use session::{OpcUaUser, SessionSpec, OWN_CERT, OWN_KEY};
use subscription::{Ask, Subscribed};

/// A plant behind an OPC UA server.
pub struct OpcUaBridge {
    endpoint: String,
    timeout: Duration,
    connect_timeout: Duration,
    reconnect_ms: u64,
    rt: Option<tokio::runtime::Runtime>,
    session: Arc<Session>,
    outputs: Vec<ReadValueId>,
    /// With a subscription: what it asks of the server, and the subscription made.
    subscribed: Option<(Ask, Subscribed)>,
    /// When a Read last confirmed the subscribed outputs.
    confirmed: Instant,
    /// How many times the session reconnected (counted by its event loop's watcher).
    reconnections: Arc<AtomicU64>,
    /// Each input's node and the type the server holds it in.
    inputs: Vec<(NodeId, VariantScalarTypeId)>,
    /// The channels that have an applied node, and their reads.
    applied: Vec<(usize, ReadValueId)>,
    safe: Vec<f64>,
    outage: LinkOutage,
    epoch: Instant,
    stopped: bool,
}

/// How often a Read confirms the outputs a subscription publishes.
const CONFIRM_EVERY: Duration = Duration::from_secs(1);

/// Why one attempt failed: the server said no (not worth another try), or the link did.
enum Failure {
    Answer(String),
    Link(String),
}

fn node(id: &str) -> Result<NodeId, PlantError> {
    id.parse::<NodeId>()
        .map_err(|_| PlantError::Server(format!("{id:?} is not a node id")))
}

impl OpcUaBridge {
    /// Connect to the server of `plant`, and learn the type of each input.
    pub fn connect(plant: &OpcUaPlant) -> Result<Self, PlantError> {
        let c = &plant.config;
        let (rt, session, reconnections) = open_session(&SessionSpec::of(plant))
            .map_err(|e| PlantError::Server(format!("{} {e}", c.endpoint)))?;
        let mut bridge = Self {
            endpoint: c.endpoint.clone(),
            timeout: plant.timeout,
            connect_timeout: Duration::from_millis(c.connect_timeout_ms),
            reconnect_ms: c.reconnect_ms,
            rt: Some(rt),
            session,
            outputs: c
                .channels
                .iter()
                .map(|ch| node(&ch.output).map(ReadValueId::new_value))
                .collect::<Result<_, _>>()?,
            subscribed: None,
            confirmed: Instant::now(),
            reconnections,
            inputs: Vec::new(),
            applied: Vec::new(),
            safe: c.channels.iter().map(|ch| ch.safe).collect(),
            outage: LinkOutage::default(),
            epoch: Instant::now(),
            // Until the inputs are known, a stop has nothing to write, and no failure of
            // the start is tried again.
            stopped: true,
        };
        for (i, ch) in c.channels.iter().enumerate() {
            if let Some(a) = &ch.applied {
                bridge.applied.push((i, ReadValueId::new_value(node(a)?)));
            }
        }
        bridge.inputs = bridge.input_types(c.channels.iter().map(|ch| ch.input.as_str()))?;
        if c.sampling == Sampling::Subscribe {
            let ask = Ask {
                interval: plant.sampling_interval,
                period: plant.period,
                outage: Duration::from_millis(c.reconnect_ms),
            };
            let made = bridge.subscribe(&ask).map_err(|e| bridge.error(&e))?;
            bridge.subscribed = Some((ask, made));
        }
        bridge.stopped = false;
        Ok(bridge)
    }

    /// Subscribe to the outputs as `ask` says, and wait (the connection's timeout at
    /// most) for a first good value of each.
    fn subscribe(&self, ask: &Ask) -> Result<Subscribed, String> {
        let rt = self.rt.as_ref().ok_or("the bridge is stopped")?;
        let made_at = self.reconnections.load(Ordering::SeqCst);
        let made = rt.block_on(subscription::subscribe(
            &self.session,
            &self.outputs,
            ask,
            made_at,
        ))?;
        let deadline = Instant::now() + self.connect_timeout;
        loop {
            let complete = made.latest.lock().is_ok_and(|l| {
                l.values
                    .iter()
                    .all(|v| v.as_ref().is_some_and(|d| d.status().is_good()))
            });
            if complete {
                return Ok(made);
            }
            if Instant::now() > deadline {
                let _ = rt.block_on(self.session.delete_subscription(made.id));
                return Err(
                    "the subscription published no good first value of every output".into(),
                );
            }
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    /// Subscribe again after a reconnection or the server's end of the subscription (the
    /// old one deleted if the server still has it), tried again while the outage lasts
    /// less than `reconnect_ms`.
    fn resubscribe(&mut self) -> Result<(), PlantError> {
        let Some((ask, old)) = self.subscribed.take() else {
            return Ok(());
        };
        if let Some(rt) = &self.rt {
            let _ = rt.block_on(async {
                tokio::time::timeout(self.timeout, self.session.delete_subscription(old.id)).await
            });
        }
        let budget = self.reconnect_ms as f64 / 1000.0;
        loop {
            match self.subscribe(&ask) {
                Ok(made) => {
                    self.outage.cleared();
                    tracing::info!(server = %self.endpoint, "OPC UA: subscribed again");
                    self.subscribed = Some((ask, made));
                    return Ok(());
                }
                Err(e) => {
                    let now = self.now();
                    if !self.outage.failed(now, budget) {
                        self.subscribed = Some((ask, old));
                        return Err(self.error(&format!(
                            "subscribing again: {e} (reconnect_ms = {})",
                            self.reconnect_ms
                        )));
                    }
                    tracing::warn!(server = %self.endpoint, "OPC UA subscribing again: {e}; trying again");
                    let pause = self.outage.left(now, budget).min(0.05);
                    std::thread::sleep(Duration::from_secs_f64(pause));
                }
            }
        }
    }

    fn error(&self, what: &str) -> PlantError {
        PlantError::Server(format!("{}: {what}", self.endpoint))
    }

    /// Each input's node and the scalar type of the value the server holds in it: what a
    /// write must carry (a server refuses another type).
    fn input_types<'a>(
        &mut self,
        ids: impl Iterator<Item = &'a str>,
    ) -> Result<Vec<(NodeId, VariantScalarTypeId)>, PlantError> {
        let nodes: Vec<NodeId> = ids.map(node).collect::<Result<_, _>>()?;
        let reads: Vec<ReadValueId> = nodes.iter().cloned().map(ReadValueId::new_value).collect();
        let values = self.with_link("read of the inputs' types", |s, rt, t| {
            read(s, rt, t, &reads)
        })?;
        nodes
            .into_iter()
            .zip(values)
            .map(|(n, dv)| {
                let t = dv
                    .value
                    .as_ref()
                    .filter(|v| !matches!(v, Variant::Array(_)))
                    .and_then(Variant::scalar_type_id)
                    .filter(|t| variant_of(0.0, *t).is_some());
                t.map(|t| (n.clone(), t)).ok_or_else(|| {
                    PlantError::Server(format!(
                        "{}: input {n} holds {:?} (status {}), not a number the bridge can write",
                        self.endpoint,
                        dv.value,
                        dv.status()
                    ))
                })
            })
            .collect()
    }

    fn now(&self) -> f64 {
        self.epoch.elapsed().as_secs_f64()
    }

    /// Run `op` on the session; a link failure is tried again while the outage lasts less
    /// than `reconnect_ms` (the session's event loop reconnects meanwhile).
    fn with_link<T>(
        &mut self,
        what: &str,
        mut op: impl FnMut(&Arc<Session>, &tokio::runtime::Runtime, Duration) -> Result<T, Failure>,
    ) -> Result<T, PlantError> {
        // Stopping (or starting): one try, not a reconnection budget.
        let budget = if self.stopped {
            0.0
        } else {
            self.reconnect_ms as f64 / 1000.0
        };
        loop {
            let rt = self.rt.as_ref().ok_or_else(|| {
                PlantError::Server(format!("{}: the bridge is stopped", self.endpoint))
            })?;
            match op(&self.session, rt, self.timeout) {
                Ok(v) => {
                    self.outage.cleared();
                    return Ok(v);
                }
                Err(Failure::Answer(e)) => {
                    return Err(PlantError::Server(format!("{} {what}: {e}", self.endpoint)))
                }
                Err(Failure::Link(e)) => {
                    let now = self.now();
                    if !self.outage.failed(now, budget) {
                        return Err(PlantError::Server(format!(
                            "{} {what}: {e} (reconnect_ms = {})",
                            self.endpoint, self.reconnect_ms
                        )));
                    }
                    tracing::warn!(server = %self.endpoint, "OPC UA {what}: {e}; trying again");
                    let pause = self.outage.left(now, budget).min(0.05);
                    std::thread::sleep(Duration::from_secs_f64(pause));
                }
            }
        }
    }

    fn read_values(&mut self, what: &str, reads: &[ReadValueId]) -> Result<Vec<f64>, PlantError> {
        let values = self.with_link(what, |s, rt, t| read(s, rt, t, reads))?;
        self.numbers(what, reads, &values)
    }

    /// The outputs as the subscription last published them (`None` once it is gone: the
    /// session reconnected, or the server ended it); a silent subscription is a link
    /// failure (tried again while the outage lasts less than `reconnect_ms`).
    fn published(&mut self, made: &Subscribed) -> Result<Option<Vec<f64>>, PlantError> {
        let what = "subscription to the outputs";
        let reconnections = self.reconnections.clone();
        let values = self.with_link(what, |_, _, _| {
            if made.gone(reconnections.load(Ordering::SeqCst)) {
                return Ok(None);
            }
            let l = made
                .latest
                .lock()
                .map_err(|_| Failure::Answer("poisoned".into()))?;
            let stale = made.stale;
            match l.heard.map(|h| h.elapsed()) {
                Some(age) if age <= stale => {}
                age => {
                    return Err(Failure::Link(format!(
                        "nothing published for {:?} (a keep-alive is due every {:?})",
                        age.unwrap_or_default(),
                        stale / 3
                    )))
                }
            }
            Ok(Some(
                l.values
                    .iter()
                    .map(|v| v.clone().unwrap_or_default())
                    .collect::<Vec<_>>(),
            ))
        })?;
        let Some(values) = values else {
            return Ok(None);
        };
        let reads = self.outputs.clone();
        self.numbers(what, &reads, &values).map(Some)
    }

    /// Each value a finite number, or an error naming its node.
    fn numbers(
        &self,
        what: &str,
        reads: &[ReadValueId],
        values: &[DataValue],
    ) -> Result<Vec<f64>, PlantError> {
        reads
            .iter()
            .zip(values)
            .map(|(r, dv)| {
                number(dv).ok_or_else(|| {
                    PlantError::Server(format!(
                        "{} {what}: {} holds no finite number ({:?}, status {})",
                        self.endpoint,
                        r.node_id,
                        dv.value,
                        dv.status()
                    ))
                })
            })
            .collect()
    }

    fn write_inputs(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        let mut writes = Vec::with_capacity(v.len());
        let mut given = Vec::with_capacity(v.len());
        for (&(ref n, t), &x) in self.inputs.iter().zip(v) {
            let value = variant_of(x, t).unwrap_or(Variant::Empty);
            given.push(match &value {
                Variant::Boolean(b) => f64::from(u8::from(*b)),
                v => v.as_f64().unwrap_or(x),
            });
            writes.push(WriteValue::value_attr(n.clone(), value));
        }
        if !writes.is_empty() {
            self.with_link("write", |s, rt, t| write(s, rt, t, &writes))?;
        }
        Ok(given)
    }
}

impl Plant for OpcUaBridge {
    fn channels(&self) -> usize {
        self.outputs.len()
    }

    fn read(&mut self) -> Result<Vec<f64>, PlantError> {
        while let Some(made) = self.subscribed.as_ref().map(|(_, m)| m.clone()) {
            let Some(values) = self.published(&made)? else {
                self.resubscribe()?;
                continue;
            };
            // A server may drop a node without a word to its subscribers (asyncua keeps
            // publishing keep-alives): a Read every second catches it.
            if self.confirmed.elapsed() >= CONFIRM_EVERY {
                let reads = self.outputs.clone();
                self.read_values("read confirming the subscription", &reads)?;
                self.confirmed = Instant::now();
            }
            return Ok(values);
        }
        let reads = self.outputs.clone();
        self.read_values("read of the outputs", &reads)
    }

    fn write(&mut self, v: &[f64]) -> Result<Vec<f64>, PlantError> {
        if v.len() != self.channels() || v.iter().any(|x| !x.is_finite()) {
            return Err(PlantError::Server(format!("refusing to write {v:?}")));
        }
        let mut given = self.write_inputs(v)?;
        if !self.applied.is_empty() {
            let reads: Vec<ReadValueId> = self.applied.iter().map(|(_, r)| r.clone()).collect();
            let values = self.read_values("read of the applied values", &reads)?;
            for ((i, _), a) in self.applied.iter().zip(values) {
                given[*i] = a;
            }
        }
        Ok(given)
    }

    fn advance(&mut self, _dt: f64) -> Result<(), PlantError> {
        Ok(())
    }

    fn stop(&mut self) -> Result<(), PlantError> {
        if self.rt.is_none() {
            return Ok(());
        }
        self.stopped = true;
        self.outage.cleared();
        let safe = self.safe.clone();
        let r = self.write_inputs(&safe).map(|_| ());
        if let Some(rt) = self.rt.take() {
            let session = self.session.clone();
            let _ = rt.block_on(async {
                tokio::time::timeout(Duration::from_secs(1), session.disconnect()).await
            });
            drop(rt);
        }
        r
    }
}

impl Drop for OpcUaBridge {
    fn drop(&mut self) {
        let stopped = crate::off_async(|| {
            let r = self.stop();
            // The runtime goes here too: never on an async worker.
            drop(self.rt.take());
            r
        });
        if let Err(e) = stopped {
            tracing::error!(server = %self.endpoint, "OPC UA safe stop on drop failed: {e}");
        }
    }
}

fn read(
    session: &Arc<Session>,
    rt: &tokio::runtime::Runtime,
    t: Duration,
    reads: &[ReadValueId],
) -> Result<Vec<DataValue>, Failure> {
    let values = rt.block_on(async {
        tokio::time::timeout(t, session.read(reads, TimestampsToReturn::Neither, 0.0)).await
    });
    let values = values
        .map_err(|_| Failure::Link("timed out".into()))?
        .map_err(|e| Failure::Link(e.to_string()))?;
    if values.len() != reads.len() {
        return Err(Failure::Answer(format!(
            "answered {} values for {} nodes",
            values.len(),
            reads.len()
        )));
    }
    Ok(values)
}

fn write(
    session: &Arc<Session>,
    rt: &tokio::runtime::Runtime,
    t: Duration,
    writes: &[WriteValue],
) -> Result<(), Failure> {
    let codes = rt
        .block_on(async { tokio::time::timeout(t, session.write(writes)).await })
        .map_err(|_| Failure::Link("timed out".into()))?
        .map_err(|e| Failure::Link(e.to_string()))?;
    if codes.len() != writes.len() {
        return Err(Failure::Answer(format!(
            "answered {} codes for {} writes",
            codes.len(),
            writes.len()
        )));
    }
    match writes.iter().zip(&codes).find(|(_, c)| !c.is_good()) {
        Some((w, c)) => Err(Failure::Answer(format!("write of {}: {c}", w.node_id))),
        None => Ok(()),
    }
}

/// A finite number in a good value: booleans as 0 or 1.
pub(crate) fn number(dv: &DataValue) -> Option<f64> {
    if !dv.status().is_good() {
        return None;
    }
    match dv.value.as_ref()? {
        Variant::Boolean(b) => Some(f64::from(u8::from(*b))),
        v => v.as_f64().filter(|x| x.is_finite()),
    }
}

/// `x` in the scalar type `t` of a node, rounded and clamped to its range; `None` for a
/// type that is not a number.
fn variant_of(x: f64, t: VariantScalarTypeId) -> Option<Variant> {
    use VariantScalarTypeId as T;
    let r = x.round();
    Some(match t {
        T::Double => Variant::Double(x),
        // Beyond f32's range a cast gives infinity: the largest finite value instead.
        T::Float => Variant::Float(x.clamp(-f64::from(f32::MAX), f64::from(f32::MAX)) as f32),
        T::SByte => Variant::SByte(r.clamp(-128.0, 127.0) as i8),
        T::Byte => Variant::Byte(r.clamp(0.0, 255.0) as u8),
        T::Int16 => Variant::Int16(r.clamp(i16::MIN.into(), i16::MAX.into()) as i16),
        T::UInt16 => Variant::UInt16(r.clamp(0.0, u16::MAX.into()) as u16),
        T::Int32 => Variant::Int32(r.clamp(i32::MIN.into(), i32::MAX.into()) as i32),
        T::UInt32 => Variant::UInt32(r.clamp(0.0, u32::MAX.into()) as u32),
        T::Int64 => Variant::Int64(r as i64),
        T::UInt64 => Variant::UInt64(r.max(0.0) as u64),
        T::Boolean => Variant::Boolean(x >= 0.5),
        _ => return None,
    })
}
