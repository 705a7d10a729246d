//! Latency histogram (1 us buckets, lock-free) and readings of a process from `/proc`.

use std::sync::atomic::{AtomicU64, Ordering};

/// Round-trip times up to [`Histogram::MAX_US`] in 1 us buckets, and a count of the ones
/// beyond. Recording is one relaxed atomic add, so zenoh's callback threads never wait.
#[derive(Debug)]
pub struct Histogram {
    buckets: Vec<AtomicU64>,
    over: AtomicU64,
    max: AtomicU64,
}

impl Default for Histogram {
    fn default() -> Self {
        Self::new()
    }
}

impl Histogram {
    /// Largest time kept to the microsecond (1 s); longer ones count only as `over`.
    pub const MAX_US: usize = 1_000_000;

    /// An empty histogram.
    pub fn new() -> Self {
        Self {
            buckets: (0..Self::MAX_US).map(|_| AtomicU64::new(0)).collect(),
            over: AtomicU64::new(0),
            max: AtomicU64::new(0),
        }
    }

    /// Record one time in microseconds.
    pub fn record(&self, us: u64) {
        match self.buckets.get(us as usize) {
            Some(b) => b.fetch_add(1, Ordering::Relaxed),
            None => self.over.fetch_add(1, Ordering::Relaxed),
        };
        self.max.fetch_max(us, Ordering::Relaxed);
    }

    /// How many times were recorded.
    pub fn count(&self) -> u64 {
        self.buckets
            .iter()
            .map(|b| b.load(Ordering::Relaxed))
            .sum::<u64>()
            + self.over.load(Ordering::Relaxed)
    }

    /// The `q` quantile (0..=1) in microseconds; `None` when empty. Times beyond the
    /// histogram's range count as [`Histogram::MAX_US`].
    pub fn quantile(&self, q: f64) -> Option<f64> {
        let n = self.count();
        if n == 0 {
            return None;
        }
        let rank = ((q.clamp(0.0, 1.0) * n as f64).ceil() as u64).max(1);
        let mut seen = 0;
        for (us, b) in self.buckets.iter().enumerate() {
            seen += b.load(Ordering::Relaxed);
            if seen >= rank {
                return Some(us as f64);
            }
        }
        Some(Self::MAX_US as f64)
    }

    /// The largest time recorded (us).
    pub fn max(&self) -> u64 {
        self.max.load(Ordering::Relaxed)
    }
}

/// CPU time a process has used (user + system), in seconds, from `/proc/{pid}/stat`.
pub fn cpu_seconds(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // Fields after the command name, which is in parentheses and may hold spaces.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the whole line: 11 and 12 after the name.
    let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    Some(ticks / clock_ticks())
}

/// Resident memory of a process (bytes), from `/proc/{pid}/status`.
pub fn rss_bytes(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Clock ticks per second of `/proc`'s times: 100 on every Linux this runs on (the
/// kernel's USER_HZ), which is what `getconf CLK_TCK` prints.
fn clock_ticks() -> f64 {
    std::process::Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .ok()
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or(100.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_of_known_times() {
        let h = Histogram::new();
        assert_eq!(h.quantile(0.5), None);
        for us in 1..=100 {
            h.record(us);
        }
        h.record(5_000_000);
        assert_eq!(h.count(), 101);
        assert_eq!(h.quantile(0.5), Some(51.0));
        assert_eq!(h.quantile(0.99), Some(100.0));
        assert_eq!(h.quantile(1.0), Some(Histogram::MAX_US as f64));
        assert_eq!(h.max(), 5_000_000);
    }

    #[test]
    fn reads_its_own_process() {
        let me = std::process::id();
        let t = cpu_seconds(me).expect("cpu time of this process");
        assert!(t >= 0.0);
        assert!(rss_bytes(me).expect("rss of this process") > 0);
        assert_eq!(cpu_seconds(u32::MAX), None);
    }
}
