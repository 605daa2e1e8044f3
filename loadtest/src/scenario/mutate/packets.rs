//! The packets a `mutate` connection sends: valid CONNECTs and session packets of every
//! kind, and their byte-level and semantic flaws, each drawn from the connection's own
//! generator.

use crate::rng::Rng;
use crate::scenario::campaign::{self, Ctx};
use crate::wire::{self, prop, Connect, Props, Will, V311, V5};

use super::{Label, State, BAD_FILTERS, BAD_UTF8, DECLARATIONS, FILTERS, TOPICS, TYPED_PAYLOADS};

/// A valid CONNECT at `level` (the login the harness was given, if any).
pub(super) fn gen_connect(rng: &mut Rng, ctx: &Ctx, i: u64, level: u8) -> Connect {
    let prefix = &ctx.prefix;
    let id: Vec<u8> = match rng.below(100) {
        0..=69 => format!("{prefix}-m{}-{i}", ctx.seed).into_bytes(),
        // A few ids shared by many connections: takeovers, sometimes of a live one.
        70..=79 => format!("{prefix}-m-shared-{}", rng.below(8)).into_bytes(),
        80..=84 => Vec::new(),
        85..=89 => format!("é-Förderband-🚀-{i}").into_bytes(),
        90..=94 => format!("{prefix}-dev-{}", rng.below(16)).into_bytes(),
        _ => format!("{prefix}-{i}-{}", "x".repeat(rng.range(50, 300) as usize)).into_bytes(),
    };
    let mut c = Connect::new(level, id);
    // MQTT 3.1.1 refuses an empty client id unless the session is clean.
    c.clean = (c.client_id.is_empty() && level != V5) || rng.chance(0.85);
    c.keep_alive = *rng.pick(&[0u16, 1, 5, 30, 60, 65_535]);
    if level == V5 {
        let mut props = Props::new();
        if !c.clean || rng.chance(0.2) {
            props = props.u32(prop::SESSION_EXPIRY, *rng.pick(&[0u32, 10, 300, u32::MAX]));
        }
        if rng.chance(0.2) {
            props = props.u16(prop::RECEIVE_MAXIMUM, rng.range(1, 100) as u16);
        }
        if rng.chance(0.1) {
            props = props.u32(prop::MAX_PACKET_SIZE, *rng.pick(&[64u32, 128, 1 << 20]));
        }
        if rng.chance(0.2) {
            props = props.u16(prop::TOPIC_ALIAS_MAXIMUM, rng.below(10) as u16);
        }
        if rng.chance(0.1) {
            props = props.byte(prop::REQUEST_PROBLEM_INFO, rng.below(2) as u8);
        }
        if rng.chance(0.1) {
            props = props.pair(
                prop::USER_PROPERTY,
                "schlüssel".as_bytes(),
                "wért 🚀".as_bytes(),
            );
        }
        c.properties = props;
    }
    if rng.chance(0.2) {
        let mut properties = Props::new();
        if level == V5 && rng.chance(0.3) {
            properties = properties.u32(prop::WILL_DELAY, rng.below(3) as u32);
        }
        c.will = Some(Will {
            topic: rng.pick(TOPICS).as_bytes().to_vec(),
            payload: format!("will of {i}").into_bytes(),
            qos: rng.below(3) as u8,
            retain: rng.chance(0.1),
            properties,
        });
    }
    let (user, password) = ctx.login();
    if user.is_some() {
        (c.username, c.password) = (user, password);
    } else if rng.chance(0.05) {
        c.username = Some("nutzer-é".as_bytes().to_vec());
        c.password = Some(rng.bytes(8));
    }
    c
}

