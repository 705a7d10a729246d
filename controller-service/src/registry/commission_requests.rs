//! A device's commissioning requests (start, confirm, abort) and its samples while a run
//! is under way: the device's side of [`super::commission`], whose rules the run holds.

use mfc::{commissioned_law, CommissionFinding, LawConfig, Order};
use protocol::{pb, printable};

use super::commission::{spec_of, Commission, Settle, Start, MAX_RUNNING, MAX_WHY};
use super::device::Device;
use crate::lease::Holder;

impl Device {
    /// Start a run on `req.channel` for `who`; why not if refused (nothing changed).
    /// `running_elsewhere`: the runs under way on the service's other devices.
    pub(super) fn start_commission(
        &mut self,
        req: &pb::CommissionRequest,
        who: &str,
        running_elsewhere: usize,
    ) -> Result<(), String> {
        if self.commission.as_ref().is_some_and(|c| c.running()) {
            return Err("a run is under way on this device: abort it first".into());
        }
        if running_elsewhere >= MAX_RUNNING {
            return Err(format!(
                "{MAX_RUNNING} runs are under way on this service already"
            ));
        }
        let st = self.check_start(req)?;
        let mut why = printable(&req.reason);
        if why.len() > MAX_WHY {
            let cut = (0..=MAX_WHY).rev().find(|&k| why.is_char_boundary(k));
            why.truncate(cut.unwrap_or(0));
        }
        self.commission = Some(Box::new(Commission {
            number: self.commission.as_ref().map_or(1, |c| c.number + 1),
            channel: st.channel,
            run: None,
            settle: Some(Settle::default()),
            spec: st.spec,
            dynamics: st.dynamics,
            phase: pb::CommissionPhase::CommissionRunning,
            started_by: who.into(),
            ended_by: String::new(),
            why,
            t0: None,
            last_t: self.last_time,
            y0: None,
            deviation: 0.0,
            alpha_before: st.alpha,
            finding: None,
            proposed: None,
            reason: "waiting for the loop to settle".into(),
            sent_u: st.u0,
        }));
        Ok(())
    }

    /// Every rule a start must pass that is about the device and the request.
    fn check_start(&self, req: &pb::CommissionRequest) -> Result<Start, String> {
        let i = req.channel as usize;
        let n = self.channels();
        if i >= n {
            return Err(format!("channel {i}: the device has {n} channels"));
        }
        let law = self.config(i).law;
        let LawConfig::Intelligent { params, .. } = law else {
            return Err(format!(
                "channel {i}: its law is not intelligent, there is no alpha to find"
            ));
        };
        let (spec, dynamics) = spec_of(req)?;
        if let Some((lo, hi)) = self.bounds[i].range() {
            if spec.max_deviation > hi - lo {
                return Err(format!(
                    "max_deviation {} is wider than the channel's whole range [{lo}, {hi}]",
                    spec.max_deviation
                ));
            }
        }
        // Refused up front if an order the run may find gives no law with these gains.
        let orders = match spec.order {
            Some(o) => vec![o],
            None => vec![Order::One, Order::Two],
        };
        for order in orders {
            let fit = mfc::CommissionFit {
                order,
                alpha: params.alpha,
                explained: 1.0,
            };
            let probe = CommissionFinding {
                best: fit,
                fits: [None, None],
                samples: 0,
            };
            if commissioned_law(&law, &probe, dynamics).is_none() {
                return Err(format!(
                    "a finding of order {} would give no law with these gains (kp and kd must be positive, or ask for error dynamics)",
                    order.n()
                ));
            }
        }
        let under_control = self
            .last_command
            .as_ref()
            .is_some_and(|c| c.mode == pb::Mode::Control as i32);
        if !under_control {
            return Err("the device is not under control (no CONTROL answer yet, or warming up): start once it is".into());
        }
        if matches!(self.claimer.holder, Holder::Other | Holder::Vacant) {
            return Err("this member does not command the plant (another holds its lease)".into());
        }
        let map = self.mimo.channels()[i].output_map();
        let v0 = self.held.as_ref().and_then(|h| h.get(i).copied());
        Ok(Start {
            channel: i,
            spec,
            dynamics,
            alpha: params.alpha,
            u0: map.inverse(v0.unwrap_or(0.0)),
        })
    }

