//! The tests of [`super`]: its rules case by case, kept apart so the file reads as the rules.

use super::*;

/// Whether zenoh's key-expression inclusion would let `rule_key` cover `key` (the
/// subset used here: `*` is one chunk, a trailing `**` any rest).
fn includes(rule_key: &str, key: &str) -> bool {
    let (r, k): (Vec<_>, Vec<_>) = (rule_key.split('/').collect(), key.split('/').collect());
    for (i, c) in r.iter().enumerate() {
        if *c == "**" {
            return true;
        }
        match k.get(i) {
            Some(kc) if c == kc || (*c == "*" && *kc != "**") => {}
            _ => return false,
        }
    }
    r.len() == k.len()
}

/// Whether `cn` may send (`ingress`) or receive (`egress`) `message` on `key`.
fn allowed(acl: &Value, cn: &str, flow: &str, message: &str, key: &str) -> bool {
    let subjects: Vec<&str> = acl["subjects"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|s| {
            s["cert_common_names"]
                .as_array()
                .unwrap()
                .iter()
                .any(|c| c == cn)
        })
        .map(|s| s["id"].as_str().unwrap())
        .collect();
    let rules: Vec<&str> = acl["policies"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|p| {
            p["subjects"]
                .as_array()
                .unwrap()
                .iter()
                .any(|s| subjects.contains(&s.as_str().unwrap()))
        })
        .flat_map(|p| {
            p["rules"]
                .as_array()
                .unwrap()
                .iter()
                .map(|r| r.as_str().unwrap())
        })
        .collect();
    acl["rules"].as_array().unwrap().iter().any(|r| {
        rules.contains(&r["id"].as_str().unwrap())
            && r["flows"].as_array().unwrap().iter().any(|f| f == flow)
            && r["messages"]
                .as_array()
                .unwrap()
                .iter()
                .any(|m| m == message)
            && r["key_exprs"]
                .as_array()
                .unwrap()
                .iter()
                .any(|k| includes(k.as_str().unwrap(), key))
    })
}

fn fleet() -> Value {
    let inv = Inventory::parse(
        "services = [\"ctl\"]\ndevices = [\"aero-1\", \"aero-2\"]\noperators = [\"alice\", { name = \"vera\", role = \"viewer\" }]\n[router]\nhosts = [\"10.0.0.1\"]\n",
    )
    .unwrap();
    access_control(&inv)
}

#[test]
fn the_control_loop_is_allowed_end_to_end() {
    let acl = fleet();
    for d in ["aero-1", "aero-2"] {
        // A sample: in from the plant, out to the service.
        assert!(allowed(&acl, d, "ingress", "put", &dev(d, "sample")));
        assert!(allowed(&acl, "ctl", "egress", "put", &dev(d, "sample")));
        // A command: in from the service, out to the plant.
        assert!(allowed(&acl, "ctl", "ingress", "put", &dev(d, "command")));
        assert!(allowed(&acl, d, "egress", "put", &dev(d, "command")));
        // The plant's subscription and token.
        assert!(allowed(
            &acl,
            d,
            "ingress",
            "declare_subscriber",
            &dev(d, "command")
        ));
        assert!(allowed(
            &acl,
            d,
            "ingress",
            "liveliness_token",
            &format!("{P}/alive/plant/{d}")
        ));
    }
    // The trap: the service's wildcard subscription, both ways.
    let wild = dev("*", "sample");
    assert!(allowed(&acl, "ctl", "ingress", "declare_subscriber", &wild));
    assert!(allowed(
        &acl,
        "aero-1",
        "egress",
        "declare_subscriber",
        &wild
    ));
    assert!(allowed(
        &acl,
        "ctl",
        "ingress",
        "liveliness_token",
        &format!("{P}/alive/controller/ctl")
    ));
}

