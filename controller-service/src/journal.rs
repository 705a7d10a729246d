//! The durable record of operators' changes, without I/O of its own: what a line of the
//! audit file says, how a file is read back into the latest state of every device, and how
//! a batch of lines is made durable on a [`Disk`] (appended, synced, rotated), all or
//! nothing. The file itself is opened and written by `service::trail` ([`FsDisk`] there);
//! the seeded simulation writes to a simulated disk through the same [`Store`].
//!
//! Why the audit file and the state are one record: an acknowledged change must survive
//! every restart *and* have its audit entry (IEC 62443-4-2 CR 2.8), and a change must never
//! be in force without its entry. Two files would need two writes and a repair after a
//! crash between them; one line needs one write and one `fdatasync`. So every accepted
//! decision's line also carries the device's whole configuration after it ([`State`]: laws,
//! output maps, envelope, reference, the change's [`Version`]) and the file's own
//! configuration it was derived from (for the three-way merge with an edited file,
//! `crate::registry`'s `recover`). A restart folds the lines into the latest state of each
//! device and puts it in force over whatever snapshot it finds: a snapshot, old or new, holds
//! the control state (estimators, sequence), never the configuration.
//!
//! Each line ends in a CRC-32 of the rest (`"crc"`, the last field): a line torn by a crash or
//! a full disk, or garbage on a bad sector, fails it and is dropped on replay, never read as
//! half a record. When a file is rotated, the new one starts with a *checkpoint*: one line per
//! device with its latest state, so that the current file and the one before it always hold
//! every device's latest state, however long ago it changed.

use std::collections::BTreeMap;
use std::io;

use base64::Engine as _;
use protocol::pb;

use crate::lease::Version;

/// A device's configuration in force after a change, as the journal keeps it.
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    /// Laws, output maps, envelope and reference in force.
    pub config: pb::DeviceConfig,
    /// The version of the change that left it ([`crate::lease::Version`]).
    pub version: Version,
    /// The configuration the service's file gave the device when this state was made: what
    /// an edited file is compared with at the next start.
    pub file: pb::DeviceConfig,
}

/// One line of the audit file: a decision (accepted or refused) and, for an accepted change,
/// the state it left.
#[derive(Debug, Clone, PartialEq)]
pub struct Record {
    pub entry: pb::AuditEntry,
    pub state: Option<State>,
}

/// What one line of the file is.
#[derive(Debug, Clone, PartialEq)]
pub enum Line {
    /// A decision.
    Record(Record),
    /// A device's latest state, written at the head of a new file by a rotation.
    Checkpoint(String, State),
    /// Anything else: a torn or corrupted line (its CRC fails or it does not parse).
    Torn,
}

/// What the journal is given to write: a decision, or a state taken from elsewhere (a
/// fleet partner's, held or handed over), which has no decision of this member's.
#[derive(Debug, Clone, PartialEq)]
pub enum Write {
    Record(Record),
    Checkpoint(String, State),
}

impl Write {
    /// Its line (without the newline), as the `i`th of a batch of `k`.
    fn line(&self, i: usize, k: usize) -> String {
        let part = (k > 1).then_some((i, k));
        match self {
            Self::Record(r) => record_line(r, part),
            Self::Checkpoint(dev, s) => checkpoint_part(dev, s, part),
        }
    }

    /// The device and state it leaves, if any.
    fn state(&self) -> Option<(&str, &State)> {
        match self {
            Self::Record(r) => r.state.as_ref().map(|s| (r.entry.device_id.as_str(), s)),
            Self::Checkpoint(dev, s) => Some((dev, s)),
        }
    }
}

