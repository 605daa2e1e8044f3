use crate::protocol::{ConnAck, ConnAckProperties, ConnectReturnCode};
use crate::protocol::{
    Filter, LastWill, LastWillProperties, Packet, Publish, QoS, RetainForwardRule, Subscribe,
    Unsubscribe,
};
pub use crate::router::wakeup::Nudge;
use crate::router::Ack;
use crate::router::{
    ids::ConnectionIds,
    iobufs::{Incoming, Outgoing},
    wakeup::WakeRx,
    Connection, Event, Notification, ShadowRequest,
};
use crate::ConnectionId;
use bytes::Bytes;
use flume::{RecvError, RecvTimeoutError, SendError, Sender, TrySendError};
use parking_lot::lock_api::MutexGuard;
use parking_lot::{Mutex, RawMutex};

use std::collections::VecDeque;
use std::mem;
use std::sync::Arc;
use std::time::Instant;

#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    #[error("Unexpected router message")]
    NotConnectionAck,
    #[error("ConnAck error {0}")]
    ConnectionAck(String),
    // fbbus: the event that could not be sent is dropped, not carried in the error:
    // `Event::Connect` made every `Result<_, LinkError>` several hundred bytes
    // (clippy::result_large_err), in every link call of every connection.
    #[error("Channel try send error")]
    TrySend(TrySendError<()>),
    #[error("Channel send error")]
    Send(SendError<()>),
    #[error("Channel recv error")]
    Recv(#[from] RecvError),
    #[error("Channel timeout recv error")]
    RecvTimeout(#[from] RecvTimeoutError),
    /// fbbus: the router holds `max_connections` connections.
    #[error("no space for a new connection in the router")]
    NoSpace,
    /// fbbus: the router refuses client ids with `+`, `#`, `/` or `$`.
    #[error("client id not accepted by the router: {0}")]
    InvalidClientId(String),
}

// fbbus: see `LinkError::TrySend`.
impl From<TrySendError<(ConnectionId, Event)>> for LinkError {
    fn from(e: TrySendError<(ConnectionId, Event)>) -> Self {
        LinkError::TrySend(match e {
            TrySendError::Full(_) => TrySendError::Full(()),
            TrySendError::Disconnected(_) => TrySendError::Disconnected(()),
        })
    }
}

impl From<SendError<(ConnectionId, Event)>> for LinkError {
    fn from(_: SendError<(ConnectionId, Event)>) -> Self {
        LinkError::Send(SendError(()))
    }
}

// used to build LinkTx and LinkRx
pub struct LinkBuilder<'a> {
    tenant_id: Option<String>,
    client_id: &'a str,
    router_tx: Sender<(ConnectionId, Event)>,
    // fbbus: where the link takes its connection id (`Router::connection_ids`).
    ids: ConnectionIds,
    // true by default
    clean_session: bool,
    last_will: Option<LastWill>,
    last_will_properties: Option<LastWillProperties>,
    // false by default
    dynamic_filters: bool,
    // default to 0, indicating to not use topic alias
    topic_alias_max: u16,
    // fbbus: true by default (`Connection::holds_publishers`)
    holds_publishers: bool,
    // fbbus: `DEFAULT_MAX_INFLIGHT` by default
    max_inflight: u16,
}

impl<'a> LinkBuilder<'a> {
    pub fn new(
        client_id: &'a str,
        router_tx: Sender<(ConnectionId, Event)>,
        ids: ConnectionIds,
    ) -> Self {
        LinkBuilder {
            client_id,
            router_tx,
            ids,
            tenant_id: None,
            clean_session: true,
            last_will: None,
            last_will_properties: None,
            dynamic_filters: false,
            topic_alias_max: 0,
            holds_publishers: true,
            max_inflight: crate::router::iobufs::DEFAULT_MAX_INFLIGHT,
        }
    }

    /// fbbus: QoS 1/2 deliveries the router sends this connection unacknowledged at most
    /// (at least 1); also its highest packet id.
    pub fn max_inflight(mut self, max: u16) -> Self {
        self.max_inflight = max.max(1);
        self
    }

