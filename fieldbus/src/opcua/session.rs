//! Opening a session with an OPC UA server: who the bridge is (its certificate, the user),
//! how it talks (the policy and mode of the secure channel), and what an operator needs to
//! hear when that fails (what the server offers, which certificate is not trusted yet).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use opcua::client::{ClientBuilder, IdentityToken, Session, SessionPollResult};
use opcua::crypto::SecurityPolicy;
use opcua::types::{EndpointDescription, MessageSecurityMode, UserTokenPolicy};
use plant::scenario::OpcUaPlant;

use super::nodelay::NoDelay;

/// Who the bridge is to a server, and how it talks to it.
pub struct SessionSpec {
    /// `opc.tcp://host:port/path`.
    pub endpoint: String,
    /// One of `plant::opcua::SECURITY_POLICIES`.
    pub policy: String,
    /// One of `plant::opcua::SECURITY_MODES`.
    pub mode: String,
    /// The bridge's PKI directory (OPC UA's layout); needed by any policy but None.
    pub pki_dir: Option<PathBuf>,
    /// The user.
    pub identity: OpcUaUser,
    /// Longest wait for one answer.
    pub request_timeout: Duration,
    /// Longest wait for the session.
    pub connect_timeout: Duration,
    /// Make the bridge's key pair in the PKI directory if it has none: the probe's
    /// `--create-keypair`. The agent never does: which certificate a plant's bridge
    /// shows is an operator's decision.
    pub create_keypair: bool,
    /// The sampling interval of subscriptions (the client's floor on how often it asks
    /// for publications: at that interval, not the library's default 100 ms).
    pub sampling_interval: Duration,
}

/// The user a session opens for.
pub enum OpcUaUser {
    /// No user.
    Anonymous,
    /// A name and its password.
    User {
        /// The name.
        name: String,
        /// Its password.
        password: String,
    },
    /// A certificate (DER or PEM) and its private key (PEM).
    Certificate {
        /// The certificate's file.
        cert: PathBuf,
        /// The key's file.
        key: PathBuf,
    },
}

impl std::fmt::Debug for OpcUaUser {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the password: a Debug print ends up in logs.
        match self {
            OpcUaUser::Anonymous => write!(f, "Anonymous"),
            OpcUaUser::User { name, .. } => write!(f, "User({name})"),
            OpcUaUser::Certificate { cert, .. } => write!(f, "Certificate({})", cert.display()),
        }
    }
}

impl SessionSpec {
    /// The session a plant file's map describes.
    pub fn of(plant: &OpcUaPlant) -> Self {
        let c = &plant.config;
        let identity = match (&c.user, &plant.password, &plant.user_certificate) {
            (Some(name), Some(password), _) => OpcUaUser::User {
                name: name.clone(),
                password: password.clone(),
            },
            (_, _, Some((cert, key))) => OpcUaUser::Certificate {
                cert: cert.clone(),
                key: key.clone(),
            },
            _ => OpcUaUser::Anonymous,
        };
        Self {
            endpoint: c.endpoint.clone(),
            policy: c.security_policy.clone(),
            mode: c.security_mode.clone(),
            pki_dir: plant.pki_dir.clone(),
            identity,
            request_timeout: plant.timeout,
            connect_timeout: Duration::from_millis(c.connect_timeout_ms),
            create_keypair: false,
            sampling_interval: plant.sampling_interval,
        }
    }

    /// An anonymous session without security, for the probe's defaults.
    pub fn plain(endpoint: &str, timeout: Duration) -> Self {
        Self {
            endpoint: endpoint.to_string(),
            policy: "None".into(),
            mode: "None".into(),
            pki_dir: None,
            identity: OpcUaUser::Anonymous,
            request_timeout: timeout,
            connect_timeout: timeout,
            create_keypair: false,
            sampling_interval: Duration::from_millis(100),
        }
    }

