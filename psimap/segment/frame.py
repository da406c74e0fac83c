"""One frame's model-free panoptic pseudo-labels: large planes become stuff, what is left splits into
connected clusters, one instance per cluster (docs/segment.md has the rules and the class table).

Every threshold in metres scales with the sensor's noise at the pixel's range (`Capture.noise`, a
psimap.geometry.depth_noise model) or with the pixel footprint z / f, so one set of defaults serves a
160x120 synthetic scene and a 640x480 Kinect alike. Planes are classified in the gravity frame the
capture-wide pass found (`Capture.up`, `Capture.floor`): orientation says horizontal or vertical,
height above the floor says floor, support or ceiling.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psimap.transforms import PIXEL_CENTER


# The class table written to labels.json: stuff first, then the thing classes by size.
FLOOR, WALL, CEILING, SUPPORT, OBJECT, FURNITURE = 1, 2, 3, 4, 5, 6
CLASS_TABLE = ((FLOOR, "floor", False), (WALL, "wall", False), (CEILING, "ceiling", False),
               (SUPPORT, "support", False), (OBJECT, "object", True), (FURNITURE, "furniture", True))
# A cluster wider or taller than this (m, along up or across it) is `furniture`, not an `object`: a
# chair, a cabinet front, a stool; the export keeps furniture static (exporters.physics.STATIC_CLASSES)
# and weighs it like furniture, so a 2 m cabinet front is not a 400 kg rigid body that tips over.
FURNITURE_EXTENT = 0.6
STUFF_NAMES = {FLOOR: "floor", WALL: "wall", CEILING: "ceiling", SUPPORT: "support"}

# A plane is horizontal / vertical when its normal is within this angle of up / of the horizon:
# tight enough to leave a ramp or a tilted lid alone, loose enough for a noisy Kinect wall.
ORIENTATION_DEGREES = 15.0
# A pixel joins a plane only when its own normal agrees within this angle: the bottom rim of a
# ball or the side of a box standing on the floor lies within the distance threshold but faces
# elsewhere, so it stays with its object.
NORMAL_AGREEMENT_DEGREES = 25.0
# A pixel is over or under a support the capture saw (cut_at_supports) when it is this much (m) plus
# the noise over or under its level: the level is a median over frames, good to about a centimetre.
SUPPORT_LEVEL_MARGIN = 0.01
# What stands on such a support shows pixels on its top within this much (m, plus the margin) over
# its level: the foot of a box or a bottle, seen from over the top.
SUPPORT_CONTACT = 0.05


@dataclass
class SegmentParams:
    """Thresholds of the per-frame segmenter (the CLI's SegmentOptions fill them)."""

    noise_k: float = 3.0              # plane / depth-edge thresholds: this many noise std at the range
    max_planes: int = 8               # RANSAC rounds per frame
    plane_samples: int = 4000         # pixels subsampled for the RANSAC fits
    min_wall_area: float = 0.8        # m^2 of one connected vertical piece for it to be a wall
    min_support_area: float = 0.15    # m^2 of one connected up-facing piece above the floor: a support
    min_stuff_piece: float = 0.01     # m^2: smaller pieces of a stuff plane are left to the objects
    floor_tolerance: float = 0.06     # m above the capture's floor level still counted as floor
    concave_degrees: float = 40.0     # a concave crease sharper than this separates clusters
    colour_edge: float = 0.0          # RGB step (0..1, Euclidean) that separates clusters; 0 = off
    min_object_pixels: int = 0        # smaller clusters are dropped (0 = from the image size)
    slope: float = 4.0                # depth step per pixel footprint a continuous surface may have


def horizontal_basis(up: np.ndarray) -> np.ndarray:
    """[3, 2]: two unit columns perpendicular to `up` [3] and to each other (the ground plane's axes)."""
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(up, a)], 1)


def large_clusters(clusters: np.ndarray, world: np.ndarray, up: np.ndarray, extent: float) -> np.ndarray:
    """Ids [K] of the clusters [H, W] (0 = none) whose points world [H, W, 3] span more than `extent`
    metres along up or along either horizontal axis (2nd..98th percentile, so a few stray pixels at
    a depth edge do not make a cup furniture)."""
    ids = np.unique(clusters[clusters > 0])
    if len(ids) == 0:
        return ids
    basis = np.concatenate([up[:, None], horizontal_basis(up)], 1)      # [3, 3] columns: up, two horizontal
    big = []
    for k in ids:
        p = world[clusters == k]
        p = p[np.isfinite(p).all(1)] @ basis
        if len(p) >= 3 and (np.percentile(p, 98, 0) - np.percentile(p, 2, 0)).max() > extent:
            big.append(k)
    return np.asarray(big, dtype=ids.dtype)


