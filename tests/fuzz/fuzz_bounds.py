"""The fuzzing tier's one rule for every case (docs/testing.md, "The fuzzing tier").

A case is one call into an input surface with one drawn input. ``run_case`` runs it and holds it to:

- an outcome: the call returns, or raises the surface's own refusal (``SpecError``, ``KuberosError``,
  ``RegistryError``, ``ValueError`` where a pure function says why that way); any other exception is a traceback the
  user would see, and fails the case with its type, message and where it was raised;
- a located refusal: the surface's ``located`` says what the message must name (for a spec the file, line and field;
  for an inventory the host and variable; for an option its name), and every refusal is text without control
  characters and without Python's exception text;
- bounds: under ``TIME_LIMIT_S`` of CPU time (the process's, every thread: a loopback server's work counts) and
  ``WALL_LIMIT_S`` of wall time, and ``MEMORY_LIMIT`` of memory at peak. CPU time is what the case costs; wall time
  on a shared two-core machine also counts what else runs there (``make test`` runs two lanes and builds images beside
  them), so its bound is looser and catches a case that waits instead of working. The memory is the process's
  peak resident size during the call over its size before (Linux: ``VmHWM`` of /proc/self/status, reset before each
  case by writing 5 to /proc/self/clear_refs), so the whole process counts, a loopback server's thread and memory
  that is not Python's too. Where that reset is not allowed, ``tracemalloc``'s peak of Python allocations stands in;
  tracing makes allocation-heavy code up to ten times slower (a billion-laughs spec: 0.17 s, traced 1.1 s), so the
  time bound, measured under it, is then stricter than it reads. A case still running after ``HANG_S`` is stopped
  (SIGALRM, in the main thread) and fails as a hang instead of stalling the tier.

``COUNTS`` holds the cases run per surface; tests/fuzz/conftest.py writes them to ``$KUBEROS_FUZZ_COUNTS`` (a JSON
file) when set, so that a benchmark can say how many cases ran.
"""

from __future__ import annotations

import collections
import contextlib
import re
import signal
import threading
import time
import traceback
import tracemalloc
from dataclasses import dataclass

from hypothesis import HealthCheck, event, settings
from hypothesis.control import currently_in_test_context

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import printable

TIME_LIMIT_S = 2.0  # CPU seconds
WALL_LIMIT_S = 10.0
MEMORY_LIMIT = 200 * 1024 * 1024
HANG_S = 30
TRACEBACK_TEXT = ("Traceback (most recent call last)", 'File "')
COUNTS: collections.Counter = collections.Counter()


def fuzz_settings(examples: int, **extra) -> settings:
    """Hypothesis settings of the tier: ``examples`` cases, derandomized (the same cases on every run, so that CI is
    reproducible and a failure replays), no example database (nothing written under .hypothesis), and no deadline of
    Hypothesis's own (``run_case`` bounds each case)."""
    return settings(
        max_examples=examples,
        derandomize=True,
        database=None,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
        **extra,
    )


class CaseHung(BaseException):
    """Raised into a case still running after ``HANG_S`` (a BaseException: the code under test's ``except
    Exception`` does not swallow it)."""


@dataclass
class Outcome:
    value: object = None
    error: BaseException | None = None
    seconds: float = 0.0
    cpu_seconds: float = 0.0
    peak_bytes: int = 0


def _resident_kib() -> dict[str, int]:
    with open("/proc/self/status", encoding="ascii") as handle:
        return {key: int(value) for key, value in re.findall(r"^(VmRSS|VmHWM):\s+(\d+) kB", handle.read(), re.M)}


def _peak_reset() -> bool:
    """Reset the process's peak resident size; False where Linux does not let it (then tracemalloc measures)."""
    try:
        with open("/proc/self/clear_refs", "w", encoding="ascii") as handle:
            handle.write("5")
        return True
    except OSError:
        return False


class _Memory:
    """The peak memory of one case: resident (see the module's docstring) or, failing that, traced."""

    def __enter__(self):
        self.resident = _peak_reset()
        if self.resident:
            self.before = _resident_kib()["VmRSS"]
        else:
            self.tracing = tracemalloc.is_tracing()
            if not self.tracing:
                tracemalloc.start()
            tracemalloc.reset_peak()
        return self

    def peak_bytes(self) -> int:
        if self.resident:
            return max(0, _resident_kib()["VmHWM"] - self.before) * 1024
        return tracemalloc.get_traced_memory()[1]

    def __exit__(self, *exc):
        self.peak = self.peak_bytes()
        if not self.resident and not self.tracing:
            tracemalloc.stop()


@contextlib.contextmanager
def _hang_alarm(surface: str):
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(_signum, _frame):
        raise CaseHung(f"{surface}: still running after {HANG_S} s")

    previous = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, HANG_S)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _where(error: BaseException) -> str:
    frames = traceback.extract_tb(error.__traceback__)
    return " <- ".join(f"{f.filename.rsplit('/', 1)[-1]}:{f.lineno} {f.name}" for f in reversed(frames[-4:]))


def run_case(surface: str, call, refusal, located, case=None) -> Outcome:
    """Run ``call()`` once as a case of ``surface``; ``refusal``: the exception type(s) the surface refuses input
    with; ``located(error)``: '' when the refusal's message says where, else what it misses. ``case`` is shown on
    failure (Hypothesis shows the drawn input too)."""
    outcome = Outcome()
    memory = _Memory()
    started, cpu_started = time.perf_counter(), time.process_time()
    try:
        with memory, _hang_alarm(surface):
            outcome.value = call()
    except refusal as error:
        outcome.error = error
    except CaseHung as error:
        raise AssertionError(f"{error}; case: {case!r}") from None
    except Exception as error:  # the traceback a user would see: the finding
        raise AssertionError(
            f"{surface}: {type(error).__name__} escaped ({error!s:.300}) at {_where(error)}; case: {case!r:.2000}"
        ) from error
    finally:
        outcome.seconds = time.perf_counter() - started
        outcome.cpu_seconds = time.process_time() - cpu_started
        outcome.peak_bytes = memory.peak
    COUNTS[surface] += 1
    if currently_in_test_context():  # Hypothesis's statistics (--hypothesis-show-statistics): what share was refused
        event(f"{surface}: " + (f"refused ({type(outcome.error).__name__})" if outcome.error is not None else "accepted"))
    assert outcome.cpu_seconds < TIME_LIMIT_S, (
        f"{surface}: {outcome.cpu_seconds:.2f} s of CPU (over {TIME_LIMIT_S} s); case: {case!r:.2000}"
    )
    assert outcome.seconds < WALL_LIMIT_S, f"{surface}: {outcome.seconds:.2f} s (over {WALL_LIMIT_S} s); case: {case!r:.2000}"
    assert outcome.peak_bytes < MEMORY_LIMIT, (
        f"{surface}: {outcome.peak_bytes / 2**20:.0f} MiB at peak (over {MEMORY_LIMIT / 2**20:.0f} MiB); case: {case!r:.2000}"
    )
    if outcome.error is not None:
        message = str(outcome.error)
        assert message.strip(), f"{surface}: {type(outcome.error).__name__} with no message; case: {case!r:.2000}"
        assert not any(text in message for text in TRACEBACK_TEXT), f"{surface}: Python's text in {message!r:.2000}"
        assert printable(message.replace("\n", " ")) == message.replace("\n", " "), (
            f"{surface}: a control character in {message!r:.2000}"
        )
        why = located(outcome.error)
        assert not why, f"{surface}: the refusal {message!r:.2000} {why}; case: {case!r:.2000}"
    return outcome
