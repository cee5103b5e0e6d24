"""Methods: planner baselines and learned policies, registered by name.

Importing this package registers every policy class; ``conf/method/*.yaml`` configures
the methods the evaluation protocol runs (:func:`get_method`).
"""

from maipp_bench.algos import (  # noqa: F401  (registration)
    greedy,
    learned,
    oracle,
    random_policy,
    sga_rrt,
)
from maipp_bench.algos.registry import POLICIES, MethodSpec, get_method, method_names

__all__ = ["POLICIES", "MethodSpec", "get_method", "method_names"]