/// A CONNECT with a semantic flaw.
pub(super) fn semantic_connect(rng: &mut Rng, connect: &Connect) -> (Vec<u8>, &'static str) {
    let mut c = connect.clone();
    match rng.below(6) {
        0 => {
            c.client_id = rng.pick(BAD_UTF8).to_vec();
            (c.encode(), "mutation_invalid_utf8_client_id")
        }
        1 => {
            c.will = Some(Will {
                topic: rng.pick(BAD_UTF8).to_vec(),
                payload: b"w".to_vec(),
                qos: 1,
                retain: false,
                properties: Props::new(),
            });
            (c.encode(), "mutation_invalid_utf8_will_topic")
        }
        2 => {
            c.will = Some(Will {
                topic: rng.pick(&["#", "+/x", "a/#"]).as_bytes().to_vec(),
                payload: b"w".to_vec(),
                qos: 3,
                retain: true,
                properties: Props::new(),
            });
            (c.encode(), "mutation_will_wildcard_qos3")
        }
        3 => {
            // Password without username (forbidden in 3.1.1), reserved flag bit.
            let mut bytes = c.encode();
            let flags = wire::header_len(&bytes) + 7;
            if let Some(f) = bytes.get_mut(flags) {
                *f = (*f & !0x80) | 0x40 | u8::from(rng.chance(0.5));
            }
            (bytes, "mutation_connect_flags")
        }
        4 => {
            c.level = V5;
            c.properties = bad_properties(rng);
            (c.encode(), "mutation_bad_properties")
        }
        _ => {
            c.username = Some(rng.pick(BAD_UTF8).to_vec());
            c.password = Some(vec![0xFF; rng.range(0, 70_000) as usize]);
            (c.encode(), "mutation_invalid_login")
        }
    }
}

/// MQTT 5 properties that are wrong: duplicated, not allowed here, unknown, truncated.
fn bad_properties(rng: &mut Rng) -> Props {
    match rng.below(6) {
        0 => Props::new()
            .u32(prop::SESSION_EXPIRY, 1)
            .u32(prop::SESSION_EXPIRY, 2),
        1 => Props::new().varint(prop::SUBSCRIPTION_ID, 0),
        2 => Props::new().raw(&[0x7F, 1, 2, 3]),
        3 => Props::new().raw(&[prop::USER_PROPERTY, 0xFF, 0xFF, b'a']),
        4 => Props::new().string(prop::AUTH_METHOD, "SCRAM-SHA-1".as_bytes()),
        _ => Props::new().u16(prop::TOPIC_ALIAS, 0),
    }
}

/// The next packet of a session with its mutation's label: a valid packet, or, when
/// `mutated`, a flawed one: a third generated flawed ([`flawed_packet`]), the rest a
/// valid packet with a byte-level mutation ([`wire::mutate`]).
pub(super) fn next_packet(
    rng: &mut Rng,
    ctx: &Ctx,
    st: &mut State,
    i: u64,
    mutated: bool,
) -> (Vec<u8>, Option<&'static str>) {
    if mutated && rng.chance(0.35) {
        let (pkt, label) = flawed_packet(rng, ctx, st, i);
        return (pkt, Some(label));
    }
    let mut pkt = valid_packet(rng, ctx, st, i);
    let label = mutated.then(|| wire::mutate(rng, &mut pkt).label());
    (pkt, label)
}

/// A valid packet of a session: PUBLISH, SUBSCRIBE, UNSUBSCRIBE, an ack, PINGREQ, an fbbus
/// declaration or typed publication.
pub(super) fn valid_packet(rng: &mut Rng, ctx: &Ctx, st: &mut State, i: u64) -> Vec<u8> {
    match rng.weighted(&[40, 20, 8, 15, 8, 5]) {
        0 => publish(rng, ctx, st, i, false).0,
        1 => subscribe(rng, ctx, st, i, false).0,
        2 => {
            let n = rng.range(1, 3) as usize;
            let filters: Vec<Vec<u8>> = (0..n)
                .map(|_| rng.pick(FILTERS).as_bytes().to_vec())
                .collect();
            wire::unsubscribe(st.level, campaign::pid(rng), &Props::new(), &filters)
        }
        3 => ack(rng, st, false).0,
        4 => wire::pingreq(),
        _ => declaration_or_typed(rng, ctx, st),
    }
}

