"""A hash of the training tree: the tracked files of the packages a run imports, so that a run records which code
trained it even where its copy carries no repository (a device copy of the working tree has no ``.git``).

:func:`tree_hash` is ``sha256:`` and the SHA-256 of the lines ``<path>\\0<sha256 of the file's bytes>\\n``, one
a file, sorted by path (POSIX, relative to the repository root). The files are those of :data:`PACKAGES`: with a
git work tree, the tracked ones (``git ls-files``, contents as they are on disk, so an edited file changes the
hash); without one, every file under those folders. Both leave out what Python writes beside the sources
(``__pycache__``, ``*.pyc``) and hidden names, so a clean checkout and a copy of it hash alike. Imports nothing
beyond the standard library.
"""

from __future__ import annotations

import hashlib
import subprocess
from dataclasses import dataclass
from pathlib import Path

#: The package folders (relative to the repository root) whose files make the training tree.
PACKAGES = ("ablations", "gradlab", "tasks", "diffrender", "vocabulary")
#: The repository root this module's copy lives in.
ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class TreeHash:
    """``value`` (``sha256:`` and 64 hex digits), ``files`` (how many it hashes) and ``source`` (``"git"``: the
    tracked files; ``"files"``: every file under the package folders, no git work tree found)."""

    value: str
    files: int
    source: str


def _kept(rel: str) -> bool:
    parts = rel.split("/")
    return not any(p.startswith(".") or p == "__pycache__" for p in parts) and not rel.endswith((".pyc", ".pyo"))


def _git_files(root: Path, packages: tuple[str, ...]) -> list[str] | None:
    """The tracked files under ``packages``, or None where ``root`` is not the top of a git work tree (or git is
    absent)."""
    try:
        top = subprocess.run(["git", "-C", str(root), "rev-parse", "--show-toplevel"], capture_output=True,
                             text=True, check=False)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root.resolve():
            return None
        out = subprocess.run(["git", "-C", str(root), "ls-files", "-z", "--", *packages], capture_output=True,
                             check=True)
    except (OSError, subprocess.CalledProcessError):
        return None
    return [p for p in out.stdout.decode().split("\0") if p]


def _walked_files(root: Path, packages: tuple[str, ...]) -> list[str]:
    return [p.relative_to(root).as_posix() for pkg in packages if (root / pkg).is_dir()
            for p in (root / pkg).rglob("*") if p.is_file()]


def tree_hash(root: Path | str = ROOT, packages: tuple[str, ...] = PACKAGES, *, use_git: bool = True) -> TreeHash:
    """The :class:`TreeHash` of ``packages`` under ``root`` (the module docstring defines it). ``use_git=False``
    hashes every file under the folders even in a git work tree (what a copy without ``.git`` hashes)."""
    root = Path(root)
    listed = _git_files(root, packages) if use_git else None
    source = "git" if listed is not None else "files"
    files = sorted({rel for rel in (listed if listed is not None else _walked_files(root, packages))
                    if _kept(rel) and (root / rel).is_file()})
    h = hashlib.sha256()
    for rel in files:
        h.update(f"{rel}\0{hashlib.sha256((root / rel).read_bytes()).hexdigest()}\n".encode())
    return TreeHash(value=f"sha256:{h.hexdigest()}", files=len(files), source=source)


def main(argv: list[str] | None = None) -> None:
    """``python -m ablations.tree_hash``: print the hash of this copy's training tree."""
    del argv
    print(tree_hash().value)


if __name__ == "__main__":
    main()
