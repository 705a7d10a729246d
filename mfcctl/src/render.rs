//! Text for people: the answers of [`crate::ops`] as short aligned tables. Pure functions
//! of the messages, so they are tested without a network. (`--json` skips this module.)

use std::fmt::Write;

use mfc::params::{LawKind, Param, Readable, Scope, PARAMS};
use protocol::pb;
use serde::Serialize;
use transport::ops;

fn opt(v: Option<f64>) -> String {
    v.map_or("-".into(), |x| Readable(x).to_string())
}

fn limits(l: &pb::ChannelLimits) -> String {
    let rate = l
        .rate_limit
        .map_or(String::new(), |r| format!(", at most {}/s", Readable(r)));
    format!("[{}, {}]{rate}", opt(l.min), opt(l.max))
}

/// Services: one line each, with their drop counters when any is nonzero.
pub fn services(list: &[pb::ServiceStatus], alive: &[String]) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<20} {:<16} {:<8} {:>5} {:>8} {:>9} {:<5}  drops",
        "controller", "process", "role", "term", "devices", "uptime s", "auth"
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
            ("forged", s.forged),
        ]
        .iter()
        .filter(|(_, n)| *n > 0)
        .map(|(k, n)| format!("{k} {n}"))
        .collect::<Vec<_>>()
        .join(", ");
        let _ = writeln!(
            out,
            "{:<20} {:<16} {:<8} {:>5} {:>8} {:>9.0} {:<5}  {}",
            s.controller_id,
            instance(s.instance),
            if s.active { "active" } else { "standby" },
            s.term,
            s.devices.len(),
            s.uptime,
            // Keys: samples checked, commands and replies sealed; open: none of it.
            if s.authenticated { "keys" } else { "open" },
            if drops.is_empty() {
                "none".into()
            } else {
                drops
            }
        );
    }
    out += &twins(list);
    let silent: Vec<&String> = alive
        .iter()
        .filter(|a| !list.iter().any(|s| &s.controller_id == *a))
        .collect();
    if !silent.is_empty() {
        let _ = writeln!(out, "alive but not answering status: {silent:?}");
    }
    out
}

