//! Commissioning on a running plant, through the controller service: the live twin of
//! [`super::commission_all`]. An in-process service ([`crate::harness`]) serves the plant
//! (the AERO simulator or a driver, behind its agent, paced in real time over Zenoh) with
//! the wrong controller; each intelligent channel in turn is commissioned as an operator
//! would with `mfcctl commission` (start, follow the status, confirm the proposal), and
//! the laws in force at the end are the commissioned set.
//!
//! The references are held at their initial values, as a user commissions a rig at a set
//! point; the service waits for each channel's loop to settle before it excites it. A
//! device not yet under control when the first start comes is refused; the start is
//! retried until it is accepted or [`SETTLE`] has passed.

use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use mfc::{CommissionFinding, CommissionFit, CommissionSpec, LawConfig, Order};
use plant::scenario::{ControllerSet, Scenario};
use protocol::pb;
use transport::ops::{self, OpError};

use super::ChannelCommission;
use crate::harness::{default_safety, open_session, run_id, service_config, ServiceHandle};

/// The device's id in the run.
const DEVICE: &str = "commission-1";
/// How long a channel may take to settle before its run may start.
const SETTLE: Duration = Duration::from_secs(30);
/// How long past its own duration a run may go on before this gives up on it.
const GRACE: Duration = Duration::from_secs(30);
const TIMEOUT: Duration = Duration::from_secs(2);

/// The scenario with every reference held at its value at 0, long enough for every run
/// twice (a retry) and the settling around them.
fn held(scenario: &Scenario, specs: &[CommissionSpec]) -> Scenario {
    let mut s = scenario.clone();
    for c in &mut s.channels {
        let y = mfc::trajectory::evaluate(&c.reference, 0.0).y;
        c.reference = vec![mfc::trajectory::Piece::Constant { value: y }];
    }
    let runs: f64 = specs
        .iter()
        .map(|p| p.duration() + 5.0 * p.period + SETTLE.as_secs_f64())
        .sum();
    s.duration = 2.0 * runs + 10.0;
    s
}

/// Commission the intelligent channels of `set` on `scenario`'s plant, live, in the
/// order `order` gives (empty: every one, in index order), with `specs[i]` for channel
/// `i`; a channel whose run proposes nothing is tried once more after the others. The set
/// in force at the end, and what each run gave.
pub async fn commission_live(
    scenario: &Scenario,
    set: &ControllerSet,
    specs: &[CommissionSpec],
    order: &[usize],
) -> Result<(ControllerSet, Vec<ChannelCommission>)> {
    let s = held(scenario, specs);
    let service = ServiceHandle::start(service_config(&s, set, &[DEVICE.into()]), None).await?;
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let plant = {
        let (s, set, ep) = (s.clone(), set.clone(), service.endpoint.clone());
        tokio::spawn(async move {
            let session = open_session(None, vec![ep], true).await?;
            let p = plant_agent::agent::open_plant(&s, s.seed).await?;
            let config = plant_agent::agent::LoopConfig::new(&s, &set, DEVICE, default_safety(&s));
            let stop = async {
                let _ = stop_rx.await;
            };
            let run =
                plant_agent::agent::run_loop(&session, p, &config, run_id(s.seed), stop).await;
            let _ = session.close().await;
            anyhow::Ok(run?)
        })
    };
    let operator = ops::Operator {
        session: service.client().await?,
        key: None,
        name: Some("mfc-lab".into()),
    };
    let runs = commission_channels(&operator, set, specs, order).await;
    let config = ops::config(&operator, DEVICE, TIMEOUT).await;
    let _ = stop_tx.send(());
    let ended = plant.await;
    let _ = operator.session.close().await;
    service.stop().await?;
    let runs = runs?;
    let config = config?;
    ended.context("the plant's task")??;
    let mut found = set.clone();
    for (law, c) in found.channels.iter_mut().zip(&config.channels) {
        *law = protocol::convert::channel_from_pb(c)
            .map_err(|e| anyhow::anyhow!("{}: {}", e.field, e.reason))?
            .law;
    }
    found.name = format!("{}-commissioned-live", set.name);
    found.description = format!("`{}` with alpha found on the running plant", set.name);
    Ok((found, runs))
}

