"""Mass of hollow and open objects: the shell model (issue #16 §5).

Solid volume x class density cannot weigh a mug: what a capture closes into a watertight solid is its
envelope, and the mug is a thin wall around air. Containers and thin-walled objects are weighed as a
shell instead: mass = shell area x areal density (wall thickness x material density), where the
shell is the object's convex envelope without its opening, and the areal density comes from the class
(the geometric middle of its common materials, so the worst relative error over them is smallest).
An object of no known container class still gets the shell model when its mesh shows an open cavity:
empty space inside its envelope walled in on five of six sides (a mug's inside, open at the top; a
mug lying down, open sideways), measured on a voxel grid. Every estimate carries its plausible range.

Areal densities (kg/m^2) are wall thickness x material density for the class's common materials
(published material densities; typical household wall thicknesses), never fitted to a benchmark:
ceramic 2.3 g/cm^3 at 4-6 mm (~11.5), glass 2.5 at 3-4 mm (~10), polypropylene / polystyrene
0.9-1.05 at 1.5-3 mm (1.4-2.7), paper / thin PS cups 0.3, aluminium 2.7 at 2 mm (5.4), cast iron
7.2 at 4 mm (28.8), sheet steel 7.9 at 0.6 mm (4.7).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# class word -> (low, high) areal density in kg/m^2 of shell (the estimate is their geometric mean)
AREAL_DENSITY: dict[str, tuple[float, float]] = {
    "mug": (2.7, 11.5),         # plastic 0.9 x 3 mm .. ceramic 2.3 x 5 mm
    "cup": (0.3, 9.2),          # paper / thin PS .. ceramic teacup 2.3 x 4 mm
    "glass": (5.0, 10.0),       # drinking glass 2.5 x 2-4 mm
    "bowl": (2.7, 11.5),        # plastic .. ceramic
    "plate": (2.7, 13.8),       # plastic .. ceramic 6 mm
    "pitcher": (1.4, 10.0),     # plastic 0.95 x 1.5 mm .. glass 2.5 x 4 mm
    "jug": (1.4, 10.0),
    "pot": (5.4, 28.8),         # aluminium 2 mm .. cast iron 4 mm
    "pan": (5.4, 28.8),
    "bucket": (1.9, 4.7),       # PE 0.95 x 2 mm .. sheet steel
    "basket": (1.0, 4.0),       # woven / thin plastic
    "bin": (1.9, 4.7),
    "vase": (10.0, 13.8),       # glass 4 mm .. ceramic 6 mm
    "container": (1.4, 4.7),    # food container: PP .. steel
    "tray": (1.4, 4.7),
}
# an open cavity measured on an object of no container class: plastic .. ceramic
UNKNOWN_OPEN = (1.4, 11.5)
# share of the envelope's volume an open cavity must hold to count (a mug's inside is ~60 %, a
# banana's or a drill's concave side is not walled in at all)
MIN_CAVITY_FRACTION = 0.2
# an envelope face belongs to the opening when its normal is within this angle of the open side
OPENING_DEGREES = 25.0


@dataclass
class Cavity:
    """Open cavity of a mesh: fraction of its convex envelope's volume that is walled-in empty space;
    axis [3]: the open side (unit, world) or None when closed on every side / no cavity."""

    fraction: float
    axis: np.ndarray | None


@dataclass
class ShellMass:
    """Mass properties of a thin shell. mass / range in kg, area in m^2, com [3], inertia [3, 3] about
    the COM (world axes); areal_density kg/m^2; key: the class word that set it ("open cavity" when
    the shape did); cavity: what was measured."""

    mass: float
    mass_range: tuple[float, float]
    area: float
    com: np.ndarray
    inertia: np.ndarray
    areal_density: float
    key: str
    cavity: Cavity


def _words(label: str) -> list[str]:
    import re

    return [w for w in re.split(r"[^a-z0-9]+", str(label).lower()) if w]


def shell_class(label: str) -> str | None:
    """The AREAL_DENSITY key a class name falls under (its head noun, last word first), or None."""
    for w in reversed(_words(label)):
        for cand in (w, w[:-1] if w.endswith("s") else None, w[:-2] if w.endswith("es") else None):
            if cand and cand in AREAL_DENSITY:
                return cand
    return None


def open_cavity(mesh, pitch: float | None = None) -> Cavity:
    """Measure the open cavity of a watertight mesh on a voxel grid (`pitch`, default 1/40 of its
    largest extent): empty cells inside the convex envelope with the solid in at least five of the
    six axis directions. The open side is the axis direction the cavity cells most often see out of."""
    v = np.asarray(mesh.vertices, np.float64)
    ext = float(np.ptp(v, axis=0).max()) if len(v) else 0.0
    if ext <= 0:
        return Cavity(0.0, None)
    pitch = pitch or ext / 40.0
    import trimesh
    from scipy import ndimage

    # solid: cells the surface passes through (dense area samples), the closed inside filled; an
    # opening connects a cavity to the outside, so it stays empty
    lo = v.min(axis=0) - pitch
    shape = tuple(np.ceil((v.max(axis=0) + pitch - lo) / pitch).astype(int) + 1)
    count = int(min(2_000_000, max(1000, 16.0 * float(mesh.area) / pitch**2)))
    pts, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
    idx = np.floor((np.vstack([pts, v]) - lo) / pitch).astype(int)
    occ = np.zeros(shape, bool)
    occ[tuple(np.clip(idx, 0, np.asarray(shape) - 1).T)] = True
    occ = ndimage.binary_fill_holes(ndimage.binary_closing(occ, iterations=1) | occ)
    # envelope: cell centres inside the convex hull (half a cell of slack)
    try:
        hull = mesh.convex_hull
    except Exception:           # degenerate meshes: no cavity to speak of
        return Cavity(0.0, None)
    grid = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    centres = lo + (grid + 0.5) * pitch
    n = np.asarray(hull.face_normals, np.float64)
    d = np.einsum("ij,ij->i", n, np.asarray(hull.triangles, np.float64)[:, 0])
    env = ((centres @ n.T - d[None, :]).max(axis=1) <= 0.5 * pitch).reshape(shape)
    empty = env & ~occ
    if not empty.any() or not env.any():
        return Cavity(0.0, None)
    walls = []
    for axis in range(3):
        walls.append(np.maximum.accumulate(occ, axis=axis))                 # solid somewhere before
        walls.append(np.flip(np.maximum.accumulate(np.flip(occ, axis), axis=axis), axis))  # after
    walled = np.stack(walls)                                                   # [6, ...]
    closed_sides = walled.sum(axis=0)
    cavity = empty & (closed_sides >= 5)
    frac = float(cavity.sum()) / float(env.sum())
    if frac <= 0:
        return Cavity(0.0, None)
    open_counts = [int((cavity & ~w).sum()) for w in walled]
    k = int(np.argmax(open_counts))
    if open_counts[k] == 0:
        return Cavity(frac, None)
    axis = np.zeros(3)
    axis[k // 2] = -1.0 if k % 2 == 0 else 1.0       # open before = towards -axis, after = +axis
    return Cavity(frac, axis)


def _surface_moments(tri: np.ndarray):
    """(area, centroid [3], second moment about the centroid [3, 3]) of a triangle set [F, 3, 3]
    with unit areal density (exact for each flat triangle)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = float(area.sum())
    centroid = (area[:, None] * (a + b + c) / 3.0).sum(0) / total
    a, b, c = a - centroid, b - centroid, c - centroid
    s = a + b + c
    outer = (np.einsum("fi,fj->fij", a, a) + np.einsum("fi,fj->fij", b, b) + np.einsum("fi,fj->fij", c, c)
             + np.einsum("fi,fj->fij", s, s))
    second = (area[:, None, None] * outer).sum(0) / 12.0
    return total, centroid, second


