//! The `plant-agent` command line. Thin: parse, resolve the configuration, open the plant
//! and the session, run, write the record, exit with the run's status.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};

use crate::agent::{self, AgentReport};
use crate::config::AgentFile;
use crate::observe;
use crate::safety::FallbackPolicy;
use plant::record::write_run;
use plant::run_id;

#[derive(Parser)]
#[command(
    name = "plant-agent",
    version,
    about = "Bridges a plant (a rig's driver or a simulator) to a model-free controller service over Zenoh"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run one plant against a controller service until the scenario's duration, SIGINT
    /// or SIGTERM; then apply the plant's safe stop and write the record.
    ///
    /// Exit status: 0 ran (or was stopped) with a controller answering; 3 no controller
    /// ever answered (the plant ran on its fallback: check endpoint, TLS, access control;
    /// also when stopped while still waiting for the router, after the safe stop);
    /// 5 the controller was lost and the run ended on the fallback; 4 the plant failed or
    /// did not confirm its safe stop; 1 the configuration or the session was refused.
    Run(RunArgs),
    /// Host many plants in one process (a cell, a building): every plant keeps its own
    /// loop and safety; their samples go out in one batch per period and their commands
    /// come back in one. Exit status: the worst of the plants' (as for `run`).
    Gateway(GatewayArgs),
    /// Look into a plant's server to write its map: read a range of a Modbus server's
    /// registers once and show each as every type a map could read it as.
    Probe {
        #[command(subcommand)]
        what: ProbeCommand,
    },
}

#[derive(Subcommand)]
enum ProbeCommand {
    /// Read `--count` values of `--kind` from `--start` on a Modbus TCP server.
    Modbus(ProbeModbusArgs),
    /// Browse an OPC UA server's address space from `--node`, `--depth` levels down: node
    /// ids, browse names, classes, and each variable's type and value.
    Opcua(ProbeOpcUaArgs),
}

#[derive(clap::Args)]
struct ProbeOpcUaArgs {
    /// The endpoint, opc.tcp://host:port/path.
    endpoint: String,
    /// Where to start (a node id). Default: the Objects folder.
    #[arg(long, default_value = "i=85")]
    node: String,
    /// How many levels to go down.
    #[arg(long, default_value_t = 3)]
    depth: usize,
    /// A user name (absent: anonymous); its password is the first line of --password-file.
    #[arg(long, requires = "password_file")]
    user: Option<String>,
    /// The user's password file.
    #[arg(long, requires = "user")]
    password_file: Option<PathBuf>,
    /// The user as a certificate (DER or PEM) instead of a name.
    #[arg(long, requires = "user_private_key", conflicts_with = "user")]
    user_certificate: Option<PathBuf>,
    /// The user certificate's private key (PEM).
    #[arg(long, requires = "user_certificate")]
    user_private_key: Option<PathBuf>,
    /// Security policy: None, Basic256Sha256, Aes128_Sha256_RsaOaep or Aes256_Sha256_RsaPss.
    #[arg(long, default_value = "None")]
    security_policy: String,
    /// Security mode: None (with the policy None), Sign or SignAndEncrypt.
    #[arg(long, default_value = "None")]
    security_mode: String,
    /// The bridge's PKI directory (own/cert.der, private/private.pem, trusted/,
    /// rejected/): needed by any policy but None.
    #[arg(long)]
    pki_dir: Option<PathBuf>,
    /// Make a self-signed certificate and key in --pki-dir if it has none (then have the
    /// server trust own/cert.der, and move the server's certificate from rejected/ to
    /// trusted/ once checked).
    #[arg(long, requires = "pki_dir")]
    create_keypair: bool,
    /// Longest wait for the session and for each answer (ms).
    #[arg(long, default_value_t = 5000)]
    timeout_ms: u64,
}

