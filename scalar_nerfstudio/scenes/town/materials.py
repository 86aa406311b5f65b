"""The town's materials: the albedo of every surface as a pure function of the 3-D hit point and of the
surface it lies on (building, face), so every view agrees (multi-view consistent).

Detail at several scales: asphalt speckle (4 cm), bricks (7.5 x 22.5 cm), pavement tiles and sign
lettering (about 10 cm), window frames and mullions, windows (about 1 m), floors (about 3 m) and
whole buildings (10-40 m). The noise is an integer hash of lattice coordinates, salted per town.

A camera's pixel averages the surface over its footprint. With ``TownConfig.textures == "filtered"`` each
point carries the width of the surface its sample covers (``footprint``, metres) and detail finer than that
is averaged (:func:`_speckle` for lattice noise, :func:`_faded` for per-brick, per-tile and smooth noise,
:func:`_lines` for thin lines): a surface far away looks the same from every view instead of
a speckle that changes with the view (aliasing, which structure-from-motion cannot match), and the ground
and roofs carry weathering at 0.3-2 m. A footprint of 0 samples the point itself: the version-2 pixels
(``"point-sampled"``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from scalar_nerfstudio.scenes.town.layout import Town

__all__ = ["SUN", "facade_colour", "ground_colour", "roof_colour", "sky_colour"]

#: Unit direction towards the sun (fixed: the lighting does not change between views).
SUN = np.array([0.5, 0.35, 0.79]) / np.linalg.norm([0.5, 0.35, 0.79])
_SKY_ZENITH = np.array([0.30, 0.50, 0.85])
_SKY_HORIZON = np.array([0.82, 0.88, 0.95])
_SIGN = np.array([
    (0.80, 0.10, 0.10), (0.10, 0.35, 0.75), (0.10, 0.55, 0.25), (0.95, 0.75, 0.10),
    (0.60, 0.15, 0.60), (0.95, 0.45, 0.10), (0.10, 0.60, 0.65), (0.12, 0.12, 0.12),
])

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _hash(salt: int, *coords: np.ndarray) -> np.ndarray:
    """Integer lattice coordinates ([P] arrays, any int/float dtype holding integers) -> [P] uniform [0, 1)."""
    h = np.full(np.shape(coords[0]), (salt * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF, dtype=np.uint64)
    for c in coords:
        h = (h ^ np.asarray(c).astype(np.int64).astype(np.uint64)) * _M1
        h ^= h >> np.uint64(31)
        h = (h + _GOLDEN) * _M2
        h ^= h >> np.uint64(29)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def _value_noise(salt: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Smooth 2-D value noise in [0, 1) on the unit lattice: [P] coordinates -> [P]."""
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    fu, fv = fu * fu * (3 - 2 * fu), fv * fv * (3 - 2 * fv)
    a, b = _hash(salt, iu, iv), _hash(salt, iu + 1, iv)
    c, d = _hash(salt, iu, iv + 1), _hash(salt, iu + 1, iv + 1)
    return (a * (1 - fu) + b * fu) * (1 - fv) + (c * (1 - fu) + d * fu) * fv


def _faded(values: np.ndarray, cell: float, footprint: np.ndarray) -> np.ndarray:
    """A per-cell random term ([P] values uniform in [0, 1), cells of ``cell`` metres) averaged over a
    ``footprint`` ([P] metres): the mean of about (footprint / cell)^2 cells varies cell / footprint as
    much about 0.5. Where the footprint is within a cell (or 0) the values are returned as they are."""
    fade = np.minimum(1.0, cell / np.maximum(footprint, 1e-12))
    return np.where(fade < 1.0, 0.5 + (values - 0.5) * fade, values)


#: The deepest level of :func:`_speckle`'s mip chain (cells 2^40 times the finest: far beyond any scene).
_MAX_LEVEL = 40


