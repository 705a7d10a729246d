//! Impairment profiles (TOML).
//!
//! ```toml
//! [[profiles]]
//! name = "loss-10-latency-20"
//! seed = 7                         # every random draw of the relay comes from this seed
//! [profiles.both]                  # both directions (plant -> controller and back)
//! loss = 0.10                      # probability a packet is lost
//! delay_ms = 20.0                  # fixed one-way delay
//! jitter_ms = 5.0                  # uniform in [-jitter, +jitter], added to the delay
//! [profiles.down]                  # optional: override for controller -> plant only
//! duplicate = 0.01
//! ```
//!
//! Fields of an impairment (all optional, all default to "no impairment"):
//! `loss`, `burst` (Gilbert-Elliott: `{ p_good_bad, p_bad_good, loss_good, loss_bad }`),
//! `delay_ms`, `jitter_ms`, `reorder` (probability that a packet is held back by
//! `reorder_ms` more, so later ones overtake it), `reorder_ms`, `duplicate`, `rate_kbps`,
//! `outages` (`[{ start_s, duration_s }]`, seconds after the relay starts impairing), and
//! `tcp_rto_ms`: over TCP a lost segment is not lost but retransmitted, so "loss" holds
//! the stream back by one retransmission timeout (Linux's minimum, 200 ms, by default) and
//! everything behind it waits; duplication and reordering do not exist on a TCP stream.

use serde::{Deserialize, Serialize};

/// Gilbert-Elliott bursty loss: a two-state Markov chain, stepped once per packet.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GilbertElliott {
    /// Probability, per packet, of going from the good to the bad state.
    pub p_good_bad: f64,
    /// Probability, per packet, of going from the bad to the good state: a burst lasts
    /// `1 / p_bad_good` packets on average.
    pub p_bad_good: f64,
    /// Loss probability in the good state. Default 0.
    #[serde(default)]
    pub loss_good: f64,
    /// Loss probability in the bad state. Default 1.
    #[serde(default = "one")]
    pub loss_bad: f64,
}

fn one() -> f64 {
    1.0
}

impl GilbertElliott {
    /// Long-run loss rate of the chain (the two states' losses weighted by the time spent in
    /// each): what the relay's observed loss should approach. The relay never uses it.
    pub fn mean_loss(&self) -> f64 {
        let pi_bad = self.p_good_bad / (self.p_good_bad + self.p_bad_good).max(1e-12);
        pi_bad * self.loss_bad + (1.0 - pi_bad) * self.loss_good
    }
}

/// A link cut: nothing passes from `start_s` for `duration_s`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Outage {
    /// Start, in seconds after the relay starts impairing (is armed), >= 0.
    pub start_s: f64,
    /// Length (s, >= 0). UDP packets that arrive during the cut are dropped; TCP chunks are
    /// held until it ends.
    pub duration_s: f64,
}

/// The impairment of one direction.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Impairment {
    /// Probability that a packet is lost, each packet drawn independently, in [0, 1]. Over
    /// TCP a "lost" chunk is delayed by `tcp_rto_ms` instead.
    pub loss: f64,
    /// Bursty loss (replaces `loss` when present).
    pub burst: Option<GilbertElliott>,
    /// Fixed one-way delay (ms).
    pub delay_ms: f64,
    /// Jitter (ms): uniform in [-jitter, +jitter] around the delay, never below zero. Over
    /// UDP packets are delayed independently, so jitter alone reorders them.
    pub jitter_ms: f64,
    /// Probability of holding a packet back by `reorder_ms` (UDP only).
    pub reorder: f64,
    /// Extra delay of a reordered packet (ms). Default 15.
    pub reorder_ms: f64,
    /// Probability of sending a packet twice (UDP only).
    pub duplicate: f64,
    /// Link rate (kbit/s, > 0): each packet waits for those before it to be sent, and none
    /// is dropped however long the queue grows. `None`: unlimited.
    pub rate_kbps: Option<f64>,
    /// Scheduled link cuts, timed from when the relay is armed.
    pub outages: Vec<Outage>,
    /// TCP: how long a "lost" segment holds the stream (ms). Default 200.
    pub tcp_rto_ms: f64,
}

impl Default for Impairment {
    fn default() -> Self {
        Self {
            loss: 0.0,
            burst: None,
            delay_ms: 0.0,
            jitter_ms: 0.0,
            reorder: 0.0,
            reorder_ms: 15.0,
            duplicate: 0.0,
            rate_kbps: None,
            outages: Vec::new(),
            tcp_rto_ms: 200.0,
        }
    }
}

/// A named profile: an impairment per direction and a seed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Profile {
    /// What `faultlab relay --profile` selects and campaign tables show. Not checked for
    /// uniqueness (a lookup takes the first); a campaign needs one named `none`.
    pub name: String,
    /// Seed of every random draw. Default 1. The up direction uses it as is, the down one a
    /// value derived from it, so the two directions do not draw the same sequence.
    #[serde(default = "seed")]
    pub seed: u64,
    /// Impairment of each direction that has no override.
    #[serde(default)]
    pub both: Impairment,
    /// Plant -> controller (samples), if different. It replaces `both` as a whole: a field
    /// it omits is unimpaired, not taken from `both`.
    #[serde(default)]
    pub up: Option<Impairment>,
    /// Controller -> plant (commands), if different; replaces `both` as `up` does.
    #[serde(default)]
    pub down: Option<Impairment>,
}

