"""A declared-topics bomb: a small RosDeployment whose modules all share one ``topics`` block through a YAML anchor
(``&t``) and aliases (``*t``), so that every module publishes and subscribes the same topics with declarations that
can never match. Checked pair by pair, it makes modules x topics x modules findings (about a million lines from
14 KB of text with the defaults). Used by the unit tests (tests/unit/test_topics_bomb.py) and the benchmarks.

    from topics_bomb import bomb_spec
    text = bomb_spec(modules=100, topics=100)
"""

from __future__ import annotations


def topics_block(topics: int, qos: bool = False) -> list[str]:
    """The shared block, anchored ``&t``: ``topics`` published as one type and subscribed as another (or, with
    ``qos``, the same type best-effort and reliable, so that every pair fails on reliability instead)."""
    published, subscribed = ("x/msg/A", "x/msg/A") if qos else ("x/msg/A", "x/msg/B")
    pub_qos = ", qos: {reliability: best_effort}" if qos else ""
    lines = ["  topics: &t", "    publishes:"]
    lines += [f"    - {{name: t{i}, type: {published}{pub_qos}}}" for i in range(topics)]
    lines += ["    subscribes:"]
    lines += [f"    - {{name: t{i}, type: {subscribed}}}" for i in range(topics)]
    return lines


def bomb_document(name: str, modules: int = 100, topics: int = 100, qos: bool = False) -> str:
    """One RosDeployment named ``name``: ``modules`` modules, the first holding the anchored block, the others
    ``topics: *t``. Every subscription is refused once per module (each publishes it with the other type)."""
    lines = ["apiVersion: kuberos.io/v1alpha1", "kind: RosDeployment", f"metadata: {{name: {name}, targetFleet: test-fleet}}"]
    lines += ["rosModules:", "- name: m0", "  image: reg/m:1", "  launch: python3 -m m"]
    lines += topics_block(topics, qos)
    for index in range(1, modules):
        lines += [f"- name: m{index}", "  image: reg/m:1", "  launch: python3 -m m", "  topics: *t"]
    return "\n".join(lines) + "\n"


def bomb_spec(modules: int = 100, topics: int = 100, documents: int = 1, qos: bool = False) -> str:
    """The bomb's YAML text: ``documents`` deployments (``bomb``, ``bomb-1``, ...) of ``bomb_document``; with the
    defaults (100 modules, 100 topics each way) one document is 13 KB and within the YAML reader's node limit."""
    return "---\n".join(bomb_document("bomb" if i == 0 else f"bomb-{i}", modules, topics, qos) for i in range(documents))


def pair_findings(modules: int = 100, topics: int = 100) -> int:
    """How many subscriber x publisher findings one bomb document holds: every module's subscription of every topic
    against every module's publication of it."""
    return modules * topics * modules


if __name__ == "__main__":
    import sys

    text = bomb_spec(*(int(a) for a in sys.argv[1:3]))
    sys.stdout.write(text)
