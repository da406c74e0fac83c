"""Step 4: decimation to an error budget.

fast-simplification (quadric edge collapse; MeshLab's topology-preserving collapse when it breaks a
closed mesh) proposes meshes of decreasing face count; each one is
measured against the pre-decimation mesh (symmetric Hausdorff distance and mean distance on surface
samples, exact point-to-triangle distances by Open3D's RaycastingScene) and the smallest face count
whose error stays within the budget (and which stays watertight when the input was) is kept.
The face count is found by bisection on the log of the count, so it is chosen by the error, not by
a fixed ratio.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from psimap.transforms import sample_surface

DEFAULT_SAMPLES = 10_000
# MeshLab's topology-preserving collapse of a closed solid can leave a hole of a few edges (a
# room's carved 132k-face shelf, genus 49: one 5-edge hole at 5.2k, 10k and 20k faces, so no
# closed candidate, the unreduced solid exported and its colliders taking a mug's place): holes up
# to this many edges are closed again; a larger opening is a real defect and stays one
MAX_PATCH_EDGES = 32


@dataclass
class DecimationResult:
    mesh: object                   # trimesh.Trimesh
    faces_before: int
    faces_after: int
    hausdorff: float               # metres, symmetric max distance
    mean_error: float              # metres, symmetric mean distance
    budget: float                  # metres
    curve: list[tuple[int, float, float]] = field(default_factory=list)  # (faces, hausdorff, mean) tried


def default_budget(mesh, relative: float = 0.005, floor: float = 0.001) -> float:
    """Error budget (m): 0.5 % of the bounding-box diagonal, at least 1 mm (below scan noise)."""
    return max(floor, relative * float(np.linalg.norm(mesh.extents)))


def surface_distance(a, b, samples: int = DEFAULT_SAMPLES, seed: int = 0) -> tuple[float, float]:
    """Symmetric (Hausdorff, mean) distance in metres between two meshes from surface samples.

    a, b: trimesh.Trimesh. Deterministic for a fixed seed.
    """
    da = distance_to_surface(b, sample_surface(a, samples, seed, with_vertices=True))
    db = distance_to_surface(a, sample_surface(b, samples, seed + 1, with_vertices=True))
    return float(max(da.max(), db.max())), float(0.5 * (da.mean() + db.mean()))


def distance_to_surface(mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance [P] float64 of points [P, 3] to the triangles of `mesh` (Open3D, float32)."""
    return surface_distance_query(mesh)(points)


def surface_distance_query(mesh):
    """points [P, 3] -> unsigned distance [P] float64 to the triangles of `mesh`: one Open3D scene
    (and its BVH, built at the first query) for many queries, as decimation's bisection asks of
    the mesh it simplifies."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))

    def distance(points: np.ndarray) -> np.ndarray:
        return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy().astype(np.float64)

    return distance


def simplify_to_count(mesh, faces: int, method: str = "auto"):
    """Quadric decimation to about `faces` faces (trimesh in, trimesh out). method: "fast"
    (fast-simplification only), "meshlab" (topology-preserving MeshLab collapse only) or "auto"
    (fast, MeshLab when fast breaks a closed mesh)."""
    import fast_simplification
    import trimesh

    from psimap.exporters.repair import drop_slivers

    if method == "meshlab":
        return _meshlab_simplify(mesh, faces)
    # open meshes (background) keep their border: collapsing it pulls the rim inwards by cm
    v, f = fast_simplification.simplify(np.asarray(mesh.vertices, np.float64),
                                        np.asarray(mesh.faces, np.int32), target_count=int(faces),
                                        preserve_border=not mesh.is_watertight)
    out = trimesh.Trimesh(v, f, process=True)
    if out.is_watertight and len(out.split(only_watertight=False)) == 1:
        return out
    if mesh.is_watertight and method == "auto":
        # fast-simplification collapses across thin (one-voxel) parts of voxel solids and leaves
        # edges shared by four faces (a carved box: 110 pieces at 2000 faces); MeshLab's quadric
        # collapse with topology preservation keeps it one closed surface
        alt = _meshlab_simplify(mesh, faces)
        if alt.is_watertight and len(alt.split(only_watertight=False)) == 1:
            return alt
    # edge collapses can pinch off tiny closed 2-face pockets: drop them, keep the real surface
    return drop_slivers(out)


def _meshlab_simplify(mesh, faces: int):
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(faces), preservetopology=True,
                                                preservenormal=True, qualitythr=0.3)
    if mesh.is_watertight:
        _close_small_holes(ms)
    o = ms.current_mesh()
    out = trimesh.Trimesh(o.vertex_matrix(), o.face_matrix(), process=True)
    out.metadata["meshlab"] = True
    return out


def _close_small_holes(ms, max_edges: int = MAX_PATCH_EDGES) -> None:
    """Close the holes of at most max_edges edges of the current mesh of pymeshlab MeshSet ms.
    Not repair._close_holes: its non-manifold repairs first and rim-friendly patching left the
    test's two-face hole open (checked on 2026-11-28, with and without its self-intersection test)."""
    if ms.get_topological_measures()["boundary_edges"]:
        ms.meshing_close_holes(maxholesize=int(max_edges))


