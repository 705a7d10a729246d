//! The `mfc-lab` command line. Thin: parsing, progress and printing; the work is in the
//! library.

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use faultlab::profile::ProfileSet;
use faultlab::relay::Link;
use plant::progress::ProgressBoard;
use plant::record::write_run;
use plant::scenario::{
    load_controller, load_scenario, shipped_controller, ControllerSet, Scenario,
    SHIPPED_CONTROLLERS, SHIPPED_SCENARIOS,
};
use plant_agent::agent::AgentReport;
use plant_agent::safety::{parse_fallback, FallbackPolicy, SafetyConfig};

use crate::campaign::{run_case, Campaign, CaseOptions};
use crate::compare::compare;
use crate::demo::{demo, DemoOptions};
use crate::harness::service_config;
use crate::offline::{simulate, simulate_timed, IoTiming, OfflineSummary};
use crate::tune::{starting_point, tune, KINDS};

#[derive(Parser)]
#[command(
    name = "mfc-lab",
    version,
    about = "Model-free control bench: simulate, tune, compare, demo over Zenoh, fault campaign"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Run a scenario closed-loop offline, in lockstep (no network, no real time), or
    /// compare every shipped controller on the shipped AERO scenarios.
    Sim(SimArgs),
    /// Run the main job: a controller service and N simulated plants over Zenoh on
    /// loopback, in real time.
    Demo(DemoArgs),
    /// Re-run a controller service's MCAP recording through the controller, offline, and
    /// say whether the commands match the recorded ones: a regression check. Exit status
    /// 0 when they match, 1 when they differ.
    Replay(ReplayArgs),
    /// Tune one controller with a fixed budget of offline runs.
    Tune(TuneArgs),
    /// Run the service and simulated plants through the impairment relay for every
    /// profile, over TCP and UDP, with several controllers side by side.
    Campaign(CampaignArgs),
    /// The networked loop in lockstep (the service's and the agent's own rules, a seeded
    /// model of the link): each controller under each loss rate and each round trip, as
    /// an RMS ratio against itself on a perfect link. Fast and repeatable; the campaign
    /// measures the real network.
    Netsim(NetsimArgs),
    /// Print a controller-service configuration that serves these devices on a scenario.
    ServiceConfig(ServiceConfigArgs),
    /// The robustness benchmark: every controller, untouched, on a seeded family of
    /// variations of the AERO (slower rotors, added mass, springs, damping, noise, motor
    /// gains, encoders), each against its own nominal run: a table and a heat map.
    Robust(RobustArgs),
    /// Commissioning offline: from a controller whose alpha is wrong (--alpha-scale), find
    /// alpha and the order of every intelligent channel from the plant's response to a
    /// bounded square wave, then run the scenario with what was found, against --compare
    Commission(CommissionArgs),
}

#[derive(clap::Args)]
struct CommissionArgs {
    /// Scenario: a shipped AERO one or a file (any plant).
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Controller to commission (default: the scenario's).
    #[arg(long)]
    controller: Option<String>,
    /// Multiply every intelligent channel's alpha by this first (a deliberately wrong start).
    #[arg(long, default_value_t = 1.0)]
    alpha_scale: f64,
    /// Square-wave half height per channel, in the law's units (one value: every channel).
    #[arg(long, value_delimiter = ',', required = true)]
    amplitude: Vec<f64>,
    /// Square-wave period per channel (s).
    #[arg(long, value_delimiter = ',', required = true)]
    period: Vec<f64>,
    /// Largest |y - y0| allowed per channel; beyond it the run aborts.
    #[arg(long, value_delimiter = ',', required = true)]
    max_deviation: Vec<f64>,
    /// Periods of the square wave.
    #[arg(long, default_value_t = 4)]
    cycles: u32,
    /// The estimator's window per channel, in intervals (default: the channel's own). A
    /// plant with a dead time needs a window longer than it: each estimate after a switch
    /// must see the response.
    #[arg(long, value_delimiter = ',')]
    window: Vec<usize>,
    /// Let each run choose the model's order (the better fit); by default it keeps the
    /// order of the law in force and reports the other's fit.
    #[arg(long)]
    choose_order: bool,
    /// Controllers whose RMS on the scenario the commissioned one is compared with.
    #[arg(long, value_delimiter = ',')]
    compare: Vec<String>,
    /// Commission on the running plant through the controller service instead (an
    /// in-process service and the plant behind its agent, in real time over Zenoh, each
    /// channel started, followed and confirmed as `mfcctl commission` does); the
    /// comparison is offline as without it.
    #[arg(long)]
    live: bool,
    /// With --live: the channels to commission, in this order (default: every
    /// intelligent one, in index order).
    #[arg(long, value_delimiter = ',', requires = "live")]
    channels: Vec<usize>,
    /// Output directory (commission.md, the commissioned controller as a file).
    #[arg(long, default_value = "out/commission")]
    out: PathBuf,
}

#[derive(clap::Args)]
struct RobustArgs {
    /// Scenario: a shipped AERO one or a file (the AERO simulator, or the heater's or the
    /// DC motor's driver).
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Controllers, comma-separated (shipped names or files). Default: every shipped AERO
    /// one; a driver plant's must be named.
    #[arg(long, value_delimiter = ',')]
    controllers: Vec<String>,
    /// Random combinations of every factor, after the one-factor variations.
    #[arg(long, default_value_t = 8)]
    random: usize,
    /// Seed of the random combinations.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Controllers the others must not lose to on any variation.
    #[arg(long, value_delimiter = ',', default_value = "pid,adrc")]
    baselines: Vec<String>,
    /// AERO factors to vary, comma-separated (rotor, mass, spring, damping, noise, motor,
    /// encoder). Default: all.
    #[arg(long, value_delimiter = ',')]
    factors: Vec<String>,
    /// Controllers held to the bars: exit status 1 if one's worst RMS ratio exceeds
    /// --bound, a baseline does better on some variation, or a run is unsafe.
    #[arg(long, value_delimiter = ',')]
    check: Vec<String>,
    /// The largest RMS over nominal that --check accepts.
    #[arg(long, default_value_t = 2.0)]
    bound: f64,
    /// Threads (default: the machine's cores).
    #[arg(long)]
    threads: Option<NonZeroUsize>,
    /// Output directory (robust.md, robust.json, robust-heatmap.svg).
    #[arg(long, default_value = "out/robust")]
    out: PathBuf,
}

#[derive(clap::Args)]
struct SimArgs {
    /// Scenario file (any plant, including a driver), or a shipped AERO one: 1, 2, 3, 4.
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Controller: a controller file (as written by `tune`) or a shipped AERO name (ip,
    /// ipi, ipd, ipd-hold, ipd-plain, ipd-tuned, ipd-fast, ipd-lag, ipd-quiet, pid,
    /// adrc). Default: the scenario's.
    #[arg(long)]
    controller: Option<String>,
    /// Output directory.
    #[arg(long, default_value = "out/sim")]
    out: PathBuf,
    /// Run every shipped controller on the four shipped scenarios and print the table;
    /// with --scenario and --controllers, those instead. In lockstep: not with
    /// --value-age-ms or --write-delay-ms.
    #[arg(long)]
    compare: bool,
    /// With --compare: controller files or shipped names, comma-separated.
    #[arg(long, value_delimiter = ',', requires = "compare")]
    controllers: Vec<String>,
    /// Run length (s), instead of the scenario's: the offline twin of a shortened live
    /// run (`plant-agent run --duration`).
    #[arg(long, conflicts_with = "compare")]
    duration: Option<f64>,
    /// Actuator maps: `scenario` (the files' own: the smooth dead-zone compensation on
    /// the shipped AERO), `paper` (the paper's step, `smoothing = 0` on every channel,
    /// for the reproduction), or `both` (with --compare: one table each).
    #[arg(long, value_enum, default_value = "scenario")]
    map: MapChoice,
    #[command(flatten)]
    timing: TimingArgs,
}

/// The loop's I/O off the sample instant, as a fieldbus has it (`sim` and `tune`).
#[derive(clap::Args)]
struct TimingArgs {
    /// How old each value is when the controller gets it (ms): the plant is read this
    /// long before the sample instant, as a subscription's published value was sampled
    /// before it. 0 is the lockstep loop.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    value_age_ms: f64,
    /// How long after the sample instant the command reaches the plant (ms), as a write
    /// across a network lands. The value's age and the write's delay together must be
    /// under the scenario's period.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    write_delay_ms: f64,
}

impl TimingArgs {
    /// The timing in seconds, each figure a number of milliseconds, 0 or more (the sum
    /// is checked against the period by the run).
    fn timing(&self) -> Result<IoTiming> {
        for (flag, ms) in [
            ("--value-age-ms", self.value_age_ms),
            ("--write-delay-ms", self.write_delay_ms),
        ] {
            if !(ms.is_finite() && ms >= 0.0) {
                bail!("{flag} must be a number of milliseconds, 0 or more, not {ms}");
            }
        }
        Ok(IoTiming {
            value_age: self.value_age_ms / 1e3,
            write_delay: self.write_delay_ms / 1e3,
        })
    }

