//! Binary snapshots of the whole controller state (feature `snapshot`, bincode).
//!
//! Every state type derives bincode's `Encode`/`Decode`, except the ones generic over the
//! window capacity `CAP`, whose derive bincode cannot generate (it copies the parameter's
//! default into the impl); those are written here, field by field.
//!
//! A snapshot may come over the network (a standby's state, a handover), so the decoder
//! refuses what a corrupted one could break, and a decoded controller is one the
//! constructors could have built: ring indices within `CAP`; each channel's configuration
//! valid, its law and output map running that configuration (the parameters in force, the
//! map's limits: an inverted clamp would panic at the next step), and its times and last
//! outputs finite. The laws' inner state (integrals, filters) is not checked: a non-finite
//! value there gives a non-finite `u`, which the channel never sends.

use bincode::de::Decoder;
use bincode::enc::Encoder;
use bincode::error::{DecodeError, EncodeError};
use bincode::{Decode, Encode};

use crate::channel::{Channel, ChannelConfig, Law, LawConfig};
use crate::estimator::{Estimator, Interval};
use crate::intelligent::IntelligentController;
use crate::mimo::MimoController;
use crate::output_map::{OutputMap, OutputMapConfig};

macro_rules! snapshot_struct {
    ($t:ident { $($f:ident),* $(,)? } $(check $check:expr)?) => {
        impl<const CAP: usize> Encode for $t<CAP> {
            fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
                $( self.$f.encode(e)?; )*
                Ok(())
            }
        }
        impl<Ctx, const CAP: usize> Decode<Ctx> for $t<CAP> {
            fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
                let v = Self { $( $f: Decode::decode(d)?, )* };
                $( #[allow(clippy::redundant_closure_call)] ($check)(&v)?; )?
                Ok(v)
            }
        }
    };
}

impl<const CAP: usize> Encode for Estimator<CAP> {
    fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
        self.config.encode(e)?;
        // The slots (the window's, not the capacity's), length first, each as the
        // interval it starts (the format of a ring of intervals); a slot outside the
        // window, as a zero-length one.
        let slots = crate::estimator::slots(&self.config, CAP);
        (slots as u64).encode(e)?;
        for i in 0..slots {
            let k = (i + slots - self.head) % slots;
            let iv = if k < self.len {
                self.interval(k)
            } else {
                let s = self.ring[i];
                s.to((s.t, s.y))
            };
            iv.encode(e)?;
        }
        self.head.encode(e)?;
        self.len.encode(e)?;
        self.next_index.encode(e)?;
        self.last.encode(e)?;
        self.primary.encode(e)?;
        self.shadow.encode(e)?;
        self.lowpass.encode(e)?;
        self.order.encode(e)
    }
}

impl<Ctx, const CAP: usize> Decode<Ctx> for Estimator<CAP> {
    fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
        let config: crate::EstimatorConfig = Decode::decode(d)?;
        let slots = crate::estimator::slots(&config, CAP);
        // The ring's length is checked before anything is allocated for it.
        let n = u64::decode(d)?;
        if n != slots as u64 {
            return Err(invalid("estimator ring not the window's length"));
        }
        let mut intervals = alloc::vec::Vec::with_capacity(slots);
        for _ in 0..slots {
            intervals.push(Interval::decode(d)?);
        }
        let mut ring = crate::estimator::empty_ring::<CAP>(slots);
        for (slot, iv) in ring[..slots].iter_mut().zip(&intervals) {
            *slot = (*iv).into();
        }
        let mut e = Self {
            config,
            ring,
            head: Decode::decode(d)?,
            len: Decode::decode(d)?,
            next_index: Decode::decode(d)?,
            last: Decode::decode(d)?,
            primary: Decode::decode(d)?,
            shadow: Decode::decode(d)?,
            lowpass: Decode::decode(d)?,
            order: Decode::decode(d)?,
        };
        check_estimator(&e, slots)?;
        check_window(&e, &intervals)?;
        e.align_shadow();
        Ok(e)
    }
}

/// What a decoded estimator must hold before it may step: a configuration it could have
/// been built with for the order its sums serve, ring indices inside the window, a shadow
/// sum that will replace the running one (it started inside the window), a sample count
/// far from overflowing, and a newest sample that ends the newest interval.
fn check_estimator<const CAP: usize>(e: &Estimator<CAP>, slots: usize) -> Result<(), DecodeError> {
    if e.config.validate(e.order, CAP).is_err() {
        return Err(invalid("estimator configuration invalid"));
    }
    let indices = e.head < slots
        && e.len <= e.config.intervals().min(CAP)
        && e.next_index >= e.len as u64
        && e.next_index < 1 << 62;
    let oldest = e.next_index.wrapping_sub(e.len as u64);
    let shadow = !e.shadow.active || (oldest..=e.next_index).contains(&e.shadow.first);
    if !(indices && shadow) {
        return Err(invalid("estimator ring indices out of range"));
    }
    Ok(())
}

