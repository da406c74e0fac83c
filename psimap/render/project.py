"""Stage 1 of the renderer (SPEC.md): per-surfel projection, shared by every backend.

Differentiable torch: the splat-to-pixel homography T, the projected centre, the sort key and the
camera-facing normal carry gradients into means / quats / scales. The integer tile boxes are
computed in float64 without gradients (they only decide which pixels are evaluated).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from psimap.transforms import quat_to_rotmat_torch

CHI = 3.0                          # the splat is cut at the 3 sigma disk u^2 + v^2 <= CHI^2
R_LOWPASS = math.sqrt(math.log(255.0))   # beyond this pixel radius exp(-rho2) < 1/255
# Slack (pixels) added to every box so that a pixel lying exactly on the ellipse / low-pass border
# is never lost to a rounding difference between the box and the per-pixel test.
BOX_SLACK = 1e-3


@dataclass
class Projected:
    """Per-surfel quantities of stage 1 (N surfels; SPEC.md).

    T: [N, 3, 3] splat-to-pixel homography (tangent point (u, v, 1) -> (x z, y z, z)).
    center: [N, 2] projected centre in pixels. depth_key: [N] camera-space depth of the centre.
    normal_c: [N, 3] unit normal in the camera frame, facing the camera.
    valid: [N] bool, False for culled surfels (near/far, non-finite input, opacity <= 0).
    box_precise / box_circle: [N, 4] int32 pixel boxes (x0, y0, x1, y1), half-open, clipped to the
    image; empty (all zeros) for culled surfels.
    """

    T: torch.Tensor
    center: torch.Tensor
    depth_key: torch.Tensor
    normal_c: torch.Tensor
    valid: torch.Tensor
    box_precise: torch.Tensor
    box_circle: torch.Tensor


def project_surfels(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                    opacities: torch.Tensor, viewmat: torch.Tensor, K: torch.Tensor,
                    width: int, height: int, near: float = 0.2, far: float = 1000.0) -> Projected:
    """Project surfels into a camera (stage 1 of SPEC.md).

    means: [N, 3], quats: [N, 4] (w, x, y, z), scales: [N, 2], opacities: [N],
    viewmat: [4, 4] world-to-camera (OpenCV), K: [3, 3]. Non-finite surfels are culled, never NaN.
    """
    n = means.shape[0]
    finite = (torch.isfinite(means).all(-1) & torch.isfinite(quats).all(-1)
              & torch.isfinite(scales).all(-1) & torch.isfinite(opacities)
              & (quats.detach().norm(dim=-1) > 0))
    # Replace culled inputs by harmless values so no NaN can leak into the graph (0 * NaN = NaN).
    fin = finite[:, None]
    means_s = torch.where(fin, means, torch.zeros_like(means))
    quats_s = torch.where(fin, quats, torch.tensor([1.0, 0, 0, 0], dtype=quats.dtype, device=quats.device))
    scales_s = torch.where(fin, scales, torch.ones_like(scales))

    R = quat_to_rotmat_torch(quats_s)                             # [N, 3, 3]
    Rc = viewmat[:3, :3]
    tc = viewmat[:3, 3]
    mu_c = means_s @ Rc.T + tc                                    # [N, 3]
    axes_c = torch.einsum("ij,njk->nik", Rc, R)                   # [N, 3, 3] camera-frame axes
    cols = torch.stack([axes_c[:, :, 0] * scales_s[:, 0:1], axes_c[:, :, 1] * scales_s[:, 1:2], mu_c],
                       dim=-1)                                    # [N, 3, 3] columns
    T = torch.einsum("ij,njk->nik", K, cols)                      # [N, 3, 3]

    depth_key = mu_c[:, 2]
    valid = finite & (depth_key.detach() > near) & (depth_key.detach() <= far) & (opacities.detach() > 0)

    z_safe = torch.where(valid, T[:, 2, 2], torch.ones_like(depth_key))
    center = torch.stack([T[:, 0, 2] / z_safe, T[:, 1, 2] / z_safe], dim=-1)   # [N, 2]

    normal = axes_c[:, :, 2]
    facing_away = (normal * mu_c).sum(-1).detach() > 0
    normal_c = torch.where(facing_away[:, None], -normal, normal)

    box_precise, box_circle = _tile_boxes(T.detach(), center.detach(), valid, width, height)
    if n == 0:
        box_precise = box_circle = torch.zeros(0, 4, dtype=torch.int32, device=means.device)
    return Projected(T=T, center=center, depth_key=depth_key, normal_c=normal_c, valid=valid,
                     box_precise=box_precise, box_circle=box_circle)


def _tile_boxes(T: torch.Tensor, center: torch.Tensor, valid: torch.Tensor, width: int, height: int):
    """Pixel boxes (precise AABB, bounding-circle square) of the 3 sigma ellipse + low-pass disk.

    T: [N, 3, 3], center: [N, 2], valid: [N]. Returns two [N, 4] int32 (x0, y0, x1, y1) half-open.
    """
    T = T.double()
    center = center.double()
    # Dual conic of the disk u^2 + v^2 <= CHI^2: Cs = T diag(1, 1, -1/CHI^2) T^T.
    D = torch.tensor([1.0, 1.0, -1.0 / CHI ** 2], dtype=T.dtype, device=T.device)
    Cs = torch.einsum("nij,j,nkj->nik", T, D, T)
    c22 = Cs[:, 2, 2]
    bounded = c22 < 0          # the whole disk lies in front of the camera
    c22s = torch.where(bounded, c22, -torch.ones_like(c22))
    ell = torch.stack([Cs[:, 0, 2] / c22s, Cs[:, 1, 2] / c22s], dim=-1)            # [N, 2]
    # 2x2 shape M of the ellipse (x - c)^T M^-1 (x - c) <= 1; its diagonal gives the AABB.
    M = (Cs[:, :2, 2, None] * Cs[:, None, 2, :2] - Cs[:, :2, :2] * c22s[:, None, None]) / (c22s ** 2)[:, None, None]
    half = torch.sqrt(torch.clamp(torch.diagonal(M, dim1=1, dim2=2), min=0.0))       # [N, 2]
    ok = bounded & torch.isfinite(ell).all(-1) & torch.isfinite(half).all(-1) & torch.isfinite(M).all(-1).all(-1)

    lo = torch.minimum(ell - half, center - R_LOWPASS) - BOX_SLACK
    hi = torch.maximum(ell + half, center + R_LOWPASS) + BOX_SLACK

    # Largest eigenvalue of the symmetric 2x2 M in closed form (no batched LAPACK call).
    a, d, b = M[:, 0, 0], M[:, 1, 1], 0.5 * (M[:, 0, 1] + M[:, 1, 0])
    lam_max = 0.5 * (a + d) + torch.sqrt(0.25 * (a - d) ** 2 + b * b)
    semi_major = torch.sqrt(torch.clamp(torch.where(ok, lam_max, torch.zeros_like(lam_max)), min=0.0))
    radius = torch.maximum(semi_major, (ell - center).norm(dim=-1) + R_LOWPASS) + BOX_SLACK
    clo = ell - radius[:, None]
    chi_ = ell + radius[:, None]

    size = torch.tensor([width, height], dtype=T.dtype, device=T.device)
    whole = torch.cat([torch.zeros_like(size), size])

    def to_box(lo, hi):
        # Pixel centres are integer coordinates: the pixels inside [lo, hi] are ceil(lo) .. floor(hi).
        lo = torch.clamp(lo, min=-1.0)
        lo = torch.minimum(lo, size + 1)
        hi = torch.clamp(hi, min=-1.0)
        hi = torch.minimum(hi, size + 1)
        box = torch.cat([torch.ceil(lo), torch.floor(hi) + 1], dim=-1)
        box = torch.where(ok[:, None], box, whole)
        box = torch.minimum(torch.clamp(box, min=0.0), torch.cat([size, size]))
        empty = (box[:, 2] <= box[:, 0]) | (box[:, 3] <= box[:, 1]) | ~valid
        box = torch.where(empty[:, None], torch.zeros_like(box), box)
        return box.to(torch.int32)

    return to_box(lo, hi), to_box(clo, chi_)
