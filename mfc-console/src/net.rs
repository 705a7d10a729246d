//! The Zenoh side of the console: what it listens to and what it asks, feeding
//! [`crate::fleet`]. Wiring only: every message is checked by the fleet's parsers, and
//! every decision is the fleet's.
//!
//! * liveliness of plants (`mfc/v1/alive/plant/*`, with history, so plants already up
//!   are listed at once): devices appear and disappear live;
//! * samples and commands on every key a loop uses: `device/*/sample` and the shard keys
//!   (`shard/*/device/*/sample`, where agents publish), `device/*/command`, and gateways'
//!   batches (`[shard/*/]gateway/*/samples`, `gateway/*/commands`);
//! * a poll of every service's status (`transport::ops::services`, one query for all
//!   devices: who serves whom, counters, round trips, F estimates, envelope);
//! * a poll of the configuration of the devices a page is showing (and at once when a page
//!   opens one not read yet).
//!
//! Zenoh callbacks run on zenoh's threads: they parse outside the lock and hold it only to
//! apply, never across an `.await`. Nothing here blocks in async code.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use protocol::keys;
use tokio::task::JoinHandle;
use transport::ops;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::fleet::{self, FleetView};
use crate::settings::Settings;
use crate::ConsoleError;

/// A page that has not asked for a device's details for this long stops its configuration
/// poll (seconds).
pub const WATCH_WINDOW: f64 = 10.0;

/// The console's state shared by the Zenoh side and the HTTP side.
pub struct Console {
    /// The operator's session: every query goes out with its identity.
    pub session: Session,
    /// The same session with the operators' key: queries go out through it, and only
    /// replies sealed with that key are shown (`transport::ops::Asker`).
    pub operator: transport::ops::Operator,
    /// The settings.
    pub settings: Settings,
    fleet: Mutex<FleetView>,
    start: Instant,
    /// Wakes the configuration poll (a page opened a device not read yet).
    pub config_wanted: tokio::sync::Notify,
}

impl Console {
    /// A console on `session` with `settings`, checking replies with `key` (`None`: the
    /// deployment runs open and replies are taken unchecked).
    pub fn new(session: Session, settings: Settings, key: Option<protocol::auth::Key>) -> Self {
        Self {
            fleet: Mutex::new(FleetView::new(settings.limits())),
            operator: transport::ops::Operator {
                session: session.clone(),
                key,
                name: None,
            },
            session,
            settings,
            start: Instant::now(),
            config_wanted: tokio::sync::Notify::new(),
        }
    }

    /// Seconds since the console started: the fleet's clock.
    pub fn now(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    /// The fleet, locked (briefly: never held across an `.await`). A panic elsewhere while
    /// it was held leaves a view that is still consistent message by message, so a poisoned
    /// lock is taken as it is.
    pub fn fleet(&self) -> MutexGuard<'_, FleetView> {
        self.fleet.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// How long a query waits.
    pub fn timeout(&self) -> Duration {
        Duration::from_millis(self.settings.query_timeout_ms)
    }
}

/// The subscribers and pollers; dropping it undeclares and stops them.
pub struct Wiring {
    _subscribers: Vec<Subscriber<()>>,
    tasks: Vec<JoinHandle<()>>,
}

impl Drop for Wiring {
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
    }
}

fn payload(s: &Sample) -> Option<Vec<u8>> {
    // The size is checked again by the parsers; this only avoids copying a huge payload.
    (s.payload().len() <= protocol::MAX_BATCH_PAYLOAD).then(|| s.payload().to_bytes().to_vec())
}

