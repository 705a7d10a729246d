//! The OPC UA bridge: a plant behind an OPC UA server as a [`Plant`], through the node ids
//! of its plant file ([`plant::opcua`]).
//!
//! Per period: one Read of every output, one Write of every input (each in the type the
//! server declared for it, learned from its value at connection), one Read of the applied
//! values if the map has them. The client (`async-opcua`) runs its session's event loop
//! (keep-alives, reconnection) on a runtime of the bridge's own with one worker; the agent's
//! plant thread blocks on each request with the map's timeout. A failing request is tried
//! again while the outage lasts less than `reconnect_ms` (the event loop reconnects behind
//! it); a node's bad status, a value that is not a number or a type the bridge cannot write
//! ends the run. Every way out writes the safe values, as for Modbus.

use std::sync::Arc;
use std::time::{Duration, Instant};

use opcua::client::{ClientBuilder, IdentityToken, Session, SessionPollResult};
use opcua::crypto::SecurityPolicy;
use opcua::types::{
    DataValue, MessageSecurityMode, NodeId, ReadValueId, TimestampsToReturn, UserTokenPolicy,
    Variant, VariantScalarTypeId, WriteValue,
};
use plant::scenario::OpcUaPlant;
use plant::{Plant, PlantError};

use crate::reconnect::LinkOutage;

/// A plant behind an OPC UA server.
pub struct OpcUaBridge {
    endpoint: String,
    timeout: Duration,
    reconnect_ms: u64,
    rt: Option<tokio::runtime::Runtime>,
    session: Arc<Session>,
    outputs: Vec<ReadValueId>,
    /// Each input's node and the type the server holds it in.
    inputs: Vec<(NodeId, VariantScalarTypeId)>,
    /// The channels that have an applied node, and their reads.
    applied: Vec<(usize, ReadValueId)>,
    safe: Vec<f64>,
    outage: LinkOutage,
    epoch: Instant,
    stopped: bool,
}

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
        let connect_timeout = Duration::from_millis(c.connect_timeout_ms);
        let user = c.user.clone().zip(plant.password.clone());
        let (rt, session) = open_session(&c.endpoint, user, plant.timeout, connect_timeout)
            .map_err(|e| PlantError::Server(format!("{} {e}", c.endpoint)))?;
        let mut bridge = Self {
            endpoint: c.endpoint.clone(),
            timeout: plant.timeout,
            reconnect_ms: c.reconnect_ms,
            rt: Some(rt),
            session,
            outputs: c
                .channels
                .iter()
                .map(|ch| node(&ch.output).map(ReadValueId::new_value))
                .collect::<Result<_, _>>()?,
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
        bridge.stopped = false;
        Ok(bridge)
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
        reads
            .iter()
            .zip(&values)
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

/// A session with `endpoint` (security None; anonymous, or `user` with its password) on a
/// runtime of its own with one worker, where the session's event loop runs (keep-alives,
/// reconnection for ever, every `request_timeout` enforced). Errors say what failed.
pub(crate) fn open_session(
    endpoint: &str,
    user: Option<(String, String)>,
    request_timeout: Duration,
    connect_timeout: Duration,
) -> Result<(tokio::runtime::Runtime, Arc<Session>), String> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("opcua-session")
        .enable_all()
        .build()
        .map_err(|e| format!("runtime: {e}"))?;
    let identity = match user {
        Some((u, p)) => {
            tracing::warn!(
                server = endpoint,
                "OPC UA: user {u}'s password goes in plain text (security None): a trusted network only"
            );
            IdentityToken::new_user_name(u, p)
        }
        None => IdentityToken::Anonymous,
    };
    let session = rt.block_on(async {
        let mut client = ClientBuilder::new()
            .application_name("mfc plant-agent")
            .application_uri("urn:mfc:plant-agent")
            .product_uri("urn:mfc:plant-agent")
            .pki_dir(std::env::temp_dir().join("mfc-opcua-pki"))
            .create_sample_keypair(false)
            .trust_server_certs(true)
            .session_retry_limit(-1)
            .session_retry_initial(Duration::from_millis(200))
            .session_retry_max(Duration::from_secs(2))
            .request_timeout(request_timeout)
            .keep_alive_interval(Duration::from_secs(1))
            .client()
            .map_err(|e| format!("client: {}", e.join("; ")))?;
        let target = (
            endpoint,
            SecurityPolicy::None.to_str(),
            MessageSecurityMode::None,
            UserTokenPolicy::anonymous(),
        );
        let (session, event_loop) = tokio::time::timeout(
            connect_timeout,
            client.connect_to_matching_endpoint(target, identity),
        )
        .await
        .map_err(|_| "connecting: timed out".to_string())?
        .map_err(|e| format!("connecting: {e}"))?;
        // The event loop, watched: the reason a session cannot open (a refused user, a
        // server that is not there) is only in its events, and an operator needs it.
        let last = Arc::new(std::sync::Mutex::new(None::<String>));
        let seen = last.clone();
        let events = event_loop.enter();
        tokio::spawn(async move {
            use futures::StreamExt;
            futures::pin_mut!(events);
            while let Some(event) = events.next().await {
                let failure = match event {
                    Ok(
                        SessionPollResult::ConnectionLost(c)
                        | SessionPollResult::ReconnectFailed(c),
                    ) => c,
                    Err(c) => c,
                    Ok(_) => continue,
                };
                if let Ok(mut l) = seen.lock() {
                    *l = Some(failure.to_string());
                }
            }
        });
        if tokio::time::timeout(connect_timeout, session.wait_for_connection())
            .await
            .is_err()
        {
            let why = last.lock().ok().and_then(|l| l.clone());
            return Err(format!(
                "opening the session: not open after {connect_timeout:?}{}",
                why.map(|w| format!(" (last failure: {w})"))
                    .unwrap_or_default()
            ));
        }
        Ok::<_, String>(session)
    });
    match session {
        Ok(s) => Ok((rt, s)),
        Err(e) => {
            // No runtime may be dropped on an async worker.
            crate::off_async(move || drop(rt));
            Err(e)
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
