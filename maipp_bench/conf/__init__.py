"""Hydra configs of ``python -m maipp_bench.train`` and method YAMLs of the protocol."""
