//! Commissioning offline: `mfc::commission` run against a plant in lockstep, channel by
//! channel, from a controller whose `α` is wrong, and the scenario then run with what it
//! found.
//!
//! This is the offline twin of commissioning a live rig: the same pure procedure, fed by
//! the same [`plant::Plant`] (the AERO simulator or a driver process), with the time in the
//! samples. Each intelligent channel in turn: the plant starts at rest, the other channels
//! run their laws on the scenario's initial reference, and the channel being commissioned
//! gets its held input plus the square wave, through its own output map (so the plant's
//! limits apply), until the run finds `α` and the order or aborts. The law that comes out
//! keeps the channel's error dynamics (its gains) and everything else; only `α` changes,
//! and the gains are recomputed from the same error dynamics if the order does.

use mfc::{
    commissioned_law, CommissionFinding, CommissionSpec, CommissionStep, Commissioning, LawConfig,
    MimoController, OutputMap, Reference,
};
use plant::scenario::{ControllerSet, Scenario};

mod live;
pub use live::commission_live;

use crate::offline::RunError;

/// What commissioning one channel gave.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ChannelCommission {
    /// The channel.
    pub channel: usize,
    /// `α` before.
    pub alpha_before: f64,
    /// What the run found, or why it found nothing.
    pub outcome: Result<CommissionFinding, String>,
    /// Plant time the run took (s).
    pub seconds: f64,
}

/// Commission `channel` of `set` on `scenario`'s plant, from rest.
pub fn commission_channel(
    scenario: &Scenario,
    set: &ControllerSet,
    channel: usize,
    spec: CommissionSpec,
) -> Result<ChannelCommission, RunError> {
    scenario.check_controller(set)?;
    let n = scenario.channels.len();
    let configs = scenario.channel_configs(set);
    let bad = |reason| RunError::Controller {
        controller: set.name.clone(),
        reason,
    };
    let Some(LawConfig::Intelligent { params, .. }) = set.channels.get(channel) else {
        return Err(RunError::Bench(format!(
            "channel {channel} of `{}` is not an intelligent law: nothing to commission",
            set.name
        )));
    };
    let alpha_before = params.alpha;
    let mut mimo: MimoController = MimoController::new(&configs).map_err(bad)?;
    let mut map = OutputMap::new(configs[channel].output).map_err(bad)?;
    let mut plant = plant::open(&scenario.plant, scenario.seed, n)?;
    let h = scenario.period;
    let refs: Vec<Reference> = scenario
        .channels
        .iter()
        .map(|c| mfc::trajectory::evaluate(&c.reference, 0.0))
        .map(|r| Reference {
            dy: 0.0,
            ddy: 0.0,
            ..r
        })
        .collect();
    let mut out = vec![mfc::ChannelOutput::default(); n];
    let (mut applied_u, mut t) = (0.0, 0.0);
    let mut run: Commissioning = Commissioning::new(spec, 0.0).map_err(bad)?;
    let limit = ((spec.duration() + 1.0) / h).ceil() as usize + 2;
    let mut outcome = Err("the run did not end".to_string());
    for k in 0..limit {
        t = k as f64 * h;
        let y = plant.read()?;
        mimo.step(t, &y, &refs, &mut out).map_err(bad)?;
        let mut v: Vec<f64> = out.iter().map(|o| o.v).collect();
        match run.step(t, y[channel], applied_u).map_err(bad)? {
            CommissionStep::Apply(u) => v[channel] = map.apply(t, u).map_err(bad)?,
            CommissionStep::Done(f) => {
                outcome = Ok(f);
                break;
            }
            CommissionStep::Aborted(a) => {
                outcome = Err(a.to_string());
                break;
            }
        }
        let applied = plant.write(&v)?;
        map.record_applied(t, applied[channel]);
        applied_u = map.inverse(applied[channel]);
        let _ = mimo.report_applied(&applied);
        plant.advance(h)?;
    }
    plant.stop()?;
    Ok(ChannelCommission {
        channel,
        alpha_before,
        outcome,
        seconds: t,
    })
}

