"""The batch manifest: which captures to process and with which options (TOML or JSON).

```toml
[defaults]                       # every capture, unless it says otherwise
formats = ["mjcf", "usd"]        # export formats (exporters.formats.FORMATS) or "all"
train = { iters = 450 }          # TrainConfig overrides (psimap/train/config.py)

[[captures]]
path = "captures/kitchen"        # a capture folder, relative to the manifest's folder

[[captures]]
path = "captures/lab_*"          # a glob: every folder it matches is one capture
up = "+y"
completion = "none"
```

JSON holds the same keys: {"defaults": {...}, "captures": [{...}, ...]}. Standard library only: the
whole manifest is checked (every path, name and option) before any work starts.
"""
from __future__ import annotations

import glob
import hashlib
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

from psimap import PsimapError

# option -> (type, default, help) of one capture; `train` is a table of TrainConfig fields
OPTIONS = {
    "formats": ((list, str), ["mjcf"], "export formats: a list of names or \"all\""),
    "completion": (str, "auto", "object completion (psimap export --completion)"),
    "up": (str, "auto", "which way is up in the capture (psimap export --up)"),
    "check": (bool, True, "the MuJoCo settle check at export and the read-back check after it"),
    "static_classes": (str, "", "classes exported static (psimap export --static-classes)"),
    "min_dynamic": ((int, float), 0.5, "the export's outcome threshold (psimap export --min-dynamic)"),
    "seed": (int, 0, "training and export seed"),
    "train": (dict, {}, "TrainConfig overrides, e.g. {iters = 200, panoptic_iters = 100}"),
}
CAPTURE_KEYS = {"path", "name"}
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")      # one safe path component per capture


@dataclass(frozen=True)
class Capture:
    """One capture of the batch: its data folder, its output name (DIR/<name>/) and its options."""

    name: str
    data: str                                   # absolute path of the capture folder
    options: dict = field(default_factory=dict)

    def key(self, stage: str = "check") -> str:
        """A short hash of what decides the result of the stages up to `stage` (train: the data path,
        the training options and the seed; check: everything): a finished stage is run again only
        when it changes."""
        used = {"data": self.data, **{k: v for k, v in self.options.items()
                                      if stage != "train" or k in ("train", "seed")}}
        return hashlib.sha1(json.dumps(used, sort_keys=True).encode()).hexdigest()[:16]


