"""Registering a robot by SSH: pin its host key, install the cluster's key, read its hardware, write the inventory.

The flow (``register``): connect with the administrator's key only (paramiko, no agent, no other keys), check
the host key against the site's pinned keys (a known_hosts file; the first contact pins it, or checks it against
an expected fingerprint), authenticate, read the hardware with one read-only shell script, and only when every
step succeeded: install the cluster's public key in the login user's ``~/.ssh/authorized_keys`` (appended once),
then write ``<inventory>/host_vars/<robot>.yml``, the pin and ``<inventory>/registered_robots.yml`` (the robot's
membership of the group ``robots``), each file atomically, the membership last. A failure at any point writes
nothing; a failed local write restores the files already replaced.

The parsing of what the robot reports (``parse_report``, ``memory_quantity``, ``kubernetes_arch``,
``device_names``, ``gpu_count``) is pure and unit-tested; ``RegistrationError`` carries one sentence for the user.
"""

from __future__ import annotations

import base64
import errno
import fnmatch
import hashlib
import os
import re
import shlex
import socket
import tempfile
from dataclasses import dataclass, field

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import KuberosError, SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.inventory import load_inventory
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.third_party import yaml
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos_site.files import text_or_none

try:
    import paramiko
except ImportError:  # reported by the module with missing_required_lib
    paramiko = None

DEFAULT_DEVICE_GLOBS = {"/dev/video*": "camera", "/dev/ttyUSB*": "serial", "/dev/ttyACM*": "serial"}
# uname -m -> the Kubernetes (GOARCH) name the inventory's kuberos_arch uses.
ARCHITECTURES = {
    "x86_64": "amd64", "amd64": "amd64",
    "aarch64": "arm64", "arm64": "arm64", "aarch64_be": "arm64",
    "armv7l": "arm", "armv7": "arm", "armv6l": "arm", "armhf": "arm",
    "i386": "386", "i486": "386", "i586": "386", "i686": "386",
    "ppc64le": "ppc64le", "s390x": "s390x", "riscv64": "riscv64", "loongarch64": "loong64",
}  # fmt: skip
GPU_DEVICE_GLOB = "/dev/nvidia[0-9]*"
MANAGED_VARS = (
    "kuberos_fleet", "kuberos_cpu", "kuberos_memory", "kuberos_gpu", "kuberos_arch", "kuberos_devices",
    "kuberos_address", "ansible_host", "ansible_user",
)  # fmt: skip
REGISTERED_ROBOTS = "registered_robots.yml"
HOST_VARS_HEADER = (
    "# Written by kuberos.platform.robot_register from what the robot reported (playbooks/register_robot.yml).\n"
    "# Registering again rewrites the kuberos_* facts and the connection variables above; other keys are kept.\n"
)
REGISTERED_HEADER = (
    "# Robots registered by kuberos.platform.robot_register (playbooks/register_robot.yml): members of the group\n"
    "# robots. Their facts are in host_vars/<robot>.yml. Load this inventory as a directory (-i <this directory>).\n"
)
_GLOB = re.compile(r"^/[A-Za-z0-9_./*?\[\]+-]+$")
_DEVICE_NAME = re.compile(r"^[a-z0-9]([-a-z0-9.]*[a-z0-9])?$")
_MARK = "@@kuberos-register:"
SECTIONS = ("nproc", "meminfo", "uname", "nvidia-smi", "paths", "authorized_keys")


class RegistrationError(KuberosError):
    """Registration stopped; the message is one sentence for the person running it. Nothing was written."""


# --- the pure parts ---------------------------------------------------------------------------------------------


def memory_quantity(meminfo: str) -> str:
    """``MemTotal`` of /proc/meminfo as a Kubernetes quantity, rounded down to whole MiB: ``'7812Mi'``, ``'8Gi'``."""
    match = re.search(r"^MemTotal:\s+(\d+)\s*kB\s*$", meminfo, re.M)
    if not match:
        raise ValueError("/proc/meminfo has no 'MemTotal: <n> kB' line")
    mebibytes = int(match.group(1)) // 1024
    if mebibytes <= 0:
        raise ValueError(f"/proc/meminfo reports MemTotal {match.group(1)} kB, less than 1 MiB")
    return quantities.format_memory(mebibytes * 1024**2)


