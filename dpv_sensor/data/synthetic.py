"""Procedural synthetic indoor scenes with exact depth and poses (numpy + OpenCV, CPU, no downloads).

Every seed is a different room: an axis-aligned box room (walls, floor, ceiling; 3-7.5 m) furnished
with cabinets (some freely rotated), sofas, crates, rugs, tables with thin legs and things on them,
shelves with thin boards and books, pillars, bins, balls, floor lamps with glowing globes, coat poles,
skirting boards, ceiling panels and pendant lamps, pictures on the walls, and mirror-like or window-like
patches. Surfaces carry procedural textures mapped in surface coordinates (checker, stripes, value-noise
fBm at several scales, tiles, wood planks, natural-image-like 1/f noise, large weakly-textured paint), so
texture is consistent across views; mip-mapped (trilinear) look-ups keep distant textures from aliasing.

Shading is Lambertian with 1-3 point lights (ceiling lights and lamps) plus ambient light, soft shadows
from blurred (variance) cube shadow maps, Blinn-Phong specular highlights (view dependent: they move between views), and
mirror / glass patches whose colour comes from an environment map looked up along the reflected or viewing
direction — colour not tied to the surface, where depth from images is genuinely uncertain. The
renderer reports those pixels (and strong highlights) in a per-frame ``specular_mask``.

The camera walks a smooth hand-held loop (see :mod:`dpv_sensor.data.trajectory`) at 0.2-0.8 m/s, turning
and looking around; furniture is only placed where it keeps a clearance from the whole loop large enough
that every visible point is at least ``min_depth`` (0.3 m) in front of the camera, and the room is sized
so that no visible point is beyond ``max_depth`` (8 m). Intrinsics (field of view 50-75 deg, principal
point jitter), exposure, lens blur, sensor noise (shot + read), vignetting, optional motion blur (averaged
sub-frame renders) and optional rolling shutter (per-band poses) are randomised per sequence.

Outputs are exact: z-depth in metres (float32) of the centre-of-exposure pose, poses T_world_cam (OpenCV
axes, z-up world), K with pixel centres at integer coordinates. The scene is static by default (only the
camera moves); ``static=False`` adds moving balls (reported in ``dynamic_mask``).

All rendering is vectorised ray casting against analytic primitives (no per-pixel Python loops):
every primitive is tested only on the pixels inside its projected bounding box; pixel rays are
(x, y, 1) in the camera, so the ray parameter of a hit is its z-depth. Textures are generated lazily
from per-material seeds. About 20-30 frames/s at 320x240 on one core without motion blur
(``python -m dpv_sensor.benchmarks.render``). Everything is deterministic per seed and options.

Usage::

    seq = render_sequence(seed=3, num_frames=60)              # in-memory Sequence, 320x240
    python -m dpv_sensor.data.synthetic --seed 3 --frames 60 --out DIR
"""
from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import sys
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

import cv2
import numpy as np

from dpv_sensor.data.sequence import Sequence, write_sequence
from dpv_sensor.params import split_assignment
from dpv_sensor.data.trajectory import HandheldTrajectory

Range = Tuple[float, float]

KIND_DIFFUSE, KIND_MIRROR, KIND_GLASS, KIND_EMISSIVE = 0, 1, 2, 3
_N_ROOM_FACES = 6
_EPS_T = 1e-4


# ==================================================================================================
# configuration
# ==================================================================================================

@dataclass
class SceneConfig:
    """Options of the synthetic renderer. ``(lo, hi)`` tuples are ranges sampled per seed (uniform;
    integer counts inclusive); scalars and booleans are fixed. Lengths in metres, angles in degrees,
    times in seconds. Any field can be passed to :func:`render_sequence` as a keyword argument.
    """
    # --- room ---
    room_size_x: Range = (3.0, 7.5)          # room length (m)
    room_size_y: Range = (3.0, 7.5)          # room width (m)
    room_height: Range = (2.4, 3.2)          # floor to ceiling (m)
    min_depth: float = 0.3                   # every visible point is at least this far (z) from the camera
    max_depth: float = 8.0                   # ... and at most this far (the room is resized until it holds)
    # --- furniture (counts are attempts; pieces that would come too close to the camera path are dropped) ---
    num_cabinets: Tuple[int, int] = (2, 6)   # boxes: cabinets, chests, wardrobes (some rotated freely)
    num_sofas: Tuple[int, int] = (0, 1)      # low wide box with a backrest
    num_tables: Tuple[int, int] = (0, 2)     # board on four thin legs, objects on top
    num_shelves: Tuple[int, int] = (0, 2)    # side boards + thin shelf boards + books
    num_pillars: Tuple[int, int] = (0, 2)    # floor-to-ceiling cylinders
    num_crates: Tuple[int, int] = (1, 5)     # small boxes on the floor, sometimes stacked, random yaw
    num_rugs: Tuple[int, int] = (0, 1)       # thin textured boxes on the floor
    skirting_prob: float = 0.6               # probability of skirting boards along the walls
    near_path_prob: float = 0.5              # free-standing pieces placed just beside the camera path
    num_bins: Tuple[int, int] = (0, 3)       # short cylinders
    num_balls: Tuple[int, int] = (1, 3)      # spheres on the floor
    num_floor_lamps: Tuple[int, int] = (0, 1)  # thin pole + glowing globe that is also a point light
    num_poles: Tuple[int, int] = (0, 2)      # thin vertical poles (coat stands)
    num_pictures: Tuple[int, int] = (1, 4)   # thin boxes on walls with natural-image-like textures
    num_mirrors: Tuple[int, int] = (0, 1)    # mirror patches on walls (environment reflection)
    num_windows: Tuple[int, int] = (0, 1)    # window-like glass patches on walls (environment seen through)
    # --- materials ---
    texture_size: int = 256                  # texels per side of each tileable procedural texture
    plain_wall_prob: float = 0.6             # probability that the walls are weakly textured paint
    glossy_prob: float = 0.35                # probability that a material has a visible highlight
    # --- lights ---
    num_lights: Tuple[int, int] = (1, 2)     # ceiling point lights (floor lamps add their own)
    light_intensity: Range = (0.6, 1.4)
    ambient: Range = (0.08, 0.25)
    shadows: bool = True                     # cube shadow maps (static casters)
    max_shadowed_lights: int = 2             # only the strongest lights cast shadows (speed)
    shadow_map_size: int = 160               # texels per cube face
    # --- camera intrinsics ---
    fov_deg: Range = (50.0, 75.0)            # horizontal field of view
    principal_point_jitter: float = 0.03     # +- fraction of the image size
    # --- trajectory (hand-held walk) ---
    fps: float = 30.0
    speed: Range = (0.2, 0.8)                # walking speed (m/s)
    camera_height: Range = (1.0, 1.7)
    pitch_deg: Range = (-28.0, 5.0)          # elevation of the optical axis (negative = looking down)
    yaw_offset_deg: Range = (20.0, 75.0)     # mean turn from the walking direction towards the loop inside
    yaw_sway_deg: float = 50.0               # slow look-around amplitude
    max_turn_rate_deg: float = 60.0          # bound on the walking direction's turn rate (path curvature)
    roll_deg: float = 3.0
    shake_m: float = 0.012                   # positional hand shake bound
    tremor_deg: float = 0.4                  # rotational hand tremor amplitude
    # --- sensor ---
    exposure: Range = (0.32, 0.5)            # target mean brightness (0..1, after gamma) of the sequence
    exposure_drift: float = 0.0              # +- relative auto-exposure drift along the sequence (0 = fixed)
    read_noise: Range = (0.001, 0.004)       # std of additive noise (linear intensity)
    shot_noise: Range = (0.002, 0.008)       # std of signal-dependent noise: shot * sqrt(linear intensity)
    vignetting: Range = (0.0, 0.2)           # relative fall-off at the image corners
    optical_blur: Range = (0.35, 0.7)        # std (pixels) of the lens point-spread function (Gaussian)
    gamma: float = 2.2
    motion_blur: bool = False                # average sub-frame renders over the exposure time
    blur_samples: int = 5
    exposure_time: Range = (0.008, 0.03)
    rolling_shutter: bool = False            # rows exposed at different times (per-band poses)
    readout_time: Range = (0.01, 0.03)       # first to last row
    rolling_shutter_bands: int = 8
    # --- dynamics ---
    static: bool = True                      # False: some balls move (reported in dynamic_mask)
    num_moving: Tuple[int, int] = (1, 2)

    def replace(self, **options) -> 'SceneConfig':
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(options) - names)
        if unknown:
            raise TypeError(f'unknown synthetic scene option(s): {", ".join(unknown)}; known: {sorted(names)}')
        return dataclasses.replace(self, **options)


# ==================================================================================================
# textures (tileable, linear albedo in [0, 1])
# ==================================================================================================

def _srgb_to_linear(c):
    return np.power(np.clip(c, 0.0, 1.0), 2.2)


def _random_color(rng, sat=(0.0, 0.6), val=(0.3, 0.95), hue=None) -> np.ndarray:
    h = rng.uniform(0, 1) if hue is None else hue
    s = rng.uniform(*sat)
    v = rng.uniform(*val)
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    rgb = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]
    return _srgb_to_linear(np.asarray(rgb, dtype=np.float64))


def _value_noise(rng, S: int, cells: int) -> np.ndarray:
    """Tileable value noise in [0, 1]: a random cells x cells lattice, bicubically interpolated."""
    cells = max(1, min(cells, S))
    g = rng.random((cells, cells)).astype(np.float32)
    pad = 2
    gp = np.pad(g, pad, mode='wrap')
    scale = S / cells
    big = cv2.resize(gp, (int(round((cells + 2 * pad) * scale)),) * 2, interpolation=cv2.INTER_CUBIC)
    o = int(round(pad * scale))
    out = big[o:o + S, o:o + S]
    return np.clip(out, 0.0, 1.0)


def _fbm(rng, S: int, base_cells: int, octaves: int, persistence: float = 0.5) -> np.ndarray:
    """Tileable fractal value noise, normalised to [0, 1]."""
    out = np.zeros((S, S), np.float32)
    amp, total = 1.0, 0.0
    cells = base_cells
    for _ in range(octaves):
        if cells > S:
            break
        out += amp * _value_noise(rng, S, cells)
        total += amp
        amp *= persistence
        cells *= 2
    out /= total
    lo, hi = out.min(), out.max()
    return (out - lo) / max(hi - lo, 1e-6)


def _spectral_noise(rng, S: int, beta: float = 1.0, fmin: float = 1.0, fmax: float = None) -> np.ndarray:
    """Tileable noise with amplitude spectrum ~ 1/f^beta (beta = 1: natural-image statistics), zero mean,
    unit standard deviation."""
    white = rng.standard_normal((S, S))
    F = np.fft.rfft2(white)
    fy = np.fft.fftfreq(S)[:, None] * S
    fx = np.fft.rfftfreq(S)[None, :] * S
    f = np.sqrt(fx ** 2 + fy ** 2)
    filt = np.zeros_like(f)
    fmax = fmax or S / 2
    band = (f >= fmin) & (f <= fmax)
    filt[band] = 1.0 / f[band] ** beta
    out = np.fft.irfft2(F * filt, s=(S, S)).astype(np.float32)
    return (out - out.mean()) / max(out.std(), 1e-9)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _mix(c0, c1, w):
    w = w[..., None]
    return (1 - w) * np.asarray(c0, np.float32) + w * np.asarray(c1, np.float32)


def _grid(S):
    y, x = np.mgrid[0:S, 0:S].astype(np.float32)
    return x, y


def _tex_plain(rng, S, color=None, strength=None):
    """Weakly textured paint: a colour with a few percent of low-frequency variation."""
    c = _random_color(rng, sat=(0.0, 0.35), val=(0.55, 0.95)) if color is None else color
    strength = rng.uniform(0.015, 0.05) if strength is None else strength
    n = _fbm(rng, S, 2, 3, 0.5) - 0.5
    return np.clip(c[None, None, :] * (1 + 2 * strength * n[..., None]), 0, 1).astype(np.float32)


