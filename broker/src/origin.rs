//! Where and how a message was published, carried through rumqttd's router.
//!
//! Three MQTT rules depend on facts rumqttd 0.20's router drops before delivery:
//! - delivery QoS = min(publication QoS, subscription QoS) [MQTT-3.8.4-8]: the router
//!   delivers at the subscription's QoS;
//! - No Local [MQTT-3.8.3-3]: the router does not know who published a message;
//! - Retain As Published [MQTT-3.3.1-12]: the router clears RETAIN on live deliveries.
//!
//! The packet path therefore attaches the [`Origin`] as a user property the router stores
//! and forwards with the message (retained copies included), and takes it off again
//! before the message leaves the broker: no client ever sees it.

use rumqttd::protocol::PublishProperties;

/// A name no client can spoof: fbbus replaces any client-sent one and strips it on the way out.
const MARKER: &str = "\u{0}fbbus:origin";

/// How a message entered the broker.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Origin {
    pub qos: u8,
    pub retain: bool,
    /// The publishing client's id.
    pub publisher: String,
}

/// Attaches `origin` (as the last user property).
pub fn mark(properties: &mut Option<PublishProperties>, origin: &Origin) {
    let props = properties.get_or_insert_with(PublishProperties::default);
    props.user_properties.retain(|(k, _)| k != MARKER);
    let value = format!(
        "{}{}{}",
        origin.qos.min(2),
        if origin.retain { 'r' } else { '-' },
        origin.publisher
    );
    props.user_properties.push((MARKER.to_owned(), value));
}

/// Removes the marker; returns the origin if the message carried one. Properties that
/// only existed for the marker become `None` again.
pub fn take(properties: &mut Option<PublishProperties>) -> Option<Origin> {
    let props = properties.as_mut()?;
    let at = props
        .user_properties
        .iter()
        .rposition(|(k, _)| k == MARKER)?;
    let (_, value) = props.user_properties.remove(at);
    if *props == PublishProperties::default() {
        *properties = None;
    }
    let mut chars = value.chars();
    let qos = chars.next()?.to_digit(10)? as u8;
    let retain = chars.next()? == 'r';
    Some(Origin {
        qos,
        retain,
        publisher: chars.as_str().to_owned(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn origin(qos: u8, retain: bool) -> Origin {
        Origin {
            qos,
            retain,
            publisher: "plc-1".into(),
        }
    }

    #[test]
    fn round_trip_leaves_no_trace() {
        let mut none = None;
        mark(&mut none, &origin(1, true));
        assert_eq!(take(&mut none), Some(origin(1, true)));
        assert_eq!(none, None);

        let mut some = Some(PublishProperties {
            user_properties: vec![("k".into(), "v".into())],
            ..Default::default()
        });
        mark(&mut some, &origin(0, false));
        assert_eq!(take(&mut some), Some(origin(0, false)));
        assert_eq!(
            some.unwrap().user_properties,
            vec![("k".to_owned(), "v".to_owned())]
        );
    }

    #[test]
    fn a_client_supplied_marker_is_replaced() {
        let mut p = Some(PublishProperties {
            user_properties: vec![(MARKER.into(), "2rother".into())],
            ..Default::default()
        });
        mark(&mut p, &origin(0, false));
        assert_eq!(take(&mut p), Some(origin(0, false)));
        assert_eq!(p, None);
    }
}
