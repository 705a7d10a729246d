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

use crate::lease::{Credentials, Fence, Lease, Pass};
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
    /// How late the controller's answers come: the most periods between a sample and
    /// its applied command lately ([`AnswerAge`]), which the lease's lapse waits out.
    answer_age: AnswerAge,
}

/// The most periods an applied command came after its sample, over the last
/// [`AnswerAge::WINDOW`] commands or so: the loop's round trip, in periods, as the plant
/// sees it. Pure counting on the agent's own periods.
#[derive(Debug, Clone, Copy, Default)]
struct AnswerAge {
    most: u32,
    /// Commands applied since `most` was last reached.
    since: u32,
}

impl AnswerAge {
    /// Commands after which the largest age, not seen again, counts one period less: a
    /// link that got faster shortens the lapse again within a second at 100 Hz.
    const WINDOW: u32 = 100;

    fn applied(&mut self, age: u64) {
        let age = u32::try_from(age).unwrap_or(u32::MAX);
        if age >= self.most {
            (self.most, self.since) = (age, 0);
        } else if self.since >= Self::WINDOW {
            (self.most, self.since) = (self.most - 1, 0);
        } else {
            self.since += 1;
        }
    }
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
            answer_age: AnswerAge::default(),
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
    /// hold, rounded up, at least one; longer, up to one period short of the hold, when
    /// the holder's answers come late: one period more than the latest of them lately
    /// (so never after the fallback would engage, and a holder whose round trip is as long
    /// as the lapse does not lose the lease to one unlucky run of answers: the fleet's
    /// simulation, seeds 31675, 51534 and 218981, links of 4-17 ms each way, a 10 ms
    /// period: answers 3 periods late, three silent periods in a row, a lapse, and the
    /// fallback while the holder claimed again). A longer lapse only makes the lease
    /// vacant later: it never lets two controllers hold it.
    pub fn lease_lapse(&self) -> u32 {
        let half = self.config.hold_periods.div_ceil(2).max(1);
        let longest = self.config.hold_periods.saturating_sub(1).max(half);
        half.max(self.answer_age.most.saturating_add(1))
            .min(longest)
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
        // The holder has been silent for half the hold (longer while its answers land late,
        // `Self::lease_lapse`): the lease lapses, so that another
        // controller can claim it (a new epoch) while the plant still holds, before the
        // fallback engages. A holder that answers "warming up" is not silent: it keeps the
        // lease while the fallback runs (the watchdog counts those periods, the lease not).
        let lapse = self.lease_lapse();
        if let Some(lease) = self.lease.as_mut().filter(|l| l.idle() >= lapse) {
            lease.lapse(k);
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
            Some(lease) => match lease.check(&cmd.lease, seq) {
                Ok(pass) => Some(pass),
                Err(fence) => return self.ignore(Ignored::Fenced(fence)),
            },
            None => None,
        };
        if let Some(why) = self.rule_out(k, &cmd) {
            // The holder's answer to a recent sample, overtaken by its newer one (the
            // network reordered them) or repeated: nothing to apply, but the holder is
            // alive and commanding, so its silence ends. Without this, a round trip as
            // long as the lapse, with jitter, lets a live holder's lease lapse on answers
            // that all came in the wrong order, and the plant holds, then falls back,
            // while it reclaims.
            let recent = k
                .checked_sub(seq)
                .is_some_and(|age| age < u64::from(self.lease_lapse()));
            let overtaken = matches!(why, Ignored::Superseded | Ignored::Duplicate);
            if let (Some(lease), Some(Pass::Holder), true) =
                (&mut self.lease, pass, recent && overtaken)
            {
                lease.heard();
            }
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
                self.answer_age.applied(k - seq);
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
mod tests;
