//! Replay a recording through the controller, offline: a regression check.
//!
//! A service's recording holds its configuration (attached as [`CONFIG_ATTACHMENT`]), the
//! state of any device it restored at start (`snapshot/{id}`), and, in the order the worker
//! handled them, every sample it stepped on, every command it sent and every change an
//! operator made. Replaying builds a [`Registry`] from that configuration and feeds it the
//! same samples and changes in the same order; the registry has no clock and no I/O of its
//! own, so the same code gives the same commands to the last bit. A build whose laws,
//! estimators, envelope or output maps compute differently shows here as commands that
//! differ from the recorded ones by more than the tolerance.
//!
//! Compared: every CONTROL and WARMING_UP command of each device, in order: the mode,
//! `u` and `v` (and the horizon's length). Not replayable: fleet handovers and standby
//! updates (state that came from another process); a recording with them is replayed up
//! to the first one and the report says so.

use std::collections::BTreeMap;

use protocol::{decode, pb};
use serde::Serialize;
use telemetry::{read_recording, RecordError, Topic};

use crate::registry::{Registry, Via};
use crate::ServiceConfig;

/// The attachment holding the service's configuration: [`ServiceConfig`] as TOML, the
/// service file's own format (which, unlike JSON, keeps infinite limits).
pub const CONFIG_ATTACHMENT: &str = "service-config.toml";

/// The default tolerance on `u` and `v`: the replay runs the same arithmetic, so anything
/// above rounding is a change of behaviour.
pub const DEFAULT_TOLERANCE: f64 = 1e-9;

/// Why a recording cannot be replayed.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// Not an MCAP file, or cut short.
    #[error("reading the recording: {0}")]
    Read(#[from] RecordError),
    /// No configuration attached: not a service's recording (an agent's, perhaps).
    #[error("the recording has no {CONFIG_ATTACHMENT} attachment: replay needs a controller service's recording (an agent's records the plant side only)")]
    NoConfig,
    /// The attached configuration does not load.
    #[error("the recorded configuration: {0}")]
    Config(String),
}

/// One device's comparison.
#[derive(Debug, Clone, Default, Serialize)]
pub struct DeviceReplay {
    /// Device id.
    pub device: String,
    /// Samples fed to the controller.
    pub samples: u64,
    /// Changes (configuration, reference, envelope) applied; refused ones are counted in
    /// `changes_refused` (a recording holds accepted ones only, so any is a difference).
    pub changes: u64,
    /// Changes the replaying controller refused.
    pub changes_refused: u64,
    /// Commands compared (CONTROL and WARMING_UP, in order).
    pub compared: u64,
    /// Commands recorded that the replay did not produce, or the other way round.
    pub unmatched: u64,
    /// Largest |difference| of `v` (the output sent).
    pub max_dv: f64,
    /// Largest |difference| of `u` (before the output map).
    pub max_du: f64,
    /// Commands that differ by more than the tolerance, or in mode or horizon length.
    pub mismatches: u64,
    /// The first of them, described.
    pub first_mismatch: Option<String>,
}

/// What a replay found.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ReplayReport {
    /// The tolerance used on `u` and `v`.
    pub tolerance: f64,
    /// Per device, by id.
    pub devices: Vec<DeviceReplay>,
    /// Whether every device matched: no mismatch, nothing unmatched, nothing refused.
    pub matched: bool,
    /// What could not be replayed, if anything.
    pub notes: Vec<String>,
}

fn kept(c: &pb::Command) -> bool {
    c.mode == pb::Mode::Control as i32 || c.mode == pb::Mode::WarmingUp as i32
}

