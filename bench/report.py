"""Write docs/benchmarks.md from bench/results/*.json: one section per benchmark, numbers only from the JSON.

Each benchmark script writes its JSON through bench/_results.py (tables, machine, date, command,
peer). A benchmark listed here without a JSON gets its section with the command that measures it
and a line saying that no current measurement is stored. tests/test_benchmarks_page.py checks that
the committed page equals what this script writes.

Run: .venv/bin/python bench/report.py [--results bench/results] [--out docs/benchmarks.md]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
PY = ".venv/bin/python"

#: name -> (section title, the command that measures it, what it is compared with), in page order.
BENCHMARKS: dict[str, tuple[str, str, str | None]] = {
    "demosaic": (
        "Demosaicing and decoding",
        f"{PY} bench/demosaic.py",
        "polanalyser (demosaicing, calcStokes, cvtStokesToAoLP/DoLP)",
    ),
    "demosaic_heldout": (
        "Decoding on held-out path-traced frames",
        f"{PY} bench/demosaic.py --held-out",
        "polanalyser (demosaicing, calcStokes, cvtStokesToAoLP/DoLP)",
    ),
    "synth": ("Synthetic captures", f"{PY} bench/synth.py", None),
    "sfm_poses": (
        "Poses (structure from motion)",
        f"{PY} bench/sfm_poses.py --models bunny --modes sfm-K sfm",
        "pycolmap's plain pipeline (SIFT, exhaustive matching, incremental mapping) on the same images",
    ),
    "geometry": ("Geometric stage (initial surface)", f"{PY} bench/geometry.py", None),
    "occlusion": (
        "Occlusion test",
        f"{PY} bench/occlusion.py",
        "the same captures fused without the occlusion test",
    ),
    "nomask": (
        "The object found without masks",
        f"{PY} bench/nomask.py",
        "the same captures with their true masks, and without seeing past the object",
    ),
    "nomask_support": (
        "The object found without masks: the table seen through the object by its colours, built-in renderer",
        f"{PY} bench/nomask.py --views 36 --size 612x512 --masks none --shapes blob,knot,mug,rock "
        "--renderers builtin --results nomask_support",
        None,
    ),
    "nomask_sparse": (
        "The object found without masks: six shapes, 16 views of 320x256",
        f"{PY} bench/nomask.py --shapes blob,knot,spring,gear,mug,rock --views 16 --size 320x256 --results nomask_sparse",
        "the same captures with their true masks",
    ),
    "nomask_stereo_grid": (
        "The object found without masks: the stereo grid on 16 views of 320x256",
        f"{PY} bench/nomask.py --shapes knot,spring --views 16 --size 320x256 --scenes table --masks none "
        "--results nomask_stereo_grid [--append --set geometry.mvs.unmasked_full_grid_px=0 "
        "[--set geometry.mvs.min_grid_px=256]] [--append --set geometry.mvs.window=3|7]",
        "the half-resolution grid (geometry.mvs.unmasked_full_grid_px 0) on the same captures",
    ),
    "nomask_refine": (
        "The object found without masks: the refined mesh",
        f"{PY} bench/nomask.py --stop-after refine --masks true,none",
        "the same captures with their true masks",
    ),
    "as_taken": (
        "A folder of full-size frames as taken: no manifest, masks or poses",
        f"{PY} bench/as_taken.py --reference",
        "the same frames with their manifest (true poses) and true masks",
    ),
    "as_taken_knot_pathtraced": (
        "A path-traced knot on a table as taken: 36 frames of 612x512, no manifest, masks or poses",
        f"{PY} bench/as_taken.py --sizes 612x512 --shape knot --renderer mitsuba --reference "
        "--results as_taken_knot_pathtraced [--append --set geometry.sfm.denoised_runs=0]",
        "the same frames with their manifest (true poses) and true masks",
    ),
    "as_taken_stanford_pathtraced": (
        "Path-traced Stanford models on a table as taken: 36 frames of 612x512, no manifest, masks or poses",
        f"{PY} bench/as_taken.py --sizes 612x512 --mesh ../shared/data/models/MODEL --mesh-up y "
        "--renderer mitsuba --reference --results as_taken_stanford_pathtraced --append, for the bunny, armadillo and dragon",
        "the same frames with their manifest (true poses) and true masks",
    ),
    "subdivision": ("Visibility and subdivision", f"{PY} bench/subdivision.py", None),
    "refine": (
        "Refinement against ground truth (the paper's Tables 3 and 4)",
        f"{PY} bench/refine.py",
        "MVIR (the same refinement without the polarimetric term)",
    ),
    "hull_min_gain_stanford": (
        "The hull fit's stop on given masks: Stanford models",
        f"{PY} bench/refine.py --models bunny dragon armadillo --tables main --views 12 --size 304x256 "
        "--iterations 10 --samples 200000 --subdivision-area 8 --out bench/results/hull_min_gain_stanford.json "
        "[--fresh --refine-option surface.hull_min_gain=0.2]",
        "the same refinement keeping every hull-fit step (refine.surface.hull_min_gain 0, the default on given masks)",
    ),
    "refine_from_truth_pathtraced": (
        "Refinement started from the true surface of a path-traced capture",
        f"{PY} bench/refine_from_truth.py CAPTURE --out bench/results/refine_from_truth_pathtraced.json "
        "--observations decoded noise-free-pol --variant full --variant mvir pol.enabled=false "
        "--variant abs-4 pol.aop_noise_scale_deg=4",
        "MVIR",
    ),
    "refine_from_truth_floor": (
        "Refinement from the true surface with noise-free data: what leaves the true relief",
        f"{PY} bench/refine_from_truth.py CAPTURE --out bench/results/refine_from_truth_floor.json "
        "--observations decoded noise-free-pol noise-free",
        "MVIR",
    ),
    "relief_aop": (
        "Decoded AoP at fine relief",
        f"{PY} bench/relief_aop.py CAPTURE",
        "the renderer's noise-free AoP",
    ),
    "aop_error_sources": (
        "Where the decoded AoP's error comes from",
        f"{PY} bench/aop_error_sources.py CAPTURE [CAPTURE ...] (captures rendered with pmvir synth --save-stokes)",
        "the renderer's own AoP",
    ),
    "refine_speed": (
        "Refinement speed and memory",
        f"{PY} bench/refine_speed.py",
        "the CPU run on the same machine (for --device cuda)",
    ),
    "refine_speed_gpu": (
        "Refinement speed on a GPU, beside the same machine's CPU",
        f"{PY} bench/refine_speed.py --device cuda --peer cpu --max-iterations 20 --results refine_speed_gpu "
        "(on a GPU machine: bash tools/device/gpu_check.sh)",
        "the CPU run on the same machine",
    ),
    "refine_speed_cuda": (
        "Refinement speed on a GPU at the default iterations",
        f"{PY} bench/refine_speed.py --device cuda --results refine_speed_cuda "
        "(on a GPU machine: bash tools/device/gpu_check.sh)",
        None,
    ),
    "relief_solver": (
        "The refinement on fine relief: fairing, preconditioner, iterations",
        f"{PY} bench/relief_solver.py",
        "MVIR (refine.pol.enabled=false)",
    ),
    "relief_pathtraced": (
        "Fine relief on a path-traced capture",
        ".venv/bin/pmvir synth --shape rock --renderer mitsuba --spp 64 --lighting envmap --seed 11 --out CAPTURE; "
        f"{PY} bench/relief_solver.py --capture CAPTURE --results relief_pathtraced",
        "MVIR (refine.pol.enabled=false)",
    ),
    "relief_pathtraced_fine": (
        "Fine relief on a path-traced capture, finer mesh",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results relief_pathtraced_fine "
        "--set geometry.subdivision.max_area_px=3 --variant full "
        "--variant fairing-in-edges refine.surface.fair_reference_area_px=0 --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "tau_schedule_builtin": (
        "The E_pol schedule on a built-in rock",
        f"{PY} bench/relief_solver.py --results tau_schedule_builtin --variant full "
        "--variant flat-15 'refine.stages.tau_pol=[15,15,15]' --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "tau_schedule_pathtraced": (
        "The E_pol schedule on a path-traced rock",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results tau_schedule_pathtraced --variant full "
        "--variant flat-15 'refine.stages.tau_pol=[15,15,15]' --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "fairing_knot": (
        "Fairing and E_pol's weights on a torus knot (genus 1)",
        f"{PY} bench/relief_solver.py --shape knot --results fairing_knot --variant full "
        "--variant no-fairing refine.surface.fair_iterations=0 --variant fairing-in-edges "
        "refine.surface.fair_reference_area_px=0 --variant abs-4 refine.pol.aop_noise_scale_deg=4 "
        "--variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "fairing_gear": (
        "Fairing and E_pol's weights on a gear (thin teeth)",
        f"{PY} bench/relief_solver.py --shape gear --results fairing_gear --variant full "
        "--variant no-fairing refine.surface.fair_iterations=0 --variant fairing-in-edges "
        "refine.surface.fair_reference_area_px=0 --variant abs-4 refine.pol.aop_noise_scale_deg=4 "
        "--variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "aop_noise_weight_pathtraced": (
        "E_pol weighted by the AoP's absolute noise: path-traced rock, 80 iterations",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results aop_noise_weight_pathtraced "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start --variant full "
        "--variant abs-4 refine.pol.aop_noise_scale_deg=4 ... --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "aop_noise_weight_knot_pathtraced": (
        "E_pol weighted by the AoP's absolute noise: path-traced torus knot, 80 iterations",
        ".venv/bin/pmvir synth --shape knot --renderer mitsuba --spp 64 --lighting envmap --views 36 --size 612x512 "
        f"--seed 13 --out CAPTURE; {PY} bench/relief_solver.py --capture CAPTURE "
        "--results aop_noise_weight_knot_pathtraced --set geometry.subdivision.max_area_px=8 "
        "--set refine.offset_scan.mode=start --variant full --variant abs-4 refine.pol.aop_noise_scale_deg=4 "
        "--variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "aop_noise_weight_builtin": (
        "E_pol weighted by the AoP's absolute noise: built-in rock, 80 iterations",
        f"{PY} bench/relief_solver.py --results aop_noise_weight_builtin "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start --variant full "
        "--variant abs-4 refine.pol.aop_noise_scale_deg=4 ... --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "aop_noise_weight_stanford": (
        "E_pol weighted by the AoP's absolute noise: Stanford models",
        f"{PY} bench/refine.py --tables ablation --ablation-rows full aop_noise_weight mvir "
        "--out bench/results/aop_noise_weight_stanford.json",
        "MVIR (--no-polarimetric)",
    ),
    "median_intensity_pathtraced": (
        "E_pho in multiples of the median intensity: path-traced rock, 80 iterations",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results median_intensity_pathtraced "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start "
        "--set refine.pho.intensity_scale=median --set refine.pho.intensity_units=6.4 "
        "--variant full --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "median_abs_noise_pathtraced": (
        "The absolute-noise weight on top of the median intensity scale: path-traced rock, 80 iterations",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results median_abs_noise_pathtraced "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start "
        "--variant full --variant abs-4 refine.pol.aop_noise_scale_deg=4",
        None,
    ),
    "intensity_units_pathtraced": (
        "More E_pho weight in median units: path-traced rock, 80 iterations",
        f"{PY} bench/relief_solver.py --capture CAPTURE --results intensity_units_pathtraced "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start "
        "--variant units-9.6 refine.pho.intensity_units=9.6 --variant units-12.8 refine.pho.intensity_units=12.8",
        None,
    ),
    "intensity_units_builtin": (
        "More E_pho weight in median units: built-in rock, 80 iterations",
        f"{PY} bench/relief_solver.py --results intensity_units_builtin "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start "
        "--variant units-9.6 refine.pho.intensity_units=9.6",
        None,
    ),
    "intensity_units_stanford": (
        "More E_pho weight in median units: Stanford models",
        f"{PY} bench/refine.py --tables ablation --ablation-rows full intensity_units_9_6 mvir "
        "--out bench/results/intensity_units_stanford.json",
        "MVIR (--no-polarimetric)",
    ),
    "median_intensity_builtin": (
        "E_pho in multiples of the median intensity: built-in rock, 80 iterations",
        f"{PY} bench/relief_solver.py --results median_intensity_builtin "
        "--set geometry.subdivision.max_area_px=8 --set refine.offset_scan.mode=start "
        "--set refine.pho.intensity_scale=median --set refine.pho.intensity_units=6.4 "
        "--variant full --variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "median_intensity_knot": (
        "E_pho in multiples of the median intensity: built-in knot, 15 iterations",
        f"{PY} bench/relief_solver.py --shape knot --results median_intensity_knot "
        "--set geometry.subdivision.max_area_px=8 --set refine.solver.max_iterations=15 "
        "--set refine.offset_scan.mode=start --variant full "
        "--variant absolute-32 refine.pho.intensity_scale=absolute refine.pho.intensity_units=32 "
        "--variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "median_intensity_gear": (
        "E_pho in multiples of the median intensity: built-in gear, 15 iterations",
        f"{PY} bench/relief_solver.py --shape gear --results median_intensity_gear "
        "--set geometry.subdivision.max_area_px=8 --set refine.solver.max_iterations=15 "
        "--set refine.offset_scan.mode=start --variant full "
        "--variant absolute-32 refine.pho.intensity_scale=absolute refine.pho.intensity_units=32 "
        "--variant mvir refine.pol.enabled=false",
        "MVIR (refine.pol.enabled=false)",
    ),
    "median_intensity_stanford": (
        "E_pho in multiples of the median intensity: Stanford models",
        f"{PY} bench/refine.py --tables ablation --ablation-rows full absolute_intensity mvir "
        "--out bench/results/median_intensity_stanford.json",
        "MVIR (--no-polarimetric)",
    ),
    "coarse_to_fine": (
        "Coarse to fine (refine.stages.coarse)",
        f"{PY} bench/coarse_to_fine.py",
        "refine.stages.coarse=0 (every stage on the subdivided surface)",
    ),
    "demo_time": ("Time of make demo", f"{PY} bench/demo_time.py", "the 90 s target"),
    "isolation": (
        "Time of the isolation without masks",
        f"{PY} bench/isolation.py --against a96713f 8b37c0a",
        "the isolation at a96713f, 8b37c0a",
    ),
    "fullsize": ("Full-size captures: memory and time per stage", f"{PY} bench/fullsize.py", None),
    "fullsize_service": (
        "A full-size capture through the service",
        f"{PY} bench/fullsize_service.py",
        None,
    ),
    "mitsuba_render": ("Path tracing (Mitsuba 3)", f"{PY} bench/mitsuba_render.py", None),
    "evaluate": ("Evaluation", f"{PY} bench/bench_evaluate.py", None),
    "service": ("Service uploads", f"{PY} bench/service.py", None),
    "throughput": ("Service throughput (jobs per hour)", f"{PY} bench/throughput.py", None),
    "console": ("Web console", f"{PY} bench/console.py", None),
}

HEADER = """# Benchmarks

