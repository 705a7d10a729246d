//! The one codec of device snapshots (bincode, pinned to 2.0.1).
//!
//! A snapshot holds everything the service knows about a device: the whole control state
//! (every channel's law, estimator window, integrals, output map; see `mfc::snapshot`), the
//! reference and its phase (its start on the plant's clock), the plant run it belongs to,
//! the last sequence number and plant time, and the counters. A format version comes first,
//! so an old file is refused rather than mis-read.

use bincode::{Decode, Encode};
use mfc::trajectory::Piece;

/// Bumped whenever the layout changes.
pub const SNAPSHOT_VERSION: u32 = 1;

/// What a device snapshot holds.
#[derive(Debug, Clone, Encode, Decode)]
pub struct DeviceSnapshot {
    /// Format version.
    pub version: u32,
    /// Device id.
    pub id: String,
    /// The control state, encoded by `mfc::snapshot`.
    pub mimo: Vec<u8>,
    /// Reference pieces per channel.
    pub reference: Vec<Vec<Piece>>,
    /// Reference start on the plant's clock.
    pub reference_start: f64,
    /// Plant run id.
    pub run_id: Option<u64>,
    /// Last answered sequence number.
    pub last_seq: Option<u64>,
    /// Plant time of that sample.
    pub last_time: f64,
    /// Counters: samples, commands, lost, duplicates, stale, rejected, plant fallbacks.
    pub counters: [u64; 7],
    /// Whether the device came from a template.
    pub from_template: bool,
}

/// Why a snapshot could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    /// Encoding failed.
    #[error("encoding a snapshot: {0}")]
    Encode(#[from] bincode::error::EncodeError),
    /// The bytes are not a snapshot of this format.
    #[error("decoding a snapshot: {0}")]
    Decode(#[from] bincode::error::DecodeError),
    /// Another format version.
    #[error("snapshot format {0}, this build reads {SNAPSHOT_VERSION}")]
    Version(u32),
}

/// Encode a snapshot.
pub fn encode(s: &DeviceSnapshot) -> Result<Vec<u8>, SnapshotError> {
    Ok(bincode::encode_to_vec(s, bincode::config::standard())?)
}

/// Decode a snapshot; never panics on any input.
pub fn decode(bytes: &[u8]) -> Result<DeviceSnapshot, SnapshotError> {
    let (s, _): (DeviceSnapshot, usize) =
        bincode::decode_from_slice(bytes, bincode::config::standard())?;
    if s.version != SNAPSHOT_VERSION {
        return Err(SnapshotError::Version(s.version));
    }
    Ok(s)
}