/// Replay `bytes` (an MCAP recording of a controller service).
pub fn replay(bytes: &[u8], tolerance: f64) -> Result<ReplayReport, ReplayError> {
    let contents = read_recording(bytes)?;
    let mut report = ReplayReport {
        tolerance,
        ..Default::default()
    };
    let registry = registry_of(&contents, &mut report.notes)?;
    if contents.truncated {
        report.notes.push(
            "the recording was cut short (its writer did not finish it): replayed up to the cut"
                .into(),
        );
    }
    let mut play = Play {
        registry,
        recorded: BTreeMap::new(),
        replayed: BTreeMap::new(),
        stats: BTreeMap::new(),
    };
    for m in &contents.messages {
        play.message(m, &mut report.notes);
    }
    report.devices = play.compare(contents.truncated, tolerance);
    report.matched = report
        .devices
        .iter()
        .all(|d| d.mismatches == 0 && d.unmatched == 0 && d.changes_refused == 0)
        && !report.devices.is_empty();
    Ok(report)
}

/// The registry the recording starts from: its configuration (one registry holds every
/// device; what decided where a device lived, workers, fleet, standby, and what the
/// process did besides control, snapshots, observers, stays out), with the devices'
/// recorded snapshots restored.
fn registry_of(
    contents: &telemetry::RecordingContents,
    notes: &mut Vec<String>,
) -> Result<Registry, ReplayError> {
    let file = contents
        .attachments
        .get(CONFIG_ATTACHMENT)
        .ok_or(ReplayError::NoConfig)?;
    let text = std::str::from_utf8(file).map_err(|e| ReplayError::Config(e.to_string()))?;
    let mut config: ServiceConfig =
        toml::from_str(text).map_err(|e| ReplayError::Config(e.to_string()))?;
    config.workers = 1;
    config.fleet = None;
    config.standby = None;
    config.snapshots = None;
    config.metrics = None;
    config.record = None;
    let mut registry = Registry::new(config).map_err(|e| ReplayError::Config(e.to_string()))?;
    for (name, data) in &contents.attachments {
        let Some(id) = name.strip_prefix("snapshot/") else {
            continue;
        };
        let restored = crate::snapshot::decode(data)
            .map_err(|e| e.to_string())
            .and_then(|s| registry.restore(&s));
        if let Err(e) = restored {
            notes.push(format!("{id}: the recorded restore does not replay: {e}"));
        }
    }
    Ok(registry)
}

/// The replay in progress: the registry, and per device the commands recorded and
/// replayed.
struct Play {
    registry: Registry,
    recorded: BTreeMap<String, Vec<pb::Command>>,
    replayed: BTreeMap<String, Vec<pb::Command>>,
    stats: BTreeMap<String, DeviceReplay>,
}

impl Play {
    /// One recorded message: a sample is answered again, a command kept for comparison, a
    /// change applied again.
    fn message(&mut self, m: &telemetry::Recorded, notes: &mut Vec<String>) {
        let dev = m.device.as_str();
        let st = self
            .stats
            .entry(dev.to_string())
            .or_insert_with(|| DeviceReplay {
                device: dev.to_string(),
                ..Default::default()
            });
        match m.topic {
            Topic::Sample => {
                let Ok(s) = decode::<pb::Sample>(&m.data) else {
                    notes.push(format!("{dev}: a recorded sample does not decode"));
                    return;
                };
                st.samples += 1;
                // The time the answer carries: when the sample was logged, as near as the
                // recording knows to when it was answered.
                let mut c = pb::Command::default();
                let served = self
                    .registry
                    .handle_sample(Via::key(dev), &s, m.log_ns, &mut c);
                if served.answered() && kept(&c) {
                    self.replayed.entry(dev.to_string()).or_default().push(c);
                }
            }
            Topic::Command => {
                if let Ok(c) = decode::<pb::Command>(&m.data) {
                    if kept(&c) {
                        self.recorded.entry(dev.to_string()).or_default().push(c);
                    }
                }
            }
            Topic::ConfigRequest
            | Topic::ReferenceUpdate
            | Topic::EnvelopeRequest
            | Topic::CommissionRequest => {
                let registry = &mut self.registry;
                let reply = match m.topic {
                    Topic::ConfigRequest => {
                        decode::<pb::ConfigRequest>(&m.data).map(|r| registry.configure(dev, &r))
                    }
                    Topic::ReferenceUpdate => decode::<pb::ReferenceUpdate>(&m.data)
                        .map(|r| registry.set_reference(dev, &r)),
                    Topic::CommissionRequest => decode::<pb::CommissionRequest>(&m.data)
                        .map(|r| registry.commission(dev, &r, "replay", m.log_ns)),
                    _ => decode::<pb::EnvelopeRequest>(&m.data)
                        .map(|r| registry.change_envelope(dev, &r)),
                };
                st.changes += 1;
                let refused = match reply {
                    Ok(r) if r.accepted => return,
                    Ok(r) => format!("{dev}: a recorded change is refused now: {}", r.reason),
                    Err(e) => format!("{dev}: a recorded change does not decode: {e}"),
                };
                st.changes_refused += 1;
                notes.push(refused);
            }
            Topic::Config | Topic::Event => {}
        }
    }

