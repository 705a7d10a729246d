//! Rules 2-7 of [`super`] for one sample of a served device: admit it (rules 2-4), check
//! the step's inputs (rule 5), take it in, step the controllers and bound the command
//! (rule 6), then keep the answer and its prediction (rule 7). Nothing about the device
//! changes before the sample has passed rules 2-5.

use mfc::trajectory::evaluate;
use mfc::{MimoController, Reference};
use protocol::pb;

use super::device::{reply, Answer, Answered, Device, PerChannel, Run, ShortId};
use super::{capped, precheck, Via, MAX_SEQ_JUMP};
use crate::lease::{Holder, LeasePolicy, Seen, Standing};
use protocol::MAX_HORIZON;

/// A gap longer than this (s) between a snapshot and the next sample makes the restored
/// estimators start a fresh window.
const RESUME_GAP: f64 = 0.1;
/// The rate limit allows a step of `rate * dt` with `dt` at most this many estimated
/// periods: plant time comes from the network, and a leap of it must not open the limit.
const RATE_DT_PERIODS: f64 = 2.0;
/// ... and at most this long (s) while no period is known yet (a device's first three
/// intervals).
const RATE_DT_UNKNOWN: f64 = 1.0;
/// Round-trip reports the delay compensation takes its median over: the most recent ones,
/// so that it follows a link whose delay changes.
const DELAY_WINDOW: usize = 32;

/// What a step needs from the registry besides the device: who answers, the
/// service-wide count of refusals, and the time the answer carries.
pub(super) struct Context<'a> {
    pub(super) controller_id: &'a str,
    pub(super) rejected: &'a mut u64,
    pub(super) now_unix_ns: u64,
    pub(super) lease: &'a LeasePolicy,
    /// The fleet's members this one sees (`None` without a fleet).
    pub(super) view: Option<&'a std::collections::BTreeSet<String>>,
    pub(super) instance: u64,
    /// Samples are authenticated, so a run id is the plant's own and its runs are ordered
    /// (`plant::run_id`): a run older than the one in force is a replay, not a restart.
    pub(super) ordered_runs: bool,
}

/// Devices awaiting their hand-over at most; beyond, a yield goes without (the preferred
/// member then claims late, or the holder takes the lease back).
const MAX_HANDING: usize = 4096;