def _speckle(salt: int, cell: float, u: np.ndarray, v: np.ndarray, footprint: np.ndarray, *ids: np.ndarray) -> np.ndarray:
    """[P] noise uniform in [0, 1) on a lattice of ``cell``-metre cells over the surface coordinates ``u``, ``v``
    ([P] metres; salted, and drawn apart for each of ``ids``, [P] integers), as a sample ``footprint`` ([P] metres)
    wide sees it. A sample within a cell (or of footprint 0) gets its cell's value. A wider one gets a mip chain's:
    at level k the cells are 2^k times wider and hold the mean of the 4^k fine cells they cover, a value drawn
    about 0.5 with 2^-k of the fine spread, interpolated between the two levels about the footprint. So far
    away the speckle is as faint as a camera records it and no longer changes with the exact point a pixel
    falls on (which, with the cells' own values, made a random speckle differ from view to view)."""
    fine = _hash(salt, np.floor(u / cell), np.floor(v / cell), *ids)
    level = np.minimum(np.log2(np.maximum(footprint, 1e-300) / cell), _MAX_LEVEL)  # [P] <= 0: within a cell
    wide = np.flatnonzero(level > 0.0)
    if len(wide) == 0:
        return fine
    uw, vw, idw = u[wide], v[wide], [np.asarray(i)[wide] for i in ids]

    def mip(k: np.ndarray) -> np.ndarray:  # [W] the level-k value (k >= 1) at the wide samples
        size = cell * np.exp2(k)
        return 0.5 + (_hash(salt + 7919, np.floor(uw / size), np.floor(vw / size), k, *idw) - 0.5) * np.exp2(-k)

    below = np.floor(level[wide])
    t = level[wide] - below
    out = fine.copy()
    out[wide] = np.where(below == 0, fine[wide], mip(np.maximum(below, 1.0))) * (1.0 - t) + mip(below + 1.0) * t
    return out


def _lines(x: np.ndarray, period, width, footprint: np.ndarray, point: Optional[np.ndarray] = None) -> np.ndarray:
    """Coverage in [0, 1] of lines ``width`` wide that start every ``period`` (where ``x mod period <
    width``), averaged over a box ``footprint`` wide about ``x`` ([P]; scalars or [P] period and width).
    A footprint of 0 gives the point test itself (0 or 1): ``point`` ([P] bool) where the caller has it
    computed its own way (the version-2 pixels), else ``x mod period < width``."""
    point = (np.mod(x, period) < width if point is None else point).astype(np.float64)
    half = np.minimum(np.asarray(footprint) / 2.0, 1e6)  # [P] (wider than any town: its mean coverage)

    def covered(t: np.ndarray) -> np.ndarray:  # line length in [0, t]
        k = np.floor(t / period)
        return k * width + np.minimum(t - k * period, width)

    box = (covered(x + half) - covered(x - half)) / np.maximum(2.0 * half, 1e-12)
    return np.where(half > 1e-9, np.clip(box, 0.0, 1.0), point)


