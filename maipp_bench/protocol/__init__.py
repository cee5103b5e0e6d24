"""The evaluation protocol: versioned suites and seeds, episode runner, results, leaderboards."""

from maipp_bench.protocol.protocol import Protocol, Setting, Suite, load_protocol, paper_results

__all__ = ["Protocol", "Setting", "Suite", "load_protocol", "paper_results"]
