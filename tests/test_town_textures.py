"""The town's textures (scalar_nerfstudio/scenes/town/materials.py): filtered by each sample's footprint, as a
camera's pixel averages the surface it sees (generator version 3), or point-sampled as generator version 2 wrote
them (``--textures point-sampled``, which the town results in docs/results.md were measured on).

All sizes are tiny: no training, a few seconds in all.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from tiny_town import write_tiny_town

from scalar_nerfstudio.scenes.town import (
    TownConfig,
    build_town,
    load_town,
    render_town_image,
    render_town_rays,
    town_camera_poses,
)
from scalar_nerfstudio.scenes.town.materials import _lines, facade_colour, ground_colour, roof_colour

#: Two frames rendered by generator version 2 (the code at commit 73ece6e), 48 x 36, seed 1, frame 1 of each capture.
VERSION_2_FRAMES = Path(__file__).parent / "fixtures" / "town-version-2-frames.npz"


def _frame(capture: str, textures: str) -> np.ndarray:
    """[36, 48, 3] uint8: frame 1 of a tiny 2 x 2 town as write_town stores it."""
    town = build_town(TownConfig(num_images=4, width=48, height=36, blocks_x=2, blocks_y=2, capture=capture, seed=1, textures=textures))
    return (render_town_image(town, town_camera_poses(town)[1])[0] * 255.0 + 0.5).astype(np.uint8)


def test_a_version_2_scene_loads_with_the_point_sampled_textures_it_was_written_with(tmp_path: Path) -> None:
    """scene.json of generator version 2 has no textures key: its frames sampled each colour at a point."""
    scene = write_tiny_town(tmp_path / "scene")
    content = json.loads((scene / "scene.json").read_text())
    assert content["version"] == 3 and content["config"]["textures"] == "filtered"
    del content["config"]["textures"]
    content["version"] = 2
    (tmp_path / "scene.json").write_text(json.dumps(content))
    assert load_town(tmp_path).config.textures == "point-sampled"


@pytest.mark.parametrize("capture", ["aerial", "rig"])
def test_point_sampled_textures_render_version_2s_frames_and_filtered_ones_do_not(capture: str) -> None:
    """``--textures point-sampled`` gives the frames generator version 2 wrote (within one 8-bit level on 0.1 %
    of the pixels at most, for another CPU's last bit); the default, filtered, frames differ from them."""
    kept = np.load(VERSION_2_FRAMES)[capture].astype(np.int16)
    difference = np.abs(_frame(capture, "point-sampled").astype(np.int16) - kept)
    assert difference.max() <= 1 and np.mean(difference > 0) <= 1e-3
    assert np.mean(np.abs(_frame(capture, "filtered").astype(np.int16) - kept)) > 1.0


def test_lines_are_box_filtered_over_the_footprint() -> None:
    """Thin periodic lines (mortar, seams, grout): a footprint of 0 is the point test; a footprint of one whole
    period covers exactly width / period of it wherever it lies; in between, the share of the box on a line."""
    x = np.random.default_rng(0).uniform(-10.0, 10.0, 1000)
    np.testing.assert_array_equal(_lines(x, 0.45, 0.015, np.zeros(1000)), (np.mod(x, 0.45) < 0.015).astype(np.float64))
    np.testing.assert_allclose(_lines(x, 0.45, 0.015, np.full(1000, 0.45)), 0.015 / 0.45, rtol=1e-9)
    np.testing.assert_allclose(_lines(x, 0.45, 0.015, np.full(1000, 4.5)), 0.015 / 0.45, rtol=1e-9)
    assert _lines(np.array([0.0075]), 0.45, 0.015, np.array([0.03]))[0] == pytest.approx(0.5)  # half the box on the line
    assert np.isfinite(_lines(x, 0.45, 0.015, np.full(1000, np.inf))).all()


def test_filtered_textures_average_the_detail_a_sample_covers() -> None:
    """A sample's colour is the surface averaged over its footprint: seen from afar, asphalt, roofs and the three
    kinds of facade keep their mean colour while the speckle finer than a sample fades and no longer changes
    with the exact point a pixel falls on (the aliasing that differs from view to view); the render path
    passes each ray's footprint. Colours stay finite in [0, 1] for any footprint, weathering included."""
    town = build_town(TownConfig(num_images=4, width=16, height=12, blocks_x=2, blocks_y=2, seed=1, textures="point-sampled"))
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-60.0, 60.0, 20000), rng.uniform(-60.0, 60.0, 20000)
    across = np.abs(x - town.street_x[np.abs(x[:, None] - town.street_x[None]).argmin(axis=1)])
    along = np.abs(y - town.street_y[np.abs(y[:, None] - town.street_y[None]).argmin(axis=1)])
    lane = (across > 0.3) & (across < 1.5) & (along > town.config.street_width / 2.0 + 4.0)  # asphalt, no markings
    x, y = x[lane], y[lane]
    n = len(x)
    roof_x = rng.uniform(town.lo[0, 0] + 0.5, town.hi[0, 0] - 0.5, n)  # building 0's roof, within its coping
    roof_y = rng.uniform(town.lo[0, 1] + 0.5, town.hi[0, 1] - 0.5, n)
    plain = ~town.shops & (town.sill > 0.8)  # no shop front and no window below 0.8 m on the ground floor
    styles = {int(style): int(np.flatnonzero(plain & (town.style == style))[0]) for style in np.unique(town.style[plain])}
    assert sorted(styles) == [0, 1, 2], "the tiny town should have brick, plaster and concrete facades"

    def colours(the_town, footprint: float, shift: float = 0.0):
        f = np.full(n, footprint)
        surfaces = {
            "asphalt": ground_colour(the_town, x + shift, y + shift, footprint=f),
            "roof": roof_colour(the_town, np.zeros(n, dtype=np.int64), x=roof_x + shift, y=roof_y + shift, footprint=f),
        }
        for style, building in styles.items():  # the wall below the ground floor's windows
            surfaces[f"facade {style}"] = facade_colour(
                the_town, np.full(n, building), np.zeros(n, dtype=np.int64), u=0.3 + (np.abs(x) % 8.4) + shift,
                v=0.1 + (np.abs(y) % 0.5) + shift, width=np.full(n, 9.0), footprint=f)
        return surfaces

    point, far = colours(town, 0.0), colours(town, 0.3)
    for name in point:
        assert np.abs(far[name].mean(axis=0) / point[name].mean(axis=0) - 1.0).max() < 0.03, name
    # The asphalt's 4 cm speckle and the roof's 5 cm gravel: a point against one 3 cm away.
    point_moved, far_moved = colours(town, 0.0, shift=0.03), colours(town, 0.3, shift=0.03)
    for name in ("asphalt", "roof"):
        assert np.mean(np.abs(far[name] - far_moved[name])) < 0.25 * np.mean(np.abs(point[name] - point_moved[name])), name

    # Rays from 50 m above the asphalt, 3 cm apart: a sample 1/600 rad wide (a 600 px focal length) covers 8 cm of it.
    origins = np.stack([x, y, np.full(n, 50.0)], axis=1)
    down = np.broadcast_to(np.array([0.0, 0.0, -1.0]), origins.shape)
    moved = origins + np.array([0.03, 0.03, 0.0])
    change = {angle: np.mean(np.abs(render_town_rays(origins, down, town, sample_angle=angle)[0]
                                    - render_town_rays(moved, down, town, sample_angle=angle)[0])) for angle in (0.0, 1.0 / 600.0)}
    assert change[1.0 / 600.0] < 0.6 * change[0.0]

    filtered = build_town(TownConfig(num_images=4, width=16, height=12, blocks_x=2, blocks_y=2, seed=1))
    for the_town in (town, filtered):
        for footprint in (0.0, 0.2, 0.8, 1e9, np.inf):
            for name, colour in colours(the_town, footprint).items():
                assert np.isfinite(colour).all() and colour.min() >= 0.0 and colour.max() <= 1.0, (name, footprint)