def kubernetes_arch(machine: str) -> str:
    """``uname -m`` as the architecture name Kubernetes and the inventory use: ``x86_64`` -> ``amd64``."""
    name = machine.strip()
    if name not in ARCHITECTURES:
        raise ValueError(f"unknown machine architecture {name!r} (uname -m); known: {', '.join(sorted(ARCHITECTURES))}")
    return ARCHITECTURES[name]


def check_device_globs(globs: dict) -> dict[str, str]:
    """Validate the mapping of device path globs to inventory device names; ``ValueError`` naming the bad entry."""
    if not isinstance(globs, dict):
        raise ValueError("device_globs must be a mapping of path globs to device names, e.g. {'/dev/video*': camera}")
    for pattern, name in globs.items():
        if not isinstance(pattern, str) or not _GLOB.match(pattern):
            raise ValueError(
                f"device glob {pattern!r} is not valid; expected an absolute path of letters, digits and _ . / * ? [ ] + -"
            )
        if not isinstance(name, str) or not _DEVICE_NAME.match(name):
            raise ValueError(f"device name {name!r} (for {pattern}) is not valid; expected lowercase letters, digits and '-'")
    return dict(globs)


def device_names(paths: list[str], globs: dict[str, str], extra: list[str] = ()) -> list[str]:
    """The inventory's ``kuberos_devices``: the names of the globs that match a path, plus ``extra``; sorted, once each."""
    names = {name for pattern, name in globs.items() if any(fnmatch.fnmatchcase(p, pattern) for p in paths)}
    return sorted(names | set(extra))


def gpu_count(nvidia_smi: str | None, paths: list[str]) -> int:
    """GPUs: the ``GPU n:`` lines of ``nvidia-smi -L`` when it ran, else the /dev/nvidia<n> device nodes."""
    if nvidia_smi is not None:
        return sum(1 for line in nvidia_smi.splitlines() if re.match(r"^GPU \d+:", line))
    return sum(1 for p in paths if fnmatch.fnmatchcase(p, GPU_DEVICE_GLOB))


def facts_script(globs: dict[str, str]) -> str:
    """The read-only shell script whose output ``parse_report`` reads (globs are validated, so safe unquoted)."""
    patterns = " ".join([GPU_DEVICE_GLOB, *sorted(globs)])
    return "\n".join(
        [
            f"echo '{_MARK}nproc'; nproc 2>/dev/null || getconf _NPROCESSORS_ONLN",
            f"echo '{_MARK}meminfo'; cat /proc/meminfo",
            f"echo '{_MARK}uname'; uname -m",
            f"echo '{_MARK}nvidia-smi'",
            "if command -v nvidia-smi >/dev/null 2>&1; then nvidia-smi -L 2>/dev/null || echo '@@failed'; "
            "else echo '@@absent'; fi",
            f"echo '{_MARK}paths'",
            f'for p in {patterns}; do if [ -e "$p" ]; then printf \'%s\\n\' "$p"; fi; done',
            f"echo '{_MARK}authorized_keys'",
            'f="$HOME/.ssh/authorized_keys"; if [ -f "$f" ]; then stat -c %a "$f"; cat "$f"; fi',
            "true",
        ]
    )


def split_report(output: str) -> dict[str, str]:
    sections: dict[str, list[str]] = {}
    current = None
    for line in output.splitlines():
        if line.startswith(_MARK):
            current = line[len(_MARK) :].strip()
            sections[current] = []
        elif current is not None:
            sections[current].append(line)
    missing = [s for s in SECTIONS if s not in sections]
    if missing:
        raise ValueError(f"the facts script's output lacks the sections {', '.join(missing)}")
    return {name: "\n".join(lines) for name, lines in sections.items()}


