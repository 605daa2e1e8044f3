//! The connection task: drives rumqttc's event loop, reconnects, re-declares, and routes
//! what arrives to the device's publishers, subscribers and watchers.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use rumqttc::{
    AsyncClient, Event, EventLoop, Incoming, Outgoing, Publish, QoS, SubscribeFilter,
    SubscribeReasonCode,
};
use tokio::sync::{broadcast, mpsc, oneshot, watch};

use super::acks::Acks;
use super::{ClientError, Diagnostic};
use crate::topic;

/// Pause between reconnection attempts.
pub(super) const RECONNECT_DELAY: Duration = Duration::from_millis(500);

/// After DISCONNECT, how long to wait for the broker to close the connection.
const DISCONNECT_LINGER: Duration = Duration::from_secs(1);

/// How many diag messages [`Shared::recent_diagnostics`] keeps.
const RECENT_DIAGNOSTICS: usize = 32;

/// Longest time the connection waits for room in a full subscriber queue (`deliver`).
const READER_WAIT: Duration = Duration::from_millis(500);

/// How long the connection may wait for a reader with this keep-alive: at most a quarter
/// of it, so the PINGREQs the waiting delays still reach the broker in time.
pub(super) fn reader_wait(keep_alive: Duration) -> Duration {
    if keep_alive.is_zero() {
        READER_WAIT
    } else {
        READER_WAIT.min(keep_alive / 4)
    }
}

/// Where messages on one subscribed topic go.
pub(super) enum Sink {
    /// A subscriber's (or a waiting INIT's) queue. When it is full the connection waits
    /// for room, see `deliver`.
    Queue(mpsc::Sender<Publish>),
    /// A decimal count (`fbbus/lines/<line>/online`), watched: receivers are notified
    /// of the first value and of every change (the broker repeats unchanged counts).
    Count { tx: watch::Sender<u64>, first: bool },
}

/// What the device handle, its publishers and subscribers share with the task.
pub(super) struct Shared {
    pub(super) id: String,
    pub(super) client: AsyncClient,
    /// The bound on every wait.
    pub(super) timeout: Duration,
    /// The longest wait for a reader's room ([`reader_wait`]).
    reader_wait: Duration,
    /// The interface as JSON, published again after every connect.
    declaration: Vec<u8>,
    diag_topic: String,
    state: Mutex<State>,
    /// INITO: (QO, STATUS).
    pub(super) status: watch::Sender<(bool, String)>,
    pub(super) diagnostics: broadcast::Sender<Diagnostic>,
    /// Set by `Device::disconnect`: the task ends instead of reconnecting.
    pub(super) closing: AtomicBool,
}

#[derive(Default)]
struct State {
    acks: Acks,
    routes: HashMap<String, Vec<(u64, Sink)>>,
    /// Queues whose reader did not make room within `reader_wait`: their messages are
    /// dropped, without waiting, until they have room again; with the count dropped.
    stalled: HashMap<u64, u64>,
    next_sink: u64,
    recent: VecDeque<Diagnostic>,
    session: u64,
    line: String,
    /// The task has ended: nothing will be sent or received any more.
    closed: bool,
}

