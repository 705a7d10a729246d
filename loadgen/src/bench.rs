//! The benchmark: the service and the echo anchor, side by side in one run, over a sweep
//! of fleet sizes, on the per-device path and through gateways.
//!
//! Every trial starts its target as a process of its own (so its CPU time and memory can
//! be read from `/proc`, and no state leaks between trials), connects a fresh generator
//! session to it on loopback (peers, multicast scouting off), runs the warm-up and the
//! measured window, and stops the target. At each fleet size the service and the anchor
//! run one after the other, in [`BenchSpec::rounds`] rounds whose order alternates, so a
//! busy machine hurts both alike and one hiccup decides nothing: a target holds a size when
//! the median of its rounds has at least [`BenchSpec::inside`] of its commands back within
//! the period, and its round trip at a size is the median of its rounds' percentiles. The
//! capacity of a target is the largest fleet it holds; after the grid, a few bisection steps
//! between the last size that held and the first that did not refine it.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::gen::{self, LoadReport, Spec};
use crate::stats;

/// Which process answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Target {
    /// The controller service, with a template that provisions every `load-*` device.
    Service,
    /// The minimal echo ([`crate::echo`]).
    Echo,
}

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchSpec {
    /// The controller-service binary.
    pub service_bin: PathBuf,
    /// The service's workers (`--workers`).
    pub service_workers: usize,
    /// This program (for `loadgen echo`).
    pub loadgen_bin: PathBuf,
    pub rate_hz: f64,
    pub warmup: Duration,
    pub measure: Duration,
    /// Fleet sizes of the per-device sweep (one message per device per period).
    pub per_device: Vec<usize>,
    /// Fleet sizes of the gateway sweep.
    pub gateway_devices: Vec<usize>,
    /// Plants per gateway.
    pub per_gateway: usize,
    /// Bisection steps after each grid.
    pub refine: usize,
    /// Fraction of commands that must be back within the period for a size to hold.
    pub inside: f64,
    /// Rounds at each size (each runs both targets, in alternating order); the medians
    /// decide.
    pub rounds: usize,
    /// The per-device fleet size whose round trips are compared (the issue's: 100).
    pub p99_at: usize,
    /// Where results go (`bench.json`, `bench.md`).
    pub out: PathBuf,
    /// Run the service with keys (`protocol::auth`): the generator seals its samples and
    /// batches and checks the service's commands; the echo anchor stays open.
    pub auth: bool,
}

/// One trial.
#[derive(Debug, Clone, Serialize)]
pub struct Trial {
    pub target: Target,
    /// Which round at this size (0-based).
    pub round: usize,
    pub path: &'static str,
    pub report: LoadReport,
    /// Target CPU time over the window per answered sample (us).
    pub cpu_us_per_sample: Option<f64>,
    /// Target CPU over the window, in cores (1.0 = one core busy).
    pub cpu_cores: Option<f64>,
    /// Target resident memory after the warm-up minus before the generator, per device.
    pub rss_bytes_per_device: Option<f64>,
    pub rss_bytes: Option<u64>,
}

/// All trials and what they show.
#[derive(Debug, Clone, Serialize)]
pub struct Results {
    pub rate_hz: f64,
    pub service_workers: usize,
    pub inside: f64,
    pub warmup_s: f64,
    pub measure_s: f64,
    pub per_gateway: usize,
    pub rounds: usize,
    /// The per-device size whose round trips the summary compares.
    pub p99_at: usize,
    pub trials: Vec<Trial>,
    /// Per size, path and target, the medians of its rounds.
    pub points: Vec<BenchPoint>,
    /// Largest per-device fleet that held, per target.
    pub capacity_service: Option<usize>,
    pub capacity_echo: Option<usize>,
    /// Largest gateway fleet that held, per target.
    pub gateway_capacity_service: Option<usize>,
    pub gateway_capacity_echo: Option<usize>,
    /// Whether the service ran with keys.
    pub auth: bool,
}

/// The medians of one target's rounds at one size.
#[derive(Debug, Clone, Serialize)]
pub struct BenchPoint {
    pub target: Target,
    pub path: &'static str,
    pub devices: usize,
    /// Rounds whose generator kept up (the others say nothing about the target).
    pub valid_rounds: usize,
    pub within: Option<f64>,
    pub p99_us: Option<f64>,
    pub cpu_us_per_sample: Option<f64>,
    pub holds: bool,
}

