//! Waking on a deadline to a tenth of a millisecond, where tokio's timer gives a
//! millisecond or two.
//!
//! tokio's timer wheel counts whole milliseconds and rounds a deadline up to the next one,
//! and the reactor's `epoll_wait` rounds its own timeout up again: on the agent's 10 ms
//! schedule a `sleep_until` wakes 1.3 ms late at the median and 2.0 ms at the 99th
//! percentile (`cargo bench -p plant-agent --bench pace`, 2-core machine). That is an
//! eighth of the period added to every sample's age and to every command's delay: at a
//! 100 ms round trip, where each millisecond costs the delay-compensated MFC about 1.7 %
//! of pitch RMS, it was a third of the gap between the lockstep model and the real loop.
//! [`sleep_until`] sleeps on tokio's timer until [`COARSE`] before the deadline, then the
//! rest on a blocking thread (`std::thread::sleep`, the kernel's high-resolution timer):
//! 0.11 ms late at the median and 0.19 ms at the 99th percentile in the same run.
//!
//! The blocking part costs a thread from tokio's blocking pool for at most [`COARSE`] per
//! wait, and no CPU: the thread sleeps. Dropping the future (a `select!` that chose
//! another branch) leaves that thread to finish its short sleep alone.

use std::time::Duration;
use tokio::time::Instant;

/// How long before the deadline tokio's timer hands over: its rounding (under 1 ms) and
/// the reactor's (under 1 ms), less what the wake itself takes.
pub const COARSE: Duration = Duration::from_micros(1500);

/// Wait until `deadline`, to about 0.1 ms on an idle machine (module documentation).
/// A deadline already past returns at once.
pub async fn sleep_until(deadline: Instant) {
    if let Some(early) = deadline.checked_sub(COARSE) {
        if early > Instant::now() {
            tokio::time::sleep_until(early).await;
        }
    }
    let rest = deadline.saturating_duration_since(Instant::now());
    if !rest.is_zero() {
        // A join error only means the runtime is shutting down: the wait is over then.
        let _ = tokio::task::spawn_blocking(move || std::thread::sleep(rest)).await;
    }
}

/// [`sleep_until`] if `precise`, else tokio's own `sleep_until` (a loop among hundreds in
/// one process: `LoopConfig::precise_wake`).
pub async fn wait_until(deadline: Instant, precise: bool) {
    if precise {
        sleep_until(deadline).await;
    } else {
        tokio::time::sleep_until(deadline).await;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Order only, no timing: a wait never ends before its deadline, and one already past
    // returns without touching a timer.
    #[tokio::test(flavor = "multi_thread")]
    async fn never_wakes_before_the_deadline() {
        for us in [0u64, 200, 1_400, 1_600, 5_000] {
            let deadline = Instant::now() + Duration::from_micros(us);
            sleep_until(deadline).await;
            assert!(
                Instant::now() >= deadline,
                "woke before a deadline {us} us away"
            );
        }
        for precise in [true, false] {
            let deadline = Instant::now() + Duration::from_millis(2);
            wait_until(deadline, precise).await;
            assert!(Instant::now() >= deadline);
        }
        if let Some(past) = Instant::now().checked_sub(Duration::from_millis(3)) {
            sleep_until(past).await;
        }
    }
}
