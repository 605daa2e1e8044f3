"""An unmodified 4diac FORTE device's MQTT layer, byte for byte on the wire: the
`fbdk[].mqtt[tcp://host:port, clientid, topic]` communication stack of FORTE's PUBLISH_n /
SUBSCRIBE_n function blocks over Eclipse Paho C (MQTTAsync), written from their source.
A raw-socket MQTT client (not paho-python), so every byte is the one FORTE's Paho C sends.

Usage:
  forte_device.py --host 127.0.0.1 --port N --client-id conv2
                  [--pub TOPIC:TYPES]... [--sub TOPIC:TYPES]...
                  [--time-unit ns|ms] [--tz utc|local] [--username U] [--password P]
                  [--keepalive 20] [--no-die-after-send-failure] [--no-v31-fallback]
                  [--reconnect-delay 0.1] [--max-connect-attempts 0]

  TYPES is a comma-separated list of the FB's SD_1..SD_n (publisher) or RD_1..RD_n
  (subscriber) types: BOOL SINT INT DINT LINT USINT UINT UDINT ULINT BYTE WORD DWORD LWORD
  REAL LREAL TIME DATE TIME_OF_DAY (TOD) DATE_AND_TIME (DT) STRING. Empty (`TOPIC:`) is
  a PUBLISH_0 / SUBSCRIBE_0. The topic is everything before the last ':'.
  --time-unit: the unit of DATE, TIME_OF_DAY and DATE_AND_TIME on the wire: `ns` FORTE
  3.x (default), `ms` FORTE 2.x. --tz: how DT#/D# literals map to the epoch: FORTE 3.x
  uses timegm (UTC), FORTE 2.x mktime (the device's local time zone); default `utc` for
  ns, `local` for ms (give `--tz utc` to pin bytes independent of the machine's zone).
  --keepalive: FORTE hard-codes 20 s; other values only to see PINGREQs sooner in tests.
  --reconnect-delay: FORTE reconnects at once, without any delay, after a lost or failed
  connection (a tight loop while the broker is down); the emulator waits this long
  between attempts (0 = FORTE's pace). --max-connect-attempts: stop after that many
  consecutive failures (0 = never stop, like FORTE).

Commands on stdin (one a line):
  pub TOPIC [V1 V2 ...]  REQ on the publisher of TOPIC with these SD values, IEC literals:
                         3, -7, 16#FF, INT#3, TRUE, REAL#1.5, 1.5e3, 'text with $' quote',
                         STRING#'x', T#1s500ms, TIME#-250ms, DT#2026-11-22-12:30:15.250,
                         D#2026-11-22, TOD#12:30:15.250
  init TOPIC             INIT(QI=TRUE) of the publisher of TOPIC again (revives a dead one)
  drop [SECS]            the network goes away: the socket is closed without DISCONNECT,
                         and no connection is attempted for SECS (default 0); then FORTE's
                         reconnect (and resubscribe) behaviour
  kill                   close the socket without DISCONNECT and exit (power cut, kill -9)
  quit                   DISCONNECT and exit (FORTE's MQTTHandler destructor); also on EOF

Lines on stdout:
  connected                         CONNACK 0 received (again after every reconnect)
  connect-failed N REASON           the Nth consecutive failed connection attempt
  disconnected REASON               the connection was lost
  subscribed TOPIC                  SUBACK for that subscriber's SUBSCRIBE
  sent TOPIC HEX                    the publisher sent this payload (CNF, QO=TRUE)
  inited TOPIC                      the publisher was INITed again (INITO, QO=TRUE)
  recv TOPIC V1 V2 ...              a subscriber's IND with QO=TRUE: its RD values, as
                                    typed IEC literals (INT#3 REAL#1.5 'hi' TRUE
                                    T#1s500ms DT#2026-11-22-12:30:15.250 ...)
  corrupted TOPIC LEN               a message longer than the 255-byte receive buffer
                                    arrived; only its first 255 bytes reach the decoder
  pending TOPIC LEN                 the decoder kept LEN bytes and raised no event (FORTE's
                                    fbdk layer waits for the rest of a value: a truncated
                                    message wedges the subscriber; see below)
  error TOPIC DATA_TYPE_ERROR       IND with QO=FALSE: a tag did not match the RD's type
  error TOPIC SEND_FAILED           CNF with QO=FALSE: REQ while not connected
  error TOPIC NO_SOCKET             CNF with QO=FALSE: REQ on a publisher that died
  error ...                         anything else (bad command, bad literal)

What FORTE does, and where its source says so (eclipse-4diac/4diac-forte: the `release`
branch = 2.0.x, and `develop` = 3.x, as of 2024-10; Paho C: eclipse/paho.mqtt.c, tag
v1.3.12 = Debian 12's libpaho-mqtt1.3, and v1.3.13):

MQTT connection (src/com/mqtt_paho/MQTTHandler.cpp `registerLayer` on 2.x,
MQTTClient.cpp `initClient` on 3.x):
- MQTTAsync_create(address, clientId, MQTTCLIENT_PERSISTENCE_NONE) and
  MQTTAsync_connectOptions_initializer with keepAliveInterval = 20 and cleansession = 1
  (3.x: MQTTClient.h smKeepAliveInterval = 20, smCleanSession = 1). No will is set,
  MQTTVersion stays MQTTVERSION_DEFAULT, so Paho C sends CONNECT "MQTT" level 4 first
  (MQTTAsyncUtils.c: DEFAULT -> MQTTVERSION_3_1_1), flags 0x02 (clean session only;
  MQTTPacketOut.c MQTTPacket_send_connect), keep-alive 20, the client id.
- Username/password only from the -mqttconfig file (MQTTClientConfigParser.cpp): when the
  file has an entry for the endpoint, BOTH pointers are set (either may be ""), so both
  flags 0x80|0x40 are sent; without an entry neither. --username/--password here: giving
  either sends both (the missing one empty).
- The ID is `fbdk[].mqtt[address, clientId, topic]`, split on ',' with surrounding blanks
  trimmed (src/core/utils/parameterParser.cpp). All com FBs with the same address share
  one Paho client: 2.x has one static client for the whole device (a second client id or
  address fails INIT with INVALID_ID); 3.x one per address (MQTTHandler::getClient: same
  address with another client id fails INIT). One connection, one client id.
- Publish: MQTTAsync_sendMessage, qos = 0 (MQTTComLayer.h QOS / MQTT_QOS 0), retained = 0.
  Subscribe: MQTTAsync_subscribe(topic, 0), one subscriber at a time, the next only after
  the previous SUBACK (MQTTHandler::run / CMQTTClient::runClient, "only try subscribe one
  at a time"); all subscribers again after every reconnect (onMqttConnectionLost rebuilds
  mToResubscribe). A SUBACK 0x80 calls onSubscribeFailed, which only wakes the handler
  thread, which subscribes the same layer again at once: endless retries, bounded
  here to 100 in a row (one `error TOPIC SUBSCRIBE_FAILED` line per refusal, then
  `error TOPIC gave up subscribing`).
- Connection lost or connect failed: state NOT_CONNECTED and the handler thread calls
  MQTTAsync_connect again at once (no delay in FORTE). Paho C's MQTTVERSION_DEFAULT: when
  a level-4 attempt fails (CONNACK refusal or the socket closing before CONNACK), Paho C
  <= 1.3.12 retries at once on a new connection with MQTT 3.1 ("MQIsdp", level 3,
  MQTTAsync_checkConn: `MQTTVersion == 4 && MQTTVersion == DEFAULT` means more to try);
  1.3.13 changed that check (`was_connected == 0 && MQTTVersion == MQTTVERSION_3_1`).
  --no-v31-fallback for the 1.3.13 behaviour.
- Keep-alive (Paho C MQTTProtocolClient.c MQTTProtocol_keepalive): PINGREQ when nothing
  was SENT for keepAliveInterval (received traffic does not count); no PINGRESP within
  1.5 x keepAliveInterval (and nothing else received) closes the session, which is a lost
  connection.
- Messages: onMqttMessageArrived hands a message to every layer whose topic is strcmp-equal
  to the message's topic: a subscriber with a wildcard topic subscribes it but never
  matches anything it receives (nothing is delivered).
- MQTTComLayer.h: `mBufferSize = 255`; MQTTComLayer::recvData: `if(paSize > mBufferSize)
  paSize = mBufferSize; //Rest of the message is discarded`. A 0-byte message reaches no
  decoder (processInterrupt skips mUsedBuffer == 0) but still raises IND with QO=TRUE and
  the previous RD values.
- A publish while not connected: MQTTAsync_sendMessage on a client made by MQTTAsync_create
  (createOptions NULL) returns MQTTASYNC_DISCONNECTED (MQTTAsync.c MQTTAsync_send), so
  MQTTComLayer::sendData returns e_ProcessDataSendFailed. That includes REQs before the
  first CONNACK. A write error after a successful call is Paho's business: the REQ reports
  success.
- The publisher stays dead afterwards: CCommFB::executeEvent (src/core/cominfra/commfb.cpp)
  tests `resp & e_Terminated`; e_Terminated is 2 and SEND_FAILED is 7
  (src/core/cominfra/comtypes.h), so the test is true and the FB calls closeConnection(),
  which deletes its com stack (basecommfb.cpp CBaseCommFB::closeConnection). Every later
  REQ finds no stack: e_ProcessDataNoSocket (6, again & 2) with STATUS NO_SOCKET, until
  the FB is INITed again. The Paho client and the other FBs carry on and reconnect.
  --no-die-after-send-failure keeps the publisher alive (not FORTE's behaviour).

fbdk encoding (src/core/cominfra/fbdkasn1layer.cpp and .h, both branches):
- Tag byte e_APPLICATION (0x40) + e_PRIMITIVE (0) + type tag, then the value big-endian
  (serializeValueSimpleDataType reverses the little-endian memory image). Tags (enum
  EDataTypeTags): BOOL 1, SINT 2, INT 3, DINT 4, LINT 5, USINT 6, UINT 7, UDINT 8,
  ULINT 9, REAL 10, LREAL 11, TIME 12, DATE 13, TIME_OF_DAY 14, DATE_AND_TIME 15,
  STRING 16, BYTE 17, WORD 18, DWORD 19, LWORD 20. Sizes (csm_aDataTags, size incl. tag):
  SINT/USINT/BYTE 2, INT/UINT/WORD 3, DINT/UDINT/DWORD/REAL 5, LINT/ULINT/LWORD/LREAL 9,
  DATE/TOD/DT/TIME 9.
- BOOL: no value byte; the tag is 0x41 for TRUE, 0x40 for FALSE (serializeValue subtracts
  e_BOOL_TAG from the tag it already wrote).
- TIME: serializeValueTime writes getInMicroSeconds() as 8 bytes, signed, on both 2.x and
  3.x: MICROseconds (deserializeValueTime: setFromMicroSeconds).
- DATE, TIME_OF_DAY, DATE_AND_TIME: written as the raw 64-bit value FORTE holds. 2.x
  (release: src/core/datatypes/forte_any_date.cpp setDateAndTime) milliseconds, from
  forte_mktime = mktime, i.e. the literal in the device's LOCAL time zone
  (src/arch/forte_architecture_time.h); TIME_OF_DAY ms since midnight
  (forte_time_of_day.cpp). 3.x (develop: forte_any_date.cpp line 48) nanoseconds, from
  forte_timegm (UTC); TIME_OF_DAY ns since midnight (forte_time_of_day.cpp line 93). DT
  and TOD literals are parsed to the millisecond in both (forte_date_and_time.cpp:
  digits past the third are cut).
- STRING: 2-byte big-endian length, then the bytes (serializeValueString).
- No SDs: serializeFBDataPointArray writes the single NULL byte scm_nNull = 5.

fbdk decoding (CFBDKASN1ComLayer::recvData, both branches) is a STREAM decoder built for
TCP: values are decoded one by one into the RDs (mDOPos); a value that is incomplete
(deserializeDataPoint <= 0 but not -2) keeps the rest in mDeserBuf and returns e_Nothing
(no event at all); the next message is appended to it. So a message truncated to 255
bytes leaves the subscriber waiting for the rest of its value, later messages are glued
to it, and once that value completes, the following tag is usually wrong:
DATA_TYPE_ERROR (-2 when a byte has the 0x40 bit but the wrong tag), which does not reset
mDOPos, so every later message fails at the same RD: the subscriber stays broken until
re-INIT. A byte without the 0x40 bit counts as "incomplete" too (e.g. a NULL 0x05 sent to
a subscriber with RDs). A SUBSCRIBE_0 (no RDs) takes any non-empty message, whatever its
bytes, as an IND. This emulator runs exactly that state machine.
"""

