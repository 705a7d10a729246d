//! `plant-agent`: the command line. Thin: parsing, progress and printing; the work is in the
//! library.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use plant_agent::agent::{run_agent, AgentReport, Fallback};
use plant_agent::compare::compare;
use plant_agent::demo::{agent_config, demo, plot_rows, rand_id, DemoOptions};
use plant_agent::offline::run;
use plant_agent::output::write_run;
use plant_agent::plant::{DriverPlant, Plant, SimPlant};
use plant_agent::scenario::{
    load_controller, load_scenario, shipped_controller, ControllerSet, SHIPPED_CONTROLLERS,
    SHIPPED_SCENARIOS,
};
use plant_agent::tune::{starting_point, tune, KINDS};

#[derive(Parser)]
#[command(
    name = "plant-agent",
    version,
    about = "Model-free control of the Quanser AERO: simulation, tuning, comparison"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Clone, Copy, clap::ValueEnum)]
enum PlantKind {
    /// The simulated Quanser AERO.
    AeroSim,
    /// An external driver process (see `plant-agent/DRIVER.md`).
    Driver,
}

/// What `demo` and `run` share: the scenario, the controller and the safety settings.
#[derive(clap::Args)]
struct LoopArgs {
    /// Scenario file, or a shipped one: 1, 2, 3, 4 (references, duration, plant).
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Shipped controller, also the local fallback (default: the scenario's).
    #[arg(long)]
    controller: Option<String>,
    /// Periods to hold the last command before falling back.
    #[arg(long, default_value_t = 5)]
    hold_periods: u32,
    /// What to fall back to.
    #[arg(long, value_enum, default_value = "local")]
    fallback: Fallback,
}

impl LoopArgs {
    fn load(&self) -> Result<(plant_agent::scenario::Scenario, ControllerSet)> {
        let scenario = load_scenario(&self.scenario)?;
        let set = match &self.controller {
            Some(k) => shipped_controller(k)?,
            None => scenario.controller.clone(),
        };
        Ok((scenario, set))
    }
}

#[derive(Subcommand)]
enum Command {
    /// Run a scenario closed-loop offline (no network), or compare every controller.
    Sim {
        /// Scenario file, or a shipped one: 1, 2, 3, 4.
        #[arg(long, default_value = "2")]
        scenario: String,
        /// Shipped controller: ip, ipi, ipd, ipd-tuned, pid, adrc. Default: the scenario's.
        #[arg(long, conflicts_with = "controller_file")]
        controller: Option<String>,
        /// Controller file, as written by `tune`.
        #[arg(long)]
        controller_file: Option<PathBuf>,
        /// Output directory.
        #[arg(long, default_value = "out/sim")]
        out: PathBuf,
        /// Run every controller on the four shipped scenarios and print the table.
        #[arg(long)]
        compare: bool,
    },
    /// Run the main job: a controller service and N simulated AEROs over Zenoh on loopback.
    Demo {
        /// Number of simulated plants.
        #[arg(long, default_value_t = 2)]
        plants: usize,
        #[command(flatten)]
        lp: LoopArgs,
        /// Output directory (per plant: run.csv, summary.json, plots).
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
    },
    /// Bridge one plant to a controller service over Zenoh.
    Run {
        /// Device id.
        #[arg(long)]
        device: String,
        /// The plant: the simulated AERO, or an external driver process.
        #[arg(long, value_enum, default_value = "aero-sim")]
        plant: PlantKind,
        /// Driver command line (for --plant driver), e.g. "python3 aero_hil.py".
        #[arg(long)]
        driver: Option<String>,
        #[command(flatten)]
        lp: LoopArgs,
        /// Where to write the run (run.csv, summary.json, plots).
        #[arg(long, default_value = "out/run")]
        out: PathBuf,
        #[command(flatten)]
        zenoh: transport::ZenohArgs,
    },
    /// Print a controller-service configuration that serves these devices on a scenario.
    ServiceConfig {
        /// Device ids, comma-separated.
        #[arg(long, value_delimiter = ',', required = true)]
        devices: Vec<String>,
        /// Scenario whose references and output maps to use.
        #[arg(long, default_value = "2")]
        scenario: String,
        /// Shipped controller (default: the scenario's).
        #[arg(long)]
        controller: Option<String>,
    },
    /// Serve the driver protocol on stdin/stdout with a simulated AERO (reference driver).
    SimDriver {
        /// Noise seed.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Add the paper's 4 g mass.
        #[arg(long)]
        added_mass: bool,
    },
    /// Tune one controller kind on one scenario with a fixed budget of simulated runs.
    Tune {
        /// Scenario file, or a shipped one: 1, 2, 3, 4.
        #[arg(long, default_value = "1")]
        scenario: String,
        /// Controller kind: ip, ipi, ipd, pid, adrc.
        #[arg(long)]
        controller: String,
        /// Where to write the tuned controller (TOML, usable by `sim --controller-file`).
        #[arg(long)]
        out: PathBuf,
        /// Number of simulated runs (the same for every kind makes the comparison fair).
        #[arg(long, default_value_t = 150)]
        budget: usize,
        /// Seed of the random phase.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Name of the written controller set. Default: the kind.
        #[arg(long)]
        name: Option<String>,
    },
}

fn main() -> std::process::ExitCode {
    match real_main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn print_reports(reports: &[AgentReport], offline: Option<&plant_agent::metrics::Summary>) {
    if let Some(first) = reports.first() {
        print!("| plant |");
        for c in &first.channels {
            print!(" {} RMS |", c.name);
        }
        println!(" RTT p50 (us) | RTT p99 (us) | missing | late | fallbacks |");
        println!(
            "|---|{}---:|---:|---:|---:|---:|",
            "---:|".repeat(first.channels.len())
        );
    }
    if let Some(o) = offline {
        print!("| offline (no network) |");
        for c in &o.channels {
            print!(" {:.3e} |", c.rms);
        }
        println!(" - | - | - | - | - |");
    }
    for r in reports {
        print!("| {} |", r.device_id);
        for c in &r.channels {
            print!(" {:.3e} |", c.rms);
        }
        println!(
            " {:.0} | {:.0} | {} | {} | {} |",
            r.rtt_p50_us, r.rtt_p99_us, r.missing, r.late, r.fallbacks
        );
    }
}

fn real_main() -> Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| "info,zenoh=warn".into()),
        )
        .with_writer(std::io::stderr)
        .init();
    match Cli::parse().command {
        Command::Demo { plants, lp, out } => {
            if plants == 0 || plants > 64 {
                bail!("--plants must be between 1 and 64");
            }
            let (scenario, set) = lp.load()?;
            let (hold_periods, fallback) = (lp.hold_periods, lp.fallback);
            let offline = run(&scenario, &set, false)?.summary;
            println!(
                "{}: {} simulated AERO(s) and a controller service over Zenoh on loopback, {:.0} s in real time...",
                scenario.name, plants, scenario.duration
            );
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()?;
            let reports = runtime.block_on(demo(
                &scenario,
                &set,
                &DemoOptions {
                    plants,
                    hold_periods,
                    fallback,
                    out: Some(out.clone()),
                },
            ))?;
            print_reports(&reports, Some(&offline));
            println!(
                "wrote {}/aero-*/{{run.csv, summary.json, *.png, *.svg}}",
                out.display()
            );
            Ok(())
        }
        Command::Run {
            device,
            plant,
            driver,
            lp,
            out,
            zenoh,
        } => {
            let (scenario, set) = lp.load()?;
            let (hold_periods, fallback) = (lp.hold_periods, lp.fallback);
            let mut plant: Box<dyn Plant> = match plant {
                PlantKind::AeroSim => {
                    Box::new(SimPlant::new(scenario.plant.clone(), scenario.seed)?)
                }
                PlantKind::Driver => {
                    let line = driver.context("--plant driver needs --driver \"COMMAND ARGS\"")?;
                    let mut words = line.split_whitespace().map(str::to_string);
                    let program = words.next().context("--driver is empty")?;
                    let args: Vec<String> = words.collect();
                    Box::new(DriverPlant::spawn(
                        &program,
                        &args,
                        std::time::Duration::from_secs_f64((scenario.period * 5.0).max(0.5)),
                    )?)
                }
            };
            let config = agent_config(
                &scenario,
                &set,
                &device,
                hold_periods,
                fallback,
                Some(out.join("run.csv")),
            );
            let runtime = tokio::runtime::Builder::new_multi_thread()
                .enable_all()
                .build()?;
            let (report, rows) = runtime.block_on(async {
                let session = zenoh.open().await?;
                let r = run_agent(&session, plant.as_mut(), &config, rand_id(0)).await;
                let _ = session.close().await;
                anyhow::Ok(r?)
            })?;
            plot_rows(&out, &scenario, &report, &rows)?;
            print_reports(std::slice::from_ref(&report), None);
            println!(
                "wrote {}/{{run.csv, summary.json, *.png, *.svg}}",
                out.display()
            );
            Ok(())
        }
        Command::ServiceConfig {
            devices,
            scenario,
            controller,
        } => {
            let scenario = load_scenario(&scenario)?;
            let set = match controller {
                Some(k) => shipped_controller(&k)?,
                None => scenario.controller.clone(),
            };
            let config = plant_agent::demo::service_config(&scenario, &set, &devices);
            config.check("(generated)")?;
            println!(
                "# controller-service configuration: {} on {} for {}\n{}",
                set.name,
                scenario.name,
                devices.join(", "),
                toml::to_string_pretty(&config)?
            );
            Ok(())
        }
        Command::SimDriver { seed, added_mass } => {
            let mut params = plant_agent::aero::AeroParams::default();
            if added_mass {
                params.added_mass = plant_agent::aero::PAPER_ADDED_MASS;
            }
            let stdin = std::io::stdin();
            plant_agent::plant::serve_sim_driver(
                params,
                seed,
                stdin.lock(),
                std::io::stdout().lock(),
            )?;
            Ok(())
        }
        Command::Sim {
            scenario,
            controller,
            controller_file,
            out,
            compare: true,
        } => {
            if controller.is_some() || controller_file.is_some() || scenario != "2" {
                bail!("--compare runs every shipped controller on every shipped scenario: drop --scenario/--controller");
            }
            sim_compare(&out)
        }
        Command::Sim {
            scenario,
            controller,
            controller_file,
            out,
            compare: false,
        } => {
            let scenario = load_scenario(&scenario)?;
            let set = match (controller, controller_file) {
                (Some(kind), _) => shipped_controller(&kind)?,
                (None, Some(file)) => load_controller(&file.to_string_lossy())?,
                (None, None) => scenario.controller.clone(),
            };
            let r = run(&scenario, &set, true)?;
            write_run(&out, &scenario, &r)?;
            println!("{} with {}:", scenario.name, set.name);
            for c in &r.summary.channels {
                println!(
                    "  {:<18} rms {:.3e}  max {:.3e}  iae {:.3e}  saturated {:.1}%  chatter {:.2} V",
                    c.name,
                    c.rms,
                    c.max_abs,
                    c.iae,
                    100.0 * c.saturated_fraction,
                    c.control_variation
                );
            }
            println!(
                "wrote {}/{{timeseries.csv, summary.json, *.png, *.svg}}",
                out.display()
            );
            Ok(())
        }
        Command::Tune {
            scenario,
            controller,
            out,
            budget,
            seed,
            name,
        } => {
            if budget == 0 {
                bail!("--budget must be at least 1");
            }
            let scenario = load_scenario(&scenario)?;
            let start = starting_point(&controller).with_context(|| {
                format!(
                    "unknown controller kind `{controller}` (known: {})",
                    KINDS.join(", ")
                )
            })?;
            let bar = ProgressBar::new(budget as u64).with_style(
                ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} runs ({eta})")
                    .expect("static template")
                    .progress_chars("=> "),
            );
            let tuned = tune(&scenario, &start, budget, seed, |done, best| {
                bar.set_position(done as u64);
                bar.set_message(format!("tuning {controller}: best {best:.4}"));
            })?;
            bar.finish_and_clear();
            let mut set = tuned.set;
            if let Some(name) = &name {
                set.name = name.clone();
            }
            let text = toml::to_string_pretty(&set)?;
            if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
                std::fs::create_dir_all(dir)?;
            }
            let command = format!(
                "plant-agent tune --scenario {} --controller {controller} --budget {budget} --seed {seed}{}",
                scenario.name,
                name.as_ref().map(|n| format!(" --name {n}")).unwrap_or_default()
            );
            std::fs::write(&out, format!("# Written by `{command}`.\n{text}"))
                .with_context(|| format!("writing {}", out.display()))?;
            println!(
                "{controller} on {}: objective {:.4} (start {:.4}) in {} runs; wrote {}",
                scenario.name,
                tuned.cost,
                tuned.start_cost,
                tuned.runs,
                out.display()
            );
            Ok(())
        }
    }
}

