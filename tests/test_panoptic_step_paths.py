"""The panoptic step's cheaper paths give what the plain ones give (issue #20): the per-surfel
gradients landing in one kept buffer, the position codes of fixed surfels computed once, the
settle test reading the adjustment's affinity, the mask loss's one-logarithm BCE."""
import pytest
import torch
import torch.nn.functional as F

from psimap.data.frames import ClassInfo
from psimap.panoptic.config import PanopticConfig
from psimap.panoptic.field import PanopticField
from psimap.panoptic.matching import Match, matched_mask_loss
from psimap.panoptic.queries import InstanceQueries, init_from_points

CLASSES = [ClassInfo(1, "floor", False), ClassInfo(2, "box", True)]


def _field(n=60, q=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    queries = InstanceQueries(torch.randn(q, 16, generator=g), torch.randn(q, 3, generator=g),
                              0.3 * torch.eye(3).expand(q, 3, 3), scene_scale=3.0, generator=g)
    field = PanopticField(n, CLASSES, queries, PanopticConfig(), generator=g)
    with torch.no_grad():
        field.semantic.normal_(generator=g)
    return field


def test_surfel_rows_land_the_indexing_gradient_in_one_kept_buffer():
    """Three steps over different surfel subsets: each step's .grad equals that of indexing the
    parameter, bit for bit (rows of the step's subset, zero elsewhere: the last step's rows are
    cleared), in the same buffer every step; a gradient the caller kept is added to, not cleared."""
    field = _field()
    plain = {name: getattr(field, name).detach().clone().requires_grad_(True) for name in ("instance", "semantic")}
    g = torch.Generator().manual_seed(1)
    buffers = set()
    for step in range(3):
        idx = torch.randperm(60, generator=g)[: 20 + 10 * step].sort().values
        w = {name: torch.randn(idx.numel(), p.shape[1], generator=g) for name, p in plain.items()}
        field.zero_grad()
        for p in plain.values():
            p.grad = None
        sum((field.surfel_rows(name, idx) * w[name]).sum() for name in plain).backward()
        sum((p[idx] * w[name]).sum() for name, p in plain.items()).backward()
        for name, p in plain.items():
            assert torch.equal(getattr(field, name).grad, p.grad), (step, name)
        buffers.add(field.instance.grad.data_ptr())
    assert len(buffers) == 1
    # no zero_grad: the second backward adds onto the kept gradient, as indexing would
    idx = torch.arange(0, 60, 3)
    (field.surfel_rows("instance", idx) * 2.0).sum().backward()
    plain["instance"][idx].mul(2.0).sum().backward()
    assert torch.equal(field.instance.grad, plain["instance"].grad)


def test_fixed_position_codes_change_no_attention():
    """fix_positions keeps the surfels' position codes: the steps' attention (losses pass the
    visible rows' codes) and the scene-wide one give the same bits as encoding each time."""
    field = _field(n=80, q=4, seed=2)
    means = torch.randn(80, 3, generator=torch.Generator().manual_seed(3)) * 2.0
    with torch.no_grad():
        field.queries.gate.fill_(0.5)               # the attention's update counts (0 at the start)
    idx = torch.arange(5, 70, 2)
    before = field.global_query_features(means)
    step = field.queries.attend(field.instance[idx], means[idx])
    field.fix_positions(means)
    assert torch.equal(field.global_query_features(means), before)
    codes = field._pos_codes.index_select(0, idx)
    assert torch.equal(field.queries.attend(field.instance[idx], means[idx], codes), step)
    # a query's attended feature moves with the codes it is given (they are read, not ignored)
    assert not torch.equal(field.queries.attend(field.instance[idx], means[idx], codes.flip(0)), step)


def test_the_settle_labels_read_the_adjustments_affinity_only_at_its_step():
    """current_labels right after adjust reads adjust's affinity (the kept queries' columns): the
    labels computed afresh; after the next step it computes them again (features that moved in
    between move the labels)."""
    from test_panoptic_field import two_clusters_three_queries

    field, means, feat, _ = two_clusters_three_queries()
    field.steps = 1000
    field.matched = torch.tensor([10.0, 0.0, 10.0])
    field.visible = torch.tensor([10.0, 10.0, 10.0])
    assert field.adjust(means) == 1
    assert field._affinity_at is not None and field._affinity_at[1].shape == (40, 2)
    cached = field.current_labels(means)
    field._affinity_at = None
    fresh = field.current_labels(means)
    assert torch.equal(cached[0], fresh[0]) and torch.equal(cached[1], fresh[1])
    assert cached[1][:20].unique().tolist() == [1] and cached[1][20:].unique().tolist() == [3]
    field.adjust(means)
    field.step()                                   # no gradients: nothing moves, but a new step
    with torch.no_grad():                          # the clusters trade features
        field.instance[:20] = 4 * feat[2]
        field.instance[20:] = 4 * feat[0]
        field.queries.mean.copy_(field.queries.mean.mean(0, keepdim=True))   # one place: features decide
    later = field.current_labels(means)[1]
    assert later[:20].unique().tolist() == [3] and later[20:].unique().tolist() == [1]


@pytest.mark.parametrize("window", [False, True])
def test_mask_loss_bce_is_the_textbook_one(window):
    """The mask loss's BCE (one logarithm a pixel for a {0, 1} target) equals
    F.binary_cross_entropy's to float rounding, value and gradient, with probabilities at the
    clamp (0 and 1 exactly) and in between."""
    g = torch.Generator().manual_seed(7)
    q, m, p = 4, 3, 500
    prob = torch.rand(q, p, generator=g)
    prob[0, :50], prob[1, :50] = 0.0, 1.0
    prob.requires_grad_(True)
    target = (torch.rand(m, p, generator=g) > 0.7).float()
    win = (torch.rand(m, p, generator=g) > 0.3).float() if window else None
    match = Match(query_idx=torch.tensor([0, 1, 3]), mask_idx=torch.tensor([2, 0, 1]), cost=torch.zeros(3))
    loss = matched_mask_loss(prob, target, match, window=win)
    (v_prob,) = torch.autograd.grad(loss, prob)

    def textbook(prob):
        pp = prob[match.query_idx].clamp(1e-6, 1 - 1e-6)
        t = target[match.mask_idx]
        inter = (pp * t).sum(-1)
        mass = pp.sum(-1) if win is None else (pp * torch.maximum(win[match.mask_idx], t)).sum(-1)
        dice = 1.0 - (2.0 * inter + 1.0) / (mass + t.sum(-1) + 1.0)
        return (dice + F.binary_cross_entropy(pp, t, reduction="none").mean(-1)).mean()

    ref = textbook(prob)
    (v_ref,) = torch.autograd.grad(ref, prob)
    loss, ref = float(loss.detach()), float(ref.detach())
    assert abs(loss - ref) <= 1e-6 * ref
    assert torch.allclose(v_prob, v_ref, rtol=1e-5, atol=1e-9)
    assert loss > 1.0                    # the clamped pixels' BCE is in it (-log 1e-6 = 13.8)


def test_a_step_on_fixed_positions_is_the_step_that_encodes_them():
    """Two-box scene, three views on frozen blends: the losses and every gradient of a field whose
    positions were fixed (codes read per view) equal, bit for bit, those of one encoding each step."""
    from test_panoptic_field import two_box_steps

    encoded, fixed = two_box_steps(gate=0.5), two_box_steps(gate=0.5, fixed=True)
    for (a_ins, a_sem, a_m, a_g), (b_ins, b_sem, b_m, b_g) in zip(encoded, fixed):
        assert a_m == b_m and torch.equal(a_ins, b_ins) and torch.equal(a_sem, b_sem)
        assert all(torch.equal(x, y) for x, y in zip(a_g, b_g))
    assert float(fixed[0][0]) > 0.0


def test_a_frame_without_semantic_labels_still_gives_a_zero_semantic_loss_with_its_graph():
    """No semantic map: l_sem is a zero tensor that still reaches the class logits (their gradient
    is a tensor, from the instance loss's P(thing)); with one, both losses are positive."""
    from test_panoptic_field import two_box_steps

    for semantic in (False, True):
        for l_ins, l_sem, _, grads in two_box_steps(2, semantic=semantic):
            assert float(l_ins) > 0.0
            assert (float(l_sem) > 0.0) == semantic
            assert all(t is not None and bool(torch.isfinite(t).all()) for t in grads)


def test_attention_projects_the_queries_not_the_surfels():
    """attend moves W_k and W_v onto the queries' side ((W_q f_q) . (W_k k) = (W_k^T W_q f_q) . k,
    sum_v a_v W_v f_v = W_v sum_v a_v f_v): the textbook cross-attention to float rounding, value and
    every gradient, with non-identity projections and an open gate."""
    import math

    from psimap.panoptic.queries import positional_encoding

    g = torch.Generator().manual_seed(11)
    q = InstanceQueries(torch.randn(6, 16, generator=g), torch.randn(6, 3, generator=g),
                        0.2 * torch.eye(3).expand(6, 3, 3), scene_scale=4.0, generator=g)
    with torch.no_grad():
        q.gate.fill_(0.7)
        for lin in (q.w_q, q.w_k, q.w_v):
            lin.weight.add_(0.3 * torch.randn(lin.weight.shape, generator=g))
    pos = torch.randn(300, 3, generator=g)
    feat = torch.randn(300, 16, generator=g).requires_grad_(True)
    codes = positional_encoding(pos, q.n_freqs, q.scene_scale)

    def textbook():
        keys = feat + q.pos_proj(codes)
        qk = q.w_q(q.feature) @ q.w_k(keys).T / math.sqrt(q.w_q.out_features)
        return q.feature + torch.tanh(q.gate) * (torch.softmax(qk, -1) @ q.w_v(feat))

    w = torch.randn(6, 16, generator=g)
    params = [feat, *q.parameters()]
    out, ref = q.attend(feat, pos, codes), textbook()
    assert torch.allclose(out, ref, rtol=1e-5, atol=1e-5)
    grads = torch.autograd.grad((out * w).sum(), params, allow_unused=True)
    grads_ref = torch.autograd.grad((ref * w).sum(), params, allow_unused=True)
    for a, b in zip(grads, grads_ref):
        assert (a is None) == (b is None)
        if a is not None:
            assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)
    assert float(grads[0].abs().sum()) > 0 and float((out - q.feature).detach().abs().max()) > 0.05


