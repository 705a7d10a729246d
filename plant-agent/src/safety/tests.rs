//! The tests of [`super`]: its rules case by case, kept apart so the file reads as the rules.

use super::*;
use mfc::{ControllerKind, LawConfig, Order, OutputMapConfig};

const H: f64 = 0.5;

fn channel() -> ChannelConfig {
    ChannelConfig {
        law: LawConfig::intelligent(ControllerKind::P, Order::One, 2.0, [3.0, 0.0, 0.0], 3),
        output: OutputMapConfig {
            dead_zone: 0.0,
            smoothing: 0.0,
            min: -24.0,
            max: 24.0,
            rate_limit: None,
        },
    }
}

fn config(max_age: u32, hold_periods: u32, fallback: FallbackPolicy) -> SafetyConfig {
    SafetyConfig {
        period: H,
        max_age,
        hold_periods,
        fallback,
    }
}

fn sup_n(n: usize, max_age: u32, hold: u32, fallback: FallbackPolicy) -> Supervisor {
    Supervisor::new(
        config(max_age, hold, fallback),
        &vec![channel(); n],
        vec![0.0; n],
    )
    .unwrap()
}

fn sup(max_age: u32, hold: u32, fallback: FallbackPolicy) -> Supervisor {
    sup_n(1, max_age, hold, fallback)
}

fn refs(n: usize) -> Vec<Reference> {
    vec![Reference::constant(1.0); n]
}

fn ctl(seq: u64, v: &[f64]) -> IncomingCommand<'_> {
    IncomingCommand {
        seq,
        body: CommandBody::Control(v),
        horizon: &[],
        lease: Credentials::default(),
    }
}

fn warm(seq: u64) -> IncomingCommand<'static> {
    IncomingCommand {
        seq,
        body: CommandBody::WarmingUp,
        horizon: &[],
        lease: Credentials::default(),
    }
}

fn rejected(seq: u64) -> IncomingCommand<'static> {
    IncomingCommand {
        seq,
        body: CommandBody::Rejected("no"),
        horizon: &[],
        lease: Credentials::default(),
    }
}

/// Begin period k with y = 0.1 k on every channel, applying any fallback write exactly.
fn begin(s: &mut Supervisor, k: u64) -> PeriodBegin {
    let n = s.channels();
    let b = s
        .begin_period(k, k as f64 * H, &vec![0.1 * k as f64; n], &refs(n))
        .unwrap();
    if let Some(v) = &b.write {
        s.applied(v);
    }
    b
}

/// Hand a command to the supervisor, applying it exactly if it is to be applied.
fn command(s: &mut Supervisor, at: f64, cmd: IncomingCommand<'_>) -> (Verdict, bool) {
    let r = s.on_command(at, cmd);
    if let Verdict::Apply { v, .. } = &r.0 {
        s.applied(v);
    }
    r
}

/// A whole period with an optional on-time command at 0.2 s.
fn period(s: &mut Supervisor, k: u64, v: Option<f64>) -> (PeriodBegin, PeriodEnd) {
    let b = begin(s, k);
    if let Some(v) = v {
        let cmd = vec![v; s.channels()];
        let (verdict, done) = command(s, 0.2, ctl(k, &cmd));
        assert!(
            matches!(verdict, Verdict::Apply { .. }) && done,
            "{verdict:?}"
        );
    }
    (b, s.end_period().unwrap())
}

fn ignored(s: &mut Supervisor, cmd: IncomingCommand<'_>) -> Ignored {
    let before = format!("{:?}", (s.mode, s.missing_streak, s.last_applied_seq));
    let applied = s.applied.clone();
    match s.on_command(0.1, cmd) {
        (Verdict::Ignored(why), false) => {
            assert_eq!(
                before,
                format!("{:?}", (s.mode, s.missing_streak, s.last_applied_seq))
            );
            assert_eq!(applied, s.applied);
            why
        }
        other => panic!("expected to be ignored: {other:?}"),
    }
}

fn total(c: &SupervisorCounters) -> u64 {
    c.commands
        + c.too_old
        + c.superseded
        + c.duplicates
        + c.warming_up
        + c.rejected
        + c.malformed
        + c.fenced
        + c.future
}

fn planned<'a>(seq: u64, v: &'a [f64], horizon: &'a [f64]) -> IncomingCommand<'a> {
    IncomingCommand {
        seq,
        body: CommandBody::Control(v),
        horizon,
        lease: Credentials::default(),
    }
}

// ---- the horizon (packetized predictive control) ----

#[test]
fn lost_commands_are_replaced_by_their_elements_of_the_last_horizon() {
    // Two channels; command 3 carries three periods: 4 -> (1, 2), 5 -> (3, 4), 6 -> (5, 6).
    let mut s = sup_n(2, 10, 5, FallbackPolicy::LocalController);
    for k in 0..3 {
        period(&mut s, k, Some(0.5));
    }
    begin(&mut s, 3);
    let h = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
    let (verdict, done) = command(&mut s, 0.1, planned(3, &[9.0, 9.5], &h));
    assert!(done && matches!(verdict, Verdict::Apply { ref v, .. } if v == &[9.0, 9.5]));
    s.end_period().unwrap();
    // Commands 4 and 5 are lost: each period starts on its element, not on the hold.
    for (k, want) in [(4, [1.0, 2.0]), (5, [3.0, 4.0]), (6, [5.0, 6.0])] {
        let b = begin(&mut s, k);
        assert_eq!(b.write.as_deref(), Some(&want[..]), "period {k}");
        assert_eq!(s.applied_now(), &want);
        let end = s.end_period().unwrap();
        assert!(end.missing);
        assert_eq!(end.mode, LoopMode::Holding);
    }
    // What each period applied is what the next sample reports: the estimator's input.
    let b = begin(&mut s, 7);
    assert_eq!(b.applied_mean, vec![5.0, 6.0]);
    // Past the horizon: the last value is held until the fallback is due (hold 5).
    assert_eq!(b.write, None);
    s.end_period().unwrap();
    let c = s.counters();
    assert_eq!((c.horizon_periods, c.holding_periods, c.missing), (3, 4, 4));
    let b = begin(&mut s, 8);
    assert_eq!(b.write, None);
    s.end_period().unwrap();
    let b = begin(&mut s, 9);
    assert_eq!(s.mode(), LoopMode::Local, "{b:?}");
    assert_eq!(s.counters().fallbacks, 1);
}

#[test]
fn the_mean_applied_over_a_period_counts_the_element_until_the_own_command_lands() {
    let mut s = sup(10, 5, FallbackPolicy::LocalController);
    begin(&mut s, 0);
    command(&mut s, 0.0, planned(0, &[2.0], &[4.0, 6.0]));
    s.end_period().unwrap();
    // Period 1: the element (4) from the deadline, the own command (8) from 0.1 s on.
    let b = begin(&mut s, 1);
    assert_eq!(b.write, Some(vec![4.0]));
    command(&mut s, 0.1, planned(1, &[8.0], &[]));
    s.end_period().unwrap();
    let b = begin(&mut s, 2);
    let want = (4.0 * 0.1 + 8.0 * (H - 0.1)) / H;
    assert!((b.applied_mean[0] - want).abs() < 1e-12, "{b:?}");
    // Command 1 had no horizon: period 2 holds 8, nothing is written.
    assert_eq!(b.write, None);
    assert_eq!(s.counters().horizon_periods, 0);
}

#[test]
fn a_late_command_applies_the_element_for_the_period_it_lands_in() {
    let mut s = sup(10, 100, FallbackPolicy::LocalController);
    for k in 0..3 {
        begin(&mut s, k);
        s.end_period().unwrap();
    }
    begin(&mut s, 3);
    // Command 0 lands in period 3: element 3 - 0 - 1 = 2 of its horizon.
    let (verdict, _) = command(&mut s, 0.1, planned(0, &[1.0], &[2.0, 3.0, 4.0, 5.0]));
    assert!(matches!(verdict, Verdict::Apply { ref v, late: true, .. } if v == &[4.0]));
    assert_eq!(s.counters().horizon_late, 1);
    s.end_period().unwrap();
    // Its next element plays in period 4.
    assert_eq!(begin(&mut s, 4).write, Some(vec![5.0]));
    s.end_period().unwrap();
    // A command later than its horizon is long applies the last element.
    begin(&mut s, 5);
    s.end_period().unwrap();
    begin(&mut s, 6);
    let (verdict, _) = command(&mut s, 0.1, planned(2, &[1.0], &[7.0, 8.0]));
    assert!(matches!(verdict, Verdict::Apply { ref v, .. } if v == &[8.0]));
}