def read_manifest(path) -> list[Capture]:
    """The captures a manifest lists, options resolved (defaults, then the capture's own); PsimapError
    (one line) for a missing or malformed manifest, an unknown option, a bad value, a path that
    matches no folder or two captures with the same name."""
    p = Path(path)
    if not p.is_file():
        raise PsimapError(f"manifest {path}: no such file")
    text = p.read_bytes()
    try:
        if p.suffix.lower() == ".json":
            doc = json.loads(text)
        else:
            import tomllib

            doc = tomllib.loads(text.decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as e:     # tomllib.TOMLDecodeError and JSONDecodeError are ValueErrors
        kind = "JSON" if p.suffix.lower() == ".json" else "TOML"
        raise PsimapError(f"manifest {path}: not valid {kind}: {str(e).splitlines()[0]}") from None
    return parse_manifest(doc, base=p.resolve().parent, where=f"manifest {path}")


def parse_manifest(doc, *, base: Path, where: str = "manifest") -> list[Capture]:
    """Captures of a parsed manifest document (see the module doc); relative paths from `base`."""
    if not isinstance(doc, dict):
        raise PsimapError(f"{where}: expected a table with 'captures'")
    unknown = set(doc) - {"defaults", "captures"}
    if unknown:
        raise PsimapError(f"{where}: unknown key {sorted(unknown)[0]!r} (expected 'defaults' and 'captures')")
    defaults = check_options(doc.get("defaults", {}), f"{where}: [defaults]")
    entries = doc.get("captures")
    if not isinstance(entries, list) or not entries:
        raise PsimapError(f"{where}: no captures (a list 'captures' of tables with a 'path')")
    captures: list[Capture] = []
    for i, entry in enumerate(entries, 1):
        at = f"{where}: capture {i}"
        if not isinstance(entry, dict) or not isinstance(entry.get("path"), str) or not entry["path"]:
            raise PsimapError(f"{at}: needs a 'path' (a capture folder or a glob)")
        own = check_options({k: v for k, v in entry.items() if k not in CAPTURE_KEYS}, at)
        opts = {**{k: v[1] for k, v in OPTIONS.items()}, **defaults, **own,
                "train": {**defaults.get("train", {}), **own.get("train", {})}}
        folders = _folders(entry["path"], base, at)
        if "name" in entry and len(folders) > 1:
            raise PsimapError(f"{at}: 'name' names one capture, but {entry['path']!r} matches {len(folders)}")
        for folder in folders:
            name = str(entry.get("name", folder.name))
            if not NAME.match(name):
                raise PsimapError(f"{at}: capture name {name!r} is not a plain folder name (letters, digits, . _ -)")
            captures.append(Capture(name, str(folder), {k: opts[k] for k in sorted(opts)}))
    seen: dict[str, str] = {}
    for c in captures:
        if c.name in seen:
            raise PsimapError(f"{where}: two captures named {c.name!r} ({seen[c.name]} and {c.data}); give "
                              f"one a 'name'")
        seen[c.name] = c.data
    return captures


def _folders(pattern: str, base: Path, at: str) -> list[Path]:
    """The capture folders `pattern` names: one folder, or every folder a glob matches (sorted)."""
    path = Path(pattern).expanduser()
    path = path if path.is_absolute() else base / path
    if glob.has_magic(pattern):
        found = sorted(Path(m).resolve() for m in glob.glob(str(path)) if Path(m).is_dir())
        if not found:
            raise PsimapError(f"{at}: {pattern!r} matches no folder")
        return found
    if not path.is_dir():
        raise PsimapError(f"{at}: {pattern!r} is not a folder ({path})")
    return [path.resolve()]


def check_options(table, at: str) -> dict:
    """`table` with every option checked (known name, type, value); PsimapError naming the first bad one."""
    if not isinstance(table, dict):
        raise PsimapError(f"{at}: expected a table of options")
    out = {}
    for key, value in table.items():
        if key not in OPTIONS:
            raise PsimapError(f"{at}: unknown option {key!r} (known: {', '.join(sorted(OPTIONS))}, path, name)")
        typ = OPTIONS[key][0]
        if isinstance(value, bool) and typ is not bool or not isinstance(value, typ):
            raise PsimapError(f"{at}: {key} = {value!r} has the wrong type")
        out[key] = _check_value(key, value, at)
    return out


def _check_value(key: str, value, at: str):
    """The option's value, normalised, or PsimapError. The registries read here are stdlib-only."""
    if key == "formats":
        from psimap.exporters.formats import format_names

        try:
            return format_names(value if isinstance(value, str) else list(value))
        except PsimapError as e:
            raise PsimapError(f"{at}: formats: {e}") from None
    if key == "completion":
        from psimap.completion.methods import Choices

        if value not in Choices():
            raise PsimapError(f"{at}: completion {value!r} is not one of {', '.join(Choices())}")
    if key == "up":
        from psimap.geometry.gravity import parse_up

        parse_up(value)
    if key == "min_dynamic" and not 0.0 <= value <= 1.0:
        raise PsimapError(f"{at}: min_dynamic must lie in 0..1, got {value}")
    if key == "train":
        return check_train(value, at)
    return value


def check_train(table: dict, at: str) -> dict:
    """TrainConfig overrides: known fields with values of the field's type."""
    from dataclasses import fields

    from psimap.train.config import TrainConfig

    types = {f.name: type(f.default) for f in fields(TrainConfig)}
    for k, v in table.items():
        if k not in types:
            raise PsimapError(f"{at}: train.{k} is no training option (psimap/train/config.py TrainConfig)")
        want = types[k]
        ok = isinstance(v, want) and not (isinstance(v, bool) and want is not bool)
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            ok = True
        if not ok:
            raise PsimapError(f"{at}: train.{k} = {v!r} should be of type {want.__name__}")
    return dict(table)