@dataclass
class Report:
    """What the robot reported: its hardware and its authorized keys."""

    cpu: int
    memory: str
    arch: str
    gpu: int
    devices: list[str]
    authorized_keys: str = ""
    authorized_keys_mode: str = ""  # octal, "" when the file is absent
    paths: list[str] = field(default_factory=list)


def parse_report(output: str, globs: dict[str, str], extra_devices: list[str] = ()) -> Report:
    """Read the facts script's output; ``ValueError`` naming what could not be read."""
    sections = split_report(output)
    nproc = sections["nproc"].strip()
    if not nproc.isdigit() or int(nproc) < 1:
        raise ValueError(f"nproc reported {nproc!r}, not a number of CPUs")
    paths = [line for line in sections["paths"].splitlines() if line.startswith("/")]
    smi = sections["nvidia-smi"]
    smi_output = None if smi.strip() in ("@@absent", "@@failed") else smi
    keys = sections["authorized_keys"].split("\n", 1) if sections["authorized_keys"] else []
    mode = keys[0].strip() if keys else ""
    return Report(
        cpu=int(nproc),
        memory=memory_quantity(sections["meminfo"]),
        arch=kubernetes_arch(sections["uname"]),
        gpu=gpu_count(smi_output, paths),
        devices=device_names(paths, globs, extra_devices),
        authorized_keys=keys[1] if len(keys) > 1 else "",
        authorized_keys_mode=mode,
        paths=paths,
    )


def fingerprint_of_blob(blob: bytes) -> str:
    """OpenSSH's SHA256 fingerprint of a public key blob: ``SHA256:<unpadded base64>``."""
    return "SHA256:" + base64.b64encode(hashlib.sha256(blob).digest()).decode().rstrip("=")


def normalize_fingerprint(text: str) -> str:
    """``SHA256:abc=`` or ``abc`` -> ``SHA256:abc`` (what ssh-keygen -lf prints)."""
    value = text.strip()
    if value.upper().startswith("SHA256:"):
        value = value[7:]
    value = value.rstrip("=")
    if not re.match(r"^[A-Za-z0-9+/]{43}$", value):
        raise ValueError(f"{text!r} is not a SHA256 fingerprint; expected e.g. SHA256:{'A' * 43} (ssh-keygen -lf)")
    return "SHA256:" + value


def public_key_line(text: str, source: str) -> tuple[str, str]:
    """The one key of a .pub file: ``(line, 'type base64')``; ``ValueError`` when it is not a single public key."""
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.strip().startswith("#")]
    if len(lines) != 1:
        raise ValueError(f"{source} holds {len(lines)} keys; expected exactly one public key (a .pub file)")
    parts = lines[0].split()
    if len(parts) < 2 or not parts[0].startswith(("ssh-", "ecdsa-", "sk-")):
        raise ValueError(f"{source} is not an OpenSSH public key; expected 'ssh-ed25519 AAAA... comment'")
    try:
        base64.b64decode(parts[1], validate=True)
    except ValueError as error:
        raise ValueError(f"{source} is not an OpenSSH public key: its key data is not base64") from error
    return lines[0], f"{parts[0]} {parts[1]}"


def has_key(authorized_keys: str, key: str) -> bool:
    """Whether ``key`` (``'type base64'``) is in authorized_keys, whatever its options and comment there."""
    kind, blob = key.split()
    for line in authorized_keys.splitlines():
        if line.lstrip().startswith("#"):
            continue
        fields = line.split()
        if blob in fields and fields.index(blob) > 0 and fields[fields.index(blob) - 1] == kind:
            return True
    return False


def known_hosts_name(address: str, port: int) -> str:
    return address if port == 22 else f"[{address}]:{port}"


