"""Launch lines run without a shell: one container per line, each a literal argv.

The rendered containers are run here as the kubelet would start them (command + args, no shell), in a temporary
directory: a ``$(...)``, a ``;``, a ``&&`` or a ``#`` in a launch line reaches the program as text and runs
nothing. A negative control runs the same lines the way they were rendered before (``bash -c "a & b & wait -n"``)
and sees the injected command run, so the check can fail.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys

import kubernetes_validate
import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.launch import container_name, launch_argv, split_amount
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.manifests import RenderOptions, render_deployment
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.quantities import parse_cpu, parse_memory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.scheduler import place_modules
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments

# A program that prints its arguments as JSON: what a module would receive.
PRINT_ARGV = f"{shlex.quote(sys.executable)} -c 'import json, sys; print(json.dumps(sys.argv[1:]))'"
HOSTILE = [
    f"{PRINT_ARGV} $(touch substituted) `touch backquoted` ; touch after-semicolon # touch commented",
    f"{PRINT_ARGV} && touch after-and | touch piped > redirected $HOME *",
    f"{PRINT_ARGV} '$(touch quoted)' \"two words\" --ros-args -p name:=a#b",
]
EXPECTED_ARGS = [
    ["$(touch", "substituted)", "`touch", "backquoted`", ";", "touch", "after-semicolon", "#", "touch", "commented"],
    ["&&", "touch", "after-and", "|", "touch", "piped", ">", "redirected", "$HOME", "*"],
    ["$(touch quoted)", "two words", "--ros-args", "-p", "name:=a#b"],
]


def spec_text(launch: list[str], resources: str = "{cpu: 1, memory: 1Gi, gpu: 1}") -> str:
    return (
        "metadata: {name: hostile, targetFleet: warehouse-fleet}\n"
        "rosModules:\n"
        "- name: scanner\n"
        "  image: ghcr.io/example/scanner:1.0\n"
        f"  launch: {json.dumps(launch)}\n"
        "  preference: cloud\n"
        "  strategy: shared\n"
        f"  resources: {resources}\n"
        "  env: {LOG_LEVEL: debug}\n"
        "  rosParameters: {rate: 2}\n"
    )


def rendered_pod(local_inventory, launch: list[str], resources: str = "{cpu: 1, memory: 1Gi, gpu: 1}") -> dict:
    deployments = load_rosdeployments(spec_text(launch, resources), "hostile.yml")
    placement = place_modules(deployments, local_inventory)
    objects = render_deployment(deployments, placement, RenderOptions())
    module = next(o for o in objects if o["kind"] == "Deployment" and o["metadata"]["labels"].get("kuberos.io/module"))
    kubernetes_validate.validate(module, "1.34", strict=True)
    return module["spec"]["template"]["spec"]


def run_container(container: dict, cwd) -> list[str]:
    """Start a container's process as the kubelet does for an image without an entrypoint: command + args, no shell."""
    argv = [*container.get("command", []), *container.get("args", [])]
    done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=60, check=True)
    return json.loads(done.stdout)


def test_hostile_launch_lines_run_literally_and_execute_nothing(local_inventory, tmp_path):
    pod = rendered_pod(local_inventory, HOSTILE)
    containers = pod["containers"]
    assert [c["name"] for c in containers] == ["scanner", "scanner-1", "scanner-2"]
    assert all("command" not in c for c in containers), "the image's entrypoint stays"
    received = [run_container(c, tmp_path) for c in containers]
    assert received == EXPECTED_ARGS
    assert sorted(os.listdir(tmp_path)) == [], "a launch line ran a command of its own"


