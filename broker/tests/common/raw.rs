//! Hand-built MQTT packets, for what a well-behaved client library will not send:
//! silence after CONNECT, malformed bytes, oversized packets.
#![allow(dead_code)]

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Duration;

fn remaining_length(mut len: usize, out: &mut Vec<u8>) {
    loop {
        let mut byte = (len % 128) as u8;
        len /= 128;
        if len > 0 {
            byte |= 0x80;
        }
        out.push(byte);
        if len == 0 {
            break;
        }
    }
}

fn string(s: &[u8], out: &mut Vec<u8>) {
    out.extend_from_slice(&(s.len() as u16).to_be_bytes());
    out.extend_from_slice(s);
}

pub fn packet(byte1: u8, body: &[u8]) -> Vec<u8> {
    let mut out = vec![byte1];
    remaining_length(body.len(), &mut out);
    out.extend_from_slice(body);
    out
}

pub struct Connect<'a> {
    pub version: u8,
    pub client_id: &'a str,
    pub keep_alive: u16,
    pub clean: bool,
    pub will: Option<(&'a str, &'a [u8])>,
    pub login: Option<(&'a str, &'a str)>,
    /// MQTT 5 only: session expiry interval property (seconds).
    pub session_expiry: Option<u32>,
    /// MQTT 5 only: will delay interval property (seconds).
    pub will_delay: Option<u32>,
    /// MQTT 5 only: the client's Maximum Packet Size property.
    pub max_packet_size: Option<u32>,
    /// MQTT 5 only: the client's Receive Maximum property.
    pub receive_maximum: Option<u16>,
    /// MQTT 5 only: the client's Topic Alias Maximum property.
    pub topic_alias_max: Option<u16>,
    /// MQTT 5 only: the will's User Properties, in order.
    pub will_user_properties: &'a [(&'a str, &'a str)],
}

impl Default for Connect<'_> {
    fn default() -> Self {
        Connect {
            version: 4,
            client_id: "raw",
            keep_alive: 60,
            clean: true,
            will: None,
            login: None,
            session_expiry: None,
            will_delay: None,
            max_packet_size: None,
            receive_maximum: None,
            topic_alias_max: None,
            will_user_properties: &[],
        }
    }
}

impl Connect<'_> {
    pub fn bytes(&self) -> Vec<u8> {
        let mut body = Vec::new();
        string(b"MQTT", &mut body);
        body.push(self.version);
        let mut flags = 0u8;
        if self.clean {
            flags |= 0x02;
        }
        if self.will.is_some() {
            flags |= 0x04;
        }
        if self.login.is_some() {
            flags |= 0xC0;
        }
        body.push(flags);
        body.extend_from_slice(&self.keep_alive.to_be_bytes());
        if self.version == 5 {
            let mut props = Vec::new();
            if let Some(s) = self.session_expiry {
                props.push(0x11);
                props.extend_from_slice(&s.to_be_bytes());
            }
            if let Some(m) = self.max_packet_size {
                props.push(0x27);
                props.extend_from_slice(&m.to_be_bytes());
            }
            if let Some(m) = self.receive_maximum {
                props.push(0x21);
                props.extend_from_slice(&m.to_be_bytes());
            }
            if let Some(m) = self.topic_alias_max {
                props.push(0x22);
                props.extend_from_slice(&m.to_be_bytes());
            }
            body.push(props.len() as u8);
            body.extend_from_slice(&props);
        }
        string(self.client_id.as_bytes(), &mut body);
        if let Some((topic, payload)) = self.will {
            if self.version == 5 {
                let mut props = Vec::new();
                if let Some(d) = self.will_delay {
                    props.push(0x18);
                    props.extend_from_slice(&d.to_be_bytes());
                }
                props.extend_from_slice(&user_properties(self.will_user_properties));
                remaining_length(props.len(), &mut body);
                body.extend_from_slice(&props);
            }
            string(topic.as_bytes(), &mut body);
            string(payload, &mut body);
        }
        if let Some((user, pass)) = self.login {
            string(user.as_bytes(), &mut body);
            string(pass.as_bytes(), &mut body);
        }
        packet(0x10, &body)
    }
}

/// MQTT 5 User Property entries (0x26), in order.
pub fn user_properties(pairs: &[(&str, &str)]) -> Vec<u8> {
    let mut out = Vec::new();
    for (k, v) in pairs {
        out.push(0x26);
        string(k.as_bytes(), &mut out);
        string(v.as_bytes(), &mut out);
    }
    out
}

/// An MQTT 5 PUBLISH body split up: (topic, packet id, property bytes, payload).
pub fn parse_publish_v5(byte1: u8, body: &[u8]) -> (Vec<u8>, u16, Vec<u8>, Vec<u8>) {
    let topic_len = u16::from_be_bytes([body[0], body[1]]) as usize;
    let topic = body[2..2 + topic_len].to_vec();
    let mut at = 2 + topic_len;
    let mut pkid = 0;
    if (byte1 >> 1) & 3 > 0 {
        pkid = u16::from_be_bytes([body[at], body[at + 1]]);
        at += 2;
    }
    let (mut len, mut shift) = (0usize, 0);
    loop {
        let b = body[at];
        at += 1;
        len |= ((b & 0x7f) as usize) << shift;
        shift += 7;
        if b & 0x80 == 0 {
            break;
        }
    }
    let props = body[at..at + len].to_vec();
    (topic, pkid, props, body[at + len..].to_vec())
}

