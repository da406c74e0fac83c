"""Panoptic building blocks: Hungarian matching, affinity, query pruning, COCO panoptic encoding."""
import json
import math

import numpy as np
import pytest
import torch

from psimap.panoptic.adjust import co_mask_duplicates, duplicate_queries, iom_matrix, useless_queries
from psimap.panoptic.coco import STUFF_OFFSET, decode_rgb, encode_rgb, write_coco_panoptic
from psimap.panoptic.matching import hungarian_match, masks_from_ids, matched_mask_loss
from psimap.panoptic.queries import InstanceQueries, init_from_points, positional_encoding


def _blocks(h=12, w=12):
    ids = torch.zeros(h, w, dtype=torch.long)
    ids[:6, :6] = 7
    ids[6:, :6] = 3
    ids[:, 8:] = 11
    return ids


def test_masks_from_ids_and_empty_frame():
    masks, ids = masks_from_ids(_blocks())
    assert ids.tolist() == [3, 7, 11]
    assert masks.shape == (3, 12, 12) and int(masks.sum()) == 36 + 36 + 48
    empty, none = masks_from_ids(torch.zeros(4, 5, dtype=torch.long))
    assert empty.shape == (0, 4, 5) and none.numel() == 0


def test_hungarian_recovers_permutation_and_rejects_non_overlap():
    masks, _ = masks_from_ids(_blocks())
    target = masks.flatten(1).float()                       # [3, P]
    perm = [2, 0, 1]
    prob = torch.full((4, target.shape[1]), 0.02)
    for q, m in enumerate(perm):
        prob[q] = target[m] * 0.9 + 0.05                     # query q renders mask perm[q]
    # query 3 covers only pixels no mask has: must not be matched
    prob[3] = 0.02
    prob[3, :2] = 0.0
    m = hungarian_match(prob, target)
    got = dict(zip(m.query_idx.tolist(), m.mask_idx.tolist()))
    assert got == {0: 2, 1: 0, 2: 1}


def test_hungarian_no_masks_and_no_queries():
    prob = torch.rand(3, 10)
    m = hungarian_match(prob, torch.zeros(0, 10))
    assert m.query_idx.numel() == 0
    p = prob.clone().requires_grad_(True)
    loss = matched_mask_loss(p, torch.zeros(0, 10), m)
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.all(p.grad == 0)
    assert hungarian_match(torch.zeros(0, 10), torch.ones(2, 10)).query_idx.numel() == 0


def test_matched_loss_decreases_toward_target():
    target = torch.tensor([[1.0, 1.0, 0.0, 0.0]])
    m = hungarian_match(torch.tensor([[0.6, 0.6, 0.4, 0.4]]), target, reject_dice=1.0)
    good = matched_mask_loss(torch.tensor([[0.95, 0.95, 0.05, 0.05]]), target, m)
    bad = matched_mask_loss(torch.tensor([[0.6, 0.6, 0.4, 0.4]]), target, m)
    assert float(good) < float(bad) * 0.5


def test_affinity_and_distribution():
    f = torch.eye(3) * 4.0
    groups = [torch.randn(50, 3) * 0.05 + torch.tensor(c) for c in ([0, 0, 0], [1.0, 0, 0], [0, 1.0, 0])]
    feat, mean, cov = init_from_points(groups, 3, generator=torch.Generator().manual_seed(0))
    q = InstanceQueries(f, mean, cov, temperature=0.05)
    pts = mean.clone()
    a = q.affinity(f, pts)                                   # surfel i sits at query i's centre
    assert a.shape == (3, 3)
    assert torch.allclose(torch.diagonal(a), torch.sigmoid(torch.tensor(16.0)), atol=1e-4)
    far = q.affinity(f, pts + 10.0)
    assert float(far.detach().max()) < 1e-6
    d = q.distribution(f, pts)
    assert torch.allclose(d.sum(-1), torch.ones(3), atol=1e-5)
    assert d.argmax(-1).tolist() == [0, 1, 2] and float(d.detach().diagonal().min()) > 0.9
    # covariance stays positive definite for a degenerate (flat, 2-point) mask
    feat2, mean2, cov2 = init_from_points([torch.tensor([[0.0, 0, 0], [1.0, 0, 0]])], 3)
    q2 = InstanceQueries(feat2, mean2, cov2)
    assert bool(torch.all(torch.linalg.eigvalsh(q2.cov()) > 0))


def test_frustum_attention_shapes_and_gradients():
    g = torch.Generator().manual_seed(1)
    feat, mean, cov = init_from_points([torch.randn(20, 3, generator=g) for _ in range(4)], 8, generator=g)
    q = InstanceQueries(feat, mean, cov, scene_scale=2.0)
    sf = torch.randn(30, 8, generator=g, requires_grad=True)
    pos = torch.randn(30, 3, generator=g)
    out = q.attend(sf, pos)
    assert out.shape == (4, 8)
    assert torch.allclose(out, q.feature)                    # gate starts closed

    def oracle(feat, pos):
        """feature + tanh(gate) softmax_V(Wq f . Wk (f_g + PE(x_g)) / sqrt(d)) Wv f_g, by hand."""
        keys = feat + q.pos_proj(positional_encoding(pos, q.n_freqs, q.scene_scale))
        logits = q.w_q(q.feature) @ q.w_k(keys).T / math.sqrt(q.w_q.out_features)     # [Q, V]
        w = torch.exp(logits - logits.max(dim=1, keepdim=True).values)
        w = w / w.sum(dim=1, keepdim=True)                  # each query's weights over the surfels
        return q.feature + torch.tanh(q.gate) * (w @ q.w_v(feat)), w

    # closed gate: the features pass through, and the gate alone learns (d out / d gate = upd)
    out.sum().backward()
    _, w = oracle(sf, pos)
    upd = (w @ q.w_v(sf)).detach()
    assert torch.allclose(q.gate.grad, upd.sum().reshape(q.gate.shape), rtol=1e-5, atol=1e-6)
    assert torch.equal(q.feature.grad, torch.ones_like(q.feature))
    assert sf.grad is None or float(sf.grad.abs().max()) == 0.0
    with torch.no_grad():
        q.gate.fill_(1.0)
    q.zero_grad()
    out2 = q.attend(sf, pos)
    want, w = oracle(sf, pos)
    assert torch.allclose(out2, want, atol=1e-6) and not torch.allclose(out2, q.feature)
    assert torch.allclose(w.sum(1), torch.ones(4)) and float(w.detach().min()) > 0
    # open gate: the visible surfels' features and every projection receive gradients
    out2.pow(2).sum().backward()
    for name, t in [("surfel features", sf), ("w_q", q.w_q.weight), ("w_k", q.w_k.weight),
                    ("w_v", q.w_v.weight), ("pos_proj", q.pos_proj.weight), ("gate", q.gate)]:
        assert t.grad is not None and float(t.grad.abs().max()) > 1e-6, name
    assert q.attend(sf[:0], torch.zeros(0, 3)).shape == (4, 8)   # nothing visible


