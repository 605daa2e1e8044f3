//! `mutate`: a bounded random-mutation campaign over the network, against any MQTT
//! broker.
//!
//! Each of `--connections` connections opens TCP, sends an MQTT 3.1.1 or 5 CONNECT (valid,
//! or with probability `--mutate-prob` mutated; 3 % start with something that is not a
//! CONNECT at all), waits briefly for the answer, then sends 0 to `--max-packets` packets
//! of a real session — SUBSCRIBE (`#`, `+`, `$share/...`, multi-byte filters),
//! PUBLISH at QoS 0/1/2 on topics such as `é/x`, `Förderband/1`, `🚀/launch`, acks,
//! PINGREQ, UNSUBSCRIBE, a second CONNECT, fbbus declarations and typed topics, AUTH —
//! each mutated with probability `--mutate-prob`, and ends it with DISCONNECT, a close,
//! a reset, or half a packet then a reset.
//!
//! A mutation is byte-level ([`wire::Mutation`]: bit flips, inserted or deleted bytes,
//! truncation, a corrupted remaining length, a 5-byte varint, a 256 MB length, a random
//! packet type, corrupted flags, a corrupted string length, the packet twice) or, for a
//! third of them, semantic: invalid UTF-8 in a topic or filter (lone continuation bytes,
//! overlong forms, surrogates, U+0000, a multi-byte character cut in half), an invalid
//! filter (`a/#/b`, `$share//x`), QoS 3, packet identifier 0, forbidden or truncated
//! MQTT 5 properties, a payload above 64 KiB. Every label is counted in the report
//! (`mutation_*`).
//!
//! See [`campaign`] for the rounds, the routing probe, memory and the
//! verdict.

use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::campaign::{self, Campaign, Close, Conn, Ctx, Outcome, Start};
use crate::rng::Rng;
use crate::session::Session;
use crate::target::Target;
use crate::wire::{self, V311, V5};

mod packets;

use packets::{gen_connect, next_packet, semantic_connect, valid_packet};

/// `mutate`'s parameters.
#[derive(Debug, Clone, Serialize)]
pub struct Mutate {
    #[serde(flatten)]
    pub campaign: Campaign,
    /// Probability that a packet (CONNECT included) is mutated.
    pub mutate_prob: f64,
    /// Packets after the CONNECT, at most (0 to this, uniformly).
    pub max_packets: u64,
}

/// This campaign's generator stream (see [`Rng::for_item`]).
const STREAM: u64 = 1;

/// Valid topics, many with multi-byte characters at every level and position.
pub const TOPICS: &[&str] = &[
    "é/x",
    "x/é",
    "é",
    "Förderband/1",
    "Förderband/Ölstand/ä",
    "🚀/launch",
    "line/🏭/cell-7",
    "日本/ライン/3",
    "𝕄𝕢𝕥𝕥/4-byte",
    "e\u{301}/combining",
    "zero\u{200b}width/x",
    "a/b/c",
    "x",
    "/leading",
    "trailing/",
    "a//b",
    "ä/ö/ü/ß",
    "Ω",
    "fb/plc-1/CONV/SPEED",
    "fbdk/plc-1/CONV/SPEED",
    "dinasore/plc-1/CONV",
    "fbbus/diag/plc-1",
    "$SYS/broker/x",
    "$é/x",
];

/// Valid filters: wildcards, shared subscriptions, `$` topics, multi-byte levels.
pub const FILTERS: &[&str] = &[
    "#",
    "+",
    "+/+",
    "+/#",
    "é/#",
    "é/+",
    "+/é",
    "Förderband/+",
    "+/1",
    "🚀/#",
    "日本/+/3",
    "$share/g/#",
    "$share/grüppe/é/+",
    "$share/g/+/x",
    "$SYS/#",
    "$é/#",
    "fb/+/+/+",
    "fbdk/#",
    "a/+/c",
    "/#",
    "+/+/+/+/+",
    "x",
    "é/x",
];

/// Filters no broker may grant.
const BAD_FILTERS: &[&str] = &[
    "a/#/b",
    "a+",
    "#/x",
    "+x/y",
    "$share//x",
    "$share/g",
    "$share/+/x",
    "é#",
    "",
    "$share/g/",
];

/// Not UTF-8, or UTF-8 that MQTT forbids (U+0000).
const BAD_UTF8: &[&[u8]] = &[
    b"\xC3\x28/x",
    b"a/\x80",
    b"\xFF\xFE",
    b"\xC0\xAF",
    b"\xED\xA0\x80/surrogate",
    b"\xF4\x90\x80\x80",
    b"nul\x00byte",
    b"\xE2\x82",
    b"F\xC3rderband/1",
    b"\xC3",
    b"#\xC3",
];

