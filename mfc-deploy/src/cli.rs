//! The command line: `example`, `generate`.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, Subcommand};

use crate::generate::{generate, CertAction};
use crate::inventory::{IdentityKind, Inventory, EXAMPLE};

/// Generate a fleet's certificates, zenoh configs and access control from its inventory.
#[derive(Parser)]
#[command(version)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print an example inventory (`mfc-deploy example > fleet.toml`).
    Example,
    /// Write (or bring up to date) one bundle per host in OUT: the CA on first use, a
    /// certificate per name that has none or whose certificate is no longer right, the
    /// router's config with the access control, a client config per name. Certificates
    /// still right are kept, so adding a device touches no other host but the router.
    Generate {
        /// The inventory (TOML; `mfc-deploy example` prints one).
        #[arg(long, short, default_value = "fleet.toml")]
        inventory: PathBuf,
        /// Output directory. It holds the CA's key: keep it on the admin machine.
        #[arg(long, short, default_value = "fleet")]
        out: PathBuf,
        /// Replace this name's key and certificate even if still valid (repeatable).
        #[arg(long, value_name = "NAME")]
        rotate: Vec<String>,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
    },
}

/// Parse the process's arguments, run, and return the exit status (0 done, 1 failed).
pub fn main() -> std::process::ExitCode {
    match run(Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("mfc-deploy: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Example => print!("{EXAMPLE}"),
        Command::Generate {
            inventory,
            out,
            rotate,
            json,
        } => {
            let inv = Inventory::load(&inventory)?;
            let now = time::OffsetDateTime::now_utc();
            let report = generate(&inv, &out, &rotate, now)
                .with_context(|| format!("generating into {}", out.display()))?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
                return Ok(());
            }
            let say = |a: &CertAction| match a {
                CertAction::Issued => "issued".to_string(),
                CertAction::Kept => "kept".to_string(),
                CertAction::Reissued(why) => format!("reissued ({why})"),
            };
            println!("{:<10} {:<20} {}", "CA", "", say(&report.ca));
            for e in &report.entries {
                let role = format!("{:?}", e.role).to_lowercase();
                let mut what = say(&e.action);
                if e.config_changed && e.action == CertAction::Kept {
                    what = "kept, config rewritten".into();
                }
                let copy = if e.to_copy() { "copy" } else { "-" };
                println!(
                    "{role:<10} {:<20} {what:<40} {copy:<5} {}",
                    e.name,
                    e.bundle.display()
                );
            }
            for r in &report.retired {
                println!("retired    {}", r.display());
            }
            println!(
                "\nCopy the bundles marked `copy` to {} on their hosts. The CA key stays in {}.",
                inv.install_dir,
                out.join("ca").display()
            );
            if report.router_restart() {
                println!(
                    "The router's certificate or access control changed: copy {} to the router and restart zenohd (plants ride through on their fallback).",
                    out.join(IdentityKind::Router.dir()).display()
                );
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_cli_is_consistent() {
        use clap::CommandFactory;
        super::Cli::command().debug_assert();
    }
}