/// Each intelligent channel in turn, then once more those that found nothing.
async fn commission_channels(
    operator: &ops::Operator,
    set: &ControllerSet,
    specs: &[CommissionSpec],
    order: &[usize],
) -> Result<Vec<ChannelCommission>> {
    let all: Vec<usize> = (0..specs.len().min(set.channels.len())).collect();
    let channels: Vec<usize> = if order.is_empty() { &all } else { order }
        .iter()
        .copied()
        .filter(|&i| matches!(set.channels.get(i), Some(LawConfig::Intelligent { .. })))
        .collect();
    if channels.is_empty() {
        bail!("no intelligent channel among {order:?}");
    }
    let mut runs = Vec::new();
    let mut retry = Vec::new();
    for &i in &channels {
        let r = one_channel(operator, i, &specs[i]).await?;
        if r.outcome.is_err() && channels.len() > 1 {
            retry.push(i);
        }
        runs.push(r);
    }
    for i in retry {
        runs.push(one_channel(operator, i, &specs[i]).await?);
    }
    Ok(runs)
}

fn start_request(channel: usize, spec: &CommissionSpec) -> pb::CommissionRequest {
    pb::CommissionRequest {
        action: pb::CommissionAction::CommissionStart as i32,
        channel: channel as u32,
        amplitude: spec.amplitude,
        max_deviation: spec.max_deviation,
        period: spec.period,
        cycles: spec.cycles,
        window: spec.window as u32,
        order: spec.order.map_or(0, |o| u32::from(o.n())),
        reason: "mfc-lab commission --live".into(),
        ..Default::default()
    }
}

/// Start, follow and (if it proposes) confirm one channel's run.
async fn one_channel(
    operator: &ops::Operator,
    channel: usize,
    spec: &CommissionSpec,
) -> Result<ChannelCommission> {
    let asked = Instant::now();
    loop {
        match ops::commission(operator, DEVICE, start_request(channel, spec), TIMEOUT).await {
            Ok(_) => break,
            Err(OpError::Refused { reason, .. })
                if reason.contains("not under control") && asked.elapsed() < SETTLE =>
            {
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => return Err(e).context(format!("starting channel {channel}")),
        }
    }
    let started = Instant::now();
    let end = loop {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let st = ops::device_status(operator, DEVICE, TIMEOUT).await?;
        let Some(c) = st.commission else {
            bail!("the status shows no run on channel {channel}");
        };
        if c.phase != pb::CommissionPhase::CommissionRunning as i32 {
            break c;
        }
        // The service may first wait up to 5 periods for the loop to settle.
        let longest = spec.duration() + 5.0 * spec.period;
        if started.elapsed() > Duration::from_secs_f64(longest) + GRACE {
            bail!("channel {channel}: the run did not end");
        }
    };
    let outcome = match finding(&end) {
        Some(f) => {
            let confirm = pb::CommissionRequest {
                action: pb::CommissionAction::CommissionConfirm as i32,
                channel: channel as u32,
                ..Default::default()
            };
            ops::commission(operator, DEVICE, confirm, TIMEOUT)
                .await
                .map(|_| f)
                .map_err(|e| format!("the confirmation was refused: {e}"))
        }
        None => Err(end.reason.clone()),
    };
    Ok(ChannelCommission {
        channel,
        alpha_before: end.alpha_before,
        outcome,
        seconds: end.elapsed,
    })
}

/// The finding a proposed run reports in the device's status.
fn finding(c: &pb::CommissionStatus) -> Option<CommissionFinding> {
    if c.phase != pb::CommissionPhase::CommissionProposed as i32 {
        return None;
    }
    let law = c.proposed.as_ref()?;
    let Some(pb::channel_config::Law::Intelligent(i)) = &law.law else {
        return None;
    };
    let fit = |f: &pb::CommissionFit| {
        Some(CommissionFit {
            order: match f.order {
                1 => Order::One,
                2 => Order::Two,
                _ => return None,
            },
            alpha: f.alpha,
            explained: f.explained,
        })
    };
    let fits: Vec<CommissionFit> = c.fits.iter().filter_map(fit).collect();
    let best = fits
        .iter()
        .copied()
        .find(|f| f.alpha == i.alpha)
        .or_else(|| {
            fits.iter()
                .copied()
                .max_by(|a, b| a.explained.total_cmp(&b.explained))
        })?;
    let of = |o: Order| fits.iter().copied().find(|f| f.order == o);
    Some(CommissionFinding {
        best,
        fits: [of(Order::One), of(Order::Two)],
        samples: 0,
    })
}
