"""register_robot.yml's second play: the robot's bootstrap token comes from the first control plane whose API server
answers, whichever it is (the first control plane may be down or being rebuilt), and with none answering the join is
refused with one sentence before anything is asked of the robot. Its control planes here: one unreachable over SSH,
one whose API server port is closed and one answering ``/livez`` over TLS on loopback (``ansible_connection=local``).
"""

from __future__ import annotations

import yaml
from helpers import playbook
from hostile_registry import HostileRegistry, closed_port, send


def _inventory(tmp_path, live_port: int) -> str:
    local = {"ansible_connection": "local", "ansible_python_interpreter": "{{ ansible_playbook_python }}"}
    hosts = {
        "cp-down": {"ansible_host": "127.0.0.1", "ansible_port": closed_port(), "ansible_user": "nobody",
                    "ansible_ssh_common_args": "-o ConnectTimeout=3 -o BatchMode=yes"},
        "cp-silent": {**local, "kubeadm_init_bind_port": closed_port()},
        "cp-live": {**local, "kubeadm_init_bind_port": live_port},
    }  # fmt: skip
    path = tmp_path / "hosts.yml"
    path.write_text(yaml.safe_dump({"all": {"children": {"control_plane": {"hosts": hosts}}}}, sort_keys=False))
    return str(path)


def _token_play(inventory: str):
    return playbook("register_robot.yml", "--tags", "kuberos_token_host", "-e", "robot_register_name=fetch-9",
                    "-e", "ansible_become=false", inventory=inventory, timeout=300)  # fmt: skip


def test_the_bootstrap_token_comes_from_the_first_control_plane_that_answers(tmp_path):
    with HostileRegistry(str(tmp_path)) as server:
        server.routes["/livez"] = lambda handler: send(handler, 200, body=b"ok")
        done = _token_play(_inventory(tmp_path, server.port))
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "the bootstrap token for fetch-9 comes from cp-live" in done.stdout, done.stdout[-3000:]
    assert any(path == "/livez" for _method, _host, path, _auth in server.requests), server.requests


def test_with_no_control_plane_answering_the_join_is_refused_in_one_sentence(tmp_path):
    done = _token_play(_inventory(tmp_path, closed_port()))
    assert done.returncode != 0
    said = " ".join(done.stdout.split())
    assert "no control plane's API server answers (cp-down, cp-silent, cp-live)" in said, done.stdout[-3000:]
    assert "-e robot_register_join=false skips the join" in said, done.stdout[-3000:]