/// A warning for each controller id carried by more than one process: the replies of
/// several, or one that sees others (`ServiceStatus.twins`).
fn twins(list: &[pb::ServiceStatus]) -> String {
    let mut by_id: std::collections::BTreeMap<&str, std::collections::BTreeSet<u64>> =
        std::collections::BTreeMap::new();
    for s in list {
        let seen = by_id.entry(&s.controller_id).or_default();
        seen.insert(s.instance);
        seen.extend(&s.twins);
    }
    let mut out = String::new();
    for (id, seen) in by_id.iter().filter(|(_, seen)| seen.len() > 1) {
        let all: Vec<String> = seen.iter().map(|&i| instance(i)).collect();
        let _ = writeln!(
            out,
            "WARNING: {id} runs in {} processes ({}): a copied bundle, or a service started twice; stop all but one",
            seen.len(),
            all.join(", ")
        );
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
    let holder = match d.lease_holder.as_str() {
        "" if d.lease_epoch == 0 => "none (or a plant without leases)".to_string(),
        "" => format!("vacant after epoch {}", d.lease_epoch),
        h => format!(
            "{h} (process {}, epoch {})",
            instance(d.lease_instance),
            d.lease_epoch
        ),
    };
    let _ = writeln!(
        out,
        "  lease holder {holder}  refused by the plant {}  fenced here {}  claims {}  yields {}",
        d.lease_refused, d.lease_fenced, d.lease_claims, d.lease_yields
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
    if let Some(c) = &d.commission {
        out += &commission(c);
    }
    out
}

/// A process's instance, as the services' logs print it (16 hex digits).
fn instance(i: u64) -> String {
    format!("{i:016x}")
}

/// Who answered a device's status and how old its word on the plant is; the other
/// members that answered too, each with its age (a member paused or cut off believes what
/// the plant said before: its word is older).
pub fn answered(all: &[pb::DeviceStatus]) -> String {
    let age = |d: &pb::DeviceStatus| match d.heard_ms_ago {
        0 => "never heard the plant".to_string(),
        ms => format!("heard the plant {:.2} s ago", ms as f64 / 1000.0),
    };
    let mut out = String::new();
    let Some(first) = all.first() else {
        return out;
    };
    let _ = writeln!(
        out,
        "  answered by {} (process {}), which {}",
        first.answered_by,
        instance(first.answered_by_instance),
        age(first)
    );
    for d in &all[1..] {
        let _ = writeln!(
            out,
            "  also answered by {} (process {}), which {}: it says the lease is {} at epoch {} (older word)",
            d.answered_by,
            instance(d.answered_by_instance),
            age(d),
            if d.lease_holder.is_empty() { "vacant" } else { &d.lease_holder },
            d.lease_epoch
        );
    }
    out
}

/// A measured value to four significant digits (the law's own values are printed whole).
fn short(x: f64) -> String {
    format!("{}", Readable(format!("{x:.4e}").parse().unwrap_or(x)))
}

/// A commissioning run: where it stands, what it found and what it proposes.
pub fn commission(c: &pb::CommissionStatus) -> String {
    use pb::CommissionPhase as P;
    let mut out = String::new();
    let phase = match P::try_from(c.phase) {
        Ok(P::CommissionRunning) => "running",
        Ok(P::CommissionProposed) => "PROPOSED, waiting for a confirmation",
        Ok(P::CommissionApplied) => "applied",
        Ok(P::CommissionAborted) => "ABORTED",
        _ => "unknown",
    };
    let ended = match c.ended_by.as_str() {
        "" => String::new(),
        e => format!(", ended by {e}"),
    };
    let _ = writeln!(
        out,
        "  commissioning run {} on channel {}: {phase} (started by {}{ended}); {:.1} of {:.1} s, largest deviation {}; alpha was {}",
        c.run,
        c.channel,
        c.started_by,
        c.elapsed,
        c.duration,
        short(c.deviation),
        Readable(c.alpha_before)
    );
    for f in &c.fits {
        let _ = writeln!(
            out,
            "    order {}: alpha {}, explains {:.0} % of F's jumps",
            f.order,
            short(f.alpha),
            100.0 * f.explained
        );
    }
    if let Some(p) = &c.proposed {
        let _ = writeln!(out, "    proposed: {}", law(p));
    }
    if !c.reason.is_empty() {
        let _ = writeln!(out, "    {}", c.reason);
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
            let window = match i.estimator {
                Some(e) if e.first_window > 0 => format!("{}, first {}", e.window, e.first_window),
                e => e.map_or(0, |e| e.window).to_string(),
            };
            format!(
                "i{} order {} alpha {} kp {} ki {} kd {} (window {window})",
                kind.trim_start_matches('i'),
                i.order,
                Readable(i.alpha),
                Readable(i.kp),
                Readable(i.ki),
                Readable(i.kd)
            )
        }
        Some(Law::Pid(p)) => format!(
            "pid kp {} ki {} kd {}",
            Readable(p.kp),
            Readable(p.ki),
            Readable(p.kd)
        ),
        Some(Law::Adrc(a)) => format!(
            "adrc order {} b0 {} wc {} wo {}",
            a.order,
            Readable(a.b0),
            Readable(a.wc),
            Readable(a.wo)
        ),
        None => "no law".into(),
    }
}

/// An accepted change: the configuration in force, then where it is kept. One name means
/// the change lives only as long as that member (a single service, or a fleet without
/// standbys), or its audit file if it is durable there; not durable, a restart loses it.
pub fn changed(c: &ops::Changed) -> String {
    let mut out = config(&c.config);
    let first = c.held_by.first().map_or("the service", String::as_str);
    let _ = match (c.held_by.as_slice(), c.durable) {
        ([] | [_], true) => writeln!(out, "acknowledged: on {first}'s disk (its audit file, fsynced)"),
        (all, true) => writeln!(
            out,
            "acknowledged: on {first}'s disk (its audit file, fsynced), held by {}",
            all.join(", ")
        ),
        ([] | [_], false) => writeln!(
            out,
            "in force on {first}, NOT durable: it has no audit file, so a restart of it loses this change"
        ),
        (all, false) => writeln!(
            out,
            "acknowledged: held by {} (NOT on {first}'s disk: it has no audit file)",
            all.join(", ")
        ),
    };
    out
}

/// The audit logs, one line per entry then its changes, oldest first per device.
pub fn audit(logs: &[pb::AuditLog]) -> String {
    let mut out = String::new();
    if logs.iter().all(|l| l.entries.is_empty()) {
        return "no audited change\n".into();
    }
    for l in logs.iter().filter(|l| !l.entries.is_empty()) {
        let _ = writeln!(out, "device {}", l.device_id);
        for e in &l.entries {
            let who = match (e.verified, e.role.as_str()) {
                (true, "") => e.operator.clone(),
                (true, r) => format!("{} ({r})", e.operator),
                (false, "") => format!("{} (unverified)", e.operator),
                (false, r) => format!("{} ({r}, unverified)", e.operator),
            };
            let result = if e.accepted {
                "accepted".to_string()
            } else {
                format!("REFUSED: {}", e.reason)
            };
            let _ = writeln!(
                out,
                "  {} {who} {} on {}: {result}",
                utc(e.unix_ns),
                e.action,
                e.member
            );
            for c in &e.changes {
                let _ = writeln!(out, "      {}: {} -> {}", c.what, c.old, c.new);
            }
            if !e.accepted && !e.asked.is_empty() {
                let _ = writeln!(out, "      asked: {}", e.asked);
            }
        }
    }
    out
}

/// Unix ns as `YYYY-MM-DD hh:mm:ss.mmm UTC` (civil calendar, no time zone database).
fn utc(unix_ns: u64) -> String {
    let secs = unix_ns / 1_000_000_000;
    let ms = (unix_ns / 1_000_000) % 1000;
    let (days, rem) = (secs / 86_400, secs % 86_400);
    // Howard Hinnant's days-to-civil.
    let z = days as i64 + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02}.{ms:03} UTC",
        rem / 3600,
        (rem / 60) % 60,
        rem % 60
    )
}

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
            Readable(o.dead_zone),
            if o.smoothing > 0.0 {
                format!(" (smooth, {})", Readable(o.smoothing))
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
        let _ = writeln!(
            out,
            "  reference starts at plant time {} s",
            Readable(r.start_time)
        );
    }
    out
}