fn probe_opcua(a: ProbeOpcUaArgs) -> Result<u8> {
    use fieldbus::opcua::{OpcUaUser, SessionSpec};
    let timeout = std::time::Duration::from_millis(a.timeout_ms);
    let mut spec = SessionSpec::plain(&a.endpoint, timeout);
    spec.identity = match (
        a.user,
        a.password_file,
        a.user_certificate,
        a.user_private_key,
    ) {
        (Some(name), Some(f), _, _) => {
            let text =
                std::fs::read_to_string(&f).with_context(|| format!("reading {}", f.display()))?;
            let password = text.lines().next().unwrap_or_default().to_string();
            OpcUaUser::User { name, password }
        }
        (_, _, Some(cert), Some(key)) => OpcUaUser::Certificate { cert, key },
        _ => OpcUaUser::Anonymous,
    };
    spec.policy = a.security_policy;
    spec.mode = a.security_mode;
    spec.pki_dir = a.pki_dir;
    spec.create_keypair = a.create_keypair;
    let own = spec
        .pki_dir
        .as_ref()
        .map(|d| d.join(fieldbus::opcua::OWN_CERT));
    let had = own.as_ref().is_some_and(|c| c.is_file());
    let tree = fieldbus::probe::opcua(&spec, &a.node, a.depth);
    // Made even when the session then fails (the server does not trust it yet): say where.
    if let Some(cert) = own.filter(|c| !had && c.is_file()) {
        eprintln!(
            "made the bridge's certificate {}: have the server trust it",
            cert.display()
        );
    }
    print!("{}", tree?);
    Ok(0)
}

#[derive(clap::Args)]
struct ProbeModbusArgs {
    /// The server, host:port.
    address: String,
    /// Unit id.
    #[arg(long, default_value_t = 1)]
    unit: u8,
    /// Register kind: holding, input, coil or discrete_input.
    #[arg(long, default_value = "holding", value_parser = parse_kind)]
    kind: plant::modbus::RegisterKind,
    /// First address (0-based, as on the wire: a manual's 40001 is holding 0).
    #[arg(long, default_value_t = 0)]
    start: u16,
    /// How many (at most 125 registers, 2000 bits).
    #[arg(long, default_value_t = 16)]
    count: u16,
    /// Longest wait for the connection and the answer (ms).
    #[arg(long, default_value_t = 2000)]
    timeout_ms: u64,
}

fn parse_kind(s: &str) -> Result<plant::modbus::RegisterKind, String> {
    toml::Value::String(s.to_string())
        .try_into()
        .map_err(|_| format!("{s}: holding, input, coil or discrete_input"))
}

#[derive(clap::Args)]
struct GatewayArgs {
    /// The gateway's file (TOML): `gateway`, `out`, and `[[plants]]` entries with the
    /// fields of a single agent's file.
    #[arg(long, short)]
    config: PathBuf,
    #[command(flatten)]
    zenoh: transport::ZenohArgs,
}

#[derive(clap::Args)]
struct RunArgs {
    /// Agent configuration file (TOML; see `plant-agent/src/config.rs`). The flags below
    /// override it.
    #[arg(long, short)]
    config: Option<PathBuf>,
    /// Device id.
    #[arg(long)]
    device: Option<String>,
    /// Scenario file, or a shipped AERO one (1, 2, 3, 4).
    #[arg(long)]
    scenario: Option<String>,
    /// Local controller (also the fallback): a controller file or a shipped name.
    #[arg(long)]
    controller: Option<String>,
    /// Run length (s), instead of the scenario's.
    #[arg(long)]
    duration: Option<f64>,
    /// Periods to hold the last command before falling back.
    #[arg(long)]
    hold_periods: Option<u32>,
    /// What to fall back to: `local` (the local controller) or `safe-stop` (zero inputs).
    #[arg(long, value_parser = crate::safety::parse_fallback)]
    fallback: Option<FallbackPolicy>,
    /// Oldest command still applied, in periods.
    #[arg(long)]
    max_age: Option<u32>,
    /// Where to write the record.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Serve Prometheus metrics on this address (`GET /metrics`).
    #[arg(long, value_name = "ADDR")]
    metrics: Option<String>,
    /// Record samples, commands and mode changes to this MCAP file.
    #[arg(long, value_name = "FILE")]
    record: Option<PathBuf>,
    #[command(flatten)]
    zenoh: transport::ZenohArgs,
}

