//! MCAP recordings.
//!
//! One topic per device and kind, `/mfc/{device}/{kind}`, each message the protobuf
//! encoding of the wire message itself ([`Topic::message`]), with the schema of package
//! `mfc.v1` embedded as a `FileDescriptorSet` ([`protocol::FILE_DESCRIPTOR_SET`]), the
//! encoding MCAP's registry calls `protobuf`: Foxglove plots `/mfc/aero-1/command.v[1]`
//! from the file alone. Attachments carry what a replay needs besides the messages (the
//! service's configuration, restored device state).
//!
//! Writing happens on a thread of its own behind a bounded queue: a control loop hands
//! over bytes it has already encoded and never waits for a disk. A full queue drops the
//! message and counts it ([`Recording::dropped`]); the count is written into the file's
//! metadata (`mfc.recording` / `dropped`) when it is finished, so a reader knows whether
//! the file is complete.

use std::collections::{BTreeMap, HashMap};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, SyncSender, TrySendError};
use std::sync::Arc;
use std::thread::JoinHandle;

use serde::{Deserialize, Serialize};

/// Where to record.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RecordSpec {
    /// The MCAP file to write. No default: recording is off unless asked for.
    pub path: PathBuf,
    /// What to do with a file already at `path` (a service restarted): keep it, renamed
    /// `{name}.{unix seconds}.mcap` (true, the default), or replace it (false).
    #[serde(default = "yes")]
    pub keep_previous: bool,
    /// Messages that may wait for the writer (default 65 536: several seconds of a
    /// thousand plants at 100 Hz); beyond it messages are dropped and counted.
    #[serde(default = "queue")]
    pub queue: usize,
    /// Most message bytes one file takes (default 4 GiB): a recording left on in a large
    /// fleet cannot fill the disk; beyond it messages are dropped and counted, and the
    /// file is finished properly at the end.
    #[serde(default = "max_bytes")]
    pub max_bytes: u64,
}

fn yes() -> bool {
    true
}

fn queue() -> usize {
    65_536
}

fn max_bytes() -> u64 {
    4 << 30
}

impl RecordSpec {
    /// Record into `path` with the default queue.
    pub fn at(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            keep_previous: true,
            queue: queue(),
            max_bytes: max_bytes(),
        }
    }
}

/// What a recorded message is; its protobuf message and topic suffix.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Topic {
    /// A sample, as received (service) or sent (agent).
    Sample,
    /// A command, as sent (service) or received (agent); its `f_est` are the F estimates.
    Command,
    /// The device's configuration: when recording starts, and after every change.
    Config,
    /// A configuration change as asked (a partial or whole `ConfigRequest`).
    ConfigRequest,
    /// A reference change as asked.
    ReferenceUpdate,
    /// An envelope change as asked.
    EnvelopeRequest,
    /// A commissioning request as asked (start, confirm, abort).
    CommissionRequest,
    /// Something that happened ([`protocol::pb::Event`]).
    Event,
}

impl Topic {
    /// Every kind.
    pub const ALL: [Topic; 8] = [
        Topic::Sample,
        Topic::Command,
        Topic::Config,
        Topic::ConfigRequest,
        Topic::ReferenceUpdate,
        Topic::EnvelopeRequest,
        Topic::CommissionRequest,
        Topic::Event,
    ];

    /// The last segment of the topic.
    pub fn suffix(self) -> &'static str {
        match self {
            Topic::Sample => "sample",
            Topic::Command => "command",
            Topic::Config => "config",
            Topic::ConfigRequest => "config_request",
            Topic::ReferenceUpdate => "reference_update",
            Topic::EnvelopeRequest => "envelope_request",
            Topic::CommissionRequest => "commission_request",
            Topic::Event => "event",
        }
    }

    /// The fully qualified protobuf message of its payload.
    pub fn message(self) -> &'static str {
        match self {
            Topic::Sample => "mfc.v1.Sample",
            Topic::Command => "mfc.v1.Command",
            Topic::Config => "mfc.v1.DeviceConfig",
            Topic::ConfigRequest => "mfc.v1.ConfigRequest",
            Topic::ReferenceUpdate => "mfc.v1.ReferenceUpdate",
            Topic::EnvelopeRequest => "mfc.v1.EnvelopeRequest",
            Topic::CommissionRequest => "mfc.v1.CommissionRequest",
            Topic::Event => "mfc.v1.Event",
        }
    }

    fn from_suffix(s: &str) -> Option<Topic> {
        Topic::ALL.into_iter().find(|t| t.suffix() == s)
    }
}