import argparse
import calendar
import datetime
import os
import re
import select
import socket
import struct
import sys
import threading
import time
from decimal import Decimal

# ---------------------------------------------------------------- output

_out_lock = threading.Lock()


def out(line):
    with _out_lock:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()


# ---------------------------------------------------------------- types

# name: (tag number, value bytes or None for variable, kind)
TYPES = {
    "BOOL": (1, 0, "bool"),
    "SINT": (2, 1, "int"),
    "INT": (3, 2, "int"),
    "DINT": (4, 4, "int"),
    "LINT": (5, 8, "int"),
    "USINT": (6, 1, "uint"),
    "UINT": (7, 2, "uint"),
    "UDINT": (8, 4, "uint"),
    "ULINT": (9, 8, "uint"),
    "REAL": (10, 4, "real"),
    "LREAL": (11, 8, "real"),
    "TIME": (12, 8, "time"),
    "DATE": (13, 8, "date"),
    "TIME_OF_DAY": (14, 8, "tod"),
    "DATE_AND_TIME": (15, 8, "dt"),
    "STRING": (16, None, "string"),
    "BYTE": (17, 1, "uint"),
    "WORD": (18, 2, "uint"),
    "DWORD": (19, 4, "uint"),
    "LWORD": (20, 8, "uint"),
}
ALIASES = {"TOD": "TIME_OF_DAY", "DT": "DATE_AND_TIME", "LTOD": None, "LDT": None}
# literal prefixes that may precede '#'
PREFIXES = {
    "T": "TIME",
    "D": "DATE",
    "TOD": "TIME_OF_DAY",
    "DT": "DATE_AND_TIME",
}