    /// Compare each device's replayed commands with its recorded ones, in order.
    fn compare(mut self, truncated: bool, tolerance: f64) -> Vec<DeviceReplay> {
        let empty = Vec::new();
        for (dev, st) in self.stats.iter_mut() {
            let rec = self.recorded.get(dev).unwrap_or(&empty);
            let rep = self.replayed.get(dev).unwrap_or(&empty);
            // A cut may fall between a sample and its command: the replay then has answers
            // the file lost, which is no difference.
            st.unmatched = if truncated {
                rec.len().saturating_sub(rep.len())
            } else {
                rec.len().abs_diff(rep.len())
            } as u64;
            for (a, b) in rec.iter().zip(rep) {
                compare_one(st, a, b, tolerance);
            }
        }
        self.stats
            .into_values()
            .filter(|d| d.samples > 0 || d.compared > 0)
            .collect()
    }
}

/// Compare a recorded command `a` with its replayed `b`, into the device's figures.
fn compare_one(st: &mut DeviceReplay, a: &pb::Command, b: &pb::Command, tolerance: f64) {
    st.compared += 1;
    let diff = |x: &[f64], y: &[f64]| -> f64 {
        if x.len() != y.len() {
            return f64::INFINITY;
        }
        x.iter()
            .zip(y)
            .map(|(p, q)| if p == q { 0.0 } else { (p - q).abs() })
            .fold(0.0, f64::max)
    };
    let (dv, du) = (diff(&a.v, &b.v), diff(&a.u, &b.u));
    st.max_dv = st.max_dv.max(dv);
    st.max_du = st.max_du.max(du);
    // Written so that a NaN difference counts as a mismatch.
    let beyond =
        |d: f64| d.partial_cmp(&tolerance) != Some(std::cmp::Ordering::Less) && d != tolerance;
    let bad = a.seq != b.seq
        || a.mode != b.mode
        || a.horizon.len() != b.horizon.len()
        || beyond(dv)
        || beyond(du);
    if bad {
        st.mismatches += 1;
        st.first_mismatch.get_or_insert_with(|| {
            format!(
                "seq {} (replayed seq {}): recorded v {:?} u {:?}, replayed v {:?} u {:?}",
                a.seq, b.seq, a.v, a.u, b.v, b.u
            )
        });
    }
}

/// The report for people: one line per device, then the notes.
pub fn render(r: &ReplayReport) -> String {
    let mut out = format!(
        "replay: {} (tolerance {:e} on u and v)\n",
        if r.matched { "MATCHES" } else { "DIFFERS" },
        r.tolerance
    );
    out.push_str("device                samples  compared  unmatched  mismatches  max |dv|   max |du|   changes\n");
    for d in &r.devices {
        out.push_str(&format!(
            "{:<20} {:>8} {:>9} {:>10} {:>11}  {:<9.2e}  {:<9.2e}  {}{}\n",
            d.device,
            d.samples,
            d.compared,
            d.unmatched,
            d.mismatches,
            d.max_dv,
            d.max_du,
            d.changes,
            if d.changes_refused > 0 {
                format!(" ({} refused)", d.changes_refused)
            } else {
                String::new()
            }
        ));
        if let Some(m) = &d.first_mismatch {
            out.push_str(&format!("  first mismatch: {m}\n"));
        }
    }
    for n in &r.notes {
        out.push_str(&format!("note: {n}\n"));
    }
    out
}
