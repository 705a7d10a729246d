//! The networked loop in lockstep: the service's per-device rules (its [`Registry`]) and
//! the agent's safety state machine (its [`Supervisor`]), with a seeded model of a lossy,
//! delayed link between them, and the plant, all in one thread on a simulated clock.
//!
//! It is the loop of `plant-agent` and `controller-service` without Zenoh, sockets or real
//! time: every decision is made by the same code as in production, only the transport is a
//! model (each message lost with a probability, delayed by a uniform draw in
//! `delay ± jitter`, and so possibly reordered). A run takes a fraction of a second and is
//! bit-for-bit repeatable, which is what designing a controller for a bad network needs;
//! the fault campaign (`mfc-lab campaign`) measures the real thing, through a real relay,
//! in real time.

use std::collections::VecDeque;

use controller_service::config::Prediction;
use controller_service::registry::{Registry, Via};
use mfc::trajectory::evaluate;
use mfc::Reference;
use plant::record::{Accumulator, ChannelMetrics};
use plant::scenario::{ControllerSet, Scenario};
use plant_agent::safety::{
    IncomingCommand, LoopMode, PeriodBegin, SafetyConfig, Supervisor, SupervisorCounters, Verdict,
};
use plant_agent::wire::sample_flags;
use protocol::{pb, PROTOCOL_VERSION};
use rand_xoshiro::rand_core::{Rng as _, SeedableRng};
use rand_xoshiro::Xoshiro256StarStar;
use serde::{Deserialize, Serialize};
use simulation::Events;

use crate::harness::service_config;
use crate::offline::RunError;

/// Which way a link loses messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "snake_case")]
pub enum Lossy {
    /// Samples and commands alike.
    Both,
    /// Samples only (plant to controller).
    Up,
    /// Commands only (controller to plant).
    Down,
}

/// The link: delays the same both ways, losses where `lossy` says.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LinkModel {
    /// Probability that a message is lost, on the ways `lossy` says.
    pub loss: f64,
    /// Which way messages are lost.
    pub lossy: Lossy,
    /// One-way delay (s).
    pub delay: f64,
    /// Half-width of the uniform spread around `delay` (s).
    pub jitter: f64,
    /// Seed of the draws.
    pub seed: u64,
}

impl LinkModel {
    /// A perfect link: nothing lost, no delay.
    pub const PERFECT: Self = Self {
        loss: 0.0,
        lossy: Lossy::Both,
        delay: 0.0,
        jitter: 0.0,
        seed: 0,
    };

    /// Check the figures.
    pub fn check(&self) -> Result<(), String> {
        if !(0.0..=1.0).contains(&self.loss) {
            return Err(format!("loss {} is not between 0 and 1", self.loss));
        }
        for (name, v) in [("delay", self.delay), ("jitter", self.jitter)] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} {v} is not a finite number >= 0"));
            }
        }
        Ok(())
    }
}

/// The service killed (kill -9) and started again from its last snapshot, as the
/// crash-and-restart fault test does in real time.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ServiceCrash {
    /// Plant time (s) of the kill: samples after it reach no one.
    pub kill: f64,
    /// Plant time (s) of the restart, from the last snapshot taken before the kill.
    pub restart: f64,
    /// How long (s) after the restart its samples still reach no one (in production:
    /// until the plant's Zenoh session has found the new process).
    pub unseen: f64,
    /// How long (s) after the restart the agent still ignores the service's commands
    /// while it hears its samples (in production: until the plant grants the new
    /// process its lease).
    pub unheard: f64,
    /// Snapshot interval (s); the service's `snapshots.interval_ms`.
    pub snapshot_every: f64,
}

/// What a run gave.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NetRun {
    /// Controller (with its options).
    pub controller: String,
    /// Per channel, over the whole run.
    pub channels: Vec<ChannelMetrics>,
    /// The agent's counters.
    pub counters: SupervisorCounters,
    /// Samples the link lost, and commands.
    pub samples_lost: u64,
    pub commands_lost: u64,
    /// With a [`ServiceCrash`]: the plant time (s) remote control resumed after it, and
    /// per channel the largest tracking error from then on.
    pub after_restart: Option<(f64, Vec<f64>)>,
}

#[derive(Debug)]
enum Event {
    /// A sample reaches the service.
    Sample(pb::Sample),
    /// A command reaches the agent; the plant time of the sample it answers.
    Command(pb::Command, f64),
}

/// Run `scenario` with `controller` (and the service's `prediction` for its device)
/// through `link`, with the agent's `safety` settings.
pub fn simulate_net(
    scenario: &Scenario,
    controller: &ControllerSet,
    prediction: Prediction,
    link: &LinkModel,
    safety: SafetyConfig,
) -> Result<NetRun, RunError> {
    simulate_crash(scenario, controller, prediction, link, safety, None)
}

