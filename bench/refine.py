"""Benchmark of the refinement (Polarimetric MVIR) against ground truth: the paper's Tables 3 and 4.

For each model of ../shared/data/models (bunny, dragon, armadillo; y up, normalized to a unit
bounding-box diagonal) a synthetic capture is made with pmvir synth (36 views of 612 x 512, seed 0,
true poses; cached under --work so re-runs skip it), decoded, and the geometric stage run ONCE
(its initial surface, visibility and cameras are cached under --work too). Every refinement
variant then starts from that same initial surface (pmvir.refine.refine_surface, as the
pipeline's refine stage calls it, with the pipeline's options for the capture: a specular-dominated
one, such as the conductor, is refined without the offset scan) and is measured with pmvir.evaluate.evaluate (1,000,000
ground-truth samples; illumination against gt/illumination.json). Measured rows are cached
under --work as JSON (with the refined mesh), so a split run (one model at a time) followed by
a run on all models only measures what is missing; --fresh measures everything again.

Tables (--tables):

* main (paper Table 3; plastic): initial surface, MVIR (--no-polarimetric), Polarimetric MVIR;
  columns vertices, accuracy, completeness, normal error (mean, median), albedo RMSE, illumination error,
  time, plus the %
  improvement of accuracy / completeness over the initial surface. Targets, on the average over
  the models (of the metrics, as the paper's "Average" rows): Polarimetric MVIR improves accuracy
  by >= 35 % and completeness by >= 15 % over the initial surface, and beats MVIR (lower accuracy
  AND lower completeness error) on every model.
* ablation (paper Table 4; plastic): full, no DoP weight, I_int instead of I_min, no polarimetric.
* materials: lambert, plastic, conductor; initial surface, MVIR, Polarimetric MVIR each.

Time: the initial surface's is the geometric stage (known poses, dense stereo, surface,
visibility, subdivision); a refined row's is the refinement alone (add the initial row's time
for the whole reconstruction). Decoding and synthesis are not included.

Prints markdown tables and writes bench/results/refine.json (or --out).
Run: .venv/bin/python bench/refine.py [--models bunny dragon armadillo] [--tables main ablation materials]
     [--ablation-rows full no_dop_weight i_int mvir ...] [--materials lambert plastic conductor]
     [--renderer builtin|mitsuba] [--spp 64] [--views 36] [--size 612x512] [--iterations N]
     [--subdivision-area 2.0] [--surface-hull 0.5] [--work DIR] [--out FILE]

--renderer mitsuba path-traces the captures with Mitsuba 3 (polarized pplastic / diffuse / conductor,
perspective-exact Stokes frames; pmvir synth --renderer mitsuba) and caches them under --work beside
the built-in renderer's, so the same tables come out for physically rendered captures. Full size
(36 views of 612 x 512, 64 spp) takes hours on 2 cores: --views, --size, --spp and --models reduce it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import table, write_results

from pmvir.camera import Camera
from pmvir.capture import open_capture
from pmvir.commands.options import parse_overrides
from pmvir.config import DecodeOptions, GeometryOptions, PipelineConfig, RefineOptions, merge_options
from pmvir.errors import PmvirError
from pmvir.evaluate import evaluate
from pmvir.geometry.stage import run_geometry
from pmvir.io.illumination import illumination_from_arrays, read_illumination
from pmvir.io.ply import Mesh, read_mesh, write_mesh_ply
from pmvir.pipeline import decode_views, median_dop_in_masks, refinement_observations, refinement_options
from pmvir.refine import make_visibility_fn, refine_surface

ROOT = Path(__file__).resolve().parent
MODELS = {"bunny": "bunny.ply", "dragon": "dragon.ply", "armadillo": "armadillo.obj"}
#: Up axis of each shared model's file (shared/data/models; the Stanford scans are y up).
UP = {"bunny": "y", "dragon": "y", "armadillo": "y"}
MATERIALS = ("lambert", "plastic", "conductor")
TABLES = ("main", "ablation", "materials")
#: Refinement variants: RefineOptions overrides (on top of the defaults and --iterations).
VARIANTS: dict[str, dict] = {
    "mvir": {"pol": {"enabled": False}},
    "full": {},
    "no_dop_weight": {"pol": {"dop_weight": False}},
    "i_int": {"pho": {"intensity": "int"}},
    "least_squares": {"pho": {"robust": "none"}},
    "raw_dop_weight": {"pol": {"dop_weight_normalized": False}},
    "least_squares_raw_weight": {"pho": {"robust": "none"}, "pol": {"dop_weight_normalized": False}},
    "no_relax": {"surface": {"relax_iterations": 0}},
    "no_fairing": {"surface": {"fair_iterations": 0}},
    "aop_noise_weight": {"pol": {"aop_noise_scale_deg": 4.0}},
    "absolute_intensity": {"pho": {"intensity_scale": "absolute", "intensity_units": 32.0}},
    "intensity_units_9_6": {"pho": {"intensity_units": 9.6}},
}
LABELS = {
    "initial": "initial surface",
    "mvir": "MVIR (--no-polarimetric)",
    "full": "Polarimetric MVIR",
    "no_dop_weight": "no DoP weight",
    "i_int": "I_int instead of I_min",
    "least_squares": "least-squares E_pho (pho_robust none)",
    "raw_dop_weight": "DoP weight not normalized",
    "least_squares_raw_weight": "least-squares E_pho and DoP weight not normalized",
    "no_relax": "no tangential relaxation",
    "no_fairing": "no fairing",
    "aop_noise_weight": "E_pol weighted by absolute AoP noise (pol.aop_noise_scale_deg 4)",
    "absolute_intensity": "E_pho in fixed units (pho.intensity_scale absolute, units 32)",
    "intensity_units_9_6": "E_pho in 9.6 (not 6.4) times the median intensity (pho.intensity_units 9.6)",
}
ROWS = {
    "main": ("initial", "mvir", "full"),
    "ablation": (
        "full",
        "no_dop_weight",
        "raw_dop_weight",
        "least_squares",
        "least_squares_raw_weight",
        "no_relax",
        "no_fairing",
        "aop_noise_weight",
        "absolute_intensity",
        "intensity_units_9_6",
        "i_int",
        "mvir",
    ),
    "materials": ("initial", "mvir", "full"),
}
#: The metrics a table shows (averaged over models in its "average" rows).
METRICS = (
    "vertices",
    "accuracy",
    "completeness",
    "normal_error",
    "normal_error_median",
    "albedo_rmse",
    "illumination_error",
    "seconds",
)
TARGET_ACCURACY_PCT = 35.0
TARGET_COMPLETENESS_PCT = 15.0
SEED = 0


def shared_dir() -> Path:
    env = os.environ.get("PMVIR_SHARED")
    return Path(env) if env else ROOT.parent / ".." / "shared"


def parse_size(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, e.g. 612x512, got {text!r}")
    return int(parts[0]), int(parts[1])


def _key(obj: object) -> str:
    return hashlib.sha1(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:10]


class Case:
    """One capture (model, material) with its decoded views and its cached initial surface."""

    def __init__(self, model: str, material: str, args: argparse.Namespace, models_dir: Path):
        self.model, self.material, self.args = model, material, args
        w, h = args.size
        # Captures of the built-in renderer are perspective-exact since the spec's section 2 says so
        # ("-exact": older cached captures used the orthographic rule).
        render = "exact" if args.renderer == "builtin" else f"mitsuba-spp{args.spp}"
        self.dir = args.work / f"{model}-{material}-{render}-v{args.views}-{w}x{h}-s{SEED}"
        self.capture = self.dir / "capture"
        self.mesh_file = models_dir / MODELS[model]
        hull = getattr(args, "surface_hull", GeometryOptions().surface.hull_tolerance_px)
        self.geometry_options = GeometryOptions(
            subdivision={"max_area_px": args.subdivision_area},
            surface={"hull_tolerance_px": None if hull is None or hull < 0 else hull},
        )
        self.geometry_file = self.dir / f"geometry-{_key(self.geometry_options.model_dump(mode='json'))}.npz"
        self._views = None
        self._geometry: dict | None = None

    def synthesize(self) -> float:
        """Make the capture unless cached; seconds spent (0 when cached)."""
        if (self.capture / "capture.json").is_file():
            return 0.0
        from pmvir.synth import synthesize

        t = time.perf_counter()
        synthesize(
            self.capture,
            mesh=self.mesh_file,
            views=self.args.views,
            size=self.args.size,
            material=self.material,
            seed=SEED,
            mesh_up=UP[self.model],
            renderer=self.args.renderer,
            **({"spp": self.args.spp} if self.args.renderer == "mitsuba" else {}),
            overwrite=True,
        )
        return time.perf_counter() - t

    def views(self) -> list:
        if self._views is None:
            with open_capture(self.capture) as cap:
                self._views = decode_views(cap, PipelineConfig())
                self.masks = [cap.read_mask(i) for i in range(len(cap.frames))]
        return self._views

    def median_dop(self) -> float | None:
        """The capture's median DoP inside the masks (pmvir.pipeline.median_dop_in_masks), cached as JSON."""
        path = self.dir / "median_dop.json"
        if path.is_file():
            return json.loads(path.read_text())["median_dop_in_masks"]
        with open_capture(self.capture) as cap:
            value = median_dop_in_masks(cap, self.views())
        path.write_text(json.dumps({"median_dop_in_masks": value}))
        return value

    def geometry(self) -> dict:
        """Initial surface, visibility, cameras and the stage's time: computed once, cached as npz."""
        if self._geometry is not None:
            return self._geometry
        if not self.geometry_file.is_file():
            views = self.views()
            with open_capture(self.capture) as cap, tempfile.TemporaryDirectory(dir=self.dir) as work:
                t = time.perf_counter()
                g = run_geometry(cap, [v.images for v in views], options=self.geometry_options, workdir=work)
                seconds = time.perf_counter() - t
            reg = np.array([c is not None for c in g.cameras])
            K = np.stack([c.K if c is not None else np.full((3, 3), np.nan) for c in g.cameras])
            R = np.stack([c.R if c is not None else np.full((3, 3), np.nan) for c in g.cameras])
            tt = np.stack([c.t if c is not None else np.full(3, np.nan) for c in g.cameras])
            size = np.array([[c.width, c.height] if c is not None else [0, 0] for c in g.cameras])
            tmp = self.geometry_file.with_suffix(".tmp.npz")
            np.savez(
                tmp,
                vertices=g.vertices,
                faces=g.faces,
                visibility=g.visibility,
                registered=reg,
                K=K,
                R=R,
                t=tt,
                size=size,
                seconds=seconds,
                rounds=g.subdivision_rounds,
                max_area_px=g.subdivision_max_area_px,
            )
            os.replace(tmp, self.geometry_file)
        z = np.load(self.geometry_file)
        cams = [
            Camera(z["K"][i], z["R"][i], z["t"][i], int(z["size"][i][0]), int(z["size"][i][1])) if r else None
            for i, r in enumerate(z["registered"])
        ]
        self._geometry = {k: z[k] for k in ("vertices", "faces", "visibility")}
        self._geometry.update(
            cameras=cams,
            seconds=float(z["seconds"]),
            rounds=int(z["rounds"]),
            max_area_px=float(z["max_area_px"]),
        )
        return self._geometry

    def gt(self) -> tuple[Mesh, object]:
        return read_mesh(self.capture / "gt" / "mesh.ply"), read_illumination(
            self.capture / "gt" / "illumination.json"
        )


