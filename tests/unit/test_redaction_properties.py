"""Property tests of a log's redaction (kuberos/module_logs.py): secrets of every shape (tests/redaction_cases.py)
among ordinary lines, cut into a tail and ``follow`` polls at any line, never show, and ordinary lines do."""

from __future__ import annotations

import redaction_cases
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import redact

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
WITHOUT_SECRET_VALUES = [shape for shape in redaction_cases.SHAPES if shape is not redaction_cases.secret_value]


@SETTINGS
@given(rng=st.randoms(use_true_random=False))
def test_no_secret_shows_in_a_tail_and_the_follow_polls_after_it(rng):
    windows, secrets, forbidden = redaction_cases.case(rng)
    assert redaction_cases.leaks(windows, secrets, forbidden) == [], windows
    assert redaction_cases.ordinary_kept(windows, secrets) == [], windows


@SETTINGS
@given(rng=st.randoms(use_true_random=False))
def test_no_secret_shows_in_any_window_read_alone(rng):
    """The dashboard's tail and each ``logs.yml lines=N``: a window that starts anywhere, read with no state
    (the dashboard knows no Secret values: it does not show the logs of pods that can read one)."""
    windows, secrets, forbidden = redaction_cases.case(rng, WITHOUT_SECRET_VALUES)
    assert secrets == {}
    for window in windows:
        shown = redact(window, {})
        assert [piece for piece in forbidden if piece in shown] == [], window


def test_the_benchmark_corpus_leaks_nothing():
    found = redaction_cases.cases(300, seed=44)
    assert len(found) == 300
    assert [c for c in found if redaction_cases.leaks(*c)] == []
