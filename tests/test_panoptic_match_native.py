"""The Hungarian matching's per-mask sums (psimap/render/csrc/match_lanes.inl,
psimap.panoptic.matching.match_sums) against their torch form (match_sums_reference).

Oracle: the reference in float64 on the same float32 probabilities, clamped in float32 as the
kernel clamps them (1 - 1e-6 rounds to 0.99999899 in float32: log(1 - x) there differs from the
float64 clamp's by 1e-3). The kernel's logarithms are held to 4e-7 relative per value (measured
1.4e-7 for log x, 2.4e-7 for log(1 - x) over 4096 values from 1e-6 to 1); the sums, which the
kernel accumulates in float64, to 1e-6 relative (measured <= 2e-7). Row lengths cover one lane,
whole vectors and partial last vectors of every instruction set (4, 8 and 16 lanes)."""
from __future__ import annotations

import pytest
import torch

from psimap.panoptic.matching import hungarian_match, mask_windows, match_costs, match_sums, match_sums_reference
from psimap.render.api import native_available

# every native output buffer starts as NaN: a value a kernel forgets to write fails
pytestmark = [pytest.mark.skipif(not native_available(), reason="native kernels not built"),
              pytest.mark.usefixtures("poison_native_outputs")]
CLAMP = 1e-6


def scene(q: int, seed: int, h: int = 30, w: int = 40):
    """prob [Q, P] float32 (softmax rows: sharp and diffuse, a few exactly 0 and 1), target [M, P] and
    window [M, P] float32 (window = mask_windows grown around each mask, containing it; some pixels in
    no window, some in two)."""
    g = torch.Generator().manual_seed(seed)
    x = torch.softmax(torch.randn(h * w, q, generator=g) * 4, -1)
    x[:7] = 0.0
    x[:7, 0] = 1.0
    masks = torch.zeros(4, h, w, dtype=torch.bool)
    masks[0, 2:8, 3:9] = True
    masks[1, 20:24, 30:33] = True
    masks[2, 10:14, 12:30] = True
    masks[3, 11:13, 14:16] = True                    # inside mask 2's window
    masks[0, 0, 0] = True                            # row 0 (exactly 0 / 1 values) is on a mask
    t = masks.flatten(1).float()
    win = torch.maximum(mask_windows(masks).flatten(1).float(), t)
    return x.T, t, win


def reference64(prob, t, win):
    """The float64 oracle on float32-clamped probabilities."""
    x = prob.clamp(CLAMP, 1 - CLAMP).double()
    return match_sums_reference(x, t.double(), win.double(), None)


@pytest.mark.parametrize("q", [1, 5, 16, 17, 33, 85])
def test_native_sums_match_the_reference_on_every_instruction_set(q):
    from psimap.render import _native

    prob, t, win = scene(q, seed=q)
    assert 0.1 < float(win.any(0).float().mean()) < 0.9
    ref = reference64(prob, t, win)
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            got = match_sums(prob, t, win, CLAMP, backend="native").double()
            assert got.shape == (5, 4, q)
            torch.testing.assert_close(got, ref, rtol=1e-6, atol=1e-9, msg=f"{isa}")
            # boolean masks mean the same (a bool + bool would be an or, not 0 / 1 / 2)
            assert torch.equal(match_sums(prob, t.bool(), win.bool(), CLAMP, backend="native").double(), got)
    finally:
        _native.use_pixel_kernels("")


def test_the_kernels_logarithms_hold_to_a_few_ulp():
    """One pixel on one mask: the sums are the clamped values and their logarithms themselves."""
    from psimap.render import _native
    from psimap.render.native import match_sums as fused

    v = torch.cat([torch.logspace(-6, 0, 4093), torch.tensor([0.5, 0.75, 1 - 1e-6])]).float()
    v = v.clamp(CLAMP, 1 - CLAMP)
    codes = torch.full((1, 1), 2, dtype=torch.uint8)
    v64 = v.double()
    try:
        for isa in _native.available_pixel_kernels():
            _native.use_pixel_kernels(isa)
            s = fused(v[None], codes, CLAMP, 1 - CLAMP)[:, 0]                         # [5, Q]
            assert torch.equal(s[0], v64) and torch.equal(s[3], v64)
            torch.testing.assert_close(s[1], torch.log(v64), rtol=4e-7, atol=0.0, msg=f"{isa}: log x")
            torch.testing.assert_close(s[2], torch.log1p(-v64), rtol=4e-7, atol=0.0, msg=f"{isa}: log(1 - x)")
            assert torch.equal(s[2], s[4])
    finally:
        _native.use_pixel_kernels("")