#[test]
fn the_safe_stop_applies_the_plants_own_safe_inputs() {
    let mut s = sup_n(2, 10, 1, FallbackPolicy::SafeStop);
    assert!(matches!(
        s.set_safe_inputs(vec![0.5]),
        Err(SafetyError::ChannelMismatch {
            expected: 2,
            got: 1,
            ..
        })
    ));
    assert!(matches!(
        s.set_safe_inputs(vec![0.5, f64::NAN]),
        Err(SafetyError::NonFiniteSafe)
    ));
    s.set_safe_inputs(vec![0.5, -2.0]).unwrap();
    begin(&mut s, 0);
    command(&mut s, 0.1, ctl(0, &[1.0, 1.0]));
    s.end_period().unwrap();
    begin(&mut s, 1);
    s.end_period().unwrap();
    // The controller is silent: the fallback writes the safe inputs, not zeros.
    assert_eq!(begin(&mut s, 2).write, Some(vec![0.5, -2.0]));
    assert_eq!(s.mode(), LoopMode::SafeStop);
}

#[test]
fn a_bad_horizon_makes_the_command_malformed_and_the_fallback_clears_it() {
    let mut s = sup_n(2, 10, 1, FallbackPolicy::SafeStop);
    begin(&mut s, 0);
    let v = [1.0, 1.0];
    assert_eq!(
        ignored(&mut s, planned(0, &v, &[1.0, 2.0, 3.0])),
        Ignored::Malformed
    );
    assert_eq!(
        ignored(&mut s, planned(0, &v, &[1.0, f64::NAN])),
        Ignored::Malformed
    );
    let long = vec![0.0; 2 * (MAX_HORIZON as usize + 1)];
    assert_eq!(ignored(&mut s, planned(0, &v, &long)), Ignored::Malformed);
    // A whole horizon is accepted; then the link dies and the safe stop engages.
    command(&mut s, 0.1, planned(0, &v, &[2.0, 2.0, 3.0, 3.0, 4.0, 4.0]));
    s.end_period().unwrap();
    assert_eq!(begin(&mut s, 1).write, Some(vec![2.0, 2.0]));
    s.end_period().unwrap();
    assert_eq!(begin(&mut s, 2).write, Some(vec![0.0, 0.0]));
    assert_eq!(s.mode(), LoopMode::SafeStop);
    s.end_period().unwrap();
    // Never the horizon again under the fallback, although it would reach period 3.
    assert_eq!(begin(&mut s, 3).write, Some(vec![0.0, 0.0]));
}

// ---- configuration, construction, serde ----

#[test]
fn config_validation_boundaries() {
    let ok = config(1000, 100_000, FallbackPolicy::SafeStop);
    assert_eq!(ok.validate(), Ok(()));
    for period in [0.0, -0.1, f64::NAN, f64::INFINITY, f64::NEG_INFINITY] {
        let c = SafetyConfig { period, ..ok };
        assert!(
            matches!(
                c.validate(),
                Err(SafetyError::InvalidConfig {
                    field: "period",
                    ..
                })
            ),
            "{period}"
        );
    }
    let c = SafetyConfig {
        max_age: 1001,
        ..ok
    };
    assert!(matches!(
        c.validate(),
        Err(SafetyError::InvalidConfig {
            field: "max_age",
            ..
        })
    ));
    let c = SafetyConfig {
        hold_periods: 100_001,
        ..ok
    };
    assert!(matches!(
        c.validate(),
        Err(SafetyError::InvalidConfig {
            field: "hold_periods",
            ..
        })
    ));
    let tiny = SafetyConfig {
        period: f64::MIN_POSITIVE,
        ..ok
    };
    assert_eq!(tiny.validate(), Ok(()));
}

#[test]
fn new_checks_everything() {
    let cfg = config(2, 3, FallbackPolicy::LocalController);
    let bad = SafetyConfig { period: 0.0, ..cfg };
    assert!(Supervisor::new(bad, &[channel()], vec![0.0]).is_err());
    assert_eq!(
        Supervisor::new(cfg, &[channel()], vec![0.0, 0.0]).unwrap_err(),
        SafetyError::ChannelMismatch {
            what: "initial_applied",
            expected: 1,
            got: 2
        }
    );
    assert_eq!(
        Supervisor::new(cfg, &[channel()], vec![f64::NAN]).unwrap_err(),
        SafetyError::NonFiniteApplied
    );
    let broken = ChannelConfig {
        law: LawConfig::intelligent(ControllerKind::P, Order::One, 0.0, [1.0, 0.0, 0.0], 3),
        ..channel()
    };
    let e = Supervisor::new(cfg, &[broken], vec![0.0]).unwrap_err();
    assert!(matches!(e, SafetyError::Controller(_)));
    assert!(std::error::Error::source(&e).is_some());
    assert!(e.to_string().starts_with("local controller: "));
    let s = Supervisor::new(cfg, &[channel(), channel()], vec![1.0, -2.0]).unwrap();
    assert_eq!(s.channels(), 2);
    assert_eq!(s.mode(), LoopMode::Remote);
    assert_eq!(s.applied_now(), &[1.0, -2.0]);
    assert_eq!(s.missing_streak(), 0);
    assert_eq!(s.last_applied_seq(), None);
    assert_eq!(s.counters().clone(), SupervisorCounters::default());
    assert_eq!(*s.config(), cfg);
}

#[test]
fn error_messages_are_not_empty() {
    let errors = [
        SafetyError::InvalidConfig {
            field: "period",
            reason: "must be finite and > 0 s",
        },
        SafetyError::ChannelMismatch {
            what: "y",
            expected: 2,
            got: 1,
        },
        SafetyError::NonFiniteApplied,
        SafetyError::PeriodOpen { open: 3 },
        SafetyError::PeriodNotIncreasing { previous: 3, k: 2 },
        SafetyError::NoOpenPeriod,
    ];
    for e in errors {
        assert!(!e.to_string().is_empty());
        assert!(std::error::Error::source(&e).is_none());
    }
}

#[test]
fn serde_and_cli_names() {
    use serde::de::value::{Error, StrDeserializer};
    use serde::de::IntoDeserializer;
    fn de<T: for<'de> Deserialize<'de>>(s: &str) -> Result<T, Error> {
        let d: StrDeserializer<'_, Error> = s.into_deserializer();
        T::deserialize(d)
    }
    assert_eq!(
        de::<FallbackPolicy>("local"),
        Ok(FallbackPolicy::LocalController)
    );
    assert_eq!(
        de::<FallbackPolicy>("safe_stop"),
        Ok(FallbackPolicy::SafeStop)
    );
    assert!(de::<FallbackPolicy>("local_controller").is_err());
    assert!(de::<FallbackPolicy>("LocalController").is_err());
    for (name, mode) in [
        ("remote", LoopMode::Remote),
        ("holding", LoopMode::Holding),
        ("local", LoopMode::Local),
        ("safe_stop", LoopMode::SafeStop),
    ] {
        assert_eq!(de::<LoopMode>(name), Ok(mode));
    }
    for p in [FallbackPolicy::LocalController, FallbackPolicy::SafeStop] {
        assert_eq!(p.to_string().parse::<FallbackPolicy>(), Ok(p));
        assert_eq!(de::<FallbackPolicy>(p.name()), Ok(p));
    }
    assert_eq!("safe-stop".parse(), Ok(FallbackPolicy::SafeStop));
    let e = "off".parse::<FallbackPolicy>().unwrap_err();
    assert!(e.to_string().contains("off"));
}

// ---- acceptance boundaries ----

#[test]
fn on_time_command_is_applied_at_its_arrival() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    begin(&mut s, 0);
    let (verdict, done) = s.on_command(0.2, ctl(0, &[4.0]));
    assert_eq!(
        verdict,
        Verdict::Apply {
            v: vec![4.0],
            advance: 0.2,
            late: false
        }
    );
    assert!(done);
    assert_eq!(s.mode(), LoopMode::Remote);
    assert_eq!(s.last_applied_seq(), Some(0));
    assert_eq!(s.applied_now(), &[4.0]);
    assert_eq!(s.counters().commands, 1);
    assert_eq!(s.counters().late, 0);
    let end = s.end_period().unwrap();
    assert_eq!(
        end,
        PeriodEnd {
            mode: LoopMode::Remote,
            advance: 0.3,
            missing: false
        }
    );
}

#[test]
fn oldest_acceptable_command_is_applied_late() {
    let max_age = 3;
    let mut s = sup(max_age, 100, FallbackPolicy::LocalController);
    for k in 0..10 {
        period(&mut s, k, None);
    }
    begin(&mut s, 10);
    let (verdict, done) = command(&mut s, 0.125, ctl(10 - u64::from(max_age), &[1.5]));
    assert_eq!(
        verdict,
        Verdict::Apply {
            v: vec![1.5],
            advance: 0.125,
            late: true
        }
    );
    assert!(!done, "the period's own command may still come");
    assert_eq!(s.counters().late, 1);
    assert_eq!(s.counters().commands, 1);
    assert_eq!(s.mode(), LoopMode::Remote);
    assert_eq!(s.missing_streak(), 0);
    // The period's own command still lands after it.
    let (verdict, done) = command(&mut s, 0.375, ctl(10, &[2.5]));
    assert_eq!(
        verdict,
        Verdict::Apply {
            v: vec![2.5],
            advance: 0.25,
            late: false
        }
    );
    assert!(done);
}

