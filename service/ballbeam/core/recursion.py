"""First-order linear recursions, the one filter the planner and the synthesis need.

``y_k = gain · u_k + pole · y_{k−1}``, evaluated in that order so the result is the same to the
bit as ``scipy.signal.lfilter([gain], [1, −pole], u, zi=[pole · y_{−1}])``, which the golden
replay was recorded with. Written out because importing ``scipy.signal`` costs every process
that plans or synthesises about a second at start (longer than the loop it replaces).
"""

from __future__ import annotations

import numpy as np


def first_order_response(
    pole: complex, drive: np.ndarray, before: complex, gain: float = 1.0
) -> np.ndarray:
    """``y`` (same length and dtype as ``drive``) of ``y_k = gain·u_k + pole·y_{k−1}`` with
    ``y_{−1} = before``."""
    values = drive.tolist()
    previous = before
    for index, value in enumerate(values):
        previous = gain * value + pole * previous
        values[index] = previous
    return np.asarray(values, dtype=drive.dtype)
