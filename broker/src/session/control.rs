//! What an operator does with sessions through the admin plane: list them, and drop a
//! kept one.
//!
//! Why dropping (issue 33): a session belongs to the identity that created it
//! (`identity`), and an MQTT 3.1.1 session kept with clean session 0 never expires. So a
//! client that once connected under a client id that is not a username (with the default
//! `[auth] client_id = "any"`, or anonymously) and left its session kept would lock the
//! device of that client id out for good: every later CONNECT of another identity is
//! refused `client_id_owned`. Dropping ends such a kept session as its expiry would (the
//! router's saved session, the store's, the redeliveries), so the client id is free again.
//! A connected session is never dropped: the operator sees who holds it and stops that
//! client, or bans its credentials.
//!
//! The admin plane runs on a runtime of its own with one thread; ending a session in the
//! router needs the broker's multi-thread runtime (`RouterHandle::link_blocking`), so the
//! drop runs there and the admin request awaits it. The context is held weakly: the admin
//! plane never keeps a stopping broker's sessions alive.

use std::sync::{Arc, Weak};
use std::time::Duration;

use super::lifetime::end_idle_session;
use super::table::Listed;
use super::Context;

/// Sessions listed per request at most.
pub const MAX_PAGE: usize = 10_000;

/// The admin plane's handle on the sessions.
pub struct SessionControl {
    ctx: Weak<Context>,
    runtime: tokio::runtime::Handle,
}

/// Why a session was not dropped.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum DropError {
    #[error("no session with client id {0:?}")]
    Unknown(String),
    #[error(
        "the session of client id {0:?} is connected: stop that client (or remove its user \
         from the password file) first; only a kept offline session is dropped"
    )]
    Connected(String),
    #[error("the broker is stopping")]
    Stopping,
}

impl SessionControl {
    /// A handle for the admin plane; to be created on the broker's runtime.
    pub fn new(ctx: &Arc<Context>) -> SessionControl {
        SessionControl {
            ctx: Arc::downgrade(ctx),
            runtime: tokio::runtime::Handle::current(),
        }
    }

    /// The sessions (connected and kept) whose client ids sort after `after`, at most
    /// `limit` ([`MAX_PAGE`] at most), and how many there are in all.
    pub fn list(&self, after: &str, limit: usize) -> (Vec<Listed>, usize) {
        match self.ctx.upgrade() {
            Some(ctx) => ctx.sessions.list(after, limit.min(MAX_PAGE)),
            None => (Vec::new(), 0),
        }
    }

    /// Drops the kept offline session of `client_id`, as its expiry would end it.
    pub async fn drop_kept(&self, client_id: &str) -> Result<(), DropError> {
        let ctx = self.ctx.upgrade().ok_or(DropError::Stopping)?;
        let (session, connected, owner) = ctx
            .sessions
            .state(client_id)
            .ok_or_else(|| DropError::Unknown(client_id.to_owned()))?;
        if connected {
            return Err(DropError::Connected(client_id.to_owned()));
        }
        let owner = owner.to_string();
        let id = client_id.to_owned();
        let task = self.runtime.spawn(async move {
            let ended = end_idle_session(&ctx, &id, session).await;
            if ended {
                ctx.metrics.sessions_dropped.inc();
            }
            ended
        });
        match tokio::time::timeout(DROP_LIMIT, task).await {
            Ok(Ok(true)) => {
                tracing::warn!(
                    client_id,
                    owner,
                    session,
                    "kept session dropped by an operator"
                );
                Ok(())
            }
            // Reconnected in between: the session is newer, or connected.
            Ok(Ok(false)) => Err(DropError::Connected(client_id.to_owned())),
            Ok(Err(_)) | Err(_) => Err(DropError::Stopping),
        }
    }
}

/// How long a drop may take: one router turn, normally well under a second.
const DROP_LIMIT: Duration = Duration::from_secs(10);
