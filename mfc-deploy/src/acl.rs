//! The router's access control, generated from the inventory.
//!
//! zenoh's access control is enforced by the router, per message, on the link the message
//! enters (`ingress`) and on the link it leaves by (`egress`), and a message passes only if
//! an `allow` rule's key expression *includes* its key. It has no per-subject substitution
//! (no "a device may use its own keys"), so every device gets rules of its own, with its
//! certificate's common name as the subject. Everything not allowed is denied.
//!
//! What each role may do (`*` is one chunk, any device or service):
//!
//! | role | sends (ingress) | receives (egress) |
//! |---|---|---|
//! | device `d` | put `device/d/sample` and `shard/{s}/device/d/sample` (`s` its shard, where the agent publishes); subscribe `device/d/command`; token `alive/plant/d` | put `device/d/command`; the services' subscriptions `device/*/sample`, `shard/*/device/*/sample` |
//! | service `s` | put `device/*/command`, `gateway/*/commands`, `group/**`; subscribe `device/*/sample`, `device/*/reference/**`, `shard/*/device/*/sample`, `gateway/*/samples`, `group/**`, the members `fleet/*/member/*`; serve and reply on `device/*/{leaf}/**` for each of `config,status,envelope,reference,audit` (the leaf and the operators' `…/by/{o}` below it) and the same under `shard/*/` (no wildcard leaf); query other members' `fleet/*/member/*/shard/*`; tokens `alive/controller/s`, `alive/instance/s/*` (one per process, watched: two processes of one name see each other) and `fleet/*/member/s`, handover queryable `fleet/*/member/s/shard/*` and status queryable `service/s/status`, under its own name only | samples, batches, references, heartbeats, fleet traffic, queries, the agents' and operators' declarations |
//! | gateway `g` hosting plants `p…` | put `gateway/g/samples` and `shard/{s}/gateway/g/samples` (`s` its shard); subscribe `gateway/g/commands`; tokens `alive/plant/p` for each of its plants | put `gateway/g/commands`; the services' subscriptions `gateway/*/samples`, `shard/*/gateway/*/samples` |
//! | operator `o` | query `device/*/{config,status,envelope,reference,audit}/by/o` (and under `shard/*/`), `service/*/status`; put `device/*/reference/by/o` (not a viewer): under its own name only; subscribe samples and commands (watch); liveliness queries | replies, samples, commands, tokens |
//!
//! So a device holding its own certificate can neither put on nor watch another device's
//! keys, cannot command even itself, and cannot change any configuration (a gateway's
//! likewise, for its plants' batches: no single plant's keys, no other gateway's); an operator can
//! steer and tune but never puts a command or a sample; only services command.
//!
//! Traps this avoids: the service subscribes with a wildcard (`device/*/sample`), so the
//! wildcard must be allowed explicitly (with per-device rules only, control silently stops:
//! the plants run on their fallback); and the egress side of every flow needs its own rule.

use serde_json::{json, Value};

use crate::inventory::Inventory;

const P: &str = protocol::keys::PREFIX;

/// The `device/*/…` keys a service serves as queryables and an operator queries.
const QUERIED: [&str; 6] = protocol::keys::QUERIED_LEAVES;

fn dev(id: &str, leaf: &str) -> String {
    format!("{P}/device/{id}/{leaf}")
}

/// `shard/{s}/device/{id}/{leaf}` with `s` the id's shard, or `*` for a wildcard id.
fn sdev(id: &str, leaf: &str) -> String {
    if id == "*" {
        format!("{P}/shard/*/device/*/{leaf}")
    } else {
        protocol::keys::shard_device(id, leaf)
    }
}

/// One rule: `messages` on `keys`, in `flows`.
fn rule(id: String, flows: &[&str], messages: &[&str], keys: Vec<String>) -> Value {
    json!({
        "id": id,
        "permission": "allow",
        "flows": flows,
        "messages": messages,
        "key_exprs": keys,
    })
}