@dataclass
class SupportLevel:
    """A support the capture-wide pass saw from above (a table, counter or cabinet top, a shelf
    board): its height along up and its footprint, a raster of `cell`-metre squares over the ground
    plane (horizontal_basis(up) coordinates: `origin` [2] is the corner of cell [0, 0]; cells [nx, ny]
    are 2 inside the top (a cell in from its edge), 1 on its edge and the rim around it (its front
    face, seen through the noise), 0 off it)."""

    height: float
    origin: np.ndarray
    cell: float
    cells: np.ndarray

    def footprint(self, ground: np.ndarray) -> np.ndarray:
        """[...] int8: 2 where ground-plane points `ground` [..., 2] lie inside the top, 1 on its edge
        or rim, 0 off it."""
        ij = np.floor((ground - self.origin) / self.cell)
        ok = np.isfinite(ij).all(-1) & (ij >= 0).all(-1) & (ij < self.cells.shape).all(-1)
        ij = np.where(ok[..., None], ij, 0).astype(np.int64)
        return np.where(ok, self.cells[ij[..., 0], ij[..., 1]], 0).astype(np.int8)


@dataclass
class Capture:
    """What the capture-wide pass found: up [3] (unit, world), floor height along up (None: no floor
    seen), noise model (z [B], sigma [B]) from depth_noise.estimate_depth_noise, and the supports it
    saw from above (SupportLevel; none: each frame knows only the supports it sees itself)."""

    up: np.ndarray
    floor: float | None
    noise: tuple = field(default_factory=lambda: (np.zeros(0), np.zeros(0)))
    supports: list = field(default_factory=list)


def camera_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points [H, W, 3] of every pixel (invalid pixels: z = 0)."""
    H, W = depth.shape
    v, u = np.mgrid[0:H, 0:W]
    z = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0)
    x = (u + PIXEL_CENTER - K[0, 2]) / K[0, 0] * z
    y = (v + PIXEL_CENTER - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=-1)


def pixel_normals(points: np.ndarray, valid: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame unit normals [H, W, 3] from central differences `step` pixels apart, averaged over
    a (2 step + 1)^2 window and turned to face the camera, and where they are defined [H, W].

    Differences a few pixels apart and the window average the sensor noise a one-pixel difference
    would amplify (a far wall's normals would scatter by tens of degrees)."""
    from scipy import ndimage

    H, W = valid.shape
    s = max(1, int(step))
    n = np.zeros((H, W, 3))
    ok = np.zeros((H, W), bool)
    if H <= 2 * s or W <= 2 * s:
        return n, ok
    dx = points[s:-s, 2 * s:] - points[s:-s, :-2 * s]
    dy = points[2 * s:, s:-s] - points[:-2 * s, s:-s]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1)
    inner = (valid[s:-s, 2 * s:] & valid[s:-s, :-2 * s] & valid[2 * s:, s:-s] & valid[:-2 * s, s:-s]
             & valid[s:-s, s:-s] & (norm > 0))
    c = c / np.where(norm > 0, norm, 1.0)[..., None]
    away = np.einsum("ijk,ijk->ij", c, points[s:-s, s:-s]) > 0      # facing away from the camera
    c[away] *= -1
    n[s:-s, s:-s] = np.where(inner[..., None], c, 0.0)
    ok[s:-s, s:-s] = inner
    size = 2 * s + 1
    n = np.stack([ndimage.uniform_filter(n[..., k], size, mode="constant") for k in range(3)], axis=-1)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0.5                 # the window's normals mostly agree (not a crease or an edge)
    n = n / np.where(norm > 0, norm, 1.0)[..., None]
    return n, ok


def noise_sigma(z: np.ndarray, noise) -> np.ndarray:
    from psimap.geometry.depth_noise import noise_at

    return noise_at(z, noise, floor=1e-3)


def depth_edges(depth: np.ndarray, valid: np.ndarray, sigma: np.ndarray, f: float, params: SegmentParams):
    """[H, W] bool: pixels on either side of a depth step larger than the sensor noise and the step a
    steep but continuous surface makes over one pixel footprint (slope x z / f)."""
    edge = ~valid.copy()
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        za, zb = depth[a], depth[b]
        z = np.minimum(za, zb)
        thr = params.noise_k * np.sqrt(2.0) * np.minimum(sigma[a], sigma[b]) + params.slope * z / f
        jump = valid[a] & valid[b] & (np.abs(za - zb) > thr)
        edge[a] |= jump
        edge[b] |= jump
    return edge


