//! Zenoh sessions for the controller service and the plant agent.
//!
//! One place decides how a session is configured (a json5 file, then the usual flags on
//! top, as zenoh's own tools do) and how control traffic is published: samples and commands
//! go out `express` (no batching), at `RealTime` priority, with `Drop` congestion control:
//! in a control loop a stale message is worse than a lost one, and a blocked publisher must
//! never stall the loop.
//!
//! [`ops`] holds what an operator asks of the controllers (status, configuration, gain and
//! reference changes), shared by `mfcctl` and the browser console.

pub mod https;
pub mod ops;

use std::path::PathBuf;

use zenoh::qos::{CongestionControl, Priority};
use zenoh::{Config, Session};

/// Why a session could not be configured or opened.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// The json5 file or a flag was refused by zenoh.
    #[error("zenoh configuration: {0}")]
    Config(String),
    /// The session did not open.
    #[error("opening the zenoh session: {0}")]
    Open(String),
    /// A declaration (publisher, subscriber, queryable, token) failed.
    #[error("declaring {what}: {reason}")]
    Declare {
        /// What was being declared, with its key: `publisher KEY`, or `query KEY` for
        /// [`get_first`].
        what: String,
        /// zenoh's reason; for a query also `no reply: ...` (nobody answered) or
        /// `error reply: ...` (the queryable answered with an error).
        reason: String,
    },
}

/// The Zenoh flags shared by every binary of the project (`--zenoh-config`, `--mode`,
/// `--listen`, `--connect`, `--no-multicast-scouting`).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ZenohArgs {
    /// A zenoh json5 configuration file; the flags below override it.
    #[arg(long = "zenoh-config", value_name = "FILE")]
    pub zenoh_config: Option<PathBuf>,
    /// Session mode: peer, client or router.
    #[arg(long, value_parser = ["peer", "client", "router"])]
    pub mode: Option<String>,
    /// Endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable).
    #[arg(long = "listen", short = 'l', value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable).
    #[arg(long = "connect", short = 'e', value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// Disable multicast scouting (recommended with explicit endpoints).
    #[arg(long)]
    pub no_multicast_scouting: bool,
}

fn insert(config: &mut Config, key: &str, value: &str) -> Result<(), TransportError> {
    config
        .insert_json5(key, value)
        .map_err(|e| TransportError::Config(format!("{key} = {value}: {e}")))
}

/// Make `config` reassemble no message larger than `bytes` (see [`ZenohArgs::open_bounded`]).
pub fn bound_messages(config: &mut Config, bytes: usize) -> Result<(), TransportError> {
    insert(
        config,
        "transport/link/rx/max_message_size",
        &bytes.to_string(),
    )
}

fn json_list(items: &[String]) -> String {
    serde_json::to_string(items).unwrap_or_else(|_| "[]".into())
}

/// Batches zenoh may queue per link for real-time traffic (samples and commands): 16, the
/// most zenoh allows, where its default is 2.
///
/// Why: a sample or command goes out express, one batch each, and with `Drop` congestion
/// control a message that finds the queue full waits at most 1 ms, then is dropped. Two
/// batches are two messages: on a busy host, where zenoh's sending task is off the CPU for
/// a few hundred microseconds now and then, a service answering a hundred plants lost about
/// one command in a thousand that way (so did the benchmark's echo anchor). Sixteen ride
/// out such a stall; a message is still dropped, not queued for ever, when the link itself
/// cannot keep up. Set only on zenoh's own defaults: a `--zenoh-config` file decides for
/// itself (`transport.link.tx.queue.size.real_time`; `deploy/GUIDE.md`).
pub const REAL_TIME_QUEUE: usize = 16;

const REAL_TIME_QUEUE_KEY: &str = "transport/link/tx/queue/size/real_time";

impl ZenohArgs {
    /// A peer on loopback: listen on `listen` (if any), connect to `connect`, no multicast
    /// scouting. What the tests and the demo use.
    pub fn loopback(listen: Option<String>, connect: Vec<String>) -> Self {
        Self {
            zenoh_config: None,
            mode: Some("peer".into()),
            listen: listen.into_iter().collect(),
            connect,
            no_multicast_scouting: true,
        }
    }

    /// Build the zenoh configuration: the file (or zenoh's defaults), then the flags.
    /// The name the zenoh configuration file gives its client (`metadata.name`, which
    /// `mfc-deploy` writes: the certificate's common name), if any.
    pub fn config_name(&self) -> Option<String> {
        let path = self.zenoh_config.as_ref()?;
        let config = Config::from_file(path).ok()?;
        let v: serde_json::Value = serde_json::from_str(&config.get_json("metadata").ok()?).ok()?;
        v.get("name")?.as_str().map(str::to_string)
    }

