"""Hand-drawn catheters turned into partial training targets (segmentation_onnx.catheter_labels)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage as ndi

from segmentation_onnx.catheter_labels import TARGETS, TIP_RADIUS, load_polylines, load_targets, make_target
from segmentation_onnx.data import IGNORE, find_real_dir


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A catheter (half width 3 px) entering at the top and feeding a vessel that runs down-right.

    The 'model' calls both vessel, as the round-7 model did on real images."""
    h = w = 160
    yy, xx = np.mgrid[:h, :w]
    catheter = (np.abs(xx - 40) <= 3) & (yy <= 70)
    t = np.clip((xx - 40) / 70.0, 0, 1)  # vessel from (40, 70) to (110, 140)
    vessel = (np.hypot(xx - (40 + 70 * t), yy - (70 + 70 * t)) <= 2.5) & (yy >= 70)
    image = np.full((h, w), 200, np.uint8)
    image[catheter] = 70
    image[vessel] = 80
    proba = np.zeros((5, h, w), np.float32)
    fg = catheter | vessel
    proba[1][fg] = 0.97
    proba[0][~fg] = 0.97
    proba[0][fg] = 0.03
    proba[1][~fg] = 0.03
    return image, proba, catheter, vessel


def test_drawn_catheter_becomes_catheter_and_the_fed_tree_vessel():
    image, proba, catheter, vessel = _scene()
    polyline = np.array([(43, 1), (38, 35), (41, 69)])  # drawn a few px off the tube
    t = make_target(image, proba, polyline)
    yy, _ = np.mgrid[:image.shape[0], :image.shape[1]]
    shaft = catheter & (yy > 12) & (yy < 70 - TIP_RADIUS)  # away from the border and the tip
    assert (t[shaft] == 2).mean() > 0.95
    assert not np.any((t == 2) & ~catheter & (yy > 12))  # nothing beside the tube is catheter
    far = vessel & (yy > 100)
    assert (t[far] == 1).mean() > 0.95  # the tree the catheter feeds stays vessel
    assert not np.any((t == 2) & vessel & (yy > 70 + TIP_RADIUS))
    assert np.all(t[(np.hypot(*np.mgrid[:160, :160][::-1] - np.array([41, 69])[:, None, None]) <= TIP_RADIUS)
                    & ~catheter] == IGNORE)  # where catheter turns into vessel: no label
    bg = (~catheter & ~vessel)
    assert (t[bg] == 0).mean() > 0.8 and set(np.unique(t)) <= {0, 1, 2, IGNORE}


def test_shipped_targets_split_and_hold_catheters():
    beside = Path(__file__).resolve().parents[2] / "shared" / "data" / "xca-real"  # ../shared of the checkout
    try:
        real = find_real_dir(beside if beside.is_dir() else None)
    except FileNotFoundError:
        pytest.skip("shared real data (xca-real) not found")
    lines, test = load_polylines(TARGETS.with_suffix(".json"))
    tr_i, tr_t, tr_n = load_targets(TARGETS, real, split="train")
    te_i, te_t, te_n = load_targets(TARGETS, real, split="test")
    assert sorted(te_n) == sorted(test) and not set(tr_n) & set(te_n)
    assert len(tr_n) + len(te_n) == len(lines) >= 40
    for im, t in zip(tr_i + te_i, tr_t + te_t, strict=True):
        assert im.shape == t.shape
        cath = t == 2
        assert cath.sum() > 300
        ring = ndi.binary_dilation(cath, iterations=8) & ~ndi.binary_dilation(cath, iterations=3)
        assert im[cath].mean() < im[ring].mean() - 5  # on a dark tube, not beside it
    with pytest.raises(ValueError, match="split"):
        load_targets(TARGETS, real, split="val")


def test_catheter_tip_error_against_a_known_tip():
    """The tip phase matching takes from labels, measured against the true tip (x, y)."""
    from segmentation_onnx.evaluate import catheter_tip_errors

    lab = np.zeros((3, 96, 96), np.uint8)
    lab[0, :61, 29:32] = 2            # catheter from the top edge down to row 60, column 30
    lab[0, 60:90, 30:33] = 1          # the vessel it feeds goes on
    lab[1, 20:70, 40:43] = 1          # no catheter at all
    lab[2, 34:37, :41] = 2            # from the left edge to column 40: tip (40, 35)
    d = catheter_tip_errors(lab, np.array([[30.0, 60.0], [50.0, 50.0], [40.0, 35.0]]))
    assert d[0] < 2.0 and d[2] < 2.0
    assert np.isnan(d[1])
    # the same labels against a tip 25 px further on: the distance says so
    d2 = catheter_tip_errors(lab[:1], np.array([[30.0, 85.0]]))
    assert 23.0 < d2[0] < 27.0
