//! The one codec of device snapshots (bincode, pinned to 2.0.1), and their files: one
//! `{id}.snap` per device in the snapshot directory ([`save_dir`], [`load_dir`]).
//!
//! A snapshot holds everything the service knows about a device: the whole control state
//! (every channel's law, estimator window, integrals, output map; see `mfc::snapshot`), the
//! reference and its phase (its start on the plant's clock), the plant run it belongs to,
//! the last sequence number and plant time, and the counters. A format version comes first,
//! so an old file is refused rather than mis-read.

use bincode::{Decode, Encode};
use mfc::trajectory::Piece;

/// Bumped whenever the layout changes; a file of another version is refused and its
/// device starts from the configuration (and a handed state of another version is not
/// restored). 2: the estimators' rings span their window only (files of 1 would be read
/// with the wrong layout). 4: the intelligent laws' `hold_estimate_filter` and
/// `hold_after`, and the time their reference has rested. 5: an intelligent controller
/// keeps its estimate's trend, for predictions. 6: a handed device carries its
/// configuration's version and whether the sender holds its lease. 7: a handed device
/// carries its latest audit entries. 8: the estimators' `first_window`, the intelligent
/// laws' `hold_band` and the sign they hold. 9: an estimator's ring is the window's
/// length (was the capacity's), and its shadow sums about the running sum's anchor. 10: an
/// estimator carries the order its running sums serve. 11: the intelligent laws'
/// `feedforward_within_range`.
pub const SNAPSHOT_VERSION: u32 = 11;

/// What a device snapshot holds.
#[derive(Debug, Clone, Encode, Decode)]
pub struct DeviceSnapshot {
    /// [`SNAPSHOT_VERSION`] when written; [`decode`] refuses any other.
    pub version: u32,
    /// Device id; the file is named after it (`{id}.snap`).
    pub id: String,
    /// The control state, encoded by `mfc::snapshot`. Its laws are compared with the
    /// configuration in force before a declared device is restored.
    pub mimo: Vec<u8>,
    /// Reference pieces per channel, as last set (a live update included); one entry per
    /// channel or the snapshot is refused.
    pub reference: Vec<Vec<Piece>>,
    /// Plant time (s) the reference is evaluated from, so a restored device keeps its phase.
    pub reference_start: f64,
    /// The plant run the state belongs to: a plant that restarted meanwhile sends another
    /// run id, and the restored control state is reset at its first sample.
    pub run_id: Option<u64>,
    /// Last sequence number answered with control values (`None`: none yet).
    pub last_seq: Option<u64>,
    /// Plant time of that sample (s). If the next sample comes more than 0.1 s later, the
    /// restored estimators start a fresh window.
    pub last_time: f64,
    /// Status counters, in this order: samples, commands, lost, duplicates, stale, rejected,
    /// samples_off_remote (samples sent off remote control, not fallback episodes).
    pub counters: [u64; 7],
    /// Provisioned from a template: restored even though no declaration names it, and
    /// without comparing its laws with the template's.
    pub from_template: bool,
}

