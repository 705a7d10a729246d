//! When a lost connection is tried again: the plant file's `reconnect_ms`, as a rule with
//! time passed in (seconds on any monotonic clock), so that it is tested with numbers.

/// An outage, from its first failure: may the bridge try again?
#[derive(Debug, Clone, Default)]
pub struct LinkOutage {
    since: Option<f64>,
}

impl LinkOutage {
    /// A request or a connection failed at `now`: `true` if the bridge may try again
    /// (the outage, counted from its first failure, is shorter than `budget` seconds).
    /// A budget of 0 never retries: the first failure ends the run.
    pub fn failed(&mut self, now: f64, budget: f64) -> bool {
        let since = *self.since.get_or_insert(now);
        now - since < budget
    }

    /// A request went through: the next failure starts a new outage.
    pub fn cleared(&mut self) {
        self.since = None;
    }

    /// Seconds left of `budget` at `now` (0 outside an outage).
    pub fn left(&self, now: f64, budget: f64) -> f64 {
        self.since.map_or(0.0, |s| (budget - (now - s)).max(0.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_outage_is_retried_for_its_budget_from_the_first_failure() {
        let mut o = LinkOutage::default();
        assert!(o.failed(10.0, 2.0));
        assert!(o.failed(11.5, 2.0));
        assert!((o.left(11.5, 2.0) - 0.5).abs() < 1e-12);
        assert!(!o.failed(12.0, 2.0), "2 s after the first failure: give up");
        o.cleared();
        assert!(o.failed(20.0, 2.0), "a success starts the count again");
        assert_eq!(o.left(30.0, 2.0), 0.0);
    }

    #[test]
    fn no_budget_never_retries() {
        let mut o = LinkOutage::default();
        assert!(!o.failed(1.0, 0.0));
    }
}