/// The `access_control` section of the router's config.
pub fn access_control(inv: &Inventory) -> Value {
    let mut acl = Acl::default();
    for d in &inv.devices {
        acl.policy(format!("device-{d}"), vec![d.clone()], device_rules(d));
    }
    for g in &inv.gateways {
        acl.policy(
            format!("gateway-{}", g.id),
            vec![g.id.clone()],
            gateway_rules(&g.id, &g.plants),
        );
    }
    let keys = SharedKeys::new();
    let service_ids = acl.add(service_rules(&keys));
    for s in &inv.services {
        let mut ids = service_ids.clone();
        ids.extend(acl.add(service_own_rules(s)));
        acl.policy_of(format!("service-{s}"), vec![s.clone()], ids);
    }
    if !inv.operators.is_empty() {
        let shared = acl.add(operator_rules(&keys));
        for o in &inv.operators {
            let mut ids = shared.clone();
            ids.extend(acl.add(operator_own_rules(&o.name, o.role != "viewer")));
            acl.policy_of(format!("operator-{}", o.name), vec![o.name.clone()], ids);
        }
        // A console: what any operator may, its own name (a viewer's: its polls), and
        // each of its people's names as they may use them (the rules added above).
        for c in &inv.consoles {
            let mut ids = shared.clone();
            ids.extend(acl.add(operator_own_rules(&c.name, false)));
            for p in &c.people {
                let steer = inv
                    .operators
                    .iter()
                    .any(|o| &o.name == p && o.role != "viewer");
                ids.extend(own_rule_ids(p, steer));
            }
            acl.policy_of(format!("console-{}", c.name), vec![c.name.clone()], ids);
        }
    }
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": acl.rules,
        "subjects": acl.subjects,
        "policies": acl.policies,
    })
}

/// The three lists of zenoh's access control, filled role by role.
#[derive(Default)]
struct Acl {
    rules: Vec<Value>,
    subjects: Vec<Value>,
    policies: Vec<Value>,
}

impl Acl {
    /// Add `rules`; their ids, for a policy.
    fn add(&mut self, rules: Vec<Value>) -> Vec<String> {
        let ids = rules
            .iter()
            .map(|r| r["id"].as_str().unwrap_or_default().to_string())
            .collect();
        self.rules.extend(rules);
        ids
    }

    /// Add `rules` and a subject `name` (these certificates' common names) bound to them.
    fn policy(&mut self, name: String, cns: Vec<String>, rules: Vec<Value>) {
        let ids = self.add(rules);
        self.policy_of(name, cns, ids);
    }

    /// A subject `name` bound to rules already added.
    fn policy_of(&mut self, name: String, cns: Vec<String>, rule_ids: Vec<String>) {
        self.subjects
            .push(json!({ "id": name.clone(), "cert_common_names": cns }));
        self.policies
            .push(json!({ "id": name.clone(), "rules": rule_ids, "subjects": [name] }));
    }
}

/// Key sets that several roles' rules name.
struct SharedKeys {
    /// What services serve as queryables (and answer): every device's queried leaves, with
    /// and without the shard; no wildcard over leaves (a service declares one queryable
    /// per queried leaf, so the leaves it does not serve stay closed).
    served: Vec<String>,
    /// `served` and the services' status keys: what may be queried.
    queried: Vec<String>,
}

impl SharedKeys {
    fn new() -> Self {
        // Each leaf and the operators' keys below it (`…/{leaf}/by/{operator}`): what a
        // service declares (`protocol::keys::served`) and replies on.
        let mut served: Vec<String> = QUERIED
            .iter()
            .map(|l| protocol::keys::served(&dev("*", l)))
            .collect();
        served.extend(
            QUERIED
                .iter()
                .map(|l| protocol::keys::served(&sdev("*", l))),
        );
        let mut queried = served.clone();
        queried.push(format!("{P}/service/*/status"));
        Self { served, queried }
    }
}

/// A device's own keys only.
fn device_rules(d: &str) -> Vec<Value> {
    let r = |n: &str| format!("device-{d}-{n}");
    vec![
        rule(
            r("put-sample"),
            &["ingress"],
            &["put"],
            vec![dev(d, "sample"), sdev(d, "sample")],
        ),
        rule(
            r("sub-command"),
            &["ingress"],
            &["declare_subscriber"],
            vec![dev(d, "command")],
        ),
        rule(
            r("token"),
            &["ingress"],
            &["liveliness_token"],
            vec![format!("{P}/alive/plant/{d}")],
        ),
        rule(
            r("get-command"),
            &["egress"],
            &["put"],
            vec![dev(d, "command")],
        ),
        // The services' wildcard subscription, declared towards the agent: without it the
        // agent's samples have nowhere to go.
        rule(
            r("see-subscription"),
            &["egress"],
            &["declare_subscriber"],
            vec![dev("*", "sample"), sdev("*", "sample")],
        ),
    ]
}

