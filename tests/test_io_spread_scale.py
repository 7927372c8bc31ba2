"""The spread-scale file (io/spread_scale.py): its reader names every bad field; the tracked-scale entry."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pinpoint_fg.errors import InputError
from pinpoint_fg.io.spread_scale import MethodScale, SpreadScale, recorded_scale, scaled_cov_xi, settings_entry


def valid_doc() -> dict:
    """A valid spread-scale document."""
    return {"format": "pinpoint-spread-scale", "version": 1, "level": 0.95, "mode_gate_rad": 0.5,
            "methods": {"svn": {"kappa_trans": 1.9, "kappa_rot": 2.2, "frames": 10, "skipped_frames": 0,
                                "wrong_mode_frames": 0, "coverage_raw_trans": 0.7, "coverage_raw_rot": None}},
            "unfitted": {"pf": "collapsed"}, "results": ["a"]}


def test_a_valid_document_loads(tmp_path: Path) -> None:
    path = tmp_path / "scale.json"
    path.write_text(json.dumps(valid_doc()))
    scale = SpreadScale.load(path)
    s = scale.methods["svn"]
    assert list(scale.methods) == ["svn"] and math.isnan(s.coverage_raw_rot)  # null: not recorded
    assert s == MethodScale(1.9, 2.2, frames=10, coverage_raw_trans=0.7, coverage_raw_rot=s.coverage_raw_rot)
    assert (scale.level, scale.mode_gate_rad, scale.unfitted, scale.results) == (0.95, 0.5, {"pf": "collapsed"}, ("a",))
    assert settings_entry(scale, "svn") == {"file": str(path.resolve()), "kappa_trans": 1.9, "kappa_rot": 2.2}
    with pytest.raises(InputError, match="could not be fitted"):
        settings_entry(scale, "pf")


def test_factors_fitted_for_another_coverage_are_not_applied(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A file of factors for 90 % coverage loads (the format allows any level) but scales no q95 column: those are
    95 % bounds, and applying it would have labelled a 90 % bound q95, silently."""
    from pinpoint_fg.cli import main

    path = tmp_path / "scale90.json"
    path.write_text(json.dumps({**valid_doc(), "level": 0.9}))
    scale = SpreadScale.load(path)
    assert scale.level == 0.9
    with pytest.raises(InputError, match="fitted for 90 % coverage") as exc:
        settings_entry(scale, "svn")
    assert exc.value.column == "level"
    run = tmp_path / "run"
    assert main(["simulate", "--scenario", "normal", "--frames", "3", "--seed", "1", "--out", str(run)]) == 0
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["track", str(run), "--method", "svn", "--spread-scale", str(path), "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "'level'" in err[0] and str(path) in err[0]
    assert not out.exists() or not any(out.iterdir())




def _set(doc: dict, dotted: str, value: object) -> dict:
    *head, last = dotted.split(".")
    d = doc
    for k in head:
        d = d[k]
    if value is _DELETE:
        del d[last]
    else:
        d[last] = value
    return doc


_DELETE = object()


@pytest.mark.parametrize(("field", "value", "column", "match"), [
    ("format", "pinpoint-noise", "format", "must be 'pinpoint-spread-scale'"),
    ("format", _DELETE, "format", "must be"),
    ("version", 2, "version", "unsupported version"),
    ("version", True, "version", "unsupported version"),
    ("level", 1.5, "level", "must lie in"),
    ("level", "0.95", "level", "must be a number"),
    ("level", _DELETE, "level", "missing required key"),
    ("mode_gate_rad", -0.1, "mode_gate_rad", "must lie in"),
    ("mode_gate_rad", 4.0, "mode_gate_rad", "must lie in"),
    ("methods", {}, "methods", "non-empty object"),
    ("methods", [1], "methods", "non-empty object"),
    ("methods.svn", 3, "methods.svn", "must be an object"),
    ("methods.svn.kappa_trans", -1.0, "methods.svn.kappa_trans", "must be positive"),
    ("methods.svn.kappa_trans", 0.0, "methods.svn.kappa_trans", "must be positive"),
    ("methods.svn.kappa_rot", _DELETE, "methods.svn.kappa_rot", "missing required key"),
    ("methods.svn.kappa_rot", None, "methods.svn.kappa_rot", "must be a number"),
    ("methods.svn.kappa_rot", True, "methods.svn.kappa_rot", "must be a number"),
    ("methods.svn.kappa_rot", 1e400, "methods.svn.kappa_rot", "must be finite"),
    ("methods.svn.frames", -3, "methods.svn.frames", "non-negative integer"),
    ("methods.svn.frames", 2.5, "methods.svn.frames", "non-negative integer"),
    ("methods.svn.coverage_raw_trans", 1.2, "methods.svn.coverage_raw_trans", "must lie in"),
    ("results", "a", "results", "list of strings"),
    ("unfitted", {"pf": 3}, "unfitted", "method -> reason"),
    ("unfitted", {"svn": "x"}, "unfitted.svn", "both fitted and unfitted"),
])
def test_reader_names_the_bad_field(tmp_path: Path, field: str, value: object, column: str, match: str) -> None:
    path = tmp_path / "scale.json"
    path.write_text(json.dumps(_set(valid_doc(), field, value)))
    with pytest.raises(InputError, match=match) as exc:
        SpreadScale.load(path)
    assert exc.value.column == column and exc.value.file == str(path)
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize("text", ["", "{", "[1, 2]", '"x"', "null", "{\"format\": NaN}", "\xff"])
def test_reader_refuses_malformed_json(tmp_path: Path, text: str) -> None:
    path = tmp_path / "scale.json"
    path.write_text(text, encoding="latin-1")
    with pytest.raises(InputError) as exc:
        SpreadScale.load(path)
    assert exc.value.file == str(path)


def test_reader_refuses_nan_and_infinity_literals(tmp_path: Path) -> None:
    for literal, column in (("NaN", "kappa_trans"), ("Infinity", "kappa_rot"), ("-Infinity", "kappa_trans")):
        path = tmp_path / "scale.json"
        path.write_text(json.dumps(valid_doc()).replace('"kappa_trans": 1.9' if column == "kappa_trans"
                                                         else '"kappa_rot": 2.2', f'"{column}": {literal}'))
        with pytest.raises(InputError, match="must be finite") as exc:
            SpreadScale.load(path)
        assert exc.value.column == f"methods.svn.{column}"


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-5, 10**20) | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12,
)
_FIELDS = ["format", "version", "level", "mode_gate_rad", "methods", "methods.svn", "methods.svn.kappa_trans",
           "methods.svn.kappa_rot", "methods.svn.frames", "methods.svn.skipped_frames",
           "methods.svn.coverage_raw_rot", "unfitted", "results"]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(_FIELDS), value=_JSON)
