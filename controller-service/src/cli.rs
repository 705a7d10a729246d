//! The command line of the service. It lives in the library so that the binary is one
//! line and the system tests can start the very same service in a process of their own.

use std::path::{Path, PathBuf};

use crate::journal::{Record, Replayed, Write};
use crate::observe::{Observers, ServiceMetrics};
use crate::{service, Registry, ServiceConfig};
use anyhow::{Context, Result};
use clap::Parser;
use protocol::keys;
use telemetry::Recording;
use transport::ZenohArgs;

#[derive(Parser)]
#[command(
    name = "controller-service",
    version,
    about = "Model-free control as a service over Zenoh"
)]
pub struct ServiceCli {
    /// Service configuration (TOML: controller_id, devices, templates).
    #[arg(long, short)]
    pub config: PathBuf,
    /// Override the controller id of the file.
    #[arg(long)]
    pub controller_id: Option<String>,
    /// Override the file's `workers` (device state sharded over this many workers).
    #[arg(long)]
    pub workers: Option<usize>,
    /// Serve Prometheus metrics on this address (`GET /metrics`), over the file's `metrics`.
    #[arg(long, value_name = "ADDR")]
    pub metrics: Option<String>,
    /// Record to this MCAP file, over the file's `record`.
    #[arg(long, value_name = "FILE")]
    pub record: Option<PathBuf>,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
}

