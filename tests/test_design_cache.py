"""What the assembly keeps between designs in one process (the parts no plan changes, and the
time-optimal plans) must give the design a fresh process would, and verify's comparison of
today's synthesis with the recorded design must not encode a design over and over."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest

from ballbeam import assembly, plant_assembly
from ballbeam.config import load_config
from ballbeam.core.control import ControllerDesign
from ballbeam.core.model import LinearModel, as_row4
from ballbeam.core.observer import design_observer
from ballbeam.core.tracker import stationary_gain
from ballbeam.logs import design_record


def _arrays(design: ControllerDesign) -> dict[str, bytes]:
    """Every recorded array, as its bytes (bit for bit), read back from the record itself."""
    with np.load(io.BytesIO(design_record.encode_design(design))) as archive:
        return {name: archive[name].tobytes() for name in archive.files}


def test_a_design_made_again_is_the_fresh_one_bit_for_bit() -> None:
    config = load_config("paper", [])
    assembly.clear_design_caches()
    fresh = _arrays(assembly.controller_design(config))
    again = assembly.controller_design(config)
    assert _arrays(again) == fresh
    # What the law reads (its rows, built from shared tuples) is the arrays' own numbers.
    assert np.array(again._gain_rows).tobytes() == np.asarray(again.gains).tobytes()
    assert np.array(again._reference_rows).tobytes() == again.reference_states.tobytes()


def test_kept_pieces_follow_the_config_they_were_made_for() -> None:
    """A config that differs in a kept piece's key gets that piece computed for it: against
    the rest gains and the observer computed directly, not through the assembly."""
    base = load_config("paper", [])
    assembly.controller_design(base)  # the default's pieces are kept now
    changed = load_config(
        "paper", ["tracker.rest_r=2.0", "observer.input_noise_v=0.7", "plan.theta_margin_deg=1"]
    )
    design = assembly.controller_design(changed)
    model = LinearModel.from_constants(plant_assembly.physical_constants(changed))
    rest, _ = stationary_gain(
        model, np.diag(changed.tracker.rest_q), np.array([[2.0]]), changed.controller.period_s
    )
    assert design.rest_gains is not None
    assert design.rest_gains.gain == as_row4(rest[0])
    observer = design_observer(
        model.discretize(changed.controller.period_s),
        input_noise_v=0.7,
        ball_noise_m_s2=changed.observer.ball_noise_m_s2,
        angle_noise_rad=changed.sensors.encoder_step_rad / math.sqrt(12.0),
        position_noise_m=math.hypot(
            assembly.DEFAULT_POSITION_NOISE_M,
            changed.sensors.adc_step_m(plant_assembly.physical_constants(changed).beam_length_m)
            / math.sqrt(12.0),
        ),
    )
    assert list(design.observer.L) == [(float(a), float(b)) for a, b in observer.L]
    # The plan's margin changed: a plan of its own, and it is the fresh process's plan.
    assert design.plan_duration_s != assembly.controller_design(base).plan_duration_s
    again = _arrays(design)
    assembly.clear_design_caches()
    assert _arrays(assembly.controller_design(changed)) == again


def test_kept_plans_cannot_be_changed_by_a_caller() -> None:
    plan = assembly.make_plan(load_config("paper", []))
    for array in (plan.input_v, plan.grid_states):  # type: ignore[attr-defined]
        with pytest.raises(ValueError):
            array[0] = 0.0


def test_comparing_two_designs_encodes_neither_more_than_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """verify reports how today's synthesis compares with the recorded design; it encoded and
    compressed today's design again for every recorded array (~70 times: 1.4 s of a 1 s log's
    1.7 s verify)."""
    design = assembly.controller_design(load_config("paper", []))
    compressed = []
    original = np.savez_compressed

    def counting(*args: object, **kwargs: object) -> None:
        compressed.append(1)
        original(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(np, "savez_compressed", counting)
    assert design_record.design_difference(design, design) == 0.0
    assert len(compressed) <= 2