def test_reader_fuzz_only_input_errors(tmp_path: Path, field: str, value: object) -> None:
    """Any value in any field either loads into a valid scale or raises one InputError; never another exception."""
    path = tmp_path / "fuzz.json"
    path.write_text(json.dumps(_set(valid_doc(), field, value)))
    try:
        scale = SpreadScale.load(path)
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    for s in scale.methods.values():
        assert math.isfinite(s.kappa_trans) and s.kappa_trans > 0
        assert math.isfinite(s.kappa_rot) and s.kappa_rot > 0
    assert 0 < scale.level < 1 and 0 < scale.mode_gate_rad <= math.pi



@pytest.mark.parametrize(("entry", "column"), [
    ([1.0], "settings.spread_scale"),
    ({"kappa_rot": 2.0}, "settings.spread_scale.kappa_trans"),
    ({"kappa_trans": 1.0, "kappa_rot": -2.0}, "settings.spread_scale.kappa_rot"),
    ({"kappa_trans": "2", "kappa_rot": 2.0}, "settings.spread_scale.kappa_trans"),
])
def test_recorded_scale_refuses_a_malformed_entry(entry: object, column: str) -> None:
    with pytest.raises(InputError) as exc:
        recorded_scale({"spread_scale": entry}, "r/result.json")
    assert exc.value.column == column
    assert recorded_scale({}, "r/result.json") is None


def test_scaled_cov_xi_scales_the_blocks_by_the_factors() -> None:
    """Rotation block by kappa_rot^2, translation by kappa_trans^2, cross by their product: the covariance of
    ``K xi`` (its Cholesky factor is ``K`` times the input's), so each draw's |omega| and |v| scale by the factors."""
    rng = np.random.default_rng(3)
    A = rng.standard_normal((6, 6)) * np.array([0.02] * 3 + [5e-4] * 3)
    C = A @ A.T + 1e-9 * np.eye(6)
    kt, kr = 2.25, 2.9
    S = scaled_cov_xi(C, kt, kr)
    np.testing.assert_allclose(S[:3, :3], kr**2 * C[:3, :3], rtol=1e-15)
    np.testing.assert_allclose(S[3:, 3:], kt**2 * C[3:, 3:], rtol=1e-15)
    np.testing.assert_allclose(S[:3, 3:], kr * kt * C[:3, 3:], rtol=1e-15)
    assert np.array_equal(S, S.T)
    K = np.diag([kr] * 3 + [kt] * 3)
    Ls = np.linalg.cholesky(S)
    np.testing.assert_allclose(Ls, K @ np.linalg.cholesky(C), rtol=1e-12, atol=1e-12 * np.abs(Ls).max())
