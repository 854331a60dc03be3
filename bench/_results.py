"""What every benchmark writes: bench/results/<name>.json, read by bench/report.py.

Each file holds the benchmark's name and title, the time of measurement (ISO 8601, UTC), the exact
command (relative to the repository root), the machine (CPU model, cores, memory), the peer it is
compared with, and its tables (``table``: a title, column names and rows of values). The script's
own fields (per-view timings, options, raw numbers) stay beside them.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import shlex
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gib() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        return None


def _gpu() -> str | None:
    """The CUDA device's name when torch is already imported by the benchmark and sees one."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.cuda.is_available():
        return None
    return str(torch.cuda.get_device_name(0))


def machine() -> dict[str, Any]:
    """The machine a measurement ran on: CPU model, logical cores (all and usable), memory, OS, Python."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "cores_usable": usable,
        "memory_gib": _memory_gib(),
        "gpu": _gpu(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
    }


def command() -> str:
    """The command that ran this benchmark, with the script's path relative to the repository root."""
    script = Path(sys.argv[0]).resolve()
    try:
        shown = str(script.relative_to(ROOT))
    except ValueError:
        shown = sys.argv[0]
    return shlex.join([".venv/bin/python", shown, *sys.argv[1:]])


def table(title: str, columns: list[str], rows: list[list[Any]], *, note: str | None = None) -> dict[str, Any]:
    """One table of the benchmarks page: ``rows`` hold one value per column (str, int, float or None)."""
    for row in rows:
        if len(row) != len(columns):
            raise ValueError(f"table {title!r}: row {row!r} has {len(row)} values for {len(columns)} columns")
    return {"title": title, "columns": columns, "rows": rows, "note": note}


def print_table(tab: dict[str, Any]) -> None:
    """A :func:`table` on standard output, a line per row, cells parted by `` | ``."""
    print(" | ".join(tab["columns"]))
    for row in tab["rows"]:
        print(" | ".join("" if v is None else str(v) for v in row))


def write_results(
    name: str,
    *,
    title: str,
    tables: list[dict[str, Any]],
    peer: str | None = None,
    data: dict[str, Any] | None = None,
    path: Path | None = None,
) -> Path:
    """Write bench/results/<name>.json (or ``path``): the tables, machine, date and command, and ``data``.

    ``data`` is the script's own record; its keys stay at the top level (the standard fields win),
    and a ``machine`` dict in it is merged into the measured one.
    """
    data = dict(data or {})
    extra_machine = data.pop("machine", None)
    doc = {
        **data,
        "benchmark": name,
        "title": title,
        "measured_at": dt.datetime.now(dt.UTC).replace(microsecond=0).isoformat(),
        "command": command(),
        "machine": {**machine(), **(extra_machine if isinstance(extra_machine, dict) else {})},
        "peer": peer,
        "tables": tables,
    }
    path = path or RESULTS / f"{name}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def capture_description(capture: Path) -> str:
    """How a synthetic capture was made, from its gt/synth.json (e.g. "rock, builtin, plastic, sh lighting,
    12 views 612x512, seed 5"); "" for a capture without one."""
    path = Path(capture) / "gt" / "synth.json"
    if not path.exists():
        return ""
    synth = json.loads(path.read_text())
    o = synth["options"]
    return (f"{synth['source'].get('shape', 'mesh')}, {o['renderer']}"
            + (f" {o['spp']} spp" if o["renderer"] == "mitsuba" else "")
            + f", {o['material']}, {o['lighting']} lighting, {o['views']} views {o['size'][0]}x{o['size'][1]}, "
            f"seed {o['seed']}")

