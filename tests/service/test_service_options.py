"""Job options over HTTP take the nested names of the configuration tree (pmvir.config)."""

from __future__ import annotations

import httpx


def test_a_job_takes_nested_refine_options(api: httpx.Client) -> None:
    options = {"stop_after": "decode", "refine": {"solver": {"max_iterations": 3}, "pol": {"k": 0.6}}}
    r = api.post("/v1/jobs", json={"options": options})
    assert r.status_code == 201, r.text
    job = api.get(f"/v1/jobs/{r.json()['id']}").json()
    assert job["options"]["refine"]["solver"]["max_iterations"] == 3
    assert job["options"]["refine"]["pol"]["k"] == 0.6
    assert job["options"]["refine"]["offset_scan"]["mode"] == "stages"  # the defaults fill the rest


def test_flat_refine_and_geometry_keys_are_422_naming_them(api: httpx.Client) -> None:
    r = api.post(
        "/v1/jobs", json={"options": {"refine": {"max_iterations": 3}, "geometry": {"mvs_planes": 32}}}
    )
    assert r.status_code == 422, r.text
    locs = {tuple(e["loc"]) for e in r.json()["errors"]}
    assert locs == {
        ("body", "options", "refine", "max_iterations"),
        ("body", "options", "geometry", "mvs_planes"),
    }