/// A gateway's own batch keys, and its plants' liveliness tokens.
fn gateway_rules(g: &str, plants: &[String]) -> Vec<Value> {
    let r = |n: &str| format!("gateway-{g}-{n}");
    let commands = protocol::keys::gateway_commands(g);
    vec![
        rule(
            r("put-samples"),
            &["ingress"],
            &["put"],
            vec![
                protocol::keys::gateway_samples(g),
                protocol::keys::shard_gateway_samples(g),
            ],
        ),
        rule(
            r("sub-commands"),
            &["ingress"],
            &["declare_subscriber"],
            vec![commands.clone()],
        ),
        // Each hosted plant announces itself as a single rig would.
        rule(
            r("tokens"),
            &["ingress"],
            &["liveliness_token"],
            plants
                .iter()
                .map(|p| protocol::keys::alive_plant(p))
                .collect(),
        ),
        rule(r("get-commands"), &["egress"], &["put"], vec![commands]),
        // The services' wildcard subscriptions, declared towards the gateway.
        rule(
            r("see-subscription"),
            &["egress"],
            &["declare_subscriber"],
            vec![
                protocol::keys::all_gateways("samples"),
                format!("{P}/shard/*/gateway/*/samples"),
            ],
        ),
    ]
}

/// A fleet's member tokens, `fleet/*/member/*`.
fn members() -> String {
    format!("{P}/fleet/*/member/*")
}

/// Every member's handover queryables, `fleet/*/member/*/shard/*`.
fn handovers() -> String {
    format!("{P}/fleet/*/member/*/shard/*")
}

/// What every service may do: every device (several services share a fleet, issue 11).
/// In a fleet, it may see every member and ask any of them for a shard, but declare a
/// member token and a handover queryable only under its own name
/// ([`service_own_rules`]): a service certificate cannot make up members.
fn service_rules(keys: &SharedKeys) -> Vec<Value> {
    let group = format!("{P}/group/**");
    let gw_samples = format!("{P}/gateway/*/samples");
    let shard_gw_samples = format!("{P}/shard/*/gateway/*/samples");
    vec![
        rule(
            "service-send".into(),
            &["ingress"],
            &["put"],
            vec![
                dev("*", "command"),
                format!("{P}/gateway/*/commands"),
                group.clone(),
            ],
        ),
        rule(
            "service-subscribe".into(),
            &["ingress"],
            &["declare_subscriber", "declare_liveliness_subscriber"],
            vec![
                dev("*", "sample"),
                sdev("*", "sample"),
                gw_samples.clone(),
                shard_gw_samples.clone(),
                references(),
                group.clone(),
                members(),
            ],
        ),
        // Members of a fleet: who is in it, and asking another member for a shard.
        rule(
            "service-fleet-ask".into(),
            &["ingress"],
            &["liveliness_query", "query"],
            vec![members(), handovers()],
        ),
        // What the other members send and declare, towards this one.
        rule(
            "service-fleet-hear".into(),
            &["egress"],
            &[
                "liveliness_token",
                "declare_liveliness_subscriber",
                "declare_queryable",
                "declare_subscriber",
                "query",
                "reply",
                "put",
            ],
            vec![members(), handovers()],
        ),
        // The agents' and gateways' command subscriptions, declared towards the service.
        rule(
            "service-see-subscriptions".into(),
            &["egress"],
            &["declare_subscriber"],
            vec![
                dev("*", "command"),
                format!("{P}/gateway/*/commands"),
                group.clone(),
            ],
        ),
        rule(
            "service-serve".into(),
            &["ingress"],
            &["declare_queryable", "reply"],
            keys.served.clone(),
        ),
        rule(
            "service-receive".into(),
            &["egress"],
            &["put"],
            vec![
                dev("*", "sample"),
                sdev("*", "sample"),
                gw_samples,
                shard_gw_samples,
                references(),
                group,
            ],
        ),
        rule(
            "service-queried".into(),
            &["egress"],
            &["query"],
            keys.queried.clone(),
        ),
    ]
}

