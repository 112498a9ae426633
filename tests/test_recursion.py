"""The first-order recursion equals scipy's lfilter to the bit (the golden replay was recorded
with lfilter), for the complex poles of the synthesis and the real ones of the planner."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from ballbeam.core.recursion import first_order_response


@pytest.mark.parametrize("seed", range(4))
def test_complex_pole_unit_gain_is_lfilter_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    drive = rng.normal(size=3000) + 1j * rng.normal(size=3000)
    pole = complex(rng.uniform(0.9, 0.9999), rng.uniform(-0.05, 0.05))
    before = complex(rng.normal(), rng.normal())
    expected = scipy.signal.lfilter([1.0], [1.0, -pole], drive, zi=[pole * before])[0]
    assert np.array_equal(first_order_response(pole, drive, before), expected)


@pytest.mark.parametrize("seed", range(4))
def test_real_pole_with_gain_is_lfilter_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    drive = rng.normal(size=2000) * 5.0
    pole = float(np.exp(-rng.uniform(1.0, 60.0) * 1e-3))
    before = float(rng.normal())
    expected = scipy.signal.lfilter([1.0 - pole], [1.0, -pole], drive, zi=[pole * before])[0]
    result = first_order_response(pole, drive, before, gain=1.0 - pole)
    assert result.dtype == drive.dtype and np.array_equal(result, expected)


def test_empty_drive_gives_empty_response() -> None:
    assert first_order_response(0.5, np.empty(0), 1.0).shape == (0,)
