//! The plant agent's safety rules, as a pure state machine.
//!
//! Every period `k` the agent samples the plant, publishes sample `k`, and applies the
//! command the remote controller answers for it. Commands can be late, lost, duplicated
//! (two controllers answering), malformed or refused; the [`Supervisor`] decides, from plain
//! numbers, what to do about each of them:
//!
//! * which command to apply and when (the newest acceptable one, the moment it arrives; a
//!   stale command is worse than none, so anything older than `max_age` periods or older
//!   than one already applied is dropped);
//! * how long to hold the last command when answers stop, and when to fall back (to the
//!   local controller, or to a safe stop);
//! * what to play instead of holding when the last command carried a horizon (packetized
//!   predictive control): in each period without its own command, the element of the last
//!   command's horizon for that period, written at the period's start; and for a command
//!   that lands late, the element for the period it lands in rather than its own `v`;
//! * what mode to report in each sample and each period, and the counters of the run;
//! * the time-weighted mean of what the plant really got over each period (a command that
//!   lands mid-period was applied for part of it only, and the estimators integrate exactly
//!   that), which is also what the local controller is fed so that it is warm and bumpless
//!   the moment it takes over.
//!
//! It does no I/O, no async and reads no clock: time comes in as numbers (the plant time
//! `t = k h` of the period, and each command's arrival as seconds since the period's
//! deadline). That is what makes every rule below testable exhaustively with plain numbers,
//! and what keeps the networked loop in `agent.rs` thin wiring: it owns the clock, the plant
//! and the network, calls these methods in this order, and does what they say:
//!
//! ```text
//! let begin = supervisor.begin_period(k, k as f64 * h, &y, &refs)?;
//! publish sample k with begin.sample_mode and begin.applied_mean;
//! if let Some(v) = begin.write { supervisor.applied(&plant.write(&v)?); }
//! until the next deadline, for each command that arrives (device id checked, decoded):
//!     let (verdict, done) = supervisor.on_command(seconds_since_deadline, command);
//!     if let Verdict::Apply { v, advance, .. } = verdict {
//!         plant.advance(advance)?;
//!         supervisor.applied(&plant.write(&v)?);
//!     }
//!     if done { break; }
//! let end = supervisor.end_period()?;
//! plant.advance(end.advance)?;
//! ```
//!
//! A period begun twice, not after the last one, or ended without being begun is refused
//! with an error that changes nothing, and a command handed over outside a period is only
//! counted (as `Future`): a logic error in the wiring must not corrupt the safety state.

use std::fmt;
use std::str::FromStr;

use mfc::{ChannelConfig, ChannelOutput, MfcError, MimoController, Reference};

use crate::lease::{Credentials, Fence, Lease};
use protocol::MAX_HORIZON;
use serde::{Deserialize, Serialize};

/// Longest `max_age` accepted: beyond a thousand periods a command describes a plant that is
/// long gone.
pub const MAX_AGE_LIMIT: u32 = 1000;
/// Longest `hold_periods` accepted: holding a command for longer is not a safety setting.
const HOLD_PERIODS_LIMIT: u32 = 100_000;

/// What to do when commands stop coming.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FallbackPolicy {
    /// Run the local controller (the same `mfc` core and configuration as the remote one,
    /// stepped every period so that it takes over bumplessly). Written `local`.
    #[serde(rename = "local")]
    LocalController,
    /// Apply zero to every input.
    SafeStop,
}

impl FallbackPolicy {
    /// The name used in files and on the command line (`local`, `safe_stop`).
    pub fn name(self) -> &'static str {
        match self {
            FallbackPolicy::LocalController => "local",
            FallbackPolicy::SafeStop => "safe_stop",
        }
    }
}

impl fmt::Display for FallbackPolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A fallback policy name that is neither `local` nor `safe_stop`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownPolicy(pub String);

impl fmt::Display for UnknownPolicy {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "unknown fallback policy {:?}: expected local or safe_stop",
            self.0
        )
    }
}

impl std::error::Error for UnknownPolicy {}

/// [`FallbackPolicy::from_str`] as a function, for a command line's value parser.
pub fn parse_fallback(s: &str) -> Result<FallbackPolicy, UnknownPolicy> {
    s.parse()
}

impl FromStr for FallbackPolicy {
    type Err = UnknownPolicy;

    /// Accepts the file spelling (`local`, `safe_stop`) and the command-line one
    /// (`safe-stop`), so a CLI can parse the policy without its own enum.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "local" => Ok(FallbackPolicy::LocalController),
            "safe_stop" | "safe-stop" => Ok(FallbackPolicy::SafeStop),
            _ => Err(UnknownPolicy(s.to_string())),
        }
    }
}

/// Who drives the plant: defined with the run's record, which keeps it per period, and
/// decided here, by the [`Supervisor`].
pub use plant::LoopMode;

/// The safety settings of the loop.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SafetyConfig {
    /// Sampling period `h` (s): the plant time between two deadlines.
    pub period: f64,
    /// Oldest command still worth applying, in periods: a command for sample `k - a` may be
    /// applied during period `k` if `a <= max_age` (on a slow link the newest command is
    /// still the best there is; beyond this age it is stale and dropped).
    pub max_age: u32,
    /// Periods to hold the last command before falling back: the fallback engages at the
    /// start of the period after `max(hold_periods, 1)` consecutive periods without an
    /// answer (a period cannot be known to be missing before it has ended).
    pub hold_periods: u32,
    /// What to fall back to.
    pub fallback: FallbackPolicy,
}

impl SafetyConfig {
    /// Default oldest command still applied, in periods (100 ms at 10 ms): later than that a
    /// command describes a plant that has moved on.
    pub const DEFAULT_MAX_AGE: u32 = 10;
    /// Default periods held before the fallback (50 ms at 10 ms): long enough to ride out a
    /// lost packet or a scheduling hiccup, short enough that a held voltage does no harm.
    pub const DEFAULT_HOLD_PERIODS: u32 = 5;

    /// Check the settings: a period that is finite and positive, `max_age <= 1000`,
    /// `hold_periods <= 100_000`.
    pub fn validate(&self) -> Result<(), SafetyError> {
        if !(self.period.is_finite() && self.period > 0.0) {
            return Err(SafetyError::InvalidConfig {
                field: "period",
                reason: "must be finite and > 0 s",
            });
        }
        if self.max_age > MAX_AGE_LIMIT {
            return Err(SafetyError::InvalidConfig {
                field: "max_age",
                reason: "must be at most 1000 periods",
            });
        }
        if self.hold_periods > HOLD_PERIODS_LIMIT {
            return Err(SafetyError::InvalidConfig {
                field: "hold_periods",
                reason: "must be at most 100000 periods",
            });
        }
        Ok(())
    }
}

/// Why the supervisor refused a call. After an error nothing has changed.
#[derive(Debug, Clone, PartialEq)]
pub enum SafetyError {
    /// A setting is out of range.
    InvalidConfig {
        /// Which setting.
        field: &'static str,
        /// What was expected.
        reason: &'static str,
    },
    /// The local controller's configuration was refused.
    Controller(MfcError),
    /// A slice does not have one entry per channel.
    ChannelMismatch {
        /// Which slice (`"y"`, `"refs"`, `"initial_applied"`).
        what: &'static str,
        /// Number of channels.
        expected: usize,
        /// Length that was passed.
        got: usize,
    },
    /// The initial applied values are NaN or infinite.
    NonFiniteApplied,
    /// A safe input is NaN or infinite.
    NonFiniteSafe,
    /// `begin_period` while a period is open (its `end_period` is missing).
    PeriodOpen {
        /// The open period.
        open: u64,
    },
    /// `begin_period` with a period number not after the previous one.
    PeriodNotIncreasing {
        /// The previous period.
        previous: u64,
        /// The period that was refused.
        k: u64,
    },
    /// `end_period` without an open period.
    NoOpenPeriod,
}

impl fmt::Display for SafetyError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SafetyError::InvalidConfig { field, reason } => write!(f, "{field} {reason}"),
            SafetyError::Controller(e) => write!(f, "local controller: {e}"),
            SafetyError::ChannelMismatch {
                what,
                expected,
                got,
            } => write!(f, "{what} has {got} entries for {expected} channels"),
            SafetyError::NonFiniteApplied => f.write_str("initial applied values must be finite"),
            SafetyError::NonFiniteSafe => f.write_str("safe inputs must be finite"),
            SafetyError::PeriodOpen { open } => {
                write!(f, "period {open} is still open: end it before the next one")
            }
            SafetyError::PeriodNotIncreasing { previous, k } => {
                write!(f, "period {k} does not come after period {previous}")
            }
            SafetyError::NoOpenPeriod => f.write_str("no period is open"),
        }
    }
}

impl std::error::Error for SafetyError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            SafetyError::Controller(e) => Some(e),
            _ => None,
        }
    }
}

impl From<MfcError> for SafetyError {
    fn from(e: MfcError) -> Self {
        SafetyError::Controller(e)
    }
}

/// What a command says, once the wiring has decoded it and checked its device id.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CommandBody<'a> {
    /// Apply these inputs (one per channel).
    Control(&'a [f64]),
    /// The controller is alive but still filling its estimation window.
    WarmingUp,
    /// The controller refused the sample (the reason, for the wiring's log).
    Rejected(&'a str),
    /// A mode this agent does not know.
    Unknown,
}

/// A command as the supervisor judges it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IncomingCommand<'a> {
    /// The sample it answers.
    pub seq: u64,
    /// What it says.
    pub body: CommandBody<'a>,
    /// For a control: the inputs predicted for the samples after `seq`, period-major
    /// (`[j * n + i]`: input `i` for sample `seq + 1 + j`); empty for none.
    pub horizon: &'a [f64],
    /// Who sent it and under which lease (judged only by a supervisor that grants
    /// leases, see [`Supervisor::grant_leases`]).
    pub lease: Credentials<'a>,
}

/// Why a command was dropped.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Ignored {
    /// It answers a sample not published yet (or arrived outside a period).
    Future,
    /// It answers the sample whose command was applied last (a second controller answering).
    Duplicate,
    /// A command for a later sample has already been applied.
    Superseded,
    /// More than `max_age` periods old.
    TooOld,
    /// Wrong number of inputs, a NaN or infinite input, a horizon that is not whole
    /// periods of finite inputs or is longer than [`MAX_HORIZON`], or an unknown mode.
    Malformed,
    /// Refused by the plant's command lease: not from its holder, under another epoch, or
    /// for another run (see [`crate::lease`]).
    Fenced(Fence),
}

/// What the wiring must do with a command.
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// Let `advance` seconds of plant time pass with the old inputs (from the end of the last
    /// segment to the command's arrival), then write `v` and report what was applied.
    Apply {
        /// The inputs to write.
        v: Vec<f64>,
        /// Plant time (s) to let pass before writing.
        advance: f64,
        /// The command answers an earlier sample than the current one.
        late: bool,
    },
    /// The controller is alive but not ready: nothing to write.
    WarmingUp,
    /// The controller refused the sample: nothing to write (log it).
    Rejected,
    /// Dropped, and why.
    Ignored(Ignored),
}