def test_iom_and_duplicate_pruning():
    n = 100
    masks = torch.zeros(n, 4, dtype=torch.bool)
    masks[:60, 0] = True        # big object
    masks[10:30, 1] = True      # part of the big object (duplicate)
    masks[70:90, 2] = True      # another object
    masks[55:75, 3] = True      # straddles two: IoM 0.25 each -> kept
    iom = iom_matrix(masks)
    assert iom[1, 0] == pytest.approx(1.0) and iom[0, 1] == pytest.approx(20 / 60)
    drop = duplicate_queries(masks, threshold=0.6)
    assert drop.tolist() == [False, True, False, False]


def test_useless_queries():
    matched = torch.tensor([10, 0, 1, 0])
    visible = torch.tensor([12, 9, 20, 1])
    assert useless_queries(matched, visible, min_rate=0.1).tolist() == [False, True, True, False]


def test_coco_panoptic_roundtrip(tmp_path):
    seg = np.array([[0, 5, STUFF_OFFSET + 1], [70000, 5, 3]])
    assert np.array_equal(decode_rgb(encode_rgb(seg)), seg)
    classes = [{"id": 1, "name": "floor", "isthing": False}, {"id": 2, "name": "chair", "isthing": True}]
    inst = np.array([[0, 4, 4], [0, 9, 9]])
    sem = np.array([[1, 2, 2], [0, 2, 1]])          # a class flip on instance 9 is overruled by the vote
    path = write_coco_panoptic(tmp_path, [("f0", inst, sem), ("f1", inst, sem)], classes, {4: 2, 9: 2})
    data = json.loads(path.read_text())
    assert [c["id"] for c in data["categories"]] == [1, 2]
    segs = {s["id"]: s["category_id"] for s in data["annotations"][0]["segments_info"]}
    assert segs == {4: 2, 9: 2, STUFF_OFFSET + 1: 1}
    from PIL import Image
    png = decode_rgb(np.asarray(Image.open(tmp_path / "f1.png")))
    assert png[0, 1] == 4 and png[1, 2] == 9 and png[0, 0] == STUFF_OFFSET + 1


def test_uncovered_mask_spawns_a_query_and_covered_one_does_not():
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    h, w = 12, 16
    K = torch.tensor([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05 + 10.0], 4)   # far from the view
    field = PanopticField(5, [ClassInfo(1, "box", True)], InstanceQueries(feat, mean, cov),
                          PanopticConfig(feat_dim=4))

    def render(idx, blocks, topk):   # nothing rendered: no query explains the mask
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        c = feats.shape[1]
        return SimpleNamespace(features=feats.sum() * 0 + torch.zeros(h, w, c), alpha=torch.ones(h, w))

    inst = torch.zeros(h, w, dtype=torch.long)
    inst[3:9, 4:12] = 5
    sem = torch.where(inst > 0, 1, 0)
    args = (render, torch.zeros(5, 3), torch.arange(5), inst, sem, K, torch.eye(4), w, h)
    l_ins, l_sem, info = field.losses(*args, depth=torch.ones(h, w))
    assert info["masks"] == 1 and info["matched"] == 0
    (l_ins + l_sem).backward()
    field.step()
    assert field.queries.count == 2
    assert torch.allclose(field.queries.mean[1], torch.tensor([0.0, 0.0, 1.0]), atol=0.2)
    # the new query covers that mask now: seeing it again spawns nothing more
    field.losses(*args, depth=torch.ones(h, w))
    field.step()
    assert field.queries.count == 2


def test_co_mask_duplicates_drop_the_weaker_piece_of_a_split_object():
    # queries 0 and 1 split one object (drawn inside the same 2D mask in 6 frames, apart in 1);
    # 2 is a bottle on that object, merged with it by the 2D model in 2 frames, apart in 8
    same = torch.zeros(3, 3)
    apart = torch.zeros(3, 3)
    same[0, 1] = same[1, 0] = 6
    apart[0, 1] = apart[1, 0] = 1
    same[0, 2] = same[2, 0] = 2
    apart[0, 2] = apart[2, 0] = 8
    matched = torch.tensor([20.0, 5.0, 3.0])
    assert co_mask_duplicates(same, apart, matched).tolist() == [False, True, False]
    # the better supported piece is kept whichever index it has
    assert co_mask_duplicates(same, apart, torch.tensor([5.0, 20.0, 3.0])).tolist() == [True, False, False]
    # too few shared frames is no evidence; one query alone is never a duplicate
    assert not co_mask_duplicates(same.clamp_max(2), apart, matched).any()
    assert not co_mask_duplicates(torch.zeros(1, 1), torch.zeros(1, 1), torch.ones(1)).any()


