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
//!   and [`MAX_PERIOD`], and with the loop settled (the output within a quarter of that
//!   deviation of its reference). The run excites around the input the plant holds.
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

use mfc::{
    commissioned_law, CommissionFinding, CommissionSpec, CommissionStep, Commissioning, LawConfig,
    Order,
};
use protocol::convert::channel_to_pb;
use protocol::{pb, printable};

use super::device::Device;
use crate::lease::Holder;

/// Runs at once in one service at most: a run holds its estimators' windows (about 20
/// KiB), and commissioning is an operator's deliberate act on a few plants, not a fleet's.
pub const MAX_RUNNING: usize = 16;
/// Periods of the square wave at most.
pub const MAX_CYCLES: u32 = 20;
/// The square wave's period at most (s).
pub const MAX_PERIOD: f64 = 600.0;

/// A device's last commissioning run.
#[derive(Debug, Clone)]
pub(super) struct Commission {
    pub(super) channel: usize,
    /// The run, while it runs.
    run: Option<Box<Commissioning>>,
    spec: CommissionSpec,
    dynamics: Option<(f64, f64)>,
    pub(super) phase: pb::CommissionPhase,
    started_by: String,
    ended_by: String,
    /// Plant time of the first sample and of the last one seen (s).
    t0: Option<f64>,
    last_t: f64,
    /// The output at the first sample, and the largest deviation from it seen.
    y0: Option<f64>,
    deviation: f64,
    alpha_before: f64,
    finding: Option<CommissionFinding>,
    proposed: Option<LawConfig>,
    reason: String,
    /// The input sent with the last command (the law's units), what the plant got since
    /// unless its sample says otherwise.
    sent_u: f64,
}

impl Commission {
    pub(super) fn running(&self) -> bool {
        self.phase == pb::CommissionPhase::CommissionRunning
    }

    /// End the run (or dismiss the proposal) without a change.
    pub(super) fn abort(&mut self, by: &str, why: String) {
        self.run = None;
        self.phase = pb::CommissionPhase::CommissionAborted;
        by.clone_into(&mut self.ended_by);
        self.reason = why;
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
                    order_number(f.best.order)
                )
            })
            .unwrap_or_default();
        let s = &self.spec;
        format!(
            "{phase} ({by}): +-{} for {} x {} s, max deviation {}{found}",
            s.amplitude, s.cycles, s.period, s.max_deviation
        )
    }

    pub(super) fn status_pb(&self, output: mfc::OutputMapConfig) -> pb::CommissionStatus {
        let fits = self.finding.map_or(Vec::new(), |f| {
            f.fits
                .iter()
                .flatten()
                .map(|fit| pb::CommissionFit {
                    order: order_number(fit.order),
                    alpha: fit.alpha,
                    explained: fit.explained,
                })
                .collect()
        });
        pb::CommissionStatus {
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
                .filter(|_| self.finding.is_some())
                .map(|law| channel_to_pb(&mfc::ChannelConfig { law, output })),
            reason: self.reason.clone(),
        }
    }
}

fn order_number(o: Order) -> u32 {
    u32::from(o.n())
}

