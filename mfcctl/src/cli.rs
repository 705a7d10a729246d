//! The command line. Every command is one or two queries through whatever session the
//! Zenoh flags describe (in a secured deployment: the operator's client config for the
//! router), printed as text, or as JSON with `--json`.
//!
//! ```text
//! mfcctl --connect tcp/10.0.0.1:7447 services
//! mfcctl devices
//! mfcctl status aero-1
//! mfcctl config aero-1
//! mfcctl set aero-1 --channel 1 kp=450 alpha=5
//! mfcctl params                                      # the tunable parameters (no network)
//! mfcctl reference aero-1 --constant 0,0.2
//! mfcctl reference aero-1 --file steps.toml          # pieces start now on the plant's clock
//! mfcctl envelope aero-1 --channel 1 --min -12 --max 12 --reason "commissioning"
//! mfcctl audit aero-1                                # who changed what, and the result
//! mfcctl commission aero-1 --channel 1 --amplitude 0.5 --max-deviation 0.2
//! ```
//!
//! Every request on a device names its operator (`--operator`, by default the local
//! user): under a deployment the router holds each certificate to its own name, and the
//! services check the name's role; without one the name is a claim, recorded as such.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use protocol::pb;
use serde::Serialize;

use crate::{ops, render};

/// Operate model-free control services: status, configuration, gains, references.
#[derive(Debug, Parser)]
#[command(name = "mfcctl", version)]
pub struct MfcctlCli {
    #[command(flatten)]
    pub zenoh: transport::ZenohArgs,
    /// Print JSON (the protobuf messages, field names as in `mfc.proto`) instead of text.
    #[arg(long, global = true)]
    pub json: bool,
    /// How long a command may take in all (ms): opening the session and every answer it
    /// waits for. A command ends by then whatever the network or a controller does (a
    /// router down, a member paused or cut off), with an error that says what it waited
    /// for. `commission` (which follows a run) bounds each of its queries by it instead.
    #[arg(long, default_value_t = 2000, global = true)]
    pub timeout_ms: u64,
    /// The operators' key file (`mfc-deploy` writes `keys/operator.key`): only replies
    /// sealed with it are shown, so a process that may reply on a controller's keys cannot
    /// answer for it. Without it, replies are taken unchecked.
    #[arg(long, global = true)]
    pub key_file: Option<PathBuf>,
    /// Who asks, named in every request on a device (`…/by/{operator}`). Under a
    /// deployment, the common name of the operator's certificate (the router refuses
    /// any other). Default: the name the zenoh configuration file gives (`mfc-deploy`
    /// writes the certificate's), else the local user (`$USER`), which services record
    /// as unverified.
    #[arg(long, global = true, env = "MFC_OPERATOR")]
    pub operator: Option<String>,
    #[command(subcommand)]
    pub command: Command,
}

