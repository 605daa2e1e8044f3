use crate::protocol::{
    ConnAck, ConnAckProperties, ConnectReturnCode, Disconnect, DisconnectReasonCode, LastWill,
    LastWillProperties, Packet, PingResp, PubAck, PubAckReason, PubComp, PubCompReason, PubRec,
    PubRecReason, PubRel, PubRelReason, Publish, PublishProperties, QoS, RetainForwardRule, SubAck,
    SubscribeReasonCode, UnsubAck, UnsubAckReason,
};
use crate::router::scheduler::{PauseReason, Tracker};
use crate::router::{ConnectionEvents, Forward};
use crate::segments::Position;
use crate::*;
use flume::{bounded, Receiver, RecvError, RecvTimeoutError, Sender, TryRecvError};
use std::collections::{HashMap, HashSet, VecDeque};
use std::str::Utf8Error;
use std::thread;
use thiserror::Error;
use tracing::{debug, error, info, trace, warn};

use super::graveyard::Graveyard;
use super::holds::Holds;
use super::ids::{ConnectionIds, IdTable};
use super::iobufs::{Incoming, Outgoing};
use super::logs::{AckLog, DataLog};
use super::retained; // fbbus
use super::scheduler::{ScheduleReason, Scheduler};
use super::shared_subs::SharedGroup;
use super::{
    packetid, Connection, DataRequest, Event, FilterIdx, Held, Notification, RouterHooks,
    ShadowRequest, SkipHook, Skipped, MAX_CHANNEL_CAPACITY, MAX_SCHEDULE_ITERATIONS,
};