#[test]
fn one_period_older_than_max_age_is_too_old() {
    let max_age = 3;
    let mut s = sup(max_age, 100, FallbackPolicy::LocalController);
    for k in 0..10 {
        period(&mut s, k, None);
    }
    begin(&mut s, 10);
    let seq = 10 - u64::from(max_age) - 1;
    assert_eq!(ignored(&mut s, ctl(seq, &[1.0])), Ignored::TooOld);
    assert_eq!(ignored(&mut s, warm(seq)), Ignored::TooOld);
    assert_eq!(ignored(&mut s, rejected(0)), Ignored::TooOld);
    assert_eq!(s.counters().too_old, 3);
    assert_eq!(s.counters().warming_up + s.counters().rejected, 0);
}

#[test]
fn max_age_zero_accepts_only_the_own_sample() {
    let mut s = sup(0, 100, FallbackPolicy::LocalController);
    period(&mut s, 0, None);
    begin(&mut s, 1);
    assert_eq!(ignored(&mut s, ctl(0, &[1.0])), Ignored::TooOld);
    assert!(matches!(
        command(&mut s, 0.1, ctl(1, &[1.0])).0,
        Verdict::Apply { late: false, .. }
    ));
}

#[test]
fn future_commands_are_ignored() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    begin(&mut s, 4);
    assert_eq!(ignored(&mut s, ctl(5, &[1.0])), Ignored::Future);
    assert_eq!(ignored(&mut s, ctl(u64::MAX, &[1.0])), Ignored::Future);
    assert_eq!(ignored(&mut s, warm(u64::MAX)), Ignored::Future);
    assert_eq!(s.counters().future, 3);
    // u64::MAX as the current period is fine too: no overflow anywhere.
    s.end_period().unwrap();
    begin(&mut s, u64::MAX);
    let (verdict, done) = command(&mut s, 0.1, ctl(u64::MAX, &[1.0]));
    assert!(matches!(verdict, Verdict::Apply { late: false, .. }) && done);
    assert_eq!(ignored(&mut s, ctl(u64::MAX, &[1.0])), Ignored::Duplicate);
    assert_eq!(ignored(&mut s, ctl(0, &[1.0])), Ignored::Superseded);
    s.end_period().unwrap();
    assert!(matches!(
        s.begin_period(u64::MAX, 0.0, &[0.0], &refs(1)),
        Err(SafetyError::PeriodNotIncreasing { .. })
    ));
}

#[test]
fn duplicates_and_superseded() {
    let mut s = sup(5, 100, FallbackPolicy::LocalController);
    for k in 0..4 {
        period(&mut s, k, None);
    }
    begin(&mut s, 4);
    assert!(matches!(
        command(&mut s, 0.1, ctl(2, &[1.0])).0,
        Verdict::Apply { late: true, .. }
    ));
    // seq == last applied: a second controller answering the same sample.
    assert_eq!(ignored(&mut s, ctl(2, &[9.0])), Ignored::Duplicate);
    assert_eq!(ignored(&mut s, warm(2)), Ignored::Duplicate);
    assert_eq!(ignored(&mut s, rejected(2)), Ignored::Duplicate);
    // seq == last applied - 1: a newer command is already applied.
    assert_eq!(ignored(&mut s, ctl(1, &[9.0])), Ignored::Superseded);
    assert_eq!(ignored(&mut s, warm(1)), Ignored::Superseded);
    let c = s.counters().clone();
    assert_eq!((c.duplicates, c.superseded, c.commands), (3, 2, 1));
    // seq == last applied + 1 is newer: applied.
    assert!(matches!(
        command(&mut s, 0.2, ctl(3, &[2.0])).0,
        Verdict::Apply { late: true, .. }
    ));
    assert_eq!(s.applied_now(), &[2.0]);
}

#[test]
fn malformed_commands_change_nothing() {
    let mut s = sup_n(2, 2, 3, FallbackPolicy::LocalController);
    begin(&mut s, 0);
    for bad in [
        &[1.0][..],
        &[1.0, 2.0, 3.0],
        &[],
        &[f64::NAN, 1.0],
        &[1.0, f64::INFINITY],
        &[f64::NEG_INFINITY, 0.0],
    ] {
        assert_eq!(ignored(&mut s, ctl(0, bad)), Ignored::Malformed, "{bad:?}");
    }
    let unknown = IncomingCommand {
        seq: 0,
        body: CommandBody::Unknown,
        horizon: &[],
        lease: Credentials::default(),
    };
    assert_eq!(ignored(&mut s, unknown), Ignored::Malformed);
    assert_eq!(s.counters().malformed, 7);
    assert_eq!(s.last_applied_seq(), None);
    // Still waiting for a usable command: the period is missing.
    assert!(s.end_period().unwrap().missing);
}

#[test]
fn acceptance_rules_apply_in_order() {
    let mut s = sup(1, 100, FallbackPolicy::LocalController);
    for k in 0..5 {
        period(&mut s, k, Some(1.0));
    }
    begin(&mut s, 5);
    let bad = [f64::NAN];
    // Future before everything else.
    assert_eq!(ignored(&mut s, ctl(6, &bad)), Ignored::Future);
    // Duplicate before Malformed (last applied is 4).
    assert_eq!(ignored(&mut s, ctl(4, &bad)), Ignored::Duplicate);
    // Superseded before TooOld and Malformed.
    assert_eq!(ignored(&mut s, ctl(1, &bad)), Ignored::Superseded);
    // TooOld before Malformed: no command applied yet in a fresh supervisor.
    let mut fresh = sup(1, 100, FallbackPolicy::LocalController);
    for k in 0..5 {
        period(&mut fresh, k, None);
    }
    begin(&mut fresh, 5);
    assert_eq!(ignored(&mut fresh, ctl(3, &bad)), Ignored::TooOld);
    assert_eq!(ignored(&mut fresh, ctl(4, &bad)), Ignored::Malformed);
}

#[test]
fn calls_out_of_order_are_refused_and_change_nothing() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    assert_eq!(s.end_period(), Err(SafetyError::NoOpenPeriod));
    // A command outside a period cannot be applied.
    assert_eq!(
        s.on_command(0.0, ctl(0, &[1.0])),
        (Verdict::Ignored(Ignored::Future), false)
    );
    assert_eq!(s.counters().future, 1);
    period(&mut s, 0, Some(1.0));
    begin(&mut s, 1);
    let before = format!("{s:?}");
    assert_eq!(
        s.begin_period(2, 2.0 * H, &[0.0], &refs(1)),
        Err(SafetyError::PeriodOpen { open: 1 })
    );
    assert_eq!(before, format!("{s:?}"));
    s.end_period().unwrap();
    let before = format!("{s:?}");
    for k in [0, 1] {
        assert_eq!(
            s.begin_period(k, 0.0, &[0.0], &refs(1)),
            Err(SafetyError::PeriodNotIncreasing { previous: 1, k })
        );
    }
    assert_eq!(s.end_period(), Err(SafetyError::NoOpenPeriod));
    assert_eq!(before, format!("{s:?}"));
    // Gaps are allowed.
    begin(&mut s, 7);
    s.end_period().unwrap();
}

#[test]
fn wrong_length_inputs_are_refused_with_state_unchanged() {
    let mut s = sup_n(2, 2, 0, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(1.0));
    period(&mut s, 1, None);
    // The fallback is due now: a refused call must not engage it.
    let before = format!("{s:?}");
    assert_eq!(
        s.begin_period(2, 2.0 * H, &[0.0], &refs(2)),
        Err(SafetyError::ChannelMismatch {
            what: "y",
            expected: 2,
            got: 1
        })
    );
    assert_eq!(
        s.begin_period(2, 2.0 * H, &[0.0; 3], &refs(2)),
        Err(SafetyError::ChannelMismatch {
            what: "y",
            expected: 2,
            got: 3
        })
    );
    assert_eq!(
        s.begin_period(2, 2.0 * H, &[0.0; 2], &refs(1)),
        Err(SafetyError::ChannelMismatch {
            what: "refs",
            expected: 2,
            got: 1
        })
    );
    assert_eq!(before, format!("{s:?}"));
    let b = begin(&mut s, 2);
    assert!(b.write.is_some());
}