/// Interface declarations for fbbus/declare/<id>, good and bad.
const DECLARATIONS: &[&str] = &[
    r#"{"fbs":{"CONV":{"data_out":{"SPEED":"INT"}}}}"#,
    r#"{"fbs":{"FÖRDER":{"data_out":{"Ö":"WSTRING","É":"REAL"}}}}"#,
    r#"{"fbs":{"CONV":{"event_out":{"CNF":["SPEED"]},"data_out":{"SPEED":"DINT"}}}}"#,
    r#"{"fbs":{"CONV":{"data_out":{"SPEED":"NOTATYPE"}}}}"#,
    r##"{"fbs":{"#":{"data_out":{"+":"INT"}}}}"##,
    r#"{"fbs":"#,
    r#"[]"#,
    r#"{"fbs":{"A":{"data_out":{"X":"STRING[99999999]"}}}}"#,
];

/// Payloads for typed FB topics.
const TYPED_PAYLOADS: &[&[u8]] = &[
    b"3",
    b"70000",
    b"-32769",
    b"\"\xC3\xA9\"",
    b"{}",
    b"{\"SPEED\":1}",
    b"1e400",
    b"",
    b"\x43\x00\x03",
    b"\xFF\xFF\xFF",
];

/// What a connection's session remembers for its next packets.
struct State {
    level: u8,
    client_id: Vec<u8>,
    /// Packet identifiers it used for QoS 1/2 publications.
    pids: Vec<u16>,
    /// Topic aliases it set (MQTT 5).
    aliases: Vec<u16>,
}

impl Mutate {
    pub fn planned(&self, targets: usize) -> u64 {
        rounds(&self.campaign) * targets as u64
    }

    pub async fn run(&self, s: &mut Session, targets: &[Target], prefix: &str) -> Vec<String> {
        let (p, max_packets) = (self.mutate_prob, self.max_packets);
        campaign::run(
            s,
            targets,
            prefix,
            &self.campaign,
            "mutate",
            move |ctx, i| connection(ctx, i, p, max_packets),
        )
        .await
    }
}

/// Rounds of a campaign (for the progress bar).
pub fn rounds(c: &Campaign) -> u64 {
    match c.probe_every {
        0 => 1,
        n => c.connections.div_ceil(n).max(1),
    }
}

/// Everything connection `i` will send, drawn from its own generator before it connects:
/// what the broker answers never changes the bytes, so a seed repeats a campaign.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Plan {
    pub first: Vec<u8>,
    /// Labels of the first packet's mutations (empty: a valid CONNECT).
    pub first_labels: Vec<&'static str>,
    /// The first packet goes out in two writes, split here, `split_pause_ms` apart.
    pub split: Option<usize>,
    pub split_pause_ms: u64,
    /// CONNECT, the session and the DISCONNECT in one write, as a client that does not
    /// wait for the CONNACK (MQTT allows it: 3.1.4).
    pub pipelined: bool,
    /// The session's packets, each with its mutation's label.
    pub packets: Vec<(Vec<u8>, Option<&'static str>)>,
    pub close: Close,
    /// Sent last: DISCONNECT (`Close::Disconnect`) or part of a packet (`MidPacket`).
    pub tail: Vec<u8>,
}

/// The plan of connection `i`.
pub fn plan(ctx: &Ctx, i: u64, p: f64, max_packets: u64) -> Plan {
    let mut rng = Rng::for_item(ctx.seed, STREAM, i);
    let level = match rng.below(100) {
        0..=47 => V311,
        48..=95 => V5,
        _ => *rng.pick(&[0u8, 3, 6, 255]),
    };
    let connect = gen_connect(&mut rng, ctx, i, level);
    let mut st = State {
        level,
        client_id: connect.client_id.clone(),
        pids: Vec::new(),
        aliases: Vec::new(),
    };
    let mut first = connect.encode();
    let mut first_labels = Vec::new();
    if level != V311 && level != V5 {
        first_labels.push("mutation_protocol_level");
    }
    if rng.below(100) < 3 {
        // Not a CONNECT first: a session packet or junk.
        first = if rng.chance(0.5) {
            first_labels.push("mutation_not_connect_first");
            valid_packet(&mut rng, ctx, &mut st, i)
        } else {
            first_labels.push("mutation_junk_first");
            let n = rng.range(1, 64) as usize;
            rng.bytes(n)
        };
    } else if rng.chance(p) {
        if rng.chance(0.3) {
            let (bytes, label) = semantic_connect(&mut rng, &connect);
            first = bytes;
            first_labels.push(label);
        } else {
            first_labels.push(wire::mutate(&mut rng, &mut first).label());
        }
    }
    // Sometimes in two writes, as a slow client's CONNECT arrives.
    let split =
        (first.len() > 4 && rng.chance(0.1)).then(|| rng.range(1, first.len() as u64 - 1) as usize);
    let split_pause_ms = rng.range(1, 20);
    let pipelined = split.is_none() && rng.chance(0.1);
    let packets = (0..rng.range(0, max_packets))
        .map(|_| {
            let mutated = rng.chance(p);
            next_packet(&mut rng, ctx, &mut st, i, mutated)
        })
        .collect();
    let close = match rng.below(100) {
        0..=39 => Close::Disconnect,
        40..=59 => Close::Drop,
        60..=79 => Close::Reset,
        _ => Close::MidPacket,
    };
    let tail = match close {
        Close::Disconnect => {
            let reason =
                (level == V5 && rng.chance(0.3)).then(|| *rng.pick(&[0x00, 0x04, 0x80, 0x8E]));
            wire::disconnect(level, reason)
        }
        Close::MidPacket => {
            let mut pkt = valid_packet(&mut rng, ctx, &mut st, i);
            let cut = if pkt.len() > 1 {
                rng.range(1, pkt.len() as u64 - 1) as usize
            } else {
                0
            };
            pkt.truncate(cut);
            pkt
        }
        Close::Drop | Close::Reset => Vec::new(),
    };
    Plan {
        first,
        first_labels,
        split,
        split_pause_ms,
        pipelined,
        packets,
        close,
        tail,
    }
}

