"""A run folder's manifest, ``run.json``: its marker (:data:`KIND`), reading it, the files a run lists with their
sizes and SHA-256 (:func:`file_entries`) and checking them (:func:`verify`, :func:`check_file`), and
:class:`RunFolderError`. :mod:`cv2x_marl.runs` writes run folders through :class:`~cv2x_marl.runs.RunFolder` and
re-exports these names.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

MANIFEST = "run.json"
#: the marker in every ``run.json`` this package writes; only such folders are ever replaced
KIND = "cv2x_marl run"
STATUSES = ("running", "complete", "interrupted", "failed")


class RunFolderError(ValueError):
    """An output folder cannot be used: in use, not empty, not writable, or corrupt."""


def is_ours(manifest: dict[str, Any] | None) -> bool:
    """Whether a ``run.json`` was written by this package (carries :data:`KIND`)."""
    return manifest is not None and manifest.get("kind") == KIND


def unlisted_files(folder: str | Path, manifest: dict[str, Any]) -> list[str]:
    """Files under ``folder`` that the run of ``manifest`` did not list (relative paths, sorted):
    files someone else put there. A run still ``running`` (killed before listing its files) lists
    none, so every file counts as its own."""
    if "files" not in manifest:
        return []
    listed = set(manifest.get("files") or {})
    folder = Path(folder)
    extra = []
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if p.is_dir() and not p.is_symlink():
            continue
        if rel != MANIFEST and rel not in listed and not p.name.endswith(".tmp"):
            extra.append(rel)
    return extra


def sha256_file(path: str | Path, chunk: int = 1 << 20) -> str:
    """Hex SHA-256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def file_entries(folder: str | Path) -> dict[str, dict[str, Any]]:
    """``{relative path: {"bytes", "sha256"}}`` of every file under ``folder`` (sorted; the
    top-level ``run.json`` and hidden temporary files excluded)."""
    folder = Path(folder)
    out: dict[str, dict[str, Any]] = {}
    for p in sorted(folder.rglob("*")):
        rel = p.relative_to(folder).as_posix()
        if not p.is_file() or rel == MANIFEST or p.name.endswith(".tmp"):
            continue
        out[rel] = {"bytes": p.stat().st_size, "sha256": sha256_file(p)}
    return out


def read_manifest(folder: str | Path) -> dict[str, Any] | None:
    """The ``run.json`` of a folder, or None when it has none (or it is unreadable)."""
    try:
        data = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def verify(folder: str | Path, names: list[str] | None = None) -> None:
    """Check files of a finished run folder against the checksums of its ``run.json``.

    Args:
        folder: the run folder.
        names: relative paths to check (default: every file the manifest lists).

    Raises:
        RunFolderError: a listed file is missing or its bytes differ (naming the file).
    """
    folder = Path(folder)
    manifest = read_manifest(folder)
    if manifest is None or "files" not in manifest:
        raise RunFolderError(f"{folder} has no {MANIFEST} with checksums (not a finished run folder)")
    files: dict[str, Any] = manifest["files"]
    for name in names if names is not None else list(files):
        entry = files.get(name)
        path = folder / name
        if entry is None:
            raise RunFolderError(f"{path} is not listed in {folder / MANIFEST}")
        if not path.is_file():
            raise RunFolderError(f"{path} is missing (listed in {folder / MANIFEST})")
        if path.stat().st_size != entry["bytes"] or sha256_file(path) != entry["sha256"]:
            raise RunFolderError(
                f"{path} does not match its checksum in {folder / MANIFEST}: the file was changed or corrupted"
            )


def check_file(path: str | Path) -> None:
    """Verify ``path`` when the ``run.json`` beside it lists it (files of older runs pass).

    Raises:
        RunFolderError: the file's bytes differ from the recorded checksum.
    """
    path = Path(path)
    manifest = read_manifest(path.parent)
    if manifest is not None and path.name in manifest.get("files", {}):
        verify(path.parent, [path.name])
