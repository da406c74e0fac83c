"""Step 7: physical properties of a watertight object mesh (mass, centre of mass, inertia, friction).

mass = volume x density, with the density looked up by class name in an editable table. The values
are bulk densities of the *reconstructed envelope* (what a scan's watertight mesh encloses), set from
general knowledge of each class (materials, typical fill), never fitted to a benchmark set.
All geometry in float64.
"""
from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from psimap import PsimapError

# kg / m^3 of the volume a watertight scan encloses. Edit freely, or pass `densities=` /
# load_density_table(json) to override. Keys are matched against the class name's words.
DENSITY_KG_M3: dict[str, float] = {
    "default": 500.0,        # unknown indoor object: mix of wood / plastic / air
    # food and kitchen
    "fruit": 950.0, "banana": 950.0, "apple": 850.0, "orange": 900.0, "lemon": 950.0,
    "bottle": 850.0,         # liquid (~1000) filled to ~85 %, thin plastic/glass wall
    "can": 900.0,            # filled drink/food can with headspace
    "box": 200.0,            # packaged dry food (cereal, crackers): ~0.15-0.25 g/cm^3
    "mug": 2300.0,           # ceramic (stoneware ~2.3 g/cm^3); the scan's walls are the solid
    "cup": 2300.0, "bowl": 2300.0, "plate": 2300.0, "vase": 2300.0,
    # tools and electronics
    "drill": 1200.0,         # ABS housing (~1.1) with steel motor/chuck and battery pack
    "tool": 1200.0, "hammer": 2500.0, "scissors": 3000.0,
    "laptop": 1000.0, "keyboard": 600.0, "monitor": 400.0, "tv": 400.0, "television": 400.0,
    "phone": 1800.0, "remote": 800.0, "speaker": 600.0, "printer": 400.0,
    # furniture and household (envelopes contain air: drawers, cushions, frames)
    "chair": 150.0, "table": 250.0, "desk": 250.0, "sofa": 120.0, "couch": 120.0, "bed": 150.0,
    "cabinet": 200.0, "shelf": 200.0, "bookshelf": 250.0, "dresser": 250.0, "nightstand": 250.0,
    "furniture": 200.0,      # psimap segment's class for any cluster over 0.6 m: a cabinet's envelope
    "book": 700.0, "books": 700.0, "box_cardboard": 80.0, "basket": 100.0, "bin": 100.0,
    "foam": 40.0, "sponge": 30.0,      # polyurethane / EVA foam: 20-60 kg/m^3
    "pillow": 40.0, "cushion": 40.0, "towel": 200.0, "lamp": 300.0, "plant": 400.0, "pot": 1500.0,
    "toy": 300.0, "ball": 100.0, "bag": 150.0, "shoe": 400.0, "clock": 500.0, "sink": 1500.0,
    "toilet": 1500.0, "refrigerator": 250.0, "microwave": 350.0, "oven": 350.0,
}

# Plausible spread of a solid's mass around volume x density (a factor: low = mass / f, high =
# mass x f): packaging and fill vary, liquids less so, an unknown class most.
DENSITY_SPREAD: dict[str, float] = {"default": 3.0, "bottle": 1.3, "can": 1.3, "fruit": 1.4, "banana": 1.4,
                                    "apple": 1.4, "orange": 1.4, "lemon": 1.4, "box": 2.0, "book": 1.3,
                                    "books": 1.3}

# Coulomb sliding friction coefficient per class (MuJoCo `friction[0]`).
FRICTION: dict[str, float] = {
    "default": 0.7,
    "fruit": 0.6, "banana": 0.6, "apple": 0.6, "orange": 0.6,
    "bottle": 0.5, "can": 0.4, "box": 0.5, "mug": 0.6, "cup": 0.6, "bowl": 0.6, "plate": 0.5,
    "drill": 0.6, "tool": 0.6, "laptop": 0.5, "book": 0.5, "books": 0.5, "ball": 0.9,
    "pillow": 1.0, "cushion": 1.0, "towel": 1.0, "shoe": 0.9, "chair": 0.6, "table": 0.5,
}

