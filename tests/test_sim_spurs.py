"""The optional mask-spur outliers of the simulator (SimConfig.mask_spur_prob)."""

from __future__ import annotations

import numpy as np
import pytest

from factors.residuals import conic_residual
from pinpoint_fg.observe import backbone_from_mask
from pinpoint_fg.sim.config import SimConfig
from pinpoint_fg.sim.scenarios import simulate_frames


def test_spurs_off_by_default_and_outliers_when_on() -> None:
    plain = simulate_frames("normal", 45, 3)
    again = simulate_frames("normal", 45, 3, SimConfig(mask_spur_prob=0.0))
    spurs = simulate_frames("normal", 45, 3, SimConfig(mask_spur_prob=1.0))
    assert plain.masks.keys() == again.masks.keys()
    for k in plain.masks:
        np.testing.assert_array_equal(plain.masks[k], again.masks[k])  # off draws nothing: same runs as before
    cam, nd = spurs.config.camera, spurs.config.needle
    far_plain, far_spur, worst = 0, 0, 0.0
    for k in sorted(set(plain.masks) & set(spurs.masks)):
        assert np.count_nonzero(spurs.masks[k]) > np.count_nonzero(plain.masks[k])  # spurs only add pixels
        for run, is_spur in ((plain, False), (spurs, True)):
            pts = backbone_from_mask(run.masks[k], cam)
            r = np.abs(conic_residual(run.cam_T_needle[k], cam.K, nd.radius_m, pts, jacobian=False)[0][0])
            if is_spur:
                far_spur += int(np.sum(r > 8.0))
                worst = max(worst, float(r.max()))
            else:
                far_plain += int(np.sum(r > 8.0))
    assert far_plain == 0
    # skeleton branches 20-35 px long (distorted px; undistortion and the first-order Sampson distance stretch it)
    assert far_spur > 50 and 15.0 < worst < 50.0


def test_spur_config_validation() -> None:
    with pytest.raises(ValueError, match="mask_spur_prob"):
        SimConfig(mask_spur_prob=1.5)
    with pytest.raises(ValueError, match="mask_spur_length_px"):
        SimConfig(mask_spur_length_px=(30.0, 20.0))
