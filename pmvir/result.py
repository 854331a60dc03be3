"""The result folder (spec section 3): every file's name, writing it, reading it back.

One table, :data:`RESULT_FILES`, names each file a run may write, which stage
writes it, its media type, and whether the service serves it singly; adding a
result file is one entry here plus the code that writes it through
:class:`ResultFolder`. Files are written under a temporary name and renamed, so a
killed run never leaves a half-written file and a repeated run replaces its own.

Examples:
    >>> [f.name for f in RESULT_FILES if f.stage == "refine"][:2]
    ['mesh.ply', 'illumination.json']
    >>> result_file("report.json").media_type
    'application/json'
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pmvir.errors import PmvirError
from pmvir.io.illumination import Illumination, read_illumination, write_illumination
from pmvir.io.ply import Mesh, read_mesh, write_mesh_ply


@dataclass(frozen=True)
class ResultFile:
    """One entry of the result folder.

    Attributes:
        name: path relative to the result folder; a folder ends in ``/``.
        stage: the pipeline stage that writes it (``decode``, ``geometry``, ``refine``, ``report``).
        media_type: the HTTP media type it is served as.
        description: what it holds, for the README, the API document and the console.
        single: served singly by the service (folders are served zipped as ``<name>.zip``).
    """

    name: str
    stage: str
    media_type: str
    description: str
    single: bool = True

    @property
    def is_folder(self) -> bool:
        return self.name.endswith("/")

    @property
    def download_name(self) -> str:
        """The name a client downloads it under (a folder as ``<folder>.zip``)."""
        return self.name.rstrip("/") + ".zip" if self.is_folder else self.name


#: Every file a run may write, in the order a reader meets them (spec section 3 first).
RESULT_FILES: tuple[ResultFile, ...] = (
    ResultFile("mesh.ply", "refine", "application/octet-stream", "the refined surface with linear albedo"),
    ResultFile("illumination.json", "refine", "application/json", "per-frame SH lighting (pmvir-sh9)"),
    ResultFile("initial.ply", "geometry", "application/octet-stream", "the initial surface"),
    ResultFile("poses/", "geometry", "application/zip", "the cameras used, a COLMAP model"),
    ResultFile(
        "images/", "geometry", "application/zip", "the viewable I_int images (8-bit sRGB PNG) poses/ names"
    ),
    ResultFile(
        "sparse.ply", "geometry", "application/octet-stream", "the sparse points (SfM / triangulation)"
    ),
    ResultFile("dense.ply", "geometry", "application/octet-stream", "the fused dense stereo points"),
    ResultFile("masks/", "geometry", "application/zip", "the object masks pmvir drew (captures without masks)"),
    ResultFile("report.json", "report", "application/json", "timings, counts, parameters, energies"),
    ResultFile(
        "capture.json", "decode", "application/json", "the manifest used (as given, or inferred from the frames)"
    ),
    ResultFile("decoded/", "decode", "application/zip", "decoded frames and previews (decode-only runs)"),
    ResultFile("previews/", "decode", "application/zip", "per view: I_int, DoP and AoP previews (PNG, small)"),
    ResultFile(
        "residuals/", "refine", "application/zip", "per view: observed minus rendered intensity and E_pol (PNG)"
    ),
    ResultFile("mesh.glb", "refine", "model/gltf-binary", "the refined mesh as glTF 2.0, +Y up, albedo COLOR_0"),
    ResultFile("textured.glb", "refine", "model/gltf-binary", "decimated mesh with a UV atlas and albedo texture"),
    ResultFile("textured.obj", "refine", "text/plain", "the same textured mesh as OBJ (with .mtl and PNG)"),
    ResultFile("textured.mtl", "refine", "text/plain", "the OBJ's material: the albedo texture"),
    ResultFile("textured_albedo.png", "refine", "image/png", "the baked albedo texture (sRGB)"),
)

#: Extra name served by the service: every file of the result in one zip.
RESULT_ZIP = "result.zip"


def result_file(name: str) -> ResultFile:
    """The entry of :data:`RESULT_FILES` called ``name`` (a folder with or without its ``/``).

    Raises:
        KeyError: no such result file.
    """
    for f in RESULT_FILES:
        if name in (f.name, f.name.rstrip("/"), f.download_name):
            return f
    raise KeyError(f"{name!r} is not a result file (known: {', '.join(f.name for f in RESULT_FILES)})")


def downloadable_names() -> tuple[str, ...]:
    """Names the service serves singly, then ``result.zip``."""
    return (*(f.download_name for f in RESULT_FILES if f.single), RESULT_ZIP)


def _atomic_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")


class ResultFolder:
    """A result folder on disk: typed writers and readers for the files of :data:`RESULT_FILES`.

    Args:
        root: the folder (created on first write).
    """

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.written: list[str] = []

    def path(self, name: str) -> Path:
        """Absolute path of a result file or folder (``name`` must be in :data:`RESULT_FILES`)."""
        return self.root / result_file(name).name.rstrip("/")

    @contextmanager
    def _writing(self, name: str) -> Iterator[Path]:
        """Yield a temporary path; rename it to ``name`` when the block succeeds."""
        entry = result_file(name)
        target = self.root / entry.name.rstrip("/")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = _atomic_path(target)
        try:
            yield tmp
            if entry.is_folder and target.exists():
                old = _atomic_path(target)
                os.replace(target, old)
                os.replace(tmp, target)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, target)
        finally:
            if tmp.is_dir():
                shutil.rmtree(tmp, ignore_errors=True)
            elif tmp.exists():
                tmp.unlink()
        self._record(entry, target)

    def _record(self, entry: ResultFile, target: Path) -> None:
        if entry.is_folder:
            names = sorted(p.relative_to(self.root).as_posix() for p in target.rglob("*") if p.is_file())
        else:
            names = [entry.name]
        self.written += [n for n in names if n not in self.written]

    def write_mesh(self, name: str, mesh: Mesh) -> Path:
        """``mesh.ply`` or ``initial.ply`` (spec PLY)."""
        with self._writing(name) as tmp:
            write_mesh_ply(tmp, mesh)
        return self.path(name)

    def write_json(self, name: str, document: dict[str, Any]) -> Path:
        """A JSON result file (``report.json``)."""
        with self._writing(name) as tmp:
            tmp.write_text(json.dumps(document, indent=1))
        return self.path(name)

    def write_illumination(self, illumination: Illumination) -> Path:
        """``illumination.json``."""
        with self._writing("illumination.json") as tmp:
            write_illumination(tmp, illumination)
        return self.path("illumination.json")

    def write_folder(self, name: str, fill: Callable[[Path], object]) -> Path:
        """A result folder (``poses/``, ``decoded/``): ``fill(tmp_dir)`` writes it, then it replaces the old one."""
        with self._writing(name) as tmp:
            tmp.mkdir()
            fill(tmp)
        return self.path(name)

    def write_file(self, name: str, fill: Callable[[Path], object]) -> Path:
        """Any other registered file: ``fill(tmp_path)`` writes it."""
        with self._writing(name) as tmp:
            fill(tmp)
        return self.path(name)

    def read_mesh(self, name: str = "mesh.ply") -> Mesh:
        return read_mesh(self._existing(name))

    def read_illumination(self) -> Illumination:
        return read_illumination(self._existing("illumination.json"))

    def read_report(self) -> dict[str, Any]:
        path = self._existing("report.json")
        try:
            return json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError) as exc:
            raise PmvirError(f"{path}: not a JSON report: {exc}") from exc

    def has(self, name: str) -> bool:
        return self.path(name).exists()

    def present(self) -> list[str]:
        """Every file under the folder that belongs to a registered entry, relative, sorted."""
        out = []
        for f in RESULT_FILES:
            p = self.root / f.name.rstrip("/")
            if f.is_folder and p.is_dir():
                out += [q.relative_to(self.root).as_posix() for q in p.rglob("*") if q.is_file()]
            elif p.is_file():
                out.append(f.name)
        return sorted(out)

    def _existing(self, name: str) -> Path:
        path = self.path(name)
        if not path.exists():
            raise PmvirError(f"{path}: the result has no {name}")
        return path
