#!/usr/bin/env python3
"""Writes the seeds of the store_replay fuzz target (seeds/store_replay/): store logs as
broker/src/store/log.rs and record.rs write them, in format 2 (records with the file's
mark and a CRC-32) and format 1, whole, with a damaged byte, cut in half, both. Every
record type, QoS 1 and 2 deliveries at each step. Deterministic; run from anywhere:
    python3 broker/fuzz/seeds/store_log.py
"""
import os
import struct
import zlib

HERE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "store_replay")
MARK = bytes([0x5A, 0xC3, 0x17, 0x9E])  # any four distinct bytes, none 0x00 or 0xFF

SESSION, OFFLINE, ENDED, SUBSCRIBE, UNSUBSCRIBE, PUBLISH, QUEUED, DONE, QOS2, WILL, WILL_DONE = range(1, 12)


def s(text):
    b = text.encode()
    return struct.pack("<H", len(b)) + b


def message(topic, payload, qos, retain=False, publisher="press-1"):
    t = topic.encode()
    var = struct.pack(">H", len(t)) + t + (struct.pack(">H", 1) if qos else b"") + b"\x00"
    rest = len(var) + len(payload)
    length = b""
    while True:
        byte, rest = rest % 128, rest // 128
        length += bytes([byte | (0x80 if rest else 0)])
        if not rest:
            break
    packet = bytes([0x30 | int(retain) | qos << 1]) + length + var + payload
    return struct.pack("<I", len(packet)) + packet + s(publisher)


def history():
    r = []
    r.append(bytes([SESSION]) + s("hmi-1") + s("alice") + bytes([0b11, 1]) + struct.pack("<I", 300))
    r.append(bytes([SUBSCRIBE]) + s("hmi-1") + s("line/#") + bytes([2, 0]) + struct.pack("<I", 0))
    r.append(bytes([SESSION]) + s("mes") + s("") + bytes([0b10, 0]))
    r.append(bytes([SUBSCRIBE]) + s("mes") + s("line/+") + bytes([1, 1]) + struct.pack("<I", 7))
    r.append(bytes([SUBSCRIBE]) + s("mes") + s("x/#") + bytes([0, 0]) + struct.pack("<I", 0))
    r.append(bytes([UNSUBSCRIBE]) + s("mes") + s("x/#"))
    for seq in range(1, 13):
        qos = 1 if seq % 3 == 0 else 2
        r.append(bytes([PUBLISH]) + struct.pack("<Q", seq)
                 + message("line/press", b"m%d" % seq, qos, retain=seq % 5 == 0))
        if seq > 2:
            d = seq - 2
            if d % 3:
                r.append(bytes([QOS2]) + s("hmi-1") + struct.pack("<Q", d) + b"\x01" + struct.pack("<H", d))
                if d != 4:
                    r.append(bytes([QOS2]) + s("hmi-1") + struct.pack("<Q", d) + b"\x02" + struct.pack("<H", d))
            if d not in (4, 5):
                r.append(bytes([DONE]) + s("hmi-1") + struct.pack("<Q", d))
            r.append(bytes([DONE]) + s("mes") + struct.pack("<Q", d))
    r.append(bytes([OFFLINE]) + s("mes") + struct.pack("<Q", 1_700_000_000) + b"\x00")
    r.append(bytes([QUEUED]) + struct.pack("<Q", 20) + message("line/oven", b"q", 2)
             + struct.pack("<I", 2) + s("hmi-1") + b"\x02\x02" + struct.pack("<H", 9)
             + s("mes") + b"\x01\x00")
    r.append(bytes([WILL]) + s("plc-2") + struct.pack("<Q", 1_700_000_500_000)
             + message("fb/plc-2/state", b"offline", 1, retain=True, publisher="plc-2"))
    r.append(bytes([WILL_DONE]) + s("plc-2"))
    r.append(bytes([ENDED]) + s("old"))
    return r


def v2(records):
    head = b"FBBUSLOG" + struct.pack("<I", 2) + MARK
    out = head + struct.pack("<I", zlib.crc32(head))
    for body in records:
        frame = MARK + struct.pack("<I", len(body))
        out += frame + struct.pack("<I", zlib.crc32(frame + body)) + body
    return out


def v1(records):
    out = b"FBBUSLOG" + struct.pack("<I", 1)
    for body in records:
        out += struct.pack("<II", len(body), zlib.crc32(body)) + body
    return out


def flip(data, at, bit=0x10):
    return data[:at] + bytes([data[at] ^ bit]) + data[at + 1:]


def main():
    os.makedirs(HERE, exist_ok=True)
    records = history()
    whole = v2(records)
    half = len(whole) // 2
    seeds = {
        "v2-whole.store": whole,
        "v2-damaged-byte.store": flip(whole, half),
        "v2-damaged-length.store": flip(whole, whole.index(MARK, half) + 5, 0x80),
        "v2-cut-in-half.store": whole[:half],
        "v2-damaged-and-cut.store": flip(whole, len(whole) // 3)[: 3 * len(whole) // 4],
        "v2-damaged-header-mark.store": flip(whole, 13),
        "v2-zeroed-block.store": whole[:half] + bytes(64) + whole[half + 64:],
        "v1-whole.store": v1(records),
        "v1-cut-in-half.store": v1(records)[: len(v1(records)) // 2],
    }
    for name, data in seeds.items():
        with open(os.path.join(HERE, name), "wb") as f:
            f.write(data)
    print("wrote %d seeds into %s" % (len(seeds), HERE))


if __name__ == "__main__":
    main()