impl Shared {
    pub(super) fn new(
        id: String,
        client: AsyncClient,
        timeout: Duration,
        reader_wait: Duration,
        declaration: Vec<u8>,
    ) -> Shared {
        Shared {
            diag_topic: topic::diag(&id),
            id,
            client,
            timeout,
            reader_wait,
            declaration,
            state: Mutex::default(),
            status: watch::Sender::new((false, "connecting".to_owned())),
            diagnostics: broadcast::Sender::new(64),
            closing: AtomicBool::new(false),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    pub(super) fn session_and_line(&self) -> (u64, String) {
        let state = self.lock();
        (state.session, state.line.clone())
    }

    pub(super) fn recent_diagnostics(&self) -> Vec<Diagnostic> {
        self.lock().recent.iter().cloned().collect()
    }

    // ------------------------------------------------------------------ requests

    /// Hands a QoS 1 publish to rumqttc; the receiver resolves on its PUBACK.
    pub(super) fn publish(
        &self,
        topic: &str,
        payload: Vec<u8>,
    ) -> Result<oneshot::Receiver<()>, ClientError> {
        let mut state = self.lock();
        if state.closed {
            return Err(ClientError::Closed);
        }
        let ack = state.acks.publishes.queue();
        if self
            .client
            .try_publish(topic, QoS::AtLeastOnce, false, payload)
            .is_err()
        {
            state.acks.publishes.unqueue();
            return Err(ClientError::Busy);
        }
        Ok(ack)
    }

    /// Hands a subscribe (QoS 1, every topic) to rumqttc; the receiver gets the SUBACK.
    fn subscribe(
        &self,
        topics: Vec<String>,
    ) -> Result<oneshot::Receiver<Vec<SubscribeReasonCode>>, ClientError> {
        let mut state = self.lock();
        if state.closed {
            return Err(ClientError::Closed);
        }
        let ack = state.acks.subscribes.queue();
        let filters = topics
            .into_iter()
            .map(|t| SubscribeFilter::new(t, QoS::AtLeastOnce));
        if self.client.try_subscribe_many(filters).is_err() {
            state.acks.subscribes.unqueue();
            return Err(ClientError::Busy);
        }
        Ok(ack)
    }

    /// Waits (bounded) for an acknowledgement.
    pub(super) async fn wait<T>(
        &self,
        ack: oneshot::Receiver<T>,
        what: &'static str,
    ) -> Result<T, ClientError> {
        match tokio::time::timeout(self.timeout, ack).await {
            Ok(Ok(value)) => Ok(value),
            // The waiter was dropped: the connection was lost or the device closed.
            Ok(Err(_)) if self.lock().closed => Err(ClientError::Closed),
            Ok(Err(_)) => Err(ClientError::ConnectionLost),
            Err(_) => Err(ClientError::Timeout {
                waited: self.timeout,
                what,
            }),
        }
    }

    /// Subscribes to one topic and waits for the broker to grant it.
    pub(super) async fn subscribe_confirmed(&self, topic: &str) -> Result<(), ClientError> {
        let ack = self.subscribe(vec![topic.to_owned()])?;
        let codes = self.wait(ack, "SUBACK").await?;
        if codes.contains(&SubscribeReasonCode::Failure) {
            return Err(ClientError::SubscribeRefused(topic.to_owned()));
        }
        Ok(())
    }

    // ------------------------------------------------------------------ routes

    /// Routes messages on `topic` (an exact topic, no wildcards) to `sink`. The caller
    /// subscribes; the returned guard removes the route again.
    pub(super) fn add_route(self: &Arc<Self>, topic: &str, sink: Sink) -> Route {
        let mut state = self.lock();
        state.next_sink += 1;
        let id = state.next_sink;
        state
            .routes
            .entry(topic.to_owned())
            .or_default()
            .push((id, sink));
        Route {
            shared: self.clone(),
            topic: topic.to_owned(),
            id,
            kept: false,
        }
    }

    /// Removes one route; unsubscribes when it was the topic's last.
    fn remove_route(&self, topic: &str, id: u64) {
        let mut state = self.lock();
        state.stalled.remove(&id);
        let Some(sinks) = state.routes.get_mut(topic) else {
            return;
        };
        sinks.retain(|(sink, _)| *sink != id);
        if sinks.is_empty() {
            state.routes.remove(topic);
            if !state.closed {
                let _ = self.client.try_unsubscribe(topic);
            }
        }
    }

    // ------------------------------------------------------------------ events

    /// A connection was established (first or again): subscribe to the diag topic and
    /// everything routed (the session is clean), and once the broker has granted that,
    /// declare. Declaring earlier can lose the answer: the broker may route it before
    /// the subscription is in place. `first` (on the first connection) learns whether the
    /// diag topic may be read.
    fn connected(self: &Arc<Self>, first: Option<oneshot::Sender<Result<(), ClientError>>>) {
        self.status.send_replace((false, "declaring".to_owned()));
        let topics: Vec<String> = {
            let state = self.lock();
            std::iter::once(self.diag_topic.clone())
                .chain(state.routes.keys().cloned())
                .collect()
        };
        let subscribed = self.subscribe(topics.clone());
        let shared = self.clone();
        tokio::spawn(async move {
            let granted = match subscribed {
                Ok(ack) => shared.wait(ack, "SUBACK").await,
                Err(e) => Err(e),
            };
            let readable = match granted {
                Ok(codes) => {
                    let refused: Vec<&String> = topics
                        .iter()
                        .zip(&codes)
                        .filter(|(_, code)| **code == SubscribeReasonCode::Failure)
                        .map(|(topic, _)| topic)
                        .collect();
                    if !refused.is_empty() {
                        tracing::warn!(
                            device = shared.id,
                            ?refused,
                            "subscriptions refused by the broker"
                        );
                    }
                    match refused.first() {
                        Some(topic) if **topic == shared.diag_topic => {
                            Err(ClientError::SubscribeRefused(shared.diag_topic.clone()))
                        }
                        _ => Ok(()),
                    }
                }
                // Declare anyway: the answer may still arrive.
                Err(ClientError::Timeout { .. }) => Ok(()),
                // The connection is gone; the next one starts over.
                Err(_) => return,
            };
            if let Err(e) = &readable {
                shared.status.send_replace((false, e.to_string()));
            }
            if let Some(first) = first {
                let _ = first.send(readable);
            }
            if let Err(e) = shared.publish(&topic::declare(&shared.id), shared.declaration.clone())
            {
                tracing::warn!(device = shared.id, error = %e, "could not declare after connecting");
            }
        });
    }

    fn connection_lost(&self, error: &rumqttc::ConnectionError) {
        tracing::warn!(device = self.id, %error, "connection lost; reconnecting");
        self.lock().acks.subscribes.connection_lost();
        self.status
            .send_replace((false, format!("reconnecting: {error}")));
    }

    /// Hands a message to every sink of its topic.
    ///
    /// A subscriber whose queue is full holds the connection until it has room, for at
    /// most `reader_wait`: meanwhile rumqttc does not read the socket, so TCP slows the
    /// broker's delivery down, and the broker holds the publishers back in turn
    /// (`slow_subscriber_hold_ms`). A subscriber that reads, only slower than a burst comes
    /// in, thus gets every message. One that made no room within `reader_wait` is stalled:
    /// its messages are dropped without waiting (counted, warned about once) until its
    /// queue has room again, so one forgotten subscriber does not hold up the device's
    /// other subscribers, its CNFs and its keep-alive for good.
    async fn deliver(&self, publish: Publish) {
        if publish.topic == self.diag_topic {
            return self.diagnose(Diagnostic::parse(&publish.payload));
        }
        let queues = self.route(&publish);
        for (sink, queue, stalled) in queues {
            let waited = match queue.try_send(publish.clone()) {
                Ok(()) => Ok(()),
                Err(mpsc::error::TrySendError::Closed(_)) => continue, // removed next time
                Err(mpsc::error::TrySendError::Full(_)) if stalled => Err(()),
                Err(mpsc::error::TrySendError::Full(publish)) => {
                    match tokio::time::timeout(self.reader_wait, queue.send(publish)).await {
                        Ok(Ok(())) => Ok(()),
                        Ok(Err(_)) => continue,
                        Err(_) => Err(()),
                    }
                }
            };
            match waited {
                Ok(()) if !stalled => {}
                Ok(()) => {
                    let dropped = self.lock().stalled.remove(&sink).unwrap_or(0);
                    tracing::warn!(
                        device = self.id,
                        topic = publish.topic,
                        dropped,
                        "subscriber reads again; messages dropped while it was stalled"
                    );
                }
                Err(()) => {
                    let mut state = self.lock();
                    let dropped = state.stalled.entry(sink).or_insert(0);
                    if *dropped == 0 {
                        tracing::warn!(
                            device = self.id,
                            topic = publish.topic,
                            waited_ms = self.reader_wait.as_millis() as u64,
                            "subscriber queue full and not read: its messages are dropped \
                             until it reads again"
                        );
                    }
                    *dropped += 1;
                }
            }
        }
    }

    /// The queues a message on this topic goes to (sink id, queue, stalled), after the
    /// watched counts among its sinks have taken it and closed sinks are removed.
    fn route(&self, publish: &Publish) -> Vec<(u64, mpsc::Sender<Publish>, bool)> {
        let mut state = self.lock();
        let State {
            routes, stalled, ..
        } = &mut *state;
        let Some(sinks) = routes.get_mut(&publish.topic) else {
            return Vec::new(); // unsubscribed meanwhile
        };
        let mut queues = Vec::new();
        sinks.retain_mut(|(id, sink)| match sink {
            Sink::Queue(tx) => {
                let open = !tx.is_closed();
                if open {
                    queues.push((*id, tx.clone(), stalled.contains_key(id)));
                } else {
                    stalled.remove(id);
                }
                open
            }
            Sink::Count { tx, first } => {
                match std::str::from_utf8(&publish.payload)
                    .ok()
                    .and_then(|s| s.trim().parse::<u64>().ok())
                {
                    Some(count) => {
                        let notify = std::mem::take(first);
                        tx.send_if_modified(|seen| {
                            let changed = *seen != count;
                            *seen = count;
                            changed || notify
                        });
                    }
                    None => tracing::warn!(topic = publish.topic, "not a decimal count: ignored"),
                }
                !tx.is_closed()
            }
        });
        if sinks.is_empty() {
            routes.remove(&publish.topic);
            let _ = self.client.try_unsubscribe(&publish.topic);
        }
        queues
    }

    fn diagnose(&self, diagnostic: Diagnostic) {
        let mut state = self.lock();
        match &diagnostic {
            Diagnostic::Declared { session, line } => {
                state.session = *session;
                state.line = line.clone();
                self.status.send_replace((true, "OK".to_owned()));
            }
            Diagnostic::DeclarationRefused { errors } => {
                tracing::warn!(device = self.id, ?errors, "declaration refused");
                self.status
                    .send_replace((false, format!("declaration refused: {}", errors.join("; "))));
            }
            Diagnostic::Rejected { topic, detail, .. } => {
                tracing::warn!(
                    device = self.id,
                    topic,
                    detail,
                    "publication refused by the broker"
                );
            }
            Diagnostic::Other(_) => {}
        }
        if state.recent.len() == RECENT_DIAGNOSTICS {
            state.recent.pop_front();
        }
        state.recent.push_back(diagnostic.clone());
        let _ = self.diagnostics.send(diagnostic);
    }

    /// The task ended (returned or aborted): every waiter and subscriber learns it.
    fn close(&self) {
        let mut state = self.lock();
        state.closed = true;
        state.acks = Acks::default();
        state.routes.clear();
        let status = if self.closing.load(Ordering::Relaxed) {
            "disconnected"
        } else {
            "closed"
        };
        self.status.send_replace((false, status.to_owned()));
    }
}

/// A route from a topic to a sink; removed (and unsubscribed if it was the last) on drop
/// unless kept.
pub(super) struct Route {
    shared: Arc<Shared>,
    topic: String,
    id: u64,
    kept: bool,
}

impl Route {
    /// Leaves the route in place for good: the connection task removes it once its sink
    /// is closed (used for watches, which have no owner to drop a route).
    pub(super) fn keep(mut self) {
        self.kept = true;
    }
}

impl Drop for Route {
    fn drop(&mut self) {
        if !self.kept {
            self.shared.remove_route(&self.topic, self.id);
        }
    }
}

/// Marks the shared state closed however the task ends, including by abort.
struct CloseOnDrop(Arc<Shared>);

impl Drop for CloseOnDrop {
    fn drop(&mut self) {
        self.0.close();
    }
}

/// The connection task. `first` learns whether the first connection attempt failed (or
/// the broker refused the diag subscription); after one connection, failures are retried
/// every [`RECONNECT_DELAY`] until the device disconnects or is dropped.
pub(super) async fn run(
    mut eventloop: EventLoop,
    shared: Arc<Shared>,
    first: oneshot::Sender<Result<(), ClientError>>,
) {
    let _close = CloseOnDrop(shared.clone());
    let mut first = Some(first);
    loop {
        let event = match eventloop.poll().await {
            Ok(event) => event,
            Err(error) => {
                if shared.closing.load(Ordering::Relaxed) {
                    return;
                }
                if let Some(first) = first.take() {
                    let _ = first.send(Err(ClientError::Connect(error.to_string())));
                    return;
                }
                shared.connection_lost(&error);
                tokio::time::sleep(RECONNECT_DELAY).await;
                continue;
            }
        };
        match event {
            Event::Incoming(Incoming::ConnAck(_)) => {
                let first = first.take();
                if !shared.closing.load(Ordering::Relaxed) {
                    shared.connected(first);
                }
            }
            Event::Incoming(Incoming::Publish(publish)) => shared.deliver(publish).await,
            Event::Incoming(Incoming::PubAck(ack)) => {
                shared.lock().acks.publishes.acked(ack.pkid, ())
            }
            Event::Incoming(Incoming::SubAck(ack)) => shared
                .lock()
                .acks
                .subscribes
                .acked(ack.pkid, ack.return_codes),
            Event::Outgoing(Outgoing::Publish(pkid)) => shared.lock().acks.publishes.written(pkid),
            Event::Outgoing(Outgoing::AwaitAck(pkid)) => {
                shared.lock().acks.publishes.collided(pkid)
            }
            Event::Outgoing(Outgoing::Subscribe(pkid)) => {
                shared.lock().acks.subscribes.written(pkid)
            }
            // INIT-: the DISCONNECT is written. Closing the socket with unread messages in
            // its buffer would reset the connection, and the broker could lose the
            // DISCONNECT and publish the will: read on until the broker closes it.
            Event::Outgoing(Outgoing::Disconnect) => {
                let _ = tokio::time::timeout(DISCONNECT_LINGER, async {
                    while eventloop.poll().await.is_ok() {}
                })
                .await;
                return;
            }
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_wait_for_a_reader_leaves_room_for_the_keep_alive() {
        assert_eq!(reader_wait(Duration::ZERO), READER_WAIT);
        assert_eq!(reader_wait(Duration::from_secs(5)), READER_WAIT);
        assert_eq!(
            reader_wait(Duration::from_secs(1)),
            Duration::from_millis(250)
        );
    }
}
