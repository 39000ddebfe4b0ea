"""Discovery beyond the vocabulary (docs/formats.md §3a), between `fitting` and
`investigation`: the missing heat of a fitted model as data, the library of learned
laws the loop scores and refits like kinds of the vocabulary, a heat network trained
inside the model and distilled into that library, and a description of the missing
heat no law explains."""

from ._describe import describe, episodes, unexplained
from ._library import LIBRARY, LearnedLaw, LibraryTerm, column_scales, learned_places
from ._missing_heat import MissingHeat, missing_heat, write_missing_heat
from ._network import Distilled, NetworkHeat, NetworkLaw, learn_network_heat

__all__ = ["LIBRARY", "Distilled", "LearnedLaw", "LibraryTerm", "MissingHeat", "NetworkHeat",
           "NetworkLaw", "column_scales", "describe", "episodes", "learn_network_heat",
           "learned_places", "missing_heat", "unexplained", "write_missing_heat"]
