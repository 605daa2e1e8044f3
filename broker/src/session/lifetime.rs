//! How long the router keeps a client's session after its connection ends.
//!
//! rumqttd keeps a link's session unless the link is clean: the MQTT 3.1.1 rule. MQTT 5
//! separates the two questions: Clean Start discards an existing session when the client
//! connects, and the Session Expiry Interval decides how long the new one outlives the
//! connection (3.1.2.4, 3.1.2.11.2). [`SessionLifetime`] maps the CONNECT onto rumqttd:
//! a v5 link is clean only for Clean Start with expiry 0; Clean Start with expiry > 0 first
//! ends the old session with a purge link; the expiry task ([`expire_sessions`]) ends an
//! idle session when due, guarded by the session number so a client that came back keeps
//! its session. The client's DISCONNECT may change the expiry ([`SessionLifetime::on_disconnect`]).

use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;

use super::context::Context;
use crate::router::{unlink, RouterHandle};
use crate::session::table::Remains;
use crate::store::{Record, Store};
use crate::supervisor::Tasks;

/// When the router's copy of a session ends.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionLifetime {
    /// Link the connection as clean: the router keeps nothing after it ends.
    pub clean_link: bool,
    /// End an existing saved session before linking (MQTT 5 Clean Start, expiry > 0).
    pub purge_before_link: bool,
    /// End the saved session this long after the connection ends (unless the client is
    /// back). None: the router's rule (clean: nothing kept; MQTT 3.1.1 persistent: forever).
    pub expires_after: Option<Duration>,
}

impl SessionLifetime {
    pub fn v311(clean_session: bool) -> SessionLifetime {
        SessionLifetime {
            clean_link: clean_session,
            purge_before_link: false,
            expires_after: None,
        }
    }

    /// MQTT 5 3.1.2.4 and 3.1.2.11.2. An expiry of 0xFFFFFFFF never expires.
    pub fn v5(clean_start: bool, session_expiry: u32) -> SessionLifetime {
        let persists = session_expiry > 0;
        SessionLifetime {
            clean_link: clean_start && !persists,
            purge_before_link: clean_start && persists,
            expires_after: match session_expiry {
                u32::MAX => None,
                _ if clean_start && !persists => None,
                secs => Some(Duration::from_secs(secs as u64)),
            },
        }
    }
}

impl SessionLifetime {
    /// MQTT 5 3.14.2.2.2: a Session Expiry Interval in the client's DISCONNECT replaces
    /// the one of its CONNECT, for what happens once the connection ends: longer, shorter
    /// (0 ends the session at once) or never (0xFFFFFFFF). None when the CONNECT's was 0
    /// (or absent) and this one is not: a Protocol Error [MQTT-3.14.2-2], which the server
    /// answers with DISCONNECT 0x82, as the spec says; the DISCONNECT is then not a valid
    /// one (the will fires) and the session ends with the connection as its CONNECT said.
    pub fn on_disconnect(self, session_expiry: u32) -> Option<SessionLifetime> {
        let connect_was_zero = self.clean_link || self.expires_after == Some(Duration::ZERO);
        match (connect_was_zero, session_expiry) {
            (true, 0) => Some(self),
            (true, _) => None,
            (false, secs) => Some(SessionLifetime {
                expires_after: match secs {
                    u32::MAX => None,
                    secs => Some(Duration::from_secs(secs as u64)),
                },
                ..self
            }),
        }
    }

    /// What the router keeps of the session once its connection ends.
    pub fn remains(&self) -> Remains {
        if self.clean_link {
            Remains::Nothing
        } else {
            Remains::Kept(self.expires_after)
        }
    }
}

/// Ends a session the router saved for `client_id`: a clean link with that client id
/// replaces the saved state, and is disconnected at once.
pub async fn purge_router_session(router: &RouterHandle, client_id: &str) {
    let linked = router.link(client_id, true, 0).await;
    if let Ok((tx, _rx, _)) = linked {
        let _ = unlink(tx).await;
    }
}

