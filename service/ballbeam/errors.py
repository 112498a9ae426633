"""One exception hierarchy for the whole project.

Every error a user can cause derives from :class:`BallbeamError` and from the builtin it
resembles, so callers may catch either. The CLI turns any of them into one line and exit 2.
"""


class BallbeamError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(BallbeamError, ValueError):
    """A configuration file, override or argument is missing, malformed or out of range."""


class PlanningError(BallbeamError, ValueError):
    """No path satisfies the requested limits from the requested start."""


class FrameError(BallbeamError, ValueError):
    """A CAN frame is malformed, corrupt, or outside the frame contract."""


class BusError(BallbeamError, OSError):
    """The CAN bus cannot be opened or used as configured."""


class LogFormatError(BallbeamError, ValueError):
    """A file is not a readable ballbeam MCAP log."""


class OutputExistsError(BallbeamError, FileExistsError):
    """A file a command would write is already there (a file, a link, anything): nothing is
    ever written over or through it."""


class DecompressionBombError(LogFormatError):
    """Compressed data in a log would inflate past the size it states, or past the bound."""


class RecorderError(BallbeamError, OSError):
    """The run recorder cannot write its log."""


class LiveViewError(BallbeamError, OSError):
    """The live view's WebSocket server cannot start (e.g. its port is taken)."""


class ClusterError(BallbeamError, ConnectionError):
    """The Dask cluster a study runs on cannot be started or reached."""
