"""The committed bridge_pb2.py and bridge_pb2_grpc.py are what grpcio-tools (pinned) generates from bridge.proto."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

from helpers import ROOT

PACKAGE = os.path.join("ansible_collections", "kuberos", "platform", "plugins", "module_utils", "kuberos_bridge")
HERE = os.path.join(ROOT, "plugins", "module_utils", "kuberos_bridge")


def test_generated_code_matches_bridge_proto(tmp_path):
    target = tmp_path / PACKAGE
    target.mkdir(parents=True)
    shutil.copy(os.path.join(HERE, "bridge.proto"), target / "bridge.proto")
    command = [
        sys.executable, "-m", "grpc_tools.protoc", f"-I{tmp_path}", f"--python_out={tmp_path}",
        f"--grpc_python_out={tmp_path}", os.path.join(PACKAGE, "bridge.proto"),
    ]  # fmt: skip
    done = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    for name in ("bridge_pb2.py", "bridge_pb2_grpc.py"):
        with open(os.path.join(HERE, name), encoding="utf-8") as committed, open(target / name, encoding="utf-8") as fresh:
            assert committed.read() == fresh.read(), (
                f"{name} is stale: regenerate it from bridge.proto (the command is at the top of bridge.proto)"
            )


def test_the_generated_stub_names_the_method_the_bridge_serves():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_bridge import bridge_pb2, bridge_pb2_grpc, envelope

    service = bridge_pb2.DESCRIPTOR.services_by_name["Bridge"]
    assert f"/{service.full_name}/Exchange" == envelope.METHOD
    assert hasattr(bridge_pb2_grpc, "BridgeStub") and hasattr(bridge_pb2_grpc, "add_BridgeServicer_to_server")