def _tex_checker(rng, S):
    n = int(rng.choice([2, 4, 8]))
    x, y = _grid(S)
    c0, c1 = _random_color(rng, val=(0.1, 0.5)), _random_color(rng, val=(0.5, 0.95))
    cell = S // n
    soft = 1.5
    fx = _smoothstep((np.abs(((x + 0.5) % cell) - cell / 2) - cell / 4) / soft + 0.5)
    fy = _smoothstep((np.abs(((y + 0.5) % cell) - cell / 2) - cell / 4) / soft + 0.5)
    w = fx + fy - 2 * fx * fy
    grain = 1 + 0.08 * (_fbm(rng, S, 16, 3) - 0.5)
    return np.clip(_mix(c0, c1, w) * grain[..., None], 0, 1)


def _tex_stripes(rng, S):
    n = int(rng.choice([4, 8, 16]))
    x, y = _grid(S)
    coord = x if rng.random() < 0.5 else (x + y if rng.random() < 0.4 else y)
    duty = rng.uniform(0.25, 0.6)
    ph = ((coord + 0.5) * n / S) % 1.0
    w = _smoothstep((ph - duty) * S / n / 1.5 + 0.5) * (1 - _smoothstep((ph - 0.98) * S / n / 1.5 + 0.5))
    c0 = _random_color(rng, val=(0.35, 0.9))
    c1 = _random_color(rng, val=(0.2, 0.9))
    grain = 1 + 0.06 * (_fbm(rng, S, 8, 4) - 0.5)
    return np.clip(_mix(c0, c1, w) * grain[..., None], 0, 1)


def _tex_fbm(rng, S):
    """Stone / fabric / plaster: fBm mapped through a 2-3 colour ramp, at a random base scale."""
    n = _fbm(rng, S, int(rng.choice([2, 4, 8, 16])), int(rng.integers(3, 7)), rng.uniform(0.45, 0.7))
    n = _smoothstep((n - 0.5) * rng.uniform(1.0, 2.5) + 0.5)
    hue = rng.uniform(0, 1)
    c0 = _random_color(rng, sat=(0.0, 0.5), val=(0.15, 0.5), hue=hue)
    c1 = _random_color(rng, sat=(0.0, 0.5), val=(0.55, 0.95), hue=(hue + rng.uniform(-0.08, 0.08)) % 1)
    return _mix(c0, c1, n)


def _tex_tiles(rng, S):
    n = int(rng.choice([2, 4, 8]))
    x, y = _grid(S)
    cell = S / n
    grout = rng.uniform(0.02, 0.06) * cell
    gx = np.minimum((x + 0.5) % cell, cell - (x + 0.5) % cell)
    gy = np.minimum((y + 0.5) % cell, cell - (y + 0.5) % cell)
    line = 1 - _smoothstep((np.minimum(gx, gy) - grout) / 1.5 + 0.5)
    base = _random_color(rng, sat=(0.0, 0.4), val=(0.4, 0.95))
    tile_id = (np.floor((y + 0.5) / cell) * n + np.floor((x + 0.5) / cell)).astype(int) % (n * n)
    jitter = 1 + rng.uniform(-0.12, 0.12, size=n * n)[tile_id]
    speck = 1 + 0.12 * (_fbm(rng, S, 32, 3) - 0.5)
    tile = base[None, None, :] * (jitter * speck)[..., None]
    grout_c = _random_color(rng, sat=(0.0, 0.1), val=(0.2, 0.7))
    return np.clip(_mix(tile, np.broadcast_to(grout_c, tile.shape), line), 0, 1)


def _tex_wood(rng, S):
    """Planks with per-plank tone, growth rings along the grain, and seams."""
    planks = int(rng.choice([2, 4, 8]))
    x, y = _grid(S)
    width = S / planks
    plank = np.floor((y + 0.5) / width).astype(int) % planks
    warp = _fbm(rng, S, 4, 4) - 0.5
    ring_f = rng.uniform(6, 20)
    offs = rng.uniform(0, 100, size=planks)[plank]
    rings = 0.5 + 0.5 * np.sin(2 * math.pi * (ring_f * ((y + 0.5) / S + 0.15 * warp) + offs * 0.37)
                               + 3 * warp)
    streak = _value_noise(rng, S, S // 2)
    hue = rng.uniform(0.05, 0.11)
    light = _random_color(rng, sat=(0.35, 0.6), val=(0.55, 0.9), hue=hue)
    dark = light * rng.uniform(0.35, 0.6)
    tone = rng.uniform(0.75, 1.1, size=planks)[plank]
    w = np.clip(0.65 * rings ** 2 + 0.35 * streak, 0, 1)
    col = _mix(light, dark, w) * tone[..., None]
    seam_d = np.minimum((y + 0.5) % width, width - (y + 0.5) % width)
    seam = 1 - 0.6 * (1 - _smoothstep(seam_d / 1.2))
    return np.clip(col * seam[..., None], 0, 1)


def _tex_natural(rng, S):
    """Natural-image-like colour texture: 1/f amplitude spectrum, correlated channels, some edges."""
    beta = rng.uniform(0.9, 1.3)
    lum = _spectral_noise(rng, S, beta, fmin=1.0)
    chroma = [_spectral_noise(rng, S, beta + 0.3, fmin=1.0) for _ in range(2)]
    blobs = _spectral_noise(rng, S, 1.6, fmin=1.0)
    lum = lum + rng.uniform(0.5, 1.5) * np.tanh(3 * blobs)   # region-like structure with edges
    lum = (lum - lum.mean()) / max(lum.std(), 1e-6)
    mean = _random_color(rng, sat=(0.1, 0.6), val=(0.35, 0.75))
    M = rng.normal(size=(3, 3)) * 0.35 + np.eye(3) * 0.2
    rgb = np.stack([lum, chroma[0], chroma[1]], -1) @ M.T.astype(np.float32)
    rgb = 0.9 * lum[..., None] + rgb * 0.5
    contrast = rng.uniform(0.15, 0.35)
    return np.clip(mean[None, None, :] * np.exp(contrast * rgb * 2.0), 0, 1).astype(np.float32)


def _tex_carpet(rng, S):
    fine = _fbm(rng, S, 64, 2, 0.6)
    coarse = _fbm(rng, S, 4, 3, 0.5)
    c = _random_color(rng, sat=(0.1, 0.6), val=(0.25, 0.75))
    return np.clip(c[None, None, :] * (0.75 + 0.35 * fine + 0.2 * (coarse - 0.5))[..., None], 0, 1)


_BRICK_ROWS = 16


def _tex_bricks(rng, S):
    rows = _BRICK_ROWS
    x, y = _grid(S)
    h = S / rows
    row = np.floor((y + 0.5) / h).astype(int)
    w = 2 * h
    xs = (x + 0.5 + (row % 2) * w / 2) % w
    ys = (y + 0.5) % h
    mortar = rng.uniform(0.06, 0.12) * h
    d = np.minimum(np.minimum(xs, w - xs), np.minimum(ys, h - ys))
    line = 1 - _smoothstep((d - mortar) / 1.2 + 0.5)
    base = _random_color(rng, sat=(0.3, 0.7), val=(0.35, 0.7), hue=rng.uniform(0.0, 0.08))
    n_bricks = int(rows * (S / w + 1))
    bid = (row * int(S / w + 1) + np.floor((x + 0.5 + (row % 2) * w / 2) / w).astype(int)) % n_bricks
    tone = rng.uniform(0.75, 1.15, size=n_bricks)[bid] * (1 + 0.15 * (_fbm(rng, S, 32, 3) - 0.5))
    brick = base[None, None, :] * tone[..., None]
    mortar_c = _random_color(rng, sat=(0.0, 0.1), val=(0.6, 0.85))
    return np.clip(_mix(brick, np.broadcast_to(mortar_c, brick.shape), line), 0, 1)


_TEXTURES = {'plain': _tex_plain, 'checker': _tex_checker, 'stripes': _tex_stripes, 'fbm': _tex_fbm,
             'tiles': _tex_tiles, 'wood': _tex_wood, 'natural': _tex_natural, 'carpet': _tex_carpet,
             'bricks': _tex_bricks}


def _mip_pyramid(tex: np.ndarray) -> List[np.ndarray]:
    levels = [np.ascontiguousarray(tex, dtype=np.float32)]
    while levels[-1].shape[0] > 1:
        s = levels[-1].shape[0] // 2
        levels.append(cv2.resize(levels[-1], (s, s), interpolation=cv2.INTER_AREA))
    return levels


class Material:
    """A surface material: a tileable texture (mip pyramid ``levels``) of linear albedo with ``texel``
    metres per level-0 texel, Blinn-Phong specular strength ``ks`` / ``shininess``, and a kind (diffuse,
    mirror, glass or emissive). Mirror and glass blend the shaded albedo with the environment map by
    ``env_mix``. The texture is generated from its own seed the first time it is looked up, so materials
    that a short clip never shows cost nothing (and the result does not depend on what was seen before)."""

    def __init__(self, name: str, pattern: str, texture_seed: int, size: int, texel: float, ks: float = 0.0,
                 shininess: float = 20.0, kind: int = KIND_DIFFUSE, env_mix: float = 0.0,
                 tex_kwargs: Optional[dict] = None):
        self.name, self.pattern = name, pattern
        self.texture_seed, self.size = int(texture_seed), int(size)
        self.texel, self.ks, self.shininess = float(texel), float(ks), float(shininess)
        self.kind, self.env_mix = kind, float(env_mix)
        self.emission: Tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._tex_kwargs = dict(tex_kwargs or {})
        self._levels: Optional[List[np.ndarray]] = None

    @property
    def levels(self) -> List[np.ndarray]:
        if self._levels is None:
            tex = _TEXTURES[self.pattern](np.random.default_rng(self.texture_seed), self.size, **self._tex_kwargs)
            self._levels = _mip_pyramid(tex)
        return self._levels


def _make_material(rng, name: str, pattern: str, S: int, scale_m: Range, glossy_prob: float,
                   ks_range: Range = (0.04, 0.35), kind: int = KIND_DIFFUSE, env_mix: float = 0.0,
                   **tex_kwargs) -> Material:
    """``scale_m``: physical size of one texture tile (metres), sampled in the range."""
    texture_seed = int(rng.integers(0, 2 ** 63 - 1))
    tile = rng.uniform(*scale_m)
    if pattern == 'bricks':                # keep bricks brick-sized (6-9 cm courses) whatever the range
        tile = _BRICK_ROWS * rng.uniform(0.06, 0.09)
    ks = rng.uniform(*ks_range) if rng.random() < glossy_prob else 0.0
    return Material(name, pattern, texture_seed, S, texel=tile / S, ks=ks, shininess=float(rng.uniform(15, 120)),
                    kind=kind, env_mix=env_mix, tex_kwargs=tex_kwargs)


def _environment_map(rng, H: int = 128, W: int = 256) -> np.ndarray:
    """Lat-long environment (rows: elevation +90..-90 deg; columns: azimuth -180..180 deg), linear RGB:
    sky with clouds, a skyline of blocks with lit windows, ground."""
    el = (0.5 - (np.arange(H) + 0.5) / H) * math.pi
    sky_top = _random_color(rng, sat=(0.2, 0.6), val=(0.6, 0.95), hue=rng.uniform(0.52, 0.66))
    sky_hor = _random_color(rng, sat=(0.0, 0.25), val=(0.8, 1.0))
    ground = _random_color(rng, sat=(0.05, 0.4), val=(0.2, 0.5))
    w = np.clip(np.sin(np.maximum(el, 0)), 0, 1)[:, None, None]
    env = (1 - w) * sky_hor + w * sky_top
    env = np.broadcast_to(env, (H, W, 3)).astype(np.float32).copy()
    clouds = _spectral_noise(rng, W, 1.2)[:H]
    env *= (1 + 0.25 * np.tanh(clouds))[..., None]
    horizon = H // 2
    env[horizon:] = ground * (1 + 0.2 * _spectral_noise(rng, W, 1.0)[:H - horizon, :W, None])
    x = 0
    while x < W:
        bw = int(rng.integers(8, 40))
        bh = int(rng.integers(4, H // 3))
        c = _random_color(rng, sat=(0.0, 0.3), val=(0.15, 0.6))
        env[horizon - bh:horizon, x:x + bw] = c
        win = rng.random((bh, min(bw, W - x))) < 0.15
        env[horizon - bh:horizon, x:x + bw][win] = np.array([1.0, 0.9, 0.6]) * rng.uniform(0.7, 1.0)
        x += bw + int(rng.integers(0, 20))
    return np.clip(env, 0, 1.2).astype(np.float32)


# ==================================================================================================
# primitives
# ==================================================================================================

def _rotz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class Primitive:
    """An analytic solid: 'box' (half extents ``half``), 'cyl' (vertical cylinder: half = (r, r, half
    height)) or 'sph' (half = (r, r, r)), centred at ``center``, rotated by ``yaw`` about the vertical."""
    kind: str
    center: np.ndarray
    half: np.ndarray
    yaw: float
    material: int
    uv_offset: Tuple[float, float] = (0.0, 0.0)
    casts_shadow: bool = True
    label: str = ''
    motion: Optional[Tuple[np.ndarray, float, np.ndarray]] = None   # (amplitude (3,), omega, phase (3,))

    def __post_init__(self):
        self.center = np.asarray(self.center, np.float64)
        self.half = np.asarray(self.half, np.float64)
        self.R = _rotz(self.yaw)
        self.half_f = tuple(float(v) for v in self.half)
        signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], np.float64)
        self._corner_offsets = (signs * self.half) @ self.R.T
        c = self.center + self._corner_offsets
        m = np.zeros(3) if self.motion is None else np.abs(np.asarray(self.motion[0], np.float64))
        self._aabb = (c.min(0) - m, c.max(0) + m)

    def center_at(self, t: float) -> np.ndarray:
        if self.motion is None:
            return self.center
        amp, w, ph = self.motion
        return self.center + amp * np.sin(w * t + ph)

    def motion_bound(self) -> float:
        return 0.0 if self.motion is None else float(np.linalg.norm(self.motion[0]))

    def corners(self, t: float = 0.0) -> np.ndarray:
        """(8, 3) world corners of the (oriented) bounding box."""
        return self.center_at(t) + self._corner_offsets

    def aabb(self, inflate: float = 0.0) -> Tuple[np.ndarray, np.ndarray]:
        lo, hi = self._aabb
        return lo - inflate, hi + inflate

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m) from world points (M, 3) to the solid at rest, minus its motion range."""
        p = (points - self.center) @ self.R
        if self.kind == 'box':
            q = np.abs(p) - self.half
            d = np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0)
        elif self.kind == 'cyl':
            r, hz = self.half[0], self.half[2]
            dr = np.linalg.norm(p[:, :2], axis=-1) - r
            dz = np.abs(p[:, 2]) - hz
            d = np.minimum(np.maximum(dr, dz), 0) + np.hypot(np.maximum(dr, 0), np.maximum(dz, 0))
        else:
            d = np.linalg.norm(p, axis=-1) - self.half[0]
        return d - self.motion_bound()


# ==================================================================================================
# ray casting helpers
# ==================================================================================================

class _PixelRays:
    """Camera rays (x, y, 1) of every pixel for intrinsics K (pixel centres at integer coordinates)."""

    def __init__(self, K: np.ndarray, width: int, height: int):
        self.K = np.asarray(K, np.float64)
        self.width, self.height = int(width), int(height)
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        u = (np.arange(width) - cx) / fx
        v = (np.arange(height) - cy) / fy
        self.dx = np.ascontiguousarray(np.broadcast_to(u[None, :], (height, width)), dtype=np.float32)
        self.dy = np.ascontiguousarray(np.broadcast_to(v[:, None], (height, width)), dtype=np.float32)
        self.norm = np.sqrt(self.dx ** 2 + self.dy ** 2 + 1).astype(np.float32)
        self.inv_norm = (1.0 / self.norm).astype(np.float32)


def _intersect_box(o, dx, dy, dz, half):
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        tnear = None
        tfar = None
        for oi, di, hi in ((o[0], dx, half[0]), (o[1], dy, half[1]), (o[2], dz, half[2])):
            inv = 1.0 / di
            ta = (-hi - oi) * inv
            tb = (hi - oi) * inv
            lo = np.minimum(ta, tb)
            hi_ = np.maximum(ta, tb)
            tnear = lo if tnear is None else np.maximum(tnear, lo)
            tfar = hi_ if tfar is None else np.minimum(tfar, hi_)
        hit = (tnear <= tfar) & (tnear > _EPS_T)
        return np.where(hit, tnear, np.float32(np.inf))


def _intersect_cyl(o, dx, dy, dz, half):
    r, hz = half[0], half[2]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        a = dx * dx + dy * dy
        b = o[0] * dx + o[1] * dy
        c = o[0] ** 2 + o[1] ** 2 - r * r
        disc = b * b - a * c
        ts = (-b - np.sqrt(disc)) / a
        z = o[2] + ts * dz
        t = np.where((disc >= 0) & (np.abs(z) <= hz) & (ts > _EPS_T), ts, np.float32(np.inf))
        if abs(o[2]) > hz:
            zc = hz if o[2] > 0 else -hz
            tc = (zc - o[2]) / dz
            xc = o[0] + tc * dx
            yc = o[1] + tc * dy
            cap = (tc > _EPS_T) & (xc * xc + yc * yc <= r * r)
            t = np.where(cap & (tc < t), tc, t)
        return t


def _intersect_sph(o, dx, dy, dz, half):
    r = half[0]
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        a = dx * dx + dy * dy + dz * dz
        b = o[0] * dx + o[1] * dy + o[2] * dz
        c = o[0] ** 2 + o[1] ** 2 + o[2] ** 2 - r * r
        disc = b * b - a * c
        ts = (-b - np.sqrt(disc)) / a
        return np.where((disc >= 0) & (ts > _EPS_T), ts, np.float32(np.inf))


_INTERSECT = {'box': _intersect_box, 'cyl': _intersect_cyl, 'sph': _intersect_sph}


def _remap_points(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear, wrap-around samples of img (h, w, 3) at float coordinates x, y (n,) -> (n, 3)."""
    n = x.shape[0]
    if n == 0:
        return np.zeros((0, img.shape[2]), np.float32)
    if n < 32000:                      # cv2.remap wants map sides below SHRT_MAX
        mx = x.astype(np.float32, copy=False).reshape(1, n)
        my = y.astype(np.float32, copy=False).reshape(1, n)
        return cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).reshape(n, -1)
    cols = 1024
    rows = (n + cols - 1) // cols
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n] = x
    my[:n] = y
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    return out.reshape(rows * cols, -1)[:n]