/// The topic of a device's messages of one kind.
pub fn topic_name(device: &str, topic: Topic) -> String {
    format!("/mfc/{device}/{}", topic.suffix())
}

/// Why a recording failed.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The file could not be created.
    #[error("recording to {path}: {source}")]
    Create {
        /// The file.
        path: PathBuf,
        /// The system's reason.
        source: std::io::Error,
    },
    /// The MCAP writer or reader refused.
    #[error("MCAP: {0}")]
    Mcap(#[from] mcap::McapError),
    /// The writer thread ended abnormally.
    #[error("the recording thread panicked")]
    Thread,
}

enum Entry {
    Message {
        device: String,
        topic: Topic,
        log_ns: u64,
        publish_ns: u64,
        data: Vec<u8>,
    },
    Attachment {
        name: String,
        media_type: String,
        data: Vec<u8>,
    },
}

/// What a finished recording holds.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct RecordSummary {
    /// Messages written.
    pub messages: u64,
    /// Messages dropped because the writer fell behind.
    pub dropped: u64,
}

/// A recording in progress. Cheap to clone (every clone feeds the same file); the file is
/// finished when [`Recording::finish`] is called on one of them, or when the last is
/// dropped.
#[derive(Clone)]
pub struct Recording {
    inner: Arc<Inner>,
}

struct Inner {
    tx: std::sync::Mutex<Option<SyncSender<Entry>>>,
    dropped: Arc<AtomicU64>,
    thread: std::sync::Mutex<Option<JoinHandle<Result<RecordSummary, RecordError>>>>,
    path: PathBuf,
}

impl Drop for Inner {
    fn drop(&mut self) {
        self.tx.lock().map(|mut t| t.take()).ok();
        if let Some(h) = self.thread.lock().ok().and_then(|mut t| t.take()) {
            match h.join() {
                Ok(Ok(_)) => {}
                Ok(Err(e)) => tracing::warn!(path = %self.path.display(), "recording: {e}"),
                Err(_) => tracing::warn!(path = %self.path.display(), "recording thread panicked"),
            }
        }
    }
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("path", &self.inner.path)
            .field("dropped", &self.dropped())
            .finish()
    }
}

impl Recording {
    /// Start recording as `spec` says; `source` names the writer (`controller-service`,
    /// `plant-agent`) in the file's header.
    pub fn create(spec: &RecordSpec, source: &str) -> Result<Self, RecordError> {
        if spec.keep_previous && spec.path.exists() {
            let stem = spec
                .path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            let secs = protocol::unix_ns() / 1_000_000_000;
            let old = spec.path.with_file_name(format!("{stem}.{secs}.mcap"));
            std::fs::rename(&spec.path, &old).map_err(|source| RecordError::Create {
                path: old.clone(),
                source,
            })?;
            tracing::info!(previous = %old.display(), "the previous recording is kept");
        }
        let file = File::create(&spec.path).map_err(|source| RecordError::Create {
            path: spec.path.clone(),
            source,
        })?;
        // Chunks of 64 KiB (the crate's default is 768 KiB): a writer killed before it
        // finishes loses at most the chunk it was filling.
        let writer = mcap::WriteOptions::new()
            .compression(None)
            .chunk_size(Some(64 * 1024))
            .profile("")
            .library(format!("mfc-zenoh {source}"))
            .create(BufWriter::new(file))?;
        let (tx, rx) = sync_channel(spec.queue.max(1));
        let dropped = Arc::new(AtomicU64::new(0));
        let d = dropped.clone();
        let (limit, path) = (spec.max_bytes, spec.path.clone());
        let thread = std::thread::Builder::new()
            .name("mcap-writer".into())
            .spawn(move || write_all(writer, rx, &d, limit, &path))
            .map_err(|source| RecordError::Create {
                path: spec.path.clone(),
                source,
            })?;
        tracing::info!(path = %spec.path.display(), "recording (MCAP)");
        Ok(Self {
            inner: Arc::new(Inner {
                tx: std::sync::Mutex::new(Some(tx)),
                dropped,
                thread: std::sync::Mutex::new(Some(thread)),
                path: spec.path.clone(),
            }),
        })
    }