#[test]
fn bad_applied_reports_are_ignored() {
    let mut s = sup_n(2, 2, 3, FallbackPolicy::LocalController);
    begin(&mut s, 0);
    command(&mut s, 0.1, ctl(0, &[1.0, 2.0]));
    s.applied(&[1.0]);
    s.applied(&[1.0, 2.0, 3.0]);
    s.applied(&[f64::NAN, 0.0]);
    s.applied(&[0.0, f64::INFINITY]);
    assert_eq!(s.applied_now(), &[1.0, 2.0]);
    s.applied(&[0.5, 2.0]);
    assert_eq!(s.applied_now(), &[0.5, 2.0]);
}

// ---- state transitions ----

#[test]
fn remote_to_holding_and_back() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    let (_, end) = period(&mut s, 1, None);
    assert_eq!(
        end,
        PeriodEnd {
            mode: LoopMode::Holding,
            advance: H,
            missing: true
        }
    );
    assert_eq!(s.mode(), LoopMode::Holding);
    assert_eq!(s.missing_streak(), 1);
    assert_eq!(s.applied_now(), &[2.0], "the last command is held");
    let (b, end) = period(&mut s, 2, Some(3.0));
    assert_eq!(b.sample_mode, LoopMode::Holding);
    assert_eq!(b.write, None);
    assert_eq!(end.mode, LoopMode::Remote);
    assert_eq!(s.mode(), LoopMode::Remote);
    assert_eq!(s.missing_streak(), 0);
    let c = s.counters().clone();
    assert_eq!((c.missing, c.holding_periods, c.fallbacks), (1, 1, 0));
}

#[test]
fn holding_to_local() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    for k in 1..=3 {
        let (b, end) = period(&mut s, k, None);
        assert_eq!(b.write, None);
        assert_eq!(end.mode, LoopMode::Holding, "period {k}");
    }
    let (b, end) = period(&mut s, 4, None);
    assert_eq!(b.sample_mode, LoopMode::Holding);
    let v = b.write.expect("the fallback engages");
    assert_eq!(v, vec![s.local_out[0].v]);
    assert_eq!(s.applied_now(), &v[..]);
    assert_eq!(end.mode, LoopMode::Local);
    assert_eq!(s.mode(), LoopMode::Local);
    let c = s.counters().clone();
    assert_eq!(
        (c.holding_periods, c.local_periods, c.fallbacks, c.missing),
        (3, 1, 1, 4)
    );
}

#[test]
fn remote_to_local_without_holding_when_hold_is_zero_or_one() {
    for hold in [0, 1] {
        let mut s = sup(2, hold, FallbackPolicy::LocalController);
        period(&mut s, 0, Some(2.0));
        let (b, end) = period(&mut s, 1, None);
        assert_eq!(
            b.write, None,
            "hold {hold}: period 1 cannot be known missing"
        );
        assert_eq!(end.mode, LoopMode::Remote, "hold {hold}");
        assert!(end.missing);
        assert_eq!(s.mode(), LoopMode::Remote);
        let (b, end) = period(&mut s, 2, None);
        assert_eq!(b.sample_mode, LoopMode::Remote);
        assert!(b.write.is_some(), "hold {hold}");
        assert_eq!(end.mode, LoopMode::Local);
        assert_eq!(s.counters().holding_periods, 0);
        assert_eq!(s.counters().fallbacks, 1);
    }
}

#[test]
fn fallback_engages_exactly_after_hold_periods() {
    for hold in [0u32, 1, 2, 5] {
        let mut s = sup(2, hold, FallbackPolicy::LocalController);
        let last_command = 3;
        for k in 0..=last_command {
            period(&mut s, k, Some(1.0));
        }
        let mut engaged = None;
        for p in last_command + 1..last_command + 20 {
            let (b, _) = period(&mut s, p, None);
            if b.write.is_some() {
                engaged = Some(p);
                break;
            }
        }
        // A period is known missing only once it has ended, so hold 0 behaves as 1.
        let p = engaged.unwrap();
        assert_eq!(p - last_command - 1, u64::from(hold.max(1)), "hold {hold}");
        // The Holding mode only shows when there is something to hold before falling back
        // (hold >= 2): with hold 0 or 1 the one missing period stays Remote.
        let holding = if hold >= 2 { u64::from(hold) } else { 0 };
        assert_eq!(s.counters().holding_periods, holding, "hold {hold}");
    }
}

#[test]
fn local_to_remote() {
    let mut s = sup(2, 1, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    period(&mut s, 1, None);
    let (b, end) = period(&mut s, 2, None);
    assert!(b.write.is_some());
    assert_eq!(end.mode, LoopMode::Local);
    // Commands are back: the fallback wrote at the start, the command replaces it.
    let b = begin(&mut s, 3);
    assert_eq!(b.sample_mode, LoopMode::Local);
    assert!(b.write.is_some(), "still Local at the start of the period");
    let (verdict, done) = command(&mut s, 0.25, ctl(3, &[7.0]));
    assert!(matches!(verdict, Verdict::Apply { late: false, .. }) && done);
    assert_eq!(s.mode(), LoopMode::Remote);
    let end = s.end_period().unwrap();
    assert_eq!(end.mode, LoopMode::Remote);
    assert_eq!(s.missing_streak(), 0);
    let (b, end) = period(&mut s, 4, Some(7.5));
    assert_eq!(b.sample_mode, LoopMode::Remote);
    assert_eq!(b.write, None);
    assert_eq!(end.mode, LoopMode::Remote);
    let c = s.counters().clone();
    assert_eq!((c.local_periods, c.fallbacks), (1, 1));
}

#[test]
fn safe_stop_policy_writes_zeros_and_resumes() {
    let mut s = sup_n(2, 2, 2, FallbackPolicy::SafeStop);
    period(&mut s, 0, Some(5.0));
    period(&mut s, 1, None);
    period(&mut s, 2, None);
    let (b, end) = period(&mut s, 3, None);
    assert_eq!(b.write, Some(vec![0.0, 0.0]));
    assert_eq!(end.mode, LoopMode::SafeStop);
    assert_eq!(s.mode(), LoopMode::SafeStop);
    assert_eq!(s.applied_now(), &[0.0, 0.0]);
    let (b, end) = period(&mut s, 4, None);
    assert_eq!(b.write, Some(vec![0.0, 0.0]), "zeros every period");
    assert_eq!(end.mode, LoopMode::SafeStop);
    // SafeStop -> Remote.
    let (b, end) = period(&mut s, 5, Some(1.0));
    assert_eq!(b.sample_mode, LoopMode::SafeStop);
    assert_eq!(end.mode, LoopMode::Remote);
    assert_eq!(s.mode(), LoopMode::Remote);
    let c = s.counters().clone();
    assert_eq!((c.safe_stop_periods, c.fallbacks), (2, 1));
}

#[test]
fn failing_local_step_means_safe_stop_even_under_local_policy() {
    let mut s = sup(2, 1, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    period(&mut s, 1, None);
    // The fallback is due, but the local controller cannot run on a NaN output.
    let b = s.begin_period(2, 2.0 * H, &[f64::NAN], &refs(1)).unwrap();
    assert_eq!(b.write, Some(vec![0.0]));
    s.applied(&[0.0]);
    assert_eq!(s.mode(), LoopMode::SafeStop);
    assert_eq!(s.end_period().unwrap().mode, LoopMode::SafeStop);
    // It recovers: Local, without a second fallback entry.
    let (b, end) = period(&mut s, 3, None);
    assert_eq!(b.sample_mode, LoopMode::SafeStop);
    assert_eq!(b.write, Some(vec![s.local_out[0].v]));
    assert_eq!(end.mode, LoopMode::Local);
    // And fails again while Local: SafeStop, still one entry.
    s.begin_period(4, 4.0 * H, &[f64::INFINITY], &refs(1))
        .unwrap();
    assert_eq!(s.mode(), LoopMode::SafeStop);
    assert_eq!(s.end_period().unwrap().mode, LoopMode::SafeStop);
    let c = s.counters().clone();
    assert_eq!(
        (c.fallbacks, c.safe_stop_periods, c.local_periods),
        (1, 2, 1)
    );
    // A bad reference or a bad time fails the same way.
    let b = s
        .begin_period(5, 5.0 * H, &[0.0], &[Reference::constant(f64::NAN)])
        .unwrap();
    assert_eq!(b.write, Some(vec![0.0]));
    s.end_period().unwrap();
    let b = s.begin_period(6, f64::NAN, &[0.0], &refs(1)).unwrap();
    assert_eq!(b.write, Some(vec![0.0]));
    s.end_period().unwrap();
}

#[test]
fn nan_output_without_fallback_due_changes_nothing() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    let b = s.begin_period(1, H, &[f64::NAN], &refs(1)).unwrap();
    assert_eq!(b.write, None);
    assert_eq!(s.mode(), LoopMode::Remote);
    command(&mut s, 0.1, ctl(1, &[3.0]));
    assert_eq!(s.end_period().unwrap().mode, LoopMode::Remote);
}

#[test]
fn warming_up_at_start_keeps_holding_without_counting_missing() {
    let mut s = sup(2, 2, FallbackPolicy::LocalController);
    for k in 0..10 {
        let b = begin(&mut s, k);
        assert_eq!(b.sample_mode, LoopMode::Remote);
        assert_eq!(b.write, None);
        let (verdict, done) = command(&mut s, 0.1, warm(k));
        assert_eq!((verdict, done), (Verdict::WarmingUp, true));
        let end = s.end_period().unwrap();
        assert_eq!(
            end,
            PeriodEnd {
                mode: LoopMode::Remote,
                advance: H,
                missing: false
            }
        );
    }
    assert_eq!(s.applied_now(), &[0.0], "the initial value is held");
    let c = s.counters().clone();
    assert_eq!((c.missing, c.warming_up, c.fallbacks), (0, 10, 0));
    assert_eq!(s.missing_streak(), 0);
    // A late warming-up answer counts too, but does not end the wait.
    begin(&mut s, 10);
    assert_eq!(s.on_command(0.1, warm(9)), (Verdict::WarmingUp, false));
    assert!(!s.end_period().unwrap().missing);
}

/// After a command was applied, a controller that answers "warming up" (it restarted,
/// or took the lease with a cold state) does not hold the plant on a stale command
/// past the watchdog: the periods count towards the fallback (not as missing).
#[test]
fn warming_up_after_commands_does_not_stop_the_watchdog() {
    let mut s = sup(2, 3, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    period(&mut s, 1, None);
    period(&mut s, 2, None);
    assert_eq!(s.missing_streak(), 2);
    begin(&mut s, 3);
    command(&mut s, 0.1, warm(3));
    let end = s.end_period().unwrap();
    assert!(!end.missing);
    assert_eq!(end.mode, LoopMode::Holding);
    assert_eq!(s.missing_streak(), 3);
    assert_eq!(s.counters().missing, 2);
    assert_eq!(s.applied_now(), &[2.0]);
    // The fallback engages at the next period, warming-up answers or not.
    assert!(period(&mut s, 4, None).0.write.is_some());
    assert_eq!(s.mode(), LoopMode::Local);
}

/// Credentials of controller `from` (process 0) for run 9.
fn creds(from: &str, epoch: u64, claim: bool) -> Credentials<'_> {
    Credentials {
        from,
        instance: 0,
        epoch,
        claim,
        release: false,
        run_id: 9,
    }
}

/// Periods `ks`, each answered within it by holder `from` under epoch 1.
fn answered_in_time(s: &mut Supervisor, from: &str, ks: std::ops::Range<u64>) {
    for k in ks {
        begin(s, k);
        command(s, 0.1, leased(k, &[1.0], from, 1, false));
        s.end_period().unwrap();
    }
}

fn leased<'a>(
    seq: u64,
    v: &'a [f64],
    from: &'a str,
    epoch: u64,
    claim: bool,
) -> IncomingCommand<'a> {
    IncomingCommand {
        lease: creds(from, epoch, claim),
        ..ctl(seq, v)
    }
}

