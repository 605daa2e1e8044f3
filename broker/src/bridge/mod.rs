//! The line's end of the bus: fbbus's router on one side, zenoh (`fb_bridge::bus`) on
//! the other. Runs inside `fbbus serve` when the configuration has a `[bridge]` section.
//!
//! ```text
//!  local client SUBSCRIBE fb/X/..  ──► Bridge::subscribed ──► import: zenoh subscriber
//!                                                               + interest token
//!  other line's interest token ──► export: router link `fbbus:bridge-out` subscribes
//!  local PUBLISH fb/<local>/.. ──► router ──► export ──► zenoh put (stamped)
//!  zenoh sample ──► dedup ─► ACL ─► typed check ─► router link `fbbus:bridge-in`
//! ```
//!
//! **Subscription-driven.** Nothing leaves a line unless another line's client subscribed
//! to it: a subscription here declares a zenoh subscriber and a liveliness token naming
//! the filter; the other lines' bridges see the token, put only the messages matching
//! some line's interest, and zenoh sends each only to the lines whose subscribers match.
//! While no other line is interested in anything, the exporter is not even subscribed on
//! its router.
//!
//! **One hop, never more.** The exporter skips every message whose origin (the marker
//! the packet path attaches, `origin`) is the import link: what came from the bus is
//! never put back on it. With each line exporting only what its own clients published,
//! no topology can loop or duplicate; the per-origin sequence numbers in each message's
//! stamp ([`fb_bridge::bus::Dedup`]) drop the copies zenoh delivers once per overlapping
//! import filter.
//!
//! **Same rules as local traffic.** A message from the bus enters the router only after
//! this line's ACL allows its device (as username and client id) to publish on its topic
//! and, once the registry knows the device's declared interface, after the same typed
//! check as a local publication (which also re-encodes it for `dinasore/` and `fbdk/`
//! subscribers). A line exports only topics its `export` filters allow and imports only
//! what its `import` filters allow.
//!
//! **Delivery.** zenoh links are reliable and every put uses blocking congestion control:
//! a slow link or a slow remote line slows the exporter down (and, behind it, the router's
//! queue for the export link), it does not drop; a line that takes nothing for 5 s
//! (zenoh's blocking limit) has its link closed, is marked unreachable and reconnects. Event ports travel at a higher zenoh
//! priority than data ports, so events overtake queued data; each topic keeps its order.
//! An MQTT QoS 1 message is acknowledged to the router only after zenoh took it, and is
//! injected on the other line at QoS 1. What holds across failures: while both bridges
//! and the link are up, every message reaches every subscribed line once, in order; a
//! message in flight when a bridge or the link goes down may be lost (zenoh keeps no
//! end-to-end acknowledgement), and nothing published while a line is cut off is queued
//! for it. What is lost is counted on both sides: by the line that missed it (a gap in the
//! topic's numbering, `fbbus_bridge_lost_total`) and, from that line's report within a
//! second, by the line that sent it (`fbbus_bridge_lost_reported_total`). Retained messages are fetched again when a line (re)starts importing a filter,
//! so retained state converges after a restart or a partition.
//!
//! **Starting alone.** A line never waits for the bus: a peer or router starts with its
//! peers down and links when they answer; a zenoh client (`mode = "client"`), whose zenoh
//! `open` waits for its router, opens in the background (`start`), serves its own devices
//! meanwhile, and imports the subscriptions its clients made once it is linked.
//!
//! **Registry federation.** The line announces itself with a liveliness token and puts
//! every local record change on the bus (a device's status is in its record: no token
//! per device, issue 32); the other lines' records arrive the same way. A device this
//! line forgets (by hand or by age) is deleted from the bus, and every other line forgets
//! it too, with the retained values it held of it. A line that comes (back) is asked for
//! its records, then for its retained messages on every imported filter: those this line
//! does not hold yet enter the router, so a subscriber that subscribed while it was away
//! gets them. Every device of a line whose token disappears is marked unreachable (within
//! the zenoh lease, `bridge.lease_ms`); the records its line serves when its token comes
//! back say what they are then.
//!
//! The files: [`import`] (local subscriptions become zenoh imports; what arrives passes
//! the publish policy and enters the router), [`export`] (what other lines want leaves
//! through the router's export link), [`federation`] (the registry across lines),
//! [`retained`] (other lines' queries for this line's retained messages).

