# Copyright: KubeROS contributors
# GNU General Public License v3.0+ (see https://www.gnu.org/licenses/gpl-3.0.txt)
"""Parses what ping printed into a round-trip time, or the reason there is none."""

from __future__ import annotations

DOCUMENTATION = r"""
name: ping_rtt
short_description: The average round-trip time of one ping run, or why there is none
version_added: 0.1.0
description:
  - Reads the summary of C(ping) (iputils, as on Debian and Ubuntu; also the BusyBox and BSD formats), that is
    the packets sent and received, the loss, and the min/avg/max round-trip times in milliseconds.
  - C(status) is C(ok) when at least one reply came back (then C(avg_ms) is set), C(lost) when ping ran and
    no reply came back, C(unresolved) when the target's name did not resolve, C(unreachable) when the
    system had no route to it, and C(error) when ping itself did not run or printed nothing this filter
    understands (a missing program, no permission to open an ICMP socket, a bad option).
  - A target that is not C(ok) has no round-trip time; it is never reported as zero.
options:
  _input:
    description:
      - The registered result of an P(ansible.builtin.command#module) task that ran ping (its C(stdout),
        C(stderr), C(rc) and C(msg) are read), or the text ping printed.
    type: raw
    required: true
"""

EXAMPLES = r"""
- name: Ping an edge server from the robot
  ansible.builtin.command:
    argv: [ping, -n, -q, -c, "5", -i, "0.2", -W, "1", 10.0.0.2]
  register: pinged
  changed_when: false
  failed_when: false

- name: Its average round-trip time in milliseconds
  ansible.builtin.debug:
    msg: "{{ (pinged | kuberos.platform.ping_rtt).avg_ms }}"
"""

RETURN = r"""
_value:
  description: The parsed run.
  type: dict
  contains:
    status:
      description: C(ok), C(lost), C(unresolved), C(unreachable) or C(error).
      type: str
    reachable:
      description: Whether at least one reply came back.
      type: bool
    avg_ms:
      description: Average round-trip time in milliseconds over the replies; null unless C(status=ok).
      type: float
    min_ms:
      description: Smallest round-trip time in milliseconds; null unless C(status=ok).
      type: float
    max_ms:
      description: Largest round-trip time in milliseconds; null unless C(status=ok).
      type: float
    transmitted:
      description: Echo requests sent; null when ping printed no summary.
      type: int
    received:
      description: Echo replies received; null when ping printed no summary.
      type: int
    loss_percent:
      description: Packet loss in percent; null when ping printed no summary.
      type: float
    message:
      description: One line saying what happened, for a report (e.g. C(100% packet loss, 5 sent)).
      type: str
"""

import re

from ansible.errors import AnsibleFilterError

# "5 packets transmitted, 5 received, 0% packet loss, time 819ms" (iputils; "+N errors, " and
# "+N duplicates, " may stand before the loss); "3 packets transmitted, 3 packets received, 0% packet loss" (BusyBox, BSD).
_COUNTS = re.compile(
    r"(?P<sent>\d+) packets transmitted, (?P<received>\d+) (?:packets )?received,(?:[^,\n]*,)*?"
    r" (?P<loss>\d+(?:\.\d+)?)% packet loss"
)
# "rtt min/avg/max/mdev = 0.031/0.109/0.239/0.092 ms" (iputils), "round-trip min/avg/max = ..." (BusyBox),
# "round-trip min/avg/max/stddev = ..." (BSD, macOS).
_TIMES = re.compile(
    r"(?:rtt|round-trip) min/avg/max(?:/\w+)? = (?P<min>\d+(?:\.\d+)?)/(?P<avg>\d+(?:\.\d+)?)/(?P<max>\d+(?:\.\d+)?)"
    r"(?:/\d+(?:\.\d+)?)? (?P<unit>ms|us|µs|s)\b"
)
_UNRESOLVED = re.compile(
    r"Name or service not known|Temporary failure in name resolution|No address associated with hostname"
    r"|unknown host|bad address|cannot resolve|Address family for hostname not supported|nodename nor servname",
    re.IGNORECASE,
)
_UNREACHABLE = re.compile(r"Network is unreachable|No route to host|Host is unreachable|Destination \w+ Unreachable", re.I)
_TO_MS = {"ms": 1.0, "us": 0.001, "µs": 0.001, "s": 1000.0}


def _text(value) -> tuple[str, str]:
    """The combined output and a fallback message of a command result or plain text."""
    if isinstance(value, str):
        return value, ""
    if isinstance(value, dict):
        output = "\n".join(str(value.get(key) or "") for key in ("stdout", "stderr"))
        fallback = str(value.get("msg") or "").rstrip(".")
        command = value.get("cmd")
        if isinstance(command, (list, tuple)):
            command = " ".join(str(c) for c in command)
        if fallback and command:
            fallback = f"{fallback}: {command}"  # e.g. the program is missing: ansible-core keeps no other detail
        return output, fallback
    raise AnsibleFilterError(f"ping_rtt: expected a command result or ping's output, got {type(value).__name__}")


def _first_line(*texts: str) -> str:
    for text in texts:
        for line in text.splitlines():
            if line.strip():
                return line.strip()
    return ""


def parse_ping(value) -> dict:
    """The round-trip times of one ping run (see DOCUMENTATION)."""
    output, fallback = _text(value)
    result = {
        "status": "error",
        "reachable": False,
        "avg_ms": None,
        "min_ms": None,
        "max_ms": None,
        "transmitted": None,
        "received": None,
        "loss_percent": None,
        "message": "",
    }
    counts = _COUNTS.search(output)
    if counts:
        sent, received = int(counts["sent"]), int(counts["received"])
        result.update(transmitted=sent, received=received, loss_percent=float(counts["loss"]))
        times = _TIMES.search(output)
        if received > 0 and times:
            scale = _TO_MS[times["unit"]]
            result.update(
                status="ok",
                reachable=True,
                min_ms=round(float(times["min"]) * scale, 3),
                avg_ms=round(float(times["avg"]) * scale, 3),
                max_ms=round(float(times["max"]) * scale, 3),
            )
            result["message"] = f"{result['avg_ms']:g} ms ({received}/{sent} replies)"
        elif received > 0:
            result["message"] = f"{received}/{sent} replies but no round-trip times in ping's summary"
        else:
            result["status"] = "lost"
            result["message"] = f"{counts['loss']}% packet loss, {sent} sent"
        return result
    line = _first_line(output, fallback)
    if _UNRESOLVED.search(output):
        result["status"] = "unresolved"
    elif _UNREACHABLE.search(output):
        result["status"] = "unreachable"
    result["message"] = line or "ping printed nothing"
    return result


class FilterModule:
    def filters(self):
        return {"ping_rtt": parse_ping}