/// [`simulate_net`], with the service killed and restarted from its snapshot if `crash`
/// says so.
pub fn simulate_crash(
    scenario: &Scenario,
    controller: &ControllerSet,
    prediction: Prediction,
    link: &LinkModel,
    safety: SafetyConfig,
    crash: Option<ServiceCrash>,
) -> Result<NetRun, RunError> {
    link.check().map_err(|reason| RunError::Link { reason })?;
    scenario.check_controller(controller)?;
    let n = scenario.channels.len();
    let id = "net-1".to_string();
    let mut config = service_config(scenario, controller, std::slice::from_ref(&id));
    for d in &mut config.devices {
        d.prediction = prediction;
    }
    let mut service = Service::new(config, crash)?;
    let mut plant = plant::open(&scenario.plant, scenario.seed, n)?;
    let initial = plant.write(&vec![0.0; n])?;
    let mut sup = Supervisor::new(safety, &scenario.channel_configs(controller), initial)
        .map_err(lockstep_error)?;
    let mut net = InFlight::new(link);
    let h = scenario.period;
    let mut acc = vec![Accumulator::default(); n];
    let mut refs = vec![Reference::default(); n];
    let mut last_rtt_us = 0u32;
    let mut previous: VecDeque<(f64, Vec<f64>, Vec<f64>)> =
        VecDeque::with_capacity(protocol::RESENT_SAMPLES);
    let mut after_restart: Option<(f64, Vec<f64>)> = None;
    for k in 0..scenario.steps() {
        let t = k as f64 * h;
        service.tick(t)?;
        let y = plant.read()?;
        for (r, c) in refs.iter_mut().zip(&scenario.channels) {
            *r = evaluate(&c.reference, t);
        }
        let begin = sup
            .begin_period(k as u64, t, &y, &refs)
            .map_err(lockstep_error)?;
        if let Some(v) = &begin.write {
            let a = plant.write(v)?;
            sup.applied(&a);
        }
        let sample = sample(&id, (k, t), &y, &begin, last_rtt_us, &previous);
        if previous.len() == protocol::RESENT_SAMPLES {
            previous.pop_back();
        }
        previous.push_front((t, y.clone(), begin.applied_mean.clone()));
        net.send_sample(t, sample);
        while let Some((at, event)) = net.next_before(ns(t + h)) {
            match event {
                Event::Sample(s) => {
                    if let Some(cmd) = service.answer(&id, &s, at) {
                        net.send_command(at, cmd, s.plant_time);
                    }
                }
                Event::Command(cmd, sent) => {
                    let now = at as f64 * 1e-9;
                    if service.unheard(now) {
                        continue;
                    }
                    last_rtt_us = ((now - sent) * 1e6).round().clamp(1.0, u32::MAX as f64) as u32;
                    let (verdict, _) = sup.on_command(now - t, IncomingCommand::from_wire(&cmd));
                    if let Verdict::Apply { v, advance, .. } = verdict {
                        plant.advance(advance)?;
                        let a = plant.write(&v)?;
                        sup.applied(&a);
                    }
                }
            }
        }
        let end = sup.end_period().map_err(lockstep_error)?;
        plant.advance(end.advance)?;
        let applied = sup.applied_now();
        for (i, c) in scenario.channels.iter().enumerate() {
            acc[i].add(y[i] - refs[i].y, h, applied[i], c.saturated(applied[i]));
        }
        if crash.is_some_and(|c| t > c.restart) {
            let worst = after_restart.get_or_insert_with(|| (f64::NAN, vec![0.0; n]));
            if worst.0.is_nan() && sup.mode() == LoopMode::Remote {
                worst.0 = t;
            }
            if !worst.0.is_nan() {
                for (w, (y, r)) in worst.1.iter_mut().zip(y.iter().zip(&refs)) {
                    *w = w.max((y - r.y).abs());
                }
            }
        }
    }
    plant.stop()?;
    Ok(NetRun {
        controller: controller.name.clone(),
        channels: crate::offline::finish(&acc, scenario),
        counters: sup.counters().clone(),
        samples_lost: net.samples_lost,
        commands_lost: net.commands_lost,
        after_restart,
    })
}

/// The service in lockstep, with its crash if any: alive until the kill, dead until the
/// restart, then a new registry restored from the last snapshot before the kill.
struct Service {
    config: controller_service::config::ServiceConfig,
    registry: Option<Registry>,
    crash: Option<ServiceCrash>,
    snapshots: Vec<controller_service::snapshot::DeviceSnapshot>,
    next_snapshot: f64,
    restarted: bool,
}

impl Service {
    fn new(
        config: controller_service::config::ServiceConfig,
        crash: Option<ServiceCrash>,
    ) -> Result<Self, RunError> {
        Ok(Self {
            registry: Some(Registry::new(config.clone()).map_err(lockstep_error)?),
            config,
            crash,
            snapshots: Vec::new(),
            next_snapshot: 0.0,
            restarted: false,
        })
    }