    fn send(&self, entry: Entry) {
        let guard = match self.inner.tx.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        };
        let Some(tx) = guard.as_ref() else {
            self.inner.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        };
        match tx.try_send(entry) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.inner.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }

    /// Record `data` (a protobuf message of `topic`'s kind) for `device`. `log_ns` is when
    /// this process saw it (Unix ns), `publish_ns` when its sender sent it.
    pub fn record(&self, device: &str, topic: Topic, log_ns: u64, publish_ns: u64, data: Vec<u8>) {
        self.send(Entry::Message {
            device: device.to_string(),
            topic,
            log_ns,
            publish_ns,
            data,
        });
    }

    /// Record an event.
    pub fn event(&self, device: &str, kind: &str, text: impl Into<String>, plant_time: f64) {
        let e = protocol::pb::Event {
            version: protocol::PROTOCOL_VERSION,
            device_id: device.to_string(),
            kind: kind.to_string(),
            text: text.into(),
            plant_time,
        };
        let now = protocol::unix_ns();
        self.record(device, Topic::Event, now, now, protocol::encode(&e));
    }

    /// Attach a file (a configuration, a device's state).
    pub fn attach(&self, name: &str, media_type: &str, data: Vec<u8>) {
        self.send(Entry::Attachment {
            name: name.to_string(),
            media_type: media_type.to_string(),
            data,
        });
    }

    /// Messages dropped so far.
    pub fn dropped(&self) -> u64 {
        self.inner.dropped.load(Ordering::Relaxed)
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.inner.path
    }

    /// Write what is queued, the summary and the footer; later calls (from clones) only
    /// count what they would have written as dropped.
    pub fn finish(&self) -> Result<RecordSummary, RecordError> {
        self.inner.tx.lock().map(|mut t| t.take()).ok();
        let handle = self.inner.thread.lock().ok().and_then(|mut t| t.take());
        match handle {
            Some(h) => h.join().map_err(|_| RecordError::Thread)?,
            None => Ok(RecordSummary::default()),
        }
    }
}

fn write_all(
    mut w: mcap::Writer<BufWriter<File>>,
    rx: Receiver<Entry>,
    dropped: &AtomicU64,
    max_bytes: u64,
    path: &Path,
) -> Result<RecordSummary, RecordError> {
    let mut bytes = 0u64;
    let mut schemas: HashMap<Topic, u16> = HashMap::new();
    let mut channels: HashMap<(String, Topic), u16> = HashMap::new();
    let mut sequence: u32 = 0;
    let mut written = 0u64;
    let no_meta = BTreeMap::new();
    while let Ok(entry) = rx.recv() {
        match entry {
            Entry::Message {
                device,
                topic,
                log_ns,
                publish_ns,
                data,
            } => {
                if bytes + data.len() as u64 > max_bytes {
                    if dropped.fetch_add(1, Ordering::Relaxed) == 0 {
                        tracing::warn!(path = %path.display(), max_bytes, "recording full: further messages are dropped (and counted)");
                    }
                    continue;
                }
                bytes += data.len() as u64;
                let schema = match schemas.get(&topic) {
                    Some(s) => *s,
                    None => {
                        let s = w.add_schema(
                            topic.message(),
                            "protobuf",
                            protocol::FILE_DESCRIPTOR_SET,
                        )?;
                        schemas.insert(topic, s);
                        s
                    }
                };
                let key = (device, topic);
                let channel = match channels.get(&key) {
                    Some(c) => *c,
                    None => match w.add_channel(
                        schema,
                        &topic_name(&key.0, topic),
                        "protobuf",
                        &no_meta,
                    ) {
                        Ok(c) => {
                            channels.insert(key, c);
                            c
                        }
                        // Out of channel ids (65 535): count, keep the rest of the file.
                        Err(mcap::McapError::TooManyChannels) => {
                            dropped.fetch_add(1, Ordering::Relaxed);
                            continue;
                        }
                        Err(e) => return Err(e.into()),
                    },
                };
                sequence = sequence.wrapping_add(1);
                w.write_to_known_channel(
                    &mcap::records::MessageHeader {
                        channel_id: channel,
                        sequence,
                        log_time: log_ns,
                        publish_time: publish_ns,
                    },
                    &data,
                )?;
                written += 1;
            }
            Entry::Attachment {
                name,
                media_type,
                data,
            } => {
                let now = protocol::unix_ns();
                w.attach(&mcap::Attachment {
                    log_time: now,
                    create_time: now,
                    name,
                    media_type,
                    data: data.into(),
                })?;
            }
        }
    }
    let summary = RecordSummary {
        messages: written,
        dropped: dropped.load(Ordering::Relaxed),
    };
    w.write_metadata(&mcap::records::Metadata {
        name: "mfc.recording".into(),
        metadata: BTreeMap::from([
            ("messages".to_string(), summary.messages.to_string()),
            ("dropped".to_string(), summary.dropped.to_string()),
        ]),
    })?;
    w.finish()?;
    Ok(summary)
}

