//! Issue 21: what a client can make the broker hold has a limit, and past it the request
//! is refused with its reason and counted, while everything else goes on.

mod common;

use common::raw::{self, Connect, RawClient};
use common::{Broker, Options};

#[test]
fn subscriptions_beyond_the_per_client_limit_are_refused_with_quota_exceeded() {
    let broker = Broker::start_with(
        Options {
            extra: "max_subscriptions_per_client = 3\n".into(),
            ..Options::default()
        },
        |_| {},
    );
    for (version, over) in [(5u8, 0x97u8), (4, 0x80)] {
        let mut c = RawClient::connect(broker.port());
        let id = format!("subs-{version}");
        assert_eq!(
            c.handshake(&Connect {
                version,
                client_id: &id,
                ..Default::default()
            }),
            0
        );
        c.send(&raw::subscribe(
            version,
            1,
            &["a/1", "a/2", "a/3", "a/4", "a/#"],
        ));
        let (b, body) = c.read_packet().expect("SUBACK");
        assert_eq!(b, 0x90);
        assert_eq!(
            raw::suback_codes(version, &body),
            vec![0, 0, 0, over, over],
            "v{version}"
        );
        // A filter already held is replaced, not added: allowed at the limit.
        c.send(&raw::subscribe(version, 2, &["a/2"]));
        let (_, body) = c.read_packet().expect("SUBACK");
        assert_eq!(raw::suback_codes(version, &body), vec![0], "v{version}");
        // The connection is served on.
        c.send(&raw::PINGREQ);
        assert_eq!(c.read_packet().expect("PINGRESP").0, 0xD0);
    }
    assert_eq!(
        broker.metric("fbbus_limit_refusals_total{limit=\"subscriptions_per_client\"}"),
        4.0
    );
}
