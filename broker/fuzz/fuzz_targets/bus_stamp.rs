//! The stamp every bridged message carries (`fb_bridge::bus::Stamp`, the device contract's
//! bus section), from another line: whatever bytes a peer with a line certificate puts as
//! the attachment, and whatever numbers a stamp that decodes carries, through the
//! duplicate window (`Dedup`) and the loss count (`Gaps`) a receiving line keeps.
//!
//! Checked: no panic (overflow checks on: sequence numbers near `u64::MAX`); a stamp that
//! decodes encodes to bytes that decode to the same stamp; a gap never counts more
//! messages than the topic's number says were put; the loss count's table stays bounded.
#![no_main]

use arbitrary::Arbitrary;
use fb_bridge::bus::{Dedup, Gaps, Stamp, GAP_TOPICS};
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

fuzz_target!(|input: Input| {
    let (mut dedup, mut gaps) = (Dedup::default(), Gaps::default());
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