/// The laws that have a parameter, as the table says them (`intelligent, pid`, or
/// `every law (output map)`).
fn laws(p: &Param) -> String {
    match p.scope {
        Scope::OutputMap => "every law (output map)".into(),
        Scope::Laws(l) => l.iter().map(|k| k.name()).collect::<Vec<_>>().join(", "),
    }
}

/// `mfcctl params`: the table of tunable parameters, one per line, in aligned columns.
pub fn params() -> String {
    let rows: Vec<[String; 5]> = PARAMS
        .iter()
        .map(|p| {
            let bounds = p.bounds.to_string();
            [
                p.name.into(),
                laws(p),
                p.unit.into(),
                bounds,
                p.meaning.into(),
            ]
        })
        .collect();
    let head = ["name", "laws", "unit", "sane bounds", "meaning"].map(String::from);
    let mut width = [0; 4];
    for r in rows.iter().chain([&head]) {
        for (w, c) in width.iter_mut().zip(r) {
            *w = (*w).max(c.chars().count());
        }
    }
    let mut out = String::new();
    for r in [&head].into_iter().chain(&rows) {
        for (w, c) in width.iter().zip(r) {
            let _ = write!(out, "{c:<w$}  ");
        }
        let _ = writeln!(out, "{}", r[4]);
    }
    out
}

/// A table cell of Markdown: `|` would end the cell.
fn cell(s: &str) -> String {
    s.replace('|', "\\|")
}

/// What `docs/parameters.md` says before the table.
const PARAMS_MD_HEAD: &str = r#"# Tunable parameters

The parameters an operator changes on a running channel, by name: `mfcctl set DEVICE
--channel N kp=450`, the console's gain form, the Python client's `Operator.update`. Each is
one optional field of the protocol's partial change, `ChannelUpdate`, of the same name. A
parameter the law in force does not have is refused, with its name.

Generated from the control core's table (`mfc::params::PARAMS` in `mfc/src/params.rs`) by
`mfcctl params --markdown`. `cargo test -p mfcctl` fails when this file differs from it;
`MFC_BLESS=1 cargo test -p mfcctl` writes it again.