    /// The flags as given, for the command a tuned file says it was made by.
    fn flags(&self) -> String {
        let mut s = String::new();
        if self.value_age_ms != 0.0 {
            s += &format!(" --value-age-ms {}", self.value_age_ms);
        }
        if self.write_delay_ms != 0.0 {
            s += &format!(" --write-delay-ms {}", self.write_delay_ms);
        }
        s
    }
}

#[derive(clap::Args)]
struct DemoArgs {
    /// Number of plants.
    #[arg(long, default_value_t = 2)]
    plants: usize,
    /// Scenario file or shipped AERO one.
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Controller file or shipped name (default: the scenario's).
    #[arg(long)]
    controller: Option<String>,
    /// Periods to hold the last command before falling back.
    #[arg(long, default_value_t = SafetyConfig::DEFAULT_HOLD_PERIODS)]
    hold_periods: u32,
    /// What to fall back to: `local` (the local controller) or `safe-stop` (zero inputs).
    #[arg(long, default_value = "local", value_parser = parse_fallback)]
    fallback: FallbackPolicy,
    /// Output directory (per plant: run.csv, summary.json, plots; and the MCAP
    /// recordings `service.mcap` and `plants.mcap`).
    #[arg(long, default_value = "out/demo")]
    out: PathBuf,
    /// Do not record to MCAP.
    #[arg(long)]
    no_record: bool,
    /// Serve the service's Prometheus metrics on this address (e.g. 127.0.0.1:9464).
    #[arg(long, value_name = "ADDR")]
    metrics: Option<String>,
    /// No live progress on stderr.
    #[arg(long)]
    quiet: bool,
}

#[derive(clap::Args)]
struct ReplayArgs {
    /// The recording (a service's: `service.mcap` of a demo, or `controller-service
    /// --record`).
    file: PathBuf,
    /// Largest difference of `u` and `v` still counted as a match.
    #[arg(long, default_value_t = controller_service::replay::DEFAULT_TOLERANCE)]
    tolerance: f64,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct TuneArgs {
    /// Scenario file or shipped AERO one.
    #[arg(long, default_value = "1")]
    scenario: String,
    /// Starting point: a built-in AERO kind (ip, ipi, ipd, pid, adrc) ...
    #[arg(long, required_unless_present = "start", conflicts_with = "start")]
    controller: Option<String>,
    /// ... or a controller file (any plant): its gains are the first guess.
    #[arg(long)]
    start: Option<PathBuf>,
    /// Where to write the tuned controller (TOML, usable by `sim --controller`).
    #[arg(long)]
    out: PathBuf,
    /// Number of offline runs (the same for every kind makes the comparison fair).
    #[arg(long, default_value_t = 150)]
    budget: usize,
    /// Seed of the random phase.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Name of the written controller set. Default: the starting point's.
    #[arg(long)]
    name: Option<String>,
    #[command(flatten)]
    timing: TimingArgs,
    #[command(flatten)]
    family: FamilyArgs,
}

/// `tune --family`: gains for a family of plants, not one (the robustness benchmark's).
#[derive(clap::Args)]
struct FamilyArgs {
    /// Tune for the whole family `robust` runs (the nominal plant, each factor at each end
    /// of its range, --random combinations): minimise the worst of the bars (the best
    /// baseline's RMS on each variation, the start's nominal RMS, --bound times the law's
    /// own nominal, the chatter bar), each as a fraction of its limit. --budget counts
    /// candidates, each run on every variation.
    #[arg(long, conflicts_with_all = ["value_age_ms", "write_delay_ms"])]
    family: bool,
    /// AERO factors to vary (as `robust --factors`). Default: all.
    #[arg(long, value_delimiter = ',', requires = "family")]
    factors: Vec<String>,
    /// Random combinations of every factor in the family.
    #[arg(long, default_value_t = 8, requires = "family")]
    random: usize,
    /// Seed of the family's random combinations (`robust --seed`).
    #[arg(long, default_value_t = 1, requires = "family")]
    family_seed: u64,
    /// The untouched laws not to lose to on any variation (shipped names or files).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "pid,adrc",
        requires = "family"
    )]
    baselines: Vec<String>,
    /// The largest RMS over the law's own nominal accepted on any variation.
    #[arg(long, default_value_t = 2.0, requires = "family")]
    bound: f64,
    /// The largest chatter accepted (mean |v(k) - v(k-1)|, the plant's input units; 0.7
    /// V is issue 30's on the AERO). Default: the starting point's own worst over the
    /// family.
    #[arg(long, requires = "family")]
    chatter: Option<f64>,
    /// Threads (default: the machine's cores).
    #[arg(long, requires = "family")]
    threads: Option<NonZeroUsize>,
}

#[derive(clap::Args)]
struct CampaignArgs {
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
    /// Controllers, side by side on the same link: shipped names or files, each
    /// optionally with `+hN` (the service sends a horizon of N periods with each
    /// command), `+dc` (delay compensation), `+notrend` (predict with `F` held, not
    /// following half its trend) or `+trendG` (`prediction.trend = G`), and `+restG`
    /// (`prediction.trend_at_rest = G`; default 0), e.g. `ipd,ipd+h10,ipd+h10+dc,pid`.
    #[arg(long, value_delimiter = ',', default_value = "ipd,pid")]
    controllers: Vec<String>,
    /// Links.
    #[arg(long, value_delimiter = ',', default_value = "tcp,udp")]
    links: Vec<Link>,
    /// The agents' oldest command still applied (periods, at most 1000): a command
    /// later than that is dropped, so a link whose round trips reach it loses commands.
    #[arg(long, default_value_t = SafetyConfig::DEFAULT_MAX_AGE)]
    max_age: u32,
    /// Run nothing: draw the plots again from a finished campaign's `campaign.json` in
    /// this directory (with the same --profiles), into --out.
    #[arg(long)]
    replot: Option<PathBuf>,
}

#[derive(clap::Args)]
struct NetsimArgs {
    /// Scenario (a file or a shipped AERO one).
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Shorten the scenario to this many seconds (the campaign runs 20 s of its own).
    #[arg(long)]
    duration: Option<f64>,
    /// Controllers, as for the campaign (`ipd+h10+dc`...).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "ipd,ipd+h10,ipd+h10+dc,pid,adrc"
    )]
    controllers: Vec<String>,
    /// Loss rates each way (0 to 1), each run with no delay.
    #[arg(long, value_delimiter = ',', default_value = "0.1,0.3,0.5")]
    loss: Vec<f64>,
    /// Round trips (ms), each run with no loss; each one-way delay spreads by
    /// ±`jitter` of itself.
    #[arg(long, value_delimiter = ',', default_value = "20,50,100")]
    rtt_ms: Vec<f64>,
    /// Spread of each one-way delay, as a fraction of it (uniform in ±jitter; 0 to 1).
    /// The default, 0.2, is the campaign's latency profiles (50 ms ± 10 ms each way).
    #[arg(long, default_value_t = 0.2)]
    jitter: f64,
    /// Seed of the link's draws.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// The agent's hold before its fallback (periods).
    #[arg(long, default_value_t = SafetyConfig::DEFAULT_HOLD_PERIODS)]
    hold_periods: u32,
    /// The agent's oldest command still applied (periods), as for the campaign.
    #[arg(long, default_value_t = SafetyConfig::DEFAULT_MAX_AGE)]
    max_age: u32,
    /// Which way the loss rates apply: both, up (samples only), down (commands only).
    #[arg(long, value_enum, default_value = "both")]
    lossy: crate::netsim::Lossy,
    /// Output directory (netsim.md, netsim.json).
    #[arg(long, default_value = "out/netsim")]
    out: PathBuf,
}

