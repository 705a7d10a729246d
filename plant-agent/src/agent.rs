//! The networked loop of the plant agent: pace the plant on absolute deadlines, publish a
//! sample every period, apply the command that answers it, and stay safe when commands are
//! late or lost.
//!
//! Every period `k` (deadline `t_k = start + k h`, never drifting):
//! 1. read the outputs and publish sample `k` (with what was applied over the last period);
//! 2. step the local controller (it runs every period, fed what was really applied, so it is
//!    warm and bumpless when it has to take over);
//! 3. if commands have been missing for more than `hold_periods`, apply the fallback at once
//!    (local controller, or a safe stop);
//! 4. until `t_{k+1}`, apply each command the moment it arrives if it is newer than the last
//!    one applied and at most `max_age` periods old (normally command `k` itself; on a slow
//!    link an older one is still the best there is); older ones are stale: dropped and
//!    counted (a stale command is worse than none).
//!
//! With a simulated plant the simulator integrates exactly the time that passes: from `t_k`
//! to the command's arrival with the old voltages, then to `t_{k+1}` with the new ones, so
//! the network's real delay acts on the simulated rig. Plant time is the nominal schedule
//! `k h`, so a busy machine delays the loop but never distorts the plant's physics.

use std::path::PathBuf;
use std::time::Duration;

use mfc::trajectory::{evaluate, Piece};
use mfc::{ChannelConfig, ChannelOutput, MimoController, Reference};
use protocol::{decode, encode, keys, pb, PROTOCOL_VERSION};
use serde::{Deserialize, Serialize};
use tokio::sync::mpsc;
use tokio::time::Instant;
use zenoh::Session;

use crate::metrics::{Accumulator, ChannelMetrics};
use crate::plant::{Plant, PlantError};

/// What to do when commands stop coming.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Fallback {
    /// Run the local controller (the same `mfc` core, the same configuration).
    Local,
    /// Apply zero volts.
    SafeStop,
}

/// Configuration of the agent loop.
#[derive(Debug, Clone)]
pub struct AgentConfig {
    /// Device id (key chunk).
    pub device_id: String,
    /// Sampling period (s).
    pub period: f64,
    /// Number of periods to run.
    pub steps: usize,
    /// Oldest command still worth applying, in periods (a command for sample `k - a` may be
    /// applied during period `k` if `a <= max_age`): on a slow link the newest command is
    /// still the best one; beyond this age it is stale and dropped.
    pub max_age: u32,
    /// Periods to hold the last command before falling back: the fallback engages at the
    /// start of the period after `hold_periods` consecutive periods without a command.
    pub hold_periods: u32,
    /// What to fall back to.
    pub fallback: Fallback,
    /// The local controller's channels (also used for the fallback).
    pub channels: Vec<ChannelConfig>,
    /// Reference per channel (for the local controller and the tracking figures).
    pub reference: Vec<Vec<Piece>>,
    /// Channel names (CSV, summary).
    pub names: Vec<String>,
    /// Saturation voltage, to count saturated samples.
    pub max_voltage: f64,
    /// Where to write the run's CSV, if anywhere.
    pub record: Option<PathBuf>,
}

/// Where the agent's loop was, per period.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LoopMode {
    /// Applying the controller's command.
    Remote,
    /// Holding the last command.
    Holding,
    /// Local fallback controller.
    Fallback,
    /// Safe stop.
    SafeStop,
}

/// One recorded period.
#[derive(Debug, Clone)]
pub struct Row {
    /// Plant time.
    pub t: f64,
    /// References.
    pub y_ref: Vec<f64>,
    /// Outputs.
    pub y: Vec<f64>,
    /// Applied at the end of the period.
    pub v: Vec<f64>,
    /// Mode during the period.
    pub mode: LoopMode,
    /// Round trip of this period's sample/command, µs (0: none).
    pub rtt_us: u32,
}

