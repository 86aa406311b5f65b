"""Progress of an evaluation over held-out images: images done, seconds per image, time left.

nerfstudio's ``ns-eval`` (``Pipeline.get_average_image_metrics``) shows a transient bar with the time
elapsed and the images done, but no time left, and on a real capture at full resolution one image takes
seconds to a minute. :class:`EvalProgress` wraps the eval data loader that method iterates: after each
image it prints one line (``eval image 3/10: 6.3 s per image, about 44 s left``), above nerfstudio's
bar. It changes nothing of what is evaluated.
"""

from __future__ import annotations

import time
from typing import Callable, Generic, Iterable, Iterator, Sized, TypeVar

from scalar_nerfstudio.blocks.length import format_duration

__all__ = ["EvalProgress", "progress_line"]

Item = TypeVar("Item")


def progress_line(*, done: int, total: int, elapsed_s: float) -> str:
    """``eval image 3/10: 6.3 s per image, about 44 s left`` after ``done`` of ``total`` images in ``elapsed_s``."""
    if done <= 0:
        return f"eval image 0/{total}"
    per_image = max(elapsed_s, 0.0) / done
    left = max(total - done, 0) * per_image
    tail = f"about {format_duration(left)} left" if done < total else f"done in {format_duration(elapsed_s)}"
    return f"eval image {done}/{total}: {per_image:.1f} s per image, {tail}"


class EvalProgress(Generic[Item]):
    """An iterable over ``loader``'s items (``(camera, batch)`` pairs) that reports after each one.

    Args:
        loader: the eval data loader (sized: nerfstudio asks its ``len``).
        report: called with each progress line (the console's print in a pipeline).
        now: the clock (seconds).
    """

    def __init__(self, loader: Iterable[Item], *, report: Callable[[str], None],
                 now: Callable[[], float] = time.perf_counter) -> None:
        self._loader = loader
        self._report = report
        self._now = now

    def __len__(self) -> int:
        if not isinstance(self._loader, Sized):
            raise TypeError(f"{type(self._loader).__name__} has no length: nerfstudio's evaluation needs one")
        return len(self._loader)

    def __iter__(self) -> Iterator[Item]:
        total = len(self)
        started = self._now()
        done = 0
        for item in self._loader:
            yield item  # the caller renders and scores it before asking for the next
            done += 1
            self._report(progress_line(done=done, total=total, elapsed_s=self._now() - started))
