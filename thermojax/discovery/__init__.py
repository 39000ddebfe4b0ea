"""Discovery beyond the vocabulary (docs/formats.md §3a), between `fitting` and
`investigation`: the missing heat of a fitted model as data, the law it follows
learned from a library of functions, and what it looks like when no law explains it."""

from ._describe import explain
from ._library import LIBRARY, LibraryTerm
from ._missing_heat import MissingHeat, missing_heat, write_missing_heat

__all__ = ["LIBRARY", "LibraryTerm", "explain", "MissingHeat", "missing_heat", "write_missing_heat"]
