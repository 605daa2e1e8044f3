//! A rig: the publishers and subscribers of one scenario, connected to one broker once
//! (like the study's "Once Only Controller"), and the batch that runs through them.
//!
//! A batch is the unit everything is measured in. Each publisher sends `n` messages,
//! either as fast as its client takes them (closed loop, a burst) or on a schedule
//! (open loop, a rate); every subscriber counts what it receives in its [`Tally`]. The
//! batch ends when every expected copy has arrived, when nothing has arrived for the
//! quiet time, or at the batch time limit, whichever is first.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use hdrhistogram::Histogram;
use tokio::sync::mpsc;

use crate::client::{self, Client, ClientConfig, OnPublish};
use crate::contract::{self, Declared, FbSubscriber};
use crate::model::Batch;
use crate::tally::{self, Tally};
use crate::target::Target;
use crate::{clock, message, Error};

/// Who subscribes to whom.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Follow {
    /// Every subscriber follows every publisher (fan-in, fan-out, the study's tests).
    All,
    /// Subscriber `i` follows publisher `i` only (pairs).
    Pairs,
}

/// A rig's connections.
#[derive(Debug, Clone)]
pub struct Shape {
    pub publishers: usize,
    pub subscribers: usize,
    pub follow: Follow,
    /// Also count at an FB subscriber (fb-bridge's client API), when the broker speaks
    /// the fbbus device contract.
    pub fb: bool,
}

/// Settings every batch of a rig shares.
#[derive(Debug, Clone)]
pub struct RigConfig {
    /// MQTT QoS of publications and subscriptions.
    pub qos: u8,
    /// Requested message size in bytes (at least [`message::MIN_SIZE`]).
    pub payload: usize,
    /// Client ids start with this (`<prefix>-pub-0`, `<prefix>-sub-0`, `<prefix>-fb`).
    pub prefix: String,
    pub inflight: u16,
    /// A batch ends after this long without a new delivery...
    pub quiet: Duration,
    /// ...and after this long in any case.
    pub batch_limit: Duration,
    /// Bound on connecting and acknowledgements.
    pub timeout: Duration,
}

/// How a batch's messages are paced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pace {
    /// Closed loop: as fast as the client takes them.
    Burst,
    /// Open loop: this many messages per second over all publishers, each message
    /// time-stamped with when it was due (coordinated omission corrected).
    Rate(f64),
}

struct Publisher {
    client: Arc<Client>,
    topic: String,
    next_seq: u64,
}

struct Subscriber {
    client: Client,
    tally: Arc<Mutex<Tally>>,
    /// Publisher indexes it follows.
    follows: Vec<usize>,
}

/// Connected publishers and subscribers on one broker. See the module docs.
pub struct Rig {
    /// The target's label in the report (`A`, `B`).
    pub label: String,
    publishers: Vec<Publisher>,
    subscribers: Vec<Subscriber>,
    fb: Option<FbSubscriber>,
    /// Why there is no FB subscriber although the shape asked for one.
    pub fb_note: Option<String>,
    /// Whether the broker answered the fbbus declaration.
    pub speaks_fbbus: bool,
    config: RigConfig,
}

