"""One exception base for the whole station, mapped to exit codes at the CLI."""

from __future__ import annotations

from pathlib import Path


class DepthstationError(Exception):
    """Base of every error the station raises on purpose; exit code 1 unless said otherwise."""

    exit_code = 1


class InputError(DepthstationError):
    """Bad input from the user (a file that is no recording, a broken protocol): exit code 2."""

    exit_code = 2

    def __init__(self, path: str | Path | None, problem: str) -> None:
        self.path = None if path is None else Path(path)
        self.problem = problem
        message = problem if path is None else f"{path}: {problem}"
        super().__init__(message)


class CaptureError(DepthstationError):
    """Reading or writing a capture failed for a reason other than bad input."""


class CameraError(DepthstationError):
    """A camera could not be opened or stopped delivering frames."""


class CameraDisconnected(CameraError):
    """The camera dropped off mid-stream (USB unplug, simulated fault)."""


class EvaluationError(DepthstationError):
    """An evaluation could not produce a result (e.g. no usable frame at all)."""


class SimulationError(DepthstationError):
    """The simulator was given a scene or model it cannot render."""


class ProtocolError(InputError):
    """A capture protocol TOML is invalid; the message names the key."""