/// Step device `d` with a sample that came `via`, and write the command into `out`,
/// stamped with the plant's lease; whether this member sends it (the lease's
/// [`crate::lease::Decision`]), or `None` if the sample is not to be answered at all
/// ([`super::Served::AlreadyAnswered`]). Every member steps every sample it gets, whoever
/// holds the lease: the state of one that does not command stays warm.
///
/// A device whose lease this member just took, or will soon yield to the preferred
/// member, goes into `handing`: its state is to be sent to its partners
/// ([`crate::Registry::take_handing`]).
pub(super) fn answer(
    (cx, handing): (Context<'_>, &mut Vec<String>),
    d: &mut Device,
    via: Via<'_>,
    s: &pb::Sample,
    out: &mut pb::Command,
) -> Option<bool> {
    let (me, policy, view) = ((cx.controller_id, cx.instance), cx.lease, cx.view);
    // The device's own lines were asked for ahead (`Device::prefetch`); the estimators'
    // windows, behind pointers in them, are asked for now, to arrive while the checks
    // below run.
    d.mimo.prefetch();
    let silent = cx.now_unix_ns.saturating_sub(d.heard_unix_ns);
    let gap = d.heard_unix_ns > 0 && silent > policy.silence_ns;
    d.heard_unix_ns = cx.now_unix_ns;
    if !write_answer(cx, d, via, s, out) {
        return None;
    }
    let seen = Seen::of(s);
    if d.lease_holder.as_str() != seen.holder {
        d.lease_holder = ShortId::new(&protocol::printable(seen.holder));
    }
    (d.lease_epoch, d.lease_instance) = (seen.epoch, seen.instance);
    d.lease_refused = u32::try_from(s.lease_refused).unwrap_or(u32::MAX);
    let warm = out.mode == pb::Mode::Control as i32;
    let st = Standing {
        preferred: via.preferred,
        warm,
        sees_holder: view.map(|v| v.contains(seen.holder)),
        gap,
    };
    let before = d.claimer.holder;
    let decision = d.claimer.decide(policy, me, st, seen);
    // Its state goes to its partners when it starts to hold the lease (they are then in
    // step with it) and halfway to a yield (the preferred member claims in step).
    let took = before != Holder::Me && d.claimer.holder == Holder::Me;
    if (took || d.claimer.hand_over_due(policy)) && handing.len() < MAX_HANDING {
        handing.push(via.key_id.to_string());
    }
    decision.stamp(s.run_id, me.1, out);
    if !decision.sends() {
        d.abort_commission("this member no longer commands the plant");
    }
    Some(decision.sends())
}

/// [`answer`] before the lease: the command, or false if none.
fn write_answer(
    mut cx: Context<'_>,
    d: &mut Device,
    via: Via<'_>,
    s: &pb::Sample,
    out: &mut pb::Command,
) -> bool {
    d.home = via.home;
    match step_sample(&mut cx, d, via.key_id, s) {
        Answered::Cached => match &d.last_command {
            Some(a) => a.write_into(cx.controller_id, via.key_id, out),
            // Not reached: a cached answer is always there.
            None => {
                *out = reply(
                    (cx.controller_id, via.key_id),
                    (s.seq, s.sent_unix_ns, cx.now_unix_ns),
                    pb::Mode::Stale,
                    String::new(),
                );
            }
        },
        Answered::Reply(c) => *out = c,
        Answered::Not => return false,
    }
    true
}

/// Why rules 2-4 did not admit a sample.
enum Refusal {
    /// The last sequence again.
    Duplicate,
    /// Older than the last answered sample, or of an ended run: `STALE`, with why.
    Stale(&'static str),
    /// `REJECTED`, with why.
    Rejected(String),
}

/// Rules 2-6 for a served device `d`.
fn step_sample(cx: &mut Context<'_>, d: &mut Device, key_id: &str, s: &pb::Sample) -> Answered {
    d.samples += 1;
    let new_run = match admit(d, key_id, s, cx.ordered_runs) {
        Ok(new_run) => new_run,
        Err(Refusal::Duplicate) => {
            return match &d.last_command {
                Some(_) => Answered::Cached,
                // Answered before a restore or a handover: nothing cached to send again,
                // and the answer went out then (counted as a duplicate only).
                None => Answered::Not,
            };
        }
        Err(Refusal::Stale(why)) => {
            d.rare.get_mut().stale += 1;
            return Answered::Reply(reply(
                (cx.controller_id, key_id),
                (s.seq, s.sent_unix_ns, cx.now_unix_ns),
                pb::Mode::Stale,
                why.into(),
            ));
        }
        Err(Refusal::Rejected(reason)) => return refuse(cx, d, key_id, s, reason),
    };
    let fresh = match check_inputs(d, s, new_run) {
        Ok(fresh) => fresh,
        Err(reason) => return refuse(cx, d, key_id, s, reason),
    };
    // The sample is good: from here on it may change state.
    let pace = take_in(d, s, fresh);
    match bounded_command(d, s, &pace) {
        Ok(v) => {
            keep_answer(d, s, v, pace.period, cx.now_unix_ns);
            Answered::Cached
        }
        Err(reason) => refuse(cx, d, key_id, s, reason),
    }
}

/// A `REJECTED` answer, counted and kept as the device's last error.
fn refuse(
    cx: &mut Context<'_>,
    d: &mut Device,
    key_id: &str,
    s: &pb::Sample,
    reason: String,
) -> Answered {
    let reason = capped(reason);
    d.rare.get_mut().rejected += 1;
    d.note_rejected(s.run_id, s.seq);
    *cx.rejected += 1;
    d.rare.get_mut().last_error.clone_from(&reason);
    Answered::Reply(reply(
        (cx.controller_id, key_id),
        (s.seq, s.sent_unix_ns, cx.now_unix_ns),
        pb::Mode::Rejected,
        reason,
    ))
}

/// Rules 2-4: whether the sample is admitted, and if so whether it starts a new run.
fn admit(d: &mut Device, key_id: &str, s: &pb::Sample, ordered: bool) -> Result<bool, Refusal> {
    // Rule 2.
    precheck(key_id, s)
        .and_then(|()| d.check_values(s))
        .map_err(Refusal::Rejected)?;
    // Rule 3.
    d.run_samples = d.run_samples.saturating_add(1);
    match d.run_of(s, ordered) {
        Run::New => return Ok(true),
        Run::Retired => return Err(Refusal::Stale("a sample of an earlier run of the plant")),
        // A captured run played back: refused as out of step, so that only a plant whose
        // clock went back, and that keeps sending, is followed (after RESYNC_AFTER
        // samples in a row with none of the run in force between them).
        Run::Earlier => {
            return if d.out_of_step(s) {
                Ok(true)
            } else {
                Err(Refusal::Stale(
                    "a sample of a run older than the one in force",
                ))
            };
        }
        Run::Same => {}
    }
    // Rule 4, within the run in force.
    let why = match d.last_seq {
        Some(last) if s.seq == last => {
            d.rare.get_mut().duplicates += 1;
            return Err(Refusal::Duplicate);
        }
        Some(last) if s.seq < last => Refusal::Stale(""),
        Some(last) if s.seq - last > MAX_SEQ_JUMP => Refusal::Rejected(format!(
            "sequence jumps from {last} to {}, more than {MAX_SEQ_JUMP}",
            s.seq
        )),
        _ if s.plant_time <= d.last_time => Refusal::Rejected(format!(
            "plant time {:?} does not advance past {:?}",
            s.plant_time, d.last_time
        )),
        _ => return Ok(false),
    };
    // Out of step with the run in force. A consistent stream the device has refused
    // RESYNC_AFTER times: the plant is there and the device is out of step with it, so
    // follow the plant.
    if d.out_of_step(s) {
        Ok(true)
    } else {
        Err(why)
    }
}

/// Rule 5, checked before anything moves: the step's inputs (a new run is checked against
/// the fresh state it would start from, which is returned). Boxed: a new run is rare, and
/// a controller of a few hundred bytes returned inline was copied twice on every sample
/// (8 % of the registry benchmark's profile, `docs/scale.md`).
fn check_inputs(
    d: &mut Device,
    s: &pb::Sample,
    new_run: bool,
) -> Result<Option<Box<MimoController>>, String> {
    for (r, pieces) in d.refs.iter_mut().zip(&d.reference) {
        *r = evaluate(pieces, s.plant_time - d.reference_start);
    }
    let fresh = if new_run {
        Some(Box::new(
            MimoController::new(&d.configs()).map_err(|e| e.to_string())?,
        ))
    } else {
        None
    };
    fresh
        .as_deref()
        .unwrap_or(&d.mimo)
        .check(s.plant_time, &s.outputs, &d.refs)
        .map_err(|e| e.to_string())?;
    Ok(fresh)
}

/// Where the rate limit of this sample's command runs from, and over how long.
struct Pace {
    /// The plant applied the last command and nothing else since.
    follows: bool,
    /// The period estimate before this sample's interval joined it.
    period: Option<f64>,
    /// The time the rate limit allows for.
    rate_dt: f64,
}

/// Take an admitted sample in: a new run, the round trip, the plant's flags, the samples
/// lost (and recovered from the copies it carries), what the plant applied.
fn take_in(d: &mut Device, s: &pb::Sample, fresh: Option<Box<MimoController>>) -> Pace {
    if let Some(m) = fresh {
        d.start_run(s.run_id, *m);
    }
    d.settle();
    if s.last_rtt_us > 0 {
        if d.rtts.len() == super::device::RTT_WINDOW {
            d.rtts.pop_front();
        }
        d.rtts.push_back(s.last_rtt_us);
    }
    let plant_trouble = pb::SampleFlags::Holding as u32
        | pb::SampleFlags::Fallback as u32
        | pb::SampleFlags::SafeStop as u32;
    if s.flags & plant_trouble != 0 {
        d.rare.get_mut().samples_off_remote += 1;
    }
    d.last_flags = s.flags;
    let dt = s.plant_time - d.last_time;
    // The plant applied the last command and nothing else since: the rate limit runs
    // from it. Otherwise (a new run, a restore, a gap, a plant holding or on its
    // fallback, a warm-up answer it did not apply) from what the plant says it applies,
    // or from the last command sent to the device, or from rest.
    let follows = d.last_seq == Some(s.seq.wrapping_sub(1))
        && s.flags & plant_trouble == 0
        && d.last_command
            .as_ref()
            .is_some_and(|c| c.mode == pb::Mode::Control as i32);
    // Read before this sample's interval joins the estimate: a leap cannot vouch for
    // itself.
    let period = d.period();
    // Within a run, the time since the last answered sample, at most two periods (a
    // lost sample in between gives the law that much more room, and the envelope the
    // same); at the start of a run or after a restore, one period from what is held
    // (nothing, before a period is known).
    let rate_dt = if d.last_seq.is_some() && !d.restored {
        dt.min(period.map_or(RATE_DT_UNKNOWN, |p| RATE_DT_PERIODS * p))
    } else {
        period.unwrap_or(0.0)
    };
    if let Some(last) = d.last_seq {
        // s.seq > last here.
        d.lost += d.missing_before(last, s.seq);
        if s.seq - last == 1 {
            d.note_interval(dt);
        }
        if s.seq.saturating_sub(last) > 1 {
            recover_previous(d, s);
        }
        if !s.applied.is_empty() {
            // Checked finite above, so this cannot fail.
            let _ = d.mimo.report_applied(&s.applied);
        }
    }
    if std::mem::take(&mut d.restored) && dt > RESUME_GAP {
        // Restarted from a snapshot after a gap: the estimators' history does not reach
        // across it. Keep gains and the reference phase, and start bumplessly from what
        // the plant applies now (its local fallback's output, reported above).
        d.mimo.forget_windows();
    }
    Pace {
        follows,
        period,
        rate_dt,
    }
}

/// Step the controllers, then rule 6: the last check before anything leaves. A
/// non-finite command is refused; one outside the envelope is clipped and counted.
fn bounded_command(d: &mut Device, s: &pb::Sample, pace: &Pace) -> Result<PerChannel<f64>, String> {
    // Not refused here: the same inputs passed `check` in rule 5 (and a commissioning
    // run's input is finite).
    let input = d.commission_input(s);
    match input {
        Some(input) => d
            .mimo
            .step_input(s.plant_time, &s.outputs, &d.refs, &mut d.outputs, input),
        None => d
            .mimo
            .step(s.plant_time, &s.outputs, &d.refs, &mut d.outputs),
    }
    .map_err(|e| e.to_string())?;
    if let Some(bad) = d.outputs.iter().find(|o| !o.v.is_finite()) {
        return Err(format!(
            "the controller produced a non-finite command ({:?}): check the gains",
            bad.v
        ));
    }
    let mut v: PerChannel<f64> = PerChannel::with_capacity(d.outputs.len());
    let mut clipped = false;
    for (i, o) in d.outputs.iter().enumerate() {
        let from = match &d.last_command {
            Some(c) if pace.follows => c.v.get(i).copied(),
            _ => s
                .applied
                .get(i)
                .copied()
                .or_else(|| d.held.as_ref().and_then(|h| h.get(i).copied())),
        }
        .unwrap_or(0.0);
        let (x, c) = d.envelope[i].clamp(o.v, Some((from, pace.rate_dt)));
        clipped |= c;
        v.push(x);
    }
    if clipped {
        d.clamped += 1;
    }
    if let (Some((i, _)), Some(c)) = (input, d.commission.as_mut()) {
        c.sent(d.mimo.channels()[i].output_map().inverse(v[i]));
    }
    Ok(v)
}

/// The sample is answered with `v`: keep the answer (for a duplicate, and where the next
/// command's rate limit runs from) with its prediction (rule 7).
fn keep_answer(
    d: &mut Device,
    s: &pb::Sample,
    v: PerChannel<f64>,
    period: Option<f64>,
    now_unix_ns: u64,
) {
    d.last_seq = Some(s.seq);
    d.last_time = s.plant_time;
    for (f, o) in d.f_est.iter_mut().zip(&d.outputs) {
        *f = o.f_est.unwrap_or(f64::NAN);
    }
    let control = !d.outputs.iter().any(|o| o.warming_up);
    // The last answer is written over in place: building a new one (its values
    // collected, cloned, the whole moved in) was 9 % of the registry benchmark's profile.
    let buffer = d
        .last_command
        .as_mut()
        .map(|a| std::mem::take(&mut a.horizon))
        .unwrap_or_default();
    // A commissioning run's square wave is not predicted: a plant that misses a sample
    // holds its level.
    let commissioning = d.commission.as_ref().is_some_and(|c| c.exciting());
    let horizon = if control && !commissioning {
        predict(d, s, &v, period, buffer)
    } else {
        Vec::new()
    };
    let answer = d.last_command.get_or_insert_with(Answer::default);
    answer.horizon = horizon;
    answer.seq = s.seq;
    answer.mode = if control {
        pb::Mode::Control
    } else {
        pb::Mode::WarmingUp
    } as i32;
    answer.controller_unix_ns = now_unix_ns;
    answer.sample_sent_unix_ns = s.sent_unix_ns;
    refill(&mut answer.u, d.outputs.iter().map(|o| o.u));
    answer.v = v;
    refill(&mut answer.f_est, d.f_est.iter().copied());
    refill(&mut answer.reference, d.refs.iter().map(|r| r.y));
    d.commands += 1;
    if control {
        match &mut d.held {
            Some(held) => refill(held, answer.v.iter().copied()),
            None => d.held = Some(PerChannel::from_slice(&answer.v)),
        }
    }
}

/// `to` now holds `from`'s values, in its own buffer.
fn refill(to: &mut PerChannel<f64>, from: impl Iterator<Item = f64>) {
    to.clear();
    to.extend(from);
}

/// The samples lost between the last answered one and `s`, from the copies `s` carries
/// (`previous_*`, newest first): the controller steps on each, oldest first (their outputs
/// are not sent, the moment has passed), so that its estimators see the data points
/// instead of a gap. Copies of samples already seen, and anything that does not fit
/// (lengths that are not whole samples, non-finite values, times that do not advance
/// inside the gap, a step the core refuses), are skipped: at worst the sample is served as
/// if it carried nothing.
fn recover_previous(d: &mut Device, s: &pb::Sample) {
    let n = d.channels();
    let k = s.previous_plant_time.len().min(protocol::RESENT_SAMPLES);
    if n == 0 || s.previous_outputs.len() != k * n || s.previous_applied.len() != k * n {
        return;
    }
    for j in (0..k).rev() {
        let t = s.previous_plant_time[j];
        let y = &s.previous_outputs[j * n..(j + 1) * n];
        let applied = &s.previous_applied[j * n..(j + 1) * n];
        let fits = t.is_finite()
            && t > d.last_time
            && t < s.plant_time
            && y.iter().chain(applied).all(|x| x.is_finite());
        if !fits {
            continue;
        }
        let refs: PerChannel<Reference> = d
            .reference
            .iter()
            .map(|pieces| evaluate(pieces, t - d.reference_start))
            .collect();
        if d.mimo.check(t, y, &refs).is_err() {
            continue;
        }
        let _ = d.mimo.report_applied(applied);
        let mut outputs = d.outputs.clone();
        if d.mimo.step(t, y, &refs, &mut outputs).is_ok() {
            d.rare.get_mut().recovered += 1;
            // Time moves on to the recovered sample: a later copy must come after it.
            d.last_time = t;
        }
    }
}

/// Rule 7, for a device with a horizon or delay compensation: the outputs its command
/// predicts for the periods after the sample's, period-major (`[j * n + i]`: channel `i`
/// in period `seq + 1 + j`), each through the envelope with the rate limit from the one
/// before, so that whatever the agent plays stays inside it. Written into `out`'s buffer
/// (kept from the last answer). Empty without prediction or before the period is known.
fn predict(
    d: &mut Device,
    s: &pb::Sample,
    v: &[f64],
    period: Option<f64>,
    mut out: Vec<f64>,
) -> Vec<f64> {
    out.clear();
    let p = d.prediction;
    let Some(h) = period.filter(|h| *h > 0.0 && h.is_finite()) else {
        return out;
    };
    // The round trip in periods: the command for `seq` lands in period `seq + m`.
    let m = if p.delay_compensation {
        // On the stack: a step allocates nothing.
        let mut window = [0u32; DELAY_WINDOW];
        let mut n = 0;
        for (slot, rtt) in window.iter_mut().zip(d.rtts.iter().rev()) {
            *slot = *rtt;
            n += 1;
        }
        let recent = &mut window[..n];
        if recent.is_empty() {
            0
        } else {
            let mid = recent.len() / 2;
            let (_, median, _) = recent.select_nth_unstable(mid);
            ((f64::from(*median) * 1e-6 / h).round() as u32).min(MAX_HORIZON)
        }
    } else {
        0
    };
    let len = p.horizon.max(m).min(MAX_HORIZON) as usize;
    if len == 0 {
        return out;
    }
    let n = v.len();
    out.resize(len * n, 0.0);
    let mut refs = Vec::with_capacity(len);
    let mut applied = Vec::with_capacity(m as usize);
    let mut elements = vec![0.0; len];
    for i in 0..n {
        refs.clear();
        refs.extend((1..=len).map(|j| {
            evaluate(
                &d.reference[i],
                s.plant_time + j as f64 * h - d.reference_start,
            )
        }));
        applied.clear();
        if let Some(sched) = &d.schedule {
            applied.extend((0..u64::from(m)).map(|j| sched.get(s.seq + j, i).unwrap_or(f64::NAN)));
        }
        let mut last = d.outputs[i];
        last.v = v[i];
        let trend = mfc::Trend {
            moving: p.trend,
            at_rest: p.trend_at_rest,
        };
        d.mimo.channels()[i].plan(&last, h, &refs, &applied, trend, &mut elements);
        let mut prev = v[i];
        for (j, e) in elements.iter().enumerate() {
            let (x, _) = d.envelope[i].clamp(*e, Some((prev, h)));
            out[j * n + i] = x;
            prev = x;
        }
    }
    if let Some(sched) = &mut d.schedule {
        // From the period it lands in on, this command drives the plant until the next
        // one lands.
        for j in m.max(1) as usize..=len {
            sched.set(s.seq + j as u64, out[(j - 1) * n..j * n].iter().copied());
        }
    }
    out
}