    pub fn to_config(&self) -> Result<Config, TransportError> {
        let mut config = match &self.zenoh_config {
            Some(path) => Config::from_file(path)
                .map_err(|e| TransportError::Config(format!("{}: {e}", path.display())))?,
            None => {
                let mut c = Config::default();
                insert(&mut c, REAL_TIME_QUEUE_KEY, &REAL_TIME_QUEUE.to_string())?;
                c
            }
        };
        if let Some(mode) = &self.mode {
            insert(&mut config, "mode", &format!("{mode:?}"))?;
        }
        if !self.listen.is_empty() {
            insert(&mut config, "listen/endpoints", &json_list(&self.listen))?;
        }
        if !self.connect.is_empty() {
            insert(&mut config, "connect/endpoints", &json_list(&self.connect))?;
        }
        if self.no_multicast_scouting {
            insert(&mut config, "scouting/multicast/enabled", "false")?;
        }
        Ok(config)
    }

    /// Open a session with this configuration.
    pub async fn open(&self) -> Result<Session, TransportError> {
        open_logged(self.to_config()?).await
    }

    /// Open a session that reassembles no message larger than `max_message_size` bytes.
    ///
    /// Zenoh reassembles a fragmented message whole before any callback sees it, up to
    /// `transport/link/rx/max_message_size` (1 GiB by default), so a size check in a
    /// callback comes too late to bound memory: one peer could make a service hold a
    /// gigabyte per link. Larger messages are dropped by zenoh's reassembly (it logs them
    /// at trace level; nothing reaches the application to count). A service passes a
    /// limit well above what it reads, so that what it refuses by size is still counted.
    pub async fn open_bounded(&self, max_message_size: usize) -> Result<Session, TransportError> {
        let mut config = self.to_config()?;
        bound_messages(&mut config, max_message_size)?;
        open_logged(config).await
    }
}

/// How often a session still opening says so.
pub const OPEN_WAIT_LOG: std::time::Duration = std::time::Duration::from_secs(5);

/// Open a session; while zenoh is still trying to connect, say so every [`OPEN_WAIT_LOG`].
///
/// A client configured to retry forever (`connect.timeout_ms: -1`, what a deployment
/// wants so that start order does not matter) waits inside `zenoh::open` until its router
/// answers, and zenoh says nothing at the default log level, even when the cause is a
/// refused certificate. Silence there looked like a hang; this names the endpoints and
/// the usual causes instead.
pub async fn open_logged(config: Config) -> Result<Session, TransportError> {
    let endpoints = config
        .get_json("connect/endpoints")
        .unwrap_or_else(|_| "[]".into());
    // On a task of its own: zenoh's open may hold the thread that polls it while it
    // retries, and the warning below must still fire.
    let mut open = tokio::spawn(async move { zenoh::open(config).await });
    let started = std::time::Instant::now();
    loop {
        tokio::select! {
            r = &mut open => {
                return match r {
                    Ok(r) => r.map_err(|e| TransportError::Open(e.to_string())),
                    Err(e) => Err(TransportError::Open(format!("the opening task failed: {e}"))),
                };
            }
            _ = tokio::time::sleep(OPEN_WAIT_LOG) => tracing::warn!(
                "not connected after {:.0} s to {endpoints}: still trying (is the router up and reachable? \
                 do this host's certificate, key and CA match the router's? see the router's log)",
                started.elapsed().as_secs_f64()
            ),
        }
    }
}

/// The declaration of a publisher for control traffic: express, real-time priority, drop
/// on congestion.
fn control_declaration(
    session: &Session,
    key: String,
) -> zenoh::pubsub::PublisherBuilder<'_, 'static> {
    session
        .declare_publisher(key)
        .congestion_control(CongestionControl::Drop)
        .priority(Priority::RealTime)
        .express(true)
}

fn declare_error(key: &str, e: zenoh::Error) -> TransportError {
    TransportError::Declare {
        what: format!("publisher {key}"),
        reason: e.to_string(),
    }
}

/// Declare a publisher for control traffic: express, real-time priority, drop on congestion.
pub async fn control_publisher(
    session: &Session,
    key: String,
) -> Result<zenoh::pubsub::Publisher<'static>, TransportError> {
    control_declaration(session, key.clone())
        .await
        .map_err(|e| declare_error(&key, e))
}

/// [`control_publisher`] for code that runs in one of zenoh's callbacks, where zenoh's
/// blocking calls are its own way; never call it from async code.
pub fn control_publisher_now(
    session: &Session,
    key: String,
) -> Result<zenoh::pubsub::Publisher<'static>, TransportError> {
    use zenoh::Wait;
    control_declaration(session, key.clone())
        .wait()
        .map_err(|e| declare_error(&key, e))
}

