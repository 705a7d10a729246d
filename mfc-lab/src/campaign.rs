//! The fault campaign: for each profile and link, a controller service and simulated
//! plants (one per controller, side by side on the same impaired link) run a scenario
//! through `faultlab`'s relay, in real time; then the table and the degradation plots.

use std::net::SocketAddr;
use std::path::Path;

use anyhow::Result;
use controller_service::config::{Prediction, ServiceConfig};
use faultlab::profile::{Profile, ProfileSet};
use faultlab::relay::{Link, Relay, RelayStats};
use plant::chart::{ensure_font, Ticks};
use plant::record::RunRecord;
use plant::scenario::{ControllerSet, Scenario};
use plant_agent::agent::AgentReport;
use plant_agent::safety::{FallbackPolicy, SafetyConfig};
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::harness::{open_session, run_plant, service_config, PlantSpec, ServiceHandle};

/// One controller's run under one profile on one link.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct CaseResult {
    /// Profile name.
    pub profile: String,
    /// Link.
    pub link: Link,
    /// Controller name.
    pub controller: String,
    /// The agent's report.
    pub report: AgentReport,
    /// RMS over the unimpaired run on the same link, per channel (filled by the campaign).
    pub rms_ratio: Vec<f64>,
    /// What the relay did.
    pub relay: RelayStats,
    /// The run, period by period.
    #[serde(skip)]
    pub record: RunRecord,
}

/// Wait (at most 5 s) until the service reports round trips for every device.
async fn wait_until_flowing(service_endpoint: &str, ids: &[String]) {
    let Ok(probe) = open_session(None, vec![service_endpoint.to_string()], false).await else {
        return;
    };
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(5);
    while tokio::time::Instant::now() < deadline {
        let mut flowing = 0;
        for id in ids {
            let status = transport::get_first(&probe, &protocol::keys::status(id), None)
                .await
                .ok()
                .and_then(|b| protocol::decode::<protocol::pb::DeviceStatus>(&b).ok());
            if status.is_some_and(|st| st.loop_rtt.is_some_and(|l| l.count >= 5)) {
                flowing += 1;
            }
        }
        if flowing == ids.len() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    let _ = probe.close().await;
}

/// Options of a case.
#[derive(Debug, Clone)]
pub struct CaseOptions {
    /// Periods to hold before falling back.
    pub hold_periods: u32,
    /// What to fall back to.
    pub fallback: FallbackPolicy,
    /// Oldest command worth applying (periods).
    pub max_age: u32,
    /// The service's prediction for each controller's device, in the order of the
    /// controllers (missing: none).
    pub predictions: Vec<Prediction>,
    /// Where the plants show their progress while they run (none: nowhere).
    pub progress: Option<std::sync::Arc<plant::progress::ProgressBoard>>,
}

impl Default for CaseOptions {
    fn default() -> Self {
        Self {
            hold_periods: SafetyConfig::DEFAULT_HOLD_PERIODS,
            fallback: FallbackPolicy::LocalController,
            max_age: SafetyConfig::DEFAULT_MAX_AGE,
            predictions: Vec::new(),
            progress: None,
        }
    }
}

/// A controller name as a device id chunk: `ipd+h10+dc` -> `ipd.h10.dc`.
fn device_part(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.') {
                c
            } else {
                '.'
            }
        })
        .collect()
}

/// A campaign entry: `KIND[+hN][+dc][+notrend|+trendG][+restG]`, a controller (a shipped
/// name or a file) with the service's packetized horizon of N periods and/or delay
/// compensation for its device; `+notrend` predicts with `F` held (`prediction.trend = 0`)
/// instead of following half its trend, `+trendG` with `trend = G` (0 to 2), and `+restG`
/// follows the fraction G of the trend at rest too (`trend_at_rest = G`; default 0).
pub fn parse_variant(spec: &str) -> Result<(String, Prediction), String> {
    let mut parts = spec.split('+');
    let base = parts.next().unwrap_or_default().to_string();
    let mut p = Prediction::default();
    for opt in parts {
        if opt == "dc" {
            p.delay_compensation = true;
        } else if opt == "notrend" {
            p.trend = 0.0;
        } else if let Some(g) = fraction(opt, "trend") {
            p.trend = g.map_err(|e| format!("{spec:?}: {e}"))?;
        } else if let Some(g) = fraction(opt, "rest") {
            p.trend_at_rest = g.map_err(|e| format!("{spec:?}: {e}"))?;
        } else if let Some(n) = opt.strip_prefix('h').and_then(|n| n.parse::<u32>().ok()) {
            p.horizon = n;
        } else {
            return Err(format!(
                "{spec:?}: unknown option {opt:?} (expected +hN for a horizon of N periods, +dc, +notrend, +trendG or +restG)"
            ));
        }
    }
    if base.is_empty() {
        return Err(format!("{spec:?}: no controller before the options"));
    }
    Ok((base, p))
}

