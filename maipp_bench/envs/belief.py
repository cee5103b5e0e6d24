"""Exact, incremental Gaussian-process beliefs for a batch of agents.

A belief is the GP posterior (fixed hyperparameters, zero prior mean) given the
measurements ``X, Y`` seen so far, evaluated at a fixed query set (the evaluation grid
and the roadmap nodes). We cache

* ``factor_inv``  L^-1, the inverse of the lower Cholesky factor L of K(X, X) + s^2 I,
* ``cross``   V = L^-1 K(X, Q), the whitened cross-covariances with the query set,
* ``whitened`` z = L^-1 Y (one column per channel: interest signal, risk),
* ``mu`` = V^T z and ``sigma2`` = diag(K(Q,Q)) - colsum(V * V),

so adding a measurement x costs O(n^2 + nQ): b = L^-1 k(X, x), d = sqrt(k(x,x) + s^2 -
|b|^2), and new rows L^-1[n] = [-b^T L^-1 / d, 1 / d], V[n] = (k(x, Q) - b^T V) / d,
z[n] = (y - b^T z) / d; the mean and variance are updated by rank one. P points at once
are the same with d replaced by the Cholesky factor of their P x P Schur complement.
Both channels share X, hence L and V: the interest and risk GPs cost one factorisation.

We keep L^-1 rather than L so that every batched operation is a matrix product: batched
LAPACK calls on many tiny matrices (triangular solves, Cholesky) are slow on CPU and
degrade badly when threads are contended; the P x P blocks are factorised by hand.

Buffers have a fixed capacity (unused rows of L are the identity, of V and z zero), so
every operation is batched over envs and agents with masks, never a Python loop over them.
:meth:`GPBelief.fantasy_variance` answers "what would the posterior variance be if these
hypothetical points were measured" from the same caches, without a refit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import tensorclass

from maipp_bench.envs.kernels import KERNELS, pairwise_distance


@dataclass(frozen=True)
class GPPrior:
    """Fixed GP hyperparameters: kernel name, length scale, prior and noise variances."""

    kernel: str
    length_scale: float
    variance: float
    noise: float

    def cov(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Prior covariance between point sets ``a [..., P, 2]`` and ``b [..., Q, 2]``."""
        return self.variance * KERNELS[self.kernel](pairwise_distance(a, b), self.length_scale)


