//! The table of tunable parameters against what ships: every law and output map written in
//! the shipped files (the plants' controller sets and scenarios, the Python client's example
//! service) lies within the table's sanity bounds, and the bounds read as documented.

use std::path::{Path, PathBuf};

use mfc::params::{param, PARAMS};
use mfc::{ChannelConfig, LawConfig, OutputMapConfig};

/// Every `.toml` under `dir`, recursively.
fn tomls(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.is_dir() {
            tomls(&path, out);
        } else if path.extension().is_some_and(|e| e == "toml") {
            out.push(path);
        }
    }
}

/// The laws and output maps anywhere in a file: a table with `law = "..."` (a controller
/// set's channel: its `law`, `params` and `estimator`), a `law = { ... }` table (a service
/// file's channel), and every `output = { ... }` table (scenarios, service files).
fn found(v: &toml::Value, laws: &mut Vec<LawConfig>, maps: &mut Vec<OutputMapConfig>) {
    match v {
        toml::Value::Table(t) => {
            match t.get("law") {
                Some(toml::Value::String(_)) => {
                    let mut law = toml::Table::new();
                    for k in ["law", "params", "estimator"] {
                        if let Some(x) = t.get(k) {
                            law.insert(k.into(), x.clone());
                        }
                    }
                    laws.push(law.try_into().unwrap());
                }
                Some(l @ toml::Value::Table(_)) => laws.push(l.clone().try_into().unwrap()),
                _ => {}
            }
            if let Some(o @ toml::Value::Table(_)) = t.get("output") {
                maps.push(o.clone().try_into().unwrap());
            }
            // A `[plant]` table holds no law and no output map (a Modbus map's `output` is a
            // register, not an actuator).
            t.iter()
                .filter(|(k, _)| k.as_str() != "plant")
                .for_each(|(_, x)| found(x, laws, maps));
        }
        toml::Value::Array(a) => a.iter().for_each(|x| found(x, laws, maps)),
        _ => {}
    }
}

fn within(c: &ChannelConfig, what: &Path) -> usize {
    let mut checked = 0;
    for p in PARAMS.iter().filter(|p| p.applies_to(c.law.kind())) {
        let v = p.get(c).unwrap();
        assert!(
            p.bounds.contains(v),
            "{}: {} = {v} is outside its bounds {}",
            what.display(),
            p.name,
            p.bounds
        );
        checked += 1;
    }
    checked
}

#[test]
fn every_shipped_value_lies_within_bounds() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut files = Vec::new();
    tomls(&root.join("plants"), &mut files);
    tomls(&root.join("clients/python/examples"), &mut files);
    let (mut laws_seen, mut maps_seen, mut values) = (0, 0, 0);
    for f in &files {
        let text = std::fs::read_to_string(f).unwrap();
        let v: toml::Value = toml::from_str(&text).unwrap();
        let (mut laws, mut maps) = (Vec::new(), Vec::new());
        found(&v, &mut laws, &mut maps);
        for law in laws {
            let c = ChannelConfig {
                law,
                output: OutputMapConfig::default(),
            };
            values += within(&c, f);
            laws_seen += 1;
        }
        for output in maps {
            let c = ChannelConfig {
                law: LawConfig::default(),
                output,
            };
            values += within(&c, f);
            maps_seen += 1;
        }
    }
    // What shipped when this was written (39 files, 53 laws, 34 output maps, 1158 values):
    // a file that stopped being read would show here.
    assert!(files.len() >= 39, "{} files", files.len());
    assert!(
        laws_seen >= 53 && maps_seen >= 34,
        "{laws_seen} laws, {maps_seen} maps"
    );
    assert!(values >= 1158, "{values} values checked");
}

#[test]
fn bounds_read_as_operators_write_them() {
    let shown = |name: &str| param(name).unwrap().bounds.to_string();
    assert_eq!(shown("kp"), "[-1e6, 1e6]");
    assert_eq!(shown("alpha"), "|x| in [1e-6, 1e6]");
    assert_eq!(shown("hold_after"), "[0, 1e4]");
    assert_eq!(shown("setpoint_weight"), "[0, 10]");
    assert_eq!(shown("min"), "[-inf, 0]");
    assert_eq!(shown("rate_limit"), "[1e-6, inf]");
}
