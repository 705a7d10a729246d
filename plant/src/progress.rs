//! The progress of the plants of a run, for a person at a terminal: per plant its time,
//! tracking RMS so far, last round trip and mode.
//!
//! A loop stores its line once per refresh (a store into shared state: observing never
//! blocks a period); whoever shows the board renders it when it likes. The board and its
//! text are pure and unit-tested.

use std::collections::BTreeMap;
use std::sync::Mutex;

use serde::Serialize;

use crate::LoopMode;

/// One plant's progress.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Progress {
    /// Device id.
    pub device: String,
    /// Plant time (s).
    pub t: f64,
    /// The run's length (s).
    pub duration: f64,
    /// Tracking RMS so far, per channel.
    pub rms: Vec<f64>,
    /// The last round trip (µs; 0 if the period's command did not come).
    pub rtt_us: u32,
    /// The mode at the end of the last period.
    pub mode: LoopMode,
    /// Times the fallback engaged.
    pub fallbacks: u64,
    /// Periods without their command (held, fallback or stopped).
    pub missing: u64,
    /// The run has ended.
    pub done: bool,
}

/// The progress of every plant of a run, by device.
#[derive(Debug, Default)]
pub struct ProgressBoard {
    plants: Mutex<BTreeMap<String, Progress>>,
}

/// Plants shown one per line; beyond, the board sums the rest up.
pub const BOARD_LINES: usize = 12;

impl ProgressBoard {
    /// An empty board.
    pub fn new() -> Self {
        Self::default()
    }

    /// Replace a plant's line.
    pub fn update(&self, p: Progress) {
        self.lock().insert(p.device.clone(), p);
    }

    /// Forget every plant (a new run of the same ids starts).
    pub fn clear(&self) {
        self.lock().clear();
    }

    /// Every plant's line, by device.
    pub fn snapshot(&self) -> Vec<Progress> {
        self.lock().values().cloned().collect()
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Progress>> {
        self.plants
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The board as text: one line per plant (time, RMS so far, last round trip, mode),
    /// at most [`BOARD_LINES`], then one line for the rest.
    pub fn render(&self) -> String {
        render(&self.snapshot())
    }
}

/// [`ProgressBoard::render`] of a list.
pub fn render(plants: &[Progress]) -> String {
    let mut out = String::new();
    for p in plants.iter().take(BOARD_LINES) {
        let rms: Vec<String> = p.rms.iter().map(|r| format!("{r:.3e}")).collect();
        out.push_str(&format!(
            "{:<14} t {:>6.1}/{:<5.0} s  rms [{}]  rtt {:>6}  {:<8}{}{}\n",
            p.device,
            p.t,
            p.duration,
            rms.join(", "),
            if p.rtt_us > 0 {
                format!("{:.1} ms", f64::from(p.rtt_us) / 1000.0)
            } else {
                "-".into()
            },
            format!("{:?}", p.mode).to_lowercase(),
            if p.fallbacks > 0 {
                format!("  fallbacks {}", p.fallbacks)
            } else {
                String::new()
            },
            if p.done { "  done" } else { "" },
        ));
    }
    if plants.len() > BOARD_LINES {
        let rest = &plants[BOARD_LINES..];
        let remote = rest.iter().filter(|p| p.mode == LoopMode::Remote).count();
        let done = rest.iter().filter(|p| p.done).count();
        out.push_str(&format!(
            "… {} more: {} remote, {} on hold/fallback/stop, {} done\n",
            rest.len(),
            remote,
            rest.len() - remote,
            done
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(dev: &str, mode: LoopMode) -> Progress {
        Progress {
            device: dev.into(),
            t: 12.34,
            duration: 40.0,
            rms: vec![0.0123, 0.00456],
            rtt_us: 1500,
            mode,
            fallbacks: 0,
            missing: 0,
            done: false,
        }
    }

    #[test]
    fn the_board_shows_time_rms_rtt_and_mode_per_plant() {
        let b = ProgressBoard::new();
        b.update(p("aero-2", LoopMode::Local));
        b.update(p("aero-1", LoopMode::Remote));
        let t = b.render();
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 2);
        assert!(lines[0].starts_with("aero-1"), "{t}");
        assert!(lines[0].contains("12.3/40"), "{t}");
        assert!(lines[0].contains("1.230e-2, 4.560e-3"), "{t}");
        assert!(lines[0].contains("1.5 ms"), "{t}");
        assert!(lines[0].contains("remote"), "{t}");
        assert!(lines[1].contains("local"), "{t}");
        // A newer figure replaces the line.
        let mut q = p("aero-1", LoopMode::Holding);
        q.done = true;
        b.update(q);
        assert!(b.render().lines().next().unwrap().contains("holding"));
        assert!(b.render().lines().next().unwrap().ends_with("done"));
    }

    #[test]
    fn a_large_run_is_summed_up_past_the_first_lines() {
        let plants: Vec<Progress> = (0..BOARD_LINES + 5)
            .map(|i| {
                p(
                    &format!("p-{i:03}"),
                    if i % 2 == 0 {
                        LoopMode::Remote
                    } else {
                        LoopMode::Local
                    },
                )
            })
            .collect();
        let t = render(&plants);
        assert_eq!(t.lines().count(), BOARD_LINES + 1);
        assert!(t.lines().last().unwrap().starts_with("… 5 more"), "{t}");
    }
}
