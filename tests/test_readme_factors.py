"""The README's factor example runs as written (its code block is extracted and executed)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from gtsam.symbol_shorthand import C, L, X

README = Path(__file__).resolve().parents[1] / "README.md"
SECTION = "## Using the factors in your own GTSAM graph"


def readme_factor_example() -> str:
    """The first ```python block of the README section on the factors."""
    text = README.read_text(encoding="utf-8")
    section = text[text.index(SECTION):]
    section = section[: section.index("\n## ", len(SECTION))]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.DOTALL)
    assert blocks, "the README section has no python block"
    return blocks[0]


def test_readme_factor_example_runs_and_recovers_the_poses(capsys) -> None:
    code = readme_factor_example()
    assert "from factors import" in code and "ISAM2" in code
    scope: dict = {}
    exec(compile(code, str(README), "exec"), scope)  # noqa: S102 - our own README, the point of the test
    est, truth = scope["estimate"], scope["truth"]
    assert est.exists(C(0)) and est.exists(L(0)), "the user's own variables are in the same graph"
    for k, T in enumerate(truth):
        E = est.atPose3(X(k))
        assert np.linalg.norm(E.translation() - T.translation()) < 1e-6
        assert np.linalg.norm(gtsam.Rot3.Logmap(E.rotation().between(T.rotation()))) < 1e-5
    assert capsys.readouterr().out.strip()  # the example prints its result


def test_factors_are_importable_from_the_package() -> None:
    import factors

    for name in ("KeypointFactor", "ConicFactor", "GraspPositionFactor", "GraspPerpendicularFactor", "MotionFactor",
                 "PosePriorFactor", "PinholeCamera", "NeedleModel"):
        assert name in factors.__all__ and getattr(factors, name) is not None
    from factors.gtsam_factors import ConicFactor

    assert factors.ConicFactor is ConicFactor
    assert set(factors.__all__) <= set(dir(factors))
    with pytest.raises(AttributeError, match="no attribute 'NoSuchFactor'"):
        factors.NoSuchFactor  # noqa: B018 - the lookup is the test


def test_the_geometry_and_the_residuals_load_without_gtsam_the_factor_classes_with_it() -> None:
    """``track``'s worker process needs the residuals and the posterior summaries, not GTSAM (~0.15 s to import):
    ``factors`` loads its factor classes on first use. Checked in a fresh interpreter, where nothing is loaded yet."""
    code = ("import sys, factors, factors.residuals, factors.lie, pinpoint_fg.offload\n"
            "assert 'gtsam' not in sys.modules, 'gtsam loaded early'\n"
            "from factors import KeypointFactor\n"
            "assert 'gtsam' in sys.modules and KeypointFactor.__module__ == 'factors.gtsam_factors'\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          cwd=Path(__file__).resolve().parents[1])
    assert done.returncode == 0, done.stderr