fn b64(bytes: &[u8]) -> String {
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

fn unb64(s: &str) -> Option<Vec<u8>> {
    base64::engine::general_purpose::STANDARD.decode(s).ok()
}

fn state_json(s: &State) -> serde_json::Value {
    let v = s.version;
    serde_json::json!({
        "config": b64(&protocol::encode(&s.config)),
        "version": [v.run, v.epoch, v.n],
        "file": b64(&protocol::encode(&s.file)),
    })
}

fn state_from_json(v: &serde_json::Value) -> Option<State> {
    let config = |k: &str| -> Option<pb::DeviceConfig> {
        protocol::decode(&unb64(v.get(k)?.as_str()?)?).ok()
    };
    let version = v.get("version")?.as_array()?;
    let n = |i: usize| version.get(i).and_then(serde_json::Value::as_u64);
    Some(State {
        config: config("config")?,
        version: Version {
            run: n(0)?,
            epoch: n(1)?,
            n: n(2)?,
        },
        file: config("file")?,
    })
}

/// The CRC field's opening, as the last field of a line.
const CRC_FIELD: &str = ",\"crc\":\"";

/// `json` (an object) with a last field `"crc"`: the CRC-32 of `json` as it was.
fn sealed(json: &serde_json::Value) -> String {
    let text = json.to_string();
    let crc = crc32fast::hash(text.as_bytes());
    let open = &text[..text.len() - 1];
    format!("{open}{CRC_FIELD}{crc:08x}\"}}")
}

/// The JSON a sealed line carries, if its CRC holds; `Err(())` for a torn or altered one,
/// `Ok(None)` for a line written before lines had one (an audit entry of an older build).
fn opened(line: &str) -> Result<Option<serde_json::Value>, ()> {
    let Some(at) = line.rfind(CRC_FIELD) else {
        return Ok(None);
    };
    let rest = &line[at + CRC_FIELD.len()..];
    let hex = rest.strip_suffix("\"}").ok_or(())?;
    let want = u32::from_str_radix(hex, 16).map_err(|_| ())?;
    if hex.len() != 8 {
        return Err(());
    }
    let text = format!("{}}}", &line[..at]);
    if crc32fast::hash(text.as_bytes()) != want {
        return Err(());
    }
    serde_json::from_str(&text).map(Some).map_err(|_| ())
}

/// One record as a line of the file (without its newline).
pub fn to_line(r: &Record) -> String {
    record_line(r, None)
}

/// A line of a batch of `part.1` lines, the `part.0`th (from 0): `"batch": [i, k]`. A batch
/// counts only whole (module documentation of [`Replayed`]); a batch of one line has none.
fn record_line(r: &Record, part: Option<(usize, usize)>) -> String {
    let mut v = crate::audit::entry_json(&r.entry);
    if let Some(s) = &r.state {
        v["state"] = state_json(s);
    }
    if let Some((i, k)) = part {
        v["batch"] = serde_json::json!([i, k]);
    }
    sealed(&v)
}

/// A checkpoint line: `device`'s latest state.
pub fn checkpoint_line(device: &str, s: &State) -> String {
    checkpoint_part(device, s, None)
}

fn checkpoint_part(device: &str, s: &State, part: Option<(usize, usize)>) -> String {
    let mut v = serde_json::json!({ "checkpoint": device, "state": state_json(s) });
    if let Some((i, k)) = part {
        v["batch"] = serde_json::json!([i, k]);
    }
    sealed(&v)
}

/// What a line of the file is. Never panics on any input.
pub fn read_line(line: &str) -> Line {
    read_part(line).0
}

/// What a line is, and its place in its batch (`[i, k]`) if it names one.
fn read_part(line: &str) -> (Line, Option<(u64, u64)>) {
    let v = match opened(line) {
        Ok(Some(v)) => v,
        // An older build's line: an entry without a state, if it parses at all.
        Ok(None) => {
            let line = match crate::audit::from_line(line) {
                Some(entry) => Line::Record(Record { entry, state: None }),
                None => Line::Torn,
            };
            return (line, None);
        }
        Err(()) => return (Line::Torn, None),
    };
    let part = v.get("batch").and_then(|b| {
        let b = b.as_array()?;
        Some((b.first()?.as_u64()?, b.get(1)?.as_u64()?))
    });
    if let Some(dev) = v.get("checkpoint").and_then(|d| d.as_str()) {
        let line = match v.get("state").and_then(state_from_json) {
            Some(s) => Line::Checkpoint(dev.to_string(), s),
            None => Line::Torn,
        };
        return (line, part);
    }
    let Some(entry) = crate::audit::entry_from_json(&v) else {
        return (Line::Torn, None);
    };
    let state = match v.get("state") {
        None => None,
        Some(s) => match state_from_json(s) {
            Some(s) => Some(s),
            None => return (Line::Torn, None),
        },
    };
    (Line::Record(Record { entry, state }), part)
}

/// A file read back: the decisions in it, the latest state of each device, and how many
/// lines were dropped as torn.
///
/// A batch of several lines (`"batch": [i, k]` in each) counts only whole: its `k` lines in
/// order, each intact. A write that failed or was cut by a crash part way through a batch
/// may have left some of its lines whole on the disk; their changes were refused (or never
/// acknowledged), so none of the batch may come back as accepted.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Replayed {
    /// The decisions, oldest first.
    pub entries: Vec<pb::AuditEntry>,
    /// Each device's latest state, by id.
    pub states: BTreeMap<String, State>,
    /// Lines dropped: torn or corrupted, or of a batch that is not whole.
    pub torn: usize,
    /// The last file folded does not end with a newline (a line torn at its end): the next
    /// line written must start a line of its own.
    pub ragged: bool,
}

