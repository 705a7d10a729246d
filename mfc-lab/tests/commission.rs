//! Commissioning offline (`mfc-lab commission`): from an `α` ten times too small or too
//! large, the runs find `α` from the plant's own response, and the scenario run with it
//! tracks within 1.3x of the reference law (the tuner's on the AERO, the model's own on the
//! coupled lags). Where commissioning does not reach that (the heater's dead time, the
//! motor's friction and backlash), `docs/results-commission.md` says so; it is not tested
//! as if it did.

use mfc::{LawConfig, Order};
use mfc_lab::commission::{commission_all, scale_alpha};
use mfc_lab::offline::simulate;
use plant::scenario::{load_controller, load_scenario, shipped_controller};

fn spec(
    amplitude: f64,
    period: f64,
    max_deviation: f64,
    window: usize,
    order: Order,
) -> mfc::CommissionSpec {
    mfc::CommissionSpec {
        amplitude,
        period,
        cycles: 4,
        max_deviation,
        window,
        order: Some(order),
    }
}

fn rms(s: &plant::scenario::Scenario, c: &plant::scenario::ControllerSet) -> Vec<f64> {
    simulate(s, c, false)
        .unwrap()
        .summary
        .channels
        .iter()
        .map(|m| m.rms)
        .collect()
}

fn alphas(c: &plant::scenario::ControllerSet) -> Vec<f64> {
    c.channels
        .iter()
        .map(|l| match l {
            LawConfig::Intelligent { params, .. } => params.alpha,
            _ => f64::NAN,
        })
        .collect()
}

#[test]
fn the_aero_is_commissioned_from_a_wrong_alpha_to_the_tuners_rms() {
    let scenario = load_scenario("1").unwrap();
    let ipd = shipped_controller("ipd").unwrap();
    let tuned = rms(&scenario, &shipped_controller("ipd-tuned").unwrap());
    let specs = [
        spec(3.0, 1.0, 0.002, 10, Order::One),
        spec(3.0, 1.0, 0.2, 20, Order::Two),
    ];
    for scale in [0.1, 10.0] {
        let wrong = scale_alpha(&ipd, scale);
        let before = rms(&scenario, &wrong);
        let (found, runs) = commission_all(&scenario, &wrong, &specs).unwrap();
        assert!(
            runs.iter().any(|r| r.channel == 1 && r.outcome.is_ok()),
            "{runs:?}"
        );
        let after = rms(&scenario, &found);
        let a = alphas(&found);
        // The pitch's alpha lands near the one the rules gave (0.2), whichever side it
        // started from; the pitch then tracks within 1.3x of the tuned iPD, and far better
        // than from the wrong start.
        assert!((0.1..0.4).contains(&a[1]), "x{scale}: {a:?}");
        assert!(
            after[1] <= 1.3 * tuned[1],
            "x{scale}: pitch {} against the tuner's {}",
            after[1],
            tuned[1]
        );
        assert!(
            after[1] < before[1] / 5.0,
            "x{scale}: {before:?} -> {after:?}"
        );
        assert!(
            after[0] <= 1.3 * tuned[0],
            "x{scale}: azimuth {} against {}",
            after[0],
            tuned[0]
        );
    }
}

#[test]
fn coupled_lags_are_commissioned_to_their_models_alpha() {
    let scenario = load_scenario("../plants/coupled-lags/scenarios/lags-3.toml").unwrap();
    let model = load_controller("../plants/coupled-lags/controllers/ip-3.toml").unwrap();
    let reference = rms(&scenario, &model);
    let specs = [spec(0.5, 1.0, 2.0, 10, Order::One); 3];
    for scale in [0.1, 10.0] {
        let (found, runs) = commission_all(&scenario, &scale_alpha(&model, scale), &specs).unwrap();
        assert!(runs.iter().all(|r| r.outcome.is_ok()), "{runs:?}");
        // alpha = b / tau of each lag, which the plant's file gives: 2, 1.467, 1.2.
        for (got, want) in alphas(&found).iter().zip(alphas(&model)) {
            assert!(
                (got / want - 1.0).abs() < 0.1,
                "x{scale}: {got} against {want}"
            );
        }
        for (got, want) in rms(&scenario, &found).iter().zip(&reference) {
            assert!(*got <= 1.3 * want, "x{scale}: {got} against {want}");
        }
    }
}