#[derive(Error, Debug)]
pub enum RouterError {
    #[error("Receive error = {0}")]
    Recv(#[from] RecvError),
    #[error("Try Receive error = {0}")]
    TryRecv(#[from] TryRecvError),
    #[error("Disconnection")]
    Disconnected,
    #[error("Topic not utf-8")]
    NonUtf8Topic(#[from] Utf8Error),
    #[error("No matching filters to topic {0}")]
    NoMatchingFilters(String),
    #[error("Invalid filter prefix {0}")]
    InvalidFilterPrefix(Filter),
    #[error("Invalid client_id {0}")]
    InvalidClientId(String),
    #[error("Disconnection (Reason: {0:?})")]
    Disconnect(DisconnectReasonCode),
}

// TODO: set this to some appropriate value
pub(crate) const TOPIC_ALIAS_MAX: u16 = 4096;

/// fbbus: how long the router waits for an event while publishers are held (`holds`).
const HELD_POLL: std::time::Duration = std::time::Duration::from_millis(1);

/// fbbus: the invariant behind every per-connection lookup that cannot fail. A connection
/// is registered in and removed from `connections`, `ibufs`, `obufs`, `ackslog` and the
/// scheduler's trackers together (`handle_new_connection`, `handle_disconnection`), so one
/// of them holding an id means all do; handlers look the id up in one first.
const SLABS_IN_STEP: &str = "invariant: a connection id is in every per-connection slab or in none";

/// fbbus: `DataLog::matches` returns indices of `DataLog::native`, whose logs are removed
/// only with every reference to them (`DataLog::remove_unused`, which clears them from
/// the matches cache too).
const MATCHED_FILTERS_EXIST: &str = "invariant: a matched filter index names a log";

pub struct Router {
    id: RouterId,
    /// Id of this router. Used to index native commitlog to store data from
    /// local connections
    config: RouterConfig,
    /// Saved state of dead persistent connections
    graveyard: Graveyard,
    /// List of connections
    connections: IdTable<Connection>,
    /// Connection map from device id to connection id
    connection_map: HashMap<String, ConnectionId>,
    /// Subscription map to interested connection ids
    subscription_map: HashMap<Filter, HashSet<ConnectionId>>,
    /// Incoming data grouped by connection
    ibufs: IdTable<Incoming>,
    /// Outgoing data grouped by connection
    obufs: IdTable<Outgoing>,
    /// Data log of all the subscriptions
    datalog: DataLog,
    /// Acks log per connection
    ackslog: IdTable<AckLog>,
    /// Scheduler to schedule connections
    scheduler: Scheduler,
    /// Parked requests that are ready because of new data on the subscription
    notifications: VecDeque<(ConnectionId, DataRequest)>,
    /// Channel receiver to receive data from all the active connections and
    /// replicators. Each connection will have a tx handle which they use
    /// to send data and requests to router
    router_rx: Receiver<(ConnectionId, Event)>,
    /// Channel sender to send data to this router. This is given to active
    /// network connections, local connections and replicators to communicate
    /// with this router
    router_tx: Sender<(ConnectionId, Event)>,
    /// Shared subscriptions map <group-name, group>
    shared_subscriptions: HashMap<String, SharedGroup>,
    /// Will messages per client_id
    last_wills: HashMap<String, (LastWill, Option<LastWillProperties>)>,
    /// fbbus: what the router reports to the broker embedding it.
    hooks: RouterHooks,
    /// fbbus: an event arrived since the router last released memory.
    dirty: bool,
    /// fbbus: when the router last released memory.
    last_release: std::time::Instant,
    /// fbbus: publishers held back for readers that would lose messages (`holds`).
    holds: Holds,
    /// fbbus: the connection ids links take before they connect (`ids`).
    ids: ConnectionIds,
}

impl Router {
    pub fn new(router_id: RouterId, config: RouterConfig) -> Router {
        let (router_tx, router_rx) = bounded(1000);

        let connections = IdTable::with_capacity(config.max_connections);
        let ibufs = IdTable::with_capacity(config.max_connections);
        let obufs = IdTable::with_capacity(config.max_connections);
        let ackslog = IdTable::with_capacity(config.max_connections);

        let max_connections = config.max_connections;
        Router {
            id: router_id,
            config: config.clone(),
            graveyard: Graveyard::new(config.max_saved_sessions),
            connections,
            connection_map: Default::default(),
            subscription_map: Default::default(),
            ibufs,
            obufs,
            datalog: DataLog::new(config).unwrap(),
            ackslog,
            scheduler: Scheduler::with_capacity(max_connections),
            notifications: VecDeque::with_capacity(1024),
            router_rx,
            router_tx,
            shared_subscriptions: HashMap::new(),
            last_wills: HashMap::new(),
            hooks: RouterHooks::default(),
            dirty: false,
            last_release: std::time::Instant::now(),
            holds: Holds::new(std::time::Duration::ZERO),
            ids: ConnectionIds::new(max_connections),
        }
    }

    /// fbbus: the pool links take their connection ids from (`LinkBuilder::new`): get it
    /// before [`Router::spawn`].
    pub fn connection_ids(&self) -> ConnectionIds {
        self.ids.clone()
    }

    /// fbbus: whether `publish` is a retained publication the retained store will not
    /// keep (a new topic beyond its bounds, `retained`).
    fn retain_refused(&self, publish: &Publish) -> bool {
        publish.retain
            && !publish.payload.is_empty()
            && std::str::from_utf8(&publish.topic).is_ok_and(|topic| {
                let size = retained::size(&publish.topic, &publish.payload);
                self.datalog.retain_refusal(topic, size).is_some()
            })
    }

    /// fbbus: sets the callbacks the router reports to (see [`RouterHooks`]).
    pub fn with_hooks(mut self, hooks: RouterHooks) -> Router {
        self.holds = Holds::new(hooks.hold_limit);
        self.graveyard.report_to(hooks.saved_sessions.clone());
        self.datalog.report_retained_to(hooks.retained.clone());
        self.hooks = hooks;
        self
    }

    /// Gets handle to the router. This is not a public method to ensure that link
    /// is created only after the router starts
    fn link(&self) -> Sender<(ConnectionId, Event)> {
        self.router_tx.clone()
    }

    // pub(crate) fn get_replica_handle(&mut self, _replica_id: NodeId) -> (LinkTx, LinkRx) {
    //     unimplemented!()
    // }

    /// Starts the router in a background thread and returns link to it. Link
    /// to communicate with router should only be returned only after it starts.
    /// For that reason, all the public methods should start the router in the
    /// background
    #[tracing::instrument(skip_all)]
    pub fn spawn(mut self) -> Sender<(ConnectionId, Event)> {
        let router = thread::Builder::new().name(format!("router-{}", self.id));
        let link = self.link();
        // fbbus: the embedder learns when the router stops, whether its loop returned or
        // it panicked (`RouterHooks::exited`): a broker whose router is gone must not keep
        // accepting connections. The unwind is caught only to report it; nothing runs on.
        let exited = self.hooks.exited.take();
        router
            .spawn(move || {
                let ran = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.run(0)));
                let reason = match ran {
                    Ok(result) => format!("the router loop ended: {result:?}"),
                    Err(panic) => format!("the router thread panicked: {}", panic_message(&panic)),
                };
                error!(reason, "Router done!");
                if let Some(exited) = exited {
                    exited(reason);
                }
            })
            .unwrap();
        link
    }

    /// Waits on incoming events when ready queue is empty.
    /// After pulling 1 event, tries to pull 500 more events
    /// before polling ready queue 100 times (connections)
    #[tracing::instrument(skip_all)]
    fn run(&mut self, count: usize) -> Result<(), RouterError> {
        match count {
            0 => loop {
                self.run_inner()?;
            },
            n => {
                for _ in 0..n {
                    self.run_inner()?;
                }
            }
        };

        Ok(())
    }

    fn run_inner(&mut self) -> Result<(), RouterError> {
        // fbbus: publishers held for a lagging reader go on once it has read enough.
        self.let_held_go();
        // Block on incoming events if there are no ready connections for consumption
        if self.consume().is_none() {
            // trace!("{}:: {:20} {:20} {:?}", self.id, "", "done-await", self.readyqueue);
            // fbbus: while publishers are held, wake up to check on them; once nothing
            // happened for `idle_after`, release memory (only when the embedder asked for
            // it with a `released` hook, and once per quiet period).
            let (id, data) = if !self.holds.is_empty() {
                match self.router_rx.recv_timeout(HELD_POLL) {
                    Ok(event) => event,
                    Err(RecvTimeoutError::Timeout) => return Ok(()),
                    Err(RecvTimeoutError::Disconnected) => return Err(RouterError::Disconnected),
                }
            } else if self.dirty && self.hooks.released.is_some() {
                match self.router_rx.recv_timeout(self.hooks.idle_after) {
                    Ok(event) => event,
                    Err(RecvTimeoutError::Timeout) => {
                        self.release_memory();
                        return Ok(());
                    }
                    Err(RecvTimeoutError::Disconnected) => return Err(RouterError::Disconnected),
                }
            } else {
                self.router_rx.recv()?
            };
            self.events(id, data);
        }

        // Try reading more from connections in a non-blocking
        // fashion to accumulate data and handle subscriptions.
        // Accumulating more data lets requests retrieve bigger
        // bulks which in turn increases efficiency
        for _ in 0..500 {
            // All these methods will handle state and errors
            match self.router_rx.try_recv() {
                Ok((id, data)) => self.events(id, data),
                Err(TryRecvError::Disconnected) => return Err(RouterError::Disconnected),
                Err(TryRecvError::Empty) => break,
            }
        }

        // A connection should not be scheduled multiple times
        #[cfg(debug_assertions)]
        if let Some(readyqueue) = self.scheduler.check_readyqueue_duplicates() {
            warn!(
                "Connection was scheduled multiple times in readyqueue: {:?}",
                readyqueue
            );
        }

        // Poll 100 connections which are ready in ready queue
        for _ in 0..100 {
            self.consume();
        }

        // fbbus: a line is rarely quiet for long; under steady traffic, memory is still
        // released every `release_every`.
        if self.dirty
            && self.hooks.released.is_some()
            && self.last_release.elapsed() >= self.hooks.release_every
        {
            self.release_memory();
        }

        Ok(())
    }

    fn events(&mut self, id: ConnectionId, data: Event) {
        // fbbus: trace, not error: per-event spans formatted their fields on every event.
        let span = tracing::trace_span!("[>] incoming", connection_id = id);
        let _guard = span.enter();
        self.dirty = true;

        match data {
            Event::Connect {
                connection,
                incoming,
                outgoing,
            } => self.handle_new_connection(id, connection, incoming, outgoing),
            Event::DeviceData => self.handle_device_payload(id),
            Event::Disconnect => self.handle_disconnection(id, None),
            Event::Ready => self.scheduler.reschedule(id, ScheduleReason::Ready),
            // fbbus: a shadow request of a link whose connection is gone is dropped
            // (upstream indexed `obufs[id]` and panicked).
            Event::Shadow(request) => {
                if let Some(outgoing) = self.obufs.get_mut(id) {
                    retrieve_shadow(&mut self.datalog, outgoing, request)
                }
            }
            Event::PublishWill((client_id, _tenant_id)) => self.handle_last_will(client_id),
        }
    }

    /// fbbus: `connection_id` is the id the link took from [`ConnectionIds`]; when the
    /// connection is refused, it is given back and the link's `outgoing` dropped (its
    /// `LinkRx` fails).
    fn handle_new_connection(
        &mut self,
        connection_id: ConnectionId,
        mut connection: Connection,
        incoming: Incoming,
        mut outgoing: Outgoing,
    ) {
        let client_id = outgoing.client_id.clone();
        if let Err(err) = validate_clientid(&client_id) {
            error!("Invalid client_id: {}", err);
            self.ids.give_back(connection_id);
            return;
        };
        if self.connections.contains(connection_id) {
            // Only a link that did not take its id from `ids` gets here.
            error!(connection_id, "connection id in use; connection refused");
            return;
        }

        let span = tracing::info_span!("incoming_connect", client_id);
        let _guard = span.enter();

        // Check if same client_id already exists and if so, replace it with this new connection
        // ref: https://docs.oasis-open.org/mqtt/mqtt/v3.1.1/os/mqtt-v3.1.1-os.html#_Toc398718032

        if let Some(&previous) = self.connection_map.get(&client_id) {
            // fbbus: debug, not error: a session takeover is MQTT's normal behaviour, which
            // the broker logs and counts itself (`fbbus_disconnects_total{reason="takeover"}`);
            // an error line per takeover let a client reconnecting in a loop fill the log.
            debug!(
                "Duplicate client_id, dropping previous connection with connection_id: {}",
                previous
            );
            self.handle_disconnection(previous, None);
        }

        if self.connections.len() >= self.config.max_connections {
            error!("no space for new connection");
            self.ids.give_back(connection_id);
            return;
        }

        // Retrieve previous connection state from graveyard
        let saved = self.graveyard.retrieve(&client_id);
        let clean_session = connection.clean;
        let previous_session = saved.as_ref().is_some_and(|s| s.session_state.is_some());
        // for qos2 pending pubrels
        let mut pending_acks = VecDeque::new();

        let tracker = if !clean_session {
            // if there was some saved state, restore the metrics
            // and get the session's state if present
            let saved_state = saved.and_then(|saved| {
                connection.events = saved.metrics;
                saved.session_state
            });

            // if session's state is present, restore that session
            // otherwise, just start new one
            saved_state.map_or_else(
                || Tracker::new(client_id.clone()),
                |session_state| {
                    connection.subscriptions = session_state.subscriptions;
                    // for using in acklog
                    pending_acks.clone_from(&session_state.unacked_pubrels);
                    outgoing.unacked_pubrels = session_state.unacked_pubrels;
                    session_state.tracker
                },
            )
        } else {
            // Only retrieve metrics in clean session
            connection.events = saved.map_or_else(ConnectionEvents::default, |s| s.metrics);
            Tracker::new(client_id.clone())
        };

        let ackslog = AckLog::new();

        // fbbus: no "connection at <time>" string is kept in the connection's event history
        // (only `print_status` reads it): it cost a formatted string and a queue per
        // connection, idle or not.

        if let Some(will) = connection.last_will.take() {
            self.last_wills.insert(
                client_id.clone(),
                (*will, connection.last_will_properties.take().map(|p| *p)),
            );
        }

        // fbbus: at the id the link took (checked free above, in every table together).
        let acked_by_link = connection.acked_by_link;
        self.connections.insert_at(connection_id, connection);
        self.ibufs.insert_at(connection_id, incoming);
        self.obufs.insert_at(connection_id, outgoing);

        self.connection_map.insert(client_id.clone(), connection_id);
        info!(connection_id, "Client connection registered");

        self.ackslog.insert_at(connection_id, ackslog);
        self.scheduler.add(connection_id, tracker);

        // Check if there are multiple data requests on same filter.
        debug_assert!(self
            .scheduler
            .check_tracker_duplicates(connection_id)
            .is_none());

        let ack = ConnAck {
            session_present: !clean_session && previous_session,
            code: ConnectReturnCode::Success,
        };

        let properties = ConnAckProperties {
            topic_alias_max: Some(TOPIC_ALIAS_MAX),
            ..Default::default()
        };

        let ackslog = self.ackslog.get_mut(connection_id).expect(SLABS_IN_STEP);
        // fbbus: a link that did not wait for the router answered its client already
        // (`LinkBuilder::build_linked`).
        if !acked_by_link {
            ackslog.connack(connection_id, ack, Some(Box::new(properties)));
        }

        pending_acks.into_iter().for_each(|pkid| {
            // NOTE: will it be better if we store the whole PubRel
            // instead of pkid in pending acks
            let pubrel = PubRel {
                pkid,
                reason: PubRelReason::Success,
            };
            ackslog.pubrel(pubrel)
        });

        self.scheduler
            .reschedule(connection_id, ScheduleReason::Init);
    }

    fn handle_disconnection(&mut self, id: ConnectionId, reason: Option<DisconnectReasonCode>) {
        // Some clients can choose to send Disconnect packet before network disconnection.
        // This will lead to double Disconnect packets in router `events`
        let client_id = match &self.obufs.get(id) {
            Some(v) => v.client_id.clone(),
            None => {
                // fbbus: debug, not error: a second disconnect of a connection already
                // removed (a DISCONNECT packet, then the link's own Disconnect event) is
                // the normal end of a connection, as the comment above says.
                debug!("no-connection id {} is already gone", id);
                return;
            }
        };

        let span = tracing::info_span!("incoming_disconnect", client_id);
        let _guard = span.enter();
        self.holds.forget(id);

        // must handle last will before sending disconnect packet
        // as the disconnecting client might have subscribed to will topic.
        // if execute_last_will {
        //     self.handle_last_will(id);
        // }

        info!("Disconnecting connection");

        if let Some(reason_code) = reason {
            let outgoing = match self.obufs.get_mut(id) {
                Some(v) => v,
                None => {
                    error!("no-connection id {} is already gone", id);
                    return;
                }
            };

            let disconnect = Disconnect { reason_code };

            let disconnect_notification = Notification::Disconnect(disconnect, None);

            outgoing
                .data_buffer
                .lock()
                .push_back(disconnect_notification);

            outgoing.handle.wake();
        }

        // Remove connection from router
        let connection = self.connections.remove(id).expect(SLABS_IN_STEP);
        let _incoming = self.ibufs.remove(id);
        let outgoing = self.obufs.remove(id).expect(SLABS_IN_STEP);
        let mut tracker = self.scheduler.remove(id).expect(SLABS_IN_STEP);
        self.connection_map.remove(&client_id);
        self.ackslog.remove(id);
        // fbbus: the id is free for the next link once it is in no table.
        self.ids.give_back(id);

        // Don't remove connection id from readyqueue with index. This will
        // remove wrong connection from readyqueue. Instead just leave disconnected
        // connection in readyqueue and allow 'consume()' method to deal with this
        // self.readyqueue.remove(id);

        let inflight_data_requests = self.datalog.clean(id);
        let retransmissions = outgoing.retransmission_map();

        // Remove connections from all groups and
        // discard empty group ( group with no client )
        // note: can we do this in better way?
        self.shared_subscriptions.retain(|_, group| {
            group.remove_client(&client_id);
            !group.is_empty()
        });

        // Remove this connection from subscriptions
        for filter in connection.subscriptions.iter() {
            // fbbus: a filter nobody subscribes any more leaves the map (upstream kept an
            // empty set for every filter ever subscribed).
            self.unsubscribe_from_map(filter, id);
        }

        // fbbus: no "disconnection at <time>" event string either (see above).

        // Save state for persistent sessions
        if !connection.clean {
            // Add inflight data requests back to tracker
            inflight_data_requests
                .into_iter()
                .for_each(|r| tracker.register_data_request(r));

            for request in tracker.data_requests.iter_mut() {
                if let Some(cursor) = retransmissions.get(&request.filter_idx) {
                    request.cursor = *cursor;
                    // reset the group cursor
                    // fbbus: only while the group still exists. The `retain` above removed
                    // it when this client was its last member; upstream's `expect("group
                    // must exists")` then panicked for every persistent shared subscriber
                    // that left with an unacknowledged delivery.
                    let group = request.group.as_ref();
                    if let Some(group) = group.and_then(|g| self.shared_subscriptions.get_mut(g)) {
                        group.cursor = *cursor;
                    }
                }
            }

            self.graveyard.save_state(
                tracker,
                connection.subscriptions,
                connection.events,
                outgoing.unacked_pubrels,
            );
        }
        // fbbus: nothing is kept for a clean session. Upstream saved its event history in
        // the graveyard, an entry per client id ever seen that was never removed: with
        // server-assigned ids, memory grew with every connection.
    }

    /// Handles new incoming data on a topic
    fn handle_device_payload(&mut self, id: ConnectionId) {
        // TODO: Retun errors and move error handling to the caller
        let incoming = match self.ibufs.get_mut(id) {
            Some(v) => v,
            None => {
                // fbbus: debug, not error. Every `LinkTx::send` queues its packet and then
                // a `DeviceData` event; the router takes everything queued on the first
                // event. When a connection's last batch and its Disconnect are both queued
                // before the router wakes, the first event handles both and ends the
                // connection, and the second event finds it gone: the normal end of a
                // connection that published just before disconnecting.
                debug!("no-connection id {} is already gone", id);
                return;
            }
        };
        // fbbus: a held publisher's packets wait in its buffer (`let_held_go`).
        if self.holds.is_held(id) {
            return;
        }

        let client_id = incoming.client_id.clone();
        // fbbus: trace, not error (per batch of packets, see FBBUS-CHANGES.md).
        let span = tracing::trace_span!("incoming_payload", client_id);
        let _guard = span.enter();

        let mut packets = incoming.take();

        let mut force_ack = false;
        let mut new_data = false;
        let mut disconnect = false;
        let mut disconnect_reason: Option<DisconnectReasonCode> = None;
        // fbbus: the filter and boundary this connection is held for (`holds`).
        let mut held = None;

        // info!("{:15.15}[I] {:20} count = {}", client_id, "packets", packets.len());

        while let Some(packet) = packets.pop_front() {
            match packet {
                Packet::Publish(publish, properties) => {
                    // fbbus: the embedder's test of a dead router (`RouterHooks`).
                    if let Some(topic) = &self.hooks.panic_on_topic {
                        if publish.topic == topic.as_bytes() {
                            panic!("panic_on_topic: a publication on {topic}");
                        }
                    }
                    // fbbus: before it is acknowledged or appended.
                    if let Some(hold) = self.hold_for(&publish.topic) {
                        packets.push_front(Packet::Publish(publish, properties));
                        held = Some(hold);
                        break;
                    }
                    // fbbus: trace, not error: an error-level span is always enabled, so
                    // every publish formatted its topic with `Debug for Bytes` (~2-3 % of
                    // the router's CPU, measured).
                    let span = tracing::trace_span!("publish", topic = ?publish.topic, pkid = publish.pkid);
                    let _guard = span.enter();

                    let qos = publish.qos;
                    let pkid = publish.pkid;

                    // Prepare acks for the above publish
                    // If any of the publish in the batch results in force flush,
                    // set global force flush flag. Force flush is triggered when the
                    // router is in instant ack more or connection data is from a replica
                    //
                    // TODO: handle multiple offsets
                    //
                    // The problem with multiple offsets is that when using replication with the current
                    // architecture, a single publish might get appended to multiple commit logs, resulting in
                    // multiple offsets (see `append_to_commitlog` function), meaning replicas will need to
                    // coordinate using multiple offsets, and we don't have any idea how to do so right now.
                    // Currently as we don't have replication, we just use a single offset, even when appending to
                    // multiple commit logs.

                    match qos {
                        QoS::AtLeastOnce => {
                            // fbbus: a retained publication the retained store will not
                            // keep is still routed, and its MQTT 5 PUBACK says 0x97
                            // (`retained`). QoS 2 has no such code before the release.
                            let reason = if self.retain_refused(&publish) {
                                PubAckReason::QuotaExceeded
                            } else {
                                PubAckReason::Success
                            };
                            let puback = PubAck { pkid, reason };

                            let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                            ackslog.puback(puback);
                            force_ack = true;
                        }
                        QoS::ExactlyOnce => {
                            let pubrec = PubRec {
                                pkid,
                                reason: PubRecReason::Success,
                            };

                            let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                            ackslog.pubrec(publish, properties, pubrec);
                            force_ack = true;
                            continue;
                        }
                        QoS::AtMostOnce => {
                            // Do nothing
                        }
                    };

                    // Try to append publish to commitlog
                    match append_to_commitlog(
                        id,
                        publish.clone(),
                        properties,
                        &mut self.datalog,
                        &mut self.notifications,
                        &mut self.connections,
                    ) {
                        Ok(_offset) => {
                            // Even if one of the data in the batch is appended to commitlog,
                            // set new data. This triggers notifications to wake waiters.
                            // Don't overwrite this flag to false if it is already true.
                            new_data = true;
                        }
                        Err(e) => {
                            // Disconnect on bad publishes
                            error!(
                                reason = ?e, "Failed to append to commitlog"
                            );
                            disconnect = true;

                            if let RouterError::Disconnect(code) = e {
                                disconnect_reason = Some(code)
                            }

                            break;
                        }
                    };

                    // fbbus: no per-topic incoming meter (`IncomingMeter::register_publish`):
                    // it copied the topic into a new String for every publish and kept an
                    // entry per topic per connection for the connection's life; fbbus meters
                    // publications itself.
                }
                Packet::Subscribe(mut subscribe, props) => {
                    let mut return_codes = Vec::new();
                    let pkid = subscribe.pkid;
                    // let len = s.len();

                    for f in &mut subscribe.filters {
                        let span =
                            tracing::info_span!("subscribe", topic = f.path, pkid = subscribe.pkid);
                        let _guard = span.enter();

                        info!("Adding subscription on topic {}", f.path);
                        let connection = self.connections.get_mut(id).expect(SLABS_IN_STEP);

                        if let Err(e) = validate_subscription(connection, f) {
                            warn!(reason = ?e,"Subscription cannot be validated: {}", e);

                            disconnect = true;
                            break;
                        }

                        let mut filter = f.path.clone();
                        let mut group = None;

                        // fbbus: a malformed `$share/` filter (no share name, or no filter
                        // after it) is refused with a failure code; the connection stays.
                        // Upstream subscribed `$share//x` as group "" and `$share/g/` as
                        // the empty filter.
                        match extract_group(&f.path) {
                            Ok(Some((grp, filter_path))) => {
                                group = Some(grp);
                                filter = filter_path;
                            }
                            Ok(None) => {}
                            Err(e) => {
                                warn!(reason = ?e, "Malformed shared subscription refused");
                                return_codes.push(SubscribeReasonCode::Failure);
                                continue;
                            }
                        };

                        let subscription_id = props.as_ref().and_then(|p| p.id);

                        if subscription_id == Some(0) {
                            error!("Subscription identifier can't be 0");
                            disconnect = true;
                            disconnect_reason = Some(DisconnectReasonCode::ProtocolError);
                            break;
                        }

                        let (idx, cursor) = self.datalog.next_native_offset(&filter);

                        // in case of shared sub original_filter will be $share/group/topic
                        // this is because we do want to treat is as diffrent subscription
                        // and create DataRequest, while using the same datalog of "topic"
                        // NOTE: topic & $share/group/topic will have same filteridx!
                        self.prepare_filter(id, cursor, idx, f, group, subscription_id);

                        let code = match f.qos {
                            QoS::AtMostOnce => SubscribeReasonCode::QoS0,
                            QoS::AtLeastOnce => SubscribeReasonCode::QoS1,
                            QoS::ExactlyOnce => SubscribeReasonCode::QoS2,
                        };

                        return_codes.push(code);
                    }

                    // let meter = &mut self.ibufs.get_mut(id).unwrap().meter;
                    // meter.total_size += len;

                    let suback = SubAck { pkid, return_codes };
                    let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                    ackslog.suback(suback);
                    force_ack = true;
                }
                Packet::Unsubscribe(unsubscribe, _) => {
                    let pkid = unsubscribe.pkid;
                    for filter in &unsubscribe.filters {
                        let span = tracing::info_span!("unsubscribe", topic = filter, pkid);
                        let _guard = span.enter();

                        debug!("Removing subscription on filter {}", filter);
                        // fbbus: the set of a filter nobody subscribes any more is removed.
                        if self.unsubscribe_from_map(filter, id) {
                            let connection = self.connections.get_mut(id).expect(SLABS_IN_STEP);
                            if !connection.subscriptions.remove(filter) {
                                warn!(
                                    pkid = unsubscribe.pkid,
                                    "Unsubscribe failed as filter was not subscribed previously"
                                );
                                continue;
                            }

                            // fbbus: the client leaves the group of this shared subscription
                            // only (groups are per share name and filter, see
                            // `extract_group`); upstream removed it from every group it was in
                            // whatever filter it unsubscribed, and its other shared
                            // subscriptions then got nothing. An empty group is discarded.
                            let shared = extract_group(filter).ok().flatten();
                            let log_filter = match &shared {
                                Some((group_name, log_filter)) => {
                                    if let Some(group) =
                                        self.shared_subscriptions.get_mut(group_name)
                                    {
                                        group.remove_client(&client_id);
                                        if group.is_empty() {
                                            self.shared_subscriptions.remove(group_name);
                                        }
                                    }
                                    log_filter.as_str()
                                }
                                None => filter.as_str(),
                            };
                            // fbbus: a parked read request is found in its filter's log
                            // (a shared subscription's is the filter's after the share name;
                            // upstream looked for a log named `$share/...`, found none and
                            // left the request parked, so the client kept receiving).
                            self.datalog.remove_waiters_for_id(id, log_filter, filter);

                            if let Some(broker_aliases) = connection.broker_topic_aliases.as_mut() {
                                broker_aliases.remove_alias(filter);
                            }

                            // remove the subscription id
                            connection.subscription_ids.remove(filter);

                            let unsuback = UnsubAck {
                                pkid,
                                // reasons are used in MQTTv5
                                reasons: vec![UnsubAckReason::Success],
                            };
                            let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                            ackslog.unsuback(unsuback);
                            self.scheduler.untrack(id, filter);
                            force_ack = true;
                        }
                    }
                }
                Packet::PubAck(puback, _) => {
                    let span = tracing::trace_span!(
                        "puback",
                        /* fbbus: trace, per packet */ pkid = puback.pkid
                    );
                    let _guard = span.enter();

                    let outgoing = self.obufs.get_mut(id).expect(SLABS_IN_STEP);
                    let pkid = puback.pkid;
                    if outgoing.register_ack(pkid).is_none() {
                        error!(pkid, "Unsolicited/ooo ack received for pkid {}", pkid);
                        disconnect = true;
                        break;
                    }

                    self.scheduler.reschedule(id, ScheduleReason::IncomingAck);
                }
                Packet::PubRec(pubrec, _) => {
                    let span = tracing::trace_span!(
                        "pubrec",
                        /* fbbus: trace, per packet */ pkid = pubrec.pkid
                    );
                    let _guard = span.enter();

                    let outgoing = self.obufs.get_mut(id).expect(SLABS_IN_STEP);
                    let pkid = pubrec.pkid;
                    if outgoing.register_ack(pkid).is_none() {
                        error!(pkid, "Unsolicited/ooo ack received for pkid {}", pkid);
                        disconnect = true;
                        break;
                    }

                    let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                    let pubrel = PubRel {
                        pkid: pubrec.pkid,
                        reason: PubRelReason::Success,
                    };

                    outgoing.register_pubrec(pubrel.pkid);
                    ackslog.pubrel(pubrel);
                    self.scheduler.reschedule(id, ScheduleReason::IncomingAck);
                }
                Packet::PubRel(pubrel, None) => {
                    let span = tracing::trace_span!(
                        "pubrel",
                        /* fbbus: trace, per packet */ pkid = pubrel.pkid
                    );
                    let _guard = span.enter();

                    // fbbus: the QoS 2 publish this PUBREL releases is appended now.
                    let topic = self
                        .ackslog
                        .get(id)
                        .and_then(|ackslog| ackslog.next_recorded_topic())
                        .cloned();
                    if let Some(hold) = topic.and_then(|topic| self.hold_for(&topic)) {
                        packets.push_front(Packet::PubRel(pubrel, None));
                        held = Some(hold);
                        break;
                    }

                    let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                    let pubcomp = PubComp {
                        pkid: pubrel.pkid,
                        reason: PubCompReason::Success,
                    };

                    // NOTE: client can try to resend previously unacked pubrels
                    // on reconnection ( with clean session false )
                    // we try to retrive publish assuming broker saved the previous state
                    // successfully in graveyard.
                    let (publish, props) = match ackslog.pubcomp(pubcomp) {
                        Some(v) => v,
                        None => {
                            disconnect = true;
                            break;
                        }
                    };

                    // Try to append publish to commitlog
                    match append_to_commitlog(
                        id,
                        publish,
                        props,
                        &mut self.datalog,
                        &mut self.notifications,
                        &mut self.connections,
                    ) {
                        Ok(_offset) => {
                            // Even if one of the data in the batch is appended to commitlog,
                            // set new data. This triggers notifications to wake waiters.
                            // Don't overwrite this flag to false if it is already true.
                            new_data = true;
                        }
                        Err(e) => {
                            // Disconnect on bad publishes
                            error!(
                                reason = ?e, "Failed to append to commitlog"
                            );
                            disconnect = true;
                            break;
                        }
                    };
                    self.scheduler.reschedule(id, ScheduleReason::IncomingAck);
                }
                Packet::PubComp(pubcomp, _) => {
                    let span = tracing::trace_span!(
                        "pubcomp",
                        /* fbbus: trace, per packet */ pkid = pubcomp.pkid
                    );
                    let _guard = span.enter();

                    let outgoing = self.obufs.get_mut(id).expect(SLABS_IN_STEP);
                    let pkid = pubcomp.pkid;
                    if outgoing.register_pubcomp(pkid).is_none() {
                        error!(
                            pkid,
                            "ack received for pkid {}, but the pkid didn't exists!", pkid
                        );
                        disconnect = true;
                        break;
                    }
                }
                Packet::PingReq(_) => {
                    let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
                    ackslog.pingresp(PingResp);

                    force_ack = true;
                }
                Packet::Disconnect(_, _) => {
                    let span = tracing::info_span!("disconnect");
                    let _guard = span.enter();
                    disconnect = true;
                    // delete the last will message
                    self.last_wills.remove(&client_id);
                    break;
                }
                incoming => {
                    warn!(packet=?incoming, "Unexpected packet received, ignoring the packet." );
                }
            }
        }

        if let Some((filter_idx, boundary)) = held {
            if let Some(incoming) = self.ibufs.get(id) {
                incoming.put_back(packets);
            }
            self.holds.hold(id, filter_idx, boundary);
        }

        // Prepare AcksRequest in tracker if router is operating in a
        // single node mode or force ack request for subscriptions
        if force_ack {
            self.scheduler.reschedule(id, ScheduleReason::FreshData);
        }

        // Notify waiting consumers only if there is publish data. During
        // subscription, data request is added to data waiter. With out this
        // if condition, connection will be woken up even during subscription
        if new_data {
            // Prepare all the consumers which are waiting for new data
            while let Some((id, request)) = self.notifications.pop_front() {
                self.scheduler.track(id, request);
                self.scheduler.reschedule(id, ScheduleReason::FreshData);
            }
        }

        // Incase BytesMut represents 10 packets, publish error/diconnect event
        // on say 5th packet should not block new data notifications for packets
        // 1 - 4. Hence we use a flag instead of diconnecting immediately
        if disconnect {
            self.handle_disconnection(id, disconnect_reason);
        }
    }

    /// Apply filter and prepare this connection to receive subscription data
    /// Handle retained messages as per subscription options!
    fn prepare_filter(
        &mut self,
        id: ConnectionId,
        cursor: Offset,
        filter_idx: FilterIdx,
        filter: &protocol::Filter,
        group: Option<String>,
        subscription_id: Option<usize>,
    ) {
        let filter_path = &filter.path;

        // Add connection id to subscription list
        match self.subscription_map.get_mut(filter_path) {
            Some(connections) => {
                connections.insert(id);
            }
            None => {
                let mut connections = HashSet::new();
                connections.insert(id);
                self.subscription_map
                    .insert(filter_path.clone(), connections);
            }
        }

        // Prepare consumer to pull data in case of subscription
        let connection = self.connections.get_mut(id).expect(SLABS_IN_STEP);

        // Add/Create shared group
        if let Some(group_name) = &group {
            let client_id = connection.client_id.clone();

            let shared_group = self
                .shared_subscriptions
                .entry(group_name.to_string())
                .or_insert(SharedGroup::new(
                    cursor,
                    self.config.shared_subscriptions_strategy.clone(),
                ));

            shared_group.add_client(client_id);
        };

        if let Some(subscription_id) = subscription_id {
            connection
                .subscription_ids
                .insert(filter_path.clone(), subscription_id);
        }

        // check is group is None because retained messages aren't sent
        // for shared subscriptions
        // fbbus: nor to a subscription with Retain Handling 2 (MQTT 5 3.8.3.1,
        // `RetainForwardRule::Never`). Upstream read them all and left the embedder to
        // drop them: a session put back at start (`broker/src/store/restore.rs`)
        // subscribes with Retain Handling 2, and 1,000 of them walked 100,000 retained
        // messages each (14 s of a restart).
        let forward_retained =
            group.is_none() && filter.retain_forward_rule != RetainForwardRule::Never;

        // call to `insert(_)` returns `true` if it didn't contain the filter_path already
        // i.e. its a new subscription
        if connection.subscriptions.insert(filter_path.clone()) {
            let request = DataRequest {
                filter: filter_path.clone(),
                filter_idx,
                qos: filter.qos as u8,
                cursor,
                read_count: 0,
                max_count: 100,
                // set true for new subscriptions
                forward_retained,
                retained_again: 0,
                group,
                skipping: false,
                slow: false,
                retained_pending: Default::default(),
            };

            self.scheduler.track(id, request);
            self.scheduler.reschedule(id, ScheduleReason::NewFilter);
            debug_assert!(self.scheduler.check_tracker_duplicates(id).is_none())
        } else {
            // fbbus: a repeated SUBSCRIBE of a filter the connection already has replaces
            // the subscription [MQTT-3.8.4-3]: its maximum QoS is the new one (upstream
            // kept the first), and it gets the retained messages again when its Retain
            // Handling is 0 (MQTT 5 [MQTT-3.3.1-9], [MQTT-3.8.4-4]; MQTT 3.1.1
            // [MQTT-3.8.4-3], which the v4 parser maps to `OnEverySubscribe`). Upstream
            // sent them only for a new filter.
            let retained_again = forward_retained
                && filter.retain_forward_rule == RetainForwardRule::OnEverySubscribe;
            self.replace_request(id, filter_path, filter.qos as u8, retained_again);
        }

        // TODO: figure out how we can update existing DataRequest
        // helpful in re-subscriptions and forwarding retained messages on
        // every subscribe
    }

    /// fbbus: updates the connection's existing data request for `filter_path` wherever
    /// it is (the connection's tracker, the router's notification queue, or parked among
    /// the filter's waiters): the subscription's new maximum `qos`, and, with
    /// `retained_again`, the retained messages to forward once more. The request keeps its
    /// cursor, so no live message is lost or repeated.
    fn replace_request(
        &mut self,
        id: ConnectionId,
        filter_path: &Filter,
        qos: u8,
        retained_again: bool,
    ) {
        let update = |request: &mut DataRequest| {
            request.qos = qos;
            if retained_again && request.forward_retained {
                // The previous SUBSCRIBE's retained messages are not sent yet: this one
                // gets its own copy after them.
                request.retained_again = request.retained_again.saturating_add(1);
            } else if retained_again {
                request.forward_retained = true;
            }
        };
        let in_tracker = self.scheduler.trackers.get_mut(id).and_then(|tracker| {
            tracker
                .data_requests
                .iter_mut()
                .find(|r| r.filter == *filter_path)
        });
        let unparked = if let Some(request) = in_tracker {
            update(request);
            false
        } else if let Some((_, request)) = self
            .notifications
            .iter_mut()
            .find(|(owner, r)| *owner == id && r.filter == *filter_path)
        {
            update(request);
            false
        } else if let Some(mut request) = self.datalog.remove_waiters_for_id(
            id,
            // fbbus: a shared subscription's request is parked in its filter's log.
            &extract_group(filter_path)
                .ok()
                .flatten()
                .map_or_else(|| filter_path.clone(), |(_, log_filter)| log_filter),
            filter_path,
        ) {
            // Parked until new data: back to the tracker and scheduled, so it is read
            // again (nothing new to read parks it again).
            update(&mut request);
            self.scheduler.track(id, request);
            true
        } else {
            return;
        };
        if retained_again || unparked {
            self.scheduler.reschedule(id, ScheduleReason::NewFilter);
        }
    }

    /// When a connection is ready, it should sweep native data from 'datalog',
    /// send data and notifications to consumer.
    /// To activate a connection, first connection's tracker is fetched and
    /// all the requests are handled.
    fn consume(&mut self) -> Option<()> {
        let (id, mut requests) = self.scheduler.poll()?;

        // fbbus: trace, not info (per scheduling round).
        let span = tracing::trace_span!("[<] outgoing", connection_id = id);
        let _guard = span.enter();

        let outgoing = match self.obufs.get_mut(id) {
            Some(v) => v,
            None => {
                error!("Connection is already disconnected");
                return Some(());
            }
        };

        let ackslog = self.ackslog.get_mut(id).expect(SLABS_IN_STEP);
        let datalog = &mut self.datalog;

        trace!("Consuming requests");

        // We always try to ack when ever a connection is scheduled
        ack_device_data(ackslog, outgoing);

        // fbbus: the connection's buffer stays locked for the whole round, and the
        // connection is woken once, at its end: the connection then reads everything the
        // round forwarded, for all its filters, in one batch. Forwards were pushed and
        // announced one filter at a time upstream, so a connection could read the copies
        // of one message for two of its overlapping subscriptions in two batches, and then
        // could not choose one copy (`broker::session::copies`).
        let buffer = outgoing.buffer();
        let mut buffer = buffer.lock();
        let mut forwarded = false;

        let connection = self.connections.get_mut(id).expect(SLABS_IN_STEP);

        // Keep track of temporarily skipped DataRequest
        // NOTE: VecDeque::new() doesn't allocate memory until elements are pushed
        let mut skipped_requests: VecDeque<DataRequest> = VecDeque::new();

        // A new connection's tracker is always initialized with acks request.
        // A subscribe will register data request.
        // So a new connection is always scheduled with at least one request
        for _ in 0..MAX_SCHEDULE_ITERATIONS {
            let mut request = match requests.pop_front() {
                // Handle next data or acks request
                Some(request) => request,
                // No requests in the queue. This implies that consumer data and
                // acks are completely caught up. Pending requests are registered
                // in waiters and awaiting new notifications (device or replica data)
                None => {
                    drop(buffer);
                    if forwarded {
                        outgoing.handle.wake();
                    }
                    if skipped_requests.is_empty() {
                        // if no requests is in skip list, that means
                        // we have nothing left to process, i.e. we caughtup
                        self.scheduler.pause(id, PauseReason::Caughtup);
                    }
                    // add back the skipped requests!
                    self.scheduler.trackv(id, skipped_requests);
                    return Some(());
                }
            };

            let shared_group = request
                .group
                .as_ref()
                .and_then(|name| self.shared_subscriptions.get_mut(name));

            match forward_device_data(
                &mut request,
                datalog,
                (outgoing, &mut buffer, &mut forwarded),
                connection,
                shared_group,
                &mut self.hooks.skipped,
            ) {
                ConsumeStatus::BufferFull => {
                    requests.push_back(request);
                    self.scheduler.pause(id, PauseReason::Busy);
                    break;
                }
                ConsumeStatus::InflightFull => {
                    requests.push_back(request);
                    self.scheduler.pause(id, PauseReason::InflightFull);
                    break;
                }
                ConsumeStatus::FilterCaughtup => {
                    let filter = &request.filter;
                    trace!(filter, "Filter caughtup {filter}, parking connection");

                    // When all the data in the log is caught up, current request is
                    // registered in waiters and not added back to the tracker. This
                    // ensures that tracker.next() stops when all the requests are done
                    datalog.park(id, request);
                }
                ConsumeStatus::PartialRead => {
                    requests.push_back(request);
                }
                ConsumeStatus::SkipRequest => {
                    skipped_requests.push_back(request);
                }
            }
        }

        drop(buffer);
        if forwarded {
            outgoing.handle.wake();
        }
        // Add requests back to the tracker if there are any
        requests.extend(skipped_requests);
        self.scheduler.trackv(id, requests);
        Some(())
    }

    /// fbbus: the filter and boundary to hold a publish on `topic` for: appending it now
    /// would drop messages a live reader has not read yet (`holds`).
    fn hold_for(&mut self, topic: &[u8]) -> Option<(FilterIdx, u64)> {
        if !self.holds.enabled() {
            return None;
        }
        let topic = std::str::from_utf8(topic).ok()?;
        self.datalog
            .drop_boundaries(topic)
            .into_iter()
            .find(|&(filter_idx, boundary)| {
                self.holds.holds(filter_idx, boundary)
                    || self
                        .lowest_live_cursor(filter_idx)
                        .is_some_and(|offset| offset < boundary)
            })
    }

    /// fbbus: the lowest offset a live reader of the filter reads next (`holds`): the
    /// subscriptions of connected clients that are not marked slow (nor of a connection
    /// that never holds publishers: `Connection::holds_publishers`), wherever their request
    /// is (scheduled, just notified, parked), shared ones at their group's cursor.
    fn lowest_live_cursor(&self, filter_idx: FilterIdx) -> Option<u64> {
        let groups = &self.shared_subscriptions;
        let holds = |id: &ConnectionId| {
            self.connections
                .get(*id)
                .is_none_or(|connection| connection.holds_publishers)
        };
        self.scheduler
            .trackers
            .iter()
            .flat_map(|(id, tracker)| tracker.data_requests.iter().map(move |r| (id, r)))
            .chain(
                self.notifications
                    .iter()
                    .map(|(id, request)| (*id, request)),
            )
            .chain(
                self.datalog
                    .native
                    .get(filter_idx)
                    .into_iter()
                    .flat_map(|data| data.waiters.waiters().iter().map(|(id, r)| (*id, r))),
            )
            .filter(|(id, request)| request.filter_idx == filter_idx && !request.slow && holds(id))
            .map(|(_, request)| reads_from(request, groups))
            .min()
    }

    /// fbbus: publishers were held for `hold_limit` and readers of the filter are still
    /// below `boundary`: they are slow now, skip what retention drops, and hold nobody back
    /// until they catch up (`holds`).
    fn mark_slow(&mut self, filter_idx: FilterIdx, boundary: u64) {
        let groups = &self.shared_subscriptions;
        let tracked = self
            .scheduler
            .trackers
            .iter_mut()
            .flat_map(|(_, tracker)| tracker.data_requests.iter_mut());
        let notified = self.notifications.iter_mut().map(|(_, request)| request);
        for request in tracked.chain(notified) {
            if request.filter_idx == filter_idx && reads_from(request, groups) < boundary {
                request.slow = true;
            }
        }
    }

    /// fbbus: lets held publishers go on once the readers they were held for have read
    /// past the boundary, or once they were held for `hold_limit` (`holds`).
    fn let_held_go(&mut self) {
        let Some(filters) = self.holds.due() else {
            return;
        };
        for (filter_idx, hold) in filters {
            let still_there = self
                .datalog
                .native
                .get(filter_idx)
                .is_some_and(|data| data.log.drop_boundary() == Some(hold.boundary));
            let behind = still_there
                && self
                    .lowest_live_cursor(filter_idx)
                    .is_some_and(|offset| offset < hold.boundary);
            let gave_up = behind && self.holds.expired(&hold);
            if behind && !gave_up {
                continue;
            }
            if gave_up {
                self.mark_slow(filter_idx, hold.boundary);
            }
            let released = self.holds.release(filter_idx);
            let report = self.hooks.held.as_mut();
            if let (Some(report), Some(data)) = (report, self.datalog.native.get(filter_idx)) {
                report(&Held {
                    filter: data.filter(),
                    publishers: released.len(),
                    waited: hold.since.elapsed(),
                    gave_up,
                });
            }
            for id in released {
                self.handle_device_payload(id);
            }
        }
    }

    /// fbbus: gives back the memory no reader needs any more, then calls the `released`
    /// hook.
    /// Commit-log data is kept from the lowest offset anyone may still read: subscribers'
    /// read requests (active, parked, of offline persistent sessions, of shared groups)
    /// and unacknowledged QoS 1/2 deliveries, which a resumed session re-reads.
    fn release_memory(&mut self) {
        self.dirty = false;
        self.last_release = std::time::Instant::now();
        let mut needed: HashMap<FilterIdx, u64> = HashMap::new();
        let mut need = |filter_idx: FilterIdx, offset: u64| {
            needed
                .entry(filter_idx)
                .and_modify(|o| *o = (*o).min(offset))
                .or_insert(offset);
        };
        let requests = self
            .scheduler
            .trackers
            .iter()
            .flat_map(|(_, tracker)| tracker.data_requests.iter())
            .chain(
                self.datalog
                    .native
                    .iter()
                    .flat_map(|(_, data)| data.waiters.waiters().iter().map(|(_, r)| r)),
            )
            .chain(self.notifications.iter().map(|(_, r)| r))
            .chain(self.graveyard.data_requests());
        for request in requests {
            need(request.filter_idx, request.cursor.1);
            let group = request.group.as_ref();
            if let Some(group) = group.and_then(|g| self.shared_subscriptions.get(g)) {
                need(request.filter_idx, group.cursor.1);
            }
        }
        for (_, outgoing) in self.obufs.iter_mut() {
            for (filter_idx, cursor) in outgoing.retransmission_map() {
                need(filter_idx, cursor.1);
            }
            outgoing.compact();
        }
        for (filter_idx, data) in self.datalog.native.iter_mut() {
            data.log.release_read(needed.get(&filter_idx).copied());
            super::iobufs::shrink_if_empty(data.waiters.get_mut());
        }
        for (_, ackslog) in self.ackslog.iter_mut() {
            ackslog.compact();
        }
        for (_, tracker) in self.scheduler.trackers.iter_mut() {
            super::iobufs::shrink_if_empty(&mut tracker.data_requests);
        }
        // fbbus: logs of filters nothing refers to any more go too (`DataLog::remove_unused`).
        self.remove_unused_filters(needed.into_keys().collect());
        // fbbus: the segments released above are freed on the freeing thread; the hook runs
        // there after them.
        crate::freer::dispose(Box::new(()), self.hooks.released.clone());
    }

    pub fn handle_last_will(&mut self, client_id: String) {
        let Some((will, will_props)) = self.last_wills.remove(&client_id) else {
            return;
        };

        let publish = Publish {
            dup: false,
            qos: will.qos,
            retain: will.retain,
            topic: will.topic,
            pkid: 0,
            payload: will.message,
            origin: None, // fbbus
        };

        let properties = will_props.map(|props| {
            Box::new(PublishProperties {
                payload_format_indicator: props.payload_format_indicator,
                message_expiry_interval: props.message_expiry_interval,
                response_topic: props.response_topic,
                correlation_data: props.correlation_data,
                user_properties: props.user_properties,
                content_type: props.content_type,
                ..Default::default()
            })
        });

        match append_will_message(
            publish,
            properties,
            &mut self.datalog,
            &mut self.notifications,
        ) {
            Ok(_offset) => {
                // Prepare all the consumers which are waiting for new data
                while let Some((id, request)) = self.notifications.pop_front() {
                    self.scheduler.track(id, request);
                    self.scheduler.reschedule(id, ScheduleReason::FreshData);
                }
            }
            Err(e) => {
                // Disconnect on bad publishes
                error!(
                    reason = ?e, "Failed to append to commitlog"
                );
                // Removed disconnect = true from here because we disconnect anyways
            }
        };
    }
}

/// fbbus: the offset a request reads next: a shared subscription reads at its group's
/// cursor.
fn reads_from(request: &DataRequest, groups: &HashMap<String, SharedGroup>) -> u64 {
    request
        .group
        .as_ref()
        .and_then(|group| groups.get(group))
        .map_or(request.cursor.1, |group| group.cursor.1)
}

fn append_to_commitlog(
    id: ConnectionId,
    mut publish: Publish,
    mut properties: Option<Box<PublishProperties>>,
    datalog: &mut DataLog,
    notifications: &mut VecDeque<(ConnectionId, DataRequest)>,
    connections: &mut IdTable<Connection>,
) -> Result<Offset, RouterError> {
    let connection = connections.get_mut(id).expect(SLABS_IN_STEP);

    let topic_alias = properties.as_mut().and_then(|p| {
        // clear the received value as it is irrelevant while forwarding publishes
        p.topic_alias.take()
    });

    // TODO: broker should properly send the disconnect packet!
    if properties
        .as_ref()
        .is_some_and(|p| !p.subscription_identifiers.is_empty())
    {
        error!("A PUBLISH packet sent from a Client to a Server MUST NOT contain a Subscription Identifier");
        return Err(RouterError::Disconnect(
            DisconnectReasonCode::MalformedPacket,
        ));
    }

    if let Some(alias) = topic_alias {
        validate_and_set_topic_alias(&mut publish, connection, alias)?;
    };

    let topic = std::str::from_utf8(&publish.topic)?;

    if publish.payload.is_empty() {
        datalog.remove_from_retained_publishes(topic.to_owned());
    } else if publish.retain {
        // fbbus: not kept beyond the retained store's bounds; routed all the same.
        let _ = datalog.insert_to_retained_publishes(
            publish.clone(),
            properties.clone(),
            topic.to_owned(),
        );
    }

    // after recording retained message, we also send that message to existing subscribers
    // as normal publish message. Therefore we are setting retain to false
    publish.retain = false;
    let pkid = publish.pkid;

    let filter_idxs = datalog.matches(topic);

    // Create a dynamic filter if dynamic_filters are enabled for this connection
    let filter_idxs = match filter_idxs {
        Some(v) => v,
        None if connection.dynamic_filters => {
            let (idx, _cursor) = datalog.next_native_offset(topic);
            vec![idx]
        }
        None => return Err(RouterError::NoMatchingFilters(topic.to_owned())),
    };

    let mut o = (0, 0);
    for filter_idx in filter_idxs {
        let datalog = datalog
            .native
            .get_mut(filter_idx)
            .expect(MATCHED_FILTERS_EXIST);
        let publish_data = (publish.clone(), properties.clone());
        let (offset, filter) = datalog.append(publish_data.into(), notifications);
        debug!(
            pkid,
            "Appended to commitlog: {}[{}, {})", filter, offset.0, offset.1,
        );

        o = offset;
    }

    // error!("{:15.15}[E] {:20} topic = {}", connections[id].client_id, "no-filter", topic);
    Ok(o)
}

fn append_will_message(
    mut publish: Publish,
    properties: Option<Box<PublishProperties>>,
    datalog: &mut DataLog,
    notifications: &mut VecDeque<(ConnectionId, DataRequest)>,
) -> Result<Offset, RouterError> {
    // TODO: broker should properly send the disconnect packet!
    if properties
        .as_ref()
        .is_some_and(|p| !p.subscription_identifiers.is_empty())
    {
        error!("A PUBLISH packet sent from a Client to a Server MUST NOT contain a Subscription Identifier");
        return Err(RouterError::Disconnect(
            DisconnectReasonCode::MalformedPacket,
        ));
    }

    let topic = std::str::from_utf8(&publish.topic)?;

    if publish.payload.is_empty() {
        datalog.remove_from_retained_publishes(topic.to_owned());
    } else if publish.retain {
        // fbbus: not kept beyond the retained store's bounds; routed all the same.
        let _ = datalog.insert_to_retained_publishes(
            publish.clone(),
            properties.clone(),
            topic.to_owned(),
        );
    }

    // after recording retained message, we also send that message to existing subscribers
    // as normal publish message. Therefore we are setting retain to false
    publish.retain = false;
    let pkid = publish.pkid;

    let filter_idxs = datalog.matches(topic);

    let filter_idxs = match filter_idxs {
        Some(v) => v,
        None => return Err(RouterError::NoMatchingFilters(topic.to_owned())),
    };

    let mut o = (0, 0);
    for filter_idx in filter_idxs {
        let datalog = datalog
            .native
            .get_mut(filter_idx)
            .expect(MATCHED_FILTERS_EXIST);
        let publish_data = (publish.clone(), properties.clone());
        let (offset, filter) = datalog.append(publish_data.into(), notifications);
        debug!(
            pkid,
            "Appended to commitlog: {}[{}, {})", filter, offset.0, offset.1,
        );

        o = offset;
    }

    Ok(o)
}

fn validate_and_set_topic_alias(
    publish: &mut Publish,
    connection: &mut Connection,
    alias: u16,
) -> Result<(), RouterError> {
    if alias == 0 || alias > TOPIC_ALIAS_MAX {
        error!("Alias must be greater than 0 and <={TOPIC_ALIAS_MAX}");
        return Err(RouterError::Disconnect(
            DisconnectReasonCode::TopicAliasInvalid,
        ));
    }

    if publish.topic.is_empty() {
        // if publish topic is empty, publisher must have set a valid alias
        let Some(alias_topic) = connection.topic_aliases.get(&alias) else {
            error!("Empty topic name with invalid alias");
            return Err(RouterError::Disconnect(DisconnectReasonCode::ProtocolError));
        };
        // set the publish topic before further processing
        publish.topic = alias_topic.to_owned().into();
    } else {
        // if publish topic isn't empty, that means
        // publisher wants to establish new mapping for topic & alias
        let topic = std::str::from_utf8(&publish.topic)?;
        connection.topic_aliases.insert(alias, topic.to_owned());
        trace!("set alias {alias} for topic {topic}");
    };

    Ok(())
}

/// Sweep ackslog for all the pending acks.
/// We write everything to outgoing buf with out worrying about buffer size
/// because acks most certainly won't cause memory bloat
fn ack_device_data(ackslog: &mut AckLog, outgoing: &mut Outgoing) -> bool {
    // fbbus: trace, not info (per acknowledgement batch).
    let span = tracing::trace_span!("outgoing_ack", client_id = outgoing.client_id);
    let _guard = span.enter();

    // fbbus: the acks are taken, leaving the log unallocated. A connection's acks come in
    // small batches (its ConnAck, a SubAck, the PubAcks of one read); a log that kept its
    // largest batch's capacity until the router was idle left, after a connection storm,
    // a hole next to every connection's memory that the allocator could not give back.
    let acks = std::mem::take(ackslog.readv());
    if acks.is_empty() {
        debug!("No acks pending");
        return false;
    }

    let mut count = 0;
    let mut buffer = outgoing.data_buffer.lock();

    // Unlike forwards, we are reading all the pending acks for a given connection.
    // At any given point of time, there can be a max of connection's buffer size
    for ack in acks {
        let pkid = packetid(&ack);
        trace!(pkid, "Ack added for pkid {}", pkid);
        let message = Notification::DeviceAck(ack);
        buffer.push_back(message);
        count += 1;
    }

    debug!(acks_count = count, "Acks sent to device");
    outgoing.handle.wake();
    true
}

enum ConsumeStatus {
    /// Limit for publishes on outgoing channel reached
    BufferFull,
    /// Limit for inflight publishes on outgoing channel reached
    InflightFull,
    /// All publishes on topic forwarded
    FilterCaughtup,
    /// Some publishes on topic have been forwarded
    PartialRead,
    /// Use to indicate we want to skip the datareqest
    /// for shared subscriptions
    SkipRequest,
}

/// Sweep datalog from offset in DataRequest and updates DataRequest
/// for next sweep. Returns (busy, caughtup) status
/// Returned arguments:
/// 1. `busy`: whether the data request was completed or not.
/// 2. `done`: whether the connection was busy or not.
/// 3. `inflight_full`: whether the inflight requests were completely filled
///
/// fbbus: forwards go to `buffer`, the connection's buffer that `Router::consume` holds
/// locked for its round, and set `forwarded`; `consume` wakes the connection at the end.
fn forward_device_data(
    request: &mut DataRequest,
    datalog: &mut DataLog,
    (outgoing, buffer, forwarded): (&mut Outgoing, &mut VecDeque<Notification>, &mut bool),
    connection: &mut Connection,
    shared_group: Option<&mut SharedGroup>,
    on_skip: &mut Option<SkipHook>,
) -> ConsumeStatus {
    // fbbus: trace, not info (per forwarded batch).
    let span = tracing::trace_span!("outgoing_publish", client_id = outgoing.client_id);
    let _guard = span.enter();

    if let Some(ref shared_group) = shared_group {
        // update the request cursor to use shared cursor
        request.cursor = shared_group.cursor;
    }

    trace!(
        "Reading from datalog: {}[{}, {}]",
        request.filter,
        request.cursor.0,
        request.cursor.1
    );

    let mut inflight_slots = if request.qos != 0 {
        // for qos 1 & 2
        let len = outgoing.free_slots();
        if len == 0 {
            trace!("Aborting read from datalog: inflight capacity reached");
            return ConsumeStatus::InflightFull;
        }

        len as u64
    } else {
        datalog.config.max_outgoing_packet_count
    };

    if shared_group
        .as_ref()
        .is_some_and(|g| g.strategy == Strategy::RoundRobin)
    {
        // only read one message in case of round robin
        // so that messages get equally distributed!
        inflight_slots = 1;
    }

    let mut publishes = Vec::new();

    if request.forward_retained {
        // NOTE: ideally we want to limit the number of read messages
        // and skip the messages previously read while reading next time.
        // but for now, we just try to read all messages and drop the excess ones
        // fbbus: read once per SUBSCRIBE, then sent a window at a time until all went
        // (`DataRequest::retained_pending`); upstream dropped what exceeded one window.
        let pending = request.retained_pending.0.get_or_insert_with(|| {
            Box::new(datalog.read_retained_messages(&request.filter).into())
        });
        let n = (inflight_slots as usize).min(pending.len());
        publishes.extend(pending.drain(..n).map(|p| (p, None)));
        inflight_slots -= n as u64;

        // we only want to forward retained messages once
        // fbbus: once per SUBSCRIBE that asked for them (`retained_again`), each sent whole.
        if pending.is_empty() {
            request.retained_pending.0 = None;
            if request.retained_again > 0 {
                request.retained_again -= 1;
            } else {
                request.forward_retained = false;
            }
        }
    }

    let (next, publishes_from_datalog) =
        match datalog.native_readv(request.filter_idx, request.cursor, inflight_slots) {
            Ok(v) => v,
            Err(e) => {
                error!(error = ?e, "Failed to read from commitlog {}", e);
                return ConsumeStatus::FilterCaughtup;
            }
        };

    publishes.extend(
        publishes_from_datalog
            .into_iter()
            .map(|(p, offset)| (p, Some(offset))),
    );

    let (start, next, caughtup) = match next {
        Position::Next { start, end } => (start, end, false),
        Position::Done { start, end } => (start, end, true),
    };
    // fbbus: retained messages still to send for a repeated SUBSCRIBE keep the request
    // reading instead of parking it until new data arrives.
    let caughtup = caughtup && !request.forward_retained;

    if let Some(ref shared_group) = shared_group {
        let skip_current_client = Some(&outgoing.client_id) != shared_group.current_client();

        if skip_current_client {
            return if caughtup {
                ConsumeStatus::FilterCaughtup
            } else {
                ConsumeStatus::SkipRequest
            };
        }
    }

    // fbbus: a jump is measured in absolute offsets (the segment index of a cursor may
    // change without any message being skipped, see `CommitLog::readv`), reported to the
    // embedder with its size, and logged here at debug level only: a lagging subscriber
    // jumps on nearly every read, the embedder logs once per episode.
    if start.1 != request.cursor.1 {
        let count = start.1.saturating_sub(request.cursor.1);
        debug!(
            request_cursor = ?request.cursor,
            start_cursor = ?start,
            count,
            "Read cursor start jumped on {}",
            request.filter
        );
        if let Some(on_skip) = on_skip.as_mut() {
            on_skip(&Skipped {
                client_id: &outgoing.client_id,
                filter: &request.filter,
                count,
                first_in_episode: !request.skipping,
            });
        }
        request.skipping = true;
    }
    if caughtup {
        request.skipping = false;
        request.slow = false;
    }

    trace!(
        "Read from commitlog, cursor = {}[{}, {}), read count = {}",
        request.filter,
        next.0,
        next.1,
        publishes.len()
    );

    let qos = request.qos;
    let filter_idx = request.filter_idx;
    request.read_count += publishes.len();
    request.cursor = next;
    // println!("{:?} {:?} {}", start, next, request.read_count);

    if publishes.is_empty() {
        return ConsumeStatus::FilterCaughtup;
    }

    let broker_topic_aliases = &mut connection.broker_topic_aliases;
    let mut topic_alias = broker_topic_aliases
        .as_ref()
        .and_then(|aliases| aliases.get_alias(&request.filter));

    let topic_alias_already_exists = topic_alias.is_some();

    // if topic alias doesn't exists, try creating new one!
    if !topic_alias_already_exists {
        topic_alias = broker_topic_aliases
            .as_mut()
            .and_then(|broker_aliases| broker_aliases.set_new_alias(&request.filter))
    }

    let subscription_id = connection.subscription_ids.get(&request.filter);

    // Fill and notify device data
    let forwards = publishes
        .into_iter()
        .map(|((mut publish, mut properties), offset)| {
            publish.qos = protocol::qos(qos)
                .expect("invariant: a data request's qos is a QoS enum's value (0, 1 or 2)");

            // if there is some topic alias to use, set it in publish properties
            if topic_alias.is_some() {
                let mut props = properties.unwrap_or_default();
                props.topic_alias = topic_alias;
                properties = Some(props);
            }

            // We want to clear topic if we are using an existing alias
            if topic_alias_already_exists {
                publish.topic.clear()
            }

            if let Some(&subscription_id) = subscription_id {
                // create new props if not already exists
                let mut props = properties.unwrap_or_default();
                props.subscription_identifiers.push(subscription_id);
                properties = Some(props);
            }

            Forward {
                cursor: offset,
                size: 0,
                publish,
                properties,
            }
        });

    let (len, inflight) = outgoing.push_forwards(forwards, qos, filter_idx, buffer);
    *forwarded = true;

    debug!(
        inflight_count = inflight,
        forward_count = len,
        "Forwarding publishes, cursor = {}[{}, {}) forward count = {}",
        request.filter,
        request.cursor.0,
        request.cursor.1,
        len
    );

    if len >= MAX_CHANNEL_CAPACITY - 1 {
        debug!("Outgoing channel reached its capacity");
        buffer.push_back(Notification::Unschedule);
        return ConsumeStatus::BufferFull;
    }

    // update the state of shared subscription
    if let Some(share) = shared_group {
        share.update_next_client();
        // update the shared cursor
        share.cursor = request.cursor;
    }

    if caughtup {
        ConsumeStatus::FilterCaughtup
    } else {
        ConsumeStatus::PartialRead
    }
}

fn retrieve_shadow(datalog: &mut DataLog, outgoing: &mut Outgoing, shadow: ShadowRequest) {
    if let Some(reply) = datalog.shadow(&shadow.filter) {
        let publish = reply.0;
        let shadow_reply = router::ShadowReply {
            topic: publish.topic,
            payload: publish.payload,
        };

        // Fill notify shadow
        let message = Notification::Shadow(shadow_reply);
        let len = outgoing.push_notification(message);
        if len >= MAX_CHANNEL_CAPACITY - 1 {
            outgoing.push_notification(Notification::Unschedule);
        }
        outgoing.handle.wake();
    }
}

fn validate_subscription(
    connection: &mut Connection,
    filter: &protocol::Filter,
) -> Result<(), RouterError> {
    trace!(
        "validate subscription = {}, tenant = {:?}",
        filter.path,
        connection.tenant_prefix
    );
    // fbbus: `$fbbus/` is the embedding broker's own namespace (its readiness probe),
    // `$SYS/` its status topics (their read rule is the broker's); fbbus refuses every
    // other `$` filter of its clients before they reach the router.
    if filter.path.starts_with('$')
        && !filter.path.starts_with("$share")
        && !filter.path.starts_with("$fbbus/")
        && !filter.path.starts_with("$SYS/")
    {
        return Err(RouterError::InvalidFilterPrefix(filter.path.to_owned()));
    }

    Ok(())
}

/// fbbus: the message of a caught panic (`&str` or `String` payloads, as `panic!` makes).
fn panic_message(panic: &Box<dyn std::any::Any + Send>) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

fn validate_clientid(client_id: &str) -> Result<(), RouterError> {
    trace!("Validating Client ID = {}", client_id,);
    // Ensure that only client devices of the tenant can
    if "+$#/".chars().any(|c| client_id.contains(c)) {
        return Err(RouterError::InvalidClientId(client_id.to_string()));
    }

    Ok(())
}

/// `$share/{share name}/{filter}`: `Ok(Some((group, filter)))`; `Ok(None)` for a filter
/// that is not shared.
///
/// fbbus: the group is keyed by share name *and* filter (`{share name}/{filter}`): MQTT 5
/// makes each a shared subscription of its own (4.8.2). Upstream keyed the group by share
/// name only, so `$share/g/a` and `$share/g/b` shared one member list and one read cursor,
/// and a cursor into one filter's log was used to read the other's.
/// A `$share/` filter without a share name, with a wildcard in it, or without a filter
/// after it is an error ([MQTT-4.8.2-1], [MQTT-4.8.2-2]).
fn extract_group(filter: &str) -> Result<Option<(String, String)>, RouterError> {
    let Some(shared) = filter.strip_prefix("$share/") else {
        return Ok(None);
    };
    match shared.split_once('/') {
        Some((group, path))
            if !group.is_empty() && !group.contains(['+', '#']) && !path.is_empty() =>
        {
            Ok(Some((shared.to_string(), path.to_string())))
        }
        _ => Err(RouterError::InvalidFilterPrefix(filter.to_owned())),
    }
}

impl Router {
    /// fbbus: removes `id` from the connections subscribed to `filter`, and the filter from
    /// the map once nobody subscribes it (upstream kept an empty set for every filter ever
    /// subscribed). Whether `id` was subscribed.
    fn unsubscribe_from_map(&mut self, filter: &str, id: ConnectionId) -> bool {
        let Some(connections) = self.subscription_map.get_mut(filter) else {
            return false;
        };
        let removed = connections.remove(&id);
        if connections.is_empty() {
            self.subscription_map.remove(filter);
        }
        removed
    }