/// Transparent huge pages for this process from now on, or none
/// ([`ServiceConfig::huge_pages`]): the kernel's flag for the whole process, which
/// overrides the allocator's requests for them. Pages already in place stay as they are;
/// little is, before the file is read. Elsewhere than on Linux, nothing.
pub fn huge_pages(allowed: bool) -> std::io::Result<()> {
    #[cfg(target_os = "linux")]
    {
        let disable = libc::c_ulong::from(!allowed);
        // The unused arguments as the kernel reads them (unsigned long, and 0: it refuses
        // the call otherwise), not as a variadic call would pass a plain 0.
        let unused: libc::c_ulong = 0;
        // SAFETY: PR_SET_THP_DISABLE reads its integer arguments and touches no memory.
        let rc = unsafe { libc::prctl(libc::PR_SET_THP_DISABLE, disable, unused, unused, unused) };
        if rc != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = allowed;
    Ok(())
}

/// Parse `args` (the first is the program name), log to stderr, serve until SIGINT or
/// SIGTERM; returns the process's exit code.
pub fn main_with_args<I, T>(args: I) -> std::process::ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a terminal: not into files or the journal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let cli = match ServiceCli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => e.exit(),
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("error: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(run(cli));
    // A stop while zenoh still retries its connection leaves that open on a worker: do not
    // wait for it.
    runtime.shutdown_background();
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Run the service described by `cli` until SIGINT or SIGTERM.
pub async fn run(cli: ServiceCli) -> Result<()> {
    // First: a SIGTERM while the session opens must end the service cleanly, not be lost.
    let mut shutdown = Box::pin(transport::shutdown_signal());
    let mut config = ServiceConfig::load(&cli.config)?;
    if let Err(e) = huge_pages(config.huge_pages) {
        tracing::warn!(%e, "transparent huge pages not set; the kernel's setting stays");
    }
    if let Some(id) = cli.controller_id {
        config.controller_id = id;
        config.check(&cli.config.display().to_string())?;
    }
    if let Some(w) = cli.workers {
        config.workers = w;
        config.check(&cli.config.display().to_string())?;
    }
    if let Some(addr) = cli.metrics {
        config.metrics = Some(telemetry::MetricsSpec {
            listen: addr,
            ..config.metrics.unwrap_or_default()
        });
    }
    if let Some(path) = cli.record {
        config.record = Some(telemetry::RecordSpec::at(path));
    }
    let here = cli.config.parent().unwrap_or(Path::new("."));
    if let Some(a) = &mut config.audit {
        a.path = here.join(&a.path);
    }
    if let Some(m) = &mut config.metrics {
        m.resolve(here);
    }
    let (observers, earlier) = observers(&config)?;
    let secret = match &config.secret_file {
        Some(f) => {
            let path = here.join(f);
            Some(protocol::auth::Secret::from_file(&path).context("secret_file")?)
        }
        None => None,
    };
    let registries = registries(
        config.worker_configs(),
        (secret, transport::link_lease(&cli.zenoh.to_config()?)),
        &observers,
        &earlier,
        &cli.config,
    )
    .await?;
    // A client of a router retries until the router answers (start order must not matter):
    // a stop meanwhile ends the service at once instead of waiting for the router.
    let session = tokio::select! {
        s = cli.zenoh.open_bounded(protocol::MAX_TRANSPORT_MESSAGE) => s?,
        _ = &mut shutdown => {
            tracing::info!("stopped while waiting for the router: nothing was served");
            return Ok(());
        }
    };
    if let Some(f) = config.fleet.as_ref().filter(|f| f.connect_wait_ms > 0) {
        // Who else is in the fleet is looked up next: first be connected to everyone named.
        let expected = transport::connect_endpoint_count(&cli.zenoh.to_config()?);
        let wait = std::time::Duration::from_millis(f.connect_wait_ms);
        let n = tokio::select! {
            n = transport::wait_connected(&session, expected, wait) => n,
            _ = &mut shutdown => {
                let _ = session.close().await;
                return Ok(());
            }
        };
        if n < expected {
            tracing::warn!(
                connected = n,
                endpoints = expected,
                waited_ms = f.connect_wait_ms,
                "not connected to every endpoint given: joining the fleet with the members in view"
            );
        }
    }
    let (stop_tx, stop_rx) = tokio::sync::watch::channel(false);
    let endpoint = match (&config.metrics, &observers.metrics) {
        (Some(spec), Some(m)) => {
            let mut stopped = stop_rx.clone();
            let (_, task) = crate::observe::serve_endpoint(spec, m.clone(), async move {
                let _ = stopped.wait_for(|s| *s).await;
            })
            .await?;
            Some(task)
        }
        _ => None,
    };
    let result = serve_workers(session, registries, &observers, shutdown, stop_tx, stop_rx).await;
    if let Some(e) = endpoint {
        let _ = e.await;
    }
    if let Some(r) = &observers.recording {
        match r.finish() {
            Ok(s) => {
                tracing::info!(path = %r.path().display(), messages = s.messages, dropped = s.dropped, "recording finished")
            }
            Err(e) => tracing::warn!(path = %r.path().display(), "recording: {e}"),
        }
    }
    result
}

/// One registry per worker configuration, each with the audit file's decisions and its
/// devices' journaled states back in force ([`recover`]); the changes an edited `file`
/// makes are recorded before this returns (an error if they cannot be: the service does
/// not serve a configuration it cannot record).
pub async fn registries(
    configs: Vec<ServiceConfig>,
    (secret, lease): (Option<protocol::auth::Secret>, std::time::Duration),
    observers: &Observers,
    earlier: &Replayed,
    file: &Path,
) -> Result<Vec<Registry>> {
    let mut registries = Vec::with_capacity(configs.len());
    let mut records = Vec::new();
    for c in configs {
        let mut r = Registry::new(c).context("building the devices")?;
        r.set_secret(secret.clone());
        // Its zenoh session's lease: how long a silence may hide changes made without it.
        r.set_liveliness_lease(lease);
        for e in &earlier.entries {
            r.audit(e.clone());
        }
        records.extend(recover(&mut r, earlier, file));
        registries.push(r);
    }
    if let Some(trail) = &observers.audit {
        let n = records.len();
        trail.write_all(records).await.map_err(|e| {
            anyhow::anyhow!("the audit file {} could not record the changes the edited configuration makes ({e}): not serving a configuration it cannot record", trail.path().display())
        })?;
        if n > 0 {
            tracing::info!(
                changes = n,
                "the file's edits since the last start are recorded as changes"
            );
        }
    }
    Ok(registries)
}

/// Put the journaled states back in force on `r`'s devices ([`Registry::recover`]), logging
/// what was done; the records of the changes an edited file makes, for the audit file
/// (each also kept with its device).
pub fn recover(r: &mut Registry, replayed: &Replayed, file: &Path) -> Vec<Write> {
    let rec = r.recover(&replayed.states);
    let mine = rec.restored + rec.file_changes.len();
    if mine > 0 || !rec.dropped.is_empty() {
        tracing::info!(controller = %r.controller_id(), restored = rec.restored, changed_by_the_file = rec.file_changes.len(), dropped = rec.dropped.len(), "acknowledged changes put back in force from the audit file");
    }
    for (dev, why) in &rec.dropped {
        tracing::warn!(device = %dev, "journaled state not put back: {why}");
    }
    let actor = crate::access::Actor {
        name: format!("file {}", file.display()),
        verified: true,
        role: None,
    };
    let mut last = 0;
    rec.file_changes
        .into_iter()
        .map(|fc| {
            let unix_ns = protocol::unix_ns();
            last = crate::audit::next_number(last, unix_ns);
            let entry = protocol::pb::AuditEntry {
                unix_ns,
                member: r.controller_id().to_string(),
                n: last,
                device_id: fc.device.clone(),
                operator: actor.name.clone(),
                verified: actor.verified,
                role: "file".into(),
                action: "configuration file".into(),
                changes: fc.changes,
                asked: String::new(),
                accepted: true,
                reason: fc.how,
            };
            tracing::info!(device = %fc.device, changes = entry.changes.len(), "{}", entry.reason);
            r.audit(entry.clone());
            Write::Record(Record {
                entry,
                state: Some(fc.state),
            })
        })
        .collect()
}

/// The recording, the metrics and the audit file the file asks for, and what the audit
/// file already holds (its decisions and every device's latest state). The recording
/// starts with the configuration itself attached (`service-config.toml`), which is what a
/// replay needs.
pub fn observers(config: &ServiceConfig) -> Result<(Observers, Replayed)> {
    let recording = match &config.record {
        Some(spec) => {
            let r = Recording::create(spec, "controller-service")?;
            let text = toml::to_string(config).context("the configuration as TOML")?;
            r.attach(
                crate::replay::CONFIG_ATTACHMENT,
                "application/toml",
                text.into_bytes(),
            );
            Some(r)
        }
        None => None,
    };
    let metrics = config.metrics.as_ref().map(|spec| {
        std::sync::Arc::new(ServiceMetrics::new(
            telemetry::Metrics::new(),
            &config.controller_id,
            spec,
            recording.clone(),
        ))
    });
    let (audit, earlier) = match &config.audit {
        Some(spec) => {
            let (trail, earlier) = crate::trail::AuditTrail::open(spec)
                .with_context(|| format!("audit file {}", spec.path.display()))?;
            tracing::info!(path = %spec.path.display(), entries = earlier.entries.len(), devices = earlier.states.len(), "audit trail: every operator's change is fsynced with its record before it is in force");
            if earlier.torn > 0 {
                tracing::warn!(path = %spec.path.display(), lines = earlier.torn, "audit file lines dropped: torn or corrupted (a crash or a full disk while they were written; none was acknowledged)");
            }
            (Some(trail), earlier)
        }
        None => {
            tracing::warn!("no audit file in the configuration: changes are in memory only and lost with the process (every reply says durable = false), and so are the latest 64 decisions per device");
            (None, Replayed::default())
        }
    };
    Ok((
        Observers {
            metrics,
            recording,
            audit,
        },
        earlier,
    ))
}

async fn serve_workers(
    session: zenoh::Session,
    mut registries: Vec<Registry>,
    observers: &Observers,
    shutdown: impl std::future::Future<Output = ()>,
    stop_tx: tokio::sync::watch::Sender<bool>,
    stop_rx: tokio::sync::watch::Receiver<bool>,
) -> Result<()> {
    if registries.len() == 1 {
        let registry = registries.pop().context("one registry")?;
        let result = service::serve(session.clone(), registry, observers.clone(), shutdown).await;
        let _ = stop_tx.send(true);
        let _ = session.close().await;
        result?;
        return Ok(());
    }
    // Several workers: each serves its own shards on its own task (the runtime runs them on
    // every core), all on this one session; one signal stops them all. They start one after
    // the other, each once the previous one's fleet token is seen: a worker that finds the
    // others there takes its shards by handover, never by believing itself alone.
    let mut tasks = Vec::new();
    for registry in registries {
        let member = registry
            .fleet()
            .map(|f| keys::fleet_member(&f.name, registry.controller_id()));
        let mut stopped = stop_rx.clone();
        tasks.push(tokio::spawn(service::serve(
            session.clone(),
            registry,
            observers.clone(),
            async move {
                let _ = stopped.wait_for(|s| *s).await;
            },
        )));
        if let Some(key) = member {
            transport::wait_for_token(&session, &key, std::time::Duration::from_secs(10)).await;
        }
    }
    shutdown.await;
    let _ = stop_tx.send(true);
    for t in tasks {
        t.await??;
    }
    let _ = session.close().await;
    Ok(())
}

#[cfg(test)]
mod tests {
    /// clap's own consistency checks (unique ids, valid defaults) on the whole CLI.
    #[test]
    fn cli_is_consistent() {
        use clap::CommandFactory;
        super::ServiceCli::command().debug_assert();
    }

    /// The kernel's own account of the process (`THP_enabled` in `/proc/self/status`)
    /// follows the setting both ways; a kernel built without huge pages reports them off
    /// whatever the setting, and then only that is checked. Other tests of this process
    /// are not disturbed: huge pages change where memory comes from, not what it holds.
    #[cfg(target_os = "linux")]
    #[test]
    fn huge_pages_follow_the_setting() {
        let enabled = || {
            let status = std::fs::read_to_string("/proc/self/status").unwrap();
            let line = status.lines().find(|l| l.starts_with("THP_enabled:"));
            let line = line.expect("THP_enabled in /proc/self/status (Linux 5.0 on)");
            line.split_whitespace().nth(1) == Some("1")
        };
        let supported = std::path::Path::new("/sys/kernel/mm/transparent_hugepage").exists();
        super::huge_pages(false).unwrap();
        assert!(!enabled());
        super::huge_pages(true).unwrap();
        assert_eq!(enabled(), supported);
    }
}