def type_name(raw):
    name = raw.strip().upper()
    name = ALIASES.get(name, name)
    if name not in TYPES:
        raise ValueError(f"unsupported type {raw!r}")
    return name


class Options:
    time_unit = "ns"  # DATE/TOD/DT: ns (FORTE 3.x) or ms (FORTE 2.x)
    tz = "utc"  # how DT#/D# literals map to the epoch


OPT = Options()


def unit_per_ms():
    return 1_000_000 if OPT.time_unit == "ns" else 1


# ---------------------------------------------------------------- IEC literals in


def strip_prefix(token, tname):
    """Drops a `TYPE#` prefix (INT#3, T#1s, DT#..., STRING#'x'); a base prefix (16#FF)
    is kept for the integer parser."""
    if "#" not in token:
        return token
    head, rest = token.split("#", 1)
    h = head.upper()
    if h in ("2", "8", "16"):
        return token
    if h in TYPES or h in PREFIXES or h in ALIASES:
        return rest
    return token


def parse_int(text):
    t = text.replace("_", "")
    sign = 1
    if t.startswith(("-", "+")):
        sign = -1 if t[0] == "-" else 1
        t = t[1:]
    if "#" in t:
        base, digits = t.split("#", 1)
        return sign * int(digits, int(base))
    return sign * int(t, 10)


