//! A gateway: one agent process hosting many plants (a cell of machines, a building).
//!
//! Each plant runs exactly the loop and the safety of a single-rig agent
//! ([`crate::agent::run_hosted`]): its own supervisor, hold, fallback and safe stop. What
//! the gateway changes is the network: the samples of all its plants leave in one
//! [`pb::SampleBatch`] per period, on `mfc/v1/shard/{s}/gateway/{gateway}/samples`, and
//! their commands come back in one [`pb::CommandBatch`] on
//! `mfc/v1/gateway/{gateway}/commands`, which the gateway splits among its plants. Zenoh
//! costs tens of microseconds per message and a controller about one per sample, so a
//! gateway of a thousand plants costs the network two messages a period instead of two
//! thousand.
//!
//! The batcher sends a period's batch as soon as every plant has given its sample, or
//! [`FLUSH_AFTER`] after the first, whichever comes first: a plant whose driver is slow
//! delays its neighbours by at most that, and its sample follows in a part of its own as
//! soon as it comes (the service keeps a gateway's parts side by side, up to one period's
//! worth of samples: `SampleBatch.plants` says how many plants that is).
//!
//! ```toml
//! gateway = "cell-1"      # gateway id (key chunk); required
//! out = "out/cell-1"      # records go to {out}/{device}/
//! [[plants]]              # one entry per plant: the fields of a single agent's file
//! device = "heater-1"
//! scenario = "plants/heater/scenarios/step.toml"
//! [[plants]]
//! device = "heater-2"
//! scenario = "plants/heater/scenarios/step.toml"
//! ```

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use protocol::auth::{Key, Kind};
use protocol::{decode, encode, encode_sample_batch, keys, pb, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use zenoh::Session;

use crate::agent::{self, AgentError, AgentRun, AuthReport};
use crate::config::{AgentConfigError, AgentFile, Resolved};
use plant::Plant;

/// Longest a period's batch waits for a late plant after its first sample.
pub const FLUSH_AFTER: Duration = Duration::from_millis(2);

/// Most plants one gateway hosts: one batch must stay under the protocol's bounds.
pub const MAX_PLANTS: usize = protocol::MAX_BATCH_SAMPLES;

/// The gateway's file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatewayFile {
    /// Gateway id (key chunk; the same rules as a device id). Required.
    pub gateway: String,
    /// Where the records go: one directory per plant under it. Default `out/{gateway}`.
    #[serde(default)]
    pub out: Option<PathBuf>,
    /// A Prometheus endpoint for all its plants (absent: none).
    #[serde(default)]
    pub metrics: Option<telemetry::MetricsSpec>,
    /// Record all its plants into one MCAP file (absent: no recording).
    #[serde(default)]
    pub record: Option<telemetry::RecordSpec>,
    /// The gateway's key file (the hex of `protocol::auth::Secret::gateway(id)`), relative
    /// to this file: one MAC per batch each way. Absent: the gateway runs open. Its plants
    /// have no `key_file` of their own. `mfc-deploy` writes it (`ID.auth` in the gateway's
    /// bundle, with its certificate and access-control rules) for every gateway of the
    /// inventory's `[[gateways]]`.
    #[serde(default)]
    pub key_file: Option<PathBuf>,
    /// The plants, each as a single agent's file would describe it (`device` required;
    /// its `out` is ignored). At least one, at most [`MAX_PLANTS`], unique ids, one period.
    pub plants: Vec<AgentFile>,
}

/// A checked gateway file.
#[derive(Debug)]
pub struct ResolvedGateway {
    pub gateway: String,
    pub out: PathBuf,
    pub metrics: Option<telemetry::MetricsSpec>,
    pub record: Option<telemetry::RecordSpec>,
    /// The gateway's key (`None`: open).
    pub key: Option<Key>,
    pub plants: Vec<Resolved>,
}

