use super::Ack;
use bytes::Bytes;
use slab::Slab;
use tracing::{info, trace, warn};

use crate::protocol::{
    matches, ConnAck, ConnAckProperties, PingResp, PubAck, PubComp, PubRec, PubRel, Publish,
    PublishProperties, SubAck, UnsubAck,
};
use crate::router::iobufs::shrink_if_empty;
// fbbus: the retained store's bounds.
use crate::router::retained::{self, RetainLimit, RetainedStats};
use crate::router::{DataRequest, FilterIdx, Waiters};
use crate::{ConnectionId, Filter, Offset, RouterConfig, Topic};

use crate::segments::{CommitLog, Position};
use crate::Storage;
use std::collections::{HashMap, HashSet, VecDeque};
use std::io;
use std::sync::Arc;
use std::time::Instant;

type PubWithProp = (Publish, Option<Box<PublishProperties>>);

/// fbbus: the invariant behind the lookups of `native` that cannot fail: `filter_indexes`
/// and the read requests name only logs in `native`; a log is removed only with its index
/// entry and once nothing refers to it (`DataLog::remove_unused`).
const INDEXED_LOGS_EXIST: &str =
    "invariant: a filter index in `filter_indexes` or a read request names a log";

/// fbbus: at most this many topics are kept in `DataLog::publish_filters`, the cache of
/// which filters each published topic matches; at the limit the cache starts over. Each
/// distinct topic published while any filter matched it kept an entry for the life of the
/// router (a topic and its list, ~150 bytes): with random topics, memory without bound.
/// A line of ~1,000 devices publishes a few thousand distinct topics; 16,384 entries are
/// ~2.5 MB. Emptying it costs a filter scan per topic on its next publish.
const MAX_CACHED_TOPICS: usize = 16_384;

#[derive(Clone)]
pub struct PublishData {
    pub publish: Publish,
    pub properties: Option<Box<PublishProperties>>,
    pub timestamp: Instant,
}

impl From<PubWithProp> for PublishData {
    fn from((publish, properties): PubWithProp) -> Self {
        PublishData {
            publish,
            properties,
            timestamp: Instant::now(),
        }
    }
}

// TODO: remove this from here
impl Storage for PublishData {
    // TODO: calculate size of publish properties as well!
    fn size(&self) -> usize {
        let publish = &self.publish;
        4 + publish.topic.len() + publish.payload.len()
    }
}

/// Stores 'device' data and 'actions' data in native commitlog
/// organized by subscription filter. Device data is replicated
/// while actions data is not
pub struct DataLog {
    pub config: RouterConfig,
    /// Native commitlog data organized by subscription. Contains
    /// device data and actions data logs.
    ///
    /// Device data is replicated while actions data is not.
    /// Also has waiters used to wake connections/replicator tracker
    /// which are caught up with all the data on 'Filter' and waiting
    /// for new data
    pub native: Slab<Data<PublishData>>,
    /// Map of subscription filter name to filter index
    filter_indexes: HashMap<Filter, FilterIdx>,
    retained_publishes: HashMap<Topic, PublishData>,
    /// fbbus: the counted retained messages and their bytes (`retained`), and where the
    /// embedder reads them.
    retained_counted: usize,
    retained_bytes: usize,
    retained_stats: Arc<RetainedStats>,
    /// List of filters associated with a topic
    publish_filters: HashMap<Topic, Vec<FilterIdx>>,
}

impl DataLog {
    pub fn new(config: RouterConfig) -> io::Result<DataLog> {
        let mut native = Slab::new();
        let mut filter_indexes = HashMap::new();
        let retained_publishes = HashMap::new();
        let publish_filters = HashMap::new();

        if let Some(warmup_filters) = config.initialized_filters.clone() {
            for filter in warmup_filters {
                let data = Data::new(&filter, &config);

                // Add commitlog to datalog and add datalog index to filter to
                // datalog index map
                let idx = native.insert(data);
                filter_indexes.insert(filter, idx);
            }
        }

        Ok(DataLog {
            config,
            native,
            publish_filters,
            filter_indexes,
            retained_publishes,
            retained_counted: 0,
            retained_bytes: 0,
            retained_stats: Arc::default(),
        })
    }