def parse_string(text):
    """An IEC STRING literal 'a$'b$$c$N$41' (or a bare word) as bytes."""
    if len(text) >= 2 and text[0] == "'" and text[-1] == "'":
        body = text[1:-1]
    else:
        return text.encode("utf-8")
    res = bytearray()
    i = 0
    while i < len(body):
        c = body[i]
        if c == "$" and i + 1 < len(body):
            n = body[i + 1]
            simple = {"$": b"$", "'": b"'", "L": b"\n", "N": b"\n", "P": b"\f", "R": b"\r", "T": b"\t"}
            if n.upper() in simple:
                res += simple[n.upper()]
                i += 2
                continue
            if i + 2 < len(body) and re.fullmatch(r"[0-9A-Fa-f]{2}", body[i + 1 : i + 3]):
                res.append(int(body[i + 1 : i + 3], 16))
                i += 3
                continue
            raise ValueError(f"bad escape in {text}")
        res += c.encode("utf-8")
        i += 1
    return bytes(res)


DURATION_NS = {"d": 86_400 * 10**9, "h": 3_600 * 10**9, "m": 60 * 10**9, "s": 10**9, "ms": 10**6, "us": 10**3, "ns": 1}


def parse_time_us(text):
    """T#1h2m3s4ms5us, TIME#-1.5s, 1500ms: microseconds, cut toward zero like FORTE's
    getInMicroSeconds on a nanosecond value."""
    t = text.replace("_", "").lower()
    neg = t.startswith("-")
    if t[:1] in "+-":
        t = t[1:]
    total = Decimal(0)
    pos = 0
    while pos < len(t):
        m = re.match(r"(\d+(?:\.\d+)?)(ms|us|ns|d|h|m|s)", t[pos:])
        if not m:
            raise ValueError(f"bad TIME literal {text!r}")
        total += Decimal(m.group(1)) * DURATION_NS[m.group(2)]
        pos += m.end()
    if pos == 0:
        raise ValueError(f"bad TIME literal {text!r}")
    us = int(total) // 1000
    if not -(2**63) <= us < 2**63:
        raise ValueError(f"{text} out of range for TIME")
    return -us if neg else us


def fraction_ms(frac):
    """FORTE's DT/TOD fraction: three digits, shorter padded, longer cut."""
    if not frac:
        return 0
    return int((frac + "000")[:3])


def epoch_seconds(y, mo, d, h, mi, s):
    if OPT.tz == "local":
        return int(time.mktime((y, mo, d, h, mi, s, 0, 0, -1)))
    return calendar.timegm((y, mo, d, h, mi, s, 0, 0, 0))


def parse_dt(text):
    m = re.fullmatch(r"(\d+)-(\d+)-(\d+)-(\d+):(\d+):(\d+)(?:\.(\d+))?", text)
    if not m:
        raise ValueError(f"bad DATE_AND_TIME literal {text!r}")
    y, mo, d, h, mi, s = (int(g) for g in m.groups()[:6])
    ms = epoch_seconds(y, mo, d, h, mi, s) * 1000 + fraction_ms(m.group(7))
    return ms * unit_per_ms()


def parse_date(text):
    m = re.fullmatch(r"(\d+)-(\d+)-(\d+)", text)
    if not m:
        raise ValueError(f"bad DATE literal {text!r}")
    y, mo, d = (int(g) for g in m.groups())
    return epoch_seconds(y, mo, d, 0, 0, 0) * 1000 * unit_per_ms()


def parse_tod(text):
    m = re.fullmatch(r"(\d+):(\d+):(\d+)(?:\.(\d+))?", text)
    if not m:
        raise ValueError(f"bad TIME_OF_DAY literal {text!r}")
    h, mi, s = (int(g) for g in m.groups()[:3])
    ms = (h * 3600 + mi * 60 + s) * 1000 + fraction_ms(m.group(4))
    return ms * unit_per_ms()


def parse_value(tname, token):
    tag, size, kind = TYPES[tname]
    text = strip_prefix(token, tname)
    if kind == "bool":
        u = text.upper()
        if u in ("TRUE", "1"):
            return True
        if u in ("FALSE", "0"):
            return False
        raise ValueError(f"bad BOOL literal {token!r}")
    if kind in ("int", "uint"):
        v = parse_int(text)
        bits = size * 8
        lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if kind == "int" else (0, 2**bits - 1)
        if not lo <= v <= hi:
            raise ValueError(f"{token} out of range for {tname}")
        return v
    if kind == "real":
        v = float(text.replace("_", ""))
        if size == 4:
            struct.pack(">f", v)  # OverflowError for out-of-range
        return v
    if kind == "time":
        return parse_time_us(text)
    if kind == "dt":
        return parse_dt(text)
    if kind == "date":
        return parse_date(text)
    if kind == "tod":
        return parse_tod(text)
    if kind == "string":
        b = parse_string(text)
        if len(b) > 65535:
            raise ValueError("STRING longer than 65535 bytes")
        return b
    raise ValueError(tname)


