"""Discovery beyond the vocabulary (docs/formats.md §3a), between `fitting` and
`investigation`: the missing heat of a fitted model as data, the library of learned
laws the loop scores and refits like kinds of the vocabulary, and a description of
the missing heat no law explains."""

from ._describe import describe, unexplained
from ._library import LIBRARY, LearnedLaw, LibraryTerm, learned_places
from ._missing_heat import MissingHeat, missing_heat, write_missing_heat

__all__ = ["LIBRARY", "LearnedLaw", "LibraryTerm", "MissingHeat", "describe",
           "learned_places", "missing_heat", "unexplained", "write_missing_heat"]
