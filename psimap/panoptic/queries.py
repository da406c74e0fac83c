"""Instance queries: a feature plus a 3D Gaussian each, and the query-to-surfel affinity (paper §4.1).

A(q, g) = sigmoid(f_q . f_g) * phi_q(p_g) / phi_q(mu_q): the density ratio is the Gaussian's
exp(-mahalanobis^2 / 2), 1 at the query's centre. The per-surfel instance distribution is a softmax
over queries; because A lies in [0, 1], a plain softmax would be almost uniform for tens of queries,
so the logits are A / temperature (temperature well below 1).
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn

from psimap.panoptic.config import PanopticConfig


def positional_encoding(x: torch.Tensor, n_freqs: int, scale: float) -> torch.Tensor:
    """psi(mu): sin/cos encoding of positions x [N, 3] (metres) -> [N, 6 * n_freqs].

    `scale` is the scene extent: the lowest frequency spans it once.
    """
    freqs = (2.0 ** torch.arange(n_freqs, device=x.device, dtype=x.dtype)) * (math.pi / max(scale, 1e-6))
    ang = x.unsqueeze(-1) * freqs                                   # [N, 3, n_freqs]
    return torch.cat([ang.sin(), ang.cos()], dim=-1).flatten(1)


# torch's CPU softmax over a last dim shorter than this takes a scalar path (80k x 11: 10 ms
# forward); over dim 0 of the transposed view it runs across rows on the vector lanes (3-7x faster,
# forward and backward; the same max-subtracted algorithm)
SMALL_SOFTMAX_DIM = 16
# Squared Mahalanobis distances are capped here in the affinity: exp(-80) is still a normal float32
MAX_MAHALANOBIS2 = 160.0


def softmax_last(x: torch.Tensor, log: bool = False) -> torch.Tensor:
    """(log-)softmax of x [R, C] over its last dim, fast for a few columns (classes, queries)."""
    fn = torch.log_softmax if log else torch.softmax
    if x.dim() == 2 and x.shape[-1] < SMALL_SOFTMAX_DIM:
        return fn(x.T, 0).T
    return fn(x, -1)


def _native_field(t: torch.Tensor) -> bool:
    """Whether the native field kernels can take t: float32 on the CPU, the module built."""
    if t.device.type != "cpu" or t.dtype != torch.float32:
        return False
    from psimap.render.api import native_available

    return native_available()


def instance_distribution_reference(dot: torch.Tensor, m2: torch.Tensor, p_thing: torch.Tensor | None,
                                    temperature: float) -> torch.Tensor:
    """softmax_q(A / temperature) * p_thing [V, Q], A = sigmoid(dot) exp(-min(m2, MAX_MAHALANOBIS2) / 2)
    (InstanceQueries.affinity) from dot [V, Q] (surfel . query features), m2 [V, Q] float64 (squared
    Mahalanobis distances, rounded to dot's dtype) and p_thing [V] (None: 1). The readable torch form
    of the native kernel psimap.render.native.instance_distribution, which the tests hold to it."""
    a = torch.sigmoid(dot) * torch.exp(-0.5 * m2.to(dot.dtype).clamp_max(MAX_MAHALANOBIS2))
    out = softmax_last(a / temperature)
    return out if p_thing is None else out * p_thing.unsqueeze(-1)


def instance_distribution(dot: torch.Tensor, terms: torch.Tensor, coef: torch.Tensor, p_thing: torch.Tensor | None,
                          temperature: float, backend: str = "auto") -> torch.Tensor:
    """instance_distribution_reference's value with m2 = terms @ coef.T (the surfels' quadratic
    monomials [V, K] and the queries' coefficients [Q, K], float64: InstanceQueries.mahalanobis_terms):
    the native fused kernel for float32 CPU tensors where it is built (backend "auto" or "native";
    "native" raises where it cannot run), else the torch form. The kernel sums each row's distances
    on its lanes: the [V, Q] float64 distances and their gradient are never built (at 93 queries
    and a room view's 17k surfels, the two float64 products and those 12 MB tensors took ~10 ms of a
    step). In torch the chain is ~9 passes over [V, Q] forward and ~13 backward."""
    native = backend in ("auto", "native") and _native_field(dot)
    if backend == "native" and not native:
        raise ValueError("instance_distribution: the native kernel needs float32 CPU tensors and the built module")
    if not native:
        return instance_distribution_reference(dot, terms.to(torch.float64) @ coef.to(torch.float64).T, p_thing,
                                               temperature)
    from psimap.render.native import instance_distribution as fused

    return fused(dot, terms.to(torch.float64), coef.to(torch.float64), p_thing, temperature)


class InstanceQueries(nn.Module):
    """Q instance queries: feature [Q, F], mean [Q, 3], covariance [Q, 3, 3] = L L^T + eps I.

    Covariances are parametrised by a lower-triangular L with a log-diagonal so they stay positive
    definite under gradient steps.
    """

    def __init__(self, feature: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor, *,
                 temperature: float = PanopticConfig.temperature, n_freqs: int = 4, scene_scale: float = 1.0,
                 attn_dim: int | None = None, generator: torch.Generator | None = None):
        super().__init__()
        q, f = feature.shape
        self.feature = nn.Parameter(feature.clone().float())
        self.mean = nn.Parameter(mean.clone().float())
        L = torch.linalg.cholesky(_regularise(cov.double())).float() if q else torch.zeros(0, 3, 3)
        diag = torch.diagonal(L, dim1=-2, dim2=-1).clamp_min(1e-6)
        self.log_diag = nn.Parameter(diag.log())
        self.offdiag = nn.Parameter(L[:, [1, 2, 2], [0, 0, 1]].clone())
        self.temperature = temperature
        self.scene_scale = float(scene_scale)
        self.n_freqs = n_freqs
        d = attn_dim or f
        # Frustum cross-attention projections (keys carry position through psi, values do not).
        # Initialised from `generator`, never from torch's global RNG: the global stream's state
        # depends on whatever ran before in the process, so the same seed gave different fits
        # (seed 1 at 15 % noise: PQ 0.861 after the 0 % run, 0.872 alone).
        self.pos_proj = nn.utils.skip_init(nn.Linear, 6 * n_freqs, f, bias=False)
        self.w_q = nn.utils.skip_init(nn.Linear, f, d, bias=False)
        self.w_k = nn.utils.skip_init(nn.Linear, f, d, bias=False)
        self.w_v = nn.utils.skip_init(nn.Linear, f, f, bias=False)
        with torch.no_grad():
            for lin in (self.w_q, self.w_k, self.w_v):
                out_f, in_f = lin.weight.shape
                if out_f == in_f:
                    lin.weight.copy_(torch.eye(in_f))  # identity start: attention compares raw features
                else:
                    lin.weight.copy_(torch.randn(out_f, in_f, generator=generator) / math.sqrt(in_f))
            self.pos_proj.weight.copy_(0.02 * torch.randn(self.pos_proj.weight.shape, generator=generator))
        # The attention update enters as a gated residual: start at 0 so early training is stable.
        self.gate = nn.Parameter(torch.zeros(()))

    @property
    def count(self) -> int:
        return int(self.feature.shape[0])

    def chol(self) -> torch.Tensor:
        """L [Q, 3, 3] lower triangular with positive diagonal."""
        q = self.count
        L = torch.zeros(q, 3, 3, dtype=self.feature.dtype, device=self.feature.device)
        idx = torch.arange(3, device=L.device)
        L[:, idx, idx] = self.log_diag.exp()
        L[:, [1, 2, 2], [0, 0, 1]] = self.offdiag
        return L

    def cov(self) -> torch.Tensor:
        L = self.chol()
        return L @ L.transpose(-1, -2)

    def mahalanobis2_reference(self, points: torch.Tensor) -> torch.Tensor:
        """Squared Mahalanobis distance of points [N, 3] to every query: [N, Q] (readable form of
        `mahalanobis2`, which the tests hold to it)."""
        L = self.chol()                                              # [Q, 3, 3]
        eye = torch.eye(3, dtype=L.dtype, device=L.device).expand_as(L)
        Linv = torch.linalg.solve_triangular(L, eye, upper=False)   # [Q, 3, 3]
        d = points.unsqueeze(1) - self.mean.unsqueeze(0)             # [N, Q, 3]
        y = torch.einsum("qij,nqj->nqi", Linv, d)                    # |y|^2 = d^T Sigma^-1 d
        return (y * y).sum(-1)

    def mahalanobis_terms(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(terms [N, 10], coef [Q, 10]), float64, with terms @ coef.T the squared Mahalanobis distance
        of points [N, 3] to every query: d^T P d = x^T P x - 2 x^T P mu + mu^T P mu (P = Sigma^-1),
        the points' quadratic monomials times the queries' coefficients (differentiable in the
        queries; the points are constants). In float64 around the points' centre: the expanded terms
        cancel (a point 5 m from a 1 cm query: 2.5e5 - 2.5e5), which float32 would leave ~0.03 off."""
        L = self.chol().double()                                     # [Q, 3, 3]
        eye = torch.eye(3, dtype=L.dtype, device=L.device).expand_as(L)
        Linv = torch.linalg.solve_triangular(L, eye, upper=False)
        prec = Linv.transpose(-1, -2) @ Linv                         # [Q, 3, 3]
        x = points.detach().double()
        centre = x.mean(0) if x.shape[0] else x.new_zeros(3)
        x = x - centre
        mu = self.mean.double() - centre                             # [Q, 3]
        p_mu = (prec @ mu.unsqueeze(-1)).squeeze(-1)                 # [Q, 3]
        # column gathers by index_select (a list index took ~0.4 ms each on a room view's 17k points)
        i, j = torch.tensor([0, 1, 2, 0, 0, 1]), torch.tensor([0, 1, 2, 1, 2, 2])
        terms = torch.cat([x.index_select(1, i) * x.index_select(1, j) * torch.tensor([1.0, 1, 1, 2, 2, 2], dtype=x.dtype),
                           -2.0 * x, torch.ones_like(x[:, :1])], dim=1)                     # [N, 10]
        coef = torch.cat([prec[:, i, j], p_mu, (mu * p_mu).sum(-1, keepdim=True)], dim=1)  # [Q, 10]
        return terms, coef

    def mahalanobis2(self, points: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
        """Squared Mahalanobis distance of points [N, 3] to every query: [N, Q] in `dtype` (None: the
        points' dtype; float64 is the product's own, no cast), as one matrix product of
        `mahalanobis_terms`. The per-query [N, 3] x [3, 3] products of the readable form were a
        batched matmul of Q tiny matrices (~40 % of a panoptic step's affinity)."""
        terms, coef = self.mahalanobis_terms(points)
        return (terms @ coef.T).to(dtype or points.dtype)   # may dip ~1e-12 below 0 by rounding: harmless

    def position_codes(self, points: torch.Tensor) -> torch.Tensor:
        """psi of points [N, 3]: [N, 6 * n_freqs], what `attend` adds to the keys (through pos_proj)."""
        return positional_encoding(points, self.n_freqs, self.scene_scale)

    def attend(self, surfel_feat: torch.Tensor, surfel_pos: torch.Tensor,
               pos_codes: torch.Tensor | None = None) -> torch.Tensor:
        """Frustum-constrained cross-attention: updated query features [Q, F].

        surfel_feat [V, F], surfel_pos [V, 3]: only the surfels visible in the current view, so the
        attention matrix is [Q, V] and memory follows what is visible, not the scene size.
        pos_codes [V, 6 * n_freqs]: `position_codes(surfel_pos)` when the caller keeps them (fixed
        surfels: the sines and cosines were ~1.5-3.5 ms of a room step).
        """
        if surfel_feat.shape[0] == 0 or self.count == 0:
            return self.feature
        if pos_codes is None:
            pos_codes = self.position_codes(surfel_pos)
        keys = surfel_feat + self.pos_proj(pos_codes)
        # (W_q f_q) . (W_k k) = (W_k^T W_q f_q) . k and sum_v a_v W_v f_v = W_v sum_v a_v f_v: the
        # projections act on the Q queries, not on the V surfels (two [V, F] x [F, F] products and
        # their four backward ones fewer a step; the same function up to float rounding)
        q_keys = self.w_q(self.feature) @ self.w_k.weight                              # [Q, F]
        qk = q_keys @ keys.T / math.sqrt(self.w_q.out_features)                          # [Q, V]
        upd = self.w_v(torch.softmax(qk, dim=-1) @ surfel_feat)                         # [Q, F]
        return self.feature + torch.tanh(self.gate) * upd

    def affinity_reference(self, surfel_feat: torch.Tensor, surfel_pos: torch.Tensor,
                           query_feat: torch.Tensor | None = None) -> torch.Tensor:
        """A(q, g) = sigmoid(f_q . f_g) * exp(-m^2/2): [N, Q] in [0, 1]. m^2 is capped at
        MAX_MAHALANOBIS2: beyond, exp(-m^2/2) falls below float32's normal range, and exponentials
        and products that give subnormal floats take a slow path on x86 (the demo's first steps, 85
        queries: 7 ms an exp of [12.8k, 85], 0.8 ms capped). The capped affinity, < 2e-35, is nothing
        next to a query within reach, as the uncapped one was. The readable torch form of
        `affinity`, differentiable."""
        fq = self.feature if query_feat is None else query_feat
        sim = torch.sigmoid(surfel_feat @ fq.T)
        return sim * torch.exp(-0.5 * self.mahalanobis2(surfel_pos).clamp_max(MAX_MAHALANOBIS2))

    def affinity(self, surfel_feat: torch.Tensor, surfel_pos: torch.Tensor,
                 query_feat: torch.Tensor | None = None) -> torch.Tensor:
        """A(q, g) [N, Q] without gradient (the scene-wide labels, adjustments and export read it):
        the native kernel for float32 CPU features where it is built (the distances summed on its
        lanes from `mahalanobis_terms`: 65k surfels x 93 queries ~130 ms in torch), else
        `affinity_reference`."""
        with torch.no_grad():
            fq = (self.feature if query_feat is None else query_feat).detach()
            feat = surfel_feat.detach()
            if not (_native_field(feat) and fq.dtype == torch.float32):
                return self.affinity_reference(feat, surfel_pos, fq)
            from psimap.render.native import instance_affinity

            terms, coef = self.mahalanobis_terms(surfel_pos)
            return instance_affinity(feat @ fq.T, terms, coef)

    def distribution(self, surfel_feat: torch.Tensor, surfel_pos: torch.Tensor,
                     query_feat: torch.Tensor | None = None, p_thing: torch.Tensor | None = None,
                     backend: str = "auto") -> torch.Tensor:
        """Per-surfel instance distribution l_ins(g) = softmax_q(A(q, g) / T) [N, Q], times p_thing [N]
        (each surfel's probability of a thing class) when given: `instance_distribution`."""
        if self.count == 0:
            return surfel_feat.new_zeros(surfel_feat.shape[0], 0)
        fq = self.feature if query_feat is None else query_feat
        terms, coef = self.mahalanobis_terms(surfel_pos)
        return instance_distribution(surfel_feat @ fq.T, terms, coef, p_thing, self.temperature, backend)

    def add(self, feature: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Append queries (feature [A, F], mean [A, 3], cov [A, 3, 3]). Re-creates parameters."""
        L = torch.linalg.cholesky(_regularise(cov.double())).float()
        diag = torch.diagonal(L, dim1=-2, dim2=-1).clamp_min(1e-6)
        new = {"feature": feature.float(), "mean": mean.float(), "log_diag": diag.log(),
               "offdiag": L[:, [1, 2, 2], [0, 0, 1]]}
        for name, rows in new.items():
            old = getattr(self, name)
            setattr(self, name, nn.Parameter(torch.cat([old.detach(), rows.to(old)]).clone()))

    def keep(self, mask: torch.Tensor) -> None:
        """Drop queries where mask [Q] is False (dynamic query adjustment). Re-creates parameters."""
        for name in ("feature", "mean", "log_diag", "offdiag"):
            old = getattr(self, name)
            setattr(self, name, nn.Parameter(old.detach()[mask].clone()))


def _regularise(cov: torch.Tensor, rel: float = 1e-4, floor: float = 1e-6) -> torch.Tensor:
    """Make covariances [Q, 3, 3] symmetric positive definite (degenerate masks give flat ones)."""
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    tr = torch.diagonal(cov, dim1=-2, dim2=-1).sum(-1).clamp_min(0)
    eye = torch.eye(3, dtype=cov.dtype, device=cov.device)
    return cov + (rel * tr + floor).view(-1, 1, 1) * eye


def init_from_points(groups: list[torch.Tensor], feat_dim: int, *, generator: torch.Generator | None = None,
                     min_sigma: float = 0.02):
    """Initial (feature [Q, F], mean [Q, 3], cov [Q, 3, 3]) from back-projected mask point sets.

    groups: list of [P_i, 3] world points, one per 2D mask. Features are random unit vectors (queries
    are told apart by their Gaussians first; features specialise during training).
    """
    q = len(groups)
    feat = torch.randn(q, feat_dim, generator=generator)
    feat = feat / feat.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    mean = torch.zeros(q, 3)
    cov = torch.zeros(q, 3, 3)
    for i, pts in enumerate(groups):
        pts = pts.double()
        mu = pts.mean(0)
        c = torch.cov(pts.T) if pts.shape[0] > 1 else torch.zeros(3, 3, dtype=torch.float64)
        # Inflate: a mask sees one side of an object; the Gaussian should cover the whole object.
        c = c * 2.0 + (min_sigma ** 2) * torch.eye(3, dtype=torch.float64)
        mean[i] = mu.float()
        cov[i] = _regularise(c.unsqueeze(0))[0].float()
    return feat, mean, cov