def test_seen_counts_only_frames_where_the_query_owns_pixels():
    """Every query keeps a little softmax mass on every pixel; it is "seen" only where it owns
    (p > 0.5) a mask-sized region, so a query of an object out of view is not counted."""
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    h, w = 12, 16
    K = torch.tensor([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05, torch.randn(30, 3) * 0.05 + 5.0], 4)
    field = PanopticField(5, [ClassInfo(1, "box", True)], InstanceQueries(feat, mean, cov),
                          PanopticConfig(feat_dim=4, spawn=False))
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[3:9, 4:12] = 7

    def render(idx, blocks, topk):   # query 0 owns the box; query 1 has 0.1 everywhere
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        img = torch.zeros(h, w, feats.shape[1])
        img[..., 0] = 0.05
        img[3:9, 4:12, 0] = 0.9
        img[..., 1] = 0.1
        return SimpleNamespace(features=img + feats.sum() * 0, alpha=torch.ones(h, w))

    for _ in range(3):
        field.losses(render, torch.zeros(5, 3), torch.arange(5), inst, torch.where(inst > 0, 1, 0),
                     K, torch.eye(4), w, h)
    assert field.visible.tolist() == [3.0, 0.0]
    assert field.matched.tolist() == [3.0, 0.0]


@pytest.mark.parametrize("w_class, winner", [(0.0, 0), (1.0, 1)])
def test_class_term_of_the_matching_cost(w_class, winner):
    """Two queries overlap a bottle mask; query 0 overlaps it a little better but renders as box,
    query 1 renders as bottle. Dice + BCE alone picks query 0; the class term picks query 1."""
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    h, w = 12, 16
    K = torch.tensor([[10.0, 0, 8], [0, 10.0, 6], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05, torch.randn(30, 3) * 0.05 + 5.0], 4)
    classes = [ClassInfo(1, "box", True), ClassInfo(2, "bottle", True)]
    field = PanopticField(5, classes, InstanceQueries(feat, mean, cov),
                          PanopticConfig(feat_dim=4, spawn=False, w_class=w_class))
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[3:9, 4:12] = 7
    sem = torch.where(inst > 0, 2, 0)

    def render(idx, blocks, topk):
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        img = torch.full((h, w, feats.shape[1]), 0.02)
        img[3:9, 3:11, 0] = 0.9          # query 0: 7 of the mask's 8 columns, one outside
        img[3:9, 6:12, 1] = 0.9          # query 1: 6 of 8 columns, none outside
        img[..., 2] = torch.where(torch.arange(w) < 9, 4.0, -4.0)    # box logit left,
        img[..., 3] = -img[..., 2]                                  # bottle logit right
        return SimpleNamespace(features=img + feats.sum() * 0, alpha=torch.ones(h, w))

    field.losses(render, torch.zeros(5, 3), torch.arange(5), inst, sem, K, torch.eye(4), w, h)
    assert field.matched.tolist() == [1.0 - winner, float(winner)]


def test_queries_matched_apart_are_not_duplicates():
    # a bottle's query (10 surfels) lies inside the 3D mask of the shelf it stands on (100 surfels)
    masks = torch.zeros(100, 2, dtype=torch.bool)
    masks[:10, 0] = True
    masks[:, 1] = True
    assert duplicate_queries(masks, 0.6).tolist() == [True, False]
    distinct = torch.tensor([[False, True], [True, False]])
    assert duplicate_queries(masks, 0.6, distinct).tolist() == [False, False]


def test_field_counts_frames_where_two_queries_match_different_masks():
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    # two surfels at x = -1 and x = +1, two queries centred on them; a frame whose two masks are
    # the two surfels' pixels matches both queries: comatched counts it, and once it reaches
    # distinct_frames the smaller query is no longer dropped as a duplicate of the larger
    feat = torch.eye(2, 4)
    q = InstanceQueries(feat, torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]]),
                        torch.eye(3).expand(2, 3, 3) * 0.3, temperature=0.1)
    classes = [{"id": 1, "name": "thing", "isthing": True}]
    f = PanopticField(2, classes, q, PanopticConfig(feat_dim=4, topk=2, distinct_frames=2))
    with torch.no_grad():
        f.instance.copy_(5 * feat)
    means = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]])
    inst = torch.tensor([[1, 2]])

    def render(idx, blocks, topk):              # one pixel per surfel, fully opaque
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        from types import SimpleNamespace

        return SimpleNamespace(features=feats.unsqueeze(0), alpha=torch.ones(1, 2))

    for _ in range(2):
        f.losses(render, means, torch.arange(2), inst, None, torch.eye(3), torch.eye(4), 2, 1)
    assert f.comatched[0, 1] == 2 and f.comatched[1, 0] == 2
    # mask_affinity 0 puts every surfel in both 3D masks (IoM 1): only the co-match evidence keeps both
    f.cfg.mask_affinity = -1.0
    f.steps = f.born.max() + f.cfg.query_grace
    f.matched[:] = 5
    f.visible[:] = 5
    assert f.adjust(means) == 0
    f.comatched.zero_()
    assert f.adjust(means) == 1


@pytest.mark.parametrize("feature, drawn, counted", [((0.0, 0.6), 0.81, 1), ((0.5, 0.16), 0.30, 0)])
def test_a_co_match_counts_only_when_both_queries_draw_their_masks(feature, drawn, counted):
    # two queries over two one-pixel masks: query 0 draws mask 1 (p ~1), query 1 is matched to mask
    # 2, which it draws at p 0.81 or 0.30 (the rest goes to query 0). Only the first frame is
    # evidence that the two are different objects: the assignment also hands a leftover mask to a
    # query that hardly draws it (a bottle's split-off query at p 0.02-0.05 on the tabletop, whose
    # "distinct" pair was never dropped as a fragment)
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    q = InstanceQueries(torch.eye(2, 4), torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3).clone(),
                        temperature=0.1)
    f = PanopticField(2, [{"id": 1, "name": "thing", "isthing": True}], q,
                      PanopticConfig(feat_dim=4, topk=2))
    with torch.no_grad():
        f.instance.zero_()
        f.instance[0, 0] = 5.0
        f.instance[1, :2] = torch.tensor(feature)
    means = torch.tensor([[-0.1, 0, 0], [0.1, 0, 0]])

    def render(idx, blocks, topk):              # one pixel per surfel, fully opaque
        from types import SimpleNamespace

        return SimpleNamespace(features=torch.cat(blocks, -1).unsqueeze(0), alpha=torch.ones(1, 2))

    with torch.no_grad():
        p = q.distribution(f.instance, means)
    assert float(p[1, 1]) == pytest.approx(drawn, abs=0.01)
    f.losses(render, means, torch.arange(2), torch.tensor([[1, 2]]), None, torch.eye(3), torch.eye(4), 2, 1)
    assert f.matched.tolist() == [1.0, 1.0]                  # matched either way
    assert f.comatched[0, 1] == counted and f.comatched[1, 0] == counted