/// Commission every intelligent channel of `set` in turn (each from rest, the channels
/// before it already commissioned), with `specs[i]` for channel `i`: the set that comes out
/// and what each run gave. A channel whose run found nothing is tried once more after the
/// others (a coupled plant's other loops, still on a wrong `α`, can drown its response);
/// if that finds nothing either, it keeps its law.
pub fn commission_all(
    scenario: &Scenario,
    set: &ControllerSet,
    specs: &[CommissionSpec],
) -> Result<(ControllerSet, Vec<ChannelCommission>), RunError> {
    let mut current = set.clone();
    let mut runs = Vec::new();
    let mut retry = Vec::new();
    let channels: Vec<usize> = (0..specs.len().min(set.channels.len()))
        .filter(|&i| matches!(set.channels[i], LawConfig::Intelligent { .. }))
        .collect();
    for &i in &channels {
        let r = commission_channel(scenario, &current, i, specs[i])?;
        adopt(&mut current, &r);
        if r.outcome.is_err() && channels.len() > 1 {
            retry.push(i);
        }
        runs.push(r);
    }
    for i in retry {
        let r = commission_channel(scenario, &current, i, specs[i])?;
        adopt(&mut current, &r);
        runs.push(r);
    }
    current.name = format!("{}-commissioned", set.name);
    current.description = format!("`{}` with alpha found by `mfc-lab commission`", set.name);
    Ok((current, runs))
}

/// The law a run found, in place of the channel's.
fn adopt(set: &mut ControllerSet, run: &ChannelCommission) {
    if let Ok(f) = &run.outcome {
        if let Some(law) = commissioned_law(&set.channels[run.channel], f, None) {
            set.channels[run.channel] = law;
        }
    }
}

/// `set` with every intelligent channel's `α` multiplied by `scale`: a deliberately wrong
/// start.
pub fn scale_alpha(set: &ControllerSet, scale: f64) -> ControllerSet {
    let mut s = set.clone();
    for law in &mut s.channels {
        if let LawConfig::Intelligent { params, .. } = law {
            params.alpha *= scale;
        }
    }
    s.name = format!("{}-alpha-x{scale}", set.name);
    s
}

/// The runs and the RMS comparison as markdown: per channel what was found, then each
/// controller's RMS per channel on the scenario.
pub fn report(
    runs: &[ChannelCommission],
    rms: &[(String, Vec<f64>)],
    channels: &[String],
) -> String {
    let mut md = String::from(
        "| channel | alpha before | alpha found | order | r² order 1 / 2 | plant time (s) |\n|---|---:|---:|---:|---|---:|\n",
    );
    let r2 =
        |f: Option<mfc::CommissionFit>| f.map_or("-".into(), |f| format!("{:.2}", f.explained));
    for r in runs {
        let name = channels.get(r.channel).map_or("?", String::as_str);
        match &r.outcome {
            Ok(f) => {
                md += &format!(
                    "| {name} | {:.4e} | {:.4e} | {} | {} / {} | {:.1} |\n",
                    r.alpha_before,
                    f.best.alpha,
                    f.best.order.n(),
                    r2(f.fits[0]),
                    r2(f.fits[1]),
                    r.seconds
                )
            }
            Err(why) => {
                md += &format!(
                    "| {name} | {:.4e} | - ({why}) | - | - | {:.1} |\n",
                    r.alpha_before, r.seconds
                )
            }
        }
    }
    md += "\n| controller |";
    for c in channels {
        md += &format!(" {c} RMS |");
    }
    md += "\n|---|";
    md += &"---:|".repeat(channels.len());
    md += "\n";
    for (name, values) in rms {
        md += &format!("| {name} |");
        for v in values {
            md += &format!(" {v:.4e} |");
        }
        md += "\n";
    }
    md
}
