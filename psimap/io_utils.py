"""Output safety shared by every command that writes: atomic writes, and never destroying what psimap
did not write.

The rules (docs/outputs.md):
- `.`, `..`, the home directory, the filesystem root and any ancestor of the working directory are
  never an output folder, whatever the options say.
- An output folder is written whole in a temporary sibling and renamed into place. An existing folder
  is replaced only when it is a previous psimap output of the same kind (its `.psimap-output` marker
  lists every file psimap wrote there) and holds nothing else. Otherwise the command refuses, unless
  the user passes `--overwrite`: then the new files are moved into the folder one by one (replacing
  files of the same name) and nothing else in it is touched, except files an earlier psimap output
  listed in its marker.
- An output file replaces an existing file only when that file carries psimap's signature (a checkpoint
  with psimap's format tag; a PNG / mesh file psimap wrote, see `written_by_psimap`), or with
  `--overwrite`. A folder is never replaced by a file.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

from psimap import PsimapError, __version__

MARKER = ".psimap-output"           # JSON {"kind", "psimap", "files": [relative paths]} in an output folder
SIGNATURE = f"written by psimap {__version__}"
OUTPUT_KINDS = ("export", "labels", "scene", "demo", "batch")
OVERWRITE_HINT = "choose another path or pass --overwrite"


# ---- where psimap may write --------------------------------------------------------------------
def forbidden_reason(path: Path) -> str | None:
    """Why `path` (resolved) can never be an output folder, or None."""
    cwd = Path.cwd().resolve()
    if path == cwd:
        return "it is the working directory"
    if path in cwd.parents:
        return "it contains the working directory"
    with contextlib.suppress(RuntimeError, KeyError):
        if path == Path.home().resolve():
            return "it is the home directory"
    if path == Path(path.anchor):
        return "it is the filesystem root"
    return None


def read_marker(folder: Path) -> dict | None:
    """The psimap marker of `folder` ({"kind", "files", ...}) or None (absent or unreadable)."""
    try:
        meta = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(meta, dict) or meta.get("kind") not in OUTPUT_KINDS or not isinstance(meta.get("files"), list):
        return None
    return meta


def _entries(folder: Path) -> set[str]:
    """Relative paths of every file (and symlink) below `folder`, the marker excluded."""
    out = set()
    for root, dirs, files in os.walk(folder):
        for name in files + [d for d in dirs if os.path.islink(os.path.join(root, d))]:
            rel = os.path.relpath(os.path.join(root, name), folder)
            if rel != MARKER:
                out.add(rel)
    return out


def _foreign(folder: Path, meta: dict | None) -> list[str]:
    """Files in `folder` that no psimap marker lists (sorted)."""
    listed = set(meta["files"]) if meta else set()
    return sorted(_entries(folder) - listed)


def resolve_output_dir(path, *, what: str = "output") -> Path:
    """`path` resolved (~ expanded, symlinks followed), or PsimapError if it can never be an output
    folder (`forbidden_reason`) or is a file."""
    p = Path(os.path.expanduser(str(path))).resolve()
    why = forbidden_reason(p)
    if why:
        raise PsimapError(f"{what} {path}: refusing to write an output folder there ({why})")
    if p.exists() and not p.is_dir():
        raise PsimapError(f"{what} {path} exists and is a file, not a folder; choose another path")
    return p


def check_output_dir(path, kind: str, *, overwrite: bool = False, what: str = "output") -> tuple[Path, str]:
    """(resolved path, mode) for writing a `kind` output folder at `path`, or PsimapError (one line).

    mode: "new" (absent or empty), "replace" (a previous psimap `kind` output holding only what psimap
    wrote) or "merge" (--overwrite into a folder psimap did not write: files are added, nothing else
    deleted). Call it before the long work, so a refusal costs the user nothing.
    """
    if kind not in OUTPUT_KINDS:
        raise ValueError(f"unknown output kind {kind!r}")
    p = resolve_output_dir(path, what=what)
    if not p.exists() or not any(p.iterdir()):
        return p, "new"
    meta = read_marker(p)
    foreign = _foreign(p, meta)
    if meta is not None and meta["kind"] == kind and not foreign:
        return p, "replace"
    if overwrite:
        return p, "merge"
    if meta is None:
        raise PsimapError(f"{what} {path} is a folder psimap did not write ({len(foreign)} file(s), e.g. "
                          f"{foreign[0]}); {OVERWRITE_HINT} (nothing of yours is deleted)")
    if meta["kind"] != kind:
        raise PsimapError(f"{what} {path} holds a psimap {meta['kind']} output, not a {kind} output; "
                          f"{OVERWRITE_HINT}")
    raise PsimapError(f"{what} {path} holds files psimap did not write ({len(foreign)}, e.g. {foreign[0]}); "
                      f"{OVERWRITE_HINT} (nothing of yours is deleted)")


def mark_output_dir(folder, kind: str, add_files=()) -> None:
    """Write or extend the marker of a folder that psimap fills in place (the demo's folder), listing
    `add_files` (relative paths) as psimap's. Such a folder is never replaced as a whole: each output
    in it is checked on its own (`check_file_in_marked_dir`, `check_output_dir`)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    meta = read_marker(folder) or {"kind": kind, "files": []}
    if meta["kind"] == kind:
        _write_marker(folder, kind, set(meta["files"]) | {str(f) for f in add_files})


def check_file_in_marked_dir(folder, rel: str, *, overwrite: bool = False, what: str = "output") -> None:
    """PsimapError unless psimap may write `folder/rel` of an in-place folder: absent, listed in the
    folder's marker, signed by psimap, or --overwrite."""
    folder = Path(folder)
    target = folder / rel
    if target.is_dir():
        raise PsimapError(f"{what} {folder}: {rel} is a folder where psimap writes a file; {OVERWRITE_HINT}")
    meta = read_marker(folder)
    if (not target.exists() or overwrite or written_by_psimap(target)
            or (meta is not None and rel in meta["files"])):
        return
    raise PsimapError(f"{what} {folder}: {rel} exists and was not written by psimap; {OVERWRITE_HINT}")


def _write_marker(folder: Path, kind: str, files) -> None:
    tmp = folder / f".{MARKER}.tmp"
    tmp.write_text(json.dumps({"kind": kind, "psimap": __version__, "files": sorted(files)}, indent=1) + "\n")
    os.replace(tmp, folder / MARKER)


@contextlib.contextmanager
def atomic_dir(path, kind: str, *, overwrite: bool = False, what: str = "output"):
    """Yield a temporary folder next to `path`; on success it becomes `path` (see the module rules).

    Nothing is written to `path` if the block raises. The checks of `check_output_dir` run again at
    the end (someone may have put files there meanwhile).
    """
    p, _ = check_output_dir(path, kind, overwrite=overwrite, what=what)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent))
    try:
        yield tmp
        files = _entries(tmp)
        _write_marker(tmp, kind, files)
        p, mode = check_output_dir(path, kind, overwrite=overwrite, what=what)
        if mode == "new":
            if p.exists():
                p.rmdir()       # empty: nothing lost (rename(2) would replace it too)
            os.replace(tmp, p)
        elif mode == "replace":
            old = Path(tempfile.mkdtemp(prefix=f".{p.name}.", suffix=".old", dir=p.parent))
            os.replace(p, old / "x")          # everything in it was listed by psimap's marker
            os.replace(tmp, p)
            shutil.rmtree(old, ignore_errors=True)
        else:
            _merge_into(tmp, p, files, kind)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _merge_into(tmp: Path, dest: Path, files: set[str], kind: str) -> None:
    """--overwrite into a folder psimap did not (only) write: move each new file into place; delete
    only files an earlier psimap marker listed that the new output does not have."""
    for rel in sorted(files):
        target = dest / rel
        for parent in reversed(target.relative_to(dest).parents[:-1]):
            if (dest / parent).exists() and not (dest / parent).is_dir():
                raise PsimapError(f"--out {dest}: {parent} is a file where psimap writes a folder; "
                                  f"refusing to replace it")
        if target.is_dir() and not target.is_symlink():
            raise PsimapError(f"--out {dest}: {rel} is a folder where psimap writes a file; refusing to replace it")
    old = read_marker(dest)
    for rel in sorted(files):
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / rel, dest / rel)
    for rel in (set(old["files"]) - files) if old else ():
        with contextlib.suppress(OSError):
            (dest / rel).unlink()
    _write_marker(dest, kind, files)
    shutil.rmtree(tmp, ignore_errors=True)


