//! Write a fleet's bundles: one directory per host role, each holding exactly what that
//! host needs, and nothing another host's compromise would reveal.
//!
//! ```text
//! OUT/ca/ca.pem ca.key fleet.secret    the CA and the fleet's secret (keep both here only)
//! OUT/router/zenohd.json5 router.pem router.key ca.pem
//! OUT/services/ID/ID.json5 ID.pem ID.key ca.pem fleet.secret
//!                   ID.access.toml     operators' roles and the audit file, for its config
//! OUT/devices/ID/…   ID.auth            the device's message key
//! OUT/operators/ID/… ID.auth            the operators' reply key
//! OUT/gateways/ID/…  ID.auth            the gateway's batch key (its plants have none)
//! OUT/acl.json5                        the access control, for review (also in zenohd.json5)
//! OUT/retired/…                        bundles of names no longer in the inventory
//! ```
//!
//! Every bundle is copied as it is to the inventory's `install_dir` on its host. Running
//! again keeps every certificate that is still right, so adding a device issues one
//! certificate and rewrites only the router's config.

use std::fs;
use std::path::{Path, PathBuf};

use serde::Serialize;
use time::{Duration, OffsetDateTime};

use crate::inventory::{IdentityKind, Inventory};
use crate::pki::{Ca, Usage};
use crate::{acl, configs, DeployError};

/// What happened to one certificate.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(tag = "action", content = "reason", rename_all = "lowercase")]
pub enum CertAction {
    /// There was none: issued.
    Issued,
    /// Still right: kept as it is.
    Kept,
    /// Reissued, with the reason (wrong name, other CA, expiring, asked to rotate).
    Reissued(String),
}

/// One identity's outcome.
#[derive(Debug, Clone, Serialize)]
pub struct Entry {
    /// Its role.
    pub role: IdentityKind,
    /// Its name (the certificate's CN).
    pub name: String,
    /// What was done.
    #[serde(flatten)]
    pub action: CertAction,
    /// Whether its zenoh config changed (another router address, port or install_dir; for
    /// the router, the access control): the bundle must be copied again even if its
    /// certificate was kept.
    pub config_changed: bool,
    /// The bundle to copy to the host's install directory.
    pub bundle: PathBuf,
}

impl Entry {
    /// Whether this bundle must be copied to its host again.
    pub fn to_copy(&self) -> bool {
        self.action != CertAction::Kept || self.config_changed
    }
}

/// What a run did.
#[derive(Debug, Clone, Serialize)]
pub struct DeployReport {
    /// The CA: issued or kept.
    pub ca: CertAction,
    /// Every identity, router first.
    pub entries: Vec<Entry>,
    /// Bundles moved to `retired/` because their names left the inventory.
    pub retired: Vec<PathBuf>,
    /// Where the router's config is (restart zenohd after any change in it).
    pub router_config: PathBuf,
}

impl DeployReport {
    /// Whether the router must be given its new bundle and restarted: its certificate or
    /// its config (the access control: a name added or removed) changed, or the CA is new.
    /// A client's rotation alone does not need it (same CA, same name).
    pub fn router_restart(&self) -> bool {
        self.ca != CertAction::Kept
            || self
                .entries
                .iter()
                .any(|e| e.role == IdentityKind::Router && e.to_copy())
    }
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DeployError + '_ {
    move |e| DeployError::Io {
        path: path.to_path_buf(),
        reason: e.to_string(),
    }
}