def test_smooth_instances_fixes_border_flips_and_keeps_small_objects():
    from psimap.panoptic.field import smooth_instances

    g = torch.stack(torch.meshgrid(torch.arange(20.0), torch.arange(10.0), indexing="ij"), -1).reshape(-1, 2)
    means = torch.cat([g * 0.01, torch.zeros(len(g), 1)], 1)           # 20 x 10 grid, 1 cm apart
    truth = torch.where(means[:, 0] < 0.095, 1, 2)                     # two objects touching at x ~ 0.1
    small = (means[:, 0] > 0.165) & (means[:, 1] < 0.025)              # a 3 x 3 object in a corner
    truth[small] = 3
    noisy = truth.clone()
    # isolated flips 1 <-> 2 one row in from the boundary (on the boundary itself a surfel's
    # neighbours are split evenly and no majority can say which side is right)
    near = torch.nonzero(((means[:, 0] - 0.095).abs() - 0.015).abs() < 1e-4).flatten()[::3]
    border = near[truth[near] < 3]
    noisy[border] = 3 - noisy[border]
    lone = torch.tensor([[5.0, 5.0, 5.0]])                              # far from everything
    means = torch.cat([means, lone])
    noisy = torch.cat([noisy, torch.tensor([4])])
    truth = torch.cat([truth, torch.tensor([4])])
    thing = torch.ones(len(noisy), dtype=torch.bool)
    assert int((noisy != truth).sum()) >= 5
    out = smooth_instances(means, noisy, thing, 8)
    assert torch.equal(out, truth)
    # surfels that are not things neither vote nor change
    thing[:5] = False
    out = smooth_instances(means, noisy, thing, 8)
    assert torch.equal(out[:5], noisy[:5])


def test_fuse_classes_gives_border_surfels_to_the_instance_their_semantics_name():
    from psimap.panoptic.field import fuse_classes

    # surfels 0-5: a table (class column 0), 6-9: a mug (column 1). The instance head gives mug
    # surfels 8, 9 to the table's query by a small margin; their semantics say "mug" clearly.
    logits = torch.zeros(10, 3)
    logits[:6, 0] = 5.0
    logits[6:8, 1] = 5.0
    logits[8:, 0], logits[8:, 1] = 1.0, 0.5
    logits[:, 2] = -1.0                                  # query 2 owns nothing
    semantic = torch.zeros(10, 2)
    semantic[:6, 0] = 4.0
    semantic[6:, 1] = 4.0
    thing = torch.ones(10, dtype=torch.bool)
    owner = logits.argmax(-1)
    assert owner[8:].tolist() == [0, 0]
    fused = fuse_classes(logits, semantic, owner, thing)
    assert fused.tolist() == [0] * 6 + [1] * 4
    # the semantic head does not override a confident instance head
    semantic[0] = torch.tensor([0.0, 1.0])
    assert int(fuse_classes(logits, semantic, owner, thing)[0]) == 0
    # surfels that are not things keep their owner
    thing[8] = False
    assert int(fuse_classes(logits, semantic, owner, thing)[8]) == 0


def test_spawned_query_starts_from_its_surfels_features_and_wins_them():
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    # a shelf's query (feature 3 e0, wide Gaussian at the origin) and a bottle at x = 0.3 m whose
    # surfels were trained toward the shelf's feature (no bottle query existed yet)
    g = torch.Generator().manual_seed(0)
    shelf = torch.rand(50, 3, generator=g) - 0.5
    bottle = torch.tensor([0.3, 0.0, 0.0]) + 0.01 * torch.randn(6, 3, generator=g)
    pos = torch.cat([shelf, bottle])
    feat = torch.zeros(56, 4)
    feat[:, 0] = 3.0
    q = InstanceQueries(torch.tensor([[3.0, 0, 0, 0]]), torch.zeros(1, 3), torch.eye(3).unsqueeze(0) * 0.09,
                        temperature=0.1)
    f = PanopticField(56, [{"id": 1, "name": "thing", "isthing": True}], q, PanopticConfig(feat_dim=4))
    pts = bottle + 0.002                                    # the bottle mask's back-projected pixels
    start = f._spawn_feature(pts, pos, feat)
    assert torch.allclose(start, torch.tensor([3.0, 0, 0, 0]), atol=1e-5)
    # the features of the surfels nearest the mask's points, not of others: the bottle's surfels
    # told apart (feature e1), half the mask's points on the shelf's nearest corner (feature e0 + e2)
    told = feat.clone()
    told[50:] = torch.tensor([0.0, 1.0, 0, 0])
    corner = int((shelf - torch.tensor([0.5, 0.5, 0.5])).norm(dim=-1).argmin())
    told[corner] = torch.tensor([1.0, 0, 1.0, 0])
    both = torch.cat([pts, shelf[corner] + 0.001 * torch.randn(len(pts), 3, generator=g)])
    mixed = f._spawn_feature(both, pos, told)
    assert torch.allclose(mixed, torch.tensor([1.0, 1.0, 1.0, 0]) / 3 ** 0.5 * 3.0, atol=1e-5), mixed
    for spawn_feat, bottle_owner in ((start, 1), (torch.tensor([0.0, 3.0, 0, 0]), 0)):
        f2 = PanopticField(56, [{"id": 1, "name": "thing", "isthing": True}],
                           InstanceQueries(q.feature.detach(), q.mean.detach(), q.cov().detach(), temperature=0.1),
                           PanopticConfig(feat_dim=4))
        f2._pending = [(pts, spawn_feat)]
        f2._spawn_pending()
        assert f2.queries.count == 2
        own = f2.queries.distribution(feat, pos).argmax(-1)
        assert (own[50:] == bottle_owner).all(), (spawn_feat, own[50:])
        assert (own[:50] == 0).float().mean() > 0.9


