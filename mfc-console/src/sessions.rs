//! The HTTP side of logins ([`crate::login`] decides; this wires it to requests).
//!
//! | method and path | what |
//! |---|---|
//! | `GET /api/me` | who the request is made by (`401` and how to log in, if nobody) |
//! | `POST /api/login` | `{"name": "alice", "password": "…"}`: a session cookie |
//! | `POST /api/logout` | the session closed |
//!
//! Every request first passes [`identify`]: the session's cookie, else the HTTPS client
//! certificate's name, else (without `[login]`) the console's own operator. The page and
//! these three routes answer anyone; every other route needs someone, and a change needs
//! a role that may change. The cookie is `HttpOnly` (no script reads it),
//! `SameSite=Strict` (no other site's page sends it) and, over HTTPS, `Secure`; a login is
//! a JSON `POST` from the console's own origin like any change (`http::Guard`), so another
//! site cannot log a browser in under its own account either.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Instant;

use axum::extract::rejection::JsonRejection;
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use ring::rand::SecureRandom;
use serde::Deserialize;
use serde_json::json;
use transport::https::PeerName;

use crate::login::{cookie, Identity, LoginSpec, Proof, Role, Sessions, MAX_PASSWORD};

/// The session cookie's name.
pub const COOKIE: &str = "mfc_session";

/// The routes that answer before anyone is known.
const PUBLIC: [&str; 6] = [
    "/",
    "/console.js",
    "/console.css",
    "/api/me",
    "/api/login",
    "/api/logout",
];

/// Who may use the console, and the sessions open.
pub struct Doors {
    spec: Option<LoginSpec>,
    sessions: Mutex<Sessions>,
    /// One password check at a time: argon2 is made to be slow, and a flood of logins
    /// must not take every core from the loops' traffic.
    checking: tokio::sync::Semaphore,
    /// A hash checked for unknown names too, so that the time taken does not tell which
    /// names exist.
    decoy: String,
    /// Without `[login]`: everyone acts as this operator.
    open_as: String,
    secure: bool,
    start: Instant,
}

impl Doors {
    /// The doors of `spec` (`None`: open, everyone is `open_as`); `secure`: the page is
    /// served over HTTPS.
    pub fn new(spec: Option<LoginSpec>, open_as: String, secure: bool) -> Self {
        let sessions = Sessions::new(spec.as_ref().unwrap_or(&LoginSpec {
            users: vec![],
            idle_minutes: 1.0,
            max_hours: 1.0,
            max_sessions: 1,
            https: None,
        }));
        // Only a console with logins checks passwords (argon2 is slow by design).
        let decoy = match &spec {
            Some(_) => crate::cli::hash_password("decoy: no such user").unwrap_or_default(),
            None => String::new(),
        };
        Self {
            spec,
            sessions: Mutex::new(sessions),
            checking: tokio::sync::Semaphore::new(1),
            decoy,
            open_as,
            secure,
            start: Instant::now(),
        }
    }

    fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn sessions(&self) -> MutexGuard<'_, Sessions> {
        self.sessions.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Whether people must log in.
    pub fn closed(&self) -> bool {
        self.spec.is_some()
    }

    /// Who makes a request with these headers over a connection of this client
    /// certificate's name.
    pub fn who(&self, headers: &HeaderMap, peer: Option<&PeerName>) -> Option<Identity> {
        let Some(spec) = &self.spec else {
            return Some(Identity {
                name: self.open_as.clone(),
                role: Role::Operator,
                proof: Proof::Open,
            });
        };
        let token = headers
            .get(header::COOKIE)
            .and_then(|v| v.to_str().ok())
            .and_then(|c| cookie(c, COOKIE));
        if let Some(who) = token.and_then(|t| self.sessions().find(t, self.now())) {
            return Some(who);
        }
        let name = peer.and_then(|p| p.0.as_deref())?;
        let user = spec.user(name)?;
        Some(Identity {
            name: user.name.clone(),
            role: user.role,
            proof: Proof::Certificate,
        })
    }

    fn set_cookie(&self, value: &str, max_age: Option<u64>) -> HeaderValue {
        let mut c = format!("{COOKIE}={value}; Path=/; HttpOnly; SameSite=Strict");
        if self.secure {
            c.push_str("; Secure");
        }
        if let Some(s) = max_age {
            c.push_str(&format!("; Max-Age={s}"));
        }
        HeaderValue::from_str(&c).unwrap_or_else(|_| HeaderValue::from_static(""))
    }
}