def refine_options(variant: str, args: argparse.Namespace) -> RefineOptions:
    values = merge_options(args.refine_option, VARIANTS[variant])
    if args.iterations is not None:
        values = merge_options(values, {"solver": {"max_iterations": args.iterations}})
    return RefineOptions(**values)


def parse_refine_options(parser: argparse.ArgumentParser, items: list[str]) -> dict:
    """``KEY=VALUE`` pairs (KEY dotted within refine, e.g. ``pol.k``; VALUE as JSON, else a string), validated."""
    try:
        out = parse_overrides(items)
        RefineOptions(**out)
    except (PmvirError, ValueError) as exc:
        parser.error(f"--refine-option: {exc}")
    return out


def metrics_row(result, seconds: float) -> dict:
    return {
        "vertices": result.n_vertices,
        "accuracy": result.accuracy,
        "completeness": result.completeness,
        "accuracy_p90": result.accuracy_p90,
        "completeness_p90": result.completeness_p90,
        "normal_error": result.normal_error,
        "normal_error_median": result.normal_error_median,
        "signed_offset": result.signed_offset,
        "albedo_rmse": result.albedo_rmse,
        "illumination_error": result.illumination_error,
        "seconds": seconds,
        "notes": list(result.notes),
    }


def measure(case: Case, row: str, args: argparse.Namespace) -> dict:
    """One row of a table (cached under the case's folder as JSON)."""
    geo_key = case.geometry_file.stem
    # as the pipeline: a specular-dominated capture is refined without the offset scan
    opts = None if row == "initial" else refinement_options(refine_options(row, args), case.median_dop())
    key = _key(
        {
            "geometry": geo_key,
            "options": None if opts is None else opts.model_dump(mode="json"),
            "samples": args.samples,
        }
    )
    cache = case.dir / f"row-{row}-{key}.json"
    if cache.is_file() and not args.fresh:
        out = json.loads(cache.read_text())
        if "normal_error" not in out and "error" not in out:  # a row cached before the metric existed
            add_normal_error(case, out, None if opts is None else case.dir / f"row-{row}-{key}.ply")
            cache.write_text(json.dumps(out, indent=1))
        return out
    geo = case.geometry()
    gt_mesh, gt_illum = case.gt()
    if opts is None:
        res = evaluate(
            Mesh(geo["vertices"], geo["faces"]), gt_mesh, gt_illum=gt_illum, n_samples=args.samples, seed=SEED
        )
        out = metrics_row(res, geo["seconds"])
        out.update(subdivision_rounds=geo["rounds"], subdivision_max_area_px=geo["max_area_px"])
    else:
        views = case.views()
        reg = [i for i, c in enumerate(geo["cameras"]) if c is not None]
        cameras = [geo["cameras"][i] for i in reg]
        with open_capture(case.capture) as cap:  # refine.demosaic may decode the frames once more
            observations = refinement_observations(cap, views, reg, DecodeOptions(), opts)
        gopts = case.geometry_options
        t = time.perf_counter()
        visibility_fn = make_visibility_fn(
            cameras,
            [case.masks[i] for i in reg],
            min_cos=gopts.visibility.min_cos,
            rel_tol=gopts.visibility.rel_tol,
        )
        refined = refine_surface(
            geo["vertices"],
            geo["faces"],
            cameras,
            observations,
            geo["visibility"][:, reg],
            options=opts,
            visibility_fn=visibility_fn,
            masks=[case.masks[i] for i in reg],
        )
        seconds = time.perf_counter() - t
        del observations
        illum = illumination_from_arrays([views[i].file for i in reg], refined.sh, refined.rgb_scale)
        mesh = Mesh(refined.vertices, geo["faces"], albedo=refined.albedo, normals=refined.normals)
        res = evaluate(mesh, gt_mesh, est_illum=illum, gt_illum=gt_illum, n_samples=args.samples, seed=SEED)
        out = metrics_row(res, seconds)
        out["options"] = opts.model_dump(mode="json")
        out["stages"] = [
            {
                "index": s.index,
                "iterations": len(s.energies) - 1,
                "stop_reason": s.stop_reason,
                "seconds": s.seconds,
            }
            for s in refined.stages
        ]
        write_mesh_ply(case.dir / f"row-{row}-{key}.ply", mesh)
    cache.write_text(json.dumps(out, indent=1))
    return out