def _either(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Coverage of the union of two line sets ([P] each) taken as independent (1 or 0 where either is exact)."""
    return 1.0 - (1.0 - a) * (1.0 - b)


def _dim(coverage: np.ndarray, factor: float) -> np.ndarray:
    """[P] brightness of a surface with ``coverage`` of it darkened to ``factor``: exactly 1 at 0 and ``factor`` at 1."""
    return (1.0 - coverage) + factor * coverage


def _mix(colour: np.ndarray, other, coverage: np.ndarray) -> np.ndarray:
    """[P, 3] ``colour`` with ``coverage`` ([P] in [0, 1]) of ``other`` ([3] or [P, 3]): exactly ``colour`` at 0
    and ``other`` at 1."""
    return colour * (1.0 - coverage)[:, None] + np.asarray(other) * coverage[:, None]


def _weathering(town: Town, salt: int, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """[P] brightness factor of stains and wear at 0.3, 0.8 and 2 m ("filtered" textures only; 1 otherwise):
    the mid-scale marks that photos of real ground and roofs carry."""
    if town.config.textures != "filtered":
        return np.ones(len(x))
    octaves = ((0.3, 0.25), (0.8, 0.4), (2.0, 0.35))
    noise = np.zeros(len(x))  # [P]
    for k, (scale, weight) in enumerate(octaves):
        noise += weight * _faded(_value_noise(salt + k, x / scale, y / scale), scale, footprint)
    return 0.7 + 0.6 * noise


def facade_colour(town: Town, building: np.ndarray, face: np.ndarray, *, u: np.ndarray, v: np.ndarray, width: np.ndarray,
                  footprint: np.ndarray) -> np.ndarray:
    """Facade texture.

    Args:
        building: [P] building index; face: [P] face id (0..3) of that building.
        u: [P] metres along the facade from its left end; v: [P] height (z); width: [P] facade width.
        footprint: [P] metres of facade a sample covers (0: the point itself; see the module's text).

    Returns:
        [P, 3] albedo.
    """
    salt = town.texture_salt
    fid = building * 4 + face
    height = town.hi[building, 2]
    floor_h = town.floor_height[building]
    pitch = town.window_pitch[building]
    win_w, win_h = town.window_size[building, 0], town.window_size[building, 1]
    style = town.style[building]
    wall = town.wall[building]
    trim = town.trim[building]
    colour = np.empty((len(u), 3))

    # Wall material at three scales.
    brick = style == 0
    if brick.any():
        ub, vb, fb, fpb = u[brick], v[brick], fid[brick], footprint[brick]
        row = np.floor(vb / 0.075)
        shifted = ub + (row % 2) * 0.1125
        along = shifted / 0.225
        col = np.floor(along)
        mortar = _either(_lines(shifted, 0.225, 0.012, fpb, point=(along - col) * 0.225 < 0.012),
                         _lines(vb, 0.075, 0.011, fpb, point=(vb - row * 0.075) < 0.011))
        brick_size = np.sqrt(0.225 * 0.075)  # a brick's side, on average (its hash is per brick, staggered)
        tone = 0.78 + 0.3 * _faded(_hash(salt + 1, col, row, fb), brick_size, fpb)
        tint = 0.06 * (_faded(_hash(salt + 2, col, row, fb), brick_size, fpb) - 0.5)
        bricks = wall[brick] * tone[:, None] + np.array([tint, 0.5 * tint, 0.0 * tint]).T
        colour[brick] = _mix(bricks, np.array([0.74, 0.71, 0.65]), mortar)
    plaster = style == 1
    if plaster.any():
        up, vp, fp, fpp = u[plaster], v[plaster], fid[plaster], footprint[plaster]
        speckle = _speckle(salt + 4, 0.04, up, vp, fpp, fp)
        tone = 0.86 + 0.1 * _value_noise(salt + 3, up / 0.8 + 7.0 * fp, vp / 0.8) + 0.06 * speckle
        groove = (vp < floor_h[plaster]) * _lines(vp, 0.45, 0.025, fpp)  # rusticated ground floor
        colour[plaster] = wall[plaster] * (tone * _dim(groove, 0.75))[:, None]
    concrete = style == 2
    if concrete.any():
        uc, vc, fc, fpc = u[concrete], v[concrete], fid[concrete], footprint[concrete]
        ph = floor_h[concrete] / 2.0
        pu, pv = np.floor(uc / 1.5), np.floor(vc / ph)
        joint = _either(_lines(uc, 1.5, 0.02, fpc, point=(uc - pu * 1.5) < 0.02), _lines(vc, ph, 0.02, fpc, point=(vc - pv * ph) < 0.02))
        hole = (((uc % 0.6) - 0.3) ** 2 + ((vc % 0.6) - 0.3) ** 2 < 0.022**2).astype(np.float64)
        hole = np.where(fpc > 0.044, np.pi * 0.022**2 / 0.36, hole)  # tie holes: their share of the wall, once unresolved
        tone = (0.84 + 0.16 * _hash(salt + 5, pu, pv, fc)) * (0.96 + 0.06 * _speckle(salt + 6, 0.05, uc, vc, fpc, fc))
        colour[concrete] = wall[concrete] * (tone * _dim(_either(joint, hole), 0.6))[:, None]

    # Storeys: floor bands and the parapet.
    floor = np.floor(v / floor_h)
    fv = v - floor * floor_h
    parapet_base = np.floor((height - 0.4) / floor_h) * floor_h
    band = (floor >= 1) & (fv < 0.16) & (style != 2) & (v < parapet_base)
    colour[band] = trim[band] * 0.92
    parapet = v >= parapet_base + 0.05
    coping = v > height - 0.12
    colour[parapet] = colour[parapet] * 0.88
    colour[coping] = trim[coping]

    # Windows: a centred grid, one row per floor, with frames, mullions, transoms and sills.
    count = np.maximum(np.floor((width - 1.0) / pitch), 0.0)
    offset = (width - count * pitch) / 2.0
    column = np.floor((u - offset) / pitch)
    fu = u - offset - column * pitch - (pitch - win_w) / 2.0
    wy = fv - town.sill[building]
    shop_floor = town.shops[building] & (floor == 0)
    rows_ok = (column >= 0) & (column < count) & (v < parapet_base) & ~shop_floor
    frame_t = 0.07
    in_outer = rows_ok & (fu >= -frame_t) & (fu < win_w + frame_t) & (wy >= -frame_t) & (wy < win_h + frame_t)
    in_glass = rows_ok & (fu >= 0) & (fu < win_w) & (wy >= 0) & (wy < win_h)
    mullion = in_glass & ((np.abs(fu - win_w / 2.0) < 0.025) | (np.abs(wy - 0.64 * win_h) < 0.025))
    sill = rows_ok & (fu >= -0.12) & (fu < win_w + 0.12) & (wy >= -frame_t - 0.07) & (wy < -frame_t)
    colour[sill] = np.array([0.82, 0.8, 0.76])
    colour[in_outer & ~in_glass] = trim[in_outer & ~in_glass]
    glass = in_glass & ~mullion
    if glass.any():
        g = np.flatnonzero(glass)
        wid_a, wid_b = column[g], floor[g]
        lit = _hash(salt + 7, wid_a, wid_b, fid[g])
        pane = town.glass[building[g]] * (0.6 + 0.5 * _hash(salt + 8, wid_a, wid_b, fid[g]))[:, None]
        pane = pane + 0.25 * np.clip(wy[g] / win_h[g], 0.0, 1.0)[:, None] * np.array([0.55, 0.65, 0.8])  # baked sky reflection
        curtain = np.array([0.85, 0.78, 0.6]) * (0.7 + 0.3 * _hash(salt + 9, wid_a, wid_b, fid[g]))[:, None]
        colour[g] = np.where((lit > 0.82)[:, None], curtain, pane)
    colour[mullion] = trim[mullion]

    # Ground-floor shops: shop windows, doors and coloured sign boards with lettering.
    shop = shop_floor & (u > 0.3) & (u < width - 0.3)
    if shop.any():
        sidx = np.flatnonzero(shop)
        us, fs, bs = u[sidx], fv[sidx], building[sidx]
        index = np.floor(us / 6.0)
        su = us - index * 6.0
        sign_colour = _SIGN[(_hash(salt + 10, index, fid[sidx]) * len(_SIGN)).astype(np.int64)]
        part = colour[sidx]
        window = (su > 0.4) & (su < 5.6) & (fs > 0.15) & (fs < 2.35)
        door = (su > 0.8) & (su < 1.9) & (fs < 2.2)
        bars = window & ((((su - 0.4) % 1.3) < 0.06) | (fs < 0.22) | (fs > 2.28))
        part[window] = town.glass[bs[window]] * 0.7 + 0.12
        part[bars] = trim[sidx][bars] * 0.8
        part[door] = sign_colour[door] * 0.35 + 0.08
        board = (su > 0.25) & (su < 5.75) & (fs > 2.5) & (fs < 2.95)
        part[board] = sign_colour[board]
        # Lettering: glyph cells of 8 x 8 cm, 5 rows, letters 5 cells wide with a blank column.
        gu, gv = np.floor((su - 0.9) / 0.08), np.floor((fs - 2.55) / 0.08)
        letter = board & (su > 0.9) & (su < 5.1) & (gv >= 0) & (gv < 5) & ((gu % 6) != 5)
        ink = letter & (_hash(salt + 11, gu, gv, np.floor(gu / 6.0) + 17.0 * index, fid[sidx]) > 0.45)
        luminance = sign_colour @ np.array([0.3, 0.59, 0.11])
        part[ink] = np.where((luminance[ink] > 0.5)[:, None], np.array([0.08, 0.08, 0.1]), np.array([0.97, 0.96, 0.9]))
        colour[sidx] = part
    # Ambient occlusion at the foot of the wall.
    return colour * (1.0 - 0.28 * np.exp(-v / 0.6))[:, None]


def roof_colour(town: Town, building: np.ndarray, *, x: np.ndarray, y: np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """[P] building index, roof point (x, y) and footprint (metres a sample covers, 0: the point) -> [P, 3] roof
    albedo (gravel, seams, vents, coping)."""
    salt = town.texture_salt
    gravel = _speckle(salt + 20, 0.05, x, y, footprint)
    tone = (0.78 + 0.22 * gravel) * (0.9 + 0.12 * _value_noise(salt + 21, x / 2.5, y / 2.5)) * _weathering(town, salt + 200, x, y, footprint)
    colour = town.roof[building] * tone[:, None]
    seam = _either(_lines(x, 2.0, 0.04, footprint), _lines(y, 2.0, 0.04, footprint))
    colour = colour * _dim(seam, 0.7)[:, None]
    cx, cy = np.floor(x / 5.0), np.floor(y / 5.0)
    ox, oy = x - cx * 5.0, y - cy * 5.0
    vent = (_hash(salt + 22, cx, cy) > 0.6) & (ox > 1.9) & (ox < 3.1) & (oy > 1.9) & (oy < 3.1)
    slats = _lines(ox[vent] - 1.9, 0.15, 0.05, footprint[vent])
    colour[vent] = np.array([0.62, 0.63, 0.65]) * _dim(slats, 0.7)[:, None]
    edge = np.minimum.reduce([x - town.lo[building, 0], town.hi[building, 0] - x, y - town.lo[building, 1], town.hi[building, 1] - y])
    colour[edge < 0.3] = town.trim[building[edge < 0.3]]
    return colour


def ground_colour(town: Town, x: np.ndarray, y: np.ndarray, *, footprint: np.ndarray) -> np.ndarray:
    """[P] ground points (x, y) and footprints (metres a sample covers, 0: the point) -> [P, 3] albedo:
    asphalt with lane markings and crossings, kerbs, tiled pavements, and grass in the empty lots."""
    salt = town.texture_salt
    config = town.config
    half_road, half_street = config.road_width / 2.0, config.street_width / 2.0
    dx = x - town.street_x[np.abs(x[:, None] - town.street_x[None]).argmin(axis=1)]
    dy = y - town.street_y[np.abs(y[:, None] - town.street_y[None]).argmin(axis=1)]
    ax, ay = np.abs(dx), np.abs(dy)
    road_v, road_h = ax < half_road, ay < half_road  # north-south road, east-west road
    street_v, street_h = ax < half_street, ay < half_street
    road = road_v | road_h
    pavement = (street_v | street_h) & ~road

    colour = np.empty((len(x), 3))
    # Asphalt: speckle (4 cm), patches (~2 m), repairs (~8 m).
    speckle = _speckle(salt + 30, 0.04, x, y, footprint)
    tone = (0.84 + 0.22 * speckle) * (0.9 + 0.14 * _value_noise(salt + 31, x / 2.0, y / 2.0))
    tone *= np.where(_value_noise(salt + 32, x / 8.0, y / 8.0) > 0.72, 0.85, 1.0)
    colour[:] = np.array([0.25, 0.25, 0.26]) * tone[:, None]
    paint = np.zeros(len(x), dtype=bool)
    # Lane markings away from the crossings: dashed centre line (3 m on, 3 m off), solid edge lines.
    mid_v = road_v & ~street_h
    mid_h = road_h & ~street_v
    paint |= mid_v & (ax < 0.075) & ((y % 6.0) < 3.0)
    paint |= mid_h & (ay < 0.075) & ((x % 6.0) < 3.0)
    paint |= mid_v & (np.abs(ax - (half_road - 0.35)) < 0.06)
    paint |= mid_h & (np.abs(ay - (half_road - 0.35)) < 0.06)
    # Zebra crossings just before each crossing: 0.5 m stripes.
    zebra_v = mid_v & (ay >= half_street + 0.3) & (ay < half_street + 3.3) & ((dx % 1.0) < 0.5) & (ax < half_road - 0.5)
    zebra_h = mid_h & (ax >= half_street + 0.3) & (ax < half_street + 3.3) & ((dy % 1.0) < 0.5) & (ay < half_road - 0.5)
    zebra_zone_v = mid_v & (ay >= half_street) & (ay < half_street + 3.6)
    zebra_zone_h = mid_h & (ax >= half_street) & (ax < half_street + 3.6)
    paint &= ~(zebra_zone_v | zebra_zone_h)
    paint |= zebra_v | zebra_h
    colour[paint] = np.array([0.9, 0.9, 0.86]) * (0.86 + 0.14 * speckle[paint])[:, None]

    # Pavement: 45 cm tiles with grout, and kerb stones (1 m) along the road.
    tx, ty = np.floor(x / 0.45), np.floor(y / 0.45)
    grout = _either(_lines(x, 0.45, 0.015, footprint, point=(x - tx * 0.45) < 0.015), _lines(y, 0.45, 0.015, footprint, point=(y - ty * 0.45) < 0.015))
    tile = np.array([0.63, 0.61, 0.57]) * (0.84 + 0.22 * _faded(_hash(salt + 33, tx, ty), 0.45, footprint))[:, None]
    tile = _mix(tile, np.array([0.42, 0.41, 0.39]), grout)
    kerb_v = street_v & ~road & (ax < half_road + 0.25) & ~road_h
    kerb_h = street_h & ~road & (ay < half_road + 0.25) & ~road_v
    kerb = kerb_v | kerb_h
    kerb_joint = np.where(kerb_v, _lines(y, 1.0, 0.02, footprint), _lines(x, 1.0, 0.02, footprint))
    tile[kerb] = _mix(np.broadcast_to(np.array([0.74, 0.74, 0.72]), (int(kerb.sum()), 3)), np.array([0.5, 0.5, 0.49]), kerb_joint[kerb])
    colour[pavement] = tile[pavement]

    # Empty lots and the rest: grass.
    lot = ~(road | pavement)
    blades = _speckle(salt + 34, 0.05, x, y, footprint)
    grass = np.array([0.28, 0.42, 0.18]) * ((0.7 + 0.45 * blades) * (0.85 + 0.2 * _value_noise(salt + 35, x, y)))[:, None]
    colour[lot] = grass[lot]
    return colour * _weathering(town, salt + 100, x, y, footprint)[:, None]  # on every ground surface


def sky_colour(directions: np.ndarray) -> np.ndarray:
    """[P, 3] unit directions -> [P, 3] sky at infinity (a gradient with a soft glow towards the sun)."""
    up = np.clip(directions[:, 2], 0.0, 1.0)[:, None]
    glow = np.clip(directions @ SUN, 0.0, 1.0)[:, None] ** 8
    return _SKY_HORIZON * (1.0 - up) + _SKY_ZENITH * up + 0.15 * glow
