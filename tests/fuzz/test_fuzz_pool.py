"""Fuzzing the robot pool: its options (``until``, ``owner``, ``reason``: what ``playbooks/pool.yml`` passes
``robot_pool``'s reserve) against a stored reservation that may be anything, and the reservation ConfigMaps every
reader reads (``pool.read``, ``robot_pool.reservations`` and ``listing``). A reserve is done, or refused in one
sentence that starts with the option's name (or says who holds the robot); a reader never fails: each ConfigMap is a
reservation or one warning naming it."""

from __future__ import annotations

import datetime

from fuzz_bounds import fuzz_settings, run_case
from fuzz_values import hostile_value, mostly
from hypothesis import given
from hypothesis import strategies as st

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import pool
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import robot_pool

NOW = datetime.datetime(2026, 11, 28, 12, 0, tzinfo=datetime.UTC)
FIELDS = ("robot", "fleet", "owner", "reason", "until", "since", "identity")
VALID = {"robot": "fetch-1", "fleet": "test-fleet", "owner": "alice", "reason": "tests", "until": "2026-11-28T18:00:00Z",
         "since": "2026-11-28T10:00:00Z", "identity": "alice"}  # fmt: skip

zones = st.one_of(
    st.just(datetime.UTC),
    st.integers(-(24 * 60 - 1), 24 * 60 - 1).map(lambda m: datetime.timezone(datetime.timedelta(minutes=m))),
)
times = st.one_of(
    st.datetimes(timezones=zones).map(lambda t: t.isoformat()),
    st.datetimes(timezones=zones).map(lambda t: t.isoformat().replace("+00:00", "Z")),
    st.datetimes().map(lambda t: t.isoformat()),  # no zone
    st.sampled_from([
        "9999-12-31T23:59:59-12:00", "0001-01-01T00:00:00+14:00", "9999-12-31T23:59:59Z", "0001-01-01T00:00:00Z",
        "2026-11-28T18:00:00Z", "2026-11-28T18:00:00", "2026-02-30T00:00:00Z", "+275760-09-13T00:00:00Z",
        "2026-11-28T18:00:00Z\n", " 2026-11-28T18:00:00Z ", "2026-11-28T18:00:00.123456789Z", "2026-11-28",
        "2026-11-28T18:00:00+99:00", "2026-11-28T18:00:00ZZ", "1" * 400, "",
    ]),
)  # fmt: skip
durations = st.one_of(
    st.tuples(
        st.one_of(st.integers(0, 10**6).map(str), st.sampled_from(["9" * 400, "0.5", "1." + "0" * 300, "00", "1e3"])),
        st.sampled_from(["", " ", "\n", "\t"]),
        st.sampled_from(["m", "min", "h", "d", "s", "w", "D", "H", ""]),
        st.sampled_from(["", " ", "\n", "x"]),
    ).map("".join),
    st.sampled_from(["90d", "2160h", "129600m", "129601m", "100000000d", "8h", "0m", "-1h", "1.5h", "nan h", "inf d"]),
)


until_options = mostly(
    st.sampled_from(["8h", "90m", "2d", "90d", "2026-12-01T00:00:00Z"]), st.one_of(durations, times, st.text(max_size=80))
)
owners = mostly(
    st.sampled_from(["alice", "alice@example.com", "bob"]),
    st.one_of(st.sampled_from(["alice\n", "al ice", "a" * 63, "a" * 64, "", "-alice", "alice-", "é"]), st.text(max_size=70)),
)
reasons = mostly(
    st.sampled_from(["", "testing"]),
    st.one_of(st.sampled_from(["a\tb", "a\nb", "x" * 200, "x" * 201, "\u202e", "é" * 200]), st.text()),
)
names = st.one_of(st.sampled_from(["fetch-1", "test-fleet", "", " ", "a b", "x" * 254, "\x00"]), st.text(max_size=20))
field_values = {
    "robot": names, "fleet": names, "owner": owners, "reason": reasons, "until": times, "since": times,
    "identity": st.one_of(st.sampled_from(["", "alice", "system:admin", "x" * 257]), st.text(max_size=20)),
}  # fmt: skip


