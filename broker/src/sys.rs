//! `$SYS/`: the broker's status for MQTT tools (`mosquitto_sub -t '$SYS/#'`, MQTT
//! Explorer, Node-RED dashboards), under Mosquitto's names where fbbus counts the same
//! thing, published every `[broker] sys_interval_s` (0: never).
//!
//! Every figure is read from the broker's metrics (`metrics`), so `$SYS` and `/metrics`
//! never disagree; README.md maps each topic to its Prometheus series and says which of
//! Mosquitto's topics fbbus leaves out and why. As Mosquitto does, the messages are
//! retained, at QoS 0, and a figure is published again only when it changed (the uptime
//! at every interval). They are not kept across a restart (`broker_publisher`): a new
//! broker publishes its own at start.
//!
//! Who reads them is the access rules' `$SYS` rule (`security::acl`): loopback clients,
//! and clients an ACL rule grants `$SYS/#`; nobody publishes there but the broker.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::broker_publisher::{BrokerPublisher, Message};
use crate::metrics::Metrics;
use crate::supervisor::Tasks;

/// The figures `$SYS` publishes, read from the metrics at one moment.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Figures {
    /// Clients connected now (`fbbus_connections`).
    pub connected: u64,
    /// Persistent sessions kept for clients not connected (`fbbus_router_saved_sessions`).
    pub disconnected: u64,
    /// The most clients connected at once since start.
    pub maximum: u64,
    /// CONNECTs accepted since start (`fbbus_connects_total`).
    pub connects: u64,
    pub publish_received: u64,
    pub publish_sent: u64,
    pub bytes_received: u64,
    pub bytes_sent: u64,
    /// Clients' retained messages (`fbbus_retained_messages`).
    pub retained: u64,
}

impl Figures {
    pub fn read(metrics: &Metrics) -> Figures {
        let count = |n: i64| u64::try_from(n).unwrap_or(0);
        Figures {
            connected: count(metrics.connections.get()),
            disconnected: metrics.router_sessions.saved() as u64,
            maximum: count(metrics.connections_peak()),
            connects: metrics.connects.get(),
            publish_received: metrics.messages_in.get(),
            publish_sent: metrics.messages_out.get(),
            bytes_received: metrics.bytes_in.get(),
            bytes_sent: metrics.bytes_out.get(),
            retained: metrics.router_retained.messages() as u64,
        }
    }
}

/// Reads one counter of [`Figures`].
type Counter = fn(&Figures) -> u64;

/// The counters with load averages, by their name under `$SYS/broker/load/`.
const LOADS: [(&str, Counter); 5] = [
    ("publish/received", |f| f.publish_received),
    ("publish/sent", |f| f.publish_sent),
    ("bytes/received", |f| f.bytes_received),
    ("bytes/sent", |f| f.bytes_sent),
    ("connections", |f| f.connects),
];

/// The averaging windows of the loads, in seconds, by their topic suffix.
const WINDOWS: [(&str, f64); 3] = [("1min", 60.0), ("5min", 300.0), ("15min", 900.0)];

/// What `$SYS` published last, to publish only what changed, and the load averages.
pub struct SysTree {
    started: Instant,
    last: Option<(Instant, Figures)>,
    /// Per minute, per [`LOADS`] entry and [`WINDOWS`] entry.
    loads: [[f64; 3]; 5],
    published: HashMap<String, String>,
}

impl SysTree {
    pub fn new(started: Instant) -> SysTree {
        SysTree {
            started,
            last: None,
            loads: [[0.0; 3]; 5],
            published: HashMap::new(),
        }
    }