    /// fbbus: removes the logs of filters nothing refers to any more
    /// (`DataLog::remove_unused`). `used`: the filters of every read request and
    /// unacknowledged delivery; the subscriptions of connected clients and saved sessions
    /// and the holds are added here.
    fn remove_unused_filters(&mut self, mut used: HashSet<FilterIdx>) {
        let subscriptions = self
            .subscription_map
            .keys()
            .chain(self.graveyard.subscriptions());
        for subscription in subscriptions {
            // A shared subscription reads the log of the filter after its share name.
            let filter = subscription
                .strip_prefix("$share/")
                .and_then(|shared| shared.split_once('/'))
                .map_or(subscription.as_str(), |(_, filter)| filter);
            used.extend(self.datalog.filter_idx(filter));
        }
        used.extend(self.holds.filters());
        let removed = self.datalog.remove_unused(&used);
        if removed > 0 {
            debug!(removed, "removed the logs of filters nothing refers to");
        }
    }
}
// #[cfg(test)]
// #[allow(non_snake_case)]
// mod test {
//     use std::{
//         thread,
//         time::{Duration, Instant},
//     };

//     use bytes::BytesMut;

//     use super::*;
//     use crate::{
//         link::local::*,
//         protocol::v4::{self, subscribe::SubscribeFilter, QoS},
//         router::ConnectionMeter,
//     };

//     /// Create a router and n connections
//     fn new_router(count: usize, clean: bool) -> (Router, VecDeque<(LinkTx, LinkRx)>) {
//         let config = RouterConfig {
//             instant_ack: true,
//             max_segment_size: 1024 * 10, // 10 KB
//             max_mem_segments: 10,
//             max_disk_segments: 0,
//             max_read_len: 128,
//             log_dir: None,
//             max_connections: 128,
//             dynamic_log: false,
//         };

//         let mut router = Router::new(0, config);
//         let link = router.link();
//         let handle = thread::spawn(move || {
//             (0..count)
//                 .map(|i| Link::new(&format!("link-{}", i), link.clone(), clean))
//                 .collect::<VecDeque<Result<_, _>>>()
//         });

//         router.run_exact(count).unwrap();
//         let links = handle
//             .join()
//             .unwrap()
//             .into_iter()
//             .map(|x| x.unwrap())
//             .collect();
//         (router, links)
//     }

//     fn reconnect(router: &mut Router, link_id: usize, clean: bool) -> (LinkTx, LinkRx) {
//         let link = router.link();
//         let handle =
//             thread::spawn(move || Link::new(&format!("link-{}", link_id), link, clean).unwrap());
//         router.run(1).unwrap();
//         handle.join().unwrap()
//     }

//     #[test]
//     fn test_graveyard_retreive_metrics_always() {
//         let (mut router, mut links) = new_router(1, false);
//         let (tx, _) = links.pop_front().unwrap();
//         let id = tx.connection_id;
//         let conn = router.connections.get_mut(id).unwrap();
//         conn.meter = ConnectionMeter {
//             publish_size: 1000,
//             publish_count: 1000,
//             subscriptions: HashSet::new(),
//             events: conn.meter.events.clone(),
//         };
//         conn.meter.push_event("graveyard-testing".to_string());
//         router.handle_disconnection(id);

//         let (tx, _) = reconnect(&mut router, 0, false);
//         let id = tx.connection_id;
//         let conn = router.connections.get_mut(id).unwrap();
//         assert_eq!(conn.meter.publish_size, 1000);
//         assert_eq!(conn.meter.publish_count, 1000);
//         assert_eq!(conn.meter.events.len(), 4);

//         let (mut router, mut links) = new_router(1, true);
//         let (tx, _) = links.pop_front().unwrap();
//         let id = tx.connection_id;
//         let conn = router.connections.get_mut(id).unwrap();
//         conn.meter = ConnectionMeter {
//             publish_size: 1000,
//             publish_count: 1000,
//             subscriptions: HashSet::new(),
//             events: conn.meter.events.clone(),
//         };
//         conn.meter.push_event("graveyard-testing".to_string());
//         router.handle_disconnection(id);

//         let (tx, _) = reconnect(&mut router, 0, true);
//         let id = tx.connection_id;
//         let conn = router.connections.get_mut(id).unwrap();
//         assert_eq!(conn.meter.publish_size, 1000);
//         assert_eq!(conn.meter.publish_count, 1000);
//         assert_eq!(conn.meter.events.len(), 4);
//     }

//     #[test]
//     #[should_panic]
//     fn test_blocking_too_many_connections() {
//         new_router(512, true);
//     }

//     #[test]
//     fn test_not_clean_sessions() {
//         // called once per data push (subscribe to 2 topics in our case)
//         // called once per each sub topic
//         // if prepare_data_request called, then Tracker::register_data_request is also called so
//         // no need to check separately for that

//         let (mut router, mut links) = new_router(2, false);
//         let (tx1, mut rx1) = links.pop_front().unwrap();
//         let id1 = tx1.connection_id;
//         let (tx2, mut rx2) = links.pop_front().unwrap();
//         let id2 = tx2.connection_id;

//         // manually subscribing to avoid calling Router::run(), so that we can see and test changes
//         // in Router::readyqueue.
//         let mut buf = BytesMut::new();
//         v4::subscribe::write(
//             vec![
//                 SubscribeFilter::new("hello/1/world".to_string(), QoS::AtMostOnce),
//                 SubscribeFilter::new("hello/2/world".to_string(), QoS::AtMostOnce),
//             ],
//             0,
//             &mut buf,
//         )
//         .unwrap();
//         let buf = buf.freeze();
//         {
//             let incoming = router.ibufs.get_mut(id1).unwrap();
//             let mut recv_buf = incoming.buffer.lock();
//             recv_buf.push_back(buf.clone());
//             assert_eq!(router.subscription_map.len(), 0);
//         }
//         {
//             let incoming = router.ibufs.get_mut(id2).unwrap();
//             let mut recv_buf = incoming.buffer.lock();
//             recv_buf.push_back(buf.clone());
//             assert_eq!(router.subscription_map.len(), 0);
//         }

//         router.handle_device_payload(id1);
//         assert_eq!(router.subscription_map.len(), 2);
//         assert_eq!(router.readyqueue.len(), 1);
//         router.consume(id1);
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             1
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             1
//         );

//         router.handle_device_payload(id2);
//         assert_eq!(router.subscription_map.len(), 2);
//         assert_eq!(router.readyqueue.len(), 2);
//         router.consume(id2);
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );

//         assert!(matches!(rx1.recv().unwrap(), Some(Notification::DeviceAck(_))));
//         assert!(matches!(rx2.recv().unwrap(), Some(Notification::DeviceAck(_))));

//         router.handle_disconnection(id1);
//         router.handle_disconnection(id2);
//         router.run(1).unwrap();

//         let (_, _) = reconnect(&mut router, 0, false);
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             1
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             1
//         );

//         let (_, _) = reconnect(&mut router, 1, false);
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//     }

//     #[test]
//     fn test_publish_appended_to_commitlog() {
//         let (mut router, mut links) = new_router(2, true);
//         let (mut sub_tx, _) = links.pop_front().unwrap();
//         let (mut pub_tx, _) = links.pop_front().unwrap();

//         sub_tx.subscribe("hello/1/world").unwrap();
//         router.run(1).unwrap();

//         // Each LinkTx::publish creates a single new event
//         for _ in 0..10 {
//             pub_tx.publish("hello/1/world", b"hello".to_vec()).unwrap();
//         }
//         router.run(1).unwrap();
//         assert_eq!(router.datalog.next_native_offset("hello/1/world").1, (0, 10));
//     }

//     #[test]
//     fn test_adding_caughtups_to_waiters() {
//         // number of times forward_device_data hit
//         //     = router.run times * topics * subscribers per topic
//         //     = 2 * 2 * 2 = 8
//         //
//         // we also call consume 2 times per subsriber, and one time it will call
//         // forward_device_data again, but no data will actually be forwarded.
//         // as 256 publishes at once, and router's config only reads 128 at a time, data needs to be
//         // read from same log twice, and thus half of the times the data reading is not done

