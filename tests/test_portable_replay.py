"""A recorded run verifies on any machine: the design travels in the log, and the per-cycle law
is plain float arithmetic, so no BLAS kernel can change a voltage."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ballbeam.assembly import controller_design
from ballbeam.config import load_config
from ballbeam.core import observer as matrix_observer
from ballbeam.core.control import (
    ControllerDesign,
    ControllerState,
    control_cycle,
    correct,
    predict,
)
from ballbeam.core.plant import SensorReading
from ballbeam.errors import LogFormatError
from ballbeam.logs import design_record
from ballbeam.plant_assembly import design_model

from .conftest import REPO, ballbeam_argv

GOLDEN = Path(__file__).parent / "data" / "golden_paper_1s.mcap"
# OpenBLAS kernels: what an Intel machine, an AVX-512 server, an AMD machine and an old
# generic x86-64 pick (None: whatever OpenBLAS picks for this CPU).
KERNELS = ("Haswell", "SkylakeX", "Zen", "Prescott", None)


@pytest.fixture(scope="module")
def design() -> ControllerDesign:
    return controller_design(load_config(None))


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_the_recorded_design_round_trips_bit_for_bit(design: ControllerDesign) -> None:
    decoded = design_record.decode_design(design_record.encode_design(design), "test")
    for name in ("gains", "offset_v", "final_gain", "reference_states", "reference_input_v"):
        assert same_bits(getattr(decoded, name), getattr(design, name)), name
    assert decoded.observer == design.observer
    assert decoded.guard == design.guard
    # Every learning and blending part of the law, present in the default design, comes back.
    for part in (
        "rest_observer", "rest_gains", "adaptation", "deadzone_learning", "noise_adaptation"
    ):
        assert getattr(design, part) is not None, part
        assert getattr(decoded, part) == getattr(design, part), part
    assert decoded.initial_state == design.initial_state
    assert (decoded.period_s, decoded.angle_per_count, decoded.position_per_count) == (
        design.period_s, design.angle_per_count, design.position_per_count
    )
    # And the same law gives the same voltages from the same readings.
    rng = np.random.default_rng(7)
    states = [ControllerState(), ControllerState()]
    for _ in range(300):
        reading = SensorReading(int(rng.integers(-600, 600)), int(rng.integers(-3000, 3000)))
        outputs = []
        for index, which in enumerate((design, decoded)):
            states[index], output = control_cycle(which, states[index], reading)
            outputs.append(output.voltage_v)
        assert outputs[0] == outputs[1]


def test_the_plain_float_law_is_the_kalman_filter_in_matrix_form(
    design: ControllerDesign,
) -> None:
    """predict/correct against the observer module's numpy form, to rounding."""
    config = load_config(None)
    gains = matrix_observer.design_observer(
        design_model(config).discretize(config.controller.period_s),
        input_noise_v=0.3, ball_noise_m_s2=0.05, angle_noise_rad=1e-3, position_noise_m=2e-4,
    )
    from ballbeam.core.control import ObserverLaw

    law = ObserverLaw.from_arrays(gains.Ad, gains.Bd, gains.C, gains.L)
    rng = np.random.default_rng(3)
    for _ in range(100):
        state = rng.normal(size=4)
        voltage = float(rng.normal())
        measurement = rng.normal(size=2) * 10
        assert_allclose(
            predict(law, tuple(state.tolist()), voltage),  # type: ignore[arg-type]
            matrix_observer.predict(gains, state, voltage), rtol=1e-13, atol=1e-13,
        )
        assert_allclose(
            correct(law, tuple(state.tolist()), tuple(measurement.tolist())),  # type: ignore[arg-type]
            matrix_observer.correct(gains, state, measurement), rtol=1e-13, atol=1e-13,
        )


