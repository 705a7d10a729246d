//! Text for people: the answers of [`crate::ops`] as short aligned tables. Pure functions
//! of the messages, so they are tested without a network. (`--json` skips this module.)

use std::fmt::Write;

use protocol::pb;

fn opt(v: Option<f64>) -> String {
    v.map_or("-".into(), |x| format!("{x}"))
}

fn limits(l: &pb::ChannelLimits) -> String {
    let rate = l
        .rate_limit
        .map_or(String::new(), |r| format!(", at most {r}/s"));
    format!("[{}, {}]{rate}", opt(l.min), opt(l.max))
}

/// Services: one line each, with their drop counters when any is nonzero.
pub fn services(list: &[pb::ServiceStatus], alive: &[String]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<20} {:<8} {:>5} {:>8} {:>9}  drops",
        "controller", "role", "term", "devices", "uptime s"
    );
    for s in list {
        let drops = [
            ("oversized", s.oversized),
            ("bad_key", s.bad_key),
            ("undecodable", s.undecodable),
            ("unknown", s.unknown_samples),
            ("table_full", s.device_table_full),
            ("superseded", s.superseded),
            ("queue_full", s.queue_full),
            ("rejected", s.rejected),
            ("refused", s.requests_refused),
        ]
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|(k, n)| format!("{k} {n}"))
        .collect::<Vec<_>>()
        .join(", ");
        let _ = writeln!(
            out,
            "{:<20} {:<8} {:>5} {:>8} {:>9.0}  {}",
            s.controller_id,
            if s.active { "active" } else { "standby" },
            s.term,
            s.devices.len(),
            s.uptime,
            if drops.is_empty() {
                "none".into()
            } else {
                drops
            }
        );
    }
    let silent: Vec<&String> = alive
        .iter()
        .filter(|a| !list.iter().any(|s| &s.controller_id == *a))
        .collect();
    if !silent.is_empty() {
        let _ = writeln!(out, "alive but not answering status: {silent:?}");
    }
    out
}

/// Devices of every service, and the plants that are up: who serves whom.
pub fn devices(list: &[pb::ServiceStatus], plants_alive: &[String]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<20} {:<16} {:>5} {:>9} {:>9} {:>7} {:>8} {:>8}  last error",
        "device", "controller", "plant", "samples", "commands", "lost", "rtt p50", "rtt p99"
    );
    let mut served = Vec::new();
    for s in list {
        for d in &s.devices {
            served.push(d.device_id.clone());
            let rtt = d.loop_rtt.unwrap_or_default();
            let _ = writeln!(
                out,
                "{:<20} {:<16} {:>5} {:>9} {:>9} {:>7} {:>6.0}us {:>6.0}us  {}",
                d.device_id,
                s.controller_id,
                if plants_alive.contains(&d.device_id) {
                    "up"
                } else {
                    "-"
                },
                d.samples,
                d.commands,
                d.lost,
                rtt.p50_us,
                rtt.p99_us,
                d.last_error
            );
        }
    }
    for p in plants_alive.iter().filter(|p| !served.contains(p)) {
        let _ = writeln!(
            out,
            "{p:<20} {:<16} {:>5}  (a plant is up, no controller serves it)",
            "-", "up"
        );
    }
    out
}

/// One device's status, every counter named.
pub fn status(d: &pb::DeviceStatus) -> String {
    let mut out = String::new();
    let rtt = d.loop_rtt.unwrap_or_default();
    let _ = writeln!(
        out,
        "device {}{}",
        d.device_id,
        if d.from_template {
            " (from a template)"
        } else {
            ""
        }
    );
    let _ = writeln!(
        out,
        "  last seq {} at plant time {:.3} s; runs {}",
        d.last_seq, d.plant_time, d.restarts
    );
    let _ = writeln!(
        out,
        "  samples {}  commands {}  lost {}  duplicates {}  stale {}  rejected {}  superseded {}",
        d.samples, d.commands, d.lost, d.duplicates, d.stale, d.rejected, d.superseded
    );
    let _ = writeln!(
        out,
        "  off remote control {}  clamped {}  references refused {}  envelope changes {}",
        d.samples_off_remote, d.clamped, d.references_refused, d.envelope_changes
    );
    let _ = writeln!(
        out,
        "  round trip p50 {:.0} us  p99 {:.0} us  max {:.0} us  ({} samples)",
        rtt.p50_us, rtt.p99_us, rtt.max_us, rtt.count
    );
    let f: Vec<String> = d.f_est.iter().map(|f| format!("{f:.4e}")).collect();
    let _ = writeln!(out, "  F estimates [{}]", f.join(", "));
    if let Some(e) = &d.envelope {
        let l: Vec<String> = e.channels.iter().map(limits).collect();
        let _ = writeln!(out, "  envelope {}", l.join("; "));
    }
    if !d.last_error.is_empty() {
        let _ = writeln!(out, "  last error: {}", d.last_error);
    }
    out
}