mod export;
mod federation;
mod import;
mod retained;

use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use fb_bridge::bus::link::{Event, Inbound, Inbox, Link, LinkError};
use fb_bridge::bus::{keys, BusConfig, Mode};
use fb_bridge::topic::filter;
use tokio::sync::mpsc;
use tokio::task::JoinHandle;

use crate::session::Context;

/// The router link messages from the bus enter through.
pub const IMPORT_CLIENT_ID: &str = crate::broker_publisher::BUS_CLIENT_ID;

/// The router link the exporter subscribes with.
pub const EXPORT_CLIENT_ID: &str = "fbbus:bridge-out";

/// What the exporter subscribes to while another line is interested in anything.
const EXPORT_FILTER: &str = "fb/#";

#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    // The link's error is the source: `{:#}` prints it after this.
    #[error("bridge")]
    Link(#[from] LinkError),
    #[error("bridge: router: {0}")]
    Router(String),
}

/// What connections (and the federation) tell the import task.
enum Interest {
    Add(String),
    Remove(String),
    /// Line `0` came (back): its retained messages on every imported filter are asked
    /// for again, and those this line does not hold yet enter the router (issue 32: a
    /// subscriber that subscribed while it was away gets them).
    Requery(String),
}

/// The handle connections hold: local subscriptions become imports.
pub struct Bridge {
    import_filters: Vec<String>,
    interest: mpsc::UnboundedSender<Interest>,
    /// The other end of `interest`, until [`Bridge::start`] hands it to the import task.
    interest_rx: Mutex<Option<mpsc::UnboundedReceiver<Interest>>>,
    /// Set once zenoh is open: at start, or for a zenoh client, once its router answers.
    link: OnceLock<Arc<Link>>,
    tasks: Mutex<Vec<JoinHandle<()>>>,
}

/// Local subscriptions become imports.
impl crate::observer::SubscriptionObserver for Bridge {
    /// A local client was granted `filter`.
    fn subscribed(&self, filter: &str) {
        for f in self.imports_for(filter) {
            let _ = self.interest.send(Interest::Add(f));
        }
    }

    /// A local client dropped `filter` (UNSUBSCRIBE, or its clean session ended).
    fn unsubscribed(&self, filter: &str) {
        for f in self.imports_for(filter) {
            let _ = self.interest.send(Interest::Remove(f));
        }
    }
}

impl Bridge {
    /// The filters to import for a local subscription to `filter`: the typed namespace
    /// in the canonical `fb/` form (`dinasore/` and `fbdk/` are re-encoded here), narrowed
    /// to the configured import filters.
    fn imports_for(&self, filter: &str) -> Vec<String> {
        let filter = filter::unshared(filter);
        let canonical = match filter.split_once('/') {
            Some(("dinasore" | "fbdk", rest)) => format!("fb/{rest}"),
            _ => filter.to_owned(),
        };
        let mut out = Vec::new();
        for allowed in &self.import_filters {
            if filter::covers(allowed, &canonical) {
                if keys::bridgeable_filter(&canonical) {
                    out.push(canonical);
                }
                return out;
            }
        }
        for allowed in &self.import_filters {
            if filter::covers(&canonical, allowed) {
                out.push(allowed.clone());
            }
        }
        out
    }

    /// The bridge's tasks (a list of handles, valid after any panic of another holder).
    fn tasks(&self) -> std::sync::MutexGuard<'_, Vec<JoinHandle<()>>> {
        self.tasks
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Closes the zenoh session (other lines see this line go at once) and stops the
    /// bridge's tasks.
    pub async fn close(&self) {
        if let Some(link) = self.link.get() {
            link.close().await;
        }
        for task in self.tasks().drain(..) {
            task.abort();
        }
    }
}

/// How long a zenoh client waits for its router before the line says it serves alone.
const ROUTER_PATIENCE: Duration = Duration::from_secs(2);

