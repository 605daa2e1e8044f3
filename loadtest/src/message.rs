//! The load message: an fbbus event with no data, `{"seq":N,"ts":T}`, padded with JSON
//! whitespace to the requested size.
//!
//! It is a valid event of the port `LOAD.MSG` (see [`crate::contract`]), so fbbus
//! type-checks it like any device's event, and any other broker just carries bytes. `seq`
//! numbers a publisher's messages from 1 (loss, duplicates and order are counted from
//! it); `ts` is when the message was published, or was due to be published in an
//! open-loop run, in [`crate::clock`] microseconds. Whitespace padding keeps the message
//! valid JSON at every size. The smallest message is 31 bytes (`{"seq":1,"ts":` + 16
//! digits + `}`); a smaller requested size (the study's 30 bytes) is rounded up to it.

/// Bytes of a message with a one-digit seq and a 16-digit timestamp: the floor of
/// `--payload`.
pub const MIN_SIZE: usize = 31;

/// The message for `seq` published at `ts`, at least `size` bytes.
pub fn encode(seq: u64, ts: u64, size: usize) -> Vec<u8> {
    let mut out = format!("{{\"seq\":{seq},\"ts\":{ts}").into_bytes();
    if out.len() + 1 < size {
        out.resize(size - 1, b' ');
    }
    out.push(b'}');
    out
}

/// `(seq, ts)` of a message, or `None` if it is not one. Reads the keys wherever they
/// are, so a broker that re-serializes the JSON is still understood.
pub fn decode(payload: &[u8]) -> Option<(u64, u64)> {
    Some((
        number_after(payload, b"\"seq\":")?,
        number_after(payload, b"\"ts\":")?,
    ))
}

fn number_after(payload: &[u8], key: &[u8]) -> Option<u64> {
    let at = payload.windows(key.len()).position(|w| w == key)? + key.len();
    let digits = payload[at..]
        .iter()
        .skip_while(|b| **b == b' ')
        .take_while(|b| b.is_ascii_digit());
    let mut value: u64 = 0;
    let mut any = false;
    for d in digits {
        value = value.checked_mul(10)?.checked_add(u64::from(d - b'0'))?;
        any = true;
    }
    any.then_some(value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_at_every_size_and_stays_json() {
        for size in [0, 30, 31, 40, 1000] {
            let m = encode(7, 1_763_800_000_123_456, size);
            assert_eq!(m.len(), size.max(MIN_SIZE));
            assert_eq!(decode(&m), Some((7, 1_763_800_000_123_456)));
            let json: serde_json::Value = serde_json::from_slice(&m).unwrap();
            assert_eq!(json["seq"], 7);
        }
        assert_eq!(encode(123_456, 1_763_800_000_123_456, 30).len(), 36);
    }

    #[test]
    fn reads_re_serialized_messages_and_refuses_others() {
        assert_eq!(decode(br#"{"ts": 5, "seq": 9}"#), Some((9, 5)));
        assert_eq!(decode(b"hello"), None);
        assert_eq!(decode(br#"{"seq":"x","ts":1}"#), None);
        assert_eq!(decode(br#"{"seq":99999999999999999999999,"ts":1}"#), None);
    }
}