fn sim_compare(out: &std::path::Path) -> Result<()> {
    let scenarios = SHIPPED_SCENARIOS
        .iter()
        .map(|(n, _, _)| load_scenario(n))
        .collect::<Result<Vec<_>, _>>()?;
    let controllers = SHIPPED_CONTROLLERS
        .iter()
        .map(|(k, _)| shipped_controller(k))
        .collect::<Result<Vec<ControllerSet>, _>>()?;
    let bar = ProgressBar::new((scenarios.len() * controllers.len()) as u64).with_style(
        ProgressStyle::with_template("{msg:<28} [{bar:30}] {pos}/{len} runs")
            .expect("static template")
            .progress_chars("=> "),
    );
    let cmp = compare(&scenarios, &controllers, |s, c| {
        bar.set_message(format!("{s} / {c}"));
        bar.inc(1);
    })?;
    bar.finish_and_clear();
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let md = format!(
        "{}\nRMS with the 4 g mass over RMS without (no retuning):\n\n{}",
        cmp.markdown(),
        cmp.mass_markdown()
    );
    std::fs::write(out.join("comparison.md"), &md)?;
    std::fs::write(
        out.join("comparison.json"),
        serde_json::to_string_pretty(&cmp)? + "\n",
    )?;
    println!("{md}");
    println!(
        "wrote {0}/comparison.md and {0}/comparison.json",
        out.display()
    );
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
