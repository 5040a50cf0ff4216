"""The pure parts of robot registration: what a robot reports, read into inventory variables."""

from __future__ import annotations

import base64
import hashlib

import pytest
import yaml

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site import robot_registration as rr


@pytest.mark.parametrize(
    ("meminfo", "expected"),
    [
        ("MemTotal:        8000000 kB\nMemFree:  1 kB\n", "7812Mi"),  # 7812.5 MiB, rounded down
        ("MemTotal:        8388608 kB\n", "8Gi"),
        ("MemFree: 5 kB\nMemTotal:  24684092 kB\n", "24105Mi"),
        ("MemTotal: 1024 kB\n", "1Mi"),
    ],
)
def test_memory_quantity(meminfo, expected):
    assert rr.memory_quantity(meminfo) == expected
    assert quantities.parse_memory(expected) <= int(meminfo.split("MemTotal:")[1].split()[0]) * 1024


@pytest.mark.parametrize("meminfo", ["", "MemFree: 10 kB\n", "MemTotal: 12 kB\n", "MemTotal: lots kB\n"])
def test_memory_quantity_rejects(meminfo):
    with pytest.raises(ValueError, match="MemTotal"):
        rr.memory_quantity(meminfo)


@pytest.mark.parametrize(
    ("machine", "expected"),
    [("x86_64", "amd64"), ("aarch64", "arm64"), ("arm64", "arm64"), ("armv7l", "arm"), ("i686", "386"),
     ("riscv64", "riscv64"), ("x86_64\n", "amd64")],
)  # fmt: skip
def test_kubernetes_arch(machine, expected):
    assert rr.kubernetes_arch(machine) == expected


def test_kubernetes_arch_rejects_unknown():
    with pytest.raises(ValueError, match="unknown machine architecture 'vax'"):
        rr.kubernetes_arch("vax")


@pytest.mark.parametrize(
    ("paths", "extra", "expected"),
    [
        (["/dev/video0", "/dev/ttyUSB0"], [], ["camera", "serial"]),
        (["/dev/video0", "/dev/video1"], [], ["camera"]),
        (["/dev/ttyACM0"], ["lidar"], ["lidar", "serial"]),
        ([], [], []),
        (["/dev/videoX/../ttyUSB0"], [], ["camera"]),  # fnmatch's * crosses '/', but the shell glob never yields this
        (["/dev/nvidia0"], ["gripper", "gripper"], ["gripper"]),
    ],
)
def test_device_names(paths, extra, expected):
    assert rr.device_names(paths, rr.DEFAULT_DEVICE_GLOBS, extra) == expected


@pytest.mark.parametrize(
    ("globs", "message"),
    [
        ({"/dev/video*; rm -rf /": "camera"}, "not valid"),
        ({"dev/video*": "camera"}, "not valid"),
        ({"/dev/video*": "Camera"}, "device name 'Camera'"),
        ({"/dev/video*": ""}, "device name ''"),
        (["/dev/video*"], "mapping"),
    ],
)
def test_device_globs_are_checked(globs, message):
    with pytest.raises(ValueError, match=message):
        rr.check_device_globs(globs)


@pytest.mark.parametrize(
    ("smi", "paths", "expected"),
    [
        ("GPU 0: Orin (UUID: GPU-1)\nGPU 1: Orin (UUID: GPU-2)\n", [], 2),
        ("No devices were found\n", ["/dev/nvidia0"], 0),  # nvidia-smi ran: it is the truth
        (None, ["/dev/nvidia0", "/dev/nvidia1", "/dev/nvidiactl", "/dev/nvidia-uvm"], 2),
        (None, ["/dev/video0"], 0),
    ],
)
def test_gpu_count(smi, paths, expected):
    assert rr.gpu_count(smi, paths) == expected