    /// The request of connection `id` for `subscription` parked in the log of `filter`.
    /// fbbus: matched by subscription too: a shared subscription `$share/g/f` parks its
    /// request in the log of `f`, next to the connection's own subscription of `f` if it has
    /// one (upstream took the connection's first request in the log, whichever it was).
    pub fn remove_waiters_for_id(
        &mut self,
        id: ConnectionId,
        filter: &str,
        subscription: &str,
    ) -> Option<DataRequest> {
        let data = self
            .native
            .get_mut(*self.filter_indexes.get(filter)?)
            .expect(INDEXED_LOGS_EXIST);
        let waiters = data.waiters.get_mut();

        waiters
            .iter()
            .position(|(conn_id, request)| *conn_id == id && request.filter == subscription)
            .and_then(|index| {
                waiters
                    .swap_remove_back(index)
                    .map(|(_, data_req)| data_req)
            })
    }

    // TODO: Currently returning a Option<Vec> instead of Option<&Vec> due to Rust borrow checker
    // limitation
    pub fn matches(&mut self, topic: &str) -> Option<Vec<usize>> {
        match &self.publish_filters.get(topic) {
            Some(v) => Some(v.to_vec()),
            None => {
                let hidden = &self.config.wildcard_hidden_prefixes;
                let v: Vec<usize> = self
                    .filter_indexes
                    .iter()
                    .filter(|(filter, _)| routes(hidden, topic, filter))
                    .map(|(_, filter_idx)| *filter_idx)
                    .collect();

                if !v.is_empty() {
                    // fbbus: bounded, see `MAX_CACHED_TOPICS`.
                    if self.publish_filters.len() >= MAX_CACHED_TOPICS {
                        self.publish_filters = HashMap::new();
                    }
                    self.publish_filters.insert(topic.to_owned(), v.clone());
                }

                Some(v)
            }
        }
    }

    /// fbbus: the filters `topic` is appended to whose next append drops messages
    /// (`CommitLog::drop_boundary`), with that boundary. Empty, and no allocation, in the
    /// common case; the filters are not copied (`matches` copies them).
    pub fn drop_boundaries(&mut self, topic: &str) -> Vec<(FilterIdx, u64)> {
        if !self.publish_filters.contains_key(topic) {
            self.matches(topic);
        }
        let Some(filters) = self.publish_filters.get(topic) else {
            return Vec::new();
        };
        filters
            .iter()
            .filter_map(|&idx| Some((idx, self.native.get(idx)?.log.drop_boundary()?)))
            .collect()
    }

    pub fn next_native_offset(&mut self, filter: &str) -> (FilterIdx, Offset) {
        let publish_filters = &mut self.publish_filters;
        let filter_indexes = &mut self.filter_indexes;

        let (filter_idx, data) = match filter_indexes.get(filter) {
            Some(idx) => (*idx, self.native.get(*idx).expect(INDEXED_LOGS_EXIST)),
            None => {
                let data = Data::new(filter, &self.config);

                // Add commitlog to datalog and add datalog index to filter to
                // datalog index map
                let idx = self.native.insert(data);
                self.filter_indexes.insert(filter.to_owned(), idx);

                // Match new filter to existing topics and add to publish_filters if it matches
                let hidden = &self.config.wildcard_hidden_prefixes;
                for (topic, filters) in publish_filters.iter_mut() {
                    if routes(hidden, topic, filter) {
                        filters.push(idx);
                    }
                }

                (
                    idx,
                    self.native.get(idx).expect("invariant: inserted just now"),
                )
            }
        };

        (filter_idx, data.log.next_offset())
    }

    pub fn native_readv(
        &self,
        filter_idx: FilterIdx,
        offset: Offset,
        len: u64,
    ) -> io::Result<(Position, Vec<(PubWithProp, Offset)>)> {
        // unwrap to get index of `self.native` is fine here, because when a new subscribe packet
        // arrives in `Router::handle_device_payload`, it first calls the function
        // `next_native_offset` which creates a new commitlog if one doesn't exist. So any new
        // reads will definitely happen on a valid filter.
        let data = self.native.get(filter_idx).expect(INDEXED_LOGS_EXIST);
        let mut o = Vec::new();
        // TODO: `readv` is infallible but its current return type does not
        // reflect that. Consequently, this method is also infallible.
        // Encoding this information is important so that calling function
        // has more information on how this method behaves.
        let next = data.log.readv(offset, len, &mut o)?;

        let now = Instant::now();
        o.retain_mut(|(pubdata, _)| {
            // Keep data if no properties exists, which implies no message expiry!
            let Some(properties) = pubdata.properties.as_mut() else {
                return true;
            };

            // Keep data if there is no message_expiry_interval
            let Some(message_expiry_interval) = properties.message_expiry_interval.as_mut() else {
                return true;
            };

            let time_spent = now.saturating_duration_since(pubdata.timestamp).as_secs() as u32;

            let is_valid = time_spent < *message_expiry_interval;

            // ignore expired messages
            if is_valid {
                // set message_expiry_interval to (original value - time spent waiting in server)
                // ref: https://docs.oasis-open.org/mqtt/mqtt/v5.0/os/mqtt-v5.0-os.html#_Toc3901112
                *message_expiry_interval -= time_spent;
            }

            is_valid
        });

        // no need to include timestamp when returning
        let o = o
            .into_iter()
            .map(|(pubdata, offset)| ((pubdata.publish, pubdata.properties), offset))
            .collect();

        Ok((next, o))
    }

