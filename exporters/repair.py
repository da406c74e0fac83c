"""Step 2: clean and repair an object mesh so that only sound, watertight geometry reaches a writer.

Order: drop non-finite vertices and degenerate / duplicate faces -> keep the largest connected
component(s) (floaters go) -> consistent outward orientation -> close small holes (pymeshlab) ->
if still not watertight and a volume is needed, rebuild the surface with fTetWild (pytetwild) ->
reject what is still degenerate (flat, sliver, no volume) with a reason instead of passing it on.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# A component is kept when its area is at least this fraction of the largest one: a scan's object
# is one piece; pieces this small are floaters or reconstruction noise.
KEEP_COMPONENT_AREA_FRACTION = 0.2


@dataclass
class RepairResult:
    mesh: object | None            # trimesh.Trimesh or None when rejected
    ok: bool
    watertight: bool
    reason: str = ""               # why it was rejected (empty when ok)
    steps: list[str] = field(default_factory=list)   # what was done, for the report


def _clean(mesh):
    import trimesh

    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(f):
        good_v = np.isfinite(v).all(axis=1)
        f = f[good_v[f].all(axis=1)]
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    m = trimesh.Trimesh(v, f, process=True, validate=False)   # merges duplicate vertices
    if len(m.faces):
        scale = max(float(np.linalg.norm(m.extents)), 1e-12)
        m.update_faces(m.area_faces > (1e-9 * scale) ** 2)       # zero-area faces
        m.update_faces(m.unique_faces())
        m.remove_unreferenced_vertices()
    return m


def consistent_winding(faces: np.ndarray) -> np.ndarray:
    """faces [F, 3] with some flipped so that each edge two faces share runs in opposite directions
    in them (edges of one or of three and more faces tie nothing, as in trimesh). Each connected
    piece keeps the orientation most of its faces have; a piece that has none (a Moebius strip)
    stays as it is. What trimesh.repair.fix_winding does (which keeps the winding of the face its
    walk starts from), from one connected-components pass over the faces' two orientations (face f
    as drawn and flipped: a shared edge ties the same or the opposite orientations of its two
    faces) where trimesh walks the face pairs in Python: 15.2 s of the real capture's (7-Scenes
    chess) export repaired the surfel-projected candidates of 46 objects, most of it that walk."""
    import trimesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n = len(f)
    if n < 2:
        return f.copy()
    pairs, edges = trimesh.graph.face_adjacency(f, return_edges=True)           # [E, 2], [E, 2]
    if len(pairs) == 0:
        return f.copy()
    a, b = pairs[:, 0], pairs[:, 1]
    u, w = edges[:, :1], edges[:, 1:]

    def runs_u_to_w(face):                  # [E] whether each face holds the directed edge u -> w
        return ((face == u) & (np.roll(face, -1, axis=1) == w)).any(1)
    flip_tie = runs_u_to_w(f[a]) == runs_u_to_w(f[b])     # the same direction: one must flip
    # nodes 0..n-1: faces as drawn, n..2n-1: flipped
    src = np.concatenate([a, a + n])
    dst = np.concatenate([np.where(flip_tie, b + n, b), np.where(flip_tie, b, b + n)])
    graph = coo_matrix((np.ones(len(src), np.int8), (src, dst)), shape=(2 * n, 2 * n))
    _, label = connected_components(graph, directed=False)
    drawn, flipped = label[:n], label[n:]
    # the two labels of a piece: keep the one that holds more of its faces as drawn (a piece with no
    # consistent winding has one label for both orientations of every face: nothing flips)
    piece = np.minimum(drawn, flipped)
    as_drawn = np.bincount(piece, weights=drawn == piece, minlength=2 * n)
    total = np.bincount(piece, minlength=2 * n)
    keep_low = as_drawn >= total - as_drawn               # keep the lower label's orientation
    flip = (drawn == piece) != keep_low[piece]
    out = f.copy()
    out[flip] = out[flip][:, ::-1]
    return out


def fix_winding(mesh) -> None:
    """trimesh.repair.fix_winding's job in place (`consistent_winding`); nothing when the mesh is
    consistently wound already."""
    if len(mesh.faces) and not mesh.is_winding_consistent:
        mesh.faces = consistent_winding(mesh.faces)


def _largest_components(mesh, fraction: float):
    import trimesh

    # the face-adjacency components counted first: most meshes are one piece, and split() builds
    # a mesh per piece (the room export's 62 calls: 3.1 s, most of them for one piece)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    if len(labels) == 0 or int(labels.max()) == 0:
        return mesh, 0
    parts = mesh.split(only_watertight=False)
    if len(parts) <= 1:
        return mesh, 0
    areas = np.array([p.area for p in parts])
    keep = [p for p, a in zip(parts, areas) if a >= fraction * areas.max()]
    return trimesh.util.concatenate(keep), len(parts) - len(keep)


def _close_holes(mesh, max_hole_edges: int):
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int32)))
    try:
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
        # selfintersection=False: the default refuses any patch touching the rim, which leaves the
        # open bottom of a scanned object (where it meets its support) unclosed
        ms.meshing_close_holes(maxholesize=max_hole_edges, newfaceselected=False, selfintersection=False)
    except Exception:   # pymeshlab raises on some inputs; the tetwild path below still applies
        pass
    out = ms.current_mesh()
    return trimesh.Trimesh(out.vertex_matrix(), out.face_matrix(), process=True)


def drop_slivers(mesh, fraction: float = KEEP_COMPONENT_AREA_FRACTION):
    """Clean a mesh and keep only its significant components (trimesh in, trimesh out)."""
    m = _clean(mesh)
    if len(m.faces) == 0:
        return m
    return _largest_components(m, fraction)[0]


def _tetwild_surface(mesh, edge_fraction: float):
    """Watertight outer surface of fTetWild's tetrahedralisation (robust to holes and self-intersection)."""
    import pytetwild
    import trimesh

    tv, tt = pytetwild.tetrahedralize(np.asarray(mesh.vertices, np.float64),
                                      np.asarray(mesh.faces, np.int32),
                                      edge_length_fac=edge_fraction, num_opt_iter=20,
                                      num_threads=1, quiet=True)
    if len(tt) == 0:
        return None
    tt = np.asarray(tt, np.int64)
    # each tet face, oriented outward for a positively oriented tet; boundary = faces seen once
    faces = np.concatenate([tt[:, [1, 2, 3]], tt[:, [0, 3, 2]], tt[:, [0, 1, 3]], tt[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = faces[counts[inv.ravel()] == 1]
    out = trimesh.Trimesh(np.asarray(tv, np.float64), boundary, process=True)
    trimesh.repair.fix_normals(out)
    return out


def repair_mesh(mesh, *, need_volume: bool = True, min_thickness: float = 0.002,
                keep_fraction: float = KEEP_COMPONENT_AREA_FRACTION,
                allow_tetwild: bool = False, pitch: float | None = None, support_z: float | None = None,
                points: np.ndarray | None = None, views=None, open_under: float | None = None) -> RepairResult:
    """Clean `mesh` (trimesh.Trimesh, metres) for export.

    need_volume: the object is dynamic and needs mass, so it must be watertight with positive
    volume; background (static) meshes pass need_volume=False and only get cleaned.
    min_thickness: smallest extent (m) along the thinnest principal axis; thinner is "flat" and
    cannot be simulated as a solid. allow_tetwild: when hole closing fails, rebuild the surface
    with fTetWild (robust, but minutes per object on a laptop CPU, hence off by default).
    pitch: voxel size (m) of a fused source; when given, an open mesh is closed as the voxel solid
    it encloses (exporters.solidify, resting on the plane z = support_z when given, with the extra
    observed surface points [P, 3], carved by the free space of `views` when given, opened under a
    furniture top at height `open_under`) before ear-cut hole filling is tried.
    """
    import trimesh

    steps: list[str] = []
    if mesh is None or len(getattr(mesh, "faces", [])) == 0:
        return RepairResult(None, False, False, "empty mesh")
    m = _clean(mesh)
    if len(m.faces) < 4:
        return RepairResult(None, False, False, "fewer than 4 valid faces after removing degenerate ones")
    m, dropped = _largest_components(m, keep_fraction)
    if dropped:
        steps.append(f"removed {dropped} floating component(s)")
    if not need_volume:
        fix_winding(m)
        return RepairResult(m, True, bool(m.is_watertight), "", steps)

    thickness = _principal_thickness(m)
    if thickness < min_thickness:
        return RepairResult(None, False, False,
                            f"flat: thickness {thickness * 1000:.2f} mm < {min_thickness * 1000:.1f} mm")
    if not m.is_watertight and pitch is not None:
        from psimap.exporters.solidify import solidify

        solid = solidify(m, float(pitch), support_z, points=points, views=views, open_under=open_under)
        if solid is not None:
            m = solid
            steps.append({"carved": f"carved from the views' free space ({pitch * 1000:.1f} mm voxels)",
                          "enclosed": f"closed as a voxel solid ({pitch * 1000:.1f} mm)",
                          "shell": f"encloses nothing: thickened to a {pitch * 1000:.0f} mm voxel band",
                          }[solid.metadata["solidify"]])
    if not m.is_watertight:
        m2 = m
        for _ in range(3):
            m2 = _close_holes(m2, max_hole_edges=len(m2.faces) + 3)
            if m2.is_watertight and len(m2.split(only_watertight=False)) == 1:
                break
            # hole filling can pinch off 2-face pockets at a ragged rim: drop them, close again
            m2 = drop_slivers(m2, keep_fraction)
        if m2.is_watertight and len(m2.split(only_watertight=False)) == 1:
            m = m2
            steps.append("closed holes")
        elif allow_tetwild:
            m3 = _tetwild_surface(m, edge_fraction=0.03)
            if m3 is not None and m3.is_watertight:
                m3, _ = _largest_components(m3, keep_fraction)
                m = m3
                steps.append("rebuilt watertight surface (fTetWild)")
    if not m.is_watertight:
        return RepairResult(None, False, False, "could not be made watertight")
    fix_winding(m)
    if m.volume < 0:
        m.invert()
        steps.append("fixed inverted orientation")
    # fix_normals' other half (its winding walk would only redo fix_winding's work, in Python: ~3 s
    # a chess export on the few meshes no winding makes consistent)
    trimesh.repair.fix_inversion(m, multibody=True)
    vol = float(m.volume)
    bbox_vol = float(np.prod(m.extents))
    if not (vol > 0) or vol < 1e-4 * bbox_vol or vol < min_thickness ** 3:
        return RepairResult(None, False, False, f"zero volume ({vol:.3g} m^3)")
    thickness = _principal_thickness(m)
    if thickness < min_thickness:
        return RepairResult(None, False, False,
                            f"sliver: thickness {thickness * 1000:.2f} mm < {min_thickness * 1000:.1f} mm")
    return RepairResult(m, True, True, "", steps)


def _principal_thickness(mesh) -> float:
    """Extent of the vertices along their thinnest principal direction (metres)."""
    v = np.asarray(mesh.vertices, np.float64)
    if len(v) < 3:
        return 0.0
    c = v - v.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    proj = c @ vt[-1]
    return float(proj.max() - proj.min())
