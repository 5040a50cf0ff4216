"""Secrets in every shape a module's log may show, among ordinary log lines, cut into the windows a reader sees.

A case is ``(windows, secrets, forbidden)``: ``windows`` are consecutive reads of one container's log (the first a
tail that may start anywhere, e.g. inside a key; each next one a ``follow`` poll that goes on where the previous one
stopped, cut at any line), ``secrets`` the values of the Secrets the pod can read (``{'<secret>/<key>': value}``)
and ``forbidden`` what must not show in any window once redacted: every body line of a key, every password, token
and access key, every Secret value in the encoding the log printed it in.

``cases(n, seed)`` gives ``n`` of them (for the benchmark: ``redaction_cases`` and ``redaction_leaks``); ``case(rng)``
builds one from a ``random.Random`` (the property test passes hypothesis's, so a failure shrinks); ``leaks(case)``
redacts the windows in order with one ``Redactor``, as ``kuberos_deploy/module_log_reader.py`` does, and returns
what showed. Test infrastructure: production never imports it.
"""

from __future__ import annotations

import base64
import itertools
import json
import random
import string
import textwrap
from urllib.parse import quote, quote_plus

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.module_logs import Redactor

B64 = string.ascii_letters + string.digits + "+/"
TOKEN = string.ascii_letters + string.digits
SHOWN_FROM = 16  # shorter pieces of a key (a last line of a few characters, a PGP checksum) are not counted

# Lines a ROS 2 module prints: they must come out as they went in, wherever a window starts. (A lone word, or a long
# CamelCase name, may be taken for the last line of a key when it follows one or opens a window: see docs/logs.md.)
ORDINARY = [
    "[INFO] [1732788001.123456789] [motion_planner]: Planning request received for group 'arm'",
    "[WARN] [1732788001.523000000] [controller_manager]: Overrun: 2.3 ms over the 10 ms period",
    "[ERROR] [1732788002.000000001] [gripper_driver]: timeout waiting for /gripper/status (5.0 s)",
    "[INFO] [1732788003.250000000] [nav2_bt_navigator]: Begin navigating from (0.00, 1.20) to (3.40, -2.10)",
    "[INFO] [launch]: All log files can be found below /tmp/.ros/log/2026-11-28-10-00-01-123456-fetch-1-42",
    "[INFO] [launch]: Default logging verbosity is set to INFO",
    "[INFO] [planner-1]: process started with pid [4242]",
    "Loading parameters from /opt/ros/humble/share/moveit_configs/config/kinematics.yaml",
    "/opt/ros/humble/lib/controller_manager/ros2_control_node",
    "/home/robot/workspace/install/pick_and_place/share/pick_and_place/launch/bringup.launch.py",
    "/opt/ros/humble/share/robotdescription/urdf/robotwithgripperandcamera",
    "image sha256:9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08 pulled",
    "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08",
    "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "2b1d6a0e-6f1c-4a51-9c58-1f1e2d3c4b5a",
    "goal 7c9e6679-7425-40de-944b-e07fc1f90ae7 accepted",
    "ghcr.io/kuberos/motion-planner:1.4.2@sha256:e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "joint_states: position=[0.0, 1.57, -0.78] velocity=[0.0, 0.0, 0.0]",
    "frame_id: base_link, child_frame_id: tool0",
    "Connected to the discovery server at 10.42.0.17:11811",
    "GET /healthz 200 0.4 ms",
    "",
    "    at rclpy.spin (executors.py:294)",
    "Node 'planner' has 12 publishers and 7 subscribers; keys: left, right",
    "==================== summary ====================",
    "Password accepted for operator console (see audit log)",
    "tokens per second: 1200",
]


def _token(rng: random.Random, low: int = 16, high: int = 40) -> str:
    """A random credential with a digit, an upper- and a lower-case letter (so it is none of the ordinary lines)."""
    body = "".join(rng.choice(TOKEN) for _ in range(rng.randint(low, high) - 3))
    return rng.choice(string.digits) + body + rng.choice(string.ascii_uppercase) + rng.choice(string.ascii_lowercase)


