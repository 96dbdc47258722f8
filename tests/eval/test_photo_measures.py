"""The photo measures against hand values (pilight.eval.photo_measures)."""

from __future__ import annotations

import numpy as np
import pytest

from pilight.eval.photo_measures import detail, exposure, halves_asymmetry


def test_asymmetry_detail_and_exposure_of_hand_images():
    gray = np.ones((4, 6, 3), np.float32)  # luminance 1 everywhere (the weights sum to 1)
    right_bright = gray.copy()
    right_bright[:, 3:] = 3.0
    assert halves_asymmetry(right_bright) == pytest.approx(0.5)  # (3 - 1) / (3 + 1)
    assert halves_asymmetry(right_bright[:, ::-1]) == pytest.approx(-0.5)
    assert detail(gray) == 0.0
    # one step of 2 between columns 2 and 3, in each of 4 rows: 8 over the 4 x 5 column differences
    assert detail(right_bright) == pytest.approx(8 / 20)
    assert exposure(2 * gray, gray) == pytest.approx(2.0)
