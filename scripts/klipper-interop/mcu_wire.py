"""Just enough of Klipper's wire protocol to download an MCU's data dictionary (identify).

The harness needs the dictionary of a `cadence-mcu` as a file, to run Klipper's host in batch
mode against it (the configuration it writes names each oid's pins). Written for Cadence from
the protocol description (docs: Klipper's Protocol.md; Cadence's links/src/proto): blocks are
`len seq payload crc16 0x7E`, integers are VLQ-encoded, `identify offset=%u count=%c` answers
`identify_response offset=%u data=%.*s` with a slice of the zlib-compressed JSON.
"""

import os
import select
import time
import zlib

SYNC = 0x7E
DEST = 0x10
IDENTIFY_ID = 1
IDENTIFY_RESPONSE_ID = 0
CHUNK = 40


def crc16_ccitt(data):
    crc = 0xFFFF
    for b in data:
        d = (b ^ (crc & 0xFF)) & 0xFF
        d = (d ^ (d << 4)) & 0xFF
        crc = (((d << 8) | (crc >> 8)) ^ (d >> 4) ^ (d << 3)) & 0xFFFF
    return crc


def vlq_encode(v):
    out = []
    if v >= 0xC000000 or v < -0x4000000:
        out.append((v >> 28) & 0x7F | 0x80)
    if v >= 0x180000 or v < -0x80000:
        out.append((v >> 21) & 0x7F | 0x80)
    if v >= 0x3000 or v < -0x1000:
        out.append((v >> 14) & 0x7F | 0x80)
    if v >= 0x60 or v < -0x20:
        out.append((v >> 7) & 0x7F | 0x80)
    out.append(v & 0x7F)
    return bytes(out)


def vlq_decode(data, pos):
    c = data[pos]
    pos += 1
    v = c & 0x7F
    if c & 0x60 == 0x60:
        v |= -0x20
    while c & 0x80:
        c = data[pos]
        pos += 1
        v = (v << 7) | (c & 0x7F)
    return v, pos


def encode_block(seq, payload):
    length = len(payload) + 5
    head = bytes([length, DEST | (seq & 0x0F)]) + payload
    crc = crc16_ccitt(head)
    return head + bytes([crc >> 8, crc & 0xFF, SYNC])


def split_blocks(buf):
    """Complete, CRC-checked blocks at the front of buf as (seq, payload), and the rest."""
    payloads = []
    while buf:
        length = buf[0]
        if length < 5 or length > 64:
            buf = buf[1:]
            continue
        if len(buf) < length:
            break
        block, buf = buf[:length], buf[length:]
        crc = crc16_ccitt(block[:-3])
        if block[-1] != SYNC or block[-3:-1] != bytes([crc >> 8, crc & 0xFF]):
            continue
        payloads.append((block[1] & 0x0F, block[2:-3]))
    return payloads, buf


def download_dictionary(tty_path, timeout=30.0):
    """The JSON text of the dictionary served by the MCU on tty_path."""
    fd = os.open(tty_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        import termios
        import tty

        tty.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(fd, termios.TCSANOW, attrs)
        seq = 0
        data = b""
        rx = b""
        deadline = time.monotonic() + timeout
        os.write(fd, bytes([SYNC]))
        while True:
            payload = bytes([IDENTIFY_ID]) + vlq_encode(len(data)) + vlq_encode(CHUNK)
            # The MCU acks with the sequence it expects next: resending after a loss or a NAK
            # uses that one.
            os.write(fd, encode_block(seq, payload))
            got = None
            retry_at = time.monotonic() + 0.5
            while got is None:
                now = time.monotonic()
                if now > deadline:
                    raise TimeoutError("no identify_response from %s" % tty_path)
                if now > retry_at:
                    break
                r, _, _ = select.select([fd], [], [], 0.1)
                if not r:
                    continue
                rx += os.read(fd, 4096)
                payloads, rx = split_blocks(rx)
                for ack_seq, p in payloads:
                    seq = ack_seq
                    if not p:
                        continue
                    msg_id, pos = vlq_decode(p, 0)
                    if msg_id != IDENTIFY_RESPONSE_ID:
                        continue
                    offset, pos = vlq_decode(p, pos)
                    n = p[pos]
                    if offset == len(data):
                        got = p[pos + 1 : pos + 1 + n]
            if got is None:
                continue
            if not got:
                return zlib.decompress(data).decode()
            data += got
    finally:
        os.close(fd)