    /// The input the run in force asks for channel `c.channel` at sample `s`, with the
    /// abort rules that do not come from the run itself.
    pub(super) fn commission_input(&mut self, s: &pb::Sample) -> Option<(usize, f64)> {
        let c = self.commission.as_mut().filter(|c| c.running())?;
        let i = c.channel;
        // A plant that holds (a command came late) keeps a level it says it applies: the
        // data stay good. One that holds without saying what, or is on its fallback or
        // stopped, gives data the fit cannot use.
        let trouble = pb::SampleFlags::Fallback as u32 | pb::SampleFlags::SafeStop as u32;
        if s.flags & trouble != 0 {
            let why = "the plant left control (its fallback, or a safe stop)";
            c.abort("service", why.into());
            return None;
        }
        if s.flags & pb::SampleFlags::Holding as u32 != 0 && s.applied.is_empty() {
            let why = "the plant held a late command without saying what it applied";
            c.abort("service", why.into());
            return None;
        }
        let map = self.mimo.channels()[i].output_map();
        let held = self.held.as_ref().and_then(|h| h.get(i).copied());
        let error = s.outputs[i] - self.refs[i].y;
        let y = s.outputs[i];
        if c.settling(s.plant_time, (y, error), map.inverse(held.unwrap_or(0.0))) {
            return None;
        }
        let applied = s.applied.get(i).map(|v| map.inverse(*v));
        let u = c.input(s.plant_time, s.outputs[i], applied);
        if c.phase == pb::CommissionPhase::CommissionProposed {
            let f = c.finding.expect("a proposal has its finding");
            c.proposed = commissioned_law(&self.mimo.channels()[i].config().law, &f, c.dynamics);
            if c.proposed.is_none() {
                c.abort("service", "the finding gives no law".into());
            }
        }
        u.map(|u| (i, u))
    }

    /// End a run whose device has not been heard for `silent_ns` (its slot among
    /// [`MAX_RUNNING`] is freed); whether it was running.
    pub(super) fn abort_silent_commission(&mut self, silent_ns: u64) -> bool {
        let running = self.commission.as_ref().is_some_and(|c| c.running());
        if running {
            let s = silent_ns as f64 / 1e9;
            self.abort_commission(&format!("no sample for {s:.1} s"));
        }
        running
    }

    /// Put the proposal of run `number` (0: the last) on `channel` in force for `who`.
    pub(super) fn confirm_commission(
        &mut self,
        (channel, number): (usize, u64),
        who: &str,
    ) -> Result<(), String> {
        let c = self.own_run(channel, number)?;
        let Some(law) = c
            .proposed
            .filter(|_| c.phase == pb::CommissionPhase::CommissionProposed)
        else {
            return Err(format!("nothing to confirm: the run is {}", c.setting()));
        };
        let mut configs = self.configs();
        configs[channel].law = law;
        self.check_bounds(&configs, None)?;
        self.mimo.reconfigure(&configs).map_err(|e| e.to_string())?;
        if let Some(c) = self.commission.as_mut() {
            c.phase = pb::CommissionPhase::CommissionApplied;
            who.clone_into(&mut c.ended_by);
        }
        Ok(())
    }

    /// Stop run `number` (0: the last) on `channel`, or dismiss its proposal, for `who`.
    pub(super) fn dismiss_commission(
        &mut self,
        (channel, number): (usize, u64),
        who: &str,
    ) -> Result<(), String> {
        let c = self.own_run(channel, number)?;
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

    fn own_run(&self, channel: usize, number: u64) -> Result<&Commission, String> {
        match &self.commission {
            None => Err("no commissioning run on this device".into()),
            Some(c) if c.channel != channel => Err(format!(
                "the last run is on channel {}, not {channel}",
                c.channel
            )),
            Some(c) if number != 0 && number != c.number => Err(format!(
                "run {number} is not the last one on this device (run {} is): look again",
                c.number
            )),
            Some(c) => Ok(c),
        }
    }
}
