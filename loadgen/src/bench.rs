//! The benchmark: the service and the echo anchor, side by side in one run, over a sweep
//! of fleet sizes, on the per-device path and through gateways.
//!
//! Every trial starts its target as a process of its own (so its CPU time and memory can
//! be read from `/proc`, and no state leaks between trials), connects a fresh generator
//! session to it on loopback (peers, multicast scouting off), runs the warm-up and the
//! measured window, and stops the target. At each fleet size the service and the anchor
//! run one after the other, so a busy machine hurts both alike. The capacity of a target is
//! the largest fleet with at least [`BenchSpec::inside`] of its commands back within the
//! period; after the grid, a few bisection steps between the last size that held and the
//! first that did not refine it.

use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde::Serialize;

use crate::gen::{self, Report, Spec};
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
    /// Where results go (`bench.json`, `bench.md`).
    pub out: PathBuf,
}

/// One trial.
#[derive(Debug, Clone, Serialize)]
pub struct Trial {
    pub target: Target,
    pub path: &'static str,
    pub report: Report,
    /// Target CPU time over the window per answered sample (us).
    pub cpu_us_per_sample: Option<f64>,
    /// Target CPU over the window, in cores (1.0 = one core busy).
    pub cpu_cores: Option<f64>,
    /// Target resident memory after the warm-up minus before the generator, per device.
    pub rss_bytes_per_device: Option<f64>,
    pub rss_bytes: Option<u64>,
}

impl Trial {
    fn holds(&self, inside: f64) -> bool {
        self.report.within_fraction() >= inside && self.report.generator_late == 0
    }
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
    pub trials: Vec<Trial>,
    /// Largest per-device fleet that held, per target.
    pub capacity_service: Option<usize>,
    pub capacity_echo: Option<usize>,
    /// Largest gateway fleet that held, per target.
    pub gateway_capacity_service: Option<usize>,
    pub gateway_capacity_echo: Option<usize>,
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
) -> anyhow::Result<Trial> {
    let mut t = trial(spec, dir, target, devices, gateways).await?;
    for _ in 1..ATTEMPTS {
        if t.report.generator_late == 0 {
            break;
        }
        eprintln!("{}  (run again)", line(&t));
        t = trial(spec, dir, target, devices, gateways).await?;
    }
    Ok(t)
}

async fn trial(
    spec: &BenchSpec,
    dir: &Path,
    target: Target,
    devices: usize,
    gateways: usize,
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
        for (k, &target) in targets.iter().enumerate() {
            if fails[k].is_some() {
                continue;
            }
            let t = trial_valid(spec, dir, target, n, gws(n)).await?;
            eprintln!("{}", line(&t));
            if t.holds(spec.inside) {
                caps[k] = Some(n);
            } else {
                fails[k] = Some(n);
            }
            trials.push(t);
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
            let t = trial_valid(spec, dir, target, mid, gws(mid)).await?;
            eprintln!("{}", line(&t));
            if t.holds(spec.inside) {
                lo = mid;
                caps[k] = Some(mid);
            } else {
                hi = mid;
            }
            trials.push(t);
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
    std::fs::write(dir.path().join("service.toml"), SERVICE_TOML)?;
    std::fs::create_dir_all(&spec.out)?;
    let mut trials = Vec::new();
    eprintln!(
        "per-device path: one message per device per period, {} Hz",
        spec.rate_hz
    );
    let (cs, ce) = sweep(spec, dir.path(), &spec.per_device, false, &mut trials).await?;
    eprintln!(
        "gateway path: {} plants per gateway, one batch per gateway per period",
        spec.per_gateway
    );
    let (gs, ge) = sweep(spec, dir.path(), &spec.gateway_devices, true, &mut trials).await?;
    let results = Results {
        rate_hz: spec.rate_hz,
        service_workers: spec.service_workers,
        inside: spec.inside,
        warmup_s: spec.warmup.as_secs_f64(),
        measure_s: spec.measure.as_secs_f64(),
        per_gateway: spec.per_gateway,
        trials,
        capacity_service: cs,
        capacity_echo: ce,
        gateway_capacity_service: gs,
        gateway_capacity_echo: ge,
    };
    std::fs::write(
        spec.out.join("bench.json"),
        serde_json::to_string_pretty(&results)?,
    )?;
    let md = markdown(&results);
    std::fs::File::create(spec.out.join("bench.md"))?.write_all(md.as_bytes())?;
    Ok(results)
}

/// The results as the README shows them.
pub fn markdown(r: &Results) -> String {
    let mut s = String::new();
    let f = |x: Option<f64>| x.map_or("-".into(), |v| format!("{v:.0}"));
    s += &format!(
        "Rate {} Hz; service workers {}; a size holds when {:.1} % of its commands are back within the period (warm-up {} s, window {} s).\n\n",
        r.rate_hz, r.service_workers, 100.0 * r.inside, r.warmup_s, r.measure_s
    );
    s += "| path | devices | target | answered | within period | p50 us | p99 us | CPU us/sample | CPU cores | RSS/device |\n|---|---:|---|---:|---:|---:|---:|---:|---:|---:|\n";
    for t in &r.trials {
        let rp = &t.report;
        s += &format!(
            "| {} | {} | {} | {:.3} % | {:.3} % | {} | {} | {} | {} | {} |\n",
            t.path,
            rp.devices,
            format!("{:?}", t.target).to_lowercase(),
            100.0 * rp.answered_fraction(),
            100.0 * rp.within_fraction(),
            f(rp.p50_us),
            f(rp.p99_us),
            t.cpu_us_per_sample
                .map_or("-".into(), |v| format!("{v:.1}")),
            t.cpu_cores.map_or("-".into(), |v| format!("{v:.2}")),
            t.rss_bytes_per_device
                .map_or("-".into(), |v| format!("{:.1} KiB", v / 1024.0)),
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
    s += &format!(
        "Capacity through gateways ({} plants each): service {}, echo {} (ratio {}).\n",
        r.per_gateway,
        cap(r.gateway_capacity_service),
        cap(r.gateway_capacity_echo),
        ratio(r.gateway_capacity_service, r.gateway_capacity_echo)
    );
    // The p99 ratio at the smallest per-device size both ran.
    let at = |target: Target, n: usize| {
        r.trials
            .iter()
            .find(|t| t.target == target && t.path == "per-device" && t.report.devices == n)
    };
    if let Some(n) = r
        .trials
        .iter()
        .filter(|t| t.path == "per-device")
        .map(|t| t.report.devices)
        .min()
    {
        if let (Some(a), Some(b)) = (at(Target::Service, n), at(Target::Echo, n)) {
            if let (Some(pa), Some(pb)) = (a.report.p99_us, b.report.p99_us) {
                s += &format!(
                    "p99 at {n} devices: service {pa:.0} us, echo {pb:.0} us (ratio {:.2}x).\n",
                    pa / pb
                );
            }
        }
    }
    s
}