# ---- output files ------------------------------------------------------------------------------
def check_output_file(path, *, overwrite: bool = False, what: str = "output") -> Path:
    """The resolved `path` if psimap may write a file there, else PsimapError (one line): never a
    folder, and an existing file only when psimap wrote it (`written_by_psimap`) or with --overwrite."""
    p = Path(os.path.expanduser(str(path))).resolve()
    if p.is_dir():
        raise PsimapError(f"{what} {path} is a folder; give a file name")
    if p.exists() and not overwrite and not written_by_psimap(p):
        raise PsimapError(f"{what} {path} exists and was not written by psimap; {OVERWRITE_HINT}")
    return p


def written_by_psimap(path) -> bool:
    """Whether the file at `path` carries psimap's signature: a psimap scene checkpoint, a PNG with
    Software = psimap, or a mesh file from `export_mesh_file` (PLY / OFF comment, OBJ first line, STL
    header, GLB asset.generator)."""
    p = Path(path)
    try:
        with open(p, "rb") as f:
            head = f.read(512)
    except OSError:
        return False
    try:
        if head.startswith(b"PK"):
            return _is_checkpoint(p)
        if head.startswith(b"\x89PNG"):
            from PIL import Image

            with Image.open(p) as im:
                return str(im.info.get("Software", "")).startswith("psimap")
        if head.startswith(b"glTF"):
            return _glb_generator(p).startswith("psimap")
        sig = SIGNATURE.split(" psimap")[0] + " psimap"          # "written by psimap", any version
        if head.startswith(b"ply") or head.startswith(b"OFF"):
            return sig.encode() in head.split(b"end_header")[0]
        if p.suffix.lower() == ".obj":
            return head.startswith(f"# {sig}".encode())
        if p.suffix.lower() == ".stl":
            return head.startswith(sig.encode())
    except Exception:       # unreadable or foreign content: not ours
        return False
    return False