/// `+{what}G` with G a number: `Some` of G if it is between 0 and 2, else of why not.
fn fraction(opt: &str, what: &str) -> Option<Result<f64, String>> {
    let g = opt.strip_prefix(what)?.parse::<f64>().ok()?;
    Some(if (0.0..=2.0).contains(&g) {
        Ok(g)
    } else {
        Err(format!("+{what}{g} is not between 0 and 2"))
    })
}

/// Run every controller of `controllers` on `scenario`, side by side, through a relay
/// impairing `link` with `profile`.
pub async fn run_case(
    scenario: &Scenario,
    controllers: &[ControllerSet],
    profile: &Profile,
    link: Link,
    options: &CaseOptions,
) -> anyhow::Result<Vec<CaseResult>> {
    let port = match link {
        Link::Tcp => transport::free_local_port()?,
        Link::Udp => transport::free_udp_port()?,
    };
    let target: SocketAddr = format!("127.0.0.1:{port}").parse()?;
    let mut config = ServiceConfig::default();
    let ids: Vec<String> = controllers
        .iter()
        .map(|c| format!("aero-{}", device_part(&c.name)))
        .collect();
    for (i, (c, id)) in controllers.iter().zip(&ids).enumerate() {
        let mut devices = service_config(scenario, c, std::slice::from_ref(id)).devices;
        for d in &mut devices {
            d.prediction = options.predictions.get(i).copied().unwrap_or_default();
        }
        config.devices.extend(devices);
    }
    let svc = ServiceHandle::start_with(
        config,
        Some(format!("{}/{target}", link.scheme())),
        false,
        None,
    )
    .await?;
    // Sessions establish through a transparent relay; it starts impairing once the loops
    // run (zenoh does not retransmit handshakes or declarations lost on a UDP link).
    let relay = Relay::start(link, "127.0.0.1:0".parse()?, target, profile, false).await?;
    let endpoint = format!("{}/{}", link.scheme(), relay.listen);

    let mut tasks = Vec::new();
    // Every controller's plant gets the scenario's noise seed: the same rig, side by side.
    for (c, id) in controllers.iter().zip(&ids) {
        let mut plant = PlantSpec::new(scenario, c, id);
        plant.loop_config.safety.hold_periods = options.hold_periods;
        plant.loop_config.safety.fallback = options.fallback;
        plant.loop_config.safety.max_age = options.max_age;
        plant.loop_config.observers.progress = options.progress.clone();
        tasks.push(tokio::spawn(run_plant(
            vec![endpoint.clone()],
            plant,
            false,
        )));
    }
    // Arm once every plant has received commands (its samples report a round trip): by
    // then every session is up and every declaration has crossed the link.
    wait_until_flowing(&format!("{}/{target}", link.scheme()), &ids).await;
    relay.arm();
    let mut results = Vec::new();
    for (task, c) in tasks.into_iter().zip(controllers) {
        let run = task.await??;
        results.push(CaseResult {
            profile: profile.name.clone(),
            link,
            controller: c.name.clone(),
            report: run.report,
            rms_ratio: Vec::new(),
            relay: relay.stats(),
            record: run.record,
        });
    }
    drop(relay);
    svc.stop().await?;
    Ok(results)
}

/// The whole campaign.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Campaign {
    /// Scenario name.
    pub scenario: String,
    /// Duration of each run (s).
    pub duration: f64,
    /// Every case.
    pub cases: Vec<CaseResult>,
}

impl Campaign {
    /// Fill each case's RMS ratio from the `none` profile on the same link and controller.
    pub fn compute_ratios(&mut self, baseline: &str) {
        let base: Vec<(Link, String, Vec<f64>)> = self
            .cases
            .iter()
            .filter(|c| c.profile == baseline)
            .map(|c| {
                (
                    c.link,
                    c.controller.clone(),
                    c.report.channels.iter().map(|m| m.rms).collect(),
                )
            })
            .collect();
        for c in &mut self.cases {
            if let Some((_, _, b)) = base
                .iter()
                .find(|(l, n, _)| *l == c.link && *n == c.controller)
            {
                c.rms_ratio = c
                    .report
                    .channels
                    .iter()
                    .zip(b)
                    .map(|(m, b)| m.rms / b)
                    .collect();
            }
        }
    }