/// A law's parameters in one line.
fn law(c: &pb::ChannelConfig) -> String {
    use pb::channel_config::Law;
    match &c.law {
        Some(Law::Intelligent(i)) => {
            let kind = pb::IntelligentKind::try_from(i.kind)
                .map(|k| {
                    k.as_str_name()
                        .trim_start_matches("INTELLIGENT_KIND_")
                        .to_lowercase()
                })
                .unwrap_or_else(|_| format!("kind {}", i.kind));
            let window = i.estimator.map_or(0, |e| e.window);
            format!(
                "i{} order {} alpha {} kp {} ki {} kd {} (window {window})",
                kind.trim_start_matches('i'),
                i.order,
                i.alpha,
                i.kp,
                i.ki,
                i.kd
            )
        }
        Some(Law::Pid(p)) => format!("pid kp {} ki {} kd {}", p.kp, p.ki, p.kd),
        Some(Law::Adrc(a)) => format!("adrc order {} b0 {} wc {} wo {}", a.order, a.b0, a.wc, a.wo),
        None => "no law".into(),
    }
}

/// A device's configuration: each channel's law, output map and envelope, the reference.
pub fn config(c: &pb::DeviceConfig) -> String {
    let mut out = String::new();
    let _ = writeln!(out, "device {}", c.device_id);
    let env = c.envelope.clone().unwrap_or_default();
    for (i, ch) in c.channels.iter().enumerate() {
        let o = ch.output.unwrap_or_default();
        let _ = writeln!(out, "  channel {i}: {}", law(ch));
        let _ = writeln!(
            out,
            "    output: dead zone {}{}, limits [{}, {}], rate {}",
            o.dead_zone,
            if o.smoothing > 0.0 {
                format!(" (smooth, {})", o.smoothing)
            } else {
                String::new()
            },
            opt(o.min),
            opt(o.max),
            opt(o.rate_limit)
        );
        if let Some(l) = env.channels.get(i) {
            let _ = writeln!(out, "    envelope: {}", limits(l));
        }
        if let Some(r) = c.reference.as_ref().and_then(|r| r.channels.get(i)) {
            let _ = writeln!(out, "    reference: {} piece(s)", r.pieces.len());
        }
    }
    if let Some(r) = &c.reference {
        let _ = writeln!(out, "  reference starts at plant time {} s", r.start_time);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn config_and_status_read_well() {
        let cfg = pb::DeviceConfig {
            version: 1,
            device_id: "aero-1".into(),
            channels: vec![protocol::convert::channel_to_pb(&mfc::ChannelConfig {
                law: mfc::LawConfig::Pid {
                    params: mfc::PidParams {
                        kp: 2.5,
                        ..Default::default()
                    },
                },
                output: mfc::OutputMapConfig::AERO,
            })],
            reference: None,
            envelope: Some(pb::Envelope {
                channels: vec![pb::ChannelLimits {
                    min: Some(-24.0),
                    max: Some(24.0),
                    rate_limit: Some(100.0),
                }],
            }),
        };
        let text = config(&cfg);
        assert!(text.contains("pid kp 2.5"), "{text}");
        assert!(text.contains("limits [-24, 24]"), "{text}");
        assert!(
            text.contains("envelope: [-24, 24], at most 100/s"),
            "{text}"
        );
        let st = pb::DeviceStatus {
            device_id: "aero-1".into(),
            samples: 10,
            last_error: "non-finite value NaN".into(),
            ..Default::default()
        };
        let text = status(&st);
        assert!(
            text.contains("samples 10") && text.contains("last error: non-finite"),
            "{text}"
        );
    }

    #[test]
    fn devices_shows_who_serves_whom() {
        let svc = pb::ServiceStatus {
            controller_id: "c1".into(),
            devices: vec![pb::DeviceStatus {
                device_id: "aero-1".into(),
                ..Default::default()
            }],
            ..Default::default()
        };
        let text = devices(&[svc], &["aero-1".into(), "lonely".into()]);
        assert!(text.contains("aero-1") && text.contains("c1"), "{text}");
        assert!(
            text.contains("lonely") && text.contains("no controller serves it"),
            "{text}"
        );
    }
}