/// With leases, only the holder's commands pass; a refused one changes nothing but
/// the count; a claim that the other rules drop grants nothing; the lease lapses
/// after half the hold, and the next claim gets a new epoch.
#[test]
fn the_lease_decides_who_commands_and_lapses_with_the_fallback() {
    let mut s = sup(3, 2, FallbackPolicy::LocalController);
    s.grant_leases(9);
    begin(&mut s, 0);
    // A claim of a future sample is dropped and grants nothing.
    assert_eq!(
        ignored(&mut s, leased(1, &[1.0], "b", 1, true)),
        Ignored::Future
    );
    assert_eq!(s.lease().unwrap().holder(), None);
    let (v, _) = command(&mut s, 0.1, leased(0, &[1.0], "a", 1, true));
    assert!(matches!(v, Verdict::Apply { .. }));
    assert_eq!(s.lease().unwrap().holder(), Some("a"));
    // The loser's claim and a forged holder's epoch are fenced, counted once each.
    let fenced = |f| Ignored::Fenced(f);
    assert_eq!(
        ignored(&mut s, leased(0, &[9.0], "b", 1, true)),
        fenced(Fence::BadClaim)
    );
    assert_eq!(
        ignored(&mut s, leased(0, &[9.0], "a", 2, false)),
        fenced(Fence::StaleEpoch)
    );
    s.end_period().unwrap();
    begin(&mut s, 1);
    let (v, _) = command(&mut s, 0.1, leased(1, &[2.0], "a", 1, false));
    assert!(matches!(v, Verdict::Apply { .. }));
    s.end_period().unwrap();
    // Silence: the lease lapses after half the hold (one period), while the plant
    // still holds; the fallback engages after the whole hold.
    period(&mut s, 2, None);
    assert_eq!(s.lease().unwrap().holder(), Some("a"));
    assert_eq!(begin(&mut s, 3).write, None);
    assert_eq!(s.lease().unwrap().holder(), None);
    s.end_period().unwrap();
    assert!(begin(&mut s, 4).write.is_some());
    // The old holder's command is refused now; its claim of the next epoch passes.
    assert_eq!(
        ignored(&mut s, leased(4, &[3.0], "a", 1, false)),
        fenced(Fence::Vacant)
    );
    let (v, _) = command(&mut s, 0.1, leased(4, &[3.0], "b", 2, true));
    assert!(matches!(v, Verdict::Apply { .. }));
    assert_eq!(s.mode(), LoopMode::Remote);
    let l = s.lease().unwrap();
    assert_eq!(
        (l.holder(), l.epoch(), l.counters().lapses),
        (Some("b"), 2, 1)
    );
    let c = s.counters();
    assert_eq!((c.fenced, c.commands, c.future), (3, 3, 1));
    assert_eq!(total(c), 7);
    let spans: Vec<_> = l
        .report()
        .spans
        .iter()
        .map(|x| (x.holder.clone(), x.epoch, x.first, x.last))
        .collect();
    assert_eq!(
        spans,
        [("a".to_string(), 1, 0, 1), ("b".to_string(), 2, 4, 4)]
    );
}

/// A holder whose answers the network reorders keeps its lease: an answer overtaken by a
/// newer one of its own, or repeated, to a sample of the last lapse's worth of periods,
/// is not silence (seed 21257 of the fleet's simulation: a round trip of three periods
/// with jitter let a live holder's lease lapse on answers that all came in the wrong
/// order). An older one is, and no answer of another controller counts for the holder.
#[test]
fn answers_overtaken_by_the_holders_newer_ones_renew_its_lease() {
    let mut s = sup(8, 6, FallbackPolicy::LocalController);
    s.grant_leases(9);
    assert_eq!(s.lease_lapse(), 3);
    begin(&mut s, 0);
    let (v, _) = command(&mut s, 0.1, leased(0, &[1.0], "a", 1, true));
    assert!(matches!(v, Verdict::Apply { .. }));
    s.end_period().unwrap();
    for k in [1, 2] {
        begin(&mut s, k);
        let (v, _) = command(&mut s, 0.1, leased(k, &[1.0], "a", 1, false));
        assert!(matches!(v, Verdict::Apply { .. }));
        s.end_period().unwrap();
    }
    // Periods 3 and 4 hear only answers overtaken (seq 1) or repeated (seq 2), two
    // periods old; period 5 a repeat three periods old (not recent: no renewal) and a
    // fenced answer of another controller.
    let late = [
        (3, 1, Ignored::Superseded),
        (4, 2, Ignored::Duplicate),
        (5, 2, Ignored::Duplicate),
    ];
    for (k, seq, why) in late {
        begin(&mut s, k);
        assert_eq!(ignored(&mut s, leased(seq, &[9.0], "a", 1, false)), why);
        s.end_period().unwrap();
    }
    begin(&mut s, 5 + 1);
    assert_eq!(
        ignored(&mut s, leased(6, &[9.0], "b", 1, false)),
        Ignored::Fenced(Fence::NotHolder)
    );
    s.end_period().unwrap();
    assert_eq!(s.lease().unwrap().idle(), 2, "periods 5 and 6 were silent");
    assert_eq!(s.lease().unwrap().holder(), Some("a"));
    begin(&mut s, 7);
    s.end_period().unwrap();
    // Three silent periods (5, 6, 7): the lease lapses, the fallback has not engaged.
    let b = begin(&mut s, 8);
    assert_eq!(s.lease().unwrap().holder(), None);
    assert_eq!(b.write, None);
    assert_eq!(s.counters().superseded + s.counters().duplicates, 3);
}