# Classes exported as static scene geometry (no freejoint / no RigidBodyAPI): heavy furniture that a
# robot treats as part of the room. Matched like the tables above (exact name, then its words).
# Edit freely, or pass `static_classes=` to export_scene (CLI: --static-classes, --dynamic-all).
STATIC_CLASSES: frozenset[str] = frozenset({
    "table", "desk", "counter", "countertop", "cabinet", "shelf", "shelves", "bookshelf", "bookcase",
    "dresser", "wardrobe", "closet", "bed", "sofa", "couch", "refrigerator", "fridge", "oven", "stove",
    "dishwasher", "washer", "dryer", "sink", "toilet", "bathtub", "piano", "nightstand", "sideboard",
    "furniture",             # psimap segment's class for any cluster over 0.6 m (docs/segment.md)
})


def is_static_class(label: str, static_classes=None) -> bool:
    """Whether objects of class `label` are exported static (same word matching as `lookup`)."""
    table = {k: 1.0 for k in (STATIC_CLASSES if static_classes is None else static_classes)}
    if not table:
        return False
    table.setdefault("default", 0.0)
    return lookup(table, label)[0] > 0


def parse_static_classes(text: str, dynamic_all: bool = False):
    """CLI value -> the static class set: "" = the default list, "none" or dynamic_all = empty,
    else comma-separated class names (they replace the default list)."""
    if dynamic_all or text.strip().lower() == "none":
        return frozenset()
    if not text.strip():
        return STATIC_CLASSES
    names = frozenset("_".join(_words(t)) for t in text.split(","))
    names = frozenset(n for n in names if n)
    if not names:
        raise PsimapError(f"--static-classes {text!r}: no class names (comma-separated, or 'none')")
    return names


def _words(label: str) -> list[str]:
    return [w for w in re.split(r"[^a-z0-9]+", label.lower()) if w]


def lookup(table: dict[str, float], label: str) -> tuple[float, str]:
    """Value for a class name: exact name, then its last word, then any word, else "default".

    Returns (value, matched key). "mustard_bottle" -> "bottle", "power drill" -> "drill".
    """
    key = "_".join(_words(label))
    if key in table:
        return float(table[key]), key
    words = _words(label)
    for w in reversed(words):           # the head noun is usually last: "coffee mug"
        if w in table:
            return float(table[w]), w
        if w.endswith("s") and w[:-1] in table:
            return float(table[w[:-1]]), w[:-1]
    return float(table["default"]), "default"


def load_density_table(path: str | Path) -> dict[str, float]:
    """Read a JSON {class name: kg/m^3} overriding/extending the defaults."""
    try:
        extra = json.loads(Path(path).read_text())
        table = dict(DENSITY_KG_M3)
        table.update({str(k).lower(): float(v) for k, v in extra.items()})
    except (OSError, ValueError, AttributeError, TypeError) as e:
        raise PsimapError(f"density table {path}: not a JSON object of class name -> kg/m^3 ({e})")
    if any(not np.isfinite(v) or v <= 0 for v in table.values()):
        raise PsimapError(f"density table {path}: densities must be positive numbers")
    return table


@dataclass
class Physics:
    mass: float                 # kg
    com: np.ndarray             # [3] world frame, metres
    inertia: np.ndarray         # [3, 3] about the COM, world axes, kg m^2
    principal_inertia: np.ndarray  # [3] eigenvalues (ascending)
    principal_axes: np.ndarray  # [3, 3] columns = principal axes (right-handed)
    volume: float               # m^3
    density: float              # kg/m^3 used (a shell's: its mass over the volume it encloses)
    density_key: str            # table key that matched the label ("shell:<key>" for a shell)
    friction: float
    model: str = "solid"        # "solid" (volume x density) | "shell" (exporters.shell)
    mass_range: tuple = (0.0, 0.0)   # plausible kg, low and high
    areal_density: float = 0.0  # kg/m^2 of a shell's wall (0 for a solid)