#[derive(clap::Args)]
struct ServiceConfigArgs {
    /// Device ids, comma-separated.
    #[arg(long, value_delimiter = ',', required = true)]
    devices: Vec<String>,
    /// Scenario whose references and output maps to use.
    #[arg(long, default_value = "2")]
    scenario: String,
    /// Controller file or shipped name (default: the scenario's).
    #[arg(long)]
    controller: Option<String>,
    /// The fleet's secret file, relative to where the configuration will be
    /// (`fleet.secret` in a bundle `mfc-deploy` wrote): the service then checks every
    /// message's proof of origin. Absent: it runs open.
    #[arg(long)]
    secret_file: Option<std::path::PathBuf>,
}

/// Parse the process's arguments and run.
pub fn main() -> std::process::ExitCode {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "warn".into()),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a terminal: not into files or the journal.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
    match real_main() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}

fn scenario_and_controller(
    scenario: &str,
    controller: Option<&str>,
) -> Result<(Scenario, ControllerSet)> {
    let s = load_scenario(scenario)?;
    let c = match controller {
        Some(c) => load_controller(c)?,
        None => s.controller.clone(),
    };
    s.check_controller(&c)?;
    Ok((s, c))
}

fn bar(len: u64, template: &str) -> ProgressBar {
    ProgressBar::new(len).with_style(
        ProgressStyle::with_template(template)
            .expect("static template")
            .progress_chars("=> "),
    )
}

/// Which dead-zone compensation a simulation runs with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum MapChoice {
    /// The scenario files' own maps.
    Scenario,
    /// The paper's step compensation on every channel.
    Paper,
    /// Both, one table each (with --compare).
    Both,
}

/// `s` with the paper's step compensation on every channel (`smoothing = 0`), named so.
fn paper_map(mut s: Scenario) -> Scenario {
    if s.channels.iter().any(|c| c.output.smoothing > 0.0) {
        for c in &mut s.channels {
            c.output.smoothing = 0.0;
        }
        s.name = format!("{} (paper map)", s.name);
    }
    s
}