def test_semantic_loss_reads_only_the_labelled_covered_pixels():
    """semantic_loss over every read pixel with the others ignored equals the cross-entropy of the
    selected pixels (value and gradients in the logits and in alpha, to float rounding), and its
    torch reference; uncovered (alpha <= 0.5) and void (column -1) pixels get no gradient; no pixel
    to read gives None; the ClassScores it is given (the matching's) give the same loss."""
    from psimap.panoptic.field import ClassScores, semantic_loss, semantic_loss_reference

    g = torch.Generator().manual_seed(12)
    for n_cls in (5, 11, 40):
        s_px = (3.0 * torch.randn(400, n_cls, generator=g)).requires_grad_(True)
        alpha = (0.2 + torch.rand(400, generator=g)).requires_grad_(True)
        with torch.no_grad():
            alpha[:20] = 0.0
        cols = torch.randint(-1, n_cls, (400,), generator=g)
        loss = semantic_loss(s_px, alpha, cols)
        ok = (cols >= 0) & (alpha > 0.5)
        ref = F.nll_loss(torch.log_softmax(s_px[ok] / alpha[ok, None].clamp_min(1e-3), -1), cols[ok])
        v, v_a = torch.autograd.grad(loss, (s_px, alpha))
        v_ref, v_a_ref = torch.autograd.grad(ref, (s_px, alpha))
        assert abs(float(loss.detach()) - float(ref.detach())) <= 1e-6 * float(ref.detach())
        assert torch.allclose(v, v_ref, rtol=1e-5, atol=1e-9)
        # alpha's gradient sums (p - onehot) z over the classes: rounding relative to its largest
        assert float((v_a - v_a_ref).abs().max()) <= 1e-5 * float(v_a_ref.abs().max())
        assert float(v[~ok].abs().sum()) == 0.0 and float(v[ok].abs().sum()) > 0.0
        assert float(v_a[~ok].abs().sum()) == 0.0 and float(v_a[ok].abs().sum()) > 0.0
        ref2 = semantic_loss_reference(s_px, alpha, cols)
        assert abs(float(loss.detach()) - float(ref2.detach())) <= 1e-6 * float(ref2.detach())
        assert torch.allclose(torch.autograd.grad(ref2, s_px)[0], v, rtol=1e-5, atol=1e-9)
        given = semantic_loss(s_px, alpha, cols, ClassScores.of(s_px, alpha))
        assert float(given.detach()) == float(loss.detach())
    # the scores live on the logits' device (a CUDA run's; "meta" checks the placement on a CPU)
    on_meta = ClassScores.of(s_px.detach().to("meta"), alpha.detach().to("meta"))
    assert on_meta.z.device.type == on_meta.p.device.type == "meta"
    s_px, alpha = s_px.detach().requires_grad_(True), alpha.detach()
    v = torch.autograd.grad(semantic_loss(s_px, alpha, cols), s_px)[0]
    assert semantic_loss(s_px, torch.zeros(400), cols) is None
    assert semantic_loss_reference(s_px, torch.zeros(400), cols) is None
    # a NaN logit or alpha on a pixel the loss ignores stays out of the loss and the gradient
    bad = s_px.detach().clone()
    alpha_bad = alpha.clone()
    off = torch.nonzero(~ok).flatten()
    bad[off[0]] = float("nan")
    alpha_bad[off[1]] = float("nan")
    bad.requires_grad_(True)
    loss_bad = semantic_loss(bad, alpha_bad, cols)
    (v_bad, ) = torch.autograd.grad(loss_bad, bad)
    assert float(loss_bad.detach()) == float(semantic_loss(s_px, alpha, cols).detach())
    assert bool(torch.isfinite(v_bad).all()) and torch.equal(v_bad, v)