impl GatewayFile {
    /// Read and check a gateway file; scenario paths are relative to it.
    pub fn load(path: &Path) -> Result<ResolvedGateway, AgentConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| AgentConfigError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        let file: GatewayFile = toml::from_str(&text).map_err(|e| AgentConfigError::Parse {
            file: path.to_path_buf(),
            message: e.to_string().trim_end().into(),
        })?;
        file.resolve(path)
    }

    /// Check the file and resolve every plant.
    pub fn resolve(&self, path: &Path) -> Result<ResolvedGateway, AgentConfigError> {
        let invalid = |field: &'static str, reason: String| AgentConfigError::Invalid {
            file: path.to_path_buf(),
            field,
            reason,
        };
        keys::check_id(&self.gateway).map_err(|e| invalid("gateway", e.to_string()))?;
        if self.plants.is_empty() || self.plants.len() > MAX_PLANTS {
            return Err(invalid(
                "plants",
                format!(
                    "between 1 and {MAX_PLANTS} plants, not {}",
                    self.plants.len()
                ),
            ));
        }
        let mut plants = Vec::with_capacity(self.plants.len());
        let mut seen = std::collections::HashSet::new();
        for p in &self.plants {
            if p.key_file.is_some() {
                return Err(invalid(
                    "plants.key_file",
                    "a gateway's plants share the gateway's key_file (one MAC per batch)".into(),
                ));
            }
            let r = p.resolve(path)?;
            if !seen.insert(r.loop_config.device_id.clone()) {
                return Err(invalid(
                    "plants",
                    format!("device {:?} appears twice", r.loop_config.device_id),
                ));
            }
            plants.push(r);
        }
        let h = plants[0].loop_config.safety.period;
        if let Some(p) = plants.iter().find(|p| p.loop_config.safety.period != h) {
            return Err(invalid(
                "plants",
                format!(
                    "one period for every plant of a gateway: {} has {} s, {} has {h} s",
                    p.loop_config.device_id,
                    p.loop_config.safety.period,
                    plants[0].loop_config.device_id
                ),
            ));
        }
        Ok(ResolvedGateway {
            out: self
                .out
                .clone()
                .unwrap_or_else(|| PathBuf::from("out").join(&self.gateway)),
            gateway: self.gateway.clone(),
            metrics: self.metrics.clone(),
            record: self.record.clone(),
            key: crate::config::read_key(path, self.key_file.as_deref())?,
            plants,
        })
    }
}