/// Query `key` (with `payload`, if any) and return the payload of the first good reply:
/// the request/reply path for configuration and status (never the control path). Error
/// replies are skipped while another replier may still answer well (a service that does
/// not serve a device says so with an error, and the one that does answers); if none does,
/// the first error is returned.
pub async fn get_first(
    session: &Session,
    key: &str,
    payload: Option<Vec<u8>>,
) -> Result<Vec<u8>, TransportError> {
    let err = |reason: String| TransportError::Declare {
        what: format!("query {key}"),
        reason,
    };
    let mut get = session.get(key.to_string());
    if let Some(p) = payload {
        get = get.payload(p);
    }
    let replies = get.await.map_err(|e| err(e.to_string()))?;
    let mut first_error = None;
    while let Ok(reply) = replies.recv_async().await {
        match reply.result() {
            Ok(sample) => return Ok(sample.payload().to_bytes().into_owned()),
            Err(e) => {
                let text = e.payload().to_bytes();
                first_error.get_or_insert_with(|| {
                    err(format!("error reply: {}", String::from_utf8_lossy(&text)))
                });
            }
        }
    }
    Err(first_error.unwrap_or_else(|| err("no reply".into())))
}

/// Wait until a liveliness token on `key` exists, polling every 100 ms for at most
/// `timeout`; true if it appeared.
pub async fn wait_for_token(session: &Session, key: &str, timeout: std::time::Duration) -> bool {
    let deadline = std::time::Instant::now() + timeout;
    while std::time::Instant::now() < deadline {
        if let Ok(replies) = session.liveliness().get(key.to_string()).await {
            if replies.recv_async().await.is_ok() {
                return true;
            }
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    false
}

/// How many endpoints `config` tells the session to connect to (`connect/endpoints`,
/// either a list or one list per mode; for a per-mode object, the longest list).
pub fn connect_endpoint_count(config: &Config) -> usize {
    let Ok(json) = config.get_json("connect/endpoints") else {
        return 0;
    };
    match serde_json::from_str::<serde_json::Value>(&json) {
        Ok(serde_json::Value::Array(v)) => v.len(),
        Ok(serde_json::Value::Object(m)) => m
            .values()
            .filter_map(|v| v.as_array().map(Vec::len))
            .max()
            .unwrap_or(0),
        _ => 0,
    }
}

/// Wait until `session` has a transport to at least `expected` peers and routers, polling
/// every 20 ms for at most `timeout`; returns how many it has.
///
/// A peer's session returns from `open` once its configured connections are up *or* after
/// zenoh's scouting delay, whichever comes first; on a loaded machine it can return before
/// a connection is made, and whatever the program then looks up (who else is there) is
/// missing that peer. A program whose decisions depend on seeing everyone waits here first.
pub async fn wait_connected(
    session: &Session,
    expected: usize,
    timeout: std::time::Duration,
) -> usize {
    let deadline = std::time::Instant::now() + timeout;
    loop {
        let info = session.info();
        let n = info.peers_zid().await.count() + info.routers_zid().await.count();
        if n >= expected || std::time::Instant::now() >= deadline {
            return n;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
}

/// A free UDP port on 127.0.0.1 (as [`free_local_port`], for UDP endpoints).
pub fn free_udp_port() -> std::io::Result<u16> {
    let s = std::net::UdpSocket::bind("127.0.0.1:0")?;
    Ok(s.local_addr()?.port())
}

/// zenoh's lease when its configuration sets none (`transport/link/tx/lease`, ms).
pub const DEFAULT_LINK_LEASE: std::time::Duration = std::time::Duration::from_secs(10);

/// The lease of `config`'s links (`transport/link/tx/lease`): how long a peer or router
/// stays silent before the others drop it, with its liveliness tokens (a fleet's view of
/// its members). zenoh's default when it is unset, unreadable or 0 (a lease of 0 would make
/// every pause of a member count as a silence that hid changes).
pub fn link_lease(config: &Config) -> std::time::Duration {
    config
        .get_json("transport/link/tx/lease")
        .ok()
        .and_then(|v| v.trim().parse::<u64>().ok())
        .filter(|&ms| ms > 0)
        .map_or(DEFAULT_LINK_LEASE, std::time::Duration::from_millis)
}

/// A free TCP port on 127.0.0.1 (bind to port 0, read it, release it), for tests and demos.
/// It is released before it is returned, so another process may take it first.
pub fn free_local_port() -> std::io::Result<u16> {
    let l = std::net::TcpListener::bind("127.0.0.1:0")?;
    Ok(l.local_addr()?.port())
}

/// Resolves on SIGINT or SIGTERM: how every long-running binary of the project is asked to
/// stop (a terminal's Ctrl-C, systemd's stop). Each then ends cleanly: the service writes
/// its snapshots, the agent applies its plant's safe stop and writes its record.
///
/// The handlers are installed when this is called, not when the future is first polled:
/// call it first thing, so that a signal sent while the process is still starting (opening
/// its session, declaring) is kept and ends the run cleanly instead of killing the process
/// or being lost. Must be called inside a tokio runtime.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let int = signal(SignalKind::interrupt());
        let term = signal(SignalKind::terminate());
        async move {
            match (int, term) {
                (Ok(mut int), Ok(mut term)) => {
                    tokio::select! {
                        _ = int.recv() => {},
                        _ = term.recv() => {},
                    }
                }
                (int, term) => {
                    eprintln!(
                        "cannot listen for signals: {:?} {:?}",
                        int.err(),
                        term.err()
                    );
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
        }
    }
    #[cfg(not(unix))]
    {
        async {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_override_the_file() {
        let dir = std::env::temp_dir().join(format!("zcfg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("z.json5");
        std::fs::write(
            &file,
            "{ mode: \"client\", connect: { endpoints: [\"tcp/127.0.0.1:1\"] } }",
        )
        .unwrap();
        let args = ZenohArgs {
            zenoh_config: Some(file),
            mode: Some("peer".into()),
            listen: vec!["tcp/127.0.0.1:7999".into()],
            connect: vec![],
            no_multicast_scouting: true,
        };
        let c = args.to_config().unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"peer\"");
        assert!(c.get_json("listen/endpoints").unwrap().contains("7999"));
        assert!(c
            .get_json("connect/endpoints")
            .unwrap()
            .contains("127.0.0.1:1"));
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        // The file says nothing of the real-time queue: zenoh's default stays.
        assert_eq!(c.get_json(REAL_TIME_QUEUE_KEY).unwrap(), "2");
        // Without a file, the project's.
        let c = ZenohArgs::loopback(None, vec![]).to_config().unwrap();
        assert_eq!(
            c.get_json(REAL_TIME_QUEUE_KEY).unwrap(),
            REAL_TIME_QUEUE.to_string()
        );
        let bad = ZenohArgs {
            listen: vec!["nonsense".into()],
            ..ZenohArgs::default()
        };
        assert!(bad.to_config().is_err());
        let missing = ZenohArgs {
            zenoh_config: Some("/nonexistent.json5".into()),
            ..ZenohArgs::default()
        };
        assert!(
            matches!(missing.to_config(), Err(TransportError::Config(m)) if m.contains("nonexistent"))
        );
    }

    #[test]
    fn reads_the_links_lease() {
        let mut c = Config::default();
        assert_eq!(link_lease(&c), DEFAULT_LINK_LEASE, "zenoh's own default");
        c.insert_json5("transport/link/tx/lease", "1000").unwrap();
        assert_eq!(link_lease(&c), std::time::Duration::from_secs(1));
        c.insert_json5("transport/link/tx/lease", "0")
            .unwrap_or_default();
        assert_ne!(
            link_lease(&c),
            std::time::Duration::ZERO,
            "never a lease of 0"
        );
    }

    #[test]
    fn counts_the_endpoints_to_connect_to() {
        let two = ZenohArgs::loopback(
            None,
            vec!["tcp/127.0.0.1:1".into(), "tcp/127.0.0.1:2".into()],
        );
        assert_eq!(connect_endpoint_count(&two.to_config().unwrap()), 2);
        let none = ZenohArgs::loopback(None, vec![]);
        assert_eq!(connect_endpoint_count(&none.to_config().unwrap()), 0);
        let mut per_mode = Config::default();
        per_mode
            .insert_json5(
                "connect/endpoints",
                r#"{ router: ["tcp/127.0.0.1:1"], peer: ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2", "tcp/127.0.0.1:3"] }"#,
            )
            .unwrap();
        assert_eq!(connect_endpoint_count(&per_mode), 3);
    }

    /// A session counts the peer it connected to, and a wait for more ends at its bound.
    #[tokio::test(flavor = "multi_thread")]
    async fn waits_for_its_connections() {
        let port = free_local_port().unwrap();
        let ep = format!("tcp/127.0.0.1:{port}");
        let a = ZenohArgs::loopback(Some(ep.clone()), vec![])
            .open()
            .await
            .unwrap();
        let b = ZenohArgs::loopback(None, vec![ep]).open().await.unwrap();
        let t = std::time::Duration::from_secs(10);
        assert_eq!(wait_connected(&b, 1, t).await, 1);
        assert_eq!(wait_connected(&a, 1, t).await, 1);
        let started = std::time::Instant::now();
        let short = std::time::Duration::from_millis(200);
        assert_eq!(wait_connected(&b, 2, short).await, 1);
        assert!(started.elapsed() >= short, "the wait lasted its bound");
        let _ = b.close().await;
        let _ = a.close().await;
    }
}
