//! The outputs by subscription: the server samples each output node and publishes what
//! changed, or a keep-alive when nothing did; the bridge keeps the last value of each and
//! when it last heard from the subscription, and a period costs no request for them.
//!
//! The bridge owns its subscription: async-opcua's own re-creation after a reconnection
//! is off (it ignores the items it fails to re-create, whose last values would then pass
//! for fresh), and the bridge subscribes anew instead ([`Subscribed::gone`]).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use opcua::client::{MonitoredItem, OnSubscriptionNotification, Session};
use opcua::client::{MonitoredItemMap, OnSubscriptionNotificationCore};
use opcua::types::{
    DataValue, ExtensionObject, MonitoredItemCreateRequest, MonitoringMode, MonitoringParameters,
    NotificationMessage, ReadValueId, StatusChangeNotification, TimestampsToReturn,
};

/// What the subscription last published.
#[derive(Debug, Default)]
pub(crate) struct Latest {
    /// Per output, its last value (`None` until the first).
    pub values: Vec<Option<DataValue>>,
    /// When the subscription was last heard from (data or keep-alive).
    pub heard: Option<Instant>,
    /// The server said the subscription ended (a status change).
    pub ended: bool,
}

/// A subscription the bridge made: where its values land, its id, and how long it may
/// stay silent (three keep-alive intervals, as the server revised them).
#[derive(Clone)]
pub(crate) struct Subscribed {
    pub latest: Arc<Mutex<Latest>>,
    pub id: u32,
    pub stale: Duration,
    /// The session's reconnections when it was made.
    pub made_at: u64,
}

impl Subscribed {
    /// Whether it must be made again: the session reconnected since (the server may have
    /// a new session without it), or the server ended it.
    pub fn gone(&self, reconnections: u64) -> bool {
        reconnections != self.made_at || self.latest.lock().map_or(true, |l| l.ended)
    }
}

/// The subscription's callback: each data value goes to its output by client handle (the
/// output's index plus one); then every message, a keep-alive too, counts as heard.
struct Notifications {
    latest: Arc<Mutex<Latest>>,
}

impl OnSubscriptionNotification for Notifications {
    fn on_data_value(&mut self, value: DataValue, item: &MonitoredItem) {
        let i = item.client_handle() as usize;
        if let Ok(mut l) = self.latest.lock() {
            if let Some(slot) = i.checked_sub(1).and_then(|i| l.values.get_mut(i)) {
                *slot = Some(value);
            }
        }
    }

    fn on_subscription_status_change(&mut self, _notification: StatusChangeNotification) {
        if let Ok(mut l) = self.latest.lock() {
            l.ended = true;
        }
    }
}

struct Heard(Notifications);

impl OnSubscriptionNotificationCore for Heard {
    fn on_subscription_notification(
        &mut self,
        notification: NotificationMessage,
        items: MonitoredItemMap<'_>,
    ) {
        OnSubscriptionNotificationCore::on_subscription_notification(
            &mut self.0,
            notification,
            items,
        );
        if let Ok(mut l) = self.0.latest.lock() {
            l.heard = Some(Instant::now());
        }
    }
}

/// How many publishing intervals a keep-alive may take, in a subscription of `interval`:
/// about every 100 ms.
fn keep_alive_count(interval: Duration) -> u32 {
    let n = 0.1 / interval.as_secs_f64().max(1e-3);
    (n.ceil() as u32).clamp(1, 1000)
}

/// How long a subscription publishing every `interval`, with a keep-alive every
/// `keep_alive` intervals, may stay silent before its values are stale: three keep-alives.
pub(crate) fn stale_after(interval: Duration, keep_alive: u32) -> Duration {
    interval * keep_alive.max(1) * 3
}

/// What a subscription asks of the server.
pub(crate) struct Ask {
    /// Sampling and publishing interval.
    pub interval: Duration,
    /// The loop's period: a server publishing slower is refused.
    pub period: Duration,
    /// How long an outage may last (the subscription must outlive it on the server).
    pub outage: Duration,
}