Units: `y` is the unit of the channel's measured output, `u` of the law's command, `v` of
what the actuator gets (the output map's side, e.g. volts), and `n` the order of the
ultra-local model `y^(n) = F + alpha u`. An output limit or rate limit that is not set reads
as infinite.

The bounds are the absolute sanity limits. The controller service refuses a change that moves
a value outside them, with the reason, and narrows some of them further from the device
(`controller-service/src/bounds.rs`): from its period once its first samples came (an
intelligent law's `|kp| <= (2/h)^n`, `|ki| <= (2/h)^(n+1)`, `|kd| <= 2/h` for `n = 2`; a
bandwidth at most the Nyquist frequency `pi/h`), and from its envelope (`dead_zone` at most
its largest command). A channel's `bounds` in the service's file replace them, wider or
narrower. The laws' own checks also decide (`alpha` and `b0` not 0; the intelligent laws' gains and
every time constant >= 0; the PID's gains of one sign; `wc`, `wo`, `rate_limit` > 0;
`min <= 0 <= max`).

| name | laws | unit | sane bounds | meaning |
|---|---|---|---|---|
"#;

/// `docs/parameters.md`, as `mfcctl params --markdown` prints it.
pub fn params_markdown() -> String {
    let mut out = String::from(PARAMS_MD_HEAD);
    for p in PARAMS.iter() {
        let _ = writeln!(
            out,
            "| `{}` | {} | {} | {} | {} |",
            p.name,
            laws(p),
            cell(p.unit),
            cell(&p.bounds.to_string()),
            cell(p.meaning)
        );
    }
    out
}

/// One parameter in `mfcctl --json params`.
#[derive(Debug, Serialize)]
pub struct ParamJson {
    /// The name operators write.
    pub name: &'static str,
    /// The laws that have it (`intelligent`, `pid`, `adrc`): all three for the output map's.
    pub laws: Vec<&'static str>,
    /// Whether it belongs to the output map (which every law has).
    pub output_map: bool,
    /// Its unit.
    pub unit: &'static str,
    /// The sane bounds as text (`[-1e6, 1e6]`, `|x| in [1e-6, 1e6]`).
    pub bounds: String,
    /// The lowest sane value (of the magnitude, if `magnitude`); `null`: unbounded.
    pub lo: Option<f64>,
    /// The highest sane value (of the magnitude, if `magnitude`); `null`: unbounded.
    pub hi: Option<f64>,
    /// Whether the bounds are on `|x|` (either sign, never 0).
    pub magnitude: bool,
    /// What it does.
    pub meaning: &'static str,
}

/// The table for `mfcctl --json params`.
pub fn params_json() -> Vec<ParamJson> {
    use mfc::params::Bounds;
    PARAMS
        .iter()
        .map(|p| {
            let (lo, hi, magnitude) = match p.bounds {
                Bounds::Range { lo, hi } => (lo, hi, false),
                Bounds::Magnitude { lo, hi } => (lo, hi, true),
            };
            ParamJson {
                name: p.name,
                laws: LawKind::ALL
                    .iter()
                    .filter(|k| p.applies_to(**k))
                    .map(|k| k.name())
                    .collect(),
                output_map: p.scope == Scope::OutputMap,
                unit: p.unit,
                bounds: p.bounds.to_string(),
                lo: Some(lo).filter(|x| x.is_finite()),
                hi: Some(hi).filter(|x| x.is_finite()),
                magnitude,
                meaning: p.meaning,
            }
        })
        .collect()
}

