//! The console's HTTP side: the page (one HTML, one script, one style sheet, bundled in the
//! binary: no CDN, nothing fetched from outside) and a small JSON API the page polls.
//!
//! | method and path | what |
//! |---|---|
//! | `GET /` | the page |
//! | `GET /api/devices` | the device list (alive, served by, mode) and the console's counters |
//! | `GET /api/devices/{id}` | status, configuration per channel (law, output map, envelope) |
//! | `GET /api/devices/{id}/series?since=N` | the plot points from position `N` on |
//! | `POST /api/devices/{id}/gains` | `{"channel": 1, "fields": {"kp": 12}}`: a partial change |
//! | `POST /api/devices/{id}/reference` | `{"values": [0, 0.05]}`: a constant reference per channel |
//!
//! A change is checked here first (the envelope, [`fleet::check_update`]) and then by the
//! service, whose refusal reason the page shows as it is. The console has the operator's
//! Zenoh identity, so its HTTP side must not be usable from another site: every request
//! must name an allowed `Host` (a rebound DNS name is refused), and a `POST` must be
//! `Content-Type: application/json` (which a cross-site form cannot send without a CORS
//! preflight the console never grants) from the console's own origin (`Origin`,
//! `Sec-Fetch-Site`). Bodies are bounded ([`MAX_BODY`]). Who may use it is
//! [`crate::sessions`]'s: with `[login]`, a person with a session or a client certificate,
//! and changes only by those whose role may change; without, the console answers on
//! loopback only, as its own operator.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::extract::rejection::JsonRejection;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Extension, Json, Router};
use protocol::{keys, pb};
use serde::{Deserialize, Serialize};
use serde_json::json;
use transport::ops::{self, OpError};

use crate::fleet::{self, mode_of, ChannelView};
use crate::login::Identity;
use crate::net::Console;
use crate::sessions::{self, Doors};

/// Largest request body (bytes): a change is a few hundred bytes.
pub const MAX_BODY: usize = 16 * 1024;

const PAGE: &str = include_str!("page/index.html");
const SCRIPT: &str = include_str!("page/console.js");
const STYLE: &str = include_str!("page/console.css");

/// The page may load only its own script and style, talk only to its own origin, and not
/// be framed (a framing page could trick a click on the gain form).
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
                   connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// Who may talk to the console: the `Host` names it answers to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Guard {
    hosts: Vec<String>,
    /// `http://` or `https://`: the origin a change must come from.
    scheme: &'static str,
}

impl Guard {
    /// The names of `listen` (the bound address), `localhost:PORT` on loopback or on an
    /// unspecified address, and `extra` (from the settings); `https`: the page is served
    /// over HTTPS, so its origin is `https://…`.
    pub fn new(listen: SocketAddr, extra: &[String], https: bool) -> Self {
        let port = listen.port();
        let mut hosts = vec![listen.to_string()];
        let ip = listen.ip();
        if ip.is_loopback() || ip.is_unspecified() {
            hosts.push(format!("localhost:{port}"));
            hosts.push(format!("127.0.0.1:{port}"));
            hosts.push(format!("[::1]:{port}"));
        }
        hosts.extend(extra.iter().cloned());
        for h in &mut hosts {
            h.make_ascii_lowercase();
        }
        hosts.sort();
        hosts.dedup();
        let scheme = if https { "https://" } else { "http://" };
        Self { hosts, scheme }
    }

    /// The accepted `Host` values.
    pub fn hosts(&self) -> &[String] {
        &self.hosts
    }

    /// Whether a request may go on; if not, the status and the reason.
    pub fn check(&self, method: &Method, headers: &HeaderMap) -> Result<(), (StatusCode, String)> {
        let text = |name: header::HeaderName| {
            headers
                .get(&name)
                .map(|v| v.to_str().map(str::to_ascii_lowercase).unwrap_or_default())
        };
        let forbidden = |why: String| Err((StatusCode::FORBIDDEN, why));
        let host = text(header::HOST).unwrap_or_default();
        if !self.hosts.contains(&host) {
            return forbidden(format!(
                "host {host:?} is not one this console answers to ({}); add it to allowed_hosts",
                self.hosts.join(", ")
            ));
        }
        if method == Method::GET || method == Method::HEAD {
            return Ok(());
        }
        let ctype = text(header::CONTENT_TYPE).unwrap_or_default();
        if !ctype.starts_with("application/json") {
            return Err((
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "a change must be sent as Content-Type: application/json".into(),
            ));
        }
        if let Some(origin) = text(header::ORIGIN) {
            let ok = origin
                .strip_prefix(self.scheme)
                .is_some_and(|o| self.hosts.iter().any(|h| h == o));
            if !ok {
                return forbidden(format!("origin {origin:?} may not change anything here"));
            }
        }
        if let Some(site) = headers.get("sec-fetch-site") {
            let site = site.to_str().unwrap_or_default();
            if site != "same-origin" && site != "none" {
                return forbidden(format!("a {site} request may not change anything here"));
            }
        }
        Ok(())
    }
}