/// Subscribe to liveliness, samples and commands, and start the polls.
pub async fn wire(console: Arc<Console>) -> Result<Wiring, ConsoleError> {
    let session = console.session.clone();
    let zerr = |what: &str, e: zenoh::Error| ConsoleError::Zenoh(format!("{what}: {e}"));
    let mut subs = Vec::new();

    let c = console.clone();
    let alive = format!("{}/alive/plant/*", keys::PREFIX);
    subs.push(
        session
            .liveliness()
            .declare_subscriber(&alive)
            .history(true)
            .callback(move |s: Sample| {
                let Some(id) = s.key_expr().as_str().rsplit('/').next() else {
                    return;
                };
                let now = c.now();
                let mut f = c.fleet();
                match s.kind() {
                    SampleKind::Put => f.plant_up(id, now),
                    SampleKind::Delete => f.plant_down(id, now),
                }
            })
            .await
            .map_err(|e| zerr(&alive, e))?,
    );

    type Handler = fn(&Console, &str, &[u8]);
    let on_sample: Handler = |c, key, bytes| {
        let r = fleet::parse_sample(key, bytes);
        let now = c.now();
        let mut f = c.fleet();
        match r {
            Ok(s) => f.apply_sample(s, now),
            Err(d) => f.dropped(d),
        }
    };
    let on_command: Handler = |c, key, bytes| {
        let r = fleet::parse_command(key, bytes);
        let mut f = c.fleet();
        match r {
            Ok(cmd) => f.apply_command(cmd),
            Err(d) => f.dropped(d),
        }
    };
    let on_sample_batch: Handler = |c, key, bytes| {
        let r = fleet::parse_sample_batch(key, bytes);
        let now = c.now();
        let mut f = c.fleet();
        match r {
            Ok(list) => list.into_iter().for_each(|s| f.apply_sample(s, now)),
            Err(d) => f.dropped(d),
        }
    };
    let on_command_batch: Handler = |c, key, bytes| {
        let r = fleet::parse_command_batch(key, bytes);
        let mut f = c.fleet();
        match r {
            Ok(list) => list.into_iter().for_each(|cmd| f.apply_command(cmd)),
            Err(d) => f.dropped(d),
        }
    };
    let p = keys::PREFIX;
    let routes: [(String, Handler); 6] = [
        (format!("{p}/device/*/sample"), on_sample),
        (format!("{p}/shard/*/device/*/sample"), on_sample),
        (format!("{p}/device/*/command"), on_command),
        (format!("{p}/gateway/*/samples"), on_sample_batch),
        (format!("{p}/shard/*/gateway/*/samples"), on_sample_batch),
        (format!("{p}/gateway/*/commands"), on_command_batch),
    ];
    for (key, handler) in routes {
        let c = console.clone();
        subs.push(
            session
                .declare_subscriber(&key)
                .callback(move |s: Sample| match payload(&s) {
                    Some(bytes) => handler(&c, s.key_expr().as_str(), &bytes),
                    None => c.fleet().dropped(fleet::Drop::Oversized),
                })
                .await
                .map_err(|e| zerr(&key, e))?,
        );
    }

    let tasks = vec![
        tokio::spawn(poll_services(console.clone())),
        tokio::spawn(poll_configs(console)),
    ];
    Ok(Wiring {
        _subscribers: subs,
        tasks,
    })
}

/// Every `status_period_ms`: all services' status, then forget devices long gone.
async fn poll_services(c: Arc<Console>) {
    let mut tick = tokio::time::interval(Duration::from_millis(c.settings.status_period_ms));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut failing = false;
    loop {
        tick.tick().await;
        match ops::services(&c.operator, c.timeout()).await {
            Ok(list) => {
                failing = false;
                let now = c.now();
                let mut f = c.fleet();
                f.apply_services(&list, now);
                f.forget(now);
            }
            Err(e) => {
                // Said once per outage, not every second.
                if !failing {
                    tracing::warn!("status poll: {e}");
                }
                failing = true;
            }
        }
    }
}

/// Every `config_period_ms` (or at once when a page opens a device not read yet): the
/// configuration of the devices pages are showing.
async fn poll_configs(c: Arc<Console>) {
    let period = Duration::from_millis(c.settings.config_period_ms);
    loop {
        tokio::select! {
            _ = tokio::time::sleep(period) => {}
            _ = c.config_wanted.notified() => {}
        }
        let ids = c.fleet().watched(c.now(), WATCH_WINDOW);
        for id in ids {
            match ops::config(&c.operator, &id, c.timeout()).await {
                Ok(cfg) => {
                    let now = c.now();
                    c.fleet().apply_config(&id, cfg, now);
                }
                Err(e) => c.fleet().config_failed(&id, e.to_string()),
            }
        }
    }
}
