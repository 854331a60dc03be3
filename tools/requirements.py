"""Requirement lists made from pyproject.toml: the declared floors, and the Docker image's lock file.

    python tools/requirements.py floors full service dev   > floors.txt   (name==floor per declared dependency)
    python tools/requirements.py lock full service         > docker/requirements.lock

``floors`` turns every ``name>=x`` of the base dependencies and the named extras
into ``name==x.*`` (the floor's release series: ``opencv-python-headless>=4.9``
becomes ``==4.9.*``, which matches 4.9.0.80); `make test-floors` installs them,
to prove the floors are true. ``lock`` pins the base dependencies and the named extras, and everything
they pull in, at the versions installed in the running environment (the lead's
tested venv), walking the installed packages' metadata.
"""

from __future__ import annotations

import re
import sys
import tomllib
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]


def declared(extras: list[str]) -> list[Requirement]:
    """The base dependencies and those of ``extras`` (self-references ``pmvir[x]`` expanded)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    optional = project["optional-dependencies"]
    out, todo, seen = [Requirement(r) for r in project["dependencies"]], list(extras), set()
    while todo:
        extra = todo.pop()
        if extra in seen:
            continue
        seen.add(extra)
        for text in optional[extra]:
            req = Requirement(text)
            if req.name == "pmvir":
                todo += sorted(req.extras)
            else:
                out.append(req)
    return out


def floors(extras: list[str]) -> list[str]:
    lines = []
    for req in declared(extras):
        low = [s.version for s in req.specifier if s.operator in (">=", "==", "~=")]
        if low:
            name = req.name + (f"[{','.join(sorted(req.extras))}]" if req.extras else "")
            lines.append(f"{name}=={low[0]}.*")
    return sorted(lines, key=str.lower)


def _canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def lock(extras: list[str]) -> list[str]:
    pins: dict[str, str] = {}
    todo = [(r, set(r.extras)) for r in declared(extras)]
    while todo:
        req, wanted = todo.pop()
        name = _canonical(req.name)
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        dist = metadata.distribution(req.name)
        first = name not in pins
        pins[name] = dist.version.split("+")[0]  # torch 2.13.0+cpu: the index picks the CPU build
        for text in dist.requires or []:
            sub = Requirement(text)
            env_ok = sub.marker is None or any(sub.marker.evaluate({"extra": e}) for e in (wanted or {""}))
            if env_ok and (first or sub.marker is not None):
                todo.append((sub, set(sub.extras)))
    return [f"{n}=={v}" for n, v in sorted(pins.items())]


if __name__ == "__main__":
    what, *extras = sys.argv[1:]
    print("\n".join({"floors": floors, "lock": lock}[what](extras)))  # noqa: T201 - the script's output