def close_small_holes(mesh, max_edges: int = MAX_PATCH_EDGES):
    """`mesh` (trimesh) with its holes of at most max_edges boundary edges closed (MeshLab's hole
    filling); larger openings stay open."""
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    _close_small_holes(ms, max_edges)
    o = ms.current_mesh()
    return trimesh.Trimesh(o.vertex_matrix(), o.face_matrix(), process=True)


# A visual mesh needs triangles no smaller than this many error budgets across, nor smaller than
# this fraction of its bounding-box diagonal: finer ones draw nothing a viewer or a camera sees.
EDGE_BUDGETS = 4.0
EDGE_DIAGONAL = 1.0 / 40.0
MIN_VISUAL_FACES = 200


def visual_face_budget(mesh, budget: float, source_faces: int = 0) -> int:
    """Most faces the visual mesh of `mesh` (trimesh) needs at error budget `budget` (m): its
    envelope's area in triangles of edge max(EDGE_BUDGETS x budget, EDGE_DIAGONAL x diagonal), at least
    MIN_VISUAL_FACES, and never more than the mesh it was made from had (`source_faces`, 0 = no
    limit): closing and decimation must not grow a small object's mesh."""
    diag = float(np.linalg.norm(mesh.extents))
    edge = max(EDGE_BUDGETS * float(budget), EDGE_DIAGONAL * diag, 1e-6)
    # the area at that scale: a rough fused surface's own area counts its noise, its envelope's not
    area = min(float(mesh.area), float(mesh.convex_hull.area))
    cap = max(MIN_VISUAL_FACES, int(np.ceil(area / (0.433 * edge * edge))))
    return min(cap, max(MIN_VISUAL_FACES, int(source_faces))) if source_faces > 0 else cap


def decimate_to_count(mesh, faces: int, fallback: DecimationResult, *, samples: int = DEFAULT_SAMPLES,
                      seed: int = 0, max_growth: int = 3) -> DecimationResult:
    """`mesh` simplified to about `faces` faces whatever the error (measured and reported); a
    watertight input must stay watertight: when no simplification to `faces` does, twice and four
    times as many are tried (max_growth steps of 2x) before `fallback` comes back: fallback is
    often the unreduced input (a voxel solid's tens of thousands of faces on a small object)."""
    out = simplify_to_count(mesh, faces)
    for _ in range(max_growth):
        if not (mesh.is_watertight and not out.is_watertight):
            break
        faces *= 2
        if faces >= len(fallback.mesh.faces):
            return fallback
        out = simplify_to_count(mesh, faces)
    if mesh.is_watertight and not out.is_watertight:
        return fallback
    haus, mean = surface_distance(mesh, out, samples=samples, seed=seed)
    return DecimationResult(out, len(mesh.faces), len(out.faces), haus, mean, fallback.budget,
                            fallback.curve + [(len(out.faces), haus, mean)])


