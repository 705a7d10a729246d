//! The outputs by subscription: the server samples each output node and publishes what
//! changed, or a keep-alive when nothing did; the bridge keeps the last value of each and
//! when it last heard from the subscription, and a period costs no request for them.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use opcua::client::{MonitoredItem, OnSubscriptionNotification, Session};
use opcua::client::{MonitoredItemMap, OnSubscriptionNotificationCore};
use opcua::types::{
    DataValue, ExtensionObject, MonitoredItemCreateRequest, MonitoringMode, MonitoringParameters,
    NotificationMessage, ReadValueId, TimestampsToReturn,
};

/// What the subscription last published.
#[derive(Debug, Default)]
pub(crate) struct Latest {
    /// Per output, its last value (`None` until the first).
    pub values: Vec<Option<DataValue>>,
    /// When the subscription was last heard from (data or keep-alive).
    pub heard: Option<Instant>,
}

/// The subscription's callback: every message (a keep-alive too) counts as heard; each
/// data value goes to its output by client handle (the output's index plus one).
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
}

struct Heard(Notifications);

impl OnSubscriptionNotificationCore for Heard {
    fn on_subscription_notification(
        &mut self,
        notification: NotificationMessage,
        items: MonitoredItemMap<'_>,
    ) {
        if let Ok(mut l) = self.0.latest.lock() {
            l.heard = Some(Instant::now());
        }
        OnSubscriptionNotificationCore::on_subscription_notification(
            &mut self.0,
            notification,
            items,
        );
    }
}

/// How many sampling intervals a keep-alive may take, in a subscription of `interval`:
/// about every 100 ms.
fn keep_alive_count(interval: Duration) -> u32 {
    let n = 0.1 / interval.as_secs_f64().max(1e-3);
    (n.ceil() as u32).clamp(1, 1000)
}

/// How long the subscription may stay silent before the bridge calls its values stale:
/// three keep-alives.
pub(crate) fn stale_after(interval: Duration) -> Duration {
    interval * keep_alive_count(interval) * 3
}

/// Subscribe to `outputs`, sampled every `interval`; the values land in the returned
/// store. Refused: an output the server cannot monitor, or one it would sample slower
/// than `period` (the loop would run on values older than a period); one it samples
/// slower than asked is taken with a warning.
pub(crate) async fn subscribe(
    session: &Arc<Session>,
    outputs: &[ReadValueId],
    interval: Duration,
    period: Duration,
) -> Result<Arc<Mutex<Latest>>, String> {
    let latest = Arc::new(Mutex::new(Latest {
        values: vec![None; outputs.len()],
        heard: None,
    }));
    let keep_alive = keep_alive_count(interval);
    // The server drops a subscription nobody asked after for `lifetime` intervals: at
    // least 3 keep-alives (OPC UA's rule), and 10 s, so a reconnection can take it over.
    let lifetime = (keep_alive * 3).max((10.0 / interval.as_secs_f64()).ceil() as u32);
    let callback = Heard(Notifications {
        latest: latest.clone(),
    });
    let id = session
        .create_subscription(interval, lifetime, keep_alive, 0, 0, true, callback)
        .await
        .map_err(|e| format!("creating the subscription: {e}"))?;
    let ms = interval.as_secs_f64() * 1000.0;
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
        if revised > period.as_secs_f64() * 1000.0 + 1e-6 {
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
    Ok(latest)
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
        assert_eq!(stale_after(ms(10)), ms(300));
        assert_eq!(stale_after(ms(500)), ms(1500));
    }
}
