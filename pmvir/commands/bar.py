"""The terminal progress bar of the ``pmvir`` commands: a tqdm bar behind a :class:`~pmvir.progress.Progress`."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from pmvir.progress import Progress


@contextmanager
def progress_bar(desc: str, *, quiet: bool = False) -> Iterator[Progress]:
    """A :class:`Progress` drawn as a tqdm bar on stderr (in per mille), closed when the block ends.

    Args:
        desc: the bar's label until the first stage reports.
        quiet: draw nothing (the progress object still times steps).
    """
    if quiet:
        yield Progress.none()
        return
    from tqdm import tqdm

    bar = tqdm(total=1000, unit="‰", file=sys.stderr, desc=desc, dynamic_ncols=True)

    def report(stage: str, fraction: float, message: str) -> None:
        bar.set_description(stage or desc)
        bar.set_postfix_str(message[:60], refresh=False)
        bar.update(int(fraction * 1000) - bar.n)

    try:
        yield Progress(report)
    finally:
        bar.close()