def _is_checkpoint(p: Path) -> bool:
    import torch

    state = torch.load(p, map_location="cpu", weights_only=True, mmap=True)
    return isinstance(state, dict) and state.get("format") == "psimap.scene"


def _glb_generator(p: Path) -> str:
    import struct

    with open(p, "rb") as f:
        f.read(12)
        n, kind = struct.unpack("<I4s", f.read(8))
        if kind != b"JSON":
            return ""
        return str(json.loads(f.read(n)).get("asset", {}).get("generator", ""))


def export_mesh_file(mesh, path) -> None:
    """Write `mesh` (trimesh) to `path` (.ply / .obj / .off / .stl / .glb) atomically, signed as
    psimap's (see `written_by_psimap`)."""
    import trimesh

    p = Path(path)
    ext = p.suffix.lower().lstrip(".")
    if ext == "glb":
        def sign(tree):
            tree.setdefault("asset", {})["generator"] = f"psimap {__version__}"

        data = trimesh.exchange.gltf.export_glb(trimesh.Scene(mesh), tree_postprocessor=sign)
    else:
        data = mesh.export(file_type=ext)
        if isinstance(data, str):
            data = data.encode()
        if ext == "ply":
            head, sep, body = data.partition(b"end_header")
            lines = [ln for ln in head.split(b"\n") if not ln.startswith(b"comment")]
            lines.insert(2, f"comment {SIGNATURE}".encode())
            data = b"\n".join(lines) + sep + body
        elif ext == "off":
            data = data.replace(b"OFF\n", f"OFF\n# {SIGNATURE}\n".encode(), 1)
        elif ext == "obj":
            data = f"# {SIGNATURE}\n".encode() + data
        elif ext == "stl":
            data = SIGNATURE.encode().ljust(80, b" ")[:80] + data[80:]
    with atomic_path(p) as tmp:
        tmp.write_bytes(data)


def save_figure(fig, path, **kw) -> None:
    """matplotlib `fig` -> PNG at `path`, atomically, tagged Software = psimap."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", metadata={"Software": f"psimap {__version__}"}, **kw)


def write_text_atomic(path, text: str) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary file path next to `path`; rename it onto `path` only if the block succeeds.

    The temporary name keeps the final suffix (some writers pick the format from it). This is the
    mechanism only: commands check where they may write with `check_output_file` first.
    """
    path = Path(path)
    if path.is_dir():
        raise PsimapError(f"{path} is a folder; refusing to replace it with a file")
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{suffix}", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
