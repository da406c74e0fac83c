"""Training losses (paper §4.2 + the 2DGS regularisers). Plain functions over torch tensors."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from psimap.transforms import pixels_to_camera_torch


def _gaussian_1d(size: int = 11, sigma: float = 1.5, dtype=torch.float32):
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-x**2 / (2 * sigma**2))
    return g / g.sum()                                                # [size]


def gaussian_blur(t, window: int = 11, sigma: float = 1.5):
    """t [1, K, H, W] blurred per channel by the normalised Gaussian window (replicate padding): the
    window is an outer product, so two 1D passes (vertical, then horizontal) give the 2D
    convolution's values with 2 x 11 taps a pixel instead of 121."""
    k, pad = t.shape[1], window // 2
    g = _gaussian_1d(window, sigma, dtype=t.dtype).to(t.device)
    t = F.pad(t, (pad,) * 4, mode="replicate")
    t = F.conv2d(t, g.view(1, 1, window, 1).expand(k, 1, window, 1), groups=k)
    return F.conv2d(t, g.view(1, 1, 1, window).expand(k, 1, 1, window), groups=k)


def ssim(a, b, window: int = 11):
    """Mean SSIM of images a, b: [H, W, C] in [0, 1] (Gaussian window 11, sigma 1.5; Wang et al.).
    Differentiable in a; b is the target. The five local means are two blur calls (separable,
    channels stacked): the target's two without gradient, a's three in one autograd node (a
    320x240 SSIM forward + backward 22 -> 11 ms against one 11x11 convolution per mean)."""
    C = a.shape[-1]
    x = a.permute(2, 0, 1)[None]
    y = b.detach().permute(2, 0, 1)[None]
    with torch.no_grad():
        my, byy = gaussian_blur(torch.cat([y, y * y], 1), window).split(C, 1)
    mx, bxx, bxy = gaussian_blur(torch.cat([x, x * x, x * y], 1), window).split(C, 1)
    sxx = bxx - mx * mx
    syy = byy - my * my
    sxy = bxy - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def rgb_loss(pred, target, ssim_weight: float = 0.2):
    """L_rgb = (1 - s) L1 + s D-SSIM, D-SSIM = 1 - SSIM. pred, target: [H, W, 3]."""
    l1 = (pred - target).abs().mean()
    if ssim_weight <= 0:
        return l1
    return (1 - ssim_weight) * l1 + ssim_weight * (1 - ssim(pred, target))


def depth_l1(pred, target, valid):
    """Mean |pred - target| over valid pixels. pred, target: [H, W] metres; valid: [H, W] bool."""
    n = valid.sum()
    if int(n) == 0:
        return pred.sum() * 0.0
    return ((pred - target).abs() * valid).sum() / n


def iso_loss(scales, unit: float = 1.0):
    """L_iso = mean ((s1 - s2) / unit)^2 over surfels; scales [N, 2] metres."""
    if scales.shape[0] == 0:
        return scales.sum() * 0.0
    return (((scales[:, 0] - scales[:, 1]) / unit) ** 2).mean()


def depth_to_normal(depth, K):
    """Camera-frame unit normals [H, W, 3] of a depth map [H, W] (metres), facing the camera.

    Back-project every pixel, take central differences along x and y, cross them. Border pixels
    and pixels next to invalid depth get a zero normal (excluded by the caller's weights).
    """
    H, W = depth.shape
    ys, xs = torch.meshgrid(torch.arange(H, dtype=depth.dtype), torch.arange(W, dtype=depth.dtype),
                            indexing="ij")
    P = pixels_to_camera_torch(xs, ys, depth, K)
    dx = torch.zeros_like(P)
    dy = torch.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dy[1:-1] = P[2:] - P[:-2]
    n = torch.cross(dx, dy, dim=-1)
    # face the camera: a surface normal points back along the viewing ray
    n = n * torch.where((n * P).sum(-1, keepdim=True) > 0, -1.0, 1.0)
    norm = n.norm(dim=-1, keepdim=True)
    ok = (depth > 0)
    ok = ok.clone()
    ok[1:-1, 1:-1] = ok[1:-1, 1:-1] & ok[2:, 1:-1] & ok[:-2, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2]
    ok[0, :] = ok[-1, :] = False
    ok[:, 0] = ok[:, -1] = False
    return torch.where(ok[..., None] & (norm > 1e-12), n / norm.clamp_min(1e-12), torch.zeros_like(n))


def normal_consistency(rendered_normal, alpha, depth, K):
    """2DGS normal consistency: mean over pixels of alpha (1 - n_render . n_depth).

    rendered_normal: [H, W, 3] alpha-weighted sum of camera-facing surfel normals (camera frame);
    alpha [H, W]; depth [H, W] rendered depth whose gradients give n_depth.
    """
    n_r = rendered_normal / rendered_normal.norm(dim=-1, keepdim=True).clamp_min(1e-8)
    n_d = depth_to_normal(depth, K)
    w = alpha * (n_d.norm(dim=-1) > 0)
    return (w * (1 - (n_r * n_d).sum(-1))).sum() / w.detach().sum().clamp_min(1.0)
