//! Putting back what the store held, before the listeners open: retained messages into
//! the router, and each persistent session into the router and the session table with its
//! subscriptions, so that what is published before its client returns is queued for it
//! as if the broker had never stopped. Its backlog (what was queued when the broker
//! stopped) stays with the store until its next connection takes it.

use std::sync::Arc;
use std::time::Instant;

use rumqttd::protocol::{Filter, Packet, QoS, RetainForwardRule, Subscribe, SubscribeProperties};
use rumqttd::Notification;

use super::context::Context;
use super::packet_ids::Resume;
use super::table::Remains;
use crate::broker_publisher::publish_packet;
use crate::identity::Owner;
use crate::policy::origin;
use crate::router::unlink;
use crate::store::{Options, Restore, RestoredSession};

/// The router link retained messages are put back through.
const RESTORE_CLIENT_ID: &str = "fbbus:restore";

/// Puts `restore` back; returns what it could not (a router error), which the caller logs.
pub async fn put_back(restore: &Restore, ctx: &Context) -> Result<(), String> {
    let started = Instant::now();
    retained(restore, ctx).await?;
    for session in &restore.sessions {
        self::session(session, ctx).await?;
    }
    // The store's line, under the store's log target whatever module puts it back: a
    // line's `[log] level = "warn,broker::store=info"` (loadtest's) must still show it.
    tracing::info!(
        target: "broker::store::restore",
        retained = restore.retained.len(),
        sessions = restore.sessions.len(),
        queued = restore.queued,
        delayed_wills = restore.wills.len(),
        read_ms = restore.took.as_millis() as u64,
        put_back_ms = started.elapsed().as_millis() as u64,
        "store restored"
    );
    Ok(())
}

/// Retained messages, published again with RETAIN at QoS 0 (no acknowledgements to wait
/// for) and their original QoS and publisher in the origin, which the delivery path uses
/// (delivery QoS, Retain As Published, No Local). A SUBSCRIBE at the end, answered after
/// every publication before it, says the router has them all.
async fn retained(restore: &Restore, ctx: &Context) -> Result<(), String> {
    if restore.retained.is_empty() {
        return Ok(());
    }
    let (mut tx, mut rx, _) = ctx
        .router
        .link(RESTORE_CLIENT_ID, true, 0)
        .await
        .map_err(|e| e.to_string())?;
    for chunk in restore.retained.chunks(1024) {
        {
            let mut buffer = tx.buffer();
            for m in chunk {
                let mut publish = publish_packet(m.topic.clone(), m.payload.clone(), 0, true, 0);
                origin::mark(
                    &mut publish,
                    origin::new(m.qos, true, &Arc::clone(&m.publisher)),
                );
                buffer.push_back(Packet::Publish(publish, m.properties.clone()));
            }
        }
        // Wakes the router for what is buffered (a SUBSCRIBE to a topic nobody publishes).
        done_marker(&mut tx, &mut rx).await?;
    }
    let _ = unlink(tx).await;
    Ok(())
}

/// Sends a SUBSCRIBE and waits for its SUBACK: the router handled everything before it.
async fn done_marker(
    tx: &mut rumqttd::local::LinkTx,
    rx: &mut rumqttd::local::LinkRx,
) -> Result<(), String> {
    tx.send(Packet::Subscribe(
        Subscribe {
            pkid: 1,
            filters: vec![Filter {
                path: "fbbus-restore/done".into(),
                qos: QoS::AtMostOnce,
                nolocal: false,
                preserve_retain: false,
                retain_forward_rule: RetainForwardRule::Never,
            }],
        },
        None,
    ))
    .await
    .map_err(|e| e.to_string())?;
    wait_suback(rx).await
}