/// Run every plant of a gateway until its scenario ends or `stop` resolves; each gets its
/// safe stop, and its run comes back (an error for a plant that could not start).
///
/// `key` is the gateway's own (`protocol::auth::Secret::gateway`): one MAC per batch each
/// way, not one per plant. A command batch that does not open with it is dropped whole
/// and counted in every hosted run's `auth.forged`. `None` runs open.
pub async fn run_gateway(
    session: &Session,
    gateway: &str,
    plants: Vec<(Box<dyn Plant>, agent::LoopConfig)>,
    key: Option<Key>,
    run_id: impl Fn() -> u64,
    stop: impl std::future::Future<Output = ()>,
) -> Result<Vec<Result<AgentRun, AgentError>>, AgentError> {
    keys::check_id(gateway).map_err(|e| AgentError::Config(e.to_string()))?;
    let n = plants.len();
    // Commands are routed and periods told apart by device id: one plant per id.
    let mut ids = std::collections::HashSet::new();
    if let Some((_, c)) = plants
        .iter()
        .find(|(_, c)| !ids.insert(c.device_id.as_str()))
    {
        return Err(AgentError::Config(format!(
            "device {:?} appears twice in gateway {gateway}",
            c.device_id
        )));
    }
    let forged = Arc::new(AtomicU64::new(0));
    if key.is_some() {
        tracing::info!(gateway, "auth: gateway key (batches sealed and checked)");
    } else {
        tracing::warn!(gateway, "auth: open (no key_file): batches unauthenticated");
    }
    // Commands: split the batch among the plants, each to its loop's queue.
    let mut routes: HashMap<String, mpsc::Sender<(Instant, Vec<u8>)>> = HashMap::new();
    let mut receivers = Vec::with_capacity(n);
    for (_, cfg) in &plants {
        let (tx, rx) = mpsc::channel(256);
        routes.insert(cfg.device_id.clone(), tx);
        receivers.push(rx);
    }
    let _commands = command_router(session, gateway, routes, key.clone(), forged.clone()).await?;
    let publisher =
        transport::control_publisher(session, keys::shard_gateway_samples(gateway)).await?;
    let (sample_tx, sample_rx) = mpsc::channel::<pb::Sample>(4 * n + 16);
    let devices: Vec<String> = plants.iter().map(|(_, c)| c.device_id.clone()).collect();
    let batcher = batcher(&publisher, gateway, key.as_ref(), &devices, sample_rx);

    let (stop_tx, stop_rx) = watch::channel(false);
    // Each plant's loop is a task of its own, so a thousand plants cost a thousand wakes a
    // period, not a thousand polls each.
    let handles: Vec<_> = plants
        .into_iter()
        .zip(receivers)
        .map(|((plant, mut cfg), rx)| {
            // Hundreds of loops: tokio's timer, not a blocking thread per wait
            // (`LoopConfig::precise_wake`); the batch waits for the slowest plant anyway.
            cfg.precise_wake = false;
            // The batch is sealed and opened here, with the gateway's key.
            cfg.auth = None;
            let (samples, mut stopped) = (sample_tx.clone(), stop_rx.clone());
            let (session, id) = (session.clone(), run_id());
            tokio::spawn(async move {
                let stop = async move {
                    let _ = stopped.wait_for(|s| *s).await;
                };
                agent::run_hosted(&session, plant, &cfg, id, stop, samples, rx).await
            })
        })
        .collect();
    drop(sample_tx);
    let all = async move {
        let mut runs = Vec::with_capacity(handles.len());
        for h in handles {
            runs.push(h.await.unwrap_or_else(|e| {
                Err(AgentError::Config(format!(
                    "a plant's loop ended abnormally: {e}"
                )))
            }));
        }
        runs
    };
    tokio::pin!(all, stop, batcher);
    let mut stop_sent = false;
    let authenticated = key.is_some();
    loop {
        tokio::select! {
            mut runs = &mut all => {
                let forged = forged.load(Ordering::Relaxed);
                if forged > 0 {
                    tracing::warn!(gateway, forged, "command batches refused for their MAC");
                }
                for r in runs.iter_mut().flatten() {
                    r.report.auth = AuthReport { authenticated, forged };
                }
                return Ok(runs);
            }
            () = &mut stop, if !stop_sent => {
                let _ = stop_tx.send(true);
                stop_sent = true;
            }
            () = &mut batcher => {}
        }
    }
}

/// The gateway's command subscriber: each batch that opens with `key` (counted in
/// `forged` when it does not) is split among the plants, each command to its loop's queue.
async fn command_router(
    session: &Session,
    gateway: &str,
    routes: HashMap<String, mpsc::Sender<(Instant, Vec<u8>)>>,
    key: Option<Key>,
    forged: Arc<AtomicU64>,
) -> Result<zenoh::pubsub::Subscriber<()>, AgentError> {
    let gw = gateway.to_string();
    session
        .declare_subscriber(keys::gateway_commands(gateway))
        .callback(move |s| {
            let now = Instant::now();
            let bytes = s.payload().to_bytes();
            let body = match &key {
                Some(k) => match k.open(Kind::CommandBatch, &bytes) {
                    Ok(body) => body,
                    Err(_) => {
                        forged.fetch_add(1, Ordering::Relaxed);
                        return;
                    }
                },
                None => &bytes[..],
            };
            let Ok(batch) = decode::<pb::CommandBatch>(body) else {
                return;
            };
            if batch.gateway_id != gw {
                return;
            }
            for c in batch.commands {
                if let Some(tx) = routes.get(&c.device_id) {
                    // A full queue drops the command: the supervisor counts it as lost.
                    let _ = tx.try_send((now, encode(&c)));
                }
            }
        })
        .await
        .map_err(|e| transport::TransportError::Declare {
            what: format!("subscriber {}", keys::gateway_commands(gateway)),
            reason: e.to_string(),
        })
        .map_err(AgentError::from)
}