    pub fn tenant_id(mut self, tenant_id: Option<String>) -> Self {
        self.tenant_id = tenant_id;
        self
    }

    pub fn last_will(mut self, last_will: Option<LastWill>) -> Self {
        self.last_will = last_will;
        self
    }

    pub fn last_will_properties(
        mut self,
        last_will_properties: Option<LastWillProperties>,
    ) -> Self {
        self.last_will_properties = last_will_properties;
        self
    }

    pub fn topic_alias_max(mut self, max: u16) -> Self {
        self.topic_alias_max = max;
        self
    }

    pub fn clean_session(mut self, clean: bool) -> Self {
        self.clean_session = clean;
        self
    }

    /// fbbus: false for an observer link whose lag must never hold publishers back: it
    /// skips what its filters' logs drop before it reads it.
    pub fn holds_publishers(mut self, holds: bool) -> Self {
        self.holds_publishers = holds;
        self
    }

    pub fn dynamic_filters(mut self, dynamic_filters: bool) -> Self {
        self.dynamic_filters = dynamic_filters;
        self
    }

    pub fn build(self) -> Result<(LinkTx, LinkRx, Notification), LinkError> {
        let (claim, event, pending) = self.connect_event(false)?;
        pending.router_tx.send((claim.id, event))?;
        claim.sent();
        pending.link_rx.recv()?;
        pending.finish()
    }

    /// fbbus: `build` without blocking the calling thread while the router registers the
    /// connection, so a runtime worker keeps serving other connections meanwhile.
    pub async fn build_async(self) -> Result<(LinkTx, LinkRx, Notification), LinkError> {
        let (claim, event, pending) = self.connect_event(false)?;
        pending.router_tx.send_async((claim.id, event)).await?;
        claim.sent();
        pending.link_rx.recv_async().await?;
        pending.finish()
    }

    /// fbbus: a clean session's link, ready without waiting for the router: its id comes
    /// from the shared pool, and what the router would answer a clean session is known
    /// (no session present, success, the router's topic alias maximum), so the ConnAck is
    /// made here and the router sends none. What the link sends after its Connect reaches
    /// the router after it (one channel), and a connection with the same client id is
    /// still dropped when the router takes this one. A link for a session the router may
    /// hold (not clean) waits with `build_async`: its ConnAck says whether one was there
    /// and pending PUBRELs follow it.
    ///
    /// This saves each connection the wait for the router thread: one connection alone
    /// is answered about 13 % sooner (docs/performance.md). With many connecting at once
    /// the worker filled that wait with the others, and the router is still woken once
    /// per Connect, so the connection rate did not change.
    pub async fn build_linked(self) -> Result<(LinkTx, LinkRx, Notification), LinkError> {
        if !self.clean_session {
            return self.build_async().await;
        }
        let (claim, event, pending) = self.connect_event(true)?;
        pending.router_tx.send_async((claim.id, event)).await?;
        let id = claim.sent();
        let ack = ConnAck {
            session_present: false,
            code: ConnectReturnCode::Success,
        };
        let properties = ConnAckProperties {
            topic_alias_max: Some(crate::router::TOPIC_ALIAS_MAX),
            ..Default::default()
        };
        let notification =
            Notification::DeviceAck(Ack::ConnAck(id, ack, Some(Box::new(properties))));
        let tx = LinkTx::new(id, pending.router_tx.clone(), pending.incoming_data_buffer);
        let rx = LinkRx::new(
            id,
            pending.router_tx,
            pending.link_rx,
            pending.outgoing_data_buffer,
        );
        Ok((tx, rx, notification))
    }

