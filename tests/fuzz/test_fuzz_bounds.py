"""The tier's rule can fail: a case over its time or memory, a traceback, an unlocated or unprintable refusal and a
hang each fail ``run_case``; a located refusal and a result pass."""

from __future__ import annotations

import time

import fuzz_bounds
import pytest
from fuzz_bounds import run_case

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError


def _refuse(message):
    def call():
        raise KuberosError(message)

    return call


def _located(error):
    return "" if str(error).startswith("lines") else "does not name lines"


def _busy():
    end = time.process_time() + fuzz_bounds.TIME_LIMIT_S + 0.1
    while time.process_time() < end:  # work, not waiting: CPU time
        pass


def _grow():
    block = bytearray(300 * 1024 * 1024)
    block[::4096] = b"x" * len(block[::4096])  # touch every page: resident, not only reserved
    return len(block)


def test_a_result_and_a_located_refusal_pass():
    assert run_case("bounds", lambda: 5, KuberosError, _located).value == 5
    assert isinstance(run_case("bounds", _refuse("lines must be from 1 to 10000"), KuberosError, _located).error, KuberosError)


@pytest.mark.parametrize(
    ("call", "expected"),
    [
        pytest.param(lambda: {}["missing"], "KeyError escaped", id="traceback"),
        pytest.param(_refuse("must be from 1 to 10000"), "does not name lines", id="unlocated"),
        pytest.param(_refuse("lines: bad \x1b[2J"), "a control character", id="control-character"),
        pytest.param(_refuse('lines: Traceback (most recent call last):\n  File "x"'), "Python's text", id="python-text"),
        pytest.param(_busy, r"s of CPU \(over 2\.0 s\)", id="slow"),
    ],
)
def test_a_case_breaking_the_rule_fails(call, expected):
    with pytest.raises(AssertionError, match=expected):
        run_case("bounds", call, KuberosError, _located)


def test_a_case_over_the_memory_bound_fails(monkeypatch):
    # touching 300 MiB can take over the time bound on a loaded machine: only the memory bound is under test here
    monkeypatch.setattr(fuzz_bounds, "TIME_LIMIT_S", 60.0)
    with pytest.raises(AssertionError, match="MiB at peak"):
        run_case("bounds", _grow, KuberosError, _located)


def test_a_case_that_waits_past_the_wall_bound_fails(monkeypatch):
    monkeypatch.setattr(fuzz_bounds, "WALL_LIMIT_S", 0.3)
    with pytest.raises(AssertionError, match=r"over 0\.3 s\)"):
        run_case("bounds", lambda: time.sleep(0.5), KuberosError, _located)


def test_a_hang_is_stopped(monkeypatch):
    monkeypatch.setattr(fuzz_bounds, "HANG_S", 0.2)
    started = time.monotonic()
    with pytest.raises(AssertionError, match=r"still running after 0\.2 s"):
        run_case("bounds", lambda: time.sleep(30), KuberosError, _located)
    assert time.monotonic() - started < 5