    /// The `(topic, payload)` pairs to publish at `now` with these figures: every topic
    /// the first time, then those whose text changed.
    pub fn update(&mut self, now: Instant, figures: Figures) -> Vec<(String, String)> {
        let uptime = now.duration_since(self.started).as_secs();
        let mut all: Vec<(String, String)> = vec![
            (
                "version".into(),
                format!("fbbus version {}", env!("CARGO_PKG_VERSION")),
            ),
            ("uptime".into(), format!("{uptime} seconds")),
            ("clients/connected".into(), figures.connected.to_string()),
            (
                "clients/disconnected".into(),
                figures.disconnected.to_string(),
            ),
            (
                "clients/total".into(),
                (figures.connected + figures.disconnected).to_string(),
            ),
            ("clients/maximum".into(), figures.maximum.to_string()),
            (
                "publish/messages/received".into(),
                figures.publish_received.to_string(),
            ),
            (
                "publish/messages/sent".into(),
                figures.publish_sent.to_string(),
            ),
            ("bytes/received".into(), figures.bytes_received.to_string()),
            ("bytes/sent".into(), figures.bytes_sent.to_string()),
            (
                "retained messages/count".into(),
                figures.retained.to_string(),
            ),
        ];
        // Mosquitto's load: an exponentially weighted average of the rate per minute
        // over each window, updated at every interval.
        if let Some((then, before)) = self.last {
            let seconds = now.duration_since(then).as_secs_f64();
            if seconds > 0.0 {
                for (i, (_, counter)) in LOADS.iter().enumerate() {
                    let per_minute =
                        counter(&figures).saturating_sub(counter(&before)) as f64 * 60.0 / seconds;
                    for (j, (_, window)) in WINDOWS.iter().enumerate() {
                        let decay = (-seconds / window).exp();
                        let load = &mut self.loads[i][j];
                        *load = per_minute + decay * (*load - per_minute);
                    }
                }
            }
        }
        for (i, (name, _)) in LOADS.iter().enumerate() {
            for (j, (suffix, _)) in WINDOWS.iter().enumerate() {
                all.push((
                    format!("load/{name}/{suffix}"),
                    format!("{:.2}", self.loads[i][j]),
                ));
            }
        }
        self.last = Some((now, figures));
        all.into_iter()
            .filter_map(|(name, payload)| {
                let topic = format!("$SYS/broker/{name}");
                if self.published.get(&topic) == Some(&payload) {
                    return None;
                }
                self.published.insert(topic.clone(), payload.clone());
                Some((topic, payload))
            })
            .collect()
    }
}

/// Publishes `$SYS` every `interval` until the broker stops (a task of `tasks`).
pub fn start(
    interval: Duration,
    metrics: Arc<Metrics>,
    publisher: Arc<BrokerPublisher>,
    tasks: &Tasks,
) {
    if interval.is_zero() {
        return;
    }
    let mut tree = SysTree::new(Instant::now());
    tasks.spawn(async move {
        let mut ticks = tokio::time::interval(interval);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            for (topic, payload) in tree.update(Instant::now(), Figures::read(&metrics)) {
                let mut message = Message::broker(topic, payload, true);
                message.qos = 0;
                publisher.publish(message);
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn payloads(updates: &[(String, String)]) -> HashMap<&str, &str> {
        updates
            .iter()
            .map(|(t, p)| (t.as_str(), p.as_str()))
            .collect()
    }

    #[test]
    fn everything_first_then_what_changed_with_mosquittos_loads() {
        let start = Instant::now();
        let mut tree = SysTree::new(start);
        let mut figures = Figures {
            connected: 2,
            disconnected: 1,
            maximum: 3,
            ..Figures::default()
        };
        let first = tree.update(start, figures);
        let got = payloads(&first);
        assert_eq!(got["$SYS/broker/uptime"], "0 seconds");
        assert_eq!(got["$SYS/broker/clients/total"], "3");
        assert_eq!(got["$SYS/broker/clients/maximum"], "3");
        assert_eq!(got["$SYS/broker/load/publish/received/1min"], "0.00");
        assert!(got["$SYS/broker/version"].starts_with("fbbus version "));
        assert_eq!(first.len(), 11 + 15);

        // 10 s later, 100 more PUBLISHes: 600 a minute; the 1-minute load moves by
        // 1 - e^(-10/60) of it, Mosquitto's formula.
        figures.publish_received = 100;
        let next = tree.update(start + Duration::from_secs(10), figures);
        let got = payloads(&next);
        assert_eq!(got["$SYS/broker/uptime"], "10 seconds");
        assert_eq!(got["$SYS/broker/publish/messages/received"], "100");
        let expected = 600.0 * (1.0 - (-10.0f64 / 60.0).exp());
        assert_eq!(
            got["$SYS/broker/load/publish/received/1min"],
            format!("{expected:.2}")
        );
        assert!(!got.contains_key("$SYS/broker/clients/total"), "unchanged");
        assert!(!got.contains_key("$SYS/broker/version"), "unchanged");
    }
}
