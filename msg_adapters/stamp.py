"""Simulated time (float seconds) as ROS 2 time stamps."""

from __future__ import annotations

import math

from builtin_interfaces.msg import Time
from rosgraph_msgs.msg import Clock

from .cdr import CdrWriter

NANOSECONDS_PER_SECOND = 1_000_000_000


def stamp_from_seconds(seconds: float) -> tuple[int, int]:
    """Return ``(sec, nanosec)`` for a time in seconds, nanoseconds rounded.

    Rounding the whole value once (instead of splitting it first) keeps
    ``nanosec`` within 0..999,999,999 and carries into ``sec``.
    """
    if not (math.isfinite(seconds) and seconds >= 0.0):
        raise ValueError(f'time stamp must be a finite value >= 0, got {seconds!r}')
    sec, nanosec = divmod(round(seconds * NANOSECONDS_PER_SECOND), NANOSECONDS_PER_SECOND)
    return int(sec), int(nanosec)


def nanoseconds_from_seconds(seconds: float) -> int:
    """Return a time in seconds as the integer nanoseconds of its stamp (a bag's log time)."""
    sec, nanosec = stamp_from_seconds(seconds)
    return sec * NANOSECONDS_PER_SECOND + nanosec


def time_message(seconds: float) -> Time:
    """Return a builtin_interfaces/Time for a time in seconds."""
    sec, nanosec = stamp_from_seconds(seconds)
    return Time(sec=sec, nanosec=nanosec)


def clock_message(seconds: float) -> Clock:
    """Return a rosgraph_msgs/Clock carrying simulated time."""
    return Clock(clock=time_message(seconds))


def clock_bytes(seconds: float) -> bytes:
    """Return a serialised rosgraph_msgs/Clock carrying simulated time, ready to publish."""
    writer = CdrWriter()
    writer.stamp(*stamp_from_seconds(seconds))
    return writer.bytes()


def seconds_from_stamp(stamp: Time) -> float:
    """Return a builtin_interfaces/Time as float seconds."""
    return stamp.sec + stamp.nanosec / NANOSECONDS_PER_SECOND
