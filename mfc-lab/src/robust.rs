//! The robustness benchmark: every controller, untouched, on a seeded family of variations
//! of the AERO simulator, each judged against its own run on the nominal plant.
//!
//! The paper's promise is that the ultra-local model absorbs what the plant does
//! differently, with no retuning. This measures how far that holds: for each variation,
//! each controller's RMS over its nominal RMS (per channel), the fraction of samples at
//! the amplifier's limit, the chatter (mean |v(k) - v(k-1)| in V) and the sign changes of
//! the command per second while the reference holds still. The family is one factor at a
//! time at the ends of each range (so a bad cell names its cause), then `random` seeded
//! combinations of all factors (log-uniform inside the ranges).
//!
//! | factor | range | what changes in `AeroParams` |
//! |---|---|---|
//! | `rotor` | x0.5 .. x4 | `rotor_time_constant` (the motors' lag) |
//! | `mass` | 0 .. 10 g | `added_mass` |
//! | `spring` | x0.3 .. x3 | `ksp` |
//! | `damping` | x0.3 .. x3 | `dp`, `dy` |
//! | `noise` | 0 .. 5 counts | `pitch_noise`, `yaw_noise`: this many encoder counts (std) |
//! | `motor` | x0.5 .. x2 | `kpp`, `kyy`, `kpy`, `kyp` |
//! | `encoder` | /1 .. /8 | `pitch_counts`, `yaw_counts` divided |
//!
//! The example plants behind drivers are varied through their command lines
//! ([`driver_factors`]): the heater's gain, time constant and dead time, the DC motor's
//! friction, backlash and inertia, each x0.5 to x2 of the scenario's value (or the driver's
//! default where the scenario gives none).
//!
//! No I/O here but the runs: [`family`] and [`judge`] are plain functions of their inputs,
//! and the runs are [`crate::offline::simulate`] (lockstep, no clock), so a seed gives the
//! same table on every machine.

use std::collections::BTreeMap;

use aero_sim::rng::Rng;
use aero_sim::AeroParams;
use plant::scenario::{ControllerSet, PlantSource, Scenario};
use serde::Serialize;

use crate::offline::{simulate, RunError};

/// A factor of the family, and its range (low, high) as the table above gives it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Factor {
    /// The rotors' lag time constant, times x.
    Rotor,
    /// Added mass at the arm, x grams.
    Mass,
    /// Pitch stiffness, times x.
    Spring,
    /// Pitch and yaw damping, times x.
    Damping,
    /// Measurement noise of x encoder counts (std), on pitch and yaw.
    Noise,
    /// Every motor's torque per volt, times x.
    Motor,
    /// Encoder counts per revolution, divided by x.
    Encoder,
}

impl Factor {
    /// Every factor, in the table's order.
    pub const ALL: [Factor; 7] = [
        Factor::Rotor,
        Factor::Mass,
        Factor::Spring,
        Factor::Damping,
        Factor::Noise,
        Factor::Motor,
        Factor::Encoder,
    ];

    /// Its range: (low, nominal, high).
    pub fn range(self) -> (f64, f64, f64) {
        match self {
            Factor::Rotor => (0.5, 1.0, 4.0),
            Factor::Mass => (0.0, 0.0, 10.0),
            Factor::Spring | Factor::Damping => (0.3, 1.0, 3.0),
            Factor::Noise => (0.0, 0.0, 5.0),
            Factor::Motor => (0.5, 1.0, 2.0),
            Factor::Encoder => (1.0, 1.0, 8.0),
        }
    }

    /// The factor of this name ([`Factor::name`]).
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|f| f.name() == name)
    }

    /// Its name in tables and variation names.
    pub fn name(self) -> &'static str {
        match self {
            Factor::Rotor => "rotor",
            Factor::Mass => "mass",
            Factor::Spring => "spring",
            Factor::Damping => "damping",
            Factor::Noise => "noise",
            Factor::Motor => "motor",
            Factor::Encoder => "encoder",
        }
    }

    fn label(self, x: f64) -> String {
        match self {
            Factor::Mass => format!("{}{x:.3}g", self.name()),
            Factor::Noise => format!("{}{x:.3}", self.name()),
            Factor::Encoder => format!("{}/{x:.3}", self.name()),
            _ => format!("{}x{x:.3}", self.name()),
        }
        .replace(".000", "")
    }

    /// `p` with this factor at `x`.
    pub fn apply(self, p: &mut AeroParams, x: f64) {
        let count = |n: u32| {
            if n == 0 {
                0.0
            } else {
                std::f64::consts::TAU / f64::from(n)
            }
        };
        match self {
            Factor::Rotor => p.rotor_time_constant *= x,
            Factor::Mass => p.added_mass += x / 1000.0,
            Factor::Spring => p.ksp *= x,
            Factor::Damping => {
                p.dp *= x;
                p.dy *= x;
            }
            Factor::Noise => {
                p.pitch_noise += x * count(p.pitch_counts);
                p.yaw_noise += x * count(p.yaw_counts);
            }
            Factor::Motor => {
                for k in [&mut p.kpp, &mut p.kyy, &mut p.kpy, &mut p.kyp] {
                    *k *= x;
                }
            }
            Factor::Encoder => {
                for c in [&mut p.pitch_counts, &mut p.yaw_counts] {
                    *c = ((f64::from(*c) / x).round() as u32).max(16);
                }
            }
        }
    }
}