/// A start request's specification, checked: every value the operator must set is set,
/// nothing beyond the service's limits.
fn spec_of(req: &pb::CommissionRequest) -> Result<(CommissionSpec, Option<(f64, f64)>), String> {
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

impl Device {
    /// Start a run on `req.channel` for `who`; why not if refused (nothing changed).
    pub(super) fn start_commission(
        &mut self,
        req: &pb::CommissionRequest,
        who: &str,
        running_elsewhere: usize,
    ) -> Result<(), String> {
        let i = req.channel as usize;
        let n = self.channels();
        if i >= n {
            return Err(format!("channel {i}: the device has {n} channels"));
        }
        if self.commission.as_ref().is_some_and(|c| c.running()) {
            return Err("a run is under way on this device: abort it first".into());
        }
        if running_elsewhere >= MAX_RUNNING {
            return Err(format!(
                "{MAX_RUNNING} runs are under way on this service already"
            ));
        }
        let LawConfig::Intelligent { params, .. } = self.configs[i].law else {
            return Err(format!(
                "channel {i}: its law is not intelligent, there is no alpha to find"
            ));
        };
        let (spec, dynamics) = spec_of(req)?;
        let under_control = self
            .last_command
            .as_ref()
            .is_some_and(|c| c.mode == pb::Mode::Control as i32);
        if !under_control {
            return Err("the device is not under control (no CONTROL answer yet, or warming up): start once it is".into());
        }
        // A run started while the output travels to its reference would measure the
        // transient and soon leave its band: the loop must have settled first.
        let error = self.outputs[i].error;
        // Written so that a NaN error is not settled.
        let settled = error.abs() <= spec.max_deviation / 4.0;
        if !settled {
            return Err(format!(
                "channel {i} is {error:.4} from its reference, more than a quarter of max_deviation: start once it has settled"
            ));
        }
        if matches!(self.claimer.holder, Holder::Other | Holder::Vacant) {
            return Err("this member does not command the plant (another holds its lease)".into());
        }
        let map = self.mimo.channels()[i].output_map();
        let v0 = self
            .held
            .as_ref()
            .and_then(|h| h.get(i).copied())
            .unwrap_or(0.0);
        let u0 = map.inverse(v0);
        let run = Commissioning::new(spec, u0).map_err(|e| e.to_string())?;
        let proposed_for =
            |f: &CommissionFinding| commissioned_law(&self.configs[i].law, f, dynamics);
        // Checked now so that a request whose gains can give no law is refused up front
        // (a finding of either order must give one).
        let probe = CommissionFinding {
            best: mfc::CommissionFit {
                order: params.order,
                alpha: params.alpha,
                explained: 1.0,
            },
            fits: [None, None],
            samples: 0,
        };
        if proposed_for(&probe).is_none() {
            return Err("no law comes from these gains".into());
        }
        self.commission = Some(Box::new(Commission {
            channel: i,
            run: Some(Box::new(run)),
            spec,
            dynamics,
            phase: pb::CommissionPhase::CommissionRunning,
            started_by: who.into(),
            ended_by: String::new(),
            t0: None,
            last_t: self.last_time,
            y0: None,
            deviation: 0.0,
            alpha_before: params.alpha,
            finding: None,
            proposed: None,
            reason: String::new(),
            sent_u: u0,
        }));
        Ok(())
    }

    /// The input the run in force asks for channel `c.channel` at sample `s`, with the
    /// abort rules that do not come from the run itself.
    pub(super) fn commission_input(&mut self, s: &pb::Sample) -> Option<(usize, f64)> {
        let c = self.commission.as_mut().filter(|c| c.running())?;
        let i = c.channel;
        // A plant that holds (a command came late) keeps the square wave's level and
        // says what it applied: the data stay good. One on its fallback or stopped does
        // not apply the run's input at all.
        let trouble = pb::SampleFlags::Fallback as u32 | pb::SampleFlags::SafeStop as u32;
        if s.flags & trouble != 0 {
            let why = "the plant left control (its fallback, or a safe stop)";
            c.abort("service", why.into());
            return None;
        }
        let map = self.mimo.channels()[i].output_map();
        let applied = s.applied.get(i).map(|v| map.inverse(*v));
        let u = c.input(s.plant_time, s.outputs[i], applied);
        if c.phase == pb::CommissionPhase::CommissionProposed {
            let f = c.finding.expect("a proposal has its finding");
            c.proposed = commissioned_law(&self.configs[i].law, &f, c.dynamics);
            if c.proposed.is_none() {
                c.abort("service", "the finding gives no law".into());
            }
        }
        u.map(|u| (i, u))
    }

    /// Abort a run in force for `why` (a restart, a change of configuration, the lease).
    pub(super) fn abort_commission(&mut self, why: &str) {
        if let Some(c) = self.commission.as_mut().filter(|c| c.running()) {
            c.abort("service", why.into());
        }
    }

    /// Put the proposal of the run on `channel` in force for `who`.
    pub(super) fn confirm_commission(&mut self, channel: usize, who: &str) -> Result<(), String> {
        let c = self.own_run(channel)?;
        let Some(law) = c
            .proposed
            .filter(|_| c.phase == pb::CommissionPhase::CommissionProposed)
        else {
            return Err(format!("nothing to confirm: the run is {}", c.setting()));
        };
        let mut configs = self.configs.clone();
        configs[channel].law = law;
        self.check_bounds(&configs, None)?;
        self.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
        self.configs = configs;
        if let Some(c) = self.commission.as_mut() {
            c.phase = pb::CommissionPhase::CommissionApplied;
            who.clone_into(&mut c.ended_by);
        }
        Ok(())
    }

    /// Stop the run on `channel`, or dismiss its proposal, for `who`.
    pub(super) fn dismiss_commission(&mut self, channel: usize, who: &str) -> Result<(), String> {
        let c = self.own_run(channel)?;
        if !matches!(
            c.phase,
            pb::CommissionPhase::CommissionRunning | pb::CommissionPhase::CommissionProposed
        ) {
            return Err(format!("nothing to abort: the run is {}", c.setting()));
        }
        if let Some(c) = self.commission.as_mut() {
            let what = if c.running() { "stopped" } else { "dismissed" };
            c.abort(who, format!("{what} by {}", printable(who)));
        }
        Ok(())
    }

    fn own_run(&self, channel: usize) -> Result<&Commission, String> {
        match &self.commission {
            None => Err("no commissioning run on this device".into()),
            Some(c) if c.channel != channel => Err(format!(
                "the last run is on channel {}, not {channel}",
                c.channel
            )),
            Some(c) => Ok(c),
        }
    }
}