def add_normal_error(case: Case, row: dict, mesh_file: Path | None) -> None:
    """The normal error of a cached row, from its saved mesh (the initial surface when None)."""
    if mesh_file is None:
        geo = case.geometry()
        mesh = Mesh(geo["vertices"], geo["faces"])
    elif mesh_file.is_file():
        mesh = read_mesh(mesh_file)
    else:
        return
    res = evaluate(mesh, case.gt()[0], n_samples=1000, seed=SEED)
    row.update(normal_error=res.normal_error, normal_error_median=res.normal_error_median)


def improvement(initial: float, value: float) -> float:
    return 100.0 * (initial - value) / max(initial, 1e-12)


def _fmt(v, scale: float = 1.0, digits: int = 3) -> str:
    return "-" if v is None else f"{v * scale:.{digits}f}"


def table_markdown(title: str, rows: dict[str, dict[str, dict]], names: tuple[str, ...]) -> str:
    """rows: model -> row name -> metrics (with 'initial' for the % columns when present)."""
    lines = [
        f"### {title}",
        "",
        (
            "| model | method | vertices | acc. (x1e-2) | comp. (x1e-2) | normal err. mean (deg) "
            "| normal err. median (deg) | albedo RMSE | illum. error | time (s) | acc. impr. | comp. impr. |"
        ),
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    groups = dict(rows)
    if len(rows) > 1:
        groups["average"] = average(rows, names)
    for model, r in groups.items():
        init = r.get("initial")
        for name in names:
            m = r.get(name)
            if m is None:
                continue
            if "error" in m:
                lines.append(f"| {model} | {LABELS[name]} | failed: {m['error'][:60]} |" + " |" * 9)
                continue
            ai = ci = "-"
            if init is not None and "error" not in init and name != "initial":
                ai = f"{improvement(init['accuracy'], m['accuracy']):+.1f}%"
                ci = f"{improvement(init['completeness'], m['completeness']):+.1f}%"
            lines.append(
                f"| {model} | {LABELS[name]} | {m['vertices']:,.0f} | {_fmt(m['accuracy'], 100)} | "
                f"{_fmt(m['completeness'], 100)} | {_fmt(m.get('normal_error'), digits=2)} | "
                f"{_fmt(m.get('normal_error_median'), digits=2)} | {_fmt(m['albedo_rmse'])} | "
                f"{_fmt(m['illumination_error'])} | "
                f"{m['seconds']:.1f} | {ai} | {ci} |"
            )
    return "\n".join(lines)


def r4(value: float | None, scale: float = 1.0) -> float | None:
    """``scale * value`` to four decimals (None stays None)."""
    return None if value is None else round(scale * value, 4)


def page_table(title: str, rows: dict[str, dict[str, dict]], names: tuple[str, ...]) -> dict:
    """The rows of :func:`table_markdown` as a table of the benchmarks page (bench/report.py)."""
    groups = dict(rows)
    if len(rows) > 1:
        groups["average"] = average(rows, names)
    out = []
    for model, r in groups.items():
        init = r.get("initial")
        for name in names:
            m = r.get(name)
            if m is None:
                continue
            if "error" in m:
                out.append([model, LABELS[name], *[None] * 10])
                continue
            ai = ci = None
            if init is not None and "error" not in init and name != "initial":
                ai = f"{improvement(init['accuracy'], m['accuracy']):+.1f}%"
                ci = f"{improvement(init['completeness'], m['completeness']):+.1f}%"

            out.append([model, LABELS[name], round(m["vertices"]), r4(m["accuracy"], 100), r4(m["completeness"], 100),
                        r4(m.get("normal_error")), r4(m.get("normal_error_median")), r4(m["albedo_rmse"]),
                        r4(m["illumination_error"]), round(m["seconds"], 1), ai, ci])
    return table(
        title,
        ["model", "method", "vertices", "accuracy x1e-2", "completeness x1e-2", "normal error mean deg",
         "normal error median deg", "albedo RMSE", "illumination error", "seconds", "accuracy gain",
         "completeness gain"],
        out,
    )


def average(rows: dict[str, dict[str, dict]], names: tuple[str, ...]) -> dict[str, dict]:
    """Per row name the mean of each metric over the models where every row succeeded."""
    ok = [r for r in rows.values() if all(n in r and "error" not in r[n] for n in names)]
    out: dict[str, dict] = {}
    if not ok:
        return out
    for n in names:
        m: dict = {}
        for k in METRICS:
            vals = [r[n].get(k) for r in ok]
            m[k] = None if any(v is None for v in vals) else float(np.mean(vals))
        out[n] = m
    return out


def targets(rows: dict[str, dict[str, dict]]) -> dict:
    """The issue's targets on the main table (module docstring)."""
    per_model = {}
    for model, r in rows.items():
        if any(n not in r or "error" in r[n] for n in ROWS["main"]):
            per_model[model] = {"error": "a row failed"}
            continue
        i, mv, f = r["initial"], r["mvir"], r["full"]
        per_model[model] = {
            "accuracy_improvement_pct": improvement(i["accuracy"], f["accuracy"]),
            "completeness_improvement_pct": improvement(i["completeness"], f["completeness"]),
            "mvir_accuracy_improvement_pct": improvement(i["accuracy"], mv["accuracy"]),
            "mvir_completeness_improvement_pct": improvement(i["completeness"], mv["completeness"]),
            "beats_mvir": bool(f["accuracy"] < mv["accuracy"] and f["completeness"] < mv["completeness"]),
        }
    avg = average(rows, ROWS["main"])
    out: dict = {
        "per_model": per_model,
        "models_averaged": len([m for m in per_model.values() if "error" not in m]),
    }
    if avg:
        acc = improvement(avg["initial"]["accuracy"], avg["full"]["accuracy"])
        comp = improvement(avg["initial"]["completeness"], avg["full"]["completeness"])
        good = [m for m in per_model.values() if "error" not in m]
        out.update(
            average_accuracy_improvement_pct=acc,
            average_completeness_improvement_pct=comp,
            mean_of_model_accuracy_improvement_pct=float(
                np.mean([m["accuracy_improvement_pct"] for m in good])
            ),
            mean_of_model_completeness_improvement_pct=float(
                np.mean([m["completeness_improvement_pct"] for m in good])
            ),
            accuracy_target_met=acc >= TARGET_ACCURACY_PCT,
            completeness_target_met=comp >= TARGET_COMPLETENESS_PCT,
            beats_mvir_on_every_model=all(m.get("beats_mvir", False) for m in per_model.values()),
        )
        out["all_targets_met"] = bool(
            out["accuracy_target_met"]
            and out["completeness_target_met"]
            and out["beats_mvir_on_every_model"]
            and "error" not in str(per_model)
        )
    return out


def targets_markdown(t: dict) -> str:
    lines = [
        "### Targets (main table, Polarimetric MVIR vs the initial surface)",
        "",
        "| model | acc. impr. | comp. impr. | MVIR acc. impr. | MVIR comp. impr. | beats MVIR |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for model, m in t["per_model"].items():
        if "error" in m:
            lines.append(f"| {model} | failed | | | | |")
            continue
        lines.append(
            f"| {model} | {m['accuracy_improvement_pct']:+.1f}% | "
            f"{m['completeness_improvement_pct']:+.1f}% | "
            f"{m['mvir_accuracy_improvement_pct']:+.1f}% | {m['mvir_completeness_improvement_pct']:+.1f}% | "
            f"{'yes' if m['beats_mvir'] else 'NO'} |"
        )
    if "average_accuracy_improvement_pct" in t:
        yn = {True: "met", False: "NOT met"}
        lines += [
            "",
            (
                f"- accuracy improvement (of the {t['models_averaged']}-model average): "
                f"{t['average_accuracy_improvement_pct']:+.1f}% (target >= {TARGET_ACCURACY_PCT:.0f}%): "
                f"{yn[t['accuracy_target_met']]} "
                f"(mean of per-model %: {t['mean_of_model_accuracy_improvement_pct']:+.1f}%)"
            ),
            (
                f"- completeness improvement: {t['average_completeness_improvement_pct']:+.1f}% "
                f"(target >= {TARGET_COMPLETENESS_PCT:.0f}%): {yn[t['completeness_target_met']]} "
                f"(mean of per-model %: {t['mean_of_model_completeness_improvement_pct']:+.1f}%)"
            ),
            f"- beats MVIR (accuracy and completeness) on every model: {yn[t['beats_mvir_on_every_model']]}",
            f"- all targets: {yn[t['all_targets_met']]}",
        ]
    return "\n".join(lines)


def run_rows(case: Case, names: tuple[str, ...], args: argparse.Namespace, log: dict) -> dict[str, dict]:
    out: dict[str, dict] = {}
    try:
        t = time.perf_counter()
        log["synth_s"] = case.synthesize()
        case.geometry()
        log["prepare_s"] = time.perf_counter() - t
    except PmvirError as exc:  # reported, not fatal: the other cases still run
        return {n: {"error": f"{type(exc).__name__}: {exc}"} for n in names}
    for name in names:
        try:
            out[name] = measure(case, name, args)
        except PmvirError as exc:
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
        m = out[name]
        status = m.get("error") or (
            f"acc {m['accuracy']:.5f} comp {m['completeness']:.5f} normal {m.get('normal_error') or 0:.2f} deg "
            f"{m['vertices']:,} vertices {m['seconds']:.1f} s"
        )
        print(f"  {case.model}/{case.material} {LABELS[name]}: {status}", file=sys.stderr, flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--tables", nargs="+", default=list(TABLES), choices=list(TABLES))
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument(
        "--renderer",
        choices=["builtin", "mitsuba"],
        default="builtin",
        help="synthesize the captures with pmvir's renderer or Mitsuba 3 (path traced, pplastic; the [mitsuba] "
        "extra). Captures are cached under --work per renderer",
    )
    parser.add_argument("--spp", type=int, default=64, help="Mitsuba samples per pixel (default 64)")
    parser.add_argument("--size", type=parse_size, default=(612, 512), help="WIDTHxHEIGHT (default 612x512)")
    parser.add_argument(
        "--iterations", type=int, default=None, help="refine max_iterations (default: config's)"
    )
    parser.add_argument(
        "--subdivision-area",
        type=float,
        default=GeometryOptions().subdivision.max_area_px,
        help="geometry.subdivision.max_area_px (px^2)",
    )
    parser.add_argument(
        "--surface-hull",
        type=float,
        default=GeometryOptions().surface.hull_tolerance_px,
        help="geometry.surface.hull_tolerance_px (px; a negative value: off, the initial surface as the stereo "
        "left it)",
    )
    parser.add_argument(
        "--samples", type=int, default=1_000_000, help="ground-truth samples for completeness"
    )
    parser.add_argument(
        "--work",
        type=Path,
        default=Path(tempfile.gettempdir()) / "pmvir-bench" / "refine",
        help="cache of captures, initial surfaces and measured rows",
    )
    parser.add_argument(
        "--refine-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a refine option for every refined row (JSON value, e.g. offset_scan.deblur_px=1.6); the rows' own "
        "variant wins where both set a key. Repeatable",
    )
    parser.add_argument(
        "--ablation-rows",
        nargs="+",
        default=list(ROWS["ablation"]),
        choices=list(ROWS["ablation"]),
        help="the ablation table's rows (default all; the paper's Table 4: full no_dop_weight i_int mvir)",
    )
    parser.add_argument(
        "--materials",
        nargs="+",
        default=list(MATERIALS),
        choices=list(MATERIALS),
        help="the materials table's materials (default all)",
    )
    parser.add_argument("--fresh", action="store_true", help="measure every row again (captures stay cached)")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "refine.json")
    args = parser.parse_args()
    args.refine_option = parse_refine_options(parser, args.refine_option)
    models_dir = shared_dir() / "data" / "models"
    if not models_dir.is_dir():
        raise SystemExit(
            f"refine bench: no models folder {models_dir} (set PMVIR_SHARED to the shared folder)"
        )
    missing = [m for m in args.models if not (models_dir / MODELS[m]).is_file()]
    if missing:
        raise SystemExit(
            f"refine bench: missing model file(s) {[MODELS[m] for m in missing]} under {models_dir}"
        )
    args.work.mkdir(parents=True, exist_ok=True)

    cases: dict[tuple[str, str], Case] = {}
    measured: dict[tuple[str, str], dict[str, dict]] = {}
    logs: dict[str, dict] = {}

    def rows_for(model: str, material: str, names: tuple[str, ...]) -> dict[str, dict]:
        key = (model, material)
        case = cases.setdefault(key, Case(model, material, args, models_dir))
        have = measured.setdefault(key, {})
        todo = tuple(n for n in names if n not in have)
        if todo:
            have.update(run_rows(case, todo, args, logs.setdefault(f"{model}/{material}", {})))
        return {n: have[n] for n in names}

    t0 = time.perf_counter()
    doc: dict = {
        "load_average_start": os.getloadavg(),
        "settings": {
            "models": args.models,
            "views": args.views,
            "renderer": args.renderer,
            "spp": args.spp if args.renderer == "mitsuba" else None,
            "size": list(args.size),
            "seed": SEED,
            "iterations": args.iterations,
            "subdivision_max_area_px": args.subdivision_area,
            "surface_hull_tolerance_px": args.surface_hull,
            "samples": args.samples,
            "refine_options": args.refine_option,
            "poses": "true (from capture.json)",
        },
        "units": "accuracy/completeness in GT bounding-box diagonals; normal error in degrees; albedo RMSE linear; illumination error "
        "relative shading RMSE; seconds: initial = geometric stage, others = refinement alone",
        "results": {},
    }
    text = []
    tables = []
    extra = "".join(f", {k}={json.dumps(v)}" for k, v in args.refine_option.items())
    by = f" ({args.renderer} renderer, {args.views} views {args.size[0]}x{args.size[1]}{extra})"
    if "main" in args.tables:
        rows = {m: rows_for(m, "plastic", ROWS["main"]) for m in args.models}
        doc["results"]["main"] = {
            "rows": rows,
            "average": average(rows, ROWS["main"]),
            "targets": targets(rows),
        }
        title = "Table 3: plastic, initial surface vs MVIR vs Polarimetric MVIR" + by
        tables.append(page_table(title, rows, ROWS["main"]))
        text += [
            table_markdown(title, rows, ROWS["main"]),
            targets_markdown(doc["results"]["main"]["targets"]),
        ]
    if "ablation" in args.tables:
        names = ("initial", *(r for r in ROWS["ablation"] if r in args.ablation_rows))
        rows = {m: rows_for(m, "plastic", names) for m in args.models}
        doc["results"]["ablation"] = {"rows": rows, "average": average(rows, names)}
        text.append(table_markdown("Table 4: ablation (plastic)" + by, rows, names))
        tables.append(page_table("Table 4: ablation (plastic)" + by, rows, names))
    if "materials" in args.tables:
        doc["results"]["materials"] = {}
        for material in (m for m in MATERIALS if m in args.materials):
            rows = {m: rows_for(m, material, ROWS["materials"]) for m in args.models}
            doc["results"]["materials"][material] = {"rows": rows, "average": average(rows, ROWS["materials"])}
            text.append(table_markdown(f"Materials: {material}" + by, rows, ROWS["materials"]))
            tables.append(page_table(f"Materials: {material}" + by, rows, ROWS["materials"]))
    doc["cases"] = logs
    doc["wall_s"] = time.perf_counter() - t0
    doc["load_average_end"] = os.getloadavg()
    print("\n\n".join(text))
    print(
        f"\naccuracy / completeness x 1e-2 GT diagonals; {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f}; wall {doc['wall_s']:.0f} s"
    )
    tmp = write_results(
        args.out.stem,  # the page's section: refine.json, or another --out's name
        title="Refinement against ground truth",
        path=args.out.with_suffix(".json.tmp"),
        peer="MVIR (the same refinement without E_pol)",
        tables=tables,
        data=doc,
    )
    os.replace(tmp, args.out)


if __name__ == "__main__":
    main()