fn real_main() -> Result<()> {
    match Cli::parse().command {
        Command::Sim(args) if args.compare => {
            if args.controller.is_some() {
                bail!("--compare takes --controllers (a list), not --controller");
            }
            if !args.timing.flags().is_empty() {
                bail!("--compare runs the lockstep loop: no --value-age-ms or --write-delay-ms");
            }
            let only =
                (!args.controllers.is_empty()).then_some((&args.scenario, &args.controllers));
            sim_compare(&args.out, only, args.map)
        }
        Command::Sim(args) => sim(&args),
        Command::Demo(args) => demo_command(&args),
        Command::Replay(args) => replay(&args),
        Command::Tune(args) => tune_command(&args),
        Command::Campaign(args) => match &args.replot {
            Some(from) => replot_campaign(&args.profiles, from, &args.out),
            None => campaign(&args),
        },
        Command::Netsim(args) => netsim(&args),
        Command::ServiceConfig(args) => print_service_config(&args),
        Command::Robust(args) => robust(&args),
        Command::Commission(args) => commission_command(&args),
    }
}

/// The family `robust` runs: the AERO's factors (all, or `--factors`), or a driver plant's
/// fixed table; a Modbus plant has none.
fn variations_of(
    scenario: &plant::scenario::Scenario,
    names: &[String],
    seed: u64,
    random: usize,
) -> Result<Vec<crate::robust::Variation>> {
    use crate::robust::{driver_factors, driver_family, family_of, Factor};
    use plant::scenario::PlantSource;
    let factors = if names.is_empty() {
        Factor::ALL.to_vec()
    } else {
        let parse = |n: &String| {
            Factor::parse(n).with_context(|| {
                format!("no factor `{n}`: rotor, mass, spring, damping, noise, motor, encoder")
            })
        };
        let factors = names.iter().map(parse).collect::<Result<Vec<_>>>()?;
        if let Some((i, _)) = factors
            .iter()
            .enumerate()
            .find(|(i, f)| factors[..*i].contains(f))
        {
            bail!("--factors names `{}` twice: each factor once", names[i]);
        }
        factors
    };
    Ok(match &scenario.plant {
        PlantSource::Aero(_) => family_of(&factors, seed, random),
        PlantSource::Modbus(_) | PlantSource::OpcUa(_) => {
            bail!("a plant behind a server (Modbus, OPC UA): robust varies simulators offline")
        }
        PlantSource::Driver(_) if !names.is_empty() => {
            bail!("--factors names the AERO's factors; a driver plant's family is fixed")
        }
        PlantSource::Driver(cmd) => match driver_factors(&cmd.argv) {
            Some(table) => driver_family(table, seed, random),
            None => bail!(
                "no family for the driver {:?}: robust varies the AERO simulator, heater.py and dc_motor.py",
                cmd.argv
            ),
        },
    })
}

/// Each named controller (a shipped AERO name or a file), checked against the scenario;
/// `flag` is the option that named them, for the error.
fn controllers_for(
    scenario: &plant::scenario::Scenario,
    names: &[String],
    flag: &str,
) -> Result<Vec<plant::scenario::ControllerSet>> {
    names
        .iter()
        .map(|n| {
            let c = load_controller(n)?;
            scenario.check_controller(&c).with_context(|| {
                format!(
                    "`{n}` ({flag}; another plant's controllers are files, such as its pid.toml)"
                )
            })?;
            Ok(c)
        })
        .collect()
}

/// `--threads`, or the machine's cores.
fn threads_or_cores(threads: Option<NonZeroUsize>) -> usize {
    threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
        NonZeroUsize::get,
    )
}

/// `robust`: the family run, judged, written.
fn robust(args: &RobustArgs) -> Result<()> {
    use crate::robust::{check, heat_map, judge, markdown, run};
    use plant::scenario::PlantSource;
    let scenario = load_scenario(&args.scenario)?;
    let variations = variations_of(&scenario, &args.factors, args.seed, args.random)?;
    let names: Vec<String> = match (&scenario.plant, args.controllers.is_empty()) {
        (_, false) => args.controllers.clone(),
        (PlantSource::Aero(_), true) => SHIPPED_CONTROLLERS
            .iter()
            .map(|(n, _)| n.to_string())
            .collect(),
        (_, true) => bail!("a driver plant's controllers are files: name them with --controllers"),
    };
    let sets = controllers_for(&scenario, &names, "--controllers")?;
    let threads = threads_or_cores(args.threads);
    eprintln!(
        "robust: {} controllers x {} variations of scenario {} on {threads} threads",
        sets.len(),
        variations.len(),
        scenario.name
    );
    let started = std::time::Instant::now();
    let cells = run(&scenario, &sets, &variations, threads)?;
    let baselines: Vec<&str> = args.baselines.iter().map(String::as_str).collect();
    let verdicts = judge(&cells, &baselines);
    let title = format!(
        "{}: RMS over each controller's nominal RMS (seed {}, {} random)",
        scenario.name, args.seed, args.random
    );
    let md = format!(
        "# Robustness: {title}\n\n{}",
        markdown(&verdicts, &cells, &variations)
    );
    std::fs::create_dir_all(&args.out)?;
    std::fs::write(args.out.join("robust.md"), &md)?;
    std::fs::write(
        args.out.join("robust.json"),
        serde_json::to_string_pretty(&serde_json::json!({
            "scenario": scenario.name, "seed": args.seed, "variations": variations,
            "cells": cells, "verdicts": verdicts,
        }))?,
    )?;
    std::fs::write(
        args.out.join("robust-heatmap.svg"),
        heat_map(&title, &scenario.names(), (&verdicts, &cells), &variations),
    )?;
    println!("{md}");
    eprintln!(
        "robust: {} runs in {:.1} s; {}",
        cells.len(),
        started.elapsed().as_secs_f64(),
        args.out.display()
    );
    let held: Vec<&str> = args.check.iter().map(String::as_str).collect();
    let failures = check(&verdicts, &held, args.bound);
    if !failures.is_empty() {
        bail!("the bars are broken:\n  {}", failures.join("\n  "));
    }
    if !held.is_empty() {
        eprintln!(
            "robust: {} hold the bars ({}x, no baseline better, safe)",
            held.join(", "),
            args.bound
        );
    }
    Ok(())
}

/// One value per channel, or one for all.
fn per_channel<T: Copy>(what: &str, v: &[T], n: usize) -> Result<Vec<T>> {
    match v.len() {
        1 => Ok(vec![v[0]; n]),
        k if k == n => Ok(v.to_vec()),
        k => bail!("--{what}: {k} values for {n} channels (give one, or one per channel)"),
    }
}