    /// The router's Connect event under the connection id taken for it, and what the link
    /// needs once the router answered it.
    fn connect_event(
        self,
        acked_by_link: bool,
    ) -> Result<(IdClaim, Event, PendingLink), LinkError> {
        // fbbus: what the router would refuse silently is refused here, before an id is
        // taken (the router gives a refused connection's id back).
        if "+$#/".chars().any(|c| self.client_id.contains(c)) {
            return Err(LinkError::InvalidClientId(self.client_id.to_owned()));
        }
        let claim = IdClaim {
            id: self.ids.take().ok_or(LinkError::NoSpace)?,
            ids: Some(self.ids),
        };
        // Connect to router
        // Local connections to the router shall have access to all subscriptions
        let mut connection = Connection::new(
            self.tenant_id,
            self.client_id.to_owned(),
            self.clean_session,
            self.dynamic_filters,
        );

        connection
            .last_will(self.last_will, self.last_will_properties)
            .topic_alias_max(self.topic_alias_max);
        connection.holds_publishers = self.holds_publishers;
        connection.acked_by_link = acked_by_link;
        let incoming = Incoming::new(connection.client_id.to_owned());
        let (outgoing, link_rx) = Outgoing::new(connection.client_id.to_owned(), self.max_inflight);
        let pending = PendingLink {
            router_tx: self.router_tx,
            link_rx,
            outgoing_data_buffer: outgoing.buffer(),
            incoming_data_buffer: incoming.buffer(),
        };

        let event = Event::Connect {
            connection,
            incoming,
            outgoing,
        };
        Ok((claim, event, pending))
    }
}

/// fbbus: a connection id taken from the pool for a Connect not yet sent. Given back if the
/// Connect never reaches the router (the router is gone, or the link's future was dropped
/// while the router's channel was full); from then on the router gives it back.
struct IdClaim {
    id: ConnectionId,
    ids: Option<ConnectionIds>,
}

impl IdClaim {
    /// The router has the Connect: the id is its to give back.
    fn sent(mut self) -> ConnectionId {
        self.ids = None;
        self.id
    }
}

impl Drop for IdClaim {
    fn drop(&mut self) {
        if let Some(ids) = self.ids.take() {
            ids.give_back(self.id);
        }
    }
}

/// fbbus: a link whose Connect event was sent, waiting for the router's ConnAck.
struct PendingLink {
    router_tx: Sender<(ConnectionId, Event)>,
    link_rx: WakeRx,
    outgoing_data_buffer: Arc<Mutex<VecDeque<Notification>>>,
    incoming_data_buffer: Arc<Mutex<VecDeque<Packet>>>,
}

impl PendingLink {
    fn finish(self) -> Result<(LinkTx, LinkRx, Notification), LinkError> {
        // fbbus: everything the router buffered with the ConnAck (a resumed session's
        // PubRels, what its subscriptions had queued) is taken with it, into the link's
        // cache: the wake-up that announced them is the one just taken (`wakeup`: they
        // coalesce), so nothing would announce them again. The router's buffer is left
        // unallocated, not kept by an idle connection.
        let (notification, rest) = {
            let mut buffer = self.outgoing_data_buffer.lock();
            let notification = buffer.pop_front().ok_or(LinkError::NotConnectionAck)?;
            (notification, mem::take(&mut *buffer))
        };

        // Right now link identifies failure with dropped rx in router,
        // which is probably ok. We need this here to get id assigned by router
        let id = match notification {
            Notification::DeviceAck(Ack::ConnAck(id, ..)) => id,
            _message => return Err(LinkError::NotConnectionAck),
        };

        let tx = LinkTx::new(id, self.router_tx.clone(), self.incoming_data_buffer);
        let mut rx = LinkRx::new(id, self.router_tx, self.link_rx, self.outgoing_data_buffer);
        rx.cache = rest;
        Ok((tx, rx, notification))
    }
}

pub struct LinkTx {
    pub(crate) connection_id: ConnectionId,
    router_tx: Sender<(ConnectionId, Event)>,
    recv_buffer: Arc<Mutex<VecDeque<Packet>>>,
}

impl LinkTx {
    pub fn new(
        connection_id: ConnectionId,
        router_tx: Sender<(ConnectionId, Event)>,
        recv_buffer: Arc<Mutex<VecDeque<Packet>>>,
    ) -> LinkTx {
        LinkTx {
            connection_id,
            router_tx,
            recv_buffer,
        }
    }