/// A service's own liveliness token and status queryable, and in a fleet its own member
/// token and handover queryable.
fn service_own_rules(s: &str) -> Vec<Value> {
    vec![
        rule(
            format!("service-{s}-member"),
            &["ingress"],
            &["liveliness_token"],
            vec![format!("{P}/fleet/*/member/{s}")],
        ),
        rule(
            format!("service-{s}-handover"),
            &["ingress"],
            &["declare_queryable", "reply"],
            vec![format!("{P}/fleet/*/member/{s}/shard/*")],
        ),
        rule(
            format!("service-{s}-own"),
            &["ingress"],
            &["declare_queryable", "reply"],
            vec![format!("{P}/service/{s}/status")],
        ),
        rule(
            format!("service-{s}-token"),
            &["ingress"],
            &["liveliness_token"],
            vec![format!("{P}/alive/controller/{s}")],
        ),
        // One token per process under its own name, and the watch on the others: two
        // processes with this name (a copied bundle) see each other and warn.
        rule(
            format!("service-{s}-instance"),
            &["ingress"],
            &[
                "liveliness_token",
                "declare_liveliness_subscriber",
                "liveliness_query",
            ],
            vec![protocol::keys::alive_instances(s)],
        ),
        rule(
            format!("service-{s}-twins"),
            &["egress"],
            &["liveliness_token", "reply"],
            vec![protocol::keys::alive_instances(s)],
        ),
    ]
}

/// Every device's reference puts, named or not: what services subscribe to.
fn references() -> String {
    protocol::keys::served(&dev("*", "reference"))
}

/// What every operator may do whoever it is: the services' status, watching samples and
/// commands, liveliness, and seeing the services' declarations. Requests on a device go
/// under the operator's own name only ([`operator_own_rules`]).
fn operator_rules(keys: &SharedKeys) -> Vec<Value> {
    let alive = format!("{P}/alive/**");
    let watched = vec![dev("*", "sample"), sdev("*", "sample"), dev("*", "command")];
    let status = vec![format!("{P}/service/*/status")];
    vec![
        rule(
            "operator-services".into(),
            &["ingress"],
            &["query"],
            status.clone(),
        ),
        rule(
            "operator-watch".into(),
            &["ingress"],
            &["declare_subscriber"],
            watched.clone(),
        ),
        rule(
            "operator-liveliness".into(),
            &["ingress"],
            &["liveliness_query", "declare_liveliness_subscriber"],
            vec![alive.clone()],
        ),
        rule(
            "operator-services-replies".into(),
            &["egress"],
            &["reply", "declare_queryable"],
            status,
        ),
        rule(
            "operator-see-queryables".into(),
            &["egress"],
            &["declare_queryable"],
            keys.served.clone(),
        ),
        rule("operator-see".into(), &["egress"], &["put"], watched),
        rule(
            "operator-tokens".into(),
            &["egress"],
            &["liveliness_token", "reply"],
            vec![alive],
        ),
        rule(
            "operator-see-subscription".into(),
            &["egress"],
            &["declare_subscriber"],
            vec![references()],
        ),
    ]
}

/// Operator `name`'s requests on devices: queries (and their replies) on every queried
/// leaf under its own name only (`…/{leaf}/by/{name}`, with or without the shard), and
/// reference puts likewise if it may change anything (`steer`: not a viewer). So a
/// certificate cannot ask as another operator, nor as nobody: the name a service reads
/// in a request's key is the certificate's.
fn operator_own_rules(name: &str, steer: bool) -> Vec<Value> {
    let ids = own_rule_ids(name, steer);
    let own = |key: String| protocol::keys::by(&key, name);
    let mut asked: Vec<String> = QUERIED.iter().map(|l| own(dev("*", l))).collect();
    asked.extend(QUERIED.iter().map(|l| own(sdev("*", l))));
    let mut rules = vec![
        rule(ids[0].clone(), &["ingress"], &["query"], asked.clone()),
        rule(ids[1].clone(), &["egress"], &["reply"], asked),
    ];
    if steer {
        rules.push(rule(
            ids[2].clone(),
            &["ingress"],
            &["put"],
            vec![own(dev("*", "reference"))],
        ));
    }
    rules
}

/// The ids of [`operator_own_rules`]`(name, steer)`: query, replies, and steer if it may.
fn own_rule_ids(name: &str, steer: bool) -> Vec<String> {
    let mut ids = vec![
        format!("operator-{name}-query"),
        format!("operator-{name}-replies"),
    ];
    if steer {
        ids.push(format!("operator-{name}-steer"));
    }
    ids
}

#[cfg(test)]
mod tests {
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
}