/// `commission`: the wrong start, the runs, the scenario with what they found.
fn commission_command(args: &CommissionArgs) -> Result<()> {
    use crate::commission::{commission_all, report, scale_alpha};
    let (scenario, set) = scenario_and_controller(&args.scenario, args.controller.as_deref())?;
    if !(args.alpha_scale.is_finite() && args.alpha_scale != 0.0) {
        bail!("--alpha-scale must be finite and non-zero (it multiplies alpha)");
    }
    if !set
        .channels
        .iter()
        .any(|l| matches!(l, mfc::LawConfig::Intelligent { .. }))
    {
        bail!(
            "`{}` has no intelligent channel: nothing to commission",
            set.name
        );
    }
    let n = scenario.channels.len();
    let (amp, period, dev) = (
        per_channel("amplitude", &args.amplitude, n)?,
        per_channel("period", &args.period, n)?,
        per_channel("max-deviation", &args.max_deviation, n)?,
    );
    let windows = if args.window.is_empty() {
        vec![]
    } else {
        per_channel("window", &args.window, n)?
    };
    let specs: Vec<mfc::CommissionSpec> = (0..n)
        .map(|i| mfc::CommissionSpec {
            amplitude: amp[i],
            period: period[i],
            cycles: args.cycles,
            max_deviation: dev[i],
            window: match (windows.get(i), set.channels[i]) {
                (Some(w), _) => *w,
                (None, mfc::LawConfig::Intelligent { estimator, .. }) => estimator.window.max(2),
                _ => 20,
            },
            order: match set.channels[i] {
                mfc::LawConfig::Intelligent { params, .. } if !args.choose_order => {
                    Some(params.order)
                }
                _ => None,
            },
        })
        .collect();
    for (i, s) in specs.iter().enumerate() {
        s.validate(mfc::DEFAULT_CAPACITY)
            .with_context(|| format!("channel {i} ({})", scenario.channels[i].name))?;
    }
    let wrong = scale_alpha(&set, args.alpha_scale);
    let (found, runs) = if args.live {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?;
        runtime.block_on(crate::commission::commission_live(
            &scenario,
            &wrong,
            &specs,
            &args.channels,
        ))?
    } else {
        commission_all(&scenario, &wrong, &specs)?
    };
    let mut rms = Vec::new();
    let mut sets = vec![wrong, found.clone()];
    for c in &args.compare {
        sets.push(load_controller(c)?);
    }
    for s in &sets {
        let sim = simulate(&scenario, s, false)?;
        rms.push((
            s.name.clone(),
            sim.summary.channels.iter().map(|c| c.rms).collect(),
        ));
    }
    let md = format!(
        "# Commissioning `{}` on {} (alpha x{}{})\n\n{}",
        set.name,
        scenario.name,
        args.alpha_scale,
        if args.live { ", live" } else { "" },
        report(&runs, &rms, &scenario.names())
    );
    std::fs::create_dir_all(&args.out)?;
    std::fs::write(args.out.join("commission.md"), &md)?;
    let file = args.out.join(format!("{}.toml", found.name));
    std::fs::write(&file, toml::to_string_pretty(&found)?)?;
    println!("{md}");
    eprintln!(
        "commission: wrote {} and {}",
        args.out.join("commission.md").display(),
        file.display()
    );
    Ok(())
}

/// `sim`: one scenario offline, its record written.
fn sim(args: &SimArgs) -> Result<()> {
    let (mut scenario, set) = scenario_and_controller(&args.scenario, args.controller.as_deref())?;
    match args.map {
        MapChoice::Scenario => {}
        MapChoice::Paper => scenario = paper_map(scenario),
        MapChoice::Both => bail!("--map both needs --compare"),
    }
    if let Some(d) = args.duration {
        if !(d.is_finite() && d > 0.0) {
            bail!("--duration must be a positive number of seconds, not {d}");
        }
        scenario.duration = d;
    }
    let r = simulate_timed(&scenario, &set, true, args.timing.timing()?)?;
    let out = &args.out;
    write_run(
        out,
        &format!("{} — {}", scenario.name, set.name),
        &r.record,
        &r.summary,
    )?;
    print_summary(&r.summary);
    println!(
        "wrote {}/{{run.csv, summary.json, *.png, *.svg}}",
        out.display()
    );
    Ok(())
}

/// `demo`: the service and N plants over Zenoh, beside the offline twin.
fn demo_command(args: &DemoArgs) -> Result<()> {
    let plants = args.plants;
    if plants == 0 || plants > 64 {
        bail!("--plants must be between 1 and 64");
    }
    let (scenario, set) = scenario_and_controller(&args.scenario, args.controller.as_deref())?;
    let offline = simulate(&scenario, &set, false)?.summary;
    println!(
        "{}: {} plant(s) and a controller service over Zenoh on loopback, keys made at start (every sample and command carries its MAC), {:.0} s in real time...",
        scenario.name, plants, scenario.duration
    );
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let out = &args.out;
    let options = DemoOptions {
        plants,
        safety: SafetyConfig {
            period: scenario.period,
            max_age: SafetyConfig::DEFAULT_MAX_AGE,
            hold_periods: args.hold_periods,
            fallback: args.fallback,
        },
        out: Some(out.clone()),
        record: (!args.no_record).then(|| out.clone()),
        metrics: args.metrics.clone(),
        progress: !args.quiet,
    };
    let reports = runtime.block_on(demo(&scenario, &set, &options))?;
    print_reports(&reports, Some(&offline));
    println!(
        "wrote {}/<device>/{{run.csv, summary.json, *.png, *.svg}}",
        out.display()
    );
    if !args.no_record {
        println!(
            "recorded {0}/service.mcap and {0}/plants.mcap (Foxglove opens them; `mfc-lab replay {0}/service.mcap` re-runs the controller on them)",
            out.display()
        );
    }
    Ok(())
}

/// `replay`: a service's recording through the controller again; exit 1 on a mismatch.
fn replay(args: &ReplayArgs) -> Result<()> {
    let (file, tolerance) = (&args.file, args.tolerance);
    if !(tolerance.is_finite() && tolerance >= 0.0) {
        bail!("--tolerance must be a finite number >= 0");
    }
    let bytes = std::fs::read(file).with_context(|| format!("reading {}", file.display()))?;
    let report = controller_service::replay::replay(&bytes, tolerance)
        .with_context(|| file.display().to_string())?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        print!("{}", controller_service::replay::render(&report));
    }
    if !report.matched {
        std::process::exit(1);
    }
    Ok(())
}