def _random_bytes(rng: random.Random, size: int) -> bytes:
    """Bytes as random as a key's, whatever ``rng`` is (hypothesis's shrinks towards zeros: AAAA... is no key)."""
    return random.Random(rng.getrandbits(64)).randbytes(size)


def _b64_lines(rng: random.Random, size: int, width: int) -> list[str]:
    data = _random_bytes(rng, size)
    return textwrap.wrap(base64.b64encode(data).decode(), width)


def _key_material(lines: list[str]) -> list[str]:
    return [line for line in lines if len(line) >= SHOWN_FROM]


def pem_key(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    """A PEM private key (PKCS#1, PKCS#8, EC, OpenSSH, encrypted with its headers), as printed, maybe indented."""
    kind = rng.choice(["PRIVATE KEY", "RSA PRIVATE KEY", "EC PRIVATE KEY", "OPENSSH PRIVATE KEY", "ENCRYPTED PRIVATE KEY"])
    body = _b64_lines(rng, rng.randint(48, 1700), 70 if kind.startswith("OPENSSH") else 64)
    headers = []
    if kind == "RSA PRIVATE KEY" and rng.random() < 0.3:  # an OpenSSL-encrypted PKCS#1 key
        headers = ["Proc-Type: 4,ENCRYPTED", "DEK-Info: AES-128-CBC,3F2504E04F8911D39A0C0305E82C3301", ""]
    indent = rng.choice(["", "", "  ", "    "])
    lines = [f"-----BEGIN {kind}-----", *headers, *body, f"-----END {kind}-----"]
    lead = rng.choice([[], ["tls.key: |"], ["loaded the key:"]])
    return lead + [indent + line for line in lines], {}, _key_material(body)


def pgp_key(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    """An ASCII-armored PGP private key block: headers, a blank line, 64-character lines, the checksum."""
    body = _b64_lines(rng, rng.randint(100, 2500), 64)
    checksum = "=" + base64.b64encode(_random_bytes(rng, 3)).decode()
    headers = rng.choice([[], ["Version: GnuPG v2"], ["Comment: robot signing key"]])
    lines = ["-----BEGIN PGP PRIVATE KEY BLOCK-----", *headers, "", *body, checksum, "-----END PGP PRIVATE KEY BLOCK-----"]
    return lines, {}, _key_material(body)


def json_key(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    """A GCP service account's JSON, its private key on one line with escaped line breaks."""
    body = _b64_lines(rng, rng.randint(600, 1200), 64)
    key = "-----BEGIN PRIVATE KEY-----\n" + "\n".join(body) + "\n-----END PRIVATE KEY-----\n"
    account = {"type": "service_account", "project_id": "robots", "private_key_id": "a1b2c3d4" * 5,
               "private_key": key, "client_email": "fleet@robots.iam.gserviceaccount.com"}  # fmt: skip
    return [json.dumps(account)], {}, _key_material(body)


def basic_auth(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    user, password = rng.choice(["robot", "fetch-1", "ci"]), _token(rng)
    encoded = base64.b64encode(f"{user}:{password}".encode()).decode()
    line = rng.choice([
        f"> Authorization: Basic {encoded}",
        f"request headers: {{'authorization': 'basic {encoded}'}}",
        f"curl -H 'Authorization: Basic {encoded}' https://registry.local/v2/",
        f"retrying with Basic {encoded}",
    ])  # fmt: skip
    return [line], {}, [encoded, password]


def url_password(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    password = _token(rng, 12, 30)
    if rng.random() < 0.5:
        password = password[:6] + rng.choice(["%40", "!", "$", "*", ";", "~", "%2F"]) + password[6:]
    url = rng.choice([
        f"postgres://planner:{password}@db.fleet.svc:5432/maps",
        f"https://bot:{password}@git.example.com/robots/config.git",
        f"redis://:{password}@cache:6379/0",
        f"amqp://guest:{password}@broker",
    ])  # fmt: skip
    return [rng.choice(["connecting to {}", "{}", "retry {} in 5 s"]).format(url)], {}, [password]


def cloud_keys(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    key_id = rng.choice(["AKIA", "ASIA"]) + "".join(rng.choice(string.ascii_uppercase + string.digits) for _ in range(16))
    secret = "".join(rng.choice(B64) for _ in range(40))
    session = _token(rng, 60, 120)
    azure = base64.b64encode(_random_bytes(rng, 64)).decode()
    lines = rng.choice([
        [f"using access key {key_id}", f"aws_secret_access_key = {secret}", f"aws_session_token={session}"],
        [f"AWS_ACCESS_KEY_ID={key_id}", f"AWS_SECRET_ACCESS_KEY={secret}", f"AWS_SESSION_TOKEN={session}"],
        [json.dumps({"Credentials": {"AccessKeyId": key_id, "SecretAccessKey": secret, "SessionToken": session}})],
        [f"DefaultEndpointsProtocol=https;AccountName=robots;AccountKey={azure};EndpointSuffix=core.windows.net"],
    ])  # fmt: skip
    forbidden = [azure] if "AccountKey" in lines[0] else [key_id, secret, session]
    return lines, {}, forbidden


def header_token(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    token = _token(rng)
    line = rng.choice([
        "X-Api-Key: {}", "x-auth-token: {}", "api_key={}", '{{"apiKey": "{}"}}', "token: {}", "refresh_token={}",
        "password={}", "PASSWORD: {}", "client_secret={}", "secret: {}", "--token={}", "GET /map?access_token={}&z=3",
        "Authorization: Bearer {}", "Authorization: token {}", "{{'password': '{}'}}", "db.password = {}",
        "private-key: {}", "Proxy-Authorization: {}", "signing with ghp_" + "{}" + "abcdefghijklmnopqrst",
    ]).format(token)  # fmt: skip
    return [line], {}, [token]


def _secret_value(rng: random.Random) -> str:
    shape = rng.randrange(4)
    if shape == 0:
        return _token(rng, 8, 60)
    if shape == 1:  # quotes, spaces, a backslash, characters URLs escape, non-ASCII
        specials = ['"', "'", " ", "\\", "/", "+", "%", "&", "=", "?", "#", "é", "☃", "\t"]
        chars = [*_token(rng, 10, 30), *rng.sample(specials, rng.randint(2, 5))]
        rng.shuffle(chars)
        return _token(rng, 4, 4) + "".join(chars)
    if shape == 2:  # several lines (a config file, a certificate)
        return "\n".join(_token(rng, 10, 50) for _ in range(rng.randint(2, 6))) + rng.choice(["", "\n"])
    return "-----BEGIN PRIVATE KEY-----\n" + "\n".join(_b64_lines(rng, 300, 64)) + "\n-----END PRIVATE KEY-----\n"


def _encodings(value: str) -> dict[str, str]:
    raw = value.encode()
    forms = {
        "raw": value,
        "base64": base64.b64encode(raw).decode(),
        "base64, no padding": base64.b64encode(raw).decode().rstrip("="),
        "urlsafe base64": base64.urlsafe_b64encode(raw).decode(),
        "urlsafe base64, no padding": base64.urlsafe_b64encode(raw).decode().rstrip("="),
        "base64 of the value and a line break": base64.b64encode(raw + b"\n").decode(),
        "percent-encoded": quote(value, safe=""),
        "form-encoded": quote_plus(value),
        "JSON string": json.dumps(value)[1:-1],
        "JSON string, UTF-8": json.dumps(value, ensure_ascii=False)[1:-1],
        "hex": raw.hex(),
    }
    return forms


def secret_value(rng: random.Random) -> tuple[list[str], dict, list[str]]:
    """A Secret's value, printed in one of its encodings (or its lines, raw, one by one), its name the label."""
    value = _secret_value(rng)
    label = f"{rng.choice(['api', 'db', 'bridge-tls', 'keys'])}/{rng.choice(['token', 'password', 'tls.key', 'config'])}"
    forms = _encodings(value)
    how = rng.choice(sorted(forms))
    shown = forms[how]
    if how == "raw":
        pieces = [line.strip() for line in value.splitlines()]
        lines = [rng.choice(["{}", "value: {}", "using {} now"]).format(line) for line in pieces]
        return lines, {label: value}, [p for p in pieces if len(p) >= 8]
    if how == "base64" and len(shown) > 76 and rng.random() < 0.5:  # as `base64` wraps it
        return textwrap.wrap(shown, 76), {label: value}, _key_material(textwrap.wrap(shown, 76))
    line = rng.choice(["{}", "config={}", 'env {{"VALUE": "{}"}}', "GET /callback?code={}&state=1"]).format(shown)
    forbidden = [shown] + [p.strip() for p in value.splitlines() if len(p.strip()) >= 8]
    return [line], {label: value}, forbidden


SHAPES = [pem_key, pgp_key, json_key, basic_auth, url_password, cloud_keys, header_token, secret_value]


def case(rng: random.Random, shapes=SHAPES) -> tuple[list[str], dict[str, str], list[str]]:
    """Ordinary lines with one to three secrets among them (a key's lines kept together), cut into windows."""
    chunks: list[list[str]] = [[rng.choice(ORDINARY)] for _ in range(rng.randint(0, 6))]
    secrets: dict[str, str] = {}
    forbidden: list[str] = []
    for _ in range(rng.randint(1, 3)):
        lines, found, bad = rng.choice(shapes)(rng)
        at = rng.randint(0, len(chunks))
        chunks[at:at] = [lines, *([rng.choice(ORDINARY)] for _ in range(rng.randint(0, 3)))]
        for label, value in found.items():
            secrets[label if label not in secrets else f"{label}-{len(secrets)}"] = value
        forbidden += bad
    log = [line for chunk in chunks for line in chunk]
    start = rng.randint(0, len(log) - 1) if rng.random() < 0.7 else 0  # the tail: lines=N, the dashboard's 40
    cuts = sorted(rng.sample(range(start + 1, len(log)), min(rng.randint(0, 5), len(log) - start - 1)))
    bounds = [start, *cuts, len(log)]
    windows = ["\n".join(log[a:b]) for a, b in itertools.pairwise(bounds)]
    return windows, secrets, forbidden


def cases(n: int, seed: int = 0) -> list[tuple[list[str], dict[str, str], list[str]]]:
    rng = random.Random(seed)
    return [case(rng) for _ in range(n)]


def redacted(windows: list[str], secrets: dict[str, str]) -> list[str]:
    """The windows as the reader shows them: one ``Redactor`` for the container, fed window after window."""
    redactor = Redactor(secrets)
    return [redactor.redact(window) for window in windows]


def leaks(windows: list[str], secrets: dict[str, str], forbidden: list[str]) -> list[str]:
    """What of ``forbidden`` shows in the redacted windows (empty: nothing leaks)."""
    shown = "\n".join(redacted(windows, secrets))
    return [piece for piece in forbidden if piece in shown]


def ordinary_kept(windows: list[str], secrets: dict[str, str]) -> list[str]:
    """The ordinary lines in ``windows`` that did not come out unchanged (empty: none was blanked)."""
    out = {line for window in redacted(windows, secrets) for line in window.split("\n")}
    ordinary = set(ORDINARY) - {""}  # a blank line is a PGP block's too
    return [line for window in windows for line in window.split("\n") if line in ordinary and line not in out]
