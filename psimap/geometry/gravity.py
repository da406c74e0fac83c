"""Which way is up: the gravity direction of a capture, from its surfaces and its cameras.

psimap's world is Z-up (docs/conventions.md), but a user's capture comes in whatever frame its
source used: ARKit, Record3D and most phone apps are Y-up, COLMAP is arbitrary, a robot's hand-eye
calibration may have z pointing down. Gravity is estimated from three kinds of evidence, each a score in
[-1, 1] for a candidate up direction u:

- supports: surfaces perpendicular to u whose normal (turned towards the camera that saw them) points
  along +u are floors, table tops and seats seen from above; along -u, ceilings and undersides. Their
  area-weighted balance is large for the true up (what a camera sees is mostly what things rest on).
- upright cameras: the image's up direction (-y of an OpenCV camera) agrees with u for a hand-held
  or head-mounted capture.
- cameras look down: the viewing direction has a component along -u (tabletops, floors) far more
  often than along +u.

score(u) = 2 supports + upright + look_down. Candidates are the principal axes of the area-weighted
normal distribution (a Manhattan room gives its three axes) and the cameras' mean up; the winner is
refined to the area-weighted normal of the surfaces it calls supports. A result within
SNAP_DEGREES of a coordinate axis is snapped to it, so a capture that is already axis-aligned is left
exactly as it is.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psimap import PsimapError

# A surface counts as horizontal (support / ceiling) under a candidate up when its normal is within
# this angle of it: loose enough for a noisy fused table top, tight enough to exclude a 30-degree ramp.
HORIZONTAL_DEGREES = 15.0
# Weight of the supports score: it is the only evidence a top-down robot camera leaves.
SUPPORT_WEIGHT = 2.0
# An estimate within this angle of a coordinate axis is taken to be that axis (a Z-up capture stays
# bit-for-bit as it is; captures are levelled to well under a degree by the supports anyway).
SNAP_DEGREES = 1.0

# A candidate up must have at least this fraction of the surface area perpendicular to it.
MIN_ANCHOR_AREA = 0.01
# Final levelling by the planes the horizontal surfaces' points lie on (_refine_by_planes): points
# whose normal is within the window, up to PLANE_FITS planes, each agreeing with the normals' up
# within PLANE_AGREE_DEGREES and holding PLANE_MIN_SHARE of those points, from PLANE_MIN_POINTS.
PLANE_WINDOW_DEGREES = 20.0
PLANE_AGREE_DEGREES = 10.0
PLANE_MIN_SHARE = 0.1
PLANE_FITS = 3
PLANE_MIN_POINTS = 50

AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclass
class UpEstimate:
    """up: [3] unit gravity-up direction in the input world frame; rotation: [3, 3] that takes it to +z
    (the smallest such rotation); source: "auto" | "given" | "default"; margin: score of the winner minus
    the best other direction (how sure, 0..~4); scores: the winner's evidence."""

    up: np.ndarray
    rotation: np.ndarray
    source: str
    margin: float = 0.0
    scores: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"input_up": [float(v) for v in self.up], "rotation": self.rotation.round(9).tolist(),
                "source": self.source, "margin": round(float(self.margin), 4),
                "scores": {k: round(float(v), 4) for k, v in self.scores.items()}}


def parse_up(text: str) -> np.ndarray | None:
    """`--up` value -> unit vector, or None for "auto". Accepts +z / -y / ... or "x,y,z"."""
    t = str(text).strip().lower()
    if t in ("", "auto"):
        return None
    if t in AXES:
        return np.asarray(AXES[t], np.float64)
    if t in ("x", "y", "z"):
        return np.asarray(AXES["+" + t], np.float64)
    try:
        v = np.asarray([float(x) for x in t.split(",")], np.float64)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-9:
        raise PsimapError(f"--up {text!r}: expected auto, one of {', '.join(AXES)}, or a vector 'x,y,z'")
    return v / np.linalg.norm(v)


