"""Exceptions raised for bad input. Each subclasses the builtin a caller would catch
(``ValueError``, ``TypeError``, ``MemoryError``) and its message names the argument."""

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


__all__ = [
    "DTypeError",
    "IndexRangeError",
    "InvalidArgumentError",
    "NonFiniteError",
    "ShapeError",
    "SizeLimitError",
    "UnitsError",
]
