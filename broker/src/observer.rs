//! Who else is told what clients subscribe to.
//!
//! Two parts of the broker act on subscriptions without being part of a session: the
//! typed-topic stage starts re-encoding into `dinasore/` and `fbdk/` once someone reads
//! them, and the bus bridge imports from the other lines what local clients read. They
//! are registered here once, at start-up, before the first client connects; the session
//! layer calls them and knows nothing else about them.

use std::sync::Arc;

/// Told of every filter local clients start or stop reading. Called on the connection's
/// task: must not block.
pub trait SubscriptionObserver: Send + Sync {
    /// A first subscription to `filter` in a session.
    fn subscribed(&self, filter: &str);
    /// A session no longer reads `filter` (UNSUBSCRIBE, or its clean session ended).
    fn unsubscribed(&self, filter: &str);
}

/// The observers, in the order they were registered.
#[derive(Default)]
pub struct Observers(Vec<Arc<dyn SubscriptionObserver>>);

impl Observers {
    pub fn register(&mut self, observer: Arc<dyn SubscriptionObserver>) {
        self.0.push(observer);
    }

    pub fn subscribed(&self, filter: &str) {
        for observer in &self.0 {
            observer.subscribed(filter);
        }
    }

    pub fn unsubscribed(&self, filter: &str) {
        for observer in &self.0 {
            observer.unsubscribed(filter);
        }
    }
}
