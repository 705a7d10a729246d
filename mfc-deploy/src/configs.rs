//! The zenoh configs: zenohd's, and one per client.
//!
//! Written as JSON, which is valid json5 (what zenohd's `-c` and our `--zenoh-config`
//! read), with certificate paths under the inventory's `install_dir`.

use serde_json::{json, Value};

use crate::inventory::{IdentityKind, Inventory, Protocol};

/// Link lease (ms), on the router and every client: how long a silent link lives. A
/// router killed outright sends nothing over QUIC (no TCP reset), and a new router process
/// knows nothing of the old links, so its clients notice only when the lease runs out, and
/// reconnect after that: an outage shorter than the lease costs the rest of the lease
/// (zenoh's 10 s default kept the plants on their fallback for 10 s after a 2 s outage;
/// 3 s, 1 s after it). With 1 s, remote control is back within about a second of the
/// router's return whatever the outage (`deploy/test/multihost.py`, router outages).
/// Keep-alives go 4 times a lease (every 250 ms), far below the control traffic; a process
/// starved of CPU for a whole second loses its link, and its plants are on their fallback
/// anyway by then.
pub const LEASE_MS: u64 = 1_000;

/// The wait between two attempts to reach the router (ms): with the inventory's
/// `open_timeout_ms`, what a client may take to come back after the router did.
pub const RETRY_MAX_MS: u64 = 100;

/// How long an operator's tool waits for the router before it gives up (ms): a script
/// wants an error, not a hang.
pub const OPERATOR_CONNECT_TIMEOUT_MS: i64 = 5_000;

/// `endpoint` with the link options this project uses: for QUIC, no UDP segmentation
/// offload. With it (zenoh's default), the plants' round trip through the router was
/// p50 1.5 ms / p99 23-28 ms in the multi-host test; without it, p50 1.2 ms / p99 10 ms,
/// and holding periods fell from 8 % to 1.3 % (one run each, same machine, same hour).
/// Options the operator wrote (after `#`) are kept as they are.
pub fn with_link_options(inv: &Inventory, endpoint: String) -> String {
    if inv.router.protocol == Protocol::Quic && !endpoint.contains('#') {
        endpoint + "#segmentation_offload=false"
    } else {
        endpoint
    }
}

fn path(inv: &Inventory, file: &str) -> String {
    format!("{}/{file}", inv.install_dir.trim_end_matches('/'))
}

/// Batches a link may queue for real-time traffic (samples and commands), where zenoh's
/// default is 2: the value the project's sessions use without a file
/// (`transport::REAL_TIME_QUEUE`, which says why), so that a deployment's short stalls on
/// a busy host do not drop commands either.
pub const REAL_TIME_QUEUE: usize = 16;

/// zenohd's config: a router listening on the secured link only (QUIC or TLS, both TLS 1.3
/// with certificates on both ends; the `tls` section configures both), no scouting, the
/// generated access control.
pub fn router(inv: &Inventory, access_control: Value) -> Value {
    let name = &inv.router.name;
    json!({
        "mode": "router",
        "listen": { "endpoints": [with_link_options(inv, inv.router_listen())] },
        // Nothing is discovered: every client names the router, and nobody else is a router.
        "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": false } },
        "transport": { "link": { "tx": { "lease": LEASE_MS, "queue": { "size": { "real_time": REAL_TIME_QUEUE } } }, "tls": {
            "root_ca_certificate": path(inv, "ca.pem"),
            "listen_certificate": path(inv, &format!("{name}.pem")),
            "listen_private_key": path(inv, &format!("{name}.key")),
            // A client without a certificate of this CA is refused at the handshake.
            "enable_mtls": true,
            "close_link_on_expiration": true,
        } } },
        "access_control": access_control,
    })
}

