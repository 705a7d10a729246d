//! Who may use the console, and how they prove it: the settings' `[login]` section and the
//! sessions it opens. Pure (time passed in as seconds; the token and the password check
//! come from the caller), unit-tested with plain values; `http` wires it to requests.
//!
//! ```toml
//! [login]
//! idle_minutes = 30          # a session unused this long is closed
//! max_hours = 12             # and any session this old
//! max_sessions = 256         # open at once (beyond: the least recently used is closed)
//!
//! [[login.users]]
//! name = "alice"             # the name the console's requests give (…/by/alice)
//! role = "operator"          # viewer | operator | admin
//! password_hash = "$argon2id$v=19$m=19456,t=2,p=1$…"   # mfc-console --hash-password
//!
//! [[login.users]]
//! name = "vera"
//! role = "viewer"            # no password_hash: she logs in with her certificate only
//!
//! [login.https]
//! cert_file = "console.pem"  # relative to this file
//! key_file = "console.key"
//! client_ca_file = "ca.pem"  # optional: people may log in with a certificate of this CA
//! ```
//!
//! A person is known by a session (a password checked once, then a cookie of 256 random
//! bits) or by the client certificate of the HTTPS connection, whose common name must be a
//! user's name (`mfc-deploy` issues operators' certificates with that name). Repeated wrong
//! passwords for one name lock it for a while ([`LOCK_AFTER`] failures, then a doubling
//! wait); the lock is per name, so it cannot be lifted by changing address, and a name
//! locked by someone else's guesses can still log in with its certificate.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

pub use protocol::roles::{Action, Role};
use serde::Deserialize;

/// Wrong passwords in a row after which a name is locked.
pub const LOCK_AFTER: u32 = 5;
/// The first lock (s); each further failure doubles it, up to [`LOCK_MAX_S`].
pub const LOCK_FIRST_S: f64 = 30.0;
/// The longest lock (s).
pub const LOCK_MAX_S: f64 = 900.0;
/// Names whose failures are remembered at once (beyond: the stalest is forgotten).
pub const MAX_FAILING_NAMES: usize = 4096;
/// Longest password accepted (bytes): argon2 takes any length, the console does not.
pub const MAX_PASSWORD: usize = 1024;

/// The `[login]` section.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LoginSpec {
    /// Who may log in.
    pub users: Vec<UserSpec>,
    /// A session unused this long is closed (minutes). Default 30.
    #[serde(default = "default_idle")]
    pub idle_minutes: f64,
    /// Any session this old is closed (hours). Default 12.
    #[serde(default = "default_max_hours")]
    pub max_hours: f64,
    /// Sessions open at once. Default 256.
    #[serde(default = "default_max_sessions")]
    pub max_sessions: usize,
    /// Serve the page over HTTPS (required off loopback).
    pub https: Option<HttpsSpec>,
}

fn default_idle() -> f64 {
    30.0
}
fn default_max_hours() -> f64 {
    12.0
}
fn default_max_sessions() -> usize {
    256
}

/// One person.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UserSpec {
    /// Their name: what the console's requests give as the operator (`…/by/{name}`), and,
    /// for a certificate login, the certificate's common name.
    pub name: String,
    /// What they may do here: a viewer sees, an operator and an admin also change.
    pub role: Role,
    /// Their password's argon2 hash (PHC string, `mfc-console --hash-password`); none:
    /// they log in with a client certificate only.
    pub password_hash: Option<String>,
}

/// The `[login.https]` section: the page's certificate and key, and the CA of people's
/// certificates. Relative paths are relative to the settings file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HttpsSpec {
    /// The console's certificate chain (PEM).
    pub cert_file: PathBuf,
    /// Its private key (PEM).
    pub key_file: PathBuf,
    /// The CA (PEM) whose client certificates log people in; none: passwords only.
    pub client_ca_file: Option<PathBuf>,
}

