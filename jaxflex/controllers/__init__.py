"""Controllers: each a pure ``(init, step, check)`` triple over a parameter pytree."""

from jaxflex.controllers.base import Controller, OpenLoopParams, combine, open_loop
from jaxflex.controllers.dfs import DFSParams, dfs
from jaxflex.controllers.fuzzy import FuzzyParams, fuzzy, fuzzy_params
from jaxflex.controllers.pd import PDParams, pd
from jaxflex.controllers.registry import by_name

__all__ = ["Controller", "OpenLoopParams", "combine", "open_loop", "DFSParams", "dfs", "FuzzyParams", "fuzzy", "fuzzy_params", "PDParams", "pd", "by_name"]