async fn guard(State(g): State<Arc<Guard>>, req: Request, next: Next) -> Response {
    match g.check(req.method(), req.headers()) {
        Ok(()) => next.run(req).await,
        Err((status, reason)) => {
            tracing::warn!("refused {} {}: {reason}", req.method(), req.uri().path());
            (
                status,
                Json(json!({ "accepted": false, "refused_by": "console", "reason": reason })),
            )
                .into_response()
        }
    }
}

/// The routes, with the guard (first), then who asks ([`sessions::identify`]), and the
/// body limit.
pub fn router(console: Arc<Console>, guard_: Guard, doors: Arc<Doors>) -> Router {
    let login = Router::new()
        .route("/api/me", get(sessions::me))
        .route("/api/login", post(sessions::login))
        .route("/api/logout", post(sessions::logout))
        .with_state(doors.clone());
    Router::new()
        .route("/", get(page))
        .route("/console.js", get(script))
        .route("/console.css", get(style))
        .route("/api/devices", get(devices))
        .route("/api/devices/{id}", get(detail))
        .route("/api/devices/{id}/series", get(series))
        .route("/api/devices/{id}/audit", get(audit))
        .route("/api/devices/{id}/gains", post(gains))
        .route("/api/devices/{id}/reference", post(reference))
        .route("/api/devices/{id}/commission", post(commission))
        .with_state(console)
        .merge(login)
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .layer(middleware::from_fn_with_state(doors, sessions::identify))
        .layer(middleware::from_fn_with_state(Arc::new(guard_), guard))
}

fn asset(body: &'static str, content_type: &'static str) -> Response {
    let mut r = body.into_response();
    let h = r.headers_mut();
    h.insert(header::CONTENT_TYPE, HeaderValue::from_static(content_type));
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(CSP),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    r
}

async fn page() -> Response {
    asset(PAGE, "text/html; charset=utf-8")
}
async fn script() -> Response {
    asset(SCRIPT, "text/javascript; charset=utf-8")
}
async fn style() -> Response {
    asset(STYLE, "text/css; charset=utf-8")
}

fn not_found(id: &str) -> Response {
    (
        StatusCode::NOT_FOUND,
        Json(json!({ "error": format!("no device {:?} here", protocol::printable(id)) })),
    )
        .into_response()
}

async fn devices(State(c): State<Arc<Console>>) -> Response {
    let now = c.now();
    let f = c.fleet();
    Json(json!({
        "now": now,
        "devices": f.list(now),
        "counters": f.counters(),
    }))
    .into_response()
}

/// One device's details for the page.
#[derive(Serialize)]
struct Detail {
    id: String,
    alive: bool,
    served_by: Option<String>,
    mode: Option<&'static str>,
    channels: usize,
    status: Option<pb::DeviceStatus>,
    status_age: Option<f64>,
    status_mode: Option<&'static str>,
    config: Option<Vec<ChannelView>>,
    config_age: Option<f64>,
    config_error: Option<String>,
    /// The reference of the last point (what a reference form starts from).
    reference_now: Vec<f64>,
}