/// What to do.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Every controller that answers: role, term, devices, drop counters.
    Services,
    /// Every device served, with its controller and whether its plant is up.
    Devices,
    /// One device's counters, round trips, F estimates and envelope.
    Status {
        /// Device id.
        device: String,
    },
    /// One device's laws, output maps, envelope and reference.
    Config {
        /// Device id.
        device: String,
    },
    /// Change single parameters of one channel (a partial change: nothing else moves).
    #[command(after_help = render::set_fields())]
    Set {
        /// Device id.
        device: String,
        /// Channel index (0-based).
        #[arg(long)]
        channel: u32,
        /// FIELD=VALUE pairs.
        #[arg(required = true, value_name = "FIELD=VALUE")]
        fields: Vec<String>,
    },
    /// The tunable parameters: name, laws, unit, sane bounds, meaning (no network).
    Params {
        /// Print the table as Markdown (what docs/parameters.md holds); not with --json.
        #[arg(long)]
        markdown: bool,
    },
    /// Steer the reference: a constant per channel, or pieces from a TOML file
    /// (`channels = [[{ kind = "smooth_step", start = 1.0, duration = 2.0, height = 0.1 }], ...]`).
    Reference {
        /// Device id.
        device: String,
        /// One constant per channel, comma-separated.
        #[arg(
            long,
            value_delimiter = ',',
            allow_hyphen_values = true,
            conflicts_with = "file"
        )]
        constant: Vec<f64>,
        /// A TOML file of pieces per channel.
        #[arg(long)]
        file: Option<PathBuf>,
        /// Times in the file are plant times (default: relative to the plant's time now).
        #[arg(long)]
        absolute: bool,
    },
    /// Narrow one channel's envelope (widening only if the service's file allows it).
    Envelope {
        /// Device id.
        device: String,
        /// Channel index (0-based).
        #[arg(long)]
        channel: usize,
        /// Lowest command.
        #[arg(long, allow_hyphen_values = true)]
        min: f64,
        /// Highest command.
        #[arg(long, allow_hyphen_values = true)]
        max: f64,
        /// Largest change per second (none: keep no rate limit).
        #[arg(long)]
        rate: Option<f64>,
        /// Who asks and why (logged by the service).
        #[arg(long)]
        reason: String,
    },
    /// Find alpha (and the model's order) of one channel on the live plant: a square wave
    /// of +-amplitude around the input it holds, aborted at once if the output moves more
    /// than --max-deviation; shows what it found and the law it proposes, and puts it in
    /// force when you confirm (docs/commissioning.md).
    Commission(CommissionArgs),
    /// The audit trail: who changed what on a device (or on every device you may see),
    /// old and new values, accepted or refused and why; the latest 64 per device.
    Audit {
        /// Device id (none: every device).
        device: Option<String>,
    },
}

/// `mfcctl commission`'s arguments.
#[derive(Debug, clap::Args)]
pub struct CommissionArgs {
    /// Device id.
    pub device: String,
    /// Channel index (0-based); its law must be intelligent.
    #[arg(long)]
    pub channel: u32,
    /// The square wave's half height, in the law's units (before the output map).
    #[arg(long, required_unless_present_any = ["confirm", "abort"])]
    pub amplitude: Option<f64>,
    /// The largest change of the output accepted; beyond it the run aborts.
    #[arg(long, required_unless_present_any = ["confirm", "abort"])]
    pub max_deviation: Option<f64>,
    /// The square wave's period (s); each half must hold the estimator's window.
    #[arg(long, default_value_t = 2.0)]
    pub period: f64,
    /// How many periods.
    #[arg(long, default_value_t = 4)]
    pub cycles: u32,
    /// The estimator's window (intervals).
    #[arg(long, default_value_t = 20)]
    pub window: u32,
    /// Fit this order only (1 or 2); default both, the better kept.
    #[arg(long)]
    pub order: Option<u32>,
    /// The error dynamics the proposed gains give (rad/s); default: the law's own.
    #[arg(long, requires = "damping")]
    pub bandwidth: Option<f64>,
    /// ... and their damping.
    #[arg(long, requires = "bandwidth")]
    pub damping: Option<f64>,
    /// Put the proposal in force without asking.
    #[arg(long)]
    pub yes: bool,
    /// Confirm the proposal of the last run on the channel (no new run).
    #[arg(long, conflicts_with_all = ["abort", "amplitude", "yes"])]
    pub confirm: bool,
    /// Stop the run on the channel, or dismiss its proposal.
    #[arg(long, conflicts_with_all = ["amplitude", "yes"])]
    pub abort: bool,
    /// Why, for the record.
    #[arg(long, default_value = "")]
    pub reason: String,
    /// With --confirm or --abort: the run meant, as `mfcctl status` numbers it (default:
    /// the device's last).
    #[arg(long, default_value_t = 0)]
    pub run: u64,
}

