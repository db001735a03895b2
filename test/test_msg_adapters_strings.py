"""msg_adapters.strings: std_msgs/String CDR bytes, compared with rclpy byte for byte."""

from __future__ import annotations

import random

import pytest
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import String

from msg_adapters.strings import string_bytes, string_size, string_text, StringMessageError

TEXTS = ['', 'a', 'ab', 'abc', 'abcd', '{"seq": 7, "accepted": false}', 'é€😀 ü',
         'x' * 10_000, '\t\n "quoted" \\']


def cdr(payload: bytes, length: int | None = None, representation: int = 1,
        order: str = 'little') -> bytes:
    """Return an encapsulation header, a length field (default: the payload's) and the payload."""
    length = len(payload) if length is None else length
    return bytes((0, representation, 0, 0)) + length.to_bytes(4, order) + payload


@pytest.mark.parametrize('text', TEXTS)
def test_string_bytes_are_rclpys(text):
    assert string_bytes(text) == serialize_message(String(data=text))


@pytest.mark.parametrize('text', TEXTS)
def test_text_round_trips(text):
    data = serialize_message(String(data=text))
    assert string_text(data) == text
    assert string_size(data) == len(text.encode('utf-8'))


ODD = {
    'embedded NUL': cdr(b'ab\x00cd\x00'),
    'invalid UTF-8': cdr(b'\xff\xfe\xc0\x80abc\x00'),
    'no NUL at the end': cdr(b'abc'),
    'no NUL, aligned': cdr(b'abcd'),
    'length 0': cdr(b''),
    'trailing bytes after the string': cdr(b'abc\x00', 4) + b'zz',
    'only a NUL': cdr(b'\x00'),
    'NULs after a short length': cdr(b'ab\x00\x00\x00\x00\x00\x00', 3),
    'big endian': cdr(b'abc\x00', representation=0, order='big'),
    'XCDR2 little endian': cdr(b'abc\x00', representation=7),
    'lone surrogate bytes': cdr('x\udcff'.encode('utf-8', 'surrogatepass') + b'\x00'),
}


@pytest.mark.parametrize('data', ODD.values(), ids=ODD.keys())
def test_odd_messages_read_as_rclpy_reads_them(data):
    assert string_text(data) == deserialize_message(data, String).data


def test_random_messages_read_as_rclpy_reads_them():
    rng = random.Random(3)
    for _ in range(300):
        payload = bytes(rng.choice((0, 0x41, 0xc3, 0xa9, 0xff, 0x80, rng.randrange(256)))
                        for _ in range(rng.randrange(0, 40)))
        data = cdr(payload, representation=rng.choice((0, 1)),
                   order='little' if rng.random() < 0.9 else 'big')
        try:
            theirs = deserialize_message(data, String).data
        except Exception:   # noqa: B902 - rclpy raises its own error type; then so must we
            with pytest.raises(StringMessageError):
                string_text(data)
        else:
            assert string_text(data) == theirs


def test_size_is_read_from_the_length_field_alone():
    # Ten MiB claimed, ten MiB present: the size comes without decoding anything.
    big = cdr(b'\xff' * (10 << 20) + b'\x00')
    assert string_size(big) == 10 << 20
    assert string_size(cdr(b'abc')) == 3


BROKEN = {
    'shorter than a header': (b'\x00\x01\x00', 'shorter than a std_msgs/String'),
    'length past the end': (cdr(b'abc', 10), 'string length 10 runs past the end of a '
                                             '11-byte message'),
    'unknown encapsulation': (cdr(b'abc\x00', representation=4),
                              'unknown CDR encapsulation 0x0004'),
    'first byte not zero': (b'\x01\x01\x00\x00' + cdr(b'a\x00')[4:],
                            'unknown CDR encapsulation 0x0101'),
}


@pytest.mark.parametrize('data, says', BROKEN.values(), ids=BROKEN.keys())
def test_broken_messages_are_refused_with_the_reason(data, says):
    with pytest.raises(StringMessageError, match=says):
        string_text(data)
    if data[0] == 0:     # rclpy refuses these as well
        with pytest.raises(Exception):   # noqa: B017 - rclpy's RMWError has no public type
            deserialize_message(data, String)
