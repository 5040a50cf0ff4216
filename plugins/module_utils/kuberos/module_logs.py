"""A module's output without kubectl: which pod serves a module of a robot, and its log made safe to show.

``instance_for`` finds the rendered Deployment of a (deployment, module, robot) among a fleet's Deployments: a
dedicated instance carries the robot's label, a shared one lists its robots in an annotation. ``secret_refs`` names
the Secrets a pod's containers can read (environment and volumes); ``redact`` takes their values out of a log, and
with them what looks like a private key or a bearer token whatever its source. ``labelled`` prefixes each line of a
module with several containers with the container's name. Pure: the I/O is ``kuberos_deploy/module_log_reader.py``
and the dashboard's.
"""

from __future__ import annotations

import base64
import itertools
import json
import re
from urllib.parse import quote, quote_plus

from . import labels

MAX_LINES = 10000


def serves(deployment: dict, robot: str) -> bool:
    meta = deployment.get("metadata") or {}
    if (meta.get("labels") or {}).get(labels.ROBOT) == robot:
        return True
    robots = (meta.get("annotations") or {}).get(labels.ROBOTS_ANNOTATION, "")
    return robot in [r.strip() for r in robots.split(",")]


def instance_for(deployments: list[dict], deployment: str, module: str, robot: str) -> dict | None:
    """The module Deployment of ``deployment`` that runs ``module`` for ``robot``, or None."""
    for obj in sorted(deployments, key=lambda d: d["metadata"]["name"]):
        found = obj["metadata"].get("labels") or {}
        if found.get(labels.DEPLOYMENT) == deployment and found.get(labels.MODULE) == module and serves(obj, robot):
            return obj
    return None


def robots_of(deployments: list[dict], deployment: str, module: str) -> list[str]:
    """Every robot some instance of ``module`` serves (to say which exist when a robot is not one of them)."""
    robots = set()
    for obj in deployments:
        meta = obj["metadata"]
        found = meta.get("labels") or {}
        if found.get(labels.DEPLOYMENT) == deployment and found.get(labels.MODULE) == module:
            robots |= {r for r in (meta.get("annotations") or {}).get(labels.ROBOTS_ANNOTATION, "").split(",") if r}
            if found.get(labels.ROBOT):
                robots.add(found[labels.ROBOT])
    return sorted(robots)


def newest_pod(pods: list[dict]) -> dict | None:
    """The newest of an instance's pods that is not being deleted (a rollout's surge runs two for a while)."""
    alive = [p for p in pods if not p["metadata"].get("deletionTimestamp")]
    return max(alive, key=lambda p: p["metadata"].get("creationTimestamp", "")) if alive else None


def secret_refs(pod_spec: dict) -> list[tuple[str, str]]:
    """(Secret, key) pairs the pod's containers can read; key '' for all of a Secret's keys."""
    refs = set()
    for container in (*(pod_spec.get("initContainers") or ()), *(pod_spec.get("containers") or ())):
        for env in container.get("env") or ():
            ref = (env.get("valueFrom") or {}).get("secretKeyRef")
            if ref:
                refs.add((ref["name"], ref.get("key", "")))
        for source in container.get("envFrom") or ():
            if source.get("secretRef"):
                refs.add((source["secretRef"]["name"], ""))
    for volume in pod_spec.get("volumes") or ():
        if volume.get("secret"):
            refs.add((volume["secret"]["secretName"], ""))
        for source in (volume.get("projected") or {}).get("sources") or ():
            if source.get("secret"):
                refs.add((source["secret"]["name"], ""))
    return sorted(refs)


def secret_values(secret: dict, key: str = "") -> dict[str, str]:
    """``{'<secret>/<key>': value}`` of a Secret object's data (base64) and stringData, one key or all."""
    name = secret["metadata"]["name"]
    values = {}
    for field, encoded in (secret.get("data") or {}).items():
        if key in ("", field):
            try:
                values[f"{name}/{field}"] = base64.b64decode(encoded).decode("utf-8", errors="replace")
            except ValueError:
                continue
    for field, value in (secret.get("stringData") or {}).items():
        if key in ("", field):
            values[f"{name}/{field}"] = str(value)
    return values