/// One plant of the family: its name and the factors moved from nominal.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Variation {
    /// `nominal`, one factor (`rotorx4`), or `random-N`.
    pub name: String,
    /// The AERO's factors moved, and where to.
    pub factors: Vec<(Factor, f64)>,
    /// A driver plant's factors ([`DriverFactor::name`]) and their multipliers.
    pub scales: Vec<(&'static str, f64)>,
}

/// A factor of a plant behind a driver: the flags it scales (with the driver's defaults,
/// used where the scenario gives no value) and its range of multipliers.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DriverFactor {
    /// Its name in tables.
    pub name: &'static str,
    /// Flags and their defaults.
    pub flags: &'static [(&'static str, f64)],
    /// Multipliers: (low, high).
    pub range: (f64, f64),
}

/// The heater (`plants/heater/heater.py`): static gain, time constant, dead time.
pub const HEATER: [DriverFactor; 3] = [
    DriverFactor {
        name: "gain",
        flags: &[("--gain", 2.5)],
        range: (0.5, 2.0),
    },
    DriverFactor {
        name: "tau",
        flags: &[("--tau", 20.0)],
        range: (0.5, 2.0),
    },
    DriverFactor {
        name: "deadtime",
        flags: &[("--dead-time", 2.0)],
        range: (0.5, 2.0),
    },
];

/// The DC motor (`plants/dc-motor/dc_motor.py`): friction (motor and load), backlash,
/// inertia (motor and load).
pub const MOTOR: [DriverFactor; 3] = [
    DriverFactor {
        name: "friction",
        flags: &[("--coulomb", 0.01), ("--load-coulomb", 0.002)],
        range: (0.5, 2.0),
    },
    DriverFactor {
        name: "backlash",
        flags: &[("--backlash", 0.01)],
        range: (0.5, 2.0),
    },
    DriverFactor {
        name: "inertia",
        flags: &[("--inertia", 2e-5), ("--load-inertia", 1e-4)],
        range: (0.5, 2.0),
    },
];

/// The factors of the driver `argv` runs, if the benchmark knows it (by its script's
/// file name).
pub fn driver_factors(argv: &[String]) -> Option<&'static [DriverFactor]> {
    argv.iter().find_map(|a| {
        let file = std::path::Path::new(a).file_name()?.to_str()?;
        match file {
            "heater.py" => Some(&HEATER[..]),
            "dc_motor.py" => Some(&MOTOR[..]),
            _ => None,
        }
    })
}

/// `argv` with each factor of `scales` applied: every flag it names set to its value in
/// `argv` (or its default) times the multiplier.
pub fn driver_argv(argv: &[String], table: &[DriverFactor], scales: &[(&str, f64)]) -> Vec<String> {
    let mut out = argv.to_vec();
    for &(name, x) in scales {
        let Some(f) = table.iter().find(|f| f.name == name) else {
            continue;
        };
        for &(flag, default) in f.flags {
            match out.iter().position(|a| a == flag) {
                Some(i) if i + 1 < out.len() => {
                    let v: f64 = out[i + 1].parse().unwrap_or(default);
                    out[i + 1] = format!("{}", v * x);
                }
                _ => out.extend([flag.to_string(), format!("{}", default * x)]),
            }
        }
    }
    out
}

/// A driver plant's family: nominal, each factor alone at each end, then `random`
/// combinations (log-uniform multipliers) drawn with `seed`.
pub fn driver_family(table: &[DriverFactor], seed: u64, random: usize) -> Vec<Variation> {
    let one = |name: String, scales| Variation {
        name,
        factors: vec![],
        scales,
    };
    let mut v = vec![one("nominal".into(), vec![])];
    for f in table {
        for x in [f.range.0, f.range.1] {
            v.push(one(format!("{}x{x}", f.name), vec![(f.name, x)]));
        }
    }
    let mut rng = Rng::new(seed);
    for i in 0..random {
        let scales = table
            .iter()
            .map(|f| (f.name, draw(&mut rng, f.range.0, f.range.1)))
            .collect();
        v.push(one(format!("random-{}", i + 1), scales));
    }
    v
}