impl LoginSpec {
    /// Every user named once, with a valid name and, if any, a valid argon2 hash with sane
    /// costs; sane session bounds; someone able to log in.
    pub fn check(&self) -> Result<(), String> {
        if self.users.is_empty() {
            return Err("[login] lists no users: nobody could log in".into());
        }
        let mut seen = std::collections::BTreeSet::new();
        for u in &self.users {
            protocol::keys::check_id(&u.name).map_err(|e| format!("user {:?}: {e}", u.name))?;
            if !seen.insert(u.name.as_str()) {
                return Err(format!("user {:?} is listed twice", u.name));
            }
            if let Some(h) = &u.password_hash {
                check_hash(h).map_err(|e| format!("user {:?}: password_hash: {e}", u.name))?;
            }
        }
        let certs = self
            .https
            .as_ref()
            .is_some_and(|h| h.client_ca_file.is_some());
        if !certs && self.users.iter().all(|u| u.password_hash.is_none()) {
            return Err(
                "no user has a password_hash and [login.https] has no client_ca_file: \
                        nobody could log in"
                    .into(),
            );
        }
        if !(self.idle_minutes > 0.0 && self.idle_minutes <= 24.0 * 60.0) {
            return Err(format!(
                "idle_minutes {} must be in (0, 1440]",
                self.idle_minutes
            ));
        }
        if !(self.max_hours > 0.0 && self.max_hours <= 24.0 * 7.0) {
            return Err(format!("max_hours {} must be in (0, 168]", self.max_hours));
        }
        if !(1..=100_000).contains(&self.max_sessions) {
            return Err(format!(
                "max_sessions {} must be 1..=100000",
                self.max_sessions
            ));
        }
        Ok(())
    }

    /// Make the HTTPS files' relative paths relative to `dir`.
    pub fn resolve(&mut self, dir: &Path) {
        if let Some(h) = &mut self.https {
            let files = [
                Some(&mut h.cert_file),
                Some(&mut h.key_file),
                h.client_ca_file.as_mut(),
            ];
            for p in files.into_iter().flatten() {
                if p.is_relative() {
                    *p = dir.join(&*p);
                }
            }
        }
    }

    /// The user of this name.
    pub fn user(&self, name: &str) -> Option<&UserSpec> {
        self.users.iter().find(|u| u.name == name)
    }
}

/// An argon2 PHC string with costs a login can afford: at most 256 MiB and 10 passes (a
/// hash of absurd cost would let every login attempt take the machine).
pub fn check_hash(phc: &str) -> Result<(), String> {
    let h = argon2::PasswordHash::new(phc).map_err(|e| e.to_string())?;
    if !h.algorithm.as_str().starts_with("argon2") {
        return Err(format!("{} is not argon2", h.algorithm));
    }
    let p = argon2::Params::try_from(&h).map_err(|e| e.to_string())?;
    if p.m_cost() > 256 * 1024 || p.t_cost() > 10 || p.p_cost() > 16 {
        return Err(format!(
            "costs m={} KiB, t={}, p={} exceed 262144, 10, 16",
            p.m_cost(),
            p.t_cost(),
            p.p_cost()
        ));
    }
    if h.hash.is_none() {
        return Err("no hash in it".into());
    }
    Ok(())
}

/// How a person proved who they are.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Proof {
    /// A password, then the session's cookie.
    Password,
    /// The HTTPS connection's client certificate.
    Certificate,
    /// Nobody: the console runs without `[login]` (loopback only), as its own operator.
    Open,
}

/// Who is asking, as the console acts for them.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct Identity {
    /// The name the console's requests give.
    pub name: String,
    /// What they may do.
    pub role: Role,
    /// How they proved it.
    pub proof: Proof,
}

#[derive(Debug, Clone)]
struct Session {
    who: Identity,
    started: f64,
    last: f64,
}

#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    locked_until: f64,
    last: f64,
}

/// The open sessions and the failed logins, bounded.
#[derive(Debug)]
pub struct Sessions {
    open: HashMap<String, Session>,
    failing: HashMap<String, Failures>,
    idle: f64,
    max_age: f64,
    max: usize,
}

impl Sessions {
    /// Empty, with `spec`'s bounds.
    pub fn new(spec: &LoginSpec) -> Self {
        Self {
            open: HashMap::new(),
            failing: HashMap::new(),
            idle: spec.idle_minutes * 60.0,
            max_age: spec.max_hours * 3600.0,
            max: spec.max_sessions,
        }
    }

    /// Sessions open now (expired ones included until next touched or evicted).
    pub fn len(&self) -> usize {
        self.open.len()
    }

    /// Whether no session is open.
    pub fn is_empty(&self) -> bool {
        self.open.is_empty()
    }

    /// Open a session for `who` under `token` (fresh random bits from the caller); when
    /// full, the expired sessions go first, then the least recently used.
    pub fn open(&mut self, token: String, who: Identity, now: f64) {
        if self.open.len() >= self.max {
            let (idle, max_age) = (self.idle, self.max_age);
            self.open
                .retain(|_, s| now - s.last < idle && now - s.started < max_age);
        }
        if self.open.len() >= self.max {
            if let Some(k) = self
                .open
                .iter()
                .min_by(|a, b| a.1.last.total_cmp(&b.1.last))
                .map(|(k, _)| k.clone())
            {
                self.open.remove(&k);
            }
        }
        self.open.insert(
            token,
            Session {
                who,
                started: now,
                last: now,
            },
        );
    }

