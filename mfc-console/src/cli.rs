//! The command line:
//!
//! ```text
//! mfc-console --connect tcp/127.0.0.1:7447                       # then open http://127.0.0.1:8080/
//! mfc-console --zenoh-config operator.json5 --listen-http 127.0.0.1:9000 --config console.toml
//! ```
//!
//! It runs until SIGINT or SIGTERM. The page is served on loopback by default: anyone who
//! can reach it acts with the operator's Zenoh identity.

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;

use clap::Parser;

use crate::http::{router, Guard};
use crate::net::{wire, Console};
use crate::settings::Settings;
use crate::ConsoleError;

/// The operator's live console: devices, live plots, status, gains and references, in a
/// browser.
#[derive(Debug, Parser)]
#[command(name = "mfc-console", version)]
pub struct ConsoleCli {
    #[command(flatten)]
    pub zenoh: transport::ZenohArgs,
    /// Address the page is served on (keep it on loopback unless a proxy authenticates).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub listen_http: SocketAddr,
    /// Settings (TOML; see `mfc_console::settings` for every field and its default).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// The operators' key file (`mfc-deploy` writes `keys/operator.key`): only replies
    /// sealed with it are shown. Without it, replies are taken unchecked (the log says so).
    #[arg(long)]
    pub key_file: Option<PathBuf>,
    /// The operator the console's requests name (`…/by/{operator}`): under a deployment,
    /// the common name of the certificate in its zenoh configuration. Default: the name
    /// that file gives (`mfc-deploy` writes it), else the local user, which services
    /// record as unverified.
    #[arg(long, env = "MFC_OPERATOR")]
    pub operator: Option<String>,
}

/// Parse `args` and run until a signal; the process's exit code: 0 stopped by a signal, 1
/// failed (the reason on stderr), 2 bad usage.
pub fn main_with_args<I, T>(args: I) -> std::process::ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = match ConsoleCli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return std::process::ExitCode::from(if e.use_stderr() { 2 } else { 0 });
        }
    };
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mfc-console: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    // The signal handlers need the runtime: made inside it.
    match runtime.block_on(async { run(cli, transport::shutdown_signal()).await }) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mfc-console: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// Run the console until `stop` completes.
pub async fn run(
    cli: ConsoleCli,
    stop: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ConsoleError> {
    let settings = match &cli.config {
        Some(p) => Settings::load(p)?,
        None => Settings::default(),
    };
    // Bind first: a port in use is reported before joining the network.
    let listener = tokio::net::TcpListener::bind(cli.listen_http)
        .await
        .map_err(|source| ConsoleError::Http {
            addr: cli.listen_http,
            source,
        })?;
    let addr = listener.local_addr().map_err(|source| ConsoleError::Http {
        addr: cli.listen_http,
        source,
    })?;
    if addr.ip().is_unspecified() && settings.allowed_hosts.is_empty() {
        tracing::warn!(
            "listening on {addr}: only localhost names are accepted as Host; name the others in allowed_hosts"
        );
    }
    // No message larger than what the console reads is reassembled (see transport).
    let session = cli
        .zenoh
        .open_bounded(protocol::MAX_TRANSPORT_MESSAGE)
        .await
        .map_err(|e| ConsoleError::Zenoh(e.to_string()))?;
    let key = match &cli.key_file {
        Some(p) => Some(protocol::auth::Key::from_file(p)?),
        None => {
            tracing::warn!(
                "no --key-file: replies are shown without checking where they came from"
            );
            None
        }
    };
    let mut console = Console::new(session.clone(), settings.clone(), key);
    console.operator.name = match &cli.operator {
        Some(n) => Some(
            protocol::keys::check_id(n)
                .map_err(|e| ConsoleError::Usage(format!("--operator: {e}")))?
                .to_string(),
        ),
        None => transport::ops::default_name(&cli.zenoh),
    };
    tracing::info!(operator = ?console.operator.name, "requests name this operator");
    let console = Arc::new(console);
    let wiring = wire(console.clone()).await?;
    let guard = Guard::new(addr, &settings.allowed_hosts);
    tracing::info!(
        "console on http://{addr}/ (accepts Host: {})",
        guard.hosts().join(", ")
    );
    let served = axum::serve(listener, router(console, guard))
        .with_graceful_shutdown(stop)
        .await
        .map_err(|source| ConsoleError::Http { addr, source });
    drop(wiring);
    let _ = session.close().await;
    served
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_parses() {
        use clap::CommandFactory;
        ConsoleCli::command().debug_assert();
        let cli =
            ConsoleCli::try_parse_from(["mfc-console", "--connect", "tcp/127.0.0.1:7447"]).unwrap();
        assert_eq!(cli.listen_http.to_string(), "127.0.0.1:8080");
        assert_eq!(cli.zenoh.connect, ["tcp/127.0.0.1:7447"]);
    }
}