/// The window's intervals, as decoded, are the ones the ring gives back
/// ([`Estimator::interval`]: each ends where the next starts, the newest at the last
/// sample). The ring keeps each shared end once ([`crate::estimator::Slot`]), so a window
/// that was not one would otherwise be changed into one. Always true of a state built by
/// steps; checked after [`check_estimator`] (the indices are inside the ring).
fn check_window<const CAP: usize>(
    e: &Estimator<CAP>,
    decoded: &[Interval],
) -> Result<(), DecodeError> {
    if e.len > 0 && e.last.is_none() {
        return Err(invalid("estimator's window has no last sample"));
    }
    for k in 0..e.len {
        let (iv, kept) = (&decoded[(e.head + k) % decoded.len()], e.interval(k));
        if (iv.b, iv.yb) != (kept.b, kept.yb) {
            return Err(invalid(if k + 1 < e.len {
                "estimator's intervals do not follow one another"
            } else {
                "estimator's last sample is not its window's end"
            }));
        }
    }
    Ok(())
}

/// As the `Option<IntelligentParams>` it was, boxed or not.
impl Encode for crate::intelligent::Pending {
    fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
        self.get().encode(e)
    }
}

impl<Ctx> Decode<Ctx> for crate::intelligent::Pending {
    fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
        let mut p = Self::default();
        if let Some(params) = Option::<crate::IntelligentParams>::decode(d)? {
            p.put(params);
        }
        Ok(p)
    }
}

snapshot_struct!(IntelligentController {
    params,
    pending,
    estimator,
    integral,
    derivative,
    last_t,
    applied,
    last_u,
    hold,
    bump,
    bumpless_start,
    observer,
    estimate,
    rest,
    trend,
    sign
});
snapshot_struct!(MimoController { channels });

// As a `Vec` of channels: one or many, the bytes are the same.
impl<const CAP: usize> Encode for crate::mimo::Channels<CAP> {
    fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
        (**self).encode(e)
    }
}

impl<Ctx, const CAP: usize> Decode<Ctx> for crate::mimo::Channels<CAP> {
    fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
        Ok(alloc::vec::Vec::<Channel<CAP>>::decode(d)?.into())
    }
}

impl<const CAP: usize> Encode for Channel<CAP> {
    fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
        self.law.encode(e)?;
        // The configuration stays in the format (a decoder checks it against the law's
        // state), though the channel reads it from that state now.
        self.config().encode(e)?;
        self.map.encode(e)?;
        self.last_t.encode(e)?;
        self.last_v.encode(e)
    }
}

impl<Ctx, const CAP: usize> Decode<Ctx> for Channel<CAP> {
    fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
        let law: Law<CAP> = Decode::decode(d)?;
        let config: ChannelConfig = Decode::decode(d)?;
        // The map as `OutputMap` encodes it (its configuration, then the last output for
        // the rate limit), rebuilt through its constructor: its fields are its own.
        let map_config: OutputMapConfig = Decode::decode(d)?;
        let last: Option<(f64, f64)> = Decode::decode(d)?;
        let mut map = OutputMap::new(map_config).map_err(|_| invalid("output map"))?;
        if let Some((t, v)) = last {
            if !(t.is_finite() && v.is_finite()) {
                return Err(invalid("output map's last output"));
            }
            map.record_applied(t, v);
        }
        let c = Self {
            law,
            map,
            last_t: Decode::decode(d)?,
            last_v: Decode::decode(d)?,
        };
        check_channel(&c, &config)?;
        Ok(c)
    }
}

fn invalid(what: &'static str) -> DecodeError {
    DecodeError::Other(what)
}

/// A decoded channel runs the configuration it was encoded with, and a valid one (module
/// documentation).
fn check_channel<const CAP: usize>(
    c: &Channel<CAP>,
    config: &ChannelConfig,
) -> Result<(), DecodeError> {
    if c.map.config() != &config.output {
        return Err(invalid(
            "output map differs from the channel's configuration",
        ));
    }
    if !c.last_v.is_finite() || c.last_t.is_some_and(|t| !t.is_finite()) {
        return Err(invalid("channel's last output or time not finite"));
    }
    let valid = match (&c.law, &config.law) {
        (Law::Intelligent(l), LawConfig::Intelligent { params, estimator }) => {
            l.params() == params
                && l.estimator.order == l.params.order
                && l.estimator.config() == estimator
                && params.validate().is_ok()
                && l.params.validate().is_ok()
                && estimator.validate(params.order, CAP).is_ok()
        }
        (Law::Pid(l), LawConfig::Pid { params }) => {
            l.params() == params && params.validate().is_ok()
        }
        (Law::Adrc(l), LawConfig::Adrc { params }) => {
            l.params() == params && params.validate().is_ok()
        }
        _ => false,
    };
    if valid {
        Ok(())
    } else {
        Err(invalid(
            "control law differs from the channel's configuration or is invalid",
        ))
    }
}

impl<const CAP: usize> Encode for Law<CAP> {
    fn encode<E: Encoder>(&self, e: &mut E) -> Result<(), EncodeError> {
        match self {
            Law::Intelligent(c) => {
                0u8.encode(e)?;
                c.encode(e)
            }
            Law::Pid(c) => {
                1u8.encode(e)?;
                c.encode(e)
            }
            Law::Adrc(c) => {
                2u8.encode(e)?;
                c.encode(e)
            }
        }
    }
}

