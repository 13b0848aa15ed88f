"""Appearance styles of the synthetic world: the same scene under different looks.

A style is a seeded distribution over :class:`~bev_mapper_core.synth.render.Look`: light and time
of day (sun elevation and azimuth, ambient and diffuse light, sky colours, clouds), the ground
palette (asphalt, markings, sidewalks, grass) and its texture, worn paint, wet roads, the colours
of buildings, cars and people (moved at render time, the objects stay as built), lit windows,
and the camera (exposure gain, white balance, saturation, sensor noise, blur, vignetting, haze).

Styles change appearance only: a style's draws come from their own random stream
(:data:`STYLE_STREAM`; ``classic`` keeps the renderer's original look stream 9), never from the
streams that build the world, its objects and the trajectory, and labels, depth, BEV ground truth
and visibility do not depend on the look. The same seed under two styles is the same drive with
different RGB images.

The styles, what each changes, and the held-out one: :data:`STYLES` (``name: summary``), also
tabled in the README. ``classic`` is ``Look.random``, the look before styles existed (drawn from
its original stream, so its RGB images are bit-identical to earlier drives).

``mixed`` (the default of :class:`~bev_mapper_core.synth.config.SynthConfig`) picks one of
:data:`TRAINING_STYLES` per drive from the seed (stream :data:`PICK_STREAM`), never the held-out
one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .raster import NUM_MATS, Mat
from .render import Look

#: ``SynthConfig.style`` that picks one of :data:`TRAINING_STYLES` per drive (per seed)
MIXED = "mixed"
#: the style kept out of ``mixed`` (and so out of training data) to test generalisation
HELD_OUT_STYLE = "dusk"
#: random streams ``[seed, stream]``: the style's own draws, and ``mixed``'s pick
STYLE_STREAM, PICK_STREAM = 21, 20
#: the renderer's original look stream (``classic``)
CLASSIC_STREAM = 9


@dataclass(frozen=True)
class Style:
    """A named appearance style: ``draw(rng, noise_scale)`` draws one :class:`Look`, ``rng``
    being ``default_rng([seed, stream])``.
    """

    name: str
    summary: str
    draw: Callable[[np.random.Generator, float], Look]
    stream: int = STYLE_STREAM

    def look(self, seed: int, noise_scale: float = 1.0) -> Look:
        """The look of this style for a drive of ``seed`` (noise sigma scaled by ``noise_scale``)."""
        return self.draw(np.random.default_rng([int(seed), self.stream]), noise_scale)


def _sun(rng: np.random.Generator, elev_deg: tuple[float, float]) -> np.ndarray:
    """Unit vector towards a sun at a random elevation in ``elev_deg`` and any azimuth."""
    elev, az = np.radians(rng.uniform(*elev_deg)), rng.uniform(-np.pi, np.pi)
    return np.array([np.cos(elev) * np.cos(az), np.cos(elev) * np.sin(az), np.sin(elev)])


def _rgb(rng: np.random.Generator, base, lo: float, hi: float) -> np.ndarray:
    """``base`` (RGB) scaled per channel by factors in ``[lo, hi]``, clipped to 0..255."""
    return np.clip(np.asarray(base, np.float64) * rng.uniform(lo, hi, 3), 0.0, 255.0)


def _grey(rng: np.random.Generator, lo: float, hi: float, cast=(1.0, 1.0, 1.0)) -> np.ndarray:
    """A grey level in ``[lo, hi]`` times the colour cast ``cast``."""
    return np.clip(rng.uniform(lo, hi) * np.asarray(cast), 0.0, 255.0)


def _ground(grass, dirt, concrete, asphalt, curb, white, yellow) -> np.ndarray:
    """Ground palette ``(NUM_MATS, 3)`` float32 from one RGB per material."""
    g = np.zeros((NUM_MATS, 3))
    for mat, col in ((Mat.GRASS, grass), (Mat.DIRT, dirt), (Mat.CONCRETE, concrete),
                     (Mat.ASPHALT, asphalt), (Mat.CURB, curb), (Mat.WHITE, white),
                     (Mat.YELLOW, yellow)):
        g[mat] = col
    return g.astype(np.float32)


def _day(rng: np.random.Generator, noise_scale: float, **over) -> Look:
    """A daylight look with ``over`` replacing any of its fields (``over["noise"]`` is scaled
    by ``noise_scale`` like the base's).
    """
    base = dict(
        ground=_ground(_rgb(rng, (70, 105, 45), 0.8, 1.15), _rgb(rng, (120, 100, 75), 0.85, 1.1),
                       _grey(rng, 145, 190), _grey(rng, 65, 100), _grey(rng, 165, 205),
                       _grey(rng, 215, 240), _rgb(rng, (225, 185, 45), 0.92, 1.05)),
        horizon=_rgb(rng, (205, 215, 228), 0.92, 1.06), zenith=_rgb(rng, (70, 120, 200), 0.88, 1.1),
        sun=_sun(rng, (25.0, 65.0)), ambient=rng.uniform(0.35, 0.5), diffuse=rng.uniform(0.5, 0.7),
        gain=rng.uniform(0.9, 1.08), noise=rng.uniform(1.5, 4.0) * noise_scale,
        fog=rng.uniform(300.0, 700.0), window=_rgb(rng, (45, 60, 80), 0.85, 1.25),
        clouds=rng.uniform(0.1, 0.6), texture=rng.uniform(0.85, 1.15),
        vignette=rng.uniform(0.1, 0.25), blur=rng.uniform(0.0, 0.4))
    if "noise" in over:
        over["noise"] *= noise_scale
    base.update(over)
    return Look(**base)


def _palette(rng: np.random.Generator, colours, lo: float, hi: float) -> np.ndarray:
    """``(K, 3)`` palette: each of ``colours`` jittered per channel by ``[lo, hi]``."""
    return np.stack([_rgb(rng, c, lo, hi) for c in colours])


def _noon(rng, ns) -> Look:
    return _day(rng, ns, sun=_sun(rng, (60.0, 80.0)), ambient=rng.uniform(0.3, 0.4),
                diffuse=rng.uniform(0.6, 0.75), zenith=_rgb(rng, (55, 110, 215), 0.9, 1.08),
                horizon=_rgb(rng, (195, 212, 235), 0.95, 1.04), clouds=rng.uniform(0.0, 0.3),
                gain=rng.uniform(0.9, 1.02), noise=rng.uniform(1.0, 2.5),
                fog=rng.uniform(500.0, 900.0), saturation=rng.uniform(1.0, 1.1))


def _overcast(rng, ns) -> Look:
    return _day(rng, ns, ambient=rng.uniform(0.6, 0.72), diffuse=rng.uniform(0.08, 0.18),
                zenith=_grey(rng, 150, 180, (1.0, 1.02, 1.06)),
                horizon=_grey(rng, 185, 210, (1.0, 1.0, 1.03)), clouds=rng.uniform(0.75, 1.0),
                cloud_color=rng.uniform(190.0, 215.0), fog=rng.uniform(200.0, 400.0),
                paint_saturation=rng.uniform(0.8, 0.95), saturation=rng.uniform(0.8, 0.9),
                tint=np.array([0.97, 1.0, 1.04]), noise=rng.uniform(2.0, 4.0))


def _dusk(rng, ns) -> Look:
    return _day(rng, ns, sun=_sun(rng, (2.0, 9.0)), ambient=rng.uniform(0.25, 0.35),
                diffuse=rng.uniform(0.55, 0.75), horizon=_rgb(rng, (235, 150, 95), 0.9, 1.06),
                zenith=_rgb(rng, (55, 65, 120), 0.85, 1.1), clouds=rng.uniform(0.2, 0.6),
                cloud_color=_rgb(rng, (240, 170, 140), 0.9, 1.05),
                tint=np.array([1.12, 0.97, 0.82]) * rng.uniform(0.97, 1.03, 3),
                gain=rng.uniform(1.1, 1.3), noise=rng.uniform(3.0, 5.5),
                lit_windows=rng.uniform(0.1, 0.3), lamp=_rgb(rng, (255, 200, 120), 0.9, 1.0),
                fog=rng.uniform(250.0, 500.0), blur=rng.uniform(0.2, 0.5),
                vignette=rng.uniform(0.2, 0.35))


def _night(rng, ns) -> Look:
    return _day(rng, ns, sun=_sun(rng, (20.0, 60.0)), ambient=rng.uniform(0.12, 0.18),
                diffuse=rng.uniform(0.04, 0.1), horizon=_rgb(rng, (40, 38, 45), 0.85, 1.2),
                zenith=_rgb(rng, (8, 10, 22), 0.8, 1.2), clouds=rng.uniform(0.1, 0.7),
                cloud_color=rng.uniform(30.0, 50.0), gain=rng.uniform(1.5, 2.2),
                noise=rng.uniform(6.0, 11.0), fog=rng.uniform(150.0, 350.0),
                window=_rgb(rng, (15, 18, 25), 0.8, 1.2), lit_windows=rng.uniform(0.25, 0.55),
                lamp=_rgb(rng, (255, 205, 130), 0.85, 1.0),
                tint=np.array([1.12, 0.98, 0.75]) * rng.uniform(0.97, 1.03, 3),
                saturation=rng.uniform(0.6, 0.8), vignette=rng.uniform(0.3, 0.45),
                blur=rng.uniform(0.3, 0.7))


def _rain(rng, ns) -> Look:
    return _day(rng, ns, ground=_ground(
                    _rgb(rng, (55, 85, 40), 0.85, 1.1), _rgb(rng, (90, 75, 58), 0.85, 1.1),
                    _grey(rng, 110, 150), _grey(rng, 40, 65), _grey(rng, 130, 165),
                    _grey(rng, 190, 220), _rgb(rng, (205, 170, 45), 0.9, 1.05)),
                ambient=rng.uniform(0.5, 0.62), diffuse=rng.uniform(0.05, 0.15),
                horizon=_grey(rng, 150, 180, (1.0, 1.01, 1.04)),
                zenith=_grey(rng, 110, 140, (1.0, 1.02, 1.06)), clouds=rng.uniform(0.85, 1.0),
                cloud_color=rng.uniform(140.0, 170.0), fog=rng.uniform(70.0, 160.0),
                wet=rng.uniform(0.5, 0.9), texture=rng.uniform(0.5, 0.8),
                paint_saturation=rng.uniform(0.7, 0.85), saturation=rng.uniform(0.7, 0.85),
                blur=rng.uniform(0.6, 1.2), noise=rng.uniform(2.5, 5.0),
                gain=rng.uniform(0.95, 1.1), tint=np.array([0.96, 1.0, 1.05]))


def _fog(rng, ns) -> Look:
    return _day(rng, ns, ambient=rng.uniform(0.55, 0.7), diffuse=rng.uniform(0.05, 0.2),
                horizon=_grey(rng, 195, 220, (1.0, 1.01, 1.02)), zenith=_grey(rng, 180, 205),
                clouds=1.0, cloud_color=rng.uniform(205.0, 225.0), fog=rng.uniform(22.0, 55.0),
                saturation=rng.uniform(0.7, 0.85), texture=rng.uniform(0.7, 0.9),
                blur=rng.uniform(0.4, 0.9), noise=rng.uniform(2.0, 4.0), wet=rng.uniform(0.0, 0.25))


_PASTELS = ((225, 205, 185), (200, 215, 220), (230, 220, 190), (210, 200, 210), (195, 205, 180))
_STRONG = ((200, 60, 50), (50, 90, 190), (230, 180, 40), (60, 150, 90), (220, 120, 40),
           (150, 70, 160), (40, 160, 170))


def _faded(rng, ns) -> Look:
    return _day(rng, ns, ground=_ground(
                    _rgb(rng, (125, 120, 70), 0.85, 1.1), _rgb(rng, (150, 130, 100), 0.9, 1.08),
                    _grey(rng, 170, 210), _grey(rng, 110, 150, (1.0, 0.99, 0.96)),
                    _grey(rng, 175, 205), _grey(rng, 185, 210), _rgb(rng, (205, 180, 95), 0.92, 1.05)),
                wear=rng.uniform(0.45, 0.85), texture=rng.uniform(1.2, 1.5),
                facade=_palette(rng, _PASTELS, 0.9, 1.05), facade_mix=rng.uniform(0.5, 0.8),
                paint_saturation=rng.uniform(0.45, 0.7), paint_gain=np.array([1.08, 1.06, 1.02]),
                saturation=rng.uniform(0.7, 0.85), sun=_sun(rng, (35.0, 70.0)), horizon=_rgb(rng, (215, 215, 210), 0.95, 1.04),
                zenith=_rgb(rng, (140, 165, 195), 0.92, 1.06), gain=rng.uniform(1.0, 1.12),
                fog=rng.uniform(200.0, 450.0))


def _vivid(rng, ns) -> Look:
    return _day(rng, ns, ground=_ground(
                    _rgb(rng, (45, 140, 35), 0.85, 1.15), _rgb(rng, (140, 95, 55), 0.9, 1.1),
                    _grey(rng, 165, 200), _grey(rng, 45, 70), _grey(rng, 185, 215),
                    _grey(rng, 235, 250), _rgb(rng, (245, 190, 20), 0.95, 1.03)),
                facade=_palette(rng, _STRONG, 0.85, 1.1), facade_mix=rng.uniform(0.6, 0.9),
                paint_saturation=rng.uniform(1.4, 1.8), saturation=rng.uniform(1.25, 1.5),
                zenith=_rgb(rng, (35, 95, 220), 0.9, 1.08), horizon=_rgb(rng, (180, 205, 240), 0.95, 1.04),
                sun=_sun(rng, (35.0, 65.0)), ambient=rng.uniform(0.35, 0.45),
                diffuse=rng.uniform(0.6, 0.75), noise=rng.uniform(1.0, 2.5),
                fog=rng.uniform(600.0, 1000.0), gain=rng.uniform(1.0, 1.1))


_STYLES = (
    Style("classic", "the look before styles existed (Look.random): random palette and sun, "
          "30 % overcast", Look.random, CLASSIC_STREAM),
    Style("noon", "high sun, deep blue sky, few clouds, strong contrast, low noise", _noon),
    Style("overcast", "grey sky and clouds, flat diffuse light, slightly cool, less saturated",
          _overcast),
    Style("dusk", "low sun, orange horizon and clouds, warm tint, dim ground, some lit windows, "
          "more gain and noise", _dusk),
    Style("night", "dark sky, weak light, high gain and noise, sodium tint, many lit windows, "
          "grainy and soft", _night),
    Style("rain", "wet dark asphalt mirroring the sky (puddles), grey sky, haze at 70-160 m, "
          "blur, muted colours", _rain),
    Style("fog", "dense fog (20-55 m), pale grey sky, low contrast and saturation, soft blur",
          _fog),
    Style("faded", "worn lane paint, pale bleached asphalt, dry grass, pastel facades, "
          "washed-out paint", _faded),
    Style("vivid", "saturated grass, facades, cars and people; dark asphalt, bright paint, "
          "deep sky", _vivid),
)
#: every named style
STYLES: dict[str, Style] = {st.name: st for st in _STYLES}
#: the styles ``mixed`` picks from: all but :data:`HELD_OUT_STYLE`
TRAINING_STYLES: tuple[str, ...] = tuple(n for n in STYLES if n != HELD_OUT_STYLE)
#: valid values of ``SynthConfig.style`` / ``bev-bag synth --style``
STYLE_CHOICES: tuple[str, ...] = (MIXED, *STYLES)


def check_style(name) -> str:
    """``name`` if it is a valid style (or ``mixed``); raises ConfigError listing the choices."""
    if not isinstance(name, str) or name not in STYLE_CHOICES:
        raise ConfigError(f"unknown style {name!r}; choices: {', '.join(STYLE_CHOICES)} "
                          f"({HELD_OUT_STYLE} is held out of {MIXED})")
    return name


def resolve_style(name: str, seed: int) -> str:
    """The style a drive of ``seed`` uses: ``name`` itself, or for ``mixed`` one of
    :data:`TRAINING_STYLES` drawn from ``[seed, PICK_STREAM]``.
    """
    if check_style(name) != MIXED:
        return name
    pick = np.random.default_rng([int(seed), PICK_STREAM]).integers(len(TRAINING_STYLES))
    return TRAINING_STYLES[int(pick)]


def style_look(name: str, seed: int, noise_scale: float = 1.0) -> Look:
    """The :class:`Look` of style ``name`` (``mixed`` resolved first) for a drive of ``seed``;
    ``noise_scale`` scales the sensor noise (``SynthConfig.image_noise``).

    Same ``(name, seed, noise_scale)`` -> the same look; the draws come from the style's own
    stream ``[seed, STYLE_STREAM]`` (``classic``: ``[seed, 9]``).
    """
    return STYLES[resolve_style(name, seed)].look(seed, noise_scale)


def style_help() -> str:
    """What ``--style`` does, naming ``mixed``'s choices and the held-out style (help texts)."""
    return (f"appearance style of the RGB images (labels and ground truth do not change); "
            f"{MIXED} picks one of {', '.join(TRAINING_STYLES)} per seed; {HELD_OUT_STYLE} is "
            f"held out of {MIXED}, for testing generalisation")