    pub fn shadow(&mut self, filter: &str) -> Option<PubWithProp> {
        let data = self.native.get_mut(*self.filter_indexes.get(filter)?)?;
        data.log.last().map(|p| (p.publish, p.properties))
    }

    /// This method is called when the subscriber has caught up with the commit log. In which case,
    /// instead of actively checking for commits in each `Router::run_inner` iteration, we instead
    /// wait and only try reading again when new messages have been added to the commit log. This
    /// methods converts a `DataRequest` (which actively reads the commit log in `Router::consume`)
    /// to a `Waiter` (which only reads when notified).
    pub fn park(&mut self, id: ConnectionId, request: DataRequest) {
        // calling unwrap on index here is fine, because only place this function is called is in
        // `Router::consume` method, when the status after reading from commit log of the same
        // filter as `request` is "done", that is, the subscriber has caught up. In other words,
        // there has been atleast 1 call to `native_readv` for the same filter, which means if
        // `native_readv` hasn't paniced, so this won't panic either.
        let data = self
            .native
            .get_mut(request.filter_idx)
            .expect(INDEXED_LOGS_EXIST);
        data.waiters.register(id, request);
    }

    /// Cleanup a connection from all the waiters
    pub fn clean(&mut self, id: ConnectionId) -> Vec<DataRequest> {
        let mut inflight = Vec::new();
        for (_, data) in self.native.iter_mut() {
            inflight.append(&mut data.waiters.remove(id));
        }

        inflight
    }

    /// fbbus: the index of the log of `filter`, if it has one.
    pub fn filter_idx(&self, filter: &str) -> Option<FilterIdx> {
        self.filter_indexes.get(filter).copied()
    }

    /// fbbus: removes the logs of filters nothing refers to any more: no read request
    /// parked in them, not in `used` (the router's read requests, subscriptions, saved
    /// sessions, unacknowledged deliveries and holds), not configured
    /// (`initialized_filters`). Upstream kept the log of every filter ever subscribed for
    /// the life of the router (a commit log, a meter and index entries, ~0.5 KB each):
    /// clients subscribing to ever new filters grew it without bound. A log without readers
    /// holds nothing anyone can read: a new subscription starts at the log's end. Removed
    /// logs leave the topic cache too, so their index may be reused. Returns how many.
    pub fn remove_unused(&mut self, used: &HashSet<FilterIdx>) -> usize {
        let configured = self.config.initialized_filters.as_deref().unwrap_or(&[]);
        let unused: HashSet<FilterIdx> = self
            .native
            .iter()
            .filter(|(idx, data)| {
                !used.contains(idx)
                    && data.waiters.waiters().is_empty()
                    && !configured.contains(&data.filter)
            })
            .map(|(idx, _)| idx)
            .collect();
        if unused.is_empty() {
            return 0;
        }
        let mut removed = Vec::with_capacity(unused.len());
        for &idx in &unused {
            let data = self.native.remove(idx);
            self.filter_indexes.remove(&data.filter);
            removed.push(data);
        }
        self.publish_filters.retain(|_, filters| {
            filters.retain(|idx| !unused.contains(idx));
            !filters.is_empty()
        });
        // Freed off the router thread, like released segments (`freer`).
        crate::freer::dispose(Box::new(removed), None);
        unused.len()
    }

    /// fbbus: filters with a log, and topics in the topic cache (tests).
    #[cfg(test)]
    pub fn sizes(&self) -> (usize, usize) {
        (self.native.len(), self.publish_filters.len())
    }

    /// fbbus: the retained store reports to `stats` from now on (`RouterHooks::retained`).
    pub fn report_retained_to(&mut self, stats: Arc<RetainedStats>) {
        stats.set(self.retained_counted, self.retained_bytes);
        self.retained_stats = stats;
    }

