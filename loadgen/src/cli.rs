//! The command line: `loadgen echo`, `loadgen run`, `loadgen bench`. It lives in the
//! library so that the binary is one line.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand};
use transport::ZenohArgs;

#[derive(Parser)]
#[command(
    name = "loadgen",
    version,
    about = "Load generator and benchmark for the controller service"
)]
pub struct LoadgenCli {
    #[command(subcommand)]
    pub cmd: Cmd,
}

#[derive(Subcommand)]
pub enum Cmd {
    /// Serve as the echo anchor: answer every sample (or batch) with a command of the same seq.
    Echo {
        #[command(flatten)]
        zenoh: ZenohArgs,
    },
    /// Run simulated plants against a controller already on the network and report.
    Run {
        /// Number of plants (ids load-0 ... load-{N-1}).
        #[arg(long, default_value_t = 100)]
        devices: usize,
        /// Samples per plant per second.
        #[arg(long, default_value_t = 100.0)]
        rate: f64,
        /// 0: each plant on its own key; otherwise the number of gateways sharing them.
        #[arg(long, default_value_t = 0)]
        gateways: usize,
        /// Warm-up before counting (s).
        #[arg(long, default_value_t = 3.0)]
        warmup: f64,
        /// Counted window (s).
        #[arg(long, default_value_t = 10.0)]
        measure: f64,
        /// Earlier samples each sample carries again, as a real agent's `resend` (0 to 3;
        /// agents default to 3).
        #[arg(long, default_value_t = 0)]
        resend: usize,
        /// Print the report as JSON.
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        zenoh: ZenohArgs,
    },
    /// The benchmark: the service and the echo anchor side by side, swept over fleet sizes,
    /// per device and through gateways. Writes bench.json and bench.md.
    Bench {
        /// Where the results go.
        #[arg(long, default_value = "loadgen-results")]
        out: PathBuf,
        /// The controller-service binary (default: beside this program).
        #[arg(long)]
        service_bin: Option<PathBuf>,
        /// The service's workers (`--workers`). Default 1: on two cores shared with the
        /// generator and the anchor, a second worker costs more in scheduling than it gives.
        #[arg(long, default_value_t = 1)]
        service_workers: usize,
        #[arg(long, default_value_t = 100.0)]
        rate: f64,
        #[arg(long, default_value_t = 3.0)]
        warmup: f64,
        #[arg(long, default_value_t = 10.0)]
        measure: f64,
        /// Fleet sizes of the per-device sweep.
        #[arg(long, value_delimiter = ',', default_value = "50,75,100,150")]
        per_device: Vec<usize>,
        /// Fleet sizes of the gateway sweep; given with no sizes, no gateway sweep (to
        /// measure only the per-device path, as `--repeat` for the p99 does).
        #[arg(
            long,
            value_delimiter = ',',
            num_args = 0..,
            default_value = "5000,7500,10000,12500,15000,17500,20000"
        )]
        gateway_devices: Vec<usize>,
        /// Plants per gateway.
        #[arg(long, default_value_t = 1000)]
        per_gateway: usize,
        /// Bisection steps after each grid.
        #[arg(long, default_value_t = 1)]
        refine: usize,
        /// Fraction of commands back within the period for a size to hold.
        #[arg(long, default_value_t = 0.999)]
        inside: f64,
        /// Rounds at each size, both targets in each (alternating order); the medians of
        /// the rounds decide.
        #[arg(long, default_value_t = 3)]
        rounds: usize,
        /// The per-device fleet size whose p99 round trips are compared.
        #[arg(long, default_value_t = 100)]
        p99_at: usize,
        /// Run the service with keys: samples and batches sealed, commands checked (the
        /// echo anchor stays open), to measure what the proof of origin costs.
        #[arg(long)]
        auth: bool,
        /// Run the whole benchmark this many times in a row, each into its own
        /// `run-K` directory under `--out`, and report the median over the runs of the
        /// service's p99 over the echo's at `--p99-at` devices (one run's p99 ratio moves
        /// with the machine by more than the service does); written to `repeated.md`.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
        repeat: u32,
    },
    /// A real Prometheus server scraping the service while it serves plants through
    /// gateways: series, exposition size and scrape time for the default metrics and
    /// for series on every device, beside a service without metrics. Writes scrape.json
    /// and scrape.md.
    Scrape(ScrapeArgs),
}

/// `loadgen scrape`'s arguments.
#[derive(clap::Args)]
pub struct ScrapeArgs {
    /// Where the results go.
    #[arg(long, default_value = "loadgen-results/scrape")]
    out: PathBuf,
    /// The controller-service binary (default: beside this program).
    #[arg(long)]
    service_bin: Option<PathBuf>,
    /// The Prometheus server.
    #[arg(long, default_value = "prometheus")]
    prometheus: PathBuf,
    /// Plants (ids load-0 ... load-{N-1}).
    #[arg(long, default_value_t = 10_000)]
    devices: usize,
    /// Gateways sharing them.
    #[arg(long, default_value_t = 10)]
    gateways: usize,
    /// Samples per plant per second.
    #[arg(long, default_value_t = 100.0)]
    rate: f64,
    /// Prometheus's scrape interval (s).
    #[arg(long, default_value_t = 5.0)]
    interval: f64,
    /// How long the plants run (s).
    #[arg(long, default_value_t = 30.0)]
    duration: f64,
}