# Redaction. Secrets' values are matched in every form a program prints them in; credentials whatever their source
# by their shape, line by line, so that what a window shows of a key does not depend on where the window starts.

REDACTED = "[redacted: {}]"
MIN_SECRET = 4  # shorter values are not taken out (they would blank ordinary words)
MIN_CORE = 8  # a value's base64 inside a longer base64 text is matched from this many characters on
MAX_BLOCK_LINES = 400  # a key block is shorter: past this, its END line was lost and the lines are read as usual
BASE64_BLOCK = "base64 block"
# A body line changes between upper case, lower case and digits more often than this: about 0.62 of neighbouring
# characters in random base64 (one line in a million of 64 characters under 0.31), under 0.25 in words and most paths.
CLASS_CHANGES = 0.25
PATH_CLASS_CHANGES = 0.4  # the same for a line with six slashes or more (CamelCase directories with digits)
_MARKER = re.compile(r"-{4,5} ?(BEGIN|END) ([A-Z0-9][A-Z0-9 ]*?) ?-{4,5}")
_BODY = re.compile(r"[A-Za-z0-9+/]{40,76}={0,2}")  # a PEM or armored body line (64, 70 or 76 characters)
_LOOSE = re.compile(r"=?[A-Za-z0-9+/]{1,76}={0,2}")  # a body's last line, or a PGP checksum (=XXXX)
_CHECKSUM = re.compile(r"=[A-Za-z0-9+/]{4}")
_HEX = re.compile(r"[0-9a-fA-F]+")
_PERCENT = re.compile(r"%[0-9A-F]{2}")
_URLSAFE = str.maketrans("+/", "-_")
_URL_PASSWORD = re.compile(r"(?<![A-Za-z0-9+.-])([A-Za-z][A-Za-z0-9+.-]{0,30}://[^\s:/?#@\[\]]*:)([^\s/?#]+)@")
_AUTHORIZATION = re.compile(
    r"(?i)\b((?:proxy-)?authorization[\"']?\s*[:=]\s*[\"']?(?:(bearer|token|basic|digest|negotiate|[a-z0-9-]*hmac[a-z0-9-]*)\s+)?)"
    r"(?!\[redacted)[^\s\"',;]+"
)
_BEARER = re.compile(r"(?i)(bearer\s+)(?!\[redacted)[A-Za-z0-9._~+/=-]{8,}")
_BASIC = re.compile(r"(?i)\b(basic\s+)([A-Za-z0-9+/]{6,}={0,2})(?![A-Za-z0-9+/=])")
_JWT = re.compile(r"\beyJ[A-Za-z0-9_-]{8,}\.[A-Za-z0-9_-]{8,}\.[A-Za-z0-9_-]{8,}")
_PREFIXED_TOKEN = re.compile(
    r"\b(?:gh[pousr]_[A-Za-z0-9]{30,}|github_pat_\w{22,}|glpat-[\w-]{20,}|xox[abprs]-[\w-]{10,}|AIza[\w-]{35}|sk_live_[0-9A-Za-z]{20,})"
)
_AWS_KEY_ID = re.compile(r"\b(?:AKIA|ASIA|ABIA|ACCA|AGPA|AIDA|AIPA|ANPA|ANVA|AROA|APKA|ASCA)[A-Z0-9]{16}\b")
_SIGNATURE = re.compile(r"([?&](?:sig|signature|X-Amz-Signature|X-Amz-Credential)=)([^&\s#\"']+)")
_NAMED = re.compile(  # a name that says it holds a credential, then ':' or '=' (a header, an option, JSON, YAML)
    r"(?<![\w.-])(?P<name>[\w.-]*(?i:[-_.]key)|[A-Za-z0-9]*[a-z0-9]Key|(?i:apikey|accountkey)"
    r"|[\w.-]*?(?i:token|secret|password|passwd|passphrase|pwd|credentials?))"
    r"(?P<sep>[\"']?\s*[:=](?!=)\s*(?:(?i:bearer|basic|token)\s+)?)"
    r"(?P<value>\"(?!\[redacted)(?:[^\"\\]|\\.)+\"|'(?!\[redacted)[^']+'"
    r"|(?!\[redacted|(?i:bearer|basic|token)\s+\[redacted)[^\s;,&\"'<>(){}\[\]]+)"
)


