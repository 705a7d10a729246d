//! Commissioning on the live plant: an operator asks the service to find `α` (and the
//! model's order) for one channel of a device from the plant's own response
//! ([`mfc::commission`]), sees what it found, and confirms or dismisses the law it
//! proposes.
//!
//! The rules, all decided here with the time in the samples:
//! - **Start** (`COMMISSION_START`): only on a channel whose law is intelligent, on a
//!   device under control (its last answer was CONTROL, this member commands it), one run
//!   per device and [`MAX_RUNNING`] per service, with the excitation's amplitude and the
//!   largest deviation of the output both set by the operator and inside [`MAX_CYCLES`]
//!   and [`MAX_PERIOD`]. The run first waits for the loop to settle (the output within a
//!   quarter of that deviation of its reference for a whole period of the square wave, at
//!   most [`SETTLE_PERIODS`] periods), then excites around the input the plant holds.
//! - **While it runs**, the channel's law steps on every sample (its estimator follows
//!   the plant) but the input sent is the run's; the envelope bounds it like any command,
//!   the other channels keep their laws, and no horizon is sent (a plant that misses a
//!   sample holds the square wave's level). The run ends by itself, with a proposal or
//!   with nothing (no fit); it is aborted, and the law in force takes the plant back at
//!   once, if the output leaves `max_deviation`, if the plant falls back, stops or
//!   restarts (holding the level while a command is late is no reason: the sample says
//!   what was applied), if its samples stop for half a period of the square wave, if
//!   this member stops commanding it, or if the device's configuration or envelope
//!   changes.
//! - **Confirm** (`COMMISSION_CONFIRM`): the proposal is put in force like a
//!   configuration change (inside the file's bounds, bumplessly), or refused with why.
//! - **Abort** (`COMMISSION_ABORT`): a run stops, a proposal is dismissed.
//!
//! Each request is decided through the audit trail (`crate::service`): the run's state is
//! one of the device's settings (`channel i commission`), so every entry shows it before
//! and after, and a confirmation shows the gains it changed.

use mfc::{CommissionFinding, CommissionSpec, CommissionStep, Commissioning, LawConfig, Order};
use protocol::convert::channel_to_pb;
use protocol::pb;

/// Runs at once in one service at most: a run holds its estimators' windows (about 20
/// KiB), and commissioning is an operator's deliberate act on a few plants, not a fleet's.
pub const MAX_RUNNING: usize = 16;
/// Periods of the square wave at most.
pub const MAX_CYCLES: u32 = 20;
/// The square wave's period at most (s).
pub const MAX_PERIOD: f64 = 600.0;
/// How long a run waits for its loop to settle before it gives up, in periods of its
/// square wave.
const SETTLE_PERIODS: f64 = 5.0;

/// A run waiting for its loop to settle: the excitation begins once the output has stayed
/// within a quarter of `max_deviation` of its reference, and within a band that wide, for
/// a whole period of the square wave (a run begun in a transient measures the transient,
/// and soon leaves its band),
/// around the mean input the law held over that time (one sample's input carries the
/// law's chatter; a square wave around it would drift the plant away).
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Settle {
    /// Plant time of the first sample waited on.
    pub(super) began: Option<f64>,
    /// Since when the output has been inside the band (`None`: it is not), and its
    /// lowest and highest value since.
    pub(super) inside_since: Option<f64>,
    pub(super) y_range: (f64, f64),
    /// The sum and count of the inputs held since then.
    pub(super) sum_u: f64,
    pub(super) count: u32,
}

/// The operator's reason kept with a run, at most (bytes).
pub(super) const MAX_WHY: usize = 64;
/// A run whose device has sent nothing for this long (Unix ns, as the service heard it)
/// is ended when another start needs its slot.
pub const SILENT_NS: u64 = 10_000_000_000;

/// A device's last commissioning run.
#[derive(Debug, Clone)]
pub(super) struct Commission {
    /// The run's number on its device (1, 2, ...): a confirmation or an abort that names
    /// one acts on that run only.
    pub(super) number: u64,
    pub(super) channel: usize,
    /// The run, once the excitation has begun and until it ends.
    pub(super) run: Option<Box<Commissioning>>,
    /// Before the excitation: waiting for the loop to settle ([`Settle`]).
    pub(super) settle: Option<Settle>,
    pub(super) spec: CommissionSpec,
    pub(super) dynamics: Option<(f64, f64)>,
    pub(super) phase: pb::CommissionPhase,
    pub(super) started_by: String,
    pub(super) ended_by: String,
    /// Why, as the operator said (printable, at most [`MAX_WHY`] bytes).
    pub(super) why: String,
    /// Plant time of the first sample and of the last one seen (s).
    pub(super) t0: Option<f64>,
    pub(super) last_t: f64,
    /// The output at the first sample, and the largest deviation from it seen.
    pub(super) y0: Option<f64>,
    pub(super) deviation: f64,
    pub(super) alpha_before: f64,
    pub(super) finding: Option<CommissionFinding>,
    pub(super) proposed: Option<LawConfig>,
    pub(super) reason: String,
    /// The input sent with the last command (the law's units), what the plant got since
    /// unless its sample says otherwise.
    pub(super) sent_u: f64,
}

