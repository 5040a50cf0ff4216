"""The fuzzing tier (tests/fuzz, docs/testing.md): the cases each surface ran, for a benchmark to report.

With ``KUBEROS_FUZZ_COUNTS`` set to a file, each process that ran fuzz cases adds its counts per surface to the JSON
object in that file (``{"spec": 600, ...}``); the tier's tests run in one lane, so one process writes it. The plain
tests of the harness and of the findings (surfaces ``bounds`` and ``findings``) are not drawn cases and not counted.
"""

from __future__ import annotations

import json
import os

from fuzz_bounds import COUNTS


def pytest_sessionfinish(session, exitstatus):
    path = os.environ.get("KUBEROS_FUZZ_COUNTS")
    if not path or not set(COUNTS) - {"bounds", "findings"}:
        return
    counts: dict = {}
    if os.path.exists(path):
        with open(path, encoding="utf-8") as handle:
            counts = json.load(handle)
    for surface, count in COUNTS.items():
        if surface in ("bounds", "findings"):
            continue
        counts[surface] = counts.get(surface, 0) + count
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(dict(sorted(counts.items())), handle, indent=2)
        handle.write("\n")