impl Replayed {
    /// Fold one file's bytes, after the files already folded (the file before it first).
    /// Invalid UTF-8 in a line makes that line torn, not the file.
    pub fn fold_bytes(&mut self, bytes: &[u8]) {
        let mut batch: Vec<Line> = Vec::new();
        for l in bytes.split(|&b| b == b'\n') {
            if l.is_empty() {
                continue;
            }
            let (line, part) = match std::str::from_utf8(l) {
                Ok(s) => read_part(s),
                Err(_) => (Line::Torn, None),
            };
            match part {
                Some((i, k)) if i as usize == batch.len() && i < k => {
                    batch.push(line);
                    if batch.len() as u64 == k {
                        batch.drain(..).for_each(|l| self.take(l));
                    }
                }
                Some((i, k)) => {
                    // Out of order: what was gathered is not a whole batch; this line may
                    // start one.
                    self.torn += batch.len();
                    batch.clear();
                    if i == 0 && k > 0 {
                        batch.push(line);
                        if k == 1 {
                            batch.drain(..).for_each(|l| self.take(l));
                        }
                    } else {
                        self.torn += 1;
                    }
                }
                None => {
                    self.torn += batch.len();
                    batch.clear();
                    self.take(line);
                }
            }
        }
        self.torn += batch.len();
        self.ragged = bytes.last().is_some_and(|&b| b != b'\n');
    }

    fn take(&mut self, line: Line) {
        match line {
            Line::Record(r) => {
                if let Some(s) = r.state {
                    self.states.insert(r.entry.device_id.clone(), s);
                }
                self.entries.push(r.entry);
            }
            Line::Checkpoint(dev, s) => {
                self.states.insert(dev, s);
            }
            Line::Torn => self.torn += 1,
        }
    }
}

/// Why a batch is not durable.
#[derive(Debug)]
pub enum Failure {
    /// It is not on the disk (the write failed and what it appended was cut off again, or
    /// it was never appended): its changes are refused, and no start brings them back.
    Refused(io::Error),
    /// The write failed and the cut failed too: the batch may be on the disk, in part or
    /// whole, and a start may find it whole (Linux may also have dropped it: a failed
    /// `fdatasync` leaves the data's fate to the kernel). Its changes are neither
    /// acknowledged nor refused: they are not in force now, and may be after a restart.
    InDoubt(io::Error),
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Refused(e) => write!(f, "{e}"),
            Self::InDoubt(e) => write!(f, "{e}, and what was written could not be cut off"),
        }
    }
}