    fn security(&self) -> Result<(SecurityPolicy, MessageSecurityMode), String> {
        let policy = match self.policy.as_str() {
            "None" => SecurityPolicy::None,
            "Basic256Sha256" => SecurityPolicy::Basic256Sha256,
            "Aes128_Sha256_RsaOaep" => SecurityPolicy::Aes128Sha256RsaOaep,
            "Aes256_Sha256_RsaPss" => SecurityPolicy::Aes256Sha256RsaPss,
            other => return Err(format!("security policy {other:?} unknown")),
        };
        let mode = match self.mode.as_str() {
            "None" => MessageSecurityMode::None,
            "Sign" => MessageSecurityMode::Sign,
            "SignAndEncrypt" => MessageSecurityMode::SignAndEncrypt,
            other => return Err(format!("security mode {other:?} unknown")),
        };
        Ok((policy, mode))
    }

    /// The PKI directory to use, checked: with security, the bridge's own certificate and
    /// key must be there (unless the probe makes them).
    fn pki(&self, policy: SecurityPolicy) -> Result<PathBuf, String> {
        let Some(dir) = self
            .pki_dir
            .clone()
            .filter(|_| policy != SecurityPolicy::None)
        else {
            if policy != SecurityPolicy::None {
                return Err(format!("the policy {} needs a PKI directory", self.policy));
            }
            if self.create_keypair {
                return Err(
                    "a key pair is for a policy other than None (nothing would use it)".into(),
                );
            }
            // No certificate is used: a scratch directory satisfies the client.
            return Ok(std::env::temp_dir().join("mfc-opcua-pki"));
        };
        if !self.create_keypair {
            for file in [OWN_CERT, OWN_KEY] {
                if !dir.join(file).is_file() {
                    return Err(format!(
                        "{}: the bridge has no certificate or key there; make a pair with \
                         `plant-agent probe opcua {} --pki-dir {} --create-keypair` (or put \
                         your own there), then have the server trust {}",
                        dir.join(file).display(),
                        self.endpoint,
                        dir.display(),
                        dir.join(OWN_CERT).display()
                    ));
                }
            }
        }
        Ok(dir)
    }

    fn identity_token(&self) -> Result<IdentityToken, String> {
        Ok(match &self.identity {
            OpcUaUser::Anonymous => IdentityToken::Anonymous,
            OpcUaUser::User { name, password } => {
                if self.policy == "None" {
                    tracing::warn!(
                        server = self.endpoint,
                        "OPC UA: user {name}'s password may cross the network in plain text (security None): a trusted network only"
                    );
                }
                IdentityToken::new_user_name(name.clone(), password.clone())
            }
            OpcUaUser::Certificate { cert, key } => IdentityToken::new_x509_path(cert, key)
                .map_err(|e| format!("user certificate {}: {e}", cert.display()))?,
        })
    }
}

/// Where the bridge's certificate and key sit in its PKI directory (async-opcua's layout).
pub const OWN_CERT: &str = "own/cert.der";
/// See [`OWN_CERT`].
pub const OWN_KEY: &str = "private/private.pem";

/// A session opened: the runtime its event loop runs on, the session, and how many times
/// it reconnected so far.
pub(crate) type Opened = (tokio::runtime::Runtime, Arc<Session>, Arc<AtomicU64>);