fn seed() -> u64 {
    1
}

/// A profile file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProfileSet {
    /// The profiles, in file order, which is the order a campaign runs them in.
    pub profiles: Vec<Profile>,
}

/// A profile that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    /// The file could not be read.
    #[error("{file}: {source}")]
    Io {
        /// The path as given to [`ProfileSet::load`].
        file: String,
        /// The I/O error of reading it (missing file, no permission, not UTF-8).
        source: std::io::Error,
    },
    /// Not valid TOML for the schema.
    #[error("{file}: {message}")]
    Parse {
        /// The path, or `<shipped>/profiles/default.toml` for the compiled-in set.
        file: String,
        /// Parser message (names the field).
        message: String,
    },
    /// A value out of range: a probability outside [0, 1], a negative or non-finite time,
    /// a rate not above 0.
    #[error("{file}: profile `{profile}`: `{field}` {reason}")]
    Invalid {
        /// As in [`ProfileError::Parse`].
        file: String,
        /// Name of the profile that holds the value.
        profile: String,
        /// The field with its direction, e.g. `both.loss`, `down.jitter_ms`; `burst` and
        /// `outages` are named as a whole.
        field: String,
        /// The rule it breaks, e.g. `must be in [0, 1]`.
        reason: String,
    },
}

/// The shipped profile set (`profiles/default.toml`, compiled in), read by
/// `ProfileSet::load("default")`; it includes the `none` baseline a campaign needs.
pub const DEFAULT_PROFILES: &str = include_str!("../profiles/default.toml");

impl Profile {
    /// The impairment of the plant -> controller direction.
    pub fn up(&self) -> &Impairment {
        self.up.as_ref().unwrap_or(&self.both)
    }
    /// The impairment of the controller -> plant direction.
    pub fn down(&self) -> &Impairment {
        self.down.as_ref().unwrap_or(&self.both)
    }
}

impl Impairment {
    fn check(&self) -> Result<(), (&'static str, &'static str)> {
        let prob = |v: f64| (0.0..=1.0).contains(&v);
        let nonneg = |v: f64| v.is_finite() && v >= 0.0;
        if !prob(self.loss) {
            return Err(("loss", "must be in [0, 1]"));
        }
        if !prob(self.reorder) {
            return Err(("reorder", "must be in [0, 1]"));
        }
        if !prob(self.duplicate) {
            return Err(("duplicate", "must be in [0, 1]"));
        }
        if let Some(b) = &self.burst {
            if ![b.p_good_bad, b.p_bad_good, b.loss_good, b.loss_bad]
                .into_iter()
                .all(prob)
            {
                return Err(("burst", "probabilities must be in [0, 1]"));
            }
        }
        for (v, f) in [
            (self.delay_ms, "delay_ms"),
            (self.jitter_ms, "jitter_ms"),
            (self.reorder_ms, "reorder_ms"),
            (self.tcp_rto_ms, "tcp_rto_ms"),
        ] {
            if !nonneg(v) {
                return Err((f, "must be finite and >= 0"));
            }
        }
        if let Some(r) = self.rate_kbps {
            if !(r.is_finite() && r > 0.0) {
                return Err(("rate_kbps", "must be > 0"));
            }
        }
        for o in &self.outages {
            if !(nonneg(o.start_s) && nonneg(o.duration_s)) {
                return Err(("outages", "start_s and duration_s must be finite and >= 0"));
            }
        }
        Ok(())
    }
}

impl ProfileSet {
    /// Parse and check a profile file's text.
    pub fn parse(file: &str, text: &str) -> Result<Self, ProfileError> {
        let set: ProfileSet = toml::from_str(text).map_err(|e| ProfileError::Parse {
            file: file.into(),
            message: e.to_string().trim_end().into(),
        })?;
        for p in &set.profiles {
            for (dir, imp) in [
                ("both", Some(&p.both)),
                ("up", p.up.as_ref()),
                ("down", p.down.as_ref()),
            ] {
                if let Some(imp) = imp {
                    imp.check()
                        .map_err(|(field, reason)| ProfileError::Invalid {
                            file: file.into(),
                            profile: p.name.clone(),
                            field: format!("{dir}.{field}"),
                            reason: reason.into(),
                        })?;
                }
            }
        }
        Ok(set)
    }

    /// Read a profile file; `default` reads the shipped set.
    pub fn load(path: &str) -> Result<Self, ProfileError> {
        if path == "default" {
            return Self::parse("<shipped>/profiles/default.toml", DEFAULT_PROFILES);
        }
        let text = std::fs::read_to_string(path).map_err(|source| ProfileError::Io {
            file: path.into(),
            source,
        })?;
        Self::parse(path, &text)
    }
}