/// The counters of a run. Every command handed to [`Supervisor::on_command`] is counted in
/// exactly one of `commands`, `too_old`, `superseded`, `duplicates`, `warming_up`,
/// `rejected`, `malformed`, `fenced` and `future` (`late` is a subset of `commands`).
///
/// Deliberately not `Copy` (fifteen counters): copies are explicit `clone()`s.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct SupervisorCounters {
    /// Periods ended.
    pub periods: u64,
    /// Commands applied.
    pub commands: u64,
    /// Commands applied after their own period (at most `max_age` periods late).
    pub late: u64,
    /// Periods that ended with neither a command applied nor a warming-up answer.
    pub missing: u64,
    /// Commands dropped as more than `max_age` periods old.
    pub too_old: u64,
    /// Commands dropped because a newer one had already been applied.
    pub superseded: u64,
    /// Answers for the sample whose command was applied last (two controllers answering).
    pub duplicates: u64,
    /// Answers saying the controller is still filling its estimation window.
    pub warming_up: u64,
    /// Samples the controller refused.
    pub rejected: u64,
    /// Commands with the wrong number of inputs, a non-finite input or an unknown mode.
    pub malformed: u64,
    /// Commands for a sample not published yet.
    pub future: u64,
    /// Times the fallback engaged (entries into Local or SafeStop, not periods).
    pub fallbacks: u64,
    /// Periods spent holding a command.
    pub holding_periods: u64,
    /// Periods driven by the local controller.
    pub local_periods: u64,
    /// Periods in safe stop.
    pub safe_stop_periods: u64,
    /// Periods without their own command that were driven by an element of the last
    /// command's horizon instead of a held value (a subset of `holding_periods`).
    #[serde(default)]
    pub horizon_periods: u64,
    /// Late commands applied with the element of their horizon for the period they landed
    /// in (a subset of `late`).
    #[serde(default)]
    pub horizon_late: u64,
    /// Commands refused by the plant's command lease (from another controller than its
    /// holder, under another epoch, or for another run); the lease counts them by reason.
    #[serde(default)]
    pub fenced: u64,
}

/// What to do at the start of a period.
#[derive(Debug, Clone, PartialEq)]
pub struct PeriodBegin {
    /// The mode to put in the sample's flags: the mode at sampling time, before this
    /// period's decisions.
    pub sample_mode: LoopMode,
    /// Time-weighted mean of what the plant applied over the last period (the initial
    /// applied value for the first period), for the sample.
    pub applied_mean: Vec<f64>,
    /// Inputs to write now, at the start of the period: the fallback's, if it is engaged,
    /// or else the last command's horizon element for this period, if it has one.
    pub write: Option<Vec<f64>>,
}

/// What to do at the end of a period.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeriodEnd {
    /// The mode of the period (for the record; already counted).
    pub mode: LoopMode,
    /// Plant time (s) still to let pass in this period, with the inputs applied now.
    pub advance: f64,
    /// The period had neither a command nor a warming-up answer.
    pub missing: bool,
}

/// The state of the open period.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Period {
    k: u64,
    /// The fallback mode written at the start of the period, if any.
    fallback: Option<LoopMode>,
    /// A command was applied during the period.
    got: bool,
    /// A warming-up answer came during the period.
    warming: bool,
    /// A horizon element was written at the start of the period.
    planned: bool,
    /// Seconds since the deadline up to which the plant has been integrated; also the
    /// start of the segment the current inputs were applied over.
    elapsed: f64,
}

/// The safety state machine of the plant agent (see the module documentation).
#[derive(Debug, Clone)]
pub struct Supervisor {
    config: SafetyConfig,
    local: MimoController,
    local_out: Vec<ChannelOutput>,
    mode: LoopMode,
    counters: SupervisorCounters,
    missing_streak: u32,
    last_applied_seq: Option<u64>,
    /// What the plant applies now.
    applied: Vec<f64>,
    /// Sum of `applied * duration` over the closed segments of the open period.
    segments: Vec<f64>,
    /// Time-weighted mean of what was applied over the last period ended.
    mean: Vec<f64>,
    period: Option<Period>,
    last_k: Option<u64>,
    /// The horizon of the last command applied (`[j * n + i]` for sample
    /// `last_applied_seq + 1 + j`); emptied when the fallback engages.
    plan: Vec<f64>,
    /// The plant's command lease, once [`Supervisor::grant_leases`] turned it on.
    lease: Option<Lease>,
    /// What the safe stop applies ([`Supervisor::set_safe_inputs`]).
    safe: Vec<f64>,
}

impl Supervisor {
    /// A supervisor with checked settings and a local controller built from `channels`.
    /// `initial_applied` is what the plant reported after the agent wrote zeros at start
    /// (one finite value per channel).
    pub fn new(
        config: SafetyConfig,
        channels: &[ChannelConfig],
        initial_applied: Vec<f64>,
    ) -> Result<Self, SafetyError> {
        config.validate()?;
        let local = MimoController::new(channels)?;
        let n = channels.len();
        if initial_applied.len() != n {
            return Err(SafetyError::ChannelMismatch {
                what: "initial_applied",
                expected: n,
                got: initial_applied.len(),
            });
        }
        if !initial_applied.iter().all(|v| v.is_finite()) {
            return Err(SafetyError::NonFiniteApplied);
        }
        Ok(Self {
            config,
            local,
            local_out: vec![ChannelOutput::default(); n],
            mode: LoopMode::Remote,
            counters: SupervisorCounters::default(),
            missing_streak: 0,
            last_applied_seq: None,
            mean: initial_applied.clone(),
            applied: initial_applied,
            segments: vec![0.0; n],
            period: None,
            last_k: None,
            plan: Vec::new(),
            lease: None,
            safe: vec![0.0; n],
        })
    }

    /// The inputs the safe stop applies, one finite value per channel (default: zero;
    /// a bridge's map may name others, [`plant::scenario::Scenario::safe_inputs`]).
    pub fn set_safe_inputs(&mut self, safe: Vec<f64>) -> Result<(), SafetyError> {
        if safe.len() != self.safe.len() {
            return Err(SafetyError::ChannelMismatch {
                what: "safe inputs",
                expected: self.safe.len(),
                got: safe.len(),
            });
        }
        if !safe.iter().all(|v| v.is_finite()) {
            return Err(SafetyError::NonFiniteSafe);
        }
        self.safe = safe;
        Ok(())
    }

    /// Judge every later command by the plant's command lease of run `run_id` too (see
    /// [`crate::lease`]): the agent always does; without it, as before leases, any
    /// controller's command that passes the other rules is applied (the bench's lockstep
    /// simulator, which has one controller, and the unit tests of the other rules).
    pub fn grant_leases(&mut self, run_id: u64) {
        self.lease = Some(Lease::new(run_id));
    }

    /// Periods without an answer of the holder after which the lease lapses: half the
    /// hold, rounded up, at least one (so never after the fallback would engage).
    pub fn lease_lapse(&self) -> u32 {
        self.config.hold_periods.div_ceil(2).max(1)
    }

    /// The command lease, if this supervisor grants one.
    pub fn lease(&self) -> Option<&Lease> {
        self.lease.as_ref()
    }

    /// The last command's horizon element for period `k`, if it reaches that far.
    fn plan_for(&self, k: u64) -> Option<&[f64]> {
        let n = self.applied.len();
        let j = k.checked_sub(self.last_applied_seq?)?.checked_sub(1)? as usize;
        self.plan.get(j * n..(j + 1) * n)
    }

    /// Start period `k` at plant time `t` with the outputs `y` just read and the references
    /// at `t`.
    ///
    /// The local controller is stepped every period, fed the mean of what was really applied
    /// over the last one, so that it is warm when it has to take over. If commands have been
    /// missing for `max(hold_periods, 1)` periods, or the fallback is already engaged, the
    /// fallback is applied now, at the start of the period, without waiting for a command
    /// that is not coming: the local controller's output, or zeros if the policy says so or
    /// the local controller cannot run (non-finite `y`, say).
    pub fn begin_period(
        &mut self,
        k: u64,
        t: f64,
        y: &[f64],
        refs: &[Reference],
    ) -> Result<PeriodBegin, SafetyError> {
        if let Some(p) = &self.period {
            return Err(SafetyError::PeriodOpen { open: p.k });
        }
        if let Some(previous) = self.last_k.filter(|&previous| k <= previous) {
            return Err(SafetyError::PeriodNotIncreasing { previous, k });
        }
        let n = self.channels();
        for (what, got) in [("y", y.len()), ("refs", refs.len())] {
            if got != n {
                return Err(SafetyError::ChannelMismatch {
                    what,
                    expected: n,
                    got,
                });
            }
        }
        let sample_mode = self.mode;
        if self.last_k.is_some() {
            // Only non-finite values are refused, and `mean` is finite by construction.
            let _ = self.local.report_applied(&self.mean);
        }
        let local_ok = self.local.step(t, y, refs, &mut self.local_out).is_ok()
            && self.local_out.iter().all(|o| o.v.is_finite());
        self.last_k = Some(k);
        self.segments.iter_mut().for_each(|s| *s = 0.0);
        let mut period = Period {
            k,
            fallback: None,
            got: false,
            warming: false,
            planned: false,
            elapsed: 0.0,
        };
        let due = self.missing_streak > 0 && self.missing_streak >= self.config.hold_periods;
        // The holder has been silent for half the hold: the lease lapses, so that another
        // controller can claim it (a new epoch) while the plant still holds, before the
        // fallback engages. A holder that answers "warming up" is not silent: it keeps the
        // lease while the fallback runs (the watchdog counts those periods, the lease not).
        let lapse = self.lease_lapse();
        if let Some(lease) = self.lease.as_mut().filter(|l| l.idle() >= lapse) {
            lease.lapse();
        }
        let write = if self.mode.is_fallback() || due {
            let (mode, v) = match (self.config.fallback, local_ok) {
                (FallbackPolicy::LocalController, true) => (
                    LoopMode::Local,
                    self.local_out.iter().map(|o| o.v).collect(),
                ),
                _ => (LoopMode::SafeStop, self.safe.clone()),
            };
            if !self.mode.is_fallback() {
                bump(&mut self.counters.fallbacks);
            }

            self.mode = mode;
            period.fallback = Some(mode);
            // A horizon is the remote controller's: it never plays under the fallback.
            self.plan.clear();
            // Until the plant reports otherwise, assume the write took effect as given.
            self.applied.clone_from(&v);
            Some(v)
        } else if let Some(v) = self.plan_for(k).map(<[f64]>::to_vec) {
            // The remote controller's prediction for this period, until (if) the period's
            // own command lands.
            period.planned = true;
            self.applied.clone_from(&v);
            Some(v)
        } else {
            None
        };
        self.period = Some(period);
        Ok(PeriodBegin {
            sample_mode,
            applied_mean: self.mean.clone(),
            write,
        })
    }

    /// The plant reports what it really applied after a write (the fallback's, at the start
    /// of the period, or an [`Verdict::Apply`]'s, at that command's arrival): it holds from
    /// that instant on, and replaces the value written for the segment. A report of the
    /// wrong length or with a non-finite value cannot be what the plant drives and is
    /// ignored (the value written stands).
    pub fn applied(&mut self, applied: &[f64]) {
        if applied.len() == self.applied.len() && applied.iter().all(|v| v.is_finite()) {
            self.applied.copy_from_slice(applied);
        }
    }

