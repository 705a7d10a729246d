//! The external-driver bridge against a real driver process (`fixtures/echo_driver.py`):
//! it is exact, it reports failures instead of hanging, and it ends drivers cleanly.

use std::time::{Duration, Instant};

use plant::driver::DriverPlant;
use plant::{Plant, PlantError};

fn fixture() -> String {
    format!(
        "{}/tests/fixtures/echo_driver.py",
        env!("CARGO_MANIFEST_DIR")
    )
}

fn echo(args: &[&str]) -> Result<DriverPlant, PlantError> {
    let mut argv = vec![fixture()];
    argv.extend(args.iter().map(|s| s.to_string()));
    DriverPlant::spawn(
        "python3",
        &argv,
        None,
        Duration::from_secs(10),
        Duration::from_millis(500),
    )
}

/// Full-precision floats both ways, any channel count, what was applied reported back.
#[test]
fn the_bridge_is_exact_for_any_channel_count() {
    for n in [1usize, 3, 16] {
        let mut d = echo(&["--channels", &n.to_string()]).unwrap();
        assert_eq!(d.channels(), n);
        let v: Vec<f64> = (0..n).map(|i| 0.1 + i as f64 / 3.0 - 2.0e-7).collect();
        assert_eq!(d.write(&v).unwrap(), v);
        d.advance(0.01).unwrap();
        assert_eq!(d.read().unwrap(), v, "bit-identical round trip");
        let big = vec![25.0; n];
        assert_eq!(
            d.write(&big).unwrap(),
            vec![10.0; n],
            "the driver's own limits"
        );
        d.stop().unwrap();
    }
}

#[test]
fn driver_failures_are_reported_not_hung() {
    // A program that never says hello.
    let t = Instant::now();
    let e = DriverPlant::spawn(
        "sleep",
        &["5".into()],
        None,
        Duration::from_millis(200),
        Duration::from_millis(200),
    )
    .err()
    .unwrap();
    assert!(matches!(e, PlantError::Timeout { .. }), "{e}");
    assert!(t.elapsed() < Duration::from_secs(4), "the drop reaped it");
    // A program that is not there.
    let e = DriverPlant::spawn(
        "/nonexistent/driver",
        &[],
        None,
        Duration::from_millis(200),
        Duration::from_millis(200),
    )
    .err()
    .unwrap();
    assert!(e.to_string().contains("/nonexistent/driver"), "{e}");
    // A driver that refuses a request: the error carries its message.
    let mut d = echo(&["--channels", "2"]).unwrap();
    let e = d.write(&[1.0]).unwrap_err();
    assert!(e.to_string().contains("needs 2 numbers"), "{e}");
    // A driver that stops answering: a timeout, not a hang.
    let mut d = echo(&["--hang-after", "2"]).unwrap();
    d.read().unwrap();
    d.read().unwrap();
    let t = Instant::now();
    assert!(matches!(d.read(), Err(PlantError::Timeout { .. })));
    assert!(t.elapsed() < Duration::from_secs(2));
    // A driver that exits.
    let mut d = echo(&["--exit-after", "1"]).unwrap();
    d.read().unwrap();
    let e = d.read().unwrap_err();
    assert!(e.to_string().contains("exited"), "{e}");
}

/// `stop` reaches the driver; a driver that ignores it is killed, not waited for forever;
/// dropping the bridge without `stop` still asks for it.
#[test]
fn drivers_are_always_stopped() {
    let dir = std::env::temp_dir().join(format!("mfc-driver-stop-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let log = dir.join("a.log");
    let mut d = echo(&["--log", log.to_str().unwrap()]).unwrap();
    d.read().unwrap();
    d.stop().unwrap();
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.lines().collect::<Vec<_>>(), ["read", "stop"]);

    let log = dir.join("b.log");
    {
        let mut d = echo(&["--log", log.to_str().unwrap()]).unwrap();
        d.read().unwrap();
    } // dropped
    let text = std::fs::read_to_string(&log).unwrap();
    assert_eq!(text.lines().last(), Some("stop"), "{text}");

    let mut d = echo(&["--hang-after", "0"]).unwrap();
    let t = Instant::now();
    assert!(d.stop().is_err());
    assert!(t.elapsed() < Duration::from_secs(4), "{:?}", t.elapsed());
    let _ = std::fs::remove_dir_all(&dir);
}
