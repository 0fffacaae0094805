"""Ground-truth depth is read as the scene's depth format is everywhere (schemas.scene_loader.read_depth_file):
the evaluate stage and the report refuse what the depth stage refuses."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from runfs.errors import PanoError
from stages.evaluate import load_gt_depth


def test_a_millimetre_png_is_metres_with_its_zeros_invalid_and_resampled_by_nearest(tmp_path):
    mm = np.full((8, 16), 2500, np.uint16)
    mm[:, :8] = 1200
    mm[0, 0] = 0  # no ground truth there
    cv2.imwrite(str(tmp_path / "d.png"), mm)
    d = load_gt_depth(tmp_path / "d.png", (4, 8))
    assert d.shape == (4, 8) and d.dtype == np.float32
    assert np.isnan(d[0, 0])
    # nearest: only values the file holds, never a blend across the 1.2 / 2.5 m edge
    np.testing.assert_allclose(np.unique(d[np.isfinite(d)]), [1.2, 2.5], rtol=1e-6)


@pytest.mark.parametrize("make, problem", [
    (lambda p: cv2.imwrite(str(p), np.full((8, 16), 200, np.uint8)), "16-bit"),
    (lambda p: cv2.imwrite(str(p), np.full((8, 12), 2000, np.uint16)), "2:1"),
])
def test_a_gt_depth_png_the_depth_stage_would_refuse_is_refused_in_one_line(tmp_path, make, problem):
    path = tmp_path / "gt.png"
    make(path)
    with pytest.raises(PanoError) as e:
        load_gt_depth(path, (8, 16))
    assert problem in str(e.value) and "\n" not in str(e.value)