def _sample_material(mat: Material, u_m: np.ndarray, v_m: np.ndarray, footprint_m: np.ndarray) -> np.ndarray:
    """Trilinear mip-mapped texture look-up at surface coordinates (metres) -> (n, 3) albedo.

    The level of detail is log2(pixel footprint / texel size); the two nearest pyramid levels are sampled
    bilinearly (cv2.remap wraps coordinates of any size around the tile) and blended."""
    n = u_m.shape[0]
    if n == 0:
        return np.zeros((0, 3), np.float32)
    levels = mat.levels
    n_lev = len(levels)
    inv_texel = np.float32(1.0 / mat.texel)
    u = u_m * inv_texel
    v = v_m * inv_texel
    lod = np.log2(np.maximum(footprint_m * inv_texel, np.float32(1e-6)))
    np.clip(lod, 0.0, n_lev - 1.001, out=lod)
    l0 = lod.astype(np.int32)
    lo, hi = int(l0.min()), int(l0.max())
    frac = (lod - l0).astype(np.float32)[:, None]
    if lo == hi:
        groups = [(lo, None)]
    else:
        groups = [(lev, np.flatnonzero(l0 == lev)) for lev in range(lo, hi + 1)]
    out = np.empty((n, 3), np.float32)
    for lev, sel in groups:
        if sel is not None and sel.size == 0:
            continue
        us, vs = (u, v) if sel is None else (u[sel], v[sel])
        pair = []
        for L in (lev, min(lev + 1, n_lev - 1)):
            scale = np.float32(1.0 / (1 << L))
            off = np.float32(0.5 * scale - 0.5)
            pair.append(_remap_points(levels[L], us * scale + off, vs * scale + off))
        f = frac if sel is None else frac[sel]
        blended = pair[0] + (pair[1] - pair[0]) * f
        if sel is None:
            out = blended
        else:
            out[sel] = blended
    return out


# ==================================================================================================
# scene
# ==================================================================================================

@dataclass
class _Light:
    position: np.ndarray
    color: np.ndarray            # linear RGB intensity
    falloff: float               # distance at which the intensity halves
    shadow_atlas: Optional[np.ndarray] = None   # (6*S*S,) euclidean distance to the first surface


@dataclass
class _RayHits:
    """The rays of the rows being shaded, flattened (n = rows x width): the camera centre ``o`` and rotation ``R`` in
    the world, the render time, the hit distance along the unnormalised ray ``tf`` and the hit id ``idf``, the world
    ray directions ``dwf`` (one array per axis), the camera-plane directions ``dxf`` / ``dyf``, 1/|ray| and 1/fx."""
    o: List[float]
    R: np.ndarray
    time: float
    tf: np.ndarray
    idf: np.ndarray
    dwf: List[np.ndarray]
    dxf: np.ndarray
    dyf: np.ndarray
    inv_dnorm: np.ndarray
    inv_fx: float

    @property
    def n(self) -> int:
        return self.tf.size


@dataclass
class _Surfaces:
    """Per hit: world normal (3, n), linear albedo (3, n), specular weight, shininess and material kind."""
    normal: np.ndarray
    albedo: np.ndarray
    ks: np.ndarray
    shin: np.ndarray
    kind: np.ndarray


def _box_normal_uv(pl, nl, half):
    """Box hits at local points ``pl``: writes the local normal into ``nl``; returns the surface coordinates
    (horizontal faces (x, y); vertical faces (horizontal, z))."""
    hx, hy, hz = half
    rx, ry, rz = np.abs(pl[0]) * (1 / hx), np.abs(pl[1]) * (1 / hy), np.abs(pl[2]) * (1 / hz)
    is_y = ry > rx
    is_z = rz > np.maximum(rx, ry)
    is_x = ~(is_y | is_z)
    is_y &= ~is_z
    nl[0] = is_x * np.sign(pl[0])
    nl[1] = is_y * np.sign(pl[1])
    nl[2] = is_z * np.sign(pl[2])
    uu = np.where(is_x, pl[1], pl[0]) + 1.7 * is_y + 3.4 * is_z + 0.9 * (nl[0] + nl[1] + nl[2])
    vv = np.where(is_z, pl[1], pl[2])
    return uu, vv


def _cylinder_normal_uv(pl, nl, half):
    """Cylinder hits (side and caps) at local points ``pl``: the local normal into ``nl``; returns (u, v)."""
    r, _, hz = half
    cap = np.abs(pl[2]) >= hz * (1 - 1e-4) - 1e-6
    side_ = ~cap
    inv_rho = 1.0 / np.maximum(np.sqrt(pl[0] ** 2 + pl[1] ** 2), 1e-9)
    nl[0] = pl[0] * inv_rho * side_
    nl[1] = pl[1] * inv_rho * side_
    nl[2] = np.sign(pl[2]) * cap
    if cap.any():
        return np.where(cap, pl[0], np.arctan2(pl[1], pl[0]) * r), np.where(cap, pl[1] + 3.1, pl[2])
    return np.arctan2(pl[1], pl[0]) * r, pl[2]


