//! The wire contract between plants, controllers and operators.
//!
//! * [`pb`]: the protobuf messages (schema in `proto/mfc/v1/mfc.proto`, compiled by prost
//!   with protox, so no system `protoc` is needed);
//! * [`keys`]: the key-expression layout, in one place;
//! * [`decode`]: decoders that check the protocol version and never panic on any input;
//! * [`convert`]: conversions between the wire configuration and the control core's types.

pub mod auth;
pub mod convert;
pub mod keys;
pub mod roles;

pub use prost::bytes::Bytes;

/// Generated protobuf types (package `mfc.v1`).
#[allow(missing_docs, clippy::all)]
pub mod pb {
    include!(concat!(env!("OUT_DIR"), "/mfc.v1.rs"));
}

/// The compiled schema of [`pb`] (package `mfc.v1`), as a serialized
/// `google.protobuf.FileDescriptorSet`: what an MCAP recording embeds with each protobuf
/// channel so that Foxglove, `mcap` tools or any protobuf library decode it as it is.
pub const FILE_DESCRIPTOR_SET: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/mfc_descriptor_set.bin"));

/// The package of every message, for fully qualified names (`mfc.v1.Sample`).
pub const PACKAGE: &str = "mfc.v1";

/// Version carried in field 1 of every top-level message; decoders refuse any other.
pub const PROTOCOL_VERSION: u32 = 1;

/// Largest payload a controller reads (bytes). A sample of 16 channels is under 400 bytes
/// and a configuration with long references a few kilobytes; anything larger is dropped
/// unread, before it is copied, so a flood of huge messages costs no memory.
pub const MAX_PAYLOAD: usize = 64 * 1024;

/// Largest message a controller's Zenoh session reassembles at all (bytes). Between
/// [`MAX_PAYLOAD`] and this, a message reaches the service and is counted as oversized;
/// beyond it, zenoh drops it while reassembling. Zenoh keeps one reassembly buffer per
/// priority and reliability of each link (16), so a peer can make the service hold at
/// most 16 times this, where zenoh's own default (1 GiB) would allow 16 GiB.
pub const MAX_TRANSPORT_MESSAGE: usize = 2 * 1024 * 1024;

/// Largest [`pb::SampleBatch`] payload a controller reads (bytes): 4096 samples of a few
/// channels fit. Larger batches are dropped unread (`oversized`).
pub const MAX_BATCH_PAYLOAD: usize = 1024 * 1024;

/// Most samples one [`pb::SampleBatch`] may carry; a batch with more is refused whole
/// (`oversized`), before any device state changes.
pub const MAX_BATCH_SAMPLES: usize = 4096;

/// Number of shards device state is spread over (inside one service, over its workers).
/// Fixed by the protocol so that every process computes the same [`shard_of`].
pub const SHARDS: u32 = 64;

/// Earlier samples an agent sends again with each sample (`Sample::previous_*`): runs of up
/// to this many lost samples leave the controller's data without a gap. Three covers the
/// runs that matter at 30 % loss (a fourth in a row: under 1 %), for about 25 bytes per
/// channel each.
pub const RESENT_SAMPLES: usize = 3;

/// Longest horizon a command carries (periods, `Command::horizon` holds this many values
/// per channel at most), with or without delay compensation: a prediction a second ahead
/// at 100 Hz has long stopped meaning anything. The service plans no further; the agent
/// ignores a longer horizon as malformed.
pub const MAX_HORIZON: u32 = 100;

/// The shard of an id (a device's, or a gateway's for the plants it hosts): FNV-1a, so
/// it is the same on every platform and easy to compute in any language (64-bit FNV-1a
/// of the UTF-8 bytes, modulo [`SHARDS`]).
pub fn shard_of(id: &str) -> u32 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in id.bytes() {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    (h % u64::from(SHARDS)) as u32
}

/// Longest string from the network that is echoed, stored or logged (characters).
pub const MAX_ECHO: usize = 64;

/// A string from the network made safe to echo, store or log: at most [`MAX_ECHO`]
/// characters, control characters escaped, and a note of how long it really was when cut.
pub fn printable(s: &str) -> String {
    let mut out: String = s
        .chars()
        .take(MAX_ECHO)
        .flat_map(char::escape_debug)
        .collect();
    let n = s.chars().count();
    if n > MAX_ECHO {
        out.push_str(&format!("... ({} bytes)", s.len()));
    }
    out
}