/// The fields `mfcctl set` accepts, per law, from the table (its help).
pub fn set_fields() -> String {
    let mut out = String::from("Fields (`mfcctl params` for units, bounds and meanings):\n");
    let names = |f: &dyn Fn(&Param) -> bool| {
        PARAMS
            .iter()
            .filter(|p| f(p))
            .map(|p| p.name)
            .collect::<Vec<_>>()
            .join(" ")
    };
    for k in LawKind::ALL {
        let law = names(&|p| matches!(p.scope, Scope::Laws(l) if l.contains(&k)));
        let _ = writeln!(out, "  {:<12} {law}", k.name());
    }
    let map = names(&|p| p.scope == Scope::OutputMap);
    let _ = writeln!(out, "  {:<12} {map} (every law)", "output map");
    out.push_str("Output limits must stay inside the envelope.");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn audit_entries_read_well() {
        // 2026-11-26 17:30:05.250 UTC.
        assert_eq!(
            utc(1_795_714_205_250_000_000),
            "2026-11-26 17:30:05.250 UTC"
        );
        assert_eq!(utc(0), "1970-01-01 00:00:00.000 UTC");
        let e = |accepted: bool, verified: bool| pb::AuditEntry {
            unix_ns: 1_795_714_205_250_000_000,
            member: "c-1".into(),
            device_id: "aero-1".into(),
            operator: "alice".into(),
            verified,
            role: "operator".into(),
            action: "configuration".into(),
            changes: vec![pb::AuditChange {
                what: "channel 1 kp".into(),
                old: "400".into(),
                new: "450".into(),
            }],
            asked: if accepted {
                String::new()
            } else {
                "updates: kp 1e308".into()
            },
            accepted,
            reason: if accepted {
                String::new()
            } else {
                "kp: at most 4e4".into()
            },
            ..Default::default()
        };
        let text = audit(&[pb::AuditLog {
            device_id: "aero-1".into(),
            entries: vec![e(true, true), e(false, false)],
            ..Default::default()
        }]);
        assert!(
            text.contains(
                "2026-11-26 17:30:05.250 UTC alice (operator) configuration on c-1: accepted"
            ),
            "{text}"
        );
        assert!(text.contains("channel 1 kp: 400 -> 450"), "{text}");
        assert!(
            text.contains(
                "alice (operator, unverified) configuration on c-1: REFUSED: kp: at most 4e4"
            ),
            "{text}"
        );
        assert!(text.contains("asked: updates: kp 1e308"), "{text}");
        assert_eq!(audit(&[]), "no audited change\n");
    }

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
    fn the_parameter_table_reads_well_in_every_form() {
        let text = params();
        assert_eq!(text.lines().count(), PARAMS.len() + 1);
        assert!(
            text.lines().any(|l| l.starts_with("alpha ")
                && l.contains("intelligent")
                && l.contains("|x| in [1e-6, 1e6]")),
            "{text}"
        );
        let md = params_markdown();
        assert!(
            md.contains("| `alpha` | intelligent | y/(u s^n) | \\|x\\| in [1e-6, 1e6] |"),
            "{md}"
        );
        assert!(md.contains("| `rate_limit` | every law (output map) | v/s | [1e-6, inf] |"));
        let json = serde_json::to_value(params_json()).unwrap();
        assert_eq!(json.as_array().unwrap().len(), PARAMS.len());
        let kp = &json[0];
        assert_eq!(kp["name"], "kp");
        assert_eq!(kp["laws"], serde_json::json!(["intelligent", "pid"]));
        assert_eq!(
            (kp["lo"].as_f64(), kp["hi"].as_f64()),
            (Some(-1e6), Some(1e6))
        );
        let max = &json[PARAMS.len() - 2];
        assert_eq!(
            (max["name"].as_str(), max["hi"].is_null()),
            (Some("max"), true)
        );
        assert_eq!(
            max["laws"],
            serde_json::json!(["intelligent", "pid", "adrc"])
        );
        let help = set_fields();
        assert!(
            help.contains("  pid          kp ki kd derivative_filter setpoint_weight\n"),
            "{help}"
        );
        assert!(
            help.contains("dead_zone smoothing min max rate_limit (every law)"),
            "{help}"
        );
    }

    /// `docs/parameters.md` is the table's rendering; `MFC_BLESS=1` writes it again.
    #[test]
    fn docs_parameters_md_is_the_rendered_table() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/parameters.md");
        let want = params_markdown();
        if std::env::var("MFC_BLESS").is_ok_and(|v| v == "1") {
            std::fs::write(&path, &want).unwrap();
        }
        let got = std::fs::read_to_string(&path).unwrap_or_default();
        assert!(
            got == want,
            "docs/parameters.md differs from `mfcctl params --markdown` (the table in \
             mfc/src/params.rs): run `MFC_BLESS=1 cargo test -p mfcctl` to write it again"
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