@tensorclass
class GPBelief:
    """Cached GP posterior for a batch of beliefs; see the module docstring.

    Example:
        >>> prior = GPPrior("matern32", 0.25, 1.0, 1e-4)
        >>> query = torch.rand(4, 50, 2, dtype=torch.float64)
        >>> gp = GPBelief.empty((4,), capacity=8, n_query=50, n_channels=1)
        >>> gp.add(prior, query, torch.rand(4, 1, 2, dtype=torch.float64),
        ...        torch.zeros(4, 1, 1, dtype=torch.float64), torch.ones(4, 1, dtype=torch.bool))
        >>> bool((gp.sigma2 < 1).any())
        True
    """

    points: torch.Tensor  # [*B, n, 2]
    factor_inv: torch.Tensor  # [*B, n, n] L^-1 (identity on unused rows)
    cross: torch.Tensor  # [*B, n, Q]
    whitened: torch.Tensor  # [*B, n, C]
    mu: torch.Tensor  # [*B, Q, C] posterior mean
    sigma2: torch.Tensor  # [*B, Q] posterior variance
    count: torch.Tensor  # [*B] int64

    @classmethod
    def empty(
        cls,
        batch_shape: tuple[int, ...],
        capacity: int,
        n_query: int,
        n_channels: int,
        prior_variance: float = 1.0,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> GPBelief:
        """A batch of prior beliefs (no measurements) with room for ``capacity`` each."""
        b = tuple(batch_shape)
        kw = dict(dtype=dtype, device=device)
        eye = torch.eye(capacity, **kw).expand(*b, capacity, capacity).clone()
        return cls(
            points=torch.zeros(*b, capacity, 2, **kw),
            factor_inv=eye,
            cross=torch.zeros(*b, capacity, n_query, **kw),
            whitened=torch.zeros(*b, capacity, n_channels, **kw),
            mu=torch.zeros(*b, n_query, n_channels, **kw),
            sigma2=torch.full((*b, n_query), float(prior_variance), **kw),
            count=torch.zeros(b, dtype=torch.int64, device=device),
            batch_size=list(b),
        )

    @property
    def capacity(self) -> int:
        return self.factor_inv.shape[-1]

    def grown(self, extra: int, dtype: torch.dtype | None = None) -> GPBelief:
        """A copy with room for ``extra`` more measurements (e.g. teammates' planned ones),
        optionally in another float dtype (planners score candidates in float32)."""
        cap = self.capacity
        dtype = dtype or self.factor_inv.dtype

        def pad(x: torch.Tensor, widths: tuple[int, ...]) -> torch.Tensor:
            return torch.nn.functional.pad(x.to(dtype), widths)

        inv = pad(self.factor_inv, (0, extra, 0, extra))
        idx = torch.arange(cap, cap + extra, device=inv.device)
        inv[..., idx, idx] = 1.0
        return GPBelief(
            points=pad(self.points, (0, 0, 0, extra)), factor_inv=inv,
            cross=pad(self.cross, (0, 0, 0, extra)), whitened=pad(self.whitened, (0, 0, 0, extra)),
            mu=self.mu.to(dtype, copy=True), sigma2=self.sigma2.to(dtype, copy=True),
            count=self.count.clone(), batch_size=self.batch_size,
        )

    def gathered(self, index: tuple[torch.Tensor, ...], extra: int,
                 dtype: torch.dtype | None = None, repeats: int = 1) -> GPBelief:
        """The beliefs at batch ``index`` (advanced indices, one per batch dim) as a flat
        batch, each repeated ``repeats`` times (row ``b * repeats + r`` copies belief b), in
        ``dtype``, with room for ``extra`` more measurements: what ``self[index]`` then
        :meth:`grown` give, at a fraction of the copying. Only the used slots are copied
        (capacity = max count + extra) and each belief once before the repeat; :meth:`add`
        reads the used prefix only, so its results are the same bits as on the full copy."""
        count = self.count[index]
        h = int(count.max()) if count.numel() else 0
        used = GPBelief(
            points=self.points[..., :h, :][index], factor_inv=self.factor_inv[..., :h, :h][index],
            cross=self.cross[..., :h, :][index], whitened=self.whitened[..., :h, :][index],
            mu=self.mu[index], sigma2=self.sigma2[index], count=count,
            batch_size=[count.numel()],
        ).grown(extra, dtype)
        if repeats == 1:
            return used
        return used[torch.arange(count.numel(), device=count.device).repeat_interleave(repeats)]

    # ------------------------------------------------------------------ updates
    def add(
        self,
        prior: GPPrior,
        query: torch.Tensor,
        x: torch.Tensor,
        y: torch.Tensor,
        mask: torch.Tensor,
    ) -> None:
        """Add up to P measurements per belief, in place (a rank-P Cholesky extension).

        Equivalent to adding the selected points one by one in order, at the same
        O(P n^2 + P n Q) cost, but in one batched call.

        Args:
            prior: the fixed hyperparameters.
            query: query points broadcastable to ``[*B, Q, 2]``.
            x: measurement locations ``[*B, P, 2]``.
            y: measured values ``[*B, P, C]``.
            mask: bool ``[*B, P]``: which points each belief takes.
        """
        cap, nq, nc = self.capacity, self.sigma2.shape[-1], self.whitened.shape[-1]
        p = x.shape[-2]
        if p == 0:
            return
        flat = mask.reshape(-1, p)
        sel = flat.any(-1)
        n_sel = int(sel.sum())
        if n_sel == 0:
            return
        # Few beliefs take points: gather them. Most do: update all in place (the others
        # get all-padding blocks, hence exact zero updates) rather than copy V.
        dense = 2 * n_sel >= sel.numel()
        idx = sel.nonzero().squeeze(-1)

        def rows(t: torch.Tensor, tag: str, h: int | None = None,
                 square: bool = False) -> torch.Tensor:
            """Per-belief rows of ``t [*B, ...]`` (first ``h`` slots): a view when dense, else
            a gather of the selected beliefs (slicing first, so only the prefix is copied)
            into a reused buffer."""
            flat_t = t.reshape(-1, *t.shape[len(bshape):])
            if h is not None:
                flat_t = flat_t[:, :h, :h] if square else flat_t[:, :h]
            if dense:
                return flat_t
            out = _scratch(tag, (len(idx), *flat_t.shape[1:]), t.dtype, t.device)
            return torch.index_select(flat_t, 0, idx, out=out)

        bshape = tuple(self.batch_size)
        dtype, dev = self.factor_inv.dtype, self.factor_inv.device
        fm = rows(mask, "mask")
        n = rows(self.count, "count")
        n_new = fm.sum(-1)
        if bool((n + n_new > cap).any()):
            raise RuntimeError(f"GPBelief capacity ({cap}) exceeded")
        # Move each belief's selected points to the front, keeping their order.
        order = torch.argsort((~fm).to(torch.int8), dim=-1, stable=True)
        fm = fm.gather(-1, order)
        xs = rows(x, "x").gather(-2, order.unsqueeze(-1).expand(-1, -1, 2)).to(dtype)
        ys = rows(y, "y").gather(-2, order.unsqueeze(-1).expand(-1, -1, nc)).to(dtype)
        # Work on the used prefix only: rows >= h are identity/zero in every selected belief.
        h = int(n.max())
        w_new = min(cap, h + p)  # columns the new rows of L^-1 can touch
        Li = rows(self.factor_inv, "factor_inv", h, square=True)
        X = rows(self.points, "points", h)
        Z = rows(self.whitened, "whitened", h)
        # Query points per belief without materialising the broadcast over beliefs.
        qb = query.to(dtype).expand(*bshape, nq, 2)
        q = qb.reshape(-1, nq, 2) if qb.is_contiguous() else None
        if q is None:
            sub = torch.arange(len(idx) if not dense else math.prod(bshape), device=dev)
            sub = sub if dense else idx
            q = qb[torch.unravel_index(sub, bshape)]
        elif not dense:
            q = q[idx]
        used = torch.arange(h, device=dev) < n.unsqueeze(-1)  # [S, h]

        kxf = prior.cov(X, xs) * (used.unsqueeze(-1) & fm.unsqueeze(-2))  # [S, h, P]
        bm = Li @ kxf  # B = L^-1 K(X, F)
        bmt = bm.transpose(-1, -2)  # [S, P, h]
        eye = torch.eye(p, dtype=dtype, device=dev)
        s = prior.cov(xs, xs) + prior.noise * eye - bmt @ bm
        s = torch.where(fm.unsqueeze(-1) & fm.unsqueeze(-2), s, eye)  # padding: identity
        ls_inv = cholesky_inverse_small(s)  # [S, P, P]
        flat_v = self.cross.view(-1, cap, nq)
        if dense:
            bv = bmt @ flat_v[:, :h]
        elif flat_v.is_cuda:  # one gather + bmm: a per-block loop would be launch bound
            bv = bmt @ torch.index_select(flat_v[:, :h], 0, idx)
        else:
            bv = _gathered_product(bmt, flat_v, idx, n)
        w = prior.cov(xs, q).sub_(bv).mul_(fm.unsqueeze(-1))  # [S, P, Q]
        v_new = ls_inv @ w
        z_new = ls_inv @ ((ys - bmt @ Z) * fm.unsqueeze(-1))

        # New rows n+i of L^-1: [-Ls^-1 B^T L^-1 (old columns), Ls^-1 (columns n..n+P-1)].
        old = torch.nn.functional.pad(-(ls_inv @ (bmt @ Li)), (0, w_new - h))  # 0 at cols >= n
        j = (torch.arange(w_new, device=dev).view(1, 1, -1) - n.view(-1, 1, 1)).expand(-1, p, -1)
        new_rows = torch.where((j >= 0) & (j < p), ls_inv.gather(-1, j.clamp(0, p - 1)), old)
        bi, pi = fm.nonzero(as_tuple=True)
        target, dst = n[bi] + pi, (bi if dense else idx[bi])
        self.factor_inv.view(-1, cap, cap)[dst, target, :w_new] = new_rows[bi, pi]
        self.points.view(-1, cap, 2)[dst, target] = xs[bi, pi]
        self.cross.view(-1, cap, nq)[dst, target] = v_new[bi, pi]
        self.whitened.view(-1, cap, nc)[dst, target] = z_new[bi, pi]
        d_mu, d_var = v_new.transpose(-1, -2) @ z_new, (v_new * v_new).sum(-2)
        if dense:
            self.mu.view(-1, nq, nc).add_(d_mu)
            self.sigma2.view(-1, nq).sub_(d_var)
        else:
            self.mu.view(-1, nq, nc).index_add_(0, idx, d_mu)  # idx unique: x[idx] += d
            self.sigma2.view(-1, nq).index_add_(0, idx, d_var, alpha=-1)
        if dense:
            self.count.view(-1).add_(n_new)
        else:
            self.count.view(-1)[idx] += n_new

    # ------------------------------------------------------------------ queries
    def fantasy_variance(
        self,
        prior: GPPrior,
        query: torch.Tensor,
        points: torch.Tensor,
        mask: torch.Tensor | None = None,
        n_query: int | None = None,
    ) -> torch.Tensor:
        """Posterior variance after hypothetically measuring ``points``, without a refit.

        The variance of a GP does not depend on measured values, so this is exact.

        Args:
            prior: the fixed hyperparameters.
            query: query points broadcastable to ``[*B, Q, 2]``.
            points: hypothetical measurement sets ``[*B, C, P, 2]`` (C candidates each).
            mask: bool ``[*B, C, P]``: which points of each set are real (padding: False).
            n_query: use only the first ``n_query`` query points (e.g. the grid).

        Returns:
            variance ``[*B, C, Qs]`` with ``Qs = n_query or Q``.
        """
        return self._fantasy(prior, query, points, mask, n_query, None)[1]

    def fantasy_posterior(
        self,
        prior: GPPrior,
        query: torch.Tensor,
        points: torch.Tensor,
        values: torch.Tensor,
        mask: torch.Tensor | None = None,
        n_query: int | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior interest mean and variance after measuring ``values [*B, C, P]``
        (channel 0) at ``points``; see :meth:`fantasy_variance` for the other arguments.

        Returns ``(mean [*B, C, Qs], variance [*B, C, Qs])``.
        """
        return self._fantasy(prior, query, points, mask, n_query, values)

    def fantasy_trace(
        self,
        prior: GPPrior,
        query: torch.Tensor,
        points: torch.Tensor,
        mask: torch.Tensor | None,
        mean: torch.Tensor,
        beta: float,
        threshold: float,
        n_grid: int,
    ) -> torch.Tensor:
        """Tr(P) over X_I after hypothetically measuring ``points`` ``[*B, C, P, 2]``, with
        the interest ``mean [*B, G2]`` held fixed (an expected-value fantasy).

        Exact and cheaper than :meth:`fantasy_variance` on the whole grid: variances only
        shrink, so with the mean fixed a cell outside X_I now stays outside, and only the
        cells in X_I now are evaluated. Returns ``[*B, C]``.
        """
        var_now = self.sigma2[..., :n_grid]
        inside = mean + beta * torch.sqrt(var_now.clamp_min(0)) >= threshold
        k = max(int(inside.sum(-1).max()), 1)
        cells = torch.argsort((~inside).to(torch.int8), dim=-1, stable=True)[..., :k]
        valid = inside.gather(-1, cells)
        var = self._fantasy(prior, query, points, mask, None, None, cells)[1]
        mu = mean.gather(-1, cells).unsqueeze(-2)
        return interest_trace(mu, torch.where(valid.unsqueeze(-2), var, 0.0), beta, threshold)

    def _fantasy(self, prior, query, points, mask, n_query, values, cells=None):
        """Shared body; ``cells [*B, Qc]`` (optional) evaluates only those query points."""
        cap, nq = self.capacity, self.sigma2.shape[-1]
        qs = nq if n_query is None else n_query
        if cells is not None:
            qs = cells.shape[-1]
        dtype = self.factor_inv.dtype
        *cand_shape, p, _ = points.shape
        sig_now, mu_now = self.sigma2[..., :qs], self.mu[..., :qs, 0]
        if cells is not None:
            sig_now, mu_now = self.sigma2.gather(-1, cells), self.mu[..., 0].gather(-1, cells)
        if p == 0:
            var = sig_now.unsqueeze(-2).expand(*cand_shape, qs).clone()
            return mu_now.unsqueeze(-2).expand(*cand_shape, qs).clone(), var
        if mask is None:
            mask = torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
        c = cand_shape[-1]
        bshape = tuple(self.batch_size)
        # Fold the candidates into the columns so V and L^-1 are never broadcast (copied).
        pts = points.to(dtype).reshape(-1, c * p, 2)
        msk = mask.reshape(-1, c * p)
        h = max(int(self.count.max()), 1)  # rows >= h are unused in every belief
        li = self.factor_inv.reshape(-1, cap, cap)[:, :h, :h]
        used = torch.arange(h, device=msk.device) < self.count.reshape(-1, 1)
        kxf = prior.cov(self.points.reshape(-1, cap, 2)[:, :h], pts)
        kxf = kxf * (used.unsqueeze(-1) & msk.unsqueeze(-2))  # [B, h, C*P]
        bm = li @ kxf
        bmt = bm.transpose(-1, -2)  # [B, C*P, h]
        b4 = bmt.reshape(-1, c, p, h)
        p4 = pts.reshape(-1, c, p, 2)
        m4 = msk.reshape(-1, c, p)
        eye = torch.eye(p, dtype=dtype, device=pts.device)
        sch = prior.cov(p4, p4) + prior.noise * eye - b4 @ b4.transpose(-1, -2)
        sch = torch.where(m4.unsqueeze(-1) & m4.unsqueeze(-2), sch, eye)
        ls_inv = cholesky_inverse_small(sch)  # [B, C, P, P]
        if cells is None:
            q = query[..., :qs, :].to(dtype).expand(*bshape, qs, 2).reshape(-1, qs, 2)
            v = self.cross.reshape(-1, cap, nq)[:, :h, :qs]
        else:
            flat_cells = cells.reshape(-1, qs)
            q = query.to(dtype).expand(*bshape, nq, 2).reshape(-1, nq, 2).gather(
                1, flat_cells.unsqueeze(-1).expand(-1, -1, 2))
            v = self.cross.reshape(-1, cap, nq)[:, :h].gather(
                2, flat_cells.unsqueeze(1).expand(-1, h, -1))
        w = (prior.cov(pts, q) - bmt @ v) * msk.unsqueeze(-1)  # [B, C*P, Qs]
        u = ls_inv @ w.reshape(-1, c, p, qs)
        var = (sig_now.reshape(-1, qs)[:, None] - (u * u).sum(-2)).reshape(*cand_shape, qs)
        if values is None:
            return None, var
        # Innovation y_f - mu(X_f), whitened by the Schur factor, then mapped to the grid.
        z = self.whitened.reshape(-1, cap, self.whitened.shape[-1])[:, :h, :1]
        innov = (values.to(dtype).reshape(-1, c * p, 1) - bmt @ z).reshape(-1, c, p, 1) * m4[
            ..., None]
        mean = mu_now.reshape(-1, qs)[:, None] + ((ls_inv @ innov) * u).sum(-2)
        return mean.reshape(*cand_shape, qs), var


_SCRATCH: dict[tuple, torch.Tensor] = {}
_CHUNK = 8  # beliefs per block of _gathered_product: a few MB, reread from cache by bmm


def _gathered_product(left: torch.Tensor, table: torch.Tensor, idx: torch.Tensor,
                      count: torch.Tensor) -> torch.Tensor:
    """``left [S, P, h] @ table[idx, :h]`` (``table [B, cap, Q]``), streaming from ``table``
    only the ``count [S]`` used rows of each selected matrix.

    Streaming V is the O(nQ) cost of :meth:`GPBelief.add`, and the selected beliefs hold
    far fewer rows than the largest (at E = 1024, 18 against 41 on average:
    ``benchmarks/env_profile.py``).
    Each block of beliefs is gathered into a reused buffer of a few MB and multiplied
    there; an unused slot reads its belief's last row instead, which is zero like every
    unused row (a slot >= count exists only if count < cap), and is read once, then hit in
    cache. Each matrix of the batch gets the operands and the shape it gets from gathering
    ``table[idx, :h]`` and one ``bmm`` (on CPU, bmm computes the items one by one): the
    same bits. CPU only (a per-block loop would be launch bound on a GPU).
    """
    s, p, h = left.shape
    cap, nq = table.shape[-2:]
    slot = torch.arange(h, device=count.device)
    src = idx.unsqueeze(-1) * cap + torch.where(slot < count.unsqueeze(-1), slot, cap - 1)
    rows = table.reshape(-1, nq)
    out = torch.empty(s, p, nq, dtype=left.dtype, device=left.device)
    block = _scratch("block", (_CHUNK * h, nq), table.dtype, table.device)
    for c0 in range(0, s, _CHUNK):
        c = min(_CHUNK, s - c0)
        blk = torch.index_select(rows, 0, src[c0:c0 + c].reshape(-1), out=block[: c * h])
        torch.bmm(left[c0:c0 + c], blk.view(c, h, nq), out=out[c0:c0 + c])
    return out


def _scratch(tag: str, shape: tuple[int, ...], dtype: torch.dtype,
             device: torch.device) -> torch.Tensor:
    """A grow-only buffer of ``shape`` for ``tag``, reused across calls.

    :meth:`GPBelief.add` gathers the selected beliefs' rows on every call; a fresh tensor
    above 32 MB is mmapped and page-faulted on every call (glibc serves such blocks from
    mmap): when V was gathered whole, 65 ms against 18 ms per gather + product at
    E = 1024 (``benchmarks/env_profile.py``).
    Contents are overwritten by the next call with the same tag: callers use them locally.
    Buffers made under ``torch.inference_mode`` (evaluation) cannot be written outside it
    (training in the same process), so each mode keeps its own.
    """
    key = (tag, dtype, device, torch.is_inference_mode_enabled())
    need = math.prod(shape)
    buf = _SCRATCH.get(key)
    if buf is None or buf.numel() < need:
        buf = torch.empty(need, dtype=dtype, device=device)
        _SCRATCH[key] = buf
    return buf[:need].view(shape)


def cholesky_inverse_small(s: torch.Tensor) -> torch.Tensor:
    """Inverse of the lower Cholesky factor of small SPD matrices ``s [..., P, P]``.

    Written as P column steps of batched products (P is the number of points added at
    once, a handful), which is much faster than batched LAPACK on many tiny matrices.
    """
    p = s.shape[-1]
    tiny = torch.finfo(s.dtype).tiny
    lo = torch.zeros_like(s)
    for j in range(p):
        row = lo[..., j, :j]
        d = torch.sqrt(torch.clamp(s[..., j, j] - (row * row).sum(-1), min=tiny))
        lo[..., j, j] = d
        if j + 1 < p:
            below = s[..., j + 1 :, j] - (lo[..., j + 1 :, :j] @ row.unsqueeze(-1)).squeeze(-1)
            lo[..., j + 1 :, j] = below / d.unsqueeze(-1)
    inv = torch.zeros_like(s)
    for i in range(p):
        diag = 1.0 / lo[..., i, i]
        inv[..., i, i] = diag
        if i:
            acc = (lo[..., i, :i].unsqueeze(-2) @ inv[..., :i, :i]).squeeze(-2)
            inv[..., i, :i] = -acc * diag.unsqueeze(-1)
    return inv


def interest_trace(
    mean: torch.Tensor,
    var: torch.Tensor,
    beta: float,
    threshold: float,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """Tr(P) over the high-interest region X_I = {mu + beta sigma >= mu_th} (paper Eq. 4).

    ``mean`` and ``var`` broadcast over ``[..., G]`` grid cells; ``weight`` (optional,
    the AOI weighting of the dual-domain objective) multiplies each cell's variance.
    """
    var = var.clamp_min(0.0)
    region = mean + beta * torch.sqrt(var) >= threshold
    terms = torch.where(region, var, torch.zeros_like(var))
    if weight is not None:
        terms = terms * weight
    return terms.sum(-1)