/// Starts the bridge. A peer or router opens zenoh here (its listeners bind, its peers
/// are tried in the background); a client (`mode = "client"`) opens it in the background,
/// because zenoh's `open` waits for the client's router: the line must serve its own
/// devices while the plant's router is down, and link up when it answers. Local
/// subscriptions made meanwhile are imported then.
impl Bridge {
    /// The bridge's handle, before anything is opened. It is registered with the session
    /// layer as a subscription observer before the first client connects; what clients
    /// subscribe to before [`Bridge::start`] links the bus is imported then.
    pub fn new(config: &BusConfig, line: &str) -> Result<Arc<Bridge>, BridgeError> {
        // A bad `[bridge]` section, or a certificate of another line, fails the start
        // whatever the mode.
        Bridge::check(config, line)?;
        let (interest, interest_rx) = mpsc::unbounded_channel();
        Ok(Arc::new(Bridge {
            import_filters: config.import.clone(),
            interest,
            interest_rx: Mutex::new(Some(interest_rx)),
            link: OnceLock::new(),
            tasks: Mutex::new(Vec::new()),
        }))
    }

    /// What `fbbus check-config` checks of the `[bridge]` section beyond its syntax: that
    /// it makes a zenoh configuration and that the certificate names this line.
    pub fn check(config: &BusConfig, line: &str) -> Result<(), BridgeError> {
        fb_bridge::bus::link::validate(config, line)?;
        Ok(())
    }

    /// Starts the bridge (once; a second call does nothing).
    pub async fn start(
        self: &Arc<Self>,
        config: &BusConfig,
        ctx: Arc<Context>,
    ) -> Result<(), BridgeError> {
        let taken = self
            .interest_rx
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .take();
        match taken {
            Some(interest_rx) => start(self, config, ctx, interest_rx).await,
            None => Ok(()),
        }
    }
}

async fn start(
    bridge: &Arc<Bridge>,
    config: &BusConfig,
    ctx: Arc<Context>,
    interest_rx: mpsc::UnboundedReceiver<Interest>,
) -> Result<(), BridgeError> {
    let line = ctx.fb.registry.line().to_owned();
    if let Some(note) = config.reach_note() {
        tracing::info!(connect = ?config.connect, "{note}");
    }
    if config.mode != Mode::Client {
        let opened = Link::open(config, &line).await?;
        return run(bridge, opened, config, ctx, interest_rx).await;
    }
    let (config, weak) = (config.clone(), Arc::downgrade(bridge));
    let opener = tokio::spawn(async move {
        let opening = Link::open(&config, &line);
        tokio::pin!(opening);
        let opened = match tokio::time::timeout(ROUTER_PATIENCE, &mut opening).await {
            Ok(opened) => opened,
            Err(_) => {
                tracing::warn!(connect = ?config.connect,
                    "zenoh router not reachable: the line serves its own devices and links to the other lines once it answers");
                opening.await
            }
        };
        let started = match (opened, weak.upgrade()) {
            (Ok(opened), Some(bridge)) => run(&bridge, opened, &config, ctx, interest_rx).await,
            (Ok(_), None) => Ok(()),
            (Err(e), _) => Err(e.into()),
        };
        if let Err(e) = started {
            tracing::error!(
                error = format!("{e:#}"),
                "bridge to the other lines not started"
            );
        }
    });
    bridge.tasks().push(opener);
    Ok(())
}

/// How often `fbbus_bridge_router_sessions_up` is brought up to date.
const ROUTER_SESSIONS_EVERY: Duration = Duration::from_secs(1);

/// Keeps the router-session gauges of a line with a session per router.
async fn router_sessions(link: Arc<Link>, metrics: Arc<crate::metrics::Metrics>) {
    while let Some((up, total)) = link.routers() {
        metrics.bridge_router_sessions.set(total as i64);
        metrics.bridge_router_sessions_up.set(up as i64);
        tokio::time::sleep(ROUTER_SESSIONS_EVERY).await;
    }
}