def concave_creases(points: np.ndarray, normals: np.ndarray, nok: np.ndarray, sigma: np.ndarray,
                    params: SegmentParams, step: int) -> np.ndarray:
    """[H, W] bool: pixels where the surface folds inwards by more than `params.concave_degrees` between
    neighbours `step` apart (two things touching, an object against a wall), by more than the noise:
    each point lies off the other's tangent plane by more than noise_k depth-noise std. Convex folds
    (a box's edges) are left alone: they belong to one object."""
    H, W = nok.shape
    out = np.zeros((H, W), bool)
    if params.concave_degrees <= 0:
        return out
    s = max(1, int(step))
    cos_t = np.cos(np.radians(params.concave_degrees))
    for a, b in (((slice(None), slice(s, None)), (slice(None), slice(None, -s))),
                 ((slice(s, None), slice(None)), (slice(None, -s), slice(None)))):
        na, nb = normals[a], normals[b]
        gap = points[a] - points[b]
        both = nok[a] & nok[b]
        bent = np.einsum("ijk,ijk->ij", na, nb) < cos_t
        # concave: the normals converge, (n_a - n_b) . (p_a - p_b) < 0
        off_a = np.einsum("ijk,ijk->ij", na, gap)
        off_b = np.einsum("ijk,ijk->ij", nb, gap)
        concave = (off_a - off_b) < -params.noise_k * np.sqrt(2.0) * np.maximum(sigma[a], sigma[b])
        crease = both & bent & concave
        out[a] |= crease
        out[b] |= crease
    return out