def host_vars_for(fleet: str, address: str, user: str, report: Report) -> dict:
    return {
        "kuberos_fleet": fleet,
        "kuberos_cpu": report.cpu,
        "kuberos_memory": report.memory,
        "kuberos_gpu": report.gpu,
        "kuberos_arch": report.arch,
        "kuberos_devices": list(report.devices),
        "kuberos_address": address,
        "ansible_host": address,
        "ansible_user": user,
    }


def check_robot(robot: str, host_vars: dict) -> None:
    """The scheduler accepts the robot (``load_inventory``); ``RegistrationError`` with every problem otherwise."""
    try:
        load_inventory({"hosts": {robot: host_vars}, "groups": {"robots": [robot]}}, source="registration")
    except SpecError as error:
        raise RegistrationError(f"robot {robot} would not be a valid inventory entry, so nothing was written: {error}") from None


def _dump(data) -> str:
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=False, width=120)


def host_vars_text(existing: str | None, host_vars: dict, path: str) -> str:
    """The host_vars file: the managed variables (in a fixed order) replaced, any other key kept."""
    kept: dict = {}
    if existing:
        try:
            loaded = yaml.safe_load(existing)
        except yaml.YAMLError as error:
            raise RegistrationError(f"{path} is not plain YAML ({error}); move it aside or fix it, then register again") from None
        if loaded is not None and not isinstance(loaded, dict):
            raise RegistrationError(f"{path} is not a mapping of variables; move it aside, then register again")
        kept = {k: v for k, v in (loaded or {}).items() if k not in MANAGED_VARS}
    return HOST_VARS_HEADER + _dump({**host_vars, **kept})


def registered_text(existing: str | None, robot: str, path: str) -> str:
    """``registered_robots.yml`` with ``robot`` among the hosts of ``robots`` (other robots kept, sorted)."""
    hosts: dict = {}
    if existing:
        try:
            loaded = yaml.safe_load(existing) or {}
            hosts = dict(loaded["all"]["children"]["robots"]["hosts"] or {})
        except (yaml.YAMLError, KeyError, TypeError, ValueError):
            raise RegistrationError(
                f"{path} is not the file robot_register writes (all.children.robots.hosts); move it aside, then register again"
            ) from None
    hosts.setdefault(robot, {})
    listed = {h: hosts[h] or {} for h in sorted(hosts)}
    return REGISTERED_HEADER + _dump({"all": {"children": {"robots": {"hosts": listed}}}})


# --- files ------------------------------------------------------------------------------------------------------


def write_atomically(path: str, text: str, mode: int = 0o644) -> None:
    """Write ``path`` through a temporary file in its directory and a rename: readers see the old or the new file."""
    directory = os.path.dirname(path) or "."
    os.makedirs(directory, exist_ok=True)
    handle, temporary = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", dir=directory)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text)
            out.flush()
            os.fsync(out.fileno())
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise


def write_all(changes: list[tuple[str, str, str | None]]) -> None:
    """Write each ``(path, new, old)`` in order; if one fails, put back the ones already written."""
    done: list[tuple[str, str | None]] = []
    try:
        for path, new, old in changes:
            write_atomically(path, new)
            done.append((path, old))
    except OSError as error:
        for path, old in reversed(done):
            if old is None:
                os.unlink(path)
            else:
                write_atomically(path, old)
        where = error.filename or "the inventory"
        raise RegistrationError(f"writing {where} failed ({error.strerror}); nothing was kept") from None


# --- SSH --------------------------------------------------------------------------------------------------------


@dataclass
class Target:
    robot: str
    address: str
    port: int
    user: str
    admin_key: str
    known_hosts: str
    expected_fingerprint: str = ""
    connect_timeout: float = 10.0
    command_timeout: float = 60.0
    admin_key_passphrase: str | None = None

    @property
    def where(self) -> str:
        return f"{self.address}:{self.port}" if self.port != 22 else self.address