/// A holder whose answers come three periods after their samples (a round trip of 30 ms
/// or more at 100 Hz) keeps its lease through three silent periods in a row: the lapse
/// waits one period more than its answers' lateness (the fleet's simulation, seed 31675:
/// it lapsed, and the plant fell back while the holder claimed again). Still before
/// the fallback, and back to half the hold once its answers are prompt for a while.
#[test]
fn a_holder_answering_late_keeps_its_lease_through_one_late_run_of_answers() {
    let mut s = sup(8, 5, FallbackPolicy::LocalController);
    s.grant_leases(9);
    assert_eq!(s.lease_lapse(), 3, "half the hold, rounded up");
    for k in 0..3 {
        begin(&mut s, k);
        s.end_period().unwrap();
    }
    for k in 3..20 {
        begin(&mut s, k);
        let (v, _) = command(&mut s, 0.1, leased(k - 3, &[1.0], "a", 1, k == 3));
        assert!(matches!(v, Verdict::Apply { late: true, .. }), "{k}: {v:?}");
        s.end_period().unwrap();
    }
    assert_eq!(s.lease_lapse(), 4, "three periods late, one more");
    // Silent for periods 20, 21 and 22: still its lease.
    for k in 20..23 {
        begin(&mut s, k);
        s.end_period().unwrap();
    }
    let b = begin(&mut s, 23);
    assert_eq!(s.lease().unwrap().holder(), Some("a"));
    assert_eq!(b.write, None);
    let (v, _) = command(&mut s, 0.1, leased(20, &[1.0], "a", 1, false));
    assert!(matches!(v, Verdict::Apply { .. }), "{v:?}");
    s.end_period().unwrap();
    // Prompt from now on: within about a hundred commands per period of lateness, the
    // lapse is half the hold again.
    answered_in_time(&mut s, "a", 24..400);
    assert_eq!(s.lease_lapse(), 3);
    // Four silent periods at most: the lease lapses before the fallback engages.
    for k in 400..404 {
        period(&mut s, k, None);
    }
    let b = begin(&mut s, 404);
    assert_eq!(s.lease().unwrap().holder(), None);
    assert_eq!(b.write, None, "a lapse, not the fallback");
}

/// A holder's answers, prompt until then, land two periods late three times in a row
/// (links of 2-15 ms each way: the fleet's simulation, seeds 540749 and 553219): the lease
/// lapses before the first of them arrives, and that answer, to a sample of the holder's
/// own tenure, gives it back while nobody has claimed. The plant never leaves remote
/// control; without it, it held, fell back for a period, and the holder claimed again.
#[test]
fn a_lapse_that_came_too_early_is_undone_by_the_holders_late_answer() {
    let mut s = sup(8, 5, FallbackPolicy::LocalController);
    s.grant_leases(9);
    begin(&mut s, 0);
    command(&mut s, 0.1, leased(0, &[1.0], "a", 1, true));
    s.end_period().unwrap();
    answered_in_time(&mut s, "a", 1..200);
    assert_eq!(s.lease_lapse(), 3);
    // Samples 200, 201 and 202 go unanswered in their periods: a lapse at 203.
    for k in 200..203 {
        period(&mut s, k, None);
    }
    begin(&mut s, 203);
    assert_eq!(s.lease().unwrap().holder(), None);
    let (v, _) = command(&mut s, 0.5, leased(201, &[1.0], "a", 1, false));
    assert!(matches!(v, Verdict::Apply { late: true, .. }), "{v:?}");
    let l = s.lease().unwrap();
    assert_eq!(
        (l.holder(), l.epoch(), l.counters().resumed),
        (Some("a"), 1, 1)
    );
    s.end_period().unwrap();
    // A claim made on the vacant sample 203 finds the lease held again.
    begin(&mut s, 204);
    assert_eq!(
        ignored(&mut s, leased(203, &[2.0], "b", 2, true)),
        Ignored::Fenced(Fence::BadClaim)
    );
    command(&mut s, 0.1, leased(204, &[1.0], "a", 1, false));
    s.end_period().unwrap();
    assert_eq!(s.counters().fallbacks, 0);
    // Its answer to the vacant sample 203 is no answer of its tenure: refused, as before.
    s.grant_leases(9);
    begin(&mut s, 205);
    command(&mut s, 0.1, leased(205, &[1.0], "a", 1, true));
    s.end_period().unwrap();
    for k in 206..209 {
        period(&mut s, k, None);
    }
    begin(&mut s, 209);
    assert_eq!(s.lease().unwrap().holder(), None);
    assert_eq!(
        ignored(&mut s, leased(209, &[1.0], "a", 1, false)),
        Ignored::Fenced(Fence::Vacant)
    );
}

/// A holder that answers "warming up" (it took the lease cold) keeps it while the
/// fallback runs: no lapse and new epoch every period until it is warm.
#[test]
fn a_warming_holder_keeps_the_lease_through_the_fallback() {
    let mut s = sup(3, 2, FallbackPolicy::LocalController);
    s.grant_leases(9);
    period(&mut s, 0, None);
    period(&mut s, 1, None);
    assert!(begin(&mut s, 2).write.is_some(), "the fallback runs");
    let holder = creds("a", 1, true);
    for k in 2..8 {
        if k > 2 {
            begin(&mut s, k);
        }
        let w = IncomingCommand {
            lease: holder,
            ..warm(k)
        };
        assert_eq!(s.on_command(0.1, w).0, Verdict::WarmingUp);
        s.end_period().unwrap();
        assert_eq!(s.mode(), LoopMode::Local);
    }
    let l = s.lease().unwrap();
    assert_eq!(
        (l.holder(), l.epoch(), l.counters().lapses),
        (Some("a"), 1, 0)
    );
    // Silent now: it lapses after half the hold (one period).
    period(&mut s, 8, None);
    begin(&mut s, 9);
    assert_eq!(s.lease().unwrap().holder(), None);
}

/// A refusal from a claimant is no answer that keeps the plant safe: it claims nothing.
#[test]
fn a_rejected_claim_grants_nothing() {
    let mut s = sup(3, 2, FallbackPolicy::LocalController);
    s.grant_leases(9);
    begin(&mut s, 0);
    let mut r = rejected(0);
    r.lease = creds("a", 1, true);
    assert_eq!(s.on_command(0.1, r).0, Verdict::Rejected);
    assert_eq!(s.lease().unwrap().holder(), None);
    let mut w = warm(0);
    w.lease = r.lease;
    assert_eq!(s.on_command(0.1, w).0, Verdict::WarmingUp);
    assert_eq!(s.lease().unwrap().holder(), Some("a"));
}