/// Connection `i` of the campaign: its [`Plan`], sent; whatever the broker answers, read.
pub async fn connection(ctx: Arc<Ctx>, i: u64, p: f64, max_packets: u64) -> Outcome {
    let plan = plan(&ctx, i, p, max_packets);
    let mut o = Outcome::default();
    let connect_mutated = !plan.first_labels.is_empty();
    o.valid_connect = !connect_mutated;
    let Ok(mut conn) = Conn::open(&ctx, i).await else {
        o.start = Start::TcpFailed;
        return o;
    };
    for l in &plan.first_labels {
        o.label(l);
    }
    if plan.pipelined {
        return pipelined(&ctx, &plan, conn, o).await;
    }
    let sent = Instant::now();
    let whole = match plan.split {
        Some(at) => {
            conn.send(&mut o, &plan.first[..at]).await && {
                tokio::time::sleep(Duration::from_millis(plan.split_pause_ms)).await;
                conn.packet(&mut o, &plan.first[at..], connect_mutated)
                    .await
            }
        }
        None => conn.packet(&mut o, &plan.first, connect_mutated).await,
    };
    if !whole {
        o.start = Start::ClosedWithoutAnswer;
        o.closed_by_broker = true;
        return o;
    }
    await_connack(&ctx, &mut conn, &mut o, sent, connect_mutated).await;
    if conn.closed {
        o.closed_by_broker = true;
        return o;
    }

    for (pkt, label) in &plan.packets {
        if !conn.packet(&mut o, pkt, label.is_some()).await {
            break;
        }
        if let Some(l) = label {
            o.label(l);
        }
        conn.drain(&mut o);
        if conn.closed {
            break;
        }
    }

    match plan.close {
        Close::Disconnect => {
            conn.packet(&mut o, &plan.tail, false).await;
        }
        Close::MidPacket if !plan.tail.is_empty() => {
            o.partial += u64::from(conn.send(&mut o, &plan.tail).await);
        }
        _ => {}
    }
    conn.close(&mut o, plan.close, ctx.read).await;
    o
}

/// A pipelined plan: everything in one write, then the answers. A valid one (nothing
/// mutated, ending with DISCONNECT) must see the broker close the connection within
/// `--read-ms` of the CONNACK: `pipelined_valid_closed`, else `pipelined_valid_left_open`
/// (the broker did not act on packets that came with the CONNECT).
/// Waits for the broker's answer to the CONNECT: as long as a CONNACK may take for a valid
/// one, the short read time for a mutated one; labels mutated CONNECTs it accepted.
async fn await_connack(
    ctx: &Ctx,
    conn: &mut Conn,
    o: &mut Outcome,
    sent: Instant,
    connect_mutated: bool,
) {
    let wait = if o.valid_connect {
        ctx.connack
    } else {
        ctx.read
    };
    conn.await_answer(o, wait, sent).await;
    if connect_mutated && o.start == Start::Accepted {
        // Not necessarily wrong (a flipped bit in a client id is still a client id), but
        // worth a look: which mutations of a CONNECT did the broker accept?
        o.label("mutated_connects_accepted");
    }
}