impl Variation {
    /// `base` with this variation's factors applied, in [`Factor::ALL`]'s order (noise is
    /// counted in the nominal encoder's counts, before a coarser encoder).
    pub fn params(&self, base: &AeroParams) -> AeroParams {
        let mut p = base.clone();
        let mut factors = self.factors.clone();
        factors.sort_by_key(|f| f.0);
        for (f, x) in factors {
            f.apply(&mut p, x);
        }
        p
    }
}

/// The family: the nominal plant, each factor alone at each end of its range, then
/// `random` combinations of every factor drawn with `seed`.
pub fn family(seed: u64, random: usize) -> Vec<Variation> {
    family_of(&Factor::ALL, seed, random)
}

/// [`family`] over some factors only: each of them alone at both ends, then `random`
/// seeded combinations of them (the others nominal). A slice that runs in seconds, for CI.
pub fn family_of(factors: &[Factor], seed: u64, random: usize) -> Vec<Variation> {
    let mut v = vec![Variation {
        name: "nominal".into(),
        factors: vec![],
        scales: vec![],
    }];
    for &f in factors {
        let (lo, nominal, hi) = f.range();
        for x in [lo, hi].into_iter().filter(|x| *x != nominal) {
            v.push(Variation {
                name: f.label(x),
                factors: vec![(f, x)],
                scales: vec![],
            });
        }
    }
    let mut rng = Rng::new(seed);
    for i in 0..random {
        let factors = factors
            .iter()
            .map(|&f| {
                let (lo, _, hi) = f.range();
                (f, draw(&mut rng, lo, hi))
            })
            .collect();
        v.push(Variation {
            name: format!("random-{}", i + 1),
            factors,
            scales: vec![],
        });
    }
    v
}

/// A value in [lo, hi], to 3 decimals: log-uniform where the range is a ratio, uniform
/// where it starts at 0.
fn draw(rng: &mut Rng, lo: f64, hi: f64) -> f64 {
    let u = rng.uniform();
    let x = if lo > 0.0 {
        (lo.ln() + u * (hi.ln() - lo.ln())).exp()
    } else {
        lo + u * (hi - lo)
    };
    (x * 1000.0).round() / 1000.0
}

/// One controller on one variation.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Cell {
    /// The controller set's name.
    pub controller: String,
    /// The variation's name.
    pub variation: String,
    /// Per channel: RMS of the tracking error.
    pub rms: Vec<f64>,
    /// Per channel: RMS over this controller's nominal RMS.
    pub ratio: Vec<f64>,
    /// Per channel: fraction of samples at the amplifier's limit.
    pub saturated: Vec<f64>,
    /// Per channel: mean |v(k) - v(k-1)| (V).
    pub chatter: Vec<f64>,
    /// Per channel: sign changes of the command per second while the reference holds
    /// still (at least 1 s after it last moved).
    pub hold_flips: Vec<f64>,
    /// The run went to the end and never hit the pitch stop.
    pub safe: bool,
}

/// Sign changes of `v` per second over the periods where the reference `r` has held still
/// for at least `settle` periods (a hold: what a hold costs the actuator); 0 if no hold.
pub fn hold_flips(r: &[f64], v: &[f64], settle: usize, h: f64) -> f64 {
    let (mut still, mut held, mut flips, mut last) = (0usize, 0usize, 0usize, 0.0f64);
    for k in 1..r.len().min(v.len()) {
        still = if r[k] == r[k - 1] { still + 1 } else { 0 };
        if still < settle {
            last = 0.0;
            continue;
        }
        held += 1;
        if v[k] != 0.0 {
            if last != 0.0 && v[k].signum() != last.signum() {
                flips += 1;
            }
            last = v[k];
        }
    }
    if held == 0 {
        0.0
    } else {
        flips as f64 / (held as f64 * h)
    }
}

/// What one run measured, per channel (see [`Cell`]).
#[derive(Debug, Clone)]
struct Measured {
    rms: Vec<f64>,
    saturated: Vec<f64>,
    chatter: Vec<f64>,
    hold_flips: Vec<f64>,
    safe: bool,
}

