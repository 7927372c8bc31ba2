"""The defensive JSON reader (pinpoint_fg/io/jsonfile.py): nesting scan, integer limits, memory on long strings."""

from __future__ import annotations

import json
import random
import re
import tracemalloc
from pathlib import Path

import pytest

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import MAX_JSON_DEPTH, json_depth, load_json

#: The scan's earlier token pattern (a string by alternation, per character), as the reference to agree with.
_REFERENCE = re.compile(r'"(?:[^"\\]|\\.)*"|[\[\]{}]', re.DOTALL)


def _reference_depth(text: str) -> int:
    depth = deepest = 0
    for m in _REFERENCE.finditer(text):
        depth += {"[": 1, "{": 1, "]": -1, "}": -1}.get(m.group(), 0)
        deepest = max(deepest, depth)
    return deepest


def test_the_depth_scan_agrees_with_the_reference_pattern_on_random_text() -> None:
    rng = random.Random(7)
    alphabet = ['"', "\\", "[", "]", "{", "}", "a", " ", "\n", "é", ":"]
    for _ in range(5000):
        text = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 40)))
        assert json_depth(text) == _reference_depth(text), text
    assert json_depth('{"a": ["[[[", {"b": "\\"]]"}]}') == 3


def test_a_long_string_costs_no_memory_per_character(tmp_path: Path) -> None:
    """A 5 MB string in a JSON file: the scan used ~730 MB of backtracking stack (6 GB at 50 MB) before."""
    text = '{"name": "' + "x" * 5_000_000 + '\\n", "list": [[1]]}'
    tracemalloc.start()
    try:
        assert json_depth(text) == 3
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1_000_000, peak
    path = tmp_path / "long.json"
    path.write_text(text, encoding="utf-8")
    assert len(load_json(path)["name"]) == 5_000_001


def test_limits_are_one_located_error(tmp_path: Path) -> None:
    path = tmp_path / "f.json"
    for text, words in (("[" * (MAX_JSON_DEPTH + 1) + "]" * (MAX_JSON_DEPTH + 1), "levels deep"),
                        ('{"a": ' + "9" * 20 + "}", "digits"), ("{'a': 1}", "not valid JSON")):
        path.write_text(text, encoding="utf-8")
        with pytest.raises(InputError, match=words) as exc:
            load_json(path)
        assert str(path) in str(exc.value)
    path.write_text(json.dumps({"a": [1, 2.5, "x"]}), encoding="utf-8")
    assert load_json(path) == {"a": [1, 2.5, "x"]}
