"""The panoptic field's warm start: 2D class labels lifted onto the surfels by the views that see them."""
import math

import numpy as np
import torch

from psimap.panoptic.associate import SEEN_DISTANCE, seen_pixels
from psimap.panoptic.lift import lifted_class_votes, vote_logits

W, H = 8, 6
K = torch.tensor([[4.0, 0, 3.5], [0, 4.0, 2.5], [0, 0, 1]])


class _View:
    def __init__(self, depth, viewmat):
        self.depth, self.K, self.viewmat = depth, K, viewmat


def _wall_depth(z=2.0):
    return torch.full((H, W), z)


def _point_at(u, v, z, w2c=torch.eye(4)):
    """World point whose camera coordinates project to pixel (u, v) at depth z."""
    cam = torch.tensor([(u - 3.5) * z / 4.0, (v - 2.5) * z / 4.0, z, 1.0], dtype=torch.float64)
    return (torch.linalg.inv(w2c.double()) @ cam)[:3]


def test_seen_pixels_keep_the_centres_on_the_surface_the_view_sees():
    depth = _wall_depth(2.0)
    depth[0, 0] = 0.0                                             # no depth there
    depth[4, 1] = float("nan")                                    # a broken depth pixel
    pts = torch.stack([
        _point_at(2, 3, 2.0),                                     # 0: on the wall -> pixel 3 * 8 + 2
        _point_at(5, 1, 2.0 + 0.09),                              # 1: within 5 % of 2 m: seen (noise)
        _point_at(5, 1, 2.0 + 0.2),                               # 2: behind the wall: hidden
        _point_at(6, 4, 1.5),                                     # 3: in front of the wall: not what it sees
        _point_at(0, 0, 2.0),                                     # 4: on a pixel without depth
        _point_at(9, 2, 2.0),                                     # 5: right of the image
        torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64),      # 6: behind the camera
        torch.tensor([float("nan"), 0.0, 2.0], dtype=torch.float64),   # 7: not a number
        _point_at(7.4, 5.4, 2.0),                                 # 8: last pixel (rounds to 7, 5)
        _point_at(7.6, 2.0, 2.0),                                 # 9: rounds to column 8: outside
        _point_at(1, 4, 2.0),                                     # 10: on the NaN depth pixel
    ]).float()
    idx, pix = seen_pixels(pts, depth, K, torch.eye(4))
    assert idx.tolist() == [0, 1, 8]
    assert pix.tolist() == [3 * W + 2, 1 * W + 5, 5 * W + 7]
    # the absolute tolerance holds near the camera, where 5 % is less than it
    near = _wall_depth(0.3)
    idx, _ = seen_pixels(torch.stack([_point_at(1, 1, 0.3 + 0.9 * SEEN_DISTANCE),
                                      _point_at(1, 1, 0.3 + 1.1 * SEEN_DISTANCE)]).float(), near, K, torch.eye(4))
    assert idx.tolist() == [0]


def test_seen_pixels_follow_the_view_pose():
    w2c = torch.eye(4)
    w2c[:3, :3] = torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])     # a camera looking along -x
    w2c[:3, 3] = torch.tensor([0.5, -0.2, 1.0])
    pts = torch.stack([_point_at(4, 2, 2.0, w2c), _point_at(4, 2, 2.0)]).float()
    idx, pix = seen_pixels(pts, _wall_depth(2.0), K, w2c)
    assert idx.tolist() == [0] and pix.tolist() == [2 * W + 4]
    empty_idx, empty_pix = seen_pixels(torch.zeros(0, 3), _wall_depth(), K, w2c)
    assert empty_idx.numel() == 0 and empty_pix.numel() == 0


def test_votes_count_the_views_that_see_each_surfel_on_each_class():
    pts = torch.stack([_point_at(1, 1, 2.0), _point_at(6, 4, 2.0), _point_at(3, 3, 2.5)]).float()
    left_wall = torch.full((H * W,), 2, dtype=torch.long)
    left_wall.view(H, W)[:, 4:] = 0
    void = torch.full((H * W,), -1, dtype=torch.long)
    void.view(H, W)[:, :4] = 1
    views = [_View(_wall_depth(2.0), torch.eye(4)), _View(_wall_depth(2.0), torch.eye(4)),
             _View(_wall_depth(2.5), torch.eye(4)), _View(_wall_depth(2.0), torch.eye(4))]
    votes = lifted_class_votes(pts, views, [left_wall, void, left_wall, None], n_classes=4)
    # point 0 (left, 2 m): class 2 in view 0, class 1 in view 1, not on the surface view 2 sees
    # (0.5 m before it), view 3 casts no vote; point 1 (right): class 0 in view 0, void in view 1;
    # point 2 (2.5 m): seen only by view 2, on its left half
    expected = torch.tensor([[0, 1, 1, 0], [1, 0, 0, 0], [0, 0, 1, 0]], dtype=torch.float32)
    assert torch.equal(votes, expected)
    assert lifted_class_votes(pts, views, [left_wall] * 4, n_classes=0).shape == (3, 0)