/// `tune`: the tuner from a built-in kind or a controller file, the result written with
/// the command that made it.
fn tune_command(args: &TuneArgs) -> Result<()> {
    let budget = args.budget;
    if budget == 0 {
        bail!("--budget must be at least 1");
    }
    let scenario = load_scenario(&args.scenario)?;
    let (start_set, from) = match (&args.controller, &args.start) {
        (Some(kind), _) => (
            starting_point(kind).with_context(|| {
                format!(
                    "unknown controller kind `{kind}` (built-in AERO starting points: {}; for another plant give --start FILE)",
                    KINDS.join(", ")
                )
            })?,
            format!("--controller {kind}"),
        ),
        (None, Some(file)) => (
            load_controller(&file.to_string_lossy())?,
            format!("--start {}", file.display()),
        ),
        (None, None) => bail!("give --controller KIND or --start FILE"),
    };
    scenario.check_controller(&start_set)?;
    if args.family.family {
        return tune_family_command(args, &scenario, &start_set, &from);
    }
    let timing = args.timing.timing()?;
    let label = start_set.name.clone();
    let bar = bar(budget as u64, "{msg} [{bar:30}] {pos}/{len} runs ({eta})");
    let tuned = tune(
        &scenario,
        &start_set,
        budget,
        args.seed,
        timing,
        |done, best| {
            bar.set_position(done as u64);
            bar.set_message(format!("tuning {label}: best {best:.4}"));
        },
    )?;
    bar.finish_and_clear();
    let mut set = tuned.set;
    if let Some(name) = &args.name {
        set.name = name.clone();
    }
    let out = &args.out;
    let command = format!(
        "mfc-lab tune --scenario {} {from} --budget {budget} --seed {}{}{}",
        args.scenario,
        args.seed,
        args.timing.flags(),
        args.name
            .as_ref()
            .map(|n| format!(" --name {n}"))
            .unwrap_or_default()
    );
    write_tuned(out, &command, &set)?;
    println!(
        "{label} on {}: objective {:.4} (start {:.4}) in {} runs; wrote {}",
        scenario.name,
        tuned.cost,
        tuned.start_cost,
        tuned.runs,
        out.display()
    );
    Ok(())
}

/// `tune --family`: the baselines and the start over the family, then the search; the
/// result written with the command that made it and the margins before and after.
fn tune_family_command(
    args: &TuneArgs,
    scenario: &plant::scenario::Scenario,
    start: &plant::scenario::ControllerSet,
    from: &str,
) -> Result<()> {
    use crate::robust::run;
    use crate::tune::{tune_family, Bars};
    let f = &args.family;
    if !(f.bound.is_finite() && f.bound >= 1.0) {
        bail!("--bound must be a ratio of 1 or more, not {}", f.bound);
    }
    if let Some(c) = f.chatter.filter(|c| !(c.is_finite() && *c > 0.0)) {
        bail!("--chatter must be a positive number, not {c}");
    }
    let variations = variations_of(scenario, &f.factors, f.family_seed, f.random)?;
    let baselines = controllers_for(scenario, &f.baselines, "--baselines")?;
    let threads = threads_or_cores(f.threads);
    eprintln!(
        "tune --family: {} variations of {}, baselines {}, {} candidates on {threads} threads",
        variations.len(),
        scenario.name,
        f.baselines.join(", "),
        args.budget
    );
    let base_cells = run(scenario, &baselines, &variations, threads)?;
    let start_cells = run(scenario, std::slice::from_ref(start), &variations, threads)?;
    let bars = Bars::new(&variations, &base_cells, &start_cells, f.bound, f.chatter)?;
    let label = start.name.clone();
    let bar = bar(
        args.budget as u64,
        "{msg} [{bar:30}] {pos}/{len} candidates ({eta})",
    );
    let tuned = tune_family(
        scenario,
        start,
        &variations,
        &bars,
        args.budget,
        args.seed,
        threads,
        |done, best| {
            bar.set_position(done as u64);
            bar.set_message(format!(
                "tuning {label} over the family: worst margin {best:.3}"
            ));
        },
    )?;
    bar.finish_and_clear();
    if !tuned.margins.worst().is_finite() {
        bail!(
            "no candidate ran the whole family safely (the start: {}): nothing written; start \
             from a law that does, or narrow the family with --factors",
            tuned.start_margins
        );
    }
    let mut set = tuned.set;
    if let Some(name) = &args.name {
        set.name = name.clone();
    }
    let mut command = format!(
        "mfc-lab tune --scenario {} {from} --budget {} --seed {} --family --random {} \
         --family-seed {} --baselines {} --bound {}",
        args.scenario,
        args.budget,
        args.seed,
        f.random,
        f.family_seed,
        f.baselines.join(","),
        f.bound
    );
    if !f.factors.is_empty() {
        command += &format!(" --factors {}", f.factors.join(","));
    }
    if let Some(c) = f.chatter {
        command += &format!(" --chatter {c}");
    }
    if let Some(n) = &args.name {
        command += &format!(" --name {n}");
    }
    write_tuned(&args.out, &command, &set)?;
    println!(
        "{label} over {} variations of {}: worst margin {:.3} (start {:.3}) in {} candidates; wrote {}\n  start: {}\n  tuned: {}",
        variations.len(),
        scenario.name,
        tuned.margins.worst(),
        tuned.start_margins.worst(),
        tuned.evaluations,
        args.out.display(),
        tuned.start_margins,
        tuned.margins,
    );
    Ok(())
}

/// Write a tuned set as TOML, headed by the command that made it.
fn write_tuned(out: &Path, command: &str, set: &plant::scenario::ControllerSet) -> Result<()> {
    let text = toml::to_string_pretty(set)?;
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    std::fs::write(out, format!("# Written by `{command}`.\n{text}"))
        .with_context(|| format!("writing {}", out.display()))
}

/// `service-config`: the service's configuration for these devices, as TOML.
fn print_service_config(args: &ServiceConfigArgs) -> Result<()> {
    let (scenario, set) = scenario_and_controller(&args.scenario, args.controller.as_deref())?;
    let mut config = service_config(&scenario, &set, &args.devices);
    config.secret_file.clone_from(&args.secret_file);
    config.check("(generated)")?;
    println!(
        "# controller-service configuration: {} on {} for {}\n{}",
        set.name,
        scenario.name,
        args.devices.join(", "),
        toml::to_string_pretty(&config)?
    );
    Ok(())
}

