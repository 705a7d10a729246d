//! A plant behind a server we did not write, for tests: pymodbus
//! (`plants/servers/modbus_plant.py`) or asyncua (`plants/servers/opcua_plant.py`), pinned
//! by `plants/servers/setup.sh`, hosting the DC motor's physics in real time. Shared by the
//! agent's tests and the system tests (included by path: neither crate may depend on the
//! other's tests).
#![allow(dead_code)] // each including test uses a part: Modbus registers or OPC UA nodes

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::Duration;

use fieldbus::opcua::{OpcUaUser, SessionSpec};
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

/// Which server.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum ServerKind {
    Modbus,
    OpcUa,
}

/// A server with the DC motor, killed when dropped.
pub struct Server {
    child: Child,
    pub port: u16,
    pub protocol: ServerKind,
}

impl Server {
    /// The pymodbus server on `port`.
    pub fn start(port: u16, flags: &[&str]) -> Self {
        Self::start_as(ServerKind::Modbus, port, flags)
    }

    /// The `protocol`'s server on `port`, with the server's `flags`.
    pub fn start_as(protocol: ServerKind, port: u16, flags: &[&str]) -> Self {
        let script = match protocol {
            ServerKind::Modbus => "plants/servers/modbus_plant.py",
            ServerKind::OpcUa => "plants/servers/opcua_plant.py",
        };
        let mut child = Command::new(python())
            .arg(root().join(script))
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
            .recv_timeout(Duration::from_secs(60))
            .expect("the server never listened");
        assert_eq!(line, format!("listening {port}"));
        Self {
            child,
            port,
            protocol,
        }
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// Modbus: `host:port`; OPC UA: the endpoint URL.
    pub fn address(&self) -> String {
        match self.protocol {
            ServerKind::Modbus => format!("127.0.0.1:{}", self.port),
            ServerKind::OpcUa => format!("opc.tcp://127.0.0.1:{}/", self.port),
        }
    }

    /// An OPC UA server's node `ns=2;s=Plant.NAME` (Output, Input, Applied) now.
    pub fn node(&self, name: &str, user: Option<(&str, &str)>) -> f64 {
        let mut spec = SessionSpec::plain(&self.address(), Duration::from_secs(10));
        if let Some((u, p)) = user {
            spec.identity = OpcUaUser::User {
                name: u.into(),
                password: p.into(),
            };
        }
        self.node_with(&spec, name)
    }

    /// The node `ns=2;s=Plant.NAME` through a session `spec` describes.
    pub fn node_with(&self, spec: &SessionSpec, name: &str) -> f64 {
        fieldbus::probe::read_node(spec, &format!("ns=2;s=Plant.{name}"))
            .expect("reading the server")
            .expect("a finite number")
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

/// A fresh scratch directory for test `name` of file `file`.
pub fn scratch(file: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("mfc-{file}-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The agent's exit status, once it exits within `limit` (killed and a panic otherwise).
pub fn wait(child: &mut Child, limit: Duration) -> i32 {
    let until = std::time::Instant::now() + limit;
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.code().expect("exited, not killed by a signal");
        }
        if std::time::Instant::now() > until {
            let _ = child.kill();
            panic!("the agent did not exit within {limit:?}");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// The run's `summary.json`.
pub fn summary(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

/// A run whose server was restarted under it: it completed (the bridge reconnected),
/// applied its safe stop, and the outage cost periods. `what` names the case.
pub fn went_on_after_the_reconnection(out: &Path, what: &str) {
    let s = summary(out);
    assert_eq!(
        s["end"], "completed",
        "{what}: the run went on after the reconnection: {s}"
    );
    assert_eq!(s["safe_stop_applied"], true, "{what}: {s}");
    assert!(
        s["overruns"].as_u64().unwrap() > 0,
        "{what}: the outage cost periods: {s}"
    );
}
