//! Whether this broker can do its job, told truthfully to `/readyz` and to the service
//! manager.
//!
//! A process that runs is not a broker that routes. When the router thread died of a
//! panic, the process stayed up, refused every connection, routed nothing and still
//! answered 200 on `/readyz`, so neither systemd nor an orchestrator restarted it. Three
//! things make the answer honest:
//!
//! - **started**: the listeners are bound; cleared when shutdown begins.
//! - **fatal**: a thread or task the whole line depends on (the router, the password
//!   verifiers, the broker's own publisher, the listeners, the registry's writer) died.
//!   [`Health::fatal`] marks it at once; `fbbus serve` waits on [`Health::died`], logs the
//!   reason and exits non-zero, so the service manager restarts it (`Restart=on-failure`).
//! - **probe**: a publication on `$fbbus/probe`, routed by the router to the broker's own
//!   probe link ([`Probe`]). `/readyz` is 200 only while that round trip completes within
//!   [`PROBE_TIMEOUT`]. One probe runs at a time and an answer is reused for
//!   [`PROBE_FRESH`], so polling `/readyz` costs the router at most a few messages a
//!   second, however many pollers there are. `$` topics match no wildcard filter
//!   [MQTT-4.7.2-1] and clients may not subscribe to `$` filters, so no client sees them;
//!   a client publication under `$fbbus/` is refused (`policy::typed`), so none can feed it.

use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use rumqttd::local::{LinkRx, LinkTx};
use tokio::sync::{watch, Notify};
use tokio::time::{timeout, Instant};

use crate::link;

/// The router link of the readiness probe; clients may not take it (`fbbus:` prefix).
pub const PROBE_CLIENT_ID: &str = "fbbus:probe";

/// The broker's own `$` namespace: clients may neither publish nor subscribe in it.
pub const RESERVED_TOPICS: &str = "$fbbus/";

/// The topic the probe publishes on and subscribes to.
pub const PROBE_TOPIC: &str = "$fbbus/probe";

/// How long a probe publication may take to come back before the broker is not ready.
pub const PROBE_TIMEOUT: Duration = Duration::from_secs(1);

/// How long a probe's answer is reused for further `/readyz` requests.
pub const PROBE_FRESH: Duration = Duration::from_millis(250);

/// Readiness and fatal failures, shared by the admin endpoint and everything that can die.
pub struct Health {
    started: AtomicBool,
    fatal: watch::Sender<Option<String>>,
    /// Set once the router runs ([`Health::set_probe`]).
    probe: OnceLock<Probe>,
}

impl Health {
    pub fn new() -> Arc<Health> {
        Arc::new(Health {
            started: AtomicBool::new(false),
            fatal: watch::channel(None).0,
            probe: OnceLock::new(),
        })
    }

    /// The probe `/readyz` runs, once the router can take its link.
    pub fn set_probe(&self, probe: Probe) {
        let _ = self.probe.set(probe);
    }

    /// The listeners are bound (true), or shutdown began (false).
    pub fn set_started(&self, started: bool) {
        self.started.store(started, Ordering::Release);
    }

    /// A part the line depends on is gone: not ready from now on, and [`Health::died`]
    /// resolves. The first reason is kept; later ones are logged only.
    pub fn fatal(&self, reason: String) {
        tracing::error!(reason, "a core part of the broker died; the broker stops");
        self.fatal.send_if_modified(|fatal| {
            if fatal.is_none() {
                *fatal = Some(reason);
                true
            } else {
                false
            }
        });
    }

    /// Why the broker cannot go on, once something fatal happened.
    #[cfg(test)]
    pub fn fatal_reason(&self) -> Option<String> {
        self.fatal.borrow().clone()
    }

    /// Resolves with the reason once something fatal happened.
    pub async fn died(&self) -> String {
        let mut fatal = self.fatal.subscribe();
        loop {
            if let Some(reason) = fatal.borrow_and_update().clone() {
                return reason;
            }
            if fatal.changed().await.is_err() {
                // The sender lives as long as `self`: not reached.
                std::future::pending::<()>().await;
            }
        }
    }