impl Rig {
    /// Connects everything: subscribers first (each granted before anything is sent),
    /// then publishers, which declare themselves. `subscribe_at` puts the subscribers
    /// on another broker (line A -> line B across a bridge).
    pub async fn connect(
        label: &str,
        target: &Target,
        subscribe_at: Option<&Target>,
        shape: &Shape,
        config: &RigConfig,
    ) -> Result<Rig, Error> {
        let ids: Vec<String> = (0..shape.publishers)
            .map(|i| format!("{}-pub-{i}", config.prefix))
            .collect();
        let topics: Vec<String> = ids.iter().map(|id| contract::topic(id)).collect();

        // Publishers first connect and declare: an fbbus subscriber's SUBSCRIBE FB needs
        // the publisher's registry record, and a declaration answered tells us the
        // broker speaks the contract.
        let mut publishers = Vec::new();
        let mut speaks_fbbus = true;
        for (id, topic) in ids.iter().zip(&topics) {
            let (diag_tx, mut diag_rx) = mpsc::unbounded_channel();
            let on_diag: OnPublish = Arc::new(move |_topic: &[u8], payload: &[u8]| {
                let _ = diag_tx.send(payload.to_vec());
            });
            let mut c = Client::connect(target, &client_config(id, config), Some(on_diag)).await?;
            if contract::declare(&mut c, &mut diag_rx).await? == Declared::NoAnswer {
                speaks_fbbus = false;
            }
            publishers.push(Publisher {
                client: Arc::new(c),
                topic: topic.clone(),
                next_seq: 1,
            });
        }

        let sub_target = subscribe_at.unwrap_or(target);
        let mut subscribers = Vec::new();
        for i in 0..shape.subscribers {
            let follows: Vec<usize> = match shape.follow {
                Follow::All => (0..shape.publishers).collect(),
                Follow::Pairs => vec![i % shape.publishers.max(1)],
            };
            let tally = Arc::new(Mutex::new(Tally::new(shape.publishers)));
            let streams: HashMap<Vec<u8>, usize> = follows
                .iter()
                .map(|&p| (topics[p].clone().into_bytes(), p))
                .collect();
            let counter = tally.clone();
            let on_publish: OnPublish = Arc::new(move |topic: &[u8], payload: &[u8]| {
                let now = clock::now_us();
                let (Some(&stream), Some((seq, ts))) =
                    (streams.get(topic), message::decode(payload))
                else {
                    return;
                };
                contract::lock(&counter).record(stream, seq, ts, now);
            });
            let id = format!("{}-sub-{i}", config.prefix);
            let mut c =
                Client::connect(sub_target, &client_config(&id, config), Some(on_publish)).await?;
            let filters: Vec<String> = follows.iter().map(|&p| topics[p].clone()).collect();
            c.subscribe(&filters, client::qos(config.qos)).await?;
            subscribers.push(Subscriber {
                client: c,
                tally,
                follows,
            });
        }

        if subscribe_at.is_some() {
            across_the_bridge(&publishers, &subscribers, config).await?;
        }

        let (fb, fb_note) = if !shape.fb {
            (None, None)
        } else if sub_target.tls {
            let note = format!(
                "{label}: no FB subscriber: fb-bridge's client speaks plain MQTT only, and {} is TLS; delivery is counted at the raw MQTT subscriber only",
                sub_target.address
            );
            (None, Some(note))
        } else if !speaks_fbbus {
            let note = format!(
                "{label}: no FB subscriber: {} did not answer the fbbus declaration (not an fbbus broker), so delivery is counted at the raw MQTT subscriber only",
                target.address
            );
            (None, Some(note))
        } else {
            let id = format!("{}-fb", config.prefix);
            match FbSubscriber::start(sub_target, &id, &ids, config.timeout).await {
                Ok(fb) => (Some(fb), None),
                Err(e) => return Err(e),
            }
        };

        Ok(Rig {
            label: label.to_owned(),
            publishers,
            subscribers,
            fb,
            fb_note,
            speaks_fbbus,
            config: config.clone(),
        })
    }

    /// Runs one batch of `per_publisher` messages from every publisher.
    /// Runs one batch of `per_publisher` messages from every publisher. Returns the
    /// batch and its latency histogram (for merging into the target's summary).
    pub async fn batch(
        &mut self,
        per_publisher: u64,
        pace: Pace,
        label: String,
        x: f64,
        repeat: u32,
    ) -> (Batch, Histogram<u64>) {
        let ranges: Vec<(u64, u64)> = self
            .publishers
            .iter_mut()
            .map(|p| {
                let base = p.next_seq;
                p.next_seq += per_publisher;
                (base, per_publisher)
            })
            .collect();
        let mut expected = 0;
        for sub in &self.subscribers {
            let own: Vec<(u64, u64)> = ranges
                .iter()
                .enumerate()
                .map(|(i, &(base, n))| {
                    if sub.follows.contains(&i) {
                        (base, n)
                    } else {
                        (0, 0)
                    }
                })
                .collect();
            expected += own.iter().map(|r| r.1).sum::<u64>();
            contract::lock(&sub.tally).begin(&own);
        }
        let fb_expected = ranges.iter().map(|r| r.1).sum::<u64>();
        if let Some(fb) = &self.fb {
            contract::lock(&fb.tally).begin(&ranges);
        }

        let started_ms = clock::now_ms();
        let start = Instant::now();
        let sent_at = clock::now_us();
        let per_publisher_rate = match pace {
            Pace::Rate(total) => Some(total / self.publishers.len().max(1) as f64),
            Pace::Burst => None,
        };
        let mut senders = Vec::new();
        for (p, &(base, n)) in self.publishers.iter().zip(&ranges) {
            let (client, topic) = (p.client.clone(), p.topic.clone());
            let (qos, size) = (client::qos(self.config.qos), self.config.payload);
            let sender = match per_publisher_rate {
                None => tokio::spawn(async move {
                    for k in 0..n {
                        let payload = message::encode(base + k, clock::now_us(), size);
                        client.publish(&topic, qos, payload).await?;
                    }
                    Ok::<u64, Error>(n)
                }),
                // Open loop on a thread of its own: tokio's timers tick in whole
                // milliseconds, so a message due at 0.3 ms would leave at 1 ms and, stamped
                // with its due time, show the timer's lateness as broker latency. A thread
                // sleeps to within the kernel's timer slack (~50 us).
                Some(rate) => {
                    let runtime = tokio::runtime::Handle::current();
                    tokio::task::spawn_blocking(move || {
                        for k in 0..n {
                            let due = start + Duration::from_secs_f64(k as f64 / rate);
                            let now = Instant::now();
                            if due > now {
                                std::thread::sleep(due - now);
                            }
                            let payload = message::encode(base + k, clock::at_us(due), size);
                            runtime.block_on(client.publish(&topic, qos, payload))?;
                        }
                        Ok::<u64, Error>(n)
                    })
                }
            };
            senders.push(sender);
        }
        let mut send_error = None;
        let mut sent = 0;
        for s in senders {
            match s.await {
                Ok(Ok(n)) => sent += n,
                Ok(Err(e)) => send_error = Some(e.to_string()),
                Err(e) => send_error = Some(format!("publisher task: {e}")),
            }
        }
        let send_us = start.elapsed().as_micros() as u64;

        self.wait_for_deliveries(expected, fb_expected).await;

        let mut delivered = 0;
        let mut duplicates = 0;
        let mut out_of_order = 0;
        let mut last_us = None::<u64>;
        let mut latency = tally::histogram();
        for sub in &self.subscribers {
            let c = contract::lock(&sub.tally).counts();
            delivered += c.delivered;
            duplicates += c.duplicates;
            out_of_order += c.out_of_order;
            last_us = last_us.max(c.last_us);
            latency.add(&c.latency).expect("same histogram bounds");
        }
        let delivered_fb = self
            .fb
            .as_ref()
            .map(|fb| contract::lock(&fb.tally).delivered());
        let processing_us = last_us.map_or(0, |l| l.saturating_sub(sent_at));
        let lost = expected.saturating_sub(delivered);
        let fb_lost = delivered_fb.map_or(0, |d| fb_expected.saturating_sub(d));
        let error = send_error.or_else(|| {
            (lost > 0 || fb_lost > 0).then(|| {
                let mut e = format!("lost {lost} of {expected}");
                if let Some(d) = delivered_fb {
                    e += &format!(" (FB subscriber: {d} of {fb_expected})");
                }
                e
            })
        });
        let batch = Batch {
            target: self.label.clone(),
            label,
            x,
            repeat,
            started_ms,
            sent,
            delivered,
            expected,
            delivered_fb,
            duplicates,
            out_of_order,
            send_us,
            processing_us,
            throughput: if processing_us == 0 {
                0.0
            } else {
                delivered as f64 / (processing_us as f64 / 1e6)
            },
            latency: tally::summarize(&latency),
            ok: error.is_none(),
            error,
        };
        (batch, latency)
    }

