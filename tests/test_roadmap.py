"""The PRM roadmap: k-NN slots, symmetrised edges, all-pairs shortest paths, pruning."""

from __future__ import annotations

import numpy as np
import torch
from scipy.sparse.csgraph import shortest_path

from maipp_bench.envs import rng
from maipp_bench.envs.roadmap import build_roadmap


def _keys(n: int) -> torch.Tensor:
    return rng.derive(rng.seed_key(17), torch.arange(n))


def test_slots_are_the_k_nearest_other_nodes():
    rm = build_roadmap(_keys(2), n_nodes=50, k=8)
    nodes = rm.nodes[0].numpy()
    d = np.linalg.norm(nodes[:, None] - nodes[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    expected = np.sort(d, axis=1)[:, :8]
    assert np.allclose(rm.neighbor_dist[0].numpy(), expected, rtol=0, atol=1e-12)
    assert (rm.neighbors[0].numpy() != np.arange(51)[:, None]).all()  # never itself
    assert rm.neighbor_valid.all()


def test_shortest_paths_match_scipy_on_the_symmetrised_graph():
    rm = build_roadmap(_keys(3), n_nodes=40, k=6)
    adj = rm.adjacency()
    assert torch.equal(adj, adj.transpose(-1, -2))
    apsp = rm.shortest_paths()
    for e in range(3):
        nbr, dist = rm.neighbors[e].numpy(), rm.neighbor_dist[e].numpy()
        w = np.zeros((41, 41))
        for i in range(41):
            w[i, nbr[i]] = dist[i]
        w = np.maximum(w, w.T)  # an edge exists if either end lists the other
        ref = shortest_path(w, method="D", directed=False)
        assert np.allclose(apsp[e].numpy(), ref, rtol=0, atol=1e-9)


def test_pruned_nodes_get_no_edges_and_the_start_stays():
    def drop_left_half(pts: torch.Tensor) -> torch.Tensor:
        return pts[..., 0] > 0.5

    rm = build_roadmap(_keys(2), n_nodes=80, k=6, node_filter=drop_left_half)
    assert rm.node_valid[:, 0].all()
    keep = rm.node_valid
    assert torch.equal(keep[:, 1:], rm.nodes[:, 1:, 0] > 0.5)
    # no slot of any node points at a removed node
    target_ok = keep.gather(1, rm.neighbors.flatten(1)).view_as(rm.neighbors)
    assert (target_ok | ~rm.neighbor_valid).all()
    # ... and routing never passes through one: no edge touches a removed node
    adj, apsp = rm.adjacency(), rm.shortest_paths()
    off_diag = ~torch.eye(81, dtype=torch.bool)
    gone = ~keep
    for d in (adj, apsp):
        assert torch.isinf(d[gone.unsqueeze(-1) & off_diag]).all()
        assert torch.isinf(d.transpose(-1, -2)[gone.unsqueeze(-1) & off_diag]).all()