/// The session table dropped `client_id`'s offline session at its limit
/// (`SessionTable::evicting`, called with the table held): the router's saved session of
/// that client id ends too, so it cannot outlive its owner's record and be resumed by
/// another identity. The router drops its oldest saved session at the same limit, but by
/// its own order; usually it has already dropped this one and the purge finds nothing.
/// Blocks the thread for one router turn (`RouterHandle::link_blocking`, multi-thread
/// runtime only, as `end_idle_session`); only a close beyond the limit does this.
pub fn purge_evicted(
    router: &RouterHandle,
    tasks: &Tasks,
    store: Option<&Arc<Store>>,
    client_id: &str,
) {
    if let Some(store) = store {
        store.set_session(client_id, false);
        store.write_now(vec![Record::Ended {
            client: client_id.into(),
        }]);
    }
    match router.link_blocking(client_id, true) {
        Ok((tx, rx, _)) => {
            tasks.spawn(async move {
                let _ = unlink(tx).await;
                drop(rx);
            });
        }
        Err(e) => tracing::warn!(
            client_id,
            error = %e,
            "could not end the router's saved session of a client id the session table \
             dropped at its limit"
        ),
    }
}

/// The expiry of a session is due (or an operator drops it, `control`): ends it in the
/// router unless the client is back. Returns whether it ended.
pub async fn end_idle_session(ctx: &Context, client_id: &str, session: u64) -> bool {
    // Linking under the table's lock orders the purge before any new connection of this
    // client id, whose own link then simply replaces the purge link.
    let linked = ctx.sessions.with_idle(client_id, session, || {
        ctx.router.link_blocking(client_id, true)
    });
    if let Some(Ok((tx, _rx, _))) = linked {
        let _ = unlink(tx).await;
        ctx.redeliveries.forget(client_id);
        if let Some(store) = &ctx.store {
            store.set_session(client_id, false);
            let ended = Record::Ended {
                client: client_id.into(),
            };
            store.write(vec![ended], false).await;
        }
        tracing::debug!(client_id, "session ended");
        return true;
    }
    false
}

/// How often the expiry task looks for sessions whose expiry is due: MQTT 5 expiry
/// intervals are whole seconds.
const EXPIRY_TICK: Duration = Duration::from_secs(1);

/// Ends the kept sessions whose expiry is due (`SessionTable::due`), until shutdown. One
/// task for all of them: their deadlines live in the session table, which is bounded.
pub async fn expire_sessions(ctx: Arc<Context>, mut shutdown: watch::Receiver<bool>) {
    let mut tick = tokio::time::interval(EXPIRY_TICK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.changed() => return,
        }
        for (client_id, session) in ctx.sessions.due(tokio::time::Instant::now()) {
            end_idle_session(&ctx, &client_id, session).await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn disconnect_replaces_the_connect_expiry() {
        let kept = SessionLifetime::v5(false, 1);
        assert_eq!(
            kept.on_disconnect(5).unwrap().remains(),
            Remains::Kept(Some(Duration::from_secs(5)))
        );
        assert_eq!(
            kept.on_disconnect(0).unwrap().remains(),
            Remains::Kept(Some(Duration::ZERO))
        );
        assert_eq!(
            kept.on_disconnect(u32::MAX).unwrap().remains(),
            Remains::Kept(None)
        );
        // Clean Start with an expiry: the new session may be given more or less.
        let fresh = SessionLifetime::v5(true, 300);
        assert_eq!(
            fresh.on_disconnect(0).unwrap().expires_after,
            Some(Duration::ZERO)
        );
        // CONNECT said 0 (Clean Start 1 or 0): only 0 may follow [MQTT-3.14.2-2].
        for connect in [SessionLifetime::v5(true, 0), SessionLifetime::v5(false, 0)] {
            assert_eq!(connect.on_disconnect(0), Some(connect));
            assert_eq!(connect.on_disconnect(5), None);
        }
    }
}
