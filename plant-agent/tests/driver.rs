//! The external-driver bridge, with `plant-agent sim-driver` as the fake rig.

use std::time::Duration;

use plant_agent::aero::AeroParams;
use plant_agent::plant::{DriverPlant, Plant, PlantError, SimPlant};

fn driver() -> DriverPlant {
    DriverPlant::spawn(
        env!("CARGO_BIN_EXE_plant-agent"),
        &["sim-driver".into(), "--seed".into(), "3".into()],
        Duration::from_secs(5),
    )
    .unwrap()
}

/// Through the bridge, the rig behaves exactly as the simulator in process.
#[test]
fn the_bridge_is_transparent() {
    let mut d = driver();
    let mut s = SimPlant::new(AeroParams::default(), 3).unwrap();
    assert_eq!(d.channels(), 2);
    for k in 0..200 {
        let v = [
            12.0 * (k as f64 * 0.05).sin(),
            30.0 * (k as f64 * 0.03).cos(),
        ];
        assert_eq!(
            d.write(&v).unwrap(),
            s.write(&v).unwrap(),
            "applied (saturated)"
        );
        d.advance(0.01).unwrap();
        s.advance(0.01).unwrap();
        let (yd, ys) = (d.read().unwrap(), s.read().unwrap());
        for (a, b) in yd.iter().zip(&ys) {
            // The line protocol carries full-precision floats.
            assert!(
                (a - b).abs() <= 1e-12 * b.abs().max(1e-12),
                "{yd:?} vs {ys:?}"
            );
        }
    }
    d.stop().unwrap();
}

#[test]
fn driver_failures_are_reported_not_hung() {
    // A program that never says hello.
    let e = DriverPlant::spawn("sleep", &["5".into()], Duration::from_millis(200))
        .err()
        .unwrap();
    assert!(matches!(e, PlantError::Timeout { .. }), "{e}");
    // A program that is not there.
    let e = DriverPlant::spawn("/nonexistent/driver", &[], Duration::from_millis(200))
        .err()
        .unwrap();
    assert!(e.to_string().contains("/nonexistent/driver"), "{e}");
    // A driver that refuses a request: the error carries its message.
    let mut d = driver();
    let e = d.write(&[1.0]).unwrap_err();
    assert!(
        e.to_string().contains("needs 2 numbers") || matches!(e, PlantError::Protocol { .. }),
        "{e}"
    );
}