def report_output(**overrides) -> str:
    sections = {
        "nproc": "4",
        "meminfo": "MemTotal:        8000000 kB\nMemFree: 10 kB",
        "uname": "aarch64",
        "nvidia-smi": "@@absent",
        "paths": "/dev/nvidia0\n/dev/video0\n/dev/ttyACM0",
        "authorized_keys": "600\nssh-ed25519 AAAAold admin\n",
        **overrides,
    }
    return "".join(f"@@kuberos-register:{name}\n{text}\n" for name, text in sections.items())


def test_parse_report():
    report = rr.parse_report(report_output(), rr.DEFAULT_DEVICE_GLOBS, ["lidar"])
    assert (report.cpu, report.memory, report.arch, report.gpu) == (4, "7812Mi", "arm64", 1)
    assert report.devices == ["camera", "lidar", "serial"]
    assert report.authorized_keys_mode == "600"
    assert rr.has_key(report.authorized_keys, "ssh-ed25519 AAAAold")


def test_parse_report_without_authorized_keys():
    report = rr.parse_report(report_output(authorized_keys=""), rr.DEFAULT_DEVICE_GLOBS)
    assert (report.authorized_keys_mode, report.authorized_keys) == ("", "")


@pytest.mark.parametrize(
    ("overrides", "message"),
    [({"nproc": "many"}, "nproc reported 'many'"), ({"meminfo": "MemFree: 1 kB"}, "MemTotal"), ({"uname": "pdp11"}, "pdp11")],
)
def test_parse_report_rejects(overrides, message):
    with pytest.raises(ValueError, match=message):
        rr.parse_report(report_output(**overrides), rr.DEFAULT_DEVICE_GLOBS)


def test_parse_report_needs_every_section():
    with pytest.raises(ValueError, match="lacks the sections uname"):
        rr.parse_report(report_output().replace("@@kuberos-register:uname\n", ""), rr.DEFAULT_DEVICE_GLOBS)


def test_facts_script_expands_only_checked_globs():
    script = rr.facts_script({"/dev/video*": "camera", "/dev/ttyUSB*": "serial"})
    assert "for p in /dev/nvidia[0-9]* /dev/ttyUSB* /dev/video*; do" in script


@pytest.mark.parametrize(
    ("authorized", "present"),
    [
        ("ssh-ed25519 AAAAkey cluster\n", True),
        ('from="10.0.0.0/8",no-pty ssh-ed25519 AAAAkey other-comment\n', True),
        ("ssh-ed25519 AAAAother cluster\nssh-rsa AAAAkey\n", False),
        ("# ssh-ed25519 AAAAkey\n", False),
        ("", False),
    ],
)
def test_has_key(authorized, present):
    assert rr.has_key(authorized, "ssh-ed25519 AAAAkey") is present


def test_public_key_line():
    assert rr.public_key_line("ssh-ed25519 AAAAC3Nz cluster@site\n", "c.pub") == (
        "ssh-ed25519 AAAAC3Nz cluster@site",
        "ssh-ed25519 AAAAC3Nz",
    )
    for bad in ("", "-----BEGIN OPENSSH PRIVATE KEY-----\nxx\n", "ssh-ed25519 A\nssh-ed25519 B\n", "ssh-ed25519 !!!\n"):
        with pytest.raises(ValueError, match=r"c\.pub"):
            rr.public_key_line(bad, "c.pub")


def test_fingerprints():
    blob = b"\x00\x00\x00\x0bssh-ed25519" + bytes(36)
    expected = "SHA256:" + base64.b64encode(hashlib.sha256(blob).digest()).decode().rstrip("=")
    assert rr.fingerprint_of_blob(blob) == expected
    assert rr.normalize_fingerprint(expected[7:] + "=") == expected
    assert rr.normalize_fingerprint(" " + expected + " ") == expected
    with pytest.raises(ValueError, match="not a SHA256 fingerprint"):
        rr.normalize_fingerprint("MD5:aa:bb")


def test_known_hosts_name():
    assert rr.known_hosts_name("10.0.0.5", 22) == "10.0.0.5"
    assert rr.known_hosts_name("10.0.0.5", 2222) == "[10.0.0.5]:2222"


