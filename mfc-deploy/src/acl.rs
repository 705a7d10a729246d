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
mod tests;