    /// At plant time `t`: snapshot, kill or restart when due.
    fn tick(&mut self, t: f64) -> Result<(), RunError> {
        let Some(c) = self.crash else {
            return Ok(());
        };
        if let Some(r) = self.registry.as_ref().filter(|_| t >= self.next_snapshot) {
            self.snapshots = r.snapshots();
            self.next_snapshot += c.snapshot_every;
        }
        if !self.restarted && t >= c.kill && self.registry.is_some() {
            self.registry = None;
        }
        if !self.restarted && t >= c.restart {
            let mut r = Registry::new(self.config.clone()).map_err(lockstep_error)?;
            for s in &self.snapshots {
                r.restore(s).map_err(lockstep_error)?;
            }
            self.registry = Some(r);
            self.restarted = true;
            self.next_snapshot = t + c.snapshot_every;
        }
        Ok(())
    }

    /// The answer to sample `s` arriving at `at` (ns), if the service is up and answers.
    fn answer(&mut self, id: &str, s: &pb::Sample, at: u64) -> Option<pb::Command> {
        if self
            .crash
            .is_some_and(|c| at as f64 * 1e-9 < c.restart + c.unseen)
            && self.restarted
        {
            return None;
        }
        let mut cmd = pb::Command::default();
        self.registry
            .as_mut()?
            .handle_sample(Via::key(id), s, at, &mut cmd)
            .answered()
            .then_some(cmd)
    }

    /// The agent ignores commands arriving at `now` (s): the restarted service is not yet
    /// its controller.
    fn unheard(&self, now: f64) -> bool {
        self.crash
            .is_some_and(|c| self.restarted && now < c.restart + c.unheard)
    }
}

fn lockstep_error(e: impl std::fmt::Display) -> RunError {
    RunError::Link {
        reason: e.to_string(),
    }
}

/// Seconds as integer nanoseconds, so that the heap orders times exactly.
fn ns(s: f64) -> u64 {
    (s * 1e9).round() as u64
}

/// Sample `k` (at plant time `t`) as the agent would publish it, with the earlier ones it
/// carries again, timestamped with the simulated clock.
fn sample(
    id: &str,
    (k, t): (usize, f64),
    y: &[f64],
    begin: &PeriodBegin,
    last_rtt_us: u32,
    previous: &VecDeque<(f64, Vec<f64>, Vec<f64>)>,
) -> pb::Sample {
    pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: id.to_string(),
        seq: k as u64,
        plant_time: t,
        outputs: y.to_vec(),
        applied: begin.applied_mean.clone(),
        flags: sample_flags(begin.sample_mode),
        sent_unix_ns: ns(t),
        last_rtt_us,
        run_id: 1,
        previous_plant_time: previous.iter().map(|p| p.0).collect(),
        previous_outputs: previous.iter().flat_map(|p| p.1.iter().copied()).collect(),
        previous_applied: previous.iter().flat_map(|p| p.2.iter().copied()).collect(),
        // One controller in lockstep: no lease to grant (`Supervisor::grant_leases`).
        ..Default::default()
    }
}

/// The link's messages in flight, in the order they arrive, with its seeded draws.
struct InFlight {
    link: LinkModel,
    rng: Xoshiro256StarStar,
    /// By arrival (ns), the earliest first, ties in the order sent.
    queue: Events<u64, Event>,
    samples_lost: u64,
    commands_lost: u64,
}

impl InFlight {
    fn new(link: &LinkModel) -> Self {
        Self {
            link: *link,
            rng: Xoshiro256StarStar::seed_from_u64(link.seed),
            queue: Events::new(),
            samples_lost: 0,
            commands_lost: 0,
        }
    }

    fn uniform(&mut self) -> f64 {
        (self.rng.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// One draw says whether a message is lost, the next how long it takes.
    fn draw(&mut self) -> (bool, f64) {
        let lost = self.uniform() < self.link.loss;
        let delay = (self.link.delay + self.link.jitter * (2.0 * self.uniform() - 1.0)).max(0.0);
        (lost, delay)
    }

    fn push(&mut self, at: u64, event: Event) {
        self.queue.push(at, event);
    }

    /// The agent sends a sample at plant time `t`.
    fn send_sample(&mut self, t: f64, sample: pb::Sample) {
        let (lost, delay) = self.draw();
        if lost && self.link.lossy != Lossy::Down {
            self.samples_lost += 1;
        } else {
            self.push(ns(t + delay), Event::Sample(sample));
        }
    }

    /// The service answers at `at` (ns) the sample taken at plant time `sent`.
    fn send_command(&mut self, at: u64, cmd: pb::Command, sent: f64) {
        let (lost, delay) = self.draw();
        if lost && self.link.lossy != Lossy::Up {
            self.commands_lost += 1;
        } else {
            self.push(at + ns(delay), Event::Command(cmd, sent));
        }
    }

    /// The next message to arrive before `end` (ns), with its arrival time.
    fn next_before(&mut self, end: u64) -> Option<(u64, Event)> {
        self.queue.pop_before(end)
    }
}
