"""Exceptions raised by submapslam. The CLI turns each into one red line and exit code 1."""

from __future__ import annotations

from pathlib import Path


class SubmapSlamError(Exception):
    """Base class of every error a user can act on."""


class InputError(SubmapSlamError):
    """A log, trajectory or data file could not be read.

    The message names the file and, when known, the 1-based line number.
    """

    def __init__(self, path: str | Path, problem: str, line: int | None = None) -> None:
        self.path = Path(path)
        self.line = line
        self.problem = problem
        where = f"{self.path}" if line is None else f"{self.path}:{line}"
        super().__init__(f"{where}: {problem}")


class UnknownFormatError(InputError):
    """The format of a log could not be sniffed, or a forced format does not exist."""


class ConfigError(SubmapSlamError):
    """A configuration file or value is invalid (misspelled key, wrong type, out of range)."""


class DependencyError(SubmapSlamError):
    """A required third-party library could not be loaded."""


class DivergenceError(SubmapSlamError):
    """An estimator's state stopped being finite (a filter linearised too far from the truth)."""


class OutputError(SubmapSlamError):
    """An output path cannot take the results (a file, an input, a folder of the user's, not
    writable, or an earlier result without ``--overwrite``); found before any work is done."""


class OptimisationError(SubmapSlamError):
    """GTSAM could not solve the pose graph, even after regularising it."""