//         let (mut router, mut links) = new_router(4, true);
//         let (mut sub1_tx, _) = links.pop_front().unwrap();
//         let (mut pub1_tx, _) = links.pop_front().unwrap();
//         let (mut sub2_tx, _) = links.pop_front().unwrap();
//         let (mut pub2_tx, _) = links.pop_front().unwrap();
//         sub1_tx.subscribe("hello/1/world").unwrap();
//         sub1_tx.subscribe("hello/2/world").unwrap();
//         sub2_tx.subscribe("hello/1/world").unwrap();
//         sub2_tx.subscribe("hello/2/world").unwrap();
//         router.run(1).unwrap();

//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );

//         for _ in 0..256 {
//             pub1_tx.publish("hello/1/world", b"hello".to_vec()).unwrap();
//             pub2_tx.publish("hello/2/world", b"hello".to_vec()).unwrap();
//         }
//         router.run(1).unwrap();

//         let tracker = router.trackers.get(sub1_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 2);
//         let tracker = router.trackers.get(sub2_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 2);

//         router.run(1).unwrap();

//         let tracker = router.trackers.get(sub1_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 2);
//         let tracker = router.trackers.get(sub2_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 2);

//         router.consume(sub1_tx.connection_id);
//         router.consume(sub2_tx.connection_id);