/// Subscribe to `outputs` as `ask` says; the values land in the returned store. Refused:
/// an output the server cannot monitor, or a server that would publish or sample slower
/// than the period (the loop would run on values older than a period); one that samples
/// slower than asked is taken with a warning.
pub(crate) async fn subscribe(
    session: &Arc<Session>,
    outputs: &[ReadValueId],
    ask: &Ask,
    made_at: u64,
) -> Result<Subscribed, String> {
    let latest = Arc::new(Mutex::new(Latest {
        values: vec![None; outputs.len()],
        heard: None,
        ended: false,
    }));
    let interval = ask.interval;
    let keep_alive = keep_alive_count(interval);
    // The server drops a subscription nobody asked after for `lifetime` intervals: at
    // least 3 keep-alives (OPC UA's rule), 10 s, and the outage the bridge rides out.
    let outlive = ask.outage.max(Duration::from_secs(10)).as_secs_f64();
    let lifetime = (keep_alive * 3).max((outlive / interval.as_secs_f64()).ceil() as u32);
    let callback = Heard(Notifications {
        latest: latest.clone(),
    });
    let id = session
        .create_subscription(interval, lifetime, keep_alive, 0, 0, true, callback)
        .await
        .map_err(|e| format!("creating the subscription: {e}"))?;
    let revised = session
        .subscription_state()
        .lock()
        .get(id)
        .map(|s| (s.publishing_interval(), s.max_keep_alive_count()));
    let (publishing, keep_alive) = revised.unwrap_or((interval, keep_alive));
    if publishing > ask.period {
        let _ = session.delete_subscription(id).await;
        return Err(format!(
            "the server publishes every {publishing:?}, slower than the period {:?}",
            ask.period
        ));
    }
    if let Err(e) = monitor(session, id, outputs, ask).await {
        let _ = session.delete_subscription(id).await;
        return Err(e);
    }
    Ok(Subscribed {
        latest,
        id,
        stale: stale_after(publishing, keep_alive),
        made_at,
    })
}

/// Monitor each output in subscription `id`, its client handle its index plus one.
async fn monitor(
    session: &Arc<Session>,
    id: u32,
    outputs: &[ReadValueId],
    ask: &Ask,
) -> Result<(), String> {
    let ms = ask.interval.as_secs_f64() * 1000.0;
    let items: Vec<MonitoredItemCreateRequest> = outputs
        .iter()
        .enumerate()
        .map(|(i, r)| {
            MonitoredItemCreateRequest::new(
                r.clone(),
                MonitoringMode::Reporting,
                MonitoringParameters {
                    client_handle: i as u32 + 1,
                    sampling_interval: ms,
                    filter: ExtensionObject::null(),
                    queue_size: 1,
                    discard_oldest: true,
                },
            )
        })
        .collect();
    let created = session
        .create_monitored_items(id, TimestampsToReturn::Neither, items)
        .await
        .map_err(|e| format!("monitoring the outputs: {e}"))?;
    if created.len() != outputs.len() {
        return Err(format!(
            "monitoring the outputs: {} answers for {} outputs",
            created.len(),
            outputs.len()
        ));
    }
    for (r, c) in outputs.iter().zip(&created) {
        if !c.result.status_code.is_good() {
            return Err(format!(
                "monitoring {}: {}",
                r.node_id, c.result.status_code
            ));
        }
        let revised = c.result.revised_sampling_interval;
        if revised > ask.period.as_secs_f64() * 1000.0 + 1e-6 {
            return Err(format!(
                "the server samples {} every {revised} ms, slower than the period",
                r.node_id
            ));
        }
        if revised > ms + 1e-6 {
            tracing::warn!(
                "OPC UA: the server samples {} every {revised} ms, not the {ms} ms asked",
                r.node_id
            );
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_keep_alive_comes_about_every_100_ms_and_three_missed_make_the_values_stale() {
        let ms = Duration::from_millis;
        assert_eq!(keep_alive_count(ms(10)), 10);
        assert_eq!(keep_alive_count(ms(1)), 100);
        assert_eq!(keep_alive_count(ms(30)), 4, "rounded up: 120 ms");
        assert_eq!(
            keep_alive_count(ms(500)),
            1,
            "slower than 100 ms: every publication"
        );
        assert_eq!(stale_after(ms(10), keep_alive_count(ms(10))), ms(300));
        assert_eq!(stale_after(ms(500), 1), ms(1500));
        assert_eq!(
            stale_after(ms(50), 20),
            ms(3000),
            "as the server revised them"
        );
        assert_eq!(
            stale_after(ms(10), 0),
            ms(30),
            "a keep-alive count of 0 read as 1"
        );
    }
}