@pytest.mark.parametrize("query_class, mug_class", [(True, 2), (False, 1)])
def test_instance_class_comes_from_the_masks_its_query_matched(query_class, mug_class):
    from types import SimpleNamespace

    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    # two surfels, one pixel each: a table (class 1) and a mug (class 2) whose surfel semantics
    # were dragged to "table" (merged masks); the mug's query is matched to "mug" masks
    classes = [{"id": 1, "name": "table", "isthing": True}, {"id": 2, "name": "mug", "isthing": True}]
    feat = torch.eye(2, 4)
    q = InstanceQueries(feat, torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]]), torch.eye(3).expand(2, 3, 3) * 0.3,
                        temperature=0.1)
    cfg = PanopticConfig(feat_dim=4, topk=2, min_instance_surfels=1, query_class=query_class)
    f = PanopticField(2, classes, q, cfg)
    with torch.no_grad():
        f.instance.copy_(5 * feat)
        f.semantic.copy_(torch.tensor([[3.0, 0.0], [3.0, 0.0]]))
    means = torch.tensor([[-1.0, 0, 0], [1.0, 0, 0]])

    def render(idx, blocks, topk):
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        return SimpleNamespace(features=feats.unsqueeze(0), alpha=torch.ones(1, 2))

    for _ in range(3):
        f.losses(render, means, torch.arange(2), torch.tensor([[1, 2]]), torch.tensor([[1, 2]]),
                 torch.eye(3), torch.eye(4), 2, 1)
    lab = f.assign(means)
    mug = int(lab["instance_id"][1])
    assert mug > 0 and lab["instance_class"][mug] == mug_class
    assert int(lab["semantic_id"][1]) == mug_class
    assert lab["instance_class"][int(lab["instance_id"][0])] == 1


@pytest.mark.parametrize("trim", [True, False])
def test_query_gaussian_ignores_mask_pixels_that_bleed_onto_the_wall_behind(trim):
    from psimap.data.frames import ClassInfo, Frame
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import backproject, init_queries

    # a 6x6 px box 1.5 m away in front of a wall at 3 m; the noisy 2D mask is the box dilated by
    # 1 px, so 28 of its 64 pixels see the wall
    h, w = 30, 40
    K = np.array([[30.0, 0, 20], [0, 30.0, 15], [0, 0, 1]])
    depth = np.full((h, w), 3.0, np.float32)
    depth[12:18, 17:23] = 1.5
    inst = np.zeros((h, w), np.uint16)
    inst[11:19, 16:24] = 4
    fr = Frame(rgb=np.zeros((h, w, 3), np.float32), depth=depth, K=K, c2w=np.eye(4),
               semantic=np.where(inst > 0, 2, 0).astype(np.uint16), instance=inst, name="f0")
    pts = backproject(torch.as_tensor(depth), torch.as_tensor(K), torch.eye(4, dtype=torch.float64),
                      torch.as_tensor(inst > 0), trim=trim)
    if not trim:                      # without trimming the wall pixels drag the Gaussian 0.6 m back
        assert pts.shape[0] == 64 and float(pts[:, 2].mean()) > 2.0
        return
    assert pts.shape[0] == 36 and torch.allclose(pts[:, 2], torch.tensor(1.5))
    q = init_queries([fr], [ClassInfo(2, "box", True)], PanopticConfig(init_frames=1), scene_scale=4.0)
    assert q.count == 1
    assert abs(float(q.mean.detach()[0, 2]) - 1.5) < 0.01
    sigma = torch.linalg.eigvalsh(q.cov()[0].detach().double()).sqrt()
    # the box is 0.3 m wide: its own spread only (std 0.087 m, inflated x sqrt 2 to cover unseen sides)
    assert float(sigma.max()) < 0.15, sigma


def test_front_layer_keeps_a_slanted_surface_and_drops_the_background():
    from psimap.panoptic.field import front_layer

    z = torch.cat([torch.linspace(1.4, 3.7, 200, dtype=torch.float64),   # a table seen obliquely
                   torch.full((20,), 6.0, dtype=torch.float64)])         # bleed onto the far wall
    keep = front_layer(z)
    assert bool(keep[:200].all()) and not bool(keep[200:].any())
    assert bool(front_layer(torch.full((5,), 2.0, dtype=torch.float64)).all())


def test_small_mask_is_matched_to_the_query_that_draws_it_despite_diffuse_tails():
    from psimap.panoptic.matching import mask_windows

    # a 160x120 frame: a shelf mask (rows 40-99) and a 2x3 px bottle mask in front of it. Query 0
    # draws the shelf, query 1 the bottle (0.6 on its pixels); every query also keeps the softmax's
    # diffuse tail of 0.03 on every pixel (~580 summed over the frame)
    h, w = 120, 160
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[40:100, 20:140] = 1
    inst[60:62, 70:73] = 2
    masks, _ = masks_from_ids(inst)
    target = masks.flatten(1).float()
    prob = torch.full((3, h * w), 0.03)
    prob[0, target[0] > 0] = 0.6
    prob[0, target[1] > 0] = 0.3          # the shelf's query holds part of the bottle too
    prob[1, target[1] > 0] = 0.6
    window = mask_windows(masks).flatten(1).float()
    assert int(window[1].sum()) == (2 * 3) * (3 * 3)          # 3x the box per axis
    whole = hungarian_match(prob, target)
    assert dict(zip(whole.query_idx.tolist(), whole.mask_idx.tolist())) == {0: 0}   # bottle rejected
    local = hungarian_match(prob, target, window=window)
    assert dict(zip(local.query_idx.tolist(), local.mask_idx.tolist())) == {0: 0, 1: 1}
    # without its own query, neither the shelf's query (as strong around the bottle as on it) nor
    # a query with only the tail may take the bottle's mask
    alone = hungarian_match(prob[[2, 0]], target[[1]], window=window[[1]])
    assert alone.query_idx.numel() == 0
    # the windowed loss of the matched bottle is far from saturated: it can teach the query
    p = prob.clone().requires_grad_(True)
    loss = matched_mask_loss(p, target, local, window=window)
    loss.backward()
    assert float(p.grad[1, target[1] > 0].mean()) < -0.05