//         let tracker = router.trackers.get(sub1_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 1);
//         let tracker = router.trackers.get(sub2_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 1);

//         router.consume(sub1_tx.connection_id);
//         router.consume(sub2_tx.connection_id);

//         let tracker = router.trackers.get(sub1_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 0);
//         let tracker = router.trackers.get(sub2_tx.connection_id).unwrap();
//         assert_eq!(tracker.get_data_requests().len(), 0);

//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/1/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//         assert_eq!(
//             router
//                 .datalog
//                 .waiters(&"hello/2/world".to_string())
//                 .unwrap()
//                 .waiters()
//                 .len(),
//             2
//         );
//     }

//     #[test]
//     fn test_disconnect_invalid_sub() {
//         let (mut router, mut links) = new_router(3, true);

//         let (mut tx, mut rx) = links.pop_front().unwrap();
//         tx.subscribe("$hello/world").unwrap();
//         router.run(1).unwrap();
//         assert!(matches!(rx.recv(), Err(LinkError::Recv(flume::RecvError::Disconnected))));

//         let (mut tx, mut rx) = links.pop_front().unwrap();
//         tx.subscribe("test/hello").unwrap();
//         router.run(1).unwrap();
//         assert!(matches!(rx.recv(), Err(LinkError::Recv(flume::RecvError::Disconnected))));
//     }