#[test]
fn a_gateway_speaks_for_its_own_plants_batches_only() {
    use protocol::keys;
    let inv = Inventory::parse(
        "services = [\"ctl\"]\ndevices = [\"aero-1\"]\n[router]\nhosts = [\"10.0.0.1\"]\n[[gateways]]\nid = \"cell-1\"\nplants = [\"heater-1\", \"heater-2\"]\n[[gateways]]\nid = \"cell-2\"\nplants = [\"heater-3\"]\n",
    )
    .unwrap();
    let acl = access_control(&inv);
    let (g, other) = ("cell-1", "cell-2");
    // The loop, end to end: batches in from the gateway and out to the service,
    // commands in from the service and out to the gateway, both subscriptions seen.
    for (cn, flow, m, k) in [
        (g, "ingress", "put", keys::shard_gateway_samples(g)),
        (g, "ingress", "put", keys::gateway_samples(g)),
        ("ctl", "egress", "put", keys::shard_gateway_samples(g)),
        ("ctl", "ingress", "put", keys::gateway_commands(g)),
        (g, "egress", "put", keys::gateway_commands(g)),
        (
            g,
            "ingress",
            "declare_subscriber",
            keys::gateway_commands(g),
        ),
        (
            "ctl",
            "egress",
            "declare_subscriber",
            keys::gateway_commands(g),
        ),
        (
            g,
            "egress",
            "declare_subscriber",
            keys::all_gateways("samples"),
        ),
        (
            g,
            "ingress",
            "liveliness_token",
            keys::alive_plant("heater-1"),
        ),
        (
            g,
            "ingress",
            "liveliness_token",
            keys::alive_plant("heater-2"),
        ),
    ] {
        assert!(allowed(&acl, cn, flow, m, &k), "{cn} {flow} {m} {k}");
    }
    // Nothing of another gateway, of a single device, of a plant it does not host;
    // no command, no configuration.
    for (flow, m, k) in [
        ("ingress", "put", keys::shard_gateway_samples(other)),
        ("ingress", "put", keys::gateway_samples(other)),
        ("ingress", "put", keys::gateway_commands(g)),
        ("ingress", "put", dev("aero-1", "sample")),
        ("ingress", "put", sdev("heater-1", "sample")),
        ("ingress", "put", dev("heater-1", "command")),
        ("ingress", "put", dev("heater-1", "reference")),
        (
            "ingress",
            "declare_subscriber",
            keys::gateway_commands(other),
        ),
        ("ingress", "declare_subscriber", dev("heater-1", "command")),
        ("ingress", "liveliness_token", keys::alive_plant("heater-3")),
        ("ingress", "liveliness_token", keys::alive_plant("aero-1")),
        ("ingress", "query", dev("heater-1", "config")),
        ("ingress", "declare_queryable", dev("heater-1", "status")),
        ("egress", "put", keys::gateway_commands(other)),
        ("egress", "put", dev("aero-1", "command")),
    ] {
        assert!(!allowed(&acl, g, flow, m, &k), "{g} may {flow} {m} {k}");
    }
    // A device's certificate cannot pass for a gateway either.
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "put",
        &keys::shard_gateway_samples(g)
    ));
}

#[test]
fn a_service_joins_a_fleet_under_its_own_name_only() {
    let inv = Inventory::parse(
        "services = [\"ctl-a\", \"ctl-b\"]\ndevices = [\"aero-1\"]\n[router]\nhosts = [\"10.0.0.1\"]\n",
    )
    .unwrap();
    let acl = access_control(&inv);
    let f = |rest: &str| format!("{P}/fleet/f/{rest}");
    // What a member declares and sends, under its own name: allowed.
    for (m, k) in [
        ("liveliness_token", f("member/ctl-a")),
        ("declare_queryable", f("member/ctl-a/shard/*")),
        ("reply", f("member/ctl-a/shard/7")),
        ("declare_liveliness_subscriber", f("member/*")),
        ("liveliness_query", f("member/*")),
        ("query", f("member/ctl-b/shard/7")),
    ] {
        assert!(allowed(&acl, "ctl-a", "ingress", m, &k), "{m} {k}");
    }
    // ... and what it hears of the others.
    for (m, k) in [
        ("liveliness_token", f("member/ctl-b")),
        ("query", f("member/ctl-a/shard/7")),
        ("reply", f("member/ctl-b/shard/7")),
    ] {
        assert!(allowed(&acl, "ctl-a", "egress", m, &k), "{m} {k}");
    }
    // Another member's name, a made-up one, a wildcard: refused.
    for (m, k) in [
        ("liveliness_token", f("member/ctl-b")),
        ("liveliness_token", f("member/ctl-z")),
        ("liveliness_token", f("member/*")),
        ("liveliness_token", format!("{P}/fleet/**")),
        ("declare_queryable", f("member/ctl-b/shard/*")),
        ("reply", f("member/ctl-b/shard/7")),
        ("declare_queryable", f("**")),
        // Owners' changes travel as sealed handover queries now: no put on the
        // fleet's keys at all.
        ("put", f("sync/7")),
        ("declare_subscriber", f("sync/*")),
    ] {
        assert!(!allowed(&acl, "ctl-a", "ingress", m, &k), "{m} {k}");
    }
    // No wildcard over leaves: only the queried ones are served.
    for k in [
        sdev("*", "*"),
        dev("*", "*"),
        sdev("*", "sample"),
        dev("*", "command"),
    ] {
        assert!(
            !allowed(&acl, "ctl-a", "ingress", "declare_queryable", &k),
            "{k}"
        );
        assert!(!allowed(&acl, "ctl-a", "ingress", "reply", &k), "{k}");
    }
    for leaf in QUERIED {
        assert!(allowed(
            &acl,
            "ctl-a",
            "ingress",
            "declare_queryable",
            &sdev("*", leaf)
        ));
        assert!(allowed(
            &acl,
            "ctl-a",
            "ingress",
            "declare_queryable",
            &dev("*", leaf)
        ));
    }
}