@pytest.mark.parametrize("split, piece_class, spawned", [(True, 1, 0), (True, 2, 1), (False, 1, 1)])
def test_second_piece_of_a_split_mask_spawns_no_query(split, piece_class, spawned):
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    # one query draws a box; the 2D model split the box's mask in two (ids 5 and 6). The second
    # piece is the same object (no new query) unless its class differs (a bottle on the box)
    h, w = 16, 20
    K = torch.tensor([[10.0, 0, 10], [0, 10.0, 8], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05 + torch.tensor([0.0, 0.0, 1.0])], 4)
    classes = [ClassInfo(1, "box", True), ClassInfo(2, "bottle", True)]
    field = PanopticField(5, classes, InstanceQueries(feat, mean, cov),
                          PanopticConfig(feat_dim=4, spawn_split=split))
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[4:12, 3:11] = 5
    inst[5:8, 12:15] = 6
    sem = torch.where(inst == 5, 1, torch.where(inst == 6, piece_class, 0))
    drawn = (inst > 0).float()

    def render(idx, blocks, topk):
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        img = torch.zeros(h, w, feats.shape[1])
        img[..., 0] = 0.9 * drawn
        return SimpleNamespace(features=feats.sum() * 0 + img, alpha=torch.ones(h, w))

    args = (render, torch.zeros(5, 3), torch.arange(5), inst, sem, K, torch.eye(4), w, h)
    l_ins, l_sem, info = field.losses(*args, depth=torch.ones(h, w))
    assert info["masks"] == 2 and info["matched"] == 1
    (l_ins + l_sem).backward()
    field.step()
    assert field.queries.count == 1 + spawned


def _two_query_field(**cfg):
    """Two converged queries on two 20-surfel clusters at (-1, -1, -1) and (1, 1, 1), 120 steps old."""
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    means = torch.cat([torch.full((20, 3), -1.0), torch.full((20, 3), 1.0)]) + 0.01 * torch.randn(40, 3)
    feat = torch.tensor([[3.0, 0, 0, 0], [0, 3.0, 0, 0]])
    q = InstanceQueries(feat, torch.tensor([[-1.0] * 3, [1.0] * 3]), torch.eye(3).repeat(2, 1, 1) * 0.04)
    f = PanopticField(40, [{"id": 1, "name": "thing", "isthing": True}], q, PanopticConfig(feat_dim=4, **cfg))
    with torch.no_grad():
        f.instance[:20] = feat[0]
        f.instance[20:] = feat[1]
    f.steps = 120
    return f, means


@pytest.mark.parametrize("comatched, dropped", [(0.0, 1), (12.0, 0)])
def test_queries_matched_to_different_masks_are_not_fragments(comatched, dropped):
    # a shelf's query (0) and a mug's (1): the 2D model merged the two in 6 frames that saw both
    # owning pixels, and the mug's few pixels were never "seen" apart; but in 12 frames the two
    # were matched to different masks. Those frames count as apart: both queries stay
    f, means = _two_query_field(distinct_frames=0)
    f.matched = torch.tensor([30.0, 20.0])
    f.visible = torch.tensor([30.0, 25.0])
    f.same = torch.tensor([[0.0, 6.0], [6.0, 0.0]])
    f.comatched = torch.tensor([[30.0, comatched], [comatched, 20.0]])
    assert f.adjust(means) == dropped
    assert f.queries.count == 2 - dropped


def test_rarely_matched_query_is_useless_by_default():
    # query 1 sat on a cabinet's border: seen in 53 frames, matched in 8 (a real object's query is
    # matched in most frames that see it); the default rate drops it, the cabinet's query stays
    f, means = _two_query_field()
    f.matched = torch.tensor([138.0, 8.0])
    f.visible = torch.tensor([154.0, 53.0])
    assert f.adjust(means) == 1
    assert torch.allclose(f.queries.mean.detach()[0], torch.full((3,), -1.0))


def test_a_spawned_query_gets_the_seed_queries_grace_before_it_is_judged():
    # query 1 was spawned at step 100 for a small object and has not been matched yet (its few
    # frames not drawn): at the adjustment 40 steps later (adjust_every) the drop rules must leave
    # it alone, as the seed queries were left alone for their first adjust_start (60) steps
    f, means = _two_query_field(adjust_start=60, adjust_every=40)
    f.matched = torch.tensor([50.0, 0.0])
    f.visible = torch.tensor([60.0, 4.0])
    f.born = torch.tensor([0.0, 100.0])
    assert f.cfg.query_grace == 60
    f.steps = 140
    assert f.adjust(means) == 0 and f.queries.count == 2
    f.steps = 180                                   # 80 steps old and still never matched: useless
    assert f.adjust(means) == 1 and f.queries.count == 1
    from psimap.panoptic.config import PanopticConfig

    assert PanopticConfig(adjust_start=30, adjust_every=40).query_grace == 40   # at least one period


@pytest.mark.parametrize("step_sigma", [0.1, 0.0])
def test_a_small_querys_centre_moves_in_steps_of_its_own_size(step_sigma):
    # Adam moves a parameter ~lr a step whatever its gradient: a mug's query (sigma 3 cm) pushed by
    # a few pixels of one frame drifted as far as a shelf's (sigma 30 cm), two of its own sigmas
    # in 25 steps, and lost its mug. Its centre (and the off-diagonal of its Cholesky factor, in
    # metres too) now moves lr x sigma / query_step_sigma; the large query's lr as before
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    cov = torch.stack([torch.eye(3) * 0.3 ** 2, torch.eye(3) * 0.03 ** 2])
    q = InstanceQueries(torch.eye(2, 4), torch.zeros(2, 3), cov)
    f = PanopticField(8, [{"id": 1, "name": "thing", "isthing": True}], q,
                      PanopticConfig(feat_dim=4, lr_query=0.01, query_step_sigma=step_sigma))
    f.zero_grad()
    for p in q.parameters():
        p.grad = torch.zeros_like(p)
    q.mean.grad = torch.ones(2, 3)
    q.offdiag.grad = torch.ones(2, 3)
    q.log_diag.grad = torch.ones(2, 3)
    log_before = q.log_diag.detach().clone()
    f.step()
    moved = -q.mean.detach()[:, 0]                  # Adam's first step: lr x sign(gradient)
    bent = -q.offdiag.detach()[:, 0]
    assert moved[0] == pytest.approx(0.01, rel=1e-3) and bent[0] == pytest.approx(0.01, rel=1e-3)
    small = 0.01 * (0.03 / step_sigma if step_sigma > 0 else 1.0)
    assert moved[1] == pytest.approx(small, rel=1e-3) and bent[1] == pytest.approx(small, rel=1e-3)
    # the log axes are scale-free: every query's take Adam's step
    assert torch.allclose(log_before - q.log_diag.detach(), torch.full((2, 3), 0.01), rtol=1e-3)


