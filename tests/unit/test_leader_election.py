"""The Lease rules of the redundant controller, without a cluster (``leader_election.judge`` and ``Timings``).

The same rules run against a real API server in tests/cluster/test_controller_ha.py.
"""

from __future__ import annotations

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_controller.leader_election import (
    LeaderElector,
    NotLeader,
    Timings,
    judge,
)

T = Timings(duration_s=6, renew_deadline_s=4, retry_s=1)


def _spec(holder, renew="2026-11-25T10:00:00.000000Z", transitions=0, duration=6):
    return {"holderIdentity": holder, "renewTime": renew, "leaseTransitions": transitions, "leaseDurationSeconds": duration}


def test_a_lease_held_by_another_is_taken_only_after_the_same_record_was_seen_for_its_duration():
    first = judge(_spec("a"), "b", now=100.0, observed=None, observed_at=0.0, stand_down=False, timings=T)
    assert not first.take and first.observed_at == 100.0, "a record seen for the first time starts the wait"
    later = judge(_spec("a"), "b", now=105.9, observed=first.observed, observed_at=first.observed_at, stand_down=False, timings=T)
    assert not later.take and later.why == "held by a"
    due = judge(_spec("a"), "b", now=106.0, observed=first.observed, observed_at=first.observed_at, stand_down=False, timings=T)
    assert due.take and due.why == "expired"


def test_a_renewal_seen_restarts_the_wait_whatever_the_clocks_say():
    seen = judge(_spec("a"), "b", 100.0, None, 0.0, False, T)
    renewed = judge(_spec("a", renew="2026-11-25T09:00:00.000000Z"), "b", 105.5, seen.observed, seen.observed_at, False, T)
    assert not renewed.take and renewed.observed_at == 105.5, "a changed record counts from when it was seen, not its stamp"
    assert not judge(_spec("a", renew="2026-11-25T09:00:00.000000Z"), "b", 111.0, renewed.observed, 105.5, False, T).take


def test_a_released_lease_is_free_at_once_and_the_holder_renews_its_own():
    assert judge(_spec(""), "b", 100.0, None, 0.0, False, T).take
    assert judge(_spec("b"), "b", 100.0, None, 0.0, False, T).why == "renew"


def test_a_replica_on_a_not_ready_node_releases_and_leaves_a_free_lease_to_a_healthy_peer():
    own = judge(_spec("b"), "b", 100.0, None, 0.0, stand_down=True, timings=T)
    assert not own.take and "releasing" in own.why
    free = judge(_spec(""), "b", 100.0, None, 0.0, stand_down=True, timings=T)
    assert not free.take
    still_free = judge(_spec(""), "b", 100.0 + 2 * T.duration_s, free.observed, free.observed_at, True, T)
    assert still_free.take, "when no healthy peer took it, a standing-down replica leads rather than nobody"


@pytest.mark.parametrize(
    ("timings", "fragment"),
    [
        (Timings(6, 6, 1), "renew deadline (6 s) must be below the lease duration"),
        (Timings(6, 4, 4), "retry period (4 s) must be above 0 and below the renew deadline"),
        (Timings(5.5, 4, 1), "whole number of seconds"),
    ],
)
def test_timings_that_would_break_the_fence_are_refused(timings, fragment):
    assert any(fragment in p for p in timings.problems())
    assert Timings().problems() == []


def test_a_replica_acts_only_until_its_renew_deadline():
    now = [1000.0]
    elector = LeaderElector.__new__(LeaderElector)
    elector.timings, elector.clock, elector.identity = T, lambda: now[0], "b"
    elector.namespace, elector.name = "kuberos-system", "kuberos-controller"
    elector._renewed_at = None
    with pytest.raises(NotLeader):
        elector.check()
    elector._renewed_at = 1000.0
    now[0] = 1003.0
    assert elector.is_leader() and elector.check() == pytest.approx(1.0), "a write gets the time left as its timeout"
    now[0] = 1004.0
    assert not elector.is_leader()
    with pytest.raises(NotLeader):
        elector.check()