/// Parse `args`, run, and return the exit code.
pub fn main_with_args<I, T>(args: I) -> std::process::ExitCode
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=error".into()),
        )
        .with_writer(std::io::stderr)
        .try_init();
    let cli = match LoadgenCli::try_parse_from(args) {
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
    runtime.shutdown_background();
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn secs(what: &str, s: f64) -> Result<Duration> {
    Duration::try_from_secs_f64(s)
        .with_context(|| format!("--{what} must be a duration in seconds"))
}

async fn run(cli: LoadgenCli) -> Result<()> {
    match cli.cmd {
        Cmd::Echo { zenoh } => {
            let stop = transport::shutdown_signal();
            let session = zenoh.open().await?;
            crate::echo::serve(session, stop)
                .await
                .map_err(|e| anyhow::anyhow!("echo: {e}"))?;
        }
        Cmd::Run {
            devices,
            rate,
            gateways,
            warmup,
            measure,
            resend,
            json,
            zenoh,
        } => {
            let session = zenoh.open().await?;
            let spec = crate::gen::Spec {
                devices,
                rate_hz: rate,
                gateways,
                prefix: "load".into(),
                warmup: secs("warmup", warmup)?,
                measure: secs("measure", measure)?,
                resend,
                secret: None,
            };
            let r = crate::gen::run(&session, &spec).await?;
            let _ = session.close().await;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!(
                    "{} devices, {} gateways: sent {}, answered {:.3} %, within the period {:.3} %, control {}, duplicates {}, p50/p99/p99.9 {:?}/{:?}/{:?} us, generator late {}",
                    r.devices, r.gateways, r.sent, 100.0 * r.answered_fraction(), 100.0 * r.within_fraction(),
                    r.control, r.duplicates, r.p50_us, r.p99_us, r.p999_us, r.generator_late
                );
            }
        }
        Cmd::Bench {
            out,
            service_bin,
            service_workers,
            rate,
            warmup,
            measure,
            per_device,
            gateway_devices,
            per_gateway,
            refine,
            inside,
            rounds,
            p99_at,
            auth,
            repeat,
        } => {
            let me = std::env::current_exe().context("locating this program")?;
            let service_bin =
                service_bin.unwrap_or_else(|| me.with_file_name("controller-service"));
            let spec = crate::bench::BenchSpec {
                service_bin,
                service_workers,
                loadgen_bin: me,
                rate_hz: rate,
                warmup: secs("warmup", warmup)?,
                measure: secs("measure", measure)?,
                per_device,
                gateway_devices,
                per_gateway,
                refine,
                inside,
                rounds,
                p99_at,
                out: out.clone(),
                auth,
            };
            if repeat == 1 {
                let r = crate::bench::run(&spec).await?;
                println!("{}", crate::bench::markdown(&r));
            } else {
                bench_repeated(spec, repeat).await?;
            }
            eprintln!("results in {}", out.display());
        }
        Cmd::Scrape(args) => scrape(args).await?,
    }
    Ok(())
}

/// `loadgen bench --repeat N`: the benchmark `n` times, each run into `run-K` under the
/// spec's `out`, then the runs' p99 ratios and their median into `repeated.md` there.
async fn bench_repeated(mut spec: crate::bench::BenchSpec, n: u32) -> Result<()> {
    let out = spec.out.clone();
    let mut runs = Vec::new();
    for k in 1..=n {
        spec.out = out.join(format!("run-{k}"));
        eprintln!("run {k} of {n}, into {}", spec.out.display());
        let r = crate::bench::run(&spec).await?;
        println!("{}", crate::bench::markdown(&r));
        runs.push(r);
    }
    let md = crate::bench::repeated_markdown(&runs);
    std::fs::write(out.join("repeated.md"), &md)
        .with_context(|| format!("writing {}", out.join("repeated.md").display()))?;
    println!("{md}");
    Ok(())
}

async fn scrape(args: ScrapeArgs) -> Result<()> {
    let ScrapeArgs {
        out,
        service_bin,
        prometheus,
        devices,
        gateways,
        rate,
        interval,
        duration,
    } = args;
    let me = std::env::current_exe().context("locating this program")?;
    let spec = crate::scrape::ScrapeSpec {
        service_bin: service_bin.unwrap_or_else(|| me.with_file_name("controller-service")),
        prometheus_bin: prometheus,
        devices,
        gateways,
        rate_hz: rate,
        interval: secs("interval", interval)?,
        duration: secs("duration", duration)?,
        variants: vec![
            ("none".into(), None),
            ("default".into(), Some(String::new())),
            (
                "per_device".into(),
                Some(format!("per_device = true\nmax_devices = {devices}")),
            ),
        ],
        out: out.clone(),
    };
    let r = crate::scrape::run(&spec).await?;
    println!("{}", crate::scrape::markdown(&spec, &r));
    eprintln!("results in {}", out.display());
    Ok(())
}
