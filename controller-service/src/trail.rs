//! The audit file on the real disk: one writer thread per process takes records from the
//! workers, writes each batch of them all or nothing through [`crate::journal::Store`]
//! (appended, `fdatasync`ed, rotated with a checkpoint), and tells each worker whether its
//! records are durable. The workers never touch the disk: they reserve a record's place in
//! the writer's bounded queue before they decide a change, and put the change in force
//! only once its record is written; a record that cannot be written refuses its change
//! (IEC 62443-4-2 CR 2.10's choice for a failing audit store: stop the audited action, not
//! the control loop).

use std::fs::{File, OpenOptions};
use std::io::{self, Write as _};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use protocol::pb;
use tokio::sync::mpsc;

use crate::config::AuditSpec;
use crate::journal::{Disk, Record, Replayed, State, Store, Write};

/// Records waiting for the writer at most; beyond, changes are refused until it caught up.
pub const WAITING: usize = 4096;

/// Records the writer makes durable with one `fdatasync`, at most.
const BATCH: usize = 256;

/// The writer's word on a record: durable, or why not.
#[derive(Debug)]
pub struct Written {
    /// The number the worker gave the record.
    pub id: u64,
    pub result: Result<(), NotWritten>,
}

/// Why a record is not durable, and whether it may be on the disk all the same
/// ([`crate::journal::Failure`]).
#[derive(Debug, Clone)]
pub struct NotWritten {
    pub why: String,
    /// The write failed and could not be undone: a restart may find the record.
    pub in_doubt: bool,
}

/// What the writer is handed: a record, and who waits for its word (its number and where
/// to send it).
pub type Pending = (Write, Option<(u64, mpsc::Sender<Written>)>);

/// What the writer did, for the status and the metrics.
#[derive(Debug, Default)]
pub struct TrailStats {
    /// Records written and synced.
    pub written: AtomicU64,
    /// Records that could not be written (the error is logged): their changes were refused.
    pub errors: AtomicU64,
}

/// A handle on the process's audit file (cheap to clone: one per worker).
#[derive(Clone)]
pub struct AuditTrail {
    tx: mpsc::Sender<Pending>,
    /// The writer's counts.
    pub stats: Arc<TrailStats>,
    path: PathBuf,
}

impl std::fmt::Debug for AuditTrail {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "AuditTrail({})", self.path.display())
    }
}

impl AuditTrail {
    /// Open (or create) the file and start its writer. Returns what the newest rotated file
    /// and the current one hold ([`Replayed`]: the decisions, oldest first, and every
    /// device's latest state), for the registries to put back in force before serving.
    pub fn open(spec: &AuditSpec) -> io::Result<(Self, Replayed)> {
        let mut replayed = Replayed::default();
        for p in [numbered(&spec.path, 1), spec.path.clone()] {
            match std::fs::read(&p) {
                Ok(bytes) => replayed.fold_bytes(&bytes),
                Err(e) if e.kind() == io::ErrorKind::NotFound => {}
                Err(e) => return Err(io::Error::new(e.kind(), format!("{}: {e}", p.display()))),
            }
        }
        let disk = FsDisk::open(spec)?;
        let store = Store::new(disk, spec.rotate_bytes, &replayed);
        let (tx, rx) = mpsc::channel(WAITING);
        let stats = Arc::new(TrailStats::default());
        let writer = Writer {
            store,
            stats: stats.clone(),
            path: spec.path.clone(),
        };
        std::thread::Builder::new()
            .name("mfc-audit".into())
            .spawn(move || writer.run(rx))?;
        let trail = Self {
            tx,
            stats,
            path: spec.path.clone(),
        };
        Ok((trail, replayed))
    }

    /// A place in the writer's queue, taken before the change it will record is decided;
    /// `None` if the queue is full.
    pub fn reserve(&self) -> Option<mpsc::OwnedPermit<Pending>> {
        self.tx.clone().try_reserve_owned().ok()
    }