# ---------------------------------------------------------------- fbdk encode


def encode_value(tname, v):
    tag, size, kind = TYPES[tname]
    t = 0x40 | tag
    if kind == "bool":
        return bytes([t if v else t - 1])
    if kind == "int" or kind == "time":
        return bytes([t]) + v.to_bytes(size, "big", signed=True)
    if kind in ("uint", "date", "tod", "dt"):
        return bytes([t]) + (v % (1 << (8 * size))).to_bytes(size, "big")
    if kind == "real":
        return bytes([t]) + struct.pack(">f" if size == 4 else ">d", v)
    if kind == "string":
        return bytes([t]) + len(v).to_bytes(2, "big") + v
    raise ValueError(tname)


def encode(types, values):
    if not types:
        return b"\x05"  # scm_nNull
    return b"".join(encode_value(t, v) for t, v in zip(types, values))


# ---------------------------------------------------------------- IEC literals out


def real_literal(v, size):
    if v != v or v in (float("inf"), float("-inf")):
        return repr(v)
    if size == 8:
        return repr(v)
    packed = struct.pack(">f", v)
    for p in range(1, 10):
        s = "%.*g" % (p, v)
        if struct.pack(">f", float(s)) == packed:
            break
    if "e" not in s and "." not in s and "n" not in s:
        s += ".0"
    return s


def time_literal(us):
    if us == 0:
        return "T#0s"
    sign = "-" if us < 0 else ""
    rest = abs(us)
    parts = []
    for unit, n in (("d", 86_400_000_000), ("h", 3_600_000_000), ("m", 60_000_000), ("s", 1_000_000), ("ms", 1000), ("us", 1)):
        q, rest = divmod(rest, n)
        if q:
            parts.append(f"{q}{unit}")
    return f"T#{sign}{''.join(parts)}"


def split_unit(raw):
    """(milliseconds, sub-millisecond remainder in the wire unit)"""
    per = unit_per_ms()
    return divmod(raw, per)


def frac_text(ms, sub):
    text = f"{ms % 1000:03d}"
    if sub:
        text += f"{sub:06d}".rstrip("0")
    return text


def utc_or_local(seconds):
    if OPT.tz == "local":
        return datetime.datetime.fromtimestamp(seconds)
    return datetime.datetime(1970, 1, 1) + datetime.timedelta(seconds=seconds)