#[test]
fn a_device_cannot_touch_another_devices_keys_nor_command_itself() {
    let acl = fleet();
    for leaf in [
        "sample",
        "command",
        "reference",
        "config",
        "status",
        "envelope",
    ] {
        let k = dev("aero-2", leaf);
        for m in [
            "put",
            "delete",
            "declare_subscriber",
            "query",
            "declare_queryable",
            "reply",
        ] {
            assert!(!allowed(&acl, "aero-1", "ingress", m, &k), "{m} {k}");
        }
    }
    assert!(!allowed(
        &acl,
        "aero-1",
        "egress",
        "put",
        &dev("aero-2", "sample")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "egress",
        "put",
        &dev("aero-2", "command")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "put",
        &dev("aero-1", "command")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "put",
        &dev("aero-1", "reference")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "query",
        &dev("aero-1", "config")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "declare_subscriber",
        &dev("*", "sample")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "liveliness_token",
        &format!("{P}/alive/plant/aero-2")
    ));
    assert!(!allowed(
        &acl,
        "aero-1",
        "ingress",
        "liveliness_token",
        &format!("{P}/alive/controller/ctl")
    ));
}

#[test]
fn operators_ask_under_their_own_name_only() {
    let acl = fleet();
    let ok = |cn: &str, flow: &str, msg: &str, key: &str| allowed(&acl, cn, flow, msg, key);
    let by = |key: String, who: &str| protocol::keys::by(&key, who);
    for leaf in QUERIED {
        let (key, sharded) = (dev("aero-1", leaf), sdev("aero-1", leaf));
        let served = protocol::keys::served(&dev("*", leaf));
        // Under its own name, with or without the shard; the service declares,
        // receives and replies on the same keys.
        let mine = by(key.clone(), "alice");
        assert!(ok("alice", "ingress", "query", &mine));
        assert!(ok("alice", "ingress", "query", &by(sharded, "alice")));
        assert!(ok("ctl", "egress", "query", &mine));
        assert!(ok("ctl", "ingress", "reply", &mine));
        assert!(ok("alice", "egress", "reply", &mine));
        assert!(ok("ctl", "ingress", "declare_queryable", &served));
        assert!(ok("alice", "egress", "declare_queryable", &served));
        // Never as another operator, nor as nobody: the name a service reads is the
        // certificate's.
        assert!(!ok("alice", "ingress", "query", &by(key.clone(), "vera")));
        assert!(!ok("alice", "ingress", "query", &key));
        assert!(!ok("alice", "ingress", "query", &by(key.clone(), "*")));
        assert!(!ok("alice", "egress", "reply", &by(key.clone(), "vera")));
        assert!(ok("vera", "ingress", "query", &by(key, "vera")));
    }
    // A viewer cannot even put a reference (the services refuse its changes too).
    let reference = |who: &str| by(dev("aero-1", "reference"), who);
    assert!(ok("alice", "ingress", "put", &reference("alice")));
    assert!(!ok("vera", "ingress", "put", &reference("vera")));
    assert!(!ok("alice", "ingress", "put", &reference("vera")));
    assert!(!ok("alice", "ingress", "put", &dev("aero-1", "reference")));
    assert!(ok("ctl", "egress", "put", &reference("alice")));
}