fn print_summary(s: &OfflineSummary) {
    match s.timing {
        Some(t) => println!("{} with {}, {t}:", s.scenario, s.controller),
        None => println!("{} with {}:", s.scenario, s.controller),
    }
    for c in &s.channels {
        println!(
            "  {:<18} rms {:.3e}  max {:.3e}  iae {:.3e}  saturated {:.1}%  chatter {:.3}",
            c.name,
            c.rms,
            c.max_abs,
            c.iae,
            100.0 * c.saturated_fraction,
            c.control_variation
        );
    }
    if !s.completed {
        println!("  the run stopped early: the controller refused the plant's data");
    }
}

fn print_reports(reports: &[AgentReport], offline: Option<&OfflineSummary>) {
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
            r.rtt_p50_us, r.rtt_p99_us, r.counters.missing, r.counters.late, r.counters.fallbacks
        );
    }
    for r in reports.iter().filter(|r| r.exit_code() != 0) {
        println!("{}", r.headline());
    }
}

fn sim_compare(out: &Path, only: Option<(&String, &Vec<String>)>, map: MapChoice) -> Result<()> {
    let (scenarios, controllers) = match only {
        Some((s, cs)) => (
            vec![load_scenario(s)?],
            cs.iter()
                .map(|c| load_controller(c))
                .collect::<Result<Vec<_>, _>>()?,
        ),
        None => (
            SHIPPED_SCENARIOS
                .iter()
                .map(|(n, _, _)| load_scenario(n))
                .collect::<Result<Vec<_>, _>>()?,
            SHIPPED_CONTROLLERS
                .iter()
                .map(|(k, _)| shipped_controller(k))
                .collect::<Result<Vec<_>, _>>()?,
        ),
    };
    let variants: Vec<(&str, Vec<Scenario>)> = match map {
        MapChoice::Scenario => vec![("", scenarios)],
        MapChoice::Paper => vec![("-paper", scenarios.into_iter().map(paper_map).collect())],
        MapChoice::Both => vec![
            ("", scenarios.clone()),
            ("-paper", scenarios.into_iter().map(paper_map).collect()),
        ],
    };
    let runs: usize = variants.iter().map(|(_, s)| s.len()).sum::<usize>() * controllers.len();
    let bar = bar(runs as u64, "{msg:<40} [{bar:30}] {pos}/{len} runs");
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let mut written = Vec::new();
    for (suffix, scenarios) in &variants {
        let cmp = compare(scenarios, &controllers, |s, c| {
            bar.set_message(format!("{s} / {c}"));
            bar.inc(1);
        })?;
        let mass = cmp.mass_markdown();
        let md = if mass.is_empty() {
            cmp.markdown()
        } else {
            format!(
                "{}\nRMS with the 4 g mass over RMS without (no retuning):\n\n{mass}",
                cmp.markdown()
            )
        };
        let (md_file, json_file) = (
            format!("comparison{suffix}.md"),
            format!("comparison{suffix}.json"),
        );
        std::fs::write(out.join(&md_file), &md)?;
        std::fs::write(
            out.join(&json_file),
            serde_json::to_string_pretty(&cmp)? + "\n",
        )?;
        bar.suspend(|| println!("{md}"));
        written.push(md_file);
        written.push(json_file);
    }
    bar.finish_and_clear();
    println!("wrote {} in {}", written.join(", "), out.display());
    Ok(())
}

