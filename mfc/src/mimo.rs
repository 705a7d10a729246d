//! MIMO control as in the paper: one ultra-local model and one controller per output,
//! `y_i^(n_i) = F_i + α_i u_i`, each `F_i` absorbing the influence of the other inputs.

use alloc::vec::Vec;

use crate::channel::{Channel, ChannelConfig, ChannelOutput};
use crate::error::{MfcError, Result};
use crate::estimator::DEFAULT_CAPACITY;
use crate::Reference;

/// A controller of `m` independent channels, stepped together.
#[derive(Debug, Clone)]
pub struct MimoController<const CAP: usize = DEFAULT_CAPACITY> {
    pub(crate) channels: Channels<CAP>,
}

/// The channels of a [`MimoController`]: one inline, more on the heap. A service holding
/// ten thousand single-output plants then reads a plant's channel in the same allocation
/// as the rest of its state, one cache miss fewer per step than behind a `Vec` (the
/// estimator's ring is behind a pointer of its own: `docs/scale.md`, "Memory per plant").
#[derive(Debug, Clone)]
#[allow(clippy::large_enum_variant)]
pub(crate) enum Channels<const CAP: usize> {
    One([Channel<CAP>; 1]),
    Many(Vec<Channel<CAP>>),
}

impl<const CAP: usize> From<Vec<Channel<CAP>>> for Channels<CAP> {
    fn from(v: Vec<Channel<CAP>>) -> Self {
        <[Channel<CAP>; 1]>::try_from(v).map_or_else(Self::Many, Self::One)
    }
}

impl<const CAP: usize> core::ops::Deref for Channels<CAP> {
    type Target = [Channel<CAP>];

    fn deref(&self) -> &[Channel<CAP>] {
        match self {
            Self::One(c) => c,
            Self::Many(v) => v,
        }
    }
}

impl<const CAP: usize> core::ops::DerefMut for Channels<CAP> {
    fn deref_mut(&mut self) -> &mut [Channel<CAP>] {
        match self {
            Self::One(c) => c,
            Self::Many(v) => v,
        }
    }
}

impl<const CAP: usize> MimoController<CAP> {
    /// One channel per configuration (allocates once, here).
    pub fn new(configs: &[ChannelConfig]) -> Result<Self> {
        // One channel straight into its place: through a `Vec`, it was an allocation
        // freed at once, which a service making thousands of devices interleaved with
        // their long-lived ones (`docs/scale.md`, "Memory per plant").
        let channels = match configs {
            [one] => Channels::One([Channel::new(one)?]),
            _ => configs
                .iter()
                .map(Channel::new)
                .collect::<Result<Vec<_>>>()?
                .into(),
        };
        Ok(Self { channels })
    }

    /// Number of channels.
    pub fn len(&self) -> usize {
        self.channels.len()
    }

    /// Whether there is no channel.
    pub fn is_empty(&self) -> bool {
        self.channels.is_empty()
    }

    /// The channels.
    pub fn channels(&self) -> &[Channel<CAP>] {
        &self.channels
    }

    /// One channel, mutably (to reconfigure it or report what it applied).
    pub fn channel_mut(&mut self, i: usize) -> Option<&mut Channel<CAP>> {
        self.channels.get_mut(i)
    }

    fn dims(&self, got: usize) -> Result<()> {
        if got == self.channels.len() {
            Ok(())
        } else {
            Err(MfcError::DimensionMismatch {
                expected: self.channels.len(),
                got,
            })
        }
    }

    /// Check a step's inputs (dimensions, time, values, references) without changing
    /// anything: what [`MimoController::step`] would refuse. A service validates a sample
    /// whole with it before it lets the sample move any of the device's state.
    pub fn check(&self, t: f64, y: &[f64], r: &[Reference]) -> Result<()> {
        self.dims(y.len())?;
        self.dims(r.len())?;
        for ((c, y), r) in self.channels.iter().zip(y).zip(r) {
            c.check(t, *y, r)?;
        }
        Ok(())
    }