async fn detail(State(c): State<Arc<Console>>, Path(id): Path<String>) -> Response {
    let now = c.now();
    let mut f = c.fleet();
    f.watch(&id, now);
    let Some(d) = f.device(&id) else {
        return not_found(&id);
    };
    let out = Detail {
        id: id.clone(),
        alive: d.alive,
        served_by: d.served_by.clone(),
        mode: d.last_sample_at.map(|_| mode_of(d.last_flags)),
        channels: d
            .channels
            .max(d.config.as_ref().map_or(0, |c| c.0.channels.len())),
        status_mode: d.status.as_ref().map(|s| mode_of(s.0.last_flags)),
        status: d.status.as_ref().map(|s| s.0.clone()),
        status_age: d.status.as_ref().map(|s| now - s.1),
        config: d.config.as_ref().map(|c| fleet::channel_views(&c.0)),
        config_age: d.config.as_ref().map(|c| now - c.1),
        config_error: d.config_error.clone(),
        reference_now: d.last_point().map(|p| p.r.clone()).unwrap_or_default(),
    };
    let wanted = d.config.is_none() && d.served_by.is_some();
    drop(f);
    if wanted {
        c.config_wanted.notify_one();
    }
    Json(out).into_response()
}

/// `GET /api/devices/{id}/audit`: the device's latest audited changes, from the service
/// that answers for it (asked as the console's operator: a service with access rules
/// answers only for the devices that operator may see).
async fn audit(
    State(c): State<Arc<Console>>,
    Extension(who): Extension<Identity>,
    Path(id): Path<String>,
) -> Response {
    if c.fleet().device(&id).is_none() {
        return not_found(&id);
    }
    let op = c.operator.as_named(&who.name);
    match transport::ops::audit(&op, Some(&id), c.timeout()).await {
        Ok(logs) => {
            let entries: Vec<pb::AuditEntry> = logs.into_iter().flat_map(|l| l.entries).collect();
            Json(json!({ "entries": entries })).into_response()
        }
        Err(e) => op_failed(e),
    }
}

#[derive(Deserialize)]
struct Since {
    #[serde(default)]
    since: u64,
}

async fn series(
    State(c): State<Arc<Console>>,
    Path(id): Path<String>,
    Query(q): Query<Since>,
) -> Response {
    match c.fleet().series(&id, q.since) {
        Some(s) => Json(s).into_response(),
        None => not_found(&id),
    }
}

/// A refusal or failure of a change, for the page: who refused (`console`: the request or
/// the envelope; `service`: the controller's reason as it gave it; `network`: no answer).
fn refused(status: StatusCode, by: &str, reason: String) -> Response {
    (
        status,
        Json(json!({ "accepted": false, "refused_by": by, "reason": reason })),
    )
        .into_response()
}

fn op_failed(e: OpError) -> Response {
    match e {
        OpError::Refused { reason, .. } => {
            refused(StatusCode::UNPROCESSABLE_ENTITY, "service", reason)
        }
        OpError::Usage(reason) => refused(StatusCode::BAD_REQUEST, "console", reason),
        e @ OpError::NoAnswer { .. } => {
            refused(StatusCode::GATEWAY_TIMEOUT, "network", e.to_string())
        }
        e => refused(StatusCode::BAD_GATEWAY, "network", e.to_string()),
    }
}

/// A request body, or why it is not one (the status axum gives it, e.g. 413 over
/// [`MAX_BODY`], and the decoder's reason).
fn body<T>(b: Result<Json<T>, JsonRejection>) -> Result<T, (StatusCode, String)> {
    b.map(|Json(t)| t).map_err(|e| (e.status(), e.body_text()))
}

/// What every change starts with: who asks may change (not a viewer), the body decodes,
/// the id is one; the operator to ask the service as, and the change. Otherwise the
/// console's refusal.
fn admitted<T>(
    c: &Console,
    who: &Identity,
    id: &str,
    b: Result<Json<T>, JsonRejection>,
) -> Result<(ops::Operator, T), Box<Response>> {
    let no = |status, reason| Box::new(refused(status, "console", reason));
    if let Err((status, reason)) = sessions::may_change(who) {
        return Err(no(status, reason));
    }
    let change = body(b).map_err(|(status, reason)| no(status, reason))?;
    if let Err(e) = keys::check_id(id) {
        return Err(no(StatusCode::BAD_REQUEST, e.to_string()));
    }
    Ok((c.operator.as_named(&who.name), change))
}

/// `POST /api/devices/{id}/gains`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct GainChange {
    channel: u32,
    fields: BTreeMap<String, f64>,
}