fn campaign(args: &CampaignArgs) -> Result<()> {
    let (profiles, out, duration) = (args.profiles.as_str(), &args.out, args.duration);
    let (controllers, links, max_age) = (&args.controllers, &args.links, args.max_age);
    if !(duration.is_finite() && duration >= 2.0) {
        bail!("--duration must be at least 2 s");
    }
    check_max_age(max_age)?;
    let set = ProfileSet::load(profiles)?;
    if !set.profiles.iter().any(|p| p.name == "none") {
        bail!("{profiles}: the campaign needs a profile named `none` (the unimpaired baseline)");
    }
    let mut s = load_scenario(&args.scenario)?;
    s.duration = duration;
    let (sets, predictions): (Vec<_>, Vec<_>) = load_variants(&s, controllers)?.into_iter().unzip();
    let board = std::sync::Arc::new(ProgressBoard::new());
    let options = CaseOptions {
        predictions,
        max_age,
        progress: Some(board.clone()),
        ..CaseOptions::default()
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?;
    let total = set.profiles.len() * links.len();
    // The case on the first line, the plants of the case running below it.
    let bar = bar(
        total as u64,
        "{prefix:<32} [{bar:30}] {pos}/{len} cases, {elapsed} ({eta} left)\n{msg}",
    );
    let tty = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let mut campaign = Campaign {
        scenario: s.name.clone(),
        duration,
        cases: Vec::new(),
    };
    for p in &set.profiles {
        for link in links {
            let case = format!("{} over {}", p.name, link.scheme());
            bar.set_prefix(case.clone());
            board.clear();
            let r = runtime.block_on(async {
                let run = run_case(&s, &sets, p, *link, &options);
                // Live: the plants' time, RMS so far, round trip and mode, twice a second
                // under the bar on a terminal; every ten seconds as plain lines otherwise.
                let show = async {
                    let mut tick = tokio::time::interval(std::time::Duration::from_millis(500));
                    for n in 0u64.. {
                        tick.tick().await;
                        let text = board.render();
                        if tty {
                            bar.set_message(text.trim_end().to_string());
                        } else if n % 20 == 19 {
                            eprint!("-- {case}\n{text}");
                        }
                    }
                };
                tokio::select! {
                    r = run => r,
                    () = show => unreachable!("the display runs until the case ends"),
                }
            })?;
            campaign.cases.extend(r);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    campaign.compute_ratios("none");
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let md = campaign.markdown();
    std::fs::write(out.join("campaign.md"), &md)?;
    std::fs::write(
        out.join("campaign.json"),
        serde_json::to_string_pretty(&campaign)? + "\n",
    )?;
    crate::campaign::plots(out, &campaign, &set)?;
    println!("{md}");
    println!(
        "wrote {0}/campaign.md, {0}/campaign.json, {0}/rms_vs_loss.png|svg, {0}/rms_vs_latency.png|svg",
        out.display()
    );
    Ok(())
}

/// The controllers of `specs` (a shipped name or a file with options, see
/// [`crate::campaign::parse_variant`]), each checked against `s` and named after its set
/// with the options appended; two of one name are refused.
fn load_variants(
    s: &Scenario,
    specs: &[String],
) -> Result<Vec<(ControllerSet, controller_service::config::Prediction)>> {
    let sets = specs
        .iter()
        .map(|spec| {
            let (base, prediction) =
                crate::campaign::parse_variant(spec).map_err(anyhow::Error::msg)?;
            let mut set = load_controller(&base)?;
            s.check_controller(&set)?;
            set.name.push_str(&spec[base.len()..]);
            Ok((set, prediction))
        })
        .collect::<Result<Vec<_>>>()?;
    // Rows, ratios and device ids go by name: two entries of one name would be measured
    // against each other's runs.
    for (i, (a, _)) in sets.iter().enumerate() {
        if let Some(j) = sets[..i].iter().position(|(b, _)| b.name == a.name) {
            bail!(
                "{} and {} are both named {:?}: give one another `name` in its file",
                specs[j],
                specs[i],
                a.name
            );
        }
    }
    Ok(sets)
}

/// `--max-age` within what the agent's configuration takes.
fn check_max_age(max_age: u32) -> Result<()> {
    use plant_agent::safety::MAX_AGE_LIMIT;
    if max_age > MAX_AGE_LIMIT {
        bail!("--max-age {max_age}: at most {MAX_AGE_LIMIT} periods");
    }
    Ok(())
}

/// Draw a finished campaign's plots again from its `campaign.json`.
fn replot_campaign(profiles: &str, from: &Path, out: &Path) -> Result<()> {
    let set = ProfileSet::load(profiles)?;
    let path = from.join("campaign.json");
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let c: Campaign = serde_json::from_str(&text)
        .with_context(|| format!("{} is not a campaign's record", path.display()))?;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    crate::campaign::plots(out, &c, &set)?;
    println!(
        "wrote {0}/rms_vs_loss.png|svg, {0}/rms_vs_latency.png|svg",
        out.display()
    );
    Ok(())
}

fn netsim(args: &NetsimArgs) -> Result<()> {
    use crate::netsim::simulate_net;
    let mut s = load_scenario(&args.scenario)?;
    if let Some(d) = args.duration {
        if !(d.is_finite() && d >= s.period) {
            bail!(
                "--duration must be at least one period ({} s), not {d}",
                s.period
            );
        }
        s.duration = d;
    }
    check_max_age(args.max_age)?;
    let jitter = args.jitter;
    if !(0.0..=1.0).contains(&jitter) {
        bail!("--jitter must be between 0 and 1 (a fraction of the one-way delay), not {jitter}");
    }
    let sets = load_variants(&s, &args.controllers)?;
    let safety = SafetyConfig {
        hold_periods: args.hold_periods,
        max_age: args.max_age,
        ..crate::harness::default_safety(&s)
    };
    let links = netsim_links(args)?;
    let bar = bar(
        (links.len() * sets.len()) as u64,
        "{msg:<40} [{bar:30}] {pos}/{len} runs",
    );
    let mut rows = Vec::new();
    for (name, link) in &links {
        for (set, prediction) in &sets {
            bar.set_message(format!("{} / {name}", set.name));
            let r = simulate_net(&s, set, *prediction, link, safety)?;
            rows.push((name.clone(), r));
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    let md = netsim_markdown(&rows);
    let out = &args.out;
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    std::fs::write(out.join("netsim.md"), &md)?;
    let json: Vec<_> = rows
        .iter()
        .map(|(name, r)| serde_json::json!({ "link": name, "run": r }))
        .collect();
    std::fs::write(
        out.join("netsim.json"),
        serde_json::to_string_pretty(&json)? + "\n",
    )?;
    println!("{md}");
    println!("wrote {0}/netsim.md and {0}/netsim.json", out.display());
    Ok(())
}

/// The links of a `netsim` run, named for its table: a perfect one, each loss rate with
/// no delay, each round trip with no loss.
fn netsim_links(args: &NetsimArgs) -> Result<Vec<(String, crate::netsim::LinkModel)>> {
    use crate::netsim::{LinkModel, Lossy};
    let (lossy, seed) = (args.lossy, args.seed);
    let mut links = vec![("perfect".to_string(), LinkModel::PERFECT)];
    for &l in &args.loss {
        let way = match lossy {
            Lossy::Both => "",
            Lossy::Up => " (samples)",
            Lossy::Down => " (commands)",
        };
        links.push((
            format!("loss {:.0} %{way}", 100.0 * l),
            LinkModel {
                loss: l,
                lossy,
                seed,
                ..LinkModel::PERFECT
            },
        ));
    }
    for &r in &args.rtt_ms {
        let one_way = r / 2000.0;
        links.push((
            format!("{r:.0} ms round trip"),
            LinkModel {
                delay: one_way,
                jitter: args.jitter * one_way,
                seed,
                ..LinkModel::PERFECT
            },
        ));
    }
    for (name, l) in &links {
        l.check().map_err(|e| anyhow::anyhow!("{name}: {e}"))?;
    }
    Ok(links)
}

/// The `netsim` table: each run's RMS per channel and its ratio to the same controller on
/// the perfect link, then what the agent counted.
fn netsim_markdown(rows: &[(String, crate::netsim::NetRun)]) -> String {
    use std::fmt::Write as _;
    let mut md = String::new();
    let channels: Vec<String> = rows
        .first()
        .map(|(_, r)| r.channels.iter().map(|c| c.name.clone()).collect())
        .unwrap_or_default();
    let _ = write!(md, "| link | controller |");
    for c in &channels {
        let _ = write!(md, " {c} RMS | ratio |");
    }
    let _ = writeln!(
        md,
        " chatter (V/sample) | periods without command | horizon played | late, from the horizon | fallbacks |"
    );
    let _ = writeln!(
        md,
        "|---|---|{}---:|---:|---:|---:|---:|",
        "---:|---:|".repeat(channels.len())
    );
    for (name, r) in rows {
        let base = rows
            .iter()
            .find(|(n, b)| n == "perfect" && b.controller == r.controller)
            .map(|(_, b)| b);
        let _ = write!(md, "| {name} | {} |", r.controller);
        for (i, c) in r.channels.iter().enumerate() {
            let ratio = base.map_or(f64::NAN, |b| c.rms / b.channels[i].rms);
            let _ = write!(md, " {:.3e} | {ratio:.2} |", c.rms);
        }
        let k = &r.counters;
        let chatter = r
            .channels
            .iter()
            .map(|c| format!("{:.2}", c.control_variation))
            .collect::<Vec<_>>()
            .join(" / ");
        let _ = writeln!(
            md,
            " {chatter} | {:.1} % | {} | {} | {} |",
            100.0 * k.missing as f64 / k.periods.max(1) as f64,
            k.horizon_periods,
            k.horizon_late,
            k.fallbacks
        );
    }
    md
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