/// Where the file lives, as [`Store`] needs it: the current file (appended to), and a way
/// to start a new one. `service::trail::FsDisk` is the real one; the simulation's loses
/// what was not synced when it crashes, and fails or tears writes when told to.
pub trait Disk {
    /// The current file's length (bytes).
    fn size(&mut self) -> io::Result<u64>;
    /// Append `bytes` to the current file; it may have written a part when it fails.
    fn append(&mut self, bytes: &[u8]) -> io::Result<()>;
    /// Make what was appended durable (`fdatasync`).
    fn sync(&mut self) -> io::Result<()>;
    /// Cut the current file back to `len` bytes, durably.
    fn truncate(&mut self, len: u64) -> io::Result<()>;
    /// Make `head` the whole of a new current file, durably, and keep the old one as the
    /// file before it: never a moment without both the old file and a complete new one.
    fn rotate(&mut self, head: &[u8]) -> io::Result<()>;
}

/// The journal's writer: it appends batches of records to a [`Disk`], each batch all or
/// nothing, and keeps every device's latest state for the checkpoint that starts each new
/// file.
#[derive(Debug)]
pub struct Store<D> {
    disk: D,
    /// Size at which the current file is rotated before the next batch.
    rotate_bytes: u64,
    /// Every device's latest state, as written.
    latest: BTreeMap<String, State>,
    /// A failed write may have left a part of a line that could not be cut off: the next
    /// batch starts on a line of its own.
    ragged: bool,
}

impl<D: Disk> Store<D> {
    /// A store on `disk`, whose files were read back as `replayed` (every device's latest
    /// state, and whether the current file ends in a torn line).
    pub fn new(disk: D, rotate_bytes: u64, replayed: &Replayed) -> Self {
        Self {
            disk,
            rotate_bytes,
            latest: replayed.states.clone(),
            ragged: replayed.ragged,
        }
    }

    /// The disk, for the simulation to crash and read.
    pub fn disk(&mut self) -> &mut D {
        &mut self.disk
    }

    /// Every device's latest state written.
    pub fn latest(&self) -> &BTreeMap<String, State> {
        &self.latest
    }

    /// Append `records` and make them durable, all or none: on an error, whatever was
    /// appended is cut off again, and no state is taken as written. If the cut fails too,
    /// the batch may be on the disk in part or whole ([`Failure::InDoubt`]), and the next
    /// batch starts a new line, so a torn part never joins a good record.
    pub fn write(&mut self, records: &[&Write]) -> Result<(), Failure> {
        if records.is_empty() {
            return Ok(());
        }
        let start = self.disk.size().map_err(Failure::Refused)?;
        if start >= self.rotate_bytes {
            self.rotate().map_err(Failure::Refused)?;
            let start = self.disk.size().map_err(Failure::Refused)?;
            return self.write_at(start, records);
        }
        self.write_at(start, records)
    }

    fn write_at(&mut self, start: u64, records: &[&Write]) -> Result<(), Failure> {
        let mut bytes = Vec::new();
        if self.ragged {
            bytes.push(b'\n');
        }
        for (i, r) in records.iter().enumerate() {
            bytes.extend_from_slice(r.line(i, records.len()).as_bytes());
            bytes.push(b'\n');
        }
        let written = self.disk.append(&bytes).and_then(|()| self.disk.sync());
        if let Err(e) = written {
            // What was appended must not stay: a record that failed is refused, and must
            // not come back as accepted at the next start. Cut back, the file ends as it
            // did (a torn line before it still wants a newline).
            return Err(match self.disk.truncate(start) {
                Ok(()) => Failure::Refused(e),
                Err(_) => {
                    self.ragged = true;
                    Failure::InDoubt(e)
                }
            });
        }
        self.ragged = false;
        for r in records {
            if let Some((dev, s)) = r.state() {
                self.latest.insert(dev.to_string(), s.clone());
            }
        }
        Ok(())
    }

