//! The stamp every bridged message carries (`fb_bridge::bus::Stamp`, the device contract's
//! bus section), from another line: whatever bytes a peer with a line certificate puts as
//! the attachment, and whatever numbers a stamp that decodes carries, through the
//! duplicate window (`Dedup`) and the loss count (`Gaps`) a receiving line keeps; and the
//! same bytes as another line's loss report (`LossReport`, `fbbus/@/loss/...`) through
//! what the origin adds up of them (`Reported`).
//!
//! Checked: no panic (overflow checks on: sequence numbers near `u64::MAX`); a stamp that
//! decodes encodes to bytes that decode to the same stamp; a gap never counts more
//! messages than the topic's number says were put; the loss count's table stays bounded;
//! a report that decodes encodes to the same bytes, and what the origin counts from one
//! receiver's run never exceeds the largest count that run reported, nor what the origin
//! sent.
#![no_main]

use arbitrary::Arbitrary;
use std::collections::HashMap;

use fb_bridge::bus::{Dedup, Gaps, LossReport, Reported, Stamp, GAP_TOPICS};
use libfuzzer_sys::fuzz_target;

#[derive(Arbitrary, Debug)]
struct Numbers {
    line: u8,
    epoch: u64,
    seq: u64,
    topic_seq: u64,
    topic: u16,
    near_max: bool,
}

#[derive(Arbitrary, Debug)]
struct Input {
    raw: Vec<Vec<u8>>,
    numbers: Vec<Numbers>,
}

/// The messages the origin put on the bus: no receiver's count is taken above it.
const SENT: u64 = 1 << 40;

fuzz_target!(|input: Input| {
    let (mut dedup, mut gaps) = (Dedup::default(), Gaps::default());
    let mut reported = Reported::new(1);
    let mut counted: HashMap<(usize, u64), (u64, u64)> = HashMap::new();
    for raw in &input.raw {
        let Some(report) = LossReport::decode(raw) else {
            continue;
        };
        assert_eq!(&report.encode(), raw);
        let receiver = raw.len() % 3;
        let new = reported.take(&format!("line-{receiver}"), report, SENT);
        if report.origin_epoch == 1 {
            let (sum, max) = counted.entry((receiver, report.receiver_epoch)).or_default();
            *sum += new;
            *max = (*max).max(report.lost.min(SENT));
            assert!(sum <= max, "{report:?}: counted {sum} of at most {max}");
        } else {
            assert_eq!(new, 0, "a report about another run of the origin");
        }
    }
    for raw in &input.raw {
        let Some(stamp) = Stamp::decode(raw) else {
            continue;
        };
        assert!(stamp.qos <= 2, "{stamp:?}");
        let again = Stamp::decode(&stamp.encode()).expect("an encoded stamp decodes");
        assert_eq!(again, stamp);
        if dedup.first_time(&stamp) {
            // None: late (dropped); else at most the numbers before this one.
            let missing = gaps.missing(&stamp, "fb/d/F/P").unwrap_or(0);
            assert!(missing < stamp.topic_seq.max(1), "{missing} of {stamp:?}");
        }
    }
    for n in &input.numbers {
        let near = |x: u64| if n.near_max { u64::MAX - (x % 8192) } else { x };
        let stamp = Stamp {
            line: format!("line-{}", n.line % 4),
            epoch: n.epoch % 3,
            seq: near(n.seq),
            topic_seq: near(n.topic_seq),
            qos: 1,
            retain: false,
        };
        let topic = format!("fb/d{}/F/P", n.topic % (GAP_TOPICS as u16 + 50));
        if dedup.first_time(&stamp) {
            let missing = gaps.missing(&stamp, &topic).unwrap_or(0);
            assert!(missing < stamp.topic_seq.max(1), "{missing} of {stamp:?}");
        }
    }
});