/// `controller` on `scenario` with `plant` instead of its own.
fn measure(
    scenario: &Scenario,
    plant: PlantSource,
    controller: &ControllerSet,
) -> Result<Measured, RunError> {
    let mut s = scenario.clone();
    s.plant = plant;
    let sim = simulate(&s, controller, true)?;
    // The plant's true outputs where the simulator gives them: a noisier sensor is then
    // judged by what the plant did, not by the noise the controller could never remove.
    let m = sim.summary.truth.as_ref().unwrap_or(&sim.summary.channels);
    let settle = (1.0 / s.period).round() as usize;
    Ok(Measured {
        rms: m.iter().map(|x| x.rms).collect(),
        saturated: m.iter().map(|x| x.saturated_fraction).collect(),
        chatter: m.iter().map(|x| x.control_variation).collect(),
        hold_flips: sim
            .record
            .traces
            .iter()
            .map(|tr| hold_flips(&tr.y_ref, &tr.v, settle, s.period))
            .collect(),
        safe: sim.summary.completed && sim.summary.limit_hits == 0,
    })
}

/// `scenario`'s plant as `v` varies it.
fn varied(scenario: &Scenario, v: &Variation) -> Result<PlantSource, RunError> {
    match &scenario.plant {
        PlantSource::Aero(base) => Ok(PlantSource::Aero(v.params(base))),
        PlantSource::Driver(cmd) => {
            let table = driver_factors(&cmd.argv).ok_or_else(|| {
                RunError::Bench(format!(
                    "no family for the driver {:?}: the benchmark varies the AERO simulator, heater.py and dc_motor.py",
                    cmd.argv
                ))
            })?;
            let mut cmd = cmd.clone();
            cmd.argv = driver_argv(&cmd.argv, table, &v.scales);
            Ok(PlantSource::Driver(cmd))
        }
        PlantSource::Modbus(_) | PlantSource::OpcUa(_) => Err(RunError::Bench(
            "a plant behind a server (Modbus, OPC UA) has no offline family to vary".into(),
        )),
    }
}

/// Run every controller on every variation of `scenario`'s plant; the cells, nominal
/// first per controller. Runs are spread over `threads` threads; the result does not
/// depend on how many.
pub fn run(
    scenario: &Scenario,
    controllers: &[ControllerSet],
    variations: &[Variation],
    threads: usize,
) -> Result<Vec<Cell>, RunError> {
    let plants = variations
        .iter()
        .map(|v| varied(scenario, v))
        .collect::<Result<Vec<_>, _>>()?;
    let jobs: Vec<(usize, usize)> = (0..controllers.len())
        .flat_map(|c| (0..variations.len()).map(move |v| (c, v)))
        .collect();
    let next = std::sync::atomic::AtomicUsize::new(0);
    let results = std::sync::Mutex::new(BTreeMap::new());
    std::thread::scope(|scope| {
        for _ in 0..threads.max(1) {
            scope.spawn(|| loop {
                let j = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                let Some(&(c, v)) = jobs.get(j) else { break };
                let r = measure(scenario, plants[v].clone(), &controllers[c]);
                results
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert((c, v), r);
            });
        }
    });
    let mut results = results.into_inner().unwrap_or_else(|e| e.into_inner());
    let mut cells = Vec::with_capacity(jobs.len());
    for (c, controller) in controllers.iter().enumerate() {
        let mut nominal: Option<Vec<f64>> = None;
        for (v, variation) in variations.iter().enumerate() {
            let m = match results.remove(&(c, v)) {
                Some(Ok(m)) => m,
                Some(Err(e)) => {
                    return Err(RunError::Bench(format!(
                        "{} on {}: {e}",
                        controller.name, variation.name
                    )))
                }
                None => return Err(RunError::Bench("a run did not finish".into())),
            };
            let base = nominal.get_or_insert_with(|| m.rms.clone());
            let ratio = m.rms.iter().zip(base.iter()).map(|(r, b)| r / b).collect();
            cells.push(Cell {
                controller: controller.name.clone(),
                variation: variation.name.clone(),
                rms: m.rms,
                ratio,
                saturated: m.saturated,
                chatter: m.chatter,
                hold_flips: m.hold_flips,
                safe: m.safe,
            });
        }
    }
    Ok(cells)
}