    /// The person of `token`, if its session is open and not expired (then it is
    /// touched: the idle time starts again).
    pub fn find(&mut self, token: &str, now: f64) -> Option<Identity> {
        let s = self.open.get_mut(token)?;
        if now - s.last >= self.idle || now - s.started >= self.max_age {
            self.open.remove(token);
            return None;
        }
        s.last = now;
        Some(s.who.clone())
    }

    /// Close `token`'s session; whether one was open.
    pub fn close(&mut self, token: &str) -> bool {
        self.open.remove(token).is_some()
    }

    /// Close every session of `name` (after a failed attempt nothing else changes; this is
    /// for an operator who removes a person).
    pub fn close_all(&mut self, name: &str) {
        self.open.retain(|_, s| s.who.name != name);
    }

    /// Whether a password may be tried for `name` now; if not, seconds to wait.
    pub fn may_try(&self, name: &str, now: f64) -> Result<(), f64> {
        match self.failing.get(name) {
            Some(f) if f.locked_until > now => Err(f.locked_until - now),
            _ => Ok(()),
        }
    }

    /// A wrong password (or an unknown name) for `name`: from the [`LOCK_AFTER`]th in a
    /// row, the name is locked, [`LOCK_FIRST_S`] doubling up to [`LOCK_MAX_S`].
    pub fn failed(&mut self, name: &str, now: f64) {
        if !self.failing.contains_key(name) && self.failing.len() >= MAX_FAILING_NAMES {
            if let Some(k) = self
                .failing
                .iter()
                .min_by(|a, b| a.1.last.total_cmp(&b.1.last))
                .map(|(k, _)| k.clone())
            {
                self.failing.remove(&k);
            }
        }
        let f = self.failing.entry(name.to_string()).or_insert(Failures {
            count: 0,
            locked_until: 0.0,
            last: now,
        });
        f.count = f.count.saturating_add(1);
        f.last = now;
        if f.count >= LOCK_AFTER {
            let doublings = (f.count - LOCK_AFTER).min(16);
            let wait = (LOCK_FIRST_S * f64::from(1u32 << doublings)).min(LOCK_MAX_S);
            f.locked_until = now + wait;
        }
    }

    /// A right password for `name`: its failures are forgotten.
    pub fn succeeded(&mut self, name: &str) {
        self.failing.remove(name);
    }
}