impl<Ctx, const CAP: usize> Decode<Ctx> for Law<CAP> {
    fn decode<D: Decoder<Context = Ctx>>(d: &mut D) -> Result<Self, DecodeError> {
        match u8::decode(d)? {
            0 => Ok(Law::Intelligent(Decode::decode(d)?)),
            1 => Ok(Law::Pid(Decode::decode(d)?)),
            2 => Ok(Law::Adrc(Decode::decode(d)?)),
            _ => Err(DecodeError::Other("unknown control law")),
        }
    }
}

/// Encode any state (a [`MimoController`], a [`Channel`], ...) to bytes.
pub fn to_bytes<T: Encode>(state: &T) -> Result<alloc::vec::Vec<u8>, EncodeError> {
    bincode::encode_to_vec(state, bincode::config::standard())
}

/// Bincode's limit for [`from_bytes`]: the bytes read plus, for each container, its
/// claimed length times its element's size in memory, so that a length claimed by
/// corrupted or hostile bytes is refused before anything is allocated for it. 16 MiB: some
/// 15 000 channels (1.1 KiB each in memory, their estimators' rings aside: a ring is the
/// window's length, checked against `CAP` and read from bytes of its own), far more than a
/// device has (a sample's outputs fit `protocol::MAX_PAYLOAD`, 64 KiB).
pub const MAX_STATE: usize = 16 << 20;

/// Decode state encoded by [`to_bytes`]; refuses trailing bytes, and never allocates past
/// [`MAX_STATE`].
pub fn from_bytes<T: Decode<()>>(bytes: &[u8]) -> Result<T, DecodeError> {
    let config = bincode::config::standard().with_limit::<MAX_STATE>();
    let (v, used) = bincode::decode_from_slice(bytes, config)?;
    if used != bytes.len() {
        return Err(DecodeError::Other("trailing bytes after the snapshot"));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::{from_bytes, to_bytes};
    use crate::{Estimator, EstimatorConfig, Order};

    fn warm() -> Estimator {
        let mut e: Estimator = Estimator::new(
            EstimatorConfig {
                window: 10,
                ..Default::default()
            },
            Order::One,
        )
        .unwrap();
        for k in 0..25 {
            e.push(f64::from(k) * 0.01, f64::from(k).sin(), 0.5)
                .unwrap();
        }
        e
    }

    /// A state that decodes but could not have been reached is refused: each tampering
    /// alone, on a state that decodes as it is.
    #[test]
    fn unreachable_estimator_states_are_refused() {
        let e = warm();
        assert!(from_bytes::<Estimator>(&to_bytes(&e).unwrap()).is_ok());
        // An empty estimator, whose indices any window admits.
        let mut window_zero: Estimator =
            Estimator::new(EstimatorConfig::default(), Order::One).unwrap();
        window_zero.config.window = 0;
        let mut overflowing = e.clone();
        overflowing.next_index = u64::MAX;
        let mut stale_shadow = e.clone();
        stale_shadow.shadow.active = true;
        stale_shadow.shadow.first = stale_shadow.next_index - stale_shadow.len as u64 - 1;
        for (what, bad) in [
            ("window 0", window_zero),
            ("count about to overflow", overflowing),
            ("shadow started before the window", stale_shadow),
        ] {
            let bytes = to_bytes(&bad).unwrap();
            assert!(from_bytes::<Estimator>(&bytes).is_err(), "{what} decoded");
        }
    }

    /// `bytes` with the first 8 bytes that encode `from` encoding `to` instead.
    fn tamper(bytes: &[u8], from: f64, to: f64) -> Vec<u8> {
        let at = bytes
            .windows(8)
            .position(|w| w == from.to_le_bytes())
            .expect("the value is in the encoding");
        let mut out = bytes.to_vec();
        out[at..at + 8].copy_from_slice(&to.to_le_bytes());
        out
    }

    /// The ring keeps each end two intervals share once, so a window whose intervals do not
    /// follow one another, or whose newest does not end at the last sample, cannot be
    /// represented: it is refused, not mended. The format is a ring of intervals: 0.20 s
    /// is where two of them meet (either copy moved opens a gap), and 0.24 s, the last
    /// sample, first appears as the newest interval's end.
    #[test]
    fn a_window_that_is_not_one_is_refused() {
        let e = warm();
        let bytes = to_bytes(&e).unwrap();
        let t = |k: u32| f64::from(k) * 0.01;
        for (what, k, message) in [
            ("a gap", 20, "do not follow one another"),
            ("the newest detached", 24, "is not its window's end"),
        ] {
            let bad = tamper(&bytes, t(k), t(k) + 0.001);
            let err = from_bytes::<Estimator>(&bad).expect_err(what).to_string();
            assert!(err.contains(message), "{what}: {err}");
        }
        let back: Estimator = from_bytes(&bytes).unwrap();
        assert_eq!(
            to_bytes(&back).unwrap(),
            bytes,
            "a state built by steps round-trips"
        );
    }
}
