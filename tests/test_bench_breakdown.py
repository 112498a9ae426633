"""bench/cycle_breakdown.py puts each function's own time in the part of the cycle it names."""

from __future__ import annotations

from .conftest import import_bench


def test_each_function_goes_to_its_part_and_a_builtin_to_its_callers() -> None:
    breakdown = import_bench("cycle_breakdown")
    recorder = ("/x/service/ballbeam/logs/recorder.py", 300, "record")
    stats = {
        ("~", 0, "<built-in method select.select>"): (1, 1, 0.5, 0.5, {}),
        ("~", 0, "<built-in method _hashlib.hmac_digest>"): (1, 1, 0.25, 0.25, {}),
        ("~", 0, "<built-in method builtins.len>"): (
            1, 1, 0.125, 0.125, {recorder: (1, 1, 0.125, 0.125)}
        ),
        recorder: (1, 1, 1.0, 1.2, {}),
        ("/x/service/ballbeam/core/control.py", 1, "control_cycle"): (1, 1, 2.0, 2.0, {}),
        ("<frozen importlib._bootstrap>", 1, "_find_and_load"): (1, 1, 4.0, 4.0, {}),
        ("/x/elsewhere.py", 1, "f"): (1, 1, 8.0, 8.0, {}),
    }
    parts = breakdown._parts(stats)
    assert parts[breakdown.WAITING] == 0.5
    assert parts["MAC (SecOC)"] == 0.25
    assert parts["recording"] == 1.125
    assert parts["control law / plant physics"] == 2.0
    assert parts[breakdown.STARTUP] == 4.0
    assert parts[breakdown.OTHER] == 8.0
    assert parts["recording: recorder.py:record"] == 1.0
