//! `faultlab`: the impairment relay as a command, and the fault-injection campaign.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use faultlab::campaign::{run_case, Campaign, CaseOptions};
use faultlab::profile::ProfileSet;
use faultlab::relay::{Link, Relay};
use indicatif::{ProgressBar, ProgressStyle};
use plant_agent::scenario::{load_scenario, shipped_controller};
use plotters::prelude::*;

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
    /// Run the service and simulated AEROs through the relay for every profile, over TCP
    /// and UDP, with the MFC and the tuned PID side by side.
    Campaign {
        /// Profile file (or `default` for the shipped set).
        #[arg(long, default_value = "default")]
        profiles: String,
        /// Output directory (campaign.md, campaign.json, plots).
        #[arg(long, default_value = "out/campaign")]
        out: PathBuf,
        /// Scenario (shortened to --duration).
        #[arg(long, default_value = "2")]
        scenario: String,
        /// Seconds per run.
        #[arg(long, default_value_t = 20.0)]
        duration: f64,
        /// Controllers, side by side on the same link.
        #[arg(long, value_delimiter = ',', default_value = "ipd,pid")]
        controllers: Vec<String>,
        /// Links.
        #[arg(long, value_delimiter = ',', default_value = "tcp,udp")]
        links: Vec<Link>,
    },
}

fn main() -> std::process::ExitCode {
    // `faultlab serve ARGS` runs the controller service itself (the same library code as
    // the `controller-service` binary), so the crash tests can kill -9 a real service
    // process built from this very tree.
    let mut args = std::env::args_os();
    if args.nth(1).is_some_and(|a| a == "serve") {
        return controller_service::cli::main_with_args(
            std::iter::once(std::ffi::OsString::from("controller-service")).chain(args),
        );
    }
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
        Command::Campaign {
            profiles,
            out,
            scenario,
            duration,
            controllers,
            links,
        } => {
            if !(duration.is_finite() && duration >= 2.0) {
                bail!("--duration must be at least 2 s");
            }
            let set = ProfileSet::load(&profiles)?;
            if !set.profiles.iter().any(|p| p.name == "none") {
                bail!("{profiles}: the campaign needs a profile named `none` (the unimpaired baseline)");
            }
            let mut s = load_scenario(&scenario)?;
            s.duration = duration;
            let sets = controllers
                .iter()
                .map(|c| shipped_controller(c))
                .collect::<Result<Vec<_>, _>>()?;
            let total = set.profiles.len() * links.len();
            let bar = ProgressBar::new(total as u64).with_style(
                ProgressStyle::with_template(
                    "{msg:<32} [{bar:30}] {pos}/{len} cases, {elapsed} ({eta} left)",
                )
                .expect("static template")
                .progress_chars("=> "),
            );
            let mut campaign = Campaign {
                scenario: s.name.clone(),
                duration,
                cases: Vec::new(),
            };
            for p in &set.profiles {
                for link in &links {
                    bar.set_message(format!("{} over {}", p.name, link.scheme()));
                    let r =
                        runtime.block_on(run_case(&s, &sets, p, *link, &CaseOptions::default()))?;
                    campaign.cases.extend(r);
                    bar.inc(1);
                }
            }
            bar.finish_and_clear();
            campaign.compute_ratios("none");
            std::fs::create_dir_all(&out).with_context(|| format!("creating {}", out.display()))?;
            let md = campaign.markdown();
            std::fs::write(out.join("campaign.md"), &md)?;
            std::fs::write(
                out.join("campaign.json"),
                serde_json::to_string_pretty(&campaign)? + "\n",
            )?;
            plots(&out, &campaign, &set)?;
            println!("{md}");
            println!("wrote {0}/campaign.md, {0}/campaign.json, {0}/rms_vs_loss.png|svg, {0}/rms_vs_latency.png|svg", out.display());
            Ok(())
        }
    }
}

/// Degradation curves: pitch RMS ratio against loss rate (pure-loss profiles) and against
/// round-trip latency (pure-latency profiles), one line per controller and link.
fn plots(out: &Path, c: &Campaign, set: &ProfileSet) -> Result<()> {
    let x_of = |name: &str, loss_axis: bool| -> Option<f64> {
        let p = set.profiles.iter().find(|p| p.name == name)?;
        let b = &p.both;
        let plain = b.burst.is_none() && b.outages.is_empty() && p.up.is_none() && p.down.is_none();
        if !plain {
            return None;
        }
        if loss_axis && b.delay_ms == 0.0 {
            Some(100.0 * b.loss)
        } else if !loss_axis && b.loss == 0.0 {
            Some(2.0 * b.delay_ms)
        } else {
            None
        }
    };
    for (file, loss_axis, xlabel) in [
        ("rms_vs_loss", true, "random loss each way (%)"),
        ("rms_vs_latency", false, "round-trip latency (ms)"),
    ] {
        let mut series: Vec<(String, Vec<(f64, f64)>)> = Vec::new();
        for case in &c.cases {
            let (Some(x), Some(y)) = (x_of(&case.profile, loss_axis), case.rms_ratio.get(1)) else {
                continue;
            };
            let name = format!("{} over {}", case.controller, case.link.scheme());
            match series.iter_mut().find(|(n, _)| *n == name) {
                Some((_, pts)) => pts.push((x, *y)),
                None => series.push((name, vec![(x, *y)])),
            }
        }
        for (_, pts) in &mut series {
            pts.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let xmax = series
            .iter()
            .flat_map(|(_, p)| p.iter().map(|x| x.0))
            .fold(1.0, f64::max);
        let ymax = series
            .iter()
            .flat_map(|(_, p)| p.iter().map(|x| x.1))
            .fold(2.0, f64::max)
            * 1.1;
        plant_agent::plot::ensure_font();
        let png = out.join(format!("{file}.png"));
        let svg = out.join(format!("{file}.svg"));
        draw(
            BitMapBackend::new(&png, (900, 600)).into_drawing_area(),
            &series,
            xlabel,
            xmax,
            ymax,
        )?;
        draw(
            SVGBackend::new(&svg, (900, 600)).into_drawing_area(),
            &series,
            xlabel,
            xmax,
            ymax,
        )?;
    }
    Ok(())
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, plotters::coord::Shift>,
    series: &[(String, Vec<(f64, f64)>)],
    xlabel: &str,
    xmax: f64,
    ymax: f64,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let e = |err: DrawingAreaErrorKind<DB::ErrorType>| anyhow::anyhow!("plot: {err:?}");
    root.fill(&WHITE).map_err(e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Pitch tracking under faults (RMS / unimpaired RMS)",
            ("sans-serif", 22),
        )
        .margin(15)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..xmax, 0.0..ymax)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(xlabel)
        .y_desc("RMS ratio")
        .draw()
        .map_err(e)?;
    let colors = [BLUE, RED, GREEN, MAGENTA, CYAN, BLACK];
    for (i, (name, pts)) in series.iter().enumerate() {
        let color = colors[i % colors.len()];
        chart
            .draw_series(LineSeries::new(pts.iter().copied(), color.stroke_width(2)))
            .map_err(e)?
            .label(name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        chart
            .draw_series(pts.iter().map(|p| Circle::new(*p, 4, color.filled())))
            .map_err(e)?;
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .map_err(e)?;
    root.present().map_err(e)?;
    Ok(())
}