/// How often the other lines are told what of theirs this line counted as lost, when
/// that moved; every [`LOSSES_AGAIN`]-th time all counts are sent again, in case a report
/// was lost with a router.
const LOSSES_EVERY: Duration = Duration::from_secs(1);
const LOSSES_AGAIN: u32 = 30;

/// Tells the other lines what of theirs never reached this line (`fbbus_bridge_lost_total`
/// here becomes `fbbus_bridge_lost_reported_total` there).
async fn report_losses(link: Arc<Link>) {
    let mut tick = 0u32;
    loop {
        tokio::time::sleep(LOSSES_EVERY).await;
        tick = tick.wrapping_add(1);
        if let Err(e) = link.report_losses(tick.is_multiple_of(LOSSES_AGAIN)).await {
            tracing::debug!(error = %e, "lost messages not reported to their lines");
        }
    }
}

/// The bridge's work once zenoh is open: its router links, registry federation, retained
/// queries, and the import, export and event tasks.
async fn run(
    bridge: &Bridge,
    (link, inbox, events): (Link, Inbox<Inbound>, Inbox<Event>),
    config: &BusConfig,
    ctx: Arc<Context>,
    interest_rx: mpsc::UnboundedReceiver<Interest>,
) -> Result<(), BridgeError> {
    let line = link.line().to_owned();
    let link = Arc::new(link);
    let metrics = Arc::clone(&ctx.metrics);

    let router = &ctx.router;
    let router_link = |id: &'static str| async move {
        router
            .link(id, true, 0)
            .await
            .map_err(|e| BridgeError::Router(e.to_string()))
    };
    let import_link = router_link(IMPORT_CLIENT_ID).await?;
    let export_link = router_link(EXPORT_CLIENT_ID).await?;

    let (remote_interest, remote_interest_rx) = mpsc::unbounded_channel();
    let (local_records, local_records_rx) = mpsc::unbounded_channel();
    let local_now = ctx.fb.registry.observe(local_records);

    let registry = Arc::clone(&ctx.fb.registry);
    let this_line = registry.line().to_owned();
    link.serve_records(move |device| {
        let records = match device {
            Some(id) => registry
                .get(id)
                .filter(|r| r.line == this_line)
                .into_iter()
                .collect(),
            None => registry.local(),
        };
        records
            .into_iter()
            .map(|r| {
                (
                    r.id.clone(),
                    serde_json::to_vec(&r).expect("records serialize"),
                )
            })
            .collect()
    })
    .await?;
    let retained_queries = link.retained_queries().await?;
    link.announce_line().await?;

    let tasks = [
        tokio::spawn(import::imports(
            Arc::clone(&link),
            interest_rx,
            Arc::clone(&ctx),
        )),
        tokio::spawn(import::inject_loop(
            (Arc::clone(&link), inbox),
            Arc::clone(&ctx),
            (import_link.0, import_link.1),
            config.import.clone(),
        )),
        tokio::spawn(export::export_loop(
            link.exporter(),
            (export_link.0, export_link.1),
            remote_interest_rx,
            Arc::clone(&ctx),
            export::Shares {
                export: config.export.clone(),
                per_line: config.max_remote_filters_per_line,
                all: config.max_remote_filters,
            },
        )),
        tokio::spawn(federation::bus_events(
            Arc::clone(&link),
            events,
            (remote_interest, bridge.interest.clone()),
            Arc::clone(&ctx),
        )),
        tokio::spawn(federation::announce_local(
            Arc::clone(&link),
            local_now,
            local_records_rx,
        )),
        tokio::spawn(retained::serve_retained(
            Arc::clone(&link),
            retained_queries,
            Arc::clone(&ctx),
            config.export.clone(),
        )),
        tokio::spawn(report_losses(Arc::clone(&link))),
    ];
    bridge.tasks().extend(tasks);
    if link.routers().is_some() {
        bridge.tasks().push(tokio::spawn(router_sessions(
            Arc::clone(&link),
            metrics.clone(),
        )));
    }
    let _ = bridge.link.set(link);
    tracing::info!(line, mode = config.mode.as_str(), listen = ?config.listen, connect = ?config.connect,
        "bridge to the other lines started (zenoh)");
    metrics.bridge_imports.set(0);
    Ok(())
}