/// Why a payload could not be used.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    /// Not a valid protobuf encoding of the message.
    #[error("malformed {what}: {source}")]
    Malformed {
        /// The message type expected ([`Versioned::NAME`], e.g. `Sample`).
        what: &'static str,
        /// prost's reason.
        source: prost::DecodeError,
    },
    /// A different protocol version (or none at all).
    #[error("{what} has protocol version {got}, this build speaks {PROTOCOL_VERSION}")]
    Version {
        /// The message type expected ([`Versioned::NAME`]).
        what: &'static str,
        /// The version the payload carries: 0 when it carries none (an empty payload
        /// decodes to all defaults).
        got: u32,
    },
}

/// Messages that carry a version in field 1.
pub trait Versioned: prost::Message + Default {
    /// The protobuf message name (`Sample`, `Command`, ...), to say which decode failed.
    const NAME: &'static str;
    /// Field 1, which [`decode`] compares with [`PROTOCOL_VERSION`].
    fn version(&self) -> u32;
}

macro_rules! versioned {
    ($($t:ident),*) => {$(
        impl Versioned for pb::$t {
            const NAME: &'static str = stringify!($t);
            fn version(&self) -> u32 {
                self.version
            }
        }
    )*};
}
versioned!(
    Sample,
    Command,
    DeviceConfig,
    ConfigRequest,
    ConfigReply,
    ReferenceUpdate,
    EnvelopeRequest,
    CommissionRequest,
    DeviceStatus,
    ServiceStatus,
    Heartbeat,
    SampleBatch,
    CommandBatch,
    Event,
    AuditLog
);

/// A [`pb::SampleBatch`] as it arrives, its samples left encoded: the same wire format,
/// since an embedded message is a length-delimited field, read here as bytes.
///
/// Decoded from a [`Bytes`] ([`decode_from`]), each sample is a slice of the payload, not
/// a copy: taking a batch in allocates the list of slices and nothing per sample. Whoever
/// steps the samples decodes each in turn into a [`pb::Sample`] it keeps
/// ([`SampleBatchView::read_sample`]), whose strings and lists keep their capacity from
/// one sample to the next. Decoding every sample on arrival allocated each one's strings
/// and lists (four or five per sample, thousands per batch) and the batch's list of them
/// (a quarter of a megabyte for a batch of a thousand), on the thread that received it
/// and freed on the thread that served it (`docs/scale.md`, "Memory per plant").
#[derive(Clone, PartialEq, prost::Message)]
pub struct SampleBatchView {
    /// [`PROTOCOL_VERSION`].
    #[prost(uint32, tag = "1")]
    pub version: u32,
    /// The gateway that sent it (the key's own, checked by the receiver).
    #[prost(string, tag = "2")]
    pub gateway_id: String,
    /// The samples, each an encoded [`pb::Sample`].
    #[prost(bytes = "bytes", repeated, tag = "3")]
    pub samples: Vec<Bytes>,
    /// As in [`pb::SampleBatch`]: how many plants the gateway hosts.
    #[prost(uint32, tag = "4")]
    pub plants: u32,
    /// As in [`pb::SampleBatch`].
    #[prost(bytes = "vec", tag = "100")]
    pub mac: Vec<u8>,
}

impl Versioned for SampleBatchView {
    const NAME: &'static str = "SampleBatch";
    fn version(&self) -> u32 {
        self.version
    }
}

impl SampleBatchView {
    /// Decode one of [`Self::samples`] into `into`, replacing what it held (its buffers
    /// are reused). Never panics. The sample's own version is not checked, as in a decoded
    /// [`pb::SampleBatch`]: the batch's is.
    pub fn read_sample(raw: &[u8], into: &mut pb::Sample) -> Result<(), DecodeError> {
        use prost::Message;
        into.clear();
        into.merge(raw).map_err(|source| DecodeError::Malformed {
            what: "Sample",
            source,
        })
    }
}

/// [`decode`] from any buffer: from a [`Bytes`], the `bytes` fields of the message (such
/// as [`SampleBatchView::samples`]) are slices of it, not copies.
pub fn decode_from<M: Versioned>(buf: impl prost::bytes::Buf) -> Result<M, DecodeError> {
    let m = M::decode(buf).map_err(|source| DecodeError::Malformed {
        what: M::NAME,
        source,
    })?;
    if m.version() != PROTOCOL_VERSION {
        return Err(DecodeError::Version {
            what: M::NAME,
            got: m.version(),
        });
    }
    Ok(m)
}