    /// Judge a command that arrived `at` seconds after this period's deadline (clamped into
    /// the part of the period not yet integrated; before the deadline counts as 0, an
    /// unknown time as now). Returns the verdict and whether the wiring can stop waiting:
    /// the period's own sample has been answered (applied, warming up or rejected).
    ///
    /// In order: a command for a sample not published yet is `Future`; one for the sample
    /// applied last is a `Duplicate`; one older than that is `Superseded`; one more than
    /// `max_age` periods old is `TooOld`; then a control with the wrong number of inputs or
    /// a non-finite one, or an unknown mode, is `Malformed`. What is left is applied, or
    /// is a warming-up answer (the controller is alive: not a missing command, but nothing
    /// to apply), or a refusal (counted, nothing else changes: a refusal is not an answer
    /// that keeps the plant safe). Outside a period nothing can be applied: `Future`.
    pub fn on_command(&mut self, at: f64, cmd: IncomingCommand<'_>) -> (Verdict, bool) {
        let n = self.applied.len();
        let h = self.config.period;
        let Some(k) = self.period.map(|p| p.k) else {
            return self.ignore(Ignored::Future);
        };
        let seq = cmd.seq;
        // The lease first: a command from anyone but the holder is refused as such,
        // whatever else is wrong with it.
        let pass = match self.lease.as_mut().filter(|_| seq <= k) {
            Some(lease) => match lease.check(&cmd.lease) {
                Ok(pass) => Some(pass),
                Err(fence) => return self.ignore(Ignored::Fenced(fence)),
            },
            None => None,
        };
        if let Some(why) = self.rule_out(k, &cmd) {
            return self.ignore(why);
        }
        let Some(p) = self.period.as_mut() else {
            return (Verdict::Ignored(Ignored::Future), false);
        };
        let own = seq == k;
        let verdict = match cmd.body {
            CommandBody::Control(v) => {
                // Late, with a horizon: the element for the period it lands in (the last
                // one if the horizon is shorter than the delay).
                let periods = cmd.horizon.len() / n.max(1);
                let v = if own || periods == 0 {
                    v
                } else {
                    bump(&mut self.counters.horizon_late);
                    let j = ((k - seq) as usize).min(periods) - 1;
                    &cmd.horizon[j * n..(j + 1) * n]
                };
                let at = if at.is_nan() {
                    p.elapsed
                } else {
                    at.max(p.elapsed).min(h)
                };
                let advance = at - p.elapsed;
                for (s, a) in self.segments.iter_mut().zip(&self.applied) {
                    *s += a * advance;
                }
                p.elapsed = at;
                p.got = true;
                // Until the plant reports otherwise, assume the write took effect as given.
                self.applied.copy_from_slice(v);
                self.last_applied_seq = Some(seq);
                self.plan.clear();
                self.plan.extend_from_slice(cmd.horizon);
                self.mode = LoopMode::Remote;
                self.missing_streak = 0;
                bump(&mut self.counters.commands);
                if !own {
                    bump(&mut self.counters.late);
                }
                Verdict::Apply {
                    v: v.to_vec(),
                    advance,
                    late: !own,
                }
            }
            CommandBody::WarmingUp => {
                p.warming = true;
                if self.last_applied_seq.is_none() {
                    self.missing_streak = 0;
                }
                bump(&mut self.counters.warming_up);
                Verdict::WarmingUp
            }
            CommandBody::Rejected(_) => {
                bump(&mut self.counters.rejected);
                Verdict::Rejected
            }
            // Refused above as malformed.
            CommandBody::Unknown => return (Verdict::Ignored(Ignored::Malformed), false),
        };
        // A refusal is no answer that keeps the plant safe: it neither claims nor releases.
        if let (Some(lease), Some(pass)) = (&mut self.lease, pass) {
            if verdict != Verdict::Rejected {
                let applied = matches!(verdict, Verdict::Apply { .. }).then_some(k);
                lease.accepted(pass, &cmd.lease, applied);
            }
        }
        (verdict, own)
    }

    /// Why the rules of [`Supervisor::on_command`] drop a command for period `k`, if they
    /// do (the lease aside).
    fn rule_out(&self, k: u64, cmd: &IncomingCommand<'_>) -> Option<Ignored> {
        let (n, seq) = (self.applied.len(), cmd.seq);
        if seq > k {
            Some(Ignored::Future)
        } else if self.last_applied_seq == Some(seq) {
            Some(Ignored::Duplicate)
        } else if self.last_applied_seq.is_some_and(|last| seq < last) {
            Some(Ignored::Superseded)
        } else if k - seq > u64::from(self.config.max_age) {
            Some(Ignored::TooOld)
        } else {
            match cmd.body {
                CommandBody::Control(v) if v.len() != n || !v.iter().all(|x| x.is_finite()) => {
                    Some(Ignored::Malformed)
                }
                CommandBody::Control(_)
                    if cmd.horizon.len() % n.max(1) != 0
                        || cmd.horizon.len() > MAX_HORIZON as usize * n
                        || !cmd.horizon.iter().all(|x| x.is_finite()) =>
                {
                    Some(Ignored::Malformed)
                }
                CommandBody::Unknown => Some(Ignored::Malformed),
                _ => None,
            }
        }
    }

    /// Count a dropped command under its reason.
    fn ignore(&mut self, why: Ignored) -> (Verdict, bool) {
        let c = &mut self.counters;
        bump(match why {
            Ignored::Future => &mut c.future,
            Ignored::Duplicate => &mut c.duplicates,
            Ignored::Superseded => &mut c.superseded,
            Ignored::TooOld => &mut c.too_old,
            Ignored::Malformed => &mut c.malformed,
            Ignored::Fenced(_) => &mut c.fenced,
        });
        (Verdict::Ignored(why), false)
    }

    /// Close the period: count it as missing if neither a command nor a warming-up answer
    /// came (after the first missing periods the mode becomes Holding, unless the fallback
    /// engages at the next start anyway), decide and count the period's mode, and finalise
    /// the time-weighted mean for the next sample.
    ///
    /// The period's mode is the fallback's if it wrote at the start and no command came,
    /// Holding if the period was missing while holding, Remote otherwise.
    pub fn end_period(&mut self) -> Result<PeriodEnd, SafetyError> {
        let p = self.period.take().ok_or(SafetyError::NoOpenPeriod)?;
        if let Some(lease) = &mut self.lease {
            lease.end_period();
        }
        let h = self.config.period;
        let missing = !p.got && !p.warming;
        // Once a command was applied in this run, a warming-up answer does not stop the
        // watchdog: a controller that lost its state cannot vouch for the command held.
        let silent = !p.got && (!p.warming || self.last_applied_seq.is_some());
        if missing {
            bump(&mut self.counters.missing);
        }
        if silent {
            self.missing_streak = self.missing_streak.saturating_add(1);
            if self.mode == LoopMode::Remote
                && self.missing_streak < self.config.hold_periods.max(1)
            {
                self.mode = LoopMode::Holding;
            }
        }
        let mode = match p.fallback {
            Some(fallback) if !p.got => fallback,
            _ if silent && self.mode == LoopMode::Holding => LoopMode::Holding,
            _ => LoopMode::Remote,
        };
        let c = &mut self.counters;
        if silent && p.planned && mode == LoopMode::Holding {
            bump(&mut c.horizon_periods);
        }
        match mode {
            LoopMode::Holding => bump(&mut c.holding_periods),
            LoopMode::Local => bump(&mut c.local_periods),
            LoopMode::SafeStop => bump(&mut c.safe_stop_periods),
            LoopMode::Remote => {}
        }
        bump(&mut c.periods);
        let advance = h - p.elapsed;
        for ((m, s), a) in self.mean.iter_mut().zip(&self.segments).zip(&self.applied) {
            *m = (s + a * advance) / h;
        }
        Ok(PeriodEnd {
            mode,
            advance,
            missing,
        })
    }

    /// Who drives the plant now.
    pub fn mode(&self) -> LoopMode {
        self.mode
    }

    /// The counters so far.
    pub fn counters(&self) -> &SupervisorCounters {
        &self.counters
    }

    /// What the plant applies now (as last reported, or as last written).
    pub fn applied_now(&self) -> &[f64] {
        &self.applied
    }

    /// Consecutive periods without an answer (a command or a warming-up reply).
    pub fn missing_streak(&self) -> u32 {
        self.missing_streak
    }

    /// The sample whose command was applied last.
    pub fn last_applied_seq(&self) -> Option<u64> {
        self.last_applied_seq
    }

    /// Number of channels.
    pub fn channels(&self) -> usize {
        self.applied.len()
    }

    /// The settings.
    pub fn config(&self) -> &SafetyConfig {
        &self.config
    }
}

/// Counters cannot realistically overflow, but a saturating add keeps the no-panic promise
/// unconditional.
fn bump(c: &mut u64) {
    *c = c.saturating_add(1);
}

#[cfg(test)]
mod tests {
    use super::*;
    use mfc::{ControllerKind, LawConfig, Order, OutputMapConfig};

    const H: f64 = 0.5;

    fn channel() -> ChannelConfig {
        ChannelConfig {
            law: LawConfig::intelligent(ControllerKind::P, Order::One, 2.0, [3.0, 0.0, 0.0], 3),
            output: OutputMapConfig {
                dead_zone: 0.0,
                smoothing: 0.0,
                min: -24.0,
                max: 24.0,
                rate_limit: None,
            },
        }
    }

    fn config(max_age: u32, hold_periods: u32, fallback: FallbackPolicy) -> SafetyConfig {
        SafetyConfig {
            period: H,
            max_age,
            hold_periods,
            fallback,
        }
    }

    fn sup_n(n: usize, max_age: u32, hold: u32, fallback: FallbackPolicy) -> Supervisor {
        Supervisor::new(
            config(max_age, hold, fallback),
            &vec![channel(); n],
            vec![0.0; n],
        )
        .unwrap()
    }

    fn sup(max_age: u32, hold: u32, fallback: FallbackPolicy) -> Supervisor {
        sup_n(1, max_age, hold, fallback)
    }

    fn refs(n: usize) -> Vec<Reference> {
        vec![Reference::constant(1.0); n]
    }

