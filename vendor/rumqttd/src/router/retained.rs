//! fbbus (whole file): the bounds of the retained-message store (issue 21).
//!
//! Upstream kept every retained message any client published, on any number of topics.
//! `RouterConfig::max_retained_messages` and `max_retained_bytes` bound what clients can
//! make the router keep: a retained publication on a topic without a retained message
//! that would go beyond either is not retained (it is still routed to the subscribers of
//! the moment). Clearing a retained message always works, and so does replacing it by
//! one no larger; a larger replacement beyond `max_retained_bytes` is refused and clears
//! the old one (a stale last value would mislead more than none). Topics under
//! `RouterConfig::retained_uncounted_prefixes` (the embedder's own, e.g. fbbus's
//! `fbbus/`) are neither counted nor refused: the embedder bounds them itself.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};

/// Which bound refused a retained message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RetainLimit {
    Messages,
    Bytes,
}

/// fbbus: the retained store's size and its refusals, for the embedder's metrics
/// (`RouterHooks::retained`). Updated by the router thread.
#[derive(Debug, Default)]
pub struct RetainedStats {
    messages: AtomicUsize,
    bytes: AtomicUsize,
    refused_messages: AtomicU64,
    refused_bytes: AtomicU64,
}

impl RetainedStats {
    /// Counted retained messages held now (uncounted prefixes excluded).
    pub fn messages(&self) -> usize {
        self.messages.load(Ordering::Relaxed)
    }

    /// Their bytes (topic and payload).
    pub fn bytes(&self) -> usize {
        self.bytes.load(Ordering::Relaxed)
    }

    /// Retained publications not retained so far, by the bound that refused them.
    pub fn refused(&self, limit: RetainLimit) -> u64 {
        match limit {
            RetainLimit::Messages => self.refused_messages.load(Ordering::Relaxed),
            RetainLimit::Bytes => self.refused_bytes.load(Ordering::Relaxed),
        }
    }

    pub(crate) fn set(&self, messages: usize, bytes: usize) {
        self.messages.store(messages, Ordering::Relaxed);
        self.bytes.store(bytes, Ordering::Relaxed);
    }

    /// Counts a refusal; true for the first of its kind (the router warns once).
    pub(crate) fn refuse(&self, limit: RetainLimit) -> bool {
        let counter = match limit {
            RetainLimit::Messages => &self.refused_messages,
            RetainLimit::Bytes => &self.refused_bytes,
        };
        counter.fetch_add(1, Ordering::Relaxed) == 0
    }
}

/// The bytes a retained message counts for: its topic and payload.
pub(crate) fn size(topic: &[u8], payload: &[u8]) -> usize {
    topic.len() + payload.len()
}