#[test]
fn warming_up_during_local_keeps_local() {
    let mut s = sup(2, 1, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    period(&mut s, 1, None);
    period(&mut s, 2, None);
    assert_eq!(s.mode(), LoopMode::Local);
    for k in 3..6 {
        let b = begin(&mut s, k);
        assert_eq!(b.sample_mode, LoopMode::Local);
        assert!(b.write.is_some(), "the local controller keeps running");
        assert_eq!(command(&mut s, 0.1, warm(k)), (Verdict::WarmingUp, true));
        let end = s.end_period().unwrap();
        assert_eq!(end.mode, LoopMode::Local);
        assert!(!end.missing);
        assert_eq!(s.mode(), LoopMode::Local);
        // Not missing, but no command either: the watchdog's count goes on.
        assert_eq!(s.missing_streak(), k as u32);
    }
    let c = s.counters().clone();
    assert_eq!((c.local_periods, c.fallbacks, c.missing), (4, 1, 2));
}

#[test]
fn rejected_is_counted_and_changes_nothing_else() {
    let mut s = sup(2, 2, FallbackPolicy::LocalController);
    period(&mut s, 0, Some(2.0));
    period(&mut s, 1, None);
    begin(&mut s, 2);
    assert_eq!(s.on_command(0.1, rejected(1)), (Verdict::Rejected, false));
    assert_eq!(s.on_command(0.1, rejected(2)), (Verdict::Rejected, true));
    assert_eq!(s.missing_streak(), 1, "a refusal is not an answer");
    assert_eq!(s.applied_now(), &[2.0]);
    let end = s.end_period().unwrap();
    assert!(end.missing);
    assert_eq!(end.mode, LoopMode::Holding);
    assert_eq!(s.counters().rejected, 2);
    assert_eq!(s.last_applied_seq(), Some(0));
    assert!(period(&mut s, 3, None).0.write.is_some());
}

#[test]
fn fallbacks_count_entries_not_periods() {
    let mut s = sup(2, 1, FallbackPolicy::LocalController);
    let mut k = 0;
    let mut run = |s: &mut Supervisor, v: Option<f64>| {
        let r = period(s, k, v);
        k += 1;
        r
    };
    for _ in 0..3 {
        run(&mut s, Some(1.0));
        for _ in 0..6 {
            run(&mut s, None);
        }
    }
    let c = s.counters().clone();
    assert_eq!(c.fallbacks, 3);
    assert_eq!(c.local_periods, 15);
    assert_eq!(c.missing, 18);
}

// ---- time accounting ----

#[test]
fn time_weighted_mean_of_a_command_landing_mid_period() {
    let h = 1.0;
    let cfg = SafetyConfig {
        period: h,
        ..config(2, 5, FallbackPolicy::LocalController)
    };
    let mut s = Supervisor::new(cfg, &[channel()], vec![0.0]).unwrap();
    s.begin_period(0, 0.0, &[0.0], &refs(1)).unwrap();
    command(&mut s, 0.0, ctl(0, &[2.0]));
    s.end_period().unwrap();
    // Holding 2 V, a new value of 5 V lands at 0.3 h.
    let b = s.begin_period(1, h, &[0.0], &refs(1)).unwrap();
    assert_eq!(b.applied_mean, vec![2.0]);
    let (verdict, _) = command(&mut s, 0.3 * h, ctl(1, &[5.0]));
    assert!(matches!(verdict, Verdict::Apply { advance, .. } if advance == 0.3 * h));
    let end = s.end_period().unwrap();
    assert!((end.advance - 0.7 * h).abs() < 1e-15);
    let b = s.begin_period(2, 2.0 * h, &[0.0], &refs(1)).unwrap();
    let expected = 0.3 * 2.0 + 0.7 * 5.0;
    assert!((b.applied_mean[0] - expected).abs() < 1e-12, "{b:?}");
}

#[test]
fn first_sample_carries_the_initial_applied() {
    let cfg = config(2, 5, FallbackPolicy::LocalController);
    let mut s = Supervisor::new(cfg, &[channel(), channel()], vec![0.25, -0.5]).unwrap();
    let b = s.begin_period(0, 0.0, &[0.0, 0.0], &refs(2)).unwrap();
    assert_eq!(b.applied_mean, vec![0.25, -0.5]);
    s.end_period().unwrap();
    let b = s.begin_period(1, H, &[0.0, 0.0], &refs(2)).unwrap();
    assert_eq!(b.applied_mean, vec![0.25, -0.5]);
}

#[test]
fn fallback_write_at_start_then_command_at_half() {
    let mut s = sup(2, 1, FallbackPolicy::SafeStop);
    period(&mut s, 0, Some(4.0));
    period(&mut s, 1, None);
    // Period 2: the fallback writes zeros at offset 0, replacing 4 V for the whole period.
    let b = begin(&mut s, 2);
    assert_eq!(b.applied_mean, vec![4.0]);
    assert_eq!(b.write, Some(vec![0.0]));
    let (verdict, done) = command(&mut s, 0.5 * H, ctl(2, &[6.0]));
    assert_eq!(
        verdict,
        Verdict::Apply {
            v: vec![6.0],
            advance: 0.5 * H,
            late: false
        }
    );
    assert!(done);
    let end = s.end_period().unwrap();
    assert_eq!(end.advance, 0.5 * H);
    assert_eq!(end.mode, LoopMode::Remote);
    let b = begin(&mut s, 3);
    assert_eq!(b.applied_mean, vec![0.5 * 0.0 + 0.5 * 6.0]);
}

#[test]
fn plant_reports_replace_the_written_value() {
    let mut s = sup(2, 5, FallbackPolicy::LocalController);
    begin(&mut s, 0);
    // The plant saturates: 30 V written, 24 V applied from 0.25 s on.
    s.on_command(0.25, ctl(0, &[30.0]));
    s.applied(&[24.0]);
    s.end_period().unwrap();
    let b = begin(&mut s, 1);
    assert_eq!(b.applied_mean, vec![(0.25 * 0.0 + 0.25 * 24.0) / H]);
}

#[test]
fn advances_sum_to_the_period() {
    let mut s = sup(3, 100, FallbackPolicy::LocalController);
    for k in 0..3 {
        period(&mut s, k, None);
    }
    begin(&mut s, 3);
    let mut sum = 0.0;
    let arrivals = [
        (-0.25, 0u64, 0.0), // before the deadline: counts as 0
        (0.125, 1, 0.125),  // on time
        (0.0625, 2, 0.0),   // arrived "before" the last one: clamped to it
        (f64::NAN, 3, 0.0), // unknown time: now
    ];
    for (at, seq, advance) in arrivals {
        match command(&mut s, at, ctl(seq, &[seq as f64])).0 {
            Verdict::Apply { advance: a, .. } => {
                assert_eq!(a, advance, "seq {seq}");
                sum += a;
            }
            other => panic!("{other:?}"),
        }
    }
    let end = s.end_period().unwrap();
    assert_eq!(sum + end.advance, H);
    // A command past the end of the period is clamped to it.
    begin(&mut s, 4);
    let Verdict::Apply { advance, .. } = command(&mut s, 9.0, ctl(4, &[1.0])).0 else {
        panic!()
    };
    assert_eq!(advance, H);
    assert_eq!(s.end_period().unwrap().advance, 0.0);
    begin(&mut s, 5);
    let Verdict::Apply { advance, .. } = command(&mut s, f64::INFINITY, ctl(5, &[1.0])).0 else {
        panic!()
    };
    assert_eq!(advance, H);
    assert_eq!(s.end_period().unwrap().advance, 0.0);
    begin(&mut s, 6);
    let Verdict::Apply { advance, .. } = command(&mut s, f64::NEG_INFINITY, ctl(6, &[1.0])).0
    else {
        panic!()
    };
    assert_eq!(advance, 0.0);
    assert_eq!(s.end_period().unwrap().advance, H);
    // Without any command the whole period is left to integrate.
    assert_eq!(period(&mut s, 7, None).1.advance, H);
}

#[test]
fn the_local_controller_is_fed_what_was_really_applied() {
    let n = 2;
    let cfg = config(2, 2, FallbackPolicy::LocalController);
    let channels = vec![channel(); n];
    let mut s = Supervisor::new(cfg, &channels, vec![0.0; n]).unwrap();
    let mut reference: MimoController = MimoController::new(&channels).unwrap();
    let mut out = vec![ChannelOutput::default(); n];
    // A plant that saturates at ±3 and whose output follows the inputs.
    let plant = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| x.clamp(-3.0, 3.0)).collect() };
    let mut y = vec![0.0; n];
    let mut applied = vec![0.0; n];
    let mut mean = vec![0.0; n];
    let mut seen_fallback = false;
    for k in 0..40u64 {
        let t = k as f64 * H;
        let r = vec![Reference::constant(1.0), Reference::constant(-0.5)];
        let b = s.begin_period(k, t, &y, &r).unwrap();
        assert_eq!(b.applied_mean, mean, "period {k}");
        if k > 0 {
            reference.report_applied(&mean).unwrap();
        }
        reference.step(t, &y, &r, &mut out).unwrap();
        let mut acc = vec![0.0; n];
        let mut seg = 0.0;
        if let Some(v) = b.write {
            seen_fallback = true;
            assert_eq!(v, out.iter().map(|o| o.v).collect::<Vec<_>>());
            applied = plant(&v);
            s.applied(&applied);
        }
        // Commands for periods 10..20 never come; the others land at 0.2 s with 5 V on
        // channel 0 (saturated by the plant).
        if !(10..20).contains(&k) {
            let cmd = [5.0, -0.25 * (k % 4) as f64];
            if let Verdict::Apply { v, advance, .. } = s.on_command(0.2, ctl(k, &cmd)).0 {
                for (a, x) in acc.iter_mut().zip(&applied) {
                    *a += x * advance;
                }
                seg = 0.2;
                applied = plant(&v);
                s.applied(&applied);
            }
        }
        let end = s.end_period().unwrap();
        assert_eq!(s.applied_now(), &applied[..]);
        for (((m, a), x), y) in mean.iter_mut().zip(&acc).zip(&applied).zip(&mut y) {
            *m = (a + x * (H - seg)) / H;
            *y += 0.1 * x * H;
        }
        assert_eq!(end.advance, H - seg);
        // Same sequence in, same controller state out.
        assert_eq!(format!("{:?}", s.local), format!("{reference:?}"));
    }
    assert!(seen_fallback);
    assert_eq!(s.counters().fallbacks, 1);
}

// ---- randomised invariants ----

/// A tiny linear congruential generator (Knuth's MMIX constants).
struct Lcg(u64);

impl Lcg {
    fn next(&mut self) -> u64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        self.0 >> 33
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }

    fn unit(&mut self) -> f64 {
        self.next() as f64 / (1u64 << 31) as f64
    }
}

/// One randomised run of a supervisor, with what the test tracks of it to check the
/// invariants after every call.
struct Trial {
    s: Supervisor,
    rng: Lcg,
    n: usize,
    max_age: u32,
    /// Everything that may legitimately be applied: the initial value, fallback
    /// outputs and accepted commands.
    legit: Vec<Vec<f64>>,
    delivered: u64,
    remote_periods: u64,
    fallbacks: u64,
    missing: u64,
}

/// What one period's commands did: the plant time they let pass, whether the
/// period's own command (or a warm-up answer) came, and every value applied in it.
struct Commands {
    advance: f64,
    answered: bool,
    values: Vec<Vec<f64>>,
}