    /// The table in Markdown.
    pub fn markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut out = String::new();
        let _ = writeln!(
            out,
            "| profile | link | controller | azimuth RMS ratio | pitch RMS ratio | pitch RMS (rad) | pitch worst (rad) | periods without command | applied late | stale | fallbacks | RTT p50 / p99 (ms) |"
        );
        let _ = writeln!(
            out,
            "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
        );
        for c in &self.cases {
            let r = &c.report;
            let ratio = |i: usize| c.rms_ratio.get(i).map_or("-".into(), |x| format!("{x:.2}"));
            let _ = writeln!(
                out,
                "| {} | {} | {} | {} | {} | {:.2e} | {:.3} | {:.1}% | {} | {} | {} | {:.1} / {:.1} |",
                c.profile,
                c.link.scheme(),
                c.controller,
                ratio(0),
                ratio(1),
                r.channels.get(1).map_or(0.0, |m| m.rms),
                r.channels.get(1).map_or(0.0, |m| m.max_abs),
                100.0 * r.counters.missing as f64 / r.counters.periods.max(1) as f64,
                r.counters.late,
                r.counters.too_old + r.counters.superseded,
                r.counters.fallbacks,
                r.rtt_p50_us / 1000.0,
                r.rtt_p99_us / 1000.0
            );
        }
        out
    }
}

/// Degradation curves: pitch RMS ratio against loss rate (pure-loss profiles) and against
/// round-trip latency (pure-latency profiles), one line per controller and link.
pub fn plots(out: &Path, c: &Campaign, set: &ProfileSet) -> Result<()> {
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
            .filter(|y| y.is_finite())
            .fold(2.0, f64::max)
            * 1.2;
        ensure_font();
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
    // A ratio axis on a log scale: a controller that breaks down (ratios of 10 or 20) must
    // not flatten the ones that matter, between 1 and 3.
    const Y_MIN: f64 = 0.8;
    let (x_ticks, y_ticks) = (Ticks::linear(0.0, xmax, 10), Ticks::log(Y_MIN, ymax, 10));
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "Pitch tracking under faults (RMS / unimpaired RMS, log scale)",
            ("sans-serif", 22),
        )
        .margin(15)
        .margin_right(30)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d(
            x_ticks.axis(0.0..xmax),
            y_ticks
                .axis((Y_MIN..ymax).log_scale())
                .with_minor(Ticks::log_minor(Y_MIN, ymax)),
        )
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(xlabel)
        .y_desc("pitch RMS / unimpaired pitch RMS")
        .x_label_formatter(&|v| x_ticks.label(*v))
        .y_label_formatter(&|v| y_ticks.label(*v))
        .draw()
        .map_err(e)?;
    // One colour per controller, the same over both links; TCP thin with open markers,
    // UDP thick with filled ones.
    let mut controllers: Vec<&str> = Vec::new();
    for (name, _) in series {
        let c = name.split(" over ").next().unwrap_or(name);
        if !controllers.contains(&c) {
            controllers.push(c);
        }
    }
    for (name, pts) in series {
        let c = name.split(" over ").next().unwrap_or(name);
        let i = controllers.iter().position(|x| *x == c).unwrap_or(0);
        let color = Palette99::pick(i).to_rgba();
        let udp = name.ends_with("udp");
        let width = if udp { 3 } else { 1 };
        chart
            .draw_series(LineSeries::new(
                pts.iter().copied(),
                color.stroke_width(width),
            ))
            .map_err(e)?
            .label(name)
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(width))
            });
        chart
            .draw_series(pts.iter().map(|p| {
                let style = if udp {
                    color.filled()
                } else {
                    color.stroke_width(1)
                };
                Circle::new(*p, 4, style)
            }))
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

#[cfg(test)]
mod tests {
    use super::parse_variant;

    #[test]
    fn variants_parse_and_bad_ones_name_the_option() {
        let (base, p) = parse_variant("ipd-hold+h10+dc+notrend").unwrap();
        assert_eq!(base, "ipd-hold");
        assert_eq!((p.horizon, p.delay_compensation, p.trend), (10, true, 0.0));
        let (_, p) = parse_variant("ipd+h5").unwrap();
        assert_eq!((p.horizon, p.delay_compensation), (5, false));
        assert_eq!(p.trend, controller_service::config::DEFAULT_TREND);
        let e = parse_variant("ipd+h10+fast").unwrap_err();
        assert!(e.contains("\"fast\""), "{e}");
        assert!(parse_variant("+dc").is_err());
        let (_, p) = parse_variant("ipd+h10+trend0.75").unwrap();
        assert_eq!(p.trend, 0.75);
        let e = parse_variant("ipd+h10+trend3").unwrap_err();
        assert!(e.contains("between 0 and 2"), "{e}");
        let (_, p) = parse_variant("ipd+h10+dc+rest0.5").unwrap();
        assert_eq!((p.trend, p.trend_at_rest), (0.5, 0.5));
        assert_eq!(
            parse_variant("ipd+h10").unwrap().1.trend_at_rest,
            controller_service::config::DEFAULT_TREND_AT_REST
        );
        let e = parse_variant("ipd+rest-1").unwrap_err();
        assert!(e.contains("+rest-1 is not between 0 and 2"), "{e}");
    }
}