fn write(path: &Path, text: &str, secret: bool) -> Result<(), DeployError> {
    if let Some(dir) = path.parent() {
        fs::create_dir_all(dir).map_err(io(dir))?;
    }
    // A key is created 0600 before a byte of it is written (an existing file is narrowed
    // first: `mode` applies only to a file being created).
    #[cfg(unix)]
    {
        use std::io::Write;
        use std::os::unix::fs::OpenOptionsExt;
        if secret && path.exists() {
            use std::os::unix::fs::PermissionsExt;
            fs::set_permissions(path, fs::Permissions::from_mode(0o600)).map_err(io(path))?;
        }
        let mut f = fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .mode(if secret { 0o600 } else { 0o644 })
            .open(path)
            .map_err(io(path))?;
        f.write_all(text.as_bytes()).map_err(io(path))?;
        if secret {
            use std::os::unix::fs::PermissionsExt;
            fs::set_permissions(path, fs::Permissions::from_mode(0o600)).map_err(io(path))?;
        }
        Ok(())
    }
    #[cfg(not(unix))]
    {
        let _ = secret;
        fs::write(path, text).map_err(io(path))
    }
}

fn read(path: &Path) -> Result<Option<String>, DeployError> {
    match fs::read_to_string(path) {
        Ok(s) => Ok(Some(s)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(io(path)(e)),
    }
}

/// The bundle directory of an identity.
pub fn bundle_dir(out: &Path, role: IdentityKind, name: &str) -> PathBuf {
    match role {
        IdentityKind::Router => out.join(role.dir()),
        _ => out.join(role.dir()).join(name),
    }
}

/// Generate (or bring up to date) the bundles of `inv` in `out`. `rotate` names
/// identities whose key and certificate are replaced even if still right. `now` is the
/// clock (passed in, so tests can age certificates).
pub fn generate(
    inv: &Inventory,
    out: &Path,
    rotate: &[String],
    now: OffsetDateTime,
) -> Result<DeployReport, DeployError> {
    let identities = inv.identities();
    if let Some(unknown) = rotate
        .iter()
        .find(|r| !identities.iter().any(|(_, n)| n == *r))
    {
        return Err(DeployError::Inventory(format!(
            "cannot rotate {unknown:?}: not in the inventory"
        )));
    }
    let (ca, ca_action) = load_or_create_ca(inv, out, now)?;
    let secret = load_or_create_secret(out)?;
    let mut entries = Vec::new();
    for (role, name) in &identities {
        entries.push(bundle(
            inv,
            out,
            &ca,
            (*role, name),
            rotate.contains(name),
            now,
        )?);
        write_message_key(&secret, out, *role, name)?;
    }
    write(
        &out.join("acl.json5"),
        &configs::to_file(
            "The router's access control (also inside router/zenohd.json5), for review.",
            &acl::access_control(inv),
        ),
        false,
    )?;
    Ok(DeployReport {
        ca: ca_action,
        entries,
        retired: retire_departed(out, &identities)?,
        router_config: out.join("router/zenohd.json5"),
    })
}

/// The CA: loaded if present, created if absent, never silently replaced; refused if it
/// expires within the renewal margin.
fn load_or_create_ca(
    inv: &Inventory,
    out: &Path,
    now: OffsetDateTime,
) -> Result<(Ca, CertAction), DeployError> {
    let (ca_cert, ca_key) = (out.join("ca/ca.pem"), out.join("ca/ca.key"));
    let (ca, ca_action) = match (read(&ca_cert)?, read(&ca_key)?) {
        (Some(c), Some(k)) => (Ca::load(&c, &k)?, CertAction::Kept),
        (None, None) => {
            let ca = Ca::create("mfc fleet CA", inv.ca_days, now)?;
            write(&ca_key, &ca.key_pem, true)?;
            write(&ca_cert, &ca.cert_pem, false)?;
            (ca, CertAction::Issued)
        }
        _ => {
            return Err(DeployError::Pki(format!(
                "{} and {} must both exist or both be absent (a CA cannot be half restored)",
                ca_cert.display(),
                ca_key.display()
            )))
        }
    };
    if ca.not_after()? - Duration::days(inv.renew_days.into()) <= now {
        return Err(DeployError::Pki(format!(
            "the CA expires {}: make a new one (move {} away) and redeploy every bundle",
            ca.not_after()?.date(),
            out.join("ca").display()
        )));
    }
    Ok((ca, ca_action))
}

/// The fleet's secret (`protocol::auth`): every message key derives from it. Made once,
/// next to the CA, and never replaced: a new one would leave every plant with a key the
/// services no longer accept.
fn load_or_create_secret(out: &Path) -> Result<protocol::auth::Secret, DeployError> {
    let path = out.join("ca/fleet.secret");
    match read(&path)? {
        Some(text) => protocol::auth::Secret::from_hex(&text)
            .map_err(|e| DeployError::Pki(format!("{}: {e}", path.display()))),
        None => {
            let s =
                protocol::auth::Secret::random().map_err(|e| DeployError::Pki(e.to_string()))?;
            write(&path, &format!("{}\n", s.to_hex()), true)?;
            Ok(s)
        }
    }
}

/// The message key an identity's bundle gets, private: a service the fleet's secret
/// (`fleet.secret`: it checks every device's messages and seals its commands), a device
/// its own key (`ID.auth`: it speaks for itself only), an operator the operators' key
/// (`ID.auth`: it can check replies, not forge commands), a gateway its own batch key
/// (`ID.auth`: it seals its plants' batches and opens their commands, nobody else's); the
/// router none (it forwards, and cannot forge what it forwards).
fn write_message_key(
    secret: &protocol::auth::Secret,
    out: &Path,
    role: IdentityKind,
    name: &str,
) -> Result<(), DeployError> {
    let dir = bundle_dir(out, role, name);
    let (file, hex) = match role {
        IdentityKind::Router => return Ok(()),
        IdentityKind::Service => ("fleet.secret".to_string(), secret.to_hex()),
        IdentityKind::Device => (format!("{name}.auth"), secret.device(name).to_hex()),
        IdentityKind::Operator | IdentityKind::Console => {
            (format!("{name}.auth"), secret.operator().to_hex())
        }
        IdentityKind::Gateway => (format!("{name}.auth"), secret.gateway(name).to_hex()),
    };
    write(&dir.join(file), &format!("{hex}\n"), true)
}

/// One identity's bundle: its key and certificate (kept if still right, else issued
/// again), the CA's certificate, and its zenoh configuration.
fn bundle(
    inv: &Inventory,
    out: &Path,
    ca: &Ca,
    (role, name): (IdentityKind, &str),
    rotate: bool,
    now: OffsetDateTime,
) -> Result<Entry, DeployError> {
    let renew = Duration::days(inv.renew_days.into());
    let dir = bundle_dir(out, role, name);
    let (cert_path, key_path) = (
        dir.join(format!("{name}.pem")),
        dir.join(format!("{name}.key")),
    );
    let usage = match role {
        IdentityKind::Router => Usage::Server(&inv.router.hosts),
        _ => Usage::Client,
    };
    let mut action = leaf(
        (ca, inv.leaf_days),
        (&cert_path, &key_path),
        (name, usage),
        rotate,
        (renew, now),
    )?;
    write(&dir.join("ca.pem"), &ca.cert_pem, false)?;
    let header = format!(
        "Generated by `mfc-deploy generate` for {role:?} {name:?}; edit the inventory, not this file.\nInstall this directory's files in {} on its host.",
        inv.install_dir
    );
    let (file, config) = match role {
        IdentityKind::Router => (
            "zenohd.json5".to_string(),
            configs::router(inv, acl::access_control(inv)),
        ),
        _ => (format!("{name}.json5"), configs::client(inv, role, name)),
    };
    let text = configs::to_file(&header, &config);
    let config_path = dir.join(file);
    let mut config_changed = read(&config_path)?.as_deref() != Some(text.as_str());
    write(&config_path, &text, false)?;
    if let Some(c) = inv.console(name).filter(|_| role == IdentityKind::Console) {
        // Its HTTPS certificate (for the names browsers reach it by) and its settings.
        let https = leaf(
            (ca, inv.leaf_days),
            (
                &dir.join(format!("{name}.https.pem")),
                &dir.join(format!("{name}.https.key")),
            ),
            (name, Usage::Server(&c.hosts)),
            rotate,
            (renew, now),
        )?;
        if action == CertAction::Kept {
            action = https;
        }
        let settings = inv.console_settings(name);
        let settings_path = dir.join(format!("{name}.console.toml"));
        config_changed |= read(&settings_path)?.as_deref() != Some(settings.as_str());
        write(&settings_path, &settings, false)?;
    }
    if role == IdentityKind::Service {
        // Who may do what on this service, for its configuration file: the operators'
        // roles and devices, and the audit file.
        let access = inv.service_access(name);
        let access_path = dir.join(format!("{name}.access.toml"));
        config_changed |= read(&access_path)?.as_deref() != Some(access.as_str());
        write(&access_path, &access, false)?;
    }
    Ok(Entry {
        role,
        name: name.to_string(),
        action,
        config_changed,
        bundle: dir,
    })
}

/// One certificate and key: kept if still right for `(name, usage)`, else issued again
/// (and written); what was done.
fn leaf(
    (ca, days): (&Ca, u32),
    (cert_path, key_path): (&Path, &Path),
    (name, usage): (&str, Usage),
    rotate: bool,
    (renew, now): (Duration, OffsetDateTime),
) -> Result<CertAction, DeployError> {
    let action = if rotate {
        CertAction::Reissued("rotated on request".into())
    } else {
        match (read(cert_path)?, read(key_path)?) {
            (Some(c), Some(k)) => match ca.check(&c, &k, name, usage, renew, now) {
                Ok(()) => CertAction::Kept,
                Err(why) => CertAction::Reissued(why),
            },
            _ => CertAction::Issued,
        }
    };
    if action != CertAction::Kept {
        let leaf = ca.issue(name, usage, days, now)?;
        write(key_path, &leaf.key_pem, true)?;
        write(cert_path, &leaf.cert_pem, false)?;
    }
    Ok(action)
}

/// Names that left the inventory: their bundles move aside; the access control no longer
/// names them, so after the router restarts their certificates open nothing.
fn retire_departed(
    out: &Path,
    identities: &[(IdentityKind, String)],
) -> Result<Vec<PathBuf>, DeployError> {
    let mut retired = Vec::new();
    for role in [
        IdentityKind::Service,
        IdentityKind::Device,
        IdentityKind::Operator,
        IdentityKind::Gateway,
        IdentityKind::Console,
    ] {
        let dir = out.join(role.dir());
        let Ok(listing) = fs::read_dir(&dir) else {
            continue;
        };
        for e in listing.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            if identities.iter().any(|(r, n)| *r == role && *n == name) {
                continue;
            }
            let to = out.join("retired").join(role.dir()).join(&name);
            if let Some(p) = to.parent() {
                fs::create_dir_all(p).map_err(io(p))?;
            }
            let _ = fs::remove_dir_all(&to);
            fs::rename(e.path(), &to).map_err(io(&to))?;
            retired.push(to);
        }
    }
    Ok(retired)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn now() -> OffsetDateTime {
        OffsetDateTime::from_unix_timestamp(1_800_000_000).unwrap()
    }

    fn inv(devices: &[&str]) -> Inventory {
        let list: Vec<String> = devices.iter().map(|d| format!("{d:?}")).collect();
        Inventory::parse(&format!(
            "services = [\"ctl\"]\noperators = [\"alice\"]\ndevices = [{}]\n[router]\nhosts = [\"10.0.0.1\"]\n",
            list.join(", ")
        ))
        .unwrap()
    }

    fn actions(r: &DeployReport) -> Vec<(String, CertAction)> {
        r.entries
            .iter()
            .map(|e| (e.name.clone(), e.action.clone()))
            .collect()
    }

    #[test]
    fn adding_a_device_issues_one_certificate_and_keeps_the_rest() {
        let out = tempfile::tempdir().unwrap();
        let first = generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap();
        assert_eq!(first.ca, CertAction::Issued);
        assert!(first.entries.iter().all(|e| e.action == CertAction::Issued));
        let before = fs::read(out.path().join("devices/aero-1/aero-1.pem")).unwrap();

        let second = generate(&inv(&["aero-1", "aero-2"]), out.path(), &[], now()).unwrap();
        assert_eq!(second.ca, CertAction::Kept);
        let issued: Vec<_> = actions(&second)
            .into_iter()
            .filter(|(_, a)| *a != CertAction::Kept)
            .collect();
        assert_eq!(issued, [("aero-2".to_string(), CertAction::Issued)]);
        assert_eq!(
            fs::read(out.path().join("devices/aero-1/aero-1.pem")).unwrap(),
            before
        );
        let acl = fs::read_to_string(out.path().join("router/zenohd.json5")).unwrap();
        assert!(acl.contains("mfc/v1/device/aero-2/sample"));
        assert!(second.router_restart(), "the access control changed");
        let copy: Vec<_> = second
            .entries
            .iter()
            .filter(|e| e.to_copy())
            .map(|e| e.name.as_str())
            .collect();
        assert_eq!(copy, ["router", "aero-2"]);
        // Nothing to do the third time.
        let third = generate(&inv(&["aero-1", "aero-2"]), out.path(), &[], now()).unwrap();
        assert!(!third.router_restart(), "{:?}", actions(&third));
        assert!(third.entries.iter().all(|e| !e.to_copy()));
    }

    #[test]
    fn rotation_and_expiry_reissue_exactly_what_they_name() {
        let out = tempfile::tempdir().unwrap();
        generate(&inv(&["aero-1", "aero-2"]), out.path(), &[], now()).unwrap();
        let key = |d: &str| fs::read(out.path().join(format!("devices/{d}/{d}.key"))).unwrap();
        let (k1, k2) = (key("aero-1"), key("aero-2"));
        let r = generate(
            &inv(&["aero-1", "aero-2"]),
            out.path(),
            &["aero-1".into()],
            now(),
        )
        .unwrap();
        assert!(matches!(actions(&r)[2], (ref n, CertAction::Reissued(_)) if n == "aero-1"));
        assert_ne!(key("aero-1"), k1, "a rotation makes a new key");
        assert_eq!(key("aero-2"), k2);
        assert!(
            !r.router_restart(),
            "a client's rotation needs no router restart"
        );
        // A year on, everything is within renew_days of expiry and is renewed.
        let later = now() + Duration::days(380);
        let r = generate(&inv(&["aero-1", "aero-2"]), out.path(), &[], later).unwrap();
        assert!(r
            .entries
            .iter()
            .all(|e| matches!(&e.action, CertAction::Reissued(w) if w.contains("expires"))));
        let e = generate(&inv(&["aero-1"]), out.path(), &["aero-9".into()], now()).unwrap_err();
        assert!(e.to_string().contains("not in the inventory"), "{e}");
    }

    #[test]
    fn a_new_router_port_rewrites_every_config_and_says_so() {
        let out = tempfile::tempdir().unwrap();
        generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap();
        let mut moved = inv(&["aero-1"]);
        moved.router.port = 7448;
        let r = generate(&moved, out.path(), &[], now()).unwrap();
        assert!(r
            .entries
            .iter()
            .all(|e| e.action == CertAction::Kept && e.config_changed));
        assert!(r.router_restart());
    }

    #[test]
    fn removed_names_are_retired_and_lose_their_rules() {
        let out = tempfile::tempdir().unwrap();
        generate(&inv(&["aero-1", "aero-2"]), out.path(), &[], now()).unwrap();
        let r = generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap();
        assert_eq!(r.retired, [out.path().join("retired/devices/aero-2")]);
        assert!(r.router_restart(), "the removed name's rules must go");
        assert!(!out.path().join("devices/aero-2").exists());
        let cfg = fs::read_to_string(out.path().join("router/zenohd.json5")).unwrap();
        assert!(!cfg.contains("aero-2"));
    }

    #[test]
    fn keys_are_private_and_a_half_ca_is_refused() {
        let out = tempfile::tempdir().unwrap();
        generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            for p in [
                "ca/ca.key",
                "devices/aero-1/aero-1.key",
                "router/router.key",
            ] {
                let mode = fs::metadata(out.path().join(p))
                    .unwrap()
                    .permissions()
                    .mode();
                assert_eq!(mode & 0o777, 0o600, "{p}");
            }
        }
        fs::remove_file(out.path().join("ca/ca.key")).unwrap();
        let e = generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap_err();
        assert!(e.to_string().contains("half restored"), "{e}");
    }

    #[test]
    fn every_bundle_holds_its_config_certificate_key_and_the_ca() {
        let out = tempfile::tempdir().unwrap();
        let r = generate(&inv(&["aero-1"]), out.path(), &[], now()).unwrap();
        for e in &r.entries {
            let conf = if e.role == IdentityKind::Router {
                "zenohd.json5".into()
            } else {
                format!("{}.json5", e.name)
            };
            for f in [
                conf,
                format!("{}.pem", e.name),
                format!("{}.key", e.name),
                "ca.pem".into(),
            ] {
                assert!(e.bundle.join(&f).is_file(), "{}: {f}", e.name);
            }
            // No bundle carries the CA's key.
            assert!(!e.bundle.join("ca.key").exists());
        }
    }

    #[test]
    fn each_bundle_gets_only_its_own_message_key_and_the_secret_stays() {
        use protocol::auth::{Key, Secret};
        let out = tempfile::tempdir().unwrap();
        let o = out.path();
        generate(&inv(&["aero-1", "aero-2"]), o, &[], now()).unwrap();
        let secret = Secret::from_file(&o.join("ca/fleet.secret")).unwrap();
        let hex = |p: &str| Key::from_file(&o.join(p)).unwrap().to_hex();
        assert_eq!(hex("services/ctl/fleet.secret"), secret.to_hex());
        assert_eq!(
            hex("devices/aero-1/aero-1.auth"),
            secret.device("aero-1").to_hex()
        );
        assert_eq!(
            hex("devices/aero-2/aero-2.auth"),
            secret.device("aero-2").to_hex()
        );
        assert_eq!(
            hex("operators/alice/alice.auth"),
            secret.operator().to_hex()
        );
        // Nobody but the services holds the secret; the router holds no message key.
        for dir in ["devices/aero-1", "operators/alice", "router"] {
            for f in fs::read_dir(o.join(dir)).unwrap() {
                let f = f.unwrap().path();
                let text = fs::read_to_string(&f).unwrap_or_default();
                assert!(!text.contains(&secret.to_hex()), "{}", f.display());
            }
        }
        assert!(!o.join("router/router.auth").exists());
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            for p in [
                "ca/fleet.secret",
                "services/ctl/fleet.secret",
                "devices/aero-1/aero-1.auth",
            ] {
                let mode = fs::metadata(o.join(p)).unwrap().permissions().mode();
                assert_eq!(mode & 0o777, 0o600, "{p}");
            }
        }
        // Generating again (a rotation included) keeps the secret: plants keep their keys.
        generate(&inv(&["aero-1", "aero-2"]), o, &["aero-1".into()], now()).unwrap();
        assert_eq!(
            Secret::from_file(&o.join("ca/fleet.secret"))
                .unwrap()
                .to_hex(),
            secret.to_hex()
        );
        assert_eq!(
            hex("devices/aero-1/aero-1.auth"),
            secret.device("aero-1").to_hex()
        );
    }

    #[test]
    fn a_console_gets_two_certificates_its_people_and_a_viewers_grant() {
        let out = tempfile::tempdir().unwrap();
        let o = out.path();
        let text = "services = [\"ctl\"]\noperators = [\"alice\", { name = \"vera\", role = \"viewer\" }]\nconsoles = [{ name = \"desk\", hosts = [\"10.0.0.9\", \"desk.lan\"], people = [\"alice\", \"vera\"] }]\n[router]\nhosts = [\"10.0.0.1\"]\n";
        let inv = Inventory::parse(text).unwrap();
        let r = generate(&inv, o, &[], now()).unwrap();
        let d = o.join("consoles/desk");
        for f in [
            "desk.pem",
            "desk.key",
            "desk.https.pem",
            "desk.https.key",
            "ca.pem",
            "desk.json5",
            "desk.auth",
        ] {
            assert!(d.join(f).exists(), "{f}");
        }
        let ca = Ca::load(
            &fs::read_to_string(o.join("ca/ca.pem")).unwrap(),
            &fs::read_to_string(o.join("ca/ca.key")).unwrap(),
        )
        .unwrap();
        let pem = |f: &str| fs::read_to_string(d.join(f)).unwrap();
        let renew = Duration::days(1);
        ca.check(
            &pem("desk.pem"),
            &pem("desk.key"),
            "desk",
            Usage::Client,
            renew,
            now(),
        )
        .unwrap();
        let hosts = ["10.0.0.9".to_string(), "desk.lan".to_string()];
        ca.check(
            &pem("desk.https.pem"),
            &pem("desk.https.key"),
            "desk",
            Usage::Server(&hosts),
            renew,
            now(),
        )
        .unwrap();
        // Its settings: its people with the inventory's roles, HTTPS with its certificate.
        let v: toml::Value = toml::from_str(&pem("desk.console.toml")).unwrap();
        let users: Vec<(&str, &str)> = v["login"]["users"]
            .as_array()
            .unwrap()
            .iter()
            .map(|u| (u["name"].as_str().unwrap(), u["role"].as_str().unwrap()))
            .collect();
        assert_eq!(users, [("alice", "operator"), ("vera", "viewer")]);
        assert_eq!(
            v["login"]["https"]["cert_file"].as_str(),
            Some("desk.https.pem")
        );
        assert_eq!(
            v["login"]["https"]["client_ca_file"].as_str(),
            Some("ca.pem")
        );
        // The services let its own name read.
        let access: toml::Value =
            toml::from_str(&fs::read_to_string(o.join("services/ctl/ctl.access.toml")).unwrap())
                .unwrap();
        let desk = access["access"]["operators"]
            .as_array()
            .unwrap()
            .iter()
            .find(|x| x["name"].as_str() == Some("desk"))
            .cloned()
            .unwrap();
        assert_eq!(desk["role"].as_str(), Some("viewer"));
        // Again: everything kept.
        assert!(r
            .entries
            .iter()
            .any(|e| e.name == "desk" && e.action == CertAction::Issued));
        let again = generate(&inv, o, &[], now()).unwrap();
        assert!(again
            .entries
            .iter()
            .all(|e| e.action == CertAction::Kept && !e.config_changed));
        // People must be operators, once each; hosts needed.
        for (bad, says) in [
            ("people = [\"bob\"]", "\"bob\" is not one of the operators"),
            ("people = [\"alice\", \"alice\"]", "listed twice"),
            ("people = []", "nobody could log in"),
        ] {
            let t = text.replace("people = [\"alice\", \"vera\"]", bad);
            let e = Inventory::parse(&t).unwrap_err().to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
        let e =
            Inventory::parse(&text.replace("hosts = [\"10.0.0.9\", \"desk.lan\"]", "hosts = []"))
                .unwrap_err()
                .to_string();
        assert!(e.contains("console \"desk\": hosts is empty"), "{e}");
    }

    #[test]
    fn each_service_gets_the_operators_roles_and_an_audit_file() {
        let out = tempfile::tempdir().unwrap();
        let o = out.path();
        let inv = Inventory::parse(
            "services = [\"ctl\"]\noperators = [\"alice\", { name = \"vera\", role = \"viewer\", devices = [\"aero-*\"] }]\n[router]\nhosts = [\"10.0.0.1\"]\n",
        )
        .unwrap();
        generate(&inv, o, &[], now()).unwrap();
        let text = fs::read_to_string(o.join("services/ctl/ctl.access.toml")).unwrap();
        let v: toml::Value = toml::from_str(&text).unwrap();
        assert_eq!(
            v["audit"]["path"].as_str(),
            Some("/var/lib/mfc/audit/ctl.jsonl")
        );
        assert_eq!(v["access"]["verified"].as_bool(), Some(true));
        let ops = v["access"]["operators"].as_array().unwrap();
        let got: Vec<(&str, &str, Vec<&str>)> = ops
            .iter()
            .map(|o| {
                let devices = o["devices"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|d| d.as_str().unwrap())
                    .collect();
                (
                    o["name"].as_str().unwrap(),
                    o["role"].as_str().unwrap(),
                    devices,
                )
            })
            .collect();
        assert_eq!(
            got,
            [
                ("alice", "operator", vec!["*"]),
                ("vera", "viewer", vec!["aero-*"])
            ]
        );
        // Bad roles and patterns are refused with the operator's name.
        for (bad, says) in [
            ("{ name = \"x\", role = \"root\" }", "role \"root\""),
            ("{ name = \"x\", devices = [\"a/b\"] }", "devices \"a/b\""),
            (
                "{ name = \"x\", colour = \"red\" }",
                "unknown field `colour`",
            ),
        ] {
            let text = format!(
                "services = [\"ctl\"]\noperators = [{bad}]\n[router]\nhosts = [\"10.0.0.1\"]\n"
            );
            let e = Inventory::parse(&text).unwrap_err().to_string();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn a_gateway_gets_a_certificate_its_own_batch_key_and_is_retired_when_it_leaves() {
        use protocol::auth::{Key, Secret};
        let out = tempfile::tempdir().unwrap();
        let o = out.path();
        let with_gateway = Inventory::parse(
            "services = [\"ctl\"]\ndevices = [\"aero-1\"]\n[router]\nhosts = [\"10.0.0.1\"]\n[[gateways]]\nid = \"cell-1\"\nplants = [\"heater-1\", \"heater-2\"]\n",
        )
        .unwrap();
        let r = generate(&with_gateway, o, &[], now()).unwrap();
        let gw = r.entries.iter().find(|e| e.name == "cell-1").unwrap();
        assert_eq!(
            (gw.role, gw.bundle.clone()),
            (IdentityKind::Gateway, o.join("gateways/cell-1"))
        );
        for f in ["cell-1.pem", "cell-1.key", "cell-1.json5", "ca.pem"] {
            assert!(gw.bundle.join(f).is_file(), "{f}");
        }
        let secret = Secret::from_file(&o.join("ca/fleet.secret")).unwrap();
        let key = Key::from_file(&o.join("gateways/cell-1/cell-1.auth")).unwrap();
        assert_eq!(key.to_hex(), secret.gateway("cell-1").to_hex());
        // Its batch key is neither a plant's device key nor the secret.
        assert_ne!(key.to_hex(), secret.device("cell-1").to_hex());
        let files: Vec<_> = fs::read_dir(&gw.bundle).unwrap().flatten().collect();
        assert!(files.iter().all(|f| !fs::read_to_string(f.path())
            .unwrap_or_default()
            .contains(&secret.to_hex())));
        let r = generate(&inv(&["aero-1"]), o, &[], now()).unwrap();
        assert_eq!(r.retired, [o.join("retired/gateways/cell-1")]);
        let cfg = fs::read_to_string(o.join("router/zenohd.json5")).unwrap();
        assert!(!cfg.contains("cell-1") && !cfg.contains("heater-1"));
    }
}
