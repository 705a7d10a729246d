//! Binary snapshots of the whole controller state (feature `snapshot`, bincode).
//!
//! Every state type derives bincode's `Encode`/`Decode`, except the ones generic over the
//! window capacity `CAP`, whose derive bincode cannot generate (it copies the parameter's
//! default into the impl); those are written here, field by field, and the decoder checks
//! what a corrupted snapshot could break (ring indices within `CAP`).

use bincode::de::Decoder;
use bincode::enc::Encoder;
use bincode::error::{DecodeError, EncodeError};
use bincode::{Decode, Encode};

use crate::channel::{Channel, Law};
use crate::estimator::Estimator;
use crate::intelligent::IntelligentController;
use crate::mimo::MimoController;

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

snapshot_struct!(Estimator { config, ring, head, len, next_index, last, primary, shadow, lowpass }
check |e: &Estimator<CAP>| if e.head < e.config.intervals().clamp(1, CAP) && e.len <= e.config.intervals().min(CAP) && e.next_index >= e.len as u64 {
    Ok(())
} else {
    Err(DecodeError::Other("estimator ring indices out of range"))
});
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
    trend
});
snapshot_struct!(Channel {
    law,
    config,
    map,
    last_t,
    last_v
});
snapshot_struct!(MimoController { channels });

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

/// Decode state encoded by [`to_bytes`]; refuses trailing bytes.
pub fn from_bytes<T: Decode<()>>(bytes: &[u8]) -> Result<T, DecodeError> {
    let (v, used) = bincode::decode_from_slice(bytes, bincode::config::standard())?;
    if used != bytes.len() {
        return Err(DecodeError::Other("trailing bytes after the snapshot"));
    }
    Ok(v)
}
