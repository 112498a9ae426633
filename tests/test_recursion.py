"""The first-order recursion equals scipy's lfilter (an independent, sequential evaluation) to
rounding, for the complex poles of the synthesis and the real ones of the planner, over a
design's whole horizon and with poles as slow as a design's."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from ballbeam.core.recursion import first_order_response


def _assert_close(result: np.ndarray, expected: np.ndarray) -> None:
    # a few units in the last place of the signal's size (the sums run in another order)
    assert np.abs(result - expected).max() <= 1e-13 * np.abs(expected).max()


@pytest.mark.parametrize("seed", range(4))
def test_complex_pole_unit_gain_is_lfilter(seed: int) -> None:
    rng = np.random.default_rng(seed)
    drive = rng.normal(size=8001) + 1j * rng.normal(size=8001)
    pole = complex(rng.uniform(0.9, 0.99999), rng.uniform(-0.05, 0.05))
    before = complex(rng.normal(), rng.normal())
    expected = scipy.signal.lfilter([1.0], [1.0, -pole], drive, zi=[pole * before])[0]
    _assert_close(first_order_response(pole, drive, before), expected)


@pytest.mark.parametrize("seed", range(4))
def test_real_pole_with_gain_is_lfilter(seed: int) -> None:
    rng = np.random.default_rng(seed)
    drive = rng.normal(size=2000) * 5.0
    pole = float(np.exp(-rng.uniform(1.0, 60.0) * 1e-3))
    before = float(rng.normal())
    expected = scipy.signal.lfilter([1.0 - pole], [1.0, -pole], drive, zi=[pole * before])[0]
    result = first_order_response(pole, drive, before, gain=1.0 - pole)
    assert result.dtype == drive.dtype
    _assert_close(result, expected)


def test_empty_drive_gives_empty_response() -> None:
    assert first_order_response(0.5, np.empty(0), 1.0).shape == (0,)


@pytest.mark.parametrize("length", [1, 2, 3, 5, 64, 1000])
def test_short_signals_and_the_first_sample(length: int) -> None:
    drive = np.arange(1.0, length + 1.0)
    expected = scipy.signal.lfilter([2.0], [1.0, -0.5], drive, zi=[0.5 * 3.0])[0]
    _assert_close(first_order_response(0.5, drive, 3.0, gain=2.0), expected)