def _floor(lo: float, cand, e: float) -> float:
    """The bracket's lower end after a probe that missed the budget: the log face count the
    simplifier reached when it stopped short of the one asked (a 644k-face room with open borders
    stays at 28k faces whatever fewer is asked: three probes below it were three whole
    simplifications of the same 28k-face result)."""
    return max(lo, float(np.log(len(cand.faces)))) if np.isfinite(e) and len(cand.faces) else lo


def next_probe(lo: float, hi: float, tried: list, budget: float, moved: str | None,
               face_tol: float) -> float:
    """The next log face count to try inside the bracket (lo, hi) of log face counts (lo misses
    the budget, hi meets it). tried: (log face count, error) of the probes so far, in order.

    A simplification's error falls about as a power of its face count, so the count where it meets
    the budget is found by the secant through the last two probes on log(error) against log(count)
    (bisection before there are two, or when they do not fall), then stepped half the face
    tolerance past it, away from the end the last probe moved, so that the next probe tends to
    close the bracket from the other side; kept a tenth of the bracket from either end. Plain
    bisection took 6-8 probes of a 644k-face room (each a whole simplification and two distance
    passes); the secant through the bracket's ends crept along its flat error curve.
    """
    w = hi - lo
    pts = [(n, e) for n, e in tried if np.isfinite(e) and e > 0]
    if len(pts) < 2 or not budget > 0:
        return 0.5 * (lo + hi)
    (n1, e1), (n2, e2) = pts[-2], pts[-1]
    slope = (np.log(e2) - np.log(e1)) / (n2 - n1) if n2 != n1 else 0.0
    if not slope < 0:
        return 0.5 * (lo + hi)
    guess = n2 + (np.log(budget) - np.log(e2)) / slope
    nudge = 0.5 * np.log1p(face_tol)
    guess += {"hi": -nudge, "lo": nudge}.get(moved, 0.0)
    return float(np.clip(guess, lo + 0.1 * w, hi - 0.1 * w))


