//! The CI slice of the robustness benchmark (`mfc-lab robust`): the headline law, untouched,
//! on the scenario with the complex references while the plant's structure changes (added
//! mass up to 10 g, pitch spring and damping x0.3 to x3, alone and in 4 seeded
//! combinations). It fails if the law's RMS leaves 2x its own nominal anywhere, if the
//! untouched PID or ADRC does better on any variation and channel, or if a run is unsafe.
//!
//! The slice is where the claim holds today. Over the whole family it does not: slower
//! rotors, other motor gains, noise and coarse encoders break the bound
//! (`docs/results-robust.md` has the full table), and this test does not pretend otherwise.

use mfc_lab::robust::{check, family_of, judge, run, Factor};
use plant::scenario::{load_scenario, shipped_controller};

#[test]
fn the_headline_law_holds_its_bars_on_the_structural_slice() {
    let scenario = load_scenario("2").unwrap();
    let sets: Vec<_> = ["ipd", "pid", "adrc"]
        .iter()
        .map(|n| shipped_controller(n).unwrap())
        .collect();
    let factors = [Factor::Mass, Factor::Spring, Factor::Damping];
    let variations = family_of(&factors, 1, 4);
    assert_eq!(
        variations.len(),
        1 + 5 + 4,
        "nominal, 5 ends (mass has one), 4 random"
    );
    let cells = run(&scenario, &sets, &variations, 2).unwrap();
    assert_eq!(cells.len(), sets.len() * variations.len());
    let verdicts = judge(&cells, &["pid", "adrc"]);
    let failures = check(&verdicts, &["ipd"], 2.0);
    assert!(failures.is_empty(), "{failures:#?}");
    // The judgement judged something: the law's runs all have finite ratios, the slice
    // moved the plant enough to show (some ratio at least 5 % away from 1), and it is a
    // slice on which the PID tuned on scenario 1 does come to grief (the bars are not
    // trivially met by a family that changes nothing).
    let ipd: Vec<_> = cells.iter().filter(|c| c.controller == "ipd").collect();
    assert_eq!(ipd.len(), variations.len());
    assert!(ipd.iter().all(|c| c.ratio.iter().all(|r| r.is_finite())));
    let moved = ipd
        .iter()
        .flat_map(|c| c.ratio.iter())
        .any(|r| (r - 1.0).abs() > 0.05);
    assert!(moved, "the slice changed nothing");
    assert!(cells.iter().any(|c| c.controller == "pid" && !c.safe));
}

/// The DC motor's law tuned for its family (`mfc-lab tune --family`,
/// `plants/dc-motor/controllers/ipd-family.toml`), untouched, over that family (friction,
/// backlash, inertia x0.5 and x2, 4 seeded combinations): within 2x its own nominal RMS
/// everywhere, safe everywhere, and its nominal RMS under the shipped `ipd`'s, which breaks
/// the 2x (2.19x with twice the inertia). What it does not hold, and this test does not
/// claim: the ADRC's nominal RMS is lower (`docs/results-robust.md`, "Gains for a family").
#[test]
fn the_motor_law_tuned_for_its_family_holds_within_twice_its_nominal() {
    use mfc_lab::robust::{driver_factors, driver_family};
    use plant::scenario::{load_controller, PlantSource};
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../plants/dc-motor");
    let scenario = load_scenario(&format!("{root}/scenarios/motor-steps.toml")).unwrap();
    let PlantSource::Driver(cmd) = &scenario.plant else {
        panic!("the motor is a driver plant")
    };
    let variations = driver_family(driver_factors(&cmd.argv).unwrap(), 1, 4);
    assert_eq!(variations.len(), 1 + 6 + 4);
    let sets: Vec<_> = ["ipd-family", "ipd"]
        .iter()
        .map(|n| load_controller(&format!("{root}/controllers/{n}.toml")).unwrap())
        .collect();
    let cells = run(&scenario, &sets, &variations, 2).unwrap();
    let verdicts = judge(&cells, &[]);
    let (family, shipped) = (&verdicts[0], &verdicts[1]);
    assert_eq!(family.controller, "ipd-family");
    assert!(family.worst.0 <= 2.0, "{family:?}");
    assert!(family.unsafe_runs.is_empty(), "{family:?}");
    assert!(
        family.nominal_rms[0] < shipped.nominal_rms[0],
        "{family:?} {shipped:?}"
    );
    // The judgement judged something: the family moved the shipped law past the bound.
    assert!(shipped.worst.0 > 2.0, "{shipped:?}");
}