    /// fbbus: whether a retained message on `topic` is outside the bounds (an embedder's
    /// own prefix).
    fn retained_uncounted(&self, topic: &str) -> bool {
        self.config
            .retained_uncounted_prefixes
            .iter()
            .any(|prefix| topic.starts_with(prefix.as_str()))
    }

    /// fbbus: the bound a retained message of `size` bytes on `topic` would go beyond, if
    /// any. Replacing an existing retained message by one no larger is never refused; a
    /// larger one is refused if the bytes without the old one plus the new one would go
    /// beyond `max_retained_bytes` (else 100,000 small retained messages, each replaced by
    /// a 64 KB one, would take 6.4 GB).
    pub fn retain_refusal(&self, topic: &str, size: usize) -> Option<RetainLimit> {
        if self.retained_uncounted(topic) {
            return None;
        }
        let old = self
            .retained_publishes
            .get(topic)
            .map(|old| retained::size(&old.publish.topic, &old.publish.payload));
        let others = self.retained_bytes.saturating_sub(old.unwrap_or(0));
        let over_bytes = others.saturating_add(size) > self.config.max_retained_bytes;
        match old {
            Some(old) if size <= old => None,
            Some(_) => over_bytes.then_some(RetainLimit::Bytes),
            None if self.retained_counted >= self.config.max_retained_messages => {
                Some(RetainLimit::Messages)
            }
            None => over_bytes.then_some(RetainLimit::Bytes),
        }
    }

    /// fbbus: the counted size of the retained message on `topic`, 0 if uncounted.
    fn counted_size(&self, topic: &str, data: &PublishData) -> usize {
        if self.retained_uncounted(topic) {
            0
        } else {
            retained::size(&data.publish.topic, &data.publish.payload)
        }
    }

    /// fbbus: takes `size` bytes (and a message when `new`) out of or into the counts.
    fn count_retained(&mut self, new: bool, size: usize, sign: isize) {
        if sign > 0 {
            self.retained_counted += usize::from(new);
            self.retained_bytes = self.retained_bytes.saturating_add(size);
        } else {
            self.retained_counted = self.retained_counted.saturating_sub(usize::from(new));
            self.retained_bytes = self.retained_bytes.saturating_sub(size);
        }
    }

    /// Keeps `publish` as the retained message of `topic`. fbbus: unless it is on a new
    /// topic beyond `max_retained_messages` or `max_retained_bytes`, or a larger
    /// replacement beyond `max_retained_bytes` (`retained`): then it is not kept (and the
    /// replaced one is cleared), counted in the stats, and the first refusal of each bound
    /// is warned.
    pub fn insert_to_retained_publishes(
        &mut self,
        publish: Publish,
        publish_properties: Option<Box<PublishProperties>>,
        topic: Topic,
    ) -> Result<(), RetainLimit> {
        let size = retained::size(&publish.topic, &publish.payload);
        if let Some(limit) = self.retain_refusal(&topic, size) {
            if self.retained_stats.refuse(limit) {
                let (setting, value) = match limit {
                    RetainLimit::Messages => {
                        ("max_retained_messages", self.config.max_retained_messages)
                    }
                    RetainLimit::Bytes => ("max_retained_bytes", self.config.max_retained_bytes),
                };
                warn!(
                    topic,
                    setting,
                    value,
                    "retained publication not retained: the retained store is full (routed \
                     to current subscribers; a larger replacement clears the old value; \
                     logged once, counted after)"
                );
            }
            // A larger replacement that does not fit clears the old value: a stale last
            // value would be worse than none.
            self.remove_from_retained_publishes(topic);
            return Err(limit);
        }
        let counted = !self.retained_uncounted(&topic);
        let pub_with_props = (publish, publish_properties);
        let old = self.retained_publishes.insert(topic, pub_with_props.into());
        if counted {
            if let Some(old) = &old {
                let old_size = retained::size(&old.publish.topic, &old.publish.payload);
                self.count_retained(false, old_size, -1);
            }
            self.count_retained(old.is_none(), size, 1);
            self.retained_stats
                .set(self.retained_counted, self.retained_bytes);
        }
        Ok(())
    }

    pub fn remove_from_retained_publishes(&mut self, topic: Topic) {
        // fbbus: counted out.
        if let Some(old) = self.retained_publishes.remove(&topic) {
            let size = self.counted_size(&topic, &old);
            if size > 0 {
                self.count_retained(true, size, -1);
                self.retained_stats
                    .set(self.retained_counted, self.retained_bytes);
            }
        }
    }