impl Commission {
    pub(super) fn running(&self) -> bool {
        self.phase == pb::CommissionPhase::CommissionRunning
    }

    /// Whether the excitation is on (not waiting for the loop to settle, not ended).
    pub(super) fn exciting(&self) -> bool {
        self.run.is_some()
    }

    /// End the run (or dismiss the proposal) without a change.
    pub(super) fn abort(&mut self, by: &str, why: String) {
        self.run = None;
        self.settle = None;
        self.phase = pb::CommissionPhase::CommissionAborted;
        by.clone_into(&mut self.ended_by);
        self.reason = why;
    }

    /// While the run waits for its loop to settle: this sample's time, output, tracking
    /// error and the input the plant holds (the law's units; the excitation is around
    /// their mean). True while it still waits (the law
    /// commands); false once the excitation begins here, or if there was nothing to
    /// wait for. A loop that does not settle within [`SETTLE_PERIODS`] ends the run.
    pub(super) fn settling(&mut self, t: f64, (y, error): (f64, f64), u_held: f64) -> bool {
        let Some(w) = self.settle.as_mut() else {
            return false;
        };
        let began = *w.began.get_or_insert(t);
        // Written so that a NaN error is outside.
        // Near the reference, and still: a transient passing through the band moves
        // more than the band is wide while it does.
        let band = self.spec.max_deviation / 4.0;
        let (lo, hi) = match w.inside_since {
            Some(_) => (w.y_range.0.min(y), w.y_range.1.max(y)),
            None => (y, y),
        };
        let inside = error.abs() <= band && hi - lo <= band && u_held.is_finite();
        if inside {
            w.inside_since.get_or_insert(t);
            (w.y_range, w.sum_u, w.count) = ((lo, hi), w.sum_u + u_held, w.count + 1);
        } else {
            (w.inside_since, w.sum_u, w.count) = (None, 0.0, 0);
        }
        let settled = w.inside_since.is_some_and(|s| t - s >= self.spec.period);
        let u0 = w.sum_u / f64::from(w.count.max(1));
        self.last_t = t;
        if settled {
            match Commissioning::new(self.spec, u0) {
                Ok(run) => {
                    self.run = Some(Box::new(run));
                    self.settle = None;
                    self.sent_u = u0;
                    self.reason.clear();
                    return false;
                }
                Err(e) => self.abort("service", e.to_string()),
            }
        } else if t - began > SETTLE_PERIODS * self.spec.period {
            let waited = t - began;
            self.abort(
                "service",
                format!("the loop did not settle within {waited:.1} s (the output within a quarter of max_deviation of its reference for a period)"),
            );
        }
        true
    }

    /// The input for the channel at this sample (its time `t`, the channel's output `y`,
    /// what the plant says it applied since the last one, in the law's units), or `None`
    /// if the run ends here: its phase then says how.
    pub(super) fn input(&mut self, t: f64, y: f64, applied: Option<f64>) -> Option<f64> {
        let run = self.run.as_mut()?;
        if t - self.last_t > self.spec.period / 2.0 {
            let gap = t - self.last_t;
            self.abort(
                "service",
                format!("the samples stopped for {gap:.3} s, over half the square wave's period"),
            );
            return None;
        }
        self.last_t = t;
        self.t0.get_or_insert(t);
        let y0 = *self.y0.get_or_insert(y);
        self.deviation = self.deviation.max((y - y0).abs());
        let step = run.step(t, y, applied.unwrap_or(self.sent_u));
        match step {
            Ok(CommissionStep::Apply(u)) => return Some(u),
            Ok(CommissionStep::Done(f)) => self.propose(f),
            Ok(CommissionStep::Aborted(a)) => self.abort("service", a.to_string()),
            Err(e) => self.abort("service", format!("the run refused a sample: {e}")),
        }
        None
    }

    /// The input the envelope let through (the law's units).
    pub(super) fn sent(&mut self, u: f64) {
        self.sent_u = u;
    }

    fn propose(&mut self, f: CommissionFinding) {
        self.run = None;
        self.finding = Some(f);
        self.phase = pb::CommissionPhase::CommissionProposed;
    }