//     #[test]
//     fn test_disconnect_invalid_pub() {
//         let (mut router, mut links) = new_router(1, true);
//         let (mut tx, mut rx) = links.pop_front().unwrap();
//         tx.publish("invalid/topic", b"hello".to_vec()).unwrap();
//         router.run(1).unwrap();
//         assert!(matches!(rx.recv(), Err(LinkError::Recv(flume::RecvError::Disconnected))));
//     }

//     #[test]
//     fn test_pingreq() {
//         let (mut router, mut links) = new_router(1, true);
//         let (mut tx, mut rx) = links.pop_front().unwrap();
//         let mut buf = BytesMut::new();
//         mqttbytes::v4::PingReq.write(&mut buf).unwrap();
//         let buf = buf.freeze();
//         for _ in 0..10 {
//             tx.push(buf.clone()).unwrap();
//         }
//         router.run(1).unwrap();
//         for _ in 0..10 {
//             let ret = rx.recv().unwrap().unwrap();
//             assert!(matches!(ret, Notification::DeviceAck(Ack::PingResp)));
//         }
//     }

//     #[test]
//     fn test_disconnect() {
//         let (mut router, mut links) = new_router(1, true);
//         let (mut tx, mut rx) = links.pop_front().unwrap();
//         let mut buf = BytesMut::new();
//         mqttbytes::v4::Disconnect.write(&mut buf).unwrap();
//         let buf = buf.freeze();
//         tx.push(buf).unwrap();
//         router.run(1).unwrap();
//         assert!(matches!(rx.recv(), Err(LinkError::Recv(flume::RecvError::Disconnected))));
//     }

//     #[test]
//     fn test_connection_in_qos1() {
//         // connection as in crate::connection::Connection struct should get filled for all unacked,
//         // and refuse to add more packets than unacked.

//         let config = RouterConfig {
//             instant_ack: true,
//             max_segment_size: 1024 * 10, // 10 KB
//             max_mem_segments: 10,
//             max_disk_segments: 0,
//             max_read_len: 256,
//             log_dir: None,
//             max_connections: 128,
//             dynamic_log: false,
//         };

//         let mut router = Router::new(0, config);
//         let link = router.link();
//         let handle = thread::spawn(move || {
//             (0..2)
//                 .map(|i| Link::new(&format!("link-{}", i), link.clone(), true))
//                 .collect::<VecDeque<Result<_, _>>>()
//         });

//         router.run(2).unwrap();
//         let mut links: VecDeque<(LinkTx, LinkRx)> = handle
//             .join()
//             .unwrap()
//             .into_iter()
//             .map(|x| x.unwrap())
//             .collect();

//         let (mut sub_tx, _sub_rx) = links.pop_front().unwrap();
//         let (mut pub_tx, _) = links.pop_front().unwrap();

//         let mut buf = BytesMut::new();
//         mqttbytes::v4::Subscribe::new("hello/1/world", mqttbytes::QoS::AtLeastOnce)
//             .write(&mut buf)
//             .unwrap();
//         let buf = buf.freeze();
//         sub_tx.push(buf).unwrap();
//         router.run(1).unwrap();

//         for _ in 0..202 {
//             pub_tx.publish("hello/1/world", b"hello".to_vec()).unwrap();
//         }
//         router.run(1).unwrap();

//         let id = sub_tx.connection_id;
//         let tracker = router.trackers.get(id).unwrap();
//         assert_eq!(tracker.get_data_requests().front().unwrap().cursor, (0, 200));
//     }

//     #[test]
//     #[ignore]
//     fn test_resend_in_qos1() {
//         unimplemented!("we don't resend QoS1 packets yet")
//     }

//     #[test]
//     fn test_wildcard_subs() {
//         let (mut router, mut links) = new_router(3, true);

//         let (mut sub1_tx, mut sub1_rx) = links.pop_front().unwrap();
//         sub1_tx.subscribe("#").unwrap();

//         let (mut sub2_tx, mut sub2_rx) = links.pop_front().unwrap();
//         sub2_tx.subscribe("hello/+/world").unwrap();

//         let (mut pub_tx, mut _pub_rx) = links.pop_front().unwrap();
//         for _ in 0..10 {
//             for i in 0..10 {
//                 pub_tx
//                     .publish(format!("hello/{}/world", i), b"hello".to_vec())
//                     .unwrap();
//             }
//         }

//         for _ in 0..10 {
//             pub_tx.publish("hello/world", b"hello".to_vec()).unwrap();
//         }

//         router.run(1).unwrap();

//         let mut count = 0;
//         while let Ok(Some(notification)) =
//             sub1_rx.recv_deadline(Instant::now() + Duration::from_millis(1))
//         {
//             match notification {
//                 Notification::Forward { .. } => count += 1,
//                 _ => {}
//             }
//         }
//         assert_eq!(count, 110);

//         count = 0;
//         while let Ok(Some(notification)) =
//             sub2_rx.recv_deadline(Instant::now() + Duration::from_millis(1))
//         {
//             match notification {
//                 Notification::Forward { .. } => count += 1,
//                 _ => {}
//             }
//         }
//         assert_eq!(count, 100);
//     }
// }

// // #[cfg(test)]
// // mod test {
// //     use crate::connection::Connection;
// //     use crate::link::local::{Link, LinkRx, LinkTx};
// //     use crate::tracker::Tracker;
// //     use crate::{ConnectionId, Notification, Router, RouterConfig};
// //     use bytes::BytesMut;
// //     use flume::Receiver;
// //     use mqttbytes::v4::{Publish, Subscribe};
// //     use mqttbytes::QoS;
// //     use std::collections::VecDeque;
// //     use std::sync::atomic::AtomicBool;
// //     use std::sync::Arc;
// //     use std::thread;

// //     /// Create a router and n connections
// //     fn router(count: usize) -> (Router, VecDeque<(LinkTx, LinkRx)>) {
// //         let config = RouterConfig {
// //             data_filter: "hello/world".to_owned(),
// //             wildcard_filters: vec![],
// //             instant_ack: true,
// //             max_segment_size: 10 * 1024,
// //             max_segment_count: 10 * 1024,
// //             max_connections: 10,
// //         };

// //         let mut router = Router::new(0, config);
// //         let link = router.link();
// //         let handle = thread::spawn(move || {
// //             (0..count)
// //                 .map(|i| Link::new(&format!("link-{}", i), link.clone()).unwrap())
// //                 .collect()
// //         });

// //         router.run(count).unwrap();
// //         let links = handle.join().unwrap();
// //         (router, links)
// //     }

// //     /// Creates a connection
// //     fn connection(client_id: &str, clean: bool) -> (Connection, Receiver<Notification>) {
// //         let (tx, rx) = flume::bounded(10);
// //         let connection = Connection::new(client_id, clean, tx, Arc::new(AtomicBool::new(false)));
// //         (connection, rx)
// //     }

// //     /// Raw publish message
// //     fn publish(topic: &str) -> BytesMut {
// //         let mut publish = Publish::new(topic, QoS::AtLeastOnce, vec![1, 2, 3]);
// //         publish.pkid = 1;

// //         let mut o = BytesMut::new();
// //         publish.write(&mut o).unwrap();
// //         o
// //     }

// //     /// Raw publish message
// //     fn subscribe(topic: &str) -> BytesMut {
// //         let mut subscribe = Subscribe::new(topic, QoS::AtLeastOnce);
// //         subscribe.pkid = 1;

// //         let mut o = BytesMut::new();
// //         subscribe.write(&mut o).unwrap();
// //         o
// //     }

// //     /// When there is new data on a subscription's commitlog, it's
// //     /// consumer should start triggering data requests to pull data
// //     /// from commitlog
// //     #[test]
// //     fn new_connection_data_triggers_acks_of_self_and_data_of_consumer() {
// //         let (mut router, mut links) = router(2);
// //         let (mut l1tx, _l1rx) = links.pop_front().unwrap();
// //         let (mut l2tx, l2rx) = links.pop_front().unwrap();

// //         l2tx.subscribe("hello/world").unwrap();
// //         l1tx.publish("hello/world", vec![1, 2, 3]).unwrap();
// //         let _ = router.run(1);

// //         // Suback
// //         match l2rx.recv().unwrap() {
// //             Notification::DeviceAcks(_) => {}
// //             v => panic!("{:?}", v),
// //         }

// //         // Consumer data
// //         match l2rx.recv().unwrap() {
// //             Notification::DeviceData { cursor, .. } => assert_eq!(cursor, (0, 1)),
// //             v => panic!("{:?}", v),
// //         }

// //         // No acks for qos0 publish
// //     }

// //     #[test]
// //     fn half_open_connections_are_handled_correctly() {
// //         let config = RouterConfig {
// //             data_filter: "hello/world".to_owned(),
// //             wildcard_filters: vec![],
// //             instant_ack: true,
// //             max_segment_size: 10 * 1024,
// //             max_segment_count: 10 * 1024,
// //             max_connections: 10,
// //         };

// //         let mut router = Router::new(0, config);
// //         let (c, rx) = connection("test", true);
// //         router.handle_new_connection(c);

// //         let id = *router.connection_map.get("test").unwrap();
// //         router.handle_device_payload(id, subscribe("hello/data"));
// //         router.handle_device_payload(id, publish("hello/data"));

// //         let trackers = router.trackers.get(id).unwrap();
// //         assert!(trackers.get_data_requests().len() > 0);
// //         dbg!(trackers);

// //         // A new connection with same client id
// //         let (c, rx) = connection("test", true);
// //         router.handle_new_connection(c);

// //         let id = *router.connection_map.get("test").unwrap();
// //         let trackers = router.trackers.get(id).unwrap();
// //         dbg!(trackers);
// //     }
// // }

// fbbus: the router's own tests, driving it directly (no thread, no links): a client is a
// registered connection whose input buffer the test fills and whose output buffer it reads.
#[cfg(test)]
mod fbbus_tests {
    use std::sync::Arc;

    use parking_lot::Mutex;

    use super::*;
    use crate::protocol::{Filter as SubscriptionFilter, Subscribe, Unsubscribe};
    use crate::router::Ack;

    fn router(max_saved_sessions: usize) -> Router {
        Router::new(
            0,
            RouterConfig {
                max_connections: 16,
                max_outgoing_packet_count: 200,
                max_segment_size: 10 * 1024,
                max_segment_count: 10,
                max_saved_sessions,
                ..Default::default()
            },
        )
    }

    struct Client {
        id: ConnectionId,
        incoming: Arc<Mutex<VecDeque<Packet>>>,
        outgoing: Arc<Mutex<VecDeque<Notification>>>,
        _wakeups: crate::router::wakeup::WakeRx,
    }

    impl Client {
        fn drain(&self) -> Vec<Notification> {
            self.outgoing.lock().drain(..).collect()
        }

        fn forwards(&self) -> usize {
            let forward = |n: &Notification| matches!(n, Notification::Forward(_));
            self.drain().iter().filter(|n| forward(n)).count()
        }
    }

