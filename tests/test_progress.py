"""pmvir.progress: one object for fraction, stage, cancellation and timing."""

from __future__ import annotations

import itertools

import pytest

from pmvir.errors import CanceledError
from pmvir.progress import Progress


def _recorder() -> tuple[list[tuple[str, float, str]], Progress]:
    events: list[tuple[str, float, str]] = []
    return events, Progress(lambda stage, fraction, message: events.append((stage, fraction, message)))


def test_steps_map_onto_their_slice_of_the_parent() -> None:
    events, progress = _recorder()
    with progress.step("decode", 0.2) as p:
        p.update(0.5, "half")
    with progress.step("refine", 0.8) as p:
        with p.step("stage 1", 0.25) as q:
            q.update(1.0, "iteration 9")
        p.update(0.5, "between stages")
    by_message = {m: (s, f) for s, f, m in events}
    assert by_message["half"] == ("decode", pytest.approx(0.1))
    assert by_message["stage 1: iteration 9"] == ("refine", pytest.approx(0.2 + 0.8 * 0.25))
    assert by_message["between stages"] == ("refine", pytest.approx(0.6))
    assert events[-1] == ("refine", pytest.approx(1.0), "refine: done")


def test_fraction_never_goes_backwards() -> None:
    events, progress = _recorder()
    with progress.step("a", 0.5) as p:
        p.update(0.9)
        p.update(0.1)  # a sub-step that restarts its own count must not move the bar back
    fractions = [f for _, f, _ in events]
    assert all(b >= a for a, b in itertools.pairwise(fractions))
    assert max(fractions) == pytest.approx(0.5)


def test_cancellation_names_where_it_stopped() -> None:
    asked = iter([False] * 4 + [True])  # each step's start and its first report poll once
    progress = Progress(should_cancel=lambda: next(asked))
    with (
        pytest.raises(CanceledError, match=r"during geometry / poses$"),
        progress.step("geometry", 0.5) as p,
        p.step("poses", 0.5) as q,
    ):
        q.update(0.5)


def test_timings_only_for_steps_that_finished() -> None:
    progress = Progress()
    with progress.step("ok", 0.5):
        pass
    with pytest.raises(RuntimeError), progress.step("broken", 0.5):
        raise RuntimeError("boom")
    assert list(progress.timings) == ["ok"] and progress.timings["ok"] >= 0.0


def test_a_weight_outside_0_1_is_refused() -> None:
    with pytest.raises(ValueError, match="weight"), Progress().step("x", 1.5):
        pass


def test_iterate_reports_each_item() -> None:
    events, progress = _recorder()
    with progress.step("decode", 1.0) as p:
        items = list(p.iterate(["a", "b"], lambda k, item: f"did {item}"))
    assert items == ["a", "b"]
    assert [(f, m) for _, f, m in events if m.startswith("did")] == [(0.5, "did a"), (1.0, "did b")]