/// What a run of the agent measured.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct AgentReport {
    /// Device id.
    pub device_id: String,
    /// Tracking per channel.
    pub channels: Vec<ChannelMetrics>,
    /// Periods run.
    pub periods: usize,
    /// Commands applied.
    pub commands: u64,
    /// Periods with no usable command in time.
    pub missing: u64,
    /// Commands applied after their own period (at most `max_age` periods late).
    pub late: u64,
    /// Commands dropped as too old, or older than one already applied.
    pub stale: u64,
    /// Second commands for a sample already answered (two controllers answering).
    pub duplicate_commands: u64,
    /// Answers saying the controller is still filling its estimation window.
    pub warming_up: u64,
    /// Commands refused by the controller (`REJECTED`).
    pub rejected: u64,
    /// Times the fallback engaged.
    pub fallbacks: u64,
    /// Periods spent holding, in fallback, in safe stop.
    pub holding_periods: u64,
    /// Periods in the local fallback.
    pub fallback_periods: u64,
    /// Periods in safe stop.
    pub safe_stop_periods: u64,
    /// Sample-to-command round trip, µs: median and 99th percentile.
    pub rtt_p50_us: f64,
    /// 99th percentile.
    pub rtt_p99_us: f64,
    /// Periods whose deadline the loop missed by more than half a period.
    pub overruns: u64,
    /// Pitch stop hits or other plant-specific safety counts are in the plant's own report.
    pub completed: bool,
}