def load_pins(target: Target):
    """The pinned keys of the robot's address: ``{key type: PKey}`` (empty on first contact)."""
    pins = paramiko.HostKeys()
    if os.path.exists(target.known_hosts):
        try:
            pins.load(target.known_hosts)
        except (OSError, paramiko.SSHException) as error:
            raise RegistrationError(f"cannot read the pinned host keys {target.known_hosts}: {error}") from None
    return dict(pins.lookup(known_hosts_name(target.address, target.port)) or {})


def _key_types(pinned: dict) -> list[str]:
    """Host key algorithms to accept: only those of the pinned keys (as OpenSSH does), so the robot shows that key."""
    types: list[str] = []
    for kind in pinned:
        types += ["rsa-sha2-512", "rsa-sha2-256", "ssh-rsa"] if kind == "ssh-rsa" else [kind]
    return types


def _unreachable(target: Target, reason: str) -> RegistrationError:
    return RegistrationError(
        f"cannot reach robot {target.robot} at {target.where}: {reason}; check that it is powered on, on the network and "
        "runs sshd, and that its address is right (nothing was written)"
    )


def load_admin_key(target: Target):
    try:
        return paramiko.PKey.from_path(target.admin_key, password=target.admin_key_passphrase)
    except FileNotFoundError:
        raise RegistrationError(f"the administrator's key {target.admin_key} does not exist") from None
    except paramiko.PasswordRequiredException:
        raise RegistrationError(
            f"the administrator's key {target.admin_key} is encrypted; give its passphrase (admin_key_passphrase)"
        ) from None
    except (paramiko.SSHException, ValueError, OSError) as error:
        raise RegistrationError(f"cannot load the administrator's key {target.admin_key}: {error}") from None


def connect(target: Target, admin_key):
    """An authenticated transport, after checking the host key; returns ``(transport, fingerprint, presented key)``."""
    pinned = load_pins(target)
    try:
        sock = socket.create_connection((target.address, target.port), timeout=target.connect_timeout)
    except ConnectionRefusedError:
        raise _unreachable(target, "connection refused") from None
    except TimeoutError:
        raise _unreachable(target, f"no answer within {target.connect_timeout:g} s") from None
    except socket.gaierror as error:
        raise _unreachable(target, f"the name does not resolve ({error.strerror})") from None
    except OSError as error:
        reason = {errno.EHOSTUNREACH: "no route to host", errno.ENETUNREACH: "network unreachable"}.get(error.errno)
        raise _unreachable(target, reason or error.strerror or str(error)) from None
    transport = paramiko.Transport(sock)
    try:
        transport.banner_timeout = target.connect_timeout
        transport.handshake_timeout = target.connect_timeout
        transport.auth_timeout = target.connect_timeout
        if pinned:
            wanted = [t for t in _key_types(pinned) if t in transport.get_security_options().key_types]
            if wanted:
                transport.get_security_options().key_types = wanted
        try:
            transport.start_client(timeout=target.connect_timeout)
        except paramiko.SSHException as error:
            if pinned and "host key" in str(error).lower():
                raise RegistrationError(
                    f"robot {target.robot} at {target.where} no longer offers a host key of the pinned type "
                    f"({', '.join(pinned)}) in {target.known_hosts}; nothing was written: if the robot was reinstalled, "
                    f"remove the old pin with `ssh-keygen -R {known_hosts_name(target.address, target.port)} -f "
                    f"{target.known_hosts}` and register it again with its new fingerprint as the expected one"
                ) from None
            raise _unreachable(target, f"the SSH handshake failed ({error})") from None
        except (EOFError, OSError) as error:
            raise _unreachable(target, f"the SSH handshake failed ({error or 'connection closed'})") from None
        presented = transport.get_remote_server_key()
        fingerprint = fingerprint_of_blob(presented.asbytes())
        check_host_key(target, pinned, presented, fingerprint)
        try:
            transport.auth_publickey(target.user, admin_key)
        except paramiko.AuthenticationException:
            raise RegistrationError(
                f"robot {target.robot} refused the administrator's key {target.admin_key} for {target.user}@{target.where} "
                f"(authentication failed); put its public key in ~{target.user}/.ssh/authorized_keys on the robot, or "
                "register with the key that is there (nothing was written)"
            ) from None
        except (paramiko.SSHException, EOFError, OSError) as error:
            raise _unreachable(target, f"authentication did not complete ({error})") from None
        return transport, fingerprint, presented
    except BaseException:
        transport.close()
        raise