    /// Start a new file with every device's latest state.
    fn rotate(&mut self) -> io::Result<()> {
        let mut head = Vec::new();
        for (dev, s) in &self.latest {
            head.extend_from_slice(checkpoint_line(dev, s).as_bytes());
            head.push(b'\n');
        }
        self.disk.rotate(&head)?;
        self.ragged = false;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(kp: f64) -> pb::DeviceConfig {
        pb::DeviceConfig {
            version: protocol::PROTOCOL_VERSION,
            device_id: "aero-1".into(),
            channels: vec![pb::ChannelConfig {
                law: Some(pb::channel_config::Law::Pid(pb::Pid {
                    kp,
                    ..Default::default()
                })),
                output: None,
            }],
            reference: None,
            envelope: None,
        }
    }

    pub(crate) fn record(dev: &str, n: u64, kp: Option<f64>) -> Write {
        Write::Record(Record {
            entry: pb::AuditEntry {
                unix_ns: n,
                member: "c-1".into(),
                n,
                device_id: dev.into(),
                operator: "alice".into(),
                action: "configuration".into(),
                accepted: kp.is_some(),
                ..Default::default()
            },
            state: kp.map(|kp| State {
                config: config(kp),
                version: Version {
                    run: 1,
                    epoch: 2,
                    n,
                },
                file: config(9.0),
            }),
        })
    }

    fn state(w: &Write) -> State {
        w.state().unwrap().1.clone()
    }

    #[test]
    fn lines_read_back_and_every_torn_line_is_told() {
        let Write::Record(r) = record("aero-1", 7, Some(12.0)) else {
            unreachable!()
        };
        let line = to_line(&r);
        assert_eq!(read_line(&line), Line::Record(r.clone()));
        // The audit file's readers see the entry as before.
        assert_eq!(crate::audit::from_line(&line), Some(r.entry.clone()));
        // Every cut of the line, and every single flipped byte, is torn.
        for k in 0..line.len() {
            assert_eq!(read_line(&line[..k]), Line::Torn, "cut at {k}");
        }
        let bytes = line.as_bytes();
        for k in (0..bytes.len()).step_by(7) {
            let mut b = bytes.to_vec();
            b[k] ^= 0x01;
            if let Ok(s) = std::str::from_utf8(&b) {
                assert_eq!(read_line(s), Line::Torn, "byte {k} flipped");
            }
        }
        let c = checkpoint_line("aero-1", r.state.as_ref().unwrap());
        assert_eq!(
            read_line(&c),
            Line::Checkpoint("aero-1".into(), r.state.clone().unwrap())
        );
        // An older build's line: the entry, no state.
        let old = crate::audit::to_line(&r.entry);
        assert_eq!(
            read_line(&old),
            Line::Record(Record {
                entry: r.entry,
                state: None
            })
        );
    }

    /// A disk in memory: the current file, the one before it, and a failure to inject.
    #[derive(Default)]
    struct Mem {
        now: Vec<u8>,
        before: Vec<u8>,
        /// The next append writes this many bytes, then fails.
        tear: Option<usize>,
        fail_truncate: bool,
    }

    impl Disk for Mem {
        fn size(&mut self) -> io::Result<u64> {
            Ok(self.now.len() as u64)
        }
        fn append(&mut self, bytes: &[u8]) -> io::Result<()> {
            match self.tear.take() {
                Some(k) => {
                    self.now.extend_from_slice(&bytes[..k.min(bytes.len())]);
                    Err(io::Error::other("no space left"))
                }
                None => {
                    self.now.extend_from_slice(bytes);
                    Ok(())
                }
            }
        }
        fn sync(&mut self) -> io::Result<()> {
            Ok(())
        }
        fn truncate(&mut self, len: u64) -> io::Result<()> {
            if self.fail_truncate {
                return Err(io::Error::other("read-only"));
            }
            self.now.truncate(len as usize);
            Ok(())
        }
        fn rotate(&mut self, head: &[u8]) -> io::Result<()> {
            self.before = std::mem::replace(&mut self.now, head.to_vec());
            Ok(())
        }
    }

    fn replay(m: &Mem) -> Replayed {
        let mut r = Replayed::default();
        r.fold_bytes(&m.before);
        r.fold_bytes(&m.now);
        r
    }

    #[test]
    fn a_failed_batch_leaves_nothing_and_the_next_one_reads_back_whole() {
        let mut s = Store::new(Mem::default(), 1 << 20, &Replayed::default());
        let (a, b, c) = (
            record("d1", 1, Some(1.0)),
            record("d1", 2, Some(2.0)),
            record("d2", 3, None),
        );
        s.write(&[&a]).unwrap();
        s.disk().tear = Some(40);
        assert!(matches!(s.write(&[&b, &c]), Err(Failure::Refused(_))));
        let r = replay(&s.disk);
        assert_eq!(r.entries.len(), 1, "the torn batch was cut off");
        assert_eq!(r.states["d1"], state(&a));
        // A cut that fails too: the part stays, but the next batch starts its own line.
        s.disk().tear = Some(40);
        s.disk().fail_truncate = true;
        assert!(matches!(s.write(&[&b]), Err(Failure::InDoubt(_))));
        s.write(&[&c, &b]).unwrap();
        let r = replay(&s.disk);
        assert_eq!(r.torn, 1);
        let ns: Vec<u64> = r.entries.iter().map(|e| e.n).collect();
        assert_eq!(ns, [1, 3, 2]);
        assert_eq!(r.states["d1"], state(&b));
    }

    /// A batch cut after whole lines of it, which could not be cut off: none of its lines
    /// counts, not even the whole ones (their changes were not acknowledged).
    #[test]
    fn a_batch_counts_only_whole() {
        let mut s = Store::new(Mem::default(), 1 << 20, &Replayed::default());
        let batch = [
            record("d1", 1, Some(1.0)),
            record("d2", 2, Some(2.0)),
            record("d3", 3, Some(3.0)),
        ];
        let refs: Vec<&Write> = batch.iter().collect();
        let one = batch[0].line(0, 3).len() + 1;
        let len: usize = (0..3).map(|i| batch[i].line(i, 3).len() + 1).sum();
        // (A cut after the last line's last character leaves the batch whole: that is why
        // such a failure is in doubt, not refused.)
        for cut in [one, one + 10, len - 20] {
            let mut m = Mem {
                tear: Some(cut),
                fail_truncate: true,
                ..Mem::default()
            };
            let mut st = Store::new(std::mem::take(&mut m), 1 << 20, &Replayed::default());
            assert!(matches!(st.write(&refs), Err(Failure::InDoubt(_))));
            let r = replay(&st.disk);
            assert!(
                r.entries.is_empty() && r.states.is_empty(),
                "cut at {cut}: {r:?}"
            );
            assert!(r.torn >= 1);
        }
        // Whole, it counts whole.
        s.write(&refs).unwrap();
        let r = replay(&s.disk);
        assert_eq!(r.entries.len(), 3);
        assert_eq!(r.states.len(), 3);
    }

    #[test]
    fn a_rotation_carries_every_latest_state_into_the_new_file() {
        let mut s = Store::new(Mem::default(), 600, &Replayed::default());
        let first = record("quiet", 1, Some(3.0));
        s.write(&[&first]).unwrap();
        for n in 2..40 {
            s.write(&[&record("busy", n, Some(n as f64))]).unwrap();
        }
        // Many rotations later, the device changed first is still in the two files kept.
        let r = replay(&s.disk);
        assert_eq!(r.states["quiet"], state(&first));
        assert_eq!(r.states["busy"].config, config(39.0));
        assert!(r.entries.len() < 39, "older files were dropped");
    }
}
