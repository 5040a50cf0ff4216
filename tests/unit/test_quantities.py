"""Units users write, and what they mean."""

import pytest

from ansible_collections.kuberos.platform.plugins.module_utils.kuberos import quantities as q

CPU = [(2, 2000), (0.5, 500), ("500m", 500), ("2", 2000), ("1.5", 1500), (" 250m ", 250), ("0", 0)]
MEMORY = [
    ("512Mi", 512 * 1024**2),
    ("2Gi", 2 * 1024**3),
    ("1G", 10**9),
    ("1000M", 10**9),
    (1024, 1024),
    ("1.5Gi", 1536 * 1024**2),
]
LATENCY = [("200 ms", 200.0), ("200ms", 200.0), ("0.5 s", 500.0), ("1s", 1000.0), (20, 20.0), (2.5, 2.5), ("15", 15.0)]
BAD_CPU = ["four", "-1", -1, "1 core", True, None, [], "1e3", float("nan"), float("inf")]
BAD_MEMORY = ["lots", "1 GB", "-5Mi", -5, True, None, "Gi"]
BAD_LATENCY = ["200 parsecs", "fast", -1, "-3 ms", True, None, "ms", "1 min"]


@pytest.mark.parametrize(("text", "millis"), CPU)
def test_cpu(text, millis):
    assert q.parse_cpu(text) == millis


@pytest.mark.parametrize(("text", "size"), MEMORY)
def test_memory(text, size):
    assert q.parse_memory(text) == size


@pytest.mark.parametrize(("text", "ms"), LATENCY)
def test_latency(text, ms):
    assert q.parse_latency_ms(text) == ms


@pytest.mark.parametrize("value", BAD_CPU)
def test_bad_cpu(value):
    with pytest.raises(ValueError, match="expected a CPU quantity"):
        q.parse_cpu(value)


@pytest.mark.parametrize("value", BAD_MEMORY)
def test_bad_memory(value):
    with pytest.raises(ValueError, match="expected a memory quantity"):
        q.parse_memory(value)


@pytest.mark.parametrize("value", BAD_LATENCY)
def test_bad_latency(value):
    with pytest.raises(ValueError, match="expected a latency"):
        q.parse_latency_ms(value)


@pytest.mark.parametrize(("millis", "text"), [(2000, "2"), (1500, "1500m"), (100, "100m")])
def test_format_cpu(millis, text):
    assert q.format_cpu(millis) == text
    assert q.parse_cpu(text) == millis


@pytest.mark.parametrize(("size", "text"), [(128 * 1024**2, "128Mi"), (2 * 1024**3, "2Gi"), (1000, "1000"), (3 * 1024, "3Ki")])
def test_format_memory(size, text):
    assert q.format_memory(size) == text
    assert q.parse_memory(text) == size