#[test]
fn a_console_asks_for_its_people_only_as_each_may() {
    let inv = Inventory::parse(
        "services = [\"ctl\"]\ndevices = [\"aero-1\"]\noperators = [\"alice\", \"bob\", { name = \"vera\", role = \"viewer\" }]\nconsoles = [{ name = \"desk\", hosts = [\"10.0.0.9\"], people = [\"alice\", \"vera\"] }]\n[router]\nhosts = [\"10.0.0.1\"]\n",
    )
    .unwrap();
    let acl = access_control(&inv);
    let ok = |flow: &str, msg: &str, key: &str| allowed(&acl, "desk", flow, msg, key);
    let by = |key: String, who: &str| protocol::keys::by(&key, who);
    for leaf in QUERIED {
        let key = dev("aero-1", leaf);
        // Its own name (its polls) and its people's; nobody else's, nor nobody's.
        for who in ["desk", "alice", "vera"] {
            assert!(
                ok("ingress", "query", &by(key.clone(), who)),
                "{leaf} {who}"
            );
            assert!(ok("egress", "reply", &by(key.clone(), who)), "{leaf} {who}");
        }
        assert!(!ok("ingress", "query", &by(key.clone(), "bob")), "{leaf}");
        assert!(!ok("ingress", "query", &key), "{leaf}");
    }
    // References: for alice (an operator), not for vera (a viewer) nor as itself.
    let reference = |who: &str| by(dev("aero-1", "reference"), who);
    assert!(ok("ingress", "put", &reference("alice")));
    assert!(!ok("ingress", "put", &reference("vera")));
    assert!(!ok("ingress", "put", &reference("desk")));
    assert!(!ok("ingress", "put", &reference("bob")));
    // Like any operator, never a command.
    assert!(!ok("ingress", "put", &dev("aero-1", "command")));
    // alice's own certificate is unchanged: her name only.
    assert!(!allowed(
        &acl,
        "alice",
        "ingress",
        "query",
        &by(dev("aero-1", "config"), "desk")
    ));
}

#[test]
fn operators_steer_and_watch_but_never_command() {
    let acl = fleet();
    assert!(allowed(
        &acl,
        "alice",
        "ingress",
        "query",
        &format!("{P}/service/*/status")
    ));
    assert!(allowed(
        &acl,
        "ctl",
        "egress",
        "query",
        &format!("{P}/service/*/status")
    ));
    assert!(allowed(
        &acl,
        "alice",
        "ingress",
        "declare_subscriber",
        &dev("aero-1", "sample")
    ));
    assert!(allowed(
        &acl,
        "alice",
        "ingress",
        "liveliness_query",
        &format!("{P}/alive/plant/*")
    ));
    assert!(!allowed(
        &acl,
        "alice",
        "ingress",
        "put",
        &dev("aero-1", "command")
    ));
    assert!(!allowed(
        &acl,
        "alice",
        "ingress",
        "put",
        &dev("aero-1", "sample")
    ));
    assert!(!allowed(
        &acl,
        "alice",
        "ingress",
        "declare_queryable",
        &dev("aero-1", "config")
    ));
    // Unknown names get nothing.
    assert!(!allowed(
        &acl,
        "mallory",
        "ingress",
        "put",
        &dev("aero-1", "sample")
    ));
    assert!(!allowed(
        &acl,
        "router",
        "ingress",
        "put",
        &dev("aero-1", "sample")
    ));
}

#[test]
fn the_inclusion_model_matches_zenoh_on_the_cases_used() {
    assert!(includes("mfc/v1/device/*/sample", "mfc/v1/device/a/sample"));
    assert!(includes("mfc/v1/device/*/sample", "mfc/v1/device/*/sample"));
    assert!(!includes(
        "mfc/v1/device/a/sample",
        "mfc/v1/device/*/sample"
    ));
    assert!(includes("mfc/v1/alive/**", "mfc/v1/alive/plant/a"));
    assert!(!includes("mfc/v1/device/*/sample", "mfc/v1/device/**"));
}