Every table on this page is generated by `bench/report.py` from the JSON files the benchmark
scripts write to `bench/results/`; no number is typed by hand. Each section names the machine,
the date of the measurement and the command that produced it, so it can be measured again.
A section without a stored measurement gives the command that makes one.

Regenerate this page after running a benchmark:

```bash
.venv/bin/python bench/report.py
```
"""


def cell(value: Any) -> str:
    """One table cell: floats to four significant digits, thousands separated, None as a dash."""
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"
    return str(value).replace("|", "\\|")


def machine_line(m: dict[str, Any]) -> str:
    parts = [str(m.get("cpu_model") or "unknown CPU")]
    if m.get("cores") is not None:
        usable = m.get("cores_usable")
        cores = f"{m['cores']} cores" + (f" ({usable} usable)" if usable not in (None, m["cores"]) else "")
        parts.append(cores)
    if m.get("memory_gib") is not None:
        parts.append(f"{m['memory_gib']} GiB memory")
    if m.get("gpu"):
        parts.append(str(m["gpu"]))
    if m.get("load_average_1min") is not None:
        parts.append(f"load average {m['load_average_1min']} at the end")
    return ", ".join(parts)


def render_table(t: dict[str, Any]) -> list[str]:
    lines = [f"### {t['title']}", "", "| " + " | ".join(cell(c) for c in t["columns"]) + " |"]
    lines.append("|" + "|".join("---" for _ in t["columns"]) + "|")
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in t["rows"]]
    if t.get("note"):
        lines += ["", str(t["note"])]
    return lines + [""]


def render_section(name: str, doc: dict[str, Any] | None) -> list[str]:
    title, command, peer = BENCHMARKS.get(name, (name, f"{PY} bench/{name}.py", None))
    if doc is not None:
        title = BENCHMARKS[name][0] if name in BENCHMARKS else doc.get("title", name)
        peer = doc.get("peer")  # what this measurement compared with (None: no peer in this run)
    lines = [f"## {title}", ""]
    if peer:
        lines += [f"Compared with: {peer}.", ""]
    if doc is None or not doc.get("tables"):
        why = "No current measurement is stored." if doc is None else (
            "The stored result predates the page's format (no tables); run the command again."
        )
        return lines + [f"{why} Measure it with:", "", "```bash", command, "```", ""]
    lines += [
        f"- Measured: {doc.get('measured_at', 'unknown')}",
        f"- Machine: {machine_line(doc.get('machine') or {})}",
        f"- Command: `{doc.get('command', command)}`",
        "",
    ]
    for t in doc["tables"]:
        lines += render_table(t)
    return lines


def render(results: Path) -> str:
    docs = {p.stem: json.loads(p.read_text()) for p in sorted(results.glob("*.json"))}
    names = list(BENCHMARKS) + sorted(n for n in docs if n not in BENCHMARKS)
    lines = HEADER.splitlines() + [""]
    for name in names:
        lines += render_section(name, docs.get(name))
    return "\n".join(lines).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=ROOT / "bench" / "results")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    args = ap.parse_args(argv)
    args.out.write_text(render(args.results))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
