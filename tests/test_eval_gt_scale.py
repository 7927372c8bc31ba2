"""Ground truth that does not describe its frame (pinpoint_fg.eval.gt_scale): behind, too small, elsewhere."""

from __future__ import annotations

import numpy as np
import pytest

from pinpoint_fg.eval.gt_scale import GT_OFFSET_GATE, GT_SCALE_GATE, gt_mismatch, gt_offset, gt_scale_ratio
from pinpoint_fg.io.recording.reader import read_recording
from pinpoint_fg.io.recording.schema import Recording
from pinpoint_fg.observe import observe_frame
from pinpoint_fg.sim.scenarios import SCENARIOS, simulate


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Recording]:
    base = tmp_path_factory.mktemp("gt_scale")
    return {s: read_recording(simulate(s, 16, seed=11, out=base / s)) for s in SCENARIOS}


def _obs(rec: Recording, k: int):  # noqa: ANN202
    o = observe_frame(rec, rec.frames[k])
    return o.tip_px, o.tail_px, o.backbone_px


def test_true_ground_truth_passes_every_test_on_every_scenario(runs) -> None:  # noqa: ANN001
    """No frame of any scenario (seed 11, unseen by the thresholds' measurement) is left out, with a wide margin:
    the offset stays below a tenth of its gate, the extent ratio below a third of its."""
    worst_offset, worst_ratio, tested = 0.0, 0.0, 0
    for rec in runs.values():
        for k, f in enumerate(rec.frames):
            if f.cam_T_needle_gt is None:
                continue
            meas = _obs(rec, k)
            why, can = gt_mismatch(rec, f.cam_T_needle_gt, *meas)
            assert why is None, (rec.info.name, f.frame, why)
            tested += can
            off = gt_offset(rec, f.cam_T_needle_gt, *meas)
            ratio = gt_scale_ratio(rec, f.cam_T_needle_gt, *meas)
            worst_offset = max(worst_offset, 0.0 if off is None else off[1])
            worst_ratio = max(worst_ratio, 0.0 if ratio is None else ratio)
    assert tested > 100
    assert worst_offset < 0.4 * GT_OFFSET_GATE and worst_ratio < GT_SCALE_GATE / 3


@pytest.mark.parametrize(("cell", "value", "kind"), [
    ((0, 3), 0.5, "elsewhere"),        # 0.5 m typed for 0.5 mm: ~10,000 px beside the needle
    ((1, 3), 0.05, "elsewhere"),       # 5 cm for 0.05 mm
    ((2, 3), "x0.2", "elsewhere"),     # depth five times too small: a huge arc, off the needle
    ((2, 3), "x100", "small"),         # depth in centimetres
    ((2, 3), 1e-9, "behind"),          # the circle through the camera centre: a seen point behind it
])
def test_a_wrong_cell_is_told_apart(runs, cell: tuple[int, int], value: float | str, kind: str) -> None:  # noqa: ANN001
    rec = runs["normal"]
    T = rec.frames[3].cam_T_needle_gt.copy()
    T[cell] = T[cell] * float(value[1:]) if isinstance(value, str) else value
    why, tested = gt_mismatch(rec, T, *_obs(rec, 3))
    assert tested and why is not None and why.kind == kind, why


def test_one_keypoint_a_few_pixels_off_is_not_evidence_against_the_pose(runs) -> None:  # noqa: ANN001
    """A single detection (no extent of its own) 30 px off the projected arc: below the absolute floor."""
    rec = runs["normal"]
    tip, _, _ = _obs(rec, 3)
    why, tested = gt_mismatch(rec, rec.frames[3].cam_T_needle_gt, np.asarray(tip) + [30.0, 0.0], None, None)
    assert tested and why is None


def test_no_measurement_cannot_be_tested(runs) -> None:  # noqa: ANN001
    rec = runs["normal"]
    assert gt_mismatch(rec, rec.frames[3].cam_T_needle_gt, None, None, None) == (None, False)
