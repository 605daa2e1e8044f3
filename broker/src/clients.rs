//! The connected clients, as the admin plane lists them (`GET /api/v1/clients`, the
//! console's clients view, issue 37): who is connected, from where, with which client id,
//! protocol and keep-alive, since when, how many subscriptions, messages in and out.
//!
//! **Bounded** by the connections themselves (`[broker] max_connections`): an entry lives
//! exactly as long as its connection's session ([`Entry`] removes it when dropped), ~200
//! bytes each. **Off the packet path**: the table's lock is taken once when a connection
//! opens and once when it ends, and by the admin plane for one page at a time (at most
//! [`MAX_PAGE`] entries copied). The counters a connection moves while it runs are its
//! own atomics ([`Client`]), next to the broker-wide counters it moves anyway.

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::SystemTime;

use serde::Serialize;

/// Clients listed per request at most.
pub const MAX_PAGE: usize = 1000;

/// One connected client.
#[derive(Debug)]
pub struct Client {
    pub client_id: Arc<str>,
    pub username: Option<Box<str>>,
    pub address: SocketAddr,
    /// The listener's name.
    pub listener: Arc<str>,
    /// The connection's session number (`session::table`).
    pub session: u64,
    /// MQTT protocol level: 4 (3.1.1) or 5.
    pub protocol: u8,
    pub keep_alive_s: u16,
    pub since: SystemTime,
    messages_in: AtomicU64,
    messages_out: AtomicU64,
    subscriptions: AtomicU32,
}

impl Client {
    pub fn new(
        (client_id, session): (Arc<str>, u64),
        username: Option<&str>,
        address: SocketAddr,
        listener: Arc<str>,
        protocol: u8,
        keep_alive_s: u16,
    ) -> Client {
        Client {
            client_id,
            session,
            username: username.map(Into::into),
            address,
            listener,
            protocol,
            keep_alive_s,
            since: SystemTime::now(),
            messages_in: AtomicU64::new(0),
            messages_out: AtomicU64::new(0),
            subscriptions: AtomicU32::new(0),
        }
    }

    /// A publication received from the client.
    pub fn received(&self) {
        self.messages_in.fetch_add(1, Ordering::Relaxed);
    }

    /// A publication sent to the client.
    pub fn sent(&self) {
        self.messages_out.fetch_add(1, Ordering::Relaxed);
    }

    /// The client's subscriptions now.
    pub fn set_subscriptions(&self, n: usize) {
        self.subscriptions
            .store(u32::try_from(n).unwrap_or(u32::MAX), Ordering::Relaxed);
    }
}

/// One client as the admin API shows it.
#[derive(Debug, Clone, Serialize)]
pub struct Listed {
    pub client_id: String,
    pub username: Option<String>,
    pub address: String,
    pub listener: String,
    /// `3.1.1` or `5`.
    pub protocol: &'static str,
    pub keep_alive_s: u16,
    /// RFC 3339, UTC.
    pub connected_since: String,
    pub subscriptions: u32,
    pub messages_in: u64,
    pub messages_out: u64,
}

type Key = (Arc<str>, u64);

/// The connected clients, by client id and session number (a client id taken over is
/// briefly held by its old and new connection).
#[derive(Default)]
pub struct Clients {
    table: Mutex<BTreeMap<Key, Arc<Client>>>,
}

impl Clients {
    fn table(&self) -> std::sync::MutexGuard<'_, BTreeMap<Key, Arc<Client>>> {
        self.table.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A connection opened: listed until the returned entry drops.
    pub fn connected(self: &Arc<Self>, client: Client) -> Entry {
        let client = Arc::new(client);
        let key = (Arc::clone(&client.client_id), client.session);
        self.table().insert(key, Arc::clone(&client));
        Entry {
            clients: Arc::clone(self),
            client,
        }
    }

    /// Up to `limit` (at most [`MAX_PAGE`]) clients whose id sorts after `after`, in
    /// client id order, and how many are connected.
    pub fn list(&self, after: &str, limit: usize) -> (Vec<Listed>, usize) {
        let table = self.table();
        let start: Key = (Arc::from(after), u64::MAX);
        let page = table
            .range((std::ops::Bound::Excluded(start), std::ops::Bound::Unbounded))
            .take(limit.min(MAX_PAGE))
            .map(|(_, c)| Listed {
                client_id: c.client_id.to_string(),
                username: c.username.as_deref().map(str::to_owned),
                address: c.address.to_string(),
                listener: c.listener.to_string(),
                protocol: if c.protocol == 5 { "5" } else { "3.1.1" },
                keep_alive_s: c.keep_alive_s,
                connected_since: humantime::format_rfc3339_millis(c.since).to_string(),
                subscriptions: c.subscriptions.load(Ordering::Relaxed),
                messages_in: c.messages_in.load(Ordering::Relaxed),
                messages_out: c.messages_out.load(Ordering::Relaxed),
            })
            .collect();
        (page, table.len())
    }
}

/// A connection's place in [`Clients`]: removed when dropped.
pub struct Entry {
    clients: Arc<Clients>,
    client: Arc<Client>,
}

impl std::ops::Deref for Entry {
    type Target = Client;

    fn deref(&self) -> &Client {
        &self.client
    }
}

impl Drop for Entry {
    fn drop(&mut self) {
        let key = (Arc::clone(&self.client.client_id), self.client.session);
        self.clients.table().remove(&key);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn client(id: &str, session: u64) -> Client {
        Client::new(
            (id.into(), session),
            Some("u"),
            "127.0.0.1:1883".parse().unwrap(),
            "main".into(),
            4,
            30,
        )
    }

    #[test]
    fn listed_in_pages_while_connected() {
        let clients = Arc::new(Clients::default());
        let a = clients.connected(client("a", 1));
        let b = clients.connected(client("b", 2));
        let b2 = clients.connected(client("b", 3));
        a.received();
        a.sent();
        a.set_subscriptions(2);
        let (page, total) = clients.list("", 2);
        assert_eq!(total, 3);
        let ids: Vec<_> = page.iter().map(|l| l.client_id.as_str()).collect();
        assert_eq!(ids, ["a", "b"]);
        assert_eq!(
            (
                page[0].messages_in,
                page[0].messages_out,
                page[0].subscriptions
            ),
            (1, 1, 2)
        );
        // After "a": both connections of "b" (a takeover in progress).
        assert_eq!(clients.list("a", 10).0.len(), 2);
        assert_eq!(clients.list("b", 10).0.len(), 0);
        drop((a, b));
        let (page, total) = clients.list("", 10);
        assert_eq!(total, 1);
        assert_eq!(page[0].client_id, "b");
        drop(b2);
        assert_eq!(clients.list("", 10).1, 0);
    }
}