def test_the_old_shell_rendering_would_have_run_the_injected_commands(tmp_path):
    """Negative control: the same lines through bash, as rendered before, run what they carry, and the first
    line's ``#`` drops the lines after it."""
    script = " & ".join(HOSTILE) + " & wait -n"
    done = subprocess.run(["/bin/bash", "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=60, check=False)
    assert sorted(os.listdir(tmp_path)) == ["after-semicolon", "backquoted", "substituted"]
    assert "two words" not in done.stdout, "the third line never ran"


def test_a_single_launch_line_is_one_plain_container(local_inventory, tmp_path):
    pod = rendered_pod(local_inventory, [HOSTILE[0]])
    (container,) = pod["containers"]
    assert container["name"] == "scanner"
    assert container["args"] == [sys.executable, "-c", "import json, sys; print(json.dumps(sys.argv[1:]))", *EXPECTED_ARGS[0]]
    assert container["resources"] == {
        "requests": {"cpu": "1", "memory": "1Gi", "nvidia.com/gpu": "1"},
        "limits": {"memory": "1Gi", "nvidia.com/gpu": "1"},
    }
    assert run_container(container, tmp_path) == EXPECTED_ARGS[0]
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    ("resources", "cpu", "memory"),
    [
        ("{cpu: 1, memory: 1Gi, gpu: 1}", ["334m", "333m", "333m"], ["357913942", "357913941", "357913941"]),
        ("{cpu: 300m, memory: 3Mi, gpu: 1}", ["100m", "100m", "100m"], ["1Mi", "1Mi", "1Mi"]),
    ],
)
def test_every_container_shares_the_module_and_the_requests_add_up_to_the_placement(local_inventory, resources, cpu, memory):
    pod = rendered_pod(local_inventory, HOSTILE, resources)
    containers = pod["containers"]
    assert [c["resources"]["requests"]["cpu"] for c in containers] == cpu
    assert [c["resources"]["requests"]["memory"] for c in containers] == memory
    assert [c["resources"]["limits"]["memory"] for c in containers] == memory, "each container's limit is its share"
    # what the placement counted, exactly (the controller and node_allocations sum every container's requests)
    requested = {
        "cpu": sum(parse_cpu(c["resources"]["requests"]["cpu"]) for c in containers),
        "memory": sum(parse_memory(c["resources"]["requests"]["memory"]) for c in containers),
        "gpu": sum(int(c["resources"]["requests"].get("nvidia.com/gpu", "0")) for c in containers),
    }
    deployments = load_rosdeployments(spec_text(HOSTILE, resources), "hostile.yml")
    (inst,) = place_modules(deployments, local_inventory).instances
    assert requested == {"cpu": inst.cpu_millis, "memory": inst.memory_bytes, "gpu": inst.gpu}
    assert [c["resources"]["requests"].get("nvidia.com/gpu") for c in containers] == ["1", None, None], "a GPU serves one"
    first = containers[0]
    for container in containers:
        assert container["image"] == first["image"] and container["env"] == first["env"]
        assert container["volumeMounts"] == [{"name": "ros-parameters", "mountPath": "/etc/kuberos", "readOnly": True}]
    env = {e["name"]: e.get("value") for e in first["env"]}
    assert env["LOG_LEVEL"] == "debug" and env["KUBEROS_PARAMS_FILE"] == "/etc/kuberos/params.yaml"
    assert env["ROS_DISCOVERY_SERVER"].startswith("$(KUBEROS_DISCOVERY_0_SERVICE_HOST):")  # expanded by the kubelet
    assert inst.namespace == "kuberos-warehouse-fleet", "in the namespace of its fleet's discovery Services"


@pytest.mark.parametrize(
    ("line", "argv"),
    [
        ("ros2 launch pkg file.launch.py", ["ros2", "launch", "pkg", "file.launch.py"]),
        ("a 'b c' \"d e\" f\\ g", ["a", "b c", "d e", "f g"]),
        ("a # b", ["a", "#", "b"]),
        ("a;b", ["a;b"]),
        ("a $(KUBEROS_ROBOT_NAME)", ["a", "$(KUBEROS_ROBOT_NAME)"]),
    ],
)
def test_launch_argv(line, argv):
    assert launch_argv(line) == argv


@pytest.mark.parametrize("line", ["", "   ", "a 'unclosed"])
def test_launch_argv_refuses_what_is_no_command(line):
    with pytest.raises(ValueError):
        launch_argv(line)


def test_container_names_and_shares():
    assert [container_name("driver", n) for n in range(3)] == ["driver", "driver-1", "driver-2"]
    assert split_amount(1000, 3) == [334, 333, 333] and split_amount(5, 1) == [5] and split_amount(1, 2) == [1, 0]
    with pytest.raises(ValueError):
        split_amount(1, 0)


@pytest.mark.parametrize("name", ["listing1", "pick-and-place", "two-fleets"])
def test_no_rendered_module_starts_a_shell(root, local_inventory, name):
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployment_file

    deployments = load_rosdeployment_file(f"{root}/examples/{name}.yml", f"examples/{name}.yml")
    objects = render_deployment(deployments, place_modules(deployments, local_inventory), RenderOptions())
    modules = [o for o in objects if o["kind"] == "Deployment" and o["metadata"]["labels"].get("kuberos.io/module")]
    assert modules
    for obj in modules:
        module = next(m for d in deployments for m in d.modules if m.name == obj["metadata"]["labels"]["kuberos.io/module"])
        containers = obj["spec"]["template"]["spec"]["containers"]
        assert [c["args"] for c in containers] == [launch_argv(line) for line in module.launch]
        for container in containers:
            argv = [*container.get("command", []), *container.get("args", [])]
            assert os.path.basename(argv[0]) not in ("sh", "bash", "dash", "zsh") and "-c" not in argv[:2], argv