    /// Waits until everything expected arrived, or the quiet time passed without a new
    /// delivery, or the batch limit.
    async fn wait_for_deliveries(&self, expected: u64, fb_expected: u64) {
        let deadline = Instant::now() + self.config.batch_limit;
        let mut last_total = u64::MAX;
        let mut last_change = Instant::now();
        loop {
            let raw: u64 = self
                .subscribers
                .iter()
                .map(|s| contract::lock(&s.tally).delivered())
                .sum();
            let fb = self
                .fb
                .as_ref()
                .map(|fb| contract::lock(&fb.tally).delivered());
            if raw >= expected && fb.is_none_or(|d| d >= fb_expected) {
                return;
            }
            let total = raw + fb.unwrap_or(0);
            let now = Instant::now();
            if total != last_total {
                last_total = total;
                last_change = now;
            } else if now - last_change >= self.config.quiet || now >= deadline {
                return;
            }
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    }

    /// Whether every connection is still up.
    pub fn alive(&self) -> bool {
        self.publishers.iter().all(|p| p.client.alive())
            && self.subscribers.iter().all(|s| s.client.alive())
    }

    /// Disconnects everything cleanly.
    pub async fn close(self) {
        for p in self.publishers {
            if let Ok(c) = Arc::try_unwrap(p.client) {
                c.disconnect().await;
            }
        }
        for s in self.subscribers {
            s.client.disconnect().await;
        }
        if let Some(fb) = self.fb {
            fb.stop().await;
        }
    }
}

/// How long a subscription on line B may take to reach line A over the bridge.
const BRIDGE_SETTLE: Duration = Duration::from_secs(15);

/// Waits until messages cross from the publishers' broker to the subscribers'.
///
/// fbbus's bridge is subscription-driven: line A forwards a topic once line B's
/// subscription has reached it over zenoh, some milliseconds after line B's SUBACK. Until
/// then a batch would be lost for a reason that is not load. So before the first batch
/// every publisher sends probes (seq 0, which no batch uses: counted as stale) until each
/// subscriber has seen one, bounded by [`BRIDGE_SETTLE`].
async fn across_the_bridge(
    publishers: &[Publisher],
    subscribers: &[Subscriber],
    config: &RigConfig,
) -> Result<(), Error> {
    let deadline = Instant::now() + BRIDGE_SETTLE;
    while Instant::now() < deadline {
        for p in publishers {
            let probe = message::encode(0, clock::now_us(), config.payload);
            p.client.publish(&p.topic, client::qos(1), probe).await?;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
        if subscribers
            .iter()
            .all(|s| contract::lock(&s.tally).counts().stale > 0)
        {
            return Ok(());
        }
    }
    Err(Error::Timeout {
        waited: BRIDGE_SETTLE,
        what: "a probe message to cross from --broker to --subscribe-at (is [bridge] configured on both lines, with the same zenoh network?)".into(),
    })
}

fn client_config(id: &str, config: &RigConfig) -> ClientConfig {
    let mut c = ClientConfig::new(id);
    c.inflight = config.inflight;
    c.timeout = config.timeout;
    c
}
