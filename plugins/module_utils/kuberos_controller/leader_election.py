"""Leader election on a ``coordination.k8s.io/v1`` Lease, so that several controller replicas run and one acts.

Every replica watches the cluster; only the holder of the Lease acts. The rules are client-go's:

- The holder renews the Lease every ``retry_s``. It may act only while ``renew_deadline_s`` has not passed
  since the start of its last successful renewal (``is_leader``), measured on its own monotonic clock.
- Another replica takes the Lease only once it has seen the same Lease record (holder, renewTime,
  transitions) unchanged for ``duration_s`` on *its* monotonic clock, and only with an update that carries
  the resourceVersion it read (two candidates cannot both win).
- Fencing by lease expiry: a leader that cannot renew (partitioned from the API server, paused, its
  requests hanging) stops acting at ``renewed_at + renew_deadline_s``. No other replica can hold the Lease
  before ``observed_at + duration_s``, and ``observed_at >= renewed_at``, so there is a gap of
  ``duration_s - renew_deadline_s`` between the two. This holds while the replicas' clocks run at about
  the same rate (no wall-clock agreement is needed) and while no single write stays in flight longer than
  that gap; writes are given a client-side timeout of the time left before the deadline.
- A replica that stops cleanly (SIGTERM) releases the Lease (empty holder), so another takes it at once.
- A replica whose own node is NotReady (``stand_down``) releases the Lease it holds and takes a free Lease
  only after it has stayed free for ``2 * duration_s``: a healthy peer goes first.
"""

from __future__ import annotations

import datetime
import logging
import threading
import time
from dataclasses import dataclass

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_kube.api import Kube, clients_of, status_of

log = logging.getLogger("kuberos.controller.lease")


class NotLeader(Exception):
    """Raised before a write when this replica does not (or no longer) hold the Lease."""


@dataclass(frozen=True)
class Timings:
    duration_s: float = 6.0  # how long others wait, after the last renewal they saw, before taking the Lease
    renew_deadline_s: float = 4.0  # how long the leader acts after the start of its last successful renewal
    retry_s: float = 1.0  # how often every replica tries to take or renew the Lease

    def problems(self) -> list[str]:
        out = []
        if not 0 < self.retry_s < self.renew_deadline_s:
            out.append(f"the retry period ({self.retry_s:g} s) must be above 0 and below the renew deadline")
        if not self.renew_deadline_s < self.duration_s:
            out.append(
                f"the renew deadline ({self.renew_deadline_s:g} s) must be below the lease duration ({self.duration_s:g} s)"
            )
        if self.duration_s != int(self.duration_s) or self.duration_s < 1:
            out.append(f"the lease duration ({self.duration_s:g} s) must be a whole number of seconds (the API stores it so)")
        return out


def micro_time(epoch: float | None = None) -> str:
    """A Lease's MicroTime: RFC 3339 in UTC with microseconds."""
    stamp = datetime.datetime.fromtimestamp(time.time() if epoch is None else epoch, datetime.UTC)
    return stamp.strftime("%Y-%m-%dT%H:%M:%S.%fZ")


@dataclass
class Judgement:
    """What a replica may do with the Lease it read (pure: ``judge``)."""

    take: bool  # write the Lease with this replica as holder (acquire or renew)
    holder: str  # the holder as read
    observed: tuple  # the record as read, to remember
    observed_at: float  # when this replica first saw that record (its monotonic clock)
    why: str = ""


def judge(spec: dict, identity: str, now: float, observed: tuple | None, observed_at: float, stand_down: bool,
          timings: Timings) -> Judgement:  # fmt: skip
    """Decide from a Lease's spec whether this replica may write itself in as holder."""
    holder = spec.get("holderIdentity") or ""
    record = (holder, spec.get("renewTime"), spec.get("leaseTransitions"), spec.get("leaseDurationSeconds"))
    if record != observed:
        observed, observed_at = record, now
    duration = float(spec.get("leaseDurationSeconds") or timings.duration_s)
    if holder == identity:
        if stand_down:
            return Judgement(False, holder, observed, observed_at, "own node is NotReady: releasing")
        return Judgement(True, holder, observed, observed_at, "renew")
    free_since = observed_at + (duration if holder else 0.0)
    if now < free_since:
        return Judgement(False, holder, observed, observed_at, f"held by {holder}")
    if stand_down and now < free_since + 2 * timings.duration_s:
        return Judgement(False, holder, observed, observed_at, "own node is NotReady: leaving the Lease to a healthy peer")
    return Judgement(True, holder, observed, observed_at, "expired" if holder else "free")


