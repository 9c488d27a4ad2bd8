"""Folders the project writes to, and the rule that keeps every other file safe.

A folder is taken for output only when it is new, empty, or carries the marker of a folder this
project made for the same purpose. The marker (``.colmap_guided.json``) lists the entries the
project wrote there, each recorded before it is written; ``--overwrite`` removes those entries and
nothing else: never the folder itself, never a file the project did not make. A folder that holds
other files, that is a file, or that holds (or lies inside) the photos is refused with one line
saying what to pass instead.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
from pathlib import Path

from .log import logger

MARKER = ".colmap_guided.json"


class OutputRefused(ValueError):
    """An output location the project will not write to; the message says what to pass instead."""


def _overlaps(path: Path, other: Path) -> bool:
    return path == other or other in path.parents or path in other.parents


def _free_name(path: Path) -> Path:
    """A suggestion beside ``path`` that does not exist yet."""
    for i in range(1, 1000):
        candidate = path.with_name(f"{path.name}_colmap_guided" + (f"_{i}" if i > 1 else ""))
        if not candidate.exists():
            return candidate
    return path.with_name(path.name + "_colmap_guided")


def _delete(target: Path) -> None:
    if target.is_dir() and not target.is_symlink():
        shutil.rmtree(target)
    elif target.exists() or target.is_symlink():
        target.unlink()


def read_marker(path: Path) -> dict | None:
    """The marker of folder ``path``, or None where it has none (or one this project cannot
    read)."""
    try:
        marker = json.loads((Path(path) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    ok = (
        isinstance(marker, dict)
        and isinstance(marker.get("kind"), str)
        and isinstance(marker.get("entries"), list)
    )
    return marker if ok else None


def check_output_file(path: Path, flag: str = "--out") -> Path:
    """A single output file: never one that exists (a lone file cannot carry the marker)."""
    path = Path(path).expanduser().resolve()
    if path.exists() or path.is_symlink():
        raise OutputRefused(f"{flag} {path} exists and is not replaced; pass a new file name.")
    return path


class Workspace:
    """A folder claimed for one ``kind`` of output (reconstruct, export, archival, ...)."""

    def __init__(self, path: Path, kind: str):
        self.path, self.kind = Path(path), kind

    @classmethod
    def check(cls, path: Path, kind: str, keep: tuple = (), flag: str = "--output") -> Path:
        """Refuse ``path`` for ``kind`` output where writing there would put a user's file at risk;
        writes nothing. ``keep``: what is only read (the photos), which may neither hold nor contain
        it."""
        path = Path(path).expanduser().resolve()
        for protected in keep:
            protected = Path(protected).resolve()
            if _overlaps(path, protected):
                where = (
                    "is"
                    if path == protected
                    else "contains"
                    if path in protected.parents
                    else "is inside"
                )
                raise OutputRefused(
                    f"{flag} {path} {where} {protected}, whose files are only read; "
                    f"pass a new folder outside it, e.g. {flag} {_free_name(protected)}."
                )
        if path.exists() and not path.is_dir():
            raise OutputRefused(
                f"{flag} {path} is a file, not a folder; pass "
                f"a new folder, e.g. {flag} {_free_name(path)}."
            )
        marker = read_marker(path) if path.is_dir() else None
        if marker is None and path.is_dir() and any(path.iterdir()):
            raise OutputRefused(
                f"{flag} {path} holds files colmap_guided did not write; "
                f"pass a new or empty folder, e.g. {flag} {_free_name(path)}."
            )
        if marker is not None and marker["kind"] != kind:
            raise OutputRefused(
                f"{flag} {path} holds the output of `{marker['kind']}`, not of "
                f"`{kind}`; pass another folder, e.g. {flag} {_free_name(path)}."
            )
        return path

    @classmethod
    def claim(
        cls,
        path: Path,
        kind: str,
        keep: tuple = (),
        overwrite: bool = False,
        flag: str = "--output",
    ) -> Workspace:
        """``check``, then take ``path`` (created if needed); with ``overwrite`` what earlier runs
        wrote there is removed first."""
        workspace = cls(cls.check(path, kind, keep, flag), kind)
        try:
            workspace.path.mkdir(parents=True, exist_ok=True)
            if read_marker(workspace.path) is None:
                workspace._write([])
        except OSError as err:
            raise OutputRefused(
                f"Cannot write to {flag} {workspace.path} "
                f"({err.strerror or err}); pass a writable folder."
            ) from None
        if overwrite:
            workspace.clear()
        return workspace

    @property
    def entries(self) -> list[str]:
        return list((read_marker(self.path) or {}).get("entries", []))

    def _write(self, entries: list[str]) -> None:
        tmp = self.path / (MARKER + ".partial")
        text = {"written_by": "colmap_guided", "kind": self.kind, "entries": sorted(set(entries))}
        tmp.write_text(json.dumps(text, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, self.path / MARKER)

    def record(self, *names: str) -> list[Path]:
        """Note entries (relative paths) as the project's before they are written; returns their
        paths."""
        names = [str(Path(n).as_posix()) for n in names]
        for name in names:
            if Path(name).is_absolute() or ".." in Path(name).parts:
                raise ValueError(
                    f"workspace entry {name!r} must be a relative path inside {self.path}"
                )
        entries = self.entries
        if not set(names) <= set(entries):
            self._write(entries + names)
        return [self.path / n for n in names]

    def take(self, name: str) -> Path:
        """``record`` one entry, refused where something the project did not write already stands
        there."""
        if (self.path / name).exists() and not self.owns(name):
            raise OutputRefused(
                f"{self.path / name} was not written by colmap_guided; move it out of {self.path}."
            )
        return self.record(name)[0]

    def owns(self, name: str) -> bool:
        return str(Path(name).as_posix()) in self.entries

    def remove(self, name: str) -> None:
        """Remove one recorded entry (file or folder the project made); anything else is left
        alone."""
        if not self.owns(name):
            raise ValueError(
                f"{self.path / name} was not written by colmap_guided; it is left as it is."
            )
        _delete(self.path / name)

    def clear(self) -> None:
        """Remove every recorded entry (what earlier runs wrote), keep the folder and all else
        in it."""
        entries = self.entries
        for name in entries:
            _delete(self.path / name)
        self._write([])
        if entries:
            logger.info(
                "Removed %d entries colmap_guided wrote in %s (--overwrite).",
                len(entries),
                self.path,
            )


def model_digest(model_dir: Path) -> str:
    """sha256 over the model's files: results of another model (a reconstruct rerun) are not
    reused."""
    digest = hashlib.sha256()
    for path in sorted(p for p in Path(model_dir).iterdir() if p.is_file()):
        digest.update(path.name.encode() + hashlib.sha256(path.read_bytes()).digest())
    return digest.hexdigest()