/// A packet that is well-formed bytes but wrong: a flawed PUBLISH or SUBSCRIBE, an ack
/// for packet id 0, a second CONNECT, junk, an unexpected AUTH, DISCONNECT then more.
fn flawed_packet(rng: &mut Rng, ctx: &Ctx, st: &mut State, i: u64) -> (Vec<u8>, &'static str) {
    let level = st.level;
    let flawed =
        |(pkt, label): (Vec<u8>, Option<&'static str>)| (pkt, label.unwrap_or("mutation_flawed"));
    match rng.weighted(&[30, 20, 10, 15, 10, 5, 10]) {
        0 => flawed(publish(rng, ctx, st, i, true)),
        1 => flawed(subscribe(rng, ctx, st, i, true)),
        2 => flawed(ack(rng, st, true)),
        3 => {
            // A second CONNECT on the same connection: a protocol violation.
            let again = gen_connect(rng, ctx, i, if level == V5 { V5 } else { V311 });
            (again.encode(), "mutation_second_connect")
        }
        5 if level == V5 => {
            let props = Props::new().string(prop::AUTH_METHOD, "SCRAM-SHA-1".as_bytes());
            (
                wire::auth(*rng.pick(&[0x18u8, 0x19]), &props),
                "mutation_unexpected_auth",
            )
        }
        6 => (
            wire::disconnect(level, None),
            "mutation_disconnect_then_more",
        ),
        _ => {
            let n = rng.range(1, 32) as usize;
            (rng.bytes(n), "mutation_junk")
        }
    }
}

fn subscribe(
    rng: &mut Rng,
    ctx: &Ctx,
    st: &State,
    i: u64,
    flaw: bool,
) -> (Vec<u8>, Option<&'static str>) {
    let level = st.level;
    let n = rng.range(1, 4) as usize;
    let mut filters = Vec::with_capacity(n);
    let mut label = None;
    for _ in 0..n {
        let f: Vec<u8> = if flaw && label.is_none() {
            if rng.chance(0.5) {
                label = Some("mutation_invalid_filter");
                rng.pick(BAD_FILTERS).as_bytes().to_vec()
            } else {
                label = Some("mutation_invalid_utf8_filter");
                rng.pick(BAD_UTF8).to_vec()
            }
        } else if rng.chance(0.15) {
            format!("{}/m/{i}/+", ctx.prefix).into_bytes()
        } else {
            rng.pick(FILTERS).as_bytes().to_vec()
        };
        let mut options = rng.below(3) as u8;
        if level == V5 {
            options |=
                (rng.below(2) as u8) << 2 | (rng.below(2) as u8) << 3 | (rng.below(3) as u8) << 4;
        }
        filters.push((f, options));
    }
    let mut props = Props::new();
    if level == V5 && rng.chance(0.2) {
        props = props.varint(prop::SUBSCRIPTION_ID, rng.range(1, 1000));
    }
    (
        wire::subscribe(level, campaign::pid(rng), &props, &filters),
        label,
    )
}

/// PUBACK, PUBREC, PUBREL or PUBCOMP, often for a packet id this session used; `flaw`:
/// for packet id 0.
fn ack(rng: &mut Rng, st: &State, flaw: bool) -> (Vec<u8>, Option<&'static str>) {
    let first = *rng.pick(&[0x40u8, 0x50, 0x62, 0x70]);
    if flaw {
        return (
            wire::ack(first, st.level, 0, None),
            Some("mutation_packet_id_zero"),
        );
    }
    let pid = if !st.pids.is_empty() && rng.chance(0.5) {
        *rng.pick(&st.pids)
    } else {
        campaign::pid(rng)
    };
    let reason = rng
        .chance(0.3)
        .then(|| *rng.pick(&[0x00u8, 0x10, 0x80, 0x92]));
    (wire::ack(first, st.level, pid, reason), None)
}

fn publish(
    rng: &mut Rng,
    ctx: &Ctx,
    st: &mut State,
    i: u64,
    flaw: bool,
) -> (Vec<u8>, Option<&'static str>) {
    let level = st.level;
    let mut label = None;
    let mut qos = *rng.pick(&[0u8, 0, 0, 0, 0, 1, 1, 1, 2, 2]);
    let pooled = rng.chance(0.85);
    let mut topic: Vec<u8> = if pooled {
        rng.pick(TOPICS).as_bytes().to_vec()
    } else {
        format!("{}/m/{i}/{}", ctx.prefix, rng.below(4)).into_bytes()
    };
    // Retained only on the fixed topics: the broker's retained store stays bounded.
    let retain = pooled && rng.chance(0.05);
    let mut payload: Vec<u8> = match rng.below(20) {
        0..=11 => {
            let n = rng.range(0, 64) as usize;
            rng.bytes(n)
        }
        12..=15 => format!("{{\"seq\":{i},\"ts\":{}}}", rng.below(1 << 40)).into_bytes(),
        16..=18 => "Förderband läuft 🚀 ✓".as_bytes().to_vec(),
        _ => {
            let n = rng.range(1024, 4096) as usize;
            rng.bytes(n)
        }
    };
    let mut props = Props::new();
    let mut pid = campaign::pid(rng);
    if flaw {
        match rng.below(6) {
            0 | 1 => {
                topic = rng.pick(BAD_UTF8).to_vec();
                label = Some("mutation_invalid_utf8_topic");
            }
            2 => {
                topic = rng.pick(&["#", "a/+", "+", "é/#"]).as_bytes().to_vec();
                label = Some("mutation_wildcard_topic");
            }
            3 => {
                qos = 3;
                label = Some("mutation_qos3");
            }
            4 => {
                payload = vec![b'x'; 70_000];
                label = Some("mutation_oversized_payload");
            }
            _ => {
                if level == V5 {
                    props = bad_properties(rng);
                    label = Some("mutation_bad_properties");
                } else {
                    qos = 1;
                    pid = 0;
                    label = Some("mutation_packet_id_zero");
                }
            }
        }
    } else if level == V5 && rng.chance(0.3) {
        props = match rng.below(7) {
            0 => Props::new()
                .byte(prop::PAYLOAD_FORMAT, 1)
                .string(prop::CONTENT_TYPE, "text/plain; charset=utf-8".as_bytes()),
            1 => Props::new().u32(prop::MESSAGE_EXPIRY, rng.range(1, 60) as u32),
            2 => Props::new()
                .string(prop::RESPONSE_TOPIC, "antwort/é".as_bytes())
                .string(prop::CORRELATION_DATA, &rng.bytes(8)),
            3 => Props::new().pair(prop::USER_PROPERTY, "ключ".as_bytes(), "値".as_bytes()),
            _ => {
                // Topic aliases: set one, or use one set before with an empty topic.
                if !st.aliases.is_empty() && rng.chance(0.5) {
                    topic.clear();
                    Props::new().u16(prop::TOPIC_ALIAS, *rng.pick(&st.aliases))
                } else {
                    let alias = rng.range(1, 4) as u16;
                    st.aliases.push(alias);
                    Props::new().u16(prop::TOPIC_ALIAS, alias)
                }
            }
        };
        if !payload.is_empty() && rng.chance(0.2) {
            // Payload format "UTF-8" on bytes that may not be.
            props = props.byte(prop::PAYLOAD_FORMAT, 1);
        }
    }
    if qos > 0 && pid != 0 {
        st.pids.push(pid);
    }
    let dup = qos > 0 && rng.chance(0.05);
    (
        wire::publish(level, &topic, qos, retain, dup, pid, &props, &payload),
        label,
    )
}

/// An fbbus declaration or a publication on a typed FB topic, for this connection's
/// device id (only the `-dev-` ids declare, so the registry stays bounded).
fn declaration_or_typed(rng: &mut Rng, ctx: &Ctx, st: &State) -> Vec<u8> {
    let id = String::from_utf8_lossy(&st.client_id).into_owned();
    let device = if id.contains("-dev-") {
        id
    } else {
        format!("{}-dev-{}", ctx.prefix, rng.below(16))
    };
    let (topic, payload) = if rng.chance(0.4) {
        (
            format!("fbbus/declare/{device}"),
            rng.pick(DECLARATIONS).as_bytes().to_vec(),
        )
    } else {
        let ns = *rng.pick(&["fb", "fbdk", "dinasore"]);
        let port = *rng.pick(&["CONV/SPEED", "FÖRDER/Ö", "CONV/CNF", "CONV", "X/Y/Z"]);
        (
            format!("{ns}/{device}/{port}"),
            rng.pick(TYPED_PAYLOADS).to_vec(),
        )
    };
    let qos = rng.below(2) as u8;
    let pid = campaign::pid(rng);
    wire::publish(
        st.level,
        topic.as_bytes(),
        qos,
        false,
        false,
        pid,
        &Props::new(),
        &payload,
    )
}