    /// Ask the processor for the memory the next step reads outside this value (the
    /// estimators' windows, on the heap), without waiting for it: a caller that holds
    /// thousands of controllers calls it before other work on the same plant, so that
    /// the fetch overlaps that work. A hint only: it changes nothing, and does nothing
    /// off x86_64.
    #[inline]
    pub fn prefetch(&self) {
        for c in self.channels.iter() {
            c.prefetch();
        }
    }

    /// Step every channel at time `t`. All inputs are checked before any channel moves, so
    /// an error leaves every channel untouched. Allocation-free.
    pub fn step(
        &mut self,
        t: f64,
        y: &[f64],
        r: &[Reference],
        out: &mut [ChannelOutput],
    ) -> Result<()> {
        self.step_with(t, y, r, out, None)
    }

    /// [`MimoController::step`] with channel `input.0` given the input `input.1` in place
    /// of its law's ([`Channel::step_input`]): commissioning excites one channel while
    /// the others keep their laws.
    pub fn step_input(
        &mut self,
        t: f64,
        y: &[f64],
        r: &[Reference],
        out: &mut [ChannelOutput],
        input: (usize, f64),
    ) -> Result<()> {
        if input.0 >= self.channels.len() {
            return Err(MfcError::DimensionMismatch {
                expected: self.channels.len(),
                got: input.0 + 1,
            });
        }
        crate::error::finite("input", input.1)?;
        self.step_with(t, y, r, out, Some(input))
    }

    fn step_with(
        &mut self,
        t: f64,
        y: &[f64],
        r: &[Reference],
        out: &mut [ChannelOutput],
        input: Option<(usize, f64)>,
    ) -> Result<()> {
        if self.channels.len() == 1 {
            // One channel checks its own inputs before it changes anything: checking
            // them here first would do it twice (a plant of one output is the common
            // case, and a service steps thousands).
            self.dims(y.len())?;
            self.dims(r.len())?;
        } else {
            self.check(t, y, r)?;
        }
        self.dims(out.len())?;
        for (i, (((c, y), r), o)) in self.channels.iter_mut().zip(y).zip(r).zip(out).enumerate() {
            *o = match input {
                Some((k, u)) if k == i => c.step_input(t, *y, r, u)?,
                _ => c.step(t, *y, r)?,
            };
        }
        // A hold (`hold_estimate_filter`) waits for every reference: the coupling a
        // moving or stepped channel brings is a disturbance the others' F must follow at
        // full speed. So every channel's time at rest is the shortest of them all. The
        // intelligent channels count their own; the others (PID, ADRC) keep no count, so
        // their references are seen through their derivatives only (a step of a PID
        // channel's set-point does not restart the others' hold).
        let rested = if r.iter().any(|r| r.dy != 0.0 || r.ddy != 0.0) {
            None
        } else {
            Some(
                self.channels
                    .iter()
                    .filter_map(Channel::rested)
                    .fold(f64::INFINITY, f64::min),
            )
        };
        for c in self.channels.iter_mut() {
            c.cap_rest(rested);
        }
        Ok(())
    }

    /// The plant reports the outputs it applied since the last step.
    pub fn report_applied(&mut self, v: &[f64]) -> Result<()> {
        self.dims(v.len())?;
        for v in v {
            crate::error::finite("applied output", *v)?;
        }
        for (c, v) in self.channels.iter_mut().zip(v) {
            c.report_applied(*v)?;
        }
        Ok(())
    }

    /// Forget every channel's data history after a gap (a restart from a snapshot).
    pub fn forget_windows(&mut self) {
        for c in self.channels.iter_mut() {
            c.forget_window();
        }
    }

    /// Reconfigure every channel; all or nothing.
    pub fn reconfigure(&mut self, configs: &[ChannelConfig]) -> Result<()> {
        self.dims(configs.len())?;
        // Try on a copy so that a refusal in channel k leaves channels 0..k untouched.
        let mut next = self.channels.clone();
        for (c, cfg) in next.iter_mut().zip(configs) {
            c.reconfigure(cfg)?;
        }
        self.channels = next;
        Ok(())
    }
}