    pub fn read_retained_messages(&mut self, filter: &str) -> Vec<PubWithProp> {
        trace!(info = "reading retain msg", filter = &filter);
        let now = Instant::now();

        // discard expired retained messages
        // fbbus: and count them out (`retained`).
        let prefixes = &self.config.retained_uncounted_prefixes;
        let (mut gone, mut gone_bytes) = (0usize, 0usize);
        self.retained_publishes.retain(|topic, pubdata| {
            let counted = !prefixes.iter().any(|p| topic.starts_with(p.as_str()));
            let size = retained::size(&pubdata.publish.topic, &pubdata.publish.payload);
            // Keep data if no properties exists, which implies no message expiry!
            let Some(properties) = pubdata.properties.as_mut() else {
                return true;
            };

            // Keep data if there is no message_expiry_interval
            let Some(message_expiry_interval) = properties.message_expiry_interval.as_mut() else {
                return true;
            };

            let time_spent = now.saturating_duration_since(pubdata.timestamp).as_secs() as u32;

            let is_valid = time_spent < *message_expiry_interval;

            // ignore expired messages
            if is_valid {
                // set message_expiry_interval to (original value - time spent waiting in server)
                // ref: https://docs.oasis-open.org/mqtt/mqtt/v5.0/os/mqtt-v5.0-os.html#_Toc3901112
                *message_expiry_interval -= time_spent;
            } else if counted {
                gone += 1;
                gone_bytes += size;
            }

            is_valid
        });
        if gone > 0 {
            self.retained_counted = self.retained_counted.saturating_sub(gone);
            self.retained_bytes = self.retained_bytes.saturating_sub(gone_bytes);
            self.retained_stats
                .set(self.retained_counted, self.retained_bytes);
        }

        // no need to include timestamp when returning
        let hidden = &self.config.wildcard_hidden_prefixes;
        self.retained_publishes
            .iter()
            .filter(|(topic, _)| routes(hidden, topic, filter))
            .map(|(_, p)| (p.publish.clone(), p.properties.clone()))
            .collect()
    }
}

/// fbbus: whether a publication on `topic` goes to a subscription of `filter`: MQTT's
/// match, except that a filter starting with a wildcard skips topics under the `hidden`
/// prefixes (`RouterConfig::wildcard_hidden_prefixes`), as it skips `$` topics.
fn routes(hidden: &[String], topic: &str, filter: &str) -> bool {
    let wild = filter.starts_with('#') || filter.starts_with('+');
    if wild && hidden.iter().any(|p| topic.starts_with(p.as_str())) {
        return false;
    }
    matches(topic, filter)
}

pub struct Data<T> {
    filter: Filter,
    pub log: CommitLog<T>,
    pub waiters: Waiters<DataRequest>,
}

impl<T> Data<T>
where
    T: Storage + Clone + Send + 'static, // fbbus: see `CommitLog`
{
    pub fn new(filter: &str, router_config: &RouterConfig) -> Data<T> {
        let mut max_segment_size = router_config.max_segment_size;
        let mut max_mem_segments = router_config.max_segment_count;

        // Override segment config for selected filter
        if let Some(config) = &router_config.custom_segment {
            for (f, segment_config) in config {
                if matches(filter, f) {
                    info!("Overriding segment config for filter: {}", filter);
                    max_segment_size = segment_config.max_segment_size;
                    max_mem_segments = segment_config.max_segment_count;
                }
            }
        }

        // max_segment_size: usize, max_mem_segments: usize
        let log = CommitLog::new(max_segment_size, max_mem_segments).unwrap();

        // fbbus: allocated on first use.
        let waiters = Waiters::with_capacity(0);
        Data {
            filter: filter.to_owned(),
            log,
            waiters,
        }
    }

    /// fbbus: the filter this log is for.
    pub fn filter(&self) -> &str {
        &self.filter
    }

    /// Writes to all the filters that are mapped to this publish topic
    /// and wakes up consumers that are matching this topic (if they exist)
    pub fn append(
        &mut self,
        item: T,
        notifications: &mut VecDeque<(ConnectionId, DataRequest)>,
    ) -> (Offset, &Filter) {
        let offset = self.log.append(item);
        if let Some(mut parked) = self.waiters.take() {
            notifications.append(&mut parked);
        }

        (offset, &self.filter)
    }
}

/// Acks log for a subscription
#[derive(Debug)]
pub struct AckLog {
    // Committed acks per connection. First pkid, last pkid, data
    committed: VecDeque<Ack>,
    // Recorded qos 2 publishes
    recorded: VecDeque<(Publish, Option<Box<PublishProperties>>)>,
}