pub fn publish_qos0(topic: &str, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    string(topic.as_bytes(), &mut body);
    body.extend_from_slice(payload);
    packet(0x30, &body)
}

/// An MQTT 5 PUBLISH with an optional topic alias property.
pub fn publish_v5(topic: &str, alias: Option<u16>, qos: u8, pkid: u16, payload: &[u8]) -> Vec<u8> {
    let mut body = Vec::new();
    string(topic.as_bytes(), &mut body);
    if qos > 0 {
        body.extend_from_slice(&pkid.to_be_bytes());
    }
    match alias {
        Some(a) => {
            body.push(3);
            body.push(0x23);
            body.extend_from_slice(&a.to_be_bytes());
        }
        None => body.push(0),
    }
    body.extend_from_slice(payload);
    packet(0x30 | (qos << 1), &body)
}

pub const DISCONNECT: [u8; 2] = [0xE0, 0x00];
pub const PINGREQ: [u8; 2] = [0xC0, 0x00];

/// SUBSCRIBE for `filters` at QoS 0 (MQTT 5 adds an empty property list).
pub fn subscribe(version: u8, pkid: u16, filters: &[&str]) -> Vec<u8> {
    let mut body = pkid.to_be_bytes().to_vec();
    if version == 5 {
        body.push(0);
    }
    for f in filters {
        string(f.as_bytes(), &mut body);
        body.push(0);
    }
    packet(0x82, &body)
}

/// MQTT 5 SUBSCRIBE of one filter with an explicit options byte (QoS in bits 0-1, No Local
/// bit 2, Retain As Published bit 3, Retain Handling bits 4-5).
pub fn subscribe_with_options(pkid: u16, filter: &str, options: u8) -> Vec<u8> {
    let mut body = pkid.to_be_bytes().to_vec();
    body.push(0);
    string(filter.as_bytes(), &mut body);
    body.push(options);
    packet(0x82, &body)
}

/// The reason codes of a SUBACK body.
pub fn suback_codes(version: u8, body: &[u8]) -> Vec<u8> {
    let skip = if version == 5 {
        3 + body[2] as usize
    } else {
        2
    };
    body[skip..].to_vec()
}

/// A raw TCP connection to the broker.
pub struct RawClient {
    pub stream: TcpStream,
}

impl RawClient {
    pub fn connect(port: u16) -> RawClient {
        let stream = TcpStream::connect(("127.0.0.1", port)).unwrap();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        RawClient { stream }
    }

    /// A connection to `broker` from the loopback address `source` (127.0.0.0/8: a
    /// broker that counts per address sees another host).
    pub fn connect_from(broker: std::net::SocketAddr, source: &str) -> RawClient {
        let socket =
            socket2::Socket::new(socket2::Domain::IPV4, socket2::Type::STREAM, None).unwrap();
        let local: std::net::SocketAddr = format!("{source}:0").parse().unwrap();
        socket.bind(&local.into()).unwrap();
        socket.connect(&broker.into()).unwrap();
        let stream: TcpStream = socket.into();
        stream
            .set_read_timeout(Some(Duration::from_secs(10)))
            .unwrap();
        RawClient { stream }
    }

    pub fn send(&mut self, bytes: &[u8]) {
        self.stream.write_all(bytes).unwrap();
    }

    /// Reads one packet: (first byte, body). None when the broker closed the connection.
    pub fn read_packet(&mut self) -> Option<(u8, Vec<u8>)> {
        let mut byte1 = [0u8; 1];
        self.stream.read_exact(&mut byte1).ok()?;
        let mut len = 0usize;
        let mut shift = 0;
        loop {
            let mut b = [0u8; 1];
            self.stream.read_exact(&mut b).ok()?;
            len |= ((b[0] & 0x7f) as usize) << shift;
            shift += 7;
            if b[0] & 0x80 == 0 {
                break;
            }
        }
        let mut body = vec![0u8; len];
        self.stream.read_exact(&mut body).ok()?;
        Some((byte1[0], body))
    }

    /// Sends CONNECT and returns the CONNACK return code.
    pub fn handshake(&mut self, connect: &Connect) -> u8 {
        self.send(&connect.bytes());
        let (byte1, body) = self.read_packet().expect("CONNACK");
        assert_eq!(byte1, 0x20, "expected CONNACK");
        body[1]
    }

    /// True once the broker has closed the connection (reads until EOF, skipping packets).
    pub fn closed_by_broker(&mut self) -> bool {
        loop {
            match self.read_packet() {
                Some(_) => continue,
                None => return true,
            }
        }
    }
}