def test_a_nan_pixel_spoils_only_the_masks_whose_window_holds_it():
    prob, t, win = scene(17, seed=3)
    p = 12 * 40 + 25                                  # on mask 2, in no other mask's window
    assert t[2, p] == 1 and win[:, p].tolist() == [0.0, 0.0, 1.0, 0.0]
    r = 9 * 40 + 14                                   # in the windows of masks 0, 2 and 3, on none
    assert t[:, r].sum() == 0 and win[:, r].tolist() == [1.0, 0.0, 1.0, 1.0]
    prob = prob.clone()
    prob[5, p] = float("nan")
    prob[9, r] = float("nan")
    got = match_sums(prob, t, win, CLAMP, backend="native")
    ref = match_sums_reference(prob, t, win, CLAMP)
    # the reference's matrix products carry a NaN into every mask's sums (0 x NaN); the kernel adds
    # a pixel only into the masks whose window holds it
    assert bool((ref.isnan() | ~got.isnan()).all())
    assert bool(got[:, 2, 5].isnan().all())                           # every sum of mask 2, query 5
    assert bool(got[3:, [0, 2, 3], 9].isnan().all()) and not bool(got[:3, [0, 3], 9].isnan().any())
    assert int(got.isnan().sum()) == 5 + 2 * 3                        # and nothing else


def test_hungarian_match_takes_the_kernel_and_keeps_the_reference_costs(monkeypatch):
    """match_costs with windows and a clamp (what every panoptic step's matching calls) runs the
    kernel, and its costs and the match equal the torch form's."""
    import psimap.panoptic.matching as matching

    prob, t, win = scene(21, seed=5)
    native = match_costs(prob, t, win, clamp=CLAMP, backend="auto")
    torch_ = match_costs(prob, t, win, clamp=CLAMP, backend="torch")
    for key in ("dice", "bce", "on_mask", "on_ring", "ring_pixels"):
        torch.testing.assert_close(native[key], torch_[key], rtol=2e-5, atol=1e-6, msg=key)
    calls = []
    real_reference, real_sums = matching.match_sums_reference, matching.match_sums
    monkeypatch.setattr(matching, "match_sums_reference", lambda *a: calls.append(1) or real_reference(*a))
    a = hungarian_match(prob, t, window=win)
    assert a.query_idx.numel() >= 2 and not calls              # the kernel ran, not the reference
    monkeypatch.setattr(matching, "match_sums", lambda p, tt, w, c, backend: real_sums(p, tt, w, c, "torch"))
    b = hungarian_match(prob, t, window=win)
    assert calls
    assert torch.equal(a.query_idx, b.query_idx) and torch.equal(a.mask_idx, b.mask_idx)


def test_bad_inputs_are_refused():
    from psimap.render.native import match_sums as fused

    prob, t, win = scene(5, seed=1)
    codes = torch.zeros(4, prob.shape[1], dtype=torch.uint8)
    with pytest.raises(ValueError, match="float32"):
        fused(prob.T.double(), codes, CLAMP, 1 - CLAMP)
    with pytest.raises(ValueError, match="codes"):
        fused(prob.T, codes[:, :-1], CLAMP, 1 - CLAMP)
    with pytest.raises(ValueError, match="lo"):
        fused(prob.T, codes, 0.0, 1.0)
    with pytest.raises(ValueError, match="native kernel"):
        match_sums(prob, t, None, CLAMP, backend="native")