impl Trial {
    fn new(seed: u64) -> Self {
        let mut rng = Lcg(seed);
        let n = 1 + rng.below(2) as usize;
        let policy = if rng.below(2) == 0 {
            FallbackPolicy::LocalController
        } else {
            FallbackPolicy::SafeStop
        };
        let max_age = rng.below(4) as u32;
        let hold = rng.below(4) as u32;
        let cfg = SafetyConfig {
            period: H,
            max_age,
            hold_periods: hold,
            fallback: policy,
        };
        Self {
            s: Supervisor::new(cfg, &vec![channel(); n], vec![0.0; n]).unwrap(),
            rng,
            n,
            max_age,
            legit: vec![vec![0.0; n]],
            delivered: 0,
            remote_periods: 0,
            fallbacks: 0,
            missing: 0,
        }
    }

    /// Begin period `k` on random outputs (sometimes a NaN), checking the sample's
    /// mode and mean and any fallback write; sometimes a wiring bug follows, which
    /// must change nothing.
    fn begin(&mut self, k: u64) {
        let (s, n) = (&mut self.s, self.n);
        let mut y = vec![self.rng.unit() - 0.5; n];
        if self.rng.below(25) == 0 {
            y[0] = f64::NAN;
        }
        let mode_before = s.mode();
        let b = s.begin_period(k, k as f64 * H, &y, &refs(n)).unwrap();
        assert_eq!(b.sample_mode, mode_before);
        assert!(b.applied_mean.iter().all(|m| m.is_finite()));
        if mode_before.is_fallback() {
            assert!(b.write.is_some());
        }
        if b.write.is_some() {
            assert!(s.mode().is_fallback());
            if !mode_before.is_fallback() {
                self.fallbacks += 1;
            }
        } else {
            assert_eq!(s.mode(), mode_before);
        }
        if let Some(v) = b.write {
            if s.mode() == LoopMode::SafeStop {
                assert!(v.iter().all(|x| *x == 0.0));
            }
            s.applied(&v);
            self.legit.push(v);
        }
        // A wiring bug in the middle must not corrupt anything.
        if self.rng.below(10) == 0 {
            let before = format!("{s:?}");
            assert!(s.begin_period(k + 1, 0.0, &y, &refs(n)).is_err());
            assert!(s.begin_period(k + 1, 0.0, &y[1..], &refs(n)).is_err());
            assert_eq!(before, format!("{s:?}"));
        }
    }

    /// Up to four random commands in period `k` (any seq, malformed inputs, odd
    /// arrival times), each verdict checked against the rules.
    fn commands(&mut self, k: u64) -> Commands {
        let mut got = Commands {
            advance: 0.0,
            answered: false,
            values: vec![self.s.applied_now().to_vec()],
        };
        for _ in 0..self.rng.below(5) {
            let (rng, s, n) = (&mut self.rng, &mut self.s, self.n);
            let seq = match rng.below(12) {
                0 => u64::MAX,
                1 => s.last_applied_seq().unwrap_or(k),
                2 => k + 1,
                r => k.saturating_sub(r % 6),
            };
            let cmd_v: Vec<f64> = match rng.below(10) {
                0 => vec![f64::NAN; n],
                1 => vec![1.0; n + 1],
                _ => (0..n).map(|_| rng.unit() * 10.0 - 5.0).collect(),
            };
            let body = match rng.below(10) {
                0 => CommandBody::WarmingUp,
                1 => CommandBody::Rejected("x"),
                2 => CommandBody::Unknown,
                _ => CommandBody::Control(&cmd_v),
            };
            let at = match rng.below(8) {
                0 => f64::NAN,
                1 => -1.0,
                2 => 2.0 * H,
                _ => rng.unit() * H,
            };
            let before = s.counters().clone();
            let last = s.last_applied_seq();
            self.delivered += 1;
            let horizon = &[];
            let (verdict, done) = s.on_command(
                at,
                IncomingCommand {
                    seq,
                    body,
                    horizon,
                    lease: Credentials::default(),
                },
            );
            assert_eq!(total(s.counters()), total(&before) + 1);
            assert_eq!(done, seq == k && !matches!(verdict, Verdict::Ignored(_)));
            match verdict {
                Verdict::Apply { v, advance, late } => {
                    assert!(seq <= k && k - seq <= u64::from(self.max_age));
                    assert!(last.is_none_or(|l| seq > l));
                    assert_eq!(late, seq < k);
                    assert!(advance >= 0.0);
                    got.advance += advance;
                    assert!(got.advance <= H + 1e-12);
                    assert_eq!(s.mode(), LoopMode::Remote);
                    s.applied(&v);
                    got.values.push(v.clone());
                    self.legit.push(v);
                    got.answered = true;
                }
                Verdict::WarmingUp => got.answered = true,
                Verdict::Rejected | Verdict::Ignored(_) => {}
            }
        }
        got
    }

    /// End period `k`: its time adds up, its mode and missing flag follow from the
    /// commands, what is applied was legitimate, the mean lies within what was
    /// applied, and the counters add up.
    fn end(&mut self, k: u64, got: &Commands) {
        let (s, n) = (&mut self.s, self.n);
        let end = s.end_period().unwrap();
        assert!(end.advance >= 0.0);
        assert!(
            (got.advance + end.advance - H).abs() <= 1e-15,
            "{} + {}",
            got.advance,
            end.advance
        );
        assert_eq!(end.missing, !got.answered);
        self.missing += u64::from(end.missing);
        if end.mode == LoopMode::Remote {
            self.remote_periods += 1;
        }
        if end.mode.is_fallback() || end.mode == LoopMode::Holding {
            assert_eq!(s.mode(), end.mode);
        }
        assert!(self.legit.iter().any(|l| l[..] == *s.applied_now()));
        // The period's mean lies between what was applied in it.
        let next = begin_mean(s, k + 1, n);
        for (i, m) in next.iter().enumerate() {
            let lo = got
                .values
                .iter()
                .map(|v| v[i])
                .fold(f64::INFINITY, f64::min);
            let hi = got
                .values
                .iter()
                .map(|v| v[i])
                .fold(f64::NEG_INFINITY, f64::max);
            assert!(
                *m >= lo - 1e-9 && *m <= hi + 1e-9,
                "{m} not in [{lo}, {hi}]"
            );
        }
        let c = s.counters();
        assert_eq!(
            c.periods,
            c.holding_periods + c.local_periods + c.safe_stop_periods + self.remote_periods
        );
        assert_eq!(total(c), self.delivered);
        assert_eq!(c.fallbacks, self.fallbacks);
        assert_eq!(c.missing, self.missing);
        assert!(c.late <= c.commands);
    }

    /// Add this run's counters to `seen`.
    fn tally(&self, seen: &mut SupervisorCounters) {
        let c = self.s.counters();
        for (sum, x) in [
            (&mut seen.commands, c.commands),
            (&mut seen.late, c.late),
            (&mut seen.missing, c.missing),
            (&mut seen.too_old, c.too_old),
            (&mut seen.superseded, c.superseded),
            (&mut seen.duplicates, c.duplicates),
            (&mut seen.warming_up, c.warming_up),
            (&mut seen.rejected, c.rejected),
            (&mut seen.malformed, c.malformed),
            (&mut seen.future, c.future),
            (&mut seen.fallbacks, c.fallbacks),
            (&mut seen.holding_periods, c.holding_periods),
            (&mut seen.local_periods, c.local_periods),
            (&mut seen.safe_stop_periods, c.safe_stop_periods),
        ] {
            *sum += x;
        }
    }
}

#[test]
fn randomised_command_sequences_keep_the_invariants() {
    let mut seen = SupervisorCounters::default();
    for seed in 0..40u64 {
        let mut trial = Trial::new(seed);
        let mut k = 0u64;
        for _ in 0..300 {
            k += 1 + u64::from(trial.rng.below(20) == 0);
            trial.begin(k);
            let got = trial.commands(k);
            trial.end(k, &got);
        }
        trial.tally(&mut seen);
    }
    // The sequences did reach every outcome and every mode.
    let all = [
        seen.commands,
        seen.late,
        seen.missing,
        seen.too_old,
        seen.superseded,
        seen.duplicates,
        seen.warming_up,
        seen.rejected,
        seen.malformed,
        seen.future,
        seen.fallbacks,
        seen.holding_periods,
        seen.local_periods,
        seen.safe_stop_periods,
    ];
    assert!(all.iter().all(|&x| x > 0), "{seen:?}");
}

/// The mean the next sample would carry, without changing the supervisor.
fn begin_mean(s: &mut Supervisor, k: u64, n: usize) -> Vec<f64> {
    let mut copy = s.clone();
    copy.begin_period(k, k as f64 * H, &vec![0.0; n], &refs(n))
        .unwrap()
        .applied_mean
}
