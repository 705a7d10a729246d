//! A plant behind a Modbus TCP server we did not write, for tests: pymodbus
//! (`plants/servers/modbus_plant.py`, pinned by `plants/servers/setup.sh`) hosting the DC
//! motor's physics in real time. Shared by the agent's tests and the system tests
//! (included by path: neither crate may depend on the other's tests).

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

use plant::modbus::{Point, RegisterKind, ValueType, WordOrder};

pub fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The venv's python with pymodbus pinned (`plants/servers/setup.sh`, once per process).
pub fn python() -> &'static Path {
    static PY: OnceLock<PathBuf> = OnceLock::new();
    PY.get_or_init(|| {
        let out = Command::new("bash")
            .arg(root().join("plants/servers/setup.sh"))
            .output()
            .expect("running plants/servers/setup.sh");
        assert!(
            out.status.success(),
            "plants/servers/setup.sh failed (python3 with venv and pip, and PyPI, are needed): {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let text = String::from_utf8(out.stdout).unwrap();
        PathBuf::from(
            text.lines()
                .last()
                .expect("setup.sh prints the venv's python")
                .trim(),
        )
    })
}

/// The pymodbus server with the DC motor, killed when dropped.
pub struct Server {
    child: Child,
    pub port: u16,
}

impl Server {
    pub fn start(port: u16, flags: &[&str]) -> Self {
        let mut child = Command::new(python())
            .arg(root().join("plants/servers/modbus_plant.py"))
            .args([
                "--plant",
                "dc-motor",
                "--seed",
                "1",
                "--port",
                &port.to_string(),
            ])
            .args(flags)
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("starting the Modbus server");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                let _ = tx.send(line);
            }
        });
        let line = rx
            .recv_timeout(Duration::from_secs(30))
            .expect("the server never listened");
        assert_eq!(line, format!("listening {port}"));
        Self { child, port }
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn address(&self) -> String {
        format!("127.0.0.1:{}", self.port)
    }

    /// The float32 at holding register 0 (the input) or input register 2 (what the plant
    /// applies).
    pub fn value(&self, kind: RegisterKind, address: u16) -> f64 {
        let p = Point {
            kind,
            address,
            value_type: Some(ValueType::Float32),
            word_order: WordOrder::Big,
            scale: 1.0,
            offset: 0.0,
        };
        fieldbus::probe::read_point(&self.address(), 1, &p, Duration::from_secs(5))
            .expect("reading the server")
            .expect("a finite number")
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.kill();
    }
}