def rotation_to_z_up(up) -> np.ndarray:
    """[3, 3] rotation R with R @ up = +z, the smallest one (about the axis up x z); for up = -z, the
    half turn about +x."""
    u = np.asarray(up, np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    c = float(u @ z)
    if c > 1.0 - 1e-15:
        return np.eye(3)
    if c < -1.0 + 1e-15:
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(u, z)
    s = np.linalg.norm(axis)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def snap_to_axis(up: np.ndarray, degrees: float = SNAP_DEGREES) -> np.ndarray:
    """`up` replaced by the nearest coordinate axis when within `degrees` of it."""
    i = int(np.argmax(np.abs(up)))
    axis = np.zeros(3)
    axis[i] = np.sign(up[i])
    if float(up @ axis) >= np.cos(np.radians(degrees)):
        return axis
    return up


def orient_towards_cameras(points: np.ndarray, normals: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """normals [N, 3] flipped to face the nearest camera centre (centres [M, 3]): a surfel is a
    two-sided disc, but the side a camera saw is the side the surface faces."""
    from scipy.spatial import cKDTree

    _, j = cKDTree(centres).query(points)
    flip = np.einsum("ij,ij->i", normals, centres[j] - points) < 0
    out = normals.copy()
    out[flip] *= -1
    return out


def up_scores(up: np.ndarray, normals: np.ndarray, weights: np.ndarray, cam_up: np.ndarray,
              cam_forward: np.ndarray) -> dict:
    """Evidence for `up` [3]: supports, upright, look_down (each in [-1, 1]) and their weighted total.
    normals [N, 3] oriented towards the cameras; weights [N] summing to 1; cam_up / cam_forward [M, 3]."""
    d = normals @ up
    horizontal = np.abs(d) >= np.cos(np.radians(HORIZONTAL_DEGREES))
    supports = float(np.sum(weights[horizontal] * np.sign(d[horizontal]))) if len(d) else 0.0
    upright = float(np.mean(cam_up @ up)) if len(cam_up) else 0.0
    look_down = float(-np.mean(cam_forward @ up)) if len(cam_forward) else 0.0
    return {"supports": supports, "upright": upright, "look_down": look_down,
            "total": SUPPORT_WEIGHT * supports + upright + look_down}


def _refine(up: np.ndarray, normals: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The area-weighted principal direction of the surfaces around ±up, signed like up: a mean shift
    on the axis distribution whose window narrows from 30 degrees to HORIZONTAL_DEGREES, so a start
    far from the floor normal still reaches it and the final window is symmetric about it (unbiased)."""
    for window in (30.0, 20.0, HORIZONTAL_DEGREES):
        for _ in range(8):
            sel = np.abs(normals @ up) >= np.cos(np.radians(window))
            if weights[sel].sum() <= 0:
                break
            n = normals[sel]
            v = np.linalg.eigh((n * weights[sel, None]).T @ n)[1][:, -1]
            v = v if v @ up >= 0 else -v
            moved = float(v @ up)
            up = v
            if moved > np.cos(np.radians(0.01)):
                break
    return up / np.linalg.norm(up)


def _refine_by_planes(up: np.ndarray, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """up [3] levelled to the planes the horizontal surfaces' points lie on (floor, table tops): a
    point-based fit, because the normals of surfels seen obliquely through noisy depth lean towards
    the camera (7-Scenes chess: the normals' estimate was 5.8 degrees off the floor's and the table's
    planes, which agreed within 0.7; the floor then split into height levels). RANSAC planes
    (psimap.geometry.planes, seeded) on the centres of surfaces within PLANE_WINDOW_DEGREES of up;
    those within PLANE_AGREE_DEGREES of it holding at least PLANE_MIN_SHARE of the points vote with
    their inlier counts. Returns up unchanged when no plane qualifies."""
    from psimap.geometry.planes import ransac_plane

    sel = np.abs(normals @ up) >= np.cos(np.radians(PLANE_WINDOW_DEGREES))
    pts = points[sel]
    if len(pts) < PLANE_MIN_POINTS:
        return up
    lo, hi = np.percentile(pts, [1, 99], axis=0)
    # inlier band: a few sensor-noise widths at room scale, proportional for larger scenes
    thr = max(0.005, 0.002 * float(np.linalg.norm(hi - lo)))
    rng = np.random.default_rng(0)                      # the same up on every run
    votes = np.zeros(3)
    left = pts
    for _ in range(PLANE_FITS):
        if len(left) < PLANE_MIN_POINTS:
            break
        plane, inliers = ransac_plane(left, thr, rng, iterations=1000)
        if len(inliers) == 0:
            break
        n = plane[:3]
        n = n if n @ up >= 0 else -n
        if n @ up >= np.cos(np.radians(PLANE_AGREE_DEGREES)) and len(inliers) >= PLANE_MIN_SHARE * len(pts):
            votes += len(inliers) * n
        left = np.delete(left, inliers, axis=0)
    if not votes.any():
        return up
    return votes / np.linalg.norm(votes)


def estimate_up(points, normals, weights, c2w) -> UpEstimate:
    """Gravity-up of a capture (see the module docstring).

    points, normals: [N, 3] surface samples (surfel centres and normals; normals need not be
    oriented); weights: [N] area of each (surfel area x opacity); c2w: [M, 4, 4] camera-to-world poses
    (OpenCV). Non-finite rows are ignored. With neither surfaces nor cameras the answer is +z
    (source "default").
    """
    P = np.asarray(points, np.float64).reshape(-1, 3)
    Nn = np.asarray(normals, np.float64).reshape(-1, 3)
    W = np.asarray(weights, np.float64).reshape(-1)
    C2W = np.asarray(c2w, np.float64).reshape(-1, 4, 4)
    C2W = C2W[np.isfinite(C2W).all(axis=(1, 2))]
    norm = np.linalg.norm(Nn, axis=1)
    ok = np.isfinite(P).all(1) & np.isfinite(Nn).all(1) & np.isfinite(W) & (W > 0) & (norm > 1e-9)
    P, Nn, W = P[ok], Nn[ok] / norm[ok, None], W[ok]
    cam_up, cam_forward, centres = -C2W[:, :3, 1], C2W[:, :3, 2], C2W[:, :3, 3]
    if len(P) == 0 and len(C2W) == 0:
        return UpEstimate(np.array([0.0, 0.0, 1.0]), np.eye(3), "default")
    if len(centres) and len(P):
        Nn = orient_towards_cameras(P, Nn, centres)
    W = W / W.sum() if len(W) else W

    candidates = []
    if len(Nn):
        T = (Nn * W[:, None]).T @ Nn
        candidates += list(np.linalg.eigh(T)[1].T)
    camera_guess = []
    if len(cam_up) and np.linalg.norm(cam_up.mean(0)) > 1e-6:
        camera_guess.append(cam_up.mean(0) / np.linalg.norm(cam_up.mean(0)))
    if len(cam_forward) and np.linalg.norm(cam_forward.mean(0)) > 1e-6:
        camera_guess.append(-cam_forward.mean(0) / np.linalg.norm(cam_forward.mean(0)))
    candidates += camera_guess
    axes = []
    for a in candidates:
        if len(Nn):
            a = _refine(a, Nn, W)
            # a direction no surface is perpendicular to is not a candidate when there are surfaces
            # (a camera-only direction between the floor normal and the mean view tilt would win
            # on the camera cues alone)
            if W[np.abs(Nn @ a) >= np.cos(np.radians(HORIZONTAL_DEGREES))].sum() < MIN_ANCHOR_AREA:
                continue
        if all(abs(float(a @ b)) < np.cos(np.radians(5.0)) for b in axes):
            axes.append(a)
    if not axes:
        axes = camera_guess[:1] or [np.array([0.0, 0.0, 1.0])]
    scored = sorted(((up_scores(s * a, Nn, W, cam_up, cam_forward), s * a) for a in axes for s in (1.0, -1.0)),
                    key=lambda t: -t[0]["total"])
    best, up = scored[0]
    # how sure: against the best direction that is really another one (not the same axis refined
    # from another start)
    others = [sc["total"] for sc, v in scored[1:] if float(v @ up) < np.cos(np.radians(30.0))]
    margin = best["total"] - max(others) if others else 0.0
    if len(P):
        up = _refine_by_planes(up, P, Nn)
    up = snap_to_axis(up)
    return UpEstimate(up, rotation_to_z_up(up), "auto", margin, best)


def resolve_up(spec: str, points, normals, weights, c2w) -> UpEstimate:
    """`--up SPEC`: "auto" estimates (estimate_up); an axis or vector is taken as given."""
    given = parse_up(spec)
    if given is None:
        return estimate_up(points, normals, weights, c2w)
    return UpEstimate(given, rotation_to_z_up(given), "given")
