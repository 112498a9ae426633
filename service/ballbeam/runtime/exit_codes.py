"""What ``ballbeam run`` and ``ballbeam daemon`` exit with: a run tells the truth about itself.

=====  ==========================================================================================
code   meaning
=====  ==========================================================================================
0      the run completed (or was stopped on request, SIGINT/SIGTERM) within its safety bound
1      the run did not complete for another reason, or (``ballbeam run``, which reads the plant's
       truth) the servo angle went beyond ``limits.theta_deg`` by more than
       ``controller.bound_tolerance_deg``
2      usage or bad input (config, log path, bus), the run could not be recorded, or its daemon
       died (``ballbeam run``: the log is then made whole and named)
3      the plant was lost: no sensor frames for ``controller.plant_lost_s`` (the run is
       recorded, 0 V commanded, the file finished)
4      a second writer commanded the plant (``second_writer``: a valid command frame the daemon
       never sent; the run stopped at 0 V at once)
=====  ==========================================================================================
"""

from __future__ import annotations

from typing import Final

EXIT_OK: Final = 0
EXIT_FAILED: Final = 1
EXIT_USAGE: Final = 2
EXIT_PLANT_LOST: Final = 3
EXIT_SECOND_WRITER: Final = 4

PLANT_LOST_REASONS: Final = frozenset({"plant_lost", "plant_silent"})
STOPPED_ON_REQUEST: Final = frozenset({"completed", "SIGINT", "SIGTERM"})

HELP: Final = (
    "exit codes: 0 completed within bounds; 1 not completed, or the angle bound broken (run); "
    "2 usage, bad input or the daemon died; 3 the plant was lost; 4 a second writer "
    "commanded the plant (stopped at 0 V)"
)


def exit_code(end_reason: str, bound_broken: bool = False) -> int:
    """The exit code of a run that ended with ``end_reason``."""
    if end_reason in PLANT_LOST_REASONS:
        return EXIT_PLANT_LOST
    if end_reason == "second_writer":
        return EXIT_SECOND_WRITER
    if end_reason not in STOPPED_ON_REQUEST or bound_broken:
        return EXIT_FAILED
    return EXIT_OK