def check_host_key(target: Target, pinned: dict, presented, fingerprint: str) -> None:
    """A pinned key must be presented unchanged; on first contact the expected fingerprint, if given, must match."""
    name = known_hosts_name(target.address, target.port)
    if pinned:
        same = pinned.get(presented.get_name())
        if same is None or same.asbytes() != presented.asbytes():
            old = ", ".join(fingerprint_of_blob(k.asbytes()) for k in pinned.values())
            raise RegistrationError(
                f"the host key of robot {target.robot} at {target.where} has changed: pinned {old} in {target.known_hosts}, "
                f"presented {fingerprint}; this is either a reinstalled robot or someone in between, so nothing was written: "
                "compare the new fingerprint with `ssh-keygen -lf /etc/ssh/ssh_host_ed25519_key.pub` on the robot's console, "
                f"then remove the old pin with `ssh-keygen -R {name} -f {target.known_hosts}` and register again with "
                "that fingerprint as the expected one"
            )
    if target.expected_fingerprint and normalize_fingerprint(target.expected_fingerprint) != fingerprint:
        raise RegistrationError(
            f"robot {target.robot} at {target.where} presents the host key {fingerprint}, not the expected "
            f"{normalize_fingerprint(target.expected_fingerprint)}; refused, nothing was written: check the address and "
            "the fingerprint (`ssh-keygen -lf /etc/ssh/ssh_host_ed25519_key.pub` on the robot's console)"
        )


def run_command(transport, target: Target, command: str, what: str) -> str:
    """Run ``command`` with the login user's shell; its stdout, or ``RegistrationError`` when it fails."""
    try:
        channel = transport.open_session(timeout=target.connect_timeout)
        channel.settimeout(target.command_timeout)
        channel.exec_command(command)
        out = channel.makefile("rb").read().decode("utf-8", "replace")
        err = channel.makefile_stderr("rb").read().decode("utf-8", "replace")
        status = channel.recv_exit_status()
        channel.close()
    except TimeoutError:
        raise RegistrationError(
            f"{what} on robot {target.robot} did not finish within {target.command_timeout:g} s (nothing was written)"
        ) from None
    except (paramiko.SSHException, EOFError, OSError) as error:
        raise RegistrationError(f"{what} on robot {target.robot} failed: {error} (nothing was written)") from None
    if status != 0:
        raise RegistrationError(
            f"{what} on robot {target.robot} exited {status}: {err.strip()[-500:] or out.strip()[-500:]} (nothing was written)"
        )
    return out


def install_key_command(key_line: str) -> str:
    """Append the key to ~/.ssh/authorized_keys (0600, in a 0700 ~/.ssh), on a line of its own."""
    return (
        'umask 077; mkdir -p "$HOME/.ssh"; chmod 0700 "$HOME/.ssh"; f="$HOME/.ssh/authorized_keys"; touch "$f"; '
        'if [ -s "$f" ] && [ -n "$(tail -c 1 "$f")" ]; then echo >> "$f"; fi; '
        f'printf \'%s\\n\' {shlex.quote(key_line)} >> "$f"; chmod 0600 "$f"'
    )


# --- the whole registration -------------------------------------------------------------------------------------


@dataclass
class Registration:
    robot: str
    address: str
    fleet: str
    inventory_dir: str
    cluster_key: str
    target: Target
    device_globs: dict = field(default_factory=lambda: dict(DEFAULT_DEVICE_GLOBS))
    extra_devices: list = field(default_factory=list)

    @property
    def host_vars_path(self) -> str:
        return os.path.join(self.inventory_dir, "host_vars", f"{self.robot}.yml")

    @property
    def registered_path(self) -> str:
        return os.path.join(self.inventory_dir, REGISTERED_ROBOTS)


