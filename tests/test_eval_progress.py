"""``ns-eval``'s line per image (engine/eval_progress.py): images done, seconds per image, time left."""

from __future__ import annotations

from typing import List

import pytest

from scalar_nerfstudio.engine.eval_progress import EvalProgress, progress_line


def test_each_image_reports_how_many_are_done_and_the_time_left_at_the_pace_so_far() -> None:
    clock = {"t": 100.0}
    lines: List[str] = []
    progress = EvalProgress(["a", "b", "c", "d"], report=lines.append, now=lambda: clock["t"])
    assert len(progress) == 4
    seen = []
    for item in progress:
        clock["t"] += 6.0  # rendering and scoring one image
        seen.append(item)
    assert seen == ["a", "b", "c", "d"]  # nothing of what is evaluated changes
    assert lines == [
        "eval image 1/4: 6.0 s per image, about 18 s left",
        "eval image 2/4: 6.0 s per image, about 12 s left",
        "eval image 3/4: 6.0 s per image, about 6 s left",
        "eval image 4/4: 6.0 s per image, done in 24 s",
    ]


def test_the_time_left_follows_the_pace_and_a_loader_without_length_is_named() -> None:
    assert progress_line(done=2, total=10, elapsed_s=90.0) == "eval image 2/10: 45.0 s per image, about 6 min 00 s left"
    assert progress_line(done=0, total=3, elapsed_s=5.0) == "eval image 0/3"
    with pytest.raises(TypeError, match="generator has no length"):
        len(EvalProgress((x for x in range(3)), report=print))
