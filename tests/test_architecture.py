"""The package's import structure: no cycles, no module importing a later stage, no reach-ins.

Every module of the package is parsed (ast, nothing is imported), imports inside functions
included: a lazy import is still a dependency, it only runs later. Folders map to their installed
names (exporters/ -> psimap.exporters, completion/ -> psimap.completion, sim/ -> psimap.sim).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = {"psimap": "psimap", "exporters": "psimap.exporters", "completion": "psimap.completion",
           "sim": "psimap.sim"}

# The import order of the stages, earliest first: a module may import its own stage and earlier
# ones. It follows the data flow of docs/architecture.md (frames -> SOGMM prior -> surfels rendered and trained
# -> scene.ckpt -> export), with three readings of it:
# - checkpoint / scene (the trained map as a value: surfels, labels, cameras, its file format, and
#   rendering / meshing of it) come before panoptic and train, which build one and return it;
#   train also resumes from one. Every later stage takes a Scene.
# - geometry (SOGMM prior, back-projected points, TSDF fusion) and render import neither each
#   other; the prior is fitted before the first surfel is rendered, so geometry comes first.
# - completion and sim are steps the export pipeline calls (complete a partial object, check the
#   written scene in MuJoCo): they come before exporters and never import it.
STAGES = [
    # shared helpers every stage uses: atomic writes, cameras, pixel / rotation / sampling maths
    ("base", ("psimap.io_utils", "psimap.camera", "psimap.transforms", "psimap.nonfinite", "psimap.cores")),
    ("data", ("psimap.data",)),
    ("geometry", ("psimap.geometry",)),
    # model-free pseudo-labels of a capture (`psimap segment`): planes and clusters of its frames
    ("segment", ("psimap.segment",)),
    # thread counts of the renderer's kernels (and torch) for the small per-view work of meshing
    ("render", ("psimap.render", "psimap.threads")),
    ("map", ("psimap.checkpoint", "psimap.scene")),
    ("panoptic", ("psimap.panoptic",)),
    ("train", ("psimap.train",)),
    ("metrics", ("psimap.metrics",)),
    ("completion", ("psimap.completion",)),
    ("sim", ("psimap.sim",)),
    ("exporters", ("psimap.exporters",)),
    # many captures through train -> export -> check as Dask tasks (`psimap batch`)
    ("batch", ("psimap.batch",)),
]
# Entry points may import any stage, and no stage imports them (psimap.options: the CLI's option
# tables, which list the choices the later stages register). The package root defines
# PsimapError (every stage raises it) and the lazy `psimap.load`; Python runs a package's
# __init__ before any of its submodules anyway, so an import of the root's own names is no edge.
FACADES = ("psimap", "psimap.__main__", "psimap.cli", "psimap.options", "psimap.demo", "psimap.api")
ROOT_NAMES = {"PsimapError", "__version__"}
# Compiled modules (psimap/render/csrc, built by the package build): no source to parse.
EXTENSIONS = {"psimap.render._native"}
# Known violations another branch of issue #15 removes (one panoptic training loop: the trainer and
# the panoptic phase stop importing each other). Each check fails once its entry is stale, so the
# entry is deleted when that branch lands.
PENDING_CYCLES: list = []
PENDING_PRIVATE: set = set()


def modules() -> dict[str, Path]:
    """Dotted installed name -> source file of every module of the package."""
    out = {}
    for folder, name in FOLDERS.items():
        for path in sorted((REPO / folder).rglob("*.py")):
            parts = list(path.relative_to(REPO / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([name, *parts])] = path
    return out


MODULES = modules()


def is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def parent(name: str) -> str:
    return name.rpartition(".")[0]


def submodule(name: str) -> str | None:
    """`name` if it is a module of the package (or a compiled one), else None."""
    return name if name in MODULES or name in EXTENSIONS else None


def owning_module(dotted: str) -> str | None:
    """The longest prefix of `dotted` that is a module of the package."""
    while dotted:
        if submodule(dotted):
            return dotted
        dotted = parent(dotted)
    return None


class Imports(ast.NodeVisitor):
    """Import statements and attribute uses of imported modules in one module, with line numbers."""

    def __init__(self, module: str):
        self.module = module
        self.edges: list[tuple[str, int]] = []            # (imported module, line)
        self.names: list[tuple[str, str, int]] = []       # (module, name taken from it, line)
        self.aliases: dict[str, str] = {}                 # local name -> module it is bound to

    def _base(self, level: int, target: str | None) -> str:
        if not level:
            return target or ""
        here = self.module if is_package(self.module) else parent(self.module)
        for _ in range(level - 1):
            here = parent(here)
        return f"{here}.{target}" if target else here

    def visit_Import(self, node: ast.Import) -> None:
        for a in node.names:
            if not a.name.startswith("psimap"):
                continue
            self.edges.append((owning_module(a.name), node.lineno))
            if a.asname:
                self.aliases[a.asname] = a.name
            else:
                self.aliases[a.name.split(".")[0]] = a.name.split(".")[0]

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        base = self._base(node.level, node.module)
        if not base.startswith("psimap"):
            return
        for a in node.names:
            sub = submodule(f"{base}.{a.name}")
            if sub:
                self.edges.append((sub, node.lineno))
                self.aliases[a.asname or a.name] = sub
            else:
                self.edges.append((owning_module(base), node.lineno))
                self.names.append((owning_module(base), a.name, node.lineno))

    def visit_Attribute(self, node: ast.Attribute) -> None:
        chain, n = [], node
        while isinstance(n, ast.Attribute):
            chain.append(n.attr)
            n = n.value
        if isinstance(n, ast.Name) and n.id in self.aliases:
            dotted = ".".join([self.aliases[n.id], *reversed(chain)])
            mod = owning_module(dotted)
            rest = dotted[len(mod) + 1:].split(".") if mod and len(dotted) > len(mod) else []
            if mod and rest:
                self.names.append((mod, rest[0], node.lineno))
            return             # the inner Attribute nodes are this chain's prefixes
        self.generic_visit(node)


def parse(name: str) -> Imports:
    v = Imports(name)
    v.visit(ast.parse(MODULES[name].read_text(), filename=str(MODULES[name])))
    return v


PARSED = {name: parse(name) for name in MODULES}


def stage_of(name: str) -> int | None:
    best, rank = -1, None
    for i, (_, prefixes) in enumerate(STAGES):
        for p in prefixes:
            if (name == p or name.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    return rank


def where(name: str, line: int) -> str:
    return f"{MODULES[name].relative_to(REPO)}:{line}"


def graph() -> dict[str, set[str]]:
    """module -> modules it imports (the root package and compiled modules left out, see above)."""
    g = {}
    for name, imp in PARSED.items():
        g[name] = {t for t, _ in imp.edges if t in MODULES and t != "psimap" and t != name}
    return g


def test_every_module_has_a_stage():
    loose = [m for m in MODULES if m not in FACADES and stage_of(m) is None]
    assert not loose, f"add these modules to STAGES (or FACADES) in {Path(__file__).name}: {loose}"


def test_no_import_cycle():
    g = graph()
    # Tarjan's strongly connected components, iteratively (every component > 1 node is a cycle)
    index, low, on_stack, stack, cycles, counter = {}, {}, set(), [], [], [0]
    for root in sorted(g):
        if root in index:
            continue
        work = [(root, iter(sorted(g[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, it = work[-1]
            nxt = next(it, None)
            if nxt is not None:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter[0]
                    counter[0] += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(g[nxt]))))
                elif nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    cycles.append(sorted(comp))
    stale = [sorted(p) for p in PENDING_CYCLES if not any(p <= set(c) for c in cycles)]
    assert not stale, f"no longer a cycle: delete it from PENDING_CYCLES: {stale}"
    detail = []
    for comp in cycles:
        if set(comp) in PENDING_CYCLES:
            continue
        members = set(comp)
        edges = sorted({f"{a} -> {b} ({where(a, line)})" for a in comp for b, line in PARSED[a].edges
                        if b in members and b != a})
        detail.append(" / ".join(edges))
    assert not detail, "import cycles:\n" + "\n".join(detail)


def test_no_module_imports_a_later_stage():
    bad = []
    for name, imp in PARSED.items():
        if name in FACADES:
            continue
        mine = stage_of(name)
        for target, line in imp.edges:
            if target is None or target == "psimap" or (target not in FACADES and stage_of(target) is None):
                continue                        # the root's own names; a module without a stage is
                                                # reported by test_every_module_has_a_stage
            if target in FACADES:
                bad.append(f"{where(name, line)}: {name} imports the entry point {target}")
            elif stage_of(target) > mine:
                bad.append(f"{where(name, line)}: {name} ({STAGES[mine][0]}) imports {target} "
                           f"({STAGES[stage_of(target)][0]})")
    assert not bad, "imports of a later stage:\n" + "\n".join(bad)


def test_stages_use_only_the_roots_own_names():
    """`psimap.load` is the users' entry point (it returns the façade's Scene, which reaches the
    export stage); inside the package a stage loads a checkpoint with psimap.scene.load_scene."""
    bad = [f"{where(name, line)}: psimap.{attr}" for name, imp in PARSED.items() if name not in FACADES
           for mod, attr, line in imp.names if mod == "psimap" and attr not in ROOT_NAMES]
    assert not bad, "stages using the package root's façade:\n" + "\n".join(bad)


def test_no_private_names_across_modules():
    """`from m import _x` and `m._x` only inside m itself; a package's private submodules (the
    compiled `_native`) are for that package's own modules."""
    bad = {}                                          # (module, private name) -> where
    for name, imp in PARSED.items():
        for mod, attr, line in imp.names:
            if attr.startswith("_") and not attr.startswith("__") and mod != name:
                bad.setdefault((name, f"{mod}.{attr}"), where(name, line))
        for target, line in imp.edges:
            last = (target or "").rpartition(".")[2]
            if last.startswith("_") and not last.startswith("__") and not name.startswith(parent(target) + "."):
                bad.setdefault((name, target), where(name, line))
    stale = PENDING_PRIVATE - set(bad)
    assert not stale, f"fixed: delete from PENDING_PRIVATE: {sorted(stale)}"
    found = sorted(f"{at}: {name} uses {what}" for (name, what), at in bad.items() if (name, what) not in PENDING_PRIVATE)
    assert not found, "private names used across modules:\n" + "\n".join(found)


@pytest.mark.parametrize("source, expected", [
    ("from psimap.render.api import _probe\n", "uses psimap.render.api._probe"),
    ("from psimap.exporters import texture as T\nT._to_uint8(1)\n", "uses psimap.exporters.texture._to_uint8"),
    ("import psimap.render.api\npsimap.render.api._check(1)\n", "uses psimap.render.api._check"),
])
def test_the_checks_see_reach_ins(source, expected):
    """The parser itself: the three spellings of a reach-in are all found."""
    v = Imports("psimap.threads")
    v.visit(ast.parse(source))
    found = [f"uses {mod}.{attr}" for mod, attr, _ in v.names if attr.startswith("_")]
    assert expected in found


def test_the_cycle_check_sees_lazy_imports():
    v = Imports("psimap.render.api")
    v.visit(ast.parse("def f():\n    from psimap.render.native import rasterize_native\n"))
    assert ("psimap.render.native", 2) in v.edges