/// Parse the process's arguments, run, and return the exit status.
pub fn main() -> std::process::ExitCode {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                // The OPC UA client logs each failed try of a session as errors (several a
                // second while a server refuses a certificate), and, with security None,
                // that it has no certificate it then needs none of. The bridge says itself
                // what matters, once: the server's last reason, which certificate to trust
                // where, a password in plain text. RUST_LOG=opcua_client=debug shows it all.
                .unwrap_or_else(|_| {
                    "info,zenoh=warn,opcua_crypto=off,opcua_core=off,opcua_client=off".into()
                }),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a terminal: not into files or the journal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    let result = match Cli::parse().command {
        Command::Run(args) => run(args),
        Command::Gateway(args) => gateway(args),
        Command::Probe {
            what: ProbeCommand::Modbus(a),
        } => fieldbus::probe::modbus(
            &a.address,
            a.unit,
            a.kind,
            a.start,
            a.count,
            std::time::Duration::from_millis(a.timeout_ms),
        )
        .map(|table| {
            print!("{table}");
            0
        })
        .map_err(Into::into),
        Command::Probe {
            what: ProbeCommand::Opcua(a),
        } => probe_opcua(a),
    };
    match result {
        Ok(code) => std::process::ExitCode::from(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn run(args: RunArgs) -> Result<u8> {
    let (mut file, source) = match &args.config {
        Some(p) => (AgentFile::load(p)?, p.clone()),
        None => (AgentFile::default(), PathBuf::from("(flags)")),
    };
    if let (Some(m), Some(p)) = (&mut file.metrics, &args.config) {
        m.resolve(p.parent().unwrap_or(std::path::Path::new(".")));
    }
    if let Some(d) = args.device {
        file.device = Some(d);
    }
    if let Some(s) = args.scenario {
        file.scenario = s;
    }
    if let Some(c) = args.controller {
        file.controller = Some(c);
    }
    if args.duration.is_some() {
        file.duration = args.duration;
    }
    if let Some(h) = args.hold_periods {
        file.hold_periods = h;
    }
    if let Some(f) = args.fallback {
        file.fallback = f;
    }
    if let Some(a) = args.max_age {
        file.max_age = a;
    }
    if let Some(o) = args.out {
        file.out = o;
    }
    if let Some(m) = args.metrics {
        file.metrics = Some(telemetry::MetricsSpec {
            listen: m,
            ..file.metrics.unwrap_or_default()
        });
    }
    if let Some(p) = args.record {
        file.record = Some(telemetry::RecordSpec::at(p));
    }
    let mut r = file.resolve(&source)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let run = runtime.block_on(async {
        // First, before the plant opens (a driver may take seconds to say hello) and before
        // the session: a stop requested meanwhile is kept, and the plant gets its safe stop
        // and the record at once instead of the process dying with nothing written.
        let mut shutdown = Box::pin(transport::shutdown_signal());
        let plant = agent::open_plant(&r.scenario, r.scenario.seed)
            .await
            .context("opening the plant")?;
        // A client of a router retries until the router answers (start order must not
        // matter), and a stop meanwhile must still be a safe stop, not a hang.
        let opened = tokio::select! {
            s = args.zenoh.open() => Some(s),
            _ = &mut shutdown => None,
        };
        let session = match opened {
            Some(Ok(s)) => s,
            Some(Err(e)) => {
                // The plant was opened: give it its safe stop before giving up.
                let _ = agent::PlantThread::spawn(plant).stop().await;
                return Err(anyhow::Error::from(e));
            }
            None => {
                let stopped = agent::PlantThread::spawn(plant).stop().await;
                return Ok(agent::never_started(&r.loop_config, stopped));
            }
        };
        let started = observe::start(file.metrics.as_ref(), file.record.as_ref()).await?;
        r.loop_config.observers = started.observers.clone();
        let out = agent::run_loop(&session, plant, &r.loop_config, run_id(), shutdown).await;
        started.finish().await;
        let _ = session.close().await;
        Ok(out?)
    });
    // zenoh's open may still be retrying on a worker: do not wait for it.
    runtime.shutdown_background();
    let run = run?;
    let title = format!("{} — {} over Zenoh", r.scenario.name, run.report.device_id);
    write_run(&r.out, &title, &run.record, &run.report)
        .with_context(|| format!("writing the record to {}", r.out.display()))?;
    print_report(&run.report);
    println!(
        "wrote {}/{{run.csv, summary.json, *.png, *.svg}}",
        r.out.display()
    );
    Ok(run.report.exit_code())
}

fn gateway(args: GatewayArgs) -> Result<u8> {
    let mut g = crate::gateway::GatewayFile::load(&args.config)?;
    if let Some(m) = &mut g.metrics {
        m.resolve(args.config.parent().unwrap_or(std::path::Path::new(".")));
    }
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let runs = runtime.block_on(async {
        let shutdown = Box::pin(transport::shutdown_signal());
        let mut plants = Vec::with_capacity(g.plants.len());
        for r in &g.plants {
            match agent::open_plant(&r.scenario, r.scenario.seed).await {
                Ok(p) => plants.push((p, r.loop_config.clone())),
                Err(e) => {
                    // The ones already open get their safe stop before giving up.
                    for (p, _) in plants {
                        let _ = agent::PlantThread::spawn(p).stop().await;
                    }
                    return Err(anyhow::anyhow!(
                        "opening the plant of {}: {e}",
                        r.loop_config.device_id
                    ));
                }
            }
        }
        let session = match args.zenoh.open().await {
            Ok(s) => s,
            Err(e) => {
                for (p, _) in plants {
                    let _ = agent::PlantThread::spawn(p).stop().await;
                }
                return Err(anyhow::Error::from(e));
            }
        };
        let started = observe::start(g.metrics.as_ref(), g.record.as_ref()).await?;
        for (_, cfg) in plants.iter_mut() {
            cfg.observers = started.observers.clone();
        }
        tracing::info!(gateway = %g.gateway, plants = plants.len(), "hosting");
        let runs = crate::gateway::run_gateway(
            &session,
            &g.gateway,
            plants,
            g.key.clone(),
            run_id,
            shutdown,
        )
        .await;
        started.finish().await;
        let _ = session.close().await;
        Ok(runs?)
    });
    runtime.shutdown_background();
    let mut code = 0u8;
    for (r, run) in g.plants.iter().zip(runs?) {
        match run {
            Ok(run) => {
                let out = g.out.join(&run.report.device_id);
                let title = format!(
                    "{} — {} via gateway {}",
                    r.scenario.name, run.report.device_id, g.gateway
                );
                write_run(&out, &title, &run.record, &run.report)
                    .with_context(|| format!("writing the record to {}", out.display()))?;
                print_report(&run.report);
                code = code.max(run.report.exit_code());
            }
            Err(e) => {
                eprintln!("{}: {e}", r.loop_config.device_id);
                code = code.max(4);
            }
        }
    }
    println!(
        "wrote {}/{{device}}/{{run.csv, summary.json, *.png, *.svg}}",
        g.out.display()
    );
    Ok(code)
}

fn print_report(r: &AgentReport) {
    println!("{}", r.headline());
    for c in &r.channels {
        println!(
            "  {:<18} rms {:.3e}  max {:.3e}  saturated {:.1}%",
            c.name,
            c.rms,
            c.max_abs,
            100.0 * c.saturated_fraction
        );
    }
    let k = &r.counters;
    println!(
        "  commands {} (late {}), missing {}, fallbacks {}, RTT p50 {:.0} us p99 {:.0} us",
        k.commands, k.late, k.missing, k.fallbacks, r.rtt_p50_us, r.rtt_p99_us
    );
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
