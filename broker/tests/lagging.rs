//! A subscriber that lags behind its filter's commit log (issue 3): what retention drops
//! before it reads it is lost for QoS 0, never silently.

mod common;

use std::time::Duration;

use common::raw::{self, Connect, RawClient};
use common::{Broker, Options};

const MESSAGES: usize = 20_000;
const PAYLOAD: usize = 1_000;

/// The subscriber reads nothing while 20 MB are published, far more than the socket
/// buffers and a commit log of one 4 KiB segment hold, then drains. Every message it did
/// not get is counted in `fbbus_messages_skipped_total`, and it is warned about once (a
/// commit log of four messages makes it fall behind and catch up many times meanwhile).
#[test]
fn messages_a_lagging_subscriber_skips_are_counted_exactly() {
    let broker = Broker::start_with(
        Options {
            extra:
                "max_packet_bytes = 4096\nrouter_segment_bytes = 4096\nrouter_segment_count = 1\n"
                    .into(),
            ..Options::default()
        },
        |_| {},
    );
    let mut subscriber = RawClient::connect(broker.port());
    let connect = Connect {
        client_id: "laggard",
        ..Connect::default()
    };
    assert_eq!(subscriber.handshake(&connect), 0);
    subscriber.send(&raw::subscribe(4, 1, &["lag/t"]));
    let (suback, _) = subscriber.read_packet().expect("SUBACK");
    assert_eq!(suback, 0x90);

    let mut publisher = RawClient::connect(broker.port());
    let connect = Connect {
        client_id: "fast",
        ..Connect::default()
    };
    assert_eq!(publisher.handshake(&connect), 0);
    let message = raw::publish_qos0("lag/t", &[7u8; PAYLOAD]);
    let burst: Vec<u8> = message.repeat(1_000);
    for _ in 0..MESSAGES / 1_000 {
        publisher.send(&burst);
    }
    let routed = broker.wait_metric("fbbus_messages_received_total", MESSAGES as f64);
    assert_eq!(routed, MESSAGES as f64);

    // Drain: everything still buffered or in the log, until the broker has nothing more.
    subscriber
        .stream
        .set_read_timeout(Some(Duration::from_secs(2)))
        .unwrap();
    let mut received = 0;
    while let Some((byte1, body)) = subscriber.read_packet() {
        assert_eq!(byte1 & 0xf0, 0x30, "only PUBLISH expected");
        assert_eq!(body.len(), 2 + "lag/t".len() + PAYLOAD);
        received += 1;
    }

    let sent = broker.metric("fbbus_messages_sent_total");
    let skipped = broker.metric("fbbus_messages_skipped_total");
    assert_eq!(sent, received as f64);
    assert!(
        received < MESSAGES,
        "the subscriber lagged by more than the commit log holds"
    );
    assert_eq!(skipped, (MESSAGES - received) as f64);
    let log = broker.log_text();
    let warnings = log
        .lines()
        .filter(|l| l.contains("WARN") && l.contains("messages skipped"))
        .count();
    assert_eq!(
        warnings, 1,
        "at most one warning a minute per client:\n{log}"
    );
}