async fn gains(
    State(c): State<Arc<Console>>,
    Extension(who): Extension<Identity>,
    Path(id): Path<String>,
    b: Result<Json<GainChange>, JsonRejection>,
) -> Response {
    let (op, change) = match admitted(&c, &who, &id, b) {
        Ok(x) => x,
        Err(refusal) => return *refusal,
    };
    if change.fields.len() > mfc::params::PARAMS.len() {
        return refused(StatusCode::BAD_REQUEST, "console", "too many fields".into());
    }
    let assignments: Vec<String> = change
        .fields
        .iter()
        .map(|(k, v)| format!("{k}={v}"))
        .collect();
    let update = match ops::parse_update(change.channel, &assignments) {
        Ok(u) => u,
        Err(e) => return op_failed(e),
    };
    // The configuration in force now (not the page's copy): the envelope to check against.
    let config = match ops::config(&op, &id, c.timeout()).await {
        Ok(x) => x,
        Err(e) => return op_failed(e),
    };
    c.fleet().apply_config(&id, config.clone(), c.now());
    if let Err(reason) = fleet::check_update(&update, &config) {
        tracing::info!("refused a change of {id}: {reason}");
        return refused(StatusCode::UNPROCESSABLE_ENTITY, "console", reason);
    }
    tracing::info!(
        user = %who.name,
        "change of {id} channel {}: {}",
        change.channel,
        assignments.join(" ")
    );
    match ops::update(&op, &id, update, c.timeout()).await {
        Ok(ops::Changed {
            config,
            held_by,
            durable,
        }) => {
            let views = fleet::channel_views(&config);
            c.fleet().apply_config(&id, config, c.now());
            Json(json!({ "accepted": true, "changed": change.fields, "channel": change.channel, "config": views, "held_by": held_by, "durable": durable }))
                .into_response()
        }
        Err(e) => {
            tracing::info!("the service refused a change of {id}: {e}");
            op_failed(e)
        }
    }
}

/// `POST /api/devices/{id}/reference`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ReferenceChange {
    values: Vec<f64>,
}

async fn reference(
    State(c): State<Arc<Console>>,
    Extension(who): Extension<Identity>,
    Path(id): Path<String>,
    b: Result<Json<ReferenceChange>, JsonRejection>,
) -> Response {
    let (op, change) = match admitted(&c, &who, &id, b) {
        Ok(x) => x,
        Err(refusal) => return *refusal,
    };
    let config = match ops::config(&op, &id, c.timeout()).await {
        Ok(x) => x,
        Err(e) => return op_failed(e),
    };
    if let Err(reason) = fleet::check_reference(&change.values, config.channels.len()) {
        return refused(StatusCode::UNPROCESSABLE_ENTITY, "console", reason);
    }
    let pieces: Vec<Vec<mfc::trajectory::Piece>> = change
        .values
        .iter()
        .map(|&value| vec![mfc::trajectory::Piece::Constant { value }])
        .collect();
    tracing::info!(user = %who.name, "reference of {id}: constant {:?}", change.values);
    let r = protocol::convert::reference_to_pb(&pieces, 0.0);
    match ops::set_reference(&op, &id, r, c.timeout()).await {
        Ok(ops::Changed {
            config,
            held_by,
            durable,
        }) => {
            c.fleet().apply_config(&id, config, c.now());
            Json(json!({ "accepted": true, "values": change.values, "held_by": held_by, "durable": durable }))
                .into_response()
        }
        Err(e) => op_failed(e),
    }
}

/// `POST /api/devices/{id}/commission`: `start` (with the excitation), `confirm` or
/// `abort` a commissioning run (`CommissionRequest` in the `.proto`); the answer carries
/// the run's state as the device's status then says.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CommissionChange {
    action: String,
    channel: u32,
    #[serde(default)]
    amplitude: f64,
    #[serde(default)]
    max_deviation: f64,
    #[serde(default)]
    period: f64,
    #[serde(default)]
    cycles: u32,
    /// `confirm`, `abort`: the run the page shows (0: the device's last).
    #[serde(default)]
    run: u64,
}

impl CommissionChange {
    fn request(&self) -> Result<pb::CommissionRequest, String> {
        use pb::CommissionAction as A;
        let action = match self.action.as_str() {
            "start" => A::CommissionStart,
            "confirm" => A::CommissionConfirm,
            "abort" => A::CommissionAbort,
            a => {
                return Err(format!(
                    "action {:?}: start, confirm or abort",
                    protocol::printable(a)
                ))
            }
        };
        Ok(pb::CommissionRequest {
            action: action as i32,
            channel: self.channel,
            amplitude: self.amplitude,
            max_deviation: self.max_deviation,
            period: self.period,
            cycles: self.cycles,
            run: self.run,
            reason: "console".into(),
            ..Default::default()
        })
    }
}

