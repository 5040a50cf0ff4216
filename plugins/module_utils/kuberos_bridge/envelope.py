"""Frames on the stream: Hello, and Batches of Envelopes (one ROS 2 message each, as CDR bytes).

Pure functions over the generated protobuf classes (bridge_pb2); no gRPC and no ROS here.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge.buffer import Outgoing

try:
    from google.protobuf.message import DecodeError

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import bridge_pb2 as pb
except ImportError:  # the bridge's image has protobuf; without it this still imports (ansible-test's import check)
    DecodeError = pb = None

PROTOCOL = 1
METHOD = "/kuberos.bridge.v1.Bridge/Exchange"
# Representation identifiers of the CDR encapsulation header (XTypes 1.3, 7.6.3.1.2): CDR, PL_CDR, CDR2,
# D_CDR2 and PL_CDR2, each big- and little-endian. ROS 2 Jazzy with Fast DDS writes CDR_LE (0x0001).
CDR_REPRESENTATIONS = frozenset({0x0000, 0x0001, 0x0002, 0x0003, 0x0006, 0x0007, 0x0008, 0x0009, 0x000A, 0x000B})

RELIABLE, BEST_EFFORT = "reliable", "best_effort"
VOLATILE, TRANSIENT_LOCAL = "volatile", "transient_local"
if pb is not None:
    _RELIABILITY = {RELIABLE: pb.RELIABLE, BEST_EFFORT: pb.BEST_EFFORT}
    _DURABILITY = {VOLATILE: pb.VOLATILE, TRANSIENT_LOCAL: pb.TRANSIENT_LOCAL}


class FrameError(ValueError):
    """A frame from the peer that is not a valid Frame."""


@dataclass(frozen=True)
class Qos:
    """The publishers' QoS that the sending bridge subscribed with and the receiving bridge publishes with."""

    reliability: str = RELIABLE
    durability: str = VOLATILE
    depth: int = 10

    def to_pb(self) -> pb.Qos:
        return pb.Qos(reliability=_RELIABILITY[self.reliability], durability=_DURABILITY[self.durability], depth=self.depth)

    @classmethod
    def from_pb(cls, qos: pb.Qos, default_depth: int) -> Qos:
        """Unspecified fields (an older or foreign sender) fall back to reliable, volatile and default_depth."""
        reliability = BEST_EFFORT if qos.reliability == pb.BEST_EFFORT else RELIABLE
        durability = TRANSIENT_LOCAL if qos.durability == pb.TRANSIENT_LOCAL else VOLATILE
        depth = qos.depth if 0 < qos.depth <= 10000 else default_depth
        return cls(reliability, durability, depth)


def cdr_problem(data: bytes) -> str | None:
    """Why data is not a serialized ROS 2 message (None if its encapsulation header looks right)."""
    if len(data) < 4:
        return f"{len(data)} bytes, shorter than the 4-byte CDR encapsulation header"
    representation = (data[0] << 8) | data[1]
    if representation not in CDR_REPRESENTATIONS:
        return f"unknown CDR representation identifier 0x{representation:04x}"
    return None


def hello_frame(role: str, session: str, topics, max_message_bytes: int) -> bytes:
    hello = pb.Hello(role=role, session=session, protocol=PROTOCOL, max_message_bytes=max_message_bytes)
    for topic in topics:
        hello.topics.add(name=topic.name, type=topic.type, direction=topic.direction)
    return pb.Frame(hello=hello).SerializeToString()


def batch_frame(items: list[Outgoing], now_ns: int | None = None) -> bytes:
    """One Batch frame of the given messages, stamped with the time they are written to the stream."""
    sent = time.time_ns() if now_ns is None else now_ns
    frame = pb.Frame()
    envelopes = frame.batch.envelopes
    for item in items:
        envelopes.add(
            topic=item.topic,
            type=item.type,
            cdr=item.cdr,
            sequence=item.sequence,
            source_timestamp_ns=item.source_ns,
            received_timestamp_ns=item.received_ns,
            sent_timestamp_ns=sent,
            qos=item.qos.to_pb(),
        )
    return frame.SerializeToString()


def decode_frame(data: bytes) -> pb.Frame:
    """Parse a frame; FrameError for bytes that are not a Frame or a Frame with neither hello nor batch."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise FrameError(f"expected bytes, got {type(data).__name__}")
    try:
        frame = pb.Frame.FromString(bytes(data))
    except (DecodeError, RuntimeError, ValueError) as error:
        raise FrameError(f"{len(data)} bytes that do not parse as a Frame: {error}") from None
    if frame.WhichOneof("body") is None:
        raise FrameError(f"{len(data)} bytes: a Frame with neither hello nor batch")
    return frame
