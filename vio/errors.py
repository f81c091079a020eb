"""Errors raised for bad input: always one line that names the file and the line."""

from __future__ import annotations

from pathlib import Path


class DataError(ValueError):
    """Malformed or inconsistent input data.

    ``str(err)`` is ``"<path>:<line>: <message>"`` (``<path>: <message>`` when no
    line applies), one line, so a user can jump straight to the offending row.
    """

    def __init__(self, path: str | Path, message: str, line: int | None = None) -> None:
        self.path = str(path)
        self.line = line
        self.message = message
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {message}")

    def __reduce__(self):
        """Picklable (errors cross from the front-end worker process, ``vio.overlap``)."""
        return type(self), (self.path, self.message, self.line)


class ConfigError(ValueError):
    """A configuration file or dictionary that does not match its dataclass."""


def one_line(exc: BaseException, width: int = 120) -> str:
    """An exception's message on one line, for a log record: its first non-blank line
    (GTSAM's messages start with a newline and run to ten lines), cut at ``width``
    characters; the exception's type name when the message is blank."""
    for line in str(exc).splitlines():
        if line.strip():
            return line.strip()[:width]
    return type(exc).__name__
