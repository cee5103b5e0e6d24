"""Probabilistic roadmap (PRM): nodes, k-NN action slots, symmetrised edges, shortest paths.

Node 0 is the shared start node; nodes 1..n are uniform on [0, 1]^2 (paper Sec. IV-A).
An agent's action picks one of the k nearest neighbours of its node (a "slot"); routing
and planners use the symmetrised k-NN graph and its all-pairs shortest paths, computed
lazily because no step of the environment needs them.
"""

from __future__ import annotations

import torch
from tensordict import tensorclass

from maipp_bench.envs import rng

_TAG_START, _TAG_NODES = 1, 2


@tensorclass
class Roadmap:
    """A batch of roadmaps (leading dim: envs)."""

    nodes: torch.Tensor  # [E, N, 2] float64, node 0 = start
    node_valid: torch.Tensor  # [E, N] bool: False for pruned (removed) nodes
    neighbors: torch.Tensor  # [E, N, k] int64: slot -> node index
    neighbor_dist: torch.Tensor  # [E, N, k] float64 edge lengths
    neighbor_valid: torch.Tensor  # [E, N, k] bool: slot exists

    def adjacency(self) -> torch.Tensor:
        """Symmetrised weighted adjacency ``[E, N, N]`` (inf where no edge; a pruned node
        has none, though its own k-NN slots are kept)."""
        e, n, _ = self.neighbors.shape
        w = torch.full((e, n, n), torch.inf, dtype=self.neighbor_dist.dtype,
                       device=self.nodes.device)
        valid = self.neighbor_valid & self.node_valid.unsqueeze(-1)
        dist = torch.where(valid, self.neighbor_dist, torch.inf)
        w.scatter_reduce_(-1, self.neighbors, dist, reduce="amin")
        w = torch.minimum(w, w.transpose(-1, -2))
        w.diagonal(dim1=-2, dim2=-1).zero_()
        return w

    def shortest_paths(self) -> torch.Tensor:
        """All-pairs shortest path lengths ``[E, N, N]`` (Floyd-Warshall, batched)."""
        d = self.adjacency()
        for k in range(d.shape[-1]):
            torch.minimum(d, d[..., :, k : k + 1] + d[..., k : k + 1, :], out=d)
        return d


def build_roadmap(
    trial_key: torch.Tensor,
    n_nodes: int,
    k: int,
    node_filter=None,
) -> Roadmap:
    """Sample E roadmaps. ``node_filter(nodes [E, N, 2]) -> bool [E, N]`` removes nodes
    (used to prune risky nodes for risk-unaware baselines); the start node always stays."""
    e, device = trial_key.shape[0], trial_key.device
    start = rng.uniform(rng.derive(trial_key, _TAG_START), (1, 2))
    others = rng.uniform(rng.derive(trial_key, _TAG_NODES), (n_nodes, 2))
    nodes = torch.cat([start, others], dim=1)  # [E, N, 2]
    valid = torch.ones(nodes.shape[:2], dtype=torch.bool, device=device)
    if node_filter is not None:
        valid = node_filter(nodes)
        valid[:, 0] = True
    # Rank by cdist (fast, tiny rounding), then measure the chosen edges exactly.
    dist = torch.cdist(nodes, nodes)  # [E, N, N]
    eye = torch.eye(nodes.shape[1], dtype=torch.bool, device=device)
    blocked = eye.unsqueeze(0) | ~valid.unsqueeze(1)
    dist = dist.masked_fill_(blocked, torch.inf)
    rank_dist, nbr = torch.topk(dist, k, dim=-1, largest=False, sorted=True)
    diff = nodes.unsqueeze(2) - nodes.gather(1, nbr.view(e, -1, 1).expand(-1, -1, 2)).view(
        e, -1, k, 2)
    nbr_dist = torch.where(torch.isfinite(rank_dist), torch.sqrt((diff * diff).sum(-1)),
                           torch.inf)
    return Roadmap(
        nodes=nodes, node_valid=valid, neighbors=nbr, neighbor_dist=nbr_dist,
        neighbor_valid=torch.isfinite(nbr_dist), batch_size=[e],
    )


# Entries of an eigenvector this close in magnitude count as tied for its sign (float64
# rounding is ~1e-15; distinct entries of a 200-node roadmap's vectors differ by far more).
SIGN_TIE = 1e-9


def laplacian_encoding(
    neighbors: torch.Tensor, valid: torch.Tensor, dim: int = 32
) -> torch.Tensor:
    """Laplacian positional encoding of roadmaps: ``[E, N, k]`` slots -> ``[E, N, dim]``.

    Eigenvectors of the symmetric normalised Laplacian I - D^-1/2 A D^-1/2 of the
    symmetrised k-NN graph (the reference code built I - D^-1/2 A by mistake), for the
    ``dim`` smallest eigenvalues after the first (constant) one; each vector's sign is
    fixed so that its largest-magnitude entry is positive (eigenvectors have no sign), the
    entry of lowest index among those within ``SIGN_TIE`` of the largest: a symmetric
    roadmap gives entries of equal magnitude and opposite sign, and rounding (which differs
    with the batch, the device) must not choose between them.
    """
    e, n, _ = neighbors.shape
    adj = torch.zeros(e, n, n, dtype=torch.float64, device=neighbors.device)
    adj.scatter_(-1, neighbors, valid.to(torch.float64))
    adj = ((adj + adj.transpose(-1, -2)) > 0).to(torch.float64)
    deg = adj.sum(-1).clamp_min(1.0)
    inv_sqrt = deg.rsqrt()
    lap = torch.eye(n, dtype=torch.float64, device=neighbors.device) - (
        inv_sqrt.unsqueeze(-1) * adj * inv_sqrt.unsqueeze(-2))
    _, vecs = torch.linalg.eigh(lap)
    vecs = vecs[..., 1 : dim + 1]
    if vecs.shape[-1] < dim:
        vecs = torch.nn.functional.pad(vecs, (0, dim - vecs.shape[-1]))
    mag = vecs.abs()
    near = mag >= mag.amax(-2, keepdim=True) - SIGN_TIE
    peak = vecs.gather(-2, near.to(torch.uint8).argmax(-2, keepdim=True))  # first of them
    return vecs * torch.where(peak < 0, -1.0, 1.0)