def test_seen_on_sampled_pixels_scales_the_mask_size():
    """A frame larger than pixels_per_step is read at a sample of its pixels (a frozen blend renders
    only those): "seen" then asks for the sample's share of min_mask_fraction, so a query owning 5/3
    of the smallest mask is seen and one owning half of it is not, as on the whole frame."""
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    h, w = 40, 60                                     # 2400 px, 600 sampled, smallest mask 120 px
    K = torch.tensor([[30.0, 0, 30], [0, 30.0, 20], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05, torch.randn(30, 3) * 0.05 + 5.0], 4)
    # single random pixels: the sample's share of a mask is then its share of the frame, every step
    cfg = PanopticConfig(feat_dim=4, spawn=False, pixels_per_step=600, sample_tile=0, min_mask_fraction=0.05)
    field = PanopticField(5, [ClassInfo(1, "box", True)], InstanceQueries(feat, mean, cov), cfg)
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[5:15, 5:25] = 7                              # 200 px: ~50 sampled, fewer than 120

    def render(idx, blocks, topk):
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        img = torch.zeros(h, w, feats.shape[1])
        img[5:15, 5:25, 0] = 0.9                      # query 0 owns the box
        img[30:36, 40:50, 1] = 0.9                    # query 1 owns 60 px elsewhere
        return SimpleNamespace(features=img + feats.sum() * 0, alpha=torch.ones(h, w))

    g = torch.Generator().manual_seed(0)
    for _ in range(4):
        field.losses(render, torch.zeros(5, 3), torch.arange(5), inst, torch.where(inst > 0, 1, 0),
                     K, torch.eye(4), w, h, generator=g)
    assert field.visible.tolist() == [4.0, 0.0]
    assert field.matched.tolist() == [4.0, 0.0]


def test_tiles_cover_the_image_once_and_the_sample_holds_every_seed_tile():
    """sample_pixels with tiles: whole tiles (edge tiles cut at the border), every seed pixel's
    tile, ~n pixels, ascending and distinct; single pixels with tile 0; None when n covers the image."""
    from psimap.panoptic.field import pixel_tiles, sample_pixels

    w, h, t = 50, 37, 8                                    # edge tiles on both axes
    of = pixel_tiles(w, h, t)
    assert of.shape == (w * h,) and int(of.max()) == 7 * 5 - 1
    sizes = torch.bincount(of, minlength=35).view(5, 7)
    assert bool((sizes[:4, :6] == 64).all()) and int(sizes[4, 6]) == 2 * 5   # inner tiles whole, corner cut
    assert int(of[8]) == 1 and int(of[8 * w]) == 7 and int(of[8 * w - 1]) == 6   # row-major tiles
    g = torch.Generator().manual_seed(0)
    seeds = torch.tensor([0, 49 + 36 * w, 20 + 10 * w])                      # corner, far corner, middle
    pix = sample_pixels(w, h, 600, t, g, seeds)
    assert torch.equal(pix, pix.unique())                                   # ascending, distinct
    for sd in seeds.tolist():                                               # the seed's whole tile
        assert bool(torch.isin(torch.nonzero(of == of[sd]).flatten(), pix).all())
    ids = of[pix].unique()                                                  # 600 // 64 = 9 whole tiles
    assert ids.numel() == 9
    assert pix.numel() == int(torch.isin(of, ids).sum()) <= 600
    many = sample_pixels(w, h, 100, t, g, torch.arange(0, w * h, 97))       # more seed tiles than n
    assert many.numel() > 100
    single = sample_pixels(w, h, 600, 0, torch.Generator().manual_seed(1))
    assert single.numel() == 600 and torch.equal(single, torch.randperm(w * h, generator=torch.Generator().manual_seed(1))[:600])
    assert sample_pixels(w, h, w * h, t, g) is None


@pytest.mark.parametrize("tile", [8, 0])
def test_every_mask_is_read_every_step_when_pixels_are_tiles(tile):
    """A 9 px mask in a 60 x 40 frame read at 120 pixels a step: tiles seeded by a pixel of every
    mask read it at every step (its query seen and matched 6 of 6); 120 single random pixels read
    ~0.5 of its 9 and leave it unread at most steps (its query not seen there)."""
    from types import SimpleNamespace

    from psimap.data.frames import ClassInfo
    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField

    h, w = 40, 60
    K = torch.tensor([[30.0, 0, 30], [0, 30.0, 20], [0, 0, 1]])
    feat, mean, cov = init_from_points([torch.randn(30, 3) * 0.05, torch.randn(30, 3) * 0.05 + 5.0], 4)
    cfg = PanopticConfig(feat_dim=4, spawn=False, pixels_per_step=120, sample_tile=tile, min_mask_fraction=0.001)
    field = PanopticField(5, [ClassInfo(1, "box", True)], InstanceQueries(feat, mean, cov), cfg)
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[17:20, 25:28] = 7                            # 9 px inside the 8 x 8 tile (16..23, 24..31)

    def render(idx, blocks, topk):
        feats = torch.cat(blocks, -1)      # losses renders [instance, class] blocks side by side
        img = torch.zeros(h, w, feats.shape[1])
        img[17:20, 25:28, 0] = 0.9                    # query 0 owns the mask
        return SimpleNamespace(features=img + feats.sum() * 0, alpha=torch.ones(h, w))

    g = torch.Generator().manual_seed(0)
    for _ in range(6):
        field.losses(render, torch.zeros(5, 3), torch.arange(5), inst, torch.where(inst > 0, 1, 0),
                     K, torch.eye(4), w, h, generator=g)
    if tile:
        assert field.visible.tolist() == [6.0, 0.0] and field.matched.tolist() == [6.0, 0.0]
    else:
        assert field.visible[0] < 6