/// A period's samples as the plants give them: each plant's sample at most once per
/// period, so that no batch holds more samples than the gateway has plants (the service
/// keeps a gateway's unread batches up to that many samples: a complete one replaces the
/// rest), and a plant's next sample begins the next period.
///
/// A period may leave in parts: what came by [`FLUSH_AFTER`] after its first sample
/// ([`Period::part`]), then the late plants' samples, sent as soon as the last of them
/// completes the period. Plants' sequence numbers say nothing about which period a sample
/// belongs to: each plant counts its own (one that started or restarted later is behind
/// its neighbours for good). Whether the plant already gave a sample this period does.
#[derive(Debug)]
struct Period {
    /// Each plant's place in `present`.
    index: HashMap<String, usize>,
    /// The plants that gave a sample this period (sent in a part already, or pending).
    present: Vec<bool>,
    count: usize,
    /// Samples not sent yet, each with its plant's place.
    pending: Vec<(usize, pb::Sample)>,
}

impl Period {
    fn new<'a>(devices: impl IntoIterator<Item = &'a str>) -> Self {
        let index: HashMap<String, usize> = devices
            .into_iter()
            .enumerate()
            .map(|(i, d)| (d.to_string(), i))
            .collect();
        let n = index.len();
        Self {
            index,
            present: vec![false; n],
            count: 0,
            pending: Vec::with_capacity(n),
        }
    }

    /// Add a plant's sample. If the plant already gave one this period, its next period
    /// began before the others gave theirs: that period ends, and what it had not sent
    /// comes back, to be sent first. A sample of a device the gateway does not host is
    /// dropped (its plants' loops are the only senders: none can come), so that a batch
    /// never holds more samples than plants.
    fn add(&mut self, sample: pb::Sample) -> Option<Vec<pb::Sample>> {
        let Some(&i) = self.index.get(sample.device_id.as_str()) else {
            debug_assert!(false, "a sample of {:?}, not hosted", sample.device_id);
            return None;
        };
        let out = if self.present[i] {
            Some(self.end()).filter(|b| !b.is_empty())
        } else {
            None
        };
        self.present[i] = true;
        self.count += 1;
        self.pending.push((i, sample));
        out
    }

    /// Whether every plant gave its sample this period.
    fn complete(&self) -> bool {
        self.count >= self.present.len()
    }

    fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }

    /// Samples waiting since the first of them.
    fn waiting(&self) -> usize {
        self.pending.len()
    }

    /// What the period has not sent yet, in the order the gateway hosts its plants
    /// (whatever order their samples came in: the service then finds each position's
    /// device where it found it the period before); the period goes on (its plants have
    /// given their sample: the rest will follow in another part).
    fn part(&mut self) -> Vec<pb::Sample> {
        self.pending.sort_unstable_by_key(|(i, _)| *i);
        self.pending.drain(..).map(|(_, s)| s).collect()
    }

    /// What the period has not sent yet; the next period begins.
    fn end(&mut self) -> Vec<pb::Sample> {
        self.present.fill(false);
        self.count = 0;
        self.part()
    }
}

