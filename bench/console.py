"""Screenshots of the web console: a job run on a live stack, its page opened in headless Chromium.

Starts redis-server, ``pmvir serve`` and a worker on loopback ports, submits a
synthetic capture (built-in blob, plastic) as a new user would (a zipped
capture in one POST, then start), waits for the result, signs in to
``/ui/`` in Debian's Chromium (Playwright), opens the job page and saves:

* ``bench/results/console-job.png``: the whole job page (albedo view);
* ``bench/results/console-<mode>.png``: the 3D view in each mode
  (albedo, shaded with view 0's lighting, normals, initial surface beside);
* ``bench/results/console.json``: timings and what the page showed.

    .venv/bin/python bench/console.py                       # 24 views of 408x340, demo options
    .venv/bin/python bench/console.py --tiny                # the browser test's 16-view job
    .venv/bin/python bench/console.py --readme docs/console.png   # also a small copy for the README
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [
    str(ROOT),
    str(ROOT / "tests" / "service"),
]  # before bench/, whose service.py shadows the package

from _results import table, write_results  # noqa: E402  (bench/, the script's folder)
from console_helpers import (  # noqa: E402  (after the sys.path set-up above)
    CHROMIUM,
    CHROMIUM_ARGS,
    TINY_OPTIONS,
    chromium_missing,
    finished_job,
    tiny_capture_zip,
)

from service.testing import ServiceStack  # noqa: E402

KEY = "bench-key"
#: The demo's schedule (service/demo.py), as job options.
DEMO_OPTIONS = {"geometry": {"subdivision": {"max_area_px": 8.0}}, "refine": {"solver": {"max_iterations": 15}}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tiny", action="store_true", help="the browser test's small job instead of the demo's")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "results")
    p.add_argument("--readme", type=Path, default=None, help="also write a reduced job-page screenshot here")
    args = p.parse_args(argv)
    if why := chromium_missing():
        print(f"cannot run: {why}", file=sys.stderr)
        return 2
    from playwright.sync_api import sync_playwright

    args.out.mkdir(parents=True, exist_ok=True)
    stats: dict = {}
    with tempfile.TemporaryDirectory(prefix="pmvir-console-") as tmp:
        t0 = time.perf_counter()
        if args.tiny:
            zipped, options = tiny_capture_zip(Path(tmp)), TINY_OPTIONS
        else:
            zipped, options = tiny_capture_zip(Path(tmp), views=24, size=(408, 340), seed=0), DEMO_OPTIONS
        stats["synth_s"] = time.perf_counter() - t0
        with ServiceStack(Path(tmp) / "stack", api_keys=(KEY,)) as stack:
            stack.start_worker()
            t0 = time.perf_counter()
            job = finished_job(stack.url, KEY, zipped, options=options, label="blob, plastic", timeout=1800)
            stats["job_s"] = time.perf_counter() - t0
            stats["stage_timings"] = job["stage_timings"]
            with sync_playwright() as pw:
                browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
                page = browser.new_page(viewport={"width": 1280, "height": 900})
                errors: list[str] = []
                page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
                t0 = time.perf_counter()
                page.goto(stack.url + "/ui/")
                page.fill("#api-key", KEY)
                page.click("#signin button[type=submit]")
                page.locator(f"#jobs tr[data-job='{job['id']}'] a").click()
                page.locator("#viewer[data-ready='1']").wait_for(timeout=60_000)
                page.wait_for_function(
                    "[...document.querySelectorAll('#view-images img')].every(i => i.complete && i.naturalWidth > 0)",
                    timeout=30_000,
                )
                page.wait_for_timeout(1000)
                stats["page_ready_s"] = time.perf_counter() - t0
                page.screenshot(path=str(args.out / "console-job.png"), full_page=True)
                if args.readme is not None:  # the page down to the per-view images (not the long lists)
                    bottom = page.locator("#view-images").bounding_box()
                    clip = {"x": 0, "y": 0, "width": 1280, "height": bottom["y"] + bottom["height"] + 40}
                    _reduced(page.screenshot(full_page=True, clip=clip), args.readme)
                canvas = page.locator("#viewer canvas")
                for mode in ("albedo", "shaded", "normals"):
                    page.check(f"input[name=mode][value={mode}]")
                    page.wait_for_timeout(500)
                    canvas.screenshot(path=str(args.out / f"console-{mode}.png"))
                page.check("input[name=mode][value=albedo]")
                page.check("#show-initial")
                page.wait_for_timeout(1000)
                canvas.screenshot(path=str(args.out / "console-initial.png"))
                stats["vertices_shown"] = int(page.locator("#viewer").get_attribute("data-vertices"))
                stats["plot_lines"] = page.locator("#plot path.term-line").count()
                stats["console_errors"] = errors
                browser.close()
    rows = [["synthesize the capture", round(stats["synth_s"], 1)],
            ["job: upload to finished", round(stats["job_s"], 1)]]
    rows += [[f"  stage {k}", round(v, 1)] for k, v in stats["stage_timings"].items() if isinstance(v, int | float)]
    rows.append(["job page ready in Chromium", round(stats["page_ready_s"], 1)])
    write_results(
        "console",
        title="Web console",
        path=args.out / "console.json",
        tables=[table(
            "A job through the live stack, then its page in headless Chromium"
            + (" (the browser test's small job)" if args.tiny else " (24 views of 408x340, the demo's options)"),
            ["step", "seconds"],
            rows,
            note=f"{stats['vertices_shown']:,} vertices shown, {len(stats['console_errors'])} console errors",
        )],
        data=stats,
    )
    print(json.dumps(stats, indent=1))
    return 0


def _reduced(png: bytes, target: Path, width: int = 900) -> None:
    """A smaller copy of a screenshot (palette PNG), for the README."""
    import io

    from PIL import Image

    img = Image.open(io.BytesIO(png)).convert("RGB")
    img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
    target.parent.mkdir(parents=True, exist_ok=True)
    img.quantize(colors=128, method=Image.Quantize.MEDIANCUT).save(target, optimize=True)


if __name__ == "__main__":
    sys.exit(main())
