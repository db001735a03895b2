"""std_msgs/String as CDR bytes, both ways, without a message object in between.

The node takes its command topics raw (the serialised bytes) so that a
request's size is known from its length field before any text is made of
it, and publishes its answers as bytes. Layout (see :mod:`msg_adapters.cdr`):
4-byte encapsulation header, uint32 length counting a trailing NUL, the
UTF-8 bytes, the NUL.

:func:`string_text` gives exactly the text ``rclpy`` would: the bytes up to
the first NUL (the C message keeps a NUL-terminated string), invalid UTF-8
replaced by U+FFFD. The tests compare both functions with
``rclpy.serialization`` byte for byte.
"""

from __future__ import annotations

from .cdr import ENCAPSULATION_CDR_LE

ENCAPSULATION_CDR_BE = b'\x00\x00\x00\x00'
_HEADER = 8                  # encapsulation (4) + length (4)
# Representation ids Fast CDR reads a String from in the same layout (plain and
# parameter-list CDR, XCDR2 forms); 4 and 5 it refuses, and so does this module.
_REPRESENTATIONS = frozenset((0, 1, 2, 3, 6, 7, 8, 9, 10, 11))


class StringMessageError(ValueError):
    """The bytes are not a serialised std_msgs/String (the reason is the message)."""


def string_bytes(text: str) -> bytes:
    """Return the serialised std_msgs/String holding ``text`` (CDR, little endian)."""
    data = text.encode('utf-8')
    return b''.join((ENCAPSULATION_CDR_LE, (len(data) + 1).to_bytes(4, 'little'), data,
                     b'\x00'))


def _little_endian(data: bytes) -> bool:
    """Return the byte order of a CDR message; raise where Fast CDR would not read it."""
    if len(data) < _HEADER:
        raise StringMessageError(f'message of {len(data)} bytes is shorter than a '
                                 'std_msgs/String')
    if data[0] != 0 or data[1] not in _REPRESENTATIONS:
        raise StringMessageError(f'unknown CDR encapsulation 0x{data[:2].hex()}')
    # The low bit of a representation id is its byte order (1: little endian).
    return bool(data[1] & 1)


def string_size(data: bytes) -> int:
    """Return the byte length of the string in a serialised String, without reading it.

    This is the length field less a terminating NUL: an upper bound of the
    text's UTF-8 size that costs nothing, so a too-long request is refused
    before a copy of it is made. Raises :class:`StringMessageError` when the
    field points past the end of ``data``.
    """
    length = int.from_bytes(data[4:8], 'little' if _little_endian(data) else 'big')
    if length > len(data) - _HEADER:
        raise StringMessageError(f'string length {length} runs past the end of a '
                                 f'{len(data)}-byte message')
    # Fast CDR drops the last byte only when it is the NUL.
    return length - 1 if length and data[_HEADER + length - 1] == 0 else length


def string_text(data: bytes) -> str:
    """Return the text of a serialised std_msgs/String exactly as ``rclpy`` would."""
    end = _HEADER + string_size(data)
    nul = data.find(b'\x00', _HEADER, end)
    return str(memoryview(data)[_HEADER:end if nul < 0 else nul], 'utf-8', 'replace')


__all__ = ['StringMessageError', 'string_bytes', 'string_size', 'string_text']
