//! What the bus link hands the broker: other lines' messages and the bus's events.

use super::Stamp;

/// A message from another line, as it came off zenoh.
#[derive(Debug, Clone)]
pub struct Inbound {
    /// The line whose key it came on (`fbbus/<line>/...`): on a mutual-TLS bus, the line
    /// zenoh's access control let speak there. The stamp must name the same line.
    pub line: String,
    pub stamp: Stamp,
    pub topic: String,
    pub payload: Vec<u8>,
}

/// A liveliness change seen on the bus (other lines only).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Event {
    LineUp(String),
    LineDown(String),
    InterestAdded {
        line: String,
        filter: String,
    },
    InterestRemoved {
        line: String,
        filter: String,
    },
    /// A registry record another line put (its device changed).
    Record {
        line: String,
        device: String,
        json: Vec<u8>,
    },
    /// Line `line` counted `lost` more of this line's messages as lost on the way (see
    /// [`super::LossReport`]).
    LossReported {
        line: String,
        lost: u64,
    },
    /// Another line forgot its device (a zenoh delete of the device's record key).
    Forgotten {
        line: String,
        device: String,
    },
}
