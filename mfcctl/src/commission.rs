//! `mfcctl commission`: start a run on one channel, follow it in the device's status to
//! its end (progress on stderr), show what it found, and put the proposal in force when
//! the operator confirms (`--yes`, or `y` at the prompt on a terminal), naming the run so
//! that a run someone else started since is never the one confirmed. Ctrl-C while it
//! runs, or any error while following it, aborts it: the law in force takes the plant
//! back. `--confirm` and `--abort` act on a run without starting one.

use std::io::{BufRead, IsTerminal, Write};
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use protocol::pb;

use crate::cli::CommissionArgs;
use crate::{ops, render};

/// How often the status is read while a run goes on.
const POLL: Duration = Duration::from_millis(250);
/// How long past the run's own duration the status may keep saying "running" before
/// mfcctl gives up following it (the plant's samples stopped, or its clock is slow).
const GRACE: Duration = Duration::from_secs(30);

/// The request for `action` on run `run` (0: the device's last).
fn request(a: &CommissionArgs, action: pb::CommissionAction, run: u64) -> pb::CommissionRequest {
    pb::CommissionRequest {
        run,
        action: action as i32,
        channel: a.channel,
        amplitude: a.amplitude.unwrap_or(0.0),
        max_deviation: a.max_deviation.unwrap_or(0.0),
        period: a.period,
        cycles: a.cycles,
        window: a.window,
        order: a.order.unwrap_or(0),
        bandwidth: a.bandwidth.unwrap_or(0.0),
        damping: a.damping.unwrap_or(0.0),
        reason: a.reason.clone(),
        ..Default::default()
    }
}

/// Run the command; the text (or JSON) to print.
pub async fn run(
    operator: &ops::Operator,
    a: &CommissionArgs,
    json: bool,
    timeout: Duration,
) -> Result<String> {
    use pb::CommissionAction as A;
    if a.confirm || a.abort {
        let action = if a.confirm {
            A::CommissionConfirm
        } else {
            A::CommissionAbort
        };
        ops::commission(operator, &a.device, request(a, action, a.run), timeout).await?;
        let s = ops::device_status(operator, &a.device, timeout).await?;
        return show(json, s.commission.unwrap_or_default());
    }
    let start = request(a, A::CommissionStart, 0);
    ops::commission(operator, &a.device, start, timeout).await?;
    let mut seen = 0;
    let end = match follow(operator, a, timeout, &mut seen).await {
        Ok(end) => end,
        Err(e) => {
            // Whatever went wrong here, the run must not go on unwatched.
            let abort = request(a, A::CommissionAbort, seen);
            let note = match ops::commission(operator, &a.device, abort, timeout).await {
                Ok(_) => "the run is aborted",
                Err(_) => {
                    "the run could not be aborted: `mfcctl commission DEVICE --channel N --abort`"
                }
            };
            return Err(e.context(note));
        }
    };
    let phase = pb::CommissionPhase::try_from(end.phase);
    if phase != Ok(pb::CommissionPhase::CommissionProposed) {
        bail!(
            "commissioning found nothing to propose:\n{}",
            render::commission(&end)
        );
    }
    eprint!("{}", render::commission(&end));
    if !(a.yes || ask("Put the proposed law in force? [y/N] ")) {
        eprintln!(
            "left as proposed: `mfcctl commission {} --channel {} --run {} --confirm` puts it in force, `--abort` dismisses it",
            a.device, a.channel, end.run
        );
        return show(json, end);
    }
    // This run's proposal, not one of a run started since by someone else.
    let confirm = request(a, A::CommissionConfirm, end.run);
    ops::commission(operator, &a.device, confirm, timeout).await?;
    let s = ops::device_status(operator, &a.device, timeout).await?;
    show(json, s.commission.unwrap_or_default())
}

/// Read the status until the run is no longer running (`seen`: its number, once read).
/// Ctrl-C, a status that cannot be read and a run that does not end are errors: the
/// caller aborts the run.
async fn follow(
    operator: &ops::Operator,
    a: &CommissionArgs,
    timeout: Duration,
    seen: &mut u64,
) -> Result<pb::CommissionStatus> {
    let started = Instant::now();
    let mut last_shown = Instant::now();
    let ctrl_c = tokio::signal::ctrl_c();
    tokio::pin!(ctrl_c);
    loop {
        tokio::select! {
            _ = &mut ctrl_c => bail!("interrupted; the law in force commands the plant"),
            _ = tokio::time::sleep(POLL) => {}
        }
        let s = ops::device_status(operator, &a.device, timeout).await?;
        let Some(c) = s.commission.filter(|c| c.channel == a.channel) else {
            bail!("the device's status shows no run on channel {}", a.channel);
        };
        *seen = c.run;
        if c.phase != pb::CommissionPhase::CommissionRunning as i32 {
            eprintln!();
            return Ok(c);
        }
        if last_shown.elapsed() >= Duration::from_secs(1) {
            last_shown = Instant::now();
            if c.reason.is_empty() {
                eprint!(
                    "\r  running: {:.1} of {:.1} s, largest deviation {:.4}   ",
                    c.elapsed, c.duration, c.deviation
                );
            } else {
                eprint!("\r  {}   ", c.reason);
            }
            let _ = std::io::stderr().flush();
        }
        // The run may first wait up to 5 periods for its loop to settle.
        let longest = (c.duration + 5.0 * a.period).max(0.0);
        if started.elapsed() > Duration::from_secs_f64(longest) + GRACE {
            bail!(
                "the run has not ended {} s after its duration",
                GRACE.as_secs()
            );
        }
    }
}

/// Ask on the terminal; false without one (a script must say `--yes`).
fn ask(prompt: &str) -> bool {
    if !std::io::stdin().is_terminal() {
        return false;
    }
    eprint!("{prompt}");
    let _ = std::io::stderr().flush();
    let mut line = String::new();
    if std::io::stdin().lock().read_line(&mut line).is_err() {
        return false;
    }
    matches!(line.trim(), "y" | "Y" | "yes")
}

fn show(json: bool, c: pb::CommissionStatus) -> Result<String> {
    if json {
        Ok(serde_json::to_string_pretty(&c)? + "\n")
    } else {
        Ok(render::commission(&c))
    }
}
