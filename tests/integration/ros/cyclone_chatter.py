"""A Cyclone DDS participant written with its Python binding (PyPI cyclonedds, which bundles libddsc): no ROS.

The participants of test_cyclonedds_netns. rclpy cannot use Cyclone DDS here (no rmw_cyclonedds_cpp wheel on
PyPI), so these stand in for module containers: the same DDS implementation, configured the same way, from
the environment only (CYCLONEDDS_URI, ROS_DOMAIN_ID).

Usage:
    cyclone_chatter.py talk TOPIC COUNT [FIRST]  wait for a reader, write COUNT samples numbered FIRST.. (1),
                                                 wait for their acknowledgement, then stay until killed
    cyclone_chatter.py listen TOPIC              print every sample taken, until killed

Both are reliable, keep-all and transient-local, so a reader gets every sample even if it matches the writer
after the first was written. Lines printed (flushed), as ros/talker.py and ros/listener.py print them: "ready",
"matched after S s" (since the participant was created), "published kuberos N subscribers=K", "acknowledged N",
"received kuberos N", "publishers=K" (when the number of matched writers changes).
SIGTERM deletes the participant (other participants learn at once that it left) and exits 0.
"""

# No `from __future__ import annotations`: the binding reads Chatter's annotations as types, not strings.
import os
import signal
import sys
import time
from dataclasses import dataclass

from cyclonedds.core import InstanceState, Policy, Qos, ReadCondition, SampleState, ViewState, WaitSet
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import int64
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration

QOS = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepAll, Policy.Durability.TransientLocal)
ACK_TIMEOUT = 30.0


@dataclass
class Chatter(IdlStruct, typename="kuberos.Chatter"):
    number: int64
    text: str


class Stop:
    def __init__(self) -> None:
        self.requested = False
        signal.signal(signal.SIGTERM, self.request)
        signal.signal(signal.SIGINT, self.request)

    def request(self, *_args) -> None:
        self.requested = True

    def sleep(self, seconds: float) -> bool:
        """Sleep up to seconds; True if a stop was requested."""
        deadline = time.monotonic() + seconds
        while not self.requested and time.monotonic() < deadline:
            time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
        return self.requested


def talk(participant: DomainParticipant, topic: Topic, count: int, first: int, stop: Stop, start: float) -> None:
    writer = DataWriter(participant, topic, qos=QOS)
    print("ready", flush=True)
    while writer.get_publication_matched_status().current_count == 0:
        if stop.sleep(0.05):
            return
    print(f"matched after {time.monotonic() - start:.2f} s", flush=True)
    for number in range(first, first + count):
        writer.write(Chatter(number=number, text=f"kuberos {number}"))
        subscribers = writer.get_publication_matched_status().current_count
        print(f"published kuberos {number} subscribers={subscribers}", flush=True)
    if writer.wait_for_acks(duration(seconds=ACK_TIMEOUT)):
        print(f"acknowledged {count}", flush=True)
    while not stop.sleep(1.0):
        pass


def listen(participant: DomainParticipant, topic: Topic, stop: Stop) -> None:
    reader = DataReader(participant, topic, qos=QOS)
    waitset = WaitSet(participant)
    waitset.attach(ReadCondition(reader, SampleState.NotRead | ViewState.Any | InstanceState.Any))
    print("ready", flush=True)
    publishers = 0
    while not stop.requested:
        waitset.wait(duration(milliseconds=200))
        for sample in reader.take(N=256):
            if isinstance(sample, Chatter):  # not the InvalidSample that tells of a writer gone
                print(f"received {sample.text}", flush=True)
        matched = reader.get_subscription_matched_status().current_count
        if matched != publishers:
            publishers = matched
            print(f"publishers={publishers}", flush=True)


def main() -> None:
    stop = Stop()
    role, topic_name = sys.argv[1], sys.argv[2]
    start = time.monotonic()
    participant = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    topic = Topic(participant, topic_name, Chatter)
    if role == "talk":
        talk(participant, topic, int(sys.argv[3]), int(sys.argv[4]) if len(sys.argv) > 4 else 1, stop, start)
    else:
        listen(participant, topic, stop)
    participant.__del__()  # dds_delete: announces the participant's end before the process exits


if __name__ == "__main__":
    main()
