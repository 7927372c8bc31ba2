"""The defensive JSON reader (pinpoint_fg/io/jsonfile.py): nesting scan, integer limits, memory on long strings."""

from __future__ import annotations

import itertools
import json
import random
import tracemalloc
from pathlib import Path

import pytest

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.jsonfile import MAX_JSON_DEPTH, json_depth, load_json


def _reference_depth(text: str) -> int:
    """JSON's string rules character by character (the textbook reading the scan must equal): the characters outside
    strings, then the running sum of their bracket steps."""
    outside = []
    in_string = escape = False
    for c in text:
        if escape:
            escape = False
        elif in_string:
            escape, in_string = c == "\\", c != '"'
        elif c == '"':
            in_string = True
        else:
            outside.append(c)
    steps = [{"[": 1, "{": 1, "]": -1, "}": -1}.get(c, 0) for c in outside]
    return max(itertools.accumulate(steps, initial=0))


def _nested(rng: random.Random, level: int) -> object:
    if level == 0 or rng.random() < 0.3:
        return rng.choice(["a]\\\"{", 1, 2.5, None, True, "[[", "\\"])
    if rng.random() < 0.5:
        return [_nested(rng, level - 1) for _ in range(rng.randint(0, 3))]
    return {f"k{i}[": _nested(rng, level - 1) for i in range(rng.randint(0, 3))}


def _structure_depth(x: object) -> int:
    if isinstance(x, list):
        return 1 + max((_structure_depth(y) for y in x), default=0)
    if isinstance(x, dict):
        return 1 + max((_structure_depth(y) for y in x.values()), default=0)
    return 0


def test_the_depth_scan_follows_json_string_rules_on_random_text() -> None:
    rng = random.Random(7)
    alphabet = ['"', "\\", "[", "]", "{", "}", "a", " ", "\n", "é", ":"]
    for _ in range(5000):
        text = "".join(rng.choice(alphabet) for _ in range(rng.randint(0, 40)))
        assert json_depth(text) == _reference_depth(text), text
    assert json_depth('{"a": ["[[[", {"b": "\\"]]"}]}') == 3
    assert json_depth('"unterminated [[[') == 0  # json.loads stops at the string as well


def test_the_depth_of_valid_json_is_its_nesting() -> None:
    rng = random.Random(11)
    for _ in range(500):
        doc = _nested(rng, 6)
        assert json_depth(json.dumps(doc)) == _structure_depth(doc)


def test_long_strings_cost_no_memory_per_character(tmp_path: Path) -> None:
    """A 5 MB string in a JSON file: the scan used ~730 MB of backtracking stack (6 GB at 50 MB) before; one of
    200,000 escapes, or an unterminated string of escaped quotes (quadratic for the regular expression), alike."""
    text = '{"name": "' + "x" * 5_000_000 + '\\n", "list": [[1]]}'
    for scanned, depth in ((text, 3), ('["' + '\\"' * 200_000 + '"]', 1), ('"' + '\\"' * 200_000, 0)):
        tracemalloc.start()
        try:
            assert json_depth(scanned) == depth
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
