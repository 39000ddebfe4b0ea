"""Discovery beyond the vocabulary (docs/formats.md §3a), between `fitting` and
`investigation`: the missing heat of a fitted model as data, the library of learned
laws the loop scores and refits like kinds of the vocabulary, a heat network trained
inside the model and distilled into that library, a symbolic search over expression
trees for laws the library does not hold, and a description of the missing heat no law
explains."""

from ._describe import describe, episodes, unexplained
from ._library import LIBRARY, LearnedLaw, LibraryTerm, column_scales, learned_places
from ._missing_heat import MissingHeat, missing_heat, write_missing_heat
from ._network import Distilled, NetworkHeat, NetworkLaw, learn_network_heat
from ._symbolic_grammar import PRIMITIVES, Primitive, Variable
from ._symbolic_search import (FoundLaw, SymbolicFront, heat_variables, law_values,
                               learned_law, symbolic_search)

__all__ = ["LIBRARY", "PRIMITIVES", "Distilled", "FoundLaw", "LearnedLaw", "LibraryTerm",
           "MissingHeat", "NetworkHeat", "NetworkLaw", "Primitive", "SymbolicFront",
           "Variable", "column_scales", "describe", "episodes", "heat_variables",
           "law_values", "learn_network_heat", "learned_law", "learned_places",
           "missing_heat", "symbolic_search", "unexplained", "write_missing_heat"]