/// A session as `spec` describes it, on a runtime of its own with one worker, where the
/// session's event loop runs (keep-alives, reconnection for ever, every request timeout
/// enforced). Errors say what failed and, where they can, what to do.
pub(crate) fn open_session(spec: &SessionSpec) -> Result<Opened, String> {
    let (policy, mode) = spec.security()?;
    let pki = spec.pki(policy)?;
    let identity = spec.identity_token()?;
    if policy != SecurityPolicy::None {
        private_key_guarded(&pki.join(OWN_KEY));
    }
    if let OpcUaUser::Certificate { key, .. } = &spec.identity {
        private_key_guarded(key);
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .thread_name("opcua-session")
        .enable_all()
        .build()
        .map_err(|e| format!("runtime: {e}"))?;
    let rejected_before = listing(&pki.join("rejected"));
    let mut server_cert = None;
    let session = rt.block_on(connect(
        spec,
        (policy, mode),
        &pki,
        identity,
        &mut server_cert,
    ));
    if spec.create_keypair {
        private_key_guarded(&pki.join(OWN_KEY));
    }
    match session {
        Ok((s, reconnections)) => Ok((rt, s, reconnections)),
        Err(e) => {
            // No runtime may be dropped on an async worker.
            crate::off_async(move || drop(rt));
            let trust = Trust {
                pki: &pki,
                rejected_before: &rejected_before,
                server_cert: server_cert.as_deref(),
            };
            let hint = trust.hint(spec, policy, &e);
            Err(e + &hint)
        }
    }
}

/// A private key readable by others than its owner is made private (a key the probe just
/// made), or, if that fails, reported: the bridge's identity is only as safe as its key.
#[cfg(unix)]
fn private_key_guarded(key: &Path) {
    use std::os::unix::fs::PermissionsExt;
    let Ok(meta) = std::fs::metadata(key) else {
        return;
    };
    if meta.permissions().mode() & 0o077 == 0 {
        return;
    }
    let private = std::fs::Permissions::from_mode(0o600);
    if let Err(e) = std::fs::set_permissions(key, private) {
        tracing::warn!(
            "{}: readable by others than its owner, and not made private: {e}",
            key.display()
        );
    }
    if let Some(dir) = key.parent() {
        let _ = std::fs::set_permissions(dir, std::fs::Permissions::from_mode(0o700));
    }
}

#[cfg(not(unix))]
fn private_key_guarded(_key: &Path) {}

async fn connect(
    spec: &SessionSpec,
    (policy, mode): (SecurityPolicy, MessageSecurityMode),
    pki: &Path,
    identity: IdentityToken,
    server_cert: &mut Option<String>,
) -> Result<(Arc<Session>, Arc<AtomicU64>), String> {
    let secure = policy != SecurityPolicy::None;
    let client = ClientBuilder::new()
        .application_name("mfc plant-agent")
        .application_uri("urn:mfc:plant-agent")
        .product_uri("urn:mfc:plant-agent")
        .pki_dir(pki)
        .create_sample_keypair(spec.create_keypair)
        // With security, a server is trusted only if its certificate is in `trusted/`;
        // without, no certificate is looked at.
        .trust_server_certs(!secure)
        .verify_server_certs(secure)
        .session_retry_limit(-1)
        .session_retry_initial(Duration::from_millis(200))
        .session_retry_max(Duration::from_secs(2))
        .request_timeout(spec.request_timeout)
        .keep_alive_interval(Duration::from_secs(1))
        .min_publish_interval(spec.sampling_interval)
        // The bridge subscribes again itself after a reconnection: the library's own
        // re-creation ignores the items it fails to re-create.
        .recreate_subscriptions(false)
        .client()
        .map_err(|e| format!("client: {}", e.join("; ")))?;
    let endpoints = tokio::time::timeout(
        spec.connect_timeout,
        client.get_server_endpoints_from_url(spec.endpoint.as_str()),
    )
    .await
    .map_err(|_| "asking for its endpoints: timed out".to_string())?
    .map_err(|e| format!("asking for its endpoints: {e}"))?;
    let ours = endpoints
        .iter()
        .find(|e| e.security_policy_uri.as_ref() == policy.to_uri() && e.security_mode == mode);
    *server_cert = ours.and_then(|e| {
        opcua::crypto::X509::from_byte_string(&e.server_certificate)
            .ok()
            .map(|c| opcua::crypto::CertificateStore::cert_file_name(&c))
    });
    if ours.is_none() {
        return Err(format!(
            "the server has no endpoint with {}/{}; it offers {}",
            spec.policy,
            spec.mode,
            offered(&endpoints)
        ));
    }
    let target = (
        spec.endpoint.as_str(),
        policy.to_str(),
        mode,
        UserTokenPolicy::anonymous(),
    );
    let (session, event_loop) = client
        .session_builder()
        .with_endpoints(endpoints)
        .with_connector(NoDelay)
        .connect_to_matching_endpoint(target)
        .and_then(|b| {
            b.user_identity_token(identity)
                .build(client.certificate_store().clone())
        })
        .map_err(|e| format!("connecting: {e}"))?;
    let (last, reconnections) = watch(event_loop);
    if tokio::time::timeout(spec.connect_timeout, session.wait_for_connection())
        .await
        .is_err()
    {
        let why = last.lock().ok().and_then(|l| l.clone());
        return Err(format!(
            "opening the session: not open after {:?}{}",
            spec.connect_timeout,
            why.map(|w| format!(" (last failure: {w})"))
                .unwrap_or_default()
        ));
    }
    Ok((session, reconnections))
}

/// Run the session's event loop, keeping its last failure (the reason a session cannot
/// open, a refused user, an untrusted certificate, a server that is not there, is only in
/// its events, and an operator needs it) and counting its reconnections (after which a
/// subscription is made again).
fn watch<T>(
    event_loop: opcua::client::SessionEventLoop<T>,
) -> (Arc<std::sync::Mutex<Option<String>>>, Arc<AtomicU64>)
where
    T: opcua::client::transport::Connector + Send + Sync + 'static,
{
    let last = Arc::new(std::sync::Mutex::new(None::<String>));
    let seen = last.clone();
    let reconnections = Arc::new(AtomicU64::new(0));
    let counted = reconnections.clone();
    let events = event_loop.enter();
    tokio::spawn(async move {
        use futures::StreamExt;
        futures::pin_mut!(events);
        while let Some(event) = events.next().await {
            let failure = match event {
                Ok(
                    SessionPollResult::ConnectionLost(c) | SessionPollResult::ReconnectFailed(c),
                ) => c,
                Err(c) => c,
                Ok(SessionPollResult::Reconnected(_)) => {
                    counted.fetch_add(1, Ordering::SeqCst);
                    continue;
                }
                Ok(_) => continue,
            };
            if let Ok(mut l) = seen.lock() {
                *l = Some(failure.to_string());
            }
        }
    });
    (last, reconnections)
}

/// The policy/mode pairs a server offers, for an error message.
fn offered(endpoints: &[EndpointDescription]) -> String {
    let mut pairs: Vec<String> = endpoints
        .iter()
        .map(|e| {
            let uri = e.security_policy_uri.as_ref();
            let name = uri.rsplit('#').next().unwrap_or(uri);
            format!("{name}/{}", e.security_mode)
        })
        .collect();
    pairs.sort();
    pairs.dedup();
    if pairs.is_empty() {
        "none".into()
    } else {
        pairs.join(", ")
    }
}

fn listing(dir: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default()
}

/// What the bridge knows of certificates when a secure session failed.
struct Trust<'a> {
    pki: &'a Path,
    /// What `rejected/` held before the attempt.
    rejected_before: &'a [PathBuf],
    /// The file name the server's certificate has in a PKI directory, if it sent one.
    server_cert: Option<&'a str>,
}

