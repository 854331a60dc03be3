"""The web console in a real browser: Debian's headless Chromium driven by Playwright against a live
redis-server + ``pmvir serve`` + ``pmvir worker`` that ran a tiny synthetic job to the end.

Every request the page makes to anything but the service is aborted and fails the test (the console and
the API docs must work offline), and so does any console error or uncaught exception.
"""

from __future__ import annotations

import io
import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
from console_helpers import (
    CHROMIUM,
    CHROMIUM_ARGS,
    TINY_OPTIONS,
    chromium_missing,
    finished_job,
    tiny_capture_zip,
)

from pmvir.result import RESULT_FILES
from service.testing import ServiceStack

from svc_helpers import KEY, require_redis

pytestmark = pytest.mark.slow
VALIDATOR = Path(__file__).resolve().parents[2] / "service" / "static" / "validate-gltf.cjs"


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ServiceStack, dict]]:
    """A stack with one finished job (about 30 s on 2 cores)."""
    require_redis()
    if why := chromium_missing():
        pytest.skip(why)
    root = tmp_path_factory.mktemp("console")
    zipped = tiny_capture_zip(root)
    st = ServiceStack(root / "stack", api_keys=(KEY,))
    try:
        st.start()
        job = finished_job(st.url, KEY, zipped, options=TINY_OPTIONS, label="tiny blob")
        yield st, job
    finally:
        st.stop()


@pytest.fixture(scope="module")
def browser(live: tuple[ServiceStack, dict]) -> Iterator[object]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


class PageWatch:
    """A page whose console errors, uncaught exceptions and requests leaving the service are recorded."""

    def __init__(self, browser: object, url: str):
        self.context = browser.new_context(viewport={"width": 1280, "height": 1600})  # type: ignore[attr-defined]
        self.errors: list[str] = []
        self.external: list[str] = []
        self.context.route("**/*", self._route)
        self.page = self.context.new_page()
        self.page.on("console", lambda m: self.errors.append(m.text) if m.type == "error" else None)
        self.page.on("pageerror", lambda e: self.errors.append(f"uncaught: {e}"))
        self.url = url

    def _route(self, route: object) -> None:
        request_url = route.request.url  # type: ignore[attr-defined]
        if request_url.startswith((self.url, "data:")):
            route.continue_()  # type: ignore[attr-defined]
        else:
            self.external.append(request_url)
            route.abort()  # type: ignore[attr-defined]

    def close(self) -> None:
        self.context.close()


@pytest.fixture()
def watch(browser: object, live: tuple[ServiceStack, dict]) -> Iterator[PageWatch]:
    w = PageWatch(browser, live[0].url)
    try:
        yield w
        assert not w.external, f"the page asked for files outside the service: {w.external}"
        assert not w.errors, f"console errors: {w.errors}"
    finally:
        w.close()


def _sign_in(w: PageWatch, key: str) -> None:
    w.page.goto(w.url + "/ui/")
    w.page.fill("#api-key", key)
    w.page.click("#signin button[type=submit]")


def _validate(path: Path) -> dict:
    """The Khronos glTF validator's report of a file (npm gltf-validator, installed by make setup)."""
    out = subprocess.run(
        ["node", str(VALIDATOR), str(path)], capture_output=True, text=True, timeout=120, check=False
    )
    return json.loads(out.stdout.splitlines()[0])


def _non_background_fraction(png: bytes, background: tuple[int, int, int] = (0x20, 0x25, 0x2F)) -> float:
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    return float((np.abs(img - np.array(background)).sum(axis=2) > 30).mean())


def test_a_wrong_key_shows_a_clear_message(watch: PageWatch) -> None:
    _sign_in(watch, "not-a-key")
    message = watch.page.locator("#signin-error")
    message.wait_for(timeout=10_000)
    assert "not accepted" in message.inner_text() and "401" in message.inner_text()
    assert watch.page.evaluate("sessionStorage.getItem('pmvir.apiKey')") is None
    # Chromium logs the refused request itself; that one error is expected, nothing else
    assert all("401" in e for e in watch.errors), watch.errors
    watch.errors.clear()


