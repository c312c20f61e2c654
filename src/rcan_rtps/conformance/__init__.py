"""`rcan-rtps conformance`: the published RCAN conformance suite (vendored with its source)
run against a bridge's API, one line per case."""

from .bridge import ConformanceError, MissingToken, ProbeError
from .runner import Result, run_suite
from .suite import LEVELS, Case, Level, Suite, load_suite

__all__ = ["LEVELS", "Case", "ConformanceError", "Level", "MissingToken", "ProbeError", "Result",
           "Suite", "load_suite", "run_suite"]
