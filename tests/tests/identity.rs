//! One identity, one process, or a loud warning: two service processes started with one
//! controller id (a copied bundle) each carry their own instance, see each other and say
//! so in their status (and their log and metrics), and `mfcctl services` lists both with
//! their processes and a warning; once one stops, the other's warning goes.

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use system_tests::{scratch_dir, SERIAL};
use transport::ops;

struct Proc(Child);
impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start(dir: &std::path::Path, listen: &str, connect: Option<&str>, log: &str) -> Proc {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_service-under-test"));
    cmd.args(["--config", dir.join("service.toml").to_str().unwrap()])
        .args([
            "--listen",
            listen,
            "--no-multicast-scouting",
            "--mode",
            "peer",
        ]);
    if let Some(c) = connect {
        cmd.args(["--connect", c]);
    }
    let child = cmd
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join(log)).unwrap())
        .spawn()
        .unwrap();
    Proc(child)
}

fn endpoint() -> String {
    format!("tcp/127.0.0.1:{}", transport::free_local_port().unwrap())
}

#[tokio::test(flavor = "multi_thread")]
async fn two_processes_of_one_identity_see_each_other_and_say_so() {
    let _s = SERIAL.lock().await;
    let dir = scratch_dir("identity");
    std::fs::write(
        dir.join("service.toml"),
        "controller_id = \"controller-1\"\n",
    )
    .unwrap();
    let (a, b) = (endpoint(), endpoint());
    let _first = start(&dir, &a, None, "a.log");
    let mut second = start(&dir, &b, Some(&a), "b.log");
    let s = transport::ZenohArgs::loopback(None, vec![a.clone(), b.clone()])
        .open()
        .await
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    let list = loop {
        let list = ops::services(&s, Duration::from_secs(1)).await.unwrap();
        if list.len() == 2 && list.iter().all(|x| x.twins.len() == 1) {
            break list;
        }
        assert!(
            Instant::now() < deadline,
            "the two never saw each other: {list:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let (x, y) = (&list[0], &list[1]);
    assert_eq!(
        (x.controller_id.as_str(), y.controller_id.as_str()),
        ("controller-1", "controller-1")
    );
    assert_ne!(x.instance, y.instance, "each process its own instance");
    assert_eq!(
        (x.twins[0], y.twins[0]),
        (y.instance, x.instance),
        "each sees the other"
    );
    for log in ["a.log", "b.log"] {
        let text = std::fs::read_to_string(dir.join(log)).unwrap();
        let warned = text
            .lines()
            .filter(|l| l.contains("another process carries this controller id"))
            .count();
        assert_eq!(warned, 1, "{log}: one warning, once: {text}");
    }
    // mfcctl: both listed with their processes, and a warning.
    let argv = [
        "mfcctl",
        "--connect",
        &a,
        "--connect",
        &b,
        "--no-multicast-scouting",
        "--mode",
        "peer",
        "services",
    ];
    let text = mfcctl::cli::run(mfcctl::cli::MfcctlCli::try_parse_from(argv).unwrap())
        .await
        .unwrap();
    println!("{text}");
    assert!(
        text.contains(&format!("{:016x}", x.instance))
            && text.contains(&format!("{:016x}", y.instance)),
        "{text}"
    );
    assert!(
        text.contains("WARNING: controller-1 runs in 2 processes"),
        "{text}"
    );
    // One stops: the other's warning goes (a clean stop removes its token at once).
    let _ = Command::new("kill")
        .args(["-TERM", &second.0.id().to_string()])
        .status();
    let _ = second.0.wait();
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let list = ops::services(&s, Duration::from_secs(1)).await.unwrap();
        if list.len() == 1 && list[0].twins.is_empty() {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the twin is still listed: {list:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let _ = s.close().await;
}
