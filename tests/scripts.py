"""Import a benchmarks/ or examples/ script as a module (neither folder is a package)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script(relpath: str, name: str):
    """ROOT/relpath imported as module `name`. Its folder goes on sys.path (a benchmark imports its
    sibling _results) and the module into sys.modules (dataclasses look their module up there)."""
    path = ROOT / relpath
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