fn refusal(status: StatusCode, reason: String) -> Response {
    (
        status,
        Json(json!({ "accepted": false, "refused_by": "console", "reason": reason })),
    )
        .into_response()
}

/// The middleware: the request's [`Identity`] in its extensions, or `401` where one is
/// needed.
pub async fn identify(State(d): State<Arc<Doors>>, mut req: Request, next: Next) -> Response {
    let who = d.who(req.headers(), req.extensions().get::<PeerName>());
    match who {
        Some(w) => {
            req.extensions_mut().insert(w);
            next.run(req).await
        }
        None if PUBLIC.contains(&req.uri().path()) => next.run(req).await,
        None => refusal(
            StatusCode::UNAUTHORIZED,
            "log in first: this console has users, and the request named none".into(),
        ),
    }
}

/// Whether `who` may change anything; if not, the status and the reason.
pub fn may_change(who: &Identity) -> Result<(), (StatusCode, String)> {
    if who.role.may(crate::login::Action::Change) {
        return Ok(());
    }
    tracing::warn!(user = %who.name, "refused a change: a {}", who.role.name());
    Err((
        StatusCode::FORBIDDEN,
        format!(
            "{} is a {} here: viewers see, operators change",
            who.name,
            who.role.name()
        ),
    ))
}

/// `GET /api/me`.
pub async fn me(State(d): State<Arc<Doors>>, who: Option<Extension<Identity>>) -> Response {
    match who {
        Some(Extension(w)) => {
            Json(json!({ "name": w.name, "role": w.role, "proof": w.proof, "closed": d.closed() }))
                .into_response()
        }
        None => (
            StatusCode::UNAUTHORIZED,
            Json(json!({ "reason": "nobody is logged in", "closed": true })),
        )
            .into_response(),
    }
}

/// `POST /api/login`.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PasswordLogin {
    name: String,
    password: String,
}

/// `POST /api/login`: a password checked (one at a time, with the name's lock), then a
/// fresh session.
pub async fn login(
    State(d): State<Arc<Doors>>,
    b: Result<Json<PasswordLogin>, JsonRejection>,
) -> Response {
    let Some(spec) = &d.spec else {
        return refusal(
            StatusCode::BAD_REQUEST,
            "this console has no logins ([login] is not set)".into(),
        );
    };
    let Json(c) = match b {
        Ok(c) => c,
        Err(e) => return refusal(e.status(), e.body_text()),
    };
    if protocol::keys::check_id(&c.name).is_err() || c.password.len() > MAX_PASSWORD {
        return refusal(StatusCode::UNAUTHORIZED, "wrong name or password".into());
    }
    if let Err(wait) = d.sessions().may_try(&c.name, d.now()) {
        tracing::warn!(user = %c.name, "login refused: locked for {wait:.0} s after wrong passwords");
        let mut r = refusal(
            StatusCode::TOO_MANY_REQUESTS,
            format!(
                "too many wrong passwords for {}: try again in {wait:.0} s",
                c.name
            ),
        );
        r.headers_mut()
            .insert(header::RETRY_AFTER, HeaderValue::from(wait.ceil() as u64));
        return r;
    }
    let user = spec.user(&c.name).filter(|u| u.password_hash.is_some());
    let hash = user
        .and_then(|u| u.password_hash.clone())
        .unwrap_or_else(|| d.decoy.clone());
    let Ok(_permit) = d.checking.acquire().await else {
        return refusal(StatusCode::SERVICE_UNAVAILABLE, "shutting down".into());
    };
    let password = c.password;
    let right = tokio::task::spawn_blocking(move || crate::cli::verify_password(&hash, &password))
        .await
        .unwrap_or(false);
    let Some(user) = user.filter(|_| right) else {
        d.sessions().failed(&c.name, d.now());
        tracing::warn!(user = %c.name, "login refused: wrong name or password");
        return refusal(StatusCode::UNAUTHORIZED, "wrong name or password".into());
    };
    let mut bits = [0u8; 32];
    if ring::rand::SystemRandom::new().fill(&mut bits).is_err() {
        return refusal(
            StatusCode::SERVICE_UNAVAILABLE,
            "no randomness for a session".into(),
        );
    }
    let token: String = bits.iter().map(|b| format!("{b:02x}")).collect();
    let who = Identity {
        name: user.name.clone(),
        role: user.role,
        proof: Proof::Password,
    };
    {
        let mut s = d.sessions();
        s.succeeded(&c.name);
        s.open(token.clone(), who.clone(), d.now());
    }
    tracing::info!(user = %who.name, role = who.role.name(), "logged in");
    let mut r =
        Json(json!({ "name": who.name, "role": who.role, "proof": who.proof })).into_response();
    r.headers_mut()
        .insert(header::SET_COOKIE, d.set_cookie(&token, None));
    r
}

