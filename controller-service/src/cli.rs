//! The command line of the service. It lives in the library so that the binary is one
//! line and the system tests can start the very same service in a process of their own.

use std::path::PathBuf;

use crate::{service, Registry, ServiceConfig};
use anyhow::{Context, Result};
use clap::Parser;
use transport::ZenohArgs;

#[derive(Parser)]
#[command(
    name = "controller-service",
    version,
    about = "Model-free control as a service over Zenoh"
)]
pub struct Cli {
    /// Service configuration (TOML: controller_id, devices, templates).
    #[arg(long, short)]
    pub config: PathBuf,
    /// Override the controller id of the file.
    #[arg(long)]
    pub controller_id: Option<String>,
    #[command(flatten)]
    pub zenoh: ZenohArgs,
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
    let cli = match Cli::try_parse_from(args) {
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
pub async fn run(cli: Cli) -> Result<()> {
    // First: a SIGTERM while the session opens must end the service cleanly, not be lost.
    let mut shutdown = Box::pin(transport::shutdown_signal());
    let mut config = ServiceConfig::load(&cli.config)?;
    if let Some(id) = cli.controller_id {
        config.controller_id = id;
        config.check(&cli.config.display().to_string())?;
    }
    let registry = Registry::new(config).context("building the devices")?;
    // A client of a router retries until the router answers (start order must not matter):
    // a stop meanwhile ends the service at once instead of waiting for the router.
    let session = tokio::select! {
        s = cli.zenoh.open_bounded(protocol::MAX_TRANSPORT_MESSAGE) => s?,
        _ = &mut shutdown => {
            tracing::info!("stopped while waiting for the router: nothing was served");
            return Ok(());
        }
    };
    service::serve(session, registry, shutdown).await?;
    Ok(())
}

#[cfg(test)]
mod tests {
    /// clap's own consistency checks (unique ids, valid defaults) on the whole CLI.
    #[test]
    fn cli_is_consistent() {
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