    /// The run's state as a setting (`channel i commission`): what the audit shows moving.
    pub(super) fn setting(&self) -> String {
        let phase = match self.phase {
            pb::CommissionPhase::CommissionRunning => "running",
            pb::CommissionPhase::CommissionProposed => "proposed",
            pb::CommissionPhase::CommissionApplied => "applied",
            _ => "aborted",
        };
        let by = match self.ended_by.as_str() {
            "" => format!("started by {}", self.started_by),
            e => format!("started by {}, ended by {e}", self.started_by),
        };
        let found = self
            .finding
            .map(|f| {
                format!(
                    ", alpha {:.4e} (order {})",
                    f.best.alpha,
                    u32::from(f.best.order.n())
                )
            })
            .unwrap_or_default();
        let s = &self.spec;
        let why = match self.why.as_str() {
            "" => String::new(),
            w => format!(", why: {w}"),
        };
        format!(
            "run {} {phase} ({by}{why}): +-{} for {} x {} s, max deviation {}{found}",
            self.number, s.amplitude, s.cycles, s.period, s.max_deviation
        )
    }

    pub(super) fn status_pb(&self, output: mfc::OutputMapConfig) -> pb::CommissionStatus {
        let fits = self.finding.map_or(Vec::new(), |f| {
            f.fits
                .iter()
                .flatten()
                .map(|fit| pb::CommissionFit {
                    order: u32::from(fit.order.n()),
                    alpha: fit.alpha,
                    explained: fit.explained,
                })
                .collect()
        });
        let proposing = matches!(
            self.phase,
            pb::CommissionPhase::CommissionProposed | pb::CommissionPhase::CommissionApplied
        );
        pb::CommissionStatus {
            run: self.number,
            channel: self.channel as u32,
            phase: self.phase as i32,
            started_by: self.started_by.clone(),
            ended_by: self.ended_by.clone(),
            elapsed: self.t0.map_or(0.0, |t0| self.last_t - t0),
            duration: self.spec.duration(),
            deviation: self.deviation,
            alpha_before: self.alpha_before,
            fits,
            proposed: self
                .proposed
                .filter(|_| proposing)
                .map(|law| channel_to_pb(&mfc::ChannelConfig { law, output })),
            reason: self.reason.clone(),
        }
    }
}

/// A start request's specification, checked: every value the operator must set is set,
/// nothing beyond the service's limits.
pub(super) fn spec_of(
    req: &pb::CommissionRequest,
) -> Result<(CommissionSpec, Option<(f64, f64)>), String> {
    let pick = |x: f64, default: f64| if x == 0.0 { default } else { x };
    let d = CommissionSpec::default();
    if !(req.amplitude.is_finite() && req.amplitude > 0.0) {
        return Err("amplitude: set the square wave's half height (> 0, the law's units)".into());
    }
    if !(req.max_deviation.is_finite() && req.max_deviation > 0.0) {
        return Err("max_deviation: set the largest change of the output you accept (> 0)".into());
    }
    let spec = CommissionSpec {
        amplitude: req.amplitude,
        period: pick(req.period, d.period),
        cycles: if req.cycles == 0 {
            d.cycles
        } else {
            req.cycles
        },
        max_deviation: req.max_deviation,
        window: if req.window == 0 {
            d.window
        } else {
            req.window as usize
        },
        order: match req.order {
            0 => None,
            1 => Some(Order::One),
            2 => Some(Order::Two),
            o => return Err(format!("order: {o}; 0 (both), 1 or 2")),
        },
    };
    if spec.cycles > MAX_CYCLES {
        return Err(format!("cycles: {} (at most {MAX_CYCLES})", spec.cycles));
    }
    if !(spec.period.is_finite() && spec.period > 0.0 && spec.period <= MAX_PERIOD) {
        return Err(format!("period: {} s (0 to {MAX_PERIOD} s)", spec.period));
    }
    spec.validate(mfc::DEFAULT_CAPACITY)
        .map_err(|e| e.to_string())?;
    let dynamics = match (req.bandwidth, req.damping) {
        (b, z) if b == 0.0 && z == 0.0 => None,
        (b, z) if b.is_finite() && z.is_finite() && b > 0.0 && z > 0.0 => Some((b, z)),
        (b, z) => {
            return Err(format!(
                "bandwidth {b} and damping {z}: both > 0 to ask for error dynamics, or both 0 to keep the law's"
            ))
        }
    };
    Ok((spec, dynamics))
}

/// What a checked start request gives: the channel, the spec, the error dynamics asked
/// for, `α` in force and the input held (the law's units).
pub(super) struct Start {
    pub(super) channel: usize,
    pub(super) spec: CommissionSpec,
    pub(super) dynamics: Option<(f64, f64)>,
    pub(super) alpha: f64,
    pub(super) u0: f64,
}