    /// Hand over entries a partner held (no reservation: they were decided elsewhere; one
    /// that does not fit is counted as an error).
    pub fn append(&self, entry: pb::AuditEntry) {
        let record = Write::Record(Record { entry, state: None });
        if self.tx.try_send((record, None)).is_err() {
            self.stats.errors.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Keep a device's state taken from a partner (held for it, or handed over), so that
    /// this member puts it back in force after a restart too; nothing waits for it (one
    /// that does not fit is counted as an error).
    pub fn keep(&self, device: &str, state: State) {
        if self
            .tx
            .try_send((Write::Checkpoint(device.into(), state), None))
            .is_err()
        {
            self.stats.errors.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Hand the writer a record whatever its queue holds, waiting for room (a withdrawal,
    /// which must follow the record it corrects).
    pub async fn send(&self, pending: Pending) -> Result<(), String> {
        self.tx
            .send(pending)
            .await
            .map_err(|_| "the audit file's writer stopped".to_string())
    }

    /// Write `records` and wait until they are durable (at a start, before anything is
    /// served); the first error if any is not.
    pub async fn write_all(&self, records: Vec<Write>) -> Result<(), String> {
        let n = records.len();
        let (tx, mut rx) = mpsc::channel(n.max(1));
        for (i, r) in records.into_iter().enumerate() {
            self.tx
                .send((r, Some((i as u64, tx.clone()))))
                .await
                .map_err(|_| "the audit file's writer stopped".to_string())?;
        }
        drop(tx);
        let mut first = Ok(());
        for _ in 0..n {
            match rx.recv().await {
                Some(w) => first = first.and(w.result.map_err(|e| e.why)),
                None => return Err("the audit file's writer stopped".into()),
            }
        }
        first
    }

    /// The file written to.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

struct Writer {
    store: Store<FsDisk>,
    stats: Arc<TrailStats>,
    path: PathBuf,
}

impl Writer {
    /// Take what waits, up to [`BATCH`] records, write it with one sync, tell each waiter.
    fn run(mut self, mut rx: mpsc::Receiver<Pending>) {
        while let Some(first) = rx.blocking_recv() {
            let mut batch = vec![first];
            while batch.len() < BATCH {
                match rx.try_recv() {
                    Ok(p) => batch.push(p),
                    Err(_) => break,
                }
            }
            let records: Vec<&Write> = batch.iter().map(|(r, _)| r).collect();
            let result = self.store.write(&records).map_err(|e| NotWritten {
                why: e.to_string(),
                in_doubt: matches!(e, crate::journal::Failure::InDoubt(_)),
            });
            let n = batch.len() as u64;
            match &result {
                Ok(()) => self.stats.written.fetch_add(n, Ordering::Relaxed),
                Err(e) if e.in_doubt => {
                    tracing::error!(path = %self.path.display(), records = n, "audit records not written, and what was written could not be cut off: their changes are not in force, and a restart may put them in force: {}", e.why);
                    self.stats.errors.fetch_add(n, Ordering::Relaxed)
                }
                Err(e) => {
                    tracing::error!(path = %self.path.display(), records = n, "audit records not written, their changes are refused: {}", e.why);
                    self.stats.errors.fetch_add(n, Ordering::Relaxed)
                }
            };
            for (_, waiter) in batch {
                if let Some((id, tx)) = waiter {
                    let _ = tx.blocking_send(Written {
                        id,
                        result: result.clone(),
                    });
                }
            }
        }
    }
}

/// `path.{k}`: a rotated file.
fn numbered(path: &Path, k: u32) -> PathBuf {
    let mut p = path.as_os_str().to_owned();
    p.push(format!(".{k}"));
    PathBuf::from(p)
}

/// The audit file on the file system, as [`Store`] writes it.
struct FsDisk {
    path: PathBuf,
    keep: u32,
    /// Open for appending; reopened after an error.
    file: Option<File>,
}

impl FsDisk {
    fn open(spec: &AuditSpec) -> io::Result<Self> {
        let dir = spec.path.parent().filter(|d| !d.as_os_str().is_empty());
        if let Some(dir) = dir {
            std::fs::create_dir_all(dir)?;
        }
        let existed = spec.path.exists();
        let mut disk = Self {
            path: spec.path.clone(),
            keep: spec.keep,
            file: None,
        };
        disk.file()?;
        if !existed {
            sync_dir(&spec.path)?;
        }
        Ok(disk)
    }

    fn file(&mut self) -> io::Result<&mut File> {
        if self.file.is_none() {
            let f = OpenOptions::new()
                .create(true)
                .append(true)
                .open(&self.path)?;
            self.file = Some(f);
        }
        Ok(self.file.as_mut().expect("opened above"))
    }

    /// Forget the file after an error: the next call opens it again.
    fn failed<T>(&mut self, r: io::Result<T>) -> io::Result<T> {
        if r.is_err() {
            self.file = None;
        }
        r
    }
}

fn sync_dir(path: &Path) -> io::Result<()> {
    match path.parent().filter(|d| !d.as_os_str().is_empty()) {
        Some(dir) => File::open(dir)?.sync_all(),
        None => File::open(".")?.sync_all(),
    }
}

impl Disk for FsDisk {
    fn size(&mut self) -> io::Result<u64> {
        let r = self.file().and_then(|f| f.metadata()).map(|m| m.len());
        self.failed(r)
    }

    fn append(&mut self, bytes: &[u8]) -> io::Result<()> {
        let r = self.file().and_then(|f| f.write_all(bytes));
        self.failed(r)
    }

    fn sync(&mut self) -> io::Result<()> {
        let r = self.file().and_then(|f| f.sync_data());
        self.failed(r)
    }

    fn truncate(&mut self, len: u64) -> io::Result<()> {
        let r = self.file().and_then(|f| {
            f.set_len(len)?;
            f.sync_data()
        });
        self.failed(r)
    }

    /// The new file is written and synced beside the current one first; then the current
    /// one becomes `path.1` (each older `path.k` moving to `path.{k+1}`, `path.{keep}`
    /// dropped) and the new one takes its name, and the directory is synced: a crash at
    /// any point leaves the current file or the new one, whole, beside `path.1`.
    fn rotate(&mut self, head: &[u8]) -> io::Result<()> {
        let fresh = numbered(&self.path, 0);
        let r = (|| {
            let mut f = File::create(&fresh)?;
            f.write_all(head)?;
            f.sync_all()?;
            let _ = std::fs::remove_file(numbered(&self.path, self.keep));
            for k in (1..self.keep).rev() {
                let from = numbered(&self.path, k);
                if from.exists() {
                    std::fs::rename(&from, numbered(&self.path, k + 1))?;
                }
            }
            std::fs::rename(&self.path, numbered(&self.path, 1))?;
            std::fs::rename(&fresh, &self.path)?;
            sync_dir(&self.path)
        })();
        self.file = None;
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(n: u64) -> Write {
        Write::Record(Record {
            entry: pb::AuditEntry {
                unix_ns: n,
                member: "c-1".into(),
                n,
                device_id: "aero-1".into(),
                operator: "alice".into(),
                action: "configuration".into(),
                accepted: true,
                ..Default::default()
            },
            state: None,
        })
    }

    #[test]
    fn entries_are_appended_read_back_and_rotated() {
        let dir = tempfile::tempdir().unwrap();
        let spec = AuditSpec {
            path: dir.path().join("log/audit.jsonl"),
            rotate_bytes: 4096,
            keep: 2,
        };
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        rt.block_on(async {
            let (trail, earlier) = AuditTrail::open(&spec).unwrap();
            assert!(earlier.entries.is_empty());
            // Ten at a time: the file is rotated between batches, never inside one.
            for k in 0..20 {
                let batch = (10 * k..10 * k + 10).map(record).collect();
                trail.write_all(batch).await.unwrap();
            }
            assert_eq!(trail.stats.written.load(Ordering::Relaxed), 200);
        });
        // Three files at most: the current one and two rotated; every line an entry, the
        // newest last, none lost within what is kept.
        let read = |p: &Path| {
            let mut r = Replayed::default();
            r.fold_bytes(&std::fs::read(p).unwrap_or_default());
            assert_eq!(r.torn, 0);
            r.entries
        };
        let current = read(&spec.path);
        let one = read(&dir.path().join("log/audit.jsonl.1"));
        let two = read(&dir.path().join("log/audit.jsonl.2"));
        assert!(!dir.path().join("log/audit.jsonl.3").exists());
        assert!(!dir.path().join("log/audit.jsonl.0").exists());
        assert_eq!(current.last().unwrap().n, 199);
        let all: Vec<u64> = two
            .iter()
            .chain(&one)
            .chain(&current)
            .map(|e| e.n)
            .collect();
        let first = all[0];
        assert_eq!(all, (first..200).collect::<Vec<_>>());
        assert!(first > 0, "rotation dropped the oldest file");
        let (_again, earlier) = rt.block_on(async { AuditTrail::open(&spec).unwrap() });
        let newest: Vec<_> = one.iter().chain(&current).cloned().collect();
        assert_eq!(earlier.entries, newest);
    }
}
