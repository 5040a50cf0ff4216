"""Why a pod cannot start because of its image, in one sentence (kuberos/status.py image_pull_problem): the image,
its registry and a cause a developer acts on, from the kubelet's own messages (as containerd 1.6 words them)."""

from __future__ import annotations

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import image_pull_problem, image_registry

IMAGE = "10.241.0.1:5443/kuberos/ros@sha256:5d41402abc4b2a76b9719d911017c592"
PREFIX = f'failed to pull and unpack image "{IMAGE}": failed to resolve reference "{IMAGE}": '


@pytest.mark.parametrize(
    "reason, message, cause",
    [
        ("ErrImagePull", PREFIX + "unexpected status from HEAD request to https://10.241.0.1:5443/v2/kuberos/ros/"
         "manifests/sha256:5d41: 401 Unauthorized", "the registry refused the credentials"),
        ("ErrImagePull", PREFIX + f"{IMAGE}: not found", "the registry has no such image"),
        ("ErrImagePull", PREFIX + "failed to do request: Head \"https://10.241.0.1:5443/v2/\": tls: failed to verify "
         "certificate: x509: certificate signed by unknown authority", "the node does not trust the registry's certificate"),
        ("ErrImagePull", PREFIX + "failed to do request: dial tcp 10.241.0.1:5443: connect: connection refused",
         "the node cannot reach the registry"),
        ("ImagePullBackOff", f'Back-off pulling image "{IMAGE}"', "the pull failed"),
        ("ErrImageNeverPull", f'Container image "{IMAGE}" is not present with pull policy of Never',
         "imagePullPolicy is Never"),
        ("InvalidImageName", 'Failed to apply default image tag "Bad Name": couldn\'t parse image name',
         "the image name is not valid"),
    ],
)  # fmt: skip
def test_the_cause_is_named_with_the_image_and_its_registry(reason, message, cause):
    text = image_pull_problem(IMAGE, reason, message)
    assert text.startswith(f"image {IMAGE} from registry 10.241.0.1:5443: {cause}"), text
    assert f"({reason}: " in text and len(text) < 600 and "\n" not in text


@pytest.mark.parametrize(
    "image, registry",
    [
        ("ros:jazzy-ros-base", "docker.io"),
        ("osrf/ros:jazzy-desktop", "docker.io"),
        ("ghcr.io/kuberos/pnp-planner:0.1", "ghcr.io"),
        ("localhost/app", "localhost"),
        ("10.0.0.1:5000/team/app@sha256:00", "10.0.0.1:5000"),
    ],
)
def test_the_registry_of_an_image(image, registry):
    assert image_registry(image) == registry


def test_every_compared_row_says_its_problem_remote_rows_included():
    """The deploy's wait reads each row's ``problem``: a module in a third-party cluster has none here."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import compare

    row = {
        "deployment": "app",
        "fleet": "f",
        "robot": "r1",
        "module": "m",
        "tier": "edge",
        "node": "edge-1",
        "instance": "app-m-r1",
    }
    placement = {"placements": [row, {**row, "module": "far", "instance": "app-far-r1", "cluster": "partner", "tier": "cloud"}]}
    pod = {"fleet": "f", "instance": "app-m-r1", "node": "edge-1", "phase": "Pending", "ready": False, "pod": "p1",
           "problem": image_pull_problem(IMAGE, "ErrImagePull", PREFIX + "not found")}  # fmt: skip
    rows = {r["module"]: r for r in compare(placement, [pod])}
    assert rows["far"]["phase"] == "Remote" and rows["far"]["problem"] == ""
    assert rows["m"]["problem"].startswith(f"image {IMAGE} from registry 10.241.0.1:5443: the registry has no such image")
    assert compare({"placements": [row]}, [])[0]["problem"] == "", "no pod yet: no problem"


class _Events:
    """The core client's event LIST for one pod, as the kubelet's Failed events."""

    def __init__(self, events):
        self.events = events

    def list_namespaced_event(self, namespace, field_selector, _preload_content):
        import json

        assert (namespace, field_selector) == ("ns", "involvedObject.uid=u1,reason=Failed")

        class Response:
            data = json.dumps({"items": self.events}).encode()

        return Response()


def _stuck_pod(reason, message):
    waiting = {"reason": reason, "message": message}
    return {
        "metadata": {"namespace": "ns", "uid": "u1"},
        "status": {"containerStatuses": [{"image": IMAGE, "state": {"waiting": waiting}}]},
    }


def test_a_backing_off_container_takes_its_cause_from_the_event_that_names_it_not_the_generic_ones():
    """The kubelet records "Error: ErrImagePull" and "Error: ImagePullBackOff" as Failed events too, often later in
    the same second than the one that says why; the cause comes from "Failed to pull image ...", whatever the order."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import _image_problem

    events = [
        {"message": f'Failed to pull image "{IMAGE}": {PREFIX}401 Unauthorized', "lastTimestamp": "2026-11-27T09:00:01Z"},
        {"message": "Error: ErrImagePull", "lastTimestamp": "2026-11-27T09:00:01Z"},
        {"message": "Error: ImagePullBackOff", "lastTimestamp": "2026-11-27T09:00:02Z"},
    ]
    text, final = _image_problem({"core": _Events(events)}, _stuck_pod("ImagePullBackOff", f'Back-off pulling image "{IMAGE}"'))
    assert text.startswith(f"image {IMAGE} from registry 10.241.0.1:5443: the registry refused the credentials"), text
    assert not final, "one failed try: the kubelet tries again (a pull secret may not have reached its cache yet)"