/// The median of `v` (the mean of the middle two for an even count); `None` if empty.
pub fn median(mut v: Vec<f64>) -> Option<f64> {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return None;
    }
    v.sort_unstable_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    })
}

impl BenchPoint {
    fn of(trials: &[&Trial], inside: f64) -> Self {
        let valid: Vec<&&Trial> = trials
            .iter()
            .filter(|t| t.report.generator_late == 0)
            .collect();
        let within = median(valid.iter().map(|t| t.report.within_fraction()).collect());
        Self {
            target: trials[0].target,
            path: trials[0].path,
            devices: trials[0].report.devices,
            valid_rounds: valid.len(),
            within,
            p99_us: median(valid.iter().filter_map(|t| t.report.p99_us).collect()),
            cpu_us_per_sample: median(valid.iter().filter_map(|t| t.cpu_us_per_sample).collect()),
            holds: within.is_some_and(|w| w >= inside),
        }
    }
}

fn free_port() -> anyhow::Result<u16> {
    Ok(transport::free_local_port()?)
}

struct Running {
    child: Child,
    endpoint: String,
}

impl Running {
    fn start(spec: &BenchSpec, target: Target, dir: &Path) -> anyhow::Result<Self> {
        let port = free_port()?;
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let mut cmd = match target {
            Target::Service => {
                let mut c = Command::new(&spec.service_bin);
                c.arg("--config").arg(dir.join("service.toml"));
                c.args(["--workers", &spec.service_workers.to_string()]);
                c
            }
            Target::Echo => {
                let mut c = Command::new(&spec.loadgen_bin);
                c.arg("echo");
                c
            }
        };
        cmd.args(["--listen", &endpoint, "--no-multicast-scouting"])
            .env("RUST_LOG", "warn,zenoh=error")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit());
        let child = cmd.spawn().map_err(|e| {
            anyhow::anyhow!(
                "starting {target:?} ({}): {e}",
                cmd.get_program().to_string_lossy()
            )
        })?;
        Ok(Self { child, endpoint })
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    fn stop(mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The service file of the benchmark: every `load-*` device gets one iP channel tuned to
/// the generator's plant (`tau dy/dt = -y + v`, tau 0.5 s, so alpha = 2), reference 1.
pub const SERVICE_TOML: &str = r#"controller_id = "bench"
max_devices = 100000
[[templates]]
pattern = "load-$*"
[[templates.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 2.0, kp = 5.0 }, estimator = { window = 10 } }
output = { min = -10.0, max = 10.0 }
reference = [{ kind = "constant", value = 1.0 }]
"#;

/// Attempts of a trial whose generator fell behind (a hiccup of the machine, not of the
/// target): such a run says nothing about the target, so it is run again.
const ATTEMPTS: usize = 3;

/// A trial, run again (at most [`ATTEMPTS`] times) while the generator itself fell behind;
/// every attempt is printed.
async fn trial_valid(
    spec: &BenchSpec,
    dir: &Path,
    target: Target,
    devices: usize,
    gateways: usize,
    round: usize,
) -> anyhow::Result<Trial> {
    let mut t = trial(spec, dir, target, devices, gateways, round).await?;
    for _ in 1..ATTEMPTS {
        if t.report.generator_late == 0 {
            break;
        }
        eprintln!("{}  (run again)", line(&t));
        t = trial(spec, dir, target, devices, gateways, round).await?;
    }
    Ok(t)
}

/// Every round of `targets` at one size; returns each target's medians, in `targets`'
/// order. Odd rounds run the targets in reverse order.
async fn size_point(
    spec: &BenchSpec,
    dir: &Path,
    targets: &[Target],
    devices: usize,
    gateways: usize,
    trials: &mut Vec<Trial>,
) -> anyhow::Result<Vec<BenchPoint>> {
    let mut mine: Vec<Trial> = Vec::new();
    for round in 0..spec.rounds.max(1) {
        let mut order = targets.to_vec();
        if round % 2 == 1 {
            order.reverse();
        }
        for target in order {
            let t = trial_valid(spec, dir, target, devices, gateways, round).await?;
            eprintln!("{}", line(&t));
            mine.push(t);
        }
    }
    let points = targets
        .iter()
        .map(|&target| {
            let of: Vec<&Trial> = mine.iter().filter(|t| t.target == target).collect();
            let p = BenchPoint::of(&of, spec.inside);
            eprintln!(
                "{:>7} {:>10} {:>6} devices: median of {} rounds: within {} %, p99 {} us -> {}",
                format!("{target:?}").to_lowercase(),
                p.path,
                devices,
                p.valid_rounds,
                p.within.map_or("-".into(), |w| format!("{:.3}", 100.0 * w)),
                p.p99_us.map_or("-".into(), |v| format!("{v:.0}")),
                if p.holds { "holds" } else { "does not hold" }
            );
            p
        })
        .collect();
    trials.extend(mine);
    Ok(points)
}

async fn trial(
    spec: &BenchSpec,
    dir: &Path,
    target: Target,
    devices: usize,
    gateways: usize,
    round: usize,
) -> anyhow::Result<Trial> {
    let running = Running::start(spec, target, dir)?;
    let pid = running.pid();
    let args = transport::ZenohArgs::loopback(None, vec![running.endpoint.clone()]);
    let result = async {
        let session = args.open().await?;
        let rss0 = stats::rss_bytes(pid);
        let gspec = Spec {
            devices,
            rate_hz: spec.rate_hz,
            gateways,
            prefix: "load".into(),
            warmup: spec.warmup,
            measure: spec.measure,
            // The benchmark's figures are for plants that send no copies (`docs/scale.md`).
            resend: 0,
            // The service's secret, if it has one; the anchor runs open.
            secret: match target {
                Target::Service if spec.auth => Some(protocol::auth::Secret::from_file(
                    &dir.join("fleet.secret"),
                )?),
                _ => None,
            },
        };
        // CPU and memory are read over the measured window, beside the generator.
        let (warmup, measure) = (spec.warmup, spec.measure);
        let probe = tokio::spawn(async move {
            // The generator first waits for the target's token; that and the sender's start
            // are well under this margin.
            tokio::time::sleep(warmup + Duration::from_millis(500)).await;
            let (c0, rss1) = (stats::cpu_seconds(pid), stats::rss_bytes(pid));
            let t0 = Instant::now();
            tokio::time::sleep(measure.saturating_sub(Duration::from_millis(500))).await;
            let c1 = stats::cpu_seconds(pid);
            (c0, c1, t0.elapsed(), rss1)
        });
        let report = gen::run(&session, &gspec).await?;
        let (c0, c1, took, rss1) = probe.await?;
        let _ = session.close().await;
        let cpu = c0.zip(c1).map(|(a, b)| b - a);
        // Samples answered while the probe watched: the window's rate times its length.
        let served = report.answered as f64 * took.as_secs_f64() / measure.as_secs_f64();
        anyhow::Ok(Trial {
            target,
            round,
            path: if gateways == 0 {
                "per-device"
            } else {
                "gateway"
            },
            cpu_us_per_sample: cpu.filter(|_| served > 0.0).map(|c| c * 1e6 / served),
            cpu_cores: cpu.map(|c| c / took.as_secs_f64()),
            rss_bytes_per_device: rss0
                .zip(rss1)
                .map(|(a, b)| (b as f64 - a as f64) / devices as f64),
            rss_bytes: rss1,
            report,
        })
    }
    .await;
    running.stop();
    result
}

fn line(t: &Trial) -> String {
    let r = &t.report;
    let f = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.0}"));
    format!(
        "{:>7} {:>10} {:>6} devices: answered {:>7.3} %, within {:>7.3} %, p50 {} us, p99 {} us, cpu {} us/sample{}{}",
        format!("{:?}", t.target).to_lowercase(),
        t.path,
        r.devices,
        100.0 * r.answered_fraction(),
        100.0 * r.within_fraction(),
        f(r.p50_us),
        f(r.p99_us),
        t.cpu_us_per_sample.map_or("-".into(), |v| format!("{v:.1}")),
        if r.duplicates > 0 { format!(", {} DUPLICATES", r.duplicates) } else { String::new() },
        if r.generator_late > 0 { format!(", generator late {}x (run not valid)", r.generator_late) } else { String::new() },
    )
}

/// Run a sweep on one path for both targets; returns the capacities.
async fn sweep(
    spec: &BenchSpec,
    dir: &Path,
    grid: &[usize],
    gateway_path: bool,
    trials: &mut Vec<Trial>,
    points: &mut Vec<BenchPoint>,
) -> anyhow::Result<(Option<usize>, Option<usize>)> {
    let gws = |n: usize| {
        if gateway_path {
            n.div_ceil(spec.per_gateway.max(1))
        } else {
            0
        }
    };
    let mut caps = [None, None];
    let mut fails: [Option<usize>; 2] = [None, None];
    let targets = [Target::Service, Target::Echo];
    for &n in grid {
        // A target that failed a smaller size is not run again, except at the size whose
        // round trips the summary compares, which both always run.
        let compared = !gateway_path && n == spec.p99_at;
        let live: Vec<Target> = targets
            .iter()
            .enumerate()
            .filter(|(k, _)| fails[*k].is_none() || compared)
            .map(|(_, t)| *t)
            .collect();
        if live.is_empty() {
            break;
        }
        for p in size_point(spec, dir, &live, n, gws(n), trials).await? {
            let k = targets.iter().position(|t| *t == p.target).unwrap_or(0);
            if fails[k].is_none() {
                if p.holds {
                    caps[k] = Some(n);
                } else {
                    fails[k] = Some(n);
                }
            }
            points.push(p);
        }
    }
    for (k, &target) in targets.iter().enumerate() {
        let mut lo = caps[k].unwrap_or(0);
        let Some(mut hi) = fails[k] else { continue };
        for _ in 0..spec.refine {
            let mid = (lo + hi) / 2;
            if mid <= lo || hi - lo <= (hi / 20).max(1) {
                break;
            }
            let p = size_point(spec, dir, &[target], mid, gws(mid), trials)
                .await?
                .remove(0);
            if p.holds {
                lo = mid;
                caps[k] = Some(mid);
            } else {
                hi = mid;
            }
            points.push(p);
        }
    }
    Ok((caps[0], caps[1]))
}

/// Run the whole benchmark and write `bench.json` and `bench.md` under `spec.out`.
pub async fn run(spec: &BenchSpec) -> anyhow::Result<Results> {
    for (what, p) in [
        ("controller-service", &spec.service_bin),
        ("loadgen", &spec.loadgen_bin),
    ] {
        anyhow::ensure!(
            p.is_file(),
            "{what} binary not found at {} (build it: cargo build --release --bins)",
            p.display()
        );
    }
    let dir = tempfile::tempdir()?;
    let toml = if spec.auth {
        let secret = protocol::auth::Secret::random()?;
        std::fs::write(dir.path().join("fleet.secret"), secret.to_hex())?;
        format!("secret_file = \"fleet.secret\"\n{SERVICE_TOML}")
    } else {
        SERVICE_TOML.to_string()
    };
    std::fs::write(dir.path().join("service.toml"), toml)?;
    std::fs::create_dir_all(&spec.out)?;
    let mut trials = Vec::new();
    let mut points = Vec::new();
    eprintln!(
        "per-device path: one message per device per period, {} Hz",
        spec.rate_hz
    );
    let (cs, ce) = sweep(
        spec,
        dir.path(),
        &spec.per_device,
        false,
        &mut trials,
        &mut points,
    )
    .await?;
    eprintln!(
        "gateway path: {} plants per gateway, one batch per gateway per period",
        spec.per_gateway
    );
    let (gs, ge) = sweep(
        spec,
        dir.path(),
        &spec.gateway_devices,
        true,
        &mut trials,
        &mut points,
    )
    .await?;
    let results = Results {
        rate_hz: spec.rate_hz,
        service_workers: spec.service_workers,
        inside: spec.inside,
        warmup_s: spec.warmup.as_secs_f64(),
        measure_s: spec.measure.as_secs_f64(),
        per_gateway: spec.per_gateway,
        rounds: spec.rounds.max(1),
        p99_at: spec.p99_at,
        trials,
        points,
        capacity_service: cs,
        capacity_echo: ce,
        gateway_capacity_service: gs,
        gateway_capacity_echo: ge,
        auth: spec.auth,
    };
    std::fs::write(
        spec.out.join("bench.json"),
        serde_json::to_string_pretty(&results)?,
    )?;
    let md = markdown(&results);
    std::fs::File::create(spec.out.join("bench.md"))?.write_all(md.as_bytes())?;
    Ok(results)
}

/// The results as the README shows them: the medians per size, then every round.
pub fn markdown(r: &Results) -> String {
    let mut s = String::new();
    let f = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.0}"));
    let pct = |x: Option<f64>| x.map_or("-".into(), |v| format!("{:.3} %", 100.0 * v));
    let name = |t: Target| format!("{t:?}").to_lowercase();
    s += &format!(
        "Rate {} Hz; service workers {}; {} rounds per size, the targets in alternating order; a size holds when the median round has {:.1} % of its commands back within the period (warm-up {} s, window {} s). {}\n\n",
        r.rate_hz, r.service_workers, r.rounds, 100.0 * r.inside, r.warmup_s, r.measure_s,
        if r.auth { "The service with keys: every sample and batch sealed, every command checked (the echo open)." } else { "Open: no MACs." }
    );
    s += "Medians over the rounds:\n\n| path | devices | target | valid rounds | within period | p99 us | CPU us/sample | holds |\n|---|---:|---|---:|---:|---:|---:|---|\n";
    let mut points: Vec<&BenchPoint> = r.points.iter().collect();
    points.sort_by_key(|p| (p.path, p.devices, name(p.target)));
    for p in points {
        s += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
            p.path,
            p.devices,
            name(p.target),
            p.valid_rounds,
            pct(p.within),
            f(p.p99_us),
            p.cpu_us_per_sample
                .map_or("-".into(), |v| format!("{v:.1}")),
            if p.holds { "yes" } else { "no" }
        );
    }
    s += "\nEvery round:\n\n| path | devices | target | round | answered | within period | p50 us | p99 us | CPU us/sample | CPU cores | RSS/device | generator late |\n|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n";
    for t in &r.trials {
        let rp = &t.report;
        s += &format!(
            "| {} | {} | {} | {} | {:.3} % | {:.3} % | {} | {} | {} | {} | {} | {} |\n",
            t.path,
            rp.devices,
            name(t.target),
            t.round,
            100.0 * rp.answered_fraction(),
            100.0 * rp.within_fraction(),
            f(rp.p50_us),
            f(rp.p99_us),
            t.cpu_us_per_sample
                .map_or("-".into(), |v| format!("{v:.1}")),
            t.cpu_cores.map_or("-".into(), |v| format!("{v:.2}")),
            t.rss_bytes_per_device
                .map_or("-".into(), |v| format!("{:.1} KiB", v / 1024.0)),
            rp.generator_late,
        );
    }
    let cap = |x: Option<usize>| x.map_or("none held".into(), |n| n.to_string());
    let ratio = |a: Option<usize>, b: Option<usize>| match (a, b) {
        (Some(a), Some(b)) if b > 0 => format!("{:.2}x", a as f64 / b as f64),
        _ => "-".into(),
    };
    s += &format!(
        "\nCapacity, per-device path: service {}, echo {} (ratio {}).\n",
        cap(r.capacity_service),
        cap(r.capacity_echo),
        ratio(r.capacity_service, r.capacity_echo)
    );
    if r.points.iter().any(|p| p.path == "gateway") {
        s += &format!(
            "Capacity through gateways ({} plants each): service {}, echo {} (ratio {}).\n",
            r.per_gateway,
            cap(r.gateway_capacity_service),
            cap(r.gateway_capacity_echo),
            ratio(r.gateway_capacity_service, r.gateway_capacity_echo)
        );
    } else {
        s += "Capacity through gateways: not measured (no gateway sizes).\n";
    }
    if let Some((a, b)) = p99_pair(r) {
        s += &format!(
            "p99 at {} devices (median of the rounds): service {a:.0} us, echo {b:.0} us (ratio {:.2}x).\n",
            r.p99_at,
            a / b
        );
    }
    if let Some(m) = rss_per_device(r) {
        s += &format!(
            "Service resident memory per device, largest gateway fleet it held: {:.1} KiB.\n",
            m / 1024.0
        );
    }
    for target in [Target::Service, Target::Echo] {
        if let Some((a, b, m)) = rss_slope(r, target) {
            s += &format!(
                "Resident memory per device added through gateways, {a} to {b} plants (medians), {}: {:.1} KiB.\n",
                name(target),
                m / 1024.0
            );
        }
    }
    s
}

