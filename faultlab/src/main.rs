//! `faultlab`: the impairment relay as a command, to put any link of your own deployment
//! under a profile. The campaign that runs this project's loop through it is `mfc-lab campaign`.

use std::net::SocketAddr;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use faultlab::profile::ProfileSet;
use faultlab::relay::{Link, Relay};

#[derive(Parser)]
#[command(
    name = "faultlab",
    version,
    about = "Network fault injection for model-free control over Zenoh"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Relay LINK traffic from --listen to --target under one profile (to test your own
    /// deployment: point the plants at --listen instead of the controller).
    Relay {
        /// udp or tcp.
        #[arg(long, value_enum)]
        link: Link,
        /// Address to listen on, e.g. 127.0.0.1:7448.
        #[arg(long)]
        listen: SocketAddr,
        /// The controller's address, e.g. 127.0.0.1:7447.
        #[arg(long)]
        target: SocketAddr,
        /// Profile file (or `default` for the shipped set).
        #[arg(long, default_value = "default")]
        profiles: String,
        /// Name of the profile to apply.
        #[arg(long)]
        profile: String,
    },
}

fn main() -> std::process::ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match real_main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn real_main() -> Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    match Cli::parse().command {
        Command::Relay {
            link,
            listen,
            target,
            profiles,
            profile,
        } => {
            let set = ProfileSet::load(&profiles)?;
            let p = set
                .profiles
                .iter()
                .find(|p| p.name == profile)
                .with_context(|| format!("no profile `{profile}` in {profiles}"))?
                .clone();
            runtime.block_on(async {
                let relay = Relay::start(link, listen, target, &p, true).await?;
                eprintln!(
                    "relaying {link:?} {} -> {target} under `{}` (Ctrl-C to stop)",
                    relay.listen, p.name
                );
                tokio::signal::ctrl_c().await?;
                eprintln!("{}", serde_json::to_string_pretty(&relay.stats())?);
                anyhow::Ok(())
            })
        }
    }
}