    fn ctl(seq: u64, v: &[f64]) -> IncomingCommand<'_> {
        IncomingCommand {
            seq,
            body: CommandBody::Control(v),
            horizon: &[],
            lease: Credentials::default(),
        }
    }

    fn warm(seq: u64) -> IncomingCommand<'static> {
        IncomingCommand {
            seq,
            body: CommandBody::WarmingUp,
            horizon: &[],
            lease: Credentials::default(),
        }
    }

    fn rejected(seq: u64) -> IncomingCommand<'static> {
        IncomingCommand {
            seq,
            body: CommandBody::Rejected("no"),
            horizon: &[],
            lease: Credentials::default(),
        }
    }

    /// Begin period k with y = 0.1 k on every channel, applying any fallback write exactly.
    fn begin(s: &mut Supervisor, k: u64) -> PeriodBegin {
        let n = s.channels();
        let b = s
            .begin_period(k, k as f64 * H, &vec![0.1 * k as f64; n], &refs(n))
            .unwrap();
        if let Some(v) = &b.write {
            s.applied(v);
        }
        b
    }

    /// Hand a command to the supervisor, applying it exactly if it is to be applied.
    fn command(s: &mut Supervisor, at: f64, cmd: IncomingCommand<'_>) -> (Verdict, bool) {
        let r = s.on_command(at, cmd);
        if let Verdict::Apply { v, .. } = &r.0 {
            s.applied(v);
        }
        r
    }

    /// A whole period with an optional on-time command at 0.2 s.
    fn period(s: &mut Supervisor, k: u64, v: Option<f64>) -> (PeriodBegin, PeriodEnd) {
        let b = begin(s, k);
        if let Some(v) = v {
            let cmd = vec![v; s.channels()];
            let (verdict, done) = command(s, 0.2, ctl(k, &cmd));
            assert!(
                matches!(verdict, Verdict::Apply { .. }) && done,
                "{verdict:?}"
            );
        }
        (b, s.end_period().unwrap())
    }

    fn ignored(s: &mut Supervisor, cmd: IncomingCommand<'_>) -> Ignored {
        let before = format!("{:?}", (s.mode, s.missing_streak, s.last_applied_seq));
        let applied = s.applied.clone();
        match s.on_command(0.1, cmd) {
            (Verdict::Ignored(why), false) => {
                assert_eq!(
                    before,
                    format!("{:?}", (s.mode, s.missing_streak, s.last_applied_seq))
                );
                assert_eq!(applied, s.applied);
                why
            }
            other => panic!("expected to be ignored: {other:?}"),
        }
    }

    fn total(c: &SupervisorCounters) -> u64 {
        c.commands
            + c.too_old
            + c.superseded
            + c.duplicates
            + c.warming_up
            + c.rejected
            + c.malformed
            + c.fenced
            + c.future
    }

    fn planned<'a>(seq: u64, v: &'a [f64], horizon: &'a [f64]) -> IncomingCommand<'a> {
        IncomingCommand {
            seq,
            body: CommandBody::Control(v),
            horizon,
            lease: Credentials::default(),
        }
    }

    // ---- the horizon (packetized predictive control) ----

    #[test]
    fn lost_commands_are_replaced_by_their_elements_of_the_last_horizon() {
        // Two channels; command 3 carries three periods: 4 -> (1, 2), 5 -> (3, 4), 6 -> (5, 6).
        let mut s = sup_n(2, 10, 5, FallbackPolicy::LocalController);
        for k in 0..3 {
            period(&mut s, k, Some(0.5));
        }
        begin(&mut s, 3);
        let h = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let (verdict, done) = command(&mut s, 0.1, planned(3, &[9.0, 9.5], &h));
        assert!(done && matches!(verdict, Verdict::Apply { ref v, .. } if v == &[9.0, 9.5]));
        s.end_period().unwrap();
        // Commands 4 and 5 are lost: each period starts on its element, not on the hold.
        for (k, want) in [(4, [1.0, 2.0]), (5, [3.0, 4.0]), (6, [5.0, 6.0])] {
            let b = begin(&mut s, k);
            assert_eq!(b.write.as_deref(), Some(&want[..]), "period {k}");
            assert_eq!(s.applied_now(), &want);
            let end = s.end_period().unwrap();
            assert!(end.missing);
            assert_eq!(end.mode, LoopMode::Holding);
        }
        // What each period applied is what the next sample reports: the estimator's input.
        let b = begin(&mut s, 7);
        assert_eq!(b.applied_mean, vec![5.0, 6.0]);
        // Past the horizon: the last value is held until the fallback is due (hold 5).
        assert_eq!(b.write, None);
        s.end_period().unwrap();
        let c = s.counters();
        assert_eq!((c.horizon_periods, c.holding_periods, c.missing), (3, 4, 4));
        let b = begin(&mut s, 8);
        assert_eq!(b.write, None);
        s.end_period().unwrap();
        let b = begin(&mut s, 9);
        assert_eq!(s.mode(), LoopMode::Local, "{b:?}");
        assert_eq!(s.counters().fallbacks, 1);
    }

    #[test]
    fn the_mean_applied_over_a_period_counts_the_element_until_the_own_command_lands() {
        let mut s = sup(10, 5, FallbackPolicy::LocalController);
        begin(&mut s, 0);
        command(&mut s, 0.0, planned(0, &[2.0], &[4.0, 6.0]));
        s.end_period().unwrap();
        // Period 1: the element (4) from the deadline, the own command (8) from 0.1 s on.
        let b = begin(&mut s, 1);
        assert_eq!(b.write, Some(vec![4.0]));
        command(&mut s, 0.1, planned(1, &[8.0], &[]));
        s.end_period().unwrap();
        let b = begin(&mut s, 2);
        let want = (4.0 * 0.1 + 8.0 * (H - 0.1)) / H;
        assert!((b.applied_mean[0] - want).abs() < 1e-12, "{b:?}");
        // Command 1 had no horizon: period 2 holds 8, nothing is written.
        assert_eq!(b.write, None);
        assert_eq!(s.counters().horizon_periods, 0);
    }

    #[test]
    fn a_late_command_applies_the_element_for_the_period_it_lands_in() {
        let mut s = sup(10, 100, FallbackPolicy::LocalController);
        for k in 0..3 {
            begin(&mut s, k);
            s.end_period().unwrap();
        }
        begin(&mut s, 3);
        // Command 0 lands in period 3: element 3 - 0 - 1 = 2 of its horizon.
        let (verdict, _) = command(&mut s, 0.1, planned(0, &[1.0], &[2.0, 3.0, 4.0, 5.0]));
        assert!(matches!(verdict, Verdict::Apply { ref v, late: true, .. } if v == &[4.0]));
        assert_eq!(s.counters().horizon_late, 1);
        s.end_period().unwrap();
        // Its next element plays in period 4.
        assert_eq!(begin(&mut s, 4).write, Some(vec![5.0]));
        s.end_period().unwrap();
        // A command later than its horizon is long applies the last element.
        begin(&mut s, 5);
        s.end_period().unwrap();
        begin(&mut s, 6);
        let (verdict, _) = command(&mut s, 0.1, planned(2, &[1.0], &[7.0, 8.0]));
        assert!(matches!(verdict, Verdict::Apply { ref v, .. } if v == &[8.0]));
    }

    #[test]
    fn the_safe_stop_applies_the_plants_own_safe_inputs() {
        let mut s = sup_n(2, 10, 1, FallbackPolicy::SafeStop);
        assert!(matches!(
            s.set_safe_inputs(vec![0.5]),
            Err(SafetyError::ChannelMismatch {
                expected: 2,
                got: 1,
                ..
            })
        ));
        assert!(matches!(
            s.set_safe_inputs(vec![0.5, f64::NAN]),
            Err(SafetyError::NonFiniteSafe)
        ));
        s.set_safe_inputs(vec![0.5, -2.0]).unwrap();
        begin(&mut s, 0);
        command(&mut s, 0.1, ctl(0, &[1.0, 1.0]));
        s.end_period().unwrap();
        begin(&mut s, 1);
        s.end_period().unwrap();
        // The controller is silent: the fallback writes the safe inputs, not zeros.
        assert_eq!(begin(&mut s, 2).write, Some(vec![0.5, -2.0]));
        assert_eq!(s.mode(), LoopMode::SafeStop);
    }

    #[test]
    fn a_bad_horizon_makes_the_command_malformed_and_the_fallback_clears_it() {
        let mut s = sup_n(2, 10, 1, FallbackPolicy::SafeStop);
        begin(&mut s, 0);
        let v = [1.0, 1.0];
        assert_eq!(
            ignored(&mut s, planned(0, &v, &[1.0, 2.0, 3.0])),
            Ignored::Malformed
        );
        assert_eq!(
            ignored(&mut s, planned(0, &v, &[1.0, f64::NAN])),
            Ignored::Malformed
        );
        let long = vec![0.0; 2 * (MAX_HORIZON as usize + 1)];
        assert_eq!(ignored(&mut s, planned(0, &v, &long)), Ignored::Malformed);
        // A whole horizon is accepted; then the link dies and the safe stop engages.
        command(&mut s, 0.1, planned(0, &v, &[2.0, 2.0, 3.0, 3.0, 4.0, 4.0]));
        s.end_period().unwrap();
        assert_eq!(begin(&mut s, 1).write, Some(vec![2.0, 2.0]));
        s.end_period().unwrap();
        assert_eq!(begin(&mut s, 2).write, Some(vec![0.0, 0.0]));
        assert_eq!(s.mode(), LoopMode::SafeStop);
        s.end_period().unwrap();
        // Never the horizon again under the fallback, although it would reach period 3.
        assert_eq!(begin(&mut s, 3).write, Some(vec![0.0, 0.0]));
    }

    // ---- configuration, construction, serde ----

    #[test]
    fn config_validation_boundaries() {
        let ok = config(1000, 100_000, FallbackPolicy::SafeStop);
        assert_eq!(ok.validate(), Ok(()));
        for period in [0.0, -0.1, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
            let c = SafetyConfig { period, ..ok };
            assert!(
                matches!(
                    c.validate(),
                    Err(SafetyError::InvalidConfig {
                        field: "period",
                        ..
                    })
                ),
                "{period}"
            );
        }
        let c = SafetyConfig {
            max_age: 1001,
            ..ok
        };
        assert!(matches!(
            c.validate(),
            Err(SafetyError::InvalidConfig {
                field: "max_age",
                ..
            })
        ));
        let c = SafetyConfig {
            hold_periods: 100_001,
            ..ok
        };
        assert!(matches!(
            c.validate(),
            Err(SafetyError::InvalidConfig {
                field: "hold_periods",
                ..
            })
        ));
        let tiny = SafetyConfig {
            period: f64::MIN_POSITIVE,
            ..ok
        };
        assert_eq!(tiny.validate(), Ok(()));
    }

    #[test]
    fn new_checks_everything() {
        let cfg = config(2, 3, FallbackPolicy::LocalController);
        let bad = SafetyConfig { period: 0.0, ..cfg };
        assert!(Supervisor::new(bad, &[channel()], vec![0.0]).is_err());
        assert_eq!(
            Supervisor::new(cfg, &[channel()], vec![0.0, 0.0]).unwrap_err(),
            SafetyError::ChannelMismatch {
                what: "initial_applied",
                expected: 1,
                got: 2
            }
        );
        assert_eq!(
            Supervisor::new(cfg, &[channel()], vec![f64::NAN]).unwrap_err(),
            SafetyError::NonFiniteApplied
        );
        let broken = ChannelConfig {
            law: LawConfig::intelligent(ControllerKind::P, Order::One, 0.0, [1.0, 0.0, 0.0], 3),
            ..channel()
        };
        let e = Supervisor::new(cfg, &[broken], vec![0.0]).unwrap_err();
        assert!(matches!(e, SafetyError::Controller(_)));
        assert!(std::error::Error::source(&e).is_some());
        assert!(e.to_string().starts_with("local controller: "));
        let s = Supervisor::new(cfg, &[channel(), channel()], vec![1.0, -2.0]).unwrap();
        assert_eq!(s.channels(), 2);
        assert_eq!(s.mode(), LoopMode::Remote);
        assert_eq!(s.applied_now(), &[1.0, -2.0]);
        assert_eq!(s.missing_streak(), 0);
        assert_eq!(s.last_applied_seq(), None);
        assert_eq!(s.counters().clone(), SupervisorCounters::default());
        assert_eq!(*s.config(), cfg);
    }

    #[test]
    fn error_messages_are_not_empty() {
        let errors = [
            SafetyError::InvalidConfig {
                field: "period",
                reason: "must be finite and > 0 s",
            },
            SafetyError::ChannelMismatch {
                what: "y",
                expected: 2,
                got: 1,
            },
            SafetyError::NonFiniteApplied,
            SafetyError::PeriodOpen { open: 3 },
            SafetyError::PeriodNotIncreasing { previous: 3, k: 2 },
            SafetyError::NoOpenPeriod,
        ];
        for e in errors {
            assert!(!e.to_string().is_empty());
            assert!(std::error::Error::source(&e).is_none());
        }
    }

    #[test]
    fn serde_and_cli_names() {
        use serde::de::value::{Error, StrDeserializer};
        use serde::de::IntoDeserializer;
        fn de<T: for<'de> Deserialize<'de>>(s: &str) -> Result<T, Error> {
            let d: StrDeserializer<'_, Error> = s.into_deserializer();
            T::deserialize(d)
        }
        assert_eq!(
            de::<FallbackPolicy>("local"),
            Ok(FallbackPolicy::LocalController)
        );
        assert_eq!(
            de::<FallbackPolicy>("safe_stop"),
            Ok(FallbackPolicy::SafeStop)
        );
        assert!(de::<FallbackPolicy>("local_controller").is_err());
        assert!(de::<FallbackPolicy>("LocalController").is_err());
        for (name, mode) in [
            ("remote", LoopMode::Remote),
            ("holding", LoopMode::Holding),
            ("local", LoopMode::Local),
            ("safe_stop", LoopMode::SafeStop),
        ] {
            assert_eq!(de::<LoopMode>(name), Ok(mode));
        }
        for p in [FallbackPolicy::LocalController, FallbackPolicy::SafeStop] {
            assert_eq!(p.to_string().parse::<FallbackPolicy>(), Ok(p));
            assert_eq!(de::<FallbackPolicy>(p.name()), Ok(p));
        }
        assert_eq!("safe-stop".parse(), Ok(FallbackPolicy::SafeStop));
        let e = "off".parse::<FallbackPolicy>().unwrap_err();
        assert!(e.to_string().contains("off"));
    }

    // ---- acceptance boundaries ----

    #[test]
    fn on_time_command_is_applied_at_its_arrival() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        begin(&mut s, 0);
        let (verdict, done) = s.on_command(0.2, ctl(0, &[4.0]));
        assert_eq!(
            verdict,
            Verdict::Apply {
                v: vec![4.0],
                advance: 0.2,
                late: false
            }
        );
        assert!(done);
        assert_eq!(s.mode(), LoopMode::Remote);
        assert_eq!(s.last_applied_seq(), Some(0));
        assert_eq!(s.applied_now(), &[4.0]);
        assert_eq!(s.counters().commands, 1);
        assert_eq!(s.counters().late, 0);
        let end = s.end_period().unwrap();
        assert_eq!(
            end,
            PeriodEnd {
                mode: LoopMode::Remote,
                advance: 0.3,
                missing: false
            }
        );
    }

    #[test]
    fn oldest_acceptable_command_is_applied_late() {
        let max_age = 3;
        let mut s = sup(max_age, 100, FallbackPolicy::LocalController);
        for k in 0..10 {
            period(&mut s, k, None);
        }
        begin(&mut s, 10);
        let (verdict, done) = command(&mut s, 0.125, ctl(10 - u64::from(max_age), &[1.5]));
        assert_eq!(
            verdict,
            Verdict::Apply {
                v: vec![1.5],
                advance: 0.125,
                late: true
            }
        );
        assert!(!done, "the period's own command may still come");
        assert_eq!(s.counters().late, 1);
        assert_eq!(s.counters().commands, 1);
        assert_eq!(s.mode(), LoopMode::Remote);
        assert_eq!(s.missing_streak(), 0);
        // The period's own command still lands after it.
        let (verdict, done) = command(&mut s, 0.375, ctl(10, &[2.5]));
        assert_eq!(
            verdict,
            Verdict::Apply {
                v: vec![2.5],
                advance: 0.25,
                late: false
            }
        );
        assert!(done);
    }

    #[test]
    fn one_period_older_than_max_age_is_too_old() {
        let max_age = 3;
        let mut s = sup(max_age, 100, FallbackPolicy::LocalController);
        for k in 0..10 {
            period(&mut s, k, None);
        }
        begin(&mut s, 10);
        let seq = 10 - u64::from(max_age) - 1;
        assert_eq!(ignored(&mut s, ctl(seq, &[1.0])), Ignored::TooOld);
        assert_eq!(ignored(&mut s, warm(seq)), Ignored::TooOld);
        assert_eq!(ignored(&mut s, rejected(0)), Ignored::TooOld);
        assert_eq!(s.counters().too_old, 3);
        assert_eq!(s.counters().warming_up + s.counters().rejected, 0);
    }

    #[test]
    fn max_age_zero_accepts_only_the_own_sample() {
        let mut s = sup(0, 100, FallbackPolicy::LocalController);
        period(&mut s, 0, None);
        begin(&mut s, 1);
        assert_eq!(ignored(&mut s, ctl(0, &[1.0])), Ignored::TooOld);
        assert!(matches!(
            command(&mut s, 0.1, ctl(1, &[1.0])).0,
            Verdict::Apply { late: false, .. }
        ));
    }

    #[test]
    fn future_commands_are_ignored() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        begin(&mut s, 4);
        assert_eq!(ignored(&mut s, ctl(5, &[1.0])), Ignored::Future);
        assert_eq!(ignored(&mut s, ctl(u64::MAX, &[1.0])), Ignored::Future);
        assert_eq!(ignored(&mut s, warm(u64::MAX)), Ignored::Future);
        assert_eq!(s.counters().future, 3);
        // u64::MAX as the current period is fine too: no overflow anywhere.
        s.end_period().unwrap();
        begin(&mut s, u64::MAX);
        let (verdict, done) = command(&mut s, 0.1, ctl(u64::MAX, &[1.0]));
        assert!(matches!(verdict, Verdict::Apply { late: false, .. }) && done);
        assert_eq!(ignored(&mut s, ctl(u64::MAX, &[1.0])), Ignored::Duplicate);
        assert_eq!(ignored(&mut s, ctl(0, &[1.0])), Ignored::Superseded);
        s.end_period().unwrap();
        assert!(matches!(
            s.begin_period(u64::MAX, 0.0, &[0.0], &refs(1)),
            Err(SafetyError::PeriodNotIncreasing { .. })
        ));
    }

    #[test]
    fn duplicates_and_superseded() {
        let mut s = sup(5, 100, FallbackPolicy::LocalController);
        for k in 0..4 {
            period(&mut s, k, None);
        }
        begin(&mut s, 4);
        assert!(matches!(
            command(&mut s, 0.1, ctl(2, &[1.0])).0,
            Verdict::Apply { late: true, .. }
        ));
        // seq == last applied: a second controller answering the same sample.
        assert_eq!(ignored(&mut s, ctl(2, &[9.0])), Ignored::Duplicate);
        assert_eq!(ignored(&mut s, warm(2)), Ignored::Duplicate);
        assert_eq!(ignored(&mut s, rejected(2)), Ignored::Duplicate);
        // seq == last applied - 1: a newer command is already applied.
        assert_eq!(ignored(&mut s, ctl(1, &[9.0])), Ignored::Superseded);
        assert_eq!(ignored(&mut s, warm(1)), Ignored::Superseded);
        let c = s.counters().clone();
        assert_eq!((c.duplicates, c.superseded, c.commands), (3, 2, 1));
        // seq == last applied + 1 is newer: applied.
        assert!(matches!(
            command(&mut s, 0.2, ctl(3, &[2.0])).0,
            Verdict::Apply { late: true, .. }
        ));
        assert_eq!(s.applied_now(), &[2.0]);
    }

    #[test]
    fn malformed_commands_change_nothing() {
        let mut s = sup_n(2, 2, 3, FallbackPolicy::LocalController);
        begin(&mut s, 0);
        for bad in [
            &[1.0][..],
            &[1.0, 2.0, 3.0],
            &[],
            &[f64::NAN, 1.0],
            &[1.0, f64::INFINITY],
            &[f64::NEG_INFINITY, 0.0],
        ] {
            assert_eq!(ignored(&mut s, ctl(0, bad)), Ignored::Malformed, "{bad:?}");
        }
        let unknown = IncomingCommand {
            seq: 0,
            body: CommandBody::Unknown,
            horizon: &[],
            lease: Credentials::default(),
        };
        assert_eq!(ignored(&mut s, unknown), Ignored::Malformed);
        assert_eq!(s.counters().malformed, 7);
        assert_eq!(s.last_applied_seq(), None);
        // Still waiting for a usable command: the period is missing.
        assert!(s.end_period().unwrap().missing);
    }

    #[test]
    fn acceptance_rules_apply_in_order() {
        let mut s = sup(1, 100, FallbackPolicy::LocalController);
        for k in 0..5 {
            period(&mut s, k, Some(1.0));
        }
        begin(&mut s, 5);
        let bad = [f64::NAN];
        // Future before everything else.
        assert_eq!(ignored(&mut s, ctl(6, &bad)), Ignored::Future);
        // Duplicate before Malformed (last applied is 4).
        assert_eq!(ignored(&mut s, ctl(4, &bad)), Ignored::Duplicate);
        // Superseded before TooOld and Malformed.
        assert_eq!(ignored(&mut s, ctl(1, &bad)), Ignored::Superseded);
        // TooOld before Malformed: no command applied yet in a fresh supervisor.
        let mut fresh = sup(1, 100, FallbackPolicy::LocalController);
        for k in 0..5 {
            period(&mut fresh, k, None);
        }
        begin(&mut fresh, 5);
        assert_eq!(ignored(&mut fresh, ctl(3, &bad)), Ignored::TooOld);
        assert_eq!(ignored(&mut fresh, ctl(4, &bad)), Ignored::Malformed);
    }

    #[test]
    fn calls_out_of_order_are_refused_and_change_nothing() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        assert_eq!(s.end_period(), Err(SafetyError::NoOpenPeriod));
        // A command outside a period cannot be applied.
        assert_eq!(
            s.on_command(0.0, ctl(0, &[1.0])),
            (Verdict::Ignored(Ignored::Future), false)
        );
        assert_eq!(s.counters().future, 1);
        period(&mut s, 0, Some(1.0));
        begin(&mut s, 1);
        let before = format!("{s:?}");
        assert_eq!(
            s.begin_period(2, 2.0 * H, &[0.0], &refs(1)),
            Err(SafetyError::PeriodOpen { open: 1 })
        );
        assert_eq!(before, format!("{s:?}"));
        s.end_period().unwrap();
        let before = format!("{s:?}");
        for k in [0, 1] {
            assert_eq!(
                s.begin_period(k, 0.0, &[0.0], &refs(1)),
                Err(SafetyError::PeriodNotIncreasing { previous: 1, k })
            );
        }
        assert_eq!(s.end_period(), Err(SafetyError::NoOpenPeriod));
        assert_eq!(before, format!("{s:?}"));
        // Gaps are allowed.
        begin(&mut s, 7);
        s.end_period().unwrap();
    }

    #[test]
    fn wrong_length_inputs_are_refused_with_state_unchanged() {
        let mut s = sup_n(2, 2, 0, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(1.0));
        period(&mut s, 1, None);
        // The fallback is due now: a refused call must not engage it.
        let before = format!("{s:?}");
        assert_eq!(
            s.begin_period(2, 2.0 * H, &[0.0], &refs(2)),
            Err(SafetyError::ChannelMismatch {
                what: "y",
                expected: 2,
                got: 1
            })
        );
        assert_eq!(
            s.begin_period(2, 2.0 * H, &[0.0; 3], &refs(2)),
            Err(SafetyError::ChannelMismatch {
                what: "y",
                expected: 2,
                got: 3
            })
        );
        assert_eq!(
            s.begin_period(2, 2.0 * H, &[0.0; 2], &refs(1)),
            Err(SafetyError::ChannelMismatch {
                what: "refs",
                expected: 2,
                got: 1
            })
        );
        assert_eq!(before, format!("{s:?}"));
        let b = begin(&mut s, 2);
        assert!(b.write.is_some());
    }

    #[test]
    fn bad_applied_reports_are_ignored() {
        let mut s = sup_n(2, 2, 3, FallbackPolicy::LocalController);
        begin(&mut s, 0);
        command(&mut s, 0.1, ctl(0, &[1.0, 2.0]));
        s.applied(&[1.0]);
        s.applied(&[1.0, 2.0, 3.0]);
        s.applied(&[f64::NAN, 0.0]);
        s.applied(&[0.0, f64::INFINITY]);
        assert_eq!(s.applied_now(), &[1.0, 2.0]);
        s.applied(&[0.5, 2.0]);
        assert_eq!(s.applied_now(), &[0.5, 2.0]);
    }

    // ---- state transitions ----

    #[test]
    fn remote_to_holding_and_back() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        let (_, end) = period(&mut s, 1, None);
        assert_eq!(
            end,
            PeriodEnd {
                mode: LoopMode::Holding,
                advance: H,
                missing: true
            }
        );
        assert_eq!(s.mode(), LoopMode::Holding);
        assert_eq!(s.missing_streak(), 1);
        assert_eq!(s.applied_now(), &[2.0], "the last command is held");
        let (b, end) = period(&mut s, 2, Some(3.0));
        assert_eq!(b.sample_mode, LoopMode::Holding);
        assert_eq!(b.write, None);
        assert_eq!(end.mode, LoopMode::Remote);
        assert_eq!(s.mode(), LoopMode::Remote);
        assert_eq!(s.missing_streak(), 0);
        let c = s.counters().clone();
        assert_eq!((c.missing, c.holding_periods, c.fallbacks), (1, 1, 0));
    }

    #[test]
    fn holding_to_local() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        for k in 1..=3 {
            let (b, end) = period(&mut s, k, None);
            assert_eq!(b.write, None);
            assert_eq!(end.mode, LoopMode::Holding, "period {k}");
        }
        let (b, end) = period(&mut s, 4, None);
        assert_eq!(b.sample_mode, LoopMode::Holding);
        let v = b.write.expect("the fallback engages");
        assert_eq!(v, vec![s.local_out[0].v]);
        assert_eq!(s.applied_now(), &v[..]);
        assert_eq!(end.mode, LoopMode::Local);
        assert_eq!(s.mode(), LoopMode::Local);
        let c = s.counters().clone();
        assert_eq!(
            (c.holding_periods, c.local_periods, c.fallbacks, c.missing),
            (3, 1, 1, 4)
        );
    }

    #[test]
    fn remote_to_local_without_holding_when_hold_is_zero_or_one() {
        for hold in [0, 1] {
            let mut s = sup(2, hold, FallbackPolicy::LocalController);
            period(&mut s, 0, Some(2.0));
            let (b, end) = period(&mut s, 1, None);
            assert_eq!(
                b.write, None,
                "hold {hold}: period 1 cannot be known missing"
            );
            assert_eq!(end.mode, LoopMode::Remote, "hold {hold}");
            assert!(end.missing);
            assert_eq!(s.mode(), LoopMode::Remote);
            let (b, end) = period(&mut s, 2, None);
            assert_eq!(b.sample_mode, LoopMode::Remote);
            assert!(b.write.is_some(), "hold {hold}");
            assert_eq!(end.mode, LoopMode::Local);
            assert_eq!(s.counters().holding_periods, 0);
            assert_eq!(s.counters().fallbacks, 1);
        }
    }

    #[test]
    fn fallback_engages_exactly_after_hold_periods() {
        for hold in [0u32, 1, 2, 5] {
            let mut s = sup(2, hold, FallbackPolicy::LocalController);
            let last_command = 3;
            for k in 0..=last_command {
                period(&mut s, k, Some(1.0));
            }
            let mut engaged = None;
            for p in last_command + 1..last_command + 20 {
                let (b, _) = period(&mut s, p, None);
                if b.write.is_some() {
                    engaged = Some(p);
                    break;
                }
            }
            // A period is known missing only once it has ended, so hold 0 behaves as 1.
            let p = engaged.unwrap();
            assert_eq!(p - last_command - 1, u64::from(hold.max(1)), "hold {hold}");
            // The Holding mode only shows when there is something to hold before falling back
            // (hold >= 2): with hold 0 or 1 the one missing period stays Remote.
            let holding = if hold >= 2 { u64::from(hold) } else { 0 };
            assert_eq!(s.counters().holding_periods, holding, "hold {hold}");
        }
    }

    #[test]
    fn local_to_remote() {
        let mut s = sup(2, 1, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        period(&mut s, 1, None);
        let (b, end) = period(&mut s, 2, None);
        assert!(b.write.is_some());
        assert_eq!(end.mode, LoopMode::Local);
        // Commands are back: the fallback wrote at the start, the command replaces it.
        let b = begin(&mut s, 3);
        assert_eq!(b.sample_mode, LoopMode::Local);
        assert!(b.write.is_some(), "still Local at the start of the period");
        let (verdict, done) = command(&mut s, 0.25, ctl(3, &[7.0]));
        assert!(matches!(verdict, Verdict::Apply { late: false, .. }) && done);
        assert_eq!(s.mode(), LoopMode::Remote);
        let end = s.end_period().unwrap();
        assert_eq!(end.mode, LoopMode::Remote);
        assert_eq!(s.missing_streak(), 0);
        let (b, end) = period(&mut s, 4, Some(7.5));
        assert_eq!(b.sample_mode, LoopMode::Remote);
        assert_eq!(b.write, None);
        assert_eq!(end.mode, LoopMode::Remote);
        let c = s.counters().clone();
        assert_eq!((c.local_periods, c.fallbacks), (1, 1));
    }

    #[test]
    fn safe_stop_policy_writes_zeros_and_resumes() {
        let mut s = sup_n(2, 2, 2, FallbackPolicy::SafeStop);
        period(&mut s, 0, Some(5.0));
        period(&mut s, 1, None);
        period(&mut s, 2, None);
        let (b, end) = period(&mut s, 3, None);
        assert_eq!(b.write, Some(vec![0.0, 0.0]));
        assert_eq!(end.mode, LoopMode::SafeStop);
        assert_eq!(s.mode(), LoopMode::SafeStop);
        assert_eq!(s.applied_now(), &[0.0, 0.0]);
        let (b, end) = period(&mut s, 4, None);
        assert_eq!(b.write, Some(vec![0.0, 0.0]), "zeros every period");
        assert_eq!(end.mode, LoopMode::SafeStop);
        // SafeStop -> Remote.
        let (b, end) = period(&mut s, 5, Some(1.0));
        assert_eq!(b.sample_mode, LoopMode::SafeStop);
        assert_eq!(end.mode, LoopMode::Remote);
        assert_eq!(s.mode(), LoopMode::Remote);
        let c = s.counters().clone();
        assert_eq!((c.safe_stop_periods, c.fallbacks), (2, 1));
    }

    #[test]
    fn failing_local_step_means_safe_stop_even_under_local_policy() {
        let mut s = sup(2, 1, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        period(&mut s, 1, None);
        // The fallback is due, but the local controller cannot run on a NaN output.
        let b = s.begin_period(2, 2.0 * H, &[f64::NAN], &refs(1)).unwrap();
        assert_eq!(b.write, Some(vec![0.0]));
        s.applied(&[0.0]);
        assert_eq!(s.mode(), LoopMode::SafeStop);
        assert_eq!(s.end_period().unwrap().mode, LoopMode::SafeStop);
        // It recovers: Local, without a second fallback entry.
        let (b, end) = period(&mut s, 3, None);
        assert_eq!(b.sample_mode, LoopMode::SafeStop);
        assert_eq!(b.write, Some(vec![s.local_out[0].v]));
        assert_eq!(end.mode, LoopMode::Local);
        // And fails again while Local: SafeStop, still one entry.
        s.begin_period(4, 4.0 * H, &[f64::INFINITY], &refs(1))
            .unwrap();
        assert_eq!(s.mode(), LoopMode::SafeStop);
        assert_eq!(s.end_period().unwrap().mode, LoopMode::SafeStop);
        let c = s.counters().clone();
        assert_eq!(
            (c.fallbacks, c.safe_stop_periods, c.local_periods),
            (1, 2, 1)
        );
        // A bad reference or a bad time fails the same way.
        let b = s
            .begin_period(5, 5.0 * H, &[0.0], &[Reference::constant(f64::NAN)])
            .unwrap();
        assert_eq!(b.write, Some(vec![0.0]));
        s.end_period().unwrap();
        let b = s.begin_period(6, f64::NAN, &[0.0], &refs(1)).unwrap();
        assert_eq!(b.write, Some(vec![0.0]));
        s.end_period().unwrap();
    }

    #[test]
    fn nan_output_without_fallback_due_changes_nothing() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        let b = s.begin_period(1, H, &[f64::NAN], &refs(1)).unwrap();
        assert_eq!(b.write, None);
        assert_eq!(s.mode(), LoopMode::Remote);
        command(&mut s, 0.1, ctl(1, &[3.0]));
        assert_eq!(s.end_period().unwrap().mode, LoopMode::Remote);
    }

    #[test]
    fn warming_up_at_start_keeps_holding_without_counting_missing() {
        let mut s = sup(2, 2, FallbackPolicy::LocalController);
        for k in 0..10 {
            let b = begin(&mut s, k);
            assert_eq!(b.sample_mode, LoopMode::Remote);
            assert_eq!(b.write, None);
            let (verdict, done) = command(&mut s, 0.1, warm(k));
            assert_eq!((verdict, done), (Verdict::WarmingUp, true));
            let end = s.end_period().unwrap();
            assert_eq!(
                end,
                PeriodEnd {
                    mode: LoopMode::Remote,
                    advance: H,
                    missing: false
                }
            );
        }
        assert_eq!(s.applied_now(), &[0.0], "the initial value is held");
        let c = s.counters().clone();
        assert_eq!((c.missing, c.warming_up, c.fallbacks), (0, 10, 0));
        assert_eq!(s.missing_streak(), 0);
        // A late warming-up answer counts too, but does not end the wait.
        begin(&mut s, 10);
        assert_eq!(s.on_command(0.1, warm(9)), (Verdict::WarmingUp, false));
        assert!(!s.end_period().unwrap().missing);
    }

    /// After a command was applied, a controller that answers "warming up" (it restarted,
    /// or took the lease with a cold state) does not hold the plant on a stale command
    /// past the watchdog: the periods count towards the fallback (not as missing).
    #[test]
    fn warming_up_after_commands_does_not_stop_the_watchdog() {
        let mut s = sup(2, 3, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        period(&mut s, 1, None);
        period(&mut s, 2, None);
        assert_eq!(s.missing_streak(), 2);
        begin(&mut s, 3);
        command(&mut s, 0.1, warm(3));
        let end = s.end_period().unwrap();
        assert!(!end.missing);
        assert_eq!(end.mode, LoopMode::Holding);
        assert_eq!(s.missing_streak(), 3);
        assert_eq!(s.counters().missing, 2);
        assert_eq!(s.applied_now(), &[2.0]);
        // The fallback engages at the next period, warming-up answers or not.
        assert!(period(&mut s, 4, None).0.write.is_some());
        assert_eq!(s.mode(), LoopMode::Local);
    }

    /// Credentials of controller `from` (process 0) for run 9.
    fn creds(from: &str, epoch: u64, claim: bool) -> Credentials<'_> {
        Credentials {
            from,
            instance: 0,
            epoch,
            claim,
            release: false,
            run_id: 9,
        }
    }

    fn leased<'a>(
        seq: u64,
        v: &'a [f64],
        from: &'a str,
        epoch: u64,
        claim: bool,
    ) -> IncomingCommand<'a> {
        IncomingCommand {
            lease: creds(from, epoch, claim),
            ..ctl(seq, v)
        }
    }

    /// With leases, only the holder's commands pass; a refused one changes nothing but
    /// the count; a claim that the other rules drop grants nothing; the lease lapses
    /// after half the hold, and the next claim gets a new epoch.
    #[test]
    fn the_lease_decides_who_commands_and_lapses_with_the_fallback() {
        let mut s = sup(3, 2, FallbackPolicy::LocalController);
        s.grant_leases(9);
        begin(&mut s, 0);
        // A claim of a future sample is dropped and grants nothing.
        assert_eq!(
            ignored(&mut s, leased(1, &[1.0], "b", 1, true)),
            Ignored::Future
        );
        assert_eq!(s.lease().unwrap().holder(), None);
        let (v, _) = command(&mut s, 0.1, leased(0, &[1.0], "a", 1, true));
        assert!(matches!(v, Verdict::Apply { .. }));
        assert_eq!(s.lease().unwrap().holder(), Some("a"));
        // The loser's claim and a forged holder's epoch are fenced, counted once each.
        let fenced = |f| Ignored::Fenced(f);
        assert_eq!(
            ignored(&mut s, leased(0, &[9.0], "b", 1, true)),
            fenced(Fence::BadClaim)
        );
        assert_eq!(
            ignored(&mut s, leased(0, &[9.0], "a", 2, false)),
            fenced(Fence::StaleEpoch)
        );
        s.end_period().unwrap();
        begin(&mut s, 1);
        let (v, _) = command(&mut s, 0.1, leased(1, &[2.0], "a", 1, false));
        assert!(matches!(v, Verdict::Apply { .. }));
        s.end_period().unwrap();
        // Silence: the lease lapses after half the hold (one period), while the plant
        // still holds; the fallback engages after the whole hold.
        period(&mut s, 2, None);
        assert_eq!(s.lease().unwrap().holder(), Some("a"));
        assert_eq!(begin(&mut s, 3).write, None);
        assert_eq!(s.lease().unwrap().holder(), None);
        s.end_period().unwrap();
        assert!(begin(&mut s, 4).write.is_some());
        // The old holder's command is refused now; its claim of the next epoch passes.
        assert_eq!(
            ignored(&mut s, leased(4, &[3.0], "a", 1, false)),
            fenced(Fence::Vacant)
        );
        let (v, _) = command(&mut s, 0.1, leased(4, &[3.0], "b", 2, true));
        assert!(matches!(v, Verdict::Apply { .. }));
        assert_eq!(s.mode(), LoopMode::Remote);
        let l = s.lease().unwrap();
        assert_eq!(
            (l.holder(), l.epoch(), l.counters().lapses),
            (Some("b"), 2, 1)
        );
        let c = s.counters();
        assert_eq!((c.fenced, c.commands, c.future), (3, 3, 1));
        assert_eq!(total(c), 7);
        let spans: Vec<_> = l
            .report()
            .spans
            .iter()
            .map(|x| (x.holder.clone(), x.epoch, x.first, x.last))
            .collect();
        assert_eq!(
            spans,
            [("a".to_string(), 1, 0, 1), ("b".to_string(), 2, 4, 4)]
        );
    }

    /// A holder that answers "warming up" (it took the lease cold) keeps it while the
    /// fallback runs: no lapse and new epoch every period until it is warm.
    #[test]
    fn a_warming_holder_keeps_the_lease_through_the_fallback() {
        let mut s = sup(3, 2, FallbackPolicy::LocalController);
        s.grant_leases(9);
        period(&mut s, 0, None);
        period(&mut s, 1, None);
        assert!(begin(&mut s, 2).write.is_some(), "the fallback runs");
        let holder = creds("a", 1, true);
        for k in 2..8 {
            if k > 2 {
                begin(&mut s, k);
            }
            let w = IncomingCommand {
                lease: holder,
                ..warm(k)
            };
            assert_eq!(s.on_command(0.1, w).0, Verdict::WarmingUp);
            s.end_period().unwrap();
            assert_eq!(s.mode(), LoopMode::Local);
        }
        let l = s.lease().unwrap();
        assert_eq!(
            (l.holder(), l.epoch(), l.counters().lapses),
            (Some("a"), 1, 0)
        );
        // Silent now: it lapses after half the hold (one period).
        period(&mut s, 8, None);
        begin(&mut s, 9);
        assert_eq!(s.lease().unwrap().holder(), None);
    }

    /// A refusal from a claimant is no answer that keeps the plant safe: it claims nothing.
    #[test]
    fn a_rejected_claim_grants_nothing() {
        let mut s = sup(3, 2, FallbackPolicy::LocalController);
        s.grant_leases(9);
        begin(&mut s, 0);
        let mut r = rejected(0);
        r.lease = creds("a", 1, true);
        assert_eq!(s.on_command(0.1, r).0, Verdict::Rejected);
        assert_eq!(s.lease().unwrap().holder(), None);
        let mut w = warm(0);
        w.lease = r.lease;
        assert_eq!(s.on_command(0.1, w).0, Verdict::WarmingUp);
        assert_eq!(s.lease().unwrap().holder(), Some("a"));
    }

    #[test]
    fn warming_up_during_local_keeps_local() {
        let mut s = sup(2, 1, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        period(&mut s, 1, None);
        period(&mut s, 2, None);
        assert_eq!(s.mode(), LoopMode::Local);
        for k in 3..6 {
            let b = begin(&mut s, k);
            assert_eq!(b.sample_mode, LoopMode::Local);
            assert!(b.write.is_some(), "the local controller keeps running");
            assert_eq!(command(&mut s, 0.1, warm(k)), (Verdict::WarmingUp, true));
            let end = s.end_period().unwrap();
            assert_eq!(end.mode, LoopMode::Local);
            assert!(!end.missing);
            assert_eq!(s.mode(), LoopMode::Local);
            // Not missing, but no command either: the watchdog's count goes on.
            assert_eq!(s.missing_streak(), k as u32);
        }
        let c = s.counters().clone();
        assert_eq!((c.local_periods, c.fallbacks, c.missing), (4, 1, 2));
    }

    #[test]
    fn rejected_is_counted_and_changes_nothing_else() {
        let mut s = sup(2, 2, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        period(&mut s, 1, None);
        begin(&mut s, 2);
        assert_eq!(s.on_command(0.1, rejected(1)), (Verdict::Rejected, false));
        assert_eq!(s.on_command(0.1, rejected(2)), (Verdict::Rejected, true));
        assert_eq!(s.missing_streak(), 1, "a refusal is not an answer");
        assert_eq!(s.applied_now(), &[2.0]);
        let end = s.end_period().unwrap();
        assert!(end.missing);
        assert_eq!(end.mode, LoopMode::Holding);
        assert_eq!(s.counters().rejected, 2);
        assert_eq!(s.last_applied_seq(), Some(0));
        assert!(period(&mut s, 3, None).0.write.is_some());
    }

    #[test]
    fn fallbacks_count_entries_not_periods() {
        let mut s = sup(2, 1, FallbackPolicy::LocalController);
        let mut k = 0;
        let mut run = |s: &mut Supervisor, v: Option<f64>| {
            let r = period(s, k, v);
            k += 1;
            r
        };
        for _ in 0..3 {
            run(&mut s, Some(1.0));
            for _ in 0..6 {
                run(&mut s, None);
            }
        }
        let c = s.counters().clone();
        assert_eq!(c.fallbacks, 3);
        assert_eq!(c.local_periods, 15);
        assert_eq!(c.missing, 18);
    }

    // ---- time accounting ----

    #[test]
    fn time_weighted_mean_of_a_command_landing_mid_period() {
        let h = 1.0;
        let cfg = SafetyConfig {
            period: h,
            ..config(2, 5, FallbackPolicy::LocalController)
        };
        let mut s = Supervisor::new(cfg, &[channel()], vec![0.0]).unwrap();
        s.begin_period(0, 0.0, &[0.0], &refs(1)).unwrap();
        command(&mut s, 0.0, ctl(0, &[2.0]));
        s.end_period().unwrap();
        // Holding 2 V, a new value of 5 V lands at 0.3 h.
        let b = s.begin_period(1, h, &[0.0], &refs(1)).unwrap();
        assert_eq!(b.applied_mean, vec![2.0]);
        let (verdict, _) = command(&mut s, 0.3 * h, ctl(1, &[5.0]));
        assert!(matches!(verdict, Verdict::Apply { advance, .. } if advance == 0.3 * h));
        let end = s.end_period().unwrap();
        assert!((end.advance - 0.7 * h).abs() < 1e-15);
        let b = s.begin_period(2, 2.0 * h, &[0.0], &refs(1)).unwrap();
        let expected = 0.3 * 2.0 + 0.7 * 5.0;
        assert!((b.applied_mean[0] - expected).abs() < 1e-12, "{b:?}");
    }

    #[test]
    fn first_sample_carries_the_initial_applied() {
        let cfg = config(2, 5, FallbackPolicy::LocalController);
        let mut s = Supervisor::new(cfg, &[channel(), channel()], vec![0.25, -0.5]).unwrap();
        let b = s.begin_period(0, 0.0, &[0.0, 0.0], &refs(2)).unwrap();
        assert_eq!(b.applied_mean, vec![0.25, -0.5]);
        s.end_period().unwrap();
        let b = s.begin_period(1, H, &[0.0, 0.0], &refs(2)).unwrap();
        assert_eq!(b.applied_mean, vec![0.25, -0.5]);
    }

    #[test]
    fn fallback_write_at_start_then_command_at_half() {
        let mut s = sup(2, 1, FallbackPolicy::SafeStop);
        period(&mut s, 0, Some(4.0));
        period(&mut s, 1, None);
        // Period 2: the fallback writes zeros at offset 0, replacing 4 V for the whole period.
        let b = begin(&mut s, 2);
        assert_eq!(b.applied_mean, vec![4.0]);
        assert_eq!(b.write, Some(vec![0.0]));
        let (verdict, done) = command(&mut s, 0.5 * H, ctl(2, &[6.0]));
        assert_eq!(
            verdict,
            Verdict::Apply {
                v: vec![6.0],
                advance: 0.5 * H,
                late: false
            }
        );
        assert!(done);
        let end = s.end_period().unwrap();
        assert_eq!(end.advance, 0.5 * H);
        assert_eq!(end.mode, LoopMode::Remote);
        let b = begin(&mut s, 3);
        assert_eq!(b.applied_mean, vec![0.5 * 0.0 + 0.5 * 6.0]);
    }

    #[test]
    fn plant_reports_replace_the_written_value() {
        let mut s = sup(2, 5, FallbackPolicy::LocalController);
        begin(&mut s, 0);
        // The plant saturates: 30 V written, 24 V applied from 0.25 s on.
        s.on_command(0.25, ctl(0, &[30.0]));
        s.applied(&[24.0]);
        s.end_period().unwrap();
        let b = begin(&mut s, 1);
        assert_eq!(b.applied_mean, vec![(0.25 * 0.0 + 0.25 * 24.0) / H]);
    }

    #[test]
    fn advances_sum_to_the_period() {
        let mut s = sup(3, 100, FallbackPolicy::LocalController);
        for k in 0..3 {
            period(&mut s, k, None);
        }
        begin(&mut s, 3);
        let mut sum = 0.0;
        let arrivals = [
            (-0.25, 0u64, 0.0), // before the deadline: counts as 0
            (0.125, 1, 0.125),  // on time
            (0.0625, 2, 0.0),   // arrived "before" the last one: clamped to it
            (f64::NAN, 3, 0.0), // unknown time: now
        ];
        for (at, seq, advance) in arrivals {
            match command(&mut s, at, ctl(seq, &[seq as f64])).0 {
                Verdict::Apply { advance: a, .. } => {
                    assert_eq!(a, advance, "seq {seq}");
                    sum += a;
                }
                other => panic!("{other:?}"),
            }
        }
        let end = s.end_period().unwrap();
        assert_eq!(sum + end.advance, H);
        // A command past the end of the period is clamped to it.
        begin(&mut s, 4);
        let Verdict::Apply { advance, .. } = command(&mut s, 9.0, ctl(4, &[1.0])).0 else {
            panic!()
        };
        assert_eq!(advance, H);
        assert_eq!(s.end_period().unwrap().advance, 0.0);
        begin(&mut s, 5);
        let Verdict::Apply { advance, .. } = command(&mut s, f64::INFINITY, ctl(5, &[1.0])).0
        else {
            panic!()
        };
        assert_eq!(advance, H);
        assert_eq!(s.end_period().unwrap().advance, 0.0);
        begin(&mut s, 6);
        let Verdict::Apply { advance, .. } = command(&mut s, f64::NEG_INFINITY, ctl(6, &[1.0])).0
        else {
            panic!()
        };
        assert_eq!(advance, 0.0);
        assert_eq!(s.end_period().unwrap().advance, H);
        // Without any command the whole period is left to integrate.
        assert_eq!(period(&mut s, 7, None).1.advance, H);
    }

    #[test]
    fn the_local_controller_is_fed_what_was_really_applied() {
        let n = 2;
        let cfg = config(2, 2, FallbackPolicy::LocalController);
        let channels = vec![channel(); n];
        let mut s = Supervisor::new(cfg, &channels, vec![0.0; n]).unwrap();
        let mut reference: MimoController = MimoController::new(&channels).unwrap();
        let mut out = vec![ChannelOutput::default(); n];
        // A plant that saturates at ±3 and whose output follows the inputs.
        let plant = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x.clamp(-3.0, 3.0)).collect() };
        let mut y = vec![0.0; n];
        let mut applied = vec![0.0; n];
        let mut mean = vec![0.0; n];
        let mut seen_fallback = false;
        for k in 0..40u64 {
            let t = k as f64 * H;
            let r = vec![Reference::constant(1.0), Reference::constant(-0.5)];
            let b = s.begin_period(k, t, &y, &r).unwrap();
            assert_eq!(b.applied_mean, mean, "period {k}");
            if k > 0 {
                reference.report_applied(&mean).unwrap();
            }
            reference.step(t, &y, &r, &mut out).unwrap();
            let mut acc = vec![0.0; n];
            let mut seg = 0.0;
            if let Some(v) = b.write {
                seen_fallback = true;
                assert_eq!(v, out.iter().map(|o| o.v).collect::<Vec<_>>());
                applied = plant(&v);
                s.applied(&applied);
            }
            // Commands for periods 10..20 never come; the others land at 0.2 s with 5 V on
            // channel 0 (saturated by the plant).
            if !(10..20).contains(&k) {
                let cmd = [5.0, -0.25 * (k % 4) as f64];
                if let Verdict::Apply { v, advance, .. } = s.on_command(0.2, ctl(k, &cmd)).0 {
                    for (a, x) in acc.iter_mut().zip(&applied) {
                        *a += x * advance;
                    }
                    seg = 0.2;
                    applied = plant(&v);
                    s.applied(&applied);
                }
            }
            let end = s.end_period().unwrap();
            assert_eq!(s.applied_now(), &applied[..]);
            for (((m, a), x), y) in mean.iter_mut().zip(&acc).zip(&applied).zip(&mut y) {
                *m = (a + x * (H - seg)) / H;
                *y += 0.1 * x * H;
            }
            assert_eq!(end.advance, H - seg);
            // Same sequence in, same controller state out.
            assert_eq!(format!("{:?}", s.local), format!("{reference:?}"));
        }
        assert!(seen_fallback);
        assert_eq!(s.counters().fallbacks, 1);
    }

    // ---- randomised invariants ----

    /// A tiny linear congruential generator (Knuth's MMIX constants).
    struct Lcg(u64);

    impl Lcg {
        fn next(&mut self) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            self.0 >> 33
        }

        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }

        fn unit(&mut self) -> f64 {
            self.next() as f64 / (1u64 << 31) as f64
        }
    }

    /// One randomised run of a supervisor, with what the test tracks of it to check the
    /// invariants after every call.
    struct Trial {
        s: Supervisor,
        rng: Lcg,
        n: usize,
        max_age: u32,
        /// Everything that may legitimately be applied: the initial value, fallback
        /// outputs and accepted commands.
        legit: Vec<Vec<f64>>,
        delivered: u64,
        remote_periods: u64,
        fallbacks: u64,
        missing: u64,
    }

    /// What one period's commands did: the plant time they let pass, whether the
    /// period's own command (or a warm-up answer) came, and every value applied in it.
    struct Commands {
        advance: f64,
        answered: bool,
        values: Vec<Vec<f64>>,
    }

    impl Trial {
        fn new(seed: u64) -> Self {
            let mut rng = Lcg(seed);
            let n = 1 + rng.below(2) as usize;
            let policy = if rng.below(2) == 0 {
                FallbackPolicy::LocalController
            } else {
                FallbackPolicy::SafeStop
            };
            let max_age = rng.below(4) as u32;
            let hold = rng.below(4) as u32;
            let cfg = SafetyConfig {
                period: H,
                max_age,
                hold_periods: hold,
                fallback: policy,
            };
            Self {
                s: Supervisor::new(cfg, &vec![channel(); n], vec![0.0; n]).unwrap(),
                rng,
                n,
                max_age,
                legit: vec![vec![0.0; n]],
                delivered: 0,
                remote_periods: 0,
                fallbacks: 0,
                missing: 0,
            }
        }

        /// Begin period `k` on random outputs (sometimes a NaN), checking the sample's
        /// mode and mean and any fallback write; sometimes a wiring bug follows, which
        /// must change nothing.
        fn begin(&mut self, k: u64) {
            let (s, n) = (&mut self.s, self.n);
            let mut y = vec![self.rng.unit() - 0.5; n];
            if self.rng.below(25) == 0 {
                y[0] = f64::NAN;
            }
            let mode_before = s.mode();
            let b = s.begin_period(k, k as f64 * H, &y, &refs(n)).unwrap();
            assert_eq!(b.sample_mode, mode_before);
            assert!(b.applied_mean.iter().all(|m| m.is_finite()));
            if mode_before.is_fallback() {
                assert!(b.write.is_some());
            }
            if b.write.is_some() {
                assert!(s.mode().is_fallback());
                if !mode_before.is_fallback() {
                    self.fallbacks += 1;
                }
            } else {
                assert_eq!(s.mode(), mode_before);
            }
            if let Some(v) = b.write {
                if s.mode() == LoopMode::SafeStop {
                    assert!(v.iter().all(|x| *x == 0.0));
                }
                s.applied(&v);
                self.legit.push(v);
            }
            // A wiring bug in the middle must not corrupt anything.
            if self.rng.below(10) == 0 {
                let before = format!("{s:?}");
                assert!(s.begin_period(k + 1, 0.0, &y, &refs(n)).is_err());
                assert!(s.begin_period(k + 1, 0.0, &y[1..], &refs(n)).is_err());
                assert_eq!(before, format!("{s:?}"));
            }
        }

        /// Up to four random commands in period `k` (any seq, malformed inputs, odd
        /// arrival times), each verdict checked against the rules.
        fn commands(&mut self, k: u64) -> Commands {
            let mut got = Commands {
                advance: 0.0,
                answered: false,
                values: vec![self.s.applied_now().to_vec()],
            };
            for _ in 0..self.rng.below(5) {
                let (rng, s, n) = (&mut self.rng, &mut self.s, self.n);
                let seq = match rng.below(12) {
                    0 => u64::MAX,
                    1 => s.last_applied_seq().unwrap_or(k),
                    2 => k + 1,
                    r => k.saturating_sub(r % 6),
                };
                let cmd_v: Vec<f64> = match rng.below(10) {
                    0 => vec![f64::NAN; n],
                    1 => vec![1.0; n + 1],
                    _ => (0..n).map(|_| rng.unit() * 10.0 - 5.0).collect(),
                };
                let body = match rng.below(10) {
                    0 => CommandBody::WarmingUp,
                    1 => CommandBody::Rejected("x"),
                    2 => CommandBody::Unknown,
                    _ => CommandBody::Control(&cmd_v),
                };
                let at = match rng.below(8) {
                    0 => f64::NAN,
                    1 => -1.0,
                    2 => 2.0 * H,
                    _ => rng.unit() * H,
                };
                let before = s.counters().clone();
                let last = s.last_applied_seq();
                self.delivered += 1;
                let horizon = &[];
                let (verdict, done) = s.on_command(
                    at,
                    IncomingCommand {
                        seq,
                        body,
                        horizon,
                        lease: Credentials::default(),
                    },
                );
                assert_eq!(total(s.counters()), total(&before) + 1);
                assert_eq!(done, seq == k && !matches!(verdict, Verdict::Ignored(_)));
                match verdict {
                    Verdict::Apply { v, advance, late } => {
                        assert!(seq <= k && k - seq <= u64::from(self.max_age));
                        assert!(last.is_none_or(|l| seq > l));
                        assert_eq!(late, seq < k);
                        assert!(advance >= 0.0);
                        got.advance += advance;
                        assert!(got.advance <= H + 1e-12);
                        assert_eq!(s.mode(), LoopMode::Remote);
                        s.applied(&v);
                        got.values.push(v.clone());
                        self.legit.push(v);
                        got.answered = true;
                    }
                    Verdict::WarmingUp => got.answered = true,
                    Verdict::Rejected | Verdict::Ignored(_) => {}
                }
            }
            got
        }

        /// End period `k`: its time adds up, its mode and missing flag follow from the
        /// commands, what is applied was legitimate, the mean lies within what was
        /// applied, and the counters add up.
        fn end(&mut self, k: u64, got: &Commands) {
            let (s, n) = (&mut self.s, self.n);
            let end = s.end_period().unwrap();
            assert!(end.advance >= 0.0);
            assert!(
                (got.advance + end.advance - H).abs() <= 1e-15,
                "{} + {}",
                got.advance,
                end.advance
            );
            assert_eq!(end.missing, !got.answered);
            self.missing += u64::from(end.missing);
            if end.mode == LoopMode::Remote {
                self.remote_periods += 1;
            }
            if end.mode.is_fallback() || end.mode == LoopMode::Holding {
                assert_eq!(s.mode(), end.mode);
            }
            assert!(self.legit.iter().any(|l| l[..] == *s.applied_now()));
            // The period's mean lies between what was applied in it.
            let next = begin_mean(s, k + 1, n);
            for (i, m) in next.iter().enumerate() {
                let lo = got
                    .values
                    .iter()
                    .map(|v| v[i])
                    .fold(f64::INFINITY, f64::min);
                let hi = got
                    .values
                    .iter()
                    .map(|v| v[i])
                    .fold(f64::NEG_INFINITY, f64::max);
                assert!(
                    *m >= lo - 1e-9 && *m <= hi + 1e-9,
                    "{m} not in [{lo}, {hi}]"
                );
            }
            let c = s.counters();
            assert_eq!(
                c.periods,
                c.holding_periods + c.local_periods + c.safe_stop_periods + self.remote_periods
            );
            assert_eq!(total(c), self.delivered);
            assert_eq!(c.fallbacks, self.fallbacks);
            assert_eq!(c.missing, self.missing);
            assert!(c.late <= c.commands);
        }

        /// Add this run's counters to `seen`.
        fn tally(&self, seen: &mut SupervisorCounters) {
            let c = self.s.counters();
            for (sum, x) in [
                (&mut seen.commands, c.commands),
                (&mut seen.late, c.late),
                (&mut seen.missing, c.missing),
                (&mut seen.too_old, c.too_old),
                (&mut seen.superseded, c.superseded),
                (&mut seen.duplicates, c.duplicates),
                (&mut seen.warming_up, c.warming_up),
                (&mut seen.rejected, c.rejected),
                (&mut seen.malformed, c.malformed),
                (&mut seen.future, c.future),
                (&mut seen.fallbacks, c.fallbacks),
                (&mut seen.holding_periods, c.holding_periods),
                (&mut seen.local_periods, c.local_periods),
                (&mut seen.safe_stop_periods, c.safe_stop_periods),
            ] {
                *sum += x;
            }
        }
    }

    #[test]
    fn randomised_command_sequences_keep_the_invariants() {
        let mut seen = SupervisorCounters::default();
        for seed in 0..40u64 {
            let mut trial = Trial::new(seed);
            let mut k = 0u64;
            for _ in 0..300 {
                k += 1 + u64::from(trial.rng.below(20) == 0);
                trial.begin(k);
                let got = trial.commands(k);
                trial.end(k, &got);
            }
            trial.tally(&mut seen);
        }
        // The sequences did reach every outcome and every mode.
        let all = [
            seen.commands,
            seen.late,
            seen.missing,
            seen.too_old,
            seen.superseded,
            seen.duplicates,
            seen.warming_up,
            seen.rejected,
            seen.malformed,
            seen.future,
            seen.fallbacks,
            seen.holding_periods,
            seen.local_periods,
            seen.safe_stop_periods,
        ];
        assert!(all.iter().all(|&x| x > 0), "{seen:?}");
    }

    /// The mean the next sample would carry, without changing the supervisor.
    fn begin_mean(s: &mut Supervisor, k: u64, n: usize) -> Vec<f64> {
        let mut copy = s.clone();
        copy.begin_period(k, k as f64 * H, &vec![0.0; n], &refs(n))
            .unwrap()
            .applied_mean
    }
}
