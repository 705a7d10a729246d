//! What one period's plant I/O costs through the Modbus TCP and OPC UA bridges, against the
//! driver path (the anchor), measured side by side in the same run on loopback: the DC
//! motor's physics behind pymodbus (`plants/servers/modbus_plant.py`), behind asyncua
//! (`plants/servers/opcua_plant.py`; the venv of `plants/servers/setup.sh`) and behind its
//! driver process (`plants/dc-motor/dc_motor.py`).
//!
//! `cargo bench -p plant-agent --bench bridges [-- PERIODS]` (default 1000 per round, three
//! rounds, the paths in turn so that all see the same machine). Each period, paced at
//! 100 Hz, does what the agent does: read the outputs, write the inputs (the bridge reads
//! back the applied value, as the shipped map asks), advance the plant's time. OPC UA
//! twice: a Read per period, and the outputs by subscription (sampled and published by
//! the server every millisecond, the default at 10 ms, no request). Prints the median and the 99th percentile of that round's time
//! per path and their ratios.

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

/// A server script on a free port, once it listens.
fn server(python: &str, script: &str) -> (std::process::Child, u16) {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut child = Command::new(python)
        .arg(root().join(script))
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
        .expect("a plant server");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    assert_eq!(line.trim(), format!("listening {port}"));
    (child, port)
}

fn scenario(rel: &str) -> plant::scenario::Scenario {
    load_scenario(root().join(rel).to_str().unwrap()).unwrap()
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
    let stdout = String::from_utf8(setup.stdout).unwrap();
    let python = stdout.lines().last().unwrap().trim();
    let (mut modbus_server, modbus_port) = server(python, "plants/servers/modbus_plant.py");
    let (mut opcua_server, opcua_port) = server(python, "plants/servers/opcua_plant.py");

    let mut modbus = scenario("plants/servers/motor-steps-modbus.toml");
    let PlantSource::Modbus(m) = &mut modbus.plant else {
        panic!("the shipped file is a Modbus plant")
    };
    m.config.address = format!("127.0.0.1:{modbus_port}");
    let mut opcua = scenario("plants/servers/motor-steps-opcua.toml");
    let PlantSource::OpcUa(o) = &mut opcua.plant else {
        panic!("the shipped file is an OPC UA plant")
    };
    o.config.endpoint = format!("opc.tcp://127.0.0.1:{opcua_port}/");
    let mut subscribed = opcua.clone();
    if let PlantSource::OpcUa(o) = &mut subscribed.plant {
        o.config.sampling = plant::opcua::Sampling::Subscribe;
    }
    let requests = fieldbus::modbus::ModbusBridge::connect(m)
        .expect("the Modbus bridge")
        .requests_per_period();
    let driver = scenario("plants/dc-motor/scenarios/motor-steps.toml");
    let mut paths: Vec<(&str, Box<dyn Plant>)> = vec![
        (
            "driver (anchor)",
            fieldbus::open(&driver.plant, 1, 1).expect("the driver"),
        ),
        (
            "modbus",
            fieldbus::open(&modbus.plant, 1, 1).expect("the Modbus bridge"),
        ),
        (
            "opcua",
            fieldbus::open(&opcua.plant, 1, 1).expect("the OPC UA bridge"),
        ),
        (
            "opcua, subscription",
            fieldbus::open(&subscribed.plant, 1, 1).expect("the OPC UA bridge, subscribed"),
        ),
    ];

    println!("| round | path | median (us) | p99 (us) |\n|---|---|---:|---:|");
    let mut ratios: Vec<Vec<(f64, f64)>> = vec![Vec::new(); paths.len()];
    for r in 1..=3 {
        let mut anchor = (0.0, 0.0);
        for (i, (name, plant)) in paths.iter_mut().enumerate() {
            let t = round(plant.as_mut(), periods);
            let (med, p99) = (percentile(&t, 0.5), percentile(&t, 0.99));
            println!("| {r} | {name} | {med:.0} | {p99:.0} |");
            if i == 0 {
                anchor = (med, p99);
            }
            ratios[i].push((med / anchor.0, p99 / anchor.1));
        }
    }
    println!();
    for ((name, _), mut r) in paths.iter().zip(ratios).skip(1) {
        r.sort_by(|a, b| a.0.total_cmp(&b.0));
        let med = r[1].0;
        r.sort_by(|a, b| a.1.total_cmp(&b.1));
        println!(
            "{name} over the driver, median of the rounds' ratios: median {med:.2}x, p99 {:.2}x",
            r[1].1
        );
    }
    println!(
        "({periods} periods per round at 100 Hz; a period reads the output, writes the input and reads \
         the applied value: {requests} Modbus requests, 3 OPC UA services, or 2 with a subscription)"
    );
    for (_, mut plant) in paths {
        let _ = plant.stop();
    }
    for s in [&mut modbus_server, &mut opcua_server] {
        let _ = s.kill();
        let _ = s.wait();
    }
}