async fn commission(
    State(c): State<Arc<Console>>,
    Extension(who): Extension<Identity>,
    Path(id): Path<String>,
    b: Result<Json<CommissionChange>, JsonRejection>,
) -> Response {
    let (op, change) = match admitted(&c, &who, &id, b) {
        Ok(x) => x,
        Err(refusal) => return *refusal,
    };
    let req = match change.request() {
        Ok(r) => r,
        Err(reason) => return refused(StatusCode::BAD_REQUEST, "console", reason),
    };
    tracing::info!(user = %who.name, "commissioning of {id} channel {}: {}", change.channel, change.action);
    match ops::commission(&op, &id, req, c.timeout()).await {
        Ok(ops::Changed {
            config,
            held_by,
            durable,
        }) => {
            c.fleet().apply_config(&id, config, c.now());
            let status = ops::device_status(&op, &id, c.timeout()).await.ok();
            let run = status.and_then(|s| s.commission);
            Json(json!({ "accepted": true, "commission": run, "held_by": held_by, "durable": durable })).into_response()
        }
        Err(e) => op_failed(e),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn headers(pairs: &[(&'static str, &str)]) -> HeaderMap {
        let mut h = HeaderMap::new();
        for (k, v) in pairs {
            h.insert(*k, HeaderValue::from_str(v).unwrap());
        }
        h
    }

    #[test]
    fn only_the_consoles_own_origin_may_change_anything() {
        let g = Guard::new(
            "127.0.0.1:8080".parse().unwrap(),
            &["Console.lan:8080".into()],
            false,
        );
        assert!(g.hosts().contains(&"localhost:8080".to_string()));
        assert!(g.hosts().contains(&"console.lan:8080".to_string()));
        let get = Method::GET;
        let post = Method::POST;
        assert!(g
            .check(&get, &headers(&[("host", "127.0.0.1:8080")]))
            .is_ok());
        assert!(g
            .check(&get, &headers(&[("host", "localhost:8080")]))
            .is_ok());
        // A rebound name, or none.
        assert!(g
            .check(&get, &headers(&[("host", "evil.example:8080")]))
            .is_err());
        assert!(g.check(&get, &headers(&[])).is_err());
        let json = ("content-type", "application/json");
        let own = ("host", "127.0.0.1:8080");
        assert!(g.check(&post, &headers(&[own, json])).is_ok());
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("origin", "http://127.0.0.1:8080")])
            )
            .is_ok());
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("sec-fetch-site", "same-origin")])
            )
            .is_ok());
        // A form post (no JSON), another origin, a cross-site fetch.
        let (s, _) = g
            .check(&post, &headers(&[own, ("content-type", "text/plain")]))
            .unwrap_err();
        assert_eq!(s, StatusCode::UNSUPPORTED_MEDIA_TYPE);
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("origin", "http://evil.example")])
            )
            .is_err());
        assert!(g
            .check(&post, &headers(&[own, json, ("origin", "null")]))
            .is_err());
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("sec-fetch-site", "cross-site")])
            )
            .is_err());
    }

    #[test]
    fn over_https_a_change_comes_from_the_https_origin_only() {
        let g = Guard::new("10.0.0.5:8443".parse().unwrap(), &[], true);
        assert_eq!(
            g.hosts(),
            ["10.0.0.5:8443"],
            "no localhost names off loopback"
        );
        let post = Method::POST;
        let own = ("host", "10.0.0.5:8443");
        let json = ("content-type", "application/json");
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("origin", "https://10.0.0.5:8443")])
            )
            .is_ok());
        assert!(g
            .check(
                &post,
                &headers(&[own, json, ("origin", "http://10.0.0.5:8443")])
            )
            .is_err());
    }

    #[test]
    fn the_page_is_bundled_and_names_only_its_own_assets() {
        assert!(PAGE.contains("console.js") && PAGE.contains("console.css"));
        for text in [PAGE, SCRIPT, STYLE] {
            assert!(!text.contains("http://") && !text.contains("https://"));
        }
    }
}