impl AckLog {
    /// New log
    pub fn new() -> AckLog {
        // fbbus: allocated on first use (upstream reserved 2 x 100 entries per connection).
        AckLog {
            committed: VecDeque::new(),
            recorded: VecDeque::new(),
        }
    }

    pub fn connack(
        &mut self,
        id: ConnectionId,
        ack: ConnAck,
        props: Option<Box<ConnAckProperties>>,
    ) {
        let ack = Ack::ConnAck(id, ack, props);
        self.committed.push_back(ack);
    }

    pub fn suback(&mut self, ack: SubAck) {
        let ack = Ack::SubAck(ack);
        self.committed.push_back(ack);
    }

    pub fn puback(&mut self, ack: PubAck) {
        let ack = Ack::PubAck(ack);
        self.committed.push_back(ack);
    }

    pub fn pubrec(&mut self, publish: Publish, props: Option<Box<PublishProperties>>, ack: PubRec) {
        let ack = Ack::PubRec(ack);
        self.recorded.push_back((publish, props));
        self.committed.push_back(ack);
    }

    pub fn pubrel(&mut self, ack: PubRel) {
        let ack = Ack::PubRel(ack);
        self.committed.push_back(ack);
    }

    /// fbbus: the topic of the QoS 2 publish the next PUBREL releases (`pubcomp`).
    pub fn next_recorded_topic(&self) -> Option<&Bytes> {
        self.recorded.front().map(|(publish, _)| &publish.topic)
    }

    pub fn pubcomp(&mut self, ack: PubComp) -> Option<(Publish, Option<Box<PublishProperties>>)> {
        let ack = Ack::PubComp(ack);
        self.committed.push_back(ack);
        self.recorded.pop_front()
    }

    pub fn pingresp(&mut self, ack: PingResp) {
        let ack = Ack::PingResp(ack);
        self.committed.push_back(ack);
    }

    pub fn unsuback(&mut self, ack: UnsubAck) {
        let ack = Ack::UnsubAck(ack);
        self.committed.push_back(ack);
    }

    pub fn readv(&mut self) -> &mut VecDeque<Ack> {
        &mut self.committed
    }

    /// fbbus: releases the memory of empty queues (called when the router is idle).
    pub fn compact(&mut self) {
        shrink_if_empty(&mut self.committed);
        shrink_if_empty(&mut self.recorded);
    }
}

#[cfg(test)]
mod test {
    use super::DataLog;
    use crate::router::shared_subs::Strategy;
    use crate::router::DataRequest;
    use crate::RouterConfig;
    use std::collections::HashSet;

    #[test]
    fn publish_filters_updating_correctly_on_new_topic_subscription() {
        let config = RouterConfig {
            max_segment_size: 1024,
            max_connections: 10,
            max_segment_count: 10,
            max_outgoing_packet_count: 1024,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Strategy::RoundRobin,
            max_saved_sessions: crate::DEFAULT_MAX_SAVED_SESSIONS, // fbbus
            ..Default::default()                                   // fbbus
        };
        let mut data = DataLog::new(config).unwrap();
        data.next_native_offset("topic/a");
        data.matches("topic/a");

        data.next_native_offset("topic/+");

        assert_eq!(data.publish_filters.get("topic/a").unwrap().len(), 2);
    }

    #[test]
    fn publish_filters_updating_correctly_on_new_publish() {
        let config = RouterConfig {
            max_segment_size: 1024,
            max_connections: 10,
            max_segment_count: 10,
            max_outgoing_packet_count: 1024,
            custom_segment: None,
            initialized_filters: None,
            shared_subscriptions_strategy: Strategy::RoundRobin,
            max_saved_sessions: crate::DEFAULT_MAX_SAVED_SESSIONS, // fbbus
            ..Default::default()                                   // fbbus
        };
        let mut data = DataLog::new(config).unwrap();
        data.next_native_offset("+/+");

        data.matches("topic/a");

        assert_eq!(data.publish_filters.get("topic/a").unwrap().len(), 1);
    }

    fn datalog() -> DataLog {
        DataLog::new(RouterConfig {
            max_segment_size: 1024,
            max_connections: 10,
            max_segment_count: 10,
            max_outgoing_packet_count: 1024,
            initialized_filters: Some(vec!["configured/#".into()]),
            ..Default::default()
        })
        .unwrap()
    }