/// A client's config: dial the router over mutual TLS, never listen, never scout.
///
/// Services, plants and gateways retry forever (`timeout_ms: -1`), so start order does not matter
/// and a router restart is ridden through; operators give up after
/// [`OPERATOR_CONNECT_TIMEOUT_MS`].
pub fn client(inv: &Inventory, role: IdentityKind, name: &str) -> Value {
    let (timeout, exit) = match role {
        IdentityKind::Operator => (OPERATOR_CONNECT_TIMEOUT_MS, true),
        _ => (-1, false),
    };
    json!({
        "mode": "client",
        "connect": {
            "endpoints": [with_link_options(inv, inv.router_endpoint())],
            "timeout_ms": timeout,
            "exit_on_failure": exit,
            // Back within a second of the router's return: an attempt every 100 ms, each
            // given up after `open_timeout_ms` (below).
            "retry": { "period_init_ms": RETRY_MAX_MS, "period_max_ms": RETRY_MAX_MS, "period_increase_factor": 1.0 },
        },
        // Who this client is (zenoh shows it in its admin space): `mfcctl` and the console
        // name an operator's requests after it, the name the router holds it to.
        "metadata": { "name": name, "role": role.dir().trim_end_matches('s') },
        // A client that listens could be reached around the router and its access control.
        "listen": { "endpoints": [] },
        "scouting": { "multicast": { "enabled": false }, "gossip": { "enabled": false } },
        "transport": { "unicast": { "open_timeout": inv.router.open_timeout_ms }, "link": { "tx": { "lease": LEASE_MS, "queue": { "size": { "real_time": REAL_TIME_QUEUE } } }, "tls": {
            "root_ca_certificate": path(inv, "ca.pem"),
            // Without it the client presents no certificate and the router refuses it.
            "enable_mtls": true,
            "connect_certificate": path(inv, &format!("{name}.pem")),
            "connect_private_key": path(inv, &format!("{name}.key")),
            "close_link_on_expiration": true,
        } } },
    })
}

/// `value` as a file: a header saying where it came from, then the JSON.
pub fn to_file(header: &str, value: &Value) -> String {
    let body = serde_json::to_string_pretty(value).unwrap_or_else(|_| "{}".into());
    let mut s = String::new();
    for l in header.lines() {
        s.push_str("// ");
        s.push_str(l);
        s.push('\n');
    }
    s + &body + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inv() -> Inventory {
        Inventory::parse(
            "install_dir = \"/etc/mfc/\"\nservices = [\"ctl\"]\ndevices = [\"aero-1\"]\noperators = [\"alice\"]\n[router]\nhosts = [\"10.0.0.1\"]\n",
        )
        .unwrap()
    }

    #[test]
    fn clients_dial_the_router_over_mtls_and_never_listen() {
        let inv = inv();
        let c = client(&inv, IdentityKind::Device, "aero-1");
        assert_eq!(c["mode"], "client");
        assert_eq!(
            c["connect"]["endpoints"][0],
            "quic/10.0.0.1:7447#segmentation_offload=false"
        );
        assert_eq!(c["connect"]["timeout_ms"], -1);
        // Back soon after the router: attempts 100 ms apart, each at most 500 ms.
        assert_eq!(c["connect"]["retry"]["period_max_ms"], RETRY_MAX_MS);
        assert_eq!(c["transport"]["unicast"]["open_timeout"], 500);
        assert_eq!(c["listen"]["endpoints"].as_array().unwrap().len(), 0);
        assert_eq!(c["scouting"]["multicast"]["enabled"], false);
        let tls = &c["transport"]["link"]["tls"];
        assert_eq!(tls["enable_mtls"], true);
        assert_eq!(tls["connect_certificate"], "/etc/mfc/aero-1.pem");
        assert_eq!(tls["connect_private_key"], "/etc/mfc/aero-1.key");
        let o = client(&inv, IdentityKind::Operator, "alice");
        assert_eq!(o["connect"]["timeout_ms"], OPERATOR_CONNECT_TIMEOUT_MS);
        assert_eq!(o["metadata"]["name"], "alice");
        assert_eq!(o["metadata"]["role"], "operator");
        assert_eq!(c["metadata"]["role"], "device");
    }

    #[test]
    fn the_router_requires_mtls_and_denies_by_default() {
        let inv = inv();
        let r = router(&inv, crate::acl::access_control(&inv));
        assert_eq!(r["mode"], "router");
        assert_eq!(
            r["listen"]["endpoints"][0],
            "quic/[::]:7447#segmentation_offload=false"
        );
        assert_eq!(r["transport"]["link"]["tls"]["enable_mtls"], true);
        assert_eq!(r["transport"]["link"]["tx"]["lease"], LEASE_MS);
        assert_eq!(
            r["transport"]["link"]["tls"]["listen_certificate"],
            "/etc/mfc/router.pem"
        );
        assert_eq!(r["access_control"]["default_permission"], "deny");
        let text = to_file("generated", &r);
        assert!(text.starts_with("// generated\n{"));
    }
}
