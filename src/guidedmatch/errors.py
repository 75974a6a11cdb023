"""The package's exceptions: every error a user can cause is a :class:`GuidedMatchError` (a ``ValueError``).

The CLI maps exactly these to one line on stderr and exit status 2; any other exception is a bug and is printed
as "internal error" with exit status 1 (``--debug`` shows the traceback).

* :class:`ConfigError` -- a configuration value out of range, of the wrong type, NaN/inf, or an unknown name.
* :class:`InputError` -- bad input data (feature arrays, descriptors, pair lists, file contents).
* :class:`ImageReadError` -- an image file that is missing, unreadable, truncated or corrupt.
* :class:`DataNotFoundError` -- evaluation data (``GUIDEDMATCH_DATA``) or a file of it is missing (also a
  ``FileNotFoundError``).
* :class:`OutputError` -- an output path that cannot be written (checked before any work).
* :class:`DatabaseError` -- a COLMAP database / feature file that is missing, inconsistent or of the wrong kind.
* :class:`DatabaseBusyError` -- another process is writing the same database.
* :class:`MemoryLimitError` -- the estimated peak memory of a step exceeds what is available.
"""
from __future__ import annotations

__all__ = ["GuidedMatchError", "ConfigError", "InputError", "ImageReadError", "DataNotFoundError", "OutputError", "DatabaseError",
           "DatabaseBusyError", "MemoryLimitError"]


class GuidedMatchError(ValueError):
    """Base class of every error caused by the user's input or configuration."""


class ConfigError(GuidedMatchError):
    """A configuration value is invalid (range, type, NaN/inf, unknown name)."""


class InputError(GuidedMatchError):
    """Input data is invalid (arrays, descriptors, pairs, file contents)."""


class ImageReadError(InputError):
    """An image cannot be read completely (missing, not an image, truncated, corrupt)."""


class DataNotFoundError(InputError, FileNotFoundError):
    """The evaluation data folder, or a file the run needs from it, is missing."""


class OutputError(GuidedMatchError):
    """An output path cannot be written."""


class DatabaseError(GuidedMatchError):
    """A COLMAP database or feature file is missing, inconsistent or of the wrong kind."""


class DatabaseBusyError(DatabaseError):
    """Another process holds the write lock of the same database."""


class MemoryLimitError(GuidedMatchError):
    """The estimated peak memory exceeds the memory available."""
