//! Conversions between the wire configuration and the control core's types.
//!
//! `*_from_pb` checks everything a peer could get wrong and returns a typed error naming the
//! field; the result is then checked again by the core when a controller is built from it.

use mfc::params::{Param, PARAMS};
use mfc::trajectory::Piece;
use mfc::{
    AdrcParams, ChannelConfig, ControllerKind, EstimatorConfig, EstimatorKind, IntelligentParams,
    LawConfig, Order, OutputMapConfig, PidParams,
};

use crate::pb;

/// A wire configuration the core cannot represent, or whose values it refuses.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {reason}")]
pub struct ConvertError {
    /// Path of the bad field inside the converted message, e.g. `intelligent.order` or
    /// `reference.channels[1].piece.duration`; just `channel` when the core refuses the
    /// assembled channel. The service prefixes a channel's index (`channels[2].`).
    pub field: String,
    /// Readable on its own: `missing`, `order must be 1 or 2, got 3`, or the core's message.
    pub reason: String,
}

fn err(field: impl Into<String>, reason: impl Into<String>) -> ConvertError {
    ConvertError {
        field: field.into(),
        reason: reason.into(),
    }
}

fn order_from(n: u32, field: &str) -> Result<Order, ConvertError> {
    match n {
        1 => Ok(Order::One),
        2 => Ok(Order::Two),
        _ => Err(err(field, format!("order must be 1 or 2, got {n}"))),
    }
}

fn order_to(o: Order) -> u32 {
    u32::from(o.n())
}

/// Core channel configuration to wire. Infinite limits go out absent and an infinite
/// `max_interval` as 0, the wire's ways of saying "unbounded".
pub fn channel_to_pb(c: &ChannelConfig) -> pb::ChannelConfig {
    use pb::channel_config::Law;
    let law = match c.law {
        LawConfig::Intelligent { params, estimator } => Law::Intelligent(pb::Intelligent {
            kind: match params.kind {
                ControllerKind::P => pb::IntelligentKind::Ip,
                ControllerKind::PI => pb::IntelligentKind::Ipi,
                ControllerKind::PD => pb::IntelligentKind::Ipd,
                ControllerKind::PID => pb::IntelligentKind::Ipid,
            } as i32,
            order: order_to(params.order),
            alpha: params.alpha,
            kp: params.kp,
            ki: params.ki,
            kd: params.kd,
            derivative_filter: params.derivative_filter,
            bumpless_time_constant: params.bumpless_time_constant,
            derivative_observer: params.derivative_observer,
            estimate_filter: params.estimate_filter,
            hold_estimate_filter: params.hold_estimate_filter,
            hold_after: Some(params.hold_after),
            hold_band: params.hold_band,
            feedforward_within_range: params.feedforward_within_range,
            estimator: Some(pb::Estimator {
                kind: match estimator.kind {
                    EstimatorKind::Algebraic => pb::estimator::Kind::Algebraic,
                    EstimatorKind::ClosedLoop => pb::estimator::Kind::ClosedLoop,
                    EstimatorKind::LowPass { .. } => pb::estimator::Kind::LowPass,
                } as i32,
                window: u32::try_from(estimator.window).unwrap_or(u32::MAX),
                time_constant: match estimator.kind {
                    EstimatorKind::LowPass { time_constant } => time_constant,
                    _ => 0.0,
                },
                max_interval: if estimator.max_interval.is_finite() {
                    estimator.max_interval
                } else {
                    0.0
                },
                first_window: u32::try_from(estimator.first_window).unwrap_or(u32::MAX),
            }),
        }),
        LawConfig::Pid { params } => Law::Pid(pb::Pid {
            kp: params.kp,
            ki: params.ki,
            kd: params.kd,
            derivative_filter: params.derivative_filter,
            setpoint_weight: params.setpoint_weight,
            tracking_gain: params.tracking_gain,
            out_min: params.out_min.is_finite().then_some(params.out_min),
            out_max: params.out_max.is_finite().then_some(params.out_max),
        }),
        LawConfig::Adrc { params } => Law::Adrc(pb::Adrc {
            order: order_to(params.order),
            b0: params.b0,
            wc: params.wc,
            wo: params.wo,
        }),
    };
    let o = c.output;
    pb::ChannelConfig {
        law: Some(law),
        output: Some(pb::OutputMap {
            dead_zone: o.dead_zone,
            smoothing: o.smoothing,
            min: o.min.is_finite().then_some(o.min),
            max: o.max.is_finite().then_some(o.max),
            rate_limit: o.rate_limit,
        }),
    }
}