/// Decode a versioned message; never panics, whatever the bytes.
pub fn decode<M: Versioned>(bytes: &[u8]) -> Result<M, DecodeError> {
    decode_from(bytes)
}

/// Encode a message to bytes; cannot fail. It does not set `version`: the caller fills it
/// with [`PROTOCOL_VERSION`], or the peer's [`decode`] refuses the message.
pub fn encode<M: prost::Message>(m: &M) -> Vec<u8> {
    m.encode_to_vec()
}

/// [`encode`] for a service's batch of commands, the same bytes with each command's length
/// computed once. prost sizes the buffer from the batch's length, which adds up its
/// commands' lengths, then computes each command's length again for its prefix: a
/// second pass over every field of a thousand commands, a sixth of encoding the batch
/// (`docs/scale.md`, "Counted in instructions"). The buffer is sized from the first
/// command's length instead (at most [`MAX_BATCH_PAYLOAD`]), and grows if the others are
/// longer.
pub fn encode_command_batch(batch: &pb::CommandBatch) -> Vec<u8> {
    // Every field named, none left to `..`: a field added to the message does not compile
    // here until it is encoded too.
    let pb::CommandBatch {
        version,
        gateway_id,
        commands,
        controller_id,
        mac,
    } = batch;
    let mut buf = Vec::with_capacity(batch_capacity(
        commands,
        gateway_id.len() + controller_id.len() + mac.len(),
    ));
    fields::uint32(1, *version, &mut buf);
    fields::string(2, gateway_id, &mut buf);
    fields::messages(3, commands, &mut buf);
    fields::string(4, controller_id, &mut buf);
    fields::bytes(100, mac, &mut buf);
    buf
}

/// [`encode_command_batch`] for a gateway's batch of samples.
pub fn encode_sample_batch(batch: &pb::SampleBatch) -> Vec<u8> {
    let pb::SampleBatch {
        version,
        gateway_id,
        samples,
        plants,
        mac,
    } = batch;
    let mut buf = Vec::with_capacity(batch_capacity(samples, gateway_id.len() + mac.len()));
    fields::uint32(1, *version, &mut buf);
    fields::string(2, gateway_id, &mut buf);
    fields::messages(3, samples, &mut buf);
    fields::uint32(4, *plants, &mut buf);
    fields::bytes(100, mac, &mut buf);
    buf
}

/// A batch's likely size: as many items as the first, each with a key and a length of at
/// most 3 bytes each, and its other fields' bytes with their keys.
fn batch_capacity<M: prost::Message>(items: &[M], other_bytes: usize) -> usize {
    let first = items.first().map_or(0, prost::Message::encoded_len);
    items
        .len()
        .saturating_mul(first.saturating_add(6))
        .saturating_add(other_bytes)
        .saturating_add(32)
        .min(MAX_BATCH_PAYLOAD)
}

/// The fields of a batch, each as prost's derived encoding writes it: a proto3 scalar at
/// its default is not written, and a nested message is its key, its length and its fields.
mod fields {
    use prost::encoding::{encode_key, encode_varint, WireType};
    use prost::Message;

    pub(super) fn uint32(tag: u32, value: u32, buf: &mut Vec<u8>) {
        if value != 0 {
            prost::encoding::uint32::encode(tag, &value, buf);
        }
    }

    pub(super) fn string(tag: u32, value: &String, buf: &mut Vec<u8>) {
        if !value.is_empty() {
            prost::encoding::string::encode(tag, value, buf);
        }
    }

    pub(super) fn bytes(tag: u32, value: &Vec<u8>, buf: &mut Vec<u8>) {
        if !value.is_empty() {
            prost::encoding::bytes::encode(tag, value, buf);
        }
    }

    pub(super) fn messages<M: Message>(tag: u32, items: &[M], buf: &mut Vec<u8>) {
        for m in items {
            encode_key(tag, WireType::LengthDelimited, buf);
            encode_varint(m.encoded_len() as u64, buf);
            m.encode_raw(buf);
        }
    }
}