/// What each device adds to the resident memory of `target` through gateways, without
/// what serving any load costs at all (threads' buffers, the allocator's pages in use,
/// code paged in): the slope of the median resident memory between the smallest and the
/// largest gateway fleet measured (those sizes, and the bytes per device). `None` with
/// fewer than two sizes.
pub fn rss_slope(r: &Results, target: Target) -> Option<(usize, usize, f64)> {
    let at = |n: usize| {
        median(
            r.trials
                .iter()
                .filter(|t| t.target == target && t.path == "gateway" && t.report.devices == n)
                .filter_map(|t| t.rss_bytes.map(|b| b as f64))
                .collect(),
        )
    };
    let sizes = || {
        r.trials
            .iter()
            .filter(|t| t.target == target && t.path == "gateway" && t.rss_bytes.is_some())
            .map(|t| t.report.devices)
    };
    let (a, b) = (sizes().min()?, sizes().max()?);
    (b > a).then_some(())?;
    Some((a, b, (at(b)? - at(a)?) / (b - a) as f64))
}

/// The runs of `loadgen bench --repeat`: each run's p99 at [`Results::p99_at`] devices,
/// the service's over the echo's, and their median (the figure the goal is set on: one
/// run's ratio moves with the machine's tail by more than the service does). A run
/// without both p99s is listed and left out of the median.
pub fn repeated_markdown(runs: &[Results]) -> String {
    let pairs: Vec<Option<(f64, f64)>> = runs.iter().map(p99_pair).collect();
    let at = runs.first().map_or(0, |r| r.p99_at);
    let mut s = format!(
        "p99 round trip at {at} devices per device, {} runs:\n\n| run | service us | echo us | ratio |\n|---:|---:|---:|---:|\n",
        runs.len()
    );
    for (k, p) in pairs.iter().enumerate() {
        s += &match p {
            Some((a, b)) => format!("| {} | {a:.0} | {b:.0} | {:.2} |\n", k + 1, a / b),
            None => format!("| {} | - | - | - |\n", k + 1),
        };
    }
    let ratios: Vec<f64> = pairs
        .iter()
        .flatten()
        .map(|(a, b)| a / b)
        .filter(|r| r.is_finite())
        .collect();
    let n = ratios.len();
    s += &match median(ratios) {
        Some(m) => format!("\nMedian ratio over the {n} runs with both: {m:.2}x.\n"),
        None => "\nNo run measured both p99s.\n".to_string(),
    };
    s
}