    /// What `/readyz` answers: Ok while started, nothing fatal happened and a probe
    /// publication made the round trip through the router; else why not.
    pub async fn ready(&self) -> Result<(), &'static str> {
        if self.fatal.borrow().is_some() {
            return Err("a core part of the broker died");
        }
        if !self.started.load(Ordering::Acquire) {
            return Err("not started, or shutting down");
        }
        let Some(probe) = self.probe.get() else {
            return Err("not started");
        };
        if !probe.round_trip().await {
            return Err("the router did not route a probe publication in time");
        }
        Ok(())
    }
}

/// The readiness probe: one task owning a router link that publishes to itself.
pub struct Probe {
    /// A probe is wanted (permits coalesce: one probe serves every request made before
    /// it started).
    wanted: Arc<Notify>,
    /// The last probe's end and outcome.
    done: watch::Receiver<Option<(Instant, bool)>>,
}

impl Probe {
    /// The probe on `link`, and its task, which the caller spawns (health is told of
    /// the tasks' deaths, so it cannot be the one to run them). The link is subscribed
    /// to [`PROBE_TOPIC`] here.
    pub fn start(link: (LinkTx, LinkRx)) -> (Probe, impl Future<Output = ()> + Send + 'static) {
        let (mut tx, mut rx) = link;
        let wanted = Arc::new(Notify::new());
        let (done_tx, done) = watch::channel(None);
        let subscribed = tx.try_subscribe(PROBE_TOPIC).is_ok();
        let task_wanted = Arc::clone(&wanted);
        let task = async move {
            let mut seq: u64 = 0;
            loop {
                task_wanted.notified().await;
                seq = seq.wrapping_add(1);
                let ok = subscribed && round_trip(&mut tx, &mut rx, seq).await;
                if done_tx.send(Some((Instant::now(), ok))).is_err() {
                    return;
                }
            }
        };
        (Probe { wanted, done }, task)
    }

    /// Whether a probe publication made the round trip, recently or now.
    async fn round_trip(&self) -> bool {
        let mut done = self.done.clone();
        if let Some((at, ok)) = *done.borrow_and_update() {
            if at.elapsed() < PROBE_FRESH {
                return ok;
            }
        }
        self.wanted.notify_one();
        match timeout(PROBE_TIMEOUT + PROBE_FRESH, done.changed()).await {
            Ok(Ok(())) => done.borrow().is_some_and(|(_, ok)| ok),
            // Timed out (the probe task waits on a router that does not answer), or the
            // task is gone.
            _ => false,
        }
    }
}

/// Publishes `seq` on the probe topic and waits for it to come back through the router.
async fn round_trip(tx: &mut LinkTx, rx: &mut LinkRx, seq: u64) -> bool {
    let payload = seq.to_be_bytes().to_vec();
    // `try_publish`: a full router queue is not ready either, and must not block a thread.
    if tx.try_publish(PROBE_TOPIC, payload.clone()).is_err() {
        return false;
    }
    let deadline = Instant::now() + PROBE_TIMEOUT;
    loop {
        let first = match tokio::time::timeout_at(deadline, rx.next()).await {
            Ok(Ok(n)) => n,
            Ok(Err(_)) | Err(_) => return false,
        };
        // Anything else is an older probe's late answer, a subscription acknowledgement,
        // or a client's publication on the probe topic: not this probe's.
        let mut answered = false;
        let taken = link::take_batch(rx, first, |forward| {
            answered |= forward.publish.payload[..] == payload[..];
        });
        // The router paused the link (its queue was full): wake it even when answered,
        // so the next probe finds it awake; give up if the router is gone.
        let resumed = match taken {
            Ok(paused) => paused.resume(rx).await.is_ok(),
            Err(_) => false,
        };
        if answered {
            return true;
        }
        if !resumed {
            return false;
        }
    }
}