def decimate_to_budget(mesh, budget: float | None = None, *, min_faces: int = 32,
                       max_faces: int | None = None, quantile: float = 1.0, samples: int = DEFAULT_SAMPLES,
                       seed: int = 0, max_iters: int = 7, face_tol: float = 0.15) -> DecimationResult:
    """Fewest faces whose symmetric Hausdorff distance to `mesh` is <= budget (metres), to within
    `face_tol` of the face count (the bisection stops once its bracket is that narrow: each probe
    simplifies and measures the whole mesh, and the last probes of a 7-step bisection moved the
    count by a few percent).

    mesh: trimesh.Trimesh. A watertight input stays watertight (candidates that lose it are
    rejected). Returns the input unchanged when no reduction meets the budget.
    max_faces: the most faces the caller keeps (an object's visual_face_budget): no count above it
    is probed, and when the mesh simplified to it misses the budget, that mesh comes back with its
    error (hausdorff > budget). A room's voxel-solid shelf (49k faces, 4.5k kept) was probed at up
    to 13k faces and then simplified to 4.5k again.
    quantile < 1: the budget holds for that quantile of the symmetric sample distances instead of
    their maximum (the result's `hausdorff` stays the maximum, which may then pass the budget): for
    the visual-only background, where a few samples on a thin edge 2 cm off held a room's 644k faces
    at 347k (objects.BACKGROUND_ERROR_QUANTILE).
    """
    budget = default_budget(mesh) if budget is None else float(budget)
    n0 = len(mesh.faces)
    watertight = bool(mesh.is_watertight)
    best = DecimationResult(mesh, n0, n0, 0.0, 0.0, budget)
    if n0 <= min_faces:
        return best
    ref_pts = sample_surface(mesh, samples, seed, with_vertices=True)
    to_mesh = surface_distance_query(mesh)
    curve = []
    tried = []                                  # (log face count, judged error) of every valid probe

    method = "auto"

    def measure(count, how=None):
        nonlocal method
        # from the smallest candidate so far that met the budget, when it has more faces: every
        # later probe asks fewer, and a simplification costs by the faces it starts from (a
        # 92k-face voxel solid: 1.2 s by MeshLab, ~0.1 s from its 4.5k-face candidate). The error
        # is always measured against `mesh` itself
        source = best.mesh if best.faces_after > count else mesh
        cand = simplify_to_count(source, count, how or method)
        if how is None and method == "auto" and watertight:
            # one answer per mesh: fast-simplification either keeps this mesh closed or it does not
            fast_ok = cand.is_watertight and cand.vertices.shape[0] > 0 and not cand.metadata.get("meshlab")
            method = "fast" if fast_ok else "meshlab"
        if len(cand.faces) == 0 or (watertight and not cand.is_watertight):
            return cand, np.inf, np.inf, np.inf
        d1 = distance_to_surface(cand, ref_pts)
        d2 = to_mesh(sample_surface(cand, samples, seed + 1, with_vertices=True))
        h, m = float(max(d1.max(), d2.max())), float(0.5 * (d1.mean() + d2.mean()))
        curve.append((int(len(cand.faces)), h, m))
        # (candidate, the error the budget judges, mean, Hausdorff)
        e = float(np.quantile(np.concatenate([d1, d2]), quantile)) if quantile < 1.0 else h
        tried.append((float(np.log(len(cand.faces))), e))
        return cand, e, m, h

    # a bracket on log(face count): error grows (almost) monotonically as faces shrink
    lo, hi = np.log(min_faces), np.log(n0)      # lo: maybe too coarse; hi: the input itself
    if max_faces is not None and min_faces < max_faces < n0:
        # the cap first: every later probe then starts from its mesh (measure). "auto", not the
        # method that probe would pin: fast-simplification that keeps the mesh closed at the cap
        # can break it at min_faces, and one that breaks it at min_faces can keep it closed at
        # the cap (a room's box: 24 mm at the cap by MeshLab, 5 mm fast)
        cand, e, m, h = measure(int(max_faces), "auto")
        if watertight and e > budget and not cand.metadata.get("meshlab"):
            # fast-simplification may keep a closed mesh closed and still collapse it: a room's
            # box cut by its neighbour came out 72 mm off at its 250-face cap, where MeshLab's
            # collapse was 2 mm off; the cap's error is kept, so it must be the better one's
            alt = measure(int(max_faces), "meshlab")
            if alt[1] < e:
                cand, e, m, h = alt
        if np.isfinite(e):                        # a valid mesh at the cap: the bracket's top
            best = DecimationResult(cand, n0, len(cand.faces), h, m, budget)
            if e > budget:                        # the cap wins over the error budget
                best.curve = sorted(curve)
                return best
            hi = np.log(max_faces)
    cand, e, m, h = measure(min_faces)
    if e <= budget:
        best = DecimationResult(cand, n0, len(cand.faces), h, m, budget)
        best.curve = sorted(curve)
        return best
    lo = _floor(lo, cand, e)
    moved = None                                  # the end the last probe moved
    for _ in range(max_iters):
        if hi - lo <= np.log1p(face_tol) and best.faces_after < n0:
            break
        mid = next_probe(lo, hi, tried, budget, moved, face_tol)
        count = int(round(np.exp(mid)))
        if count >= np.exp(hi) * 0.97:
            break
        cand, e, m, h = measure(count)
        if e <= budget:
            hi, moved = mid, "hi"
            best = DecimationResult(cand, n0, len(cand.faces), h, m, budget)
        else:
            lo, moved = _floor(mid, cand, e), "lo"
    best.curve = sorted(curve)
    return best
