//! The load generator's kind of device as the registry's benchmark and the memory test
//! drive it (`loadgen`'s own, in its crate, is the same law): one iP channel with a
//! 10-interval window, and its samples.

use protocol::{pb, PROTOCOL_VERSION};

/// A service whose template admits `load-{i}`.
pub const CONFIG: &str = r#"
controller_id = "load"
max_devices = 100000
[[templates]]
pattern = "load-$*"
[[templates.channels]]
law = { law = "intelligent", params = { kind = "ip", alpha = 2.0, kp = 5.0 }, estimator = { window = 10 } }
output = { min = -10.0, max = 10.0 }
reference = [{ kind = "constant", value = 1.0 }]
"#;

/// Device `load-{i}`'s sample `k` (period 10 ms), carrying the `resend` samples before it
/// as agents do (3 by default; the load generator sends none).
pub fn sample(i: usize, k: u64, resend: usize) -> pb::Sample {
    pb::Sample {
        version: PROTOCOL_VERSION,
        device_id: format!("load-{i}"),
        seq: k,
        plant_time: k as f64 * 0.01,
        outputs: vec![0.5],
        applied: vec![1.0],
        run_id: 7,
        sent_unix_ns: 1,
        previous_plant_time: (1..=resend as u64).map(|j| (k - j) as f64 * 0.01).collect(),
        previous_outputs: vec![0.5; resend],
        previous_applied: vec![1.0; resend],
        ..Default::default()
    }
}
