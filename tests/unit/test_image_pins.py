"""Images pinned by digest (kuberos/image_pins.py): how a resolved tag is rendered and kept, and which images are
asked for. The registry side is tests/integration/test_image_pinning.py; a deploy's is tests/cluster."""

from __future__ import annotations

import base64
import json

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import image_pins
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.record import build_records, parse_record
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_deploy import image_digests

ONE = "sha256:" + "1" * 64
TWO = "sha256:" + "2" * 64


@pytest.mark.parametrize(
    "image, expected",
    [
        ("ghcr.io/kuberos/pnp-planner:0.1", ("ghcr.io", "kuberos/pnp-planner", "0.1")),
        ("ros:jazzy-ros-base", ("docker.io", "library/ros", "jazzy-ros-base")),
        ("osrf/ros:humble-desktop", ("docker.io", "osrf/ros", "humble-desktop")),
        ("10.0.0.5:5443/team/app", ("10.0.0.5:5443", "team/app", "latest")),
    ],
)
def test_an_image_is_asked_where_a_container_runtime_would_ask_for_it(image, expected):
    assert image_pins.registry_and_repository(image) == expected


def test_a_resolved_tag_is_rendered_with_its_digest_and_an_image_with_one_is_left_as_it_is():
    digests = {"ghcr.io/kuberos/app:1": ONE}
    assert image_pins.pinned("ghcr.io/kuberos/app:1", digests) == f"ghcr.io/kuberos/app:1@{ONE}"
    assert image_pins.pinned(f"ghcr.io/kuberos/app:1@{TWO}", digests) == f"ghcr.io/kuberos/app:1@{TWO}"
    assert image_pins.pinned("ghcr.io/kuberos/other:1", digests) == "ghcr.io/kuberos/other:1"
    assert image_pins.unpinned(["a/b:1", f"a/c:1@{ONE}", "a/b:1", ""]) == ["a/b:1"]


def spec(image: str) -> dict:
    return {
        "metadata": {"name": "app", "targetFleet": "test-fleet"},
        "rosModules": [{"name": "talker", "image": image, "launch": "ros2 run demo_nodes_cpp talker"}],
    }


def test_every_rendered_image_takes_its_digest_and_the_record_keeps_tag_and_digest(local_inventory, local_raw):
    import yaml

    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments

    text = yaml.safe_dump(spec("ghcr.io/kuberos/app:1"))
    [dep] = load_rosdeployments(text, "app.yml")
    placement = place_modules([dep], local_inventory)
    images = image_pins.deployment_images([dep], "ros:jazzy-ros-base", "ghcr.io/kuberos/bridge:0.2.0", with_bridge=False)
    assert images == ["ghcr.io/kuberos/app:1", "ros:jazzy-ros-base"]
    options = RenderOptions(image_digests=(("ghcr.io/kuberos/app:1", ONE), ("ros:jazzy-ros-base", TWO)))
    objects = render_deployment([dep], placement, options)
    rendered = {c["image"] for o in objects if o["kind"] == "Deployment" for c in o["spec"]["template"]["spec"]["containers"]}
    assert rendered == {f"ghcr.io/kuberos/app:1@{ONE}", f"ros:jazzy-ros-base@{TWO}"}
    _revision, record = build_records(text, "app.yml", [dep], placement, local_raw, options, "kuberos")
    assert json.loads(record["data"]["options.json"])["image_digests"] == dict(options.image_digests)
    assert parse_record(record).options.image_digests == options.image_digests, "the controller renders the same"


def test_pull_secrets_give_the_credentials_of_their_registries():
    config = {"auths": {"https://10.0.0.5:5443/": {"auth": base64.b64encode(b"robot:s3cret").decode()},
                        "ghcr.io": {"username": "ci", "password": "token"}}}  # fmt: skip
    secret = {"data": {".dockerconfigjson": base64.b64encode(json.dumps(config).encode()).decode()}}
    assert image_digests.credentials([secret, {"data": {}}]) == {
        "10.0.0.5:5443": ("robot", "s3cret"),
        "ghcr.io": ("ci", "token"),
    }


def test_a_mirror_is_asked_before_the_registry_itself_and_docker_hub_at_its_api_host():
    mirrors = {
        "docker.io": [{"url": "https://mirror.site:5000/", "ca": "/etc/ca.crt"}, {"url": "http://plain:80", "insecure": True}]
    }
    found = [(e.address, e.ca_file, e.insecure) for e in image_digests.endpoints("docker.io", mirrors)]
    assert found == [("mirror.site:5000", "/etc/ca.crt", False), ("plain:80", None, True), ("registry-1.docker.io", None, False)]
    assert [e.address for e in image_digests.endpoints("ghcr.io", mirrors)] == ["ghcr.io"]
