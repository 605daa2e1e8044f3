//! The QoS a message was published with, carried through rumqttd's router.
//!
//! MQTT delivers a message at min(publication QoS, subscription QoS) [MQTT-3.8.4-8].
//! rumqttd 0.20's router forgets the publication QoS and delivers at the subscription's.
//! The packet path therefore attaches the publication QoS as a user property the router
//! stores and forwards with the message (retained copies included), and takes it off again
//! before the message leaves the broker: no client ever sees it.

use rumqttd::protocol::PublishProperties;

/// A name no client can send: user property names are UTF-8 strings, but fbbus strips
/// this one on the way out, so even a client that sent it could not spoof a QoS.
const MARKER: &str = "\u{0}fbbus:qos";

/// Attaches the publication QoS (last user property).
pub fn mark(properties: &mut Option<PublishProperties>, qos: u8) {
    let props = properties.get_or_insert_with(PublishProperties::default);
    props.user_properties.retain(|(k, _)| k != MARKER);
    props
        .user_properties
        .push((MARKER.to_owned(), char::from(b'0' + qos.min(2)).to_string()));
}

/// Removes the marker; returns the publication QoS if the message carried one.
/// Properties that only existed for the marker become `None` again.
pub fn take(properties: &mut Option<PublishProperties>) -> Option<u8> {
    let props = properties.as_mut()?;
    let at = props
        .user_properties
        .iter()
        .rposition(|(k, _)| k == MARKER)?;
    let (_, value) = props.user_properties.remove(at);
    if *props == PublishProperties::default() {
        *properties = None;
    }
    value.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_leaves_no_trace() {
        let mut none = None;
        mark(&mut none, 1);
        assert_eq!(take(&mut none), Some(1));
        assert_eq!(none, None);

        let mut some = Some(PublishProperties {
            user_properties: vec![("k".into(), "v".into())],
            ..Default::default()
        });
        mark(&mut some, 0);
        assert_eq!(take(&mut some), Some(0));
        assert_eq!(
            some.unwrap().user_properties,
            vec![("k".to_owned(), "v".to_owned())]
        );
    }

    #[test]
    fn a_client_supplied_marker_is_replaced() {
        let mut p = Some(PublishProperties {
            user_properties: vec![(MARKER.into(), "2".into())],
            ..Default::default()
        });
        mark(&mut p, 0);
        assert_eq!(take(&mut p), Some(0));
        assert_eq!(p, None);
    }
}