    /// fbbus: a retained message on a new topic beyond `max_retained_messages` or
    /// `max_retained_bytes` is not kept and is counted; clearing and replacing by a message
    /// no larger always work, a larger replacement within the bytes; uncounted prefixes
    /// are neither counted nor refused.
    #[test]
    fn the_retained_store_is_bounded() {
        use crate::protocol::Publish;
        use crate::router::{RetainLimit, RetainedStats};
        let mut data = DataLog::new(RouterConfig {
            max_retained_messages: 2,
            max_retained_bytes: 100,
            retained_uncounted_prefixes: vec!["own/".into()],
            ..Default::default()
        })
        .unwrap();
        let stats = std::sync::Arc::new(RetainedStats::default());
        data.report_retained_to(stats.clone());
        let retain = |data: &mut DataLog, topic: &str, payload: &str| {
            data.insert_to_retained_publishes(
                Publish::new(topic.to_owned(), payload.to_owned(), true),
                None,
                topic.to_owned(),
            )
        };
        assert_eq!(retain(&mut data, "a", "1234"), Ok(()));
        assert_eq!(retain(&mut data, "b", "1234"), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (2, 10));
        assert_eq!(data.retain_refusal("c", 5), Some(RetainLimit::Messages));
        assert_eq!(retain(&mut data, "c", "1234"), Err(RetainLimit::Messages));
        assert_eq!(retain(&mut data, "c", "1234"), Err(RetainLimit::Messages));
        assert_eq!(stats.refused(RetainLimit::Messages), 2);
        // Replacing works at the limit, and its bytes replace the old ones.
        assert_eq!(retain(&mut data, "a", "123456789"), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (2, 15));
        // The embedder's own topics are outside the bounds.
        assert_eq!(retain(&mut data, "own/x", "1234"), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (2, 15));
        // Clearing frees a place; bytes bound a new topic too.
        data.remove_from_retained_publishes("b".into());
        assert_eq!((stats.messages(), stats.bytes()), (1, 10));
        let big = "x".repeat(90);
        assert_eq!(retain(&mut data, "c", &big), Err(RetainLimit::Bytes));
        assert_eq!(stats.refused(RetainLimit::Bytes), 1);
        assert_eq!(retain(&mut data, "c", "1234"), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (2, 15));
        data.remove_from_retained_publishes("own/x".into());
        assert_eq!((stats.messages(), stats.bytes()), (2, 15));
        assert_eq!(data.read_retained_messages("#").len(), 2);
        // A larger replacement within the bytes is kept; beyond them it is refused and
        // the old value is cleared (a stale last value would mislead); a smaller one is
        // always kept.
        let within = "x".repeat(80);
        assert_eq!(retain(&mut data, "a", &within), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (2, 86));
        assert_eq!(
            retain(&mut data, "c", &"y".repeat(20)),
            Err(RetainLimit::Bytes)
        );
        assert_eq!((stats.messages(), stats.bytes()), (1, 81));
        assert_eq!(stats.refused(RetainLimit::Bytes), 2);
        assert_eq!(retain(&mut data, "a", "1"), Ok(()));
        assert_eq!((stats.messages(), stats.bytes()), (1, 2));
        assert_eq!(data.read_retained_messages("#").len(), 1);
    }

    /// fbbus: a filter starting with a wildcard does not match topics under the hidden
    /// prefixes, whether the filter or the topic came first, nor their retained messages;
    /// a filter naming the prefix does.
    #[test]
    fn wildcard_filters_skip_hidden_prefixes() {
        use crate::protocol::Publish;
        let mut data = datalog();
        data.config.wildcard_hidden_prefixes = vec!["mirror/".into()];
        let (all, _) = data.next_native_offset("#");
        let (plus, _) = data.next_native_offset("+/x");
        let (named, _) = data.next_native_offset("mirror/#");
        assert_eq!(data.matches("mirror/x"), Some(vec![named]));
        let mut plain = data.matches("plain/x").unwrap();
        plain.sort_unstable();
        assert_eq!(plain, vec![all, plus]);
        // A filter subscribed after the topic was cached.
        let (late, _) = data.next_native_offset("+/+");
        let (late_named, _) = data.next_native_offset("mirror/+");
        let mut cached = data.matches("mirror/x").unwrap();
        cached.sort_unstable();
        assert_eq!(cached, vec![named, late_named]);
        assert!(data.matches("plain/x").unwrap().contains(&late));
        for topic in ["mirror/x", "plain/x"] {
            data.insert_to_retained_publishes(
                Publish::new(topic.to_owned(), "1".to_owned(), true),
                None,
                topic.to_owned(),
            )
            .unwrap();
        }
        assert_eq!(data.read_retained_messages("#").len(), 1);
        assert_eq!(data.read_retained_messages("+/x").len(), 1);
        assert_eq!(data.read_retained_messages("mirror/#").len(), 1);
    }