/// Parse `args`, run, print; the process's exit code: 0 done, 1 refused or failed (the
/// reason on stderr), 2 bad usage.
pub fn main_with_args<I, T>(args: I) -> std::process::ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = match MfcctlCli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return std::process::ExitCode::from(if e.use_stderr() { 2 } else { 0 });
        }
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            eprintln!("mfcctl: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(run(cli));
    // Whatever zenoh's tasks still wait for (a reconnection, a close), they are not waited
    // for: the command has its answer, or its error.
    runtime.shutdown_background();
    match result {
        Ok(text) => {
            print!("{text}");
            std::process::ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("mfcctl: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

/// `devices --json`.
#[derive(Serialize)]
struct DevicesJson {
    services: Vec<pb::ServiceStatus>,
    plants_up: Vec<String>,
}

fn out<T: Serialize>(json: bool, value: &T, text: impl FnOnce(&T) -> String) -> Result<String> {
    if json {
        Ok(serde_json::to_string_pretty(value)? + "\n")
    } else {
        Ok(text(value))
    }
}

/// The reference file's shape.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ReferenceFile {
    /// Pieces per channel, summed.
    channels: Vec<Vec<mfc::trajectory::Piece>>,
}

/// The pieces of `reference` and their start (plant time): one constant per channel, or a
/// file's pieces, whose times count from the plant's time now unless `absolute`.
async fn reference(
    operator: &ops::Operator,
    device: &str,
    constant: &[f64],
    file: Option<&std::path::Path>,
    absolute: bool,
    timeout: Duration,
) -> Result<(Vec<Vec<mfc::trajectory::Piece>>, f64)> {
    Ok(match file {
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .with_context(|| format!("reading {}", path.display()))?;
            let f: ReferenceFile =
                toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
            let start = if absolute {
                0.0
            } else {
                ops::device_status(operator, device, timeout)
                    .await?
                    .plant_time
            };
            (f.channels, start)
        }
        None if !constant.is_empty() => (
            constant
                .iter()
                .map(|&value| vec![mfc::trajectory::Piece::Constant { value }])
                .collect(),
            0.0,
        ),
        None => bail!("give --constant V[,V...] or --file FILE"),
    })
}

/// `params`: the table as text, JSON or Markdown.
fn params(markdown: bool, json: bool) -> Result<String> {
    if markdown && json {
        bail!("params: give --json or --markdown, not both");
    }
    if markdown {
        Ok(render::params_markdown())
    } else {
        out(json, &render::params_json(), |_| render::params())
    }
}

/// Run one command; the text (or JSON) to print.
pub async fn run(cli: MfcctlCli) -> Result<String> {
    // The table is the core's: no session needed.
    if let Command::Params { markdown } = cli.command {
        return params(markdown, cli.json);
    }
    let timeout = Duration::from_millis(cli.timeout_ms);
    let key = match &cli.key_file {
        Some(p) => Some(protocol::auth::Key::from_file(p).context("--key-file")?),
        None => None,
    };
    let name = match cli.operator {
        Some(n) => Some(
            protocol::keys::check_id(&n)
                .context("--operator")?
                .to_string(),
        ),
        None => ops::default_name(&cli.zenoh),
    };
    let deadline = tokio::time::Instant::now() + timeout;
    let session = tokio::time::timeout_at(deadline, cli.zenoh.open())
        .await
        .map_err(|_| {
            anyhow::anyhow!(
                "no zenoh session within {} ms: the router (or the peers given) did not answer (is it up and reachable from here?)",
                timeout.as_millis()
            )
        })??;
    let operator = ops::Operator {
        session: session.clone(),
        key,
        name,
    };
    let result = match &cli.command {
        // A commissioning run is followed for as long as it runs: each query is bounded.
        Command::Commission(_) => command(&operator, &cli.command, cli.json, timeout).await,
        c => {
            let run = command(&operator, c, cli.json, timeout);
            tokio::time::timeout_at(deadline, run)
                .await
                .unwrap_or_else(|_| {
                    Err(anyhow::anyhow!(
                        "no answer within {} ms (is a controller up and reachable?)",
                        timeout.as_millis()
                    ))
                })
        }
    };
    // Closing says goodbye to the router; a router that does not answer is not waited for.
    let _ = tokio::time::timeout(CLOSE_WAIT, session.close()).await;
    result
}

/// How long `mfcctl` waits for its session to close before it exits anyway.
const CLOSE_WAIT: Duration = Duration::from_millis(200);

async fn command(
    operator: &ops::Operator,
    command: &Command,
    json: bool,
    timeout: Duration,
) -> Result<String> {
    let session = &operator.session;
    Ok(match command {
        Command::Services => {
            let list = ops::services(operator, timeout).await?;
            let alive = ops::alive(session, "controller").await?;
            if list.is_empty() && alive.is_empty() {
                bail!("no controller answered within {} ms", timeout.as_millis());
            }
            out(json, &list, |l| render::services(l, &alive))?
        }
        Command::Devices => {
            let list = ops::services(operator, timeout).await?;
            let plants = ops::alive(session, "plant").await?;
            // JSON: the services' statuses as `services`, and the plants whose agents are
            // up (liveliness) as `plants_up`, served or not.
            let both = DevicesJson {
                services: list,
                plants_up: plants,
            };
            out(json, &both, |b| render::devices(&b.services, &b.plants_up))?
        }
        Command::Status { device } => {
            let all = ops::device_statuses(operator, device, timeout).await?;
            out(json, &all[0], |s| {
                render::status(s) + &render::answered(&all)
            })?
        }
        Command::Config { device } => {
            let c = ops::config(operator, device, timeout).await?;
            out(json, &c, render::config)?
        }
        Command::Set {
            device,
            channel,
            fields,
        } => {
            let u = ops::parse_update(*channel, fields)?;
            let c = ops::update(operator, device, u, timeout).await?;
            out(json, &c, render::changed)?
        }
        Command::Params { markdown } => params(*markdown, json)?,
        Command::Reference {
            device,
            constant,
            file,
            absolute,
        } => {
            let (pieces, start) = reference(
                operator,
                device,
                constant,
                file.as_deref(),
                *absolute,
                timeout,
            )
            .await?;
            let r = protocol::convert::reference_to_pb(&pieces, start);
            let c = ops::set_reference(operator, device, r, timeout).await?;
            out(json, &c, render::changed)?
        }
        Command::Envelope {
            device,
            channel,
            min,
            max,
            rate,
            reason,
        } => {
            let now = ops::config(operator, device, timeout).await?;
            let mut env = now.envelope.unwrap_or_default();
            let n = env.channels.len();
            let Some(slot) = env.channels.get_mut(*channel) else {
                bail!("device {device} has {n} channels, not {}", channel + 1);
            };
            *slot = pb::ChannelLimits {
                min: Some(*min),
                max: Some(*max),
                rate_limit: *rate,
            };
            let c = ops::change_envelope(operator, device, env, reason, timeout).await?;
            out(json, &c, render::changed)?
        }
        Command::Audit { device } => {
            let logs = ops::audit(operator, device.as_deref(), timeout).await?;
            out(json, &logs, |l| render::audit(l))?
        }
        Command::Commission(a) => crate::commission::run(operator, a, json, timeout).await?,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_parses() {
        use clap::CommandFactory;
        MfcctlCli::command().debug_assert();
        let cli = MfcctlCli::try_parse_from([
            "mfcctl",
            "--json",
            "reference",
            "a",
            "--constant",
            "-1,0.5",
        ])
        .unwrap();
        assert!(cli.json);
        assert!(
            matches!(cli.command, Command::Reference { ref constant, .. } if constant == &[-1.0, 0.5])
        );
        // `params` needs no network: it answers even with nothing to connect to.
        let rt = tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap();
        let md = MfcctlCli::try_parse_from(["mfcctl", "params", "--markdown"]).unwrap();
        assert_eq!(rt.block_on(run(md)).unwrap(), render::params_markdown());
        let json = MfcctlCli::try_parse_from(["mfcctl", "--json", "params"]).unwrap();
        let v: serde_json::Value = serde_json::from_str(&rt.block_on(run(json)).unwrap()).unwrap();
        assert_eq!(v[3]["name"], "alpha");
        let both = MfcctlCli::try_parse_from(["mfcctl", "--json", "params", "--markdown"]).unwrap();
        assert!(rt.block_on(run(both)).is_err());
        // `set`'s help lists the table's names.
        let help = MfcctlCli::command()
            .find_subcommand_mut("set")
            .unwrap()
            .render_long_help()
            .to_string();
        assert!(
            help.contains("hold_estimate_filter") && help.contains("rate_limit"),
            "{help}"
        );
    }
}