def test_host_vars_make_a_robot_the_scheduler_accepts():
    report = rr.parse_report(report_output(), rr.DEFAULT_DEVICE_GLOBS)
    host_vars = rr.host_vars_for("test-fleet", "10.0.0.9", "root", report)
    rr.check_robot("fetch-9", host_vars)
    inventory = load_inventory({"hosts": {"fetch-9": host_vars}, "groups": {"robots": ["fetch-9"]}})
    node = inventory.nodes["fetch-9"]
    assert (node.cpu_millis, node.memory_bytes, node.arch, node.gpu) == (4000, 7812 * 1024**2, "arm64", 1)
    assert node.devices == {"camera", "serial"} and node.fleet == "test-fleet"


def test_an_invalid_robot_is_refused_before_writing():
    report = rr.parse_report(report_output(), rr.DEFAULT_DEVICE_GLOBS)
    with pytest.raises(rr.RegistrationError, match="fetch_9 would not be a valid inventory entry"):
        rr.check_robot("fetch_9", rr.host_vars_for("test-fleet", "10.0.0.9", "root", report))


def test_host_vars_text_keeps_other_keys_and_replaces_facts():
    existing = "kuberos_cpu: 2\nkuberos_link_latency_ms: {cloud-1: 80}\n"
    text = rr.host_vars_text(existing, {"kuberos_cpu": 4, "kuberos_fleet": "f"}, "hv.yml")
    assert text.startswith("# Written by kuberos.platform.robot_register")
    assert yaml.safe_load(text) == {"kuberos_cpu": 4, "kuberos_fleet": "f", "kuberos_link_latency_ms": {"cloud-1": 80}}
    assert rr.host_vars_text(text, {"kuberos_cpu": 4, "kuberos_fleet": "f"}, "hv.yml") == text  # a fixed point
    with pytest.raises(rr.RegistrationError, match=r"hv\.yml is not a mapping"):
        rr.host_vars_text("- a\n", {}, "hv.yml")


def test_registered_text_adds_each_robot_once_and_sorted():
    first = rr.registered_text(None, "fetch-9", "r.yml")
    both = rr.registered_text(rr.registered_text(first, "alpha-1", "r.yml"), "fetch-9", "r.yml")
    assert yaml.safe_load(both) == {"all": {"children": {"robots": {"hosts": {"alpha-1": {}, "fetch-9": {}}}}}}
    assert rr.registered_text(both, "alpha-1", "r.yml") == both
    with pytest.raises(rr.RegistrationError, match=r"r\.yml is not the file robot_register writes"):
        rr.registered_text("robots: [a]\n", "fetch-9", "r.yml")


def test_write_all_puts_back_what_it_wrote_when_a_write_fails(tmp_path):
    kept = tmp_path / "kept.yml"
    kept.write_text("old\n")
    new = tmp_path / "new.yml"
    blocked = tmp_path / "file" / "x.yml"
    (tmp_path / "file").write_text("a file, not a directory")
    with pytest.raises(rr.RegistrationError, match="nothing was kept"):
        rr.write_all([(str(kept), "new\n", "old\n"), (str(new), "n\n", None), (str(blocked), "x\n", None)])
    assert kept.read_text() == "old\n"
    assert not new.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "kept.yml"]  # no temporary files left


def test_a_refused_connection_is_one_sentence(tmp_path):
    import socket

    with socket.socket() as probe:  # a loopback port nobody listens on
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    target = rr.Target("fetch-9", "127.0.0.1", port, "root", "admin_ed25519", str(tmp_path / ".known_hosts"), connect_timeout=2)
    with pytest.raises(rr.RegistrationError) as error:
        rr.connect(target, admin_key=None)
    assert str(error.value).startswith(f"cannot reach robot fetch-9 at 127.0.0.1:{port}: connection refused; check that")
    assert not (tmp_path / ".known_hosts").exists()