async fn pipelined(ctx: &Ctx, plan: &Plan, mut conn: Conn, mut o: Outcome) -> Outcome {
    o.label("pipelined");
    let mut bytes = plan.first.clone();
    for (p, _) in &plan.packets {
        bytes.extend_from_slice(p);
    }
    bytes.extend_from_slice(&plan.tail);
    let sent = Instant::now();
    if !conn.send(&mut o, &bytes).await {
        o.start = Start::ClosedWithoutAnswer;
        o.closed_by_broker = true;
        return o;
    }
    let connect_mutated = !plan.first_labels.is_empty();
    o.packets += 1 + plan.packets.len() as u64;
    o.mutated += u64::from(connect_mutated);
    for (_, label) in &plan.packets {
        if let Some(l) = label {
            o.mutated += 1;
            o.label(l);
        }
    }
    match plan.close {
        Close::Disconnect => o.packets += 1,
        Close::MidPacket if !plan.tail.is_empty() => o.partial += 1,
        _ => {}
    }
    let valid = !connect_mutated
        && plan.packets.iter().all(|(_, l)| l.is_none())
        && plan.close == Close::Disconnect;
    await_connack(ctx, &mut conn, &mut o, sent, connect_mutated).await;
    let accepted = o.start == Start::Accepted;
    let closed = conn.close(&mut o, plan.close, ctx.read).await;
    if valid && accepted {
        o.label(if closed {
            "pipelined_valid_closed"
        } else {
            "pipelined_valid_left_open"
        });
    }
    o
}

/// Labels of byte-level mutations in the report.
trait Label {
    fn label(self) -> &'static str;
}

impl Label for wire::Mutation {
    fn label(self) -> &'static str {
        match self {
            wire::Mutation::BitFlip => "mutation_bit_flip",
            wire::Mutation::InsertBytes => "mutation_insert_bytes",
            wire::Mutation::DeleteBytes => "mutation_delete_bytes",
            wire::Mutation::Truncate => "mutation_truncate",
            wire::Mutation::LengthField => "mutation_length_field",
            wire::Mutation::VarintOverflow => "mutation_varint_overflow",
            wire::Mutation::OversizedLength => "mutation_oversized_length",
            wire::Mutation::PacketType => "mutation_packet_type",
            wire::Mutation::Flags => "mutation_flags",
            wire::Mutation::StringLength => "mutation_string_length",
            wire::Mutation::Duplicate => "mutation_duplicate",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_seed_gives_the_same_plans_and_another_seed_others() {
        let a = campaign::test_ctx(7);
        let plans: Vec<Plan> = (0..300).map(|i| plan(&a, i, 0.3, 8)).collect();
        let again: Vec<Plan> = (0..300).rev().map(|i| plan(&a, i, 0.3, 8)).collect();
        assert!(plans.iter().eq(again.iter().rev()), "order does not matter");
        let b = campaign::test_ctx(8);
        let other: Vec<Plan> = (0..300).map(|i| plan(&b, i, 0.3, 8)).collect();
        assert_ne!(plans, other);
        // Some plans mutate their CONNECT, some close mid-packet, most send packets.
        assert!(plans.iter().any(|p| !p.first_labels.is_empty()));
        assert!(plans.iter().any(|p| p.first_labels.is_empty()));
        assert!(plans
            .iter()
            .any(|p| p.close == Close::MidPacket && !p.tail.is_empty()));
        assert!(plans.iter().any(|p| p.pipelined));
        let packets: usize = plans.iter().map(|p| p.packets.len()).sum();
        assert!(packets > 300, "{packets}");
        // With probability 0 no packet of a session is mutated (the first packet still is
        // in 3 % + 4 %: no CONNECT at all, an unknown protocol level).
        let clean: Vec<Plan> = (0..300).map(|i| plan(&a, i, 0.0, 8)).collect();
        assert!(clean
            .iter()
            .all(|p| p.packets.iter().all(|(_, l)| l.is_none())));
        let odd_first = clean.iter().filter(|p| !p.first_labels.is_empty()).count();
        assert!(odd_first < 40, "{odd_first}");
        // With probability 1 every one is.
        let all: Vec<Plan> = (0..100).map(|i| plan(&a, i, 1.0, 8)).collect();
        assert!(all.iter().all(|p| !p.first_labels.is_empty()));
        assert!(all
            .iter()
            .all(|p| p.packets.iter().all(|(_, l)| l.is_some())));
    }

    #[test]
    fn topics_and_filters_are_valid_utf8_and_bad_ones_are_not() {
        for t in TOPICS.iter().chain(FILTERS) {
            assert!(!t.contains('\0'), "{t}");
        }
        assert!(
            TOPICS.iter().any(|t| t.len() != t.chars().count()),
            "multi-byte topics"
        );
        for b in BAD_UTF8 {
            let s = std::str::from_utf8(b);
            assert!(s.is_err() || s.unwrap().contains('\0'), "{b:?} is valid");
        }
    }
}