/// One controller over the whole family.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RobustVerdict {
    /// The controller set's name.
    pub controller: String,
    /// Nominal RMS per channel.
    pub nominal_rms: Vec<f64>,
    /// The largest RMS ratio over every variation and channel, and where.
    pub worst: (f64, String, usize),
    /// The median over every variation (nominal aside) of its worst channel's ratio.
    pub median: f64,
    /// The largest chatter over the family (V per sample), and where.
    pub worst_chatter: (f64, String),
    /// The median of the largest hold sign-change rate per variation (per second).
    pub median_hold_flips: f64,
    /// Variations where the run stopped or hit the pitch stop.
    pub unsafe_runs: Vec<String>,
    /// Variations where one of `baselines` (untouched too) had a lower RMS on some
    /// channel (empty for a baseline itself).
    pub beaten_by_baseline: Vec<String>,
}

/// Where `controllers` break the bars over the family: a worst RMS ratio above `bound`
/// (or not a number), a variation where a baseline did better, an unsafe run, or a
/// controller missing from the verdicts. Empty when they hold.
pub fn check(verdicts: &[RobustVerdict], controllers: &[&str], bound: f64) -> Vec<String> {
    let mut failures = Vec::new();
    for &name in controllers {
        let Some(v) = verdicts.iter().find(|v| v.controller == name) else {
            failures.push(format!("{name}: not in the run"));
            continue;
        };
        let (ratio, where_, ch) = &v.worst;
        if ratio.is_nan() || *ratio > bound {
            failures.push(format!(
                "{name}: RMS {ratio:.2}x its nominal on {where_}, channel {ch} (bound {bound}x)"
            ));
        }
        if !v.beaten_by_baseline.is_empty() {
            failures.push(format!(
                "{name}: a baseline did better on {}",
                v.beaten_by_baseline.join(", ")
            ));
        }
        if !v.unsafe_runs.is_empty() {
            failures.push(format!("{name}: unsafe on {}", v.unsafe_runs.join(", ")));
        }
    }
    failures
}

fn median(mut x: Vec<f64>) -> f64 {
    if x.is_empty() {
        return f64::NAN;
    }
    x.sort_by(f64::total_cmp);
    let n = x.len();
    if n % 2 == 1 {
        x[n / 2]
    } else {
        (x[n / 2 - 1] + x[n / 2]) / 2.0
    }
}

fn max_of(x: &[f64]) -> f64 {
    x.iter().copied().fold(f64::NEG_INFINITY, f64::max)
}

/// Each controller's verdict over the family; `baselines` (e.g. `pid`, `adrc`) are what
/// the others must not lose to on any variation.
pub fn judge(cells: &[Cell], baselines: &[&str]) -> Vec<RobustVerdict> {
    let mut names: Vec<&str> = Vec::new();
    for c in cells {
        if !names.contains(&c.controller.as_str()) {
            names.push(&c.controller);
        }
    }
    names
        .iter()
        .map(|&name| {
            let mine: Vec<&Cell> = cells.iter().filter(|c| c.controller == name).collect();
            let mut worst = (f64::NEG_INFINITY, String::new(), 0);
            let mut chatter = (f64::NEG_INFINITY, String::new());
            for c in &mine {
                for (ch, r) in c.ratio.iter().enumerate() {
                    if *r > worst.0 || r.is_nan() {
                        worst = (*r, c.variation.clone(), ch);
                    }
                }
                let ch = max_of(&c.chatter);
                if ch > chatter.0 {
                    chatter = (ch, c.variation.clone());
                }
            }
            let beaten = if baselines.contains(&name) {
                vec![]
            } else {
                mine.iter()
                    .filter(|c| {
                        cells.iter().any(|b| {
                            baselines.contains(&b.controller.as_str())
                                && b.variation == c.variation
                                && b.rms.iter().zip(&c.rms).any(|(x, y)| x < y)
                        })
                    })
                    .map(|c| c.variation.clone())
                    .collect()
            };
            RobustVerdict {
                controller: name.to_string(),
                nominal_rms: mine.first().map(|c| c.rms.clone()).unwrap_or_default(),
                worst,
                median: median(mine.iter().skip(1).map(|c| max_of(&c.ratio)).collect()),
                worst_chatter: chatter,
                median_hold_flips: median(mine.iter().map(|c| max_of(&c.hold_flips)).collect()),
                unsafe_runs: mine
                    .iter()
                    .filter(|c| !c.safe)
                    .map(|c| c.variation.clone())
                    .collect(),
                beaten_by_baseline: beaten,
            }
        })
        .collect()
}

