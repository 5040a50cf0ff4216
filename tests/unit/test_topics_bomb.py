"""Declared topics stay bounded (issue 44): a spec whose modules share one ``topics`` block through YAML aliases is
refused in at most 20 lines and a count, quickly and in little memory; on ordinary specs the findings are the ones the
pair-by-pair check gives, in the same order."""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import pytest
from topics_bomb import bomb_spec, pair_findings

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import topics
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments
from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec_model import DeclaredTopic

TESTS = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
COLLECTIONS = os.path.join(os.path.dirname(TESTS), ".collections")


def _refusal(text: str) -> list[str]:
    with pytest.raises(SpecError) as caught:
        load_rosdeployments(text, "bomb.yml")
    return [str(p) for p in caught.value.problems]


@pytest.mark.parametrize("qos", [False, True], ids=["types", "qos"])
def test_the_bomb_is_refused_in_twenty_lines_and_a_count(qos):
    lines = _refusal(bomb_spec(qos=qos))
    assert len(lines) == topics.MAX_FINDINGS + 1, len(lines)
    assert all(line.startswith("bomb.yml:") for line in lines), lines[0]
    assert "m0 subscribes to /{robot}/t0 but m19 publishes it: " in lines[-2]
    more = pair_findings() - topics.MAX_FINDINGS
    assert lines[-1].endswith(f": ... and {more} more problems of declared topics like these (the first 20 are listed)")


def test_every_document_of_a_bombed_file_shows_its_own_twenty_lines():
    lines = _refusal(bomb_spec(modules=50, topics=20, documents=3))
    assert len(lines) == 3 * (topics.MAX_FINDINGS + 1)
    assert sum("more problems of declared topics" in line for line in lines) == 3


def test_a_file_of_many_bombs_is_refused_by_its_total_of_nodes_before_the_schema_sees_them_all():
    from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import yaml_source

    lines = _refusal(bomb_spec(documents=10))
    assert len(lines) == 1, lines
    assert lines[0].endswith(
        f"file too large: more than {yaml_source.MAX_TOTAL_NODES} YAML nodes in the file's documents together (aliases included)"
    ), lines[0]


def test_the_bomb_takes_under_two_seconds_and_200_mib():
    """In a fresh process: the CPU time of the refusal (not its wall time, which other tests running beside it
    stretch) and the process's peak resident memory (VmHWM: getrusage's ru_maxrss keeps the forking test process's
    size across exec). Before the cap: 9.5 s, 800 MiB, a million lines."""
    child = textwrap.dedent(
        f"""
        import json, sys, time
        sys.path[:0] = [{TESTS!r}, {COLLECTIONS!r}]
        from topics_bomb import bomb_spec
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.errors import SpecError
        from ansible_collections.kuberos.platform.plugins.module_utils.kuberos.spec import load_rosdeployments
        text = bomb_spec(qos=True)
        start = time.process_time()
        try:
            load_rosdeployments(text, "bomb.yml")
        except SpecError as exc:
            out = str(exc)
        seconds = time.process_time() - start
        with open("/proc/self/status") as status:
            peak = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:")) / 1024
        print(json.dumps({{"seconds": seconds, "peak_mib": peak, "lines": out.count(chr(10)) + 1}}))
        """
    )
    result = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=120, check=True)
    figures = json.loads(result.stdout)
    assert figures["lines"] == topics.MAX_FINDINGS + 2, figures  # the title, 20 findings, the count
    assert figures["seconds"] < 2.0, figures
    assert figures["peak_mib"] < 200, figures


# -- the same findings as the pair-by-pair check ------------------------------------------------------------------


def _pairwise(modules) -> list[str]:
    """The check as it was before grouping: every subscription against every publication of its topic."""
    lines, publishers, seen = [], {}, {}
    for module in modules:
        for topic in module.topics:
            key = (module.name, topic.direction, topics.scoped(topic.name))
            if key in seen:
                lines.append(
                    f"{module.name} already declares {topic.direction} {topics.scoped(topic.name)} "
                    f"({topic.direction}[{seen[key].position}]); expected each topic once"
                )
                continue
            seen[key] = topic
            if topic.rate_min is not None and topic.rate_max is not None and topic.rate_min > topic.rate_max:
                lines.append(f"rate min {topic.rate_min:g} Hz is above max {topic.rate_max:g} Hz")
            if topic.direction == "publishes":
                publishers.setdefault(topics.scoped(topic.name), []).append((module, topic))
    for module in modules:
        for topic in module.topics:
            if (
                topic.direction != "subscribes"
                or seen.get((module.name, topic.direction, topics.scoped(topic.name))) is not topic
            ):
                continue
            name = topics.scoped(topic.name)
            offered = publishers.get(name, [])
            if not offered and not topic.external:
                lines.append(
                    f"{module.name} subscribes to {name}, which no module of the deployment publishes; expected a module "
                    "that declares it in publishes, or external: true for a topic published outside the deployment"
                )
            for other, published in offered:
                why = topics._pair_problem(published, topic)  # pylint: disable=protected-access
                if why:
                    lines.append(f"{module.name} subscribes to {name} but {other.name} publishes it: {why}")
    return lines


def _random_modules(rng: random.Random) -> list:
    names = ["a", "b", "/{robot}/a", "/fleet/c"]
    modules = []
    for index in range(rng.randint(1, 6)):
        declared = []
        for direction in topics.DIRECTIONS:
            for position in range(rng.randint(0, 5)):
                low = rng.choice([None, 1.0, 5.0, 20.0])
                declared.append(
                    DeclaredTopic(
                        name=rng.choice(names),
                        type=rng.choice(["x/msg/A", "x/msg/B"]),
                        direction=direction,
                        reliability=rng.choice(["reliable", "best_effort"]),
                        durability=rng.choice(["volatile", "transient_local"]),
                        deadline_ms=rng.choice([None, 100.0, 200.0]),
                        liveliness=rng.choice(["automatic", "manual_by_topic"]),
                        lease_ms=rng.choice([None, 1000.0]),
                        rate_min=low,
                        rate_max=rng.choice([None, 2.0, 10.0, 50.0]),
                        external=direction == "subscribes" and rng.random() < 0.2,
                        position=position,
                    )
                )
        modules.append(SimpleNamespace(name=f"m{index}", topics=tuple(declared)))
    return modules


@pytest.mark.parametrize("seed", range(300))
def test_the_grouped_check_finds_what_the_pairwise_check_finds_in_the_same_order(seed):
    modules = _random_modules(random.Random(seed))
    expected = _pairwise(modules)
    everything = topics.declaration_findings(modules, limit=10**6)
    assert [f.message for f in everything.shown] == expected
    assert everything.more == 0
    limit = random.Random(seed).randint(0, 8)
    capped = topics.declaration_findings(modules, limit=limit)
    assert [f.message for f in capped.shown] == expected[:limit]
    assert capped.more == max(0, len(expected) - limit)