    pub fn buffer(&self) -> MutexGuard<'_, RawMutex, VecDeque<Packet>> {
        self.recv_buffer.lock()
    }

    /// Send raw device data
    fn push(&mut self, data: Packet) -> Result<usize, LinkError> {
        let len = {
            let mut buffer = self.recv_buffer.lock();
            buffer.push_back(data);
            buffer.len()
        };

        self.router_tx
            .send((self.connection_id, Event::DeviceData))?;

        Ok(len)
    }

    /// Send raw device data
    pub async fn send(&mut self, data: Packet) -> Result<usize, LinkError> {
        let len = {
            let mut buffer = self.recv_buffer.lock();
            buffer.push_back(data);
            buffer.len()
        };

        self.router_tx
            .send((self.connection_id, Event::DeviceData))?;

        Ok(len)
    }

    fn try_push(&mut self, data: Packet) -> Result<usize, LinkError> {
        let len = {
            let mut buffer = self.recv_buffer.lock();
            buffer.push_back(data);
            buffer.len()
        };

        self.router_tx
            .try_send((self.connection_id, Event::DeviceData))?;
        Ok(len)
    }

    /// Sends a MQTT Publish to the router
    pub fn publish<S, V>(&mut self, topic: S, payload: V) -> Result<usize, LinkError>
    where
        S: Into<Bytes>,
        V: Into<Bytes>,
    {
        let publish = Publish {
            dup: false,
            qos: QoS::AtMostOnce,
            retain: false,
            topic: topic.into(),
            pkid: 0,
            payload: payload.into(),
            origin: None, // fbbus
        };

        let len = self.push(Packet::Publish(publish, None))?;
        Ok(len)
    }

    /// Sends a MQTT Publish to the router
    pub fn try_publish<S, V>(&mut self, topic: S, payload: V) -> Result<usize, LinkError>
    where
        S: Into<Bytes>,
        V: Into<Bytes>,
    {
        let publish = Publish {
            dup: false,
            qos: QoS::AtMostOnce,
            retain: false,
            topic: topic.into(),
            pkid: 0,
            payload: payload.into(),
            origin: None, // fbbus
        };

        let len = self.try_push(Packet::Publish(publish, None))?;
        // TODO: Remote item in buffer after failure and write unittest
        Ok(len)
    }

    /// Sends a MQTT Subscribe to the eventloop
    pub fn subscribe<S: Into<String>>(&mut self, filter: S) -> Result<usize, LinkError> {
        let filters = vec![Filter {
            path: filter.into(),
            qos: QoS::AtMostOnce,
            nolocal: false,
            preserve_retain: false,
            retain_forward_rule: RetainForwardRule::Never,
        }];

        let subscribe = Subscribe { pkid: 0, filters };

        let len = self.push(Packet::Subscribe(subscribe, None))?;
        Ok(len)
    }

    /// Sends a MQTT Subscribe to the eventloop
    pub fn try_subscribe<S: Into<String>>(&mut self, filter: S) -> Result<usize, LinkError> {
        let filters = vec![Filter {
            path: filter.into(),
            qos: QoS::AtMostOnce,
            nolocal: false,
            preserve_retain: false,
            retain_forward_rule: RetainForwardRule::Never,
        }];

        let subscribe = Subscribe { pkid: 0, filters };

        let len = self.try_push(Packet::Subscribe(subscribe, None))?;
        Ok(len)
    }

    /// Sends a MQTT Unsubscribe to the eventloop
    pub fn unsubscribe<S: Into<String>>(&mut self, filter: S) -> Result<usize, LinkError> {
        let unsubscribe = Unsubscribe {
            pkid: 0,
            filters: vec![filter.into()],
        };

        let len = self.push(Packet::Unsubscribe(unsubscribe, None))?;
        Ok(len)
    }

    /// Sends a MQTT Unsubscribe to the eventloop
    pub fn try_unsubscribe<S: Into<String>>(&mut self, filter: S) -> Result<usize, LinkError> {
        let unsubscribe = Unsubscribe {
            pkid: 0,
            filters: vec![filter.into()],
        };

        let len = self.try_push(Packet::Unsubscribe(unsubscribe, None))?;
        Ok(len)
    }

    /// Request to get device shadow
    pub fn shadow<S: Into<String>>(&mut self, filter: S) -> Result<(), LinkError> {
        let message = Event::Shadow(ShadowRequest {
            filter: filter.into(),
        });

        self.router_tx.try_send((self.connection_id, message))?;
        Ok(())
    }
}

