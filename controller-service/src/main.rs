//! `controller-service`: serve the devices of a configuration file over Zenoh until SIGINT
//! or SIGTERM.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Parser;
use controller_service::{service, Registry, ServiceConfig};
use transport::ZenohArgs;

#[derive(Parser)]
#[command(
    name = "controller-service",
    version,
    about = "Model-free control as a service over Zenoh"
)]
struct Cli {
    /// Service configuration (TOML: controller_id, devices, templates).
    #[arg(long, short)]
    config: PathBuf,
    /// Override the controller id of the file.
    #[arg(long)]
    controller_id: Option<String>,
    #[command(flatten)]
    zenoh: ZenohArgs,
}

async fn shutdown_signal() {
    let ctrl_c = tokio::signal::ctrl_c();
    #[cfg(unix)]
    {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(s) => s,
                Err(e) => {
                    tracing::warn!("cannot listen for SIGTERM: {e}");
                    let _ = ctrl_c.await;
                    return;
                }
            };
        tokio::select! {
            _ = ctrl_c => {},
            _ = term.recv() => {},
        }
    }
    #[cfg(not(unix))]
    {
        let _ = ctrl_c.await;
    }
}

#[tokio::main(flavor = "multi_thread")]
async fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .init();
    match run().await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

async fn run() -> Result<()> {
    let cli = Cli::parse();
    let mut config = ServiceConfig::load(&cli.config)?;
    if let Some(id) = cli.controller_id {
        config.controller_id = id;
        config.check(&cli.config.display().to_string())?;
    }
    let registry = Registry::new(config).context("building the devices")?;
    let session = cli.zenoh.open().await?;
    service::run(session, registry, shutdown_signal()).await?;
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