/// One message of a recording, as read back.
#[derive(Debug, Clone, PartialEq)]
pub struct Recorded {
    /// The device of its topic.
    pub device: String,
    /// Its kind.
    pub topic: Topic,
    /// When the recording process saw it (Unix ns).
    pub log_ns: u64,
    /// When its sender sent it (Unix ns).
    pub publish_ns: u64,
    /// The protobuf bytes.
    pub data: Vec<u8>,
}

/// What [`read_recording`] returns: the messages in file order, the attachments by name,
/// and the file's `mfc.recording` metadata (absent if the writer was killed before it
/// finished).
#[derive(Debug, Clone, Default)]
pub struct RecordingContents {
    /// Messages on `/mfc/{device}/{kind}` topics, in the order written.
    pub messages: Vec<Recorded>,
    /// Attachments by name.
    pub attachments: BTreeMap<String, Vec<u8>>,
    /// The writer's closing metadata.
    pub metadata: BTreeMap<String, String>,
    /// Messages on topics this project does not write (kept out of `messages`).
    pub foreign: usize,
    /// The file ends before its footer (the writer was killed): `messages` and
    /// `attachments` hold what was written before the cut, and there is no metadata.
    pub truncated: bool,
}

/// Read a whole recording. Refuses a file that is not MCAP; a file cut short (a writer
/// killed before it finished) gives the messages before the cut, marked `truncated`.
pub fn read_recording(bytes: &[u8]) -> Result<RecordingContents, RecordError> {
    if !bytes.starts_with(mcap::MAGIC) {
        return Err(mcap::McapError::BadMagic.into());
    }
    let mut out = RecordingContents::default();
    let finished = mcap::read::footer(bytes).is_ok();
    for m in mcap::MessageStream::new(bytes)? {
        let m = match m {
            Ok(m) => m,
            Err(e) if !finished => {
                tracing::debug!("recording cut short: {e}");
                out.truncated = true;
                break;
            }
            Err(e) => return Err(e.into()),
        };
        let parsed = m
            .channel
            .topic
            .strip_prefix("/mfc/")
            .and_then(|rest| rest.rsplit_once('/'))
            .and_then(|(dev, kind)| Topic::from_suffix(kind).map(|t| (dev.to_string(), t)));
        match parsed {
            Some((device, topic)) => out.messages.push(Recorded {
                device,
                topic,
                log_ns: m.log_time,
                publish_ns: m.publish_time,
                data: m.data.into_owned(),
            }),
            None => out.foreign += 1,
        }
    }
    if !finished {
        // No summary to find the attachments by: walk the records up to the cut.
        out.truncated = true;
        for r in mcap::read::LinearReader::new(bytes)? {
            match r {
                Ok(mcap::records::Record::Attachment { header, data, .. }) => {
                    out.attachments.insert(header.name, data.into_owned());
                }
                Ok(_) => {}
                Err(_) => break,
            }
        }
        return Ok(out);
    }
    if let Some(summary) = mcap::Summary::read(bytes)? {
        for a in summary.attachment_indexes.iter() {
            let att = mcap::read::attachment(bytes, a)?;
            out.attachments
                .insert(att.name.clone(), att.data.into_owned());
        }
        for mi in summary.metadata_indexes.iter() {
            let md = mcap::read::metadata(bytes, mi)?;
            if md.name == "mfc.recording" {
                out.metadata = md.metadata;
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::pb;

    #[test]
    fn a_recording_reads_back_with_its_schema_attachments_and_counts() {
        let dir = tempfile::tempdir().unwrap();
        let spec = RecordSpec::at(dir.path().join("r.mcap"));
        let rec = Recording::create(&spec, "test").unwrap();
        let s = pb::Sample {
            version: protocol::PROTOCOL_VERSION,
            device_id: "aero-1".into(),
            seq: 7,
            outputs: vec![0.5, -0.25],
            ..Default::default()
        };
        rec.record("aero-1", Topic::Sample, 10, 9, protocol::encode(&s));
        rec.event("aero-1", "start", "recording starts", 0.0);
        rec.attach("service-config.json", "application/json", b"{}".to_vec());
        let clone = rec.clone();
        let summary = rec.finish().unwrap();
        assert_eq!(
            summary,
            RecordSummary {
                messages: 2,
                dropped: 0
            }
        );
        // A clone's later message is counted, not lost silently.
        clone.record("aero-1", Topic::Sample, 11, 11, vec![]);
        assert_eq!(clone.dropped(), 1);

        let bytes = std::fs::read(&spec.path).unwrap();
        let c = read_recording(&bytes).unwrap();
        assert_eq!(c.messages.len(), 2);
        assert_eq!(c.messages[0].device, "aero-1");
        assert_eq!(c.messages[0].topic, Topic::Sample);
        assert_eq!((c.messages[0].log_ns, c.messages[0].publish_ns), (10, 9));
        let back: pb::Sample = protocol::decode(&c.messages[0].data).unwrap();
        assert_eq!(back, s);
        let ev: pb::Event = protocol::decode(&c.messages[1].data).unwrap();
        assert_eq!(ev.kind, "start");
        assert_eq!(c.attachments["service-config.json"], b"{}");
        assert_eq!(c.metadata["messages"], "2");
        assert_eq!(c.metadata["dropped"], "0");

        // The schema travels in the file: its descriptor set names the message.
        let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
        let ch = summary.channels.values().next().unwrap();
        let schema = ch.schema.as_ref().unwrap();
        assert_eq!(schema.encoding, "protobuf");
        assert_eq!(ch.message_encoding, "protobuf");
        let fds = <prost_types_shim::Fds as prost::Message>::decode(&schema.data[..]).unwrap();
        assert!(fds
            .file
            .iter()
            .any(|f| f.package.as_deref() == Some("mfc.v1")));
    }

    #[test]
    fn a_full_recording_drops_and_counts_and_still_finishes() {
        let dir = tempfile::tempdir().unwrap();
        let mut spec = RecordSpec::at(dir.path().join("r.mcap"));
        spec.max_bytes = 250;
        let rec = Recording::create(&spec, "test").unwrap();
        for _ in 0..5 {
            rec.record("d", Topic::Sample, 1, 1, vec![0u8; 100]);
        }
        let s = rec.finish().unwrap();
        assert_eq!((s.messages, s.dropped), (2, 3));
        let c = read_recording(&std::fs::read(&spec.path).unwrap()).unwrap();
        assert_eq!(c.messages.len(), 2);
        assert_eq!(c.metadata["dropped"], "3");
    }

    #[test]
    fn a_previous_recording_is_kept_unless_told_otherwise() {
        let dir = tempfile::tempdir().unwrap();
        let mut spec = RecordSpec::at(dir.path().join("s.mcap"));
        std::fs::write(&spec.path, b"earlier").unwrap();
        Recording::create(&spec, "test").unwrap().finish().unwrap();
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names.len(), 2, "{names:?}");
        let kept = names.iter().find(|n| *n != "s.mcap").unwrap();
        assert!(kept.starts_with("s.") && kept.ends_with(".mcap"), "{kept}");
        assert_eq!(std::fs::read(dir.path().join(kept)).unwrap(), b"earlier");
        spec.keep_previous = false;
        Recording::create(&spec, "test").unwrap().finish().unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[test]
    fn a_file_cut_short_gives_what_was_written_before() {
        let dir = tempfile::tempdir().unwrap();
        let mut spec = RecordSpec::at(dir.path().join("r.mcap"));
        let rec = Recording::create(&spec, "test").unwrap();
        for i in 0..2000u64 {
            rec.record("d", Topic::Sample, i, i, vec![7u8; 500]);
        }
        rec.finish().unwrap();
        let bytes = std::fs::read(&spec.path).unwrap();
        let whole = read_recording(&bytes).unwrap();
        assert!(!whole.truncated);
        assert_eq!(whole.messages.len(), 2000);
        // Cut in the middle, as a kill -9 would leave it.
        let cut = read_recording(&bytes[..bytes.len() / 2]).unwrap();
        assert!(cut.truncated);
        assert!(
            !cut.messages.is_empty() && cut.messages.len() < 2000,
            "{}",
            cut.messages.len()
        );
        assert!(cut
            .messages
            .iter()
            .enumerate()
            .all(|(i, m)| m.log_ns == i as u64));
        spec.path = dir.path().join("x");
        assert!(read_recording(&bytes[..4]).is_err(), "not even the magic");
    }

    #[test]
    fn garbage_is_refused_not_panicked_on() {
        assert!(read_recording(b"not an mcap file at all").is_err());
        assert!(read_recording(&[]).is_err());
    }

    /// The two fields of `google.protobuf.FileDescriptorSet` this test reads.
    mod prost_types_shim {
        #[derive(Clone, PartialEq, prost::Message)]
        pub struct Fds {
            #[prost(message, repeated, tag = "1")]
            pub file: Vec<Fd>,
        }
        #[derive(Clone, PartialEq, prost::Message)]
        pub struct Fd {
            #[prost(string, optional, tag = "1")]
            pub name: Option<String>,
            #[prost(string, optional, tag = "2")]
            pub package: Option<String>,
        }
    }
}