def shell_mass(mesh, label: str, *, cavity: Cavity | None = None) -> ShellMass | None:
    """The shell model for `mesh` (watertight, world Z-up) of class `label`, or None when it is not a
    shell: neither a container class nor an open cavity of MIN_CAVITY_FRACTION of its envelope.

    The shell is the convex envelope's surface without the opening: the faces facing the open side
    (measured, else +z for a container class: upright, open at the top)."""
    key = shell_class(label)
    cavity = open_cavity(mesh) if cavity is None else cavity
    if key is None and cavity.fraction < MIN_CAVITY_FRACTION:
        return None
    lo, hi = AREAL_DENSITY[key] if key else UNKNOWN_OPEN
    axis = cavity.axis if cavity.axis is not None and cavity.fraction >= MIN_CAVITY_FRACTION else \
        np.array([0.0, 0.0, 1.0])
    hull = mesh.convex_hull
    n = np.asarray(hull.face_normals, np.float64)
    wall = n @ axis < np.cos(np.radians(OPENING_DEGREES))
    tri = np.asarray(hull.triangles, np.float64)[wall]
    if len(tri) == 0:
        return None
    area, com, second = _surface_moments(tri)
    rho = float(np.sqrt(lo * hi))
    inertia = rho * (np.trace(second) * np.eye(3) - second)
    return ShellMass(mass=rho * area, mass_range=(lo * area, hi * area), area=area, com=com,
                     inertia=0.5 * (inertia + inertia.T), areal_density=rho,
                     key=key or "open cavity", cavity=cavity)