def redact(text: str, secrets: dict[str, str]) -> str:
    """``text`` without the values of ``secrets``, keys, passwords and tokens: one window read alone (the
    dashboard's tail, ``logs.yml lines=N``); ``Redactor`` reads a stream of windows."""
    return Redactor(secrets).redact(text)


class Redactor:
    """Takes secrets out of one container's log, read window after window (a tail, then each ``follow`` poll).

    Line by line, so that no window shows a piece of a key whatever line it starts or ends at:

    - from a private key's or PGP private key's BEGIN line to its END line, every line is hidden, the block shown as
      one ``[redacted: private key]``; the state carries from one window to the next (a certificate's or a public
      key's block is shown);
    - a line shaped like a PEM or armored body line (40 to 76 characters of the base64 alphabet with upper- and
      lower-case letters and a digit, ``+`` or ``/``, changing between them as randomly as base64 does: not hex,
      not a path, not a CamelCase name) is hidden wherever it is, and so are the
      short last line and the PGP checksum after it, an END line and the body lines just before it, and the first
      line of a stream when it looks like a body's last line (it may be one, cut from the rest by the window);
    - on every other line: the Secrets' values in every form (``value_forms``), a URL's password, the credentials
      of an ``Authorization`` header (Basic, Bearer, any scheme), bearer tokens and JWTs, AWS access key ids, the
      tokens of GitHub, GitLab, Slack, Google and Stripe by their prefixes, and the value of anything named like a
      credential (``*-key``, ``*_key``, ``*Key``, ``token``, ``*_token``, ``secret``, ``password``..., then ``:`` or
      ``=``), the name kept.
    """

    def __init__(self, secrets: dict[str, str] | None = None):
        self._values, self._labels = _values_pattern(secrets or {})
        self._block: str | None = None  # the label of the key block being read; "" in a public block
        self._block_lines = 0
        self._after_body = 0  # how many more lines may still end the body just hidden
        self._started = False

    def redact(self, text: str) -> str:
        if not text:  # nothing read yet: the next window's first line is still the stream's first
            return text
        lines = text.split("\n")
        newline = len(lines) > 1 and lines[-1] == ""
        out: list[tuple[str, str | None]] = []  # (what shows, the label when it is a redacted block's)
        for line in lines[:-1] if newline else lines:
            self._line(line, out)
        return "\n".join(shown for shown, _label in out) + ("\n" if newline else "")

    def _line(self, line: str, out: list) -> None:
        first, self._started = not self._started, True
        if self._block is not None and self._in_block(line, out):
            return
        if _MARKER.search(line):
            self._marked(line, out)
            return
        bare = line.strip()
        if _is_body(bare):
            _hide(out, BASE64_BLOCK)
            self._after_body = 2
        elif (self._after_body and _ends_body(bare, self._after_body)) or (first and _may_end_body(bare)):
            _hide(out, BASE64_BLOCK)
            self._after_body = max(self._after_body - 1, 0)
        else:
            self._after_body = 0
            out.append((self._scrub(line), None))

    def _in_block(self, line: str, out: list) -> bool:
        """Whether ``line`` was a line of the block being read (else the block ended long ago: read it as usual)."""
        self._block_lines += 1
        marker = _MARKER.search(line)
        label = self._block
        if marker and marker.group(1) == "BEGIN" and not label:  # a public block's END was lost: read the new one
            self._block = None
            return False
        if marker and marker.group(1) == "END":
            self._block = None
            rest = line[marker.end() :]
            if not label:
                out.append((self._scrub(line), None))
            elif rest.strip():
                _hide(out, label)
                out[-1] = (out[-1][0] + self._scrub(rest), None)
            else:
                _hide(out, label)
            return True
        if self._block_lines > MAX_BLOCK_LINES:
            self._block = None
            return False
        if label:
            _hide(out, label)
        else:
            out.append((self._scrub(line), None))
        return True

    def _marked(self, line: str, out: list) -> None:
        """A line with BEGIN or END markers: whole blocks on it hidden, an open one entered, an END's block before it."""
        shown: list[str] = []
        pos, label = 0, None
        while (marker := _MARKER.search(line, pos)) is not None:
            kind = marker.group(2)
            label = _block_label(kind)
            if marker.group(1) == "END":
                if label:  # the end of a key whose BEGIN line this window does not show
                    if not shown:
                        _retract(out)
                    shown.append(REDACTED.format(label))
                else:
                    shown.append(self._scrub(line[pos : marker.end()]))
                pos = marker.end()
                continue
            closing = re.compile(rf"-{{4,5}} ?END {re.escape(kind)} ?-{{4,5}}").search(line, marker.end())
            if label:
                shown.append(self._scrub(line[pos : marker.start()]) + REDACTED.format(label))
            else:
                shown.append(self._scrub(line[pos : closing.end() if closing else len(line)]))
            if closing is None:
                self._block, self._block_lines, pos = label, 0, len(line)
                break
            pos = closing.end()
        rest = line[pos:]
        if rest:
            shown.append(self._scrub(rest))
            label = None
        self._after_body = 0
        text = "".join(shown)
        if label and out and out[-1][1] == label and text == REDACTED.format(label):
            return
        out.append((text, label or None))

    def _scrub(self, text: str) -> str:
        """``text`` without the Secrets' values and without what has the shape of a credential."""
        if self._values is not None:
            text = self._values.sub(lambda m: REDACTED.format(self._labels[m.group(0)]), text)
        text = _URL_PASSWORD.sub(lambda m: m.group(1) + REDACTED.format("password") + "@", text)
        text = _AUTHORIZATION.sub(_authorization, text)
        text = _BEARER.sub(lambda m: m.group(1) + REDACTED.format("token"), text)
        text = _BASIC.sub(_basic, text)
        text = _JWT.sub(REDACTED.format("token"), text)
        text = _PREFIXED_TOKEN.sub(REDACTED.format("token"), text)
        text = _AWS_KEY_ID.sub(REDACTED.format("AWS access key id"), text)
        text = _SIGNATURE.sub(lambda m: m.group(1) + REDACTED.format("signature"), text)
        return _NAMED.sub(_named, text)