/// The value of cookie `name` in a `Cookie` header.
pub fn cookie<'a>(header: &'a str, name: &str) -> Option<&'a str> {
    header.split(';').find_map(|pair| {
        let (k, v) = pair.trim().split_once('=')?;
        (k == name).then_some(v)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(text: &str) -> Result<LoginSpec, String> {
        let s: LoginSpec = toml::from_str(text).map_err(|e| e.to_string())?;
        s.check()?;
        Ok(s)
    }

    fn hash(pw: &str) -> String {
        crate::cli::hash_password(pw).unwrap()
    }

    fn who(name: &str) -> Identity {
        Identity {
            name: name.into(),
            role: Role::Operator,
            proof: Proof::Password,
        }
    }

    #[test]
    fn the_section_is_checked() {
        let h = hash("correct horse");
        let ok =
            format!("[[users]]\nname = \"alice\"\nrole = \"operator\"\npassword_hash = \"{h}\"\n");
        let s = spec(&ok).unwrap();
        assert_eq!(
            (s.idle_minutes, s.max_hours, s.max_sessions),
            (30.0, 12.0, 256)
        );
        assert_eq!(s.user("alice").unwrap().role, Role::Operator);
        let bad = |t: &str| spec(t).unwrap_err();
        assert!(bad("users = []").contains("no users"));
        assert!(bad(&format!("{ok}{ok}")).contains("twice"));
        assert!(bad(&ok.replace("operator", "root")).contains("unknown variant"));
        assert!(bad(&ok.replace("\"alice\"", "\"al ice\"")).contains("al ice"));
        assert!(bad(&ok.replace(&h, "hunter2")).contains("password_hash"));
        assert!(bad(&format!("{ok}pasword = 1\n")).contains("unknown field"));
        // Nobody could log in: no password and no CA for certificates.
        assert!(bad("[[users]]\nname = \"vera\"\nrole = \"viewer\"\n").contains("nobody"));
        let certs = "[[users]]\nname = \"vera\"\nrole = \"viewer\"\n[https]\ncert_file = \"c.pem\"\nkey_file = \"c.key\"\nclient_ca_file = \"ca.pem\"\n";
        let mut s = spec(certs).unwrap();
        s.resolve(Path::new("/etc/mfc"));
        let h = s.https.unwrap();
        assert_eq!(h.client_ca_file.unwrap(), Path::new("/etc/mfc/ca.pem"));
        assert_eq!(h.cert_file, Path::new("/etc/mfc/c.pem"));
    }

    #[test]
    fn a_hash_of_absurd_cost_is_refused() {
        let h = hash("x");
        assert!(check_hash(&h).is_ok());
        let costly = h.replace("m=19456", "m=4194304");
        assert!(
            check_hash(&costly).unwrap_err().contains("exceed"),
            "{costly}"
        );
        assert!(check_hash("$pbkdf2-sha256$i=1000$c2FsdA$aGFzaA").is_err());
    }

    #[test]
    fn sessions_expire_idle_and_old_and_stay_bounded() {
        let s = spec(&format!(
            "max_sessions = 2\nidle_minutes = 1\nmax_hours = 1\n[[users]]\nname = \"a\"\nrole = \"viewer\"\npassword_hash = \"{}\"\n",
            hash("p")
        ))
        .unwrap();
        let mut ss = Sessions::new(&s);
        ss.open("t1".into(), who("a"), 0.0);
        assert_eq!(ss.find("t1", 59.0).unwrap().name, "a");
        // Touched at 59: idle from there.
        assert!(ss.find("t1", 118.0).is_some());
        assert!(ss.find("t1", 178.5).is_none(), "idle for over a minute");
        assert!(ss.find("t1", 179.0).is_none(), "gone once expired");
        // Used every 50 s, it still ends after an hour.
        ss.open("t2".into(), who("a"), 0.0);
        let mut t = 0.0;
        while t < 3550.0 {
            t += 50.0;
            assert!(ss.find("t2", t).is_some(), "{t}");
        }
        assert!(ss.find("t2", 3600.0).is_none());
        // Full: the least recently used goes.
        ss.open("x".into(), who("a"), 10.0);
        ss.open("y".into(), who("b"), 11.0);
        assert!(ss.find("x", 12.0).is_some());
        ss.open("z".into(), who("c"), 13.0);
        assert_eq!(ss.len(), 2);
        assert!(ss.find("y", 14.0).is_none() && ss.find("x", 14.0).is_some());
        assert!(ss.close("x") && !ss.close("x"));
        ss.close_all("c");
        assert!(ss.is_empty());
        assert!(ss.find("", 15.0).is_none() && ss.find("nope", 15.0).is_none());
    }

    #[test]
    fn wrong_passwords_lock_the_name_for_longer_each_time() {
        let s = spec(&format!(
            "[[users]]\nname = \"a\"\nrole = \"viewer\"\npassword_hash = \"{}\"\n",
            hash("p")
        ))
        .unwrap();
        let mut ss = Sessions::new(&s);
        for i in 0..LOCK_AFTER - 1 {
            ss.failed("a", f64::from(i));
            assert!(ss.may_try("a", f64::from(i)).is_ok());
        }
        ss.failed("a", 10.0);
        assert_eq!(ss.may_try("a", 10.0), Err(LOCK_FIRST_S));
        assert!(ss.may_try("b", 10.0).is_ok(), "other names are not locked");
        assert!(ss.may_try("a", 10.0 + LOCK_FIRST_S).is_ok());
        ss.failed("a", 50.0);
        assert_eq!(ss.may_try("a", 50.0), Err(2.0 * LOCK_FIRST_S));
        for _ in 0..40 {
            ss.failed("a", 100.0);
        }
        assert_eq!(ss.may_try("a", 100.0), Err(LOCK_MAX_S));
        ss.succeeded("a");
        assert!(ss.may_try("a", 100.0).is_ok());
        // Bounded: a flood of made-up names forgets the stalest.
        for i in 0..MAX_FAILING_NAMES + 10 {
            ss.failed(&format!("n{i}"), i as f64);
        }
        assert_eq!(ss.failing.len(), MAX_FAILING_NAMES);
        assert!(!ss.failing.contains_key("n0"));
    }

    #[test]
    fn cookies_are_found_by_name() {
        let h = "theme=dark; mfc_session=abc123 ; other=1";
        assert_eq!(cookie(h, "mfc_session"), Some("abc123"));
        assert_eq!(cookie(h, "mfc"), None);
        assert_eq!(cookie("", "mfc_session"), None);
        assert_eq!(cookie("mfc_session", "mfc_session"), None);
    }
}