/// Why a snapshot could not be used.
#[derive(Debug, thiserror::Error)]
pub enum SnapshotError {
    /// bincode could not encode it; the device is then left out of that save.
    #[error("encoding a snapshot: {0}")]
    Encode(#[from] bincode::error::EncodeError),
    /// The bytes are not a snapshot of this format.
    #[error("decoding a snapshot: {0}")]
    Decode(#[from] bincode::error::DecodeError),
    /// The bytes decode, but carry another [`SNAPSHOT_VERSION`].
    #[error("snapshot format {0}, this build reads {SNAPSHOT_VERSION}")]
    Version(u32),
}

/// Encode a snapshot with bincode's standard configuration, as [`decode`] expects.
pub fn encode(s: &DeviceSnapshot) -> Result<Vec<u8>, SnapshotError> {
    Ok(bincode::encode_to_vec(s, bincode::config::standard())?)
}

/// Decode a snapshot; never panics on any input, never allocates past
/// [`mfc::snapshot::MAX_STATE`].
pub fn decode(bytes: &[u8]) -> Result<DeviceSnapshot, SnapshotError> {
    let cfg = bincode::config::standard().with_limit::<{ mfc::snapshot::MAX_STATE }>();
    let (s, _): (DeviceSnapshot, usize) = bincode::decode_from_slice(bytes, cfg)?;
    if s.version != SNAPSHOT_VERSION {
        return Err(SnapshotError::Version(s.version));
    }
    Ok(s)
}

/// One device as handed from one fleet member to another ([`crate::fleet`]): its snapshot,
/// the shard it lives in (its gateway's, if it came through one), and its envelope in
/// force (`min`, `max`, `rate_limit` per channel), which a snapshot file leaves to the
/// service's configuration but a live handover must carry (it may have been narrowed).
#[derive(Debug, Clone, Encode, Decode)]
pub struct HandedDevice {
    pub snapshot: DeviceSnapshot,
    pub home: u32,
    pub envelope: Vec<(f64, f64, Option<f64>)>,
    /// Whether the live configuration (laws, maps) is to be taken as it is, even where it
    /// differs from the file's (a remote change made on the previous owner).
    pub live_config: bool,
    /// Which changes its configuration holds: it replaces the receiver's only if not
    /// older.
    pub config_version: crate::lease::Version,
    /// The plant's run and the lease epoch under which the sender holds the device's
    /// lease, if it does: the receiver is then in step with the holder.
    pub holds: Option<(u64, u64)>,
    /// The run and epoch of the lease as the sender last heard it (`(0, 0)`: never
    /// leased there): a receiver in step only with an earlier one missed a holder.
    pub heard: (u64, u64),
    /// Its latest audit entries (`pb::AuditLog`, protobuf), so that the member taking it
    /// over keeps its history (`crate::audit::merge`).
    pub audit: Vec<u8>,
}

/// The state of one shard, in a handover reply.
#[derive(Debug, Clone, Encode, Decode)]
pub struct ShardState {
    /// [`SNAPSHOT_VERSION`].
    pub version: u32,
    pub shard: u32,
    pub devices: Vec<HandedDevice>,
}

/// Largest shard state a member decodes (bytes): thousands of devices fit; a bigger or
/// hostile reply is refused before it is allocated.
pub const MAX_SHARD_STATE: usize = 64 << 20;

/// Encode a shard's state.
pub fn encode_shard(s: &ShardState) -> Result<Vec<u8>, SnapshotError> {
    Ok(bincode::encode_to_vec(s, bincode::config::standard())?)
}

/// Decode a shard's state; never panics, never allocates past [`MAX_SHARD_STATE`].
pub fn decode_shard(bytes: &[u8]) -> Result<ShardState, SnapshotError> {
    let cfg = bincode::config::standard().with_limit::<MAX_SHARD_STATE>();
    let (s, _): (ShardState, usize) = bincode::decode_from_slice(bytes, cfg)?;
    if s.version != SNAPSHOT_VERSION {
        return Err(SnapshotError::Version(s.version));
    }
    Ok(s)
}

/// Write every device's snapshot into `dir` (write to a temporary file, then rename: a
/// crash mid-write never leaves a torn snapshot). Returns how many were written; a device
/// that does not encode is skipped; the first I/O error ends the pass.
pub fn save_dir(registry: &crate::Registry, dir: &std::path::Path) -> std::io::Result<usize> {
    std::fs::create_dir_all(dir)?;
    let mut n = 0;
    for s in registry.snapshots() {
        let Ok(bytes) = encode(&s) else {
            continue;
        };
        let tmp = dir.join(format!(".{}.snap.tmp", s.id));
        std::fs::write(&tmp, bytes)?;
        std::fs::rename(&tmp, dir.join(format!("{}.snap", s.id)))?;
        n += 1;
    }
    Ok(n)
}

/// What [`load_dir`] did.
#[derive(Debug, Default)]
pub struct Loaded {
    /// Devices restored.
    pub restored: usize,
    /// Files refused, each with why (for the caller to log).
    pub refused: Vec<(std::path::PathBuf, String)>,
}

/// Restore every device that has a `.snap` file in `dir` into `registry`; nothing (not an
/// error) if `dir` cannot be read.
pub fn load_dir(registry: &mut crate::Registry, dir: &std::path::Path) -> Loaded {
    let mut out = Loaded::default();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return out;
    };
    for e in entries.flatten() {
        let path = e.path();
        if path.extension().is_none_or(|x| x != "snap") {
            continue;
        }
        let result = std::fs::read(&path)
            .map_err(|e| e.to_string())
            .and_then(|b| decode(&b).map_err(|e| e.to_string()))
            .and_then(|s| registry.restore(&s));
        match result {
            Ok(()) => out.restored += 1,
            Err(reason) => out.refused.push((path, reason)),
        }
    }
    out
}