def mass_properties(mesh, label: str, *, densities: dict[str, float] | None = None,
                    frictions: dict[str, float] | None = None,
                    density: float | None = None, shell: bool = True) -> Physics:
    """Mass, centre of mass and inertia of a watertight mesh (trimesh.Trimesh, metres, world frame).

    Containers and objects with a measured open cavity are thin shells (exporters.shell: a mug is
    a wall around air), unless `shell` is False or a `density` is given; everything else is a solid
    of its class's density. Each mass comes with a plausible range (`Physics.mass_range`).
    The mesh must enclose a positive volume (repair first); otherwise PsimapError.
    """
    table = DENSITY_KG_M3 if densities is None else densities
    if density is None:
        density, key = lookup(table, label)
    else:
        key = "explicit"
    friction, _ = lookup(FRICTION if frictions is None else frictions, label)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    if len(f) == 0 or not np.isfinite(v).all():
        raise PsimapError(f"mass properties of '{label}': empty or non-finite mesh")
    volume, com, inertia_unit = _integrate(v, f)
    if not (volume > 0 and np.isfinite(volume)):
        raise PsimapError(f"mass properties of '{label}': mesh encloses no volume ({volume:.3g} m^3)")
    mass = float(volume * density)
    inertia = inertia_unit * density
    model, spread = "solid", DENSITY_SPREAD.get(key, DENSITY_SPREAD["default"] if key == "default" else 1.6)
    mass_range, areal = (mass / spread, mass * spread), 0.0
    sh = None
    if shell and key != "explicit":
        from psimap.exporters.shell import shell_mass

        sh = shell_mass(mesh, label)
    if sh is not None:
        mass, com, inertia = float(sh.mass), np.asarray(sh.com, np.float64), np.asarray(sh.inertia, np.float64)
        model, mass_range, areal, density, key = "shell", sh.mass_range, sh.areal_density, mass / volume, \
            f"shell:{sh.key}"
    inertia = 0.5 * (inertia + inertia.T)
    evals, evecs = np.linalg.eigh(inertia)
    if not (evals > 0).all():
        # a closed but self-intersecting surface integrates to an impossible body (MuJoCo and
        # PhysX reject it, USD validation flags it)
        raise PsimapError(f"mass properties of '{label}': inertia is not positive definite "
                          "(self-intersecting surface)")
    if np.linalg.det(evecs) < 0:
        evecs[:, 2] *= -1
    return Physics(mass=mass, com=com, inertia=inertia, principal_inertia=evals,
                   principal_axes=evecs, volume=float(volume), density=float(density),
                   density_key=key, friction=float(friction), model=model,
                   mass_range=(float(mass_range[0]), float(mass_range[1])), areal_density=float(areal))


def centre_of_volume(mesh) -> np.ndarray:
    """[3] the centroid of the solid a closed trimesh encloses (`_integrate`); the vertices' mean
    for one that encloses no volume (trimesh's center_mass divides by zero there)."""
    return _integrate(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces))[1]


def _integrate(v: np.ndarray, f: np.ndarray):
    """Volume, centroid, and unit-density inertia about the centroid of a closed triangle mesh.

    Exact polyhedral integrals (divergence theorem over signed tetrahedra from a reference point
    near the mesh, which keeps float64 cancellation small far from the origin).
    v: [V, 3] float64, f: [F, 3].
    """
    ref = v.mean(axis=0)
    a, b, c = v[f[:, 0]] - ref, v[f[:, 1]] - ref, v[f[:, 2]] - ref     # [F, 3] each
    det = np.einsum("ij,ij->i", a, np.cross(b, c))                     # 6 x signed tet volume
    vol = det.sum() / 6.0
    if vol == 0:
        return 0.0, ref.copy(), np.zeros((3, 3))
    centroid_rel = (det[:, None] * (a + b + c)).sum(axis=0) / (24.0 * vol)
    # second moments: integral of x_i x_j over a tet (0, a, b, c) = det/120 * (sum_k p_ki p_kj + s_i s_j)
    s = a + b + c
    outer = (np.einsum("fi,fj->fij", a, a) + np.einsum("fi,fj->fij", b, b)
             + np.einsum("fi,fj->fij", c, c) + np.einsum("fi,fj->fij", s, s))
    second = (det[:, None, None] * outer).sum(axis=0) / 120.0           # about ref
    # shift to the centroid (parallel axis on the second moment)
    second_c = second - vol * np.outer(centroid_rel, centroid_rel)
    inertia = np.trace(second_c) * np.eye(3) - second_c
    return float(vol), ref + centroid_rel, inertia