def npz(**arrays: object) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def good_arrays(design: ControllerDesign) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(design_record.encode_design(design))) as archive:
        return {name: archive[name] for name in archive.files}


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        ({"gains": np.zeros((10, 3))}, "gains"),
        ({"offset_v": np.array([np.nan])}, "not finite"),
        ({"format_version": np.array(99)}, "format 99"),
        ({"observer_L": np.zeros((2, 4))}, "observer"),
        ({"period_s": np.zeros(3)}, "scalar"),
        ({"code": np.array([print], dtype=object)}, "unreadable"),  # would need pickle
    ],
)
def test_a_bad_recorded_design_is_one_clear_error(
    design: ControllerDesign, change: dict[str, object], fragment: str
) -> None:
    arrays: dict[str, object] = {**good_arrays(design), **change}
    with pytest.raises(LogFormatError, match=fragment):
        design_record.decode_design(npz(**arrays), "log.mcap")


def test_a_missing_array_is_named(design: ControllerDesign) -> None:
    arrays = good_arrays(design)
    del arrays["gains"]
    with pytest.raises(LogFormatError, match="missing array 'gains'"):
        design_record.decode_design(npz(**arrays), "log.mcap")


def test_a_design_that_would_unpack_to_gigabytes_is_refused() -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("gains.npy", b"\0" * (design_record.MAX_UNPACKED_BYTES + 1))
    with pytest.raises(LogFormatError, match="refused"):
        design_record.decode_design(buffer.getvalue(), "log.mcap")


# -- across BLAS kernels, in subprocesses ---------------------------------------------------


def kernel_env(kernel: str | None) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("OPENBLAS_CORETYPE", None)
    if kernel is not None:
        env["OPENBLAS_CORETYPE"] = kernel
    return env


def require_kernel(kernel: str | None) -> None:
    """Skip a kernel this CPU cannot execute (SkylakeX needs AVX-512: SIGILL elsewhere)."""
    probe = subprocess.run(
        [sys.executable, "-c", "import numpy as n; a = n.ones((64, 64)); print((a @ a).sum())"],
        env=kernel_env(kernel), capture_output=True, text=True, timeout=60, check=False,
    )
    if probe.returncode != 0:
        pytest.skip(
            f"this CPU cannot run OpenBLAS's {kernel} kernel (exit {probe.returncode}); "
            "run on a machine that can, e.g. one with AVX-512 for SkylakeX"
        )


def verify_under(kernel: str | None, log: Path) -> dict[str, object]:
    completed = subprocess.run(
        ballbeam_argv("replay", str(log), "--verify", "--json"),
        env=kernel_env(kernel), capture_output=True, text=True, timeout=300, check=False,
        cwd=REPO,
    )
    assert completed.returncode == 0, completed.stderr
    payload: dict[str, object] = json.loads(completed.stdout)
    return payload


@pytest.fixture(scope="module")
def fresh_logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """A short lock-step run recorded under each of two kernels that round differently."""
    logs = {}
    for kernel in ("Prescott", "Haswell"):
        directory = tmp_path_factory.mktemp(f"recorded-{kernel}")
        completed = subprocess.run(
            ballbeam_argv("run", "--set", "run.duration_s=0.5", "--set",
                          f"run.log_dir='{directory}'", "--json"),
            env=kernel_env(kernel), capture_output=True, text=True, timeout=300, check=False,
            cwd=REPO,
        )
        assert completed.returncode == 0, completed.stderr
        logs[kernel] = Path(json.loads(completed.stdout)["log_path"])
    return logs


@pytest.mark.bus
@pytest.mark.parametrize("kernel", KERNELS, ids=lambda kernel: kernel or "unset")
def test_logs_verify_bit_for_bit_under_every_kernel(
    kernel: str | None, fresh_logs: dict[str, Path]
) -> None:
    require_kernel(kernel)
    for log in (GOLDEN, *fresh_logs.values()):
        payload = verify_under(kernel, log)
        assert payload["verify_ok"] is True, (log, payload)
        assert payload["verify_design"] == "recorded"
        assert payload["verify_cycles"] in (1000, 500)
        # The synthesis itself may differ in its last bits between kernels: only reported.
        assert isinstance(payload["resynthesis_max_rel_diff"], float)
        assert payload["resynthesis_max_rel_diff"] < 1e-9