class LeaderElector:
    """Takes and renews one Lease in a thread; ``is_leader`` says whether this replica may act now."""

    def __init__(self, api_client, namespace: str, name: str, identity: str, timings: Timings | None = None,
                 on_change=None, stand_down=None, clock=time.monotonic):  # fmt: skip
        self.timings = timings or Timings()
        deadline = self.timings.renew_deadline_s
        self.kube = Kube(clients_of(api_client), timeout=deadline, read_timeout=deadline)
        self.namespace = namespace
        self.name = name
        self.identity = identity
        self.on_change = on_change or (lambda leading: None)
        self.stand_down = stand_down or (lambda: None)  # returns why this replica should not lead, or None
        self.clock = clock
        self.holder = ""
        self.transitions = 0  # leaseTransitions as last read or written
        self._renewed_at: float | None = None
        self._observed: tuple | None = None
        self._observed_at = 0.0
        self._leading = False
        self._lock = threading.Lock()

    # -- what the controller asks ----------------------------------------------------------------
    def is_leader(self) -> bool:
        at = self._renewed_at
        return at is not None and self.clock() < at + self.timings.renew_deadline_s

    def time_left(self) -> float:
        """Seconds this replica may still act without a new renewal (0 when it is not the leader)."""
        at = self._renewed_at
        return 0.0 if at is None else max(0.0, at + self.timings.renew_deadline_s - self.clock())

    def check(self) -> float:
        """Before a write: the seconds left to act, or NotLeader."""
        left = self.time_left()
        if left <= 0.05:
            raise NotLeader(f"{self.identity} does not hold the Lease {self.namespace}/{self.name}")
        return left

    # -- the Lease ---------------------------------------------------------------------------------
    def _read(self) -> dict | None:
        return self.kube.get("Lease", self.name, self.namespace)

    def _body(self, old: dict | None, holder: str, acquired: bool, duration: float) -> dict:
        spec = dict((old or {}).get("spec") or {})
        now = micro_time()
        transitions = int(spec.get("leaseTransitions") or 0)
        if acquired:
            spec["acquireTime"] = now
            if old is not None and (spec.get("holderIdentity") or "") != holder:
                transitions += 1
        spec.update(holderIdentity=holder, leaseDurationSeconds=int(duration), renewTime=now, leaseTransitions=transitions)
        metadata = {"name": self.name, "namespace": self.namespace, "labels": {"app.kubernetes.io/managed-by": "kuberos"}}
        if old is not None:
            metadata["resourceVersion"] = old["metadata"]["resourceVersion"]
        return {"apiVersion": "coordination.k8s.io/v1", "kind": "Lease", "metadata": metadata, "spec": spec}

    def _write(self, old: dict | None, body: dict) -> bool:
        try:
            if old is None:
                try:
                    self.kube.create(body)
                except Exception as exc:
                    if status_of(exc) != 404:
                        raise
                    self._ensure_namespace()
                    self.kube.create(body)
            else:
                self.kube.replace(body)
        except Exception as exc:
            if status_of(exc) in (409, 422):  # another replica wrote first (conflict or already exists)
                return False
            raise
        self.transitions = body["spec"]["leaseTransitions"]
        return True

    def _ensure_namespace(self) -> None:
        try:
            self.kube.create({"apiVersion": "v1", "kind": "Namespace", "metadata": {"name": self.namespace}})
            log.info("created namespace %s for the Lease", self.namespace)
        except Exception as exc:
            if status_of(exc) != 409:
                raise

    def attempt(self) -> bool:
        """One try to take or renew the Lease; True when this replica holds it now."""
        sent = self.clock()
        lease = self._read()
        why = self.stand_down()
        if lease is None:
            if why:
                return False
            won = self._write(None, self._body(None, self.identity, True, self.timings.duration_s))
            if won:
                self._renewed_at, self.holder = sent, self.identity
                log.info("%s created the Lease %s/%s and leads", self.identity, self.namespace, self.name)
            return won
        verdict = judge(lease.get("spec") or {}, self.identity, sent, self._observed, self._observed_at, bool(why),
                        self.timings)  # fmt: skip
        self._observed, self._observed_at, self.holder = verdict.observed, verdict.observed_at, verdict.holder
        self.transitions = int((lease.get("spec") or {}).get("leaseTransitions") or 0)
        if not verdict.take:
            if verdict.holder == self.identity:  # holder, but standing down
                self._release(lease, f"{verdict.why} ({why})")
            else:
                self._renewed_at = None
            return False
        taking = verdict.holder != self.identity
        if not self._write(lease, self._body(lease, self.identity, taking, self.timings.duration_s)):
            self._renewed_at = None
            return False
        self._renewed_at, self.holder = sent, self.identity
        if taking:
            log.info("%s took the Lease %s/%s (%s)", self.identity, self.namespace, self.name, verdict.why)
        return True

    def _release(self, lease: dict | None, why: str) -> None:
        self._renewed_at = None  # stop acting before the Lease is given up
        lease = lease if lease is not None else self._read()
        if lease is None or ((lease.get("spec") or {}).get("holderIdentity") or "") != self.identity:
            return
        if self._write(lease, self._body(lease, "", False, 1)):
            self.holder = ""
            log.info("%s released the Lease %s/%s: %s", self.identity, self.namespace, self.name, why)

    def release(self, why: str = "stopping") -> None:
        try:
            self._release(None, why)
        except Exception as exc:  # the API server may be gone: the Lease then expires by itself
            log.warning("releasing the Lease failed (%s); it expires in %g s", exc.__class__.__name__, self.timings.duration_s)

    # -- the loop ----------------------------------------------------------------------------------
    def _notify(self) -> None:
        leading = self.is_leader()
        with self._lock:
            changed, self._leading = leading != self._leading, leading
        if changed:
            log.info(
                "%s %s", self.identity, "is the leader" if leading else f"is not the leader (holder: {self.holder or 'none'})"
            )
            self.on_change(leading)

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            started = self.clock()
            try:
                self.attempt()
            except Exception as exc:  # the API server restarting, a timeout: is_leader runs out by itself
                log.warning("lease %s/%s: %s: %s", self.namespace, self.name, exc.__class__.__name__, str(exc)[:200])
            self._notify()
            # Wake at the retry period, or earlier when the right to act runs out, to report the change on time.
            wait = self.timings.retry_s - (self.clock() - started)
            left = self.time_left()
            if self._leading and 0 < left < wait:
                wait = left
            stop.wait(max(0.01, wait))
            self._notify()
        self.release()
        self._notify()