def test_signed_in_the_job_list_and_job_page_show_the_finished_job(
    watch: PageWatch, live: tuple[ServiceStack, dict], tmp_path: Path
) -> None:
    stack, job = live
    page = watch.page
    _sign_in(watch, KEY)
    row = page.locator(f"#jobs tr[data-job='{job['id']}']")
    row.wait_for(timeout=15_000)
    assert row.locator("[data-status]").inner_text() == "succeeded"
    assert "tiny blob" in row.inner_text() and "100%" in row.inner_text()
    assert KEY not in page.url  # the key never goes into an address

    row.locator("a").click()
    page.wait_for_url(f"**/ui/jobs/{job['id']}")
    page.locator("#viewer[data-ready='1']").wait_for(timeout=30_000)
    assert page.locator("#job-stage").inner_text() == "refine"
    assert page.locator("#job-progress").inner_text() == "100%"
    assert page.locator("#timings tr").count() >= 3
    page.locator("#log").filter(has_text="succeeded").wait_for(timeout=10_000)

    # the 3D view: as many vertices as mesh.ply, and the canvas shows the mesh in every mode
    with httpx.Client(base_url=stack.url, headers={"Authorization": f"Bearer {KEY}"}) as c:
        report = c.get(f"/v1/jobs/{job['id']}/results/report.json").json()
        listing = c.get(f"/v1/jobs/{job['id']}/results").json()["files"]
    assert int(page.locator("#viewer").get_attribute("data-vertices")) == report["refine"]["vertices"]
    canvas = page.locator("#viewer canvas")
    page.wait_for_timeout(500)
    assert _non_background_fraction(canvas.screenshot()) > 0.03
    for mode in ("shaded", "normals", "albedo"):
        page.check(f"input[name=mode][value={mode}]")
        page.wait_for_timeout(300)
        assert page.locator("#viewer").get_attribute("data-mode") == mode
        assert _non_background_fraction(canvas.screenshot()) > 0.03, mode
    page.check("#show-initial")
    page.wait_for_timeout(800)
    assert _non_background_fraction(canvas.screenshot()) > 0.03

    # the convergence plot: one line per energy term of report.json
    terms = {k for st in report["refine"]["stages"] for e in st["energies"] for k in e}
    lines = page.locator("#plot path.term-line")
    assert lines.count() == len(terms) >= 5
    assert {lines.nth(i).get_attribute("data-term") for i in range(lines.count())} == terms
    for i in range(lines.count()):
        assert lines.nth(i).get_attribute("d").count("L") >= 1

    # per-view previews and residual images, every one decoded by the browser
    images = page.locator("#view-images img")
    assert images.count() == 5
    page.wait_for_function(
        "[...document.querySelectorAll('#view-images img')].every(i => i.complete && i.naturalWidth > 0)",
        timeout=10_000,
    )
    page.select_option("#view-select", index=3)
    page.wait_for_function(
        "[...document.querySelectorAll('#view-images img')].every(i => i.complete && i.naturalWidth > 0 "
        "&& i.dataset.path.includes(document.querySelector('#view-select').value))",
        timeout=10_000,
    )

    # a download link for every result file
    links = {a.get_attribute("data-path") for a in page.locator("#downloads a[data-path]").all()}
    assert links == {f["path"] for f in listing}
    for name in (
        "mesh.glb",
        "textured.glb",
        "textured.obj",
        "textured.mtl",
        "textured_albedo.png",
        "initial.ply",
    ):
        assert name in links
    zips = {a.get_attribute("data-zip") for a in page.locator("#downloads a[data-zip]").all()}
    # each folder of a full run's result also as one zip (decoded/ is written by decode-only runs,
    # masks/ only when the capture had no masks and pmvir drew them)
    assert zips == {f.download_name for f in RESULT_FILES if f.is_folder and f.name not in ("decoded/", "masks/")}
    with page.expect_download() as dl:
        page.locator("#downloads a[data-path='mesh.glb']").click()
    saved = tmp_path / "mesh.glb"
    dl.value.save_as(saved)
    assert saved.read_bytes()[:4] == b"glTF"
    verdict = _validate(saved)
    assert verdict["errors"] == 0, verdict["messages"]
    assert verdict["info"]["totalVertexCount"] == report["refine"]["vertices"]  # every vertex of mesh.ply
    textured = tmp_path / "textured.glb"
    with httpx.Client(base_url=stack.url, headers={"Authorization": f"Bearer {KEY}"}) as c:
        textured.write_bytes(c.get(f"/v1/jobs/{job['id']}/results/textured.glb").content)
    verdict = _validate(textured)
    assert verdict["errors"] == 0 and verdict["info"]["hasTextures"], verdict["messages"]
    page.screenshot(path=str(tmp_path / "job.png"), full_page=True)


def test_api_docs_work_offline(watch: PageWatch) -> None:
    page = watch.page
    page.goto(watch.url + "/docs")
    page.locator(".swagger-ui .info .title").wait_for(timeout=20_000)
    assert "pmvir" in page.locator(".swagger-ui .info .title").inner_text()
    page.locator(".opblock-tag").first.wait_for(timeout=10_000)
    page.goto(watch.url + "/redoc")
    page.locator("h1").filter(has_text="pmvir").wait_for(timeout=30_000)
    assert page.locator("[data-section-id]").count() > 3


def test_a_zipped_capture_chosen_on_the_page_becomes_a_job_and_a_bad_one_names_its_files(
    watch: PageWatch, live: tuple[ServiceStack, dict], tmp_path: Path
) -> None:
    import zipfile

    from service.testing import write_noise_capture

    capture = write_noise_capture(tmp_path / "cap", frames=3, masks=True, seed=5)
    good, bad = tmp_path / "good.zip", tmp_path / "bad.zip"
    for target, drop in ((good, None), (bad, "frames/001.png")):
        with zipfile.ZipFile(target, "w") as zf:
            for p in sorted(capture.rglob("*")):
                rel = p.relative_to(capture).as_posix()
                if p.is_file() and rel != drop:
                    zf.write(p, rel)
    page = watch.page
    _sign_in(watch, KEY)
    page.locator("#jobs").wait_for()
    page.fill("#job-options", '{"stop_after": "decode"}')
    page.fill("#job-label", "noise")
    page.set_input_files("#capture-file", str(good))
    started = page.locator("#upload-status a")
    started.wait_for(timeout=30_000)
    job_id = started.inner_text()
    page.locator(f"#jobs tr[data-job='{job_id}']").wait_for(timeout=10_000)
    with httpx.Client(base_url=live[0].url, headers={"Authorization": f"Bearer {KEY}"}) as c:
        job = c.get(f"/v1/jobs/{job_id}").json()
    assert job["label"] == "noise" and job["options"]["stop_after"] == "decode" and len(job["files"]) == 7

    page.set_input_files("#capture-file", str(bad))
    problem = page.locator("#upload-status .error")
    problem.wait_for(timeout=30_000)
    assert "frames/001.png" in problem.inner_text()
    # the refused start is a 422 answer, which Chromium logs as a failed resource: expected, nothing else
    assert all("422" in e for e in watch.errors), watch.errors
    watch.errors.clear()