/// `POST /api/logout`: the session closed and its cookie cleared.
pub async fn logout(State(d): State<Arc<Doors>>, headers: HeaderMap) -> Response {
    let token = headers
        .get(header::COOKIE)
        .and_then(|v| v.to_str().ok())
        .and_then(|c| cookie(c, COOKIE));
    let closed = token.is_some_and(|t| d.sessions().close(t));
    let mut r = Json(json!({ "closed": closed })).into_response();
    r.headers_mut()
        .insert(header::SET_COOKIE, d.set_cookie("", Some(0)));
    r
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::login::UserSpec;

    fn spec() -> LoginSpec {
        let user = |name: &str, role, password_hash: Option<String>| UserSpec {
            name: name.into(),
            role,
            password_hash,
        };
        LoginSpec {
            users: vec![
                user(
                    "alice",
                    Role::Operator,
                    Some(crate::cli::hash_password("pw").unwrap()),
                ),
                user("vera", Role::Viewer, None),
            ],
            idle_minutes: 30.0,
            max_hours: 12.0,
            max_sessions: 4,
            https: None,
        }
    }

    fn cookie_header(token: &str) -> HeaderMap {
        let mut h = HeaderMap::new();
        h.insert(
            header::COOKIE,
            HeaderValue::from_str(&format!("a=b; {COOKIE}={token}")).unwrap(),
        );
        h
    }

    #[test]
    fn a_request_is_made_by_its_session_or_its_certificate_or_nobody() {
        let d = Doors::new(Some(spec()), "desk".into(), true);
        let none = HeaderMap::new();
        assert_eq!(d.who(&none, None), None);
        assert_eq!(d.who(&none, Some(&PeerName(None))), None);
        // A certificate of a user: that user, with the role the settings give.
        let vera = d.who(&none, Some(&PeerName(Some("vera".into())))).unwrap();
        assert_eq!((vera.role, vera.proof), (Role::Viewer, Proof::Certificate));
        assert!(may_change(&vera).is_err());
        // A certificate of the CA but of nobody listed: nobody.
        assert_eq!(d.who(&none, Some(&PeerName(Some("mallory".into())))), None);
        // A session: its person, whatever the certificate says.
        let alice = Identity {
            name: "alice".into(),
            role: Role::Operator,
            proof: Proof::Password,
        };
        d.sessions().open("t0k3n".into(), alice.clone(), d.now());
        assert_eq!(
            d.who(
                &cookie_header("t0k3n"),
                Some(&PeerName(Some("vera".into())))
            ),
            Some(alice.clone())
        );
        assert!(may_change(&alice).is_ok());
        assert_eq!(d.who(&cookie_header("forged"), None), None);
        // Its cookie: not for scripts, not for other sites, only over TLS.
        let c = d.set_cookie("t0k3n", None);
        assert_eq!(
            c.to_str().unwrap(),
            "mfc_session=t0k3n; Path=/; HttpOnly; SameSite=Strict; Secure"
        );
    }

    #[test]
    fn without_login_everyone_is_the_consoles_operator() {
        let d = Doors::new(None, "alice".into(), false);
        let who = d.who(&HeaderMap::new(), None).unwrap();
        assert_eq!(
            (who.name.as_str(), who.role, who.proof),
            ("alice", Role::Operator, Proof::Open)
        );
        assert!(!d.closed());
        assert!(!d
            .set_cookie("x", Some(0))
            .to_str()
            .unwrap()
            .contains("Secure"));
    }
}