def test_a_real_time_design_records_its_lateness_look_ahead() -> None:
    """The guard's lateness steps, allowance and hold come back from the log bit for bit (a
    real-time run replays its look-ahead from /timing with them)."""
    design = controller_design(load_config(None, ["run.mode='realtime'"]))
    assert design.guard is not None and design.guard.lateness_steps
    decoded = design_record.decode_design(design_record.encode_design(design), "test")
    assert decoded.guard == design.guard
    # And how far its commands looked ahead; a log from before (no such array): none.
    assert design.lookahead_periods == decoded.lookahead_periods == 20
    arrays = dict(np.load(io.BytesIO(design_record.encode_design(design))))
    del arrays["lookahead_periods"]
    older = io.BytesIO()
    np.savez_compressed(older, **arrays)
    assert design_record.decode_design(older.getvalue(), "older").lookahead_periods == 0


# -- the re-planning law, across BLAS kernels ----------------------------------------------

# OpenBLAS kernels an x86-64 CPU without AVX-512 can run, each rounding some products its own way
REPLANNING_KERNELS = ("Haswell", "Prescott", "Nehalem", "Sandybridge", "Zen", "SkylakeX")
# Products of the sizes the re-planning law's filter and design use, through numpy and LAPACK.
NUMPY_PROBE = """
import hashlib, numpy as np
rng = np.random.default_rng(1)
F, P = rng.normal(size=(5, 5)), rng.normal(size=(5, 5))
P = P @ P.T
out = []
for _ in range(50):
    P = F @ P @ F.T / np.abs(P).max()
    out.append(np.linalg.solve(P + np.eye(5), F))
print(hashlib.sha1(np.array(out).tobytes()).hexdigest())
"""


def numpy_bits(kernel: str) -> str | None:
    """A digest of numpy's small products under ``kernel`` (None: this CPU cannot run it)."""
    probe = subprocess.run(
        [sys.executable, "-c", NUMPY_PROBE], env=kernel_env(kernel), capture_output=True,
        text=True, timeout=60, check=False,
    )
    return probe.stdout.strip() if probe.returncode == 0 else None


@pytest.fixture(scope="module")
def two_kernels() -> tuple[str, str]:
    """Two kernels this CPU runs whose numpy products differ in their bits."""
    runnable = [(kernel, bits) for kernel in REPLANNING_KERNELS if (bits := numpy_bits(kernel))]
    for kernel, bits in runnable[1:]:
        if bits != runnable[0][1]:
            return runnable[0][0], kernel
    pytest.skip(f"the kernels this CPU runs ({[k for k, _ in runnable]}) round numpy alike")


@pytest.mark.bus
def test_a_replanning_log_verifies_bit_for_bit_under_kernels_that_round_numpy_differently(
    two_kernels: tuple[str, str], tmp_path: Path
) -> None:
    """Recorded in lock-step under one kernel (its designs' Riccati solutions that kernel's),
    re-run under both: every command the same to the bit, with the designs the run took
    injected (none solved again) and the law's cycle in plain floats."""
    recorded_under, other = two_kernels
    completed = subprocess.run(
        ballbeam_argv(
            "run", "--set", "controller.kind='replanning'", "--set", "run.duration_s=0.6",
            "--set", f"run.log_dir='{tmp_path}'", "--json",
        ),
        env=kernel_env(recorded_under), capture_output=True, text=True, timeout=300,
        check=False, cwd=REPO,
    )
    assert completed.returncode == 0, completed.stderr
    log = Path(json.loads(completed.stdout)["log_path"])
    for kernel in (recorded_under, other):
        payload = verify_under(kernel, log)
        assert payload["verify_ok"] is True, (kernel, payload)
        assert payload["verify_cycles"] == 600, (kernel, payload)