#[derive(Debug)]
pub struct LinkRx {
    connection_id: ConnectionId,
    router_tx: Sender<(ConnectionId, Event)>,
    router_rx: WakeRx,
    send_buffer: Arc<Mutex<VecDeque<Notification>>>,
    cache: VecDeque<Notification>,
}

impl LinkRx {
    pub(crate) fn new(
        connection_id: ConnectionId,
        router_tx: Sender<(ConnectionId, Event)>,
        router_rx: WakeRx,
        outgoing_data_buffer: Arc<Mutex<VecDeque<Notification>>>,
    ) -> LinkRx {
        LinkRx {
            connection_id,
            router_tx,
            router_rx,
            send_buffer: outgoing_data_buffer,
            // fbbus: unallocated while idle, see `refill`.
            cache: VecDeque::new(),
        }
    }

    pub fn id(&self) -> ConnectionId {
        self.connection_id
    }

    /// fbbus: a handle that wakes this link from outside the router ([`Nudge`]).
    pub fn nudge(&self) -> Nudge {
        self.router_rx.nudge()
    }

    /// fbbus: whether a [`Nudge`] woke this link since it last looked (taken: asked again,
    /// false until the next nudge).
    pub fn nudged(&self) -> bool {
        self.router_rx.take_nudge()
    }

    /// Collects 'all' the notifications the router buffered (one router trigger signifies
    /// a bunch of them). fbbus: takes the router's buffer instead of swapping in the empty
    /// cache, so neither side keeps a batch-sized allocation while the connection is idle
    /// (upstream preallocated 100 notifications per link and the swap kept both buffers).
    fn refill(&mut self) {
        self.cache = mem::take(&mut *self.send_buffer.lock());
    }

    pub fn recv(&mut self) -> Result<Option<Notification>, LinkError> {
        // Read from cache first
        // One router_rx trigger signifies a bunch of notifications. So we
        // should always check cache first
        match self.cache.pop_front() {
            Some(v) => Ok(Some(v)),
            None => {
                // If cache is empty, check for router trigger and get fresh notifications
                self.router_rx.recv()?;
                // Collect 'all' the data in the buffer after a notification.
                // Notification means fresh data which isn't previously collected
                self.refill();
                Ok(self.cache.pop_front())
            }
        }
    }

    pub fn recv_deadline(&mut self, deadline: Instant) -> Result<Option<Notification>, LinkError> {
        // Read from cache first
        // One router_rx trigger signifies a bunch of notifications. So we
        // should always check cache first
        match self.cache.pop_front() {
            Some(v) => Ok(Some(v)),
            None => {
                // If cache is empty, check for router trigger and get fresh notifications
                self.router_rx.recv_deadline(deadline)?;
                self.refill();
                Ok(self.cache.pop_front())
            }
        }
    }

    /// fbbus: waits until the router sent something, without taking it: the next `recv*`
    /// or `next` returns it. A caller waiting on several things (a socket, the router)
    /// then holds no notification, and no allocation, while it waits.
    pub async fn wait(&mut self) -> Result<(), LinkError> {
        if self.cache.is_empty() {
            self.cache = VecDeque::new();
            self.router_rx.recv_async().await?;
            self.refill();
        }
        Ok(())
    }

    pub async fn next(&mut self) -> Result<Option<Notification>, LinkError> {
        // Read from cache first
        // One router_rx trigger signifies a bunch of notifications. So we
        // should always check cache first
        match self.cache.pop_front() {
            Some(v) => Ok(Some(v)),
            None => {
                // fbbus: hold no allocation while waiting.
                self.cache = VecDeque::new();
                // If cache is empty, check for router trigger and get fresh notifications
                self.router_rx.recv_async().await?;
                // Collect 'all' the data in the buffer after a notification.
                // Notification means fresh data which isn't previously collected
                self.refill();
                Ok(self.cache.pop_front())
            }
        }
    }