/// Wire channel configuration to core (checked by the core as well). The inverse of
/// [`channel_to_pb`]: absent limits read as infinite, `max_interval` 0 as infinite.
pub fn channel_from_pb(c: &pb::ChannelConfig) -> Result<ChannelConfig, ConvertError> {
    use pb::channel_config::Law;
    let law = match &c.law {
        None => return Err(err("law", "missing")),
        Some(Law::Intelligent(i)) => {
            let kind = match pb::IntelligentKind::try_from(i.kind) {
                Ok(pb::IntelligentKind::Ip) => ControllerKind::P,
                Ok(pb::IntelligentKind::Ipi) => ControllerKind::PI,
                Ok(pb::IntelligentKind::Ipd) => ControllerKind::PD,
                Ok(pb::IntelligentKind::Ipid) => ControllerKind::PID,
                _ => return Err(err("intelligent.kind", format!("unknown kind {}", i.kind))),
            };
            let e = i.estimator.unwrap_or_default();
            let est_kind = match pb::estimator::Kind::try_from(e.kind) {
                Ok(pb::estimator::Kind::Algebraic) => EstimatorKind::Algebraic,
                Ok(pb::estimator::Kind::ClosedLoop) => EstimatorKind::ClosedLoop,
                Ok(pb::estimator::Kind::LowPass) => EstimatorKind::LowPass {
                    time_constant: e.time_constant,
                },
                Err(_) => {
                    return Err(err(
                        "intelligent.estimator.kind",
                        format!("unknown kind {}", e.kind),
                    ))
                }
            };
            LawConfig::Intelligent {
                params: IntelligentParams {
                    kind,
                    order: order_from(i.order, "intelligent.order")?,
                    alpha: i.alpha,
                    kp: i.kp,
                    ki: i.ki,
                    kd: i.kd,
                    derivative_filter: i.derivative_filter,
                    bumpless_time_constant: i.bumpless_time_constant,
                    derivative_observer: i.derivative_observer,
                    estimate_filter: i.estimate_filter,
                    hold_estimate_filter: i.hold_estimate_filter,
                    hold_after: i
                        .hold_after
                        .unwrap_or(IntelligentParams::default().hold_after),
                    hold_band: i.hold_band,
                    feedforward_within_range: i.feedforward_within_range,
                },
                estimator: EstimatorConfig {
                    kind: est_kind,
                    window: e.window as usize,
                    max_interval: if e.max_interval == 0.0 {
                        f64::INFINITY
                    } else {
                        e.max_interval
                    },
                    first_window: e.first_window as usize,
                },
            }
        }
        Some(Law::Pid(p)) => LawConfig::Pid {
            params: PidParams {
                kp: p.kp,
                ki: p.ki,
                kd: p.kd,
                derivative_filter: p.derivative_filter,
                setpoint_weight: p.setpoint_weight,
                tracking_gain: p.tracking_gain,
                out_min: p.out_min.unwrap_or(f64::NEG_INFINITY),
                out_max: p.out_max.unwrap_or(f64::INFINITY),
            },
        },
        Some(Law::Adrc(a)) => LawConfig::Adrc {
            params: AdrcParams {
                order: order_from(a.order, "adrc.order")?,
                b0: a.b0,
                wc: a.wc,
                wo: a.wo,
            },
        },
    };
    let o = c.output.unwrap_or_default();
    let output = OutputMapConfig {
        dead_zone: o.dead_zone,
        smoothing: o.smoothing,
        min: o.min.unwrap_or(f64::NEG_INFINITY),
        max: o.max.unwrap_or(f64::INFINITY),
        rate_limit: o.rate_limit,
    };
    let cfg = ChannelConfig { law, output };
    // Let the core say what is out of range.
    mfc::Channel::<{ mfc::DEFAULT_CAPACITY }>::new(&cfg)
        .map_err(|e| err("channel", e.to_string()))?;
    Ok(cfg)
}

/// The field of a [`pb::ChannelUpdate`] that carries the tunable parameter `name` (a name
/// of [`mfc::params::PARAMS`]); `None` for any other name. The one place that binds the
/// table's names to the wire's fields: a test checks through the schema that the update's
/// optional numbers are exactly the table's names, each bound to the field of its name.
pub fn update_field<'a>(u: &'a mut pb::ChannelUpdate, name: &str) -> Option<&'a mut Option<f64>> {
    Some(match name {
        "kp" => &mut u.kp,
        "ki" => &mut u.ki,
        "kd" => &mut u.kd,
        "alpha" => &mut u.alpha,
        "derivative_filter" => &mut u.derivative_filter,
        "derivative_observer" => &mut u.derivative_observer,
        "estimate_filter" => &mut u.estimate_filter,
        "hold_estimate_filter" => &mut u.hold_estimate_filter,
        "hold_after" => &mut u.hold_after,
        "hold_band" => &mut u.hold_band,
        "b0" => &mut u.b0,
        "wc" => &mut u.wc,
        "wo" => &mut u.wo,
        "setpoint_weight" => &mut u.setpoint_weight,
        "dead_zone" => &mut u.dead_zone,
        "smoothing" => &mut u.smoothing,
        "min" => &mut u.min,
        "max" => &mut u.max,
        "rate_limit" => &mut u.rate_limit,
        _ => return None,
    })
}