def _sphere_normal_uv(pl, nl, half):
    """Sphere hits at local points ``pl``: the local normal into ``nl``; returns (u, v) (longitude, latitude)."""
    r = half[0]
    nl[0], nl[1], nl[2] = pl[0] * (1 / r), pl[1] * (1 / r), pl[2] * (1 / r)
    return np.arctan2(pl[1], pl[0]) * r, np.arcsin(np.clip(pl[2] * (1 / r), -1, 1)) * r


class _FurnitureMaker:
    """The furniture pieces of a scene: each method draws one piece at a random spot of the room and returns its
    primitives (the scene places them with :meth:`SyntheticScene._try_place`). The draws from the scene's random
    generator come in a fixed order, so a seed gives the same room."""

    def __init__(self, scene: 'SyntheticScene', rng):
        self.scene = scene
        self.rng = rng

    def count(self, r) -> int:
        """A count drawn from an inclusive ``(lo, hi)`` range."""
        return int(self.rng.integers(r[0], r[1] + 1))

    def uvo(self):
        """A random texture offset."""
        return (float(self.rng.uniform(0, 10)), float(self.rng.uniform(0, 10)))

    def box(self, center, half, yaw, mat, label, **kw):
        return Primitive('box', center, half, yaw, mat, self.uvo(), label=label, **kw)

    def cabinet(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        w, d, h = rng.uniform(0.4, 1.6), rng.uniform(0.3, 0.7), rng.uniform(0.4, 2.1)
        c, yaw = scene._floor_spot(rng, w, d, 0.7)
        return [self.box([c[0], c[1], h / 2], [w / 2, d / 2, h / 2], yaw, int(rng.choice(mf)), 'cabinet')]

    def sofa(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        w, d = rng.uniform(1.3, 2.2), rng.uniform(0.75, 1.0)
        c, yaw = scene._floor_spot(rng, w, d, 0.6)
        R = _rotz(yaw)
        mat = int(rng.choice(mf))
        seat_h = rng.uniform(0.35, 0.5)
        back_d = rng.uniform(0.15, 0.25)
        back_h = rng.uniform(0.75, 0.95)
        # local +y points to the back (towards the wall for wall-standing pieces)
        seat_c = np.r_[c, seat_h / 2] + R @ np.array([0, -back_d / 2, 0])
        back_c = np.r_[c, back_h / 2] + R @ np.array([0, (d - back_d) / 2, 0])
        return [self.box(seat_c, [w / 2, (d - back_d) / 2, seat_h / 2], yaw, mat, 'sofa seat'),
                self.box(back_c, [w / 2, back_d / 2, back_h / 2], yaw, mat, 'sofa back')]

    def table(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        w, d = rng.uniform(0.6, 1.8), rng.uniform(0.5, 1.0)
        h, th = rng.uniform(0.68, 0.8), rng.uniform(0.025, 0.05)
        c, yaw = scene._floor_spot(rng, w, d, 0.3)
        R = _rotz(yaw)
        top_mat = int(rng.choice(mf))
        leg_r = rng.uniform(0.015, 0.035)
        leg_mat = scene.mat_metal if rng.random() < 0.5 else top_mat
        parts = [self.box([c[0], c[1], h - th / 2], [w / 2, d / 2, th / 2], yaw, top_mat, 'table top')]
        inset = rng.uniform(0.04, 0.1)
        for sx in (-1, 1):
            for sy in (-1, 1):
                p = np.r_[c, 0] + R @ np.array([sx * (w / 2 - inset), sy * (d / 2 - inset), 0])
                parts.append(Primitive('cyl', [p[0], p[1], (h - th) / 2], [leg_r, leg_r, (h - th) / 2], 0.0,
                                       leg_mat, self.uvo(), label='table leg'))
        for _ in range(int(rng.integers(0, 4))):   # things on the table
            sw, sd, sh = rng.uniform(0.06, 0.3), rng.uniform(0.06, 0.3), rng.uniform(0.03, 0.3)
            local = np.array([rng.uniform(-(w - sw) / 2, (w - sw) / 2),
                              rng.uniform(-(d - sd) / 2, (d - sd) / 2), 0])
            p = np.r_[c, 0] + R @ local
            kind = rng.choice(['box', 'cyl', 'sph'])
            mat = int(rng.choice(mf + scene.mat_pictures))
            if kind == 'box':
                parts.append(self.box([p[0], p[1], h + sh / 2], [sw / 2, sd / 2, sh / 2],
                                      yaw + rng.uniform(-0.5, 0.5), mat, 'table object'))
            elif kind == 'cyl':
                r = min(sw, sd) / 2
                parts.append(Primitive('cyl', [p[0], p[1], h + sh / 2], [r, r, sh / 2], 0.0, mat, self.uvo(),
                                       label='table object'))
            else:
                r = min(sw, sd) / 2
                parts.append(Primitive('sph', [p[0], p[1], h + r], [r, r, r], 0.0, mat, self.uvo(),
                                       label='table object'))
        return parts

    def shelf(self):
        scene, rng, L, mf = self.scene, self.rng, self.scene.room, self.scene.mat_furniture
        w, d, h = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4), rng.uniform(1.0, min(2.2, L[2] - 0.1))
        c, yaw = scene._floor_spot(rng, w, d, 1.0)
        R = _rotz(yaw)
        mat = int(rng.choice(mf))
        th = rng.uniform(0.015, 0.03)
        parts = []
        for sx in (-1, 1):
            p = np.r_[c, h / 2] + R @ np.array([sx * (w / 2 - th / 2), 0, 0])
            parts.append(self.box(p, [th / 2, d / 2, h / 2], yaw, mat, 'shelf side'))
        nb = int(rng.integers(3, 6))
        zs = np.linspace(th / 2 + 0.05, h - th / 2, nb)
        for z in zs:
            parts.append(self.box([c[0], c[1], z], [w / 2 - th, d / 2, th / 2], yaw, mat, 'shelf board'))
        for z0, z1 in zip(zs[:-1], zs[1:]):     # books
            x = -w / 2 + th + 0.01
            while x < w / 2 - th - 0.05 and rng.random() < 0.93:
                bw = rng.uniform(0.02, 0.06)
                bh = min(rng.uniform(0.15, 0.3), z1 - z0 - th - 0.01)
                bd = rng.uniform(0.6, 0.95) * d
                if bh > 0.05 and x + bw < w / 2 - th:
                    p = np.r_[c, 0] + R @ np.array([x + bw / 2, (d - bd) / 2, 0])
                    parts.append(self.box([p[0], p[1], z0 + th / 2 + bh / 2], [bw / 2, bd / 2, bh / 2], yaw,
                                          int(rng.choice(mf + scene.mat_pictures)), 'book'))
                x += bw + rng.uniform(0.0, 0.08)
        return parts

    def crate(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        w, d, h = rng.uniform(0.2, 0.7), rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.7)
        c, yaw = scene._floor_spot(rng, w, d, 0.3)
        parts = [self.box([c[0], c[1], h / 2], [w / 2, d / 2, h / 2], yaw, int(rng.choice(mf)), 'crate')]
        if rng.random() < 0.4:   # a second one stacked on top
            w2, d2, h2 = w * rng.uniform(0.5, 0.9), d * rng.uniform(0.5, 0.9), rng.uniform(0.1, 0.4)
            parts.append(self.box([c[0], c[1], h + h2 / 2], [w2 / 2, d2 / 2, h2 / 2], yaw + rng.uniform(-0.6, 0.6),
                                  int(rng.choice(mf)), 'crate'))
        return parts

    def rug(self):
        scene, rng, L = self.scene, self.rng, self.scene.room
        w, d, h = rng.uniform(0.8, 2.5), rng.uniform(0.6, 1.8), rng.uniform(0.004, 0.012)
        c = np.array([rng.uniform(w / 2, L[0] - w / 2), rng.uniform(d / 2, L[1] - d / 2)])
        return [self.box([c[0], c[1], h / 2], [w / 2, d / 2, h / 2], float(rng.choice([0.0, math.pi / 2])) +
                         rng.normal(0, 0.1), scene.mat_rug, 'rug', casts_shadow=False)]

    def pillar(self):
        scene, rng, L, mf = self.scene, self.rng, self.scene.room, self.scene.mat_furniture
        r = rng.uniform(0.1, 0.35)
        c = scene._free_spot(rng, r)
        return [Primitive('cyl', [c[0], c[1], L[2] / 2], [r, r, L[2] / 2],
                          0.0, int(rng.choice(mf + [scene.mat_wall])), self.uvo(), label='pillar')]

    def bin_(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        r, hh = rng.uniform(0.12, 0.3), rng.uniform(0.3, 0.8)
        c = scene._free_spot(rng, r)
        return [Primitive('cyl', [c[0], c[1], hh / 2], [r, r, hh / 2],
                          0.0, int(rng.choice(mf)), self.uvo(), label='bin')]

    def ball(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        r = rng.uniform(0.1, 0.35)
        c = scene._free_spot(rng, r)
        return [Primitive('sph', [c[0], c[1], r], [r, r, r], 0.0,
                          int(rng.choice(mf + scene.mat_pictures + [scene.mat_metal])), self.uvo(), label='ball')]

    def pole(self):
        scene, rng, L = self.scene, self.rng, self.scene.room
        r, hh = rng.uniform(0.01, 0.025), rng.uniform(1.2, min(2.0, L[2] - 0.2))
        c = scene._free_spot(rng, 0.1)
        return [Primitive('cyl', [c[0], c[1], hh / 2],
                          [r, r, hh / 2], 0.0, scene.mat_metal, self.uvo(), label='pole')]

    def floor_lamp(self):
        scene, rng, L = self.scene, self.rng, self.scene.room
        r, hh = rng.uniform(0.012, 0.02), rng.uniform(1.2, min(1.8, L[2] - 0.5))
        gr = rng.uniform(0.1, 0.18)
        x, y = scene._free_spot(rng, 0.3)
        return [Primitive('cyl', [x, y, hh / 2], [r, r, hh / 2], 0.0, scene.mat_metal, self.uvo(), label='lamp pole'),
                Primitive('sph', [x, y, hh + gr], [gr, gr, gr], 0.0, scene.mat_lamp, self.uvo(), casts_shadow=False,
                          label='lamp globe')]

    def wall_patch(self, mat, label, size_w, size_h, z_range, thick):
        """A thin box on a random wall (pictures, mirrors, windows)."""
        rng, L = self.rng, self.scene.room
        w, hh = rng.uniform(*size_w), rng.uniform(*size_h)
        wall = int(rng.integers(0, 4))
        z = rng.uniform(max(z_range[0], hh / 2 + 0.05), max(min(z_range[1], L[2] - hh / 2 - 0.05), z_range[0]))
        t = thick / 2
        if wall == 0:
            c, yaw = [t, rng.uniform(w / 2, L[1] - w / 2), z], math.pi / 2
        elif wall == 1:
            c, yaw = [L[0] - t, rng.uniform(w / 2, L[1] - w / 2), z], -math.pi / 2
        elif wall == 2:
            c, yaw = [rng.uniform(w / 2, L[0] - w / 2), t, z], math.pi
        else:
            c, yaw = [rng.uniform(w / 2, L[0] - w / 2), L[1] - t, z], 0.0
        return [self.box(c, [w / 2, t, hh / 2], yaw, mat, label, casts_shadow=False)]

    def moving_ball(self):
        scene, rng, mf = self.scene, self.rng, self.scene.mat_furniture
        r = rng.uniform(0.1, 0.25)
        amp = np.array([rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6), 0.0])
        xy = scene._free_spot(rng, r + float(np.linalg.norm(amp)))
        c = [xy[0], xy[1], r]
        return [Primitive('sph', c, [r, r, r], 0.0, int(rng.choice(mf + scene.mat_pictures)), self.uvo(),
                          casts_shadow=False, label='moving ball',
                          motion=(amp, rng.uniform(0.5, 1.5), rng.uniform(0, 2 * math.pi, 3)))]

    def picture(self):
        rng = self.rng
        return self.wall_patch(int(rng.choice(self.scene.mat_pictures)), 'picture', (0.3, 1.2), (0.3, 0.9),
                               (1.0, 2.0), rng.uniform(0.01, 0.04))

    def mirror(self):
        return self.wall_patch(self.scene.mat_mirror, 'mirror', (0.5, 1.2), (0.6, 1.5), (1.0, 1.6), 0.01)

    def window(self):
        return self.wall_patch(self.scene.mat_glass, 'window', (0.6, 1.6), (0.6, 1.4), (1.2, 1.8), 0.01)


class SyntheticScene:
    """A random furnished room, lights, materials, camera intrinsics and trajectory for one seed.

    ``render_frame(i)`` renders frame i (deterministic, independent of the order frames are rendered in)
    and returns a dict with ``image`` (uint8 HxWx3 RGB), ``depth`` (float32 HxW z-depth in metres),
    ``pose`` (4x4 T_world_cam), ``stamp`` (s), ``specular_mask`` (bool HxW: mirror/glass pixels and
    visible highlights), and ``dynamic_mask`` when the scene is not static.
    """

    def __init__(self, seed: int, width: int = 320, height: int = 240, config: Optional[SceneConfig] = None,
                 **options):
        self.config = (config or SceneConfig()).replace(**options)
        self.seed = int(seed)
        self.width, self.height = int(width), int(height)
        cfg = self.config
        rng = np.random.default_rng([self.seed, 0x5EED])
        self._build_camera(rng)
        self._build_room_and_path(rng)
        self._build_materials(rng)
        self._build_furniture(rng)
        self._build_lights(rng)
        self._build_sensor(rng)
        self.rays = _PixelRays(self.K, self.width, self.height)
        if cfg.shadows:
            self._build_shadow_maps()
        self.exposure_gain = self._auto_exposure()

    # ----------------------------------------------------------------------------------------------
    # construction
    # ----------------------------------------------------------------------------------------------
    def _build_camera(self, rng):
        cfg = self.config
        fov = math.radians(rng.uniform(*cfg.fov_deg))
        f_norm = 0.5 / math.tan(fov / 2)                   # focal length in units of the image width
        j = cfg.principal_point_jitter
        cx_norm, cy_norm = 0.5 + rng.uniform(-j, j), 0.5 + rng.uniform(-j, j)
        self.intrinsics_normalised = (f_norm, cx_norm, cy_norm)
        self.K = self.intrinsics_for(self.width, self.height)
        # Largest angle between the optical axis and a pixel ray (image corners, in units of the image
        # width; the aspect ratio is taken as at least 3:4 so that every landscape size of a seed — 320x240,
        # 96x72, 640x360 ... — gets the same clearance and hence the same furniture).
        aspect = max(self.height / self.width, 0.75)
        x = np.array([-cx_norm, 1.0 - cx_norm]) / f_norm
        y = np.array([-cy_norm, 1.0 - cy_norm]) * aspect / f_norm
        self.max_ray_angle = float(np.max(np.arctan(np.hypot(x[:, None], y[None, :]))))
        # any surface at euclidean distance >= clearance is at z-depth >= min_depth
        self.clearance = round(cfg.min_depth / math.cos(self.max_ray_angle) + 0.03, 9)

    def intrinsics_for(self, width: int, height: int) -> np.ndarray:
        """K of this scene's camera at another resolution: the same camera scaled by the project
        convention (fx' = fx*s, cx' = (cx + 0.5)*s - 0.5), so K_for(W/2, H/2) == scale(K_for(W, H), 1/2)."""
        f_norm, cx_norm, cy_norm = self.intrinsics_normalised
        f = f_norm * width
        return np.array([[f, 0.0, cx_norm * width - 0.5], [0.0, f, cy_norm * height - 0.5], [0.0, 0.0, 1.0]])

    def _build_room_and_path(self, rng):
        cfg = self.config
        for _ in range(200):
            L = np.array([rng.uniform(*cfg.room_size_x), rng.uniform(*cfg.room_size_y),
                          rng.uniform(*cfg.room_height)])
            margin = self.clearance + cfg.shake_m + 0.02
            h_lo = max(cfg.camera_height[0], margin)
            h_hi = min(cfg.camera_height[1], L[2] - margin)
            if h_hi <= h_lo:
                continue
            center = L[:2] / 2 + rng.uniform(-0.1, 0.1, size=2) * L[:2]
            max_ax = min(center[0], L[0] - center[0]) - margin
            max_ay = min(center[1], L[1] - center[1]) - margin
            if max_ax < 0.3 or max_ay < 0.3:
                continue
            for _ in range(20):   # smooth enough: the walking direction turns at most max_turn_rate_deg/s
                traj = HandheldTrajectory.random(
                    rng, center=center, max_ax=max_ax, max_ay=max_ay, height_range=(h_lo, h_hi),
                    speed_range=cfg.speed, pitch_range_deg=cfg.pitch_deg, yaw_offset_deg=cfg.yaw_offset_deg,
                    yaw_sway_deg=cfg.yaw_sway_deg, roll_deg=cfg.roll_deg, shake_m=cfg.shake_m,
                    tremor_deg=cfg.tremor_deg)
                if traj.max_turn_rate() <= math.radians(cfg.max_turn_rate_deg):
                    break
            else:
                continue
            loop = traj.dense_loop(0.01)
            J = traj.shake_bound + 0.01
            lo_ok = np.all(loop.min(0) - J >= self.clearance)
            hi_ok = np.all(L - loop.max(0) - J >= self.clearance)
            # farthest visible point: a room corner
            corners = np.array([[i, j, k] for i in (0, L[0]) for j in (0, L[1]) for k in (0, L[2])])
            far = np.max(np.linalg.norm(loop[:, None, :] - corners[None], axis=-1)) + J
            if lo_ok and hi_ok and far <= cfg.max_depth:
                self.room = L
                self.trajectory = traj
                self.loop_points = traj.dense_loop(0.02)   # for clearance checks (margins cover the gaps)
                self.path_margin = J
                return
        raise RuntimeError(f'seed {self.seed}: could not fit a room and a camera path (check the config ranges)')

    def _build_materials(self, rng):
        cfg = self.config
        S = cfg.texture_size
        gp = cfg.glossy_prob
        mats: List[Material] = []

        def add(m):
            mats.append(m)
            return len(mats) - 1

        # walls: weakly textured paint most of the time, sometimes wallpaper / bricks
        if rng.random() < cfg.plain_wall_prob:
            self.mat_wall = add(_make_material(rng, 'wall', 'plain', S, (1.5, 4.0), 0.1, (0.02, 0.06)))
        else:
            pattern = str(rng.choice(['stripes', 'fbm', 'natural', 'bricks', 'tiles']))
            self.mat_wall = add(_make_material(rng, 'wall', pattern, S, (0.6, 2.5), 0.1, (0.02, 0.08)))
        self.mat_wall2 = self.mat_wall
        if rng.random() < 0.35:   # an accent wall
            pattern = str(rng.choice(['plain', 'stripes', 'bricks', 'fbm', 'natural']))
            self.mat_wall2 = add(_make_material(rng, 'accent wall', pattern, S, (0.8, 3.0), 0.1))
        floor_pattern = str(rng.choice(['wood', 'tiles', 'carpet', 'checker', 'fbm', 'wood']))
        self.mat_floor = add(_make_material(rng, 'floor', floor_pattern, S, (0.6, 2.4), 0.5, (0.05, 0.3)))
        self.mat_ceiling = add(_make_material(
            rng, 'ceiling', 'plain', S, (2.0, 5.0), 0.0,
            color=_random_color(rng, sat=(0.0, 0.08), val=(0.8, 0.95)), strength=rng.uniform(0.01, 0.03)))
        furniture_patterns = ['wood', 'wood', 'plain', 'plain', 'fbm', 'checker', 'stripes', 'natural',
                              'carpet', 'tiles']
        self.mat_furniture = [add(_make_material(rng, f'furniture{k}', str(rng.choice(furniture_patterns)),
                                                 S, (0.3, 1.6), gp)) for k in range(int(rng.integers(4, 8)))]
        self.mat_pictures = [add(_make_material(rng, f'picture{k}', 'natural', S, (0.5, 1.4), 0.3, (0.05, 0.2)))
                             for k in range(3)]
        self.mat_rug = add(_make_material(rng, 'rug', str(rng.choice(['natural', 'stripes', 'carpet', 'checker'])),
                                          S, (0.6, 2.0), 0.0))
        self.mat_skirting = add(_make_material(rng, 'skirting', 'plain', 64, (1.0, 2.0), 0.5, (0.05, 0.2),
                                               color=_random_color(rng, sat=(0.0, 0.3), val=(0.2, 0.95))))
        self.mat_metal = add(_make_material(
            rng, 'metal', 'plain', S, (1.0, 2.0), 1.0, (0.3, 0.6),
            color=_random_color(rng, sat=(0.0, 0.1), val=(0.3, 0.8)), strength=0.02))
        mirror = _make_material(rng, 'mirror', 'plain', 64, (1.0, 2.0), 0.0, kind=KIND_MIRROR, env_mix=0.85,
                                color=np.array([0.2, 0.2, 0.2]), strength=0.01)
        self.mat_mirror = add(mirror)
        glass = _make_material(rng, 'glass', 'plain', 64, (1.0, 2.0), 1.0, (0.2, 0.4), kind=KIND_GLASS,
                               env_mix=0.8, color=_random_color(rng, sat=(0.0, 0.2), val=(0.3, 0.6)),
                               strength=0.01)
        self.mat_glass = add(glass)
        lamp = _make_material(rng, 'lamp', 'plain', 64, (1.0, 2.0), 0.0, kind=KIND_EMISSIVE,
                              color=np.array([1.0, 1.0, 1.0]), strength=0.0)
        self.mat_lamp = add(lamp)
        self.materials = mats
        self.env_map = _environment_map(rng)

    # -- furniture ---------------------------------------------------------------------------------
    def _fits(self, prims: List[Primitive], allow_overlap_with: Tuple[Primitive, ...] = ()) -> bool:
        """All parts inside the room, clear of the camera path, and not overlapping other furniture."""
        L = self.room
        need = self.clearance + self.path_margin + 0.01
        for p in prims:
            lo, hi = p.aabb()
            if np.any(lo < -1e-6) or np.any(hi > L + 1e-6):
                return False
            if np.min(p.sdf(self.loop_points)) < need:
                return False
        others = [q for q in self.prims if not any(q is a for a in allow_overlap_with)]
        if not others:
            return True
        qlo = np.array([q._aabb[0] for q in others])
        qhi = np.array([q._aabb[1] for q in others])
        for p in prims:
            lo, hi = p.aabb(inflate=-0.005)
            if np.any(np.all(lo < qhi, axis=1) & np.all(qlo < hi, axis=1)):
                return False
        return True

    def _floor_spot(self, rng, w: float, d: float, against_wall_prob: float):
        """Centre (x, y) and yaw for a w x d footprint, against a wall or free-standing."""
        L = self.room
        if rng.random() < against_wall_prob:
            wall = int(rng.integers(0, 4))
            gap = rng.uniform(0.0, 0.05)
            if wall == 0:   # x = 0 wall, object front faces +x
                return np.array([d / 2 + gap, rng.uniform(w / 2, L[1] - w / 2)]), math.pi / 2 + rng.normal(0, 0.02)
            if wall == 1:
                return (np.array([L[0] - d / 2 - gap, rng.uniform(w / 2, L[1] - w / 2)]),
                        -math.pi / 2 + rng.normal(0, 0.02))
            if wall == 2:
                return np.array([rng.uniform(w / 2, L[0] - w / 2), d / 2 + gap]), math.pi + rng.normal(0, 0.02)
            return np.array([rng.uniform(w / 2, L[0] - w / 2), L[1] - d / 2 - gap]), rng.normal(0, 0.02)
        return self._free_spot(rng, 0.5 * math.hypot(w, d)), rng.uniform(0, 2 * math.pi)

    def _free_spot(self, rng, extent: float) -> np.ndarray:
        """A floor position (x, y) for a free-standing object of horizontal radius ``extent``: with
        probability ``near_path_prob`` just beside the camera path (so near objects, occlusions and
        disocclusions are common), else anywhere in the room."""
        L = self.room
        if rng.random() < self.config.near_path_prob:
            loop = self.loop_points
            i = int(rng.integers(0, len(loop)))
            tangent = loop[(i + 1) % len(loop), :2] - loop[i - 1, :2]
            normal = np.array([-tangent[1], tangent[0]]) / max(np.linalg.norm(tangent), 1e-9)
            if rng.random() < 0.5:
                normal = -normal
            dist = self.clearance + self.path_margin + extent + rng.uniform(0.03, 0.8)
            return loop[i, :2] + normal * dist
        return np.array([rng.uniform(extent, L[0] - extent), rng.uniform(extent, L[1] - extent)])

    def _try_place(self, rng, make, tries: int = 25) -> bool:
        for _ in range(tries):
            group = make()
            if group and self._fits(group):
                self.prims.extend(group)
                return True
        return False

    def _build_furniture(self, rng):
        cfg = self.config
        self.prims: List[Primitive] = []
        make = _FurnitureMaker(self, rng)
        # large things first, small things later
        for count, piece in ((cfg.num_shelves, make.shelf), (cfg.num_sofas, make.sofa),
                             (cfg.num_cabinets, make.cabinet), (cfg.num_tables, make.table),
                             (cfg.num_pillars, make.pillar), (cfg.num_crates, make.crate), (cfg.num_rugs, make.rug),
                             (cfg.num_bins, make.bin_), (cfg.num_balls, make.ball), (cfg.num_poles, make.pole),
                             (cfg.num_floor_lamps, make.floor_lamp), (cfg.num_pictures, make.picture),
                             (cfg.num_mirrors, make.mirror), (cfg.num_windows, make.window)):
            for _ in range(make.count(count)):
                self._try_place(rng, piece)
        if rng.random() < cfg.skirting_prob:
            self._add_skirting(make)
        if not cfg.static:
            for _ in range(make.count(cfg.num_moving)):
                self._try_place(rng, make.moving_ball, tries=60)
        self.dynamic_ids = [i for i, p in enumerate(self.prims) if p.motion is not None]

    def _add_skirting(self, make: _FurnitureMaker) -> None:
        """Skirting boards along the four walls (each kept where it fits)."""
        rng, L = make.rng, self.room
        hh, th = rng.uniform(0.05, 0.12), rng.uniform(0.008, 0.02)
        mat = self.mat_skirting
        for c, half in (([th / 2, L[1] / 2, hh / 2], [th / 2, L[1] / 2 - th, hh / 2]),
                        ([L[0] - th / 2, L[1] / 2, hh / 2], [th / 2, L[1] / 2 - th, hh / 2]),
                        ([L[0] / 2, th / 2, hh / 2], [L[0] / 2, th / 2, hh / 2]),
                        ([L[0] / 2, L[1] - th / 2, hh / 2], [L[0] / 2, th / 2, hh / 2])):
            part = make.box(c, half, 0.0, mat, 'skirting', casts_shadow=False)
            if self._fits([part], allow_overlap_with=tuple(self.prims)):
                self.prims.append(part)

    def _build_lights(self, rng):
        """Ceiling lights (each with a visible fixture when it fits: a glowing panel on the ceiling or a
        pendant globe on a cord) and the lights inside floor-lamp globes."""
        cfg = self.config
        L = self.room
        self.lights: List[_Light] = []
        warm = np.array([1.0, 0.85, 0.65])
        cool = np.array([0.85, 0.92, 1.0])
        self.materials[self.mat_lamp].emission = (3.0, 2.8, 2.5)
        for _ in range(int(rng.integers(cfg.num_lights[0], cfg.num_lights[1] + 1))):
            pendant = rng.random() < 0.4
            drop = rng.uniform(0.45, 0.9) if pendant else 0.06
            for _try in range(50):
                p = np.array([rng.uniform(0.4, L[0] - 0.4), rng.uniform(0.4, L[1] - 0.4), L[2] - drop])
                if all(q.sdf(p[None])[0] > 0.15 for q in self.prims):
                    break
            if pendant:
                gr = rng.uniform(0.07, 0.14)
                cord = (L[2] - p[2] - gr) / 2
                fixture = [Primitive('sph', p, [gr, gr, gr], 0.0, self.mat_lamp, casts_shadow=False, label='pendant'),
                           Primitive('cyl', [p[0], p[1], L[2] - cord], [0.006, 0.006, cord], 0.0, self.mat_metal,
                                     casts_shadow=False, label='pendant cord')]
            else:
                sz = rng.uniform(0.15, 0.35)
                fixture = [Primitive('box', [p[0], p[1], L[2] - 0.01], [sz, sz, 0.01], float(rng.uniform(0, math.pi)),
                                     self.mat_lamp, casts_shadow=False, label='ceiling panel')]
            if self._fits(fixture):
                self.prims.extend(fixture)
            w = rng.random()
            col = (w * warm + (1 - w) * cool) * rng.uniform(*cfg.light_intensity)
            self.lights.append(_Light(p, col, falloff=rng.uniform(2.0, 4.0)))
        for q in self.prims:
            if q.label == 'lamp globe':
                col = warm * rng.uniform(0.5, 0.9) * np.mean(cfg.light_intensity)
                self.lights.append(_Light(q.center.copy(), col, falloff=rng.uniform(1.5, 2.5)))
        self.ambient = rng.uniform(*cfg.ambient) * (0.9 + 0.2 * rng.random(3))

    def _build_sensor(self, rng):
        cfg = self.config
        self.target_brightness = rng.uniform(*cfg.exposure)
        self.read_noise = rng.uniform(*cfg.read_noise)
        self.shot_noise = rng.uniform(*cfg.shot_noise)
        self.vignetting = rng.uniform(*cfg.vignetting)
        self.optical_blur = rng.uniform(*cfg.optical_blur)
        self.exposure_time = rng.uniform(*cfg.exposure_time)
        self.readout_time = rng.uniform(*cfg.readout_time)
        self.exposure_drift_terms = [(cfg.exposure_drift * rng.uniform(0.5, 1.0), rng.uniform(0.1, 0.5),
                                      rng.uniform(0, 2 * math.pi))]

    def _build_shadow_maps(self):
        """Variance shadow maps: for each shadowing light a cube map (six 90-degree faces, each with a
        one-texel margin so bilinear look-ups never cross faces) of the first two moments of the distance
        to the nearest static surface, blurred so that shadows get soft, alias-free penumbrae."""
        S = self.config.shadow_map_size
        f = S / 2.0
        P = S + 2
        Kf = np.array([[f, 0, P / 2 - 0.5], [0, f, P / 2 - 0.5], [0, 0, 1]])
        rays = _PixelRays(Kf, P, P)
        casters = [i for i, p in enumerate(self.prims) if p.casts_shadow and p.motion is None]
        # R_world_face of face 2a + (s < 0): columns e_(a+1), s e_(a+2), s e_a (see _shadow)
        eye = np.eye(3)
        self._cube_rot = np.stack([np.stack([eye[(a + 1) % 3], s * eye[(a + 2) % 3], s * eye[a]], axis=1)
                                   for a in range(3) for s in (1.0, -1.0)])
        self._cube_K = Kf
        strength = [float(np.sum(light.color)) for light in self.lights]
        shadowed = np.argsort(strength)[::-1][:max(0, int(self.config.max_shadowed_lights))]
        for li in shadowed:
            light = self.lights[li]
            faces = []
            for R in self._cube_rot:
                T = np.eye(4)
                T[:3, :3] = R
                T[:3, 3] = light.position
                t, _, _ = self._cast(rays, T, 0.0, 0, P, casters)
                d = (t * rays.norm).astype(np.float32)
                m = np.stack([d, d * d], axis=-1)
                faces.append(cv2.GaussianBlur(m, (5, 5), 1.0, borderType=cv2.BORDER_REPLICATE))
            light.shadow_atlas = np.ascontiguousarray(np.concatenate(faces, axis=1))   # (P, 6P, 2)

    def _auto_exposure(self) -> float:
        """Gain that brings the mean brightness of a few low-resolution views to the target."""
        w, h = 64, 48
        K = self.intrinsics_for(w, h)
        rays = _PixelRays(K, w, h)
        means = []
        for t in (0.0, 1.0, 2.0):
            lin, _, _, _ = self._render_linear(rays, self.trajectory.pose(t), t)
            means.append(float(np.mean(lin)))
        m = max(np.mean(means), 1e-4)
        target_linear = self.target_brightness ** self.config.gamma
        # mean of gamma-encoded values is above gamma of the mean; correct roughly
        return float(target_linear / m * 0.8)

    # ----------------------------------------------------------------------------------------------
    # rendering
    # ----------------------------------------------------------------------------------------------
    def stamp(self, i: int) -> float:
        return i / self.config.fps

    def pose(self, i: int) -> np.ndarray:
        """T_world_cam of frame i (the pose at the middle of its exposure / readout)."""
        return self.trajectory.pose(self.stamp(i))

    def _cast(self, rays: _PixelRays, T_world_cam: np.ndarray, time: float, r0: int, r1: int,
              prim_ids: Optional[List[int]] = None):
        """Z-buffer ray casting for rows [r0, r1): returns z-depth t (h, W) float32, id map (h, W) int16
        (0-5 room faces, 6+k primitive k) and the world ray directions (3 float32 arrays).

        The ray of pixel (u, v) is o + t * R (x, y, 1) with (x, y) = K^-1 (u, v), so the ray parameter t
        of a hit is its z-depth. Each primitive is tested only inside its projected bounding box."""
        R = np.asarray(T_world_cam[:3, :3], np.float64)
        o = np.asarray(T_world_cam[:3, 3], np.float64)
        R32 = R.astype(np.float32)
        dx, dy = rays.dx[r0:r1], rays.dy[r0:r1]
        W = rays.width
        dw = [R32[i, 0] * dx + R32[i, 1] * dy + R32[i, 2] for i in range(3)]
        L = self.room
        t = None
        ids = None
        with np.errstate(divide='ignore', invalid='ignore'):
            for i in range(3):
                inv = np.float32(1.0) / dw[i]
                ti = np.maximum(np.float32(-o[i]) * inv, np.float32(L[i] - o[i]) * inv)
                face = (dw[i] > 0).astype(np.int16)
                face += np.int16(2 * i)
                if t is None:
                    t, ids = ti, face
                else:
                    closer = ti < t
                    np.copyto(t, ti, where=closer)
                    np.copyto(ids, face, where=closer)
        fx, fy, cx, cy = rays.K[0, 0], rays.K[1, 1], rays.K[0, 2], rays.K[1, 2]
        ids_iter = range(len(self.prims)) if prim_ids is None else prim_ids
        for k in ids_iter:
            p = self.prims[k]
            c_w = p.center_at(time)
            corners = (p.corners(time) - o) @ R
            if np.all(corners[:, 2] > 1e-3):
                u = fx * corners[:, 0] / corners[:, 2] + cx
                v = fy * corners[:, 1] / corners[:, 2] + cy
                u0, u1 = max(0, int(math.floor(u.min()))), min(W, int(math.ceil(u.max())) + 1)
                v0, v1 = max(r0, int(math.floor(v.min()))), min(r1, int(math.ceil(v.max())) + 1)
            elif np.all(corners[:, 2] <= 1e-3):
                continue
            else:
                u0, u1, v0, v1 = 0, W, r0, r1
            if u0 >= u1 or v0 >= v1:
                continue
            M = (p.R.T @ R).astype(np.float32)
            ol = [float(x) for x in p.R.T @ (o - c_w)]
            sx, sy = dx[v0 - r0:v1 - r0, u0:u1], dy[v0 - r0:v1 - r0, u0:u1]
            dl = [M[i, 0] * sx + M[i, 1] * sy + M[i, 2] for i in range(3)]
            tp = _INTERSECT[p.kind](ol, dl[0], dl[1], dl[2], p.half_f)
            tsub = t[v0 - r0:v1 - r0, u0:u1]
            closer = tp < tsub
            if closer.any():
                np.copyto(tsub, tp, where=closer)
                ids[v0 - r0:v1 - r0, u0:u1][closer] = 6 + k
        return t, ids, dw

    def _render_linear(self, rays: _PixelRays, T_world_cam: np.ndarray, time: float, r0: int = 0,
                       r1: Optional[int] = None):
        """Shade rows [r0, r1): returns linear colour (h, W, 3), its view-dependent part (h, W, 3)
        (highlights, mirror/glass reflections), z-depth (h, W) float32 and the id map (h, W)."""
        r1 = rays.height if r1 is None else r1
        t, ids, dw = self._cast(rays, T_world_cam, time, r0, r1)
        h, W = t.shape
        hits = _RayHits(o=[float(x) for x in T_world_cam[:3, 3]], R=np.asarray(T_world_cam[:3, :3], np.float64),
                        time=time, tf=t.reshape(-1), idf=ids.reshape(-1), dwf=[d.reshape(-1) for d in dw],
                        dxf=rays.dx[r0:r1].reshape(-1), dyf=rays.dy[r0:r1].reshape(-1),
                        inv_dnorm=rays.inv_norm[r0:r1].reshape(-1), inv_fx=1.0 / float(rays.K[0, 0]))
        surf = self._surfaces(hits)
        color, view_dep = self._light(hits, surf)
        self._reflect_environment(hits, surf, color, view_dep)
        return (color.T.reshape(h, W, 3), view_dep.T.reshape(h, W, 3), t, ids)

    def _surfaces(self, hits: '_RayHits') -> '_Surfaces':
        """Normal, albedo and material of every hit, one surface (room face or primitive) at a time."""
        n = hits.n
        surf = _Surfaces(normal=np.empty((3, n), np.float32), albedo=np.empty((3, n), np.float32),
                         ks=np.zeros(n, np.float32), shin=np.ones(n, np.float32), kind=np.zeros(n, np.int8))
        dwf = hits.dwf
        order = np.argsort(hits.idf, kind='stable')
        counts = np.bincount(hits.idf, minlength=_N_ROOM_FACES + len(self.prims))
        starts = np.concatenate([[0], np.cumsum(counts)])
        for gid in np.flatnonzero(counts):
            idx = order[starts[gid]:starts[gid + 1]]
            tt = hits.tf[idx]
            if gid < _N_ROOM_FACES:
                mat, nw, uu, vv = self._room_face_surface(gid, idx, tt, hits)
                uvo = (0.0, 0.0)
            else:
                p = self.prims[gid - _N_ROOM_FACES]
                mat = self.materials[p.material]
                nw, uu, vv = self._primitive_surface(p, idx, tt, hits)
                uvo = p.uv_offset
            surf.normal[:, idx] = nw
            surf.kind[idx] = mat.kind
            surf.ks[idx] = mat.ks
            surf.shin[idx] = mat.shininess
            if mat.kind == KIND_EMISSIVE:
                surf.albedo[:, idx] = np.asarray(mat.emission, np.float32)[:, None]
                continue
            cosv = np.abs(nw[0] * dwf[0][idx] + nw[1] * dwf[1][idx] + nw[2] * dwf[2][idx]) * hits.inv_dnorm[idx]
            foot = tt * hits.inv_fx / np.maximum(cosv, 0.25)
            surf.albedo[:, idx] = _sample_material(mat, uu + uvo[0], vv + uvo[1], foot).T
        return surf

    def _room_face_surface(self, gid: int, idx: np.ndarray, tt: np.ndarray, hits: '_RayHits'):
        """(material, world normal (3, m), surface coordinates u, v) of the hits ``idx`` on room face ``gid``."""
        room_mats = [self.mat_wall, self.mat_wall, self.mat_wall2, self.mat_wall, self.mat_floor, self.mat_ceiling]
        o, dwf = hits.o, hits.dwf
        axis, side = gid // 2, gid % 2
        nw = np.zeros((3, idx.size), np.float32)
        nw[axis] = -1.0 if side else 1.0
        P = [o[i] + tt * dwf[i][idx] for i in range(3)]
        if axis == 0:
            uu, vv = P[1] + 0.37 * side, P[2]
        elif axis == 1:
            uu, vv = P[0] + 0.61 * side, P[2]
        else:
            uu, vv = P[0], P[1]
        return self.materials[room_mats[gid]], nw, uu, vv

    @staticmethod
    def _primitive_surface(p: Primitive, idx: np.ndarray, tt: np.ndarray, hits: '_RayHits'):
        """(world normal (3, m), surface coordinates u, v) of the hits ``idx`` on primitive ``p``."""
        M = (p.R.T @ hits.R).astype(np.float32)
        ol = [float(x) for x in p.R.T @ (np.asarray(hits.o) - p.center_at(hits.time))]
        sx, sy = hits.dxf[idx], hits.dyf[idx]
        pl = [ol[i] + tt * (M[i, 0] * sx + M[i, 1] * sy + M[i, 2]) for i in range(3)]
        nl = np.zeros((3, idx.size), np.float32)
        if p.kind == 'box':
            uu, vv = _box_normal_uv(pl, nl, p.half_f)
        elif p.kind == 'cyl':
            uu, vv = _cylinder_normal_uv(pl, nl, p.half_f)
        else:
            uu, vv = _sphere_normal_uv(pl, nl, p.half_f)
        if p.yaw == 0.0:
            nw = nl
        else:
            Rp = p.R.astype(np.float32)
            nw = np.stack([Rp[0, 0] * nl[0] + Rp[0, 1] * nl[1], Rp[1, 0] * nl[0] + Rp[1, 1] * nl[1], nl[2]])
        return nw, uu, vv

    def _light(self, hits: '_RayHits', surf: '_Surfaces') -> Tuple[np.ndarray, np.ndarray]:
        """Lighting: ambient + point lights (Lambert + Blinn-Phong), soft shadows from cube maps; returns the
        colour (3, n) and its view-dependent part (3, n)."""
        o, tf, dwf, inv_dnorm = hits.o, hits.tf, hits.dwf, hits.inv_dnorm
        n, ks, shin = hits.n, surf.ks, surf.shin
        Px = o[0] + tf * dwf[0]
        Py = o[1] + tf * dwf[1]
        Pz = o[2] + tf * dwf[2]
        vx, vy, vz = -dwf[0] * inv_dnorm, -dwf[1] * inv_dnorm, -dwf[2] * inv_dnorm
        Nx, Ny, Nz = surf.normal
        amb_w = np.float32(0.8) + np.float32(0.2) * Nz
        light_acc = [amb_w * np.float32(self.ambient[c]) for c in range(3)]
        spec = None
        glossy = bool(np.any(ks > 0))
        if glossy:
            spec = [np.zeros(n, np.float32) for _ in range(3)]
            spec_norm = ks * (shin + 8) * np.float32(1 / 8)
        for light in self.lights:
            lp = [float(x) for x in light.position]
            lx, ly, lz = lp[0] - Px, lp[1] - Py, lp[2] - Pz
            d2 = lx * lx + ly * ly + lz * lz
            dist = np.sqrt(d2)
            inv = 1.0 / np.maximum(dist, 1e-6)
            lx *= inv
            ly *= inv
            lz *= inv
            ndl = Nx * lx + Ny * ly + Nz * lz
            att = 1.0 / (1.0 + d2 * np.float32(1.0 / (light.falloff * light.falloff)))
            w = np.maximum(ndl, 0) * att
            if light.shadow_atlas is not None:
                w *= self._shadow(light, Px - lp[0], Py - lp[1], Pz - lp[2], dist, ndl)
            col = [float(c) for c in light.color]
            for c in range(3):
                light_acc[c] += w * col[c]
            if glossy:
                hx, hy, hz_ = lx + vx, ly + vy, lz + vz
                hn = 1.0 / np.maximum(np.sqrt(hx * hx + hy * hy + hz_ * hz_), 1e-6)
                ndh = np.maximum((Nx * hx + Ny * hy + Nz * hz_) * hn, 1e-20)
                sp = np.exp(np.log(ndh) * shin) * spec_norm * w
                for c in range(3):
                    spec[c] += sp * col[c]
        color = np.stack([surf.albedo[c] * light_acc[c] for c in range(3)])
        view_dep = np.zeros((3, n), np.float32) if spec is None else np.stack(spec)
        color += view_dep
        emissive = surf.kind == KIND_EMISSIVE
        if emissive.any():
            color[:, emissive] = surf.albedo[:, emissive]
        return color, view_dep

    def _reflect_environment(self, hits: '_RayHits', surf: '_Surfaces', color: np.ndarray,
                             view_dep: np.ndarray) -> None:
        """Mirrors and glass: mix the environment seen in the reflected (or through the refracted) direction into
        ``color`` and ``view_dep`` (in place)."""
        kind = surf.kind
        special = (kind == KIND_MIRROR) | (kind == KIND_GLASS)
        if not special.any():
            return
        sel = np.flatnonzero(special)
        d = np.stack([hits.dwf[i][sel] * hits.inv_dnorm[sel] for i in range(3)])
        nn = surf.normal[:, sel]
        refl = d - 2 * np.sum(d * nn, axis=0) * nn
        glass = kind[sel] == KIND_GLASS
        look = np.where(glass[None, :], d - 0.15 * nn, refl)
        look /= np.linalg.norm(look, axis=0, keepdims=True)
        env = self._environment(look).T
        mix = np.array([self.materials[self.mat_mirror].env_mix, self.materials[self.mat_glass].env_mix],
                       np.float32)[glass.astype(int)][None, :]
        env_part = mix * env * np.float32(self.ambient.mean() * 2 + 0.6)
        view_dep[:, sel] += env_part
        color[:, sel] = (1 - mix) * color[:, sel] + env_part

    def _environment(self, d: np.ndarray) -> np.ndarray:
        H, W = self.env_map.shape[:2]
        az = np.arctan2(d[1], d[0])
        el = np.arcsin(np.clip(d[2], -1, 1))
        x = (az / (2 * math.pi) + 0.5) * W - 0.5
        y = (0.5 - el / math.pi) * H - 0.5
        return _remap_points(self.env_map, x, y)

    def _shadow(self, light: _Light, vx, vy, vz, dist, ndl) -> np.ndarray:
        """Fraction of the light reaching surface points at offsets v = P - light: Chebyshev bound of the
        variance shadow map (bilinear look-up of the blurred distance moments), with light-bleeding
        reduction.

        Cube face (a, s) (dominant axis a, sign s) looks along s*e_a with image x along e_(a+1) and image
        y along s*e_(a+2), so its pixel coordinates are f * v_(a+1) / |v_a| + c and f * v_(a+2) / v_a + c.
        """
        S = self.config.shadow_map_size
        P = S + 2
        ax, ay, az = np.abs(vx), np.abs(vy), np.abs(vz)
        use_y = ay > ax
        use_z = az > np.maximum(ax, ay)
        use_y &= ~use_z
        dom = vx.copy()
        np.copyto(dom, vy, where=use_y)
        np.copyto(dom, vz, where=use_z)
        p = vy.copy()
        np.copyto(p, vz, where=use_y)
        np.copyto(p, vx, where=use_z)
        q = vz.copy()
        np.copyto(q, vx, where=use_y)
        np.copyto(q, vy, where=use_z)
        face = (dom < 0).view(np.int8) + np.int8(2) * use_y.view(np.int8) + np.int8(4) * use_z.view(np.int8)
        f = np.float32(self._cube_K[0, 0])
        c0 = np.float32(self._cube_K[0, 2])
        inv = f / dom
        u = p * np.abs(inv) + c0
        v = q * inv + c0
        np.clip(u, 0.5, P - 1.5, out=u)
        np.clip(v, 0.5, P - 1.5, out=v)
        u += face.astype(np.float32) * np.float32(P)
        mom = _remap_points(light.shadow_atlas, u, v)
        mu, m2 = mom[:, 0], mom[:, 1]
        d = dist - (0.01 + dist * np.float32(2.0 / S) * (1.0 + 1.0 / np.maximum(np.abs(ndl), 0.2)))
        var = np.maximum(m2 - mu * mu, np.float32(2e-4) * (1.0 + mu * mu))
        diff = np.maximum(d - mu, 0)
        pmax = var / (var + diff * diff)
        lit = np.clip((pmax - 0.35) * np.float32(1 / 0.65), 0, 1)
        return lit

    def _exposure_at(self, time: float) -> float:
        g = 1.0
        for a, w, p in self.exposure_drift_terms:
            g *= 1.0 + a * math.sin(w * time + p)
        return self.exposure_gain * g

    def render_frame(self, i: int) -> Dict[str, np.ndarray]:
        """Render frame i; see the class docstring for the returned keys."""
        cfg = self.config
        stamp = self.stamp(i)
        rays = self.rays
        H = self.height
        T_mid = self.trajectory.pose(stamp)
        if cfg.motion_blur and cfg.blur_samples > 1:
            ns = int(cfg.blur_samples)
            offsets = (np.arange(ns) + 0.5) / ns - 0.5
            offsets *= self.exposure_time
        else:
            offsets = np.zeros(1)
        mid_lin = None
        acc = np.zeros((H, self.width, 3), np.float32)
        for off in offsets:
            t_sub = stamp + off
            if cfg.rolling_shutter:
                nb = max(1, min(int(cfg.rolling_shutter_bands), H))
                edges = np.linspace(0, H, nb + 1).round().astype(int)
                for b in range(nb):
                    r0, r1 = edges[b], edges[b + 1]
                    if r1 <= r0:
                        continue
                    row_mid = (r0 + r1 - 1) / 2
                    t_row = t_sub + (row_mid / max(H - 1, 1) - 0.5) * self.readout_time
                    lin, _, _, _ = self._render_linear(rays, self.trajectory.pose(t_row), t_row, r0, r1)
                    acc[r0:r1] += lin
            else:
                lin, vd, depth, ids = self._render_linear(rays, self.trajectory.pose(t_sub), t_sub)
                acc += lin
                if off == 0.0:
                    mid_lin, mid_vd, mid_depth, mid_ids = lin, vd, depth, ids
        lin = acc / len(offsets)
        if self.optical_blur > 0.05:
            lin = cv2.GaussianBlur(lin, (0, 0), self.optical_blur, borderType=cv2.BORDER_REFLECT)
        if mid_lin is None:
            mid_lin, mid_vd, mid_depth, mid_ids = self._render_linear(rays, T_mid, stamp)

        gain = self._exposure_at(stamp)
        vig = self._vignette()
        rng = np.random.default_rng([self.seed, 0xF4A3, int(i)])
        x = lin * (gain * vig)[..., None]
        noise = rng.standard_normal(x.shape, dtype=np.float32)
        x = x + noise * (self.shot_noise * np.sqrt(np.maximum(x, 0)) + self.read_noise)
        image = self._encode(x)
        # pixels whose (noise-free) value would change by more than 1.5/255 without view-dependent light
        scale = (gain * vig)[..., None]
        vd = mid_vd * scale
        spec_mask = np.zeros(mid_ids.shape, bool)
        cand = np.max(vd, axis=-1) > 1e-5
        if cand.any():
            base = mid_lin[cand] * scale[cand]
            change = self._encode_float(base) - self._encode_float(base - vd[cand])
            spec_mask[cand] = np.max(np.abs(change), axis=-1) > 1.5 / 255
        special_ids = [k + _N_ROOM_FACES for k, p in enumerate(self.prims)
                       if self.materials[p.material].kind in (KIND_MIRROR, KIND_GLASS)]
        if special_ids:
            spec_mask |= np.isin(mid_ids, special_ids)
        out = {'image': image, 'depth': mid_depth.astype(np.float32), 'pose': T_mid, 'stamp': stamp,
               'specular_mask': spec_mask}
        if not cfg.static:
            out['dynamic_mask'] = np.isin(mid_ids, [k + _N_ROOM_FACES for k in self.dynamic_ids])
        return out

    def _vignette(self) -> np.ndarray:
        if not hasattr(self, '_vig_cache'):
            K = self.K
            x = (np.arange(self.width) - K[0, 2]) / (self.width / 2)
            y = (np.arange(self.height) - K[1, 2]) / (self.width / 2)
            r2 = x[None, :] ** 2 + y[:, None] ** 2
            r2max = ((self.width / 2) ** 2 + (self.height / 2) ** 2) / (self.width / 2) ** 2
            self._vig_cache = (1.0 - self.vignetting * r2 / r2max).astype(np.float32)
        return self._vig_cache

    def _encode_float(self, x: np.ndarray) -> np.ndarray:
        return np.power(np.clip(x, 0.0, 1.0), 1.0 / self.config.gamma)

    def _encode(self, x: np.ndarray) -> np.ndarray:
        """Linear intensity -> 8-bit gamma-encoded (through a 16-bit look-up table)."""
        if not hasattr(self, '_gamma_lut'):
            levels = np.arange(65536, dtype=np.float64) / 65535.0
            self._gamma_lut = np.round(np.power(levels, 1.0 / self.config.gamma) * 255.0).astype(np.uint8)
        idx = (np.clip(x, 0.0, 1.0) * np.float32(65535.0) + np.float32(0.5)).astype(np.uint16)
        return self._gamma_lut[idx]

    def describe(self) -> dict:
        """JSON-friendly description of the scene (stored in the sequence meta)."""
        counts: Dict[str, int] = {}
        for p in self.prims:
            counts[p.label] = counts.get(p.label, 0) + 1
        tr = self.trajectory
        return {
            'generator': 'dpv_sensor.data.synthetic', 'seed': self.seed,
            'room_size_m': [float(v) for v in self.room], 'objects': counts,
            'num_lights': len(self.lights),
            'materials': [m.pattern if m.kind == KIND_DIFFUSE else m.name for m in self.materials],
            'fov_deg': float(math.degrees(2 * math.atan(self.width / 2 / self.K[0, 0]))),
            'speed_range_mps': [float(v) for v in tr.speed_range], 'loop_length_m': tr.loop_length,
            'exposure_gain': self.exposure_gain, 'read_noise': self.read_noise, 'shot_noise': self.shot_noise,
            'vignetting': self.vignetting, 'optical_blur_px': self.optical_blur,
            'exposure_time_s': self.exposure_time if self.config.motion_blur else 0.0,
            'readout_time_s': self.readout_time if self.config.rolling_shutter else 0.0,
            'depth_convention': 'z-depth of the pose at the middle of the exposure, metres',
            'world_frame': 'z up, room spans [0, size]',
            'config': dataclasses.asdict(self.config),
        }

    def distance_to_surfaces(self, points: np.ndarray, time: float = 0.0) -> np.ndarray:
        """Euclidean distance from world points (M, 3) to the nearest surface (walls, floor, ceiling,
        furniture at rest; moving objects count with their whole range of motion)."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        d = np.min(np.concatenate([pts, self.room - pts], axis=1), axis=1)
        for p in self.prims:
            d = np.minimum(d, p.sdf(pts))
        return d


# ==================================================================================================
# public API
# ==================================================================================================

def render_sequence(seed: int, num_frames: int, width: int = 320, height: int = 240,
                    config: Optional[SceneConfig] = None, lazy: bool = False, progress: bool = False,
                    cache_frames: int = 64, **options) -> Sequence:
    """Render ``num_frames`` frames (30 Hz by default) of the room of ``seed`` as an in-memory
    :class:`~dpv_sensor.data.sequence.Sequence` with images, exact z-depth, poses, K, stamps, the scene
    description in ``seq.meta`` and per-frame extras ``specular_mask`` (and ``dynamic_mask`` when
    ``static=False``).

    ``options`` are :class:`SceneConfig` fields (e.g. ``motion_blur=True``, ``fov_deg=(60, 60)``).
    With ``lazy=True`` frames are rendered when first asked for (the last ``cache_frames`` are kept), so
    sampling a few windows of a long sequence costs only those frames. Rendering is deterministic per
    (seed, options, size): frame i is identical whichever frames are rendered before it. ``progress`` shows
    a tqdm bar while rendering eagerly. The :class:`SyntheticScene` is attached as ``seq.scene``.
    """
    scene = SyntheticScene(seed, width, height, config=config, **options)
    n = int(num_frames)
    poses = np.stack([scene.pose(i) for i in range(n)]) if n else np.zeros((0, 4, 4))
    stamps = np.array([scene.stamp(i) for i in range(n)], np.float64)
    meta = scene.describe()
    meta['num_frames'] = n
    if not lazy:
        frames = []
        iterator = range(n)
        if progress:
            from tqdm import tqdm
            iterator = tqdm(iterator, desc=f'rendering seed {seed}', unit='frame')
        for i in iterator:
            frames.append(scene.render_frame(i))
        extras = {'specular_mask': [f['specular_mask'] for f in frames]}
        if not scene.config.static:
            extras['dynamic_mask'] = [f['dynamic_mask'] for f in frames]
        seq = Sequence.from_arrays([f['image'] for f in frames], [f['depth'] for f in frames], poses,
                                   scene.K, stamps, meta=meta, extras=extras, name=f'synthetic_seed{seed}')
        seq.scene = scene
        return seq

    frame = functools.lru_cache(maxsize=max(1, int(cache_frames)))(scene.render_frame)

    extras = {'specular_mask': lambda i: frame(i)['specular_mask'].copy()}
    if not scene.config.static:
        extras['dynamic_mask'] = lambda i: frame(i)['dynamic_mask'].copy()
    seq = Sequence._from_loaders(K=scene.K, size=(scene.width, scene.height), poses=poses, stamps=stamps,
                                 load_image=lambda i: frame(i)['image'].copy(),
                                 load_depth=lambda i: frame(i)['depth'].copy(), meta=meta, extras=extras,
                                 name=f'synthetic_seed{seed}')
    seq.scene = scene
    return seq


def _parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    if text.lower() in ('true', 'false'):
        return text.lower() == 'true'
    if ',' in text:
        return tuple(_parse_value(t) for t in text.split(','))
    return text


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog='python -m dpv_sensor.data.synthetic',
        description='Render a procedural indoor sequence (exact depth and poses) into a sequence folder.')
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--frames', type=int, default=60)
    parser.add_argument('--width', type=int, default=320)
    parser.add_argument('--height', type=int, default=240)
    parser.add_argument('--out', required=True, help='output sequence folder')
    parser.add_argument('--lossless', action='store_true', help='PNG images instead of JPEG q95')
    parser.add_argument('--motion-blur', action='store_true')
    parser.add_argument('--rolling-shutter', action='store_true')
    parser.add_argument('--dynamic', action='store_true', help='add moving balls (static=False)')
    parser.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                        help='any SceneConfig field, e.g. --set fov_deg=60,60 --set num_lights=2,2')
    args = parser.parse_args(argv)
    options = {}
    for item in args.set:
        try:
            k, v = split_assignment(item)
        except ValueError as exc:
            parser.error(f'--set: {exc}')
        options[k] = _parse_value(v)
    if args.motion_blur:
        options['motion_blur'] = True
    if args.rolling_shutter:
        options['rolling_shutter'] = True
    if args.dynamic:
        options['static'] = False
    seq = render_sequence(args.seed, args.frames, args.width, args.height, lazy=True, **options)
    write_sequence(args.out, seq, lossless=args.lossless, progress=True)
    print(f'wrote {len(seq)} frames ({args.width}x{args.height}) of seed {args.seed} to {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
