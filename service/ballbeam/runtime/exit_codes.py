"""What ``ballbeam run`` and ``ballbeam daemon`` exit with: a run tells the truth about itself.

=====  ==========================================================================================
code   meaning
=====  ==========================================================================================
0      the run completed (or was stopped on request, SIGINT/SIGTERM) and broke no safety bound
1      a safety bound was broken (the servo angle beyond ``limits.theta_deg``), or the run did
       not complete for another reason
2      usage or bad input (config, log path, bus), or the run could not be recorded
3      the plant was lost (no sensor frames: ``plant_lost``, ``plant_silent``, or none at start)
4      a second writer commanded the plant (``second_writer``): the run was stopped at 0 V
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
# The daemon's codes that mean "a run was recorded" (the launcher summarises its log).
RECORDED_RUN_CODES: Final = frozenset({EXIT_OK, EXIT_FAILED, EXIT_PLANT_LOST, EXIT_SECOND_WRITER})

HELP: Final = (
    "exit codes: 0 completed within bounds; 1 a safety bound broken or the run not completed; "
    "2 usage or bad input; 3 plant lost; 4 a second writer commanded the plant"
)


def exit_code(end_reason: str, bound_broken: bool) -> int:
    """The exit code of a run that ended with ``end_reason``."""
    if end_reason == "second_writer":
        return EXIT_SECOND_WRITER
    if end_reason in PLANT_LOST_REASONS:
        return EXIT_PLANT_LOST
    if end_reason not in STOPPED_ON_REQUEST or bound_broken:
        return EXIT_FAILED
    return EXIT_OK
