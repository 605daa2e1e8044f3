//! Where and how a message was published, carried through rumqttd's router.
//!
//! Three MQTT rules depend on facts rumqttd 0.20's router drops before delivery:
//! - delivery QoS = min(publication QoS, subscription QoS) [MQTT-3.8.4-8]: the router
//!   delivers at the subscription's QoS;
//! - No Local [MQTT-3.8.3-3]: the router does not know who published a message;
//! - Retain As Published [MQTT-3.3.1-12]: the router clears RETAIN on live deliveries.
//!
//! The packet path therefore attaches the [`Origin`] to the message as it enters the
//! router, the router stores and forwards it with the message (retained copies included),
//! and the delivery path takes it off again. It is a field of the vendored router's
//! `Publish` (`vendor/rumqttd/FBBUS-CHANGES.md`), never encoded on the wire: no client
//! can set or see it, and carrying it costs a reference count per delivery. (It used to
//! be a user property: five allocations per message and per delivery, a fifth of a
//! bridged line's CPU.)

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

pub use rumqttd::protocol::Origin;
use rumqttd::protocol::Publish;

/// Numbers publications for [`Origin::seq`]: unique within a broker process.
static NEXT_SEQ: AtomicU64 = AtomicU64::new(1);

/// The origin of a message `publisher` published at `qos` with `retain`, with a new
/// publication number (`seq`: every copy the router makes carries it).
pub fn new(qos: u8, retain: bool, publisher: &Arc<str>) -> Origin {
    Origin {
        qos: qos.min(2),
        retain,
        publisher: Arc::clone(publisher),
        seq: NEXT_SEQ.fetch_add(1, Ordering::Relaxed),
        stored: 0,
    }
}

/// Attaches `origin` to a message entering the router.
pub fn mark(publish: &mut Publish, origin: Origin) {
    publish.origin = Some(origin);
}

/// Takes the origin off a message leaving the router, if it carried one.
pub fn take(publish: &mut Publish) -> Option<Origin> {
    publish.origin.take()
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytes::BytesMut;
    use rumqttd::protocol::{v5::V5, Packet, Protocol, PublishProperties};

    #[test]
    fn round_trip_leaves_no_trace() {
        let mut publish = Publish::new("fb/plc-1/x", "1", false);
        let plain = publish.clone();
        let origin = new(1, true, &"plc-1".into());
        assert_ne!(origin.seq, new(1, true, &"plc-1".into()).seq);
        mark(&mut publish, origin.clone());
        assert_eq!(take(&mut publish), Some(origin));
        let taken = new(1, true, &"plc-1".into());
        assert_eq!(
            (taken.qos, taken.retain, &*taken.publisher),
            (1, true, "plc-1")
        );
        assert_eq!(publish, plain);
    }

    #[test]
    fn no_client_can_send_or_see_an_origin() {
        let mut publish = Publish::new("t", "p", false);
        mark(&mut publish, new(2, false, &"plc-1".into()));
        let properties = PublishProperties {
            user_properties: vec![("\u{0}fbbus:origin".into(), "2rother".into())],
            ..Default::default()
        };
        let mut wire = BytesMut::new();
        V5.write(
            Packet::Publish(publish, Some(Box::new(properties.clone()))),
            &mut wire,
        )
        .unwrap();
        assert!(
            !wire.windows(5).any(|w| w == b"plc-1"),
            "origin on the wire"
        );
        let Packet::Publish(read, read_properties) = V5.read_mut(&mut wire, usize::MAX).unwrap()
        else {
            panic!("not a publish")
        };
        assert_eq!(read.origin, None);
        // A client's user property of any name is just a user property.
        assert_eq!(read_properties, Some(Box::new(properties)));
    }
}