def format_value(tname, v):
    tag, size, kind = TYPES[tname]
    if kind == "bool":
        return "TRUE" if v else "FALSE"
    if kind in ("int", "uint"):
        return f"{tname}#{v}"
    if kind == "real":
        return f"{tname}#{real_literal(v, size)}"
    if kind == "time":
        return time_literal(v)
    if kind == "string":
        res = "'"
        for b in v:
            c = chr(b)
            if c == "$":
                res += "$$"
            elif c == "'":
                res += "$'"
            elif 0x20 <= b < 0x7F:
                res += c
            else:
                res += f"${b:02X}"
        return res + "'"
    ms, sub = split_unit(v)
    if kind == "tod":
        s = ms // 1000
        return f"TOD#{s // 3600:02d}:{s // 60 % 60:02d}:{s % 60:02d}.{frac_text(ms, sub)}"
    d = utc_or_local(ms // 1000)
    if kind == "date":
        if d.hour == d.minute == d.second == 0 and ms % 1000 == 0 and sub == 0:
            return f"D#{d:%Y-%m-%d}"
        return f"DATE#{v}"  # not a midnight: the raw wire value
    return f"DT#{d:%Y-%m-%d-%H:%M:%S}.{frac_text(ms, sub)}"


# ---------------------------------------------------------------- fbdk decode (stream)

OK, NOTHING, DTYPE = "ok", "nothing", "dtype"


def initial_value(tname):
    kind = TYPES[tname][2]
    return {"bool": False, "real": 0.0, "string": b""}.get(kind, 0)


class FbdkSubscriber:
    """CFBDKASN1ComLayer::recvData of one SUBSCRIBE_n, state and all."""

    def __init__(self, topic, types):
        self.topic = topic
        self.types = types
        self.rds = [initial_value(t) for t in types]
        self.deser_buf = b""
        self.deser_buf_pos = 0
        self.do_pos = 0
        self.sub_failures = 0

    def deserialize_data_point(self, buf, i):
        """FORTE's deserializeDataPoint: bytes used, 0 or -1 incomplete, -2 wrong tag."""
        if len(buf) == 0 or (buf[0] & 0x40) != 0x40:
            return -1
        tname = self.types[i]
        tag, size, kind = TYPES[tname]
        b0 = buf[0]
        if kind == "bool":
            if b0 not in (0x40, 0x41):
                return -2
            self.rds[i] = b0 == 0x41
            return 1
        if b0 != (0x40 | tag):
            return -2
        body = buf[1:]
        if kind == "string":
            if len(body) < 2:
                return 0
            n = (body[0] << 8) | body[1]
            if len(body) < n + 2:
                return 0
            self.rds[i] = bytes(body[2 : 2 + n])
            return 1 + 2 + n
        if len(body) < size:
            return 0
        raw = bytes(body[:size])
        if kind == "int" or kind == "time":
            self.rds[i] = int.from_bytes(raw, "big", signed=True)
        elif kind == "real":
            self.rds[i] = struct.unpack(">f" if size == 4 else ">d", raw)[0]
        else:
            self.rds[i] = int.from_bytes(raw, "big")
        return 1 + size

    def recv(self, data):
        num_rd = len(self.types)
        ret = NOTHING
        if self.deser_buf_pos == 0:
            used = bytes(data)
        else:
            self.deser_buf = self.deser_buf[: self.deser_buf_pos] + bytes(data)
            self.deser_buf_pos += len(data)
            used = self.deser_buf[: self.deser_buf_pos]
        off = 0
        size = len(used)
        while size != 0:
            if num_rd == 0:
                nbuf = 1
            else:
                nbuf = self.deserialize_data_point(used[off : off + size], self.do_pos)
            if nbuf <= 0:
                if nbuf == -2:
                    ret = DTYPE
                    break
                if self.deser_buf_pos == 0:
                    self.deser_buf = used[off : off + size]
                    self.deser_buf_pos = size
                nbuf = size
            else:
                self.do_pos += 1
                self.deser_buf_pos = 0
            size -= nbuf
            off += nbuf
            if self.do_pos >= num_rd:
                self.do_pos = 0
                ret = OK
        return ret

    def values_text(self):
        return " ".join(format_value(t, v) for t, v in zip(self.types, self.rds))


class Publisher:
    def __init__(self, topic, types):
        self.topic = topic
        self.types = types
        self.dead = False


# ---------------------------------------------------------------- MQTT wire


def utf(s):
    b = s.encode("utf-8") if isinstance(s, str) else s
    return len(b).to_bytes(2, "big") + b


def packet(first, body):
    n = len(body)
    rl = bytearray()
    while True:
        d = n % 128
        n //= 128
        rl.append(d | (0x80 if n else 0))
        if not n:
            break
    return bytes([first]) + bytes(rl) + body


def connect_packet(client_id, keepalive, level, username, password):
    """Paho C MQTTPacket_send_connect."""
    vh = (utf("MQTT") + b"\x04") if level == 4 else (utf("MQIsdp") + b"\x03")
    flags = 0x02  # cleansession = 1, no will
    if username is not None:
        flags |= 0x80
    if password is not None:
        flags |= 0x40
    vh += bytes([flags]) + keepalive.to_bytes(2, "big")
    body = vh + utf(client_id)
    if username is not None:
        body += utf(username)
    if password is not None:
        body += utf(password)
    return packet(0x10, body)


class PacketReader:
    def __init__(self):
        self.buf = b""

    def feed(self, data):
        self.buf += data
        packets = []
        while True:
            if len(self.buf) < 2:
                break
            mult, n, i = 1, 0, 1
            while True:
                if i >= len(self.buf):
                    return packets
                b = self.buf[i]
                n += (b & 0x7F) * mult
                mult *= 128
                i += 1
                if not b & 0x80:
                    break
                if i > 4:
                    raise ValueError("bad remaining length")
            if len(self.buf) < i + n:
                break
            packets.append((self.buf[0], self.buf[i : i + n]))
            self.buf = self.buf[i + n :]
        return packets


MAX_SUBSCRIBE_RETRIES = 100


class Lost(Exception):
    pass


class Device:
    def __init__(self, args, pubs, subs):
        self.args = args
        self.pubs = pubs
        self.subs = subs
        self.lock = threading.RLock()
        self.sock = None
        self.connected = False
        self.stopping = False
        self.drop_until = 0.0
        self.msgid = 0
        self.last_sent = 0.0
        self.last_received = 0.0
        self.ping_outstanding = False
        self.last_ping = 0.0
        self.to_resubscribe = []
        self.sub_inflight = None
        self.session = 0

    # -- sending

    def next_msgid(self):
        self.msgid = self.msgid % 65535 + 1
        return self.msgid

    def write(self, data):
        with self.lock:
            s = self.sock
            if s is None:
                raise Lost("no socket")
            try:
                s.sendall(data)
            except OSError as e:
                raise Lost(f"write: {e}") from e
            self.last_sent = time.monotonic()

    # -- connecting

    def connect_once(self, level):
        """One Paho C connect attempt; the socket on success, else raises Lost."""
        a = self.args
        try:
            s = socket.create_connection((a.host, a.port), timeout=30)
        except OSError as e:
            raise Lost(f"tcp: {e}") from e
        try:
            s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            s.sendall(connect_packet(a.client_id, a.keepalive, level, a.username_eff, a.password_eff))
            reader = PacketReader()
            deadline = time.monotonic() + 30
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise Lost("no CONNACK in 30 s")
                s.settimeout(left)
                data = s.recv(4096)
                if not data:
                    raise Lost("closed before CONNACK")
                packets = reader.feed(data)
                if packets:
                    first, body = packets[0]
                    if first >> 4 != 2 or len(body) < 2:
                        raise Lost(f"expected CONNACK, got packet type {first >> 4}")
                    if body[1] != 0:
                        raise Lost(f"CONNACK {body[1]}")
                    s.settimeout(None)
                    return s, reader, packets[1:]
        except Lost:
            s.close()
            raise
        except OSError as e:
            s.close()
            raise Lost(f"connect: {e}") from e

    def run(self):
        failures = 0
        while not self.stopping:
            wait = self.drop_until - time.monotonic()
            if wait > 0:
                time.sleep(min(wait, 0.2))
                continue
            try:
                try:
                    s, reader, early = self.connect_once(4)
                except Lost:
                    if not self.args.v31_fallback or self.stopping:
                        raise
                    s, reader, early = self.connect_once(3)
            except Lost as e:
                if self.stopping:
                    return
                failures += 1
                out(f"connect-failed {failures} {e}")
                if self.args.max_connect_attempts and failures >= self.args.max_connect_attempts:
                    out("error gave up connecting")
                    return
                time.sleep(self.args.reconnect_delay)
                continue
            failures = 0
            with self.lock:
                if self.stopping:
                    s.close()
                    return
                self.sock = s
                now = time.monotonic()
                self.last_sent = now
                self.last_received = now
                self.ping_outstanding = False
                self.to_resubscribe = list(self.subs)
                self.sub_inflight = None
                self.connected = True
                self.session += 1
                session = self.session
            out("connected")
            reason = self.session_loop(s, reader, early, session)
            with self.lock:
                if self.session != session:
                    reason = "dropped"  # `drop` closed the socket under the reader
                if self.sock is s:
                    self.sock = None
                    self.connected = False
                try:
                    s.close()
                except OSError:
                    pass
            if self.stopping:
                return
            out(f"disconnected {reason}")
            time.sleep(self.args.reconnect_delay)

    def session_loop(self, s, reader, early, session):
        ka = self.args.keepalive
        pending = list(early)
        while True:
            try:
                for first, body in pending:
                    self.handle(first, body)
                pending = []
                with self.lock:
                    if self.session != session or self.sock is not s:
                        return "dropped"
                    if self.sub_inflight is None and self.to_resubscribe:
                        layer = self.to_resubscribe[0]
                        mid = self.next_msgid()
                        self.sub_inflight = (mid, layer)
                        self.write(packet(0x82, mid.to_bytes(2, "big") + utf(layer.topic) + b"\x00"))
                try:
                    r, _, _ = select.select([s], [], [], 0.2)
                except (OSError, ValueError):
                    return "dropped"
                if r:
                    try:
                        data = s.recv(65536)
                    except OSError as e:
                        return f"read: {e}"
                    if not data:
                        return "closed by the broker"
                    self.last_received = time.monotonic()
                    pending = reader.feed(data)
                now = time.monotonic()
                if ka > 0:
                    if self.ping_outstanding:
                        if now - self.last_ping >= 1.5 * ka and now - self.last_received >= 1.5 * ka:
                            return "PINGRESP not received in keepalive interval"
                    elif now - self.last_sent >= ka:
                        self.write(b"\xc0\x00")
                        self.ping_outstanding = True
                        self.last_ping = now
            except Lost as e:
                return str(e)

    def handle(self, first, body):
        kind = first >> 4
        if kind == 3:  # PUBLISH
            qos = (first >> 1) & 3
            n = (body[0] << 8) | body[1]
            topic = body[2 : 2 + n].decode("utf-8", "replace")
            pos = 2 + n
            if qos:
                mid = body[pos : pos + 2]
                pos += 2
                self.write(packet(0x40 if qos == 1 else 0x50, mid))
            self.deliver(topic, body[pos:])
        elif kind == 6:  # PUBREL
            self.write(packet(0x70, body[:2]))
        elif kind == 9:  # SUBACK
            mid = (body[0] << 8) | body[1]
            with self.lock:
                inflight = self.sub_inflight
                if inflight and inflight[0] == mid:
                    self.sub_inflight = None
                    layer = inflight[1]
                    if body[2:3] == b"\x80":
                        # FORTE subscribes the same layer again at once, forever; bounded here
                        layer.sub_failures += 1
                        out(f"error {layer.topic} SUBSCRIBE_FAILED")
                        if layer.sub_failures >= MAX_SUBSCRIBE_RETRIES:
                            self.to_resubscribe.remove(layer)
                            out(f"error {layer.topic} gave up subscribing")
                    else:
                        layer.sub_failures = 0
                        if layer in self.to_resubscribe:
                            self.to_resubscribe.remove(layer)
                        out(f"subscribed {layer.topic}")
        elif kind == 13:  # PINGRESP
            self.ping_outstanding = False

    def deliver(self, topic, payload):
        for layer in self.subs:
            if layer.topic != topic:  # strcmp, no wildcard matching
                continue
            size = len(payload)
            if size > 255:
                out(f"corrupted {topic} {size}")
                size = 255
            if size == 0:
                out(f"recv {topic} {layer.values_text()}".rstrip())
                continue
            res = layer.recv(payload[:size])
            if res == OK:
                out(f"recv {topic} {layer.values_text()}".rstrip())
            elif res == DTYPE:
                out(f"error {topic} DATA_TYPE_ERROR")
            else:
                out(f"pending {topic} {layer.deser_buf_pos}")

    # -- commands

    def publish(self, topic, tokens):
        layer = next((p for p in self.pubs if p.topic == topic), None)
        if layer is None:
            out(f"error {topic} no publisher on this topic")
            return
        if layer.dead:
            out(f"error {topic} NO_SOCKET")
            return
        if len(tokens) != len(layer.types):
            out(f"error {topic} {len(layer.types)} values expected, got {len(tokens)}")
            return
        try:
            values = [parse_value(t, v) for t, v in zip(layer.types, tokens)]
            payload = encode(layer.types, values)
        except (ValueError, OverflowError) as e:
            out(f"error {topic} bad literal: {e}")
            return
        with self.lock:
            if not self.connected:
                if self.args.die_after_send_failure:
                    layer.dead = True
                out(f"error {topic} SEND_FAILED")
                return
            body = utf(topic) + payload
            try:
                self.write(packet(0x30, body))
            except Lost:
                pass  # Paho's send thread hits the error; MQTTAsync_sendMessage returned 0
        out(f"sent {topic} {payload.hex()}")

    def init(self, topic):
        layer = next((p for p in self.pubs if p.topic == topic), None)
        if layer is None:
            out(f"error {topic} no publisher on this topic")
            return
        layer.dead = False
        out(f"inited {topic}")

    def drop(self, secs):
        with self.lock:
            self.drop_until = time.monotonic() + secs
            s = self.sock
            self.sock = None
            self.connected = False
            self.session += 1
            if s is not None:
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def finish(self, graceful):
        with self.lock:
            self.stopping = True
            s = self.sock
            if s is not None:
                if graceful and self.connected:
                    try:
                        s.sendall(b"\xe0\x00")
                    except OSError:
                        pass
                try:
                    s.close()
                except OSError:
                    pass
        os._exit(0)


# ---------------------------------------------------------------- control


def tokenize(line):
    """Whitespace-separated tokens; '...' IEC strings (with $-escapes) stay one token."""
    tokens = []
    i = 0
    n = len(line)
    while i < n:
        if line[i].isspace():
            i += 1
            continue
        start = i
        while i < n and not line[i].isspace():
            if line[i] == "'":
                i += 1
                while i < n and line[i] != "'":
                    i += 2 if line[i] == "$" else 1
                i += 1
            else:
                i += 1
        tokens.append(line[start:i])
    return tokens


def port_spec(text):
    if ":" not in text:
        raise argparse.ArgumentTypeError(f"{text!r}: TOPIC:TYPES expected")
    topic, types = text.rsplit(":", 1)
    names = [type_name(t) for t in types.split(",") if t.strip()] if types.strip() else []
    return topic, names


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, required=True)
    p.add_argument("--client-id", required=True)
    p.add_argument("--pub", action="append", default=[], type=port_spec)
    p.add_argument("--sub", action="append", default=[], type=port_spec)
    p.add_argument("--time-unit", choices=["ns", "ms"], default="ns")
    p.add_argument("--tz", choices=["utc", "local"])
    p.add_argument("--username")
    p.add_argument("--password")
    p.add_argument("--keepalive", type=int, default=20)
    p.add_argument("--die-after-send-failure", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--v31-fallback", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--reconnect-delay", type=float, default=0.1)
    p.add_argument("--max-connect-attempts", type=int, default=0)
    args = p.parse_args()
    OPT.time_unit = args.time_unit
    OPT.tz = args.tz or ("utc" if args.time_unit == "ns" else "local")
    if args.username is not None or args.password is not None:
        args.username_eff = args.username or ""
        args.password_eff = args.password or ""
    else:
        args.username_eff = args.password_eff = None

    pubs = [Publisher(t, ty) for t, ty in args.pub]
    subs = [FbdkSubscriber(t, ty) for t, ty in args.sub]
    dev = Device(args, pubs, subs)
    threading.Thread(target=dev.run, daemon=True).start()

    for line in sys.stdin:
        tokens = tokenize(line.strip())
        if not tokens:
            continue
        cmd = tokens[0].lower()
        if cmd == "pub" and len(tokens) >= 2:
            dev.publish(tokens[1], tokens[2:])
        elif cmd == "init" and len(tokens) == 2:
            dev.init(tokens[1])
        elif cmd == "drop":
            try:
                secs = float(tokens[1]) if len(tokens) > 1 else 0.0
            except ValueError:
                out(f"error bad command: {line.strip()}")
                continue
            dev.drop(secs)
        elif cmd == "kill":
            dev.finish(graceful=False)
        elif cmd == "quit":
            dev.finish(graceful=True)
        else:
            out(f"error bad command: {line.strip()}")
    dev.finish(graceful=True)


if __name__ == "__main__":
    main()