/// Wall clock in Unix nanoseconds (0 if the clock is before 1970): the `sent_unix_ns` and
/// `controller_unix_ns` stamps. The controllers never step on it: they follow `plant_time`.
pub fn unix_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_nanos() as u64)
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        /// Every decoder survives arbitrary bytes.
        #[test]
        fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = decode::<pb::Sample>(&bytes);
            let _ = decode::<pb::Command>(&bytes);
            let _ = decode::<pb::DeviceConfig>(&bytes);
            let _ = decode::<pb::ConfigRequest>(&bytes);
            let _ = decode::<pb::ConfigReply>(&bytes);
            let _ = decode::<pb::ReferenceUpdate>(&bytes);
            let _ = decode::<pb::EnvelopeRequest>(&bytes);
            let _ = decode::<pb::DeviceStatus>(&bytes);
            let _ = decode::<pb::ServiceStatus>(&bytes);
            let _ = decode::<pb::Heartbeat>(&bytes);
            let _ = decode::<pb::SampleBatch>(&bytes);
            let _ = decode::<pb::CommandBatch>(&bytes);
            if let Ok(view) = decode_from::<SampleBatchView>(Bytes::from(bytes.clone())) {
                let mut s = pb::Sample::default();
                for raw in &view.samples {
                    let _ = SampleBatchView::read_sample(raw, &mut s);
                }
            }
        }

        /// Mutations of a valid sample decode or fail, never panic, and a decoded config
        /// converts or fails cleanly.
        #[test]
        fn mutated_messages_never_panic(flips in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..16)) {
            let cfg = pb::ConfigRequest {
                version: PROTOCOL_VERSION,
                channels: vec![convert::channel_to_pb(&mfc::ChannelConfig::default())],
                reference: Some(convert::reference_to_pb(&[vec![mfc::trajectory::Piece::Constant { value: 1.0 }]], 0.0)),
                updates: vec![pb::ChannelUpdate { channel: 0, kp: Some(2.0), max: Some(1.0), ..Default::default() }],
            };
            let mut bytes = encode(&cfg);
            for (i, b) in flips {
                if !bytes.is_empty() {
                    let n = bytes.len();
                    bytes[i % n] ^= b;
                }
            }
            if let Ok(m) = decode::<pb::ConfigRequest>(&bytes) {
                for c in &m.channels {
                    let _ = convert::channel_from_pb(c);
                }
                if let Some(r) = &m.reference {
                    let _ = convert::reference_from_pb(r);
                }
                for u in &m.updates {
                    let _ = convert::apply_update(&mfc::ChannelConfig::default(), u);
                }
            }
        }
    }

    fn text() -> impl Strategy<Value = String> {
        proptest::string::string_regex("[a-z0-9-]{0,12}").unwrap()
    }

    fn floats(max: usize) -> impl Strategy<Value = Vec<f64>> {
        proptest::collection::vec(any::<f64>(), 0..max)
    }

    prop_compose! {
        fn command()(device_id in text(), seq in any::<u64>(), u in floats(4), v in floats(4),
                     f_est in floats(3), horizon in floats(40), error in text(),
                     ns in any::<u64>(), mode in 0..5i32, epoch in any::<u64>()) -> pb::Command {
            pb::Command {
                version: PROTOCOL_VERSION, device_id, seq, u, v, f_est, horizon, error, mode,
                controller_unix_ns: ns, lease_epoch: epoch, controller_id: "svc".into(),
                ..Default::default()
            }
        }
    }

    prop_compose! {
        fn sample()(device_id in text(), seq in any::<u64>(), t in any::<f64>(),
                    outputs in floats(4), applied in floats(4), previous in floats(12),
                    run_id in any::<u64>(), flags in any::<u32>()) -> pb::Sample {
            pb::Sample {
                version: PROTOCOL_VERSION, device_id, seq, plant_time: t, outputs, applied,
                previous_outputs: previous, run_id, flags, ..Default::default()
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(500))]
        /// The batches' own encoders write exactly prost's bytes, for any commands or
        /// samples, of equal lengths or not (the buffer sized from the first then grows),
        /// and with each of the batch's own fields set or at its default.
        #[test]
        fn batch_encoders_write_what_prost_writes(
            version in prop_oneof![Just(0u32), any::<u32>()], gateway_id in text(),
            controller_id in text(), mac in proptest::collection::vec(any::<u8>(), 0..40),
            plants in prop_oneof![Just(0u32), any::<u32>()],
            commands in proptest::collection::vec(command(), 0..30),
            samples in proptest::collection::vec(sample(), 0..30),
        ) {
            let c = pb::CommandBatch { version, gateway_id: gateway_id.clone(), commands, controller_id, mac: mac.clone() };
            prop_assert_eq!(encode_command_batch(&c), encode(&c));
            let s = pb::SampleBatch { version, gateway_id, samples, plants, mac };
            prop_assert_eq!(encode_sample_batch(&s), encode(&s));
        }
    }

    /// A batch read as a view gives back every sample as the whole decode does, each a
    /// slice of the payload; a reused sample leaves nothing of the one before.
    #[test]
    fn a_batch_view_reads_what_the_batch_holds() {
        let sample = |i: u64, outputs: Vec<f64>, holder: &str| pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: format!("load-{i}"),
            seq: i,
            plant_time: i as f64 * 0.01,
            outputs,
            applied: vec![0.5; (i % 2) as usize],
            lease_holder: holder.into(),
            ..Default::default()
        };
        let batch = pb::SampleBatch {
            version: PROTOCOL_VERSION,
            gateway_id: "gw-1".into(),
            samples: vec![
                sample(1, vec![1.0, 2.0, 3.0], "bench"),
                sample(2, vec![4.0], ""),
                sample(3, vec![], "other"),
            ],
            plants: 3,
            mac: Vec::new(),
        };
        let payload = Bytes::from(encode(&batch));
        let range = payload.as_ptr_range();
        let view: SampleBatchView = decode_from(payload.clone()).unwrap();
        assert_eq!((view.version, view.gateway_id.as_str()), (1, "gw-1"));
        assert_eq!(view.samples.len(), 3);
        assert_eq!(view.plants, 3);
        let mut s = pb::Sample::default();
        for (k, want) in batch.samples.iter().enumerate() {
            assert!(
                range.contains(&view.samples[k].as_ptr()),
                "sample {k} copied"
            );
            SampleBatchView::read_sample(&view.samples[k], &mut s).unwrap();
            assert_eq!(&s, want);
        }
        // A length past the end, inside a batch whose own framing holds.
        assert!(SampleBatchView::read_sample(&[0x12, 0x05, 0x01], &mut s).is_err());
        let old = pb::SampleBatch {
            version: 2,
            ..batch
        };
        assert!(matches!(
            decode_from::<SampleBatchView>(Bytes::from(encode(&old))),
            Err(DecodeError::Version { got: 2, .. })
        ));
    }

    #[test]
    fn shards_are_stable_and_spread() {
        // Fixed values: another implementation must compute the same shards.
        assert_eq!(shard_of(""), (0xcbf2_9ce4_8422_2325u64 % 64) as u32);
        // The same values as deploy/test/multihost.py's shard_of.
        assert_eq!(
            (shard_of("aero-1"), shard_of("aero-2"), shard_of("load-0")),
            (22, 35, 52)
        );
        let mut seen = [0u32; SHARDS as usize];
        for i in 0..6400 {
            seen[shard_of(&format!("load-{i}")) as usize] += 1;
        }
        // 100 expected per shard: every shard used, none with more than twice its share.
        assert!(seen.iter().all(|&n| n > 0 && n < 200), "{seen:?}");
    }

    #[test]
    fn printable_caps_and_escapes() {
        assert_eq!(printable("aero-1"), "aero-1");
        assert_eq!(printable("a\nb"), "a\\nb");
        let huge = "x".repeat(1 << 20);
        let p = printable(&huge);
        assert!(p.len() < 100 && p.ends_with("(1048576 bytes)"), "{p}");
    }

    #[test]
    fn version_is_checked() {
        let s = pb::Sample {
            version: 2,
            ..Default::default()
        };
        assert!(matches!(
            decode::<pb::Sample>(&encode(&s)),
            Err(DecodeError::Version { got: 2, .. })
        ));
        // An empty payload decodes to version 0: refused, not mistaken for a sample.
        assert!(matches!(
            decode::<pb::Sample>(&[]),
            Err(DecodeError::Version { got: 0, .. })
        ));
        let ok = pb::Sample {
            version: PROTOCOL_VERSION,
            device_id: "aero-1".into(),
            seq: 7,
            outputs: vec![1.0, 2.0],
            ..Default::default()
        };
        assert_eq!(decode::<pb::Sample>(&encode(&ok)).unwrap(), ok);
    }
}