@st.composite
def configmaps(draw) -> dict:
    """A reservation ConfigMap as the API serves it: metadata and data (values text, but for the hostile ones)."""
    data = {}
    for field in FIELDS:
        kind = draw(st.sampled_from(["drawn", "drawn", "drawn", "valid", "missing", "hostile"]))
        if kind == "drawn":
            data[field] = draw(field_values[field])
        elif kind == "valid":
            data[field] = VALID[field]
        elif kind == "hostile":
            data[field] = draw(hostile_value)
    configmap = {
        "apiVersion": "v1",
        "kind": "ConfigMap",
        "metadata": {
            "name": draw(st.sampled_from(["kuberos-reservation-fetch-1", "kuberos-reservation-x"])),
            "namespace": "kuberos-test-fleet",
        },
        "data": data,
    }
    shape = draw(st.integers(0, 19))
    if shape == 0:
        configmap["data"] = draw(hostile_value)
    elif shape == 1:
        del configmap["data"]
    return configmap


class FakeKube:
    """The calls reserve and the readers make: the caller's identity, the stored reservation, the pool's ConfigMaps."""

    def __init__(self, stored=None, listed=(), identity="alice"):
        self.stored, self.listed, self.identity, self.applied = stored, list(listed), identity, []

    def create(self, obj):
        return {"status": {"userInfo": {"username": self.identity}}}

    def get(self, kind, name, namespace=""):
        return self.stored if kind == "ConfigMap" else {"metadata": {"name": name}}

    def list(self, kind, namespace="", selector=""):
        return self.listed if kind == "ConfigMap" and selector.startswith(pool.LABEL) else []

    def apply(self, obj, manager=""):
        self.applied.append(obj)
        return obj

    def delete(self, kind, name, namespace=""):
        self.stored = None


OPTIONS = (pool.HOLD_OPTION, "owner:", "reason:")


def option_located(error: KuberosError) -> str:
    message = str(error)
    if isinstance(error, robot_pool.PoolRefused):
        return "" if message.startswith("robot fetch-1 is ") else "does not name the robot"
    return "" if message.startswith(OPTIONS) else f"does not start with the option's name ({', '.join(OPTIONS)})"


@fuzz_settings(600)
@given(
    until=until_options,
    owner=owners,
    reason=reasons,
    stored=st.one_of(st.none(), configmaps()),
    identity=field_values["identity"],
    check_mode=st.booleans(),
)
def test_reserving_is_done_or_refused_naming_the_option(until, owner, reason, stored, identity, check_mode):
    kube = FakeKube(stored, identity=identity)
    case = {"until": until, "owner": owner, "reason": reason, "stored": stored}
    outcome = run_case(
        "pool-options",
        lambda: robot_pool.reserve(kube, "test-fleet", "fetch-1", owner, reason, until, check_mode),
        KuberosError,
        option_located,
        case,
    )
    if outcome.error is None:
        after = outcome.value["after"]
        assert NOW - datetime.timedelta(days=1) < after.until <= robot_pool.now() + pool.MAX_HOLD, case
        assert not pool.owner_problem(after.owner) and not pool.reason_problem(after.reason), case


@fuzz_settings(400)
@given(found=st.lists(configmaps(), max_size=4), moment=st.datetimes(timezones=st.just(datetime.UTC)))
def test_every_reader_reads_each_reservation_or_warns_of_it(found, moment):
    kube = FakeKube(listed=found)
    warned: list[str] = []

    def read_all():
        held = robot_pool.reservations(kube, "test-fleet", warn=warned.append)
        return held, robot_pool.listing(kube, moment), pool.held(held, moment)

    outcome = run_case("pool-reservations", read_all, (), lambda error: "", found)
    held, listing, _now_held = outcome.value
    assert len(held) + len(warned) == len(found), (held, warned)
    assert listing["ignored"] == warned and len(listing["reservations"]) == len(held)
    for warning in warned:
        assert warning.startswith("reservation kuberos-test-fleet/") and " ignored (it holds nothing): " in warning, warning
        assert "\n" not in warning and warning.isprintable(), warning