def test_vote_logits_are_smoothed_log_shares_and_zero_where_no_view_voted():
    votes = torch.tensor([[3.0, 1.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
    logits = vote_logits(votes)
    assert torch.allclose(logits[0], torch.log(torch.tensor([4.0, 2.0, 1.0]) / 7.0))
    assert torch.equal(logits[1], torch.zeros(3))                   # unseen: the uniform start
    assert logits.argmax(-1).tolist() == [0, 0, 2]
    assert math.isclose(float(logits[2, 2] - logits[2, 0]), math.log(11.0), rel_tol=1e-6)
    assert torch.isfinite(logits).all()
    assert vote_logits(torch.zeros(2, 0)).shape == (2, 0)


def test_the_field_starts_from_the_views_majority_class():
    """train_field with the lift: before any step every surfel that some view sees carries its
    majority class (the two-box scene's 2D labels are exact); with lift_semantic False, all zeros."""
    from test_panoptic_field import CLASSES, _two_box_scene

    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import PanopticField, id_to_column
    from psimap.panoptic.fit import lift_semantic_start, view_of

    s, frames, _ = _two_box_scene(n_frames=6)
    views = [view_of(f) for f in frames]
    ids = torch.tensor([c.id for c in CLASSES])
    columns = [id_to_column(ids, v.semantic.reshape(-1)) for v in views]
    votes = lifted_class_votes(s["means"], views, columns, 2)
    seen = votes.sum(-1) > 0
    assert float(seen.float().mean()) > 0.8                      # most surfels are seen by some view
    from psimap.panoptic.queries import InstanceQueries

    q = InstanceQueries(torch.randn(2, 4), torch.zeros(2, 3), torch.eye(3).expand(2, 3, 3).clone())
    field = PanopticField(s["means"].shape[0], CLASSES, q, PanopticConfig(feat_dim=4))
    assert torch.equal(field.semantic.detach(), torch.zeros_like(field.semantic))
    lift_semantic_start(field, s["means"], views)
    start = field.semantic.detach()
    assert torch.equal(start[~seen], torch.zeros_like(start[~seen]))
    assert torch.equal(start[seen].argmax(-1), votes[seen].argmax(-1))
    # the majority is the scene's own class: the boxes' surfels (class id 2) and the floor's (1)
    truth = (s["semantic_id"].long() == 2).long()
    agree = float((start[seen].argmax(-1) == truth[seen]).float().mean())
    assert agree > 0.97, agree


def test_train_field_starts_from_the_lift_unless_told_not_to():
    """The semantic logits train_field returns after 0 steps are the lifted votes' (lift_semantic,
    the default), or the uniform zeros."""
    from test_panoptic_field import CLASSES, _two_box_scene

    from psimap.panoptic.config import PanopticConfig
    from psimap.panoptic.field import id_to_column
    from psimap.panoptic.fit import train_field, view_of

    s, frames, _ = _two_box_scene(n_frames=4)
    views = [view_of(f) for f in frames]
    geometry = (s["means"], s["quats"], s["scales"], s["opacities"], torch.zeros_like(s["means"]))
    ids = torch.tensor([c.id for c in CLASSES])
    expected = vote_logits(lifted_class_votes(s["means"], views, [id_to_column(ids, v.semantic.reshape(-1))
                                                                  for v in views], 2))
    for lift, want in ((None, expected), (False, torch.zeros_like(expected))):
        cfg = PanopticConfig(init_frames=2) if lift is None else PanopticConfig(init_frames=2, lift_semantic=lift)
        state, _ = train_field(views, CLASSES, cfg, lambda: geometry, iters=0, scene_scale=1.2,
                               rng=np.random.default_rng(0), generator=torch.Generator().manual_seed(0))
        assert torch.equal(state["surfels"]["semantic"], want)