/// The service's and the anchor's median p99 at [`Results::p99_at`] devices, per device.
pub fn p99_pair(r: &Results) -> Option<(f64, f64)> {
    let at = |target: Target| {
        r.points
            .iter()
            .find(|p| p.target == target && p.path == "per-device" && p.devices == r.p99_at)
            .and_then(|p| p.p99_us)
    };
    Some((at(Target::Service)?, at(Target::Echo)?))
}

/// The service's resident memory per device at the largest gateway fleet it held (the
/// median of its rounds).
pub fn rss_per_device(r: &Results) -> Option<f64> {
    let n = r.gateway_capacity_service?;
    median(
        r.trials
            .iter()
            .filter(|t| t.target == Target::Service && t.path == "gateway" && t.report.devices == n)
            .filter_map(|t| t.rss_bytes_per_device)
            .collect(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn round(target: Target, within: u64, p99: f64, late: u64) -> Trial {
        Trial {
            target,
            round: 0,
            path: "per-device",
            report: LoadReport {
                devices: 100,
                sent: 1000,
                answered: 1000,
                within,
                p99_us: Some(p99),
                generator_late: late,
                ..LoadReport::default()
            },
            cpu_us_per_sample: None,
            cpu_cores: None,
            rss_bytes_per_device: None,
            rss_bytes: None,
        }
    }

    fn gateway_round(target: Target, devices: usize, rss: u64) -> Trial {
        let mut t = round(target, 1000, 300.0, 0);
        t.path = "gateway";
        t.report.devices = devices;
        t.rss_bytes = Some(rss);
        t
    }

    /// The slope between the smallest and the largest fleet, of the medians, per target.
    #[test]
    fn memory_per_added_device_is_the_slope_of_the_medians() {
        let (s, e) = (Target::Service, Target::Echo);
        let mut r = empty_results();
        r.trials = vec![
            gateway_round(s, 2000, 40 << 20),
            gateway_round(s, 2000, 90 << 20), // an outlier: the median ignores it
            gateway_round(s, 2000, 41 << 20),
            gateway_round(s, 10_000, 73 << 20),
            gateway_round(s, 5000, 1),
            gateway_round(e, 10_000, 30 << 20),
        ];
        let (a, b, m) = rss_slope(&r, s).unwrap();
        assert_eq!((a, b), (2000, 10_000));
        let want = (73.0 - 41.0) * 1048576.0 / 8000.0;
        assert!((m - want).abs() < 1e-6, "{m} against {want}");
        assert_eq!(rss_slope(&r, e), None, "one size: no slope");
        assert!(markdown(&r).contains(&format!("service: {:.1} KiB", want / 1024.0)));
    }

    fn empty_results() -> Results {
        Results {
            rate_hz: 100.0,
            service_workers: 1,
            inside: 0.999,
            warmup_s: 1.0,
            measure_s: 1.0,
            per_gateway: 1000,
            rounds: 3,
            p99_at: 100,
            trials: Vec::new(),
            points: Vec::new(),
            capacity_service: None,
            capacity_echo: None,
            gateway_capacity_service: None,
            gateway_capacity_echo: None,
            auth: false,
        }
    }

    fn with_p99(service: Option<f64>, echo: f64) -> Results {
        let mut r = empty_results();
        for (target, p99) in [(Target::Service, service), (Target::Echo, Some(echo))] {
            r.points.push(BenchPoint {
                target,
                path: "per-device",
                devices: 100,
                valid_rounds: 3,
                within: Some(1.0),
                p99_us: p99,
                cpu_us_per_sample: None,
                holds: true,
            });
        }
        r
    }

    /// `--repeat`: every run's ratio listed, the median over those with both p99s.
    #[test]
    fn repeated_runs_report_the_median_ratio() {
        let runs = [
            with_p99(Some(300.0), 200.0), // 1.50
            with_p99(Some(100.0), 200.0), // 0.50
            with_p99(None, 200.0),        // no service p99: left out
            with_p99(Some(220.0), 200.0), // 1.10
        ];
        let md = repeated_markdown(&runs);
        assert!(md.contains("| 1 | 300 | 200 | 1.50 |"), "{md}");
        assert!(md.contains("| 3 | - | - | - |"), "{md}");
        assert!(
            md.contains("Median ratio over the 3 runs with both: 1.10x."),
            "{md}"
        );
        assert!(
            markdown(&runs[0]).contains("Capacity through gateways: not measured"),
            "no gateway sweep is not a capacity of none"
        );
        let none = repeated_markdown(&[with_p99(None, 1.0)]);
        assert!(none.contains("No run measured both p99s."), "{none}");
    }

    #[test]
    fn the_median_of_odd_and_even_counts() {
        assert_eq!(median(vec![]), None);
        assert_eq!(median(vec![3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(vec![4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(vec![f64::NAN, 5.0]), Some(5.0));
    }

    #[test]
    fn one_bad_round_of_three_decides_nothing_and_late_rounds_do_not_count() {
        let s = Target::Service;
        // Two rounds at 100 %, one at 98 %: the median holds.
        let t = [
            round(s, 1000, 300.0, 0),
            round(s, 980, 900.0, 0),
            round(s, 1000, 320.0, 0),
        ];
        let p = BenchPoint::of(&t.iter().collect::<Vec<_>>(), 0.999);
        assert!(p.holds);
        assert_eq!(p.p99_us, Some(320.0));
        assert_eq!(p.valid_rounds, 3);
        // Two bad rounds of three: it does not.
        let t = [
            round(s, 990, 300.0, 0),
            round(s, 980, 900.0, 0),
            round(s, 1000, 320.0, 0),
        ];
        assert!(!BenchPoint::of(&t.iter().collect::<Vec<_>>(), 0.999).holds);
        // A round whose generator fell behind is left out, good or bad.
        let t = [round(s, 1000, 300.0, 3), round(s, 990, 900.0, 0)];
        let p = BenchPoint::of(&t.iter().collect::<Vec<_>>(), 0.999);
        assert_eq!(p.valid_rounds, 1);
        assert!(!p.holds);
        // No valid round: nothing holds.
        let t = [round(s, 1000, 300.0, 1)];
        let p = BenchPoint::of(&t.iter().collect::<Vec<_>>(), 0.999);
        assert!(!p.holds);
        assert_eq!(p.within, None);
    }
}