/// Why the agent stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    /// The plant failed.
    #[error(transparent)]
    Plant(#[from] PlantError),
    /// Zenoh refused a declaration.
    #[error(transparent)]
    Transport(#[from] transport::TransportError),
    /// The local controller's configuration was refused.
    #[error("local controller: {0}")]
    Controller(#[from] mfc::MfcError),
    /// The configuration does not fit the plant.
    #[error("{0}")]
    Config(String),
    /// Writing the record.
    #[error("writing {path}: {source}")]
    Record {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

fn percentile(sorted: &[u32], q: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    f64::from(sorted[((sorted.len() - 1) as f64 * q).round() as usize])
}

/// Run the loop for `config.steps` periods on `session`, then stop the plant.
pub async fn run_agent(
    session: &Session,
    plant: &mut dyn Plant,
    config: &AgentConfig,
    run_id: u64,
) -> Result<(AgentReport, Vec<Row>), AgentError> {
    let n = plant.channels();
    if config.channels.len() != n || config.reference.len() != n {
        return Err(AgentError::Config(format!(
            "the plant has {n} channels, the configuration {} and the reference {}",
            config.channels.len(),
            config.reference.len()
        )));
    }
    protocol::keys::check_id(&config.device_id).map_err(|e| AgentError::Config(e.to_string()))?;
    let id = config.device_id.as_str();
    let mut local: MimoController = MimoController::new(&config.channels)?;

    let (tx, mut rx) = mpsc::channel::<(Instant, Vec<u8>)>(256);
    let _commands = session
        .declare_subscriber(keys::command(id))
        .callback(move |s| {
            let _ = tx.try_send((Instant::now(), s.payload().to_bytes().into_owned()));
        })
        .await
        .map_err(|e| transport::TransportError::Declare {
            what: format!("subscriber {}", keys::command(id)),
            reason: e.to_string(),
        })?;
    let publisher = transport::control_publisher(session, keys::sample(id)).await?;
    let _token = session
        .liveliness()
        .declare_token(keys::alive_plant(id))
        .await
        .map_err(|e| transport::TransportError::Declare {
            what: "liveliness token".into(),
            reason: e.to_string(),
        })?;

    let h = config.period;
    let period = Duration::from_secs_f64(h);
    let mut applied = plant.write(&vec![0.0; n])?;
    // Time-weighted mean of what was applied over the last period: a command that lands
    // mid-period was applied for only part of it, and the estimator integrates exactly
    // that.
    let mut interval_mean = vec![0.0; n];
    let mut interval_acc = vec![0.0; n];
    let mut refs = vec![Reference::default(); n];
    let mut local_out = vec![ChannelOutput::default(); n];
    let mut acc = vec![Accumulator::default(); n];
    let mut rows = Vec::with_capacity(if config.record.is_some() {
        config.steps
    } else {
        0
    });
    let mut rtts: Vec<u32> = Vec::with_capacity(config.steps);
    let mut report = AgentReport {
        device_id: id.to_string(),
        channels: Vec::new(),
        periods: 0,
        commands: 0,
        missing: 0,
        late: 0,
        stale: 0,
        duplicate_commands: 0,
        warming_up: 0,
        rejected: 0,
        fallbacks: 0,
        holding_periods: 0,
        fallback_periods: 0,
        safe_stop_periods: 0,
        rtt_p50_us: 0.0,
        rtt_p99_us: 0.0,
        overruns: 0,
        completed: false,
    };
    let mut missing_streak: u32 = 0;
    let mut last_applied: Option<u64> = None;
    let mut sent_at: std::collections::VecDeque<(u64, Instant)> = std::collections::VecDeque::new();
    let mut last_rtt_us: u32 = 0;
    let mut mode = LoopMode::Remote;
    // Give the subscriptions a moment to propagate before the first sample.
    tokio::time::sleep(Duration::from_millis(100)).await;
    let start = Instant::now();

    for k in 0..config.steps {
        let deadline = start + period * k as u32;
        let next = deadline + period;
        tokio::time::sleep_until(deadline).await;
        if Instant::now() > deadline + period / 2 {
            report.overruns += 1;
        }
        let t = k as f64 * h;
        let y = plant.read()?;
        let flags = match mode {
            LoopMode::Remote => 0,
            LoopMode::Holding => pb::SampleFlags::Holding as u32,
            LoopMode::Fallback => pb::SampleFlags::Fallback as u32,
            LoopMode::SafeStop => pb::SampleFlags::SafeStop as u32,
        };
        let sample = pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: id.to_string(),
            seq: k as u64,
            plant_time: t,
            outputs: y.clone(),
            applied: interval_mean.clone(),
            flags,
            sent_unix_ns: protocol::unix_ns(),
            last_rtt_us,
            run_id,
        };
        sent_at.push_back((k as u64, Instant::now()));
        if sent_at.len() > config.max_age as usize + 2 {
            sent_at.pop_front();
        }
        if let Err(e) = publisher.put(encode(&sample)).await {
            tracing::warn!(device = id, "publishing sample {k}: {e}");
        }
        // The local controller follows every period, fed what was really applied.
        for (r, pieces) in refs.iter_mut().zip(&config.reference) {
            *r = evaluate(pieces, t);
        }
        if k > 0 {
            let _ = local.report_applied(&interval_mean);
        }
        let local_ok = local.step(t, &y, &refs, &mut local_out).is_ok();
        let mut period_mode = mode;
        let in_fallback = matches!(mode, LoopMode::Fallback | LoopMode::SafeStop);
        if in_fallback || (missing_streak > 0 && missing_streak >= config.hold_periods) {
            // Commands have been missing too long: fall back now, locally, without delay.
            let v: Vec<f64> = match (config.fallback, local_ok) {
                (Fallback::Local, true) => local_out.iter().map(|o| o.v).collect(),
                _ => vec![0.0; n],
            };
            let new_mode = if config.fallback == Fallback::Local && local_ok {
                LoopMode::Fallback
            } else {
                LoopMode::SafeStop
            };
            if !matches!(mode, LoopMode::Fallback | LoopMode::SafeStop) {
                report.fallbacks += 1;
                tracing::warn!(
                    device = id,
                    seq = k,
                    "no command for {missing_streak} periods: {new_mode:?}"
                );
            }
            mode = new_mode;
            period_mode = new_mode;
            applied = plant.write(&v)?;
        }

        let mut seg_start = 0.0;
        interval_acc.iter_mut().for_each(|a| *a = 0.0);
        // Apply the newest acceptable command as soon as it arrives, until the next
        // deadline: normally command k; on a slow link an older one, up to `max_age`
        // periods old. Anything older, or not newer than the last applied, is dropped.
        let mut elapsed_in_period = 0.0;
        let mut got = false;
        let mut warming = false;
        let mut rtt_us = 0;
        loop {
            let Ok(Some((arrival, bytes))) = tokio::time::timeout_at(next, rx.recv()).await else {
                break;
            };
            let cmd = match decode::<pb::Command>(&bytes) {
                Ok(c) => c,
                Err(e) => {
                    tracing::warn!(device = id, "undecodable command: {e}");
                    continue;
                }
            };
            let s = cmd.seq;
            if cmd.device_id != id || s > k as u64 {
                continue;
            }
            if last_applied == Some(s) {
                report.duplicate_commands += 1;
                continue;
            }
            if last_applied.is_some_and(|l| s < l) || k as u64 - s > u64::from(config.max_age) {
                report.stale += 1;
                continue;
            }
            match pb::Mode::try_from(cmd.mode) {
                Ok(pb::Mode::Control)
                    if cmd.v.len() == n && cmd.v.iter().all(|v| v.is_finite()) =>
                {
                    let at = (arrival - deadline).as_secs_f64().clamp(0.0, h);
                    plant.advance(at - elapsed_in_period)?;
                    elapsed_in_period = at;
                    for (a, v) in interval_acc.iter_mut().zip(&applied) {
                        *a += v * (at - seg_start);
                    }
                    seg_start = at;
                    applied = plant.write(&cmd.v)?;
                    if let Some((_, sent)) = sent_at.iter().find(|(q, _)| *q == s) {
                        rtt_us = u32::try_from((arrival - *sent).as_micros()).unwrap_or(u32::MAX);
                        rtts.push(rtt_us);
                    }
                    report.commands += 1;
                    if s < k as u64 {
                        report.late += 1;
                    }
                    if matches!(mode, LoopMode::Fallback | LoopMode::SafeStop) {
                        tracing::info!(
                            device = id,
                            seq = k,
                            "commands are back: remote control resumes"
                        );
                    }
                    last_applied = Some(s);
                    mode = LoopMode::Remote;
                    missing_streak = 0;
                    got = true;
                    if s == k as u64 {
                        break;
                    }
                }
                Ok(pb::Mode::WarmingUp) => {
                    // The controller is alive but not ready: not a missing command, and
                    // nothing to apply (keep holding, or keep the local fallback running).
                    warming = true;
                    report.warming_up += 1;
                    missing_streak = 0;
                    if s == k as u64 {
                        break;
                    }
                }
                Ok(pb::Mode::Rejected) => {
                    report.rejected += 1;
                    tracing::warn!(
                        device = id,
                        seq = s,
                        "sample refused by the controller: {}",
                        cmd.error
                    );
                    if s == k as u64 {
                        break;
                    }
                }
                _ => {}
            }
        }
        if !got && !warming {
            report.missing += 1;
            missing_streak += 1;
            if mode == LoopMode::Remote && missing_streak < config.hold_periods.max(1) {
                mode = LoopMode::Holding;
            }
            if mode == LoopMode::Holding {
                period_mode = LoopMode::Holding;
            }
        }
        match period_mode {
            LoopMode::Holding => report.holding_periods += 1,
            LoopMode::Fallback => report.fallback_periods += 1,
            LoopMode::SafeStop => report.safe_stop_periods += 1,
            LoopMode::Remote => {}
        }
        plant.advance(h - elapsed_in_period)?;
        for ((m, a), v) in interval_mean.iter_mut().zip(&interval_acc).zip(&applied) {
            *m = (a + v * (h - seg_start)) / h;
        }
        last_rtt_us = rtt_us;
        for i in 0..n {
            acc[i].add(
                y[i] - refs[i].y,
                h,
                applied[i],
                applied[i].abs() >= config.max_voltage - 1e-9,
            );
        }
        if config.record.is_some() {
            rows.push(Row {
                t,
                y_ref: refs.iter().map(|r| r.y).collect(),
                y,
                v: applied.clone(),
                mode: period_mode,
                rtt_us,
            });
        }
        report.periods += 1;
    }
    plant.stop()?;
    rtts.sort_unstable();
    report.rtt_p50_us = percentile(&rtts, 0.5);
    report.rtt_p99_us = percentile(&rtts, 0.99);
    report.channels = acc
        .iter()
        .zip(&config.names)
        .map(|(a, name)| a.finish(name))
        .collect();
    report.completed = true;
    if let Some(path) = &config.record {
        write_rows(path, &config.names, &rows).map_err(|source| AgentError::Record {
            path: path.clone(),
            source,
        })?;
    }
    Ok((report, rows))
}

fn write_rows(path: &std::path::Path, names: &[String], rows: &[Row]) -> std::io::Result<()> {
    use std::io::Write;
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let mut w = std::io::BufWriter::new(std::fs::File::create(path)?);
    write!(w, "t")?;
    for n in names {
        write!(w, ",{n}_ref,{n},{n}_v")?;
    }
    writeln!(w, ",mode,rtt_us")?;
    for r in rows {
        write!(w, "{:.4}", r.t)?;
        for i in 0..names.len() {
            write!(w, ",{:e},{:e},{:e}", r.y_ref[i], r.y[i], r.v[i])?;
        }
        writeln!(w, ",{:?},{}", r.mode, r.rtt_us)?;
    }
    w.flush()
}