    fn connect(router: &mut Router, client_id: &str, clean: bool) -> Client {
        let connection = Connection::new(None, client_id.to_owned(), clean, false);
        let incoming = Incoming::new(client_id.to_owned());
        let (outgoing, wakeups) = Outgoing::new(
            client_id.to_owned(),
            crate::router::iobufs::DEFAULT_MAX_INFLIGHT,
        );
        let client = Client {
            id: 0,
            incoming: incoming.buffer(),
            outgoing: outgoing.buffer(),
            _wakeups: wakeups,
        };
        let id = router.ids.take().expect("a free connection id");
        router.handle_new_connection(id, connection, incoming, outgoing);
        assert_eq!(router.connection_map[client_id], id);
        run(router);
        Client { id, ..client }
    }

    /// The session_present flag of the ConnAck a connection got.
    fn session_present(client: &Client) -> bool {
        client.drain().iter().any(|n| {
            matches!(n, Notification::DeviceAck(Ack::ConnAck(_, ack, _)) if ack.session_present)
        })
    }

    fn send(router: &mut Router, client: &Client, packet: Packet) {
        client.incoming.lock().push_back(packet);
        router.handle_device_payload(client.id);
        run(router);
    }

    fn run(router: &mut Router) {
        for _ in 0..1000 {
            if router.consume().is_none() {
                return;
            }
        }
    }

    fn subscribe(filters: &[&str], qos: QoS) -> Packet {
        let filters = filters
            .iter()
            .map(|path| SubscriptionFilter {
                path: path.to_string(),
                qos,
                nolocal: false,
                preserve_retain: false,
                retain_forward_rule: RetainForwardRule::Never,
            })
            .collect();
        Packet::Subscribe(Subscribe { pkid: 1, filters }, None)
    }

    fn unsubscribe(filter: &str) -> Packet {
        let filters = vec![filter.to_owned()];
        Packet::Unsubscribe(Unsubscribe { pkid: 2, filters }, None)
    }

    fn publish(topic: &str) -> Packet {
        Packet::Publish(Publish::new(topic.to_owned(), "m".to_owned(), false), None)
    }

    fn suback_codes(client: &Client) -> Vec<SubscribeReasonCode> {
        client
            .drain()
            .into_iter()
            .filter_map(|n| match n {
                Notification::DeviceAck(Ack::SubAck(suback)) => Some(suback.return_codes),
                _ => None,
            })
            .flatten()
            .collect()
    }

    /// Publishes `n` messages of 1 KiB on `topic` from `publisher`, one device read each;
    /// how many of them the router took (a held publisher's stay in its incoming buffer).
    fn publish_kib(router: &mut Router, publisher: &Client, topic: &str, n: usize) -> usize {
        let payload = "x".repeat(1024);
        for _ in 0..n {
            let publish = Publish::new(topic.to_owned(), payload.clone(), false);
            send(router, publisher, Packet::Publish(publish, None));
        }
        n - publisher.incoming.lock().len()
    }

    /// fbbus: a subscriber that stops reading holds the publishers of its filter back
    /// (`holds`), unless its connection does not hold publishers (an observer such as the
    /// line console): then the publisher goes on, and the observer skips.
    #[test]
    fn an_observer_that_stops_reading_never_holds_publishers() {
        for (holds_publishers, held) in [(true, true), (false, false)] {
            let mut router = router(16);
            router.holds = Holds::new(std::time::Duration::from_secs(60));
            let mut connection = Connection::new(None, "reader".to_owned(), true, false);
            connection.holds_publishers = holds_publishers;
            let incoming = Incoming::new("reader".to_owned());
            let (outgoing, _wakeups) = Outgoing::new(
                "reader".to_owned(),
                crate::router::iobufs::DEFAULT_MAX_INFLIGHT,
            );
            let (reader_in, reader_out) = (incoming.buffer(), outgoing.buffer());
            let id = router.ids.take().expect("a free connection id");
            router.handle_new_connection(id, connection, incoming, outgoing);
            let reader = Client {
                id: router.connection_map["reader"],
                incoming: reader_in,
                outgoing: reader_out,
                _wakeups,
            };
            run(&mut router);
            send(&mut router, &reader, subscribe(&["t/#"], QoS::AtMostOnce));
            reader.drain();
            // The reader never drains again: 200 packets fill its outgoing buffer, and the
            // filter's log (10 segments of 10 KiB) fills behind it.
            let publisher = connect(&mut router, "pub", true);
            let taken = publish_kib(&mut router, &publisher, "t/a", 400);
            if held {
                assert!(
                    taken < 400,
                    "a reader that holds: the publisher is held ({taken})"
                );
            } else {
                assert_eq!(taken, 400, "an observer holds nobody back");
            }
        }
    }

    /// A persistent session with a shared subscription leaves with a delivery it did not
    /// acknowledge, as the group's last member. Upstream: `expect("group must exists")`.
    #[test]
    fn a_persistent_shared_subscriber_leaves_with_an_unacked_delivery() {
        let mut router = router(16);
        let subscriber = connect(&mut router, "sub", false);
        send(
            &mut router,
            &subscriber,
            subscribe(&["$share/g/x"], QoS::AtLeastOnce),
        );
        let publisher = connect(&mut router, "pub", true);
        send(&mut router, &publisher, publish("x"));
        assert_eq!(subscriber.forwards(), 1);

        router.handle_disconnection(subscriber.id, None);
        assert!(router.shared_subscriptions.is_empty());
        assert!(router.graveyard.get("sub").is_some());
    }

    /// A link's wake-up (`Event::Ready`) after the router dropped its connection, also once
    /// the id is another connection's; a shadow request likewise. Upstream: `unwrap` on the
    /// gone tracker, a debug assertion on the reused one, `obufs[id]`.
    #[test]
    fn events_of_a_link_whose_connection_is_gone_are_ignored() {
        let mut router = router(16);
        let gone = connect(&mut router, "a", true);
        router.handle_disconnection(gone.id, None);
        router.events(gone.id, Event::Ready);
        router.events(gone.id, Event::DeviceData);
        router.events(gone.id, Event::Disconnect);
        router.events(gone.id, Event::Shadow(ShadowRequest { filter: "x".into() }));

        let reused = connect(&mut router, "b", true);
        assert_eq!(reused.id, gone.id, "the slab reuses the id");
        router.events(gone.id, Event::Ready);
        run(&mut router);
        send(&mut router, &reused, subscribe(&["x"], QoS::AtMostOnce));
        let publisher = connect(&mut router, "pub", true);
        send(&mut router, &publisher, publish("x"));
        assert_eq!(reused.forwards(), 1);
    }

    /// One SUBSCRIBE of a filter and of a shared subscription of it: two requests on one
    /// log. Upstream: the tracker's duplicate check (by log) failed a debug assertion.
    #[test]
    fn a_filter_and_its_shared_subscription_in_one_subscribe() {
        let mut router = router(16);
        let subscriber = connect(&mut router, "sub", true);
        send(
            &mut router,
            &subscriber,
            subscribe(&["x", "$share/g/x"], QoS::AtMostOnce),
        );
        assert_eq!(
            suback_codes(&subscriber),
            vec![SubscribeReasonCode::QoS0, SubscribeReasonCode::QoS0]
        );
        let publisher = connect(&mut router, "pub", true);
        send(&mut router, &publisher, publish("x"));
        assert_eq!(subscriber.forwards(), 2);
    }

    /// Malformed `$share/` filters get a failure code, the connection stays, and neither a
    /// group nor a log is made for them.
    #[test]
    fn malformed_shared_subscriptions_are_refused() {
        let mut router = router(16);
        let client = connect(&mut router, "sub", true);
        let bad = [
            "$share//x",
            "$share/g/",
            "$share/g",
            "$share/g+/x",
            "$share/#/x",
        ];
        let mut filters = bad.to_vec();
        filters.push("ok");
        send(&mut router, &client, subscribe(&filters, QoS::AtMostOnce));
        let mut expected = vec![SubscribeReasonCode::Failure; bad.len()];
        expected.push(SubscribeReasonCode::QoS0);
        assert_eq!(suback_codes(&client), expected);
        assert!(router.connections.contains(client.id));
        assert!(router.shared_subscriptions.is_empty());
        assert_eq!(router.datalog.sizes().0, 1, "only `ok` has a log");
        assert_eq!(router.subscription_map.len(), 1);
    }

    /// Each shared subscription is a group of its own: `$share/g/a` and `$share/g/b` do not
    /// share a cursor (upstream read one filter's log with the other's cursor).
    #[test]
    fn shared_subscriptions_of_two_filters_in_one_group_each_get_their_messages() {
        let mut router = router(16);
        let subscriber = connect(&mut router, "sub", true);
        send(
            &mut router,
            &subscriber,
            subscribe(&["$share/g/a"], QoS::AtMostOnce),
        );
        send(
            &mut router,
            &subscriber,
            subscribe(&["$share/g/b"], QoS::AtMostOnce),
        );
        let publisher = connect(&mut router, "pub", true);
        for topic in ["a", "a", "a", "b"] {
            send(&mut router, &publisher, publish(topic));
        }
        assert_eq!(subscriber.forwards(), 4);
    }

    /// Unsubscribing one filter keeps the client's other shared subscriptions; unsubscribing
    /// a shared subscription ends it, parked request included (upstream: removed from every
    /// group, and a parked shared request stayed and kept delivering).
    #[test]
    fn unsubscribing_ends_exactly_that_subscription() {
        let mut router = router(16);
        let subscriber = connect(&mut router, "sub", true);
        send(
            &mut router,
            &subscriber,
            subscribe(&["$share/g/x", "y"], QoS::AtMostOnce),
        );
        let publisher = connect(&mut router, "pub", true);

        send(&mut router, &subscriber, unsubscribe("y"));
        send(&mut router, &publisher, publish("x"));
        send(&mut router, &publisher, publish("y"));
        assert_eq!(subscriber.forwards(), 1, "x only");

        send(&mut router, &subscriber, unsubscribe("$share/g/x"));
        assert!(router.shared_subscriptions.is_empty());
        send(&mut router, &publisher, publish("x"));
        assert_eq!(subscriber.forwards(), 0);
        assert!(router.subscription_map.is_empty());
    }

    /// A clean session leaves nothing behind; persistent ones are saved up to
    /// `max_saved_sessions`, the oldest dropped and counted; a clean connect ends a saved
    /// session (fbbus's expiry and Clean Start purge).
    #[test]
    fn saved_sessions_are_bounded() {
        let stats = Arc::new(crate::SavedSessions::default());
        let mut router = router(2).with_hooks(RouterHooks {
            saved_sessions: stats.clone(),
            ..Default::default()
        });
        let clean = connect(&mut router, "clean", true);
        send(&mut router, &clean, subscribe(&["c"], QoS::AtLeastOnce));
        router.handle_disconnection(clean.id, None);
        assert_eq!(router.graveyard.len(), 0);

        for client_id in ["p1", "p2", "p3"] {
            let client = connect(&mut router, client_id, false);
            assert!(!session_present(&client));
            send(
                &mut router,
                &client,
                subscribe(&[client_id], QoS::AtLeastOnce),
            );
            router.handle_disconnection(client.id, None);
        }
        assert_eq!((stats.saved(), stats.dropped()), (2, 1));

        let p1 = connect(&mut router, "p1", false);
        assert!(!session_present(&p1), "p1 was dropped");
        let p3 = connect(&mut router, "p3", false);
        assert!(session_present(&p3));
        let publisher = connect(&mut router, "pub", true);
        send(&mut router, &publisher, publish("p3"));
        assert_eq!(p3.forwards(), 1, "the saved subscription is back");
        // p2 is still saved; a clean link with its client id ends it.
        assert_eq!(stats.saved(), 1);
        let purge = connect(&mut router, "p2", true);
        assert!(!session_present(&purge));
        router.handle_disconnection(purge.id, None);
        assert_eq!((stats.saved(), stats.dropped()), (0, 1));
    }

    /// The subscription map and the filters' logs shrink with the subscriptions: a client
    /// subscribing to ever new filters leaves nothing behind once it is gone.
    #[test]
    fn filters_nobody_subscribes_are_forgotten() {
        let mut router = router(1);
        let churn = connect(&mut router, "churn", true);
        let filters: Vec<String> = (0..100).map(|i| format!("f/{i}/#")).collect();
        let filters: Vec<&str> = filters.iter().map(String::as_str).collect();
        send(&mut router, &churn, subscribe(&filters, QoS::AtMostOnce));
        let persistent = connect(&mut router, "persistent", false);
        send(
            &mut router,
            &persistent,
            subscribe(&["kept"], QoS::AtLeastOnce),
        );
        router.handle_disconnection(persistent.id, None);
        let publisher = connect(&mut router, "pub", true);
        send(&mut router, &publisher, publish("f/1/x"));
        assert_eq!(churn.forwards(), 1);

        router.release_memory();
        assert_eq!(router.datalog.sizes().0, 101, "all still subscribed");
        router.handle_disconnection(churn.id, None);
        assert_eq!(router.subscription_map.len(), 0);
        router.release_memory();
        assert_eq!(
            router.datalog.sizes(),
            (1, 0),
            "the saved session's log stays"
        );

        // Dropped at the cap (1) by another saved session: its log goes too.
        let other = connect(&mut router, "other", false);
        router.handle_disconnection(other.id, None);
        router.release_memory();
        assert_eq!(router.datalog.sizes().0, 0);
    }
}
