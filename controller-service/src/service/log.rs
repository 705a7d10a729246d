//! Throttled warnings: the first of each kind at once, then at most one line per interval
//! saying how many were not logged, so a flood of garbage cannot flood the log.

use std::time::{Duration, Instant};

/// Throttled warnings: at most one line per kind per interval.
pub(super) const LOG_INTERVAL: Duration = Duration::from_secs(5);

/// Throttled logging of one kind of event: the first at once, then at most one line per
/// interval saying how many were not logged. Pure: the caller passes the time.
#[derive(Debug, Default)]
pub struct Throttle {
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    /// An event at `now`: `Some(n)` if it should be logged, `n` being how many were
    /// suppressed since the last line; `None` if it is only counted.
    pub fn hit(&mut self, now: Instant, interval: Duration) -> Option<u64> {
        match self.last {
            Some(t) if now.saturating_duration_since(t) < interval => {
                self.suppressed += 1;
                None
            }
            _ => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
        }
    }

    /// At `now`, the events counted but not logged, if a line is due: so a burst's count
    /// is told even when nothing of its kind follows.
    pub fn flush(&mut self, now: Instant, interval: Duration) -> Option<u64> {
        match self.last {
            Some(t) if self.suppressed > 0 && now.saturating_duration_since(t) >= interval => {
                self.last = Some(now);
                Some(std::mem::take(&mut self.suppressed))
            }
            _ => None,
        }
    }
}

/// The kinds of throttled warnings.
#[derive(Debug, Default)]
pub(super) struct Warnings {
    pub(super) undecodable: Throttle,
    pub(super) rejected: Throttle,
    pub(super) unknown: Throttle,
    pub(super) table_full: Throttle,
    pub(super) refused: Throttle,
    pub(super) changed: Throttle,
    pub(super) envelope: Throttle,
}

impl Warnings {
    /// Log how many of each kind were held back, for the kinds whose interval is over.
    pub(super) fn flush(&mut self, now: Instant) {
        for (kind, t) in [
            ("undecodable requests or heartbeats", &mut self.undecodable),
            ("samples refused", &mut self.rejected),
            ("samples from unknown devices", &mut self.unknown),
            (
                "samples refused for a full device table",
                &mut self.table_full,
            ),
            ("requests refused", &mut self.refused),
            ("configuration changes", &mut self.changed),
            ("envelope changes", &mut self.envelope),
        ] {
            if let Some(n) = t.flush(now, LOG_INTERVAL) {
                tracing::warn!(
                    count = n,
                    "{kind} not logged one by one since the last line"
                );
            }
        }
    }
}

/// Log through a throttle: `throttled!(throttle, level, fields..., "fmt", args)`.
macro_rules! throttled {
    ($t:expr, $level:ident, $($arg:tt)+) => {
        if let Some(n) = $t.hit(std::time::Instant::now(), $crate::service::log::LOG_INTERVAL) {
            if n > 0 {
                tracing::$level!(suppressed = n, $($arg)+);
            } else {
                tracing::$level!($($arg)+);
            }
        }
    };
}
pub(super) use throttled;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn throttle_logs_the_first_then_one_line_per_interval_with_a_count() {
        let t0 = Instant::now();
        let s = Duration::from_secs(5);
        let mut t = Throttle::default();
        assert_eq!(t.hit(t0, s), Some(0), "the first is logged at once");
        for k in 1..1000u64 {
            assert_eq!(t.hit(t0 + Duration::from_millis(k), s), None);
        }
        assert_eq!(t.flush(t0 + Duration::from_secs(1), s), None, "not due yet");
        assert_eq!(t.flush(t0 + s, s), Some(999), "the burst's count is told");
        assert_eq!(t.flush(t0 + 3 * s, s), None, "nothing more to tell");
        assert_eq!(t.hit(t0 + 3 * s, s), Some(0));
    }
}
