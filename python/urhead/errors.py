"""Exceptions raised for bad input. Each subclasses the builtin a caller would catch
(``ValueError``, ``TypeError``, ``MemoryError``) and its message names the argument."""

import os
import pickle
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from urhead._core import (
    IndexRangeError,
    InvalidArgumentError,
    NonFiniteError,
    ShapeError,
    SizeLimitError,
)


class DTypeError(TypeError):
    """A tensor has the wrong dtype or device."""


class UnitsError(ValueError):
    """Lengths are not in the unit the computation is stated in (metres)."""


class CorruptFileError(ValueError):
    """A file cannot be read as what it should be (truncated, another format, a part
    missing). ``path`` names the file."""

    def __init__(self, path: str | os.PathLike, message: str):
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class UnsafePickleError(pickle.UnpicklingError, ValueError):
    """A pickle names a callable that loading it would run (``os.system``, ``eval``, …):
    refused before anything is called. A ``ValueError`` too, so it reaches the user as the
    one-line error it is."""


@contextmanager
def reading(path: str | os.PathLike, what: str) -> Iterator[None]:
    """Any failure while reading ``path`` (a ``what``) becomes an error naming it: a
    :class:`CorruptFileError` for what a damaged file raises from deep inside a parser
    (``BadZipFile``, ``EOFError``, ``KeyError``, ``UnpicklingError``, ``RecursionError``,
    …); typed input errors keep their type, with the path put in front when missing."""
    try:
        yield
    except (ValueError, TypeError, OSError) as e:
        if str(path) in str(e):
            raise
        if isinstance(e, FileNotFoundError):
            raise FileNotFoundError(e.errno, f"{path}: {what} not found") from None
        try:
            renamed = type(e)(f"{path}: {e}")
        except TypeError:  # an exception type with another constructor
            renamed = CorruptFileError(path, f"is not a readable {what} ({e})")
        raise renamed from None
    except Exception as e:
        raise CorruptFileError(
            path, f"is not a readable {what} ({type(e).__name__}: {e})"
        ) from None


__all__ = [
    "CorruptFileError",
    "DTypeError",
    "IndexRangeError",
    "InvalidArgumentError",
    "NonFiniteError",
    "ShapeError",
    "SizeLimitError",
    "UnitsError",
    "UnsafePickleError",
]
