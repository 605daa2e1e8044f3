//! The store's log (`broker::store`, issue 17) on arbitrary bytes: a file on disk is
//! outside input (a torn write, a disk error, someone's edit). Framing, checksums, every
//! record type's decoder (a stored message is decoded by rumqttd's v5 codec), the replay
//! that rebuilds retained messages, sessions and queues under limits, and a compaction of
//! the result, which must rebuild the same state. No input may panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = broker::store::replay_for_fuzzing(data);
});