def test_match_costs_equal_the_readable_dice_and_bce_costs():
    """hungarian_match's one-product costs (match_costs, over the windows' pixels only) equal
    dice_cost / bce_cost and the ring means written out, with windows and without."""
    from psimap.panoptic.matching import bce_cost, dice_cost, mask_windows, match_costs

    g = torch.Generator().manual_seed(3)
    h, w = 30, 40
    inst = torch.zeros(h, w, dtype=torch.long)
    inst[2:8, 3:9] = 1
    inst[20:24, 30:33] = 2
    inst[10:14, 12:30] = 3
    masks, _ = masks_from_ids(inst)
    t = masks.flatten(1).float()
    win = torch.maximum(mask_windows(masks).flatten(1).float(), t)
    assert float(win.any(0).float().mean()) < 0.8            # some pixels lie in no window
    p = torch.rand(5, h * w, generator=g).clamp(1e-6, 1 - 1e-6)
    full = match_costs(p, t)
    torch.testing.assert_close(full["dice"], dice_cost(p, t), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(full["bce"], bce_cost(torch.logit(p), t), rtol=1e-5, atol=1e-5)
    local = match_costs(p, t, win)
    torch.testing.assert_close(local["dice"], dice_cost(p, t, window=win), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(local["bce"], bce_cost(torch.logit(p), t, window=win), rtol=1e-5, atol=1e-5)
    inter = p @ t.T
    ring = (p @ win.T - inter) / (win - t).sum(-1).unsqueeze(0)
    torch.testing.assert_close(local["on_mask"], inter / t.sum(-1).unsqueeze(0), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(local["on_ring"], ring, rtol=1e-5, atol=1e-6)


def test_affinity_is_the_written_out_formula_and_stays_normal_far_away():
    """A(q, g) = sigmoid(f_q . f_g) exp(-m^2 / 2) wherever exp(-m^2 / 2) is a normal float32 (m^2 up
    to 160, relative 1e-5: a capped distance there would be off by orders of magnitude); farther,
    its exponential stays exp(-80), a normal float (subnormal floats take a slow path on x86)."""
    g = torch.Generator().manual_seed(2)
    queries = InstanceQueries(torch.randn(3, 8, generator=g), torch.zeros(3, 3),
                              torch.eye(3).expand(3, 3, 3) * torch.tensor([0.01, 0.04, 0.09]).view(3, 1, 1))
    d = torch.linspace(0.0, 2.0, 400)                                  # metres along x from the queries
    pts = torch.stack([d, torch.zeros_like(d), torch.zeros_like(d)], -1)
    feat = torch.randn(400, 8, generator=g)
    a = queries.affinity(feat, pts).detach()
    m2 = queries.mahalanobis2_reference(pts).detach().double()
    written = torch.sigmoid(feat.double() @ queries.feature.detach().double().T) * torch.exp(-0.5 * m2)
    near = m2 < 159.0
    assert int(near.sum()) > 300 and int((~near).sum()) > 100 and float(m2[near].max()) > 150
    torch.testing.assert_close(a.double()[near], written[near], rtol=1e-4, atol=0.0)
    sim = torch.sigmoid(feat.double() @ queries.feature.detach().double().T)
    far = m2 > 161.0
    torch.testing.assert_close(a.double()[far], sim[far] * math.exp(-80.0), rtol=1e-4, atol=0.0)


def test_mahalanobis_product_form_matches_the_readable_one_far_from_small_queries():
    """mahalanobis2 (quadratic monomials x coefficients, float64) gives the per-query triangular
    solve's values and gradients, for 1 cm queries seen from 6 m away as for near points."""
    g = torch.Generator().manual_seed(1)
    q = 6
    size = torch.tensor([0.01, 0.01, 0.01, 0.3, 0.3, 0.3]).view(q, 1, 1)     # three 1 cm queries
    a = torch.randn(q, 3, 3, generator=g) * size
    cov = a @ a.transpose(-1, -2) + 1e-6 * torch.eye(3)
    mean = torch.randn(q, 3, generator=g) + torch.tensor([5.0, -2.0, 1.0])
    queries = InstanceQueries(torch.randn(q, 8, generator=g), mean, cov)
    near = mean[torch.randint(0, q, (200,), generator=g)] + 0.02 * torch.randn(200, 3, generator=g)
    far = torch.randn(300, 3, generator=g) * 2.0 - 1.0
    pts = torch.cat([near, far])
    fast, slow = queries.mahalanobis2(pts), queries.mahalanobis2_reference(pts)
    small = slow < 50                                          # where exp(-m^2 / 2) is not ~0
    assert int(small.sum()) > 100
    torch.testing.assert_close(fast[small], slow[small], rtol=1e-4, atol=1e-4)
    assert bool((fast[~small] > 45).all())
    params = [queries.mean, queries.log_diag, queries.offdiag]
    w = torch.exp(-0.5 * slow.detach())                        # weigh the pairs the affinity reads
    g_fast = torch.autograd.grad((fast * w).sum(), params)
    g_slow = torch.autograd.grad((queries.mahalanobis2_reference(pts) * w).sum(), params)
    for x, y in zip(g_fast, g_slow):
        torch.testing.assert_close(x, y, rtol=1e-3, atol=1e-3 * float(y.abs().max()))


@pytest.mark.parametrize("cols", [3, 11, 15, 16, 40])
def test_softmax_last_is_the_softmax_over_the_last_dim(cols):
    from psimap.panoptic.queries import softmax_last

    g = torch.Generator().manual_seed(cols)
    x = (torch.randn(257, cols, generator=g) * 4).requires_grad_(True)
    up = torch.randn(257, cols, generator=g)
    for log, ref in ((False, torch.softmax), (True, torch.log_softmax)):
        a = softmax_last(x, log=log)
        b = ref(x, -1)
        torch.testing.assert_close(a, b)
        ga, = torch.autograd.grad((a * up).sum(), x)
        gb, = torch.autograd.grad((b * up).sum(), x)
        torch.testing.assert_close(ga, gb)