/// The verdicts as a Markdown table, then every cell's worst-channel ratio.
pub fn markdown(verdicts: &[RobustVerdict], cells: &[Cell], variations: &[Variation]) -> String {
    let mut s = String::from(
        "| controller | nominal RMS per channel | worst ratio (where) | median ratio | worst chatter V (where) | hold flips/s (median) | unsafe runs | lost to PID/ADRC on |\n|---|---|---|---|---|---|---|---|\n",
    );
    for v in verdicts {
        let nominal: Vec<String> = v.nominal_rms.iter().map(|x| format!("{x:.3e}")).collect();
        s.push_str(&format!(
            "| {} | {} | {:.2} ({}, channel {}) | {:.2} | {:.2} ({}) | {:.2} | {} | {} |\n",
            v.controller,
            nominal.join(", "),
            v.worst.0,
            v.worst.1,
            v.worst.2,
            v.median,
            v.worst_chatter.0,
            v.worst_chatter.1,
            v.median_hold_flips,
            v.unsafe_runs.len(),
            if v.beaten_by_baseline.is_empty() {
                "-".to_string()
            } else {
                v.beaten_by_baseline.join(", ")
            },
        ));
    }
    s.push_str("\nRMS over the controller's own nominal RMS, per variation, channel by channel (`a / b`):\n\n| variation |");
    for v in verdicts {
        s.push_str(&format!(" {} |", v.controller));
    }
    s.push_str("\n|---|");
    s.push_str(&"---|".repeat(verdicts.len()));
    s.push('\n');
    for var in variations {
        s.push_str(&format!("| {} |", var.name));
        for v in verdicts {
            let r = cells
                .iter()
                .find(|c| c.controller == v.controller && c.variation == var.name)
                .map_or_else(
                    || "–".to_string(),
                    |c| {
                        let each: Vec<String> = c.ratio.iter().map(|r| format!("{r:.2}")).collect();
                        each.join(" / ")
                    },
                );
            s.push_str(&format!(" {r} |"));
        }
        s.push('\n');
    }
    s
}

/// A heat map (SVG) of the RMS ratio: a row per controller and channel (`channels` names
/// them), a column per variation; green at 1 (or better), red from 4 on, on a log scale.
pub fn heat_map(
    title: &str,
    channels: &[String],
    (verdicts, cells): (&[RobustVerdict], &[Cell]),
    variations: &[Variation],
) -> String {
    let (left, top, w, h) = (190.0, 150.0, 46.0, 24.0);
    let rows: Vec<(&str, usize)> = verdicts
        .iter()
        .flat_map(|v| (0..channels.len()).map(move |ch| (v.controller.as_str(), ch)))
        .collect();
    let width = left + w * variations.len() as f64 + 20.0;
    let height = top + h * rows.len() as f64 + 30.0;
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" height=\"{height}\" font-family=\"sans-serif\" font-size=\"11\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n<text x=\"10\" y=\"20\" font-size=\"14\">{}</text>\n",
        xml(title)
    );
    for (j, var) in variations.iter().enumerate() {
        let x = left + w * j as f64 + w / 2.0;
        s.push_str(&format!(
            "<text transform=\"translate({x},{}) rotate(-60)\">{}</text>\n",
            top - 6.0,
            xml(&var.name)
        ));
    }
    for (i, &(controller, ch)) in rows.iter().enumerate() {
        let y = top + h * i as f64;
        let label = format!("{controller} · {}", channels[ch]);
        s.push_str(&format!(
            "<text x=\"6\" y=\"{}\">{}</text>\n",
            y + h * 0.65,
            xml(&label)
        ));
        for (j, var) in variations.iter().enumerate() {
            let r = cells
                .iter()
                .find(|c| c.controller == controller && c.variation == var.name)
                .and_then(|c| c.ratio.get(ch).copied())
                .unwrap_or(f64::NAN);
            let x = left + w * j as f64;
            s.push_str(&format!(
                "<rect x=\"{x}\" y=\"{y}\" width=\"{w}\" height=\"{h}\" fill=\"{}\" stroke=\"white\"/><text x=\"{}\" y=\"{}\" text-anchor=\"middle\">{}</text>\n",
                colour(r),
                x + w / 2.0,
                y + h * 0.65,
                if r.is_finite() { format!("{r:.1}") } else { "–".into() }
            ));
        }
    }
    s.push_str("</svg>\n");
    s
}