/// The parameters `u` sets, in the table's order, with their values.
pub fn update_values(u: &pb::ChannelUpdate) -> impl Iterator<Item = (&'static Param, f64)> {
    let mut u = *u;
    PARAMS.iter().filter_map(move |p| {
        update_field(&mut u, p.name)
            .and_then(|v| *v)
            .map(|v| (p, v))
    })
}

/// Apply a merge change ([`pb::ChannelUpdate`]) to one channel's configuration: a new law
/// first if the update carries one (the output map is kept), then every single parameter
/// present, through the table ([`mfc::params`]). A parameter the law in force does not
/// have is refused with its name, so a client never believes a gain changed when it did
/// not. Output-map limits come out as asked; fitting them into the device's envelope is
/// the caller's job.
pub fn apply_update(
    c: &ChannelConfig,
    u: &pb::ChannelUpdate,
) -> Result<ChannelConfig, ConvertError> {
    use pb::channel_config::Law as CLaw;
    use pb::channel_update::Law as ULaw;
    let mut cfg = *c;
    if let Some(law) = &u.law {
        let law = match law {
            ULaw::Intelligent(i) => CLaw::Intelligent(*i),
            ULaw::Pid(p) => CLaw::Pid(*p),
            ULaw::Adrc(a) => CLaw::Adrc(*a),
        };
        let mut wire = channel_to_pb(c);
        wire.law = Some(law);
        cfg.law = channel_from_pb(&wire)?.law;
    }
    for (p, v) in update_values(u) {
        p.set(&mut cfg, v).map_err(|e| err(p.name, e.to_string()))?;
    }
    // Let the core say what is out of range (a NaN gain, a negative alpha, min above max).
    mfc::Channel::<{ mfc::DEFAULT_CAPACITY }>::new(&cfg)
        .map_err(|e| err("channel", e.to_string()))?;
    Ok(cfg)
}

/// Core piece to wire; a sine that never ends goes out without `end`.
pub fn piece_to_pb(p: &Piece) -> pb::Piece {
    use pb::piece::Shape;
    let shape = match *p {
        Piece::Constant { value } => Shape::Constant(pb::Constant { value }),
        Piece::Ramp { start, end, slope } => Shape::Ramp(pb::Ramp { start, end, slope }),
        Piece::SmoothStep {
            start,
            duration,
            height,
        } => Shape::SmoothStep(pb::SmoothStep {
            start,
            duration,
            height,
        }),
        Piece::Sine {
            amplitude,
            period,
            phase,
            start,
            end,
            fade,
        } => Shape::Sine(pb::Sine {
            amplitude,
            period,
            phase,
            start,
            end: end.is_finite().then_some(end),
            fade,
        }),
    };
    pb::Piece { shape: Some(shape) }
}

/// Wire piece to core, checked by `Piece::validate`; a sine without `end` never ends.
pub fn piece_from_pb(p: &pb::Piece) -> Result<Piece, ConvertError> {
    use pb::piece::Shape;
    let piece = match &p.shape {
        None => return Err(err("piece", "missing shape")),
        Some(Shape::Constant(c)) => Piece::Constant { value: c.value },
        Some(Shape::Ramp(r)) => Piece::Ramp {
            start: r.start,
            end: r.end,
            slope: r.slope,
        },
        Some(Shape::SmoothStep(s)) => Piece::SmoothStep {
            start: s.start,
            duration: s.duration,
            height: s.height,
        },
        Some(Shape::Sine(s)) => Piece::Sine {
            amplitude: s.amplitude,
            period: s.period,
            phase: s.phase,
            start: s.start,
            end: s.end.unwrap_or(f64::INFINITY),
            fade: s.fade,
        },
    };
    piece
        .validate()
        .map_err(|(field, reason)| err(format!("piece.{field}"), reason))?;
    Ok(piece)
}