async fn wait_suback(rx: &mut rumqttd::local::LinkRx) -> Result<(), String> {
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        let next = tokio::time::timeout_at(deadline, rx.next())
            .await
            .map_err(|_| "the router did not answer within 30 s".to_string())?;
        match next.map_err(|e| e.to_string())? {
            Some(Notification::Unschedule) => {
                let _ = rx.wake().await;
            }
            Some(n) => {
                let packet: Option<Packet> = n.into();
                if matches!(packet, Some(Packet::SubAck(..))) {
                    return Ok(());
                }
            }
            None => {}
        }
    }
}

/// The owner of each restored session (a delayed will is cancelled by its owner's return).
pub fn owners(restore: &Restore) -> std::collections::HashMap<String, Owner> {
    restore
        .sessions
        .iter()
        .map(|s| (s.client.clone(), owner(&s.owner)))
        .collect()
}

fn owner(name: &str) -> Owner {
    if name.is_empty() {
        Owner::Anonymous
    } else {
        Owner::User(name.into())
    }
}

/// A stored subscription as the router's filter, with `retain`'s Retain Handling.
fn filter(path: &str, o: &Options, retain: RetainForwardRule) -> Filter {
    Filter {
        path: path.to_owned(),
        qos: match o.qos {
            0 => QoS::AtMostOnce,
            1 => QoS::AtLeastOnce,
            _ => QoS::ExactlyOnce,
        },
        nolocal: o.no_local,
        preserve_retain: o.retain_as_published,
        retain_forward_rule: retain,
    }
}

fn rule(retain_handling: u8) -> RetainForwardRule {
    match retain_handling {
        0 => RetainForwardRule::OnEverySubscribe,
        1 => RetainForwardRule::OnNewSubscribe,
        _ => RetainForwardRule::Never,
    }
}

/// One persistent session: linked as persistent, subscribed (Retain Handling 2: a
/// resumed session gets no retained messages), unlinked, so the router keeps it offline;
/// its offline entry in the session table with its owner and what is left of its expiry.
async fn session(s: &RestoredSession, ctx: &Context) -> Result<(), String> {
    let owner = owner(&s.owner);
    let Ok((session, _)) = ctx.sessions.open(&s.client, &owner) else {
        return Ok(());
    };
    let (mut tx, mut rx, _) = ctx
        .router
        .link(&s.client, false, 0)
        .await
        .map_err(|e| e.to_string())?;
    // One SUBSCRIBE per Subscription Identifier: the identifier is per packet.
    let mut by_id: std::collections::BTreeMap<u32, Vec<Filter>> = Default::default();
    for (path, o) in &s.subscriptions {
        by_id
            .entry(o.id)
            .or_default()
            .push(filter(path, o, RetainForwardRule::Never));
    }
    for (pkid, (id, filters)) in by_id.into_iter().enumerate() {
        for f in &filters {
            ctx.observers.subscribed(&f.path);
        }
        let properties = (id > 0).then(|| SubscribeProperties {
            id: Some(id as usize),
            user_properties: Vec::new(),
        });
        tx.send(Packet::Subscribe(
            Subscribe {
                pkid: (pkid % 65535 + 1) as u16,
                filters,
            },
            properties,
        ))
        .await
        .map_err(|e| e.to_string())?;
        wait_suback(&mut rx).await?;
    }
    let _ = unlink(tx).await;
    drop(rx);
    ctx.sessions
        .close(&s.client, session, Remains::Kept(s.expires_in));
    // Options the router ignores (No Local, Retain As Published, Retain Handling) are
    // applied by the session from its own table: handed to its next connection.
    let special = s
        .subscriptions
        .iter()
        .any(|(_, o)| o.no_local || o.retain_as_published || o.retain_handling == 2);
    if special {
        let filters = s
            .subscriptions
            .iter()
            .map(|(path, o)| (path.clone(), filter(path, o, rule(o.retain_handling))))
            .collect();
        ctx.redeliveries.save(
            &s.client,
            session,
            Resume::with_subscriptions(filters),
            false,
        );
    }
    Ok(())
}
