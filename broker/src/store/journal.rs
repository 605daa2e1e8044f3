//! What one session has to tell the store between two of its batches.
//!
//! Most of it is `Done`: one for every stored message delivered to a persistent session,
//! as many as the messages themselves. Those are kept as bare message numbers and written
//! by the writer as `Done` records after the batch's other records, so a session hands
//! over its client id once per batch instead of once per message (`docs/performance.md`,
//! "Done records by number"). The order the log needs still holds: a message's `Done`
//! follows its `Publish`, which was handed over before the message was routed, so in an
//! earlier batch; and whatever the session recorded about that message before (its QoS 2
//! step) is in this batch's records or an earlier batch, so before the `Done`.

use std::sync::Arc;

use super::record::{ClientId, Record};

#[derive(Debug, Default)]
pub struct Journal {
    records: Vec<Record>,
    done: Vec<u64>,
}

impl Journal {
    pub fn push(&mut self, record: Record) {
        self.records.push(record);
    }

    /// Room for `n` more records.
    pub fn reserve(&mut self, n: usize) {
        self.records.reserve(n);
    }

    /// The session is done with stored message `seq` (acknowledged, or not sent).
    pub fn done(&mut self, seq: u64) {
        self.done.push(seq);
    }

    pub fn is_empty(&self) -> bool {
        self.records.is_empty() && self.done.is_empty()
    }

    /// Everything `client`'s session recorded so far: its records, and its `Done`
    /// numbers with the client id (none if there are none). The numbers leave room for as
    /// many again (a session's batches tend to be alike); the records are reserved by the
    /// next batch that has any ([`Journal::reserve`]).
    pub fn take(&mut self, client: &ClientId) -> (Vec<Record>, Option<(ClientId, Vec<u64>)>) {
        let room = self.done.len().min(4096);
        let done = std::mem::replace(&mut self.done, Vec::with_capacity(room));
        let done = (!done.is_empty()).then(|| (Arc::clone(client), done));
        (std::mem::take(&mut self.records), done)
    }
}