    pub fn ready(&self) -> Result<(), LinkError> {
        self.router_tx.send((self.connection_id, Event::Ready))?;
        Ok(())
    }

    pub async fn wake(&self) -> Result<(), LinkError> {
        self.router_tx
            .send_async((self.connection_id, Event::Ready))
            .await?;

        Ok(())
    }
}

#[cfg(test)]
mod test {
    use super::LinkTx;
    use flume::bounded;
    use parking_lot::Mutex;
    use std::{collections::VecDeque, sync::Arc, thread};

    #[test]
    fn push_sends_all_data_and_notifications_to_router() {
        let (router_tx, router_rx) = bounded(10);
        let mut buffers = Vec::new();
        const CONNECTIONS: usize = 1000;
        const MESSAGES_PER_CONNECTION: usize = 100;

        for i in 0..CONNECTIONS {
            let buffer = Arc::new(Mutex::new(VecDeque::new()));
            let mut link_tx = LinkTx::new(i, router_tx.clone(), buffer.clone());
            buffers.push(buffer);
            thread::spawn(move || {
                for _ in 0..MESSAGES_PER_CONNECTION {
                    link_tx.publish("hello/world", vec![1, 2, 3]).unwrap();
                }
            });
        }

        // Router should receive notifications from all the connections
        for _ in 0..CONNECTIONS * MESSAGES_PER_CONNECTION {
            let _v = router_rx.recv().unwrap();
        }

        // Every connection has expected number of messages
        for item in buffers.iter().take(CONNECTIONS) {
            assert_eq!(item.lock().len(), MESSAGES_PER_CONNECTION);
        }

        // TODO: Write a similar test to benchmark buffer vs channels
    }

    /// fbbus: a resumed session's ConnAck and what the router buffered with it (its
    /// PubRels, what its subscriptions kept) can be announced by one wake-up, since
    /// wake-ups coalesce: the link that takes the ConnAck keeps the rest and reads it
    /// without another wake-up. (A broker suite lost a resumed session's deliveries in 3
    /// runs of 5 when the rest stayed in the router's buffer.)
    #[test]
    fn what_the_router_buffered_with_the_connack_is_read_without_another_wake_up() {
        use super::PendingLink;
        use crate::protocol::{ConnAck, ConnectReturnCode};
        use crate::router::{wakeup::wakeup, Ack, Notification};
        let (router_tx, _router_rx) = bounded(10);
        let (wake_tx, link_rx) = wakeup();
        let outgoing = Arc::new(Mutex::new(VecDeque::new()));
        let connack = ConnAck {
            session_present: true,
            code: ConnectReturnCode::Success,
        };
        outgoing.lock().extend([
            Notification::DeviceAck(Ack::ConnAck(7, connack, None)),
            Notification::Unschedule,
        ]);
        wake_tx.wake();
        let pending = PendingLink {
            router_tx,
            link_rx,
            outgoing_data_buffer: outgoing,
            incoming_data_buffer: Arc::new(Mutex::new(VecDeque::new())),
        };
        pending.link_rx.recv().unwrap();
        let (_tx, mut rx, ack) = pending.finish().unwrap();
        assert!(matches!(ack, Notification::DeviceAck(Ack::ConnAck(7, ..))));
        let now = std::time::Instant::now();
        assert!(matches!(
            rx.recv_deadline(now),
            Ok(Some(Notification::Unschedule))
        ));
    }

    /// fbbus: links that do not wait for the router (`LinkBuilder::build_linked`), against
    /// a running router.
    mod linked {
        use super::super::{LinkBuilder, LinkError};
        use crate::protocol::{Disconnect, DisconnectReasonCode, Packet};
        use crate::router::{Ack, Notification};
        use crate::{Router, RouterConfig};
        use std::time::{Duration, Instant};

        const MAX: usize = 4;

        fn router() -> (
            flume::Sender<(crate::ConnectionId, crate::router::Event)>,
            crate::ConnectionIds,
        ) {
            let router = Router::new(
                0,
                RouterConfig {
                    max_connections: MAX,
                    max_outgoing_packet_count: 200,
                    max_segment_size: 10 * 1024,
                    max_segment_count: 10,
                    ..Default::default()
                },
            );
            let ids = router.connection_ids();
            (router.spawn(), ids)
        }