fn xml(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

/// Green (ratio 1 or less) through yellow (2) to red (4 and more); grey if unknown.
fn colour(r: f64) -> String {
    if !r.is_finite() {
        return "#bbbbbb".into();
    }
    let t = (r.max(1.0).log2() / 2.0).clamp(0.0, 1.0);
    let (red, green) = if t < 0.5 {
        (80.0 + 350.0 * t, 190.0)
    } else {
        (255.0, 190.0 - 300.0 * (t - 0.5))
    };
    format!("rgb({:.0},{:.0},90)", red.min(255.0), green.max(40.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_family_is_seeded_named_and_inside_its_ranges() {
        let f = family(7, 5);
        assert_eq!(f[0].name, "nominal");
        assert!(f[0].factors.is_empty());
        // One factor at a time, at each end that is not nominal: 2 + 1 + 2 + 2 + 1 + 2 + 1.
        let single: Vec<&str> = f
            .iter()
            .filter(|v| v.factors.len() == 1)
            .map(|v| v.name.as_str())
            .collect();
        assert_eq!(single.len(), 11, "{single:?}");
        assert!(
            single.contains(&"rotorx4")
                && single.contains(&"mass10g")
                && single.contains(&"encoder/8"),
            "{single:?}"
        );
        assert_eq!(f.len(), 1 + 11 + 5);
        assert_eq!(family(7, 5), f, "the same seed, the same family");
        assert_ne!(family(8, 5), f);
        for v in &f {
            for &(fa, x) in &v.factors {
                let (lo, _, hi) = fa.range();
                assert!(x >= lo && x <= hi, "{} {x}", fa.name());
            }
        }
    }

    #[test]
    fn factors_move_what_they_name() {
        let base = AeroParams::default();
        let p = Variation {
            name: "x".into(),
            factors: vec![
                (Factor::Rotor, 4.0),
                (Factor::Mass, 10.0),
                (Factor::Encoder, 8.0),
                (Factor::Noise, 2.0),
            ],
            scales: vec![],
        }
        .params(&base);
        assert_eq!(p.rotor_time_constant, base.rotor_time_constant * 4.0);
        assert!((p.added_mass - 0.010).abs() < 1e-12);
        assert_eq!(p.pitch_counts, base.pitch_counts / 8);
        assert!(
            (p.pitch_noise - 2.0 * std::f64::consts::TAU / f64::from(base.pitch_counts)).abs()
                < 1e-12
        );
        assert!(p.validate().is_ok());
    }

    #[test]
    fn a_driver_plant_is_varied_through_its_command_line() {
        let argv: Vec<String> = ["python3", "../heater.py", "--seed", "2", "--gain", "2.0"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        let table = driver_factors(&argv).unwrap();
        assert_eq!(table[0].name, "gain");
        // The scenario's own gain is scaled; the dead time, absent, from its default.
        let out = driver_argv(&argv, table, &[("gain", 0.5), ("deadtime", 2.0)]);
        assert_eq!(
            out[..6],
            ["python3", "../heater.py", "--seed", "2", "--gain", "1"]
        );
        assert_eq!(out[6..], ["--dead-time", "4"]);
        assert_eq!(driver_argv(&argv, table, &[]), argv);
        assert!(driver_factors(&["python3".into(), "other.py".into()]).is_none());
        let motor = driver_factors(&["x/dc_motor.py".into()]).unwrap();
        let out = driver_argv(&["dc_motor.py".into()], motor, &[("inertia", 2.0)]);
        assert_eq!(
            out[1..],
            ["--inertia", "0.00004", "--load-inertia", "0.0002"]
        );
        let f = driver_family(&HEATER, 3, 2);
        let names: Vec<&str> = f.iter().map(|v| v.name.as_str()).collect();
        assert_eq!(
            names,
            [
                "nominal",
                "gainx0.5",
                "gainx2",
                "taux0.5",
                "taux2",
                "deadtimex0.5",
                "deadtimex2",
                "random-1",
                "random-2"
            ]
        );
        assert_eq!(driver_family(&HEATER, 3, 2), f);
    }

    #[test]
    fn hold_flips_count_sign_changes_on_holds_only() {
        // 3 s: the reference moves for 1 s, then holds; the command alternates throughout.
        let r: Vec<f64> = (0..300)
            .map(|k| if k < 100 { k as f64 } else { 100.0 })
            .collect();
        let v: Vec<f64> = (0..300)
            .map(|k| if k % 2 == 0 { 1.0 } else { -1.0 })
            .collect();
        // Held from k = 100 + 50 (settle 50): 150 periods of 10 ms, 149 flips.
        let f = hold_flips(&r, &v, 50, 0.01);
        assert!((f - 149.0 / 1.5).abs() < 1e-9, "{f}");
        let still = vec![0.5; 300];
        assert_eq!(hold_flips(&r, &still, 50, 0.01), 0.0);
        assert_eq!(
            hold_flips(&(0..300).map(f64::from).collect::<Vec<_>>(), &v, 50, 0.01),
            0.0,
            "no hold"
        );
    }

    #[test]
    fn the_benchmark_sees_a_slower_rotor_and_gives_one_answer_whatever_the_threads() {
        let scenario = plant::scenario::load_scenario("1").unwrap();
        let sets: Vec<ControllerSet> = ["ipd", "pid"]
            .iter()
            .map(|n| plant::scenario::shipped_controller(n).unwrap())
            .collect();
        let f: Vec<Variation> = family(1, 1)
            .into_iter()
            .filter(|v| ["nominal", "rotorx4", "random-1"].contains(&v.name.as_str()))
            .collect();
        assert_eq!(f.len(), 3);
        let one = run(&scenario, &sets, &f, 1).unwrap();
        assert_eq!(
            run(&scenario, &sets, &f, 2).unwrap(),
            one,
            "threads change nothing"
        );
        assert_eq!(one.len(), 6);
        for c in one.iter().filter(|c| c.variation == "nominal") {
            assert_eq!(c.ratio, vec![1.0; c.rms.len()], "{c:?}");
        }
        // A rotor four times slower costs the headline law on pitch (channel 1).
        let slow = one
            .iter()
            .find(|c| c.controller == "ipd" && c.variation == "rotorx4")
            .unwrap();
        assert!(slow.ratio[1] > 1.5, "{slow:?}");
        assert!(slow.chatter.iter().all(|x| x.is_finite() && *x >= 0.0));
    }

    #[test]
    fn verdicts_name_the_worst_and_who_did_better() {
        let cell = |c: &str, v: &str, rms: f64, ratio: f64| Cell {
            controller: c.into(),
            variation: v.into(),
            rms: vec![rms],
            ratio: vec![ratio],
            saturated: vec![0.0],
            chatter: vec![ratio / 10.0],
            hold_flips: vec![0.0],
            safe: v != "bad",
        };
        let cells = vec![
            cell("ipd", "nominal", 1.0, 1.0),
            cell("ipd", "slow", 3.0, 3.0),
            cell("ipd", "bad", 1.5, 1.5),
            cell("pid", "nominal", 2.0, 1.0),
            cell("pid", "slow", 2.5, 1.25),
            cell("pid", "bad", 2.0, 1.0),
        ];
        let v = judge(&cells, &["pid"]);
        assert_eq!(v[0].worst, (3.0, "slow".into(), 0));
        assert_eq!(v[0].median, 2.25);
        assert_eq!(v[0].beaten_by_baseline, ["slow"]);
        assert_eq!(v[0].unsafe_runs, ["bad"]);
        assert!(v[1].beaten_by_baseline.is_empty());
        let md = markdown(&v, &cells, &family(1, 0)[..1]);
        assert!(
            md.contains("| ipd | 1.000e0 | 3.00 (slow, channel 0) | 2.25 |"),
            "{md}"
        );
        let svg = heat_map("t", &["y".into()], (&v, &cells), &family(1, 0)[..1]);
        assert!(svg.starts_with("<svg") && svg.contains(">1.0<"), "{svg}");
        assert_eq!(colour(1.0), "rgb(80,190,90)");
        assert_eq!(colour(8.0), "rgb(255,40,90)");
        // The bars: ipd breaks all three; with a bound of 3 and the slow and bad runs
        // left out, it holds them.
        let broken = check(&v, &["ipd", "nobody"], 2.0);
        assert_eq!(broken.len(), 4, "{broken:?}");
        assert!(
            broken[0].contains("3.00x its nominal on slow"),
            "{broken:?}"
        );
        assert!(broken[1].contains("a baseline did better on slow"));
        assert!(broken[2].contains("unsafe on bad"));
        assert!(broken[3].contains("nobody: not in the run"));
        let kept: Vec<Cell> = cells
            .into_iter()
            .filter(|c| c.variation == "nominal")
            .collect();
        assert!(check(&judge(&kept, &["pid"]), &["ipd"], 3.0).is_empty());
    }

    #[test]
    fn a_slice_of_the_family_varies_only_its_factors() {
        let f = family_of(&[Factor::Mass, Factor::Spring], 3, 2);
        let names: Vec<&str> = f.iter().map(|v| v.name.as_str()).collect();
        assert_eq!(
            names[..4],
            ["nominal", "mass10g", "springx0.300", "springx3"]
        );
        assert_eq!(f.len(), 6);
        for v in &f[4..] {
            let moved: Vec<Factor> = v.factors.iter().map(|(f, _)| *f).collect();
            assert_eq!(moved, [Factor::Mass, Factor::Spring], "{v:?}");
        }
        assert_eq!(Factor::parse("damping"), Some(Factor::Damping));
        assert_eq!(Factor::parse("dampings"), None);
    }
}
