//! The recorder: one format for every run, offline or networked.
//!
//! A run leaves a directory with `run.csv` (one row per period), `summary.json` (what the
//! run measured and how it ended) and one PNG and one SVG plot per channel. The same code
//! writes all three for `mfc-lab sim`, `plant-agent run` and the demo, so a networked run
//! and its offline twin can be compared column by column.
//!
//! `run.csv` columns: `t`, then per channel `{name}_ref, {name}, {name}_u, {name}_v,
//! {name}_f_est` (reference, output, controller output `u`, applied input `v`, estimate of
//! `F`; empty where unknown, e.g. `F` for a PID), then for networked runs `mode` and
//! `rtt_us` (the agent's mode during the period and the round trip of its sample, 0 when
//! no command came).

pub mod metrics;
mod plot;

use std::fs;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::LoopMode;

pub use metrics::{percentile, Accumulator, ChannelMetrics};

/// Why a record could not be written.
#[derive(Debug, thiserror::Error)]
pub enum RunRecordError {
    /// A file could not be written.
    #[error("writing {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The summary could not be serialised.
    #[error("summary: {0}")]
    Json(#[from] serde_json::Error),
    /// A plot could not be drawn.
    #[error("plot {path}: {reason}")]
    Plot {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> RunRecordError + '_ {
    move |source| RunRecordError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// One channel's time series.
#[derive(Debug, Clone, Default)]
pub struct Trace {
    /// Reference `y*`.
    pub y_ref: Vec<f64>,
    /// Measured output `y`.
    pub y: Vec<f64>,
    /// Controller output `u` (NaN: unknown).
    pub u: Vec<f64>,
    /// Applied input `v`.
    pub v: Vec<f64>,
    /// Estimate of `F` (NaN while the window fills, for PID and ADRC, or unknown).
    pub f_est: Vec<f64>,
}

/// The record of one run, period by period, column-oriented (plots take whole columns):
/// what `run.csv` and the plots are written from. (Named apart from `telemetry`'s
/// `Recording`, an MCAP file of messages.)
#[derive(Debug, Clone, Default)]
pub struct RunRecord {
    /// Channel names.
    pub names: Vec<String>,
    /// Channel units.
    pub units: Vec<String>,
    /// Plant time of each period.
    pub t: Vec<f64>,
    /// Per channel.
    pub traces: Vec<Trace>,
    /// Networked runs: the agent's mode in each period (empty offline).
    pub modes: Vec<LoopMode>,
    /// Networked runs: round trip of each period's sample, µs (0: no command).
    pub rtt_us: Vec<u32>,
}

/// One period, as handed to [`RunRecord::push`].
#[derive(Debug, Clone, Copy)]
pub struct Period<'a> {
    /// Plant time.
    pub t: f64,
    /// References.
    pub y_ref: &'a [f64],
    /// Outputs.
    pub y: &'a [f64],
    /// Controller outputs, if known.
    pub u: Option<&'a [f64]>,
    /// Applied inputs.
    pub v: &'a [f64],
    /// Estimates of `F`, if known.
    pub f_est: Option<&'a [f64]>,
    /// Networked runs: the mode and the round trip (µs).
    pub net: Option<(LoopMode, u32)>,
}

impl RunRecord {
    /// An empty record of these channels, with room for `periods` rows.
    pub fn new(names: Vec<String>, units: Vec<String>, periods: usize) -> Self {
        let traces = names
            .iter()
            .map(|_| Trace {
                y_ref: Vec::with_capacity(periods),
                y: Vec::with_capacity(periods),
                u: Vec::with_capacity(periods),
                v: Vec::with_capacity(periods),
                f_est: Vec::with_capacity(periods),
            })
            .collect();
        Self {
            names,
            units,
            t: Vec::with_capacity(periods),
            traces,
            modes: Vec::new(),
            rtt_us: Vec::new(),
        }
    }

    /// Number of periods recorded.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// Whether nothing was recorded.
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// Append one period. Missing values of a short slice are recorded as NaN, so a
    /// caller's bug shows in the file instead of shifting columns.
    pub fn push(&mut self, p: Period<'_>) {
        let at = |s: &[f64], i: usize| s.get(i).copied().unwrap_or(f64::NAN);
        self.t.push(p.t);
        for (i, tr) in self.traces.iter_mut().enumerate() {
            tr.y_ref.push(at(p.y_ref, i));
            tr.y.push(at(p.y, i));
            tr.u.push(p.u.map_or(f64::NAN, |u| at(u, i)));
            tr.v.push(at(p.v, i));
            tr.f_est.push(p.f_est.map_or(f64::NAN, |f| at(f, i)));
        }
        if let Some((mode, rtt)) = p.net {
            self.modes.push(mode);
            self.rtt_us.push(rtt);
        }
    }

    /// The mode of period `k`, for networked runs.
    pub fn mode(&self, k: usize) -> Option<LoopMode> {
        self.modes.get(k).copied()
    }

    /// Write `run.csv` (see the module doc for the columns).
    pub fn write_csv(&self, path: &Path) -> Result<(), RunRecordError> {
        let file = fs::File::create(path).map_err(io(path))?;
        let mut w = BufWriter::new(file);
        self.csv(&mut w).map_err(io(path))
    }

    fn csv(&self, w: &mut impl Write) -> std::io::Result<()> {
        let net = !self.modes.is_empty();
        write!(w, "t")?;
        for n in &self.names {
            write!(w, ",{n}_ref,{n},{n}_u,{n}_v,{n}_f_est")?;
        }
        if net {
            write!(w, ",mode,rtt_us")?;
        }
        writeln!(w)?;
        let num = |x: f64| {
            if x.is_nan() {
                String::new()
            } else {
                format!("{x:e}")
            }
        };
        for (k, t) in self.t.iter().enumerate() {
            write!(w, "{t:.4}")?;
            for tr in &self.traces {
                write!(
                    w,
                    ",{},{},{},{},{}",
                    num(tr.y_ref[k]),
                    num(tr.y[k]),
                    num(tr.u[k]),
                    num(tr.v[k]),
                    num(tr.f_est[k])
                )?;
            }
            if net {
                let mode = self.modes.get(k).map(|m| m.as_str()).unwrap_or("");
                write!(w, ",{mode},{}", self.rtt_us.get(k).copied().unwrap_or(0))?;
            }
            writeln!(w)?;
        }
        w.flush()
    }
}

/// Write a run's directory: `run.csv`, `summary.json`, and per channel `{name}.png` and
/// `{name}.svg` titled `{title} — {name}`. Creates `dir`.
pub fn write_run(
    dir: &Path,
    title: &str,
    record: &RunRecord,
    summary: &impl Serialize,
) -> Result<(), RunRecordError> {
    fs::create_dir_all(dir).map_err(io(dir))?;
    record.write_csv(&dir.join("run.csv"))?;
    write_summary(dir, summary)?;
    for (i, name) in record.names.iter().enumerate() {
        let unit = record.units.get(i).map(String::as_str).unwrap_or("");
        plot::channel(
            dir,
            name,
            unit,
            &format!("{title} — {name}"),
            &record.t,
            &record.traces[i],
        )?;
    }
    Ok(())
}

/// Write `summary.json` into `dir` (created if missing).
pub fn write_summary(dir: &Path, summary: &impl Serialize) -> Result<(), RunRecordError> {
    fs::create_dir_all(dir).map_err(io(dir))?;
    let path = dir.join("summary.json");
    fs::write(&path, serde_json::to_string_pretty(summary)? + "\n").map_err(io(&path))
}