@pytest.mark.parametrize(
    "counts, final",
    [((1,), False), ((2,), True), ((1, 1), True), ((), False)],
)
def test_a_failed_pull_is_final_once_the_kubelet_has_failed_it_twice(counts, final):
    """Two tries (one event seen twice, or two events with different words) make the problem final; one does not,
    even while the container still shows that first failure during the second pull."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import _image_problem

    events = [
        {"message": f'Failed to pull image "{IMAGE}": {PREFIX}attempt {n}: 401 Unauthorized', "count": count,
         "lastTimestamp": f"2026-11-27T09:00:0{n}Z"}
        for n, count in enumerate(counts)
    ] + [{"message": "Error: ErrImagePull", "count": 5}]  # fmt: skip
    text, is_final = _image_problem({"core": _Events(events)}, _stuck_pod("ErrImagePull", PREFIX + "401 Unauthorized"))
    assert "the registry refused the credentials" in text and is_final is final


def test_an_image_the_kubelet_never_tries_again_is_final_at_once():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy.cluster_state import _image_problem

    never = _stuck_pod("ErrImageNeverPull", f'Container image "{IMAGE}" is not present with pull policy of Never')
    text, final = _image_problem({"core": _Events([])}, never)
    assert "imagePullPolicy is Never" in text and final
    assert _image_problem({"core": _Events([])}, {"metadata": {}, "status": {}}) == ("", False)


def _pod(phase, **status):
    return {"status": {"phase": phase, **status}}


@pytest.mark.parametrize(
    "pod, note",
    [
        (_pod("Failed", reason="Evicted", message="The node was low on resource: ephemeral-storage. "),
         "Evicted: The node was low on resource: ephemeral-storage."),
        (_pod("Failed", reason="Terminated", message="Pod was terminated in response to imminent node shutdown."),
         "Terminated: Pod was terminated in response to imminent node shutdown."),
        (_pod("Succeeded"), "ended (Succeeded)"),
        (_pod("Pending", conditions=[{"type": "PodScheduled", "status": "False", "reason": "Unschedulable", "message":
              "0/8 nodes are available: 8 node(s) had untolerated taint {node.kubernetes.io/disk-pressure: }."}]),
         "not scheduled: 0/8 nodes are available: 8 node(s) had untolerated taint {node.kubernetes.io/disk-pressure: }."),
        (_pod("Running", containerStatuses=[{"name": "main", "state": {"waiting": {"reason": "CrashLoopBackOff"}},
                                             "lastState": {"terminated": {"exitCode": 1}}}]),
         "container main: CrashLoopBackOff, last exit code 1"),
        (_pod("Pending", containerStatuses=[{"name": "main", "state": {"waiting": {"reason": "ContainerCreating"}}}]), ""),
        (_pod("Running"), ""),
    ],
)  # fmt: skip
def test_a_pod_that_is_not_ready_says_why_in_the_clusters_words(pod, note):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import pod_note

    assert pod_note(pod) == note


def test_an_ended_pod_its_deployment_replaced_is_history_the_new_one_is_compared():
    """An evicted pod stays listed (Failed) beside its replacement: the row is the replacement's, with its note."""
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.status import compare

    row = {"deployment": "app", "fleet": "f", "robot": "r1", "module": "m", "tier": "edge", "node": "edge-1",
           "instance": "app-m-r1"}  # fmt: skip
    ended = {"fleet": "f", "instance": "app-m-r1", "node": "edge-1", "phase": "Failed", "ready": False, "pod": "old",
             "note": "Evicted: The node was low on resource: memory."}  # fmt: skip
    waiting = {**ended, "node": None, "phase": "Pending", "pod": "new", "note": "not scheduled: 0/1 nodes are available"}
    [compared] = compare({"placements": [row]}, [ended, waiting])
    assert (compared["pod"], compared["phase"], compared["note"]) == ("new", "Pending", waiting["note"])
    [alone] = compare({"placements": [row]}, [ended])
    assert (alone["pod"], alone["note"]) == ("old", ended["note"]), "with nothing newer, the ended pod says why"