    /// fbbus: the topic cache starts over at `MAX_CACHED_TOPICS` instead of growing with
    /// every distinct topic published.
    #[test]
    fn the_topic_cache_is_bounded() {
        let mut data = datalog();
        let (all, _) = data.next_native_offset("#");
        for i in 0..super::MAX_CACHED_TOPICS + 10 {
            assert_eq!(data.matches(&format!("t/{i}")), Some(vec![all]));
        }
        assert_eq!(data.sizes().1, 10);
        assert_eq!(data.matches("t/0"), Some(vec![all]));
    }

    /// fbbus: the log of a filter nothing refers to is removed, with its cache entries; a
    /// used, parked-on or configured one stays.
    #[test]
    fn unused_logs_are_removed() {
        let mut data = datalog();
        let (a, _) = data.next_native_offset("a/+");
        let (b, _) = data.next_native_offset("b/#");
        let (c, _) = data.next_native_offset("c");
        let request = |filter: &str, filter_idx| DataRequest {
            filter: filter.into(),
            filter_idx,
            qos: 0,
            cursor: (0, 0),
            read_count: 0,
            max_count: 100,
            forward_retained: false,
            retained_again: 0,
            group: None,
            skipping: false,
            slow: false,
            retained_pending: Default::default(),
        };
        data.park(7, request("c", c));
        assert_eq!(data.matches("a/x"), Some(vec![a]));
        assert_eq!(data.matches("b/x"), Some(vec![b]));
        assert_eq!(data.sizes(), (4, 2));

        assert_eq!(data.remove_unused(&[b].into_iter().collect()), 1);
        assert_eq!(data.sizes(), (3, 1));
        assert_eq!(data.filter_idx("a/+"), None);
        assert_eq!(data.matches("a/x"), Some(vec![]));
        assert!(data.filter_idx("configured/#").is_some());
        assert_eq!(
            data.remove_waiters_for_id(7, "c", "c")
                .map(|r| r.filter_idx),
            Some(c)
        );

        assert_eq!(data.remove_unused(&HashSet::new()), 2);
        assert_eq!(data.sizes(), (1, 0));
        // A filter subscribed again gets a new log.
        let (again, cursor) = data.next_native_offset("b/#");
        assert_eq!(cursor, (0, 0));
        assert_eq!(data.matches("b/x"), Some(vec![again]));
    }

    /// fbbus: a connection's parked request is found by subscription, also when it has
    /// both a filter's own and a shared subscription of it in one log.
    #[test]
    fn a_parked_request_is_found_by_its_subscription() {
        let mut data = datalog();
        let (x, _) = data.next_native_offset("x");
        for filter in ["x", "$share/g/x"] {
            data.park(
                3,
                DataRequest {
                    filter: filter.into(),
                    filter_idx: x,
                    qos: 0,
                    cursor: (0, 0),
                    read_count: 0,
                    max_count: 100,
                    forward_retained: false,
                    retained_again: 0,
                    group: None,
                    skipping: false,
                    slow: false,
                    retained_pending: Default::default(),
                },
            );
        }
        let removed = data.remove_waiters_for_id(3, "x", "$share/g/x");
        assert_eq!(removed.map(|r| r.filter), Some("$share/g/x".to_string()));
        assert_eq!(data.remove_waiters_for_id(3, "x", "$share/g/x"), None);
        assert!(data.remove_waiters_for_id(3, "x", "x").is_some());
    }

    //     #[test]
    //     fn appends_are_written_to_correct_commitlog() {
    //         pretty_env_logger::init();
    //         let config = RouterConfig {
    //             instant_ack: true,
    //             max_segment_size: 1024,
    //             max_connections: 10,
    //             max_mem_segments: 10,
    //             max_disk_segments: 0,
    //             max_read_len: 1024,
    //             log_dir: None,
    //             dynamic_log: true,
    //         };

    //         let mut data = DataLog::new(config).unwrap();
    //         data.next_native_offset("/devices/2321/actions");
    //         for i in 0..2 {
    //             let publish = Publish::new("/devices/2321/events/imu/jsonarray", QoS::AtLeastOnce, vec![1, 2, 3]);
    //             let v = data.native_append(publish);
    //             dbg!(v);
    //         }

    //         for i in 0..2 {
    //             let publish = Publish::new("/devices/2321/actions", QoS::AtLeastOnce, vec![1, 2, 3]);
    //             let v = data.native_append(publish);
    //             dbg!(v);
    //         }
    //     }
}