def register(reg: Registration, check_mode: bool = False) -> dict:
    """Register the robot; the result for the module (``changed``, ``host_vars``, ``diff``...). ``RegistrationError``."""
    if paramiko is None:
        raise RegistrationError("the Python package paramiko is needed on the machine running Ansible")
    try:
        globs = check_device_globs(reg.device_globs)
        if reg.target.expected_fingerprint:
            normalize_fingerprint(reg.target.expected_fingerprint)
        bad = [name for name in reg.extra_devices if not _DEVICE_NAME.match(str(name))]
        if bad:
            raise ValueError(f"extra device names {bad} are not valid; expected lowercase letters, digits and '-'")
    except ValueError as error:
        raise RegistrationError(str(error)) from None
    pub = text_or_none(reg.cluster_key)
    if pub is None:
        raise RegistrationError(f"the cluster's public key {reg.cluster_key} does not exist")
    try:
        key_line, key = public_key_line(pub, reg.cluster_key)
    except ValueError as error:
        raise RegistrationError(str(error)) from None
    if not os.path.isdir(reg.inventory_dir):
        raise RegistrationError(f"the inventory directory {reg.inventory_dir} does not exist")
    admin_key = load_admin_key(reg.target)

    transport, fingerprint, presented = connect(reg.target, admin_key)
    try:
        output = run_command(transport, reg.target, facts_script(globs), "reading the hardware facts")
        try:
            report = parse_report(output, globs, reg.extra_devices)
        except ValueError as error:
            raise RegistrationError(
                f"robot {reg.robot} reported facts that cannot be read: {error} (nothing was written)"
            ) from None
        host_vars = host_vars_for(reg.fleet, reg.address, reg.target.user, report)
        check_robot(reg.robot, host_vars)

        old_vars = text_or_none(reg.host_vars_path)
        new_vars = host_vars_text(old_vars, host_vars, reg.host_vars_path)
        old_registered = text_or_none(reg.registered_path)
        new_registered = registered_text(old_registered, reg.robot, reg.registered_path)
        first_contact = not load_pins(reg.target)
        old_pins = text_or_none(reg.target.known_hosts)
        pin_line = f"{known_hosts_name(reg.address, reg.target.port)} {presented.get_name()} {presented.get_base64()}\n"
        new_pins = ((old_pins + ("" if old_pins.endswith("\n") else "\n")) if old_pins else "") + pin_line
        install_key = not has_key(report.authorized_keys, key)
        fix_mode = not install_key and report.authorized_keys_mode not in ("600", "400")

        changes = [(reg.host_vars_path, new_vars, old_vars)] if new_vars != old_vars else []
        if first_contact:
            changes.append((reg.target.known_hosts, new_pins, old_pins))
        if new_registered != old_registered:
            changes.append((reg.registered_path, new_registered, old_registered))  # membership last: the commit point
        result = {
            "changed": bool(changes) or install_key or fix_mode,
            "robot": reg.robot,
            "address": reg.address,
            "host_vars": host_vars,
            "host_vars_file": reg.host_vars_path,
            "registered_file": reg.registered_path,
            "known_hosts": reg.target.known_hosts,
            "host_key_fingerprint": fingerprint,
            "host_key_pinned": first_contact,
            "cluster_key_installed": install_key,
            "written": [path for path, _new, _old in changes],
            "diff": [
                {"before_header": path, "after_header": path, "before": old or "", "after": new} for path, new, old in changes
            ],
        }
        if check_mode:
            result["written"] = []
            return result
        if install_key or fix_mode:
            command = install_key_command(key_line) if install_key else ('chmod 0600 "$HOME/.ssh/authorized_keys"')
            run_command(transport, reg.target, command, "installing the cluster's public key")
    finally:
        transport.close()
    write_all(changes)
    return result