def value_forms(value: str) -> set[str]:
    """The forms a Secret's value takes in a log: itself and each of its lines; its base64 (standard and URL-safe,
    with and without padding, with a line break after it, and inside a longer base64 text: the groups made of its
    bytes alone); percent-encoded (as a path, a query or a form), JSON- and Python-escaped, and hex."""
    forms = {line.strip() for line in value.splitlines()}
    for whole in dict.fromkeys((value, value.strip())):
        if len(whole.strip()) < MIN_SECRET:
            continue
        data = whole.encode()
        forms |= {whole, json.dumps(whole)[1:-1], json.dumps(whole, ensure_ascii=False)[1:-1], repr(whole)[1:-1],
                  data.hex(), data.hex().upper()}  # fmt: skip
        for percent in (quote(whole, safe=""), quote(whole), quote_plus(whole)):
            forms |= {percent, _PERCENT.sub(lambda m: m.group(0).lower(), percent)}
        for raw in (data, data + b"\n"):
            for encode in (base64.b64encode, base64.urlsafe_b64encode):
                encoded = encode(raw).decode()
                forms |= {encoded, encoded.rstrip("=")}
        for offset in (0, 1, 2):
            core = base64.b64encode(b"\0" * offset + data).decode()[4 if offset else 0 : 4 * ((offset + len(data)) // 3)]
            if len(core) >= MIN_CORE:
                forms |= {core, core.translate(_URLSAFE)}
    return {form for form in forms if len(form.strip()) >= MIN_SECRET and "\n" not in form}


def _values_pattern(secrets: dict[str, str]) -> tuple[re.Pattern | None, dict[str, str]]:
    labels_of: dict[str, str] = {}
    for label, value in secrets.items():
        for form in value_forms(value):
            labels_of.setdefault(form, label)
    if not labels_of:
        return None, {}
    return re.compile("|".join(re.escape(form) for form in sorted(labels_of, key=len, reverse=True))), labels_of


def _block_label(kind: str) -> str:
    """What a BEGIN/END block of ``kind`` is redacted as; "" for a block that is shown (a certificate, a public key)."""
    if not any(word in kind for word in ("PRIVATE", "SECRET", "ENCRYPTED")):
        return ""
    return "PGP private key" if kind.startswith("PGP") else "private key"


def _class_changes(bare: str) -> float:
    """How often the next letter or digit is of another kind (upper, lower, digit)."""
    kinds = [c.isupper() - c.islower() for c in bare if c.isalnum()]
    return sum(a != b for a, b in itertools.pairwise(kinds)) / max(len(kinds) - 1, 1)


def _looks_like_path(bare: str) -> bool:
    """Words between slashes: few changes of kind, or a little more with many slashes (random base64 has one slash in
    64 characters, a path one in ten)."""
    slashes, changes = bare.count("/"), _class_changes(bare)
    return (slashes >= 2 and changes < CLASS_CHANGES) or (slashes >= 6 and changes < PATH_CLASS_CHANGES)


def _is_body(bare: str) -> bool:
    if not _BODY.fullmatch(bare) or _HEX.fullmatch(bare) or _class_changes(bare) < CLASS_CHANGES or _looks_like_path(bare):
        return False
    return any(c.isupper() for c in bare) and any(c.islower() for c in bare) and any(c in "+/" or c.isdigit() for c in bare)


def _ends_body(bare: str, allowance: int) -> bool:
    """Right after a body line: its short last line (any length), then the PGP checksum."""
    if allowance == 1:
        return bool(_CHECKSUM.fullmatch(bare))
    return bool(_LOOSE.fullmatch(bare)) and not _HEX.fullmatch(bare) and not _looks_like_path(bare)


def _may_end_body(bare: str) -> bool:
    """The first line of a stream that may be a body's last line: 16 or more base64 characters of two kinds."""
    if len(bare) < 16 or not _LOOSE.fullmatch(bare) or _HEX.fullmatch(bare) or _looks_like_path(bare):
        return False
    return sum((any(c.isupper() for c in bare), any(c.islower() for c in bare), any(c.isdigit() for c in bare))) >= 2


def _hide(out: list, label: str) -> None:
    """One ``[redacted: label]`` for a run of hidden lines."""
    if not (out and out[-1][1] == label):
        out.append((REDACTED.format(label), label))


def _retract(out: list) -> None:
    """Before an END line whose BEGIN is not in the window: the body lines this window showed or hid go with it."""
    while out and (out[-1][1] == BASE64_BLOCK or (out[-1][1] is None and _LOOSE.fullmatch(out[-1][0].strip()))):
        out.pop()


def _authorization(match: re.Match) -> str:
    scheme = (match.group(2) or "").lower()
    return match.group(1) + REDACTED.format("token" if scheme in ("bearer", "token") else "credentials")


def _basic(match: re.Match) -> str:
    """``Basic <base64>`` outside a header: redacted when it decodes to ``user:password``."""
    encoded = match.group(2)
    try:
        decoded = base64.b64decode(encoded + "=" * (-len(encoded) % 4), validate=True).decode()
    except (ValueError, UnicodeDecodeError):
        return match.group(0)
    return match.group(1) + REDACTED.format("credentials") if ":" in decoded else match.group(0)


def _named(match: re.Match) -> str:
    name, value = match.group("name"), match.group("value")
    lowered = name.lower()
    if lowered.endswith("key"):
        what = "key"
    else:
        what = next((label for word, label in _NAMED_LABELS if word in lowered), "password")
    quote_mark = value[0] if value[0] in "\"'" else ""
    return f"{name}{match.group('sep')}{quote_mark}{REDACTED.format(what)}{quote_mark}"


_NAMED_LABELS = (("token", "token"), ("secret", "secret"), ("credential", "credentials"))


def labelled(container: str, text: str, several: bool) -> list[str]:
    """The log's lines, each prefixed with ``[container]`` when the module has several containers."""
    lines = text.splitlines()[-MAX_LINES:]
    return [f"[{container}] {line}" for line in lines] if several else lines