/// Per-channel pieces, and the plant time (s) they are evaluated from, to wire.
pub fn reference_to_pb(channels: &[Vec<Piece>], start_time: f64) -> pb::Reference {
    pb::Reference {
        channels: channels
            .iter()
            .map(|pieces| pb::ChannelReference {
                pieces: pieces.iter().map(piece_to_pb).collect(),
            })
            .collect(),
        start_time,
    }
}

/// Most pieces one channel's reference may have. Every piece is evaluated at every sample,
/// so a request must not be able to make each step of a device slow; the shipped
/// scenarios use a dozen at most.
pub const MAX_PIECES: usize = 256;

/// Wire reference to per-channel pieces and start time, checked. The number of channels is
/// not: only the caller knows the device it is meant for.
pub fn reference_from_pb(r: &pb::Reference) -> Result<(Vec<Vec<Piece>>, f64), ConvertError> {
    if !r.start_time.is_finite() {
        return Err(err("reference.start_time", "must be finite"));
    }
    if let Some((i, c)) = r
        .channels
        .iter()
        .enumerate()
        .find(|(_, c)| c.pieces.len() > MAX_PIECES)
    {
        return Err(err(
            format!("reference.channels[{i}].pieces"),
            format!("{} pieces, more than {MAX_PIECES}", c.pieces.len()),
        ));
    }
    let channels = r
        .channels
        .iter()
        .enumerate()
        .map(|(i, c)| {
            c.pieces
                .iter()
                .map(piece_from_pb)
                .collect::<Result<Vec<_>, _>>()
                .map_err(|e| err(format!("reference.channels[{i}].{}", e.field), e.reason))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((channels, r.start_time))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `.proto` cannot drift from the table: the optional numbers of `ChannelUpdate`
    /// are exactly the table's names, and [`update_field`] binds each name to the field of
    /// that name (set through the binding, read back through the schema).
    #[test]
    fn channel_update_carries_exactly_the_tables_parameters() {
        use prost::Message;
        use prost_reflect::{Cardinality, DescriptorPool, DynamicMessage, Kind, Value};
        let pool = DescriptorPool::decode(crate::FILE_DESCRIPTOR_SET).unwrap();
        let update = pool
            .get_message_by_name(&format!("{}.ChannelUpdate", crate::PACKAGE))
            .unwrap();
        let mut wire: Vec<String> = update
            .fields()
            .filter(|f| {
                f.kind() == Kind::Double
                    && f.cardinality() == Cardinality::Optional
                    && f.supports_presence()
            })
            .map(|f| f.name().to_string())
            .collect();
        let mut table: Vec<String> = mfc::params::names().map(String::from).collect();
        wire.sort();
        table.sort();
        assert_eq!(
            wire, table,
            "ChannelUpdate's optional doubles against the table"
        );
        for (i, p) in PARAMS.iter().enumerate() {
            let mut u = pb::ChannelUpdate::default();
            *update_field(&mut u, p.name).unwrap() = Some(i as f64 + 0.5);
            let dm = DynamicMessage::decode(update.clone(), u.encode_to_vec().as_slice()).unwrap();
            let set: Vec<_> = dm
                .fields()
                .map(|(f, v)| (f.name().to_string(), v.clone()))
                .collect();
            assert_eq!(set, [(p.name.to_string(), Value::F64(i as f64 + 0.5))]);
            assert_eq!(
                update_values(&u)
                    .map(|(q, v)| (q.name, v))
                    .collect::<Vec<_>>(),
                [(p.name, i as f64 + 0.5)]
            );
        }
        assert!(update_field(&mut pb::ChannelUpdate::default(), "channel").is_none());
    }

    #[test]
    fn an_update_sets_what_the_law_has_and_names_what_it_has_not() {
        let pid = ChannelConfig {
            law: LawConfig::Pid {
                params: PidParams::default(),
            },
            output: OutputMapConfig::AERO,
        };
        let u = pb::ChannelUpdate {
            kp: Some(2.5),
            setpoint_weight: Some(0.5),
            rate_limit: Some(40.0),
            ..Default::default()
        };
        let c = apply_update(&pid, &u).unwrap();
        let LawConfig::Pid { params } = c.law else {
            panic!("{c:?}")
        };
        assert_eq!((params.kp, params.setpoint_weight), (2.5, 0.5));
        assert_eq!(c.output.rate_limit, Some(40.0));
        let e = apply_update(
            &pid,
            &pb::ChannelUpdate {
                kp: Some(3.0),
                alpha: Some(2.0),
                ..Default::default()
            },
        )
        .unwrap_err();
        assert_eq!(
            (e.field.as_str(), e.reason.as_str()),
            ("alpha", "the pid law in force has no alpha")
        );
        // A new law comes first: its parameters may then be set.
        let to_adrc = pb::ChannelUpdate {
            law: Some(pb::channel_update::Law::Adrc(pb::Adrc {
                order: 1,
                b0: 1.0,
                wc: 5.0,
                wo: 25.0,
            })),
            wc: Some(7.0),
            ..Default::default()
        };
        let c = apply_update(&pid, &to_adrc).unwrap();
        assert!(matches!(c.law, LawConfig::Adrc { params } if params.wc == 7.0));
        assert_eq!(c.output, OutputMapConfig::AERO);
        let e = apply_update(
            &c,
            &pb::ChannelUpdate {
                kp: Some(1.0),
                ..Default::default()
            },
        );
        assert_eq!(e.unwrap_err().reason, "the adrc law in force has no kp");
    }

    #[test]
    fn round_trips() {
        let configs = [
            ChannelConfig::default(),
            ChannelConfig {
                law: LawConfig::intelligent(
                    ControllerKind::PD,
                    Order::Two,
                    0.1,
                    [9.0, 0.0, 3.0],
                    20,
                ),
                output: OutputMapConfig::AERO,
            },
            // Every option of an intelligent law away from its default.
            ChannelConfig {
                law: LawConfig::Intelligent {
                    params: mfc::IntelligentParams {
                        kind: ControllerKind::PD,
                        order: Order::Two,
                        alpha: -0.2,
                        derivative_observer: 30.0,
                        estimate_filter: 0.05,
                        hold_estimate_filter: 0.15,
                        hold_after: 0.5,
                        hold_band: 1.0,
                        feedforward_within_range: true,
                        ..Default::default()
                    },
                    estimator: mfc::EstimatorConfig {
                        window: 20,
                        first_window: 5,
                        ..Default::default()
                    },
                },
                output: OutputMapConfig::AERO,
            },
            ChannelConfig {
                law: LawConfig::Pid {
                    params: PidParams {
                        kp: 3.0,
                        ki: 1.0,
                        out_min: -5.0,
                        out_max: 5.0,
                        ..Default::default()
                    },
                },
                output: OutputMapConfig {
                    rate_limit: Some(100.0),
                    ..Default::default()
                },
            },
            ChannelConfig {
                law: LawConfig::Adrc {
                    params: AdrcParams::default(),
                },
                output: OutputMapConfig::default(),
            },
        ];
        for c in configs {
            assert_eq!(channel_from_pb(&channel_to_pb(&c)).unwrap(), c);
        }
        let pieces = vec![
            vec![
                Piece::Constant { value: 1.0 },
                Piece::Sine {
                    amplitude: 0.1,
                    period: 2.0,
                    phase: 0.0,
                    start: 0.0,
                    end: f64::INFINITY,
                    fade: 0.0,
                },
            ],
            vec![Piece::SmoothStep {
                start: 1.0,
                duration: 2.0,
                height: 0.3,
            }],
        ];
        assert_eq!(
            reference_from_pb(&reference_to_pb(&pieces, 4.0)).unwrap(),
            (pieces, 4.0)
        );
    }

    #[test]
    fn a_reference_with_too_many_pieces_is_refused() {
        let ok = vec![vec![Piece::Constant { value: 1.0 }; MAX_PIECES]];
        assert!(reference_from_pb(&reference_to_pb(&ok, 0.0)).is_ok());
        let long = vec![vec![], vec![Piece::Constant { value: 1.0 }; MAX_PIECES + 1]];
        let e = reference_from_pb(&reference_to_pb(&long, 0.0)).unwrap_err();
        assert_eq!(e.field, "reference.channels[1].pieces");
    }

    #[test]
    fn bad_wire_configs_are_refused_with_the_field() {
        let mut c = channel_to_pb(&ChannelConfig::default());
        if let Some(pb::channel_config::Law::Intelligent(i)) = &mut c.law {
            i.alpha = 0.0;
        }
        assert!(channel_from_pb(&c).unwrap_err().reason.contains("alpha"));
        let mut c = channel_to_pb(&ChannelConfig::default());
        if let Some(pb::channel_config::Law::Intelligent(i)) = &mut c.law {
            i.order = 3;
        }
        assert_eq!(channel_from_pb(&c).unwrap_err().field, "intelligent.order");
        assert_eq!(
            channel_from_pb(&pb::ChannelConfig::default())
                .unwrap_err()
                .field,
            "law"
        );
        let bad = pb::Piece {
            shape: Some(pb::piece::Shape::SmoothStep(pb::SmoothStep {
                start: 0.0,
                duration: -1.0,
                height: 1.0,
            })),
        };
        assert_eq!(piece_from_pb(&bad).unwrap_err().field, "piece.duration");
    }
}
