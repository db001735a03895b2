"""A minimal little-endian CDR writer for ROS 2 messages built from numpy arrays.

rmw_fastrtps serialises a message as a 4-byte encapsulation header (CDR,
little endian) followed by the fields in declaration order, each primitive
aligned to its own size (8 for float64) relative to the first byte after
the header. Strings are a uint32 length that counts a trailing NUL, then
the bytes and the NUL; sequences are a uint32 count, then the elements.

Writing that layout directly lets a whole particle array become one
copy into the message instead of one Python message object per particle:
an array is kept as a view of its bytes and copied once, when ``bytes()``
joins the fields (a large world's message is not copied a second time by
``tobytes`` first). ``rclpy`` publishes the resulting ``bytes`` as an
already serialised message. The tests compare every byte with
``rclpy.serialization``.
"""

from __future__ import annotations

import numpy as np

ENCAPSULATION_CDR_LE = b'\x00\x01\x00\x00'


def byte_view(values: np.ndarray) -> memoryview:
    """Return the bytes of ``values`` in C order as a flat view (copied only if not C-contiguous).

    The same bytes as ``values.tobytes()``, without a copy of a contiguous
    array: a large world's message is then copied once, into the message.
    """
    flat = np.ascontiguousarray(values).reshape(-1)
    return memoryview(flat.view(np.uint8))


class CdrWriter:
    """Append CDR fields; ``bytes()`` returns the message ready to publish.

    ``padding`` lists the (offset, length) of every alignment gap, offsets
    counted from the start of the returned bytes (the writer fills gaps
    with zeros; rmw leaves them unspecified).
    """

    def __init__(self) -> None:
        """Start a message with the encapsulation header."""
        self._chunks: list[bytes | memoryview] = [ENCAPSULATION_CDR_LE]
        self._offset = 0          # bytes written after the encapsulation header
        self.padding: list[tuple[int, int]] = []

    def align(self, size: int) -> None:
        """Pad with zeros so the next field starts at a multiple of ``size``."""
        gap = -self._offset % size
        if gap:
            self.padding.append((self._offset + len(ENCAPSULATION_CDR_LE), gap))
            self._chunks.append(b'\x00' * gap)
            self._offset += gap

    def raw(self, data: bytes | memoryview, alignment: int = 1) -> None:
        """Append bytes already in CDR layout, aligned to ``alignment``.

        ``data`` may be a byte view of an array (``byte_view``): it is read
        when ``bytes()`` joins the fields, so the array must not change
        before. Fast CDR aligns an array only when it has elements, so empty
        data adds neither bytes nor padding.
        """
        size = len(data)
        if not size:
            return
        self.align(alignment)
        self._chunks.append(data)
        self._offset += size

    def uint32(self, value: int) -> None:
        """Append an unsigned 32-bit integer."""
        self.raw(int(value).to_bytes(4, 'little'), 4)

    def int32(self, value: int) -> None:
        """Append a signed 32-bit integer."""
        self.raw(int(value).to_bytes(4, 'little', signed=True), 4)

    def uint8(self, value: int) -> None:
        """Append one byte (also ``bool``)."""
        self.raw(bytes((int(value),)))

    def float64s(self, values: np.ndarray) -> None:
        """Append float64 values (C order) without a count."""
        self.raw(byte_view(np.asarray(values, dtype='<f8')), 8)

    def float32s(self, values: np.ndarray) -> None:
        """Append float32 values (C order) without a count."""
        self.raw(byte_view(np.asarray(values, dtype='<f4')), 4)

    def string(self, text: str) -> None:
        """Append a string: length with the NUL, bytes, NUL."""
        data = text.encode('utf-8') + b'\x00'
        self.uint32(len(data))
        self.raw(data)

    def stamp(self, sec: int, nanosec: int) -> None:
        """Append a builtin_interfaces/Time."""
        self.int32(sec)
        self.uint32(nanosec)

    def header(self, sec: int, nanosec: int, frame_id: str) -> None:
        """Append a std_msgs/Header."""
        self.stamp(sec, nanosec)
        self.string(frame_id)

    @property
    def offset(self) -> int:
        """Bytes written after the encapsulation header."""
        return self._offset

    def bytes(self) -> bytes:
        """Return the serialised message."""
        return b''.join(self._chunks)