/// Collect the plants' samples and send one batch per period, or its parts when a plant
/// is late: what came by [`FLUSH_AFTER`] after the first sample, and the rest as it comes.
async fn batcher(
    publisher: &zenoh::pubsub::Publisher<'_>,
    gateway: &str,
    key: Option<&Key>,
    devices: &[String],
    mut rx: mpsc::Receiver<pb::Sample>,
) {
    let mut period = Period::new(devices.iter().map(String::as_str));
    let plants = u32::try_from(devices.len()).unwrap_or(u32::MAX);
    let mut deadline = Instant::now();
    let send = |batch: Vec<pb::Sample>| {
        let payload = encode_sample_batch(&pb::SampleBatch {
            version: PROTOCOL_VERSION,
            gateway_id: gateway.to_string(),
            samples: batch,
            plants,
            mac: Vec::new(),
        });
        let payload = match key {
            Some(k) => k.seal(Kind::SampleBatch, payload),
            None => payload,
        };
        async move {
            if let Err(e) = publisher.put(payload).await {
                tracing::warn!("publishing a gateway batch: {e}");
            }
        }
    };
    loop {
        let next = if period.is_empty() {
            rx.recv().await
        } else {
            match tokio::time::timeout_at(deadline, rx.recv()).await {
                Ok(s) => s,
                Err(_) => {
                    send(period.part()).await;
                    continue;
                }
            }
        };
        let Some(sample) = next else {
            if !period.is_empty() {
                send(period.end()).await;
            }
            // Every loop ended: nothing more will come.
            std::future::pending::<()>().await;
            return;
        };
        if let Some(earlier) = period.add(sample) {
            send(earlier).await;
        }
        if period.waiting() == 1 {
            deadline = Instant::now() + FLUSH_AFTER;
        }
        if period.complete() {
            send(period.end()).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(device: &str, seq: u64) -> pb::Sample {
        pb::Sample {
            device_id: device.into(),
            seq,
            ..Default::default()
        }
    }

    fn ids(batch: &[pb::Sample]) -> Vec<(&str, u64)> {
        batch
            .iter()
            .map(|s| (s.device_id.as_str(), s.seq))
            .collect()
    }

    #[test]
    fn a_period_is_complete_with_each_plants_sample_whatever_their_sequences() {
        let mut p = Period::new(["a", "b", "c"]);
        // c started later than its neighbours: its sequence is behind theirs for good.
        assert!(p.add(sample("a", 40)).is_none());
        assert!(p.add(sample("c", 7)).is_none());
        assert!(!p.complete());
        assert!(p.add(sample("b", 40)).is_none());
        assert!(p.complete());
        // In the order the gateway hosts its plants, not the order they came in.
        assert_eq!(ids(&p.end()), [("a", 40), ("b", 40), ("c", 7)]);
        assert!(p.is_empty() && !p.complete());
    }

    #[test]
    fn a_late_plant_completes_its_period_in_a_part_of_its_own() {
        let mut p = Period::new(["a", "b", "c"]);
        p.add(sample("a", 1));
        p.add(sample("b", 1));
        // The deadline: a and b leave; c is late.
        assert_eq!(ids(&p.part()), [("a", 1), ("b", 1)]);
        assert!(p.add(sample("c", 1)).is_none());
        assert!(p.complete(), "c completes the period: sent at once");
        assert_eq!(ids(&p.end()), [("c", 1)]);
        // Next period, in one batch, in the order the gateway hosts its plants.
        for d in ["b", "c", "a"] {
            assert!(p.add(sample(d, 2)).is_none());
        }
        assert!(p.complete());
        assert_eq!(ids(&p.end()), [("a", 2), ("b", 2), ("c", 2)]);
    }

    #[test]
    fn a_plants_next_sample_ends_the_period_it_missed() {
        let mut p = Period::new(["a", "b", "c"]);
        p.add(sample("a", 1));
        p.add(sample("b", 1));
        // c gives nothing this period: a's next sample ends it, a and b's leave first.
        let rest = p.add(sample("a", 2)).expect("a and b's samples");
        assert_eq!(ids(&rest), [("a", 1), ("b", 1)]);
        assert!(
            p.add(sample("c", 1)).is_none(),
            "c's late sample joins the next period"
        );
        assert!(p.add(sample("b", 2)).is_none());
        assert!(p.complete());
        assert_eq!(ids(&p.end()), [("a", 2), ("b", 2), ("c", 1)]);
        // After a part, a plant's next sample ends the period with nothing left to send.
        p.add(sample("a", 3));
        assert_eq!(p.part().len(), 1);
        assert!(p.add(sample("a", 4)).is_none());
        assert_eq!(ids(&p.part()), [("a", 4)]);
    }
}