        async fn next(rx: &mut super::super::LinkRx) -> Notification {
            let wait = tokio::time::timeout(Duration::from_secs(5), rx.next());
            wait.await
                .expect("a notification within 5 s")
                .unwrap()
                .unwrap()
        }

        /// What a clean link sends right after connecting is the router's to handle after
        /// its Connect, and the router sends it no ConnAck of its own: the first thing the
        /// subscriber hears is its SubAck, then the publication.
        #[tokio::test]
        async fn a_clean_link_is_used_at_once_and_gets_no_second_connack() {
            let (tx, ids) = router();
            let (mut sub_tx, mut sub_rx, ack) = LinkBuilder::new("sub", tx.clone(), ids.clone())
                .build_linked()
                .await
                .unwrap();
            assert!(matches!(
                ack,
                Notification::DeviceAck(Ack::ConnAck(_, ref connack, _)) if !connack.session_present
            ));
            sub_tx.subscribe("t/#").unwrap();
            assert!(matches!(
                next(&mut sub_rx).await,
                Notification::DeviceAck(Ack::SubAck(_))
            ));
            let (mut pub_tx, _pub_rx, _) = LinkBuilder::new("pub", tx.clone(), ids.clone())
                .build_linked()
                .await
                .unwrap();
            pub_tx.publish("t/1", vec![1]).unwrap();
            match next(&mut sub_rx).await {
                Notification::Forward(forward) => assert_eq!(&forward.publish.topic[..], b"t/1"),
                other => panic!("expected the publication, got {other:?}"),
            }
        }

        /// Ids are bounded by the router's `max_connections` at the link, and come back
        /// when the router has removed a connection: connecting and leaving many times
        /// more than `MAX` never runs out.
        #[tokio::test]
        async fn ids_run_out_at_max_connections_and_come_back_when_connections_leave() {
            let (tx, ids) = router();
            let mut links = Vec::new();
            for i in 0..MAX {
                let link = LinkBuilder::new(&format!("c{i}"), tx.clone(), ids.clone())
                    .build_linked()
                    .await
                    .unwrap();
                links.push(link);
            }
            let full = LinkBuilder::new("one-more", tx.clone(), ids.clone()).build_linked();
            assert!(matches!(full.await, Err(LinkError::NoSpace)));
            for round in 0..10 * MAX {
                let (mut link_tx, _, _) = links.remove(0);
                let disconnect = Disconnect {
                    reason_code: DisconnectReasonCode::NormalDisconnection,
                };
                link_tx
                    .send(Packet::Disconnect(disconnect, None))
                    .await
                    .unwrap();
                // The id comes back once the router has handled the Disconnect.
                let deadline = Instant::now() + Duration::from_secs(5);
                let link = loop {
                    let client_id = format!("r{round}");
                    match LinkBuilder::new(&client_id, tx.clone(), ids.clone())
                        .build_linked()
                        .await
                    {
                        Ok(link) => break link,
                        Err(LinkError::NoSpace) if Instant::now() < deadline => {
                            tokio::time::sleep(Duration::from_millis(1)).await
                        }
                        Err(e) => panic!("round {round}: {e}"),
                    }
                };
                links.push(link);
            }
        }

        /// A client id the router would drop without a word is refused at the link, and
        /// takes no id.
        #[tokio::test]
        async fn a_client_id_the_router_refuses_is_refused_at_the_link() {
            let (tx, ids) = router();
            for client_id in ["a/b", "a+", "#", "$sys"] {
                let refused = LinkBuilder::new(client_id, tx.clone(), ids.clone()).build_linked();
                assert!(matches!(refused.await, Err(LinkError::InvalidClientId(_))));
            }
            for i in 0..MAX {
                let client_id = format!("c{i}");
                let linked = LinkBuilder::new(&client_id, tx.clone(), ids.clone()).build_linked();
                assert!(linked.await.is_ok(), "all {MAX} ids still free");
            }
        }
    }
}
