//! What one period's plant I/O costs through the Modbus TCP bridge, against the driver
//! path (the anchor), measured side by side in the same run on loopback: the DC motor's
//! physics behind pymodbus (`plants/servers/modbus_plant.py`, the venv of
//! `plants/servers/setup.sh`) and behind its driver process (`plants/dc-motor/dc_motor.py`).
//!
//! `cargo bench -p plant-agent --bench bridges [-- PERIODS]` (default 1000 per round, three
//! rounds, the two paths alternating so that both see the same machine). Each period, paced
//! at 100 Hz, does what the agent does: read the outputs, write the inputs (the bridge reads
//! back the applied value, as the shipped map asks), advance the plant's time. Prints the
//! median and the 99th percentile of that round's time per path and their ratios.

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use plant::scenario::{load_scenario, PlantSource};
use plant::Plant;

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// One round on `plant`: `periods` periods at 100 Hz; the time of each period's I/O (µs).
fn round(plant: &mut dyn Plant, periods: u32) -> Vec<f64> {
    let h = Duration::from_millis(10);
    let start = Instant::now() + h;
    let mut took = Vec::with_capacity(periods as usize);
    for k in 0..periods {
        let deadline = start + h * k;
        std::thread::sleep(deadline.saturating_duration_since(Instant::now()));
        let t0 = Instant::now();
        plant.read().expect("read");
        let v = 0.3 * (f64::from(k) * 0.05).sin();
        plant.write(&[v]).expect("write");
        plant.advance(0.01).expect("advance");
        took.push(t0.elapsed().as_secs_f64() * 1e6);
    }
    took.sort_by(f64::total_cmp);
    took
}

fn main() {
    let periods: u32 = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .and_then(|a| a.parse().ok())
        .unwrap_or(1000);
    let setup = Command::new("bash")
        .arg(root().join("plants/servers/setup.sh"))
        .output()
        .expect("plants/servers/setup.sh");
    assert!(setup.status.success(), "plants/servers/setup.sh failed");
    let python = String::from_utf8(setup.stdout).unwrap();
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut server = Command::new(python.lines().last().unwrap().trim())
        .arg(root().join("plants/servers/modbus_plant.py"))
        .args([
            "--plant",
            "dc-motor",
            "--seed",
            "1",
            "--port",
            &port.to_string(),
        ])
        .stdout(Stdio::piped())
        .spawn()
        .expect("the Modbus server");
    let mut line = String::new();
    BufReader::new(server.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    assert_eq!(line.trim(), format!("listening {port}"));

    let mut modbus = load_scenario(
        root()
            .join("plants/servers/motor-steps-modbus.toml")
            .to_str()
            .unwrap(),
    )
    .unwrap();
    let PlantSource::Modbus(m) = &mut modbus.plant else {
        panic!("the shipped file is a Modbus plant")
    };
    m.config.address = format!("127.0.0.1:{port}");
    let driver = load_scenario(
        root()
            .join("plants/dc-motor/scenarios/motor-steps.toml")
            .to_str()
            .unwrap(),
    )
    .unwrap();
    let mut bridge = fieldbus::modbus::ModbusBridge::connect(m).expect("the bridge");
    let requests = bridge.requests_per_period();
    let mut anchor = fieldbus::open(&driver.plant, 1, 1).expect("the driver");

    println!("| round | path | median (us) | p99 (us) |\n|---|---|---:|---:|");
    let (mut med, mut p99) = (Vec::new(), Vec::new());
    for r in 1..=3 {
        let a = round(anchor.as_mut(), periods);
        let b = round(&mut bridge, periods);
        for (name, t) in [("driver (anchor)", &a), ("modbus", &b)] {
            println!(
                "| {r} | {name} | {:.0} | {:.0} |",
                percentile(t, 0.5),
                percentile(t, 0.99)
            );
        }
        med.push(percentile(&b, 0.5) / percentile(&a, 0.5));
        p99.push(percentile(&b, 0.99) / percentile(&a, 0.99));
    }
    med.sort_by(f64::total_cmp);
    p99.sort_by(f64::total_cmp);
    println!(
        "\nmodbus over driver, median of the rounds' ratios: median {:.2}x, p99 {:.2}x ({periods} periods per round at 100 Hz; the bridge's period makes {} requests)",
        med[1],
        p99[1],
        requests
    );
    let _ = bridge.stop();
    let _ = anchor.stop();
    let _ = server.kill();
    let _ = server.wait();
}
