"""The expiry of a control plane's kubeadm certificates, read from ``kubeadm certs check-expiration -o json``.

Pure: kubeadm's output (``output.kubeadm.k8s.io`` ``CertificateExpirationInfo``: each certificate's name, its
notAfter as ``expirationDate``, the seconds left as ``residualTime``, its CA, whether it is externally managed or
missing) in, one row per certificate and authority out, and the rows as a table a person reads. Given the output
from before a renewal too, each row says what its notAfter was and whether it moved later. The structured output is
read rather than the text table: the table's columns and its duration format ("364d", "9y") are for people.
"""

from __future__ import annotations

import datetime
import json

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import Problem, SpecError

SOURCE = "kubeadm certs check-expiration"
DAY = 86400


def _document(text, what: str) -> dict:
    body = str(text or "").strip()
    start = body.find("{")
    try:
        found = json.loads(body[start:]) if start >= 0 else None
    except ValueError:
        found = None
    if not isinstance(found, dict) or not isinstance(found.get("certificates"), list):
        shown = body[:200] or "nothing"
        raise SpecError(
            [Problem(SOURCE, what, f"not kubeadm's JSON expiration info (-o json): {shown!r}")], "unreadable certificate expiry"
        )
    return found


def _rows(document: dict) -> list[dict]:
    rows = []
    for kind, key in (("certificate", "certificates"), ("authority", "certificateAuthorities")):
        for entry in document.get(key) or []:
            if not isinstance(entry, dict) or not entry.get("name"):
                continue
            missing = bool(entry.get("missing"))
            residual = entry.get("residualTime")
            residual = residual if isinstance(residual, int) and not isinstance(residual, bool) else None
            rows.append({
                "name": str(entry["name"]),
                "kind": kind,
                "expires": "" if missing else str(entry.get("expirationDate") or ""),
                "residual_days": None if missing or residual is None else residual // DAY,
                "ca": str(entry.get("caName") or ""),
                "externally_managed": bool(entry.get("externallyManaged")),
                "missing": missing,
            })  # fmt: skip
    return rows


def _moment(text: str):
    """An RFC 3339 time (kubeadm's metav1.Time) as an aware datetime; None when empty or not a time."""
    try:
        return datetime.datetime.fromisoformat(str(text).replace("Z", "+00:00")) if text else None
    except ValueError:
        return None


def expiration(text, before=None) -> dict:
    """kubeadm's expiration info as ``{"rows": [...], "soonest_days": n, "moved": bool | None}``: a row per
    certificate and authority (``name``, ``kind``, ``expires`` (RFC 3339, UTC), ``residual_days`` (whole days left,
    negative when expired), ``ca``, ``externally_managed``, ``missing``); with ``before`` (the same command's output
    before a renewal) each row also has ``expires_before`` and ``moved`` (its notAfter later than before), and
    ``moved`` says whether every certificate that kubeadm manages moved (authorities are not renewed)."""
    rows = _rows(_document(text, "output"))
    days = [row["residual_days"] for row in rows if row["residual_days"] is not None]
    result = {"rows": rows, "soonest_days": min(days) if days else None, "moved": None}
    if before is not None:
        earlier = {(row["kind"], row["name"]): row["expires"] for row in _rows(_document(before, "output before renewal"))}
        for row in rows:
            row["expires_before"] = earlier.get((row["kind"], row["name"]), "")
            after, earlier_time = _moment(row["expires"]), _moment(row["expires_before"])
            row["moved"] = bool(after and earlier_time and after > earlier_time)
        renewable = [row for row in rows if row["kind"] == "certificate" and not row["externally_managed"] and not row["missing"]]
        result["moved"] = bool(renewable) and all(row["moved"] for row in renewable)
    return result


def table(result: dict, host: str = "") -> list[str]:
    """The rows of ``expiration`` as aligned lines: name, expires, residual days (and what it expired before)."""
    renewed = any("expires_before" in row for row in result.get("rows", []))
    header = ["CERTIFICATE", "EXPIRES", "RESIDUAL DAYS", *(["BEFORE RENEWAL", "MOVED"] if renewed else [])]
    lines = [header]
    for row in result.get("rows", []):
        name = row["name"] + (" (CA)" if row["kind"] == "authority" else "")
        expires = "MISSING" if row["missing"] else row["expires"]
        days = "" if row["residual_days"] is None else str(row["residual_days"])
        extra = [row.get("expires_before", ""), "yes" if row.get("moved") else "no"] if renewed else []
        lines.append([name, expires, days, *extra])
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    text = ["  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip() for line in lines]
    return [f"{host}:", *("  " + line for line in text)] if host else text
