"""Parsing of the units users write: CPU, memory, latency, bandwidth and packet loss.

All functions return integers or floats in one canonical unit (millicores, bytes,
milliseconds) and raise ``ValueError`` with a message naming what is expected.
"""

from __future__ import annotations

import math
import re

_CPU = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(m?)\s*$")
_MEMORY = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(Ki|Mi|Gi|Ti|k|K|M|G|T)?\s*$")
_LATENCY = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(ms|s)?\s*$")
_BANDWIDTH = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(kbit/s|Mbit/s|Gbit/s)?\s*$")
_BANDWIDTH_FACTORS = {None: 1e6, "kbit/s": 1e3, "Mbit/s": 1e6, "Gbit/s": 1e9}
_LOSS = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*(%)?\s*$")

_MEMORY_FACTORS = {
    None: 1,
    "k": 1000,
    "K": 1000,
    "M": 1000**2,
    "G": 1000**3,
    "T": 1000**4,
    "Ki": 1024,
    "Mi": 1024**2,
    "Gi": 1024**3,
    "Ti": 1024**4,
}

CPU_EXPECTED = "expected a CPU quantity such as 2, 0.5 or '500m'"
MEMORY_EXPECTED = "expected a memory quantity such as '512Mi', '2Gi' or '1G'"
LATENCY_EXPECTED = "expected a latency such as '200 ms', '0.5 s' or a number of milliseconds"
BANDWIDTH_EXPECTED = "expected a bandwidth above zero such as '20 Mbit/s', '512 kbit/s', '1 Gbit/s' or a number of Mbit/s"
LOSS_EXPECTED = "expected a packet loss such as '2%' or a number of percent, from 0 to below 100"


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _parse(value, pattern: re.Pattern, from_number, from_match, expected: str):
    """A non-negative finite number, or a string matching ``pattern``; ``ValueError(expected)`` otherwise."""
    if _is_number(value) and value >= 0:
        return from_number(value)
    if isinstance(value, str):
        match = pattern.match(value)
        if match:
            return from_match(float(match.group(1)), match.group(2))
    raise ValueError(expected)


def parse_cpu(value) -> int:
    """CPU in millicores: ``2`` -> 2000, ``'500m'`` -> 500."""
    return _parse(value, _CPU, lambda n: round(n * 1000), lambda n, milli: round(n if milli else n * 1000), CPU_EXPECTED)


def parse_memory(value) -> int:
    """Memory in bytes: ``'512Mi'`` -> 536870912, plain numbers are bytes."""
    return _parse(value, _MEMORY, int, lambda n, unit: int(n * _MEMORY_FACTORS[unit]), MEMORY_EXPECTED)


def parse_latency_ms(value) -> float:
    """Latency in milliseconds: ``'200 ms'`` -> 200.0, ``'0.5 s'`` -> 500.0, ``20`` -> 20.0."""
    return _parse(value, _LATENCY, float, lambda n, unit: n * 1000.0 if unit == "s" else n, LATENCY_EXPECTED)


def parse_bandwidth_bps(value) -> float:
    """A link's bandwidth in bits per second: ``'20 Mbit/s'`` -> 2e7, ``'512 kbit/s'`` -> 512000.0, ``54`` -> 5.4e7."""
    bps = _parse(value, _BANDWIDTH, lambda n: n * 1e6, lambda n, unit: n * _BANDWIDTH_FACTORS[unit], BANDWIDTH_EXPECTED)
    if bps <= 0:
        raise ValueError(BANDWIDTH_EXPECTED)
    return float(bps)


def parse_loss_fraction(value) -> float:
    """A link's packet loss as a fraction: ``'2%'`` -> 0.02, ``0.5`` -> 0.005 (numbers are percent)."""
    fraction = _parse(value, _LOSS, lambda n: n / 100.0, lambda n, _unit: n / 100.0, LOSS_EXPECTED)
    if fraction >= 1.0:
        raise ValueError(LOSS_EXPECTED)
    return float(fraction)


def format_cpu(millis: int) -> str:
    """Kubernetes form of a CPU amount: ``1500`` -> ``'1500m'``, ``2000`` -> ``'2'``."""
    return str(millis // 1000) if millis % 1000 == 0 else f"{millis}m"


def format_memory(size: int) -> str:
    """Kubernetes form of a memory amount, in the largest binary unit that divides it."""
    for unit in ("Ti", "Gi", "Mi", "Ki"):
        factor = _MEMORY_FACTORS[unit]
        if size and size % factor == 0:
            return f"{size // factor}{unit}"
    return str(size)


def format_latency(ms: float) -> str:
    return f"{ms:g} ms"