impl Trust<'_> {
    /// What to do about certificates after a secure session failed with `error`: the
    /// server's certificate the bridge refused (now or before: the operator checks it and
    /// moves it to `trusted/`), a trusted one that fails the bridge's checks, or, when
    /// the server refused a certificate, the bridge's own (or the user's).
    fn hint(&self, spec: &SessionSpec, policy: SecurityPolicy, error: &str) -> String {
        if policy == SecurityPolicy::None {
            return String::new();
        }
        let (rejected, trusted) = (self.pki.join("rejected"), self.pki.join("trusted"));
        let new = listing(&rejected)
            .into_iter()
            .find(|p| !self.rejected_before.contains(p));
        let theirs = |dir: &Path| {
            self.server_cert
                .map(|n| dir.join(n))
                .filter(|p| p.is_file())
        };
        if let Some(cert) = new.or_else(|| theirs(&rejected)) {
            return format!(
                "; the server's certificate is not trusted: it is in {}; check it (the \
                 server's operator knows its thumbprint) and move it to {}",
                cert.display(),
                trusted.display()
            );
        }
        let checks = [
            "BadCertificateHostNameInvalid",
            "BadCertificateTimeInvalid",
            "BadCertificateUriInvalid",
            "BadCertificateInvalid",
        ];
        if let Some(cert) = theirs(&trusted).filter(|_| checks.iter().any(|c| error.contains(c))) {
            return format!(
                "; the server's certificate {} is trusted but fails the bridge's checks (the \
                 host in the endpoint, its validity dates, its application URI)",
                cert.display()
            );
        }
        if error.contains("Certificate") || error.contains("BadSecurityChecksFailed") {
            let user = match &spec.identity {
                OpcUaUser::Certificate { cert, .. } => {
                    format!(", or the user's certificate {}", cert.display())
                }
                _ => String::new(),
            };
            return format!(
                "; the server refused the bridge: have it trust {}{user} (for {})",
                self.pki.join(OWN_CERT).display(),
                spec.endpoint
            );
        }
        String::new()
    }
}
