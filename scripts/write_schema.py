"""Write docs/rosdeployment.schema.json from the schema the validator uses."""

import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, ".collections"))

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.schema import SCHEMA  # noqa: E402

TARGET = os.path.join(ROOT, "docs", "rosdeployment.schema.json")


def schema_text() -> str:
    return json.dumps(SCHEMA, indent=2) + "\n"


if __name__ == "__main__":
    os.makedirs(os.path.dirname(TARGET), exist_ok=True)
    with open(TARGET, "w", encoding="utf-8") as handle:
        handle.write(schema_text())
    print(f"wrote {os.path.relpath(TARGET, ROOT)}")