def colour_edges(rgb: np.ndarray | None, threshold: float) -> np.ndarray | None:
    """[H, W] bool: pixels beside an RGB step larger than `threshold` (None when off)."""
    if rgb is None or threshold <= 0:
        return None
    c = np.asarray(rgb, np.float32)
    if c.ndim != 3:
        return None
    out = np.zeros(c.shape[:2], bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        step = np.linalg.norm(c[a] - c[b], axis=-1) > threshold
        out[a] |= step
        out[b] |= step
    return out


def _pixel_area(z: np.ndarray, cos_view: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Surface area (m^2) each pixel covers: its footprint z^2 / (fx fy), stretched by the viewing angle
    (bounded so a grazing pixel does not count as a square metre)."""
    return z * z / (K[0, 0] * K[1, 1]) / np.clip(cos_view, 0.2, 1.0)


def _components(mask: np.ndarray):
    from scipy import ndimage

    lab, n = ndimage.label(mask, structure=np.ones((3, 3), bool))
    return lab, n


def fit_planes(world: np.ndarray, wnormals: np.ndarray, valid: np.ndarray, usable: np.ndarray, sigma: np.ndarray,
               area: np.ndarray, cam_height: float, capture: Capture, params: SegmentParams,
               rng: np.random.Generator) -> tuple[np.ndarray, list[dict]]:
    """Stuff classes [H, W] (0 = not stuff) from planes fitted by RANSAC on a pixel subsample.

    world / wnormals: [H, W, 3] world points and camera-facing world normals; usable: [H, W] pixels
    with both; sigma: [H, W] depth noise std; area: [H, W] m^2 per pixel. Returns the stuff map, the
    class of the stuff plane each pixel lies on by distance alone (normal aside; 0 = none), the height
    of the support each support pixel belongs to (NaN elsewhere) and one dict per plane kept (class,
    height, area)."""
    from scipy import ndimage

    from psimap.geometry.planes import ransac_plane

    H, W = usable.shape
    stuff = np.zeros((H, W), np.uint16)
    on_plane = np.zeros((H, W), np.uint16)
    level = np.full((H, W), np.nan)
    planes: list[dict] = []
    idx = np.flatnonzero(usable.ravel())
    if len(idx) < 50:
        return stuff, on_plane, level, planes
    if len(idx) > params.plane_samples:
        idx = np.sort(rng.choice(idx, params.plane_samples, replace=False))
    pts_all = world.reshape(-1, 3)
    nrm_all = wnormals.reshape(-1, 3)
    sig_all = sigma.ravel()
    up = capture.up
    cos_h = np.cos(np.radians(ORIENTATION_DEGREES))
    sin_v = np.sin(np.radians(ORIENTATION_DEGREES))
    cos_agree = np.cos(np.radians(NORMAL_AGREEMENT_DEGREES))
    heights = world @ up
    min_inliers = max(30, len(idx) // 50)
    pool = idx
    for _ in range(params.max_planes):
        if len(pool) < min_inliers:
            break
        thr = float(params.noise_k * np.median(sig_all[pool])) + 0.003
        # seeded numpy RANSAC: the same labels on every run, whichever thread labels the frame
        model, inl = ransac_plane(pts_all[pool], thr, rng, iterations=200)
        if len(inl) < min_inliers:
            break
        n = np.asarray(model[:3], np.float64)
        d = float(model[3]) / np.linalg.norm(n)
        n = n / np.linalg.norm(n)
        # the side the cameras saw: most sampled normals of the inliers point that way
        if float(np.sum(nrm_all[pool[inl]] @ n)) < 0:
            n, d = -n, -d
        sample = pts_all[pool[inl]]
        pool = np.delete(pool, inl)
        c_up = float(n @ up)
        # Snapped to gravity: a floor or table top is level and a wall plumb; a plane through three
        # noisy points is tilted a little, enough to lose the far side of a table top.
        if abs(c_up) >= cos_h:
            kind = "up" if c_up > 0 else "down"
            n = up * np.sign(c_up)
        elif abs(c_up) <= sin_v:
            kind = "vertical"
            n = n - c_up * up
            n /= np.linalg.norm(n)
        else:
            continue                                    # a slanted plane: a ramp, a lid, a roof of a box
        d = -float(np.median(sample @ n))
        dist = np.abs(world @ n + d)
        # the offset again from every pixel near the plane (the sample's median carries its noise)
        close = valid & (stuff == 0) & (dist < params.noise_k * sigma + 0.003)
        if close.any():
            d -= float(np.median((world @ n + d)[close]))
            dist = np.abs(world @ n + d)
        near = valid & (stuff == 0) & (dist < params.noise_k * sigma + 0.003)
        # a pixel without a normal (image border, beside an invalid one) goes by its distance alone
        member = near & (~usable | (wnormals @ n > cos_agree))
        lab, count = _components(member)
        if count == 0:
            continue
        piece_area = np.bincount(lab.ravel(), weights=np.where(member, area, 0.0).ravel(), minlength=count + 1)
        h = float(np.median(heights[member]))
        cls, need = 0, np.inf
        if kind == "up":
            if capture.floor is not None and h <= capture.floor + params.floor_tolerance:
                cls, need = FLOOR, params.min_stuff_piece
            else:
                cls, need = SUPPORT, params.min_support_area
        elif kind == "down":
            if h > cam_height:                           # seen from below: over the camera's head
                cls, need = CEILING, params.min_stuff_piece
        else:
            cls, need = WALL, params.min_wall_area
        if cls == 0:
            continue
        big = piece_area >= need
        big[0] = False
        if cls == WALL and big.any():
            # one wall: its large piece qualifies it; smaller pieces of the same plane (between
            # objects standing against it) are wall too
            big = piece_area >= params.min_stuff_piece
            big[0] = False
        if not big.any():
            continue
        take = big[lab]
        stuff[take] = cls
        # beside the pieces taken: the specks and rims their normal test lost (not a far coplanar top)
        beside = ndimage.binary_dilation(take, iterations=3)
        on_plane[near & beside & (on_plane == 0)] = cls
        if cls == SUPPORT:
            level[take] = h
        planes.append({"class": STUFF_NAMES[cls], "height": h, "area": float(piece_area[big].sum())})
    return stuff, on_plane, level, planes


def grow_into(labels: np.ndarray, free: np.ndarray, depth: np.ndarray, tolerance: np.ndarray,
              max_pixels: float = 2.0) -> np.ndarray:
    """`labels` [H, W] extended into `free` pixels within `max_pixels` of a labelled pixel whose
    depth differs by less than `tolerance` [H, W]: the edge pixels the split left out rejoin the
    cluster they continue."""
    from scipy import ndimage

    if not labels.any():
        return labels
    dist, (iv, iu) = ndimage.distance_transform_edt(labels == 0, return_indices=True)
    near = free & (labels == 0) & (dist <= max_pixels)
    ok = near & (np.abs(depth - depth[iv, iu]) < tolerance)
    out = labels.copy()
    out[ok] = labels[iv[ok], iu[ok]]
    return out


def _circle(xy: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares circle through points xy [N, 2] (algebraic fit): (centre [2], radius, rms residual)."""
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    sol, *_ = np.linalg.lstsq(A, (xy ** 2).sum(1), rcond=None)
    c = sol[:2]
    r = float(np.sqrt(max(sol[2] + c @ c, 0.0)))
    rms = float(np.sqrt(np.mean((np.linalg.norm(xy - c, axis=1) - r) ** 2)))
    return c, r, rms


def _holds(outer_xy: np.ndarray, inner_xy: np.ndarray, margin: float) -> bool:
    """Whether the ground footprint of `outer_xy` [N, 2] holds `inner_xy` [M, 2]: inside its bounding
    box, or, for a round outside (a mug or bowl seen from one side shows half its wall), inside the
    circle the wall lies on."""
    lo, hi = outer_xy.min(0) - margin, outer_xy.max(0) + margin
    if np.all(inner_xy >= lo) and np.all(inner_xy <= hi):
        return True
    if len(outer_xy) < 8:
        return False
    c, r, rms = _circle(outer_xy)
    if not (0.01 < r < 0.5) or rms > 0.2 * r:
        return False
    return float(np.mean(np.linalg.norm(inner_xy - c, axis=1) <= r + margin)) >= 0.95


def merge_nested(labels: np.ndarray, world: np.ndarray, up: np.ndarray, margin: float) -> np.ndarray:
    """Neighbouring clusters of which one lies inside the other's footprint on the ground, and does
    not rise above its top, are one object: a mug's or a bowl's inside, cut from its outside by the
    rim's depth step. A thing standing in or on another small thing joins it too (a limit).

    labels: [H, W] cluster ids; world: [H, W, 3]; margin: metres a footprint may stick out."""
    from scipy import ndimage

    n = int(labels.max())
    if n < 2:
        return labels
    # neighbours: clusters within 2 pixels of each other in the image
    grown = ndimage.grey_dilation(labels, size=(5, 5))
    touch = (labels > 0) & (grown > 0) & (grown != labels)
    if not touch.any():
        return labels
    pairs = np.unique(np.sort(np.stack([labels[touch], grown[touch]], 1), axis=1), axis=0)
    # ground coordinates along two horizontal axes perpendicular to up, and heights
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    starts = np.searchsorted(flat[order], np.arange(n + 2))
    P = world.reshape(-1, 3)

    cache: dict = {}

    def cluster(i):
        """(ground xy [N, 2], heights [N], largest ground extent) of cluster i, computed once."""
        if i not in cache:
            members = order[starts[i]:starts[i + 1]]
            pts = P[members[::max(1, len(members) // 2000)]]        # a regular subsample: the tests are statistics
            xy = np.column_stack([pts @ a, pts @ b])
            cache[i] = (xy, pts @ up, float(np.ptp(xy, axis=0).max()))
        return cache[i]

    parent = np.arange(n + 1)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in pairs:
        ci, cj = cluster(i), cluster(j)
        for (xo, ho, extent), (xn, hn, _) in ((ci, cj), (cj, ci)):
            if extent > 1.0:                                # an object's inside, not a furniture's
                continue
            if np.percentile(hn, 95) <= np.percentile(ho, 99) + margin and _holds(xo, xn, margin):
                parent[root(i)] = root(j)
                break
    roots = np.array([root(i) for i in range(n + 1)])
    return roots[labels]


def join_fragments(labels: np.ndarray, world: np.ndarray, max_pixels: int, gap: np.ndarray) -> np.ndarray:
    """Clusters of fewer than `max_pixels` join the neighbouring cluster they touch in 3D (closest
    points within `gap` [H, W] metres of each other): a box's side seen at a grazing angle, cut off
    by the depth steps such a side makes from pixel to pixel. A small thing alone on a plane has no
    neighbouring cluster and stays.

    labels: [H, W]; world: [H, W, 3]."""
    from scipy import ndimage

    n = int(labels.max())
    if n < 2:
        return labels
    from scipy.spatial import cKDTree

    size = np.bincount(labels.ravel(), minlength=n + 1)
    out = labels.copy()
    boxes = ndimage.find_objects(labels)
    H, W = labels.shape
    for i in np.flatnonzero((size > 0) & (size < max_pixels)):
        if i == 0 or boxes[i - 1] is None:
            continue
        sv, su = boxes[i - 1]
        crop = (slice(max(sv.start - 2, 0), min(sv.stop + 2, H)), slice(max(su.start - 2, 0), min(su.stop + 2, W)))
        lab = labels[crop]
        mine = lab == i
        ring = ndimage.binary_dilation(mine, iterations=2) & ~mine & (lab > 0)
        if not ring.any():
            continue
        pts = world[crop]
        d, j = cKDTree(pts[ring]).query(pts[mine])
        k = int(np.argmin(d))
        if d[k] <= gap[crop][mine][k]:
            out[crop][mine] = out[crop][ring][j[k]]
    return out


def cut_at_supports(clusters: np.ndarray, heights: np.ndarray, world: np.ndarray, up: np.ndarray,
                    tolerance: np.ndarray, supports: list, min_part: int) -> np.ndarray:
    """What stands on a support the capture saw from above (Capture.supports), cut from the cluster
    that runs down past the support's level.

    A frame that sees a cabinet or table top edge-on (a camera near its height: a sliver of pixels,
    no plane) cannot tell what stands on it from its front or apron: one cluster runs from the
    cabinet's front up the box on it. For a cluster with at least `min_part` pixels in a support's
    footprint (its rim included: the front) more than `tolerance` under its level, each connected
    part of it over the level (by half a tolerance) that stands on the top - its foot, the pixels
    within SUPPORT_CONTACT over the level, at least `min_part` of them and most on the top's inside
    (SupportLevel cells 2) - becomes a cluster of its own. The rest keeps its id: a bookcase's side
    rises past each board beside the board, and its higher boards stand on nothing.

    clusters: [H, W] ids (0 = none); heights: [H, W] along `up` [3]; world: [H, W, 3];
    tolerance: [H, W] metres."""
    from scipy import ndimage

    if not supports or not clusters.any():
        return clusters
    ground = world @ horizontal_basis(up)                   # [H, W, 2]
    eight = np.ones((3, 3), bool)
    for support in supports:
        n = int(clusters.max())
        where = np.where(clusters > 0, support.footprint(ground), 0)
        if not where.any():
            continue
        under = (where > 0) & (heights < support.height - tolerance)
        candidates = np.flatnonzero(np.bincount(clusters[under], minlength=n + 1) >= min_part)
        over = heights > support.height + 0.5 * tolerance
        foot = over & (heights <= support.height + tolerance + SUPPORT_CONTACT)
        for k in candidates[candidates > 0]:
            parts, count = ndimage.label((clusters == k) & over, structure=eight)
            if count == 0:
                continue
            on_top = np.bincount(parts[foot & (where == 2)], minlength=count + 1)
            standing = (on_top >= min_part) & (on_top >= 0.5 * np.bincount(parts[foot], minlength=count + 1))
            standing[0] = False
            if standing.any():
                ids = np.zeros(count + 1, np.int64)
                ids[standing] = int(clusters.max()) + 1 + np.arange(int(standing.sum()))
                clusters = np.where(standing[parts], ids[parts], clusters)
    return clusters


def absorb_support_parts(clusters: np.ndarray, stuff: np.ndarray, level: np.ndarray, heights: np.ndarray,
                         depth: np.ndarray, tolerance: float, depth_below: float = 0.12) -> tuple[np.ndarray, np.ndarray]:
    """Clusters that hang from a support are the support's furniture: a table's legs, apron and the
    edge of its top, a shelf's sides. Such a cluster touches a support piece in the image (or a part
    already joined to one: a leg hangs from the top's edge) and its top lies just under that support's
    level (within `depth_below` under it, at most `tolerance` over); a thing standing on the support
    rises above it and stays a thing. A cluster the support hides the top of (it meets the support
    more than depth_below / 2 behind it) hangs from it when it stays under its level.

    level: [H, W] support height at support pixels (NaN elsewhere); heights, depth: [H, W] pixel
    heights and depths."""
    from scipy import ndimage

    level = level.copy()
    stuff = stuff.copy()
    for _ in range(4):                                  # top -> its edge -> the legs under the edge
        n = int(clusters.max())
        if n == 0 or not np.isfinite(level).any():
            break
        # the support level next to each pixel (within 2 pixels): the highest one around
        near_level = ndimage.maximum_filter(np.where(np.isfinite(level), level, -np.inf), size=5)
        ids = np.arange(1, n + 1)
        support_h = np.asarray(ndimage.maximum(near_level, clusters, ids), np.float64).reshape(-1)
        present = np.bincount(clusters.ravel(), minlength=n + 1)[1:] > 0
        touching = np.isfinite(support_h) & present
        if not touching.any():
            break
        # the support's depth next to each pixel: a cluster farther than it where they meet goes on
        # behind it (a back leg under a table top), its top hidden by the support
        near_depth = ndimage.minimum_filter(np.where(np.isfinite(level), depth, np.inf), size=5)
        top = np.full(n, np.inf)
        hidden = np.zeros(n, bool)
        for i in np.flatnonzero(touching):
            mine = clusters == i + 1
            top[i] = np.percentile(heights[mine], 95)
            contact = mine & np.isfinite(near_depth)
            hidden[i] = contact.any() and np.median(depth[contact] - near_depth[contact]) > depth_below / 2
        hang = touching & (top <= support_h + tolerance) & ((top >= support_h - depth_below) | hidden)
        if not hang.any():
            break
        lut_h = np.concatenate([[np.nan], np.where(hang, support_h, np.nan)])
        take = np.isfinite(lut_h[clusters])
        stuff[take] = SUPPORT
        level[take] = lut_h[clusters][take]
        clusters = np.where(take, 0, clusters)
    return clusters, stuff


def absorb_floor_patches(clusters: np.ndarray, stuff: np.ndarray, heights: np.ndarray, up_cos: np.ndarray,
                         nok: np.ndarray, below: float, share: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Clusters lying flat under `below` (the floor level + tolerance) are floor: a far, grazing patch of
    a real floor the frame's plane missed (a Kinect's floor bends by centimetres at 3 m). Flat: `share`
    of the pixels with a normal face up within 30 degrees; a small box on the floor shows its sides.

    heights, up_cos: [H, W] pixel height and normal . up; nok: [H, W] normal defined."""
    n = int(clusters.max())
    if n == 0:
        return clusters, stuff
    flat = nok & (up_cos >= np.cos(np.radians(30.0)))
    size = np.bincount(clusters.ravel(), minlength=n + 1)
    up_share = np.bincount(clusters.ravel(), weights=flat.ravel(), minlength=n + 1) / np.maximum(size, 1)
    low = np.zeros(n + 1, bool)
    for i in np.flatnonzero((up_share >= share) & (size > 0)):
        if i:
            low[i] = np.percentile(heights[clusters == i], 95) <= below
    if not low.any():
        return clusters, stuff
    take = low[clusters]
    stuff = stuff.copy()
    stuff[take] = FLOOR
    return np.where(take, 0, clusters), stuff


def fill_stuff_holes(semantic: np.ndarray, valid: np.ndarray, stuff: np.ndarray, max_pixels: float = 2.0):
    """Valid pixels left unlabelled within `max_pixels` of a stuff pixel take its class: the specks a
    plane's distance or normal test missed (noise), not worth an object each."""
    from scipy import ndimage

    if not stuff.any():
        return semantic
    dist, (iv, iu) = ndimage.distance_transform_edt(stuff == 0, return_indices=True)
    take = valid & (semantic == 0) & (dist <= max_pixels)
    out = semantic.copy()
    out[take] = stuff[iv[take], iu[take]]
    return out


def fill_invalid_specks(semantic: np.ndarray, instance: np.ndarray, valid: np.ndarray):
    """Invalid pixels whose 8 neighbours hold one label (class and instance) take it."""
    from scipy import ndimage

    key = semantic.astype(np.int64) * 65536 + instance
    lo = ndimage.grey_erosion(np.where(valid, key, np.iinfo(np.int64).max), size=(3, 3))
    hi = ndimage.grey_dilation(np.where(valid, key, -1), size=(3, 3))
    surrounded = ndimage.uniform_filter(valid.astype(np.float32), size=3, mode="constant") * 9 >= 7.5
    take = ~valid & surrounded & (lo == hi) & (hi > 0)
    sem, inst = semantic.copy(), instance.copy()
    sem[take] = (hi[take] // 65536).astype(sem.dtype)
    inst[take] = (hi[take] % 65536).astype(inst.dtype)
    return sem, inst


def relabel(labels: np.ndarray, min_pixels: int) -> np.ndarray:
    """Clusters with at least `min_pixels` renumbered 1..K (largest first, so ids read the same in every
    run); smaller ones become 0."""
    count = np.bincount(labels.ravel())
    count[0] = 0
    keep = np.flatnonzero(count >= max(1, min_pixels))
    order = keep[np.argsort(-count[keep], kind="stable")]
    lut = np.zeros(len(count), np.int64)
    lut[order] = np.arange(1, len(order) + 1)
    return lut[labels]


def segment_frame(depth: np.ndarray, rgb: np.ndarray | None, K: np.ndarray, c2w: np.ndarray,
                  capture: Capture, params: SegmentParams | None = None,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Panoptic pseudo-labels of one RGB-D frame.

    depth: [H, W] metres (0 / NaN = no return); rgb: [H, W, 3] in [0, 1] or None; K: [3, 3];
    c2w: [4, 4] camera-to-world (OpenCV). Returns (semantic [H, W] uint16 with CLASS_TABLE ids,
    instance [H, W] uint16: 1..K per object cluster, 0 on stuff and unlabelled pixels, info dict:
    planes [{class, height, area}], objects).
    """
    from scipy import ndimage

    params = params or SegmentParams()
    depth = np.asarray(depth, np.float64)
    K = np.asarray(K, np.float64)
    c2w = np.asarray(c2w, np.float64)
    H, W = depth.shape
    valid = np.isfinite(depth) & (depth > 0)
    semantic = np.zeros((H, W), np.uint16)
    instance = np.zeros((H, W), np.uint16)
    info = {"planes": [], "objects": 0}
    if valid.sum() < 10:
        return semantic, instance, info
    z = np.where(valid, depth, 0.0)
    f = float(np.sqrt(K[0, 0] * K[1, 1]))
    step = max(1, round(W / 160))
    points = camera_points(depth, K)
    normals, nok = pixel_normals(points, valid, step)
    sigma = np.where(valid, noise_sigma(z, capture.noise), 0.0)
    R, t = c2w[:3, :3], c2w[:3, 3]
    world = points @ R.T + t
    wnormals = normals @ R.T
    ray = points / np.maximum(np.linalg.norm(points, axis=-1, keepdims=True), 1e-12)
    cos_view = np.abs(np.einsum("ijk,ijk->ij", normals, ray))
    area = np.where(valid, _pixel_area(z, np.where(nok, cos_view, 1.0), K), 0.0)
    rng = np.random.default_rng(seed)
    stuff, on_plane, level, planes = fit_planes(world, wnormals, valid, valid & nok, sigma, area, float(t @ capture.up), capture,
                               params, rng)
    semantic[:] = stuff
    info["planes"] = planes

    edges = depth_edges(z, valid, sigma, f, params)
    edges |= concave_creases(points, normals, nok, sigma, params, step)
    col = colour_edges(rgb, params.colour_edge)
    if col is not None:
        edges |= col
    # pixels on a stuff plane by distance whose normal failed its test (beside a thing's edge, or
    # turned by a noise outlier) are not a thing's: they go to the plane below (fill_stuff_holes)
    free = valid & (stuff == 0) & (on_plane == 0)
    clusters, _ = ndimage.label(free & ~edges)
    min_pixels = params.min_object_pixels or max(6, int(round(H * W / 4000)))
    clusters = relabel(clusters, max(2, min_pixels // 3))
    tolerance = params.noise_k * np.sqrt(2.0) * sigma + params.slope * z / f
    clusters = grow_into(clusters, free, z, tolerance)
    clusters = merge_nested(clusters, world, capture.up, margin=0.02)
    clusters = join_fragments(clusters, world, 4 * min_pixels, 2 * tolerance + 0.005)
    heights = world @ capture.up
    clusters = cut_at_supports(clusters, heights, world, capture.up, params.noise_k * sigma + SUPPORT_LEVEL_MARGIN,
                               capture.supports, max(2, min_pixels // 3))
    clusters, stuff = absorb_support_parts(clusters, stuff, level, heights, z, params.floor_tolerance)
    if capture.floor is not None:
        clusters, stuff = absorb_floor_patches(clusters, stuff, heights, wnormals @ capture.up, nok,
                                               capture.floor + params.floor_tolerance)
    clusters = relabel(clusters, min_pixels)
    instance[:] = clusters.astype(np.uint16)
    semantic[:] = stuff
    semantic[clusters > 0] = OBJECT
    semantic[np.isin(clusters, large_clusters(clusters, world, capture.up, FURNITURE_EXTENT))] = FURNITURE
    semantic[(semantic == 0) & (on_plane > 0)] = on_plane[(semantic == 0) & (on_plane > 0)]
    semantic[:] = fill_stuff_holes(semantic, valid, stuff)
    # a lone invalid pixel inside a labelled region takes its label: the sensor missed a speck
    semantic[:], instance[:] = fill_invalid_specks(semantic, instance, valid)
    info["objects"] = int(clusters.max())
    return semantic, instance, info
