"""maipp_bench: benchmark suite for multi-agent informative path planning."""

__version__ = "0.1.0"
